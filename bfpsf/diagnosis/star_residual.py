"""The stacked, flux-normalised residual of the stars against P(F) (a fixed diagnostic)."""

import numpy as np

from ..io.amplifiers import read_amplifiers
from ..io.saturation import saturation_e
from ..measure.prepare import linearity_of, prepare_image
from ..measure.sources import measure_sources, sky_level
from ..model.bf_term import pixelised_stamp
from ..plotting.diagnose import radial_profile
from ..workflow import psf_from_images

__all__ = ["stacked_star_residual", "star_residual_with"]

#: Half size of the stacked stamps (or the PSF's, if smaller), pixels.
STACK_HALF_SIZE = 7


def stacked_star_residual(images, tables, psf, *, half_size=None, noise_e=0.0, min_peak_e=0.0):
    """Stacked, flux-normalised residual of stars against the flux-dependent PSF P(F).

    For each star (row of a `bfpsf.measure.sources.measure_sources` table, unflagged, peak
    above ``min_peak_e``): the model ``psf.star_image(F)`` (`FluxDependentPSF.star_image`, the
    code `bfpsf.validation.validate` stacks) at the star's sub-pixel phase, F refitted once
    by linear least squares on the stamp; the residual (data - model) / F is averaged over
    stars. Its expected variance per pixel, sum (model + noise_e^2) / F^2 / N^2 (Poisson and
    read noise), gives a chi2 per pixel: about 1 when P(F) describes the stars.

    Parameters
    ----------
    images : sequence of ndarray [y, x]
        Images, e- (background subtracted).
    tables : sequence of astropy Table
        Source tables of the images (``x``, ``y``, ``flux_e``, ``peak_e``, ``flags``).
    psf : bfpsf.model.psf.FluxDependentPSF or sequence of them
        In e- (``gain=1``); a sequence holds one model per image (each exposure's own P0:
        its seeing).
    half_size : int, optional
        Stamps are 2 half_size + 1 pixels square; default the PSF's half size.
    noise_e : float
        Read noise (and sky), e- rms per pixel.
    min_peak_e : float
        Only stars brighter than this enter the stack.

    Returns
    -------
    dict or None (no star)
        ``image`` (stacked residual, fraction of the unit-flux star per pixel), ``sigma``
        (its expected noise), ``model_peak`` (peak of the unit-flux model), ``rms_over_peak``
        (rms of the stack / model peak), ``chi2_per_pixel``, ``stars_chi2_per_pixel`` (each
        star's own chi2 per pixel, its flux and position refitted, averaged over the stars:
        what the stack's mean leaves out, a shape of P(F) that fits the faint stars and not
        the bright ones), ``n_stars``,
        ``radius`` and
        ``profile`` (azimuthal mean in rings of 0.5 px, `bfpsf.plotting.diagnose`).
    """
    models = list(psf) if isinstance(psf, (list, tuple)) else [psf] * len(images)
    half = int(models[0].half_size if half_size is None else half_size)
    total, variance, model_sum, count, own = 0.0, 0.0, 0.0, 0, 0.0
    for image, table, psf in zip(images, tables, models):
        image = np.asarray(image, float)
        ny, nx = image.shape
        good = (np.asarray(table["flags"]) == 0) & (np.asarray(table["peak_e"]) > min_peak_e)
        for row in np.flatnonzero(good):
            x, y = float(table["x"][row]), float(table["y"][row])
            cx, cy = int(np.round(x)), int(np.round(y))
            if cx - half < 0 or cy - half < 0 or cx + half >= nx or cy + half >= ny:
                continue        # too close to the edge for a full stamp
            data = image[cy - half:cy + half + 1, cx - half:cx + half + 1]
            flux = float(table["flux_e"][row])
            # at its position: an EMPIRICAL term may change over the detector
            model = psf.star_image(flux, x, y, x_phase=x - cx, y_phase=y - cy, half_size=half)
            flux *= float(np.sum(data * model) / np.sum(model * model))
            model = psf.star_image(flux, x, y, x_phase=x - cx, y_phase=y - cy, half_size=half)
            total = total + (data - model) / flux
            own += _own_chi2(psf, data, model, flux, x, y, cx, cy, half, noise_e)
            variance = variance + (np.clip(model, 0, None) + noise_e ** 2) / flux ** 2
            model_sum = model_sum + model / flux
            count += 1
    if count == 0:
        return None
    stack = total / count
    sigma = np.sqrt(variance) / count
    peak = float(np.max(model_sum / count))
    radius, profile = radial_profile(stack)
    return {"image": stack, "sigma": sigma, "model_peak": peak,
            "rms_over_peak": float(np.std(stack) / peak),
            "chi2_per_pixel": float(np.mean((stack / sigma) ** 2)), "n_stars": count,
            "stars_chi2_per_pixel": own / count,
            "radius": radius, "profile": profile}


def _own_chi2(psf, data, image, flux, x, y, cx, cy, half, noise_e, step=0.05):
    """A star's chi2 per pixel against P(F) with its flux and position refitted (two
    weighted Gauss-Newton steps from ``image``, the model at ``flux``, ``x``, ``y``): a
    position left as detection measured it put a dipole in every bright star that a blurring
    pattern kind partly hid (the bench's transfer to the neighbours lost, 1.00 against 0.95,
    to a broad kind)."""
    def model(flux, x, y):
        return psf.star_image(flux, x, y, x_phase=x - cx, y_phase=y - cy, half_size=half)

    # the position's derivatives from P0 at the star (F p; the BF term and an EMPIRICAL
    # term move it by a few %, the step's direction only, while the chi2 is the full
    # model's): a third of the cost, where each P(F) recomputes the term's pattern
    local = psf.at(x, y)

    def unit(x, y):
        return pixelised_stamp(local, x_phase=x - cx, y_phase=y - cy, half_size=half)

    for _ in range(2):
        weight = 1.0 / (np.clip(image, 0, None) + noise_e ** 2)
        centre = unit(x, y)
        design = np.stack([image / flux, flux * (unit(x + step, y) - centre) / step,
                           flux * (unit(x, y + step) - centre) / step]).reshape(3, -1)
        normal = (design * weight.ravel()) @ design.T
        change = np.linalg.lstsq(normal, (design * weight.ravel()) @ (data - image).ravel(),
                                 rcond=None)[0]
        if not np.all(np.isfinite(change)) or np.any(np.abs(change[1:]) > 1.0):
            break  # a failed step: the chi2 at the last position
        flux, x, y = flux + change[0], x + change[1], y + change[2]
        image = model(flux, x, y)
    return float(np.mean((data - image) ** 2 / (np.clip(image, 0, None) + noise_e ** 2)))


def star_residual_with(calibration, paths, exposures, *, amp=None, background=None,
                       saturation=None, cache=None, same_sky=False):
    """The stacked star residual of some exposures against the P(F) a calibration gives them
    through the user's path: each image prepared (`prepare_image`, with a refined
    calibration's linearity correction) and its own P0 fitted with the calibration
    (`bfpsf.workflow.psf_from_images`: its build-up and EMPIRICAL term included, at the
    exposure's order in ``paths``), as ``bfpsf psf`` would on that image alone.

    ``bfpsf diagnose --output-calib`` calls it on the held-out exposures with the flats'
    calibration and with each refined one: the same stars and the same path, so the chi2
    compare (the stack of every exposure, `stacked_star_residual` in the observables, uses
    the loop's own P0 fit).

    Parameters
    ----------
    calibration : bfpsf.calibration.product.Calibration
    paths : sequence of str
        Every image given to diagnose, in its order.
    exposures : sequence of int
        Indices into ``paths`` of the exposures to stack.
    amp, background, saturation
        As ``bfpsf diagnose``: the amplifier, a known sky (ADU) and a saturation level (ADU).
    cache : dict, optional
        Kept between calls on the same images: each image as read, prepared and detected
        for a gain and linearity correction (calibrations that share them share these), the
        sky that its last fit with ``same_sky`` False found, and the stars found on it.
    same_sky : bool, optional
        Each image with the sky (and the wings' glow) of the last fit of it in ``cache``, if
        any, and one P0 fit (`psf_from_images`' ``refit_sky``): a third of the fits, for comparing
        calibrations on one sky. Default False, the user's path.

    Returns
    -------
    dict or None
        `stacked_star_residual`'s, with ``exposures``.
    """
    gain = float(calibration.gain)
    linearity = linearity_of(calibration)
    cache = {} if cache is None else cache
    pixels, tables, models, noise = [], [], [], []
    for index in exposures:
        key = (str(paths[index]), amp, gain, linearity, background)
        if key not in cache:
            amplifier = read_amplifiers(paths[index], amp, what="image")[0]
            prepared = prepare_image(amplifier.data, gain=gain, linearity_c_per_1e5=linearity,
                                     background_e=None if background is None
                                     else background * gain)
            cache[key] = (amplifier, prepared, {}, {}, {})
        amplifier, prepared, sources, fitted_sky, found = cache[key]
        level = saturation_e(amplifier, gain, saturation, calibration)
        # (a calibration of another gain or linearity has no fit of its own yet: the path)
        sky = fitted_sky.get(level) if same_sky else None
        prepared = prepared if sky is None else sky
        fit = psf_from_images([prepared], calibration, saturation_e=level, exposure=index,
                              refit_sky=sky is None,
                              detections=None if sky is None else found.get(level))
        if sky is None:
            fitted_sky[level] = fit.prepared[0]
        else:  # the stars on that sky, for the next calibration compared on it
            found[level] = fit.detections
        # the stars on the sky (and less the glow) P0 was fitted on
        pixels.append(fit.prepared[0].sky_subtracted)
        if level not in sources:
            sources[level] = measure_sources(prepared.image_e, saturation=level)
        tables.append(sources[level])
        models.append(fit.psf)
        noise.append(prepared.sky.rms if background is None else sky_level(prepared.image_e)[1])
    star = stacked_star_residual(pixels, tables, models,
                                 half_size=min(models[0].half_size, STACK_HALF_SIZE),
                                 noise_e=float(np.median(noise)))
    return None if star is None else dict(star, exposures=[int(index) for index in exposures])
