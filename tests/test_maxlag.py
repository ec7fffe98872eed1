"""``maxlag='auto'``: the largest lag the flats constrain (`bfpsf.calibration.maxlag`).

The under-constrained case of issue 14: a full PTC model fitted on 4 flat pairs. Truth: gain
1.5 e-/ADU and read noise 5 e- (`simulate_flats`). At maxlag 8 these 4 pairs of 128^2 ITL
flats give a gain 28 % high and 68 e- of read noise; the lags beyond the nearest neighbours
carry no measured correlation (ring 2 at 0.4 sigma), and the automatic choice stays at 2.
"""

import json
import re

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration import calibrate
from bfpsf.calibration.covariance import pair_covariance
from bfpsf.calibration.maxlag import choose_maxlag, ring_significance
from bfpsf.calibration.ptc import stack_pairs
from bfpsf.cli import main
from bfpsf.errors import BFPSFValueError
from bfpsf.validation.simulate_flats import simulate_flats

GAIN = 1.5
READ_NOISE = 5.0
UNDER_CONSTRAINED = "the full PTC model is under-constrained by 4 flat pairs"


@pytest.fixture(scope="module")
def four_levels():
    """The issue's case: 4 levels, one pair each, 128^2 SiliconSensor ITL flats (4 s)."""
    flats = simulate_flats("lsst_itl_50_8", [2e4, 4e4, 6e4, 8e4], pairs=1, size=128, nsteps=5,
                           gain=GAIN, read_noise_e=READ_NOISE, seed=0)
    return [image for image, _, _ in flats], [exptime for _, exptime, _ in flats]


def test_auto_keeps_the_four_level_fit_near_truth(four_levels):
    images, exptimes = four_levels
    options = dict(exptimes=exptimes, solve_shifts=False, n_monte_carlo=0)
    auto = calibrate(images, **options)
    fixed = calibrate(images, maxlag=8, **options)
    print(f"auto: maxlag {auto.maxlag}, gain {auto.gain:.4f} +- {auto.gain_err:.4f}, "
          f"noise {auto.noise_e:.2f} e-; maxlag 8: gain {fixed.gain:.4f}, "
          f"noise {fixed.noise_e:.2f} e-; rings {auto.parameters['maxlag_ring_sigma']}")
    assert auto.maxlag == 2 and auto.parameters["maxlag_auto"] is True
    ring = auto.parameters["maxlag_ring_sigma"]
    assert ring[0] < 3 and auto.parameters["maxlag_reason"] == (
        f"lag ring 1 is measured at {ring[0]:.2f} sigma (< 3); raised to the least maxlag 2")
    # the truth within the errors of 4 pairs (gain 1.51 +- 0.20, noise 1.3 +- 740 e-: a
    # PTC from 2e4 e- up does not see 5 e- of read noise); the lags the flats do not
    # constrain drove the noise to 60 e- and the gain to 1.84 at maxlag 8
    assert abs(auto.gain - GAIN) < 2 * auto.gain_err
    assert abs(auto.noise_e - READ_NOISE) < 2 * auto.noise_e_err
    assert fixed.gain / GAIN - 1 > 0.2 and fixed.noise_e > 50
    assert fixed.parameters["maxlag_auto"] is False and fixed.parameters["maxlag"] == 8
    # either way the user is told that 4 pairs under-constrain the full model
    for calibration in (auto, fixed):
        assert calibration.warnings[0].startswith(UNDER_CONSTRAINED)


def test_auto_maxlag_on_the_command_line(four_levels, tmp_path, capsys):
    images, exptimes = four_levels
    paths = []
    for index, (image, exptime) in enumerate(zip(images, exptimes)):
        paths.append(str(tmp_path / f"flat{index}.fits"))
        fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(paths[-1])
    code = main(["calibrate", *paths, "-o", str(tmp_path / "c.fits"), "--json",
                 str(tmp_path / "c.json"), "--n-monte-carlo", "0", "--workers", "1"])
    assert code == 0
    out = capsys.readouterr().out
    # the linearity is said when it is not flagged too (simulated flats: linear)
    assert re.search(r"linearity: [0-9.e-]+ per mil peak to peak \(not flagged: <= 3\)", out)
    summary = json.loads((tmp_path / "c.json").read_text())
    ring = summary["parameters"]["maxlag_ring_sigma"][0]
    assert (f"maxlag 2 (chosen from the data: lag ring 1 is measured at {ring:.2f} sigma (< 3); "
            "raised to the least maxlag 2)") in out
    assert summary["maxlag"] == 2 and np.shape(summary["a"]) == (3, 3)
    assert summary["parameters"]["maxlag_auto"] is True
    assert len(summary["parameters"]["maxlag_ring_sigma"]) == 12   # measured to lag 12
    code = main(["calibrate", *paths, "-o", str(tmp_path / "d.fits"), "--maxlag", "3",
                 "--n-monte-carlo", "0", "--workers", "1"])
    assert code == 0 and "maxlag 3 (given)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["calibrate", *paths, "-o", str(tmp_path / "e.fits"), "--maxlag", "many"])
    assert "argument --maxlag: expected 'auto' or a positive integer, got 'many'" in (
        capsys.readouterr().err)


def _correlated_pair(rng, mean, coefficient, size=96):
    """Two flats whose pixels are correlated at lag (1, 0) only: q + c q shifted along x."""
    flats = []
    for _ in range(2):
        white = rng.normal(0.0, np.sqrt(mean), (size, size + 1))
        flats.append(mean + (white[:, 1:] + coefficient * white[:, :-1])
                     / np.sqrt(1 + coefficient**2))
    return flats


def test_ring_significance_is_calibrated_on_noise():
    """Rings of pure noise: significance |N(0, 1)|; a ring with a correlation: found."""
    rng = np.random.default_rng(5)
    noise = []
    for _ in range(40):
        means = np.array([1e3, 2e3, 3e3, 4e3])
        pairs = [pair_covariance(*_correlated_pair(rng, mean, 5e-5 * mean), maxlag=4)
                 for mean in means]
        data = stack_pairs(pairs)
        significance = ring_significance(data.mean_adu, data.cov_adu, data.npix)
        # ring 1 holds rho(1, 0) = c / (1 + c^2), c = 5e-5 mu: 0.19 at 4e3 ADU, many sigma
        assert significance[0] > 10
        noise.extend(significance[1:])
    noise = np.array(noise)
    # 120 draws of |N(0, 1)|: mean square 1 +- 0.13 (one sigma)
    assert 0.6 < np.mean(noise**2) < 1.4, np.mean(noise**2)
    assert np.mean(noise > 3.0) < 0.02


def _table(means, significance_of, size=6):
    """Covariances (one pair per mean, 1e6 pixel products per lag, V = 1) whose lag rings
    have the given significances: rho = k mu on ring r, k = sigma * (error of the ring mean)."""
    ring = np.maximum.outer(np.arange(size), np.arange(size))
    npix = np.full((means.size, size, size), 1e6)
    slope_err = 1.0 / np.sqrt(np.sum(1e6 * means**2))
    cov = np.zeros((means.size, size, size))
    for radius, sigma in significance_of.items():
        members = ring == radius
        if not members.any():
            continue
        cov[:, members] = (sigma * slope_err / np.sqrt(members.sum())) * means[:, None]
    cov[:, 0, 0] = 1.0
    return means, cov, npix


def test_choose_maxlag_stops_at_the_first_unmeasured_ring_and_bounds():
    rings = {1: 20.0, 2: 8.0, 3: 4.0, 4: 1.0, 5: 5.0}
    choice = choose_maxlag(*_table(np.arange(1.0, 9.0), rings))
    np.testing.assert_allclose(choice.significance, [20, 8, 4, 1, 5])
    assert choice.maxlag == 3 and choice.reason == "lag ring 4 is measured at 1.00 sigma (< 3)"
    # fewer than 8 pairs: the full model is held to 2, the exponential is not
    four = _table(np.arange(1.0, 5.0), rings)
    held = choose_maxlag(*four)
    assert held.maxlag == 2 and held.reason.endswith(
        "; held to 2: 4 pairs under-constrain the full model's a, b and n at each further lag")
    assert choose_maxlag(*four, model="exponential").maxlag == 3
    # every ring measured: the largest lag measured
    choice = choose_maxlag(*_table(np.arange(1.0, 9.0), rings, size=4))
    assert choice.maxlag == 3 and choice.reason == (
        "every measured ring is above 3 sigma; largest lag measured")
    # nothing measured: the least maxlag the shift solvers need
    choice = choose_maxlag(*_table(np.arange(1.0, 9.0), {1: 0.5}))
    assert choice.maxlag == 2 and choice.reason == (
        "lag ring 1 is measured at 0.50 sigma (< 3); raised to the least maxlag 2")


def test_maxlag_argument_is_validated():
    with pytest.raises(BFPSFValueError, match="maxlag must be 'auto' or a positive integer, "
                                              "got 'eight'"):
        calibrate([np.ones((8, 8))] * 2, exptimes=[1.0, 1.0], maxlag="eight")
