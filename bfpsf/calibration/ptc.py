"""Photon transfer curve (PTC) fits: gain, read noise and area coefficients a(dx, dy).

Three models of the flat-field covariances C(dx, dy) against the mean signal mu, all fitted
below a turnoff detected from the data:

``'quadratic'``
    G15 section 4.3.2: V = -alpha N^2 + N / G + const (ADU), so a(0, 0) = -alpha; the other
    a(dx, dy) are the first-order slopes of R(dx, dy) = C(dx, dy) / V against mu in electrons
    (G15 eq. covar).
``'exponential'``
    Astier et al. 2019 (A+19) eq. 16: C00 = (exp(2 a00 g mu) - 1) / (2 g^2 a00) + n00 / g^2,
    mu in ADU, g in e-/ADU; other a(dx, dy) as for ``'quadratic'``.
``'full'`` (default)
    A+19 eq. 20, fitted to every lag at once::

        C_ij = mu/g [delta_ij + a_ij mu g + 2/3 (a*a + ab)_ij (mu g)^2
                     + 1/6 (2 a*a*a + 5 a*ab)_ij (mu g)^3] + n_ij / g^2

    where * is a 2-D convolution over the full plane of lags; the a-only part is summed to
    `SERIES_ORDER` powers of a (the exact b = 0 solution, of which A+19 print three terms:
    stopping there biases a(0, 0) by 1 % at a00 mu = -0.33). It removes the first-order bias:
    on a thick sensor a00 mu is about -0.2 at 100 ke-, and the slope of C / (V mu) then misses
    a00 by about 13 % and the gain by about 1 %. The ``b`` term absorbs the flux dependence of
    a itself (GalSim's SiliconSensor a(1, 0) of lsst_e2v_50_8 falls by a third between 0 and
    1e5 e-), so the fitted ``a`` is the zero-flux response.

Covariances are single-image covariances in ADU^2 indexed [dy, dx] (quadrant averaged), as
`bfpsf.calibration.covariance.pair_covariance` returns them.
"""

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize

from ..errors import BFPSFInputError, BFPSFValueError

__all__ = [
    "PTC_MODELS",
    "PTCData",
    "PTCFit",
    "stack_pairs",
    "covariance_errors",
    "detect_turnoff",
    "fit_quadratic_ptc",
    "fit_exponential_ptc",
    "fit_full_covariance_model",
    "B_CHOICES",
    "SERIES_ORDER",
    "full_covariance_model",
    "fit_ptc",
    "ptc_table",
    "summed_covariance_ptc",
]

#: Names accepted by `fit_ptc` (``model=``).
PTC_MODELS = ("full", "exponential", "quadratic")

# Parameter scales of the full-model fit, so that the optimiser sees numbers of order one.
_A_SCALE = 1e-6     # 1/e-
_C_SCALE = 1e-12    # 1/e-^2


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
# ---------------------------------------------------------------------------------------------
def detect_turnoff(mean_adu, var_adu, var_err, *, nsigma=3.0):
    """Pairs below the PTC extremum (G15 section 4.3.2), found from the data.

    The variance maximum is located; pairs at a higher mean whose variance lies more than
    ``nsigma`` errors below it are past the turnoff, and so is every pair above the first of them.
    If the variance never falls significantly, every pair is kept (no turnoff in the data).

    Parameters
    ----------
    mean_adu, var_adu, var_err : ndarray (n,)
        Mean (ADU), single-image variance and its error (ADU^2).
    nsigma : float, optional
        Significance of the fall. Default 3.

    Returns
    -------
    used : ndarray of bool (n,)
        True below the turnoff.
    detected : bool
        True if a turnoff was found inside the data.
    """
    mean_adu = np.asarray(mean_adu, dtype=float)
    var_adu = np.asarray(var_adu, dtype=float)
    finite = np.isfinite(mean_adu) & np.isfinite(var_adu)
    used = finite.copy()
    if not finite.any():
        return used, False
    peak = np.nanargmax(np.where(finite, var_adu, -np.inf))
    fallen = finite & (mean_adu > mean_adu[peak]) & (
        var_adu < var_adu[peak] - nsigma * np.asarray(var_err)[peak])
    if not fallen.any():
        return used, False
    first_fallen = mean_adu[fallen].min()
    used &= mean_adu < first_fallen
    return used, True


# ---------------------------------------------------------------------------------------------
# G15 quadratic and A+19 exponential fits of the variance
# ---------------------------------------------------------------------------------------------
def _weighted_polyfit(x, y, sigma, degree):
    """Weighted least squares of y = sum_k p_k x^k; returns p (low order first), cov, chi2."""
    design = np.vander(x, degree + 1, increasing=True) / sigma[:, None]
    target = y / sigma
    params, *_ = np.linalg.lstsq(design, target, rcond=None)
    covariance = np.linalg.inv(design.T @ design)
    chi2 = float(np.sum((design @ params - target) ** 2))
    return params, covariance, chi2


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
    params, cov, chi2 = _weighted_polyfit(mean_adu, var_adu, var_err, 2)
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


def _exponential_variance(mean_adu, a00, gain, noise_e2):
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
    start = np.array([initial["a00"] / _A_SCALE, gain0, max(initial.get("read_var_adu", 0.0), 0.0)
                      * gain0**2])

    def residuals(p):
        return (_exponential_variance(mean_adu, p[0] * _A_SCALE, p[1], p[2]) - var_adu) / var_err

    result = scipy.optimize.least_squares(residuals, start, method="lm", x_scale="jac")
    covariance, chi2, ndof = _parameter_covariance(result, mean_adu.size)
    errors = np.sqrt(np.diag(covariance))
    return {
        "gain": float(result.x[1]), "gain_err": float(errors[1]),
        "a00": float(result.x[0] * _A_SCALE), "a00_err": float(errors[0] * _A_SCALE),
        "noise_e2": float(result.x[2]), "noise_e2_err": float(errors[2]),
        "chi2": chi2, "ndof": ndof,
    }


def _parameter_covariance(result, ndata):
    """Covariance of least-squares parameters, scaled up by chi2/ndof when that exceeds 1."""
    jac = result.jac
    chi2 = float(np.sum(result.fun**2))
    ndof = int(ndata - jac.shape[1])
    covariance = np.linalg.pinv(jac.T @ jac)
    if ndof > 0 and chi2 > ndof:
        covariance = covariance * (chi2 / ndof)
    return covariance, chi2, ndof


def _first_order_slopes(mean_e, cov_adu, npix):
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
            params, cov, _ = _weighted_polyfit(mean_e, correlation[:, dy, dx],
                                               corr_err[:, dy, dx], 1)
            intercept[dy, dx], slope[dy, dx] = params
            intercept_err[dy, dx], slope_err[dy, dx] = np.sqrt(np.diag(cov))
    return slope, slope_err, intercept, intercept_err


# ---------------------------------------------------------------------------------------------
# A+19 full covariance model (eq. 20)
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _convolution_tensor(nlag):
    """W[q, r, s] such that quadrant(full(x) * full(y))[q] = sum_rs W[q, r, s] x[s] y[r].

    q, r, s index the flattened [dy, dx] quadrant 0..nlag-1; the full plane of lags mirrors the
    quadrant (C(dx, dy) = C(|dx|, |dy|)), and lags beyond nlag - 1 are zero, as in A+19.
    """
    offsets = np.arange(-(nlag - 1), nlag)
    tensor = np.zeros((nlag * nlag, nlag * nlag, nlag * nlag))
    for qy in range(nlag):
        for qx in range(nlag):
            for uy in offsets:
                for ux in offsets:
                    vy, vx = qy - uy, qx - ux
                    if abs(vy) < nlag and abs(vx) < nlag:
                        tensor[qy * nlag + qx, abs(vy) * nlag + abs(vx),
                               abs(uy) * nlag + abs(ux)] += 1.0
    tensor.flags.writeable = False
    return tensor


def _convolution_matrix(x):
    """Matrix of y -> quadrant(full(x) * full(y)) on flattened quadrants."""
    nlag = x.shape[0]
    return _convolution_tensor(nlag) @ x.ravel()


#: Powers of a summed in the full model. A+19 eq. 20 stops at a*a*a (mu^4); the b = 0 build-up
#: dC/dmu = 1 + 2 a*C has the exact solution C = sum_n (2 mu)^n a^{*n} mu / (n + 1)!, and at
#: a00 mu = -0.33 (ITL at 300 ke-, E2V at 150 ke-) stopping at n = 3 biases a(0, 0) by 1 % and
#: the gain by 0.07 %; n = 6 leaves < 1e-5 of the variance.
SERIES_ORDER = 6


def _series_coefficients(order):
    """2^n / (n + 1)! for n = 1..order (1, 2/3, 1/3, 2/15, ...)."""
    return [2.0**n / math.factorial(n + 1) for n in range(1, order + 1)]


def _powers(a, order):
    """Flattened a^{*n}, n = 1..order, and the convolution matrix of a."""
    conv_a = _convolution_matrix(a)
    powers = [a.ravel()]
    for _ in range(order - 1):
        powers.append(conv_a @ powers[-1])
    return powers, conv_a


def _model_electrons(mean_e, a, c, order):
    """Noise-free covariances in e-^2, [pair, flattened lag], and d/dmu of them."""
    nsq = a.size
    powers, conv_a = _powers(a, order)
    ac = conv_a @ c.ravel()
    delta = np.zeros(nsq)
    delta[0] = 1.0
    mu = mean_e[:, None]
    model = mu * delta + 2.0 / 3.0 * mu**3 * c.ravel() + 5.0 / 6.0 * mu**4 * ac
    slope = delta + 2.0 * mu**2 * c.ravel() + 10.0 / 3.0 * mu**3 * ac
    for n, (coefficient, power) in enumerate(zip(_series_coefficients(order), powers), start=1):
        model = model + coefficient * mu ** (n + 1) * power
        slope = slope + coefficient * (n + 1) * mu**n * power
    return model, slope, powers, conv_a


def full_covariance_model(mean_adu, a, c, noise_e2, gain, *, order=SERIES_ORDER):
    """A+19 eq. 20: covariances C(dx, dy) in ADU^2, shape (n, L, L).

    The a-only part is summed to ``order`` powers of a (A+19 print three: a, 2/3 a*a,
    1/3 a*a*a); the b part is theirs, 2/3 ab mu^3 + 5/6 a*ab mu^4.

    Parameters
    ----------
    mean_adu : array_like (n,)
        Mean signals, ADU.
    a : ndarray (L, L)
        Area coefficients a(dx, dy), 1/e-, indexed [dy, dx].
    c : ndarray (L, L)
        The product a b of A+19, 1/e-^2 (zero for the b = 0 model).
    noise_e2 : ndarray (L, L)
        Zero-flux covariances n(dx, dy), e-^2 (n00 is the read-noise variance).
    gain : float
        e-/ADU.
    order : int, optional
        Powers of a summed. Default `SERIES_ORDER`; 3 is A+19 eq. 20 as printed.
    """
    a = np.asarray(a, dtype=float)
    nlag = a.shape[0]
    mean_e = np.asarray(mean_adu, dtype=float) * gain
    model, _, _, _ = _model_electrons(mean_e, a, np.asarray(c, dtype=float), order)
    return (model + np.ravel(noise_e2)).reshape(-1, nlag, nlag) / gain**2


def _full_model_jacobian(mean_adu, a, c, noise_e2, gain, b_mask, order=SERIES_ORDER):
    """d C_ADU / d (a, c[b_mask], n, gain): blocks [pair, lag, parameter]."""
    nsq = a.size
    mean_adu = np.asarray(mean_adu, dtype=float)
    mean_e = mean_adu * gain
    model, slope, powers, conv_a = _model_electrons(mean_e, a, c, order)
    conv_c = _convolution_matrix(c)
    identity = np.eye(nsq)
    mu = mean_e[:, None, None]
    scale = 1.0 / gain**2
    # a^{*n} = Conv(a) a^{*(n-1)} truncated at maxlag, so (Conv symmetric in its arguments)
    # d a^{*n}/da = Conv(a) d a^{*(n-1)}/da + Conv(a^{*(n-1)}), starting from the identity
    jac_a = 5.0 / 6.0 * mu**4 * conv_c
    d_power = identity
    for n, coefficient in enumerate(_series_coefficients(order), start=1):
        if n > 1:
            d_power = conv_a @ d_power + _convolution_tensor(a.shape[0]) @ powers[n - 2]
        jac_a = jac_a + coefficient * mu ** (n + 1) * d_power
    jac_a = jac_a * scale
    jac_c = (2.0 / 3.0 * mu**3 * identity + 5.0 / 6.0 * mu**4 * conv_a)[:, :, b_mask.ravel()]
    jac_c = jac_c * scale
    jac_n = np.broadcast_to(identity * scale, (mean_e.size, nsq, nsq))
    # C_ADU = (M_e(g m) + n) / g^2: dC/dg = m M_e'(mu) / g^2 - 2 (M_e + n) / g^3
    jac_g = (mean_adu[:, None] * slope - 2.0 * (model + np.ravel(noise_e2)) / gain) * scale
    return jac_a, jac_c, jac_n, jac_g


#: Choices of the lags whose A+19 b is fitted (`fit_full_covariance_model`, ``fit_b=``).
B_CHOICES = ("off-origin", "all", "none")


def _b_mask(fit_b, nlag):
    """Boolean [dy, dx] mask of the lags whose b (c = a b) is a free parameter."""
    if fit_b is True:
        fit_b = "all"
    elif fit_b is False or fit_b is None:
        fit_b = "none"
    if fit_b not in B_CHOICES:
        msg = f"fit_b must be one of {B_CHOICES} (or True / False), got {fit_b!r}"
        raise BFPSFValueError(msg, fit_b)
    mask = np.full((nlag, nlag), fit_b != "none")
    if fit_b == "off-origin":
        mask[0, 0] = False
    return mask


def fit_full_covariance_model(mean_adu, cov_adu, cov_err, *, fit_b="off-origin",
                              initial_gain=None, systematics=()):
    """Fit A+19 eq. 20 to every lag at once.

    Parameters
    ----------
    mean_adu : ndarray (n,)
        Means of the pairs below the turnoff, ADU.
    cov_adu, cov_err : ndarray (n, L, L)
        Covariances and their errors, ADU^2.
    fit_b : {'off-origin', 'all', 'none'} or bool, optional
        Lags whose b term (the flux dependence of a) is fitted. Default ``'off-origin'``: b(0, 0)
        only enters the mu^3 term of the variance, where it is nearly degenerate with a(0, 0)
        and the gain (freeing it costs a factor 5 in their precision on a 10-pair PTC), and the
        self-response a(0, 0) hardly depends on the flux (0.3 % between 0 and 1e5 e- for
        GalSim's ITL and E2V sensors), while a(1, 0) of the E2V sensor falls by a third. True
        means 'all', False 'none'.
    initial_gain : float, optional
        Starting gain, e-/ADU (default: from the G15 quadratic fit).
    systematics : sequence of (ndarray (n, L, L), float), optional
        Uncertain corrections already applied to ``cov_adu``: a direction in the data (ADU^2)
        and its 1-sigma amplitude (e.g. a subtracted readout pedestal: the variance at one lag,
        times the pedestal error). Their effect on the parameters, to first order, is added
        to the parameter covariance.

    Returns
    -------
    dict
        ``a``, ``a_err`` (1/e-), ``a_cov`` (covariance of ``a.ravel()``, 1/e-^2), ``b``,
        ``b_err`` (1/e-; b = c / a, 0 where not fitted), ``c``, ``c_err`` (1/e-^2),
        ``noise_e2``, ``noise_e2_err`` (e-^2), ``gain``, ``gain_err`` (e-/ADU), ``chi2``,
        ``ndof``. Errors are scaled by sqrt(chi2/ndof) when that exceeds 1.
    """
    mean_adu = np.asarray(mean_adu, dtype=float)
    cov_adu = np.asarray(cov_adu, dtype=float)
    cov_err = np.asarray(cov_err, dtype=float)
    npairs, nlag = cov_adu.shape[0], cov_adu.shape[1]
    b_mask = _b_mask(fit_b, nlag)
    nb = int(b_mask.sum())
    needed = 4 if nb else 3
    if npairs < needed:
        msg = (f"the full covariance model {'with' if nb else 'without'} b needs at least "
               f"{needed} pairs below the turnoff, got {npairs}")
        raise BFPSFInputError(msg, npairs)
    if initial_gain is None:
        initial_gain = fit_quadratic_ptc(mean_adu, cov_adu[:, 0, 0], cov_err[:, 0, 0])["gain"]
    gain0 = initial_gain
    # Starting point: per-lag polynomial n + a mu^2 (+ k mu^3 where b is free), electrons.
    mean_e = mean_adu * gain0
    cov_e = cov_adu * gain0**2
    err_e = cov_err * gain0**2
    shot = np.zeros_like(cov_e)
    shot[:, 0, 0] = mean_e
    a0 = np.zeros((nlag, nlag))
    noise0 = np.zeros((nlag, nlag))
    for dy in range(nlag):
        for dx in range(nlag):
            degree = 3 if (b_mask[dy, dx] and npairs >= 4) else 2
            design = np.vander(mean_e, degree + 1, increasing=True)
            design = np.delete(design, 1, axis=1) / err_e[:, dy, dx][:, None]
            target = (cov_e[:, dy, dx] - shot[:, dy, dx]) / err_e[:, dy, dx]
            params, *_ = np.linalg.lstsq(design, target, rcond=None)
            noise0[dy, dx], a0[dy, dx] = params[0], params[1]
    nsq = nlag * nlag
    start = np.concatenate([a0.ravel() / _A_SCALE, np.zeros(nb), noise0.ravel(), [gain0]])
    weight = 1.0 / cov_err

    def unpack(p):
        a = p[:nsq].reshape(nlag, nlag) * _A_SCALE
        c = np.zeros((nlag, nlag))
        c[b_mask] = p[nsq:nsq + nb] * _C_SCALE
        noise = p[nsq + nb:2 * nsq + nb].reshape(nlag, nlag)
        return a, c, noise, p[-1]

    def residuals(p):
        a, c, noise, gain = unpack(p)
        return ((full_covariance_model(mean_adu, a, c, noise, gain) - cov_adu) * weight).ravel()

    flat_weight = weight.reshape(npairs, nsq)

    def jacobian(p):
        a, c, noise, gain = unpack(p)
        jac_a, jac_c, jac_n, jac_g = _full_model_jacobian(mean_adu, a, c, noise, gain, b_mask)
        blocks = [jac_a * _A_SCALE, jac_c * _C_SCALE, jac_n, jac_g[:, :, None]]
        return np.concatenate([block * flat_weight[:, :, None] for block in blocks],
                              axis=2).reshape(npairs * nsq, -1)

    result = scipy.optimize.least_squares(residuals, start, jac=jacobian, method="lm",
                                          x_scale="jac")
    covariance, chi2, ndof = _parameter_covariance(result, cov_adu.size)
    if len(systematics):
        normal = np.linalg.pinv(result.jac.T @ result.jac)
        for direction, sigma in systematics:
            # parameter shift per unit of the direction (linearised least squares)
            response = normal @ (result.jac.T @ (np.asarray(direction) * weight).ravel())
            covariance = covariance + sigma**2 * np.outer(response, response)
    errors = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    a, c, noise, gain = unpack(result.x)
    a_err, c_err, noise_err, gain_err = unpack(errors)
    with np.errstate(divide="ignore", invalid="ignore"):
        safe_a = np.where(a != 0, a, np.inf)
        b = np.where(b_mask, c / safe_a, 0.0)
        b_err = np.where(b_mask, np.hypot(c_err / safe_a, c * a_err / safe_a**2), 0.0)
    a_cov = covariance[:nsq, :nsq] * _A_SCALE**2
    return {
        "a": a, "a_err": a_err, "a_cov": a_cov, "b": b, "b_err": b_err, "c": c, "c_err": c_err,
        "noise_e2": noise, "noise_e2_err": noise_err,
        "gain": float(gain), "gain_err": float(gain_err), "chi2": chi2, "ndof": ndof,
    }


# ---------------------------------------------------------------------------------------------
# the result and the driver
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PTCFit:
    """Result of `fit_ptc`.

    Attributes
    ----------
    model : str
        One of `PTC_MODELS`.
    gain, gain_err : float
        e-/ADU.
    noise_e, noise_e_err : float
        Read noise, e- rms (sqrt of n00; 0 if the fitted n00 is negative).
    a, a_err : ndarray [dy, dx]
        Area coefficients a(dx, dy), 1/e-.
    b, b_err : ndarray [dy, dx]
        A+19 b coefficients, 1/e- (zero unless ``model='full'``).
    noise_matrix_e2 : ndarray [dy, dx]
        Zero-flux covariances n(dx, dy), e-^2 (only n00 outside the full model).
    turnoff_adu, turnoff_e : float
        Mean signal of the brightest pair used in the fit (ADU, e-).
    turnoff_detected : bool
        True if the PTC extremum was found inside the data (pairs above it excluded).
    used : ndarray of bool (n,)
        Pairs used in the fit, in input order.
    chi2, ndof : float, int
        Goodness of the fit of the chosen model.
    quadratic : dict
        The G15 quadratic fit (always done: gain, alpha, a00 with errors).
    a_cov : ndarray (L*L, L*L) or None
        Covariance of ``a.ravel()`` (full model only), 1/e-^2.
    """

    model: str
    gain: float
    gain_err: float
    noise_e: float
    noise_e_err: float
    a: np.ndarray
    a_err: np.ndarray
    b: np.ndarray
    b_err: np.ndarray
    noise_matrix_e2: np.ndarray
    turnoff_adu: float
    turnoff_e: float
    turnoff_detected: bool
    used: np.ndarray
    chi2: float
    ndof: int
    quadratic: dict = field(default_factory=dict)
    a_cov: np.ndarray = None

    @property
    def maxlag(self):
        return self.a.shape[0] - 1


def _noise_from_variance(noise_e2, noise_e2_err):
    noise = float(np.sqrt(max(noise_e2, 0.0)))
    error = float(noise_e2_err / (2 * noise)) if noise > 0 else float(np.sqrt(max(noise_e2_err, 0)))
    return noise, error


def fit_ptc(data, *, model="full", turnoff_nsigma=3.0, model_fail_nsigma=5.0,
            fit_b="off-origin", pedestal=None):
    """Fit the photon transfer curve and the covariances of flat pairs.

    Parameters
    ----------
    data : PTCData or sequence of PairCovariance
        Per-pair means and covariances (ADU). Subtract a readout pedestal first
        (`bfpsf.calibration.pedestal.subtract_pedestal`).
    model : {'full', 'exponential', 'quadratic'}, optional
        See the module docstring. Default ``'full'`` (A+19 eq. 20), the model without the
        first-order bias.
    turnoff_nsigma : float, optional
        Significance of the variance fall that marks the PTC extremum (`detect_turnoff`).
    model_fail_nsigma : float, optional
        After the extremum cut, the brightest pairs are dropped one at a time while their
        variance departs from the A+19 exponential PTC (eq. 16) by more than this many errors
        (the PTC bends down before its extremum as the wells fill). Default 5.
    fit_b : {'off-origin', 'all', 'none'} or bool, optional
        Lags whose A+19 b term is fitted in the full model (`fit_full_covariance_model`).
        Default ``'off-origin'``.
    pedestal : Pedestal, optional
        The readout pedestal already subtracted from ``data``; in the full model the errors of
        its detected lags are propagated into the parameter errors.

    Returns
    -------
    PTCFit
    """
    if model not in PTC_MODELS:
        msg = f"model must be one of {PTC_MODELS}, got {model!r}"
        raise BFPSFValueError(msg, model)
    if not isinstance(data, PTCData):
        data = stack_pairs(data)
    cov_err = covariance_errors(data.cov_adu, data.npix)
    var_err = cov_err[:, 0, 0]
    used, detected = detect_turnoff(data.mean_adu, data.var_adu, var_err, nsigma=turnoff_nsigma)
    quadratic = fit_quadratic_ptc(data.mean_adu[used], data.var_adu[used], var_err[used])
    # "Where the model fails": drop the brightest pair while its variance departs from the
    # A+19 exponential PTC by more than model_fail_nsigma (a quadratic would fail early on a
    # thick sensor, where the mu^3 term of the variance is several sigma by 100 ke-).
    while used.sum() > 4:
        exponential = fit_exponential_ptc(data.mean_adu[used], data.var_adu[used],
                                          var_err[used], initial=quadratic)
        brightest = np.flatnonzero(used)[np.argmax(data.mean_adu[used])]
        predicted = _exponential_variance(data.mean_adu[brightest], exponential["a00"],
                                          exponential["gain"], exponential["noise_e2"])
        if abs(data.var_adu[brightest] - predicted) <= model_fail_nsigma * var_err[brightest]:
            break
        used[brightest] = False
        detected = True
        quadratic = fit_quadratic_ptc(data.mean_adu[used], data.var_adu[used], var_err[used])
    # Weights from a smooth model of the variance, not the noisy measured one.
    smooth = fit_exponential_ptc(data.mean_adu[used], data.var_adu[used], var_err[used],
                                 initial=quadratic)
    variance_model = np.where(used, _exponential_variance(data.mean_adu, smooth["a00"],
                                                          smooth["gain"], smooth["noise_e2"]),
                              data.var_adu)
    cov_err = covariance_errors(data.cov_adu, data.npix, variance_model)
    var_err = cov_err[:, 0, 0]
    quadratic = fit_quadratic_ptc(data.mean_adu[used], data.var_adu[used], var_err[used])

    mean_adu = data.mean_adu[used]
    cov_adu = data.cov_adu[used]
    nlag = cov_adu.shape[1]
    noise_matrix = np.zeros((nlag, nlag))
    b = np.zeros((nlag, nlag))
    b_err = np.zeros((nlag, nlag))
    a_cov = None
    if model == "full":
        systematics = []
        if pedestal is not None:
            # a subtracted pedestal p V is uncertain by sigma_p V: propagate into the errors
            for dy, dx in zip(*np.nonzero(pedestal.detected)):
                direction = np.zeros_like(cov_adu)
                direction[:, dy, dx] = data.var_adu[used]
                systematics.append((direction, float(pedestal.error[dy, dx])))
        fit = fit_full_covariance_model(mean_adu, cov_adu, cov_err[used], fit_b=fit_b,
                                        initial_gain=quadratic["gain"], systematics=systematics)
        gain, gain_err = fit["gain"], fit["gain_err"]
        a, a_err = fit["a"], fit["a_err"]
        b, b_err = fit["b"], fit["b_err"]
        noise_matrix = fit["noise_e2"]
        a_cov = fit["a_cov"]
        noise_e, noise_e_err = _noise_from_variance(noise_matrix[0, 0], fit["noise_e2_err"][0, 0])
        chi2, ndof = fit["chi2"], fit["ndof"]
    else:
        if model == "quadratic":
            gain, gain_err = quadratic["gain"], quadratic["gain_err"]
            a00, a00_err = quadratic["a00"], quadratic["a00_err"]
            noise_e2 = quadratic["read_var_adu"] * gain**2
            noise_e2_err = quadratic["read_var_err"] * gain**2
            chi2, ndof = quadratic["chi2"], quadratic["ndof"]
        else:
            fit = fit_exponential_ptc(mean_adu, cov_adu[:, 0, 0], cov_err[used][:, 0, 0],
                                      initial=quadratic)
            gain, gain_err = fit["gain"], fit["gain_err"]
            a00, a00_err = fit["a00"], fit["a00_err"]
            noise_e2, noise_e2_err = fit["noise_e2"], fit["noise_e2_err"]
            chi2, ndof = fit["chi2"], fit["ndof"]
        a, a_err, _, _ = _first_order_slopes(mean_adu * gain, cov_adu, data.npix[used])
        a[0, 0], a_err[0, 0] = a00, a00_err
        noise_matrix[0, 0] = noise_e2
        noise_e, noise_e_err = _noise_from_variance(noise_e2, noise_e2_err)
    turnoff_adu = float(mean_adu.max())
    for array in (a, a_err, b, b_err, noise_matrix):
        array.flags.writeable = False
    used.flags.writeable = False
    return PTCFit(model=model, gain=float(gain), gain_err=float(gain_err), noise_e=noise_e,
                  noise_e_err=noise_e_err, a=a, a_err=a_err, b=b, b_err=b_err,
                  noise_matrix_e2=noise_matrix, turnoff_adu=turnoff_adu,
                  turnoff_e=turnoff_adu * float(gain), turnoff_detected=bool(detected),
                  used=used, chi2=float(chi2), ndof=int(ndof), quadratic=quadratic,
                  a_cov=a_cov)


# ---------------------------------------------------------------------------------------------
# tables and the G15 appendix A check
# ---------------------------------------------------------------------------------------------
def _summed_covariances(cov, maxlag=None):
    """Sum of C over the full plane of lags |dx|, |dy| <= maxlag, without C00."""
    nlag = cov.shape[-1] if maxlag is None else int(maxlag) + 1
    quadrant = cov[..., :nlag, :nlag]
    weights = np.full((nlag, nlag), 4.0)
    weights[0, :] = 2.0
    weights[:, 0] = 2.0
    weights[0, 0] = 0.0
    return np.sum(quadrant * weights, axis=(-2, -1))


def ptc_table(data, gain, used=None):
    """Per-pair PTC table (astropy Table) with units.

    Columns: ``exptime`` (s), ``mean_adu``, ``mean_e`` (e-), ``var_adu``, ``var_e`` (e-^2),
    ``cov10_adu``,
    ``cov01_adu``, ``cov11_adu`` (C(dx=1, dy=0) etc., ADU^2), ``sum_cov_adu`` (sum of the
    covariances over the full plane of lags up to maxlag, C00 excluded), ``npix`` (pixel
    products at lag 0), ``used`` (in the PTC fit).
    """
    from astropy.table import Table

    if not isinstance(data, PTCData):
        data = stack_pairs(data)
    n = data.mean_adu.size
    used = np.ones(n, dtype=bool) if used is None else np.asarray(used, dtype=bool)
    cov = data.cov_adu
    nlag = cov.shape[1]
    lag = (lambda dy, dx: cov[:, dy, dx] if max(dx, dy) < nlag else np.full(n, np.nan))
    table = Table()
    table["exptime"] = data.exptime
    table["exptime"].unit = "s"
    table["mean_adu"] = data.mean_adu
    table["mean_adu"].unit = "adu"
    # FITS has no electron unit: electron columns say so in their description.
    table["mean_e"] = data.mean_adu * gain
    table["mean_e"].description = "electron"
    table["var_adu"] = data.var_adu
    table["var_adu"].unit = "adu2"
    table["var_e"] = data.var_adu * gain**2
    table["var_e"].description = "electron^2"
    for name, (dy, dx) in (("cov10_adu", (0, 1)), ("cov01_adu", (1, 0)), ("cov11_adu", (1, 1))):
        table[name] = lag(dy, dx)
        table[name].unit = "adu2"
    table["sum_cov_adu"] = _summed_covariances(cov)
    table["sum_cov_adu"].unit = "adu2"
    table["npix"] = data.npix[:, 0, 0].astype(np.int64)
    table["used"] = used
    return table


def summed_covariance_ptc(data, gain, *, maxlag=None, used=None):
    """G15 appendix A: variance plus the covariances summed back, against the mean (e-).

    Charge conservation makes the sum of all covariances the Poisson variance, so V + sum C
    grows linearly with slope 1 (in electrons) even where the raw PTC bends. Truncating the sum
    at ``maxlag`` slightly underestimates it (G15: 0.5 % at 4 pixels).

    Parameters
    ----------
    data : PTCData or sequence of PairCovariance
    gain : float
        e-/ADU.
    maxlag : int, optional
        Largest |dx|, |dy| summed. Default: every lag measured.
    used : array of bool, optional
        Pairs to include in the slope fits (default all).

    Returns
    -------
    dict
        ``mean_e``, ``var_e`` (raw variance), ``summed_e`` (V + sum C, e-^2), ``slope_summed``
        and ``slope_summed_err`` (the summed PTC's slope through the read-noise intercept,
        1 for Poisson), ``slope_raw`` (the same for the raw variance), and
        ``max_frac_deviation`` (largest |summed / (mu + n) - 1| with n the intercept).
    """
    if not isinstance(data, PTCData):
        data = stack_pairs(data)
    used = np.ones(data.mean_adu.size, dtype=bool) if used is None else np.asarray(used, bool)
    mean_e = data.mean_adu * gain
    var_e = data.var_adu * gain**2
    summed_e = var_e + _summed_covariances(data.cov_adu, maxlag) * gain**2
    nlag = data.cov_adu.shape[1] if maxlag is None else int(maxlag) + 1
    # Shot-noise error of the sum, lags taken as independent (each weighted by its multiplicity).
    npix = data.npix[:, 0, 0]
    lag_err = covariance_errors(data.cov_adu, data.npix)[:, :nlag, :nlag] * gain**2
    weights = np.full((nlag, nlag), 4.0)
    weights[0, :] = 2.0
    weights[:, 0] = 2.0
    weights[0, 0] = 1.0
    summed_err = np.sqrt(np.sum((weights * lag_err) ** 2, axis=(-2, -1)))
    params, cov, _ = _weighted_polyfit(mean_e[used], summed_e[used], summed_err[used], 1)
    raw_params, _, _ = _weighted_polyfit(mean_e[used], var_e[used],
                                         var_e[used] * np.sqrt(2.0 / npix[used]), 1)
    linear = params[0] + mean_e
    return {
        "mean_e": mean_e, "var_e": var_e, "summed_e": summed_e, "summed_err_e": summed_err,
        "slope_summed": float(params[1]), "slope_summed_err": float(np.sqrt(cov[1, 1])),
        "intercept_e2": float(params[0]), "slope_raw": float(raw_params[1]),
        "max_frac_deviation": float(np.max(np.abs(summed_e[used] / linear[used] - 1.0))),
    }
