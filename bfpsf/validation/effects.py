"""The catalogue of candidate effects the brighter-fatter model may be missing (closed loop).

The base model predicts every observable from the calibration: spot sizes from the G15
redistribution (eq. scrambling_model) of a model spot scaled to each peak, flat-field
correlations R(dx, dy) = a(dx, dy) mu (eq. covar), flat means linear in exposure time. Each
candidate below is an explicit extension of that model with its own parameter(s): it states how
it changes each observable per unit parameter (a *template*, the Jacobian of the prediction),
so that `bfpsf.validation.diagnose` can fit it to the residuals by weighted least squares and
score it by the chi-square improvement and the Bayesian information criterion.

Observables (each optional; a candidate with no template on any observable present is "not
testable" on that data set and says so):

* `SizeTable`: spot size against peak flux in X and Y (sigma_x, sigma_y, pixels), with errors,
  a data-set index (``group``: e.g. an amplifier) and an optional colour.
* `LinearityTable`: flat mean against exposure time.
* `CorrelationTable`: flat-field correlation coefficients R(dx, dy) = C(dx, dy) / V against the
  mean signal (their zero-flux intercepts are the readout pedestal).
* `PTCTable`: flat-pair variance against mean minus the calibrated PTC model (A+19 eq. 20)
  evaluated with a(0, 0) from the sum rule (see `PTCTable`).

Candidates (`CATALOGUE`), parameters in brackets:

``gain_nonlinearity`` [c]
    Pixel values v -> v (1 + c v / 1e5 e-): flat means gain a term c (k t)^2 / 1e5, bright spots
    are compressed at the core (sizes change like BF), the PTC variance at a measured mean m
    gains (4 m V(m) - m^2 V'(m)) c / 1e5 (about 3 c m^2 / 1e5, which a free a(0, 0) absorbs
    but the sum-rule a(0, 0) of `PTCTable` does not). Templates: linearity, sizes, ptc.
``readout_pedestal`` [R0(1,0), R0(0,1)]
    Readout correlation constant in flux (G15 section 4.2.3, R10 ~ -0.003): the correlation
    table gains an intercept per lag. Template: correlations. Its PTC template is zero: a
    serial readout correlation q_i + c q_(i-1) scales the mean by 1 + c and the variance by
    1 + c^2, a change of the PTC gain that the PTC block's free gain column absorbs; the
    calibration subtracts the pedestal before a(dx, dy) enter the sum rule.
``xy_anisotropy`` [q]
    X/Y anisotropy of the nearest boundaries beyond the smoothing model: a quadrupole boundary
    displacement around the source pixel (its E/W boundaries move out by q * s, its N/S
    boundaries in by q * s, s the mean |a^E(0,0)|, |a^N(0,0)|), the curl of a stream function
    on the four corners of the source pixel. It changes no pixel area, so the flats cannot see
    it (it is the null mode the shift solver fixes by a model ratio). q > 0: a charged pixel
    shrinks less in X and more in Y, so BF moves from sigma_x to sigma_y. Template: sizes.
``second_order`` [t]
    Second-order (flux^2) redistribution / build-up: t times R[Q + R[Q]] - R[Q], the term of
    order a^2 Q^3 that the one-step model drops. Template: sizes (grows as peak^2).
``boundary_density`` [t]
    The boundary-density (sampling) error (G15 fig. bva): t times the difference between the
    redistribution with the exact charge density integrated along each boundary and with the
    (Q_00 + Q_X) / 2 approximation (eq. density-approx). t = 1 is the physical value. Large
    for undersampled spots. Template: sizes.
``chromatic_size`` [c]
    Size correlated with colour, colour correlated with flux (G15 section 3.2): sigma gains
    c (colour - mean colour) in X and Y. Template: sizes (needs a colour column).
``flux_diffusion`` [d]
    Flux-dependent short-range diffusion: an isotropic Gaussian blur of variance d pixel^2 per
    100 ke- of peak, sigma^2 -> sigma^2 + d peak / 1e5 (first order in d). Template: sizes.
``sum_rule_tail`` [t]
    Area beyond the measured lags missing from a(0, 0) of tables normalised to a zero sum
    (see `SumRuleTail`); t = 1 is the Ei-model tail. Template: sizes.
``calibration_scale`` [s]
    Every boundary shift times (1 + s): a calibration amplitude error. Template: sizes.
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import fftconvolve

from ..errors import BFPSFInputError, BFPSFValueError
from ..shifts import BoundaryShifts

__all__ = [
    "SizeTable", "LinearityTable", "CorrelationTable", "PTCTable", "Observables",
    "SpotForwardModel",
    "Effect", "CATALOGUE", "quadrupole_shifts", "exact_density_delta", "effect_names",
    "get_effect",
]

#: Reference flux of the flux-scaled parameters (nonlinearity, diffusion), e-.
FLUX_SCALE = 1e5


# -- observables ---------------------------------------------------------------------------------
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
        Data set of each entry (amplifier, epoch); intercepts are free per group.
    colour : ndarray (n,) or None
        Colour of each entry (magnitudes), for the size-colour candidate.
    label : str
    """

    peak_e: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    sigma_x_err: np.ndarray
    sigma_y_err: np.ndarray
    group: np.ndarray = None
    colour: np.ndarray = None
    label: str = ""

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
        if n < 3:
            msg = f"a size table needs at least 3 entries, got {n}"
            raise BFPSFInputError(msg, n)

    @property
    def n_groups(self):
        return int(self.group.max()) + 1

    def __len__(self):
        return self.peak_e.size


@dataclass(frozen=True)
class LinearityTable:
    """Flat mean against exposure time (G15 section 4.1; linearity).

    Attributes
    ----------
    exptime : ndarray (n,), s
    mean_e, mean_err_e : ndarray (n,), e-
    """

    exptime: np.ndarray
    mean_e: np.ndarray
    mean_err_e: np.ndarray

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
        residual of the stars, `bfpsf.validation.diagnose.stacked_star_residual`), the inputs.
    ptc : PTCTable or None
        PTC residuals (images mode).
    """

    sizes: SizeTable = None
    spot_model: "SpotForwardModel" = None
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


# -- the redistribution variants the templates need ---------------------------------------------
def _shift_fields(image, shifts):
    """(sum_ij a^N_ij Q_ij, sum_ij a^E_ij Q_ij) at every pixel (zero charge outside)."""
    fields = []
    for kernel in (shifts.north, shifts.east):
        fields.append(fftconvolve(image, kernel[::-1, ::-1], mode="same"))
    return fields


def exact_density_delta(image, north_density, east_density, shifts):
    """dQ with the exact charge density on each boundary (G15 section 6.2, fig. bva).

    Parameters
    ----------
    image : ndarray [y, x]
        Pixel charges, e-.
    north_density : ndarray (ny - 1, nx)
        Charge density integrated along the boundary between pixel (x, y) and (x, y + 1),
        e- per pixel length (equals Q for a uniform image).
    east_density : ndarray (ny, nx - 1)
        Same for the boundary between (x, y) and (x + 1, y).
    shifts : BoundaryShifts

    Returns
    -------
    ndarray [y, x]
        dQ of eq. scrambling_model with (Q_00 + Q_X) / 2 replaced by the exact density:
        boundary flux = 1/2 a * Q * rho (the 1/2 of the build-up, eq. def-a). Charge conserving.
    """
    shift_north, shift_east = _shift_fields(image, shifts)
    flux_north = 0.5 * shift_north[:-1, :] * north_density
    flux_east = 0.5 * shift_east[:, :-1] * east_density
    delta = np.zeros(image.shape)
    delta[:-1, :] += flux_north
    delta[1:, :] -= flux_north
    delta[:, :-1] += flux_east
    delta[:, 1:] -= flux_east
    return delta


def quadrupole_shifts(shifts, amplitude):
    """Area-preserving X/Y quadrupole of the boundaries around the source pixel.

    A stream function psi = +c on the source pixel's corners (+1/2, +1/2) and (-1/2, -1/2),
    -c on the other two, gives boundary displacements (curl of psi) that change no pixel area:
    the source pixel's E and W boundaries move out by 2c, its N and S boundaries in by 2c, and
    the nearest neighbours deform accordingly.

    Parameters
    ----------
    shifts : BoundaryShifts
        Only its grid radius and the scale s = (|a^N(0,0)| + |a^E(0,0)|) / 2 are used.
    amplitude : float
        q: 2c = q s.

    Returns
    -------
    BoundaryShifts
        The added displacement field (1/e-), parity-symmetric and with zero area everywhere.
    """
    m = shifts.radius
    scale = 0.5 * (abs(shifts.north[m, m]) + abs(shifts.east[m, m]))
    c = 0.5 * amplitude * scale

    def psi(x, y):
        # corners of the source pixel relative to the source: (+-1/2, +-1/2)
        value = np.zeros(np.broadcast(x, y).shape)
        on = (np.abs(np.abs(x) - 0.5) < 1e-9) & (np.abs(np.abs(y) - 0.5) < 1e-9)
        value[on] = c * np.sign(x[on] * y[on])
        return value

    dy, dx = np.mgrid[-m:m + 1, -m:m + 1].astype(float)
    px, py = -dx, -dy            # pixel (0, 0) relative to a source at (dx, dy)
    north = psi(px - 0.5, py + 0.5) - psi(px + 0.5, py + 0.5)
    east = psi(px + 0.5, py + 0.5) - psi(px + 0.5, py - 0.5)
    return BoundaryShifts(north, east, check=True)


def _add_shifts(first, second):
    radius = max(first.radius, second.radius)
    first, second = first.padded(radius), second.padded(radius)
    return BoundaryShifts(first.north + second.north, first.east + second.east, check=False)


# -- the forward model of spot sizes --------------------------------------------------------------
def _gaussian_fit_sigmas(stamps):
    """sigma_x, sigma_y of a pixel-integrated elliptical Gaussian fitted to each stamp (pixels).

    The measurement of Lage's spot tables (forward-modelled 2-D Gaussian, uniform weights).
    """
    from scipy.optimize import least_squares
    from scipy.special import erf

    n, ny, nx = stamps.shape
    edges_x = np.arange(nx + 1) - 0.5
    edges_y = np.arange(ny + 1) - 0.5

    def integral(edges, centre, sigma):
        cdf = 0.5 * (1 + erf((edges - centre) / (np.sqrt(2) * sigma)))
        return np.diff(cdf)

    sigma_x = np.empty(n)
    sigma_y = np.empty(n)
    for index, stamp in enumerate(stamps):
        total = stamp.sum()
        yy, xx = np.mgrid[:ny, :nx]
        x0 = (stamp * xx).sum() / total
        y0 = (stamp * yy).sum() / total

        def residuals(p):
            model = p[0] * np.outer(integral(edges_y, p[2], p[4]), integral(edges_x, p[1], p[3]))
            return (model - stamp).ravel()

        start = [total, x0, y0, 1.0, 1.0]
        fit = least_squares(residuals, start, x_scale=[total, 1, 1, 1, 1], xtol=1e-12,
                            ftol=1e-12, gtol=1e-12)
        sigma_x[index], sigma_y[index] = abs(fit.x[3]), abs(fit.x[4])
    return sigma_x, sigma_y


class SpotForwardModel:
    """Sizes of a model spot scaled to given peaks and redistributed (G15 section 6.3).

    The G15 procedure: a low-flux spot model, scaled to each flux, transformed by
    eq. scrambling_model, then measured like the data. The model spot is a GalSim profile,
    pixel-integrated at ``phases x phases`` sub-pixel positions (sizes averaged over them).

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux spot profile without the pixel (e.g. ``galsim.Gaussian``, ``galsim.Moffat``).
    shifts : BoundaryShifts
        Boundary shifts a^X, 1/e-.
    stamp_size : int, optional
        Stamp side, pixels (odd). Default: 8 sigma of the profile, at least 11.
    phases : int, optional
        Sub-pixel positions per axis (default 3).
    oversampling : int, optional
        Fine samples per pixel for the exact boundary density (default 10).
    measure : {'moments', 'gaussian_fit'}, optional
        Adaptive moments (`bfpsf.measure.moments`, G15 section 3.2, default) or a
        pixel-integrated Gaussian fit (as Lage's spot tables).

    Notes
    -----
    The peak of a spot of flux F is F times the central-pixel fraction of the centred profile;
    the data's peaks are converted to fluxes with the same fraction.
    """

    def __init__(self, profile, shifts, *, stamp_size=None, phases=3, oversampling=10,
                 measure="moments"):
        import galsim

        if not isinstance(profile, galsim.GSObject):
            msg = f"profile must be a galsim.GSObject, got {type(profile).__name__}"
            raise BFPSFValueError(msg, profile)
        if not isinstance(shifts, BoundaryShifts):
            shifts = getattr(shifts, "shifts", shifts)
            if not isinstance(shifts, BoundaryShifts):
                msg = "shifts must be a BoundaryShifts (or carry one in .shifts)"
                raise BFPSFValueError(msg, shifts)
        if measure not in ("moments", "gaussian_fit"):
            msg = f"measure must be 'moments' or 'gaussian_fit', got {measure!r}"
            raise BFPSFValueError(msg, measure)
        self.profile = profile.withFlux(1.0)
        self.shifts = shifts
        self.measure = measure
        if stamp_size is None:
            sigma = galsim.hsm.FindAdaptiveMom(
                self.profile.drawImage(nx=64, ny=64, scale=1.0)).moments_sigma
            stamp_size = max(11, int(2 * np.ceil(4 * sigma) + 1))
        self.stamp_size = int(stamp_size) | 1
        self.oversampling = int(oversampling)
        grid = (np.arange(phases) + 0.5) / phases - 0.5
        self.phases = [(px, py) for py in grid for px in grid]
        self._cache = {}
        self._fine = [self._draw_fine(px, py) for px, py in self.phases]
        centred = self.profile.drawImage(nx=self.stamp_size, ny=self.stamp_size, scale=1.0)
        self.peak_fraction = float(centred.array[self.stamp_size // 2, self.stamp_size // 2])

    def _draw_fine(self, px, py):
        """Pixel charges and exact boundary densities of the unit-flux spot at a phase."""
        s, n = self.oversampling, self.stamp_size
        fine = self.profile.drawImage(nx=n * s, ny=n * s, scale=1.0 / s, method="no_pixel",
                                      offset=(px * s, py * s)).array
        pixels = fine.reshape(n, s, n, s).sum(axis=(1, 3))
        # density on the boundary between pixel columns i and i + 1: mean of the two fine
        # columns beside it, integrated along the pixel (sum over its s fine rows, times s).
        columns = fine.reshape(n, s, n * s).sum(axis=1)             # [pixel row, fine x]
        east = s * 0.5 * (columns[:, s - 1:-1:s] + columns[:, s::s])
        rows = fine.reshape(n * s, n, s).sum(axis=2)                # [fine y, pixel column]
        north = s * 0.5 * (rows[s - 1:-1:s, :] + rows[s::s, :])
        return pixels, north, east

    def fluxes(self, peaks_e):
        """Total flux of a spot of each peak, e-."""
        return np.asarray(peaks_e, dtype=float) / self.peak_fraction

    def stamps(self, peaks_e, *, shifts=None, density="approx", second_order=0.0,
               nonlinearity=0.0):
        """Redistributed model stamps, shape (n_peaks, n_phases, size, size), e-.

        Parameters
        ----------
        peaks_e : array_like
            Peaks, e-.
        shifts : BoundaryShifts, optional
            Override the model's shifts.
        density : {'approx', 'exact'}
            (Q_00 + Q_X)/2 (G15 eq. density-approx) or the exact boundary density.
        second_order : float
            Scale t of the second-order term R[Q + R[Q]] - R[Q].
        nonlinearity : float
            c: pixel values v -> v (1 + c v / 1e5).
        """
        from ..model.redistribution import redistribution_delta

        shifts = self.shifts if shifts is None else shifts
        fluxes = self.fluxes(peaks_e)
        out = np.empty((fluxes.size, len(self.phases), self.stamp_size, self.stamp_size))
        for j, (pixels, north, east) in enumerate(self._fine):
            for i, flux in enumerate(fluxes):
                charge = flux * pixels
                if density == "exact":
                    delta = exact_density_delta(charge, flux * north, flux * east, shifts)
                else:
                    delta = redistribution_delta(charge, shifts)
                image = charge + delta
                if second_order:
                    image = image + second_order * (redistribution_delta(image, shifts) - delta)
                if nonlinearity:
                    image = image * (1.0 + nonlinearity * image / FLUX_SCALE)
                out[i, j] = image
        return out

    def sizes(self, peaks_e, **options):
        """(sigma_x, sigma_y) of the model at each peak, pixels, averaged over the phases."""
        def hashable(value):
            # shifts by content (an id() could be reused by a new object)
            if isinstance(value, BoundaryShifts):
                return (value.north.tobytes(), value.east.tobytes())
            return value

        key = (tuple(np.round(np.asarray(peaks_e, float), 6)),
               tuple(sorted((k, hashable(v)) for k, v in options.items())))
        if key in self._cache:
            return self._cache[key]
        stamps = self.stamps(peaks_e, **options)
        n_peaks, n_phases = stamps.shape[:2]
        flat = stamps.reshape(-1, self.stamp_size, self.stamp_size)
        if self.measure == "moments":
            from ..measure.moments import adaptive_moments_batch

            result = adaptive_moments_batch(flat)
            sigma_x, sigma_y = np.sqrt(result.mxx), np.sqrt(result.myy)
            failed = np.flatnonzero(np.asarray(result.flags) != 0)
            if failed.size:
                # Only spots with no adaptive-moment solution are flagged (HSM fails on them
                # too: centred spots with sigma below ~0.7 px).
                msg = (f"adaptive moments failed on {failed.size} of {len(flat)} model stamps "
                       f"({result[int(failed[0])].flag_string}); the spot is too undersampled "
                       "for adaptive moments: use measure='gaussian_fit'")
                raise BFPSFValueError(msg, failed.size)
        else:
            sigma_x, sigma_y = _gaussian_fit_sigmas(flat)
        value = (sigma_x.reshape(n_peaks, n_phases).mean(axis=1),
                 sigma_y.reshape(n_peaks, n_phases).mean(axis=1))
        self._cache[key] = value
        return value


# -- the candidates -------------------------------------------------------------------------------
class Effect:
    """A candidate extension of the model.

    Attributes
    ----------
    name : str
    parameters : tuple of str
        Parameter names (k = len(parameters)).
    physical_value : tuple of float or None
        The value physics predicts, when it does (e.g. 1 for the exact boundary density).
    bounds : tuple of (low, high) per parameter, or None
        Physically allowed range; a fit outside it is rejected by the loop (e.g. a negative
        diffusion, a negative area beyond the measured lags).
    description : str
    """

    name = ""
    parameters = ()
    physical_value = None
    bounds = None
    description = ""

    @property
    def k(self):
        return len(self.parameters)

    def templates(self, observables):
        """Change of each observable per unit parameter.

        Returns
        -------
        dict
            Observable key (``'sizes'``, ``'linearity'``, ``'correlations'``, ``'ptc'``) -> array
            (n_key, k) in the order of `bfpsf.validation.diagnose` residual vectors. Missing
            keys mean no change. An empty dict means the effect is not testable on this data.
        """
        raise NotImplementedError

    def __repr__(self):
        return f"<Effect {self.name} k={self.k}>"


def _size_template(observables, step, **options):
    """Finite-difference size template of one forward-model option, (2n, 1)."""
    sizes, model = observables.sizes, observables.spot_model
    base_x, base_y = model.sizes(sizes.peak_e)
    new_x, new_y = model.sizes(sizes.peak_e, **options)
    return np.concatenate([(new_x - base_x) / step, (new_y - base_y) / step])[:, None]


class GainNonlinearity(Effect):
    name = "gain_nonlinearity"
    parameters = ("c_per_1e5",)
    description = "pixel values v -> v (1 + c v / 1e5 e-)"

    def templates(self, observables):
        out = {}
        if observables.linearity is not None:
            # mean = k t (1 + c k t / 1e5) + b: the template is the LINEAR signal k t squared
            # (the measured mean squared is wrong at second order, c^2 (k t)^3, which is
            # hundreds of sigma for -4 % at 1e5 e- on large flats); k from a weighted
            # quadratic fit of the mean against exposure time
            table = observables.linearity
            if table.exptime.size > 3:
                k = np.polyfit(table.exptime, table.mean_e, 2, w=1.0 / table.mean_err_e)[1]
                linear = k * table.exptime
            else:
                linear = table.mean_e
            out["linearity"] = (linear ** 2 / FLUX_SCALE)[:, None]
        if observables.ptc is not None:
            # at a fixed measured mean m: true mu = m - c m^2 / 1e5, variance times
            # (1 + 2 c mu / 1e5)^2, so dV/dc = (4 m V(m) - m^2 V'(m)) / 1e5
            ptc = observables.ptc
            out["ptc"] = ((4.0 * ptc.mean_e * ptc.model_e - ptc.mean_e ** 2 * ptc.model_slope)
                          / FLUX_SCALE)[:, None]
        if observables.sizes is not None:
            step = 0.01
            out["sizes"] = _size_template(observables, step, nonlinearity=step)
        return out


class ReadoutPedestal(Effect):
    name = "readout_pedestal"
    description = "zero-flux readout correlation R0(dx, dy), constant in flux"

    def __init__(self, lags=((1, 0), (0, 1))):
        self.lags = tuple(lags)
        self.parameters = tuple(f"R0({dx},{dy})" for dx, dy in self.lags)

    def templates(self, observables):
        table = observables.correlations
        if table is None:
            return {}
        n = table.mean_e.size
        design = np.zeros((n * len(table.lags), len(self.lags)))
        for column, lag in enumerate(self.lags):
            if lag in table.lags:
                index = table.lags.index(lag)
                design[index * n:(index + 1) * n, column] = 1.0
        if not np.any(design):
            return {}
        return {"correlations": design}


class XYAnisotropy(Effect):
    name = "xy_anisotropy"
    parameters = ("q",)
    description = ("area-preserving X/Y quadrupole of the nearest boundaries (E/W out, N/S in "
                   "by q times the mean nearest shift); invisible in flats")

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        model = observables.spot_model
        step = 0.2
        shifts = _add_shifts(model.shifts, quadrupole_shifts(model.shifts, step))
        return {"sizes": _size_template(observables, step, shifts=shifts)}


class SecondOrder(Effect):
    name = "second_order"
    parameters = ("t",)
    physical_value = None
    description = "t * (R[Q + R[Q]] - R[Q]): the flux^2 term of the redistribution (build-up)"

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        return {"sizes": _size_template(observables, 1.0, second_order=1.0)}


class BoundaryDensity(Effect):
    name = "boundary_density"
    parameters = ("t",)
    physical_value = (1.0,)
    # the exact density is computed from the model spot: allow it to be off by a factor 2
    bounds = ((0.0, 2.0),)
    description = ("t * (exact boundary charge density - (Q00 + QX)/2 approximation), "
                   "G15 fig. bva; t = 1 is the physical value")

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        return {"sizes": _size_template(observables, 1.0, density="exact")}


class ChromaticSize(Effect):
    name = "chromatic_size"
    parameters = ("dsigma_dcolour",)
    description = "sigma_x, sigma_y += c (colour - mean colour), pixels per magnitude"

    def templates(self, observables):
        sizes = observables.sizes
        if sizes is None or sizes.colour is None:
            return {}
        centred = sizes.colour - sizes.colour.mean()
        return {"sizes": np.concatenate([centred, centred])[:, None]}


class FluxDiffusion(Effect):
    name = "flux_diffusion"
    parameters = ("d_pix2_per_1e5",)
    bounds = ((0.0, np.inf),)
    description = "isotropic blur, sigma^2 -> sigma^2 + d peak / 1e5 e-"

    def templates(self, observables):
        sizes = observables.sizes
        if sizes is None:
            return {}
        sigma_x, sigma_y = observables.spot_model.sizes(sizes.peak_e)
        scaled = sizes.peak_e / FLUX_SCALE
        return {"sizes": np.concatenate([scaled / (2 * sigma_x), scaled / (2 * sigma_y)])[:, None]}


class SumRuleTail(Effect):
    """Correlations beyond the measured lags (the truncated sum rule).

    Tables normalised so that the measured a(dx, dy) sum to zero over the measured window
    (Lage's corr_meas: C00 = Cov00 / V_tot - 1) miss the area beyond it, so their a(0, 0) is
    too small in magnitude. The extension lowers a(0, 0) by t times the Ei-model area outside
    the window (G15 eq. f_r fitted to the measured lags, summed to lag 200) and re-solves the
    shifts; t = 1 is the physical value. Needs ``observables.meta['area']`` (a [dy, dx], 1/e-),
    and applies only to tables whose full-plane sum is zero (to 1 % of a(0, 0)): otherwise
    a(0, 0) was measured on its own and already holds the tail.
    """

    name = "sum_rule_tail"
    parameters = ("t",)
    physical_value = (1.0,)
    # the area beyond the window is positive; the Ei extrapolation may underestimate a
    # power-law tail by a few times
    bounds = ((0.0, 10.0),)
    description = ("a(0,0) lowered by t times the Ei-model area beyond the measured lags "
                   "(truncated sum rule); t = 1 is the physical value")

    def tail_area(self, area):
        """Ei-model area outside the measured window, 1/e- (full plane, (0, 0) excluded)."""
        from ..calibration.coefficients import smoothing_model_area, solve_ei_shifts

        solution = solve_ei_shifts(area, n_monte_carlo=0)
        p0, p1 = solution.p0, solution.p1
        big = smoothing_model_area(p0, p1, 200)
        weights = np.ones_like(big)
        weights[1:, :] *= 2
        weights[:, 1:] *= 2
        n = area.shape[0]
        total = (weights * big).sum() - big[0, 0]
        inside = (weights * big)[:n, :n].sum() - big[0, 0]
        return float(total - inside)

    def templates(self, observables):
        area = observables.meta.get("area")
        if observables.sizes is None or area is None:
            return {}
        from ..calibration.coefficients import solve_ei_shifts

        area = np.array(area, dtype=float)
        weights = np.ones_like(area)
        weights[1:, :] *= 2
        weights[:, 1:] *= 2
        if abs(np.sum(weights * area)) > 0.01 * abs(area[0, 0]):
            # a(0, 0) measured independently (e.g. a PTC fit): the tail is already in it
            return {}
        tail = self.tail_area(area)
        if not tail > 0:
            return {}
        lowered = area.copy()
        lowered[0, 0] -= tail
        base = solve_ei_shifts(area, n_monte_carlo=0).shifts
        shifts = solve_ei_shifts(lowered, n_monte_carlo=0).shifts
        model = observables.spot_model
        # the difference of the two solutions, added to the model's own shifts
        change = _add_shifts(shifts, base.scaled(-1.0))
        return {"sizes": _size_template(observables, 1.0,
                                        shifts=_add_shifts(model.shifts, change))}


class CalibrationScale(Effect):
    """A common scale error of the calibrated shifts (every a^X times 1 + s).

    Not a physical effect but the most common missing piece in practice: the flats measure the
    a(dx, dy) with errors (their noise propagated to the BF slope is 15-25 % for a few
    384^2 flats), or at another flux than the spots. Physical value 0.
    """

    name = "calibration_scale"
    parameters = ("s",)
    physical_value = None
    description = "every boundary shift times (1 + s): a calibration amplitude error"

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        step = 0.1
        shifts = observables.spot_model.shifts.scaled(1.0 + step)
        return {"sizes": _size_template(observables, step, shifts=shifts)}


#: The catalogue tested by `bfpsf.validation.diagnose.diagnose`, in report order.
CATALOGUE = (GainNonlinearity(), ReadoutPedestal(), XYAnisotropy(), SecondOrder(),
             BoundaryDensity(), ChromaticSize(), FluxDiffusion(), SumRuleTail(),
             CalibrationScale())


def effect_names():
    """Names of the catalogue's candidates."""
    return [effect.name for effect in CATALOGUE]


def get_effect(name):
    """The catalogue entry called ``name``."""
    for effect in CATALOGUE:
        if effect.name == name:
            return effect
    msg = f"unknown effect {name!r}; the catalogue has {effect_names()}"
    raise BFPSFValueError(msg, name)
