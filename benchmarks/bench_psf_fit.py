"""Fitting P0 from 3600 SiliconSensor stars: one P0 and a 3 x 3 grid, against EPSFBuilder.

The issue-13 set: 36 exposures of 400 x 400 pixels, 100 SiliconSensor ``lsst_e2v_50_8`` Moffat
stars each (one per 40 x 40 tile), peaks 3-120 ke-, FWHM 3.0 -> 3.9 px across the field, e1
-0.04 -> +0.04 (`simulate_varying_exposures`). Drawing it takes about 15 minutes on one core,
so it is cached (``--cache``). Boundary shifts: SiliconSensor's landing shifts
(`bfpsf.silicon_boundary_shifts`). Timed side by side in one run: `fit_psf` with one P0 and
with a 3 x 3 grid (BF term removed star by star; target <= 2 minutes, converged), and the
static ePSF of photutils' `~photutils.psf.EPSFBuilder` (10 iterations, no BF term, one P0) on
the stars of the first ``--epsf-exposures`` exposures (it takes about 0.17 s a star), scaled to
the whole set per star, as the reference. Before issue 13 the one-P0 fit took 16 minutes and stopped
after 40 iterations, not converged, on such a set.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_psf_fit.py [--cache FILE.npz]
[--exposures 36] [--epsf-exposures 4]``
"""

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np


def load_or_draw(path, n_exposures, seed):
    if path.exists():
        stored = np.load(path)
        return stored["images"], stored["image"], stored["x"], stored["y"]
    from bfpsf.validation.simulate_spots import simulate_varying_exposures

    print(f"drawing {n_exposures} exposures of SiliconSensor stars into {path} (slow, once)")
    images, _, truth = simulate_varying_exposures(n_exposures=n_exposures, seed=seed,
                                                  bf_free_twin=False, progress=True)
    np.savez(path, images=images, image=np.asarray(truth["image"]), x=np.asarray(truth["x"]),
             y=np.asarray(truth["y"]))
    return images, np.asarray(truth["image"]), np.asarray(truth["x"]), np.asarray(truth["y"])


def time_epsfbuilder(images, index, x, y):
    from astropy.nddata import NDData
    from astropy.table import Table
    from photutils.psf import EPSFBuilder, extract_stars

    data = [NDData(image) for image in images]
    catalogs = [Table({"x": x[index == i], "y": y[index == i]}) for i in range(len(images))]
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stars = extract_stars(data, catalogs, size=25)
        EPSFBuilder(oversampling=2, maxiters=10, progress_bar=False)(stars)
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cache", type=Path, default=Path("/tmp/bfpsf_bench_psf_fit.npz"))
    parser.add_argument("--exposures", type=int, default=36)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--epsf-exposures", type=int, default=4,
                        help="exposures given to EPSFBuilder (0: skip it)")
    args = parser.parse_args()
    if os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: set OMP_NUM_THREADS=1 for one-core timings")

    import bfpsf
    from bfpsf.model.psf_fit import fit_psf

    images, index, x, y = load_or_draw(args.cache, args.exposures, args.seed)
    positions = [np.column_stack([x[index == i], y[index == i]]) for i in range(len(images))]
    shifts = bfpsf.silicon_boundary_shifts("lsst_e2v_50_8")
    print(f"{len(x)} stars in {len(images)} exposures of {images.shape[2]} x {images.shape[1]}")
    timings = {}
    for label, grid in (("fit_psf, one P0", None), ("fit_psf, 3 x 3 grid", (3, 3))):
        start = time.perf_counter()
        result = fit_psf(list(images), positions, shifts, oversampling=2, size=25, grid=grid,
                         progress=True)
        timings[label] = time.perf_counter() - start
        used = int(np.sum(result.stars["flags"] == 0))
        print(f"{label:24s} {timings[label]:7.1f} s  {result.iterations:3d} iterations  "
              f"converged {result.converged}  last change {result.changes[-1]:.1e}  "
              f"{used} stars used")
    if args.epsf_exposures > 0:
        subset = np.arange(min(args.epsf_exposures, len(images)))
        chosen = np.isin(index, subset)
        seconds = time_epsfbuilder(images[subset], index[chosen], x[chosen], y[chosen])
        reference = seconds * len(x) / chosen.sum()
        print(f"{'EPSFBuilder (static)':24s} {reference:7.1f} s   10 iterations (reference: "
              f"{seconds:.1f} s for {chosen.sum()} stars, scaled per star)")
        for label, value in timings.items():
            print(f"  {label}: {value / reference:.3f} x EPSFBuilder")
    print("before issue 13, one P0: about 960 s, 40 iterations, not converged (issue 13)")


if __name__ == "__main__":
    main()
