"""Inverse brighter-fatter: the image before charge redistribution, by fixed-point iteration or
G15's first-order sign flip."""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFConvergenceError, BFPSFValueError
from ..shifts import as_shifts
from .redistribution import add_redistribution, as_image, validate_dtype

__all__ = ["correct", "CorrectionResult"]


@dataclass(frozen=True)
class CorrectionResult:
    """Result of `correct` with ``full_output=True``.

    Attributes
    ----------
    image : ndarray
        Corrected image x, e-.
    method : str
        'iterative' or 'first_order'.
    iterations : int
        Forward evaluations of the iteration (the residual of the returned image is the last);
        1 for 'first_order', whose residual costs one more.
    residual : float
        max |redistribute(x) - image|, e- (for 'first_order' too).
    relative_residual : float
        ``residual / max|image|``.
    error_bound : float
        Estimated max |x - x_true| / max|image|: the residual divided by (1 - contraction).
    contraction : float
        Observed ratio of successive residuals (nan if fewer than two iterations).
    converged : bool
        Whether the stopping rule was met.
    residual_history : tuple of float
        max |residual| after each iteration, e-.
    """

    image: np.ndarray
    method: str
    iterations: int
    residual: float
    relative_residual: float
    error_bound: float
    contraction: float
    converged: bool
    residual_history: tuple


def correct(image_e, shifts, *, method="iterative", rtol=1e-10, max_iter=100, density=None,
            nan_policy="raise", full_output=False, strict=True, dtype=np.float64, workers=None):
    """Inverse brighter-fatter: the image x with ``redistribute(x) == image_e``, e-.

    Parameters
    ----------
    image_e : array_like [y, x]
        Observed charge image, e-.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    method : {'iterative', 'first_order'}, optional
        'first_order': G15's sign flip, x = Q - dQ(Q) (section 7.3; error O(a^2 Q^3)).
        'iterative': fixed-point iteration x_{k+1} = x_k + r_k with the residual
        r_k = Q - redistribute(x_k), one forward evaluation per iteration.
    rtol : float, optional
        Stopping rule of 'iterative': stop when the estimated error of x,
        max|r_k| / (1 - c), is at most ``rtol * max|image|``, with c the observed contraction
        max|r_k| / max|r_{k-1}| (the linear convergence factor of the iteration, of order
        |a(0,0)| Q_peak / 2). Since r_k is the residual of the returned x, the bound is on
        the answer, not on a step size. Default 1e-10.
    max_iter : int, optional
        Largest number of iterations. Default 100.
    density : (ndarray, ndarray), optional
        Boundary density of the corrected image (e.g. `~bfpsf.model.density.exact_boundary_density` of a model of
        the scene), held fixed during the iteration; default G15's mean of each iterate.
    nan_policy, dtype, workers
        As in `~bfpsf.model.redistribution.redistribute`.
    full_output : bool, optional
        Return a `CorrectionResult` instead of the image. Default False.
    strict : bool, optional
        Raise `~bfpsf.errors.BFPSFConvergenceError` if the stopping rule is not met within
        ``max_iter`` or the iteration diverges; otherwise return the last iterate with
        ``converged=False``. Default True.

    Returns
    -------
    ndarray or CorrectionResult
    """
    image, bad = as_image(image_e, nan_policy)
    shifts = as_shifts(shifts)
    dtype = validate_dtype(dtype)
    if method not in ("iterative", "first_order"):
        msg = f"method must be 'iterative' or 'first_order', got {method!r}"
        raise BFPSFValueError(msg, method)
    if not (rtol > 0):
        msg = f"rtol must be positive, got {rtol}"
        raise BFPSFValueError(msg, rtol)
    if int(max_iter) < 1:
        msg = f"max_iter must be at least 1, got {max_iter}"
        raise BFPSFValueError(msg, max_iter)
    scale = float(np.abs(image).max()) or 1.0

    def forward_delta(x):
        return add_redistribution(np.zeros(x.shape), x, shifts, density, dtype, workers)

    history = []
    contraction = np.nan
    converged = False
    if method == "first_order":
        x = image - forward_delta(image)
        residual = image - x - forward_delta(x)
        history.append(float(np.abs(residual).max()))
        iterations = 1
        converged = True
        error = history[-1]
    else:
        x = image.copy()
        for iterations in range(1, int(max_iter) + 1):
            residual = image - x - forward_delta(x)
            history.append(float(np.abs(residual).max()))
            if len(history) >= 2:
                contraction = history[-1] / history[-2] if history[-2] > 0 else 0.0
            rate = min(contraction, 0.99) if np.isfinite(contraction) else 0.0
            error = history[-1] / (1.0 - rate)
            if error <= rtol * scale:
                converged = True
                break
            if (len(history) >= 3 and contraction >= 1.0) or iterations == int(max_iter):
                break  # diverging, or out of iterations: x is the iterate r_k belongs to
            x = x + residual
    if not converged and strict:
        msg = (f"iterative correction did not converge: residual {history[-1]:.3g} e- "
               f"({history[-1] / scale:.3g} of the peak) after {iterations} iterations, "
               f"contraction {contraction:.3g}; increase max_iter or rtol")
        raise BFPSFConvergenceError(msg)
    if bad is not None:
        x = x.copy()
        x[bad] = np.nan
    if not full_output:
        return x
    return CorrectionResult(image=x, method=method, iterations=iterations,
                            residual=history[-1], relative_residual=history[-1] / scale,
                            error_bound=error / scale, contraction=float(contraction),
                            converged=converged, residual_history=tuple(history))
