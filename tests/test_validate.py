"""End-to-end validation on GalSim SiliconSensor (bfpsf validate) and the two CLI commands."""

import dataclasses
import json

import numpy as np
import pytest

from bfpsf.cli import main
from bfpsf.validation.validate import FULL, QUICK, TRUTH_LABEL, validate


#: A very small run for the quick test: 4 levels x 9 phases of FWHM 3 px spots, tiny flats.
TINY = dataclasses.replace(QUICK, peaks_e=(1e4, 5e4, 9e4, 1.2e5), n_per_level=9,
                           flat_levels_e=(2e4, 5e4, 8e4, 1.1e5), flat_size=64, flat_nsteps=5)


@pytest.fixture(scope="module")
def tiny_run():
    # SiliconSensor landing shifts: a diagnostic of the PSF model alone (the flats path is
    # tested in test_flats_to_psf.py)
    return validate(TINY, shifts_for_model="truth")


def test_validate_runs_every_stage(tiny_run):
    for stage in ("calibration", "area", "slopes", "prediction", "psf", "inverse", "diagnose"):
        assert tiny_run[stage]["available"], (stage, tiny_run[stage])
    assert tiny_run["slopes"]["n_flagged"] == 0
    for key in ("residual_before", "candidates", "selected", "residual_after"):
        assert key in tiny_run["diagnose"]


def test_validate_physics(tiny_run):
    slopes = tiny_run["slopes"]
    # SiliconSensor spots broaden with flux, faster in Y (parallel) on ITL (G15 table 1)
    assert slopes["slope_x"] > 0 and slopes["slope_y"] > 0
    truth_row = [row for row in tiny_run["prediction"]["rows"]
                 if row["shifts"] == TRUTH_LABEL][0]
    # the G15 prediction from SiliconSensor's own shifts matches the measured slope; 36 spots
    # measure it to ~10 %, so allow 30 %
    assert 0.7 < truth_row["predicted_over_measured_x"] < 1.3
    assert 0.7 < truth_row["predicted_over_measured_y"] < 1.3
    # the BF-free twins measure the same slope as the spots alone, far more precisely
    for axis in "xy":
        paired, paired_err = slopes[f"paired_slope_{axis}"], slopes[f"paired_slope_{axis}_err"]
        assert abs(paired - slopes[f"slope_{axis}"]) < 3 * slopes[f"slope_{axis}_err"]
        assert paired_err < 0.3 * slopes[f"slope_{axis}_err"]
    psf = tiny_run["psf"]
    # P(F) with SiliconSensor's own shifts: the paired residual is a few % of the raw slope at
    # most (36 spots), the pixel inverse likewise
    for stage in (psf, tiny_run["inverse"]):
        for axis in "xy":
            assert abs(stage[f"residual_slope_{axis}_percent"]) < 10
            assert (stage[f"residual_slope_{axis}_percent_err"]
                    < 0.5 * stage[f"residual_slope_{axis}_unpaired_percent_err"])
    # a static PSF made from the bright spots biases the faint ones by several mmag (bright
    # minus faint > 0: the faint come out too bright); P(F) removes most of it (noise of 9
    # spots per level: ~0.5 mmag). Uniform weights (sky-limited limit): measured static +6.7,
    # P(F) +0.26 mmag.
    assert psf["photometry_bias_static_mmag"] > 2.0
    assert abs(psf["photometry_bias_flux_dependent_mmag"]) < 0.4 * psf[
        "photometry_bias_static_mmag"]
    # photutils with the weights of a 1000 e- sky: a smaller static bias, the bright spots'
    # own Poisson variance weighing their core less (measured static +1.6, P(F) -0.07 mmag;
    # with the sky-free Poisson weights the static bias would vanish)
    assert psf["photometry_bias_photutils_static_mmag"] > 1.0
    assert abs(psf["photometry_bias_photutils_flux_dependent_mmag"]) < 0.4 * psf[
        "photometry_bias_photutils_static_mmag"]


@pytest.mark.slow
def test_validate_full():
    """The full run (about 30 minutes on 2 cores): the acceptance numbers of issue 5/6."""
    result = validate(FULL)
    psf = result["psf"]
    # P(F) with the flats' shifts leaves at most a few % of the raw slope beyond what the
    # flats' calibration error allows (2 pairs x 6 levels of 384^2 know the slope to about
    # 8 %): the bound had held the spots' statistics alone (0.2 %), and passed by the luck of
    # one flat draw (103 % of the twin slope); the charge-conserving draw gives 87 %
    row = next(row for row in result["prediction"]["rows"]
               if row["shifts"] == result["model_shifts"])
    for axis in "xy":
        calibration = 100 * row[f"predicted_slope_{axis}_err"] / abs(
            result["slopes"][f"slope_{axis}"])
        print(f"{axis}: residual after P(F) {psf[f'residual_slope_{axis}_percent']:+.1f} +- "
              f"{psf[f'residual_slope_{axis}_percent_err']:.1f} % of raw, calibration "
              f"+- {calibration:.1f} %")
        assert abs(psf[f"residual_slope_{axis}_percent"]) < 2 + 3 * np.hypot(
            psf[f"residual_slope_{axis}_percent_err"], calibration)
    assert abs(psf["photometry_bias_flux_dependent_mmag"]) < 1.0
    assert psf["photometry_bias_static_mmag"] > 3.0
    # photutils, weights of a 1000 e- sky: measured static +2.2, P(F) +0.3 +- 0.6 mmag
    assert abs(psf["photometry_bias_photutils_flux_dependent_mmag"]) < 1.0
    assert psf["photometry_bias_photutils_static_mmag"] > 1.0
    area = result["area"]
    pulls = [abs(p) for p in area["pull"] if p is not None]
    assert max(pulls) < 4


def test_cli_validate_json_and_report(tmp_path, capsys):
    args = ["validate", "--quick", "--peaks", "1e4", "6e4", "1.2e5", "--spots-per-level", "4",
            "--flat-size", "128",
            "--flat-levels", "2e4", "5e4", "8e4", "1.1e5", "--no-progress",
            "--json", str(tmp_path / "v.json"), "--report", str(tmp_path / "report")]
    code = main(args)
    summary = json.loads((tmp_path / "v.json").read_text())
    assert {"slopes", "prediction", "psf", "inverse", "diagnose", "area"} <= set(summary)
    # the residual after P(F) is printed with the flats' own calibration error beside it (a
    # new user read a +42 +- 0.4 % residual of a four-level flat set as a 100 sigma failure)
    row = next(row for row in summary["prediction"]["rows"]
               if row["shifts"] == summary["model_shifts"])
    error_x = 100 * row["predicted_slope_x_err"] / abs(summary["slopes"]["slope_x"])
    captured = capsys.readouterr()
    assert (f"(the shifts of the flats calibration carry their own error: +- {error_x:.1f} % "
            f"in X") in captured.out
    # its spots' photometry adds a noiseless sky by design: no read-noise warning for each
    # spot (a new user's `validate --quick` printed 88 of them)
    assert "read noise" not in captured.err, captured.err[:300]
    # and the loop's line says what "nothing" means here (a new user read it as a failure)
    line = next(line for line in captured.out.splitlines() if "closed loop" in line)
    assert line.startswith("closed loop (bfpsf diagnose) selected: ")
    assert ("as it should" in line) == (summary["diagnose"]["selected"] == [])
    # and the run ends on a verdict (a new user saw no pass or fail), its exit code with it:
    # four flat pairs of 128^2 are too few (3 seeds of 4 predict a BF of the wrong sign, 3.3
    # to 5.7 sigma off, and P(F) makes the photometry worse than a static PSF), and whichever
    # way this seed goes, the verdict says what it found
    from bfpsf.validation.verdict import verdict_failures

    assert summary["verdict"]["failures"] == verdict_failures(summary)
    assert code == (0 if summary["verdict"]["passed"] else 1)
    lines = captured.out.splitlines()
    index = next(index for index, line in enumerate(lines) if line.startswith("verdict: "))
    assert lines[index].startswith("verdict: PASS: " if summary["verdict"]["passed"] else
                                   "verdict: FAIL: " + summary["verdict"]["failures"][0])
    # a failed run is followed by what the flats' calibration said of itself (this set: its
    # shifts' sign unphysical, their amplitude poorly determined)
    said = [line.split("warned: ", 1)[1] for line in lines[index + 1:]]
    assert said == (summary["calibration"]["warnings"] if not summary["verdict"]["passed"]
                    else [])
    text = (tmp_path / "report" / "report.md").read_text()
    assert "Truth a vs recovered" in text and "Residual slope" in text
    assert (tmp_path / "report" / "sizes.png").stat().st_size > 1000
    # outputs are never overwritten without --overwrite
    assert main(args) == 1
    assert "pass --overwrite to replace it" in capsys.readouterr().err


def test_cli_diagnose_measured(tmp_path, capsys):
    out = tmp_path / "d.json"
    assert main(["diagnose", "--measured", "bot_r22_s11", "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert list(summary)[:4] == ["residual_before", "candidates", "selected", "residual_after"]
    assert np.isfinite(summary["residual_before"]["slope_x_percent"])
    capsys.readouterr()
    assert main(["diagnose", "--measured", "bot_r22_s11", "--json", str(out)]) == 1
    assert capsys.readouterr().err == (f"bfpsf diagnose: error: {out} exists; pass --overwrite "
                                       "to replace it\n")


def test_cli_diagnose_lists_and_refuses_unknown_measured_sets(capsys):
    from bfpsf.data import measured_sets

    assert main(["diagnose", "--list-measured"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in listed] == list(measured_sets())
    assert main(["diagnose", "--measured", "nosuch"]) == 1
    assert capsys.readouterr().err == (
        "bfpsf diagnose: error: unknown measured data set 'nosuch'; known: itl3800c002, "
        "bot_r22_s11, poisson_ccd, cp_pipe_r22_s11, sitcomtn148 (bfpsf diagnose "
        "--list-measured)\n")


def test_cli_diagnose_needs_inputs(capsys):
    assert main(["diagnose"]) == 1
    assert "give --flats and --images" in capsys.readouterr().err


def test_cli_diagnose_images_mode(tmp_path, capsys):
    """Flats and star images as FITS: calibrate, measure the stars, run the loop. The stars
    carry BF from bfpsf's BFSensor with SiliconSensor's shifts; 128^2 flats give a noisy
    calibration (without the b term), so only the chain and its outputs are checked here (the physics of the loop
    is in test_diagnose.py)."""
    from bfpsf.interop.galsim_sensor import BFSensor
    from bfpsf.interop.silicon_truth import silicon_boundary_shifts
    from bfpsf.validation.simulate_flats import write_flats
    from bfpsf.validation.simulate_spots import simulate_star_field, write_image_adu

    flats = write_flats(tmp_path / "flats", "lsst_itl_50_8", (2e4, 5e4, 8e4, 1.1e5),
                        size=128, nsteps=5, gain=1.5)
    sensor = BFSensor(silicon_boundary_shifts("lsst_itl_50_8"))
    field = simulate_star_field(shape=(240, 240), n_stars=36, spacing=40, fwhm=3.0,
                                sensor=sensor, seed=3)
    image = tmp_path / "stars.fits"
    write_image_adu(image, field.image, gain=1.5)
    out = tmp_path / "d.json"
    code = main(["diagnose", "--flats", *map(str, flats), "--images", str(image), "--beta",
                 "3.5", "--bins", "6", "--no-fit-b", "--json", str(out), "--report", str(tmp_path / "r")])
    assert code == 0
    # the flats' calibration warns as `bfpsf calibrate` does (four 128^2 levels: the shifts'
    # amplitude is poorly determined)
    assert "WARNING: flats calibration: amplitude of the boundary shifts poorly determined" in (
        capsys.readouterr().err)
    summary = json.loads(out.read_text())
    assert {"residual_before", "candidates", "selected", "residual_after"} <= set(summary)
    # the flats give the linearity and correlation observables too
    assert "linearity_chi2_per_point" in summary["residual_before"]
    assert "correlations_chi2_per_point" in summary["residual_before"]
    assert (tmp_path / "r" / "report.md").exists()
    # which exposures' own P0 (the star residual's) did not converge is said apart from the
    # loop's P0 (`p0_converged`); the one exposure's converged here
    assert summary["inputs"]["star_residual_p0"] == "per exposure"
    assert summary["inputs"]["star_residual_p0_not_converged"] == []


def test_the_verdict_names_what_fails(tiny_run):
    """`verdict_failures` on a run doctored one way at a time: a false detection, a
    prediction 4 sigma off, a residual beyond its errors, P(F) no better than a static PSF."""
    import copy

    from bfpsf.validation.verdict import verdict_failures

    assert verdict_failures(tiny_run) == []
    run = copy.deepcopy(tiny_run)
    run["diagnose"]["selected"] = ["gain_nonlinearity"]
    assert verdict_failures(run) == ["the loop named gain_nonlinearity (a false detection)"]
    run = copy.deepcopy(tiny_run)
    row = next(row for row in run["prediction"]["rows"] if row["shifts"] == run["model_shifts"])
    row["pull_y"] = 4.0
    assert [text.split(" slope")[0] for text in verdict_failures(run)] == ["Y"]
    run = copy.deepcopy(tiny_run)
    run["psf"]["residual_slope_x_percent"] = 1e3
    assert verdict_failures(run)[0].startswith("P(F) leaves +1000.0 % of the raw X slope")
    run = copy.deepcopy(tiny_run)
    run["psf"]["photometry_bias_flux_dependent_mmag"] = run["psf"]["photometry_bias_static_mmag"]
    assert "is not below the static PSF's" in verdict_failures(run)[0]
