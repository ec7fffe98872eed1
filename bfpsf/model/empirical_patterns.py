"""The EMPIRICAL term's pixel-space patterns B_k (`bfpsf.model.empirical`): what each adds
to a star, in two kinds, with their series along the BF term for P(F)'s table mode.

Each pattern is charge-conserving and centroid-preserving, and adds F pixel^2 to the second
moment along its axis (B_xx, B_yy; half the difference of the two diagonals, B_xy, to Mxy
alone) of any star of flux F. The kinds: the half second difference D of the squared charge
(a transfer of a fraction of each pixel's charge proportional to that charge), and of the
charge itself (a smear whose variance grows with the star's flux).
"""

import numpy as np

from ..errors import BFPSFValueError

__all__ = ["PATTERNS", "FLUX_REFERENCE", "PATTERN_KIND", "CHARGE_KIND", "PATTERN_KINDS",
           "apply_pattern", "pattern_series", "pattern_tables"]

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
#: Every pattern kind a term may have; `bfpsf diagnose` keeps the one whose held-out star
#: residual is the lower (`bfpsf.cli.diagnose`).
PATTERN_KINDS = (PATTERN_KIND, CHARGE_KIND)


#: The transfers of each pattern: (step (dy, dx), weight). Along X, along Y, and half the
#: difference of the two diagonals, which changes Mxy alone.
_STEPS = {"xx": (((0, 1), 1.0),), "yy": (((1, 0), 1.0),),
          "xy": (((1, 1), 0.5), ((1, -1), -0.5))}


def _ranges(shift, n):
    """Slices of the pixels p and of their neighbours p + shift that are both inside."""
    if shift >= 0:
        return slice(0, n - shift), slice(shift, n)
    return slice(-shift, n), slice(0, n + shift)


def _half_second_difference(image, step):
    """1/2 sum over s = +-1 of (I[p + s step] - I[p]), over the neighbours inside the image:
    each pixel passes half of its value to each neighbour along ``step`` (dy, dx) and none
    across the stamp's edge, so the sum is conserved exactly. Along X this is
    1/2 (I[i+1] - 2 I[i] + I[i-1]) with the image extended by its edge pixels."""
    out = np.zeros_like(image)
    ny, nx = image.shape[-2:]
    for sign in (1, -1):
        (rows, neighbour_rows), (columns, neighbour_columns) = (
            _ranges(sign * step[0], ny), _ranges(sign * step[1], nx))
        out[..., rows, columns] += 0.5 * (image[..., neighbour_rows, neighbour_columns]
                                          - image[..., rows, columns])
    return out


def _steps(pattern):
    """The transfers of ``pattern`` (`_STEPS`); an unknown pattern is refused."""
    steps = _STEPS.get(pattern)
    if steps is None:
        msg = f"pattern must be one of {PATTERNS}, got {pattern!r}"
        raise BFPSFValueError(msg, pattern)
    return steps


def _difference(image, pattern):
    """The pattern's transfer operator on ``image`` (`_STEPS`)."""
    return sum(weight * _half_second_difference(image, step)
               for step, weight in _steps(pattern))


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

    With (I + e dI)^2 = q0 + 2 e q1 + e^2 q2 (q0 = I^2, q1 = I dI, q2 = dI^2, where I > 0)
    and D the half second difference, the pattern is D[(I + e dI)^2] s(e), s = (F + e dF) /
    sum((I + e dI)^2), so each B_n collects the D[q_m] with the coefficients of s's series.
    The table mode of P(F) tabulates them for dI = R, the BF term (`pattern_tables`); the
    PSF fit's flux derivative is B1 along d model / d F. With ``kind`` `CHARGE_KIND`, the
    same of D[I + e dI] (F + e dF) / sum(I + e dI)."""
    image = np.asarray(image, float)
    _steps(pattern)
    if kind not in PATTERN_KINDS:
        msg = f"pattern kind must be one of {PATTERN_KINDS}, got {kind!r}"
        raise BFPSFValueError(msg, kind)
    positive = np.clip(image, 0.0, None)
    change = np.where(image > 0, np.asarray(change, float), 0.0)
    if total is None:
        s1, d1 = _star_total(image, None), _star_total(change, None)
    else:
        s1, d1 = _star_total(image, total), _star_total(image, total_change)
    if kind == CHARGE_KIND:
        return _charge_series(positive, change, pattern, s1, d1, order)
    s2, d12, d22 = (value.sum(axis=(-2, -1), keepdims=True)
                    for value in (positive ** 2, positive * change, change ** 2))
    s2 = np.where(s2 > 0, s2, np.inf)  # an image with no positive pixel: no pattern
    # s(e) = (s1 + e d1) / (s2 + 2 e d12 + e^2 d22), to second order in e
    scale = (s1 / s2, d1 / s2 - 2 * s1 * d12 / s2 ** 2,
             (4 * s1 * d12 ** 2 / s2 - s1 * d22 - 2 * d1 * d12) / s2 ** 2)
    d0 = _difference(positive ** 2, pattern)
    series = [d0 * scale[0]]
    if order >= 1:
        d_mixed = _difference(positive * change, pattern)
        series.append(2 * d_mixed * scale[0] + d0 * scale[1])
    if order >= 2:
        d2 = _difference(change ** 2, pattern)
        series.append(d2 * scale[0] + 2 * d_mixed * scale[1] + d0 * scale[2])
    return tuple(series)


def _charge_series(positive, change, pattern, s1, d1, order):
    """`pattern_series` of `CHARGE_KIND`: D[I + e dI] s(e), s = (s1 + e d1) / sum(I + e dI),
    to second order in e."""
    s2, d2 = (value.sum(axis=(-2, -1), keepdims=True) for value in (positive, change))
    s2 = np.where(s2 > 0, s2, np.inf)  # an image with no positive pixel: no pattern
    scale = (s1 / s2, d1 / s2 - s1 * d2 / s2 ** 2, (s1 * d2 ** 2 / s2 - d1 * d2) / s2 ** 2)
    d0 = _difference(positive, pattern)
    series = [d0 * scale[0]]
    if order >= 1:
        d_change = _difference(change, pattern)
        series.append(d_change * scale[0] + d0 * scale[1])
    if order >= 2:
        series.append(d_change * scale[1] + d0 * scale[2])
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
