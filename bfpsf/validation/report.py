"""Markdown + PNG reports of `bfpsf diagnose` and `bfpsf validate`.

`write_diagnosis_report` and `write_validation_report` write ``report.md`` and the figures
into a directory; they refuse to replace existing files unless ``overwrite=True``.
"""

from pathlib import Path

import numpy as np

from ..diagnosis.nuisances import GLOBAL_NUISANCES
from ..diagnosis.signature import describe_entry
from ..files import refuse_overwrite
from ..outputs import save_figure, write_text
from ..plotting.diagnose import (plot_candidates, plot_ptc_residuals, plot_radial_profile,
                                 plot_residual_image, plot_sizes_before_after)

__all__ = ["write_diagnosis_report", "write_validation_report", "format_number"]

#: What a report folder holds (`write_diagnosis_report`, `write_validation_report` and the
#: figures the commands add): an earlier report there is replaced only with --overwrite.
REPORT_FILES = ("report.md", "*.png")


def prediction_cells(row):
    """The X and Y text of one row of ``validate``'s ``prediction['rows']``: the predicted
    slope (px per 100 ke-) with its error, its ratio to the measured slope and its pull
    where known (the printed table and the report share it)."""
    cells = []
    for axis in "xy":
        error = row.get(f"predicted_slope_{axis}_err")
        cells.append(f"{row[f'predicted_slope_{axis}']:.4f}"
                     + (f" +- {error:.4f}" if error is not None else "")
                     + f" ({100 * row[f'predicted_over_measured_{axis}']:.1f} %"
                     + (f", pull {row[f'pull_{axis}']:+.1f}" if f"pull_{axis}" in row else "")
                     + ")")
    return cells


def format_number(value, digits=3):
    """Compact text of a number (None and NaN as 'n/a')."""
    if value is None:
        return "n/a"
    if isinstance(value, (list, tuple)):
        return ", ".join(format_number(item, digits) for item in value)
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if not np.isfinite(value):
        return "n/a"
    return f"{value:.{digits}g}"


def _prepare(directory, names, overwrite):
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name in names:
        refuse_overwrite(directory / name, overwrite)
    return directory


def _save(figure, path):
    # _prepare has checked the names: a figure replaces a file only with overwrite
    save_figure(figure, path, overwrite=True, dpi=110)


def _residual_rows(before, after, physical=None, heldout=None):
    keys = [("slope_x_percent", "BF slope residual X (% of raw)"),
            ("slope_y_percent", "BF slope residual Y (% of raw)"),
            ("photometry_bias_mmag", "photometry bias implied for sky-limited stars (mmag, "
                                     "faint - bright; bright stars' fits are far less biased)"),
            ("chi2", "chi2"), ("n", "points"),
            ("sizes_chi2_per_point", "sizes chi2 / point"),
            ("linearity_chi2_per_point", "linearity chi2 / point"),
            ("correlations_chi2_per_point", "correlations chi2 / point"),
            ("ptc_chi2_per_point", "PTC residuals chi2 / point"),
            ("ptc_max_frac_residual", "PTC max |residual| / variance"),
            ("star_residual_rms_over_peak", "stacked star residual rms / peak (fixed)"),
            ("star_residual_chi2_per_pixel", "stacked star residual chi2 / pixel (fixed)")]
    header = "| quantity | before | after |" + (" physical only |" if physical else "")
    if heldout:
        header += " held-out before | held-out after |"
    columns = 3 + bool(physical) + 2 * bool(heldout)
    lines = [header, "|" + "---|" * columns]
    for key, label in keys:
        if key not in before:
            continue
        row = f"| {label} | {format_number(before[key])} | {format_number(after[key])} |"
        if physical:
            row += f" {format_number(physical.get(key))} |"
        if heldout:
            row += " " + " | ".join(format_number(part.get(key)) for part in heldout) + " |"
        lines.append(row)
    return lines


def _star_residual_lines(star):
    lines = ["## Stacked residual of the stars", "",
             f"{star['n_stars']} stars, data minus P(F) (`FluxDependentPSF.star_image`), divided "
             "by each star's flux and averaged: rms "
             f"{format_number(star['rms_over_peak'])} of the model peak, chi2 / pixel "
             f"{format_number(star['chi2_per_pixel'])} against Poisson + read noise (about 1 "
             "when P(F) describes the stars). No candidate changes it: it is reported, not "
             "fitted.", "", "| radius (px) | mean residual / peak |", "|---|---|"]
    peak = star["model_peak"]
    lines += [f"| {radius:.2f} | {format_number(value / peak)} |"
              for radius, value in zip(star["radius"], star["profile"])]
    return lines + [""]


def diagnosis_markdown(result, *, title="bfpsf diagnose", figures=(), context=(),
                       star_residual=None):
    """Markdown text of a `DiagnosisResult` (and of the stars' stacked residual, if given)."""
    data = result.to_json_dict()
    lines = [f"# {title}", ""]
    lines += list(context)
    if context:
        lines.append("")
    if star_residual is not None:
        lines += _star_residual_lines(star_residual)
    lines += ["## Residuals before and after", ""]
    heldout = None
    if data.get("residual_after_heldout"):
        heldout = (data["residual_before_heldout"], data["residual_after_heldout"])
    lines += _residual_rows(data["residual_before"], data["residual_after"],
                            data.get("residual_physical"), heldout)
    if heldout:
        holdout = data["holdout"]
        lines += ["", f"Held out: a fraction {holdout['fraction']:g} of the data (sizes split by "
                  f"{holdout['sizes_split_by']}; flat pairs alternate), never fitted: the "
                  "effects and the size scale are fixed at their in-sample values. An effect "
                  "that does not lower the held-out chi2 is not confirmed.", ""]
        lines += [f"- `{name}`: {'confirmed' if ok else 'NOT CONFIRMED'} on the held-out data"
                  for name, ok in data["confirmed"].items()]
    titles = {entry.name: (entry.title, entry.prior_text) for entry in GLOBAL_NUISANCES}
    for name, value in data.get("nuisance", {}).items():
        title, prior = titles.get(name, (name, "the flats' error"))
        against = value.get("contradicted_by")
        lines += ["", f"{title} (nuisance; prior {format_number(value['prior'])}: {prior}): "
                  f"{format_number(value['value'])} +- {format_number(value['error'])}"
                  + (f"; contradicted by {against}, not applied." if against else ".")]
    lines += ["", "## Unexplained", ""]
    if not data.get("unexplained"):
        # nothing beyond 3 errors on the held-out exposures; the verdict may still name what
        # the fitted ones showed (a new user's "Nothing significant" beside NOT EXPLAINED)
        reasons = (data.get("verdict") or {}).get("reasons") or []
        lines.append("Nothing significant left unexplained" + (
            f" on the held-out exposures alone; the verdict's reasons: {'; '.join(reasons)}."
            if reasons else "."))
    # the line the command prints: axis, parity, flux, column, row and exposure dependence
    lines += [f"- {describe_entry(entry)}" for entry in data.get("unexplained", [])]
    if data.get("residual_physical"):
        lines += ["", "'physical only': every effect with a physical value fixed at it, no free "
                  f"parameter ({', '.join(data['residual_physical']['effects'])})."]
    lines += ["", f"Selected (Delta BIC < {result.threshold:g}, in order): "
              + (", ".join(f"`{name}`" for name in result.selected) or "nothing"), ""]
    for name, values in data["parameters"].items():
        lines.append(f"- `{name}`: {', '.join(values['names'])} = "
                     f"{format_number(values['value'])} +- {format_number(values['error'])}"
                     + (f" (physical value {format_number(values['physical'])})"
                        if values["physical"] else ""))
        if data["ambiguous"].get(name):
            lines.append(f"  - not distinguishable from: "
                         f"{', '.join('`' + n + '`' for n in data['ambiguous'][name])}")
    lines += ["", "## Candidates", "",
              "| round | candidate | k | Delta chi2 | Delta BIC | parameters | allowed |",
              "|---|---|---|---|---|---|---|"]
    for entry in data["candidates"]:
        if not entry["testable"]:
            lines.append(f"| {entry['round']} | {entry['name']} | {entry['k']} | not testable "
                         "(no observable it changes) | | | |")
            continue
        lines.append(f"| {entry['round']} | {entry['name']} | {entry['k']} | "
                     f"{format_number(entry['statistic'], 4)} | "
                     f"{format_number(entry['delta_bic'], 4)} | "
                     f"{format_number(entry['parameters'])} +- "
                     f"{format_number(entry['errors'], 2)} | {format_number(entry['allowed'])} |")
    if figures:
        lines += ["", "## Figures", ""]
        lines += [f"![{name}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


def write_diagnosis_report(result, directory, *, title="bfpsf diagnose", context=(),
                           residual_images=None, star_residual=None, overwrite=False):
    """Write ``report.md``, ``sizes.png``, ``candidates.png`` (and residual images) to a directory.

    With PTC residuals (``result.ptc_curves``) also ``ptc_residuals.png``.

    Parameters
    ----------
    result : DiagnosisResult
    directory : str or Path
    title : str
    context : sequence of str
        Lines of Markdown put before the tables (data set, caveats).
    residual_images : dict, optional
        Label -> stacked residual image (e-); drawn with their radial profiles.
    star_residual : dict, optional
        `bfpsf.diagnosis.star_residual.stacked_star_residual` output: summarised in the text.
    overwrite : bool

    Returns
    -------
    Path
        The Markdown file.
    """
    names = ["report.md", "candidates.png"]
    if result.curves:
        names.append("sizes.png")
    if result.ptc_curves:
        names.append("ptc_residuals.png")
    if residual_images:
        names += ["residual_images.png", "radial_profile.png"]
    directory = _prepare(directory, names, overwrite)
    figures = []
    if result.curves:
        _save(plot_sizes_before_after(result.curves, title=title), directory / "sizes.png")
        figures.append("sizes.png")
    _save(plot_candidates(result.to_json_dict()["candidates"], threshold=result.threshold),
          directory / "candidates.png")
    figures.append("candidates.png")
    if result.ptc_curves:
        _save(plot_ptc_residuals(result.ptc_curves), directory / "ptc_residuals.png")
        figures.append("ptc_residuals.png")
    if residual_images:
        _save_residual_images(residual_images, directory)
        figures += ["residual_images.png", "radial_profile.png"]
    path = directory / "report.md"
    write_text(path, diagnosis_markdown(result, title=title, figures=figures, context=context,
                                        star_residual=star_residual), overwrite=True)
    return path


def _save_residual_images(images, directory):
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, len(images), figsize=(4.5 * len(images), 4), squeeze=False)
    limit = max(np.nanmax(np.abs(image)) for image in images.values())
    for ax, (label, image) in zip(axes[0], images.items()):
        plot_residual_image(np.clip(image, -limit, limit), ax=ax, title=label)
    _save(figure, directory / "residual_images.png")
    _save(plot_radial_profile(list(images.values()), list(images.keys())),
          directory / "radial_profile.png")


def validation_markdown(result, *, figures=()):
    """Markdown text of a `bfpsf.validation.validate.validate` result."""
    config = result["config"]
    lines = ["# bfpsf validate: end-to-end on GalSim SiliconSensor", "",
             f"Sensor `{config['sensor']}`, Moffat FWHM {config['fwhm']} px, beta "
             f"{config['beta']}, peaks {', '.join(f'{p / 1e3:g}' for p in config['peaks_e'])} "
             f"ke-, {config['n_per_level']} spots per level; flats "
             f"{config['flat_size']}^2 px, {len(config['flat_levels_e'])} levels x "
             f"{config['flat_pairs']} pairs. Model shifts for P(F), inverse and loop: "
             f"{result.get('model_shifts')}.", ""]
    area = result["area"]
    lines += ["## Truth a vs recovered (1/e-)", "",
              "| lag (dx,dy) | truth | recovered | error | pull |", "|---|---|---|---|---|"]
    for index, lag in enumerate(area["lags"]):
        recovered = area["recovered"][index] if area["recovered"] else None
        error = area["recovered_err"][index] if area["recovered_err"] else None
        pull = area["pull"][index] if area["pull"] else None
        lines.append(f"| ({lag[0]},{lag[1]}) | {format_number(area['truth'][index])} | "
                     f"{format_number(recovered)} | {format_number(error, 2)} | "
                     f"{format_number(pull, 2)} |")
    if not result["calibration"].get("available"):
        lines.append(f"\nCalibration not available: {result['calibration'].get('reason')}")
    slopes = result["slopes"]

    def measured(label, prefix):
        return (f"| {label} | " + " | ".join(
            f"{format_number(slopes[f'{prefix}slope_{axis}'], 4)} +- "
            f"{format_number(slopes[f'{prefix}slope_{axis}_err'], 2)}" for axis in "xy")
            + " |")

    lines += ["", "## Brighter-fatter slopes (pixels per 100 ke- of peak)", "",
              "| | X | Y |", "|---|---|---|", measured("measured (SiliconSensor spots)", "")]
    if "paired_slope_x" in slopes:
        lines.append(measured("measured, spot minus its BF-free twin", "paired_"))
    for row in result["prediction"].get("rows", []):
        cells = prediction_cells(row)
        lines.append(f"| predicted from {row['shifts']} | {cells[0]} | {cells[1]} |")
    lines += ["", "## Residual slope (percent of the raw slope)", "",
              "Paired: each spot's BF change against its BF-free twin (same photons, diffusion "
              "and noise with BF off) minus the model's; unpaired: the sizes alone.", "",
              "| method | X paired | Y paired | X unpaired | Y unpaired |",
              "|---|---|---|---|---|"]
    for key, label in (("psf", "flux-dependent PSF P(F)"),
                       ("inverse", "pixel-level inverse (G15)")):
        stage = result[key]
        if not stage.get("available"):
            lines.append(f"| {label} | not available: {stage.get('reason')} | |")
            continue
        cells = [f"{format_number(stage[f'residual_slope_{axis}{kind}_percent'], 3)} +- "
                 f"{format_number(stage[f'residual_slope_{axis}{kind}_percent_err'], 2)}"
                 for kind in ("", "_unpaired") for axis in "xy"]
        lines.append(f"| {label} | {' | '.join(cells)} |")
    psf = result["psf"]
    if psf.get("available"):
        lines += ["", "## Photometry bias, brightest minus faintest level (mmag)", "",
                  "| flux fit | static PSF from the bright spots | P(F) |", "|---|---|---|",
                  f"| least squares, whole stamp, true position | "
                  f"{format_number(psf['photometry_bias_static_mmag'], 3)} | "
                  f"{format_number(psf['photometry_bias_flux_dependent_mmag'], 3)} |"]
        if "photometry_bias_photutils_static_mmag" in psf:
            lines.append(f"| photutils PSFPhotometry (bfpsf.measure.photometry) | "
                         f"{format_number(psf['photometry_bias_photutils_static_mmag'], 3)} | "
                         f"{format_number(psf['photometry_bias_photutils_flux_dependent_mmag'], 3)} |")
    diagnosis = result["diagnose"]
    lines += ["", "## Closed loop on the same data", "",
              f"Selected: {', '.join(diagnosis['selected']) or 'nothing'}; BF slope residual "
              f"before X {format_number(diagnosis['residual_before'].get('slope_x_percent'))} %,"
              f" Y {format_number(diagnosis['residual_before'].get('slope_y_percent'))} %; after "
              f"X {format_number(diagnosis['residual_after'].get('slope_x_percent'))} %, Y "
              f"{format_number(diagnosis['residual_after'].get('slope_y_percent'))} %."]
    lines += ["", "## Timing (s)", "", "| stage | s |", "|---|---|"]
    lines += [f"| {name} | {value:.1f} |" for name, value in result["timing_s"].items()]
    if figures:
        lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


def write_validation_report(result, directory, *, overwrite=False):
    """Write ``report.md`` and figures of a validation run; returns the Markdown path."""
    names = ["report.md", "sizes.png", "candidates.png"]
    images = result.get("residual_images")
    if images:
        names += ["residual_images.png", "radial_profile.png"]
    directory = _prepare(directory, names, overwrite)

    diagnosis = result["diagnosis"]
    figures = []
    if diagnosis.curves:
        _save(plot_sizes_before_after(diagnosis.curves, title="SiliconSensor spots"),
              directory / "sizes.png")
        figures.append("sizes.png")
    _save(plot_candidates(diagnosis.to_json_dict()["candidates"],
                          threshold=diagnosis.threshold), directory / "candidates.png")
    figures.append("candidates.png")
    if images:
        _save_residual_images(images, directory)
        figures += ["residual_images.png", "radial_profile.png"]
    path = directory / "report.md"
    write_text(path, validation_markdown(result, figures=figures), overwrite=True)
    return path
