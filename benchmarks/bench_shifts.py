"""Benchmark: solving boundary shifts from area coefficients, the electrostatic fit against G15's
Ei solver, same run.

The area coefficients are GalSim's own (`silicon_area_coefficients` of lsst_itl_50_8, lags
0..``--maxlag``) with 2 % errors. Prints the time of one electrostatic model evaluation (the
compiled kernel `_unit_shift_kernel`, both boundaries of every lag), of the electrostatic fit
with ``--samples`` Monte Carlo refits (its default error propagation, what `bfpsf calibrate`
runs per amplifier), and of the Ei solver with as many samples, and the ratio of the two.

Run:  OMP_NUM_THREADS=1 python benchmarks/bench_shifts.py [--maxlag 4] [--samples 100]
"""

import argparse
import time

import numpy as np

from bfpsf.calibration.boundary_shifts import solve_boundary_shifts
from bfpsf.calibration.shifts_electrostatic import ElectrostaticGeometry, electrostatic_area
from bfpsf.interop.silicon_truth import silicon_area_coefficients


def best_of(function, repeat):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--maxlag", type=int, default=4)
    parser.add_argument("--samples", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)

    area = silicon_area_coefficients("lsst_itl_50_8", maxlag=args.maxlag)
    errors = 0.02 * np.abs(area) + 1e-3 * np.abs(area[0, 0])
    geometry = ElectrostaticGeometry(thickness=10.0, charge_height=0.1, horizontal_height=0.5,
                                     vertical_height=1.0, half_width_x=0.3, half_width_y=0.3)
    electrostatic_area(geometry, 1.0, args.maxlag)  # compile (cached after the first run)
    evaluation = best_of(lambda: [electrostatic_area(geometry, 1.0, args.maxlag)
                                  for _ in range(1000)], args.repeat) / 1000
    fits = {method: best_of(lambda: solve_boundary_shifts(area, errors, method=method,
                                                          n_samples=args.samples),
                            args.repeat)
            for method in ("electrostatic", "ei")}
    print(f"lags 0..{args.maxlag}, {args.samples} samples, best of {args.repeat}")
    print(f"electrostatic model evaluation: {1e6 * evaluation:.0f} us")
    print(f"electrostatic fit: {fits['electrostatic']:.2f} s; Ei solver: {fits['ei']:.2f} s; "
          f"ratio {fits['electrostatic'] / fits['ei']:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
