"""The observable tables the closed loop compares with the model.

Each is optional; a candidate with no template on any observable present is "not testable" on
that data set and says so:

* `SizeTable`: spot size against peak flux in X and Y (sigma_x, sigma_y, pixels), with errors,
  a data-set index (``group``: e.g. an amplifier), an optional colour and an optional exposure
  index (for the held-out split, `bfpsf.diagnosis.heldout`).
* `LinearityTable`: flat mean against exposure time.
* `CorrelationTable`: flat-field correlation coefficients R(dx, dy) = C(dx, dy) / V against the
  mean signal (their zero-flux intercepts are the readout pedestal).
* `PTCTable`: flat-pair variance against mean minus the calibrated PTC model (A+19 eq. 20)
  evaluated with a(0, 0) from the sum rule (see `PTCTable`).

`Observables` holds them; the builders are in `bfpsf.diagnosis.observables`.
"""

from dataclasses import dataclass, field

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import weighted_least_squares
from .spot_model import SpotForwardModel

__all__ = ["SizeTable", "LinearityTable", "CorrelationTable", "PTCTable", "Observables",
           "interleaved"]


def _column(values, name, n=None, positive=False):
    array = np.asarray(values, dtype=float).ravel()
    if n is not None and array.size != n:
        msg = f"{name} must have {n} values, got {array.size}"
        raise BFPSFInputError(msg, array.size)
    if not np.all(np.isfinite(array)):
        msg = f"{name} has {np.count_nonzero(~np.isfinite(array))} non-finite values"
        raise BFPSFInputError(msg, name)
    if positive and np.any(array <= 0):
        msg = f"{name} must be positive, got minimum {array.min():g}"
        raise BFPSFInputError(msg, float(array.min()))
    return array


#: Optional per-entry columns of a `SizeTable` beyond the colour and the exposure.
_OPTIONAL_COLUMNS = ("x_detector", "y_detector", "skew_x", "skew_y", "skew_x_err", "skew_y_err",
                     "cross", "cross_err")


@dataclass(frozen=True)
class SizeTable:
    """Spot size against peak flux (the brighter-fatter observable, G15 section 3).

    Attributes
    ----------
    peak_e : ndarray (n,)
        Peak flux of each entry (a level or a star), e- in the brightest pixel.
    sigma_x, sigma_y : ndarray (n,)
        Widths sqrt(Mxx), sqrt(Myy) (or Gaussian-fit sigmas), pixels.
    sigma_x_err, sigma_y_err : ndarray (n,)
        1-sigma errors, pixels.
    group : ndarray of int (n,)
        Data set of each entry (amplifier, epoch, a range of detector columns); intercepts
        are free per group and exposure (`intercepts`).
    colour : ndarray (n,) or None
        Colour of each entry (magnitudes), for the size-colour candidate.
    label : str
    exposure : ndarray of int (n,) or None
        Exposure each entry was measured on, when known: the held-out split
        (`bfpsf.diagnosis.loop.split_observables`) keeps whole exposures apart. Exposure
        numbers are in the order of the night (the residual report's exposure-order terms).
    x_detector : ndarray (n,) or None
        Mean position of the entry's stars on the detector along X (distance from the
        amplifier), pixels: the position dependence of the residual
        (`bfpsf.diagnosis.signature`).
    y_detector : ndarray (n,) or None
        The same along Y (the row: the parallel transfers to the serial register), pixels.
    skew_x, skew_y, skew_x_err, skew_y_err : ndarray (n,) or None
        Third standardised moments of the stars along X and Y (`bfpsf.validation.effects_bench.skewness`)
        and their errors: the odd (centroid- and skew-like) part of the residual.
    cross, cross_err : ndarray (n,) or None
        The stars' cross moment, e2 = 2 Mxy / (Mxx + Myy) of their adaptive moments, and its
        error: the diagonal part, which no catalogue effect changes with flux in a star
        symmetric about X or Y (`bfpsf.diagnosis.signature.cross_test`).
    """

    peak_e: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    sigma_x_err: np.ndarray
    sigma_y_err: np.ndarray
    group: np.ndarray = None
    colour: np.ndarray = None
    label: str = ""
    exposure: np.ndarray = None
    x_detector: np.ndarray = None
    y_detector: np.ndarray = None
    skew_x: np.ndarray = None
    skew_y: np.ndarray = None
    skew_x_err: np.ndarray = None
    skew_y_err: np.ndarray = None
    cross: np.ndarray = None
    cross_err: np.ndarray = None

    def __post_init__(self):
        n = np.size(self.peak_e)
        object.__setattr__(self, "peak_e", _column(self.peak_e, "peak_e", positive=True))
        for name in ("sigma_x", "sigma_y", "sigma_x_err", "sigma_y_err"):
            object.__setattr__(self, name, _column(getattr(self, name), name, n, positive=True))
        group = np.zeros(n, int) if self.group is None else np.asarray(self.group).ravel()
        if group.size != n:
            msg = f"group must have {n} values, got {group.size}"
            raise BFPSFInputError(msg, group.size)
        object.__setattr__(self, "group", np.unique(group, return_inverse=True)[1])
        if self.colour is not None:
            object.__setattr__(self, "colour", _column(self.colour, "colour", n))
        if self.exposure is not None:
            exposure = np.asarray(self.exposure).ravel()
            if exposure.size != n:
                msg = f"exposure must have {n} values, got {exposure.size}"
                raise BFPSFInputError(msg, exposure.size)
            object.__setattr__(self, "exposure", exposure.astype(int))
        for name in _OPTIONAL_COLUMNS:
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _column(getattr(self, name), name, n,
                                                       positive=name.endswith("_err")))
        if (self.skew_x is None) != (self.skew_x_err is None) or \
                (self.skew_y is None) != (self.skew_y_err is None):
            msg = "skewness columns need their errors (skew_x_err, skew_y_err)"
            raise BFPSFInputError(msg)
        if (self.cross is None) != (self.cross_err is None):
            msg = "the cross moment column needs its error (cross_err)"
            raise BFPSFInputError(msg)
        if n < 3:
            msg = f"a size table needs at least 3 entries, got {n}"
            raise BFPSFInputError(msg, n)

    @property
    def n_groups(self):
        return int(self.group.max()) + 1

    @property
    def intercepts(self):
        """Index of each entry's free intercept, ndarray of int (n,): its group and, when the
        exposure is known, its exposure. Every exposure has its own seeing, so its own size
        at zero flux (a new user's null with a 3 % seeing change from exposure to exposure
        was "not explained" with one intercept for the night); the brighter-fatter slope
        against peak is common."""
        if self.exposure is None:
            return self.group
        pairs = np.column_stack([self.group, self.exposure])
        return np.unique(pairs, axis=0, return_inverse=True)[1].ravel()

    def intercept_design(self):
        """One 0/1 column per intercept (`intercepts`), ndarray (n, n_intercepts)."""
        index = self.intercepts
        return (index[:, None] == np.arange(index.max() + 1)[None, :]).astype(float)

    def peak_slope(self, values, errors):
        """Weighted slope of a per-entry quantity against peak, per 1e5 e-, with an intercept
        per `intercepts` (the odd moments' and e2's flux dependence, with or without a
        model subtracted): (slope, error, chi2, degrees of freedom)."""
        design = np.column_stack([self.peak_e / 1e5, self.intercept_design()])
        params, covariance, chi2, _ = weighted_least_squares(np.asarray(values, float),
                                                             errors, design)
        return (float(params[0]), float(np.sqrt(abs(covariance[0, 0]))), float(chi2),
                max(len(self) - design.shape[1], 1))

    def __len__(self):
        return self.peak_e.size

    def subset(self, rows):
        """The table restricted to ``rows`` (boolean mask or indices)."""
        def pick(values):
            return None if values is None else np.asarray(values)[rows]

        return SizeTable(self.peak_e[rows], self.sigma_x[rows], self.sigma_y[rows],
                         self.sigma_x_err[rows], self.sigma_y_err[rows], group=self.group[rows],
                         colour=pick(self.colour), label=self.label,
                         exposure=pick(self.exposure),
                         **{name: pick(getattr(self, name)) for name in _OPTIONAL_COLUMNS})


@dataclass(frozen=True)
class LinearityTable:
    """Flat mean against exposure time (G15 section 4.1; linearity).

    Attributes
    ----------
    exptime : ndarray (n,), s
    mean_e, mean_err_e : ndarray (n,), e-
        ``mean_err_e`` includes the error floor.
    error_floor : float
        Relative error added in quadrature to the shot noise of each mean (lamp flicker,
        `lamp_error_floor`); reported by the loop. Default 0.
    """

    exptime: np.ndarray
    mean_e: np.ndarray
    mean_err_e: np.ndarray
    error_floor: float = 0.0

    def __post_init__(self):
        n = np.size(self.exptime)
        object.__setattr__(self, "exptime", _column(self.exptime, "exptime"))
        object.__setattr__(self, "mean_e", _column(self.mean_e, "mean_e", n))
        object.__setattr__(self, "mean_err_e", _column(self.mean_err_e, "mean_err_e", n,
                                                       positive=True))


@dataclass(frozen=True)
class CorrelationTable:
    """Flat-field correlation coefficients R(dx, dy) = C(dx, dy) / V against the mean signal.

    Attributes
    ----------
    mean_e : ndarray (n,)
        Mean signal of each pair, e-.
    lags : tuple of (dx, dy)
    r, r_err : ndarray (n, n_lags)
        R and its error (dimensionless).
    """

    mean_e: np.ndarray
    lags: tuple
    r: np.ndarray
    r_err: np.ndarray

    def __post_init__(self):
        n = np.size(self.mean_e)
        object.__setattr__(self, "mean_e", _column(self.mean_e, "mean_e", positive=True))
        lags = tuple((int(dx), int(dy)) for dx, dy in self.lags)
        object.__setattr__(self, "lags", lags)
        for name in ("r", "r_err"):
            array = np.asarray(getattr(self, name), dtype=float).reshape(n, len(lags))
            _column(array, name)
            object.__setattr__(self, name, array)
        _column(self.r_err, "r_err", positive=True)


@dataclass(frozen=True)
class PTCTable:
    """Flat-pair variance against mean and the calibrated PTC model (G15 section 4.1).

    The model is A+19 eq. 20 (`bfpsf.calibration.ptc.full_covariance_model`) with the
    calibrated gain, read noise and a(dx, dy), except a(0, 0), which is replaced by its sum-rule
    value -sum a(dx, dy) over the other measured lags (charge conservation, G15 eq. sum rule):
    a free a(0, 0) absorbs a quadratic gain non-linearity (it adds ~3 c m^2 / 1e5 to the
    variance, exactly like a(0, 0) m^2), the sum rule does not. The area beyond the measured
    lags is missing from that sum (a bias of a(0, 0) of a few percent, G15 section 4.2.2).

    Attributes
    ----------
    mean_e : ndarray (n,)
        Mean signal of each pair, e-.
    var_e, var_err_e : ndarray (n,)
        Measured single-image variance and its shot-noise error, e-^2.
    model_e : ndarray (n,)
        The PTC model at ``mean_e``, e-^2.
    model_slope : ndarray (n,)
        dV/dm of the model, dimensionless (for the non-linearity template).
    sum_rule_err : float
        Error of the sum-rule a(0, 0), 1/e-: common to every pair (the loop fits a term
        delta_a m^2 with this prior width). 0: no such freedom.
    """

    mean_e: np.ndarray
    var_e: np.ndarray
    var_err_e: np.ndarray
    model_e: np.ndarray
    model_slope: np.ndarray
    sum_rule_err: float = 0.0

    def __post_init__(self):
        n = np.size(self.mean_e)
        object.__setattr__(self, "mean_e", _column(self.mean_e, "mean_e", positive=True))
        for name in ("var_e", "model_e", "model_slope"):
            object.__setattr__(self, name, _column(getattr(self, name), name, n))
        object.__setattr__(self, "var_err_e", _column(self.var_err_e, "var_err_e", n,
                                                      positive=True))
        if not (np.isfinite(self.sum_rule_err) and self.sum_rule_err >= 0):
            msg = f"sum_rule_err must be finite and >= 0, got {self.sum_rule_err!r}"
            raise BFPSFValueError(msg, self.sum_rule_err)

    @property
    def residual_e(self):
        """Measured minus model variance, e-^2."""
        return self.var_e - self.model_e


@dataclass(frozen=True)
class Observables:
    """Everything the closed loop compares with the model.

    Attributes
    ----------
    sizes : SizeTable or None
    spot_model : SpotForwardModel or None
        Base-model predictions of the sizes (required with ``sizes``).
    linearity : LinearityTable or None
    correlations : CorrelationTable or None
    meta : dict
        Anything else: ``area`` (measured a, for the sum-rule tail), ``residual_images``
        (label -> stacked residual image, e-, for the report), ``star_residual`` (the stacked
        residual of the stars, `bfpsf.diagnosis.star_residual.stacked_star_residual`), the inputs.
    ptc : PTCTable or None
        PTC residuals (images mode).
    """

    sizes: SizeTable = None
    spot_model: SpotForwardModel = None
    linearity: LinearityTable = None
    correlations: CorrelationTable = None
    meta: dict = field(default_factory=dict)
    ptc: PTCTable = None

    def __post_init__(self):
        if self.sizes is not None and self.spot_model is None:
            msg = "a size table needs a spot_model to predict the sizes"
            raise BFPSFInputError(msg)
        if all(getattr(self, name) is None
               for name in ("sizes", "linearity", "correlations", "ptc")):
            msg = "no observable given (sizes, linearity, correlations or ptc)"
            raise BFPSFInputError(msg)


def interleaved(n, fraction):
    """Boolean mask of the held-out members of n ordered items, evenly interleaved (the
    held-out split of `bfpsf.diagnosis.loop.split_observables`)."""
    index = np.arange(n)
    return np.floor((index + 1) * fraction) > np.floor(index * fraction)
