"""The BF term of a flux-dependent PSF: R[P0] at the star's phase, and its operator.

`bf_response_table` tabulates R[p] (G15 eq. scrambling_model on the unit pixelised stamp) at
every sub-pixel phase of an oversampled P0, for the table mode of `FluxDependentPSF`;
`pixelised_stamp` samples a P0 at a phase; `BFTerm` holds the operator a model applies to a
star (one step of G15's, or the build-up; G15's mean boundary density or the exact one of the
star's profile), the first-order limit of the model, and the EMPIRICAL term of a refined
calibration on top.
"""

import warnings

import numpy as np
from scipy.interpolate import RectBivariateSpline

from ..errors import BFPSFWarning
from .buildup import redistribute_buildup
from .density import exact_boundary_density
from .empirical import PATTERNS, pattern_tables
from .redistribution import redistribution_delta

__all__ = ["BFTerm", "bf_response_table", "exact_density_table", "pixelised_stamp",
           "star_phases"]


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


def exact_density_table(profile, shifts, shape, oversampling, sub):
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


class BFTerm:
    """The BF term of `FluxDependentPSF` (its ``shifts``, ``buildup_steps``,
    ``density_profile``, ``empirical`` and tables): R at any phase, the operator on any
    charge, and the flux beyond which the first-order model breaks."""

    def _bf_term_exact(self, dx, dy, flux, position=None):
        """g F |F| R at offsets (dx, dy), R computed on the pixel grid through each point
        (and the EMPIRICAL term of a star at ``position`` = (x, y), `_stamp_delta`)."""
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
            delta = self._stamp_delta(stamp, flux, -px, -py, position)
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

    def _stamp_delta(self, stamp, flux, x_phase, y_phase, position=None):
        """BF term (image unit) of a star of flux F on its pixelised unit stamp (star at
        ``(x_phase, y_phase)`` from the central pixel), as mode='exact' computes it, with the
        EMPIRICAL term of a star at ``position`` = (x, y) (default the term's reference)."""
        density = self.boundary_density(x_phase, y_phase, stamp.shape[0] // 2)
        if self.buildup_steps is not None:
            delta = self._buildup_delta(stamp, flux, density)
        else:
            delta = self.electrons_per_unit * flux * abs(flux) * redistribution_delta(
                stamp, self.shifts, density=density)
        # the EMPIRICAL term of a refined calibration (issue 22; not physics), on the star's
        # image with its BF: the table mode interpolates the same (`_empirical_table_term`)
        if self.empirical is not None:
            x, y = (None, None) if position is None else position
            delta = delta + self.empirical.delta(flux * stamp + delta,
                                                 self.electrons_per_unit * abs(flux), x,
                                                 total=flux, y=y)
        return delta

    def _empirical_table_term(self, xi, yi, outside, flux, position):
        """The EMPIRICAL term in table mode (image unit) at fractional data indices, for a
        star of flux F at ``position`` = (x, y): sum_k v_k(F, x, y) B_k[F p + g F |F| R], to
        second order
        in the BF term, from the series of B_k[P0] along R tabulated at every phase
        (`bfpsf.model.empirical.pattern_tables`), as ``star_image`` applies it to the star's
        image."""
        # in a dict made by the constructor, so the copies (which share P0 and R) share it
        kind = self.empirical.kind
        splines = self._tables.get(("pattern_splines", kind))
        if splines is None:
            grid = (np.arange(self.data.shape[1]), np.arange(self.data.shape[0]))
            tables = pattern_tables(self.data, self.bf_table, self.oversampling, kind)
            splines = {pattern: [RectBivariateSpline(*grid, table.T, kx=3, ky=3, s=0)
                                 for table in tables[pattern]] for pattern in PATTERNS}
            self._tables[("pattern_splines", kind)] = splines
        g = self.electrons_per_unit
        term = np.zeros(np.shape(xi))
        changes = self.empirical.variance_change(g * abs(flux), x=position[0], y=position[1])
        for pattern, change in zip(PATTERNS, changes):
            if change:
                e = g * abs(flux)
                term += float(change) * flux * sum(e ** n * spline(xi, yi, grid=False)
                                                   for n, spline in enumerate(splines[pattern]))
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
