"""Measured size and correlation tables (the published data sets) as loop observables.

`read_lage_spot_table` (UC Davis ITL-3800C-002 spots, Lage), `read_bot_spot_table` (LSSTCam BOT
E2V spot moments), `observables_from_tables` (a correlation table and a size table) and
`observables_from_measured` (a data-set folder named in `MEASURED_SETS`).
"""

import os

import numpy as np
from astropy.table import Table
from scipy.special import erf

from ..calibration.measured import read_measured_area
from ..calibration.shifts_ei import solve_ei_shifts
from ..errors import BFPSFError, BFPSFInputError, BFPSFValueError
from ..least_squares import polynomial_fit
from .observables import observables_from_sizes
from .tables import SizeTable

__all__ = ["read_lage_spot_table", "read_bot_spot_table", "observables_from_tables",
           "observables_from_measured", "MEASURED_SETS"]


def _scatter_errors(peak, values, group, degree=2):
    """Per-point error from the scatter about a polynomial in peak, per group (pixels).

    For tables that give no per-point errors. A quadratic (not a line) so that curvature, which
    a candidate may explain, does not inflate the errors; the rms is corrected for the fitted
    degrees of freedom.
    """
    errors = np.empty_like(values)
    for g in np.unique(group):
        members = group == g
        x, y = peak[members] / 1e5, values[members]
        if members.sum() <= degree + 2:
            msg = f"group {g} has {members.sum()} points: too few to estimate errors"
            raise BFPSFInputError(msg, int(members.sum()))
        chi2 = polynomial_fit(x, y, 1.0, degree)[2]  # unit errors: the sum of squares
        errors[members] = np.sqrt(chi2 / (members.sum() - degree - 1))
    return errors


def read_lage_spot_table(path, *, corrected=False):
    """Lage's spot sizes vs peak (UC Davis ITL-3800C-002) as a `SizeTable`.

    The table gives no per-point errors: they are estimated from the scatter about a quadratic
    per segment and axis (`_scatter_errors`). ``corrected=True`` reads the sizes after Lage's
    kernel correction.
    """
    table = Table.read(path, format="ascii.csv")
    prefix = "corr_" if corrected else ""
    try:
        peak = np.asarray(table[f"{prefix}peak_pixel_electrons"], float)
        sigma_x = np.asarray(table[f"{prefix}sigma_x_pix"], float)
        sigma_y = np.asarray(table[f"{prefix}sigma_y_pix"], float)
        group = np.unique(np.asarray(table["segment"]), return_inverse=True)[1]
    except KeyError as error:
        msg = f"{path}: missing column {error} of Lage's spot table"
        raise BFPSFInputError(msg, path) from None
    return SizeTable(peak, sigma_x, sigma_y, _scatter_errors(peak, sigma_x, group),
                     _scatter_errors(peak, sigma_y, group), group=group,
                     label="ITL-3800C-002 spots (Lage)")


def read_bot_spot_table(path, *, gain, peak_fraction=None, corrected=False):
    """LSSTCam BOT spot moments (Lage's notebooks) as a `SizeTable` with peak in e-.

    sigma = sqrt(xx), error = max(rms / sqrt(n) / (2 sigma), scatter about a quadratic): the
    exposures come from different epochs and jump by more than the statistical error
    (SOURCE.md). The peak is flux * gain * ``peak_fraction``; default the central-pixel
    fraction of a Gaussian of the mean size.
    """
    table = Table.read(path, format="ascii.csv", comment="#")
    prefix = "corr_" if corrected else ""
    flux_e = np.asarray(table[f"{prefix}mean_flux_adu"], float) * gain
    xx = np.asarray(table[f"{prefix}mean_xx_pix2"], float)
    yy = np.asarray(table[f"{prefix}mean_yy_pix2"], float)
    n = np.asarray(table[f"{prefix}n_spots"], float)
    sigma_x, sigma_y = np.sqrt(xx), np.sqrt(yy)
    if peak_fraction is None:
        edge_x = 0.5 / (np.sqrt(2) * np.sqrt(np.mean(xx) - 1 / 12))
        edge_y = 0.5 / (np.sqrt(2) * np.sqrt(np.mean(yy) - 1 / 12))
        peak_fraction = erf(edge_x) * erf(edge_y)
    peak = flux_e * peak_fraction
    group = np.zeros(peak.size, int)
    stat_x = np.asarray(table[f"{prefix}rms_xx_pix2"], float) / np.sqrt(n) / (2 * sigma_x)
    stat_y = np.asarray(table[f"{prefix}rms_yy_pix2"], float) / np.sqrt(n) / (2 * sigma_y)
    err_x = np.maximum(stat_x, _scatter_errors(peak, sigma_x, group))
    err_y = np.maximum(stat_y, _scatter_errors(peak, sigma_y, group))
    return SizeTable(peak, sigma_x, sigma_y, err_x, err_y, group=group,
                     label="LSSTCam BOT R22_S11 E2V spots (Lage)")


#: The measured data sets the table mode knows by folder name.
MEASURED_SETS = {
    "lage_BF_Kernel_ITL3800C002": dict(
        correlations="corr_meas_VBB60_7_2_3500flats.txt",
        sizes="spot_sizes_vs_flux_ITL-3800C-002_20171128_VBB60.csv", kind="lage",
        measure="gaussian_fit"),
    "lage_LSSTCam_BOT_spots_2019": dict(
        correlations=("../lsst_cp_pipe_LSSTCam_R22_S11_amatrix/"
                      "amatrix_LSSTCam_R22_S11_E2V-CCD250-382.csv"),
        sizes="spot_moments_vs_flux_BOT_E2V_R22_S11.csv", kind="bot",
        ptc="ptc_polyfit_BOT_E2V_R22_S11.csv", measure="moments"),
}


def observables_from_tables(correlations, sizes, *, kind=None, gain=None, measure=None,
                            phases=3, corrected=False):
    """Observables from a measured a / correlation table and a size-vs-flux table.

    Parameters
    ----------
    correlations : path
        Any table `bfpsf.calibration.measured.read_measured_area` reads.
    sizes : path
        Lage's ITL spot table (``kind='lage'``) or BOT spot moments (``kind='bot'``; needs
        ``gain``, e-/ADU). The kind is guessed from the header when not given.
    measure : {'moments', 'gaussian_fit'}, optional
        How the sizes were measured (default: Gaussian fit for Lage's table, moments for BOT).
    corrected : bool
        Use the sizes after the published kernel correction instead of the raw ones.

    Returns
    -------
    Observables
        With ``meta`` holding ``area``, ``area_err``, ``shift_solution`` and the inputs.
    """
    measured = read_measured_area(correlations)
    solution = solve_ei_shifts(measured.area, measured.area_err, n_monte_carlo=0)
    with open(sizes) as handle:
        text = handle.read(4096)
    if kind is None:
        kind = "lage" if text.startswith("segment,") else "bot"
    if kind == "lage":
        table = read_lage_spot_table(sizes, corrected=corrected)
        measure = measure or "gaussian_fit"
    elif kind == "bot":
        if gain is None:
            msg = "BOT spot moments are in ADU: give the gain (e-/ADU)"
            raise BFPSFInputError(msg, sizes)
        table = read_bot_spot_table(sizes, gain=gain, corrected=corrected)
        measure = measure or "moments"
    else:
        msg = f"kind must be 'lage' or 'bot', got {kind!r}"
        raise BFPSFValueError(msg, kind)
    meta = {"correlations": str(correlations), "sizes": str(sizes), "kind": kind,
            "measure": measure, "shift_solution": solution, "area_err": measured.area_err,
            "gain": gain, "corrected": corrected}
    return observables_from_sizes(table, solution.shifts, area=measured.area,
                                  shift_draws=_area_shift_draws(measured.area,
                                                                measured.area_err),
                                  measure=measure, phases=phases, meta=meta)


def _area_shift_draws(area, area_err, n_draws=8, seed=0):
    """Shifts of a(dx, dy) drawn within their errors (lags independent), each solved as the
    table's own shifts are (`bfpsf.calibration.shifts_ei.solve_ei_shifts`); draws the
    solver rejects are left out. A measured table carries errors, not bootstrap samples."""
    area, area_err = np.asarray(area, float), np.asarray(area_err, float)
    if not np.any(area_err > 0):
        return []
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(int(n_draws)):
        try:
            draws.append(solve_ei_shifts(area + rng.standard_normal(area.shape) * area_err,
                                         n_monte_carlo=0).shifts)
        except BFPSFError:
            continue
    return draws


def observables_from_measured(directory, *, phases=3, corrected=False):
    """Observables of one of the measured data sets (`MEASURED_SETS`) by its folder."""
    directory = os.fspath(directory).rstrip("/")
    name = os.path.basename(directory)
    if name not in MEASURED_SETS:
        msg = f"unknown measured data set {name!r}; known: {sorted(MEASURED_SETS)}"
        raise BFPSFInputError(msg, name)
    spec = MEASURED_SETS[name]
    gain = None
    if "ptc" in spec:
        ptc = Table.read(os.path.join(directory, spec["ptc"]), format="ascii.csv", comment="#")
        gain = float(np.mean(ptc["gain_e_per_adu"]))
    return observables_from_tables(os.path.join(directory, spec["correlations"]),
                                   os.path.join(directory, spec["sizes"]), kind=spec["kind"],
                                   gain=gain, measure=spec["measure"], phases=phases,
                                   corrected=corrected)

