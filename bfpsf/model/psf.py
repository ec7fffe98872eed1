"""The flux-dependent PSF P(F) = P0 + F R[P0] (G15 eq. scrambling_model folded into the PSF).

A star of flux F whose unit-flux pixelised image is p (pixel response included, sampled on the
image pixel grid at the star's own sub-pixel phase) is, after charge redistribution,

    Q = F p + dQ(F p) = F p + F**2 R[p],     R[p] = redistribution_delta(p, shifts)

exactly, because the G15 operator (eq. scrambling_model) is quadratic in the charge. The PSF a
star of flux F shows is therefore P(F) = Q / F = p + F R[p]: a two-term model. R depends on the
sub-pixel phase of the star, because the pixelised PSF does; `FluxDependentPSF` precomputes R at
every phase of the oversampled P0 grid (the ``'table'`` mode, as fast as an image PSF) or
recomputes it at the exact phase of each evaluation (the ``'exact'`` mode). With oversampling
4 the phase interpolation of the table mode errs by 5e-5 of the largest BF pixel (1e-3 at
oversampling 2); the exact mode costs one FFT of a small stamp per evaluation (3.5x slower).

Limits: each star is redistributed by its own charge only. Overlapping stars also push each
other's boundaries (the operator is quadratic in the summed charge): the cross term is not in
a sum of per-star models (0.3 % flux error measured for 120 ke- peaks 4 pixels apart). A
uniform sky S adds a term linear in F that P0 absorbs when it is fitted at that sky level.
"""

import copy

import numpy as np
from astropy.modeling import Parameter
from scipy.interpolate import RectBivariateSpline

from ..errors import BFPSFValueError, integer_at_least
from ..shifts import as_shifts
from .base import MODES, BFPSFModel, validate_data, validate_oversampling, validate_units
from .bf_term import (BFTerm, bf_response_table, exact_density_table, pixelised_stamp,
                      star_phases)
from .empirical import empirical_of

__all__ = ["FluxDependentPSF", "bf_response_table", "pixelised_stamp", "star_phases"]

class FluxDependentPSF(BFTerm, BFPSFModel):
    r"""A PSF whose shape depends on the star's flux through charge redistribution.

    The model of a star of flux F centred at (x_0, y_0) is (G15 eq. scrambling_model applied
    to the star's own charge)

    .. math:: M(x, y) = F\,p(x - x_0, y - y_0) + g\,F\,|F|\,R[p](x - x_0, y - y_0)

    where p is the base PSF P0 (pixel response included), R[p] the redistribution of the unit
    PSF pixelised at the phase of the evaluation grid, and g = `electrons_per_unit` (1 for a
    model in electrons, the gain for one in ADU: ``flux_unit``).
    The normalised PSF at flux F is P(F) = p + g F R[p].

    Parameters
    ----------
    data : 2-D ndarray [y, x]
        Oversampled base PSF P0 with the pixel response included (an ePSF, as from
        `photutils.psf.EPSFBuilder`), normalised to sum ``oversampling**2`` for unit flux.
        Its support must hold the PSF: charge is neither moved into nor out of its edge.
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (G15 eq. def-a). A calibration refined by ``bfpsf
        diagnose --output-calib`` also brings its EMPIRICAL term (``empirical``, applied by
        every evaluation; `bfpsf.model.empirical`).
    flux : float, optional
        Total flux of the star, in ``flux_unit``.
    x_0, y_0 : float, optional
        Centre of the star, pixels (pixel centres at integers).
    origin : (float, float), optional
        (x, y) of the star centre in ``data``; default its centre.
    oversampling : int or (int, int), optional
        Oversampling of ``data`` (y, x). Default 1.
    flux_unit : {'electron', 'adu'}, optional
        Unit of ``flux`` and of the model values. ``'electron'`` (the default when no ``gain``
        is given): the BF term is F |F| R. ``'adu'``: the model describes an image in ADU and
        the BF term is g F |F| R with g = ``gain`` (the charge is what pushes the boundaries).
        Required whenever ``gain`` is given, so that a gain can never change the BF term
        without the caller saying so.
    gain : float, optional
        e-/ADU of the images the PSF describes (the detector gain, never its inverse). With
        ``flux_unit='adu'`` it scales the BF term; with ``flux_unit='electron'`` it is only
        recorded (the PSF product keeps it, ``bfpsf photometry`` converts ADU images with it).
    mode : {'table', 'exact'}, optional
        ``'table'`` (default): R is precomputed at each of the oversampling phases (exact there)
        and interpolated between phases with the same cubic spline as P0; cost about that of a
        static image PSF. ``'exact'``: R is recomputed at the exact phase of every evaluation
        from the pixelised P0 (one small FFT per call).
    buildup_steps : int, optional
        Integrate the build-up of the boundary shifts during the exposure in this many steps
        (`bfpsf.model.buildup.redistribute_buildup`). The response is then no longer
        quadratic in F (the redistributed charge acts back, second order in a), so it requires
        ``mode='exact'``, where each star is redistributed at its own flux. Default None:
        the one-step model of G15.
    bf_table : ndarray, optional
        Precomputed R at every phase of ``data`` (same shape, ``mode='table'``), e.g. with
        the exact boundary density (`from_galsim` with ``density='exact'``); default
        `bf_response_table` of ``data`` (G15's mean density).
    density_profile : galsim.GSObject, optional
        The unit-flux profile (no pixel) whose charge density integrated along each pixel
        boundary replaces G15's mean of the two pixels
        (`bfpsf.model.density.exact_boundary_density`): in mode 'table' it makes the
        table (unless ``bf_table`` is given); in mode 'exact' it is used at every evaluation
        phase and in every build-up step. `from_galsim` with ``density='exact'`` sets it.
        Default None.
    density_oversampling : int, optional
        Sub-pixels per pixel for ``density_profile``. Default 8.
    fill_value : float, optional
        Model value outside the PSF data. Default 0.

    Notes
    -----
    * Fluxes F <= 0 carry no physical star; the BF term uses F |F| so the model is odd in F
      and continuously differentiable through F = 0 (a fitter stepping through zero sees a
      smooth model; the term is negligible for faint trial fluxes anyway). NaN parameters give
      NaN model values; no error is raised.
    * ``evaluate`` never reads the parameter values of the instance (photutils evaluates many
      sources with one model) and holds no state; ``copy()`` shares the arrays and splines.
    * A uniform sky S adds a term linear in F, S F (a^X * p)/2 summed over boundaries, which
      is absorbed in P0 when P0 is fitted on images with that sky.
    """

    kind = "a single PSF"
    product_kind = "single"

    flux = Parameter(default=1, description="Total flux of the star (image unit)")
    x_0 = Parameter(default=0, description="x position of the star centre (pixels)")
    y_0 = Parameter(default=0, description="y position of the star centre (pixels)")

    @property
    def reference_position(self):
        """The position taken when none is given: (0, 0), the model being the same
        everywhere; with an EMPIRICAL term that changes with the column or the row, that
        term's reference column or row (rounded to a pixel centre)."""
        term = self.empirical
        if term is None or not term.position_dependent:
            return (0.0, 0.0)
        return (float(np.floor(term.x_reference + 0.5)) if term.column_dependent else 0.0,
                float(np.floor(term.y_reference + 0.5)) if term.row_dependent else 0.0)

    def __init__(self, data, shifts, *, flux=flux.default, x_0=x_0.default, y_0=y_0.default,
                 origin=None, oversampling=1, flux_unit=None, gain=None, mode="table",
                 buildup_steps=None, bf_table=None, fill_value=0.0, density_profile=None,
                 density_oversampling=8, **kwargs):
        self.data = validate_data(data)
        self.data.flags.writeable = False
        self.shifts = as_shifts(shifts)
        self.oversampling = validate_oversampling(oversampling)
        if origin is None:
            origin = ((self.data.shape[1] - 1) / 2.0, (self.data.shape[0] - 1) / 2.0)
        origin = np.asarray(origin, dtype=float)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            msg = f"origin must be two finite numbers (x, y), got {origin!r}"
            raise BFPSFValueError(msg, origin)
        self.origin = origin
        self.flux_unit, self.gain = validate_units(flux_unit, gain)
        if mode not in MODES:
            msg = f"mode must be one of {MODES}, got {mode!r}"
            raise BFPSFValueError(msg, mode)
        if buildup_steps is not None:
            buildup_steps = integer_at_least("buildup_steps", buildup_steps, 1)
            if mode != "exact":
                msg = ("buildup_steps makes the BF response non-quadratic in flux; it requires "
                       f"mode='exact', got mode={mode!r}")
                raise BFPSFValueError(msg, mode)
        self.buildup_steps = buildup_steps
        if bf_table is not None:
            bf_table = np.array(bf_table, dtype=float)
            if mode != "table" or bf_table.shape != self.data.shape:
                msg = (f"bf_table must have the shape of data {self.data.shape} and needs "
                       f"mode='table', got shape {bf_table.shape} and mode={mode!r}")
                raise BFPSFValueError(msg, bf_table.shape)
        self.density_profile = density_profile
        self.density_oversampling = integer_at_least("density_oversampling",
                                                     density_oversampling, 2)
        self.mode = mode
        self.fill_value = float(fill_value)
        #: Product metadata (`bfpsf.model.base`): ``calibration`` (file name of the shifts),
        #: ``linearity_c_per_1e5``, ``flux_correction`` and its error.
        self._init_metadata()
        if getattr(shifts, "refinement", None):
            # a calibration refined by `bfpsf diagnose --output-calib`: its EMPIRICAL term
            self.empirical = empirical_of(shifts)
        #: Shifts drawn from the calibration's uncertainty (`Calibration.shift_samples`):
        #: predictions made with this model propagate them (``bfpsf slope --psf``).
        self.shift_samples = (tuple(shifts.shift_samples()) if hasattr(shifts, "shift_samples")
                              else ())
        #: Boundary shifts of each amplifier the model was fitted on, {EXTNAME: BoundaryShifts}
        #: (``bfpsf psf`` on several amplifiers; empty otherwise): `for_amplifier`.
        self.amplifier_shifts = {}
        x = np.arange(self.data.shape[1])
        y = np.arange(self.data.shape[0])
        self._base_spline = RectBivariateSpline(x, y, self.data.T, kx=3, ky=3, s=0)
        self._tables = {}  # built when first needed (the EMPIRICAL term's pattern splines)
        if mode == "table":
            if bf_table is None and density_profile is not None:
                if self.oversampling[0] != self.oversampling[1]:
                    msg = ("density_profile needs the same oversampling in x and y, got "
                           f"{tuple(self.oversampling.tolist())}")
                    raise BFPSFValueError(msg, tuple(self.oversampling.tolist()))
                bf_table = exact_density_table(density_profile, self.shifts, self.data.shape,
                                                int(self.oversampling[0]),
                                                self.density_oversampling)
            self.bf_table = (bf_table if bf_table is not None
                             else bf_response_table(self.data, self.shifts, self.oversampling))
            self.bf_table.flags.writeable = False
            self._bf_spline = RectBivariateSpline(x, y, self.bf_table.T, kx=3, ky=3, s=0)
        else:
            self.bf_table = None
            self._bf_spline = None
        super().__init__(flux, x_0, y_0, **kwargs)

    # -- construction from other PSF descriptions --------------------------------------------
    @classmethod
    def from_image_psf(cls, image_psf, shifts, **kwargs):
        """Build from a photutils `~photutils.psf.ImagePSF` (e.g. an EPSFBuilder result)."""
        oversampling = np.asarray(image_psf.oversampling)
        return cls(np.asarray(image_psf.data, dtype=float), shifts,
                   origin=np.asarray(image_psf.origin), oversampling=oversampling,
                   flux=float(image_psf.flux.value), x_0=float(image_psf.x_0.value),
                   y_0=float(image_psf.y_0.value), **kwargs)

    @classmethod
    def from_galsim(cls, profile, shifts, *, oversampling=4, size=25, density="mean",
                    density_oversampling=8, **kwargs):
        """Build from a GalSim profile of the optics and atmosphere (no pixel).

        Parameters
        ----------
        profile : galsim.GSObject
            PSF in pixel units (scale 1); it is convolved with the unit pixel and drawn
            at ``1 / oversampling`` pixel spacing, unit flux.
        oversampling : int, optional
            Default 4.
        size : int, optional
            Support of P0 in pixels (odd). Default 25.
        density : {'mean', 'exact'}, optional
            Boundary charge density of the BF table: G15's mean of the two pixels (eq.
            density-approx, default) or the density integrated along each boundary from the
            profile drawn at ``density_oversampling`` sub-pixels per pixel
            (`bfpsf.model.density.exact_boundary_density`), for undersampled PSFs.
        density_oversampling : int, optional
            Sub-pixels per pixel for ``density='exact'``. Default 8.
        **kwargs
            Passed to the constructor.
        """
        import galsim

        size = int(size)
        if size < 3 or size % 2 == 0:
            msg = f"size must be an odd number of pixels >= 3, got {size}"
            raise BFPSFValueError(msg, size)
        if density not in ("mean", "exact"):
            msg = f"density must be 'mean' or 'exact', got {density!r}"
            raise BFPSFValueError(msg, density)
        over = int(validate_oversampling(oversampling)[0])
        npix = size * over + (1 - over % 2)  # odd, so that the centre is a sample
        unit = profile.withFlux(1.0)
        pixelised = galsim.Convolve(unit, galsim.Pixel(1.0))
        image = pixelised.drawImage(nx=npix, ny=npix, scale=1.0 / over, method="no_pixel")
        data = image.array * over**2
        if density == "exact":
            kwargs.update(density_profile=unit, density_oversampling=density_oversampling)
        return cls(data, shifts, oversampling=over, **kwargs)

    # -- units and options ---------------------------------------------------------------------
    @property
    def options(self):
        """The keyword arguments that rebuild this model from ``data`` and ``shifts``.

        Everything but the GalSim ``density_profile``: in mode 'table' its effect is in
        ``bf_table``, which is included (the PSF product stores each of these).
        """
        options = {"origin": tuple(float(value) for value in self.origin),
                   "oversampling": tuple(int(value) for value in self.oversampling),
                   "flux_unit": self.flux_unit, "gain": self.gain, "mode": self.mode,
                   "buildup_steps": self.buildup_steps, "fill_value": self.fill_value,
                   "density_oversampling": self.density_oversampling,
                   "flux": float(self.flux.value), "x_0": float(self.x_0.value),
                   "y_0": float(self.y_0.value)}
        if self.mode == "table":
            options["bf_table"] = self.bf_table
        return options

    def with_flux_unit(self, flux_unit, gain=None):
        """The same PSF for images in another unit (``'electron'`` or ``'adu'``).

        Parameters
        ----------
        flux_unit : {'electron', 'adu'}
        gain : float, optional
            e-/ADU; default the model's own.

        Returns
        -------
        FluxDependentPSF
            Shares P0 and the BF table; its BF term is scaled for the new unit, so a star of
            F ADU gets the redistribution of g F electrons.
        """
        options = self.options
        options.update(flux_unit=flux_unit, gain=self.gain if gain is None else gain,
                       density_profile=self.density_profile)
        new = self.__class__(self.data, self.shifts, **options)
        return self.copy_metadata_to(new, shift_samples=True)

    def at(self, x=None, y=None):
        """The model at image position (x, y): a single P(F) is the same everywhere, itself;
        with an EMPIRICAL term that changes with the column or the row, a copy with the term
        at (x, y)."""
        if (x is None and y is None) or not self.varies_over_field:
            return self
        return self.with_empirical_term(self.empirical.at_position(x, y))

    @property
    def varies_over_field(self):
        """True only with an EMPIRICAL term that changes with the column or the row."""
        return self.empirical is not None and self.empirical.position_dependent

    @property
    def field_nodes(self):
        """(x_nodes, y_nodes), pixels: the reference position; with an EMPIRICAL term that
        changes with the column (the row), the ends of the columns (rows) it was learned on
        (the term is linear in each, so interpolating between them is exact)."""
        x_ref, y_ref = self.reference_position
        nodes = [np.array([x_ref]), np.array([y_ref])]
        if self.varies_over_field:
            term = self.empirical
            for axis, (dependent, span) in enumerate(((term.column_dependent, term.x_range),
                                                      (term.row_dependent, term.y_range))):
                if dependent and span is not None and span[1] > span[0]:
                    nodes[axis] = np.array(span, dtype=float)
        return tuple(nodes)

    def _value_state(self):
        options = self.options
        options.pop("bf_table", None)
        return (self.data, self.bf_table, self.shifts.north, self.shifts.east, options,
                self.density_profile, self.metadata_state(),
                {name: (one.north, one.east) for name, one in self.amplifier_shifts.items()},
                [(one.north, one.east) for one in self.shift_samples])

    def with_shifts(self, shifts):
        """The same P0 and options with other boundary shifts (a new model; the BF table, if
        any, is recomputed from the new shifts, a custom ``bf_table`` is not carried over);
        the per-amplifier shifts are kept, so ``for_amplifier`` works on the result too."""
        options = self.options
        options.pop("bf_table", None)
        new = self.__class__(self.data, shifts, density_profile=self.density_profile, **options)
        return self.copy_metadata_to(new)

    @property
    def half_size(self):
        """Half-width, in pixels, of the pixel stamps used for R (covers the data)."""
        ny, nx = self.data.shape
        return int(np.ceil(max(nx / self.oversampling[1], ny / self.oversampling[0]) / 2.0))

    @property
    def bounding_box(self):
        """((y_min, y_max), (x_min, x_max)) of the PSF data around (x_0, y_0), pixels."""
        oy, ox = self.oversampling
        ny, nx = self.data.shape
        x_low = -self.origin[0] / ox - 0.5 / ox
        x_high = (nx - 1 - self.origin[0]) / ox + 0.5 / ox
        y_low = -self.origin[1] / oy - 0.5 / oy
        y_high = (ny - 1 - self.origin[1]) / oy + 0.5 / oy
        x_0, y_0 = float(self.x_0.value), float(self.y_0.value)
        return ((y_0 + y_low, y_0 + y_high), (x_0 + x_low, x_0 + x_high))

    def data_coordinates(self, dx, dy):
        """Fractional indices (xi, yi) into ``data`` of offsets (dx, dy) from the star centre,
        pixels, and the mask of the offsets outside the data."""
        xi = self.oversampling[1] * dx + self.origin[0]
        yi = self.oversampling[0] * dy + self.origin[1]
        ny, nx = self.data.shape
        outside = (xi < 0) | (xi > nx - 1) | (yi < 0) | (yi > ny - 1)
        return xi, yi, outside

    def evaluate_base(self, dx, dy):
        """Unit-flux P0 at offsets (dx, dy) from the star centre, zero outside the data."""
        shape = np.shape(dx)
        xi, yi, outside = self.data_coordinates(np.ravel(dx), np.ravel(dy))
        values = self._base_spline(xi, yi, grid=False)
        values[outside] = 0.0
        return values.reshape(shape)

    def evaluate(self, x, y, flux, x_0, y_0):
        """Model value at (x, y) for the given parameters (image unit per pixel).

        Parameters
        ----------
        x, y : float or array_like
            Pixel coordinates (any shape; pixel centres at integers).
        flux : float
            Total flux of the star, image unit; the BF term uses this value (never the
            instance's parameter).
        x_0, y_0 : float
            Star centre, pixels.

        Returns
        -------
        ndarray
            F p + g F |F| R[p] (G15 eq. scrambling_model), shaped like ``x``; g is
            `electrons_per_unit`.
        """
        flux = float(np.ravel(flux)[0]) if np.size(flux) == 1 else np.asarray(flux)
        x_0 = float(np.ravel(x_0)[0]) if np.size(x_0) == 1 else np.asarray(x_0)
        y_0 = float(np.ravel(y_0)[0]) if np.size(y_0) == 1 else np.asarray(y_0)
        if np.ndim(flux) or np.ndim(x_0) or np.ndim(y_0):
            msg = "FluxDependentPSF evaluates one star per call (no model sets)"
            raise BFPSFValueError(msg, np.shape(flux))
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        x, y = np.broadcast_arrays(x, y)
        shape = x.shape
        dx = np.ravel(x) - x_0
        dy = np.ravel(y) - y_0
        xi, yi, outside = self.data_coordinates(dx, dy)
        if not (np.isfinite(flux) and np.isfinite(x_0) and np.isfinite(y_0)):
            return np.full(shape, np.nan)
        self._warn_beyond_first_order(flux)
        if self.mode == "table":
            # F (p + g |F| R[p]) in one spline evaluation: P0's and R's splines share their
            # knots, so the sum of their coefficients is the spline of the sum
            result = flux * self._table_spline(self.electrons_per_unit * abs(flux))(
                xi, yi, grid=False)
            result[outside] = self.fill_value
            if self.empirical is not None:
                result += self._empirical_table_term(xi, yi, outside, flux, (x_0, y_0))
            return result.reshape(shape)
        result = flux * self._base_spline(xi, yi, grid=False)
        result[outside] = self.fill_value
        # Charge may cross the edge of the P0 support: keep it (conservation).
        result += self._bf_term_exact(dx, dy, flux, (x_0, y_0))
        return result.reshape(shape)

    def _table_spline(self, weight):
        """The spline of P0 + ``weight`` R[P0] (table mode): both tables are splined on the
        same grid with the same knots, so their coefficients add."""
        spline = copy.copy(self._base_spline)
        knots_x, knots_y, coefficients = self._base_spline.tck
        spline.tck = (knots_x, knots_y, coefficients + weight * self._bf_spline.tck[2])
        return spline

    # -- convenience -------------------------------------------------------------------------
    def star_image(self, flux, x=None, y=None, *, x_phase=None, y_phase=None, half_size=None):
        """Pixel image of a star of flux F, centred on the central pixel plus a phase.

        Always exact (R recomputed at the phase, with the exact boundary density when the
        model has a ``density_profile``), whatever the mode.

        Parameters
        ----------
        flux : float
            Flux, image unit.
        x, y : float, optional
            Image position of the star, pixels: its sub-pixel phase is the default phase (a
            single P(F) is the same everywhere; a field-varying one is taken there).
        x_phase, y_phase : float, optional
            Star centre minus the centre of the central pixel, pixels; default the phase of
            (x, y), 0 without them.
        half_size : int, optional
            The image is ``2 * half_size + 1`` pixels square.

        Returns
        -------
        ndarray [y, x]
            F p + g F |F| R[p]; divide by F for the normalised P(F).
        """
        x_phase, y_phase = star_phases(x, y, x_phase, y_phase)
        half = self.half_size if half_size is None else int(half_size)
        self._warn_beyond_first_order(flux)
        stamp = pixelised_stamp(self, x_phase=x_phase, y_phase=y_phase, half_size=half)
        return flux * stamp + self._stamp_delta(stamp, flux, x_phase, y_phase,
                                                self.position_or_reference(x, y))

    def __repr__(self):
        return (f"<FluxDependentPSF(flux={float(self.flux.value):g}, "
                f"x_0={float(self.x_0.value):g}, y_0={float(self.y_0.value):g}, "
                f"shape={self.data.shape}, oversampling={tuple(self.oversampling.tolist())}, "
                f"mode={self.mode!r}, flux_unit={self.flux_unit!r}, gain={self.gain!r})>")
