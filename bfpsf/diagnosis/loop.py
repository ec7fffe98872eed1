"""The closed loop: residual -> missing effect -> added -> before / after.

`diagnose` fits the base model to the observables (`bfpsf.diagnosis.observables`), looks at what
is left, and tests every candidate of the catalogue: each candidate's template is fitted
jointly with the base model's nuisance parameters and the effects already selected, by weighted
least squares with the observables' errors. Its statistic is the chi-square improvement
Delta chi2 = chi2(before) - chi2(with it), and it is scored by the Bayesian information
criterion

    Delta BIC = -Delta chi2 + k ln N

(k its parameters, N the data points; negative is better). The best candidate is added if its
Delta BIC is below ``threshold`` (default -10: "very strong" evidence on the Kass & Raftery
1995 scale, about a 3.6 sigma improvement for k = 1 and N ~ 100), the model is refitted, and
the loop repeats until no candidate passes.

Effects whose parameter physics predicts (the exact boundary density, t = 1; the area beyond
the measured lags, t = 1) are also tested fixed at that value, as ``name@physical`` with k = 0:
a parameter-free prediction. ``prefer_physical=True`` adds a significant parameter-free
prediction before any fitted effect. A fit outside an effect's physical bounds (a negative
diffusion, say) cannot be selected. Candidates of other families within 10 in Delta BIC of
the winner are reported as indistinguishable (``ambiguous``): on sizes alone, isotropic
terms (non-linearity, diffusion, more BF) are nearly degenerate, and a linearity observable
is what separates them.

Base model and its nuisance parameters:

* sizes: measured sigma minus the G15 prediction (model spot scaled to each peak and
  redistributed, eq. scrambling_model); a free intercept per data-set group and axis.
* linearity: flat mean = k t + b (both free).
* correlations: R(dx, dy) = a(dx, dy) mu (eq. covar), a free per lag (no intercept).
* ptc (images mode): flat-pair variance minus the calibrated PTC model with the sum-rule
  a(0, 0) (`bfpsf.diagnosis.tables.PTCTable`); a free constant (read noise), a free
  term linear in the mean (gain), and a term in mean^2 (the sum-rule a(0, 0)) free within
  its error (a Gaussian prior, one pseudo data point).

Residual summaries: the brighter-fatter slope residual in X and Y (slope of the size residual
against peak, percent of the raw measured slope), the photometry bias the size residual implies
(a PSF fit with a template of width sigma on a star of width sigma (1 + eps) is biased by
-eps in flux, 1.0857 eps mag, for Gaussian profiles), and chi2 / N per observable.
"""

import dataclasses
import logging

import numpy as np
from scipy.stats import chi2 as _chi2

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import weighted_least_squares
from .catalogue import CATALOGUE, get_effect
from .heldout import split_observables, with_empirical, with_heldout
from .nuisances import (GLOBAL_NUISANCES, PRIOR_NSIGMA, SCALE, SPLIT, beyond_the_flats,
                        without_priors)
from .problem import (build_problem, effect_columns, effect_design, effect_values,
                      global_priors, slope_residuals, summarise)
from .quiet_axis import scale_beside_the_effect
from .refine import unapplied
from .result import DiagnosisResult
from .signature import (SIGNATURE_ALPHA, contradiction, cross_test, flux_competitors,
                        flux_shape_test, TEMPLATE_TOLERANCE, parity_test, signature_parts,
                        signature_test)
from .unexplained import (STAR_CHI2_FACTOR, UNEXPLAINED_NSIGMA, describe_unexplained, verdict,
                          with_scale_parts)

__all__ = ["DiagnosisResult", "diagnose", "DEFAULT_THRESHOLD", "slope_residuals", "split_observables",
           "describe_unexplained", "UNEXPLAINED_NSIGMA", "verdict", "STAR_CHI2_FACTOR"]

log = logging.getLogger(__name__)

#: Families `bfpsf.diagnosis.refine` folds into a calibration (second order: when positive).
_FOLDABLE = ("calibration_scale", "xy_anisotropy", "gain_nonlinearity")

#: The candidate a contradicted one may be named with (`_run_loop`'s ``with_scale``).
_SCALE = SCALE.name

#: Delta BIC below which a candidate is added (Kass & Raftery 1995: "very strong").
DEFAULT_THRESHOLD = -10.0


def diagnose(observables, *, catalogue=CATALOGUE, threshold=DEFAULT_THRESHOLD, max_rounds=4,
             prefer_physical=False, holdout_fraction=None, signature_alpha=SIGNATURE_ALPHA):
    """Find, by information criterion, the effects the base model is missing.

    Parameters
    ----------
    observables : Observables
    catalogue : sequence of Effect, optional
        Candidates (default `bfpsf.diagnosis.catalogue.CATALOGUE`).
    threshold : float, optional
        Add the best candidate when its Delta BIC is below this (default -10).
    max_rounds : int, optional
        At most this many effects are added (default 4).
    prefer_physical : bool, optional
        In each round, add the best parameter-free prediction (an effect fixed at its physical
        value, ``name@physical``) when it passes the threshold, before considering fitted
        effects (Occam: a prediction beats a fit that explains the same residual). Default
        False: plain BIC ranking.
    holdout_fraction : float, optional
        Fit on part of the data and report the residual on the rest (`split_observables`):
        ``residual_before_heldout``, ``residual_after_heldout`` and, per selected effect,
        whether it improves the held-out residual (``confirmed``). Default None: no split.
    signature_alpha : float or None, optional
        A candidate is named only when its signature matches in every dimension at this
        p-value (`bfpsf.diagnosis.signature`, default 1e-3); those that pass the
        information criterion but not the signature are reported in ``rejected``. None: the
        information criterion alone (the loop before issue 22).

    Returns
    -------
    DiagnosisResult
    """
    options = (catalogue, threshold, max_rounds, prefer_physical, signature_alpha)
    fit_part, heldout = (split_observables(observables, holdout_fraction) if holdout_fraction
                         else (observables, None))
    result, state = _run_loop(fit_part, *options)
    contradicted, given = {}, (observables, fit_part, heldout)
    while True:
        against = {name: entry for name, entry in result.nuisance.items()
                   if entry.get("contradicted_by") and name not in contradicted}
        if not against:
            break
        # a global nuisance's signature is contradicted: the effects were chosen and fitted
        # with it free, so the loop runs again without it (without the split too when the
        # scale goes; its test is kept in the report); a candidate that needed it (an effect
        # fitted beside a scale far from the flats') is then judged on its own
        contradicted.update(against)
        dropped = ((SCALE.error_key, SPLIT.error_key) if SCALE.name in contradicted
                   else (SPLIT.error_key,))
        observables, fit_part, heldout = (without_priors(part, dropped)
                                          for part in (observables, fit_part, heldout))
        result, state = _run_loop(fit_part, *options)
    if contradicted:
        result = dataclasses.replace(result, nuisance=dict(result.nuisance, **contradicted))
    if heldout is not None:
        result = with_heldout(result, state, heldout, holdout_fraction)
        # a scale contradicted by an effect's dependence on one axis: fitted on the other
        beside = contradicted and scale_beside_the_effect(
            result, state, contradicted, given, lambda part: _run_loop(part, *options),
            holdout_fraction)
        if beside:
            result, state, observables, heldout = beside
    else:
        result = _with_unexplained(result, state, observables)
    return _with_verdict(with_empirical(result, state, heldout, observables), observables)


def _run_loop(observables, catalogue, threshold, max_rounds, prefer_physical,
              signature_alpha=SIGNATURE_ALPHA):
    """The loop itself: the result and what the held-out evaluation needs."""
    if not threshold < 0:
        msg = f"threshold must be a negative Delta BIC, got {threshold!r}"
        raise BFPSFValueError(msg, threshold)
    problem = build_problem(observables)
    n_points = problem.residual.size
    if n_points <= problem.nuisance.shape[1] + 1:
        msg = (f"{n_points} data points cannot constrain {problem.nuisance.shape[1]} base "
               "parameters and a candidate")
        raise BFPSFInputError(msg, n_points)
    if not np.all(np.isfinite(problem.residual)):
        msg = (f"the base model gives {np.count_nonzero(~np.isfinite(problem.residual))} "
               "non-finite predictions (size measurement of the model spot failed)")
        raise BFPSFInputError(msg)
    designs = {}
    for effect in catalogue:
        try:
            templates = effect.templates(observables)
        except BFPSFValueError as error:
            # its template could not be measured on these data (e.g. the model spot with the
            # effect's shifts outgrew its stamp): not testable, the others still are
            log.warning("%s is not testable on these data: %s", effect.name, error)
            templates = None
        design = effect_design(problem, templates) if templates else None
        if design is not None and not np.all(np.isfinite(design)):
            design = None     # the template could not be computed: not testable
        designs[effect.name] = design

    # Effects with a physical value are also tested FIXED at it: a parameter-free prediction
    # (k = 0, so Delta BIC = -Delta chi2) named "<name>@physical".
    fixed = {}
    for effect in catalogue:
        if effect.physical_value is not None and designs[effect.name] is not None:
            fixed[f"{effect.name}@physical"] = (designs[effect.name]
                                               @ np.asarray(effect.physical_value, float))

    def fit(names):
        free = [name for name in names if name not in fixed]
        offset = sum((fixed[name] for name in names if name in fixed),
                     np.zeros_like(problem.residual))
        blocks = [problem.nuisance] + [designs[name] for name in free]
        params, covariance, chi2, model = weighted_least_squares(problem.residual - offset, problem.sigma,
                                               np.column_stack(blocks))
        return params, covariance, chi2, model + offset

    def family(name):
        return name.split("@")[0]

    options = []
    for effect in catalogue:
        options.append((effect.name, effect))
        if f"{effect.name}@physical" in fixed:
            options.append((f"{effect.name}@physical", effect))

    selected = []
    _, _, chi2_current, model_before = fit([])
    if problem.global_columns:
        # "before": the prediction as it stands, global nuisances (the size scale) at zero
        local = np.delete(problem.nuisance, list(problem.global_columns), axis=1)
        model_before = weighted_least_squares(problem.residual, problem.sigma, local)[3]
    candidates = []
    ambiguous = {}
    rejected = {}
    parts = signature_parts(problem, observables)
    tolerance = TEMPLATE_TOLERANCE
    competitors = flux_competitors(problem, observables)
    parity = parity_test(observables.sizes, alpha=signature_alpha or SIGNATURE_ALPHA)
    cross = cross_test(observables.sizes, alpha=signature_alpha or SIGNATURE_ALPHA)

    def signature(design, nuisance=None, flux=None, extra=()):
        """The signature test of a template given the effects already selected and those in
        ``extra`` (with the flux dimension for an effect whose identity is its flux shape:
        ``flux`` its competitor, `Effect.flux_signature`)."""
        free = [other for other in [*selected, *extra] if other not in fixed]
        offset = sum((fixed[other] for other in selected if other in fixed),
                     np.zeros_like(problem.residual))
        base = np.column_stack([problem.nuisance if nuisance is None else nuisance]
                               + [designs[other] for other in free])
        test = signature_test(problem.residual - offset, problem.sigma, base, design, parts,
                              alpha=signature_alpha, tolerance=tolerance)
        if flux and np.any(competitors[flux]):
            test["flux_shape"] = flux_shape_test(problem.residual - offset, problem.sigma, base,
                                                 design, competitors[flux], kind=flux,
                                                 alpha=signature_alpha or SIGNATURE_ALPHA)
        if parity is not None and "sizes" in problem.slices and np.any(
                design[problem.slices["sizes"]]):
            test["parity"] = parity
        if cross is not None and "sizes" in problem.slices and np.any(
                design[problem.slices["sizes"]]):
            test["cross"] = cross
        return test

    pairs = {}

    def with_scale(name, effect):
        """A candidate contradicted by the observable dimension, tested again with the stars'
        BF amplitude free (the ``calibration_scale`` candidate beside it): the sizes cannot
        tell a BF-like template from a scale of the flats' BF beyond its prior, so a size
        part that disagrees with the flats' may be that scale. (Delta BIC of both, chi2, the
        candidate's signature) when the pair passes the threshold, the scale its physical
        bounds and both their signatures; else None. GalSim's E2V stars show 23 % less BF
        than its flats: a hidden gain non-linearity of -1.5 % at 1e5 e- had its size part
        at +0.036 +- 0.010 against the flat means' -0.0137 +- 0.0012, and was rejected."""
        scale = next((other for other in catalogue if other.name == _SCALE), None)
        if (scale is None or designs[_SCALE] is None or _SCALE in selected
                or effect.name == _SCALE or "sizes" not in problem.slices):
            return None
        params, covariance, chi2, _ = fit(selected + [name, _SCALE])
        delta_bic = -(chi2_current - chi2) + (effect.k + 1) * np.log(n_points)
        error = float(np.sqrt(abs(covariance[-1, -1])))
        if not (delta_bic < threshold and scale.allows(*_bounded(
                scale, [float(params[-1])], [error], params, covariance,
                problem.global_columns, False))):
            return None
        test = signature(designs[effect.name], flux=effect.flux_signature, extra=[_SCALE])
        against = signature(designs[_SCALE], extra=[name], flux=scale.flux_signature)
        return None if contradiction(test) or contradiction(against) else (delta_bic, chi2, test)

    for round_index in range(int(max_rounds)):
        scores = []
        taken = {family(name) for name in selected}
        for name, effect in options:
            # a candidate whose signature the data contradicted stays out: selected in a later
            # round (its test then conditional on what was selected since) it was reported
            # both rejected and named
            if family(name) in taken or name in rejected:
                continue
            is_fixed = name in fixed
            k = 0 if is_fixed else effect.k
            entry = {"round": round_index + 1, "name": name, "k": k,
                     "testable": designs[effect.name] is not None}
            if designs[effect.name] is None:
                entry.update(statistic=None, delta_bic=None, parameters=None, errors=None,
                             allowed=None)
            else:
                params, covariance, chi2, _ = fit(selected + [name])
                statistic = chi2_current - chi2
                delta_bic = -statistic + k * np.log(n_points)
                # a value fixed by physics is judged by the free fit's bounds: a new user's
                # halo had boundary_density@physical named where its template's data asked
                # for t = 12.1
                free, free_covariance = fit(selected + [effect.name])[:2] if is_fixed else (
                    params, covariance)
                own = slice(free.size - effect.k, free.size)
                values = free[own].tolist()
                errors = np.sqrt(np.abs(np.diag(free_covariance)[own])).tolist()
                allowed = effect.allows(*_bounded(effect, values, errors, free, free_covariance,
                                                  problem.global_columns, is_fixed))
                if is_fixed:
                    values, errors = list(effect.physical_value), [0.0] * effect.k
                entry.update(statistic=float(statistic), delta_bic=float(delta_bic),
                             parameters=values, errors=errors, allowed=bool(allowed))
                if not allowed and delta_bic < threshold:
                    # it would be named but for physics: reported with its values
                    rejected.setdefault(name, {
                        "round": round_index + 1, "delta_bic": float(delta_bic),
                        "contradicted_by": "bounds", "p_value": None,
                        "values": [float(value) for value in free[own]],
                        "bounds": [list(bound) for bound in effect.bounds]})
                if allowed and delta_bic < threshold and signature_alpha:
                    test = signature(designs[effect.name], flux=effect.flux_signature)
                    against = contradiction(test)
                    entry.update(signature=test, contradicted_by=against)
                    paired = (with_scale(name, effect) if against == "observable"
                              and not is_fixed else None)
                    if paired is not None:
                        # named together with the stars' own BF amplitude
                        delta_bic, chi2, test = paired
                        pairs[name] = _SCALE
                        entry.update(signature=test, contradicted_by=None, paired_with=_SCALE,
                                     paired_delta_bic=float(delta_bic))
                    elif against is not None:
                        rejected.setdefault(name, {
                            "round": round_index + 1, "delta_bic": float(delta_bic),
                            "contradicted_by": against,
                            "p_value": test[against]["p_value"], "signature": test})
                        allowed = False
                if allowed:
                    scores.append((delta_bic, name, chi2))
            candidates.append(entry)
        if not scores:
            break
        physical_scores = [score for score in scores if score[1] in fixed]
        if prefer_physical and physical_scores and min(physical_scores)[0] < threshold:
            scores = physical_scores
        best_bic, best_name, best_chi2 = min(scores)
        if not best_bic < threshold:
            break
        if best_name in pairs:
            selected.append(pairs[best_name])
        # candidates the data cannot tell apart from the winner (Delta BIC within 10 of it)
        ambiguous[best_name] = sorted(name for bic, name, _ in scores
                                      if name != best_name and family(name) != family(best_name)
                                      and bic - best_bic < -DEFAULT_THRESHOLD)
        selected.append(best_name)
        chi2_current = best_chi2

    physical_names = sorted(fixed)
    residual_physical = None
    if physical_names:
        # parameter-free: the physical values, global nuisances (the size scale) at zero
        offset = sum(fixed[name] for name in physical_names)
        local = np.delete(problem.nuisance, list(problem.global_columns), axis=1)
        model_physical = weighted_least_squares(problem.residual - offset, problem.sigma, local)[3] + offset
        residual_physical = summarise(problem, observables, model_physical)
        residual_physical["effects"] = physical_names
    params, covariance, _, model_after = fit(selected)
    parameters = {}
    by_name = {effect.name: effect for effect in catalogue}
    for name, own in effect_columns(problem, selected, fixed, by_name, family).items():
        effect = by_name[family(name)]
        physical = list(effect.physical_value) if effect.physical_value else None
        value, error = ((physical, [0.0] * effect.k) if own is None else (
            params[own].tolist(), np.sqrt(np.abs(np.diag(covariance)[own])).tolist()))
        parameters[name] = {"names": list(effect.parameters), "value": value, "error": error,
                            "physical": physical}

    nuisance = {}
    priors = global_priors(observables.meta)
    for (name, prior), column in zip(priors.items(), problem.global_columns):
        entry = nuisance[name] = {"value": float(params[column]),
                                  "error": float(np.sqrt(abs(covariance[column, column]))),
                                  "prior": float(prior),
                                  "draws": list(observables.meta.get("draws", {}).get(name, []))}
        if not signature_alpha:
            continue
        # the flats' scale and split: nuisances within the flats' errors, with a signature
        # (the same everywhere, every exposure) and a pull on the prior within 3 sigma
        test = signature(problem.nuisance[:, [column]],
                         nuisance=np.delete(problem.nuisance, column, axis=1),
                         flux=get_effect(_SCALE).flux_signature if name == _SCALE else None)
        if name == SPLIT.name:
            # its template is X against Y by construction: the axis parts are not one
            # amplitude of it
            test.pop("axis", None)
        pull = entry["value"] / entry["prior"]
        test["flats_prior"] = {"parts": ["flats", "stars"], "amplitudes": [[0.0],
                               [entry["value"]]], "errors": [[entry["prior"]],
                               [entry["error"]]], "chi2": pull ** 2, "dof": 1,
                               "p_value": float(_chi2.sf(pull ** 2, 1)),
                               "matches": bool(abs(pull) <= PRIOR_NSIGMA)}
        # an odd residual is another effect, not an error of the flats' BF amplitude (verdict)
        entry.update(signature=test, contradicted_by=contradiction(
            {key: value for key, value in test.items() if key != "parity"}))
        # and the scale within its physical range (the prior passed its test above)
        if entry["contradicted_by"] is None and beyond_the_flats(
                name, entry["value"], entry["error"], entry["prior"]):
            entry.update(contradicted_by="bounds",
                         bounds=list(get_effect(_SCALE).bounds[0]))
    curves = {}
    sizes = observables.sizes
    if sizes is not None:
        n = len(sizes)
        block = problem.slices["sizes"]
        predicted_x, predicted_y = observables.spot_model.sizes(sizes.peak_e)
        base = np.concatenate([predicted_x, predicted_y]) + model_before[block]
        final = np.concatenate([predicted_x, predicted_y]) + model_after[block]
        curves = {"peak_e": sizes.peak_e, "group": sizes.group,
                  "sigma_x": sizes.sigma_x, "sigma_y": sizes.sigma_y,
                  "sigma_x_err": sizes.sigma_x_err, "sigma_y_err": sizes.sigma_y_err,
                  "base_x": base[:n], "base_y": base[n:], "final_x": final[:n],
                  "final_y": final[n:]}
    ptc_curves = {}
    if observables.ptc is not None:
        block = problem.slices["ptc"]
        ptc_curves = {"mean_e": observables.ptc.mean_e, "var_e": observables.ptc.var_e,
                      "error": observables.ptc.var_err_e,
                      "residual_raw": observables.ptc.residual_e,
                      "residual_before": problem.residual[block] - model_before[block],
                      "residual_after": problem.residual[block] - model_after[block]}
    # what a calibration can hold (`bfpsf.diagnosis.refine`), refitted jointly without the
    # rest: a fitted second order goes into the build-up only when positive (the build-up's
    # own second order strengthens BF); otherwise the others are refitted without it
    foldable = [name for name in selected if family(name) in _FOLDABLE
                or (family(name) == "second_order" and parameters[name]["value"][0] > 0)]
    values = fit(foldable)[0]
    folded_globals = {name: float(values[column])
                      for name, column in zip(priors, problem.global_columns)}
    folded = {"names": foldable,
              "effects": {name: np.asarray(value).tolist() for name, value in
                          effect_values(values, problem, foldable, fixed, by_name,
                                         family).items()},
              **{entry.folded_key: folded_globals.get(entry.name)
                 for entry in GLOBAL_NUISANCES}}
    result = DiagnosisResult(residual_before=summarise(problem, observables, model_before),
                             candidates=candidates, selected=selected,
                             residual_after=summarise(problem, observables, model_after),
                             parameters=parameters, threshold=float(threshold), curves=curves,
                             ambiguous=ambiguous, residual_physical=residual_physical,
                             ptc_curves=ptc_curves, nuisance=nuisance, folded=folded,
                             rejected=rejected)
    # for the held-out evaluation: the effect and global-nuisance values of each step, the
    # first one the bare prediction
    steps = [{"names": [], "global": np.zeros(len(problem.global_columns)), "effects": {},
              "model": model_before}] if problem.global_columns else []
    for k in range(len(selected) + 1):
        names = selected[:k]
        values, covariance, _, model = fit(names)
        steps.append({"names": names, "global": values[list(problem.global_columns)],
                      "effects": effect_values(values, problem, names, fixed, by_name, family),
                      "model": model,
                      "covariance": _step_covariance(covariance, problem, names, fixed,
                                                     by_name, family)})
    state = {"problem": problem, "steps": steps, "fixed": fixed, "family": family,
             "by_name": by_name, "observables": observables}
    return result, state


def _bounded(effect, values, errors, params, covariance, global_columns, is_fixed):
    """What a candidate's bounds apply to, with its errors: its fitted values, except for the
    size scale beside the nuisance of the same template (the flats' scale, with its prior),
    where the bounds are those of the stars' total scale (the candidate alone is uncertain
    by the prior: stars without BF fitted it -0.98 +- 0.21, the total -0.98 +- 0.008)."""
    if effect.name != _SCALE or is_fixed or not global_columns:
        return values, errors
    own, nuisance = params.size - 1, global_columns[0]
    variance = (covariance[own, own] + covariance[nuisance, nuisance]
                + 2 * covariance[own, nuisance])
    return [float(params[own] + params[nuisance])], [float(np.sqrt(abs(variance)))]


def _step_covariance(covariance, problem, names, fixed, by_name, family):
    """Covariance of a step's parameters in the order the held-out prediction uses them
    (the global nuisances, then each effect's values as `effect_values` gives them; an effect
    fixed at its physical value has none): what the prediction on held-out data inherits
    from the fit (`bfpsf.diagnosis.heldout`)."""
    index = list(problem.global_columns)
    for name, own in effect_columns(problem, names, fixed, by_name, family).items():
        index += ([None] * by_name[family(name)].k if own is None
                  else list(range(own.start, own.stop)))
    out = np.zeros((len(index), len(index)))
    kept = [i for i, value in enumerate(index) if value is not None]
    columns = [index[i] for i in kept]
    out[np.ix_(kept, kept)] = covariance[np.ix_(columns, columns)]
    return out


def _with_unexplained(result, state, observables):
    model = state["steps"][-1]["model"]
    return dataclasses.replace(result, unexplained=describe_unexplained(
        state["problem"], observables, model))


def _with_verdict(result, observables):
    meta = observables.meta
    unexplained = with_scale_parts(result.unexplained, result.nuisance)
    return dataclasses.replace(result, unexplained=unexplained, verdict=verdict(
        unexplained, result.nuisance, meta.get("star_residual"),
        meta.get("star_chi2_null", 1.0), meta.get("position_split"), result.empirical,
        unapplied(result.selected)))
