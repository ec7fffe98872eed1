"""The closed loop: residual -> missing effect -> added -> before / after.

`diagnose` fits the base model to the observables (`bfpsf.validation.effects`), looks at what
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
  a(0, 0) (`bfpsf.validation.effects.PTCTable`); a free constant (read noise), a free
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
from .effects import CATALOGUE

__all__ = ["DiagnosisResult", "diagnose", "DEFAULT_THRESHOLD", "slope_residuals", "matched_profile",
           "observables_from_sizes", "observables_from_tables", "observables_from_measured",
           "read_lage_spot_table", "read_bot_spot_table", "MEASURED_SETS",
           "observables_from_images", "flat_observables", "ptc_observable",
           "stacked_star_residual"]

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


def _line_slope(x, y, sigma, group):
    """Weighted slope of y against x with a free intercept per group."""
    groups = np.unique(group)
    design = np.column_stack([x] + [(group == g).astype(float) for g in groups])
    params, covariance, _, _ = _wls(y, sigma, design)
    return float(params[0]), float(np.sqrt(max(covariance[0, 0], 0.0)))


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
    peak = sizes.peak_e / 1e5
    out = {}
    for axis, measured, error, residual in (("x", sizes.sigma_x, sizes.sigma_x_err, residual_x),
                                            ("y", sizes.sigma_y, sizes.sigma_y_err, residual_y)):
        raw, _ = _line_slope(peak, measured, error, sizes.group)
        slope, slope_err = _line_slope(peak, residual, error, sizes.group)
        out[f"raw_slope_{axis}"] = raw
        out[f"slope_{axis}_percent"] = 100.0 * slope / raw
        out[f"slope_{axis}_percent_err"] = 100.0 * slope_err / abs(raw)
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
        Candidates (default `bfpsf.validation.effects.CATALOGUE`).
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


# -- observables from data -----------------------------------------------------------------------
def _scatter_errors(peak, values, group, degree=2):
    """Per-point error from the scatter about a polynomial in peak, per group (pixels).

    For tables that give no per-point errors. A quadratic (not a line) so that curvature, which
    a candidate may explain, does not inflate the errors; the rms is corrected for the fitted
    degrees of freedom.
    """
    errors = np.empty_like(values)
    for g in np.unique(group):
        members = group == g
        x, y = peak[members] / 1e5, values[members]
        if members.sum() <= degree + 2:
            msg = f"group {g} has {members.sum()} points: too few to estimate errors"
            raise BFPSFInputError(msg, int(members.sum()))
        fit = np.polyval(np.polyfit(x, y, degree), x)
        errors[members] = np.sqrt(np.sum((y - fit) ** 2) / (members.sum() - degree - 1))
    return errors


def matched_profile(sigma_x, sigma_y, *, beta=None, measure="moments", pixel=True):
    """A GalSim profile whose measured size (pixelised, as measured) is (sigma_x, sigma_y).

    Parameters
    ----------
    sigma_x, sigma_y : float
        Target widths, pixels (the zero-flux intercepts of the data).
    beta : float, optional
        Moffat index; default a Gaussian.
    measure : {'moments', 'gaussian_fit'}
        How the data measured them; a pixel-integrated Gaussian fit returns the Gaussian's own
        sigma, adaptive moments of pixelised data add the pixel response.
    pixel : bool
        Whether the measurement saw pixelised images (default True).

    Returns
    -------
    galsim.GSObject of unit flux (pixel response not included)
    """
    import galsim

    def build(sx, sy):
        base = galsim.Gaussian(sigma=1.0) if beta is None else galsim.Moffat(beta=beta,
                                                                             half_light_radius=1.0)
        size = galsim.hsm.FindAdaptiveMom(base.drawImage(nx=96, ny=96, scale=0.05,
                                                         method="no_pixel")).moments_sigma * 0.05
        return base.transform(sx / size, 0.0, 0.0, sy / size)

    if measure == "gaussian_fit" and beta is None:
        return build(sigma_x, sigma_y)
    sx, sy = sigma_x, sigma_y
    for _ in range(4):
        profile = build(sx, sy)
        stamp = profile.drawImage(nx=41, ny=41, scale=1.0, method="auto" if pixel else "no_pixel")
        # GalSim's HSM as the reference estimator here (same definition as bfpsf's moments,
        # robust for the small, exactly centred spots of this model-building step)
        from ..measure.moments import moments_from_hsm

        mxx, myy = moments_from_hsm(galsim.hsm.FindAdaptiveMom(stamp))[:2]
        sx *= sigma_x / np.sqrt(mxx)
        sy *= sigma_y / np.sqrt(myy)
    return build(sx, sy)


def _intercepts(table):
    px = np.polyfit(table.peak_e, table.sigma_x, 1)
    py = np.polyfit(table.peak_e, table.sigma_y, 1)
    return px[1], py[1]


def observables_from_sizes(sizes, shifts, *, area=None, beta=None, measure="moments", phases=3,
                           linearity=None, correlations=None, meta=None, ptc=None):
    """Observables for a size table and a set of boundary shifts (the G15 prediction).

    The model spot is matched to the zero-flux intercepts of the sizes (`matched_profile`).
    """
    from .effects import Observables, SpotForwardModel

    sigma_x0, sigma_y0 = _intercepts(sizes)
    profile = matched_profile(sigma_x0, sigma_y0, beta=beta, measure=measure)
    model = SpotForwardModel(profile, shifts, phases=phases, measure=measure)
    meta = dict(meta or {})
    if area is not None:
        meta["area"] = np.asarray(area, dtype=float)
    return Observables(sizes=sizes, spot_model=model, linearity=linearity,
                       correlations=correlations, meta=meta, ptc=ptc)


def read_lage_spot_table(path, *, corrected=False):
    """Lage's spot sizes vs peak (UC Davis ITL-3800C-002) as a `SizeTable`.

    The table gives no per-point errors: they are estimated from the scatter about a quadratic
    per segment and axis (`_scatter_errors`). ``corrected=True`` reads the sizes after Lage's
    kernel correction.
    """
    from astropy.table import Table

    from .effects import SizeTable

    table = Table.read(path, format="ascii.csv")
    prefix = "corr_" if corrected else ""
    try:
        peak = np.asarray(table[f"{prefix}peak_pixel_electrons"], float)
        sigma_x = np.asarray(table[f"{prefix}sigma_x_pix"], float)
        sigma_y = np.asarray(table[f"{prefix}sigma_y_pix"], float)
        group = np.unique(np.asarray(table["segment"]), return_inverse=True)[1]
    except KeyError as error:
        msg = f"{path}: missing column {error} of Lage's spot table"
        raise BFPSFInputError(msg, path) from None
    return SizeTable(peak, sigma_x, sigma_y, _scatter_errors(peak, sigma_x, group),
                     _scatter_errors(peak, sigma_y, group), group=group,
                     label="ITL-3800C-002 spots (Lage)")


def read_bot_spot_table(path, *, gain, peak_fraction=None, corrected=False):
    """LSSTCam BOT spot moments (Lage's notebooks) as a `SizeTable` with peak in e-.

    sigma = sqrt(xx), error = max(rms / sqrt(n) / (2 sigma), scatter about a quadratic): the
    exposures come from different epochs and jump by more than the statistical error
    (SOURCE.md). The peak is flux * gain * ``peak_fraction``; default the central-pixel
    fraction of a Gaussian of the mean size.
    """
    from astropy.table import Table

    from .effects import SizeTable

    table = Table.read(path, format="ascii.csv", comment="#")
    prefix = "corr_" if corrected else ""
    flux_e = np.asarray(table[f"{prefix}mean_flux_adu"], float) * gain
    xx = np.asarray(table[f"{prefix}mean_xx_pix2"], float)
    yy = np.asarray(table[f"{prefix}mean_yy_pix2"], float)
    n = np.asarray(table[f"{prefix}n_spots"], float)
    sigma_x, sigma_y = np.sqrt(xx), np.sqrt(yy)
    if peak_fraction is None:
        from scipy.special import erf

        edge_x = 0.5 / (np.sqrt(2) * np.sqrt(np.mean(xx) - 1 / 12))
        edge_y = 0.5 / (np.sqrt(2) * np.sqrt(np.mean(yy) - 1 / 12))
        peak_fraction = erf(edge_x) * erf(edge_y)
    peak = flux_e * peak_fraction
    group = np.zeros(peak.size, int)
    stat_x = np.asarray(table[f"{prefix}rms_xx_pix2"], float) / np.sqrt(n) / (2 * sigma_x)
    stat_y = np.asarray(table[f"{prefix}rms_yy_pix2"], float) / np.sqrt(n) / (2 * sigma_y)
    err_x = np.maximum(stat_x, _scatter_errors(peak, sigma_x, group))
    err_y = np.maximum(stat_y, _scatter_errors(peak, sigma_y, group))
    return SizeTable(peak, sigma_x, sigma_y, err_x, err_y, group=group,
                     label="LSSTCam BOT R22_S11 E2V spots (Lage)")


#: The measured data sets the table mode knows by folder name.
MEASURED_SETS = {
    "lage_BF_Kernel_ITL3800C002": dict(
        correlations="corr_meas_VBB60_7_2_3500flats.txt",
        sizes="spot_sizes_vs_flux_ITL-3800C-002_20171128_VBB60.csv", kind="lage",
        measure="gaussian_fit"),
    "lage_LSSTCam_BOT_spots_2019": dict(
        correlations=("../lsst_cp_pipe_LSSTCam_R22_S11_amatrix/"
                      "amatrix_LSSTCam_R22_S11_E2V-CCD250-382.csv"),
        sizes="spot_moments_vs_flux_BOT_E2V_R22_S11.csv", kind="bot",
        ptc="ptc_polyfit_BOT_E2V_R22_S11.csv", measure="moments"),
}


def observables_from_tables(correlations, sizes, *, kind=None, gain=None, measure=None,
                            phases=3, corrected=False):
    """Observables from a measured a / correlation table and a size-vs-flux table.

    Parameters
    ----------
    correlations : path
        Any table `bfpsf.calibration.measured.read_measured_area` reads.
    sizes : path
        Lage's ITL spot table (``kind='lage'``) or BOT spot moments (``kind='bot'``; needs
        ``gain``, e-/ADU). The kind is guessed from the header when not given.
    measure : {'moments', 'gaussian_fit'}, optional
        How the sizes were measured (default: Gaussian fit for Lage's table, moments for BOT).
    corrected : bool
        Use the sizes after the published kernel correction instead of the raw ones.

    Returns
    -------
    Observables
        With ``meta`` holding ``area``, ``area_err``, ``shift_solution`` and the inputs.
    """
    from ..calibration.coefficients import solve_ei_shifts
    from ..calibration.measured import read_measured_area

    measured = read_measured_area(correlations)
    solution = solve_ei_shifts(measured.area, measured.area_err, n_monte_carlo=0)
    with open(sizes) as handle:
        text = handle.read(4096)
    if kind is None:
        kind = "lage" if text.startswith("segment,") else "bot"
    if kind == "lage":
        table = read_lage_spot_table(sizes, corrected=corrected)
        measure = measure or "gaussian_fit"
    elif kind == "bot":
        if gain is None:
            msg = "BOT spot moments are in ADU: give the gain (e-/ADU)"
            raise BFPSFInputError(msg, sizes)
        table = read_bot_spot_table(sizes, gain=gain, corrected=corrected)
        measure = measure or "moments"
    else:
        msg = f"kind must be 'lage' or 'bot', got {kind!r}"
        raise BFPSFValueError(msg, kind)
    meta = {"correlations": str(correlations), "sizes": str(sizes), "kind": kind,
            "measure": measure, "shift_solution": solution, "area_err": measured.area_err,
            "gain": gain, "corrected": corrected}
    return observables_from_sizes(table, solution.shifts, area=measured.area, measure=measure,
                                  phases=phases, meta=meta)


def observables_from_measured(directory, *, phases=3, corrected=False):
    """Observables of one of the measured data sets (`MEASURED_SETS`) by its folder."""
    import os

    directory = os.fspath(directory).rstrip("/")
    name = os.path.basename(directory)
    if name not in MEASURED_SETS:
        msg = f"unknown measured data set {name!r}; known: {sorted(MEASURED_SETS)}"
        raise BFPSFInputError(msg, name)
    spec = MEASURED_SETS[name]
    gain = None
    if "ptc" in spec:
        from astropy.table import Table

        ptc = Table.read(os.path.join(directory, spec["ptc"]), format="ascii.csv", comment="#")
        gain = float(np.mean(ptc["gain_e_per_adu"]))
    return observables_from_tables(os.path.join(directory, spec["correlations"]),
                                   os.path.join(directory, spec["sizes"]), kind=spec["kind"],
                                   gain=gain, measure=spec["measure"], phases=phases,
                                   corrected=corrected)


def _binned_sizes(peak, sigma_x, sigma_y, n_bins, label):
    """Mean sizes in quantile bins of peak, errors from the scatter in each bin."""
    from .effects import SizeTable

    edges = np.quantile(peak, np.linspace(0.0, 1.0, n_bins + 1))
    index = np.clip(np.searchsorted(edges, peak, side="right") - 1, 0, n_bins - 1)
    rows = []
    for k in range(n_bins):
        members = index == k
        if members.sum() < 3:
            continue
        root_n = np.sqrt(members.sum())
        rows.append((peak[members].mean(), sigma_x[members].mean(), sigma_y[members].mean(),
                     sigma_x[members].std(ddof=1) / root_n, sigma_y[members].std(ddof=1) / root_n))
    if len(rows) < 3:
        msg = f"only {len(rows)} peak bins hold 3 or more stars: too few to diagnose"
        raise BFPSFInputError(msg, len(rows))
    rows = np.array(rows)
    return SizeTable(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], label=label)


def flat_observables(calibration):
    """Linearity and correlation tables of a `Calibration` (its per-pair PTC table).

    The correlations are R(dx, dy) = C(dx, dy) / C(0, 0) of each pair BEFORE the pedestal
    subtraction, for lags (1, 0) and (0, 1), with error 1 / sqrt(pixel products).
    """
    from .effects import CorrelationTable, LinearityTable

    ptc = calibration.ptc
    used = np.asarray(ptc["used"], bool)
    mean = np.asarray(ptc["mean_e"], float)[used]
    linearity = LinearityTable(np.asarray(ptc["exptime"], float)[used], mean,
                               np.sqrt(np.asarray(ptc["var_e"], float)[used]
                                       / np.asarray(ptc["npix"], float)[used]))
    correlations = None
    if calibration.covariances_adu is not None:
        cov = np.asarray(calibration.covariances_adu, float)[used]
        npix = np.asarray(calibration.npix, float)[used]
        lags = ((1, 0), (0, 1))
        r = np.column_stack([cov[:, dy, dx] / cov[:, 0, 0] for dx, dy in lags])
        r_err = np.column_stack([1.0 / np.sqrt(npix[:, dy, dx]) for dx, dy in lags])
        correlations = CorrelationTable(mean, lags, r, r_err)
    return linearity, correlations


def ptc_observable(calibration):
    """PTC residuals of a `Calibration`: variance minus the PTC model with the sum-rule a(0, 0).

    The model is A+19 eq. 20 (`bfpsf.calibration.ptc.full_covariance_model`) with the
    calibrated gain, noise matrix, a and b, and a(0, 0) = -sum of the other a(dx, dy) over the
    full plane of measured lags (each off-axis lag counted 4 times, each on-axis lag twice).
    Errors: shot noise of the variance (`bfpsf.calibration.ptc.covariance_errors`); the error
    of the sum (from a_err, lags independent) is kept apart (``sum_rule_err``): it is common
    to all pairs. Pairs not used by the calibration (above the PTC turnoff) are left out.

    Returns
    -------
    PTCTable
    """
    from ..calibration.ptc import covariance_errors, full_covariance_model
    from .effects import PTCTable

    if calibration.covariances_adu is None or calibration.npix is None:
        msg = "the calibration holds no per-pair covariances: cannot form PTC residuals"
        raise BFPSFInputError(msg)
    used = np.asarray(calibration.ptc["used"], bool)
    gain = float(calibration.gain)
    mean_adu = np.asarray(calibration.ptc["mean_adu"], float)[used]
    cov = np.asarray(calibration.covariances_adu, float)[used]
    npix = np.asarray(calibration.npix, float)[used]
    area = np.array(calibration.a, dtype=float)
    area_err = np.asarray(calibration.a_err, dtype=float)
    weights = np.full(area.shape, 4.0)
    weights[0, :] = 2.0
    weights[:, 0] = 2.0
    weights[0, 0] = 0.0
    area[0, 0] = -np.sum(weights * area)
    sum_rule_err = float(np.sqrt(np.sum((weights * area_err) ** 2)))
    c = area * np.asarray(calibration.b, dtype=float)
    noise = np.asarray(calibration.noise_matrix_e2, dtype=float)

    def variance(mean):
        return full_covariance_model(mean, area, c, noise, gain)[:, 0, 0] * gain ** 2

    mean_e = mean_adu * gain
    model = variance(mean_adu)
    step = 1e-4 * mean_adu
    slope = (variance(mean_adu + step) - variance(mean_adu - step)) / (2 * step * gain)
    var_e = cov[:, 0, 0] * gain ** 2
    shot = covariance_errors(cov, npix)[:, 0, 0] * gain ** 2
    return PTCTable(mean_e, var_e, shot, model, slope, sum_rule_err=sum_rule_err)


def stacked_star_residual(images, tables, psf, *, half_size=None, noise_e=0.0, min_peak_e=0.0):
    """Stacked, flux-normalised residual of stars against the flux-dependent PSF P(F).

    For each star (row of a `bfpsf.measure.sources.measure_sources` table, unflagged, peak
    above ``min_peak_e``): the model ``psf.star_image(F)`` (`FluxDependentPSF.star_image`, the
    code `bfpsf.validation.validate` stacks) at the star's sub-pixel phase, F refitted once
    by linear least squares on the stamp; the residual (data - model) / F is averaged over
    stars. Its expected variance per pixel, sum (model + noise_e^2) / F^2 / N^2 (Poisson and
    read noise), gives a chi2 per pixel: about 1 when P(F) describes the stars.

    Parameters
    ----------
    images : sequence of ndarray [y, x]
        Images, e- (background subtracted).
    tables : sequence of astropy Table
        Source tables of the images (``x``, ``y``, ``flux_e``, ``peak_e``, ``flags``).
    psf : bfpsf.model.psf.FluxDependentPSF
        In e- (``gain=1``).
    half_size : int, optional
        Stamps are 2 half_size + 1 pixels square; default the PSF's half size.
    noise_e : float
        Read noise (and sky), e- rms per pixel.
    min_peak_e : float
        Only stars brighter than this enter the stack.

    Returns
    -------
    dict or None (no star)
        ``image`` (stacked residual, fraction of the unit-flux star per pixel), ``sigma``
        (its expected noise), ``model_peak`` (peak of the unit-flux model), ``rms_over_peak``
        (rms of the stack / model peak), ``chi2_per_pixel``, ``n_stars``, ``radius`` and
        ``profile`` (azimuthal mean in rings of 0.5 px, `bfpsf.plotting.diagnose`).
    """
    from ..plotting.diagnose import radial_profile

    half = int(psf.half_size if half_size is None else half_size)
    total, variance, model_sum, count = 0.0, 0.0, 0.0, 0
    for image, table in zip(images, tables):
        image = np.asarray(image, float)
        ny, nx = image.shape
        good = (np.asarray(table["flags"]) == 0) & (np.asarray(table["peak_e"]) > min_peak_e)
        for row in np.flatnonzero(good):
            x, y = float(table["x"][row]), float(table["y"][row])
            cx, cy = int(np.round(x)), int(np.round(y))
            if cx - half < 0 or cy - half < 0 or cx + half >= nx or cy + half >= ny:
                continue        # too close to the edge for a full stamp
            data = image[cy - half:cy + half + 1, cx - half:cx + half + 1]
            flux = float(table["flux_e"][row])
            model = psf.star_image(flux, x_phase=x - cx, y_phase=y - cy, half_size=half)
            flux *= float(np.sum(data * model) / np.sum(model * model))
            model = psf.star_image(flux, x_phase=x - cx, y_phase=y - cy, half_size=half)
            total = total + (data - model) / flux
            variance = variance + (np.clip(model, 0, None) + noise_e ** 2) / flux ** 2
            model_sum = model_sum + model / flux
            count += 1
    if count == 0:
        return None
    stack = total / count
    sigma = np.sqrt(variance) / count
    peak = float(np.max(model_sum / count))
    radius, profile = radial_profile(stack)
    return {"image": stack, "sigma": sigma, "model_peak": peak,
            "rms_over_peak": float(np.std(stack) / peak),
            "chi2_per_pixel": float(np.mean((stack / sigma) ** 2)), "n_stars": count,
            "radius": radius, "profile": profile}


def observables_from_images(flats, images, *, beta=None, maxlag=4, n_bins=10, gain=None,
                            calibration=None, fit_b=True, amp=None):
    """Observables from flat-field FITS and spot / star images (ADU, bias subtracted).

    The flats are calibrated (`bfpsf.calibrate`), the sources of every image measured
    (`bfpsf.measure.sources.measure_sources`, unflagged sources only) and their sizes averaged
    in ``n_bins`` quantile bins of peak; the spot model is matched to the zero-flux intercept
    (a Moffat of index ``beta``, or a Gaussian). ``fit_b`` is passed to `bfpsf.calibrate`
    (False for a few small flats, whose b term is unconstrained). The loop works on one
    amplifier: ``amp`` names it in multi-amplifier files (flats and images are read by
    `bfpsf.io.amplifiers`).

    Also formed: the PTC residuals (`ptc_observable`, a fitted observable) and the stacked
    residual of the stars against P(F) built from the matched profile and the calibrated
    shifts (`stacked_star_residual`, in ``meta['star_residual']``, with the stacked image in
    ``meta['residual_images']`` for the report).
    """
    from ..calibration import calibrate
    from ..calibration.product import Calibration
    from ..io.amplifiers import read_amplifiers
    from ..measure.sources import measure_sources

    cal = calibration or calibrate(list(flats), maxlag=maxlag, n_monte_carlo=0, fit_b=fit_b,
                                   amps=amp)
    if not isinstance(cal, Calibration):
        msg = (f"the flats hold {len(cal)} amplifiers ({', '.join(cal.names)}); the closed loop "
               "works on one: choose it with --amp NAME")
        raise BFPSFInputError(msg, cal.names)
    if cal.shifts is None:
        reason = cal.parameters.get("shifts_failure", "not solved")
        msg = f"the calibration has no boundary shifts ({reason})"
        raise BFPSFInputError(msg)
    gain = cal.gain if gain is None else gain
    peaks, sigma_x, sigma_y = [], [], []
    pixels, tables = [], []
    for path in images:
        amplifiers = read_amplifiers(path, amp, what="image")
        if len(amplifiers) > 1:
            msg = (f"{path} holds {len(amplifiers)} amplifiers; the closed loop works on one: "
                   "choose it with --amp NAME")
            raise BFPSFInputError(msg, str(path))
        data = amplifiers[0].data
        table = measure_sources(data * gain)
        pixels.append(data * gain)
        tables.append(table)
        good = np.asarray(table["flags"]) == 0
        peaks.append(np.asarray(table["peak_e"], float)[good])
        sigma_x.append(np.asarray(table["sigma_x"], float)[good])
        sigma_y.append(np.asarray(table["sigma_y"], float)[good])
    peaks, sigma_x, sigma_y = (np.concatenate(v) for v in (peaks, sigma_x, sigma_y))
    sizes = _binned_sizes(peaks, sigma_x, sigma_y, n_bins, f"{len(images)} images")
    linearity, correlations = flat_observables(cal)
    meta = {"flats": len(list(flats)), "images": len(list(images)), "gain": float(gain),
            "n_sources": int(peaks.size)}
    try:
        ptc = ptc_observable(cal)
    except (BFPSFInputError, BFPSFValueError) as error:
        # e.g. a calibration read from a file without per-pair covariances: said, not hidden
        ptc = None
        meta["ptc_unavailable"] = str(error)
    observables = observables_from_sizes(sizes, cal.shifts, area=cal.a, beta=beta,
                                         linearity=linearity, correlations=correlations,
                                         meta=meta, ptc=ptc)
    from ..model.psf import FluxDependentPSF

    psf = FluxDependentPSF.from_galsim(observables.spot_model.profile, cal.shifts)
    star = stacked_star_residual(pixels, tables, psf, half_size=min(psf.half_size, 7),
                                 noise_e=float(cal.noise_e))
    if star is not None:
        observables.meta["star_residual"] = star
        observables.meta["residual_images"] = {"stars - P(F), stacked / F": star["image"]}
    return observables
