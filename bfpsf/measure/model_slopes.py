"""What a flux-dependent PSF predicts for a star table: its size increments with flux, the
sizes of each star's model (flux, position, sub-pixel phase), and the BF slopes it predicts
with the calibration error, fitted as `bfpsf.measure.slopes.bf_slopes` fits the measured
sizes (``bfpsf slope --psf``)."""

import numpy as np

from ..model.gridded import bilinear_weights
from ..moments.adaptive import adaptive_moments_batch
from ..moments.shapes import distortion, psf_shapes
from .slopes import SIZE_AXES, SHAPE_AXES, bf_slopes
from .sources import model_flux

__all__ = ["model_size_increments", "model_star_sizes", "predicted_slopes", "star_positions"]


def model_size_increments(psf, flux_e, *, x=None, y=None, n_grid=24, x_phase=None,
                          y_phase=None):
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
    x_phase, y_phase : float, optional
        Sub-pixel phase of the star image measured (``psf.star_image``); default 0, where
        an undersampled model has no adaptive moments (NaN).

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
            stamps = np.array([model.star_image(max(flux, 1.0), x_phase=x_phase,
                                                y_phase=y_phase) / max(flux, 1.0)
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


def predicted_slopes(psf, table, *, min_peak_e=None, max_peak_e=None, use_errors=True,
                     rows=None, sizes=None, scatter=None):
    """The BF slopes a flux-dependent PSF predicts for a star table, with the calibration error.

    The model's sizes of each star (`model_star_sizes`: its flux, position and sub-pixel
    phase, as the star was measured) are fitted exactly as the measured sizes are
    (`bf_slopes`: the same stars, peak range and weights; ``rows``, the measured fit's
    ``SlopeFit.rows``, fixes the stars, and ``scatter``, its ``SlopeFit.scatter``, the
    weights, so that the measured slope minus this one is the
    slope of the measured-minus-model sizes: a new user's ``slope --psf`` printed measured
    0.0145, predicted 0.0170 and a residual of +0.0055, the increments at phase 0 and the
    residual's own clipping not adding up). The error is the spread of the same fit over
    the shift samples the model carries (``psf.shift_samples``, the calibration's
    uncertainty), on each sample's sizes of the stars (`model_star_sizes`).

    Parameters
    ----------
    sizes : dict, optional
        `model_star_sizes` of the table's stars, when already computed.

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

    axes = SIZE_AXES + tuple(axis for axis in SHAPE_AXES if axis[1] in table.colnames)

    def slopes_of(values):
        predicted = table.copy()
        for key, column, _ in axes:
            predicted[column] = values[key]
        fits = bf_slopes(predicted, min_peak_e=min_peak_e, max_peak_e=max_peak_e,
                         use_errors=use_errors, rows=rows, warn_span=False, scatter=scatter)
        return np.array([fits[key].slope for key, _, _ in axes])

    if sizes is None:
        sizes = model_star_sizes(psf, flux, x=x, y=y)
    best = slopes_of(sizes)
    # each sample's sizes at every star's own phase, as ``best``: increments at phase 0 are
    # NaN for every star of an undersampled model (no adaptive moments on a pixel centre)
    draws = np.array([slopes_of(model_star_sizes(psf.with_shifts(sample), flux, x=x, y=y))
                      for sample in psf.shift_samples])
    errors = (draws.std(axis=0, ddof=1) if len(draws) >= 2
              else np.full(best.shape, np.nan))
    out = {key: {"slope": float(value), "slope_err": float(error)}
           for (key, _, _), value, error in zip(axes, best, errors)}
    out["n_samples"] = int(len(draws))
    return out
