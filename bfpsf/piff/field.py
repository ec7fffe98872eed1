"""The Piff acceptance field: SiliconSensor exposures written as Piff input, Piff configs for
plain and BrighterFatter fits, and the residual slopes of size and e1 against flux.

`write_field` draws `bfpsf.validation.simulate_spots.simulate_varying_exposures` (isolated
Moffat stars through `galsim.SiliconSensor`, FWHM varying with x and e1 with y over each
exposure, log-uniform peaks) and writes each exposure as a FITS image in ADU with a star
catalogue, as a user hands them to ``piffify``. `piff_config` is the config of one exposure;
`residual_slopes` measures data and model shapes with Piff's own `piff.Stats.measureShapes`
(HSM on the star stamps and on the model drawn at each star's fitted flux) and fits
``(T_data - T_model) / T_model`` and ``e1_data - e1_model`` against the flux with
`bfpsf.measure.slopes.fit_bf_slope` (one free intercept per exposure).
"""

import time
from pathlib import Path

import numpy as np
from astropy.table import Table

from ..measure.slopes import fit_bf_slope
from ..model.redistribution import redistribute
from ..moments.adaptive import adaptive_moments
from ..validation.simulate_spots import simulate_varying_exposures, write_image_adu

__all__ = ["write_field", "piff_config", "residual_slopes", "inner_psf_config"]


def write_field(directory, *, n_exposures=4, sensor="lsst_itl_50_8", gain=1.5,
                read_noise_e=5.0, seed=0, shape=(400, 400), spacing=40,
                peak_range_e=(3e3, 1.2e5), control=False):
    """Simulate exposures and write ``exposure_K.fits`` (ADU) and ``stars_K.fits``.

    Parameters
    ----------
    directory : str or path
        Created if needed.
    n_exposures, shape, spacing, peak_range_e, seed
        As `simulate_varying_exposures` (100 stars per 400 x 400 exposure by default).
    sensor : str
        GalSim SiliconSensor name (the sensor the calibration's flats come from).
    gain : float
        e-/ADU of the written images.
    read_noise_e : float
        Gaussian read noise added, e- rms.
    control : bool, optional
        Also write ``control_K.fits``: each exposure drawn again without BF, with the same
        photons, diffusion and noise (SiliconSensor at strength 1e-9, `SpotSet.twin`). Plain
        Piff on them measures what the residual slopes hold without any BF (the noise bias of
        the sizes of faint stars, the fit's own flux dependence). Doubles the run time.

    Returns
    -------
    list of (Path, Path)
        Image and catalogue of each exposure (catalogue columns ``x``, ``y``: 1-based image
        coordinates, as Piff reads FITS images; ``flux_e``, ``peak_e``, ``fwhm``, ``e1``).
        With ``control``, a second list of (control image, catalogue) follows.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    images, twins, truth = simulate_varying_exposures(
        n_exposures=n_exposures, shape=shape, spacing=spacing, sensor=sensor,
        peak_range_e=peak_range_e, seed=seed, bf_free_twin=control)
    noise = np.random.default_rng(seed + 1)
    files, controls = [], []
    for index, image in enumerate(images):
        read_noise = noise.normal(0.0, read_noise_e, image.shape)
        image_path = directory / f"exposure_{index}.fits"
        catalog_path = directory / f"stars_{index}.fits"
        write_image_adu(image_path, image + read_noise, gain=gain, overwrite=True)
        if control:
            controls.append((directory / f"control_{index}.fits", catalog_path))
            write_image_adu(controls[-1][0], twins[index] + read_noise, gain=gain,
                            overwrite=True)
        rows = truth[truth["image"] == index]
        catalog = Table({"x": np.asarray(rows["x"]) + 1.0, "y": np.asarray(rows["y"]) + 1.0,
                         "flux_e": rows["flux_e"], "peak_e": rows["peak_e"],
                         "fwhm": rows["fwhm"], "e1": rows["e1"]})
        catalog.write(catalog_path, overwrite=True)
        files.append((image_path, catalog_path))
    return (files, controls) if control else files


def inner_psf_config(*, size=17, order=1):
    """The plain Piff PSF of the acceptance: PixelGrid (pixel scale 1) and BasisPolynomial."""
    return {"type": "Simple",
            "model": {"type": "PixelGrid", "scale": 1.0, "size": int(size)},
            "interp": {"type": "BasisPolynomial", "order": int(order)},
            "outliers": {"type": "Chisq", "nsigma": 5, "max_remove": 0.05}}


def piff_config(image_path, catalog_path, *, psf, gain=1.5, read_noise_e=5.0, stamp_size=25,
                reserve_frac=0.2, seed=1, calib=None):
    """The Piff config of one exposure: plain ``psf`` or, with ``calib``, BrighterFatter
    around it (``modules: [bfpsf.piff]``).

    ``noise`` is the read-noise variance in ADU^2 and ``gain`` lets Piff add the stars'
    Poisson variance to the weights; ``reserve_frac`` of the stars are reserved.
    """
    config = {
        "input": {"image_file_name": str(image_path), "cat_file_name": str(catalog_path),
                  "x_col": "x", "y_col": "y", "stamp_size": int(stamp_size),
                  "noise": float((read_noise_e / gain) ** 2), "gain": float(gain)},
        "select": {"reserve_frac": float(reserve_frac), "seed": int(seed)},
        "psf": dict(psf),
        "verbose": 0,
    }
    if calib is not None:
        config["modules"] = ["bfpsf.piff"]
        config["psf"] = {"type": "BrighterFatter", "calib": str(calib), "psf": dict(psf)}
    return config


def residual_slopes(fits, *, gain):
    """Slopes of the size and e1 residuals (data minus model) against flux.

    Parameters
    ----------
    fits : list of piff.PSF
        Fitted PSFs, one per exposure (their ``stars``, flagged ones left out, reserve ones
        included).
    gain : float
        e-/ADU, to put the fluxes in electrons.

    Returns
    -------
    dict
        ``size`` and ``e1``: `bfpsf.measure.slopes.SlopeFit` of dT/T and de1 per 100 ke- of
        total flux; ``flux_e``, ``size_residual``, ``e1_residual``, ``exposure``, ``x``,
        ``y`` (arrays, one per star).
    """
    import piff

    fluxes, size_residual, e1_residual, exposure, xs, ys = [], [], [], [], [], []
    for index, psf in enumerate(fits):
        stars = [star for star in psf.stars if not star.is_flagged]
        _, data, model = piff.Stats().measureShapes(psf, stars)
        good = (data[:, 6] == 0) & (model[:, 6] == 0)
        fluxes.append(np.array([star.fit.flux for star in stars])[good] * gain)
        size_residual.append((data[good, 3] - model[good, 3]) / model[good, 3])
        e1_residual.append(_e1(data[good]) - _e1(model[good]))
        exposure.append(np.full(np.count_nonzero(good), index))
        xs.append(np.array([star.image_pos.x for star in stars])[good])
        ys.append(np.array([star.image_pos.y for star in stars])[good])
    result = {"flux_e": np.concatenate(fluxes), "size_residual": np.concatenate(size_residual),
              "e1_residual": np.concatenate(e1_residual), "exposure": np.concatenate(exposure),
              "x": np.concatenate(xs), "y": np.concatenate(ys)}
    result["size"] = fit_bf_slope(result["flux_e"], result["size_residual"],
                                  group=result["exposure"])
    result["e1"] = fit_bf_slope(result["flux_e"], result["e1_residual"],
                                group=result["exposure"])
    return result


def _e1(shapes):
    """e1 = (Mxx - Myy) / (Mxx + Myy) from the reduced shear (g1, g2) of measureShapes."""
    g1, g2 = shapes[:, 4], shapes[:, 5]
    return 2.0 * g1 / (1.0 + g1**2 + g2**2)


def fit_exposures(files, *, calib=None, gain=1.5, psf=None):
    """Fit each exposure with Piff (``piff.process`` of `piff_config`).

    Returns
    -------
    fits : list of piff.PSF
    seconds : float
        CPU time of the fits (process time: the machine may be shared).
    """
    import piff

    psf = inner_psf_config() if psf is None else psf
    start = time.process_time()
    fits = [piff.process(piff_config(image, catalog, psf=psf, gain=gain, calib=calib))
            for image, catalog in files]
    return fits, time.process_time() - start


def acceptance(files, calib, *, gain=1.5, controls=None):
    """Plain Piff and BrighterFatter around it on the same exposures, side by side.

    Parameters
    ----------
    files : list of (Path, Path)
        Exposures and catalogues (`write_field`).
    calib : str or path
        The calibration of BrighterFatter.
    controls : list of (Path, Path), optional
        The same exposures without BF (`write_field` with ``control=True``), fitted with plain
        Piff: the slopes that are there without BF are subtracted from both before the ratios
        (``control``), so that they compare the BF part of the slopes.

    Returns
    -------
    dict
        ``plain``, ``bf`` (and ``control``): the `residual_slopes` dicts, each with
        ``seconds`` (CPU time of its fits) and ``fits``; ``size_plain``, ``size_left``,
        ``e1_plain``, ``e1_left``: the slopes of plain Piff and of BrighterFatter (`SlopeFit`;
        with ``controls``, of each star's residual minus its control's); ``size_ratio``,
        ``e1_ratio``: left / plain, with ``size_ratio_err``, ``e1_ratio_err`` (the left
        slope's error over plain's slope); ``time_ratio``: BF fit time / plain fit time.
    """
    result = {}
    runs = [("plain", files, None), ("bf", files, calib)]
    if controls is not None:
        runs.append(("control", controls, None))
    for kind, exposures, calibration in runs:
        fits, seconds = fit_exposures(exposures, calib=calibration, gain=gain)
        result[kind] = residual_slopes(fits, gain=gain)
        result[kind].update(seconds=seconds, fits=fits)
    for key in ("size", "e1"):
        plain, left = result["plain"][key], result["bf"][key]
        if controls is not None:  # star by star: the noise common to both cancels
            plain = _slope_of_difference(result["plain"], result["control"], key)
            left = _slope_of_difference(result["bf"], result["control"], key)
        result[f"{key}_plain"], result[f"{key}_left"] = plain, left
        result[f"{key}_ratio"] = left.slope / plain.slope
        result[f"{key}_ratio_err"] = left.slope_err / abs(plain.slope)
    result["time_ratio"] = result["bf"]["seconds"] / result["plain"]["seconds"]
    return result


def _slope_of_difference(bf, control, key):
    """Slope of (BF residual - control residual) per star, over the stars both kept (same
    exposure and position): the noise common to an exposure and its BF-free twin cancels."""
    pairs = []
    for index, (group, x, y) in enumerate(zip(bf["exposure"], bf["x"], bf["y"])):
        same = np.flatnonzero((control["exposure"] == group)
                              & (np.hypot(control["x"] - x, control["y"] - y) < 0.5))
        if same.size:
            pairs.append((index, same[0]))
    pairs = np.array(pairs, dtype=int).reshape(-1, 2)
    difference = (bf[f"{key}_residual"][pairs[:, 0]]
                  - control[f"{key}_residual"][pairs[:, 1]])
    return fit_bf_slope(bf["flux_e"][pairs[:, 0]], difference,
                        group=bf["exposure"][pairs[:, 0]])


def carried_errors(calibration, *, fwhm=3.45, beta=3.5, flux_e=2e6, diffusion=0.0):
    """The calibration's own error on the BF change of a star's size and e1, relative.

    The change of T and e1 between a faint star and one of ``flux_e`` electrons (Moffat of
    ``fwhm``, convolved with a Gaussian charge ``diffusion`` sigma, redistributed with G15's
    operator) predicted with each of the calibration's shift samples: their standard deviation
    over the prediction with its shifts.

    Returns
    -------
    dict
        ``size`` and ``e1``: relative errors of the predicted changes (NaN without samples).
    """
    import galsim

    profile = galsim.Moffat(beta=beta, fwhm=fwhm)
    if diffusion > 0:
        profile = galsim.Convolve(profile, galsim.Gaussian(sigma=diffusion))
    unit = profile.drawImage(nx=33, ny=33, scale=1.0).array

    def change(shifts):
        faint = adaptive_moments(unit)
        bright = adaptive_moments(redistribute(flux_e * unit, shifts))
        size = (bright.mxx + bright.myy) / (faint.mxx + faint.myy) - 1
        e1 = ((bright.mxx - bright.myy) / (bright.mxx + bright.myy)
              - (faint.mxx - faint.myy) / (faint.mxx + faint.myy))
        return np.array([size, e1])

    samples = [change(shifts) for shifts in calibration.shift_samples()]
    if len(samples) < 2:
        return {"size": float("nan"), "e1": float("nan")}
    spread = np.std(samples, axis=0, ddof=1) / np.abs(change(calibration.shifts))
    return {"size": float(spread[0]), "e1": float(spread[1])}
