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

from pathlib import Path

import numpy as np

from ..measure.slopes import fit_bf_slope

__all__ = ["write_field", "piff_config", "residual_slopes", "inner_psf_config"]


def write_field(directory, *, n_exposures=4, sensor="lsst_itl_50_8", gain=1.5,
                read_noise_e=5.0, seed=0, shape=(400, 400), spacing=40,
                peak_range_e=(3e3, 1.2e5)):
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

    Returns
    -------
    list of (Path, Path)
        Image and catalogue of each exposure (catalogue columns ``x``, ``y``: 1-based image
        coordinates, as Piff reads FITS images; ``flux_e``, ``peak_e``, ``fwhm``, ``e1``).
    """
    from astropy.table import Table

    from ..validation.simulate_spots import simulate_varying_exposures, write_image_adu

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    images, _, truth = simulate_varying_exposures(
        n_exposures=n_exposures, shape=shape, spacing=spacing, sensor=sensor,
        peak_range_e=peak_range_e, seed=seed, bf_free_twin=False)
    noise = np.random.default_rng(seed + 1)
    files = []
    for index, image in enumerate(images):
        image = image + noise.normal(0.0, read_noise_e, image.shape)
        image_path = directory / f"exposure_{index}.fits"
        catalog_path = directory / f"stars_{index}.fits"
        write_image_adu(image_path, image, gain=gain, overwrite=True)
        rows = truth[truth["image"] == index]
        catalog = Table({"x": np.asarray(rows["x"]) + 1.0, "y": np.asarray(rows["y"]) + 1.0,
                         "flux_e": rows["flux_e"], "peak_e": rows["peak_e"],
                         "fwhm": rows["fwhm"], "e1": rows["e1"]})
        catalog.write(catalog_path, overwrite=True)
        files.append((image_path, catalog_path))
    return files


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
        total flux; ``flux_e``, ``size_residual``, ``e1_residual``, ``exposure`` (arrays).
    """
    import piff

    fluxes, size_residual, e1_residual, exposure = [], [], [], []
    for index, psf in enumerate(fits):
        stars = [star for star in psf.stars if not star.is_flagged]
        _, data, model = piff.Stats().measureShapes(psf, stars)
        good = (data[:, 6] == 0) & (model[:, 6] == 0)
        fluxes.append(np.array([star.fit.flux for star in stars])[good] * gain)
        size_residual.append((data[good, 3] - model[good, 3]) / model[good, 3])
        e1_residual.append(_e1(data[good]) - _e1(model[good]))
        exposure.append(np.full(np.count_nonzero(good), index))
    result = {"flux_e": np.concatenate(fluxes), "size_residual": np.concatenate(size_residual),
              "e1_residual": np.concatenate(e1_residual), "exposure": np.concatenate(exposure)}
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
    import time

    import piff

    psf = inner_psf_config() if psf is None else psf
    start = time.process_time()
    fits = [piff.process(piff_config(image, catalog, psf=psf, gain=gain, calib=calib))
            for image, catalog in files]
    return fits, time.process_time() - start


def acceptance(files, calib, *, gain=1.5):
    """Plain Piff and BrighterFatter around it on the same exposures, side by side.

    Returns
    -------
    dict
        ``plain`` and ``bf``: the `residual_slopes` dicts, each with ``seconds`` (CPU time of
        its fits) and ``fits``; ``size_ratio`` and ``e1_ratio``: BF slope / plain slope;
        ``time_ratio``: BF fit time / plain fit time.
    """
    result = {}
    for kind, calibration in (("plain", None), ("bf", calib)):
        fits, seconds = fit_exposures(files, calib=calibration, gain=gain)
        result[kind] = residual_slopes(fits, gain=gain)
        result[kind].update(seconds=seconds, fits=fits)
    for key in ("size", "e1"):
        result[f"{key}_ratio"] = result["bf"][key].slope / result["plain"][key].slope
    result["time_ratio"] = result["bf"]["seconds"] / result["plain"]["seconds"]
    return result
