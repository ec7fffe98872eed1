"""Attribution by signature: a candidate is named only when its shape matches in every observable.

A fit alone cannot reject a wrong attribution: an effect nobody declared is present in the
fitted and in the held-out data alike, so any flexible template that takes part of it also
improves the held-out residual. Each catalogue effect predicts more than an amplitude: its
template (`bfpsf.diagnosis.catalogue`) fixes how the change is shared between the observables
(flat means, flat correlations, PTC, star sizes), between the axes (sigma_x against sigma_y),
between faint and bright stars, over the detector and over the night (a catalogue effect is
the same at every position and in every exposure). The signature test checks each of these
*dimensions* separately.

Test statistic, per dimension d with parts i = 1..m (e.g. the X and the Y sizes):

1. Refit the residual with the effect's template split into m copies, each restricted to the
   rows of one part and with its own amplitude p_i, jointly with the base model's nuisances
   and the effects already named (weighted least squares, the observables' errors). Rows of
   the template outside every part keep one common amplitude.
2. Under the hypothesis that the effect (and only its template) is what the data hold, the
   p_i estimate one amplitude a, each through a template accurate to a factor exp(eta_i):
   with C their covariance, chi2_d = min over a, eta of
   (p_i - a exp(eta_i))^T C^-1 (p_i - a exp(eta_i)) + sum eta_i^2 / tau_d^2
   (`one_amplitude_chi2`; a log-normal tolerance, so a part of the other sign, or nil while
   the others are large, contradicts the template however loose tau_d is). tau_d =
   `TEMPLATE_TOLERANCE` [d] is the relative accuracy of the first-order templates between the
   parts: 30 % between observables (a gain non-linearity's amplitude from the flat means and
   from the PTC agree to about 30 %, `tests/test_diagnosis_heldout.py`), 10 % between the
   axes (the model spot's shape), 30 % between faint and bright stars (the first-order
   templates' flux dependence, and the faint stars' size measurement: on the null user path,
   images through P0 fitted from the stars, the BF amplitude of the faint half differs from
   the bright half's by 2 times its 10 % error), 0 between positions and between exposures
   (the same template on the same kind of stars: its errors are common to both halves). The
   covariance is not scaled by the fit's chi2: an effect outside the catalogue inflates that
   chi2 and would weaken the very test meant to catch it.
3. Null distribution: chi-square with (m - 1) k degrees of freedom (k the effect's
   parameters), exact for Gaussian errors and tau = 0, conservative (fewer rejections) with
   tau > 0. The effect matches in d when its p-value is at least ``alpha`` (default
   `SIGNATURE_ALPHA` = 1e-3, 3.3 sigma one-sided).

An effect is named only when it matches in every dimension where its template puts something
in at least two parts; otherwise it is rejected and the report names the dimension with the
smallest p-value (the observable that contradicts it) with the amplitudes of its parts. Only
the parts that measure what the candidate predicts there take part (its amplitude fitted on
the whole template at least `MEASURABLE` errors of the part's): a part that cannot tell the
prediction from nothing cannot contradict it, whatever else it holds. A new user's flats
lost 4e-4 of their charge at 1.3e5 e- (a gain non-linearity their stars, drawn by photon
shooting, do not have), which predicts star sizes 0.2 errors from nothing; a smear along X
in the same stars rejected it "by axis" (p = 4e-22), while the flats with stars without the
smear named it. Where some parts cannot measure it, those that can must find it at the
amplitude its whole template was fitted at (`_support`, chi-square with k degrees of
freedom, the dimension's tolerance): else that fit rests on the parts that hold something
else (a row smear in the star sizes fitted a gain non-linearity the flats did not have).

Dimensions (`signature_parts`): ``observable`` (linearity, correlations, PTC, sizes: flats and
stars must agree), ``axis`` (sizes X, Y), ``position`` (near and far half from the amplifier,
with ``SizeTable.x_detector``), ``row`` (low and high rows, with ``SizeTable.y_detector``) and ``exposure_order`` (first and second half of the night,
with ``SizeTable.exposure``). ``flux`` (faint and bright half of the peaks) is available but
off by default: on the null user path (FITS images, P0 fitted from the stars) the faint
half's BF amplitude differs from the bright half's by more than 3 sigma (the faint stars'
size measurement is biased by their noise), so it rejects the flats' size scale on data the
model describes; none of the bench's outside effects needs it.

``flux_shape`` (`flux_shape_test`), for effects whose identity is how they grow with flux
(``Effect.flux_signature``): the flux^2 term's amplitude must not move when a term linear in
peak is fitted beside it, a diffusion's (linear in peak) when a term in peak^2 is. The
faint-against-bright split could not tell a flux^2 template from a linear residual (5.5 +-
0.5 against 6.2 +- 0.07 on stars without BF: the groups' intercepts are common to both
halves).

``parity`` (`parity_test`): every catalogue effect that changes the stars is even under
reflection (the G15 redistribution of a symmetric star, a non-linearity, a blur), so each
predicts that the stars' odd moments (``SizeTable.skew_x``, ``skew_y``) do not change with
flux. The statistic is the chi2 of the two skewness slopes against peak (free intercepts per
group), null distribution chi-square with 2 degrees of freedom; when it is significant, no
even effect matches and every candidate with a size template is rejected by parity.

``cross`` (`cross_test`): every catalogue effect moves pixel boundaries along X and Y, so each
predicts that the stars' cross moment e2 (``SizeTable.cross``) does not change with flux
beyond BF's own share on an elliptical star; a diagonal effect contradicts them all.
"""

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.stats import chi2 as chi2_distribution

from ..least_squares import weighted_least_squares

__all__ = ["SIGNATURE_ALPHA", "TEMPLATE_TOLERANCE", "MEASURABLE", "CROSS_TOLERANCE",
           "CROSS_FLOOR", "signature_parts", "signature_test", "one_amplitude_chi2",
           "flux_competitors", "flux_shape_test", "contradiction", "parity_test", "cross_test",
           "describe_entry", "describe_rejection"]

#: p-value below which a dimension contradicts a candidate (3.3 sigma one-sided).
SIGNATURE_ALPHA = 1e-3
#: Relative accuracy of the first-order templates between the parts of each dimension (tau_d).
#: ``flux_shape``: how far the flux^2 term's amplitude may move beside a linear term (in
#: rendered second-order spots it moved 5 % at t = 40 and 31 +- 12 % at t = 10; on stars
#: without BF, a linear residual, 95 %).
#: A part of a dimension tests a candidate only where the candidate's amplitude is at least
#: this many of the part's errors (the part measures what the candidate predicts there).
MEASURABLE = 2.0
TEMPLATE_TOLERANCE = {"observable": 0.3, "axis": 0.1, "flux": 0.3, "position": 0.0,
                      "row": 0.0, "exposure_order": 0.0, "flux_shape": 0.15}


def _halves(values):
    """Boolean mask of the upper half of ``values`` (None when they do not vary)."""
    values = np.asarray(values, float)
    if np.ptp(values) == 0:
        return None
    upper = values > np.median(values)
    if upper.all() or not upper.any():
        upper = values >= np.median(values)
    return upper if upper.any() and not upper.all() else None


def signature_parts(problem, observables, *, flux=False):
    """The dimensions of the signature test and their parts.

    Parameters
    ----------
    problem : bfpsf.diagnosis.problem.Problem
        The stacked residual (its ``keys`` and ``slices``).
    observables : Observables
    flux : bool
        Also split faint from bright stars (default False: module docstring).

    Returns
    -------
    dict
        Dimension -> list of (part label, boolean row mask over the residual vector).
    """
    n_rows = problem.residual.size
    out = {"observable": []}
    for key in problem.keys:
        mask = np.zeros(n_rows, bool)
        mask[problem.slices[key]] = True
        out["observable"].append((key, mask))
    sizes = observables.sizes
    if sizes is None:
        return out
    start, n = problem.slices["sizes"].start, len(sizes)

    def size_rows(select_x, select_y):
        mask = np.zeros(n_rows, bool)
        mask[start:start + n] = select_x
        mask[start + n:start + 2 * n] = select_y
        return mask

    every, none = np.ones(n, bool), np.zeros(n, bool)
    out["axis"] = [("x", size_rows(every, none)), ("y", size_rows(none, every))]
    splits = {"flux": (sizes.peak_e, ("faint", "bright"))} if flux else {}
    if sizes.x_detector is not None:
        splits["position"] = (sizes.x_detector, ("near the amplifier", "far from it"))
    if sizes.y_detector is not None:
        splits["row"] = (sizes.y_detector, ("low rows", "high rows"))
    if sizes.exposure is not None:
        order = np.unique(sizes.exposure, return_inverse=True)[1]
        splits["exposure_order"] = (order, ("early", "late"))
    for dimension, (values, labels) in splits.items():
        upper = _halves(values)
        if upper is not None:
            out[dimension] = [(labels[0], size_rows(~upper, ~upper)),
                              (labels[1], size_rows(upper, upper))]
    return out


def signature_test(residual, sigma, base_design, effect_design, parts, *, alpha=SIGNATURE_ALPHA,
                   tolerance=TEMPLATE_TOLERANCE):
    """The signature test of one candidate, in every dimension its template reaches.

    Parameters
    ----------
    residual, sigma : ndarray (N,)
        Residual to explain (fixed effects already subtracted) and its errors.
    base_design : ndarray (N, m)
        Nuisances and the free effects already named.
    effect_design : ndarray (N, k)
        The candidate's template (`bfpsf.diagnosis.problem.effect_design`).
    parts : dict
        `signature_parts`.
    alpha : float
        The p-value threshold.
    tolerance : dict
        tau_d per dimension (module docstring); 0 for dimensions not in it.

    Returns
    -------
    dict
        Dimension -> {``parts`` (labels), ``amplitudes``, ``errors`` (per part and parameter),
        ``chi2``, ``dof``, ``p_value``, ``matches``}; dimensions where the template reaches
        fewer than two parts are left out.
    """
    k = effect_design.shape[1]
    # the candidate's own amplitude (its template whole): what it predicts in every part
    whole, _, _, _ = weighted_least_squares(residual, sigma,
                                            np.column_stack([base_design, effect_design]))
    predicted = np.abs(whole[-k:])
    out = {}
    for dimension, members in parts.items():
        labels, columns = [], []
        for label, mask in members:
            part = effect_design * mask[:, None]
            if np.any(part):
                labels.append(label)
                columns.append(part)
        if len(columns) < 2:
            continue
        covered = np.any([mask for _, mask in members], axis=0)
        rest = effect_design * (~covered)[:, None]
        blocks = [base_design] + ([rest] if np.any(rest) else []) + columns
        params, covariance, _, _ = weighted_least_squares(residual, sigma,
                                                          np.column_stack(blocks))
        first = params.size - len(columns) * k
        amplitudes = params[first:].reshape(len(columns), k)
        errors = np.sqrt(np.abs(np.diag(covariance)[first:])).reshape(len(columns), k)
        # a part can contradict the candidate only where it measures what the candidate
        # predicts there (`MEASURABLE` errors): a flats' non-linearity of 4e-4 predicts star
        # sizes 0.2 errors from nothing, and a new user's smear along X, in the X sizes,
        # rejected it "by axis" (p = 4e-22) while the same flats without the smear named it
        measurable = np.flatnonzero(np.any(predicted >= MEASURABLE * errors, axis=1))
        tau = tolerance.get(dimension, 0.0)
        # where some parts cannot measure the candidate, those that can must find it at the
        # amplitude it was fitted at: else its fit rests on parts that hold something else
        support = (_support(amplitudes, covariance[first:, first:], measurable, whole[-k:],
                            tau) if 0 < measurable.size < len(labels) else None)
        if measurable.size < 2 and support is None:
            continue
        statistic, dof = 0.0, (measurable.size - 1) * k
        for j in range(k if dof else 0):
            index = first + j + k * measurable
            statistic += one_amplitude_chi2(amplitudes[measurable, j],
                                            covariance[np.ix_(index, index)], tau)
        p_value = float(chi2_distribution.sf(statistic, dof)) if dof else 1.0
        out[dimension] = {"parts": labels, "amplitudes": amplitudes.tolist(),
                          "errors": errors.tolist(), "chi2": statistic, "dof": dof,
                          "p_value": p_value}
        if support is not None:
            out[dimension].update(support=support, chi2=statistic + support["chi2"],
                                  dof=dof + k, p_value=min(p_value, support["p_value"]))
            out[dimension]["measured_in"] = [labels[index] for index in measurable]
        out[dimension]["matches"] = bool(out[dimension]["p_value"] >= alpha)
    return out


def _support(amplitudes, covariance, measurable, fitted, tau):
    """The parts that measure a candidate (``measurable``) against the amplitude its whole
    template was fitted at (``fitted``, one per parameter): their common amplitude m +- s
    (generalised least squares) and min over eta of ((m - fitted e^eta) / s)^2 +
    eta^2 / tau^2 summed over the parameters, chi-square with k degrees of freedom."""
    k = len(fitted)
    values, errors, statistic = [], [], 0.0
    for j in range(k):
        index = j + k * measurable
        inverse = np.linalg.pinv(covariance[np.ix_(index, index)])
        ones = np.ones(index.size)
        error = float(1.0 / np.sqrt(ones @ inverse @ ones))
        value = float(error ** 2 * (ones @ inverse @ amplitudes[measurable, j]))
        # eta lies between 0 and log(m / fitted) (-30 for m of the other sign)
        distance = float(np.log(value / fitted[j])) if value * fitted[j] > 0 else -30.0

        def penalised(eta):
            return (((value - fitted[j] * np.exp(eta)) / error) ** 2
                    + (eta / tau if tau > 0 else 0.0) ** 2)

        statistic += penalised(0.0) if tau <= 0 or distance == 0 else min(penalised(0.0), float(
            minimize_scalar(penalised, bounds=sorted((0.0, distance)), method="bounded",
                            options={"xatol": 1e-6}).fun))
        values.append(value)
        errors.append(error)
    return {"amplitude": values, "error": errors, "fitted": [float(v) for v in fitted],
            "chi2": float(statistic), "p_value": float(chi2_distribution.sf(statistic, k))}


def _whitener(covariance):
    """W with W C W^T = 1 on the range of C (a pseudo-inverse square root)."""
    values, vectors = np.linalg.eigh(covariance)
    keep = values > values.max() * 1e-12
    return (vectors[:, keep] / np.sqrt(values[keep])).T


def one_amplitude_chi2(values, covariance, tau):
    """chi2 of the hypothesis that the parts' amplitudes ``values`` (covariance ``covariance``)
    are one amplitude a, each part's template accurate to a factor exp(eta_i), with the eta_i
    independent N(0, tau^2).

    The tolerance is multiplicative (log-normal), as a template's accuracy is: a part may be
    30 % above or below the others, not of the other sign or nil while they are large. (A
    Gaussian tolerance tau |a| on the difference let a part measured at 0 +- 0.002 pass beside
    one at 0.12 +- 0.001 at 3.3 sigma: stars without brighter-fatter and linear flats named a
    gain non-linearity.) The statistic is the minimum over a and the eta_i of
    (values - a exp(eta))^T C^-1 (values - a exp(eta)) + sum(eta^2) / tau^2; for tau = 0 the
    generalised-least-squares chi2 about the weighted mean, exact chi-square with m - 1
    degrees of freedom, and asymptotically so for tau > 0.
    """
    values = np.asarray(values, float)
    whiten = _whitener(np.asarray(covariance, float))
    white = whiten @ values
    design = whiten @ np.ones(values.size)
    mean = float(design @ white / (design @ design))
    chi2 = float(np.sum((white - mean * design) ** 2))
    if tau <= 0 or chi2 == 0.0:
        return chi2

    def residual(theta):
        return np.concatenate([white - whiten @ (theta[0] * np.exp(theta[1:])),
                               theta[1:] / tau])

    best = chi2 + 0.0
    scale = max(np.abs(values).max(), 1e-300)
    for start in {mean, *values.tolist()}:
        if start == 0.0:
            continue
        fit = least_squares(residual, np.concatenate([[start], np.zeros(values.size)]),
                            x_scale=np.concatenate([[scale], np.full(values.size, tau)]))
        best = min(best, float(np.sum(fit.fun ** 2)))
    return best


def parity_test(sizes, *, alpha=SIGNATURE_ALPHA):
    """The stars' odd moments against flux (the ``parity`` dimension), or None without them.

    Returns
    -------
    dict or None
        As a `signature_test` entry: ``parts`` ("skew x", "skew y"), ``amplitudes`` (slopes,
        per 1e5 e- of peak), ``errors``, ``chi2``, ``dof`` (2), ``p_value``, ``matches``.
    """
    if sizes is None or sizes.skew_x is None or sizes.skew_y is None:
        return None
    slopes, errors, statistic = [], [], 0.0
    for values, sigma in ((sizes.skew_x, sizes.skew_x_err), (sizes.skew_y, sizes.skew_y_err)):
        slope, error = sizes.peak_slope(values, sigma)[:2]
        slopes.append([slope])
        errors.append([error])
        statistic += (slope / error) ** 2
    p_value = float(chi2_distribution.sf(statistic, 2))
    return {"parts": ["skew x", "skew y"], "amplitudes": slopes, "errors": errors,
            "chi2": float(statistic), "dof": 2, "p_value": p_value,
            "matches": bool(p_value >= alpha)}


#: Change of the stars' e2 with flux that brighter-fatter itself may give, per 1e5 e- of
#: peak, relative to their mean e2: BF grows a star's sizes by a few % per 1e5 e- and keeps
#: its ellipticity to that order (0.1: twice the largest size slope).
CROSS_TOLERANCE = 0.1
#: Least error of the e2 slope, per 1e5 e- of peak: a new user's BF-only SiliconSensor stars
#: (double Gaussian, 8 exposures of 36) gave -0.0039 +- 0.0006 and +0.0009 +- 0.0007 in the
#: two halves of the night (binned e2 scatters 2x its pooled errors there: the sub-pixel
#: phase), 0.0004 +- 0.0012 from the stars one by one; the diagonal smear it was tried
#: against gave 0.035.
CROSS_FLOOR = 0.002


def cross_test(sizes, *, alpha=SIGNATURE_ALPHA):
    """The stars' cross moment e2 against flux (the ``cross`` dimension), or None without it.

    Every catalogue effect moves the boundaries of a pixel along X and Y and leaves a star
    symmetric about X or Y so (its e2 stays 0); on an elliptical star BF changes e2 in
    proportion to it (`CROSS_TOLERANCE` of the mean e2 per 1e5 e-, added to the slope's
    error, with `CROSS_FLOOR`; the slope's own error is scaled by the fit's chi2 per degree of
    freedom when above 1). A diagonal effect (a charge-dependent smear along x = y, which a
    new user's stars carried: e2 0 -> 0.012) changes e2 with flux and contradicts every
    candidate that changes sizes; the statistic is the squared slope over its variance,
    chi-square with 1 degree of freedom.

    Returns
    -------
    dict or None
        As a `signature_test` entry: ``parts`` ("e2"), ``amplitudes`` (slope per 1e5 e- of
        peak), ``errors``, ``chi2``, ``dof`` (1), ``p_value``, ``matches``.
    """
    if sizes is None or sizes.cross is None:
        return None
    slope, slope_err, chi2, dof = sizes.peak_slope(sizes.cross, sizes.cross_err)
    # the slope's error scaled by the fit's own scatter (a linear e2 change is in the fit,
    # so it does not inflate it), with BF's own share and the floor
    statistical = slope_err * np.sqrt(max(chi2 / dof, 1.0))
    error = float(np.sqrt(statistical ** 2 + (CROSS_TOLERANCE * np.mean(sizes.cross)) ** 2
                          + CROSS_FLOOR ** 2))
    statistic = float((slope / error) ** 2)
    p_value = float(chi2_distribution.sf(statistic, 1))
    return {"parts": ["e2"], "amplitudes": [[slope]], "errors": [[error]],
            "chi2": statistic, "dof": 1, "p_value": p_value, "matches": bool(p_value >= alpha)}


def flux_competitors(problem, observables):
    """The competitors of the ``flux_shape`` dimension (`Effect.flux_signature`): a size
    change linear and one quadratic in peak on both axes, as rows of the stacked residual
    (zero without sizes)."""
    out = {kind: np.zeros(problem.residual.size) for kind in ("linear", "quadratic")}
    if "sizes" in problem.slices:
        scaled = np.tile(observables.sizes.peak_e / 1e5, 2)
        out["linear"][problem.slices["sizes"]] = scaled
        out["quadratic"][problem.slices["sizes"]] = scaled**2
    return out


def flux_shape_test(residual, sigma, base_design, effect_design, competitor, *,
                    kind="linear", alpha=SIGNATURE_ALPHA,
                    tolerance=TEMPLATE_TOLERANCE["flux_shape"]):
    """The ``flux_shape`` dimension of an effect whose identity is how it grows with flux
    (``Effect.flux_signature``).

    Its amplitude is fitted twice: as the loop fits it, and beside a ``competitor`` term of
    another flux shape (``kind``): for the flux^2 term, a size change linear in peak (the
    shape of a brighter-fatter scale error); for an effect linear in peak, one in peak^2.
    When the effect is what the residual holds, the competitor takes nothing and the two
    agree; a residual linear in flux (stars with no BF against flats with BF: the flux^2 term
    had been named at t = 6.3 there) moves the flux^2 term, one that rises faster than
    linearly (a halo of the brightest stars) moves the linear one. The
    statistic is Hausman's, d^T (C_1 - C_0 + (tau a_0)^2 I)^-1 d with d = a_0 - a_1, tau
    `TEMPLATE_TOLERANCE` ['flux_shape'], chi-square with k degrees of freedom (the amplitude with
    the linear term is the less precise one, so C_1 - C_0 is the variance of d).

    Returns
    -------
    dict
        As a `signature_test` entry: ``parts`` ("alone", "beside a linear term" or
        "beside a quadratic term"),
        ``amplitudes``, ``errors``, ``chi2``, ``dof``, ``p_value``, ``matches``.
    """
    k = effect_design.shape[1]
    own = slice(base_design.shape[1], base_design.shape[1] + k)
    fits = [weighted_least_squares(residual, sigma, np.column_stack(blocks))[:2]
            for blocks in ([base_design, effect_design],
                           [base_design, effect_design, competitor[:, None]])]
    (alone, alone_cov), (beside, beside_cov) = [(params[own], covariance[own, own])
                                                for params, covariance in fits]
    difference = alone - beside
    variance = beside_cov - alone_cov + np.diag((tolerance * alone) ** 2)
    statistic = float(difference @ np.linalg.pinv(variance) @ difference)
    p_value = float(chi2_distribution.sf(statistic, k))
    return {"parts": ["alone", f"beside a {kind} term"],
            "amplitudes": [alone.tolist(), beside.tolist()],
            "errors": [np.sqrt(np.abs(np.diag(alone_cov))).tolist(),
                       np.sqrt(np.abs(np.diag(beside_cov))).tolist()],
            "chi2": statistic, "dof": k, "p_value": p_value, "matches": bool(p_value >= alpha)}


def contradiction(test):
    """The dimension of a `signature_test` with the smallest p-value among those that do not
    match, or None when the candidate matches everywhere."""
    failed = {name: entry for name, entry in test.items() if not entry["matches"]}
    if not failed:
        return None
    return min(failed, key=lambda name: failed[name]["p_value"])


def describe_rejection(name, entry):
    """One line of a rejected candidate (`bfpsf.diagnosis.loop.DiagnosisResult.rejected`)."""
    head = f"{name} (Delta BIC {entry['delta_bic']:.0f})"
    if entry["contradicted_by"] == "bounds":
        values = ", ".join(f"{value:.3g}" for value in entry["values"])
        ranges = ", ".join(str(tuple(bound)) for bound in entry["bounds"])
        return f"{head}: its fit {values} is outside its physical range {ranges}"
    # what the parts read (the first parameter), for a person to judge
    test = (entry.get("signature") or {}).get(entry["contradicted_by"]) or {}
    parts = "".join(f"; {label} {values[0]:+.3g} +- {errors[0]:.2g}" for label, values, errors
                    in zip(test.get("parts", ()), test.get("amplitudes", ()),
                           test.get("errors", ())))
    return (f"{head}: its signature is contradicted by {entry['contradicted_by']} "
            f"(p = {entry['p_value']:.1e}{parts})")


def describe_entry(entry):
    """One line of an unexplained residual (`bfpsf.diagnosis.unexplained.describe_unexplained`)."""
    words = [entry["observable"]]
    if entry.get("axis"):
        words.append(f"along {entry['axis']}")
    words.append(f"{entry['significance']:.1f} sigma")
    if entry.get("parity"):
        skew = entry.get("skew")
        lean = (f": its skewness changes with flux, {skew['slope_per_1e5']:+.4f} +- "
                f"{skew['error']:.4f} per 1e5 e-" if skew else "")
        if entry.get("odd_direction"):
            lean += f"; with the other axis's, {entry['odd_direction']}"
        words.append(f"{entry['parity']} parity" + (f" (centroid- or skew-like{lean})"
                                                    if entry["parity"] == "odd" else ""))
    if entry.get("sign"):
        words.append(f"{entry['sign']} with flux")
    dependence = entry.get("flux_dependence") or {}
    if dependence.get("kind"):
        words.append(f"{dependence['kind']} in flux")
    if dependence.get("faint_end"):
        words.append("with a 1/flux part ("
                     + ("larger" if dependence["inverse_1e5"] > 0 else "smaller")
                     + " on the faint stars)")
    for key in ("position_dependence", "row_dependence", "exposure_dependence"):
        kind = (entry.get(key) or {}).get("kind")
        if kind and kind != "none":
            words.append(kind)
    if entry.get("flats"):
        words.append(entry["flats"])
    part = entry.get("scale_part")
    if part:
        words.append(f"within the flats' BF amplitude error (the size scale on this axis "
                     f"{part['value']:+.2f} +- {part['error']:.2f}, prior {part['prior']:.2f}: "
                     "it may be the calibration, not a second effect)")
    return ", ".join(words)
