"""PSF photometry at defaults under a curved sky (docs/defaults.md, "A curved sky").

One image (``--size``^2) of GalSim Kolmogorov x obscured Airy stars (no BF, peaks
log-uniform 500-120000 e-, random positions 20 px apart; `simulate_field`) on a sky of 600 e-
with a shape (``--sky``:
flat, plane, bowl: +60 e- at the edges' middle, hump: +80 e- of scattered light off
centre), Poisson and 5 e- of read noise; PSF photometry with the true PSF and the sky of
the defaults (``auto``) or of a given degree. Prints, per flux bin (5-20, 20-100,
100-2000 ke-), the median m_fit - m_true and its robust spread, mmag.

Run: ``OMP_NUM_THREADS=1 python benchmarks/curved_sky.py --sky bowl --seed 1 --degrees 1 2``
(about 20 s; --sky hump --seed 2 --degrees 1 2 3, --sky flat --seed 1 ...)
"""

import argparse

import galsim
import numpy as np

import bfpsf
from bfpsf.measure.photometry import psf_photometry
from bfpsf.measure.prepare import prepare_image
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_fields import simulate_field

BINS = ((5e3, 2e4), (2e4, 1e5), (1e5, 2e6))


def sky_surface(kind, size):
    """The sky ``kind`` of a ``size``^2 image, a function of (x, y), e- per pixel."""
    def surface(x, y):
        u, v = (np.asarray(x) - size / 2) / (size / 2), (np.asarray(y) - size / 2) / (size / 2)
        return 600.0 + {"flat": 0 * u, "plane": 40 * u - 25 * v,
                        "bowl": 60 * (u ** 2 + v ** 2),
                        "hump": 80 * np.exp(-((u - 0.4) ** 2 + (v + 0.3) ** 2) / 0.5)}[kind]
    return surface


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sky", choices=("flat", "plane", "bowl", "hump"), default="bowl")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--size", type=int, default=768)
    parser.add_argument("--stars", type=int, default=120)
    parser.add_argument("--degrees", type=int, nargs="*", default=[1],
                        help="sky degrees to run besides the default's choice")
    args = parser.parse_args()
    profile = galsim.Convolve(galsim.Kolmogorov(fwhm=2.6),
                              galsim.Airy(lam_over_diam=0.9, obscuration=0.4))
    field = simulate_field(profile, n_images=1, shape=(args.size, args.size),
                           n_stars=args.stars, peak_range_e=(5e2, 1.2e5), min_separation=20.0,
                           sensor=None, sky_surface=sky_surface(args.sky, args.size),
                           seed=args.seed, stamp=256)
    data, truth = field.images[0], field.truth[0]
    x, y, flux = (np.asarray(truth[name], float) for name in ("x", "y", "flux_e"))
    psf = bfpsf.FluxDependentPSF.from_galsim(
        profile, BoundaryShifts.from_radial_profile(lambda r: 0 * r, 2))
    for degree in ["auto", *args.degrees]:
        prepared = prepare_image(data, sky_degree=degree)
        table = psf_photometry(prepared, psf, read_noise_e=5.0)
        distance = np.hypot(table["x_fit"][None] - x[:, None], table["y_fit"][None] - y[:, None])
        nearest = np.argmin(distance, axis=1)
        found = distance[np.arange(len(x)), nearest] < 1.0
        offset = 1e3 * 2.5 * np.log10(flux / np.clip(table["flux_fit"][nearest], 1.0, None))
        cells = []
        for low, high in BINS:
            members = found & (flux >= low) & (flux < high)
            median = np.median(offset[members])
            spread = 1.4826 * np.median(np.abs(offset[members] - median))
            cells.append(f"{low / 1e3:g}-{high / 1e3:g} ke- {median:+.1f} ({spread:.1f}, "
                         f"{members.sum()})")
        print(f"sky {args.sky} seed {args.seed}, degree {degree!s:4s} -> "
              f"{prepared.sky.kind}: found {found.sum()}/{len(x)}; " + "; ".join(cells),
              flush=True)


if __name__ == "__main__":
    main()
