"""The closed loop finds an effect injected into simulated data without telling the model.

Quick variants: Gaussian spots drawn by GalSim (pixel-integrated) at a fixed set of sub-pixel
phases per level, redistributed by GalSim's CDModel (`conftest.galsim_redistribute`: not
bfpsf's operator, which the loop's spot model uses; the exact-density variant uses bfpsf's,
GalSim having no such operator), with
the injected effect applied in the rendering (not through the candidate's template), Poisson
noise, adaptive moments; flat means and flat correlations drawn from their model plus the
injected effect and Gaussian noise. The slow variant uses GalSim SiliconSensor spots.

Acceptance (issue 6): the loop selects the injected effect first, and cuts the error at least
3x (the BF slope residual in X and Y, in quadrature, for effects on the sizes; the correlation
rms for the pedestal); a null data set selects nothing.
"""

import functools

import numpy as np
import pytest

from bfpsf.calibration.shifts_ei import solve_ei_shifts
from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.shifts import BoundaryShifts
from bfpsf.moments.adaptive import adaptive_moments_batch
from bfpsf.model.density import exact_boundary_density
from bfpsf.model.redistribution import redistribute
from bfpsf.diagnosis.catalogue import add_shifts, quadrupole_shifts
from bfpsf.diagnosis.loop import diagnose
from bfpsf.diagnosis.observables import observables_from_sizes
from bfpsf.diagnosis.tables import CorrelationTable, LinearityTable, SizeTable
from conftest import galsim_bf_stars, galsim_redistribute

PEAKS = np.linspace(1.5e4, 1.5e5, 8)
SIGMA = 1.2
STAMP = 15


@pytest.fixture(scope="module")
def shifts():
    """Realistic anisotropic shifts: ITL-like area coefficients (Lage's a at 80 ke-)."""
    area = np.zeros((4, 4))
    area[0, 0] = -1.12e-6
    area[0, 1], area[1, 0], area[1, 1] = 5.9e-8, 1.63e-7, 4.0e-8
    area[0, 2], area[2, 0], area[1, 2], area[2, 1] = 1.8e-8, 2.4e-8, 1.26e-8, 1.45e-8
    area[2, 2], area[0, 3], area[3, 0] = 8.9e-9, 5e-9, 1.06e-8
    area[1, 3], area[3, 1], area[2, 3], area[3, 2], area[3, 3] = 5e-9, 6e-9, 4e-9, 4e-9, 3e-9
    return solve_ei_shifts(area, n_monte_carlo=0).shifts


def _phases(n, seed=0):
    """n sub-pixel offsets: a regular k x k grid (k^2 = n) of cell centres, so that the phase
    average of pixelised sizes is the uniform one the model uses (a few random phases would
    bias it: undersampled BF depends on the phase)."""
    k = int(round(np.sqrt(n)))
    if k * k != n:
        return np.random.default_rng(seed).uniform(-0.5, 0.5, size=(n, 2))
    grid = (np.arange(k) + 0.5) / k - 0.5
    return np.array([(x, y) for y in grid for x in grid])


def render_sizes(shifts, *, n_phases=16, sigma=SIGMA, seed=1, nonlinearity=0.0, quadrupole=0.0,
                 second_order=0.0, exact_density=False, diffusion=0.0, colour_slope=0.0,
                 peaks=PEAKS, size_noise=None):
    """Mean sizes per level of rendered, redistributed, noisy spots, with one injected effect.

    Returns sigma_x, sigma_y, their errors (from the scatter about a line with per-phase
    intercepts), and the mean colour of each level. With ``size_noise`` (pixels) the stamps
    are noiseless and Gaussian noise of that rms is added to the level means instead (for
    effects too small to be seen through Poisson noise in a quick test).
    """
    import galsim

    rng = np.random.default_rng(seed)
    phases = _phases(n_phases)
    model_shifts = shifts
    if quadrupole:
        model_shifts = add_shifts(shifts, quadrupole_shifts(shifts, quadrupole))
    stamps, level, phase_index, colours = [], [], [], []
    for k, peak in enumerate(peaks):
        for j, (px, py) in enumerate(phases):
            # colour: correlated with flux, plus scatter; blue (small colour) spots are larger
            colour = 0.4 + 0.8 * peak / 1e5 + rng.normal(0.0, 0.3)
            size = sigma * (1.0 + colour_slope * colour / sigma)
            if diffusion:
                size = np.sqrt(size ** 2 + diffusion * peak / 1e5)
            profile = galsim.Gaussian(sigma=size)
            centred = profile.drawImage(nx=STAMP, ny=STAMP, scale=1.0).array.max()
            flux = peak / centred
            if exact_density:
                oversampling = 8
                fine = profile.withFlux(flux).drawImage(
                    nx=STAMP * oversampling, ny=STAMP * oversampling, scale=1.0 / oversampling,
                    method="no_pixel", offset=(px * oversampling, py * oversampling)).array
                pixels, density = exact_boundary_density(fine, oversampling)
                image = redistribute(pixels, model_shifts, density=density)
            else:
                pixels = profile.withFlux(flux).drawImage(nx=STAMP, ny=STAMP, scale=1.0,
                                                          offset=(px, py)).array
                image = galsim_redistribute(pixels, model_shifts)
                if second_order:
                    first = image - pixels
                    image = image + second_order * (galsim_redistribute(image, model_shifts)
                                                    - image - first)
            if size_noise is None:
                image = rng.poisson(np.clip(image, 0, None)).astype(float)
            if nonlinearity:
                image = image * (1.0 + nonlinearity * image / 1e5)
            stamps.append(image)
            level.append(k)
            phase_index.append(j)
            colours.append(colour)
    moments = adaptive_moments_batch(np.array(stamps))
    assert np.all(moments.flags == 0)
    level, phase_index = np.array(level), np.array(phase_index)
    colours = np.array(colours)
    out = []
    x = np.asarray(peaks)[level] / 1e5
    design = np.column_stack([x] + [(phase_index == j).astype(float) for j in range(n_phases)])
    for values in (np.sqrt(moments.mxx), np.sqrt(moments.myy)):
        means = np.array([values[level == k].mean() for k in range(len(peaks))])
        if size_noise is not None:
            out += [means + rng.normal(0.0, size_noise, means.size),
                    np.full(len(peaks), size_noise)]
            continue
        params, *_ = np.linalg.lstsq(design, values, rcond=None)
        rms = np.sqrt(np.sum((values - design @ params) ** 2) / (values.size - design.shape[1]))
        out += [means, np.full(len(peaks), rms / np.sqrt(n_phases))]
    mean_colour = np.array([colours[level == k].mean() for k in range(len(peaks))])
    return out[0], out[2], out[1], out[3], mean_colour


def flat_tables(*, nonlinearity=0.0, pedestal=0.0, seed=2):
    """Flat means against exposure time and R(1,0), R(0,1) against the mean, with noise."""
    rng = np.random.default_rng(seed)
    exptime = np.linspace(10.0, 120.0, 12)
    mean = 1000.0 * exptime
    measured = mean * (1.0 + nonlinearity * mean / 1e5)
    mean_err = np.full(mean.size, 20.0)
    linearity = LinearityTable(exptime, measured + rng.normal(0, 20.0, mean.size), mean_err)
    a = np.array([1.63e-7, 5.9e-8])
    r = mean[:, None] * a[None, :] + pedestal + rng.normal(0, 2e-4, (mean.size, 2))
    correlations = CorrelationTable(mean, ((1, 0), (0, 1)), r, np.full(r.shape, 2e-4))
    return linearity, correlations


def observables(shifts, *, colour=False, linearity_kwargs=None, **render_kwargs):
    sigma_x, sigma_y, err_x, err_y, mean_colour = render_sizes(shifts, **render_kwargs)
    table = SizeTable(PEAKS, sigma_x, sigma_y, err_x, err_y,
                      colour=mean_colour if colour else None)
    linearity, correlations = flat_tables(**(linearity_kwargs or {}))
    return observables_from_sizes(table, shifts, linearity=linearity, correlations=correlations)


def _slope_error(summary):
    return np.hypot(summary["slope_x_percent"], summary["slope_y_percent"])


@pytest.mark.parametrize("name, render, flats", [
    ("gain_nonlinearity", {"nonlinearity": -0.04}, {"nonlinearity": -0.04}),
    # the largest physical quadrupole (|q| < 1: a charge shrinks its own pixel on all four
    # sides) changes the sizes by little: seen through 1e-4 px of size noise
    ("xy_anisotropy", {"quadrupole": 0.9, "size_noise": 1e-4}, {}),
    ("second_order", {"second_order": 40.0}, {}),
    ("flux_diffusion", {"diffusion": 0.03}, {}),
])
def test_loop_finds_injected_size_effect(shifts, name, render, flats):
    result = diagnose(observables(shifts, linearity_kwargs=flats, **render))
    assert result.selected, result.candidates
    assert result.selected[0].split("@")[0] == name
    before = _slope_error(result.residual_before)
    after = _slope_error(result.residual_after)
    # acceptance: the error is cut at least 3x
    assert before > 3 * after, (before, after)


def test_an_effect_whose_template_fails_is_untestable_not_fatal(shifts, caplog):
    """A template the model cannot measure (a user's wide spots: the model spot with the
    effect's shifts outgrew its stamp) leaves that effect untestable, with a warning; the
    loop runs on and still finds the injected effect (the run stopped with one line
    before)."""
    from bfpsf.diagnosis.catalogue import CATALOGUE, Effect

    class Unmeasurable(Effect):
        name = "unmeasurable"
        parameters = ("u",)

        def templates(self, observables):
            raise BFPSFValueError("adaptive moments failed on 3 of 9 model stamps (edge)")

    result = diagnose(observables(shifts, diffusion=0.03),
                      catalogue=[*CATALOGUE, Unmeasurable()])
    assert result.selected[:1] == ["flux_diffusion"]
    entry = next(c for c in result.candidates if c["name"] == "unmeasurable")
    assert entry["testable"] is False
    assert "unmeasurable is not testable on these data" in caplog.text


def test_unphysical_anisotropy_is_rejected_by_its_bounds(shifts):
    """A quadrupole of 4 times the nearest shift (a charge would grow its own pixel along Y)
    fits the sizes but is outside the physical range: rejected with its value, never named
    (it was named q = -3.6 on an X-only smear when the flats did not fix the BF amplitude)."""
    result = diagnose(observables(shifts, quadrupole=4.0))
    assert "xy_anisotropy" not in result.selected
    entry = result.rejected["xy_anisotropy"]
    assert entry["contradicted_by"] == "bounds" and entry["values"][0] > 1.0
    assert entry["bounds"] == [[-1.0, 1.0]]


def test_loop_finds_boundary_density(shifts):
    """The exact boundary density (G15 fig. bva), rendered with bfpsf's own exact-density
    engine (`exact_boundary_density`, independent of the template's); undersampled spots
    (sigma 0.8 px) make it about 10 % of the slope. Poisson noise would hide it in a quick
    test, so the sizes get 1e-4 px of Gaussian noise per level instead."""
    result = diagnose(observables(shifts, exact_density=True, sigma=0.8, size_noise=1e-4))
    assert result.selected and result.selected[0].split("@")[0] == "boundary_density"
    before = _slope_error(result.residual_before)
    after = _slope_error(result.residual_after)
    assert before > 3 * after, (before, after)


def test_loop_finds_chromatic_size(shifts):
    result = diagnose(observables(shifts, colour=True, colour_slope=0.02))
    assert result.selected and result.selected[0] == "chromatic_size"
    assert _slope_error(result.residual_before) > 3 * _slope_error(result.residual_after)
    value = result.parameters["chromatic_size"]["value"][0]
    # injected: d sigma / d colour = 0.02 px per mag; level-mean colours carry the scatter
    assert value == pytest.approx(0.02, rel=0.3)


def test_loop_finds_readout_pedestal(shifts):
    result = diagnose(observables(shifts, linearity_kwargs={"pedestal": -3e-3}))
    assert result.selected and result.selected[0] == "readout_pedestal"
    before = result.residual_before["correlation_rms"]
    after = result.residual_after["correlation_rms"]
    assert before > 3 * after
    values = result.parameters["readout_pedestal"]["value"]
    # injected R0 = -3e-3 on both lags; noise 2e-4 per point over 12 points
    assert values == pytest.approx([-3e-3, -3e-3], abs=3e-4)


@pytest.mark.parametrize("size_noise", [None, 1e-4])
def test_null_selects_nothing(shifts, size_noise):
    result = diagnose(observables(shifts, sigma=0.8 if size_noise else SIGMA,
                                  size_noise=size_noise))
    assert result.selected == []
    assert result.residual_before == result.residual_after
    # the base model predicts the BF slope of spots rendered with the same physics
    assert abs(result.residual_before["slope_x_percent"]) < 5
    assert abs(result.residual_before["slope_y_percent"]) < 5


def test_result_json_keys(shifts):
    result = diagnose(observables(shifts, n_phases=4))
    data = result.to_json_dict()
    for key in ("residual_before", "candidates", "selected", "residual_after"):
        assert key in data
    for entry in data["candidates"]:
        assert {"name", "statistic", "delta_bic"} <= set(entry)
    for key in ("slope_x_percent", "slope_y_percent", "photometry_bias_mmag"):
        assert key in data["residual_before"]


def test_bad_threshold_and_inputs(shifts):
    obs = observables(shifts, n_phases=4)
    with pytest.raises(BFPSFValueError, match="threshold must be a negative Delta BIC"):
        diagnose(obs, threshold=5.0)
    with pytest.raises(BFPSFInputError, match="sigma_x must have 8 values"):
        SizeTable(PEAKS, np.ones(7), np.ones(8), np.ones(8), np.ones(8))
    with pytest.raises(BFPSFInputError, match="peak_e must be positive"):
        SizeTable(-PEAKS, np.ones(8), np.ones(8), np.ones(8), np.ones(8))


@pytest.mark.slow
def test_loop_on_silicon_sensor_null_and_injected_nonlinearity():
    """SiliconSensor spots (GalSim physics, independent of G15) with the SiliconSensor shifts:
    the null selects nothing; the same spots with an injected non-linearity select it."""
    import galsim

    from bfpsf.interop.silicon_truth import silicon_boundary_shifts

    sensor_name = "lsst_itl_50_8"
    truth = silicon_boundary_shifts(sensor_name)
    rng = galsim.BaseDeviate(5)
    sensor = galsim.SiliconSensor(name=sensor_name, rng=rng)
    profile = galsim.Moffat(fwhm=3.0, beta=3.5)
    phases = _phases(12, seed=3)
    peaks = np.linspace(1e4, 1.2e5, 7)
    stamps, level, phase_index = [], [], []
    for k, peak in enumerate(peaks):
        for j, (px, py) in enumerate(phases):
            fraction = profile.drawImage(nx=24, ny=24, scale=1.0, offset=(px, py)).array.max()
            image = profile.withFlux(peak / fraction).drawImage(
                nx=24, ny=24, scale=1.0, method="phot", sensor=sensor, rng=rng, offset=(px, py))
            stamps.append(image.array.copy())
            level.append(k)
            phase_index.append(j)
    stamps = np.array(stamps)
    level, phase_index = np.array(level), np.array(phase_index)
    selections = {}
    for label, nonlinearity in (("null", 0.0), ("nonlinear", -0.04)):
        data = stamps * (1 + nonlinearity * stamps / 1e5)
        moments = adaptive_moments_batch(data)
        x = peaks[level] / 1e5
        design = np.column_stack([x] + [(phase_index == j).astype(float) for j in range(12)])
        columns = []
        for values in (np.sqrt(moments.mxx), np.sqrt(moments.myy)):
            params, *_ = np.linalg.lstsq(design, values, rcond=None)
            rms = np.sqrt(np.sum((values - design @ params) ** 2)
                          / (values.size - design.shape[1]))
            columns += [np.array([values[level == k].mean() for k in range(7)]),
                        np.full(7, rms / np.sqrt(12))]
        table = SizeTable(peaks, columns[0], columns[2], columns[1], columns[3])
        linearity, correlations = flat_tables(nonlinearity=nonlinearity)
        obs = observables_from_sizes(table, truth, beta=3.5, linearity=linearity,
                                     correlations=correlations)
        selections[label] = diagnose(obs).selected
    assert selections["null"] == []
    assert selections["nonlinear"][:1] == ["gain_nonlinearity"]


# -- PTC residuals and the stars' stacked residual (images mode observables) -------------------
@functools.lru_cache(maxsize=None)
def _itl_flats(nonlinearity):
    """SiliconSensor flats (192^2, 10 levels to 120 ke-, one pair each, gain 1.5), simulated
    once per test process; with a non-linearity, the same charges read through
    signal = s (1 + c s), s the linear flats' signal (read noise included: it changes the
    read noise by 2 c q, 8 % at 100 ke- for c = -4e-7, against 316 e- of shot noise), so the
    two sets share one GalSim simulation."""
    from bfpsf.validation.simulate_flats import simulate_flats

    gain = 1.5
    if nonlinearity:
        return [((image * gain) * (1.0 + nonlinearity * image * gain) / gain, exptime,
                 dict(header, SIMNONLI=float(nonlinearity)))
                for image, exptime, header in _itl_flats(0.0)]
    return simulate_flats("lsst_itl_50_8", np.linspace(1e4, 1.2e5, 10), pairs=1, size=192,
                          nsteps=4, seed=3, gain=gain)


def _calibrated_flats(nonlinearity):
    """`_itl_flats`, calibrated."""
    from bfpsf.calibration import calibrate

    flats = _itl_flats(nonlinearity)
    return calibrate([image for image, _, _ in flats], exptimes=[t for _, t, _ in flats],
                     maxlag=3, n_monte_carlo=0, fit_b=False)


def _flat_observables(cal):
    from bfpsf.diagnosis.observables import flat_observables, ptc_observable
    from bfpsf.diagnosis.tables import Observables

    linearity, correlations = flat_observables(cal)
    return Observables(linearity=linearity, correlations=correlations,
                       ptc=ptc_observable(cal))


def test_ptc_residual_null_flats_select_nothing():
    """Linear SiliconSensor flats: the PTC with the sum-rule a(0, 0) fits within the shot
    noise, and the loop on the flat observables (linearity, correlations, PTC) adds nothing."""
    obs = _flat_observables(_calibrated_flats(0.0))
    pulls = obs.ptc.residual_e / obs.ptc.var_err_e
    # the area beyond lag 3 is missing from the sum rule: ~8 % of a(0, 0), < 2 sigma here
    assert np.max(np.abs(pulls)) < 3.0, pulls
    result = diagnose(obs)
    assert result.selected == []
    assert result.residual_before["ptc_chi2_per_point"] < 2.0


def test_ptc_residual_shows_injected_nonlinearity(tmp_path):
    """Flats with signal = q (1 - 4e-7 q) (-4 % at 100 ke-; c = -0.04 per 1e5 e-): the
    calibration's free a(0, 0) absorbs it, the sum-rule PTC model does not, so the PTC
    residuals run to many sigma at the bright end; the loop selects gain_nonlinearity and
    the PTC residuals fall back to the null level."""
    from bfpsf.validation.report import write_diagnosis_report

    obs = _flat_observables(_calibrated_flats(-4e-7))
    pulls = obs.ptc.residual_e / obs.ptc.var_err_e
    assert pulls[-1] < -10, pulls
    assert np.all(pulls[3:] < -3), pulls
    result = diagnose(obs)
    assert result.selected[:1] == ["gain_nonlinearity"]
    value = result.parameters["gain_nonlinearity"]["value"][0]
    # first-order templates, and the calibrated gain absorbs part of the curvature: 25 %
    assert value == pytest.approx(-0.04, rel=0.25)
    after = result.ptc_curves["residual_after"] / result.ptc_curves["error"]
    assert np.max(np.abs(after)) < 3.0, after
    assert result.residual_after["linearity_chi2_per_point"] < 3.0
    path = write_diagnosis_report(result, tmp_path)
    assert (tmp_path / "ptc_residuals.png").stat().st_size > 0
    assert "PTC residuals chi2 / point" in path.read_text()


@pytest.fixture(scope="module")
def star_field(shifts):
    """64 stars drawn by GalSim and redistributed by GalSim's CDModel (`galsim_bf_stars`),
    2e5-1.2e6 e-, random phases, Poisson + 5 e- read noise; the source table holds the true
    positions; the model is P(F) of the same Gaussian."""
    import galsim
    from astropy.table import Table

    from bfpsf.model.psf import FluxDependentPSF

    # GalSim's default rendering accuracy (kvalue_accuracy 1e-5) shows in a residual stacked
    # over 64 stars of 1e6 e-: chi2 per pixel 1.28-1.44 over three seeds, 1.02-1.15 with these
    profile = galsim.Gaussian(sigma=SIGMA, gsparams=galsim.GSParams(
        kvalue_accuracy=1e-8, xvalue_accuracy=1e-8, folding_threshold=1e-5,
        maxk_threshold=1e-5))
    psf = FluxDependentPSF.from_galsim(profile, shifts, size=15)
    rng = np.random.default_rng(4)
    pitch = 24
    centres = pitch * np.arange(8) + pitch // 2
    xy = np.array([(cx, cy) for cx in centres for cy in centres], dtype=float)
    xy += rng.uniform(-0.5, 0.5, xy.shape)
    fluxes = rng.uniform(2e5, 1.2e6, len(xy))
    image = galsim_bf_stars(profile, xy, fluxes, (8 * pitch,) * 2, shifts)
    peaks = image[np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)]
    image = rng.poisson(np.clip(image, 0.0, None)).astype(float) + rng.normal(0.0, 5.0,
                                                                               image.shape)
    table = Table([xy[:, 0], xy[:, 1], fluxes, peaks, np.zeros(len(xy), int)],
                  names=["x", "y", "flux_e", "peak_e", "flags"])
    return psf, image, table


def test_stacked_star_residual_consistent_with_noise(shifts, star_field):
    import galsim

    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.diagnosis.star_residual import stacked_star_residual

    psf, image, table = star_field
    same = stacked_star_residual([image], [table], psf, half_size=7, noise_e=5.0)
    assert same["n_stars"] == 64
    # chi2 per pixel of 225 pixels: 1 +- 0.09; the per-star flux refit removes a little
    assert 0.75 < same["chi2_per_pixel"] < 1.3
    assert same["rms_over_peak"] < 5e-4
    assert same["radius"].size == same["profile"].size
    # the same stars against the static PSF (no BF): the BF signature stands out
    static = FluxDependentPSF.from_galsim(galsim.Gaussian(sigma=SIGMA), shifts.scaled(0.0),
                                          size=15)
    other = stacked_star_residual([image], [table], static, half_size=7, noise_e=5.0)
    assert other["chi2_per_pixel"] > 10 * same["chi2_per_pixel"]
    # brighter-fatter: the static model leaves a deficit at the core (charge pushed out)
    assert other["profile"][0] < -5 * np.max(same["sigma"])
    assert stacked_star_residual([image], [table], psf, min_peak_e=1e9) is None


def test_cli_images_mode_ptc_and_star_residual(tmp_path, star_field):
    """``bfpsf diagnose --flats --images``: linear SiliconSensor flats and stars drawn with
    P(F): the JSON keeps its keys and adds the stars' stacked residual; the report holds the
    PTC residual plot and the residual image with its radial profile."""
    import json

    from astropy.io import fits

    from bfpsf.cli import main

    paths = []
    for index, (image, exptime, _) in enumerate(_itl_flats(0.0)):
        paths.append(str(tmp_path / f"flat{index:02d}.fits"))
        fits.PrimaryHDU(image, header=fits.Header({"EXPTIME": exptime})).writeto(paths[-1])
    _, stars, _ = star_field
    fits.PrimaryHDU(stars / 1.5).writeto(tmp_path / "stars.fits")
    code = main(["diagnose", "--flats", *paths, "--images", str(tmp_path / "stars.fits"),
                 "--no-fit-b", "--maxlag", "3", "--bins", "6", "--report",
                 str(tmp_path / "report"), "--json", str(tmp_path / "d.json")])
    assert code == 0
    data = json.loads((tmp_path / "d.json").read_text())
    for key in ("residual_before", "candidates", "selected", "residual_after", "unexplained"):
        assert key in data
    assert "ptc_chi2_per_point" in data["residual_before"]
    # one image: the held-out half is every other peak bin, with the same summary keys
    assert data["holdout"]["sizes_split_by"] == "alternate peak bins"
    assert set(data["residual_after_heldout"]) == set(data["residual_after"])
    star = data["star_residual"]
    # unflagged sources only (measure_sources flags some of the 64 bright, close stars)
    assert 20 <= star["n_stars"] <= 64
    # the calibration from 192^2 flats misses the BF amplitude of the stars' shifts by tens
    # of percent: the stack shows it at a fraction of a percent of the peak, not more
    assert 0 < star["rms_over_peak"] < 0.01
    assert star["units"]["profile"].startswith("mean residual per unit star flux")
    for name in ("ptc_residuals.png", "residual_images.png", "radial_profile.png"):
        assert (tmp_path / "report" / name).stat().st_size > 0
    assert "Stacked residual of the stars" in (tmp_path / "report" / "report.md").read_text()


def test_a_residual_of_stars_without_bf_is_not_a_percentage():
    """Sizes with no BF slope on X (raw slope within its error) and a clear one on Y: the X
    residual is given in pixels per 100 ke- with the raw slope beside it, never as a percent
    of a slope consistent with zero (a new user read +957 % of raw); Y stays in percent."""
    from bfpsf.diagnosis.problem import describe_slope, slope_residuals
    from bfpsf.diagnosis.tables import SizeTable

    rng = np.random.default_rng(5)
    peak = np.repeat([1e4, 4e4, 8e4, 1.2e5], 20)
    error = np.full(peak.size, 1e-3)
    sigma_x = 1.3 + error * rng.standard_normal(peak.size)
    sigma_y = 1.3 + 0.02 * peak / 1e5 + error * rng.standard_normal(peak.size)
    sizes = SizeTable(peak, sigma_x, sigma_y, error, error)
    values = slope_residuals(sizes, sigma_x - 1.3, sigma_y - 1.3 - 0.019 * peak / 1e5)
    assert not values["stars_show_bf_x"] and values["stars_show_bf_y"]
    assert abs(values["raw_slope_x"]) < 3 * values["raw_slope_x_err"]
    assert abs(values["residual_slope_y"] - 0.001) < 3 * values["residual_slope_y_err"]
    text_x, text_y = describe_slope(values, "x"), describe_slope(values, "y")
    assert "% of raw" not in text_x and "the stars' BF slope in X is not significant" in text_x
    assert text_y.endswith("% of raw")
    assert abs(values["slope_y_percent"] - 5.0) < 3 * values["slope_y_percent_err"]


@pytest.mark.parametrize("e2_slope", [0.0, 0.03])
def test_an_e2_change_with_flux_contradicts_every_size_effect(shifts, e2_slope):
    """A diagonal effect (a new user's charge-dependent smear along x = y: e2 0 -> 0.012)
    grows the stars on both axes like a size effect, and the flats' size scale had taken it
    (+0.84, "explained"). No catalogue effect changes the e2 of a star symmetric about X or Y,
    so the stars' e2 rising with flux contradicts each (``cross``), and it is reported as
    unexplained; with a flat e2 the injected flux diffusion is named as before."""
    import dataclasses

    observed = observables(shifts, diffusion=0.03)
    rng = np.random.default_rng(3)
    error = np.full(PEAKS.size, 5e-4)
    cross = e2_slope * PEAKS / 1e5 + error * rng.standard_normal(PEAKS.size)
    observed = dataclasses.replace(observed, sizes=dataclasses.replace(
        observed.sizes, cross=cross, cross_err=error))
    result = diagnose(observed)
    if e2_slope:
        assert result.selected == []
        assert result.rejected["flux_diffusion"]["contradicted_by"] == "cross"
        entry = next(entry for entry in result.unexplained
                     if entry["observable"] == "cross moment e2")
        assert entry["sign"] == "rising" and entry["significance"] > 5
        assert not result.verdict["success"]
    else:
        assert result.selected[0] == "flux_diffusion"
        assert not [entry for entry in result.unexplained
                    if entry["observable"] == "cross moment e2"]


def test_a_rising_residual_is_not_constant_in_flux():
    """A residual rising with peak at about 5 sigma: in a fit of x and x^2 together neither
    is significant (they are correlated), which had read "rising with flux, constant in
    flux"; the linear term alone, as the slope that reported it, says linear."""
    from bfpsf.diagnosis.unexplained import _flux_dependence

    rng = np.random.default_rng(11)
    peak = np.tile(np.linspace(1e4, 1.2e5, 6), 4)
    sigma = np.full(peak.size, 1e-3)
    residual = 0.0025 * peak / 1e5 + sigma * rng.standard_normal(peak.size)
    group = np.repeat(np.arange(4), 6)
    assert _flux_dependence(peak, residual, sigma, group)["kind"] == "linear"
    assert _flux_dependence(peak, sigma * rng.standard_normal(peak.size), sigma,
                            group)["kind"] == "constant"


def test_a_heldout_residual_carries_the_error_of_the_fitted_parameters(shifts):
    """On held-out exposures the model's parameters come from the fit part, so a residual
    slope there is uncertain by their error too, and by the templates' accuracy between the
    axes: a new user's BF-only seed read "unexplained sizes y 4.2 sigma" against the
    held-out noise alone. A design of slope 1 per 100 ke- on X with a variance 3 times the
    noise's doubles the X slope's error and leaves Y's alone."""
    from bfpsf.diagnosis.problem import build_problem
    from bfpsf.diagnosis.unexplained import describe_unexplained

    observed = observables(shifts, diffusion=0.03)
    problem = build_problem(observed)
    model = np.zeros_like(problem.residual)

    def by_axis(entries):
        return {entry["axis"]: entry for entry in entries if entry["observable"] == "sizes"}

    alone = by_axis(describe_unexplained(problem, observed, model))
    assert alone["x"]["significance"] > 6 and alone["y"]["significance"] > 6
    design = np.zeros((problem.residual.size, 1))
    start = problem.slices["sizes"].start
    design[start:start + len(observed.sizes), 0] = PEAKS / 1e5
    variance = np.array([[3 * alone["x"]["slope_err"] ** 2]])
    carried = by_axis(describe_unexplained(problem, observed, model,
                                           prediction=(design, variance, np.zeros(1))))
    assert carried["x"]["slope_err"] == pytest.approx(2 * alone["x"]["slope_err"], rel=1e-9)
    assert carried["x"]["significance"] == pytest.approx(alone["x"]["significance"] / 2)
    assert carried["y"]["slope_err"] == pytest.approx(alone["y"]["slope_err"], rel=1e-12)
    # and the templates' 10 % between the axes of the slope the fitted part adds
    value = 30 * alone["x"]["slope_err"]
    carried = by_axis(describe_unexplained(problem, observed, model,
                                           prediction=(design, 0 * variance, np.array([value]))))
    assert carried["x"]["slope_err"] == pytest.approx(np.hypot(alone["x"]["slope_err"],
                                                               0.1 * value), rel=1e-9)


def test_a_residual_held_by_the_faint_stars_is_said_so():
    """A change that falls as 1 / peak (a fixed number of charge traps: a new user's deferred
    charge) beside a rising BF scale error: the slope reads "rising", and the 1/flux part
    says where the rest is (larger on the faint stars); a purely linear residual has none."""
    from bfpsf.diagnosis.unexplained import _flux_dependence

    rng = np.random.default_rng(12)
    peak = np.tile(np.geomspace(3e3, 1.2e5, 8), 4)
    sigma = np.full(peak.size, 5e-4)
    group = np.repeat(np.arange(4), 8)
    x = peak / 1e5
    trail = 0.004 * x + 2e-4 / x + sigma * rng.standard_normal(peak.size)
    found = _flux_dependence(peak, trail, sigma, group)
    assert found["kind"] != "constant" and found["faint_end"] and found["inverse_1e5"] > 0
    plain = _flux_dependence(peak, 0.004 * x + sigma * rng.standard_normal(peak.size), sigma,
                             group)
    assert not plain["faint_end"]


def test_the_flats_split_error_is_a_nuisance_not_an_effect(shifts):
    """Flats that fix a^N against a^E poorly (a new user's E2V flats: a^N / (a^N + a^E) at
    (0, 0) 0.42 +- 0.10) predict the stars' X against Y no better. Spots rendered with the
    split moved by d = 0.4 (`split_shifts`: X's BF +20 %, Y's -20 %) beside flats whose split
    error is 0.25: the size block's split nuisance takes it, within its prior, and nothing is
    named (measured: d = 0.396 +- 0.009; X +13.6 -> +0.02, Y -20.5 -> -0.02 % of raw). With
    the scale's prior alone (the loop before the split nuisance) the same data had the scale
    contradicted by axis and the residual left as it was."""
    from bfpsf.diagnosis.catalogue import split_shifts

    sigma_x, sigma_y, err_x, err_y, _ = render_sizes(split_shifts(shifts, 0.4), size_noise=1e-4)
    table = SizeTable(PEAKS, sigma_x, sigma_y, err_x, err_y)
    linearity, correlations = flat_tables()
    meta = {"scale_err": 0.1, "split_err": 0.25}
    both = diagnose(observables_from_sizes(table, shifts, linearity=linearity,
                                           correlations=correlations, meta=meta))
    assert both.selected == [], both.candidates
    split = both.nuisance["calibration_split"]
    assert split["contradicted_by"] is None
    assert split["value"] == pytest.approx(0.4, abs=3 * split["error"])
    assert abs(both.residual_after["slope_x_percent"]) < 3
    assert abs(both.residual_after["slope_y_percent"]) < 3
    scale_only = diagnose(observables_from_sizes(table, shifts, linearity=linearity,
                                                 correlations=correlations,
                                                 meta={"scale_err": 0.1}))
    assert "calibration_split" not in scale_only.nuisance
    assert scale_only.nuisance["calibration_scale"]["contradicted_by"] == "axis"
    assert scale_only.residual_after["slope_y_percent"] < -15


def test_the_split_prior_is_the_spread_of_the_draws(shifts):
    """`bf_scale_error` on shift draws that differ from the nominal shifts only by a split
    (`split_shifts`, d drawn with an rms of 0.2) and by a scale (rms 0.05): the split prior
    is the draws' rms of d to its sampling error (40 draws: 11 %); the scale prior, the rms
    per axis, holds the scale's and each axis' share of the split (d / 2 at most) and no
    more; parity holds for every moved split."""
    from bfpsf.diagnosis.catalogue import split_shifts

    rng = np.random.default_rng(3)
    d, s = rng.normal(0.0, 0.2, 40), rng.normal(0.0, 0.05, 40)
    draws = [split_shifts(shifts.scaled(1 + s_i), d_i) for d_i, s_i in zip(d, s)]
    for draw in draws[:3]:
        BoundaryShifts(draw.north, draw.east)      # raises on broken parity
    table = SizeTable(PEAKS, *render_sizes(shifts, n_phases=4)[:4])
    meta = observables_from_sizes(table, shifts, shift_draws=draws).meta
    assert meta["split_err"] == pytest.approx(np.std(d, ddof=1), rel=0.15)
    assert 0.8 * np.std(s, ddof=1) < meta["scale_err"] < np.hypot(np.std(s, ddof=1),
                                                                    0.6 * np.std(d, ddof=1))


def test_a_nonlinearity_is_named_beside_a_bf_amplitude_the_flats_did_not_predict(shifts):
    """Stars with 30 % less BF than their flats predict (GalSim's own E2V stars: 23-33 %)
    and a gain non-linearity of -1.5 % at 1e5 e-, flats with a BF amplitude error of 8 %:
    the size scale nuisance cannot reach -0.3 within its prior, so the non-linearity's size
    part (-0.028) disagrees with the flat means' (-0.0153 +- 0.0005) and the observable
    dimension contradicts it. Tested again with the stars' BF amplitude free (the
    ``calibration_scale`` candidate beside it), both signatures match: both are named,
    each to its error (measured: s = -0.284 +- 0.019, c = -0.0153 +- 0.0005)."""
    sigma_x, sigma_y, err_x, err_y, _ = render_sizes(shifts.scaled(0.7), nonlinearity=-0.015)
    table = SizeTable(PEAKS, sigma_x, sigma_y, err_x, err_y)
    linearity, correlations = flat_tables(nonlinearity=-0.015)
    result = diagnose(observables_from_sizes(table, shifts, linearity=linearity,
                                             correlations=correlations,
                                             meta={"scale_err": 0.08, "split_err": 0.05}))
    assert result.selected == ["calibration_scale", "gain_nonlinearity"], result.rejected
    entry = next(c for c in result.candidates if c["name"] == "gain_nonlinearity")
    assert entry["paired_with"] == "calibration_scale"
    for name, truth in (("gain_nonlinearity", -0.015), ("calibration_scale", -0.3)):
        value, error = (result.parameters[name][key][0] for key in ("value", "error"))
        nuisance = result.nuisance.get(name) or {}
        total = value + (0.0 if nuisance.get("contradicted_by") else nuisance.get("value", 0))
        assert total == pytest.approx(truth, abs=3 * error)


def test_the_verdict_says_how_much_the_flats_errors_could_hide():
    """`hiding_room`: an undeclared effect shaped like BF hides in the scale's 3 sigma and in
    half the split's (each axis moves by d / 2): precise flats leave no caveat, a new user's
    20 ITL flats of 130^2 (priors 0.64 and 1.31) leave 192 % isotropic and 196 % on one
    axis, said in the verdict; a contradicted nuisance hides nothing (it is not applied)."""
    from bfpsf.diagnosis.unexplained import hiding_room, verdict

    def nuisance(scale, split, against=None, value=0.62):
        return {"calibration_scale": {"prior": scale, "contradicted_by": against,
                                      "value": value, "error": 0.02},
                "calibration_split": {"prior": split, "contradicted_by": None,
                                      "value": -0.04, "error": 0.09}}

    assert hiding_room(nuisance(0.05, 0.1, value=0.04)) == []
    assert hiding_room({}) == []
    # precise flats, but the stars took the scale beyond 1 of its prior: said (a new user's
    # star-only non-linearity took +0.13 +- 0.05 of a prior of 0.085 without a word)
    (line,) = hiding_room(nuisance(0.085, 0.065, value=0.13))
    assert "isotropic up to 26 %" in line and "the scale +0.13 +- 0.02, 1.5 of its prior" in line
    (line,) = verdict([], nuisance(0.64, 1.31))["caveats"]
    assert "isotropic up to 192 %, on one axis up to 196 %" in line
    # and how much of it this set's stars took
    assert "the scale +0.62 +- 0.02, 1.0 of its prior and the X / Y split -0.04" in line
    (line,) = hiding_room(nuisance(0.64, 0.3, against="axis"))
    assert "isotropic" not in line and "on one axis up to 45 %" in line


def test_signature_plot_of_candidates_rejected_by_their_range_alone(tmp_path):
    """A loop whose only rejected candidate lay outside its physical range (a new user's
    ``xy_anisotropy`` at 8.35) has no signature to draw: the plot names it, and matplotlib's
    'No artists with labels' warning (an error in this suite) is not raised."""
    from types import SimpleNamespace

    from bfpsf.plotting.diagnose import plot_signatures

    values = {"slope_x_percent": -27.0, "slope_x_percent_err": 7.6,
              "slope_y_percent": 25.6, "slope_y_percent_err": 6.2}
    result = SimpleNamespace(
        empirical=None, residual_after_heldout=values, residual_after=values, verdict={},
        rejected={"xy_anisotropy": {"reason": "its fit 8.35 is outside its physical range"}})
    figure = plot_signatures(result)
    texts = [text.get_text() for ax in figure.axes for text in ax.texts]
    assert any("xy_anisotropy" in text for text in texts)
    figure.savefig(tmp_path / "signatures.png")


def test_an_odd_residual_that_leaves_the_sizes_alone_is_reported(shifts):
    """A trail that leaves the sizes alone (a new user's serial charge-transfer trail: every
    size candidate was contradicted by parity and the report named nothing): the stars'
    skewness along X changes with flux, more so far from the amplifier, while their sizes
    are explained. The report says "skewness, along x, odd parity" with its dependence on
    the column, nothing on Y, and the verdict is no success."""
    import dataclasses

    from bfpsf.diagnosis.problem import build_problem
    from bfpsf.diagnosis.signature import describe_entry
    from bfpsf.diagnosis.unexplained import describe_unexplained, verdict

    observed = observables(shifts)
    table = observed.sizes
    rng = np.random.default_rng(14)
    columns = np.repeat([100.0, 700.0, 1300.0, 1900.0], len(table))
    tiled = {name: np.tile(getattr(table, name), 4) for name in
             ("peak_e", "sigma_x", "sigma_y", "sigma_x_err", "sigma_y_err")}
    error = np.full(columns.size, 2e-4)
    trail = -2e-3 * tiled["peak_e"] / 1e5 * columns / 1000.0  # grows from the amplifier
    sizes = SizeTable(**tiled, x_detector=columns, skew_x=trail + error * rng.standard_normal(
        columns.size), skew_y=error * rng.standard_normal(columns.size), skew_x_err=error,
        skew_y_err=error)
    observed = dataclasses.replace(observed, sizes=sizes)
    problem = build_problem(observed)
    entries = describe_unexplained(problem, observed, problem.residual.copy())
    assert [(entry["observable"], entry["axis"], entry["parity"]) for entry in entries] == [
        ("skewness", "x", "odd")], entries
    entry = entries[0]
    assert entry["sign"] == "falling" and entry["significance"] > 10
    assert entry["position_dependence"]["kind"] == "falling with distance from the amplifier"
    assert entry["flats"] == "stars only"
    assert describe_entry(entry).startswith("skewness, along x, ")
    assert not verdict(entries, {})["success"]


def test_an_effect_no_product_applies_is_no_success():
    """A named effect that no refined calibration applies (P(F) has no flux-dependent blur)
    leaves what it explains in every product: the verdict says so and is no success (a new
    user's star-only non-linearity, 4 times the size, was named flux_diffusion and read
    "explained" while held-out P(F) left +45 % of the raw X slope); the readout pedestal,
    which the calibration subtracts, and a gain non-linearity, which it applies, are not."""
    from bfpsf.diagnosis.refine import unapplied
    from bfpsf.diagnosis.unexplained import verdict

    named = unapplied(["flux_diffusion", "readout_pedestal", "gain_nonlinearity",
                       "boundary_density@physical"])
    assert list(named) == ["flux_diffusion", "boundary_density@physical"]
    judged = verdict([], {}, unapplied=named)
    assert not judged["success"] and len(judged["reasons"]) == 2
    assert judged["reasons"][0].startswith("flux_diffusion is named, but no refined "
                                           "calibration applies it (P(F) has no flux-dependent")
    assert verdict([], {}, unapplied=unapplied(["readout_pedestal"]))["success"]
