"""``bfpsf simulate``: write simulated data with known truth.

    bfpsf simulate flats --sensor lsst_itl_50_8 --levels 10000 30000 ... --pairs N --size N
                         --gain G --read-noise R --nsteps K --seed S -o DIR [--overwrite]

Each target is a sub-command of ``simulate`` (``flats`` here; others, e.g. ``spots``, can be
added to ``TARGETS``).
"""

import argparse

from . import (add_common_options, finite_float, flat_level_option, non_negative_float,
               non_negative_int, output_options, positive_float, positive_int, _real)

__all__ = ["add_parser", "run", "TARGETS"]


def readout_correlation_option(text):
    """``--readout-correlation``: the fraction c of the previous pixel's charge added to each
    pixel (R(1, 0) = c / (1 + c^2) for a flat): -1 < c < 1."""
    return _real(text, lambda value: -1 < value < 1,
                 "a fraction of the previous pixel's charge, -1 < c < 1")


def lamp_flicker_option(text):
    """``--lamp-flicker``: the relative rms of each exposure's lamp level, in [0, 0.5)."""
    return _real(text, lambda value: 0 <= value < 0.5, "a relative rms in [0, 0.5)")


def _add_flats(targets):
    from ..validation.simulate_flats import DEFAULT_LEVELS_E

    parser = targets.add_parser(
        "flats",
        help="flat-field pairs from GalSim's SiliconSensor (truth for `bfpsf calibrate`)",
        description="Write flat-field pairs made with GalSim's SiliconSensor, in ADU, with "
                    "EXPTIME and the true simulation parameters in each FITS header.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--sensor", default="lsst_itl_50_8",
                        help="GalSim SiliconSensor name (lsst_itl_50_8, lsst_e2v_50_8, ...)")
    parser.add_argument("--levels", type=flat_level_option, nargs="+",
                        default=list(DEFAULT_LEVELS_E),
                        metavar="E", help="flat levels, electrons per pixel")
    parser.add_argument("--pairs", type=positive_int, default=1, help="pairs per level")
    parser.add_argument("--size", type=positive_int, default=256, help="image side, pixels")
    parser.add_argument("--gain", type=positive_float, default=1.5, help="gain, e-/ADU")
    parser.add_argument("--read-noise", type=non_negative_float, default=5.0,
                        help="read noise, e- rms")
    parser.add_argument("--nsteps", type=positive_int, default=20,
                        help="charge increments per flat (covariance bias ~ 1/nsteps^2)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="random seed")
    parser.add_argument("--exptime-per-e", type=positive_float, default=1e-3,
                        help="EXPTIME per electron of level, s")
    parser.add_argument("--nonlinearity", type=finite_float, default=0.0,
                        help="quadratic non-linearity, 1/e-: signal = q (1 + NL q)")
    parser.add_argument("--readout-correlation", type=readout_correlation_option, default=0.0,
                        help="serial readout correlation c (G15 pedestal, R(1,0) ~ c)")
    parser.add_argument("--hot-columns", type=non_negative_int, nargs="*", default=[], metavar="X",
                        help="columns with 2%% extra charge")
    parser.add_argument("--defect-clusters", type=non_negative_int, default=0,
                        help="number of 3x3 defect clusters")
    parser.add_argument("--lamp-flicker", type=lamp_flicker_option, default=0.0, metavar="F",
                        help="relative rms of each exposure's lamp level (default 0; real "
                             "lamps flicker by about 1e-3; bfpsf diagnose measures the floor "
                             "of the flats' means from their scatter about a quadratic in "
                             "exposure time, 0 where the shot noise explains it)")
    parser.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="output directory (created if missing)")
    output_options(parser, json=False)
    add_common_options(parser)
    return parser


def _run_flats(args):
    from ..resources import check_flat_simulation
    from ..validation.simulate_flats import write_flats

    check_flat_simulation(args.size, 2 * args.pairs * len(args.levels), args.nsteps,
                          option=f"--size {args.size}, --nsteps {args.nsteps}, "
                                 f"{len(args.levels)} --levels x --pairs {args.pairs}")
    paths = write_flats(args.output, args.sensor, args.levels, overwrite=args.overwrite,
                        pairs=args.pairs, size=args.size, gain=args.gain,
                        read_noise_e=args.read_noise, nsteps=args.nsteps, seed=args.seed,
                        exptime_per_e=args.exptime_per_e, nonlinearity=args.nonlinearity,
                        readout_correlation=args.readout_correlation,
                        hot_columns=args.hot_columns, defect_clusters=args.defect_clusters,
                        lamp_jitter=args.lamp_flicker, progress=args.progress)
    print(f"wrote {len(paths)} flats ({len(args.levels)} levels x {args.pairs} pair(s)) "
          f"to {args.output}")
    return 0


#: simulate targets: name -> (function adding its parser, function running it)
TARGETS = {"flats": (_add_flats, _run_flats)}


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "simulate", help="write simulated data with known truth (flats, ...)",
        description="Write simulated data with known truth.")
    targets = parser.add_subparsers(dest="simulate_target", metavar="TARGET")
    for name, (add, run_target) in TARGETS.items():
        add(targets).set_defaults(_simulate_run=run_target)
    parser.set_defaults(_simulate_parser=parser)
    return parser


def run(args):
    if not hasattr(args, "_simulate_run"):
        args._simulate_parser.print_help()
        return 2
    return args._simulate_run(args)
