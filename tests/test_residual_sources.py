"""PSF photometry finds the stars detection missed in the residual of its fit
(`bfpsf.measure.residual_sources`), against GalSim stars of a non-Moffat profile."""

import galsim
import numpy as np
import pytest

from bfpsf.measure.photometry import psf_photometry
from bfpsf.measure.residual_sources import residual_sources
from bfpsf.measure.sources import SourceFlag
from bfpsf.model.psf import FluxDependentPSF
from bfpsf.shifts import BoundaryShifts
from conftest import galsim_bf_stars

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
#: Kolmogorov seeing through an obscured pupil: wings a Moffat lacks
PROFILE = galsim.Convolve(galsim.Kolmogorov(fwhm=3.0),
                          galsim.Airy(lam_over_diam=1.2, obscuration=0.3))
SKY = 300.0
N_BRIGHT = 12


@pytest.fixture(scope="module")
def psf():
    return FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=25)


@pytest.fixture(scope="module")
def field():
    """12 bright stars (4-8e5 e-) 40 px apart, each with a companion of 4-10 % of its flux
    7.5-9.5 px away (on its wing: detection makes no peak of most), on a 300 e- sky; and the
    same bright stars alone."""
    rng = np.random.default_rng(3)
    bright = (np.array([(40 * (i + 0.5), 40 * (j + 0.5)) for j in range(3) for i in range(4)])
              + rng.uniform(-0.5, 0.5, (N_BRIGHT, 2)))
    angle, separation = rng.uniform(0, 2 * np.pi, N_BRIGHT), rng.uniform(7.5, 9.5, N_BRIGHT)
    companions = bright + separation[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    flux_bright = rng.uniform(4e5, 8e5, N_BRIGHT)
    flux = np.r_[flux_bright, flux_bright * rng.uniform(0.04, 0.1, N_BRIGHT)]
    xy = np.vstack([bright, companions])

    def noisy(positions, fluxes):
        image = galsim_bf_stars(PROFILE, positions, fluxes, (120, 160), SHIFTS)
        return rng.poisson(image + SKY) + rng.normal(0.0, 5.0, image.shape)

    return noisy(xy, flux), xy, flux, noisy(bright, flux_bright), flux_bright


def _matched(result, xy):
    """Each true star's nearest fit: (its row, distance)."""
    distance = np.hypot(np.asarray(result["x_fit"])[:, None] - xy[None, :, 0],
                        np.asarray(result["y_fit"])[:, None] - xy[None, :, 1])
    return distance.argmin(axis=0), distance.min(axis=0)


def test_photometry_finds_the_companions_detection_missed(psf, field):
    """Detection splits 3 of the 12 companions from their bright star; the search of the
    fit's residual finds the other 9 (flagged IN_RESIDUAL) and every star is measured:
    companions within 1.5 % (median; 2.8 % at worst), bright stars within 0.3 %. Without
    it (``residual_passes=0``) 9 companions are missing."""
    data, xy, flux, _, _ = field
    without = psf_photometry(data, psf, read_noise_e=5.0, residual_passes=0)
    _, distance = _matched(without, xy)
    assert np.sum(distance[N_BRIGHT:] < 1.0) <= N_BRIGHT // 2
    result = psf_photometry(data, psf, read_noise_e=5.0)
    row, distance = _matched(result, xy)
    assert len(result) == len(xy) and np.all(distance < 1.0)
    found = (np.asarray(result["source_flags"]) & SourceFlag.IN_RESIDUAL) > 0
    assert result.meta["residual_sources"] == {"found": int(found.sum()), "lost": 0}
    assert found.sum() == len(xy) - len(without) and not found[row[:N_BRIGHT]].any()
    ratio = np.asarray(result["flux_fit"])[row] / flux - 1
    assert np.abs(ratio[:N_BRIGHT]).max() < 0.005, ratio[:N_BRIGHT]
    assert abs(np.median(ratio[N_BRIGHT:])) < 0.015 and np.abs(ratio[N_BRIGHT:]).max() < 0.05


def test_the_residual_of_isolated_stars_holds_no_star(psf, field):
    """The bright stars alone: their fit's residual (P(F)'s misfit of 4-8e5 e- cores, the
    noise) gives no source."""
    _, _, _, data, flux = field
    result = psf_photometry(data, psf, read_noise_e=5.0)
    assert len(result) == N_BRIGHT
    assert result.meta["residual_sources"] == {"found": 0, "lost": 0}


def test_a_level_the_sky_model_missed_is_no_star():
    """A residual holding what a sky plane cannot follow (a frame tiled 2 x 2 has seams of
    hundreds of e-: the search found 737 sources on 120 stars and took 284 s) and a trail: a
    step of 80 e- over half the frame, a band of 60 e- 3 px wide along it, and two faint
    Gaussian stars (2500 e-, about 12 sigma), one on each side of the step, against a noise
    of the sky alone. Only the stars are found: a source's light is measured above the
    surface about it and a source is round (DAOFIND's roundness: its marginals alike);
    without the roundness 10 were found."""
    rng = np.random.default_rng(11)
    shape, sky = (120, 160), 300.0
    y, x = np.mgrid[:shape[0], :shape[1]].astype(float)
    stars = np.array([[40.3, 30.6], [120.7, 80.2]])
    light = sum(2500.0 / (2 * np.pi * 1.5**2)
                * np.exp(-((x - sx)**2 + (y - sy)**2) / (2 * 1.5**2)) for sx, sy in stars)
    residual = (light + 80.0 * (y >= 60) + 60.0 * (np.abs(y - 95) <= 1)
                + rng.normal(0.0, np.sqrt(sky), shape))
    found = residual_sources(residual, np.full(shape, sky), np.empty((0, 2)), threshold=5.0)
    assert len(found) == 2
    distance = np.hypot(found["x_init"][:, None] - stars[:, 0], found["y_init"][:, None]
                        - stars[:, 1])
    assert np.all(distance.min(axis=1) < 1.5)


def test_a_refit_starts_where_the_fit_before_is_sane():
    """A refit starts from the fit before where that is finite and of positive flux, else
    from its start: a fit on a satellite trail went to a flux of -6e7 and its refits ran off
    to x = 3.8e8, a row of NaN in the output."""
    from astropy.table import Table

    from bfpsf.measure.neighbour_fits import _refit_init

    init = Table({"x_init": [10.0, 20.0, 30.0, 40.0], "y_init": [5.0, 6.0, 7.0, 8.0],
                  "flux_init": [1e4, 2e4, 3e4, 4e4]})
    # the last ran off with a positive flux (a fit on a cosmic-ray track: x = -1096, NaN after)
    result = Table({"x_fit": [10.5, 3.8e8, np.nan, -1096.0], "y_fit": [5.5, 2e8, 7.0, 8.0],
                    "flux_fit": [1.1e4, -6e7, 3e4, 227.0]})
    start = _refit_init(init, result)
    np.testing.assert_array_equal(start["x_init"], [10.5, 20.0, 30.0, 40.0])
    np.testing.assert_array_equal(start["y_init"], [5.5, 6.0, 7.0, 8.0])
    np.testing.assert_array_equal(start["flux_init"], [1.1e4, 2e4, 3e4, 4e4])
