"""``bfpsf photometry IMAGE... --psf PSF.fits -o PHOT.ecsv``: PSF photometry with P(F).

Parse, read the PSF product and the images (ADU -> e- with the product's gain), call
`bfpsf.measure.photometry.psf_photometry` (photutils PSFPhotometry with the flux-dependent
PSF), write the table (fluxes in e-) and the JSON summary.
"""


import numpy as np

from ..files import check_outputs, write_json, write_table
from ..measure.sources import DETECTION_THRESHOLD
from ._files import read_image


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "photometry", help="PSF photometry with the flux-dependent PSF P(F)",
        description="Detect stars and fit each with P(F) = P0 + F R[P0] at its own flux "
                    "(photutils PSFPhotometry, grouped fits for close stars). Columns x_fit, "
                    "y_fit, flux_fit, flux_err (e-), flags, plus photutils' own.")
    parser.add_argument("images", nargs="+", metavar="IMAGE.fits",
                        help="bias-subtracted images in ADU (first 2-D image HDU)")
    parser.add_argument("--psf", required=True, metavar="PSF.fits",
                        help="PSF product written by 'bfpsf psf'")
    parser.add_argument("-o", "--output", required=True, metavar="PHOT.ecsv",
                        help="photometry table to write (ECSV)")
    parser.add_argument("--gain", type=float, default=None,
                        help="e-/ADU (default: the gain stored in the PSF product)")
    parser.add_argument("--read-noise", type=float, default=0.0, metavar="E",
                        help="read noise, e- rms, for the pixel errors (default 0)")
    parser.add_argument("--threshold", type=float, default=DETECTION_THRESHOLD,
                        help=f"detection threshold, RMS of the smoothed image (default "
                             f"{DETECTION_THRESHOLD:g})")
    parser.add_argument("--fit-shape", type=int, default=None,
                        help="fit box, pixels, odd (default about 3 FWHM)")
    parser.add_argument("--static", action="store_true",
                        help="fit the static P0 (no BF term), for comparison")
    parser.add_argument("--no-cross-terms", action="store_true",
                        help="skip the refit of blended stars without the BF of their charge "
                             "on each other")
    parser.add_argument("--json", metavar="FILE", help="write a JSON summary")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    return parser


def run(args):
    from astropy.table import vstack

    from ..errors import BFPSFInputError
    from ..interop.photutils import static_image_psf
    from ..measure.photometry import psf_photometry
    from ..model.psf import FluxDependentPSF

    check_outputs([args.output, args.json], args.overwrite)
    psf = FluxDependentPSF.read(args.psf)
    if psf.flux_unit != "electron":
        psf = psf.with_flux_unit("electron")  # the images are converted to e- below
    gain = psf.gain if args.gain is None else float(args.gain)
    if gain is None:
        msg = f"{args.psf} records no gain: give --gain G (e-/ADU of the images)"
        raise BFPSFInputError(msg, args.psf)
    if not (np.isfinite(gain) and gain > 0):
        msg = f"the gain must be positive e-/ADU, got {gain!r}"
        raise BFPSFInputError(msg, gain)
    model = static_image_psf(psf) if args.static else psf
    tables, per_image = [], []
    for path in args.images:
        image_e = read_image(path)[0] * gain
        table = psf_photometry(image_e, model, read_noise_e=args.read_noise,
                               fit_shape=args.fit_shape, detection_threshold=args.threshold,
                               cross_terms=not args.no_cross_terms)
        table.add_column(str(path), name="image", index=0)
        tables.append(table)
        per_image.append({"image": str(path), "n_stars": len(table),
                          "n_flagged": int(np.sum(table["flags"] != 0)),
                          "background_e": table.meta["background_e"],
                          "n_blended": int(np.sum(table["group_size"] > 1)),
                          "cross_term_refits": table.meta["cross_term_refits"]})
    result = vstack(tables, metadata_conflicts="silent") if len(tables) > 1 else tables[0]
    result.meta.update({"psf": str(args.psf), "gain": gain, "flux_unit": "electron",
                        "static_psf": bool(args.static)})
    result["flux_fit"].unit = "electron"
    result["flux_err"].unit = "electron"
    write_table(result, args.output, overwrite=args.overwrite)
    summary = {"output": str(args.output), "psf": str(args.psf), "gain": gain,
               "static_psf": bool(args.static), "n_stars": len(result),
               "n_flagged": int(np.sum(result["flags"] != 0)), "images": per_image}
    if args.json:
        write_json(args.json, summary, overwrite=args.overwrite)
    print(f"{len(result)} stars fitted in {len(args.images)} image(s) "
          f"({summary['n_flagged']} flagged); wrote {args.output}")
    return 0
