"""The interface every flux-dependent PSF kind shares (as GalSim's ``GSObject`` for profiles).

`BFPSFModel` is the base of the single P(F) (`~bfpsf.model.psf.FluxDependentPSF`) and of the
field-varying P(F, x, y) (`~bfpsf.model.gridded.GriddedFluxDependentPSF`). A PSF fitted with
each amplifier's boundary shifts (``amplifier_shifts``) and one built from a calibration refined
by ``bfpsf diagnose --output-calib`` (build-up steps, a linearity correction of the images) are
these same classes with that metadata, so every kind answers the same calls:

=========================================  ==================================================
``psf.star_image(flux, x, y)``             pixel image of a star of flux F at (x, y)
``psf.shape(flux, x, y)``                  adaptive moments of the model a fitter sees there
``psf.at(x, y)``                           the single P(F) at (x, y) (a single PSF: itself)
``psf.with_flux_unit(unit, gain)``         the same PSF for images in e- or ADU
``psf.with_shifts(shifts)``                other boundary shifts, same P0
``psf.for_amplifier(name)``                the model of one amplifier's stars
``psf.charge_delta(charge_e)``             the model's own BF operator on any charge image
``psf.to_galsim(flux, x, y)``              a GalSim profile (pixel response included)
``psf.write(path)`` / ``read(path)``       the PSF product (``save`` / ``load`` alike)
``psf == other``, ``pickle.dumps(psf)``    value equality; pickling (Dask ships models)
=========================================  ==================================================

Every kind is a photutils-compatible model itself (``flux``, ``x_0``, ``y_0``; stateless
``evaluate``), so no caller needs to test which kind it holds.

Product metadata carried by every kind (kept by the PSF product, `bfpsf.model.product`):
``calibration`` (file name), ``shift_samples`` (the calibration's uncertainty),
``amplifier_shifts`` ({EXTNAME: BoundaryShifts}), ``linearity_c_per_1e5`` (a refined
calibration's linearity correction, applied to the images on input by
`bfpsf.measure.prepare.prepare_image`), and ``flux_correction`` / ``flux_correction_err``: the ratio of
a star's total flux to the flux P0 holds in its support (the wings beyond it), measured from
the bright isolated stars, applied by photometry so that ``flux_fit`` is the total flux, with
its change across the image, ``flux_correction_slope`` (per pixel, with its
``flux_correction_slope_err``) about ``flux_correction_centre`` (a grid's; `flux_correction_at`),
the profile of those wings, ``wing_coefficients``, ``wing_tail_power`` and ``wing_half_size``
(`bfpsf.model.wings.WingModel`, its nodes set by the support it was fitted beyond: 12 for
``--size 25``, where the model's stamp ``half_size`` is 13), whose glow the sky estimate
leaves out; and
``empirical``: the EMPIRICAL term of a calibration refined by ``bfpsf diagnose
--output-calib`` (`bfpsf.model.empirical.EmpiricalTerm`, None without one), which every
evaluation applies (``evaluate`` in both modes, ``star_image``, ``shape``, ``to_galsim``).
"""

import copy
import logging

import numpy as np
from astropy.modeling import Fittable2DModel, Parameter

from ..errors import BFPSFValueError
from ..moments.result import MomentsFlag
from ..moments.shapes import calibration_shape_error, psf_shape
from .galsim_profile import to_galsim
from .product import read_psf, register_kind, write_psf

log = logging.getLogger(__name__)

__all__ = ["BFPSFModel"]

#: How `bfpsf.model.psf.FluxDependentPSF` computes its BF term (a table of R at every phase,
#: or R at the exact phase of each evaluation).
MODES = ("table", "exact")
#: The flux units of a model: e- or ADU (with its gain).
FLUX_UNITS = ("electron", "adu")


def validate_oversampling(oversampling):
    values = np.atleast_1d(np.asarray(oversampling))
    if values.size == 1:
        values = np.repeat(values, 2)
    if (values.size != 2 or not np.all(np.isfinite(values))
            or np.any(values != np.round(values)) or np.any(values < 1)):
        msg = f"oversampling must be one or two (y, x) integers >= 1, got {oversampling!r}"
        raise BFPSFValueError(msg, oversampling)
    return values.astype(int)


def validate_units(flux_unit, gain):
    """(flux_unit, gain) of a model; a gain without a stated flux unit is refused."""
    if gain is not None:
        if not (np.isfinite(gain) and gain > 0):
            msg = f"gain must be a positive number of e-/ADU, got {gain!r}"
            raise BFPSFValueError(msg, gain)
        gain = float(gain)
        if flux_unit is None:
            msg = ("gain given without flux_unit: say flux_unit='adu' (fluxes and images in "
                   "ADU, the BF term scaled by the gain) or flux_unit='electron' (the gain "
                   "only recorded for converting images)")
            raise BFPSFValueError(msg, gain)
    flux_unit = "electron" if flux_unit is None else flux_unit
    if flux_unit not in FLUX_UNITS:
        msg = f"flux_unit must be one of {FLUX_UNITS}, got {flux_unit!r}"
        raise BFPSFValueError(msg, flux_unit)
    if flux_unit == "adu" and gain is None:
        msg = "flux_unit='adu' needs the gain (e-/ADU) that turns the fluxes into charge"
        raise BFPSFValueError(msg, flux_unit)
    return flux_unit, gain


def validate_data(data):
    if not isinstance(data, np.ndarray) or data.ndim != 2:
        msg = f"data must be a 2-D numpy array [y, x], got {type(data).__name__}"
        raise BFPSFValueError(msg, getattr(data, "shape", None))
    if not np.all(np.isfinite(data)):
        msg = f"data has {np.count_nonzero(~np.isfinite(data))} non-finite values"
        raise BFPSFValueError(msg)
    if min(data.shape) < 4:
        msg = f"data must be at least 4 x 4 (cubic spline), got shape {data.shape}"
        raise BFPSFValueError(msg, data.shape)
    return np.array(data, dtype=float)

#: Metadata every kind carries (name -> default factory), copied by the derived models.
_METADATA = {"calibration": str, "linearity_c_per_1e5": float,
             "flux_correction": lambda: 1.0, "flux_correction_err": lambda: float("nan"),
             "star_flux_e": lambda: float("nan"), "p0_converged": lambda: None,
             "wing_coefficients": tuple, "wing_tail_power": lambda: 4.0, "wing_half_size": int,
             "empirical": lambda: None, "flux_correction_slope": lambda: (0.0, 0.0),
             "flux_correction_slope_err": lambda: (float("nan"),) * 2,
             "flux_correction_centre": lambda: (0.0, 0.0)}


class BFPSFModel(Fittable2DModel):
    """Base class of the flux-dependent PSF kinds (module docstring for the interface).

    Subclasses implement ``evaluate``, `at`, `star_image`, `with_shifts`, `with_flux_unit`,
    `charge_delta`, ``reference_position`` and ``_value_state``.
    """

    #: What the kind is, in words (messages).
    kind = "a flux-dependent PSF"
    #: `read` returns whatever kind the product holds (False: only this class).
    reads_any_kind = True
    #: The product kind a class writes and reads back as ('single', 'grid'; None: abstract).
    product_kind = None

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "product_kind" in cls.__dict__:  # the kind's own class, not a user's subclass
            register_kind(cls.product_kind, cls)

    flux = Parameter(default=1, description="Total flux of the star (image unit)")
    x_0 = Parameter(default=0, description="x position of the star centre (pixels)")
    y_0 = Parameter(default=0, description="y position of the star centre (pixels)")

    def _init_metadata(self):
        for name, factory in _METADATA.items():
            self.__dict__.setdefault(name, factory())

    def metadata_state(self):
        """The product metadata as a tuple (value equality; the EMPIRICAL term by its
        record)."""
        return tuple(getattr(value, "to_dict", lambda value=value: value)()
                     for value in (getattr(self, name) for name in _METADATA))

    def with_empirical_term(self, term):
        """A copy of the model applying the EMPIRICAL term ``term``
        (`bfpsf.model.empirical.EmpiricalTerm`, or None for none) in every evaluation; this
        model is left as it is."""
        out = self.copy()
        out.empirical = term
        return out

    def flux_correction_at(self, x, y):
        """``flux_correction`` at pixel (x, y): the product's, plus its change across the
        image where it was measured (``flux_correction_slope`` per pixel about
        ``flux_correction_centre``; a grid's, `bfpsf.measure.total_flux.wing_gradient`)."""
        (slope_x, slope_y), (x_0, y_0) = self.flux_correction_slope, self.flux_correction_centre
        return (self.flux_correction + slope_x * (np.asarray(x, dtype=float) - x_0)
                + slope_y * (np.asarray(y, dtype=float) - y_0))

    def copy_metadata_to(self, other, *, shift_samples=False):
        """Give ``other`` this model's product metadata (and shift samples if asked)."""
        for name in _METADATA:
            setattr(other, name, getattr(self, name))
        other.amplifier_shifts = dict(self.amplifier_shifts)
        if shift_samples:
            other.shift_samples = tuple(self.shift_samples)
        return other

    # -- the interface ---------------------------------------------------------------------
    def at(self, x, y):
        """The single `FluxDependentPSF` of a star at image position (x, y), pixels."""
        raise NotImplementedError

    @property
    def field_nodes(self):
        """(x_nodes, y_nodes), pixels: the positions the model is defined at and interpolated
        between (bilinearly, `bfpsf.model.gridded.bilinear_weights`); one node for a model
        that is the same everywhere."""
        x_ref, y_ref = self.reference_position
        return np.array([x_ref]), np.array([y_ref])

    @property
    def varies_over_field(self):
        """True when the model differs from one image position to another (a grid)."""
        return self.at() is not self

    def position_or_reference(self, x, y):
        """(x, y) with None replaced by ``reference_position`` (the grid centre of a
        field-varying model; 0 for a single one)."""
        x_ref, y_ref = self.reference_position
        return (x_ref if x is None else float(x)), (y_ref if y is None else float(y))

    def shape(self, flux, x=None, y=None):
        """Adaptive moments of the pixelised model at a flux and image position.

        The model of a star of flux F at (x, y) (``evaluate`` on the pixels around it: BF,
        pixel response and, for a field-varying model, the interpolation at (x, y) included,
        exactly what a fitter sees there) is measured with the estimator of the star
        measurements (`bfpsf.moments.adaptive.adaptive_moments`).

        Parameters
        ----------
        flux : float
            Flux, ``flux_unit``; > 0.
        x, y : float, optional
            Image position, pixels: its sub-pixel phase sets the pixelisation (R depends on
            it), and a field-varying model is taken there. Default ``reference_position``.

        Returns
        -------
        bfpsf.moments.shapes.PSFShape
            NaN with the flag ``UNDERSAMPLED`` (and a warning) where the pixelised model has
            no adaptive moments at that phase: narrower than ~0.7 px, on a pixel centre.
        """
        shape = psf_shape(self, flux, x=x, y=y)
        if shape.flags & MomentsFlag.UNDERSAMPLED:
            x_0, y_0 = self.position_or_reference(x, y)
            log.warning("the model at flux %.3g has no adaptive moments at sub-pixel phase "
                        "(%.2f, %.2f) (flag 'undersampled': the weight collapses onto the "
                        "central pixel of a model this narrow): its shape depends on the "
                        "phase; ask at another position, e.g. x + 0.5, y + 0.5", flux,
                        x_0 - np.floor(x_0 + 0.5), y_0 - np.floor(y_0 + 0.5))
        return shape

    def shape_error(self, flux, x=None, y=None):
        """The error of `shape` at ``flux`` that the calibration's boundary shifts carry
        (`bfpsf.moments.shapes.calibration_shape_error`): the stars fix the model near the
        flux they weigh in at (``star_flux_e``, e-, recorded by ``bfpsf psf``), and at other
        fluxes, a galaxy's far below them, the BF change from there comes from the shifts.

        Returns
        -------
        dict or None
            ``sigma_percent``, ``e1``, ``e2``, ``n_samples``; None without shift samples or
            without ``star_flux_e`` (a model not fitted from stars).
        """
        if not np.isfinite(self.star_flux_e):
            return None
        return calibration_shape_error(self, self.star_flux_e / self.electrons_per_unit, flux,
                                       x=x, y=y)

    def to_galsim(self, flux, x=None, y=None, *, x_phase=None, y_phase=None, normalise=True):
        """The pixelised PSF of a star of flux F at (x, y) (at its sub-pixel phase unless the
        phases are given) as a GalSim profile; see `bfpsf.model.galsim_profile.to_galsim`
        (returns ``(profile, pixel_included)``)."""
        return to_galsim(self, flux, x, y, x_phase=x_phase, y_phase=y_phase,
                         normalise=normalise)

    def for_amplifier(self, name):
        """The model of the stars of amplifier ``name`` (EXTNAME): P0 with that amplifier's
        boundary shifts (`with_shifts`) when the model has per-amplifier shifts
        (``amplifier_shifts``, from ``bfpsf psf`` on several amplifiers), else this model."""
        if not self.amplifier_shifts:
            return self
        if name not in self.amplifier_shifts:
            what = f"amplifier {name!r}" if name else "a single-HDU image"
            msg = (f"the PSF was fitted on amplifiers {', '.join(sorted(self.amplifier_shifts))}"
                   f", each with its own shifts: it has none for {what}")
            raise BFPSFValueError(msg, name)
        return self.with_shifts(self.amplifier_shifts[name])

    @property
    def electrons_per_unit(self):
        """e- per flux unit: 1 in electrons, the gain in ADU (the factor g of the BF term)."""
        return self.gain if self.flux_unit == "adu" else 1.0

    # -- astropy model interface -------------------------------------------------------------
    def copy(self):
        """Copy with the parameter values copied and the arrays, splines and nodes shared."""
        new = object.__new__(self.__class__)
        for key, value in self.__dict__.items():
            new.__dict__[key] = copy.copy(value) if key in self.param_names else value
        return new

    def deepcopy(self):
        """A copy that owns every array."""
        return copy.deepcopy(self)

    # -- the PSF product (its FITS layout is bfpsf.model.product's) -----------------------------
    def write(self, path, *, calibration=None, meta=None, overwrite=False):
        """Write the PSF product (FITS); see `bfpsf.model.product.write_psf`."""
        write_psf(self, path, calibration=calibration, meta=meta, overwrite=overwrite)

    @classmethod
    def read(cls, path, **kwargs):
        """Read a PSF product (`bfpsf.model.product.read_psf`): any kind through this class or
        `FluxDependentPSF` (``reads_any_kind``), only a grid through
        `GriddedFluxDependentPSF`."""
        if cls.product_kind == "single":  # FluxDependentPSF or a subclass: read as cls
            kwargs.setdefault("cls", cls)
        psf = read_psf(path, **kwargs)
        if not (cls.reads_any_kind or isinstance(psf, cls)):
            msg = f"{path} holds {psf.kind}, not {cls.kind}"
            raise BFPSFValueError(msg, str(path))
        return psf

    save = write
    load = read

    # -- value semantics -----------------------------------------------------------------------
    def _value_state(self):
        """Everything that makes the model what it is (arrays, shifts, options, metadata)."""
        raise NotImplementedError

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return _equal(self._value_state(), other._value_state())

    def __ne__(self, other):
        equal = self.__eq__(other)
        return equal if equal is NotImplemented else not equal

    def __hash__(self):
        # equal models share these; the parameters (mutable) and arrays stay out of it
        return hash((type(self).__name__, self.half_size, self.flux_unit, self.gain))


def _equal(left, right):
    """Equality of nested tuples, dicts and arrays (arrays by value)."""
    if isinstance(left, dict) and isinstance(right, dict):
        return left.keys() == right.keys() and all(_equal(left[k], right[k]) for k in left)
    if isinstance(left, (tuple, list)) and isinstance(right, (tuple, list)):
        return len(left) == len(right) and all(_equal(a, b) for a, b in zip(left, right))
    if isinstance(left, np.ndarray) or isinstance(right, np.ndarray):
        return np.shape(left) == np.shape(right) and np.array_equal(left, right)
    if isinstance(left, float) and isinstance(right, float) and np.isnan(left):
        return bool(np.isnan(right))  # an unknown error equals an unknown error
    return bool(left == right)
