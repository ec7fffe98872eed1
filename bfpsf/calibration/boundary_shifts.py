"""From measured area coefficients a(dx, dy) to boundary shifts a^N, a^E: the default route.

Two solvers are available:

* ``'electrostatic'`` (default, `bfpsf.calibration.shifts_electrostatic`): a physical model of
  the sensor (Astier & Regnault 2023) fitted to every measured lag with the covariance of a.
  Every boundary, the nearest ones included, has the physical sign by construction, and the
  N/E split of a(0, 0), which flat-field areas do not see, is fixed by the physics.
* ``'ei'`` (G15 section 6.1, `bfpsf.calibration.shifts_ei`): the Ei smoothing model of the
  far lags plus an exact linear solve. It reproduces every measured a, but its N/E split of
  a(0, 0) follows the far lags' radial profile, which finite flats measure poorly: on 150
  small E2V flats it moved the E/W boundaries of a charged pixel outward.

Both return an object with ``shifts``, ``north_err``, ``east_err``, ``samples_north``,
``samples_east`` (shifts drawn from the calibration's uncertainty, propagated by every
prediction), ``chi2``, ``dof`` and ``method``. `shift_warnings` says in words when the split or
the amplitude is poorly determined.
"""

import numpy as np

from ..errors import BFPSFValueError
from .shifts_ei import solve_ei_shifts
from .electrostatic_fit import fit_electrostatic

__all__ = ["SHIFT_METHODS", "solve_boundary_shifts", "shift_warnings", "split_fraction"]

#: Solvers of `solve_boundary_shifts`, the default first.
SHIFT_METHODS = ("electrostatic", "ei")

# Thresholds of `shift_warnings`: relative 1-sigma error of the N/E split and of the amplitude
# a^N(0,0) + a^E(0,0) above which they are called poorly determined, the chi2/dof above which
# a model does not describe the a-matrix, and the Ei solver's sensitivity to p1 (G15: ~1 %).
SPLIT_TOLERANCE = 0.15
AMPLITUDE_TOLERANCE = 0.10
CHI2_TOLERANCE = 3.0
EI_SENSITIVITY_TOLERANCE = 0.5


def solve_boundary_shifts(area, area_err=None, *, area_cov=None, method="electrostatic",
                          n_samples=100, seed=0, thickness=10.0):
    """Boundary shifts a^N, a^E (1/e-) from measured area coefficients.

    Parameters
    ----------
    area : array_like, shape (n + 1, n + 1)
        a(dx, dy) = C(dx, dy) / (V mu), 1/e-, [dy, dx], dx, dy = 0..n; a(0, 0) < 0
        (G15 eq. covar).
    area_err : array_like, optional
        1-sigma errors of ``area``.
    area_cov : array_like, shape ((n + 1)^2, (n + 1)^2), optional
        Full covariance of ``area.ravel()``.
    method : {'electrostatic', 'ei'}, optional
        The solver (module notes). Default ``'electrostatic'``.
    n_samples : int, optional
        Samples of the shifts drawn from the calibration error (0: none). Default 100.
    seed : int, optional
        Seed of the samples.
    thickness : float, optional
        Sensor thickness in pixels (electrostatic model only). Default 10.

    Returns
    -------
    `~bfpsf.calibration.electrostatic_fit.ElectrostaticFit` or
    `~bfpsf.calibration.shifts_ei.ShiftSolution`
    """
    if method == "electrostatic":
        return fit_electrostatic(area, area_err, area_cov=area_cov, thickness=thickness,
                                 n_samples=n_samples, seed=seed)
    if method == "ei":
        return solve_ei_shifts(area, area_err, area_cov=area_cov, n_monte_carlo=n_samples,
                               seed=seed)
    msg = f"method must be one of {SHIFT_METHODS}, got {method!r}"
    raise BFPSFValueError(msg, method)


def split_fraction(north, east):
    """a^N(0,0) / (a^N(0,0) + a^E(0,0)) of shift grids [..., 2m+1, 2m+1]: the N/E split."""
    m = np.shape(north)[-1] // 2
    centre_north = np.asarray(north)[..., m, m]
    centre_east = np.asarray(east)[..., m, m]
    return centre_north / (centre_north + centre_east)


def shift_warnings(solution):
    """Plain-language warnings about a shift solution (an empty list when all is well).

    Raised when a boundary of the charged pixel moves outward (unphysical), when the N/E split
    of a(0, 0) or the amplitude a^N(0,0) + a^E(0,0) has a relative error above
    `SPLIT_TOLERANCE` / `AMPLITUDE_TOLERANCE` (from the samples), when the fit does not
    describe the a-matrix (chi2/dof above `CHI2_TOLERANCE`), when electrostatic parameters end
    on their physical bounds, and when the Ei solution depends on its smoothing model.
    """
    warnings = []
    shifts = solution.shifts
    m = shifts.radius
    north, east = shifts.north[m, m], shifts.east[m, m]
    for label, value in (("a^N(0,0)", north), ("a^E(0,0)", east)):
        if not value < 0:
            side = "N/S" if label == "a^N(0,0)" else "E/W"
            warnings.append(f"unphysical boundary shifts: {label} = {value:.3g} >= 0 (the {side} "
                            f"boundaries of a charged pixel move outward); the N/E split of "
                            f"a(0,0) is not determined by these flats ({solution.method} solver)")
    samples_north, samples_east = solution.samples_north, solution.samples_east
    if len(samples_north) >= 2:
        fraction = split_fraction(samples_north, samples_east)
        best = split_fraction(shifts.north, shifts.east)
        spread = float(np.std(fraction, ddof=1))
        if not spread <= SPLIT_TOLERANCE * abs(best):
            warnings.append(f"N/E split of a(0,0) poorly determined: a^N/(a^N + a^E) at (0,0) = "
                            f"{best:.3f} +- {spread:.3f}")
        amplitude = samples_north[:, m, m] + samples_east[:, m, m]
        spread = float(np.std(amplitude, ddof=1))
        if not spread <= AMPLITUDE_TOLERANCE * abs(north + east):
            warnings.append(f"amplitude of the boundary shifts poorly determined: a^N + a^E at "
                            f"(0,0) = {north + east:.3g} +- {spread:.2g} 1/e-")
    else:
        warnings.append("no uncertainty on the boundary shifts (no errors on a, or no samples): "
                        "predictions carry no calibration error")
    unconverged = getattr(solution, "n_unconverged", 0)
    if unconverged:
        warnings.append(f"{unconverged} of the {solution.method} fits (the best fit and its "
                        f"{len(samples_north)} Monte Carlo refits) stopped on their evaluation "
                        "bound, not converged: the shifts or their errors are uncertain (more "
                        "flat pairs narrow them; the samples that stopped are in the errors)")
    if solution.dof > 0 and solution.chi2 / solution.dof > CHI2_TOLERANCE:
        warnings.append(f"the {solution.method} model does not describe the measured a: "
                        f"chi2/dof = {solution.chi2:.1f}/{solution.dof}; shift errors are scaled "
                        f"by sqrt(chi2/dof)" if solution.method == "electrostatic" else
                        f"the {solution.method} smoothing model does not describe the far lags: "
                        f"chi2/dof = {solution.chi2:.1f}/{solution.dof}")
    for name in getattr(solution, "at_bound", ()):
        warnings.append(f"electrostatic parameter {name} ended on its physical bound: its "
                        f"error (and the shifts' errors) may be underestimated (more flat pairs "
                        f"or levels constrain it; `bfpsf calibrate --shift-method ei` solves "
                        f"the shifts without the sensor model, with its own errors)")
    sensitivity = getattr(solution, "sensitivity", None)
    if sensitivity and sensitivity.get("max_relative", 0.0) > EI_SENSITIVITY_TOLERANCE:
        warnings.append(f"the Ei solution depends on its smoothing model: shifts change by up to "
                        f"{100 * sensitivity['max_relative']:.0f} % when p1 moves by "
                        f"{sensitivity['nsigma']:g} sigma")
    return warnings
