"""P(F, x, y): the flux-dependent PSF on a grid of fiducial positions over the image.

Each node k of an ``nx`` x ``ny`` grid holds its own `~bfpsf.model.psf.FluxDependentPSF`,
P_k(F) = P0_k + F R[P0_k] (G15 eq. scrambling_model folded into the PSF). Between nodes the
model is interpolated as photutils' `~photutils.psf.GriddedPSFModel` does: bilinearly between
the four nearest nodes, with the node positions clamped at the edge of the grid (a star outside
the outer nodes takes the edge nodes' PSF). Because every node model is linear in its P0 and
in its BF term, interpolating the node models is interpolating P0 and R[P0] separately:

    P(F, x, y) = sum_k w_k(x, y) (P0_k + F R[P0_k]),      sum_k w_k = 1.

In table mode that is itself a `FluxDependentPSF` (data sum_k w_k P0_k, BF table
sum_k w_k R[P0_k]): `GriddedFluxDependentPSF.at` returns it, e.g. for GalSim or shapes.
R is interpolated, not recomputed from the interpolated P0. R is quadratic in P0, so between
two nodes at weights w and 1 - w the two differ by w (1 - w) R[P0_1 - P0_2] (second order in
the node difference). Measured midway between Moffat nodes (beta 3.5, E2V landing shifts, BF
change at 1.5e6 e-): FWHM 3.0 / 3.3 px, the interpolated term changes sigma 0.5 % more and e1
0.5 % more than R of the interpolated P0; FWHM 3.0 / 3.45 px with e1 -0.04 / 0 (neighbouring
nodes of the 3 x 3 acceptance grid, tests/test_gridded_silicon.py): sigma 1.0 %, e1 0.7 %
(1.6e-5). Exact alternative, not implemented: the interpolated P0's R is
sum_kl w_k w_l B[P0_k, P0_l] with B the symmetric bilinear BF response, which needs the cross
tables of neighbouring nodes.
"""


import numpy as np
from astropy.modeling import Parameter

from ..errors import BFPSFValueError
from .base import BFPSFModel
from .bf_term import star_phases
from .psf import FluxDependentPSF

__all__ = ["GriddedFluxDependentPSF", "bilinear_weights", "grid_node_positions"]


def grid_node_positions(n_nodes, length):
    """``n_nodes`` node coordinates spanning an axis of ``length`` pixels, pixels.

    Two or more nodes sit from the first to the last pixel centre (0 and ``length - 1``), so
    that every star is interpolated, never extrapolated, and a PSF varying linearly over the
    image is followed exactly; a single node sits at the centre.
    """
    n_nodes = int(n_nodes)
    if n_nodes < 1:
        msg = f"a grid needs at least one node per axis, got {n_nodes}"
        raise BFPSFValueError(msg, n_nodes)
    if n_nodes == 1:
        return np.array([(length - 1) / 2.0])
    return np.linspace(0.0, length - 1.0, n_nodes)


def _axis_weights(values, nodes):
    """Lower node index and weight of the upper node along one axis (clamped at the edges)."""
    values = np.asarray(values, dtype=float)
    if nodes.size == 1:
        return np.zeros(values.shape, dtype=int), np.zeros(values.shape)
    clamped = np.clip(values, nodes[0], nodes[-1])
    lower = np.clip(np.searchsorted(nodes, clamped, side="right") - 1, 0, nodes.size - 2)
    upper_weight = (clamped - nodes[lower]) / (nodes[lower + 1] - nodes[lower])
    return lower, upper_weight


def bilinear_weights(x, y, x_nodes, y_nodes):
    """The four nearest nodes of positions (x, y) and their bilinear weights.

    Parameters
    ----------
    x, y : array_like
        Positions, pixels (same shape, any).
    x_nodes, y_nodes : 1-D ndarray
        Increasing node coordinates along x (nx) and y (ny), pixels.

    Returns
    -------
    indices : ndarray of int, shape ``x.shape + (4,)``
        Flat node indices ``iy * nx + ix`` (row-major [y, x]); repeated for a 1-node axis.
    weights : ndarray, shape ``x.shape + (4,)``
        Non-negative, summing to 1; the interpolated model is sum of weight x node model.
    """
    x_nodes, y_nodes = np.asarray(x_nodes, dtype=float), np.asarray(y_nodes, dtype=float)
    ix, tx = _axis_weights(x, x_nodes)
    iy, ty = _axis_weights(y, y_nodes)
    nx = x_nodes.size
    step_x = int(nx > 1)
    step_y = nx if y_nodes.size > 1 else 0
    base = iy * nx + ix
    indices = np.stack([base, base + step_x, base + step_y, base + step_y + step_x], axis=-1)
    weights = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=-1)
    return indices, weights


class GriddedFluxDependentPSF(BFPSFModel):
    r"""A flux-dependent PSF that varies over the image, interpolated between grid nodes.

    .. math:: M(x, y) = \sum_k w_k(x_0, y_0)\,[F\,p_k(x - x_0, y - y_0)
                        + g\,F\,|F|\,R[p_k](x - x_0, y - y_0)]

    with w_k the bilinear weights of the four nodes nearest to the star (photutils
    `~photutils.psf.GriddedPSFModel`'s interpolation) and p_k, R[p_k] the P0 and BF term of
    node k (`~bfpsf.model.psf.FluxDependentPSF`, G15 eq. scrambling_model).

    Parameters
    ----------
    nodes : sequence of FluxDependentPSF
        ``ny * nx`` node models, row-major ([y, x]: node ``iy * nx + ix`` sits at
        ``(x_nodes[ix], y_nodes[iy])``), with equal data shape, oversampling, origin, shifts,
        gain and mode.
    x_nodes, y_nodes : 1-D array_like
        Increasing node coordinates, pixels of the image (pixel centres at integers).
    flux, x_0, y_0 : float, optional
        As `FluxDependentPSF`.

    Notes
    -----
    ``evaluate`` never reads the instance's parameters and holds no state, so photutils
    `~photutils.psf.PSFPhotometry` and `~photutils.psf.IterativePSFPhotometry` evaluate it
    with one copy for all stars; ``copy()`` shares the node models.
    """

    kind = "a grid"
    reads_any_kind = False
    product_kind = "grid"

    flux = Parameter(default=1, description="Total flux of the star (image unit)")
    x_0 = Parameter(default=0, description="x position of the star centre (pixels)")
    y_0 = Parameter(default=0, description="y position of the star centre (pixels)")

    def __init__(self, nodes, x_nodes, y_nodes, *, flux=flux.default, x_0=x_0.default,
                 y_0=y_0.default, **kwargs):
        self.x_nodes = self._validate_nodes_axis(x_nodes, "x_nodes")
        self.y_nodes = self._validate_nodes_axis(y_nodes, "y_nodes")
        nodes = list(nodes)
        if len(nodes) != self.x_nodes.size * self.y_nodes.size or not all(
                isinstance(node, FluxDependentPSF) for node in nodes):
            msg = (f"nodes must be {self.y_nodes.size} x {self.x_nodes.size} FluxDependentPSF "
                   f"models (row-major [y, x]), got {len(nodes)}")
            raise BFPSFValueError(msg, len(nodes))
        first = nodes[0]
        for node in nodes[1:]:
            if (node.data.shape != first.data.shape
                    or np.any(node.oversampling != first.oversampling)
                    or np.any(node.origin != first.origin) or node.mode != first.mode
                    or node.gain != first.gain or node.shifts is not first.shifts
                    and not (np.array_equal(node.shifts.north, first.shifts.north)
                             and np.array_equal(node.shifts.east, first.shifts.east))):
                msg = ("grid nodes must share data shape, oversampling, origin, mode, gain and "
                       "boundary shifts")
                raise BFPSFValueError(msg, node)
        self.nodes = tuple(nodes)
        #: Product metadata (`bfpsf.model.base`): ``calibration`` (file name of the shifts),
        #: ``linearity_c_per_1e5``, ``flux_correction`` and its error.
        self._init_metadata()
        super().__init__(flux, x_0, y_0, **kwargs)

    @staticmethod
    def _validate_nodes_axis(values, name):
        values = np.atleast_1d(np.asarray(values, dtype=float))
        if values.ndim != 1 or not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0):
            msg = f"{name} must be increasing finite pixel coordinates, got {values!r}"
            raise BFPSFValueError(msg, values)
        return values

    @classmethod
    def from_data(cls, data, x_nodes, y_nodes, shifts, **psf_kwargs):
        """Build from a cube of node P0s.

        Parameters
        ----------
        data : ndarray, shape (ny_nodes, nx_nodes, n, n) or (ny_nodes * nx_nodes, n, n)
            Oversampled P0 of each node (as `FluxDependentPSF` ``data``), row-major [y, x].
        x_nodes, y_nodes : 1-D array_like
            Node coordinates, pixels.
        shifts : BoundaryShifts or Calibration
        **psf_kwargs
            Passed to every node's `FluxDependentPSF` (``oversampling``, ``mode``, ...);
            ``bf_table`` may be a cube like ``data``.
        """
        data = np.asarray(data, dtype=float)
        data = data.reshape((-1,) + data.shape[-2:])
        tables = psf_kwargs.pop("bf_table", None)
        if tables is not None:
            tables = np.asarray(tables, dtype=float).reshape(data.shape)
        nodes = [FluxDependentPSF(node_data, shifts,
                                  bf_table=None if tables is None else tables[index],
                                  **psf_kwargs)
                 for index, node_data in enumerate(data)]
        return cls(nodes, x_nodes, y_nodes)

    # -- what every node shares ---------------------------------------------------------------
    @property
    def grid_shape(self):
        """(ny, nx) nodes."""
        return (self.y_nodes.size, self.x_nodes.size)

    @property
    def data(self):
        """Node P0s, ndarray (ny, nx, n, n)."""
        return np.array([node.data for node in self.nodes]).reshape(
            self.grid_shape + self.nodes[0].data.shape)

    oversampling = property(lambda self: self.nodes[0].oversampling, doc="(oy, ox)")
    origin = property(lambda self: self.nodes[0].origin, doc="(x, y) of the star in the data")
    shifts = property(lambda self: self.nodes[0].shifts, doc="Boundary shifts a^X, 1/e-")
    mode = property(lambda self: self.nodes[0].mode, doc="BF term mode of the nodes")
    gain = property(lambda self: self.nodes[0].gain, doc="e- per image unit")
    flux_unit = property(lambda self: self.nodes[0].flux_unit, doc="'electron' or 'adu'")
    buildup_steps = property(lambda self: self.nodes[0].buildup_steps,
                             doc="build-up steps of the BF term (None: G15's one step)")
    fill_value = property(lambda self: self.nodes[0].fill_value, doc="value outside the data")
    half_size = property(lambda self: self.nodes[0].half_size, doc="stamp half-width, pixels")

    varies_over_field = True
    field_nodes = property(lambda self: (self.x_nodes, self.y_nodes),
                           doc="(x_nodes, y_nodes), pixels")

    @property
    def reference_position(self):
        """(x, y) of the grid's centre, pixels: the position taken when none is given."""
        return (float(np.mean(self.x_nodes)), float(np.mean(self.y_nodes)))

    @property
    def shift_samples(self):
        """Shifts drawn from the calibration's uncertainty (shared by every node)."""
        return self.nodes[0].shift_samples

    @shift_samples.setter
    def shift_samples(self, samples):
        for node in self.nodes:
            node.shift_samples = tuple(samples)

    @property
    def amplifier_shifts(self):
        """Boundary shifts of each amplifier the grid was fitted on (held by every node, so
        shared with the copies, which share the nodes; empty for one amplifier), as
        `FluxDependentPSF.amplifier_shifts`."""
        return self.nodes[0].amplifier_shifts

    @amplifier_shifts.setter
    def amplifier_shifts(self, shifts):
        for node in self.nodes:
            node.amplifier_shifts = dict(shifts)

    @property
    def empirical(self):
        """The EMPIRICAL term of a refined calibration (`bfpsf.model.empirical`), held by
        every node (each applies it at the star's column), or None."""
        return self.nodes[0].empirical

    @empirical.setter
    def empirical(self, term):
        for node in self.nodes:
            node.empirical = term

    def with_empirical_term(self, term):
        """A grid of copies of the nodes applying ``term`` (`BFPSFModel.with_empirical_term`;
        the copies of a grid share its nodes, so the nodes are copied first)."""
        new = self.__class__([node.with_empirical_term(term) for node in self.nodes],
                             self.x_nodes, self.y_nodes)
        self.copy_metadata_to(new, shift_samples=True)
        for name in self.param_names:
            getattr(new, name).value = getattr(self, name).value
        new.empirical = term
        return new

    def with_shifts(self, shifts):
        """The same node P0s and options with other boundary shifts (every node's
        `FluxDependentPSF.with_shifts`); the per-amplifier shifts are kept."""
        new = self.__class__([node.with_shifts(shifts) for node in self.nodes], self.x_nodes,
                             self.y_nodes)
        return self.copy_metadata_to(new)

    def with_flux_unit(self, flux_unit, gain=None):
        """The same grid for images in another unit (every node's
        `FluxDependentPSF.with_flux_unit`)."""
        new = self.__class__([node.with_flux_unit(flux_unit, gain) for node in self.nodes],
                             self.x_nodes, self.y_nodes)
        return self.copy_metadata_to(new, shift_samples=True)

    def charge_delta(self, charge_e, density=None):
        """The charge each pixel gains under the model's operator, e- (every node shares the
        shifts and build-up): `FluxDependentPSF.charge_delta`."""
        return self.nodes[0].charge_delta(charge_e, density)

    def _value_state(self):
        return (self.x_nodes, self.y_nodes, [node._value_state() for node in self.nodes],
                [float(getattr(self, name).value) for name in self.param_names],
                self.metadata_state())

    @property
    def bounding_box(self):
        """((y_min, y_max), (x_min, x_max)) of the PSF data around (x_0, y_0), pixels."""
        node = self.nodes[0]
        (y_low, y_high), (x_low, x_high) = node.bounding_box
        shift_x = float(self.x_0.value) - float(node.x_0.value)
        shift_y = float(self.y_0.value) - float(node.y_0.value)
        return ((y_low + shift_y, y_high + shift_y), (x_low + shift_x, x_high + shift_x))

    def weights(self, x, y):
        """Nodes and bilinear weights at image position (x, y); see `bilinear_weights`."""
        return bilinear_weights(x, y, self.x_nodes, self.y_nodes)

    def evaluate(self, x, y, flux, x_0, y_0):
        """Model value at (x, y): the weighted node models of the star at (x_0, y_0).

        Parameters
        ----------
        x, y : float or array_like
            Pixel coordinates (any shape).
        flux : float
            Total flux of the star, image unit.
        x_0, y_0 : float
            Star centre, pixels: it also sets the interpolation weights.

        Returns
        -------
        ndarray
            sum_k w_k (F p_k + g F |F| R[p_k]), shaped like ``x``.
        """
        if np.size(x_0) != 1 or np.size(y_0) != 1 or np.size(flux) != 1:
            msg = "GriddedFluxDependentPSF evaluates one star per call (no model sets)"
            raise BFPSFValueError(msg, np.shape(flux))
        x_0, y_0 = float(np.ravel(x_0)[0]), float(np.ravel(y_0)[0])
        if not (np.isfinite(x_0) and np.isfinite(y_0)):
            return np.full(np.broadcast(x, y).shape, np.nan)
        indices, weights = self.weights(x_0, y_0)
        result = 0.0
        for index, weight in zip(indices, weights):
            if weight > 0:
                result = result + weight * self.nodes[index].evaluate(x, y, flux, x_0, y_0)
        return np.asarray(result) * np.ones(np.broadcast(x, y).shape)

    # -- views at one position ----------------------------------------------------------------
    def at(self, x=None, y=None):
        """The model at image position (x, y) as one `FluxDependentPSF` (default the grid's
        centre), with the grid's metadata.

        In table mode its data is sum_k w_k P0_k and its BF table sum_k w_k R[P0_k], exactly
        the gridded model evaluated for a star at (x, y). In exact mode (e.g. the build-up of
        a refined calibration) its data is sum_k w_k P0_k and R is recomputed from it: R of
        the interpolated P0, which differs from the interpolated R at second order in the
        node difference (module docstring).
        """
        x, y = self.position_or_reference(x, y)
        indices, weights = self.weights(x, y)
        data = sum(weight * self.nodes[index].data for index, weight in zip(indices, weights))
        node = self.nodes[0]
        options = dict(node.options, flux=float(self.flux.value), x_0=x, y_0=y)
        if self.mode == "table":
            options.update(bf_table=sum(weight * self.nodes[index].bf_table
                                        for index, weight in zip(indices, weights)))
        else:
            options.update(density_profile=node.density_profile)
        psf = self.copy_metadata_to(FluxDependentPSF(data, node.shifts, **options),
                                    shift_samples=True)
        # the EMPIRICAL term at this column, as the grid applies it to a star here
        return psf.at(x, y)

    def star_image(self, flux, x=None, y=None, *, x_phase=None, y_phase=None, half_size=None):
        """Pixel image of a star of flux F at image position (x, y), like
        `FluxDependentPSF.star_image` (exact at the phase, in every mode).

        Parameters
        ----------
        flux : float
        x, y : float, optional
            Position of the star on the image, pixels: it sets the node weights (default the
            grid's centre) and the default phase.
        x_phase, y_phase : float, optional
            Star centre minus the centre of the stamp's central pixel, pixels; default the
            phase of (x, y).
        half_size : int, optional

        Returns
        -------
        ndarray [y, x]
            sum_k w_k (F p_k + g F |F| R[p_k]).
        """
        x_phase, y_phase = star_phases(x, y, x_phase, y_phase)
        x, y = self.position_or_reference(x, y)
        indices, weights = self.weights(x, y)
        return sum(weight * self.nodes[index].star_image(flux, x, y, x_phase=x_phase,
                                                         y_phase=y_phase, half_size=half_size)
                   for index, weight in zip(indices, weights) if weight > 0)

    def __repr__(self):
        return (f"<GriddedFluxDependentPSF(flux={float(self.flux.value):g}, "
                f"x_0={float(self.x_0.value):g}, y_0={float(self.y_0.value):g}, "
                f"grid={self.grid_shape[1]}x{self.grid_shape[0]}, "
                f"shape={self.nodes[0].data.shape}, mode={self.mode!r})>")
