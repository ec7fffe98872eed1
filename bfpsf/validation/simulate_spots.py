"""Spots and star fields drawn with GalSim photon shooting through a sensor (BF truth).

`simulate_spots` draws Moffat spots at chosen peak levels through `galsim.SiliconSensor`
(brighter-fatter from Poisson_CCD pixel boundaries, independent of G15), through any other
`galsim.Sensor` (e.g. bfpsf's own sensor), or with no BF at all; `simulate_star_field` draws a
full image of stars with varied fluxes and an optional colour-dependent size, for the source
measurement; `write_image_adu` writes an image in ADU with the headers the ``bfpsf`` commands
read.

Timing: a 2.7e6 e- spot takes about 0.3 s through SiliconSensor (DESIGN.md). SiliconSensor
uses OpenMP: run with ``OMP_NUM_THREADS=1`` when anything else runs on the machine.
"""

from dataclasses import dataclass, field

import numpy as np
from astropy.io import fits
from astropy.table import Table
from tqdm import tqdm

from ..errors import BFPSFInputError, BFPSFValueError, integer_at_least
from ..files import refuse_overwrite
from ..outputs import write_fits

__all__ = ["SpotSet", "StarField", "simulate_spots", "simulate_star_field", "write_image_adu",
           "peak_fraction", "bf_free_sensor", "simulate_varying_exposures"]


@dataclass(frozen=True)
class SpotSet:
    """Simulated spots.

    Attributes
    ----------
    stamps : ndarray, shape (n, stamp_size, stamp_size)
        Spot images, electrons, mean sky subtracted (sky and read noise included if asked).
    x, y : ndarray, shape (n,)
        True centres, pixels, 0-based stamp coordinates (pixel centres at integers).
    fluxes : ndarray, shape (n,)
        Total flux asked of GalSim, electrons (photon shooting adds Poisson scatter).
    peaks : ndarray, shape (n,)
        Requested peak, electrons: the flux times the peak-pixel fraction of the same spot drawn
        without sensor. The measured peak differs by noise and by BF (bright spots flatten).
    level : ndarray of int, shape (n,)
        Index into ``parameters['peaks_e']`` of each spot.
    parameters : dict
        The arguments used.
    twin : ndarray or None
        With ``bf_free_twin=True``: the same spots drawn again with the same photons, the same
        sensor random numbers (diffusion) and the same noise, through the same SiliconSensor
        with its BF switched off. ``stamps - twin`` is the BF change of each spot with almost
        none of its photon noise: a control variate that makes BF slopes about 20 times more
        precise than the stamps alone.
    phase : ndarray of int or None
        With ``offsets`` given to `simulate_spots`: the index of each spot's sub-pixel offset
        (the same offsets at every level), e.g. a free intercept per phase in a slope fit.
    """

    stamps: np.ndarray
    x: np.ndarray
    y: np.ndarray
    fluxes: np.ndarray
    peaks: np.ndarray
    level: np.ndarray
    parameters: dict = field(default_factory=dict)
    twin: np.ndarray = None
    phase: np.ndarray = None

    def mosaic(self, n_columns=None, margin=0):
        """Tile the stamps into one image (row by row), e.g. to run ``bfpsf measure`` on them.

        Parameters
        ----------
        n_columns : int, optional
            Stamps per row (default: ceil(sqrt(n))).
        margin : int, optional
            Empty pixels around the mosaic (default 0), so that stamps of the same size
            centred on the spots stay inside the image.

        Returns
        -------
        image : ndarray
            Electrons; tiles without a spot are zero.
        truth : astropy.table.Table
            ``x``, ``y`` (0-based image pixels), ``flux_e``, ``peak_e``, ``level``,
            ``stamp`` (index into ``stamps``).
        """
        n_spots, size, _ = self.stamps.shape
        n_columns = int(np.ceil(np.sqrt(n_spots))) if n_columns is None else int(n_columns)
        n_rows = int(np.ceil(n_spots / n_columns))
        image = np.zeros((n_rows * size + 2 * margin, n_columns * size + 2 * margin))
        row, column = np.divmod(np.arange(n_spots), n_columns)
        for index in range(n_spots):
            y_start = margin + row[index] * size
            x_start = margin + column[index] * size
            image[y_start:y_start + size, x_start:x_start + size] = self.stamps[index]
        truth = Table({"x": self.x + column * size + margin, "y": self.y + row * size + margin,
                       "flux_e": self.fluxes, "peak_e": self.peaks, "level": self.level,
                       "stamp": np.arange(n_spots)})
        return image, truth


@dataclass(frozen=True)
class StarField:
    """A simulated image of stars.

    Attributes
    ----------
    image : ndarray, shape (ny, nx)
        Electrons, sky included (``sky_e`` per pixel) with its Poisson noise, and read noise.
    truth : astropy.table.Table
        One row per star: ``x, y`` (0-based pixels), ``flux_e``, ``peak_e`` (requested peak),
        ``fwhm`` (pixels), and the colour column.
    parameters : dict
        The arguments used.
    """

    image: np.ndarray
    truth: object
    parameters: dict = field(default_factory=dict)


def _make_sensor(sensor, rng):
    import galsim

    if sensor is None:
        return galsim.Sensor()
    if isinstance(sensor, str):
        return galsim.SiliconSensor(name=sensor, rng=rng)
    if isinstance(sensor, galsim.Sensor):
        return sensor
    msg = f"sensor must be a SiliconSensor name, a galsim.Sensor or None, got {sensor!r}"
    raise BFPSFValueError(msg, sensor)


def bf_free_sensor(name, rng):
    """The SiliconSensor ``name`` with its BF switched off, drawing on ``rng``.

    Given a deviate seeded like that of a SiliconSensor draw, it consumes the same random
    numbers in the same order (photons, conversion depths, diffusion steps), so the image it
    makes is that draw without BF. GalSim divides by the strength, so it is 1e-9, not 0.
    """
    import galsim

    return galsim.SiliconSensor(name=name, strength=1e-9, rng=rng)


def _sensor_label(sensor):
    return sensor if isinstance(sensor, (str, type(None))) else type(sensor).__name__


def peak_fraction(profile, size=15, offset=(0.0, 0.0)):
    """Fraction of the flux in the brightest pixel, drawn without sensor (pixel-integrated),
    the star centred ``offset`` pixels from the centre of a ``size``-pixel stamp: a star of
    peak P has flux P / peak_fraction (0.0518 for a Moffat of beta 3, FWHM 3.5 px)."""
    image = profile.withFlux(1.0).drawImage(nx=size, ny=size, scale=1.0, offset=offset)
    return float(image.array.max())


def _check_positive(name, value):
    if not (np.isfinite(value) and value > 0):
        msg = f"{name} must be positive, got {value!r}"
        raise BFPSFValueError(msg, value)


def simulate_spots(*, sensor="lsst_e2v_50_8", fwhm=4.0, beta=3.5, peaks_e=(10e3, 50e3, 100e3),
                   n_per_level=4, stamp_size=32, g1=0.0, g2=0.0, seed=0, read_noise_e=0.0,
                   sky_e=0.0, bf_free_twin=False, offsets=None):
    """Moffat spots at given peak levels, photon-shot through a sensor.

    Parameters
    ----------
    sensor : str, galsim.Sensor or None, optional
        A `galsim.SiliconSensor` name (default ``'lsst_e2v_50_8'``: BF truth), any
        `galsim.Sensor` instance (e.g. bfpsf's sensor), or None for no BF.
    fwhm : float, optional
        Moffat FWHM, pixels (default 4.0).
    beta : float, optional
        Moffat index (default 3.5).
    peaks_e : sequence of float, optional
        Peak levels, electrons in the brightest pixel (without BF). The total flux of each spot
        is ``peak / f`` with ``f`` the peak-pixel fraction of that spot (at its sub-pixel
        offset) drawn without sensor.
    n_per_level : int, optional
        Spots per level (default 4).
    stamp_size : int, optional
        Stamp side, pixels (default 32).
    g1, g2 : float, optional
        Reduced shear applied to the Moffat (default round).
    seed : int, optional
        Seed of offsets, photons and noise (default 0).
    read_noise_e : float, optional
        Gaussian read noise RMS, electrons (default 0).
    sky_e : float, optional
        Sky level, electrons per pixel, added with Poisson noise and its mean subtracted again
        (default 0).
    bf_free_twin : bool, optional
        Also draw every spot through the same SiliconSensor with BF switched off
        (``strength=1e-9``), with identical photons, diffusion steps and noise: `SpotSet.twin`.
        Needs ``sensor`` to be a SiliconSensor name. Doubles the run time. Default False.
    offsets : array_like, shape (n_per_level, 2), optional
        Sub-pixel offsets (x, y) in [-0.5, 0.5], pixels, repeated at every level (`SpotSet.phase`
        indexes them). The measured size of a pixelised spot depends on its phase by a few
        millipixels, as much as the BF change between levels; the same offsets at every level
        cancel it in the slopes. Default: random offsets for every spot.

    Returns
    -------
    SpotSet
    """
    import galsim

    _check_positive("fwhm", fwhm)
    _check_positive("beta", beta)
    peaks = np.asarray(peaks_e, dtype=float).ravel()
    if peaks.size == 0 or np.any(~(peaks > 0)):
        msg = f"peaks_e must be positive electrons, got {peaks_e!r}"
        raise BFPSFValueError(msg, peaks_e)
    integer_at_least("n_per_level", n_per_level, 1)
    integer_at_least("stamp_size", stamp_size, 8, "pixels")
    if read_noise_e < 0 or sky_e < 0:
        msg = f"read_noise_e and sky_e must be >= 0, got {read_noise_e!r}, {sky_e!r}"
        raise BFPSFValueError(msg, (read_noise_e, sky_e))

    if bf_free_twin and not isinstance(sensor, str):
        msg = f"bf_free_twin needs a SiliconSensor name as sensor, got {sensor!r}"
        raise BFPSFValueError(msg, sensor)

    rng = np.random.default_rng(seed)
    galsim_seed = int(rng.integers(1, 2**31 - 1))
    galsim_rng = galsim.BaseDeviate(galsim_seed)
    sensor_object = _make_sensor(sensor, galsim_rng)
    profile = galsim.Moffat(fwhm=fwhm, beta=beta)
    if g1 or g2:
        profile = profile.shear(g1=g1, g2=g2)

    level = np.repeat(np.arange(peaks.size), int(n_per_level))
    n_spots = level.size
    phase = None
    if offsets is None:
        offsets = rng.uniform(-0.5, 0.5, size=(n_spots, 2))
    else:
        offsets = np.asarray(offsets, dtype=float)
        if offsets.shape != (int(n_per_level), 2) or np.any(np.abs(offsets) > 0.5):
            msg = (f"offsets must be {int(n_per_level)} (x, y) pairs within [-0.5, 0.5], got "
                   f"shape {offsets.shape}")
            raise BFPSFValueError(msg, offsets.shape)
        phase = np.tile(np.arange(int(n_per_level)), peaks.size)
        offsets = offsets[phase]
    stamps = np.empty((n_spots, stamp_size, stamp_size))
    twin = np.empty_like(stamps) if bf_free_twin else None
    draws = [(sensor_object, galsim_rng, stamps)]
    if bf_free_twin:  # its own deviate, seeded alike: the same random numbers
        twin_rng = galsim.BaseDeviate(galsim_seed)
        draws.append((bf_free_sensor(sensor, twin_rng), twin_rng, twin))
    fluxes = np.empty(n_spots)
    for index in range(n_spots):
        offset = galsim.PositionD(*offsets[index])
        fluxes[index] = peaks[level[index]] / peak_fraction(profile, stamp_size, offset)
        for sensor_, deviate, out in draws:
            image = galsim.ImageD(stamp_size, stamp_size, scale=1.0)
            profile.withFlux(fluxes[index]).drawImage(
                image=image, method="phot", sensor=sensor_, rng=deviate, offset=offset)
            out[index] = image.array
    noise = np.zeros_like(stamps)
    if sky_e > 0:
        noise += rng.poisson(sky_e, size=stamps.shape) - sky_e
    if read_noise_e > 0:
        noise += read_noise_e * rng.standard_normal(stamps.shape)
    stamps += noise
    centre = (stamp_size - 1) / 2.0          # GalSim true_center, 0-based
    parameters = dict(sensor=_sensor_label(sensor), fwhm=fwhm, beta=beta,
        peaks_e=tuple(peaks), n_per_level=int(n_per_level), stamp_size=int(stamp_size),
        g1=g1, g2=g2, seed=seed, read_noise_e=read_noise_e, sky_e=sky_e,
        bf_free_twin=bool(bf_free_twin), offsets=None if phase is None else offsets.tolist())
    return SpotSet(stamps=stamps, x=centre + offsets[:, 0], y=centre + offsets[:, 1],
                   fluxes=fluxes, peaks=peaks[level], level=level, parameters=parameters,
                   twin=twin + noise if bf_free_twin else None, phase=phase)


def simulate_star_field(*, shape=(512, 512), n_stars=100, peak_range_e=(2e3, 1.2e5),
                        fwhm=4.0, beta=3.5, sensor=None, spacing=40, colour_name="g_i",
                        colour_flux_slope=0.0, colour_scatter=0.3, fwhm_colour_slope=0.0,
                        colour_reference=1.0, sky_e=100.0, read_noise_e=5.0, seed=0):
    """An image of Moffat stars with varied fluxes and an optional size-colour relation.

    Stars sit on a grid of step ``spacing`` pixels with random sub-pixel jitter (no blends).
    Each star has a colour ``c = colour_reference + colour_flux_slope * log10(peak / 1e4)
    + N(0, colour_scatter)`` and a FWHM ``fwhm * (1 + fwhm_colour_slope * (c -
    colour_reference))``: with both slopes non-zero the size correlates with flux through colour
    (G15 section 3.2), which the colour correction must remove.

    Parameters
    ----------
    shape : tuple of int, optional
        Image shape ``(ny, nx)``, pixels (default 512 x 512).
    n_stars : int, optional
        Stars (at most the grid positions; default 100).
    peak_range_e : tuple of float, optional
        Peak levels are drawn log-uniformly in this range, electrons (without BF).
    fwhm, beta : float, optional
        Moffat FWHM (pixels) and index at the reference colour.
    sensor : str, galsim.Sensor or None, optional
        As in `simulate_spots` (default None: no BF; the stars are then drawn by GalSim's
        default method and Poisson noise is added, instead of photon shooting).
    spacing : int, optional
        Grid step, pixels (default 40).
    colour_name : str, optional
        Name of the colour column in ``truth`` (default ``'g_i'``).
    colour_flux_slope, colour_scatter, fwhm_colour_slope, colour_reference : float, optional
        The colour model above (mag per dex of peak, mag, fractional FWHM per mag, mag).
    sky_e : float, optional
        Sky level, electrons per pixel (default 100), left in the image.
    read_noise_e : float, optional
        Read noise RMS, electrons (default 5).
    seed : int, optional
        Seed (default 0).

    Returns
    -------
    StarField
    """
    import galsim

    ny, nx = (int(value) for value in shape)
    half = spacing // 2
    grid_y, grid_x = np.mgrid[half:ny - half + 1:spacing, half:nx - half + 1:spacing]
    if grid_x.size < n_stars:
        msg = (f"an image of shape {shape} holds {grid_x.size} stars at spacing {spacing}, "
               f"fewer than n_stars={n_stars}")
        raise BFPSFValueError(msg, n_stars)
    rng = np.random.default_rng(seed)
    galsim_rng = galsim.BaseDeviate(int(rng.integers(1, 2**31 - 1)))
    sensor_object = _make_sensor(sensor, galsim_rng)
    chosen = rng.permutation(grid_x.size)[:n_stars]
    x = grid_x.ravel()[chosen] + rng.uniform(-0.5, 0.5, n_stars)
    y = grid_y.ravel()[chosen] + rng.uniform(-0.5, 0.5, n_stars)
    low, high = peak_range_e
    peaks = np.exp(rng.uniform(np.log(low), np.log(high), n_stars))
    colour = (colour_reference + colour_flux_slope * np.log10(peaks / 1e4)
              + colour_scatter * rng.standard_normal(n_stars))
    star_fwhm = fwhm * (1.0 + fwhm_colour_slope * (colour - colour_reference))
    if np.any(star_fwhm <= 0):
        msg = "fwhm_colour_slope makes some FWHM non-positive"
        raise BFPSFValueError(msg, fwhm_colour_slope)

    image = galsim.ImageD(nx, ny, scale=1.0, xmin=0, ymin=0)
    fluxes = np.empty(n_stars)
    stamp_half = half - 1
    for index in range(n_stars):
        profile = galsim.Moffat(fwhm=star_fwhm[index], beta=beta)
        centre = galsim.PositionD(x[index], y[index])
        integer = galsim.PositionI(int(np.floor(x[index] + 0.5)), int(np.floor(y[index] + 0.5)))
        offset = centre - galsim.PositionD(integer.x, integer.y)
        size = 2 * stamp_half + 1
        fluxes[index] = peaks[index] / peak_fraction(profile, size, offset)
        bounds = galsim.BoundsI(integer.x - stamp_half, integer.x + stamp_half,
                                integer.y - stamp_half, integer.y + stamp_half) & image.bounds
        if sensor is None:
            # no BF: draw the expectation, Poisson noise is added below (much faster)
            profile.withFlux(fluxes[index]).drawImage(
                image=image[bounds], center=centre, add_to_image=True)
        else:
            profile.withFlux(fluxes[index]).drawImage(
                image=image[bounds], method="phot", sensor=sensor_object, rng=galsim_rng,
                center=centre, add_to_image=True)
    if sensor is None:
        array = rng.poisson(np.maximum(image.array, 0.0) + sky_e).astype(float)
    else:
        array = image.array.copy()
        if sky_e > 0:
            array += rng.poisson(sky_e, size=array.shape)
    if read_noise_e > 0:
        array += read_noise_e * rng.standard_normal(array.shape)
    truth = Table({"x": x, "y": y, "flux_e": fluxes, "peak_e": peaks, "fwhm": star_fwhm,
                   colour_name: colour})
    parameters = dict(shape=(ny, nx), n_stars=n_stars, peak_range_e=tuple(peak_range_e),
                      fwhm=fwhm, beta=beta, sensor=_sensor_label(sensor), spacing=spacing,
                      colour_name=colour_name,
                      colour_flux_slope=colour_flux_slope, colour_scatter=colour_scatter,
                      fwhm_colour_slope=fwhm_colour_slope, colour_reference=colour_reference,
                      sky_e=sky_e, read_noise_e=read_noise_e, seed=seed)
    return StarField(image=array, truth=truth, parameters=parameters)


def simulate_varying_exposures(*, n_exposures=36, shape=(400, 400), spacing=40,
                               sensor="lsst_e2v_50_8", fwhm_range=(3.0, 3.9),
                               e1_range=(-0.04, 0.04), beta=3.5, peak_range_e=(3e3, 1.2e5),
                               seed=0, bf_free_twin=True, progress=False):
    """Exposures of isolated `simulate_spots` stars whose PSF varies over the field.

    Each exposure holds one star per ``spacing`` x ``spacing`` tile (random sub-pixel
    position, log-uniform peak). The Moffat FWHM grows linearly with x across the image from
    ``fwhm_range[0]`` to ``fwhm_range[1]``, and the distortion e1 = (Mxx - Myy) / (Mxx + Myy)
    linearly with y over ``e1_range`` (reduced shear g1 = e1 / (1 + sqrt(1 - e1**2))).

    Parameters
    ----------
    n_exposures : int, optional
    shape : (int, int), optional
        (ny, nx) of each exposure, pixels; multiples of ``spacing``.
    spacing : int, optional
        Tile side, pixels (the stamp of each star).
    sensor, beta, seed, bf_free_twin
        As in `simulate_spots`.
    fwhm_range : (float, float), optional
        FWHM at x = 0 and x = nx, pixels.
    e1_range : (float, float), optional
        e1 at y = 0 and y = ny.
    peak_range_e : (float, float), optional
        Peaks drawn log-uniformly, electrons.
    progress : bool, optional
        Show a tqdm progress bar.

    Returns
    -------
    images : ndarray (n_exposures, ny, nx)
        Electrons, no sky.
    twins : ndarray or None
        The same exposures without BF (`SpotSet.twin`).
    truth : astropy.table.Table
        ``image``, ``x``, ``y`` (pixels), ``flux_e``, ``peak_e``, ``fwhm``, ``e1``.
    """
    ny, nx = (int(value) for value in shape)
    if ny % spacing or nx % spacing:
        msg = f"shape {shape} must be a multiple of spacing {spacing}"
        raise BFPSFValueError(msg, shape)
    rng = np.random.default_rng(seed)
    images = np.zeros((n_exposures, ny, nx))
    twins = np.zeros_like(images) if bf_free_twin else None
    rows = []
    tiles = [(row, column) for row in range(ny // spacing) for column in range(nx // spacing)]
    low, high = np.log(peak_range_e)
    for exposure in tqdm(range(n_exposures), disable=not progress, desc="exposures"):
        for row, column in tiles:
            peak = float(np.exp(rng.uniform(low, high)))
            x_tile, y_tile = (column + 0.5) * spacing, (row + 0.5) * spacing
            fwhm = fwhm_range[0] + (fwhm_range[1] - fwhm_range[0]) * x_tile / nx
            e1 = e1_range[0] + (e1_range[1] - e1_range[0]) * y_tile / ny
            spot = simulate_spots(sensor=sensor, fwhm=fwhm, beta=beta, peaks_e=(peak,),
                                  n_per_level=1, stamp_size=spacing,
                                  g1=e1 / (1 + np.sqrt(1 - e1**2)),
                                  seed=int(rng.integers(2**31)), bf_free_twin=bf_free_twin)
            box = (exposure, slice(row * spacing, (row + 1) * spacing),
                   slice(column * spacing, (column + 1) * spacing))
            images[box] = spot.stamps[0]
            if bf_free_twin:
                twins[box] = spot.twin[0]
            rows.append((exposure, column * spacing + spot.x[0], row * spacing + spot.y[0],
                         spot.fluxes[0], peak, fwhm, e1))
    truth = Table(rows=rows, names=("image", "x", "y", "flux_e", "peak_e", "fwhm", "e1"))
    return images, twins, truth


def write_image_adu(path, image_e, *, gain, exptime=1.0, catalog=None, overwrite=False):
    """Write an image in electrons to FITS in ADU, as the ``bfpsf`` commands read it.

    Parameters
    ----------
    path : str or path-like
        Output FITS file.
    image_e : ndarray
        Image, electrons (background included or not).
    gain : float
        e-/ADU; the file holds ``image_e / gain``, header ``GAIN``.
    exptime : float, optional
        Header ``EXPTIME``, seconds (default 1).
    catalog : astropy.table.Table, optional
        Written as a binary-table extension ``CATALOG`` (e.g. the truth with colours: ``bfpsf
        measure --color`` reads colours from it).
    overwrite : bool, optional
        Replace an existing file (default False: `BFPSFFileExistsError`).
    """
    _check_positive("gain", gain)
    refuse_overwrite(path, overwrite, how="overwrite=True")
    array = np.asarray(image_e, dtype=float)
    if array.ndim != 2:
        msg = f"image_e must be 2-D, got shape {array.shape}"
        raise BFPSFInputError(msg, array.shape)
    header = fits.Header()
    header["EXPTIME"] = (float(exptime), "exposure time [s]")
    header["GAIN"] = (float(gain), "gain [e-/ADU]")
    header["BUNIT"] = ("adu", "pixel unit")
    hdus = [fits.PrimaryHDU((array / gain).astype(np.float32), header=header)]
    if catalog is not None:
        hdus.append(fits.table_to_hdu(catalog))
        hdus[-1].name = "CATALOG"
    write_fits(fits.HDUList(hdus), path, overwrite=overwrite)
