"""The odd (centroid- and skew-like) part of stars: third moments under the adaptive weight.

Brighter-fatter and every catalogue effect are even under reflection of a symmetric star, so a
skewness that changes with flux is the signature of something else (a charge trail, a
flux-dependent centroid shift); `bfpsf.diagnosis.signature.parity_test` tests it.
"""

from types import SimpleNamespace

import numpy as np

__all__ = ["skewness", "star_skewness"]


def skewness(stamps, moments):
    """Third standardised moments along X and Y under the adaptive Gaussian weight.

    skew_x = sum w I (x - x0)^3 / (sum w I) / Mxx^(3/2), w the elliptical Gaussian of the
    adaptive moments; zero for a profile symmetric under x -> -x about its centroid, so it
    measures the odd (centroid- and skew-like) part of a star. Dimensionless.
    """
    n, ny, nx = stamps.shape
    y, x = np.mgrid[:ny, :nx].astype(float)
    dx = x[None] - np.asarray(moments.x)[:, None, None]
    dy = y[None] - np.asarray(moments.y)[:, None, None]
    mxx, myy, mxy = (np.asarray(v)[:, None, None] for v in (moments.mxx, moments.myy,
                                                             moments.mxy))
    det = mxx * myy - mxy ** 2
    weight = np.exp(-0.5 * (myy * dx ** 2 - 2 * mxy * dx * dy + mxx * dy ** 2) / det)
    total = np.sum(weight * stamps, axis=(1, 2))
    skew_x = np.sum(weight * stamps * dx ** 3, axis=(1, 2)) / total / mxx[:, 0, 0] ** 1.5
    skew_y = np.sum(weight * stamps * dy ** 3, axis=(1, 2)) / total / myy[:, 0, 0] ** 1.5
    return skew_x, skew_y


def star_skewness(image, table, *, half_size=7):
    """`skewness` of the stars of a `bfpsf.measure.sources.measure_sources` table.

    Parameters
    ----------
    image : ndarray [y, x]
        Background-subtracted image, e-.
    table : astropy Table
        ``x``, ``y``, ``mxx``, ``myy``, ``mxy`` of each star (0-based pixels, pixel^2).
    half_size : int
        Stamps of 2 half_size + 1 pixels around each star.

    Returns
    -------
    (ndarray, ndarray)
        skew_x, skew_y per row; NaN for stars too close to the edge or without moments.
    """
    image = np.asarray(image, float)
    ny, nx = image.shape
    n = len(table)
    out = np.full((2, n), np.nan)
    x, y = (np.asarray(table[name], float) for name in ("x", "y"))
    moments = {name: np.asarray(table[name], float) for name in ("mxx", "myy", "mxy")}
    for row in range(n):
        if not (np.isfinite(x[row]) and np.isfinite(y[row]) and moments["mxx"][row] > 0):
            continue
        cx, cy = int(np.round(x[row])), int(np.round(y[row]))
        if cx - half_size < 0 or cy - half_size < 0 or cx + half_size >= nx \
                or cy + half_size >= ny:
            continue
        stamp = image[cy - half_size:cy + half_size + 1, cx - half_size:cx + half_size + 1]
        local = SimpleNamespace(x=[x[row] - cx + half_size], y=[y[row] - cy + half_size],
                                **{name: [value[row]] for name, value in moments.items()})
        skew_x, skew_y = skewness(stamp[None], local)
        out[:, row] = skew_x[0], skew_y[0]
    return out[0], out[1]
