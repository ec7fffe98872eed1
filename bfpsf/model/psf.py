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
import warnings

import numpy as np
from astropy.modeling import Parameter
from scipy.interpolate import RectBivariateSpline

from ..errors import BFPSFValueError, BFPSFWarning
from ..shifts import as_shifts
from .base import BFPSFModel
from .buildup import redistribute_buildup
from .density import exact_boundary_density
from .redistribution import redistribution_delta

__all__ = ["FluxDependentPSF", "bf_response_table", "pixelised_stamp", "star_phases"]

_MODES = ("table", "exact")
_FLUX_UNITS = ("electron", "adu")


def _validate_oversampling(oversampling):
    values = np.atleast_1d(np.asarray(oversampling))
    if values.size == 1:
        values = np.repeat(values, 2)
    if (values.size != 2 or not np.all(np.isfinite(values))
            or np.any(values != np.round(values)) or np.any(values < 1)):
        msg = f"oversampling must be one or two (y, x) integers >= 1, got {oversampling!r}"
        raise BFPSFValueError(msg, oversampling)
    return values.astype(int)


def _validate_units(flux_unit, gain):
    """(flux_unit, gain) of a model; a gain without a stated flux unit is refused."""
    if gain is not None:
        if not (np.isfinite(gain) and gain > 0):
            msg = f"gain must be a positive number of e-/ADU, got {gain!r}"
            raise BFPSFValueError(msg, gain)
        gain = float(gain)
        if flux_unit is None:
            msg = ("gain given without flux_unit: say flux_unit='adu' (fluxes and images in "
                   "ADU, the BF term scaled by the gain) or flux_unit='electron' (the gain "
                   "only recorded for converting images)")
            raise BFPSFValueError(msg, gain)
    flux_unit = "electron" if flux_unit is None else flux_unit
    if flux_unit not in _FLUX_UNITS:
        msg = f"flux_unit must be one of {_FLUX_UNITS}, got {flux_unit!r}"
        raise BFPSFValueError(msg, flux_unit)
    if flux_unit == "adu" and gain is None:
        msg = "flux_unit='adu' needs the gain (e-/ADU) that turns the fluxes into charge"
        raise BFPSFValueError(msg, flux_unit)
    return flux_unit, gain


def _validate_data(data):
    if not isinstance(data, np.ndarray) or data.ndim != 2:
        msg = f"data must be a 2-D numpy array [y, x], got {type(data).__name__}"
        raise BFPSFValueError(msg, getattr(data, "shape", None))
    if not np.all(np.isfinite(data)):
        msg = f"data has {np.count_nonzero(~np.isfinite(data))} non-finite values"
        raise BFPSFValueError(msg)
    if min(data.shape) < 4:
        msg = f"data must be at least 4 x 4 (cubic spline), got shape {data.shape}"
        raise BFPSFValueError(msg, data.shape)
    return np.array(data, dtype=float)


def bf_response_table(data, shifts, oversampling):
    """R[p] at every sub-pixel phase of an oversampled PSF, on the same grid, 1/e-.

    Parameters
    ----------
    data : ndarray [y, x]
        Oversampled PSF with the pixel response included, normalised so that every phase
        ``data[a::oy, b::ox]`` is the unit-flux pixelised PSF at that phase (sum ``oy * ox``
        overall, as photutils `~photutils.psf.ImagePSF` expects).
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    oversampling : (int, int)
        (oy, ox).

    Returns
    -------
    ndarray, same shape as ``data``
        ``table[a::oy, b::ox] = redistribution_delta(data[a::oy, b::ox], shifts)``: the charge
        each pixel gains per e-**2 of flux (G15 eq. scrambling_model), for the star at the
        phase of each oversampled pixel. Each phase sums to zero (charge conservation).
    """
    oy, ox = oversampling
    table = np.zeros_like(data)
    for a in range(oy):
        for b in range(ox):
            table[a::oy, b::ox] = redistribution_delta(data[a::oy, b::ox], shifts)
    return table


def _exact_density_table(profile, shifts, shape, oversampling, sub):
    """`bf_response_table` with the exact boundary density of a GalSim profile (no pixel)."""
    origin = (shape[1] - 1) / 2.0
    table = np.zeros(shape)
    for a in range(oversampling):
        for b in range(oversampling):
            rows = np.arange(a, shape[0], oversampling)
            cols = np.arange(b, shape[1], oversampling)
            # Offsets of the stamp pixel centres from the star, pixels.
            u_x0 = (cols[0] - origin) / oversampling
            u_y0 = (rows[0] - origin) / oversampling
            # Star position relative to the stamp's true centre, in sub-pixels.
            offset = ((-u_x0 - (cols.size - 1) / 2.0) * sub, (-u_y0 - (rows.size - 1) / 2.0) * sub)
            fine = profile.drawImage(nx=cols.size * sub, ny=rows.size * sub, scale=1.0 / sub,
                                     offset=offset, dtype=np.float64).array
            stamp, density = exact_boundary_density(fine, sub)
            table[a::oversampling, b::oversampling] = redistribution_delta(
                stamp, shifts, density=density)
    return table


def _phase_density(profile, x_phase, y_phase, half_size, sub):
    """Exact boundary density of a unit-flux GalSim profile (no pixel) on the stamp of
    `pixelised_stamp` (star at ``(x_phase, y_phase)`` from the central pixel's centre)."""
    n = (2 * half_size + 1) * sub  # the fine image's centre is the central pixel's centre
    fine = profile.drawImage(nx=n, ny=n, scale=1.0 / sub, offset=(x_phase * sub, y_phase * sub),
                             dtype=np.float64).array  # charge per sub-pixel
    return exact_boundary_density(fine, sub)[1]


def star_phases(x, y, x_phase=None, y_phase=None):
    """(x_phase, y_phase) of a star: the given phases, else those of its position (x, y)
    (``x - round(x)``), else 0."""
    if x_phase is None:
        x_phase = 0.0 if x is None else float(x - np.floor(x + 0.5))
    if y_phase is None:
        y_phase = 0.0 if y is None else float(y - np.floor(y + 0.5))
    return float(x_phase), float(y_phase)


def pixelised_stamp(psf, *, x_phase=0.0, y_phase=0.0, half_size=None):
    """Unit-flux pixelised P0 of ``psf`` on the pixel grid of a star at a sub-pixel phase.

    Parameters
    ----------
    psf : FluxDependentPSF
    x_phase, y_phase : float, optional
        Star centre minus the centre of the stamp's central pixel, pixels.
    half_size : int, optional
        The stamp is ``2 * half_size + 1`` pixels square; default covers the PSF data.

    Returns
    -------
    ndarray [y, x]
        p(k - x_phase, l - y_phase) for k, l = -half_size..half_size.
    """
    half_size = psf.half_size if half_size is None else int(half_size)
    offsets = np.arange(-half_size, half_size + 1, dtype=float)
    dy, dx = np.meshgrid(offsets - y_phase, offsets - x_phase, indexing="ij")
    return psf.evaluate_base(dx, dy)


class FluxDependentPSF(BFPSFModel):
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

    flux = Parameter(default=1, description="Total flux of the star (image unit)")
    x_0 = Parameter(default=0, description="x position of the star centre (pixels)")
    y_0 = Parameter(default=0, description="y position of the star centre (pixels)")

    @property
    def reference_position(self):
        """The position taken when none is given: (0, 0), the model being the same
        everywhere; with an EMPIRICAL term that changes with the column, that term's
        reference column (rounded to a pixel centre) and row 0."""
        if self.empirical is not None and self.empirical.position_dependent:
            return (float(np.floor(self.empirical.x_reference + 0.5)), 0.0)
        return (0.0, 0.0)

    def __init__(self, data, shifts, *, flux=flux.default, x_0=x_0.default, y_0=y_0.default,
                 origin=None, oversampling=1, flux_unit=None, gain=None, mode="table",
                 buildup_steps=None, bf_table=None, fill_value=0.0, density_profile=None,
                 density_oversampling=8, **kwargs):
        self.data = _validate_data(data)
        self.data.flags.writeable = False
        self.shifts = as_shifts(shifts)
        self.oversampling = _validate_oversampling(oversampling)
        if origin is None:
            origin = ((self.data.shape[1] - 1) / 2.0, (self.data.shape[0] - 1) / 2.0)
        origin = np.asarray(origin, dtype=float)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            msg = f"origin must be two finite numbers (x, y), got {origin!r}"
            raise BFPSFValueError(msg, origin)
        self.origin = origin
        self.flux_unit, self.gain = _validate_units(flux_unit, gain)
        if mode not in _MODES:
            msg = f"mode must be one of {_MODES}, got {mode!r}"
            raise BFPSFValueError(msg, mode)
        if buildup_steps is not None:
            if int(buildup_steps) != buildup_steps or buildup_steps < 1:
                msg = f"buildup_steps must be a positive integer, got {buildup_steps!r}"
                raise BFPSFValueError(msg, buildup_steps)
            if mode != "exact":
                msg = ("buildup_steps makes the BF response non-quadratic in flux; it requires "
                       f"mode='exact', got mode={mode!r}")
                raise BFPSFValueError(msg, mode)
            buildup_steps = int(buildup_steps)
        self.buildup_steps = buildup_steps
        if bf_table is not None:
            bf_table = np.array(bf_table, dtype=float)
            if mode != "table" or bf_table.shape != self.data.shape:
                msg = (f"bf_table must have the shape of data {self.data.shape} and needs "
                       f"mode='table', got shape {bf_table.shape} and mode={mode!r}")
                raise BFPSFValueError(msg, bf_table.shape)
        if int(density_oversampling) != density_oversampling or density_oversampling < 2:
            msg = f"density_oversampling must be an integer >= 2, got {density_oversampling!r}"
            raise BFPSFValueError(msg, density_oversampling)
        self.density_profile = density_profile
        self.density_oversampling = int(density_oversampling)
        self.mode = mode
        self.fill_value = float(fill_value)
        #: Product metadata (`bfpsf.model.base`): ``calibration`` (file name of the shifts),
        #: ``linearity_c_per_1e5``, ``flux_correction`` and its error.
        self._init_metadata()
        if getattr(shifts, "refinement", None):
            from .empirical import empirical_of

            # a calibration refined by `bfpsf diagnose --output-calib`: its EMPIRICAL term
            self.empirical = empirical_of(shifts)
        #: Shifts drawn from the calibration's uncertainty (`Calibration.shift_samples`):
        #: predictions made with this model propagate them (``bfpsf slope --psf``).
        self.shift_samples = tuple(shifts.shift_samples()) if hasattr(shifts, "shift_samples") else ()
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
                bf_table = _exact_density_table(density_profile, self.shifts, self.data.shape,
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
        over = int(_validate_oversampling(oversampling)[0])
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
        with an EMPIRICAL term that changes with the column, a copy with the term at ``x``."""
        if x is None or self.empirical is None or not self.empirical.position_dependent:
            return self
        return self.with_empirical_term(self.empirical.at_position(x))

    @property
    def varies_over_field(self):
        """True only with an EMPIRICAL term that changes with the column."""
        return self.empirical is not None and self.empirical.position_dependent

    @property
    def field_nodes(self):
        """(x_nodes, y_nodes), pixels: the reference position; with an EMPIRICAL term that
        changes with the column, the ends of the columns it was learned on (the term is
        linear in the column, so interpolating between them is exact)."""
        x_ref, y_ref = self.reference_position
        if self.varies_over_field and self.empirical.x_range is not None:
            low, high = self.empirical.x_range
            if high > low:
                return np.array([low, high], dtype=float), np.array([y_ref])
        return np.array([x_ref]), np.array([y_ref])

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

    def _bf_term_exact(self, dx, dy, flux, x=None):
        """g F |F| R at offsets (dx, dy), R computed on the pixel grid through each point
        (and the EMPIRICAL term of a star at column ``x``, `_stamp_delta`)."""
        result = np.zeros(dx.shape)
        # The grid through a point (x, y) has the phase of its offset from the star.
        phase_x = dx - np.floor(dx + 0.5)
        phase_y = dy - np.floor(dy + 0.5)
        keys = np.round(phase_x * 1e9) + 3e9 * np.round(phase_y * 1e9)
        half = self.half_size
        for key in np.unique(keys):
            members = keys == key
            px, py = phase_x[members][0], phase_y[members][0]
            # Offsets dx = n + px from the star: the star sits at phase -px on this grid.
            stamp = pixelised_stamp(self, x_phase=-px, y_phase=-py, half_size=half)
            delta = self._stamp_delta(stamp, flux, -px, -py, x)
            col = np.rint(dx[members] - px).astype(int) + half
            row = np.rint(dy[members] - py).astype(int) + half
            inside = (col >= 0) & (col <= 2 * half) & (row >= 0) & (row <= 2 * half)
            values = np.zeros(col.shape)
            values[inside] = delta[row[inside], col[inside]]
            result[members] = values
        return result

    @property
    def first_order_flux(self):
        """Largest |flux| (image unit) for which P(F) = P0 + F R[P0] stays above -1 % of the
        peak of P0 everywhere: beyond it G15's first-order model is broken (pixels go negative)
        and `evaluate` and `star_image` warn (`~bfpsf.errors.BFPSFWarning`)."""
        if getattr(self, "_first_order_flux", None) is None:
            if self.bf_table is not None:
                base, response = self.data, self.electrons_per_unit * self.bf_table
            else:
                base = pixelised_stamp(self)
                response = self.electrons_per_unit * redistribution_delta(base, self.shifts)
            # pixels the BF term lowers where P0 is positive (a fitted P0 can be slightly
            # negative in its noisy wings: a pixel at -0.9997 % of the peak, just inside the
            # margin, with a response of 1e-13 gave a limit of 1e6 e- for a grid node)
            margin = base + 0.01 * base.max()
            shrinking = (response < 0) & (base > 0)
            limit = np.inf
            if np.any(shrinking):
                limit = float(np.min(margin[shrinking] / -response[shrinking]))
            self._first_order_flux = limit
        return self._first_order_flux

    def _warn_beyond_first_order(self, flux):
        if abs(flux) > self.first_order_flux:
            warnings.warn(f"flux {flux:.3g} is beyond the first-order BF model (G15): P(F) goes "
                          f"negative above {self.first_order_flux:.3g} for these boundary shifts",
                          BFPSFWarning, stacklevel=3)

    def _stamp_delta(self, stamp, flux, x_phase, y_phase, x=None):
        """BF term (image unit) of a star of flux F on its pixelised unit stamp (star at
        ``(x_phase, y_phase)`` from the central pixel), as mode='exact' computes it, with the
        EMPIRICAL term of a star at column ``x`` (default the term's reference column)."""
        density = self.boundary_density(x_phase, y_phase, stamp.shape[0] // 2)
        if self.buildup_steps is not None:
            delta = self._buildup_delta(stamp, flux, density)
        else:
            delta = self.electrons_per_unit * flux * abs(flux) * redistribution_delta(
                stamp, self.shifts, density=density)
        # the EMPIRICAL term of a refined calibration (issue 22; not physics), on the star's
        # image with its BF: the table mode interpolates the same (`_empirical_table_term`)
        if self.empirical is not None:
            delta = delta + self.empirical.delta(flux * stamp + delta,
                                                 self.electrons_per_unit * abs(flux), x)
        return delta

    def _empirical_table_term(self, xi, yi, outside, flux, x):
        """The EMPIRICAL term in table mode (image unit) at fractional data indices, for a
        star of flux F at column ``x``: sum_k v_k(F, x) B_k[F p + g F |F| R], with B_k of P0
        and of R tabulated at every phase (`bfpsf.model.empirical.pattern_tables`), as
        ``star_image`` applies it to the star's image."""
        from .empirical import PATTERNS, pattern_tables

        # in a dict made by the constructor, so the copies (which share P0 and R) share it
        splines = self._tables.get("pattern_splines")
        if splines is None:
            grid = (np.arange(self.data.shape[1]), np.arange(self.data.shape[0]))
            tables = [pattern_tables(table, self.oversampling)
                      for table in (self.data, self.bf_table)]
            splines = {pattern: [RectBivariateSpline(*grid, table[pattern].T, kx=3, ky=3, s=0)
                                 for table in tables] for pattern in PATTERNS}
            self._tables["pattern_splines"] = splines
        g = self.electrons_per_unit
        term = np.zeros(np.shape(xi))
        for pattern, change in zip(PATTERNS, self.empirical.variance_change(g * abs(flux),
                                                                            x=x)):
            if change:
                base, bf = splines[pattern]
                term += float(change) * (flux * base(xi, yi, grid=False)
                                         + g * flux * abs(flux) * bf(xi, yi, grid=False))
        term[outside] = 0.0
        return term

    def _buildup_delta(self, stamp, flux, density=None):
        """BF term of the star (image unit) with the build-up integrated, odd in F."""
        to_electrons = self.electrons_per_unit
        charge = to_electrons * abs(flux) * stamp
        if density is not None:  # per unit flux -> e- of this star
            density = tuple(to_electrons * abs(flux) * part for part in density)
        return np.sign(flux) * self.charge_delta(charge, density) / to_electrons

    def charge_delta(self, charge_e, density=None):
        """The charge each pixel gains under this model's operator, e-.

        One step of G15 eq. scrambling_model, or ``buildup_steps`` steps of the build-up;
        ``density`` is the boundary density of the charge (`boundary_density`), default G15's
        mean. Applied to the summed charge of several stars it gives their BF including the
        cross terms between them, with the same physics as each star's own term.

        Parameters
        ----------
        charge_e : ndarray [y, x]
            Charge without BF, e-.
        density : (ndarray, ndarray), optional

        Returns
        -------
        ndarray [y, x]
        """
        if self.buildup_steps is not None:
            collected = redistribute_buildup(charge_e, self.shifts, nsteps=self.buildup_steps,
                                             density=density)
            return collected - charge_e
        return redistribution_delta(charge_e, self.shifts, density=density)

    def boundary_density(self, x_phase=0.0, y_phase=0.0, half_size=None):
        """Exact boundary density of the unit-flux star on its stamp, or None (G15's mean).

        The density of ``density_profile`` (`bfpsf.model.redistribution.exact_boundary_density`)
        for the stamp of `star_image` (``2 * half_size + 1`` pixels, star at the phase): north
        boundaries ``(2h, 2h + 1)``, east ``(2h + 1, 2h)``, per unit flux. None without a
        ``density_profile``.
        """
        if self.density_profile is None:
            return None
        half = self.half_size if half_size is None else int(half_size)
        return _phase_density(self.density_profile, x_phase, y_phase, half,
                              self.density_oversampling)

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
                result += self._empirical_table_term(xi, yi, outside, flux, x_0)
            return result.reshape(shape)
        result = flux * self._base_spline(xi, yi, grid=False)
        result[outside] = self.fill_value
        # Charge may cross the edge of the P0 support: keep it (conservation).
        result += self._bf_term_exact(dx, dy, flux, x_0)
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
                                                self.position_or_reference(x, y)[0])

    def __repr__(self):
        return (f"<FluxDependentPSF(flux={float(self.flux.value):g}, "
                f"x_0={float(self.x_0.value):g}, y_0={float(self.y_0.value):g}, "
                f"shape={self.data.shape}, oversampling={tuple(self.oversampling.tolist())}, "
                f"mode={self.mode!r}, flux_unit={self.flux_unit!r}, gain={self.gain!r})>")
