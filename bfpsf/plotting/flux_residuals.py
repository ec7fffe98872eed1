"""Figure of PSF-model residuals against flux: plain Piff next to BrighterFatter (issue 23).

Imports matplotlib inside, takes ``axes=None`` and returns the figure.
"""

import numpy as np

from .moments import _binned

__all__ = ["plot_flux_residuals"]


def plot_flux_residuals(results, *, axes=None, n_bins=8):
    """Size and e1 residuals (data minus model) of the stars against their flux.

    Parameters
    ----------
    results : dict
        {label: `bfpsf.piff.field.residual_slopes` dict} (``flux_e``, ``size_residual``,
        ``e1_residual``, ``exposure``, ``size``, ``e1``), e.g. ``{'plain Piff': ...,
        'BrighterFatter': ...}``.
    axes : (Axes, Axes), optional
        Where to draw size and e1 (default: a new figure of two panels).
    n_bins : int, optional
        Flux bins of equal star counts (default 8): their means with errors; the lines are
        the fitted slopes (one intercept per exposure, their mean drawn).

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if axes is None:
        figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    else:
        figure = axes[0].figure
    for (label, result), colour in zip(results.items(), ("C0", "C3", "C2", "C1")):
        flux = np.asarray(result["flux_e"]) / 1e5
        for ax, key, scale in ((axes[0], "size", 100.0), (axes[1], "e1", 1e4)):
            values = np.asarray(result[f"{key}_residual"])
            fit = result[key]
            # each exposure's intercept removed, so the bins show the common slope
            offsets = np.zeros_like(values)
            for group in np.unique(result["exposure"]):
                members = result["exposure"] == group
                offsets[members] = np.mean(values[members] - fit.slope * flux[members])
            centres, means, errors = _binned(flux, values - offsets, n_bins)
            ax.errorbar(centres, scale * means, scale * errors, fmt="o", color=colour,
                        label=f"{label}: {scale * fit.slope:+.3f} +- {scale * fit.slope_err:.3f}"
                              " per 100 ke-")
            line = np.array([0.0, flux.max()])
            ax.plot(line, scale * fit.slope * line, color=colour, lw=1)
    axes[0].set_ylabel("size residual dT/T (%)")
    axes[1].set_ylabel(r"e1 residual ($10^{-4}$)")
    for ax in axes:
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.set_xlabel("star flux (100 ke-)")
        ax.legend(fontsize=8)
    figure.tight_layout()
    return figure
