"""Saturation from the header alone: every star with a clipped pixel is flagged by measure and
photometry, and left out (and counted) by psf; the level is read from SATURATE or a variant,
the primary header of a multi-extension file, and moved by the subtracted overscan."""

import json

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.cli import main
from bfpsf.errors import BFPSFInputError
from bfpsf.io.amplifiers import read_amplifiers
from bfpsf.io.saturation import (SATURATION_KEYWORDS, header_saturation, saturated_stars,
                                 saturation_e)

galsim = pytest.importorskip("galsim")

GAIN = 1.5
SATURATE = 30000.0  # ADU


@pytest.fixture(scope="module")
def clipped_image(tmp_path_factory):
    """A 192^2 image of 36 Moffat stars (fluxes 2e4-3e6 e-, seed 11), clipped at SATURATE,
    with the truth: which stars have a pixel at or above it before clipping."""
    from bfpsf.model.galsim_profile import render_stars

    rng = np.random.default_rng(11)
    grid = np.linspace(21, 171, 6)
    xy = np.array([(x, y) for x in grid for y in grid]) + rng.uniform(-0.5, 0.5, (36, 2))
    flux = np.geomspace(2e4, 3e6, 36)
    rng.shuffle(flux)
    image_e = render_stars(galsim.Moffat(beta=3.0, fwhm=3.0), xy, flux, (192, 192)) + 200.0
    image_adu = (rng.poisson(image_e) + rng.normal(0.0, 5.0, image_e.shape)) / GAIN
    rows, columns = np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)
    truth = np.array([image_adu[r - 4:r + 5, c - 4:c + 5].max() >= SATURATE
                      for r, c in zip(rows, columns)])
    directory = tmp_path_factory.mktemp("saturation")
    path = directory / "clipped.fits"
    header = fits.Header({"EXPTIME": 10.0, "GAIN": GAIN, "SATURATE": SATURATE})
    fits.PrimaryHDU(np.minimum(image_adu, SATURATE).astype(np.float32),
                    header=header).writeto(path)
    assert 5 <= truth.sum() <= 20  # both kinds present, or the test cannot fail
    return path, xy, truth


def _matched(xy, x, y):
    from scipy.spatial import cKDTree

    distance, index = cKDTree(xy).query(np.column_stack([x, y]))
    assert np.all(distance < 1.5)
    return index


def test_header_keywords_and_bad_values():
    for keyword in SATURATION_KEYWORDS:
        assert header_saturation(fits.Header({keyword: 1234})) == 1234.0
    assert header_saturation(fits.Header({"EXPTIME": 1.0})) is None
    for bad in ("lots", -5, 0, True):
        with pytest.raises(BFPSFInputError, match=r"^img.fits: header SATURATE = .* is not a "
                                                  r"saturation level"):
            header_saturation(fits.Header({"SATURATE": bad}), where="img.fits")


def test_primary_header_and_overscan(tmp_path):
    """A level in the primary header reaches each amplifier; the overscan (here 1000 ADU)
    lowers it in the subtracted pixels."""
    data = np.full((20, 30), 1000.0)
    data[5, 5] = 60000.0
    amp = fits.ImageHDU(data, name="A1")
    amp.header["DATASEC"] = "[1:20,1:20]"
    amp.header["BIASSEC"] = "[21:30,1:20]"
    primary = fits.PrimaryHDU(header=fits.Header({"SATURATE": 60000.0, "EXPTIME": 1.0}))
    fits.HDUList([primary, amp]).writeto(tmp_path / "mef.fits")
    (amplifier,) = read_amplifiers(tmp_path / "mef.fits")
    level = saturation_e(amplifier, 2.0)
    assert level == pytest.approx(2.0 * (60000.0 - 1000.0))
    assert saturated_stars(amplifier.data * 2.0, level, [5, 15], [5, 15], 5).tolist() == [
        True, False]


def test_turnoff_lowers_the_level():
    class Turnoff:
        turnoff_e, turnoff_detected = 5e4, True

    class Amplifier:
        header, label, overscan_adu = fits.Header({"SATURATE": 6e4}), "x.fits", None

    assert saturation_e(Amplifier, 1.5, None, Turnoff) == 5e4
    Turnoff.turnoff_detected = False
    assert saturation_e(Amplifier, 1.5, None, Turnoff) == 9e4


def test_measure_and_photometry_flag_every_saturated_star(clipped_image, tmp_path, capsys):
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.shifts import BoundaryShifts
    from astropy.table import Table

    path, xy, truth = clipped_image
    out = tmp_path / "m.ecsv"
    assert main(["measure", str(path), "-o", str(out), "--json", str(tmp_path / "m.json")]) == 0
    stars = Table.read(out)
    flagged = (np.asarray(stars["flags"]) & 8) != 0
    index = _matched(xy, stars["x"], stars["y"])
    assert len(stars) == len(xy)
    np.testing.assert_array_equal(flagged, truth[index])
    summary = json.loads((tmp_path / "m.json").read_text())
    assert summary["n_saturated"] == truth.sum()

    y, x = np.mgrid[-12:13, -12:13]
    shifts = BoundaryShifts.from_radial_profile(lambda r: 1e-8 * np.exp(-r), 2)
    FluxDependentPSF(np.exp(-(x**2 + y**2) / 6.5) / (6.5 * np.pi), shifts,
                     gain=GAIN, flux_unit="electron").write(tmp_path / "psf.fits")
    out = tmp_path / "p.ecsv"
    assert main(["photometry", str(path), "--psf", str(tmp_path / "psf.fits"), "-o", str(out),
                 "--fit-shape", "7"]) == 0
    photometry = Table.read(out)
    index = _matched(xy, photometry["x_fit"], photometry["y_fit"])
    np.testing.assert_array_equal(np.asarray(photometry["saturated"]), truth[index])
    # and in the source flags, as measure flags them
    np.testing.assert_array_equal((np.asarray(photometry["source_flags"]) & 8) != 0,
                                  truth[index])
    assert f"{truth.sum()} of them saturated" in capsys.readouterr().out


def test_psf_leaves_saturated_stars_out(clipped_image, tmp_path, capsys):
    from test_product import calibration as calibration_fixture

    path, _, truth = clipped_image
    calibration_fixture.__wrapped__().write(tmp_path / "c.fits")
    summary_path = tmp_path / "psf.json"
    assert main(["psf", str(path), "--calib", str(tmp_path / "c.fits"), "-o",
                 str(tmp_path / "psf.fits"), "--json", str(summary_path),
                 "--max-iterations", "8"]) == 0
    summary = json.loads(summary_path.read_text())
    assert summary["n_saturated"] == truth.sum()
    assert summary["images"][0]["n_isolated"] == len(truth) - truth.sum()
