"""Source measurement: detection, stamps, sky, peak, flux and adaptive moments.

The star table feeding the size-colour correction and the brighter-fatter slopes (G15
sections 3.2-3.3). Sources are detected with photutils image segmentation on the smoothed,
sky-subtracted image; each gets a stamp, the sky of every command under it (the surface of
`bfpsf.measure.sky.estimate_sky`, beyond the masked sources), its peak and aperture flux in
electrons, and adaptive moments (`bfpsf.moments.adaptive`). Saturated, blended and edge
sources are flagged, never dropped.
"""

import warnings

import numpy as np
from astropy.convolution import convolve
from astropy.stats import gaussian_fwhm_to_sigma, sigma_clipped_stats
from astropy.table import Table
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import BFPSFInputError, BFPSFValueError, integer_at_least
from ..model.nanfill import harmonic_fill
from ..moments.adaptive import adaptive_moments_batch
from ..moments.moment_errors import moment_errors
from ..moments.result import MomentsFlag
from ..moments.shapes import distortion
from ..resources import check_pixels
from .cosmic_rays import image_cosmic_rays
from .line_features import near_lines, resolve_lines
from .neighbour_light import neighbour_light
from .source_flags import SourceFlag, source_flag_string
from .sky import estimate_sky
from .smoothing import detection_kernel

__all__ = ["SourceFlag", "measure_sources", "ray_mask", "sky_level",
           "source_flag_string", "aperture_fraction", "model_flux", "STAR_COLUMNS",
           "DETECTION_THRESHOLD", "LINE_REACH"]

#: columns every star table holds (the ``bfpsf measure`` contract)
STAR_COLUMNS = ["x", "y", "flux_e", "peak_e", "mxx", "myy", "mxy", "sigma_x", "sigma_y", "iq",
                "e1", "e2", "flags"]


def sky_level(image, *, maxiters=10):
    """Global sky level of an image and its noise per pixel.

    The 3-sigma clipped median and standard deviation of the finite pixels
    (`astropy.stats.sigma_clipped_stats`, at most ``maxiters`` clipping iterations): stars,
    cosmic rays and hot pixels are clipped, NaN and inf pixels left out. The wings of the stars are not
    clipped, so a dense field of bright stars biases the level high; pass the known sky where
    it matters (``--background`` of ``bfpsf psf``, ``photometry`` and ``diagnose``).

    Parameters
    ----------
    image : array_like
        Image, e- per pixel (or ADU: the level and noise come in the image's unit).
    maxiters : int, optional
        Clipping iterations at most. Default 10 (`measure_sources`' detection pedestal keeps
        astropy's 5: 10 would move its detections and centroids).

    Returns
    -------
    level : float
        Sky level, e- per pixel.
    rms : float
        Clipped standard deviation, e- per pixel: the noise of the sky, read noise included.

    Raises
    ------
    BFPSFInputError
        If the image has no finite pixel.
    """
    pixels = np.asarray(image)
    pixels = pixels[np.isfinite(pixels)]
    if pixels.size == 0:
        msg = "image has no finite pixel: no sky level"
        raise BFPSFInputError(msg, np.shape(image))
    _, level, rms = sigma_clipped_stats(pixels, sigma=3.0, maxiters=maxiters)
    return float(level), float(rms)


def _cutouts(image, x_centres, y_centres, size):
    """Stamps of ``size`` around the nearest pixels, NaN outside the image; and their origins."""
    ny, nx = image.shape
    half = size // 2
    ix = np.floor(np.asarray(x_centres) + 0.5).astype(int) - half
    iy = np.floor(np.asarray(y_centres) + 0.5).astype(int) - half
    padded = np.pad(image, size, mode="constant", constant_values=np.nan)
    rows = (iy + size)[:, None] + np.arange(size)[None, :]
    cols = (ix + size)[:, None] + np.arange(size)[None, :]
    stamps = padded[rows[:, :, None], cols[:, None, :]]
    crosses = (ix < 0) | (iy < 0) | (ix + size > nx) | (iy + size > ny)
    return stamps, ix, iy, crosses


def _deblended(smoothed, segments, labels, n_pixels):
    """``segments`` with the segments ``labels`` split into their sources (photutils'
    multi-thresholding and watershed, on the smoothed image as detection)."""
    from photutils.segmentation import deblend_sources

    with warnings.catch_warnings():
        # photutils says when a segment cannot be split at its contrast: flagged instead
        warnings.simplefilter("ignore", UserWarning)
        return deblend_sources(smoothed, segments, n_pixels, labels=labels,
                               progress_bar=False)


def _segments_with_several_peaks(smoothed, segment_map, min_level, fwhm):
    """Labels of segments holding more than one local maximum of the smoothed image."""
    size = 2 * int(np.ceil(fwhm)) + 1
    local_max = (smoothed == ndimage.maximum_filter(smoothed, size=size)) & (
        smoothed >= min_level) & (segment_map > 0)
    # a flat (saturated) top is one peak: count connected groups of maxima
    groups, n_groups = ndimage.label(local_max, structure=np.ones((3, 3)))
    if n_groups == 0:
        return np.array([], dtype=int)
    group_label = ndimage.maximum(segment_map, groups, index=np.arange(1, n_groups + 1))
    labels, counts = np.unique(np.asarray(group_label, dtype=int), return_counts=True)
    return labels[counts > 1]


def _empty_table(colour_columns):
    names = ["id", *STAR_COLUMNS[:-1], "gauss_flux_e", "background_e", "background_rms_e",
             "mxx_err", "myy_err", "mxy_err", "sigma_x_err", "sigma_y_err", "iq_err",
             "e1_err", "e2_err", "neighbour_size_bias", "n_iter", "flags", "flag_string",
             *colour_columns]
    dtypes = [int] + [float] * (len(names) - 4 - len(colour_columns)) + [int, int, str] \
        + [float] * len(colour_columns)
    return Table(names=names, dtype=dtypes)


#: Default detection threshold of every bfpsf command and function, in units of the RMS of the
#: smoothed background-subtracted image.
DETECTION_THRESHOLD = 5.0
#: A source this many of its sigmas from a trail's or a hot column's pixels is ``ON_LINE``
#: (its adaptive moments' weight reaches about so far).
LINE_REACH = 4.0


def _aperture_flux(stamps, radius2, sigma, aperture_nsigma):
    """Sum of each stamp within ``aperture_nsigma`` adaptive sigmas of its centroid (pixel
    centres; 2 px where sigma failed): ``flux_e`` of `measure_sources`."""
    radius = aperture_nsigma * np.where(np.isfinite(sigma), sigma, 2.0)
    inside = (radius2 <= radius[:, None, None]**2) & np.isfinite(stamps)
    return np.sum(np.where(inside, stamps, 0.0), axis=(1, 2))


def aperture_fraction(psf, *, aperture_nsigma=5.0, phases=4, size=32):
    """Fraction of a star's total flux that the ``flux_e`` aperture of `measure_sources` holds,
    from a PSF model: its aperture correction.

    ``flux_e`` sums the pixels within ``aperture_nsigma`` adaptive sigmas of the centroid,
    which misses the PSF's outer wings (0.8 % for a Moffat of beta 3.5 and FWHM 3.45 px at
    5 sigma). A model of total flux F evaluated at ``flux_e`` is evaluated 0.8 % too faint,
    and its BF term 0.8 % too weak; ``flux_e / aperture_fraction(psf)`` is the total flux.

    Parameters
    ----------
    psf : FluxDependentPSF or GriddedFluxDependentPSF
        Any model with ``evaluate(x, y, flux, x_0, y_0)``; evaluated at unit flux, where its BF
        term is negligible, and a gridded one at the centre of its grid (the fraction changes
        by 0.1 % between FWHM 3 and 3.9 px).
    aperture_nsigma : float, optional
        As in `measure_sources` (default 5).
    phases : int, optional
        Sub-pixel phases per axis averaged over (default 4).
    size : int, optional
        Stamp side, pixels (default 32, `measure_sources`' default stamp).

    Returns
    -------
    float
    """
    offsets = (np.arange(phases) + 0.5) / phases - 0.5
    yy, xx = np.mgrid[:size, :size]
    centre = (size - 1) / 2.0
    # a PSF that varies over the field (GriddedFluxDependentPSF) is taken at its reference
    # position (the grid's centre)
    x_field, y_field = (value - centre for value in psf.reference_position)
    stamps = np.array([psf.evaluate(xx + x_field, yy + y_field, 1.0, centre + x_field + dx,
                                    centre + y_field + dy)
                       for dy in offsets for dx in offsets])
    moments = adaptive_moments_batch(stamps)
    radius2 = (xx[None] - moments.x[:, None, None])**2 + (yy[None] - moments.y[:, None, None])**2
    total = stamps.sum(axis=(1, 2))
    return float(np.mean(_aperture_flux(stamps, radius2, moments.sigma, aperture_nsigma) / total))


def model_flux(psf, flux_e, *, aperture_nsigma=5.0):
    """The flux F at which the PSF model is evaluated for stars whose `measure_sources`
    aperture fluxes are ``flux_e``, e-: the flux P0 holds in its support (``flux_e`` over the
    model's share of it in the aperture, `aperture_fraction`). The star's total flux is this
    times ``psf.flux_correction`` (the light beyond the support), as `psf_photometry`
    reports it."""
    return np.asarray(flux_e, dtype=float) / aperture_fraction(psf,
                                                              aperture_nsigma=aperture_nsigma)


def measure_sources(image_e, *, threshold=DETECTION_THRESHOLD, n_pixels=5, stamp_size=32, saturation=None,
                    colour=None, colour_columns=None, match_radius=2.0, sky=None,
                    detection_fwhm=3.0, blend_radius=None, deblend=True,
                    aperture_nsigma=5.0, lines=True, cosmic_rays=True):
    """Detect and measure the sources of an image in electrons.

    Parameters
    ----------
    image_e : array_like, shape (ny, nx)
        Image, electrons, background included or not; non-finite pixels are masked.
    threshold : float, optional
        Detection threshold in units of the RMS of the smoothed background-subtracted image
        (default 5).
    n_pixels : int, optional
        Minimum connected pixels above threshold (default 5).
    stamp_size : int, optional
        Side of the measurement stamps, pixels (default 32).
    saturation : float, optional
        Saturation level of the raw image, electrons: a pixel at or above it inside the
        3-sigma ellipse sets ``SATURATED`` (the source is kept and measured).
    colour : astropy.table.Table, optional
        Catalogue with ``x``, ``y`` (0-based pixels) and colour columns, matched to the
        detections by nearest position within ``match_radius`` pixels.
    colour_columns : list of str, optional
        Columns of ``colour`` passed through (default: every column but ``x`` and ``y``).
    match_radius : float, optional
        Pixels (default 2).
    sky : bfpsf.measure.sky.SkyModel, optional
        The sky under the sources, e- per pixel (a known sky: `SkyModel.constant`); default
        the sky surface of every command (`bfpsf.measure.sky.estimate_sky` of this image, a
        surface fitted beyond the masked sources). A local annulus per star was the sky here
        before: its median holds the star's own wings and its neighbours' (+5 e- for
        Kolmogorov x Airy stars of 3-100 ke- peaks, issue 21) and the noise of a few hundred
        pixels.
    detection_fwhm : float, optional
        FWHM of the Gaussian smoothing kernel for detection, pixels (default 3).
    blend_radius : float, optional
        A source with another detection closer than this is flagged ``BLENDED`` (default
        ``stamp_size / 2``).
    deblend : bool, optional
        Split a segment holding several peaks of the smoothed image (a peak is the maximum of
        a window of ``2 * detection_fwhm + 1`` pixels, at least 3 RMS above the threshold) into
        its sources (`photutils.segmentation.deblend_sources`, multi-thresholding and
        watershed), and flag ``BLENDED`` a segment that still holds several (default True). A
        bright star's wings stay above the threshold far out: 1.2e4 e- stars 14-24 px from
        1e6 e- Kolmogorov x Airy ones were merged into their segments, and a new user's pairs
        of 0.65-2.5e6 e- stars 22 px apart were one blended source.
    aperture_nsigma : float, optional
        ``flux_e`` is the background-subtracted sum within ``aperture_nsigma * iq`` of the
        centroid (default 5: 98 % of a Moffat beta 3.5 flux).
    lines : bool or ndarray of bool [y, x], optional
        Pixels of trails and hot columns, replaced by the sky before detection and
        measurement: True (default) finds them (`bfpsf.measure.line_features.line_mask`),
        an array gives them, False leaves none out. A source within `LINE_REACH` of its
        sigma from one is flagged ``ON_LINE``.
    cosmic_rays : bool or ndarray of bool [y, x], optional
        Pixels of cosmic rays, filled from their neighbours before detection and
        measurement: True (default) finds them against the image's own stars
        (`bfpsf.measure.cosmic_rays.image_cosmic_rays`; ``meta['cosmic_ray_pixels']``, -1
        where too few stars said how sharp a star is; ``meta['cosmic_rays']`` where,
        `ray_mask`), an array gives them, False leaves them in. A source within
        `LINE_REACH` of its sigma from one is flagged ``COSMIC_RAY``.

    Returns
    -------
    astropy.table.Table
        One row per detection: ``id``, ``x``, ``y`` (0-based image pixels), ``flux_e``
        (aperture), ``peak_e`` (brightest background-subtracted pixel within 2 pixels of the
        centroid), ``gauss_flux_e`` (matched Gaussian), ``background_e``,
        ``background_rms_e`` (per pixel), ``mxx``, ``myy``, ``mxy`` (pixel^2), ``sigma_x``,
        ``sigma_y``, ``iq`` (pixels), ``e1``, ``e2`` (distortion,
        `bfpsf.moments.shapes.distortion`) and their ``*_err``, ``neighbour_size_bias``
        (`bfpsf.measure.neighbour_light`), ``n_iter``, ``flags``
        (`SourceFlag`), ``flag_string`` and the colour columns.
    """
    from photutils.segmentation import SourceCatalog, detect_sources
    from photutils.utils.exceptions import NoDetectionsWarning

    image = np.asarray(image_e, dtype=float)
    if image.ndim != 2:
        msg = f"image_e must be a 2-D array [y, x], got shape {image.shape}"
        raise BFPSFInputError(msg, image.shape)
    integer_at_least("stamp_size", stamp_size, 8, "pixels")
    if not threshold > 0:
        msg = f"threshold must be positive, got {threshold!r}"
        raise BFPSFValueError(msg, threshold)
    bad = ~np.isfinite(image)
    if bad.all():
        msg = "the image has no finite pixel"
        raise BFPSFInputError(msg, image.shape)
    if isinstance(cosmic_rays, np.ndarray) and cosmic_rays.any():
        image = harmonic_fill(image, cosmic_rays, isolated="nan")
    if colour is not None:
        for name in ("x", "y"):
            if name not in colour.colnames:
                msg = f"the colour table needs columns x and y, got {colour.colnames}"
                raise BFPSFInputError(msg, colour.colnames)
        if colour_columns is None:
            colour_columns = [name for name in colour.colnames if name not in ("x", "y")]
    colour_columns = list(colour_columns or [])

    # the sky surface of every command (a plane beyond the masked sources, bfpsf.measure.sky):
    # the detection pedestal (a sloped sky leaves the threshold where it is) and each source's
    # sky
    if sky is None:
        sky = estimate_sky(np.where(bad, np.nan, image))
    data = np.where(bad, np.nan, image - sky.image())
    kernel = detection_kernel(detection_fwhm)
    convolved = convolve(np.where(bad, 0.0, data), kernel, normalize_kernel=True)
    _, _, smooth_rms = sigma_clipped_stats(convolved[~bad], sigma=3.0)
    lines = resolve_lines(lines, data, threshold, smoothed=convolved, rms=smooth_rms)
    if lines.any():  # the sky in their place
        data = np.where(lines, 0.0, data)
        image = np.where(lines, sky.image(), image)
        convolved = convolve(np.where(bad, 0.0, data), kernel, normalize_kernel=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoDetectionsWarning)
        segments = detect_sources(convolved, threshold * smooth_rms, n_pixels, mask=bad)
    if segments is None:
        empty = _empty_table(colour_columns)
        empty.meta["line_pixels"] = int(lines.sum())
        given = isinstance(cosmic_rays, np.ndarray)
        empty.meta["cosmic_ray_pixels"] = int(np.sum(cosmic_rays)) if given else -1
        empty.meta["cosmic_rays"] = np.flatnonzero(cosmic_rays) if given else np.zeros(0, int)
        empty.meta["sky_degree"] = sky.kind
        return empty
    peak_level = (threshold + 3.0) * smooth_rms
    blended_labels = _segments_with_several_peaks(convolved, segments.data, peak_level,
                                                  detection_fwhm)
    if deblend and blended_labels.size:
        segments = _deblended(convolved, segments, blended_labels, n_pixels)
        # what deblending could not split stays flagged
        blended_labels = _segments_with_several_peaks(convolved, segments.data, peak_level,
                                                      detection_fwhm)
    catalog = SourceCatalog(np.where(bad, 0.0, data), segments, convolved_data=convolved,
                            mask=bad)
    x_detect = np.asarray(catalog.x_centroid, dtype=float)
    y_detect = np.asarray(catalog.y_centroid, dtype=float)
    n_sources = len(x_detect)

    background = np.asarray(sky(x_detect, y_detect), dtype=float)
    rms = sky.rms
    if not np.isfinite(rms):  # a known sky: the clipped scatter of the sky-subtracted pixels
        _, _, rms = sigma_clipped_stats(data[~bad & (segments.data == 0)], sigma=3.0)
    background_rms = np.full(n_sources, float(rms))

    check_pixels(n_sources * float(stamp_size) ** 2, copies=16, option=f"stamp size {stamp_size}",
                 what=f"measuring {n_sources} sources")
    raw_stamps, x_origin, y_origin, crosses = _cutouts(image, x_detect, y_detect, stamp_size)
    stamps = raw_stamps - background[:, None, None]
    labels, _, _, _ = _cutouts(segments.data.astype(float), x_detect, y_detect, stamp_size)
    own_label = np.asarray(catalog.label, dtype=float)[:, None, None]
    # pixels of other detected sources are masked (weight 0)
    weight = ~((labels > 0) & (labels != own_label))
    saturation_stamp = None if saturation is None else saturation - background
    moments = adaptive_moments_batch(
        stamps, centroid=np.stack([x_detect - x_origin, y_detect - y_origin], axis=1),
        weight=weight.astype(float), saturation=saturation_stamp)
    errors = moment_errors(np.where(weight, stamps, np.nan), moments,
                           background_variance=background_rms**2)

    flags = np.asarray(moments.flags, dtype=np.int64).copy()
    flags |= np.where(crosses, SourceFlag.STAMP_EDGE, 0)
    # the pixels beyond the image are STAMP_EDGE's, not bad pixels (a new user read
    # "bad_pixels|stamp_edge" on images without a bad pixel)
    # (the segment map's cutouts are NaN exactly beyond the image)
    bad_inside = np.any(~np.isfinite(raw_stamps) & np.isfinite(labels), axis=(1, 2))
    flags &= ~np.where(crosses & ~bad_inside, MomentsFlag.BAD_PIXELS, 0)
    if blend_radius is None:
        blend_radius = stamp_size / 2.0
    separation = np.hypot(x_detect[:, None] - x_detect[None, :],
                          y_detect[:, None] - y_detect[None, :])
    np.fill_diagonal(separation, np.inf)
    flags |= np.where(separation.min(axis=1, initial=np.inf) < blend_radius,
                      SourceFlag.BLENDED, 0)
    flags |= np.where(np.isin(np.asarray(catalog.label), blended_labels),
                      SourceFlag.BLENDED, 0)

    x_stamp = np.where(np.isfinite(moments.x), moments.x, x_detect - x_origin)
    y_stamp = np.where(np.isfinite(moments.y), moments.y, y_detect - y_origin)
    yy, xx = np.mgrid[:stamp_size, :stamp_size]
    radius2 = (xx[None] - x_stamp[:, None, None])**2 + (yy[None] - y_stamp[:, None, None])**2
    near = (radius2 <= 4.0) & np.isfinite(stamps)
    peak = np.max(np.where(near, stamps, -np.inf), axis=(1, 2))
    peak[~np.isfinite(peak)] = np.nan
    # neighbours' wings beyond their segments make a faint star large
    light_bias, lit = neighbour_light(stamps, radius2, np.asarray(moments.sigma, float),
                                      np.asarray(moments.flux, float), background_rms,
                                      errors["sigma_err"], usable=flags == 0)
    flags |= np.where(lit, SourceFlag.NEIGHBOUR_LIGHT, 0)
    sigma = np.asarray(moments.sigma, float)
    reach = LINE_REACH * np.where(np.isfinite(sigma), sigma,
                                  detection_fwhm * gaussian_fwhm_to_sigma)
    flags |= np.where(near_lines(lines, x_stamp + x_origin, y_stamp + y_origin, reach),
                      SourceFlag.ON_LINE, 0)
    if cosmic_rays is True:
        # found against the stars just measured, then measured again without them
        rays = image_cosmic_rays(data, rms, x_stamp + x_origin, y_stamp + y_origin, peak,
                                 flags == 0, sigma,
                                 excluded=bad | lines | _saturated(image, saturation),
                                 smoothed=convolved, detection_fwhm=detection_fwhm)
        if rays is not None and rays.any():
            return measure_sources(
                image, threshold=threshold, n_pixels=n_pixels, stamp_size=stamp_size,
                saturation=saturation, colour=colour, colour_columns=colour_columns,
                match_radius=match_radius, sky=sky, detection_fwhm=detection_fwhm,
                blend_radius=blend_radius, deblend=deblend, aperture_nsigma=aperture_nsigma,
                lines=lines, cosmic_rays=rays)
        cosmic_rays = np.zeros(data.shape, dtype=bool) if rays is None else rays
        ray_pixels = -1 if rays is None else 0
    else:
        cosmic_rays = np.asarray(cosmic_rays, dtype=bool)  # False: none
        ray_pixels = int(cosmic_rays.sum())
    flags |= np.where(near_lines(np.broadcast_to(cosmic_rays, data.shape), x_stamp + x_origin,
                                 y_stamp + y_origin, reach), SourceFlag.COSMIC_RAY, 0)
    aperture_flux = _aperture_flux(stamps, radius2, moments.sigma, aperture_nsigma)

    table = Table()
    table["id"] = np.asarray(catalog.label, dtype=int)
    table["x"] = x_stamp + x_origin
    table["y"] = y_stamp + y_origin
    table["flux_e"] = aperture_flux
    table["peak_e"] = peak
    table["gauss_flux_e"] = moments.flux
    table["background_e"] = background
    table["background_rms_e"] = background_rms
    table["mxx"] = moments.mxx
    table["myy"] = moments.myy
    table["mxy"] = moments.mxy
    table["sigma_x"] = moments.sigma_x
    table["sigma_y"] = moments.sigma_y
    table["iq"] = moments.sigma
    table["e1"], table["e2"] = distortion(moments.mxx, moments.myy, moments.mxy)
    table["mxx_err"] = errors["mxx_err"]
    table["myy_err"] = errors["myy_err"]
    table["mxy_err"] = errors["mxy_err"]
    table["sigma_x_err"] = errors["sigma_x_err"]
    table["sigma_y_err"] = errors["sigma_y_err"]
    table["iq_err"] = errors["sigma_err"]
    table["e1_err"] = errors["e1_err"]
    table["e2_err"] = errors["e2_err"]
    table["neighbour_size_bias"] = light_bias
    table["n_iter"] = np.asarray(moments.n_iter, dtype=int)
    if colour is not None:
        flags |= _match_colours(table, colour, colour_columns, match_radius)
    table["flags"] = flags
    table["flag_string"] = source_flag_string(flags).astype(str)
    for name, unit in (("x", "pix"), ("y", "pix"), ("flux_e", "electron"), ("peak_e", "electron"),
                       ("gauss_flux_e", "electron"), ("background_e", "electron"),
                       ("background_rms_e", "electron"), ("mxx", "pix2"), ("myy", "pix2"),
                       ("mxy", "pix2"), ("sigma_x", "pix"), ("sigma_y", "pix"), ("iq", "pix")):
        table[name].unit = unit
    table.meta["stamp_size"] = int(stamp_size)
    table.meta["threshold"] = float(threshold)
    table.meta["saturation_e"] = None if saturation is None else float(saturation)
    table.meta["line_pixels"] = int(lines.sum())
    table.meta["cosmic_ray_pixels"] = ray_pixels
    # where they are (flat indices of the image: `ray_mask`)
    table.meta["cosmic_rays"] = np.flatnonzero(np.broadcast_to(cosmic_rays, data.shape))
    table.meta["sky_degree"] = sky.kind
    return table


def ray_mask(table, shape):
    """The cosmic rays' pixels of a `measure_sources` table's image, [y, x] bool."""
    mask = np.zeros(shape, dtype=bool)
    mask.flat[np.asarray(table.meta.get("cosmic_rays", []), dtype=int)] = True
    return mask


def _saturated(image, saturation):
    """The pixels at or above ``saturation`` and those within 2 of them (none for None)."""
    if saturation is None:
        return np.zeros(image.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        return ndimage.binary_dilation(image >= saturation, iterations=2)


def _match_colours(table, colour, colour_columns, match_radius):
    """Add the colour columns by nearest match; returns NO_COLOUR flags."""
    positions = np.stack([np.asarray(colour["x"], float), np.asarray(colour["y"], float)], 1)
    distance, nearest = cKDTree(positions).query(
        np.stack([np.asarray(table["x"], float), np.asarray(table["y"], float)], 1))
    matched = np.isfinite(distance) & (distance <= match_radius)
    nearest = np.where(matched, nearest, 0)
    for name in colour_columns:
        if name not in colour.colnames:
            msg = f"colour column {name!r} is not in the colour table {colour.colnames}"
            raise BFPSFInputError(msg, name)
        values = np.asarray(colour[name], dtype=float)[nearest]
        table[name] = np.where(matched, values, np.nan)
    return np.where(matched, 0, SourceFlag.NO_COLOUR)
