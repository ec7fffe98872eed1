"""Bad input never gives a traceback: each case is one line naming the file and the problem,
exit code 1 (through the CLI's main, as a user sees it), or a warning where a result is still
computed but may be wrong."""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.errors import BFPSFInputError, BFPSFValueError, BFPSFWarning, integer_at_least
from bfpsf.model.redistribution import redistribute
from bfpsf.shifts import BoundaryShifts

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 1e-7 * np.exp(-r), 2)
LEVELS = ((2e3, 1.0), (1e4, 5.0), (3e4, 15.0), (6e4, 30.0))


@pytest.fixture()
def flats(tmp_path, monkeypatch):
    """Four Poisson flat pairs, 64 x 64, in the working directory (short names in messages)."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(1)
    names = []
    for level, exptime in LEVELS:
        for member in (1, 2):
            name = f"f{int(exptime)}_{member}.fits"
            image = (rng.poisson(level, (64, 64)) / 1.5).astype(np.float32)
            fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(name)
            names.append(name)
    return names


def run(capsys, *argv):
    code = main(list(argv))
    return code, capsys.readouterr().err


def test_fits_file_cut_short(flats, capsys):
    data = Path(flats[0]).read_bytes()
    Path("short.fits").write_bytes(data[:len(data) // 2])
    assert run(capsys, "calibrate", "short.fits", *flats[1:], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: short.fits is not a readable flat FITS file (truncated, "
           "damaged or another format)\n")
    assert run(capsys, "measure", "short.fits", "--gain", "1.5", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: short.fits is not a readable FITS image (truncated, damaged "
           "or another format)\n")


def test_zero_variance_flats(flats, capsys):
    constant = np.full((64, 64), 100.0, dtype=np.float32)
    fits.PrimaryHDU(constant, header=fits.Header({"EXPTIME": 1.0})).writeto("zero.fits")
    assert run(capsys, "calibrate", "zero.fits", *flats[1:], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: flat zero.fits has zero variance (a constant image), not a "
           "flat-field exposure\n")


def test_flats_at_two_levels_give_no_calibration(tmp_path, monkeypatch, capsys):
    """Flats at two exposure levels do not constrain the photon transfer curve (gain, read
    noise and a(0, 0)) and give any gain: refused in one line, no calibration written (a new
    user's two-level flats were written with gain -0.046 and exit code 0)."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(2)
    names = []
    for level, exptime in ((2e4, 2.0), (6e4, 6.0)):
        for member in range(6):
            name = f"q{exptime:g}_{member}.fits"
            image = (rng.poisson(level, (64, 64)) / 1.5).astype(np.float32)
            fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(name)
            names.append(name)
    code, err = run(capsys, "calibrate", *names, "-o", "c.fits")
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith(f"bfpsf calibrate: error: the photon transfer curve of flats "
                          f"{names[0]} ... {names[-1]} (6 pairs at 2 exposure level(s)) gives "
                          f"a gain of "), err
    assert err.endswith("it needs pairs at 3 or more levels over the flux range, their "
                        "variance growing with their mean)\n"), err
    assert not Path("c.fits").exists()


def test_same_file_as_both_members_of_a_pair(flats, capsys):
    assert run(capsys, "calibrate", flats[0], flats[0], *flats[2:], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: flat f1_1.fits is given twice: each file may be used once\n")


def test_identical_copies_as_a_pair(flats, capsys):
    Path("copy.fits").write_bytes(Path(flats[0]).read_bytes())
    assert run(capsys, "calibrate", flats[0], "copy.fits", *flats[2:], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: flats f1_1.fits and copy.fits are identical (their "
           "difference has zero variance): a pair needs two exposures\n")


def test_same_pair_listed_twice(flats, capsys):
    assert run(capsys, "calibrate", *flats, *flats[:2], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: flat f1_1.fits is given twice: each file may be used once\n")


def test_same_image_given_twice(flats, capsys):
    assert run(capsys, "measure", flats[0], flats[0], "--gain", "1.5", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: image f1_1.fits is given twice: each file may be used once\n")


def test_maxlag_bounded_by_memory_time_and_image_size(flats, capsys):
    assert run(capsys, "calibrate", *flats, "-o", "c.fits", "--maxlag", "60") == (
        1, "bfpsf calibrate: error: maxlag 60 is too large for the full PTC model: its memory "
           "and time grow as (maxlag + 1)^6 (384 GiB here); use maxlag <= 12 or the "
           "exponential PTC model\n")
    assert run(capsys, "calibrate", *flats, "-o", "c.fits", "--maxlag", "40",
               "--model", "exponential") == (
        1, "bfpsf calibrate: error: flat f1_1.fits (64 x 64 pixels) is too small for maxlag "
           "40 inside its 10-pixel edge border (--edge): give maxlag < 22 or a smaller edge\n")
    assert run(capsys, "calibrate", *flats, "-o", "c.fits", "--maxlag", "40", "--edge", "0",
               "--model", "exponential") == (
        1, "bfpsf calibrate: error: flat f1_1.fits (64 x 64 pixels) is too small for maxlag "
           "40: give maxlag < 32\n")


def test_ecsv_given_as_calibration_or_psf(flats, capsys):
    Table({"x": [1.0]}).write("t.ecsv")
    assert run(capsys, "measure", flats[0], "--calib", "t.ecsv", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: t.ecsv is not a bfpsf calibration file (not FITS)\n")
    assert run(capsys, "photometry", flats[0], "--psf", "t.ecsv", "-o", "p.ecsv") == (
        1, "bfpsf photometry: error: t.ecsv is not a bfpsf PSF product file (not FITS)\n")


def test_calibration_with_a_missing_hdu_or_column(capsys, tmp_path, monkeypatch):
    from test_product import calibration as calibration_fixture

    monkeypatch.chdir(tmp_path)
    calibration = calibration_fixture.__wrapped__()
    calibration.write("c.fits")
    with fits.open("c.fits") as hdul:
        del hdul["PTC"]
        hdul.writeto("no_ptc.fits")
    with fits.open("c.fits") as hdul:
        summary = Table.read(hdul["SUMMARY"])
        summary.remove_column("gain")
        hdul["SUMMARY"] = fits.table_to_hdu(summary)
        hdul["SUMMARY"].name = "SUMMARY"
        hdul.writeto("no_gain.fits")
    fits.PrimaryHDU(np.ones((8, 8))).writeto("img.fits")
    assert run(capsys, "measure", "img.fits", "--calib", "no_ptc.fits", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: no_ptc.fits is an incomplete bfpsf calibration file "
           "(Extension 'PTC' not found)\n")
    assert run(capsys, "measure", "img.fits", "--calib", "no_gain.fits", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: no_gain.fits is an incomplete bfpsf calibration file (no "
           "column or extension 'gain')\n")


def test_slope_given_a_fits_file(flats, capsys):
    assert run(capsys, "slope", flats[0]) == (
        1, "bfpsf slope: error: f1_1.fits is not a readable star table (truncated, damaged or "
           "another format)\n")


def test_missing_catalog(flats, capsys):
    assert run(capsys, "measure", flats[0], "--gain", "1.5", "--catalog", "nosuch.ecsv",
               "-o", "m.ecsv") == (1, "bfpsf measure: error: catalog nosuch.ecsv does not exist\n")


def test_directory_given_as_an_image(flats, capsys, tmp_path):
    (tmp_path / "sub").mkdir()
    assert run(capsys, "measure", "sub", "--gain", "1.5", "-o", "m.ecsv") == (
        1, "bfpsf measure: error: image sub is a directory, not a file\n")
    assert run(capsys, "calibrate", "sub", *flats[1:], "-o", "c.fits") == (
        1, "bfpsf calibrate: error: flat file sub is a directory, not a file\n")


def test_photometry_fit_shape_must_be_odd(capsys, tmp_path, monkeypatch):
    from bfpsf.model.psf import FluxDependentPSF

    monkeypatch.chdir(tmp_path)
    y, x = np.mgrid[-12:13, -12:13]
    FluxDependentPSF(np.exp(-(x**2 + y**2) / 8.0), SHIFTS).write("psf.fits")
    image = np.zeros((40, 40), dtype=np.float32)
    image[20, 20] = 1e4
    fits.PrimaryHDU(image).writeto("img.fits")
    assert run(capsys, "photometry", "img.fits", "--psf", "psf.fits", "--gain", "1",
               "--fit-shape", "4", "-o", "p.ecsv") == (
        1, "bfpsf photometry: error: fit shape must be an odd number of pixels >= 3 (e.g. 5, "
           "7), got 4\n")


def test_photometry_fit_shape_wider_than_the_star_spacing():
    from bfpsf.measure.photometry import psf_photometry
    from bfpsf.model.psf import FluxDependentPSF

    y, x = np.mgrid[-12:13, -12:13]
    psf = FluxDependentPSF(np.exp(-(x**2 + y**2) / 8.0), SHIFTS)
    positions = np.array([(10.0 + 8 * i, 10.0 + 8 * j) for i in range(6) for j in range(6)])
    with pytest.raises(BFPSFValueError) as error:
        psf_photometry(np.zeros((60, 60)), psf, positions=positions, background_e=0.0,
                       fit_shape=41)
    assert str(error.value) == ("fit shape 41 px (group separation 41 px) puts 36 of the 36 "
                                "stars in one group fitted together (at most 25): the stars are "
                                "closer than that (give a smaller fit shape), or the "
                                "detection took noise for stars (a blank image, or a sky given "
                                "too low: check the image and --background)")


def test_fit_shape_set_by_an_outlying_grid_node_names_the_node():
    """A node fitted from too few stars (a new user's 10.2 px against 4.2-4.7) set a 31 px fit
    box, and the error blamed the image: it names the node."""
    import galsim

    from bfpsf.interop.photutils import outlying_nodes
    from bfpsf.measure.photometry import psf_photometry
    from bfpsf.model.gridded import GriddedFluxDependentPSF
    from bfpsf.model.psf import FluxDependentPSF

    nodes = [FluxDependentPSF.from_galsim(galsim.Gaussian(fwhm=fwhm), SHIFTS, oversampling=2,
                                          size=25) for fwhm in (4.2, 4.7, 4.4, 10.2)]
    psf = GriddedFluxDependentPSF(nodes, [0.0, 99.0], [0.0, 99.0])
    outliers, median = outlying_nodes(psf)
    assert [(x, y) for x, y, _, _ in outliers] == [(99.0, 99.0)]
    assert outliers[0][2] == pytest.approx(10.2, abs=0.1) and 4.4 < median < 4.8
    # a 10 % field variation is no outlier
    assert outlying_nodes(GriddedFluxDependentPSF(nodes[:2] * 2, [0.0, 99.0], [0.0, 99.0]))[0] == []
    positions = np.array([(10.0 + 12 * i, 10.0 + 12 * j) for i in range(7) for j in range(7)])
    with pytest.raises(BFPSFValueError) as error:
        psf_photometry(np.zeros((100, 100)), psf, positions=positions, background_e=0.0)
    assert str(error.value) == (
        "fit shape 31 px (group separation 31 px) puts 49 of the 49 "
        "stars in one group fitted together (at most 25): the PSF sets that fit shape from its "
        "grid node (x 99, y 99) 10.2 px against a median FWHM 4.6 px over the nodes: a node "
        "fitted from too few stars; refit the PSF with fewer --grid nodes or give a fit shape")


def test_simulate_unknown_sensor(capsys, tmp_path):
    code, err = run(capsys, "simulate", "flats", "--sensor", "nosuch", "-o",
                    str(tmp_path / "sim"), "--levels", "1000", "--size", "16")
    assert code == 1
    assert err.startswith("bfpsf simulate flats: error: unknown GalSim SiliconSensor 'nosuch'; GalSim "
                          "has lsst_e2v_32, ")
    assert "lsst_itl_50_8" in err and err.count("\n") == 1
    assert not (tmp_path / "sim").exists()


def test_redistribute_refuses_an_empty_image_and_honours_masks():
    with pytest.raises(BFPSFInputError) as error:
        redistribute(np.zeros((0, 0)), SHIFTS)
    assert str(error.value) == "image has no pixel (shape (0, 0))"
    image = np.full((9, 9), 1e4)
    mask = np.zeros(image.shape, dtype=bool)
    mask[4, 4] = True
    masked = np.ma.masked_array(image.copy(), mask=mask)
    masked.data[4, 4] = 1e9  # a bad value under the mask must not move any charge
    with pytest.raises(BFPSFInputError, match="image has 1 non-finite pixels"):
        redistribute(masked, SHIFTS)
    result = redistribute(masked, SHIFTS, nan_policy="interpolate")
    assert np.isnan(result[4, 4])
    np.testing.assert_allclose(result[~mask], redistribute(image, SHIFTS)[~mask], rtol=1e-12)


def test_huge_fluxes_warn_where_first_order_breaks():
    image = np.zeros((9, 9))
    image[4, 4] = 1e5
    redistribute(image, SHIFTS)  # fine: no warning (filterwarnings = error)
    image[4, 4] = 1e12
    with pytest.warns(BFPSFWarning, match="beyond the first-order BF model"):
        redistribute(image, SHIFTS)


def test_photometry_carries_the_blend_flags_of_the_detection():
    from bfpsf.model.galsim_profile import render_stars
    from bfpsf.measure.photometry import psf_photometry
    from bfpsf.measure.sources import SourceFlag
    from bfpsf.model.psf import FluxDependentPSF

    galsim = pytest.importorskip("galsim")
    y, x = np.mgrid[-12:13, -12:13]
    psf = FluxDependentPSF(np.exp(-(x**2 + y**2) / 8.0) / (8 * np.pi), SHIFTS)
    xy = np.array([[30.0, 30.0], [90.0, 40.0], [95.5, 43.0], [40.0, 90.0]])  # one close pair
    image = render_stars(galsim.Gaussian(sigma=2.0), xy, np.full(4, 2e5), (130, 130)) + 100.0
    image += np.random.default_rng(3).normal(0.0, 10.0, image.shape)
    result = psf_photometry(image, psf, background_e=100.0, read_noise_e=10.0, cross_terms=0,
                            weights="data")
    assert "source_flags" in result.colnames
    blended = (np.asarray(result["source_flags"]) & SourceFlag.BLENDED) != 0
    near_pair = np.hypot(result["x_fit"] - 92.7, result["y_fit"] - 41.5) < 6
    assert near_pair.sum() >= 1 and np.all(blended[near_pair])
    assert not blended[~near_pair].any()


@pytest.mark.parametrize("command", ["psf", "photometry", "diagnose"])
def test_background_must_be_finite(command, capsys):
    """--background nan or inf is refused before any work, in one line (argparse's exit 2)."""
    arguments = {"psf": ["x.fits", "--calib", "c.fits", "-o", "p.fits"],
                 "photometry": ["x.fits", "--psf", "p.fits", "-o", "p.ecsv"],
                 "diagnose": ["--flats", "f.fits", "--images", "x.fits"]}[command]
    for value in ("nan", "inf", "sky"):
        with pytest.raises(SystemExit) as exit_info:
            main([command, *arguments, "--background", value])
        assert exit_info.value.code == 2
        assert capsys.readouterr().err.splitlines()[-1] == (
            f"bfpsf {command}: error: argument --background: expected a finite sky level in "
            f"ADU, got '{value}'")


@pytest.mark.parametrize("value, accepted", [
    (3, 3), (3.0, 3), (np.int64(8), 8), (2, None), (2.5, None), ("8", None), (None, None),
    (float("nan"), None), (float("inf"), None)])
def test_integer_arguments_are_checked_in_one_place(value, accepted):
    """`integer_at_least`, the check of every integer argument: whole numbers at or above the
    bound pass as int; fractions, strings, None, NaN and inf are one-line errors."""
    if accepted is None:
        with pytest.raises(BFPSFValueError, match=r"^steps must be an integer >= 3, got "):
            integer_at_least("steps", value, 3)
    else:
        result = integer_at_least("steps", value, 3)
        assert (result, type(result)) == (accepted, int)


def test_psf_fwhm_is_taken_through_the_peak_not_the_origin():
    """A comatic P0's origin (its centroid) lies off its peak: the FWHM along x is the one
    through the peak (4.09 px through the origin against 3.91 on a new user's Kolmogorov x
    coma). Here a core of FWHM 3 px 1.5 px from the origin along y, on a halo of FWHM 8 px
    centred on the origin: 3.46 px through the peak's row, 3.98 px through the origin's."""
    from bfpsf.interop.photutils import psf_fwhm
    from bfpsf.model.psf import FluxDependentPSF

    def profile(x, y):
        core = np.exp(-(x ** 2 + (y - 1.5) ** 2) / (2 * (3.0 / 2.3548) ** 2))
        return core + 0.3 * np.exp(-(x ** 2 + y ** 2) / (2 * (8.0 / 2.3548) ** 2))

    def row_fwhm(y):
        x = np.linspace(0.0, 12.0, 120001)
        values = profile(x, y)
        return 2 * x[np.argmax(values < values[0] / 2)]

    nodes = (np.arange(51) - 25) / 2.0
    psf = FluxDependentPSF(profile(nodes[None, :], nodes[:, None]), SHIFTS, oversampling=2)
    peak_row = nodes[np.argmax(profile(0.0, nodes))]
    assert row_fwhm(0.0) > row_fwhm(peak_row) + 0.4
    assert psf_fwhm(psf) == pytest.approx(row_fwhm(peak_row), abs=0.03)
