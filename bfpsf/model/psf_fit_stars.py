"""The stars of a P0 fit (`bfpsf.model.psf_fit.fit_psf`): their cutouts, stacked for
vectorised fitting, the neighbours modelled beside them, their flags and the result tables."""

import logging

import numpy as np
from astropy.table import Table
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.stats import theilslopes

from ..errors import BFPSFInputError
from ..least_squares import clipped_least_squares
from ..moments.adaptive import adaptive_moments_batch
from ..moments.moment_errors import moment_errors

__all__ = ["STAR_FLAGS", "OUTSIDE", "NONFINITE", "NONPOSITIVE", "MOVED", "UNLIKE",
           "MISFIT_SIGMA", "MISFIT_SIZE", "MISFIT_SHAPE", "MISFIT_NEIGHBOURS", "COMPANION_SIGMA",
           "COMPANION_RADIUS", "COMPANION_FRACTION", "misfits", "hidden_companions", "Stars",
           "as_star_list", "cut_stars", "cut_neighbours", "star_table", "neighbour_table",
           "companion_pixels", "unlike_others"]

log = logging.getLogger(__name__)


#: Per-star flags of `fit_psf` (bit values), named below.
OUTSIDE, NONFINITE, NONPOSITIVE, MOVED, UNLIKE = 1, 2, 4, 8, 16
STAR_FLAGS = {
    OUTSIDE: "cutout outside the image (star not used)",
    NONFINITE: "non-finite pixel in the cutout (star not used)",
    NONPOSITIVE: "non-positive flux estimate (star not used)",
    MOVED: "position fit failed or moved more than 1 pixel (star not used in the last "
           "iteration)",
    UNLIKE: "its shape is not the other stars' (`misfits`: an unresolved blend, a cosmic "
            "ray, a galaxy) or it holds a companion detection did not split "
            "(`hidden_companions`); modelled, not used",
}

#: `misfits`: a star is a misfit beyond this many of its shape's statistical errors
MISFIT_SIGMA = 5.0
#: `misfits`: and beyond this change of its adaptive size T (relative) or of its e1 or e2 (the
#: bench's effects outside the catalogue, growing with flux and with the row, make bright stars
#: up to 11 % larger than their neighbours; the blends that spoiled P0 were 27-230 % larger)
MISFIT_SIZE = 0.15
MISFIT_SHAPE = 0.08
#: `misfits`: how many of the nearest stars of its image a star is compared with
MISFIT_NEIGHBOURS = 8
#: `hidden_companions`: a companion lies beyond this many errors of the filtered residual ...
COMPANION_SIGMA = 7.0
#: ... at least this far from the star's centre, pixels (a nearer one changes its moments:
#: `misfits`) ...
COMPANION_RADIUS = 4.5
#: ... and holds at least this fraction of the star's filtered peak
COMPANION_FRACTION = 0.05
#: the compensated Gaussian of `hidden_companions`: a Gaussian of the detection's FWHM
#: (3 px, `bfpsf.measure.sources.measure_sources`) less its mean over 9 x 9 pixels
_COMPANION_KERNEL = np.exp(-0.5 * (np.arange(-4, 5)[:, None]**2 + np.arange(-4, 5)**2)
                           / (3.0 / 2.3548)**2)
_COMPANION_KERNEL = _COMPANION_KERNEL / _COMPANION_KERNEL.sum() - 1.0 / 81
#: `companion_pixels`: a fainter companion lies beyond this many errors (as in
#: `hidden_companions`, of any fraction of the star's peak) ...
MASK_SIGMA = 5.0
#: ... and holds at least this fraction of the star's filtered peak (P0's errors, not
#: companions, reach 5 sigma on the brightest stars of a field without companions) ...
MASK_FRACTION = 0.003
#: ... its pixels masked within this many pixels of where it does ...
MASK_GROWTH = 3
#: ... and no nearer the star's centre than this, pixels
MASK_INNER = 2.5
_MASK_DISK = np.hypot(*np.mgrid[-MASK_GROWTH:MASK_GROWTH + 1,
                                -MASK_GROWTH:MASK_GROWTH + 1]) <= MASK_GROWTH + 0.01


def as_star_list(images, positions):
    if isinstance(images, np.ndarray) and images.ndim == 2:
        images, positions = [images], [positions]
    images = [np.asarray(image, dtype=float) for image in images]
    positions = [np.atleast_2d(np.asarray(xy, dtype=float)) for xy in positions]
    if len(images) != len(positions):
        msg = f"got {len(images)} images but {len(positions)} position lists"
        raise BFPSFInputError(msg, len(positions))
    for index, (image, xy) in enumerate(zip(images, positions)):
        if image.ndim != 2:
            msg = f"image {index} must be 2-D [y, x], got shape {image.shape}"
            raise BFPSFInputError(msg, image.shape)
        if xy.size and (xy.ndim != 2 or xy.shape[1] != 2):
            msg = f"positions of image {index} must be an (N, 2) array of (x, y), got {xy.shape}"
            raise BFPSFInputError(msg, xy.shape)
    return images, positions


class Stars:
    """Cutouts of the usable stars, stacked for vectorised fitting.

    Attributes: ``data`` (N, n, n) e-; ``column``, ``row`` (N,) pixel of the cutout's first
    column / row; ``floor`` (N,) variance floor, e-**2; ``flux``, ``x_0``, ``y_0`` (N,) the
    current estimates (first: the cutout's sum and the positions given); ``flags`` (N,)
    `STAR_FLAGS`; ``image`` (N,) image of each; ``valid`` (N, n, n) pixels inside the image;
    ``p0`` (N,) True for the stars P0 is fitted to, False for the neighbours (modelled only);
    ``rejected`` (N,) stars left out of P0 by `misfits` (modelled, as the neighbours are);
    ``masked`` (N, n, n) pixels of a companion (`companion_pixels`), weighing nothing.
    """

    def __init__(self, data, column, row, floor, x_0, y_0, image, valid, p0):
        self.data, self.column, self.row, self.floor = data, column, row, floor
        self.image, self.valid, self.p0 = image, valid, p0
        # the positions given (a centroid of the whole cutout would be pulled towards a
        # neighbour's light; one of its central pixels towards the pixel centre, a bias of
        # the held positions that made the grid fit diverge)
        self.x_start, self.y_start = np.array(x_0, dtype=float), np.array(y_0, dtype=float)
        self.flags = np.zeros(len(data), dtype=int)
        self.rejected = np.zeros(len(data), dtype=bool)
        self.masked = np.zeros(data.shape, dtype=bool)
        self.restart()

    def restart(self):
        """Fluxes and positions back to their first estimates: the cutouts' sums and the
        positions given (a P0 fit that starts again without its misfits)."""
        self.flux = self.data.sum(axis=(1, 2))
        self.x_0, self.y_0 = self.x_start.copy(), self.y_start.copy()

    @property
    def used(self):
        """The stars P0 is fitted to now: not neighbours, not rejected by `misfits`."""
        return self.p0 & ~self.rejected

    def others(self, model, shapes):
        """Per star, the light of every other star's model in its cutout, e-: the
        neighbours subtracted from each cutout."""
        size = model.shape[1]
        own = np.where(self.valid, model, 0.0)
        canvases = [np.zeros((ny + 2 * size, nx + 2 * size)) for ny, nx in shapes]
        rows = self.row.astype(int) + size
        columns = self.column.astype(int) + size
        for star in range(len(model)):
            canvases[self.image[star]][rows[star]:rows[star] + size,
                                       columns[star]:columns[star] + size] += own[star]
        return np.array([canvases[self.image[star]][rows[star]:rows[star] + size,
                                                    columns[star]:columns[star] + size]
                         for star in range(len(model))]) - own


def cut_neighbours(images, neighbours, half):
    """Cutouts of the neighbours (centres inside their image): image index, cutout (0 beyond
    the image), valid pixels, corner (column, row) and centre (x, y) of each."""
    found = ([], [], [], [], [])
    for index, (image, xy) in enumerate(zip(images, neighbours)):
        ny, nx = image.shape
        padded = np.pad(image, half, constant_values=np.nan)
        for x_0, y_0 in np.atleast_2d(np.asarray(xy, dtype=float)).reshape(-1, 2):
            column, row = int(np.rint(x_0)), int(np.rint(y_0))
            if not (0 <= column < nx and 0 <= row < ny):
                continue
            cutout = padded[row:row + 2 * half + 1, column:column + 2 * half + 1]
            valid = np.isfinite(cutout)
            for values, value in zip(found, (index, np.where(valid, cutout, 0.0), valid,
                                             (column - half, row - half), (x_0, y_0))):
                values.append(value)
    return found


def cut_stars(images, positions, half, floors, neighbours=None):
    """Flags of every star (bits 1, 2, 4 of `STAR_FLAGS`), its image, and the usable ones
    followed by the neighbours (``p0`` False)."""
    flags, image_index, cutouts, corners, star_floors, centres = [], [], [], [], [], []
    for index, (image, xy) in enumerate(zip(images, positions)):
        ny, nx = image.shape
        for x_0, y_0 in xy:
            image_index.append(index)
            if not (np.isfinite(x_0) and np.isfinite(y_0)):
                flags.append(OUTSIDE)
                continue
            column, row = int(np.rint(x_0)) - half, int(np.rint(y_0)) - half
            if column < 0 or row < 0 or column + 2 * half >= nx or row + 2 * half >= ny:
                flags.append(OUTSIDE)
                continue
            cutout = image[row:row + 2 * half + 1, column:column + 2 * half + 1]
            if not np.all(np.isfinite(cutout)):
                flags.append(NONFINITE)
                continue
            if not cutout.sum() > 0:
                flags.append(NONPOSITIVE)
                continue
            flags.append(0)
            cutouts.append(cutout)
            corners.append((column, row))
            star_floors.append(floors[index])
            centres.append((x_0, y_0))
    flags = np.array(flags, dtype=int)
    image_index = np.array(image_index, dtype=int)
    if not cutouts:
        return flags, image_index, None
    n_stars = len(cutouts)
    images_of = list(image_index[flags == 0])
    valid = [np.ones_like(cutout, dtype=bool) for cutout in cutouts]
    if neighbours is not None:
        index, cut, inside, corner, centre = cut_neighbours(images, neighbours, half)
        images_of += index
        cutouts += cut
        valid += inside
        corners += corner
        centres += centre
        star_floors += [floors[one] for one in index]
    corners, centres = np.array(corners, dtype=float), np.array(centres, dtype=float)
    stars = Stars(np.array(cutouts, dtype=float), corners[:, 0], corners[:, 1],
                   np.array(star_floors, dtype=float), centres[:, 0], centres[:, 1],
                   np.array(images_of, dtype=int), np.array(valid),
                   np.arange(len(cutouts)) < n_stars)
    return flags, image_index, stars


def misfits(stars, clean):
    """The stars P0 is fitted to whose shape is not that of the stars around them: an
    unresolved blend (a new user's crowded field: 9 of 48 "isolated" stars had a neighbour
    4-7 px away that detection had not split; weighted by their flux they were half of P0,
    which came out double-peaked, 10 % too large and "converged"), a cosmic ray on a star, a
    galaxy.

    P0 carries the misfits' own shape, so a misfit is what differs from most stars: the
    adaptive size T = Mxx + Myy and the ellipticity (e1, e2) of each star's cutout (its
    neighbours' models subtracted: ``clean``), against the stars of its image (each
    exposure has its seeing; `_expected`: a plane over the image and the median of the
    `MISFIT_NEIGHBOURS` nearest, for a field's variation), less
    a robust straight line in flux (Theil-Sen: BF and effects that grow with flux), beyond
    `MISFIT_SIGMA` times its own statistical error (`moment_errors`: a faint star's shape is
    noisy) and beyond `MISFIT_SIZE` of T (larger only: a blend is never smaller) or
    `MISFIT_SHAPE` of e. On that field the stars' T was 5.70-5.87 px^2, the blends' 6.1-19.2.
    (The pixels' chi2 against P0 is no such test: in a dense field of Kolmogorov stars,
    neighbours' far wings beyond P0's support left a third of the stars 5 times the median
    chi2, and P0 without them put the sky 2.4 e- low.)

    Returns
    -------
    ndarray of bool (N,)
    """
    used = stars.used & ((stars.flags & MOVED) == 0)
    out = np.zeros(len(clean), dtype=bool)
    cutouts = np.where(stars.valid, clean, 0.0)
    star = adaptive_moments_batch(cutouts, weight=stars.valid)
    errors = moment_errors(cutouts, star, background_variance=stars.floor)
    size = star.mxx + star.myy
    # the sub-pixel phase's terms (0 on a pixel centre): size and e1 are even in each
    # phase, e2 odd in their product
    dx, dy = (2.0 * (value - np.round(value)) for value in (stars.x_0, stars.y_0))
    ax, ay = np.abs(dx), np.abs(dy)
    even = (ax, ay, dx**2, dy**2, ax**3, ay**3, dx**4, dy**4, ax * ay, dx**2 * dy**2)
    odd = (dx * dy, dx * dy * (dx**2 + dy**2))
    # twice: the second time against the stars the first left, so that a star among misfits
    # is compared with stars
    for _ in range(2):
        reference, out = used & ~out, np.zeros(len(clean), dtype=bool)
        for values, error, floor, size_like, basis in (
                (size, np.hypot(errors["mxx_err"], errors["myy_err"]) / size, MISFIT_SIZE,
                 True, even),
                ((star.mxx - star.myy) / size, errors["e1_err"], MISFIT_SHAPE, False, even),
                (2 * star.mxy / size, errors["e2_err"], MISFIT_SHAPE, False, odd)):
            local = _expected(values, stars, reference)
            relative = values / local - 1.0 if size_like else values - local
            good = reference & np.isfinite(relative)
            if np.sum(good) < 6 or np.ptp(stars.flux[good]) == 0:
                continue
            relative = _less_the_phase(relative, basis, good)
            slope, intercept = theilslopes(relative[good], stars.flux[good])[:2]
            relative = relative - intercept - slope * stars.flux
            # a blend or a galaxy is larger than a star, never smaller
            beyond = relative if size_like else np.abs(relative)
            out |= np.isfinite(relative) & (beyond > np.maximum(
                floor, MISFIT_SIGMA * np.nan_to_num(error, nan=np.inf)))
    return used & out


def _less_the_phase(relative, basis, good):
    """``relative`` less its robust fit (`clipped_least_squares`) on the sub-pixel phase's
    ``basis`` (columns), where the terms together lie beyond 5 sigma of none: an undersampled
    star's moments follow its phase (a new user's stars of FWHM 1.5 px: T some 25 % larger
    on a pixel corner than on its centre, e1 with the phase along one axis), and 62 of 300
    isolated stars away from pixel centres had been left out as blends."""
    design = np.column_stack([np.ones(len(relative)), *basis])
    if np.sum(good) < 3 * design.shape[1]:
        return relative
    fit = clipped_least_squares(relative[good], design[good])
    terms, k = fit.params[1:], design.shape[1] - 1
    # the terms together, against the chi2 of k terms of nothing (mean k, sigma sqrt(2 k))
    if not terms @ np.linalg.pinv(fit.covariance[1:, 1:]) @ terms > k + 5 * np.sqrt(2 * k):
        return relative
    return relative - design[:, 1:] @ terms


def unlike_others(stars, clean, model, variance):
    """The stars to leave out of P0 once it and the positions have settled: `misfits` (a new
    user's unresolved blends made P0 double-peaked); where it finds none, P0 fitted without
    them, `hidden_companions` (a companion detection did not split); where that finds none,
    the pixels of fainter companions (`companion_pixels`) are masked in ``stars.masked``.
    ``clean`` is every cutout less its neighbours' models. Returns (N,) bool."""
    rejected = misfits(stars, clean)
    if not rejected.any():
        rejected = hidden_companions(stars, clean, model, variance)
    if not rejected.any():
        masked = companion_pixels(stars, clean, model, variance) & ~stars.masked
        if masked.any():
            log.info("P0 fit: %d pixels of %d stars masked (fainter companions)",
                     masked.sum(), masked.any(axis=(1, 2)).sum())
            stars.masked |= masked
    return rejected


def hidden_companions(stars, clean, model, variance):
    """The stars P0 is fitted to that hold a source detection did not split, beyond the
    reach of `misfits`: a new user's crowded field (220 Kolmogorov x Airy stars per 320^2)
    left a fifth of its "isolated" stars with a neighbour 4-14 px away at 0.04-0.74 of their
    flux, which moved the adaptive moments too little to be seen (their Gaussian weight is
    1e-4 at 6 px) and gave P0 10 % of its light in wings beyond 4 px that the stars do not
    have (photometry -16 mmag against a P0 from a sparse field of the same stars).

    Each star's residual (``clean`` less its own ``model``) is filtered with a compensated
    Gaussian of the detection's width (`_COMPANION_KERNEL`: zero sum, so a smooth gradient,
    the far wings of a neighbour, gives nothing); a companion is where the filtered residual
    lies beyond `COMPANION_SIGMA` of its noise (``variance`` filtered with the kernel
    squared) at least `COMPANION_RADIUS` from the star's centre, and beyond as many errors
    above the point opposite through the centre (an error of P0 or of its brighter-fatter, a
    ring or an elongation, is even under that reflection; a companion is not), and holds
    `COMPANION_FRACTION` of the star's filtered peak or more.

    Returns
    -------
    ndarray of bool (N,)
    """
    used = stars.used & ((stars.flags & MOVED) == 0)
    filtered, peak, found = _companions(stars, clean, model, variance, COMPANION_SIGMA)
    with np.errstate(invalid="ignore"):
        found &= filtered > COMPANION_FRACTION * np.abs(peak)[:, None, None]
    return used & found.any(axis=(1, 2))


def companion_pixels(stars, clean, model, variance):
    """The pixels of the stars P0 is fitted to that hold a companion fainter than
    `hidden_companions` leaves out: where the filtered residual lies beyond `MASK_SIGMA` of its
    noise and of the point opposite, at least `COMPANION_RADIUS` from the centre, grown by
    `MASK_GROWTH` pixels (the companion's light beyond its core), no nearer the centre than
    `MASK_INNER`; the neighbours' light beyond their support, which their models do not hold,
    too. A new user's crowded field (250 Kolmogorov x Airy stars per 350^2) had 46-49 of its
    174 P0 stars with such pixels, and P0 1.0 % too much light beyond 6 px (photometry -6.5
    mmag against a sparse field's P0 of the same stars; -0.1 with them masked). Returns
    (N, n, n) bool."""
    used = stars.used & ((stars.flags & MOVED) == 0)
    filtered, peak, found = _companions(stars, clean, model, variance, MASK_SIGMA)
    with np.errstate(invalid="ignore"):
        found &= used[:, None, None] & (filtered > MASK_FRACTION * np.abs(peak)[:, None, None])
    size = clean.shape[-1]
    rows, columns = np.indices((size, size))
    radius = np.hypot(columns - (stars.x_0 - stars.column)[:, None, None],
                      rows - (stars.y_0 - stars.row)[:, None, None])
    return ndimage.binary_dilation(found, _MASK_DISK[None]) & (radius >= MASK_INNER)


def _companions(stars, clean, model, variance, nsigma):
    """The filtered residual of every star, its filtered model's peak, and where the filtered
    residual lies beyond ``nsigma`` of its noise and of the point opposite, beyond
    `COMPANION_RADIUS`."""
    kernel = _COMPANION_KERNEL[None]
    residual = np.where(stars.valid, clean - model, 0.0)
    filtered = ndimage.correlate(residual, kernel, mode="constant")
    noise = np.sqrt(ndimage.correlate(variance, kernel**2, mode="constant", cval=np.inf))
    # the opposite point through each star's centre (integer pixels: a star is
    # reflected about the pixel nearest its centre, half a pixel at most from it)
    size = residual.shape[-1]
    centre_x = np.rint(stars.x_0 - stars.column).astype(int)
    centre_y = np.rint(stars.y_0 - stars.row).astype(int)
    rows, columns = np.indices((size, size))
    mirror_rows = 2 * centre_y[:, None, None] - rows
    mirror_columns = 2 * centre_x[:, None, None] - columns
    inside = ((mirror_rows >= 0) & (mirror_rows < size) & (mirror_columns >= 0)
              & (mirror_columns < size))
    star = np.arange(len(residual))[:, None, None]
    opposite = np.where(inside, filtered[star, np.clip(mirror_rows, 0, size - 1),
                                         np.clip(mirror_columns, 0, size - 1)], 0.0)
    opposite_noise = np.where(inside, noise[star, np.clip(mirror_rows, 0, size - 1),
                                            np.clip(mirror_columns, 0, size - 1)], np.inf)
    far = (np.hypot(rows - centre_y[:, None, None], columns - centre_x[:, None, None])
           >= COMPANION_RADIUS)
    peak = ndimage.correlate(np.where(stars.valid, model, 0.0), kernel, mode="constant")[
        np.arange(len(model)), np.clip(centre_y, 0, size - 1), np.clip(centre_x, 0, size - 1)]
    with np.errstate(invalid="ignore", divide="ignore"):
        found = (far & (filtered > nsigma * noise)
                 & (filtered - opposite > nsigma * np.hypot(noise, opposite_noise)))
    return filtered, peak, found


def _expected(values, stars, used):
    """Each star's expected ``values`` from the other stars of its image used for P0: a
    plane over the image (a PSF varying over the field: FWHM 3.0 -> 3.9 px across a grid
    fit's image left its edge stars 9 % larger than their neighbours), fitted with one
    clipping at 3 robust sigma, plus the median of the residuals of its `MISFIT_NEIGHBOURS`
    nearest (NaN in an image with fewer than 5 of them)."""
    out = np.full(values.shape, np.nan)
    position = np.column_stack([stars.x_0, stars.y_0])
    for image in np.unique(stars.image[used]):
        mine = np.flatnonzero(used & (stars.image == image) & np.isfinite(values))
        if mine.size < 5:
            continue
        members = np.flatnonzero(stars.image == image)
        design = np.column_stack([np.ones(len(stars.x_0)), position])
        plane = clipped_least_squares(values[mine], design[mine], nsigma=3.0,
                                      max_iterations=2, min_kept=3).params
        residual = values - design @ plane
        count = min(MISFIT_NEIGHBOURS + 1, mine.size)
        _, nearest = cKDTree(position[mine]).query(position[members], k=count)
        rows = mine[nearest.reshape(len(members), count)]
        others = residual[rows]
        # each star's own row left out, else its farthest: `count - 1` others
        own = rows == members[:, None]
        own[~own.any(axis=1), -1] = True
        out[members] = design[members] @ plane + np.median(
            others[~own].reshape(len(members), count - 1), axis=1)
    return out


def neighbour_table(stars):
    """One row per neighbour the fit modelled (see `PSFFitResult`)."""
    mine = ~stars.p0
    table = Table()
    table["image"] = stars.image[mine]
    for name, values in (("x_fit", stars.x_0), ("y_fit", stars.y_0), ("flux_fit", stars.flux)):
        table[name] = values[mine]
    table["flux_fit"].unit = "electron"
    table["flags"] = stars.flags[mine]
    return table


def star_table(flags, image_index, positions, stars, variance):
    """One row per input star (see `PSFFitResult`)."""
    used = np.flatnonzero(flags == 0)
    flags = flags.copy()
    mine = stars.p0
    flags[used] |= stars.flags[mine] | np.where(stars.rejected[mine], UNLIKE, 0)
    share = np.where((stars.flags[mine] & MOVED) | stars.rejected[mine], 0.0,
                     stars.flux[mine]**2 / variance[mine].mean(axis=(1, 2)))
    table = Table()
    table["image"] = image_index
    table["x_init"] = np.concatenate([np.asarray(xy)[:, 0] for xy in positions if xy.size])
    table["y_init"] = np.concatenate([np.asarray(xy)[:, 1] for xy in positions if xy.size])
    for name, values in (("x_fit", stars.x_0[mine]), ("y_fit", stars.y_0[mine]),
                         ("flux_fit", stars.flux[mine]), ("weight", share / share.sum())):
        column = np.full(len(flags), np.nan if name != "weight" else 0.0)
        column[used] = values
        table[name] = column
    table["flux_fit"].unit = "electron"
    table["flags"] = flags
    masked = np.zeros(len(flags), dtype=int)
    masked[used] = stars.masked[mine].sum(axis=(1, 2))
    table["masked"] = masked
    return table
