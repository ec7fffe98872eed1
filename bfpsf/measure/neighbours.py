"""A star's neighbours: every peak of the image, the companions detection merged, and the
stars isolated enough to fit a PSF from.

`smoothed_peaks` finds the maxima of the smoothed image (the peaks `measure_sources` counts to
flag a segment ``BLENDED``); `sources_with_companions` adds a peak of a blend that detection
left out as a source of its own, so PSF photometry fits it; `isolated_stars` keeps the stars
with no detected neighbour within a stamp, for the P0 fit.
"""

import numpy as np
from astropy.stats import gaussian_fwhm_to_sigma, sigma_clipped_stats
from astropy.table import Table
from scipy import ndimage
from scipy.spatial import cKDTree

from ..model.nanfill import harmonic_fill
from .line_features import near_lines, resolve_lines
from .smoothing import smoothed_image
from .sources import DETECTION_THRESHOLD, LINE_REACH, SourceFlag, measure_sources, ray_mask

__all__ = ["smoothed_peaks", "sources_with_companions", "isolated_stars",
           "COMPANION_SEPARATION"]

#: A peak this far (pixels) from every detection is a companion of its own.
COMPANION_SEPARATION = 2.5


def smoothed_peaks(image_e, *, threshold=DETECTION_THRESHOLD, detection_fwhm=3.0):
    """Peaks of the smoothed sky-subtracted image, (x, y) pixels: maxima of a window of
    ``2 * detection_fwhm + 1`` pixels at least ``threshold + 3`` RMS of the smoothed image
    (the peaks `measure_sources` counts to flag a segment ``BLENDED``), centroided on their
    3 x 3 neighbourhood.

    Parameters
    ----------
    image_e : ndarray [y, x]
        Sky-subtracted image, e-; non-finite pixels count as 0.
    threshold : float, optional
        Detection threshold, RMS of the smoothed image (default 5).
    detection_fwhm : float, optional
        FWHM of the smoothing, pixels (default 3, as `measure_sources`).

    Returns
    -------
    ndarray (N, 2)
    """
    smoothed = smoothed_image(image_e, detection_fwhm)
    _, _, rms = sigma_clipped_stats(smoothed, sigma=3.0)
    x, y, _, _ = local_peaks(smoothed, (threshold + 3.0) * rms, detection_fwhm)
    return np.column_stack([x, y])


def local_peaks(values, level, detection_fwhm, border=1):
    """Maxima of ``values`` within a window of ``2 * ceil(detection_fwhm) + 1`` pixels, at
    least ``level`` and more than ``border`` pixels inside the image, centroided on their
    3 x 3 neighbourhood: (x, y, rows, columns)."""
    size = 2 * int(np.ceil(detection_fwhm)) + 1
    peaks = (values == ndimage.maximum_filter(values, size=size)) & (values >= level)
    rows, columns = np.nonzero(peaks)
    inside = ((rows >= border) & (rows < values.shape[0] - border) & (columns >= border)
              & (columns < values.shape[1] - border))
    rows, columns = rows[inside], columns[inside]
    offsets = np.arange(-1, 2)
    windows = values[rows[:, None, None] + offsets[None, :, None],
                     columns[:, None, None] + offsets[None, None, :]]
    windows = np.clip(windows - windows.min(axis=(1, 2), keepdims=True), 0, None)
    total = np.maximum(windows.sum(axis=(1, 2)), 1e-30)
    x = columns + np.sum(windows.sum(axis=1) * offsets, axis=1) / total
    y = rows + np.sum(windows.sum(axis=2) * offsets, axis=1) / total
    return x, y, rows, columns


def sources_with_companions(image_e, *, threshold=DETECTION_THRESHOLD, lines=True,
                            cosmic_rays=True, **kwargs):
    """Every source of an image: the detections of `measure_sources` and the companions a
    merged segment hides (peaks of the smoothed image, `smoothed_peaks`, more than 2.5
    pixels from every detection, flagged ``BLENDED``; their ``flux_e`` the sum of the 5 x 5
    pixels around the peak). A segment is one detection however many stars it holds.

    Parameters
    ----------
    image_e : ndarray [y, x]
        Sky-subtracted image, e-; non-finite pixels count as 0.
    threshold : float, optional
        Detection threshold (`measure_sources`).
    lines : bool or ndarray of bool [y, x], optional
        Pixels of trails and hot columns, left out (`measure_sources`): True (default) finds
        them, an array gives them, False leaves none out.
    cosmic_rays : bool or ndarray of bool [y, x], optional
        Pixels of cosmic rays, filled from their neighbours (`measure_sources`): True
        (default) finds them, an array gives them, False leaves them in (a cosmic ray is
        then a source, or a companion).
    **kwargs
        Passed to `measure_sources`.

    Returns
    -------
    astropy.table.Table
        ``x``, ``y``, ``flux_e``, ``flags`` (`SourceFlag`); the detections first, then the
        companions; ``meta['n_detected']`` the detections, ``meta['line_pixels']`` the pixels
        of lines left out, ``meta['cosmic_ray_pixels']`` and ``meta['cosmic_rays']`` those
        of cosmic rays filled (`bfpsf.measure.sources.ray_mask`).
    """
    image = np.where(np.isfinite(image_e), image_e, 0.0)
    lines = resolve_lines(lines, image, threshold)
    image = np.where(lines, 0.0, image)
    sources = measure_sources(image, threshold=threshold, lines=lines, cosmic_rays=cosmic_rays,
                              **kwargs)
    rays = ray_mask(sources, image.shape)
    if rays.any():  # no companion on a cosmic ray
        image = harmonic_fill(image, rays, isolated="nan")
    x = np.asarray(sources["x"], dtype=float)
    y = np.asarray(sources["y"], dtype=float)
    flux = np.asarray(sources["flux_e"], dtype=float)
    flags = np.asarray(sources["flags"], dtype=np.int64)
    peaks = smoothed_peaks(image, threshold=threshold)
    if len(peaks) and len(x):
        distance, _ = cKDTree(np.column_stack([x, y])).query(peaks)
        peaks = peaks[distance > COMPANION_SEPARATION]
    if len(peaks):
        rows = np.clip(np.rint(peaks[:, 1]).astype(int), 2, image.shape[0] - 3)
        columns = np.clip(np.rint(peaks[:, 0]).astype(int), 2, image.shape[1] - 3)
        boxes = [np.sum(image[row - 2:row + 3, column - 2:column + 3])
                 for row, column in zip(rows, columns)]
        x, y = np.r_[x, peaks[:, 0]], np.r_[y, peaks[:, 1]]
        flux = np.r_[flux, np.maximum(boxes, 1.0)]
        flags = np.r_[flags, np.full(len(peaks), SourceFlag.BLENDED, dtype=np.int64)
                      | np.where(near_lines(lines, peaks[:, 0], peaks[:, 1], LINE_REACH
                                            * kwargs.get("detection_fwhm", 3.0)
                                            * gaussian_fwhm_to_sigma),
                                 SourceFlag.ON_LINE, 0)]
    table = Table({"x": x, "y": y, "flux_e": flux, "flags": flags})
    table.meta["n_detected"] = len(sources)
    table.meta["line_pixels"] = int(lines.sum())
    table.meta["cosmic_ray_pixels"] = sources.meta["cosmic_ray_pixels"]
    table.meta["cosmic_rays"] = sources.meta["cosmic_rays"]
    return table


#: the flags of a source that the P0 fit takes all the same (`isolated_stars`)
P0_TAKES = SourceFlag.NEIGHBOUR_LIGHT | SourceFlag.UNDERSAMPLED


def isolated_stars(image_e, size, *, threshold=DETECTION_THRESHOLD, saturation_e=None,
                   lines=True, cosmic_rays=True, return_rays=False):
    """Clean, unsaturated detections isolated within ``size`` pixels: the stars a P0 fit
    (`bfpsf.model.psf_fit.fit_psf`) takes; and every other source (`sources_with_companions`),
    the neighbours the P0 fit models alongside them.

    Parameters
    ----------
    image_e : ndarray [y, x]
        Background-subtracted image, e-.
    size : int
        Side of the P0 support and of the star cutouts, pixels.
    threshold : float, optional
        Detection threshold (`measure_sources`).
    saturation_e : float, optional
        Saturation level above the background, e-.
    lines : bool or ndarray of bool [y, x], optional
        Pixels of trails and hot columns (`sources_with_companions`): no star with one in its
        cutout is isolated.
    cosmic_rays : bool or ndarray of bool [y, x], optional
        Pixels of cosmic rays (`sources_with_companions`).
    return_rays : bool, optional
        Return the cosmic rays' pixels too (ndarray of bool [y, x], last).

    Returns
    -------
    positions : ndarray (N, 2)
        (x, y) of the stars, pixels.
    n_detected : int
        All detections, flagged ones included (companions not counted).
    others : ndarray (M, 2)
        (x, y) of every other source: flagged detections and the companions of merged
        segments.
    """
    lines = resolve_lines(lines, image_e, threshold)
    sources = sources_with_companions(image_e, threshold=threshold, lines=lines,
                                      cosmic_rays=cosmic_rays, blend_radius=size / 2 + 2,
                                      saturation=saturation_e, stamp_size=size + 6)
    xy = np.column_stack([np.asarray(sources["x"], dtype=float),
                          np.asarray(sources["y"], dtype=float)])
    # neighbours' light biases a star's moments, not the P0 fit, which models the wings of
    # every source it knows and fits the sky with their glow; a star too sharp for moments
    # has its detection's centroid, and P0 needs no moments (a new user's stars of FWHM 1.6
    # px: P0 from 27 of 200, not converged); a line in a cutout is no model's
    clean = (((np.asarray(sources["flags"]) & ~P0_TAKES) == 0)
             & ~near_lines(lines, xy[:, 0], xy[:, 1], size / np.sqrt(2.0)))
    found = xy[clean], int(sources.meta["n_detected"]), xy[~clean]
    return (*found, ray_mask(sources, image_e.shape)) if return_rays else found
