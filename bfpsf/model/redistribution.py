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

import concurrent.futures
import functools
import operator
import os
import queue
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
# FFT size of a tile by precision. A tile's transforms must stay in the core's cache: on the
# development machine (AMD EPYC, 512 kB of L2 per core) a float64 inverse rfft2 costs 4x more
# per pixel above ~200 px than below, a float32 one above ~330 px
# (benchmarks/bench_redistribution.py --tiles).
_TILE = {np.float64: 192, np.float32: 256}


def _default_workers():
    """Threads used when ``workers`` is None: the CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _validate_workers(workers):
    """Number of threads: None -> all CPUs; negative values count back from all CPUs as in
    `scipy.fft` (-1: all, -2: all but one)."""
    if workers is None:
        return _default_workers()
    try:
        count = operator.index(workers)
    except TypeError:
        msg = f"workers must be an integer or None, got {workers!r}"
        raise BFPSFValueError(msg, workers) from None
    if count == 0:
        msg = "workers must not be 0 (None or -1: all CPUs)"
        raise BFPSFValueError(msg, workers)
    if count < 0:
        count = max(_default_workers() + 1 + count, 1)
    return count


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


@functools.lru_cache(maxsize=32)
def _cached_spectrum(kernel_bytes, side, shape, complex_dtype):
    """`_kernel_spectrum` of a (side x side) float64 kernel given by its bytes, read-only and
    cached: repeated calls (BFSensor stamps, iterative correction) reuse it."""
    kernel = np.frombuffer(kernel_bytes, dtype=np.float64).reshape(side, side)
    spectrum = _kernel_spectrum(kernel, shape).astype(complex_dtype)
    spectrum.flags.writeable = False
    return spectrum


def _tiling(n, m, tile):
    """(block, fft_size) along one axis: output blocks of ``block`` pixels, inputs of block+2m."""
    if n + 2 * m <= tile:
        size = scipy.fft.next_fast_len(n + 2 * m, real=True)
        return n, size
    size = scipy.fft.next_fast_len(max(tile, 4 * m + 16), real=True)
    return size - 2 * m, size


def _run_bands(sources, kernels, task, *, dtype=np.float64, workers=None, tile=None):
    """Correlate ``sources[0]`` with each kernel by overlap-save FFT and hand the result,
    horizontal band by band, to ``task(y0, rows, tiles, scratch)``; return the tasks' results
    in band order.

    The image is cut into tiles of about ``tile`` pixels (default by dtype, `_TILE`); each tile
    is read with a margin of m pixels, transformed once with a real FFT shared by all kernels,
    and every kernel's correlation is read back from its own inverse FFT. ``tiles`` iterates
    over the band's tiles as (x0, cols, correlations, windows), with

        correlations[k][r, c] = sum_{dx,dy} K_k[dy+m, dx+m] sources[0][y0+r+dy, x0+c+dx]
        windows[i][r, c] = sources[i][y0 + r, x0 + c]

    for 0 <= r < rows, 0 <= c < cols (windows: also r = rows, c = cols), sources taken as
    zero outside the image. All of a tile's arrays stay in cache while the task consumes them
    and are overwritten by the next tile. Bands run in ``workers`` threads (default: all
    CPUs; scipy.fft and numpy release the GIL); ``scratch`` is a dict private to the thread,
    for the task's buffers, and a task may write only to rows y0..y0+rows-1 of shared arrays.
    The numbers do not depend on ``workers``.
    """
    source = sources[0]
    ny, nx = source.shape
    kernels = [np.asarray(kernel, dtype=float) for kernel in kernels]
    m = kernels[0].shape[0] // 2
    if m == 0:  # one-pixel kernels: a margin of one pixel for the windows' extra row/column
        kernels = [np.pad(kernel, 1) for kernel in kernels]
        m = 1
    block_y, size_y = _tiling(ny, m, _TILE[dtype] if tile is None else tile)
    block_x, size_x = _tiling(nx, m, _TILE[dtype] if tile is None else tile)
    nby = -(-ny // block_y)
    nbx = -(-nx // block_x)
    shape = (size_y, size_x)
    complex_dtype = np.result_type(dtype, np.complex64)
    spectra = [_cached_spectrum(np.ascontiguousarray(kernel).tobytes(), kernel.shape[0], shape,
                                np.dtype(complex_dtype).str) for kernel in kernels]
    window_shape = (block_y + 2 * m, nbx * block_x + 2 * m)

    def new_buffers():
        return ([np.zeros(window_shape, dtype=dtype) for _ in sources],
                np.empty((size_y, size_x // 2 + 1), dtype=complex_dtype), {})

    def tiles(y0, rows, windows, product):
        for ix in range(nbx):
            x0 = ix * block_x
            cols = min(block_x, nx - x0)
            span = slice(x0, x0 + block_x + 2 * m)
            spectrum_in = scipy.fft.rfft2(windows[0][:, span], s=shape)
            correlations = []
            for spectrum in spectra:
                np.multiply(spectrum_in, spectrum, out=product)
                out = scipy.fft.irfft2(product, s=shape, overwrite_x=True)
                correlations.append(out[m:m + rows, m:m + cols])
            yield (x0, cols, correlations,
                   [window[m:m + rows + 1, x0 + m:x0 + m + cols + 1] for window in windows])

    def run(iy, buffers):
        windows, product, scratch = buffers
        y0 = iy * block_y
        rows = min(block_y, ny - y0)
        # Rows y0 - m .. y0 + block_y + m of the image, zero outside it (the column margins
        # are never written).
        top, bottom = max(y0 - m, 0), min(y0 + block_y + m, ny)
        first, last = top - (y0 - m), bottom - (y0 - m)
        for window, image in zip(windows, sources):
            window[:first] = 0.0
            window[last:] = 0.0
            window[first:last, m:m + nx] = image[top:bottom]
        return task(y0, rows, tiles(y0, rows, windows, product), scratch)

    workers = min(_validate_workers(workers), nby)
    if workers == 1:
        buffers = new_buffers()
        return [run(iy, buffers) for iy in range(nby)]
    free = queue.SimpleQueue()
    for _ in range(workers):
        free.put(new_buffers())

    def job(iy):
        buffers = free.get()
        try:
            return run(iy, buffers)
        finally:
            free.put(buffers)

    with concurrent.futures.ThreadPoolExecutor(workers) as executor:
        return list(executor.map(job, range(nby)))


def _correlate(image, kernels, *, dtype=np.float64, workers=None, tile=None):
    """Full-image correlations sum_{dx,dy} K(dx, dy) image[y + dy, x + dx], zero outside."""
    results = [np.empty(image.shape, dtype=dtype) for _ in kernels]

    def task(y0, rows, tiles, scratch):
        for x0, cols, correlations, _ in tiles:
            for result, correlation in zip(results, correlations):
                result[y0:y0 + rows, x0:x0 + cols] = correlation

    _run_bands([image], kernels, task, dtype=dtype, workers=workers, tile=tile)
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
    computed while the tile's correlations are in cache (`_run_bands`), in double precision
    (float32 mode: the float32 products, exactly).
    """
    ny, nx = image.shape
    if density is not None:
        density_north, density_east = _validate_density(density, image.shape)
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

    return _run_bands(sources, kernels, band_task, dtype=dtype, workers=workers)


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


def _redistributed(result, image, shifts, density, dtype, workers, *, source=None, factor=0.5,
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
        `exact_boundary_density`. Default: G15's (Q_p + Q_q) / 2 (eq. density-approx).
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
    result = _redistributed(np.empty(image.shape), image, _as_shifts(shifts), density,
                            _validate_dtype(dtype), workers, base=image)
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
