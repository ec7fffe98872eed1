"""``bfpsf photometry IMAGE... --psf PSF.fits -o PHOT.ecsv``: PSF photometry with P(F).

Parse, read the PSF product and the images (ADU -> e- with the product's gain), call
`bfpsf.measure.photometry.psf_photometry` (photutils PSFPhotometry with the flux-dependent
PSF), write the table (fluxes in e-) and the JSON summary.
"""

import sys

import numpy as np

from ..files import about, check_outputs, input_files
from ..outputs import write_json, write_table
from ..measure.photometry import RESIDUAL_PASSES
from ..measure.sources import SourceFlag
from ..moments.result import MomentsFlag
from . import (image_arguments, non_negative_float, non_negative_int, output_options,
               positive_float, positive_int, star_image_options)
from ._files import one_fit_per_star, place_stars, read_image, warn_unconverged
from .psf import FLUX_CORRECTION_TOLERANCE


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "photometry", help="PSF photometry with the flux-dependent PSF P(F)",
        description="Detect stars and fit each with P(F) = P0 + F R[P0] at its own flux "
                    "(photutils PSFPhotometry, grouped fits for close stars). Columns x_fit, "
                    "y_fit, flux_fit, flux_err (e-), flags, plus photutils' own.")
    image_arguments(parser, "fit")
    parser.add_argument("--calib", metavar="CALIB.fits",
                        help="per-amplifier gains and boundary shifts (needed for images of "
                             "several amplifiers; default: the PSF product's), and the "
                             "linearity correction of a calibration refined by "
                             "'bfpsf diagnose --output-calib'")
    parser.add_argument("--psf", required=True, metavar="PSF.fits",
                        help="PSF product written by 'bfpsf psf'")
    parser.add_argument("-o", "--output", required=True, metavar="PHOT.ecsv",
                        help="photometry table to write (ECSV)")
    parser.add_argument("--gain", type=positive_float, default=None,
                        help="e-/ADU (default: the gain stored in the PSF product)")
    parser.add_argument("--read-noise", type=non_negative_float, default=None, metavar="E",
                        help="read noise, e- rms, for the pixel errors (with --background 0 "
                             "on sky-subtracted images: include the sky's noise; default the "
                             "calibration's with --calib where its PTC determined it, else "
                             "measured on the image's sky)")
    star_image_options(parser, saturation="stars with a pixel at or above it in the fit box "
                                          "are flagged (column saturated and flag value 8 in "
                                          "source_flags)")
    parser.add_argument("--fit-shape", type=positive_int, default=None,
                        help="fit box, pixels, odd (default about 3 FWHM)")
    parser.add_argument("--static", action="store_true",
                        help="fit the static P0 (no BF term), for comparison (total fluxes "
                             "too: the product's correction for the light beyond P0)")
    parser.add_argument("--no-cross-terms", action="store_true",
                        help="skip the refit of blended stars without the BF of their charge "
                             "on each other")
    parser.add_argument("--residual-passes", type=non_negative_int, default=RESIDUAL_PASSES,
                        metavar="N",
                        help="searches of the fit's residual for stars detection missed (a "
                             "companion on a bright star's wing, faint stars of a crowded "
                             f"field; bit 4096 of source_flags); default {RESIDUAL_PASSES}, "
                             "0: none")
    output_options(parser)
    return parser


def _amplifier_model(psf, gain, one, amplifier, gain_option, static):
    """Gain (e-/ADU), the model fitted and the flux-dependent model of one amplifier: with
    its calibration ``one``, its gain (unless --gain), P0 with that amplifier's boundary
    shifts and the calibration's linearity correction (a calibration refined by 'bfpsf
    diagnose --output-calib'), and its EMPIRICAL term where the product holds none (the
    product's was fitted with its P0, at the amplitude its stars' pixels gave:
    `bfpsf.model.psf_fit_empirical`); else the PSF product's, with the amplifier's own
    shifts where the product has them (`BFPSFModel.for_amplifier`). With --static the model
    fitted is the static P0."""
    from ..interop.photutils import static_image_psf
    from ..measure.prepare import linearity_of
    from ..model.empirical import empirical_of

    model = psf.for_amplifier(amplifier.name)
    if one is not None:
        gain = one.gain if gain_option is None else float(gain_option)
        if one.shifts is not None and one.shifts is not psf.shifts:
            model = psf.with_shifts(one.shifts)
        model = model.copy()  # the calibration's linearity correction, undone on input
        model.linearity_c_per_1e5 = linearity_of(one)
        term = empirical_of(one)
        if term is not None and psf.empirical is None:
            model = model.with_empirical_term(term)
    return float(gain), (static_image_psf(model) if static else model), model


def _warn_beyond_field(psf, table, path, psf_path, tolerance=2.0):
    """Say how many stars lie beyond the field a PSF that varies over it was fitted on (its
    nodes, or the positions its EMPIRICAL term was learned on): it is extrapolated there (a
    new user's 2 x 2 grid fitted on 320^2 pixels, used on 640^2: two thirds of the stars
    beyond it, about 7 mmag worse, without a word)."""
    if not psf.varies_over_field or len(table) == 0:
        return
    beyond = np.zeros(len(table), dtype=bool)
    spans = []
    for column, nodes in zip(("x_fit", "y_fit"), psf.field_nodes):
        if len(nodes) < 2:  # no dependence along this axis
            continue
        values = np.asarray(table[column], dtype=float)
        beyond |= (values < nodes.min() - tolerance) | (values > nodes.max() + tolerance)
        spans.append(f"{column[0]} {nodes.min():.0f} to {nodes.max():.0f}")
    if beyond.any():
        print(f"WARNING: {path}: {beyond.sum()} of {len(table)} stars lie beyond the field "
              f"{psf_path} was fitted on ({', '.join(spans)}): its field dependence is "
              "extrapolated there", file=sys.stderr)


def _read_noise(args, calibration):
    """``--read-noise``, else the amplifier's calibrated read noise (``--calib``) where its PTC
    determined it (`Calibration.read_noise_determined`: beyond 2 errors, as ``calibrate``
    warns) and None where it did not: from the image's sky
    (`bfpsf.measure.read_noise.image_read_noise`; new users' calibrations had 0.43 +- 48.7
    and 10.5 +- 6.8 e-, against 5 and 4.5), as without a calibration. The Python path
    (`psf_photometry(..., read_noise_e=...)`) gives the same numbers."""
    if args.read_noise is not None:
        return float(args.read_noise)
    if calibration is None or not calibration.read_noise_determined:
        return None
    return float(calibration.noise_e)


def run(args):
    from astropy.table import vstack

    from ..calibration.detector import calibration_of_amplifier, read_calibration
    from ..errors import BFPSFInputError, BFPSFValueError
    from ..interop.photutils import default_fit_shape, psf_fwhm
    from ..io.amplifiers import shared_sides
    from ..io.saturation import (beyond_flats, describe_beyond_flats, saturated_stars,
                                 saturation_e)
    from ..measure.photometry import psf_photometry
    from ..model.psf import FluxDependentPSF

    check_outputs([args.output, args.json], args.overwrite,
                  inputs=input_files(args.images, args.psf, args.calib))
    psf = FluxDependentPSF.read(args.psf)
    if psf.flux_unit != "electron":
        psf = psf.with_flux_unit("electron")  # the images are converted to e- below
    gain = psf.gain if args.gain is None else float(args.gain)
    if gain is not None and not (np.isfinite(gain) and gain > 0):  # --gain is checked
        msg = (f"{args.psf}: the PSF product's GAIN = {gain!r} is not a gain (a positive "
               "number of e-/ADU); give --gain G")
        raise BFPSFInputError(msg, gain)
    calibration = read_calibration(args.calib) if args.calib else None
    if calibration is None and args.gain is None and len(psf.amplifier_shifts or {}) > 1:
        # the product's GAIN is a mean of its amplifiers' (a new user's +169 mmag on one)
        msg = (f"{args.psf} was fitted on amplifiers {', '.join(sorted(psf.amplifier_shifts))}, "
               "each with its own gain, which the product does not keep: give --calib "
               "CALIB.fits (or --gain G)")
        raise BFPSFInputError(msg, args.psf)
    tables, per_image, beyond_tops = [], [], []
    for path in args.images:
        amplifiers, _ = read_image(path, args.amp)
        if len(amplifiers) > 1 and calibration is None:
            msg = (f"{path} has {len(amplifiers)} amplifiers: give --calib CALIB.fits for the "
                   "gain and boundary shifts of each")
            raise BFPSFInputError(msg, str(path))
        if gain is None and calibration is None:
            msg = f"{args.psf} records no gain: give --gain G (e-/ADU of the images)"
            raise BFPSFInputError(msg, args.psf)
        sides = shared_sides([amplifier.layout for amplifier in amplifiers])
        for amplifier in amplifiers:
            one = None if calibration is None else calibration_of_amplifier(
                calibration, amplifier.name, str(path), len(amplifiers))
            try:
                amp_gain, model, bf_model = _amplifier_model(psf, gain, one, amplifier,
                                                             args.gain, args.static)
            except BFPSFValueError as error:  # an image of another camera than the PSF's
                msg = f"{path} with {args.psf}: {error}"
                raise BFPSFInputError(msg, str(path)) from None
            read_noise = _read_noise(args, one)
            level = saturation_e(amplifier, amp_gain, args.saturation, one)
            # the image preparation (linearity, sky) is psf_photometry's, as in Python
            with about(path):
                table = psf_photometry(amplifier.data * amp_gain, model,
                                       linearity_c_per_1e5=bf_model.linearity_c_per_1e5,
                                       read_noise_e=read_noise, fit_shape=args.fit_shape,
                                       background_e=(None if args.background is None
                                                     else args.background * amp_gain),
                                       sky_degree=args.sky_degree,
                                       detection_threshold=args.threshold,
                                       cross_terms=not args.no_cross_terms,
                                       residual_passes=args.residual_passes,
                                       saturation_e=level,
                                       # --static too: total fluxes, with the product's
                                       # correction for the light beyond P0's support, and
                                       # its wings taken out of the sky as P(F)'s are
                                       wings=bf_model)
            table["saturated"] = saturated_stars(
                amplifier.data * amp_gain, level, table["x_fit"], table["y_fit"],
                args.fit_shape or default_fit_shape(model))
            if "source_flags" in table.colnames:  # as `bfpsf measure` flags them
                table["source_flags"] |= np.where(table["saturated"], SourceFlag.SATURATED, 0)
            _warn_beyond_field(psf, table, path, args.psf)
            # the stars whose brightest pixel lies above the flats' highest level
            beyond, top = beyond_flats(
                bf_model, np.asarray(table["flux_fit"], float)
                / bf_model.flux_correction_at(table["x_fit"], table["y_fit"]),
                table["sky_e"], one, x=np.asarray(table["x_fit"], float),
                y=np.asarray(table["y_fit"], float))
            beyond_tops += [] if top is None else [top]
            margin = (args.fit_shape or 2 * psf.half_size + 1) / 2
            place_stars(table, amplifier, sides, margin, x="x_fit", y="y_fit")
            if "x_init" in table.colnames and amplifier.layout.detsec is not None:
                table["x_init"] = table["x_init"] + amplifier.layout.detsec.x.start
                table["y_init"] = table["y_init"] + amplifier.layout.detsec.y.start
            table.add_column(str(path), name="image", index=0)
            tables.append(table)
            per_image.append({"image": str(path), "amplifier": amplifier.name,
                              "gain": amp_gain, "read_noise_e": table.meta["read_noise_e"],
                              "read_noise_source": (
                                  "--read-noise" if args.read_noise is not None else
                                  "image" if read_noise is None else "calibration"),
                              "sky_scatter": table.meta["sky_scatter"],
                              "linearity_c_per_1e5": bf_model.linearity_c_per_1e5,
                              "n_stars": len(table),
                              "n_flagged": int(np.sum((table["flags"] != 0)
                                                      | table["saturated"])),
                              "saturation_e": level,
                              "n_saturated": int(np.sum(table["saturated"])),
                              "n_amp_boundary": int(np.sum(table["amp_boundary"])),
                              "background_e": table.meta["background_e"],
                              "sky": table.meta["sky"],
                              "flux_correction": table.meta["flux_correction"],
                              "flux_correction_err": table.meta["flux_correction_err"],
                              "n_blended": int(np.sum(table["group_size"] > 1)),
                              "n_unlike_psf": _unlike(table),
                              "n_beyond_flats": beyond,
                              "cross_term_refits": table.meta["cross_term_refits"],
                              "residual_sources": table.meta["residual_sources"],
                              "line_pixels": table.meta["line_pixels"],
                              "n_on_line": _flagged(table, SourceFlag.ON_LINE),
                              "cosmic_ray_pixels": table.meta["cosmic_ray_pixels"],
                              "n_cosmic_ray": _flagged(table, SourceFlag.COSMIC_RAY)})
    result = vstack(tables, metadata_conflicts="silent") if len(tables) > 1 else tables[0]
    # a star near a shared side is fitted on both amplifiers: the fit from its own is kept
    result, n_twice = one_fit_per_star(result, 2 * psf_fwhm(psf), x="x_fit", y="y_fit")
    # the product's (one for every image; vstack would join the images' lists)
    result.meta.update({"psf": str(args.psf), "gain": gain, "flux_unit": "electron",
                        "static_psf": bool(args.static),
                        "flux_correction_slope": tables[0].meta["flux_correction_slope"]})
    # the EMPIRICAL term the model applied (psf_photometry's meta; None for --static)
    result.meta["empirical"] = tables[0].meta.get("empirical")
    result["flux_fit"].unit = "electron"
    result["flux_err"].unit = "electron"
    write_table(result, args.output, overwrite=args.overwrite)
    warn_unconverged(psf, args.psf)
    summary = {"output": str(args.output), "psf": str(args.psf), "gain": gain,
               "static_psf": bool(args.static), "n_stars": len(result),
               "n_flagged": int(np.sum((result["flags"] != 0) | result["saturated"])),
               "n_saturated": int(np.sum(result["saturated"])), "images": per_image,
               "n_fitted_twice": n_twice,
               "n_unlike_psf": _unlike(result),
               "n_on_line": _flagged(result, SourceFlag.ON_LINE),
               "n_cosmic_ray": _flagged(result, SourceFlag.COSMIC_RAY),
               # detection's adaptive moments collapsed onto one pixel (`measure`'s warning)
               "n_undersampled": _flagged(result, MomentsFlag.UNDERSAMPLED),
               "empirical": result.meta["empirical"],
               "flux_correction_slope": result.meta["flux_correction_slope"]}
    summary["residual_passes"] = args.residual_passes
    summary["n_in_residual"] = sum(entry["residual_sources"]["found"] for entry in per_image)
    summary["n_residual_lost"] = sum(entry["residual_sources"]["lost"] for entry in per_image)
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    n_blended = sum(entry["n_blended"] for entry in per_image)
    if n_twice:
        print(f"{n_twice} stars near a side two amplifiers share were fitted on both: the fit "
              "from the amplifier that holds the star's centre is kept, the other left out "
              "(n_fitted_twice)", file=sys.stderr)
    warning = describe_beyond_flats(sum(entry["n_beyond_flats"] for entry in per_image),
                                    len(result), min(beyond_tops, default=None))
    if warning:
        print(warning, file=sys.stderr)
    # with --static too, each star against the product's P(F) (psf_photometry's ``wings``)
    unlike = (f"{summary['n_unlike_psf']} unlike the PSF (two stars fitted as one, a galaxy, "
              "a cosmic ray); ")
    print(f"{len(result)} stars fitted in {len(args.images)} image(s) "
          f"({summary['n_flagged']} fits flagged by photutils or saturated, "
          f"{summary['n_saturated']} of them saturated; "
          f"{n_blended} fitted in a group with their neighbours; {unlike}"
          + (f"{summary['n_in_residual']} found in the fit's residual, missed by detection "
             f"({summary['n_residual_lost']} more found there left out: a failed fit, too "
             "faint or the same star twice); " if args.residual_passes else
             "no search of the fit's residual (--residual-passes 0); ")
          + (f"{sum(entry['line_pixels'] for entry in per_image)} pixels of trails or hot "
             f"columns left out, {summary['n_on_line']} stars beside them flagged on_line; "
             if any(entry["line_pixels"] for entry in per_image) else "")
          + (f"{summary['n_cosmic_ray']} stars hit by a cosmic ray, its pixels left out of "
             "their fit (flagged cosmic_ray); " if summary["n_cosmic_ray"] else "")
          + (f"{summary['n_undersampled']} undersampled, without adaptive moments (flagged "
             "undersampled, docs/limitations.md); "
             if summary["n_undersampled"] else "")
          + "detection's flags and unlike_psf in source_flags, bits in "
          f"bfpsf.measure.sources.SourceFlag.NAMES); wrote {args.output}")
    # the product's total-flux correction, a scale common to every flux: said where poorly
    # measured (a new user's scattered-light sky: 1.244 +- 0.128, every flux -200 mmag, and
    # photometry said nothing; bfpsf psf had)
    correction, correction_err = (tables[0].meta["flux_correction"],
                                  tables[0].meta["flux_correction_err"])
    if correction_err is not None and correction_err > FLUX_CORRECTION_TOLERANCE:
        print(f"WARNING: the PSF's total-flux correction is {correction:.4f} +- "
              f"{correction_err:.4f} (the light beyond its P0's support, as bfpsf psf measured "
              f"it): every flux carries a common scale error of +- "
              f"{2.5e3 * np.log10(1 + correction_err / correction):.1f} mmag (docs/"
              "limitations.md: a sky no low-order surface follows)", file=sys.stderr)
    # where the pixel errors' read noise came from, when nobody gave it (a new user read
    # 9.9 e- in the JSON, against its true 6, and found no word of it)
    measured = [entry["read_noise_e"] for entry in per_image
                if entry["read_noise_source"] == "image"]
    if measured:
        print(f"read noise measured on each image's sky: "
              f"{', '.join(f'{value:.2f}' for value in measured)} e- (neither --read-noise "
              "nor a calibration that determined it; read_noise_e in the JSON)")
    return 0


def _flagged(table, flag):
    """How many fitted stars have the `SourceFlag` (or detection's `MomentsFlag`) ``flag`` in
    ``source_flags``."""
    return int(np.sum((np.asarray(table["source_flags"]) & flag) > 0))


def _unlike(table):
    """How many fitted stars are flagged ``UNLIKE_PSF`` (`bfpsf.measure.psf_likeness`)."""
    return _flagged(table, SourceFlag.UNLIKE_PSF)
