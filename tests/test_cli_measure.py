"""``bfpsf measure`` and ``bfpsf slope`` end to end, against GalSim HSM on SiliconSensor spots."""

import json

import numpy as np
import pytest
from astropy.table import Table
from scipy.spatial import cKDTree

from bfpsf.cli import main
from bfpsf.moments.result import moments_from_hsm
from bfpsf.measure.slopes import fit_bf_slope
from bfpsf.validation.simulate_spots import simulate_spots, simulate_star_field, write_image_adu

galsim = pytest.importorskip("galsim")

GAIN = 1.7


@pytest.fixture(scope="module")
def star_image(tmp_path_factory):
    """A star field with colours (no BF) written in ADU with its CATALOG."""
    field = simulate_star_field(shape=(240, 240), n_stars=16, spacing=60,
                                peak_range_e=(3e3, 6e4), seed=21)
    path = tmp_path_factory.mktemp("field") / "field.fits"
    write_image_adu(path, field.image, gain=GAIN, exptime=30.0, catalog=field.truth)
    return path, field


def test_measure_converts_adu_with_the_header_gain(star_image, tmp_path, capsys):
    path, field = star_image
    output = tmp_path / "stars.ecsv"
    summary = tmp_path / "measure.json"
    assert main(["measure", str(path), "-o", str(output), "--color", "g_i",
                 "--json", str(summary)]) == 0
    stars = Table.read(output, format="ascii.ecsv")
    for name in ("x", "y", "flux_e", "peak_e", "mxx", "myy", "mxy", "sigma_x", "sigma_y", "iq",
                 "e1", "e2", "e1_err", "e2_err", "flags", "g_i"):
        assert name in stars.colnames
    assert len(stars) == len(field.truth)
    distance, index = cKDTree(np.stack([field.truth["x"], field.truth["y"]], 1)).query(
        np.stack([stars["x"], stars["y"]], 1))
    # electrons again: peaks within 4 sigma of Poisson (peak + 100 e- sky), colours matched
    pull = (stars["peak_e"] - field.truth["peak_e"][index]) / np.sqrt(
        field.truth["peak_e"][index] + 100.0)
    assert np.max(np.abs(pull)) < 4.0
    np.testing.assert_allclose(stars["g_i"], field.truth["g_i"][index])
    trace = stars["mxx"] + stars["myy"]
    np.testing.assert_allclose(stars["e1"], (stars["mxx"] - stars["myy"]) / trace)
    np.testing.assert_allclose(stars["e2"], 2 * stars["mxy"] / trace)
    result = json.loads(summary.read_text())
    assert result["n_stars"] == len(stars) and result["images"][0]["gain"] == GAIN
    # isolated stars: none on a neighbour's light, and the count is said
    assert result["n_neighbour_light"] == 0
    assert "0 on a bright neighbour's light" in capsys.readouterr().out

    # --gain overrides the header: sizes are unchanged, electrons scale
    other = tmp_path / "stars_gain.ecsv"
    assert main(["measure", str(path), "-o", str(other), "--gain", str(2 * GAIN)]) == 0
    doubled = Table.read(other, format="ascii.ecsv")
    np.testing.assert_allclose(doubled["peak_e"], 2 * stars["peak_e"], rtol=1e-5)
    np.testing.assert_allclose(doubled["iq"], stars["iq"], rtol=1e-5)


def test_measure_refuses_to_overwrite_and_reports_bad_input(star_image, tmp_path, capsys):
    path, _ = star_image
    output = tmp_path / "stars.ecsv"
    output.write_text("keep me")
    assert main(["measure", str(path), "-o", str(output)]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert output.read_text() == "keep me"
    assert main(["measure", str(tmp_path / "missing.fits"), "-o", str(tmp_path / "a.ecsv")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["measure", str(path), "-o", str(tmp_path / "b.ecsv"),
                 "--calib", str(tmp_path / "missing_calib.fits")]) == 1
    assert "calibration file" in capsys.readouterr().err


def test_slope_json_plot_and_psf_hook(star_image, tmp_path, capsys):
    path, _ = star_image
    stars = tmp_path / "stars.ecsv"
    assert main(["measure", str(path), "-o", str(stars), "--color", "g_i"]) == 0
    summary, plot = tmp_path / "slope.json", tmp_path / "slope.png"
    assert main(["slope", str(stars), "--json", str(summary), "--plot", str(plot),
                 "--color", "g_i"]) == 0
    result = json.loads(summary.read_text())
    assert {"x", "y", "iq", "n_stars"} <= set(result)
    for key in ("x", "y", "iq"):
        assert set(result[key]) == {"slope", "slope_err", "intercept", "relative_percent"}
        # no BF in this field: the slope is zero within 4 sigma
        assert abs(result[key]["slope"]) < 4 * result[key]["slope_err"]
    assert result["details"]["colour_fit"]["colour_column"] == "g_i"
    assert plot.stat().st_size > 10_000
    assert main(["slope", str(stars), "--psf", str(tmp_path / "psf.fits")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_slope_psf_says_no_percentage_of_a_slope_consistent_with_zero(tmp_path, capsys):
    """Stars without BF (GalSim's own Moffats, no sensor) measured against a P(F) with BF: the
    measured slope is zero within its errors, and a residual in percent of it is meaningless
    (a new user's BF-free twins printed "+18106 % of the measured slope"); `slope --psf` says
    so, and the pull says what is left."""
    import galsim

    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.shifts import BoundaryShifts

    shifts = BoundaryShifts.from_radial_profile(lambda r: 1.2e-6 * np.exp(-r / 0.8), 5)
    field = simulate_star_field(shape=(320, 320), n_stars=64, spacing=40, fwhm=3.5, beta=3.5,
                                peak_range_e=(3e3, 1.2e5), sky_e=0.0, read_noise_e=5.0, seed=6)
    image = tmp_path / "field.fits"
    write_image_adu(image, field.image, gain=1.0, exptime=30.0)
    psf_path = tmp_path / "psf.fits"
    FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.5, fwhm=3.5), shifts).write(psf_path)
    stars, summary = tmp_path / "stars.ecsv", tmp_path / "slope.json"
    assert main(["measure", str(image), "-o", str(stars), "--gain", "1"]) == 0
    capsys.readouterr()
    assert main(["slope", str(stars), "--psf", str(psf_path), "--json", str(summary)]) == 0
    out = capsys.readouterr().out
    result = json.loads(summary.read_text())
    for key, label in (("x", "sigma_x"), ("y", "sigma_y")):
        raw = result[key]
        assert abs(raw["slope"]) < 2 * raw["slope_err"], raw
        line = next(text for text in out.splitlines() if text.startswith(label)
                    and "residual after P(F)" in text)
        assert "no percentage of it" in line and "% of the measured slope" not in line, line
        # the residual is the model's BF, far beyond its error
        assert result["model_residual"][key]["pull"] < -3


def test_slope_psf_model_residual_removes_the_bf_slope(tmp_path):
    """Stars drawn with bfpsf's own redistribution (BFSensor): the raw slope is significant, the
    slope left after subtracting the sizes P(F) predicts is zero within errors."""
    import galsim

    from bfpsf.interop.galsim_sensor import BFSensor
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.shifts import BoundaryShifts

    # E2V-like strength: a(0,0) ~ -2e-6 per e-, a few percent growth at 100 ke- peak; the
    # serial (east) boundaries move 1.6 times more than the parallel ones, so the stars grow
    # more along x than y and e1 changes with flux.
    radial = BoundaryShifts.from_radial_profile(lambda r: 1.2e-6 * np.exp(-r / 0.8), 5)
    shifts = BoundaryShifts(radial.north * 0.8, radial.east * 1.3, check=False)
    field = simulate_star_field(shape=(320, 320), n_stars=64, spacing=40, fwhm=3.5, beta=3.5,
                                peak_range_e=(3e3, 1.2e5), sensor=BFSensor(shifts),
                                sky_e=0.0, read_noise_e=5.0, seed=5)
    image = tmp_path / "field.fits"
    write_image_adu(image, field.image, gain=1.0, exptime=30.0)
    psf_path = tmp_path / "psf.fits"
    psf = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.5, fwhm=3.5), shifts)
    # a calibration uncertainty of 5 % on the amplitude of the shifts
    psf.shift_samples = tuple(shifts.scaled(factor) for factor in (0.95, 1.0, 1.05))
    psf.write(psf_path)
    stars, summary = tmp_path / "stars.ecsv", tmp_path / "slope.json"
    assert main(["measure", str(image), "-o", str(stars), "--gain", "1"]) == 0
    assert main(["slope", str(stars), "--psf", str(psf_path), "--json", str(summary),
                 "--psf-plot", str(tmp_path / "diagnostics.png")]) == 0
    assert (tmp_path / "diagnostics.png").stat().st_size > 10_000
    result = json.loads(summary.read_text())
    assert result["prediction"]["n_samples"] == 3
    for key in ("x", "y"):
        raw, residual = result[key], result["model_residual"][key]
        predicted = result["prediction"][key]
        assert set(residual) == {"slope", "slope_err", "intercept", "relative_percent",
                                 "slope_err_total", "pull", "percent_of_raw"}
        assert residual["percent_of_raw"] == pytest.approx(100 * residual["slope"]
                                                           / raw["slope"])
        assert raw["slope"] > 5 * raw["slope_err"]
        # the residual is consistent with zero (4 sigma) and far below the raw slope
        assert abs(residual["slope"]) < 4 * residual["slope_err"]
        assert abs(residual["slope"]) < 0.25 * raw["slope"]
        # the prediction carries the calibration error: 5 % of the slope (samples 0.95-1.05)
        assert abs(predicted["slope"] - raw["slope"]) < 4 * np.hypot(raw["slope_err"],
                                                                     predicted["slope_err"])
        assert 0.03 < predicted["slope_err"] / predicted["slope"] < 0.07
        assert residual["slope_err_total"] > residual["slope_err"]
        assert residual["pull"] == pytest.approx(residual["slope"] / residual["slope_err_total"])
    for key in ("e1", "e2"):
        assert set(result[key]) == {"slope", "slope_err", "intercept"}
        # the ellipticity residuals carry the calibration's error too (the prediction's)
        assert set(result["model_residual"][key]) == {"slope", "slope_err", "intercept",
                                                      "slope_err_total", "pull"}
        assert set(result["prediction"][key]) == {"slope", "slope_err"}
    # e1 grows with flux (x broadens more), which the model explains; e2 does not move.
    raw, residual = result["e1"], result["model_residual"]["e1"]
    assert raw["slope"] > 5 * raw["slope_err"]
    assert abs(residual["slope"]) < 4 * residual["slope_err"]
    assert abs(residual["slope"]) < 0.25 * raw["slope"]
    assert abs(result["e2"]["slope"]) < 4 * result["e2"]["slope_err"]


def _slopes_against_hsm(tmp_path, peaks, n_per_level, seed):
    """bfpsf measure + slope on a mosaic of SiliconSensor spots, and HSM on the same stamps."""
    spots = simulate_spots(peaks_e=peaks, n_per_level=n_per_level, stamp_size=40, seed=seed,
                           read_noise_e=5.0)
    image, truth = spots.mosaic(margin=8)
    path = tmp_path / "spots.fits"
    write_image_adu(path, image, gain=GAIN)
    stars_path, summary = tmp_path / "spots.ecsv", tmp_path / "spots.json"
    assert main(["measure", str(path), "-o", str(stars_path)]) == 0
    assert main(["slope", str(stars_path), "--json", str(summary)]) == 0
    result = json.loads(summary.read_text())
    stars = Table.read(stars_path, format="ascii.ecsv")
    assert np.all(stars["flags"] == 0) and len(stars) == len(truth)
    _, index = cKDTree(np.stack([truth["x"], truth["y"]], 1)).query(
        np.stack([stars["x"], stars["y"]], 1))
    hsm_sizes = []
    for stamp in spots.stamps[truth["stamp"][index]]:
        mxx, myy, _, _, _ = moments_from_hsm(galsim.hsm.FindAdaptiveMom(galsim.ImageD(stamp)))
        hsm_sizes.append((np.sqrt(mxx), np.sqrt(myy)))
    hsm_sizes = np.array(hsm_sizes)
    hsm = {axis: fit_bf_slope(stars["peak_e"], hsm_sizes[:, column],
                              size_err=stars[f"sigma_{axis}_err"])
           for column, axis in enumerate(("x", "y"))}
    return result, hsm


def test_slope_agrees_with_hsm_on_silicon_spots(tmp_path):
    # quick variant: 8 spots. Same stamps, two implementations of the same estimator; the
    # local background and stamp cut are the only differences
    result, hsm = _slopes_against_hsm(tmp_path, (1e4, 4e4, 8e4, 1.2e5), 2, seed=4)
    for axis in ("x", "y"):
        assert abs(result[axis]["slope"] - hsm[axis].slope) < result[axis]["slope_err"]
        # and BF is there: lsst_e2v_50_8 broadens spots by a few 0.01 pixel per 100 ke-
        assert 0.01 < result[axis]["slope"] < 0.08


@pytest.mark.slow
def test_slope_agrees_with_hsm_on_silicon_spots_full(tmp_path):
    # full variant: 60 spots from 5 to 130 ke- (G15 stays below blooming at ~130 ke-)
    result, hsm = _slopes_against_hsm(tmp_path, (5e3, 2e4, 4e4, 6e4, 8e4, 1e5, 1.3e5), 9,
                                      seed=5)
    for axis in ("x", "y"):
        assert abs(result[axis]["slope"] - hsm[axis].slope) < result[axis]["slope_err"]
    # GalSim's E2V sensor: the parallel (y) slope exceeds the serial one, as G15 table
    # xy_ccd_comp finds for the E2V-250
    assert result["y"]["slope"] > result["x"]["slope"]
