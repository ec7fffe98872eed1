"""What the brighter-fatter slope against peak is confounded with, fitted beside it: the
stars' size changing across the field (a PSF that varies over it: a wide star has a low
peak) and with the sub-pixel phase (undersampled stars: small and peaked on a pixel centre,
large and flat on a corner). `bfpsf.measure.slopes.bf_slopes` warns of each and keeps what
it found under ``'beside'``."""

import logging

import numpy as np

from ..least_squares import least_squares_with_scatter, weighted_least_squares

__all__ = ["changes_beside", "PHASE_SIZE_CHANGE", "FIELD_SIZE_CHANGE"]

log = logging.getLogger(__name__)


def changes_beside(table, clean, result, use_errors, axes, peak_unit, warn=True):
    """`bf_slopes`' fits of ``axes`` (``result``, on the ``clean`` rows of ``table``) repeated
    with the field's and the phase's terms beside the slope against peak (per ``peak_unit``
    e-): {'field' or 'phase': {axis: what changed}} where the size changes beyond 1 % and 5
    of its errors, each warned of (``warn``)."""
    found = {"field": _warn_field(table, clean, result, use_errors, axes, peak_unit, warn),
             "phase": _warn_phase(table, clean, result, use_errors, axes, peak_unit, warn)}
    return {name: entry for name, entry in found.items() if entry}


def _changes_beside(table, clean, result, use_errors, columns_of, fraction, axes,
                    peak_unit):
    """Each axis's fit of `bf_slopes` repeated on the stars it kept, with the image intercepts
    and two more columns beside the slope (``columns_of(x, y)`` of those stars); yields
    (key, size column, rows, what changed) where a column changes the size by more than
    ``fraction`` of it and 5 errors: {``size``, ``change_percent``, ``change_percent_err``
    (the two columns'), ``slope_beside``, ``slope_beside_err``}. Errors and a scatter
    beyond them, or without errors the scatter alone, as `fit_bf_slope`'s."""
    x, y = (np.asarray(table[name], dtype=float) for name in ("x", "y"))
    images = (np.unique(np.asarray(table["image"]), return_inverse=True)[1]
              if "image" in table.colnames else np.zeros(len(table), dtype=int))
    for key, column, error_column in axes:
        rows = result[key].rows & clean & np.isfinite(x) & np.isfinite(y)
        if rows.sum() < 10:
            continue
        size = np.asarray(table[column], dtype=float)[rows]
        weighted = use_errors and error_column in table.colnames
        errors = (np.asarray(table[error_column], dtype=float)[rows] if weighted
                  else np.full(size.size, 1.0))
        groups = np.unique(images[rows], return_inverse=True)[1]
        design = np.column_stack([np.eye(groups.max() + 1)[groups],
                                  np.asarray(table["peak_e"], float)[rows] / peak_unit,
                                  *columns_of(x[rows], y[rows])])
        if weighted:  # as `fit_bf_slope`: a scatter beyond the errors added to them
            params, covariance = least_squares_with_scatter(size, errors, design)[:2]
        else:
            params, covariance, chi2, _ = weighted_least_squares(size, errors, design)
            covariance = covariance * chi2 / max(size.size - design.shape[1], 1)
        intercept = float(np.mean(params[:-3]))
        change, change_err = params[-2:], np.sqrt(np.diag(covariance)[-2:])
        if np.any((np.abs(change) / intercept > fraction) & (np.abs(change) > 5 * change_err)):
            yield key, column, rows, {
                "size": intercept,
                "change_percent": [float(100 * value / intercept) for value in change],
                "change_percent_err": [float(100 * value / intercept) for value in change_err],
                "slope_beside": float(params[-3]),
                "slope_beside_err": float(np.sqrt(covariance[-3, -3]))}


#: `bf_slopes` warns when the stars' size changes with their sub-pixel phase, beside its slope
#: against peak, by more than this fraction (and 5 of its errors) from centre to corner
PHASE_SIZE_CHANGE = 0.01


def _warn_phase(table, clean, result, use_errors, axes, peak_unit, warn):
    """Warn where the stars' size depends on their sub-pixel phase: undersampled stars (sigma
    below ~1 px) have adaptive moments biased by the pixels, small on a pixel centre, large on
    a corner, and a peak that is high on a centre and low on a corner, so the slope against
    peak measures the pixelisation (a double Gaussian of FWHM 1.7 px: sigma_y -0.114 +- 0.013
    px per 100 ke- where BF made +0.012). The fit of each axis is repeated with terms in the
    squared phases 4 (x - round(x))^2, 4 (y - round(y))^2 (0 on a pixel centre, 1 on its
    edge) beside the slope."""
    def phases(x, y):
        return [4.0 * (v - np.round(v)) ** 2 for v in (x, y)]

    found = {}
    for key, column, _, change in _changes_beside(table, clean, result, use_errors, phases,
                                                  PHASE_SIZE_CHANGE, axes, peak_unit):
        found[key] = change
        if not warn:
            continue
        log.warning("the stars' %s (%.2f px) changes with their sub-pixel phase: %+.1f +- %.1f "
                    "%% from a pixel centre to its edge along x, %+.1f +- %.1f %% along y: the "
                    "stars are undersampled, their moments and peaks depend on the phase, and "
                    "the slope against peak (%+.4f +- %.4f px per 100 ke-) measures it, not "
                    "brighter-fatter; with the phase terms beside it, %+.4f +- %.4f. Fit P(F) "
                    "(bfpsf psf) and read the residual of `slope --psf`, measured at each "
                    "star's phase", column, change["size"], change["change_percent"][0],
                    change["change_percent_err"][0], change["change_percent"][1],
                    change["change_percent_err"][1], result[key].slope, result[key].slope_err,
                    change["slope_beside"], change["slope_beside_err"])
    return found


#: `bf_slopes` warns when the stars' size changes across the field, beside its slope
#: against peak, by more than this fraction (and 5 of its errors)
FIELD_SIZE_CHANGE = 0.01


def _warn_field(table, clean, result, use_errors, axes, peak_unit, warn):
    """Warn where the stars' size changes with their position, beside brighter-fatter: a PSF
    varying over the field confounds the slope against peak (a wide star has a low peak; a
    new user's FWHM 3.2 -> 3.9 px across 400 px gave sigma_x -0.33 +- 0.10 px per 100 ke-
    where BF made +0.013). The fit of each axis is repeated with a plane in (x, y) beside
    the slope and the image intercepts, on the stars it kept."""
    def plane(x, y):
        return [(v - v.mean()) / (np.ptp(v) or 1.0) for v in (x, y)]

    found = {}
    for key, column, rows, change in _changes_beside(table, clean, result, use_errors, plane,
                                                     FIELD_SIZE_CHANGE, axes, peak_unit):
        x, y = (np.asarray(table[name], dtype=float)[rows] for name in ("x", "y"))
        found[key] = change
        if not warn:
            continue
        log.warning("the stars' %s changes across the field beside its brighter-fatter: "
                    "%+.2f +- %.2f %% from x %.0f to %.0f, %+.2f +- %.2f %% from y %.0f to "
                    "%.0f: the PSF varies over the field, and a wide star has a low peak, so "
                    "the slope against peak (%+.4f +- %.4f px per 100 ke-) is confounded "
                    "with it; with a plane over the field beside it, %+.4f +- %.4f. Fit a "
                    "gridded P(F) (bfpsf psf --grid) and read the residual of `slope --psf`",
                    column, change["change_percent"][0], change["change_percent_err"][0],
                    x.min(), x.max(), change["change_percent"][1],
                    change["change_percent_err"][1], y.min(), y.max(),
                    result[key].slope, result[key].slope_err, change["slope_beside"],
                    change["slope_beside_err"])
    return found
