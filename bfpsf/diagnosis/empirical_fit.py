"""Learning the EMPIRICAL term from the stars' size residual, and judging it out of sample.

When the loop leaves a size residual that no catalogue effect matches (`bfpsf.diagnosis.signature`),
`fit_empirical` fits `bfpsf.model.empirical.EmpiricalTerm` to it: per axis, the residual
sigma^2 - sigma_model^2 is [c(x, t) F / F_ref + q(x, t) (F / F_ref)^2] (through the adaptive
moments' response to the patterns, `adaptive_response`) plus an intercept per group, c and q
each a constant plus a position term (x - x_ref) / 1000, a row term (y - y_ref) / 1000 and an
exposure term (t - t_ref); the position, row and exposure terms enter only where the residual report found that dependence
(`bfpsf.diagnosis.unexplained.describe_unexplained`). Weighted least squares with the sizes' errors.

`evaluate_empirical` applies a term to other data (the held-out exposures of the loop's split;
for a term that changes over the night, also a contiguous block of late exposures fitted on
the early ones) and reports the BF slope residual left (percent of the raw slope, per axis)
and the photometry bias it implies (mmag, as `bfpsf.diagnosis.loop` computes it), before and
after the term.
"""

import dataclasses

import numpy as np

from ..least_squares import weighted_least_squares
from ..model.empirical import (FLUX_REFERENCE, PATTERN_KIND, PATTERNS, EmpiricalTerm,
                               apply_pattern)
from ..moments.adaptive import adaptive_moments_batch
from .problem import slope_residuals
from .tables import Observables

__all__ = ["fit_empirical", "evaluate_empirical", "predicted_size_change",
           "predicted_cross_change", "cross_slope", "early_late", "adaptive_response",
           "MOMENTS"]



def _terms(sizes, fluxes, references, position, exposure, row=False):
    """Columns multiplying each term of c and q (`EmpiricalTerm`) per entry: the flux basis
    (F / F_ref, (F / F_ref)^2) times (1, position, row, exposure); ``references`` are the
    column, row and exposure the terms are centred on."""
    x_reference, y_reference, exposure_reference = references
    scaled = np.asarray(fluxes, float) / FLUX_REFERENCE
    dependence = {"": np.ones(len(sizes))}
    if position and sizes.x_detector is not None:
        dependence["position"] = (sizes.x_detector - x_reference) / 1000.0
    if row and sizes.y_detector is not None:
        dependence["row"] = (sizes.y_detector - y_reference) / 1000.0
    if exposure and sizes.exposure is not None:
        dependence["exposure"] = np.asarray(sizes.exposure, float) - exposure_reference
    columns = {}
    for name, values in dependence.items():
        columns[name or "constant"] = scaled * values
        columns["flux2_" + name if name else "flux2"] = scaled ** 2 * values
    return columns


def adaptive_response(spot_model, peak_e, *, step=0.05, kind=PATTERN_KIND):
    """How the measured (adaptive) second moments respond to each pattern, per unit pattern
    variance: {pattern: {'mxx': d Mxx, 'myy': d Myy, 'mxy': d Mxy}}.

    The patterns change the plain second moments by exactly their coefficient along their own
    axis; the adaptive moments the loop measures weight the core and re-shape their weight, so
    they see about 3.4 times the change along the pattern's axis (the pattern, like the
    charge-driven effects it stands for, acts on the core, where their weight is) and a
    fraction of it along the other (0.58 for a Moffat of beta 3). Measured on the model spot at
    ``peak_e``, averaged over its phases; ``kind``: the patterns' (`PATTERN_KINDS`).
    """
    stamps = spot_model.stamps([peak_e])[0]
    base = adaptive_moments_batch(stamps)
    out = {}
    for pattern in PATTERNS:
        changed = np.array([stamp + step * apply_pattern(stamp, pattern, kind=kind)
                            for stamp in stamps])
        after = adaptive_moments_batch(changed)
        out[pattern] = {moment: float(np.mean((np.asarray(getattr(after, moment))
                                               - np.asarray(getattr(base, moment))) / step))
                        for moment in MOMENTS}
    return out


#: The measured second moments, in the order of `EmpiricalTerm.variance_change`'s patterns.
MOMENTS = ("mxx", "myy", "mxy")
_IDENTITY = {pattern: {moment: float(k == j) for k, moment in enumerate(MOMENTS)}
             for j, pattern in enumerate(PATTERNS)}


def _measured_trace(model_sigma, residual):
    """Mxx + Myy of the measured sizes (the model's plus the residual), pixel^2: what turns
    e2 into Mxy and back."""
    return sum((sigma + part) ** 2 for sigma, part in zip(model_sigma, residual))


def _mxy_rows(sizes, model_sigma, residual, cross_residual):
    """The cross moment as Mxy: (target, errors) = e2 residual and its error times
    (Mxx + Myy) / 2 of the measured sizes."""
    half_trace = 0.5 * _measured_trace(model_sigma, residual)
    return (np.asarray(cross_residual, float) * half_trace,
            np.asarray(sizes.cross_err, float) * half_trace)


def fit_empirical(sizes, fluxes, model_sigma, residual, *, position=False, exposure=False,
                  response=None, cross_residual=None, row=False, extent=None, night=None,
                  kind=PATTERN_KIND):
    """Fit the empirical term to a size residual (and a cross-moment one).

    Parameters
    ----------
    sizes : SizeTable
        Groups, positions (``x_detector``, ``y_detector``) and exposures of the entries.
    fluxes : ndarray (n,)
        Total flux of each entry, e-.
    model_sigma : (ndarray, ndarray)
        The model's sigma_x, sigma_y of each entry, pixels.
    residual : (ndarray, ndarray)
        Measured minus model sigma_x, sigma_y, pixels (errors from ``sizes``).
    position, exposure, row : bool
        Fit a dependence of the coefficients on the column / the exposure / the row.
    extent : ((float, float), (float, float)), optional
        The columns and rows the stars span, pixels: the term's field (``x_range``,
        ``y_range``); default the entries' positions, which for size bins are their mean
        positions and span a fraction of the stars' (a new user's photometry said 13 of 45
        stars lay beyond the field of a PSF fitted on those very images: x 45 to 249 against
        the stars' 26 to 273).
    night : (float, float), optional
        The first and last exposure order the term is valid over (``exposure_range``):
        default the entries'. The loop gives the night's, as its held-out exposures
        interleave with those it fitted (a new user's diagnose warned that its own term was
        extrapolated to its last held-out exposure, one beyond the last it fitted).
    response : dict, optional
        `adaptive_response` of the measured sizes (default: the plain moments' identity):
        the coefficients are those of the patterns; both axes are fitted jointly.
    kind : str, optional
        The patterns' kind (`bfpsf.model.empirical.PATTERN_KINDS`; ``response`` must be
        that kind's).
    cross_residual : ndarray (n,), optional
        Measured minus model cross moment e2 (errors ``sizes.cross_err``): the diagonal
        pattern is fitted to it jointly (as Mxy, with an intercept per group); without it the
        term has no diagonal pattern.

    Returns
    -------
    EmpiricalTerm
    """
    references = [float(np.mean(values)) if values is not None else 0.0
                  for values in (sizes.x_detector, sizes.y_detector, sizes.exposure)]
    terms = _terms(sizes, fluxes, references, position, exposure, row)
    response = response or _IDENTITY
    moments = MOMENTS if cross_residual is not None else MOMENTS[:2]
    patterns = PATTERNS if cross_residual is not None else PATTERNS[:2]
    groups = sizes.intercept_design()
    blocks = [np.kron(np.eye(len(moments))[:, [k]], groups) for k in range(len(moments))]
    for pattern in patterns:
        for column in terms.values():
            blocks.append(np.concatenate([response[pattern][moment] * column
                                          for moment in moments])[:, None])
    # in second moments, where the term is linear: (sigma_model + r)^2 - sigma_model^2, with
    # errors 2 sigma err (fitting r ~ dM / (2 sigma) instead leaves r^2, 2 % of the raw slope
    # for an effect of half of it)
    measured = [sigma + part for sigma, part in zip(model_sigma, residual)]
    targets = [m ** 2 - sigma ** 2 for m, sigma in zip(measured, model_sigma)]
    errors_m = [2 * m * err for m, err in zip(measured, (sizes.sigma_x_err, sizes.sigma_y_err))]
    if cross_residual is not None:
        target, error = _mxy_rows(sizes, model_sigma, residual, cross_residual)
        targets.append(target)
        errors_m.append(error)
    params, covariance, _, _ = weighted_least_squares(
        np.concatenate(targets), np.concatenate(errors_m), np.hstack(blocks))
    first = len(moments) * groups.shape[1]
    coefficients, errors, names, columns = {}, {}, [], []
    for index, pattern in enumerate(patterns):
        for k, name in enumerate(terms):
            column = first + index * len(terms) + k
            coefficients.setdefault(pattern, {})[name] = float(params[column])
            errors.setdefault(pattern, {})[name] = float(np.sqrt(abs(covariance[column,
                                                                                column])))
            names.append([pattern, name])
            columns.append(column)
    if extent is not None:
        x_range, y_range = (tuple(float(value) for value in span) for span in extent)
    else:
        x_range, y_range = (None if values is None else (float(np.min(values)),
                                                         float(np.max(values)))
                            for values in (sizes.x_detector, sizes.y_detector))
    exposure_range = (None if sizes.exposure is None else
                      tuple(float(value) for value in night) if night is not None else
                      (float(np.min(sizes.exposure)), float(np.max(sizes.exposure))))
    return EmpiricalTerm(coefficients, errors=errors, x_reference=references[0],
                         y_reference=references[1], exposure_reference=references[2],
                         x_range=x_range, y_range=y_range, exposure_range=exposure_range,
                         kind=kind, covariance={"names": names, "matrix": covariance[
                             np.ix_(columns, columns)]})


def _moment_changes(term, sizes, fluxes, response):
    """dMxx, dMyy, dMxy the term predicts for each entry as measured (``response``:
    `adaptive_response`), pixel^2."""
    x = sizes.x_detector
    exposure = None if sizes.exposure is None else np.asarray(sizes.exposure, float)
    changes = dict(zip(PATTERNS, term.variance_change(fluxes, x=x, exposure=exposure,
                                                      y=sizes.y_detector)))
    response = response or _IDENTITY
    return [sum(response[pattern][moment] * change for pattern, change in changes.items())
            for moment in MOMENTS]


def predicted_size_change(term, sizes, fluxes, model_sigma, response=None):
    """(d sigma_x, d sigma_y) the term predicts for each entry as measured (``response``:
    `adaptive_response`), pixels."""
    changes = _moment_changes(term, sizes, fluxes, response)
    return tuple(np.sqrt(np.clip(sigma ** 2 + change, 1e-12, None)) - sigma
                 for change, sigma in zip(changes, model_sigma))


def predicted_cross_change(term, sizes, fluxes, model_sigma, residual, response=None):
    """d e2 the term predicts for each entry as measured: 2 dMxy over the measured trace."""
    d_mxy = _moment_changes(term, sizes, fluxes, response)[2]
    return 2.0 * np.asarray(d_mxy, float) / _measured_trace(model_sigma, residual)


def cross_slope(sizes, cross_residual):
    """Slope of an e2 residual against peak (per 1e5 e-, an intercept per group) and its
    error: {'slope_per_1e5', 'slope_err'}."""
    slope, error = sizes.peak_slope(cross_residual, sizes.cross_err)[:2]
    return {"slope_per_1e5": slope, "slope_err": error}


def evaluate_empirical(term, sizes, fluxes, model_sigma, residual, response=None,
                       cross_residual=None):
    """The BF slope residual and photometry bias before and after the term (and the e2
    slope, with ``cross_residual``).

    Returns
    -------
    dict
        ``before`` and ``after``: ``slope_x_percent``, ``slope_y_percent`` (of the raw slope)
        with errors, ``photometry_bias_mmag`` (faintest to brightest entry, as the loop's
        summary) and, with ``cross_residual``, ``cross`` (`cross_slope`); ``n`` entries.
    """
    change = predicted_size_change(term, sizes, fluxes, model_sigma, response)
    out = {"n": len(sizes)}
    for label, (rx, ry) in (("before", residual),
                            ("after", (residual[0] - change[0], residual[1] - change[1]))):
        out[label] = slope_residuals(sizes, rx, ry)
    d_e2 = None
    if cross_residual is not None:
        d_e2 = predicted_cross_change(term, sizes, fluxes, model_sigma, residual, response)
        out["before"]["cross"] = cross_slope(sizes, cross_residual)
        out["after"]["cross"] = cross_slope(sizes, np.asarray(cross_residual) - d_e2)
    _add_term_errors(out["after"], term, sizes, fluxes, model_sigma, residual, response,
                     change, d_e2)
    return out


def _add_term_errors(after, term, sizes, fluxes, model_sigma, residual, response, base,
                     base_e2):
    """Add to the errors of ``after`` (`evaluate_empirical`) the error of the term's own
    prediction, from its coefficients' covariance (`EmpiricalTerm.covariance`), in
    quadrature: the data the term was fitted on are not those it is judged on, and the
    residual it leaves scatters by both (on 7 noise draws of the quick one-axis user path the
    held-out X residual scattered by 1.8 % of raw against the 1.3 % of its data alone). Each
    slope is linear in the coefficients (the sizes to first order): one column of its
    Jacobian per coefficient, by a step of that coefficient's error, about the term's own
    predictions ``base`` (d sigma_x, d sigma_y) and ``base_e2`` (d e2, None without the
    cross moment). ``after`` gains ``slope_{x,y}_percent_term_err`` (and
    ``cross['slope_term_err']``)."""
    covariance = term.covariance
    if not covariance or not len(covariance["names"]):
        return
    cross = base_e2 is not None
    matrix = np.asarray(covariance["matrix"], float)
    steps = np.sqrt(np.clip(np.diag(matrix), 0.0, None))
    jacobian = {key: np.zeros(len(steps)) for key in ("x", "y", "cross")}
    for index, ((pattern, name), step) in enumerate(zip(covariance["names"], steps)):
        if not step:
            continue
        coefficients = {key: dict(terms) for key, terms in term.coefficients.items()}
        coefficients[pattern][name] = coefficients[pattern].get(name, 0.0) + step
        moved = dataclasses.replace(term, coefficients=coefficients)
        change = predicted_size_change(moved, sizes, fluxes, model_sigma, response)
        slopes = slope_residuals(sizes, change[0] - base[0], change[1] - base[1])
        for axis in "xy":
            jacobian[axis][index] = slopes[f"slope_{axis}_percent"] / step
        if cross:
            d_e2 = predicted_cross_change(moved, sizes, fluxes, model_sigma, residual,
                                          response)
            jacobian["cross"][index] = cross_slope(sizes, d_e2 - base_e2)["slope_per_1e5"] / step
    for axis in "xy":
        error = float(np.sqrt(max(jacobian[axis] @ matrix @ jacobian[axis], 0.0)))
        after[f"slope_{axis}_percent_term_err"] = error
        after[f"slope_{axis}_percent_err"] = float(np.hypot(after[f"slope_{axis}_percent_err"],
                                                            error))
    if cross:
        error = float(np.sqrt(max(jacobian["cross"] @ matrix @ jacobian["cross"], 0.0)))
        after["cross"]["slope_term_err"] = error
        after["cross"]["slope_err"] = float(np.hypot(after["cross"]["slope_err"], error))


def early_late(observables, late_fraction=1.0 / 3.0):
    """Sizes-only observables of the early exposures and of a contiguous block of late ones
    (the last ``late_fraction`` of the night), or None with fewer than 4 exposures."""
    sizes = observables.sizes
    if sizes is None or sizes.exposure is None:
        return None
    exposures = np.unique(sizes.exposure)
    if exposures.size < 4:
        return None
    n_late = max(1, int(round(late_fraction * exposures.size)))
    late = np.isin(sizes.exposure, exposures[-n_late:])
    parts = []
    for rows in (~late, late):
        if rows.sum() < 3 or np.unique(sizes.group[rows]).size < sizes.n_groups:
            return None
        parts.append(Observables(sizes=sizes.subset(rows), spot_model=observables.spot_model,
                                 meta=observables.meta))
    return tuple(parts)
