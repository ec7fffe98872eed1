"""Input files of the commands: FITS images (outputs: `bfpsf.outputs`)."""

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

    Adds ``amplifier`` (name) and ``amp_boundary`` (True when the star lies within ``margin``
    pixels of a side shared with another amplifier, so its light falls on two amplifiers
    read with different gains) and moves ``x``, ``y`` to detector pixels (DETSEC offset).
    """
    from ..io.amplifiers import detector_offset, near_shared_side

    xs, ys = np.asarray(table[x], dtype=float), np.asarray(table[y], dtype=float)
    table["amplifier"] = np.full(len(table), amplifier.name, dtype=f"U{max(len(amplifier.name), 1)}")
    table["amp_boundary"] = near_shared_side(xs, ys, amplifier.data.shape,
                                             sides.get(amplifier.name, set()), margin)
    x0, y0 = detector_offset(amplifier.layout)
    table[x] = xs + x0
    table[y] = ys + y0
    return table
