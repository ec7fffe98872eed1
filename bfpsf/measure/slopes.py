"""Brighter-fatter slopes: size against peak flux (G15 section 3.3, figure mbf, table xy_ccd_comp).

G15 fits the width of spots and stars, ``sigma_x = sqrt(Mxx)`` and ``sigma_y = sqrt(Myy)``
(and the image quality ``IQ = (Mxx Myy - Mxy^2)^(1/4)``), linearly against the peak flux below
the level where blooming sets in, and quotes the slope in pixels per 100 ke- of peak and the
relative broadening.

Units of a `SlopeFit`:

- ``slope``: pixels per 100 ke- of peak flux (G15 table xy_ccd_comp, "Delta sigma @ 100 ke-").
- ``intercept``: pixels, the size extrapolated to zero flux (G15's "reference size").
- ``relative_percent``: ``100 * slope / intercept``, the size increase in percent of the
  zero-flux size per 100 ke- of peak.
- ``range_percent``: ``100 * slope * (peak_max - peak_min) / 100 ke- / intercept``, the
  increase over the fitted peak range in percent (G15's "3.5 % from a vanishing spot to
  saturation" when the range starts near zero).
"""

import logging
from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.stats import median_abs_deviation

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import least_squares_with_scatter, weighted_least_squares
from ..moments.result import MomentsFlag
from .slopes_beside import changes_beside

__all__ = ["SlopeFit", "fit_bf_slope", "bf_slopes", "PEAK_UNIT_E", "SIZE_AXES", "SHAPE_AXES"]

#: the flux unit of slopes: 100 ke- of peak
PEAK_UNIT_E = 1e5

#: `bf_slopes` warns when the fitted stars' brightest peak is less than this many times their
#: faintest: the slope then rests on a span of flux too short to set it (a new user's frame
#: of stars of one flux gave -5.69 +- 3.06 px per 100 ke- without a word).
MIN_PEAK_SPAN = 2.0

log = logging.getLogger(__name__)
#: bfpsf.measure.sources.SourceFlag.STAMP_EDGE (kept here so slopes does not import photutils)
_STAMP_EDGE = 256


@dataclass(frozen=True)
class SlopeFit:
    """Weighted straight-line fit of a size against peak flux (module docstring for units).

    Attributes
    ----------
    slope, slope_err : float
        Pixels per 100 ke- of peak.
    intercept, intercept_err : float
        Pixels.
    relative_percent, relative_percent_err : float
        Percent of the intercept per 100 ke-.
    range_percent : float
        Percent over the fitted peak range.
    chi2, dof : float, int
        Of the fit with the given errors (None errors: residual-scaled, chi2 = dof).
    error_scale : float
        Factor applied to the errors, ``max(1, sqrt(chi2 / dof))`` (1 if not scaled, or
        with a scatter fitted).
    scatter : float
        The scatter added to the given errors in quadrature (``scatter`` of `fit_bf_slope`),
        pixels; 0 for none.
    n_points : int
        Points fitted.
    peak_min_e, peak_max_e : float
        Peak range fitted, electrons.
    slope_err_colour : float
        Part of ``slope_err`` from the size-colour fit's coefficient errors (pixels per
        100 ke-; 0 without colour correction), added in quadrature by `bf_slopes`.
    n_clipped : int
        Outliers left out by the clipping (``clip_nsigma`` of `fit_bf_slope`), not counted in
        ``n_points``.
    rows : ndarray of bool or None
        The points fitted, over the points given (`bf_slopes`: over the table's rows), so
        that other quantities can be fitted on the same stars (``use`` of `fit_bf_slope`,
        ``rows`` of `bf_slopes`); not part of `as_dict`.
    """

    slope: float
    slope_err: float
    intercept: float
    intercept_err: float
    relative_percent: float
    relative_percent_err: float
    range_percent: float
    chi2: float
    dof: int
    error_scale: float
    n_points: int
    peak_min_e: float
    peak_max_e: float
    slope_err_colour: float = 0.0
    n_clipped: int = 0
    scatter: float = 0.0
    rows: np.ndarray = field(default=None, repr=False, compare=False)

    def as_dict(self, short=False):
        """The fit as a dict (``short=True``: slope, slope_err, intercept, relative_percent)."""
        values = {item.name: getattr(self, item.name) for item in fields(self)
                  if item.name != "rows"}
        values = {key: (float(value) if isinstance(value, (float, np.floating)) else value)
                  for key, value in values.items()}
        if short:
            return {key: values[key] for key in
                    ("slope", "slope_err", "intercept", "relative_percent")}
        return values

    def predict(self, peak_e):
        """Size at ``peak_e`` electrons of peak, pixels."""
        return self.intercept + self.slope * np.asarray(peak_e) / PEAK_UNIT_E


def fit_bf_slope(peak_e, size, *, size_err=None, min_peak_e=None, max_peak_e=None,
                 scale_errors=True, clip_nsigma=5.0, group=None, use=None, scatter=None):
    """Weighted linear fit ``size = intercept + slope * peak / 100 ke-``.

    The one slope fitter of bfpsf (``bfpsf slope``, ``bfpsf validate`` and the closed loop).

    Parameters
    ----------
    peak_e : array_like
        Peak flux of each object, electrons.
    size : array_like
        Size of each object, pixels (sigma_x, sigma_y or IQ).
    size_err : array_like, optional
        Errors of ``size``, pixels; weights are ``1 / size_err^2``. Without them the fit is
        unweighted and the errors come from the residual scatter.
    min_peak_e, max_peak_e : float, optional
        Fit only ``min_peak_e <= peak <= max_peak_e`` (G15 stays below blooming: ~130 ke- for
        the E2V-250). Non-finite values are always left out.
    scale_errors : bool, optional
        Multiply the errors by ``sqrt(chi2 / dof)`` when it exceeds 1 (default True), so
        scatter beyond the given errors (e.g. PSF variations) shows up in the slope error.
    clip_nsigma : float or None, optional
        Leave out, iteratively, the points whose normalised residual is more than
        ``clip_nsigma`` robust standard deviations (1.4826 x the median absolute deviation)
        from the line: one unresolved blend must not set the slope. Default 5; None: no
        clipping. The number left out is ``SlopeFit.n_clipped``.
    group : array_like of int, optional
        A free intercept per group (an amplifier, a data set, the sub-pixel phase of a spot)
        and one common slope; ``intercept`` is then the mean of the group intercepts.
    use : array_like of bool, optional
        Fit exactly these points (those of another fit, its ``SlopeFit.rows``), without
        clipping: a model's slope and the measured-minus-model slope on the stars the
        measured slope was fitted on add up to it.
    scatter : float or 'fit', optional
        A scatter beyond ``size_err``, added to it in quadrature (another fit's
        ``SlopeFit.scatter``, for the same weights); 'fit': the one that brings chi2 / dof to
        1 where it exceeds it (`bfpsf.least_squares.least_squares_with_scatter`), for
        errors that miss a scatter which follows them (the sizes of undersampled stars
        follow their sub-pixel phase, and so do their errors: weighted by the errors alone,
        the stars of one phase set the slope). Default None: neither.

    Returns
    -------
    SlopeFit
    """
    peak = np.asarray(peak_e, dtype=float).ravel()
    values = np.asarray(size, dtype=float).ravel()
    if peak.shape != values.shape:
        msg = f"peak_e and size differ in length: {peak.size} and {values.size}"
        raise BFPSFInputError(msg, (peak.size, values.size))
    errors = None
    if size_err is not None:
        errors = np.broadcast_to(np.asarray(size_err, dtype=float), values.shape).ravel()
        if scatter is not None and not isinstance(scatter, str):
            errors = np.hypot(errors, float(scatter))
    keep = np.isfinite(peak) & np.isfinite(values)
    if errors is not None:
        keep &= np.isfinite(errors) & (errors > 0)
    if min_peak_e is not None:
        keep &= peak >= min_peak_e
    if max_peak_e is not None:
        keep &= peak <= max_peak_e
    if use is not None:
        keep &= np.asarray(use, dtype=bool).ravel()
        clip_nsigma = None
    n_points = int(keep.sum())
    if n_points < 3:
        within = ("" if min_peak_e is None and max_peak_e is None else
                  f" in the peak range [{0 if min_peak_e is None else min_peak_e:g}, "
                  f"{'inf' if max_peak_e is None else f'{max_peak_e:g}'}] e-")
        msg = (f"a brighter-fatter slope needs at least 3 usable objects{within}, "
               f"got {n_points}")
        raise BFPSFValueError(msg, n_points)
    n_usable = n_points
    group = None if group is None else np.broadcast_to(np.asarray(group), values.shape).ravel()
    for _ in range(20):
        x = peak[keep] / PEAK_UNIT_E
        y = values[keep]
        weights = np.ones(n_points) if errors is None else 1.0 / errors[keep]**2
        labels = (np.zeros(n_points, int) if group is None
                  else np.unique(group[keep], return_inverse=True)[1])
        n_groups = int(labels.max()) + 1
        design = np.column_stack([x] + [(labels == g).astype(float) for g in range(n_groups)])
        normal = design.T @ (weights[:, None] * design)
        if np.linalg.cond(normal) > 1e12:
            msg = "the peak fluxes span no range: the slope is undetermined"
            raise BFPSFValueError(msg, (x.min(), x.max()))
        params, covariance, _, model = weighted_least_squares(y, 1.0 / np.sqrt(weights),
                                                              design)
        residual = y - model
        if clip_nsigma is None or n_points <= 3:
            break
        normalised = residual * np.sqrt(weights)
        scale = median_abs_deviation(normalised, scale="normal")
        outliers = np.abs(normalised) > clip_nsigma * scale if scale > 0 else np.zeros(
            n_points, dtype=bool)
        if not outliers.any() or n_points - outliers.sum() < 3:
            break
        indices = np.flatnonzero(keep)
        keep[indices[outliers]] = False
        n_points = int(keep.sum())
    dof = n_points - design.shape[1]
    if dof < 1:
        msg = f"{n_points} objects cannot constrain a slope and {n_groups} intercepts"
        raise BFPSFValueError(msg, n_points)
    chi2 = float(np.sum(weights * residual**2))
    if errors is None:
        error_scale, scatter = np.sqrt(chi2 / dof), None
        chi2 = float(dof)
    elif scatter == "fit" and chi2 > dof:
        # added to the errors, not laid on them as a factor: the weights then stop
        # following errors that miss it
        error_scale = 1.0
        params, covariance, chi2, _, scatter = least_squares_with_scatter(
            values[keep], errors[keep], design)
    else:
        error_scale = max(1.0, np.sqrt(chi2 / dof)) if scale_errors else 1.0
    covariance = covariance * error_scale**2
    scatter = 0.0 if scatter is None or isinstance(scatter, str) else float(scatter)
    # intercept: the mean of the group intercepts (vector v), with its covariance with the slope
    mean_vector = np.r_[0.0, np.full(n_groups, 1.0 / n_groups)]
    slope, intercept = float(params[0]), float(mean_vector @ params)
    slope_err = np.sqrt(covariance[0, 0])
    intercept_err = np.sqrt(mean_vector @ covariance @ mean_vector)
    cross = float(covariance[0] @ mean_vector)
    if intercept == 0:
        # e.g. a residual size: no relative slope
        relative = relative_err = np.nan
    else:
        relative = 100.0 * slope / intercept
        # error of slope / intercept with their covariance
        relative_err = abs(relative) * np.sqrt(
            (slope_err / slope)**2 + (intercept_err / intercept)**2
            - 2.0 * cross / (slope * intercept)) if slope != 0 else \
            100.0 * slope_err / abs(intercept)
    span = (peak[keep].max() - peak[keep].min()) / PEAK_UNIT_E
    return SlopeFit(slope=float(slope), slope_err=float(slope_err), intercept=float(intercept),
                    intercept_err=float(intercept_err), relative_percent=float(relative),
                    relative_percent_err=float(relative_err),
                    range_percent=float(relative * span), chi2=chi2, dof=int(dof),
                    error_scale=float(error_scale), scatter=float(scatter), n_points=n_points,
                    peak_min_e=float(peak[keep].min()), peak_max_e=float(peak[keep].max()),
                    n_clipped=n_usable - n_points, rows=keep)


#: (result key, size column, error column) fitted by `bf_slopes`
SIZE_AXES = (("x", "sigma_x", "sigma_x_err"), ("y", "sigma_y", "sigma_y_err"), ("iq", "iq", "iq_err"))
#: (result key, column, error column) of the ellipticity fits, when the table has them
SHAPE_AXES = (("e1", "e1", "e1_err"), ("e2", "e2", "e2_err"))


def bf_slopes(table, *, min_peak_e=None, max_peak_e=None, use_errors=True, flag_mask=None,
              colour_fit=None, rows=None, warn_span=True, scatter=None):
    """Brighter-fatter slopes of sigma_x, sigma_y and IQ from a star table (G15 fig. mbf).

    Parameters
    ----------
    table : astropy.table.Table
        Output of `bfpsf.measure.sources.measure_sources` (columns ``peak_e``, ``sigma_x``,
        ``sigma_y``, ``iq``, ``flags``, optionally ``*_err``).
    min_peak_e, max_peak_e : float, optional
        Peak range fitted, electrons (G15: below blooming).
    use_errors : bool, optional
        Weight by the ``*_err`` columns when present (default True).
    flag_mask : int, optional
        Objects with any of these flag bits are left out. Default: every bit except
        ``BAD_PIXELS`` and ``STAMP_EDGE`` (masked or missing pixels do not by themselves spoil
        a measurement; the moments' ``EDGE`` flag marks a truncated object).
    colour_fit : bfpsf.measure.colour.SizeColourFit, optional
        The size-colour fit already subtracted from ``table``: the errors of its coefficients
        move every corrected size coherently, and are propagated into ``slope_err``
        (``slope_err_colour``). The Mxx and Myy fits are taken as independent for IQ.
    rows : dict, optional
        Key (``'x'``, ...) -> boolean mask over the table's rows: fit exactly those stars, not
        clipped (``SlopeFit.rows`` of another `bf_slopes` of the same table).
    warn_span : bool, optional
        Warn when the fitted stars' peaks span less than a factor `MIN_PEAK_SPAN` (default
        True; not with ``rows``, whose fit has warned). The model's predicted slopes of the
        same stars (`bfpsf.measure.model_slopes`) pass False. With it, where the sizes
        follow the stars' sub-pixel phase (`bfpsf.measure.slopes_beside`), every axis is
        fitted again with the scatter beyond the errors added to them (``scatter`` 'fit'
        of `fit_bf_slope`: the errors follow the phase too; a new user's undersampled
        stars' slopes came out 37-45 % low, and their BF-free twins' 4.4 sigma from zero).
    scatter : dict, optional
        Key -> ``scatter`` of `fit_bf_slope` (``SlopeFit.scatter`` of another `bf_slopes` of
        the same stars, with ``rows``: the same weights).

    Stars of several images (an ``image`` column) get a free intercept per image and one
    common slope: the seeing changes between exposures, not within one (a new user's 12
    exposures of seeing +-1 %, one intercept: IQ slope 0.0091 +- 0.0019 at chi2 1710 / 182,
    below both sigma_x's 0.0136 and sigma_y's 0.0164).

    Returns
    -------
    dict
        ``{'x': SlopeFit, 'y': SlopeFit, 'iq': SlopeFit, 'n_stars': int}``, plus ``'e1'``
        and ``'e2'`` (the same straight line fitted to the distortion against peak: slope per
        100 ke- of peak, intercept dimensionless) when the table has those columns, and
        ``'beside'`` with the table's x and y: what was warned of, ``{'field' or 'phase':
        {axis: {'size', 'change_percent': [along x, along y], 'change_percent_err',
        'slope_beside', 'slope_beside_err'}}}`` (the size, px, its change over the field or
        the sub-pixel phase, and the slope fitted beside it), empty where nothing was.
    """
    missing = [name for name in ("peak_e", "sigma_x", "sigma_y", "iq") if name not in
               table.colnames]
    if missing:
        msg = (f"the star table lacks columns {missing} (bfpsf slope reads the table of "
               "bfpsf measure)")
        raise BFPSFInputError(msg, missing)
    if flag_mask is None:
        flag_mask = ~(MomentsFlag.BAD_PIXELS | _STAMP_EDGE)
    if "flags" in table.colnames:
        clean = (np.asarray(table["flags"], dtype=np.int64) & flag_mask) == 0
    else:
        clean = np.ones(len(table), dtype=bool)
    peak = np.asarray(table["peak_e"], dtype=float)
    group = None
    if "image" in table.colnames and len(np.unique(np.asarray(table["image"])[clean])) > 1:
        group = np.unique(np.asarray(table["image"]), return_inverse=True)[1][clean]
    result = {}
    shape_axes = tuple(axis for axis in SHAPE_AXES if axis[1] in table.colnames)
    beside = warn_span and rows is None and {"x", "y"} <= set(table.colnames)

    def fit_axes(scatter):
        for key, column, error_column in SIZE_AXES + shape_axes:
            errors = None
            if use_errors and error_column in table.colnames:
                errors = np.asarray(table[error_column], dtype=float)[clean]
            use = None if rows is None or key not in rows else np.asarray(rows[key])[clean]
            fit = fit_bf_slope(peak[clean], np.asarray(table[column], dtype=float)[clean],
                               size_err=errors, min_peak_e=min_peak_e, max_peak_e=max_peak_e,
                               group=group, use=use, scatter=(scatter or {}).get(key))
            fitted = np.zeros(len(table), dtype=bool)
            fitted[np.flatnonzero(clean)[fit.rows]] = True
            result[key] = replace(fit, rows=fitted)

    fit_axes(scatter)
    if beside and "phase" in changes_beside(table, clean, result, use_errors, SIZE_AXES[:2],
                                            PEAK_UNIT_E, warn=False):
        fit_axes({key: "fit" for key, _, _ in SIZE_AXES + shape_axes})
    if colour_fit is not None:
        _add_colour_errors(result, table, clean, colour_fit, min_peak_e, max_peak_e,
                           use_errors)
    result["n_stars"] = result["x"].n_points
    span = result["x"].peak_max_e / result["x"].peak_min_e
    if warn_span and rows is None and not span >= MIN_PEAK_SPAN:
        log.warning("the stars' peaks span %.3g-%.3g e- (a factor %.2f): a brighter-fatter "
                    "slope needs stars of many fluxes, and the slope of X %+.4f +- %.4f px "
                    "per 100 ke- rests on too short a lever arm to mean much",
                    result["x"].peak_min_e, result["x"].peak_max_e, span, result["x"].slope,
                    result["x"].slope_err)
    if beside:
        result["beside"] = changes_beside(table, clean, result, use_errors, SIZE_AXES[:2],
                                          PEAK_UNIT_E)
    return result


def _add_colour_errors(result, table, clean, colour_fit, min_peak_e, max_peak_e, use_errors):
    """Propagate the size-colour coefficient covariance into the slope errors."""
    colour = np.asarray(table[colour_fit.colour_column], dtype=float)[clean]
    has_colour = np.isfinite(colour)
    powers = np.arange(colour_fit.degree, -1, -1)
    # d(p(c) - p(c_ref)) / d coefficient_k, zero for stars left uncorrected
    design = np.where(has_colour[:, None],
                      np.where(has_colour, colour, 0.0)[:, None]**powers
                      - colour_fit.colour_reference**powers, 0.0)
    peak = np.asarray(table["peak_e"], dtype=float)[clean]
    moments = {name: np.asarray(table[name], dtype=float)[clean] for name in ("mxx", "myy")}
    derivatives = {}
    for key, column, error_column in SIZE_AXES:
        size = np.asarray(table[column], dtype=float)[clean]
        errors = (np.asarray(table[error_column], dtype=float)[clean]
                  if use_errors and error_column in table.colnames else None)
        base = result[key].slope

        def slope_change(perturbation):
            # the fit is linear in the sizes: the slope change of a unit perturbation
            return fit_bf_slope(peak, size + perturbation, size_err=errors,
                                min_peak_e=min_peak_e, max_peak_e=max_peak_e).slope - base

        variance = 0.0
        for moment in (("mxx",) if key == "x" else ("myy",) if key == "y" else ("mxx", "myy")):
            if moment not in colour_fit.coefficients:
                continue
            if key == "iq":
                # d iq / d M = iq * M_other / (4 det), det ~ Mxx Myy
                other = moments["myy" if moment == "mxx" else "mxx"]
                dsize_dm = size * other / (4.0 * moments["mxx"] * moments["myy"])
            else:
                dsize_dm = 1.0 / (2.0 * size)
            gradient = np.array([slope_change(-dsize_dm * design[:, k])
                                 for k in range(design.shape[1])])
            variance += gradient @ colour_fit.covariance[moment] @ gradient
        derivatives[key] = np.sqrt(variance)
    for key, colour_err in derivatives.items():
        fit = result[key]
        total = np.hypot(fit.slope_err, colour_err)
        result[key] = replace(fit, slope_err=float(total), slope_err_colour=float(colour_err),
                              relative_percent_err=float(fit.relative_percent_err * total
                                                         / fit.slope_err))
