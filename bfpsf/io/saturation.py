"""Saturation levels from the headers, the options and the calibration; saturated stars.

A star with a saturated pixel (its charge spilled or clipped), or with a pixel above the
linearity turnoff of the calibration (where the PTC, hence the brighter-fatter model, no longer
holds), is mis-measured by every fit: it is flagged and left out of the P0 fit, never silently
used. The level comes from

* the command's ``--saturation ADU`` option, else
* the image header: ``SATURATE`` (SExtractor, DECam, Subaru) or a common variant
  (`SATURATION_KEYWORDS`), in the HDU of the amplifier or in the primary header,

in ADU of the raw pixels. Where the overscan is subtracted, the level in the subtracted
pixels is the raw level minus the largest overscan level (a star is flagged a little early
rather than missed). With a calibration whose linearity turnoff was detected, the lower of the
two (in electrons) applies.
"""

import numpy as np
from scipy import ndimage

from ..errors import BFPSFInputError

__all__ = ["SATURATION_KEYWORDS", "header_saturation", "saturation_adu", "saturation_e",
           "saturated_stars", "count_saturated_regions", "flats_top_e", "beyond_flats",
           "describe_beyond_flats"]

#: Header keywords holding the saturation level in ADU, in order of preference.
SATURATION_KEYWORDS = ("SATURATE", "SATURATN", "SATLEVEL", "SAT_LEVL", "SATLEV", "SATUR",
                       "SATURAT")


def header_saturation(header, *, where=""):
    """The saturation level of a header (`SATURATION_KEYWORDS`), ADU; None if it has none.

    Raises
    ------
    BFPSFInputError
        The keyword holds something other than a positive finite number.
    """
    for keyword in SATURATION_KEYWORDS:
        if keyword not in header:
            continue
        value = header[keyword]
        try:
            level = float(value)
        except (TypeError, ValueError):
            level = float("nan")
        if isinstance(value, bool) or not (np.isfinite(level) and level > 0):
            msg = (f"{where}: header {keyword} = {value!r} is not a saturation level (a "
                   "positive number of ADU); give --saturation ADU")
            raise BFPSFInputError(msg, value)
        return level
    return None


def saturation_adu(amplifier, option=None):
    """The saturation level in the ADU of ``amplifier.data`` (overscan subtracted), or None.

    Parameters
    ----------
    amplifier : bfpsf.io.amplifiers.Amplifier
    option : float, optional
        ``--saturation``, raw ADU; overrides the header.
    """
    if option is not None:
        level = float(option)
        if not (np.isfinite(level) and level > 0):
            msg = f"--saturation must be a positive number of ADU, got {option!r}"
            raise BFPSFInputError(msg, option)
    else:
        level = header_saturation(amplifier.header, where=amplifier.label)
    if level is None:
        return None
    if amplifier.overscan_adu is not None and np.size(amplifier.overscan_adu):
        level -= float(np.max(amplifier.overscan_adu))
    return level


def saturation_e(amplifier, gain, option=None, calibration=None):
    """The level (e-, in ``amplifier.data * gain``) above which a pixel spoils its star: the
    saturation (`saturation_adu`) or the calibration's linearity turnoff where it was
    detected, whichever is lower; None if neither is known.

    Parameters
    ----------
    amplifier : bfpsf.io.amplifiers.Amplifier
    gain : float
        e-/ADU.
    option : float, optional
        ``--saturation``, ADU.
    calibration : bfpsf.Calibration, optional
        The amplifier's calibration: its ``turnoff_e`` when ``turnoff_detected``.
    """
    levels = []
    adu = saturation_adu(amplifier, option)
    if adu is not None:
        levels.append(adu * float(gain))
    if calibration is not None and getattr(calibration, "turnoff_detected", False):
        turnoff = float(calibration.turnoff_e)
        if np.isfinite(turnoff) and turnoff > 0:
            levels.append(turnoff)
    return min(levels) if levels else None


def saturated_stars(image, level, x, y, box):
    """True for each star with a pixel at or above ``level`` in its fit box.

    Parameters
    ----------
    image : ndarray [y, x]
    level : float or None
        In the units of ``image``; None: no star is saturated.
    x, y : array_like
        Star centres, pixels of ``image``.
    box : int
        Side of the fit box, pixels (clipped at the image edges).
    """
    x, y = np.atleast_1d(np.asarray(x, dtype=float)), np.atleast_1d(np.asarray(y, dtype=float))
    flagged = np.zeros(x.shape, dtype=bool)
    if level is None:
        return flagged
    hot = np.asarray(image) >= level
    if not hot.any():
        return flagged
    # summed-area table: the count of saturated pixels in any box in O(1)
    counts = np.pad(hot.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    ny, nx = hot.shape
    half = int(box) // 2
    finite = np.isfinite(x) & np.isfinite(y)
    column = np.where(finite, np.rint(x), -10 * (half + 1) - nx).astype(int)
    row = np.where(finite, np.rint(y), -10 * (half + 1) - ny).astype(int)
    x0, x1 = np.clip(column - half, 0, nx), np.clip(column + half + 1, 0, nx)
    y0, y1 = np.clip(row - half, 0, ny), np.clip(row + half + 1, 0, ny)
    inside = counts[y1, x1] - counts[y0, x1] - counts[y1, x0] + counts[y0, x0]
    return inside > 0


def count_saturated_regions(image, level):
    """Number of connected groups of pixels at or above ``level`` (saturated stars), 0 for
    None."""
    if level is None:
        return 0
    _, count = ndimage.label(np.asarray(image) >= level)
    return int(count)


def flats_top_e(calibration):
    """The highest mean level of the flats a calibration's PTC used, e- per pixel (None
    without a PTC table): above it the boundary shifts are extrapolated, not measured."""
    table = getattr(calibration, "ptc", None)
    if table is None or "mean_e" not in table.colnames or not len(table):
        return None
    used = (np.asarray(table["used"], dtype=bool) if "used" in table.colnames
            else np.ones(len(table), dtype=bool))
    means = np.asarray(table["mean_e"], dtype=float)[used]
    means = means[np.isfinite(means)]
    return float(means.max()) if means.size else None


def beyond_flats(psf, flux_e, sky_e, calibration, x=None, y=None):
    """How many of the stars of fluxes ``flux_e`` inside P0's support (e-) on a sky ``sky_e``
    (e- per pixel) have a brightest pixel, the flux times P0's peak plus the sky, above the
    flats' highest level (`flats_top_e`), and that level (0 and None without one). A new
    user's stars peaked up to 1.2e5 e- over flats to 1e5: no command said so. With the
    stars' positions ``x``, ``y``, P0's peak at each star's sub-pixel phase (and place), not
    on a pixel centre: an undersampled P0 peaks far higher there than on a corner (a new
    user's "8 of 300 stars peak above" where none did)."""
    top = flats_top_e(calibration)
    if top is None:
        return 0, None
    flux = np.asarray(flux_e, dtype=float)
    if x is None or y is None:
        fraction = float(np.max(psf.star_image(1.0)))
    else:
        fraction = np.array([np.max(psf.star_image(1.0, float(column), float(row)))
                             if np.isfinite(column) and np.isfinite(row) else np.nan
                             for column, row in zip(np.broadcast_to(x, flux.shape),
                                                    np.broadcast_to(y, flux.shape))])
    peaks = flux * fraction + np.asarray(sky_e, dtype=float)
    return int(np.sum(peaks[np.isfinite(peaks)] > top)), top


def describe_beyond_flats(count, total, top):
    """The warning line of `beyond_flats`, or None when no star is beyond."""
    if not count:
        return None
    return (f"WARNING: {count} of {total} stars peak above the flats' highest level "
            f"({top:.4g} e- per pixel, sky included): their brighter-fatter is extrapolated "
            "beyond what the flats measured; add brighter flats to calibrate it")
