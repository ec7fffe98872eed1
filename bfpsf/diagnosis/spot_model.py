"""The base model of spot sizes: a model spot scaled to each peak and redistributed (G15 6.3).

The model spot is the base PSF P0 that `bfpsf psf` fits from the stars (``base_psf``), so that
what the loop finds is what P(F) needs; for size tables without images (measured data) it is a
GalSim profile matched to the sizes. The redistribution is the model layer's (`bfpsf.model.redistribution`): G15's boundary density
(Q_00 + Q_X) / 2 (eq. density-approx) or the exact density integrated along each boundary of
an oversampled model (`exact_boundary_density`, fourth order), the same operator `bfpsf psf`
and `bfpsf.redistribute` use.
"""

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from ..errors import BFPSFValueError
from ..model.bf_term import pixelised_stamp
from ..model.density import exact_boundary_density
from ..model.redistribution import redistribution_delta
from ..moments.adaptive import adaptive_moments_batch
from ..moments.shapes import distortion
from ..shifts import BoundaryShifts

__all__ = ["SpotForwardModel", "flux_of_peak", "FLUX_SCALE"]

#: Reference flux of the flux-scaled parameters (nonlinearity), e-.
FLUX_SCALE = 1e5

def _gaussian_fit_sigmas(stamps):
    """sigma_x, sigma_y of a pixel-integrated elliptical Gaussian fitted to each stamp (pixels).

    The measurement of Lage's spot tables (forward-modelled 2-D Gaussian, uniform weights).
    """
    n, ny, nx = stamps.shape
    edges_x = np.arange(nx + 1) - 0.5
    edges_y = np.arange(ny + 1) - 0.5

    def integral(edges, centre, sigma):
        cdf = 0.5 * (1 + erf((edges - centre) / (np.sqrt(2) * sigma)))
        return np.diff(cdf)

    sigma_x = np.empty(n)
    sigma_y = np.empty(n)
    for index, stamp in enumerate(stamps):
        total = stamp.sum()
        yy, xx = np.mgrid[:ny, :nx]
        x0 = (stamp * xx).sum() / total
        y0 = (stamp * yy).sum() / total

        def residuals(p):
            model = p[0] * np.outer(integral(edges_y, p[2], p[4]), integral(edges_x, p[1], p[3]))
            return (model - stamp).ravel()

        start = [total, x0, y0, 1.0, 1.0]
        fit = least_squares(residuals, start, x_scale=[total, 1, 1, 1, 1], xtol=1e-12,
                            ftol=1e-12, gtol=1e-12)
        sigma_x[index], sigma_y[index] = abs(fit.x[3]), abs(fit.x[4])
    return sigma_x, sigma_y


def flux_of_peak(peak_e, flux_e):
    """(c1, c2) of flux = c1 peak + c2 peak**2, least squares on measured stars (e-).

    The relation a star table holds between its peaks and fluxes: phase-averaged, with the
    peaks of bright stars lowered by their BF (the quadratic term).
    """
    peak = np.asarray(peak_e, dtype=float)
    flux = np.asarray(flux_e, dtype=float)
    good = np.isfinite(peak) & np.isfinite(flux) & (peak > 0)
    if good.sum() < 3:
        msg = f"only {good.sum()} stars with a finite peak and flux: cannot relate them"
        raise BFPSFValueError(msg, int(good.sum()))
    design = np.column_stack([peak[good], peak[good] ** 2])
    # relative errors: every star counts alike
    weight = 1.0 / flux[good]
    coefficients = np.linalg.lstsq(design * weight[:, None], flux[good] * weight, rcond=None)[0]
    return float(coefficients[0]), float(coefficients[1])


class SpotForwardModel:
    """Sizes of a model spot scaled to given peaks and redistributed (G15 section 6.3).

    The G15 procedure: a low-flux spot model, scaled to each flux, transformed by
    eq. scrambling_model, then measured like the data. The model spot is a GalSim profile,
    pixel-integrated at ``phases x phases`` sub-pixel positions (sizes averaged over them).

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux spot profile without the pixel (e.g. ``galsim.Gaussian``, ``galsim.Moffat``).
    shifts : BoundaryShifts
        Boundary shifts a^X, 1/e-.
    stamp_size : int, optional
        Stamp side, pixels (odd). Default: 8 sigma of the profile, at least 11.
    phases : int, optional
        Sub-pixel positions per axis (default 3).
    oversampling : int, optional
        Fine samples per pixel for the exact boundary density (default 10, at least 2).
    measure : {'moments', 'gaussian_fit'}, optional
        Adaptive moments (`bfpsf.moments.adaptive`, G15 section 3.2, default) or a
        pixel-integrated Gaussian fit (as Lage's spot tables).
    base_psf : FluxDependentPSF, optional
        A P0 fitted from the stars (`bfpsf.model.psf_fit.fit_psf`): its pixelised P0 at each
        phase is the model's unit charge, so the loop's sizes are those of the P(F) that
        ``bfpsf psf`` builds. ``profile`` then only gives the exact boundary density (the
        ``boundary_density`` candidate), which a pixel-integrated P0 does not hold.
    peak_to_flux : (float, float), optional
        (c1, c2): the data's total flux at a peak p is c1 p + c2 p**2, fitted on the measured
        stars (`flux_of_peak`). Measured peaks are averaged over sub-pixel phases and lowered
        by the BF of bright stars; with this relation the model is evaluated at the flux the
        stars were measured at, as ``bfpsf slope --psf`` evaluates P(F).

    Notes
    -----
    Without ``peak_to_flux``, the peak of a spot of flux F is F times the central-pixel
    fraction of the centred model spot (the peaks of tables computed from fluxes).
    """

    def __init__(self, profile, shifts, *, stamp_size=None, phases=3, oversampling=10,
                 measure="moments", base_psf=None, peak_to_flux=None):
        import galsim

        if not isinstance(profile, galsim.GSObject):
            msg = f"profile must be a galsim.GSObject, got {type(profile).__name__}"
            raise BFPSFValueError(msg, profile)
        if not isinstance(shifts, BoundaryShifts):
            shifts = getattr(shifts, "shifts", shifts)
            if not isinstance(shifts, BoundaryShifts):
                msg = "shifts must be a BoundaryShifts (or carry one in .shifts)"
                raise BFPSFValueError(msg, shifts)
        if measure not in ("moments", "gaussian_fit"):
            msg = f"measure must be 'moments' or 'gaussian_fit', got {measure!r}"
            raise BFPSFValueError(msg, measure)
        self.profile = profile.withFlux(1.0)
        self.base_psf = base_psf
        self.peak_to_flux = None if peak_to_flux is None else tuple(map(float, peak_to_flux))
        self.shifts = shifts
        self.measure = measure
        if stamp_size is None:
            sigma = galsim.hsm.FindAdaptiveMom(
                self.profile.drawImage(nx=64, ny=64, scale=1.0)).moments_sigma
            stamp_size = max(11, int(2 * np.ceil(4 * sigma) + 1))
        self.stamp_size = int(stamp_size) | 1
        self.oversampling = int(oversampling)
        grid = (np.arange(phases) + 0.5) / phases - 0.5
        self.phases = [(px, py) for py in grid for px in grid]
        self._cache = {}
        self._fine = [self._draw_fine(px, py) for px, py in self.phases]
        centred = self._draw_fine(0.0, 0.0)[0]
        self.peak_fraction = float(centred[self.stamp_size // 2, self.stamp_size // 2])

    def _draw_fine(self, px, py):
        """Pixel charges and exact boundary densities of the unit-flux spot at a phase
        (`bfpsf.model.redistribution.exact_boundary_density`); the charges are the base
        PSF's pixelised P0 when there is one."""
        s, n = self.oversampling, self.stamp_size
        fine = self.profile.drawImage(nx=n * s, ny=n * s, scale=1.0 / s, method="no_pixel",
                                      offset=(px * s, py * s)).array
        pixels, (north, east) = exact_boundary_density(fine, s)
        if self.base_psf is not None:
            pixels = pixelised_stamp(self.base_psf, x_phase=px, y_phase=py, half_size=n // 2)
        return pixels, north, east

    def fluxes(self, peaks_e):
        """Total flux of a spot of each peak, e- (``peak_to_flux``, or the centred peak
        fraction)."""
        peaks = np.asarray(peaks_e, dtype=float)
        if self.peak_to_flux is None:
            return peaks / self.peak_fraction
        c1, c2 = self.peak_to_flux
        return c1 * peaks + c2 * peaks ** 2

    def stamps(self, peaks_e, *, shifts=None, density="approx", second_order=0.0,
               nonlinearity=0.0):
        """Redistributed model stamps, shape (n_peaks, n_phases, size, size), e-.

        Parameters
        ----------
        peaks_e : array_like
            Peaks, e-.
        shifts : BoundaryShifts, optional
            Override the model's shifts.
        density : {'approx', 'exact'}
            (Q_00 + Q_X)/2 (G15 eq. density-approx) or the exact boundary density.
        second_order : float
            Scale t of the second-order term R[Q + R[Q]] - R[Q].
        nonlinearity : float
            c: pixel values v -> v (1 + c v / 1e5).
        """
        shifts = self.shifts if shifts is None else shifts
        fluxes = self.fluxes(peaks_e)
        out = np.empty((fluxes.size, len(self.phases), self.stamp_size, self.stamp_size))
        for j, (pixels, north, east) in enumerate(self._fine):
            for i, flux in enumerate(fluxes):
                charge = flux * pixels
                exact = (flux * north, flux * east) if density == "exact" else None
                delta = redistribution_delta(charge, shifts, density=exact, workers=1)
                image = charge + delta
                if second_order:
                    image = image + second_order * (
                        redistribution_delta(image, shifts, workers=1) - delta)
                if nonlinearity:
                    image = image * (1.0 + nonlinearity * image / FLUX_SCALE)
                out[i, j] = image
        return out

    def sizes(self, peaks_e, **options):
        """(sigma_x, sigma_y) of the model at each peak, pixels, averaged over the phases."""
        def hashable(value):
            # shifts by content (an id() could be reused by a new object)
            if isinstance(value, BoundaryShifts):
                return (value.north.tobytes(), value.east.tobytes())
            return value

        key = (tuple(np.round(np.asarray(peaks_e, float), 6)),
               tuple(sorted((k, hashable(v)) for k, v in options.items())))
        if key in self._cache:
            return self._cache[key]
        stamps = self.stamps(peaks_e, **options)
        n_peaks, n_phases = stamps.shape[:2]
        flat = stamps.reshape(-1, self.stamp_size, self.stamp_size)
        if self.measure == "moments":
            result = adaptive_moments_batch(flat)
            sigma_x, sigma_y = np.sqrt(result.mxx), np.sqrt(result.myy)
            failed = np.flatnonzero(np.asarray(result.flags) != 0)
            if failed.size:
                # Only spots with no adaptive-moment solution are flagged (HSM fails on them
                # too: centred spots with sigma below ~0.7 px).
                flag = result[int(failed[0])].flag_string
                why = (f"the model spot outgrew its {self.stamp_size}-pixel stamp"
                       if "edge" in flag else
                       "the spot is too undersampled for adaptive moments (Python: "
                       "SpotForwardModel(..., measure='gaussian_fit'))")
                msg = (f"adaptive moments failed on {failed.size} of {len(flat)} model stamps "
                       f"({flag}): {why}")
                raise BFPSFValueError(msg, failed.size)
        else:
            sigma_x, sigma_y = _gaussian_fit_sigmas(flat)
        value = (sigma_x.reshape(n_peaks, n_phases).mean(axis=1),
                 sigma_y.reshape(n_peaks, n_phases).mean(axis=1))
        self._cache[key] = value
        return value

    def cross(self, peaks_e):
        """The model's cross moment e2 = 2 Mxy / (Mxx + Myy) at each peak (adaptive moments,
        averaged over the phases; `SizeTable.cross` measures the stars' the same way); 0
        where the sizes are Gaussian fits (``measure='gaussian_fit'``)."""
        peaks = np.asarray(peaks_e, float)
        if self.measure != "moments":
            return np.zeros(peaks.size)
        key = ("cross", tuple(np.round(peaks, 6)))
        if key not in self._cache:
            stamps = self.stamps(peaks)
            result = adaptive_moments_batch(stamps.reshape(-1, self.stamp_size,
                                                           self.stamp_size))
            e2 = distortion(result.mxx, result.myy, result.mxy)[1]
            self._cache[key] = e2.reshape(stamps.shape[:2]).mean(axis=1)
        return self._cache[key]

