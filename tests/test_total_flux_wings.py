"""Total fluxes of stars with power-law wings, at defaults: an Airy x Kolmogorov profile (an
obscured telescope through the atmosphere, 3.0 % of its light beyond the 27-pixel support of
P0) drawn with its whole wings, brighter-fatter from G15 shifts, through ``bfpsf psf`` and
``bfpsf photometry`` as a user runs them.

A new user's Airy stars, drawn by GalSim's SiliconSensor on 49-pixel stamps, came out 2.0 +-
0.3 mmag brighter bright than faint (docs/limitations.md, helper-28): the same photons with the
light beyond each stamp added gave -0.16 +- 0.18 mmag. The stamps had cut the wings that P0's
wing model carries on; real stars' wings are not cut, and these are not.
"""

import json

import galsim
import numpy as np
import pytest
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_fields import simulate_field
from bfpsf.validation.simulate_spots import peak_fraction, write_image_adu

from test_photometry import make_calibration

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
PROFILE = galsim.Convolve(galsim.Airy(lam_over_diam=1.2, obscuration=0.3),
                          galsim.Kolmogorov(fwhm=2.9))
GAIN = 1.5
STAMP = 161  # each star's light out to 80 pixels: all but 0.19 % of it
PEAKS = (1e4, 1.2e5)  # e-: the faint end's noise sets the drift's error


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    directory = tmp_path_factory.mktemp("wings")
    field = simulate_field(PROFILE, n_images=3, shape=(256, 256), n_stars=40,
                           peak_range_e=PEAKS, sensor=None, shifts=SHIFTS, seed=24,
                           stamp=STAMP)
    paths = [str(directory / f"image{index}.fits") for index in range(len(field.images))]
    for path, image in zip(paths, field.images):
        write_image_adu(path, image, gain=GAIN)
    make_calibration(SHIFTS, GAIN, 5.0).write(directory / "calib.fits")
    assert main(["psf", *paths, "--calib", str(directory / "calib.fits"), "-o",
                 str(directory / "psf.fits"), "--json", str(directory / "psf.json")]) == 0
    assert main(["photometry", *paths, "--psf", str(directory / "psf.fits"), "-o",
                 str(directory / "phot.ecsv")]) == 0
    return directory, field, paths


def _support_fraction(size):
    return float(PROFILE.drawImage(nx=size, ny=size, scale=1.0).array.sum())


def test_the_wing_model_gives_the_light_beyond_the_support(field):
    directory = field[0]
    summary = json.loads((directory / "psf.json").read_text())
    truth = 1.0 / _support_fraction(27)  # 1.0306
    # measured 1.0332 here; 1.0328-1.0356 over seeds 5-7 and 24-29 (the r^-p fitted beyond
    # 13 px, carried outwards: its p and amplitude from the wings of 120 stars)
    assert summary["flux_correction"] == pytest.approx(truth, abs=0.006)


def test_fluxes_are_total_and_do_not_drift_with_brightness(field):
    directory, simulated, paths = field
    table = Table.read(directory / "phot.ecsv")
    # the truth is the star's whole flux (its light beyond the image edge included, as a
    # total flux includes it), less the 0.19 % beyond the drawn stamp
    total_per_peak = _support_fraction(STAMP) / peak_fraction(PROFILE)
    magnitudes, peaks = [], []
    for path, truth in zip(paths, simulated.truth):
        mine = table[table["image"] == path]
        distance = np.hypot(np.asarray(mine["x_fit"])[:, None] - truth["x"],
                            np.asarray(mine["y_fit"])[:, None] - truth["y"])
        matched, nearest = distance.min(axis=1) < 1.0, distance.argmin(axis=1)
        assert matched.sum() >= len(truth) - 1
        true_flux = truth["peak_e"][nearest[matched]] * total_per_peak
        magnitudes.append(-2.5e3 * np.log10(np.asarray(mine["flux_fit"])[matched] / true_flux))
        peaks.append(truth["peak_e"][nearest[matched]])
    magnitudes, peaks = np.concatenate(magnitudes), np.concatenate(peaks)
    bright, faint = magnitudes[peaks > 4e4], magnitudes[peaks < 2e4]
    drift = bright.mean() - faint.mean()
    error = np.hypot(bright.std(ddof=1) / np.sqrt(bright.size),
                     faint.std(ddof=1) / np.sqrt(faint.size))
    print(f"mean {magnitudes.mean():+.2f} mmag, bright - faint {drift:+.2f} +- {error:.2f} mmag")
    # the wing model's excess (above, 0.25-0.5 %) is -2.7 to -5 mmag on every star: seeds
    # 24-29 gave means of -1.3 to -4.6 mmag
    assert -6.0 < magnitudes.mean() < 1.0
    # drifts over seeds 24-29: +1.08, -1.14, +1.42, +0.28, +0.54, +0.84 mmag (sd 0.9 against
    # errors of 0.42-0.53: P0 fitted from 120 stars adds about 0.7 mmag seed to seed)
    assert abs(drift) < 3 * np.hypot(error, 0.7) and error < 0.6


def test_sky_and_wings_fit_recovers_each_plane_and_the_power_law():
    """The joint fit of every image's sky plane and the stars' r^-p glow on an analytic case
    (planes, glow of 0.03 F r^-3 beyond a 7-pixel half support: 2.5 % of F; 1 e- of noise; one
    image empty of stars): its block solution (each image's plane projected out, the
    amplitude from what is left) gives the planes and the wings' fraction (on a new user's
    four amplifiers of eight exposures the dense least squares it replaces took 589 s and
    2 GB against 13 s and 0.48 GB, the same numbers to 1e-15)."""
    from bfpsf.measure.total_flux import _beyond_square, fit_sky_and_wings

    rng = np.random.default_rng(7)
    half, amplitude, power, shape = 7, 0.03, 3.0, (120, 150)
    planes = [(300.0, 0.05, -0.02), (120.0, -0.03, 0.04), (505.0, 0.0, 0.01)]
    images, stars = [], []
    y, x = np.mgrid[:shape[0], :shape[1]]
    for index, (level, slope_x, slope_y) in enumerate(planes):
        n = 0 if index == 2 else 6
        star_x, star_y = rng.uniform(20, 130, n), rng.uniform(20, 100, n)
        flux = rng.uniform(2e5, 2e6, n)
        sky = level + slope_x * (x - (shape[1] - 1) / 2) + slope_y * (y - (shape[0] - 1) / 2)
        glow = np.zeros(shape)  # A F r^-p beyond each star's support, to the image's edge
        for x_0, y_0, value in zip(star_x, star_y, flux):
            outside = ((np.abs(x - np.rint(x_0)) > half) | (np.abs(y - np.rint(y_0)) > half))
            glow += np.where(outside, value * amplitude
                             * np.hypot(x - x_0, y - y_0).clip(1.0) ** -power, 0.0)
        images.append(sky + glow + rng.normal(0.0, 1.0, shape))
        stars.append((star_x, star_y, flux))
    skies, wings = fit_sky_and_wings(images, stars, half_size=half)
    truth = amplitude * _beyond_square(power, half)
    # measured: p 3.1, fraction 0.02161 against 0.02259 (-4 %), skies +0.69, +0.67 and
    # +0.003 e-: the glow beyond the template's reach (6 half-widths, 45 px) goes into the
    # planes of the images with stars (docs/limitations.md)
    assert wings.power == pytest.approx(power, abs=0.15)
    assert wings.fraction == pytest.approx(truth, rel=0.06)
    for sky, (level, _, _), image_stars in zip(skies, planes, stars):
        assert sky.level == pytest.approx(level, abs=1.0 if len(image_stars[0]) else 0.05)
