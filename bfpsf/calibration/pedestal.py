"""Readout pedestal: a pixel correlation that does not vanish at zero flux (G15 section 4.2.3).

The readout chain (an incomplete reset of the baseline, for instance) can correlate consecutive
pixels independently of the charge. It adds a covariance proportional to the variance, i.e. a
constant correlation R(dx, dy) = C(dx, dy) / V, whereas brighter-fatter correlations grow from
zero with the flux. G15 measured R(1, 0) ~ -0.003 on the LSST E2V-250 from the intercept of R
against flux and subtracted it from every measurement. `measure_pedestal` fits that intercept
for every lag; `subtract_pedestal` removes the significant ones (pedestal times V) from the
covariances before the PTC fit.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError

__all__ = ["Pedestal", "measure_pedestal", "subtract_pedestal"]


@dataclass(frozen=True)
class Pedestal:
    """Zero-flux correlations R0(dx, dy), dimensionless, indexed [dy, dx].

    Attributes
    ----------
    value, error : ndarray [dy, dx]
        Intercept of R(dx, dy) against the mean signal and its error ([0, 0] is 0).
    nsigma : float
        Detection threshold on |value / error|.
    degree : int
        Degree of the polynomial in flux fitted to R (2 absorbs the curvature of
        brighter-fatter correlations so that it does not leak into the intercept).
    """

    value: np.ndarray
    error: np.ndarray
    nsigma: float
    degree: int

    @property
    def significance(self):
        """value / error ([0, 0] is 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.error > 0, self.value / self.error, 0.0)

    @property
    def detected(self):
        """Lags whose pedestal is significant (|significance| > nsigma)."""
        return np.abs(self.significance) > self.nsigma

    @property
    def applied(self):
        """The correlation subtracted by `subtract_pedestal`: value where detected, else 0."""
        return np.where(self.detected, self.value, 0.0)

    @property
    def any_detected(self):
        return bool(self.detected.any())


def measure_pedestal(mean_adu, cov_adu, npix, *, nsigma=4.0, degree=2):
    """Intercept at zero flux of the correlations R(dx, dy) = C(dx, dy) / V (G15 fig. chip1a82).

    Parameters
    ----------
    mean_adu : array_like (n,)
        Mean signal of each pair, ADU (pairs below the PTC turnoff).
    cov_adu : array_like (n, L, L)
        Single-image covariances, ADU^2, indexed [pair, dy, dx].
    npix : array_like (n, L, L)
        Pixel products per lag (the error of R is 1 / sqrt(npix)).
    nsigma : float, optional
        Significance above which a pedestal counts as detected and is subtracted. Default 4:
        about 80 lags are tested at maxlag 8, and 4 sigma keeps the chance of a false detection
        in a calibration below 1 % (G15 quote > 3 sigma for their R(1, 0)).
    degree : int, optional
        Polynomial degree of R against flux. Default 2.

    Returns
    -------
    Pedestal
    """
    mean_adu = np.asarray(mean_adu, dtype=float)
    cov_adu = np.asarray(cov_adu, dtype=float)
    npix = np.broadcast_to(np.asarray(npix, dtype=float), cov_adu.shape)
    if degree < 1:
        msg = f"degree must be at least 1, got {degree}"
        raise BFPSFValueError(msg, degree)
    if np.unique(mean_adu).size < degree + 2:
        msg = (f"the pedestal fit of degree {degree} needs at least {degree + 2} flux levels, "
               f"got {np.unique(mean_adu).size}")
        raise BFPSFInputError(msg, mean_adu.size)
    correlation = cov_adu / cov_adu[:, :1, :1]
    corr_err = 1.0 / np.sqrt(np.maximum(npix, 1.0))
    # Scale the flux to order one for a well-conditioned design matrix.
    x = mean_adu / np.max(np.abs(mean_adu))
    design = np.vander(x, degree + 1, increasing=True)
    nlag = cov_adu.shape[1]
    value = np.zeros((nlag, nlag))
    error = np.zeros((nlag, nlag))
    for dy in range(nlag):
        for dx in range(nlag):
            if dx == dy == 0:
                continue
            weight = 1.0 / corr_err[:, dy, dx]
            weighted = design * weight[:, None]
            params, *_ = np.linalg.lstsq(weighted, correlation[:, dy, dx] * weight, rcond=None)
            covariance = np.linalg.inv(weighted.T @ weighted)
            value[dy, dx] = params[0]
            error[dy, dx] = np.sqrt(covariance[0, 0])
    value.flags.writeable = False
    error.flags.writeable = False
    return Pedestal(value=value, error=error, nsigma=float(nsigma), degree=int(degree))


def subtract_pedestal(cov_adu, pedestal):
    """Covariances minus the detected pedestal times the variance, ADU^2.

    Parameters
    ----------
    cov_adu : array_like (n, L, L)
    pedestal : Pedestal

    Returns
    -------
    ndarray (n, L, L)
        A new array; lags without a significant pedestal are unchanged.
    """
    cov_adu = np.array(cov_adu, dtype=float)
    return cov_adu - pedestal.applied[None, :, :] * cov_adu[:, :1, :1]
