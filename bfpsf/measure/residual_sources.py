"""Sources found in the residual of a PSF fit: the stars the first detection missed.

Detection on the image (`bfpsf.measure.neighbours.sources_with_companions`) misses two kinds of
star: a companion on a bright star's wing makes no peak of its own (a shoulder), and in a
crowded field the smoothed image's clipped RMS, the unit of the threshold, holds the stars'
wings, so faint isolated stars fall under it. Photometry then gives the bright star its
companion's light (a new user's 4e4-1.6e5 e- companions 8-10 px from 1e6 e- stars: +4 to +6 %
of the bright star's flux, some unflagged), and leaves the faint stars out (46 of 55 isolated
stars of 1-2e4 e- in a crowded ITL field, none in a sparse one).

Once the stars are fitted, their models are subtracted and the residual is searched again, as
photutils' ``IterativePSFPhotometry`` does, but against the noise the fit predicts (the sky,
the stars' Poisson noise, the read noise and `MODEL_ERROR` of each model pixel, for the PSF's
own error at bright cores) rather than the image's RMS: the matched-filter significance of
every peak, the same threshold as detection's companions. A source is light above the surface
about it (what the sky model left there) and shaped as the fitted stars, so that a seam of
the sky, a trail or a cosmic ray is none.
"""

import numpy as np
from astropy.convolution import convolve
from astropy.table import Table
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from .neighbours import COMPANION_SEPARATION, local_peaks
from .smoothing import detection_kernel
from .sources import SourceFlag

__all__ = ["residual_sources", "MODEL_ERROR"]

#: The fraction of each model pixel counted as the model's own error in the residual's noise:
#: P(F) fits a bright star's core to about 1 % of its peak (a P0 of 15 stars per grid node
#: worse), and a residual there is not a star; a companion on the wing is far above it.
MODEL_ERROR = 0.05

#: The most of a star's flux a misfit of it holds (the peak's 5 x 5 pixels): misfits found
#: held 0.03-0.7 % (a wrong PSF, a poor grid, clipped cores), 1-2 % once.
MISFIT_FRACTION = 0.01

#: How near the edge of a star's support (pixels) a peak is taken for the model's end.
SUPPORT_EDGE = 1.5

#: DAOFIND's bound on a source's roundness (its marginals' heights along x and y, 2 (hx -
#: hy) / (hx + hy)): a line along a row or a column (a seam of the sky) has one marginal
#: flat, a star both alike.
MAX_ROUNDNESS = 1.0

#: How far (pixels, each side) a source's line fraction samples the filtered residual
#: (`_line_fractions`).
LINE_LENGTH = 4

#: The detection smoothing's FWHM, pixels (`measure_sources`' default).
DETECTION_FWHM = 3.0


def residual_sources(residual_e, variance_e, known_xy, *, threshold, model_e=None,
                     known_flux=None, reach=None, support=None, excluded=None,
                     detection_fwhm=DETECTION_FWHM):
    """Sources in the residual of a PSF fit: peaks of its matched filter at least
    ``threshold + 3`` times the filter's noise (detection's rule for the companions of a
    merged segment, `bfpsf.measure.neighbours.smoothed_peaks`), whose light, as it is and
    above the quadratic surface about them, is ``threshold`` times its noise, shaped as a
    star (`_line_fractions`: neither a line nor sharper than the fitted stars), more than
    `COMPANION_SEPARATION` pixels from every known source and, within ``reach`` of a known
    star, ``threshold`` above the point opposite through that star (the one of largest flux
    over distance cubed; the highest within 2 pixels of that point): a misfit of the star is
    a ring (a Gaussian PSF's fit of 36 Moffat stars, 18 of them clipped by saturation, left
    172 peaks about them), a companion is on one side (`bfpsf.model.psf_fit_stars` masks a
    P0 star's companions by the same rule).

    Parameters
    ----------
    residual_e : ndarray [y, x]
        The image minus the sky and the fitted stars' models, e-; non-finite pixels count as 0.
    variance_e : ndarray [y, x]
        The pixels' variance the fit predicts (sky, stars, read noise), e-^2.
    known_xy : ndarray (N, 2)
        (x, y) of the sources fitted already.
    threshold : float
        Detection threshold (`bfpsf.measure.sources.DETECTION_THRESHOLD` by default in
        photometry).
    model_e : ndarray [y, x], optional
        The fitted stars' models, e-: `MODEL_ERROR` of each pixel is added to its noise.
    known_flux : ndarray (N,), optional
        Their fluxes, e-, for the test against the point opposite (with ``reach``).
    reach : float, optional
        How far a star's misfit reaches, pixels (its model's support).
    support : float, optional
        Half-width of the PSF model's square support, pixels: no source is taken within
        `SUPPORT_EDGE` of its edge about its host star (the model ends there).
    excluded : ndarray of bool [y, x], optional
        Pixels where no source is sought and whose light is none (about a saturated star:
        its clipped core is no model's; the cosmic rays detection found).
    detection_fwhm : float, optional
        FWHM of the Gaussian filter, pixels.

    Returns
    -------
    astropy.table.Table
        ``x_init``, ``y_init``, ``flux_init`` (the residual's sum over the 5 x 5 pixels about
        the peak above the surface about it, at least ``threshold`` times its noise: light,
        not a misfit's pattern),
        ``source_flags`` (``IN_RESIDUAL``), ``significance``; empty when none.
    """
    residual = np.where(np.isfinite(residual_e), residual_e, 0.0)
    if excluded is not None:  # (zero before the filter, which spreads them beside)
        residual = np.where(excluded, 0.0, residual)
    variance = np.where(np.isfinite(variance_e), np.clip(variance_e, 1.0, None), 1.0)
    if model_e is not None:
        variance = variance + (MODEL_ERROR * np.clip(model_e, 0.0, None)) ** 2
    weights = np.asarray(detection_kernel(detection_fwhm).array, dtype=float)
    weights = weights / weights.sum()
    # the filter's output over its noise: sum k r / sqrt(sum k^2 v)
    filtered = convolve(residual, weights, normalize_kernel=False, boundary="extend")
    noise = np.sqrt(convolve(variance, weights ** 2, normalize_kernel=False, boundary="extend"))
    significance = filtered / noise
    if excluded is not None:
        significance = np.where(excluded, 0.0, significance)
    x, y, rows, columns = local_peaks(significance, threshold + 3.0, detection_fwhm, border=2)
    known_xy = np.asarray(known_xy, dtype=float).reshape(-1, 2)
    finite = np.all(np.isfinite(known_xy), axis=1)
    known_xy = known_xy[finite]
    if len(x) and len(known_xy):
        distance, _ = cKDTree(known_xy).query(np.column_stack([x, y]))
        keep = distance > COMPANION_SEPARATION
        x, y, rows, columns = x[keep], y[keep], rows[keep], columns[keep]
    # light, not a pattern: the 5 x 5 pixels about the peak hold ``threshold`` times their
    # noise, as they are (a misfit's dipole or ring sums to about nothing: a 2 x 2 grid of
    # 15 stars per node left 18 peaks of 8-16 errors whose pixels held 1-500 e-) and above
    # the surface about them (a level the sky model missed is no light: a frame tiled 2 x 2,
    # its seams steps of the sky of hundreds of e-, gave 737 sources about 120 stars, 284 s
    # of fits)
    flux, error = (np.array([np.sum(values[row - 2:row + 3, column - 2:column + 3])
                             for row, column in zip(rows, columns)], dtype=float)
                   for values in (residual, variance))
    stamps, surfaces = _stamps(residual, rows, columns)
    flux = np.minimum(flux, stamps[:, 2:-2, 2:-2].sum(axis=(1, 2)))
    # the fitted stars' own line fraction (a convolution of the whole model image): only
    # when a peak is left to compare with it
    star, point = (_reference_fractions(model_e, known_xy, weights) if len(x)
                   else (np.nan, np.nan))
    fraction = _line_fractions(filtered, rows, columns, surfaces)
    # a star's shape: round, neither a line in any direction (the line fraction halfway from
    # a star's to 1: a trail, a seam) nor sharper than the fitted stars (halfway to a single
    # pixel's: a cosmic ray). Noise on a seam of the sky can pass the line fraction, a
    # diagonal trail passes the roundness: with both, a new user's trails of 100, 200 and
    # 400 e- per pixel left 19, 12 and 5 sources instead of 40, 33 and 32 (the trail's ends
    # at the stars detection fitted on it have one side, as a companion's off-centre peak)
    shaped = ((np.abs(_roundness(stamps, detection_fwhm)) <= MAX_ROUNDNESS)
              & (fraction < star + 0.5 * (1.0 - star))
              & (fraction > point + 0.5 * (star - point)))
    light = (flux >= threshold * np.sqrt(error)) & shaped
    x, y, rows, columns, flux = x[light], y[light], rows[light], columns[light], flux[light]
    if len(x) and known_flux is not None and reach is not None:
        opposite = _opposite_significance(significance, np.column_stack([x, y]), flux,
                                          known_xy, np.asarray(known_flux, float)[finite],
                                          reach, support)
        keep = significance[rows, columns] - opposite >= threshold
        x, y, rows, columns, flux = x[keep], y[keep], rows[keep], columns[keep], flux[keep]
    return Table({"x_init": x, "y_init": y, "flux_init": flux,
                  "source_flags": np.full(len(x), SourceFlag.IN_RESIDUAL, dtype=np.int64),
                  "significance": significance[rows, columns]})


def _opposite_significance(significance, xy, flux_xy, known_xy, known_flux, reach,
                           support=None):
    """The highest significance within 2 pixels of the point opposite each peak ``xy`` (of
    light ``flux_xy``) through the known star of largest flux over distance cubed within
    ``reach`` (a ring's peaks are rarely exactly opposite): inf where that point is off the
    image or the peak lies within `SUPPORT_EDGE` of the edge of that star's square support of
    half-width ``support``; -inf where there is no such star or the peak holds more than
    `MISFIT_FRACTION` of its flux (a star's misfit is a small part of its light: faint
    isolated stars 10-14 px from bright ones were taken for misfits)."""
    opposite = np.full(len(xy), -np.inf)
    if not len(known_xy):
        return opposite
    flux = np.where(np.isfinite(known_flux) & (known_flux > 0), known_flux, 0.0)
    tree = cKDTree(known_xy)
    for index, near in enumerate(tree.query_ball_point(xy, reach)):
        if not near:
            continue
        near = np.asarray(near, dtype=int)
        distance = np.hypot(*(known_xy[near] - xy[index]).T)
        host = near[np.argmax(flux[near] / np.maximum(distance, 1.0) ** 3)]
        if flux_xy[index] > MISFIT_FRACTION * flux[host]:
            continue
        if support is not None and abs(np.abs(xy[index] - known_xy[host]).max()
                                       - support) <= SUPPORT_EDGE:
            # at the edge of the host's square support, where its model ends and its wings
            # go on (a grid's P0 of 15 stars per node left 16 peaks 12 px below 7e5-1.6e6 e-
            # stars in a field of 60): not a source
            opposite[index] = np.inf
            continue
        column, row = np.rint(2 * known_xy[host] - xy[index]).astype(int)
        box = significance[max(row - 2, 0):row + 3, max(column - 2, 0):column + 3]
        # off the image, nothing tells a misfit from a companion: not a source
        opposite[index] = box.max() if box.size else np.inf
    return opposite


def _stamps(residual, rows, columns, inner=4, outer=7):
    """The residual's (2 ``inner`` + 1)^2 pixels about each peak, less the quadratic surface
    fitted to the ring ``inner`` < |dx|, |dy| <= ``outer`` about it (what the sky model left
    there, a level or a slope, and the curvature of a bright neighbour's wing, not light of
    the peak), and that surface's coefficients (1, dx, dy, dx^2, dx dy, dy^2)."""
    offsets = np.arange(-outer, outer + 1)
    dy, dx = (grid.ravel() for grid in np.meshgrid(offsets, offsets, indexing="ij"))
    ring = np.maximum(np.abs(dy), np.abs(dx)) > inner
    solver = np.linalg.pinv(_quadratic(dx, dy)[ring])
    design = _quadratic(dx, dy)
    padded = np.pad(residual, outer, mode="edge")
    centre = slice(outer - inner, outer + inner + 1)
    stamps = np.empty((len(rows), 2 * inner + 1, 2 * inner + 1))
    surfaces = np.empty((len(rows), 6))
    for index, (row, column) in enumerate(zip(rows, columns)):
        box = padded[row:row + 2 * outer + 1, column:column + 2 * outer + 1]
        surfaces[index] = solver @ box.ravel()[ring]
        stamps[index] = (box - (design @ surfaces[index]).reshape(box.shape))[centre, centre]
    return stamps, surfaces


def _quadratic(dx, dy):
    dx, dy = np.asarray(dx, float), np.asarray(dy, float)
    return np.column_stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy])


def _line_fractions(filtered, rows, columns, surfaces=None, length=LINE_LENGTH):
    """Each peak's line fraction: the lower of the means of the filtered image (less the
    surface about the peak) at 1 to ``length`` pixels on either side of it, along the best of
    8 directions, over its value at the peak: about 0.5 for a star, 1 for a line (a trail, a
    seam of the sky), 0.35 for a single pixel (a cosmic ray) through the detection filter."""
    steps = np.r_[-length:0, 1:length + 1].astype(float)
    angles = np.arange(8) * np.pi / 8
    dx, dy = np.outer(np.cos(angles), steps), np.outer(np.sin(angles), steps)
    design = _quadratic(dx.ravel(), dy.ravel())
    fractions = np.full(len(rows), np.inf)
    for index, (row, column) in enumerate(zip(rows, columns)):
        along = map_coordinates(filtered, [row + dy.ravel(), column + dx.ravel()], order=1,
                                mode="nearest").reshape(dx.shape)
        peak = filtered[row, column]
        if surfaces is not None:
            along = along - (design @ surfaces[index]).reshape(dx.shape)
            peak = peak - surfaces[index][0]
        if peak > 0:  # both sides: a star off the peak (on a wing's slope) has one
            fractions[index] = np.minimum(along[:, :length].mean(axis=1),
                                          along[:, length:].mean(axis=1)).max() / peak
    return fractions


def _reference_fractions(model_e, known_xy, weights):
    """The line fraction of a star (the median over the known stars of the fitted models,
    or a Gaussian as wide as the filter without them) and of a single pixel, through the
    filter ``weights``."""
    size = weights.shape[0] + 2 * LINE_LENGTH + 2
    point = np.zeros((size, size))
    point[size // 2, size // 2] = 1.0
    spread = convolve(point, weights, normalize_kernel=False)
    centre = np.array([size // 2])
    single = _line_fractions(spread, centre, centre)[0]
    if model_e is not None and len(known_xy):
        columns, rows = np.rint(known_xy).astype(int).T
        inside = ((rows >= 0) & (rows < model_e.shape[0]) & (columns >= 0)
                  & (columns < model_e.shape[1]))
        if inside.any():
            stars = convolve(np.clip(model_e, 0.0, None), weights, normalize_kernel=False,
                             boundary="extend")
            return float(np.median(_line_fractions(stars, rows[inside], columns[inside]))), single
    return float(_line_fractions(convolve(spread, weights, normalize_kernel=False),
                                 centre, centre)[0]), single


def _roundness(stamps, fwhm, width=5):
    """DAOFIND's ``roundness2`` of each stamp: the heights hx, hy of its marginals along x
    and y (the highest correlation with a zero-sum Gaussian of ``fwhm`` over ``width``
    pixels, so that a peak off the stamp's centre keeps its height), 2 (hx - hy) /
    (hx + hy); 0 for a round source, beyond +-1 for a line."""
    offsets = np.arange(width) - width // 2
    profile = np.exp(-0.5 * (offsets / (fwhm / 2.3548)) ** 2)
    profile = profile - profile.mean()
    windows = np.lib.stride_tricks.sliding_window_view
    hx, hy = ((windows(stamps.sum(axis=axis), width, axis=-1) @ profile).max(axis=-1)
              for axis in (1, 2))
    total = hx + hy
    return np.where(total > 0, 2.0 * (hx - hy) / np.where(total > 0, total, 1.0), np.inf)
