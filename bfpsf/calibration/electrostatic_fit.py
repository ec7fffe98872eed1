"""The fit of the electrostatic model of the boundary shifts
(`bfpsf.calibration.shifts_electrostatic`, Astier & Regnault 2023) to measured area
coefficients.

The five geometric parameters (``thickness`` is held fixed) and ``alpha`` are fitted to every
measured lag by weighted least squares with the full covariance of a (`scipy.optimize`), each
bounded to a physical range. The shifts' uncertainty is a parametric bootstrap: the measured
a are redrawn from their covariance (scaled by chi2/dof when chi2 exceeds its 99th
percentile, so that a model that does not describe the data carries that into its errors)
and refitted from every distinct local minimum, which follows parameters stopped on a bound
and solutions that move between minima of nearly equal chi2. The refitted shifts are
returned as samples, which every downstream prediction propagates.
"""

import dataclasses

import numpy as np
from scipy import optimize, stats

from ..errors import BFPSFValueError
from ..shifts import BoundaryShifts
from .shifts_electrostatic import (GEOMETRY_BOUNDS, ElectrostaticGeometry, electrostatic_area,
                                   electrostatic_shifts)

__all__ = ["fit_electrostatic", "ElectrostaticFit", "DEFAULT_SAMPLES"]

# Fitted vector: charge height, the two boundary heights above it (so that both stay above the
# charge), in units of the thickness, and the two sheet half-widths in pixels.
_NAMES = ("charge_height", "horizontal_gap", "vertical_gap", "half_width_x", "half_width_y")
_LOWER = np.array([0.0, 1e-4, 1e-4, GEOMETRY_BOUNDS["half_width_x"][0],
                   GEOMETRY_BOUNDS["half_width_y"][0]])
_UPPER = np.array([GEOMETRY_BOUNDS["charge_height"][1], 0.25, 0.25,
                   GEOMETRY_BOUNDS["half_width_x"][1], GEOMETRY_BOUNDS["half_width_y"][1]])
# Starting points: a grid over the two boundary heights and the sheet half-widths. The
# landscape has several local minima of nearly equal chi2 that split a(0, 0) differently
# between N and E: every start is fitted coarsely, the best few are polished.
_STARTS = tuple((charge, horizontal, vertical, half_x, half_y)
                for charge in (0.01,)
                for horizontal, vertical in ((0.01, 0.01), (0.003, 0.1), (0.1, 0.003),
                                             (0.05, 0.2), (0.2, 0.05), (0.1, 0.1))
                for half_x, half_y in ((0.2, 0.2), (0.4, 0.4), (0.4, 0.15), (0.15, 0.4)))
_POLISHED = 3
# Monte Carlo samples of the shifts kept for downstream error propagation.
DEFAULT_SAMPLES = 100


def _geometry(vector, thickness):
    charge, horizontal, vertical, half_x, half_y = vector
    return ElectrostaticGeometry(
        thickness=thickness, charge_height=charge * thickness,
        horizontal_height=(charge + horizontal) * thickness,
        vertical_height=(charge + vertical) * thickness,
        half_width_x=half_x, half_width_y=half_y)


@dataclasses.dataclass(frozen=True)
class ElectrostaticFit:
    """Boundary shifts fitted with the electrostatic model, with their uncertainties.

    Attributes
    ----------
    shifts : BoundaryShifts
        a^N, a^E (1/e-) on offsets -m..m, m = n + 1 (n the largest measured lag).
    north_err, east_err : ndarray
        Standard deviations of ``shifts.north`` and ``shifts.east`` over the samples (1/e-).
    samples_north, samples_east : ndarray, shape (S, 2m + 1, 2m + 1)
        The shifts of refits of a drawn from its covariance (scaled by chi2/dof when the
        model does not describe the data): the calibration error every prediction propagates.
    geometry : ElectrostaticGeometry
        Best-fit geometry (pixels).
    alpha : float
        Best-fit amplitude.
    parameters, parameter_cov : ndarray
        The fitted vector (charge height / t, the two boundary heights above it / t, the
        two half-widths, alpha) and its covariance over the samples.
    at_bound : tuple of str
        Parameters that ended on their physical bound (their error is then not Gaussian).
    chi2 : float
        Chi-square of the fit on the measured a(dx, dy), with their covariance.
    dof : int
        Measured lags minus 6.
    error_scale : float
        The factor applied to the errors of a in the refits: sqrt(chi2 / dof) without given
        errors or when chi2 exceeds its 99th percentile, else 1.
    area, area_err : ndarray
        The measured a [dy, dx] and its 1-sigma errors (1/e-).
    area_model : ndarray
        The model's a [dy, dx] at the measured lags.
    n_unconverged : int
        Fits that stopped on their evaluation bound instead of a tolerance: the best fit (1)
        and the Monte Carlo refits behind the samples. Reported by `shift_warnings`.
    """

    shifts: BoundaryShifts
    north_err: np.ndarray
    east_err: np.ndarray
    samples_north: np.ndarray
    samples_east: np.ndarray
    geometry: ElectrostaticGeometry
    alpha: float
    parameters: np.ndarray
    parameter_cov: np.ndarray
    at_bound: tuple
    chi2: float
    dof: int
    error_scale: float
    area: np.ndarray
    area_err: np.ndarray
    area_model: np.ndarray
    n_unconverged: int = 0

    method = "electrostatic"

    @property
    def maxlag(self):
        return self.area.shape[0] - 1


def _covariance_roots(area_err, area_cov):
    """(W, S) from one decomposition of the covariance of a.ravel(): |W r|^2 is the chi-square
    of residuals r, and S S^T the covariance (semi-definite accepted) for drawing noise."""
    if area_cov is None:
        return np.diag(1.0 / area_err.ravel()), np.diag(area_err.ravel())
    eigenvalues, eigenvectors = np.linalg.eigh(area_cov)
    floor = 1e-12 * eigenvalues.max()
    whiten = (eigenvectors / np.sqrt(np.maximum(eigenvalues, floor))).T
    return whiten, eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))


def _default_errors(area):
    """Errors for an a-matrix given without any: equal per independent measurement.

    A quadrant-averaged lag off both axes averages 4 lags of the full plane, one on an axis 2
    and (0, 0) 1 (with twice the error of a fitted slope), as in cp_pipe: relative variances
    1, 2 and 8 for 4, 2 and 1 replicas, i.e. sigma 1/2, 1 and sqrt(8) (times 1e-3 |a(0, 0)|).
    """
    errors = np.full(area.shape, 0.5)
    errors[0, :] = 1.0
    errors[:, 0] = 1.0
    errors[0, 0] = np.sqrt(8.0)
    return errors * 1e-3 * abs(area[0, 0])


def fit_electrostatic(area, area_err=None, *, area_cov=None, thickness=10.0,
                      n_samples=DEFAULT_SAMPLES, seed=0, max_evaluations=200):
    """Fit the electrostatic model to measured area coefficients and return the shifts.

    Parameters
    ----------
    area : array_like, shape (n + 1, n + 1)
        a(dx, dy) = C(dx, dy) / (V mu), 1/e-, [dy, dx], dx, dy = 0..n, n >= 1; a(0, 0) < 0.
    area_err : array_like, optional
        1-sigma errors of ``area``. Without them (and without ``area_cov``) the fit weights
        the lags as `_default_errors` and scales the errors by the fit's chi2/dof.
    area_cov : array_like, shape ((n + 1)^2, (n + 1)^2), optional
        Full covariance of ``area.ravel()`` (takes precedence over ``area_err``).
    thickness : float, optional
        Sensor thickness in pixels, held fixed. Default 10 (100 um, 10 um pixels: the LSST
        E2V and ITL sensors).
    n_samples : int, optional
        Monte Carlo samples of the shifts. Default 100.
    seed : int, optional
        Seed of the samples.
    max_evaluations : int, optional
        Bound on the model evaluations of the final fit (default 200; typical fits take about
        20) and, halved, of each Monte Carlo refit. A fit that reaches it is counted in
        ``n_unconverged`` and reported by `bfpsf.calibration.boundary_shifts.shift_warnings`.

    Returns
    -------
    ElectrostaticFit
    """
    area = np.array(area, dtype=float)
    if area.ndim != 2 or area.shape[0] != area.shape[1] or area.shape[0] < 2:
        msg = f"area must be a square 2-D array a[dy, dx] for lags 0..n, n >= 1, got {area.shape}"
        raise BFPSFValueError(msg, area.shape)
    if not np.all(np.isfinite(area)):
        msg = f"area contains {np.count_nonzero(~np.isfinite(area))} non-finite values"
        raise BFPSFValueError(msg)
    if not area[0, 0] < 0:
        msg = (f"area a(0, 0) must be negative (a charge shrinks its own pixel), "
               f"got {area[0, 0]:.4g}")
        raise BFPSFValueError(msg, area[0, 0])
    given_errors = area_err is not None or area_cov is not None
    if area_cov is not None:
        area_cov = np.array(area_cov, dtype=float)
        if area_cov.shape != (area.size, area.size) or not np.all(np.isfinite(area_cov)):
            msg = (f"area_cov must be a finite ({area.size}, {area.size}) covariance, "
                   f"got shape {area_cov.shape}")
            raise BFPSFValueError(msg, area_cov.shape)
        area_err = np.sqrt(np.clip(np.diag(area_cov), 0.0, None)).reshape(area.shape)
    elif area_err is not None:
        area_err = np.array(area_err, dtype=float)
        if area_err.shape != area.shape or not np.all(np.isfinite(area_err) & (area_err > 0)):
            msg = f"area_err must be finite, positive and shaped like area {area.shape}"
            raise BFPSFValueError(msg, area_err.shape)
    else:
        area_err = _default_errors(area)
    whiten, noise_root = _covariance_roots(area_err, area_cov)
    n = area.shape[0] - 1
    radius = n + 1
    data = whiten @ area.ravel()

    def model_area(vector):
        return electrostatic_area(_geometry(vector, thickness), 1.0, n)

    def _profile(vector, target):
        """Best alpha (linear) for the geometry ``vector`` and the whitened residuals."""
        basis = whiten @ model_area(vector).ravel()
        alpha = float(basis @ target / (basis @ basis))
        return alpha, target - alpha * basis

    def profile(vector):
        return _profile(vector, data)

    def fit(start, **tolerances):
        return optimize.least_squares(lambda v: profile(v)[1], np.asarray(start),
                                      bounds=(_LOWER, _UPPER), x_scale="jac", **tolerances)

    coarse = sorted((fit(start, max_nfev=15, xtol=1e-4, ftol=1e-4) for start in _STARTS),
                    key=lambda result: result.cost)
    # every fit has an evaluation bound (scipy's default, 100 per parameter, can take many
    # minutes on data the model cannot describe)
    polished = sorted((fit(result.x, xtol=1e-10, ftol=1e-10, gtol=1e-10,
                           max_nfev=int(max_evaluations))
                       for result in coarse[:_POLISHED]), key=lambda result: result.cost)
    best = polished[0]
    vector = best.x
    alpha, residual = profile(vector)
    chi2 = float(residual @ residual)
    dof = max(area.size - 6, 1)

    # Errors are scaled by chi2/dof when the model does not describe the data: always without
    # given errors, and when chi2 exceeds its 99th percentile with them (a normal fluctuation
    # of chi2 above dof is not a model failure).
    if not given_errors:
        scale = chi2 / dof
    else:
        scale = chi2 / dof if chi2 > stats.chi2.ppf(0.99, dof) else 1.0
    at_bound = tuple(name for name, value, low, high in zip(_NAMES, vector, _LOWER, _UPPER)
                     if min(value - low, high - value) < 1e-6 * (high - low))
    geometry = _geometry(vector, thickness)
    shifts = electrostatic_shifts(geometry, alpha, radius)

    # The calibration error: refit data drawn from the covariance of a (scaled by chi2/dof
    # when the model does not describe the data), from each distinct local minimum found
    # above. Unlike a linearised covariance, this follows parameters that stop on a physical
    # bound and solutions that jump between minima of nearly equal chi2 (the N/E split).
    minima = [best.x]
    for result in polished:
        if all(np.max(np.abs(result.x - kept) / (_UPPER - _LOWER)) > 0.02 for kept in minima):
            minima.append(result.x)
    noise_root = noise_root * np.sqrt(scale)
    rng = np.random.default_rng(seed)
    draws, samples_north, samples_east = [], [], []
    n_unconverged = int(best.status == 0)
    for _ in range(int(n_samples)):
        perturbed = whiten @ (area.ravel() + noise_root @ rng.standard_normal(area.size))
        refits = []
        for start in minima:
            refit = optimize.least_squares(lambda v: _profile(v, perturbed)[1], start,
                                           bounds=(_LOWER, _UPPER), x_scale="jac",
                                           xtol=1e-6, ftol=1e-6,
                                           max_nfev=max(int(max_evaluations) // 2, 1))
            refits.append(refit)
        refit = min(refits, key=lambda result: result.cost)
        n_unconverged += refit.status == 0  # scipy: the evaluation bound was reached
        draw_alpha = _profile(refit.x, perturbed)[0]
        draws.append(np.append(refit.x, draw_alpha))
        sample = electrostatic_shifts(_geometry(refit.x, thickness), draw_alpha, radius)
        samples_north.append(sample.north)
        samples_east.append(sample.east)
    full = np.append(vector, alpha)
    samples_north = np.array(samples_north).reshape((-1,) + shifts.shape)
    samples_east = np.array(samples_east).reshape((-1,) + shifts.shape)
    if n_samples >= 2:
        parameter_cov = np.cov(np.array(draws), rowvar=False)
        north_err = samples_north.std(axis=0, ddof=1)
        east_err = samples_east.std(axis=0, ddof=1)
    else:
        parameter_cov = np.full((full.size, full.size), np.nan)
        north_err = np.full(shifts.shape, np.nan)
        east_err = np.full(shifts.shape, np.nan)
    return ElectrostaticFit(
        shifts=shifts, north_err=north_err, east_err=east_err, samples_north=samples_north,
        samples_east=samples_east, geometry=geometry, alpha=alpha, parameters=full,
        parameter_cov=parameter_cov, at_bound=at_bound, chi2=chi2, dof=dof,
        error_scale=float(np.sqrt(scale)), area=area, area_err=area_err,
        area_model=shifts.area_quadrant(n), n_unconverged=int(n_unconverged))
