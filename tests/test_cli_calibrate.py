"""``bfpsf calibrate``: files in, calibration / JSON / plots out, never overwriting silently."""

import json

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration.product import Calibration
from bfpsf.cli import main
from bfpsf.validation.simulate_flats import write_flats

GAIN = 1.5
JSON_KEYS = {"gain", "gain_err", "noise_e", "a", "a_err", "maxlag", "n_pairs", "turnoff_e",
             "linearity_max_frac_residual", "pedestal"}


@pytest.fixture(scope="module")
def flat_files(tmp_path_factory):
    """Small SiliconSensor ITL flats (64 x 64, 8 levels): a few seconds of GalSim."""
    directory = tmp_path_factory.mktemp("flats")
    levels = [100.0, 2e4, 4e4, 6e4, 8e4, 1e5, 1.3e5, 1.6e5]
    return write_flats(directory, "lsst_itl_50_8", levels, size=64, nsteps=10, gain=GAIN, seed=3)


@pytest.fixture(scope="module")
def calibrated(flat_files, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    paths = {"calib": out / "calib.fits", "json": out / "calib.json", "plots": out / "plots"}
    code = main(["calibrate", *map(str, flat_files), "-o", str(paths["calib"]), "--maxlag", "3",
                 "--json", str(paths["json"]), "--plots", str(paths["plots"]),
                 "--n-monte-carlo", "20"])
    assert code == 0
    return paths


def test_json_summary(calibrated):
    summary = json.loads(calibrated["json"].read_text())
    assert JSON_KEYS <= set(summary)
    assert summary["maxlag"] == 3 and summary["n_pairs"] == 8
    assert np.shape(summary["a"]) == (4, 4) and np.shape(summary["a_err"]) == (4, 4)
    assert np.shape(summary["pedestal"]) == (4, 4)
    # 8 pairs of 64 x 64 pixels: the gain is known to ~1.5 %; allow 4 sigma
    assert abs(summary["gain"] - GAIN) < 4 * summary["gain_err"]
    # the self-response is negative (a pixel shrinks as it fills) and measured here
    assert summary["a"][0][0] < 0


def test_file_matches_json(calibrated):
    calibration = Calibration.read(calibrated["calib"])
    summary = json.loads(calibrated["json"].read_text())
    assert calibration.gain == summary["gain"]
    np.testing.assert_array_equal(calibration.a, np.array(summary["a"]))
    assert len(calibration.inputs) == 16


def test_plots_are_written(calibrated):
    for name in ("ptc.png", "correlation_map.png", "area_profile.png"):
        path = calibrated["plots"] / name
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_refuses_to_overwrite(flat_files, calibrated, capsys):
    before = calibrated["calib"].read_bytes()
    code = main(["calibrate", *map(str, flat_files), "-o", str(calibrated["calib"])])
    assert code == 1
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert calibrated["calib"].read_bytes() == before


def test_missing_exptime_is_named(tmp_path, capsys):
    path = tmp_path / "no_exptime.fits"
    fits.PrimaryHDU(np.ones((16, 16), dtype=np.float32)).writeto(path)
    code = main(["calibrate", str(path), "-o", str(tmp_path / "c.fits")])
    assert code == 1
    assert "no_exptime.fits: header keyword EXPTIME is missing" in capsys.readouterr().err


def test_undetermined_read_noise_is_said(calibrated, capsys):
    """Flats far above the read noise leave it undetermined (a new user's ITL flats from
    4 ke- gave 0.000 +- 5.870 e-, stored and used by photometry without a word): the
    summary says so, and says nothing when it is measured."""
    import dataclasses

    from bfpsf.calibration.product import Calibration
    from bfpsf.cli.calibrate import _print

    calibration = Calibration.read(calibrated["calib"])
    for noise, err, warned in ((0.0, 5.87, True), (5.0, 0.3, False)):
        _print("", dataclasses.replace(calibration, noise_e=noise, noise_e_err=err))
        out = capsys.readouterr().out
        assert ("WARNING: these flats do not determine the read noise" in out) is warned
        if warned:
            assert "(0.000 +- 5.870 e-)" in out and "--read-noise" in out
