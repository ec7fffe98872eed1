"""G15 section 6.2 experiments: the error of the boundary-density approximation (fig. bva) and of
the one-step model against the build-up during the exposure, on Moffat spots drawn with GalSim."""

import galsim
import numpy as np
from astropy.table import Table

from ..model.buildup import redistribute_buildup
from ..model.density import exact_boundary_density
from ..model.redistribution import redistribute

__all__ = ["moffat_charge", "density_approximation_error", "buildup_error"]


def moffat_charge(fwhm, peak, *, beta=2.5, size=None, oversampling=8, offset=(0.0, 0.0)):
    """A Moffat spot drawn with GalSim on an oversampled grid, in electrons.

    Parameters
    ----------
    fwhm : float
        Image quality (FWHM of the Moffat before pixel integration), pixels.
    peak : float
        Charge of the brightest pixel, e-.
    beta : float, optional
        Moffat index. Default 2.5.
    size : int, optional
        Stamp side in pixels (odd). Default ``8 * fwhm + 17`` rounded to odd.
    oversampling : int, optional
        Sub-pixels per pixel side. Default 8.
    offset : (float, float), optional
        Sub-pixel offset of the centre from the central pixel, pixels.

    Returns
    -------
    image_e : ndarray (size, size)
        Pixel charges, e-.
    oversampled_e : ndarray (size * n, size * n)
        Sub-pixel charges, e- (for `exact_boundary_density`).
    """
    n = int(oversampling)
    if size is None:
        size = int(8 * fwhm + 17) | 1
    profile = galsim.Moffat(beta=beta, fwhm=float(fwhm))
    sub = profile.drawImage(nx=size * n, ny=size * n, scale=1.0 / n, method="auto",
                            offset=(offset[0] * n, offset[1] * n)).array.astype(float)
    # The profile is centred on the true centre of the sub-pixel grid, which (size odd) is the
    # centre of the central pixel.
    image = sub.reshape(size, n, size, n).sum(axis=(1, 3))
    factor = peak / image.max()
    return image * factor, sub * factor


def _sigma(image):
    """Adaptive-moment size (Mxx Myy - Mxy^2)^(1/4), px: G15's IQ (section 3.2), measured
    with galsim.hsm.FindAdaptiveMom (elliptical Gaussian weight matched to the object)."""
    moments = galsim.hsm.FindAdaptiveMom(galsim.ImageD(np.ascontiguousarray(image)),
                                         strict=True)
    return float(moments.moments_sigma)


def _moffat_for_iq(iq, peak, *, beta, oversampling):
    """Moffat spot whose pixelised adaptive-moment size is ``iq`` px (to 1e-4 relative)."""
    fwhm = 2.1 * iq  # close for beta = 2.5; refined by fixed-point steps below
    for _ in range(8):
        image, sub = moffat_charge(fwhm, peak, beta=beta, oversampling=oversampling)
        sigma = _sigma(image)
        if abs(sigma / iq - 1.0) < 1e-4:
            break
        fwhm *= iq / sigma
    return fwhm, sigma, image, sub


def density_approximation_error(shifts, iq=(1.0, 1.2, 1.4, 1.6, 2.0, 2.5, 3.0, 3.5), *,
                                peak=1e5, oversampling=8, beta=2.5):
    """BF size change with G15's boundary density and with the exact one (G15 fig. bva).

    For each image quality, a Moffat spot with ``peak`` electrons in its brightest pixel is
    redistributed with rho = (Q_p + Q_q)/2 (eq. density-approx) and with the density
    integrated along each boundary of the oversampled model (`exact_boundary_density`).

    Parameters
    ----------
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    iq : sequence of float
        Image qualities, px, as G15 defines them (section 3.2): the adaptive-moment size
        (Mxx Myy - Mxy^2)^(1/4) of the pixelised spot without BF. The Moffat FWHM is adjusted
        to match.
    peak : float
        Charge of the brightest pixel, e-. Default 1e5 (G15 fig. bva).
    oversampling : int
        Sub-pixels per pixel side of the model used for the exact density. Default 8.
    beta : float
        Moffat index. Default 2.5.

    Returns
    -------
    astropy.table.Table
        Columns ``iq`` (px), ``fwhm`` (Moffat FWHM, px), ``dsigma_mean`` and ``dsigma_exact``
        (relative size increase IQ/IQ0 - 1 with each density), ``error`` (dsigma_mean -
        dsigma_exact, relative size; negative: the approximation underestimates the size) and
        ``error_fraction`` (error / dsigma_exact: the fraction of the BF effect misestimated).
    """
    rows = []
    for target in iq:
        fwhm, sigma0, image, sub = _moffat_for_iq(target, peak, beta=beta,
                                                  oversampling=oversampling)
        _, density = exact_boundary_density(sub, oversampling)
        mean = _sigma(redistribute(image, shifts)) / sigma0 - 1.0
        exact = _sigma(redistribute(image, shifts, density=density)) / sigma0 - 1.0
        rows.append((target, fwhm, mean, exact, mean - exact, (mean - exact) / exact))
    return Table(rows=rows, names=("iq", "fwhm", "dsigma_mean", "dsigma_exact", "error",
                                   "error_fraction"))


def buildup_error(shifts, peaks=(2e4, 5e4, 1e5, 1.5e5), *, fwhm=4.0, nsteps=32, beta=2.5):
    """One-step BF model against the time-stepped build-up, for Moffat spots.

    Sizes are adaptive moments (G15 IQ); ``nsteps`` steps of
    `bfpsf.model.buildup.redistribute_buildup` (K = 32: integration error ~2e-3
    of the difference).

    Returns
    -------
    astropy.table.Table
        Columns ``peak`` (e-, brightest pixel), ``dsigma_one_step`` and ``dsigma_buildup``
        (relative size increase with each model), ``size_difference`` (their difference,
        relative size), ``size_difference_fraction`` (over dsigma_buildup) and
        ``max_pixel_difference`` (max |Q_one_step - Q_buildup| / max |dQ_buildup|).
    """
    rows = []
    unit, _ = moffat_charge(fwhm, 1.0, beta=beta)
    sigma0 = _sigma(unit)
    for peak in peaks:
        image = unit * peak
        one = redistribute(image, shifts)
        steps = redistribute_buildup(image, shifts, nsteps=nsteps)
        d_one = _sigma(one) / sigma0 - 1.0
        d_steps = _sigma(steps) / sigma0 - 1.0
        pixel = np.abs(one - steps).max() / np.abs(steps - image).max()
        rows.append((peak, d_one, d_steps, d_one - d_steps, (d_one - d_steps) / d_steps, pixel))
    return Table(rows=rows, names=("peak", "dsigma_one_step", "dsigma_buildup",
                                   "size_difference", "size_difference_fraction",
                                   "max_pixel_difference"))
