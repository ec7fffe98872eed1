"""Boundary shifts a^X solved from four published measurements of a(dx, dy) (G15 section 6.1).

Usage::

    python examples/measured_shifts.py [--output DIR] [--quick]

G15's Ei solver is shown in detail (its smoothing model is what sets the N/E split); the line
"electrostatic" gives the split of bfpsf's default solver (`bfpsf.solve_boundary_shifts`) on the
same table for comparison. ``--quick``: the first table only.

The tables ship with bfpsf (`bfpsf.data`, short names as in ``bfpsf diagnose --list-measured``).
For each table it
prints the smoothing model, the truncated sum rule of the input, the solved a^N and a^E near the
source with their Monte Carlo errors, the symmetry / sum-rule residuals of the solution, how
well it sums back to the input, and the sensitivity to p1 +- 5 sigma.
"""

import argparse
import time
from pathlib import Path

import numpy as np

from bfpsf.calibration.boundary_shifts import solve_boundary_shifts, split_fraction
from bfpsf.calibration.shifts_ei import solve_ei_shifts
from bfpsf.calibration.measured import read_measured_area
from bfpsf.data import measured_path

SETS = {
    "ITL-3800C-002 corr_meas (Lage, C at 80 ke-)":
        ("itl3800c002", "corr_meas_VBB60_7_2_3500flats.txt"),
    "E2V CCD250 (Lage 2019, Poisson_CCD)": ("poisson_ccd", "e2v_covariances_21oct19.txt"),
    "ITL STA3800C (Lage 2019, Poisson_CCD)": ("poisson_ccd", "itl_covariances_21oct19.txt"),
    "LSSTCam R22_S11 E2V (cp_pipe DM-51897)":
        ("cp_pipe_r22_s11", "amatrix_LSSTCam_R22_S11_E2V-CCD250-382.csv"),
}


def print_near_source(label, values, errors, m):
    """a^X(dx, dy) for dx, dy = 0..2 with errors, in 1e-9 / e-."""
    print(f"  {label} [1e-9/e-], rows dy = 0, 1, 2; columns dx = 0, 1, 2:")
    for dy in range(3):
        cells = []
        for dx in range(3):
            value, error = values[dy + m, dx + m], errors[dy + m, dx + m]
            cells.append(f"{value * 1e9:8.2f} +- {error * 1e9:5.2f}")
        print("    " + "   ".join(cells))


def report(name, path, plots):
    measured = read_measured_area(path)
    start = time.perf_counter()
    solution = solve_ei_shifts(measured.area, measured.area_err, n_monte_carlo=200, seed=0)
    elapsed = time.perf_counter() - start
    shifts = solution.shifts
    m = shifts.radius
    a00 = measured.area[0, 0]
    print(f"== {name}: {Path(path).name}, lags 0..{solution.maxlag} "
          f"(solve + 200 Monte Carlo draws: {elapsed:.2f} s)")
    print(f"  input a(0,0) = {a00:.4g} /e-, a(0,1) parallel = {measured.area[1, 0]:.4g}, "
          f"a(1,0) serial = {measured.area[0, 1]:.4g}")
    print(f"  truncated sum rule of the input: sum a(-n..n) = {solution.truncation_residual:.3g}"
          f" /e- = {solution.truncation_residual / abs(a00):+.2%} of |a(0,0)|")
    print(f"  smoothing f(r) = p0 Ei(p1 r): p0 = {solution.p0:.4g} +- {solution.p0_err:.2g} /e-, "
          f"p1 = {solution.p1:.4f} +- {solution.p1_err:.3f} /px, "
          f"chi2 = {solution.chi2:.1f} / {solution.dof}")
    print(f"  far_scale (solved farthest boundaries / Ei extrapolation) = {solution.far_scale:.3g}")
    print_near_source("a^N", shifts.north, solution.north_err, m)
    print_near_source("a^E", shifts.east, solution.east_err, m)
    parallel, serial = shifts.north[m + 1, m], shifts.east[m, m + 1]
    print(f"  nearest boundaries: parallel a^N(0,1) = {parallel:.4g} +- "
          f"{solution.north_err[m + 1, m]:.2g}, serial a^E(1,0) = {serial:.4g} +- "
          f"{solution.east_err[m, m + 1]:.2g} (ratio {parallel / serial:.2f})")
    largest = max(np.abs(shifts.north).max(), np.abs(shifts.east).max())
    residuals = shifts.symmetry_residuals()
    worst = max(residuals.values()) / largest
    print(f"  symmetries + sum rules of the solution: worst residual / largest a^X = {worst:.1e} "
          f"({', '.join(f'{k} {v:.1e}' for k, v in residuals.items())})")
    sum_back = np.max(np.abs(solution.area_model - measured.area) / measured.area_err)
    print(f"  sums back to the input: max |a_model - a| / sigma = {sum_back:.1e}")
    electrostatic = solve_boundary_shifts(measured.area, measured.area_err, n_samples=0)
    print(f"  N/E split a^N/(a^N + a^E) at (0,0): Ei {split_fraction(shifts.north, shifts.east):.3f}"
          f", electrostatic {split_fraction(electrostatic.shifts.north, electrostatic.shifts.east):.3f}"
          f" (chi2 {electrostatic.chi2:.1f} / {electrostatic.dof})")
    sensitivity = solution.sensitivity
    print(f"  p1 +- {sensitivity['nsigma']:.0f} sigma (p1 = {sensitivity['p1_values'][0]:.3f} / "
          f"{sensitivity['p1_values'][1]:.3f}): a^X change rms {sensitivity['rms_relative']:.2%}, "
          f"max {sensitivity['max_relative']:.1%} (over a^X above 1 % of the largest)")
    if plots is not None:
        import matplotlib
        matplotlib.use("Agg")

        from bfpsf.outputs import save_figure
        from bfpsf.plotting.shifts import plot_radial_profile

        plots.mkdir(parents=True, exist_ok=True)
        fig = plot_radial_profile(solution)
        fig.suptitle(name)
        out = plots / (Path(path).stem + "_radial.png")
        save_figure(fig, out, overwrite=True, dpi=100)
        print(f"  figure: {out}")
    print()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=Path("measured_shifts_output"),
                        help="output directory (the a(r) figure of each table)")
    parser.add_argument("--quick", action="store_true", help="the first table only")
    args = parser.parse_args(argv)
    for name, (short_name, filename) in list(SETS.items())[:1 if args.quick else None]:
        report(name, measured_path(short_name, filename), args.output)


if __name__ == "__main__":
    main()
