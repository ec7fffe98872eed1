"""``bfpsf measure IMAGE... -o STARS.ecsv``: detect and measure stars.

Parse, read the images (ADU, converted to electrons with the gain), call
`bfpsf.measure.sources.measure_sources`, write the star table (ECSV) and the JSON summary.
"""

import sys

import numpy as np

from ..errors import BFPSFInputError
from ..files import about, check_outputs, input_files, read_table, refuse_duplicates
from ..outputs import write_json, write_table
from . import image_arguments, output_options, positive_float, stamp_size_option, star_image_options
from ._files import place_stars, read_image


def _amplifier_colours(colour_table, amplifier):
    """The colour catalogue (detector x, y) in the pixels of one amplifier."""
    from ..io.amplifiers import detector_offset

    x0, y0 = detector_offset(amplifier.layout)
    if not (x0 or y0):
        return colour_table
    shifted = colour_table.copy()
    shifted["x"] = shifted["x"] - x0
    shifted["y"] = shifted["y"] - y0
    return shifted


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "measure", help="detect stars and measure adaptive moments (sizes) in electrons",
        description="Detect sources (photutils segmentation), subtract the sky (a plane, "
                    "or of degree 2 or 3 where the sky is curved, fitted beyond the masked "
                    "sources, as every command), and "
                    "measure peak, flux and adaptive second moments (G15 section 3.2). "
                    "Saturated, blended and edge sources are flagged, not dropped.")
    image_arguments(parser, "measure", about=" with header EXPTIME",
                    after="; x, y are detector pixels")
    parser.add_argument("-o", "--output", required=True, metavar="STARS.ecsv",
                        help="star table to write (ECSV)")
    gain = parser.add_mutually_exclusive_group()
    gain.add_argument("--calib", metavar="CALIB.fits",
                      help="take the gain (e-/ADU) from this calibration file")
    gain.add_argument("--gain", type=positive_float, metavar="G",
                      help="gain, e-/ADU (default: header GAIN of each image)")
    parser.add_argument("--color", "--colour", dest="colour", action="append", metavar="COLUMN",
                        help="colour column to pass through, read from --catalog or from the "
                             "image's CATALOG extension (x, y in 0-based pixels); repeatable")
    parser.add_argument("--catalog", metavar="FILE",
                        help="table with x, y and colour columns (default: CATALOG HDU)")
    parser.add_argument("--stamp-size", type=stamp_size_option, default=32,
                        help="measurement stamp side, pixels (default 32)")
    star_image_options(parser, saturation="flags, does not drop", background=False)
    output_options(parser)
    return parser


def _gain(args, header, path, calibration, amplifier):
    """The gain of one amplifier: --gain, its calibration's (``calibration``, the
    amplifier's own), or the header's."""
    if args.gain is not None:
        return float(args.gain)  # positive and finite (positive_float)
    if calibration is not None:
        gain = calibration.gain
        where = f"{args.calib}: the gain of amplifier {amplifier!r}"
    elif "GAIN" in header:
        where = f"{path}: header GAIN = {header['GAIN']!r}"
        try:
            gain = float(header["GAIN"])
        except (TypeError, ValueError):
            gain = float("nan")
    else:
        msg = f"{path}: no gain: give --gain G or --calib CALIB.fits (no GAIN header)"
        raise BFPSFInputError(msg, path)
    if not (np.isfinite(gain) and gain > 0):
        msg = f"{where} is not a gain (a positive number of e-/ADU); give --gain G"
        raise BFPSFInputError(msg, gain)
    return float(gain)


def run(args):
    from astropy.table import vstack

    from ..calibration.detector import calibration_of_amplifier, read_calibration
    from ..io.amplifiers import shared_sides
    from ..io.saturation import saturation_e
    from ..moments.adaptive import MomentsFlag
    from ..measure.sources import SourceFlag, measure_sources
    from ..measure.prepare import electrons, linearity_of

    check_outputs([args.output, args.json], args.overwrite,
                  inputs=input_files(args.images, args.calib, args.catalog))
    refuse_duplicates(args.images, "image")
    external = (read_table(args.catalog, "catalog", numeric=("x", "y", *(args.colour or ())))
                if args.catalog else None)
    tables, summary_images = [], []
    # read_calibration names a missing or foreign file itself
    calibration = read_calibration(args.calib) if args.calib else None
    for path in args.images:
        amplifiers, catalog = read_image(path, args.amp)
        colour_table = external if external is not None else catalog
        if args.colour and colour_table is None:
            msg = f"{path}: --color needs --catalog FILE or a CATALOG extension in the image"
            raise BFPSFInputError(msg, path)
        sides = shared_sides([amplifier.layout for amplifier in amplifiers])
        for amplifier in amplifiers:
            header = amplifier.header
            amplifier_calibration = None if calibration is None else calibration_of_amplifier(
                calibration, amplifier.name, str(path), len(amplifiers))
            gain = _gain(args, header, path, amplifier_calibration, amplifier.name)
            level = saturation_e(amplifier, gain, args.saturation, amplifier_calibration)
            # the one image preparation: e-, and a refined calibration's linearity undone
            linearity = (0.0 if amplifier_calibration is None
                         else linearity_of(amplifier_calibration))
            with about(path):
                table = measure_sources(  # e- (measure_sources fits its own sky)
                    electrons(amplifier.data, gain=gain, linearity_c_per_1e5=linearity),
                    threshold=args.threshold, stamp_size=args.stamp_size, saturation=level,
                    colour=(_amplifier_colours(colour_table, amplifier) if args.colour
                            else None),
                    colour_columns=args.colour)
            table.meta.pop("cosmic_rays")  # their pixels: counted, not listed
            place_stars(table, amplifier, sides, args.stamp_size / 2)
            table.add_column(str(path), name="image", index=0)
            tables.append(table)
            summary_images.append({"image": str(path), "amplifier": amplifier.name,
                                   "gain": gain, "n_sources": len(table),
                                   "n_clean": int(np.sum(table["flags"] == 0)),
                                   "saturation_e": level,
                                   "n_saturated": int(np.sum(
                                       (table["flags"] & MomentsFlag.SATURATED) != 0)),
                                   "n_amp_boundary": int(np.sum(table["amp_boundary"])),
                                   "line_pixels": table.meta["line_pixels"],
                                   # -1: too few bright stars to say how sharp a star is
                                   "cosmic_ray_pixels": table.meta["cosmic_ray_pixels"],
                                   "sky_degree": table.meta["sky_degree"],
                                   "exptime": header.get("EXPTIME")})
    stars = vstack(tables, metadata_conflicts="silent") if len(tables) > 1 else tables[0]
    stars.meta["gains"] = [entry["gain"] for entry in summary_images]
    stars.meta["images"] = [entry["image"] for entry in summary_images]
    write_table(stars, args.output, overwrite=args.overwrite)
    summary = {"output": str(args.output), "n_stars": len(stars),
               "n_clean": int(np.sum(stars["flags"] == 0)),
               "n_flagged": int(np.sum(stars["flags"] != 0)),
               "n_saturated": sum(entry["n_saturated"] for entry in summary_images),
               # on a bright neighbour's wings, which make them large (slope leaves them out)
               "n_neighbour_light": int(np.sum((stars["flags"] & SourceFlag.NEIGHBOUR_LIGHT)
                                               != 0)),
               # beside a trail or a hot column, whose pixels were left out
               "n_on_line": int(np.sum((stars["flags"] & SourceFlag.ON_LINE) != 0)),
               # a cosmic ray within 4 sigma, its pixels filled from their neighbours
               "n_cosmic_ray": int(np.sum((stars["flags"] & SourceFlag.COSMIC_RAY) != 0)),
               # no adaptive-moment solution: the weight collapsed onto one pixel
               "n_undersampled": int(np.sum((stars["flags"] & MomentsFlag.UNDERSAMPLED) != 0)),
               "images": summary_images}
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    print(f"{len(stars)} sources ({summary['n_clean']} clean, {summary['n_saturated']} "
          f"saturated, {summary['n_neighbour_light']} on a bright neighbour's light, which "
          f"makes them large"
          + (f", {summary['n_on_line']} beside a trail or a hot column, whose "
             f"{sum(entry['line_pixels'] for entry in summary_images)} pixels were left out"
             if any(entry["line_pixels"] for entry in summary_images) else "")
          + (f", {summary['n_cosmic_ray']} beside a cosmic ray, whose "
             f"{sum(max(entry['cosmic_ray_pixels'], 0) for entry in summary_images)} pixels "
             "were filled from their neighbours" if summary["n_cosmic_ray"] else "")
          + f") in {len(args.images)} image(s); wrote {args.output}")
    if summary["n_undersampled"]:
        _warn_undersampled(stars, summary["n_undersampled"])
    return 0


def _warn_undersampled(stars, count):
    """One line on the sources whose adaptive moments collapsed onto one pixel (flag
    'undersampled'), with the size of the others: such stars are undersampled, and the
    sizes measured of them depend on their sub-pixel phase (`bfpsf.moments.adaptive`)."""
    sigma = np.asarray(stars["iq"], dtype=float)[np.asarray(stars["flags"]) == 0]
    size = (f"median sigma {np.median(sigma):.2f} px of the clean ones" if sigma.size
            else "no clean source")
    print(f"WARNING: {count} of {len(stars)} sources have no adaptive-moment solution (flag "
          f"'undersampled': the weight collapsed onto the central pixel; {size}): stars this "
          "narrow are undersampled, and the sizes measured of the others change with their "
          "sub-pixel phase by more than brighter-fatter changes them (docs/limitations.md)",
          file=sys.stderr)
