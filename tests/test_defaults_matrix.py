"""Every command that takes a calibration or a PSF product, crossed with every kind it takes,
at defaults, on one small generated set, each asserting numbers against the truth (issue 21,
item 5); and the Python path giving the command line's numbers (item 4).

The set: two 220^2 exposures of 30 Moffat stars (FWHM 3.45 px, beta 3.5, peaks 3-120 ke-),
brighter-fatter from the shifts below, each exposure with its own sloped sky (20-610 e-), a
gain of 1.5 e-/ADU and a gain non-linearity v = q (1 + c q / 1e5), c = 0.01, that only the
refined calibration knows. Kinds: calibrations from the flats' PTC (``flats``) and that
calibration refined (``refined``: the linearity correction and 4 build-up steps, as ``bfpsf
diagnose --output-calib`` writes them); PSF products single, ``--grid 2 2`` and refined.
"""

import dataclasses
import json

import galsim
import numpy as np
import pytest
from astropy.table import Table

from bfpsf.cli import main
from bfpsf.measure.bf_agreement import disagreeing_axes
from bfpsf.measure.sources import SourceFlag
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_fields import simulate_field
from bfpsf.validation.simulate_spots import write_image_adu

from test_photometry import make_calibration

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
GAIN = 1.5
LINEARITY_C = 0.01
PROFILE = galsim.Moffat(beta=3.5, fwhm=3.45)


def _non_linear(charge):
    """v = q (1 + c q / 1e5): what the refined calibration's correction undoes."""
    return charge * (1.0 + LINEARITY_C * charge / 1e5)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    directory = tmp_path_factory.mktemp("matrix")
    field = simulate_field(PROFILE, n_images=2, shape=(220, 220), n_stars=30,
                           min_separation=30, sensor=None, shifts=SHIFTS, seed=2111)
    paths = []
    for index, image in enumerate(field.images):
        paths.append(directory / f"image{index}.fits")
        write_image_adu(paths[-1], _non_linear(image), gain=GAIN)
    flats = make_calibration(SHIFTS, GAIN, 5.0)
    flats.write(directory / "flats.fits")
    # the refined calibration carries shift samples (its uncertainty), which every PSF
    # product built from it keeps, the Python path's too
    samples = [SHIFTS.scaled(scale) for scale in (0.96, 1.0, 1.04)]
    refined = dataclasses.replace(
        make_calibration(SHIFTS, GAIN, 5.0),
        shift_samples_north=np.array([sample.north for sample in samples]),
        shift_samples_east=np.array([sample.east for sample in samples]))
    refined.refinement.update({"linearity_c_per_1e5": LINEARITY_C, "buildup_steps": 4,
                               "applied": {"gain_nonlinearity": "linearity correction"}})
    refined.write(directory / "refined.fits")
    return directory, field, [str(path) for path in paths]


#: PSF product kind -> (calibration, extra options of ``bfpsf psf``)
PSF_KINDS = {"single": ("flats", []), "gridded": ("flats", ["--grid", "2", "2"]),
             "refined": ("refined", [])}


@pytest.fixture(scope="module")
def products(data):
    directory, _, images = data
    summaries = {}
    for kind, (calibration, options) in PSF_KINDS.items():
        assert main(["psf", *images, "--calib", str(directory / f"{calibration}.fits"),
                     "-o", str(directory / f"psf_{kind}.fits"), "--json",
                     str(directory / f"{kind}.json"), *options]) == 0
        summaries[kind] = json.loads((directory / f"{kind}.json").read_text())
    return summaries


def _matched(table, truth, x="x_fit", y="y_fit"):
    distance = np.hypot(np.asarray(table[x])[:, None] - truth["x"],
                        np.asarray(table[y])[:, None] - truth["y"])
    nearest = distance.argmin(axis=1)
    return distance.min(axis=1) < 1.0, nearest


@pytest.mark.parametrize("kind", sorted(PSF_KINDS))
def test_psf_finds_the_sky_and_the_wings(data, products, kind):
    directory, field, _ = data
    summary = products[kind]
    linear = PSF_KINDS[kind][0] == "refined"
    for entry, sky in zip(summary["images"], field.skies):
        # the true sky at the centre (as the images hold it without the refined calibration's
        # linearity correction); 0.2 e- of 30 e- noise per pixel over ~3e4 pixels, and the
        # wings' model (a 0.4 e- offset was seen on 64 bright stars, test_photometry)
        level = sky[0] if linear else _non_linear(sky[0])
        assert entry["background_e"] == pytest.approx(level, abs=0.6)
        assert entry["sky_slope"] == pytest.approx(sky[1:], abs=0.01)
    # a Moffat of beta 3.5 has 0.12 % of its flux beyond the 25-pixel support
    assert summary["flux_correction"] == pytest.approx(1.0012, abs=0.003)
    # the stars' own BF against the product's (`bf_agreement`), with the true shifts: x, y
    # 0.91, 0.93 +- 0.03 (single: the flats' calibration leaves the non-linearity in the
    # stars), 1.03 +- 0.09, 0.96 +- 0.06 (gridded), 1.01, 1.04 +- 0.03 (refined)
    for entry in summary["bf_agreement"].values():
        assert entry["ratio"] == pytest.approx(1.0, abs=0.15) and entry["n"] >= 50
    assert disagreeing_axes(summary["bf_agreement"]) == []
    if kind == "gridded":  # 15 stars per node: no node stands out
        assert summary["grid"]["outlying_nodes"] == []
        assert sum(summary["grid"]["star_weights"]) == pytest.approx(summary["n_used"])


def test_psf_names_grid_nodes_fitted_from_too_few_stars(tmp_path, capsys):
    """27 stars on --grid 3 3 (1.3-7.7 stars per node): nodes of 1.9-4.3 px FWHM where the
    stars' is 3.45 px are named, with the stars' weight at every node."""
    field = simulate_field(PROFILE, n_images=1, shape=(220, 220), n_stars=30,
                           min_separation=30, sensor=None, shifts=SHIFTS, seed=2111)
    write_image_adu(tmp_path / "image.fits", field.images[0], gain=GAIN)
    make_calibration(SHIFTS, GAIN, 5.0).write(tmp_path / "flats.fits")
    assert main(["psf", str(tmp_path / "image.fits"), "--calib", str(tmp_path / "flats.fits"),
                 "-o", str(tmp_path / "psf.fits"), "--json", str(tmp_path / "psf.json"),
                 "--grid", "3", "3"]) == 0
    grid = json.loads((tmp_path / "psf.json").read_text())["grid"]
    err = capsys.readouterr().err
    assert len(grid["outlying_nodes"]) >= 1
    median = np.median(grid["fwhm_pixels"])
    for node in grid["outlying_nodes"]:
        assert (not median / 1.3 < node["fwhm_pixels"] < median * 1.3) or node["dip"] < -0.2
        assert f"(x {node['x']:.0f}, y {node['y']:.0f}) {node['fwhm_pixels']:.1f} px" in err
    few = sum(weight < 10 for weight in grid["star_weights"])
    assert f"{few} of 9 grid nodes have less than 10 stars' weight" in err
    assert "too few stars for --grid 3 3: use fewer nodes or more images" in err
    assert min(grid["star_weights"]) < 2.0
    # what it names is wrong against the truth (the stars' pixelised FWHM: 3.45-3.5 px)
    assert max(abs(node["fwhm_pixels"] / 3.47 - 1) for node in grid["outlying_nodes"]) > 0.25


@pytest.mark.parametrize("psf_kind", sorted(PSF_KINDS))
@pytest.mark.parametrize("with_calibration", [False, True])
def test_photometry_gives_total_fluxes(data, products, psf_kind, with_calibration):
    """Every product, alone and with the calibration it was built with (``--calib``)."""
    calibration = PSF_KINDS[psf_kind][0] if with_calibration else None
    directory, field, images = data
    output = directory / f"phot_psf_{psf_kind}_{calibration}.ecsv"
    argv = ["photometry", *images, "--psf", str(directory / f"psf_{psf_kind}.fits"), "-o",
            str(output)]
    if calibration:
        argv += ["--calib", str(directory / f"{calibration}.fits")]
    assert main(argv) == 0
    table = Table.read(output)
    linearised = PSF_KINDS[psf_kind][0] == "refined"
    ratios, peaks = [], []
    for index, path in enumerate(images):
        mine = table[table["image"] == path]
        truth = field.truth[index]
        matched, nearest = _matched(mine, truth)
        assert matched.sum() >= len(truth) - 1
        ratios.append(np.asarray(mine["flux_fit"])[matched] / truth["flux_e"][nearest[matched]])
        peaks.append(truth["peak_e"][nearest[matched]])
        # the sky under each star is the true sky there: 0.2 e- at the centre to 0.4 e- at a
        # corner (the plane's noise), and up to 0.5 e- from the wings' model
        true_sky = field.sky_image(index)[np.rint(mine["y_fit"]).astype(int),
                                          np.rint(mine["x_fit"]).astype(int)]
        true_sky = true_sky if linearised else _non_linear(true_sky)
        assert np.all(np.abs(np.asarray(mine["sky_e"]) - true_sky) < 1.5)
    # isolated stars, each like its product's P(F) at its flux and place (`unlike_psf`)
    assert not np.any(np.asarray(table["source_flags"]) & SourceFlag.UNLIKE_PSF)
    ratio, peak = np.concatenate(ratios), np.concatenate(peaks)
    # the linearity correction is the refined calibration's and the refined product's:
    # without it the brightest stars come out about c * peak / 2e5 ~ 0.2 % high
    magnitudes = -2.5e3 * np.log10(ratio)
    bright, faint = magnitudes[peak > 4e4], magnitudes[peak < 1e4]
    drift = bright.mean() - faint.mean()
    print(f"{psf_kind} --calib {calibration}: mean {magnitudes.mean():+.2f} mmag, "
          f"bright - faint {drift:+.2f} mmag")
    # 60 stars: the faint ones' noise gives 0.5 mmag on the drift, 0.2 on the mean
    if linearised:
        assert abs(magnitudes.mean()) < 3.0 and abs(drift) < 1.5
    else:
        # the non-linearity makes every star too bright by c times its mean charge, and P0
        # fitted on those stars is distorted: measured -2.2 (single), +0.2 mmag (2 x 2 grid,
        # 15 stars per node; -3.8 before P0's sub-pixel phases were each normalised); bright
        # stars too bright against faint ones
        assert -6.0 < magnitudes.mean() < 1.0 and drift < -1.5


@pytest.mark.parametrize("calibration", ["flats", "refined"])
def test_measure_takes_every_calibration(data, calibration):
    directory, field, images = data
    output = directory / f"stars_{calibration}.ecsv"
    assert main(["measure", *images, "--calib", str(directory / f"{calibration}.fits"), "-o",
                 str(output)]) == 0
    table = Table.read(output)
    first = table[table["image"] == images[0]]
    matched, nearest = _matched(first, field.truth[0], x="x", y="y")
    assert matched.sum() >= len(field.truth[0]) - 1
    # flux_e is an aperture of 5 adaptive sigmas (98 % of a beta 3.5 Moffat); the refined
    # calibration removes the non-linearity (0.6 % of a pixel at 60 ke-)
    peak = field.truth[0]["peak_e"][nearest[matched]]
    ratio = np.asarray(first["flux_e"])[matched] / field.truth[0]["flux_e"][nearest[matched]]
    slope = np.polyfit(peak / 1e5, ratio, 1)[0]
    if calibration == "refined":
        assert abs(slope) < 0.004
    else:
        assert slope > 0.002  # c = 0.5 per 1e5 e- of charge, peaks to 1.2e5


@pytest.mark.parametrize("psf_kind", sorted(PSF_KINDS))
def test_slope_takes_every_product(data, products, psf_kind):
    directory, _, images = data
    stars = directory / "stars_slope.ecsv"
    if not stars.exists():
        assert main(["measure", *images, "--calib", str(directory / "refined.fits"), "-o",
                     str(stars)]) == 0
    summary = directory / f"slope_{psf_kind}.json"
    assert main(["slope", str(stars), "--psf", str(directory / f"psf_{psf_kind}.fits"),
                 "--json", str(summary)]) == 0
    result = json.loads(summary.read_text())
    for axis in ("x", "y"):
        raw, residual = result[axis], result["model_residual"][axis]
        # the model explains the measured slope: residual within 2.5 sigma or 20 % of raw
        # (the calibration here has no shift samples: the statistical error alone)
        error = residual["slope_err_total"] or residual["slope_err"]
        print(f"slope --psf {psf_kind} {axis}: raw {raw['slope']:+.4f}, residual "
              f"{residual['slope']:+.4f} +- {error:.4f} pix/100ke-")
        assert abs(residual["slope"]) < max(2.5 * error, 0.2 * abs(raw["slope"]))


def test_python_path_gives_the_command_line_numbers(data, products):
    """`prepare_image`, `psf_from_images` and `psf_photometry` on the same pixels give what
    ``bfpsf psf`` and ``bfpsf photometry`` wrote, to rounding."""
    from astropy.io import fits

    import bfpsf

    directory, _, images = data
    calibration = bfpsf.read_calibration(directory / "refined.fits")
    frames = [bfpsf.prepare_image(fits.getdata(path), gain=calibration.gain,
                                  linearity_c_per_1e5=LINEARITY_C) for path in images]
    fit = bfpsf.psf_from_images(frames, calibration, calibration_name="refined.fits")
    command_line = bfpsf.FluxDependentPSF.read(directory / "psf_refined.fits")
    np.testing.assert_allclose(fit.psf.data, command_line.data, rtol=0, atol=1e-12)
    assert fit.psf.flux_correction == pytest.approx(command_line.flux_correction, rel=1e-12)
    assert fit.psf.linearity_c_per_1e5 == command_line.linearity_c_per_1e5 == LINEARITY_C
    phot = bfpsf.psf_photometry(fits.getdata(images[0]) * calibration.gain, command_line)
    cli = Table.read(directory / "phot_psf_refined_None.ecsv")
    cli = cli[cli["image"] == images[0]]
    # the same pixels to float rounding (the command reads them through bfpsf.io), the fit
    # converged to the fitter's tolerance: 2e-8 of the flux
    np.testing.assert_allclose(np.asarray(phot["flux_fit"]), np.asarray(cli["flux_fit"]),
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(phot["sky_e"]), np.asarray(cli["sky_e"]), rtol=1e-6)
    # the calibration's uncertainty in both products (slope --psf's prediction errors)
    assert len(fit.psf.shift_samples) == len(command_line.shift_samples) == 3
    for mine, theirs in zip(fit.psf.shift_samples, command_line.shift_samples):
        np.testing.assert_allclose(mine.north, theirs.north, rtol=1e-12)
    # with --calib, the read noise of the pixel errors is the calibration's, as the README's
    # Python block passes it
    output = directory / "phot_python_path.ecsv"
    assert main(["photometry", images[0], "--psf", str(directory / "psf_refined.fits"),
                 "--calib", str(directory / "refined.fits"), "-o", str(output), "--json",
                 str(directory / "phot_python_path.json")]) == 0
    summary = json.loads((directory / "phot_python_path.json").read_text())
    assert summary["images"][0]["read_noise_e"] == calibration.noise_e == 5.0
    assert summary["images"][0]["read_noise_source"] == "calibration"
    phot = bfpsf.psf_photometry(fits.getdata(images[0]) * calibration.gain, command_line,
                                read_noise_e=calibration.noise_e)
    np.testing.assert_allclose(np.asarray(phot["flux_fit"]),
                               np.asarray(Table.read(output)["flux_fit"]), rtol=1e-6)


@pytest.mark.parametrize("kind", ["single", "gridded"])
def test_static_comparison_gives_total_fluxes_too(data, products, kind):
    """``photometry --static`` (the static P0, for comparison) applies the product's total-flux
    correction too, so both columns compare at total fluxes; a gridded product's static
    models too (a new user's ``--static`` with a 2 x 2 grid was an internal error)."""
    directory, field, images = data
    output = directory / f"phot_static_{kind}.ecsv"
    assert main(["photometry", images[0], "--psf", str(directory / f"psf_{kind}.fits"), "-o",
                 str(output), "--static", "--json",
                 str(directory / f"phot_static_{kind}.json")]) == 0
    if kind == "gridded":
        table = Table.read(output)
        matched, nearest = _matched(table, field.truth[0])
        assert matched.sum() >= len(field.truth[0]) - 1
        ratio = (np.asarray(table["flux_fit"])[matched]
                 / field.truth[0]["flux_e"][nearest[matched]])
        assert abs(np.median(ratio) - 1.0) < 0.01
        return
    summary = json.loads((directory / "phot_static_single.json").read_text())
    assert summary["images"][0]["flux_correction"] == pytest.approx(
        products["single"]["flux_correction"], rel=1e-12)
    assert summary["images"][0]["flux_correction"] > 1.0
    # and its error, from the product as for P(F) (psf_photometry fills it: one place)
    assert summary["images"][0]["flux_correction_err"] == pytest.approx(
        products["single"]["flux_correction_err"], rel=1e-12)
    table = Table.read(output)
    matched, nearest = _matched(table, field.truth[0])
    ratio = np.asarray(table["flux_fit"])[matched] / field.truth[0]["flux_e"][nearest[matched]]
    # the static P0 misses the BF of the bright stars (a few mmag), not the wings' light
    assert abs(np.median(ratio) - 1.0) < 0.01
    # and its sky is P(F)'s: the product's wings are taken out of it too (a new user's
    # static sky of Airy stars stood 5-6 e- above P(F)'s, the faint stars 2-4 mmag too faint)
    flux_dependent = directory / "phot_for_static.ecsv"
    assert main(["photometry", images[0], "--psf", str(directory / "psf_single.fits"), "-o",
                 str(flux_dependent)]) == 0
    skies = [float(np.median(Table.read(path)["sky_e"])) for path in (output, flux_dependent)]
    # (302.049 against 301.984 e- without the wings: the Moffat's are faint here)
    assert skies[0] == pytest.approx(skies[1], abs=0.02)


def test_psf_warns_when_the_seeing_differs(data, products, tmp_path, capsys):
    """Each image's stars against the one P0: an exposure 4 % wider than the others is named
    with its offset; images of one seeing are not (their common offset is the estimator's)."""
    directory, _, images = data
    for kind in ("single", "gridded"):
        offsets = [entry["size_offset"] for entry in products[kind]["images"]]
        errors = [entry["size_offset_err"] for entry in products[kind]["images"]]
        assert abs(offsets[0] - offsets[1]) < 3 * np.hypot(*errors) + 0.003, offsets
    wide = simulate_field(galsim.Moffat(beta=3.5, fwhm=3.45 * 1.04), n_images=1,
                          shape=(220, 220), n_stars=30, min_separation=30, sensor=None,
                          shifts=SHIFTS, seed=2112)
    path = str(tmp_path / "wide.fits")
    write_image_adu(path, _non_linear(wide.images[0]), gain=GAIN)
    capsys.readouterr()
    assert main(["psf", *images, path, "--calib", str(directory / "flats.fits"), "-o",
                 str(tmp_path / "psf.fits"), "--json", str(tmp_path / "psf.json")]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "seeing" in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"WARNING: {path}: its stars are +")
    entries = json.loads((tmp_path / "psf.json").read_text())["images"]
    # the wide image against the others: about 4 % in FWHM, somewhat less in adaptive sigma
    assert entries[2]["size_offset"] - np.median([e["size_offset"] for e in entries]) > 0.02


def test_photometry_says_where_a_gridded_psf_is_extrapolated(data, products, tmp_path, capsys):
    """A new user's 2 x 2 grid fitted on 320^2 pixels used on a 640^2 image: two thirds of the
    stars beyond its field, about 7 mmag worse, without a word. Here the 220^2 frame tiled
    2 x 2: the stars beyond the grid's field are counted in a warning; its own frame none."""
    from astropy.io import fits

    directory, field, images = data
    tiled = tmp_path / "tiled.fits"
    frame = fits.getdata(images[0])
    fits.PrimaryHDU(np.tile(frame, (2, 2)), header=fits.getheader(images[0])).writeto(tiled)
    psf = str(directory / "psf_gridded.fits")
    capsys.readouterr()
    assert main(["photometry", images[0], "--psf", psf, "-o", str(tmp_path / "own.ecsv")]) == 0
    printed = capsys.readouterr()
    assert "beyond the field" not in printed.err
    # no calibration: the read noise is measured on the image's sky, and said (a new user
    # found it in the JSON alone)
    assert "read noise measured on each image's sky: " in printed.out
    assert main(["photometry", str(tiled), "--psf", psf, "-o", str(tmp_path / "big.ecsv"),
                 "--json", str(tmp_path / "big.json")]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "beyond" in line]
    table = Table.read(tmp_path / "big.ecsv")
    summary = json.loads((tmp_path / "big.json").read_text())
    assert summary["residual_passes"] == 2 and summary["n_in_residual"] == 0
    # the tiles' seams (sky steps of hundreds of e-, stars cut) are no stars: at d63c7c5 the
    # search of the residual took them for 737 (284 s), its noise from a read noise of 0
    # (the command's default without --calib) and any peak's light counted, round or not
    assert table.meta["residual_sources"]["found"] == 0 and len(table) <= 4 * 30
    beyond = int(np.sum((table["x_fit"] > 221) | (table["y_fit"] > 221)))
    assert beyond > len(table) / 2 and warnings == [
        f"WARNING: {tiled}: {beyond} of {len(table)} stars lie beyond the field {psf} was "
        "fitted on (x 0 to 219, y 0 to 219): its field dependence is extrapolated there"]


def test_static_epsf_from_flats_without_brighter_fatter(data, tmp_path, capsys):
    """Flats that show no brighter-fatter give a calibration without shifts: `psf` says a
    static ePSF needs none, `psf --no-bf` fits one, and `photometry` and `slope --psf` take it
    (a new user's static ePSF was refused with or without --no-bf)."""
    directory, field, images = data
    flats = make_calibration(SHIFTS, GAIN, 5.0)
    dataclasses.replace(flats, shifts=None).write(tmp_path / "no_shifts.fits")
    argv = ["psf", *images, "--calib", str(tmp_path / "no_shifts.fits"), "-o",
            str(tmp_path / "static.fits")]
    assert main(argv) == 1
    assert capsys.readouterr().err.endswith("has no boundary shifts (its flats showed no "
                                            "brighter-fatter, or it was solved without "
                                            "them): a static ePSF needs none (--no-bf)\n")
    assert main([*argv, "--no-bf"]) == 0
    output = tmp_path / "phot.ecsv"
    assert main(["photometry", images[0], "--psf", str(tmp_path / "static.fits"), "--calib",
                 str(tmp_path / "no_shifts.fits"), "-o", str(output)]) == 0
    # the fits' flags and the detection's are told apart (a new user read "0 flagged" beside
    # 58 rows of blended and neighbour_light in source_flags)
    assert "fits flagged" in capsys.readouterr().out
    table = Table.read(output)
    matched, nearest = _matched(table, field.truth[0])
    ratio = np.asarray(table["flux_fit"])[matched] / field.truth[0]["flux_e"][nearest[matched]]
    # a static ePSF on BF stars and a gain non-linearity: within a few percent of the truth
    assert abs(np.median(ratio) - 1) < 0.03
    stars = tmp_path / "stars.ecsv"
    assert main(["measure", *images, "--calib", str(tmp_path / "no_shifts.fits"), "-o",
                 str(stars)]) == 0
    capsys.readouterr()
    assert main(["slope", str(stars), "--psf", str(tmp_path / "static.fits")]) == 0
    out = capsys.readouterr().out
    assert "(the PSF carries no calibration samples: no calibration error)" in out
    assert "nan" not in out
