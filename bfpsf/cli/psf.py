"""``bfpsf psf IMAGE... --calib CALIB.fits -o PSF.fits``: fit the flux-dependent PSF (issue 5).

Parse, read the images (ADU -> e- with the calibration gain), detect isolated stars
(`bfpsf.measure.sources.measure_sources`), fit P0 from stars of all fluxes with the
brighter-fatter term of each removed (`bfpsf.model.psf_fit.fit_psf`; with ``--grid NX NY`` one
P0 per node of a grid over the image, `bfpsf.model.gridded.GriddedFluxDependentPSF`), write the
PSF product and the JSON summary.
"""

from pathlib import Path

import numpy as np

from ..errors import BFPSFInputError
from ._files import check_free, read_image, write_json


def add_parser(subparsers):
    parser = subparsers.add_parser(
        "psf", help="fit the flux-dependent PSF P(F) = P0 + F R[P0] from stars of all fluxes",
        description="Fit the base PSF P0 (oversampled, pixel response included) from isolated "
                    "stars of all fluxes, each modelled as F P0 + F^2 R[P0] with R the G15 "
                    "charge redistribution of the calibration, and write the PSF product.")
    parser.add_argument("images", nargs="+", metavar="IMAGE.fits",
                        help="bias-subtracted images in ADU (first 2-D image HDU)")
    parser.add_argument("--calib", required=True, metavar="CALIB.fits",
                        help="calibration (boundary shifts, gain, read noise)")
    parser.add_argument("-o", "--output", required=True, metavar="PSF.fits",
                        help="PSF product to write (FITS)")
    parser.add_argument("--oversampling", type=int, default=2,
                        help="oversampling of P0 (default 2; 4 needs several hundred stars)")
    parser.add_argument("--size", type=int, default=25,
                        help="support of P0 and star cutouts, pixels, odd (default 25)")
    parser.add_argument("--threshold", type=float, default=10.0,
                        help="detection threshold, RMS of the smoothed image (default 10)")
    parser.add_argument("--saturation", type=float, default=None, metavar="ADU",
                        help="saturation level, ADU: saturated stars are not used")
    parser.add_argument("--grid", type=int, nargs=2, metavar=("NX", "NY"), default=None,
                        help="fit P0 on NX x NY nodes over the image (P(F, x, y), bilinear "
                             "between nodes, as photutils GriddedPSFModel); default one P0")
    parser.add_argument("--max-iterations", type=int, default=40,
                        help="iterations of the P0 fit (default 40)")
    parser.add_argument("--no-bf", dest="include_bf", action="store_false",
                        help="fit a static ePSF (no BF term), for comparison")
    parser.add_argument("--json", metavar="FILE", help="write a JSON summary")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    return parser


def _isolated_stars(image_e, threshold, saturation_e, size):
    """Clean, unsaturated, isolated detections: positions (N, 2) and background (e-)."""
    from ..measure.sources import measure_sources

    sources = measure_sources(image_e, threshold=threshold, blend_radius=size / 2 + 2,
                              saturation=saturation_e, stamp_size=size + 6)
    clean = np.asarray(sources["flags"]) == 0
    xy = np.column_stack([np.asarray(sources["x"], dtype=float)[clean],
                          np.asarray(sources["y"], dtype=float)[clean]])
    return xy, len(sources)


def run(args):
    from astropy.stats import sigma_clipped_stats

    from ..calibration.product import Calibration
    from ..model.psf_fit import fit_psf

    check_free(args.output, args.overwrite)
    check_free(args.json, args.overwrite)
    calibration = Calibration.read(args.calib)
    if calibration.shifts is None:
        msg = f"{args.calib} has no boundary shifts (calibration solved without them)"
        raise BFPSFInputError(msg, args.calib)
    gain = float(calibration.gain)
    images, positions, skies, per_image = [], [], [], []
    for path in args.images:
        image_e = read_image(path)[0] * gain
        _, background, _ = sigma_clipped_stats(image_e[np.isfinite(image_e)], sigma=3.0)
        image_e = image_e - background
        saturation_e = None if args.saturation is None else args.saturation * gain - background
        xy, n_detected = _isolated_stars(image_e, args.threshold, saturation_e, args.size)
        images.append(image_e)
        skies.append(max(float(background), 0.0))
        positions.append(xy)
        per_image.append({"image": str(path), "n_detected": int(n_detected),
                          "n_isolated": int(len(xy)), "background_e": float(background)})
    result = fit_psf(images, positions, calibration.shifts, oversampling=args.oversampling,
                     size=args.size, read_noise=float(calibration.noise_e),
                     sky_e=skies, include_bf=args.include_bf,
                     max_iterations=args.max_iterations, grid=args.grid, progress=None)
    psf = result.psf
    psf.image_gain = gain
    psf.calibration = Path(args.calib).name
    psf.write(args.output, meta={"NSTARS": int(np.sum(result.stars["flags"] == 0)),
                                 "CONVERGD": bool(result.converged),
                                 "BFTERM": bool(args.include_bf)},
              overwrite=args.overwrite)
    from ..interop.photutils import psf_fwhm

    used = result.stars["flags"] == 0
    summary = {"output": str(args.output), "calibration": str(args.calib), "gain": gain,
               "oversampling": int(args.oversampling), "size": int(args.size),
               "include_bf": bool(args.include_bf), "n_stars": int(len(result.stars)),
               "n_used": int(np.sum(used)), "iterations": int(result.iterations),
               "converged": bool(result.converged),
               "fwhm_pixels": psf_fwhm(psf if args.grid is None
                                       else psf.nodes[len(psf.nodes) // 2]),
               "flux_range_e": [float(np.min(result.stars["flux_fit"][used])),
                                float(np.max(result.stars["flux_fit"][used]))]
               if np.any(used) else None,
               "images": per_image}
    if args.grid is not None:
        summary["grid"] = {"nx": int(args.grid[0]), "ny": int(args.grid[1]),
                           "x_nodes": psf.x_nodes.tolist(), "y_nodes": psf.y_nodes.tolist(),
                           "fwhm_pixels": [psf_fwhm(node) for node in psf.nodes]}
    if args.json:
        write_json(args.json, summary)
    print(f"P0 from {summary['n_used']} of {summary['n_stars']} stars in "
          f"{len(args.images)} image(s), {result.iterations} iterations "
          f"({'converged' if result.converged else 'NOT converged'}); wrote {args.output}")
    return 0
