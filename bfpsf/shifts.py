"""Pixel-boundary shift coefficients a^X(dx, dy): the contract between calibration and model.

Conventions (G15 section 5.2, eq. def-a):

* Source offsets are ``(dx, dy)`` relative to the pixel (0, 0) whose boundaries move; arrays are
  indexed ``[dy + m, dx + m]`` on a square grid of offsets ``-m..m``.
* Boundaries of pixel (0, 0): N is shared with (0, +1), S with (0, -1), E with (+1, 0),
  W with (-1, 0).
* ``a^X(dx, dy)`` is the displacement of boundary X, in pixel units, per electron in pixel
  (dx, dy) at the end of the exposure, positive outward (pixel (0, 0) grows).

Only N and E are independent. Translation invariance (G15 eq. trans) gives
``a^S(dx, dy) = -a^N(dx, dy + 1)`` and ``a^W(dx, dy) = -a^E(dx + 1, dy)``; parity (G15 eq. par)
``a^X(dx, dy) = a^{-X}(-dx, -dy)`` then says that N is antisymmetric about the centre of the
boundary, ``a^N(dx, dy) = -a^N(-dx, 1 - dy)``, and likewise ``a^E(dx, dy) = -a^E(1 - dx, -dy)``.
The sum rule (G15 eq. sum-rule) is ``sum a^X = 0`` for every X. The area coefficient measured by
flat-field covariances (G15 eq. covar) is ``a(dx, dy) = sum_X a^X(dx, dy)``, a discrete
divergence of the boundary-shift field.
"""

import numpy as np

from .errors import BFPSFValueError

__all__ = ["BoundaryShifts", "BOUNDARIES", "as_shifts"]

#: Boundary labels and the (dx, dy) of the neighbour that shares each boundary with (0, 0).
BOUNDARIES = {"N": (0, 1), "S": (0, -1), "E": (1, 0), "W": (-1, 0)}


def _validate_grid(array, name):
    array = np.array(array, dtype=float)
    if array.ndim != 2 or array.shape[0] != array.shape[1] or array.shape[0] % 2 != 1:
        msg = f"{name} must be a square 2-D array of odd size (offsets -m..m), got shape {array.shape}"
        raise BFPSFValueError(msg, array.shape)
    if not np.all(np.isfinite(array)):
        msg = f"{name} contains {np.count_nonzero(~np.isfinite(array))} non-finite values"
        raise BFPSFValueError(msg)
    array.flags.writeable = False
    return array


def _radial(profile, tangential, normal):
    """-f(r) cos(theta) for a boundary seen at (tangential, normal) from the source."""
    r = np.hypot(tangential, normal)
    return -np.asarray(profile(r), dtype=float) * normal / r


class BoundaryShifts:
    """Boundary-shift coefficients a^N and a^E (1/e-), from which a^S, a^W and a follow.

    Parameters
    ----------
    north, east : array_like, shape (2m+1, 2m+1)
        a^N(dx, dy) and a^E(dx, dy) in pixels per electron, indexed ``[dy + m, dx + m]``.
        The outermost row of ``north`` at dy = -m and column of ``east`` at dx = -m must be
        zero: parity maps them outside the grid.
    check : bool, optional
        Raise `~bfpsf.errors.BFPSFValueError` if parity is violated by more than ``rtol``
        times the largest coefficient. Default True.
    rtol : float, optional
        Tolerance of the parity check. Default 1e-9.

    Notes
    -----
    Objects are immutable: the arrays are read-only copies.
    """

    __slots__ = ("_north", "_east")

    def __init__(self, north, east, *, check=True, rtol=1e-9):
        north = _validate_grid(north, "north")
        east = _validate_grid(east, "east")
        if north.shape != east.shape:
            msg = f"north and east must have the same shape, got {north.shape} and {east.shape}"
            raise BFPSFValueError(msg)
        self._north = north
        self._east = east
        if check:
            scale = max(np.abs(north).max(), np.abs(east).max(), 1e-300)
            worst = max(self.symmetry_residuals()[key] for key in ("parity_N", "parity_E"))
            if worst > rtol * scale:
                msg = (f"boundary shifts violate parity a^X(dx,dy) = a^-X(-dx,-dy) by {worst:.3g} "
                       f"(largest coefficient {scale:.3g})")
                raise BFPSFValueError(msg, worst)

    @classmethod
    def from_radial_profile(cls, profile, radius):
        """Shifts of the G15 smoothing form a^X(dx, dy) = -f(r) cos(theta), exactly symmetric.

        Parameters
        ----------
        profile : callable
            f(r), r in pixels from the source pixel centre to the centre of the boundary; f > 0
            means charge repels charge (a^N(0, 0) < 0, the charged pixel shrinks).
        radius : int
            Offsets -radius..radius. The row of a^N at dy = -radius and the column of a^E at
            dx = -radius are set to zero so that parity and the sum rule hold exactly.

        Notes
        -----
        theta is the angle between the vector from the source to the boundary centre and the
        outward normal of the boundary (G15 section 6.1, eq. f_r).
        """
        grid = np.arange(-radius, radius + 1, dtype=float)
        dy, dx = np.meshgrid(grid, grid, indexing="ij")
        # North boundary centre at (0, 1/2), outward normal +y; east at (1/2, 0), normal +x.
        north = _radial(profile, -dx, 0.5 - dy)
        east = _radial(profile, -dy, 0.5 - dx)
        north[0, :] = 0.0
        east[:, 0] = 0.0
        return cls(north, east)

    # -- the grid ------------------------------------------------------------------------------
    @property
    def radius(self):
        """m: offsets run from -m to m."""
        return self._north.shape[0] // 2

    @property
    def shape(self):
        return self._north.shape

    def offsets(self):
        """Return (dx, dy) integer grids of the source offsets, each shaped like the arrays."""
        m = self.radius
        dy, dx = np.mgrid[-m:m + 1, -m:m + 1]
        return dx, dy

    # -- the four boundaries -------------------------------------------------------------------
    @property
    def north(self):
        """a^N(dx, dy), 1/e-, indexed [dy + m, dx + m]."""
        return self._north

    @property
    def east(self):
        """a^E(dx, dy), 1/e-, indexed [dy + m, dx + m]."""
        return self._east

    @property
    def south(self):
        """a^S(dx, dy) = -a^N(dx, dy + 1) (translation invariance)."""
        south = np.zeros_like(self._north)
        south[:-1, :] = -self._north[1:, :]
        return south

    @property
    def west(self):
        """a^W(dx, dy) = -a^E(dx + 1, dy) (translation invariance)."""
        west = np.zeros_like(self._east)
        west[:, :-1] = -self._east[:, 1:]
        return west

    def boundary(self, label):
        """a^X for X in 'N', 'S', 'E', 'W'."""
        try:
            return {"N": self.north, "S": self.south, "E": self.east, "W": self.west}[label]
        except KeyError:
            msg = f"boundary label must be one of N, S, E, W, got {label!r}"
            raise BFPSFValueError(msg, label) from None

    @property
    def area(self):
        """Area coefficient a(dx, dy) = sum_X a^X(dx, dy), 1/e-, indexed [dy + m, dx + m]."""
        return self.north + self.south + self.east + self.west

    def area_quadrant(self, maxlag=None):
        """a(dx, dy) for dx, dy = 0..maxlag, indexed [dy, dx] (the table the flats measure)."""
        m = self.radius
        maxlag = m if maxlag is None else int(maxlag)
        if not 0 <= maxlag <= m:
            msg = f"maxlag must be between 0 and {m}, got {maxlag}"
            raise BFPSFValueError(msg, maxlag)
        return self.area[m:m + maxlag + 1, m:m + maxlag + 1].copy()

    # -- checks and transforms -----------------------------------------------------------------
    def symmetry_residuals(self):
        """Largest violation of each symmetry, in 1/e-.

        Returns
        -------
        dict
            ``parity_N``: max |a^N(dx,dy) + a^N(-dx,1-dy)|; ``parity_E``: max
            |a^E(dx,dy) + a^E(1-dx,-dy)|; ``sum_N``, ``sum_E``, ``sum_S``, ``sum_W``: |sum a^X|
            (G15 sum rule); ``sum_area``: |sum a|. Translation holds by construction.
        """
        north, east = self._north, self._east
        # a^N(-dx, 1-dy): flip both axes, then shift one row (dy -> dy - 1 in the flipped grid).
        mirrored_north = np.zeros_like(north)
        mirrored_north[1:, :] = north[::-1, ::-1][:-1, :]
        mirrored_east = np.zeros_like(east)
        mirrored_east[:, 1:] = east[::-1, ::-1][:, :-1]
        return {
            "parity_N": float(np.abs(north + mirrored_north).max()),
            "parity_E": float(np.abs(east + mirrored_east).max()),
            "sum_N": abs(float(north.sum())),
            "sum_S": abs(float(self.south.sum())),
            "sum_E": abs(float(east.sum())),
            "sum_W": abs(float(self.west.sum())),
            "sum_area": abs(float(self.area.sum())),
        }

    def scaled(self, factor):
        """Return a new object with every coefficient multiplied by ``factor``."""
        return BoundaryShifts(self._north * factor, self._east * factor, check=False)

    def padded(self, radius):
        """Return the same shifts on a larger grid of offsets -radius..radius (zeros outside)."""
        m = self.radius
        if radius < m:
            msg = f"radius must be at least the current radius {m}, got {radius}"
            raise BFPSFValueError(msg, radius)
        pad = radius - m
        return BoundaryShifts(np.pad(self._north, pad), np.pad(self._east, pad), check=False)

    def __eq__(self, other):
        if not isinstance(other, BoundaryShifts):
            return NotImplemented
        return (self.shape == other.shape and np.array_equal(self._north, other._north)
                and np.array_equal(self._east, other._east))

    __hash__ = None

    def __repr__(self):
        m = self.radius
        return (f"BoundaryShifts(radius={m}, a00={self.area[m, m]:.4g}, "
                f"aN(0,0)={self._north[m, m]:.4g}, aE(0,0)={self._east[m, m]:.4g})")


def as_shifts(shifts):
    """Accept a BoundaryShifts or anything carrying one in ``.shifts`` (a Calibration)."""
    if isinstance(shifts, BoundaryShifts):
        return shifts
    inner = getattr(shifts, "shifts", None)
    if isinstance(inner, BoundaryShifts):
        return inner
    msg = f"expected BoundaryShifts or an object with a .shifts attribute, got {type(shifts).__name__}"
    raise BFPSFValueError(msg, shifts)
