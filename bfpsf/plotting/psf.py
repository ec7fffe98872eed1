"""Figures of the flux-dependent PSF: P0, P(F) - P0 (G15 fig. spots-diff), fit residuals.

Each function imports matplotlib inside, takes ``ax=None`` (or ``axes=None``) and returns the
figure.
"""

import numpy as np

from ..model.bf_term import pixelised_stamp

__all__ = ["plot_psf", "plot_bf_difference", "plot_residuals"]


def _figure(ax, **subplot_kwargs):
    import matplotlib.pyplot as plt

    if ax is None:
        figure, ax = plt.subplots(**subplot_kwargs)
        return figure, ax
    return ax.figure, ax


def plot_psf(psf, *, ax=None, oversampled=True, log=True):
    """The base PSF P0 (unit flux, pixel response included).

    Parameters
    ----------
    psf : FluxDependentPSF
    ax : matplotlib.axes.Axes, optional
    oversampled : bool, optional
        Show the oversampled data (default) or the pixelised P0 at phase 0.
    log : bool, optional
        Logarithmic colour scale (default True).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.colors import LogNorm

    figure, ax = _figure(ax, figsize=(5, 4.4))
    if oversampled:
        oy, ox = psf.oversampling
        data = psf.data  # each node: the pixel-integrated P0 of a star at that phase
        ny, nx = data.shape
        extent = (-psf.origin[0] / ox - 0.5 / ox, (nx - 1 - psf.origin[0]) / ox + 0.5 / ox,
                  -psf.origin[1] / oy - 0.5 / oy, (ny - 1 - psf.origin[1]) / oy + 0.5 / oy)
    else:
        data = pixelised_stamp(psf)
        half = data.shape[0] // 2
        extent = (-half - 0.5, half + 0.5, -half - 0.5, half + 0.5)
    positive = data[data > 0]
    norm = LogNorm(vmin=max(positive.max() * 1e-5, positive.min()), vmax=positive.max()) \
        if log and positive.size else None
    shown = np.where(data > 0, data, np.nan) if log else data
    image = ax.imshow(shown, origin="lower", extent=extent, norm=norm, cmap="viridis")
    figure.colorbar(image, ax=ax, label="P0 in the pixel (unit flux)")
    ax.set_xlabel("x - x_0 (pixels)")
    ax.set_ylabel("y - y_0 (pixels)")
    ax.set_title("base PSF P0" + (f" (oversampling {psf.oversampling[1]})" if oversampled
                                  else " (pixelised, phase 0)"))
    return figure


def plot_bf_difference(psf, fluxes, *, axes=None, half_size=6, x_phase=0.0, y_phase=0.0):
    """P(F) - P0 of unit-flux stars at several fluxes (G15 fig. spots-diff).

    Parameters
    ----------
    psf : FluxDependentPSF
    fluxes : sequence of float
        Fluxes of the panels, e- (the PSF's image unit).
    axes : sequence of matplotlib.axes.Axes, optional
        One per flux (default: a new row of panels).
    half_size : int, optional
        Panels show ``2 * half_size + 1`` pixels. Default 6.
    x_phase, y_phase : float, optional
        Sub-pixel phase of the star, pixels.

    Returns
    -------
    matplotlib.figure.Figure
        Common symmetric colour scale, in units of the peak of P0: the core loses charge to
        the wings, by an amount proportional to F (G15 eq. scrambling_model).
    """
    import matplotlib.pyplot as plt

    fluxes = list(fluxes)
    if axes is None:
        figure, axes = plt.subplots(1, len(fluxes), figsize=(3.4 * len(fluxes) + 1.5, 3.6),
                                    squeeze=False)
        axes = axes[0]
    else:
        figure = axes[0].figure
    base = pixelised_stamp(psf, x_phase=x_phase, y_phase=y_phase, half_size=half_size)
    peak = base.max()
    differences = [psf.star_image(flux, x_phase=x_phase, y_phase=y_phase,
                                  half_size=half_size) / flux - base for flux in fluxes]
    limit = max(np.abs(diff).max() for diff in differences) / peak
    extent = (-half_size - 0.5, half_size + 0.5, -half_size - 0.5, half_size + 0.5)
    for ax, flux, diff in zip(axes, fluxes, differences):
        image = ax.imshow(diff / peak, origin="lower", extent=extent, cmap="RdBu_r",
                          vmin=-limit, vmax=limit)
        ax.set_title(f"F = {flux:.2g} e-\npeak {flux * peak:.2g} e-", fontsize=10)
        ax.set_xlabel("x (pixels)")
    axes[0].set_ylabel("y (pixels)")
    figure.colorbar(image, ax=list(axes), label="(P(F) - P0) / peak of P0")
    return figure


def plot_residuals(image, model, *, error=None, ax=None, limit=5.0):
    """Fit residuals (data - model), in units of the pixel error when given.

    Parameters
    ----------
    image, model : ndarray [y, x]
        Data and the summed model of the fitted stars (e.g. photutils
        ``PSFPhotometry.make_model_image``), same unit.
    error : ndarray or float, optional
        Pixel errors; residuals are shown in sigma (clipped to +-``limit``).
    ax : matplotlib.axes.Axes, optional
    limit : float, optional
        Colour range in sigma (or, without ``error``, in percent of the model's peak).

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _figure(ax, figsize=(5.4, 4.6))
    residual = np.asarray(image, dtype=float) - np.asarray(model, dtype=float)
    if error is not None:
        shown, label = residual / error, "(data - model) / sigma"
        vmax = limit
    else:
        shown, label = 100 * residual / np.nanmax(model), "(data - model) / peak (%)"
        vmax = limit
    picture = ax.imshow(shown, origin="lower", cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    figure.colorbar(picture, ax=ax, label=label)
    ax.set_xlabel("x (pixels)")
    ax.set_ylabel("y (pixels)")
    ax.set_title(f"residuals: rms {np.nanstd(shown):.3g}")
    return figure
