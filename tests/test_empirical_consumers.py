"""The EMPIRICAL term reaches every consumer of a refined calibration (issue 22, item 3).

One path: a calibration refined by ``bfpsf diagnose --output-calib`` holds the term
(``refinement['empirical']``); `bfpsf.model.empirical.empirical_of` takes it out for every
consumer: ``bfpsf psf`` / `psf_from_images` (the P0 fit and the product), the product's
save / load, ``shape``, the photutils model of ``photometry``, ``slope --psf``, ``to_galsim``,
and the Piff and GalSim plug-ins (tests/test_piff_plugin.py, below for GalSim). Every check
is against a truth built here: stars rendered by P(F) with a known term, whose pattern adds
exactly c F / F_ref pixel^2 to a star's plain second moment along X.
"""

import dataclasses
import json
import pickle

import galsim
import numpy as np
import pytest
from astropy.table import Table

from bfpsf.model.empirical import FLUX_REFERENCE, PATTERN_KINDS, EmpiricalTerm, apply_pattern
from bfpsf.model.gridded import GriddedFluxDependentPSF
from bfpsf.model.psf import FluxDependentPSF
from test_photometry import MOFFAT, SHIFTS, grid_positions, make_calibration

GAIN = 1.5
SKY = 200.0
#: the truth: a size term along X only, 0.06 pixel^2 per 1e6 e- (about 4 % of the star's
#: Mxx at the brightest stars here, comparable to their BF)
TERM = EmpiricalTerm({"xx": {"constant": 0.06}, "yy": {"constant": 0.0}},
                     validation={"validated": True})


def _plain_moments(image):
    y, x = np.mgrid[:image.shape[0], :image.shape[1]].astype(float)
    total = image.sum()
    cx, cy = (image * x).sum() / total, (image * y).sum() / total
    return (image * (x - cx) ** 2).sum() / total, (image * (y - cy) ** 2).sum() / total


def _render(model, positions, fluxes, shape, half=12):
    """Noiseless charge image of stars drawn by ``model.star_image`` (its term included)."""
    image = np.zeros(shape)
    for (x, y), flux in zip(positions, fluxes):
        column, row = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        image[row - half:row + half + 1, column - half:column + half + 1] += model.star_image(
            flux, x, y, half_size=half)
    return image


@pytest.fixture(scope="module")
def truth():
    return FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25)


@pytest.mark.parametrize("kind", PATTERN_KINDS)
def test_every_evaluation_applies_the_term(truth, kind):
    """star_image (exact), evaluate in table and exact mode, shape, to_galsim, a gridded
    P(F, x, y) and the copies: the term's pattern on the star's BF image, so its plain Mxx
    grows by exactly c F / F_ref (where the kind's reach stays within the 25 px stamp); the
    table mode interpolates the same term to 2e-5 of the peak at 1.2e6 e- (1e-4 for the
    cubed charge's, whose series in the BF term has a larger third order), and the term-less
    model is unchanged. Each pattern kind."""
    from bfpsf.model.empirical_patterns import power_and_reach

    power, reach = power_and_reach(kind)
    flux = 1.2e6
    term = EmpiricalTerm({"xx": {"constant": 0.1, "position": 0.05},
                          "yy": {"flux2": 0.04}}, x_reference=500.0, x_range=(0.0, 1000.0),
                         kind=kind)
    model = truth.with_empirical_term(term)
    assert truth.empirical is None and model.empirical is term
    for x in (120.3, 880.0):
        plain = truth.star_image(flux, x, 40.2, half_size=12)
        image = model.star_image(flux, x, 40.2, half_size=12)
        expected = sum(change * apply_pattern(plain, pattern, total=flux, kind=kind)
                       for pattern, change in zip(("xx", "yy"),
                                                  term.variance_change(flux, x=x)))
        np.testing.assert_allclose(image - plain, expected, rtol=0, atol=1e-9 * flux)
        d_mxx = _plain_moments(image)[0] - _plain_moments(plain)[0]
        if reach is None or reach <= 2:
            assert d_mxx == pytest.approx(term.variance_change(flux, x=x)[0], rel=0.02)
        # what a fitter sees: evaluate on the star's pixels, table and exact mode
        column = int(np.floor(x + 0.5))
        rows, columns = np.mgrid[28:53, column - 12:column + 13].astype(float)
        table = model.evaluate(columns, rows, flux, x, 40.2)
        exact = FluxDependentPSF(truth.data, SHIFTS, oversampling=4, mode="exact")
        exact = exact.with_empirical_term(term).evaluate(columns, rows, flux, x, 40.2)
        # the table's series in the BF term stops at second order: its third order is
        # 1.4e-5 of the peak at this flux (far beyond a full well), 7e-7 at half of it
        np.testing.assert_allclose(table, image, rtol=0,
                                   atol=(2e-5 if power < 3 else 1e-4) * image.max())
        np.testing.assert_allclose(exact, image, rtol=0, atol=1e-4 * image.max())
        # shape (adaptive moments): the term's change through the adaptive response (about
        # 3.4 for a Moffat with the squared charge's pattern, which acts on the core where
        # the weight is, 1.24 with the charge's: `bfpsf.diagnosis.empirical_fit.
        # adaptive_response`; the cubed charge's, nearer the peak, 5.6; the broad kinds move
        # charge beyond the weight: less)
        change = model.shape(flux, x, 40.0).mxx - truth.shape(flux, x, 40.0).mxx
        low, high = {PATTERN_KINDS[0]: (3.0, 4.2), PATTERN_KINDS[1]: (1.0, 1.5)}.get(
            kind, (0.0, 6.5))
        assert low < change / term.variance_change(flux, x=x)[0] < high
        # to_galsim: the model's image (at the star's column), drawn at the star's phase (the
        # term, like R, is not the same at another phase)
        profile, _ = model.to_galsim(flux, x, 40.0)
        drawn = profile.drawImage(nx=25, ny=25, scale=1.0, method="no_pixel",
                                  offset=(x - np.floor(x + 0.5), 0.0)).array
        np.testing.assert_allclose(drawn, model.star_image(flux, x, 40.0, half_size=12) / flux,
                                   rtol=0, atol=2e-3 * drawn.max())
    # a position term: the model varies over the field, between the columns it was learned on
    assert model.varies_over_field and not truth.varies_over_field
    np.testing.assert_array_equal(model.field_nodes[0], [0.0, 1000.0])
    assert model.at(880.0, 3.0).empirical.position_dependent is False
    # a grid: every node applies the term at the star's column, as the single model
    grid = GriddedFluxDependentPSF([truth, truth], [0.0, 1000.0], [0.0]).with_empirical_term(term)
    for x in (120.3, 880.0):
        np.testing.assert_allclose(grid.star_image(flux, x, 40.2, half_size=12),
                                   model.star_image(flux, x, 40.2, half_size=12), rtol=1e-12)
        rows, columns = np.mgrid[28:53, int(np.floor(x + 0.5)) - 12:
                                 int(np.floor(x + 0.5)) + 13].astype(float)
        np.testing.assert_allclose(grid.evaluate(columns, rows, flux, x, 40.2),
                                   model.evaluate(columns, rows, flux, x, 40.2), rtol=1e-12)
        np.testing.assert_allclose(grid.at(x, 40.2).star_image(flux, x, 40.2, half_size=12),
                                   model.star_image(flux, x, 40.2, half_size=12), rtol=1e-9)
    assert grid.empirical is term and all(node.empirical is None for node in (truth,))
    # with_shifts and with_flux_unit keep it (for_amplifier, photometry in ADU)
    assert model.with_shifts(SHIFTS).empirical is term
    adu = model.with_flux_unit("adu", gain=GAIN)
    np.testing.assert_allclose(adu.star_image(flux / GAIN, 120.3, 40.2, half_size=12) * GAIN,
                               model.star_image(flux, 120.3, 40.2, half_size=12), rtol=1e-9)


def test_a_row_term_is_applied_at_the_star_row(truth, tmp_path):
    """A term that changes with the row (a parallel-transfer effect): every evaluation
    applies it at the star's row (star_image, table and exact evaluate, a gridded model),
    the model varies over the field between the rows it was learned on, ``at(x, y)`` folds
    it, and the product keeps its row reference and range."""
    flux = 1.2e6
    term = EmpiricalTerm({"yy": {"constant": 0.1, "row": 0.08}, "xx": {"flux2_row": 0.03}},
                         y_reference=500.0, y_range=(0.0, 1000.0))
    model = truth.with_empirical_term(term)
    images = {}
    for y in (120.3, 880.0):
        plain = truth.star_image(flux, 40.2, y, half_size=12)
        images[y] = model.star_image(flux, 40.2, y, half_size=12)
        expected = sum(change * apply_pattern(plain, pattern, total=flux)
                       for pattern, change in zip(("xx", "yy"),
                                                  term.variance_change(flux, y=y)))
        np.testing.assert_allclose(images[y] - plain, expected, rtol=0, atol=1e-9 * flux)
        row = int(np.floor(y + 0.5))
        rows, columns = np.mgrid[row - 12:row + 13, 28:53].astype(float)
        np.testing.assert_allclose(model.evaluate(columns, rows, flux, 40.2, y), images[y],
                                   rtol=0, atol=2e-5 * images[y].max())
        exact = FluxDependentPSF(truth.data, SHIFTS, oversampling=4, mode="exact")
        np.testing.assert_allclose(exact.with_empirical_term(term).evaluate(
            columns, rows, flux, 40.2, y), images[y], rtol=0, atol=1e-4 * images[y].max())
        np.testing.assert_allclose(model.at(40.2, y).star_image(flux, 40.2, y, half_size=12),
                                   images[y], rtol=1e-12)
    # the term moves Myy by 0.08 x (880 - 120) / 1000 per F_ref between the two rows
    d_myy = _plain_moments(images[880.0])[1] - _plain_moments(images[120.3])[1]
    assert d_myy == pytest.approx(0.08 * (880.0 - 120.3) / 1000 * flux / FLUX_REFERENCE,
                                  rel=0.02)
    assert model.varies_over_field and model.reference_position == (0.0, 500.0)
    np.testing.assert_array_equal(model.field_nodes[0], [0.0])
    np.testing.assert_array_equal(model.field_nodes[1], [0.0, 1000.0])
    assert model.at(3.0, 880.0).empirical.position_dependent is False
    grid = GriddedFluxDependentPSF([truth, truth], [0.0], [0.0, 1000.0]).with_empirical_term(term)
    np.testing.assert_allclose(grid.star_image(flux, 40.2, 880.0, half_size=12), images[880.0],
                               rtol=1e-12)
    path = tmp_path / "row.fits"
    model.write(path)
    back = FluxDependentPSF.read(path)
    assert back == model and back.empirical.y_range == (0.0, 1000.0)
    assert back.empirical.y_reference == 500.0


@pytest.mark.parametrize("kind", PATTERN_KINDS)
def test_product_round_trip_keeps_the_term(truth, tmp_path, kind):
    """save / load (single and grid), value equality and pickling with the term (each
    pattern kind, which the product keeps); a product without one reads back without
    one."""
    term = EmpiricalTerm({"xx": {"constant": 0.1, "position": 0.05}, "yy": {"flux2": 0.04}},
                         errors={"xx": {"constant": 0.01}}, x_reference=500.0,
                         x_range=(0.0, 1000.0), validation={"heldout": {"n": 3}}, kind=kind)
    grid = GriddedFluxDependentPSF([truth, truth], [0.0, 1000.0], [0.0])
    for model in (truth, grid):
        with_term = model.with_empirical_term(term)
        assert with_term != model and with_term == model.with_empirical_term(term)
        assert pickle.loads(pickle.dumps(with_term)) == with_term
        for name, one in (("with", with_term), ("without", model)):
            path = tmp_path / f"{type(model).__name__}_{name}.fits"
            one.write(path)
            back = type(model).read(path)
            assert back == one
            assert (back.empirical is None) == (name == "without")
            assert name == "without" or back.empirical.kind == kind
        np.testing.assert_array_equal(
            type(model).read(tmp_path / f"{type(model).__name__}_with.fits").star_image(
                1e6, 700.0, 3.0), with_term.star_image(1e6, 700.0, 3.0))


@pytest.fixture(scope="module")
def user_path(tmp_path_factory):
    """Two 288 x 288 exposures of 64 stars each (peaks 3-100 ke-) drawn by P(F) with TERM,
    a refined calibration holding TERM and the plain one; ``bfpsf psf`` with each."""
    from bfpsf.cli import main
    from bfpsf.validation.simulate_spots import write_image_adu

    directory = tmp_path_factory.mktemp("empirical")
    truth = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25)
    model = truth.with_empirical_term(TERM)
    plain = make_calibration(SHIFTS, GAIN, 5.0)
    refined = dataclasses.replace(plain, refinement={
        "empirical": TERM.to_dict(), "applied": {"empirical": "EMPIRICAL (test)"}})
    plain.write(directory / "plain.fits")
    refined.write(directory / "refined.fits")
    rng = np.random.default_rng(11)
    images, stars = [], []
    for index in range(2):
        xy = grid_positions(8, 8, 36, rng)
        peaks = np.exp(rng.uniform(np.log(3e3), np.log(1e5), len(xy)))
        fluxes = peaks / 0.0518
        image = _render(model, xy, fluxes, (288, 288)) + SKY
        image = image + rng.normal(0.0, np.sqrt(image + 25.0))
        images.append(str(directory / f"stars{index}.fits"))
        write_image_adu(images[-1], image, gain=GAIN)
        stars.append((xy, fluxes))
    for label, options in (("plain", []), ("refined", []), ("grid", ["--grid", "2", "1"])):
        calib = "plain" if label == "plain" else "refined"
        assert main(["psf", *images, "--calib", str(directory / f"{calib}.fits"),
                     "-o", str(directory / f"psf_{label}.fits"), "--size", "21",
                     "--background", str(SKY / GAIN), *options,
                     "--json", str(directory / f"psf_{label}.json")]) == 0
    return directory, images, stars, truth


def test_psf_from_a_refined_calibration_applies_the_term(user_path):
    """``bfpsf psf --calib REFINED``: the product holds the term (labelled in its JSON), P0
    is fitted with each star's term in its model (so P0 does not absorb it): the product's
    size growth with flux is the truth's; with the plain calibration P0 takes the term at
    the stars' typical flux and the growth misses the term's slope."""
    directory, _, _, truth = user_path
    summaries = {label: json.loads((directory / f"psf_{label}.json").read_text())
                 for label in ("plain", "refined")}
    assert summaries["plain"]["empirical"] is None
    assert summaries["refined"]["empirical"]["label"] == "empirical"
    assert "empirical" in summaries["refined"]["refinement_applied"]
    refined = FluxDependentPSF.read(directory / "psf_refined.fits")
    plain = FluxDependentPSF.read(directory / "psf_plain.fits")
    # the stars' pixels give the term (drawn with it) its own amplitude, 1 (to their noise;
    # `bfpsf.model.psf_fit_empirical`), and the product holds it so scaled
    amplitude = refined.empirical.amplitude
    assert amplitude == pytest.approx(1.0, abs=0.03)
    assert summaries["refined"]["empirical"]["amplitude"] == pytest.approx(amplitude)
    assert refined.empirical == TERM.at_exposure().scaled(amplitude)
    assert plain.empirical is None
    faint, bright = 6e4, 1.8e6

    def growth(model):
        return model.shape(bright).mxx - model.shape(faint).mxx

    term_growth = growth(truth.with_empirical_term(TERM)) - growth(truth)
    assert term_growth > 0.05  # the term's part of the growth, about as large as the BF's
    assert growth(refined) == pytest.approx(growth(truth.with_empirical_term(TERM)),
                                            abs=0.1 * term_growth)
    assert growth(plain) == pytest.approx(growth(truth), abs=0.15 * term_growth)
    # the same P0 with and without the term differs by the term alone
    assert growth(refined) - growth(refined.with_empirical_term(None)) == pytest.approx(
        term_growth, rel=0.05)
    # psf --grid: P(F, x, y) fitted and stored with the term, every node applying it
    grid = GriddedFluxDependentPSF.read(directory / "psf_grid.fits")
    assert json.loads((directory / "psf_grid.json").read_text())["empirical"]["label"] == \
        "empirical"
    assert grid.empirical.amplitude == pytest.approx(1.0, abs=0.03)
    assert grid.empirical == TERM.at_exposure().scaled(grid.empirical.amplitude)
    assert all(node.empirical == grid.empirical for node in grid.nodes)
    for x in (40.0, 250.0):
        at = grid.at(x, 144.0)
        assert at.shape(bright).mxx - at.shape(faint).mxx == pytest.approx(
            growth(truth.with_empirical_term(TERM)), abs=0.15 * term_growth)


def test_photometry_and_slope_apply_the_term(user_path):
    """``photometry`` with the refined product: its table and JSON say EMPIRICAL; fluxes
    from faint to bright stars as the truth (no drift beyond the noise). ``slope --psf``: the
    prediction of the refined product exceeds that of its P0 without the term by the
    term's size slope, and the star sizes leave no residual."""
    from bfpsf.cli import main
    from bfpsf.measure.model_slopes import predicted_slopes

    directory, images, stars, _ = user_path
    offsets = {}
    for label in ("plain", "refined"):
        out = directory / f"phot_{label}.ecsv"
        assert main(["photometry", *images, "--psf", str(directory / f"psf_{label}.fits"),
                     "-o", str(out), "--read-noise", "5", "--background", str(SKY / GAIN),
                     "--json", str(directory / f"phot_{label}.json")]) == 0
        table = Table.read(out)
        summary = json.loads((directory / f"phot_{label}.json").read_text())
        assert (table.meta["empirical"] is None) == (label == "plain")
        assert (summary["empirical"] is None) == (label == "plain")
        ratio, flux = [], []
        for path, (xy, fluxes) in zip(images, stars):
            rows = table[table["image"] == path]
            distance = np.hypot(rows["x_fit"][:, None] - xy[None, :, 0],
                                rows["y_fit"][:, None] - xy[None, :, 1])
            matched = distance.min(axis=1) < 0.5
            nearest = distance.argmin(axis=1)[matched]
            ratio.append(np.asarray(rows["flux_fit"])[matched] / fluxes[nearest])
            flux.append(fluxes[nearest])
        ratio, flux = np.concatenate(ratio), np.concatenate(flux)
        assert ratio.size >= 120
        mag = -2.5 * np.log10(ratio)
        slope, intercept = np.polyfit(flux / FLUX_REFERENCE, mag, 1)
        scatter = np.std(mag - (slope * flux / FLUX_REFERENCE + intercept), ddof=2)
        error = scatter / np.sqrt(np.sum((flux / FLUX_REFERENCE - np.mean(
            flux / FLUX_REFERENCE)) ** 2))
        offsets[label] = (1e3 * slope, 1e3 * error)
    assert table.meta["empirical"]["label"] == "empirical"
    # photometry --calib REFINED with a product made without the term: the calibration's
    assert main(["photometry", images[0], "--psf", str(directory / "psf_plain.fits"),
                 "--calib", str(directory / "refined.fits"), "--background", str(SKY / GAIN),
                 "-o", str(directory / "phot_calib.ecsv")]) == 0
    assert Table.read(directory / "phot_calib.ecsv").meta["empirical"] == \
        TERM.at_exposure().to_dict()
    slope, error = offsets["refined"]
    assert abs(slope) < 3 * error + 1.0, offsets  # mmag per 1e6 e-
    # slope --psf: the EMPIRICAL term in the prediction and the JSON
    assert main(["measure", *images, "--calib", str(directory / "plain.fits"),
                 "-o", str(directory / "stars.ecsv")]) == 0
    stars_table = Table.read(directory / "stars.ecsv")
    refined = FluxDependentPSF.read(directory / "psf_refined.fits")
    with_term = predicted_slopes(refined, stars_table)
    without = predicted_slopes(refined.with_empirical_term(None), stars_table)
    # the term's slope of sigma_x: d sqrt(Mxx + r c F / F_ref) = r c / (2 sigma_x) dF / F_ref
    # per 100 ke- of peak (F = peak / 0.0518), r the adaptive response of the model
    sigma_x = np.sqrt(refined.shape(1e5).mxx)
    response = ((refined.shape(1e6).mxx - refined.with_empirical_term(None).shape(1e6).mxx)
                / TERM.variance_change(1e6)[0])
    expected = response * 0.06 / (2 * sigma_x) * 1e5 / 0.0518 / FLUX_REFERENCE
    assert with_term["x"]["slope"] - without["x"]["slope"] == pytest.approx(expected, rel=0.15)
    assert with_term["y"]["slope"] - without["y"]["slope"] < 0.3 * expected
    for label in ("plain", "refined"):
        assert main(["slope", str(directory / "stars.ecsv"),
                     "--psf", str(directory / f"psf_{label}.fits"),
                     "--json", str(directory / f"slope_{label}.json")]) == 0
    summaries = {label: json.loads((directory / f"slope_{label}.json").read_text())
                 for label in ("plain", "refined")}
    assert summaries["refined"]["empirical"]["label"] == "empirical"
    assert summaries["plain"]["empirical"] is None
    residual = summaries["refined"]["model_residual"]["x"]
    assert abs(residual["slope"]) < 3 * residual["slope_err"]  # (no shift samples here)
    # the plain product misses the term's slope: its residual is the term's slope
    assert summaries["plain"]["model_residual"]["x"]["slope"] == pytest.approx(expected,
                                                                               rel=0.25)


def test_galsim_sensor_applies_the_refined_term(user_path):
    """``sensor: {type: BrighterFatter, calib: REFINED}``: the sensor adds the term to each
    stamp's charge, so a star's plain Mxx grows by c F / F_ref more than with the plain
    calibration; Myy does not change."""
    from bfpsf.galsim import build_sensor

    directory = user_path[0]
    flux = 1.5e6
    moments = {}
    for label in ("plain", "refined"):
        sensor = build_sensor(str(directory / f"{label}.fits"))
        assert (sensor.empirical is None) == (label == "plain")
        image = galsim.ImageD(41, 41, scale=1.0)
        MOFFAT.withFlux(flux).drawImage(image=image, method="phot", sensor=sensor,
                                        rng=galsim.BaseDeviate(3), add_to_image=True)
        moments[label] = _plain_moments(image.array)
    assert moments["refined"][0] - moments["plain"][0] == pytest.approx(
        TERM.variance_change(flux)[0], rel=0.02)
    assert moments["refined"][1] == pytest.approx(moments["plain"][1], abs=1e-3)


def test_one_term_per_calibration_set():
    """`empirical_of`: the term at an exposure order (exposure terms folded in, position
    terms kept, `at_position` folds them), None without one, refused when calibrations
    disagree (one PSF applies one term)."""
    from types import SimpleNamespace

    from bfpsf.errors import BFPSFValueError
    from bfpsf.model.empirical import empirical_of

    term = EmpiricalTerm({"xx": {"constant": 0.1, "exposure": 0.01, "position": 0.2,
                                 "flux2": 0.02, "flux2_exposure": -0.001}},
                         x_reference=1000.0, exposure_reference=3.0)
    refined = SimpleNamespace(refinement={"empirical": term.to_dict()})
    plain = SimpleNamespace(refinement={})
    at = empirical_of([refined, refined], exposure=7.0)
    assert at.coefficients["xx"] == pytest.approx({"constant": 0.14, "flux2": 0.016,
                                                   "position": 0.2})
    for flux, x in ((5e5, 1500.0), (2e6, 200.0)):
        assert at.variance_change(flux, x=x)[0] == pytest.approx(
            term.variance_change(flux, x=x, exposure=7.0)[0])
        assert at.at_position(x).variance_change(flux)[0] == pytest.approx(
            term.variance_change(flux, x=x, exposure=7.0)[0])
    assert empirical_of(refined).exposure_reference == 3.0
    assert empirical_of([plain, plain]) is None
    other = SimpleNamespace(refinement={"empirical": term.at_exposure(1.0).to_dict()})
    for mixed in ([refined, plain], [refined, other]):
        with pytest.raises(BFPSFValueError, match="different EMPIRICAL terms"):
            empirical_of(mixed)


def test_python_consumers_of_a_refined_calibration(user_path, truth):
    """The Python API takes the term from a refined calibration too: `FluxDependentPSF`
    built with it, `BFSensor` and `draw_with_bf` (one object: its charge, its column)."""
    from bfpsf import Calibration
    from bfpsf.interop.galsim_sensor import BFSensor, draw_with_bf

    directory = user_path[0]
    plain, refined = (Calibration.read(directory / f"{label}.fits")
                      for label in ("plain", "refined"))
    assert FluxDependentPSF(truth.data, refined, oversampling=4).empirical == TERM.at_exposure()
    assert FluxDependentPSF(truth.data, plain, oversampling=4).empirical is None
    assert BFSensor(refined).empirical == TERM.at_exposure() and BFSensor(plain).empirical is None
    flux = 1.5e6
    images = {label: draw_with_bf(MOFFAT.withFlux(flux), calib, nx=41, ny=41, rng=5).array
              for label, calib in (("plain", plain), ("refined", refined))}
    assert _plain_moments(images["refined"])[0] - _plain_moments(images["plain"])[0] == \
        pytest.approx(TERM.variance_change(images["plain"].sum())[0], rel=0.02)


def test_a_term_of_the_night_warns_without_the_exposure_order(caplog):
    """A refined calibration's EMPIRICAL term that changes over the night, applied without an
    exposure order, is taken at the middle of the exposures it was learned on: said, with
    the orders' meaning (a new user's late exposures kept 70 % of the excess at that silent
    default); an order beyond those learned is said too; one within them is not."""
    import logging
    from types import SimpleNamespace

    from bfpsf.model.empirical import EmpiricalTerm, empirical_of

    term = EmpiricalTerm({"xx": {"constant": 0.01, "exposure": 0.002}}, exposure_reference=3.5,
                         exposure_range=(0.0, 7.0))
    calibration = SimpleNamespace(refinement={"empirical": term.to_dict()})
    assert EmpiricalTerm.from_dict(term.to_dict()).exposure_range == (0.0, 7.0)
    with caplog.at_level(logging.WARNING, logger="bfpsf"):
        empirical_of(calibration)
        assert "applied at exposure order 3.5" in caplog.text and "0 to 7" in caplog.text
        caplog.clear()
        assert empirical_of(calibration, 9.5).coefficient("xx") == pytest.approx(0.022)
        assert "outside the orders" in caplog.text
        caplog.clear()
        empirical_of(calibration, 6.0)
        assert caplog.text == ""
