"""PSF photometry with the flux-dependent PSF P(F) (photutils `~photutils.psf.PSFPhotometry`).

Each star is fitted with F p + F |F| R[p] at its own flux and sub-pixel phase
(`bfpsf.model.psf.FluxDependentPSF`), so bright and faint stars are measured with the shape
they actually have and the faint-to-bright flux scale is free of the brighter-fatter bias a
static PSF from bright stars carries. Pixels and their noise are left untouched; the pixel
weights come from the fitted model, not from the noisy pixel values (``weights``). Blends
are fitted together (photutils' ``SourceGrouper``), and every group's final fit is made on
the data minus the models of the stars outside it (`bfpsf.measure.neighbour_fits`). The stars
detection missed are searched for in the fit's residual and fitted with the others
(`bfpsf.measure.residual_sources`, as photutils' ``IterativePSFPhotometry``).
"""

import contextlib
import logging
import warnings

import numpy as np
from astropy.table import Table, vstack
from astropy.utils.exceptions import AstropyUserWarning
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import BFPSFInputError, BFPSFValueError, BFPSFWarning
from ..interop.photutils import (default_fit_shape, describe_outlying_nodes,
                                make_psf_photometry, outlying_nodes)
from ..model.base import BFPSFModel
from .neighbour_fits import (fit_without_neighbours, merged, model_image, refit_pulled, with_found,
                            without_lost)
from .neighbours import COMPANION_SEPARATION, sources_with_companions
from .prepare import PreparedImage, prepare_image
from .psf_likeness import misfit_outliers, unlike_psf
from .read_noise import check_read_noise, check_sky, image_read_noise
from .cosmic_rays import cosmic_ray_mask, psf_sharpness
from .cross_terms import cross_term_image
from .line_features import near_lines, resolve_lines
from .residual_sources import residual_sources
from .sources import DETECTION_THRESHOLD, SourceFlag, ray_mask
from ..model.wings import WingModel, wing_image

__all__ = ["psf_photometry", "PHOTOMETRY_COLUMNS"]

log = logging.getLogger(__name__)

#: photutils' flag of a fit that did not converge.
NO_CONVERGENCE = 8

#: Searches of the fit's residual for the stars detection missed (photutils'
#: ``IterativePSFPhotometry`` iterates up to 3 times: detection, then two searches).
RESIDUAL_PASSES = 2

#: How far a star's misfit reaches, in half-widths of the PSF's support
#: (`bfpsf.measure.residual_sources`): beyond the support's edge too.
MISFIT_REACH = 1.5

#: Columns every photometry table holds (the ``bfpsf photometry`` contract), plus photutils'.
PHOTOMETRY_COLUMNS = ["x_fit", "y_fit", "flux_fit", "flux_err", "flags"]


def _initial_positions(image_e, detection_threshold, lines, cosmic_rays):
    """Every source (`bfpsf.measure.neighbours.sources_with_companions`: the detections and the
    companions a merged segment hides, flagged ``BLENDED``; ``lines`` left out, cosmic rays
    filled where ``cosmic_rays``, no source of their own) as photutils' initial table. Fitted
    as one, a close pair gives one star with both fluxes (a dense field: -250 mmag). The
    detection's ``COSMIC_RAY`` is not carried: photometry's own says a ray's pixels were
    left out of the fit. Returns the table and the cosmic rays' pixels."""
    sources = sources_with_companions(image_e, threshold=detection_threshold, lines=lines,
                                      cosmic_rays=cosmic_rays)
    table = Table()
    table["x_init"], table["y_init"] = sources["x"], sources["y"]
    table["flux_init"] = sources["flux_e"]
    table["source_flags"] = np.asarray(sources["flags"]) & ~SourceFlag.COSMIC_RAY
    return table, ray_mask(sources, image_e.shape)


@contextlib.contextmanager
def _quiet():
    """photutils' warning that some fits did not converge is not passed on: most fits here
    are refitted (with the model's weights, with the sources found in a residual, without the
    cross terms), and a new user read it beside a table whose every flag was 0; the final
    fits' flags are said once (`psf_photometry`). Nor is the model's warning of a flux beyond
    its first-order range met on the fitter's way (-6e7 e- on a satellite trail, printed 8
    times with photutils' source lines): the final fluxes beyond it are said once."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="One or more fit",
                                category=AstropyUserWarning)
        warnings.filterwarnings("ignore", message="flux .* is beyond the first-order BF model",
                                category=BFPSFWarning)
        # photutils' reduced chi2 of a fit with no degree of freedom (chi2 / 0, inf in the
        # table), which a new user read on stderr beside bfpsf's summary
        warnings.filterwarnings("ignore", message="divide by zero", category=RuntimeWarning,
                                module=r"photutils\.")
        yield


def _model_variance(sky, stars_e, read_noise_e):
    """The variance of every pixel the sky and the fitted stars' models predict, e-^2."""
    return np.clip(sky.image(), 0.0, None) + np.clip(stars_e, 0.0, None) + read_noise_e**2


def _glow(psf, table, shape):
    """The light of the fitted stars beyond the PSF support (the PSF's wing model), e-."""
    wings = WingModel(tuple(psf.wing_coefficients), psf.wing_tail_power,
                      psf.wing_half_size or psf.half_size, 0.0, 0.0, 0)
    return wing_image(wings, np.asarray(table["x_fit"], float),
                      np.asarray(table["y_fit"], float), np.asarray(table["flux_fit"], float),
                      shape)


#: Largest group of stars fitted together that `psf_photometry` accepts: photutils fits a
#: group as one model with 3 parameters per star, so a larger one is slow and poorly conditioned.
MAX_GROUP_SIZE = 25


def _check_groups(psf, fit_shape, group_separation, init):
    """Refuse a fit box (or group separation) so wide against the star spacing that many stars
    would be fitted as one group: slow, and biased with flags 0."""
    if len(init) <= MAX_GROUP_SIZE:
        return
    side = float(np.max(np.atleast_1d(default_fit_shape(psf) if fit_shape is None
                                      else fit_shape)))
    separation = side if group_separation is None else float(group_separation)
    xy = np.column_stack([np.asarray(init["x_init"], float), np.asarray(init["y_init"], float)])
    pairs = cKDTree(xy).query_pairs(separation, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xy),) * 2)
    _, labels = connected_components(graph, directed=False)
    largest = int(np.bincount(labels).max())
    if largest > MAX_GROUP_SIZE:
        outliers = describe_outlying_nodes(*outlying_nodes(psf)) if fit_shape is None else ""
        if outliers:
            # the image is not to blame (a new user's 31 px box came from one node of 10.2 px)
            cause = (f"the PSF sets that fit shape from its {outliers}: a node fitted from too "
                     "few stars; refit the PSF with fewer --grid nodes or give a fit shape")
        else:
            cause = ("the stars are closer than that (give a smaller fit shape), or the "
                     "detection took noise for stars (a blank image, or a sky given too low: "
                     "check the image and --background)")
        msg = (f"fit shape {side:g} px (group separation {separation:g} px) puts {largest} of "
               f"the {len(xy)} stars in one group fitted together (at most {MAX_GROUP_SIZE}): "
               + cause)
        raise BFPSFValueError(msg, side)


def psf_photometry(image_e, psf, *, positions=None, read_noise_e=None, background_e=None,
                   fit_shape=None, group_separation=None,
                   detection_threshold=DETECTION_THRESHOLD, weights="model", cross_terms=True,
                   linearity_c_per_1e5=None, flux_correction=None, wings=None,
                   residual_passes=RESIDUAL_PASSES, saturation_e=None, mask_lines=True,
                   mask_cosmic_rays=True,
                   sky_degree="auto", **kwargs):
    """Fit every star of an image with the flux-dependent PSF.

    Parameters
    ----------
    image_e : array_like [y, x] or bfpsf.measure.prepare.PreparedImage
        Image in electrons (the BF term needs charge), sky included, prepared here
        (``background_e``, ``linearity_c_per_1e5``); or an image prepared already
        (`bfpsf.measure.prepare.prepare_image`: its sky and linearity are used as they are).
    psf : FluxDependentPSF or photutils PSF model
        PSF model in electrons (``flux_unit='electron'``; an ADU model is refused); or a
        static photutils model, for comparison.
    positions : astropy.table.Table or (N, 2) array_like, optional
        Initial ``x_init``, ``y_init`` (and optionally ``flux_init``) or (x, y) pairs, pixels;
        default: detected with `bfpsf.measure.sources.measure_sources`.
    read_noise_e : float or None, optional
        Read noise, e- rms, for the pixel errors (Poisson noise of the image is included).
        Default None: from the image's sky pixels, `image_read_noise` (their scatter about
        the fitted sky less its Poisson variance: what the sky model misses counts as noise,
        and is said when it exceeds the pixel-to-pixel noise), as `bfpsf photometry` does
        without a calibration or where its PTC left the read noise undetermined.
    background_e : float, optional
        A known sky level, e- per pixel, subtracted before fitting; default the sky surface
        of the image (`bfpsf.measure.sky.estimate_sky`: a plane, curved where the sky is,
        beyond the masked sources, per image; its degree ``sky_degree``, default 'auto'),
        through the one image preparation of every command (`bfpsf.measure.prepare.
        prepare_image`, which also undoes the PSF's linearity correction,
        ``psf.linearity_c_per_1e5``, of a refined calibration).
    fit_shape : int, optional
        Fit box, pixels (odd); default about 3 FWHM.
    group_separation : float, optional
        Stars closer than this (pixels) are fitted together; default the fit box.
    detection_threshold : float, optional
        Detection threshold in background rms when ``positions`` is None. Default 5.
    weights : {'model', 'data'}, optional
        Pixel variances of the fit. ``'model'`` (default): a first fit with the variance of
        the pixel values, then the final fit with the variance of the fitted model,
        ``background_e + model + read_noise_e**2`` (at least 1 e-**2), so the weights do not
        depend on each pixel's own noise, each group on the data minus the first fit's models
        of every other star (a neighbour outside the group leaves its wings in the fit box
        otherwise: +0.82 against +0.43 mmag bright-minus-faint in a dense field). ``'data'``: one fit with the variance of the pixel
        values, ``max(image_e, 0) + read_noise_e**2``; on noisy images this under-estimates
        every flux by about one e- per fitted pixel (a pixel that fluctuates low gets more
        weight, Neyman's chi-square bias): -1.0e-3 (1.1 mmag) for a 3 ke- peak star on a
        1000 e- sky, -1.2 mmag for a sky-free 5 ke- peak spot.
    cross_terms : int or bool, optional
        Refits of the blended stars (``group_size`` > 1) that remove the BF of the stars'
        charge on each other, which no single-star model carries (G15 eq. scrambling_model is
        quadratic in the summed charge): the cross terms are computed from the previous fit
        and subtracted from the data. Default True (one refit, the effect being second order
        in a); 0 or False: none. Only for a `FluxDependentPSF`.
    linearity_c_per_1e5 : float, optional
        Linearity correction undone on input (`bfpsf.measure.prepare.prepare_image`); default the
        PSF's own (``psf.linearity_c_per_1e5``, 0 for a photutils model).
    flux_correction : float, optional
        The total flux over the flux the PSF holds (the light beyond its support), applied to
        ``flux_fit`` and ``flux_err``; default the product's own at each star
        (``flux_correction_at``, measured when it was fitted; the product is the PSF, or
        ``wings`` for a photutils model such as a static P0,
        `bfpsf.interop.photutils.static_image_psf`), 1 for a photutils model alone.
    wings : BFPSFModel, optional
        The model whose wing profile gives the stars' light beyond the support, subtracted with
        the sky of the final fit, and whose P(F) the stars are compared with (`unlike_psf`);
        default the PSF itself when it is a bfpsf model, none for a photutils model: give the
        product's to compare a static P0 with the same sky and flags (without it, a static P0
        took the Airy stars' wings into the sky, 304-305 e- against the true 300 and P(F)'s
        299, its faint stars 2-4 mmag too faint; and flagged no pair fitted as one).
    residual_passes : int, optional
        With detected stars (``positions`` None): searches of the residual of the fit for the
        stars detection missed (`bfpsf.measure.residual_sources`: a companion on a bright
        star's wing, faint stars of a crowded field), each followed by a fit of every star
        with the ones it found, flagged ``IN_RESIDUAL``; default `RESIDUAL_PASSES`, 0: none.
    saturation_e : float, optional
        Saturation level, e- (sky included): no source is sought within the PSF's support of
        a pixel at or above it (a clipped core is no model's; 38 saturated stars left 38
        peaks beside them).
    mask_lines : bool, optional
        With detected stars: the pixels of trails and hot columns
        (`bfpsf.measure.line_features.line_mask`) are left out of detection and of every
        fit, and a star whose fit box holds some is flagged ``ON_LINE`` (default True).
    mask_cosmic_rays : bool, optional
        Cosmic rays found in the fit's residual (`bfpsf.measure.cosmic_rays`) are left out
        of a refit of the stars whose fit box they touch, flagged ``COSMIC_RAY`` (default
        True).
    **kwargs
        Passed to `photutils.psf.PSFPhotometry`.

    Returns
    -------
    astropy.table.Table
        photutils' result table: ``x_fit``, ``y_fit`` (pixels), ``flux_fit``, ``flux_err``
        (e-; the star's total flux: the flux P0 holds times ``psf.flux_correction_at`` the
        star, the light beyond its support; ``flux_err`` leaves out its error, a scale common
        to every star, as the gain's is), ``sky_e`` (the sky subtracted under each star, e-
        per pixel), ``flags`` (`photutils.psf.decode_psf_flags`) and photutils' other
        columns; ``meta['flux_correction']``, ``_err`` and ``_slope``: the correction at the
        image's centre, its error (None when unknown or given) and its change per pixel;
        ``meta['background_e']`` the subtracted sky, ``meta['weights']`` the variance
        model, ``meta['cross_term_refits']`` the refits made,
        ``meta['empirical']`` the EMPIRICAL term the model applied (its record, label
        ``'empirical'``; None without one).
        ``source_flags``: `bfpsf.measure.sources.SourceFlag` bits, those of the detection here
        (or of a ``positions`` table with a ``source_flags`` column; ``BLENDED``: a neighbour
        within the blend radius; ``IN_RESIDUAL``: found in a fit's residual, ``residual_passes``)
        and, for a bfpsf model, ``UNLIKE_PSF``: the fitted star, its
        neighbours' models subtracted, is larger or more elongated than the PSF at its flux
        (two stars detection did not split; `bfpsf.measure.psf_likeness`).
    """
    prepared = image_e if isinstance(image_e, PreparedImage) else None
    image = np.asarray(image_e.image_e if prepared else image_e, dtype=float)
    if image.ndim != 2:
        msg = f"image must be 2-D [y, x], got shape {image.shape}"
        raise BFPSFInputError(msg, image.shape)
    finite = np.isfinite(image)
    if not finite.any():
        msg = "image has no finite pixel"
        raise BFPSFInputError(msg, image.shape)
    if read_noise_e is not None and (read_noise_e < 0 or not np.isfinite(read_noise_e)):
        msg = f"read_noise_e must be a finite number >= 0 e- or None, got {read_noise_e!r}"
        raise BFPSFValueError(msg, read_noise_e)
    if getattr(psf, "flux_unit", "electron") != "electron":
        msg = (f"psf_photometry fits images in e- but the PSF is in {psf.flux_unit!r}: pass "
               "psf.with_flux_unit('electron') and the image times the gain")
        raise BFPSFValueError(msg, psf.flux_unit)
    if weights not in ("model", "data"):
        msg = f"weights must be 'model' or 'data', got {weights!r}"
        raise BFPSFValueError(msg, weights)
    bfpsf_model = isinstance(psf, BFPSFModel)
    if linearity_c_per_1e5 is None:
        linearity_c_per_1e5 = psf.linearity_c_per_1e5 if bfpsf_model else 0.0
    if prepared is None:
        prepared = prepare_image(image, background_e=background_e, sky_degree=sky_degree,
                                 linearity_c_per_1e5=linearity_c_per_1e5)
    image, sky = prepared.image_e, prepared.sky
    scatter = check_sky(prepared)
    noise_source = "given"
    if read_noise_e is None:
        read_noise_e, noise_source = image_read_noise(prepared), "image"
    else:
        check_read_noise(prepared, float(read_noise_e))
    variance = np.clip(np.where(finite, image, 0.0), 0.0, None) + read_noise_e**2
    error = np.sqrt(np.where(variance > 0, variance, 1.0))
    data = prepared.sky_subtracted
    # trails and hot columns: left out of detection and of every fit
    lines = resolve_lines(positions is None and bool(mask_lines), data, detection_threshold)
    mask = ~finite | lines
    rays = False  # the cosmic rays detection found (none where the positions are given)
    if positions is None:
        init, rays = _initial_positions(np.where(finite, data, 0.0), detection_threshold,
                                        lines, bool(mask_cosmic_rays))
    elif isinstance(positions, Table):
        init = positions
    else:
        xy = np.atleast_2d(np.asarray(positions, dtype=float))
        if xy.ndim != 2 or xy.shape[1] != 2:
            msg = f"positions must be an (N, 2) array of (x, y), got shape {xy.shape}"
            raise BFPSFInputError(msg, xy.shape)
        init = Table({"x_init": xy[:, 0], "y_init": xy[:, 1]})
    if len(init) == 0:
        msg = "no star to fit (no detection and no positions given)"
        raise BFPSFInputError(msg, 0)
    _check_groups(psf, fit_shape, group_separation, init)
    source_flags = None
    if "source_flags" in init.colnames:  # measure_sources' flags (blended, ...), carried over
        source_flags = np.asarray(init["source_flags"], dtype=np.int64)
        init = init.copy()
        init.remove_column("source_flags")
    photometry = make_psf_photometry(psf, fit_shape=fit_shape, group_separation=group_separation,
                                     **kwargs)
    mask = mask if mask.any() else None
    with _quiet():
        result = photometry(data, mask=mask, error=error, init_params=init)
    rows = None  # every star; then those near the sources found in the residual
    n_lost = 0
    # how far a star's misfit reaches: its wings beyond the support too (a 3e6 e- Moffat's
    # left peaks 13 px from its centre, beyond a 12 px support)
    half_width = (getattr(psf, "half_size", None)
                  or float(np.max(np.atleast_1d(photometry.fit_shape))) / 2)
    reach = MISFIT_REACH * half_width
    # the support about every saturated pixel: a clipped core is no model's (a fit's flux of
    # it too low to tell its misfit by: 10 peaks of 1e4 e- 6-8 px from 3e6 e- stars)
    clipped = None if saturation_e is None else ndimage.binary_dilation(
        np.where(finite, image, 0.0) >= saturation_e, structure=np.ones((3, 3), dtype=bool),
        iterations=int(half_width) + 1)
    sharpness = (psf_sharpness(photometry.psf_model, *((np.array(data.shape[::-1]) - 1) // 2))
                 if mask_cosmic_rays else None)  # the PSF's own, once
    def cosmic_rays_in(stars):
        """The cosmic rays in the residual of the stars' models (none unless masked)."""
        if not mask_cosmic_rays:
            return np.zeros(data.shape, dtype=bool)
        return cosmic_ray_mask(
            data - stars, _model_variance(sky, stars, read_noise_e), stars,
            read_noise_e=read_noise_e, excluded=lines if clipped is None else clipped | lines,
            sharpness=sharpness)

    box = float(np.max(np.atleast_1d(photometry.fit_shape))) / np.sqrt(2.0)  # half diagonal
    cosmic = np.zeros(data.shape, dtype=bool)
    for residual_pass in range(1 + (int(residual_passes) if positions is None else 0)):
        if residual_pass:  # the stars detection missed, in the residual of the last fit
            stars = model_image(photometry, result, data.shape)
            # the cosmic rays on the stars first, which detection cannot tell from them: the
            # stars they hit refitted without them (a hit brighter than a star's peak pulls
            # its fit aside, and the residual then holds the star: a new user's stars of
            # 8e3-4e4 e- hit 2-3 px from their centres came out as two rows each)
            early = cosmic_rays_in(stars)
            cosmic = cosmic | early
            with _quiet():
                result, mask, pulled = refit_pulled(photometry, psf, data, mask, error, init,
                                                    result, early, box)
            if pulled:
                stars = model_image(photometry, result, data.shape)
            # (nor are the cosmic rays detection found sources: a new user's 40 hits and 15
            # tracks on the sky had come back as 35 stars "missed by detection")
            excluded = lines | rays | cosmic
            found = residual_sources(
                data - stars, _model_variance(sky, stars, read_noise_e),
                np.column_stack([result["x_fit"], result["y_fit"]]),
                threshold=detection_threshold, model_e=stars, known_flux=result["flux_fit"],
                reach=reach, support=getattr(psf, "half_size", None),
                excluded=excluded if clipped is None else clipped | excluded)
            if not len(found):
                break
            source_flags = np.r_[np.zeros(len(init), np.int64) if source_flags is None
                                 else source_flags, found["source_flags"]]
            init = vstack([init, found[init.colnames]])
            previous, rows = with_found(result, found, photometry, psf)
            if residual_pass == 1:  # their fits and their neighbours' kept near their start
                photometry = make_psf_photometry(
                    psf, fit_shape=fit_shape, group_separation=group_separation,
                    **{"xy_bounds": COMPANION_SEPARATION, **kwargs})
            with _quiet():
                result = merged(result, fit_without_neighbours(
                    photometry, psf, data, mask, error, init, previous, rows), rows)
            # a found source its fit lost (merged into a neighbour, no flux) is not a star
            init, source_flags, rows, result, lost = without_lost(
                init, source_flags, rows, result, detection_threshold + 3.0)
            n_lost += lost
        if weights == "model":
            # Refit with the variance the fitted stars and the sky predict: weights computed
            # from the noisy pixels themselves bias every flux low (see ``weights``). The
            # 1 e-**2 floor keeps pixels beyond the PSF support of a sky-free image finite.
            stars = model_image(photometry, result, data.shape)
            wing_model = psf if (bfpsf_model and wings is None) else wings
            if (wing_model is not None and max(wing_model.wing_coefficients, default=0.0) > 0
                    and prepared.glow_e is None):
                # the sky again, beyond the fitted stars: their models within the support
                # and the glow of their wings beyond it (which is subtracted with it): the
                # sky is what is left beyond their total-flux model
                prepared = prepared.with_glow(_glow(wing_model, result, data.shape), stars)
                sky, data = prepared.sky, prepared.sky_subtracted
            error = np.sqrt(np.maximum(_model_variance(sky, stars, read_noise_e), 1.0))
            with _quiet():
                if rows is None or rows.any():
                    result = merged(result, fit_without_neighbours(
                        photometry, psf, data, mask, error, init, result, rows), rows)
            if residual_pass:
                init, source_flags, rows, result, lost = without_lost(
                    init, source_flags, rows, result, detection_threshold + 3.0)
                n_lost += lost
    # cosmic rays in the residual: the stars whose fit box they touch refitted without them
    stars = model_image(photometry, result, data.shape)
    cosmic = cosmic | cosmic_rays_in(stars)
    hit = near_lines(cosmic, result["x_fit"], result["y_fit"], box)
    on_ray = near_lines(cosmic, result["x_fit"], result["y_fit"], 1.5)  # a cosmic ray itself
    if hit.any():
        mask = cosmic if mask is None else mask | cosmic
        with _quiet():
            result = merged(result, fit_without_neighbours(
                photometry, psf, data, mask, error, init, result, hit), hit)
    n_cross = 0
    if cross_terms and bfpsf_model and "group_size" in result.colnames:
        blended = np.asarray(result["group_size"]) > 1
        for _ in range(int(cross_terms) if blended.any() else 0):
            # Refit the blended stars on the data minus their BF on each other.
            cross = cross_term_image(psf, result, data.shape)
            with _quiet():
                refit = fit_without_neighbours(photometry, psf, data - cross, mask, error,
                                                init, result, blended)
            for name in refit.colnames:
                if name in result.colnames and name not in ("id", "group_id", "group_size"):
                    result[name][blended] = refit[name]
            n_cross += 1
    limit = getattr(psf, "first_order_flux", np.inf)
    beyond = int(np.sum(np.asarray(result["flux_fit"], dtype=float) > limit))
    if beyond:
        log.warning("%d of %d fitted fluxes are beyond the first-order BF model (P(F) goes "
                    "negative above %.3g for these boundary shifts)", beyond, len(result), limit)
    unconverged = int(np.sum((np.asarray(result["flags"], dtype=int) & NO_CONVERGENCE) > 0))
    if unconverged:
        log.warning("%d of %d fits did not converge (flag value %d in the flags column)",
                    unconverged, len(result), NO_CONVERGENCE)
    result["source_flags"] = (np.zeros(len(result), dtype=np.int64) if source_flags is None
                              else source_flags[np.asarray(result["id"], dtype=int) - 1])
    # the product (the model, or a static P0's ``wings``): stars unlike its P(F) are flagged
    product = psf if bfpsf_model else wings
    if isinstance(product, BFPSFModel):
        if hit.any() or n_cross:  # refitted since the models were drawn for the cosmic rays
            stars = model_image(photometry, result, data.shape)
        residual = np.where(lines | cosmic, 0.0, data - stars)
        unlike = unlike_psf(residual, result["x_fit"], result["y_fit"], result["flux_fit"],
                            product, max(float(sky.level), 0.0) + float(read_noise_e)**2)
        unlike |= misfit_outliers(result["reduced_chi2"], result["flux_fit"]) & ~hit
        result["source_flags"] |= np.where(unlike | on_ray, SourceFlag.UNLIKE_PSF, 0)
    on_line = near_lines(lines, result["x_fit"], result["y_fit"], box)  # within the fit box
    result["source_flags"] |= (np.where(on_line, SourceFlag.ON_LINE, 0)
                               | np.where(hit, SourceFlag.COSMIC_RAY, 0))
    # the total flux: the light beyond P0's support (measured when the PSF was fitted), at
    # each star's place (a grid's changes across the image)
    given = flux_correction is not None or not isinstance(product, BFPSFModel)
    correction = (np.float64(1.0 if flux_correction is None else flux_correction) if given
                  else product.flux_correction_at(np.asarray(result["x_fit"], float),
                                                  np.asarray(result["y_fit"], float)))
    if not given:  # a failed fit (no position) keeps its NaN flux, at the image's correction
        correction = np.where(np.isfinite(correction), correction, product.flux_correction)
    correction_err = (None if given or not np.isfinite(product.flux_correction_err)
                      else float(product.flux_correction_err))  # given: unknown here
    if not (np.all(np.isfinite(correction)) and np.all(correction > 0)):
        msg = f"flux_correction must be a positive finite number, got {flux_correction!r}"
        raise BFPSFValueError(msg, flux_correction)
    result["flux_fit"] = result["flux_fit"] * correction
    result["flux_err"] = result["flux_err"] * correction
    result["sky_e"] = sky(np.asarray(result["x_fit"], float), np.asarray(result["y_fit"], float))
    result.meta["flux_correction"] = float(correction if given else product.flux_correction)
    result.meta["flux_correction_err"] = correction_err
    result.meta["flux_correction_slope"] = [0.0, 0.0] if given else list(
        product.flux_correction_slope)
    result.meta["background_e"] = sky.level
    # the slope per pixel is what `bfpsf psf` reports (``sky_slope``), and the coefficients say
    # what they multiply: a new user compared the two
    result.meta["sky"] = {"method": sky.method, "degree": sky.kind,
                          "coefficients": list(sky.coefficients),
                          "coefficients_of": sky.coefficients_of,
                          "slope": list(sky.slope), "rms_e": sky.rms}
    result.meta["cross_term_refits"] = n_cross
    # sources found in a fit's residual (IN_RESIDUAL), and those whose fit failed
    result.meta["residual_sources"] = {"found": int(np.sum(
        (result["source_flags"] & SourceFlag.IN_RESIDUAL) > 0)), "lost": n_lost}
    result.meta["weights"] = weights
    result.meta["read_noise_e"] = float(read_noise_e)
    result.meta["read_noise_source"] = noise_source
    # the sky pixels' scatter about the fitted sky over their pixel-to-pixel variance
    result.meta["sky_scatter"] = scatter
    result.meta["flux_unit"] = "electron"
    result.meta["line_pixels"] = int(lines.sum())
    result.meta["cosmic_ray_pixels"] = int(cosmic.sum())
    # the EMPIRICAL term of a refined calibration the model applied (issue 22), labelled
    term = getattr(psf, "empirical", None) if bfpsf_model else None
    result.meta["empirical"] = None if term is None else term.to_dict()
    return result
