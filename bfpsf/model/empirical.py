"""An EMPIRICAL flux-dependent correction to P(F): what the stars show and no physics explains.

When the closed loop (`bfpsf.diagnosis`) finds a residual that no catalogue effect matches, the
user still needs a PSF that works. The empirical term is a low-order basis in flux times a
pixel-space pattern, with a position and an exposure dependence where the residual shows one:

    image(F) = BF image(F) + sum_k [(F / F_ref) c_k(x, t) + (F / F_ref)^2 q_k(x, t)] B_k[image(F)]

with the charge-conserving, centroid-preserving patterns of a charge-dependent transfer (each
pixel passing its neighbours a fraction of its charge proportional to that charge, as every
charge-driven effect of a CCD does at first order)

    B_xx[I] = 1/2 d^2/dx^2 (I^2) F / sum(I^2)   (three-point, along columns; F the star's
                                                 flux, by default sum(I)),
    B_yy[I] = the same along rows,
    B_xy[I] = half the difference of the same along the two diagonals (x = y and x = -y),

B_xx and B_yy each adding c_k F / F_ref + q_k (F / F_ref)^2 pixel^2 to the second moment
along its axis of any star, B_xy as much to Mxy alone (exactly for the unweighted moments of
a pixelised image away from its edges; no transfer crosses the stamp's edge, so the flux is
conserved exactly), and

    c_k(x, y, t) = constant_k + position_k (x - x_ref) / 1000 + row_k (y - y_ref) / 1000
                   + exposure_k (t - t_ref),
    q_k(x, y, t) = the same with flux2_k, flux2_position_k, flux2_row_k, flux2_exposure_k,

x the column (distance from the amplifier, pixels), y the row (the parallel transfers), t the
exposure's order in the night. F_ref
is 1e6 e- of total flux. It is labelled empirical everywhere: it describes, it does not
explain, and it is valid only over the fluxes, positions and exposures it was learned on.

Pattern kinds (`bfpsf.model.empirical_patterns`; ``kind``): the squared charge's above
(`PATTERN_KIND`, a transfer of each pixel's charge in proportion to it) and the charge's,
B_k[I] = 1/2 d^2 I / dx^2 F / sum(I) (`CHARGE_KIND`, a smear whose variance grows with the
star's flux), each to the nearest pixels or to a Gaussian reach of 2, 4 or 8 pixels (a halo;
`bfpsf.model.empirical_patterns.REACHES`). The term is fitted to the stars' adaptive
(Gaussian-weighted) sizes and used by PSF photometry, which weights the pixels by their
variance; the two agree only when the pattern has the shape of the effect, and the sizes cannot tell the kinds apart: ``bfpsf
diagnose`` learns every kind and keeps the one whose held-out stars the P(F) it gives fits
the best (`bfpsf.diagnosis.pattern_choice`). The P0 fit gives the term the amplitude the
stars' pixels ask for (``amplitude``; `bfpsf.model.psf_fit_empirical`). On the
bench's transfer the square's held-out photometry drift is 0.14 mmag (0.37 without a term,
1.1 with the charge's); on a new user's smear growing over the night, P0 took what the
square left in the bright stars and the faint ones came out +0.63 mmag bright against the
same stars without the smear, +0.14 with the charge's (docs/undeclared_effects.md). A
record without its kind (written before 2026-11) is refused (`from_dict`).

Odd (centroid- and skew-like) residuals are reported by the loop but not corrected: a PSF fit
takes a flux-dependent centroid shift into its position.
"""

import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import BFPSFValueError
from .empirical_patterns import (CHARGE_KIND, FLUX_REFERENCE, PATTERN_KIND, PATTERN_KINDS,
                                 PATTERNS, apply_pattern, pattern_series, pattern_tables)

log = logging.getLogger(__name__)

__all__ = ["EmpiricalTerm", "PATTERNS", "PATTERN_KIND", "CHARGE_KIND", "PATTERN_KINDS",
           "FLUX_REFERENCE", "apply_pattern",
           "pattern_series", "empirical_of", "with_empirical", "pattern_tables"]

_TERMS = ("constant", "position", "row", "exposure", "flux2", "flux2_position", "flux2_row",
          "flux2_exposure")
#: The terms that change over the detector: along the columns and along the rows.
_FIELD_TERMS = ("position", "flux2_position", "row", "flux2_row")


@dataclass(frozen=True)
class EmpiricalTerm:
    """The empirical correction (module docstring), learned by `bfpsf.diagnosis.empirical_fit`.

    Attributes
    ----------
    coefficients : dict
        Pattern (``'xx'``, ``'yy'``, ``'xy'``; a missing one is 0: a record fitted before the
        diagonal pattern holds two) -> {``constant`` (pixel^2 per F_ref), ``position``
        (pixel^2 per F_ref per 1000 pixels of column), ``row`` (the same per 1000 rows),
        ``exposure`` (pixel^2 per F_ref per exposure), ``flux2``, ``flux2_position``,
        ``flux2_row``, ``flux2_exposure`` (the same for q, pixel^2 per F_ref^2)}; missing
        terms are 0.
    errors : dict
        Same layout: 1-sigma errors.
    x_reference, y_reference : float
        Column the position term and row the row term are centred on, pixels.
    exposure_reference : float
        Exposure order the exposure term is centred on.
    validation : dict
        How it did on data it was not fitted on (`bfpsf.diagnosis.empirical_fit`).
    label : str
        Always ``'empirical'``.
    x_range, y_range : (float, float) or None
        Columns and rows of the stars it was learned on, pixels (a PSF model that applies a
        position or row term takes them as its field nodes,
        `bfpsf.model.psf.FluxDependentPSF.field_nodes`).
    exposure_range : (float, float) or None
        Exposure orders it was learned on (0-based, in the order of the images given to
        ``bfpsf diagnose``).
    kind : str
        Its patterns' kind, one of `PATTERN_KINDS` (default the squared charge's).
    amplitude : float
        What the coefficients learned from the stars' sizes were multiplied by to fit the
        stars' pixels (`bfpsf.model.psf_fit.fit_psf`; `scaled`): 1 in a refined calibration.
    covariance : dict
        The fit's covariance of its coefficients: ``names`` ([pattern, term] pairs) and
        ``matrix`` (pixel^4 per the terms' units); empty when not known. What a prediction
        from the term is uncertain by (`bfpsf.diagnosis.empirical_fit.evaluate_empirical`);
        a term evaluated at a position or an exposure (`at`) has none.
    """

    coefficients: dict
    errors: dict = field(default_factory=dict)
    x_reference: float = 0.0
    exposure_reference: float = 0.0
    validation: dict = field(default_factory=dict)
    label: str = "empirical"
    x_range: tuple = None
    y_reference: float = 0.0
    y_range: tuple = None
    exposure_range: tuple = None
    kind: str = PATTERN_KIND
    covariance: dict = field(default_factory=dict)
    amplitude: float = 1.0

    def __post_init__(self):
        if self.kind not in PATTERN_KINDS:
            msg = f"empirical pattern kind must be one of {PATTERN_KINDS}, got {self.kind!r}"
            raise BFPSFValueError(msg, self.kind)
        for pattern, terms in self.coefficients.items():
            if pattern not in PATTERNS or set(terms) - set(_TERMS):
                msg = (f"empirical coefficients must map {PATTERNS} to {_TERMS}, got "
                       f"{pattern!r}: {sorted(terms)}")
                raise BFPSFValueError(msg, pattern)
            if not all(np.isfinite(value) for value in terms.values()):
                msg = f"empirical coefficients of {pattern!r} must be finite, got {terms}"
                raise BFPSFValueError(msg, terms)

    def coefficient(self, pattern, x=None, exposure=None, *, order=1, y=None):
        """c_k (``order=1``, pixel^2 per F_ref) or q_k (``order=2``, per F_ref^2) at column
        ``x``, row ``y`` and exposure order ``exposure`` (the references when None)."""
        terms = self.coefficients.get(pattern, {})
        prefix = "" if order == 1 else "flux2_"
        value = terms.get("constant" if order == 1 else "flux2", 0.0)
        if x is not None:
            value = value + terms.get(prefix + "position", 0.0) * (
                np.asarray(x, float) - self.x_reference) / 1000.0
        if y is not None:
            value = value + terms.get(prefix + "row", 0.0) * (
                np.asarray(y, float) - self.y_reference) / 1000.0
        if exposure is not None:
            value = value + terms.get(prefix + "exposure", 0.0) * (
                np.asarray(exposure, float) - self.exposure_reference)
        return value

    def variance_change(self, flux, x=None, exposure=None, *, y=None):
        """(dMxx, dMyy, dMxy) of a star of total flux ``flux`` (e-) at column ``x`` and row
        ``y``, pixel^2 (`PATTERNS`)."""
        scale = np.asarray(flux, float) / FLUX_REFERENCE
        return tuple(scale * self.coefficient(pattern, x, exposure, y=y)
                     + scale ** 2 * self.coefficient(pattern, x, exposure, order=2, y=y)
                     for pattern in PATTERNS)

    def delta(self, image, flux, x=None, exposure=None, total=None, *, y=None):
        """The term's change of a star image of total flux ``flux`` (e-) at column ``x`` and
        row ``y``, image units; ``total`` is that flux in the image's unit (default the
        image's sum: `apply_pattern`)."""
        changes = self.variance_change(float(flux), x, exposure, y=y)
        out = np.zeros_like(np.asarray(image, float))
        for pattern, change in zip(PATTERNS, changes):
            if change:
                out = out + float(change) * apply_pattern(image, pattern, total, self.kind)
        return out

    def _depends_on(self, names):
        return any(terms.get(name, 0.0) for terms in self.coefficients.values()
                   for name in names)

    @property
    def position_dependent(self):
        """True when a coefficient changes over the detector (a ``position`` term along the
        columns or a ``row`` term)."""
        return self._depends_on(_FIELD_TERMS)

    @property
    def column_dependent(self):
        """True when a coefficient changes with the column."""
        return self._depends_on(("position", "flux2_position"))

    @property
    def row_dependent(self):
        """True when a coefficient changes with the row."""
        return self._depends_on(("row", "flux2_row"))

    def at(self, x=None, exposure=None, y=None):
        """The term with its position and exposure dependence evaluated: constants only (for
        a PSF that holds one position and one exposure)."""
        return self.at_exposure(exposure).at_position(x, y)

    def at_exposure(self, exposure=None):
        """The term at exposure order ``exposure`` (default its reference): the exposure
        terms folded into the constants, the position terms kept (a PSF of one exposure
        applies them at each star's column)."""
        coefficients = {}
        for pattern, terms in self.coefficients.items():
            coefficients[pattern] = {name: value for name, value in terms.items()
                                     if name in _FIELD_TERMS}
            coefficients[pattern]["constant"] = float(self.coefficient(pattern, None,
                                                                       exposure))
            coefficients[pattern]["flux2"] = float(self.coefficient(pattern, None, exposure,
                                                                    order=2))
        reference = self.exposure_reference if exposure is None else float(exposure)
        return self._replaced(coefficients, exposure_reference=reference)

    def scaled(self, factor):
        """The term with every coefficient (and error) times ``factor``, and ``amplitude``
        with it."""
        def times(table):
            return {pattern: {name: factor * value for name, value in terms.items()}
                    for pattern, terms in table.items()}

        return self._replaced(times(self.coefficients), errors=times(self.errors),
                              amplitude=float(self.amplitude * factor))

    def _replaced(self, coefficients, **references):
        """A copy with other coefficients (and references); the covariance, which is the
        original coefficients', is not carried."""
        options = {"errors": self.errors, "x_reference": self.x_reference,
                   "y_reference": self.y_reference,
                   "exposure_reference": self.exposure_reference,
                   "validation": self.validation, "x_range": self.x_range,
                   "y_range": self.y_range, "exposure_range": self.exposure_range,
                   "kind": self.kind, "amplitude": self.amplitude}
        options.update(references)
        return EmpiricalTerm(coefficients, **options)

    def at_position(self, x=None, y=None):
        """The term at column ``x`` and row ``y`` (default its references): the position and
        row terms folded into the constants (the exposure terms kept)."""
        if not self.position_dependent or (x is None and y is None):
            return self
        coefficients = {}
        for pattern, terms in self.coefficients.items():
            coefficients[pattern] = {name: value for name, value in terms.items()
                                     if name in ("exposure", "flux2_exposure")}
            field_only = EmpiricalTerm({pattern: {key: value for key, value in terms.items()
                                                  if key not in ("exposure",
                                                                 "flux2_exposure")}},
                                       x_reference=self.x_reference,
                                       y_reference=self.y_reference)
            for name, order in (("constant", 1), ("flux2", 2)):
                coefficients[pattern][name] = float(field_only.coefficient(
                    pattern, x, order=order, y=y))
        return self._replaced(coefficients,
                              x_reference=self.x_reference if x is None else float(x),
                              y_reference=self.y_reference if y is None else float(y))

    def to_dict(self):
        """JSON-ready form (stored in a refined calibration's ``refinement['empirical']`` and
        in the PSF product's ``EMPIRIC`` HDU)."""
        record = {"label": self.label, "coefficients": self.coefficients,
                  "errors": self.errors, "x_reference": float(self.x_reference),
                  "exposure_reference": float(self.exposure_reference),
                  "flux_reference_e": FLUX_REFERENCE,
                  "patterns": [pattern for pattern in PATTERNS if pattern in self.coefficients],
                  "pattern": self.kind,
                  "validation": self.validation}
        if self.x_range is not None:
            record["x_range"] = [float(value) for value in self.x_range]
        if self.y_range is not None:
            record["y_range"] = [float(value) for value in self.y_range]
        if self.y_reference:
            record["y_reference"] = float(self.y_reference)
        if self.exposure_range is not None:
            record["exposure_range"] = [float(value) for value in self.exposure_range]
        if self.amplitude != 1.0:
            record["amplitude"] = float(self.amplitude)
        if self.covariance:
            record["covariance"] = {"names": [list(name) for name in self.covariance["names"]],
                                    "matrix": np.asarray(self.covariance["matrix"],
                                                         float).tolist()}
        return record

    @classmethod
    def from_dict(cls, record):
        """Inverse of `to_dict`."""
        if record.get("label") != "empirical":
            msg = f"not an empirical term record (label {record.get('label')!r})"
            raise BFPSFValueError(msg, record.get("label"))
        if record.get("pattern") not in PATTERN_KINDS:
            msg = (f"empirical term fitted with another pattern "
                   f"({record.get('pattern') or 'the half second difference of the image'}; "
                   f"this bfpsf uses the {' or the '.join(PATTERN_KINDS)}): its coefficients "
                   f"do not apply; run bfpsf diagnose --output-calib again")
            raise BFPSFValueError(msg, record.get("pattern"))
        if float(record.get("flux_reference_e", FLUX_REFERENCE)) != FLUX_REFERENCE:
            msg = (f"empirical term with flux reference {record['flux_reference_e']} e-; this "
                   f"bfpsf uses {FLUX_REFERENCE}")
            raise BFPSFValueError(msg, record["flux_reference_e"])
        return cls({pattern: {key: float(value) for key, value in terms.items()}
                    for pattern, terms in record["coefficients"].items()},
                   errors=record.get("errors", {}),
                   x_reference=float(record.get("x_reference", 0.0)),
                   exposure_reference=float(record.get("exposure_reference", 0.0)),
                   validation=record.get("validation", {}),
                   x_range=None if record.get("x_range") is None else tuple(
                       float(value) for value in record["x_range"]),
                   y_reference=float(record.get("y_reference", 0.0)),
                   y_range=None if record.get("y_range") is None else tuple(
                       float(value) for value in record["y_range"]),
                   exposure_range=None if record.get("exposure_range") is None else tuple(
                       float(value) for value in record["exposure_range"]),
                   kind=record["pattern"], covariance=record.get("covariance", {}),
                   amplitude=float(record.get("amplitude", 1.0)))

    @classmethod
    def from_calibration(cls, calibration):
        """The empirical term a refined calibration holds, or None."""
        record = (getattr(calibration, "refinement", None) or {}).get("empirical")
        return None if not record else cls.from_dict(record)


def empirical_of(calibrations, exposure=None):
    """The one EMPIRICAL term of some calibrations (a refined calibration's, at exposure
    order ``exposure``, its position terms kept), or None when none holds one. Every
    consumer of a calibration takes the term through here (`bfpsf.workflow.psf_from_images`,
    the Piff and GalSim plug-ins)."""
    if not isinstance(calibrations, (list, tuple)):
        calibrations = [calibrations]
    terms = [EmpiricalTerm.from_calibration(calibration) for calibration in calibrations]
    records = {repr(term.to_dict()): term for term in terms if term is not None}
    if len(records) > 1 or (records and None in terms):
        msg = ("the calibrations hold different EMPIRICAL terms (or some none); one PSF "
               "applies one (refine them together with bfpsf diagnose)")
        raise BFPSFValueError(msg, len(records))
    if not records:
        return None
    term = next(iter(records.values()))
    _warn_exposure(term, exposure)
    return term.at_exposure(exposure)


def _warn_exposure(term, exposure):
    """A warning where a term that changes over the night is applied without an exposure
    order, or beyond the orders it was learned on (a new user's late exposures kept 70 % of
    a night-growing excess at the silent default, the middle of the learned night)."""
    changes = any(terms.get(name, 0.0) for terms in term.coefficients.values()
                  for name in ("exposure", "flux2_exposure"))
    if not changes:
        return
    learned = term.exposure_range
    span = "" if learned is None else f" {learned[0]:g} to {learned[1]:g}"
    if exposure is None:
        log.warning("the calibration's EMPIRICAL term changes over the night; it is applied at "
                    "exposure order %g, the middle of the exposures it was learned on%s: give "
                    "the images' order (--exposure-order; 0-based, in the order of the images "
                    "given to bfpsf diagnose)", term.exposure_reference, span)
    elif learned is not None and not learned[0] <= exposure <= learned[1]:
        log.warning("exposure order %g is outside the orders the EMPIRICAL term was learned "
                    "on (%g to %g): it is extrapolated", exposure, learned[0], learned[1])


def with_empirical(psf, calibration, *, x=None, exposure=None):
    """A copy of ``psf`` (any `BFPSFModel` kind) applying the EMPIRICAL term of a refined
    calibration at exposure order ``exposure`` (and, when ``x`` is given, at column ``x``
    only; default: at each star's column); ``psf`` itself when the calibration holds none
    (every calibration not refined by the loop)."""
    term = empirical_of(calibration, exposure)
    if term is None:
        return psf
    out = psf.copy()
    out.empirical = term.at_position(x)
    return out
