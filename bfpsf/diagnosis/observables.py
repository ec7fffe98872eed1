"""What the closed loop compares with the model: the builders of its observables.

The tables (`SizeTable`, `LinearityTable`, `CorrelationTable`, `PTCTable`, `Observables`)
are in `bfpsf.diagnosis.tables`. Builders: `observables_from_sizes` (a size table and
boundary shifts), `observables_from_images` (flat-field and spot FITS files: calibrate,
measure, bin, fit P0 as `bfpsf psf`), `flat_observables` and `ptc_observable` (the flat tables
of a `Calibration`). The measured-table readers are in `bfpsf.diagnosis.readers`.
"""

import numpy as np
from scipy.optimize import brentq

from ..calibration import calibrate
from ..calibration.product import Calibration
from ..calibration.ptc import covariance_errors, full_covariance_model
from ..errors import BFPSFInputError, BFPSFValueError
from ..io.amplifiers import read_amplifiers
from ..io.saturation import saturation_e
from ..least_squares import polynomial_fit
from ..measure.neighbours import isolated_stars
from ..measure.prepare import prepare_image
from ..measure.slopes import fit_bf_slope
from ..measure.sources import aperture_fraction, measure_sources, sky_level
from ..model.psf_fit import DEFAULT_SIZE, fit_psf
from ..moments.result import moments_from_hsm
from .binning import DEFAULT_BINS, auto_position_bins, binned_sizes, position_grid
from .position_split import star_slope_split
from .catalogue import split_shifts
from .nuisances import SCALE, SPLIT
from .odd_moments import star_skewness
from .spot_model import FLUX_SCALE, SpotForwardModel, flux_of_peak
from .star_residual import STACK_HALF_SIZE, stacked_star_residual
from .tables import CorrelationTable, LinearityTable, Observables, PTCTable, interleaved

__all__ = ["matched_profile", "observables_from_sizes", "observables_from_images",
           "flat_observables", "ptc_observable", "lamp_error_floor", "bf_scale_error",
           "FLUX_SCALE"]


def matched_profile(sigma_x, sigma_y, *, beta=None, measure="moments", pixel=True):
    """A GalSim profile whose measured size (pixelised, as measured) is (sigma_x, sigma_y).

    Parameters
    ----------
    sigma_x, sigma_y : float
        Target widths, pixels (the zero-flux intercepts of the data).
    beta : float, optional
        Moffat index; default a Gaussian.
    measure : {'moments', 'gaussian_fit'}
        How the data measured them; a pixel-integrated Gaussian fit returns the Gaussian's own
        sigma, adaptive moments of pixelised data add the pixel response.
    pixel : bool
        Whether the measurement saw pixelised images (default True).

    Returns
    -------
    galsim.GSObject of unit flux (pixel response not included)
    """
    import galsim

    def build(sx, sy):
        base = galsim.Gaussian(sigma=1.0) if beta is None else galsim.Moffat(beta=beta,
                                                                             half_light_radius=1.0)
        size = galsim.hsm.FindAdaptiveMom(base.drawImage(nx=96, ny=96, scale=0.05,
                                                         method="no_pixel")).moments_sigma * 0.05
        return base.transform(sx / size, 0.0, 0.0, sy / size)

    if measure == "gaussian_fit" and beta is None:
        return build(sigma_x, sigma_y)
    sx, sy = sigma_x, sigma_y
    for _ in range(4):
        profile = build(sx, sy)
        stamp = profile.drawImage(nx=41, ny=41, scale=1.0, method="auto" if pixel else "no_pixel")
        # GalSim's HSM as the reference estimator here (same definition as bfpsf's moments,
        # robust for the small, exactly centred spots of this model-building step)
        mxx, myy = moments_from_hsm(galsim.hsm.FindAdaptiveMom(stamp))[:2]
        sx *= sigma_x / np.sqrt(mxx)
        sy *= sigma_y / np.sqrt(myy)
    return build(sx, sy)


def _intercepts(table):
    """The zero-flux sizes (x, y) of a size table: the intercepts of unweighted lines."""
    return tuple(float(polynomial_fit(table.peak_e, sizes, 1.0, 1)[0][0])
                 for sizes in (table.sigma_x, table.sigma_y))


def observables_from_sizes(sizes, shifts, *, shift_draws=(), area=None, beta=None,
                           measure="moments",
                           phases=3, linearity=None, correlations=None, meta=None, ptc=None,
                           base_psf=None, peak_to_flux=None):
    """Observables for a size table and a set of boundary shifts (the G15 prediction).

    The model spot is ``base_psf``'s P0 when given (a P0 fitted from the stars, as
    ``bfpsf psf`` does), else a GalSim profile matched to the zero-flux intercepts of the sizes
    (`matched_profile`). With ``shift_draws`` (shifts drawn within the calibration's errors),
    the relative errors of the predicted BF amplitude and of its X / Y split
    (`bf_scale_error`) are kept in ``meta['scale_err']`` and ``meta['split_err']``, each
    draw's own in ``meta['draws']``;
    ``peak_to_flux`` relates the table's peaks to fluxes
    (`SpotForwardModel`); ``area`` (the calibrated a, 1/e-) is kept in ``meta['area']`` for
    the ``sum_rule_tail`` candidate.
    """
    sigma_x0, sigma_y0 = _intercepts(sizes)
    profile = matched_profile(sigma_x0, sigma_y0, beta=beta, measure=measure)
    model = SpotForwardModel(profile, shifts, phases=phases, measure=measure, base_psf=base_psf,
                             peak_to_flux=peak_to_flux)
    meta = dict(meta or {})
    if area is not None:
        meta["area"] = np.asarray(area, dtype=float)
    if len(shift_draws):
        meta["scale_err"], meta["split_err"], meta["draws"] = bf_scale_error(
            model, shift_draws, sizes.peak_e)
    return Observables(sizes=sizes, spot_model=model, linearity=linearity,
                       correlations=correlations, meta=meta, ptc=ptc)


def bf_scale_error(spot_model, shift_draws, peaks_e):
    """Errors of the predicted BF slope from the calibration's shift errors: the relative
    error of its amplitude, and the error of its X / Y split in units of `split_shifts`.

    The model spot's size change between the faintest and brightest peak is recomputed with
    each of ``shift_draws`` (shifts drawn within the calibration's errors: its bootstrap
    samples, `Calibration.shift_samples`). The amplitude's error is the rms of the log of its
    ratio to the nominal one on each axis, averaged over X and Y (a split error moves each
    axis too: the wider, conservative prior); the split's, the rms of the log of the X ratio
    over the Y ratio, divided by what a unit split (`split_shifts`) does to that log. The
    size block (`bfpsf.diagnosis.problem`) gives both a nuisance with a Gaussian prior of
    that width: the prediction is no better than its flats. Flats that fix a^N against a^E
    poorly (a new user's 16 pairs of 160^2 E2V flats, a^N / (a^N + a^E) at (0, 0)
    0.42 +- 0.10) predict X against Y no better: its BF-only stars, with the scale alone
    free, had the scale contradicted by axis (0.35 +- 0.07 on X, 0.85 +- 0.09 on Y) and
    `flux_diffusion` named. Also each draw's own scale and split, in the order of
    ``shift_draws`` (`refine_calibration` re-centres the calibration's samples on what the
    stars fixed). (0, 0, {}) with fewer than 3 draws.
    """
    if len(shift_draws) < 3:
        return 0.0, 0.0, {}
    peaks = np.array([np.min(peaks_e), np.max(peaks_e)])

    def increments(shifts=None):
        options = {} if shifts is None else {"shifts": shifts}
        return np.array([np.diff(v)[0] for v in spot_model.sizes(peaks, **options)])

    nominal = increments()
    ratios = np.array([increments(shifts) / nominal for shifts in shift_draws])
    step = 0.1
    moved = increments(split_shifts(spot_model.shifts, step)) / nominal
    per_split = np.log(moved[0] / moved[1]) / step
    logs = np.log(ratios)
    scale, split = np.expm1(logs.mean(axis=1)), (logs[:, 0] - logs[:, 1]) / per_split
    return (float(np.mean(np.std(logs, axis=0, ddof=1))), float(np.std(split, ddof=1)),
            {SCALE.name: scale.tolist(), SPLIT.name: split.tolist()})


def lamp_error_floor(exptime, mean_e, shot_e):
    """Relative error floor of flat means from their scatter (lamp flicker), dimensionless.

    Real lamps vary by about 0.1 % from exposure to exposure, hundreds of times the shot noise
    of a large flat's mean. The floor f is the value that makes the scatter of the means about
    a quadratic in exposure time consistent with sqrt(shot^2 + (f mean)^2) (chi2 / dof = 1);
    0 when the shot noise already explains it. A quadratic, so that a smooth non-linearity
    (which the loop tests) does not enter the floor.
    """
    exptime, mean_e, shot_e = (np.asarray(v, float) for v in (exptime, mean_e, shot_e))
    dof = exptime.size - 3
    if dof < 2:
        return 0.0

    def excess(floor):
        sigma = np.hypot(shot_e, floor * mean_e)
        fit = np.polyval(np.polyfit(exptime, mean_e, 2, w=1.0 / sigma), exptime)
        return float(np.sum(((mean_e - fit) / sigma) ** 2)) / dof - 1.0

    if excess(0.0) <= 0:
        return 0.0
    return float(brentq(excess, 0.0, 1.0, xtol=1e-7))


def flat_observables(calibration):
    """Linearity and correlation tables of a `Calibration` (its per-pair PTC table).

    The correlations are R(dx, dy) = C(dx, dy) / C(0, 0) of each pair BEFORE the pedestal
    subtraction, for lags (1, 0) and (0, 1), with error 1 / sqrt(pixel products). The means'
    errors are the shot noise plus the lamp-flicker floor (`lamp_error_floor`).
    """
    ptc = calibration.ptc
    used = np.asarray(ptc["used"], bool)
    mean = np.asarray(ptc["mean_e"], float)[used]
    exptime = np.asarray(ptc["exptime"], float)[used]
    shot = np.sqrt(np.asarray(ptc["var_e"], float)[used] / np.asarray(ptc["npix"], float)[used])
    floor = lamp_error_floor(exptime, mean, shot)
    linearity = LinearityTable(exptime, mean, np.hypot(shot, floor * mean), error_floor=floor)
    correlations = None
    if calibration.covariances_adu is not None:
        cov = np.asarray(calibration.covariances_adu, float)[used]
        npix = np.asarray(calibration.npix, float)[used]
        lags = ((1, 0), (0, 1))
        r = np.column_stack([cov[:, dy, dx] / cov[:, 0, 0] for dx, dy in lags])
        r_err = np.column_stack([1.0 / np.sqrt(npix[:, dy, dx]) for dx, dy in lags])
        correlations = CorrelationTable(mean, lags, r, r_err)
    return linearity, correlations


def ptc_observable(calibration):
    """PTC residuals of a `Calibration`: variance minus the PTC model with the sum-rule a(0, 0).

    The model is A+19 eq. 20 (`bfpsf.calibration.ptc.full_covariance_model`) with the
    calibrated gain, noise matrix, a and b, and a(0, 0) = -sum of the other a(dx, dy) over the
    full plane of measured lags (each off-axis lag counted 4 times, each on-axis lag twice).
    Errors: shot noise of the variance (`bfpsf.calibration.ptc.covariance_errors`); the error
    of the sum (from a_err, lags independent) is kept apart (``sum_rule_err``): it is common
    to all pairs. Pairs not used by the calibration (above the PTC turnoff) are left out.

    Returns
    -------
    PTCTable
    """
    if calibration.covariances_adu is None or calibration.npix is None:
        msg = "the calibration holds no per-pair covariances: cannot form PTC residuals"
        raise BFPSFInputError(msg)
    used = np.asarray(calibration.ptc["used"], bool)
    gain = float(calibration.gain)
    mean_adu = np.asarray(calibration.ptc["mean_adu"], float)[used]
    cov = np.asarray(calibration.covariances_adu, float)[used]
    npix = np.asarray(calibration.npix, float)[used]
    area = np.array(calibration.a, dtype=float)
    area_err = np.asarray(calibration.a_err, dtype=float)
    weights = np.full(area.shape, 4.0)
    weights[0, :] = 2.0
    weights[:, 0] = 2.0
    weights[0, 0] = 0.0
    area[0, 0] = -np.sum(weights * area)
    sum_rule_err = float(np.sqrt(np.sum((weights * area_err) ** 2)))
    c = area * np.asarray(calibration.b, dtype=float)
    noise = np.asarray(calibration.noise_matrix_e2, dtype=float)

    def variance(mean):
        return full_covariance_model(mean, area, c, noise, gain)[:, 0, 0] * gain ** 2

    mean_e = mean_adu * gain
    model = variance(mean_adu)
    step = 1e-4 * mean_adu
    slope = (variance(mean_adu + step) - variance(mean_adu - step)) / (2 * step * gain)
    var_e = cov[:, 0, 0] * gain ** 2
    shot = covariance_errors(cov, npix)[:, 0, 0] * gain ** 2
    return PTCTable(mean_e, var_e, shot, model, slope, sum_rule_err=sum_rule_err)



def observables_from_images(flats, images, *, beta=None, maxlag="auto", n_bins=None, gain=None,
                            calibration=None, fit_b="off-origin", amp=None,
                            holdout_fraction=0.5, n_monte_carlo=30, background=None,
                            progress=False, position_bins="auto", saturation=None,
                            edge=None):
    """Observables from flat-field FITS and spot / star images (ADU, bias subtracted).

    The flats are calibrated (`bfpsf.calibrate`, with ``n_monte_carlo`` bootstrap samples of
    the shifts), the sources of every image measured (`bfpsf.measure.sources.measure_sources`,
    unflagged sources only) and their sizes averaged in ``n_bins`` quantile bins of flux (None:
    10, or as many as the default position grid leaves, `bfpsf.diagnosis.binning.auto_position_bins`) for
    each image (rows labelled by exposure, for the held-out split). ``fit_b`` is passed to
    `bfpsf.calibrate` (its default, 'off-origin', as ``bfpsf calibrate``; False for a few
    small flats, whose b term is unconstrained). The loop
    works on one amplifier: ``amp`` names it in multi-amplifier files (flats and images are
    read by `bfpsf.io.amplifiers`). ``background`` is the images' sky level, ADU per pixel
    (default: the sky surface of each image, `bfpsf.measure.sky.estimate_sky`).
    ``saturation`` is the images' saturation level, ADU (default the header's SATURATE or a variant; the calibration's
    turnoff where lower): saturated stars are flagged and not used. ``position_bins`` N > 1
    also splits the bins by the stars' column (`bfpsf.diagnosis.binning.binned_sizes`): the residual's dependence on
    the distance from the amplifier, each row then carrying its stars' mean column
    (``x_detector``); (N, M) splits them in N ranges of column and M of row (``y_detector``,
    the parallel transfers); ``'auto'`` (default) is
    `bfpsf.diagnosis.binning.AUTO_POSITION_GRID` where every exposure has the stars for it
    (`bfpsf.diagnosis.binning.auto_position_bins`), else 1, said in
    ``meta['position_bins']``. Every
    row carries the stars' mean skewness (`bfpsf.diagnosis.odd_moments.star_skewness`), the
    odd part of the residual. ``edge`` is the border of the flats left out of their statistics
    (default that of `bfpsf.calibrate`).

    The model spot is the P0 that ``bfpsf psf`` would fit (`bfpsf.model.psf_fit.fit_psf`, its
    defaults, the calibrated shifts) from the isolated stars of the exposures the loop fits
    (all but the held-out ones of a ``holdout_fraction`` split, or all for 0): what the loop
    finds is then what P(F) needs, and the held-out exposures stay unseen. The model is
    evaluated at the stars' measured fluxes (`flux_of_peak`), aperture-corrected to total
    fluxes with P0 (`bfpsf.measure.sources.aperture_fraction`), as ``bfpsf slope --psf``
    evaluates P(F). ``beta`` shapes the
    GalSim profile that only gives the exact boundary density (a Moffat, or a Gaussian).

    Also formed: the PTC residuals (`ptc_observable`, a fitted observable), the relative error
    of the predicted BF amplitude from the calibration's shift samples (``meta['scale_err']``)
    and the stacked residual of the stars against that P(F) (`stacked_star_residual`, in
    ``meta['star_residual']``, with the stacked image in ``meta['residual_images']``).
    """
    cal = calibration or calibrate(list(flats), maxlag=maxlag, n_monte_carlo=n_monte_carlo,
                                   fit_b=fit_b, amps=amp, edge=edge)
    if not isinstance(cal, Calibration):
        msg = (f"the flats hold {len(cal)} amplifiers ({', '.join(cal.names)}); the closed loop "
               "works on one: choose it with --amp NAME")
        raise BFPSFInputError(msg, cal.names)
    if cal.shifts is None:
        reason = cal.parameters.get("shifts_failure", "not solved")
        msg = f"the calibration has no boundary shifts ({reason})"
        raise BFPSFInputError(msg)
    gain = cal.gain if gain is None else gain

    fluxes, peaks, sigma_x, sigma_y, exposure = [], [], [], [], []
    columns, rows, skews = [], [], []
    pixels, tables, sky_noise, levels, skies = [], [], [], [], []
    for index, path in enumerate(images):
        amplifiers = read_amplifiers(path, amp, what="image")
        if len(amplifiers) > 1:
            msg = (f"{path} holds {len(amplifiers)} amplifiers; the closed loop works on one: "
                   "choose it with --amp NAME")
            raise BFPSFInputError(msg, str(path))
        # the image preparation and sky of every command (bfpsf.measure.prepare.prepare_image)
        prepared = prepare_image(amplifiers[0].data, gain=gain, background_e=(
            None if background is None else float(background) * gain))
        data = prepared.image_e
        # saturated spots (header SATURATE, calibration turnoff) are flagged, not used
        level = saturation_e(amplifiers[0], gain, saturation, cal)
        table = measure_sources(data, saturation=level)
        # the P0 fit below works on the sky-subtracted pixels: the level under the highest sky
        levels.append(None if level is None else level - float(prepared.sky.image().max()))
        pixels.append(prepared.sky_subtracted)
        skies.append(max(prepared.sky.level, 0.0))
        sky_noise.append(prepared.sky.rms if background is None else sky_level(data)[1])
        tables.append(table)
        good = np.asarray(table["flags"]) == 0
        fluxes.append(np.asarray(table["flux_e"], float)[good])
        peaks.append(np.asarray(table["peak_e"], float)[good])
        sigma_x.append(np.asarray(table["sigma_x"], float)[good])
        sigma_y.append(np.asarray(table["sigma_y"], float)[good])
        exposure.append(np.full(good.sum(), index))
        columns.append(np.asarray(table["x"], float)[good])
        rows.append(np.asarray(table["y"], float)[good])
        # the odd moments and the cross moment e2 (measure_sources' column) of each star
        skews.append(np.column_stack([np.array(star_skewness(
            prepared.sky_subtracted, table[good])).T.reshape(-1, 2),
            np.asarray(table["e2"], float)[good]]))
    fluxes, peaks, sigma_x, sigma_y, exposure, columns, rows, skews = (
        np.concatenate(v) for v in (fluxes, peaks, sigma_x, sigma_y, exposure, columns, rows,
                                    skews))
    # the stars `bfpsf slope` fits (`fit_bf_slope`'s clipping on each axis, an intercept per
    # exposure): in a new user's crowded field a tenth of the clean stars were unresolved
    # blends, 10-230 % larger, and the size bins' slope errors were 90 times `slope`'s
    kept = np.ones(fluxes.size, dtype=bool)
    if fluxes.size >= 9:
        for values in (sigma_x, sigma_y):
            try:
                kept &= fit_bf_slope(peaks, values, group=exposure).rows
            except BFPSFValueError:  # no range of peaks: nothing to clip against
                pass
    fluxes, peaks, sigma_x, sigma_y, exposure, columns, rows, skews = (
        values[kept] for values in (fluxes, peaks, sigma_x, sigma_y, exposure, columns, rows,
                                    skews))
    if fluxes.size < 9:  # the size bins need 3 of 3 stars; no quantile of nothing
        msg = (f"{', '.join(map(str, images))}: {fluxes.size} clean star(s), too few to "
               "diagnose (9 or more)")
        raise BFPSFInputError(msg, fluxes.size)
    # every star's BF slope against its column and row: a test that needs no grid
    split = star_slope_split(peaks, sigma_x, sigma_y, exposure, columns, rows)
    chosen = None
    if isinstance(position_bins, str):
        if position_bins != "auto":
            msg = f"position_bins must be an int, (columns, rows) or 'auto', got {position_bins!r}"
            raise BFPSFValueError(msg, position_bins)
        position_bins, n_bins, chosen = auto_position_bins(
            np.bincount(exposure)[np.unique(exposure)], n_bins, split)
    elif n_bins is None:
        n_bins = DEFAULT_BINS
    cells = int(np.prod(position_grid(position_bins)))
    if n_bins * cells > fluxes.size:  # more bins than stars; before they allocate
        msg = (f"{', '.join(map(str, images))}: {fluxes.size} clean stars cannot fill "
               f"{n_bins} peak bins x {cells} position bin(s) of 3 or more stars; "
               f"give --bins N --position-bins M (n_bins, position_bins) with N x M <= "
               f"{max(fluxes.size // 3, 1)}")
        raise BFPSFInputError(msg, n_bins)
    # (one position range: the bins' mean columns or rows would differ by chance only)
    sizes = binned_sizes(fluxes, peaks, sigma_x, sigma_y, exposure, n_bins,
                          f"{len(images)} images", x=columns, y=rows, skew=skews.T,
                          position_bins=position_bins)
    # P0 from the exposures the loop fits (`bfpsf.diagnosis.loop.split_observables`)
    fitted = np.unique(sizes.exposure)
    if holdout_fraction and fitted.size >= 2:
        fitted = fitted[~interleaved(fitted.size, holdout_fraction)]
    # saturated spots (header, calibration turnoff) are left out of P0 as in `bfpsf psf`;
    # every other source is modelled alongside the stars, as `bfpsf psf` does (in a crowded
    # field a new user's P0 fitted without them did not converge: star residual chi2 6e4)
    found = [isolated_stars(image, DEFAULT_SIZE, saturation_e=level)
             for image, level in zip(pixels, levels)]

    def fit_p0(indices, progress=False):
        return fit_psf([pixels[index] for index in indices],
                       [found[index][0] for index in indices], cal.shifts,
                       read_noise=float(cal.noise_e), sky_e=[skies[index] for index in indices],
                       flux_unit="electron", gain=float(gain),
                       progress=progress, neighbours=[found[index][2] for index in indices])

    n_fitted = sum(len(found[index][0]) for index in fitted)
    if n_fitted < 10:
        msg = f"only {n_fitted} isolated stars in the fitted exposures: too few to fit P0"
        raise BFPSFInputError(msg)
    fit = fit_p0(fitted, progress)
    psf = fit.psf
    # the model's flux is the total flux: the aperture fluxes miss the PSF's wings
    fraction = aperture_fraction(psf)
    total = fluxes / fraction
    linearity, correlations = flat_observables(cal)
    meta = {"flats": len(list(flats)), "images": len(list(images)), "gain": float(gain),
            "n_sources": int(peaks.size), "n_clipped": int(np.sum(~kept)), "calibration": cal,
            "image_paths": [str(path) for path in images],
            "p0_exposures": [int(index) for index in fitted],
            "p0_stars": int(np.sum(fit.stars["flags"] == 0)),
            "p0_converged": bool(fit.converged), "aperture_fraction": fraction,
            "position_bins": chosen or "x".join(map(str, position_grid(position_bins))),
            "position_split": split,
            # the columns and rows the stars span (an EMPIRICAL term's field; the size bins'
            # mean positions span a fraction of it)
            "star_extent": ((float(columns.min()), float(columns.max())),
                            (float(rows.min()), float(rows.max())))}
    try:
        ptc = ptc_observable(cal)
    except (BFPSFInputError, BFPSFValueError) as error:
        # e.g. a calibration read from a file without per-pair covariances: said, not hidden
        ptc = None
        meta["ptc_unavailable"] = str(error)
    observables = observables_from_sizes(sizes, cal.shifts, area=cal.a,
                                         shift_draws=cal.shift_samples(), beta=beta,
                                         linearity=linearity, correlations=correlations,
                                         meta=meta, ptc=ptc, base_psf=psf,
                                         peak_to_flux=flux_of_peak(peaks, total))
    # sky-subtracted images; the noise per pixel is the sky's (read noise included); each
    # exposure against its own P0 (its seeing: one P0 for a night whose seeing changed by 3 %
    # left a null's stars at chi2 12 per pixel), the loop's P0 where too few stars
    own = {index: fit_p0([index]) for index in range(len(pixels)) if len(found[index][0]) >= 10}
    models = [own[index].psf if index in own else psf for index in range(len(pixels))]
    # (in the observables' meta: ``meta`` was copied into them above)
    observables.meta["star_residual_p0"] = (
        "per exposure" if all(model is not psf for model in models)
        else "per exposure where 10 isolated stars or more")
    # said beside the chi2: `p0_converged` is the loop's own P0 (a new user took a warning of
    # one exposure's fit for it)
    observables.meta["star_residual_p0_not_converged"] = [
        int(index) for index, fit in own.items() if not fit.converged]
    star = stacked_star_residual(pixels, tables, models,
                                 half_size=min(psf.half_size, STACK_HALF_SIZE),
                                 noise_e=float(np.median(sky_noise)))
    if star is not None:
        observables.meta["star_residual"] = star
        observables.meta["residual_images"] = {"stars - P(F), stacked / F": star["image"]}
    return observables
