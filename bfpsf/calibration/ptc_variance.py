"""Variance-only PTC models and first-order correlations (the ``'quadratic'`` and
``'exponential'`` models of `bfpsf.calibration.ptc`).

``'quadratic'``
    G15 section 4.3.2: V = -alpha N^2 + N / G + const (ADU), so a(0, 0) = -alpha; the other
    a(dx, dy) are the first-order slopes of R(dx, dy) = C(dx, dy) / V against mu in electrons
    (G15 eq. covar), `first_order_slopes`.
``'exponential'``
    Astier et al. 2019 (A+19) eq. 16: C00 = (exp(2 a00 g mu) - 1) / (2 g^2 a00) + n00 / g^2,
    mu in ADU, g in e-/ADU.
"""

import numpy as np
import scipy.optimize

from ..errors import BFPSFInputError
from ..least_squares import polynomial_fit

__all__ = ["fit_quadratic_ptc", "fit_exponential_ptc", "exponential_variance", "first_order_slopes",
           "parameter_covariance", "A_SCALE"]

# Parameter scale of a00 in the fits, so that the optimiser sees numbers of order one.
A_SCALE = 1e-6     # 1/e-


def fit_quadratic_ptc(mean_adu, var_adu, var_err):
    """G15's quadratic PTC V = -alpha N^2 + N / G + c (section 4.3.2, eq. quadptc).

    Parameters
    ----------
    mean_adu, var_adu, var_err : ndarray (n,)
        Pairs below the turnoff: mean (ADU), variance and its error (ADU^2).

    Returns
    -------
    dict
        ``gain`` and ``gain_err`` (e-/ADU), ``alpha`` and ``alpha_err`` (1/ADU),
        ``a00`` and ``a00_err`` (1/e-; = -alpha numerically, as
        V_ADU = (mu_e + a00 mu_e^2) / G^2), ``read_var_adu`` (c, ADU^2),
        ``read_var_err``, ``chi2``, ``ndof``.
    """
    mean_adu, var_adu, var_err = (np.asarray(v, dtype=float) for v in (mean_adu, var_adu, var_err))
    if mean_adu.size < 3:
        msg = f"the quadratic PTC fit needs at least 3 pairs below the turnoff, got {mean_adu.size}"
        raise BFPSFInputError(msg, mean_adu.size)
    params, cov, chi2, _ = polynomial_fit(mean_adu, var_adu, var_err, 2)
    intercept, slope, curvature = params
    gain = 1.0 / slope
    gain_err = np.sqrt(cov[1, 1]) / slope**2
    # V_ADU = (mu_e + a00 mu_e^2) / G^2 = N / G + a00 N^2 (G15 eq. quadptc): alpha = -a00.
    alpha = -curvature
    a00 = curvature
    a00_err = float(np.sqrt(cov[2, 2]))
    return {
        "gain": float(gain), "gain_err": float(gain_err),
        "alpha": float(alpha), "alpha_err": float(np.sqrt(cov[2, 2])),
        "a00": float(a00), "a00_err": a00_err,
        "read_var_adu": float(intercept), "read_var_err": float(np.sqrt(cov[0, 0])),
        "chi2": chi2, "ndof": int(mean_adu.size - 3),
    }


def exponential_variance(mean_adu, a00, gain, noise_e2):
    """A+19 eq. 16 in ADU^2; tends to mu / g + n / g^2 when a00 -> 0."""
    x = 2.0 * a00 * gain * mean_adu
    # expm1(x) / x, continuous at x = 0
    ratio = np.where(np.abs(x) > 1e-12, np.expm1(x) / np.where(x == 0, 1.0, x), 1.0 + x / 2)
    return ratio * mean_adu / gain + noise_e2 / gain**2


def fit_exponential_ptc(mean_adu, var_adu, var_err, *, initial=None):
    """A+19 exponential approximation (their eq. 16) of the variance.

    Parameters
    ----------
    mean_adu, var_adu, var_err : ndarray (n,)
        Pairs below the turnoff.
    initial : dict, optional
        Starting point with ``gain`` and ``a00`` (e.g. from `fit_quadratic_ptc`).

    Returns
    -------
    dict
        ``gain``, ``gain_err`` (e-/ADU), ``a00``, ``a00_err`` (1/e-), ``noise_e2``,
        ``noise_e2_err`` (n00, e-^2), ``chi2``, ``ndof``.
    """
    mean_adu, var_adu, var_err = (np.asarray(v, dtype=float) for v in (mean_adu, var_adu, var_err))
    if mean_adu.size < 3:
        msg = ("the exponential PTC fit needs at least 3 pairs below the turnoff, "
               f"got {mean_adu.size}")
        raise BFPSFInputError(msg, mean_adu.size)
    if initial is None:
        initial = fit_quadratic_ptc(mean_adu, var_adu, var_err)
    gain0 = initial["gain"]
    start = np.array([initial["a00"] / A_SCALE, gain0, max(initial.get("read_var_adu", 0.0), 0.0)
                      * gain0**2])

    def residuals(p):
        return (exponential_variance(mean_adu, p[0] * A_SCALE, p[1], p[2]) - var_adu) / var_err

    result = scipy.optimize.least_squares(residuals, start, method="lm", x_scale="jac")
    covariance, chi2, ndof = parameter_covariance(result, mean_adu.size)
    errors = np.sqrt(np.diag(covariance))
    return {
        "gain": float(result.x[1]), "gain_err": float(errors[1]),
        "a00": float(result.x[0] * A_SCALE), "a00_err": float(errors[0] * A_SCALE),
        "noise_e2": float(result.x[2]), "noise_e2_err": float(errors[2]),
        "chi2": chi2, "ndof": ndof,
    }


def parameter_covariance(result, ndata):
    """Covariance of least-squares parameters, scaled up by chi2/ndof when that exceeds 1."""
    jac = result.jac
    chi2 = float(np.sum(result.fun**2))
    ndof = int(ndata - jac.shape[1])
    covariance = np.linalg.pinv(jac.T @ jac)
    if ndof > 0 and chi2 > ndof:
        covariance = covariance * (chi2 / ndof)
    return covariance, chi2, ndof


def first_order_slopes(mean_e, cov_adu, npix):
    """Slopes of R(dx, dy) = C / V against mu (e-), with intercept: G15's a to first order.

    Returns slope, slope_err, intercept, intercept_err, each [dy, dx] (the [0, 0] entries are 0).
    """
    variance = cov_adu[:, 0, 0][:, None, None]
    correlation = cov_adu / variance
    # Error of R: sqrt(1/N) at non-zero lags (the variance error is second order for R << 1).
    corr_err = 1.0 / np.sqrt(np.maximum(npix, 1.0))
    nlag = cov_adu.shape[1]
    slope = np.zeros((nlag, nlag))
    slope_err = np.zeros((nlag, nlag))
    intercept = np.zeros((nlag, nlag))
    intercept_err = np.zeros((nlag, nlag))
    for dy in range(nlag):
        for dx in range(nlag):
            if dx == dy == 0:
                continue
            params, cov, _, _ = polynomial_fit(mean_e, correlation[:, dy, dx],
                                               corr_err[:, dy, dx], 1)
            intercept[dy, dx], slope[dy, dx] = params
            intercept_err[dy, dx], slope_err[dy, dx] = np.sqrt(np.diag(cov))
    return slope, slope_err, intercept, intercept_err


# ---------------------------------------------------------------------------------------------
# A+19 full covariance model (eq. 20)
# ---------------------------------------------------------------------------------------------
