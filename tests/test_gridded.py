"""P(F, x, y): the gridded flux-dependent PSF, its joint fit, photutils, GalSim and the product."""

import json

import galsim
import numpy as np
import pytest

from bfpsf.errors import BFPSFValueError
from bfpsf.model.galsim_profile import render_stars
from bfpsf.model.gridded import GriddedFluxDependentPSF, bilinear_weights, grid_node_positions
from bfpsf.model.psf import FluxDependentPSF, pixelised_stamp
from bfpsf.model.psf_fit import fit_psf
from bfpsf.model.redistribution import redistribute
from bfpsf.shifts import BoundaryShifts

#: E2V-like shifts, as tests/test_psf_fit.py.
SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
LENGTH = 288
FWHM_RANGE = (3.0, 3.9)  # 30 % over the image, linear in x


def fwhm_at(x):
    return FWHM_RANGE[0] + (FWHM_RANGE[1] - FWHM_RANGE[0]) * x / (LENGTH - 1)


def moffat(x):
    return galsim.Moffat(beta=3.0, fwhm=fwhm_at(x))


def gaussian_size(stamp, sigma=2.5):
    half = stamp.shape[0] // 2
    y, x = np.mgrid[-half:half + 1, -half:half + 1]
    weighted = stamp * np.exp(-(x**2 + y**2) / (2 * sigma**2))
    return (weighted * (x**2 + y**2)).sum() / weighted.sum() / 2


@pytest.fixture(scope="module")
def varying_field():
    """64 noiseless stars, peaks 3-120 ke-, FWHM 3.0 -> 3.9 px along x, BF applied."""
    rng = np.random.default_rng(2)
    grid = 36 * (np.arange(8) + 0.5)
    xy = np.array([(x, y) for y in grid for x in grid]) + rng.uniform(-0.5, 0.5, (64, 2))
    peaks = np.exp(rng.uniform(np.log(3e3), np.log(1.2e5), 64))
    image = np.zeros((LENGTH, LENGTH))
    fluxes = []
    for (x, y), peak in zip(xy, peaks):
        profile = moffat(x)
        fluxes.append(peak / galsim.Convolve(profile, galsim.Pixel(1.0)).xValue(0, 0))
        image += render_stars(profile, [(x, y)], [fluxes[-1]], image.shape)
    return redistribute(image, SHIFTS, workers=1), xy, np.array(fluxes), peaks


@pytest.fixture(scope="module")
def fits(varying_field):
    image, xy, _, _ = varying_field
    gridded = fit_psf(image, xy, SHIFTS, oversampling=2, size=21, read_noise=5.0, grid=(3, 1))
    single = fit_psf(image, xy, SHIFTS, oversampling=2, size=21, read_noise=5.0)
    return gridded, single


def test_bilinear_weights_interpolate_and_clamp():
    x_nodes, y_nodes = grid_node_positions(3, 100), grid_node_positions(2, 50)
    assert np.allclose(x_nodes, [0, 49.5, 99]) and np.allclose(y_nodes, [0, 49])
    assert grid_node_positions(1, 100) == pytest.approx([49.5])
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-20, 120, 200), rng.uniform(-20, 70, 200)
    indices, weights = bilinear_weights(x, y, x_nodes, y_nodes)
    assert np.allclose(weights.sum(axis=-1), 1) and np.all(weights >= 0)
    # Linear functions of the node coordinates are reproduced inside the grid (clamped out).
    node_x = np.tile(x_nodes, 2)[indices]
    node_y = np.repeat(y_nodes, 3)[indices]
    assert np.allclose((weights * node_x).sum(-1), np.clip(x, 0, 99))
    assert np.allclose((weights * node_y).sum(-1), np.clip(y, 0, 49))
    # At a node, that node alone.
    indices, weights = bilinear_weights(49.5, 49.0, x_nodes, y_nodes)
    assert weights[indices == 4].sum() == pytest.approx(1.0)


def test_gridded_model_interpolates_its_node_models():
    nodes = [FluxDependentPSF.from_galsim(moffat(x), SHIFTS, oversampling=2, size=21)
             for x in (0.0, LENGTH - 1.0)]
    psf = GriddedFluxDependentPSF(nodes, [0.0, LENGTH - 1.0], [0.0])
    y, x = np.mgrid[90:111, 30:51]
    flux = 2e6
    at_node = psf.evaluate(x, y, flux, 0.2, 100.3)
    assert np.allclose(at_node, nodes[0].evaluate(x, y, flux, 0.2, 100.3), rtol=0, atol=1e-9)
    x_0 = 0.25 * (LENGTH - 1)
    mixed = psf.evaluate(x + 40, y, flux, x_0, 100.3)
    expected = sum(w * node.evaluate(x + 40, y, flux, x_0, 100.3)
                   for w, node in zip((0.75, 0.25), nodes))
    assert np.allclose(mixed, expected, rtol=0, atol=1e-9)
    # at(x, y) is the same model as one FluxDependentPSF (table mode).
    single = psf.at(x_0, 100.3)
    assert np.allclose(single.evaluate(x + 40, y, flux, x_0, 100.3), mixed, rtol=0, atol=1e-9)
    # The BF term is there and conserves charge (box holding the whole support).
    y, x = np.mgrid[85:116, 57:88]
    bf = psf.evaluate(x, y, flux, x_0, 100.3) - flux * psf.evaluate(x, y, 1.0, x_0, 100.3)
    assert np.abs(bf).max() > 1e-3 * flux * psf.evaluate(x, y, 1.0, x_0, 100.3).max()
    assert abs(bf.sum()) < 1e-6 * flux  # table mode: spline between phases (measured 1e-7)
    with pytest.raises(BFPSFValueError, match="FluxDependentPSF models"):
        GriddedFluxDependentPSF(nodes, [0.0, 1.0, 2.0], [0.0])
    with pytest.raises(BFPSFValueError, match="increasing"):
        GriddedFluxDependentPSF(nodes, [5.0, 1.0], [0.0])


def test_joint_grid_fit_follows_the_field(varying_field, fits):
    """The 3 x 1 grid fitted from all 64 stars recovers the PSF at its nodes and measures the
    stars' fluxes better than one P0 for the whole field."""
    _, _, fluxes, peaks = varying_field
    gridded, single = fits
    assert gridded.converged and isinstance(gridded.psf, GriddedFluxDependentPSF)
    assert isinstance(single.psf, FluxDependentPSF)
    for node, x_node in zip(gridded.psf.nodes, gridded.psf.x_nodes):
        truth = FluxDependentPSF.from_galsim(moffat(x_node), SHIFTS, oversampling=2, size=21)
        error = gaussian_size(pixelised_stamp(node, half_size=10)) / gaussian_size(
            pixelised_stamp(truth, half_size=10)) - 1
        # measured +0.6, +0.02, +0.4 %: the field between nodes is a mix of two Moffats,
        # which bilinear interpolation matches only to second order in the FWHM change.
        assert abs(error) < 0.01
    ratio_grid = np.asarray(gridded.stars["flux_fit"]) / fluxes
    ratio_single = np.asarray(single.stars["flux_fit"]) / fluxes
    # measured rms 0.25 % (grid) vs 0.45 % (one P0, not converged: no single shape fits)
    assert np.std(ratio_grid) < 0.7 * np.std(ratio_single)
    faint, bright = peaks < 1e4, peaks > 5e4
    bias = 2500 * np.log10(np.median(ratio_grid[bright]) / np.median(ratio_grid[faint]))
    assert abs(bias) < 2.0  # mmag; noiseless, limited by the interpolation (measured ~0.5)


@pytest.mark.parametrize("iterative", [False, True])
def test_photutils_photometry_with_the_gridded_model(varying_field, fits, iterative):
    from photutils.detection import DAOStarFinder

    from bfpsf.interop.photutils import make_psf_photometry

    image, xy, fluxes, _ = varying_field
    psf = fits[0].psf
    rng = np.random.default_rng(3)
    data = image + rng.normal(0.0, 5.0, image.shape)
    if iterative:
        finder = DAOStarFinder(threshold=1500.0, fwhm=3.5)  # above the model residuals
        photometry = make_psf_photometry(psf, iterative=True, maxiters=2, finder=finder,
                                         fit_shape=9)
        result = photometry(data, error=np.sqrt(np.clip(image, 0, None) + 25.0))
    else:
        photometry = make_psf_photometry(psf, fit_shape=9)
        init = {"x_init": xy[:, 0], "y_init": xy[:, 1]}
        from astropy.table import Table

        result = photometry(data, error=np.sqrt(np.clip(image, 0, None) + 25.0),
                            init_params=Table(init))
    distance = np.hypot(result["x_fit"][:, None] - xy[None, :, 0],
                        result["y_fit"][:, None] - xy[None, :, 1])
    nearest = distance.argmin(axis=1)
    assert len(result) == len(xy) and len(set(nearest)) == len(xy)
    assert np.all(distance.min(axis=1) < 0.05)
    # 9 x 9 fit box: the fraction of the flux outside it is in every star alike.
    ratio = np.asarray(result["flux_fit"]) / fluxes[nearest]
    assert np.std(ratio) < 0.01


def test_galsim_export_at_a_position(fits):
    from bfpsf.model.galsim_profile import to_galsim

    psf = fits[0].psf
    flux, x, y = 1.5e6, 100.3, 77.8
    profile, pixel_included = to_galsim(psf, flux, position=(x, y), x_phase=0.3, y_phase=-0.2)
    assert pixel_included
    drawn = profile.drawImage(nx=21, ny=21, scale=1.0, method="no_pixel",
                              offset=(0.3, -0.2)).array
    expected = psf.star_image(flux, x=x, y=y, x_phase=0.3, y_phase=-0.2, half_size=10) / flux
    # lanczos5 interpolation of a 2x-sampled PSF: a few 1e-4 of the peak
    assert np.abs(drawn - expected).max() < 2e-3 * expected.max()
    # without a position: the model at the grid's reference position (its centre), phase 0,
    # as star_image with no position
    profile, _ = to_galsim(psf, flux)
    drawn = profile.drawImage(nx=21, ny=21, scale=1.0, method="no_pixel").array
    expected = psf.star_image(flux, half_size=10) / flux
    assert np.abs(drawn - expected).max() < 2e-3 * expected.max()


def test_gridded_product_round_trip(fits, tmp_path):
    from astropy.io import fits as pyfits

    from bfpsf.model.product import PSF_SCHEMA_VERSION

    psf = fits[0].psf
    psf.calibration = "cal.fits"
    path = tmp_path / "grid.fits"
    psf.write(path)
    back = GriddedFluxDependentPSF.read(path)
    assert back.grid_shape == (1, 3) and np.array_equal(back.x_nodes, psf.x_nodes)
    assert back.calibration == "cal.fits"
    y, x = np.mgrid[60:80, 140:160]
    assert np.array_equal(back.evaluate(x, y, 8e5, 150.2, 70.1),
                          psf.evaluate(x, y, 8e5, 150.2, 70.1))
    with pyfits.open(path) as hdul:
        assert hdul[0].header["BFPSFVER"] == PSF_SCHEMA_VERSION >= 3
    single_path = tmp_path / "single.fits"
    fits[1].psf.write(single_path)
    with pytest.raises(BFPSFValueError, match="not a grid"):
        GriddedFluxDependentPSF.read(single_path)


def test_cli_psf_grid(varying_field, tmp_path, capsys):
    """``psf --grid 3 1`` follows the field; one P(F) on the same stars is said not to (a new
    user's FWHM 3.2 -> 3.9 px across 400 px gave photometry 50-73 mmag off from one side to
    the other without a word): its stars' size against it changes along x as GalSim's
    adaptive sigma does (+25.0 % from x 0 to 287; +22.8 +- 0.1 % measured when written, the
    stars at every phase against P0 at a pixel's centre), not along y; against the grid, by
    less than 1 %."""
    from bfpsf.cli import main
    from bfpsf.moments.adaptive import adaptive_moments
    from bfpsf.validation.simulate_spots import write_image_adu

    from test_photometry import make_calibration

    image, _, _, _ = varying_field
    rng = np.random.default_rng(4)
    noisy = image + rng.normal(0.0, np.sqrt(np.clip(image, 0, None) + 25.0))
    write_image_adu(tmp_path / "stars.fits", noisy, gain=1.0)
    make_calibration(SHIFTS, 1.0, 5.0).write(tmp_path / "calib.fits")
    args = ["psf", str(tmp_path / "stars.fits"), "--calib", str(tmp_path / "calib.fits"),
            "-o", str(tmp_path / "psf.fits"), "--size", "21", "--grid", "3", "1",
            "--json", str(tmp_path / "psf.json")]
    assert main(args) == 0
    summary = json.loads((tmp_path / "psf.json").read_text())
    assert summary["grid"]["nx"] == 3 and summary["converged"]
    # Node FWHM follows the field (3.0 -> 3.9 px, plus the pixel).
    widths = summary["grid"]["fwhm_pixels"]
    assert widths[0] < widths[1] < widths[2]
    assert isinstance(FluxDependentPSF.read(tmp_path / "psf.fits"), GriddedFluxDependentPSF)
    across = summary["images"][0]["size_across"]
    assert across["change"] < max(0.01, 5 * across["change_err"])
    assert "varies over the field" not in capsys.readouterr().err
    assert main([*args[:5], str(tmp_path / "single.fits"), "--size", "21", "--json",
                 str(tmp_path / "single.json")]) == 0
    err = capsys.readouterr().err
    across = json.loads((tmp_path / "single.json").read_text())["images"][0]["size_across"]
    ends = [adaptive_moments(galsim.Convolve(moffat(x), galsim.Pixel(1.0)).drawImage(
        nx=41, ny=41, scale=1.0, method="no_pixel").array).sigma for x in (0.0, LENGTH - 1.0)]
    truth = (ends[1] - ends[0]) / np.mean(ends)
    print(f"along x {across['along_x']:+.4f} +- {across['along_x_err']:.4f} against {truth:+.4f}"
          f", along y {across['along_y']:+.4f} +- {across['along_y_err']:.4f}")
    assert across["along_x"] == pytest.approx(truth, abs=3 * across["along_x_err"] + 0.03)
    assert abs(across["along_y"]) < 3 * across["along_y_err"] + 0.01
    assert "1 of 1 images the stars' size against P(F) changes across the image" in err
    assert "the PSF varies over the field" in err and "fit a grid (--grid NX NY" in err


def test_gridded_model_of_each_amplifier(fits, tmp_path):
    """Per-amplifier shifts on a grid: `for_amplifier` gives every node that amplifier's
    shifts (the model photometry uses for its stars), the product keeps them."""
    psf = fits[0].psf.with_shifts(SHIFTS)  # new node models: the fixture's stay untouched
    weak, strong = SHIFTS.scaled(0.6), SHIFTS.scaled(1.4)
    assert psf.for_amplifier("C00") is psf  # no per-amplifier shifts: the model itself
    psf.amplifier_shifts = {"C00": weak, "C01": strong}
    one = psf.for_amplifier("C01")
    assert all(node.shifts == strong for node in one.nodes)
    assert one.amplifier_shifts == psf.amplifier_shifts
    y, x = np.mgrid[60:80, 140:160]
    star = (x, y, 8e5, 150.2, 70.1)
    node_level = sum(weight * psf.nodes[k].with_shifts(strong).evaluate(*star)
                     for k, weight in zip(*psf.weights(150.2, 70.1)))
    np.testing.assert_allclose(one.evaluate(*star), node_level, rtol=1e-12, atol=1e-12)
    # the BF term scales with the shifts: the strong amplifier's differs from the weak one's
    assert not np.allclose(one.evaluate(*star), psf.for_amplifier("C00").evaluate(*star))
    with pytest.raises(BFPSFValueError, match="it has none for amplifier 'C02'"):
        psf.for_amplifier("C02")
    psf.write(tmp_path / "amps.fits")
    back = GriddedFluxDependentPSF.read(tmp_path / "amps.fits")
    assert set(back.amplifier_shifts) == {"C00", "C01"}
    assert back.amplifier_shifts["C01"] == strong


def test_unconverged_grid_fit_keeps_its_best_iterate():
    """A 3 x 3 grid fitted from 210 stars (the acceptance set's layout: FWHM 3.0 -> 3.9 px
    along x, 3 exposures of 320^2, 70 stars each; GalSim Moffats with photon noise and a
    300 e- sky, no BF) does not converge in 40 iterations: after iteration ~12 the update
    leaves the optimum again (its chi-square rose from 148e3 to 189e3 on the acceptance set).
    The fit returns the iterate of least chi-square; its model at the stars, against GalSim's
    truth at each star's own FWHM and phase, measured: e1 rms 0.0035 and sigma_x rms 0.0054
    px, against 0.0048 and 0.0072 for the last iterate."""
    from bfpsf.moments.adaptive import adaptive_moments_batch
    from bfpsf.measure.model_slopes import model_star_sizes
    from bfpsf.validation.simulate_fields import simulate_field

    shape = (320, 320)

    def profile(x, y):
        return galsim.Moffat(beta=3.5, fwhm=3.0 + 0.9 * x / (shape[1] - 1))

    field = simulate_field(profile, n_images=3, shape=shape, n_stars=70, min_separation=25.0,
                           sensor=None, shifts=None, sky_range_e=(300.0, 300.0), seed=7305)
    fit = fit_psf([image - 300.0 for image in field.images],
                  [np.column_stack([truth["x"], truth["y"]]) for truth in field.truth],
                  SHIFTS.scaled(0.0), grid=(3, 3), read_noise=5.0, sky_e=300.0)
    assert not fit.converged  # what the safeguard is for (this set is not fitted to 3e-4)
    x = np.concatenate([truth["x"] for truth in field.truth])
    y = np.concatenate([truth["y"] for truth in field.truth])
    model = model_star_sizes(fit.psf, np.full(x.shape, 1e4), x=x, y=y)
    truth = adaptive_moments_batch(np.array([
        profile(a, b).drawImage(nx=25, ny=25, scale=1.0,
                                offset=(a - np.rint(a), b - np.rint(b))).array
        for a, b in zip(x, y)]))
    e1 = (truth.mxx - truth.myy) / (truth.mxx + truth.myy)
    assert np.sqrt(np.mean((model["e1"] - e1)**2)) < 0.0042
    assert np.sqrt(np.mean((model["x"] - np.sqrt(truth.mxx))**2)) < 0.0065


def test_slopes_say_when_the_field_confounds_them(varying_field, caplog):
    """A PSF varying over the field gives the wide stars of a flux low peaks: the slope of
    size against peak is confounded with the field (a new user's -0.33 +- 0.10 px per 100
    ke- where BF made +0.013), and its scatter swamps the slope. `bf_slopes` says so, with the
    slope fitted beside a plane over the field: on the same stars without brighter-fatter
    (GalSim's stars, not redistributed; their peaks drawn independently of x here) that slope
    is zero within 3 of its errors, which are a fifth of the raw slope's or less (+0.093 +-
    0.039 raw, -0.0004 +- 0.0013 beside the plane, sigma_x, when written)."""
    import logging
    import re

    from bfpsf.measure.slopes import bf_slopes
    from bfpsf.measure.sources import measure_sources

    _, xy, fluxes, _ = varying_field
    image = sum(render_stars(moffat(x), [(x, y)], [flux], (LENGTH, LENGTH))
                for (x, y), flux in zip(xy, fluxes))
    rng = np.random.default_rng(5)
    noisy = image + rng.normal(0.0, np.sqrt(image + 25.0))
    stars = measure_sources(noisy)
    with caplog.at_level(logging.WARNING, logger="bfpsf"):
        slopes = bf_slopes(stars)
    number = r"(\d+\.\d+)"
    found = re.search(r"the stars' sigma_x changes across the field.*?([+-]\d+\.\d+) \+- "
                      rf"{number} % from x.*with a plane over the field beside it, "
                      rf"([+-]\d+\.\d+) \+- {number}", caplog.text)
    assert found, caplog.text
    change, _, beside, error = (float(value) for value in found.groups())
    print(f"raw {slopes['x'].slope:+.4f} +- {slopes['x'].slope_err:.4f}, change {change:+.1f} "
          f"%, beside the plane {beside:+.4f} +- {error:.4f}")
    assert change > 10.0  # 30 % in FWHM along x
    assert error < slopes["x"].slope_err / 5 and abs(beside) < 3 * error


def test_a_field_varying_psf_is_no_change_of_the_bf_slope(varying_field):
    """Every star's BF slope against the column (`star_slope_split`) on the field whose FWHM
    grows 30 % along x, without brighter-fatter: the sizes change over the field at every
    flux, the slope nowhere, and the split says so (it had no term for a size that changes
    over the field, and read 13 sigma "rising with the column" here). A dependence the split
    does find fails the verdict while no term of the model follows it, and passes with a
    validated EMPIRICAL term along the column."""
    from bfpsf.diagnosis.position_split import SPLIT_NSIGMA, star_slope_split
    from bfpsf.diagnosis.unexplained import verdict
    from bfpsf.measure.sources import measure_sources

    _, xy, fluxes, _ = varying_field
    # the peaks drawn independently of the width (wide stars of a flux have low peaks)
    fluxes = np.exp(np.random.default_rng(8).uniform(np.log(5e4), np.log(3e6), len(xy)))
    image = sum(render_stars(moffat(x), [(x, y)], [flux], (LENGTH, LENGTH))
                for (x, y), flux in zip(xy, fluxes))
    noisy = image + np.random.default_rng(6).normal(0.0, np.sqrt(image + 25.0))
    stars = measure_sources(noisy)
    stars = stars[stars["flags"] == 0]
    split = star_slope_split(stars["peak_e"], stars["sigma_x"], stars["sigma_y"],
                             np.zeros(len(stars)), stars["x"], stars["y"])
    print({along: {axis: round(values["significance"], 1) for axis, values in entry.items()}
           for along, entry in split.items()})
    assert max(values["significance"] for entry in split.values()
               for values in entry.values()) < SPLIT_NSIGMA
    assert verdict([], {}, position_split=split)["success"]
    found = {"column": {"x": dict(split["column"]["x"], significance=13.2, change=0.01)}}
    judged = verdict([], {}, position_split=found)
    assert [reason for reason in judged["reasons"] if "depends on the column" in reason]
    followed = {"validation": {"position_term": True, "validated": True}}
    assert verdict([], {}, position_split=found, empirical=followed)["success"]
