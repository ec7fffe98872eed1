"""Input files of the commands: FITS images (outputs: `bfpsf.outputs`)."""

import sys

import numpy as np

from ..files import reading


def read_image(path, amps=None):
    """The amplifiers of an image file and its CATALOG table (every command reads images so).

    Single-HDU files give one amplifier (named ``''``); multi-extension files one per image
    HDU, overscan-subtracted and trimmed (`bfpsf.io.amplifiers.read_amplifiers`, which names
    the file and HDU of anything it cannot interpret).

    Returns
    -------
    amplifiers : list of bfpsf.io.amplifiers.Amplifier
        ``.data`` [y, x] in ADU, ``.header``, ``.name``, ``.layout`` (DETSEC).
    catalog : astropy.table.Table or None
        The ``CATALOG`` extension when present (e.g. colours of simulated stars).
    """
    from astropy.io import fits

    from ..io.amplifiers import read_amplifiers

    amplifiers = read_amplifiers(path, amps, what="image")
    catalog = None
    with reading(path, "FITS image"), fits.open(path, memmap=False) as hdus:
        if "CATALOG" in hdus:
            from astropy.table import Table

            catalog = Table.read(hdus["CATALOG"])
    return amplifiers, catalog


def place_stars(table, amplifier, sides, margin, *, x="x", y="y"):
    """Stars measured on one amplifier, placed on the detector.

    Adds ``amplifier`` (name), ``amp_boundary`` (True when the star lies within ``margin``
    pixels of a side shared with another amplifier, so its light falls on two amplifiers
    read with different gains) and ``amp_depth`` (`shared_side_depth`: how far inside its
    amplifier, from the nearest shared side, pixels) and moves ``x``, ``y`` to detector
    pixels (DETSEC offset).
    """
    from ..io.amplifiers import detector_offset, near_shared_side, shared_side_depth

    xs, ys = np.asarray(table[x], dtype=float), np.asarray(table[y], dtype=float)
    table["amplifier"] = np.full(len(table), amplifier.name, dtype=f"U{max(len(amplifier.name), 1)}")
    table["amp_boundary"] = near_shared_side(xs, ys, amplifier.data.shape,
                                             sides.get(amplifier.name, set()), margin)
    table["amp_depth"] = shared_side_depth(xs, ys, amplifier.data.shape,
                                           sides.get(amplifier.name, set()))
    x0, y0 = detector_offset(amplifier.layout)
    table[x] = xs + x0
    table[y] = ys + y0
    return table


def one_fit_per_star(table, radius, *, x="x", y="y"):
    """The table without the second fit of a star near a shared side: fitted on both
    amplifiers (each sees its light), the fit from the amplifier that holds the star's centre
    (the larger ``amp_depth``) is kept. Returns (table, number left out). A new user's
    boundary stars came out twice, the copy from the other amplifier off by -45 mmag (rms
    242)."""
    if "amp_depth" not in table.colnames or len(table) < 2:
        return table, 0
    # the pairs of boundary rows of one image, from two amplifiers, within ``radius``
    rows = np.flatnonzero(np.asarray(table["amp_boundary"], dtype=bool))
    images = (np.asarray(table["image"])[rows] if "image" in table.colnames
              else np.zeros(rows.size, dtype=int))
    amplifiers = np.asarray(table["amplifier"])[rows]
    xs, ys = (np.asarray(table[name], dtype=float)[rows] for name in (x, y))
    depth = np.asarray(table["amp_depth"], dtype=float)[rows]
    first, second = np.nonzero(np.triu((np.hypot(xs[:, None] - xs, ys[:, None] - ys) < radius)
                                       & (images[:, None] == images)
                                       & (amplifiers[:, None] != amplifiers), k=1))
    # of each pair, the fit from the shallower side is left out
    drop = np.unique(rows[np.where(depth[first] >= depth[second], second, first)])
    keep = np.ones(len(table), dtype=bool)
    keep[drop] = False
    return table[keep], int(drop.size)


def warn_unconverged(psf, path):
    """Say when the PSF product's P0 fit did not converge (``psf.p0_converged``, its CONVERGD
    card, `bfpsf psf`): a new user's P0 of 7 stars, "NOT converged", was then used by
    photometry without a word (-16.6 mmag, scatter 38 mmag). `photometry` and `slope --psf`
    call it."""
    if psf.p0_converged is False:
        print(f"WARNING: {path}: its P0 fit did not converge (bfpsf psf said so): what is "
              "measured with it may be biased; refit it from more stars", file=sys.stderr)
