"""``bfpsf calibrate FLAT.fits... -o CALIB.fits``: flat-field calibration.

Parse, call `bfpsf.calibrate`, write the calibration file, the plots and the JSON summary.
"""

import sys
from pathlib import Path

from ..files import check_outputs, write_json

PLOT_NAMES = ("ptc.png", "correlation_map.png", "area_profile.png")


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "calibrate", help="measure gain, a(dx, dy) and boundary shifts from flat pairs",
        description="Flat-field calibration of brighter-fatter (G15 sections 4 and 6.1): flats "
                    "of equal EXPTIME are paired, their covariances fitted with the Astier+19 "
                    "PTC model, and the boundary shifts a^X solved.")
    parser.add_argument("flats", nargs="+", metavar="FLAT.fits",
                        help="bias-subtracted flats in ADU with header EXPTIME (s)")
    parser.add_argument("-o", "--output", required=True, metavar="CALIB.fits",
                        help="calibration file to write (versioned multi-extension FITS)")
    parser.add_argument("--maxlag", type=int, default=8,
                        help="largest lag of the covariances and of a(dx, dy) (default 8)")
    parser.add_argument("--model", choices=("full", "exponential", "quadratic"), default="full",
                        help="PTC model: Astier+19 eq. 20 'full' (default), eq. 16 "
                             "'exponential', or G15's 'quadratic'")
    parser.add_argument("--saturation", type=float, default=None, metavar="ADU",
                        help="mask pixels at or above this level (ADU)")
    parser.add_argument("--shift-method", choices=("electrostatic", "ei"),
                        default="electrostatic",
                        help="solver of the boundary shifts: the electrostatic sensor model of "
                             "Astier & Regnault 2023 (default) or G15's Ei smoothing model")
    parser.add_argument("--thickness", type=float, default=10.0, metavar="PIXELS",
                        help="sensor thickness in pixels for the electrostatic model "
                             "(default 10: 100 um with 10 um pixels)")
    parser.add_argument("--n-monte-carlo", type=int, default=100,
                        help="samples of the boundary shifts drawn from the calibration error, "
                             "kept for error propagation (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples (default 0)")
    parser.add_argument("--plots", metavar="DIR",
                        help="write PTC, correlation-map and a(r) plots (PNG) into DIR")
    parser.add_argument("--json", metavar="FILE", help="write a JSON summary")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing output files")
    return parser


def run(args):
    from ..calibration import calibrate

    # Refuse before the (long) computation rather than after it.
    plots = [Path(args.plots) / name for name in PLOT_NAMES] if args.plots else []
    check_outputs([args.output, args.json, *plots], args.overwrite, directories=[args.plots])

    calibration = calibrate(args.flats, maxlag=args.maxlag, ptc_model=args.model,
                            saturation=args.saturation, shift_method=args.shift_method,
                            thickness=args.thickness, n_monte_carlo=args.n_monte_carlo,
                            seed=args.seed, progress=args.progress)
    calibration.write(args.output, overwrite=args.overwrite)
    if args.plots:
        from ..plotting.calibration import save_calibration_plots

        save_calibration_plots(calibration, args.plots, overwrite=args.overwrite)
    if args.json:
        write_json(args.json, calibration.to_json_dict(), overwrite=args.overwrite)

    a = calibration.a
    print(f"gain {calibration.gain:.5f} +- {calibration.gain_err:.5f} e-/ADU, "
          f"read noise {calibration.noise_e:.3f} e-, {calibration.n_pairs} pairs, "
          f"turnoff {calibration.turnoff_e:.4g} e-"
          + (" (detected)" if calibration.turnoff_detected else " (not reached)"))
    print(f"a(0,0) {a[0, 0]:.4e} +- {calibration.a_err[0, 0]:.2e}, a(1,0) {a[0, 1]:.4e}, "
          f"a(0,1) {a[1, 0]:.4e} 1/e-  [{calibration.model} model]")
    if calibration.linearity.flagged:
        print(f"WARNING: non-linear response, {1e3 * calibration.linearity.peak_to_peak:.3g} "
              f"per mil peak to peak > {1e3 * calibration.linearity.threshold:.3g}")
    if calibration.pedestal.any_detected:
        print(f"readout pedestal subtracted at {int(calibration.pedestal.detected.sum())} lag(s)")
    if calibration.shifts is not None:
        m = calibration.shifts.radius
        north, east = calibration.shifts.north[m, m], calibration.shifts.east[m, m]
        print(f"boundary shifts ({calibration.shift_method}): a^N(0,0) {north:.3e} +- "
              f"{calibration.shifts_north_err[m, m]:.1e}, a^E(0,0) {east:.3e} +- "
              f"{calibration.shifts_east_err[m, m]:.1e} 1/e-")
    for warning in calibration.warnings:
        print(f"WARNING: {warning}", file=sys.stderr)
    print(f"wrote {args.output}")
    return 0

