"""The sky under the stars: a low-order surface fitted to the pixels the stars leave.

One sky model for every command (``psf``, ``measure``, ``photometry``, ``diagnose`` through the
image preparation, `bfpsf.measure.prepare.prepare_image`). A user does not know their sky, and three
things bias the obvious estimators:

* the wings of bright stars reach far: a sigma-clipped median of the image clips the cores but
  keeps the wings, so it comes out high in a field of bright stars (the level the BF-aware
  photometry then subtracts is too high by the stars' own light: a flux bias that grows with
  the stars' brightness, 2.8 mmag bright-minus-faint on E2V spots, issue 21);
* the sky is not flat: a gradient across the image leaves each star a different sky;
* every exposure has its own sky.

`estimate_sky` fits a plane to the pixels away from the sources, with sigma clipping, per
image, or a surface of degree 2 or 3 where those pixels show the sky curved (a vignetting
bowl), or a bicubic spline with knots 128 px apart where they ask for more than a cubic
follows (a patch of scattered light: `choose_degree`; the surfaces are
`bfpsf.measure.sky_surface.SkyModel`). The sources are masked where the smoothed
image exceeds twice its noise, each out to three times its own radius at that level
(`source_mask`), so a bright star's wings are masked further than a faint one's; a dense
field, where that leaves less than 15 % of the image, is masked out to fewer radii. No mask
removes the wings beyond it: summed over a field of bright stars they are a glow (8 e- per
pixel for 60 Kolmogorov stars of peaks 3-120 ke- on 300^2 pixels) that a sky between the
stars takes for sky. So the sky is fitted
beyond the stars' total-flux model: ``bfpsf psf`` fits every image's plane jointly with the
wings beyond P0's support of every source its P0 fit models, neighbours and blends too
(`bfpsf.measure.total_flux.fit_sky_and_wings`), and the PSF product keeps that wing profile;
photometry fits the plane, then again beyond its fitted stars (their models within the
support and the glow of their wings beyond it; `bfpsf.measure.prepare.PreparedImage.with_glow`),
in its model-weighted refit. Fitting the plane to the image
minus the stars' models within P0's support alone was tried and rejected: their wings beyond
the support, left in the pixels the masks no longer cover, biased it more (0.77 e- against
0.31 e- for 64 bright Moffat stars on a sky of 0, tests/test_gridded.py's field).
Why a plane and not a local annulus per star (photutils ``LocalBackground``): both
follow a linear gradient exactly (an annulus symmetric about the star averages a plane to its
centre value), but the annulus median carries the noise of a few hundred pixels into every
star (0.3 % of a 3 ke- peak star's flux on a 600 e- sky), and in a dense field its pixels are
mostly neighbours' wings; the plane uses every free pixel of the image. A sky with structure
on the scale of the stars is beyond either; give it with ``--background`` (a known sky).
"""

import numpy as np
from astropy.stats import sigma_clipped_stats
from scipy import ndimage

from ..errors import BFPSFInputError, BFPSFValueError
from ..least_squares import clipped_least_squares
from .sky_surface import SPLINE, SPLINE_SPACING, SkyModel

__all__ = ["SkyModel", "estimate_sky", "choose_degree", "sky_pixels", "source_mask",
           "SPLINE"]

#: Pixels at most used in the surface fit (a regular subsample of the free pixels beyond).
_MAX_FIT_PIXELS = 250_000
#: Smallest share of the image the source mask leaves free before it is shrunk.
_MIN_FREE_FRACTION = 0.15


#: A source masked for the sky peaks above this many RMS of the smoothed image (`source_mask`):
#: a starless image's noise seldom makes one (four starless 300^2 images were 58 % free at 2
#: RMS, 89 % at 3, 99 % at 4), and their sky is then within 0.06 e- of 384 e- (-1.0 at 2).
SOURCE_PEAK = 4.0


def source_mask(image_e, *, threshold=2.0, peak=SOURCE_PEAK, reach=3.0, grow=2,
                smoothing_fwhm=3.0):
    """Pixels of the sources and their wings.

    Sources are where the smoothed image minus a rough sky exceeds ``threshold`` times its
    noise and peaks above ``peak`` times it; each is masked out to ``reach`` times its
    equivalent radius at that threshold (sqrt(area / pi)) from its centroid, so a bright
    star's wings are masked further than a faint one's: for a Moffat of beta 3 the wing left
    at the mask's edge is 3^-6 of the threshold level, for a Kolmogorov profile (r^-11/3)
    3^-3.7 = 2 % of it. Without the peak's condition the noise's own upward blobs were
    masked (42 % of a starless 300^2 image) and the sky left beneath was 0.05 of its noise
    low: -1.0 e- on 384 e- (a new user's faint stars 10 mmag bright).

    Parameters
    ----------
    image_e : ndarray [y, x]
        Image, e- (sky included); non-finite pixels are masked.
    threshold : float, optional
        In RMS of the smoothed image (default 2: well below the detection threshold).
    reach : float, optional
        Mask radius in units of each source's equivalent radius (default 3).
    grow : int, optional
        Pixels added to every mask radius (default 2).
    smoothing_fwhm : float, optional
        Gaussian smoothing before thresholding, pixels (default 3).

    Returns
    -------
    ndarray of bool [y, x]
    """
    image = np.asarray(image_e, dtype=float)
    bad = ~np.isfinite(image)
    if bad.all():
        msg = "the image has no finite pixel"
        raise BFPSFInputError(msg, image.shape)
    filled = np.where(bad, np.median(image[~bad]), image)
    smoothed = ndimage.gaussian_filter(filled, smoothing_fwhm / 2.3548, mode="nearest")
    _, level, rms = sigma_clipped_stats(smoothed[~bad], sigma=3.0, maxiters=5)
    # a rough sky that follows a gradient: a wide median of the smoothed image
    if min(image.shape) >= 32:
        step = 4  # on a coarse grid: a median filter of a quarter of the image is slow
        coarse = ndimage.median_filter(smoothed[::step, ::step],
                                       size=max(3, min(image.shape) // (4 * step)) | 1,
                                       mode="nearest")
        rough = ndimage.zoom(coarse, (image.shape[0] / coarse.shape[0],
                                      image.shape[1] / coarse.shape[1]), order=1,
                             mode="nearest")[:image.shape[0], :image.shape[1]]
    else:
        rough = level
    labels, n_sources = ndimage.label((smoothed - rough) > threshold * rms)
    mask = bad.copy()
    if n_sources:
        index = np.arange(1, n_sources + 1)
        # the noise's own blobs are left alone: only what peaks above ``peak`` is measured
        index = index[ndimage.maximum(smoothed - rough, labels, index) > peak * rms]
        areas = ndimage.sum_labels(np.ones(image.shape), labels, index)
        centres = ndimage.center_of_mass(np.ones(image.shape), labels, index)
        ny, nx = image.shape
        for area, (y_c, x_c) in zip(areas, centres):
            radius = reach * np.sqrt(area / np.pi) + grow
            low_y, high_y = max(int(y_c - radius), 0), min(int(y_c + radius) + 2, ny)
            low_x, high_x = max(int(x_c - radius), 0), min(int(x_c + radius) + 2, nx)
            yy, xx = np.mgrid[low_y:high_y, low_x:high_x]
            mask[low_y:high_y, low_x:high_x] |= np.hypot(xx - x_c, yy - y_c) <= radius
    return mask


def sky_pixels(image_e):
    """The pixels beyond the sources that `estimate_sky` fits (True = sky), ndarray of bool.

    `source_mask` out to 3 radii of each source; a dense field, which leaves less than 15 %
    of the image free at that reach, is masked out to fewer radii (2, 1.5, then 1).
    """
    for reach in (3.0, 2.0, 1.5, 1.0):
        free = ~source_mask(image_e, reach=reach)
        if free.mean() >= _MIN_FREE_FRACTION:
            break
    return free


#: Cells per side of the image in which `choose_degree` averages the sky pixels' residual.
DEGREE_CELLS = 8
#: `choose_degree` keeps the lowest degree where its cells' misfit beyond their noise is
#: below this fraction of the pixels' noise.
DEGREE_GATE = 0.05
#: Pixels at most `choose_degree` averages (a regular subsample; 780 per cell, their mean
#: known to 0.04 of the pixels' noise).
_DEGREE_PIXELS = 50_000
#: Free pixels a cell needs to count in `choose_degree`, and usable cells it needs.
_CELL_PIXELS, _MIN_CELLS = 30, 16


def _clipped_fit(design, values, clip_nsigma, max_iterations):
    """`bfpsf.least_squares.clipped_least_squares` as the sky fits: at least 10 pixels per
    term kept. Returns (coefficients, rms, kept)."""
    fit = clipped_least_squares(values, design, nsigma=clip_nsigma,
                                max_iterations=max_iterations, min_kept=10 * design.shape[1])
    return fit.params, fit.scale, fit.keep


def choose_degree(rows, columns, values, shape, *, degrees=(1, 2, 3), clip_nsigma=3.0,
                  spline=True):
    """The degree of the sky surface the pixels ask for: the least Bayesian information
    criterion of each degree's fit on `DEGREE_CELLS` x `DEGREE_CELLS` cells of the image.

    Every degree is fitted by least squares to the same pixels (those the highest degree
    keeps within ``clip_nsigma`` of its fit); its residual is averaged in each cell with at
    least 30 of them. A cell's error is the pixels' scatter over the root of their number,
    and, added in quadrature, the cells' own scatter about the highest degree beyond it
    (faint neighbours, a glow of wings: structure that no low-order surface holds, which
    would otherwise make every added term "significant"); the pixels' variance is at least
    the sky's level (Poisson, e-), so that a noiseless image keeps a plane. The criterion is
    chi2 + k ln(N) over the N cells, k the degree's terms. A plane on a sky curved like a
    vignetting bowl (+60 e- at the edges' middle on 600 e-, 768^2 pixels of Kolmogorov x
    Airy stars, `benchmarks/curved_sky.py`) read the faint stars +26.8 mmag with a spread of
    132 mmag; the chosen degree 2, -0.8 and 14.8 mmag (20.1 under a flat sky). Returns
    ``min(degrees)`` where fewer than 16 cells have 30 pixels. With ``spline``, 'spline' where the
    pixels ask for more than the chosen polynomial follows (`_spline_asked`): a ring of
    scattered light (10-25 e- on 300 e-, 35 px wide) is followed by no polynomial, which
    then keeps the plane."""
    degrees = sorted(int(degree) for degree in degrees)
    if len(degrees) == 1:
        return degrees[0]
    step = max(1, values.size // _DEGREE_PIXELS)  # a regular subsample: the choice's cost
    rows, columns, values = rows[::step], columns[::step], values[::step]
    highest = SkyModel.template(degrees[-1], shape).basis(columns, rows)
    _, rms, keep = _clipped_fit(highest, values, clip_nsigma, 5)
    cell = (rows * DEGREE_CELLS // shape[0]) * DEGREE_CELLS + columns * DEGREE_CELLS // shape[1]
    counts = np.bincount(cell[keep], minlength=DEGREE_CELLS ** 2)
    used = counts >= _CELL_PIXELS
    if used.sum() < _MIN_CELLS:
        return degrees[0]

    # an image in e- has at least the Poisson variance of its sky (a noiseless image's
    # pixels scatter by the stars' wings alone: its sky is left a plane)
    variance = max(rms ** 2, float(np.median(values[keep])))
    if not variance > 0:
        return degrees[0]
    noise = variance / counts[used]
    means, excess = _cell_misfits(
        {degree: highest[:, :(degree + 1) * (degree + 2) // 2] for degree in degrees},
        values, keep, cell, counts, used, noise)
    # a misfit of the lowest degree below `DEGREE_GATE` of the pixels' noise is left to it:
    # the glow of the stars' wings, highest where the stars are, bends a freer surface (a
    # grid of 36 Moffat stars of 3-80 ke- on 100 e-: degree 2 took 0.4 e- more at the centre)
    if excess[degrees[0]] < (DEGREE_GATE ** 2) * variance:
        return degrees[0]
    information = _information(means, excess, degrees[-1], noise,
                               {degree: (degree + 1) * (degree + 2) // 2 for degree in degrees})
    chosen = min(degrees, key=lambda degree: (information[degree], degree))
    if spline and _spline_asked(rows, columns, values, shape, chosen,
                                highest[:, :(chosen + 1) * (chosen + 2) // 2], clip_nsigma):
        return SPLINE
    return chosen


def _cell_misfits(designs, values, keep, cell, counts, used, noise):
    """Each design's least-squares residual of ``values`` (on the ``keep`` pixels) averaged
    in every used cell (`choose_degree`), and the mean square of those means beyond
    ``noise`` (each mean's variance): two dicts by the designs' keys."""
    means, excess = {}, {}
    for kind, design in designs.items():
        residual = values - design @ np.linalg.lstsq(design[keep], values[keep], rcond=None)[0]
        sums = np.bincount(cell[keep], weights=residual[keep], minlength=counts.size)
        means[kind] = sums[used] / counts[used]
        excess[kind] = float(np.mean(means[kind] ** 2 - noise))
    return means, excess


def _information(means, excess, freest, noise, terms):
    """Each surface's criterion on the cells: chi2 + k ln(cells) (``terms``: k by kind),
    every cell's error its ``noise`` plus the ``freest`` surface's misfit beyond it (per
    degree of freedom)."""
    cells = noise.size
    floor = max(excess[freest] * cells / max(cells - terms[freest], 1), 0.0)
    return {kind: float(np.sum(means[kind] ** 2 / (noise + floor))) + terms[kind] * np.log(cells)
            for kind in means}


def _spline_asked(rows, columns, values, shape, degree, polynomial, clip_nsigma):
    """Whether the sky pixels ask for the spline beyond the polynomial of ``degree`` (its
    terms at the pixels: ``polynomial``): the least information criterion, as
    `choose_degree`'s, on cells twice as fine as the spline's basis along each axis (a
    quarter of a cell per coefficient), where the polynomial's misfit beyond the noise is
    at least `DEGREE_GATE` of it; never on an image
    narrower than two `SPLINE_SPACING` (its knots would come closer than a bright star's
    glow reaches: two 128^2 amplifiers of a constant sky took the spline for their stars'
    wings, the flux correction's error 0.014 for 0.005). A patch of
    scattered light (90 e- over a Gaussian of 140 px) on a gradient, which a cubic followed
    to within 10-20 e-, had left its misfit in the wings of the total-flux fit: a flux
    correction of 1.244 +- 0.128 where the truth was 1.042 (every flux -200 mmag)."""
    if min(shape) < 2 * SPLINE_SPACING:  # knots closer than a star's glow reaches
        return False
    spline = SkyModel.template(SPLINE, shape)
    designs = {SPLINE: spline.basis(columns, rows), degree: polynomial}
    _, rms, keep = _clipped_fit(designs[SPLINE], values, clip_nsigma, 5)
    cells_y, cells_x = (2 * (intervals + 3) for intervals in spline.intervals)
    cell = (rows * cells_y // shape[0]) * cells_x + columns * cells_x // shape[1]
    counts = np.bincount(cell[keep], minlength=cells_y * cells_x)
    used = counts >= _CELL_PIXELS
    variance = max(rms ** 2, float(np.median(values[keep])))
    if used.sum() < 2 * len(spline.coefficients) or not variance > 0:
        return False
    noise = variance / counts[used]
    means, excess = _cell_misfits(designs, values, keep, cell, counts, used, noise)
    if excess[degree] < (DEGREE_GATE ** 2) * variance:
        return False
    information = _information(means, excess, SPLINE, noise,
                               {kind: design.shape[1] for kind, design in designs.items()})
    return information[SPLINE] < information[degree]


def estimate_sky(image_e, *, glow_e=None, mask=None, degree="auto", clip_nsigma=3.0,
                 max_iterations=10, sky_pixels_mask=None):
    """The sky surface of an image (module docstring for the choice).

    Parameters
    ----------
    image_e : array_like [y, x]
        Image, e- per pixel, sky included.
    glow_e : ndarray [y, x], optional
        The stars' light beyond the PSF support (`bfpsf.model.wings.wing_image`),
        e-: the surface is fitted to ``image_e - glow_e`` (the sources still masked), so the
        sky is what is left beyond the stars' total-flux model.
    mask : ndarray of bool, optional
        Further pixels to leave out (True = not sky).
    degree : int, 'spline' or 'auto', optional
        Polynomial degree of the surface (0: a constant, 1: a plane, up to 3), or 'spline'
        (a bicubic B-spline, knots `SPLINE_SPACING` apart); default ``'auto'``: a plane, or
        degree 2 or 3 or the spline where the sky pixels show a curved sky
        (`choose_degree`).
    clip_nsigma : float, optional
        Pixels further than this many clipped RMS from the surface are left out, iteratively
        (default 3: cosmic rays, faint undetected stars).
    max_iterations : int, optional
        Clipping iterations at most (default 10).
    sky_pixels_mask : ndarray of bool, optional
        The pixels beyond the sources (`sky_pixels` of this image), when known already: the
        sky again beyond the stars' glow reuses the first estimate's mask.

    Returns
    -------
    SkyModel
    """
    image = np.asarray(image_e, dtype=float)
    if image.ndim != 2:
        msg = f"image must be 2-D [y, x], got shape {image.shape}"
        raise BFPSFInputError(msg, image.shape)
    automatic = isinstance(degree, str) and degree == "auto"
    if not automatic and degree != SPLINE and (isinstance(degree, str) or int(degree) != degree
                                               or not 0 <= degree <= 3):
        msg = (f"degree of the sky surface must be 0, 1, 2, 3, 'spline' or 'auto', got "
               f"{degree!r}")
        raise BFPSFValueError(msg, degree)
    residual, method = image, "masked"
    if glow_e is not None:
        residual, method = image - np.asarray(glow_e, dtype=float), "masked, wings subtracted"
    free = sky_pixels(image) if sky_pixels_mask is None else np.array(sky_pixels_mask,
                                                                       dtype=bool)
    if free.shape != image.shape:
        msg = f"sky_pixels_mask has shape {free.shape}, the image {image.shape}"
        raise BFPSFInputError(msg, free.shape)
    if mask is not None:
        free &= ~np.asarray(mask, dtype=bool)
    free &= np.isfinite(residual)
    rows, columns = np.nonzero(free)
    n_terms = len(SkyModel.template(1 if automatic else degree, image.shape).coefficients)
    if rows.size < 10 * n_terms:
        free = np.isfinite(image)  # nearly every pixel is a star: fit what there is
        rows, columns = np.nonzero(free)
        if rows.size == 0:
            msg = "the image has no finite pixel"
            raise BFPSFInputError(msg, image.shape)
    step = max(1, rows.size // _MAX_FIT_PIXELS)
    rows, columns = rows[::step], columns[::step]
    values = residual[rows, columns]
    kind = (choose_degree(rows, columns, values, image.shape, clip_nsigma=clip_nsigma)
            if automatic else degree)
    template = SkyModel.template(kind, image.shape, method)
    coefficients, rms, keep = _clipped_fit(template.basis(columns, rows), values, clip_nsigma,
                                           max_iterations)
    return SkyModel(tuple(float(c) for c in coefficients), template.degree, image.shape,
                    float(rms), method, int(keep.sum()), template.intervals)
