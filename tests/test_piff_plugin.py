"""The Piff plug-in ``bfpsf.piff``: PSF type ``BrighterFatter`` run through real Piff.

Quick tests use a calibration whose boundary shifts are GalSim's E2V sensor's (measured from
SiliconSensor, `silicon_boundary_shifts`) and stars photon-shot through bfpsf's `BFSensor`
with those shifts, so the model can be checked against the physics that made the data. The
slow test is the acceptance on SiliconSensor stars with a calibration from simulated flats
(`bfpsf.piff.field.acceptance`, also run by benchmarks/bench_piff.py).
"""

import subprocess
import sys
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

galsim = pytest.importorskip("galsim")
piff = pytest.importorskip("piff")

import bfpsf.piff  # noqa: E402  (registers the PSF type)
from bfpsf import BFSensor, calibrate  # noqa: E402
from bfpsf.calibration.detector import DetectorCalibration  # noqa: E402
from bfpsf.errors import BFPSFInputError  # noqa: E402
from bfpsf.interop.silicon_truth import silicon_boundary_shifts  # noqa: E402
from bfpsf.model.redistribution import redistribute  # noqa: E402
from bfpsf.piff.field import (inner_psf_config, piff_config, residual_slopes,  # noqa: E402
                              write_field)
from bfpsf.shifts import BoundaryShifts  # noqa: E402

GAIN = 1.5
#: The quick field's shifts are the E2V sensor's times this, so that BF is measured to many
#: sigma on 300 stars (first order still holds: no pixel goes negative below 60 ke- of peak).
BF_BOOST = 4.0


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory):
    """A calibration file with gain 1.5 and the E2V SiliconSensor shifts (x BF_BOOST): its
    PTC fields come from small Poisson flats, only the gain and shifts are used here."""
    rng = np.random.default_rng(0)
    levels = np.repeat([1e3, 5e3, 1e4, 2e4, 4e4, 6e4], 2)
    images = [rng.poisson(level, (40, 40)).astype(float) for level in levels]
    base = calibrate(images, exptimes=levels / 1e3, maxlag=1, solve_shifts=False, fit_b="none")
    shifts = silicon_boundary_shifts("lsst_e2v_50_8", radius=3)
    boosted = BoundaryShifts(BF_BOOST * shifts.north, BF_BOOST * shifts.east, check=False)
    path = tmp_path_factory.mktemp("calib") / "calib.fits"
    replace(base, gain=GAIN, shifts=boosted).write(path)
    return path


@pytest.fixture(scope="module")
def field(tmp_path_factory, calibration_file):
    """Three 400 x 400 exposures of 100 stars (3-60 ke- peak) shot through BFSensor."""
    from bfpsf import Calibration

    shifts = Calibration.read(calibration_file).shifts
    return write_field(tmp_path_factory.mktemp("field"), n_exposures=3, gain=GAIN, seed=7,
                       sensor=BFSensor(shifts), peak_range_e=(3e3, 6e4))


@pytest.fixture(scope="module")
def fits(field, calibration_file):
    """Plain Piff and BrighterFatter fitted to the same exposures (same selection, reserve)."""
    result = {}
    for kind, calib in (("plain", None), ("bf", calibration_file)):
        result[kind] = [piff.process(piff_config(image, catalog, psf=inner_psf_config(),
                                                 gain=GAIN, calib=calib))
                        for image, catalog in field]
    return result


def test_bf_removes_the_size_and_e1_slopes_of_plain_piff(fits):
    plain = residual_slopes(fits["plain"], gain=GAIN)
    bf = residual_slopes(fits["bf"], gain=GAIN)
    # plain Piff leaves the BF growth in its residuals: measured to > 8 sigma here
    assert plain["size"].slope > 8 * plain["size"].slope_err, plain["size"]
    # BrighterFatter: each star's model has its flux, so no slope is left; 3 sigma of the
    # slope's own error (from the scatter of the residuals), and < 5 % of plain Piff's
    # within that error
    assert abs(bf["size"].slope) < 0.05 * plain["size"].slope + 3 * bf["size"].slope_err, bf["size"]
    assert abs(bf["e1"].slope) < 0.2 * abs(plain["e1"].slope) + 3 * bf["e1"].slope_err, bf["e1"]


def test_fit_keeps_reserve_stars_and_outlier_rejection(fits):
    for psf in fits["bf"]:
        reserve = [star for star in psf.stars if star.is_reserve]
        # reserve_frac 0.2 of 100 stars, as in plain Piff's selection
        assert 10 <= len(reserve) <= 30
        assert psf.niter >= 2 and psf.dof > 0
        # chisq per dof of the fit: the data are the model's physics plus noise
        assert psf.chisq / psf.dof < 1.3, (psf.chisq, psf.dof)
    # the plain fit of the same stars has a worse chisq (BF left in the residuals)
    assert sum(p.chisq for p in fits["plain"]) > sum(p.chisq for p in fits["bf"])


def test_draw_is_the_inner_psf_redistributed_with_the_gain(fits):
    psf = fits["bf"][0]
    shifts = psf.amplifier_at(0, 100, 100).shifts
    for flux in (1e3, 3e5):
        drawn = psf.draw(150.3, 220.8, chipnum=0, flux=flux)
        inner = psf.psf.draw(150.3, 220.8, chipnum=0, flux=flux)
        expected = redistribute(inner.array * GAIN, shifts) / GAIN
        np.testing.assert_allclose(drawn.array, expected, rtol=0, atol=1e-12 * flux)
        # charge conserved: the flux of the star is the flux asked for (to the stamp's loss)
        assert abs(drawn.array.sum() - inner.array.sum()) < 1e-9 * flux
    faint = psf.draw(150.3, 220.8, chipnum=0, flux=1e3).FindAdaptiveMom()
    bright = psf.draw(150.3, 220.8, chipnum=0, flux=3e5).FindAdaptiveMom()
    assert bright.moments_sigma > faint.moments_sigma * 1.005  # 4.5e5 e-: BF of a few %


def test_model_growth_matches_the_sensor_that_made_the_stars(fits, calibration_file):
    """The model's size at flux F minus at low flux equals that of a noiseless star drawn
    with the same operator (draw_with_bf's redistribution of the true Moffat) to 10 %."""
    from bfpsf import Calibration

    shifts = Calibration.read(calibration_file).shifts
    psf = fits["bf"][0]
    x, y = 200.0, 200.0  # centre of the exposure: FWHM 3.45, e1 0
    true = galsim.Moffat(beta=3.5, fwhm=3.45)
    growth_model, growth_true = [], []
    for flux_e in (1e4, 6e5):
        model = psf.draw(x, y, chipnum=0, flux=flux_e / GAIN, stamp_size=31)
        image = true.withFlux(flux_e).drawImage(nx=31, ny=31, scale=1.0)
        star = redistribute(image.array, shifts)
        growth_model.append(model.FindAdaptiveMom().moments_sigma)
        growth_true.append(galsim.Image(star).FindAdaptiveMom().moments_sigma)
    model_change = growth_model[1] / growth_model[0] - 1
    true_change = growth_true[1] / growth_true[0] - 1
    assert true_change > 0.01
    assert abs(model_change / true_change - 1) < 0.1, (model_change, true_change)


def test_write_read_gives_identical_draws_without_the_calibration(fits, calibration_file,
                                                                  tmp_path):
    psf = fits["bf"][1]
    path = tmp_path / "bf.piff"
    psf.write(str(path))
    moved = calibration_file.with_suffix(".moved")
    calibration_file.rename(moved)  # the Piff file alone must be enough
    try:
        read = piff.read(str(path))
    finally:
        moved.rename(calibration_file)
    assert isinstance(read, bfpsf.piff.BrighterFatterPSF)
    for flux in (10.0, 2e5):
        np.testing.assert_array_equal(read.draw(77.2, 301.6, chipnum=0, flux=flux).array,
                                      psf.draw(77.2, 301.6, chipnum=0, flux=flux).array)
    assert len(read.stars) == len(psf.stars)


def test_get_profile_holds_at_the_pixel_phase_of_its_position(fits):
    psf = fits["bf"][0]
    x, y, flux = 123.4, 250.7, 2e5
    profile, method = psf.get_profile(x, y, chipnum=0, flux=flux)
    assert method == "no_pixel"
    drawn = psf.draw(x, y, chipnum=0, flux=flux)
    again = profile.drawImage(image=drawn.copy(), method=method, center=(x, y))
    # interpolating kernel: at the pixel centres of that phase it gives the pixels back
    np.testing.assert_allclose(again.array, drawn.array, rtol=0, atol=1e-6 * drawn.array.max())
    assert abs(profile.flux / flux - 1) < 1e-6


def test_example_config_runs_with_piff_stats(field, calibration_file, tmp_path):
    """examples/piff_config/piff_bf.yaml as a user runs it (piffify), with its stats."""
    import yaml
    from astropy.table import Table

    example = Path(__file__).resolve().parents[1] / "examples" / "piff_config" / "piff_bf.yaml"
    config = yaml.safe_load(example.read_text())
    image, catalog = field[0]
    config["input"].update(image_file_name=str(image), cat_file_name=str(catalog))
    config["psf"]["calib"] = str(calibration_file)
    config["output"]["dir"] = str(tmp_path)
    config["output"]["stats"].append({"type": "HSMCatalog", "file_name": "hsm.fits"})
    config["verbose"] = 0
    piff.piffify(config)
    for name in ("bf.piff", "rho.png", "sizemag.png", "stars.png", "hsm.fits"):
        assert (tmp_path / name).stat().st_size > 0, name
    table = Table.read(tmp_path / "hsm.fits")
    good = table["flag_data"] == 0
    # HSM sizes of data and model (drawn at each star's flux) agree to 1 % on average
    ratio = np.asarray(table["T_model"][good]) / np.asarray(table["T_data"][good])
    assert abs(np.median(ratio) - 1) < 0.01
    psf = piff.read(str(tmp_path / "bf.piff"))
    assert isinstance(psf, bfpsf.piff.BrighterFatterPSF)


def test_amplifiers_route_gain_and_shifts_by_position(fits, calibration_file, tmp_path):
    from bfpsf import Calibration

    one = Calibration.read(calibration_file)
    weak = replace(one, gain=1.2, amplifier="C01",
                   shifts=BoundaryShifts(0.5 * one.shifts.north, 0.5 * one.shifts.east,
                                         check=False))
    detector = DetectorCalibration({"C00": replace(one, amplifier="C00"), "C01": weak})
    sections = {"C00": "[1:200,1:400]", "C01": "[201:400,1:400]"}
    inner = fits["bf"][0].psf
    both = bfpsf.piff.BrighterFatterPSF(inner, detector, amplifiers=sections)
    both.set_context(fits["bf"][0].wcs)
    for x, calib in ((120.0, one), (320.0, weak)):
        alone = bfpsf.piff.BrighterFatterPSF(inner, calib)
        alone.set_context(fits["bf"][0].wcs)
        np.testing.assert_array_equal(both.draw(x, 150.0, chipnum=0, flux=2e5).array,
                                      alone.draw(x, 150.0, chipnum=0, flux=2e5).array)
    # the two amplifiers' operators differ (else the routing above could not be told apart)
    weak_alone = bfpsf.piff.BrighterFatterPSF(inner, weak)
    weak_alone.set_context(fits["bf"][0].wcs)
    assert not np.allclose(both.draw(120.0, 150.0, chipnum=0, flux=2e5).array,
                           weak_alone.draw(120.0, 150.0, chipnum=0, flux=2e5).array)
    path = tmp_path / "amps.piff"
    both.write(str(path))
    read = piff.read(str(path))
    assert [amp.section for amp in read.amplifiers[None]] == [(1, 200, 1, 400),
                                                              (201, 400, 1, 400)]
    np.testing.assert_array_equal(read.draw(320.0, 150.0, chipnum=0, flux=2e5).array,
                                  both.draw(320.0, 150.0, chipnum=0, flux=2e5).array)
    with pytest.raises(BFPSFInputError, match="give the section of each in 'amplifiers'"):
        bfpsf.piff.BrighterFatterPSF(inner, detector)


def test_single_chip_and_gsobject_inner_psfs(field, calibration_file, tmp_path):
    """A SingleChip inner PSF (two exposures as two chips) and a GSObject (Moffat) model."""
    images = [str(image) for image, _ in field[:2]]
    catalogs = [str(catalog) for _, catalog in field[:2]]
    inner = {"type": "SingleChip", "model": {"type": "Moffat", "beta": 3.5, "fastfit": True},
             "interp": {"type": "Polynomial", "order": 1}}
    config = piff_config(images[0], catalogs[0], psf=inner, gain=GAIN, calib=calibration_file)
    config["input"].update(image_file_name=images, cat_file_name=catalogs, nstars=40)
    psf = piff.process(config)
    assert isinstance(psf.psf, piff.SingleChipPSF) and sorted(psf.psf.psf_by_chip) == [0, 1]
    for chipnum in (0, 1):
        faint = psf.draw(200.0, 200.0, chipnum=chipnum, flux=1e3).FindAdaptiveMom()
        bright = psf.draw(200.0, 200.0, chipnum=chipnum, flux=4e5).FindAdaptiveMom()
        assert bright.moments_sigma > 1.005 * faint.moments_sigma
    psf.write(str(tmp_path / "chips.piff"))
    read = piff.read(str(tmp_path / "chips.piff"))
    np.testing.assert_array_equal(read.draw(90.0, 310.0, chipnum=1, flux=3e5).array,
                                  psf.draw(90.0, 310.0, chipnum=1, flux=3e5).array)


def test_config_errors_are_one_line(calibration_file):
    with pytest.raises(BFPSFInputError, match="needs the key 'calib'"):
        piff.PSF.process({"type": "BrighterFatter", "psf": inner_psf_config()})
    with pytest.raises(BFPSFInputError, match=r"has no key\(s\) \['gain'\]"):
        piff.PSF.process({"type": "BrighterFatter", "psf": inner_psf_config(),
                          "calib": str(calibration_file), "gain": 2})
    with pytest.raises(BFPSFInputError, match="missing.fits"):
        piff.PSF.process({"type": "BrighterFatter", "psf": inner_psf_config(),
                          "calib": "missing.fits"})


def test_bfpsf_works_without_piff():
    # importing the rest of bfpsf does not import piff
    code = ("import sys, bfpsf, bfpsf.cli, bfpsf.model.psf, bfpsf.interop.galsim_sensor, "
            "bfpsf.galsim, bfpsf.model.product; bfpsf.FluxDependentPSF; "
            "assert 'piff' not in sys.modules, 'piff imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
    # with piff not installed (its import blocked), bfpsf runs and only bfpsf.piff fails
    blocked = ("import sys\nclass Block:\n    def find_spec(self, name, path=None, target=None):"
               "\n        if name == 'piff' or name.startswith('piff.'):\n"
               "            raise ImportError('No module named piff')\n"
               "sys.meta_path.insert(0, Block())\n"
               "import numpy, bfpsf\nfrom bfpsf.cli import main\n"
               "image = bfpsf.redistribute(numpy.ones((8, 8)) * 1e4, "
               "bfpsf.BoundaryShifts(numpy.zeros((3, 3)), numpy.zeros((3, 3))))\n"
               "try:\n    import bfpsf.piff\nexcept ImportError as error:\n"
               "    assert 'piff' in str(error)\nelse:\n    raise AssertionError('imported')\n")
    subprocess.run([sys.executable, "-c", blocked], check=True)


def test_extras_name_piff_and_all_holds_every_optional_part():
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml")
                            .read_text())["project"]
    extras = project["optional-dependencies"]
    assert extras["piff"] == ["piff>=1.7"] and "piff>=1.7" in extras["test"]
    optional = {name for key, names in extras.items() if key not in ("test", "all")
                for name in names}
    assert optional <= set(extras["all"])


@pytest.mark.slow
def test_acceptance_on_a_silicon_sensor_field(tmp_path):
    """Issue 23's targets on the user's path: SiliconSensor flats -> bfpsf calibrate ->
    Piff on SiliconSensor exposures (PSF varying over the field, 3-120 ke- of peak), plain
    Piff and BrighterFatter around it, each star's residual minus that of its BF-free twin
    (same photons and noise: `write_field` with ``control=True``). The flats are those of
    benchmarks/bench_piff.py (64 of 512^2 px; 256^2 px leave a carried error of 50 % on the
    e1 change); 15 minutes on a shared 2-core machine; the 12-exposure run is the benchmark."""
    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma
    from bfpsf.piff.field import acceptance, carried_errors
    from bfpsf.validation.simulate_flats import simulate_flats

    flats = simulate_flats("lsst_itl_50_8", np.geomspace(5e3, 1e5, 8), pairs=4, size=512,
                           nsteps=10, gain=GAIN, read_noise_e=5.0, seed=1031)
    calibration = calibrate([image for image, _, _ in flats],
                            exptimes=[time for _, time, _ in flats])
    calibration.write(tmp_path / "calib.fits")
    files, controls = write_field(tmp_path / "field", n_exposures=3, sensor="lsst_itl_50_8",
                                  seed=41, control=True)
    result = acceptance(files, tmp_path / "calib.fits", gain=GAIN, controls=controls)
    carried = carried_errors(calibration, diffusion=silicon_diffusion_sigma("lsst_itl_50_8"))
    assert result["size_plain"].slope > 20 * result["size_plain"].slope_err
    # size: <= 5 % of plain Piff's BF slope, within 2 sigma of the measurement's error and
    # the calibration's carried error (its shift samples: the flats' statistics)
    size_sigma = np.hypot(result["size_ratio_err"], carried["size"])
    assert abs(result["size_ratio"]) < 0.05 + 2 * size_sigma, (result["size_ratio"], carried)
    # e1: <= 20 % of plain Piff's, or within 2 sigma (measurement and calibration)
    e1_sigma = np.hypot(result["e1_ratio_err"], carried["e1"])
    assert abs(result["e1_ratio"]) < max(0.2, 2 * e1_sigma), (result["e1_ratio"], carried)
    assert result["time_ratio"] < 2.0


def test_refined_calibration_brings_its_empirical_term(fits, calibration_file, tmp_path):
    """A calibration refined with an EMPIRICAL term (`bfpsf diagnose --output-calib`):
    BrighterFatter adds the term to every drawn star after the redistribution, at the star's
    charge (so its plain Mxx grows by c g F / F_ref), and keeps it through write / read."""
    from bfpsf import Calibration
    from bfpsf.model.empirical import EmpiricalTerm

    one = Calibration.read(calibration_file)
    term = EmpiricalTerm({"xx": {"constant": 0.08}, "yy": {"constant": 0.0}})
    refined = replace(one, refinement={"empirical": term.to_dict()})
    inner = fits["bf"][0].psf
    plain, with_term = (bfpsf.piff.BrighterFatterPSF(inner, calib) for calib in (one, refined))
    for psf in (plain, with_term):
        psf.set_context(fits["bf"][0].wcs)
    assert plain.amplifiers[None][0].empirical is None
    flux = 4e5
    before = plain.draw(150.3, 220.8, chipnum=0, flux=flux, stamp_size=41).array
    after = with_term.draw(150.3, 220.8, chipnum=0, flux=flux, stamp_size=41).array
    np.testing.assert_allclose(after - before, term.delta(before, GAIN * before.sum()),
                               rtol=0, atol=1e-9 * before.max())
    y, x = np.mgrid[:41, :41].astype(float)

    def mxx(image):
        cx = (image * x).sum() / image.sum()
        return (image * (x - cx) ** 2).sum() / image.sum()

    assert mxx(after) - mxx(before) == pytest.approx(term.variance_change(GAIN * flux)[0],
                                                     rel=0.03)
    path = tmp_path / "empirical.piff"
    with_term.write(str(path))
    read = piff.read(str(path))
    assert read.amplifiers[None][0].empirical == term.at_exposure()
    np.testing.assert_array_equal(read.draw(150.3, 220.8, chipnum=0, flux=flux,
                                            stamp_size=41).array, after)
