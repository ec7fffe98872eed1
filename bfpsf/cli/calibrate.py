"""``bfpsf calibrate FLAT.fits... -o CALIB.fits``: flat-field calibration (issues 2 and 12).

Parse, call `bfpsf.calibration.calibrate_detectors`, write the calibration file(s), the plots
and the JSON summary. Inputs are flat files (one detector, one product) or directories (one
detector each, every ``*.fits`` in it; ``-o`` is then a directory receiving ``DETECTOR.fits``).
"""

import sys
from pathlib import Path

from ..errors import BFPSFInputError
from ..files import check_outputs, input_files
from ..outputs import make_directory, write_json
from ..resources import check_time
from . import (flat_edge_option, maxlag_option, non_negative_int, output_options, positive_float,
               positive_int, saturation_option)

PLOT_NAMES = ("ptc.png", "correlation_map.png", "area_profile.png")
AMPLIFIER_PLOT = "amplifiers.png"
#: Least time of one Monte Carlo refit of the electrostatic shifts, s (0.16 s measured on a
#: 96^2 flat set at maxlag 2; more at larger maxlag): the time guard of --n-monte-carlo.
MONTE_CARLO_SECONDS = 0.05


def add_parser(subparsers):
    from ..parallel import default_workers

    parser = subparsers.add_parser(
        "calibrate", help="measure gain, a(dx, dy) and boundary shifts from flat pairs",
        description="Flat-field calibration of brighter-fatter (G15 sections 4 and 6.1): flats "
                    "of one amplifier and equal EXPTIME are paired, their covariances fitted "
                    "with the Astier+19 PTC model, and the boundary shifts a^X solved, for "
                    "each amplifier.")
    parser.add_argument("flats", nargs="*", metavar="FLAT.fits",
                        help="flats in ADU with header EXPTIME (s): single-image bias-"
                             "subtracted files, or one HDU per amplifier (EXTNAME, optional "
                             "BIASSEC/DATASEC/DETSEC); or directories, one per detector")
    parser.add_argument("-o", "--output", required=True, metavar="CALIB.fits",
                        help="calibration file to write (versioned multi-extension FITS, one "
                             "HDU group per amplifier); a directory for directory inputs")
    parser.add_argument("--from-ptc", metavar="PTC.fits",
                        help="start from an LSST cp_pipe PTC dataset (its per-pair covariances) "
                             "instead of flats")
    parser.add_argument("--export-ptc", metavar="PTC.fits",
                        help="also write the calibration as a cp_pipe PTC dataset")
    parser.add_argument("--amp", action="append", metavar="NAME",
                        help="calibrate only this amplifier (EXTNAME); repeatable")
    parser.add_argument("--overscan", choices=("median", "clipped_mean"), default="median",
                        help="row-by-row overscan estimator where BIASSEC is given "
                             "(default median)")
    parser.add_argument("--maxlag", type=maxlag_option, default="auto", metavar="auto|N",
                        help="largest lag of the covariances and of a(dx, dy): 'auto' "
                             "(default) picks, per amplifier, the largest lag ring whose "
                             "correlation the flats measure (3 sigma), or give an integer")
    parser.add_argument("--model", choices=("full", "exponential", "quadratic"), default="full",
                        help="PTC model: Astier+19 eq. 20 'full' (default), eq. 16 "
                             "'exponential', or G15's 'quadratic'")
    parser.add_argument("--saturation", type=saturation_option, default=None, metavar="ADU",
                        help="mask pixels at or above this level (ADU)")
    flat_edge_option(parser)
    parser.add_argument("--shift-method", choices=("electrostatic", "ei"),
                        default="electrostatic",
                        help="solver of the boundary shifts: the electrostatic sensor model of "
                             "Astier & Regnault 2023 (default) or G15's Ei smoothing model")
    parser.add_argument("--thickness", type=positive_float, default=10.0, metavar="PIXELS",
                        help="sensor thickness in pixels for the electrostatic model "
                             "(default 10: 100 um with 10 um pixels)")
    parser.add_argument("--n-monte-carlo", type=non_negative_int, default=100,
                        help="samples of the boundary shifts drawn from the calibration error, "
                             "kept for error propagation (default 100)")
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="seed of the samples (default 0)")
    parallel = parser.add_mutually_exclusive_group()
    parallel.add_argument("--workers", type=positive_int, default=default_workers(), metavar="N",
                          help="processes measuring the pairs (Dask LocalCluster; 1: in this "
                               f"process; default the CPU count, {default_workers()})")
    parallel.add_argument("--scheduler", metavar="ADDRESS",
                          help="run on an existing Dask cluster (e.g. tcp://host:8786)")
    parser.add_argument("--plots", metavar="DIR",
                        help="write PTC, correlation-map and a(r) plots (PNG) into DIR")
    output_options(parser)
    return parser


def _detectors(args):
    """``({detector: sources}, {detector: output path})``."""
    if bool(args.flats) == bool(args.from_ptc):
        msg = "give flat files (or detector directories), or --from-ptc PTC.fits; not both"
        raise BFPSFInputError(msg, args.flats)
    if args.from_ptc:
        for option, value in (("--edge", args.edge), ("--saturation", args.saturation)):
            if value is not None:
                msg = f"{option} applies to flats; cp_pipe measured {args.from_ptc} with its own"
                raise BFPSFInputError(msg, option)
        return {"": None}, {"": Path(args.output)}
    paths = [Path(path) for path in args.flats]
    directories = [path.is_dir() for path in paths]
    if not any(directories):
        return {"": args.flats}, {"": Path(args.output)}
    if not all(directories):
        # directories are detectors only when every input is one
        directory = paths[directories.index(True)]
        msg = f"flat file {directory} is a directory, not a file"
        raise BFPSFInputError(msg, str(directory))
    detectors, outputs = {}, {}
    for path in paths:
        files = sorted(str(file) for file in path.glob("*.fits"))
        if not files:
            msg = f"{path}: no *.fits flats in this detector directory"
            raise BFPSFInputError(msg, str(path))
        detectors[path.name] = files
        outputs[path.name] = Path(args.output) / f"{path.name}.fits"
    return detectors, outputs


def _plot_paths(args, calibration):
    if not args.plots:
        return []
    amplifiers = getattr(calibration, "amplifiers", None)
    if amplifiers is None:
        return [Path(args.plots) / name for name in PLOT_NAMES]
    return [Path(args.plots) / AMPLIFIER_PLOT, *(Path(args.plots) / amp / name
                                                  for amp in amplifiers for name in PLOT_NAMES)]


def _print(detector, calibration):
    from ..calibration.detector import amplifiers_of

    for name, one in amplifiers_of(calibration).items():
        label = " ".join(part for part in (detector, name) if part)
        prefix = f"{label}: " if label else ""
        a = one.a
        print(f"{prefix}gain {one.gain:.5f} +- {one.gain_err:.5f} e-/ADU, "
              f"read noise {one.noise_e:.3f} +- {one.noise_e_err:.3f} e-, {one.n_pairs} pairs, "
              f"turnoff {one.turnoff_e:.4g} e-"
              + (" (detected)" if one.turnoff_detected else " (not reached)"))
        if not one.read_noise_determined:
            # the PTC's intercept: flats far above the read noise do not measure it
            print(f"{prefix}WARNING: these flats do not determine the read noise "
                  f"({one.noise_e:.3f} +- {one.noise_e_err:.3f} e-); `bfpsf photometry` "
                  f"measures it on each image's sky unless given --read-noise (bias frames "
                  f"or a flat level near the read noise measure it)")
        how = ("chosen from the data: " + one.parameters["maxlag_reason"]
               if one.parameters.get("maxlag_auto") else "given")
        print(f"{prefix}maxlag {one.maxlag} ({how})")
        print(f"{prefix}a(0,0) {a[0, 0]:.4e} +- {one.a_err[0, 0]:.2e}, a(1,0) {a[0, 1]:.4e}, "
              f"a(0,1) {a[1, 0]:.4e} 1/e-  [{one.model} model]")
        if one.linearity.flagged:
            print(f"{prefix}WARNING: non-linear response, "
                  f"{1e3 * one.linearity.peak_to_peak:.3g} per mil peak to peak > "
                  f"{1e3 * one.linearity.threshold:.3g}")
        elif one.linearity.measured:  # said either way (a new user looked for it in vain)
            print(f"{prefix}linearity: {1e3 * one.linearity.peak_to_peak:.3g} per mil peak to "
                  f"peak (not flagged: <= {1e3 * one.linearity.threshold:.3g})")
        if one.pedestal.any_detected:
            print(f"{prefix}readout pedestal subtracted at "
                  f"{int(one.pedestal.detected.sum())} lag(s)")
        if one.shifts is not None:
            m = one.shifts.radius
            north, east = one.shifts.north[m, m], one.shifts.east[m, m]
            print(f"{prefix}boundary shifts ({one.shift_method}): a^N(0,0) {north:.3e} +- "
                  f"{one.shifts_north_err[m, m]:.1e}, a^E(0,0) {east:.3e} +- "
                  f"{one.shifts_east_err[m, m]:.1e} 1/e-")


def run(args):
    from ..calibration import calibrate_detectors

    detectors, outputs = _detectors(args)
    # Refuse before the (long) computation rather than after it.
    if args.export_ptc and len(detectors) > 1:
        msg = "--export-ptc takes one detector"
        raise BFPSFInputError(msg, args.export_ptc)
    if args.plots and len(detectors) > 1:
        msg = "--plots takes one detector; calibrate the directories one at a time for plots"
        raise BFPSFInputError(msg, args.plots)
    inputs = input_files(args.flats, args.from_ptc)
    check_time(MONTE_CARLO_SECONDS * args.n_monte_carlo, option=f"--n-monte-carlo "
               f"{args.n_monte_carlo}", what="sampling the boundary shifts' errors")
    check_outputs([*outputs.values(), args.json, args.export_ptc], args.overwrite,
                  directories=[None if "" in detectors else args.output],
                  folders=[(args.plots, ("*.png", "*/*.png"))], inputs=inputs)

    if args.from_ptc:
        from ..calibration import calibrate_from_ptc

        calibrations = {"": calibrate_from_ptc(
            args.from_ptc, amps=args.amp, maxlag=args.maxlag, ptc_model=args.model,
            shift_method=args.shift_method, thickness=args.thickness,
            n_monte_carlo=args.n_monte_carlo, seed=args.seed)}
    else:
        calibrations = calibrate_detectors(
            detectors, maxlag=args.maxlag, ptc_model=args.model, saturation=args.saturation,
            shift_method=args.shift_method, thickness=args.thickness,
            n_monte_carlo=args.n_monte_carlo, seed=args.seed, progress=args.progress,
            amps=args.amp, overscan=args.overscan, workers=args.workers,
            scheduler=args.scheduler, edge=args.edge)
    for calibration in calibrations.values():
        check_outputs(_plot_paths(args, calibration), args.overwrite, directories=[args.plots],
                      inputs=inputs)
    if "" not in detectors:  # made once the work has succeeded: a failed run leaves nothing
        make_directory(args.output)
    summaries = []
    for detector, calibration in calibrations.items():
        calibration.write(outputs[detector], overwrite=args.overwrite)
        if args.plots:
            _save_plots(calibration, args.plots, args.overwrite)
        summaries.append({"output": str(outputs[detector]), "detector": detector,
                          **calibration.to_json_dict()})
        _print(detector, calibration)
        for warning in calibration.warnings:
            print(f"WARNING: {' '.join(filter(None, (detector, warning)))}", file=sys.stderr)
        print(f"wrote {outputs[detector]}")
        if args.export_ptc:
            from ..calibration.cp_pipe import write_ptc_dataset

            write_ptc_dataset(args.export_ptc, calibration, overwrite=args.overwrite)
            print(f"wrote {args.export_ptc} (cp_pipe PTC dataset)")
    if args.json:
        write_json(args.json, summaries[0] if len(summaries) == 1 else {"detectors": summaries},
                   overwrite=args.overwrite)
    return 0


def _save_plots(calibration, directory, overwrite):
    """The calibration plots; for several amplifiers, those of each in DIR/AMP/ and the
    comparison of all in DIR/amplifiers.png."""
    from ..outputs import save_figure
    from ..plotting.amplifiers import plot_amplifiers
    from ..plotting.calibration import save_calibration_plots

    amplifiers = getattr(calibration, "amplifiers", None)
    if amplifiers is None:
        save_calibration_plots(calibration, directory, overwrite=overwrite)
        return
    for name, one in amplifiers.items():
        save_calibration_plots(one, Path(directory) / name, overwrite=overwrite)
    save_figure(plot_amplifiers(calibration), Path(directory) / AMPLIFIER_PLOT,
                overwrite=overwrite, dpi=100)
