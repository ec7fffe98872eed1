"""The noise of an image's sky pixels and the read noise it implies.

PSF photometry weights every pixel by the variance it predicts (sky, stars, read noise); a read
noise from a calibration that does not describe the images (another amplifier, a PTC that
left it undetermined) scales every flux error. `image_read_noise` measures it from the sky
pixels; `check_read_noise` says when a given one disagrees with them.
"""

import logging

import numpy as np
from scipy.stats import median_abs_deviation

__all__ = ["sky_variance", "pixel_variance", "image_read_noise", "sky_scatter", "check_sky",
           "check_read_noise",
           "READ_NOISE_MISMATCH"]

log = logging.getLogger(__name__)

#: A given read noise whose background variance (with the sky's Poisson variance) is more
#: than this factor from the sky pixels' variance is said (`_check_read_noise`): the sky's
#: own scatter is known to about 1 % from 1e4 pixels, its level to the gain's error.
READ_NOISE_MISMATCH = 1.2

def sky_variance(prepared):
    """The sky pixels' variance about the fitted sky (1.4826 times their median absolute
    deviation, squared) and their mean level, e-^2 and e-; None with fewer than 10 of them.

    Parameters
    ----------
    prepared : bfpsf.measure.prepare.PreparedImage

    Returns
    -------
    (float, float) or None
    """
    data = prepared.sky_subtracted
    free = prepared.sky_pixels & np.isfinite(data)  # the pixels its sky was fitted on
    if free.sum() < 10:
        return None
    values = data[free]
    spread = median_abs_deviation(values, scale="normal")
    return float(spread ** 2), float(np.mean(np.clip(prepared.sky.image()[free], 0.0, None)))


def pixel_variance(prepared):
    """The sky pixels' pixel-to-pixel variance, e-^2: half the variance of the differences of
    neighbours along rows (1.4826 times their median absolute deviation, squared), which a
    sky the fitted one does not follow (a step, a slope, a glow) leaves alone; None with
    fewer than 10 pairs."""
    data = prepared.sky_subtracted
    free = prepared.sky_pixels & np.isfinite(data)
    pairs = free[:, 1:] & free[:, :-1]
    if pairs.sum() < 10:
        return None
    difference = (data[:, 1:] - data[:, :-1])[pairs]
    return float(median_abs_deviation(difference, scale="normal") ** 2 / 2)


def image_read_noise(prepared):
    """Read noise of an image from its sky, e- rms: `sky_variance` less the sky's Poisson
    variance (its level), 0 when that is negative or there are too few sky pixels. What
    the fitted sky misses counts as noise here, as it does in the fluxes (`check_sky` says
    when it is there)."""
    sky = sky_variance(prepared)
    return 0.0 if sky is None else _read_noise_of(*sky)


def _scatter(prepared):
    """(`sky_scatter`, the sky pixels' variance about the fitted sky, their `pixel_variance`),
    or None."""
    sky, pixels = sky_variance(prepared), pixel_variance(prepared)
    if sky is None or not pixels:
        return None
    return float(sky[0] / pixels), sky, pixels


def sky_scatter(prepared):
    """The sky pixels' variance about the fitted sky over their `pixel_variance`: 1 where the
    sky is the fitted surface (None when either is unknown)."""
    found = _scatter(prepared)
    return None if found is None else found[0]


def check_sky(prepared):
    """`sky_scatter`, with a warning when it is above `READ_NOISE_MISMATCH`: the sky is not
    the fitted surface, and every star's flux carries its misfit (a new user's halves of the
    sky 220 e- apart: a read noise of 61.5 e- from the image against 5, and stars near the
    seam off by up to 70 mmag, unsaid; quadrants 150-450 e-: faint stars off by 30-56 mmag)."""
    found = _scatter(prepared)
    if found is None:
        return None
    ratio, sky, pixels = found
    if ratio > READ_NOISE_MISMATCH:
        log.warning("the sky pixels scatter %.3g e- rms about the fitted sky, %.2g times the "
                    "variance they show from pixel to pixel (%.3g e- rms): the sky is not the "
                    "fitted surface (amplifiers' offsets, seams, scattered light) or holds "
                    "the light of faint neighbours (a crowded field), and the stars' fluxes "
                    "carry its misfit; subtract the sky first and give --background 0 with "
                    "the read noise", np.sqrt(sky[0]), ratio, np.sqrt(pixels))
    return float(ratio)


def _read_noise_of(variance, level):
    return float(np.sqrt(max(variance - level, 0.0)))


def check_read_noise(prepared, read_noise_e):
    """Warn when a given read noise and the sky's level make a background variance
    `READ_NOISE_MISMATCH` times larger or smaller than the sky pixels show: every flux error
    scales with it (a new user's calibration gave 11.8 +- 2.1 e- where its images' read noise
    was 5: 1.30 times the sky's variance, flux pulls of rms 0.74-0.89)."""
    sky = sky_variance(prepared)
    if sky is None or not sky[0] > 0:
        return
    variance, level = sky
    ratio = (level + read_noise_e ** 2) / variance
    if not 1 / READ_NOISE_MISMATCH <= ratio <= READ_NOISE_MISMATCH:
        log.warning("read noise %.3g e- and a sky of %.4g e- make a background variance %.3g "
                    "times what the image's sky pixels show (%.4g e-^2, read noise %.3g e-): "
                    "faint stars' flux errors are %s by up to %.0f %%; give the read noise "
                    "(--read-noise; read_noise_e in Python)%s", read_noise_e, level, ratio,
                    variance, _read_noise_of(variance, level),
                    "too large" if ratio > 1 else "too small", 100 * abs(np.sqrt(ratio) - 1),
                    "" if ratio > 1 else ", unless the sky pixels hold the light of faint "
                    "neighbours (a crowded field), which no read noise describes")
