"""Boundary shifts from an electrostatic model of the sensor (Astier & Regnault 2023).

The flats measure the area coefficients a(dx, dy) = sum_X a^X(dx, dy) (G15 eq. covar). How
a(0, 0) splits between the N/S and the E/W boundaries is, to first order, invisible to them:
moving the N and S boundaries of a pixel in and the E and W ones out by the same amount
changes no area. G15's Ei smoothing model fixes that split from the far lags' radial profile,
which finite flats measure poorly. This module fixes it with physics instead, as Astier &
Regnault (2023, A&A 670, A118; the model behind LSST cp_pipe's
``ElectrostaticBrighterFatterSolveTask``) do:

* The collected charge is a uniform rectangular sheet of half-sizes (``half_width_x``,
  ``half_width_y``) at height ``charge_height`` above the clock (gate) plane, in a sensor of
  ``thickness``. Both faces are held at fixed potential, so the sheet has image charges of
  alternating sign at ``2 n t +- z_q`` for every integer n (the method of images).
* An electron converted at the entrance face (z = t) drifts to the collection plane. The
  transverse field of the collected charge deflects it; with a uniform drift field the
  deflection is proportional to the transverse field integrated along z. It is integrated from
  the entrance face down to the height at which the pixel boundaries are fixed by the clock
  potentials: ``horizontal_height`` for the N/S boundaries (fixed by the parallel clocks) and
  ``vertical_height`` for the E/W ones (the channel stops), which need not be equal. That
  difference, with the aspect ratio of the charge sheet, is what sets the N/E split.
* A boundary moves by minus the mean deflection of the electrons that reach it, averaged along
  the boundary (Gauss-Legendre), times one overall amplitude ``alpha`` (1 / (epsilon E_drift),
  which is fitted rather than computed).

All lengths are in pixels. The shifts are positive outward and in pixels per electron, as
everywhere in bfpsf (`bfpsf.shifts`); they obey parity and the mirror symmetries by
construction, and every boundary is physical: a repulsive charge always shrinks its own pixel
on all four sides.

Fitted to measured area coefficients by `bfpsf.calibration.electrostatic_fit`.
"""

import dataclasses

import numba
import numpy as np

from ..errors import BFPSFValueError
from ..shifts import BoundaryShifts

__all__ = ["ElectrostaticGeometry", "electrostatic_shifts", "electrostatic_area",
           "GEOMETRY_BOUNDS"]

# Gauss-Legendre nodes along a boundary and across the charge sheet, and image-charge pairs
# on each side. 8 nodes along a boundary half a pixel from the sheet edge are exact to 1e-4;
# the images beyond 2 K t contribute (rho / (2 K t))^3 of the field at distance rho.
_BOUNDARY_NODES = 8
_SHEET_NODES = 3
_IMAGE_PAIRS = 6
# Their nodes and weights on [-1, 1], found once (numpy's leggauss solves an eigenproblem).
_SHEET_RULE = np.polynomial.legendre.leggauss(_SHEET_NODES)
_BOUNDARY_RULE = np.polynomial.legendre.leggauss(_BOUNDARY_NODES)

#: Physical ranges of the fitted geometry, in units of the sensor thickness for heights and
#: of the pixel for the sheet. The sheet reaches at most 0.49 pixel from its centre in each
#: direction (as in cp_pipe); the boundary heights are above the charge and below half the
#: thickness.
GEOMETRY_BOUNDS = {
    "charge_height": (0.0, 0.25),
    "horizontal_height": (0.0, 0.5),
    "vertical_height": (0.0, 0.5),
    "half_width_x": (0.01, 0.49),
    "half_width_y": (0.01, 0.49),
}


@dataclasses.dataclass(frozen=True)
class ElectrostaticGeometry:
    """Geometry of the electrostatic model, in pixels.

    Attributes
    ----------
    thickness : float
        Sensor thickness t (held fixed in the fit; 10 for 100 um sensors with 10 um pixels).
    charge_height : float
        Height z_q of the collected-charge sheet above the clock plane.
    horizontal_height, vertical_height : float
        Heights z_sh, z_sv below which the N/S (horizontal) and E/W (vertical) boundaries no
        longer move; the deflection is integrated from them to the entrance face.
    half_width_x, half_width_y : float
        Half-sizes of the charge sheet along x (serial) and y (parallel).
    """

    thickness: float
    charge_height: float
    horizontal_height: float
    vertical_height: float
    half_width_x: float
    half_width_y: float

    def __post_init__(self):
        if not self.thickness > 0:
            msg = f"thickness must be positive, got {self.thickness}"
            raise BFPSFValueError(msg, self.thickness)
        if not 0 <= self.charge_height < min(self.horizontal_height, self.vertical_height):
            msg = (f"the charge ({self.charge_height:.3g} px) must lie below both boundary "
                   f"heights ({self.horizontal_height:.3g}, {self.vertical_height:.3g} px)")
            raise BFPSFValueError(msg, self.charge_height)
        if max(self.horizontal_height, self.vertical_height) >= self.thickness:
            msg = "the boundary heights must lie inside the sensor thickness"
            raise BFPSFValueError(msg)
        if not (0 < self.half_width_x < 0.5 and 0 < self.half_width_y < 0.5):
            msg = (f"the charge sheet must lie inside its pixel, got half-widths "
                   f"{self.half_width_x:.3g}, {self.half_width_y:.3g}")
            raise BFPSFValueError(msg)

    def as_dict(self):
        return dataclasses.asdict(self)


@numba.njit(cache=True, nogil=True, inline="always")
def _z_integral(rho2, z_low, z_high, height):
    """int_{z_low}^{z_high} dz / (rho^2 + (z - c)^2)^(3/2), times rho^2, for a charge at c."""
    top = z_high - height
    bottom = z_low - height
    return top / np.sqrt(rho2 + top * top) - bottom / np.sqrt(rho2 + bottom * bottom)


@numba.njit(cache=True, nogil=True)
def _unit_shift_kernel(centres, normals, z_low, thickness, charge_height, axis_half_width,
                       cross_half_width, sheet_nodes, sheet_weights, boundary_nodes,
                       boundary_weights, image_pairs):
    """Minus the transverse field of the unit sheet, normal to a unit boundary, integrated over
    z from ``z_low`` to the thickness and along the boundary: the shift of the boundary.

    Boundary ``i`` is centred ``centres[i]`` along itself and ``normals[i]`` along its normal
    from the sheet centre. The sheet (half-sizes ``axis_half_width`` along the normal,
    ``cross_half_width`` along the boundary) and its image in the clock plane are integrated
    by Gauss-Legendre; the other images, at least 2 t - z_q away, are point charges at the
    sheet centre. For a point charge at height c,
    int E_n dz = n / rho^2 [(z - c) / sqrt(rho^2 + (z - c)^2)], rho the horizontal distance.
    """
    t = thickness
    c = charge_height
    out = np.empty(centres.size)
    for i in range(centres.size):
        normal = normals[i]
        total = 0.0
        for b in range(boundary_nodes.size):
            along = centres[i] + boundary_nodes[b] / 2.0
            near = 0.0
            for j in range(sheet_nodes.size):
                n = normal - sheet_nodes[j] * axis_half_width
                for k in range(sheet_nodes.size):
                    v = along - sheet_nodes[k] * cross_half_width
                    rho2 = n * n + v * v
                    weight = sheet_weights[j] * sheet_weights[k] / 4.0
                    near += weight * n / rho2 * (_z_integral(rho2, z_low, t, c)
                                                 - _z_integral(rho2, z_low, t, -c))
            rho2 = normal * normal + along * along
            far = 0.0
            for order in range(1, image_pairs + 1):
                for height in (2.0 * order * t, -2.0 * order * t):
                    far += (_z_integral(rho2, z_low, t, height + c)
                            - _z_integral(rho2, z_low, t, height - c))
            total += boundary_weights[b] / 2.0 * (near + normal / rho2 * far)
        out[i] = -total
    return out


def _unit_shift(centres, normals, z_low, geometry, axis_half_width, cross_half_width):
    """`_unit_shift_kernel` on any broadcastable arrays of boundary centres and normals."""
    centres, normals = np.broadcast_arrays(np.asarray(centres, dtype=float),
                                           np.asarray(normals, dtype=float))
    shift = _unit_shift_kernel(np.ascontiguousarray(centres).ravel(),
                               np.ascontiguousarray(normals).ravel(), float(z_low),
                               float(geometry.thickness), float(geometry.charge_height),
                               float(axis_half_width), float(cross_half_width), *_SHEET_RULE,
                               *_BOUNDARY_RULE, _IMAGE_PAIRS)
    return shift.reshape(centres.shape)


def _unit_north(geometry, dx, dy):
    """a^N(dx, dy) for alpha = 1 on any grid of source offsets.

    The N boundary of pixel (0, 0) seen from a charge at (dx, dy) is the segment
    y = 1/2 - dy, x in -dx +- 1/2; the charge deflects electrons along +y there by the
    integral of E_y, so the boundary moves by minus that (outward positive).
    """
    return _unit_shift(-np.asarray(dx, dtype=float), 0.5 - np.asarray(dy, dtype=float),
                       geometry.horizontal_height, geometry, geometry.half_width_y,
                       geometry.half_width_x)


def _unit_east(geometry, dx, dy):
    """a^E(dx, dy) for alpha = 1: the segment x = 1/2 - dx, y in -dy +- 1/2, field E_x."""
    return _unit_shift(-np.asarray(dy, dtype=float), 0.5 - np.asarray(dx, dtype=float),
                       geometry.vertical_height, geometry, geometry.half_width_x,
                       geometry.half_width_y)


def electrostatic_shifts(geometry, alpha, radius):
    """Boundary shifts a^N, a^E of the electrostatic model on offsets -radius..radius.

    Parameters
    ----------
    geometry : ElectrostaticGeometry
    alpha : float
        Amplitude, pixels per electron per unit integrated field (pixel^-1).
    radius : int
        Offsets -radius..radius. As in `BoundaryShifts.from_radial_profile`, the row of a^N
        at dy = -radius and the column of a^E at dx = -radius (outside the grid by parity)
        are zero.

    Returns
    -------
    BoundaryShifts
    """
    m = int(radius)
    grid = np.arange(-m, m + 1, dtype=float)
    dy, dx = np.meshgrid(grid, grid, indexing="ij")
    north = alpha * _unit_north(geometry, dx, dy)
    east = alpha * _unit_east(geometry, dx, dy)
    north[0, :] = 0.0
    east[:, 0] = 0.0
    return BoundaryShifts(north, east, check=True, rtol=1e-9)


def electrostatic_area(geometry, alpha, maxlag):
    """Area coefficients a(dx, dy) = sum_X a^X of the model, [dy, dx] for 0..maxlag, 1/e-.

    Only the boundaries that enter the quadrant are computed (G15 eq. covar):
    a = a^N(dx, dy) - a^N(dx, dy + 1) + a^E(dx, dy) - a^E(dx + 1, dy).
    """
    n = int(maxlag)
    dy, dx = np.mgrid[0:n + 2, 0:n + 2].astype(float)
    north = _unit_north(geometry, dx[:, :n + 1], dy[:, :n + 1])   # dy = 0..n+1
    east = _unit_east(geometry, dx[:n + 1, :], dy[:n + 1, :])     # dx = 0..n+1
    return alpha * (north[:-1] - north[1:] + east[:, :-1] - east[:, 1:])
