"""Figures of the charge-redistribution engine (issue 3).

Each function imports matplotlib inside, takes ``ax=None`` (or a pair of axes where it draws
two panels) and returns the figure.
"""

import numpy as np

__all__ = ["plot_density_approximation", "plot_buildup", "plot_correction_convergence",
           "plot_boundary_shifts"]


def _axes(ax, count, **figure_kwargs):
    import matplotlib.pyplot as plt

    if ax is None:
        if count == 1:
            fig, ax = plt.subplots(**figure_kwargs)
        else:
            fig, ax = plt.subplots(count, 1, sharex=True, **figure_kwargs)
        return fig, ax
    axes = np.atleast_1d(ax)
    if axes.size != count:
        msg = f"ax must hold {count} axes, got {axes.size}"
        raise ValueError(msg)
    return axes.ravel()[0].figure, (axes.ravel()[0] if count == 1 else axes.ravel())


def plot_density_approximation(table, ax=None):
    """G15 fig. bva: BF size increase with the (Q_p + Q_q)/2 density and with the exact one.

    Parameters
    ----------
    table : astropy.table.Table
        Output of `bfpsf.validation.approximations.density_approximation_error`.
    ax : pair of matplotlib Axes, optional
        Top: relative size increase against IQ; bottom: the approximation's error.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, (top, bottom) = _axes(ax, 2, figsize=(5.5, 6))
    iq = np.asarray(table["iq"])
    top.plot(iq, 100 * np.asarray(table["dsigma_mean"]), "o-", color="tab:red",
             label="(Q$_p$ + Q$_q$)/2 (G15 eq. density-approx)")
    top.plot(iq, 100 * np.asarray(table["dsigma_exact"]), "s--", color="tab:blue",
             label="exact boundary density")
    top.set_ylabel(r"$\Delta\sigma/\sigma$ [%]")
    top.legend(fontsize="small")
    bottom.axhline(0, color="0.6", lw=0.8)
    bottom.plot(iq, 100 * np.asarray(table["error"]), "o-", color="k")
    bottom.set_xlabel("IQ (Moffat FWHM) [pixel]")
    bottom.set_ylabel("approx. - exact [%]")
    return fig


def plot_buildup(table, ax=None):
    """One-step BF model against the time-stepped build-up, as a function of peak charge.

    Parameters
    ----------
    table : astropy.table.Table
        Output of `bfpsf.validation.approximations.buildup_error`.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(ax, 1, figsize=(5.5, 4))
    peak = np.asarray(table["peak"]) / 1e3
    ax.plot(peak, 100 * np.asarray(table["size_difference_fraction"]), "o-",
            label="size: (one-step - build-up) / build-up")
    ax.plot(peak, 100 * np.asarray(table["max_pixel_difference"]), "s--",
            label="pixels: max|difference| / max|dQ|")
    ax.axhline(0, color="0.6", lw=0.8)
    ax.set_xlabel("peak [ke$^-$]")
    ax.set_ylabel("difference [% of the BF effect]")
    ax.legend(fontsize="small")
    return fig


def plot_correction_convergence(result, ax=None):
    """Residual of the iterative inverse (`bfpsf.model.inverse.correct`) per iteration.

    Parameters
    ----------
    result : CorrectionResult
        From ``correct(..., full_output=True)``.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = _axes(ax, 1, figsize=(5, 3.5))
    history = np.asarray(result.residual_history)
    ax.semilogy(np.arange(1, history.size + 1), history, "o-")
    ax.set_xlabel("iteration")
    ax.set_ylabel("max |redistribute(x) - image| [e$^-$]")
    ax.set_title(f"contraction {result.contraction:.3g}, error bound "
                 f"{result.error_bound:.2g} of the peak", fontsize="small")
    return fig


def plot_boundary_shifts(shifts, ax=None):
    """Maps of a^N and a^E (1/e-) over the source offsets (dx, dy).

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if ax is None:
        fig, ax = plt.subplots(1, 2, figsize=(9, 4))
    fig, axes = _axes(ax, 2)
    m = shifts.radius
    extent = (-m - 0.5, m + 0.5, -m - 0.5, m + 0.5)
    for axis, label, values in zip(axes, ("N", "E"), (shifts.north, shifts.east)):
        limit = np.abs(values).max() or 1.0
        image = axis.imshow(values, origin="lower", extent=extent, cmap="RdBu_r",
                            vmin=-limit, vmax=limit)
        axis.set_title(f"$a^{label}$(dx, dy) [1/e$^-$]")
        axis.set_xlabel("dx")
        axis.set_ylabel("dy")
        fig.colorbar(image, ax=axis, shrink=0.8)
    return fig
