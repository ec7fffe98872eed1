"""Total flux: the light beyond the PSF's support, measured from the bright isolated stars.

P0 is normalised inside its support (``bfpsf psf --size``, 25 pixels): a star's flux fitted
with it is the flux inside that square, and the wings beyond it are lost (0.1 % for a Moffat
of beta 3.5 and FWHM 3.45 px, 1.5 % for a Kolmogorov atmosphere with an optical PSF, whose
wings fall as r^-11/3). Those wings are also what biases a sky estimated from the pixels
between the stars: summed over a field of bright stars they make a glow that no mask
removes (8 e- per pixel for 60 Kolmogorov stars of peaks 3-120 ke- on 300^2 pixels).

`WingModel` is a power law W(r) = A r^-p per unit fitted flux beyond the support, measured
from the radial profiles of the bright isolated stars (`measure_wings`); its integral beyond
the support is ``flux_correction - 1``, the total flux over the fitted flux, which the PSF
product keeps and photometry applies, so that ``flux_fit`` is the star's total flux.
`wing_image` is the glow of a set of stars, which the sky estimate subtracts
(`bfpsf.measure.sky.estimate_sky`), so the sky is what is left beyond the stars' total-flux
model. Sky and wings are measured in turn (`bfpsf.workflow.psf_from_images`): the bright stars
set the wings (a sky error enters W as sky / F), the wings the sky.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFInputError
from .sky import SkyModel, _powers, source_mask

__all__ = ["WingModel", "fit_sky_and_wings", "wing_image"]

#: Outer radius of the wings fitted and of a star's glow (`wing_image`), in support
#: half-widths.
GLOW = 6.0


@dataclass(frozen=True)
class WingModel:
    """A star's light beyond the PSF support, per unit of the flux inside it.

    Attributes
    ----------
    amplitude : float
        A of W(r) = A r^-p, per pixel per unit fitted flux (r in pixels).
    power : float
        p (> 2: finite total flux).
    half_size : int
        Half-width of the support, pixels (the square inside is P0's).
    fraction, fraction_err : float
        Flux beyond the support over the flux inside it, and its error: ``flux_correction``
        is 1 + ``fraction``.
    n_stars : int
        Stars measured.
    """

    amplitude: float
    power: float
    half_size: int
    fraction: float
    fraction_err: float
    n_stars: int

    @classmethod
    def none(cls, half_size):
        """No wings known (too few isolated stars): no correction, an unknown error."""
        return cls(0.0, 4.0, int(half_size), 0.0, float("nan"), 0)

    def __call__(self, r):
        """W at radius ``r`` (pixels), per pixel per unit fitted flux."""
        r = np.maximum(np.asarray(r, dtype=float), 1.0)
        return self.amplitude * r**-self.power


#: Powers p of the wings tried (W = A r^-p): from a Kolmogorov atmosphere's 11/3 (and
#: shallower) to a Moffat of beta 4's 8.
_POWERS = np.arange(2.6, 8.01, 0.1)


def _beyond_square(power, half_size):
    """Integral of r^-p over the plane outside the (2h + 1)^2 support (unit amplitude)."""
    reach = int(np.ceil(GLOW * (half_size + 0.5)))
    y, x = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    r = np.hypot(x, y)
    outside = ((np.abs(x) > half_size) | (np.abs(y) > half_size)) & (r <= reach)
    return float(np.sum(r[outside]**-power) + 2 * np.pi * reach**(2 - power) / (power - 2))


def _pairs(x, y, flux, rows, columns, half_size):
    """(pixel, star radius, star flux) of every pixel within `GLOW` half-widths of a star and
    outside its support, and the pixels inside any star's support."""
    from scipy.spatial import cKDTree

    reach = GLOW * (half_size + 0.5)
    inside = np.zeros(rows.size, dtype=bool)
    pixel, radius, weight = [], [], []
    tree = cKDTree(np.column_stack([columns, rows]))
    for x_0, y_0, value in zip(x, y, flux):
        if not np.all(np.isfinite((x_0, y_0, value))):
            continue
        near = np.asarray(tree.query_ball_point((x_0, y_0), reach), dtype=int)
        if near.size == 0:
            continue
        column, row = int(np.rint(x_0)), int(np.rint(y_0))
        within = ((np.abs(columns[near] - column) <= half_size + 1)
                  & (np.abs(rows[near] - row) <= half_size + 1))
        inside[near[within]] = True
        pixel.append(near[~within])
        radius.append(np.hypot(columns[near[~within]] - x_0, rows[near[~within]] - y_0))
        weight.append(np.full((~within).sum(), value))
    if not pixel:
        return np.zeros(0, int), np.zeros(0), np.zeros(0), inside
    return np.concatenate(pixel), np.concatenate(radius), np.concatenate(weight), inside


def fit_sky_and_wings(images_e, stars, *, half_size, degree=1, max_pixels=40_000,
                      clip_nsigma=4.0):
    """The sky surface of every image and the stars' wings beyond the PSF support, fitted
    jointly: pixel = sky_k(x, y) + A sum_i F_i r_i^-p.

    For each power p of `_POWERS` the model is linear (A and the sky coefficients of every
    image); the p of least chi-square is kept. A power law ties the glow far from the stars
    (where it is degenerate with the sky) to the rings next to them (where it is not).
    Pixels inside any fitted star's support, and the cores of other sources
    (`bfpsf.measure.sky.source_mask`, one radius), are left out; sigma clipping removes what
    neither model holds.

    Parameters
    ----------
    images_e : sequence of ndarray [y, x]
        Images, e-, sky included (linearised).
    stars : sequence of (x, y, flux) arrays
        Per image, the fitted stars: positions (pixels) and the flux inside the support (e-).
    half_size : int
        Half-width of the PSF support, pixels.
    degree : int, optional
        Of each image's sky surface (default 1, a plane).
    max_pixels : int, optional
        Pixels per image at most (a regular subsample), default 40000.
    clip_nsigma : float, optional

    Returns
    -------
    skies : list of bfpsf.measure.sky.SkyModel
        ``method`` "fitted with the stars' wings".
    wings : WingModel
        Its ``fraction`` (flux beyond the support over flux inside it) and the error of that
        fraction: the amplitude's statistical error and the range of p within chi-square + 1.
    """
    n_terms = (degree + 1) * (degree + 2) // 2
    bases, values, pair_sets, offsets, templates = [], [], [], [0], []
    for index, (image, (x, y, flux)) in enumerate(zip(images_e, stars)):
        image = np.asarray(image, dtype=float)
        core = source_mask(image, reach=1.0, grow=1)
        rows, columns = np.nonzero(np.isfinite(image))
        step = max(1, rows.size // max_pixels)
        rows, columns = rows[::step], columns[::step]
        pixel, radius, weight, inside = _pairs(np.asarray(x, float), np.asarray(y, float),
                                               np.asarray(flux, float), rows, columns,
                                               half_size)
        # the fitted stars' supports and every source's core (a star not fitted, e.g. a
        # blend, would otherwise put its light in the sky) are left out
        keep = ~inside & ~core[rows, columns]
        if keep.sum() < 10 * n_terms:  # a field filled with stars: no sky to fit
            msg = (f"image {index + 1}: {int(keep.sum())} pixels lie beyond the stars' supports "
                   f"({2 * int(half_size) + 1} px) and the sources' cores, too few for its sky; "
                   "give the sky (--background) or a smaller --size")
            raise BFPSFInputError(msg, int(keep.sum()))
        new_index = np.cumsum(keep) - 1
        chosen = keep[pixel]
        pair_sets.append((new_index[pixel[chosen]] + offsets[-1], radius[chosen],
                          weight[chosen]))
        template = SkyModel((0.0,) * n_terms, degree, image.shape, np.nan, "")
        templates.append(template)
        x_centre, y_centre, scale = template._scale()
        bases.append(_powers((columns[keep] - x_centre) / scale,
                             (rows[keep] - y_centre) / scale, degree).T)
        values.append(image[rows[keep], columns[keep]])
        offsets.append(offsets[-1] + int(keep.sum()))
    values = np.concatenate(values)
    pixel = np.concatenate([pairs[0] for pairs in pair_sets])
    radius = np.concatenate([pairs[1] for pairs in pair_sets])
    weight = np.concatenate([pairs[2] for pairs in pair_sets])

    def solve(power, keep):
        """The least squares of [wing template, each image's sky terms] on the kept pixels,
        by blocks: each image's sky is projected out of the data and of the wing template
        (its terms touch its own pixels only), the amplitude is the ratio of what is left,
        and each sky is its projection less the amplitude's share. The same solution as one
        dense least squares, whose design (1 + terms x images columns) had taken 2 GB and
        20 times the time on a new user's four amplifiers of eight exposures.
        Returns (amplitude and the sky terms, deviation of every pixel, the wing
        template's squared norm beyond the skies: the amplitude's inverse variance per rms^2)."""
        wing = np.bincount(pixel, weights=weight * radius**-power, minlength=values.size)
        wing_left, values_left, parts = np.empty_like(values), np.empty_like(values), []
        for index, basis in enumerate(bases):
            block = slice(offsets[index], offsets[index + 1])
            mine = keep[block]
            of_wing, of_values = np.linalg.lstsq(
                basis[mine], np.column_stack([wing[block][mine], values[block][mine]]),
                rcond=None)[0].T
            wing_left[block] = wing[block] - basis @ of_wing
            values_left[block] = values[block] - basis @ of_values
            parts.append((of_wing, of_values))
        norm = float(np.sum(wing_left[keep] ** 2))
        amplitude = float(np.sum(wing_left[keep] * values_left[keep]) / norm) if norm > 0 else 0.0
        solution = np.concatenate([[amplitude]] + [of_values - amplitude * of_wing
                                                   for of_wing, of_values in parts])
        return solution, values_left - amplitude * wing_left, norm

    keep = np.ones(values.size, dtype=bool)
    # a noiseless sky beyond the stars (a simulation, a known sky subtracted) has no scatter:
    # the floor keeps the clipping and the chi-square of the powers finite
    floor = 1e-12 * max(1.0, float(np.max(np.abs(values))) if values.size else 1.0)
    for _ in range(10):  # the clipping, at a Kolmogorov-like power
        _, deviation, _ = solve(11 / 3, keep)
        rms = max(1.4826 * float(np.median(np.abs(deviation[keep]))), floor)
        new_keep = np.abs(deviation) <= clip_nsigma * rms
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    chi2 = np.array([np.sum(solve(power, keep)[1][keep]**2) for power in _POWERS]) / rms**2
    best = int(np.argmin(chi2))
    power = float(_POWERS[best])
    solution, deviation, norm = solve(power, keep)
    amplitude_err = rms / np.sqrt(norm) if norm > 0 else 0.0
    amplitude = float(solution[0])
    fraction = amplitude * _beyond_square(power, half_size)
    # the powers within chi-square + 1, at their own best amplitudes
    within = np.flatnonzero(chi2 <= chi2[best] + 1.0)
    spread = [solve(_POWERS[k], keep)[0][0] * _beyond_square(_POWERS[k], half_size)
              for k in (within.min(), within.max())]
    error = float(np.hypot(amplitude_err * _beyond_square(power, half_size),
                           (max(spread) - min(spread)) / 2))
    skies = []
    for index, template in enumerate(templates):
        part = solution[1 + index * n_terms:1 + (index + 1) * n_terms]
        mine = keep[offsets[index]:offsets[index + 1]]
        scatter = deviation[offsets[index]:offsets[index + 1]][mine]
        skies.append(SkyModel(tuple(float(c) for c in part), degree, template.shape,
                              float(1.4826 * np.median(np.abs(scatter))),
                              "fitted with the stars' wings", int(mine.sum())))
    n_stars = int(sum(len(star[0]) for star in stars))
    return skies, WingModel(max(amplitude, 0.0), power, int(half_size), fraction, error,
                            n_stars)


def wing_image(wings, x, y, flux, shape):
    """The glow of stars beyond their supports out to `GLOW` half-widths, e- per pixel.

    Parameters
    ----------
    wings : WingModel
    x, y, flux : array_like
        Star positions (pixels) and fluxes inside the support (e-); non-finite ones skipped.
    shape : (int, int)

    Returns
    -------
    ndarray [y, x]
    """
    image = np.zeros(shape)
    if wings.amplitude <= 0:
        return image
    half = wings.half_size
    for x_0, y_0, value in zip(np.ravel(x), np.ravel(y), np.ravel(flux)):
        if not np.all(np.isfinite((x_0, y_0, value))) or value <= 0:
            continue
        # out to where the star's glow falls below 1e-3 e- per pixel, at most GLOW
        reach = int(np.ceil(min(GLOW * (half + 0.5), max(
            half + 1.0, (value * wings.amplitude / 1e-3) ** (1.0 / wings.power)))))
        column, row = int(np.rint(x_0)), int(np.rint(y_0))
        rows = slice(max(row - reach, 0), min(row + reach + 1, shape[0]))
        columns = slice(max(column - reach, 0), min(column + reach + 1, shape[1]))
        if rows.start >= rows.stop or columns.start >= columns.stop:
            continue
        yy, xx = np.mgrid[rows, columns]
        outside = (np.abs(xx - column) > half) | (np.abs(yy - row) > half)
        image[rows, columns] += np.where(outside, value * wings(np.hypot(xx - x_0, yy - y_0)),
                                         0.0)
    return image
