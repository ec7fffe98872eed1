"""The EMPIRICAL term's pixel-space patterns B_k (`bfpsf.model.empirical`): what each adds
to a star, in several kinds, with their series along the BF term for P(F)'s table mode.

Each pattern is charge-conserving and centroid-preserving, and adds F pixel^2 to the second
moment along its axis (B_xx, B_yy; half the difference of the two diagonals, B_xy, to Mxy
alone) of any star of flux F. The kinds: the half second difference D of the squared charge
(a transfer of a fraction of each pixel's charge proportional to that charge), of the
charge itself (a smear whose variance grows with the star's flux) and of the cubed charge
(a transfer the brightest pixels make more than in proportion). Each moves charge to the
nearest pixels; the squared and the cubed charge also to a Gaussian reach of pixels
(`REACHES`: a halo of the brightest pixels).
"""

import functools

import numpy as np
from scipy import ndimage

from ..errors import BFPSFValueError

__all__ = ["PATTERNS", "FLUX_REFERENCE", "PATTERN_KIND", "CHARGE_KIND", "CUBE_KIND",
           "PATTERN_KINDS", "REACHES", "broad_kind", "power_and_reach", "apply_pattern",
           "pattern_series", "pattern_tables"]

#: The pixel-space patterns, in the order of `EmpiricalTerm.variance_change`.
PATTERNS = ("xx", "yy", "xy")
#: Reference total flux of the coefficients, e-.
FLUX_REFERENCE = 1e6
#: The pattern's name in a term's record (`EmpiricalTerm.to_dict`): a record without it, or
#: with another, was fitted with another pattern and its coefficients do not apply. The
#: default, B_k[I] = D[I^2] F / sum(I^2): a transfer of a fraction of each pixel's charge
#: proportional to that charge.
PATTERN_KIND = "half second difference of the squared charge"
#: The other: B_k[I] = D[I] F / sum(I), a smear whose variance grows with the star's flux
#: (three new users' undeclared effects; with the square, their PSF photometry drifted by
#: +0.6 to +1.2 mmag faint to bright, P0 taking what the square's shape missed).
CHARGE_KIND = "half second difference of the charge"
#: Reaches (pixels, the Gaussian's sigma) of the broad kinds, of the squared and the cubed
#: charge: every pixel passes its share to the pixels along the pattern's axis with Gaussian
#: weights, and B_xx + B_yy is an isotropic Gaussian blur (a halo) less the charge it takes.
#: Spaced by factors of two, so that a halo of any width from 1.4 to 11 px is within a
#: factor 1.4 of one of them. (A broad transfer of the charge itself, a halo whose share
#: grows with the star's flux alone, was never kept on the bench nor on a new user's halo,
#: and each kind costs `bfpsf diagnose` a PSF fit per held-out exposure.)
REACHES = (2.0, 4.0, 8.0)


def broad_kind(kind, reach):
    """The name of the broad kind of ``reach`` of ``kind``'s function (`PATTERN_KIND`'s
    squared charge, `CHARGE_KIND`'s charge)."""
    return f"Gaussian transfer of the {kind.split(' of the ')[-1]}, reach {reach:g} px"


#: The cubed charge's transfer to the nearest pixels: a transfer that the brightest pixels
#: of a star make more than in proportion to their charge (a threshold).
CUBE_KIND = "half second difference of the cubed charge"
#: Every kind: (the power of the charge it moves; the reach, None for the nearest pixels).
_KINDS = {PATTERN_KIND: (2, None), CHARGE_KIND: (1, None), CUBE_KIND: (3, None),
          **{broad_kind(kind, reach): (power, reach)
             for kind, power in ((PATTERN_KIND, 2), (CUBE_KIND, 3)) for reach in REACHES}}
#: Every pattern kind a term may have; `bfpsf diagnose` keeps the one whose P(F) fits the
#: held-out stars best (`bfpsf.diagnosis.pattern_choice`).
PATTERN_KINDS = tuple(_KINDS)


def power_and_reach(kind):
    """(the power of the charge a pattern kind moves, its Gaussian reach in pixels or None
    for the nearest pixels); an unknown kind is refused."""
    if kind not in _KINDS:
        msg = f"pattern kind must be one of {PATTERN_KINDS}, got {kind!r}"
        raise BFPSFValueError(msg, kind)
    return _KINDS[kind]


#: The transfers of each pattern: (step (dy, dx), weight). Along X, along Y, and half the
#: difference of the two diagonals, which changes Mxy alone.
_STEPS = {"xx": (((0, 1), 1.0),), "yy": (((1, 0), 1.0),),
          "xy": (((1, 1), 0.5), ((1, -1), -0.5))}


def _transfer(image, step, weights=((1, 0.5),)):
    """sum over k, s = +-1 of w_k (I[p + s k step] - I[p]), ``weights`` the (k, w_k) pairs,
    over the pairs of pixels both inside the image: each pixel passes w_k of its value to
    each pixel k steps away along ``step`` (dy, dx) and none across the stamp's edge, so the
    sum is conserved exactly. The default, the half second difference, is along X
    1/2 (I[i+1] - 2 I[i] + I[i-1]) with the image extended by its edge pixels; with
    sum 2 k^2 w_k = 1 every transfer adds the image's sum to sum (x - x0)^2 I along it.
    Along a row or a column it is one correlation with the weights (zero beyond the edge)
    less each pixel times the weight of its neighbours inside; along a diagonal, the sum of
    the shifted differences."""
    ny, nx = image.shape[-2:]
    if not (step[0] and step[1]):
        kernel, inside = _line_kernel(weights, ny if step[0] else nx)
        return (ndimage.correlate1d(image, kernel, axis=-2 if step[0] else -1, mode="constant")
                - image * (inside[:, None] if step[0] else inside))
    out = np.zeros_like(image)
    for distance, weight in weights:
        if distance >= min(ny, nx):
            break  # no pair of pixels this far apart in the image (distances rise)
        for sign in (distance, -distance):
            (rows, neighbour_rows), (columns, neighbour_columns) = (
                _ranges(sign * step[0], ny), _ranges(sign * step[1], nx))
            out[..., rows, columns] += weight * (image[..., neighbour_rows, neighbour_columns]
                                                 - image[..., rows, columns])
    return out


def _ranges(shift, n):
    """Slices of the pixels p and of their neighbours p + shift that are both inside."""
    if shift >= 0:
        return slice(0, n - shift), slice(shift, n)
    return slice(-shift, n), slice(0, n + shift)


@functools.lru_cache(maxsize=64)
def _line_kernel(weights, n):
    """The symmetric kernel of ``weights`` (`_transfer`) along a line of ``n`` pixels, and
    the weight of each pixel's neighbours inside the line."""
    half = min(max(distance for distance, _ in weights), n - 1)
    kernel = np.zeros(2 * half + 1)
    for distance, weight in weights:
        if distance <= half:
            kernel[half + distance] = kernel[half - distance] = weight
    return kernel, ndimage.correlate1d(np.ones(n), kernel, mode="constant")


@functools.lru_cache(maxsize=None)
def _gaussian_weights(reach):
    """(k, w_k) of a discrete Gaussian of sigma ``reach`` out to 3 sigma, less the charge it
    keeps, per unit variance (`_transfer` adds the image's sum to the variance along its
    step), and that variance, v: I + v T is the Gaussian's blur."""
    distances = np.arange(1, int(np.ceil(3.0 * reach)) + 1)
    kernel = np.exp(-0.5 * (distances / reach) ** 2)
    total = 1.0 + 2.0 * kernel.sum()
    variance = 2.0 * (kernel * distances ** 2).sum() / total
    return tuple(zip(distances.tolist(), (kernel / total / variance).tolist())), variance


def _steps(pattern):
    """The transfers of ``pattern`` (`_STEPS`); an unknown pattern is refused."""
    steps = _STEPS.get(pattern)
    if steps is None:
        msg = f"pattern must be one of {PATTERNS}, got {pattern!r}"
        raise BFPSFValueError(msg, pattern)
    return steps


def _difference(image, pattern, reach=None):
    """The pattern's transfer operator on ``image`` (`_STEPS`): to the nearest pixels, or
    (``reach``) with Gaussian weights, where B_xx = T_x + v/2 T_x T_y (and B_yy the same
    along y), so that B_xx + B_yy = (G_x G_y - 1) / v, a round Gaussian blur less the charge
    it takes, and B_xx adds to sum x^2 I alone; along the diagonals B_xy has the weights of
    the Gaussian along them."""
    if reach is None:
        return sum(weight * _transfer(image, step) for step, weight in _steps(pattern))
    weights, variance = _gaussian_weights(reach)
    if pattern == "xy":
        return sum(sign * _transfer(image, step, weights) for step, sign in _steps(pattern))
    (step, _), = _steps(pattern)
    along = _transfer(image, step, weights)
    return along + 0.5 * variance * _transfer(_transfer(image, (0, 1), weights), (1, 0),
                                              weights)


def _star_total(image, total):
    """The star's total flux, shaped to divide a stack [..., y, x]: ``total`` (scalar or one
    per image) or, without it, the image's sum."""
    if total is None:
        return image.sum(axis=(-2, -1), keepdims=True)
    return np.reshape(np.asarray(total, float), np.shape(total) + (1, 1))


def apply_pattern(image, pattern, total=None, kind=PATTERN_KIND):
    """B_k[image] (module docstring): the half three-point second difference of the squared
    charge (negative pixels taken as 0) along x ('xx'), y ('yy') or half the difference of
    the two diagonals ('xy'), times F / sum(I^2).

    It conserves the flux exactly, and for a star that fits in the stamp it leaves the
    centroid unchanged and adds F to sum (x - x0)^2 I ('xx'; 'yy' along y; 'xy' to
    sum (x - x0)(y - y0) I alone): B_k[lambda I] = lambda B_k[I].
    ``total`` is the star's flux F in the image's unit (one per image of a stack [..., y, x];
    default the image's sum): a stamp that cuts the star's wings keeps the same pattern,
    since sum(I^2) is all in the core. ``image`` may be a stack [..., y, x] (each image on its
    own). ``kind`` `CHARGE_KIND`: the same of the charge itself, times F / sum(I).
    """
    return pattern_series(image, 0.0, pattern, total, order=0, kind=kind)[0]


def pattern_series(image, change, pattern, total=None, total_change=0.0, order=2,
                   kind=PATTERN_KIND):
    """B_k[I + e dI] = B0 + e B1 + e^2 B2 + O(e^3): (B0, B1, B2) at ``image`` along
    ``change``, the star's flux F + e dF (``total``, default the image's sum, and
    ``total_change``, default the change's sum when ``total`` is None, else 0); the terms
    up to ``order`` only (0, 1 or 2).

    With (I + e dI)^n = a0 + e a1 + e^2 a2 (a0 = I^n, a1 = n I^(n-1) dI, a2 = n (n - 1) / 2
    I^(n-2) dI^2, where I > 0; n the kind's power of the charge: 2 for `PATTERN_KIND`, 1 for
    `CHARGE_KIND`) and D the kind's transfer, the pattern is D[(I + e dI)^n] s(e),
    s = (F + e dF) / sum((I + e dI)^n), so each B_n collects the D[a_m] with the
    coefficients of s's series. The table mode of P(F) tabulates them for dI = R, the BF
    term (`pattern_tables`); the PSF fit's flux derivative is B1 along d model / d F."""
    image = np.asarray(image, float)
    _steps(pattern)
    power, reach = power_and_reach(kind)
    positive = np.clip(image, 0.0, None)
    change = np.where(image > 0, np.asarray(change, float), 0.0)
    if total is None:
        s1, d1 = _star_total(image, None), _star_total(change, None)
    else:
        s1, d1 = _star_total(image, total), _star_total(image, total_change)
    # (I + e dI)^n = a0 + e a1 + e^2 a2 + O(e^3), where I > 0 (dI is 0 elsewhere)
    safe = np.where(positive > 0, positive, 1.0)
    parts = (positive ** power, power * safe ** (power - 1) * change,
             power * (power - 1) / 2 * safe ** (power - 2) * change ** 2)
    s0, s_1, s_2 = (part.sum(axis=(-2, -1), keepdims=True) for part in parts)
    s0 = np.where(s0 > 0, s0, np.inf)  # an image with no positive pixel: no pattern
    # s(e) = (s1 + e d1) / (s0 + e s_1 + e^2 s_2), to second order in e
    scale = (s1 / s0, d1 / s0 - s1 * s_1 / s0 ** 2,
             (s1 * s_1 ** 2 / s0 - s1 * s_2 - d1 * s_1) / s0 ** 2)
    terms = [_difference(parts[0], pattern, reach)]
    series = [terms[0] * scale[0]]
    if order >= 1:
        terms.append(_difference(parts[1], pattern, reach))
        series.append(terms[1] * scale[0] + terms[0] * scale[1])
    if order >= 2:
        terms.append(_difference(parts[2], pattern, reach))
        series.append(terms[2] * scale[0] + terms[1] * scale[1] + terms[0] * scale[2])
    return tuple(series)


def pattern_tables(data, bf_data, oversampling, kind=PATTERN_KIND):
    """B_k at every sub-pixel phase of an oversampled P0 and its series along R:
    {pattern: (B0, B1, B2) tables} (`pattern_series`), each phase ``data[a::oy, b::ox]`` (the
    pixelised unit star p at that phase, r its BF term) as a star image gets it. The table
    mode of `bfpsf.model.psf.FluxDependentPSF` interpolates F (B0 + e B1 + e^2 B2), e = g |F|,
    which is B_k[F p + g F |F| r] to second order in the BF term, as its exact mode and
    ``star_image`` compute it (they agree to 1e-6 of the peak at 6e5 e-, 2e-5 at 1.2e6 e-)."""
    oy, ox = (int(value) for value in oversampling)
    data, bf_data = np.asarray(data, float), np.asarray(bf_data, float)
    tables = {}
    for pattern in PATTERNS:
        series = tuple(np.zeros_like(data) for _ in range(3))
        for a in range(oy):
            for b in range(ox):
                # a unit star (R moves charge, it adds none)
                phase = pattern_series(data[a::oy, b::ox], bf_data[a::oy, b::ox], pattern,
                                       total=1.0, kind=kind)
                for table, part in zip(series, phase):
                    table[a::oy, b::ox] = part
        tables[pattern] = series
    return tables
