"""``bfpsf diagnose``: the closed loop, residual -> missing effect -> added -> before / after.

Two modes (a thin layer over `bfpsf.diagnosis`):

* images: ``bfpsf diagnose --flats FLAT.fits... --images IMAGE.fits... [--beta B]``: calibrate
  the flats (`bfpsf.calibrate`), measure the spots of the images (`bfpsf.measure.sources`),
  predict their sizes from the shifts, and test the catalogue on the sizes, the flat linearity
  and the flat correlations.
* tables: ``bfpsf diagnose --correlations A.txt --sizes SIZES.csv [--gain G]`` or
  ``bfpsf diagnose --measured NAME`` for a published data set shipped with bfpsf
  (``bfpsf diagnose --list-measured`` lists them; `bfpsf.data`).

JSON keys: ``residual_before``, ``candidates``, ``selected``, ``residual_after``,
``residual_before_heldout``, ``residual_after_heldout`` (same keys as ``residual_after``),
``confirmed``, ``holdout``, ``unexplained``, ``rejected`` (candidates whose signature the data
contradict, `bfpsf.diagnosis.signature`), ``verdict``, ``empirical`` (the EMPIRICAL term
learned from what is left, with its out-of-sample validation; None when nothing is left) (plus ``nuisance``, ``output_calib``,
``parameters``, ``ambiguous``, ``residual_physical``, ``threshold``, ``inputs``, and in images
mode ``star_residual``: the stacked residual of the stars against P(F), ``rms_over_peak``,
``chi2_per_pixel``, ``n_stars`` and its radial profile; with ``--output-calib``
``star_residual_refined``: the held-out exposures' stacked residual against P(F) from the
flats' calibration and from the refined one, ``flats`` and ``refined`` each with
``chi2_per_pixel``, ``rms_over_peak`` and ``n_stars``. The verdict keeps the flats' figure:
what the refinement absorbed is not evidence that it was the calibration's).
"""

import argparse
import sys
from pathlib import Path

from ..diagnosis.pattern_choice import keep_the_pattern_the_pixels_prefer, refined_star_residual
from ..diagnosis.position_split import describe_split
from ..diagnosis.problem import describe_slope
from ..diagnosis.signature import describe_entry, describe_rejection
from ..errors import BFPSFInputError, BFPSFValueError
from . import (flat_edge_option, maxlag_option, output_options, positive_float, positive_int,
               star_image_options)

__all__ = ["add_parser", "run"]


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "diagnose", help="find the effect the BF model misses (closed loop)",
        description="Fit the brighter-fatter model, test a catalogue of candidate effects on "
                    "the residuals, add the best by BIC, repeat (bfpsf.diagnosis).")
    data = parser.add_argument_group("images mode")
    data.add_argument("--flats", nargs="+", metavar="FLAT.fits", help="flat-field FITS (ADU)")
    data.add_argument("--images", nargs="+", metavar="IMAGE.fits",
                      help="spot / star images (ADU, bias subtracted)")
    data.add_argument("--amp", metavar="NAME",
                      help="the amplifier (EXTNAME) of multi-extension flats and images")
    data.add_argument("--beta", type=float, default=None,
                      help="Moffat index of the profile that gives the exact boundary density "
                           "(default: Gaussian); the spot model itself is the P0 fitted from "
                           "the stars")
    star_image_options(data, saturation="saturated stars are not used", wings=False,
                       threshold=False, sky_degree=False)
    data.add_argument("--maxlag", type=maxlag_option, default="auto", metavar="auto|N",
                      help="calibration lags: 'auto' (default, as bfpsf calibrate) or an "
                           "integer")
    flat_edge_option(data)
    data.add_argument("--no-fit-b", dest="fit_b", action="store_const", const="none",
                      default="off-origin",
                      help="calibrate without the Astier+19 b term (few or small flats); by "
                           "default b is fitted off the origin, as bfpsf calibrate does")
    data.add_argument("--bins", type=positive_int, default=None,
                      help="peak bins of the measured sizes (default 10; fewer, down to 6, "
                           "where that lets every exposure fill the default 2x2 position "
                           "grid with 3 stars per cell)")
    data.add_argument("--position-bins", type=position_bins_option, default=None,
                      metavar="N|NxM",
                      help="also split the bins in N ranges of column (distance from the "
                           "amplifier), or N of column x M of row (the parallel transfers: "
                           "1x3 splits the rows only), for the residual's position "
                           "dependence (default: 2x2 where every exposure has 12 stars "
                           "per peak bin, 72 or more, else 1)")
    tables = parser.add_argument_group("table mode")
    tables.add_argument("--correlations", metavar="FILE",
                        help="measured a / correlation table (corr_meas, Poisson_CCD, cp_pipe)")
    tables.add_argument("--sizes", metavar="FILE", help="size-vs-flux table (Lage ITL or BOT)")
    tables.add_argument("--gain", type=positive_float, help="e-/ADU of a size table in ADU")
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
    parser.add_argument("--holdout-fraction", type=float, default=0.5, metavar="F",
                        help="fit on the rest, report the residual on this fraction of the "
                             "data (whole exposures where known, else alternate flux bins; "
                             "0: no split; default 0.5)")
    parser.add_argument("--output-calib", metavar="REFINED.fits",
                        help="images mode: write the flats' calibration with the confirmed "
                             "effects folded in (bfpsf.diagnosis.refine), for bfpsf psf")
    parser.add_argument("--report", metavar="DIR", help="write report.md and PNG figures")
    output_options(parser)
    return parser


def _observables(args):
    from ..diagnosis import observables as builders
    from ..diagnosis import readers

    if args.measured:
        from ..data import measured_path

        return readers.observables_from_measured(measured_path(args.measured),
                                                 corrected=args.corrected)
    if args.correlations or args.sizes:
        if not (args.correlations and args.sizes):
            msg = "table mode needs both --correlations and --sizes"
            raise BFPSFInputError(msg)
        return readers.observables_from_tables(args.correlations, args.sizes, gain=args.gain,
                                            corrected=args.corrected)
    if args.flats and args.images:
        observables = builders.observables_from_images(
            args.flats, args.images, beta=args.beta, maxlag=args.maxlag, n_bins=args.bins,
            fit_b=args.fit_b, amp=args.amp, holdout_fraction=args.holdout_fraction,
            background=args.background, saturation=args.saturation, progress=None,
            position_bins=args.position_bins, edge=args.edge)
        # the flats' calibration warns as `bfpsf calibrate` does: a new user's diagnose had
        # been silent on electrostatic parameters ended on their bounds
        for warning in getattr(observables.meta.get("calibration"), "warnings", ()):
            print(f"WARNING: flats calibration: {warning}", file=sys.stderr)
        return observables
    msg = ("give --flats and --images, or --correlations and --sizes, or --measured NAME")
    raise BFPSFInputError(msg)


def position_bins_option(text):
    """``--position-bins``: N (ranges of column) or NxM (of column and of row), each >= 1."""
    parts = text.lower().split("x")
    try:
        if len(parts) > 2:
            raise argparse.ArgumentTypeError(text)
        values = tuple(positive_int(part) for part in parts)
    except argparse.ArgumentTypeError:
        msg = f"expected N or NxM of positive integers (e.g. 3 or 1x3), got {text!r}"
        raise argparse.ArgumentTypeError(msg) from None
    return values if len(values) == 2 else values[0]


def _check_binning(args):
    """--bins and --position-bins bin the stars measured in images mode; the tables of the
    other modes come binned: refuse them there rather than ignore them (a user who asks for
    1000 bins expects 1000 bins or an error, not the default's result). Then the defaults."""
    given = [option for option, value in (("--bins", args.bins),
                                          ("--position-bins", args.position_bins))
             if value is not None]
    if given and not (args.flats or args.images):
        mode = "--measured" if args.measured else "--correlations/--sizes"
        msg = (f"{given[0]} bins the stars of images mode (--flats and --images); the sizes "
               f"of {mode} come binned already")
        raise BFPSFInputError(msg)
    # images mode chooses the peak bins with the position grid where neither is given
    if not (args.flats or args.images):
        args.bins = 10 if args.bins is None else args.bins
    args.position_bins = "auto" if args.position_bins is None else args.position_bins


def run(args):
    from ..diagnosis.loop import diagnose
    from ..files import check_outputs, input_files
    from ..outputs import write_json
    from ..validation.report import REPORT_FILES, write_diagnosis_report

    if args.list_measured:
        from ..data import measured_sets

        for name, description in measured_sets().items():
            print(f"{name}: {description}")
        return 0

    _check_binning(args)
    report = Path(args.report) / "report.md" if args.report else None
    check_outputs([args.json, report, args.output_calib,
                   Path(args.report) / "signatures.png" if args.report else None],
                  args.overwrite, folders=[(args.report, REPORT_FILES)],
                  inputs=input_files(args.flats, args.images, args.correlations, args.sizes))
    if args.output_calib and not (args.flats and args.images):
        msg = ("--output-calib needs images mode (--flats and --images): it refines their "
               "calibration")
        raise BFPSFInputError(msg)
    if not 0 <= args.holdout_fraction < 1:
        msg = f"--holdout-fraction must be in [0, 1), got {args.holdout_fraction}"
        raise BFPSFInputError(msg, args.holdout_fraction)
    observables = _observables(args)
    try:
        result = diagnose(observables, threshold=args.threshold,
                          prefer_physical=args.physical_first,
                          holdout_fraction=args.holdout_fraction or None)
    except BFPSFValueError as error:  # a fit the data cannot constrain (too few stars)
        if isinstance(error, BFPSFInputError):
            raise
        images = observables.meta.get("image_paths") or []
        what = f"{len(images)} images ({images[0]}, ...)" if images else "the data"
        msg = (f"{what}: {error}: too few stars for the diagnosis; give more exposures, fewer "
               "--bins or --position-bins, or --holdout-fraction 0")
        raise BFPSFInputError(msg) from None
    images = observables.meta.get("image_paths")
    chosen = None
    # the held-out images as read, prepared and detected, shared by every star residual
    cache = {}
    if args.output_calib:
        # the EMPIRICAL term's pattern kind its held-out stars' pixels prefer
        result, chosen = keep_the_pattern_the_pixels_prefer(
            result, observables, amp=args.amp, background=args.background,
            saturation=args.saturation, cache=cache)
    summary = result.to_json_dict()
    if result.holdout and images and observables.sizes.exposure is not None:
        held = result.holdout.get("heldout_exposures") or []
        result.holdout["fit_images"] = [p for i, p in enumerate(images) if i not in held]
        result.holdout["heldout_images"] = [p for i, p in enumerate(images) if i in held]
        summary["holdout"] = result.holdout
    if args.output_calib:
        from ..diagnosis.refine import refine_calibration

        provenance = {"flats": [str(p) for p in args.flats],
                      "images": (result.holdout or {}).get("fit_images", images),
                      "command": "bfpsf diagnose"}
        refined = refine_calibration(observables.meta["calibration"], result,
                                     provenance=provenance)
        refined.write(args.output_calib, overwrite=args.overwrite)
        if chosen:
            summary["empirical_pattern"] = chosen
            print(f"EMPIRICAL pattern: the {chosen['kind']} (held-out stars' own chi2 per "
                  "pixel against P(F) " + ", ".join(f"{value:.2f} with the {kind}" for kind, value
                                       in chosen["chi2_per_pixel"].items()) + ")")
        summary["output_calib"] = {"path": str(args.output_calib),
                                   **refined.refinement}
        record = refined.refinement
        # the scale and split it applies, said (a new user found the shifts times 2.50 only
        # in the JSON), and the selected effects it does not hold
        print(f"refined calibration: {args.output_calib} "
              f"({', '.join(record['applied']) or 'nothing applied'})"
              + (f"; its shifts are the flats' times {1 + record['scale']:.3f}, X / Y split "
                 f"{record['split']:+.3f}" if record["scale"] or record["split"] else ""))
        unheld = [name for name in result.selected if name in record["not_applied"]]
        for name, why in refined.refinement.get("not_applied", {}).items():
            print(f"  not applied: {name}: {why}")
        summary["star_residual_refined"] = (chosen or {}).get("star_residual") or (
            refined_star_residual(observables, refined,
                                  (result.holdout or {}).get("heldout_exposures"),
                                  amp=args.amp, background=args.background,
                                  saturation=args.saturation, cache=cache))
    summary["inputs"] = {key: value for key, value in observables.meta.items()
                         if isinstance(value, (str, float, int, bool)) or value is None}
    summary["position_split"] = observables.meta.get("position_split", {})
    summary["star_extent"] = observables.meta.get("star_extent")
    summary["inputs"]["star_residual_p0_not_converged"] = [
        str(observables.meta["image_paths"][index])
        for index in observables.meta.get("star_residual_p0_not_converged", [])]
    star = observables.meta.get("star_residual")
    if star is not None:
        summary["star_residual"] = {key: star[key] for key in (
            "rms_over_peak", "chi2_per_pixel", "n_stars", "model_peak", "radius", "profile")}
        # what the numbers are (a new user read the profile against report.md's, which is
        # divided by the model peak)
        summary["star_residual"]["units"] = {
            "profile": "mean residual per unit star flux (report.md: over model_peak)",
            "model_peak": "peak of the unit-flux model", "radius": "pixels"}
    before, after = result.residual_before, result.residual_after
    print(f"selected: {', '.join(result.selected) or 'nothing'}")
    # "after" is the selected effects': with an EMPIRICAL term, say so (a new user read the
    # equal before and after of a run that selected nothing as "nothing improved")
    alone = (" (the selected effects; the EMPIRICAL term's figures are its own lines)"
             if result.empirical else "")
    if args.output_calib and unheld:  # a new user read them as the refined calibration's
        alone += f" ({', '.join(unheld)} not in {args.output_calib})"
    rows = [("before", before), (f"after{alone}", after)]
    if result.residual_after_heldout:
        rows += [("held-out before", result.residual_before_heldout),
                 (f"held-out after{alone}", result.residual_after_heldout)]
        for name, confirmed in result.confirmed.items():
            print(f"{name}: {'confirmed' if confirmed else 'NOT CONFIRMED'} on held-out data")
    for name, entry in result.nuisance.items():
        if entry.get("fitted_on"):  # `bfpsf.diagnosis.quiet_axis`
            print(f"{name} (nuisance): {entry['value']:+.3f} +- {entry['error']:.3f}, fitted on "
                  f"{entry['fitted_on']} ({entry['why']})")
    for name, entry in result.rejected.items():
        print(f"rejected: {describe_rejection(name, entry)}")
    for entry in result.unexplained:
        print(f"unexplained: {describe_entry(entry)}")
    for line in _empirical_lines(result):
        print(line)
    if observables.meta.get("position_bins"):
        print(f"position bins: {observables.meta['position_bins']}")
    for line in _position_lines(observables):
        print(line)
    verdict = result.verdict
    if verdict.get("star_residual_chi2_per_pixel") is not None:
        unsettled = summary["inputs"]["star_residual_p0_not_converged"]
        note = (f"; the P0 of {', '.join(unsettled)} alone did not converge (the best iterate "
                "is used)" if unsettled else "")
        print(f"star residual chi2 per pixel {verdict['star_residual_chi2_per_pixel']:.1f} "
              f"(null expectation {verdict['null_expectation']:.1f}{note})")
    for line in _refined_star_lines(summary.get("star_residual_refined")):
        print(line)
    print("verdict: " + ("explained" if verdict.get("success") else
                         "NOT EXPLAINED: " + "; ".join(verdict.get("reasons", []))))
    for caveat in verdict.get("caveats", []):
        print(f"caveat: {caveat}")
    for label, values in rows:
        if "slope_x_percent" in values:
            print(f"{label}: BF slope residual X {describe_slope(values, 'x')}, "
                  f"Y {describe_slope(values, 'y')}; photometry bias of sky-limited stars, "
                  f"faint - bright, {values['photometry_bias_mmag']:+.2f} +- "
                  f"{values['photometry_bias_mmag_err']:.2f} mmag; chi2 "
                  f"{values['chi2']:.1f} / {values['n']}")
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
        _add_signature_report(result, Path(args.report), observables,
                              summary.get("star_residual_refined"))
        print(f"report: {path}", file=sys.stderr)
    return 0


def _refined_star_lines(entry):
    """The refined calibration's star residual, one line (none without it)."""
    if not entry or not entry.get("flats") or not entry.get("refined"):
        return []
    which = "held-out exposures" if entry["heldout"] else "every exposure"
    return [f"star residual chi2 per pixel on the {which} ({entry['refined']['n_stars']} "
            f"stars, each exposure its own P0): {entry['flats']['chi2_per_pixel']:.1f} with "
            f"the flats' calibration, {entry['refined']['chi2_per_pixel']:.1f} with the "
            "refined one"]


def _position_lines(observables):
    """The stars' BF slope in the two halves of the columns and of the rows, where they
    differ (`bfpsf.diagnosis.position_split`): a test of every star, with or without a
    position grid."""
    return [f"position (each star, no model): {line}"
            for line in describe_split(observables.meta.get("position_split", {}))]


def _add_signature_report(result, directory, observables, refined_star=None):
    """signatures.png and a section of report.md: what was rejected and why, what is left,
    the EMPIRICAL term, the verdict (issue 22) and the refined calibration's star residual."""
    from ..outputs import save_figure, write_text
    from ..plotting.diagnose import plot_signatures

    save_figure(plot_signatures(result), directory / "signatures.png", overwrite=True, dpi=110)
    lines = ["", "## Attribution by signature (issue 22)", ""]
    verdict = result.verdict or {}
    lines.append("Verdict: " + ("explained." if verdict.get("success") else
                                "**NOT EXPLAINED**: " + "; ".join(verdict.get("reasons", []))))
    lines += [f"- caveat: {caveat}" for caveat in verdict.get("caveats", [])]
    lines += [f"- {line}" for line in _refined_star_lines(refined_star)]
    for name, entry in result.rejected.items():
        lines.append(f"- rejected {describe_rejection(name, entry)}")
    for entry in result.unexplained:
        lines.append(f"- unexplained: {describe_entry(entry)}")
    lines += [f"- {line}" for line in _empirical_lines(result)]
    lines += [f"- {line}" for line in _position_lines(observables)]
    lines += ["", "![signatures](signatures.png)", ""]
    path = directory / "report.md"
    write_text(path, path.read_text() + "\n".join(lines), overwrite=True)


def _empirical_lines(result):
    """The EMPIRICAL term's out-of-sample figures, one line per validation block."""
    validation = (result.empirical or {}).get("validation", {})
    lines = []
    if result.empirical:
        lines.append("EMPIRICAL term (it describes the stars, it explains nothing): "
                     + ("written by --output-calib; bfpsf psf, photometry, slope --psf and "
                        "the Piff and GalSim plug-ins apply it"
                        if validation.get("validated", True) else
                        "NOT written by --output-calib (not validated out of sample)"))
    for block in ("heldout", "late_block"):
        if block in validation:
            before, after = validation[block]["before"], validation[block]["after"]
            axes = []
            for axis in "xy":
                if after.get(f"stars_show_bf_{axis}", True):
                    axes.append(f"{axis.upper()} {before[f'slope_{axis}_percent']:+.1f} -> "
                                f"{describe_slope(after, axis, 1)}")
                else:
                    axes.append(f"{axis.upper()} {describe_slope(before, axis)} -> "
                                f"{after[f'residual_slope_{axis}']:+.4f}")
            cross = ""
            if "cross" in after:
                cross = (f"; e2 slope {before['cross']['slope_per_1e5']:+.4f} -> "
                         f"{after['cross']['slope_per_1e5']:+.4f} +- "
                         f"{after['cross']['slope_err']:.4f} per 1e5 e-")
            lines.append(
                f"EMPIRICAL term ({block}): BF slope residual (errors: these stars' and the "
                f"term's own) {', '.join(axes)}; photometry "
                f"bias the sizes imply for sky-limited stars (faint - bright; PSF "
                f"photometry measures the pattern's shape too: docs/undeclared_effects.md) "
                f"{before['photometry_bias_mmag']:+.2f} -> {after['photometry_bias_mmag']:+.2f} "
                f"mmag{cross}")
    odd = [entry["axis"].upper() for entry in result.unexplained
           if entry.get("observable") in ("sizes", "skewness") and entry.get("parity") == "odd"]
    if result.empirical and odd:
        # a new user's diagonal trail: sizes and e2 corrected, its centroid shift (0.025 px
        # at the bright end) neither removed nor said to be
        lines.append(f"EMPIRICAL term: its patterns are even (sizes, e2): the odd part of the "
                     f"residual on {' and '.join(odd)} (a centroid shift or a trail with flux) "
                     "is not in it")
    for entry in validation.get("left", []):
        lines.append(
            f"EMPIRICAL term leaves {entry['axis'].upper()} {entry['after']:+.1f} +- "
            f"{entry['error']:.1f} % of raw on the {BLOCK_NAMES[entry['block']]} ("
            + (f"an overshoot of the {entry['before']:+.1f} before it: "
               if entry["overshoot"] else f"{entry['before']:+.1f} before it: ")
            + "the effect depends on something the term does not hold, e.g. the position "
            "or the exposure; see the unexplained residual's dependences)")
    return lines


#: The EMPIRICAL term's validation blocks, for a person.
BLOCK_NAMES = {"heldout": "held-out exposures", "late_block": "late block"}
