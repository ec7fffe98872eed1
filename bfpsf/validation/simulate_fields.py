"""Star fields for the defaults' acceptance: any PSF profile, a sloped sky of its own per
exposure, sparse or dense, and every electron of every star counted.

`simulate_field` draws stars of a GalSim profile (a Moffat, or a Kolmogorov atmosphere
convolved with an optical PSF: wings unlike a Moffat's) on a large stamp each (64 pixels by
default: the light beyond a PSF model's support is drawn too; ``stamp`` for wider wings), through a GalSim `SiliconSensor` (photon
shooting, the brighter-fatter truth) or with bfpsf's own redistribution of given boundary
shifts, and adds a sky plane with Poisson noise and read noise. The truth table holds each
star's total charge as simulated (``flux_e``: the sum of its whole stamp, the light that
falls beyond the image's edge included, before the sky).
"""

from dataclasses import dataclass, field

import numpy as np
from astropy.table import Table

from ..errors import BFPSFValueError
from ..model.redistribution import redistribute
from .simulate_spots import peak_fraction

__all__ = ["SimulatedField", "simulate_field", "kolmogorov_optical"]

#: Default side of the stamp each star is drawn on, pixels (``simulate_field(stamp=...)``).
STAMP = 64


def kolmogorov_optical(fwhm=3.5, *, lam_over_diam=0.8, defocus=0.3, astig1=0.15):
    """A Kolmogorov atmosphere convolved with an optical PSF (pixel units): wings falling as
    r^-11/3 and diffraction structure, unlike a Moffat's."""
    import galsim

    return galsim.Convolve(galsim.Kolmogorov(fwhm=fwhm),
                           galsim.OpticalPSF(lam_over_diam=lam_over_diam, defocus=defocus,
                                             astig1=astig1, obscuration=0.3))


@dataclass(frozen=True)
class SimulatedField:
    """Images (e-, sky and noise included) and the truth of their stars.

    Attributes
    ----------
    images : list of ndarray [y, x]
    truth : list of astropy.table.Table
        Per image: ``x``, ``y`` (pixels), ``flux_e`` (total charge drawn), ``peak_e``.
    skies : list of (float, float, float)
        Per image: the sky plane (level at the image centre, d/dx, d/dy), e- per pixel (with
        a ``sky_surface``: its level at the centre, its slopes NaN; `sky_image` evaluates
        it).
    parameters : dict
    """

    images: list
    truth: list
    skies: list
    parameters: dict = field(default_factory=dict)

    def sky_image(self, index):
        """The true sky of image ``index``, e- per pixel."""
        ny, nx = self.images[index].shape
        y, x = np.mgrid[:ny, :nx]
        surface = self.parameters.get("sky_surface")
        if surface is not None:
            return np.asarray(surface(x, y), dtype=float)
        level, slope_x, slope_y = self.skies[index]
        return level + slope_x * (x - (nx - 1) / 2) + slope_y * (y - (ny - 1) / 2)


def simulate_field(profile, *, n_images=2, shape=(256, 256), n_stars=40,
                   peak_range_e=(3e3, 1.2e5), min_separation=30.0, sky_range_e=(20.0, 610.0),
                   sensor="lsst_e2v_50_8", shifts=None, read_noise_e=5.0, seed=0, stamp=STAMP,
                   sky_surface=None):
    """Star fields of one profile, each image with its own sloped sky.

    Parameters
    ----------
    profile : galsim.GSObject or callable
        PSF without the pixel, pixel units; or ``profile(x, y)`` giving the PSF at an image
        position (a PSF varying over the field).
    n_images : int, optional
        Exposures (default 2).
    shape : (int, int), optional
        (ny, nx) of each image.
    n_stars : int, optional
        Stars per image (default 40), placed at random at least ``min_separation`` pixels
        apart and 10 pixels from the edges (a small separation makes a dense field of blends).
    peak_range_e : (float, float), optional
        Peaks drawn log-uniformly, e- (without BF; the flux is peak over the profile's
        pixelised peak fraction).
    min_separation : float, optional
        Pixels (default 30: isolated stars for a 25-pixel PSF support).
    sky_range_e : (float, float), optional
        Each image's sky is a plane whose values over the image span a random sub-range of
        this one, e- per pixel, in a random direction (default 20-610 e-).
    sensor : str or None, optional
        GalSim SiliconSensor name (photon shooting, default ``'lsst_e2v_50_8'``), or None to
        draw the expectation and apply ``shifts`` with bfpsf's redistribution.
    shifts : BoundaryShifts, optional
        With ``sensor=None``: the brighter-fatter redistribution applied (None: no BF).
    read_noise_e : float, optional
        Default 5 e-.
    seed : int, optional
    stamp : int, optional
        Side of the square each star is drawn on, pixels (default `STAMP`, 64). The light
        beyond it is not drawn, and the truth's ``flux_e`` is what is drawn: a profile with
        wide wings loses it (a Kolmogorov atmosphere with an optical PSF, 0.8 % of its flux
        beyond 32 pixels), and a sky fitted with a model of the whole wings comes out low
        there. Give a larger stamp for such profiles (photon shooting through a sensor is
        slower on a larger stamp).
    sky_surface : callable, optional
        ``sky_surface(x, y)``, e- per pixel: the sky of every image instead of the random
        plane (a curved sky: a vignetting bowl, scattered light).

    Returns
    -------
    SimulatedField
    """
    import galsim

    rng = np.random.default_rng(seed)
    ny, nx = (int(value) for value in shape)
    profile_at = profile if callable(profile) and not isinstance(profile, galsim.GSObject) \
        else (lambda x, y: profile)

    galsim_rng = galsim.BaseDeviate(int(rng.integers(1, 2**31 - 1)))
    sensor_object = None
    if sensor is not None:
        sensor_object = galsim.SiliconSensor(name=sensor, rng=galsim_rng)
    images, truths, skies = [], [], []
    for _ in range(n_images):
        xy = _positions(rng, n_stars, (ny, nx), min_separation)
        peaks = np.exp(rng.uniform(*np.log(peak_range_e), len(xy)))
        image = galsim.ImageD(nx, ny, xmin=0, ymin=0, scale=1.0)
        fluxes = []
        for (x, y), peak in zip(xy, peaks):
            column, row = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
            box = galsim.ImageD(galsim.BoundsI(column - stamp // 2, column + stamp // 2,
                                               row - stamp // 2, row + stamp // 2), scale=1.0)
            star_profile = profile_at(x, y)
            star = star_profile.withFlux(float(peak / peak_fraction(star_profile)))
            if sensor_object is None:
                star.drawImage(box, center=galsim.PositionD(x, y))
            else:
                star.drawImage(box, center=galsim.PositionD(x, y), method="phot",
                               sensor=sensor_object, rng=galsim_rng, poisson_flux=False)
            # the truth is the star's whole charge, its light beyond the image's edge included
            # (the sum over the image alone had left a Kolmogorov x optics star 30 px from
            # the edge 0.2-0.4 % short of the total flux that photometry measures)
            fluxes.append(float(box.array.sum()))
            overlap = box.bounds & image.bounds
            image[overlap] += box[overlap]
        array = image.array.copy()
        if sensor_object is None:
            if shifts is not None:
                array = redistribute(array, shifts, workers=1)
            array = rng.poisson(np.clip(array, 0, None)).astype(float)
        y_grid, x_grid = np.mgrid[:ny, :nx]
        if sky_surface is None:
            low, high = np.sort(rng.uniform(*sky_range_e, 2))
            angle = rng.uniform(0, 2 * np.pi)
            slope = (high - low) / np.hypot(nx - 1, ny - 1)
            sky = ((low + high) / 2, slope * np.cos(angle), slope * np.sin(angle))
            sky_image = (sky[0] + sky[1] * (x_grid - (nx - 1) / 2)
                         + sky[2] * (y_grid - (ny - 1) / 2))
        else:
            sky_image = np.asarray(sky_surface(x_grid, y_grid), dtype=float)
            sky = (float(sky_surface((nx - 1) / 2, (ny - 1) / 2)), np.nan, np.nan)
        array = array + rng.poisson(sky_image) + read_noise_e * rng.standard_normal(array.shape)
        images.append(array)
        truths.append(Table({"x": xy[:, 0], "y": xy[:, 1], "flux_e": np.array(fluxes),
                             "peak_e": peaks}))
        skies.append(sky)
    parameters = dict(n_images=n_images, shape=(ny, nx), n_stars=n_stars, stamp=int(stamp),
                      peak_range_e=tuple(peak_range_e), min_separation=min_separation,
                      sky_range_e=tuple(sky_range_e), sensor=sensor, seed=seed,
                      read_noise_e=read_noise_e, sky_surface=sky_surface)
    return SimulatedField(images, truths, skies, parameters)


def _positions(rng, n_stars, shape, min_separation, margin=10.0):
    """Random positions at least ``min_separation`` apart (as many as fit, up to n_stars)."""
    ny, nx = shape
    chosen = []
    for _ in range(200 * n_stars):
        candidate = rng.uniform((margin, margin), (nx - 1 - margin, ny - 1 - margin))
        if all(np.hypot(*(candidate - other)) >= min_separation for other in chosen):
            chosen.append(candidate)
            if len(chosen) == n_stars:
                break
    if len(chosen) < 3:
        msg = f"fewer than 3 stars fit in {shape} at {min_separation} pixels apart"
        raise BFPSFValueError(msg, min_separation)
    return np.array(chosen)
