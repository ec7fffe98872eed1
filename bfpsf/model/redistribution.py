"""Charge redistribution across pixel boundaries (G15 eq. scrambling_model), its inverse, the
exact boundary charge density and the build-up of the boundary shifts during the exposure.

Each boundary between two pixels moves by the boundary shift a^X times the charge around it,
and the charge drifting on that boundary is transferred from one pixel to the other:

    dQ_00 = 1/4 sum_X sum_ij a^X_ij Q_ij (Q_00 + Q_X)          (G15 eq. scrambling_model)

The operator is computed from boundary fluxes: for every boundary between pixel p and its
north (or east) neighbour q, the flux F = 1/4 (a^N * Q)(p) (Q_p + Q_q) is added to p and taken
from q, so charge is conserved to rounding by construction. One factor 1/2 is the build-up
(the boundaries move linearly during the exposure, G15 section 5.2); the other is the boundary
charge density rho = (Q_p + Q_q) / 2 (G15 eq. density-approx), which `exact_boundary_density`
replaces by the density integrated along the boundary of an oversampled model.

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

from dataclasses import dataclass

import numpy as np
import scipy.fft

from ..errors import BFPSFConvergenceError, BFPSFInputError, BFPSFValueError
from ..shifts import BoundaryShifts

__all__ = [
    "redistribution_delta",
    "redistribute",
    "boundary_fluxes",
    "correct",
    "CorrectionResult",
    "exact_boundary_density",
    "redistribute_buildup",
    "single_pixel_delta",
]

_NAN_POLICIES = ("raise", "interpolate")
_DTYPES = (np.float64, np.float32)


# -- input validation ----------------------------------------------------------------------------
def _as_shifts(shifts):
    """Accept a BoundaryShifts or anything carrying one in ``.shifts`` (a Calibration)."""
    if isinstance(shifts, BoundaryShifts):
        return shifts
    inner = getattr(shifts, "shifts", None)
    if isinstance(inner, BoundaryShifts):
        return inner
    msg = f"expected BoundaryShifts or an object with a .shifts attribute, got {type(shifts).__name__}"
    raise BFPSFValueError(msg, shifts)


def _as_image(image, nan_policy="raise"):
    """Return (finite float64 image, mask of the pixels that were not finite or None)."""
    image = np.asarray(image, dtype=float)
    if image.ndim != 2:
        msg = f"image must be 2-D [y, x], got {image.ndim} dimensions"
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
    return _harmonic_fill(image, bad), bad


def _harmonic_fill(image, bad):
    """Replace ``image[bad]`` by the solution of Laplace's equation with the finite pixels as
    boundary values (each filled pixel is the mean of its in-image neighbours)."""
    import scipy.ndimage
    import scipy.sparse
    import scipy.sparse.linalg

    ny, nx = image.shape
    ys, xs = np.nonzero(bad)
    index = -np.ones(image.shape, dtype=np.int64)
    index[ys, xs] = np.arange(ys.size)
    rows, cols, vals = [], [], []
    rhs = np.zeros(ys.size)
    degree = np.zeros(ys.size)
    for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ny_, nx_ = ys + dy, xs + dx
        inside = (ny_ >= 0) & (ny_ < ny) & (nx_ >= 0) & (nx_ < nx)
        degree += inside
        k = np.nonzero(inside)[0]
        neighbour_bad = bad[ny_[k], nx_[k]]
        kb = k[neighbour_bad]
        rows.append(kb)
        cols.append(index[ny_[kb], nx_[kb]])
        vals.append(-np.ones(kb.size))
        kg = k[~neighbour_bad]
        np.add.at(rhs, kg, image[ny_[kg], nx_[kg]])
    rows.append(np.arange(ys.size))
    cols.append(np.arange(ys.size))
    vals.append(degree)
    matrix = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(ys.size, ys.size))
    # A group of bad pixels with no finite neighbour would make the system singular.
    good_neighbours = degree.copy()
    for bad_rows in rows[:-1]:
        np.subtract.at(good_neighbours, bad_rows, 1.0)
    labels, count = scipy.ndimage.label(bad)
    per_group = scipy.ndimage.sum_labels(good_neighbours, labels[ys, xs],
                                         index=np.arange(1, count + 1))
    isolated = int(np.count_nonzero(per_group == 0))
    if isolated:
        msg = (f"cannot interpolate: {isolated} group(s) of non-finite pixels have no finite "
               f"neighbour ({ys.size} non-finite pixels of {image.size})")
        raise BFPSFInputError(msg, isolated)
    filled = image.copy()
    filled[ys, xs] = scipy.sparse.linalg.spsolve(matrix.tocsc(), rhs)
    return filled


def _validate_dtype(dtype):
    dtype = np.dtype(dtype).type
    if dtype not in _DTYPES:
        msg = f"dtype must be float64 or float32, got {np.dtype(dtype).name}"
        raise BFPSFValueError(msg, dtype)
    return dtype


# -- correlation by blocked FFT (overlap-save) ---------------------------------------------------
def _kernel_spectrum(kernel, shape):
    """conj(DFT) of a (2m+1)^2 kernel centred on offset 0, on an rfft grid of ``shape``.

    Computed as E_y K E_x^T with small complex exponential matrices: much cheaper than the FFT
    of a zero-padded kernel. Multiplying an image spectrum by it correlates:
    out[y, x] = sum_{dx,dy} K[dy+m, dx+m] in[y + dy, x + dx] (circularly)."""
    m = kernel.shape[0] // 2
    py, px = shape
    offsets = np.arange(-m, m + 1)
    phase_y = np.exp(2j * np.pi * np.outer(np.arange(py), offsets) / py)
    phase_x = np.exp(2j * np.pi * np.outer(np.arange(px // 2 + 1), offsets) / px)
    return phase_y @ kernel @ phase_x.T


def _tiling(n, m, tile):
    """(block, fft_size) along one axis: output blocks of ``block`` pixels, inputs of block+2m."""
    if n + 2 * m <= tile:
        size = scipy.fft.next_fast_len(n + 2 * m, real=True)
        return n, size
    size = scipy.fft.next_fast_len(max(tile, 4 * m + 16), real=True)
    return size - 2 * m, size


def _correlated_bands(image, kernels, *, dtype=np.float64, workers=None, tile=256):
    """Yield (y0, rows, [band of each correlation]) over horizontal bands of the image.

    Each correlation is sum_{dx,dy} K(dx, dy) image[y + dy, x + dx], zero outside the image.
    Overlap-save: the image is cut into blocks of about ``tile`` pixels, each block is read
    with a margin of m pixels, transformed once with a real FFT shared by all kernels, and
    every kernel's correlation is read back from its own inverse FFT. Small blocks keep the
    transforms in cache, which is faster on large images than one FFT of the whole image; the
    caller consumes each band while it is in cache, and no image-sized array is allocated here
    (fresh large arrays cost page faults comparable to the FFTs). The yielded bands are
    overwritten by the next iteration.
    """
    ny, nx = image.shape
    m = kernels[0].shape[0] // 2
    block_y, size_y = _tiling(ny, m, tile)
    block_x, size_x = _tiling(nx, m, tile)
    nby = -(-ny // block_y)
    nbx = -(-nx // block_x)
    complex_dtype = np.result_type(dtype, np.complex64)
    spectra = [_kernel_spectrum(np.asarray(kernel, dtype=float), (size_y, size_x))
               .astype(complex_dtype) for kernel in kernels]
    window = (block_y + 2 * m, block_x + 2 * m)
    band = np.zeros((window[0], nbx * block_x + 2 * m), dtype=dtype)
    outputs = [np.empty((block_y, nbx * block_x), dtype=dtype) for _ in kernels]
    for iy in range(nby):
        y0 = iy * block_y
        # Rows y0 - m .. y0 + block_y + m of the image, zero outside it.
        top, bottom = max(y0 - m, 0), min(y0 + block_y + m, ny)
        band[:] = 0.0
        band[top - (y0 - m):bottom - (y0 - m), m:m + nx] = image[top:bottom]
        tiles = np.lib.stride_tricks.sliding_window_view(band, window, axis=(0, 1))
        tiles = tiles[0, ::block_x]  # (nbx, window_y, window_x), a view
        tiles_ft = scipy.fft.rfft2(tiles, s=(size_y, size_x), axes=(-2, -1), workers=workers)
        rows = min(block_y, ny - y0)
        bands = []
        for spectrum, output in zip(spectra, outputs):
            out = scipy.fft.irfft2(tiles_ft * spectrum, s=(size_y, size_x), axes=(-2, -1),
                                   workers=workers, overwrite_x=True)
            # (nbx, rows, block_x) -> (rows, nbx * block_x)
            output.reshape(block_y, nbx, block_x)[:rows] = (
                out[:, m:m + rows, m:m + block_x].transpose(1, 0, 2))
            bands.append(output[:rows, :nx])
        yield y0, rows, bands


def _correlate(image, kernels, *, dtype=np.float64, workers=None, tile=256):
    """Full-image correlations of `_correlated_bands`."""
    results = [np.empty(image.shape, dtype=dtype) for _ in kernels]
    for y0, rows, bands in _correlated_bands(image, kernels, dtype=dtype, workers=workers,
                                             tile=tile):
        for result, band in zip(results, bands):
            result[y0:y0 + rows] = band
    return results


# -- boundary fluxes -----------------------------------------------------------------------------
def _validate_density(density, shape):
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


def _flux_bands(image, shifts, density, dtype, workers, *, source=None, factor=0.5):
    """Yield (y0, flux_north band, flux_east band): the boundary fluxes row band by row band.

    The fluxes are ``factor (a^X * source) rho`` on every north and east boundary, e-.
    ``source`` (default ``image``) is the charge that moves the boundaries; ``rho`` is
    ``density`` or, by default, G15's (Q_p + Q_q) / 2 of ``image`` (eq. density-approx).
    With factor 1/2 (the time-averaged shift) this is G15 eq. delta-q-x. The north band
    covers the boundaries above rows y0..y0 + len - 1 (the image's last row has none).
    """
    ny, nx = image.shape
    source = image if source is None else source
    if density is not None:
        density_north, density_east = _validate_density(density, image.shape)
        # rho is given: fold the factor into the kernels.
        kernel_factor = factor
    else:
        # (Q_p + Q_q) / 2: fold both the factor and the 1/2 into the kernels.
        kernel_factor = 0.5 * factor
    kernels = [shifts.north * kernel_factor, shifts.east * kernel_factor]
    buffer_north = buffer_east = None
    for y0, rows, (shift_north, shift_east) in _correlated_bands(source, kernels, dtype=dtype,
                                                                 workers=workers):
        if buffer_north is None:
            buffer_north = np.empty((rows, nx), dtype=dtype)
            buffer_east = np.empty((rows, nx - 1), dtype=dtype)
        y1 = y0 + rows
        north_rows = min(y1, ny - 1) - y0
        flux_north = buffer_north[:north_rows]
        flux_east = buffer_east[:rows]
        if density is None:
            np.add(image[y0:y0 + north_rows], image[y0 + 1:y0 + north_rows + 1], out=flux_north,
                   casting="same_kind")
            flux_north *= shift_north[:north_rows]
            np.add(image[y0:y1, :-1], image[y0:y1, 1:], out=flux_east, casting="same_kind")
            flux_east *= shift_east[:, :-1]
        else:
            np.multiply(shift_north[:north_rows], density_north[y0:y0 + north_rows],
                        out=flux_north, casting="same_kind")
            np.multiply(shift_east[:, :-1], density_east[y0:y1], out=flux_east,
                        casting="same_kind")
        yield y0, flux_north, flux_east


def _fluxes_of(image, shifts, density, dtype, workers, *, source=None, factor=0.5):
    """Full flux arrays (ny - 1, nx) and (ny, nx - 1) of `_flux_bands`."""
    ny, nx = image.shape
    flux_north = np.empty((ny - 1, nx), dtype=dtype)
    flux_east = np.empty((ny, nx - 1), dtype=dtype)
    for y0, north, east in _flux_bands(image, shifts, density, dtype, workers, source=source,
                                       factor=factor):
        flux_north[y0:y0 + len(north)] = north
        flux_east[y0:y0 + len(east)] = east
    return flux_north, flux_east


def _redistributed(result, image, shifts, density, dtype, workers, *, source=None, factor=0.5):
    """Add to ``result`` (float64, in place) the charge each pixel gains from its boundaries.

    The fluxes are added and subtracted in double precision band by band, so charge is
    conserved to rounding whatever ``dtype`` the fluxes were computed in.
    """
    for y0, north, east in _flux_bands(image, shifts, density, dtype, workers, source=source,
                                       factor=factor):
        rows = len(east)
        result[y0:y0 + len(north)] += north
        result[y0 + 1:y0 + len(north) + 1] -= north
        result[y0:y0 + rows, :-1] += east
        result[y0:y0 + rows, 1:] -= east
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
        `exact_boundary_density`. Default: G15's (Q_p + Q_q) / 2 (eq. density-approx).
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the FFT correlation and of the fluxes. float32 is about twice as fast;
        the fluxes are then accurate to ~1e-6 of the largest flux, and charge stays conserved
        (the fluxes are added and subtracted in double precision).
    workers : int, optional
        Threads for `scipy.fft`. Default: one.

    Returns
    -------
    flux_north : ndarray, shape (ny - 1, nx)
        Charge gained by pixel (x, y) from pixel (x, y + 1) through their shared boundary,
        1/2 (a^N * Q)(x, y) rho_N(x, y) (G15 eq. delta-q-x).
    flux_east : ndarray, shape (ny, nx - 1)
        Charge gained by pixel (x, y) from pixel (x + 1, y).
    """
    image, _ = _as_image(image_e)
    return _fluxes_of(image, _as_shifts(shifts), density, _validate_dtype(dtype), workers)


def redistribution_delta(image_e, shifts, *, density=None, dtype=np.float64, workers=None):
    """dQ of G15 eq. scrambling_model: the charge each pixel gains, e-.

    Quadratic in the image: ``redistribution_delta(F * P, s) = F**2 * redistribution_delta(P, s)``
    (with the default density). Pixels outside the image hold no charge and no charge crosses
    the image border, so ``dQ.sum() == 0`` to rounding. Keywords as in `boundary_fluxes`.
    """
    image, _ = _as_image(image_e)
    return _redistributed(np.zeros(image.shape), image, _as_shifts(shifts), density,
                          _validate_dtype(dtype), workers)


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
        Exact boundary charge density (see `exact_boundary_density`); default G15's mean.
    nan_policy : {'raise', 'interpolate'}, optional
        What to do with non-finite pixels (module docstring). Default 'raise'.
    dtype, workers
        FFT precision and threads, see `boundary_fluxes`.

    Returns
    -------
    ndarray [y, x]
        Q' = Q + dQ (G15 eq. perturbPTC), total charge unchanged (to 1e-15 relative).
    """
    image, bad = _as_image(image_e, nan_policy)
    result = _redistributed(image.copy(), image, _as_shifts(shifts), density,
                            _validate_dtype(dtype), workers)
    if bad is not None:
        result[bad] = np.nan
    return result


def single_pixel_delta(charge, shifts):
    """Closed form of dQ for ``charge`` electrons in one pixel of an empty image.

    Only the four boundaries of the charged pixel carry charge (density Q/2), so
    dQ(0, 0) = Q^2/4 a(0, 0) and the neighbour across boundary X gains -Q^2/4 a^X(0, 0).

    Returns
    -------
    ndarray, shape (3, 3)
        dQ indexed [dy + 1, dx + 1], e-.
    """
    shifts = _as_shifts(shifts)
    m = shifts.radius
    q2 = 0.25 * float(charge) ** 2
    delta = np.zeros((3, 3))
    delta[1, 1] = q2 * shifts.area[m, m]
    delta[2, 1] = -q2 * shifts.north[m, m]
    delta[0, 1] = -q2 * shifts.south[m, m]
    delta[1, 2] = -q2 * shifts.east[m, m]
    delta[1, 0] = -q2 * shifts.west[m, m]
    return delta


# -- inverse -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CorrectionResult:
    """Result of `correct` with ``full_output=True``.

    Attributes
    ----------
    image : ndarray
        Corrected image x, e-.
    method : str
        'iterative' or 'first_order'.
    iterations : int
        Forward evaluations of the iteration (the residual of the returned image is the last);
        1 for 'first_order', whose residual costs one more.
    residual : float
        max |redistribute(x) - image|, e- (for 'first_order' too).
    relative_residual : float
        ``residual / max|image|``.
    error_bound : float
        Estimated max |x - x_true| / max|image|: the residual divided by (1 - contraction).
    contraction : float
        Observed ratio of successive residuals (nan if fewer than two iterations).
    converged : bool
        Whether the stopping rule was met.
    residual_history : tuple of float
        max |residual| after each iteration, e-.
    """

    image: np.ndarray
    method: str
    iterations: int
    residual: float
    relative_residual: float
    error_bound: float
    contraction: float
    converged: bool
    residual_history: tuple


def correct(image_e, shifts, *, method="iterative", rtol=1e-10, max_iter=100, density=None,
            nan_policy="raise", full_output=False, strict=True, dtype=np.float64, workers=None):
    """Inverse brighter-fatter: the image x with ``redistribute(x) == image_e``, e-.

    Parameters
    ----------
    image_e : array_like [y, x]
        Observed charge image, e-.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    method : {'iterative', 'first_order'}, optional
        'first_order': G15's sign flip, x = Q - dQ(Q) (section 7.3; error O(a^2 Q^3)).
        'iterative': fixed-point iteration x_{k+1} = x_k + r_k with the residual
        r_k = Q - redistribute(x_k), one forward evaluation per iteration.
    rtol : float, optional
        Stopping rule of 'iterative': stop when the estimated error of x,
        max|r_k| / (1 - c), is at most ``rtol * max|image|``, with c the observed contraction
        max|r_k| / max|r_{k-1}| (the linear convergence factor of the iteration, of order
        |a(0,0)| Q_peak / 2). Since r_k is the residual of the returned x, the bound is on
        the answer, not on a step size. Default 1e-10.
    max_iter : int, optional
        Largest number of iterations. Default 100.
    density : (ndarray, ndarray), optional
        Boundary density of the corrected image (e.g. `exact_boundary_density` of a model of
        the scene), held fixed during the iteration; default G15's mean of each iterate.
    nan_policy, dtype, workers
        As in `redistribute`.
    full_output : bool, optional
        Return a `CorrectionResult` instead of the image. Default False.
    strict : bool, optional
        Raise `~bfpsf.errors.BFPSFConvergenceError` if the stopping rule is not met within
        ``max_iter`` or the iteration diverges; otherwise return the last iterate with
        ``converged=False``. Default True.

    Returns
    -------
    ndarray or CorrectionResult
    """
    image, bad = _as_image(image_e, nan_policy)
    shifts = _as_shifts(shifts)
    dtype = _validate_dtype(dtype)
    if method not in ("iterative", "first_order"):
        msg = f"method must be 'iterative' or 'first_order', got {method!r}"
        raise BFPSFValueError(msg, method)
    if not (rtol > 0):
        msg = f"rtol must be positive, got {rtol}"
        raise BFPSFValueError(msg, rtol)
    if int(max_iter) < 1:
        msg = f"max_iter must be at least 1, got {max_iter}"
        raise BFPSFValueError(msg, max_iter)
    scale = float(np.abs(image).max()) or 1.0

    def forward_delta(x):
        return _redistributed(np.zeros(x.shape), x, shifts, density, dtype, workers)

    history = []
    contraction = np.nan
    converged = False
    if method == "first_order":
        x = image - forward_delta(image)
        residual = image - x - forward_delta(x)
        history.append(float(np.abs(residual).max()))
        iterations = 1
        converged = True
        error = history[-1]
    else:
        x = image.copy()
        for iterations in range(1, int(max_iter) + 1):
            residual = image - x - forward_delta(x)
            history.append(float(np.abs(residual).max()))
            if len(history) >= 2:
                contraction = history[-1] / history[-2] if history[-2] > 0 else 0.0
            rate = min(contraction, 0.99) if np.isfinite(contraction) else 0.0
            error = history[-1] / (1.0 - rate)
            if error <= rtol * scale:
                converged = True
                break
            if (len(history) >= 3 and contraction >= 1.0) or iterations == int(max_iter):
                break  # diverging, or out of iterations: x is the iterate r_k belongs to
            x = x + residual
    if not converged and strict:
        msg = (f"iterative correction did not converge: residual {history[-1]:.3g} e- "
               f"({history[-1] / scale:.3g} of the peak) after {iterations} iterations, "
               f"contraction {contraction:.3g}; increase max_iter or rtol")
        raise BFPSFConvergenceError(msg)
    if bad is not None:
        x = x.copy()
        x[bad] = np.nan
    if not full_output:
        return x
    return CorrectionResult(image=x, method=method, iterations=iterations,
                            residual=history[-1], relative_residual=history[-1] / scale,
                            error_bound=error / scale, contraction=float(contraction),
                            converged=converged, residual_history=tuple(history))


# -- exact boundary density ----------------------------------------------------------------------
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
        flat image). Pass as ``density=`` to `redistribute`.
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


# -- build-up during the exposure ---------------------------------------------------------------
def redistribute_buildup(image_e, shifts, *, nsteps=16, density=None, dtype=np.float64,
                         workers=None, full_output=False):
    """Forward BF integrated over the exposure: charge arrives in ``nsteps`` equal steps.

    The one-step model (`redistribute`) moves the charge with the end-of-exposure shifts
    halved, assuming the boundaries move linearly in time with the *ideal* collected charge.
    Here the collected charge C (redistributed charge included) sets the boundary shifts
    a^X * C at the middle of each step, and the charge arriving in the step, Q / K, is moved
    with them:

        C_k = C_{k-1} + Q/K + M_k,   M_k = div[ (a^X * (C_{k-1} + (Q/K + M_{k-1})/2)) rho(Q) / K ]

    For K = 1 this is exactly the one-step model (midpoint rule on a linear build-up); the
    difference for K > 1 comes from the redistributed charge acting back on the boundaries,
    second order in a (error of the integration O(1/K^2)).

    Parameters
    ----------
    image_e : array_like [y, x]
        Charge without BF at the end of the exposure, e-.
    shifts : BoundaryShifts or Calibration
        End-of-exposure boundary shifts a^X, 1/e-.
    nsteps : int, optional
        K. Default 16.
    density : (ndarray, ndarray), optional
        Boundary density of the full exposure (`exact_boundary_density`); default G15's mean.
    full_output : bool, optional
        Also return the list of the collected images after each step.

    Returns
    -------
    ndarray [y, x] (and list of ndarray if ``full_output``)
        Collected charge at the end of the exposure, e-; total charge equals ``image_e``'s.
    """
    image, _ = _as_image(image_e)
    shifts = _as_shifts(shifts)
    dtype = _validate_dtype(dtype)
    k_steps = int(nsteps)
    if k_steps < 1 or k_steps != nsteps:
        msg = f"nsteps must be a positive integer, got {nsteps}"
        raise BFPSFValueError(msg, nsteps)
    if density is not None:
        density = _validate_density(density, image.shape)
    arriving = image / k_steps
    collected = np.zeros_like(image)
    moved = np.zeros_like(image)
    steps = []
    for _ in range(k_steps):
        # Shifts at mid-step from the charge collected so far (the charge moved during this
        # step estimated by the previous step's, for O(1/K^2)); density of the arriving charge.
        moved = _redistributed(np.zeros(image.shape), image, shifts, density, dtype, workers,
                               source=collected + 0.5 * (arriving + moved),
                               factor=1.0 / k_steps)
        collected = collected + arriving + moved
        if full_output:
            steps.append(collected)
    return (collected, steps) if full_output else collected
