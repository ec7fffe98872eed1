"""Whether the stars' BF slope depends on where they are: a test of every star, free of any
model of the effect.

The closed loop's position test needs a grid of position cells in every exposure
(`bfpsf.diagnosis.binning.auto_position_bins`: 72 stars per exposure for 2 x 2), so an
exposure of fewer stars is "not tested". A new user's smear along Y, growing with the row,
on 8 exposures of 55 stars went unreported although the stars' Y slope in the upper half of
the rows was 0.0322 +- 0.0006 against 0.0222 +- 0.0006 in the lower.

`star_slope_split` fits, per axis and for the columns and the rows in turn, every star of
every exposure: sigma = a_exposure + e1 u + e2 u^2 + b p + c p^2 + d p u, with p the peak
in 100 ke- and u the star's column (row) from the median over the span of the stars. d is
the change of the BF slope across the span; the quadratic keeps the slope's run with flux
out of it, so that a layout whose rows follow the peak (spots laid out in rows of one level)
makes d degenerate (a large error), not spurious; the terms in u keep out a size that
changes over the field at every flux (a PSF varying over the field; the faint stars' trail
of a serial charge transfer: without them a new user's trail read "the X BF slope rises
with the column, +0.048 +- 0.008" where the stars' own slope fell by 0.0025). BF itself
(one calibration, one P0) predicts d = 0.
"""

import numpy as np

from ..least_squares import clipped_least_squares

__all__ = ["star_slope_split", "describe_split", "dependent_directions", "SPLIT_NSIGMA"]

#: A change of the slope beyond this many errors is reported as a dependence.
SPLIT_NSIGMA = 3.0

#: Stars beyond this many robust standard deviations of the fit (blends) are left out.
_CLIP = 5.0


def star_slope_split(peak_e, sigma_x, sigma_y, exposure, x, y):
    """The change of the BF slope of sigma_x and sigma_y (pixels per 100 ke- of peak) across
    the columns and across the rows the stars span.

    Returns
    -------
    dict
        {along: {axis: {slope, change, change_err, significance, span}}} for along in
        ("column", "row") and axis in ("x", "y"): the slope at the median position, its
        change from one end of the span (pixels) to the other, and its error (the errors
        scaled by the scatter). A fit without enough stars is left out.
    """
    p = np.asarray(peak_e, float) / 1e5
    groups = np.unique(np.asarray(exposure), return_inverse=True)[1]
    intercepts = np.eye(groups.max() + 1)[groups] if groups.size else np.zeros((0, 1))
    out = {}
    for along, where in (("column", np.asarray(x, float)), ("row", np.asarray(y, float))):
        span = float(np.ptp(where)) if where.size else 0.0
        if span == 0 or where.size < intercepts.shape[1] + 8:
            continue
        u = (where - np.median(where)) / span
        design = np.column_stack([intercepts, u, u ** 2, p, p ** 2, p * u])
        entry = {}
        for axis, sigma in (("x", sigma_x), ("y", sigma_y)):
            fit = _robust_fit(np.asarray(sigma, float), design)
            if fit is None:
                continue
            params, covariance = fit
            change, error = float(params[-1]), float(np.sqrt(covariance[-1, -1]))
            entry[axis] = {"slope": float(params[-3]), "change": change, "change_err": error,
                           "significance": abs(change) / error if error > 0 else 0.0,
                           "span": span}
        if entry:
            out[along] = entry
    return out


def _robust_fit(values, design):
    """Least squares with the errors from the scatter, clipping at `_CLIP` robust sigma
    (`bfpsf.least_squares.clipped_least_squares`): (params, covariance), or None when fewer
    than 5 degrees of freedom are left."""
    fit = clipped_least_squares(values, design, nsigma=_CLIP)
    if fit.dof < 5:
        return None
    return fit.params, fit.covariance


def dependent_directions(split):
    """{along: the largest significance of its axes} for the directions ("column", "row")
    along which every star's BF slope changes beyond `SPLIT_NSIGMA`."""
    out = {}
    for along, entry in (split or {}).items():
        significance = max((value["significance"] for value in entry.values()), default=0.0)
        if significance > SPLIT_NSIGMA:
            out[along] = significance
    return out


def describe_split(split):
    """One line per significant dependence (beyond `SPLIT_NSIGMA`), in words; where every
    star was tested and none is, one line saying so (a new user's "position bins: not
    tested" stood alone, as if position had not been looked at)."""
    lines = []
    for along, entry in split.items():
        for axis, values in entry.items():
            if values["significance"] > SPLIT_NSIGMA:
                trend = "rises" if values["change"] > 0 else "falls"
                lines.append(
                    f"the stars' {axis.upper()} BF slope ({values['slope']:.4f} px per 100 "
                    f"ke- at the median {along}) {trend} with the {along}, by "
                    f"{values['change']:+.4f} +- {values['change_err']:.4f} over the "
                    f"{values['span']:.0f} px the stars span ({values['significance']:.1f} "
                    "sigma; brighter-fatter predicts none)")
    tested = [values["significance"] for entry in split.values() for values in entry.values()]
    if tested and not lines:
        lines.append(f"the stars' BF slope depends on neither the column nor the row (largest "
                     f"{max(tested):.1f} sigma, every star tested)")
    return lines
