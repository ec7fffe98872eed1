"""The PSF-diagnostics figure of survey pipelines (HSC, DES): star minus model against magnitude.

Rows: size (d sigma / sigma), e1 and e2 of each star minus those of the PSF model at the star's
flux, binned in magnitude (mean and its error per bin of equal numbers of stars). Columns: a static PSF (the model frozen at the flux of the bright
stars it is built from, what an ePSF from bright stars gives) and the flux-dependent P(F). A
static PSF leaves the brighter-fatter trend with magnitude; P(F) removes it.
"""

import numpy as np

from ..moments.shapes import shape_residuals

__all__ = ["plot_psf_diagnostics"]


def _binned(magnitude, values, n_bins):
    keep = np.isfinite(magnitude) & np.isfinite(values)
    edges = np.quantile(magnitude[keep], np.linspace(0, 1, n_bins + 1))
    index = np.clip(np.searchsorted(edges, magnitude[keep], side="right") - 1, 0, n_bins - 1)
    centres, means, errors = [], [], []
    for b in range(n_bins):
        members = values[keep][index == b]
        if members.size < 2:
            continue
        centres.append(np.mean(magnitude[keep][index == b]))
        means.append(np.mean(members))
        errors.append(np.std(members, ddof=1) / np.sqrt(members.size))
    return np.array(centres), np.array(means), np.array(errors)


def plot_psf_diagnostics(stars, psf, *, static_flux=None, n_bins=8, zero_point=25.0,
                         axes=None):
    """Star-minus-model size and ellipticity against magnitude, static PSF beside P(F).

    Parameters
    ----------
    stars : astropy.table.Table
        Star table of `bfpsf.measure.sources.measure_sources` (``flux_e``, ``iq``, ``e1``,
        ``e2``, ``flags``); flagged stars are left out.
    psf : FluxDependentPSF
        The model, in electrons.
    static_flux : float, optional
        Flux (e-) at which the static PSF is frozen; default the median flux of the brightest
        quarter of the stars.
    n_bins : int, optional
        Magnitude bins (equal numbers of stars). Default 8.
    zero_point : float, optional
        Magnitude of 1 e-: ``mag = zero_point - 2.5 log10(flux_e)``. Default 25.
    axes : array of matplotlib.axes.Axes, shape (3, 2), optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    clean = np.asarray(stars["flags"]) == 0 if "flags" in stars.colnames else slice(None)
    stars = stars[clean]
    flux = np.asarray(stars["flux_e"], dtype=float)
    magnitude = zero_point - 2.5 * np.log10(np.where(flux > 0, flux, np.nan))
    if static_flux is None:
        static_flux = float(np.median(np.sort(flux)[-max(len(flux) // 4, 1):]))
    static = shape_residuals(stars, psf, flux=static_flux)
    dependent = shape_residuals(stars, psf)
    if axes is None:
        figure, axes = plt.subplots(3, 2, figsize=(8, 7), sharex=True, sharey="row")
    else:
        figure = np.ravel(axes)[0].figure
    rows = (("sigma", r"$\delta\sigma / \sigma$ (star - model)"),
            ("e1", r"$\delta e_1$"), ("e2", r"$\delta e_2$"))
    columns = ((static, f"static PSF (frozen at {static_flux:.3g} e-)"),
               (dependent, "flux-dependent P(F)"))
    for column, (residuals, title) in enumerate(columns):
        for row, (name, label) in enumerate(rows):
            ax = axes[row][column]
            residual = residuals[name]
            centres, means, errors = _binned(magnitude, residual, n_bins)
            ax.errorbar(centres, means, errors, fmt="o", color="C0" if column else "C3",
                        zorder=2)
            ax.axhline(0.0, color="k", lw=0.8)
            if column == 0:
                ax.set_ylabel(label)
            if row == 0:
                ax.set_title(title, fontsize=10)
            if row == 2:
                ax.set_xlabel(f"magnitude ({zero_point:g} - 2.5 log10 flux/e-)")
    figure.tight_layout()
    return figure
