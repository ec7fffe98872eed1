"""Figures of the flat-field calibration (G15 figs. varprof, 2dplot2, ccl/df).

Each function takes a `~bfpsf.calibration.product.Calibration`, draws on ``ax`` (a new figure
when None), imports matplotlib inside and returns the figure.
"""

from pathlib import Path

import numpy as np

from ..calibration.ei_profile import smoothing_model_area
from ..calibration.ptc import PTCData, full_covariance_model, summed_covariance_ptc
from ..errors import BFPSFValueError
from ..files import refuse_overwrite
from ..outputs import save_figure

__all__ = ["plot_ptc", "plot_correlation_map", "plot_area_profile", "plot_area_matrix",
           "save_calibration_plots"]


def _axes(ax, **figure_kwargs):
    import matplotlib.pyplot as plt

    if ax is None:
        figure, ax = plt.subplots(**figure_kwargs)
        return figure, ax
    return ax.figure, ax


def _corrected_covariances(calibration):
    """Per-pair covariances (ADU^2) minus the subtracted pedestal, or None if not stored."""
    cov = calibration.covariances_adu
    if cov is None:
        return None
    return cov - calibration.pedestal.applied[None] * cov[:, :1, :1]


def plot_ptc(calibration, ax=None, *, maxlag=None):
    """Raw PTC and PTC with the covariances summed back, in electrons (G15 fig. varprof).

    Parameters
    ----------
    calibration : Calibration
    ax : matplotlib Axes, optional
    maxlag : int, optional
        Largest |dx|, |dy| summed (default: all stored lags; G15 sum to 4).

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _axes(ax, figsize=(6.4, 4.8))
    table = calibration.ptc
    gain = calibration.gain
    used = np.asarray(table["used"], dtype=bool)
    mean_e = np.asarray(table["mean_e"], dtype=float)
    var_e = np.asarray(table["var_e"], dtype=float)
    ax.plot(mean_e[used], var_e[used], "o", color="C0", label="variance (raw PTC)")
    if (~used).any():
        ax.plot(mean_e[~used], var_e[~used], "o", mfc="none", color="C0", label="past turnoff")
    cov = _corrected_covariances(calibration)
    if cov is not None:
        data = PTCData(np.asarray(table["exptime"], float), np.asarray(table["mean_adu"], float),
                       cov, calibration.npix)
        summed = summed_covariance_ptc(data, gain, maxlag=maxlag, used=used)
        lags = cov.shape[1] - 1 if maxlag is None else maxlag
        ax.errorbar(mean_e[used], summed["summed_e"][used], summed["summed_err_e"][used],
                    fmt="s", color="C1", ms=4,
                    label=f"variance + covariances to lag {lags} "
                          f"(slope {summed['slope_summed']:.4f})")
    grid = np.linspace(0, mean_e.max() * 1.02, 200)
    ax.plot(grid, grid + calibration.noise_e**2, "--", color="C3", label="Poisson + read noise")
    if calibration.model == "full":
        model = full_covariance_model(grid / gain, calibration.a,
                                      calibration.a * calibration.b,
                                      calibration.noise_matrix_e2, gain)[:, 0, 0] * gain**2
        ax.plot(grid, model, "-", color="C0", lw=1, label="Astier+19 full model")
    ax.axvline(calibration.turnoff_e, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("mean signal (e-)")
    ax.set_ylabel("variance (e-$^2$)")
    ax.set_title(f"PTC: gain {gain:.4f} $\\pm$ {calibration.gain_err:.4f} e-/ADU")
    ax.legend(fontsize="small")
    return figure


def plot_correlation_map(calibration, ax=None, *, level_e=5e4, maxlag=4):
    """Correlation map R(dx, dy) = C / V of the pair nearest ``level_e`` (G15 fig. 2dplot2).

    Parameters
    ----------
    calibration : Calibration
        Must carry the per-pair covariances (``covariances_adu``).
    ax : matplotlib Axes, optional
    level_e : float, optional
        Flux of the pair shown, e- (G15: 50 ke-). Default 5e4.
    maxlag : int, optional
        Largest lag shown. Default 4.

    Returns
    -------
    matplotlib.figure.Figure
    """
    cov = _corrected_covariances(calibration)
    if cov is None:
        msg = "this calibration stores no per-pair covariances to map"
        raise BFPSFValueError(msg)
    figure, ax = _axes(ax, figsize=(5.6, 4.8))
    mean_e = np.asarray(calibration.ptc["mean_e"], dtype=float)
    used = np.asarray(calibration.ptc["used"], dtype=bool)
    candidates = np.flatnonzero(used) if used.any() else np.arange(mean_e.size)
    index = candidates[np.argmin(np.abs(mean_e[candidates] - level_e))]
    maxlag = min(maxlag, cov.shape[1] - 1)
    correlation = (cov[index] / cov[index, 0, 0])[:maxlag + 1, :maxlag + 1].copy()
    correlation[0, 0] = np.nan
    image = ax.imshow(correlation, origin="lower", cmap="viridis")
    for dy in range(maxlag + 1):
        for dx in range(maxlag + 1):
            if dx or dy:
                ax.text(dx, dy, f"{1e3 * correlation[dy, dx]:.2f}", ha="center", va="center",
                        fontsize="x-small", color="w")
    figure.colorbar(image, ax=ax, label="R(dx, dy) = C / V")
    ax.set_xlabel("dx (serial, X)")
    ax.set_ylabel("dy (parallel, Y)")
    ax.set_title(f"correlations at {mean_e[index] / 1e3:.0f} ke- (values in per mil)")
    return figure


def plot_area_profile(calibration, ax=None):
    """|a(dx, dy)| against distance with the G15 smoothing model (figs. ccl and df).

    Filled markers are positive a, open ones negative; a(0, 0) < 0 is left out. The curve is
    the area of the fitted f(r) = p0 Ei(p1 r) model when the shifts were solved.

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _axes(ax, figsize=(6.4, 4.8))
    a, a_err = calibration.a, calibration.a_err
    nlag = a.shape[0]
    dy, dx = np.mgrid[0:nlag, 0:nlag]
    radius = np.hypot(dx, dy)
    off = radius > 0
    positive = off & (a > 0)
    negative = off & (a <= 0)
    ax.errorbar(radius[positive], a[positive], a_err[positive], fmt="o", color="C0",
                label="a(dx, dy) > 0")
    ax.errorbar(radius[negative], -a[negative], a_err[negative], fmt="o", mfc="none",
                color="C0", label="-a(dx, dy) (negative)")
    for label, (i, j) in (("(1,0)", (0, 1)), ("(0,1)", (1, 0)), ("(1,1)", (1, 1))):
        if max(i, j) < nlag:
            ax.annotate(label, (radius[i, j], abs(a[i, j])), fontsize="x-small",
                        xytext=(4, 4), textcoords="offset points")
    fit = calibration.shift_fit
    if "p0" in fit and "p1" in fit:
        model = smoothing_model_area(fit["p0"], fit["p1"], nlag - 1)
        model_points = off & ~((dx <= 1) & (dy <= 1))
        ax.plot(radius[model_points], np.abs(model[model_points]), "x", color="C1", ms=8,
                label=f"Ei model (fitted lags), p1 = {fit['p1']:.3g} $\\pm$ "
                      f"{fit.get('p1_err', np.nan):.2g}")
    ax.set_yscale("log")
    ax.set_xlabel("distance r (pixels)")
    ax.set_ylabel("|a(dx, dy)| (1/e-)")
    ax.set_title(f"area coefficients, a(0,0) = {a[0, 0]:.3e} / e-")
    ax.legend(fontsize="small")
    return figure


def save_calibration_plots(calibration, directory, *, overwrite=False):
    """Write ptc.png, correlation_map.png and area_profile.png into ``directory``.

    Returns
    -------
    list of pathlib.Path
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    makers = {"ptc.png": plot_ptc, "area_profile.png": plot_area_profile}
    if calibration.covariances_adu is not None:
        makers["correlation_map.png"] = plot_correlation_map
    paths = []
    for name, maker in makers.items():
        path = directory / name
        refuse_overwrite(path, overwrite)
        save_figure(maker(calibration), path, overwrite=overwrite, dpi=110, bbox_inches="tight")
        paths.append(path)
    return paths


def plot_area_matrix(area, ax=None, *, title=None, vmin=None, vmax=None):
    """The a-matrix a(dx, dy) as an image, dx, dy >= 0 (a(0, 0) < 0 left blank).

    Parameters
    ----------
    area : array_like [dy, dx]
        Area coefficients, 1/e- (``Calibration.a``, a measured or true table).
    ax : matplotlib.axes.Axes, optional
    title : str, optional
        Default: the value of a(0, 0).
    vmin, vmax : float, optional
        Colour scale, 1/e- (to share it between panels); default from 0 (or the smallest
        off-origin value if negative) to the largest.

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _axes(ax, figsize=(4.6, 3.8))
    area = np.asarray(area, dtype=float)
    shown = area.copy()
    shown[0, 0] = np.nan
    vmin = min(0.0, np.nanmin(shown)) if vmin is None else vmin
    vmax = np.nanmax(shown) if vmax is None else vmax
    image = ax.imshow(shown * 1e7, origin="lower", cmap="viridis", vmin=vmin * 1e7,
                      vmax=vmax * 1e7)
    figure.colorbar(image, ax=ax, label="a(dx, dy) (1e-7 / e-)")
    ax.set_xlabel("dx (serial)")
    ax.set_ylabel("dy (parallel)")
    ax.set_title(title or f"a-matrix, a(0,0) = {area[0, 0] * 1e7:.1f}e-7 / e- (blank)",
                 fontsize=9)
    return figure
