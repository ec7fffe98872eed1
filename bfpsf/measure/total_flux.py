"""Total flux: the light beyond the PSF's support, measured from the stars of the images.

P0 is normalised inside its support (``bfpsf psf --size``, 25 pixels): a star's flux fitted
with it is the flux inside that square, and the wings beyond it are lost (0.1 % for a Moffat
of beta 3.5 and FWHM 3.45 px, 1.5 % for a Kolmogorov atmosphere with an optical PSF, 5.5 %
for one with struts and defocus). Those wings are also what biases a sky estimated from the
pixels between the stars: summed over a field of bright stars they make a glow that no mask
removes (8 e- per pixel for 60 Kolmogorov stars of peaks 3-120 ke- on 300^2 pixels).

`WingModel` is a profile W(r) per unit fitted flux beyond the support: free at six nodes
from the support's edge to six half-widths, and carried on beyond at a power law the images
choose. It is fitted jointly with every image's sky (`fit_sky_and_wings`): the stars' glow,
of known places and fluxes, is told from a plane. Its integral beyond the support is
``flux_correction - 1``, the total flux over the fitted flux, which the PSF product keeps and
photometry applies, so that ``flux_fit`` is the star's total flux. `wing_image` is the glow
of a set of stars, which the sky estimate subtracts (`bfpsf.measure.sky.estimate_sky`), so
the sky is what is left beyond the stars' total-flux model. Sky and wings are measured in
turn (`bfpsf.workflow.psf_from_images`): the bright stars set the wings, the wings the sky.

A single power law, the model before the nodes, missed a profile with a steep ring and a
shallow aureole by 2 % of the flux (a new user's Kolmogorov x OpticalPSF stars, too faint at
a 25-pixel support and too bright at 41), with a stated error 5-70 times too small.
"""

import functools

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import nnls
from scipy.spatial import cKDTree

from ..errors import BFPSFInputError
from ..model.wings import (BASE_POWER, GLOW, WING_NODES, WingModel, node_basis,
                           node_radii, wing_image)
from .sky import SPLINE, SkyModel, source_mask

__all__ = ["fit_sky_and_wings", "wing_gradient"]

#: Powers tried for the light beyond the last node (W ~ r^-p there), chosen by chi-square.
TAIL_POWERS = tuple(np.arange(2.5, 8.01, 0.5))

#: Free parameters of each family of profiles, for Akaike's criterion (chi-square + 2 k):
#: the free nodes and the tail's power; a power law's amplitude and power.
PARAMETERS = {"nodes": WING_NODES + 1, "power law": 2}

#: The light beyond this many support half-widths is extrapolated at the tail's power, not
#: measured: half of it is in the error.
TAIL_REACH = 2 * GLOW


@functools.lru_cache(maxsize=16)
def _node_integrals(half_size, oversampling=2):
    """Each node basis function summed over the pixels beyond P0's support, within the last
    node, averaged over P0's sub-pixel phases.

    P0 holds a square of nodes (from -(h + 1/2) to h + 1/2 with an even oversampling), and
    each sublattice of nodes (a star's phase) is normalised to unit flux: a star centred on a
    pixel has 2h + 1 pixels inside, one half-way between pixels 2h + 2 (oversampling 2).
    The light beyond is what P0 does not hold, phase by phase: taking the (2h + 1)^2 square
    for every phase counted the half-pixel ring P0 holds twice (0.08 % of the flux, -0.9
    mmag, for a Kolmogorov x optical PSF; 0.01 % for a Moffat of beta 3.5)."""
    outer = node_radii(half_size)[-1]
    reach = int(np.ceil(outer)) + 1
    # P0's nodes, as `bfpsf.model.psf_fit.fit_psf` lays them out, and each sublattice's
    # offset from the pixel grid
    over = int(oversampling)
    n_nodes = (2 * half_size + 1) * over + (1 - over % 2)
    edge = (n_nodes - 1) / (2 * over) + 1e-9
    phases = [((b - (n_nodes - 1) / 2) / over) % 1.0 for b in range(over)]
    rows, columns = np.mgrid[-reach:reach + 1, -reach:reach + 1].astype(float)
    total = np.zeros(WING_NODES)
    for phase_x in phases:
        for phase_y in phases:
            x, y = columns + phase_x, rows + phase_y
            r = np.hypot(x, y)
            outside = ((np.abs(x) > edge) | (np.abs(y) > edge)) & (r <= outer)
            total += node_basis(r[outside], half_size).sum(axis=1)
    return total / len(phases) ** 2


def _tail(half_size, power, start=1.0):
    """The light beyond ``start`` times the last node's radius R, per unit of the last node's
    coefficient, for W = R^-3 (r / R)^-p beyond R."""
    outer = node_radii(half_size)[-1]
    return 2.0 * np.pi * outer ** (2.0 - BASE_POWER) * start ** (2.0 - power) / (power - 2.0)


def _templates(x, y, flux, rows, columns, half_size):
    """Every node's glow template at the given pixels (sum over stars of F_i times the node's
    basis at r_i; the last node's carried on beyond it over the whole image, at each power of
    `TAIL_POWERS`), and the pixels inside any star's support. Glow left out of the templates
    goes into the sky and steepens the tail (r^-3 wings on a 150-pixel image: 5 % of the
    light beyond the support missed when the glow stopped at 90 pixels; 7 % when the
    faintest of six stars had no tail).

    Returns (templates [pixel, node], tails [pixel, power], inside [pixel])."""
    outer = node_radii(half_size)[-1]
    inside = np.zeros(rows.size, dtype=bool)
    templates = np.zeros((rows.size, WING_NODES))
    # the tails laid out power by power (contiguous rows for the in-place products below)
    tails = np.zeros((len(TAIL_POWERS), rows.size))
    good = np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & (flux > 0)
    if rows.size == 0 or not good.any():
        return templates, tails.T, inside
    tree = cKDTree(np.column_stack([columns, rows]))
    step = TAIL_POWERS[1] - TAIL_POWERS[0]
    term, squared = np.empty(rows.size), np.empty(rows.size)
    for x_0, y_0, value in zip(x[good], y[good], flux[good]):
        near = np.asarray(tree.query_ball_point((x_0, y_0), outer), dtype=int)
        column, row = int(np.rint(x_0)), int(np.rint(y_0))
        within = ((np.abs(columns[near] - column) <= half_size + 1)
                  & (np.abs(rows[near] - row) <= half_size + 1))
        inside[near[within]] = True
        near = near[~within]
        radius = np.hypot(columns[near] - x_0, rows[near] - y_0)
        templates[near] += value * node_basis(radius, half_size).T
        # the tail, over every pixel (no gather): (r / R)^-p for the evenly spaced powers, by
        # products in place (np.hypot and exp take ten times as long); zero within R
        np.subtract(columns, x_0, out=squared)
        np.multiply(squared, squared, out=squared)
        np.subtract(rows, y_0, out=term)
        np.multiply(term, term, out=term)
        squared += term
        squared *= outer ** -2
        squared[squared <= 1.0] = np.inf
        factor = np.power(squared, -step / 2)
        np.power(squared, -TAIL_POWERS[0] / 2, out=term)
        term *= value * outer ** -BASE_POWER
        for tail in tails:
            tail += term
            term *= factor
    return templates, tails.T, inside


def _without_skies(columns, bases, offsets, keep):
    """Each image's sky terms projected out of
    ``columns`` on the kept pixels (image k's pixels are rows ``offsets[k]:offsets[k + 1]``,
    and its terms touch them only): (what is left of every column, and per image the sky
    terms of every column)."""
    left, parts = np.empty_like(columns), []
    for index, basis in enumerate(bases):
        block = slice(offsets[index], offsets[index + 1])
        of_columns = np.linalg.lstsq(basis[keep[block]], columns[block][keep[block]],
                                     rcond=None)[0]
        left[block] = columns[block] - basis @ of_columns
        parts.append(of_columns)
    return left, parts


def fit_sky_and_wings(images_e, stars, *, half_size, degree=1, max_pixels=40_000,
                      clip_nsigma=4.0, oversampling=2):
    """The sky surface of every image and the stars' wings beyond the PSF support, fitted
    jointly: pixel = sky_k(x, y) + sum_i F_i W(r_i), W = c(r) r^-3 (`WingModel`).

    The model is linear in the node coefficients of W and in the sky coefficients of every
    image, solved in one least squares. The stars' glow ties the light far from them (where
    it is degenerate with the sky) to the rings next to them (where it is not): stars at
    different places and of different fluxes tell a sky from a wing. Pixels inside any
    fitted star's support, and the cores of other sources (`bfpsf.measure.sky.source_mask`,
    one radius), are left out; sigma clipping removes what neither model holds.

    Parameters
    ----------
    images_e : sequence of ndarray [y, x]
        Images, e-, sky included (linearised).
    stars : sequence of (x, y, flux) arrays
        Per image, the fitted stars: positions (pixels) and the flux inside the support (e-).
    half_size : int
        Half-width of the PSF support, pixels.
    degree : int or 'spline', optional
        Highest degree of each image's sky surface (default 1, a plane), or 'spline' (every
        image's sky the spline surface, `bfpsf.measure.sky_surface`). Every lower degree
        is fitted too, and the one of least Bayesian information criterion kept (one for all
        the images); the fraction's error then holds half the difference from the highest
        degree's fraction. On small images the tilts of a plane per image trade with the
        glow's run across them: a new user's crowded 128^2 amplifiers (60 Kolmogorov stars
        each, a constant sky) gave a flux correction of 1.080 +- 0.038 against a true 1.008
        with planes, and keep a constant, 1.015 +- 0.032. A sky that is not constant keeps
        its plane; on a constant one a sparse field's wings of Kolmogorov x optics stars
        come out 0.4 % low (1.0246 against 1.0286; with planes 1.0290 +- 0.0051), within
        the error stated (+- 0.0022).
    max_pixels : int, optional
        Pixels per image at most (a regular subsample), default 40000.
    clip_nsigma : float, optional
    oversampling : int, optional
        Of P0 (default 2): its support differs by a half-pixel ring from phase to phase
        (`_node_integrals`).

    Returns
    -------
    skies : list of bfpsf.measure.sky.SkyModel
        ``method`` "fitted with the stars' wings".
    wings : WingModel
        The likeliest profile, with ``fraction`` (flux beyond P0's support over flux inside
        it) and its error averaged over the profiles the images allow (both families, every
        tail power, Akaike weights), the error at least half the range of the likeliest
        family's fractions within chi-square + 4. Where the likeliest profile has a negative
        node, the nodes are fitted again at the chosen sky degree held at >= 0 (the power law
        stands), and the error holds half the change.
    """
    # the kinds of sky tried: every degree up to ``degree``, or the spline alone (where the
    # sky pixels ask for it, `bfpsf.measure.sky.choose_degree`; left to this criterion, a
    # vignetting of r^4 kept degree 2, whose misfit took the flux correction +1.6 sigma)
    kinds = [SPLINE] if degree == SPLINE else list(range(degree, -1, -1))
    bases, values, wings, tails, offsets, shapes = {kind: [] for kind in kinds}, [], [], [], [0], []
    for index, (image, (x, y, flux)) in enumerate(zip(images_e, stars)):
        image = np.asarray(image, dtype=float)
        core = source_mask(image, reach=1.0, grow=1)
        rows, columns = np.nonzero(np.isfinite(image))
        step = max(1, rows.size // max_pixels)
        rows, columns = rows[::step], columns[::step]
        wing, tail, inside = _templates(np.asarray(x, float), np.asarray(y, float),
                                        np.asarray(flux, float), rows, columns, half_size)
        # the fitted stars' supports and every source's core (a star not fitted, e.g. a
        # blend, would otherwise put its light in the sky) are left out
        keep = ~inside & ~core[rows, columns]
        n_terms = len(SkyModel.template(kinds[0], image.shape).coefficients)
        if keep.sum() < 10 * n_terms:  # a field filled with stars: no sky to fit
            msg = (f"image {index + 1}: {int(keep.sum())} pixels lie beyond the stars' supports "
                   f"({2 * int(half_size) + 1} px) and the sources' cores, too few for its sky; "
                   "give the sky (--background) or a smaller --size")
            raise BFPSFInputError(msg, int(keep.sum()))
        wings.append(wing[keep])
        tails.append(tail[keep])
        shapes.append(image.shape)
        # the freest kind's terms; a lower degree's are the first of its polynomial's
        basis = SkyModel.template(kinds[0], image.shape).basis(columns[keep], rows[keep])
        for kind in kinds:
            bases[kind].append(basis if kind == kinds[0] else
                               basis[:, :(kind + 1) * (kind + 2) // 2])
        values.append(image[rows[keep], columns[keep]])
        offsets.append(offsets[-1] + int(keep.sum()))
    values, wings, tails = np.concatenate(values), np.concatenate(wings), np.concatenate(tails)

    columns = np.column_stack([wings, tails, values])

    def project(keep, kind=kinds[0]):
        """The skies of ``kind`` projected out of the node and tail templates and of the
        data (`_without_skies`). Linear, so done once for all the designs below, which are
        combinations of these columns."""
        return _without_skies(columns, bases[kind], offsets, keep)

    def solve(projected, keep, matrix, tail, nonnegative=False):
        """The least squares of [the nodes' templates with the last carried on at TAIL_POWERS
        [tail], times ``matrix`` (nodes = matrix @ parameters), each image's sky terms] on the
        kept pixels, by blocks: the parameters solve the normal equations of what the skies
        leave, each sky is its projection less the parameters' share. The same solution as
        one dense least squares, whose design (nodes + terms x images columns) had taken
        2 GB and 20 times the time on a new user's four amplifiers of eight exposures.
        With ``nonnegative`` the parameters are >= 0 (`scipy.optimize.nnls` on what the
        skies leave). Returns (parameters, sky terms of each image, deviation of every pixel,
        the normal matrix of the parameters beyond the skies: their inverse covariance per
        rms^2)."""
        left, parts = projected

        def design(of):
            return of[..., :WING_NODES] @ matrix + np.multiply.outer(
                of[..., WING_NODES + tail], matrix[-1])

        wing_left, values_left = design(left), left[:, -1]
        normal = wing_left[keep].T @ wing_left[keep]
        # parameters no star reaches (a field of faint stars only) have no column: zero
        reached = np.diag(normal) > 0
        parameters = np.zeros(matrix.shape[1])
        if reached.any() and nonnegative:
            parameters[reached] = nnls(wing_left[keep][:, reached], values_left[keep])[0]
        elif reached.any():
            parameters[reached] = np.linalg.lstsq(
                normal[np.ix_(reached, reached)], wing_left[keep][:, reached].T
                @ values_left[keep], rcond=None)[0]
        sky_terms = [of[:, -1] - design(of) @ parameters for of in parts]
        return parameters, sky_terms, values_left - wing_left @ parameters, normal

    keep = np.ones(values.size, dtype=bool)
    # a noiseless sky beyond the stars (a simulation, a known sky subtracted) has no scatter:
    # the floor keeps the clipping and the chi-square of the powers finite
    floor = 1e-12 * max(1.0, float(np.max(np.abs(values))) if values.size else 1.0)
    for _ in range(10):  # the clipping, with the free nodes and a tail of r^-3.5
        projected = project(keep)
        _, _, deviation, _ = solve(projected, keep, np.eye(WING_NODES), TAIL_POWERS.index(3.5))
        rms = max(1.4826 * float(np.median(np.abs(deviation[keep]))), floor)
        new_keep = np.abs(deviation) <= clip_nsigma * rms
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    else:  # not settled: the projection of the last pixels kept
        projected = project(keep)
    # two families, each at every tail power: the free nodes, and a power law (the nodes on
    # A r^(3 - p), carried on at the same p)
    families = {"nodes": lambda power: np.eye(WING_NODES),
                "power law": lambda power: node_radii(half_size)[:, None] ** (BASE_POWER - power)}

    def fit_families(projected, names=tuple(families), nonnegative=False):
        results = {}
        for name in names:
            fits, models = [], []
            for index, power in enumerate(TAIL_POWERS):
                matrix = families[name](power)
                params, sky_terms, deviation, normal = solve(projected, keep, matrix, index,
                                                             nonnegative=nonnegative)
                covariance = matrix @ (rms**2 * np.linalg.pinv(normal)) @ matrix.T
                fits.append((sky_terms, deviation))
                models.append(_wing_model(matrix @ params, covariance, half_size, power, 0,
                                          oversampling))
            chi2 = np.array([np.sum(deviation[keep] ** 2) for _, deviation in fits]) / rms**2
            results[name] = (chi2, fits, models)
        return results

    # every kind of sky on the same pixels (clipped with the most flexible), the one of
    # least Bayesian information criterion kept (the docstring)
    n_kept = max(int(keep.sum()), 2)
    candidates = {}
    for kind in kinds:
        of_kind = projected if kind == kinds[0] else project(keep, kind)
        results = fit_families(of_kind)
        averaged = _averaged(results)
        information = averaged[0] + sum(basis.shape[1] for basis in bases[kind]) * np.log(
            n_kept)
        candidates[kind] = (information, results, averaged, of_kind)
    highest = candidates[kinds[0]][2]
    kind = min(candidates, key=lambda kind: candidates[kind][0])
    _, results, (_, name, best, fraction, error), of_order = candidates[kind]
    if kind != kinds[0]:
        error = max(error, abs(fraction - highest[3]) / 2)
    if name == "nodes" and min(results[name][2][best].coefficients) < 0:
        # a star's light is never negative. Free, the outer nodes (52-75 px), where the glow
        # of a field's stars is nearly flat over the image, went negative with the sky high in
        # their stead (a new user's Airy x Moffat stars cut at 40 px: -0.093 at 75 px, the sky
        # 5.8 e- high, the flux correction 1.0183 for a true 1.029, photometry +16 mmag).
        # Refitted with the nodes held at >= 0 (after the sky's degree is chosen: held
        # there, the criterion chose a plane over the true constant sky of crowded small
        # amplifiers); half the change is added to the error (a node at its bound). The
        # power law's single amplitude is not held: its fits stand
        free = fraction
        results = {**results, **fit_families(of_order, ("nodes",), nonnegative=True)}
        _, name, best, fraction, held_error = _averaged(results)
        error = max(error, held_error, abs(fraction - free) / 2)
    _, fits, models = results[name]
    sky_terms, deviation = fits[best]
    model = models[best]
    wings = WingModel(model.coefficients, model.tail_power, int(half_size), max(fraction, 0.0),
                      error, int(sum(len(star[0]) for star in stars)))
    skies = []
    for index, (shape, part) in enumerate(zip(shapes, sky_terms)):
        mine = keep[offsets[index]:offsets[index + 1]]
        scatter = deviation[offsets[index]:offsets[index + 1]][mine]
        template = SkyModel.template(kind, shape)
        skies.append(SkyModel(tuple(float(c) for c in part), template.degree, shape,
                              float(1.4826 * np.median(np.abs(scatter))),
                              "fitted with the stars' wings", int(mine.sum()),
                              template.intervals))
    return skies, wings


def _averaged(results):
    """The fraction beyond the support and its error from the fits of both families at every
    tail power: (least Akaike criterion, family and power of the likeliest profile, fraction,
    error).

    The profile kept (its glow subtracted with the sky) is the family and power of least
    Akaike criterion; the fraction and its error are averaged over both families and every
    power, each weighted by exp(-criterion / 2) (Burnham and Anderson's model averaging), on
    a fine grid of powers between those tried: the faint light beyond the last node sets the
    power, and a flat chi-square over it (a two-component profile's, whose best power, 2.5,
    gave 4.3 % against a true 3.1 %) spreads the weight over it. The error is at least half
    the range of the kept family's fractions over the powers within chi-square + 4 of its
    best: the profile is not the truth between its nodes, and a GalSim Kolmogorov star's true
    power, 3.4, stood at chi-square + 4 of the best, 5.0 (the average alone: 3.3 sigma low).
    """
    criteria = {name: chi2 + 2 * PARAMETERS[name] for name, (chi2, _, _) in results.items()}
    lowest = min(criterion.min() for criterion in criteria.values())
    name = min(criteria, key=lambda key: criteria[key].min())
    chi2, _, models = results[name]
    best = int(np.argmin(chi2))
    fine = np.linspace(TAIL_POWERS[0], TAIL_POWERS[-1], 20 * len(TAIL_POWERS))
    weights, fractions, variances = [], [], []
    for key, (_, _, family) in results.items():
        weights.append(np.exp(-(CubicSpline(TAIL_POWERS, criteria[key])(fine) - lowest) / 2))
        fractions.append(CubicSpline(TAIL_POWERS, [m.fraction for m in family])(fine))
        variances.append(CubicSpline(TAIL_POWERS, [m.fraction_err**2 for m in family])(fine))
    weights, fractions = np.concatenate(weights), np.concatenate(fractions)
    variances = np.clip(np.concatenate(variances), 0.0, None)
    weights /= weights.sum()
    fraction = float(weights @ fractions)
    error = float(np.sqrt(weights @ (variances + (fractions - fraction) ** 2)))
    within = CubicSpline(TAIL_POWERS, chi2)(fine) <= chi2[best] + 4.0
    spread = CubicSpline(TAIL_POWERS, [m.fraction for m in models])(fine[within])
    if spread.size:
        error = max(error, float(np.ptp(spread)) / 2)
    return float(lowest), name, best, fraction, error


def _wing_model(coefficients, covariance, half_size, power, n_stars, oversampling=2):
    """The `WingModel` of fitted node coefficients, their covariance and the tail's power:
    the fraction beyond the support (the nodes' integrals and the tail beyond the last node)
    and its error (the covariance, and half the light beyond `TAIL_REACH`, extrapolated)."""
    gradient = (_node_integrals(half_size, oversampling)
                + _tail(half_size, power) * np.eye(WING_NODES)[-1])
    fraction = float(gradient @ coefficients)
    beyond = _tail(half_size, power, TAIL_REACH / GLOW) * max(coefficients[-1], 0.0)
    error = float(np.hypot(np.sqrt(max(gradient @ covariance @ gradient, 0.0)), beyond / 2))
    return WingModel(tuple(float(c) for c in coefficients), float(power), int(half_size),
                     max(fraction, 0.0), error, n_stars)


def wing_gradient(images_e, stars, wings, skies, *, max_pixels=40_000, clip_nsigma=4.0):
    """How the light beyond the support changes across the image, for a PSF that varies over
    the field (a grid of P0s): the wings' amplitude as a plane over the image, fitted with
    every image's sky terms (of ``skies``' degree) on the pixels beyond every star's support
    and the sources' cores, as `fit_sky_and_wings` masks them (subsampled to ``max_pixels``
    after the masking, not before as there), the profile's shape held at ``wings``. A new
    user's field of FWHM 2.7 -> 3.5 px had a true flux correction of 1.0170 -> 1.0207 along
    it, and one correction for the whole grid put +2.3 mmag between its bottom and top stars.

    The plane is of the light beyond the support per unit of each star's fitted flux, so it
    also takes up how the grid's fluxes change across the field: on GalSim Airy x Kolmogorov
    stars of FWHM 2.4 -> 3.6 px (a 3 x 1 grid) it reads +0.0085 +- 0.0007 and +0.0068 +-
    0.0006 across the image where the profile's own change is +0.0058, and leaves their
    photometry flat (-0.38 +- 0.37 and +0.11 +- 0.47 mmag from one third to the other;
    +5.58 and +4.78 without it). Separate planes for the inner and outer halves of the
    profile read the profile's change better (+0.0049 +- 0.0018, +0.0026 +- 0.0016) and the
    photometry worse (+2.2, +3.0 mmag).

    Parameters
    ----------
    images_e : sequence of ndarray [y, x]
        Images, e-, sky included, all of one shape.
    stars : sequence of (x, y, flux) arrays
        Per image, the fitted stars (as `fit_sky_and_wings`).
    wings : WingModel
        The profile (``fraction`` its integral beyond the support at the image's centre).
    skies : sequence of bfpsf.measure.sky.SkyModel
        Their degree is the sky terms' fitted here beside the plane.

    Returns
    -------
    slope, slope_err : (float, float) each
        d(flux_correction)/dx and /dy per pixel about the image's centre, and their errors.
    """
    shape = np.asarray(images_e[0]).shape
    size = np.array(shape[::-1], dtype=float)
    centre = (size - 1.0) / 2.0
    half = int(wings.half_size)
    columns_of, values, offsets, bases = [], [], [0], []
    for image, (x, y, flux), sky in zip(images_e, stars, skies):
        image = np.asarray(image, dtype=float)
        core = source_mask(image, reach=1.0, grow=1)
        inside = np.zeros(shape, dtype=bool)
        x, y, flux = (np.asarray(value, dtype=float) for value in (x, y, flux))
        good = np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & (flux > 0)
        for x_0, y_0 in zip(x[good], y[good]):
            column, row = int(np.rint(x_0)), int(np.rint(y_0))
            inside[max(row - half - 1, 0):row + half + 2,
                   max(column - half - 1, 0):column + half + 2] = True
        rows, columns = np.nonzero(np.isfinite(image) & ~inside & ~core)
        step = max(1, rows.size // max_pixels)
        rows, columns = rows[::step], columns[::step]
        # the glow of the stars weighted by 1 and by their place (0 to 1 across the image)
        u, v = (np.clip((place - middle) / length + 0.5, 1e-6, 1.0)
                for place, middle, length in zip((x, y), centre, size))
        glows = [wing_image(wings, x[good], y[good], (flux * weight)[good], shape)
                 for weight in (np.ones_like(x), u, v)]
        columns_of.append(np.column_stack([glow[rows, columns] for glow in glows]))
        values.append(image[rows, columns])
        bases.append(sky.basis(columns, rows))
        offsets.append(offsets[-1] + rows.size)
    columns = np.column_stack([np.concatenate(columns_of), np.concatenate(values)])
    keep = np.ones(len(columns), dtype=bool)
    for _ in range(5):  # clipped as `fit_sky_and_wings` clips
        left = _without_skies(columns, bases, offsets, keep)[0]
        normal = left[keep, :3].T @ left[keep, :3]
        amplitude = np.linalg.lstsq(normal, left[keep, :3].T @ left[keep, 3], rcond=None)[0]
        deviation = left[:, 3] - left[:, :3] @ amplitude
        rms = 1.4826 * float(np.median(np.abs(deviation[keep])))
        new_keep = np.abs(deviation) <= clip_nsigma * rms
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    covariance = rms**2 * np.linalg.pinv(normal)
    # the amplitude at (u, v) is a + b u + c v: ``fraction`` at the centre (u = v = 1/2)
    scale = wings.fraction / (amplitude[0] + 0.5 * (amplitude[1] + amplitude[2])) / size
    slope = tuple(float(value) for value in amplitude[1:] * scale)
    slope_err = tuple(float(value) for value in np.sqrt(np.diag(covariance)[1:]) * scale)
    return slope, slope_err
