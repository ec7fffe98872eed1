"""Simulation tests: a GalSim scene drawn with brighter-fatter, measured back.

For whoever tests a pipeline on simulations. A scene of Moffat stars of many fluxes and a few
sheared exponential galaxies is drawn twice with the same boundary shifts: by photon shooting
through `bfpsf.BFSensor` (a GalSim Sensor, a drop-in for ``SiliconSensor``) and by
`bfpsf.draw_with_bf` (the same distribution without shooting photons, about a hundred times
faster for bright objects). The stars are measured back with `bfpsf.measure_sources`
(adaptive moments), their brighter-fatter slope fitted (`bfpsf.measure.slopes.bf_slopes`)
and compared with the slope the flux-dependent PSF predicts from the shifts alone.

Usage::

    python examples/simulate_with_bf.py [--quick] [--output DIR]
"""

import argparse
from pathlib import Path

import galsim
import numpy as np
from scipy.spatial import cKDTree

import bfpsf
from bfpsf.measure.slopes import bf_slopes, fit_bf_slope
from bfpsf.measure.model_slopes import model_size_increments

SHIFTS = bfpsf.BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
STAR = galsim.Moffat(beta=3.5, fwhm=3.5)
SPACING = 40
#: Photons shot per batch (memory about 100 bytes each).
PHOTON_BATCH = 2_000_000


def scene(n_cells, seed, max_peak_e=1.2e5):
    """Stars (3 ke- to ``max_peak_e`` of peak) and every fifth cell a galaxy, on a grid with
    random phases."""
    rng = np.random.default_rng(seed)
    peak_fraction = STAR.drawImage(nx=15, ny=15, scale=1.0).array.max()
    objects, stars, fluxes = [], [], []
    size = n_cells * SPACING
    for index in range(n_cells**2):
        x, y = (index % n_cells + 0.5) * SPACING, (index // n_cells + 0.5) * SPACING
        x, y = x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5)
        # galsim places (0, 0) of the profile at the true centre of the image
        shift = (x - (size / 2 - 0.5), y - (size / 2 - 0.5))
        if index % 5 == 2:
            galaxy = galsim.Exponential(half_light_radius=2.5, flux=rng.uniform(2e4, 2e5))
            galaxy = galsim.Convolve(galaxy.shear(e1=rng.uniform(-0.3, 0.3), e2=0.1), STAR)
            objects.append(galaxy.shift(shift))
            continue
        peak = np.exp(rng.uniform(np.log(3e3), np.log(max_peak_e)))
        objects.append(STAR.withFlux(peak / peak_fraction).shift(shift))
        stars.append((x, y))
        fluxes.append(peak / peak_fraction)
    return galsim.Add(objects), np.array(stars), np.array(fluxes), size


def measure(image, star_xy, star_flux):
    """measure_sources on an image in e-, keeping the detections of the true stars (with
    their true flux in ``flux_true``)."""
    table = bfpsf.measure_sources(image)
    distance, index = cKDTree(np.stack([table["x"], table["y"]], 1)).query(star_xy)
    found = distance < 2.0
    stars = table[index[found]]
    stars["flux_true"] = star_flux[found]
    return stars


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small scene, seconds")
    parser.add_argument("--output", default="simulation_output", help="output directory")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    # quick: fewer and fainter stars (photon shooting costs about 1 s per 4e6 e-)
    profile, star_xy, star_flux, size = (scene(4, seed=4, max_peak_e=6e4) if args.quick
                                         else scene(12, seed=4))
    sky = 50.0
    rng = galsim.BaseDeviate(7)
    # photons in batches of PHOTON_BATCH (BFSensor resumes the exposure across them): the
    # full scene shoots about 1e8 photons, 13 GB in one array
    shot = profile.drawImage(nx=size, ny=size, scale=1.0, method="phot",
                             sensor=bfpsf.BFSensor(SHIFTS), rng=rng, maxN=PHOTON_BATCH)
    fast = bfpsf.draw_with_bf(profile, SHIFTS, nx=size, ny=size, rng=8)
    noise = np.random.default_rng(9)
    images = {name: image.array + noise.poisson(sky, image.array.shape) - sky
              for name, image in (("BFSensor (photon shooting)", shot), ("draw_with_bf", fast))}
    psf = bfpsf.FluxDependentPSF.from_galsim(STAR, SHIFTS)
    results = {}
    for name, image in images.items():
        stars = measure(image, star_xy, star_flux)
        slopes = bf_slopes(stars)
        results[name] = (stars, slopes)
        print(f"{name:28s} {len(stars)} stars: sigma_x slope {slopes['x'].slope:.4f} +- "
              f"{slopes['x'].slope_err:.4f}, sigma_y {slopes['y'].slope:.4f} +- "
              f"{slopes['y'].slope_err:.4f} pix / 100 ke- of peak")
    # The model's size growth at each star's flux, against the star's measured peak (which
    # depends on its sub-pixel phase as much as on its flux): the slope to expect
    stars = results["draw_with_bf"][0]
    increments = model_size_increments(psf, stars["flux_true"])
    # (same weights as the measured fit: stars at different phases scatter about the line)
    predicted = {axis: fit_bf_slope(stars["peak_e"], increments[axis],
                                    size_err=stars[f"sigma_{axis}_err"]).slope
                 for axis in ("x", "y")}
    print(f"{'predicted from the shifts':28s} sigma_x slope {predicted['x']:.4f}, sigma_y "
          f"{predicted['y']:.4f} pix / 100 ke- of peak")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    shown = np.arcsinh(images["draw_with_bf"] / 20.0)
    left.imshow(shown, origin="lower", cmap="gray_r", vmin=0, vmax=np.quantile(shown, 0.998))
    left.set_title("scene drawn with draw_with_bf", fontsize=9)
    left.set_xticks([])
    left.set_yticks([])
    for marker, (name, (table, slopes)) in zip("os", results.items()):
        right.plot(table["peak_e"] / 1e3, table["sigma_x"], marker, mfc="none",
                   label=f"{name}: {slopes['x'].slope:.4f} +- {slopes['x'].slope_err:.4f}")
    peaks = np.linspace(0, 1.2e5, 10)
    intercept = results["draw_with_bf"][1]["x"].intercept
    right.plot(peaks / 1e3, intercept + predicted["x"] * peaks / 1e5, "k-",
               label=f"P(F) prediction: {predicted['x']:.4f}")
    right.set_xlabel("peak (ke-)")
    right.set_ylabel("sigma_x (pixels)")
    right.set_title("brighter-fatter slope, pix / 100 ke- of peak", fontsize=9)
    right.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(output / "simulate_with_bf.png", dpi=70)
    print(f"wrote {output / 'simulate_with_bf.png'}")
    return {name: slopes for name, (_, slopes) in results.items()}, predicted


if __name__ == "__main__":
    main()
