"""The catalogue of candidate effects the brighter-fatter model may be missing (closed loop).

The base model predicts every observable from the calibration: spot sizes from the G15
redistribution (eq. scrambling_model) of a model spot scaled to each peak, flat-field
correlations R(dx, dy) = a(dx, dy) mu (eq. covar), flat means linear in exposure time. Each
candidate below is an explicit extension of that model with its own parameter(s): it states how
it changes each observable per unit parameter (a *template*, the Jacobian of the prediction),
so that `bfpsf.diagnosis.loop` can fit it to the residuals by weighted least squares and
score it by the chi-square improvement and the Bayesian information criterion.

The observables are in `bfpsf.diagnosis.observables`; a candidate with no template on any
observable present is "not testable" on that data set and says so.

Candidates (`CATALOGUE`), parameters in brackets:

``gain_nonlinearity`` [c]
    Pixel values v -> v (1 + c v / 1e5 e-): flat means gain a term c (k t)^2 / 1e5, bright spots
    are compressed at the core (sizes change like BF), the PTC variance at a measured mean m
    gains (4 m V(m) - m^2 V'(m)) c / 1e5 (about 3 c m^2 / 1e5, which a free a(0, 0) absorbs
    but the sum-rule a(0, 0) of the PTC table does not). Templates: linearity, sizes, ptc.
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
    shrinks less in X and more in Y, so BF moves from sigma_x to sigma_y. Bounds |q| < 1 (a
    charge shrinks its own pixel on all four sides). Template: sizes.
``second_order`` [t]
    Second-order (flux^2) redistribution / build-up: t times R[Q + R[Q]] - R[Q], the term of
    order a^2 Q^3 that the one-step model drops. Template: sizes (grows as peak^2). Bounds
    t >= 0 (the build-up strengthens BF).
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

import numpy as np

from ..calibration.ei_profile import smoothing_model_area
from ..calibration.shifts_ei import solve_ei_shifts
from ..errors import BFPSFValueError
from ..shifts import BoundaryShifts
from .spot_model import FLUX_SCALE

__all__ = ["Effect", "CATALOGUE", "quadrupole_shifts", "split_shifts", "split_template",
           "add_shifts", "effect_names",
           "get_effect"]

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


def split_shifts(shifts, split):
    """The shifts with their X / Y split moved by ``split``: a^E times exp(split / 2), a^N
    times exp(-split / 2) (1 +- split / 2 to first order; the exponential keeps both signs
    for any split, and two moves add).

    The flats fix the sum a(0, 0) of a pixel's four boundaries far better than its share
    between the E/W and the N/S boundaries (a new user's 16 pairs of 160^2 E2V flats:
    a^N / (a^N + a^E) at (0, 0) 0.42 +- 0.10), and the stars' BF in X follows a^E, in Y a^N:
    this is the direction in which the flats' prediction of the stars is least certain (the
    size block's split nuisance, `bfpsf.diagnosis.problem`). Parity is kept; the area
    a(0, 0) changes only at second order when a^N and a^E are alike.
    """
    return BoundaryShifts(shifts.north * np.exp(-0.5 * split), shifts.east * np.exp(0.5 * split),
                          check=False)


def split_template(observables, step=0.1):
    """Size template of `split_shifts`, (2n, 1): the change of sigma_x and sigma_y per unit
    split."""
    shifts = split_shifts(observables.spot_model.shifts, step)
    return _size_template(observables, step, shifts=shifts)


def add_shifts(first, second):
    radius = max(first.radius, second.radius)
    first, second = first.padded(radius), second.padded(radius)
    return BoundaryShifts(first.north + second.north, first.east + second.east, check=False)



# -- the candidates -------------------------------------------------------------------------------
#: How many of its errors a fitted value may lie beyond its effect's physical bounds.
BOUNDS_NSIGMA = 3.0


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
    flux_signature : str or None
        The competitor of the ``flux_shape`` dimension
        (`bfpsf.diagnosis.signature.flux_shape_test`), for effects whose identity is how they
        grow with flux: ``'linear'`` (a size change linear in peak) for the flux^2 term, where
        a residual linear in flux must not pass; ``'quadratic'`` for an effect linear in
        peak, where one that grows faster must not.
    description : str
    """

    name = ""
    parameters = ()
    physical_value = None
    bounds = None
    flux_signature = None
    description = ""

    def allows(self, values, errors=None):
        """Whether fitted ``values`` (one per parameter) lie within the effect's `bounds`, to
        `BOUNDS_NSIGMA` of their ``errors`` (a fit at a bound lands beyond it by its noise)."""
        errors = np.zeros(len(values)) if errors is None else np.asarray(errors, float)
        return self.bounds is None or all(
            low - BOUNDS_NSIGMA * error <= value <= high + BOUNDS_NSIGMA * error
            for value, error, (low, high) in zip(values, errors, self.bounds))

    @property
    def k(self):
        return len(self.parameters)

    def templates(self, observables):
        """Change of each observable per unit parameter.

        Returns
        -------
        dict
            Observable key (``'sizes'``, ``'linearity'``, ``'correlations'``, ``'ptc'``) -> array
            (n_key, k) in the order of `bfpsf.diagnosis.loop` residual vectors. Missing
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
    # |q| < 1: each boundary of a charged pixel still moves in (by s -+ q s when its N and E
    # shifts are alike); beyond it a charge would grow its own pixel along one axis, which no
    # electrostatics allows. Without the bound an X-only excess of size was named an
    # anisotropy of q = -3.6 when the flats could not fix the BF amplitude (issue 22).
    bounds = ((-1.0, 1.0),)

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        model = observables.spot_model
        step = 0.2
        shifts = add_shifts(model.shifts, quadrupole_shifts(model.shifts, step))
        return {"sizes": _size_template(observables, step, shifts=shifts)}


class SecondOrder(Effect):
    name = "second_order"
    parameters = ("t",)
    physical_value = None
    # flux^2: a residual linear in flux (stars with no BF against flats with BF) had been
    # named second_order at t = 6.3; beside a linear term its amplitude falls
    flux_signature = "linear"
    # t >= 0: the build-up strengthens BF (each step's charge sees the boundaries the charge
    # before it moved); a new user's halo that only stars above 3e4 e- of peak spread (sizes
    # growing faster than linearly in flux) was named second_order at t = -74.9 +- 8.0, which
    # --output-calib then could not apply
    bounds = ((0.0, np.inf),)
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
    # linear in peak: a new user's halo that only stars above 3e4 e- of peak spread (sizes
    # rising faster than linearly; second_order rejected by its sign) was named a diffusion
    # and "confirmed" on held-out exposures; beside a size term in peak^2 its amplitude moves
    # (p = 8e-7)
    flux_signature = "quadratic"
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
        change = add_shifts(shifts, base.scaled(-1.0))
        return {"sizes": _size_template(observables, 1.0,
                                        shifts=add_shifts(model.shifts, change))}


class CalibrationScale(Effect):
    """A common scale error of the calibrated shifts (every a^X times 1 + s).

    Not a physical effect but the most common missing piece in practice: the flats measure the
    a(dx, dy) with errors (their noise propagated to the BF slope is 15-25 % for a few
    384^2 flats), or at another flux than the spots. Physical value 0.
    """

    name = "calibration_scale"
    parameters = ("s",)
    physical_value = None
    # the stars' BF within a factor of 2 of the flats': a scale of the calibration, not its
    # absence (stars with no BF at all, from a pipeline that corrected them, fit s = -1 and
    # "confirm" it on held-out exposures, the effect being in all of them). GalSim's own flats
    # and stars differ by up to -35 % (its two rules, `bfpsf.interop.silicon_truth`).
    bounds = ((-0.5, 1.0),)
    # BF's own flux shape: a halo of the brightest stars (nothing below 3e4 e- of peak,
    # faster than linear above) was taken as the flats' scale, s = 0.45 +- 0.01 against a
    # prior of 0.16 (the bench's ``halo``); beside a size term in peak^2 it moves
    flux_signature = "quadratic"
    description = "every boundary shift times (1 + s): a calibration amplitude error"

    def templates(self, observables):
        if observables.sizes is None:
            return {}
        step = 0.1
        shifts = observables.spot_model.shifts.scaled(1.0 + step)
        return {"sizes": _size_template(observables, step, shifts=shifts)}


#: The catalogue tested by `bfpsf.diagnosis.loop.diagnose`, in report order.
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
