"""The sky's surface over an image: a polynomial of degree 0-3, or a bicubic B-spline with knots
`SPLINE_SPACING` apart for a sky no cubic follows (scattered light). `SkyModel` holds either:
its terms at any pixels (`SkyModel.basis`, what a fit solves for), its value, its image.
Which surface an image's sky pixels ask for, and the fit, are `bfpsf.measure.sky`'s.
"""

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline

__all__ = ["SkyModel", "SPLINE", "spline_intervals"]

#: The kind of a sky surface for a sky no polynomial of degree 3 follows: a bicubic
#: B-spline (`SkyModel` ``intervals``).
SPLINE = "spline"
#: Knot spacing of the spline sky, pixels: a scattered-light patch of 140 px (a Gaussian's
#: sigma) is followed within a few % of its height; the glow of a star beyond a 25 px
#: support reaches 75 px, so the spline does not take one star's wing for sky.
SPLINE_SPACING = 128
#: Intervals of the spline along each axis, at least and at most (a 4k^2 CCD: 8, knots 512
#: px apart; its 121 coefficients keep the fits fast).
SPLINE_INTERVALS = (2, 8)


@dataclass(frozen=True)
class SkyModel:
    """A sky surface over an image, e- per pixel.

    Attributes
    ----------
    coefficients : tuple of float
        Polynomial coefficients in the normalised coordinates u = (x - xc) / s, v = (y - yc) / s
        (centre and half-size of the image), ordered 1, u, v, u^2, u v, v^2, ... (e- per pixel).
    degree : int
        Polynomial degree (0: a constant, 1: a plane).
    shape : (int, int)
        (ny, nx) of the image.
    rms : float
        Clipped scatter of the fitted pixels about the surface, e- per pixel (the sky's noise,
        read noise included).
    method : str
        ``'known'`` (given by the caller), ``'masked'`` (fitted beyond the masked sources) or
        ``'masked, wings subtracted'`` (and the stars' wings beyond the PSF support
        subtracted).
    n_pixels : int
        Pixels the fit used (0 for a known sky).
    intervals : tuple of int
        () for a polynomial; for a spline sky (``kind`` 'spline', ``degree`` 3) the
        intervals of its bicubic B-spline along y and x, evenly spaced over the image
        (`spline_intervals`), and ``coefficients`` those of its (intervals + 3)^2 basis
        functions, x running fastest.
    """

    coefficients: tuple
    degree: int
    shape: tuple
    rms: float
    method: str
    n_pixels: int = 0
    intervals: tuple = ()

    @classmethod
    def constant(cls, level, shape, *, rms=np.nan, method="known"):
        """A flat sky of ``level`` e- per pixel."""
        return cls((float(level),), 0, tuple(int(n) for n in shape), float(rms), method)

    @classmethod
    def template(cls, kind, shape, method=""):
        """A surface of ``kind`` (a degree 0-3, or 'spline') over an image of ``shape``, its
        coefficients zero: its `basis` is what a fit of that kind solves for."""
        shape = tuple(int(n) for n in shape)
        if kind == SPLINE:
            intervals = spline_intervals(shape)
            n_terms = (intervals[0] + 3) * (intervals[1] + 3)
            return cls((0.0,) * n_terms, 3, shape, np.nan, method, 0, intervals)
        return cls((0.0,) * ((kind + 1) * (kind + 2) // 2), int(kind), shape, np.nan, method)

    @property
    def kind(self):
        """'spline', or the polynomial's degree."""
        return SPLINE if self.intervals else int(self.degree)

    def _scale(self):
        ny, nx = self.shape
        return (nx - 1) / 2.0, (ny - 1) / 2.0, max(nx, ny, 2) / 2.0

    def _splines(self, x, y):
        """The B-splines along y and x at (x, y) (1-D arrays): two matrices [point, spline]."""
        return tuple(_bspline_design(coordinate, length, intervals) for coordinate, length,
                     intervals in zip((y, x), self.shape, self.intervals))

    def basis(self, x, y):
        """The surface's terms at the positions (x, y) (1-D arrays, pixels): ndarray
        [point, term], so that ``basis(x, y) @ coefficients`` is the sky there."""
        x, y = np.ravel(np.asarray(x, dtype=float)), np.ravel(np.asarray(y, dtype=float))
        if self.intervals:
            along_y, along_x = self._splines(x, y)
            return (along_y[:, :, None] * along_x[:, None, :]).reshape(x.size, -1)
        x_centre, y_centre, scale = self._scale()
        return _powers((x - x_centre) / scale, (y - y_centre) / scale, self.degree).T

    def __call__(self, x, y):
        """Sky at image positions (x, y), pixels; e- per pixel, shaped like ``x``."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        return (self.basis(x, y) @ np.asarray(self.coefficients, dtype=float)).reshape(x.shape)

    def image(self):
        """The sky on every pixel of the image, ndarray [y, x], e-."""
        if self.intervals:  # separable: B_y C B_x^T
            along_y, along_x = self._splines(np.arange(self.shape[1]), np.arange(self.shape[0]))
            grid = np.reshape(self.coefficients, (along_y.shape[1], along_x.shape[1]))
            return along_y @ grid @ along_x.T
        y, x = np.mgrid[:self.shape[0], :self.shape[1]]
        return self(x, y)

    @property
    def level(self):
        """Sky at the image's centre, e- per pixel."""
        if self.intervals:
            x_centre, y_centre, _ = self._scale()
            return float(self(x_centre, y_centre))
        return float(self.coefficients[0])

    @property
    def coefficients_of(self):
        """What ``coefficients`` multiply, in words (u, v of the image's centre and scale)."""
        if self.intervals:
            return (f"bicubic B-splines, {self.intervals[0]} x {self.intervals[1]} even "
                    "intervals over the image's y and x, x running fastest")
        x_centre, y_centre, scale = self._scale()
        return (f"powers of (x - {x_centre:g}) / {scale:g} and (y - {y_centre:g}) / "
                f"{scale:g}")

    @property
    def slope(self):
        """(d sky / dx, d sky / dy) at the image's centre (a polynomial's linear terms), e-
        per pixel per pixel."""
        if self.intervals:
            x_centre, y_centre, _ = self._scale()
            return (float(self(x_centre + 0.5, y_centre) - self(x_centre - 0.5, y_centre)),
                    float(self(x_centre, y_centre + 0.5) - self(x_centre, y_centre - 0.5)))
        if self.degree < 1:
            return 0.0, 0.0
        scale = self._scale()[2]
        return float(self.coefficients[1]) / scale, float(self.coefficients[2]) / scale


def spline_intervals(shape):
    """The spline sky's intervals along y and x of an image of ``shape``: its length over
    `SPLINE_SPACING`, within `SPLINE_INTERVALS`."""
    low, high = SPLINE_INTERVALS
    return tuple(int(np.clip(round(length / SPLINE_SPACING), low, high)) for length in shape)


def _bspline_design(coordinate, length, intervals):
    """The cubic B-splines on ``intervals`` even intervals over pixels -0.5 .. length - 0.5
    (clamped at the ends; beyond them the edge's value), at ``coordinate``: [point, spline]."""
    edges = np.linspace(-0.5, length - 0.5, intervals + 1)
    knots = np.concatenate([[edges[0]] * 3, edges, [edges[-1]] * 3])
    coordinate = np.ravel(coordinate).astype(float)
    finite = np.isfinite(coordinate)  # a failed fit's position: NaN, as a polynomial gives
    inside = np.clip(np.where(finite, coordinate, 0.0), edges[0], edges[-1])
    design = BSpline.design_matrix(inside, knots, 3).toarray()
    design[~finite] = np.nan
    return design


def _powers(u, v, degree):
    """Monomials 1, u, v, u^2, u v, v^2, ... up to ``degree``, stacked on a first axis."""
    terms = [u**(order - k) * v**k for order in range(degree + 1) for k in range(order + 1)]
    return np.stack([np.broadcast_to(term, np.shape(u)) for term in terms])
