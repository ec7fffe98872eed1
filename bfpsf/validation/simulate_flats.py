"""Flat-field pairs simulated with GalSim's SiliconSensor: the truth for the calibration.

Photon-shooting a big flat through `galsim.SiliconSensor` takes days, so flats are built the
way GalSim's own tests build them (DESIGN.md, "Flats"): the image is accumulated in ``nsteps``
increments; before each, the pixel areas of the charge collected so far are computed with
``sensor.calculate_pixel_areas`` and Poisson(step * area) electrons are added. A margin of a
few pixels is simulated around the image and cropped, because charge leaks out at the edges
(GalSim shifts boundaries up to 4 pixels from a charge).

GalSim's pixel areas do not tile the plane exactly: on a uniform charge Q every interior pixel's
area is 1 - c Q^2 (c = 7.6e-14 per e-^2 for ``lsst_e2v_50_8``: 5.5e-4 at 85 ke-; 2.2e-14 for
``lsst_itl_50_32``, 1.2e-14 for ``lsst_itl_50_8``, -2.4e-15 for ``lsst_e2v_50_32``), a second-order
term of its polygon areas, while its photon shooting puts every photon into some pixel (a star
drawn through the same sensor keeps its flux to 2e-5 at any flux). Summed over an exposure that
made a flat lose c Q^2 / 3 of its charge (1.8e-4 at 85 ke- on ``lsst_e2v_50_8``), a spurious
quadratic non-linearity that a flicker-free PTC measures at 9 sigma. Each step's areas are
therefore divided by the interior area of a uniform charge at the image's mean: the flats
conserve charge, as the sensor's stars do, and their covariances are unchanged (the factor is
the same for every pixel).

The areas of step k are evaluated at the middle of the step (the charge so far scaled by
(k + 1/2) / k), a midpoint rule: evaluating them at the start of each step under-estimates the
covariances that build up during the exposure by the fraction 1 / nsteps (5 % for 20 steps),
the midpoint rule by 1 / nsteps**2 (0.25 %).

The lamp may flicker: each exposure's level is the nominal one times (1 + lamp_jitter * N(0, 1)),
as real flat-field lamps scatter by about 0.1 % from exposure to exposure. The charge image
(electrons) is then read out: an optional serial readout correlation and an optional quadratic
non-linearity, both applied to the electrons before the read noise, Gaussian read noise, and
conversion to ADU with the gain.
"""

import logging
from pathlib import Path

import numpy as np
from astropy.io import fits
from tqdm import tqdm

from ..errors import BFPSFFileExistsError, BFPSFValueError, integer_at_least
from ..outputs import write_fits

__all__ = ["simulate_flat", "simulate_flats", "uniform_area", "write_flats", "DEFAULT_LEVELS_E",
           "MAX_LEVEL_E"]

log = logging.getLogger(__name__)

#: Default flat levels, electrons: a PTC from low flux to about 100 ke-.
DEFAULT_LEVELS_E = (5_000.0, 10_000.0, 20_000.0, 35_000.0, 50_000.0, 65_000.0, 80_000.0,
                    100_000.0)

#: Highest flat level, electrons per pixel: ten times a CCD's full well (~1e5 e-). GalSim's
#: SiliconSensor pixel areas diverge beyond a few 1e6 e- (numpy's Poisson then refuses the
#: infinite means: "lam value too large", seen at 1e7 e-).
MAX_LEVEL_E = 1e6

_zero_charge_areas = {}
#: Side of the uniform image whose central pixel gives the area of a uniform charge (GalSim
#: moves boundaries up to 4 pixels from a charge, so the centre of 13 x 13 is interior).
_UNIFORM_SIDE = 13
_UNIFORM_LEVEL = 1e5
_uniform_loss = {}


def _sensor(sensor):
    import galsim

    if isinstance(sensor, str):
        from ..interop.silicon_truth import silicon_sensor  # imports GalSim: only when used

        return silicon_sensor(sensor)
    if not isinstance(sensor, galsim.Sensor):
        msg = f"sensor must be a GalSim sensor name or a galsim.Sensor, got {sensor!r}"
        raise BFPSFValueError(msg, sensor)
    return sensor


def _areas(sensor, image):
    areas = sensor.calculate_pixel_areas(image)
    return areas.array if hasattr(areas, "array") else np.full(image.array.shape, float(areas))


def uniform_area(sensor, charge_e):
    """Area of an interior pixel of a uniform charge ``charge_e`` per pixel, pixels: GalSim's
    `calculate_pixel_areas` is 1 - c Q^2 there (module docstring); c is computed once per
    sensor, from the centre of a uniform image of 1e5 e-."""
    import galsim

    key = repr(sensor)
    if key not in _uniform_loss:
        image = galsim.ImageD(np.full((_UNIFORM_SIDE, _UNIFORM_SIDE), _UNIFORM_LEVEL))
        centre = _areas(sensor, image)[_UNIFORM_SIDE // 2, _UNIFORM_SIDE // 2]
        _uniform_loss[key] = (1.0 - float(centre)) / _UNIFORM_LEVEL**2
    return 1.0 - _uniform_loss[key] * float(charge_e) ** 2


def simulate_flat(sensor, level_e, *, size, nsteps=20, rng, margin=5, midpoint=True):
    """One flat-field charge image collected through a GalSim sensor, electrons.

    Parameters
    ----------
    sensor : galsim.Sensor or str
        The sensor (e.g. ``galsim.SiliconSensor(name='lsst_itl_50_8')``) or its name.
    level_e : float
        Expected charge per pixel of a sensor without brighter-fatter, electrons.
    size : int or (int, int)
        Image shape (ny, nx) after cropping, pixels.
    nsteps : int, optional
        Number of increments; the covariances are under-estimated by about 1 / nsteps**2
        (module docstring). Default 20.
    rng : numpy.random.Generator
        Source of the Poisson draws.
    margin : int, optional
        Pixels simulated around the image and cropped. Default 5 (GalSim moves boundaries up
        to 4 pixels from a charge).
    midpoint : bool, optional
        Evaluate the areas of each step at its middle (default) rather than at its start
        (GalSim's tests), which under-estimates the covariances by 1 / nsteps.

    Returns
    -------
    ndarray, shape (ny, nx)
        Collected electrons per pixel (float64 holding integers).
    """
    import galsim

    sensor = _sensor(sensor)
    ny, nx = (size, size) if np.ndim(size) == 0 else tuple(size)
    if level_e < 0 or not np.isfinite(level_e):
        msg = f"level_e must be a finite charge >= 0 electrons, got {level_e}"
        raise BFPSFValueError(msg, level_e)
    integer_at_least("nsteps", nsteps, 1)
    if min(ny, nx) < 1 or margin < 0:
        msg = f"size must be positive and margin >= 0, got size {size}, margin {margin}"
        raise BFPSFValueError(msg, (size, margin))
    shape = (ny + 2 * margin, nx + 2 * margin)
    charge = np.zeros(shape)
    image = galsim.ImageD(charge.copy())  # GalSim works on its own copy of the pixels
    key = (repr(sensor), shape)
    if key not in _zero_charge_areas:
        _zero_charge_areas[key] = _areas(sensor, image).copy()
    step = float(level_e) / nsteps
    for k in range(int(nsteps)):
        if k == 0:
            areas = _zero_charge_areas[key]
        else:
            scale = (k + 0.5) / k if midpoint else 1.0
            image.array[:] = charge * scale  # charge at the middle (or start) of the step
            interior = charge[margin:margin + ny, margin:margin + nx]
            areas = _areas(sensor, image) / uniform_area(sensor, interior.mean() * scale)
        charge += rng.poisson(step * areas)
    return charge[margin:margin + ny, margin:margin + nx]


def simulate_flats(sensor="lsst_itl_50_8", levels_e=DEFAULT_LEVELS_E, *, pairs=1, size=256,
                   gain=1.5, read_noise_e=5.0, nsteps=20, seed=0, exptime_per_e=1e-3,
                   nonlinearity=0.0, readout_correlation=0.0, hot_columns=(),
                   hot_column_fraction=0.02, defect_clusters=0, defect_excess_sigma=6.0,
                   margin=5, progress=False, lamp_jitter=0.0):
    """Flat-field pairs in ADU from a GalSim SiliconSensor, with known truth.

    Each flat: the charge collected by `simulate_flat`; optional hot columns and defect
    clusters (the same pixels in every flat: they belong to the sensor); an optional serial
    readout correlation ``q[:, i] + c q[:, i - 1]`` (the G15 "pedestal": a correlation
    R(1, 0) ~ c at every flux); an optional quadratic non-linearity
    ``q (1 + nonlinearity * q)``; Gaussian read noise; division by the gain.

    Parameters
    ----------
    sensor : str or galsim.Sensor, optional
        Default ``'lsst_itl_50_8'``.
    levels_e : sequence of float, optional
        Charge levels, electrons per pixel. Default `DEFAULT_LEVELS_E`.
    pairs : int, optional
        Pairs per level. Default 1.
    size : int, optional
        Image side, pixels. Default 256.
    gain : float, optional
        Gain, e-/ADU. Default 1.5.
    read_noise_e : float, optional
        Read noise, electrons rms. Default 5.
    nsteps : int, optional
        Increments per flat (`simulate_flat`). Default 20.
    seed : int, optional
        Seed of every random draw. Default 0.
    exptime_per_e : float, optional
        EXPTIME per electron of level, seconds (EXPTIME = level * exptime_per_e). Default 1e-3.
    nonlinearity : float, optional
        Quadratic non-linearity, 1/e-: signal = q (1 + nonlinearity q). Default 0.
    readout_correlation : float, optional
        Serial readout correlation c (G15 section 4.2.3 pedestal). Default 0.
    hot_columns : sequence of int, optional
        Columns (x, after cropping) with extra charge. Default none.
    hot_column_fraction : float, optional
        Extra mean charge of a hot column, as a fraction of the level. Default 0.02.
    defect_clusters : int, optional
        Number of 3 x 3 defect clusters at random places. Default 0.
    defect_excess_sigma : float, optional
        Extra mean charge of a defect pixel, in units of sqrt(level). Default 6.
    margin : int, optional
        Pixels simulated around each image and cropped. Default 5.
    progress : bool, optional
        Show a tqdm progress bar. Default False.
    lamp_jitter : float, optional
        Relative rms of the lamp level from exposure to exposure (0.001: 0.1 %), the same for
        both flats of a pair only by chance; the header keeps the drawn level (SIMLAMP).
        Default 0.

    Returns
    -------
    list of (ndarray, float, dict)
        For each level and pair, two entries ``(image_adu, exptime_s, header)``; the image is
        float64 [y, x] in ADU; the header holds EXPTIME, BUNIT and the true parameters
        (SIMGAIN, SIMNOISE, SENSOR, SIMLEVEL, SEED, ...).
    """
    levels_e = np.atleast_1d(np.asarray(levels_e, dtype=float))
    _validate(levels_e, pairs, size, gain, read_noise_e, hot_columns)
    _validate_readout(seed, exptime_per_e, nonlinearity, readout_correlation, defect_clusters)
    sensor_object = _sensor(sensor)
    sensor_name = sensor if isinstance(sensor, str) else getattr(sensor, "name", repr(sensor))
    if not (np.isfinite(lamp_jitter) and 0 <= lamp_jitter < 0.5):
        msg = f"lamp_jitter must be a relative rms in [0, 0.5), got {lamp_jitter!r}"
        raise BFPSFValueError(msg, lamp_jitter)
    hot_columns = tuple(int(column) for column in hot_columns)
    master = np.random.default_rng(seed)
    # Sensor features are fixed: draw them from their own stream.
    defect_rng = np.random.default_rng([seed, 1])
    defect_corners = defect_rng.integers(0, size - 2, size=(int(defect_clusters), 2))

    total = len(levels_e) * int(pairs) * 2
    bar = None
    if progress:
        bar = tqdm(total=total * int(nsteps), desc="simulating flats", unit="step")
    outputs = []
    for level in levels_e:
        for pair in range(int(pairs)):
            for member in (1, 2):
                rng = np.random.default_rng(master.integers(2**63))
                lamp = 1.0 + lamp_jitter * rng.standard_normal() if lamp_jitter else 1.0
                # one extra column on the left feeds the readout correlation of column 0
                charge = simulate_flat(sensor_object, level * lamp, size=(size, size + 1),
                                       nsteps=nsteps, rng=rng, margin=margin)
                if bar is not None:
                    bar.update(int(nsteps))
                _add_features(charge[:, 1:], level, hot_columns, hot_column_fraction,
                              defect_corners, defect_excess_sigma, rng)
                if readout_correlation:
                    charge[:, 1:] += readout_correlation * charge[:, :-1]
                charge = charge[:, 1:]
                signal = charge * (1.0 + nonlinearity * charge) if nonlinearity else charge
                signal = signal + rng.normal(0.0, read_noise_e, signal.shape)
                header = {
                    "EXPTIME": float(level * exptime_per_e),
                    "BUNIT": "ADU",
                    "SENSOR": str(sensor_name),
                    "SIMLEVEL": float(level),
                    "SIMGAIN": float(gain),
                    "SIMNOISE": float(read_noise_e),
                    "SIMNSTEP": int(nsteps),
                    "SIMNONLI": float(nonlinearity),
                    "SIMRCORR": float(readout_correlation),
                    "SIMLAMP": float(level * lamp),
                    "SIMHOTC": ",".join(str(column) for column in hot_columns),
                    "SIMNDEF": int(defect_clusters),
                    "SIMPAIR": int(pair),
                    "SIMMEMB": int(member),
                    "SEED": int(seed),
                }
                outputs.append((signal / gain, header["EXPTIME"], header))
    if bar is not None:
        bar.close()
    return outputs


def _validate(levels_e, pairs, size, gain, read_noise_e, hot_columns):
    if levels_e.size == 0 or not np.all((levels_e >= 0) & (levels_e <= MAX_LEVEL_E)):
        msg = (f"the flat levels must be charges from 0 to {MAX_LEVEL_E:.0e} e- (MAX_LEVEL_E), "
               f"got {levels_e.tolist()}")
        raise BFPSFValueError(msg, levels_e)
    integer_at_least("pairs", pairs, 1)
    integer_at_least("size", size, 8, "pixels")
    if not 0 < gain < np.inf:
        msg = f"gain must be positive (e-/ADU), got {gain}"
        raise BFPSFValueError(msg, gain)
    if not 0 <= read_noise_e < np.inf:
        msg = f"read_noise_e must be >= 0 electrons, got {read_noise_e}"
        raise BFPSFValueError(msg, read_noise_e)
    for column in hot_columns:
        if not 0 <= int(column) < size:
            msg = f"hot column {column} is outside the image (0..{size - 1})"
            raise BFPSFValueError(msg, column)


def _validate_readout(seed, exptime_per_e, nonlinearity, readout_correlation,
                      defect_clusters):
    checks = (
        (float(seed).is_integer() and seed >= 0, "seed must be an integer >= 0", seed),
        (0 < exptime_per_e < np.inf, "exptime_per_e must be a positive finite time (s)",
         exptime_per_e),
        (np.isfinite(nonlinearity), "nonlinearity must be finite (1/e-)", nonlinearity),
        (-1 < readout_correlation < 1, "readout_correlation must be a fraction of the previous "
                                       "pixel's charge, -1 < c < 1", readout_correlation),
        (float(defect_clusters).is_integer() and defect_clusters >= 0,
         "defect_clusters must be an integer >= 0", defect_clusters))
    for passes, requirement, value in checks:
        if not passes:
            msg = f"{requirement}, got {value}"
            raise BFPSFValueError(msg, value)


def _add_features(charge, level, hot_columns, hot_column_fraction, defect_corners,
                  defect_excess_sigma, rng):
    """Add hot columns and defect clusters to ``charge`` in place."""
    if hot_columns:
        columns = list(hot_columns)
        charge[:, columns] += rng.poisson(hot_column_fraction * level,
                                          (charge.shape[0], len(columns)))
    for y0, x0 in defect_corners:
        excess = defect_excess_sigma * np.sqrt(max(level, 1.0))
        charge[y0:y0 + 3, x0:x0 + 3] += rng.poisson(excess, (3, 3))


def write_flats(outdir, sensor="lsst_itl_50_8", levels_e=DEFAULT_LEVELS_E, *, overwrite=False,
                **options):
    """Simulate flat pairs (`simulate_flats`) and write them as FITS files.

    Each file holds one float32 image in ADU with EXPTIME, BUNIT = 'ADU' and the true
    simulation parameters in its header. Names are ``flat_<level>e_p<pair>_<1|2>.fits``.

    Parameters
    ----------
    outdir : str or path
        Output directory (created if needed).
    sensor, levels_e : optional
        As in `simulate_flats`.
    overwrite : bool, optional
        Replace existing files. Default False: an existing file is an error, raised before
        any simulation.
    **options
        Passed to `simulate_flats`.

    Returns
    -------
    list of pathlib.Path
        The files written, in the order of `simulate_flats`.

    Raises
    ------
    BFPSFFileExistsError
        A file exists and ``overwrite`` is False.
    """
    outdir = Path(outdir)
    levels = np.atleast_1d(np.asarray(levels_e, dtype=float))
    pairs = int(options.get("pairs", 1))
    paths = [outdir / f"flat_{level:08.0f}e_p{pair:02d}_{member}.fits"
             for level in levels for pair in range(pairs) for member in (1, 2)]
    if len(set(paths)) != len(paths):
        msg = f"the flat levels repeat a value: {levels.tolist()}"
        raise BFPSFValueError(msg, levels.tolist())
    if not overwrite:
        existing = [str(path) for path in paths if path.exists()]
        if existing:
            msg = (f"{len(existing)} output file(s) exist, e.g. {existing[0]}; "
                   "use overwrite=True (--overwrite) to replace them")
            raise BFPSFFileExistsError(msg)
    flats = simulate_flats(sensor, levels, **options)
    outdir.mkdir(parents=True, exist_ok=True)
    for path, (image, _, header) in zip(paths, flats):
        hdu = fits.PrimaryHDU(image.astype(np.float32))
        for key, value in header.items():
            hdu.header[key] = value
        hdu.header.comments["EXPTIME"] = "exposure time (s)"
        hdu.header.comments["SIMGAIN"] = "true gain (e-/ADU)"
        hdu.header.comments["SIMNOISE"] = "true read noise (e-)"
        hdu.header.comments["SIMLEVEL"] = "nominal charge level (e-)"
        write_fits(fits.HDUList([hdu]), path, overwrite=overwrite)
        log.info("wrote %s", path)
    return paths
