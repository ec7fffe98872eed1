"""The loop's "after" on data it never fitted: the held-out split of the observables.

`split_observables` keeps whole exposures apart (evenly interleaved) when the sizes carry
them, and `with_heldout` measures the selected model's residual on the held-out part
(parameters fixed from the fitted part); `with_empirical` fits the EMPIRICAL term
(`bfpsf.diagnosis.empirical_fit`) where nothing physical explains the residual and measures it
on the held-out exposures and on a contiguous block of late ones.
"""

import dataclasses

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import weighted_least_squares
from ..model.empirical import PATTERN_KIND, PATTERN_KINDS
from .empirical_fit import adaptive_response, early_late, evaluate_empirical, fit_empirical
from .nuisances import HELDOUT_LABEL
from .position_split import dependent_directions
from .problem import build_problem, effect_design, summarise
from .tables import CorrelationTable, LinearityTable, Observables, PTCTable
from .tables import interleaved as _interleaved
from .unexplained import describe_unexplained

__all__ = ["split_observables", "with_heldout", "with_empirical", "term_leaves", "LEFT_NSIGMA"]

def split_observables(observables, fraction=0.5):
    """Split the observables into a part to fit and a held-out part.

    Sizes: by exposure when the table has it (``SizeTable.exposure``: whole exposures held
    out, evenly interleaved), otherwise alternate peak bins within each group. Flat tables
    (linearity, correlations, PTC): alternate flat pairs in order of mean signal. The spot
    model and ``meta`` are shared.

    Returns
    -------
    (Observables, Observables)
    """
    if not 0 < fraction < 1:
        msg = f"holdout_fraction must be between 0 and 1 (exclusive), got {fraction!r}"
        raise BFPSFValueError(msg, fraction)
    parts = {"fit": {}, "heldout": {}}
    how = None
    sizes = observables.sizes
    if sizes is not None:
        exposures = None if sizes.exposure is None else np.unique(sizes.exposure)
        if exposures is not None and exposures.size >= 2:
            held_exposures = exposures[_interleaved(exposures.size, fraction)]
            held = np.isin(sizes.exposure, held_exposures)
            how = "exposure"
        else:
            held = np.zeros(len(sizes), bool)
            for group in np.unique(sizes.group):
                members = np.flatnonzero(sizes.group == group)
                members = members[np.argsort(sizes.peak_e[members])]
                held[members[_interleaved(members.size, fraction)]] = True
            how = "alternate peak bins"
        for part, rows in (("fit", ~held), ("heldout", held)):
            if rows.sum() < 3 or len(np.unique(sizes.group[rows])) < sizes.n_groups:
                msg = (f"the {part} part of a {fraction:g} held-out split holds {rows.sum()} "
                       "size entries: too few (at least 3 and every group); give more "
                       "exposures or no held-out split (--holdout-fraction 0)")
                raise BFPSFInputError(msg, int(rows.sum()))
            parts[part]["sizes"] = sizes.subset(rows)

    def rows_by_mean(mean):
        order = np.argsort(mean)
        held = np.zeros(mean.size, bool)
        held[order[_interleaved(mean.size, fraction)]] = True
        return held

    table = observables.linearity
    if table is not None:
        held = rows_by_mean(table.mean_e)
        for part, rows in (("fit", ~held), ("heldout", held)):
            parts[part]["linearity"] = LinearityTable(table.exptime[rows], table.mean_e[rows],
                                                      table.mean_err_e[rows],
                                                      error_floor=table.error_floor)
    table = observables.correlations
    if table is not None:
        held = rows_by_mean(table.mean_e)
        for part, rows in (("fit", ~held), ("heldout", held)):
            parts[part]["correlations"] = CorrelationTable(table.mean_e[rows], table.lags,
                                                           table.r[rows], table.r_err[rows])
    table = observables.ptc
    if table is not None:
        held = rows_by_mean(table.mean_e)
        for part, rows in (("fit", ~held), ("heldout", held)):
            parts[part]["ptc"] = PTCTable(table.mean_e[rows], table.var_e[rows],
                                          table.var_err_e[rows], table.model_e[rows],
                                          table.model_slope[rows],
                                          sum_rule_err=table.sum_rule_err)
    meta = dict(observables.meta)
    meta["holdout_sizes_split_by"] = how
    return tuple(Observables(spot_model=observables.spot_model, meta=meta, **parts[part])
                 for part in ("fit", "heldout"))


def _evaluate(state, observables, step):
    """Residual model on ``observables`` with one step's effects and global nuisances fixed
    at their in-sample values and the local nuisances refitted: (problem, model,
    prediction), where ``prediction`` is (design, covariance, values) of the fixed part, what
    the model inherits from the fit (`describe_unexplained`)."""
    problem = build_problem(observables)
    by_name = state["by_name"]
    global_columns = list(problem.global_columns)
    columns = [problem.nuisance[:, global_columns]] if global_columns else []
    values = [np.asarray(step["global"], float)] if global_columns else []
    for name, effect_value in step["effects"].items():
        templates = by_name[state["family"](name)].templates(observables)
        columns.append(effect_design(problem, templates))
        values.append(np.asarray(effect_value, float))
    design = (np.column_stack(columns) if columns
              else np.zeros((problem.residual.size, 0)))
    values = np.concatenate(values) if values else np.zeros(0)
    offset = design @ values
    local = np.delete(problem.nuisance, global_columns, axis=1)
    _, _, _, model = weighted_least_squares(problem.residual - offset, problem.sigma, local)
    covariance = step.get("covariance")
    if covariance is None:  # the physical values' step: nothing fitted
        covariance = np.zeros((design.shape[1], design.shape[1]))
    return problem, model + offset, (design, covariance, values)


def _kept_step(result, state, confirmed):
    """The last step of the loop whose effects were all confirmed, with the size scale at
    zero when it was not confirmed (a contradicted one is in no step: `diagnose` ran the
    loop again without it)."""
    kept = [name for name in result.selected if confirmed.get(name, True)]
    step = next(s for s in reversed(state["steps"]) if all(n in kept for n in s["names"]))
    if step.get("global") is not None and not confirmed.get(HELDOUT_LABEL,
                                                             True):
        covariance = np.array(step["covariance"], float)
        n_global = np.size(step["global"])
        covariance[:n_global, :] = covariance[:, :n_global] = 0.0
        step = dict(step, **{"global": np.zeros_like(step["global"]),
                             "covariance": covariance})
    return step


def _size_residual(state, observables, step):
    """Measured minus predicted sigma_x, sigma_y with one step's effects and global
    nuisances (no intercepts fitted), pixels."""

    only = Observables(sizes=observables.sizes, spot_model=observables.spot_model,
                       meta=observables.meta)
    problem = build_problem(only)
    offset = np.zeros_like(problem.residual)
    for name, values in step["effects"].items():
        templates = state["by_name"][state["family"](name)].templates(only)
        offset += effect_design(problem, templates) @ np.asarray(values, float)
    if problem.global_columns and step.get("global") is not None:
        offset += problem.nuisance[:, list(problem.global_columns)] @ step["global"]
    residual = (problem.residual - offset)[problem.slices["sizes"]]
    n = len(observables.sizes)
    return residual[:n], residual[n:]


def term_validated(validation):
    """Whether `refine` applies an EMPIRICAL term: on every block it did not fit
    (``heldout``, ``late_block``), it lowers the slope residual (X and Y in quadrature, or
    the e2 slope where it has a diagonal pattern) and makes no axis, nor the e2 slope,
    worse beyond twice its error (a term that traded a Y gain for an X loss on the late
    block, +8.5 -> +15.1 +- 1.6 % of raw, had been applied)."""
    def residual(block, when, axis):
        return validation[block][when][f"slope_{axis}_percent"]

    def cross(block, when):
        return validation[block][when].get("cross")

    def passes(block):
        sizes_better = (sum(residual(block, "after", a) ** 2 for a in "xy")
                        < sum(residual(block, "before", a) ** 2 for a in "xy"))
        no_axis_worse = all(abs(residual(block, "after", a)) <= abs(residual(block, "before", a))
                            + 2 * validation[block]["after"][f"slope_{a}_percent_err"]
                            for a in "xy")
        before, after = cross(block, "before"), cross(block, "after")
        if before is None or after is None:
            return sizes_better and no_axis_worse
        e2_better = abs(after["slope_per_1e5"]) < abs(before["slope_per_1e5"])
        e2_not_worse = (abs(after["slope_per_1e5"]) <= abs(before["slope_per_1e5"])
                        + 2 * after["slope_err"])
        return (sizes_better or e2_better) and no_axis_worse and e2_not_worse

    return all(passes(block) for block in ("heldout", "late_block") if block in validation)


#: A residual the EMPIRICAL term leaves on a block it did not fit is reported beyond this many
#: errors (`term_leaves`).
LEFT_NSIGMA = 3.0


def term_leaves(validation, nsigma=LEFT_NSIGMA):
    """What the EMPIRICAL term leaves on the blocks it did not fit, beyond ``nsigma`` errors
    of zero, per block and axis: ``block``, ``axis``, ``before``, ``after``, ``error`` (% of
    the raw slope) and ``overshoot`` (the residual changed sign). `term_validated` asks that
    the term lower the residual; this says where it does not leave it consistent with zero
    (a new user's term, without the row dependence its effect had, passed with held-out X
    +45 -> -22.1 +- 6.3 % of raw, and nothing said so)."""
    left = []
    for block in ("heldout", "late_block"):
        if block not in validation:
            continue
        before, after = validation[block]["before"], validation[block]["after"]
        for axis in "xy":
            if not after.get(f"stars_show_bf_{axis}", True):
                continue  # a percentage of a slope consistent with zero means nothing
            value, error = after[f"slope_{axis}_percent"], after[f"slope_{axis}_percent_err"]
            if abs(value) > nsigma * error:
                was = before[f"slope_{axis}_percent"]
                left.append({"block": block, "axis": axis, "before": float(was),
                             "after": float(value), "error": float(error),
                             "overshoot": bool(np.sign(value) == -np.sign(was))})
    return left


def with_empirical(result, state, heldout, observables, late_fraction=1.0 / 3.0):
    """The EMPIRICAL term (`bfpsf.diagnosis.empirical_fit`) when a size residual is left:
    fitted on the loop's fit part, judged on its held-out exposures and, with at least 4
    exposures, fitted on the early exposures and judged on a contiguous late block. Its
    diagonal pattern is fitted where the stars' e2 change is unexplained too (the model's e2,
    `SpotForwardModel.cross`, subtracted)."""
    left = [entry for entry in result.unexplained if entry["observable"] == "sizes"]
    diagonal = any(entry["observable"] == "cross moment e2" for entry in result.unexplained)
    if not (left or diagonal) or observables.sizes is None:
        return result
    def shows(key):
        return any((entry.get(key) or {}).get("kind", "none") != "none" for entry in left)

    position, row, exposure = (shows(key) for key in ("position_dependence", "row_dependence",
                                                      "exposure_dependence"))
    # or where every star's BF slope depends on the column or row (`position_split`), which
    # the binned residual may not resolve (a new user's smear growing with the row, 55 stars
    # per exposure: unreported, and a term without it left -16 % of the raw slope held out)
    dependent = dependent_directions(observables.meta.get("position_split"))
    position, row = position or "column" in dependent, row or "row" in dependent
    # or where the signature test found the residual changing over the night, which the
    # held-out report says only with 3 exposures or more (a night-growing smear on 4
    # exposures: every candidate contradicted by exposure_order, p = 1e-74, and a term
    # without the exposure left 23 % of the raw slope held out and 42 % on the late block)
    exposure = exposure or any(
        (entry or {}).get("contradicted_by") == "exposure_order"
        for entry in (*result.rejected.values(), *(result.nuisance or {}).values()))
    step = _kept_step(result, state, result.confirmed)
    model = observables.spot_model

    def inputs(part):
        """The term's inputs of one part (sizes, fluxes, model sizes, residual, and the e2
        residual where the diagonal is fitted), computed once for every pattern kind."""
        sizes = part.sizes
        cross = ({"cross_residual": sizes.cross - model.cross(sizes.peak_e)}
                 if diagonal else {})
        return (sizes, model.fluxes(sizes.peak_e), model.sizes(sizes.peak_e),
                _size_residual(state, part, step)), cross

    fitted = inputs(state["observables"])
    held = None if heldout is None else inputs(heldout)
    split = early_late(observables, late_fraction)
    early, late = (None, None) if split is None else (inputs(part) for part in split)
    # valid over the night: the held-out exposures interleave with the fitted ones
    orders = observables.sizes.exposure
    night = None if orders is None else (float(np.min(orders)), float(np.max(orders)))

    def learn(kind):
        """The term of one pattern kind, with its validation (a record)."""
        response = adaptive_response(model, float(np.median(observables.sizes.peak_e)),
                                     kind=kind)
        # the term's field: the columns and rows the stars span, not the size bins' mean
        # positions
        options = {"position": position, "row": row, "exposure": exposure,
                   "response": response, "extent": observables.meta.get("star_extent"),
                   "kind": kind}
        term = fit_empirical(*fitted[0], **options, night=night, **fitted[1])
        validation = {"fitted_on": "the loop's fit part", "adaptive_response": response,
                      "position_term": position, "row_term": row, "exposure_term": exposure,
                      "diagonal_term": diagonal}
        if held is not None:
            validation["heldout"] = evaluate_empirical(term, *held[0], response, **held[1])
        if split is not None:
            early_term = fit_empirical(*early[0], **options, **early[1])
            # with the term fitted on the early exposures, so that its pixel-level use (PSF
            # photometry of the late block) can be checked as well
            validation["late_block"] = dict(
                evaluate_empirical(early_term, *late[0], response, **late[1]),
                exposures=sorted(np.unique(split[1].sizes.exposure).tolist()),
                term=early_term.to_dict())
        validation["validated"] = term_validated(validation)
        validation["left"] = term_leaves(validation)
        return dataclasses.replace(term, validation=validation).to_dict()

    # every pattern kind: the sizes cannot tell them apart, the stars' pixels can (`bfpsf
    # diagnose` keeps the kind whose held-out star residual is the lower)
    return dataclasses.replace(result, empirical=learn(PATTERN_KIND), empirical_alternatives={
        kind: learn(kind) for kind in PATTERN_KINDS if kind != PATTERN_KIND})


def with_heldout(result, state, heldout, fraction, confirmed=None):
    """The result with the held-out residuals (after: the confirmed effects alone), the
    confirmation of each selected effect and the unexplained residuals (judged on the
    held-out data); ``confirmed``, where given, is the confirmation judged on another view
    of the held-out data (`bfpsf.diagnosis.quiet_axis`: on one axis)."""
    chi2 = []
    evaluations = []
    for step in state["steps"]:
        problem, model, _ = _evaluate(state, heldout, step)
        evaluations.append((problem, model))
        chi2.append(float((((problem.residual - model) / problem.sigma) ** 2).sum()))
    # the first step fits the global nuisances together (the size scale and, where the flats
    # give its prior, the X / Y split): one confirmation, under the scale's name
    names = [HELDOUT_LABEL] * (len(state["steps"]) - 1 - len(result.selected))
    names += result.selected
    if confirmed is None:
        confirmed = {name: chi2[k + 1] < chi2[k] for k, name in enumerate(names)}
    before = summarise(evaluations[0][0], heldout, evaluations[0][1])
    physical = None
    if result.residual_physical:
        names = result.residual_physical["effects"]
        step = {"names": names, "global": np.zeros(len(state["problem"].global_columns)),
                "effects": {name: np.asarray(state["by_name"][state["family"](name)]
                                             .physical_value, float) for name in names}}
        problem, model, _ = _evaluate(state, heldout, step)
        physical = summarise(problem, heldout, model)
        physical["effects"] = names
    # "after": what the confirmed effects leave, as the refined calibration applies them (a
    # new user's held-out "after" had included a size scale that was not confirmed, and so
    # not applied; a size scale whose signature is contradicted is in no step: `diagnose`
    # ran the loop again without it); the unexplained residuals are judged on the same
    step = _kept_step(result, state, confirmed)
    problem, model, prediction = _evaluate(state, heldout, step)
    after = summarise(problem, heldout, model)
    sizes = heldout.sizes
    holdout = {"fraction": float(fraction),
               "sizes_split_by": heldout.meta.get("holdout_sizes_split_by"),
               "heldout_exposures": (sorted(np.unique(sizes.exposure).tolist())
                                     if sizes is not None and sizes.exposure is not None
                                     else None),
               "n_fit": int(result.residual_after["n"]), "n_heldout": int(after["n"]),
               "heldout_size_entries": 0 if sizes is None else len(sizes)}
    unexplained = describe_unexplained(problem, heldout, model, prediction=prediction)
    return dataclasses.replace(result, residual_before_heldout=before,
                               residual_after_heldout=after, confirmed=confirmed,
                               residual_physical_heldout=physical,
                               holdout=holdout, unexplained=unexplained)
