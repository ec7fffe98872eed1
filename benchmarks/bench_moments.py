"""Benchmark: bfpsf adaptive moments against galsim.hsm.FindAdaptiveMom, same run.

10^4 noisy Moffat stamps of 32 x 32 pixels (FWHM 4 pixels, beta 3.5, S/N about 200, random
sub-pixel offsets and small shears). Prints the throughput of
`bfpsf.moments.adaptive.adaptive_moments_batch`, of the per-stamp `adaptive_moments`, and of
`galsim.hsm.FindAdaptiveMom` in a Python loop, and the ratios. Also prints the largest relative
difference of sigma between the two on stamps both measured.

Run:  OMP_NUM_THREADS=1 python benchmarks/bench_moments.py [--n 10000]
"""

import argparse
import time

import numpy as np


def make_stamps(n_stamps, size=32, seed=0):
    import galsim

    rng = np.random.default_rng(seed)
    profile = galsim.Moffat(fwhm=4.0, beta=3.5)
    # draw a few hundred distinct noiseless stamps and reuse them with fresh noise
    n_unique = min(n_stamps, 200)
    base = np.empty((n_unique, size, size))
    for index in range(n_unique):
        shear = rng.uniform(-0.05, 0.05, 2)
        offset = rng.uniform(-0.5, 0.5, 2)
        image = profile.shear(g1=shear[0], g2=shear[1]).withFlux(1e4).drawImage(
            nx=size, ny=size, scale=1.0, offset=offset)
        base[index] = image.array
    stamps = base[rng.integers(0, n_unique, n_stamps)]
    # S/N about 200 for the matched filter: noise RMS from flux / (S/N sqrt(4 pi sigma^2))
    noise = 1e4 / (200.0 * np.sqrt(4.0 * np.pi * 1.75**2))
    return stamps + noise * rng.standard_normal(stamps.shape)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000, help="number of stamps (default 1e4)")
    args = parser.parse_args(argv)

    import galsim

    from bfpsf.moments.adaptive import adaptive_moments, adaptive_moments_batch

    stamps = make_stamps(args.n)
    print(f"{args.n} stamps of {stamps.shape[1]}x{stamps.shape[2]} pixels")

    start = time.perf_counter()
    batch = adaptive_moments_batch(stamps)
    time_batch = time.perf_counter() - start

    n_single = min(args.n, 500)
    start = time.perf_counter()
    for stamp in stamps[:n_single]:
        adaptive_moments(stamp)
    time_single = (time.perf_counter() - start) * args.n / n_single

    start = time.perf_counter()
    hsm_sigma = np.full(args.n, np.nan)
    for index, stamp in enumerate(stamps):
        result = galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp), strict=False)
        if result.moments_status == 0:
            hsm_sigma[index] = result.moments_sigma
    time_hsm = time.perf_counter() - start

    for name, seconds in [("bfpsf adaptive_moments_batch", time_batch),
                          ("bfpsf adaptive_moments (loop, extrapolated)", time_single),
                          ("galsim.hsm.FindAdaptiveMom (loop)", time_hsm)]:
        print(f"{name:45s} {seconds:8.3f} s  {args.n / seconds:10.0f} stamps/s")
    print(f"throughput ratio batch / HSM  = {time_hsm / time_batch:.2f}")
    print(f"throughput ratio single / HSM = {time_hsm / time_single:.2f}")
    both = (batch.flags == 0) & np.isfinite(hsm_sigma)
    difference = np.abs(batch.sigma[both] / hsm_sigma[both] - 1.0)
    print(f"stamps measured by both: {both.sum()} / {args.n}; "
          f"max |sigma / sigma_HSM - 1| = {difference.max():.2e}")
    print(f"bfpsf flags set on {np.sum(batch.flags != 0)} stamps, "
          f"HSM failures on {np.sum(~np.isfinite(hsm_sigma))}")


if __name__ == "__main__":
    main()
