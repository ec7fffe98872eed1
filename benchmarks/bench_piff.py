"""Plain Piff against BrighterFatter on SiliconSensor exposures: residual slopes and fit time.

The acceptance of issue 23, on the path a user takes: flats simulated from GalSim's
SiliconSensor and calibrated with ``bfpsf simulate flats`` / ``bfpsf calibrate`` (not the
simulator's truth), exposures of the same sensor with the PSF varying over the field and
stars of 3 to 120 ke- of peak (`bfpsf.piff.field.write_field`), each exposure fitted by
``piff.process`` with PixelGrid + BasisPolynomial (order 1), plain and inside
``type: BrighterFatter``. Prints both residual slopes and both fit CPU times side by side.

    OMP_NUM_THREADS=1 python benchmarks/bench_piff.py --workdir bench_piff_work \
        [--exposures 12] [--seed 23] [--plot residuals.png] [--json result.json]
    python benchmarks/bench_piff.py --quick          # seconds-to-minutes smoke run

Files already in ``--workdir`` (flats, calibration, exposures) are reused.
"""

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np

from bfpsf.piff.field import acceptance, write_field


def calibration(workdir, sensor, quick, seed):
    """``bfpsf simulate flats`` + ``bfpsf calibrate`` (the README's commands), cached."""
    path = workdir / "calib.fits"
    if path.exists():
        return path
    flats = workdir / "flats"
    size, pairs = ("128", "2") if quick else ("512", "4")
    subprocess.run(["bfpsf", "simulate", "flats", "--sensor", sensor, "--pairs", pairs,
                    "--size", size, "--nsteps", "10", "--seed", str(seed), "-o", str(flats),
                    "--no-progress"], check=True)
    subprocess.run(["bfpsf", "calibrate", *sorted(str(p) for p in flats.glob("*.fits")),
                    "-o", str(path)], check=True)
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("bench_piff_work"))
    parser.add_argument("--exposures", type=int, default=12)
    parser.add_argument("--seed", type=int, default=23)
    parser.add_argument("--sensor", default="lsst_itl_50_8")
    parser.add_argument("--calib", type=Path, help="use this calibration instead of flats")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    workdir = args.workdir
    workdir.mkdir(parents=True, exist_ok=True)
    exposures = 2 if args.quick else args.exposures
    calib = args.calib or calibration(workdir, args.sensor, args.quick, args.seed + 1000)
    field = workdir / f"field_{args.sensor}_{args.seed}"
    files = [(field / f"exposure_{k}.fits", field / f"stars_{k}.fits") for k in range(exposures)]
    if not all(image.exists() for image, _ in files):
        files = write_field(field, n_exposures=exposures, sensor=args.sensor, seed=args.seed)
    result = acceptance(files, calib)
    print(f"{len(result['plain']['flux_e'])} stars in {exposures} exposures, calibration {calib}")
    print(f"{'':16s}{'size slope (%/100 ke-)':>26s}{'e1 slope (1e-4/100 ke-)':>28s}"
          f"{'fit CPU (s)':>14s}")
    for kind, label in (("plain", "plain Piff"), ("bf", "BrighterFatter")):
        row = result[kind]
        print(f"{label:16s}{100 * row['size'].slope:+14.4f} +- {100 * row['size'].slope_err:.4f}"
              f"{1e4 * row['e1'].slope:+16.3f} +- {1e4 * row['e1'].slope_err:.3f}"
              f"{row['seconds']:14.1f}")
    print(f"ratios BF / plain: size {result['size_ratio']:.3f}, e1 {result['e1_ratio']:.3f}, "
          f"fit time {result['time_ratio']:.2f}")
    if args.plot:
        from bfpsf.plotting.flux_residuals import plot_flux_residuals

        plot_flux_residuals({"plain Piff": result["plain"],
                             "BrighterFatter": result["bf"]}).savefig(args.plot, dpi=110)
    if args.json:
        summary = {kind: {key: {"slope": result[kind][key].slope,
                                "slope_err": result[kind][key].slope_err}
                          for key in ("size", "e1")} | {"seconds": result[kind]["seconds"]}
                   for kind in ("plain", "bf")}
        summary.update({key: float(result[key]) for key in ("size_ratio", "e1_ratio",
                                                            "time_ratio")},
                       n_stars=int(len(result["plain"]["flux_e"])),
                       calibration=str(calib), exposures=exposures,
                       unit="slopes per 100 ke- of total flux; size = dT/T")
        args.json.write_text(json.dumps(summary, indent=1, default=float))
    return 0 if np.isfinite(result["time_ratio"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
