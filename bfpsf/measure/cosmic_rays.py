"""Cosmic rays on the stars: found in the residual of the PSF fit and left out of a refit.

A cosmic ray is charge deposited in one exposure, sharper than any star: one to a few pixels
of hundreds to thousands of e-. Detection fits one far from the stars as a source (flagged
``unlike_psf``, `bfpsf.measure.psf_likeness`), but one that lands in a star's fit box went
into the star's flux unflagged: 40 hits of 300-3000 e- per pixel 1.5-5 px from the centres
of 120 Kolmogorov x Airy stars on 768^2 pixels read those stars -14 mmag at the median, 17
of them beyond 20 mmag and up to -360 (a 19 ke- star), with no flag.

L.A.Cosmic (van Dokkum 2001, `astroscrappy`) finds cosmic rays by their Laplacian against
the noise and against the image's fine structure. Run on the image itself it takes the
cores of undersampled stars for cosmic rays (33 core pixels of 120 stars of 1.6 px FWHM);
run on the residual of the PSF fit, with the variance the fitted stars and the sky predict,
the stars are gone from what it reads, whatever their sampling. A set of touching pixels is
kept as a cosmic ray's only where its brightest carries a tenth or more of the fitted model
there (`MODEL_SHARE`): at the core of a bright star, the PSF model's own misfit is sharp too
(and L.A.Cosmic grows it into the pixels beside it, whose own model is faint), and a deposit
below a tenth of the core's light moves the star's flux by less than a few mmag. And only
where that pixel is sharper than a star (`SHARPER` times the PSF's own at its sharpest
phase, `psf_sharpness`; how sharp a pixel is: its excess over the median of its 8
neighbours as a share of its 3 x 3, `excess_share`): the residual of two stars fitted as
one, a star itself, had been taken for a cosmic ray in 13 pairs of 17. The pixels kept,
grown by one (a track's faint edges), are left out of the refit of the stars whose fit box
they touch, and those stars are flagged ``cosmic_ray``.

Without a PSF model (`image_cosmic_rays`: `bfpsf.measure.sources.measure_sources`, so
``measure``, ``psf``'s star selection, photometry's detection and ``diagnose``), the search
reads the sky-subtracted image, and the sharpness a cosmic ray must exceed is the stars'
own (`star_sharpness`, at the `SHARPEST` percentile of the clean stars of a star's size
brighter than `STAR_PEAK` sky sigmas, clipped above: rays detected as stars). Two
searches: L.A.Cosmic's own, each connected set judged at its brightest pixel (a track 2 px
wide, whose pixels are not sharp against each other), and one with a low contrast over the
fine structure, which had hidden every ray near a bright core, each pixel judged alone,
`SHARPER` than a star within `CENTRE_REACH` of a centre and `WING_SHARPER` elsewhere (a
star's light is in the 3 x 3 sum, so a deposit on a bright wing that moves the star's
moments little is not sharp there). The pixels found are filled from their neighbours
(`bfpsf.model.nanfill.harmonic_fill`), and the stars with one within a few of their sigmas
are flagged ``cosmic_ray``, left out of the slopes and of P0. Not found: tracks on undersampled stars,
as sharp as their cores (docs/limitations.md).
"""

import astroscrappy
import numpy as np
from astropy.stats import mad_std, sigma_clip
from scipy import ndimage

from .smoothing import detection_kernel, smoothed_image

__all__ = ["cosmic_ray_mask", "image_cosmic_rays", "psf_sharpness",
           "star_sharpness", "excess_share", "SIGMA_CLIP", "OBJECT_LIMIT", "MODEL_SHARE",
           "SHARPER", "SHARP_SIGMA", "STAR_PEAK", "SHARPEST"]

#: L.A.Cosmic's detection limit, in noise sigma of the Laplacian (astroscrappy's default
#: 4.5: the noise of a crowded field of 80 stars on 320^2 pixels then put a few false ones in
#: the stars' fit boxes; a cosmic ray of 300 e- on 300 e- of sky is at 17).
SIGMA_CLIP = 6.0
#: L.A.Cosmic's iterations (its default 4: each finds the rays' neighbours the previous
#: cleaning left; two found as many ray pixels of tracks at half the time).
ITERATIONS = 2
#: L.A.Cosmic's contrast of a cosmic ray's Laplacian over the fine structure about it.
OBJECT_LIMIT = 5.0
#: A cosmic ray's pixel carries at least this share of the fitted stars' model there.
MODEL_SHARE = 0.1
#: A cosmic ray's brightest pixel holds this many times the share of its 3 x 3 pixels that
#: a star's holds at its sharpest (`psf_sharpness`).
SHARPER = 1.5
#: ... by this many of the pixel's noise.
SHARP_SIGMA = 3.0
#: Stars whose peak is this many sky sigmas or more give an image's star sharpness.
STAR_PEAK = 20.0
#: The percentile of their sharpness taken as the stars' sharpest (most stars lie off a
#: pixel's centre; a few hit by a cosmic ray are sharper).
SHARPEST = 90.0
#: ... and whose adaptive size is more than this share of the median of theirs.
STAR_SIZE = 0.75
#: Fewer such stars and an image is not searched without a PSF model.
MIN_STARS = 3
#: L.A.Cosmic's contrast over the fine structure on an image itself.
IMAGE_OBJECT_LIMIT = 0.5
#: Pixels from a star's centre within which a cosmic ray must be `SHARPER` than a star.
CENTRE_REACH = 1.5
#: Away from the centres a cosmic ray is this many times sharper than a star's core (a
#: companion's core on a bright star's wing, 1.05 times in a crowded field, is none).
WING_SHARPER = 1.25
#: Pixels of a set of them from those left out (a line) within which it is the line's.
LINE_GAP = 10
#: A centre is also a peak of the detection's smoothed image at this many of its noise
#: sigmas or more.
PEAK_SIGMA = 5.0
#: The (dy, dx) of a pixel's 3 x 3 window, the pixel itself at index 4.
_WINDOW = np.array([(dy, dx) for dy in range(-1, 2) for dx in range(-1, 2)])


def excess_share(values, rows, columns):
    """How sharp a pixel is: its excess over the median of its 8 neighbours as a share of its
    3 x 3 pixels (their positive parts), at each (row, column) of ``values`` (the 3 x 3 held
    within the image). On a smooth slope (a star's wing) the median is the slope's own level,
    so a cosmic ray there is as sharp as on the sky, its share diluted only by the light under
    it. Returns (share, the 3 x 3 sum)."""
    values = np.clip(np.nan_to_num(np.asarray(values, dtype=float)), 0.0, None)
    rows = np.clip(np.asarray(rows, dtype=int), 1, values.shape[0] - 2)
    columns = np.clip(np.asarray(columns, dtype=int), 1, values.shape[1] - 2)
    windows = values[rows[:, None] + _WINDOW[None, :, 0], columns[:, None] + _WINDOW[None, :, 1]]
    total = np.maximum(windows.sum(axis=1), 1e-30)
    return (windows[:, 4] - np.median(np.delete(windows, 4, axis=1), axis=1)) / total, total


def psf_sharpness(model, x_0=0.0, y_0=0.0):
    """`excess_share` of a star's brightest pixel, centred on the pixel (its sharpest
    phase), of a photutils PSF model (flux, x_0, y_0) at (x_0, y_0)."""
    model = model.copy()
    model.flux, model.x_0, model.y_0 = 1.0, float(x_0), float(y_0)
    y, x = np.mgrid[-1:2, -1:2].astype(float)
    values = np.asarray(model(x + x_0, y + y_0), dtype=float)
    return float(excess_share(values, [1], [1])[0][0])


def cosmic_ray_mask(residual_e, variance_e2, model_e, *, read_noise_e, excluded=None,
                    sharpness=0.0, object_limit=OBJECT_LIMIT, per_pixel=False):
    """The pixels of cosmic rays in the residual of a PSF fit (module docstring).

    Parameters
    ----------
    residual_e : ndarray [y, x]
        Image minus its sky and its fitted stars' models, e-.
    variance_e2 : ndarray [y, x]
        The variance of each pixel the sky and the fitted models predict, e-^2.
    model_e : ndarray [y, x]
        The fitted stars' models, e-.
    read_noise_e : float
    excluded : ndarray of bool, optional
        Pixels not to read (non-finite, trails, saturated cores).
    sharpness : float or ndarray [y, x], optional
        A star's `excess_share` at its sharpest (at each pixel): a cosmic ray's brightest
        pixel has `SHARPER` times more.
    object_limit : float, optional
        L.A.Cosmic's contrast over the fine structure (default `OBJECT_LIMIT`).
    per_pixel : bool, optional
        Judge each pixel found alone rather than each connected set at its brightest (with a
        low ``object_limit`` a star's core joins a cosmic ray beside it).
    Returns
    -------
    ndarray of bool [y, x]
        True on a cosmic ray's pixels and the pixels beside them.
    """
    residual = np.asarray(residual_e, dtype=float)
    finite = np.isfinite(residual) & np.isfinite(variance_e2)
    left_out = ~finite if excluded is None else ~finite | np.asarray(excluded, dtype=bool)
    variance = np.where(finite, variance_e2, 1.0)
    found, _ = astroscrappy.detect_cosmics(
        np.where(finite, residual, 0.0).astype(np.float32), inmask=left_out,
        invar=np.maximum(variance, 1.0).astype(np.float32), sigclip=SIGMA_CLIP,
        objlim=object_limit, gain=1.0, readnoise=float(read_noise_e), satlevel=1e30,
        niter=ITERATIONS)
    found &= ~left_out
    # each connected set of pixels judged at its brightest: a misfit at a bright core
    # grows into its neighbours, whose own model is faint
    if per_pixel:
        labels, count = np.where(found, np.cumsum(found).reshape(found.shape), 0), found.sum()
    else:
        labels, count = ndimage.label(found, structure=np.ones((3, 3)))
    if count:
        peaks = tuple(np.array(ndimage.maximum_position(residual, labels,
                                                        np.arange(1, count + 1))).T)
        share = residual[peaks] > MODEL_SHARE * np.clip(model_e, 0.0, None)[peaks]
        # sharper than a star: the brightest pixel's excess over its neighbours as a share
        # of its 3 x 3, against the PSF's own at its sharpest phase
        # by SHARP_SIGMA of the pixel's noise (a wing's noise on its curvature is no ray)
        excess, total = excess_share(np.where(finite, residual, 0.0), *peaks)
        sharp = (excess - SHARPER * np.broadcast_to(sharpness, residual.shape)[peaks]
                 > SHARP_SIGMA * np.sqrt(variance[peaks]) / total)
        found = np.r_[False, share & sharp][labels]
    return ndimage.binary_dilation(found, iterations=1) & ~left_out


def star_sharpness(data_e, x, y):
    """`excess_share` of each star's brightest pixel within 1.5 pixels of (x, y), of a
    sky-subtracted image; NaN where that leaves the image."""
    data = np.nan_to_num(np.asarray(data_e, dtype=float))
    ny, nx = data.shape
    centre_y, centre_x = np.rint(y).astype(int), np.rint(x).astype(int)
    rows = np.clip(centre_y[:, None] + _WINDOW[None, :, 0], 1, ny - 2)
    columns = np.clip(centre_x[:, None] + _WINDOW[None, :, 1], 1, nx - 2)
    brightest = np.argmax(data[rows, columns], axis=1)
    picked = np.arange(len(rows))
    share, _ = excess_share(data, rows[picked, brightest], columns[picked, brightest])
    inside = (centre_y >= 2) & (centre_y < ny - 2) & (centre_x >= 2) & (centre_x < nx - 2)
    return np.where(inside, share, np.nan)


def image_cosmic_rays(data_e, rms_e, x, y, peak_e, usable, sigma, *, excluded=None,
                      smoothed=None, detection_fwhm=3.0):
    """The pixels of cosmic rays of a sky-subtracted image without a PSF model, judged
    against its own stars (module docstring).

    Parameters
    ----------
    data_e : ndarray [y, x]
        The image less its sky, e-.
    rms_e : float
        The sky's noise per pixel, e-.
    x, y, peak_e : ndarray (N,)
        The sources' positions and peaks (e-).
    usable : ndarray of bool (N,)
        The clean sources (stars measured without a flag).
    sigma : ndarray (N,)
        Their adaptive sizes, pixels: a source `STAR_SIZE` times the median size of the
        bright ones or smaller is no star (a cosmic ray detected as a source). Rays as large
        as stars (tracks, worms) are left out by their sharpness, clipped at 3 robust sigma
        above the median: 113 clean bright sources of an image with 120 rays had put the
        stars' 90th percentile at 0.18 for a median of 0.055.
    excluded : ndarray of bool [y, x], optional
        Pixels not to read (non-finite, trails, saturated).
    smoothed : ndarray [y, x], optional
        The image smoothed as detection smooths it (`bfpsf.measure.smoothing.smoothed_image`
        of ``data_e`` with ``detection_fwhm``; computed here where not given).
    detection_fwhm : float, optional
        The FWHM of that smoothing, pixels (default 3).

    Returns
    -------
    ndarray of bool [y, x] or None
        The cosmic rays' pixels and those beside them; None where fewer than `MIN_STARS`
        stars are bright enough to say how sharp a star is (the image is not searched).
    """
    data = np.asarray(data_e, dtype=float)
    # the sky's noise, or the pixels' own where that is less (exact zeros, a region without
    # data, had made a sky's scatter nil)
    read = np.isfinite(data) & (data != 0) & (True if excluded is None else ~excluded)
    noise = max(float(rms_e), float(mad_std(data[read])) if read.any() else 0.0)
    bright = np.asarray(usable, dtype=bool) & (np.asarray(peak_e, dtype=float)
                                               > STAR_PEAK * noise)
    sigma = np.asarray(sigma, dtype=float)
    if bright.any():
        bright &= sigma > STAR_SIZE * np.nanmedian(sigma[bright])
    shares = star_sharpness(data_e, np.asarray(x)[bright], np.asarray(y)[bright])
    shares = shares[np.isfinite(shares)]
    if len(shares) < MIN_STARS:
        return None
    variance = noise**2 + np.clip(np.nan_to_num(data), 0.0, None)
    # the stars' sharpness at their centres; away from them, a pixel as sharp as a star's
    # core is none of theirs (the fine structure about a bright core hides a cosmic ray from
    # L.A.Cosmic's contrast test there, which the sharpness takes over)
    # (the centres: the sources' and every significant peak of the image smoothed by a star,
    # the cores of a pair detection took as one: 15 pixels of 3 such pairs of a crowded
    # field had been taken for rays)
    kernel = np.asarray(detection_kernel(detection_fwhm).array, dtype=float)
    kernel = kernel / kernel.sum()
    if smoothed is None:
        smoothed = smoothed_image(data, detection_fwhm)
    centres = ((smoothed == ndimage.maximum_filter(smoothed, size=3))
               & (smoothed > PEAK_SIGMA * noise * np.sqrt(np.sum(kernel**2))))
    inside = (np.abs(np.rint(y) - (data.shape[0] - 1) / 2) < data.shape[0] / 2) & (
        np.abs(np.rint(x) - (data.shape[1] - 1) / 2) < data.shape[1] / 2)
    centres[np.rint(np.asarray(y)[inside]).astype(int),
            np.rint(np.asarray(x)[inside]).astype(int)] = True
    near = ndimage.distance_transform_edt(~centres) <= CENTRE_REACH
    # the stars' sharpness, rays detected as sources (their shares far above) clipped
    shares = sigma_clip(shares, sigma_lower=np.inf, sigma_upper=3.0, stdfunc="mad_std",
                        maxiters=None).compressed()
    star = float(np.percentile(shares, SHARPEST))
    # L.A.Cosmic's own search, each connected set judged at its brightest pixel (a track
    # 2 px wide, whose pixels are not sharp against each other), and its search near bright
    # cores, each pixel judged alone
    model = np.zeros_like(data)
    rays = cosmic_ray_mask(data, variance, model, read_noise_e=noise, excluded=excluded,
                           sharpness=star) | cosmic_ray_mask(
        data, variance, model, read_noise_e=noise, excluded=excluded,
        sharpness=np.where(near, star, star * WING_SHARPER / SHARPER),
        object_limit=IMAGE_OBJECT_LIMIT, per_pixel=True)
    if excluded is None or not rays.any():
        return rays
    # a set of them within `LINE_GAP` of the pixels left out is what is left of a line
    # beside a star (the line mask stops short of the star's light), not a cosmic ray:
    # filled, its ends had become sources (a hot column's 34 rows beside a 3e5 e- star)
    labels, count = ndimage.label(rays, structure=np.ones((3, 3)))
    touching = np.unique(labels[ndimage.binary_dilation(excluded, iterations=LINE_GAP) & rays])
    return rays & ~np.isin(labels, touching[touching > 0])
