"""The loop's result as a calibration: what the stars found, folded into what ``psf`` uses.

`refine_calibration` takes the flats' `Calibration` and a `DiagnosisResult` and returns a new
`Calibration` in which each selected (and, with a held-out split, confirmed) effect goes where
the PSF model can use it:

* ``calibration_scale`` (the candidate and the size block's scale nuisance): every boundary
  shift times (1 + s);
* ``calibration_split`` (the size block's split nuisance): a^E times exp(d / 2) and a^N
  times exp(-d / 2) (`bfpsf.diagnosis.catalogue.split_shifts`): the X / Y share the stars
  fix within the flats' error of it;
* ``xy_anisotropy``: the area-preserving quadrupole of the nearest boundaries
  (`bfpsf.diagnosis.catalogue.quadrupole_shifts`) added to the shifts: the flux dependence of
  star sizes in X and Y constrains what the flats cannot see;
* ``gain_nonlinearity``: a linearity correction applied to the images on input
  (`linearise`, inverse of v = q (1 + c q / 1e5));
* ``second_order``: the PSF integrates the build-up of the shifts during the exposure
  (``buildup_steps``; the model's own second order, not the fitted amplitude);
* ``flux_diffusion``, ``boundary_density``, ``sum_rule_tail``, ``chromatic_size`` and
  ``readout_pedestal`` are recorded but not applied (P(F) has no flux-dependent blur term; P0
  fitted from the stars holds the flux-independent part; the pedestal is already subtracted by
  the calibration), and the refinement says so;
* when a size residual is left that no catalogue effect matches, the loop's EMPIRICAL term
  (`bfpsf.model.empirical.EmpiricalTerm`, with its out-of-sample validation) is stored in
  ``refinement['empirical']``: the PSF model applies it (`EmpiricalTerm.from_calibration`),
  and it is labelled empirical wherever it is reported.

The provenance (effects, parameters, errors, whether the held-out data confirmed them, the input
files) is kept in ``Calibration.refinement`` and written to the file's REFINE extension.
"""

import dataclasses

import numpy as np

from ..errors import BFPSFValueError
from ..outputs import json_safe
from ..calibration.linearity import linearise
from .catalogue import add_shifts, quadrupole_shifts, split_shifts
from .nuisances import GLOBAL_NUISANCES, HELDOUT_LABEL, SCALE, SPLIT, beyond_the_flats

__all__ = ["refine_calibration", "linearise", "undo_refined_linearity", "BUILDUP_STEPS",
           "NOT_APPLIED", "unapplied"]

#: Build-up steps the PSF integrates when the loop found a second-order term.
BUILDUP_STEPS = 16

NOT_APPLIED = {
    "flux_diffusion": "P(F) has no flux-dependent blur term; P0 fitted from the stars holds "
                      "the flux-independent diffusion",
    "boundary_density": "needs the optical profile (density_profile) of the PSF model",
    "sum_rule_tail": "a change of a(0, 0) beyond the measured lags: recalibrate with more lags",
    "chromatic_size": "a colour term of the size, not of the brighter-fatter response",
    "readout_pedestal": "the calibration already subtracts the readout pedestal",
    "second_order": "a negative second order is not the build-up's (which strengthens BF); "
                    "the scale and anisotropy were refitted without it",
}


def unapplied(selected):
    """{named effect: why} of the effects ``selected`` that no refined calibration applies
    (`NOT_APPLIED`), but for the readout pedestal, which the calibration subtracts already:
    what they explain stays in every product's residual."""
    return {name: NOT_APPLIED[name.split("@")[0]] for name in selected
            if name.split("@")[0] in NOT_APPLIED and not name.startswith("readout_pedestal")}


def undo_refined_linearity(image_e, calibration):
    """The image with the linearity correction of a refined calibration undone on input
    (`linearise`), and that correction c per 1e5 e- (0 and the image itself when the
    calibration holds none): what ``bfpsf psf`` and ``bfpsf photometry`` apply.

    Parameters
    ----------
    image_e : ndarray
        Measured values, e-.
    calibration : Calibration
        One amplifier's calibration (``refinement['linearity_c_per_1e5']``).

    Returns
    -------
    (ndarray, float)
    """
    c = float(calibration.refinement.get("linearity_c_per_1e5") or 0.0)
    return (linearise(image_e, c) if c else image_e), c


def refine_calibration(calibration, result, *, provenance=None):
    """A copy of ``calibration`` with the loop's effects folded in (module docstring).

    Parameters
    ----------
    calibration : Calibration
        The flats' calibration the loop started from (its shifts are the base model's).
    result : DiagnosisResult
        With a held-out split, only confirmed effects are folded in.
    provenance : dict, optional
        What the effects came from (input files, split), JSON-serialisable.

    Returns
    -------
    Calibration
        ``shifts`` refined, ``refinement`` holding the record.
    """
    if calibration.shifts is None:
        msg = "the calibration has no boundary shifts to refine"
        raise BFPSFValueError(msg)
    shifts = calibration.shifts
    anisotropy = None
    applied, not_applied, parameters = {}, {}, {}
    linearity_c, buildup = 0.0, None
    folded = result.folded or {"names": [], "effects": {}}
    nuisances = {}  # the global nuisances applied: name -> value
    for entry in GLOBAL_NUISANCES:
        value = folded.get(entry.folded_key)
        if value is None:
            continue
        label = f"{entry.name} (nuisance)"
        fitted = result.nuisance.get(entry.name) or {}
        against = fitted.get("contradicted_by")
        # refitted without an effect the calibration cannot hold, the value must still pass
        # the test the loop's own did
        beyond = beyond_the_flats(entry.name, value, fitted.get("error", 0.0),
                                  fitted.get("prior", np.inf))
        if not against and beyond:
            against = f"{beyond} (refitted to {value:+.3f})"
        if against:
            not_applied[label] = (f"its signature is contradicted by {against} (an effect "
                                  "outside the catalogue)")
        elif result.confirmed.get(HELDOUT_LABEL, True):
            # the held-out step of the global nuisances confirms the scale and split together
            nuisances[entry.name] = value
            applied[label] = entry.how
            parameters[label] = dict(result.nuisance[entry.name], value=value)
    scale = nuisances.get(SCALE.name, 0.0)
    split = nuisances.get(SPLIT.name, 0.0)
    for name in result.selected:
        family = name.split("@")[0]
        parameters[name] = result.parameters[name]
        if not result.confirmed.get(name, True):
            not_applied[name] = "not confirmed on the held-out data"
            continue
        if name not in folded["names"]:
            not_applied[name] = NOT_APPLIED.get(family, "no place in the calibration")
            continue
        # the values of the joint fit of what the calibration holds
        value = folded["effects"][name]
        parameters[name] = dict(parameters[name], folded_value=value)
        if family == SCALE.name:
            scale += value[0]
            applied[name] = "shifts times (1 + s)"
        elif family == "xy_anisotropy":
            anisotropy = quadrupole_shifts(calibration.shifts, value[0])
            shifts = add_shifts(shifts, anisotropy)
            applied[name] = "quadrupole of the nearest boundaries added to the shifts"
        elif family == "gain_nonlinearity":
            linearity_c = float(value[0])
            applied[name] = "linearity correction of the images on input"
        elif family == "second_order":
            buildup = BUILDUP_STEPS
            applied[name] = f"build-up of the shifts integrated in {BUILDUP_STEPS} steps"

    # each sample of the flats' shifts carries its own scale and split (`bf_scale_error`):
    # where the stars fixed them, the sample is re-centred on the stars' values, drawn within
    # the fit's errors, so the refined calibration's spread is the stars' in those two
    # directions and the flats' in the others
    count = 0 if calibration.shift_samples_north is None else len(calibration.shift_samples_north)
    own = {name: draws for name in nuisances
           if (draws := np.asarray(result.nuisance[name].get("draws") or [], float)).size == count}
    rng = np.random.default_rng(0)

    def refine_sample(index, sample):
        sample = sample if anisotropy is None else add_shifts(sample, anisotropy)
        sample_scale, sample_split = scale, split
        if SCALE.name in own:
            sample = sample.scaled(1.0 / (1.0 + own[SCALE.name][index]))
            sample_scale += rng.normal(0.0, result.nuisance[SCALE.name]["error"])
        if SPLIT.name in own:
            sample = split_shifts(sample, -own[SPLIT.name][index])
            sample_split += rng.normal(0.0, result.nuisance[SPLIT.name]["error"])
        return split_shifts(sample.scaled(1.0 + sample_scale), sample_split)

    shifts = split_shifts(shifts.scaled(1.0 + scale), split) if scale or split else shifts
    # the calibration's uncertainty follows the same refinement, sample by sample
    samples = {}
    if calibration.shift_samples_north is not None:
        refined = [refine_sample(index, sample)
                   for index, sample in enumerate(calibration.shift_samples())]
        samples = {"shift_samples_north": np.array([sample.north for sample in refined]),
                   "shift_samples_east": np.array([sample.east for sample in refined])}
        if len(refined) >= 2:
            samples["shifts_north_err"] = samples["shift_samples_north"].std(axis=0, ddof=1)
            samples["shifts_east_err"] = samples["shift_samples_east"].std(axis=0, ddof=1)
    refinement = {"effects": list(result.selected), "parameters": parameters,
                  "applied": applied, "not_applied": not_applied,
                  "confirmed": dict(result.confirmed), "holdout": result.holdout,
                  "linearity_c_per_1e5": linearity_c, "buildup_steps": buildup,
                  "scale": scale, "split": split, "provenance": dict(provenance or {})}
    if result.empirical and not result.empirical.get("validation", {}).get("validated", True):
        not_applied["empirical"] = ("the EMPIRICAL term did not lower the slope residual on "
                                    "data it was not fitted on")
    elif result.empirical:
        # what no physics explained: the EMPIRICAL term (`bfpsf.model.empirical`), applied by
        # every consumer of the calibration and labelled empirical in every report
        refinement["empirical"] = result.empirical
        applied["empirical"] = ("EMPIRICAL flux-dependent size term learned from the stars "
                                "(not physics)")
    return dataclasses.replace(calibration, shifts=shifts, refinement=json_safe(refinement),
                               **samples)

