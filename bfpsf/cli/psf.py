"""``bfpsf psf IMAGE... --calib CALIB.fits -o PSF.fits``: fit the flux-dependent PSF.

Parse, read the images (ADU -> e- with the calibration gain), detect isolated stars
(`bfpsf.measure.sources.measure_sources`), fit P0 from stars of all fluxes with the
brighter-fatter term of each removed (`bfpsf.model.psf_fit.fit_psf`; with ``--grid NX NY`` one
P0 per node of a grid over the image, `bfpsf.model.gridded.GriddedFluxDependentPSF`), write the
PSF product and the JSON summary. A calibration refined by ``bfpsf diagnose --output-calib``
brings its linearity correction, build-up and EMPIRICAL term (`bfpsf.model.empirical`): the
term enters every star's model during the fit and is stored in the product, which applies it
everywhere; the JSON's ``empirical`` (label ``'empirical'``) says so.
"""

import sys
from pathlib import Path

import numpy as np

from ..errors import BFPSFInputError
from ..files import about, check_outputs, input_files, refuse_duplicates
from ..outputs import write_json
from . import (finite_float, image_arguments, output_options, positive_int, stamp_size_option,
               star_image_options)
from ..measure.bf_agreement import disagreeing_axes
from ..measure.model_slopes import model_size_increments
from ..model.psf_fit import DEFAULT_SIZE
from ..model.psf_fit_stars import UNLIKE
from ..measure.read_noise import READ_NOISE_MISMATCH
from ..moments.result import MomentsFlag
from ..moments.shapes import MAG_PER_SIZE_ERROR, psf_shape
from ._files import read_image

#: Size offset of an image's stars from P0 above which (and above 3 sigma) `psf` warns that
#: the seeing differs between its images: 0.3 %, about 3 mmag of photometry bias there.
SEEING_TOLERANCE = 0.003
#: The stars' size against P(F) changing across an image by more than this (a fraction of
#: sigma, and 5 of its errors) is a PSF varying over the field that the model does not follow:
#: 1 %, about 11 mmag of photometry bias from one side to the other for sky-limited stars.
FIELD_TOLERANCE = 0.01
#: A grid node whose used stars weigh less than this (their summed bilinear weights) is said
#: to have too few: a new user's corner nodes of 6-9 came out broken, 15 fit (tests).
MIN_NODE_STARS = 10

#: Beyond this error the flux correction (the light beyond P0's support) is said to be poorly
#: measured: every flux carries it as a scale (a new user's crowded 128^2 amplifiers, 240
#: stars per exposure, with a sky plane per amplifier: 1.080 +- 0.038 against 1.008; with
#: the constant their images prefer, 1.015 +- 0.032).
FLUX_CORRECTION_TOLERANCE = 0.01
#: A total flux more than this many times the flux inside P0's support is a failed fit, not a
#: PSF: no product is written (the widest wings measured here, a Kolmogorov atmosphere with
#: struts and defocus, hold 5.5 % beyond a 25-pixel support).
MAX_FLUX_CORRECTION = 1.5


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "psf", help="fit the flux-dependent PSF P(F) = P0 + F R[P0] from stars of all fluxes",
        description="Fit the base PSF P0 (oversampled, pixel response included) from isolated "
                    "stars of all fluxes, each modelled as F P0 + F^2 R[P0] with R the G15 "
                    "charge redistribution of the calibration, and write the PSF product.")
    image_arguments(parser, "use")
    parser.add_argument("--calib", required=True, metavar="CALIB.fits",
                        help="calibration (boundary shifts, gain, read noise)")
    parser.add_argument("-o", "--output", required=True, metavar="PSF.fits",
                        help="PSF product to write (FITS)")
    parser.add_argument("--oversampling", type=positive_int, default=2,
                        help="oversampling of P0 (default 2; 4 needs several hundred stars)")
    parser.add_argument("--size", type=stamp_size_option, default=DEFAULT_SIZE,
                        help="support of P0 and star cutouts, pixels, odd (default 25)")
    star_image_options(parser, saturation="saturated stars are not used")
    parser.add_argument("--grid", type=positive_int, nargs=2, metavar=("NX", "NY"), default=None,
                        help="fit P0 on NX x NY nodes over the image (P(F, x, y), bilinear "
                             "between nodes, as photutils GriddedPSFModel); default one P0")
    parser.add_argument("--exposure-order", type=finite_float, default=None, metavar="T",
                        help="exposure order of the images in the night, for a refined "
                             "calibration's EMPIRICAL term that changes over the night: "
                             "0-based, in the order of the images given to bfpsf diagnose "
                             "(default the middle of the exposures it was learned on, with a "
                             "warning)")
    parser.add_argument("--max-iterations", type=positive_int, default=None,
                        help="iterations of the P0 fit after its last restart (default 40, "
                             "100 with --grid)")
    parser.add_argument("--no-bf", dest="include_bf", action="store_false",
                        help="fit a static ePSF (no BF term), for comparison")
    output_options(parser)
    return parser


def run(args):
    from ..calibration.detector import calibration_of_amplifier, read_calibration
    from ..io.amplifiers import detector_offset, near_shared_side, shared_sides
    from ..io.saturation import count_saturated_regions, describe_beyond_flats, saturation_e
    from ..measure.prepare import linearity_of, prepare_image
    from ..resources import check_psf_fit, resource_option
    from ..workflow import default_iterations, psf_from_images

    check_outputs([args.output, args.json], args.overwrite,
                  inputs=input_files(args.images, args.calib))
    refuse_duplicates(args.images, "image")
    if args.max_iterations is None:
        args.max_iterations = default_iterations(args.grid)
    check_psf_fit(0, args.size, args.oversampling, args.grid, args.max_iterations)
    calibration = read_calibration(args.calib)
    refinement = {}
    prepared, calibrations, exclude, saturation, per_image, frames = [], [], [], [], [], []
    for path in args.images:
        amplifiers, _ = read_image(path, args.amp)
        if args.grid is not None and len(amplifiers) > 1:
            # the grid spans one image's frame: on a detector each amplifier's (a new user's
            # four amplifiers shared nodes at 0-159, the detector's field unmodelled)
            msg = (f"{path}: --grid on {len(amplifiers)} amplifiers would put its nodes on "
                   "one amplifier's frame, not the detector's: fit each amplifier's grid "
                   "with --amp NAME")
            raise BFPSFInputError(msg, str(path))
        sides = shared_sides([amplifier.layout for amplifier in amplifiers])
        for amplifier in amplifiers:
            # each amplifier in electrons with its own gain
            one = calibration_of_amplifier(calibration, amplifier.name, str(path),
                                           len(amplifiers))
            if one.shifts is None and args.include_bf:
                msg = (f"{args.calib} has no boundary shifts"
                       f"{f' for amplifier {one.amplifier}' if one.amplifier else ''} "
                       "(its flats showed no brighter-fatter, or it was solved without "
                       "them): a static ePSF needs none (--no-bf)")
                raise BFPSFInputError(msg, args.calib)
            gain = float(one.gain)
            # a calibration refined by `bfpsf diagnose --output-calib`: its linearity
            # correction on input and its build-up (the shifts are already refined)
            refinement.update(one.refinement)
            with about(path):
                prepared.append(prepare_image(
                    amplifier.data, gain=gain, linearity_c_per_1e5=linearity_of(one),
                    background_e=None if args.background is None else args.background * gain,
                    sky_degree=args.sky_degree))
            calibrations.append(one)
            # saturated or beyond the turnoff (header SATURATE, --saturation, calibration):
            # left out of the P0 fit, and counted
            level = saturation_e(amplifier, gain, args.saturation, one)
            saturation.append(np.nan if level is None else level)
            # a star whose light falls on two amplifiers (two gains) is left out, and counted
            exclude.append(lambda xy, shape, side=sides[amplifier.name]: near_shared_side(
                xy[:, 0], xy[:, 1], shape, side, args.size / 2))
            # the amplifiers of one exposure share their stars' glow (the sky-and-wings fit)
            frames.append((str(path), *detector_offset(amplifier.layout)))
            per_image.append({"image": str(path), "amplifier": amplifier.name, "gain": gain,
                              "n_saturated": count_saturated_regions(prepared[-1].image_e,
                                                                     level)})
    # a FITS header is ASCII: other characters of the name stored escaped (\xe4, \u20ac)
    calibration_name = Path(args.calib).name.encode("ascii", "backslashreplace").decode()
    with (about(", ".join(map(str, args.images)), name_warnings=False),
          resource_option(f"--size {args.size}")):
        fitted = psf_from_images(prepared, calibrations, size=args.size,
                                 oversampling=args.oversampling, grid=args.grid,
                                 threshold=args.threshold, saturation_e=saturation,
                                 include_bf=args.include_bf, max_iterations=args.max_iterations,
                                 exclude=exclude, calibration_name=calibration_name,
                                 exposure=args.exposure_order,
                                 amplifiers=[entry["amplifier"] for entry in per_image],
                                 frames=frames)
    for entry, found in zip(per_image, fitted.images):
        entry.update(n_detected=found["n_detected"], n_isolated=found["n_isolated"],
                     n_amp_boundary=found["n_excluded"], background_e=found["background_e"],
                     sky_slope=found["sky_slope"], sky_method=found["sky_method"],
                     sky_degree=found["sky_degree"], line_pixels=found["line_pixels"],
                     cosmic_ray_pixels=found["cosmic_ray_pixels"],
                     sky_scatter=found["sky_scatter"],
                     **{key: found[key] for key in ("size_offset", "size_offset_err",
                                                    "n_sized", "seeing_bias_mmag",
                                                    "size_across")})
    result = fitted.fit
    psf = fitted.psf
    if psf.flux_correction > MAX_FLUX_CORRECTION:  # False for NaN (not measured)
        # a new user's vignetted sky held at a plane: P0 unconverged, 2.98 +- 0.63, written,
        # and every flux of photometry 1.2 mag off with a warning alone
        msg = (f"{', '.join(map(str, args.images))}: the light beyond P0's support came out "
               f"{psf.flux_correction - 1:.2f} +- {psf.flux_correction_err:.2f} of the light "
               f"inside it (P0 {'converged' if result.converged else 'NOT converged'}): the "
               "sky is not the fitted surface (give --sky-degree auto, or subtract the sky "
               f"and give --background 0) or the stars are not one PSF; {args.output} not "
               "written")
        raise BFPSFInputError(msg, psf.flux_correction)
    gain = float(psf.gain)  # of the images the stars came from, weighted by their stars
    psf.write(args.output, meta={"NSTARS": int(np.sum(result.stars["flags"] == 0)),
                                 "BFTERM": bool(args.include_bf)},
              overwrite=args.overwrite)
    from ..interop.photutils import describe_outlying_nodes, outlying_nodes, psf_fwhm

    used = result.stars["flags"] == 0
    summary = {"output": str(args.output), "calibration": str(args.calib), "gain": gain,
               "oversampling": int(args.oversampling), "size": int(args.size),
               "include_bf": bool(args.include_bf), "n_stars": int(len(result.stars)),
               "n_used": int(np.sum(used)), "iterations": int(result.iterations),
               "n_unlike": int(np.sum(np.asarray(result.stars["flags"]) & UNLIKE > 0)),
               "n_masked": int(np.sum(np.asarray(result.stars["masked"])[used] > 0)),
               "n_saturated": sum(entry["n_saturated"] for entry in per_image),
               "converged": bool(result.converged),
               "fwhm_pixels": psf_fwhm(psf),
               "flux_range_e": [float(np.min(result.stars["flux_fit"][used])),
                                float(np.max(result.stars["flux_fit"][used]))]
               if np.any(used) else None,
               "images": per_image,
               "flux_correction": psf.flux_correction,
               "flux_correction_err": psf.flux_correction_err,
               "flux_correction_slope": list(psf.flux_correction_slope),
               "flux_correction_slope_err": list(psf.flux_correction_slope_err),
               "flux_correction_centre": list(psf.flux_correction_centre),
               "refinement_applied": sorted(refinement.get("applied", {})),
               # the EMPIRICAL term (issue 22): it describes the stars, it explains nothing
               "empirical": None if psf.empirical is None else psf.empirical.to_dict()}
    if args.grid is not None:
        outliers, median_fwhm = outlying_nodes(psf)
        summary["grid"] = {"nx": int(args.grid[0]), "ny": int(args.grid[1]),
                           "x_nodes": psf.x_nodes.tolist(), "y_nodes": psf.y_nodes.tolist(),
                           "fwhm_pixels": [psf_fwhm(psf, x, y) for y in psf.y_nodes
                                           for x in psf.x_nodes],
                           # each node's share of the used stars (their bilinear weights)
                           "star_weights": node_star_weights(psf, result.stars[used]).tolist(),
                           "outlying_nodes": [{"x": x, "y": y, "fwhm_pixels": fwhm,
                                               "dip": dip}
                                              for x, y, fwhm, dip in outliers]}
    # P0, the PSF of faint sources, and the calibration's error of the BF amplitude: the stars
    # weigh in near their weighted flux, and P0 carries the error of the BF change below it
    where = _summary_position(psf) if args.include_bf else {}
    p0_error = psf.shape_error(1.0, **where) if args.include_bf else None
    reference = psf.star_flux_e
    summary["p0_calibration_error"] = (None if p0_error is None
                                       else dict(p0_error, reference_flux_e=reference))
    beyond = _beyond_flats(psf, result.stars[used], per_image, calibrations)
    summary["n_beyond_flats"] = beyond[0]
    change = _bf_size_change(psf, bool(where)) if args.include_bf else None
    if change is not None:
        summary["bf_size_change_px"] = change
    # the stars' own BF against the calibration's (a new user's small flats gave 6 times it)
    agreement = fitted.bf_agreement() if args.include_bf else None
    summary["bf_agreement"] = agreement
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    shrinking = [axis.upper() for axis in "xy" if change is not None and change[axis] < 0]
    if shrinking:
        print(f"WARNING: P(F) makes stars shrink with flux along {' and '.join(shrinking)} "
              f"(sigma_x {change['x']:+.4f}, sigma_y {change['y']:+.4f} px at "
              f"{change['flux_e']:.3g} e-, the stars' flux): brighter-fatter broadens them; "
              f"the calibration's boundary shifts have the unphysical sign (too few flats: "
              f"`bfpsf calibrate` says why; calibrate with more flat pairs and levels)",
              file=sys.stderr)
    for axis in disagreeing_axes(agreement):
        entry = agreement[axis]
        print(f"WARNING: along {axis.upper()} the stars grow with flux "
              f"{entry['ratio']:.2f} +- {entry['ratio_err']:.2f} times as much as the "
              f"calibration predicts (sigma_{axis} {entry['measured_px']:+.4f} against "
              f"{entry['predicted_px']:+.4f} px from faint to the brightest star): its boundary "
              "shifts do not describe these stars (flats too few, or of another sensor or "
              "setting) or the stars show an effect it lacks; `bfpsf slope --psf` measures "
              "what is left, `bfpsf diagnose --output-calib` refines the calibration from "
              "these images", file=sys.stderr)
    warning = describe_beyond_flats(*beyond)
    if warning:
        print(warning, file=sys.stderr)
    if result.diverged:  # flagged in the product (CONVERGD) and the JSON too
        # more iterations do not help (a new user read "raise --max-iterations" after 11 of
        # 80, and "last change 15 of the peak")
        print(f"WARNING: P0 fit diverged after {result.iterations} iterations and kept its "
              "iterate of least chi-square: too few stars for this model (fewer --grid "
              "nodes, a smaller --size) or stars it cannot describe", file=sys.stderr)
    elif not result.converged:
        # after a restart without the stars left out the count starts again (a new user read
        # "did not converge in 80 iterations" beside --max-iterations' default of 40)
        again = (f" after it started again without the stars it left out ({result.iterations} "
                 "in all)" if result.iterations > args.max_iterations else "")
        print(f"WARNING: P0 did not converge in {args.max_iterations} iterations{again} "
              f"(last change {100 * result.changes[-1]:.2g} % of the peak): raise "
              "--max-iterations or check the stars", file=sys.stderr)
    if args.grid is not None:
        weights = summary["grid"]["star_weights"]
        few = int(np.sum(np.asarray(weights) < MIN_NODE_STARS))
        if outliers or few:
            # a node fitted from too few stars (a new user's 10.2 px against 4.2-4.7, unsaid
            # until photometry blamed the image for a 31 px fit box; another's corner nodes
            # of 6-9 stars dipped to -1.0 of their peak, photometry 0.3-0.5 mag off there)
            what = (describe_outlying_nodes(outliers, median_fwhm) + "; " if outliers
                    else "")
            listed = ", ".join(f"{weight:.1f}" for weight in weights)
            print(f"WARNING: {what}{few} of {len(weights)} grid nodes have less than "
                  f"{MIN_NODE_STARS} stars' weight (the used stars weigh {listed} at the nodes, "
                  f"row by row from y = {psf.y_nodes[0]:.0f}, x fastest; about 30 each fit "
                  f"well): too few stars for --grid {args.grid[0]} {args.grid[1]}: use fewer "
                  "nodes or more images", file=sys.stderr)
    # each image against the others: their median offset is the estimator's (faint stars'
    # noise; +0.17 % on a new user's constant-seeing night), not a seeing
    sized = [entry for entry in per_image if np.isfinite(entry["size_offset"])]
    common = float(np.median([entry["size_offset"] for entry in sized])) if len(sized) > 1 \
        else np.nan
    # the median's own error (1.25 sigma / sqrt(n)) too: with 8-9 stars per image, four
    # images of one seeing gave -1.02 +- 0.30 % against their median, +- 0.40 with it
    common_err = 1.2533 * np.sqrt(np.mean([entry["size_offset_err"] ** 2 for entry in sized])
                                  / len(sized)) if len(sized) > 1 else np.nan
    for entry in per_image:
        offset = entry["size_offset"] - common
        error = float(np.hypot(entry["size_offset_err"], common_err))
        if abs(offset) > max(3 * error, SEEING_TOLERANCE):  # False for NaN (too few stars)
            name = entry["image"] + (f" [{entry['amplifier']}]" if entry["amplifier"] else "")
            print(f"WARNING: {name}: its stars are {100 * offset:+.2f} +- {100 * error:.2f} % "
                  f"{'larger' if offset > 0 else 'smaller'} against P0 than the other images' "
                  f"median: its seeing differs from theirs (PSF photometry of its sky-limited "
                  f"stars up to {abs(1e3 * MAG_PER_SIZE_ERROR * offset):.1f} mmag too "
                  f"{'faint' if offset > 0 else 'bright'}, less for bright stars); fit each "
                  "exposure's PSF on its own images, or, if its stars lie in another part of "
                  "the field than the others' (an amplifier), the PSF varies over the field: "
                  "--grid", file=sys.stderr)
    _warn_field_variation(per_image, args.grid)
    for entry in per_image:  # the image a joint fit's sky-and-wings misfit comes from
        if (entry.get("sky_scatter") or 0.0) > READ_NOISE_MISMATCH:
            name = entry["image"] + (f" [{entry['amplifier']}]" if entry["amplifier"] else "")
            print(f"WARNING: {name}: its sky pixels scatter {entry['sky_scatter']:.2f} times "
                  "their pixel-to-pixel variance about its fitted sky: its sky is not the "
                  "surface fitted (a seam, structure on the scale of the stars) and the light "
                  "beyond P0's support, one for all the images, carries its misfit; subtract "
                  "its sky and give --background 0, or fit the PSF without it", file=sys.stderr)
    if psf.flux_correction_err > FLUX_CORRECTION_TOLERANCE:  # False for NaN (not measured)
        print(f"WARNING: the light beyond P0's support is poorly measured on these images: "
              f"total flux {psf.flux_correction:.4f} +- {psf.flux_correction_err:.4f} times the "
              "flux in the support, a scale error of every flux (the sky's noise or misfit "
              "against the wings of these stars: too few bright stars, too few pixels "
              "between them (a crowded field, small amplifiers), or a sky no low-order "
              "surface follows, such as scattered light or vignetting); fit the PSF on more "
              "images or brighter stars, or subtract such a sky and give --background 0",
              file=sys.stderr)
    if p0_error is not None:
        print(f"P0 (the PSF of sources far fainter than the stars) carries the calibration's "
              f"error of the BF amplitude: sigma +- {p0_error['sigma_percent']:.2f} %, e1 +- "
              f"{p0_error['e1']:.4f}, e2 +- {p0_error['e2']:.4f} (the stars weigh in at "
              f"{reference:.3g} e-; `shape(flux)` nearer that flux carries less)"
              + (" at sub-pixel phase (0.5, 0.5)" if where else ""))
    n_detected = sum(entry["n_detected"] for entry in per_image)
    # (a new user's 52 stars hit by cosmic rays were "blended, near an edge or with bad
    # pixels" alone)
    rays = any(entry.get("cosmic_ray_pixels") for entry in per_image)
    others = ("; the others blended, near an edge, with bad pixels"
              f"{' or hit by a cosmic ray' if rays else ''}"
              if n_detected > summary["n_stars"] else "")
    unlike = (f"; {summary['n_unlike']} left out as unlike the other stars (unresolved "
              "blends; bit 16 of the P0 fit's star flags)" if summary["n_unlike"] else "")
    # the rest: cut by an edge, bad pixels, a flux or position fit that failed (a new
    # user's "170 of 244 ... 73 left out" did not add up)
    failed = summary["n_stars"] - summary["n_used"] - summary["n_unlike"]
    unlike += (f"; {failed} not used: cut by an edge, bad pixels or a failed fit (bits 1-8)"
               if failed else "")
    unlike += (f"; {summary['n_masked']} with a fainter companion's pixels masked"
               if summary["n_masked"] else "")
    print(f"P0 from {summary['n_used']} of {summary['n_stars']} isolated stars ({n_detected} "
          f"sources detected{others}{unlike}) in "
          f"{len(args.images)} image(s), {result.iterations} iterations "
          + ("in all, restarts without the stars left out included " if
             result.iterations > args.max_iterations else "")
          + f"({'converged' if result.converged else 'NOT converged'}); "
          f"{summary['n_saturated']} saturated stars left out; "
          f"total flux {psf.flux_correction:.4f}"
          f"{f' +- {psf.flux_correction_err:.4f}' if np.isfinite(psf.flux_correction_err) else ''}"
          f" times the flux in the {args.size}-pixel support{_across(psf)}; {_skies(per_image)}; "
          f"{_empirical(psf.empirical)}wrote {args.output}")
    return 0


def _empirical(term):
    """What the product says of its EMPIRICAL term: applied, at the amplitude the stars'
    pixels gave the coefficients learned from their sizes (`bfpsf.model.psf_fit`)."""
    if term is None:
        return ""
    return (f"EMPIRICAL term applied, at {term.amplitude:.2f} times the amplitude the stars' "
            "sizes gave it (their pixels'); ")


def _across(psf):
    """A grid's flux correction from one edge of the image to the other along x and y."""
    if not any(psf.flux_correction_slope):
        return ""
    length = 2 * np.array(psf.flux_correction_centre) + 1.0
    change = np.array(psf.flux_correction_slope) * length
    error = np.array(psf.flux_correction_slope_err) * length
    return (f" at the centre, {change[0]:+.4f} +- {error[0]:.4f} from left to right and "
            f"{change[1]:+.4f} +- {error[1]:.4f} from bottom to top")


def _skies(per_image):
    """The skies fitted with the stars' wings at each image's centre, e- and ADU (each image
    with its own gain; a new user found them only in the JSON)."""
    def span(values):
        low, high = float(np.min(values)), float(np.max(values))
        return f"{low:.1f}" if high - low < 0.05 else f"{low:.1f} to {high:.1f}"

    electrons = np.array([entry["background_e"] for entry in per_image], dtype=float)
    adu = electrons / np.array([entry["gain"] for entry in per_image], dtype=float)
    return (f"sky {span(electrons)} e- ({span(adu)} ADU) at the image "
            f"centre{'s' if len(per_image) > 1 else ''}")


def _summary_position(psf):
    """Where P0's shape is summarised (its calibration error, its BF size change): ``{}``,
    the reference position, or ``{x, y}`` half a pixel from it along both axes, with a
    warning, when P0 has no adaptive moments there (undersampled: on a pixel centre the weight
    collapses onto one pixel; a double Gaussian of FWHM 1.7 px printed 'sigma +- nan %')."""
    if not psf_shape(psf, 1.0).flags & MomentsFlag.UNDERSAMPLED:
        return {}
    x_ref, y_ref = psf.reference_position
    print("WARNING: P0 has no adaptive moments on a pixel centre (flag 'undersampled': the "
          "weight collapses onto the central pixel of a PSF this narrow): its shape depends on "
          "the sub-pixel phase, and its summaries below are taken at phase (0.5, 0.5), a pixel "
          "corner", file=sys.stderr)
    return {"x": x_ref + 0.5, "y": y_ref + 0.5}


def _bf_size_change(psf, corner=False):
    """The change of sigma_x and sigma_y (pixels) from P0 to a star of the stars' flux that
    P(F) predicts, with that flux (e-), or None without it. Negative: a BF of the unphysical
    sign (a new user's four 128^2 flat pairs gave shifts whose charged pixels grow, and P(F)
    then biased the photometry more than a static PSF, 19 against 7 mmag)."""
    flux = float(psf.star_flux_e)
    if not np.isfinite(flux) or flux <= 0:
        return None
    model = psf if psf.flux_unit == "electron" else psf.with_flux_unit("electron")
    phase = 0.5 if corner else None  # a pixel corner for an undersampled P0
    change = model_size_increments(model, [flux], n_grid=4, x_phase=phase, y_phase=phase)
    return {"x": float(change["x"][0]), "y": float(change["y"][0]), "flux_e": flux,
            **({"phase": [phase, phase]} if corner else {})}


def _beyond_flats(psf, stars, per_image, calibrations):
    """(stars above the flats' highest level, stars, the lowest such level) of the used
    stars, each on its image's sky (`bfpsf.io.saturation.beyond_flats`)."""
    from ..io.saturation import beyond_flats

    counts, tops = 0, []
    for index, (entry, calibration) in enumerate(zip(per_image, calibrations)):
        mine = np.asarray(stars["image"]) == index
        count, top = beyond_flats(psf, np.asarray(stars["flux_fit"], float)[mine],
                                  entry["background_e"], calibration,
                                  x=np.asarray(stars["x_fit"], float)[mine],
                                  y=np.asarray(stars["y_fit"], float)[mine])
        counts += count
        tops += [] if top is None else [top]
    return counts, len(stars), min(tops) if tops else None


def node_star_weights(psf, stars):
    """The summed bilinear weight of ``stars`` (columns x_fit, y_fit) at each node of a
    gridded ``psf``, row-major [y, x]."""
    indices, weights = psf.weights(np.asarray(stars["x_fit"], float),
                                   np.asarray(stars["y_fit"], float))
    return np.bincount(indices.ravel(), weights=weights.ravel(),
                       minlength=psf.x_nodes.size * psf.y_nodes.size)


def _warn_field_variation(per_image, grid):
    """One warning for the images whose stars' size against P(F) changes across them beyond
    `FIELD_TOLERANCE` and 5 of its errors (`bfpsf.moments.shapes.size_across`)."""
    varying = [entry for entry in per_image if entry.get("size_across") and (
        entry["size_across"]["change"] > max(FIELD_TOLERANCE,
                                             5 * entry["size_across"]["change_err"]))]
    if not varying:
        return
    worst = max(varying, key=lambda entry: entry["size_across"]["change"])
    across = worst["size_across"]
    name = worst["image"] + (f" [{worst['amplifier']}]" if worst["amplifier"] else "")
    advice = (f"a finer grid than --grid {grid[0]} {grid[1]}" if grid is not None
              else "a grid (--grid NX NY, about 30 stars per node)")
    along = ", ".join(f"{100 * across['along_' + axis]:+.1f} +- "
                      f"{100 * across['along_' + axis + '_err']:.1f} % along {axis}"
                      for axis in ("x", "y"))
    print(f"WARNING: on {len(varying)} of {len(per_image)} images the stars' size against "
          f"P(F) changes across the image, by up to {100 * across['change']:.1f} +- "
          f"{100 * across['change_err']:.1f} % of sigma ({name}: {along}, from one side to "
          f"the other): the PSF varies over the field and the model does not follow it "
          # the model is the field's mean: each edge is half the change off (a new user read
          # the whole change as a bias and measured a third of it on its faint stars)
          "(PSF photometry of sky-limited stars up to "
          f"+-{1e3 * MAG_PER_SIZE_ERROR * across['change'] / 2:.0f} mmag off at the field's "
          "edges, less for bright ones; `unlike_psf` flags on single stars); fit "
          f"{advice}", file=sys.stderr)
