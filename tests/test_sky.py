"""The sky surface of every command (`bfpsf.measure.sky`): the degree the sky pixels ask for,
and what a plane under a curved sky does to PSF photometry at defaults."""

import pathlib

import galsim
import numpy as np
import pytest

import bfpsf
from bfpsf.errors import BFPSFValueError
from bfpsf.measure.photometry import psf_photometry
from bfpsf.measure.prepare import prepare_image
from bfpsf.measure.sky import SkyModel, estimate_sky
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_fields import simulate_field


def _sky(kind, n):
    """A sky of 400 e- with a shape: flat, a gradient, a vignetting bowl (+24 e- at the
    edges' middle), a broad hump of scattered light off centre."""
    y, x = np.mgrid[:n, :n].astype(float)
    u, v = (x - n / 2) / (n / 2), (y - n / 2) / (n / 2)
    return 400.0 + {"flat": 0 * u, "plane": 30 * u - 20 * v, "bowl": 24 * (u ** 2 + v ** 2),
                    "hump": 40 * np.exp(-((u - 0.4) ** 2 + (v + 0.3) ** 2) / 0.5)}[kind]


@pytest.mark.parametrize("kind, chosen", [("flat", 1), ("plane", 1), ("bowl", 2),
                                          ("hump", "spline")])
def test_the_sky_takes_the_degree_its_pixels_ask_for(kind, chosen):
    """A flat or planar sky keeps a plane on every one of 4 noise draws (the criterion's
    false alarms would be curvature fitted to noise); a bowl takes degree 2, within 1 e- of
    the sky everywhere; a hump of scattered light (a Gaussian of 75 px) the spline sky,
    within 1.2 e- rms where the cubic is 2.7 e- from it (its best fit to the noiseless
    hump: 2.7 e- rms, 15 e- at a corner)."""
    rng = np.random.default_rng(3)
    sky = _sky(kind, 300)
    for _ in range(4):
        image = rng.poisson(sky) + rng.normal(0.0, 5.0, sky.shape)
        fitted = estimate_sky(image)
        assert fitted.kind == chosen
        if kind == "hump":  # noise at the spline's edges: 3-5 e- at the corners
            assert np.std(fitted.image() - sky) < 1.2
            assert np.std(estimate_sky(image, degree=3).image() - sky) > 2.5
        else:
            assert np.abs(fitted.image() - sky).max() < 1.0
    assert estimate_sky(image, degree=1).degree == 1
    with pytest.raises(BFPSFValueError, match="0, 1, 2, 3, 'spline' or 'auto'"):
        estimate_sky(image, degree="plane")


def test_the_spline_sky_is_a_surface():
    """The spline sky's basis sums to one everywhere (a constant is a spline), its image is
    its value at every pixel, and its level and slope are those at the image's centre."""
    shape = (300, 520)
    template = SkyModel.template("spline", shape)
    assert template.intervals == (2, 4) and len(template.coefficients) == 5 * 7
    y, x = np.mgrid[:shape[0], :shape[1]]
    np.testing.assert_allclose(template.basis(x.ravel(), y.ravel()).sum(axis=1), 1.0)
    rng = np.random.default_rng(5)
    sky = SkyModel(tuple(rng.normal(100.0, 10.0, 35)), 3, shape, 1.0, "", 0, (2, 4))
    image = sky.image()
    np.testing.assert_allclose(image[y[::37, ::41], x[::37, ::41]], sky(x[::37, ::41],
                                                                        y[::37, ::41]))
    assert sky.level == pytest.approx(sky(259.5, 149.5))
    assert sky.slope[0] == pytest.approx((sky(260.5, 149.5) - sky(258.5, 149.5)) / 2, rel=0.05)


@pytest.fixture(scope="module")
def bowl_field():
    """512^2 pixels of 70 Kolmogorov x obscured Airy stars (peaks 500-1.2e5 e-, no BF) on a
    vignetting bowl (+60 e- at the edges' middle on 600 e-): (data, x, y, flux, psf, sky)."""
    n = 512
    profile = galsim.Convolve(galsim.Kolmogorov(fwhm=2.6),
                              galsim.Airy(lam_over_diam=0.9, obscuration=0.4))
    bowl = SkyModel((600.0, 0.0, 0.0, 60.0, 0.0, 60.0), 2, (n, n), np.nan, "known")
    field = simulate_field(profile, n_images=1, shape=(n, n), n_stars=70,
                           peak_range_e=(5e2, 1.2e5), min_separation=20.0, sensor=None,
                           sky_surface=bowl, seed=1, stamp=256)
    truth = field.truth[0]
    psf = bfpsf.FluxDependentPSF.from_galsim(
        profile, BoundaryShifts.from_radial_profile(lambda r: 0 * r, 2))
    return (field.images[0], *(np.asarray(truth[name], float) for name in ("x", "y", "flux_e")),
            psf, bowl)


def test_photometry_at_defaults_under_a_curved_sky(bowl_field):
    """The bowl: the plane, the default before, read the 13 faint stars (below 20 ke-) with
    a spread of 67 mmag against the 18 mmag of the true sky; the sky the pixels ask for
    (degree 2), 19 mmag, and the 27 bright ones 0.1 mmag from the true sky's."""
    data, x, y, flux, psf, bowl = bowl_field

    def offsets(prepared):
        table = psf_photometry(prepared, psf, read_noise_e=5.0)
        distance = np.hypot(table["x_fit"][None] - x[:, None],
                            table["y_fit"][None] - y[:, None])
        nearest = np.argmin(distance, axis=1)  # each star's fit
        assert distance[np.arange(len(x)), nearest].max() < 0.5  # every star found
        fitted = np.asarray(table["flux_fit"], float)[nearest]
        return table.meta["sky"]["degree"], 1e3 * 2.5 * np.log10(flux / fitted)

    def spread(values):
        return 1.4826 * np.median(np.abs(values - np.median(values)))

    faint, bright = flux < 2e4, flux > 2e5
    degree, chosen = offsets(prepare_image(data))
    _, plane = offsets(prepare_image(data, sky_degree=1))
    _, true = offsets(prepare_image(data).with_sky(bowl))
    assert degree == 2
    assert spread(plane[faint]) > 2.5 * spread(true[faint])
    assert spread(chosen[faint]) < 1.3 * spread(true[faint])
    assert abs(np.median(chosen[bright] - true[bright])) < 2.0


def test_the_commands_take_the_sky_degree(bowl_field, tmp_path):
    """`bfpsf photometry` at its defaults chooses the bowl's degree 2 (in its JSON),
    ``--sky-degree 1`` holds it at a plane and ``spline`` asks for the spline; a degree
    beyond 3 is refused; `bfpsf measure`
    says its degree."""
    import json

    from astropy.io import fits

    from bfpsf.cli import main

    data, _, _, _, psf, _ = bowl_field
    image, product = tmp_path / "bowl.fits", tmp_path / "psf.fits"
    fits.PrimaryHDU(data.astype(np.float32), header=fits.Header({"EXPTIME": 1.0})).writeto(
        image)
    psf.write(product)
    for option, degree in (([], 2), (["--sky-degree", "1"], 1),
                           (["--sky-degree", "spline"], "spline")):
        out = tmp_path / f"phot{degree}.ecsv"
        assert main(["photometry", str(image), "--psf", str(product), "--gain", "1",
                     "--read-noise", "5", "-o", str(out), "--json", f"{out}.json",
                     *option]) == 0
        summary = json.loads(pathlib.Path(f"{out}.json").read_text())
        assert [entry["sky"]["degree"] for entry in summary["images"]] == [degree], summary
    with pytest.raises(SystemExit):
        main(["photometry", str(image), "--psf", str(product), "--gain", "1", "-o",
              str(tmp_path / "x.ecsv"), "--sky-degree", "4"])
    # measure's sky, the same surface, says its degree too
    assert main(["measure", str(image), "--gain", "1", "-o", str(tmp_path / "stars.ecsv"),
                 "--json", str(tmp_path / "stars.json")]) == 0
    summary = json.loads((tmp_path / "stars.json").read_text())
    assert [entry["sky_degree"] for entry in summary["images"]] == [2]


def test_psf_refuses_wings_that_took_the_sky(tmp_path, capsys):
    """A sky 120 e- darker at the edges' middle held at a plane: the sky-and-wings fit gave
    the light beyond P0's support as twice the light inside it (flux correction 3.0 +- 0.6;
    a new user's vignetted image, 2.98, was written and read every flux 1.2 mag off). No
    product is written, with a one-line error; at defaults the sky's degree 2 gives 1.005
    +- 0.002 for this Moffat (beta 3: 0.1 % beyond 12.5 px)."""
    from astropy.io import fits

    from bfpsf.cli import main
    from test_photometry import SHIFTS, make_calibration

    n = 384
    bowl = SkyModel((800.0, 0.0, 0.0, -120.0, 0.0, -120.0), 2, (n, n), np.nan, "known")
    field = simulate_field(galsim.Moffat(beta=3.0, fwhm=3.5), n_images=1, shape=(n, n),
                           n_stars=60, peak_range_e=(1e3, 1e5), min_separation=25.0,
                           sensor=None, sky_surface=bowl, seed=3)
    image, calib = tmp_path / "vignetted.fits", tmp_path / "calib.fits"
    fits.PrimaryHDU(field.images[0], header=fits.Header({"EXPTIME": 1.0})).writeto(image)
    make_calibration(SHIFTS, 1.0, 5.0).write(calib)
    out = tmp_path / "psf.fits"
    assert main(["psf", str(image), "--calib", str(calib), "-o", str(out),
                 "--sky-degree", "1"]) == 1
    error = capsys.readouterr().err
    assert "the light beyond P0's support came out" in error and "not written" in error
    assert not out.exists()
    assert main(["psf", str(image), "--calib", str(calib), "-o", str(out)]) == 0
    product = bfpsf.read_psf(out)
    assert product.flux_correction == pytest.approx(1.0, abs=0.02)
    # a correction measured to 5 % (a sky no low-order surface follows) is said by
    # photometry too, as the scale error of every flux; one measured to 0.2 % is not
    for error, said in ((product.flux_correction_err, False), (0.05, True)):
        product.flux_correction_err = error
        product.write(tmp_path / f"psf{error}.fits")
        capsys.readouterr()
        assert main(["photometry", str(image), "--psf", str(tmp_path / f"psf{error}.fits"),
                     "--gain", "1", "--read-noise", "5", "-o",
                     str(tmp_path / f"phot{error}.ecsv")]) == 0
        assert ("every flux carries a common scale error of +- 5"
                in capsys.readouterr().err) == said


def test_psf_names_the_image_whose_sky_is_not_the_surface(tmp_path, capsys):
    """A joint `bfpsf psf` of an image whose halves differ by 150 e- (amplifiers' offsets
    given as one HDU: no surface follows the step) and a flat one: the JSON gives each
    image's sky scatter about its fitted sky over its pixel-to-pixel variance, and the
    warning names the stepped image, not the flat one (a new user's joint fit of a flat
    image and a ringed one gave a flux correction 3 sigma high, and nothing said which)."""
    import json

    from astropy.io import fits

    from bfpsf.cli import main
    from test_photometry import SHIFTS, make_calibration

    n = 300
    paths = []
    for name, step in (("flat", 0.0), ("stepped", 150.0)):
        field = simulate_field(galsim.Moffat(beta=3.0, fwhm=3.5), n_images=1, shape=(n, n),
                               n_stars=40, peak_range_e=(1e3, 1e5), min_separation=25.0,
                               sensor=None, seed=5 if step else 6,
                               sky_surface=lambda x, y, step=step: 300.0 + step * (x > n / 2))
        paths.append(tmp_path / f"{name}.fits")
        fits.PrimaryHDU(field.images[0], header=fits.Header({"EXPTIME": 1.0})).writeto(
            paths[-1])
    make_calibration(SHIFTS, 1.0, 5.0).write(tmp_path / "calib.fits")
    capsys.readouterr()
    assert main(["psf", *map(str, paths), "--calib", str(tmp_path / "calib.fits"), "-o",
                 str(tmp_path / "psf.fits"), "--json", str(tmp_path / "psf.json")]) == 0
    error = capsys.readouterr().err
    scatter = [entry["sky_scatter"] for entry in
               json.loads((tmp_path / "psf.json").read_text())["images"]]
    print(scatter)
    assert scatter[0] < 1.1 < 1.2 < scatter[1]
    assert f"{paths[1]}: its sky pixels scatter" in error
    assert f"{paths[0]}: its sky pixels scatter" not in error
