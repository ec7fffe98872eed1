"""Boundary shifts a^X(dx, dy) from measured area coefficients a(dx, dy) (G15 section 6.1).

The flats measure only the area coefficients a(dx, dy) = sum_X a^X(dx, dy) (G15 eq. covar) on
a quadrant of lags dx, dy = 0..n. The boundary shifts are recovered as in G15 section 6.1:

1. A smoothing model f(r) = p0 Ei(p1 r) (G15 eq. f_r) is fitted to the area coefficients of
   the non-nearest neighbours (every lag but (0, 0), (1, 0), (0, 1) and (1, 1), as G15 does),
   with a^X = -f(r) cos(theta) (the convention of `BoundaryShifts.from_radial_profile`: theta
   between the source -> boundary-centre vector and the outward normal, f > 0 for repulsion).
   With ``scipy.special.expi`` = G15's Ei, a profile that decays needs p1 < 0 and then
   Ei(p1 r) = -E1(|p1| r) < 0, so repulsion gives p0 < 0: f(r) = |p0| E1(|p1| r). The fit is
   restricted to p1 < 0 (Ei of a positive argument grows exponentially).
2. One linear system gives every boundary shift. Symmetries are built into the unknowns:
   translation (G15 eq. trans), parity (eq. par) and the mirror symmetries x -> -x, y -> -y
   implied by the quadrant-averaged flats leave, for L = n + 1 lags per axis, the 2 L^2
   unknowns N(i, j) = a^N(i, j) (i = 0..n, j = 1..L) and E(i, j) = a^E(i, j) (i = 1..L,
   j = 0..n) (G15's "2 n^2 coefficients", their n being L); the sum rule (eq. sum-rule) then holds by
   construction. Equations:

   * EXACT: the L^2 measured a(dx, dy), INCLUDING a(0, 0) (eq. covar);
   * LEAST SQUARES, from the Ei model (each row scaled to a relative departure from it):
     - the ratio a^S / a^W of the two far boundaries of every source except (0, 0), (1, 0),
       (0, 1) (G15's ratio constraint, extended from i, j > 0 to the axis sources i >= 2) and
       the corner (n, n), whose far boundaries are both limit conditions;
     - the ratio a^N(1, 1) / a^E(1, 1) (= 1 for the isotropic model);
     - the limit conditions on the 2 L farthest boundaries N(i, L), E(L, j): their SHAPE
       follows the Ei model, their common AMPLITUDE is one more unknown (see below).

   The boundaries between the source and its nearest neighbours are left free. Why not G15's
   set as printed: with the unknowns above it is rank deficient by n (checked numerically,
   with or without a(0, 0)): the off-axis ratios constrain only the two far boundaries of
   each pixel, so the information coming from the axes is lost. Adding a^N(1, 1) / a^E(1, 1)
   (which removes an area-free circulation around the corner shared by (0, 0), (1, 0),
   (0, 1), (1, 1)) still leaves n - 1 null modes; the axis-source ratios remove them and
   over-determine the model part by 2 n - 2 rows. The data rows are therefore imposed
   exactly (null-space method, x = A^+ a + Z y) and the model rows solved for y by QR least
   squares: one linear problem, full rank for every p1 (checked by the tests). When the
   input follows the Ei model beyond the nearest neighbours the model rows are satisfied
   exactly and the solution is the exact one (tested).

Truncated sum rule. The sum of the measured a over the symmetric square -n..n is not zero:
area lies outside the measured lags. In the boundary-shift representation all of it crosses
the farthest boundaries, whose total displacement is exactly minus that truncation residual
(discrete divergence theorem). Rather than predicting a(0, 0) from the Ei extrapolation (G15,
who use n^2 - 1 correlations, i.e. drop a(0, 0)), the amplitude of the limit conditions is
solved so that the measured a(0, 0) is reproduced: the solved shifts sum back to EVERY input
a exactly, and
``far_scale`` = (solved farthest boundaries) / (Ei extrapolation) tells whether the measured
a(0, 0) agrees with the smoothing model (1 means agreement; Lage's corr_meas tables are
normalised so that their truncated sum is zero, which forces it to ~0).

The boundary shifts are returned on offsets -m..m with m = n + 1, the smallest grid holding
a^N(dx, n + 1) and a^E(n + 1, dy). Shifts on that outer ring not reached by the measured lags
(a^N at |dx| = m, a^E at |dy| = m) take the Ei model with the solved amplitude.

Uncertainties: Monte Carlo over the input errors (independent Gaussian, or a full
covariance), re-fitting the smoothing model and re-solving for every draw, all draws solved
at once (about 1 s for n = 8 and 200 draws on one core). The solution depends on p1 only: p0
cancels from every model row (ratios, and the shape of the limit conditions).
"""

import dataclasses
import functools

import numpy as np
from scipy.special import expi

from ..errors import BFPSFCovarianceError, BFPSFValueError
from ..shifts import BoundaryShifts
from .ei_profile import (P1_LIMITS, FitBasis, fit_p1, fit_profile, fit_smoothing_model,
                         non_nearest_mask, smoothing_model_area, unit_east, unit_north,
                         validate_area)

__all__ = ["ShiftSolution", "solve_ei_shifts", "fit_smoothing_model",
           "smoothing_model_area", "non_nearest_mask"]

# Smallest model value, relative to the largest, below which a constraint row is weighted as if
# its boundary had that value (keeps the least-squares problem well conditioned).
_MIN_RELATIVE = 1e-4


@dataclasses.dataclass(frozen=True)
class ShiftSolution:
    """Boundary shifts solved from measured area coefficients, with their uncertainties.

    Attributes
    ----------
    shifts : BoundaryShifts
        a^N, a^E (1/e-) on offsets -m..m, m = n + 1.
    north_err, east_err : ndarray, shape (2m + 1, 2m + 1)
        Monte Carlo standard deviation of ``shifts.north`` and ``shifts.east`` (1/e-); NaN when
        no input errors were given.
    p0, p1 : float
        Smoothing model f(r) = p0 Ei(p1 r) (G15 eq. f_r), a^X = -f(r) cos(theta); p0 in 1/e-,
        p1 in 1/pixel (p1 < 0: decaying profile).
    p0_err, p1_err : float
        1-sigma errors of p0, p1 from the fit covariance (scaled by chi2/dof when no input
        errors were given); p1_err is inf when the non-nearest lags carry no signal.
    chi2 : float
        Chi-square of the smoothing fit over the non-nearest neighbours (unit weights when no
        errors were given).
    dof : int
        Degrees of freedom of that fit (points - 2).
    far_scale : float
        Solved farthest boundaries / Ei extrapolation (1: measured a(0, 0) agrees with the
        model's tail; see the module notes on the truncated sum rule). NaN when p0 = 0.
    truncation_residual : float
        Sum of the input a over the symmetric square -n..n, 1/e- (zero if no area lies outside).
    sensitivity : dict
        Change of the a^X when p1 moves by +-``nsigma`` p1_err (G15: about 1 %): ``nsigma``,
        ``max_relative`` (largest |change| / |a^X| over coefficients above 1 % of the largest
        one), ``rms_relative`` (rms change / rms coefficient), ``p1_values``.
    area_model : ndarray, shape (n + 1, n + 1)
        a(dx, dy) implied by the solved shifts, [dy, dx], 1/e-.
    area, area_err : ndarray, shape (n + 1, n + 1)
        The input, [dy, dx], 1/e- (area_err None when not given).
    n_monte_carlo : int
        Draws used for the errors.
    samples_north, samples_east : ndarray, shape (n_monte_carlo, 2m + 1, 2m + 1)
        The Monte Carlo solutions themselves (empty without input errors): the calibration
        error that downstream predictions propagate.
    """

    shifts: BoundaryShifts
    north_err: np.ndarray
    east_err: np.ndarray
    p0: float
    p1: float
    p0_err: float
    p1_err: float
    chi2: float
    dof: int
    far_scale: float
    truncation_residual: float
    sensitivity: dict
    area_model: np.ndarray
    area: np.ndarray
    area_err: np.ndarray | None
    n_monte_carlo: int
    samples_north: np.ndarray
    samples_east: np.ndarray

    method = "ei"

    @property
    def maxlag(self):
        """n: the largest measured lag."""
        return self.area.shape[0] - 1

    def radial_profile(self, r):
        """f(r) = p0 Ei(p1 r), 1/e-, r in pixels (G15 eq. f_r; f > 0 is repulsion)."""
        return self.p0 * expi(self.p1 * np.asarray(r, dtype=float))


# -- the linear system ---------------------------------------------------------------------------
class _Layout:
    """Index bookkeeping of the 2 L^2 + 1 unknowns for L = n + 1 lags per axis.

    Unknowns: N(i, j) = a^N(i, j), i = 0..n, j = 1..L at i * L + j - 1; E(i, j) = a^E(i, j),
    i = 1..L, j = 0..n at L^2 + (i - 1) * L + j; the amplitude of the limit conditions last.
    """

    def __init__(self, maxlag):
        self.n = maxlag
        self.lags = L = maxlag + 1
        self.size = 2 * L * L + 1
        self.amplitude = 2 * L * L
        self._build_constant()
        self._build_gather()

    def north(self, i, j):
        return i * self.lags + j - 1

    def east(self, i, j):
        return self.lags ** 2 + (i - 1) * self.lags + j

    def _build_constant(self):
        """Area rows (G15 eq. covar) and the index lists of the model rows."""
        n, L = self.n, self.lags
        area_rows = np.zeros((L * L, self.size))
        for dy in range(L):
            for dx in range(L):
                row = area_rows[dy * L + dx]
                # north + south: a^N(dx, dy) - a^N(dx, dy + 1); a^N(dx, 0) = -a^N(dx, 1)
                if dy >= 1:
                    row[self.north(dx, dy)] += 1.0
                    row[self.north(dx, dy + 1)] -= 1.0
                else:
                    row[self.north(dx, 1)] -= 2.0
                if dx >= 1:
                    row[self.east(dx, dy)] += 1.0
                    row[self.east(dx + 1, dy)] -= 1.0
                else:
                    row[self.east(1, dy)] -= 2.0
        self.area_rows = area_rows
        # ratio of the two far boundaries (a^S / a^W) of every source but (0, 0), (1, 0),
        # (0, 1) and the corner (n, n) (whose far boundaries are both limit conditions)
        excluded = {(0, 0), (1, 0), (0, 1), (n, n)}
        self.ratio_sources = np.array([(i, j) for j in range(L) for i in range(L)
                                       if (i, j) not in excluded], dtype=float).reshape(-1, 2)
        # limit conditions: N(i, L), i = 0..n and E(L, j), j = 0..n
        self.far_north_i = np.arange(L, dtype=float)
        self.far_east_j = np.arange(L, dtype=float)
        self.far_columns = np.array([self.north(k, L) for k in range(L)]
                                    + [self.east(L, k) for k in range(L)])
        i, j = self.ratio_sources[:, 0].astype(int), self.ratio_sources[:, 1].astype(int)
        ratio_columns = np.stack([i * L + j, L * L + i * L + j], axis=1)  # N(i,j+1), E(i+1,j)
        inner_columns = np.array([[self.north(1, 1), self.east(1, 1)]])
        far_columns = np.stack([self.far_columns, np.full(2 * L, 2 * L * L)], axis=1)
        self.model_columns = np.concatenate([ratio_columns, inner_columns, far_columns])
        # null space of the area rows (constant): x = particular + null_space @ y
        _, singular, vt = np.linalg.svd(area_rows)
        rank = int(np.sum(singular > 1e-10 * singular[0]))
        if rank != L * L:  # pragma: no cover - the area operator has full row rank
            raise AssertionError(f"area operator has rank {rank} < {L * L}")
        self.area_pinv = np.linalg.pinv(area_rows)
        self.null_space = vt[rank:].T

    def model_rows(self, p1):
        """Smoothing-model constraints C(p1) x = 0 in sparse form: two terms per row.

        Returns ``columns`` [R, 2] (unknown indices) and ``weights`` [D, R, 2]. Each row is
        scaled so that its residual is the RELATIVE departure from the Ei model times the model
        amplitude; model values below ``_MIN_RELATIVE`` of the largest are weighted as if they
        had that value, so that negligible far boundaries do not dominate.
        """
        p1 = np.asarray(p1, dtype=float).reshape(-1, 1)
        i, j = self.ratio_sources[:, 0], self.ratio_sources[:, 1]
        # a^S(i, j) = -N(i, j + 1), a^W(i, j) = -E(i + 1, j): N * model_W - E * model_S = 0
        model_s = -unit_north(i, j + 1, p1)
        model_w = -unit_east(i + 1, j, p1)
        # a^N(1, 1) * model_E(1, 1) - a^E(1, 1) * model_N(1, 1) = 0
        model_n11 = unit_north(1.0, 1.0, p1)
        model_e11 = unit_east(1.0, 1.0, p1)
        far = self.far_model(p1)
        largest = np.max(np.abs(np.concatenate([model_s, model_w, far], axis=1)), axis=1,
                         keepdims=True)
        floor = _MIN_RELATIVE * largest
        # unit direction of the model pair times largest / max(|model|, floor)
        size = np.hypot(model_s, model_w)
        ratio_norm = size * np.maximum(size, floor) / largest
        size = np.hypot(model_n11, model_e11)
        inner_norm = size * np.maximum(size, floor) / largest
        # limit conditions: far boundary_k - amplitude * far_k / max|far| = 0, relative
        far_weight = largest / np.maximum(np.abs(far), floor)
        far_shape = far / np.max(np.abs(far), axis=1, keepdims=True)
        first = np.concatenate([model_w / ratio_norm, model_e11 / inner_norm, far_weight], axis=1)
        second = np.concatenate([-model_s / ratio_norm, -model_n11 / inner_norm,
                                 -far_weight * far_shape], axis=1)
        return self.model_columns, np.stack([first, second], axis=-1)

    def far_model(self, p1):
        """Unit-p0 model of the 2 L farthest boundaries, [D, 2 L]."""
        p1 = np.asarray(p1, dtype=float).reshape(-1, 1)
        L = self.lags
        return np.concatenate([unit_north(self.far_north_i, L, p1),
                               unit_east(L, self.far_east_j, p1)], axis=1)

    def _build_gather(self):
        """Indices mapping [unknowns, outer-ring model, 0] onto the (2m+1)^2 grids, with signs."""
        n, L = self.n, self.lags
        m = L
        zero = self.size - 1 + 2 * L   # index of the appended zero
        north_index = np.full((2 * m + 1, 2 * m + 1), zero)
        north_sign = np.ones((2 * m + 1, 2 * m + 1))
        east_index = np.full((2 * m + 1, 2 * m + 1), zero)
        east_sign = np.ones((2 * m + 1, 2 * m + 1))
        outer = self.size - 1  # after the 2 L^2 shifts: L outer-north then L outer-east values
        for dy in range(-m, m + 1):
            for dx in range(-m, m + 1):
                # a^N(dx, dy) = a^N(|dx|, dy); dy <= 0: -a^N(|dx|, 1 - dy)
                j, sign = (dy, 1.0) if dy >= 1 else (1 - dy, -1.0)
                i = abs(dx)
                if j <= L:
                    north_index[dy + m, dx + m] = (self.north(i, j) if i <= n
                                                   else outer + j - 1)
                    north_sign[dy + m, dx + m] = sign
                # a^E(dx, dy) = a^E(dx, |dy|); dx <= 0: -a^E(1 - dx, |dy|)
                i, sign = (dx, 1.0) if dx >= 1 else (1 - dx, -1.0)
                j = abs(dy)
                if i <= L:
                    east_index[dy + m, dx + m] = (self.east(i, j) if j <= n
                                                  else outer + L + i - 1)
                    east_sign[dy + m, dx + m] = sign
        self.north_index, self.north_sign = north_index, north_sign
        self.east_index, self.east_sign = east_index, east_sign

    def grids(self, solution, p1):
        """north, east [D, 2m+1, 2m+1] from solutions [D, size] solved at p1 [D]."""
        L = self.lags
        p1 = np.asarray(p1, dtype=float).reshape(-1, 1)
        far = self.far_model(p1)
        amplitude = solution[:, self.amplitude:self.amplitude + 1] / np.max(
            np.abs(far), axis=1, keepdims=True)
        ring = np.arange(1, L + 1, dtype=float)
        outer_north = amplitude * unit_north(float(L), ring, p1)   # a^N(L, j), j = 1..L
        outer_east = amplitude * unit_east(ring, float(L), p1)     # a^E(i, L), i = 1..L
        values = np.concatenate([solution[:, :self.amplitude], outer_north, outer_east,
                                 np.zeros((solution.shape[0], 1))], axis=1)
        north = values[:, self.north_index] * self.north_sign
        east = values[:, self.east_index] * self.east_sign
        return north, east


@functools.lru_cache(maxsize=16)
def _layout(maxlag):
    """The (immutable) layout of the system for ``maxlag``, built once."""
    return _Layout(maxlag)


def _solve_batch(layout, area_batch, p1_batch):
    """Solve for a batch of areas [D, L, L] and p1 [D]; returns (north, east) grids, amplitude.

    The area equations are imposed exactly (null-space method): x = A^+ a + Z y, and y
    minimises |C(p1) x| by a QR least-squares solve, batched over the draws.
    """
    scale = np.max(np.abs(area_batch), axis=(1, 2), keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    flat = (area_batch / scale).reshape(area_batch.shape[0], -1)
    particular = flat @ layout.area_pinv.T                            # [D, size]
    columns, weights = layout.model_rows(p1_batch)                   # [R, 2], [D, R, 2]
    reduced = np.einsum("drt,rtk->drk", weights, layout.null_space[columns])   # C Z [D, R, K]
    q, r = np.linalg.qr(reduced)
    target = -np.einsum("drt,drt->dr", weights, particular[:, columns])
    coefficients = np.linalg.solve(r, np.einsum("drk,dr->dk", q, target)[..., None])[..., 0]
    solution = particular + coefficients @ layout.null_space.T
    solution *= scale.reshape(-1, 1)
    return layout.grids(solution, p1_batch), solution[:, layout.amplitude]


# -- validation ---------------------------------------------------------------------------------
def _validate_covariance(area_cov, area):
    """A square root S of the covariance (S S^T = area_cov); semi-definite matrices accepted."""
    size = area.size
    area_cov = np.array(area_cov, dtype=float)
    if area_cov.shape != (size, size):
        msg = (f"area_cov (covariance of area.ravel(), [dy, dx] order) must have shape "
               f"({size}, {size}), got {area_cov.shape}")
        raise BFPSFCovarianceError(msg, area_cov.shape)
    if not np.all(np.isfinite(area_cov)) or not np.allclose(area_cov, area_cov.T, rtol=1e-8,
                                                            atol=0.0):
        msg = "area_cov must be a finite symmetric covariance matrix"
        raise BFPSFCovarianceError(msg)
    try:
        return np.linalg.cholesky(area_cov)
    except np.linalg.LinAlgError:
        pass
    # semi-definite (e.g. a fit covariance with an exactly degenerate direction)
    eigenvalues, eigenvectors = np.linalg.eigh(area_cov)
    if eigenvalues.min() < -1e-10 * max(eigenvalues.max(), 0.0) or eigenvalues.max() <= 0:
        msg = (f"area_cov is not a positive semi-definite covariance "
               f"(smallest eigenvalue {eigenvalues.min():.3g})")
        raise BFPSFCovarianceError(msg, float(eigenvalues.min()))
    return eigenvectors * np.sqrt(np.clip(eigenvalues, 0.0, None))


# -- the public solver --------------------------------------------------------------------------
def _sensitivity(layout, area, p1, p1_err, nsigma, north, east):
    """Relative change of the a^X when p1 moves by +-nsigma p1_err."""
    p1_values = np.array([p1 - nsigma * p1_err, p1 + nsigma * p1_err])
    # stay within the range the fit explores (a decaying, not too steep profile)
    p1_values = np.clip(p1_values, *P1_LIMITS)
    (north_v, east_v), _ = _solve_batch(layout, np.broadcast_to(area, (2,) + area.shape),
                                        p1_values)
    reference = np.concatenate([north.ravel(), east.ravel()])
    changes = np.concatenate([(north_v - north).reshape(2, -1),
                              (east_v - east).reshape(2, -1)], axis=1)
    significant = np.abs(reference) >= 0.01 * np.abs(reference).max()
    max_relative = float(np.max(np.abs(changes[:, significant]) / np.abs(reference[significant])))
    rms_relative = float(np.max(np.sqrt(np.mean(changes ** 2, axis=1)
                                        / np.mean(reference ** 2))))
    return {"nsigma": float(nsigma), "max_relative": max_relative,
            "rms_relative": rms_relative, "p1_values": tuple(float(v) for v in p1_values)}


def solve_ei_shifts(area, area_err=None, *, area_cov=None, n_monte_carlo=200, seed=0,
                          p1_sensitivity_nsigma=5.0):
    """Boundary shifts a^N, a^E from measured area coefficients (G15 section 6.1).

    Parameters
    ----------
    area : array_like, shape (n + 1, n + 1)
        a(dx, dy) = C(dx, dy) / (V mu), 1/e-, indexed [dy, dx], dx, dy = 0..n, n >= 2;
        a(0, 0) < 0 (G15 eq. covar).
    area_err : array_like, optional
        1-sigma errors of ``area`` (1/e-), used to weight the smoothing fit and for the Monte
        Carlo. Without them the fit is unweighted and no Monte Carlo is run (errors NaN).
    area_cov : array_like, shape ((n + 1)^2, (n + 1)^2), optional
        Full covariance of ``area.ravel()`` for the Monte Carlo draws (default: independent
        Gaussian errors ``area_err``).
    n_monte_carlo : int, optional
        Monte Carlo draws: each perturbs the input, re-fits p1 and re-solves. Default 200.
    seed : int, optional
        Seed of the draws. Default 0.
    p1_sensitivity_nsigma : float, optional
        The sensitivity to the smoothing model is the change of the a^X when p1 moves by
        +-this many sigma (G15: 5 sigma, about 1 %). Default 5.

    Returns
    -------
    ShiftSolution

    Raises
    ------
    BFPSFValueError
        Wrong shape, non-finite values, a(0, 0) >= 0, bad errors or covariance.

    Notes
    -----
    See the module docstring for the system of equations and the handling of the truncated
    sum rule. The solution reproduces every input a(dx, dy) to rounding and obeys the
    symmetries and the sum rule by construction.
    """
    area, area_err = validate_area(area, area_err)
    n_monte_carlo = int(n_monte_carlo)
    if n_monte_carlo < 0 or n_monte_carlo == 1:
        msg = f"n_monte_carlo must be 0 or at least 2, got {n_monte_carlo}"
        raise BFPSFValueError(msg, n_monte_carlo)
    if p1_sensitivity_nsigma < 0:
        msg = f"p1_sensitivity_nsigma must be non-negative, got {p1_sensitivity_nsigma}"
        raise BFPSFValueError(msg, p1_sensitivity_nsigma)
    cholesky = None
    if area_cov is not None:
        cholesky = _validate_covariance(area_cov, area)
        if area_err is None:
            derived = np.sqrt(np.clip(np.diag(np.asarray(area_cov, dtype=float)), 0.0, None))
            area, area_err = validate_area(area, derived.reshape(area.shape))
    n = area.shape[0] - 1
    layout = _layout(n)
    p0, p1, p0_err, p1_err, chi2, dof = fit_profile(area, area_err)
    (north, east), amplitude = _solve_batch(layout, area[None], np.array([p1]))
    north, east = north[0], east[0]
    shifts = BoundaryShifts(north, east, check=True, rtol=1e-9)

    # solved far boundaries = amplitude * unit / max|unit|; the Ei extrapolation = p0 * unit
    far_unit = layout.far_model(np.array([p1]))[0]
    # nan when p0 is 0 or so small (a denormal far tail) that the ratio is not a number
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        far_scale = float(amplitude[0] / np.max(np.abs(far_unit)) / p0) if p0 != 0 else np.nan
    far_scale = far_scale if np.isfinite(far_scale) else np.nan
    signs = np.ones_like(area)
    signs[1:, :] *= 2.0
    signs[:, 1:] *= 2.0
    truncation_residual = float(np.sum(signs * area))

    north_err = np.full_like(north, np.nan)
    east_err = np.full_like(east, np.nan)
    north_draws = np.empty((0,) + north.shape)
    east_draws = np.empty((0,) + east.shape)
    if area_err is not None and n_monte_carlo >= 2:
        rng = np.random.default_rng(seed)
        normal = rng.standard_normal((n_monte_carlo, area.size))
        if cholesky is not None:
            noise = normal @ cholesky.T
        else:
            noise = normal * area_err.ravel()
        draws = area[None] + noise.reshape((n_monte_carlo,) + area.shape)
        mask = non_nearest_mask(n)
        dy, dx = np.nonzero(mask)
        # p1 to 5e-8 relative per draw: far below its Monte Carlo scatter
        p1_draws = fit_p1(draws[:, mask], 1.0 / area_err[mask] ** 2, FitBasis(dx, dy),
                           tolerance=1e-6)
        (north_draws, east_draws), _ = _solve_batch(layout, draws, p1_draws)
        north_err = north_draws.std(axis=0, ddof=1)
        east_err = east_draws.std(axis=0, ddof=1)
    for array in (north_err, east_err):
        array.flags.writeable = False

    sensitivity = _sensitivity(layout, area, p1, p1_err, p1_sensitivity_nsigma, north, east)
    area_model = shifts.area_quadrant(n)
    area_model.flags.writeable = False
    return ShiftSolution(shifts=shifts, north_err=north_err, east_err=east_err, p0=p0, p1=p1,
                         p0_err=p0_err, p1_err=p1_err, chi2=chi2, dof=dof, far_scale=far_scale,
                         truncation_residual=truncation_residual, sensitivity=sensitivity,
                         area_model=area_model, area=area, area_err=area_err,
                         n_monte_carlo=n_monte_carlo if area_err is not None else 0,
                         samples_north=north_draws, samples_east=east_draws)
