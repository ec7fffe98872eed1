"""The versioned Calibration product: exact FITS round trip, schema guard, JSON keys."""

import json

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration import ptc
from bfpsf.calibration.linearity import measure_linearity
from bfpsf.calibration.pedestal import measure_pedestal
from bfpsf.calibration.product import SCHEMA_VERSION, Calibration
from bfpsf.errors import BFPSFFileExistsError, BFPSFInputError, BFPSFValueError
from bfpsf.shifts import BoundaryShifts

JSON_KEYS = {"gain", "gain_err", "noise_e", "a", "a_err", "maxlag", "n_pairs", "turnoff_e",
             "linearity_max_frac_residual", "pedestal"}


@pytest.fixture(scope="module")
def calibration():
    """A Calibration built from a model PTC (no GalSim needed)."""
    rng = np.random.default_rng(0)
    maxlag = 3
    area = np.zeros((maxlag + 1, maxlag + 1))
    area[0, 0], area[0, 1], area[1, 0], area[1, 1] = -2e-6, 1e-7, 3.5e-7, 1e-7
    area[0, 0] -= 2 * area[0, 1:].sum() + 2 * area[1:, 0].sum() + 4 * area[1:, 1:].sum()
    mean_adu = np.linspace(3e3, 8e4, 10)
    noise = np.zeros_like(area)
    noise[0, 0] = 25.0
    cov = ptc.full_covariance_model(mean_adu, area, np.zeros_like(area), noise, 1.5)
    npix = np.full(cov.shape, 1e6)
    cov += rng.standard_normal(cov.shape) * ptc.covariance_errors(cov, npix)
    exptime = mean_adu / 1e4
    data = ptc.PTCData(exptime, mean_adu, cov, npix)
    fit = ptc.fit_ptc(data)
    pedestal = measure_pedestal(mean_adu, cov, npix)
    linearity = measure_linearity(exptime, mean_adu, used=fit.used)
    shifts = BoundaryShifts.from_radial_profile(lambda r: 1e-7 / r**2, 4)
    table = ptc.ptc_table(data, fit.gain, fit.used)
    table["name1"] = [f"flat{2 * i}.fits" for i in range(len(table))]
    return Calibration(
        gain=fit.gain, gain_err=fit.gain_err, noise_e=fit.noise_e, noise_e_err=fit.noise_e_err,
        a=fit.a, a_err=fit.a_err, b=fit.b, b_err=fit.b_err, noise_matrix_e2=fit.noise_matrix_e2,
        ptc=table, linearity=linearity, pedestal=pedestal, model=fit.model,
        turnoff_e=fit.turnoff_e, turnoff_detected=fit.turnoff_detected, chi2=fit.chi2,
        ndof=fit.ndof, shifts=shifts, shifts_north_err=np.abs(shifts.north) * 0.1,
        shifts_east_err=np.abs(shifts.east) * 0.1,
        shift_fit={"p0": -1.3e-7, "p1": -0.71, "p1_err": 0.05, "sensitivity_max_relative": 0.01},
        covariances_adu=cov, npix=npix, inputs=["flat0.fits", "flat1.fits"],
        parameters={"maxlag": maxlag, "ptc_model": "full", "saturation": None})


def test_round_trip_is_exact(calibration, tmp_path):
    path = tmp_path / "calib.fits"
    calibration.write(path)
    back = Calibration.read(path)
    for name in ("gain", "gain_err", "noise_e", "noise_e_err", "turnoff_e", "chi2", "ndof",
                 "model", "turnoff_detected", "inputs", "parameters", "shift_fit",
                 "bfpsf_version", "schema_version", "maxlag", "n_pairs"):
        assert getattr(back, name) == getattr(calibration, name), name
    for name in ("a", "a_err", "b", "b_err", "noise_matrix_e2", "shifts_north_err",
                 "shifts_east_err", "covariances_adu", "npix"):
        np.testing.assert_array_equal(getattr(back, name), getattr(calibration, name), name)
    assert back.shifts == calibration.shifts
    assert back.ptc.colnames == calibration.ptc.colnames
    for column in calibration.ptc.colnames:
        np.testing.assert_array_equal(back.ptc[column], calibration.ptc[column], column)
        assert back.ptc[column].unit == calibration.ptc[column].unit
    for name in ("value", "error"):
        np.testing.assert_array_equal(getattr(back.pedestal, name),
                                      getattr(calibration.pedestal, name))
    assert (back.pedestal.nsigma, back.pedestal.degree) == (calibration.pedestal.nsigma,
                                                            calibration.pedestal.degree)
    for name in ("exptime", "mean_adu", "frac_residual", "used"):
        np.testing.assert_array_equal(getattr(back.linearity, name),
                                      getattr(calibration.linearity, name))
    for name in ("slope", "intercept", "threshold", "measured", "flagged"):
        assert getattr(back.linearity, name) == getattr(calibration.linearity, name)
    assert back.to_json_dict() == calibration.to_json_dict()


def test_arrays_are_read_only(calibration):
    with pytest.raises(ValueError):
        calibration.a[0, 0] = 0.0


def test_never_overwrites_without_permission(calibration, tmp_path):
    path = tmp_path / "calib.fits"
    calibration.write(path)
    with pytest.raises(BFPSFFileExistsError, match="overwrite=True"):
        calibration.write(path)
    calibration.write(path, overwrite=True)


def test_newer_schema_is_refused(calibration, tmp_path):
    path = tmp_path / "calib.fits"
    calibration.write(path)
    with fits.open(path, mode="update") as hdul:
        hdul[0].header["BFSCHEMA"] = SCHEMA_VERSION + 1
    with pytest.raises(BFPSFInputError, match=f"schema version {SCHEMA_VERSION + 1}, newer"):
        Calibration.read(path)


def test_foreign_file_is_refused(tmp_path):
    path = tmp_path / "image.fits"
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(path)
    with pytest.raises(BFPSFInputError, match="not a bfpsf calibration file"):
        Calibration.read(path)
    with pytest.raises(BFPSFInputError, match="does not exist"):
        Calibration.read(tmp_path / "missing.fits")


def test_json_keys_and_layout(calibration):
    summary = calibration.to_json_dict()
    assert JSON_KEYS <= set(summary)
    text = json.dumps(summary, allow_nan=False)  # strictly valid JSON
    summary = json.loads(text)
    maxlag = summary["maxlag"]
    assert len(summary["a"]) == maxlag + 1 and len(summary["a"][0]) == maxlag + 1
    assert summary["a"][1][0] == calibration.a[1, 0]  # [dy][dx]
    assert len(summary["pedestal"]) == maxlag + 1
    assert summary["n_pairs"] == 10


def test_round_trip_keeps_undetected_turnoff_as_nan(calibration, tmp_path):
    """A PTC whose turnoff was not reached has turnoff_e = NaN; it must read back as NaN,
    without a warning (warnings are errors here)."""
    import dataclasses

    undetected = dataclasses.replace(calibration, turnoff_e=float("nan"), turnoff_detected=False,
                                     chi2=float("nan"))
    path = tmp_path / "calib.fits"
    undetected.write(path)
    back = Calibration.read(path)
    assert np.isnan(back.turnoff_e) and np.isnan(back.chi2)
    assert back.turnoff_detected is False
    assert back.to_json_dict()["turnoff_e"] is None or np.isnan(back.to_json_dict()["turnoff_e"])


def test_psf_product_round_trip_and_schema_checks(tmp_path):
    import galsim

    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.model.product import PSF_SCHEMA_VERSION
    from bfpsf.shifts import BoundaryShifts

    shifts = BoundaryShifts.from_radial_profile(lambda r: 5e-7 * np.exp(-r), 2)
    psf = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=3.0), shifts,
                                       oversampling=2, size=11, flux_unit="electron",
                                       gain=1.7)
    path = tmp_path / "psf.fits"
    psf.write(path, calibration="calib.fits")
    back = FluxDependentPSF.read(path)
    np.testing.assert_array_equal(back.data, psf.data)
    assert back.shifts == shifts and back.gain == 1.7 and back.calibration == "calib.fits"
    assert back.evaluate(3.2, 4.1, 2e5, 3.0, 4.0) == psf.evaluate(3.2, 4.1, 2e5, 3.0, 4.0)
    with pytest.raises(BFPSFFileExistsError, match="overwrite=True"):
        psf.write(path)
    # an exact-density table is stored (its GalSim profile is not) and read back
    exact = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=3.0), shifts,
                                        oversampling=2, size=11, density="exact")
    exact.write(tmp_path / "exact.fits")
    np.testing.assert_array_equal(FluxDependentPSF.read(tmp_path / "exact.fits").bf_table,
                                  exact.bf_table)
    assert not np.array_equal(exact.bf_table, back.bf_table)
    exact_mode = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=3.0), shifts,
                                             oversampling=2, size=11, density="exact",
                                             mode="exact")
    with pytest.raises(BFPSFValueError, match="density_profile cannot be stored"):
        exact_mode.write(tmp_path / "refused.fits")
    assert not (tmp_path / "refused.fits").exists()
    with fits.open(path, mode="update") as hdul:
        hdul[0].header["BFPSFVER"] = PSF_SCHEMA_VERSION + 1
    with pytest.raises(BFPSFInputError, match=f"schema version {PSF_SCHEMA_VERSION + 1}, newer"):
        FluxDependentPSF.read(path)
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(tmp_path / "image.fits")
    with pytest.raises(BFPSFInputError, match="not a bfpsf PSF product file"):
        FluxDependentPSF.read(tmp_path / "image.fits")
    with pytest.raises(BFPSFInputError, match="PSF product file .* does not exist"):
        FluxDependentPSF.read(tmp_path / "missing.fits")


def _with_samples(calibration, amplifier="", warnings=("a warning",), method="electrostatic"):
    from dataclasses import replace

    rng = np.random.default_rng(1)
    north = calibration.shifts.north * (1 + 0.1 * rng.standard_normal((5, 1, 1)))
    east = calibration.shifts.east * (1 + 0.1 * rng.standard_normal((5, 1, 1)))
    return replace(calibration, shift_samples_north=north, shift_samples_east=east,
                   shift_method=method, warnings=tuple(warnings), amplifier=amplifier)


def test_per_amplifier_groups_carry_samples_method_and_warnings(calibration, tmp_path):
    from bfpsf.calibration.detector import DetectorCalibration, read_calibration

    left = _with_samples(calibration, "C00", ("no measurable brighter-fatter",))
    right = _with_samples(calibration, "C01", (), method="ei")
    detector = DetectorCalibration({"C00": left, "C01": right}, detector="R22_S11")
    path = tmp_path / "detector.fits"
    detector.write(path)
    back = read_calibration(path)
    assert back.names == ["C00", "C01"]
    assert back["C00"].shift_method == "electrostatic" and back["C01"].shift_method == "ei"
    assert back["C00"].warnings == ("no measurable brighter-fatter",)
    assert back["C01"].warnings == ()
    np.testing.assert_array_equal(back["C00"].shift_samples_north, left.shift_samples_north)
    np.testing.assert_array_equal(back["C01"].shift_samples_east, right.shift_samples_east)
    summary = back.to_json_dict()
    assert summary["warnings"] == ["C00: no measurable brighter-fatter"]
    assert [entry["shift_method"] for entry in summary["amplifiers"]] == ["electrostatic", "ei"]
    assert summary["amplifiers"][0]["warnings"] == ["no measurable brighter-fatter"]
    assert summary["schema_version"] == SCHEMA_VERSION == 3


def test_schema_two_single_amplifier_file_reads(calibration, tmp_path):
    """A file of main's schema 2 (issue 10: samples, SHIFTMTH in the primary header, WARNINGS;
    no HDU groups) reads with its samples, solver and warnings."""
    one = _with_samples(calibration)
    path = tmp_path / "schema2.fits"
    one.write(path)
    with fits.open(path, mode="update") as hdul:
        hdul[0].header["BFSCHEMA"] = 2
        del hdul[0].header["NAMP"]
        for hdu in hdul[1:]:
            del hdu.header["AMPNAME"]
            del hdu.header["EXTVER"]
        del hdul["SUMMARY"].header["SHIFTMTH"]
    back = Calibration.read(path)
    assert back.schema_version == 2 and back.amplifier == ""
    assert back.shift_method == "electrostatic" and back.warnings == ("a warning",)
    np.testing.assert_array_equal(back.shift_samples_north, one.shift_samples_north)
    assert len(back.shift_samples(limit=3)) == 3
