"""``bfpsf validate``: end-to-end validation on GalSim SiliconSensor simulations.

A thin layer over `bfpsf.validation.validate.validate`: simulate flats and Moffat spots, run the
chain, print the side-by-side table, write the JSON summary and the Markdown report.
"""

import sys
from pathlib import Path

from . import (flat_level_option, non_negative_int, output_options, positive_float, positive_int,
               _real)


__all__ = ["add_parser", "run"]


def moffat_beta_option(text):
    """``--beta``: a Moffat index GalSim draws untruncated, > 1.1."""
    return _real(text, lambda value: value > 1.1, "a Moffat index > 1.1 (GalSim's untruncated "
                                                  "Moffat)")


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "validate", help="end-to-end validation on GalSim SiliconSensor simulations",
        description="Simulate SiliconSensor flats and Moffat spots, calibrate, predict the BF "
                    "slopes, fit P(F), compare with the pixel-level inverse and the photometry "
                    "of a static PSF, and run the closed loop.")
    parser.add_argument("--quick", action="store_true",
                        help="small run (under 3 minutes on 2 cores); the README's command")
    parser.add_argument("--sensor", default=None,
                        help="SiliconSensor name (default lsst_itl_50_8)")
    parser.add_argument("--fwhm", type=positive_float, default=None, help="Moffat FWHM, pixels")
    parser.add_argument("--beta", type=moffat_beta_option, default=None, help="Moffat index")
    parser.add_argument("--peaks", type=positive_float, nargs="+", default=None, metavar="E",
                        help="spot peak levels, e-")
    parser.add_argument("--spots-per-level", type=positive_int, default=None, dest="n_per_level",
                        help="spots per peak level (default: the configuration's)")
    parser.add_argument("--flat-size", type=positive_int, default=None, help="flat side, pixels")
    parser.add_argument("--flat-pairs", type=positive_int, default=None,
                        help="pairs per flat level")
    parser.add_argument("--flat-levels", type=flat_level_option, nargs="+", default=None,
                        metavar="E",
                        help="flat levels, electrons (default: the configuration's)")
    parser.add_argument("--model-shifts", choices=("flats", "truth"), default="flats",
                        help="shifts for P(F), the inverse and the loop: from the simulated "
                             "flats (default, the path a user takes) or SiliconSensor's landing "
                             "truth (a diagnostic, labelled as such)")
    parser.add_argument("--seed", type=non_negative_int, default=None,
                        help="random seed (default: the configuration's)")
    parser.add_argument("--report", metavar="DIR", help="write report.md and PNG figures")
    output_options(parser)
    return parser


def _config(args):
    import dataclasses

    from ..validation.validate import FULL, QUICK

    base = QUICK if args.quick else FULL
    changes = {"sensor": args.sensor, "fwhm": args.fwhm, "beta": args.beta,
               "peaks_e": tuple(args.peaks) if args.peaks else None,
               "n_per_level": args.n_per_level, "flat_size": args.flat_size,
               "flat_pairs": args.flat_pairs, "seed": args.seed,
               "flat_levels_e": tuple(args.flat_levels) if args.flat_levels else None}
    return dataclasses.replace(base, **{k: v for k, v in changes.items() if v is not None})


def _print_table(result):
    from ..validation.report import prediction_cells

    slopes = result["slopes"]
    print(f"measured BF slope (pix / 100 ke-): X {slopes['slope_x']:.4f} +- "
          f"{slopes['slope_x_err']:.4f}, Y {slopes['slope_y']:.4f} +- {slopes['slope_y_err']:.4f}")
    for row in result["prediction"].get("rows", []):
        cells = prediction_cells(row)
        print(f"predicted from {row['shifts']}: X {cells[0]}, Y {cells[1]}")
    for key, label in (("psf", "residual slope after P(F)"),
                       ("inverse", "residual slope after pixel inverse")):
        stage = result[key]
        if stage.get("available"):
            print(f"{label}: X {stage['residual_slope_x_percent']:+.1f} +- "
                  f"{stage['residual_slope_x_percent_err']:.1f} %, Y "
                  f"{stage['residual_slope_y_percent']:+.1f} +- "
                  f"{stage['residual_slope_y_percent_err']:.1f} % of raw (paired with the "
                  f"BF-free twins; unpaired X {stage['residual_slope_x_unpaired_percent']:+.1f}"
                  f" +- {stage['residual_slope_x_unpaired_percent_err']:.1f}, Y "
                  f"{stage['residual_slope_y_unpaired_percent']:+.1f} +- "
                  f"{stage['residual_slope_y_unpaired_percent_err']:.1f})")
        else:
            print(f"{label}: not available ({stage.get('reason')})")
    _print_calibration_error(result)
    psf = result["psf"]
    if psf.get("available"):
        print(f"photometry bias bright - faint: static PSF "
              f"{psf['photometry_bias_static_mmag']:+.2f} mmag, P(F) "
              f"{psf['photometry_bias_flux_dependent_mmag']:+.2f} mmag")
    print(f"P(F), inverse and loop used the shifts of: {result['model_shifts']}")
    # the simulation holds brighter-fatter alone: the loop should name no instrument effect
    # (a new user read "selected: nothing" as a failure)
    selected = ", ".join(result["diagnose"]["selected"])
    print("closed loop (bfpsf diagnose) selected: "
          + (f"{selected} (the simulation holds brighter-fatter alone: a false detection)"
             if selected else "nothing, as it should: the simulation holds brighter-fatter "
             "alone, no other instrument effect"))


def _print_calibration_error(result):
    """The residuals above carry the spots' statistics only; the shifts the model used carry
    their own calibration error (a small flat set's is tens of percent of the slope): said
    beside them so that a residual is read against both."""
    slopes = result["slopes"]
    for row in result["prediction"].get("rows", []):
        errors = [row.get(f"predicted_slope_{axis}_err") for axis in "xy"]
        if row["shifts"] != result["model_shifts"] or None in errors:
            continue
        x, y = (100 * error / abs(slopes[f"slope_{axis}"])
                for error, axis in zip(errors, "xy"))
        print(f"  (the shifts of the {row['shifts']} carry their own error: +- {x:.1f} % in X, "
              f"+- {y:.1f} % in Y of raw)")


def run(args):
    from ..files import check_outputs
    from ..outputs import write_json
    from ..resources import check_flat_simulation, check_spot_simulation
    from ..validation.report import REPORT_FILES, write_validation_report
    from ..validation.validate import validate
    from ..validation.verdict import VERDICT_CHECKS, verdict_failures

    report = Path(args.report) / "report.md" if args.report else None
    check_outputs([args.json, report], args.overwrite,
                  folders=[(args.report, REPORT_FILES)])
    config = _config(args)
    check_flat_simulation(config.flat_size, 2 * config.flat_pairs * len(config.flat_levels_e),
                          config.flat_nsteps,
                          option=f"--flat-size {config.flat_size}, {len(config.flat_levels_e)} "
                                 f"--flat-levels x --flat-pairs {config.flat_pairs}")
    check_spot_simulation(config.n_per_level, config.peaks_e, config.fwhm, config.stamp_size,
                          option=f"--spots-per-level {config.n_per_level}, "
                                 f"{len(config.peaks_e)} --peaks up to {max(config.peaks_e):g}")
    result = validate(config, progress=args.progress,
                      shifts_for_model=args.model_shifts)
    _print_table(result)
    failures = verdict_failures(result)
    print("verdict: " + ("PASS: " + VERDICT_CHECKS if not failures
                         else "FAIL: " + "; ".join(failures)))
    if failures:  # what the flats' calibration said of itself, as `bfpsf calibrate` says it
        for warning in result["calibration"].get("warnings", []):
            print(f"  the flats calibration warned: {warning}")
    if args.json:
        summary = {key: value for key, value in result.items()
                   if key not in ("diagnosis", "truth_area", "residual_images")}
        summary["verdict"] = {"passed": not failures, "failures": failures}
        write_json(args.json, summary, overwrite=args.overwrite)
    if args.report:
        path = write_validation_report(result, args.report, overwrite=args.overwrite)
        print(f"report: {path}", file=sys.stderr)
    return 1 if failures else 0
