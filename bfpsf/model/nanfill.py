"""Harmonic (Laplace) filling of pixels from their neighbours.

`bfpsf.model.redistribution.redistribute` with ``nan_policy='interpolate'`` fills the
non-finite pixels with this (so that charge can be moved through them), redistributes the
filled image and sets them back to NaN; the measurements fill cosmic rays with it
(`bfpsf.measure.cosmic_rays`).
"""

import numpy as np
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg

from ..errors import BFPSFInputError

__all__ = ["harmonic_fill"]


def harmonic_fill(image, bad, *, isolated="raise"):
    """Replace ``image[bad]`` by the solution of Laplace's equation with the finite pixels as
    boundary values: each filled pixel is the mean of its neighbours in the image that are
    finite or filled (a non-finite pixel outside ``bad`` is left as it is and is no
    boundary).

    Parameters
    ----------
    image : ndarray [y, x]
    bad : ndarray of bool [y, x]
        The pixels to fill.
    isolated : {'raise', 'nan'}, optional
        A group of ``bad`` pixels without a finite neighbour: `BFPSFInputError`, or NaN.

    Returns
    -------
    ndarray [y, x]
        A copy of ``image``, filled.
    """
    image = np.asarray(image, dtype=float)
    bad = np.asarray(bad, dtype=bool)
    if not bad.any():
        return image.copy()
    ny, nx = image.shape
    ys, xs = np.nonzero(bad)
    index = -np.ones(image.shape, dtype=np.int64)
    index[ys, xs] = np.arange(ys.size)
    rows, cols, vals = [], [], []
    rhs = np.zeros(ys.size)
    degree = np.zeros(ys.size)
    for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        ny_, nx_ = ys + dy, xs + dx
        inside = (ny_ >= 0) & (ny_ < ny) & (nx_ >= 0) & (nx_ < nx)
        inside[inside] = (bad[ny_[inside], nx_[inside]]
                          | np.isfinite(image[ny_[inside], nx_[inside]]))
        degree += inside
        k = np.nonzero(inside)[0]
        neighbour_bad = bad[ny_[k], nx_[k]]
        kb = k[neighbour_bad]
        rows.append(kb)
        cols.append(index[ny_[kb], nx_[kb]])
        vals.append(-np.ones(kb.size))
        kg = k[~neighbour_bad]
        np.add.at(rhs, kg, image[ny_[kg], nx_[kg]])
    rows.append(np.arange(ys.size))
    cols.append(np.arange(ys.size))
    vals.append(degree)
    matrix = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(ys.size, ys.size))
    # A group of bad pixels with no finite neighbour would make the system singular.
    good_neighbours = degree.copy()
    for bad_rows in rows[:-1]:
        np.subtract.at(good_neighbours, bad_rows, 1.0)
    labels, count = scipy.ndimage.label(bad)
    per_group = scipy.ndimage.sum_labels(good_neighbours, labels[ys, xs],
                                         index=np.arange(1, count + 1))
    alone = per_group == 0
    if alone.any() and isolated == "raise":
        msg = (f"cannot interpolate: {int(alone.sum())} group(s) of non-finite pixels have no "
               f"finite neighbour ({ys.size} non-finite pixels of {image.size})")
        raise BFPSFInputError(msg, int(alone.sum()))
    # a group alone is NaN (its system is singular: solved as x = 0 apart from the others)
    lost = alone[labels[ys, xs] - 1]
    if lost.any():
        keep = scipy.sparse.diags((~lost).astype(float))
        matrix = keep @ matrix + scipy.sparse.diags(lost.astype(float))
        rhs[lost] = 0.0
    filled = image.copy()
    filled[ys, xs] = np.where(lost, np.nan, scipy.sparse.linalg.spsolve(matrix.tocsc(), rhs))
    return filled
