"""Shear: the PSF a galaxy needs is not the PSF of the bright stars.

For the weak-lensing pipeline. A galaxy is faint: its image is blurred by the PSF at (nearly)
zero flux, P0, while the stars a PSF model is built from are bright and broadened by
brighter-fatter. This script measures the PSF size and ellipticity at every flux with
``FluxDependentPSF.shape`` (adaptive moments, the estimator of the star measurements), and
the multiplicative shear bias m of a galaxy whose shear is estimated (GalSim HSM, REGAUSS)
with the bright stars' PSF instead of P0, against the galaxy-to-PSF size ratio. It compares m
with the first-order estimate m = dT_psf / T_gal (Paulin-Henriksson et al. 2008).

Usage::

    python examples/shear_psf_size.py [--quick] [--output DIR]

The shifts are E2V-like with parallel (north) boundaries 1.6 times stiffer than the serial
ones, so that e1 changes with flux too.
"""

import argparse
from pathlib import Path

import galsim
import numpy as np

import bfpsf
from bfpsf.model.galsim_profile import to_galsim

RADIAL = bfpsf.BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
SHIFTS = bfpsf.BoundaryShifts(RADIAL.north * 1.3, RADIAL.east * 0.8, check=False)
#: 0.7 arcsec seeing at 0.2 arcsec per pixel, slightly elliptical
OPTICS = galsim.Moffat(beta=3.5, fwhm=3.5).shear(e1=0.02, e2=-0.01)
GALAXY_FLUX, STAR_FLUX = 2e3, 1.5e6  # e-: a faint galaxy, a star with a 100 ke- peak
SHEAR = 0.02


def psf_image(psf, flux):
    profile, _ = to_galsim(psf, flux)  # pixel included: draw with method='no_pixel'
    return profile.drawImage(nx=33, ny=33, scale=1.0, method="no_pixel")


def shear_response(psf_used, p0_profile, galaxy):
    """Estimated e1 (REGAUSS) of the galaxy sheared by +-SHEAR, blurred by P0 itself."""
    estimates = []
    for sign in (1, -1):
        observed = galsim.Convolve(galaxy.shear(g1=sign * SHEAR), p0_profile)
        image = observed.drawImage(nx=49, ny=49, scale=1.0, method="no_pixel")
        result = galsim.hsm.EstimateShear(image, psf_used, shear_est="REGAUSS")
        estimates.append(result.corrected_e1)
    return (estimates[0] - estimates[1]) / 2.0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer fluxes and sizes")
    parser.add_argument("--output", default="shear_output", help="output directory")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    psf = bfpsf.FluxDependentPSF.from_galsim(OPTICS, SHIFTS, oversampling=4, size=25)

    fluxes = np.linspace(1e3, 2e6, 5 if args.quick else 12)
    shapes = [psf.shape(flux) for flux in fluxes]
    faint, bright = psf.shape(GALAXY_FLUX), psf.shape(STAR_FLUX)
    print(f"PSF at the galaxy's flux ({GALAXY_FLUX:.0e} e-): sigma {faint.sigma:.4f} px, "
          f"e1 {faint.e1:+.5f}, e2 {faint.e2:+.5f}")
    print(f"PSF of the bright stars ({STAR_FLUX:.1e} e-): sigma {bright.sigma:.4f} px, "
          f"e1 {bright.e1:+.5f}, e2 {bright.e2:+.5f}")
    print(f"  dT/T = {bright.T / faint.T - 1:+.4f}, de1 = {bright.e1 - faint.e1:+.5f}")

    p0_profile, _ = to_galsim(psf, GALAXY_FLUX)
    right, wrong = psf_image(psf, GALAXY_FLUX), psf_image(psf, STAR_FLUX)
    ratios = np.array([1.0, 2.0] if args.quick else [0.6, 0.8, 1.0, 1.4, 2.0, 3.0])
    measured, predicted = [], []
    for ratio in ratios:
        # an exponential galaxy with T_gal = T_observed - T_psf = ratio * T_psf
        radius = 1.0
        for _ in range(5):
            galaxy = galsim.Exponential(half_light_radius=radius)
            t_gal = _adaptive_t(galsim.Convolve(galaxy, p0_profile)) - faint.T
            radius *= np.sqrt(ratio * faint.T / t_gal)
        galaxy = galsim.Exponential(half_light_radius=radius)
        bias = shear_response(wrong, p0_profile, galaxy) / shear_response(right, p0_profile,
                                                                          galaxy) - 1
        measured.append(bias)
        predicted.append((bright.T - faint.T) / (ratio * faint.T))
        print(f"T_gal / T_psf = {ratio:.1f}: m = {bias:+.5f} with the bright stars' PSF "
              f"(first order dT_psf / T_gal: {predicted[-1]:+.5f})")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, middle, right_ax) = plt.subplots(1, 3, figsize=(11, 3.3))
    sigma = np.array([shape.sigma for shape in shapes])
    left.plot(fluxes / 1e6, 100 * (sigma / faint.sigma - 1), "o-")
    left.set_xlabel("flux (1e6 e-)")
    left.set_ylabel("sigma / sigma(galaxy flux) - 1 (%)")
    middle.plot(fluxes / 1e6, 1e3 * np.array([shape.e1 - faint.e1 for shape in shapes]), "o-",
                label="e1")
    middle.plot(fluxes / 1e6, 1e3 * np.array([shape.e2 - faint.e2 for shape in shapes]), "s-",
                label="e2")
    middle.set_xlabel("flux (1e6 e-)")
    middle.set_ylabel("e - e(galaxy flux) (1e-3)")
    middle.legend(fontsize=8)
    for ax in (left, middle):
        ax.axvline(GALAXY_FLUX / 1e6, color="C2", ls=":", lw=1.5)
        ax.axvline(STAR_FLUX / 1e6, color="C3", ls="--", lw=1)
    right_ax.plot(ratios, 100 * np.array(measured), "o", label="REGAUSS, bright-star PSF")
    right_ax.plot(ratios, 100 * np.array(predicted), "-", label="dT_psf / T_gal")
    right_ax.set_xlabel("T_gal / T_psf")
    right_ax.set_ylabel("multiplicative bias m (%)")
    right_ax.legend(fontsize=8)
    figure.suptitle("PSF at a faint galaxy's flux (dotted) and at the bright stars' (dashed)",
                    fontsize=10)
    figure.tight_layout()
    figure.savefig(output / "shear_psf_size.png", dpi=70)
    print(f"wrote {output / 'shear_psf_size.png'}")
    return {"faint": faint, "bright": bright, "ratios": ratios, "m": np.array(measured),
            "m_first_order": np.array(predicted)}


def _adaptive_t(profile):
    """Mxx + Myy of a pixelised profile (pixel included), bfpsf's adaptive moments."""
    image = profile.drawImage(nx=65, ny=65, scale=1.0, method="no_pixel").array
    moments = bfpsf.adaptive_moments(image)
    return moments.mxx + moments.myy


if __name__ == "__main__":
    main()
