"""The loop's result used by ``bfpsf psf``: E2V SiliconSensor flats and spots, the loop fitted on
half the exposures (``diagnose --output-calib``), P(F) fitted with the refined calibration on
the other half and judged there (``slope --psf``, ``photometry``).

The loop's model spot is the P0 that ``bfpsf psf`` fits (from the exposures the loop fits only),
evaluated at the stars' measured fluxes as ``slope --psf`` evaluates P(F): what the loop finds
is then what P(F) needs. A Moffat matched to the sizes and fluxes from the centred peak
fraction overshot the BF scale by 9 % (the held-out residual after ``--output-calib`` was
-10 % of raw instead of 0).

The quick test runs in CI (3 levels, 4 exposures); `test_output_calib_then_psf_full` is the
acceptance of issue 11 (6 levels, 16 exposures, 432 held-out spots; slow).
"""

import json

import numpy as np
import pytest

from bfpsf.diagnosis.spot_model import flux_of_peak
from bfpsf.errors import BFPSFValueError

SENSOR = "lsst_e2v_50_8"
GAIN = 1.5


def test_flux_of_peak_recovers_a_quadratic_relation():
    peak = np.linspace(1e3, 1.2e5, 40)
    flux = 16.4 * peak + 1.06e-5 * peak ** 2
    assert flux_of_peak(peak, flux) == pytest.approx((16.4, 1.06e-5), rel=1e-9)
    with pytest.raises(BFPSFValueError, match="only 2 stars"):
        flux_of_peak([1.0, 2.0, np.nan], [1.0, 2.0, 3.0])


def _flats(directory, n_levels, size, seed=3):
    """One pair per level of SiliconSensor flats with 0.1 % lamp flicker, as FITS (ADU)."""
    from astropy.io import fits

    from bfpsf.validation.simulate_flats import simulate_flats

    paths = []
    flats = simulate_flats(SENSOR, np.linspace(1e4, 1.2e5, n_levels), pairs=1, size=size,
                           nsteps=4, seed=seed, gain=GAIN, lamp_jitter=1e-3)
    for index, (image, exptime, _) in enumerate(flats):
        paths.append(directory / f"flat{index:02d}.fits")
        fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(paths[-1])
    return paths


def _spots(directory, peaks, n_exposures):
    """Exposures of Moffat spots (FWHM 3 px, beta 3) at 9 sub-pixel phases per level, sky
    50 e- (subtracted) and read noise 5 e-, as FITS (ADU), with their truth tables."""
    from astropy.io import fits

    from bfpsf.validation.simulate_spots import simulate_spots

    grid = (np.arange(3) + 0.5) / 3 - 0.5
    offsets = np.array([(x, y) for y in grid for x in grid])
    paths, truths = [], []
    for exposure in range(n_exposures):
        spots = simulate_spots(sensor=SENSOR, fwhm=3.0, beta=3.0, peaks_e=peaks, n_per_level=9,
                               stamp_size=24, seed=10 + exposure, sky_e=50.0, read_noise_e=5.0,
                               offsets=offsets)
        image, truth = spots.mosaic(margin=8)
        paths.append(directory / f"spots{exposure:02d}.fits")
        fits.PrimaryHDU(image / GAIN, header=fits.Header({"EXPTIME": 1.0})).writeto(paths[-1])
        truths.append(truth)
    return paths, truths


def _loop_then_psf(tmp_path, flats, images, truths, n_bins):
    """diagnose --output-calib on half the exposures, then psf / measure / slope /
    photometry on the other half with the flats' and the refined calibration: the held-out
    slope residual (% of raw, with its error) and the photometry bias faint - bright (mmag)."""
    from bfpsf.calibration import calibrate
    from bfpsf.cli import main

    sky = ["--background", "0"]  # the simulation subtracted its sky
    cal = tmp_path / "cal.fits"
    calibrate([str(p) for p in flats], maxlag=3, fit_b=False, n_monte_carlo=30).write(cal)
    refined, summary = tmp_path / "refined.fits", tmp_path / "diagnose.json"
    assert main(["diagnose", "--flats", *map(str, flats), "--images", *map(str, images),
                 "--beta", "3", "--no-fit-b", "--maxlag", "3", "--bins", str(n_bins), *sky,
                 "--output-calib", str(refined), "--json", str(summary)]) == 0
    loop = json.loads(summary.read_text())
    held = loop["holdout"]["heldout_images"]
    assert set(held).isdisjoint(loop["holdout"]["fit_images"])
    assert main(["measure", *held, "--calib", str(cal), "-o", str(tmp_path / "stars.ecsv")]) == 0
    held_truth = [truths[[str(p) for p in images].index(path)] for path in held]
    out = {"loop": loop}
    for label, calib, options in (("flats", cal, []), ("refined", refined, []),
                                  ("static", cal, ["--no-bf"])):
        psf = tmp_path / f"psf_{label}.fits"
        assert main(["psf", *held, "--calib", str(calib), "-o", str(psf), *sky, *options,
                     "--json", str(tmp_path / f"psf_{label}.json")]) == 0
        assert main(["slope", str(tmp_path / "stars.ecsv"), "--psf", str(psf),
                     "--json", str(tmp_path / f"slope_{label}.json")]) == 0
        slopes = json.loads((tmp_path / f"slope_{label}.json").read_text())
        residual = {axis: (100 * slopes["model_residual"][axis]["slope"] / slopes[axis]["slope"],
                           100 * slopes["model_residual"][axis]["slope_err"]
                           / slopes[axis]["slope"]) for axis in ("x", "y")}
        phot = tmp_path / f"phot_{label}.ecsv"
        assert main(["photometry", *held, "--psf", str(psf), "-o", str(phot), *sky,
                     "--read-noise", "8.66", *(["--static"] if label == "static" else [])]) == 0
        out[label] = {"residual": residual, "bias": _faint_minus_bright(phot, held, held_truth),
                      "psf": json.loads((tmp_path / f"psf_{label}.json").read_text())}
        print(f"{label}: X {residual['x'][0]:+.1f} +- {residual['x'][1]:.1f} %, "
              f"Y {residual['y'][0]:+.1f} +- {residual['y'][1]:.1f} % of raw; photometry "
              f"faint - bright {out[label]['bias'][0]:+.2f} +- {out[label]['bias'][1]:.2f} mmag")
    out["calibrations"] = (cal, refined)
    return out


def _faint_minus_bright(path, images, truths):
    """Faint minus bright (first and last level) of -2.5 log10(flux_fit / true flux), mmag,
    with its error; every truth spot is matched to the nearest fitted star."""
    from astropy.table import Table

    table = Table.read(path)
    ratios = {}
    for image, truth in zip(images, truths):
        fitted = table[table["image"] == image]
        for row in truth:
            distance = np.hypot(fitted["x_fit"] - row["x"], fitted["y_fit"] - row["y"])
            nearest = int(np.argmin(distance))
            assert distance[nearest] < 1.0 and fitted["flags"][nearest] == 0
            ratios.setdefault(int(row["level"]), []).append(
                fitted["flux_fit"][nearest] / row["flux_e"])
    faint, bright = (np.array(ratios[level]) for level in (min(ratios), max(ratios)))
    bias = -2500 * np.log10(faint.mean() / bright.mean())
    error = 2500 / np.log(10) * np.hypot(faint.std(ddof=1) / faint.mean() / np.sqrt(faint.size),
                                         bright.std(ddof=1) / bright.mean()
                                         / np.sqrt(bright.size))
    return float(bias), float(error)


def test_loop_model_predicts_what_psf_predicts(quick_inputs):
    """The loop's spot model and the P(F) of ``bfpsf psf`` give the same BF size growth for
    the same shifts (the condition for ``--output-calib`` to transfer): the model spot is the
    P0 fitted from the loop's exposures only, evaluated at the stars' measured fluxes. 3
    levels (3, 60, 120 ke- peak), 2 exposures (one fitted, one held out), small flats. The
    matched Moffat at the centred-peak fluxes (the loop's model before) misses by more."""
    from bfpsf.calibration import calibrate
    from bfpsf.diagnosis.observables import matched_profile, observables_from_images
    from bfpsf.diagnosis.spot_model import SpotForwardModel
    from bfpsf.measure.model_slopes import model_size_increments

    flats, images, _ = quick_inputs
    images = images[:2]
    cal = calibrate([str(p) for p in flats], maxlag=3, fit_b=False, n_monte_carlo=0)
    observables = observables_from_images([], images, calibration=cal, beta=3.0, n_bins=3,
                                          background=0.0)
    model = observables.spot_model
    assert observables.meta["p0_exposures"] == [0]  # exposure 1 is held out
    assert observables.meta["p0_converged"]
    peaks = np.unique(observables.sizes.peak_e)
    sigma_x0, sigma_y0 = (float(v[0]) for v in model.sizes([1.0]))
    moffat = SpotForwardModel(matched_profile(sigma_x0, sigma_y0, beta=3.0), cal.shifts)
    for scale in (1.0, 1.3):
        shifts = cal.shifts.scaled(scale)
        loop = np.array(model.sizes(peaks, shifts=shifts)) - np.array(
            model.sizes([1.0], shifts=shifts))
        psf = model_size_increments(model.base_psf.with_shifts(shifts), model.fluxes(peaks))
        expected = np.array([psf["x"], psf["y"]])
        np.testing.assert_allclose(loop[:, -1], expected[:, -1], rtol=0.03)
        before = np.array(moffat.sizes(peaks, shifts=shifts)) - np.array(
            moffat.sizes([1.0], shifts=shifts))
        print(scale, loop[:, -1] / expected[:, -1], before[:, -1] / expected[:, -1])
        assert np.all(np.abs(before[:, -1] / expected[:, -1] - 1) > 0.05)


@pytest.fixture(scope="module")
def quick_inputs(tmp_path_factory):
    """The quick tests' flats (8 levels, 128^2) and 4 exposures of 3 levels, as FITS, made
    once: `test_loop_model_predicts_what_psf_predicts` takes the first 2 exposures."""
    directory = tmp_path_factory.mktemp("loop_inputs")
    return (_flats(directory, 8, 128), *_spots(directory, (3e3, 6e4, 1.2e5), 4))


def test_p0_of_one_exposure_of_few_phases_settles(quick_inputs):
    """P0 from one exposure of 27 spots at 3 x 3 sub-pixel phases (what ``diagnose
    --output-calib`` fits per held-out exposure): exposure 1 diverged on its second step
    with free positions (chi-square x40) and kept an iterate 0.029 of the peak from the
    next; exposure 3 crept for 40 iterations at 0.0013. Going back to the best iterate with
    the positions fixed and half the step, and halving the step when the change grows with
    the positions fixed, settles both (measured: 0.00033 after 39 iterations, converged in
    14)."""
    from astropy.io import fits

    from bfpsf.measure.neighbours import isolated_stars
    from bfpsf.model.psf_fit import DEFAULT_SIZE, fit_psf
    from bfpsf.shifts import BoundaryShifts

    shifts = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
    for path in (quick_inputs[1][1], quick_inputs[1][3]):
        image = fits.getdata(path) * GAIN
        positions, _, neighbours = isolated_stars(image, DEFAULT_SIZE)
        fit = fit_psf([image], [positions], shifts, read_noise=8.66, neighbours=[neighbours])
        assert len(positions) == 27
        assert fit.converged or fit.changes[-1] < 2 * 3e-4, (path, fit.changes[-3:])


def test_output_calib_then_psf_cli_quick(tmp_path, quick_inputs):
    """The user path in CI: ``diagnose --output-calib`` on 2 of 4 exposures (3 levels), then
    ``psf --calib REFINED`` on the other 2: the refinement recorded is the one ``psf`` applies,
    the shifts are the flats' times (1 + s) with the split d moved (`split_shifts`), and the held-out residual is within the errors
    of 54 spots (small flats: their BF amplitude error is large and the loop may or may not
    confirm a scale on so few spots)."""
    from bfpsf.calibration.product import Calibration
    from bfpsf.diagnosis.catalogue import split_shifts

    flats, images, truths = quick_inputs
    out = _loop_then_psf(tmp_path, flats, images, truths, n_bins=3)
    cal, refined = (Calibration.read(path) for path in out["calibrations"])
    record = refined.refinement
    assert sorted(record["applied"]) == out["refined"]["psf"]["refinement_applied"]
    assert record["provenance"]["images"] == out["loop"]["holdout"]["fit_images"]
    expected = split_shifts(cal.shifts.scaled(1 + record["scale"]), record["split"])
    for side in ("north", "east"):
        np.testing.assert_allclose(getattr(refined.shifts, side), getattr(expected, side),
                                   rtol=1e-12)
    # the held-out stars' pixels against P(F) from either calibration, through psf's path:
    # the refinement of BF-only spots leaves them as the flats' calibration did
    stack = out["loop"]["star_residual_refined"]
    print("star residual chi2 per pixel, held out:", stack)
    assert stack["heldout"] and stack["exposures"] == out["loop"]["holdout"]["heldout_exposures"]
    assert stack["refined"]["n_stars"] == stack["flats"]["n_stars"] > 0
    # measured 0.6 and 1.4 (27 spots per exposure, each its own P0); the verdict's limit 10
    assert max(stack["flats"]["chi2_per_pixel"], stack["refined"]["chi2_per_pixel"]) < 5.0
    for axis in ("x", "y"):
        residual, error = out["refined"]["residual"][axis]
        assert abs(residual) < 2.0 + 3 * error
        # a static P0 predicts no BF change: the residual (star minus the model at its own
        # phase) is the raw slope, but for the pixelised model's size at each star's
        # sub-pixel phase (measured 99.4 %)
        assert out["static"]["residual"][axis][0] == pytest.approx(100.0, abs=2.0)


@pytest.mark.slow
def test_output_calib_then_psf_full(tmp_path):
    """Issue 11's acceptance: 12 flat pairs (192^2), 16 exposures of 6 levels (3 to 120 ke-
    peak): the loop on 8, P(F) with the refined calibration on the other 8 (432 spots).
    The BF slope residual is at most 2 % of raw in X and Y, the photometry bias between the
    faintest and brightest spots at most 1 mmag (within its error)."""
    flats = _flats(tmp_path, 12, 192)
    images, truths = _spots(tmp_path, (3e3, 2.5e4, 5e4, 7.5e4, 1e5, 1.2e5), 16)
    out = _loop_then_psf(tmp_path, flats, images, truths, n_bins=6)
    assert out["loop"]["selected"] == []
    for axis in ("x", "y"):
        residual, error = out["refined"]["residual"][axis]
        assert abs(residual) <= 2.0 + error
        # the flats alone are off (-23 % in X since the flats conserve charge, +5 % or
        # more before): the refinement matters
        assert abs(out["flats"]["residual"][axis][0]) > 5.0
    bias, error = out["refined"]["bias"]
    assert abs(bias) <= 1.0 + error
