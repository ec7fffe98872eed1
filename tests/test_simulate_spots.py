"""The spot and star-field simulator: peaks, centres, flux, BF sign, FITS writer (issue 4)."""

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.errors import BFPSFFileExistsError, BFPSFValueError
from bfpsf.moments.adaptive import adaptive_moments_batch
from bfpsf.validation.simulate_spots import simulate_spots, simulate_star_field, write_image_adu

galsim = pytest.importorskip("galsim")


def test_spots_without_sensor_have_the_requested_peak_and_centre():
    peaks = (2e4, 8e4)
    spots = simulate_spots(sensor=None, peaks_e=peaks, n_per_level=6, seed=1)
    assert spots.stamps.shape == (12, 32, 32)
    np.testing.assert_array_equal(spots.peaks, np.repeat(peaks, 6))
    measured_peak = spots.stamps.max(axis=(1, 2))
    # photon shooting: the brightest pixel scatters by its Poisson noise (plus the max of
    # a few neighbours, biased up by < 1 sigma): within 4 sqrt(peak)
    np.testing.assert_array_less(np.abs(measured_peak - spots.peaks), 4 * np.sqrt(spots.peaks))
    moments = adaptive_moments_batch(spots.stamps)
    # a symmetric profile's centroid is its centre; photon noise moves it by
    # ~sigma / sqrt(flux) < 0.01 pixel
    np.testing.assert_allclose(moments.x, spots.x, atol=0.01)
    np.testing.assert_allclose(moments.y, spots.y, atol=0.01)
    # flux: all photons land in the 32 x 32 stamp except the Moffat wing beyond ~16 pixels
    # (0.2 % for beta 3.5) and Poisson scatter of the photon count
    np.testing.assert_allclose(spots.stamps.sum(axis=(1, 2)), spots.fluxes, rtol=0.004)


def test_spots_are_reproducible_and_seeded():
    first = simulate_spots(sensor=None, peaks_e=(1e4,), n_per_level=2, seed=5)
    again = simulate_spots(sensor=None, peaks_e=(1e4,), n_per_level=2, seed=5)
    other = simulate_spots(sensor=None, peaks_e=(1e4,), n_per_level=2, seed=6)
    np.testing.assert_array_equal(first.stamps, again.stamps)
    assert not np.array_equal(first.stamps, other.stamps)


def test_silicon_sensor_spots_grow_with_flux():
    # brighter-fatter truth: lsst_e2v_50_8 spots broaden with flux in x and y; without BF the
    # same spots do not (difference of the two: BF alone, photon noise ~ 1e-3 pixel)
    peaks = (5e3, 1e5)
    bf = simulate_spots(peaks_e=peaks, n_per_level=2, seed=2)
    no_bf = simulate_spots(sensor=None, peaks_e=peaks, n_per_level=2, seed=2)
    growth = []
    for spots in (bf, no_bf):
        moments = adaptive_moments_batch(spots.stamps)
        sigma_x = np.sqrt(moments.mxx).reshape(2, 2).mean(axis=1)
        sigma_y = np.sqrt(moments.myy).reshape(2, 2).mean(axis=1)
        growth.append((sigma_x[1] - sigma_x[0], sigma_y[1] - sigma_y[0]))
    (bf_x, bf_y), (flat_x, flat_y) = growth
    # G15 and GalSim: a few 0.01 pixel per 100 ke-
    assert 0.01 < bf_x - flat_x < 0.08
    assert 0.01 < bf_y - flat_y < 0.08
    assert abs(flat_x) < 0.01 and abs(flat_y) < 0.01


def test_bf_free_twin_replays_the_same_photons():
    # the twin has the same photons (identical totals: photon count and edge losses), the same
    # noise, and differs from the spot only by BF: its size does not grow with flux, and the
    # spot-minus-twin size difference is the BF growth with far less scatter than the sizes
    spots = simulate_spots(peaks_e=(5e3, 1e5), n_per_level=4, seed=4, read_noise_e=3.0,
                           bf_free_twin=True)
    np.testing.assert_allclose(spots.stamps.sum(axis=(1, 2)), spots.twin.sum(axis=(1, 2)),
                               rtol=1e-12)
    sigma = np.sqrt(adaptive_moments_batch(spots.stamps).mxx).reshape(2, 4)
    twin = np.sqrt(adaptive_moments_batch(spots.twin).mxx).reshape(2, 4)
    difference = sigma - twin
    assert np.all(difference[1] > difference[0])           # BF grows with flux
    assert np.all(np.abs(difference[0]) < 0.1 * difference[1].min())  # ~linear in flux
    # faint spots: the photon noise of the sizes (~3e-3 px) cancels in the pair
    assert difference[0].std() < 0.2 * sigma[0].std()
    with pytest.raises(BFPSFValueError, match="bf_free_twin"):
        simulate_spots(sensor=None, bf_free_twin=True)


def test_mosaic_places_spots_at_their_true_positions():
    spots = simulate_spots(sensor=None, peaks_e=(1e4,), n_per_level=5, seed=3)
    image, truth = spots.mosaic(margin=4)
    assert image.shape == (2 * 32 + 8, 3 * 32 + 8)
    for row in truth:
        iy, ix = int(round(row["y"])), int(round(row["x"]))
        window = image[iy - 1:iy + 2, ix - 1:ix + 2]
        assert window.max() == image[iy - 3:iy + 4, ix - 3:ix + 4].max()


def test_star_field_truth_and_colour_relation():
    field = simulate_star_field(shape=(160, 160), n_stars=9, spacing=50, fwhm_colour_slope=0.1,
                                colour_flux_slope=0.5, seed=4)
    truth = field.truth
    assert len(truth) == 9 and "g_i" in truth.colnames
    expected_fwhm = 4.0 * (1 + 0.1 * (truth["g_i"] - 1.0))
    np.testing.assert_allclose(truth["fwhm"], expected_fwhm)
    # charge: sky of 100 e- per pixel (left in the image) plus the stars; the Moffat wings
    # beyond the 24-pixel drawing stamps hold < 2e-4 of the flux, Poisson noise 2e-4
    total = 100.0 * field.image.size + truth["flux_e"].sum()
    assert field.image.sum() == pytest.approx(total, rel=1e-3)
    with pytest.raises(BFPSFValueError, match="fewer than n_stars=50"):
        simulate_star_field(shape=(100, 100), n_stars=50)


def test_write_image_adu_round_trip(tmp_path):
    image = np.arange(12.0).reshape(3, 4) * 10.0
    path = tmp_path / "image.fits"
    write_image_adu(path, image, gain=2.0, exptime=15.0)
    with fits.open(path) as hdus:
        np.testing.assert_allclose(hdus[0].data, image / 2.0)
        assert hdus[0].header["GAIN"] == 2.0 and hdus[0].header["EXPTIME"] == 15.0
    with pytest.raises(BFPSFFileExistsError, match="overwrite=True"):
        write_image_adu(path, image, gain=2.0)
    write_image_adu(path, 2 * image, gain=2.0, overwrite=True)
    assert fits.getdata(path)[1, 1] == pytest.approx(50.0)


def test_invalid_arguments_raise():
    with pytest.raises(BFPSFValueError, match="peaks_e must be positive"):
        simulate_spots(peaks_e=(-1.0,))
    with pytest.raises(BFPSFValueError, match="sensor must be"):
        simulate_spots(sensor=3, peaks_e=(1e3,), n_per_level=1)
    with pytest.raises(BFPSFValueError, match="fwhm must be positive"):
        simulate_spots(fwhm=0.0)
