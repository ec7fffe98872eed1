"""Correlation of an image with small kernels by blocked FFT (overlap-save), in threads.

The image is cut into horizontal bands of cache-sized tiles; each tile is transformed once and
every kernel's correlation read back from its own inverse FFT while it is in cache. Used by the
redistribution operator (`bfpsf.model.redistribution`) and by `bfpsf.interop.galsim_sensor`.
"""

import concurrent.futures
import functools
import operator
import os
import queue

import numpy as np
import scipy.fft

from ..errors import BFPSFValueError

__all__ = ["TILE", "correlate", "default_workers", "run_bands", "set_default_workers",
           "validate_workers"]

# FFT size of a tile by precision. A tile's transforms must stay in the core's cache: on the
# development machine (AMD EPYC, 512 kB of L2 per core) a float64 inverse rfft2 costs 4x more
# per pixel above ~200 px than below, a float32 one above ~330 px
# (benchmarks/bench_redistribution.py --tiles).
TILE = {np.float64: 192, np.float32: 256}


_WORKERS = None


def set_default_workers(count):
    """Threads used when ``workers`` is None (``bfpsf --threads``); None: every CPU."""
    global _WORKERS  # noqa: PLW0603
    _WORKERS = None if count is None else validate_workers(count)


def default_workers():
    """Threads used when ``workers`` is None: `set_default_workers`, else the CPUs this
    process may run on."""
    if _WORKERS is not None:
        return _WORKERS
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def validate_workers(workers):
    """Number of threads: None -> all CPUs; negative values count back from all CPUs as in
    `scipy.fft` (-1: all, -2: all but one)."""
    if workers is None:
        return default_workers()
    try:
        count = operator.index(workers)
    except TypeError:
        msg = f"workers must be an integer or None, got {workers!r}"
        raise BFPSFValueError(msg, workers) from None
    if count == 0:
        msg = "workers must not be 0 (None or -1: all CPUs)"
        raise BFPSFValueError(msg, workers)
    if count < 0:
        count = max(default_workers() + 1 + count, 1)
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


def run_bands(sources, kernels, task, *, dtype=np.float64, workers=None, tile=None):
    """Correlate ``sources[0]`` with each kernel by overlap-save FFT and hand the result,
    horizontal band by band, to ``task(y0, rows, tiles, scratch)``; return the tasks' results
    in band order.

    The image is cut into tiles of about ``tile`` pixels (default by dtype, `TILE`); each tile
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
    block_y, size_y = _tiling(ny, m, TILE[dtype] if tile is None else tile)
    block_x, size_x = _tiling(nx, m, TILE[dtype] if tile is None else tile)
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

    def tiles(rows, windows, product):
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
        return task(y0, rows, tiles(rows, windows, product), scratch)

    workers = min(validate_workers(workers), nby)
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


def correlate(image, kernels, *, dtype=np.float64, workers=None, tile=None):
    """Full-image correlations sum_{dx,dy} K(dx, dy) image[y + dy, x + dx], zero outside."""
    results = [np.empty(image.shape, dtype=dtype) for _ in kernels]

    def task(y0, rows, tiles, scratch):
        for x0, cols, correlations, _ in tiles:
            for result, correlation in zip(results, correlations):
                result[y0:y0 + rows, x0:x0 + cols] = correlation

    run_bands([image], kernels, task, dtype=dtype, workers=workers, tile=tile)
    return results
