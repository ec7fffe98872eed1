"""photutils fits of groups of stars, each on the data minus the models of every other star.

photutils' `~photutils.psf.PSFPhotometry` fits each group of stars within its fit boxes and
leaves a neighbour outside the group in the pixels: in a dense field, a bright neighbour's
wings in a faint star's fit box. `fit_without_neighbours` subtracts every other star's model
first; `with_found`, `without_lost` and `merged` let the stars found in a fit's residual
(`bfpsf.measure.residual_sources`) join that fit without refitting the whole field.
"""

import numpy as np
from astropy.table import Table, vstack
from scipy.spatial import cKDTree

from .line_features import near_lines
from .neighbours import COMPANION_SEPARATION
from .sources import SourceFlag

#: photutils' flags of a fit that failed: negative flux, no convergence, fully masked.
FAILED_FIT = 4 | 8 | 128

__all__ = ["model_image", "fit_without_neighbours", "with_found", "without_lost", "merged",
           "refit_pulled", "PULLED"]

#: How far (pixels) a star's refit without the cosmic rays found on it must move for its
#: first fit to have been pulled aside by them (`refit_pulled`).
PULLED = 0.3


#: A first fit farther than this from its start (pixels) ran off: its refit starts again.
REFIT_MOVE = 10.0


def _refit_init(init, result):
    """Initial table of the model-weighted refit: the first fit where it is finite, of
    positive flux and within `REFIT_MOVE` of its start, else the start (a fit on a satellite
    trail went to a flux of -6e7 and ran off to x = 3.8e8 in its refits, a row of NaN; a fit
    on a cosmic-ray track, of positive flux, to x = -1096; holding every refit within 5 px of
    its start instead cost a third more time on the trail, its pieces sliding along it)."""
    refit = Table(init, copy=True)
    fitted, start = {}, {}
    for column in ("x", "y", "flux"):
        fitted[column] = np.asarray(result[f"{column}_fit"], dtype=float)
        start[column] = np.asarray(refit[f"{column}_init"] if f"{column}_init" in refit.colnames
                                   else result[f"{column}_init"], dtype=float)
    with np.errstate(invalid="ignore"):
        kept = (np.all(np.isfinite([fitted["x"], fitted["y"], fitted["flux"]]), axis=0)
                & (fitted["flux"] > 0)
                & (np.hypot(fitted["x"] - start["x"], fitted["y"] - start["y"]) <= REFIT_MOVE))
    for column in ("x", "y", "flux"):
        refit[f"{column}_init"] = np.where(kept, fitted[column], start[column])
    return refit


def model_image(photometry, table, shape, rows=None):
    """Image of the models of the stars of a result table (all, or ``rows``) with finite
    fitted parameters, e- (`photutils.datasets.make_model_image`, as photutils'
    ``make_model_image``)."""
    from photutils.datasets import make_model_image

    model = photometry.psf_model
    names = ("x_fit", "y_fit", "flux_fit")
    values = [np.asarray(table[name], dtype=float) for name in names]
    keep = np.all(np.isfinite(values), axis=0)
    if rows is not None:
        keep &= rows
    if not keep.any():
        return np.zeros(shape)
    params = Table({name: value[keep] for name, value in zip(("x_0", "y_0", "flux"), values)})
    return make_model_image(shape, model, params, x_name="x_0", y_name="y_0")


def _reach(photometry, psf):
    """How far a star's model reaches into another's fit box: the support's half-width and
    the box's half-width, pixels."""
    box = float(np.max(np.atleast_1d(photometry.fit_shape)))
    support = getattr(psf, "half_size", None)
    support = box / 2 if support is None else support + 0.5
    return box / 2 + support + 1.0


def fit_without_neighbours(photometry, psf, data, mask, error, init, previous, rows=None):
    """photutils' fit of the stars ``rows`` of ``init`` (default all), each group on the data
    minus the models of every other star from ``previous`` (a result table of the same stars).

    photutils fits each group within its fit boxes and leaves a neighbour outside the group
    in the pixels: in a dense field a bright neighbour's wings in a faint star's fit box. Here
    every other star's model is subtracted first. Groups no model of one of which reaches the
    fit boxes of another are fitted in one photutils call (a greedy colouring of the groups);
    the others in further calls, each on its own neighbour-subtracted image.
    """
    n_stars = len(previous)
    rows = np.ones(n_stars, dtype=bool) if rows is None else np.asarray(rows, dtype=bool)
    start = _refit_init(init, previous)
    start["id"] = np.asarray(previous["id"], dtype=int)
    xy = np.column_stack([np.asarray(start["x_init"], float), np.asarray(start["y_init"], float)])
    groups = np.unique(np.asarray(previous["group_id"]), return_inverse=True)[1].ravel()
    reach = _reach(photometry, psf)
    chosen = np.flatnonzero(rows)
    pairs = cKDTree(xy[chosen]).query_pairs(reach, output_type="ndarray")
    n_groups = int(groups.max()) + 1
    conflicts = [set() for _ in range(n_groups)]
    for first, second in groups[chosen][pairs] if len(pairs) else ():
        if first != second:
            conflicts[first].add(second)
            conflicts[second].add(first)
    colour = np.full(n_groups, -1)
    for group in np.unique(groups[chosen]):
        taken = {colour[other] for other in conflicts[group]}
        colour[group] = next(value for value in range(n_groups + 1) if value not in taken)
    others = model_image(photometry, previous, data.shape)
    fits, offset = [], 0
    for value in range(int(colour.max()) + 1):
        mine = rows & (colour[groups] == value)
        if not mine.any():
            continue
        image = data - others + model_image(photometry, previous, data.shape, mine)
        fit = photometry(image, mask=mask, error=error, init_params=start[mine])
        fit["group_id"] = np.asarray(fit["group_id"]) + offset
        offset = int(np.max(fit["group_id"]))
        fits.append(fit)
    result = vstack(fits, metadata_conflicts="silent")
    result.sort("id")
    return result


def _fitted_xy(result):
    """The fitted positions (N, 2), a failed fit's far off the image (for nearest-star
    queries)."""
    xy = np.column_stack([np.asarray(result["x_fit"], float), np.asarray(result["y_fit"], float)])
    return np.where(np.isfinite(xy), xy, -1e9)


def with_found(result, found, photometry, psf):
    """The fitted stars of ``result`` and the sources ``found`` in its residual as the previous
    fit of `fit_without_neighbours` (``id``, ``group_id``, ``x_fit``, ``y_fit``,
    ``flux_fit``), and the rows to refit: the groups of every star whose fit box the found
    sources' models reach. A found source joins the group of the nearest star within the
    group separation, else a group of its own; fitted with every other star subtracted, groups
    do not merge (refitted by photutils' grouping, a crowded field's 210 stars and 88 found
    made groups whose joint fits took ten times as long)."""
    previous = Table({name: np.asarray(result[name]) for name in
                      ("id", "group_id", "x_fit", "y_fit", "flux_fit")})
    groups = np.asarray(result["group_id"], dtype=int)
    tree = cKDTree(_fitted_xy(result))
    new_xy = np.column_stack([found["x_init"], found["y_init"]])
    distance, nearest = tree.query(new_xy)
    separation = getattr(photometry.grouper, "min_separation", 0.0)
    new_groups = np.where(distance <= separation, groups[nearest],
                          groups.max() + 1 + np.arange(len(found)))
    previous = vstack([previous, Table({
        "id": len(result) + 1 + np.arange(len(found)), "group_id": new_groups,
        "x_fit": found["x_init"], "y_fit": found["y_init"], "flux_fit": found["flux_init"]})])
    reached = np.zeros(len(previous), dtype=bool)
    reached[len(result):] = True
    for near in tree.query_ball_point(new_xy, _reach(photometry, psf)):
        reached[np.asarray(near, dtype=int)] = True
    return previous, np.isin(previous["group_id"], previous["group_id"][reached])


def without_lost(init, source_flags, rows, result, threshold):
    """``init``, ``source_flags``, ``rows`` and ``result`` (row for row, ``result`` renumbered)
    without the sources found in a residual (``IN_RESIDUAL``) whose fit failed (`FAILED_FIT`
    flags: photutils' warning for them is not passed on), gave a flux
    under ``threshold`` times its error (photometry: detection's threshold + 3, its rule for
    companions; a bright core's misfit, 200-3000 e- 3-7 px from stars of 1e5-1e6 e-, the
    truncated wings of sky-free spots tiled side by side) or ended within
    `COMPANION_SEPARATION` of another star (the same star twice), and how many."""
    flux, error = (np.asarray(result[name], dtype=float) for name in ("flux_fit", "flux_err"))
    xy = _fitted_xy(result)
    nearest = cKDTree(xy).query(xy, k=2)[0][:, 1] if len(xy) > 1 else np.full(len(xy), np.inf)
    failed = (np.asarray(result["flags"], dtype=int) & FAILED_FIT) > 0
    lost = ~(np.isfinite(flux) & (flux > threshold * error) & (nearest > COMPANION_SEPARATION)
             & ~failed)
    kept = ~(lost & ((source_flags & SourceFlag.IN_RESIDUAL) > 0))
    result = result[kept]
    result["id"] = np.arange(1, len(result) + 1)
    return (init[kept], source_flags[kept], None if rows is None else rows[kept], result,
            int(np.sum(~kept)))


def merged(result, refit, rows):
    """``result`` with the stars ``rows`` (all when None) replaced by their ``refit``."""
    if rows is None:
        return refit
    refit["group_id"] = np.asarray(refit["group_id"]) + int(np.max(result["group_id"]))
    merged = vstack([result[~rows[:len(result)]], refit], metadata_conflicts="silent")
    merged.sort("id")
    return merged


def refit_pulled(photometry, psf, data, mask, error, init, result, rays, box):
    """The stars whose fit box (half diagonal ``box``) the cosmic rays ``rays`` touch,
    refitted without them; those the refit moves by more than `PULLED` take it, and the
    rays' pixels about them join ``mask`` for the fits that follow: (result, mask, how many
    took it). A hit brighter than a faint star's peak pulls its fit aside and leaves the
    star in the residual (a new user's stars of 8e3-4e4 e- hit 2-3 px from their centres
    came out as two rows each); a wrong PSF's core misfits, read as rays, move no star, and
    their refits had left lumps on the wings that were taken for stars."""
    hit = near_lines(rays, result["x_fit"], result["y_fit"], box)
    if not hit.any():
        return result, mask, 0
    refit = fit_without_neighbours(photometry, psf, data, rays if mask is None else mask | rays,
                                   error, init, result, hit)
    index = np.searchsorted(np.asarray(result["id"]), np.asarray(refit["id"]))
    moved = np.hypot(np.asarray(refit["x_fit"]) - np.asarray(result["x_fit"])[index],
                     np.asarray(refit["y_fit"]) - np.asarray(result["y_fit"])[index]) > PULLED
    if not moved.any():
        return result, mask, 0
    rows, columns = np.indices(data.shape)
    near = np.zeros(data.shape, dtype=bool)
    for x, y in zip(np.asarray(refit["x_fit"])[moved], np.asarray(refit["y_fit"])[moved]):
        near |= (columns - x) ** 2 + (rows - y) ** 2 <= box ** 2
    pulled = np.isin(np.asarray(result["id"]), np.asarray(refit["id"])[moved])
    mask = rays & near if mask is None else mask | (rays & near)
    return merged(result, refit[moved], pulled), mask, int(moved.sum())
