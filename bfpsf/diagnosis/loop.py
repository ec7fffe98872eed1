"""The closed loop: residual -> missing effect -> added -> before / after.

`diagnose` fits the base model to the observables (`bfpsf.diagnosis.observables`, `bfpsf.diagnosis.catalogue`), looks at what
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
  a(0, 0) (`bfpsf.diagnosis.observables.PTCTable`); a free constant (read noise), a free
  term linear in the mean (gain), and a term in mean^2 (the sum-rule a(0, 0)) free within
  its error (a Gaussian prior, one pseudo data point).

Residual summaries: the brighter-fatter slope residual in X and Y (slope of the size residual
against peak, percent of the raw measured slope), the photometry bias the size residual implies
(a PSF fit with a template of width sigma on a star of width sigma (1 + eps) is biased by
-eps in flux, 1.0857 eps mag, for Gaussian profiles), and chi2 / N per observable.
"""

from dataclasses import dataclass, field

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from .catalogue import CATALOGUE

__all__ = ["DiagnosisResult", "diagnose", "DEFAULT_THRESHOLD", "slope_residuals"]

#: Delta BIC below which a candidate is added (Kass & Raftery 1995: "very strong").
DEFAULT_THRESHOLD = -10.0

_MAG_PER_FRACTION = 2.5 / np.log(10.0)


@dataclass(frozen=True)
class _Problem:
    """The stacked residual vector of every observable and the base nuisance design."""

    keys: tuple            # observable key of each block
    slices: dict           # key -> slice into the vector
    residual: np.ndarray   # data - fixed base prediction
    sigma: np.ndarray
    nuisance: np.ndarray   # (N, m)


def _size_block(observables):
    sizes, model = observables.sizes, observables.spot_model
    predicted_x, predicted_y = model.sizes(sizes.peak_e)
    residual = np.concatenate([sizes.sigma_x - predicted_x, sizes.sigma_y - predicted_y])
    sigma = np.concatenate([sizes.sigma_x_err, sizes.sigma_y_err])
    n, groups = len(sizes), sizes.n_groups
    nuisance = np.zeros((2 * n, 2 * groups))
    for axis in range(2):
        nuisance[axis * n + np.arange(n), axis * groups + sizes.group] = 1.0
    return residual, sigma, nuisance


def _linearity_block(observables):
    table = observables.linearity
    nuisance = np.column_stack([table.exptime, np.ones_like(table.exptime)])
    return table.mean_e.copy(), table.mean_err_e.copy(), nuisance


def _correlation_block(observables):
    table = observables.correlations
    n, n_lags = table.r.shape
    nuisance = np.zeros((n * n_lags, n_lags))
    for lag in range(n_lags):
        nuisance[lag * n:(lag + 1) * n, lag] = table.mean_e
    return table.r.T.ravel(), table.r_err.T.ravel(), nuisance


def _ptc_block(observables):
    """PTC residuals; nuisance: read noise, gain and the sum-rule a(0, 0) within its error.

    The error of the sum-rule a(0, 0) is common to every pair (a term delta_a m^2): it is a
    nuisance column with a Gaussian prior of that width, entered as one extra pseudo data
    point (zero, with that error) so the weighted least squares stays diagonal.
    """
    table = observables.ptc
    scaled = table.mean_e / 1e5
    if not table.sum_rule_err > 0:
        # a(0, 0) taken as exact: no freedom in the m^2 term
        nuisance = np.column_stack([np.ones_like(scaled), scaled])
        return table.residual_e, table.var_err_e.copy(), nuisance
    nuisance = np.column_stack([np.ones_like(scaled), scaled, scaled ** 2])
    prior_design = np.array([[0.0, 0.0, 1.0]])
    prior_sigma = np.array([table.sum_rule_err * 1e10])
    return table.residual_e, table.var_err_e.copy(), nuisance, (prior_design, prior_sigma)


_BLOCKS = {"sizes": _size_block, "linearity": _linearity_block,
           "correlations": _correlation_block, "ptc": _ptc_block}


def _build_problem(observables):
    keys, slices, residuals, sigmas, nuisances = [], {}, [], [], []
    start = 0
    for key, block in _BLOCKS.items():
        if getattr(observables, key) is None:
            continue
        residual, sigma, nuisance, *prior = block(observables)
        keys.append(key)
        slices[key] = slice(start, start + residual.size)
        start += residual.size
        if prior:
            # prior rows of the block's nuisance: pseudo data (zero) outside the key's slice,
            # so no effect template reaches them
            prior_design, prior_sigma = prior[0]
            residual = np.concatenate([residual, np.zeros(prior_sigma.size)])
            sigma = np.concatenate([sigma, prior_sigma])
            nuisance = np.vstack([nuisance, prior_design])
            start += prior_sigma.size
        residuals.append(residual)
        sigmas.append(sigma)
        nuisances.append(nuisance)
    total = sum(n.shape[1] for n in nuisances)
    design = np.zeros((start, total))
    column = 0
    for key, nuisance in zip(keys, nuisances):
        rows = slice(slices[key].start, slices[key].start + nuisance.shape[0])
        design[rows, column:column + nuisance.shape[1]] = nuisance
        column += nuisance.shape[1]
    return _Problem(tuple(keys), slices, np.concatenate(residuals), np.concatenate(sigmas),
                    design)


def _effect_design(problem, templates):
    """Full-length (N, k) design of one effect from its per-observable templates."""
    k = next(iter(templates.values())).shape[1]
    design = np.zeros((problem.residual.size, k))
    for key, template in templates.items():
        if key in problem.slices:
            design[problem.slices[key]] = template
    return design


def _wls(residual, sigma, design):
    """Weighted least squares: parameters, covariance, chi2, fitted model."""
    weights = 1.0 / sigma
    a = design * weights[:, None]
    b = residual * weights
    # scale columns for conditioning
    norms = np.sqrt((a ** 2).sum(axis=0))
    norms[norms == 0] = 1.0
    solution, *_ = np.linalg.lstsq(a / norms, b, rcond=None)
    params = solution / norms
    model = design @ params
    chi2 = float((((residual - model) * weights) ** 2).sum())
    try:
        covariance = np.linalg.pinv((a / norms).T @ (a / norms)) / np.outer(norms, norms)
    except np.linalg.LinAlgError:
        covariance = np.full((params.size, params.size), np.nan)
    return params, covariance, chi2, model


def slope_residuals(sizes, residual_x, residual_y):
    """BF slope residual in X and Y, percent of the raw measured slope, and the raw slopes.

    Parameters
    ----------
    sizes : SizeTable
    residual_x, residual_y : ndarray
        Measured minus model sigma, pixels.

    Returns
    -------
    dict
        ``raw_slope_x``, ``raw_slope_y`` (pixels per 100 ke- of peak), ``slope_x_percent``,
        ``slope_y_percent`` and their errors (percent).
    """
    from ..measure.slopes import fit_bf_slope

    out = {}
    for axis, measured, error, residual in (("x", sizes.sigma_x, sizes.sigma_x_err, residual_x),
                                            ("y", sizes.sigma_y, sizes.sigma_y_err, residual_y)):
        # the given errors, not rescaled by the scatter (the chi2 is reported apart)
        raw = fit_bf_slope(sizes.peak_e, measured, size_err=error, group=sizes.group,
                           scale_errors=False).slope
        fit = fit_bf_slope(sizes.peak_e, residual, size_err=error, group=sizes.group,
                           scale_errors=False)
        out[f"raw_slope_{axis}"] = raw
        out[f"slope_{axis}_percent"] = 100.0 * fit.slope / raw
        out[f"slope_{axis}_percent_err"] = 100.0 * fit.slope_err / abs(raw)
    return out


def _summary(problem, observables, model):
    """Residual summary of data - (fixed base prediction + fitted model)."""
    residual = problem.residual - model
    out = {"chi2": float(((residual / problem.sigma) ** 2).sum()), "n": int(residual.size)}
    for key in problem.keys:
        block = problem.slices[key]
        part = residual[block] / problem.sigma[block]
        out[f"{key}_chi2_per_point"] = float(np.mean(part ** 2))
    sizes = observables.sizes
    if sizes is not None:
        block = residual[problem.slices["sizes"]]
        n = len(sizes)
        residual_x, residual_y = block[:n], block[n:]
        out.update(slope_residuals(sizes, residual_x, residual_y))
        # photometry bias implied by the size residual between the faintest and brightest
        mean_sigma = 0.5 * (sizes.sigma_x.mean() + sizes.sigma_y.mean())
        span = (sizes.peak_e.max() - sizes.peak_e.min()) / 1e5
        slopes = [out[f"raw_slope_{a}"] * out[f"slope_{a}_percent"] / 100.0 for a in "xy"]
        out["photometry_bias_mmag"] = float(1e3 * _MAG_PER_FRACTION * np.mean(slopes) * span
                                            / mean_sigma)
        out["size_rms_x_pix"] = float(np.std(residual_x))
        out["size_rms_y_pix"] = float(np.std(residual_y))
    if observables.correlations is not None:
        out["correlation_rms"] = float(np.std(residual[problem.slices["correlations"]]))
    if observables.linearity is not None:
        block = residual[problem.slices["linearity"]]
        out["linearity_max_frac_residual"] = float(
            np.max(np.abs(block / observables.linearity.mean_e)))
    if observables.ptc is not None:
        block = residual[problem.slices["ptc"]]
        out["ptc_max_frac_residual"] = float(np.max(np.abs(block / observables.ptc.var_e)))
    star = observables.meta.get("star_residual")
    if star is not None:
        # the stars' stacked residual is a fixed diagnostic (no candidate changes it)
        out["star_residual_rms_over_peak"] = star["rms_over_peak"]
        out["star_residual_chi2_per_pixel"] = star["chi2_per_pixel"]
    return out


@dataclass(frozen=True)
class DiagnosisResult:
    """Outcome of the closed loop.

    Attributes
    ----------
    residual_before, residual_after : dict
        Residual summaries of the base model and of the final model (see module notes).
    candidates : list of dict
        One entry per candidate and round: ``round``, ``name``, ``statistic`` (Delta chi2,
        positive = better fit; None if not testable), ``delta_bic`` (None if not testable),
        ``k``, ``parameters`` and ``errors`` of the joint fit, ``testable``, ``allowed``
        (False: the fit is outside the effect's physical bounds, so it cannot be selected).
    selected : list of str
        Names of the added effects, in order (``name@physical``: fixed at its physical value).
    parameters : dict
        Final fitted parameters of each selected effect: name -> {value, error, physical}.
    threshold : float
    curves : dict
        Arrays for the plots: ``peak_e``, ``sigma_x``, ``sigma_y``, errors, ``base_x``,
        ``base_y`` (base model with fitted intercepts), ``final_x``, ``final_y``, ``group``.
    ptc_curves : dict
        PTC residuals for the plot (empty without a PTC observable): ``mean_e``,
        ``residual_raw`` (data minus the calibrated sum-rule model, nothing refitted),
        ``residual_before``, ``residual_after`` (data minus base / final model with the
        nuisance refitted, e-^2), ``error``, ``var_e``.
    """

    residual_before: dict
    candidates: list
    selected: list
    residual_after: dict
    parameters: dict
    threshold: float
    curves: dict = field(default_factory=dict)
    ambiguous: dict = field(default_factory=dict)
    residual_physical: dict = None
    ptc_curves: dict = field(default_factory=dict)

    def to_json_dict(self):
        """The ``--json`` summary: residual_before, candidates, selected, residual_after (+)."""
        def clean(value):
            if isinstance(value, dict):
                return {key: clean(item) for key, item in value.items()}
            if isinstance(value, (list, tuple, np.ndarray)):
                return [clean(item) for item in value]
            if isinstance(value, (float, np.floating)):
                return float(value) if np.isfinite(value) else None
            if isinstance(value, np.integer):
                return int(value)
            if isinstance(value, np.bool_):
                return bool(value)
            return value

        return clean({"residual_before": self.residual_before, "candidates": self.candidates,
                      "selected": self.selected, "residual_after": self.residual_after,
                      "parameters": self.parameters, "threshold": self.threshold,
                      "ambiguous": self.ambiguous,
                      "residual_physical": self.residual_physical})


def diagnose(observables, *, catalogue=CATALOGUE, threshold=DEFAULT_THRESHOLD, max_rounds=4,
             prefer_physical=False):
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

    Returns
    -------
    DiagnosisResult
    """
    if not threshold < 0:
        msg = f"threshold must be a negative Delta BIC, got {threshold!r}"
        raise BFPSFValueError(msg, threshold)
    problem = _build_problem(observables)
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
        templates = effect.templates(observables)
        design = _effect_design(problem, templates) if templates else None
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
        params, covariance, chi2, model = _wls(problem.residual - offset, problem.sigma,
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
    candidates = []
    ambiguous = {}
    for round_index in range(int(max_rounds)):
        scores = []
        taken = {family(name) for name in selected}
        for name, effect in options:
            if family(name) in taken:
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
                if is_fixed:
                    values, errors = list(effect.physical_value), [0.0] * effect.k
                else:
                    own = slice(params.size - k, params.size)
                    values = params[own].tolist()
                    errors = np.sqrt(np.abs(np.diag(covariance)[own])).tolist()
                allowed = effect.bounds is None or all(
                    low <= value <= high for value, (low, high) in zip(values, effect.bounds))
                entry.update(statistic=float(statistic), delta_bic=float(delta_bic),
                             parameters=values, errors=errors, allowed=bool(allowed))
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
        # candidates the data cannot tell apart from the winner (Delta BIC within 10 of it)
        ambiguous[best_name] = sorted(name for bic, name, _ in scores
                                      if name != best_name and family(name) != family(best_name)
                                      and bic - best_bic < -DEFAULT_THRESHOLD)
        selected.append(best_name)
        chi2_current = best_chi2

    physical_names = sorted(fixed)
    residual_physical = None
    if physical_names:
        residual_physical = _summary(problem, observables, fit(physical_names)[3])
        residual_physical["effects"] = physical_names
    params, covariance, _, model_after = fit(selected)
    parameters = {}
    column = problem.nuisance.shape[1]
    by_name = {effect.name: effect for effect in catalogue}
    for name in selected:
        effect = by_name[family(name)]
        physical = list(effect.physical_value) if effect.physical_value else None
        if name in fixed:
            parameters[name] = {"names": list(effect.parameters), "value": physical,
                                "error": [0.0] * effect.k, "physical": physical}
            continue
        own = slice(column, column + effect.k)
        parameters[name] = {"names": list(effect.parameters), "value": params[own].tolist(),
                            "error": np.sqrt(np.abs(np.diag(covariance)[own])).tolist(),
                            "physical": physical}
        column += effect.k

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
    return DiagnosisResult(residual_before=_summary(problem, observables, model_before),
                           candidates=candidates, selected=selected,
                           residual_after=_summary(problem, observables, model_after),
                           parameters=parameters, threshold=float(threshold), curves=curves,
                           ambiguous=ambiguous, residual_physical=residual_physical,
                           ptc_curves=ptc_curves)


