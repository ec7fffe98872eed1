"""The A+19 full covariance model (Astier et al. 2019 eq. 20), fitted to every lag at once::

    C_ij = mu/g [delta_ij + a_ij mu g + 2/3 (a*a + ab)_ij (mu g)^2
                 + 1/6 (2 a*a*a + 5 a*ab)_ij (mu g)^3] + n_ij / g^2

where * is a 2-D convolution over the full plane of lags; the a-only part is summed to
`SERIES_ORDER` powers of a (the exact b = 0 solution). See `bfpsf.calibration.ptc`.
"""

import functools
import math

import numpy as np
import scipy.optimize

from ..errors import BFPSFInputError, BFPSFValueError
from .ptc_variance import A_SCALE, fit_quadratic_ptc, parameter_covariance

__all__ = ["B_CHOICES", "SERIES_ORDER", "MAX_FULL_MODEL_MAXLAG", "MIN_PAIRS_FULL_MODEL",
           "b_term_mask", "full_covariance_model", "fit_full_covariance_model"]

C_SCALE = 1e-12    # 1/e-^2, parameter scale of b in the fit

#: Largest maxlag of the full PTC model: its convolution tensor holds 8 (maxlag + 1)^6 bytes and
#: the fit's time grows as fast (maxlag 8: 1.3 s; 16: 106 s and 190 MB; 60: 384 GiB).
MAX_FULL_MODEL_MAXLAG = 12

#: Fewest flat pairs for the full PTC model (a, b and the noise at every lag): with fewer the
#: fit is under-constrained (4 levels at maxlag 8 gave a gain 13 % high and 27 e- read noise).
MIN_PAIRS_FULL_MODEL = 8


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


def b_term_mask(fit_b, nlag):
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
    b_mask = b_term_mask(fit_b, nlag)
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
    start = np.concatenate([a0.ravel() / A_SCALE, np.zeros(nb), noise0.ravel(), [gain0]])
    weight = 1.0 / cov_err

    def unpack(p):
        a = p[:nsq].reshape(nlag, nlag) * A_SCALE
        c = np.zeros((nlag, nlag))
        c[b_mask] = p[nsq:nsq + nb] * C_SCALE
        noise = p[nsq + nb:2 * nsq + nb].reshape(nlag, nlag)
        return a, c, noise, p[-1]

    def residuals(p):
        a, c, noise, gain = unpack(p)
        return ((full_covariance_model(mean_adu, a, c, noise, gain) - cov_adu) * weight).ravel()

    flat_weight = weight.reshape(npairs, nsq)

    def jacobian(p):
        a, c, noise, gain = unpack(p)
        jac_a, jac_c, jac_n, jac_g = _full_model_jacobian(mean_adu, a, c, noise, gain, b_mask)
        blocks = [jac_a * A_SCALE, jac_c * C_SCALE, jac_n, jac_g[:, :, None]]
        return np.concatenate([block * flat_weight[:, :, None] for block in blocks],
                              axis=2).reshape(npairs * nsq, -1)

    result = scipy.optimize.least_squares(residuals, start, jac=jacobian, method="lm",
                                          x_scale="jac")
    covariance, chi2, ndof = parameter_covariance(result, cov_adu.size)
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
    a_cov = covariance[:nsq, :nsq] * A_SCALE**2
    return {
        "a": a, "a_err": a_err, "a_cov": a_cov, "b": b, "b_err": b_err, "c": c, "c_err": c_err,
        "noise_e2": noise, "noise_e2_err": noise_err,
        "gain": float(gain), "gain_err": float(gain_err), "chi2": chi2, "ndof": ndof,
    }
