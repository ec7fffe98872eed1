"""The charge density on each pixel boundary, integrated along it, from an oversampled model
(replaces G15's mean of the two pixels, eq. density-approx)."""

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError

__all__ = ["exact_boundary_density"]


def exact_boundary_density(oversampled_e, oversampling):
    """Pixel image and charge density integrated along every boundary, from an oversampled model.

    G15 approximates the charge density drifting on the boundary between pixels p and q by
    (Q_p + Q_q) / 2 (eq. density-approx), which underestimates the BF of undersampled spots
    (fig. bva). Here the surface density on each boundary line is interpolated from the
    sub-pixel charges with the fourth-order interface formula
    f(0) = (-s_{-2} + 7 s_{-1} + 7 s_0 - s_1) / 12 (exact for cubic densities) and summed
    along the boundary.

    Parameters
    ----------
    oversampled_e : ndarray, shape (ny * n, nx * n)
        Charge in sub-pixels, e-: pixel (x, y) is the block
        ``[y*n:(y+1)*n, x*n:(x+1)*n]``, e.g. a GalSim profile drawn with scale 1/n.
    oversampling : int
        n, at least 2.

    Returns
    -------
    image_e : ndarray, shape (ny, nx)
        Pixel charges (block sums), e-.
    density : (ndarray, ndarray)
        Density on the north boundaries, shape (ny - 1, nx), and on the east boundaries,
        shape (ny, nx - 1), e- (surface density integrated along the boundary; equals Q for a
        flat image). Pass as ``density=`` to `~bfpsf.model.redistribution.redistribute`.
    """
    n = int(oversampling)
    sub = np.asarray(oversampled_e, dtype=float)
    if n < 2 or n != oversampling:
        msg = f"oversampling must be an integer of at least 2, got {oversampling}"
        raise BFPSFValueError(msg, oversampling)
    if sub.ndim != 2 or sub.shape[0] % n or sub.shape[1] % n:
        msg = (f"oversampled image must be 2-D with sides multiple of oversampling={n}, "
               f"got shape {sub.shape}")
        raise BFPSFInputError(msg, sub.shape)
    if not np.all(np.isfinite(sub)):
        msg = f"oversampled image has {np.count_nonzero(~np.isfinite(sub))} non-finite values"
        raise BFPSFInputError(msg)
    ny, nx = sub.shape[0] // n, sub.shape[1] // n
    image = sub.reshape(ny, n, nx, n).sum(axis=(1, 3))
    # North boundaries: lines between sub-rows r-1 and r, r = (y + 1) n, y = 0..ny-2.
    r = np.arange(1, ny) * n
    # With n >= 2, rows r - 2 and r + 1 lie inside the two pixels sharing the boundary.
    line = (7.0 * (sub[r - 1] + sub[r]) - (sub[r - 2] + sub[r + 1])) / 12.0
    density_north = n * line.reshape(ny - 1, nx, n).sum(axis=2)
    c = np.arange(1, nx) * n
    column = (7.0 * (sub[:, c - 1] + sub[:, c])
              - (sub[:, c - 2] + sub[:, c + 1])) / 12.0
    density_east = n * column.reshape(ny, n, nx - 1).sum(axis=1)
    return image, (density_north, density_east)
