"""Figures of star sizes: size against peak flux with the brighter-fatter fits (G15 fig. mbf).

Each function imports matplotlib inside, takes ``ax=None`` and returns the figure.
"""

import numpy as np

__all__ = ["plot_size_vs_peak"]

_STYLE = {"x": ("sigma_x", "C0", r"$\sigma_x=\sqrt{M_{xx}}$"),
          "y": ("sigma_y", "C3", r"$\sigma_y=\sqrt{M_{yy}}$"),
          "iq": ("iq", "C2", "IQ")}


def _binned(peak, size, n_bins):
    edges = np.quantile(peak, np.linspace(0, 1, n_bins + 1))
    centres, means, errors = [], [], []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (peak >= low) & (peak <= high)
        if inside.sum() >= 2:
            centres.append(peak[inside].mean())
            means.append(size[inside].mean())
            errors.append(size[inside].std(ddof=1) / np.sqrt(inside.sum()))
    return np.array(centres), np.array(means), np.array(errors)


def plot_size_vs_peak(table, slopes=None, *, ax=None, axes=("x", "y"), relative=True,
                      max_peak_e=None, n_bins=10, show_points=True):
    """Star size against peak flux with the linear BF fits (G15 fig. mbf).

    Parameters
    ----------
    table : astropy.table.Table
        Star table (``peak_e``, ``sigma_x``, ``sigma_y``, ``iq``, ``flags``).
    slopes : dict, optional
        Output of `bfpsf.measure.slopes.bf_slopes`; its lines are drawn and, with
        ``relative=True``, its intercepts normalise the sizes.
    ax : matplotlib.axes.Axes, optional
        Axes to draw into (default: a new figure).
    axes : sequence of {'x', 'y', 'iq'}, optional
        Sizes drawn (default sigma_x and sigma_y).
    relative : bool, optional
        Plot ``size / intercept - 1`` in percent, as G15 (needs ``slopes``; default True).
    max_peak_e : float, optional
        Stars above this peak are drawn grey (outside the fit).
    n_bins : int, optional
        Quantile bins of peak for the binned means (default 10).
    show_points : bool, optional
        Draw every star as a faint dot (default True).

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if ax is None:
        figure, ax = plt.subplots(figsize=(6.4, 4.4))
    else:
        figure = ax.figure
    relative = relative and slopes is not None
    flags = np.asarray(table["flags"]) if "flags" in table.colnames else np.zeros(len(table))
    peak_all = np.asarray(table["peak_e"], dtype=float)
    clean = (flags == 0) & np.isfinite(peak_all)
    in_fit = clean if max_peak_e is None else clean & (peak_all <= max_peak_e)
    for key in axes:
        column, colour, label = _STYLE[key]
        size = np.asarray(table[column], dtype=float)
        fit = slopes[key] if slopes is not None else None
        scale = (lambda value: 100.0 * (value / fit.intercept - 1.0)) if relative else \
            (lambda value: value)
        if show_points:
            ax.plot(peak_all[in_fit] / 1e3, scale(size[in_fit]), ".", color=colour,
                    alpha=0.25, ms=3)
            outside = clean & ~in_fit
            if np.any(outside):
                ax.plot(peak_all[outside] / 1e3, scale(size[outside]), ".", color="0.6",
                        ms=3)
        centres, means, errors = _binned(peak_all[in_fit], size[in_fit], n_bins)
        if relative:
            errors = 100.0 * errors / fit.intercept
        ax.errorbar(centres / 1e3, scale(means), yerr=errors, fmt="o", color=colour, ms=4,
                    capsize=2, label=label)
        if fit is not None:
            grid = np.linspace(0.0, peak_all[in_fit].max(), 50)
            ax.plot(grid / 1e3, scale(fit.predict(grid)), "-", color=colour,
                    label=f"{fit.slope:.4f} $\\pm$ {fit.slope_err:.4f} pix/100 ke$^-$")
    ax.set_xlabel("peak flux [ke$^-$]")
    ax.set_ylabel("size / intercept - 1 [%]" if relative else "size [pixel]")
    ax.legend(fontsize=8)
    ax.set_title("brighter-fatter: size against peak flux")
    return figure
