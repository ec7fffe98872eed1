"""The difference of a flat pair, its sigma clipping, and the variance a clipped Gaussian keeps.

The difference image of a pair (`difference_kernel`, with its sums) is clipped at ``nsigma`` of its own scatter, iterated to a
self-consistent threshold (numba kernels over the image, no temporary of its size); the
variance of a unit Gaussian truncated at the threshold (`clip_variance_factor`) restores the
variance the clipping removed (`bfpsf.calibration.covariance.pair_covariance`).
"""

import logging

import numba
import numpy as np
from scipy.stats import median_abs_deviation
from scipy.special import erf

from .kernels import FASTMATH, flag_row, flagged_positions

__all__ = ["clip_variance_factor", "sigma_clip", "self_consistent_threshold",
           "difference_kernel"]

log = logging.getLogger(__name__)


def clip_variance_factor(threshold):
    """Variance fraction of a unit Gaussian truncated at +-``threshold``.

    ``v(t) = 1 - 2 t phi(t) / (2 Phi(t) - 1)``; cp_pipe's ``sigmaClipCorrection`` returns
    ``1 / sqrt(v)``.
    """
    t = float(threshold)
    if not np.isfinite(t):
        return 1.0
    inside = erf(t / np.sqrt(2.0))
    density = np.exp(-0.5 * t * t) / np.sqrt(2.0 * np.pi)
    return 1.0 - 2.0 * t * density / inside


def self_consistent_threshold(nsigma):
    """Clipping threshold in units of the true sigma when the cut is ``nsigma`` times the
    sigma of the kept (truncated) values, as iterative clipping converges to:
    t = nsigma * sqrt(v(t))."""
    t = float(nsigma)
    for _ in range(100):
        new = nsigma * np.sqrt(clip_variance_factor(t))
        if abs(new - t) < 1e-13:
            break
        t = new
    return t


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def difference_kernel(image1, image2, factor1, factor2, out):
    """``out[:] = factor1 * image1 - factor2 * image2`` (computed in double precision, stored
    in ``out``'s precision); returns the sum and the sum of squares of the stored values."""
    ny, nx = image1.shape
    total = 0.0
    total2 = 0.0
    for i in range(ny):
        row1, row2, row = image1[i], image2[i], out[i]
        row_sum = 0.0
        row_sum2 = 0.0
        for j in range(nx):
            row[j] = factor1 * row1[j] - factor2 * row2[j]
            value = row[j]  # as stored
            row_sum += value
            row_sum2 += value * value
        total += row_sum
        total2 += row_sum2
    return total, total2


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def _beyond_kernel(image, cut, out):
    """Writes the flat indices (row-major over ``image``) of the values with |value| > cut to
    ``out``; returns their number (a vectorised flag row per image row, `flagged_positions`)."""
    ny, nx = image.shape
    flags = flag_row(nx)
    positions = np.empty(nx, dtype=np.int64)
    count = 0
    for i in range(ny):
        row = image[i]
        for j in range(nx):
            flags[j] = abs(row[j]) > cut
        for k in range(flagged_positions(flags, nx, positions)):
            out[count] = i * nx + positions[k]
            count += 1
    return count


def _beyond(image, cut):
    """Flat indices (over ``image``, row-major) of the values with ``|value| > cut``."""
    out = np.empty(image.size, dtype=np.int64)
    return out[:_beyond_kernel(image, image.dtype.type(cut), out)].copy()


def sigma_clip(image, nsigma, count, total, total2, max_iterations=50):
    """Iterative sigma clipping of the good pixels of a zero-mean, zero-filled image.

    ``image`` (2-D, single or double precision, possibly a view into a larger buffer; sums
    in double) holds ``count`` good pixels and zeros at the bad ones, whose sum and sum of
    squares are ``total`` and ``total2``; since the good pixels average to zero, the fill
    values always lie inside the cut. Pixels more than ``nsigma`` times the sigma of the kept
    pixels from their mean are clipped, iterated to convergence. The running sums are
    updated from a pre-selected tail of candidate outliers, so an iteration costs only the
    tail, not the whole image.

    Returns the flat (row-major over ``image``) indices of the clipped pixels.
    """
    sigma = np.sqrt(max(total2 / count - (total / count) ** 2, 0.0))
    step = max(1, int(np.sqrt(image.size / 100_000)))
    sample = image[::step, ::step].ravel()
    robust = median_abs_deviation(sample, scale="normal")
    tail_cut = 0.8 * nsigma * (robust if robust > 0 else sigma)
    if not tail_cut > 0:
        return np.empty(0, dtype=np.intp)  # a constant image: nothing to clip
    flat_values = image.ravel() if image.flags.c_contiguous else None
    for _ in range(40):  # each restart widens the candidate tail by 1 / 0.7
        tail_index = _beyond(image, tail_cut)
        if flat_values is not None:
            tail = flat_values[tail_index].astype(np.float64)
        else:
            tail = image[np.divmod(tail_index, image.shape[1])].astype(np.float64)
        centre = total / count
        sigma = np.sqrt(max(total2 / count - centre * centre, 0.0))
        kept = np.ones(tail.size, dtype=bool)
        for _ in range(max_iterations):
            cut = nsigma * sigma
            if centre - cut > -tail_cut or centre + cut < tail_cut:
                break  # the cut reaches inside the candidate tail: widen it and restart
            new_kept = np.abs(tail - centre) <= cut
            removed = tail[~new_kept]
            kept_count = count - removed.size
            centre = (total - removed.sum()) / kept_count
            sigma = np.sqrt(max((total2 - np.dot(removed, removed)) / kept_count
                                - centre * centre, 0.0))
            converged = np.array_equal(new_kept, kept)
            kept = new_kept
            if converged:
                return tail_index[~kept]
        else:
            log.warning("sigma clipping did not converge in %d iterations", max_iterations)
            return tail_index[~kept]
        tail_cut *= 0.7
    log.warning("sigma clipping stopped: the distribution of the difference is degenerate")
    return tail_index[~kept]
