"""Covariances of flat-pair differences (G15 section 4.2; Astier et al. 2019 appendix A).

The difference of two flats of equal exposure removes the fixed pattern and keeps twice the
shot noise; its covariances at small lags, divided by two, are the single-image covariances
C(dx, dy) = Cov(Q[y, x], Q[y + dy, x + dx]) (DESIGN.md) that the PTC fit turns into area
coefficients (G15 eq. covar: C(dx, dy) / (V mu) = a(dx, dy) to first order).

The estimator is the one of cp_pipe (Astier et al. 2019, appendix A): for each lag k, over the
pixel pairs (n, n + k) where both pixels are good,

    C(k) = [sum d(n) d(n + k) - sum d(n) * sum d(n + k) / N(k)] / N(k),

the sums taken by FFT. Because only lags up to ``maxlag`` are wanted, the inverse transform is
evaluated at those lags only (a small matrix product) and, when few pixels are masked, the pair
counts N(k) and the partial sums are computed directly from the masked-pixel list, so one
forward FFT of the masked difference suffices.
"""

import logging

import numpy as np
from scipy import fft
from scipy.fft import next_fast_len

from ..errors import BFPSFInputError, BFPSFValueError, integer_at_least
from .flats import Flat, FlatPair
from .pair_covariance_result import PairCovariance
from .pair_difference import (clip_variance_factor, difference_kernel, self_consistent_threshold,
                              sigma_clip)

__all__ = ["PairCovariance", "pair_covariance", "covariance_map", "fold_quadrants",
           "clip_variance_factor"]

log = logging.getLogger(__name__)

_PRECISIONS = {"single": np.float32, "double": np.float64}


# ---------------------------------------------------------------------------------------------
# The FFT kernel


def _fast_length(n):
    return next_fast_len(int(n), real=True)


def _partial_inverse(spectrum, lags_y, lags_x, shape):
    """Inverse real 2-D DFT of a half spectrum (``rfft2`` layout) at the given lags only.

    Returns ``irfft2(spectrum, shape)[lags_y][:, lags_x]`` (negative lags wrapping) by two
    matrix products, for spectra of real signals.
    """
    ly, lx = shape
    nfx = spectrum.shape[1]
    real_dtype = np.float32 if spectrum.dtype in (np.float32, np.complex64) else np.float64
    weight = np.full(nfx, 2.0)
    weight[0] = 1.0
    if lx % 2 == 0:
        weight[-1] = 1.0
    phase_y = 2.0 * np.pi * np.outer(lags_y, np.arange(ly)) / ly
    phase_x = 2.0 * np.pi * np.outer(np.arange(nfx), lags_x) / lx
    along_x = (weight[:, None] * np.exp(1j * phase_x)).astype(np.complex128)
    if np.isrealobj(spectrum):
        basis = np.concatenate([np.cos(phase_y), np.sin(phase_y)]).astype(real_dtype)
        rows = basis @ spectrum
        half = len(lags_y)
        along_y = rows[:half].astype(np.float64) + 1j * rows[half:].astype(np.float64)
    else:
        basis = np.exp(1j * phase_y).astype(spectrum.dtype)
        along_y = (basis @ spectrum).astype(np.complex128)
    return (along_y @ along_x).real / (ly * lx)


def _compress(image, maxlag):
    """Sum an image into the (2m + 1) x (2m + 1) blocks that the overlap rectangles of lags
    up to m are made of: the first m and last m rows (and columns) singly, the rest as one."""
    m = maxlag
    ny, nx = image.shape

    columns = np.concatenate([image[:, :m],
                              image[:, m:nx - m].sum(axis=1, keepdims=True, dtype=np.float64),
                              image[:, nx - m:]], axis=1)
    return np.concatenate([columns[:m], columns[m:ny - m].sum(axis=0, keepdims=True),
                           columns[ny - m:]], axis=0)


def _compress_points(y, x, weights, shape, maxlag):
    """`_compress` of a sparse image given as points (y, x) with ``weights``."""
    m = maxlag
    ny, nx = shape
    by = np.where(y < m, y, np.where(y >= ny - m, y - ny + 2 * m + 1, m))
    bx = np.where(x < m, x, np.where(x >= nx - m, x - nx + 2 * m + 1, m))
    size = 2 * m + 1
    return np.bincount(by * size + bx, weights=weights, minlength=size * size).reshape(size, size)


def _rectangle_sums(compressed, maxlag):
    """Sums over every rectangle that drops 0..m rows at the top and at the bottom and 0..m
    columns at the left and at the right, from a `_compress`-ed image.

    Returns an array indexed ``[top, bottom, left, right]``.
    """
    m = maxlag
    zero = np.zeros((compressed.shape[0], 1))
    left = np.hstack([zero, np.cumsum(compressed[:, :m], axis=1)])
    right = np.hstack([zero, np.cumsum(compressed[:, ::-1][:, :m], axis=1)])
    rows = compressed.sum(axis=1)[:, None, None] - left[:, :, None] - right[:, None, :]
    zero_row = np.zeros((1, m + 1, m + 1))
    top = np.concatenate([zero_row, np.cumsum(rows[:m], axis=0)])
    bottom = np.concatenate([zero_row, np.cumsum(rows[::-1][:m], axis=0)])
    return rows.sum(axis=0)[None, None] - top[:, None] - bottom[None, :]


def _pair_sums(values, bad_index, maxlag, spectrum=None, shape=None):
    """Pair counts N(k) and partial sums near(k) = sum over good pairs (n, n + k) of
    values(n), for k in -maxlag..maxlag; ``values`` is zero at the bad pixels.

    With b the bad pixels and O_k the overlap (pixels n with n and n + k inside the image),
    N(k) = |O_k| - #bad in O_k - #bad in O_k + k + #(b, b + k both bad) and
    near(k) = sum over O_k of values - sum_b values(b - k). The rectangle sums are exact; the
    two sums over bad pixels are taken from the list of bad pixels (cost proportional to
    their number) or, when ``spectrum`` (the rfft2 of ``values`` zero-padded to ``shape``) is
    given, by FFT of the bad-pixel image.

    Returns (count, near) indexed ``[ky + m, kx + m]``.
    """
    m = maxlag
    ny, nx = values.shape
    lags = np.arange(-m, m + 1)
    bad_y, bad_x = np.divmod(bad_index, nx)
    value_sums = _rectangle_sums(_compress(values, m), m)
    bad_sums = _rectangle_sums(_compress_points(bad_y, bad_x, None, values.shape, m), m)
    if spectrum is None:
        both_bad, partner_values = _bad_pair_sums_direct(values, bad_y, bad_x, lags)
    else:
        both_bad, partner_values = _bad_pair_sums_fft(spectrum, bad_index, values.shape,
                                                      shape, lags)
    count = np.empty((2 * m + 1, 2 * m + 1))
    near = np.empty((2 * m + 1, 2 * m + 1))
    for ky in lags:
        for kx in lags:
            region = (max(0, -ky), max(0, ky), max(0, -kx), max(0, kx))          # O_k
            shifted_region = (max(0, ky), max(0, -ky), max(0, kx), max(0, -kx))  # O_k + k
            npairs = (ny - abs(ky)) * (nx - abs(kx))
            count[ky + m, kx + m] = (npairs - bad_sums[region] - bad_sums[shifted_region]
                                     + both_bad[ky + m, kx + m])
            near[ky + m, kx + m] = value_sums[region] - partner_values[ky + m, kx + m]
    return count, near


def _bad_pair_sums_direct(values, bad_y, bad_x, lags):
    """#(b, b - k both bad) and sum_b values(b - k) over the bad pixels b, from their list."""
    ny, nx = values.shape
    is_bad = np.zeros(values.size, dtype=bool)
    is_bad[bad_y * nx + bad_x] = True
    partner_x = bad_x[:, None] - lags[None, :]  # [bad, kx]
    column_inside = (partner_x >= 0) & (partner_x < nx)
    both_bad = np.empty((lags.size, lags.size))
    partner_values = np.empty((lags.size, lags.size))
    for row, ky in enumerate(lags):
        partner_y = bad_y - ky
        inside = column_inside & ((partner_y >= 0) & (partner_y < ny))[:, None]
        partner = np.where(inside, partner_y[:, None] * nx + partner_x, 0)
        both_bad[row] = np.count_nonzero(is_bad[partner] & inside, axis=0)
        partner_values[row] = np.where(inside, values[np.divmod(partner, nx)], 0.0).sum(axis=0)
    return both_bad, partner_values


def _bad_pair_sums_fft(spectrum, bad_index, image_shape, shape, lags):
    """As `_bad_pair_sums_direct`, by FFT of the bad-pixel image: many bad pixels."""
    # Counts up to n_bad must round exactly: single precision does below ~2e5 bad pixels.
    single = spectrum.dtype == np.complex64 and bad_index.size < 200_000
    dtype = np.float32 if single else np.float64
    bad = np.zeros(shape, dtype=dtype)
    bad[:image_shape[0], :image_shape[1]].flat[bad_index] = 1.0
    bad_spectrum = fft.rfft2(bad, workers=1)
    del bad
    bad_power = bad_spectrum.real * bad_spectrum.real + bad_spectrum.imag * bad_spectrum.imag
    both_bad = np.rint(_partial_inverse(bad_power, lags, lags, shape))
    del bad_power
    # sum_b values(b - k) = sum_n values(n) bad(n + k)
    cross = spectrum.conj()
    cross *= bad_spectrum.astype(spectrum.dtype, copy=False)
    partner_values = _partial_inverse(cross, lags, lags, shape)
    return both_bad, partner_values


def covariance_map(diff, weights, maxlag, *, precision="single", sparse=None):
    """Covariances of a masked image at lags -maxlag..maxlag, by FFT.

    For each lag k = (dx, dy), over the pixel pairs (n, n + k) with both pixels good,

        C(k) = [sum d(n) d(n + k) - sum d(n) sum d(n + k) / N(k)] / N(k)

    (Astier et al. 2019 appendix A, as in cp_pipe), with the convention of DESIGN.md:
    C(dx, dy) = Cov(d[y, x], d[y + dy, x + dx]).

    Parameters
    ----------
    diff : ndarray, shape (ny, nx)
        The image (a flat-pair difference), any unit; values at bad pixels are ignored.
    weights : ndarray of bool, shape (ny, nx)
        True (or 1) for a good pixel.
    maxlag : int
        Largest |dx| and |dy|.
    precision : {'single', 'double'}, optional
        Floating-point precision of the FFT of the image. The image is centred first, so in
        single precision the rounding error on C is a few 1e-8 of the variance, far below
        the statistical error of any image that fits in memory (1/sqrt(N) of the variance,
        2.4e-4 for 4k x 4k); 'double' is exact to about 1e-14 of the variance and 30 % slower.
        Pair counts are exact either way. Default 'single'.
    sparse : bool, optional
        Compute the pair counts and partial sums from the list of bad pixels rather than by
        one more FFT (of the bad-pixel image). Default: when that is cheaper (few bad
        pixels).

    Returns
    -------
    cov : ndarray, shape (2 maxlag + 1, 2 maxlag + 1)
        C(dx, dy) indexed ``[dy + maxlag, dx + maxlag]``; C(-k) = C(k). NaN where no pair.
    npix : ndarray of int, same shape
        Number of good pixel pairs N(k).
    """
    diff = np.asarray(diff, dtype=np.float64)
    good = np.asarray(weights).astype(bool)
    maxlag = _validate_maxlag(maxlag, diff.shape)
    if good.shape != diff.shape:
        msg = f"weights shape {good.shape} differs from the image shape {diff.shape}"
        raise BFPSFInputError(msg, good.shape)
    bad_index = np.flatnonzero(~good)
    ngood = diff.size - bad_index.size
    if ngood < 2:
        msg = f"only {ngood} good pixels: cannot compute covariances"
        raise BFPSFInputError(msg, ngood)
    padded, centred = _fft_buffer(diff.shape, maxlag, precision)
    values = np.where(good, diff, 0.0)
    # C(k) is invariant under an offset: centring (in double precision) improves precision
    centred[...] = np.where(good, values - values.sum() / ngood, 0.0)
    return _masked_covariances(padded, diff.shape, bad_index, maxlag, sparse)


def _fft_buffer(image_shape, maxlag, precision):
    """A zeroed array of the padded FFT shape for lags up to ``maxlag`` and its
    ``image_shape`` corner (a view), where the image is written."""
    if precision not in _PRECISIONS:
        msg = f"precision must be 'single' or 'double', got {precision!r}"
        raise BFPSFValueError(msg, precision)
    ny, nx = image_shape
    padded = np.zeros((_fast_length(ny + maxlag), _fast_length(nx + maxlag)),
                      dtype=_PRECISIONS[precision])
    return padded, padded[:ny, :nx]


def _masked_covariances(padded, image_shape, bad_index, maxlag, sparse=None):
    """`covariance_map` of an image written in the corner of ``padded`` (`_fft_buffer`), zero
    at the bad pixels (flat ``bad_index``) and close to zero mean over the good ones."""
    real_dtype = padded.dtype.type
    m = maxlag
    ny, nx = image_shape
    centred = padded[:ny, :nx]
    if sparse is None:
        sparse = bad_index.size * (2 * m + 1) ** 2 <= 2 * centred.size
    shape = padded.shape
    lags = np.arange(-m, m + 1)
    half = np.arange(0, m + 1)  # C(-k) = C(k): the upper half-plane is enough for auto terms

    spectrum = fft.rfft2(padded, workers=1)
    if sparse:
        npix, near = _pair_sums(centred, bad_index, m)
        # the spectrum is not needed again: square its parts in place
        parts = spectrum.view(real_dtype)
        np.square(parts, out=parts)
        power = parts[:, 0::2] + parts[:, 1::2]
        del spectrum, parts
    else:
        npix, near = _pair_sums(centred, bad_index, m, spectrum=spectrum, shape=shape)
        power = spectrum.real * spectrum.real + spectrum.imag * spectrum.imag
        del spectrum
    products_half = _partial_inverse(power, half, lags, shape)  # [dy, dx + m], dy = 0..m
    del power
    products = np.concatenate([products_half[:0:-1, ::-1], products_half])
    far = near[::-1, ::-1]  # sum of d(n + k) over the pairs = near(-k)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = (products - near * far / npix) / npix
    cov[npix == 0] = np.nan
    return cov, npix.astype(np.int64)


def fold_quadrants(cov_map, npix_map):
    """Combine C(dx, dy) and C(dx, -dy) into the quadrant table of G15.

    Parameters
    ----------
    cov_map, npix_map : ndarray, shape (2m + 1, 2m + 1)
        As returned by `covariance_map`.

    Returns
    -------
    cov : ndarray, shape (m + 1, m + 1)
        Indexed ``[dy, dx]``, dx, dy = 0..m; where dx > 0 and dy > 0 the pair-count weighted
        mean of C(dx, dy) and C(dx, -dy).
    npix : ndarray of int, shape (m + 1, m + 1)
        Pixel pairs behind each element (both quadrants summed where combined).
    """
    m = cov_map.shape[0] // 2
    upper = cov_map[m:, m:]
    lower = cov_map[m::-1, m:]  # [dy, dx] -> C(dx, -dy)
    n_upper = npix_map[m:, m:].astype(np.float64)
    n_lower = npix_map[m::-1, m:].astype(np.float64)
    both = np.ones((m + 1, m + 1), dtype=bool)
    both[0, :] = both[:, 0] = False
    with np.errstate(invalid="ignore", divide="ignore"):
        combined = (upper * n_upper + lower * n_lower) / (n_upper + n_lower)
    cov = np.where(both, combined, upper)
    npix = np.where(both, n_upper + n_lower, n_upper).astype(np.int64)
    return cov, npix


def _validate_maxlag(maxlag, shape):
    maxlag = integer_at_least("maxlag", maxlag, 0)
    if min(shape) <= 2 * maxlag:
        msg = f"maxlag={maxlag} is too large for an image of shape {shape}"
        raise BFPSFValueError(msg, maxlag)
    return maxlag


# ---------------------------------------------------------------------------------------------
# One pair


def _image_and_name(flat, default):
    # native-order double precision (a FITS image is big-endian: the compiled difference needs it)
    if isinstance(flat, Flat):
        return np.asarray(flat.data, dtype=np.float64), flat.name, flat.exptime
    return np.asarray(flat, dtype=np.float64), default, np.nan


def pair_covariance(flat1, flat2=None, *, mask=None, maxlag=8, clip_nsigma=4.0,
                    precision="single"):
    """Mean, variance and covariances of one flat pair (G15 section 4.2).

    The difference is taken symmetrically, as cp_pipe does,
    ``d = (mu2 * flat1 - mu1 * flat2) / mu`` with mu = (mu1 + mu2) / 2, so that a small
    difference of illumination cancels to second order (for a pair that is not a flat, means
    not both positive within a factor 1.5 of each other, e.g. bias frames, the plain
    difference ``flat1 - flat2`` is used); it is sigma-clipped (pixels more than
    ``clip_nsigma`` sigma from the mean, iterated to convergence), and its covariances are
    computed by `covariance_map` over the good, unclipped pixels. Clipping removes the tails
    of the distribution and so biases the variance low: the variance is divided by the
    truncated-Gaussian variance fraction v and the covariances by v**2 (the covariance of two
    small-correlation Gaussian variables both truncated scales as v**2), as cp_pipe does
    (``sigmaClipCorrection``); v is evaluated at the self-consistent threshold the iteration
    converges to (``clip_nsigma`` times the *clipped* sigma).

    Parameters
    ----------
    flat1 : Flat, ndarray or FlatPair
        First flat (ADU), or a pair (then ``flat2`` is omitted).
    flat2 : Flat or ndarray, optional
        Second flat of the same exposure time, ADU.
    mask : ndarray of bool, optional
        True for bad pixels (from `bfpsf.calibration.flat_mask.pair_mask`), applied to both flats.
        Non-finite pixels are always masked.
    maxlag : int, optional
        Largest lag. Default 8.
    clip_nsigma : float or None, optional
        Clipping threshold of the difference, sigma (at least 2); None for no clipping.
        Default 4.
    precision : {'single', 'double'}, optional
        Precision of the difference image and of its FFT, see `covariance_map` (the means and
        every sum are in double precision). Default 'single'.

    Returns
    -------
    PairCovariance
    """
    if isinstance(flat1, FlatPair):
        if flat2 is not None:
            msg = "give either a FlatPair or two flats, not both"
            raise BFPSFValueError(msg)
        flat1, flat2 = flat1.flat1, flat1.flat2
    if flat2 is None:
        msg = "pair_covariance needs two flats (or a FlatPair)"
        raise BFPSFValueError(msg)
    image1, name1, exptime = _image_and_name(flat1, "flat1")
    image2, name2, _ = _image_and_name(flat2, "flat2")
    if image1.ndim != 2 or image1.shape != image2.shape:
        msg = (f"flats {name1} and {name2} must be 2-D images of one shape, got "
               f"{image1.shape} and {image2.shape}")
        raise BFPSFInputError(msg, (image1.shape, image2.shape))
    maxlag = _validate_maxlag(maxlag, image1.shape)
    bad = None
    total1, total2 = image1.sum(), image2.sum()
    nonfinite = not (np.isfinite(total1) and np.isfinite(total2))
    if nonfinite:
        bad = ~(np.isfinite(image1) & np.isfinite(image2))
        log.info("flats %s, %s: %d non-finite pixels masked", name1, name2, np.count_nonzero(bad))
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != image1.shape:
            msg = f"mask shape {mask.shape} differs from the flats' shape {image1.shape}"
            raise BFPSFInputError(msg, mask.shape)
        bad = mask if bad is None else bad | mask
    bad_index = np.flatnonzero(bad) if bad is not None else np.empty(0, dtype=np.intp)
    n_masked = int(bad_index.size)
    ngood = image1.size - n_masked
    if ngood < 2:
        msg = f"flats {name1} and {name2}: fewer than two good pixels"
        raise BFPSFInputError(msg, ngood)
    if nonfinite:
        image1 = np.where(bad, 0.0, image1)
        image2 = np.where(bad, 0.0, image2)
        total1, total2 = image1.sum(), image2.sum()
    sum1 = total1 - image1.flat[bad_index].sum()
    sum2 = total2 - image2.flat[bad_index].sum()
    mean1, mean2 = sum1 / ngood, sum2 / ngood
    mean = 0.5 * (mean1 + mean2)
    # the difference goes straight into the FFT's zero-padded buffer, its sums on the way
    padded, diff = _fft_buffer(image1.shape, maxlag, precision)
    flat_pair = min(mean1, mean2) > 0 and max(mean1, mean2) < 1.5 * min(mean1, mean2)
    factors = (mean2 / mean, mean1 / mean) if flat_pair else (1.0, 1.0)
    total, total2 = difference_kernel(image1, image2, *factors, diff)
    if n_masked:
        at_bad = diff.flat[bad_index].astype(np.float64)
        total, total2 = total - at_bad.sum(), total2 - np.dot(at_bad, at_bad)
        diff.flat[bad_index] = 0.0
    if not flat_pair:
        # not a flat pair (e.g. bias frames, means ~ 0): the plain difference, centred
        offset = total / ngood
        diff -= diff.dtype.type(offset)
        diff.flat[bad_index] = 0.0
        total, total2 = 0.0, total2 - offset * offset * ngood
    # a flat pair's good pixels average to zero (up to rounding)

    n_clipped = 0
    clip_factor = 1.0
    if clip_nsigma is not None and np.isfinite(clip_nsigma):
        if clip_nsigma < 2:
            # below sqrt(3) iterative clipping collapses onto the centre
            msg = f"clip_nsigma must be at least 2 (or None for no clipping), got {clip_nsigma}"
            raise BFPSFValueError(msg, clip_nsigma)
        clipped_index = sigma_clip(diff, clip_nsigma, ngood, total, total2)
        n_clipped = int(clipped_index.size)
        if n_clipped:
            diff.flat[clipped_index] = 0.0
            # clipped pixels are never bad ones (those are zero, at the centre)
            bad_index = np.concatenate([bad_index, clipped_index])
        clip_factor = clip_variance_factor(self_consistent_threshold(clip_nsigma))
    else:
        clip_nsigma = np.inf

    cov_map, npix_map = _masked_covariances(padded, image1.shape, bad_index, maxlag)
    cov, npix = fold_quadrants(cov_map, npix_map)
    cov = cov / 2.0 / clip_factor**2
    cov[0, 0] *= clip_factor
    log.debug("pair %s, %s: mean %.6g ADU, var %.6g ADU^2, %d masked, %d clipped",
              name1, name2, mean, cov[0, 0], n_masked, n_clipped)
    return PairCovariance(exptime=float(exptime), mean_adu=float(mean), mean1_adu=float(mean1),
                          mean2_adu=float(mean2), var_adu=float(cov[0, 0]), cov_adu=cov,
                          npix=npix, n_masked=n_masked, n_clipped=n_clipped, maxlag=maxlag,
                          clip_nsigma=float(clip_nsigma), clip_factor=float(clip_factor),
                          names=(name1, name2))
