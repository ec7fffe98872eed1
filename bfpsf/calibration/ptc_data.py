"""The PTC's inputs: per-pair means and covariances stacked, and their shot-noise errors.

Covariances are single-image covariances in ADU^2 indexed [dy, dx] (quadrant averaged), as
`bfpsf.calibration.covariance.pair_covariance` returns them.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFInputError

__all__ = ["PTCData", "stack_pairs", "covariance_errors"]


@dataclass(frozen=True)
class PTCData:
    """Per-pair PTC inputs stacked along the first axis.

    Attributes
    ----------
    exptime : ndarray (n,)
        Exposure time, s.
    mean_adu : ndarray (n,)
        Mean signal of the pair, ADU.
    cov_adu : ndarray (n, L, L)
        Single-image covariances C(dx, dy), ADU^2, indexed [pair, dy, dx]; [:, 0, 0] is the
        variance.
    npix : ndarray (n, L, L)
        Number of pixel products behind each covariance.
    """

    exptime: np.ndarray
    mean_adu: np.ndarray
    cov_adu: np.ndarray
    npix: np.ndarray

    @property
    def var_adu(self):
        """Single-image variance, ADU^2."""
        return self.cov_adu[:, 0, 0]

    @property
    def maxlag(self):
        return self.cov_adu.shape[1] - 1

    def to_maxlag(self, maxlag):
        """Return a copy with the lags 0..``maxlag`` only."""
        keep = slice(0, int(maxlag) + 1)
        return PTCData(self.exptime, self.mean_adu, self.cov_adu[:, keep, keep],
                       self.npix[:, keep, keep])

    def with_covariances(self, cov_adu):
        """Return a copy with ``cov_adu`` replaced (e.g. after pedestal subtraction)."""
        return PTCData(self.exptime, self.mean_adu, np.asarray(cov_adu, dtype=float), self.npix)


def stack_pairs(pairs):
    """Stack a sequence of `~bfpsf.calibration.covariance.PairCovariance` into `PTCData`.

    Parameters
    ----------
    pairs : sequence of PairCovariance
        Each with ``exptime`` (s), ``mean_adu``, ``cov_adu`` [dy, dx] and ``npix`` [dy, dx].

    Returns
    -------
    PTCData
    """
    pairs = list(pairs)
    if not pairs:
        msg = "no flat pairs to fit: the PTC needs at least 3 pairs at different levels"
        raise BFPSFInputError(msg, 0)
    shapes = {np.shape(pair.cov_adu) for pair in pairs}
    if len(shapes) != 1:
        msg = f"all pairs must have covariances to the same maxlag, got shapes {sorted(shapes)}"
        raise BFPSFInputError(msg, shapes)
    cov = np.array([np.asarray(pair.cov_adu, dtype=float) for pair in pairs])
    npix = np.array([np.broadcast_to(np.asarray(pair.npix, dtype=float), cov.shape[1:])
                     for pair in pairs])
    exptime = np.array([np.nan if pair.exptime is None else float(pair.exptime)
                        for pair in pairs])
    mean = np.array([float(pair.mean_adu) for pair in pairs])
    return PTCData(exptime, mean, cov, npix)


def covariance_errors(cov_adu, npix, variance=None):
    """Shot-noise standard error of measured single-image covariances, ADU^2.

    For a pair difference D = I1 - I2 with Var(D) = 2V, the mean of D(p) D(p + l) over N pixel
    products has variance (2V)^2 / N at a non-zero lag and 2 (2V)^2 / N at lag 0; halving gives
    the single-image errors V sqrt(1/N) and V sqrt(2/N) (N counts the products of both quadrants
    that were averaged).

    Parameters
    ----------
    cov_adu : ndarray (..., L, L)
        Covariances, [..., 0, 0] the variance V.
    npix : ndarray (..., L, L)
        Pixel products per lag.
    variance : array_like (...), optional
        The variance V to use (ADU^2), e.g. a fitted model. Default: the measured
        ``cov_adu[..., 0, 0]``. Fits should pass a model: weights from the measured variance
        favour pairs that fluctuated low and bias the gain and a(0, 0) (by ~0.4 sigma on a
        54-pair PTC).

    Returns
    -------
    ndarray (..., L, L)
    """
    cov_adu = np.asarray(cov_adu, dtype=float)
    factor = np.ones(cov_adu.shape[-2:])
    factor[0, 0] = 2.0
    if variance is None:
        variance = cov_adu[..., 0, 0]
    variance = np.abs(np.asarray(variance, dtype=float))[..., None, None]
    return variance * np.sqrt(factor / np.maximum(npix, 1.0))


# ---------------------------------------------------------------------------------------------
# turnoff
