"""Charge redistribution across pixel boundaries (G15 eq. scrambling_model): the forward operator.

Its inverse is `bfpsf.model.inverse.correct`, the exact boundary charge density
`bfpsf.model.density.exact_boundary_density` and the build-up of the boundary shifts during the
exposure `bfpsf.model.buildup.redistribute_buildup`.

Each boundary between two pixels moves by the boundary shift a^X times the charge around it,
and the charge drifting on that boundary is transferred from one pixel to the other:

    dQ_00 = 1/4 sum_X sum_ij a^X_ij Q_ij (Q_00 + Q_X)          (G15 eq. scrambling_model)

The operator is computed from boundary fluxes: for every boundary between pixel p and its
north (or east) neighbour q, the flux F = 1/4 (a^N * Q)(p) (Q_p + Q_q) is added to p and taken
from q, so charge is conserved to rounding by construction. One factor 1/2 is the build-up
(the boundaries move linearly during the exposure, G15 section 5.2); the other is the boundary
charge density rho = (Q_p + Q_q) / 2 (G15 eq. density-approx), which
`~bfpsf.model.density.exact_boundary_density` replaces by the density integrated along the
boundary of an oversampled model.

Edges
-----
Pixels outside the image hold no charge (they neither push boundaries nor receive charge) and
the image border is closed: no charge crosses it, so ``redistribute(Q).sum() == Q.sum()`` to
rounding (1e-15 relative in double precision). A star within a few pixels of the border is
therefore redistributed as if the outside were empty.

Non-finite pixels
-----------------
``nan_policy='raise'`` (default) refuses an image with NaN or inf pixels, naming the count.
``nan_policy='interpolate'`` fills them with the harmonic (Laplace) interpolation of their
finite neighbours, redistributes the filled image and returns NaN again at those pixels, so
masked pixels stay masked; charge is then conserved for the filled image.
"""

import warnings

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError, BFPSFWarning
from ..shifts import as_shifts
from .nanfill import harmonic_fill
from .tiles import run_bands

__all__ = [
    "redistribution_delta",
    "redistribute",
    "boundary_fluxes",
    "single_pixel_delta",
]

_NAN_POLICIES = ("raise", "interpolate")
_DTYPES = (np.float64, np.float32)


# -- input validation ----------------------------------------------------------------------------
def as_image(image, nan_policy="raise"):
    """Return (finite float64 image, mask of the pixels that were not finite or None).

    The masked pixels of a numpy masked array are treated as non-finite (``nan_policy``)."""
    if np.ma.isMaskedArray(image):
        image = np.ma.filled(np.ma.asarray(image, dtype=float), np.nan)
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        msg = f"image must be 2-D [y, x], got {image.ndim} dimensions"
        raise BFPSFInputError(msg, image.shape)
    if image.size == 0:
        msg = f"image has no pixel (shape {image.shape})"
        raise BFPSFInputError(msg, image.shape)
    if nan_policy not in _NAN_POLICIES:
        msg = f"nan_policy must be one of {_NAN_POLICIES}, got {nan_policy!r}"
        raise BFPSFValueError(msg, nan_policy)
    if np.isfinite(np.sum(image)):
        return image, None  # cheap test first: no image-sized mask for clean images
    bad = ~np.isfinite(image)
    nbad = np.count_nonzero(bad)
    if not nbad:
        return image, None
    if nan_policy == "raise":
        msg = (f"image has {nbad} non-finite pixels; interpolate or replace them before "
               "redistributing (charge cannot be moved through an unknown pixel), or pass "
               "nan_policy='interpolate'")
        raise BFPSFInputError(msg, nbad)
    return harmonic_fill(image, bad), bad


def validate_dtype(dtype):
    dtype = np.dtype(dtype).type
    if dtype not in _DTYPES:
        msg = f"dtype must be float64 or float32, got {np.dtype(dtype).name}"
        raise BFPSFValueError(msg, dtype)
    return dtype


# -- boundary fluxes -------------------------------------------------------------------------------
def validate_density(density, shape):
    try:
        north, east = density
    except (TypeError, ValueError):
        msg = "density must be a pair (density_north, density_east)"
        raise BFPSFValueError(msg, density) from None
    ny, nx = shape
    north = np.asarray(north, dtype=float)
    east = np.asarray(east, dtype=float)
    if north.shape != (ny - 1, nx) or east.shape != (ny, nx - 1):
        msg = (f"density_north must have shape {(ny - 1, nx)} and density_east {(ny, nx - 1)} "
               f"for an image of shape {shape}, got {north.shape} and {east.shape}")
        raise BFPSFValueError(msg, (north.shape, east.shape))
    if not (np.all(np.isfinite(north)) and np.all(np.isfinite(east))):
        msg = "density contains non-finite values"
        raise BFPSFValueError(msg)
    return north, east


def _scratch(scratch, key, rows, cols, dtype):
    """A (rows, cols) array from a thread's scratch dict, reallocated when too small."""
    array = scratch.get(key)
    if array is None or array.size < rows * cols:
        array = scratch[key] = np.empty(rows * cols, dtype=dtype)
    return array[:rows * cols].reshape(rows, cols)


def _run_fluxes(image, shifts, density, dtype, workers, task, *, source=None, factor=0.5):
    """Boundary fluxes ``factor (a^X * source) rho``, e-, handed band by band to
    ``task(y0, rows, fill, scratch)``. ``fill(scratch)`` iterates over the band's tiles as
    (x0, cols, flux_north, flux_east): flux_north[r, c] is the flux through the boundary above
    pixel (x0 + c, y0 + r) for r < min(rows, ny - 1 - y0) (the image's last row has none),
    flux_east[r, c] through the boundary right of it for c < min(cols, nx - 1 - x0). The arrays
    are overwritten by the next tile.

    ``source`` (default ``image``) is the charge that moves the boundaries; ``rho`` is
    ``density`` or, by default, G15's (Q_p + Q_q) / 2 of ``image`` (eq. density-approx).
    With factor 1/2 (the time-averaged shift) this is G15 eq. delta-q-x. The fluxes are
    computed while the tile's correlations are in cache (`run_bands`), in double precision
    (float32 mode: the float32 products, exactly).
    """
    ny, nx = image.shape
    if density is not None:
        density_north, density_east = validate_density(density, image.shape)
        # rho is given: fold the factor into the kernels.
        kernel_factor = factor
    else:
        # (Q_p + Q_q) / 2: fold both the factor and the 1/2 into the kernels.
        kernel_factor = 0.5 * factor
    kernels = [shifts.north * kernel_factor, shifts.east * kernel_factor]
    sources = [image] if source is None else [source, image]

    def band_task(y0, rows, tiles, scratch):
        north_rows = min(rows, ny - 1 - y0)

        def fill(scratch):
            for x0, cols, (shift_north, shift_east), windows in tiles:
                east_cols = min(cols, nx - 1 - x0)
                shift_north = shift_north[:north_rows]
                shift_east = shift_east[:, :east_cols]
                if dtype is np.float64:  # in place of the correlations
                    flux_north, flux_east = shift_north, shift_east
                else:  # float32 products kept in double: the sums that follow are not mixed
                    flux_north = _scratch(scratch, "north", north_rows, cols, np.float64)
                    flux_east = _scratch(scratch, "east", rows, east_cols, np.float64)
                if density is None:
                    charge = windows[-1]  # the image, one more row and column than the band
                    pair_sum = _scratch(scratch, "sum", rows, cols, dtype)
                    np.add(charge[:north_rows, :cols], charge[1:north_rows + 1, :cols],
                           out=pair_sum[:north_rows])
                    np.multiply(shift_north, pair_sum[:north_rows], out=flux_north)
                    np.add(charge[:rows, :east_cols], charge[:rows, 1:east_cols + 1],
                           out=pair_sum[:, :east_cols])
                    np.multiply(shift_east, pair_sum[:, :east_cols], out=flux_east)
                else:
                    np.multiply(shift_north, density_north[y0:y0 + north_rows, x0:x0 + cols],
                                out=flux_north)
                    np.multiply(shift_east, density_east[y0:y0 + rows, x0:x0 + east_cols],
                                out=flux_east)
                yield x0, cols, flux_north, flux_east

        return task(y0, rows, fill, scratch)

    return run_bands(sources, kernels, band_task, dtype=dtype, workers=workers)


def _fluxes_of(image, shifts, density, dtype, workers, *, source=None, factor=0.5):
    """Full flux arrays (ny - 1, nx) and (ny, nx - 1) of `_run_fluxes`."""
    ny, nx = image.shape
    flux_north = np.empty((ny - 1, nx), dtype=dtype)
    flux_east = np.empty((ny, nx - 1), dtype=dtype)

    def task(y0, rows, fill, scratch):
        for x0, cols, north, east in fill(scratch):
            flux_north[y0:y0 + len(north), x0:x0 + cols] = north
            flux_east[y0:y0 + rows, x0:x0 + east.shape[1]] = east

    _run_fluxes(image, shifts, density, dtype, workers, task, source=source, factor=factor)
    return flux_north, flux_east


def add_redistribution(result, image, shifts, density, dtype, workers, *, source=None, factor=0.5,
                   base=None):
    """Add to ``result`` (float64, in place) the charge each pixel gains from its boundaries;
    with ``base`` (an array like ``image``), set ``result`` to ``base`` plus that gain.

    Each tile's fluxes are added and subtracted in double precision while they are in cache;
    a flux whose boundary separates two tiles is kept and subtracted by the next tile on the
    right (east) or, for the boundaries between two bands (north), from the same array once
    all bands are done (a band's thread writes only its own rows). Charge is thus conserved
    to rounding whatever ``dtype`` the fluxes were computed in.
    """
    ny, nx = image.shape

    def task(y0, rows, fill, scratch):
        north_rows = min(rows, ny - 1 - y0)
        inside = min(north_rows, rows - 1)  # north boundaries with both pixels in the band
        crossing = np.empty(nx) if north_rows == rows else None  # fluxes are float64
        east_carry = None
        for x0, cols, flux_north, flux_east in fill(scratch):
            # The tile's gain, built in a cache-resident buffer and written to result once.
            gain = _scratch(scratch, "gain", rows, cols, np.float64)
            if base is None:
                gain[:north_rows] = flux_north
                gain[north_rows:] = 0.0
            else:
                np.add(base[y0:y0 + north_rows, x0:x0 + cols], flux_north,
                       out=gain[:north_rows])
                # The image's last row has no boundary above it.
                gain[north_rows:] = base[y0 + north_rows:y0 + rows, x0:x0 + cols]
            gain[1:inside + 1] -= flux_north[:inside]
            east_cols = flux_east.shape[1]
            gain[:, :east_cols] += flux_east
            inside_east = min(east_cols, cols - 1)  # east boundaries inside the tile
            gain[:, 1:inside_east + 1] -= flux_east[:, :inside_east]
            if east_carry is not None:  # the boundary left of the tile, from the tile before
                gain[:, 0] -= east_carry
            east_carry = flux_east[:, cols - 1].copy() if east_cols == cols else None
            if crossing is not None:
                crossing[x0:x0 + cols] = flux_north[rows - 1]
            target = result[y0:y0 + rows, x0:x0 + cols]
            if base is None:
                target += gain
            else:
                target[...] = gain
        return None if crossing is None else (y0 + rows, crossing)

    for crossing in _run_fluxes(image, shifts, density, dtype, workers, task, source=source,
                                factor=factor):
        if crossing is not None:
            row, flux = crossing
            result[row] -= flux
    return result


def boundary_fluxes(image_e, shifts, *, density=None, dtype=np.float64, workers=None):
    """Charge moved across each north and east boundary, e-.

    Parameters
    ----------
    image_e : ndarray [y, x]
        Charge image in electrons. Non-finite pixels are refused.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    density : (ndarray, ndarray), optional
        Charge density on each boundary, integrated along it (e- per pixel of boundary
        displacement), shapes (ny - 1, nx) and (ny, nx - 1), e.g. from
        `~bfpsf.model.density.exact_boundary_density`. Default: G15's (Q_p + Q_q) / 2
        (eq. density-approx).
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the FFT correlation and of the fluxes. float32 is about twice as fast;
        the fluxes are then accurate to ~1e-6 of the largest flux, and charge stays conserved
        (the fluxes are added and subtracted in double precision).
    workers : int, optional
        Threads, each computing whole bands of FFT tiles (scipy.fft and numpy release the
        GIL). Default None: every CPU this process may use (``os.sched_getaffinity``, else
        ``os.cpu_count()``); negative values count back from it as in `scipy.fft` (-1: all,
        -2: all but one). The result does not depend on it, bit for bit.

    Returns
    -------
    flux_north : ndarray, shape (ny - 1, nx)
        Charge gained by pixel (x, y) from pixel (x, y + 1) through their shared boundary,
        1/2 (a^N * Q)(x, y) rho_N(x, y) (G15 eq. delta-q-x).
    flux_east : ndarray, shape (ny, nx - 1)
        Charge gained by pixel (x, y) from pixel (x + 1, y).
    """
    image, _ = as_image(image_e)
    return _fluxes_of(image, as_shifts(shifts), density, validate_dtype(dtype), workers)


def redistribution_delta(image_e, shifts, *, density=None, dtype=np.float64, workers=None):
    """dQ of G15 eq. scrambling_model: the charge each pixel gains, e-.

    Quadratic in the image: ``redistribution_delta(F * P, s) = F**2 * redistribution_delta(P, s)``
    (with the default density). Pixels outside the image hold no charge and no charge crosses
    the image border, so ``dQ.sum() == 0`` to rounding. Keywords as in `boundary_fluxes`.
    """
    image, _ = as_image(image_e)
    return add_redistribution(np.zeros(image.shape), image, as_shifts(shifts), density,
                          validate_dtype(dtype), workers)


def redistribute(image_e, shifts, *, density=None, nan_policy="raise", dtype=np.float64,
                 workers=None):
    """Forward brighter-fatter: the image after charge redistribution, e-.

    Parameters
    ----------
    image_e : array_like [y, x]
        Charge the pixels would hold without brighter-fatter, e-.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (end of exposure; the 1/4 of G15 includes the build-up 1/2).
    density : (ndarray, ndarray), optional
        Exact boundary charge density (see `~bfpsf.model.density.exact_boundary_density`);
        default G15's mean.
    nan_policy : {'raise', 'interpolate'}, optional
        What to do with non-finite pixels (module docstring). Default 'raise'.
    dtype, workers
        FFT precision and threads, see `boundary_fluxes`.

    Returns
    -------
    ndarray [y, x]
        Q' = Q + dQ (G15 eq. perturbPTC), total charge unchanged (to 1e-15 relative).
    """
    image, bad = as_image(image_e, nan_policy)
    result = add_redistribution(np.empty(image.shape), image, as_shifts(shifts), density,
                            validate_dtype(dtype), workers, base=image)
    _warn_beyond_first_order(image, result)
    if bad is not None:
        result[bad] = np.nan
    return result


def _warn_beyond_first_order(image, result):
    """Warn when the image is so bright that G15's first-order model breaks: a pixel that held
    at least 1 % of the peak charge ends with less than none (fainter pixels may go negative
    through their noise alone)."""
    broken = (result < 0) & (image >= 0.01 * image.max())
    if broken.any():
        warnings.warn(f"charge up to {image.max():.3g} e- is beyond the first-order BF model "
                      f"(G15): {np.count_nonzero(broken)} pixel(s) went negative; the fluxes are "
                      "too large for these boundary shifts", BFPSFWarning, stacklevel=3)


def single_pixel_delta(charge, shifts):
    """Closed form of dQ for ``charge`` electrons in one pixel of an empty image.

    Only the four boundaries of the charged pixel carry charge (density Q/2), so
    dQ(0, 0) = Q^2/4 a(0, 0) and the neighbour across boundary X gains -Q^2/4 a^X(0, 0).

    Returns
    -------
    ndarray, shape (3, 3)
        dQ indexed [dy + 1, dx + 1], e-.
    """
    shifts = as_shifts(shifts)
    m = shifts.radius
    q2 = 0.25 * float(charge) ** 2
    delta = np.zeros((3, 3))
    delta[1, 1] = q2 * shifts.area[m, m]
    delta[2, 1] = -q2 * shifts.north[m, m]
    delta[0, 1] = -q2 * shifts.south[m, m]
    delta[1, 2] = -q2 * shifts.east[m, m]
    delta[1, 0] = -q2 * shifts.west[m, m]
    return delta
