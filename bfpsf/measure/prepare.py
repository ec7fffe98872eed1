"""Image preparation: the one step every command and the Python API take first.

`prepare_image`: ADU -> e- with the gain, the linearity correction of a calibration refined
by ``bfpsf diagnose --output-calib`` undone on input (`linearity_of`), and the sky surface of
the image (`bfpsf.measure.sky.estimate_sky`; a known sky with ``background_e``), held in a
`PreparedImage`. `electrons` is the same without the sky.
"""

from dataclasses import dataclass, field

import numpy as np

from ..calibration.linearity import linearise
from ..errors import BFPSFInputError, BFPSFValueError
from .sky import SkyModel, estimate_sky, sky_pixels

__all__ = ["PreparedImage", "electrons", "prepare_image", "linearity_of"]


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
        The stars' light beyond the PSF support (`bfpsf.model.wings.wing_image`), e-,
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

    @property
    def sky_pixels(self):
        """The pixels beyond the sources (`bfpsf.measure.sky.sky_pixels`), found once per
        image: every sky estimate of it fits these."""
        if "sky_pixels" not in self._cache:
            self._cache["sky_pixels"] = sky_pixels(self.image_e)
        return self._cache["sky_pixels"]

    def with_glow(self, glow_e, stars_e):
        """The image with the sky re-estimated beyond the fitted stars (a known sky is kept):
        fitted to the image minus ``stars_e`` (the stars' models within the PSF support)
        minus ``glow_e`` (their wings beyond it), on the pixels beyond the sources
        (`sky_pixels`) where the two together are below the sky's noise, and ``glow_e`` kept
        to be subtracted with it (every pixel where the models are that faint, near faint
        stars too, left the sky of sparse Moffat fields 0.5-1.6 e- high).

        The source mask alone (`sky_pixels`) leaves the inner wings of neighbours in a dense
        field: 300 Kolmogorov stars 9 px apart on 320^2 pixels gave a sky 14-16 e- high and
        faint stars 8.8 mmag faint; with the models subtracted the sky there is the sky."""
        if self.sky.method == "known":
            return self.with_sky(self.sky, glow_e)
        light = np.asarray(stars_e, dtype=float) + np.asarray(glow_e, dtype=float)
        free = self.sky_pixels & np.isfinite(light) & (light < self.sky.rms)
        sky = estimate_sky(self.image_e, glow_e=light, degree=self.sky.kind,
                           sky_pixels_mask=free)
        return self.with_sky(sky, glow_e)

    def with_sky(self, sky, glow_e=None):
        """The image with another sky model and glow (the same pixels: the same sources)."""
        prepared = PreparedImage(self.image_e, sky, self.gain, self.linearity_c_per_1e5, glow_e)
        if "sky_pixels" in self._cache:
            prepared._cache["sky_pixels"] = self._cache["sky_pixels"]
        return prepared


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
                  sky_degree="auto"):
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
        (`bfpsf.measure.sky.estimate_sky`, a surface fitted beyond the masked sources).
    sky_degree : int, 'spline' or 'auto', optional
        Degree of the estimated sky surface (default ``'auto'``: a plane, or degree 2 or 3
        or a spline where the sky pixels ask for it, `bfpsf.measure.sky.choose_degree`).

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
    prepared._cache["sky_pixels"] = free  # kept for the sky again beyond the glow
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
