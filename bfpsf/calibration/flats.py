"""Flat-field ingest, pairing by exposure time, and pixel masks (G15 section 4.2).

Flats enter the calibration as pairs of equal exposure time: the difference of the two images
removes the fixed pattern (pixel response, illumination), leaving the shot noise whose
covariances measure the brighter-fatter effect (G15 section 4.2.1). Before the covariances are
computed, pixels that would add spurious correlations are masked (G15 section 4.2.3): non-finite
and saturated pixels, hot or dark columns, and clusters of defect pixels.

Images are ``data[y, x]`` in ADU, bias-subtracted (DESIGN.md conventions).
"""

import logging
import os
from dataclasses import dataclass, replace

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError

__all__ = ["Flat", "FlatPair", "MaskReport", "read_flats", "group_amplifiers", "pair_flats",
           "check_pair", "pair_mask"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Flat:
    """One flat-field image (one amplifier of one exposure).

    Attributes
    ----------
    data : ndarray, shape (ny, nx), or None
        Pixel values in ADU, bias- (overscan-) subtracted and trimmed, indexed ``[y, x]``
        (float64); None for a flat not read yet (``layout`` says where it is; `load`).
    exptime : float
        Exposure time in seconds (header EXPTIME).
    name : str
        Where the image came from (file name, ``file[AMP]`` for an amplifier of a
        multi-extension file, or ``'array[i]'``); used in error messages.
    header : dict-like or None
        The FITS header of the image HDU, or None for an array input or a flat not read yet.
    amplifier : str
        Amplifier name (EXTNAME), ``''`` for a single-image file or an array.
    layout : bfpsf.io.amplifiers.AmplifierLayout or None
        Where the pixels are in their file (None for an array input).
    """

    data: np.ndarray
    exptime: float
    name: str
    header: object = None
    amplifier: str = ""
    layout: object = None

    @property
    def shape(self):
        """Image shape (ny, nx)."""
        return self.data.shape if self.data is not None else tuple(self.layout.shape)

    def mean(self):
        """Mean of the finite pixels, ADU."""
        return float(np.mean(self.data[np.isfinite(self.data)])) if self.data.size else np.nan

    def load(self, *, overscan="median"):
        """This flat with its pixels read (itself if they are already in memory)."""
        if self.data is not None:
            return self
        from ..io.amplifiers import read_amplifier

        amplifier = read_amplifier(self.layout, overscan=overscan)
        return replace(self, data=amplifier.data, header=amplifier.header)


@dataclass(frozen=True, eq=False)
class FlatPair:
    """Two flats of equal exposure time, the unit of the covariance measurement.

    Attributes
    ----------
    flat1, flat2 : Flat
        The two images; their difference carries the shot noise (G15 section 4.2.1).
    """

    flat1: Flat
    flat2: Flat

    @property
    def exptime(self):
        """Exposure time of the pair, seconds."""
        return self.flat1.exptime

    @property
    def names(self):
        """Names of the two flats."""
        return (self.flat1.name, self.flat2.name)


@dataclass(frozen=True)
class MaskReport:
    """How many pixels of a pair each masking cause flagged.

    A pixel can be flagged by several causes, so the causes may add up to more than
    ``total``, the number of masked pixels.

    Attributes
    ----------
    nonfinite : int
        Pixels that are NaN or infinite in either flat.
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
                f"{self.nonfinite} non-finite, {self.saturated} saturated, "
                f"{self.columns} in hot/dark columns, {self.defects} in defect clusters")


# ---------------------------------------------------------------------------------------------
# Ingest


def _as_exptime(value, name):
    try:
        exptime = float(value)
    except (TypeError, ValueError):
        msg = f"{name}: EXPTIME must be a number of seconds, got {value!r}"
        raise BFPSFInputError(msg, value) from None
    if not np.isfinite(exptime) or exptime < 0:
        msg = f"{name}: EXPTIME must be finite and >= 0 seconds, got {value!r}"
        raise BFPSFInputError(msg, value)
    return exptime


def read_flats(sources, exptimes=None, *, amps=None, lazy=False, overscan="median"):
    """Read flat-field images (every amplifier of every file) from FITS files or arrays.

    Parameters
    ----------
    sources : str, path, ndarray, Flat, or a sequence of them
        FITS files (single-HDU bias-subtracted images, or one image HDU per amplifier with
        EXTNAME and optional BIASSEC / DATASEC / DETSEC: `bfpsf.io.amplifiers`; the HDU
        header, or the primary header, must have EXPTIME), 2-D arrays in ADU (then
        ``exptimes`` is required), or `Flat` objects (passed through).
    exptimes : sequence of float, optional
        Exposure times in seconds, one per source. Required for arrays; when given for files
        it overrides the header EXPTIME.
    amps : str or sequence of str, optional
        Amplifiers (EXTNAME) to read from every file. Default: all.
    lazy : bool, optional
        Read only the headers: the flats of files come back with ``data=None`` and are read
        by `Flat.load` (as a worker of `bfpsf.parallel` does). Default False.
    overscan : {'median', 'clipped_mean'}, optional
        Row-by-row overscan estimator where a BIASSEC is given. Default ``'median'``.

    Returns
    -------
    list of Flat
        One per amplifier of each file, in file order.

    Raises
    ------
    BFPSFInputError
        A file is missing or unreadable, holds HDUs bfpsf cannot interpret
        (`bfpsf.io.amplifiers.amplifier_layout`), has no EXPTIME, an array is not 2-D, or the
        number of ``exptimes`` does not match the number of sources.
    """
    from ..io.amplifiers import amplifier_layout

    if isinstance(sources, (str, os.PathLike, np.ndarray, Flat)):
        sources = [sources]
    sources = list(sources)
    if not sources:
        msg = "no flats given"
        raise BFPSFInputError(msg)
    if exptimes is not None:
        exptimes = list(np.atleast_1d(exptimes))
        if len(exptimes) != len(sources):
            msg = f"got {len(exptimes)} exptimes for {len(sources)} flats; give one per flat"
            raise BFPSFInputError(msg, len(exptimes))
    flats = []
    for index, source in enumerate(sources):
        override = None if exptimes is None else exptimes[index]
        if isinstance(source, Flat):
            if override is not None:
                source = replace(source, exptime=_as_exptime(override, source.name))
            flats.append(source if lazy else source.load(overscan=overscan))
        elif isinstance(source, (str, os.PathLike)):
            for layout in amplifier_layout(source, amps, what="flat file"):
                exptime = override if override is not None else layout.exptime
                if exptime is None:
                    msg = (f"{layout.label}: header keyword EXPTIME is missing (exposure time "
                           "in seconds)")
                    raise BFPSFInputError(msg, layout.label)
                flat = Flat(None, _as_exptime(exptime, layout.label), layout.label,
                            amplifier=layout.name, layout=layout)
                flats.append(flat if lazy else flat.load(overscan=overscan))
        else:
            name = f"array[{index}]"
            data = np.array(source, dtype=np.float64)
            if override is None:
                msg = (f"{name}: flats given as arrays need exptimes (seconds), "
                       "e.g. read_flats(arrays, exptimes=[...])")
                raise BFPSFInputError(msg, name)
            if data.ndim != 2:
                msg = f"{name}: a flat must be a 2-D image, got shape {data.shape}"
                raise BFPSFInputError(msg, data.shape)
            flats.append(Flat(data, _as_exptime(override, name), name))
    return flats


def group_amplifiers(flats):
    """The flats of each amplifier, ``{name: [Flat, ...]}`` in order of first appearance."""
    groups = {}
    for flat in flats:
        groups.setdefault(flat.amplifier, []).append(flat)
    return groups


# ---------------------------------------------------------------------------------------------
# Pairing


def pair_flats(flats, *, mean_tolerance=0.05):
    """Pair flats by equal exposure time.

    Flats of one amplifier and one EXPTIME are paired in the order given: (1st, 2nd),
    (3rd, 4th), ... The means are compared here for flats in memory, and by `check_pair`
    once they are read for flats read lazily.

    Parameters
    ----------
    flats : sequence of Flat, or anything `read_flats` accepts
        The flats to pair.
    mean_tolerance : float, optional
        Largest accepted relative difference of the two means, ``|m1 - m2| / ((m1 + m2) / 2)``.
        A larger difference means the illumination changed between the two exposures, which
        the pair difference does not cancel. Not applied at EXPTIME = 0. Default 0.05.

    Returns
    -------
    list of FlatPair
        Sorted by exposure time.

    Raises
    ------
    BFPSFInputError
        A flat has no partner at its EXPTIME (an odd number of flats there), the two flats of
        a pair differ in shape, or their means differ by more than ``mean_tolerance``.
    """
    flats = list(flats)
    if not all(isinstance(flat, Flat) for flat in flats):
        flats = read_flats(flats)
    if mean_tolerance <= 0:
        msg = f"mean_tolerance must be positive, got {mean_tolerance}"
        raise BFPSFValueError(msg, mean_tolerance)
    pairs = []
    for amplifier_flats in group_amplifiers(flats).values():
        pairs += _pair_by_exptime(amplifier_flats, mean_tolerance)
    return sorted(pairs, key=lambda pair: pair.exptime)


def _pair_by_exptime(flats, mean_tolerance):
    groups = {}
    for flat in flats:
        for exptime in groups:
            if np.isclose(flat.exptime, exptime, rtol=1e-9, atol=1e-12):
                groups[exptime].append(flat)
                break
        else:
            groups[flat.exptime] = [flat]
    pairs = []
    for exptime in sorted(groups):
        group = groups[exptime]
        if len(group) % 2:
            others = ", ".join(flat.name for flat in group[:-1])
            msg = (f"{group[-1].name} (EXPTIME={exptime:g} s) has no partner: flats are paired "
                   "by equal EXPTIME" + (f" and {others} already pair up" if others else ""))
            raise BFPSFInputError(msg, group[-1].name)
        for first, second in zip(group[0::2], group[1::2]):
            check_pair(first, second, mean_tolerance)
            pairs.append(FlatPair(first, second))
    return pairs


def check_pair(first, second, mean_tolerance):
    """Raise `BFPSFInputError` if two flats of one EXPTIME cannot be a pair: different shapes,
    or (once their pixels are read) means that differ by more than ``mean_tolerance``."""
    if first.shape != second.shape:
        msg = (f"flats {first.name} {first.shape} and {second.name} {second.shape} have the "
               "same EXPTIME but different shapes")
        raise BFPSFInputError(msg, (first.shape, second.shape))
    if first.exptime <= 0 or first.data is None or second.data is None:
        return
    mean1, mean2 = first.mean(), second.mean()
    mean = 0.5 * (mean1 + mean2)
    if not (np.isfinite(mean1) and np.isfinite(mean2)) or mean <= 0:
        msg = (f"flats {first.name} and {second.name} have non-positive or undefined means "
               f"({mean1:.6g}, {mean2:.6g} ADU) at EXPTIME={first.exptime:g} s")
        raise BFPSFInputError(msg, (mean1, mean2))
    difference = abs(mean1 - mean2) / mean
    if difference > mean_tolerance:
        msg = (f"flats {first.name} and {second.name} (EXPTIME={first.exptime:g} s) have means "
               f"{mean1:.6g} and {mean2:.6g} ADU, differing by {100 * difference:.3g} % > "
               f"mean_tolerance={100 * mean_tolerance:.3g} %: the illumination changed")
        raise BFPSFInputError(msg, difference)


# ---------------------------------------------------------------------------------------------
# Masks


def _robust_sigma(values):
    """Standard deviation from the median absolute deviation (Gaussian-consistent)."""
    values = values[np.isfinite(values)]
    if values.size == 0:
        return np.nan
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def _tile_rows(ny, box):
    """Row slices of the tile rows of an image with ``ny`` rows."""
    return [slice(y0, min(y0 + box, ny)) for y0 in range(0, ny, box)]


def _per_column(per_tile, box, nx):
    """Expand one row of per-tile values to one value per column."""
    return np.repeat(per_tile, box)[:nx].astype(np.float32)


def _tile_statistics(image, good, box):
    """Mean and sigma of the good pixels of each ``box x box`` tile, estimated twice (G15).

    First over all good pixels of the tile, then over the good pixels within 2 sigma of that
    first mean (G15 section 4.2.3, footnote). Works one row of tiles at a time, so the
    temporaries stay small.

    Returns
    -------
    mean, sigma : ndarray, shape (ntiles_y, ntiles_x)
        NaN in a tile with fewer than two good pixels.
    """
    ny, nx = image.shape
    starts = np.arange(0, nx, box)
    rows = _tile_rows(ny, box)
    mean = np.full((len(rows), starts.size), np.nan)
    sigma = np.full((len(rows), starts.size), np.nan)
    for row, band in enumerate(rows):
        values = image[band]
        kept = good[band].copy()
        for iteration in range(2):
            if iteration:
                centre = _per_column(tile_mean, box, nx)
                width = _per_column(2.0 * tile_sigma, box, nx)
                with np.errstate(invalid="ignore"):
                    kept &= np.abs(values - centre) <= width
            masked = np.where(kept, values, np.float32(0.0))
            count = np.add.reduceat(np.count_nonzero(kept, axis=0), starts)
            total = np.add.reduceat(masked.sum(axis=0, dtype=np.float64), starts)
            square = np.add.reduceat(np.einsum("ij,ij->j", masked, masked, dtype=np.float64),
                                     starts)
            with np.errstate(invalid="ignore", divide="ignore"):
                tile_mean = total / count
                tile_sigma = np.sqrt(np.maximum(square / count - tile_mean**2, 0.0))
            unusable = count < 2
            tile_mean[unusable] = tile_sigma[unusable] = np.nan
        mean[row], sigma[row] = tile_mean, tile_sigma
    return mean, sigma


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


def _scan(image, good, mean, sigma, box, defect_nsigma, column_clip=5.0):
    """One pass over the tile rows of an image for the column and defect tests.

    Returns
    -------
    levels : ndarray, shape (nx,)
        Mean of the good pixels of each column within ``column_clip`` local sigma of the local
        mean (so a single defect does not move it); NaN for a column without such pixels.
    high : ndarray of bool, shape (ny, nx)
        Good pixels more than ``defect_nsigma`` local sigma above the local mean.
    """
    ny, nx = image.shape
    sums = np.zeros(nx)
    counts = np.zeros(nx, dtype=np.int64)
    high = np.zeros((ny, nx), dtype=bool)
    for row, band in enumerate(_tile_rows(ny, box)):
        values = image[band]
        centre = _per_column(mean[row], box, nx)
        width = _per_column(sigma[row], box, nx)
        deviation = values - centre
        with np.errstate(invalid="ignore"):
            kept = good[band] & (np.abs(deviation) <= column_clip * width)
            high[band] = good[band] & (deviation > defect_nsigma * width)
        sums += np.where(kept, values, np.float32(0.0)).sum(axis=0, dtype=np.float64)
        counts += np.count_nonzero(kept, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        levels = np.where(counts > 0, sums / counts, np.nan)
    return levels, high


def _bad_columns(levels, nsigma, window=31):
    """Columns whose level departs from their neighbours' by more than ``nsigma`` sigma.

    Each column level is compared with the median of the ``window - 1`` neighbouring columns
    (so a smooth illumination gradient is not flagged); sigma is the robust scatter of those
    residuals over all columns.
    """
    usable = np.isfinite(levels)
    if np.count_nonzero(usable) < 3:
        return np.zeros(levels.size, dtype=bool)
    reference = np.where(usable, levels, np.nanmedian(levels))
    residual = levels - _neighbour_median(reference, window)
    sigma = _robust_sigma(residual)
    if not np.isfinite(sigma) or sigma == 0:
        return np.zeros(levels.size, dtype=bool)
    with np.errstate(invalid="ignore"):
        return usable & (np.abs(residual) > nsigma * sigma)


def _clustered(high):
    """G15 section 4.2.3: the high pixels with more than two high pixels among their eight
    neighbours (high pixels are few, so their neighbours are looked up directly)."""
    ny, nx = high.shape
    y, x = np.divmod(np.flatnonzero(high), nx)
    neighbours = np.zeros(y.size, dtype=np.int8)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                yy, xx = y + dy, x + dx
                inside = (yy >= 0) & (yy < ny) & (xx >= 0) & (xx < nx)
                neighbours[inside] += high[yy[inside], xx[inside]]
    clustered = np.zeros((ny, nx), dtype=bool)
    clustered[y[neighbours > 2], x[neighbours > 2]] = True
    return clustered


def pair_mask(flat1, flat2, *, saturation=None, column_nsigma=5.0, defect_nsigma=3.0,
              defect_box=128):
    """Mask of the pixels of a flat pair that must not enter the covariances.

    Causes, in order (each is evaluated on the pixels not already masked):

    1. non-finite pixels (NaN or inf) in either image: masked and counted, never an error;
    2. pixels at or above ``saturation`` (ADU) in either image;
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
    image1 = flat1.data if isinstance(flat1, Flat) else np.asarray(flat1, dtype=np.float64)
    image2 = flat2.data if isinstance(flat2, Flat) else np.asarray(flat2, dtype=np.float64)
    if image1.ndim != 2 or image1.shape != image2.shape:
        msg = f"flats of a pair must be 2-D images of one shape, got {image1.shape} and {image2.shape}"
        raise BFPSFInputError(msg, (image1.shape, image2.shape))
    if defect_box < 3:
        msg = f"defect_box must be at least 3 pixels, got {defect_box}"
        raise BFPSFValueError(msg, defect_box)

    if np.isfinite(image1.sum()) and np.isfinite(image2.sum()):
        nonfinite = np.zeros(image1.shape, dtype=bool)
    else:
        nonfinite = ~(np.isfinite(image1) & np.isfinite(image2))
    mask = nonfinite.copy()
    if nonfinite.any():
        log.info("masked %d non-finite pixels", np.count_nonzero(nonfinite))

    saturated = np.zeros_like(mask)
    if saturation is not None:
        with np.errstate(invalid="ignore"):
            saturated = (image1 >= saturation) | (image2 >= saturation)
        mask |= saturated

    good = ~mask
    if not good.any():
        msg = "every pixel of the pair is non-finite or saturated"
        raise BFPSFInputError(msg)
    image1 = image1.astype(np.float32)  # thresholds only: single precision is plenty
    image2 = image2.astype(np.float32)
    mean1 = image1.sum(dtype=np.float64, where=good) / np.count_nonzero(good)
    mean2 = image2.sum(dtype=np.float64, where=good) / np.count_nonzero(good)
    flat_pair = min(mean1, mean2) > 0 and max(mean1, mean2) < 1.5 * min(mean1, mean2)
    scale = mean1 / mean2 if flat_pair else 1.0  # bias-like pairs: the plain difference
    with np.errstate(invalid="ignore"):
        difference = image2 * np.float32(-scale)
        difference += image1

    box = int(defect_box)
    bad_columns = np.zeros(image1.shape[1], dtype=bool)
    high = []
    for image in (image1, image2, difference):
        mean, sigma = _tile_statistics(image, good, box)
        levels, image_high = _scan(image, good, mean, sigma, box, defect_nsigma)
        bad_columns |= _bad_columns(levels, column_nsigma)
        high.append(image_high)
    columns = np.zeros_like(mask)
    columns[:, bad_columns] = True
    if bad_columns.any():
        log.info("masked %d hot/dark columns: %s", np.count_nonzero(bad_columns),
                 np.flatnonzero(bad_columns).tolist())
    mask |= columns
    # the defect test runs on the pixels that the column test left
    defects = np.zeros_like(mask)
    for image_high in high:
        image_high[:, bad_columns] = False
        defects |= _clustered(image_high)
    mask |= defects

    report = MaskReport(nonfinite=int(nonfinite.sum()), saturated=int(saturated.sum()),
                        columns=int(columns.sum()), defects=int(defects.sum()),
                        total=int(mask.sum()), npix=int(mask.size))
    log.info("%s", report)
    return mask, report
