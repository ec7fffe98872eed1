"""End-to-end validation against GalSim's SiliconSensor (the truth, DESIGN.md).

`validate` simulates SiliconSensor flats and Moffat spots, runs the whole chain and reports, side
by side:

1. truth a(dx, dy) (`bfpsf.interop.silicon_truth.silicon_area_coefficients`) against the a
   recovered by `bfpsf.calibrate` from the simulated flats;
2. the measured BF slope of the spots in X and Y (adaptive moments, G15 section 3.2) against
   the slope predicted from the boundary shifts (G15 section 6.3: the faint-spot model scaled
   and redistributed), for the shifts of the flats calibration (with the error propagated from
   the a errors by re-solving 20 draws) and for SiliconSensor's own shifts
   (`silicon_boundary_shifts`, scaled to its landing under a spot: a diagnostic);
3. the residual slope after the flux-dependent PSF P(F) (`bfpsf.model.psf_fit.fit_psf`):
   measured sizes minus the sizes of P(F) at each spot's flux and phase, percent of the raw
   slope. Every spot is also drawn as a BF-free twin (same photons, diffusion and noise through
   the sensor with BF off, `bfpsf.validation.simulate_spots`): the residual is computed on the
   BF change of each pair (measured twin difference minus P(F) - P0), which removes the photon
   noise of the sizes (``residual_slope_*``); the plain unpaired value is reported beside it
   (``residual_slope_*_unpaired``);
4. the residual slope after G15's pixel-level inverse (`bfpsf.correct`), for comparison (paired
   the same way);
5. the photometry bias, brightest minus faintest level (mmag of measured over collected
   charge; positive when the faint spots come out too bright), with a static PSF built from the
   bright spots and with P(F): a uniform-weight least-squares flux over the whole stamp at the
   true position (``photometry_bias_*``: the sky-limited limit, where a shape error biases the
   flux most), and photutils PSFPhotometry through `bfpsf.measure.photometry.psf_photometry`
   when installed (``photometry_bias_photutils_*``) with the inverse-variance weights of the
   spots seen on a sky of `PHOTOMETRY_SKY_E` (the sky enters the weights, not the noise);
6. the closed loop (`bfpsf.diagnosis.loop`) on the same data: what the residual asks for.

A stage whose module is not installed reports ``{"available": False, "reason": ...}``.
SiliconSensor uses OpenMP; run with ``OMP_NUM_THREADS`` at most the free cores.
"""

import logging
import time

import numpy as np
from tqdm import tqdm

from .. import calibration
from ..diagnosis.loop import diagnose
from ..diagnosis.observables import flat_observables, observables_from_sizes
from ..diagnosis.spot_model import SpotForwardModel
from ..diagnosis.tables import SizeTable
from ..errors import BFPSFError, BFPSFValueError
from ..measure import photometry, read_noise
from ..measure.slopes import PEAK_UNIT_E, fit_bf_slope
from ..model import psf_fit
from ..model.inverse import correct
from ..moments.adaptive import adaptive_moments_batch
from . import simulate_flats as simulate
from .simulate_spots import simulate_spots
from .validation_config import FULL, QUICK, ValidationConfig

__all__ = ["ValidationConfig", "QUICK", "FULL", "validate", "FLATS_LABEL", "TRUTH_LABEL"]

#: How the two sources of boundary shifts are named in every result and table.
FLATS_LABEL = "flats calibration"
TRUTH_LABEL = "SiliconSensor landing under a spot (diagnostic)"

_MAG = 2.5 / np.log(10.0)

#: Sky, e- per pixel, under the spots for the photutils photometry (the simulated spots have
#: none). It sets the weights of a real sky-limited image; without it the Poisson weights of
#: the spot alone make a PSF fit an aperture sum over the fit box, blind to the shape of the
#: PSF: the static-PSF bias vanishes (+0.3 mmag, FULL run) and says nothing about real images.
PHOTOMETRY_SKY_E = 1000.0


def _unavailable(reason):
    return {"available": False, "reason": reason}


def _progress(enabled, total, description):
    if not enabled:
        return None
    return tqdm(total=total, desc=description, unit="stage")


def _slope(peak_e, values, group=None):
    """Slope of values against peak, per 100 ke-, its error and the mean intercept.

    ``group`` (e.g. the sub-pixel phase of each spot) gets its own intercept, so that the
    phase dependence of a pixelised size cancels. Points are weighted by the inverse variance
    of the residuals at their peak level (faint spots are noisier), estimated from an
    unweighted first pass; the error comes from those variances. Both passes are
    `bfpsf.measure.slopes.fit_bf_slope`.
    """
    peak = np.asarray(peak_e, float)
    y = np.asarray(values, float)
    first = fit_bf_slope(peak, y, group=group, clip_nsigma=None)
    # residuals of the first pass: refit the group intercepts at the common slope
    detrended = y - first.slope * peak / PEAK_UNIT_E
    labels = np.zeros(y.size, int) if group is None else np.unique(group, return_inverse=True)[1]
    offsets = np.array([detrended[labels == g].mean() for g in range(labels.max() + 1)])
    residual = detrended - offsets[labels]
    dof_fraction = max(first.dof, 1) / y.size
    error = np.empty_like(y)
    for level in np.unique(peak):
        members = peak == level
        error[members] = np.sqrt(max(np.mean(residual[members] ** 2) / dof_fraction, 1e-30))
    fit = fit_bf_slope(peak, y, size_err=error, group=group, clip_nsigma=None)
    return fit.slope, fit.slope_err, fit.intercept


def _moments(stamps):
    result = adaptive_moments_batch(np.asarray(stamps))
    return np.sqrt(result.mxx), np.sqrt(result.myy), np.asarray(result.flags)


def _level_means(spots, values):
    """Mean size per level and its error.

    Every level holds the same sub-pixel phases, so the phase dependence cancels in the means;
    the error is the rms about a line with per-phase intercepts over sqrt(spots per level).
    """
    levels = np.unique(spots.level)
    means = np.array([values[spots.level == k].mean() for k in levels])
    # unweighted: the error scale is the rms about the line
    rms = fit_bf_slope(spots.peaks, values, group=spots.phase, clip_nsigma=None).error_scale
    per_level = values.size / levels.size
    return means, np.full(levels.size, rms / np.sqrt(per_level))


def _residual_percent(spots, residual, raw_slope):
    slope, slope_err, _ = _slope(spots.peaks, residual, spots.phase)
    return 100.0 * slope / raw_slope, 100.0 * slope_err / abs(raw_slope)


def _residual_entries(spots, raw, measured, twin, predicted=(0.0, 0.0), static=(0.0, 0.0)):
    """Residual slopes in percent of ``raw``, paired with the BF-free twins and unpaired.

    Paired: (measured - twin) - (predicted - static) against peak, i.e. the BF change of each
    spot minus the model's; unpaired: measured - predicted. Both estimate the same slope (the
    twins and the static model do not depend on flux); the paired one without photon noise.
    """
    out = {}
    for index, axis in enumerate("xy"):
        paired = (measured[index] - twin[index]) - (predicted[index] - static[index])
        percent, error = _residual_percent(spots, paired, raw[axis])
        out[f"residual_slope_{axis}_percent"] = percent
        out[f"residual_slope_{axis}_percent_err"] = error
        percent, error = _residual_percent(spots, measured[index] - predicted[index], raw[axis])
        out[f"residual_slope_{axis}_unpaired_percent"] = percent
        out[f"residual_slope_{axis}_unpaired_percent_err"] = error
    return out


# -- stages ---------------------------------------------------------------------------------------
def _stage_flats(config):
    flats = simulate.simulate_flats(config.sensor, config.flat_levels_e, pairs=config.flat_pairs,
                                    size=config.flat_size, gain=config.gain,
                                    read_noise_e=config.read_noise_e, nsteps=config.flat_nsteps,
                                    seed=config.seed)
    # fit_b=False: the A+19 b term is not constrained by a few small flats and its freedom
    # inflates the a errors about 5x (measured on 256^2 ITL flats: sigma a(1,0) 1.5e-7 with b,
    # 3.5e-8 without)
    try:
        cal = calibration.calibrate([flat[0] for flat in flats],
                                    exptimes=[flat[1] for flat in flats], maxlag=config.maxlag,
                                    fit_b=config.fit_b, n_monte_carlo=20, seed=config.seed)
    except BFPSFError as error:
        # reported in the table; the spot stages still run with the truth shifts
        return _unavailable(f"calibration failed: {error}"), None
    return {"available": True, "gain": cal.gain, "gain_err": cal.gain_err,
            "gain_true": config.gain, "n_flats": len(flats),
            "warnings": list(getattr(cal, "warnings", ()))}, cal


def _stage_truth(config, cal):
    from ..interop import silicon_truth as interop  # imports GalSim: only when used

    truth = interop.silicon_area_coefficients(config.sensor, maxlag=config.maxlag)
    out = {"available": True, "lags": [], "truth": [], "recovered": [], "recovered_err": [],
           "pull": []}
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2)):
        out["lags"].append([dx, dy])
        out["truth"].append(float(truth[dy, dx]))
        if cal is not None:
            value, error = float(cal.a[dy, dx]), float(cal.a_err[dy, dx])
            out["recovered"].append(value)
            out["recovered_err"].append(error)
            out["pull"].append((value - truth[dy, dx]) / error if error > 0 else None)
    # GalSim's landing is not additive: the shifts its spots see are the single-pixel landing
    # shifts scaled to where the boundaries sit under a spot's charge (`landing_under`)
    shifts = interop.silicon_boundary_shifts(config.sensor, radius=config.maxlag,
                                             under=_spot_charge(config))
    return out, truth, shifts


def _spot_profile(config):
    """The spots' charge profile: the Moffat blurred by SiliconSensor's diffusion."""
    import galsim

    from ..interop.silicon_truth import silicon_diffusion_sigma  # imports GalSim: only when used

    return galsim.Convolve(galsim.Moffat(fwhm=config.fwhm, beta=config.beta),
                           galsim.Gaussian(sigma=silicon_diffusion_sigma(config.sensor)))


def _spot_charge(config):
    size = int(config.stamp_size) | 1
    return _spot_profile(config).drawImage(nx=size, ny=size, scale=1.0).array


def _phase_grid(n, seed):
    """n sub-pixel offsets in [-0.5, 0.5)^2: a shifted 2-D Halton-like lattice (fixed per run)."""
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    shift = np.random.default_rng(seed).uniform(size=2)
    k = np.arange(n)
    return np.column_stack([((k + 0.5) / n + shift[0]) % 1.0 - 0.5,
                            (k * golden + shift[1]) % 1.0 - 0.5])


def _stage_spots(config):
    """Moffat spots photon-shot through SiliconSensor with their BF-free twins, the SAME
    sub-pixel phases at every level (`bfpsf.validation.simulate_spots.simulate_spots`)."""
    return simulate_spots(sensor=config.sensor, fwhm=config.fwhm, beta=config.beta,
                          peaks_e=config.peaks_e, n_per_level=config.n_per_level,
                          stamp_size=config.stamp_size, seed=config.seed + 1,
                          bf_free_twin=True,
                          offsets=_phase_grid(config.n_per_level, config.seed))


def _stage_prediction(config, spots, measured, shift_sets, cal=None, n_draws=20):
    # the spots BF acts on are the optical Moffat blurred by SiliconSensor's charge diffusion
    profile = _spot_profile(config)
    out = {"available": True, "rows": []}
    peaks = np.asarray(config.peaks_e, float)

    def predict(shifts):
        model = SpotForwardModel(profile, shifts, stamp_size=spots.stamps.shape[1] - 1 | 1,
                                 phases=3)
        sigma_x, sigma_y = model.sizes(peaks)
        return _slope(peaks, sigma_x)[0], _slope(peaks, sigma_y)[0]

    for label, shifts in shift_sets.items():
        row = {"shifts": label}
        slopes = predict(shifts)
        errors = (None, None)
        if label == FLATS_LABEL and cal is not None and n_draws:
            # the calibration error: the slope of every shift sample the calibration carries
            draws = [predict(sample) for sample in cal.shift_samples(limit=n_draws)]
            if len(draws) >= 2:
                errors = tuple(np.std(np.array(draws), axis=0, ddof=1))
        for index, axis in enumerate("xy"):
            row[f"predicted_slope_{axis}"] = slopes[index]
            row[f"predicted_slope_{axis}_err"] = errors[index]
            row[f"predicted_over_measured_{axis}"] = slopes[index] / measured[f"slope_{axis}"]
            # pull against the BF-free-twin slope (the measured slope without photon noise)
            if errors[index] is not None:
                difference = slopes[index] - measured[f"paired_slope_{axis}"]
                sigma = np.hypot(errors[index], measured[f"paired_slope_{axis}_err"])
                row[f"pull_{axis}"] = float(difference / sigma)
        out["rows"].append(row)
    return out


def _psf_sizes(psf, spots, fluxes):
    """Sizes of P(F) at each spot's flux and sub-pixel phase (moments of the model image)."""
    half = spots.stamps.shape[1] // 2 - 1
    images = []
    for x, y, flux in zip(spots.x, spots.y, fluxes):
        phase_x, phase_y = x - np.round(x), y - np.round(y)
        images.append(psf.star_image(flux, x_phase=phase_x, y_phase=phase_y, half_size=half))
    sigma_x, sigma_y, _ = _moments(np.array(images))
    return sigma_x, sigma_y


def _flux_fit(psf, stamp, x, y, flux_guess, *, flux_dependent, iterations=3):
    """Least-squares flux of one stamp with the model at its true position (uniform weights)."""
    half = psf.half_size
    ny, nx = stamp.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    inside = (np.abs(xx - x) <= half) & (np.abs(yy - y) <= half)
    flux = flux_guess
    for _ in range(iterations if flux_dependent else 1):
        template = psf.evaluate(xx[inside], yy[inside], flux if flux_dependent else 1.0, x, y)
        template = template / (flux if flux_dependent else 1.0)
        flux = float(np.sum(template * stamp[inside]) / np.sum(template ** 2))
    return flux


def _stage_psf(config, spots, measured_sizes, twin_sizes, raw, shifts):
    fluxes = spots.stamps.sum(axis=(1, 2))
    positions = [[(x, y)] for x, y in zip(spots.x, spots.y)]
    images = list(spots.stamps)
    size = 2 * (spots.stamps.shape[1] // 2) - 5
    fit = psf_fit.fit_psf(images, positions, shifts, oversampling=config.psf_oversampling,
                          size=size, max_iterations=20)
    psf = fit.psf
    predicted = _psf_sizes(psf, spots, fluxes)
    static_sizes = _psf_sizes(psf, spots, np.ones_like(fluxes))  # P0: BF of 1 e- is nil
    out = {"available": True, "converged": bool(fit.converged), "iterations": fit.iterations,
           **_residual_entries(spots, raw, measured_sizes, twin_sizes, predicted,
                               static_sizes)}
    # stacked residual images of the brightest level: data minus the static (zero-flux) model
    # scaled to each spot's flux (the BF signature, G15 fig. spots-diff), and minus P(F)
    brightest = np.flatnonzero(spots.level == spots.level.max())
    half = spots.stamps.shape[1] // 2 - 1
    stack_static, stack_model = 0.0, 0.0
    for index in brightest:
        phase_x = spots.x[index] - np.round(spots.x[index])
        phase_y = spots.y[index] - np.round(spots.y[index])
        cx, cy = int(np.round(spots.x[index])), int(np.round(spots.y[index]))
        data = spots.stamps[index][cy - half:cy + half + 1, cx - half:cx + half + 1]
        model = psf.star_image(fluxes[index], x_phase=phase_x, y_phase=phase_y,
                               half_size=half)
        static_model = psf.star_image(1.0, x_phase=phase_x, y_phase=phase_y,
                                      half_size=half) * fluxes[index]
        stack_static = stack_static + (data - static_model) / brightest.size
        stack_model = stack_model + (data - model) / brightest.size
    residual_images = {"bright - static model (e-)": stack_static,
                       "bright - P(F) (e-)": stack_model}
    # photometry: static PSF from the bright spots vs P(F)
    bright = spots.level >= spots.level.max() - 1
    static = psf_fit.fit_psf([images[i] for i in np.flatnonzero(bright)],
                             [positions[i] for i in np.flatnonzero(bright)], shifts,
                             oversampling=config.psf_oversampling, size=size,
                             include_bf=False, max_iterations=20).psf

    magnitudes = {"static": [], "flux_dependent": [], "photutils_static": [],
                  "photutils_flux_dependent": []}
    quiet = _NoiselessSkyByDesign()
    read_noise.log.addFilter(quiet)
    try:
        _photometry_of_spots(images, spots, fluxes, static, psf, config, magnitudes)
    finally:
        read_noise.log.removeFilter(quiet)
    for key, values in magnitudes.items():
        values = np.asarray(values)
        faint = values[spots.level == spots.level.min()].mean()
        brightest = values[spots.level == spots.level.max()].mean()
        name = (f"photometry_bias_photutils_{key[len('photutils_'):]}_mmag"
                if key.startswith("photutils_") else f"photometry_bias_{key}_mmag")
        out[name] = float(1e3 * (brightest - faint))
    return out, residual_images


class _NoiselessSkyByDesign(logging.Filter):
    """Drops `psf_photometry`'s read-noise and sky checks: the spots' photometry adds a
    noiseless sky and weighs with the sky's and the read noise's variance by design, which
    the checks reported for every spot (88 warnings in ``bfpsf validate --quick``: a new
    user's terminal flooded)."""

    def filter(self, record):
        return not record.getMessage().startswith(("read noise", "the sky pixels scatter"))


def _photometry_of_spots(images, spots, fluxes, static, psf, config, magnitudes):
    """Each spot's flux with the static PSF and with P(F), by a direct fit and through
    `psf_photometry` (photutils), as magnitudes against the truth, into ``magnitudes``."""
    for index in range(len(images)):
        for key, model, dependent in (("static", static, False),
                                      ("flux_dependent", psf, True)):
            flux = _flux_fit(model, images[index], spots.x[index], spots.y[index],
                             fluxes[index], flux_dependent=dependent)
            magnitudes[key].append(-_MAG * np.log(flux / fluxes[index]))
            # the sky is noiseless: the bias is not buried in its photon noise
            table = photometry.psf_photometry(
                images[index] + PHOTOMETRY_SKY_E, model, background_e=PHOTOMETRY_SKY_E,
                read_noise_e=config.read_noise_e,
                positions=np.array([[spots.x[index], spots.y[index]]]))
            flux = float(table["flux_fit"][0])
            magnitudes[f"photutils_{key}"].append(-_MAG * np.log(flux / fluxes[index]))


def _stage_inverse(spots, raw, twin_sizes, shifts):
    corrected = np.array([correct(np.clip(stamp, 0, None), shifts)
                          for stamp in spots.stamps])
    sigma_x, sigma_y, _ = _moments(corrected)
    return {"available": True,
            **_residual_entries(spots, raw, (sigma_x, sigma_y), twin_sizes)}


def _stage_diagnose(config, spots, sizes_x, sizes_y, shifts, cal):
    sigma_x, err_x = _level_means(spots, sizes_x)
    sigma_y, err_y = _level_means(spots, sizes_y)
    table = SizeTable(np.asarray(config.peaks_e, float), sigma_x, sigma_y, err_x, err_y,
                      label=f"SiliconSensor {config.sensor} Moffat spots")
    linearity = correlations = None
    if cal is not None:
        linearity, correlations = flat_observables(cal)
    observables = observables_from_sizes(table, shifts, beta=config.beta, linearity=linearity,
                                         correlations=correlations)
    return diagnose(observables)


def validate(config=None, *, quick=False, progress=False, shifts_for_model="flats"):
    """Run the end-to-end validation on GalSim SiliconSensor simulations.

    Parameters
    ----------
    config : ValidationConfig, optional
        Default `QUICK` when ``quick`` else `FULL`.
    quick : bool, optional
    progress : bool, optional
        tqdm progress bar over the stages.
    shifts_for_model : {'flats', 'truth'}, optional
        Boundary shifts given to P(F), the pixel inverse and the closed loop: the flats
        calibration (``'flats'``, default: the path a user takes) or SiliconSensor's own
        landing shifts (``'truth'``: a diagnostic that isolates the PSF model from the
        calibration; every table names it as such). The slope prediction is reported for both.

    Returns
    -------
    dict
        ``config``, ``timing_s`` and one entry per stage: ``calibration``, ``area``,
        ``slopes``, ``prediction``, ``psf``, ``inverse``, ``diagnose`` (each with
        ``available``), plus ``diagnosis`` (the `DiagnosisResult`), ``residual_images`` and
        ``truth_area`` (arrays, for the report).
    """
    if shifts_for_model not in ("truth", "flats"):
        msg = f"shifts_for_model must be 'truth' or 'flats', got {shifts_for_model!r}"
        raise BFPSFValueError(msg, shifts_for_model)
    config = config or (QUICK if quick else FULL)
    timing = {}
    result = {"config": config.to_dict(), "shifts_for_model": shifts_for_model}
    bar = _progress(progress, 7, "bfpsf validate")

    def step(name, function, *args):
        start = time.perf_counter()
        if bar is not None:
            bar.set_postfix_str(name)
        value = function(*args)
        timing[name] = time.perf_counter() - start
        if bar is not None:
            bar.update(1)
        return value

    result["calibration"], cal = step("flats+calibration", _stage_flats, config)
    result["area"], truth_area, truth_shifts = step("truth", _stage_truth, config, cal)
    spots = step("spots", _stage_spots, config)

    sizes_x, sizes_y, flags = _moments(spots.stamps)
    slopes = {"available": True, "n_spots": int(len(spots.peaks)),
              "n_flagged": int(np.count_nonzero(flags))}
    raw = {}
    for axis, values in (("x", sizes_x), ("y", sizes_y)):
        slope, error, intercept = _slope(spots.peaks, values, spots.phase)
        slopes[f"slope_{axis}"], slopes[f"slope_{axis}_err"] = slope, error
        slopes[f"intercept_{axis}"] = intercept
        slopes[f"relative_{axis}_percent"] = 100 * slope * max(config.peaks_e) / 1e5 / intercept
        raw[axis] = slope
    # the BF change of each spot against its BF-free twin: the same slope, without photon noise
    twin_x, twin_y, _ = _moments(spots.twin)
    for axis, values, twin in (("x", sizes_x, twin_x), ("y", sizes_y, twin_y)):
        slope, error, _ = _slope(spots.peaks, values - twin, spots.phase)
        slopes[f"paired_slope_{axis}"], slopes[f"paired_slope_{axis}_err"] = slope, error
    result["slopes"] = slopes

    shift_sets = {}
    if cal is not None and cal.shifts is not None:
        shift_sets[FLATS_LABEL] = cal.shifts
    if truth_shifts is not None:
        shift_sets[TRUTH_LABEL] = truth_shifts
    result["prediction"] = step("prediction", _stage_prediction, config, spots, slopes,
                                shift_sets, cal)
    flats_shifts = cal.shifts if cal is not None else None
    if shifts_for_model == "flats" and flats_shifts is None:
        msg = ("the flats calibration gave no boundary shifts "
               f"({result['calibration'].get('reason', 'no brighter-fatter signal')}); "
               "use shifts_for_model='truth' for a diagnostic run")
        raise BFPSFValueError(msg, shifts_for_model)
    model_shifts = flats_shifts if shifts_for_model == "flats" else truth_shifts
    result["model_shifts"] = FLATS_LABEL if shifts_for_model == "flats" else TRUTH_LABEL
    result["psf"], result["residual_images"] = step(
        "P(F)", _stage_psf, config, spots, (sizes_x, sizes_y), (twin_x, twin_y), raw, model_shifts)
    result["inverse"] = step("inverse", _stage_inverse, spots, raw, (twin_x, twin_y),
                             model_shifts)
    diagnosis = step("diagnose", _stage_diagnose, config, spots, sizes_x, sizes_y,
                     model_shifts, cal)
    result["diagnose"] = {"available": True, **diagnosis.to_json_dict()}
    result["diagnosis"] = diagnosis
    if bar is not None:
        bar.close()
    result["timing_s"] = timing
    result["truth_area"] = truth_area
    return result
