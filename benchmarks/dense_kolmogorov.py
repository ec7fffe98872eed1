"""Photometry at defaults in a dense field of Kolmogorov stars (docs/defaults.md, "A denser
field of Kolmogorov stars").

Three exposures (320^2, ``--size``) of Kolmogorov stars (FWHM 3.5 px, wings r^-11/3, each
drawn on 201^2 pixels) at least ``--separation`` pixels apart, brighter-fatter with the
shifts of a calibration from simulated E2V SiliconSensor flats; the README's ``bfpsf psf``
and ``bfpsf photometry`` with no option. Prints the mean offset from the true total flux and the
brightest fifth minus the faintest, mmag, with the calibration's gain error taken out.

Run: ``OMP_NUM_THREADS=1 python benchmarks/dense_kolmogorov.py --separation 9 --stars 300
--seed 8803`` (about a minute; 12 / 220 / 8802 and 20 / 110 / 8801 for the other rows)
"""

import argparse
import sys
import tempfile
from pathlib import Path

import galsim
import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--separation", type=float, default=9.0)
    parser.add_argument("--stars", type=int, default=300)
    parser.add_argument("--seed", type=int, default=8803)
    parser.add_argument("--size", type=int, default=320, help="side of each exposure, pixels")
    args = parser.parse_args()

    from bfpsf import calibrate
    from bfpsf.validation.simulate_fields import simulate_field
    from bfpsf.validation.simulate_flats import simulate_flats

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_acceptance_defaults import GAIN as gain, run_defaults

    flats = simulate_flats("lsst_e2v_50_8", np.linspace(5e3, 1e5, 8), pairs=3, size=128,
                           nsteps=10, gain=gain, read_noise_e=5.0, seed=99)
    cal = calibrate([image for image, _, _ in flats], exptimes=[t for _, t, _ in flats],
                    maxlag=6, fit_b=False, n_monte_carlo=12)
    field = simulate_field(galsim.Kolmogorov(fwhm=3.5), n_images=3, shape=(args.size, args.size),
                           n_stars=args.stars, min_separation=args.separation, sensor=None,
                           shifts=cal.shifts, seed=args.seed, stamp=201)
    with tempfile.TemporaryDirectory() as directory:
        figures, summary, _ = run_defaults(field, cal, Path(directory))
    gain_mmag = -2500 * np.log10(cal.gain / gain)
    skies = [entry["background_e"] - sky[0] for entry, sky in zip(summary["images"],
                                                                  field.skies)]
    print(f"{args.stars} stars per {args.size}^2 image, >= {args.separation:g} px, seed "
          f"{args.seed}: mean "
          f"{figures['mean'] - gain_mmag:+.2f} +- {figures['mean_err']:.2f} mmag (gain "
          f"{cal.gain:.4f}: {gain_mmag:+.2f} mmag taken out), brightest - faintest "
          f"{figures['drift']:+.2f} +- {figures['drift_err']:.2f} mmag; psf sky - truth "
          f"{', '.join(f'{value:+.2f}' for value in skies)} e-")


if __name__ == "__main__":
    main()
