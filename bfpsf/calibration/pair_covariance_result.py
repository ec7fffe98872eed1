"""The covariances of one flat pair (`PairCovariance`): what `pair_covariance` returns."""

from dataclasses import dataclass

import numpy as np

__all__ = ["PairCovariance"]


@dataclass(frozen=True, eq=False)
class PairCovariance:
    """Mean, variance and covariances of one flat pair, single-image units (ADU).

    Attributes
    ----------
    exptime : float
        Exposure time, seconds (NaN when the flats were given as bare arrays).
    mean_adu : float
        Mean of the two masked flats, ``(mean1_adu + mean2_adu) / 2``, ADU.
    mean1_adu, mean2_adu : float
        Means of the good (unmasked) pixels of each flat, ADU.
    var_adu : float
        Single-image variance, var(difference) / 2, corrected for the sigma clipping, ADU^2.
        Equal to ``cov_adu[0, 0]``.
    cov_adu : ndarray, shape (maxlag + 1, maxlag + 1)
        Single-image covariances C(dx, dy), ADU^2, indexed ``[dy, dx]`` for dx, dy = 0..maxlag;
        (dx, dy) and (dx, -dy) combined (weighted by their pair counts) as G15 do; corrected for
        the sigma clipping.
    npix : ndarray of int, shape (maxlag + 1, maxlag + 1)
        Number of pixel pairs behind each element (both quadrants summed where combined).
    n_masked : int
        Pixels excluded by the mask (including non-finite pixels).
    n_clipped : int
        Further pixels excluded by the sigma clipping of the difference.
    maxlag : int
        Largest lag.
    clip_nsigma : float
        Clipping threshold, sigma (inf when no clipping).
    clip_factor : float
        The truncated-Gaussian variance fraction v the clipping left (1 without clipping):
        the measured variance was divided by v and the covariances by v**2.
    names : tuple of str
        Names of the two flats.
    """

    exptime: float
    mean_adu: float
    mean1_adu: float
    mean2_adu: float
    var_adu: float
    cov_adu: np.ndarray
    npix: np.ndarray
    n_masked: int
    n_clipped: int
    maxlag: int
    clip_nsigma: float = np.inf
    clip_factor: float = 1.0
    names: tuple = ()

    @property
    def corr(self):
        """Correlation coefficients R(dx, dy) = C(dx, dy) / V, indexed ``[dy, dx]``."""
        return self.cov_adu / self.var_adu

    @property
    def cov_err_adu(self):
        """Statistical error of ``cov_adu`` for Gaussian noise, ADU^2, indexed ``[dy, dx]``.

        V / sqrt(N) off the origin (G15 section 4.2.2: 1/sqrt(N) on a correlation) and
        V sqrt(2 / N) for the variance.
        """
        with np.errstate(divide="ignore"):
            err = self.var_adu / np.sqrt(self.npix)
        err[0, 0] *= np.sqrt(2.0)
        return err
