"""``bfpsf slope STARS.ecsv``: brighter-fatter slopes of the star sizes.

Parse, read the star table of ``bfpsf measure``, optionally correct the size-colour relation
(G15 section 3.3), fit sigma_x, sigma_y and IQ against peak flux
(`bfpsf.measure.slopes.bf_slopes`), print, write the JSON summary and the plot.

JSON keys: ``x``, ``y``, ``iq`` (each ``{slope, slope_err, intercept, relative_percent}``,
slope in pixels per 100 ke- of peak, relative_percent in percent of the intercept per
100 ke-), ``e1``, ``e2`` (each ``{slope, slope_err, intercept}``, slope per 100 ke- of peak;
when the table has e1, e2), ``n_stars``, and ``details`` (full fits, colour fit, peak range).
With ``--psf``: ``prediction`` (``{x, y, iq: {slope, slope_err}}``, the slopes P(F) predicts
for these stars, slope_err the calibration error from the shift samples in the PSF product)
and ``model_residual``: slopes of the measured sizes and ellipticities minus the model's at each
star's own flux, position and sub-pixel phase (so neither the BF change the model explains nor
the field's size variation of a ``--grid`` product is left in them), each with
``slope_err_total`` (the statistical and calibration errors combined) and ``pull``; the sizes'
``intercept`` is star minus model at zero flux and their ``relative_percent`` is the residual
slope in percent of the stars' own size (the raw intercept), ``percent_of_raw`` in percent of
the measured slope. ``prediction`` holds ``e1`` and
``e2`` too, with their calibration errors.
And ``empirical``: the EMPIRICAL term of a refined calibration the PSF product applies (its
record, label ``'empirical'``; in the prediction and the residual), or None.
"""

import sys

import numpy as np

from ..errors import BFPSFInputError
from . import output_options, _real
from ._files import warn_unconverged
from ..files import about, check_outputs, input_files, read_table
from ..outputs import save_figure, write_json


def peak_option(text):
    """``--min-peak``, ``--max-peak``, ``--color-max-peak``: a positive finite peak, e-."""
    return _real(text, lambda value: value > 0, "a positive finite peak in e-")


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "slope", help="fit star sizes against peak flux (brighter-fatter slopes)",
        description="Weighted linear fits of sigma_x = sqrt(Mxx), sigma_y = sqrt(Myy) and "
                    "IQ against peak flux below a maximum peak (G15 section 3.3, fig. mbf).")
    parser.add_argument("stars", metavar="STARS.ecsv", help="star table from bfpsf measure")
    parser.add_argument("--psf", metavar="PSF.fits",
                        help="flux-dependent PSF product: adds prediction (the slopes the model predicts, with the calibration error) and model_residual")
    parser.add_argument("--color", "--colour", dest="colour", metavar="COLUMN",
                        help="correct the size-colour relation with this column first")
    parser.add_argument("--color-max-peak", dest="colour_max_peak", type=peak_option, metavar="E",
                        help="peak limit of the colour-fit stars, e- (default: faintest half)")
    parser.add_argument("--min-peak", type=peak_option, default=None, metavar="E",
                        help="smallest peak fitted, e- (default: all)")
    parser.add_argument("--max-peak", type=peak_option, default=None, metavar="E",
                        help="largest peak fitted, e- (G15: below blooming; default: all "
                             "unflagged stars)")
    parser.add_argument("--unweighted", action="store_true",
                        help="ignore the *_err columns (errors from the scatter)")
    parser.add_argument("--plot", metavar="FILE", help="write size against peak (PNG, PDF)")
    parser.add_argument("--psf-plot", metavar="FILE",
                        help="with --psf: star-minus-model size, e1, e2 against magnitude, "
                             "static PSF beside P(F) (PNG, PDF)")
    output_options(parser)
    return parser


def _model_residual(stars, args, colour_fit, psf, slopes):
    """Slopes of the sizes measured minus the sizes of the flux-dependent PSF at each star's
    own flux, position and phase (zero-flux size, field variation and BF change together),
    on the stars of the measured fits (``slopes``), and the slopes the model predicts on
    them: the measured slope minus the predicted one is the residual's."""
    from ..measure.slopes import bf_slopes
    from ..measure.model_slopes import model_star_sizes, predicted_slopes, star_positions
    from ..measure.sources import model_flux

    if "flux_e" not in stars.colnames:
        msg = f"{args.stars} has no flux_e column: --psf needs each star's flux"
        raise BFPSFInputError(msg, args.stars)
    # P(F) takes the total flux; flux_e is an aperture flux (it misses the PSF's wings)
    x, y = star_positions(psf, stars)
    model = model_star_sizes(psf, model_flux(psf, stars["flux_e"]), x=x, y=y)
    residual = stars.copy()
    for key, column in (("x", "sigma_x"), ("y", "sigma_y"), ("iq", "iq"), ("e1", "e1"),
                        ("e2", "e2")):
        if column in residual.colnames:
            residual[column] = residual[column] - model[key]
    rows = {key: fit.rows for key, fit in slopes.items() if hasattr(fit, "rows")}
    # stars measured whose model has no size (an undersampled P(F) collapses onto the central
    # pixel at their phase, where the star itself did not): left out of both fits, and said
    lost = int(np.sum(slopes["iq"].rows & ~np.isfinite(model["iq"])))
    if lost:
        print(f"WARNING: {lost} of the {slopes['iq'].n_points} stars fitted have no model size "
              "at their flux and sub-pixel phase (P(F) is undersampled there: its adaptive "
              "moments collapse onto the central pixel): the prediction and the residual "
              "leave them out", file=sys.stderr)
    # the measured fit's stars and weights (its scatter beyond the errors, if any)
    options = {"min_peak_e": args.min_peak, "max_peak_e": args.max_peak,
               "use_errors": not args.unweighted, "rows": rows,
               "scatter": {key: slopes[key].scatter for key in rows}}
    return (bf_slopes(residual, colour_fit=colour_fit, **options),
            predicted_slopes(psf, stars, sizes=model, **options))


def _summary(slopes):
    """The JSON keys of a set of slope fits (sizes with relative_percent; e1, e2 without)."""
    summary = {key: slopes[key].as_dict(short=True) for key in ("x", "y", "iq")}
    for key in ("e1", "e2"):
        if key in slopes:
            summary[key] = {name: slopes[key].as_dict()[name]
                            for name in ("slope", "slope_err", "intercept")}
    return summary


def _check_amplifiers(stars, psf, args):
    """A PSF fitted on several amplifiers predicts for their stars only (as ``photometry``
    refuses their images): a table measured elsewhere is refused in one line."""
    fitted = set(getattr(psf, "amplifier_shifts", None) or {})
    if not fitted:
        return
    column = stars["amplifier"] if "amplifier" in stars.colnames else [""]
    # a single-HDU image's '' reads back from ECSV masked
    names = {str(name) for name in np.ma.filled(np.ma.asarray(column), "")}
    foreign = sorted(names - fitted)
    if foreign:
        what = ", ".join(repr(name) if name else "a single-HDU image" for name in foreign)
        msg = (f"{args.stars} holds stars of {what}, but {args.psf} was fitted on amplifiers "
               f"{', '.join(sorted(fitted))}: measure the images the PSF was fitted on")
        raise BFPSFInputError(msg, args.stars)


def run(args):
    from ..measure.colour import correct_size_colour
    from ..measure.slopes import bf_slopes

    check_outputs([args.json, args.plot, args.psf_plot], args.overwrite,
                  inputs=input_files(args.stars, args.psf))
    if args.psf_plot and not args.psf:
        msg = "--psf-plot needs --psf PSF.fits"
        raise BFPSFInputError(msg, args.psf_plot)
    stars = read_table(args.stars, "star table", format="ascii.ecsv",
                       numeric=("peak_e", "flux", "sigma_x", "sigma_y", "e1", "e2", "x", "y",
                                "flags", *([args.colour] if args.colour else [])))
    colour_fit = None
    if args.colour:
        stars, colour_fit = correct_size_colour(stars, args.colour,
                                                max_peak_e=args.colour_max_peak)
    with about(args.stars):
        slopes = bf_slopes(stars, min_peak_e=args.min_peak, max_peak_e=args.max_peak,
                           use_errors=not args.unweighted, colour_fit=colour_fit)
    summary = _summary(slopes)
    summary["n_stars"] = int(slopes["n_stars"])
    # what the fits beside the slope warned of (over the field, over the sub-pixel phase)
    summary["beside"] = slopes.get("beside", {})
    residual = prediction = psf = None
    if args.psf is not None:
        from ..model.psf import FluxDependentPSF

        psf = FluxDependentPSF.read(args.psf)
        _check_amplifiers(stars, psf, args)
        residual, prediction = _model_residual(stars, args, colour_fit, psf, slopes)
        summary["model_residual"] = _summary(residual)
        for key in ("x", "y", "iq", "e1", "e2"):
            if key not in summary["model_residual"]:
                continue
            entry = summary["model_residual"][key]
            if key in ("x", "y", "iq"):
                # the residual's intercept is star minus model at zero flux (about 0): the
                # residual slope in percent of the stars' own size
                entry["relative_percent"] = 100.0 * entry["slope"] / summary[key]["intercept"]
                # and in percent of the measured (raw) slope, the README's figure of merit (a
                # new user read relative_percent -10.2 as the residual; it was -512 % of raw)
                raw = summary[key]["slope"]
                entry["percent_of_raw"] = 100.0 * entry["slope"] / raw if raw else np.nan
            # the residual's error with the calibration's: what a pull should divide by
            # (a PSF without calibration samples, e.g. a static ePSF, has none: NaN)
            calibration_err = prediction[key]["slope_err"]
            entry["slope_err_total"] = float(np.hypot(entry["slope_err"], calibration_err)
                                             if np.isfinite(calibration_err)
                                             else entry["slope_err"])
            entry["pull"] = entry["slope"] / entry["slope_err_total"]
        summary["prediction"] = prediction
        summary["empirical"] = None if psf.empirical is None else psf.empirical.to_dict()
    summary["details"] = {
        "units": {"slope": "pixel per 100 ke- of peak", "intercept": "pixel",
                  "relative_percent": "percent of the intercept per 100 ke- of peak",
                  "range_percent": "percent of the intercept over the fitted peak range",
                  "e1, e2 slope": "per 100 ke- of peak"},
        **{key: slopes[key].as_dict() for key in ("x", "y", "iq", "e1", "e2") if key in slopes},
        "colour_fit": None if colour_fit is None else colour_fit.as_dict(),
        "stars": str(args.stars),
    }
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    if args.plot:
        from ..plotting.moments import plot_size_vs_peak

        figure = plot_size_vs_peak(stars, slopes, max_peak_e=args.max_peak)
        save_figure(figure, args.plot, overwrite=args.overwrite, dpi=120)
    if args.psf_plot:
        from ..plotting.psf_diagnostics import plot_psf_diagnostics

        save_figure(plot_psf_diagnostics(stars, psf), args.psf_plot, overwrite=args.overwrite,
                    dpi=100)
    for key, label in (("x", "sigma_x"), ("y", "sigma_y"), ("iq", "IQ")):
        fit = slopes[key]
        if residual is not None:
            entry = summary["model_residual"][key]
            error = prediction[key]["slope_err"]
            # a gridded model's prediction holds the field's variation too (a new user read
            # -0.386 as the calibration's BF), and at undersampled stars' phases the phase's
            # pull on the slope against peak, as the measured slope does (a new user read
            # +0.0165 as the model's BF, 0.030 by its twins)
            gridded = len(psf.field_nodes[0]) * len(psf.field_nodes[1]) > 1
            print(f"{label:8s} predicted by " + ("P(F, x, y) " if gridded else "P(F) ")
                  + ("(its BF and the field's variation) " if gridded else "")
                  + ("(at each star's phase: its BF and the phase's pull on the slope, as "
                     "the measured one's; read the residual) "
                     if slopes.get("beside", {}).get("phase") else "")
                  + f"{prediction[key]['slope']:+.5f} "
                  + (f"+- {error:.5f} (calibration)" if np.isfinite(error) else
                     "(the PSF carries no calibration samples: no calibration error)")
                  + "; residual after P(F) "
                  f"{entry['slope']:+.5f} +- {entry['slope_err_total']:.5f} pix/100ke- "
                  f"({_of_raw(entry['percent_of_raw'], fit)}; pull {entry['pull']:+.1f})")
        print(f"{label:8s} slope {fit.slope:+.5f} +- {fit.slope_err:.5f} pix/100ke-  "
              f"intercept {fit.intercept:.4f} pix  {fit.relative_percent:+.3f} %/100ke-")
    for key in ("e1", "e2"):
        if key in slopes:
            after = ""
            if residual is not None:
                entry = summary["model_residual"][key]
                after = (f"  residual after P(F) {entry['slope']:+.2e} +- "
                         f"{entry['slope_err_total']:.2e} (pull {entry['pull']:+.1f})")
            print(f"{key:8s} slope {slopes[key].slope:+.2e} +- {slopes[key].slope_err:.2e} "
                  f"/100ke-  intercept {slopes[key].intercept:+.5f}{after}")
    # the stars each slope fit left out beyond 5 robust sigma (blends, or an effect the
    # model lacks: a new user's smear growing with the column left 7 of 180 out, unsaid)
    clipped = {key: fit.n_clipped for key, fit in slopes.items()
               if getattr(fit, "n_clipped", 0)}
    print(f"{slopes['n_stars']} stars fitted"
          + (f", colour-corrected with {args.colour} ({colour_fit.n_stars} faint stars)"
             if colour_fit else "")
          + ("; left out beyond 5 robust sigma of the line: "
             + ", ".join(f"{count} in {key}" for key, count in clipped.items()) if clipped
             else ""))
    if args.psf:
        warn_unconverged(psf, args.psf)
    return 0


def _of_raw(percent, fit):
    """The residual in percent of the measured slope, or why not: a measured slope within 2
    of its errors of zero (a BF-free twin's) makes any percentage of it meaningless (a new
    user read +18106 %)."""
    if not np.isfinite(percent) or abs(fit.slope) < 2 * fit.slope_err:
        return (f"the measured slope {fit.slope:+.5f} +- {fit.slope_err:.5f} is within 2 of its "
                "errors of zero: no percentage of it")
    return f"{percent:+.0f} % of the measured slope"
