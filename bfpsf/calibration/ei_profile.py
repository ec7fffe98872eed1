"""The smoothing model of the boundary shifts, f(r) = p0 Ei(p1 r) (G15 eq. f_r), and its fit.

a^X = -f(r) cos(theta) (the convention of `bfpsf.shifts.BoundaryShifts.from_radial_profile`:
theta between the source -> boundary-centre vector and the outward normal, f > 0 for
repulsion). The fit (`fit_smoothing_model`) uses the area coefficients of the non-nearest
neighbours (every lag but (0, 0), (1, 0), (0, 1) and (1, 1), as G15 does): p1 by a grid and
golden-section search on the profile chi-square, p0 linear for each p1, restricted to p1 < 0
(Ei of a positive argument grows exponentially). `bfpsf.calibration.shifts_ei` solves every
boundary shift with this model's ratios and limit conditions.
"""

import numpy as np
from scipy.special import expi

from ..errors import BFPSFValueError

__all__ = ["fit_smoothing_model", "smoothing_model_area", "non_nearest_mask", "P1_LIMITS"]

# Search range of |p1| (1/pixel) for the smoothing fit: decay lengths 1/|p1| from 1000 pixels
# down to 1/2 pixel. Steeper profiles are unphysical for CCDs thicker than a pixel and make the
# ratio constraints of far boundaries vanish (the solution then runs away).
P1_LIMITS = (-2.0, -1e-3)
_LOG_P1_RANGE = (np.log10(-P1_LIMITS[1]), np.log10(-P1_LIMITS[0]))
_GRID_POINTS = 241
_GOLDEN_ITERATIONS = 60


def unit_north(dx, dy, p1):
    """a^N(dx, dy) of the model with p0 = 1: -Ei(p1 r) cos(theta), boundary centre (0, 1/2)."""
    normal = 0.5 - dy
    r = np.hypot(dx, normal)
    return -expi(p1 * r) * normal / r


def unit_east(dx, dy, p1):
    """a^E(dx, dy) of the model with p0 = 1, boundary centre (1/2, 0)."""
    return unit_north(dy, dx, p1)


def _unit_area(dx, dy, p1):
    """Model a(dx, dy) with p0 = 1 (the discrete divergence of eq. f_r, G15 eq. covar)."""
    return (unit_north(dx, dy, p1) - unit_north(dx, dy + 1, p1)
            + unit_east(dx, dy, p1) - unit_east(dx + 1, dy, p1))


def _unit_area_dp1(dx, dy, p1):
    """d(unit area)/d(p1); d Ei(p1 r)/d p1 = exp(p1 r) / p1."""
    def north(dx, dy):
        normal = 0.5 - dy
        r = np.hypot(dx, normal)
        return -np.exp(p1 * r) / p1 * normal / r

    def east(dx, dy):
        return north(dy, dx)

    return north(dx, dy) - north(dx, dy + 1) + east(dx, dy) - east(dx + 1, dy)


def smoothing_model_area(p0, p1, maxlag):
    """Area coefficients of the smoothing model, a(dx, dy) [dy, dx] for 0..maxlag, 1/e-."""
    dy, dx = np.mgrid[0:maxlag + 1, 0:maxlag + 1].astype(float)
    return p0 * _unit_area(dx, dy, p1)


def non_nearest_mask(maxlag):
    """Boolean [dy, dx] mask of the lags used in the smoothing fit.

    Every lag except (0, 0) and the three nearest neighbours (1, 0), (0, 1), (1, 1), whose
    anisotropy the radial model cannot describe (G15 section 6.1: 21 of 25 lags for n = 4).
    """
    mask = np.ones((maxlag + 1, maxlag + 1), dtype=bool)
    mask[:2, :2] = False
    return mask


def _profile_chi2(data, weights, basis):
    """chi2 minimised over p0 (linear), for data [..., P] and basis [..., P]."""
    cross = np.sum(weights * data * basis, axis=-1)
    norm = np.sum(weights * basis * basis, axis=-1)
    return np.sum(weights * data * data, axis=-1) - cross ** 2 / norm, cross / norm


class FitBasis:
    """The unit-p0 model area at the fit lags as expi at the distinct radii times a matrix.

    Every boundary distance satisfies 4 r^2 = integer, so the distinct radii are found exactly;
    evaluating expi once per distinct radius keeps the Monte Carlo fit cheap.
    """

    def __init__(self, dx, dy):
        dx = np.asarray(dx, dtype=float)
        dy = np.asarray(dy, dtype=float)
        # unit area = N(dx, dy) - N(dx, dy + 1) + E(dx, dy) - E(dx + 1, dy), E(x, y) = N(y, x),
        # N(x, y) = -expi(p1 r) (1/2 - y) / r with r = hypot(x, 1/2 - y)
        terms = [(dx, dy, 1.0), (dx, dy + 1, -1.0), (dy, dx, 1.0), (dy, dx + 1, -1.0)]
        keys, coefficients, points = [], [], []
        for x, y, sign in terms:
            normal = 0.5 - y
            radius = np.hypot(x, normal)
            keys.append(np.rint(4 * radius ** 2).astype(int))
            coefficients.append(-sign * normal / radius)
            points.append(np.arange(dx.size))
        keys = np.concatenate(keys)
        unique, inverse = np.unique(keys, return_inverse=True)
        self.radii = np.sqrt(unique / 4.0)
        self.matrix = np.zeros((dx.size, unique.size))
        np.add.at(self.matrix, (np.concatenate(points), inverse), np.concatenate(coefficients))

    def __call__(self, p1):
        """Unit-p0 model area at the fit lags, [..., P], for p1 of shape [...]."""
        p1 = np.asarray(p1, dtype=float)
        return expi(p1[..., None] * self.radii) @ self.matrix.T


def fit_p1(data, weights, basis, tolerance=1e-10):
    """Best p1 < 0 for each row of data [D, P]: grid search then golden section in log10|p1|.

    ``tolerance`` is the final bracket width in units of the grid step (0.019 in log10|p1|).
    """
    grid = np.linspace(*_LOG_P1_RANGE, _GRID_POINTS)
    chi2, _ = _profile_chi2(data[:, None, :], weights, basis(-10.0 ** grid)[None])  # [D, G]
    best = np.argmin(chi2, axis=1)
    step = grid[1] - grid[0]
    low = grid[np.clip(best - 1, 0, _GRID_POINTS - 1)]
    high = grid[np.clip(best + 1, 0, _GRID_POINTS - 1)]
    ratio = (np.sqrt(5.0) - 1.0) / 2.0

    def evaluate(q):
        return _profile_chi2(data, weights, basis(-10.0 ** q))[0]

    inner_low = high - ratio * (high - low)
    inner_high = low + ratio * (high - low)
    chi_low, chi_high = evaluate(inner_low), evaluate(inner_high)
    for _ in range(_GOLDEN_ITERATIONS):
        left = chi_low < chi_high    # minimum in [low, inner_high]
        high = np.where(left, inner_high, high)
        low = np.where(left, low, inner_low)
        # the surviving inner point becomes one of the new inner points
        kept = np.where(left, inner_low, inner_high)
        kept_chi = np.where(left, chi_low, chi_high)
        new = np.where(left, high - ratio * (high - low), low + ratio * (high - low))
        new_chi = evaluate(new)
        inner_low = np.where(left, new, kept)
        chi_low = np.where(left, new_chi, kept_chi)
        inner_high = np.where(left, kept, new)
        chi_high = np.where(left, kept_chi, new_chi)
        if np.all(high - low < tolerance * step):
            break
    return -10.0 ** (0.5 * (low + high))


def fit_smoothing_model(area, area_err=None):
    """Fit f(r) = p0 Ei(p1 r) (G15 eq. f_r) to the non-nearest area coefficients.

    Parameters
    ----------
    area : array_like, shape (n + 1, n + 1)
        a(dx, dy), [dy, dx], 1/e-; n >= 2.
    area_err : array_like, optional
        1-sigma errors (1/e-). Without them the fit is unweighted and the parameter errors are
        scaled by chi2/dof.

    Returns
    -------
    p0, p1, p0_err, p1_err, chi2, dof : float, float, float, float, float, int
        a^X = -p0 Ei(p1 r) cos(theta); p1 < 0.
    """
    area, area_err = validate_area(area, area_err)
    return fit_profile(area, area_err)


def fit_profile(area, area_err):
    """`fit_smoothing_model` on a validated area: (p0, p1, p0_err, p1_err, chi2, dof)."""
    n = area.shape[0] - 1
    mask = non_nearest_mask(n)
    dy, dx = np.nonzero(mask)
    dx, dy = dx.astype(float), dy.astype(float)
    data = area[mask]
    weights = np.ones_like(data) if area_err is None else 1.0 / area_err[mask] ** 2
    p1 = float(fit_p1(data[None, :], weights, FitBasis(dx, dy))[0])
    basis = _unit_area(dx, dy, p1)
    p0 = float(_profile_chi2(data, weights, basis)[1])
    chi2 = float(np.sum(weights * (data - p0 * basis) ** 2))
    dof = data.size - 2
    jacobian = np.stack([basis, p0 * _unit_area_dp1(dx, dy, p1)], axis=1)
    scale = chi2 / dof if area_err is None and dof > 0 else 1.0
    curvature = jacobian.T @ (weights[:, None] * jacobian)
    diagonal = np.sqrt(np.diag(curvature))
    variances = None
    normalised = curvature / np.outer(diagonal, diagonal) if np.all(diagonal > 0) else None
    if normalised is not None and np.linalg.cond(normalised) < 1e12:
        # invert the normalised matrix: a denormal curvature (a tail of 1e-165) is singular to
        # np.linalg.inv although its normalised form is well conditioned
        with np.errstate(over="ignore", divide="ignore"):
            variances = np.diag(np.linalg.inv(normalised)) / diagonal ** 2 * scale
    if variances is not None and np.all(variances > 0):
        p0_err, p1_err = np.sqrt(variances)
    else:
        # p0 = 0 (no signal beyond the nearest neighbours, or a signal of 1e-166 whose
        # inverse curvature rounds negative): p1 is not constrained at all
        p0_err = float(np.sqrt(scale / curvature[0, 0]))
        p1_err = np.inf
    return p0, p1, float(p0_err), float(p1_err), float(chi2), int(dof)


def validate_area(area, area_err):
    area = np.array(area, dtype=float)
    if area.ndim != 2 or area.shape[0] != area.shape[1]:
        msg = f"area must be a square 2-D array a[dy, dx] for lags 0..n, got shape {area.shape}"
        raise BFPSFValueError(msg, area.shape)
    if area.shape[0] < 3:
        msg = (f"area must cover lags 0..n with n >= 2 (the smoothing fit needs non-nearest "
               f"neighbours), got shape {area.shape}")
        raise BFPSFValueError(msg, area.shape)
    bad = np.count_nonzero(~np.isfinite(area))
    if bad:
        msg = f"area contains {bad} non-finite values"
        raise BFPSFValueError(msg, bad)
    if not area[0, 0] < 0:
        msg = (f"area a(0, 0) must be negative (a charge shrinks its own pixel), "
               f"got {area[0, 0]:.4g}")
        raise BFPSFValueError(msg, area[0, 0])
    if area_err is not None:
        area_err = np.array(area_err, dtype=float)
        if area_err.shape != area.shape:
            msg = f"area_err must have the shape of area {area.shape}, got {area_err.shape}"
            raise BFPSFValueError(msg, area_err.shape)
        if not np.all(np.isfinite(area_err)) or np.any(area_err <= 0):
            worst = area_err[~(np.isfinite(area_err) & (area_err > 0))].flat[0]
            msg = f"area_err must be finite and positive, got {worst}"
            raise BFPSFValueError(msg, worst)
        area_err.flags.writeable = False
    area.flags.writeable = False
    return area, area_err
