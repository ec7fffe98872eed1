"""Charge redistribution across pixel boundaries (G15 eq. scrambling_model).

Each boundary between two pixels moves by the boundary shift a^X times the charge around it,
and the charge drifting on that boundary is transferred from one pixel to the other:

    dQ_00 = 1/4 sum_X sum_ij a^X_ij Q_ij (Q_00 + Q_X)          (G15 eq. scrambling_model)

The operator is computed from boundary fluxes: for every boundary between pixel p and its
north (or east) neighbour q, the flux F = 1/4 (a^N * Q)(p) (Q_p + Q_q) is added to p and taken
from q, so charge is conserved to rounding by construction.
"""

import numpy as np
import scipy.fft

from ..errors import BFPSFInputError, BFPSFValueError
from ..shifts import BoundaryShifts

__all__ = ["redistribution_delta", "redistribute", "boundary_fluxes"]


def _as_shifts(shifts):
    """Accept a BoundaryShifts or anything carrying one in ``.shifts`` (a Calibration)."""
    if isinstance(shifts, BoundaryShifts):
        return shifts
    inner = getattr(shifts, "shifts", None)
    if isinstance(inner, BoundaryShifts):
        return inner
    msg = f"expected BoundaryShifts or an object with a .shifts attribute, got {type(shifts).__name__}"
    raise BFPSFValueError(msg, shifts)


def _as_image(image):
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        msg = f"image must be 2-D [y, x], got {image.ndim} dimensions"
        raise BFPSFInputError(msg, image.shape)
    bad = np.count_nonzero(~np.isfinite(image))
    if bad:
        msg = (f"image has {bad} non-finite pixels; interpolate or replace them before "
               "redistributing (charge cannot be moved through an unknown pixel)")
        raise BFPSFInputError(msg, bad)
    return image


def _correlate(image, kernels):
    """sum_{dx,dy} K(dx, dy) image[y + dy, x + dx] for each kernel, zero outside the image."""
    ny, nx = image.shape
    m = kernels[0].shape[0] // 2
    shape = (scipy.fft.next_fast_len(ny + 2 * m, real=True),
             scipy.fft.next_fast_len(nx + 2 * m, real=True))
    image_ft = scipy.fft.rfft2(image, shape)
    results = []
    for kernel in kernels:
        # Correlation = convolution with the kernel flipped through its centre.
        kernel_ft = scipy.fft.rfft2(kernel[::-1, ::-1], shape)
        full = scipy.fft.irfft2(image_ft * kernel_ft, shape)
        results.append(full[m:m + ny, m:m + nx])
    return results


def boundary_fluxes(image_e, shifts):
    """Charge moved across each north and east boundary, e-.

    Parameters
    ----------
    image_e : ndarray [y, x]
        Charge image in electrons.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.

    Returns
    -------
    flux_north : ndarray, shape (ny - 1, nx)
        Charge gained by pixel (x, y) from pixel (x, y + 1) through their shared boundary.
    flux_east : ndarray, shape (ny, nx - 1)
        Charge gained by pixel (x, y) from pixel (x + 1, y).
    """
    image = _as_image(image_e)
    shifts = _as_shifts(shifts)
    shift_north, shift_east = _correlate(image, [shifts.north, shifts.east])
    flux_north = 0.25 * shift_north[:-1, :] * (image[:-1, :] + image[1:, :])
    flux_east = 0.25 * shift_east[:, :-1] * (image[:, :-1] + image[:, 1:])
    return flux_north, flux_east


def redistribution_delta(image_e, shifts):
    """dQ of G15 eq. scrambling_model: the charge each pixel gains, e-.

    Quadratic in the image: ``redistribution_delta(F * P, s) = F**2 * redistribution_delta(P, s)``.
    Pixels outside the image hold no charge and no charge crosses the image border, so
    ``dQ.sum() == 0`` to rounding.
    """
    flux_north, flux_east = boundary_fluxes(image_e, shifts)
    delta = np.zeros(np.shape(image_e))
    delta[:-1, :] += flux_north
    delta[1:, :] -= flux_north
    delta[:, :-1] += flux_east
    delta[:, 1:] -= flux_east
    return delta


def redistribute(image_e, shifts):
    """Forward brighter-fatter: the image after charge redistribution, e-.

    Parameters
    ----------
    image_e : array_like [y, x]
        Charge the pixels would hold without brighter-fatter, e-. Non-finite pixels are refused.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (end of exposure; the 1/4 of G15 includes the build-up 1/2).

    Returns
    -------
    ndarray [y, x]
        Q' = Q + dQ (G15 eq. perturbPTC), total charge unchanged.
    """
    image = _as_image(image_e)
    return image + redistribution_delta(image, shifts)
