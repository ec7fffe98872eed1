"""Star sizes binned for the closed loop: in quantile bins of flux, per exposure, and in a grid
of detector position (columns, the distance from the amplifier; rows, the parallel transfers),
with errors pooled over the rows of each flux bin."""

import numpy as np

from ..errors import BFPSFInputError
from .position_split import dependent_directions
from .tables import SizeTable

__all__ = ["AUTO_POSITION_GRID", "DEFAULT_BINS", "MIN_GRID_BINS", "auto_position_bins",
           "binned_sizes", "position_grid"]


def position_grid(position_bins):
    """``position_bins`` as (columns, rows): an int N is N ranges of column (the distance
    from the amplifier) and one of row, as ``--position-bins N``; a pair as given."""
    if np.ndim(position_bins) == 0:
        return int(position_bins), 1
    columns, rows = (int(value) for value in position_bins)
    return columns, rows


#: The grid (columns, rows) ``position_bins='auto'`` splits the bins in where every cell of
#: every exposure can hold 3 stars.
AUTO_POSITION_GRID = (2, 2)
#: Peak bins by default, and the fewest that a default position grid may leave: with 4, the
#: bench's 54 spots per exposure (in rows of one level, the phases along x) lost a factor 4
#: in the slope's error (held-out X +2.8 +- 5.6 against +2.1 +- 1.3 % of raw, one range of
#: 10 bins); a new user's 48 randomly placed stars lost 1.5 on X and none on Y.
DEFAULT_BINS = 10
MIN_GRID_BINS = 6
#: The fewest peak bins one range is given by default (an exposure of fewer than 30 stars
#: fills only ``stars // 3`` bins with 3 stars).
MIN_ONE_RANGE_BINS = 3


def auto_position_bins(stars_per_exposure, n_bins=None, split=None):
    """``position_bins='auto'``: `AUTO_POSITION_GRID` when the exposure with the fewest stars
    fills each of its peak bins x 4 cells with 3 stars; else two ranges of the row (1 x 2)
    or of the column (2 x 1) where every star's BF slope shows a dependence on it
    (``split``, `bfpsf.diagnosis.position_split.star_slope_split`, beyond its
    `SPLIT_NSIGMA`) and each cell can hold 3 stars in `MIN_ONE_RANGE_BINS` peak bins or
    more; else one range.

    With ``n_bins`` None (not chosen by the user) the peak bins are `DEFAULT_BINS`, or as
    many as the grid leaves (at least `MIN_GRID_BINS`, so 72 stars per exposure): a new
    user's row-dependent smear, without a grid and so without its row term, left the
    EMPIRICAL term overshooting held out (X +45 -> -22 +- 6 % of raw); with a 2 x 2 grid of
    6 bins, -8 +- 10. Fewer stars keep one range (``--position-bins 2x2 --bins 4`` asks for
    the grid at the cost of precision).

    Returns
    -------
    (position_bins, n_bins, str)
        The grid (or 1), the peak bins, and the choice in words for the report.
    """
    cells = int(np.prod(AUTO_POSITION_GRID))
    fewest = int(np.min(stars_per_exposure))
    fits = fewest // (3 * cells)
    if n_bins is not None:
        bins = fewest_bins = int(n_bins)
    else:
        bins = fits if MIN_GRID_BINS <= fits < DEFAULT_BINS else DEFAULT_BINS
        fewest_bins = MIN_GRID_BINS
    grid = "x".join(map(str, AUTO_POSITION_GRID))
    if fits >= bins:
        return AUTO_POSITION_GRID, bins, (f"{grid} (auto: {fewest} or more stars per "
                                          f"exposure, {bins} peak bins)")
    dependent = dependent_directions(split)
    along = max(dependent, key=dependent.get) if dependent else None
    if along is not None and (n_bins is None or fewest // (3 * 2) >= int(n_bins)):
        # one axis of the position split in two: the direction every star's slope depends on
        halves = fewest // (3 * 2)
        bins = int(n_bins) if n_bins is not None else int(min(halves, DEFAULT_BINS))
        if bins >= MIN_ONE_RANGE_BINS:
            grid = (1, 2) if along == "row" else (2, 1)
            return grid, bins, (f"{grid[0]}x{grid[1]} (auto: {fewest} stars in an exposure, "
                                f"too few for a {'x'.join(map(str, AUTO_POSITION_GRID))} "
                                f"grid; every star's BF slope depends on the {along}; "
                                f"{bins} peak bins)")
    if n_bins is None:
        # one range: as many bins as a typical exposure fills with 3 stars each, at least 3
        # (helper-30's 9 stars per exposure in 10 bins left 5 binned points for 4 exposures
        # held out, and the diagnosis stopped)
        typical = int(np.median(stars_per_exposure))
        bins = int(np.clip(typical // 3, MIN_ONE_RANGE_BINS, DEFAULT_BINS))
    return 1, bins, (f"not tested (auto: {fewest} stars in an exposure; a {grid} grid of "
                     f"{fewest_bins} peak bins needs {3 * cells * fewest_bins}: "
                     "give --bins and --position-bins; every star's slope is tested for the "
                     "column and the row without a grid)")


def _quantile_cells(values, count):
    """Index 0..count-1 of each value's quantile range (all 0 for one range)."""
    if values is None or count <= 1:
        return None
    edges = np.quantile(values, np.linspace(0.0, 1.0, count + 1))
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, count - 1)


def binned_sizes(flux, peak, sigma_x, sigma_y, exposure, n_bins, label, *, x=None, y=None,
                  skew=None, position_bins=1):
    """Mean peak and sizes in quantile bins of flux for each exposure (the same bin edges for
    all), errors from the scatter pooled over the rows of each flux bin (`_pool_errors`);
    bins with fewer than 3 stars are left out.

    Bins are in total flux, not in measured peak: at one flux the peak of a pixelised star
    depends on its sub-pixel phase (by 30 % for a 3 px FWHM), and so does its size, so bins
    of measured peak would select phases and bias the sizes with the peak.

    With ``x`` and ``y`` (star columns and rows, pixels) and ``position_bins`` (N, or
    (N columns, M rows), `position_grid`) above one, every bin is also split in that many
    quantile ranges of x (the distance from the amplifier) and of y (the row, the parallel
    transfers): the rows carry their stars' mean x (``x_detector``) where the columns are
    split and mean y (``y_detector``) where the rows are, and each cell of the grid is an
    intercept group. With ``skew`` ((skew_x,
    skew_y) per star, `bfpsf.diagnosis.odd_moments.star_skewness`, and optionally the cross
    moment e2) the rows carry their means and errors (stars without one left out of it).
    """
    edges = np.quantile(flux, np.linspace(0.0, 1.0, n_bins + 1))
    index = np.clip(np.searchsorted(edges, flux, side="right") - 1, 0, n_bins - 1)
    n_columns, n_rows = position_grid(position_bins)
    x_cell, y_cell = _quantile_cells(x, n_columns), _quantile_cells(y, n_rows)
    column = np.zeros(flux.size, int)
    if x_cell is not None:
        column = column + x_cell * n_rows
    if y_cell is not None:
        column = column + y_cell
    rows, row_members = [], []
    for image in np.unique(exposure):
        for part in np.unique(column):
            for k in range(n_bins):
                members = (index == k) & (exposure == image) & (column == part)
                if members.sum() < 3:
                    continue
                root_n = np.sqrt(members.sum())
                row = [peak[members].mean(), sigma_x[members].mean(), sigma_y[members].mean(),
                       sigma_x[members].std(ddof=1) / root_n,
                       sigma_y[members].std(ddof=1) / root_n, image, part,
                       np.nan if x_cell is None else x[members].mean(),
                       np.nan if y_cell is None else y[members].mean()]
                for values in (skew if skew is not None else ()):
                    known = members & np.isfinite(values)
                    row += ([values[known].mean(), values[known].std(ddof=1)
                             / np.sqrt(known.sum())] if known.sum() >= 3 else [np.nan, np.nan])
                rows.append(row)
                row_members.append((k, members))
    if len(rows) < 3:
        msg = f"only {len(rows)} peak bins hold 3 or more stars: too few to diagnose"
        raise BFPSFInputError(msg, len(rows))
    rows = np.array(rows)
    # always pooled: a row of one exposure holds a few stars (6 in a new user's field), whose
    # own scatter is a poor error and, as a weight, inflates chi2 by (n - 1) / (n - 3)
    _pool_errors(rows, row_members, (sigma_x, sigma_y, *(skew if skew is not None else ())))
    extra = {}
    if x_cell is not None:
        extra["x_detector"] = rows[:, 7]
    if y_cell is not None:
        extra["y_detector"] = rows[:, 8]
    if skew is not None and np.all(np.isfinite(rows[:, 9:13])) and np.all(rows[:, [10, 12]] > 0):
        extra.update(skew_x=rows[:, 9], skew_x_err=rows[:, 10], skew_y=rows[:, 11],
                     skew_y_err=rows[:, 12])
    if (skew is not None and len(skew) > 2 and np.all(np.isfinite(rows[:, 13:15]))
            and np.all(rows[:, 14] > 0)):
        extra.update(cross=rows[:, 13], cross_err=rows[:, 14])
    return SizeTable(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], label=label,
                     exposure=rows[:, 5].astype(int), group=rows[:, 6].astype(int), **extra)


def _pool_errors(rows, row_members, quantities):
    """Errors of binned means from the scatter pooled over every row of the same flux bin
    (rows of a few stars each estimate their own scatter badly: 3 stars give it to 50 %)."""
    columns = ((1, 3), (2, 4), (9, 10), (11, 12))
    for values, (mean_column, error_column) in zip(quantities, columns):
        for k in {k for k, _ in row_members}:
            deviations, count = [], 0
            for (bin_k, members), row in zip(row_members, rows):
                if bin_k != k:
                    continue
                known = members & np.isfinite(values)
                deviations.append(values[known] - values[known].mean())
                count += 1
            deviations = np.concatenate(deviations)
            pooled = np.sqrt(np.sum(deviations ** 2) / max(deviations.size - count, 1))
            for index, (bin_k, members) in enumerate(row_members):
                if bin_k == k:
                    known = members & np.isfinite(values)
                    rows[index, error_column] = pooled / np.sqrt(max(known.sum(), 1))
