"""Pixels on a linear feature: a satellite or aircraft trail, a hot or bleeding column.

Detection splits a trail into a string of peaks, and PSF photometry then fitted each as a star
(a new user's 512^2 image with two trails, a hot column and 40 cosmic rays: 163 spurious
stars from the lines, fitted in chained groups, in minutes). `line_mask` finds the pixels of
such features so that detection, the residual search and every fit leave them out (that
image: 7.7 s, 8 sources from the lines where they pass bright stars, every star found;
docs/defaults.md, "Trails and hot columns").

On the detection's smoothed image (and on its negative: a dead column is a dark line), a
pixel at or above `LINE_LEVEL` rms (or the detection threshold, if lower) is on a line along
one of `N_DIRECTIONS` directions when

* along it, the image stays bright on both sides: the lower quartile of the samples from
  `INNER` to `OUTER` pixels away, on the fainter side, is at least `ALONG_FRACTION` of the
  pixel's value (a star's light is gone 4 pixels out; a neighbour's core raises 3 of the 13
  samples at most, not the quartile);
* across it, the image falls on one side at least: the median of the samples on the fainter
  side is at most `ACROSS_FRACTION` of it (the inside of a broad source, of a step of the
  sky, is bright on both; a star beside a trail raises one side only).

The pixels of each direction then make a line only when they reach `MIN_LENGTH` along
their own axis with an rms width of at most `MAX_WIDTH`, cover `MIN_COVERAGE` of that length
and the image along it is even (`MIN_EVEN`), pieces `GAP` pixels apart joined along the
direction, never across it. A bright star's halo passes the tests along its tangent, a
different direction every few pixels; a crowded field's bridges between bright stars pass
over a few pixels; a chain of bright stars has its cores and dips. A star on a trail,
brighter than the trail, is a star (its core fails the first test). The mask is grown over
the line's wings, never into a source brighter than the line beside it.

Limits: a line is not masked where a bright star's light falls along it (within about 25
pixels of a star of 2e6 e-: a star of 8e4 e- on such a stretch of a trail was 37 mmag too
bright, flagged ``ON_LINE`` by the masked trail beyond), nor at an image's corner; a line
fainter than about `LINE_LEVEL` times the smoothed image's rms is not seen; a new user's
bleed trail of a saturated star was not masked (its star is flagged saturated).
"""

import numpy as np
from astropy.stats import sigma_clipped_stats
from scipy import ndimage

from .smoothing import smoothed_image

__all__ = ["line_mask", "resolve_lines", "near_lines", "N_DIRECTIONS", "INNER", "OUTER",
           "ALONG_FRACTION", "ACROSS_FRACTION", "RIDGE_FRACTION", "RIDGE_SHARE", "MIN_LENGTH",
           "MIN_COVERAGE", "MIN_EVEN", "LINE_LEVEL", "GAP", "MAX_WIDTH"]

#: Directions tested, evenly over 180 degrees (11.25 degrees apart: a trail between two of
#: them is off by at most 1.6 pixels at `OUTER`, about the smoothed trail's width).
N_DIRECTIONS = 16
#: Distances along a direction, pixels: from beyond a star's core to five of its FWHM.
INNER, OUTER = 4, 16
#: Along the line, the fainter side's lower quartile over the pixel's value, at least this.
ALONG_FRACTION = 0.6
#: Across the line, the fainter side's median over the pixel's value, at most this.
ACROSS_FRACTION = 0.3
#: Across the line, the brighter side's median over the pixel's value, at most this.
RIDGE_FRACTION = 1.0
#: The share of a line's pixels that are ridges (`RIDGE_FRACTION`), at least.
RIDGE_SHARE = 0.5
#: A line is at least this long, pixels (as far as the tests reach on both sides).
MIN_LENGTH = 2 * OUTER
#: The fraction of a line's length its pixels cover, at least.
MIN_COVERAGE = 0.8
#: The fraction of a line's length where the image is within a factor of 2 of its median
#: along it, at least.
MIN_EVEN = 0.7
#: A line's pixels are at least this many rms of the smoothed image (or the detection
#: threshold, if lower): a trail of 2.5 times the pixel noise, under the detection
#: threshold, left 13 sources in the residual search.
LINE_LEVEL = 3.0
#: Gaps a line may have, pixels.
GAP = 6
#: The rms width of a line's pixels about its axis, at most, pixels (a smoothed trail of 1.5
#: px sigma above the level: about 1.5).
MAX_WIDTH = 3.0
#: Candidate pixels examined at once (memory: 13 samples each, per direction and side).
_CHUNK = 200_000


def _side_levels(smoothed, rows, columns):
    """The lower quartile and the median of the smoothed image from `INNER` to `OUTER` pixels
    along each direction and its opposite, at each pixel: ndarray (2 quantiles, 2 sides,
    N_DIRECTIONS, n); inf on a side whose middle sample lies beyond the image's edge."""
    ny, nx = smoothed.shape
    distances = np.arange(INNER, OUTER + 1, dtype=float)
    angles = np.pi * np.arange(N_DIRECTIONS) / N_DIRECTIONS
    middle = distances.size // 2
    out = np.empty((2, 2, N_DIRECTIONS, rows.size))
    for side, sign in enumerate((1.0, -1.0)):
        for index, angle in enumerate(angles):
            row = rows[None, :] + sign * distances[:, None] * np.sin(angle)
            column = columns[None, :] + sign * distances[:, None] * np.cos(angle)
            # bilinear, beyond the image's edge its edge pixels
            samples = ndimage.map_coordinates(smoothed, [row.ravel(), column.ravel()], order=1,
                                              mode="nearest").reshape(row.shape)
            out[:, side, index] = np.percentile(samples, [25, 50], axis=0)
            # a side mostly beyond the edge says nothing: the other side decides (a trail
            # that leaves the image, to its last pixels)
            beyond = ((row[middle] < 0) | (row[middle] > ny - 1) | (column[middle] < 0)
                      | (column[middle] > nx - 1))
            out[:, side, index, beyond] = np.inf
    return out


def _bright_along(smoothed, rows, columns):
    """The pixels (rows, columns) that may pass the test along a line: the image halfway
    from `INNER` to `OUTER` on both sides, along one of the directions, at least half
    `ALONG_FRACTION` of the pixel's value (a star's pixels are not: the full test looks at 26
    samples per direction, this at 2; on a crowded field's pixels it is most of the cost)."""
    value = smoothed[rows, columns]
    middle = (INNER + OUTER) / 2.0
    keep = np.zeros(rows.size, dtype=bool)
    for angle in np.pi * np.arange(N_DIRECTIONS) / N_DIRECTIONS:
        sides = [ndimage.map_coordinates(
            smoothed, [rows + sign * middle * np.sin(angle),
                       columns + sign * middle * np.cos(angle)], order=1, mode="nearest")
                 for sign in (1.0, -1.0)]
        keep |= np.minimum(*sides) >= 0.5 * ALONG_FRACTION * value
    return rows[keep], columns[keep]


def _line_structure(angle):
    """A line of `GAP` + 1 pixels through the centre along ``angle``: the structuring
    element that joins the pieces of a line along it, and not lines that cross it."""
    half = GAP // 2
    structure = np.zeros((2 * half + 1, 2 * half + 1), dtype=bool)
    steps = np.linspace(-half, half, 4 * GAP + 1)
    structure[np.rint(half + steps * np.sin(angle)).astype(int),
              np.rint(half + steps * np.cos(angle)).astype(int)] = True
    return structure


def _even(smoothed, centre, axis, start, stop):
    """Whether ``smoothed`` along the line (from ``start`` to ``stop`` pixels along ``axis``
    from ``centre``, x and y) stays within a factor of 2 of its median over `MIN_EVEN` of
    its length: a trail does, a chain of stars does not (its cores, its dips between)."""
    steps = np.arange(start, stop + 1.0)
    samples = ndimage.map_coordinates(smoothed, [centre[1] + steps * axis[1],
                                                 centre[0] + steps * axis[0]], order=1,
                                      mode="nearest")
    median = np.median(samples)
    return median > 0 and np.mean((samples >= median / 2) & (samples <= 2 * median)) >= MIN_EVEN


def _long(mask, angle, smoothed, ridges):
    """The pixels of ``mask`` in lines along ``angle`` at least `MIN_LENGTH` long and at most
    `MAX_WIDTH` wide about their own axis (a trail between two directions tested), its pieces
    joined along ``angle`` over gaps of up to `GAP` pixels (a line's pixels beside a star
    or a cosmic ray may fail the tests), never across (lines that cross stay apart), and
    with pixels along at least `MIN_COVERAGE` of their length (a chain of bright stars
    passes the tests between them, not on their cores: a new user's crowded field had a
    chain of 4 masked) and even along them (`_even`), and where at least `RIDGE_SHARE` of
    them are ridges (``ridges``: the brighter side across no brighter than the pixel; a
    trail beside a star is not, there; the light between the bright stars of a dense field,
    a saddle with a star on one side, nowhere: a new user's cluster of 440 stars above 1e5
    e- had 590 pixels masked and 12 stars flagged)."""
    joined = ndimage.binary_dilation(mask, structure=_line_structure(angle))
    labels, count = ndimage.label(joined, structure=np.ones((3, 3), dtype=bool))
    labels = np.where(mask, labels, 0)
    keep = np.zeros(count + 1, dtype=bool)
    for label, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None or np.hypot(box[0].stop - box[0].start,
                                   box[1].stop - box[1].start) < MIN_LENGTH:
            continue
        member = labels[box] == label
        rows, columns = np.nonzero(member)
        points = np.column_stack([columns + box[1].start, rows + box[0].start]).astype(float)
        centre = points.mean(axis=0)
        points -= centre
        axes = np.linalg.eigh(points.T @ points)[1]  # its own axis: a line between two
        along, across = points @ axes[:, -1], points @ axes[:, 0]  # directions tested
        extent = along.max() - along.min()
        covered = np.unique(np.floor(along - along.min())).size / (np.floor(extent) + 1.0)
        keep[label] = (extent >= MIN_LENGTH and np.std(across) <= MAX_WIDTH
                       and covered >= MIN_COVERAGE
                       and np.mean(ridges[box][member]) >= RIDGE_SHARE
                       and _even(smoothed, centre, axes[:, -1], along.min(), along.max()))
    return keep[labels]


def line_mask(image_e, threshold, *, detection_fwhm=3.0, smoothed=None, rms=None):
    """Pixels of the linear features of an image (trails, hot or bleeding columns).

    Parameters
    ----------
    image_e : ndarray [y, x]
        Sky-subtracted image, e-; non-finite pixels count as 0.
    threshold : float
        Detection threshold, RMS of the smoothed image (detection's,
        `bfpsf.measure.sources.DETECTION_THRESHOLD` by default): a line's pixels are above
        it or above `LINE_LEVEL`, the lower.
    detection_fwhm : float, optional
        FWHM of the Gaussian smoothing, pixels (default 3, as detection's).
    smoothed, rms : ndarray [y, x] and float, optional
        The image smoothed by that Gaussian and its clipped rms, where detection has them
        already (`bfpsf.measure.sources.measure_sources`); default computed here.

    Returns
    -------
    ndarray of bool [y, x]
        True on the pixels of a line and of its wings.
    """
    if smoothed is None:
        smoothed = smoothed_image(image_e, detection_fwhm)
    if rms is None:
        _, _, rms = sigma_clipped_stats(smoothed, sigma=3.0)
    mask = np.zeros(smoothed.shape, dtype=bool)
    level = min(threshold, LINE_LEVEL) * rms
    for sign in (1.0, -1.0):  # bright lines, and dark ones (a dead column)
        mask |= _lines_of(sign * smoothed, level, detection_fwhm)
    return mask


def _lines_of(smoothed, level, detection_fwhm):
    """`line_mask` of the lines brighter than their surroundings in ``smoothed``."""
    bright = smoothed >= level
    rows, columns = _bright_along(smoothed, *np.nonzero(bright))
    on_line = np.zeros((N_DIRECTIONS, rows.size), dtype=bool)
    ridge = np.zeros((N_DIRECTIONS, rows.size), dtype=bool)
    across = (np.arange(N_DIRECTIONS) + N_DIRECTIONS // 2) % N_DIRECTIONS
    for start in range(0, rows.size, _CHUNK):
        part = slice(start, start + _CHUNK)
        value = smoothed[rows[part], columns[part]]
        quartile, median = _side_levels(smoothed, rows[part], columns[part])
        along = np.min(quartile, axis=0)  # the fainter side, per direction
        beside = np.min(median, axis=0)[across]  # the fainter side across it
        on_line[:, part] = (along >= ALONG_FRACTION * value) & (beside <= ACROSS_FRACTION * value)
        # the brighter side across no brighter than the pixel: a ridge (`_long`)
        ridge[:, part] = np.max(median, axis=0)[across] <= RIDGE_FRACTION * value
    mask = np.zeros(smoothed.shape, dtype=bool)
    for direction in np.flatnonzero(on_line.any(axis=1)):
        pixels = np.zeros(smoothed.shape, dtype=bool)
        pixels[rows[on_line[direction]], columns[on_line[direction]]] = True
        ridges = np.zeros(smoothed.shape, dtype=bool)
        chosen = on_line[direction] & ridge[direction]
        ridges[rows[chosen], columns[chosen]] = True
        mask |= _long(pixels, np.pi * direction / N_DIRECTIONS, smoothed, ridges)
    if not mask.any():
        return mask
    # its wings: the pixels about it no brighter than the line beside them (a trail's edges
    # fail the tests, the image falling steeply across them; a star's core beside the line
    # is brighter than the line) and not of the other sign (a star beside a dead column)
    reach = int(np.ceil(detection_fwhm)) + 1
    grown = ndimage.binary_dilation(mask, structure=ndimage.generate_binary_structure(2, 1),
                                    iterations=reach)
    line_level = ndimage.maximum_filter(np.where(mask, smoothed, -np.inf), size=2 * reach + 1)
    return mask | (grown & (smoothed <= line_level) & (smoothed >= -level))


def resolve_lines(lines, image_e, threshold, **options):
    """The line pixels a ``lines`` option names: True finds them (`line_mask` of ``image_e``,
    with ``options``), False or None none, an array of bool [y, x] those."""
    if lines is True:
        return line_mask(image_e, threshold, **options)
    if lines is None or lines is False:
        return np.zeros(np.shape(image_e), dtype=bool)
    return np.asarray(lines, dtype=bool)


def near_lines(mask, x, y, reach):
    """Whether a pixel of ``mask`` lies within ``reach`` pixels (a number, or one per source)
    of each (x, y): ndarray of bool (False where x or y is not finite)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if not np.any(mask):
        return np.zeros(x.shape, dtype=bool)
    distance = ndimage.distance_transform_edt(~np.asarray(mask, dtype=bool))
    good = np.isfinite(x) & np.isfinite(y)
    row = np.clip(np.rint(np.where(good, y, 0)).astype(int), 0, distance.shape[0] - 1)
    column = np.clip(np.rint(np.where(good, x, 0)).astype(int), 0, distance.shape[1] - 1)
    return good & (distance[row, column] <= reach)
