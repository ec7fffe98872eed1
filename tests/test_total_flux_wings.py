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
