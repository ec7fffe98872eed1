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

from dataclasses import dataclass, field

import numpy as np
from astropy.table import Table

from ..errors import BFPSFValueError
from ..least_squares import polynomial_fit
from .ptc_data import PTCData, covariance_errors, stack_pairs
from .ptc_full import B_CHOICES, SERIES_ORDER, fit_full_covariance_model, full_covariance_model
from .ptc_variance import (exponential_variance, first_order_slopes, fit_exponential_ptc,
                           fit_quadratic_ptc)
from .turnoff import detect_turnoff

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
        predicted = exponential_variance(data.mean_adu[brightest], exponential["a00"],
                                          exponential["gain"], exponential["noise_e2"])
        if abs(data.var_adu[brightest] - predicted) <= model_fail_nsigma * var_err[brightest]:
            break
        used[brightest] = False
        detected = True
        quadratic = fit_quadratic_ptc(data.mean_adu[used], data.var_adu[used], var_err[used])
    # Weights from a smooth model of the variance, not the noisy measured one.
    smooth = fit_exponential_ptc(data.mean_adu[used], data.var_adu[used], var_err[used],
                                 initial=quadratic)
    variance_model = np.where(used, exponential_variance(data.mean_adu, smooth["a00"],
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
        a, a_err, _, _ = first_order_slopes(mean_adu * gain, cov_adu, data.npix[used])
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


# tables and the G15 appendix A check
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
    params, cov, _, _ = polynomial_fit(mean_e[used], summed_e[used], summed_err[used], 1)
    raw_params, _, _, _ = polynomial_fit(mean_e[used], var_e[used],
                                         var_e[used] * np.sqrt(2.0 / npix[used]), 1)
    linear = params[0] + mean_e
    return {
        "mean_e": mean_e, "var_e": var_e, "summed_e": summed_e, "summed_err_e": summed_err,
        "slope_summed": float(params[1]), "slope_summed_err": float(np.sqrt(cov[1, 1])),
        "intercept_e2": float(params[0]), "slope_raw": float(raw_params[1]),
        "max_frac_deviation": float(np.max(np.abs(summed_e[used] / linear[used] - 1.0))),
    }
