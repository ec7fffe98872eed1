"""Figures of the closed loop and of the end-to-end validation.

Each function imports matplotlib inside, takes ``ax=None`` (or ``axes=None``) and returns the
figure.
"""

import numpy as np

__all__ = ["plot_sizes_before_after", "plot_candidates", "plot_residual_image",
           "plot_radial_profile", "plot_ptc_residuals"]


def _new_axes(ax, ncols=1, figsize=(6, 4)):
    import matplotlib.pyplot as plt

    if ax is not None:
        return ax.figure, ax
    figure, axes = plt.subplots(1, ncols, figsize=figsize, squeeze=False)
    return figure, axes[0] if ncols > 1 else axes[0, 0]


def plot_sizes_before_after(curves, *, axes=None, title=None):
    """Size against peak in X and Y: data, base model, final model (left), residuals (right).

    Parameters
    ----------
    curves : dict
        ``DiagnosisResult.curves`` (``peak_e``, ``sigma_x``, ``sigma_y``, errors, ``base_*``,
        ``final_*``, ``group``).
    axes : sequence of two matplotlib Axes, optional
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if axes is None:
        figure, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    else:
        figure = axes[0].figure
    peak = np.asarray(curves["peak_e"]) / 1e3
    for axis, colour, offset in (("x", "C0", 0.0), ("y", "C3", 0.0)):
        data = np.asarray(curves[f"sigma_{axis}"])
        error = np.asarray(curves[f"sigma_{axis}_err"])
        base = np.asarray(curves[f"base_{axis}"])
        final = np.asarray(curves[f"final_{axis}"])
        axes[0].errorbar(peak, data, error, fmt="o", ms=3, color=colour,
                         label=f"measured $\\sigma_{axis}$")
        group = np.asarray(curves.get("group", np.zeros(peak.size, int)))
        for g in np.unique(group):
            members = np.flatnonzero(group == g)
            order = members[np.argsort(peak[members])]
            first = g == group.min()
            axes[0].plot(peak[order], base[order], "--", color=colour, lw=1,
                         label=f"base model {axis}" if first else None)
            axes[0].plot(peak[order], final[order], "-", color=colour, lw=1.5,
                         label=f"final model {axis}" if first else None)
        axes[1].errorbar(peak, 1e3 * (data - base), 1e3 * error, fmt="o", ms=3, mfc="none",
                         color=colour, label=f"{axis}: before")
        axes[1].errorbar(peak + offset, 1e3 * (data - final), 1e3 * error, fmt="s", ms=3,
                         color=colour, alpha=0.8, label=f"{axis}: after")
    axes[0].set_xlabel("peak (ke-)")
    axes[0].set_ylabel("sigma (pixels)")
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].axhline(0, color="k", lw=0.8)
    axes[1].set_xlabel("peak (ke-)")
    axes[1].set_ylabel("measured - model (millipixels)")
    axes[1].legend(fontsize=7, ncol=2)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    return figure


def plot_candidates(candidates, *, ax=None, threshold=-10.0):
    """Delta BIC of every candidate, one group of bars per round (negative is better).

    Parameters
    ----------
    candidates : list of dict
        ``DiagnosisResult.candidates``.
    ax : matplotlib.axes.Axes, optional
    threshold : float
        Drawn as a dashed line.

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _new_axes(ax, figsize=(8, 4))
    names = []
    for entry in candidates:
        if entry["name"] not in names:
            names.append(entry["name"])
    rounds = sorted({entry["round"] for entry in candidates})
    width = 0.8 / max(len(rounds), 1)
    for index, round_number in enumerate(rounds):
        values = []
        for name in names:
            match = [c for c in candidates if c["round"] == round_number and c["name"] == name]
            value = match[0]["delta_bic"] if match and match[0]["delta_bic"] is not None else 0
            values.append(np.sign(value) * np.log10(1 + abs(value)))
        positions = np.arange(len(names)) + (index - (len(rounds) - 1) / 2) * width
        ax.bar(positions, values, width, label=f"round {round_number}")
        for position, name in zip(positions, names):
            match = [c for c in candidates if c["round"] == round_number and c["name"] == name]
            if match and match[0]["delta_bic"] is None:
                ax.text(position, 0.02, "n/t", ha="center", va="bottom", fontsize=6,
                        rotation=90)
    ax.axhline(-np.log10(1 + abs(threshold)), ls="--", color="k", lw=0.8,
               label=f"threshold {threshold:g}")
    ax.set_xticks(np.arange(len(names)))
    ax.set_xticklabels(names, rotation=35, ha="right", fontsize=8)
    ax.set_ylabel("sign(dBIC) log10(1 + |dBIC|)")
    ax.legend(fontsize=8)
    figure.tight_layout()
    return figure


def plot_residual_image(image, *, ax=None, title="stacked residual (e-)"):
    """A residual image with a symmetric colour scale."""
    figure, ax = _new_axes(ax, figsize=(4.5, 4))
    image = np.asarray(image, float)
    limit = np.nanmax(np.abs(image)) or 1.0
    shown = ax.imshow(image, origin="lower", cmap="RdBu_r", vmin=-limit, vmax=limit)
    figure.colorbar(shown, ax=ax)
    ax.set_title(title)
    ax.set_xlabel("x (pixels)")
    ax.set_ylabel("y (pixels)")
    figure.tight_layout()
    return figure


def radial_profile(image, centre=None, *, bin_width=0.5):
    """Azimuthal mean of an image in rings of ``bin_width`` pixels: (radius, mean)."""
    image = np.asarray(image, float)
    ny, nx = image.shape
    if centre is None:
        centre = ((nx - 1) / 2.0, (ny - 1) / 2.0)
    yy, xx = np.mgrid[:ny, :nx]
    radius = np.hypot(xx - centre[0], yy - centre[1])
    index = (radius / bin_width).astype(int)
    sums = np.bincount(index.ravel(), image.ravel())
    counts = np.bincount(index.ravel())
    good = counts > 0
    return (np.flatnonzero(good) + 0.5) * bin_width, sums[good] / counts[good]


def plot_ptc_residuals(curves, *, ax=None):
    """PTC residuals (variance minus the calibrated model), before and after the loop.

    Parameters
    ----------
    curves : dict
        ``DiagnosisResult.ptc_curves`` (``mean_e``, ``var_e``, ``error``, ``residual_raw``
        (optional), ``residual_before``, ``residual_after``, e-^2).
    ax : matplotlib.axes.Axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    figure, ax = _new_axes(ax)
    mean = np.asarray(curves["mean_e"], float)
    var = np.asarray(curves["var_e"], float)
    error = np.asarray(curves["error"], float)
    series = [("residual_before", "o", "before (base model, noise and gain refitted)"),
              ("residual_after", "s", "after (selected effects)")]
    if "residual_raw" in curves:
        series.insert(0, ("residual_raw", "^", "data - calibrated model"))
    for key, marker, label in series:
        ax.errorbar(mean / 1e3, 100 * np.asarray(curves[key], float) / var, 100 * error / var,
                    fmt=marker, ms=3, mfc="none" if key != "residual_after" else None,
                    label=label)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("flat mean (ke-)")
    ax.set_ylabel("variance - PTC model (% of variance)")
    ax.set_title("PTC residuals (sum-rule a(0,0))")
    ax.legend(fontsize=8)
    figure.tight_layout()
    return figure


def plot_radial_profile(images, labels, *, ax=None):
    """Radial profiles of residual images (e.g. before and after)."""
    figure, ax = _new_axes(ax)
    for image, label in zip(images, labels):
        radius, profile = radial_profile(image)
        ax.plot(radius, profile, "o-", ms=3, label=label)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("radius (pixels)")
    ax.set_ylabel("mean residual per pixel (unit as labelled)")
    ax.legend(fontsize=8)
    figure.tight_layout()
    return figure


def plot_signatures(result, *, axes=None):
    """What the stars' residual is and why no catalogue effect was named (issue 22).

    Left: the unexplained size residual per axis (BF slope, percent of the raw slope, on the
    held-out data) before and after the EMPIRICAL term, with the verdict and the stars' chi2
    per pixel against its null expectation in the title. Right: each rejected candidate's
    amplitudes in the parts of the dimension that contradicts it (normalised to their mean,
    1 = one amplitude fits all parts), with errors.

    Parameters
    ----------
    result : DiagnosisResult
    axes : sequence of two matplotlib.axes.Axes, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib.pyplot as plt

    if axes is None:
        figure, axes = plt.subplots(1, 2, figsize=(11, 4))
    else:
        figure = axes[0].figure
    left, right = axes
    validation = (result.empirical or {}).get("validation", {})
    heldout = validation.get("heldout") or {}
    stages = [("loop", result.residual_after_heldout or result.residual_after)]
    if heldout:
        stages += [("before empirical", heldout["before"]), ("after EMPIRICAL", heldout["after"])]
    width = 0.8 / len(stages)
    no_bf = set()
    for index, (label, values) in enumerate(stages):
        if not values or "slope_x_percent" not in values:
            continue
        # no bar where the stars show no BF slope: a percentage of it means nothing
        shown = [values.get(f"stars_show_bf_{axis}", True) for axis in "xy"]
        no_bf.update(axis for axis, ok in zip("XY", shown) if not ok)
        left.bar(np.arange(2) + index * width,
                 [values[f"slope_{axis}_percent"] if ok else np.nan
                  for axis, ok in zip("xy", shown)], width,
                 yerr=[values[f"slope_{axis}_percent_err"] if ok else np.nan
                       for axis, ok in zip("xy", shown)],
                 label=label)
    left.axhline(0.0, color="k", lw=0.8)
    for bound in (-2.0, 2.0):
        left.axhline(bound, color="grey", ls=":", lw=0.8)
    left.set_xticks(np.arange(2) + 0.4 - width / 2,
                    [axis + (" (no BF slope in the stars)" if axis in no_bf else "")
                     for axis in "XY"])
    left.set_ylabel("BF slope residual, held-out (% of raw)")
    verdict = result.verdict or {}
    title = "explained" if verdict.get("success") else "NOT EXPLAINED"
    chi2 = verdict.get("star_residual_chi2_per_pixel")
    if chi2 is not None:
        title += (f"; star chi2/pixel {chi2:.1f} (null {verdict['null_expectation']:.1f}, "
                  f"limit {verdict['limit']:.0f})")
    left.set_title(title, fontsize=9)
    left.legend(fontsize=8)
    offset = 0
    ticks, labels = [], []
    for name, entry in result.rejected.items():
        if "signature" not in entry:  # outside its physical range: no signature test
            continue
        test = entry["signature"][entry["contradicted_by"]]
        amplitudes = np.array([values[0] for values in test["amplitudes"]])
        errors = np.array([values[0] for values in test["errors"]])
        mean = np.mean(amplitudes) or 1.0
        if entry["contradicted_by"] in ("parity", "cross"):
            # slopes that every catalogue effect predicts to be 0: 1 + slope / error, so
            # that 1 is what the candidate predicts and each unit a sigma away from it
            amplitudes, errors, mean = 1.0 + amplitudes / errors, np.ones_like(errors), 1.0
        positions = offset + np.arange(amplitudes.size)
        right.errorbar(positions, amplitudes / mean, yerr=np.abs(errors / mean), fmt="o",
                       label=f"{name}: {entry['contradicted_by']} (p={entry['p_value']:.0e})")
        ticks += list(positions)
        labels += test["parts"]
        offset += amplitudes.size + 1
    right.axhline(1.0, color="k", lw=0.8)
    right.set_xticks(ticks, labels, rotation=30, fontsize=7)
    right.set_ylabel("part amplitude / mean (parity, cross: 1 + slope / error)")
    right.set_title("rejected: the observable that contradicts each", fontsize=9)
    if ticks:  # rejected only outside their physical range have no signature to draw
        right.legend(fontsize=7)
    elif result.rejected:
        right.text(0.5, 0.5, "rejected outside their physical range:\n"
                   + ", ".join(result.rejected), ha="center", va="center", fontsize=8,
                   transform=right.transAxes)
    figure.tight_layout()
    return figure
