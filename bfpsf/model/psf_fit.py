"""Fitting the base PSF P0 from stars of all fluxes at once.

Every star i is modelled as (G15 eq. scrambling_model folded into the PSF)

    d_i = F_i p_i + F_i**2 R[p_i] + noise,       p_i = P0 pixelised at the phase of star i,

so that, once each star's predicted brighter-fatter term is removed, the bright stars (which
give the signal-to-noise) no longer bias P0 towards a broader profile. The fit is a fixed-point
iteration, as in the ePSF construction of Anderson & King (2000) and photutils'
`~photutils.psf.EPSFBuilder`:

1. start from a stack of d_i / F_i on the oversampled grid (nearest node, inverse-variance
   weights, empty nodes filled from their neighbours);
2. for each star, fit F_i (and, after ``hold_positions`` iterations at the flux-weighted
   centroids, x_i and y_i) with the current `FluxDependentPSF`, with pixel variances from the
   model (sky and read noise included), not from the noisy data;
3. add to P0 the inverse-variance weighted average, in each node, of the normalised residuals
   (d_i - model_i) / F_i at the samples that fall in the node, then renormalise each phase to
   unit flux;
4. repeat until the largest change of P0 is below ``tolerance`` times its peak.

Binning the residuals rather than the data removes the broadening that nearest-node binning
would otherwise cause: at the fixed point the binned residuals vanish.
"""

from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import scipy.optimize
from astropy.table import Table

from ..errors import BFPSFConvergenceError, BFPSFInputError, BFPSFValueError
from .psf import FluxDependentPSF
from ..shifts import as_shifts

__all__ = ["PSFFitResult", "fit_psf", "STAR_FLAGS"]

#: Per-star flags of `fit_psf` (bit values).
STAR_FLAGS = {
    1: "cutout outside the image (star not used)",
    2: "non-finite pixel in the cutout (star not used)",
    4: "non-positive flux estimate (star not used)",
    8: "position fit failed or moved more than 1 pixel (star not used in the last iteration)",
}


@dataclass(frozen=True)
class PSFFitResult:
    """Result of `fit_psf`.

    Attributes
    ----------
    psf : FluxDependentPSF
        The model with the fitted P0 (``psf.data``), unit flux.
    stars : astropy.table.Table
        One row per input star: ``image``, ``x_init``, ``y_init``, ``x_fit``, ``y_fit``
        (pixels), ``flux_fit`` (e-), ``weight`` (share of the stack), ``flags`` (`STAR_FLAGS`).
    iterations : int
    converged : bool
    changes : ndarray
        Largest change of P0 at each iteration, relative to its peak.
    """

    psf: FluxDependentPSF
    stars: Table
    iterations: int
    converged: bool
    changes: np.ndarray


def _as_star_list(images, positions):
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


class _Star:
    """Cutout of one star: pixel coordinates, data, variance."""

    __slots__ = ("x", "y", "data", "variance", "flux", "x_0", "y_0", "flags", "noise_floor")

    def __init__(self, image, x_0, y_0, half, noise_floor):
        self.flags = 0
        self.flux, self.x_0, self.y_0 = np.nan, x_0, y_0
        col, row = int(np.rint(x_0)), int(np.rint(y_0))
        ny, nx = image.shape
        if not (np.isfinite(x_0) and np.isfinite(y_0)) or (
                col - half < 0 or row - half < 0 or col + half >= nx or row + half >= ny):
            self.flags |= 1
            return
        cutout = image[row - half:row + half + 1, col - half:col + half + 1]
        if not np.all(np.isfinite(cutout)):
            self.flags |= 2
            return
        y, x = np.mgrid[row - half:row + half + 1, col - half:col + half + 1]
        self.x, self.y, self.data = x.ravel().astype(float), y.ravel().astype(float), cutout.ravel()
        # Data-based variance only for the first stack; model-based once fitted (a variance
        # from the noisy data itself biases the weighted means).
        self.noise_floor = noise_floor
        self.variance = np.clip(self.data, 0.0, None) + noise_floor
        self.flux = float(self.data.sum())
        if self.flux <= 0:
            self.flags |= 4
            return
        weights = np.clip(self.data, 0.0, None)
        self.x_0 = float((weights * self.x).sum() / weights.sum())
        self.y_0 = float((weights * self.y).sum() / weights.sum())

    @property
    def usable(self):
        return self.flags & 7 == 0


def _node_indices(psf, star):
    xi, yi, outside = psf.data_coordinates(star.x - star.x_0, star.y - star.y_0)
    col = np.rint(xi).astype(int)
    row = np.rint(yi).astype(int)
    return row, col, ~outside


def _stack(shape, stars, psf_like, values_of):
    """Inverse-variance weighted nearest-node average of per-star normalised samples."""
    total = np.zeros(shape)
    weight = np.zeros(shape)
    for star in stars:
        row, col, inside = _node_indices(psf_like, star)
        values, weights = values_of(star)
        np.add.at(total, (row[inside], col[inside]), (weights * values)[inside])
        np.add.at(weight, (row[inside], col[inside]), weights[inside])
    return total, weight


def _fill_empty(stack, weight):
    """Fill nodes without samples by normalised Gaussian interpolation from their neighbours."""
    empty = weight <= 0
    if not empty.any():
        return stack
    filled = stack.copy()
    have = (~empty).astype(float)
    for sigma in (0.7, 1.5, 3.0):
        numerator = scipy.ndimage.gaussian_filter(np.where(empty, 0.0, filled), sigma)
        denominator = scipy.ndimage.gaussian_filter(have, sigma)
        ok = empty & (denominator > 1e-3)
        filled[ok] = numerator[ok] / denominator[ok]
        have = np.where(ok, 1.0, have)
        empty = empty & ~ok
    filled[empty] = 0.0
    return filled


def _normalise(data, oversampling):
    oy, ox = oversampling
    total = data.sum()
    if not total > 0:
        msg = f"the stacked PSF has non-positive total {total:.3g}; check the star list"
        raise BFPSFValueError(msg, total)
    return data * (oy * ox / total)


def _fit_star(psf, star, *, positions=True):
    """Least-squares F (and x_0, y_0) of one star with the current model; False on failure."""
    sigma = np.sqrt(star.variance)
    if not positions:
        # Linear in F apart from the small F|F| term: two Newton steps are exact enough.
        flux = star.flux
        for _ in range(3):
            base = psf.evaluate(star.x, star.y, 1.0, star.x_0, star.y_0)
            model = psf.evaluate(star.x, star.y, flux, star.x_0, star.y_0)
            bf_unit = (model - flux * base) / (flux * abs(flux))
            derivative = base + 2 * abs(flux) * bf_unit
            flux += (np.sum(derivative * (star.data - model) / sigma**2)
                     / np.sum(derivative**2 / sigma**2))
        if not (np.isfinite(flux) and flux > 0):
            return False
        star.flux = float(flux)
        _update_variance(psf, star)
        return True

    def residuals(params):
        return (star.data - psf.evaluate(star.x, star.y, *params)) / sigma

    start = np.array([star.flux, star.x_0, star.y_0])
    try:
        solution = scipy.optimize.least_squares(residuals, start, method="lm",
                                                x_scale=[max(star.flux, 1.0), 1.0, 1.0])
    except (ValueError, np.linalg.LinAlgError):
        return False
    flux, x_0, y_0 = solution.x
    if not (solution.success and flux > 0 and abs(x_0 - start[1]) < 1 and abs(y_0 - start[2]) < 1):
        return False
    star.flux, star.x_0, star.y_0 = float(flux), float(x_0), float(y_0)
    _update_variance(psf, star)
    return True


def _update_variance(psf, star):
    """Pixel variances from the fitted model (not the noisy data), e-**2."""
    model = psf.evaluate(star.x, star.y, star.flux, star.x_0, star.y_0)
    star.variance = np.clip(model, 0.0, None) + star.noise_floor


def fit_psf(images_e, positions, shifts, *, oversampling=2, size=25, read_noise=0.0,
            sky_e=0.0, include_bf=True, initial=None, hold_positions=10, damping=1.0,
            max_iterations=40, tolerance=3e-4, strict=False, **psf_kwargs):
    """Fit the base PSF P0 of `FluxDependentPSF` from isolated stars of all fluxes.

    Parameters
    ----------
    images_e : ndarray [y, x] or sequence of them
        Background-subtracted images in electrons.
    positions : (N, 2) array_like of (x, y), or a sequence of them (one per image)
        Approximate star centres, pixels. Stars must be isolated within ``size`` pixels.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (G15 eq. def-a).
    oversampling : int, optional
        Oversampling of P0. Default 2: with 144 noisy stars (peaks 3-120 ke-) it recovers
        the P0 size to 0.05 %, where oversampling 4 (9 stars per phase cell) neither
        converges nor does better than -0.5 %; use 4 with several hundred stars.
    size : int, optional
        Side of the star cutouts and of the P0 support, pixels (odd). Default 25.
    read_noise : float, optional
        Read noise, e-, for the inverse-variance weights (Poisson noise of the data is
        included). Default 0.
    sky_e : float or sequence of float, optional
        Sky level subtracted from the images (one per image or one for all), e- per pixel:
        its Poisson variance enters the weights. Default 0.
    include_bf : bool, optional
        Subtract each star's BF term F_i**2 R[p_i] (default). False gives the static ePSF of
        the same stars, for comparison.
    initial : ndarray, optional
        Starting P0 on the oversampled grid (shape ``(size * oversampling + 1,)*2`` for even
        oversampling, ``size * oversampling`` squared for odd); default the stack of the stars.
    hold_positions : int, optional
        Iterations during which the star positions stay at their flux-weighted centroids
        (only fluxes are refitted). Default 10.
    damping : float, optional
        Fraction of the binned residual added to P0 at each iteration (0 < damping <= 1).
        Default 1.
    max_iterations : int, optional
        Default 40.
    tolerance : float, optional
        Stop when the largest change of P0 is below ``tolerance`` times its peak. Default
        3e-4 (noisy stars reach a floor of about 1e-4 as their positions are refitted).
    strict : bool, optional
        Raise `~bfpsf.errors.BFPSFConvergenceError` if not converged; otherwise report it in
        ``converged``. Default False.
    **psf_kwargs
        Passed to `FluxDependentPSF`; the images are in e-, so ``flux_unit`` must be
        'electron' (``gain`` is then only recorded).

    Returns
    -------
    PSFFitResult
    """
    shifts = as_shifts(shifts)
    if psf_kwargs.get("flux_unit", "electron") != "electron":
        msg = (f"fit_psf works on images in e-: flux_unit must be 'electron', got "
               f"{psf_kwargs['flux_unit']!r} (convert the fitted model with with_flux_unit)")
        raise BFPSFValueError(msg, psf_kwargs["flux_unit"])
    size = int(size)
    if size < 5 or size % 2 == 0:
        msg = f"size must be an odd number of pixels >= 5, got {size}"
        raise BFPSFValueError(msg, size)
    over = int(oversampling)
    if over < 1 or over != oversampling:
        msg = f"oversampling must be an integer >= 1, got {oversampling!r}"
        raise BFPSFValueError(msg, oversampling)
    images, positions = _as_star_list(images_e, positions)
    skies = np.broadcast_to(np.asarray(sky_e, dtype=float), (len(images),))
    if np.any(~np.isfinite(skies)) or np.any(skies < 0):
        msg = f"sky_e must be finite and >= 0 e- per pixel, got {sky_e!r}"
        raise BFPSFValueError(msg, sky_e)
    half = size // 2 + 1  # cutouts one pixel wider than P0: every node gets samples
    stars, image_index = [], []
    for index, (image, xy) in enumerate(zip(images, positions)):
        for x_0, y_0 in xy:
            stars.append(_Star(image, x_0, y_0, half, read_noise**2 + skies[index] + 1.0))
            image_index.append(index)
    usable = [star for star in stars if star.usable]
    if len(usable) < 3:
        msg = f"need at least 3 usable stars to fit a PSF, got {len(usable)} of {len(stars)}"
        raise BFPSFInputError(msg, len(usable))
    if not include_bf:
        shifts = shifts.scaled(0.0)

    npix = size * over + (1 - over % 2)
    shape = (npix, npix)
    # A model of the right geometry to map samples to nodes (its data is a placeholder).
    geometry = FluxDependentPSF(np.ones(shape), shifts, oversampling=over, mode="exact")

    def normalised_data(star):
        return star.data / star.flux, star.flux**2 / star.variance

    if initial is None:
        stack, weight = _stack(shape, usable, geometry, normalised_data)
        data = _normalise(_fill_empty(np.divide(stack, weight, out=np.zeros(shape),
                                                where=weight > 0), weight), (over, over))
    else:
        data = np.asarray(initial, dtype=float)
        if data.shape != shape:
            msg = f"initial must have shape {shape} for size {size}, got {data.shape}"
            raise BFPSFValueError(msg, data.shape)
        data = _normalise(data, (over, over))
    psf = FluxDependentPSF(data, shifts, oversampling=over, **psf_kwargs)
    changes = []
    converged = False
    for iteration in range(1, max_iterations + 1):
        # Hold the centroids while P0 is far from converged: free positions would absorb a
        # phase-dependent distortion of the first stack (bright stars at different phases
        # carry different BF), a near-degeneracy the iteration would not leave.
        free_positions = iteration > hold_positions
        for star in usable:
            star.flags &= ~8
            if not _fit_star(psf, star, positions=free_positions):
                star.flags |= 8
        fitted = [star for star in usable if not star.flags & 8]

        def normalised_residual(star, psf=psf):
            model = psf.evaluate(star.x, star.y, star.flux, star.x_0, star.y_0)
            return (star.data - model) / star.flux, star.flux**2 / star.variance

        residual, weight = _stack(shape, fitted, psf, normalised_residual)
        update = np.divide(residual, weight, out=np.zeros(shape), where=weight > 0)
        # Nodes no star samples (phases nobody covers) follow their neighbours' update:
        # left alone they would distort the spline at the sampled phases around them.
        update = _fill_empty(update, weight)
        new_data = _normalise(psf.data + damping * update, (over, over))
        change = float(np.abs(new_data - psf.data).max() / np.abs(psf.data).max())
        changes.append(change)
        psf = FluxDependentPSF(new_data, shifts, oversampling=over, **psf_kwargs)
        if change < tolerance and iteration > hold_positions:
            converged = True
            break
    if not converged and strict:
        msg = (f"P0 did not converge in {max_iterations} iterations (last change "
               f"{changes[-1]:.3g} of the peak, tolerance {tolerance:.3g})")
        raise BFPSFConvergenceError(msg)
    for star in usable:  # final positions and fluxes with the final P0
        star.flags &= ~8
        if not _fit_star(psf, star):
            star.flags |= 8
    total_weight = sum(star.flux**2 / star.variance.mean() for star in usable
                       if not star.flags & 8)
    table = Table()
    table["image"] = np.array(image_index, dtype=int)
    table["x_init"] = np.concatenate([np.asarray(xy)[:, 0] for xy in positions if xy.size])
    table["y_init"] = np.concatenate([np.asarray(xy)[:, 1] for xy in positions if xy.size])
    table["x_fit"] = [star.x_0 if star.usable else np.nan for star in stars]
    table["y_fit"] = [star.y_0 if star.usable else np.nan for star in stars]
    table["flux_fit"] = [star.flux if star.usable else np.nan for star in stars]
    table["flux_fit"].unit = "electron"
    table["weight"] = [star.flux**2 / star.variance.mean() / total_weight
                       if star.usable and not star.flags & 8 else 0.0 for star in stars]
    table["flags"] = np.array([star.flags for star in stars], dtype=int)
    return PSFFitResult(psf=psf, stars=table, iterations=len(changes), converged=converged,
                        changes=np.array(changes))
