"""Weighted linear least squares: the one solver of bfpsf's linear fits.

`weighted_least_squares` fits values = design @ params with Gaussian errors ``sigma``
(columns scaled to unit norm for conditioning; a singular design gets the pseudo-inverse
covariance). `polynomial_fit` is its polynomial case. The PTC fits
(`bfpsf.calibration.ptc_variance`), the closed loop's joint fits and signatures
(`bfpsf.diagnosis`) and the size tables' error estimates use them; the brighter-fatter
slope (`bfpsf.measure.slopes.fit_bf_slope`, with its clipping and group intercepts) solves
through it too.
"""

import numpy as np

__all__ = ["weighted_least_squares", "polynomial_fit"]


def weighted_least_squares(values, sigma, design):
    """Weighted least squares of ``values = design @ params``.

    Parameters
    ----------
    values : ndarray (n,)
    sigma : ndarray (n,) or float
        Errors of ``values`` (weights 1 / sigma^2).
    design : ndarray (n, k)

    Returns
    -------
    params : ndarray (k,)
    covariance : ndarray (k, k)
        From the given errors (not scaled by the chi-square).
    chi2 : float
    model : ndarray (n,)
        ``design @ params``.
    """
    values = np.asarray(values, dtype=float)
    design = np.asarray(design, dtype=float)
    weights = 1.0 / np.broadcast_to(np.asarray(sigma, dtype=float), values.shape)
    a = design * weights[:, None]
    b = values * weights
    norms = np.sqrt((a ** 2).sum(axis=0))
    norms[norms == 0] = 1.0
    solution, *_ = np.linalg.lstsq(a / norms, b, rcond=None)
    params = solution / norms
    model = design @ params
    chi2 = float((((values - model) * weights) ** 2).sum())
    try:
        covariance = np.linalg.pinv((a / norms).T @ (a / norms)) / np.outer(norms, norms)
    except np.linalg.LinAlgError:
        covariance = np.full((params.size, params.size), np.nan)
    return params, covariance, chi2, model


def polynomial_fit(x, values, sigma, degree):
    """`weighted_least_squares` of ``values = sum_k p_k x^k`` (p low order first)."""
    design = np.vander(np.asarray(x, dtype=float), int(degree) + 1, increasing=True)
    return weighted_least_squares(values, sigma, design)
