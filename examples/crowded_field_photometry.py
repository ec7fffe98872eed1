"""PSF photometry of a crowded field: a static ePSF against the flux-dependent P(F).

For the photometrist. Simulates a crowded field of Moffat stars whose charge is redistributed
by brighter-fatter (the whole image at once, so blended stars push each other's boundaries),
fits two PSFs from the isolated stars -- a static ePSF from the bright ones, as
`photutils.psf.EPSFBuilder` would give, and P0 of P(F) from all of them with each star's BF
term removed -- and measures every star with both (`bfpsf.measure.photometry.psf_photometry`,
forced at the true positions). The static PSF is too broad for the faint stars: they come out
too bright, a flux bias that grows towards faint magnitudes; P(F) has none. Stars blended
with brighter neighbours scatter both alike; the difference of the two is the BF bias.

Usage::

    python examples/crowded_field_photometry.py [--quick] [--output DIR]

The shifts are E2V-like (a(0, 0) = -2.3e-6 / e-, as GalSim's lsst_e2v_50_8); with your own
data use the shifts of ``bfpsf calibrate`` and ``bfpsf psf`` / ``bfpsf photometry``.
"""

import argparse
from pathlib import Path

import galsim
import numpy as np

import bfpsf
from bfpsf.model.galsim_profile import render_stars
from bfpsf.interop.photutils import static_image_psf
from bfpsf.measure.photometry import psf_photometry
from bfpsf.model.psf_fit import fit_psf

SHIFTS = bfpsf.BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
PROFILE = galsim.Moffat(beta=4.0, fwhm=3.5)
SKY_E, READ_NOISE_E = 200.0, 5.0
ZERO_POINT = 25.0  # magnitude of 1 e-


def simulate_field(n_stars, size, seed):
    """Noisy image (e-, sky included), true positions and fluxes (log-uniform 3e4-2.5e6 e-)."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(12, size - 12, (n_stars, 2))
    fluxes = np.exp(rng.uniform(np.log(3e4), np.log(2.5e6), n_stars))
    charge = render_stars(PROFILE, positions, fluxes, (size, size), shifts=SHIFTS)
    image = rng.poisson(charge + SKY_E) + rng.normal(0.0, READ_NOISE_E, charge.shape)
    return image.astype(float), positions, fluxes


def isolated(positions, radius):
    distance = np.hypot(*(positions[:, None, :] - positions[None, :, :]).T)
    np.fill_diagonal(distance, np.inf)
    return distance.min(axis=0) > radius


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small field, seconds")
    parser.add_argument("--output", default="photometry_output", help="output directory")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    # P0 support and isolation: a neighbour inside the cutout of a PSF star spoils the fit
    n_stars, size, support, isolation = (80, 320, 15, 18) if args.quick else (800, 1000, 21, 22)
    image, positions, fluxes = simulate_field(n_stars, size, seed=1)
    data = image - SKY_E
    alone = isolated(positions, isolation)
    bright = alone & (fluxes > 3e5)
    print(f"{n_stars} stars on {size}^2 pixels, {alone.sum()} isolated, {bright.sum()} bright "
          "and isolated")
    options = dict(oversampling=2, size=support, read_noise=READ_NOISE_E, sky_e=SKY_E)
    # A static P0 cannot fit stars of different BF exactly: it settles near their mean shape
    # and keeps moving slowly, so its iterations are capped.
    static = fit_psf(data, positions[bright], SHIFTS, include_bf=False, max_iterations=15,
                     **options).psf
    fit = fit_psf(data, positions[alone], SHIFTS, **options)
    dependent = fit.psf
    print(f"P0 of P(F) from {alone.sum()} stars: converged {fit.converged} in "
          f"{fit.iterations} iterations")
    models = {"static ePSF (bright stars)": static_image_psf(static), "P(F)": dependent}
    magnitude = ZERO_POINT - 2.5 * np.log10(fluxes)
    results = {}
    for name, model in models.items():
        table = psf_photometry(image, model, positions=positions, background_e=SKY_E,
                               read_noise_e=READ_NOISE_E)
        ratio = np.asarray(table["flux_fit"]) / fluxes
        good = np.asarray(table["flags"]) == 0
        faint = good & (fluxes < np.quantile(fluxes, 0.3))
        top = good & (fluxes > np.quantile(fluxes, 0.7))
        # magnitude error of the faint third minus that of the bright third, mmag: negative
        # when the faint stars come out too bright (median of each third)
        bias = -2.5e3 * (np.log10(np.median(ratio[faint])) - np.log10(np.median(ratio[top])))
        results[name] = {"ratio": ratio, "good": good, "bias_mmag": bias}
        print(f"{name:28s} faint - bright flux bias {bias:+6.2f} mmag "
              f"({good.sum()} stars fitted)")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6),
                                         gridspec_kw={"width_ratios": [1, 1.6]})
    shown = np.arcsinh(data / 50.0)
    left.imshow(shown, origin="lower", cmap="gray_r", vmin=0, vmax=np.quantile(shown, 0.995))
    left.set_title("simulated field (BF on the whole image)", fontsize=9)
    left.set_xticks([])
    left.set_yticks([])
    edges = np.quantile(magnitude, np.linspace(0, 1, 7))
    for colour, (name, result) in zip(("C3", "C0"), results.items()):
        usable = result["good"] & (result["ratio"] > 0)
        mmag = -2.5e3 * np.log10(np.where(usable, result["ratio"], 1.0))
        centres, medians, errors = [], [], []
        for low, high in zip(edges[:-1], edges[1:]):
            members = usable & (magnitude >= low) & (magnitude <= high)
            median = np.median(mmag[members])
            centres.append(np.mean(magnitude[members]))
            medians.append(median)
            # error of the median from the median absolute deviation (blends are outliers)
            spread = 1.4826 * np.median(np.abs(mmag[members] - median))
            errors.append(1.2533 * spread / np.sqrt(members.sum()))
        right.errorbar(centres, medians, errors, fmt="o-", color=colour,
                       label=f"{name}: {result['bias_mmag']:+.1f} mmag faint - bright")
    right.axhline(0.0, color="k", lw=0.8)
    right.set_xlabel(f"magnitude ({ZERO_POINT:g} - 2.5 log10 true flux / e-)")
    right.set_ylabel("measured - true (mmag)")
    right.legend(fontsize=8)
    right.set_title("PSF photometry, median per magnitude bin", fontsize=9)
    figure.tight_layout()
    figure.savefig(output / "crowded_field_photometry.png", dpi=70)
    print(f"wrote {output / 'crowded_field_photometry.png'}")
    return results


if __name__ == "__main__":
    main()
