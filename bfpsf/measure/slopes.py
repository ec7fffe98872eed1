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

from dataclasses import asdict, dataclass, replace

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import weighted_least_squares
from ..model.gridded import bilinear_weights
from ..moments.adaptive import adaptive_moments_batch
from ..moments.result import MomentsFlag
from ..moments.shapes import distortion, psf_shapes
from .sources import model_flux

__all__ = ["SlopeFit", "fit_bf_slope", "bf_slopes", "PEAK_UNIT_E", "model_size_increments",
           "model_star_sizes", "predicted_slopes", "star_positions"]

#: the flux unit of slopes: 100 ke- of peak
PEAK_UNIT_E = 1e5
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
        Factor applied to the errors, ``max(1, sqrt(chi2 / dof))`` (1 if not scaled).
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

    def as_dict(self, short=False):
        """The fit as a dict (``short=True``: slope, slope_err, intercept, relative_percent)."""
        values = {key: (float(value) if isinstance(value, (float, np.floating)) else value)
                  for key, value in asdict(self).items()}
        if short:
            return {key: values[key] for key in
                    ("slope", "slope_err", "intercept", "relative_percent")}
        return values

    def predict(self, peak_e):
        """Size at ``peak_e`` electrons of peak, pixels."""
        return self.intercept + self.slope * np.asarray(peak_e) / PEAK_UNIT_E


def fit_bf_slope(peak_e, size, *, size_err=None, min_peak_e=None, max_peak_e=None,
                 scale_errors=True, clip_nsigma=5.0, group=None):
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
    keep = np.isfinite(peak) & np.isfinite(values)
    if errors is not None:
        keep &= np.isfinite(errors) & (errors > 0)
    if min_peak_e is not None:
        keep &= peak >= min_peak_e
    if max_peak_e is not None:
        keep &= peak <= max_peak_e
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
        scale = 1.4826 * np.median(np.abs(normalised - np.median(normalised)))
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
        error_scale = np.sqrt(chi2 / dof)
        chi2 = float(dof)
    else:
        error_scale = max(1.0, np.sqrt(chi2 / dof)) if scale_errors else 1.0
    covariance = covariance * error_scale**2
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
                    error_scale=float(error_scale), n_points=n_points,
                    peak_min_e=float(peak[keep].min()), peak_max_e=float(peak[keep].max()),
                    n_clipped=n_usable - n_points)


#: (result key, size column, error column) fitted by `bf_slopes`
_AXES = (("x", "sigma_x", "sigma_x_err"), ("y", "sigma_y", "sigma_y_err"), ("iq", "iq", "iq_err"))
#: (result key, column, error column) of the ellipticity fits, when the table has them
_SHAPE_AXES = (("e1", "e1", "e1_err"), ("e2", "e2", "e2_err"))


def bf_slopes(table, *, min_peak_e=None, max_peak_e=None, use_errors=True, flag_mask=None,
              colour_fit=None):
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

    Returns
    -------
    dict
        ``{'x': SlopeFit, 'y': SlopeFit, 'iq': SlopeFit, 'n_stars': int}``, plus ``'e1'``
        and ``'e2'`` (the same straight line fitted to the distortion against peak: slope per
        100 ke- of peak, intercept dimensionless) when the table has those columns.
    """
    missing = [name for name in ("peak_e", "sigma_x", "sigma_y", "iq") if name not in
               table.colnames]
    if missing:
        msg = f"the star table lacks columns {missing}"
        raise BFPSFInputError(msg, missing)
    if flag_mask is None:
        flag_mask = ~(MomentsFlag.BAD_PIXELS | _STAMP_EDGE)
    if "flags" in table.colnames:
        clean = (np.asarray(table["flags"], dtype=np.int64) & flag_mask) == 0
    else:
        clean = np.ones(len(table), dtype=bool)
    peak = np.asarray(table["peak_e"], dtype=float)
    result = {}
    shape_axes = tuple(axis for axis in _SHAPE_AXES if axis[1] in table.colnames)
    for key, column, error_column in _AXES + shape_axes:
        errors = None
        if use_errors and error_column in table.colnames:
            errors = np.asarray(table[error_column], dtype=float)[clean]
        result[key] = fit_bf_slope(peak[clean], np.asarray(table[column], dtype=float)[clean],
                                   size_err=errors, min_peak_e=min_peak_e,
                                   max_peak_e=max_peak_e)
    if colour_fit is not None:
        _add_colour_errors(result, table, clean, colour_fit, min_peak_e, max_peak_e,
                           use_errors)
    result["n_stars"] = result["x"].n_points
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
    for key, column, error_column in _AXES:
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


def model_size_increments(psf, flux_e, *, x=None, y=None, n_grid=24):
    """Growth of sigma_x, sigma_y, IQ (and change of e1, e2) that a flux-dependent PSF predicts at each flux, pixels.

    The PSF's star image at flux F (``psf.star_image``, phase 0) is measured with
    `~bfpsf.moments.adaptive.adaptive_moments_batch` on a grid of fluxes spanning ``flux_e``;
    the sizes at F = 0 are subtracted and the increments interpolated (linear) to each star's
    flux. A model that varies over the field (``psf.varies_over_field``) is measured at each of
    its ``field_nodes`` and the increments interpolated bilinearly to each star's position
    (the model's own interpolation). Subtracting them from measured sizes leaves the
    size-vs-flux relation the model does not explain (``model_residual`` of ``bfpsf slope
    --psf``).

    Parameters
    ----------
    psf : bfpsf.model.base.BFPSFModel
        The model (any kind), in electrons.
    flux_e : array_like
        Total fluxes of the stars, e-.
    x, y : array_like, optional
        Image positions of the stars, pixels; default the model's reference position.
    n_grid : int, optional
        Fluxes on which the model is measured. Default 24.

    Returns
    -------
    dict of ndarray
        ``{'x': d sigma_x, 'y': d sigma_y, 'iq': d IQ}``, one value per star, pixels, and
        ``'e1'``, ``'e2'``: the change of the distortion.
    """
    flux_e = np.asarray(flux_e, dtype=float)
    finite = np.isfinite(flux_e)
    top = float(np.max(flux_e[finite], initial=0.0))
    grid = np.linspace(0.0, max(top, 1.0), n_grid)
    x_nodes, y_nodes = psf.field_nodes
    increments = []  # per field node, row-major [y, x]
    for y_node in y_nodes:
        for x_node in x_nodes:
            model = psf.at(x_node, y_node)
            # F = 0 renders nothing: the shape at unit flux (BF term ~1e-6 of it), scaled
            stamps = np.array([model.star_image(max(flux, 1.0)) / max(flux, 1.0)
                               for flux in grid])
            moments = adaptive_moments_batch(stamps)
            sizes = {"x": np.sqrt(moments.mxx), "y": np.sqrt(moments.myy), "iq": moments.sigma}
            sizes["e1"], sizes["e2"] = distortion(moments.mxx, moments.myy, moments.mxy)
            increments.append({key: np.interp(flux_e, grid, value - value[0], left=np.nan,
                                              right=np.nan) for key, value in sizes.items()})
    x_ref, y_ref = psf.reference_position
    x = np.broadcast_to(x_ref if x is None else np.asarray(x, dtype=float), flux_e.shape)
    y = np.broadcast_to(y_ref if y is None else np.asarray(y, dtype=float), flux_e.shape)
    indices, weights = bilinear_weights(x, y, x_nodes, y_nodes)
    star = np.arange(flux_e.size).reshape(flux_e.shape)
    result = {}
    for key in increments[0]:
        per_node = np.array([node[key] for node in increments])  # (nodes, stars)
        result[key] = sum(weights[..., corner] * per_node[indices[..., corner], star]
                          for corner in range(4))
    return result


def star_positions(psf, table):
    """(x, y) of a star table's stars, pixels ((None, None) for a table without positions:
    the model's reference position is then taken)."""
    if "x" not in table.colnames or "y" not in table.colnames:
        return None, None
    return np.asarray(table["x"], dtype=float), np.asarray(table["y"], dtype=float)


def model_star_sizes(psf, flux_e, *, x=None, y=None):
    """sigma_x, sigma_y, IQ, e1 and e2 of the model of each star: at its own flux, image
    position and sub-pixel phase (`bfpsf.moments.shapes.psf_shapes`).

    What a star measured with the same estimator should show if the model is right: the
    zero-flux size, its variation over the field (a grid's P0 interpolated to the star) and
    the BF change at the star's flux. Measured minus this is ``model_residual`` of ``bfpsf
    slope --psf``: it carries neither the brighter-fatter slope the model explains nor the
    field's size variation (which, against peak, would dominate the residual's error).

    Parameters
    ----------
    psf : bfpsf.model.base.BFPSFModel
        In electrons.
    flux_e : array_like
        Total fluxes of the stars, e-.
    x, y : array_like, optional
        Image positions, pixels; default the model's reference position (phase 0).

    Returns
    -------
    dict of ndarray
        ``{'x', 'y', 'iq'}`` (pixels) and ``{'e1', 'e2'}``, one value per star; NaN where the
        flux is not positive.
    """
    flux_e = np.asarray(flux_e, dtype=float)
    x_ref, y_ref = psf.reference_position
    x = np.broadcast_to(x_ref if x is None else np.asarray(x, dtype=float), flux_e.shape)
    y = np.broadcast_to(y_ref if y is None else np.asarray(y, dtype=float), flux_e.shape)
    shapes = psf_shapes(psf, flux_e, x, y)
    return {key: value.reshape(flux_e.shape) for key, value in (
        ("x", np.sqrt(shapes["mxx"])), ("y", np.sqrt(shapes["myy"])), ("iq", shapes["sigma"]),
        ("e1", shapes["e1"]), ("e2", shapes["e2"]))}


def predicted_slopes(psf, table, *, min_peak_e=None, max_peak_e=None, use_errors=True):
    """The BF slopes a flux-dependent PSF predicts for a star table, with the calibration error.

    The model's size increments at each star's flux (`model_size_increments`) are fitted
    exactly as the measured sizes are (`bf_slopes`: same stars, peak range and weights); the
    fit of every shift sample the model carries (``psf.shift_samples``, the calibration's
    uncertainty) gives the error.

    Returns
    -------
    dict
        ``{'x': {...}, 'y': {...}, 'iq': {...}, 'n_samples': int}``, and ``'e1'``, ``'e2'``
        when the table has those columns; each axis holds ``slope`` and ``slope_err``
        (pixels, or for e1 and e2 distortion, per 100 ke- of peak; the error is that of the
        calibration, NaN without samples).
    """
    flux = model_flux(psf, table["flux_e"])  # the flux P(F) takes; flux_e is an aperture's
    x, y = star_positions(psf, table)

    axes = _AXES + tuple(axis for axis in _SHAPE_AXES if axis[1] in table.colnames)

    def slopes_of(model):
        increments = model_size_increments(model, flux, x=x, y=y)
        predicted = table.copy()
        for key, column, _ in axes:
            predicted[column] = increments[key]
        fits = bf_slopes(predicted, min_peak_e=min_peak_e, max_peak_e=max_peak_e,
                         use_errors=use_errors)
        return np.array([fits[key].slope for key, _, _ in axes])

    best = slopes_of(psf)
    draws = np.array([slopes_of(psf.with_shifts(sample)) for sample in psf.shift_samples])
    errors = (draws.std(axis=0, ddof=1) if len(draws) >= 2
              else np.full(best.shape, np.nan))
    out = {key: {"slope": float(value), "slope_err": float(error)}
           for (key, _, _), value, error in zip(axes, best, errors)}
    out["n_samples"] = int(len(draws))
    return out
