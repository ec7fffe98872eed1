"""The size prediction's global nuisances: the flats' BF scale and their X / Y split.

The predicted BF slope of the stars is no better than its flats. Two numbers carry that
error into the closed loop (`bfpsf.diagnosis.problem.global_priors`): a common scale of the
boundary shifts and a move of their X / Y split (`bfpsf.diagnosis.catalogue.split_shifts`),
each with a Gaussian prior of the width the calibration's shift samples give
(`bfpsf.diagnosis.observables.bf_scale_error`). Each is fitted in-sample, held fixed on the
held-out data, tested by its signature like a candidate, reported, and applied by
``--output-calib`` (`bfpsf.diagnosis.refine`). This module is the one list of them: every
consumer iterates over `GLOBAL_NUISANCES`, in this order (the scale first: the split exists
only beside it).
"""

import dataclasses
from dataclasses import dataclass

from .catalogue import get_effect

__all__ = ["GlobalNuisance", "GLOBAL_NUISANCES", "SCALE", "SPLIT", "HELDOUT_LABEL",
           "PRIOR_NSIGMA", "without_priors", "beyond_the_flats"]

#: How many of the flats' prior a global nuisance may lie from zero.
PRIOR_NSIGMA = 3.0


@dataclass(frozen=True)
class GlobalNuisance:
    """One global nuisance of the size prediction and the words each consumer uses for it."""

    #: Its name in every record (the loop's ``nuisance``, the refined calibration, reports).
    name: str
    #: The observables' ``meta`` key of its prior width.
    error_key: str
    #: The key of its in-sample value in `DiagnosisResult.folded`.
    folded_key: str
    #: What the verdict calls it ("the ... is contradicted by ...").
    what: str
    #: The report's heading and what its prior is.
    title: str
    prior_text: str
    #: The room it leaves an undeclared effect (`bfpsf.diagnosis.unexplained.hiding_room`):
    #: the share of its prior one axis moves by, which axes, and its short name.
    room_share: float
    room_kind: str
    short: str
    #: How ``--output-calib`` applies it.
    how: str


SCALE = GlobalNuisance(
    name="calibration_scale", error_key="scale_err", folded_key="scale_nuisance",
    what="size scale", title="Size-prediction scale",
    prior_text=("the spread of the predicted size slope over the calibration's shift samples, "
                "which carries every shift's error, not a(0, 0)'s alone"),
    room_share=1.0, room_kind="isotropic", short="scale", how="shifts times (1 + s)")

SPLIT = GlobalNuisance(
    name="calibration_split", error_key="split_err", folded_key="split_nuisance",
    what="X / Y split of the size prediction", title="Size-prediction X / Y split",
    prior_text=("the spread of the predicted X slope over the Y slope over the shift samples: "
                "a^E against a^N"),
    # a split d moves each axis by about d / 2
    room_share=0.5, room_kind="on one axis", short="X / Y split",
    how="a^E times exp(d / 2), a^N times exp(-d / 2)")

GLOBAL_NUISANCES = (SCALE, SPLIT)

#: The held-out step of the global nuisances (`bfpsf.diagnosis.heldout`): it confirms the
#: scale and the split together, under the scale's name.
HELDOUT_LABEL = f"{SCALE.name} (nuisance)"


def without_priors(part, keys):
    """Observables ``part`` (or None) without the priors of some global nuisances (their
    ``error_key`` in its ``meta``, ``keys``): the loop then has no column for them."""
    return None if part is None else dataclasses.replace(
        part, meta={key: value for key, value in part.meta.items() if key not in keys})


def beyond_the_flats(name, value, error, prior):
    """What a global nuisance's ``value`` (with its ``error``) contradicts: ``'flats_prior'``
    beyond `PRIOR_NSIGMA` of the flats' ``prior``, ``'bounds'`` for a scale outside its
    physical range (`bfpsf.diagnosis.catalogue.CalibrationScale.bounds`: a new user's
    isotropic spill was taken as +1.5, within 2.2 sigma of 150^2 flats); None where neither.
    The loop tests its fit so, and ``--output-calib`` a value refitted without an effect the
    calibration cannot hold (a new user's scale refitted to +1.496 had been applied unsaid)."""
    if abs(value) > PRIOR_NSIGMA * prior:
        return "flats_prior"
    if name == SCALE.name and not get_effect(SCALE.name).allows([value], [error]):
        return "bounds"
    return None
