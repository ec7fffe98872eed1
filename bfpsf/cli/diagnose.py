"""``bfpsf diagnose``: the closed loop, residual -> missing effect -> added -> before / after.

Two modes (a thin layer over `bfpsf.validation.diagnose`):

* images: ``bfpsf diagnose --flats FLAT.fits... --images IMAGE.fits... [--beta B]``: calibrate
  the flats (`bfpsf.calibrate`), measure the spots of the images (`bfpsf.measure.sources`),
  predict their sizes from the shifts, and test the catalogue on the sizes, the flat linearity
  and the flat correlations.
* tables: ``bfpsf diagnose --correlations A.txt --sizes SIZES.csv [--gain G]`` or
  ``bfpsf diagnose --measured NAME`` for a published data set shipped with bfpsf
  (``bfpsf diagnose --list-measured`` lists them; `bfpsf.data`).

JSON keys: ``residual_before``, ``candidates``, ``selected``, ``residual_after`` (plus
``parameters``, ``ambiguous``, ``residual_physical``, ``threshold``, ``inputs``, and in images
mode ``star_residual``: the stacked residual of the stars against P(F), ``rms_over_peak``,
``chi2_per_pixel``, ``n_stars`` and its radial profile).
"""

import sys
from pathlib import Path

from ..errors import BFPSFInputError

__all__ = ["add_parser", "run"]


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "diagnose", help="find the effect the BF model misses (closed loop)",
        description="Fit the brighter-fatter model, test a catalogue of candidate effects on "
                    "the residuals, add the best by BIC, repeat (bfpsf.validation.diagnose).")
    data = parser.add_argument_group("images mode")
    data.add_argument("--flats", nargs="+", metavar="FLAT.fits", help="flat-field FITS (ADU)")
    data.add_argument("--images", nargs="+", metavar="IMAGE.fits",
                      help="spot / star images (ADU, bias subtracted)")
    data.add_argument("--amp", metavar="NAME",
                      help="the amplifier (EXTNAME) of multi-extension flats and images")
    data.add_argument("--beta", type=float, default=None,
                      help="Moffat index of the spot model (default: Gaussian)")
    data.add_argument("--maxlag", type=int, default=4, help="calibration lags (default 4)")
    data.add_argument("--no-fit-b", dest="fit_b", action="store_false",
                      help="calibrate without the Astier+19 b term (few or small flats)")
    data.add_argument("--bins", type=int, default=10,
                      help="peak bins of the measured sizes (default 10)")
    tables = parser.add_argument_group("table mode")
    tables.add_argument("--correlations", metavar="FILE",
                        help="measured a / correlation table (corr_meas, Poisson_CCD, cp_pipe)")
    tables.add_argument("--sizes", metavar="FILE", help="size-vs-flux table (Lage ITL or BOT)")
    tables.add_argument("--gain", type=float, help="e-/ADU of a size table in ADU")
    tables.add_argument("--measured", metavar="NAME",
                        help="a measured data set shipped with bfpsf, by short name (e.g. "
                             "itl3800c002; see --list-measured)")
    tables.add_argument("--list-measured", action="store_true",
                        help="list the shipped measured data sets and exit")
    tables.add_argument("--corrected", action="store_true",
                        help="use the sizes after the published kernel correction")
    parser.add_argument("--threshold", type=float, default=-10.0,
                        help="Delta BIC below which an effect is added (default -10)")
    parser.add_argument("--physical-first", action="store_true",
                        help="add parameter-free physical predictions before fitted effects")
    parser.add_argument("--report", metavar="DIR", help="write report.md and PNG figures")
    parser.add_argument("--json", metavar="FILE", help="write the JSON summary")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    return parser


def _observables(args):
    from ..validation import diagnose as loop

    if args.measured:
        from ..data import measured_path

        return loop.observables_from_measured(measured_path(args.measured),
                                              corrected=args.corrected)
    if args.correlations or args.sizes:
        if not (args.correlations and args.sizes):
            msg = "table mode needs both --correlations and --sizes"
            raise BFPSFInputError(msg)
        return loop.observables_from_tables(args.correlations, args.sizes, gain=args.gain,
                                            corrected=args.corrected)
    if args.flats and args.images:
        return loop.observables_from_images(args.flats, args.images, beta=args.beta,
                                            maxlag=args.maxlag, n_bins=args.bins,
                                            fit_b=args.fit_b, amp=args.amp)
    msg = ("give --flats and --images, or --correlations and --sizes, or --measured NAME")
    raise BFPSFInputError(msg)


def run(args):
    from ..validation.diagnose import diagnose
    from ..files import check_outputs, write_json
    from ..validation.report import write_diagnosis_report

    if args.list_measured:
        from ..data import measured_sets

        for name, description in measured_sets().items():
            print(f"{name}: {description}")
        return 0

    report = Path(args.report) / "report.md" if args.report else None
    check_outputs([args.json, report], args.overwrite, directories=[args.report])
    observables = _observables(args)
    result = diagnose(observables, threshold=args.threshold,
                      prefer_physical=args.physical_first)
    summary = result.to_json_dict()
    summary["inputs"] = {key: value for key, value in observables.meta.items()
                         if isinstance(value, (str, float, int, bool)) or value is None}
    star = observables.meta.get("star_residual")
    if star is not None:
        summary["star_residual"] = {key: star[key] for key in (
            "rms_over_peak", "chi2_per_pixel", "n_stars", "model_peak", "radius", "profile")}
    before, after = result.residual_before, result.residual_after
    print(f"selected: {', '.join(result.selected) or 'nothing'}")
    for label, values in (("before", before), ("after", after)):
        if "slope_x_percent" in values:
            print(f"{label}: BF slope residual X {values['slope_x_percent']:+.2f} %, "
                  f"Y {values['slope_y_percent']:+.2f} % of raw; photometry bias "
                  f"{values['photometry_bias_mmag']:+.2f} mmag; chi2 {values['chi2']:.1f} "
                  f"/ {values['n']}")
        else:
            print(f"{label}: chi2 {values['chi2']:.1f} / {values['n']}")
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    if args.report:
        label = getattr(observables.sizes, "label", "") if observables.sizes is not None else ""
        context = [f"Data: {label or 'flats and images'}."]
        context += [f"- {key}: `{value}`" for key, value in summary["inputs"].items()]
        path = write_diagnosis_report(result, args.report, title="bfpsf diagnose",
                                      context=context,
                                      residual_images=observables.meta.get("residual_images"),
                                      star_residual=star, overwrite=args.overwrite)
        print(f"report: {path}", file=sys.stderr)
    return 0
