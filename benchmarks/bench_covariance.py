"""Benchmark: covariances of one 4k x 4k flat pair to lag 8.

Times `bfpsf.calibration.covariance.pair_covariance` (single precision FFT, the default, and
double) beside a plain numpy implementation (two zero-padded ``numpy.fft.rfft2`` and three full
``irfft2``, the cp_pipe / Astier et al. 2019 recipe) in the same run, on one core, and checks
that the answers agree. Wall-clock and CPU seconds are both printed: on a shared machine the
CPU time is the steadier figure.

Run (one core, as the target is stated):

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_covariance.py [--size 4096]
"""

import argparse
import os
import sys
import time

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
# measure the bfpsf of this checkout, not whichever one is installed
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
from scipy.fft import next_fast_len  # noqa: E402

from bfpsf.calibration.covariance import pair_covariance  # noqa: E402
from bfpsf.calibration.flat_mask import pair_mask  # noqa: E402


def plain_numpy(flat1, flat2, mask, maxlag):
    """Reference: masked difference, cp_pipe FFT covariances with numpy.fft, no clipping.

    Zero-padded to fast FFT lengths (scipy.fft.next_fast_len) so the reference is not
    penalised by an awkward size.
    """
    good = ~mask
    mean1, mean2 = flat1[good].mean(), flat2[good].mean()
    mean = 0.5 * (mean1 + mean2)
    diff = (mean2 * flat1 - mean1 * flat2) / mean
    weights = good.astype(float)
    data = diff * weights
    shape = (next_fast_len(flat1.shape[0] + maxlag, real=True),
             next_fast_len(flat1.shape[1] + maxlag, real=True))
    transform_data = np.fft.rfft2(data, shape)
    transform_mask = np.fft.rfft2(weights, shape)
    products = np.fft.irfft2(transform_data * transform_data.conj(), shape)
    near = np.fft.irfft2(transform_mask * transform_data.conj(), shape)
    counts = np.rint(np.fft.irfft2(transform_mask * transform_mask.conj(), shape))
    cov = np.zeros((maxlag + 1, maxlag + 1))
    for dy in range(maxlag + 1):
        for dx in range(maxlag + 1):
            values, numbers = [], []
            for sy in ((1, -1) if dx and dy else (1,)):
                ky = sy * dy
                npairs = counts[ky, dx]
                values.append((products[ky, dx] - near[ky, dx] * near[-ky, -dx] / npairs)
                              / npairs)
                numbers.append(npairs)
            cov[dy, dx] = np.average(values, weights=numbers) / 2.0
    return cov


def best_time(function, repeat):
    """Best wall-clock and CPU (process) time of ``repeat`` calls; on a shared machine the CPU
    time is the steadier figure."""
    walls, cpus = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        result = function()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - start_cpu)
    return min(walls), min(cpus), result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=4096)
    parser.add_argument("--maxlag", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(0)
    size, maxlag = args.size, args.maxlag
    level = 50_000.0
    flat1 = rng.normal(level, np.sqrt(level), (size, size))
    flat2 = rng.normal(level, np.sqrt(level), (size, size))
    mask = np.zeros((size, size), dtype=bool)
    mask[:, size // 3] = True                       # a bad column
    mask[rng.integers(0, size, 2000), rng.integers(0, size, 2000)] = True   # defects

    print(f"covariances of one {size} x {size} pair to lag {maxlag}, one core, best of "
          f"{args.repeat} (wall / CPU seconds)")
    plain_wall, plain_cpu, plain_cov = best_time(
        lambda: plain_numpy(flat1, flat2, mask, maxlag), args.repeat)
    print(f"  {'plain numpy rfft2/irfft2 (no clipping)':40s} {plain_wall:6.3f} / {plain_cpu:6.3f}")
    rows = [("bfpsf, double precision, no clipping", dict(precision="double", clip_nsigma=None)),
            ("bfpsf, single precision, no clipping", dict(precision="single", clip_nsigma=None)),
            ("bfpsf, double precision, 4-sigma clip", dict(precision="double")),
            ("bfpsf, single precision, 4-sigma clip", dict(precision="single"))]
    for label, options in rows:
        wall, cpu, result = best_time(
            lambda: pair_covariance(flat1, flat2, mask=mask, maxlag=maxlag, **options),
            args.repeat)
        line = (f"  {label:40s} {wall:6.3f} / {cpu:6.3f}   plain/bfpsf = {plain_wall / wall:5.2f}"
                f" / {plain_cpu / cpu:5.2f}")
        if options.get("clip_nsigma", 4.0) is None:
            error = np.abs(result.cov_adu - plain_cov).max() / plain_cov[0, 0]
            line += f"   max |C - C_plain| / V = {error:.1e}"
        print(line)
    dense_mask = rng.random((size, size)) < 0.02
    wall, cpu, _ = best_time(lambda: pair_covariance(flat1, flat2, mask=dense_mask,
                                                     maxlag=maxlag), args.repeat)
    print(f"  {'bfpsf, default, 2 % of pixels masked':40s} {wall:6.3f} / {cpu:6.3f}   "
          "(many bad pixels: counts by FFT)")

    wall, cpu, (mask_bfpsf, report) = best_time(lambda: pair_mask(flat1, flat2), args.repeat)
    print(f"  {'pair_mask of the same pair':40s} {wall:6.3f} / {cpu:6.3f}   ({report.total} "
          "pixels masked)")
    cov_wall, cov_cpu, _ = best_time(
        lambda: pair_covariance(flat1, flat2, mask=mask_bfpsf, maxlag=maxlag), args.repeat)
    print(f"  {'per pair: pair_mask + pair_covariance':40s} {wall + cov_wall:6.3f} / "
          f"{cpu + cov_cpu:6.3f}   (issue 12 target: 0.3 s on one core)")
    # the floor: the one forward FFT the covariances need, and one pass over the two flats
    from scipy import fft

    shape = (next_fast_len(size + maxlag, real=True), next_fast_len(size + maxlag, real=True))
    padded = np.zeros(shape, dtype=np.float32)
    padded[:size, :size] = flat1 - flat2
    wall, cpu, _ = best_time(lambda: fft.rfft2(padded, workers=1), args.repeat)
    print(f"  {'floor: one single-precision rfft2':40s} {wall:6.3f} / {cpu:6.3f}   "
          f"(padded to {shape[0]} x {shape[1]})")
    wall, cpu, _ = best_time(lambda: np.subtract(flat1, flat2, out=padded[:size, :size],
                                                 casting="same_kind"), args.repeat)
    print(f"  {'floor: one pass, flat1 - flat2':40s} {wall:6.3f} / {cpu:6.3f}")


if __name__ == "__main__":
    main()
