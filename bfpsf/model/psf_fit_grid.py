"""P0 on its oversampled grid (one node or a grid of nodes over the image) for the fit of
`bfpsf.model.psf_fit.fit_psf`: the sampling of every star's pixels on the grid (the cubic
spline of `FluxDependentPSF`), the least-squares node solution of the residuals, the
normalisation of each sub-pixel phase, and the recentring of the converged P0."""

import numpy as np
import scipy.ndimage
from scipy.interpolate import make_interp_spline

from ..errors import BFPSFInputError, BFPSFValueError
from ..moments.adaptive import adaptive_moments
from ..shifts import BoundaryShifts, as_shifts
from .gridded import grid_node_positions
from .psf import FluxDependentPSF

__all__ = ["Grid", "Sampling", "cardinal_splines", "project", "dense_weights_of",
           "node_solution", "normalise", "normalise_nodes", "without_translation", "recentred",
           "fill_empty", "grid_nodes", "shift_sets_of", "mean_shifts"]


def fill_empty(stack, weight):
    """Fill nodes without samples by normalised Gaussian interpolation from their neighbours."""
    empty = weight <= 0
    if not empty.any():
        return stack
    filled = stack.copy()
    have = (~empty).astype(float)
    for sigma in (0.7, 1.5, 3.0):
        numerator = scipy.ndimage.gaussian_filter(np.where(empty, 0.0, filled), sigma)
        denominator = scipy.ndimage.gaussian_filter(have, sigma)
        ok = empty & (denominator > 1e-3)
        filled[ok] = numerator[ok] / denominator[ok]
        have = np.where(ok, 1.0, have)
        empty = empty & ~ok
    filled[empty] = 0.0
    return filled


def normalise(data, oversampling):
    """P0 normalised to unit flux in every sub-pixel phase: each of the ``oy * ox`` sublattices
    of the oversampled grid (the nodes a star at one phase samples) sums to 1.

    A star's flux and the sum of the sublattice its pixels sample are degenerate (a star at
    phase 0 sees the even nodes, one at phase 1/2 the odd ones): left free, the sublattices
    drift apart, each star's flux compensating, and P0 holds a checkerboard whose flux
    depends on the phase (0.68-1.47 in a dense field of blends, fluxes 40 % off). A
    well-sampled PSF has equal sublattice sums (its transform vanishes at the pixel
    frequency), so each is scaled to 1.
    """
    oy, ox = oversampling
    total = data.sum()
    if not total > 0:
        msg = f"the stacked PSF has non-positive total {total:.3g}; check the star list"
        raise BFPSFInputError(msg, total)
    data = data * (oy * ox / total)
    sums = np.array([[data[a::oy, b::ox].sum() for b in range(ox)] for a in range(oy)])
    if np.all(sums > 0):
        for a in range(oy):
            for b in range(ox):
                data[a::oy, b::ox] /= sums[a, b]
    return data


def normalise_nodes(data, oversampling, x_nodes, y_nodes, dense_weights):
    """`normalise` of every node; on a grid, a node that cannot be normalised is named in the
    error, with its place and the stars' weight there."""
    if len(data) == 1:
        return np.array([normalise(data[0], oversampling)])
    nodes = []
    for k, node in enumerate(data):
        try:
            nodes.append(normalise(node, oversampling))
        except BFPSFInputError as error:
            msg = (f"P0 at grid node {k + 1} of {len(data)} (x {x_nodes[k % x_nodes.size]:.0f}, "
                   f"y {y_nodes[k // x_nodes.size]:.0f}; the stars there weigh "
                   f"{dense_weights[:, k].sum():.1f}) has non-positive total "
                   f"{error.value:.3g}: too few stars there for the grid; use fewer grid "
                   "nodes or more images")
            raise BFPSFInputError(msg, error.value) from None
    return np.array(nodes)


class Sampling:
    """Where each star's pixels fall on the oversampled P0 grid, along one axis.

    ``matrix[i, j, a]`` is the not-a-knot cubic interpolating spline through the unit vector a
    of the P0 grid, evaluated at pixel j of star i: the same spline as
    `FluxDependentPSF` (scipy's ``RectBivariateSpline`` with ``s=0`` is its tensor product), so
    ``Ly @ P0 @ Lx.T`` is the model's ``evaluate`` of P0 at every pixel of every cutout.
    ``derivative`` is d/d(pixel offset); ``node`` the nearest grid node of each pixel; pixels
    beyond the data (``outside``) have zero rows, as the model is zero there.
    """

    def __init__(self, start, centre, size, oversampling, origin, cardinal):
        n_data = cardinal[0].c.shape[0]
        coords = oversampling * (start[:, None] + np.arange(size) - centre[:, None]) + origin
        self.outside = (coords < 0) | (coords > n_data - 1)
        flat = np.clip(coords, 0, n_data - 1).ravel()
        shape = coords.shape + (n_data,)
        self.matrix = cardinal[0](flat).reshape(shape)
        self.derivative = oversampling * cardinal[1](flat).reshape(shape)
        self.matrix[self.outside] = 0.0
        self.derivative[self.outside] = 0.0
        self.node = np.clip(np.rint(coords).astype(int), 0, n_data - 1)


def cardinal_splines(n_data):
    spline = make_interp_spline(np.arange(n_data), np.eye(n_data), k=3)
    return spline, spline.derivative()


def project(rows, grid, columns):
    """``rows @ grid @ columns.T`` per star: (N, n, M) @ (N or 1, M, M) @ (N, M, n)."""
    return (rows @ grid) @ np.swapaxes(columns, 1, 2)


class Grid:
    """The node P0s being fitted, their node models for each set of shifts (one per
    amplifier), and each star's interpolation weights and set of shifts."""

    def __init__(self, data, x_nodes, y_nodes, shift_sets, star_set, oversampling, psf_kwargs,
                 amplitude=1.0):
        self.data = data                    # (K, M, M)
        self.x_nodes, self.y_nodes = x_nodes, y_nodes
        self.oversampling, self.psf_kwargs = oversampling, psf_kwargs
        self.star_set = star_set            # (N,) index into shift_sets
        psf_kwargs = dict(psf_kwargs)
        # the EMPIRICAL term as given, and the amplitude the stars' pixels give it
        self.empirical, self.amplitude = psf_kwargs.pop("empirical", None), float(amplitude)
        self.set_nodes = [[FluxDependentPSF(node, shifts, oversampling=oversampling,
                                            **psf_kwargs) for node in data]
                          for shifts in shift_sets]
        scaled = None if self.empirical is None else self.empirical.scaled(self.amplitude)
        for node in (node for nodes in self.set_nodes for node in nodes):
            node.empirical = scaled  # the exact mode's evaluate applies it
        self.nodes = self.set_nodes[0]
        self.table = self.nodes[0].mode == "table"

    def per_star(self, cube, weights):
        """Each star's bilinear mix of a node cube: (1, M, M) for one node, else (N, M, M)."""
        if len(cube) == 1:
            return cube
        return (weights @ cube.reshape(len(cube), -1)).reshape((-1,) + cube.shape[1:])

    def star_tables(self, weights):
        """Each star's BF table (its amplifier's shifts, its bilinear mix of the nodes)."""
        cube = np.array([[node.bf_table for node in nodes] for nodes in self.set_nodes])
        if len(cube) == 1:
            return self.per_star(cube[0], weights)
        return np.einsum("nk,nkab->nab", weights, cube[self.star_set])


def dense_weights_of(indices, weights, n_nodes):
    dense = np.zeros((len(indices), n_nodes))
    np.add.at(dense, (np.arange(len(indices))[:, None], indices), weights)
    return dense


def node_solution(values, sample_weights, dense_weights, xs, ys, n_data):
    """Least-squares node values that best give ``values`` at every star pixel.

    In the nearest-node approximation the model of pixel j of star i is
    sum_k w_ik v_k[c_ij], with c_ij the oversampled node of the pixel and w_ik the star's
    bilinear weight of grid node k: for each oversampled node c, the grid nodes' values
    v_k[c] solve a small K x K weighted normal system (one value per c for one node: the
    weighted average). Nodes without samples are filled from their neighbours.

    Parameters
    ----------
    values, sample_weights : ndarray (N, n, n)
    dense_weights : ndarray (N, K)
        Bilinear weight of every grid node for every star.
    xs, ys : Sampling
    n_data : int
        M, the side of the oversampled grid.

    Returns
    -------
    ndarray (K, M, M)
    """
    n_stars, n_nodes = dense_weights.shape
    n_cells = n_data * n_data
    inside = ~(ys.outside[:, :, None] | xs.outside[:, None, :])
    cell = ys.node[:, :, None] * n_data + xs.node[:, None, :]
    flat = (np.arange(n_stars)[:, None, None] * n_cells + cell)[inside]
    # Per star and oversampled node: sum of weight x value, and of weight.
    weighted = np.bincount(flat, weights=(sample_weights * values)[inside],
                           minlength=n_stars * n_cells).reshape(n_stars, n_cells)
    weight = np.bincount(flat, weights=sample_weights[inside],
                         minlength=n_stars * n_cells).reshape(n_stars, n_cells)
    right = (dense_weights.T @ weighted).T                              # (M*M, K)
    pairs = (dense_weights[:, :, None] * dense_weights[:, None, :]).reshape(n_stars, -1)
    normal = (pairs.T @ weight).T.reshape(n_cells, n_nodes, n_nodes)   # (M*M, K, K)
    diagonal = np.einsum("ckk->ck", normal).copy()
    empty = diagonal <= 0
    # Unsampled grid nodes of a cell get an identity row (value 0, filled below). A ridge of
    # 1 % of the diagonal damps cells where grid nodes are seen only in nearly the same
    # mixture (few stars); it shrinks each update, not the converged P0 (update 0).
    normal[empty[:, :, None] & np.eye(n_nodes, dtype=bool)[None]] = 1.0
    if n_nodes > 1:
        normal += 1e-2 * np.einsum("ck,kl->ckl", np.where(empty, 0.0, diagonal),
                                   np.eye(n_nodes))
    solution = np.linalg.solve(normal, right[..., None])[..., 0]
    solution[empty] = 0.0
    shape = (n_nodes, n_data, n_data)
    solution, diagonal = solution.T.reshape(shape), diagonal.T.reshape(shape)
    return np.array([fill_empty(node, node_weight)
                     for node, node_weight in zip(solution, diagonal)])


def without_translation(update, data):
    """The update minus its least-squares projection on a shift of P0 (its x and y
    gradients): a shift of P0 with every star moved alike fits the data as well, so that
    direction is left to the star positions instead of letting P0 drift."""
    gradients = np.array(np.gradient(data)).reshape(2, -1)
    amplitudes = np.linalg.lstsq(gradients.T, update.ravel(), rcond=None)[0]
    return update - (amplitudes @ gradients).reshape(update.shape)


def recentred(data, oversampling):
    """P0 shifted so that its Gaussian-weighted centroid (`bfpsf.moments.adaptive_moments`,
    the centroid ``measure`` gives a star) is the origin (the centre of the grid), normalised.

    A shift of P0 with every star moved alike fits the data as well; the iteration leaves that
    direction alone (`without_translation`) and the converged P0 is recentred once, so the
    fitted star positions are centroids of the PSF (photutils' `~photutils.psf.EPSFBuilder`
    recentres its ePSF too). The centroid of every node follows a lobe at P0's edge: a new
    user's P0 of one exposure's 17 Kolmogorov x Airy stars, its fit diverged, had a node as
    high as its core 12 px out, and recentring on all nodes moved the core 2 px off the
    origin (``bfpsf diagnose``'s star residual chi2 163 per pixel over 12 exposures; 1.6
    recentred on the core). The unweighted centroid is kept where the adaptive one fails.
    """
    centre = (np.asarray(data.shape) - 1) / 2.0
    moments = adaptive_moments(data)
    if moments.flags == 0:
        offsets = [moments.y - centre[0], moments.x - centre[1]]
    else:
        weights = np.clip(data, 0.0, None)
        offsets = [(weights * np.arange(n).reshape(shape)).sum() / weights.sum() - c
                   for n, shape, c in ((data.shape[0], (-1, 1), centre[0]),
                                       (data.shape[1], (1, -1), centre[1]))]
    shifted = scipy.ndimage.shift(data, [-offset for offset in offsets], order=3,
                                  mode="constant")
    return normalise(shifted, (oversampling, oversampling))


def grid_nodes(grid, images):
    """Node coordinates (x_nodes, y_nodes) of `fit_psf`'s ``grid`` over the images (one node:
    (0, 0))."""
    if grid is None:
        return np.zeros(1), np.zeros(1)
    grid = np.asarray(grid)
    if grid.shape != (2,) or np.any(grid != np.round(grid)) or np.any(grid < 1):
        msg = f"grid must be two positive integers (nx, ny), got {grid!r}"
        raise BFPSFValueError(msg, grid)
    shapes = {image.shape for image in images}
    if len(shapes) != 1:
        msg = f"a grid needs images of one shape (it covers the image), got {sorted(shapes)}"
        raise BFPSFInputError(msg, sorted(shapes))
    ny, nx = shapes.pop()
    return grid_node_positions(int(grid[0]), nx), grid_node_positions(int(grid[1]), ny)


def shift_sets_of(shifts, n_images):
    """The distinct sets of shifts and the set of each image (`fit_psf`'s ``shifts``)."""
    if not isinstance(shifts, (list, tuple)):
        return [as_shifts(shifts)], np.zeros(n_images, dtype=int)
    if len(shifts) != n_images:
        msg = f"got {len(shifts)} sets of shifts for {n_images} images (one per image, or one)"
        raise BFPSFValueError(msg, len(shifts))
    sets, image_set = [], []
    for one in shifts:
        one = as_shifts(one)
        same = [index for index, known in enumerate(sets)
                if known.radius == one.radius and np.array_equal(known.north, one.north)
                and np.array_equal(known.east, one.east)]
        if not same:
            same = [len(sets)]
            sets.append(one)
        image_set.append(same[0])
    return sets, np.array(image_set, dtype=int)


def mean_shifts(shift_sets, star_set):
    """Mean of the shift sets weighted by their stars (every set alike when none)."""
    counts = np.bincount(star_set, minlength=len(shift_sets)).astype(float)
    weights = counts / counts.sum() if counts.sum() else np.full(len(shift_sets),
                                                                 1.0 / len(shift_sets))
    radius = max(one.radius for one in shift_sets)
    padded = [one.padded(radius) for one in shift_sets]
    return BoundaryShifts(sum(w * one.north for w, one in zip(weights, padded)),
                          sum(w * one.east for w, one in zip(weights, padded)), check=False)
