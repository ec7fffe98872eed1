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
import sys
from pathlib import Path

import numpy as np

from bfpsf.piff.field import acceptance, carried_errors, write_field


def calibration(workdir, sensor, quick, seed):
    """``bfpsf simulate flats`` + ``bfpsf calibrate`` (the README's commands), cached."""
    path = workdir / "calib.fits"
    if path.exists():
        return path
    flats = workdir / "flats"
    size, pairs = ("128", "2") if quick else ("512", "4")
    bfpsf = [sys.executable, "-m", "bfpsf"]  # this environment's, activated or not
    subprocess.run([*bfpsf, "simulate", "flats", "--sensor", sensor, "--pairs", pairs,
                    "--size", size, "--nsteps", "10", "--seed", str(seed), "-o", str(flats),
                    "--no-progress"], check=True)
    subprocess.run([*bfpsf, "calibrate", *sorted(str(p) for p in flats.glob("*.fits")),
                    "-o", str(path)], check=True)
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", type=Path, default=Path("bench_piff_work"))
    parser.add_argument("--exposures", type=int, default=12)
    parser.add_argument("--seed", type=int, default=23)
    parser.add_argument("--flats-seed", type=int,
                        help="seed of the flats made when the work directory has no "
                             "calibration (default: --seed + 1000)")
    parser.add_argument("--sensor", default="lsst_itl_50_8")
    parser.add_argument("--calib", type=Path, help="use this calibration instead of flats")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--control", action="store_true",
                        help="also draw every exposure without BF (same photons and noise) "
                             "and subtract plain Piff's residuals on it, star by star")
    parser.add_argument("--plot", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    workdir = args.workdir
    workdir.mkdir(parents=True, exist_ok=True)
    exposures = 2 if args.quick else args.exposures
    flats_seed = args.seed + 1000 if args.flats_seed is None else args.flats_seed
    calib = args.calib or calibration(workdir, args.sensor, args.quick, flats_seed)
    field = workdir / f"field_{args.sensor}_{args.seed}"
    files = [(field / f"exposure_{k}.fits", field / f"stars_{k}.fits") for k in range(exposures)]
    controls = [(field / f"control_{k}.fits", field / f"stars_{k}.fits")
                for k in range(exposures)] if args.control else None
    if not all(image.exists() for image, _ in files + (controls or [])):
        written = write_field(field, n_exposures=exposures, sensor=args.sensor, seed=args.seed,
                              control=args.control)
        files, controls = written if args.control else (written, None)
    result = acceptance(files, calib, controls=controls)
    print(f"{len(result['plain']['flux_e'])} stars in {exposures} exposures, calibration {calib}")
    print(f"{'':16s}{'size slope (%/100 ke-)':>26s}{'e1 slope (1e-4/100 ke-)':>28s}"
          f"{'fit CPU (s)':>14s}")
    for kind, label in (("plain", "plain Piff"), ("bf", "BrighterFatter")):
        row = result[kind]
        print(f"{label:16s}{100 * row['size'].slope:+14.4f} +- {100 * row['size'].slope_err:.4f}"
              f"{1e4 * row['e1'].slope:+16.3f} +- {1e4 * row['e1'].slope_err:.3f}"
              f"{row['seconds']:14.1f}")
    if controls is not None:
        row = result["control"]
        print(f"{'no-BF control':16s}{100 * row['size'].slope:+14.4f} +- "
              f"{100 * row['size'].slope_err:.4f}{1e4 * row['e1'].slope:+16.3f} +- "
              f"{1e4 * row['e1'].slope_err:.3f}   (plain Piff on the same stars without BF)")
        for key, scale in (("size", 100), ("e1", 1e4)):
            plain, left = result[f"{key}_plain"], result[f"{key}_left"]
            print(f"{key} minus control, star by star: plain {scale * plain.slope:+.4f} +- "
                  f"{scale * plain.slope_err:.4f}, BrighterFatter {scale * left.slope:+.4f} +- "
                  f"{scale * left.slope_err:.4f}")
    from bfpsf import Calibration
    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma

    carried = carried_errors(Calibration.read(calib),
                             diffusion=silicon_diffusion_sigma(args.sensor))
    result.update(size_carried=carried["size"], e1_carried=carried["e1"])
    print(f"the calibration's carried error (its shift samples) on the BF change of a star: "
          f"size {100 * carried['size']:.1f} %, e1 {100 * carried['e1']:.1f} %")
    print(f"ratios BF / plain: size {result['size_ratio']:.3f} +- {result['size_ratio_err']:.3f}, "
          f"e1 {result['e1_ratio']:.3f} +- {result['e1_ratio_err']:.3f}, "
          f"fit time {result['time_ratio']:.2f}")
    if args.plot:
        from bfpsf.plotting.flux_residuals import plot_flux_residuals

        plot_flux_residuals({"plain Piff": result["plain"],
                             "BrighterFatter": result["bf"]}).savefig(args.plot, dpi=110)
    if args.json:
        summary = {kind: {key: {"slope": result[kind][key].slope,
                                "slope_err": result[kind][key].slope_err}
                          for key in ("size", "e1")} | {"seconds": result[kind]["seconds"]}
                   for kind in ("plain", "bf", "control") if kind in result}
        for key in ("size", "e1"):
            for part in ("plain", "left"):
                fit = result[f"{key}_{part}"]
                summary[f"{key}_{part}"] = {"slope": fit.slope, "slope_err": fit.slope_err}
        summary.update({key: float(result[key]) for key in (
            "size_ratio", "size_ratio_err", "e1_ratio", "e1_ratio_err", "time_ratio",
            "size_carried", "e1_carried")},
                       n_stars=int(len(result["plain"]["flux_e"])),
                       calibration=str(calib), exposures=exposures,
                       unit="slopes per 100 ke- of total flux; size = dT/T")
        args.json.write_text(json.dumps(summary, indent=1, default=float))
    return 0 if np.isfinite(result["time_ratio"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
