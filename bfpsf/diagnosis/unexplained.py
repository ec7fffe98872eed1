"""What the loop leaves, described without a model, and whether a run may report success.

`describe_unexplained` gives each significant residual's signature (axis, parity, sign, flux,
position and exposure-order dependence, flats against stars); `verdict` is never a success
while something is left or the stars' residual chi2 per pixel is far above its null
expectation (issue 22). Both are used by `bfpsf.diagnosis.loop`.
"""

import numpy as np

from ..least_squares import weighted_least_squares
from ..measure.slopes import fit_bf_slope
from .nuisances import GLOBAL_NUISANCES, SCALE
from .position_split import SPLIT_NSIGMA
from .signature import SIGNATURE_ALPHA, TEMPLATE_TOLERANCE, cross_test

__all__ = ["describe_unexplained", "verdict", "with_scale_parts", "hiding_room",
           "HIDING_ROOM_PERCENT", "UNEXPLAINED_NSIGMA",
           "STAR_CHI2_FACTOR", "POSITION_VERDICT_NSIGMA"]


#: Percent of the raw slope an undeclared BF-like effect may hide in the flats' errors before
#: the verdict says so (`hiding_room`).
HIDING_ROOM_PERCENT = 30.0

#: A dependence of every star's BF slope on the column or the row beyond this many errors
#: (`bfpsf.diagnosis.position_split`), which no term of the model follows, fails the verdict
POSITION_VERDICT_NSIGMA = 5.0

#: The stacked star residual's chi2 per pixel is "far above" its null expectation beyond this
#: factor (the null expectation is 1 for the noise model of `stacked_star_residual`; a
#: measured null, ``meta['star_chi2_null']``, replaces it).
STAR_CHI2_FACTOR = 10.0


def verdict(unexplained, nuisance, star=None, null_expectation=1.0, position_split=None,
            empirical=None, unapplied=None):
    """Whether a run explains its data: never a success while something is left.

    Parameters
    ----------
    unexplained : list of dict
        `describe_unexplained`.
    nuisance : dict
        `DiagnosisResult.nuisance` (the size scale and its signature).
    star : dict, optional
        The stacked star residual (`stacked_star_residual`), with ``chi2_per_pixel``.
    null_expectation : float
        Its chi2 per pixel on data the model describes (1 for the noise model).
    position_split : dict, optional
        The test of every star's BF slope against the column and the row
        (`bfpsf.diagnosis.position_split.star_slope_split`): a dependence beyond
        `POSITION_VERDICT_NSIGMA` that no validated term of the model follows (``empirical``'s
        position or row term) is left, though the slope over the field is explained (a new
        user's PSF varying over the field, one P0 per exposure: the X slope rose with the
        column at 13.2 sigma, and the run said "explained").
    empirical : dict, optional
        The EMPIRICAL term (`DiagnosisResult.empirical`).
    unapplied : dict, optional
        Named effects no refined calibration applies, and why
        (`bfpsf.diagnosis.refine.unapplied`): the loop's model explains what the products
        leave (a new user's star-only non-linearity, 4 times the size, named
        flux_diffusion, "explained", and held-out P(F) left +45 % of the raw X slope).

    Returns
    -------
    dict
        ``success``, ``reasons`` (list of str), ``star_residual_chi2_per_pixel``,
        ``null_expectation``, ``limit`` (`STAR_CHI2_FACTOR` times the expectation),
        ``caveats`` (`hiding_room`).
    """
    reasons = [f"unexplained {entry['observable']}"
               + (f" {entry['axis']}" if entry.get("axis") else "")
               + f" ({entry['significance']:.1f} sigma)" for entry in unexplained]
    for entry in GLOBAL_NUISANCES:
        against = (nuisance.get(entry.name) or {}).get("contradicted_by")
        if against:
            reasons.append(f"the {entry.what} is contradicted by {against}")
    for name, why in (unapplied or {}).items():
        reasons.append(f"{name} is named, but no refined calibration applies it ({why}): "
                       "bfpsf psf, photometry and slope --psf leave what it explains")
    parity = ((nuisance.get(SCALE.name) or {}).get("signature") or {}).get("parity")
    if parity and not parity["matches"]:
        reasons.append(f"the stars' odd moments change with flux (parity p = "
                       f"{parity['p_value']:.1e}): an odd effect, a trail or a centroid shift, "
                       "that no term holds")
    validation = (empirical or {}).get("validation") or {}
    for along, term in (("column", "position_term"), ("row", "row_term")):
        worst = max(((values["significance"], axis) for axis, values
                     in ((position_split or {}).get(along) or {}).items()), default=None)
        if worst and worst[0] > POSITION_VERDICT_NSIGMA and not (
                validation.get(term) and validation.get("validated")):
            reasons.append(f"the stars' {worst[1].upper()} BF slope depends on the {along} "
                           f"({worst[0]:.1f} sigma) and no term of the model does (a PSF "
                           "varying over the field: bfpsf psf --grid)")
    chi2 = None if star is None else float(star["chi2_per_pixel"])
    limit = STAR_CHI2_FACTOR * float(null_expectation)
    if chi2 is not None and chi2 > limit:
        reasons.append(f"star residual chi2 per pixel {chi2:.1f}, null expectation "
                       f"{null_expectation:.1f} (limit {limit:.1f})")
    return {"success": not reasons, "reasons": reasons, "star_residual_chi2_per_pixel": chi2,
            "null_expectation": float(null_expectation), "limit": limit,
            "caveats": hiding_room(nuisance)}


def hiding_room(nuisance):
    """What an undeclared effect shaped like BF could hide in the flats' errors, as lines.

    The size scale and the X / Y split are nuisances within the flats' priors (3 sigma
    allowed): an effect that grows with flux like BF, isotropic or on one axis, with no other
    signature (position, row, exposure, parity, e2), is taken by them and cannot be named.
    An isotropic one up to 3 times the scale's prior, a one-axis one up to 3 times half the
    split's (a split d moves each axis by about d / 2), in percent of the raw slope; said
    when either exceeds `HIDING_ROOM_PERCENT` or the stars took either beyond 1 of its prior
    (a new user's star-only non-linearity took the scale to +0.13 +- 0.05, 1.5 of its prior,
    beside a room of 25 %, without a word). A new user's 20 ITL flats of 130^2 (priors
    0.64 and 1.31) took a Y smear of +51 % of the Y slope as a split of -0.14 and read
    "explained"; the refined calibration, with N shifts 1.58 times the BF-only set's, still
    fitted the held-out stars (Y -0.5 % of raw)."""
    room, used, pulled = {}, [], False
    for global_nuisance in GLOBAL_NUISANCES:
        entry = nuisance.get(global_nuisance.name) or {}
        if entry.get("prior") and not entry.get("contradicted_by"):
            room[global_nuisance.room_kind] = (300.0 * global_nuisance.room_share
                                               * float(entry["prior"]))
            used.append(f"the {global_nuisance.short} {entry['value']:+.2f} +- "
                        f"{entry['error']:.2f}, {abs(entry['value']) / entry['prior']:.1f} of "
                        "its prior")
            pulled |= abs(entry["value"]) > entry["prior"]
    if not room or (max(room.values()) <= HIDING_ROOM_PERCENT and not pulled):
        return []
    return ["the flats' errors leave room for an undeclared effect that grows with flux like "
            "BF and has no other signature: "
            + ", ".join(f"{kind} up to {value:.0f} %" for kind, value in room.items())
            + " of the raw slope, it would be taken as the flats' BF scale or X / Y split and "
              "not reported (more or larger flat pairs narrow this); the stars took "
            + " and ".join(used) + "; the refined calibration still fits the stars"]


def with_scale_parts(unexplained, nuisance):
    """The unexplained size entries with the part of the size scale on their axis, where the
    scale was contradicted and dropped.

    The flats' BF amplitude is uncertain (the scale's prior); when something else acts on one
    axis, the scale is contradicted by ``axis`` and dropped, and the flats' own error comes
    back as an unexplained residual on the other axis (a new user's ITL stars, a smear along
    Y: "unexplained sizes x, 7.2 sigma" beside the real Y, the scale's X part +1.21 +- 0.11
    within 3 of its prior's 0.56). The entry on the axis whose scale part is the smaller (the
    other holds the effect that contradicted the scale), when that part lies within 3 of the
    prior's sigma, gets ``scale_part`` {value, error, prior}, said by `describe_entry` (an
    X-only smear, whose Y part is near 0, leaves its X entry as it is)."""
    scale = nuisance.get(SCALE.name) or {}
    test = (scale.get("signature") or {}).get("axis")
    if not scale.get("contradicted_by") or not test or not scale.get("prior"):
        return unexplained
    parts = {label: (amplitude[0], error[0]) for label, amplitude, error in
             zip(test["parts"], test["amplitudes"], test["errors"])}
    smaller = min(parts, key=lambda label: abs(parts[label][0]))
    out = []
    for entry in unexplained:
        # a calibration error is the same at every position and in every exposure: an entry
        # that changes with them is not the scale's (a new user's night-growing smear read
        # "rising over the night" and "it may be the calibration" in one line)
        varies = any((entry.get(key) or {}).get("kind", "none") != "none" for key in
                     ("position_dependence", "row_dependence", "exposure_dependence"))
        part = (parts[smaller] if entry["observable"] == "sizes" and entry.get("axis") == smaller
                and not varies else None)
        if part is not None and abs(part[0]) <= 3.0 * scale["prior"]:
            entry = dict(entry, scale_part={"value": float(part[0]), "error": float(part[1]),
                                            "prior": float(scale["prior"])})
        out.append(entry)
    return out


#: Significance (sigma) above which a residual is reported as unexplained.
UNEXPLAINED_NSIGMA = 3.0


def _parity(star, axis):
    """'even' or 'odd': the larger part of the stacked star residual under reflection along
    ``axis`` (x: columns mirrored, y: rows mirrored); None without a stacked residual."""
    if not star:
        return None
    image = np.asarray(star["image"], float)
    mirrored = image[:, ::-1] if axis == "x" else image[::-1, :]
    even = 0.5 * (image + mirrored)
    odd = 0.5 * (image - mirrored)
    return "even" if np.sum(even ** 2) >= np.sum(odd ** 2) else "odd"


def _flux_dependence(peak, residual, sigma, group, inverse=True):
    """How a residual grows with peak: 'constant', 'linear' or 'quadratic' (the highest power
    significant at 3 sigma in a fit with per-group intercepts: the square term in the fit with
    both, the linear one in a fit of it alone, as the slope that reported the residual; in
    the fit with both, the two are correlated and a new user's rising residual read
    "rising with flux, constant in flux"), with the coefficients of the fit with both; and
    ``faint_end``: whether a term in 1 / peak is significant beside the linear one (a change
    held by the faint stars, as of a fixed number of charge traps: a new user's deferred
    charge, which falls with flux, read "rising, linear" from the slope alone; tested for the
    stars' sizes, ``inverse``)."""
    x = np.asarray(peak, float) / 1e5
    groups = [(group == g).astype(float) for g in np.unique(group)]
    params, covariance, _, _ = weighted_least_squares(residual, sigma,
                                                      np.column_stack([x, x ** 2] + groups))
    linear, linear_covariance, _, _ = weighted_least_squares(residual, sigma,
                                                             np.column_stack([x] + groups))
    reciprocal, reciprocal_covariance, _, _ = weighted_least_squares(
        residual, sigma, np.column_stack([x, 1.0 / x] + groups))
    quadratic = abs(params[1]) > UNEXPLAINED_NSIGMA * np.sqrt(abs(covariance[1, 1]))
    slope = abs(linear[0]) > UNEXPLAINED_NSIGMA * np.sqrt(abs(linear_covariance[0, 0]))
    faint_end = inverse and (abs(reciprocal[1]) > UNEXPLAINED_NSIGMA
                             * np.sqrt(abs(reciprocal_covariance[1, 1])))
    kind = "quadratic" if quadratic else "linear" if slope else "constant"
    return {"kind": kind, "per_1e5": float(params[0]), "per_1e10": float(params[1]),
            "faint_end": bool(faint_end), "inverse_1e5": float(reciprocal[1])}


def _each_star(dependence, observables, along, axis, labels):
    """A binned ``dependence`` (`_dependences`, or None) that reads none, replaced by the test
    of every star (`bfpsf.diagnosis.position_split`) where that finds one beyond its
    `SPLIT_NSIGMA` along ``along`` on ``axis``: the bins' mean positions span a fraction of
    the stars' (a new user's 45 stars per exposure in 2 x 1 cells read 2.9 sigma beside the
    stars' 10.8). Its ``per_1e5_per_unit`` is per 1000 pixels, as the binned one's."""
    star = ((observables.meta.get("position_split") or {}).get(along) or {}).get(axis)
    if star is None or star["significance"] <= SPLIT_NSIGMA or (
            dependence is not None and dependence["kind"] != "none"):
        return dependence
    per_1000 = 1000.0 / star["span"]
    return {"kind": labels[int(star["change"] < 0)], "per_1e5_per_unit":
            star["change"] * per_1000, "error": star["change_err"] * per_1000,
            "significance": float(star["significance"]), "source": "each star"}


def _odd_parity(sizes, axis):
    """'odd' when the stars' skewness along ``axis`` changes with flux at more than
    `UNEXPLAINED_NSIGMA`, else 'even'; None without skewness columns. With it, the skewness's
    slope per 1e5 e- of peak and its error, or None. (Its sign is not the way the light
    moves: a trail toward +x of a fixed fraction gives a positive skewness under the adaptive
    weight, one whose fraction grows with the pixel's charge, moving the core more than the
    wings, a negative one: -0.0016 for a Kolmogorov star of 4.5e4 e- peak passing 0.05 Q /
    1e5 e- to its (+1, +1) neighbour.)"""
    values = getattr(sizes, f"skew_{axis}")
    if values is None:
        return None, None
    slope, error = sizes.peak_slope(values, getattr(sizes, f"skew_{axis}_err"))[:2]
    if abs(slope) <= UNEXPLAINED_NSIGMA * error:
        return "even", None
    return "odd", {"slope_per_1e5": slope, "error": error}


def _skewness_entries(sizes, entries):
    """The stars' skewness changing with flux on an axis whose size residual is not
    significant (an odd effect that leaves the sizes alone, a centroid shift or a trail: a
    new user's serial charge-transfer trail contradicted every size candidate by parity and
    the report named nothing), with its dependence on the column, the row and the exposure."""
    out = []
    if sizes is None:
        return out
    for axis in "xy":
        if any(entry["observable"] == "sizes" and entry["axis"] == axis for entry in entries):
            continue
        parity, skew = _odd_parity(sizes, axis)
        if parity != "odd":
            continue
        values = np.asarray(getattr(sizes, f"skew_{axis}"), float)
        errors = np.asarray(getattr(sizes, f"skew_{axis}_err"), float)
        out.append({"observable": "skewness", "axis": axis, "parity": "odd", "skew": skew,
                    "sign": "rising" if skew["slope_per_1e5"] > 0 else "falling",
                    "flux_dependence": None,
                    "significance": float(abs(skew["slope_per_1e5"]) / skew["error"]),
                    **_dependences(sizes, values, errors)})
    return out


#: The detector directions of `_dependences`: key, `SizeTable` column, words, split's name.
_ALONG = (("position_dependence", "x_detector", "with distance from the amplifier", "column"),
          ("row_dependence", "y_detector", "with the row (parallel transfers)", "row"))


def _dependences(sizes, values, errors):
    """A residual's ``position_dependence``, ``row_dependence`` and ``exposure_dependence``
    (None where the stars do not span the direction), fitted together: the coefficients of
    peak x (column - mean) / 1000, peak x (row - mean) / 1000 and peak x (exposure order -
    mean) beside a common slope in peak and per-group intercepts, each with its error,
    significance and kind (``none`` below `UNEXPLAINED_NSIGMA`). Fitted one at a time, a
    smear growing over a night of 4 exposures had read "rising with distance from the
    amplifier" too (3.0 sigma; every star's split 0.3)."""
    directions = [(key, np.asarray(getattr(sizes, column), float), 1000.0,
                   (f"rising {what}", f"falling {what}"))
                  for key, column, what, _ in _ALONG if getattr(sizes, column) is not None]
    if sizes.exposure is not None:
        directions.append(("exposure_dependence",
                           np.unique(sizes.exposure, return_inverse=True)[1].astype(float),
                           1.0, ("rising over the night", "falling over the night")))
    directions = [entry for entry in directions if np.ptp(entry[1]) > 0]
    out = {key: None for key, _, _, _ in _ALONG}
    out["exposure_dependence"] = None
    if not directions:
        return out
    x = sizes.peak_e / 1e5
    columns = [x * (along - np.mean(along)) / scale for _, along, scale, _ in directions]
    params, covariance, _, _ = weighted_least_squares(
        values, errors, np.column_stack([x, *columns, sizes.intercept_design()]))
    for index, (key, _, _, labels) in enumerate(directions, start=1):
        error = float(np.sqrt(abs(covariance[index, index])))
        significance = abs(params[index]) / error if error > 0 else 0.0
        kind = "none" if significance <= UNEXPLAINED_NSIGMA else labels[int(params[index] < 0)]
        out[key] = {"kind": kind, "per_1e5_per_unit": float(params[index]), "error": error,
                    "significance": float(significance)}
    return out


def _odd_direction(entries):
    """The odd size residuals of X and Y together: when both skewness slopes have one sign
    and are within a factor `DIAGONAL_RATIO` of each other, the odd part lies along the
    x = y diagonal (opposite signs: x = -y), said on both entries (``odd_direction``): a new
    user's trail toward (+1, +1) was read as two odd axes."""
    skews = {entry["axis"]: entry["skew"] for entry in entries
             if entry["observable"] in ("sizes", "skewness") and entry.get("skew")}
    if set(skews) != {"x", "y"}:
        return
    x, y = skews["x"]["slope_per_1e5"], skews["y"]["slope_per_1e5"]
    if 1 / DIAGONAL_RATIO <= abs(x / y) <= DIAGONAL_RATIO:
        direction = "along the x = y diagonal" if x * y > 0 else "along the x = -y diagonal"
        for entry in entries:
            if entry["observable"] in ("sizes", "skewness") and entry.get("skew"):
                entry["odd_direction"] = direction


#: `_odd_direction`: the largest ratio of the X and Y skewness slopes of a diagonal odd part.
DIAGONAL_RATIO = 3.0


def _prediction_slope_variance(prediction, block, peak_e, errors, group, axis_tolerance):
    """Variance of a size residual's slope that the model's fitted part carries on held-out
    data, where its parameters come from the fit part: their covariance, and the templates'
    accuracy between the axes (``axis_tolerance``, `bfpsf.diagnosis.signature.TEMPLATE_TOLERANCE`,
    of the slope the fitted part adds on this axis). A new user's BF-only seed (the flats' scale -0.46 +- 0.04, so the
    model moved each axis by some 80 % of raw) read "unexplained sizes y 4.2 sigma" against
    the held-out noise alone."""
    if prediction is None:
        return 0.0
    design, covariance, values = prediction
    if design.shape[1] == 0:
        return 0.0
    gradient = np.array([fit_bf_slope(peak_e, design[block, j], size_err=errors, group=group,
                                      scale_errors=False, clip_nsigma=None).slope
                         for j in range(design.shape[1])])
    template = axis_tolerance * float(gradient @ values)
    return float(max(gradient @ covariance @ gradient, 0.0)) + template ** 2


def describe_unexplained(problem, observables, model, prediction=None):
    """Significant residuals left by a model, with their signature.

    Sizes, per axis: the slope of the size residual against peak (per-group intercepts) at
    more than `UNEXPLAINED_NSIGMA` of its error; its sign (``rising`` or ``falling`` with
    flux); its parity: ``odd`` when the stars' skewness along the axis changes with flux
    (``SizeTable.skew_x``, ``skew_y``), else that of the stacked star residual under
    reflection along the axis; its flux dependence the highest significant power of peak;
    its ``position_dependence`` (the slope's change with the distance from the amplifier,
    per 1000 pixels, with ``SizeTable.x_detector``), ``row_dependence`` (the same along the
    rows, with ``SizeTable.y_detector``) and ``exposure_dependence`` (per exposure
    of the night, with ``SizeTable.exposure``), each with its significance and a kind
    (``none`` below `UNEXPLAINED_NSIGMA`); ``flats`` says whether a flat observable is
    unexplained too (``stars; the flats' linearity too``, naming them: the same effect or
    another) or not (``stars only``). Other observables: a chi2
    per point whose excess over its degrees of freedom is significant, (chi2 - N) / sqrt(2 N).

    Parameters
    ----------
    problem, observables, model
        The residual problem (`build_problem`), its observables and the model of its
        residual.
    prediction : (ndarray, ndarray, ndarray), optional
        Design, covariance and values of the model's parameters fitted elsewhere (held-out
        data: `bfpsf.diagnosis.heldout`): a size slope's error then includes what they carry
        (`_prediction_slope_variance`).

    Returns
    -------
    list of dict
        {observable, axis, parity, flux_dependence, significance (sigma)} and, for sizes,
        sign, slope, slope_err (the noise's and the prediction's), position_dependence,
        row_dependence, exposure_dependence, flats and, where the parity is odd, skew (the
        skewness's slope with flux and the way the light leans: `_odd_parity`).
    """
    residual = problem.residual - model
    out = []
    for key in problem.keys:
        block = problem.slices[key]
        part, sigma = residual[block], problem.sigma[block]
        if key == "sizes":
            sizes = observables.sizes
            n = len(sizes)
            for index, axis in enumerate("xy"):
                values, errors = part[index * n:(index + 1) * n], sigma[index * n:(index + 1) * n]
                fit = fit_bf_slope(sizes.peak_e, values, size_err=errors, group=sizes.intercepts,
                                   scale_errors=False, clip_nsigma=None)
                rows = np.arange(block.start, block.stop)[index * n:(index + 1) * n]
                slope_err = np.hypot(fit.slope_err, np.sqrt(_prediction_slope_variance(
                    prediction, rows, sizes.peak_e, errors, sizes.intercepts,
                    TEMPLATE_TOLERANCE["axis"])))
                significance = abs(fit.slope) / slope_err
                if significance > UNEXPLAINED_NSIGMA:
                    parity, skew = _odd_parity(sizes, axis)
                    if parity is None:
                        parity = _parity(observables.meta.get("star_residual"), axis)
                    entry = {"observable": "sizes", "axis": axis, "parity": parity,
                             "skew": skew,
                             "sign": "rising" if fit.slope > 0 else "falling",
                             "flux_dependence": _flux_dependence(sizes.peak_e, values, errors,
                                                                 sizes.intercepts),
                             "significance": float(significance),
                             "slope": float(fit.slope), "slope_err": float(slope_err),
                             **_dependences(sizes, values, errors)}
                    for key, _, what, name in _ALONG:
                        entry[key] = _each_star(entry[key], observables, name, axis,
                                                (f"rising {what}", f"falling {what}"))
                    out.append(entry)
            continue
        n_points = part.size
        chi2 = float(np.sum((part / sigma) ** 2))
        significance = (chi2 - n_points) / np.sqrt(2.0 * n_points)
        if significance > UNEXPLAINED_NSIGMA:
            mean = {"linearity": getattr(observables.linearity, "mean_e", None),
                    "ptc": getattr(observables.ptc, "mean_e", None)}.get(key)
            dependence = None
            if mean is not None and mean.size > 3:
                dependence = _flux_dependence(mean, part, sigma, np.zeros(mean.size, int),
                                              inverse=False)
            out.append({"observable": key, "axis": None, "parity": None,
                        "flux_dependence": dependence, "significance": float(significance)})
    out += _skewness_entries(observables.sizes, out)
    cross = cross_test(observables.sizes, alpha=SIGNATURE_ALPHA)
    if cross is not None:
        # the stars' e2 against flux: no catalogue effect changes it (`cross_test`)
        slope, error = cross["amplitudes"][0][0], cross["errors"][0][0]
        significance = abs(slope) / error
        if significance > UNEXPLAINED_NSIGMA:
            out.append({"observable": "cross moment e2", "axis": "diagonal",
                        "parity": "even", "sign": "rising" if slope > 0 else "falling",
                        "flux_dependence": None, "significance": float(significance),
                        "slope_per_1e5": float(slope), "slope_err": float(error)})
    stars = ("sizes", "skewness", "cross moment e2")
    flats = [entry["observable"] for entry in out if entry["observable"] not in stars]
    for entry in out:
        if entry["observable"] in stars:
            # what the flats leave too, by name: the same effect or another (a new user's
            # flats with an edge artefact in their means read "flats and stars" beside a
            # trail the flats did not have)
            entry["flats"] = ("stars only" if not flats else
                              f"stars; the flats' {' and '.join(flats)} too")
    _odd_direction(out)
    return out
