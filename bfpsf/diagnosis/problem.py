"""The least-squares problem of the closed loop (`bfpsf.diagnosis.loop.diagnose`).

Every observable (`bfpsf.diagnosis.observables`) is a block of data with its errors and the
base model's nuisance parameters (a free intercept per data-set group, exposure and axis for
the sizes, k t + b for the flat means, a per lag for the correlations, the PTC's read noise,
gain and sum-rule a(0, 0)); `build_problem` stacks them, `effect_design` adds a candidate's
template (`bfpsf.diagnosis.catalogue`) to the design, and `summarise` reads the residual's figures:
the brighter-fatter slope residual in X and Y (slope of the size residual against peak,
percent of the raw measured slope), the photometry bias the size residual implies (a PSF fit
with a template of width sigma on a star of width sigma (1 + eps) is biased by -eps in flux,
1.0857 eps mag, for Gaussian profiles), and chi2 / N per observable.
"""

from dataclasses import dataclass

import numpy as np

from ..measure.slopes import fit_bf_slope
from ..moments.shapes import MAG_PER_SIZE_ERROR
from .catalogue import get_effect, split_template
from .nuisances import GLOBAL_NUISANCES, SCALE, SPLIT

__all__ = ["Problem", "build_problem", "describe_slope", "effect_columns", "effect_design",
           "effect_values", "global_priors",
           "slope_residuals", "BF_DETECTION_SIGMA",
           "summarise"]

#: A raw BF slope below this many times its error is no BF slope: the residual is then
#: reported in pixels, not in percent of it (`describe_slope`).
BF_DETECTION_SIGMA = 3.0


@dataclass(frozen=True)
class Problem:
    """The stacked residual vector of every observable and the base nuisance design."""

    keys: tuple            # observable key of each block
    slices: dict           # key -> slice into the vector
    residual: np.ndarray   # data - fixed base prediction
    sigma: np.ndarray
    nuisance: np.ndarray   # (N, m)
    # nuisance columns held fixed on held-out data: the size scale and split (`global_priors`)
    global_columns: tuple = ()


def _size_block(observables):
    """Size residuals; nuisance: an intercept per group, exposure and axis
    (`SizeTable.intercepts`) and, when the observables carry the calibration's errors of the
    BF prediction (``meta['scale_err']``, ``meta['split_err']``,
    `bfpsf.diagnosis.observables.bf_scale_error`), a common scale of the shifts and a move of
    their X / Y split (`bfpsf.diagnosis.catalogue.split_shifts`) within them (Gaussian
    priors, one pseudo data point each): the prediction is no better than its flats. Both are
    global nuisances (`global_priors`, in that order): fitted in-sample, fixed on held-out
    data.
    """
    sizes, model = observables.sizes, observables.spot_model
    predicted_x, predicted_y = model.sizes(sizes.peak_e)
    residual = np.concatenate([sizes.sigma_x - predicted_x, sizes.sigma_y - predicted_y])
    sigma = np.concatenate([sizes.sigma_x_err, sizes.sigma_y_err])
    intercepts = sizes.intercept_design()
    zeros = np.zeros_like(intercepts)
    nuisance = np.block([[intercepts, zeros], [zeros, intercepts]])
    priors = global_priors(observables.meta)
    if not priors:
        return residual, sigma, nuisance
    templates = [get_effect(SCALE.name).templates(observables)["sizes"]]
    if SPLIT.name in priors:
        templates.append(split_template(observables))
    nuisance = np.hstack([nuisance] + templates)
    prior_design = np.zeros((len(priors), nuisance.shape[1]))
    columns = tuple(range(nuisance.shape[1] - len(priors), nuisance.shape[1]))
    prior_design[np.arange(len(priors)), columns] = 1.0
    return (residual, sigma, nuisance, (prior_design, np.array(list(priors.values()))),
            columns)


def global_priors(meta):
    """The size block's global nuisances (`bfpsf.diagnosis.nuisances.GLOBAL_NUISANCES`) and
    their prior widths: ``calibration_scale`` (``meta['scale_err']``) and, beside it,
    ``calibration_split`` (``meta['split_err']``) where they are positive; {} without the
    scale's."""
    out = {}
    for nuisance in GLOBAL_NUISANCES:
        width = float((meta or {}).get(nuisance.error_key, 0.0) or 0.0)
        if not width > 0:
            if nuisance is SCALE:
                return {}
            continue
        out[nuisance.name] = width
    return out


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


def build_problem(observables):
    keys, slices, residuals, sigmas, nuisances, global_columns = [], {}, [], [], [], []
    start = 0
    for key, block in _BLOCKS.items():
        if getattr(observables, key) is None:
            continue
        residual, sigma, nuisance, *prior = block(observables)
        if len(prior) == 2:
            offset = sum(n.shape[1] for n in nuisances)
            global_columns += [offset + column for column in prior.pop()]
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
    return Problem(tuple(keys), slices, np.concatenate(residuals), np.concatenate(sigmas),
                    design, tuple(global_columns))


def effect_design(problem, templates):
    """Full-length (N, k) design of one effect from its per-observable templates."""
    k = next(iter(templates.values())).shape[1]
    design = np.zeros((problem.residual.size, k))
    for key, template in templates.items():
        if key in problem.slices:
            design[problem.slices[key]] = template
    return design


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
        ``raw_slope_x``, ``raw_slope_y`` and their errors, ``residual_slope_x``,
        ``residual_slope_y`` and their errors (pixels per 100 ke- of peak), ``slope_x_percent``,
        ``slope_y_percent`` and their errors (percent), and ``stars_show_bf_x``,
        ``stars_show_bf_y``: whether the raw slope is above `BF_DETECTION_SIGMA` times its
        error (when not, a percentage of it means nothing: `describe_slope`), and
        ``photometry_bias_mmag``: the bias of PSF photometry the size residual implies between
        the faintest and the brightest entry (module docstring), with its error
        ``photometry_bias_mmag_err``.
    """
    out = {}
    for axis, measured, error, residual in (("x", sizes.sigma_x, sizes.sigma_x_err, residual_x),
                                            ("y", sizes.sigma_y, sizes.sigma_y_err, residual_y)):
        # the given errors, not rescaled by the scatter (the chi2 is reported apart)
        raw_fit = fit_bf_slope(sizes.peak_e, measured, size_err=error, group=sizes.intercepts,
                               scale_errors=False, clip_nsigma=None)
        raw = raw_fit.slope
        fit = fit_bf_slope(sizes.peak_e, residual, size_err=error, group=sizes.intercepts,
                           scale_errors=False, clip_nsigma=None)
        out[f"raw_slope_{axis}"] = raw
        out[f"raw_slope_{axis}_err"] = raw_fit.slope_err
        out[f"residual_slope_{axis}"] = fit.slope
        out[f"residual_slope_{axis}_err"] = fit.slope_err
        out[f"stars_show_bf_{axis}"] = bool(abs(raw) > BF_DETECTION_SIGMA * raw_fit.slope_err)
        out[f"slope_{axis}_percent"] = 100.0 * fit.slope / raw
        out[f"slope_{axis}_percent_err"] = 100.0 * fit.slope_err / abs(raw)
    mean_sigma = 0.5 * (sizes.sigma_x.mean() + sizes.sigma_y.mean())
    span = (sizes.peak_e.max() - sizes.peak_e.min()) / 1e5
    slopes = [out["residual_slope_x"], out["residual_slope_y"]]
    scale = 1e3 * MAG_PER_SIZE_ERROR * span / mean_sigma
    out["photometry_bias_mmag"] = float(scale * np.mean(slopes))
    # (the two axes' errors as independent: a new user read +18.17 mmag without one, where
    # its residual slopes were +27 +- 22 and +31 +- 18 % of raw)
    out["photometry_bias_mmag_err"] = float(scale * 0.5 * np.hypot(
        out["residual_slope_x_err"], out["residual_slope_y_err"]))
    return out


def describe_slope(values, axis, digits=2):
    """One axis's BF slope residual for a person: percent of the raw slope, or, when the stars
    show no BF slope on that axis (``stars_show_bf_{axis}`` false), the residual and the raw
    slope in pixels per 100 ke- of peak (a percentage of a slope consistent with zero means
    nothing: a new user read +957 % of raw on stars with no BF)."""
    if values.get(f"stars_show_bf_{axis}", True):
        text = f"{values[f'slope_{axis}_percent']:+.{digits}f}"
        if f"slope_{axis}_percent_err" in values:
            text += f" +- {values[f'slope_{axis}_percent_err']:.{digits}f}"
        return text + " % of raw"
    return (f"{values[f'residual_slope_{axis}']:+.4f} +- "
            f"{values[f'residual_slope_{axis}_err']:.4f} px per 100 ke- (the stars' BF slope "
            f"in {axis.upper()} is not significant: raw {values[f'raw_slope_{axis}']:+.4f} +- "
            f"{values[f'raw_slope_{axis}_err']:.4f})")


def summarise(problem, observables, model):
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


def effect_columns(problem, names, fixed, by_name, family):
    """name -> slice of each effect's parameters in a joint fit over ``names`` (the nuisance
    columns first, then the free effects in order), or None for an effect fixed at its
    physical value (no column)."""
    out = {}
    column = problem.nuisance.shape[1]
    for name in names:
        if name in fixed:
            out[name] = None
            continue
        k = by_name[family(name)].k
        out[name] = slice(column, column + k)
        column += k
    return out


def effect_values(values, problem, names, fixed, by_name, family):
    """name -> parameter vector of each effect of a joint fit over ``names``."""
    return {name: (np.asarray(by_name[family(name)].physical_value, float) if own is None
                   else values[own])
            for name, own in effect_columns(problem, names, fixed, by_name, family).items()}
