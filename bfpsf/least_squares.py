"""Weighted linear least squares: the one solver of bfpsf's linear fits.

`weighted_least_squares` fits values = design @ params with Gaussian errors ``sigma``
(columns scaled to unit norm for conditioning; a singular design gets the pseudo-inverse
covariance). `polynomial_fit` is its polynomial case. `clipped_least_squares` is the robust
fit where the errors are unknown and outliers are expected (the sky's surface, a quantity's
plane over the image, a slope's dependence on position), clipping about the fit. The PTC fits
(`bfpsf.calibration.ptc_variance`), the closed loop's joint fits and signatures
(`bfpsf.diagnosis`) and the size tables' error estimates use them; the brighter-fatter
slope (`bfpsf.measure.slopes.fit_bf_slope`, with its clipping and group intercepts) solves
through it too.
"""

from dataclasses import dataclass

import numpy as np

__all__ = ["weighted_least_squares", "least_squares_with_scatter", "polynomial_fit",
           "clipped_least_squares", "ClippedFit"]


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


def least_squares_with_scatter(values, sigma, design, *, max_iterations=40):
    """`weighted_least_squares` with a scatter beyond the given errors: where the chi-square
    exceeds its degrees of freedom, each point's error is ``sqrt(sigma^2 + s^2)`` with the one
    ``s`` that makes chi2 / dof = 1 (errors that miss an intrinsic scatter, as the sizes of
    undersampled stars, which follow their sub-pixel phase far beyond their noise, must not
    weight the fit: the stars of smallest error were those of one phase, and a new user's
    slopes of sizes against peak came out 37-45 % low, a BF-free twin's 4.4 sigma from zero).
    Returns (params, covariance, chi2, model, s); chi2 with the given errors alone."""
    values = np.asarray(values, dtype=float)
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), values.shape)
    dof = values.size - np.shape(design)[1]
    params, covariance, chi2, model = weighted_least_squares(values, sigma, design)
    if dof < 1 or not chi2 > dof:
        return params, covariance, chi2, model, 0.0
    low, high = 0.0, float(np.std(values - model)) * 2.0 + float(np.max(sigma))
    for _ in range(max_iterations):  # chi2(s) falls as s grows: bisection on s
        middle = 0.5 * (low + high)
        total = np.sqrt(sigma ** 2 + middle ** 2)
        fitted = weighted_least_squares(values, total, design)
        low, high = (middle, high) if fitted[2] > dof else (low, middle)
        if high - low < 1e-4 * high:
            break
    total = np.sqrt(sigma ** 2 + high ** 2)
    params, covariance, _, model = weighted_least_squares(values, total, design)
    return params, covariance, float(np.sum(((values - model) / sigma) ** 2)), model, high


def polynomial_fit(x, values, sigma, degree):
    """`weighted_least_squares` of ``values = sum_k p_k x^k`` (p low order first)."""
    design = np.vander(np.asarray(x, dtype=float), int(degree) + 1, increasing=True)
    return weighted_least_squares(values, sigma, design)


@dataclass(frozen=True)
class ClippedFit:
    """A `clipped_least_squares` fit: ``params``, ``scale`` (the robust sigma of the kept
    points' residuals, 1.4826 times their median absolute value), ``keep`` (the points kept,
    bool), and the design and values it was fitted to (for `covariance`)."""

    params: np.ndarray
    scale: float
    keep: np.ndarray
    design: np.ndarray
    values: np.ndarray

    @property
    def dof(self):
        """Kept points less parameters."""
        return int(self.keep.sum()) - self.design.shape[1]

    @property
    def covariance(self):
        """Of ``params``, from the kept points' scatter: their residual sum of squares per
        degree of freedom times (X^T X)^-1 (computed when asked: a sky's design has 250k
        rows)."""
        design, values = self.design[self.keep], self.values[self.keep]
        residual = values - design @ self.params
        variance = float(residual @ residual) / max(self.dof, 1)
        return variance * np.linalg.pinv(design.T @ design)


def clipped_least_squares(values, design, *, nsigma=3.0, max_iterations=5, min_kept=None):
    """Least squares of ``values = design @ params`` with iterative sigma clipping about the
    fit: a point further than ``nsigma`` robust sigma (1.4826 times the kept points' median
    absolute residual) from the fit is left out, and the fit repeated on the others, until
    nothing changes, after ``max_iterations`` fits, or where fewer than ``min_kept`` points
    (default: parameters + 5) would be left. Points of non-finite value or design are never
    kept. A design of one column of ones is fitted by the median (a level robust to the
    tails, as a sky's). Returns a `ClippedFit`."""
    values = np.asarray(values, dtype=float)
    design = np.asarray(design, dtype=float)
    finite = np.isfinite(values) & np.all(np.isfinite(design), axis=1)
    min_kept = design.shape[1] + 5 if min_kept is None else int(min_kept)
    level = design.shape[1] == 1 and np.all(design[finite] == 1.0)
    keep = finite
    for _ in range(max_iterations):
        if level:
            params = np.array([np.median(values[keep])])
        else:
            params = np.linalg.lstsq(design[keep], values[keep], rcond=None)[0]
        deviation = values - design @ params
        scale = 1.4826 * float(np.median(np.abs(deviation[keep])))
        new_keep = finite & (np.abs(deviation) <= nsigma * max(scale, 1e-12))
        if np.array_equal(new_keep, keep) or new_keep.sum() < min_kept:
            break
        keep = new_keep
    return ClippedFit(params, scale, keep, design, values)
