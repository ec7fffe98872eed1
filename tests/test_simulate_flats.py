"""SiliconSensor flat simulator: brighter-fatter physics against GalSim truth, the injected
readout correlation, non-linearity, hot columns and defects, files and command line."""

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration.covariance import pair_covariance
from bfpsf.calibration.flat_mask import pair_mask
from bfpsf.calibration.flats import pair_flats, read_flats
from bfpsf.cli import main
from bfpsf.errors import BFPSFFileExistsError
from bfpsf.interop.silicon_truth import silicon_area_coefficients
from bfpsf.validation.simulate_flats import simulate_flats, write_flats

SENSOR = "lsst_itl_50_8"
GAIN = 1.5
NOISE_E = 5.0


def pair_results(flats, maxlag=2, **options):
    """PairCovariance of consecutive simulated flats, converted to electrons."""
    results = []
    for (image1, exptime, _), (image2, _, _) in zip(flats[0::2], flats[1::2]):
        results.append(pair_covariance(image1, image2, maxlag=maxlag, **options))
    return results


def astier_variance(mean_e, a00, noise_e):
    """Astier et al. 2019 eq. 16 (gain 1): C00 = (exp(2 a00 mu) - 1) / (2 a00) + n."""
    return np.expm1(2 * a00 * mean_e) / (2 * a00) + noise_e**2


QUICK_SIZE = 384
QUICK_STEPS = 5
#: the midpoint rule under-estimates the brighter-fatter terms by 1 / nsteps^2
QUICK_BIAS = 1 - 1 / QUICK_STEPS**2


@pytest.fixture(scope="module")
def itl_flats():
    # Two pairs of 384 x 384 at 100 ke-: sigma(a) = 1 / (sqrt(N) mu sqrt(2)) = 1.8e-8 per e-,
    # so a(1, 0) = 7.4e-8 is a 4-sigma signal and a(0, 1) - a(1, 0) a 4.6-sigma one.
    return simulate_flats(SENSOR, [100_000.0], pairs=2, size=QUICK_SIZE, gain=GAIN,
                          read_noise_e=NOISE_E, nsteps=QUICK_STEPS, seed=1)


@pytest.fixture(scope="module")
def truth():
    return silicon_area_coefficients(SENSOR, maxlag=2)


def test_itl_flats_show_anisotropic_brighter_fatter(itl_flats, truth):
    results = pair_results(itl_flats)
    mean_e = np.mean([r.mean_adu for r in results]) * GAIN
    a = np.mean([r.cov_adu / (r.var_adu * r.mean_adu) for r in results], axis=0) / GAIN
    # statistical error of C / (V mu): 1 / (sqrt(N) mu) per pair (G15 section 4.2.2)
    error = 1 / (np.sqrt(QUICK_SIZE**2 * len(results)) * mean_e)
    # a(1, 0) > 0: neighbours grow; the parallel neighbour a(0, 1) more than the serial one
    assert a[0, 1] > 2 * error
    assert a[1, 0] - a[0, 1] > 2 * np.sqrt(2) * error
    # and both agree with GalSim's truth (second-order factor 1 + a00 mu / 3 of Astier+19)
    expected = truth * (1 + truth[0, 0] * mean_e / 3) * QUICK_BIAS
    assert abs(a[0, 1] - expected[0, 1]) < 3 * error
    assert abs(a[1, 0] - expected[1, 0]) < 3 * error


def test_itl_variance_falls_below_poisson_as_astier_eq16(itl_flats, truth):
    results = pair_results(itl_flats)
    for result in results:
        mean_e = result.mean_adu * GAIN
        variance_e = result.var_adu * GAIN**2
        error = variance_e * np.sqrt(2 / QUICK_SIZE**2)
        # the brighter-fatter deficit is ~10 % at 100 ke-, 25 standard errors
        assert variance_e < mean_e - 10 * error
        # (the 1 / nsteps^2 scaling of the deficit is exact to first order; the second-order
        # remainder, 1e-2 * 4e-2 of the variance, is 0.1 error)
        poisson = mean_e + NOISE_E**2
        expected = poisson + QUICK_BIAS * (astier_variance(mean_e, truth[0, 0], NOISE_E) - poisson)
        assert abs(variance_e - expected) < 3 * error


def test_itl_flats_are_not_masked(itl_flats):
    (image1, _, _), (image2, _, _) = itl_flats[:2]
    mask, report = pair_mask(image1, image2)
    assert report.total == report.edge


def test_readout_correlation_appears_as_r10():
    c = 0.02
    options = dict(pairs=1, size=256, gain=GAIN, read_noise_e=NOISE_E, nsteps=2, seed=3)
    plain = pair_results(simulate_flats(SENSOR, [20_000.0], **options))[0]
    correlated = pair_results(simulate_flats(SENSOR, [20_000.0], readout_correlation=c,
                                             **options))[0]
    # The same seed draws the same charge: the correlation adds c / (1 + c^2) to R(1, 0),
    # diluted by the read noise (25 / 2e4); sampling noise of R is common to both and
    # cancels to O(c / sqrt(N)) = 1e-4.
    expected = c / (1 + c**2) * (1 - NOISE_E**2 / 20_000)
    assert correlated.corr[0, 1] - plain.corr[0, 1] == pytest.approx(expected, abs=3e-4)
    assert correlated.corr[1, 0] == pytest.approx(plain.corr[1, 0], abs=3e-4)  # parallel: none
    assert correlated.mean_adu == pytest.approx((1 + c) * plain.mean_adu, rel=1e-4)


def test_nonlinearity_is_quadratic_in_charge():
    options = dict(pairs=1, size=64, gain=GAIN, read_noise_e=0.0, nsteps=1, seed=4)
    linear = simulate_flats(SENSOR, [50_000.0], **options)
    curved = simulate_flats(SENSOR, [50_000.0], nonlinearity=1e-6, **options)
    for (image, _, _), (bent, _, header) in zip(linear, curved):
        charge = image * GAIN
        np.testing.assert_allclose(bent * GAIN, charge * (1 + 1e-6 * charge), rtol=1e-12)
        assert header["SIMNONLI"] == 1e-6


def test_hot_columns_and_defect_clusters_are_injected_and_masked():
    flats = simulate_flats(SENSOR, [50_000.0], pairs=1, size=128, nsteps=1, seed=5,
                           hot_columns=(20, 90), defect_clusters=3)
    (image1, _, header), (image2, _, _) = flats
    assert header["SIMHOTC"] == "20,90" and header["SIMNDEF"] == 3
    mask, report = pair_mask(image1, image2, edge=0)
    assert mask[:, 20].all() and mask[:, 90].all()
    assert report.columns == 2 * 128
    # three 3x3 clusters (fixed pattern, the same pixels in both flats), seed 5: disjoint
    assert report.defects == 27
    assert report.total == 2 * 128 + 27


def test_simulation_is_reproducible():
    options = dict(pairs=1, size=32, nsteps=2)
    first = simulate_flats(SENSOR, [1000.0], seed=7, **options)
    again = simulate_flats(SENSOR, [1000.0], seed=7, **options)
    other = simulate_flats(SENSOR, [1000.0], seed=8, **options)
    np.testing.assert_array_equal(first[0][0], again[0][0])
    assert not np.array_equal(first[0][0], other[0][0])
    assert not np.array_equal(first[0][0], first[1][0])  # the two flats of a pair differ


def test_write_flats_headers_pairing_and_overwrite(tmp_path):
    options = dict(pairs=1, size=32, nsteps=1, gain=2.0, read_noise_e=4.0, seed=9)
    paths = write_flats(tmp_path, SENSOR, [1000.0, 3000.0], **options)
    assert len(paths) == 4 and all(path.exists() for path in paths)
    header = fits.getheader(paths[2])
    assert header["EXPTIME"] == 3.0 and header["BUNIT"] == "ADU"
    assert header["SIMGAIN"] == 2.0 and header["SIMNOISE"] == 4.0
    assert header["SENSOR"] == SENSOR and header["SIMLEVEL"] == 3000.0 and header["SEED"] == 9
    pairs = pair_flats(read_flats(paths))
    assert [pair.exptime for pair in pairs] == [1.0, 3.0]
    with pytest.raises(BFPSFFileExistsError, match="4 output file\\(s\\) exist"):
        write_flats(tmp_path, SENSOR, [1000.0, 3000.0], **options)
    before = fits.getdata(paths[0]).copy()
    write_flats(tmp_path, SENSOR, [1000.0, 3000.0], overwrite=True,
                **{**options, "seed": 10})
    assert not np.array_equal(before, fits.getdata(paths[0]))


def test_command_line_writes_flats(tmp_path, capsys):
    argv = ["simulate", "flats", "--sensor", SENSOR, "--levels", "1000", "2000", "--pairs", "1",
            "--size", "32", "--gain", "1.2", "--read-noise", "3", "--nsteps", "1", "--seed", "2",
            "-o", str(tmp_path), "--no-progress"]
    assert main(argv) == 0
    files = sorted(tmp_path.glob("*.fits"))
    assert len(files) == 4
    assert fits.getheader(files[0])["SIMGAIN"] == 1.2
    assert "wrote 4 flats" in capsys.readouterr().out
    assert main(argv) == 1  # refuses to overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0
    assert main(["simulate"]) == 2
    # a flickering lamp (a new user found no option for it: real flats' means scatter by
    # about 1e-3, which the loop takes as their error floor)
    assert main(argv + ["--overwrite", "--lamp-flicker", "0.01"]) == 0
    ratios = [fits.getheader(path)["SIMLAMP"] / fits.getheader(path)["SIMLEVEL"]
              for path in sorted(tmp_path.glob("*.fits"))]
    assert len(set(ratios)) == 4 and 0.95 < min(ratios) and max(ratios) < 1.05
    with pytest.raises(SystemExit):
        main(argv + ["--overwrite", "--lamp-flicker", "0.7"])
    assert ("argument --lamp-flicker: expected a relative rms in [0, 0.5), got '0.7'"
            in capsys.readouterr().err)


@pytest.mark.slow
def test_itl_flats_match_galsim_truth_at_full_size(truth):
    # 512 x 512, two pairs at 100 ke-, 20 steps: sigma(a) = 1.4e-8 per e- (7 % of a(0, 1));
    # variance to 0.2 %.
    flats = simulate_flats(SENSOR, [100_000.0], pairs=2, size=512, gain=GAIN,
                           read_noise_e=NOISE_E, nsteps=20, seed=11)
    results = pair_results(flats)
    mean_e = np.mean([r.mean_adu for r in results]) * GAIN
    a = np.mean([r.cov_adu / (r.var_adu * r.mean_adu) for r in results], axis=0) / GAIN
    error = 1 / (np.sqrt(512**2 * len(results)) * mean_e)
    expected = truth * (1 + truth[0, 0] * mean_e / 3)
    for dy, dx in [(0, 1), (1, 0), (1, 1), (0, 2), (2, 0)]:
        assert abs(a[dy, dx] - expected[dy, dx]) < 3 * error, (dx, dy)
    for result in results:
        variance_e = result.var_adu * GAIN**2
        expected_variance = astier_variance(result.mean_adu * GAIN, truth[0, 0], NOISE_E)
        assert abs(variance_e - expected_variance) < 3 * variance_e * np.sqrt(2 / 512**2)


def test_flats_conserve_charge_as_the_sensor_s_stars_do():
    """GalSim's polygon areas lose c Q^2 on a uniform charge (5.5e-4 at 85 ke- on
    lsst_e2v_50_8), its photon shooting loses nothing: the flats follow the photons."""
    import galsim

    from bfpsf.interop.silicon_truth import silicon_sensor
    from bfpsf.validation.simulate_flats import uniform_area

    sensor = silicon_sensor("lsst_e2v_50_8")
    level = 85_000.0
    direct = sensor.calculate_pixel_areas(galsim.ImageD(np.full((15, 15), level / 2)))
    assert uniform_area(sensor, level / 2) == pytest.approx(direct.array[7, 7], abs=1e-8)  # c Q^2
    assert 1 - uniform_area(sensor, level) == pytest.approx(5.52e-4, rel=0.01)
    # a star of 1e6 e- (peak 54 ke-) through the same sensor keeps its flux
    star = galsim.ImageD(64, 64, scale=1.0)
    galsim.Moffat(beta=3, fwhm=3.0, flux=1e6).drawImage(
        star, method="phot", sensor=galsim.SiliconSensor(name="lsst_e2v_50_8"),
        rng=galsim.BaseDeviate(7), poisson_flux=False)
    wings = 1 - galsim.Moffat(beta=3, fwhm=3.0).drawImage(nx=64, ny=64, scale=1.0).array.sum()
    assert star.array.sum() / 1e6 - 1 == pytest.approx(-wings, abs=2e-5)
    # the flats: sigma of the mean 1.6e-5, the loss they had 1.8e-4 (11 sigma)
    flats = simulate_flats(sensor, [level], pairs=1, size=150, nsteps=5, read_noise_e=0.0,
                           gain=1.0, seed=11)
    means = [image.mean() / level - 1 for image, _, _ in flats]
    sigma = 1 / np.sqrt(level * flats[0][0].size * len(flats))
    assert abs(np.mean(means)) < 4 * sigma, means


def test_sensor_edges_lose_charge_that_the_default_edge_border_leaves_out():
    """Flats drawn through SiliconSensor with the sensor's own edges (margin 0): the edge
    rows and columns lose a fraction of their charge that grows with the flux (boundaries
    pushed outwards by the charge inside), so the whole-frame means bend like a quadratic
    non-linearity, 6.6e-4 to 8.4e-4 at 120 ke- and 6.7 to 8.9 sigma on 96^2 pixels
    (seeds 11-14); the default border of `DEFAULT_EDGE` pixels leaves it out (|t| <= 1.0),
    as cp_pipe's PTC does. A diagnosis had named a gain non-linearity from such flats."""
    from bfpsf.calibration import calibrate
    from bfpsf.diagnosis.observables import flat_observables

    levels = np.linspace(1.5e4, 1.2e5, 8)
    flats = simulate_flats("lsst_e2v_50_8", levels, pairs=1, size=96, nsteps=4, seed=12,
                           gain=GAIN, margin=0)
    curvature = {}
    for edge in (0, None):
        options = {} if edge is None else {"edge": edge}
        calibration = calibrate([image for image, _, _ in flats],
                                exptimes=[exptime for _, exptime, _ in flats], maxlag=2,
                                fit_b="none", n_monte_carlo=0, **options)
        linearity = flat_observables(calibration)[0]
        coefficients, covariance = np.polyfit(linearity.exptime, linearity.mean_e, 2,
                                              w=1 / linearity.mean_err_e, cov="unscaled")
        curvature[edge] = coefficients[0] / np.sqrt(covariance[0, 0])
    assert curvature[0] < -5, curvature
    assert abs(curvature[None]) < 3, curvature
