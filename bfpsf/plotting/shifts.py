"""Figures of the boundary-shift solution (G15 figs. ccl and df)."""

import numpy as np

from ..calibration.ei_profile import non_nearest_mask, smoothing_model_area

__all__ = ["plot_radial_profile"]


def _boundary_radial_parts(solution):
    """Distance r, f = -a^X / cos(theta) and its error for every solved N and E boundary."""
    shifts = solution.shifts
    m = shifts.radius
    lags = np.arange(0, m + 1)
    distances, values, errors = [], [], []
    for array, error, transpose in ((shifts.north, solution.north_err, False),
                                    (shifts.east, solution.east_err, True)):
        for i in lags:
            for j in range(1, m + 1):
                # a^N(i, j): boundary centre (0, 1/2) seen from (i, j); a^E(j, i) by symmetry
                dy, dx = (i, j) if transpose else (j, i)
                normal = 0.5 - j
                r = np.hypot(i, normal)
                cosine = normal / r
                distances.append(r)
                values.append(-array[dy + m, dx + m] / cosine)
                errors.append(abs(error[dy + m, dx + m] / cosine))
    return np.array(distances), np.array(values), np.array(errors)


def plot_radial_profile(solution, ax=None):
    """Area coefficients and boundary shifts against distance, with the Ei smoothing model.

    Left: a(dx, dy) against r = hypot(dx, dy) (points with errors; nearest neighbours, not
    fitted, in grey) and the smoothing model at the same lags (G15 fig. ccl). Right: the
    solved boundary shifts divided by -cos(theta), i.e. the radial part f(r) of each a^X
    (G15 eq. f_r), with Monte Carlo errors, and the fitted f(r) = p0 Ei(p1 r) (G15 fig. df).

    Parameters
    ----------
    solution : `~bfpsf.calibration.shifts_ei.ShiftSolution`
    ax : sequence of two matplotlib Axes, optional
        Where to draw; a new figure with two panels is made when None.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if ax is None:
        fig, (ax_area, ax_shift) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    else:
        ax_area, ax_shift = ax
        fig = ax_area.figure
    n = solution.maxlag
    dy, dx = np.mgrid[0:n + 1, 0:n + 1]
    r = np.hypot(dx, dy)
    fitted = non_nearest_mask(n)
    errors = (solution.area_err if solution.area_err is not None
              else np.zeros_like(solution.area))
    model = smoothing_model_area(solution.p0, solution.p1, n)
    ax_area.errorbar(r[fitted], solution.area[fitted], yerr=errors[fitted], fmt="^", color="k",
                     ms=4, label="measured (fitted)")
    nearest = ~fitted & (r > 0)
    ax_area.errorbar(r[nearest], solution.area[nearest], yerr=errors[nearest], fmt="s",
                     color="0.6", ms=4, label="nearest (not fitted)")
    ax_area.plot(r[r > 0], model[r > 0], "o", mfc="none", color="tab:red",
                 label=f"Ei model, p1 = {solution.p1:.3f}")
    positive = np.abs(solution.area[r > 0])
    ax_area.set_yscale("symlog", linthresh=max(float(np.median(positive)) * 0.05, 1e-300))
    ax_area.set_xlabel("distance r (pixels)")
    ax_area.set_ylabel("a(dx, dy) (1/e-)")
    ax_area.legend(fontsize="small")

    distance, radial, radial_err = _boundary_radial_parts(solution)
    ax_shift.errorbar(distance, radial, yerr=np.nan_to_num(radial_err), fmt=".",
                      color="tab:blue", label="solved a^X / -cos(theta)")
    grid = np.linspace(0.5, distance.max(), 200)
    ax_shift.plot(grid, solution.radial_profile(grid), "--", color="tab:red",
                  label="f(r) = p0 Ei(p1 r)")
    ax_shift.set_yscale("symlog", linthresh=max(float(np.median(np.abs(radial))) * 0.05, 1e-300))
    ax_shift.set_xlabel("distance source - boundary centre (pixels)")
    ax_shift.set_ylabel("radial part f (1/e-)")
    ax_shift.legend(fontsize="small")
    return fig
