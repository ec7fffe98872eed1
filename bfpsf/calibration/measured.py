"""Readers for published tables of measured area coefficients a(dx, dy).

Three formats are recognised from their header line (the tables shipped in `bfpsf.data`):

* Lage ``corr_meas*.txt`` (UC Davis BF_Kernel): columns ``ii jj C sig N`` with ``ii`` the ROW
  (parallel, dy) offset and ``jj`` the COLUMN (serial, dx) offset; ``C`` is the correlation
  coefficient at a reference flux (80 ke- for the published files), so a = C / flux per e-.
  The (0, 0) entry is Cov00 / V_tot - 1. Footer lines (``Slope = ...``, ``C10 = ...``) are not
  table rows and are skipped.
* Lage ``*_covariances_*.txt`` (Poisson_CCD measurements): columns ``i j "Cov mean" "Cov std"``,
  a_ij in 1/e- with i = x (serial) and j = y (parallel).
* cp_pipe a-matrix CSV: ``i,j,a_mean_per_e,a_sigma_per_e`` with i = x, j = y (cp_pipe
  ``makeCovArray`` convention).

Every reader returns the table in the package convention: indexed [dy, dx], 1/e-.
"""

import dataclasses
import os

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError

__all__ = ["MeasuredArea", "read_measured_area"]


@dataclasses.dataclass(frozen=True)
class MeasuredArea:
    """Area coefficients read from a published table.

    Attributes
    ----------
    area, area_err : ndarray, shape (n + 1, n + 1)
        a(dx, dy) and its 1-sigma error, 1/e-, indexed [dy, dx] for dx, dy = 0..n.
    path : str
        The file read.
    table_format : str
        ``'corr_meas'``, ``'poisson_ccd'`` or ``'cp_pipe_csv'``.
    """

    area: np.ndarray
    area_err: np.ndarray
    path: str
    table_format: str


def _rows(path, delimiter=None, ncols=4):
    """Numeric rows of a text table, stopping at the first line that is not ``ncols`` numbers."""
    rows = []
    with open(path) as handle:
        lines = handle.read().splitlines()
    for line in lines[1:]:
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split(delimiter)
        try:
            values = [float(field) for field in fields if field.strip()]
        except ValueError:
            break  # footer (e.g. "Slope = -1.214")
        if len(values) < ncols:
            break
        rows.append(values[:ncols])
    if not rows:
        msg = f"{path}: no numeric table rows found"
        raise BFPSFInputError(msg, path)
    return np.array(rows)


def _to_grid(path, first, second, values, errors, first_is_dy):
    first = first.astype(int)
    second = second.astype(int)
    size = max(first.max(), second.max()) + 1
    if first.min() < 0 or second.min() < 0 or len(values) != size * size:
        msg = (f"{path}: expected a full {size}x{size} quadrant of non-negative lags, "
               f"got {len(values)} rows")
        raise BFPSFInputError(msg, path)
    area = np.full((size, size), np.nan)
    area_err = np.full((size, size), np.nan)
    dy, dx = (first, second) if first_is_dy else (second, first)
    area[dy, dx] = values
    area_err[dy, dx] = errors
    if not (np.all(np.isfinite(area)) and np.all(np.isfinite(area_err))):
        msg = f"{path}: lags repeated or missing in the table"
        raise BFPSFInputError(msg, path)
    return area, area_err


def read_measured_area(path, *, flux=80000.0):
    """Read a measured a(dx, dy) table in one of the published formats.

    Parameters
    ----------
    path : str or path-like
        The table.
    flux : float, optional
        Reference flux, e-, of a ``corr_meas`` table: its correlation coefficients C are
        converted to a = C / flux per electron (G15 eq. covar: C = a mu to first order).
        Default 80000 (the flux at which Lage's published C are quoted). Ignored for tables
        already in 1/e-.

    Returns
    -------
    MeasuredArea
        area and area_err indexed [dy, dx], 1/e-.

    Raises
    ------
    BFPSFInputError
        Unknown header, incomplete table.
    """
    path = os.fspath(path)
    if flux <= 0:
        msg = f"flux must be positive (e-), got {flux}"
        raise BFPSFValueError(msg, flux)
    with open(path) as handle:
        header = handle.readline()
    words = header.replace(",", " ").split()
    if words[:2] == ["ii", "jj"]:
        rows = _rows(path)
        area, area_err = _to_grid(path, rows[:, 0], rows[:, 1], rows[:, 2] / flux,
                                  rows[:, 3] / flux, first_is_dy=True)
        return MeasuredArea(area, area_err, path, "corr_meas")
    if words[:3] == ["i", "j", "Cov"]:
        rows = _rows(path)
        area, area_err = _to_grid(path, rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3],
                                  first_is_dy=False)
        return MeasuredArea(area, area_err, path, "poisson_ccd")
    if words[:3] == ["i", "j", "a_mean_per_e"]:
        rows = _rows(path, delimiter=",")
        area, area_err = _to_grid(path, rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3],
                                  first_is_dy=False)
        return MeasuredArea(area, area_err, path, "cp_pipe_csv")
    if header.startswith("#"):
        # cp_pipe CSV with comment lines: find the real header
        with open(path) as handle:
            lines = [line for line in handle if not line.startswith("#")]
        if lines and lines[0].replace(",", " ").split()[:3] == ["i", "j", "a_mean_per_e"]:
            values = np.array([[float(v) for v in line.split(",")] for line in lines[1:]
                               if line.strip()])
            area, area_err = _to_grid(path, values[:, 0], values[:, 1], values[:, 2],
                                      values[:, 3], first_is_dy=False)
            return MeasuredArea(area, area_err, path, "cp_pipe_csv")
    msg = (f"{path}: unrecognised table header {header.strip()!r}; expected 'ii jj C sig' "
           "(corr_meas), 'i j Cov mean Cov std' (Poisson_CCD) or 'i,j,a_mean_per_e,a_sigma_per_e'")
    raise BFPSFInputError(msg, path)
