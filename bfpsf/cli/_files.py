"""Files of the commands: FITS images in, outputs never overwritten without ``--overwrite``,
JSON summaries."""

import json
import math
from pathlib import Path

import numpy as np

from ..errors import BFPSFInputError
from ..files import refuse_overwrite


def check_free(path, overwrite):
    """Raise `BFPSFFileExistsError` if ``path`` exists and ``overwrite`` is false.

    Called for every output before any work is done, so a refused run writes nothing.
    ``path=None`` (an output not requested) is accepted.
    """
    if path is not None:
        refuse_overwrite(path, overwrite, how="--overwrite")


def _strict(value):
    """Plain JSON types; NaN and infinities (not JSON) become null."""
    if isinstance(value, dict):
        return {str(key): _strict(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(item) for item in value]
    if isinstance(value, np.ndarray):
        return _strict(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path, summary):
    """Write a command's machine-readable summary as strict JSON (NaN written as null)."""
    with open(path, "w") as stream:
        json.dump(_strict(summary), stream, indent=1, allow_nan=False)
        stream.write("\n")


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

    if not Path(path).exists():
        msg = f"image {path} does not exist"
        raise BFPSFInputError(msg, str(path))
    amplifiers = read_amplifiers(path, amps)
    catalog = None
    with fits.open(path) as hdus:
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
