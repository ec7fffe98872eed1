"""Photometry at defaults: P(F) against the static PSF with the same sky method (issue 21).

``bfpsf.psf_photometry(image, psf)`` as ``bfpsf photometry`` runs it (image preparation, the
sky plane beyond the masked sources, the first fit, the sky again beyond the glow of the
fitted stars' wings, the model-weighted refit, the cross-term refit of blends, the total-flux
correction) against the same call with the static P0 (`bfpsf.interop.photutils.static_image_psf`:
the same preparation and sky plane, the same two fits, and the glow step with the product's
wings, ``wings=psf``, as ``bfpsf photometry --static`` runs it). Timed side by side in one run, the calls in turn within each of N repeats, best
of N; the ratio is printed (target: at most 1.2x). Stars on a grid 20 pixels apart (bench_photometry's field) on a sloped sky (200-500 e-).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_photometry_defaults.py [--stars 400]
[--repeat 3]``
"""

import argparse
import time
import warnings

import galsim
import numpy as np


def star_field(n_stars, spacing, shifts):
    """bench_photometry's field (1000 e- sky, subtracted) on a sloped sky of 200-500 e-."""
    from bench_photometry import star_field as flat_sky_field

    image, _, _, _ = flat_sky_field(n_stars, spacing, shifts)
    y, x = np.mgrid[:image.shape[0], :image.shape[1]]
    return image + 200.0 + 300.0 * (x + y) / (2 * image.shape[0])


def best_times(functions, repeat):
    """Best of ``repeat`` runs of each function, the functions taken in turn within each
    repeat (so a machine that slows down or speeds up between them biases no ratio), and the
    last result of each."""
    best, results = [np.inf] * len(functions), [None] * len(functions)
    for _ in range(repeat):
        for index, function in enumerate(functions):
            start = time.perf_counter()
            results[index] = function()
            best[index] = min(best[index], time.perf_counter() - start)
    return best, results


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stars", type=int, default=400)
    parser.add_argument("--repeat", type=int, default=3, help="best of N runs (default 3)")
    args = parser.parse_args()

    from bfpsf.interop.photutils import static_image_psf
    from bfpsf.measure.photometry import psf_photometry
    from bfpsf.model.wings import WingModel
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.shifts import BoundaryShifts

    shifts = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
    psf = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=3.5), shifts,
                                       oversampling=2, size=25)
    # the wings of a beta 3 Moffat beyond the support, as psf_from_images measures them
    psf.wing_coefficients = WingModel.power_law(15.0, 6.0, psf.half_size).coefficients
    psf.wing_tail_power, psf.wing_half_size = 6.0, psf.half_size
    static = static_image_psf(psf)
    image = star_field(args.stars, 20, shifts)
    print(f"{args.stars} stars, Moffat FWHM 3.5 px, peaks 3-120 ke-, sloped sky, image "
          f"{image.shape}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # photutils warnings on unconverged noisy fits
        no_wings = psf.copy()
        no_wings.wing_coefficients = ()
        (t_static, t_bf, t_plain), (r_static, r_bf, _) = best_times(
            [lambda model=model, wings=wings: psf_photometry(image, model, read_noise_e=5.0,
                                                             wings=wings)
             for model, wings in ((static, psf), (psf, None), (no_wings, None))], args.repeat)
    print(f"static P0, same sky method: {t_static:.2f} s ({r_static.meta['sky']['method']})")
    print(f"P(F) at defaults:           {t_bf:.2f} s ({r_bf.meta['sky']['method']})")
    print(f"P(F) without the glow step: {t_plain:.2f} s")
    print(f"ratio P(F) / static: {t_bf / t_static:.2f}x (target <= 1.2x); without the glow "
          f"step {t_plain / t_static:.2f}x")


if __name__ == "__main__":
    main()
