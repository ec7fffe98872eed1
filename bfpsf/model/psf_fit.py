"""Fitting the base PSF P0 from stars of all fluxes at once, on one node or a grid of nodes.

Every star i is modelled as (G15 eq. scrambling_model folded into the PSF)

    d_i = F_i p_i + F_i**2 R[p_i] + noise,       p_i = sum_k w_ik P0_k at the phase of star i,

with w_ik the bilinear weights of the grid nodes k around the star (one node: w = 1; the model
is `~bfpsf.model.gridded.GriddedFluxDependentPSF`), so that, once each star's predicted
brighter-fatter term is removed, the bright stars (which give the signal-to-noise) no longer
bias P0 towards a broader profile. The fit is a fixed-point iteration, as in the ePSF
construction of Anderson & King (2000) and photutils' `~photutils.psf.EPSFBuilder`:

1. start from the stack of d_i / F_i on the oversampled grid (nearest node, inverse-variance
   weights, grid nodes solved jointly, empty nodes filled from their neighbours);
2. one weighted Gauss-Newton step of every star's F_i (and, after ``hold_positions``
   iterations at the positions given, x_i and y_i) on its cutout minus the models of the
   other stars and of the neighbours (``neighbours``: blends and other sources, fitted with P0
   but not used for it), with pixel variances from the model (sky, read noise and the
   neighbours' light included), not from the noisy data;
3. add to each P0_k the least-squares solution, in each oversampled pixel, for the normalised
   residuals (d_i - model_i) / F_i predicted after the star step (a K x K system per pixel
   couples the grid nodes), without its translation, then renormalise every sub-pixel phase
   (`normalise`: a star's flux and the sum of the sublattice of nodes its phase samples are
   degenerate);
4. once P0 has nearly settled, fix the positions (P0's odd part and the positions share a
   weakly constrained direction along which alternating updates creep); stop when the largest
   change of P0 is below ``tolerance`` of its peak; recentre P0 (centroid) and refit the stars.

Binning the residuals rather than the data removes the broadening that nearest-node binning
would otherwise cause: at the fixed point the binned residuals vanish. Every star's model is a
product of small matrices, ``Ly @ P0_i @ Lx.T``, with rows of the cubic interpolating spline
that `FluxDependentPSF` evaluates (so the fit and the model agree to rounding), evaluated for
all stars at once: 3600 stars and a 3 x 3 grid take about a minute on one core
(``benchmarks/bench_psf_fit.py``).
"""

import logging
from dataclasses import dataclass

import numpy as np
from astropy.table import Table
from tqdm import tqdm

from ..errors import BFPSFConvergenceError, BFPSFInputError, BFPSFValueError, integer_at_least
from ..resources import check_psf_fit
from .gridded import GriddedFluxDependentPSF, bilinear_weights
from .psf import FluxDependentPSF
from .psf_fit_empirical import amplitude_step, with_empirical
from .psf_fit_grid import (Grid, Sampling, cardinal_splines, dense_weights_of, grid_nodes,
                           mean_shifts, node_solution, normalise_nodes, project, recentred,
                           shift_sets_of, without_translation)
from .psf_fit_stars import (MOVED, STAR_FLAGS, as_star_list, cut_stars, neighbour_table,
                             star_table, unlike_others)

__all__ = ["PSFFitResult", "fit_psf", "STAR_FLAGS", "DEFAULT_SIZE"]

log = logging.getLogger(__name__)

#: Default side of P0's support and of the star cutouts, pixels (``bfpsf psf --size``).
DEFAULT_SIZE = 25
#: Chi-square, in units of the least one so far, at which the iteration is taken to diverge:
#: it goes on from the least one's iterate with half the step, down to `MIN_DAMPING`, then
#: stops there (a slow drift away from the optimum, 1.3x on a sparse grid, is left to run).
DIVERGED = 10.0
MIN_DAMPING = 1.0 / 8
#: The fit has converged only when the EMPIRICAL term's amplitude changes by less than this
#: too (`bfpsf.model.psf_fit_empirical`), or by less than `AMPLITUDE_ERROR_FRACTION` of its
#: statistical error (a step lost in the noise): P0 settled while the amplitude still crept
#: up by 0.005 an iteration, 10 % short of its end.
AMPLITUDE_TOLERANCE = 1e-3
AMPLITUDE_ERROR_FRACTION = 0.1


@dataclass(frozen=True)
class PSFFitResult:
    """Result of `fit_psf`.

    Attributes
    ----------
    psf : FluxDependentPSF or GriddedFluxDependentPSF
        The model with the fitted P0 (``psf.data``), unit flux; gridded when ``grid`` is
        given.
    stars : astropy.table.Table
        One row per input star: ``image``, ``x_init``, ``y_init``, ``x_fit``, ``y_fit``
        (pixels), ``flux_fit`` (e-), ``weight`` (share of the stack), ``flags`` (`STAR_FLAGS`),
        ``masked`` (pixels of a companion left out,
        `~bfpsf.model.psf_fit_stars.companion_pixels`).
    iterations : int
        Iterations run (those that went back from a diverging step too).
    converged, diverged : bool
        The change fell below ``tolerance``; or the iteration still diverged at its smallest
        step (`MIN_DAMPING`) and stopped at its iterate of least chi-square.
    changes : ndarray
        Largest change of P0, relative to its peak, at each iteration taken.
    neighbours : astropy.table.Table
        One row per neighbour modelled (``neighbours`` of `fit_psf` whose centre is in its
        image): ``image``, ``x_fit``, ``y_fit``, ``flux_fit`` (e-, with P0), ``flags``.
    """

    psf: FluxDependentPSF
    stars: Table
    iterations: int
    converged: bool
    changes: np.ndarray
    neighbours: Table = None
    diverged: bool = False


def _exact_bf_terms(grid, weights, stars):
    """Each star's BF term (e-) from the node models' own evaluation (modes other than
    'table': exact phase, build-up), weighted over the nodes."""
    size = stars.data.shape[1]
    columns = stars.column[:, None] + np.arange(size)
    rows = stars.row[:, None] + np.arange(size)
    terms = np.zeros_like(stars.data)
    for star in range(len(stars.data)):
        y, x = np.meshgrid(rows[star], columns[star], indexing="ij")
        flux, x_0, y_0 = stars.flux[star], stars.x_0[star], stars.y_0[star]
        for node, weight in zip(grid.set_nodes[grid.star_set[star]], weights[star]):
            if weight > 0:
                terms[star] += weight * (node.evaluate(x, y, flux, x_0, y_0)
                                         - flux * node.evaluate_base(x - x_0, y - y_0))
    return terms


def _star_models(grid, weights, stars, free_positions):
    """Model of every star, the Jacobian of (F, x_0, y_0), the samplings and the EMPIRICAL
    term's part of the model per unit of its amplitude (None without one)."""
    size = stars.data.shape[1]
    over = grid.oversampling
    origin = grid.nodes[0].origin
    cardinal = grid.cardinal
    xs = Sampling(stars.column, stars.x_0, size, over, origin[0], cardinal)
    ys = Sampling(stars.row, stars.y_0, size, over, origin[1], cardinal)
    p0 = grid.per_star(grid.data, weights)
    base = project(ys.matrix, p0, xs.matrix)
    flux = stars.flux[:, None, None]
    if grid.table:
        tables = grid.star_tables(weights)
        bf_unit = project(ys.matrix, tables, xs.matrix)
        bf = flux * np.abs(flux) * bf_unit
        d_flux = base + 2 * np.abs(flux) * bf_unit
        charge = flux * p0 + flux * np.abs(flux) * tables
    else:
        tables = None
        bf = _exact_bf_terms(grid, weights, stars)
        d_flux = base + 2 * bf / flux
        charge = flux * p0  # the BF term's own position derivative is neglected here
    model, unit = flux * base + bf, None
    if tables is not None and grid.empirical is not None:
        model, d_flux, unit = with_empirical(grid.empirical, model, d_flux, stars,
                                              grid.amplitude)
    jacobian = [d_flux]
    if free_positions:
        jacobian.append(-project(ys.matrix, charge, xs.derivative))
        jacobian.append(-project(ys.derivative, charge, xs.matrix))
    return model, np.stack(jacobian, axis=1), xs, ys, unit


def _gauss_newton(stars, data, model, jacobian, variance, usable):
    """One weighted Gauss-Newton step of every star's (F[, x_0, y_0]) on its cutout ``data``
    (the neighbours subtracted); returns the residuals predicted after the step and flags
    bit 8 where the step fails."""
    n_stars, n_params = jacobian.shape[:2]
    jac = jacobian.reshape(n_stars, n_params, -1)
    residual = (data - model).reshape(n_stars, -1)
    weighted = jac / variance.reshape(n_stars, 1, -1)
    normal = weighted @ np.swapaxes(jac, 1, 2)
    gradient = np.einsum("ipq,iq->ip", weighted, residual)
    # Solve with unit diagonal (F and positions differ in scale by F).
    scale = np.sqrt(np.clip(np.einsum("ipp->ip", normal), 1e-300, None))
    scaled = normal / (scale[:, :, None] * scale[:, None, :])
    step = np.zeros((n_stars, n_params))
    good = usable & (np.linalg.cond(scaled) < 1e10)
    step[good] = np.linalg.solve(scaled[good], (gradient / scale)[good][..., None])[..., 0]
    step /= scale
    if n_params == 3:
        step[:, 1:] = np.clip(step[:, 1:], -0.5, 0.5)
    flux = stars.flux + step[:, 0]
    failed = usable & ~(good & np.isfinite(flux) & (flux > 0))
    if n_params == 3:
        x_0, y_0 = stars.x_0 + step[:, 1], stars.y_0 + step[:, 2]
        failed |= usable & ((np.abs(x_0 - stars.x_start) > 1) | (np.abs(y_0 - stars.y_start) > 1))
        ok = ~failed & usable
        stars.x_0[ok], stars.y_0[ok] = x_0[ok], y_0[ok]
    ok = ~failed & usable
    stars.flux[ok] = flux[ok]
    step[~ok] = 0.0
    stars.flags[failed] |= MOVED
    return (residual - np.einsum("ip,ipq->iq", step, jac)).reshape(data.shape)


def fit_psf(images_e, positions, shifts, *, oversampling=2, size=DEFAULT_SIZE, read_noise=0.0,
            sky_e=0.0, include_bf=True, grid=None, initial=None, hold_positions=5,
            damping=1.0, max_iterations=40, tolerance=3e-4, strict=False, progress=False,
            neighbours=None, **psf_kwargs):
    """Fit the base PSF P0 of `FluxDependentPSF` from isolated stars of all fluxes, on one
    node or on a grid of nodes over the image (`GriddedFluxDependentPSF`).

    Parameters
    ----------
    images_e : ndarray [y, x] or sequence of them
        Background-subtracted images in electrons (all of one shape when ``grid`` is given:
        the grid covers the image).
    positions : (N, 2) array_like of (x, y), or a sequence of them (one per image)
        Star centres, pixels (held for the first ``hold_positions`` iterations: give
        centroids, e.g. `bfpsf.measure.neighbours.isolated_stars`). Another source within
        ``size`` pixels is to be given in ``neighbours``.
    shifts : BoundaryShifts or Calibration, or a sequence of them (one per image)
        Boundary shifts a^X, 1/e- (G15 eq. def-a). With one per image (e.g. the amplifiers of
        a detector, each an image with its own calibration), each star's BF term uses the
        shifts of its image; the returned model then carries their mean weighted by the
        stars used (evaluate an amplifier with ``psf.with_shifts(its shifts)``).
    oversampling : int, optional
        Oversampling of P0. Default 2: with 144 noisy stars (peaks 3-120 ke-) it recovers
        the P0 size to 0.05 %; use 4 only with several hundred stars per node.
    size : int, optional
        Side of the star cutouts and of the P0 support, pixels (odd). Default 25.
    read_noise : float, optional
        Read noise, e-, for the inverse-variance weights (Poisson noise of the data is
        included). Default 0.
    sky_e : float or sequence of float, optional
        Sky level subtracted from the images (one per image or one for all), e- per pixel:
        its Poisson variance enters the weights. Default 0.
    include_bf : bool, optional
        Subtract each star's BF term F_i**2 R[p_i] (default). False gives the static ePSF of
        the same stars, for comparison.
    empirical : bfpsf.model.empirical.EmpiricalTerm, optional
        The EMPIRICAL term of a refined calibration: each star's model carries it at its
        flux and column (so P0 does not absorb it), and the fitted model applies it
        (``psf.empirical``). Left out with ``include_bf=False``.
    grid : (int, int), optional
        (nx, ny) nodes over the image, from edge to edge
        (`~bfpsf.model.gridded.grid_node_positions`): every node's P0 is fitted jointly from
        all stars, each star weighted by its bilinear weights; returns a
        `GriddedFluxDependentPSF`. Default None: one P0 (the 1 x 1 case), a
        `FluxDependentPSF`.
    initial : ndarray, optional
        Starting P0 (one node, or a cube of ``ny * nx`` nodes) on the oversampled grid (shape
        ``(size * oversampling + 1,)*2`` for even oversampling, ``size * oversampling``
        squared for odd); default the stack of the stars.
    hold_positions : int, optional
        Iterations during which the star positions stay at the positions given (only fluxes
        are refitted). Default 5.
    damping : float, optional
        Fraction of the binned residual added to P0 at each iteration (0 < damping <= 1).
        Default 1; halved, down to `MIN_DAMPING`, where the iteration diverges (it goes
        back to its iterate of least chi-square and fixes the positions there) or its change
        grows three times running with the positions fixed.
    max_iterations : int, optional
        Default 40.
    tolerance : float, optional
        Stop when the largest change of any node's P0 is below ``tolerance`` times its peak.
        Default 3e-4.
    strict : bool, optional
        Raise `~bfpsf.errors.BFPSFConvergenceError` if not converged; otherwise report it in
        ``converged``. Default False.
    progress : bool or None, optional
        Show a tqdm progress bar of the iterations (None: only on a terminal). Default False.
    neighbours : (M, 2) array_like of (x, y), or a sequence of them (one per image), optional
        Other sources of the images (blends, stars too close to another): each is fitted with
        P0 (flux and position) alongside the stars and its model subtracted from every
        cutout it reaches, its light counted in the pixel variances, but it is not used for
        P0. The stars' models are subtracted from each other's cutouts too. Default None.
    **psf_kwargs
        Passed to `FluxDependentPSF`; the images are in e-, so ``flux_unit`` must be
        'electron' (``gain`` is then only recorded). In ``mode='table'`` (default) every
        star's model is a product of small matrices (fast); other modes evaluate each star's
        BF term with the model itself (slow).

    Returns
    -------
    PSFFitResult

    Notes
    -----
    Each iteration is one weighted Gauss-Newton step of every star's flux (and position)
    followed by one update of every node: the average, in each oversampled pixel, of the
    normalised residuals predicted after the star step, each star weighted by its bilinear
    weight of that node times its inverse variance. That average is the gradient step of the
    joint least-squares problem, so its fixed point is the joint fit. The step is not a
    guaranteed descent: a fit that does not converge returns the iterate of least chi-square
    (``converged`` stays False).
    """
    if psf_kwargs.get("flux_unit", "electron") != "electron":
        msg = (f"fit_psf works on images in e-: flux_unit must be 'electron', got "
               f"{psf_kwargs['flux_unit']!r} (convert the fitted model with with_flux_unit)")
        raise BFPSFValueError(msg, psf_kwargs["flux_unit"])
    size = int(size)
    if size < 5 or size % 2 == 0:
        msg = f"size must be an odd number of pixels >= 5, got {size}"
        raise BFPSFValueError(msg, size)
    over = integer_at_least("oversampling", oversampling, 1)
    images, positions = as_star_list(images_e, positions)
    skies = np.broadcast_to(np.asarray(sky_e, dtype=float), (len(images),))
    if np.any(~np.isfinite(skies)) or np.any(skies < 0):
        msg = f"sky_e must be finite and >= 0 e- per pixel, got {sky_e!r}"
        raise BFPSFValueError(msg, sky_e)
    x_nodes, y_nodes = grid_nodes(grid, images)
    n_nodes = x_nodes.size * y_nodes.size
    # refused before anything is allocated when its memory or time is beyond the limits
    check_psf_fit(sum(len(xy) for xy in positions), size, over,
                  None if grid is None else (x_nodes.size, y_nodes.size), max_iterations)
    half = size // 2 + 1  # cutouts one pixel wider than P0: every node gets samples
    if neighbours is not None:
        neighbours = as_star_list(images_e, neighbours)[1]
    flags, image_index, stars = cut_stars(images, positions, half,
                                           read_noise**2 + skies + 1.0, neighbours)
    if stars is None or np.sum(stars.p0) < 3:
        n_usable = 0 if stars is None else int(np.sum(stars.p0))
        msg = f"need at least 3 usable stars to fit a PSF, got {n_usable} of {len(flags)}"
        raise BFPSFInputError(msg, n_usable)
    shift_sets, image_set = shift_sets_of(shifts, len(images))
    if not include_bf:
        shift_sets = [shift_sets[0].scaled(0.0)]
        image_set = np.zeros(len(images), dtype=int)
        psf_kwargs.pop("empirical", None)
    star_set = image_set[stars.image]
    node_indices, node_weights = bilinear_weights(stars.x_0, stars.y_0, x_nodes, y_nodes)
    dense_weights = dense_weights_of(node_indices, node_weights, n_nodes)

    npix = size * over + (1 - over % 2)
    shape = (npix, npix)
    cardinal = cardinal_splines(npix)
    origin = ((npix - 1) / 2.0,) * 2
    shapes = [image.shape for image in images]

    def stack():
        """P0 from the stack of the stars used, at the positions given."""
        xs = Sampling(stars.column, stars.x_0, 2 * half + 1, over, origin[0], cardinal)
        ys = Sampling(stars.row, stars.y_0, 2 * half + 1, over, origin[1], cardinal)
        flux = stars.flux[:, None, None]
        variance = np.clip(stars.data, 0.0, None) + stars.floor[:, None, None]
        return node_solution(stars.data / flux, np.where(stars.used[:, None, None],
                                                          flux**2 / variance, 0.0),
                             dense_weights, xs, ys, npix)

    if initial is None:
        data = stack()
    else:
        data = np.asarray(initial, dtype=float)
        if data.shape[-2:] != shape or data.size != n_nodes * npix * npix:
            msg = (f"initial must have shape {shape} (per node, {n_nodes} nodes) for size "
                   f"{size}, got {data.shape}")
            raise BFPSFValueError(msg, data.shape)
        data = data.reshape((n_nodes,) + shape)
    data = normalise_nodes(data, (over, over), x_nodes, y_nodes, dense_weights)
    fitted = Grid(data, x_nodes, y_nodes, shift_sets, star_set, over, psf_kwargs)
    fitted.cardinal = cardinal
    changes = []
    converged = diverged = False
    positions_settled, free_iterations, settle_factor = False, 0, 5.0
    best = None  # (chi-square, P0, fluxes, x_0, y_0) of the best iterate
    bar = tqdm(total=max_iterations, disable=(False if progress else
                                              None if progress is None else True),
               desc="P0 fit", unit="it", leave=False)
    iteration = start = 0  # a restart without the misfits counts from ``start``
    first_damping = damping
    amplitude_damping, last_step = 1.0, 0.0
    while iteration < start + max_iterations:
        iteration += 1
        bar.update()
        # Hold the positions while P0 is far from converged: free positions would absorb a
        # phase-dependent distortion of the first stack (bright stars at different phases
        # carry different BF), a near-degeneracy the iteration would not leave.
        # Then free them until P0 has nearly settled, and finish with them fixed: P0 and the
        # positions share a weakly constrained direction (the odd part of P0 against each
        # star's centre) along which alternating updates creep; with the positions fixed the
        # remaining problem is linear in P0 and the fluxes and converges in a few steps.
        free_positions = iteration - start > hold_positions and not positions_settled
        model, residual, variance, xs, ys, chi2, unit = _fit_step(
            fitted, dense_weights, stars, free_positions, shapes)
        if best is None or chi2 < best[0]:
            best = (chi2, fitted, stars.flux.copy(), stars.x_0.copy(), stars.y_0.copy())
        amplitude, residual, error = amplitude_step(
            fitted.amplitude, unit, residual, variance, ((stars.flags & MOVED) == 0) & stars.used,
            model, stars.flux, damping * amplitude_damping)
        amplitude_change = amplitude - fitted.amplitude
        settled = abs(amplitude_change) < max(AMPLITUDE_TOLERANCE,
                                              AMPLITUDE_ERROR_FRACTION * error)
        swung_back = amplitude_change * last_step < -0.5 * last_step ** 2
        last_step = amplitude_change
        if swung_back:
            # back by more than half its last step: the amplitude's step overshoots (P0 takes
            # its share of the same residual); undamped, one swung by +-0.1 (its error 0.024)
            # for all 40 iterations of a new user's fit
            amplitude_damping = max(amplitude_damping / 2, MIN_DAMPING)
        # Nodes and samples follow the stars' new positions.
        xs = Sampling(stars.column, stars.x_0, 2 * half + 1, over, origin[0], cardinal)
        ys = Sampling(stars.row, stars.y_0, 2 * half + 1, over, origin[1], cardinal)
        flux = stars.flux[:, None, None]
        # the neighbours are modelled, not used for P0
        weight = np.where(((stars.flags & MOVED) == 0)[:, None, None] & stars.used[:, None, None],
                          flux**2 / variance, 0.0)
        update = node_solution(residual / flux, weight, dense_weights, xs, ys, npix)
        stepped = [node + damping * without_translation(step, node)
                   for node, step in zip(fitted.data, update)]
        diverging = chi2 > DIVERGED * best[0] or not all(node.sum() > 0 for node in stepped)
        if diverging and damping > MIN_DAMPING:
            # diverging (27 spots of one exposure at 3 x 3 phases, chi-square x25 once the
            # positions were free): on from the best iterate, positions fixed, half the step
            log.info("P0 fit diverging at iteration %d (chi-square %.3g, least %.3g): back to "
                     "the iterate of least chi-square, positions fixed, step %.3g",
                     iteration, chi2, best[0], damping / 2)
            _, fitted, stars.flux[:], stars.x_0[:], stars.y_0[:] = best
            positions_settled, damping = True, damping / 2
            continue
        if diverging:
            diverged = True
            # diverging at the smallest step: its best iterate is kept (54 stars: P0's total < 0)
            log.warning("P0 fit diverging at iteration %d (chi-square %.3g, least %.3g): "
                        "keeping the iterate of least chi-square", iteration, chi2, best[0])
            break
        new_data = normalise_nodes(stepped, (over, over), x_nodes, y_nodes, dense_weights)
        change = float(max(np.abs(new - old).max() / np.abs(old).max()
                           for new, old in zip(new_data, fitted.data)))
        changes.append(change)
        if (not free_positions and iteration - start > hold_positions + 3
                and damping > MIN_DAMPING and len(changes) >= 4
                and np.all(np.diff(changes[-4:]) > 0)):
            # grown 3 times running with the positions fixed: the step overshoots (0.0016 -> 0.014)
            damping /= 2
        bar.set_postfix(change=f"{change:.2e}")
        fitted = Grid(new_data, x_nodes, y_nodes, shift_sets, star_set, over, psf_kwargs,
                      amplitude)
        fitted.cardinal = cardinal
        if free_positions:
            free_iterations += 1
            positions_settled = change < settle_factor * tolerance or free_iterations >= 15
            # once P0 and the positions have settled, stars unlike the others leave P0 (and
            # their companions' pixels), and the fit starts again (their shape is in P0)
            rejected = (unlike_others(stars, stars.data - stars.others(model, shapes), model,
                                      variance) if positions_settled
                        else np.zeros(len(model), dtype=bool))
            if rejected.any() and np.sum(stars.used & ~rejected) >= np.sum(stars.p0) / 2:
                log.info("P0 fit: %d stars unlike the others left out; starting again",
                         np.sum(rejected))
                stars.rejected |= rejected
                stars.restart()
                fitted = Grid(normalise_nodes(stack(), (over, over), x_nodes, y_nodes,
                                              dense_weights), x_nodes, y_nodes, shift_sets,
                              star_set, over, psf_kwargs, fitted.amplitude)
                fitted.cardinal = cardinal
                positions_settled, free_iterations, damping = False, 0, first_damping
                best, start = None, iteration
                bar.reset(total=max_iterations)
        elif change < tolerance and settled and iteration - start > hold_positions:
            converged = True
            break
    bar.close()
    if not converged and strict:
        msg = (f"P0 did not converge in {max_iterations} iterations (last change "
               f"{changes[-1]:.3g} of the peak, tolerance {tolerance:.3g})")
        raise BFPSFConvergenceError(msg)
    if not converged:
        # the iterate of least chi-square, not the last: on a grid with few stars per node the
        # iteration can leave the optimum again (a 3 x 3 grid on 200 stars: chi-square
        # 148e3 at iteration 12, 189e3 at 40, node e1 off by up to 0.03)
        _, fitted, stars.flux[:], stars.x_0[:], stars.y_0[:] = best
    fitted = Grid(np.array([recentred(node, over) for node in fitted.data]), x_nodes,
                   y_nodes, shift_sets, star_set, over, psf_kwargs, fitted.amplitude)
    fitted.cardinal = cardinal
    for _ in range(3):  # final positions and fluxes with the final P0
        variance = _fit_step(fitted, dense_weights, stars, True, shapes)[2]
    if len(shift_sets) > 1:  # the model carries the mean of the stars' shifts
        fitted = Grid(fitted.data, x_nodes, y_nodes,
                       [mean_shifts(shift_sets,
                                     star_set[((stars.flags & MOVED) == 0) & stars.used])],
                       np.zeros_like(star_set), over, psf_kwargs, fitted.amplitude)
    psf = (fitted.nodes[0] if grid is None
           else GriddedFluxDependentPSF(fitted.nodes, x_nodes, y_nodes))
    table = star_table(flags, image_index, positions, stars, variance)
    n_kept = int(np.sum(table["flags"] == 0))
    if n_kept < 3:  # a P0 that no star's fit holds is not a result
        msg = (f"the P0 fit kept {n_kept} of {len(table)} stars (the others' flux or position "
               "fits failed): check the sky level and the star list")
        raise BFPSFInputError(msg, n_kept)
    return PSFFitResult(psf=psf, stars=table,
                        iterations=iteration, converged=converged, changes=np.array(changes),
                        neighbours=neighbour_table(stars), diverged=bool(diverged))


def _fit_step(fitted, dense_weights, stars, free_positions, shapes):
    """Every star's model and one Gauss-Newton step on its cutout minus its neighbours'
    models: (model, residual predicted after the step, pixel variance, xs, ys, chi-square of
    the P0 stars before the step, the EMPIRICAL term's part per unit amplitude or None)."""
    stars.flags[:] = 0
    model, jacobian, xs, ys, unit = _star_models(fitted, dense_weights, stars, free_positions)
    others = stars.others(model, shapes)
    # the neighbours' light is noise in every cutout; pixels beyond the image weigh nothing
    variance = np.where(stars.valid & ~stars.masked, np.clip(model + others, 0.0, None)
                        + stars.floor[:, None, None], np.inf)
    chi2 = float(np.nansum(((stars.data - others - model)**2 / variance)[stars.used]))
    residual = _gauss_newton(stars, stars.data - others, model, jacobian, variance,
                             np.ones(len(model), dtype=bool))
    return model, residual, variance, xs, ys, chi2, unit


