"""Pixel masks of a flat pair (G15 section 4.2.3).

Before the covariances are computed, pixels that would add spurious correlations are masked:
non-finite and saturated pixels, hot or dark columns, and clusters of defect pixels. The tile
tests run as compiled kernels (numba, cached after the first run).

Images are ``data[y, x]`` in ADU, bias-subtracted (DESIGN.md conventions).
"""

import logging
from dataclasses import dataclass

import numba
import numpy as np
from scipy.stats import median_abs_deviation

from ..errors import BFPSFInputError, BFPSFValueError
from .flats import Flat
from .kernels import FASTMATH, flag_row, flagged_positions

__all__ = ["DEFAULT_EDGE", "MaskReport", "pair_mask"]

log = logging.getLogger(__name__)

#: Pixels masked along each edge of an amplifier's image by default, as cp_pipe's PTC ISR
#: configuration does (``numEdgeSuspect = 10``, ``edgeMaskLevel = 'AMP'``; its LSSTCam
#: pipelines use 20). The first rows and columns of a sensor collect less charge, and
#: lose a fraction that grows with the flux (GalSim's SiliconSensor: 4.4, 1.4, 0.7 and 0.3 %
#: in the first four rows at 100 ke-), which the PTC would read as a gain non-linearity.
DEFAULT_EDGE = 10


@dataclass(frozen=True)
class MaskReport:
    """How many pixels of a pair each masking cause flagged.

    A pixel can be flagged by several causes, so the causes may add up to more than
    ``total``, the number of masked pixels.

    Attributes
    ----------
    nonfinite : int
        Pixels that are NaN or infinite in either flat.
    edge : int
        Pixels within the edge border.
    saturated : int
        Pixels at or above the saturation level in either flat.
    columns : int
        Pixels in hot or dark columns.
    defects : int
        Pixels in defect clusters (G15 section 4.2.3).
    total : int
        Pixels masked for any cause.
    npix : int
        Pixels in the image.
    """

    nonfinite: int
    saturated: int
    edge: int
    columns: int
    defects: int
    total: int
    npix: int

    @property
    def fraction(self):
        """Fraction of the image masked."""
        return self.total / self.npix if self.npix else 0.0

    def __str__(self):
        return (f"{self.total} of {self.npix} pixels masked ({100 * self.fraction:.3g} %): "
                f"{self.nonfinite} non-finite, {self.saturated} saturated, {self.edge} in the edge border, "
                f"{self.columns} in hot/dark columns, {self.defects} in defect clusters")


def _robust_sigma(values):
    """Standard deviation from the median absolute deviation (Gaussian-consistent)."""
    values = values[np.isfinite(values)]
    if values.size == 0:
        return np.nan
    return float(median_abs_deviation(values, scale="normal"))


#: The ``good`` argument of the compiled kernels when every pixel is good.
_NO_MASK = np.empty((0, 0), dtype=bool)


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def _tile_sums(band, good, j0, j1, centre, cut):
    """Sum, sum of squares and number of the good values of columns ``j0:j1`` of ``band``
    within ``cut`` of ``centre``, as offsets from it (``good`` empty: every pixel is good).
    Single precision along a row of the tile, double precision across rows."""
    use_good = good.shape[0] > 0
    centre = np.float32(centre)
    cut = np.float32(cut)
    total = 0.0
    total2 = 0.0
    kept = 0.0
    for i in range(band.shape[0]):
        row = band[i, j0:j1]
        row_sum = np.float32(0.0)
        row_sum2 = np.float32(0.0)
        row_kept = np.float32(0.0)
        if use_good:
            row_good = good[i, j0:j1]
            for j in range(row.size):
                offset = row[j] - centre
                inside = np.float32((abs(offset) <= cut) & row_good[j])
                offset = offset * inside
                row_sum += offset
                row_sum2 += offset * offset
                row_kept += inside
        else:
            for j in range(row.size):
                offset = row[j] - centre
                inside = np.float32(abs(offset) <= cut)
                offset = offset * inside
                row_sum += offset
                row_sum2 += offset * offset
                row_kept += inside
        total += row_sum
        total2 += row_sum2
        kept += row_kept
    return total, total2, kept


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def _tile_row_kernel(band, good, box, defect_nsigma, column_clip, usable, high, excluded_sums,
                     excluded_counts):
    """The tests of `_band_tests` on each tile of a row of tiles, compiled.

    Per tile: the first mean and sigma (every good pixel), the second (the good pixels within
    2 sigma of the first mean), then one pass that flags the pixels beyond the lowest
    threshold into a byte row and visits only the flagged ones (`flagged_positions`): high
    pixels go to ``high`` (the count is returned), pixels beyond ``column_clip`` sigma to the
    per-column ``excluded_sums`` / ``excluded_counts``. ``usable[tile]`` is set where both
    estimates exist.
    """
    rows, nx = band.shape
    use_good = good.shape[0] > 0
    n_high = 0
    flags = flag_row(box)
    positions = np.empty(box, dtype=np.int64)
    for tile in range((nx + box - 1) // box):
        j0 = tile * box
        j1 = min(nx, j0 + box)
        total, total2, count = _tile_sums(band, good, j0, j1, 0.0, np.inf)
        if count < 2:
            continue
        mean = total / count
        if not np.isfinite(mean):
            continue
        cut = 2.0 * np.sqrt(max(total2 / count - mean * mean, 0.0))
        total, total2, kept = _tile_sums(band, good, j0, j1, mean, cut)
        if kept < 2:
            continue
        shift = total / kept
        if not np.isfinite(shift):
            continue
        width = np.sqrt(max(total2 / kept - shift * shift, 0.0))
        usable[tile] = True
        high_limit = np.float32(mean + shift + defect_nsigma * width)
        upper = np.float32(mean + shift + column_clip * width)
        lower = np.float32(mean + shift - column_clip * width)
        lowest = min(high_limit, upper)
        for i in range(rows):
            row = band[i, j0:j1]
            for j in range(row.size):
                flags[j] = (row[j] > lowest) | (row[j] < lower)
            for k in range(flagged_positions(flags, row.size, positions)):
                j = positions[k]
                if use_good and not good[i, j0 + j]:
                    continue
                value = row[j]
                if value > high_limit:
                    high[n_high] = i * nx + j0 + j
                    n_high += 1
                if value > upper or value < lower:
                    excluded_sums[j0 + j] += value
                    excluded_counts[j0 + j] += 1.0
    return n_high


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def _fill_bands(rows1, rows2, good, mean1, mean2, scale, bands):
    """The three images the tests run on, for a band of rows of a pair, in single precision:
    each flat less its mean, and their difference ``(flat1 - mean1) - scale (flat2 -
    mean2)``; zero at the bad pixels (``good`` empty: none), whatever their values."""
    use_good = good.shape[0] > 0
    for i in range(rows1.shape[0]):
        row1, row2 = rows1[i], rows2[i]
        first, second, difference = bands[0, i], bands[1, i], bands[2, i]
        for j in range(row1.size):
            value1 = np.float32(row1[j] - mean1)
            value2 = np.float32(row2[j] - mean2)
            if use_good and not good[i, j]:
                value1 = np.float32(0.0)
                value2 = np.float32(0.0)
            first[j] = value1
            second[j] = value2
            difference[j] = value1 - scale * value2


def _band_tests(band, good, box, defect_nsigma, column_clip=5.0, buffer=None):
    """The column sums and the high pixels of one row of ``box x box`` tiles of an image.

    In each tile the mean and sigma of the good pixels are estimated twice (G15 section
    4.2.3, footnote): over all of them, then over those within 2 sigma of that first mean.
    With the second estimate, a good pixel is *high* when more than ``defect_nsigma`` sigma
    above the mean, and the level of a column is the mean of its good pixels within
    ``column_clip`` sigma of the mean (so a single defect does not move it). The per-tile
    work is compiled (`_tile_row_kernel`, numba): three passes over the band instead of
    fifteen array operations.

    Parameters
    ----------
    band : ndarray of float32, shape (rows, nx)
        The tile row, less a constant offset (so that single precision sums over its rows
        stay exact enough), zero at the bad pixels.
    good : ndarray of bool or None
        The good pixels of the band (None: all).
    buffer : ndarray of int64, optional
        Scratch space for the high pixels' indices, at least ``band.size`` long (reused
        across the bands of an image).

    Returns
    -------
    level_sums, level_counts : ndarray, shape (nx,)
        Sum (in the units of ``band``) and number of the pixels of each column that enter
        its level.
    high : ndarray of int
        Flat indices of the high pixels in the band, increasing.
    """
    rows, nx = band.shape
    band = np.ascontiguousarray(band, dtype=np.float32)
    column_sums = band.sum(axis=0).astype(np.float64)  # single precision over the rows
    counts = (np.full(nx, float(rows)) if good is None
              else good.sum(axis=0, dtype=np.int32).astype(np.float64))
    usable = np.zeros((nx + box - 1) // box, dtype=bool)
    high = np.empty(band.size, dtype=np.int64) if buffer is None else buffer
    excluded_sums = np.zeros(nx)
    excluded_counts = np.zeros(nx)
    n_high = _tile_row_kernel(band, _NO_MASK if good is None else np.ascontiguousarray(good),
                              int(box), float(defect_nsigma), float(column_clip), usable, high,
                              excluded_sums, excluded_counts)
    usable = np.repeat(usable, box)[:nx]
    level_sums = np.where(usable, column_sums - excluded_sums, 0.0)
    level_counts = np.where(usable, counts - excluded_counts, 0.0)
    return level_sums, level_counts, np.sort(high[:n_high])


def _image_tests(image1, image2, bad, box, defect_nsigma, totals=None):
    """Column levels and high pixels (`_band_tests`) of two flats and of their difference,
    one row of tiles at a time.

    The second flat is scaled to the first's mean in the difference (for a pair that is not a
    flat, means not both positive within a factor 1.5 of each other, e.g. bias frames, the
    plain difference is taken). ``totals``: the sums of the two images, when known and
    ``bad`` is None.

    Returns
    -------
    levels : list of three ndarray, shape (nx,)
        Column levels of flat 1, flat 2 and the difference, less their means (NaN for a
        column without good pixels within the clip).
    high : list of three ndarray of int
        Flat indices of their high pixels.

    Notes
    -----
    The tests run in single precision on each image less its mean, the sums in single
    precision over the rows of a tile and in double precision across tiles and tile rows.
    """
    ny, nx = image1.shape
    if bad is None:
        totals = totals or [image.sum(dtype=np.float64) for image in (image1, image2)]
        means = [total / image1.size for total in totals]
    else:
        means = [image.sum(dtype=np.float64, where=~bad) / np.count_nonzero(~bad)
                 for image in (image1, image2)]
    flat_pair = min(means) > 0 and max(means) < 1.5 * min(means)
    scale = np.float32(means[0] / means[1] if flat_pair else 1.0)
    level_sums = np.zeros((3, nx))
    level_counts = np.zeros((3, nx))
    high = [[], [], []]
    buffer = np.empty(box * nx, dtype=np.int64)
    band_buffer = np.empty((3, box, nx), dtype=np.float32)
    for y0 in range(0, ny, box):
        rows = slice(y0, y0 + box)
        good = None if bad is None or not bad[rows].any() else ~bad[rows]
        bands = band_buffer[:, :image1[rows].shape[0]]
        _fill_bands(image1[rows], image2[rows], _NO_MASK if good is None else good, means[0],
                    means[1], scale, bands)
        for number, band in enumerate(bands):
            sums, counts, band_high = _band_tests(band, good, box, defect_nsigma,
                                                  buffer=buffer)
            level_sums[number] += sums
            level_counts[number] += counts
            high[number].append(band_high + y0 * nx)
    with np.errstate(invalid="ignore", divide="ignore"):
        levels = np.where(level_counts > 0, level_sums / level_counts, np.nan)
    return list(levels), [np.concatenate(parts) for parts in high]


def _neighbour_median(values, window):
    """Median of the ``window - 1`` neighbours of each element (itself excluded), the ends
    mirrored; a quadratic trend is removed first so the mirrored ends follow it."""
    n = values.size
    half = max(1, min(window // 2, n - 1))
    index = np.arange(n)
    trend = np.polyval(np.polyfit(index, values, 2), index) if n > 3 else np.zeros(n)
    detrended = values - trend
    padded = np.pad(detrended, half, mode="reflect")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
    neighbours = np.delete(windows, half, axis=1)
    return np.median(neighbours, axis=1) + trend


def _bad_columns(levels, nsigma, window=31):
    """Columns whose level departs from their neighbours' by more than ``nsigma`` sigma.

    Each column level is compared with the median of the ``window - 1`` neighbouring columns
    (so a smooth illumination gradient is not flagged); sigma is the robust scatter of those
    residuals over all columns.
    """
    usable = np.isfinite(levels)
    if np.count_nonzero(usable) < 3:
        return np.zeros(levels.size, dtype=bool)
    # columns with no good pixel (the edge border) are left out of the neighbours: filled
    # with the median level, they bent the running median of a sloped flat near its edges
    residual = np.full(levels.size, np.nan)
    residual[usable] = levels[usable] - _neighbour_median(levels[usable], window)
    sigma = _robust_sigma(residual)
    if not np.isfinite(sigma) or sigma == 0:
        return np.zeros(levels.size, dtype=bool)
    with np.errstate(invalid="ignore"):
        return usable & (np.abs(residual) > nsigma * sigma)


def _clustered(highs, shape):
    """G15 section 4.2.3: the high pixels with more than two high pixels among their eight
    neighbours, in each image of a list (``highs``: flat indices of the high pixels of images
    of ``shape``). High pixels are few, so their neighbours are looked up directly in one
    image padded by one pixel, cleared between images.

    Returns the flat indices of the clustered pixels of each image.
    """
    ny, nx = shape
    padded = np.zeros((ny + 2) * (nx + 2), dtype=np.int8)
    clustered = []
    for high in highs:
        y, x = np.divmod(high, nx)
        padded_index = (y + 1) * (nx + 2) + (x + 1)
        padded[padded_index] = 1
        neighbours = np.zeros(high.size, dtype=np.int8)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    neighbours += padded[padded_index + dy * (nx + 2) + dx]
        padded[padded_index] = 0
        clustered.append(high[neighbours > 2])
    return clustered


def pair_mask(flat1, flat2, *, saturation=None, edge=DEFAULT_EDGE, column_nsigma=5.0,
              defect_nsigma=3.0, defect_box=128):
    """Mask of the pixels of a flat pair that must not enter the covariances.

    Causes, in order (each is evaluated on the pixels not already masked):

    1. non-finite pixels (NaN or inf) in either image: masked and counted, never an error;
    2. pixels at or above ``saturation`` (ADU) in either image, and the ``edge`` pixels along
       each side of the image;
    3. hot or dark columns: the level of a column (mean of its pixels within 5 local sigma
       of the local mean), in either image or their difference, departs from the running
       median of the levels of its 30 neighbouring columns by more than ``column_nsigma``
       times the robust scatter of the column levels (G15 section 4.2.3: "wherever hot or
       dark columns are being detected, they are masked"); the median of 30 neighbours
       follows smooth illumination gradients while adding only 5 % to the residual scatter;
    4. defect clusters (G15 section 4.2.3): in each ``defect_box`` x ``defect_box`` tile the
       mean and sigma are estimated once with all pixels and again with the pixels within
       2 sigma of the first mean; a pixel more than ``defect_nsigma`` sigma above the mean is
       masked when more than two of its eight neighbours are too. Applied to both images and
       to their difference (the second image scaled to the first's mean).

    The union is the mask of both images (and hence of their difference).

    Parameters
    ----------
    flat1, flat2 : Flat or ndarray, shape (ny, nx)
        The two flats of a pair, ADU.
    saturation : float, optional
        Saturation level, ADU. Default None: no saturation mask.
    edge : int, optional
        Pixels masked along each side of the image (one amplifier). Default `DEFAULT_EDGE`.
    column_nsigma : float, optional
        Threshold of the column test, in robust sigma of the column medians. Default 5.
    defect_nsigma : float, optional
        Threshold of the defect test, sigma above the local mean (G15: 3). Default 3.
    defect_box : int, optional
        Tile size of the local mean and sigma, pixels (G15: 128). Default 128.

    Returns
    -------
    mask : ndarray of bool, shape (ny, nx)
        True for a masked (bad) pixel.
    report : MaskReport
        Pixel counts per cause.

    Notes
    -----
    The second, 2-sigma-clipped estimate of sigma is about 0.88 times the Gaussian sigma, so
    the defect threshold is about 2.6 Gaussian sigma as G15 apply it; a clean flat still has
    almost no false detections, since a pixel needs three neighbours above the threshold too.
    """
    # native-order double precision (a FITS image is big-endian: the compiled tests need it)
    image1 = np.asarray(flat1.data if isinstance(flat1, Flat) else flat1, dtype=np.float64)
    image2 = np.asarray(flat2.data if isinstance(flat2, Flat) else flat2, dtype=np.float64)
    if image1.ndim != 2 or image1.shape != image2.shape:
        msg = f"flats of a pair must be 2-D images of one shape, got {image1.shape} and {image2.shape}"
        raise BFPSFInputError(msg, (image1.shape, image2.shape))
    edge = int(edge)
    if edge < 0 or 2 * edge >= min(image1.shape):
        msg = (f"the edge border ({edge} pixels on each side) leaves no pixel of the "
               f"{image1.shape[1]} x {image1.shape[0]} flats")
        raise BFPSFInputError(msg, edge)
    if defect_box < 3:
        msg = f"defect_box must be at least 3 pixels, got {defect_box}"
        raise BFPSFValueError(msg, defect_box)

    # Each cause keeps a full-size array only when it flags something: on a clean pair the
    # bookkeeping costs one mask, not five.
    totals = [image1.sum(dtype=np.float64), image2.sum(dtype=np.float64)]
    bad = None
    n_nonfinite = n_saturated = 0
    if not np.isfinite(totals).all():
        bad = ~(np.isfinite(image1) & np.isfinite(image2))
        n_nonfinite = int(np.count_nonzero(bad))
        log.info("masked %d non-finite pixels", n_nonfinite)
    if saturation is not None:
        with np.errstate(invalid="ignore"):
            saturated = (image1 >= saturation) | (image2 >= saturation)
        n_saturated = int(np.count_nonzero(saturated))
        if n_saturated:
            bad = saturated if bad is None else bad | saturated
    if edge:
        border = np.ones(image1.shape, dtype=bool)
        border[edge:-edge, edge:-edge] = False
        bad = border if bad is None else bad | border
    if bad is not None and not bad.any():
        bad = None
    if bad is not None and bad.all():
        msg = "every pixel of the pair is non-finite or saturated"
        raise BFPSFInputError(msg)
    box = int(defect_box)
    bad_columns = np.zeros(image1.shape[1], dtype=bool)
    levels, high = _image_tests(image1, image2, bad, box, defect_nsigma, totals)
    for image_levels in levels:
        bad_columns |= _bad_columns(image_levels, column_nsigma)
    if bad_columns.any():
        log.info("masked %d hot/dark columns: %s", np.count_nonzero(bad_columns),
                 np.flatnonzero(bad_columns).tolist())
    # the defect test runs on the pixels that the column test left
    nx = image1.shape[1]
    high = [image_high[~bad_columns[image_high % nx]] for image_high in high]
    defects = np.unique(np.concatenate(_clustered(high, image1.shape)))
    mask = np.zeros(image1.shape, dtype=bool) if bad is None else bad.copy()
    mask[:, bad_columns] = True
    mask.ravel()[defects] = True

    n_edge = image1.size - (image1.shape[0] - 2 * edge) * (image1.shape[1] - 2 * edge)
    report = MaskReport(nonfinite=n_nonfinite, saturated=n_saturated, edge=n_edge,
                        columns=int(np.count_nonzero(bad_columns)) * image1.shape[0],
                        defects=int(defects.size), total=int(np.count_nonzero(mask)),
                        npix=int(mask.size))
    log.info("%s", report)
    return mask, report
