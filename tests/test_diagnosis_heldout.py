"""The closed loop made honest: errors that match the data (lamp flicker), held-out before /
after, what no candidate explains, and the loop's result written as a calibration.

The physics tests are not circular: flats come from GalSim's SiliconSensor
(`bfpsf.validation.simulate_flats`) with lamp flicker, and the undeclared effects (a quadratic
non-linearity, a serial readout correlation) are applied to the electrons before readout, not
through a catalogue template. Quick variants on small flats here; the full variant with
SiliconSensor spots is `test_silicon_flats_and_spots_full` (slow).
"""

import numpy as np
import pytest

from bfpsf.diagnosis.catalogue import CATALOGUE, get_effect, quadrupole_shifts
from bfpsf.diagnosis.loop import diagnose, split_observables
from bfpsf.diagnosis.observables import flat_observables, lamp_error_floor, ptc_observable
from bfpsf.diagnosis.tables import Observables, SizeTable
from bfpsf.calibration.linearity import linearise
from bfpsf.diagnosis.refine import refine_calibration
from bfpsf.errors import BFPSFInputError, BFPSFValueError


# -- lamp flicker --------------------------------------------------------------------------------
def test_lamp_error_floor_recovers_jitter_and_ignores_nonlinearity():
    """Means 1e4-1.2e5 e- with 0.1 % lamp jitter and a 1e-3 e- shot noise: the floor comes back
    at 0.1 % (to the precision of 40 exposures), with or without a 2 % quadratic
    non-linearity (the quadratic fit takes it, so it does not inflate the floor)."""
    rng = np.random.default_rng(1)
    exptime = np.linspace(10.0, 120.0, 40)
    linear = 1000.0 * exptime
    jitter = 1e-3 * rng.standard_normal(exptime.size)
    shot = np.full(exptime.size, 2.0)
    for c in (0.0, -2e-7):
        measured = linear * (1 + jitter) * (1 + c * linear * (1 + jitter))
        floor = lamp_error_floor(exptime, measured, shot)
        # relative error of an rms from 37 degrees of freedom: 12 %, held to 3 sigma
        assert floor == pytest.approx(1e-3, rel=0.35)
    # no flicker: no floor
    assert lamp_error_floor(exptime, linear + rng.normal(0, 2.0, exptime.size), shot) < 2e-5


#: the serial readout correlation c of the flats' read-out: q[:, i] + c q[:, i - 1]
SERIAL = -0.03


@pytest.fixture(scope="module")
def flat_sets():
    """Calibrated SiliconSensor flats (160^2, 10 levels to 120 ke-, one pair each, 0.1 % lamp
    jitter) of both sensors: null, a hidden quadratic non-linearity (-1.5 % at 100 ke-) and a
    serial readout correlation (-0.03: the loop measures it to 4.2e-3 from 10 pairs of 160^2, so
    7 sigma; at -0.02, 5 sigma, one realisation in eight missed the Delta BIC of -10), both
    applied to the read-out null images of one sensor (the simulator applies them to the
    electrons before the read noise; here the 5 e- of read noise goes through them too, a
    change of 3 % or less of it), so each differs from its null by the effect alone."""
    from bfpsf.calibration import calibrate
    from bfpsf.validation.simulate_flats import simulate_flats

    def nonlinear(image, meta):
        electrons = image * meta["SIMGAIN"]
        return electrons * (1.0 - 1.5e-7 * electrons) / meta["SIMGAIN"]

    def serial(image, meta):
        read = image.copy()
        read[:, 1:] += SERIAL * image[:, :-1]
        return read

    sets = {}
    for sensor, variant, readout in (("lsst_e2v_50_8", "nonlinear", nonlinear),
                                     ("lsst_itl_50_8", "serial", serial)):
        null = simulate_flats(sensor, np.linspace(1e4, 1.2e5, 10), pairs=1, size=160,
                              nsteps=4, seed=3, lamp_jitter=1e-3)
        for label, flats in (("null", null),
                             (variant, [(readout(image, meta), exptime, meta)
                                        for image, exptime, meta in null])):
            sets[sensor, label] = calibrate([image for image, _, _ in flats],
                                            exptimes=[t for _, t, _ in flats], maxlag=3,
                                            n_monte_carlo=0, fit_b=False)
    return sets


def _flat_only(cal):
    linearity, correlations = flat_observables(cal)
    return Observables(linearity=linearity, correlations=correlations, ptc=ptc_observable(cal))


@pytest.mark.parametrize("sensor", ["lsst_e2v_50_8", "lsst_itl_50_8"])
def test_null_flats_with_lamp_jitter_select_nothing(flat_sets, sensor):
    observables = _flat_only(flat_sets[sensor, "null"])
    # the floor is measured and reported (about the 0.1 % injected, to 10 exposures' precision)
    assert 3e-4 < observables.linearity.error_floor < 3e-3
    result = diagnose(observables, holdout_fraction=0.5)
    assert result.selected == []
    assert result.unexplained == []
    assert result.residual_before["linearity_chi2_per_point"] < 3


def test_hidden_nonlinearity_is_named(flat_sets):
    result = diagnose(_flat_only(flat_sets["lsst_e2v_50_8", "nonlinear"]))
    assert result.selected[:1] == ["gain_nonlinearity"]
    # injected c = -0.015 per 1e5 e-; first-order templates and a calibrated gain that
    # absorbs part of the curvature: 35 %
    assert result.parameters["gain_nonlinearity"]["value"][0] == pytest.approx(-0.015, rel=0.35)


def test_serial_correlation_names_pedestal_and_no_nonlinearity(flat_sets):
    result = diagnose(_flat_only(flat_sets["lsst_itl_50_8", "serial"]))
    assert result.selected[:1] == ["readout_pedestal"]
    assert "gain_nonlinearity" not in result.selected
    fitted = result.parameters["readout_pedestal"]
    assert abs(fitted["value"][0] - SERIAL) < 3 * fitted["error"][0]


def test_effect_left_out_of_the_catalogue_is_unexplained(flat_sets):
    """Without gain_nonlinearity in the catalogue, the loop does not force the non-linear
    flats onto another candidate: it reports the PTC / linearity residual as unexplained,
    growing with the signal."""
    catalogue = [effect for effect in CATALOGUE if effect.name != "gain_nonlinearity"]
    result = diagnose(_flat_only(flat_sets["lsst_e2v_50_8", "nonlinear"]), catalogue=catalogue,
                      holdout_fraction=0.5)
    assert "gain_nonlinearity" not in result.selected
    assert all(result.confirmed.values()) or result.unexplained
    observables = {entry["observable"] for entry in result.unexplained}
    assert observables & {"ptc", "linearity"}, result.unexplained
    for entry in result.unexplained:
        assert entry["significance"] > 3
        assert entry["flux_dependence"]["kind"] in ("linear", "quadratic")


# -- held-out split ------------------------------------------------------------------------------
def _sizes(exposure=None, n=12):
    peaks = np.tile(np.linspace(1e4, 1.2e5, n // 2), 2) if exposure is not None else \
        np.linspace(1e4, 1.2e5, n)
    return SizeTable(peaks, np.full(n, 1.5), np.full(n, 1.5), np.full(n, 1e-3),
                     np.full(n, 1e-3), exposure=exposure)


def test_split_by_exposure_and_alternate_bins(flat_sets):
    import galsim

    from bfpsf.diagnosis.spot_model import SpotForwardModel

    cal = flat_sets["lsst_itl_50_8", "null"]
    model = SpotForwardModel(galsim.Gaussian(sigma=1.2), cal.shifts, phases=1)
    linearity, correlations = flat_observables(cal)
    by_exposure = Observables(sizes=_sizes(np.repeat([0, 1], 6)), spot_model=model,
                              linearity=linearity, correlations=correlations)
    fit, held = split_observables(by_exposure, 0.5)
    assert set(fit.sizes.exposure) == {0} and set(held.sizes.exposure) == {1}
    assert held.meta["holdout_sizes_split_by"] == "exposure"
    # flat pairs alternate in mean: neither half holds all the bright pairs
    assert fit.linearity.mean_e.size + held.linearity.mean_e.size == linearity.mean_e.size
    assert held.linearity.mean_e.max() > fit.linearity.mean_e.min()
    alternate = Observables(sizes=_sizes(), spot_model=model)
    fit, held = split_observables(alternate, 0.5)
    assert held.meta["holdout_sizes_split_by"] == "alternate peak bins"
    assert np.array_equal(np.sort(np.r_[fit.sizes.peak_e, held.sizes.peak_e]),
                          alternate.sizes.peak_e)
    assert np.all(np.isin(held.sizes.peak_e, alternate.sizes.peak_e[1::2]))
    with pytest.raises(BFPSFValueError, match="holdout_fraction must be between 0 and 1"):
        split_observables(alternate, 1.0)
    with pytest.raises(BFPSFInputError, match="too few"):
        split_observables(Observables(sizes=_sizes(n=4), spot_model=model), 0.5)


# -- the loop's result as a calibration ----------------------------------------------------------
def test_linearise_inverts_the_nonlinearity():
    q = np.linspace(0.0, 2e5, 50)
    for c in (-0.02, 0.0, 0.015):
        assert np.allclose(linearise(q * (1 + c * q / 1e5), c), q, rtol=1e-12, atol=1e-9)


def test_refined_calibration_round_trip(flat_sets, tmp_path):
    """Scale and anisotropy go into the shifts (the anisotropy changes no pixel area), the
    non-linearity into a linearity correction; the record survives write / read."""
    from bfpsf.calibration.product import Calibration
    from bfpsf.diagnosis.loop import DiagnosisResult

    cal = flat_sets["lsst_itl_50_8", "null"]
    result = DiagnosisResult(
        residual_before={}, candidates=[], residual_after={}, threshold=-10.0,
        selected=["xy_anisotropy", "gain_nonlinearity", "flux_diffusion"],
        parameters={"xy_anisotropy": {"names": ["q"], "value": [0.5], "error": [0.1]},
                    "gain_nonlinearity": {"names": ["c"], "value": [-0.01], "error": [0.001]},
                    "flux_diffusion": {"names": ["d"], "value": [0.01], "error": [0.001]}},
        nuisance={"calibration_scale": {"value": 0.1, "error": 0.05, "prior": 0.2}},
        folded={"names": ["xy_anisotropy", "gain_nonlinearity"],
                "effects": {"xy_anisotropy": [0.5], "gain_nonlinearity": [-0.01]},
                "scale_nuisance": 0.1},
        confirmed={"calibration_scale (nuisance)": True, "xy_anisotropy": True,
                   "gain_nonlinearity": True, "flux_diffusion": False})
    refined = refine_calibration(cal, result, provenance={"images": ["a.fits"]})
    expected = (cal.shifts.north + quadrupole_shifts(cal.shifts, 0.5).north) * 1.1
    np.testing.assert_allclose(refined.shifts.north, expected, rtol=1e-12)
    np.testing.assert_allclose(refined.shifts.area, 1.1 * cal.shifts.area, rtol=1e-10,
                               atol=1e-22)
    record = refined.refinement
    assert record["linearity_c_per_1e5"] == -0.01
    assert "flux_diffusion" in record["not_applied"]
    assert set(record["applied"]) == {"calibration_scale (nuisance)", "xy_anisotropy",
                                      "gain_nonlinearity"}
    path = tmp_path / "refined.fits"
    refined.write(path)
    back = Calibration.read(path)
    assert back.refinement == record
    np.testing.assert_array_equal(back.shifts.east, refined.shifts.east)
    assert Calibration.read(path).refinement["provenance"] == {"images": ["a.fits"]}
    assert get_effect("xy_anisotropy").name == "xy_anisotropy"


@pytest.mark.parametrize("folded_scale, applied", [(0.5, True), (0.7, False), (1.5, False)])
def test_a_scale_refitted_beyond_the_flats_is_not_applied(flat_sets, folded_scale, applied):
    """A new user's halo: second_order named at t < 0, which the calibration cannot hold;
    refitted without it, the flats' scale went to +1.496 (prior 0.22, bounds -0.5 to 1) and
    every shift was multiplied by 2.50, said nowhere. A refitted scale beyond 3 of the flats'
    prior (here 0.2) or outside its bounds is not applied, and the refinement says why."""
    from bfpsf.diagnosis.loop import DiagnosisResult

    cal = flat_sets["lsst_itl_50_8", "null"]
    result = DiagnosisResult(
        residual_before={}, candidates=[], residual_after={}, threshold=-10.0, selected=[],
        parameters={}, nuisance={"calibration_scale": {"value": 0.1, "error": 0.05,
                                                       "prior": 0.2}},
        folded={"names": [], "effects": {}, "scale_nuisance": folded_scale},
        confirmed={"calibration_scale (nuisance)": True})
    record = refine_calibration(cal, result).refinement
    label = "calibration_scale (nuisance)"
    assert (label in record["applied"]) == applied
    assert record["scale"] == (folded_scale if applied else 0.0)
    if not applied:
        assert "refitted to" in record["not_applied"][label]


def test_refined_samples_carry_the_stars_errors_of_scale_and_split(flat_sets):
    """Each shift sample of the flats carries its own BF scale and X / Y split
    (`bf_scale_error`'s ``draws``); where the stars fixed them, `refine_calibration`
    re-centres every sample on the stars' values within the fit's errors. Samples drawn as
    the nominal shifts times 1 + s_i (rms 0.3) with the split moved by d_i (rms 0.5): the
    refined samples' spread is the stars' 0.02 and 0.05 (to the sampling error of 40
    samples), not the flats' (a new user's ``slope --psf`` after refinement: +- 0.0178 px
    per 100 ke-, 107 % of the raw slope, every pull 0; re-centred +- 0.0022)."""
    import dataclasses

    from bfpsf.diagnosis.catalogue import split_shifts
    from bfpsf.diagnosis.loop import DiagnosisResult

    cal = flat_sets["lsst_itl_50_8", "null"]
    rng = np.random.default_rng(5)
    scales, splits = rng.normal(0.0, 0.3, 40), rng.normal(0.0, 0.5, 40)
    samples = [split_shifts(cal.shifts.scaled(1 + s), d) for s, d in zip(scales, splits)]
    cal = dataclasses.replace(cal, shift_samples_north=np.array([x.north for x in samples]),
                              shift_samples_east=np.array([x.east for x in samples]))
    result = DiagnosisResult(
        residual_before={}, candidates=[], residual_after={}, threshold=-10.0, selected=[],
        parameters={},
        nuisance={"calibration_scale": {"value": 0.1, "error": 0.02, "prior": 0.3,
                                        "draws": scales.tolist()},
                  "calibration_split": {"value": -0.2, "error": 0.05, "prior": 0.5,
                                        "draws": splits.tolist()}},
        folded={"names": [], "effects": {}, "scale_nuisance": 0.1, "split_nuisance": -0.2},
        confirmed={"calibration_scale (nuisance)": True})
    refined = refine_calibration(cal, result)
    nominal = refined.shifts
    np.testing.assert_allclose(nominal.north, split_shifts(cal.shifts.scaled(1.1), -0.2).north,
                               rtol=1e-12)
    centre = (nominal.north[nominal.radius + 1, nominal.radius],
              nominal.east[nominal.radius, nominal.radius + 1])
    north = refined.shift_samples_north[:, nominal.radius + 1, nominal.radius] / centre[0]
    east = refined.shift_samples_east[:, nominal.radius, nominal.radius + 1] / centre[1]
    # north = (1 + 0.1 + ds) / 1.1 exp(-dd / 2), east the same with exp(+dd / 2)
    scale_part = np.log(north * east) / 2
    split_part = np.log(east / north)
    assert np.std(scale_part, ddof=1) == pytest.approx(0.02 / 1.1, rel=0.3)
    assert np.std(split_part, ddof=1) == pytest.approx(0.05, rel=0.3)
    assert abs(np.mean(split_part)) < 3 * 0.05 / np.sqrt(40)


# -- the full variant: SiliconSensor flats and spots ---------------------------------------------
def _write_silicon_set(directory, sensor, *, nonlinearity=0.0, spots_cache=None):
    """12 flat pairs (192^2, 0.1 % lamp jitter) and 4 spot exposures (6 peaks 3-120 ke-, 9
    phases each, Moffat FWHM 3 px, sky 50 e-, read noise 5 e-), the non-linearity applied
    to the electrons of both before readout. Returns (flat paths, image paths, spot images)."""
    from astropy.io import fits

    from bfpsf.validation.simulate_flats import simulate_flats
    from bfpsf.validation.simulate_spots import simulate_spots

    directory.mkdir()
    flats = simulate_flats(sensor, np.linspace(1e4, 1.2e5, 12), pairs=1, size=192, nsteps=4,
                           seed=3, gain=1.5, lamp_jitter=1e-3,
                           nonlinearity=nonlinearity)
    flat_paths = []
    for index, (image, exptime, _) in enumerate(flats):
        flat_paths.append(directory / f"flat{index:02d}.fits")
        fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(
            flat_paths[-1])
    if spots_cache is None:
        grid = (np.arange(3) + 0.5) / 3 - 0.5
        offsets = np.array([(x, y) for y in grid for x in grid])
        spots_cache = [simulate_spots(sensor=sensor, fwhm=3.0, beta=3.0,
                                      peaks_e=(3e3, 2.5e4, 5e4, 7.5e4, 1e5, 1.2e5),
                                      n_per_level=9, stamp_size=24, seed=10 + exposure,
                                      sky_e=50.0, read_noise_e=5.0,
                                      offsets=offsets).mosaic(margin=8)[0]
                       for exposure in range(4)]
    image_paths = []
    for index, charge in enumerate(spots_cache):
        signal = charge * (1 + nonlinearity * charge)
        image_paths.append(directory / f"spots{index}.fits")
        fits.PrimaryHDU(signal / 1.5, header=fits.Header({"EXPTIME": 1.0})).writeto(
            image_paths[-1])
    return flat_paths, image_paths, spots_cache


@pytest.mark.slow
def test_silicon_flats_and_spots_full(tmp_path):
    """E2V SiliconSensor flats and spots through ``bfpsf diagnose``: the null selects nothing
    (the flats' BF amplitude error is taken by the size scale, confirmed on the held-out
    exposures); a hidden quadratic non-linearity of -1.5 % at 100 ke- is named.
    The peak bins (--bins 6) are the six simulated levels: bins that split a level would
    select sub-pixel phases (the levels are set by peak)."""
    import json

    from bfpsf.cli import main

    selections = {}
    cache = None
    for label, nonlinearity in (("null", 0.0), ("nonlinear", -1.5e-7)):
        flats, images, cache = _write_silicon_set(tmp_path / label, "lsst_e2v_50_8",
                                                  nonlinearity=nonlinearity, spots_cache=cache)
        out = tmp_path / f"{label}.json"
        assert main(["diagnose", "--flats", *map(str, flats), "--images", *map(str, images),
                     "--beta", "3", "--no-fit-b", "--maxlag", "3", "--bins", "6",
                     "--json", str(out)]) == 0
        selections[label] = json.loads(out.read_text())
    assert selections["null"]["selected"] == []
    assert selections["null"]["holdout"]["sizes_split_by"] == "exposure"
    # named, beside the size scale: since the flats conserve charge the stars of this set show
    # 23-33 % less BF than its flats (nsteps 4, and GalSim's two rules), beyond the flats'
    # prior of 8 %: the non-linearity's size part disagrees with the flat means' until the
    # stars' BF amplitude is free, and the two are named together (`paired_with`; measured
    # s = -0.33 +- 0.08, c = -0.0135 +- 0.0012 per 1e5 e-, true -0.015)
    nonlinear = selections["nonlinear"]
    assert "gain_nonlinearity" in nonlinear["selected"]
    value, error = (nonlinear["parameters"]["gain_nonlinearity"][key][0]
                    for key in ("value", "error"))
    assert value == pytest.approx(-0.015, abs=3 * error)


def test_binned_size_errors_give_chi2_one_with_few_stars_per_bin():
    """Six stars per flux bin and exposure (a new user's field of stars at random sub-pixel
    phases): each bin's own scatter as its error made the null's size chi2 per point 2.8 and
    named effects on it; the scatter pooled over the exposures gives chi2 per point 1."""
    from bfpsf.diagnosis.binning import binned_sizes

    rng = np.random.default_rng(11)
    levels, exposures, per_bin = 6, 40, 6
    flux = np.tile(np.repeat(np.geomspace(3e4, 1.2e6, levels), per_bin), exposures)
    exposure = np.repeat(np.arange(exposures), levels * per_bin)
    truth_x = 1.30 + 0.02 * flux / 1e6
    # the phase scatter of a pixelised star's size: 0.02 px, the same at every exposure
    sigma_x = truth_x + 0.02 * rng.standard_normal(flux.size)
    sigma_y = 1.25 + 0.02 * rng.standard_normal(flux.size)
    table = binned_sizes(flux, flux / 16, sigma_x, sigma_y, exposure, levels, "sizes")
    expected = 1.30 + 0.02 * np.array([flux[(exposure == e) & np.isclose(flux, f, rtol=1e-9)]
                                       .mean() for e, f in zip(table.exposure,
                                                               16 * table.peak_e)]) / 1e6
    chi2 = np.mean(((table.sigma_x - expected) / table.sigma_x_err) ** 2)
    assert chi2 == pytest.approx(1.0, abs=0.15)


@pytest.mark.parametrize("stars, n_bins, grid, bins", [
    (126, None, (2, 2), 10), (80, None, (2, 2), 6), (54, None, 1, 10), (48, 4, (2, 2), 4),
    (48, 6, 1, 6), (200, 8, (2, 2), 8)])
def test_default_position_grid_where_the_stars_fill_it(stars, n_bins, grid, bins):
    """``position_bins='auto'``: a 2 x 2 grid where the exposure with the fewest stars puts 3
    in every cell of every peak bin; the peak bins, when the user gave none, shrink to as few
    as 6 for it; a grid that does not fit is not tested, and the report says so."""
    from bfpsf.diagnosis.binning import auto_position_bins

    chosen, n, words = auto_position_bins([stars + 10, stars], n_bins)
    assert (chosen, n) == (grid, bins)
    assert words.startswith("2x2 (auto" if grid != 1 else "not tested (auto")


@pytest.mark.parametrize("significances, n_bins, grid, bins", [
    ({"row": 8.6, "column": 0.2}, None, (1, 2), 9), ({"row": 1.0, "column": 4.0}, None, (2, 1), 9),
    ({"row": 2.0, "column": 2.5}, None, 1, 10), ({"row": 8.6, "column": 0.2}, 6, (1, 2), 6),
    ({"row": 8.6, "column": 0.2}, 12, 1, 12)])
def test_too_few_stars_for_the_grid_split_the_direction_every_star_depends_on(
        significances, n_bins, grid, bins):
    """55 stars per exposure are too few for a 2 x 2 grid; where every star's BF slope
    depends on the row (or the column) beyond 3 sigma (`position_split`), that direction is
    split in two (a new user's row-growing smear: its EMPIRICAL term then has a row term),
    with as many peak bins as each half fills with 3 stars (9), or the user's if they fit."""
    from bfpsf.diagnosis.binning import auto_position_bins

    split = {along: {"x": {"significance": 0.1}, "y": {"significance": value}}
             for along, value in significances.items()}
    chosen, n, words = auto_position_bins([60, 55], n_bins, split)
    assert (chosen, n) == (grid, bins)
    if grid != 1:
        assert "depends on the " + ("row" if grid == (1, 2) else "column") in words
