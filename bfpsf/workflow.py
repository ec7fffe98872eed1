"""The user's path in the library: image preparation and the PSF from a set of images.

Every command and the Python API go through the same steps, so the Python path and the
command line give the same numbers:

1. `prepare_image`: ADU -> e- with the gain, the linearity correction of a calibration refined
   by ``bfpsf diagnose --output-calib`` undone on input, and the sky surface of the image
   (`bfpsf.measure.sky.estimate_sky`; a known sky with ``background_e``).
2. `psf_from_images`: isolated stars of every prepared image, the joint P0 fit with each
   image's boundary shifts (`bfpsf.model.psf_fit.fit_psf`, the build-up and the EMPIRICAL
   term of a refined calibration included; every other source, blends included, fitted
   alongside and subtracted from the stars' cutouts, not used for P0), the sky fitted jointly
   with the wings of all those stars, the total-flux correction measured from the bright
   isolated stars
   (`bfpsf.measure.total_flux.flux_correction`), and the product metadata (calibration,
   linearity correction, per-amplifier shifts).
3. `bfpsf.measure.photometry.psf_photometry` with the PSF product: the same sky model, the
   PSF's linearity correction, the total-flux correction.

``bfpsf psf``, ``bfpsf photometry`` and ``bfpsf measure`` read the files and call these.
"""

from dataclasses import dataclass, field

import numpy as np

from .calibration.linearity import linearise
from .errors import BFPSFInputError, BFPSFValueError
from .measure.sky import SkyModel, estimate_sky, sky_pixels
from .resources import check_psf_fit

__all__ = ["PreparedImage", "electrons", "prepare_image", "linearity_of", "psf_from_images",
           "PSFFromImages"]


@dataclass(frozen=True)
class PreparedImage:
    """An image ready for measurement.

    Attributes
    ----------
    image_e : ndarray [y, x]
        Linear charge, e- per pixel, sky included.
    sky : SkyModel
        The sky under the stars, e- per pixel.
    gain : float
        e-/ADU applied.
    linearity_c_per_1e5 : float
        Linearity correction undone on input (0: none).
    glow_e : ndarray [y, x] or None
        The stars' light beyond the PSF support (`bfpsf.measure.total_flux.wing_image`), e-,
        left out of the sky and subtracted with it (None: not modelled).
    """

    image_e: np.ndarray
    sky: SkyModel
    gain: float = 1.0
    linearity_c_per_1e5: float = 0.0
    glow_e: object = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def sky_subtracted(self):
        """``image_e`` minus the sky surface (and the stars' glow), e- per pixel."""
        if "data" not in self._cache:
            data = self.image_e - self.sky.image()
            self._cache["data"] = data if self.glow_e is None else data - self.glow_e
        return self._cache["data"]

    def with_glow(self, glow_e):
        """The image with the sky re-estimated beyond ``glow_e`` (a known sky is kept)."""
        if self.sky.method == "known":
            return self.with_sky(self.sky, glow_e)
        if "sky_pixels" not in self._cache:
            self._cache["sky_pixels"] = sky_pixels(self.image_e)
        sky = estimate_sky(self.image_e, glow_e=glow_e, degree=self.sky.degree,
                           sky_pixels_mask=self._cache["sky_pixels"])
        prepared = self.with_sky(sky, glow_e)
        prepared._cache["sky_pixels"] = self._cache["sky_pixels"]
        return prepared

    def with_sky(self, sky, glow_e=None):
        """The image with another sky model and glow."""
        return PreparedImage(self.image_e, sky, self.gain, self.linearity_c_per_1e5, glow_e)


def linearity_of(calibration):
    """The linearity correction c per 1e5 e- a (refined) calibration holds, 0 without one."""
    refinement = getattr(calibration, "refinement", None) or {}
    return float(refinement.get("linearity_c_per_1e5") or 0.0)


def electrons(data, *, gain=1.0, linearity_c_per_1e5=0.0):
    """The image in e-, a refined calibration's linearity correction undone (`prepare_image`
    without the sky: for `bfpsf.measure.sources.measure_sources`, which has its own)."""
    image = np.asarray(data, dtype=float)
    if image.ndim != 2:
        msg = f"an image must be 2-D [y, x], got shape {image.shape}"
        raise BFPSFInputError(msg, image.shape)
    if not (np.isfinite(gain) and gain > 0):
        msg = f"the gain must be positive e-/ADU, got {gain!r}"
        raise BFPSFValueError(msg, gain)
    image_e = image * float(gain)
    if linearity_c_per_1e5:
        image_e = linearise(image_e, linearity_c_per_1e5)
    return image_e


def prepare_image(data, *, gain=1.0, linearity_c_per_1e5=0.0, background_e=None,
                  sky_degree=1):
    """An image in e- with its sky: the one preparation step of every command.

    Parameters
    ----------
    data : array_like [y, x]
        Bias-subtracted image, ADU (or e- with ``gain=1``).
    gain : float, optional
        e-/ADU (default 1).
    linearity_c_per_1e5 : float, optional
        A refined calibration's linearity correction (`linearity_of`), undone on input
        (`bfpsf.calibration.linearity.linearise`). Default 0.
    background_e : float, optional
        A known sky, e- per pixel (``--background`` times the gain); default: estimated
        (`bfpsf.measure.sky.estimate_sky`, a plane fitted beyond the masked sources).
    sky_degree : int, optional
        Degree of the estimated sky surface (default 1, a plane).

    Returns
    -------
    PreparedImage
    """
    image_e = electrons(data, gain=gain, linearity_c_per_1e5=linearity_c_per_1e5)
    if background_e is not None:
        _check_known_sky(float(background_e), image_e)
        sky = SkyModel.constant(background_e, image_e.shape)
        return PreparedImage(image_e, sky, float(gain), float(linearity_c_per_1e5))
    free = sky_pixels(image_e)
    prepared = PreparedImage(image_e, estimate_sky(image_e, degree=sky_degree,
                                                   sky_pixels_mask=free),
                             float(gain), float(linearity_c_per_1e5))
    prepared._cache["sky_pixels"] = free  # the sky again beyond the glow: `with_glow`
    return prepared


def _check_known_sky(background_e, image_e):
    """A known sky (``--background``) must be possible: not above every pixel (every star
    would be negative), nor further below the darkest pixel than the image's whole range
    (every pixel a star's; a noiseless image of stars alone has its sky just below its
    darkest pixel, and is accepted)."""
    finite = image_e[np.isfinite(image_e)]
    if finite.size == 0:
        return  # named by the step that needs pixels
    low, high = float(finite.min()), float(finite.max())
    if not low - (high - low) <= background_e <= high:
        msg = (f"the given sky, {background_e:.6g} e- per pixel, is not possible for an image "
               f"whose pixels span {low:.6g} to {high:.6g} e-")
        raise BFPSFInputError(msg, background_e)


@dataclass(frozen=True)
class PSFFromImages:
    """Result of `psf_from_images`: the PSF product, the fit and what each image gave.

    Attributes
    ----------
    psf : BFPSFModel
        The fitted model with its metadata (``flux_correction``, ``linearity_c_per_1e5``, ...).
    fit : bfpsf.model.psf_fit.PSFFitResult
    images : list of dict
        Per image: ``n_detected``, ``n_isolated``, ``n_excluded``, ``background_e`` (the sky at
        the image centre), ``sky_slope`` (e- per pixel per pixel in x, y).
    """

    psf: object
    fit: object
    images: list


def psf_from_images(images, calibrations, *, size=None, oversampling=2, grid=None,
                    threshold=None, saturation_e=None, include_bf=True, max_iterations=40,
                    exclude=None, calibration_name="", shift_samples=(), exposure=None):
    """Fit the flux-dependent PSF from prepared images (what ``bfpsf psf`` does).

    Parameters
    ----------
    images : sequence of PreparedImage
        From `prepare_image` (one per image or amplifier).
    calibrations : Calibration or sequence of Calibration
        One for all, or one per image: boundary shifts (and a refined calibration's build-up
        steps); the read noise is their mean.
    size, oversampling, grid, max_iterations, include_bf
        As `bfpsf.model.psf_fit.fit_psf` (size default its ``DEFAULT_SIZE``).
    threshold : float, optional
        Detection threshold (default `bfpsf.measure.sources.DETECTION_THRESHOLD`).
    saturation_e : float or sequence, optional
        Saturation level of each image, e- (sky included): saturated stars are not used.
    exclude : sequence of callables, optional
        Per image, ``exclude[i](xy, shape) -> bool array`` of stars to leave out (e.g. near a
        side shared with another amplifier); counted as ``n_excluded``.
    calibration_name : str, optional
        Name of the calibration file (product metadata).
    shift_samples : sequence of BoundaryShifts, optional
        The calibration's uncertainty, kept in the product.
    exposure : float, optional
        Exposure order in the night of the images, for the exposure dependence of a refined
        calibration's EMPIRICAL term (default the term's reference, the middle of the
        exposures it was learned on).

    Returns
    -------
    PSFFromImages
    """
    from .measure.neighbours import isolated_stars
    from .measure.sources import DETECTION_THRESHOLD
    from .model.psf_fit import DEFAULT_SIZE, fit_psf

    size = DEFAULT_SIZE if size is None else int(size)
    threshold = DETECTION_THRESHOLD if threshold is None else float(threshold)
    images = list(images)
    if not isinstance(calibrations, (list, tuple)):
        calibrations = [calibrations] * len(images)
    saturation = np.broadcast_to(np.asarray(saturation_e if saturation_e is not None
                                            else np.nan, dtype=float), (len(images),))
    positions, others, per_image = [], [], []
    for index, prepared in enumerate(images):
        data = prepared.sky_subtracted
        # the level in the sky-subtracted image: below it wherever the sky is highest (a
        # clipped pixel minus a sloped sky falls under the level minus the sky's mean)
        level = None if not np.isfinite(saturation[index]) else float(
            saturation[index] - prepared.sky.image().max())
        xy, n_detected, neighbours = isolated_stars(data, size, threshold=threshold,
                                                    saturation_e=level)
        excluded = np.zeros(len(xy), dtype=bool)
        if exclude is not None and exclude[index] is not None and len(xy):
            excluded = np.asarray(exclude[index](xy, data.shape), dtype=bool)
        positions.append(xy[~excluded])
        # every other source (and an excluded star) is modelled in the P0 fit, not used
        others.append(np.concatenate([neighbours, xy[excluded]]))
        per_image.append({"n_detected": int(n_detected), "n_isolated": int(np.sum(~excluded)),
                          "n_excluded": int(np.sum(excluded)),
                          "background_e": prepared.sky.level,
                          "sky_slope": list(prepared.sky.slope),
                          "sky_method": prepared.sky.method})
    buildups = {calibration.refinement.get("buildup_steps")
                for calibration in calibrations if getattr(calibration, "refinement", None)}
    buildups.discard(None)
    options = {}
    if buildups:
        options = {"mode": "exact", "buildup_steps": int(max(buildups))}
    from .model.empirical import empirical_of

    # a refined calibration's EMPIRICAL term: in every star's model during the P0 fit (P0
    # does not absorb it) and in the product, which applies it everywhere
    empirical = empirical_of(list(calibrations), exposure) if include_bf else None
    if empirical is not None:
        options["empirical"] = empirical
    # the read noise and gain of the images the stars came from
    counts = np.array([len(xy) for xy in positions], dtype=float)
    counts = counts if counts.sum() else None
    noise = float(np.average([calibration.noise_e for calibration in calibrations],
                             weights=counts))
    gain = float(np.average([prepared.gain for prepared in images], weights=counts))

    def fit():
        return fit_psf([prepared.sky_subtracted for prepared in images], positions,
                       [calibration.shifts for calibration in calibrations],
                       oversampling=oversampling, size=size, read_noise=noise,
                       sky_e=[max(prepared.sky.level, 0.0) for prepared in images],
                       include_bf=include_bf, max_iterations=max_iterations,
                       flux_unit="electron", gain=gain, grid=grid, progress=None,
                       neighbours=others, **options)

    n_stars = int(sum(len(xy) for xy in positions))
    if n_stars < 3:
        msg = f"{n_stars} isolated, unsaturated star(s); the P0 fit needs 3 or more"
        raise BFPSFInputError(msg, n_stars)
    check_psf_fit(n_stars, size, oversampling, grid, max_iterations)
    result = fit()
    from .measure.total_flux import fit_sky_and_wings

    known = all(prepared.sky.method == "known" for prepared in images)
    for _ in range(1 if known else 2):
        # the sky of every image and the stars' wings beyond the support, fitted jointly
        # (the wings' glow biases a sky between the stars; the sky, the wings), then P0
        # refitted on the images with that sky and glow; a known sky is subtracted and only
        # a constant left free (what the wings' glow adds to it is not sky)
        skies, wings = fit_sky_and_wings(
            [prepared.image_e - prepared.sky.image() if known else prepared.image_e
             for prepared in images],
            _stars_of_images(result, len(images)), half_size=size // 2,
            degree=0 if known else images[0].sky.degree)
        if known:
            break
        images = [prepared.with_sky(prepared.sky if prepared.sky.method == "known" else sky,
                                    _glow(wings, stars, prepared.image_e.shape))
                  for prepared, sky, stars in zip(
                      images, skies, _stars_of_images(result, len(images)))]
        result = fit()
    for entry, prepared in zip(per_image, images):
        entry.update(background_e=prepared.sky.level, sky_slope=list(prepared.sky.slope),
                     sky_method=prepared.sky.method)
    psf = result.psf
    psf.empirical = empirical
    psf.calibration = str(calibration_name)
    psf.shift_samples = tuple(shift_samples)
    linearities = {prepared.linearity_c_per_1e5 for prepared in images}
    if len(linearities) > 1:
        msg = ("the images had different linearity corrections; one PSF product records one "
               f"(got {sorted(linearities)})")
        raise BFPSFValueError(msg, sorted(linearities))
    psf.linearity_c_per_1e5 = linearities.pop() if linearities else 0.0
    psf.wing_amplitude, psf.wing_power = wings.amplitude, wings.power
    # the flux beyond the support, over the flux inside it
    psf.flux_correction = 1.0 + wings.fraction
    psf.flux_correction_err = wings.fraction_err
    return PSFFromImages(psf, result, per_image)



def _stars_of_images(result, n_images):
    """Per image, (x, y, flux) of the stars `fit_psf` fitted: the used stars of its star table
    and the neighbours it modelled (every source of the image)."""
    parts = [result.stars[np.asarray(result.stars["flags"]) == 0]]
    if result.neighbours is not None and len(result.neighbours):
        parts.append(result.neighbours)
    images = [np.asarray(part["image"], dtype=int) for part in parts]
    return [tuple(np.concatenate([np.asarray(part[name], float)[image == index]
                                  for part, image in zip(parts, images)])
                  for name in ("x_fit", "y_fit", "flux_fit")) for index in range(n_images)]


def _glow(wings, stars, shape):
    from .measure.total_flux import wing_image

    return wing_image(wings, *stars, shape)
