"""photutils glue: PSF photometry with the flux-dependent PSF.

`FluxDependentPSF` is a photutils-compatible PSF model (``flux``, ``x_0``, ``y_0``; stateless
``evaluate``; ``copy`` sharing arrays; ``bounding_box``), so it goes straight into
`photutils.psf.PSFPhotometry` and `~photutils.psf.IterativePSFPhotometry`. The helpers here
choose sensible defaults from the PSF (fit box, grouping distance) and build the static
`~photutils.psf.ImagePSF` counterpart used for comparison.
"""

import numpy as np
from astropy.nddata import NDData

from ..errors import BFPSFValueError
from ..model.base import BFPSFModel
from ..model.bf_term import bf_response_table

__all__ = ["default_fit_shape", "make_psf_photometry", "static_image_psf", "psf_fwhm",
           "outlying_nodes", "describe_outlying_nodes"]

#: A node of a varying PSF whose FWHM differs from the median over its nodes by more than this
#: factor is an outlier (`outlying_nodes`): a field rarely varies that much across one image,
#: while a node fitted from too few stars does (a new user's 10.2 px against 4.2-4.7).
NODE_FWHM_FACTOR = 1.3
#: ... and so is a node whose P0 dips below -this of its peak within the fit box (where
#: photometry uses it): well-fitted P0s dip to -0.001 to -0.1, nodes fitted from 6-9 stars'
#: weight to -0.2 to -1.7 (two new users' grids). Beyond the box a well-fitted node may dip
#: further at a single node of the support's edge (-0.31, 12.5 px out, a 2 x 2 grid's corner
#: node of 13 stars' weight).
NODE_NEGATIVE_LOBE = 0.2


def psf_fwhm(psf, x=None, y=None):
    """FWHM of the pixelised P0 along x through its peak, pixels (half-maximum crossing), at
    image position (x, y) (`BFPSFModel.at`; default the model's reference position). The
    peak is sought within a quarter of the table from its origin (a spike at a poorly fitted
    edge is not the peak); the origin, P0's centroid, lies off the peak of a comatic PSF (a
    new user's Kolmogorov x coma: 4.09 px through the origin, 3.91 through the peak)."""
    psf = psf.at(x, y) if isinstance(psf, BFPSFModel) else psf  # or a photutils ImagePSF
    oy, ox = psf.oversampling
    centre = int(round(psf.origin[1]))
    reach = max(1, psf.data.shape[0] // 4)
    low = max(centre - reach, 0)
    window = psf.data[low:centre + reach + 1]
    row = psf.data[low + np.unravel_index(np.argmax(window), window.shape)[0]]
    half = row.max() / 2
    above = np.nonzero(row >= half)[0]
    left, right = above[0], above[-1]

    def crossing(inside, outside):
        return inside + (row[inside] - half) / (row[inside] - row[outside]) * (outside - inside)

    x_left = crossing(left, left - 1) if left > 0 else left
    x_right = crossing(right, right + 1) if right < row.size - 1 else right
    return float((x_right - x_left) / ox)


def largest_fwhm(psf):
    """The largest `psf_fwhm` over the model's field nodes (any kind, and a photutils
    `~photutils.psf.GriddedPSFModel`: ``photometry --static`` with a gridded product), pixels."""
    from photutils.psf import GriddedPSFModel, ImagePSF

    if isinstance(psf, GriddedPSFModel):
        return max(psf_fwhm(ImagePSF(node, oversampling=psf.oversampling))
                   for node in psf.data)
    if not isinstance(psf, BFPSFModel):
        return psf_fwhm(psf)
    x_nodes, y_nodes = psf.field_nodes
    return max(psf_fwhm(psf, x, y) for y in y_nodes for x in x_nodes)


def outlying_nodes(psf, factor=NODE_FWHM_FACTOR, lobe=NODE_NEGATIVE_LOBE):
    """Field nodes whose `psf_fwhm` is more than ``factor`` from the median over the nodes, or
    whose P0 dips below ``-lobe`` of its peak within the default fit box (`default_fit_shape`).

    Returns
    -------
    outliers : list of (x, y, fwhm, lobe)
        Pixels, and the node's P0 minimum within the fit box over its maximum; empty for a
        model with fewer than two nodes.
    median : float
        The median FWHM over the nodes, pixels.
    """
    x_nodes, y_nodes = psf.field_nodes if isinstance(psf, BFPSFModel) else ([None], [None])
    nodes = []
    for y in y_nodes:
        for x in x_nodes:
            nodes.append((x, y, psf_fwhm(psf, x, y)))
    median = float(np.median([node[2] for node in nodes]))
    if len(nodes) < 2:
        return [], median
    half = _fit_side(max(node[2] for node in nodes)) // 2  # `default_fit_shape`'s box
    nodes = [(x, y, fwhm, _dip(psf.at(x, y), half)) for x, y, fwhm in nodes]
    return [(float(x), float(y), fwhm, dip) for x, y, fwhm, dip in nodes
            if not median / factor <= fwhm <= median * factor or dip < -lobe], median


def _dip(psf, half):
    """P0's minimum within ``half`` pixels of its centre, over its maximum."""
    data = psf.data
    centre = (np.asarray(data.shape) - 1) // 2
    reach = np.round(half * np.asarray(psf.oversampling)).astype(int)
    low, high = np.maximum(centre - reach, 0), centre + reach + 1
    return float(data[low[0]:high[0], low[1]:high[1]].min() / data.max())


def describe_outlying_nodes(outliers, median):
    """One phrase naming the outlying nodes of `outlying_nodes` (empty when there are none)."""
    if not outliers:
        return ""
    places = ", ".join(f"(x {x:.0f}, y {y:.0f}) {fwhm:.1f} px"
                       + (f" with a dip of {dip:.2f} of its peak" if dip < -NODE_NEGATIVE_LOBE
                          else "")
                       for x, y, fwhm, dip in outliers)
    return (f"grid node{'s' if len(outliers) > 1 else ''} {places} against a median FWHM "
            f"{median:.1f} px over the nodes")


def default_fit_shape(psf):
    """Odd fit box of about 3 FWHM (at least 5 pixels; the largest FWHM over the field),
    pixels."""
    return _fit_side(largest_fwhm(psf))


def _fit_side(fwhm):
    size = max(5, int(np.ceil(3 * fwhm)))
    return size + 1 - size % 2


def _forget_grouped_models(psf):
    """Drop photutils' cached group models of ``psf``'s class.

    photutils (3.0) fits a group of N stars with a model class it builds around a copy of the
    first PSF model it saw, cached by (N, model class): a later fit with another model of the
    same class (another P0, other shifts, static and P(F) as two FluxDependentPSF) would
    silently evaluate the first one for its groups. Called for every photometry object made
    here; the cache is private photutils state, so nothing happens if it is not there.
    Upstream fix: astropy/photutils#2384 (merged 2026-08, a cache per fitter keyed on the
    number of sources; not in 3.0.0, the newest release): with it this is a no-op.
    `tests/test_photometry.py::test_two_models_of_one_class_fitted_in_turn` fails without it
    on photutils 3.0.0.
    """
    try:
        from photutils.psf import _components
    except ImportError:  # pragma: no cover - a photutils without the module
        return
    cache = getattr(_components, "_FLAT_MODEL_CACHE", None)
    if cache is None:
        return
    model_type = f"{type(psf).__module__}.{type(psf).__name__}"
    for key in [key for key in list(cache.keys()) if key[1:] == (model_type,)]:
        cache.pop(key, None)


def make_psf_photometry(psf, *, fit_shape=None, group_separation=None, iterative=False,
                        **kwargs):
    """A photutils PSF photometry object using the flux-dependent PSF.

    Parameters
    ----------
    psf : FluxDependentPSF or photutils PSF model
        The model fitted to each source (``evaluate`` at the fitted flux, BF included).
    fit_shape : int or (int, int), optional
        Fit box, pixels (odd); default `default_fit_shape`.
    group_separation : float, optional
        Sources closer than this (pixels) are fitted simultaneously
        (`photutils.psf.SourceGrouper`); default the fit box (stars whose boxes overlap are
        fitted together), 0 disables grouping. Light of an ungrouped neighbour inside a fit box
        biases that star; large values chain dense fields into very large groups.
    iterative : bool, optional
        Return an `~photutils.psf.IterativePSFPhotometry` (needs ``finder`` in kwargs).
    **kwargs
        Passed to the photutils class (``finder``, ``aperture_radius``, ``fitter``, ...).

    Returns
    -------
    photutils.psf.PSFPhotometry or photutils.psf.IterativePSFPhotometry
    """
    from photutils.psf import IterativePSFPhotometry, PSFPhotometry, SourceGrouper

    if fit_shape is None:
        fit_shape = default_fit_shape(psf)
    sides = np.atleast_1d(fit_shape)
    if sides.size > 2 or np.any(sides != np.round(sides)) or np.any(sides < 3) or np.any(
            sides % 2 == 0):
        msg = f"fit shape must be an odd number of pixels >= 3 (e.g. 5, 7), got {fit_shape!r}"
        raise BFPSFValueError(msg, fit_shape)
    if group_separation is None:
        group_separation = float(np.max(np.atleast_1d(fit_shape)))
    if group_separation < 0:
        msg = f"group_separation must be >= 0 pixels, got {group_separation}"
        raise BFPSFValueError(msg, group_separation)
    if group_separation > 0:
        kwargs.setdefault("grouper", SourceGrouper(min_separation=group_separation))
    kwargs.setdefault("aperture_radius", 1.5 * largest_fwhm(psf))
    _forget_grouped_models(psf)
    if iterative:
        if kwargs.get("finder") is None:
            msg = "iterative photometry needs a finder (e.g. photutils.detection.DAOStarFinder)"
            raise BFPSFValueError(msg, None)
        return IterativePSFPhotometry(psf, fit_shape, **kwargs)
    return PSFPhotometry(psf, fit_shape, **kwargs)


def static_image_psf(psf, flux=None):
    """A photutils `~photutils.psf.ImagePSF` of the PSF at one flux (static, no BF in fits).

    Parameters
    ----------
    psf : BFPSFModel
        Any kind; a model varying over the field gives a photutils
        `~photutils.psf.GriddedPSFModel` of the static models at its ``field_nodes``
        (photutils interpolates them bilinearly, as the bfpsf grid does).
    flux : float, optional
        Flux at which the shape is frozen (the naive practice freezes it at the flux of the
        bright stars the PSF was built from); default None gives P0 itself.

    Returns
    -------
    photutils.psf.ImagePSF or photutils.psf.GriddedPSFModel
        Data ``P0 + F R[P0]`` on the oversampled grid (R of each phase, table of
        `~bfpsf.model.bf_term.bf_response_table`), normalised like P0.
    """
    from photutils.psf import ImagePSF

    if psf.varies_over_field:
        return _static_gridded_psf(psf, flux)
    data = np.array(psf.data)
    if flux is not None:
        table = psf.bf_table if psf.bf_table is not None else bf_response_table(
            psf.data, psf.shifts, psf.oversampling)
        data = data + psf.electrons_per_unit * flux * table
    return ImagePSF(data, origin=tuple(psf.origin), oversampling=tuple(psf.oversampling))


def _static_gridded_psf(psf, flux):
    """photutils GriddedPSFModel of the static models at a field-varying model's nodes."""
    from photutils.psf import GriddedPSFModel

    x_nodes, y_nodes = psf.field_nodes
    positions = [(x, y) for y in y_nodes for x in x_nodes]
    cube = np.array([static_image_psf(psf.at(x, y), flux).data for x, y in positions])
    oversampling = tuple(int(value) for value in psf.oversampling)
    return GriddedPSFModel(NDData(cube, meta={"grid_xypos": positions,
                                              "oversampling": oversampling}))
