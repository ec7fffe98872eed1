"""Flat-field ingest and pairing by exposure time (G15 section 4.2).

Flats enter the calibration as pairs of equal exposure time: the difference of the two images
removes the fixed pattern (pixel response, illumination), leaving the shot noise whose
covariances measure the brighter-fatter effect (G15 section 4.2.1). The pixels that would add
spurious correlations are masked by `bfpsf.calibration.flat_mask.pair_mask`.

Images are ``data[y, x]`` in ADU, bias-subtracted (DESIGN.md conventions).
"""

import os
from dataclasses import dataclass, replace

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from ..io.amplifiers import amplifier_layout, read_amplifier

__all__ = ["Flat", "FlatPair", "read_flats", "group_amplifiers", "pair_flats", "check_pair"]


@dataclass(frozen=True, eq=False)
class Flat:
    """One flat-field image (one amplifier of one exposure).

    Attributes
    ----------
    data : ndarray, shape (ny, nx), or None
        Pixel values in ADU, bias- (overscan-) subtracted and trimmed, indexed ``[y, x]``
        (float64); None for a flat not read yet (``layout`` says where it is; `load`).
    exptime : float
        Exposure time in seconds (header EXPTIME).
    name : str
        Where the image came from (file name, ``file[AMP]`` for an amplifier of a
        multi-extension file, or ``'array[i]'``); used in error messages.
    header : dict-like or None
        The FITS header of the image HDU, or None for an array input or a flat not read yet.
    amplifier : str
        Amplifier name (EXTNAME), ``''`` for a single-image file or an array.
    layout : bfpsf.io.amplifiers.AmplifierLayout or None
        Where the pixels are in their file (None for an array input).
    """

    data: np.ndarray
    exptime: float
    name: str
    header: object = None
    amplifier: str = ""
    layout: object = None

    @property
    def shape(self):
        """Image shape (ny, nx)."""
        return self.data.shape if self.data is not None else tuple(self.layout.shape)

    def mean(self):
        """Mean of the finite pixels, ADU."""
        return float(np.mean(self.data[np.isfinite(self.data)])) if self.data.size else np.nan

    def load(self, *, overscan="median"):
        """This flat with its pixels read (itself if they are already in memory)."""
        if self.data is not None:
            return self

        amplifier = read_amplifier(self.layout, overscan=overscan)
        return replace(self, data=amplifier.data, header=amplifier.header)


@dataclass(frozen=True, eq=False)
class FlatPair:
    """Two flats of equal exposure time, the unit of the covariance measurement.

    Attributes
    ----------
    flat1, flat2 : Flat
        The two images; their difference carries the shot noise (G15 section 4.2.1).
    """

    flat1: Flat
    flat2: Flat

    @property
    def exptime(self):
        """Exposure time of the pair, seconds."""
        return self.flat1.exptime

    @property
    def names(self):
        """Names of the two flats."""
        return (self.flat1.name, self.flat2.name)


# ---------------------------------------------------------------------------------------------
# Ingest


def _as_exptime(value, name):
    try:
        exptime = float(value)
    except (TypeError, ValueError):
        msg = f"{name}: EXPTIME must be a number of seconds, got {value!r}"
        raise BFPSFInputError(msg, value) from None
    if not np.isfinite(exptime) or exptime < 0:
        msg = f"{name}: EXPTIME must be finite and >= 0 seconds, got {value!r}"
        raise BFPSFInputError(msg, value)
    return exptime


def read_flats(sources, exptimes=None, *, amps=None, lazy=False, overscan="median"):
    """Read flat-field images (every amplifier of every file) from FITS files or arrays.

    Parameters
    ----------
    sources : str, path, ndarray, Flat, or a sequence of them
        FITS files (single-HDU bias-subtracted images, or one image HDU per amplifier with
        EXTNAME and optional BIASSEC / DATASEC / DETSEC: `bfpsf.io.amplifiers`; the HDU
        header, or the primary header, must have EXPTIME), 2-D arrays in ADU (then
        ``exptimes`` is required), or `Flat` objects (passed through).
    exptimes : sequence of float, optional
        Exposure times in seconds, one per source. Required for arrays; when given for files
        it overrides the header EXPTIME.
    amps : str or sequence of str, optional
        Amplifiers (EXTNAME) to read from every file. Default: all.
    lazy : bool, optional
        Read only the headers: the flats of files come back with ``data=None`` and are read
        by `Flat.load` (as a worker of `bfpsf.parallel` does). Default False.
    overscan : {'median', 'clipped_mean'}, optional
        Row-by-row overscan estimator where a BIASSEC is given. Default ``'median'``.

    Returns
    -------
    list of Flat
        One per amplifier of each file, in file order.

    Raises
    ------
    BFPSFInputError
        A file is missing or unreadable, holds HDUs bfpsf cannot interpret
        (`bfpsf.io.amplifiers.amplifier_layout`), has no EXPTIME, an array is not 2-D, or the
        number of ``exptimes`` does not match the number of sources.
    """
    if isinstance(sources, (str, os.PathLike, np.ndarray, Flat)):
        sources = [sources]
    sources = list(sources)
    if not sources:
        msg = "no flats given"
        raise BFPSFInputError(msg)
    if exptimes is not None:
        exptimes = list(np.atleast_1d(exptimes))
        if len(exptimes) != len(sources):
            msg = f"got {len(exptimes)} exptimes for {len(sources)} flats; give one per flat"
            raise BFPSFInputError(msg, len(exptimes))
    flats = []
    for index, source in enumerate(sources):
        override = None if exptimes is None else exptimes[index]
        if isinstance(source, Flat):
            if override is not None:
                source = replace(source, exptime=_as_exptime(override, source.name))
            flats.append(source if lazy else source.load(overscan=overscan))
        elif isinstance(source, (str, os.PathLike)):
            for layout in amplifier_layout(source, amps, what="flat file"):
                exptime = override if override is not None else layout.exptime
                if exptime is None:
                    msg = (f"{layout.label}: header keyword EXPTIME is missing (exposure time "
                           "in seconds)")
                    raise BFPSFInputError(msg, layout.label)
                flat = Flat(None, _as_exptime(exptime, layout.label), layout.label,
                            amplifier=layout.name, layout=layout)
                flats.append(flat if lazy else flat.load(overscan=overscan))
        else:
            name = f"array[{index}]"
            data = np.array(source, dtype=np.float64)
            if override is None:
                msg = (f"{name}: flats given as arrays need exptimes (seconds), "
                       "e.g. read_flats(arrays, exptimes=[...])")
                raise BFPSFInputError(msg, name)
            if data.ndim != 2:
                msg = f"{name}: a flat must be a 2-D image, got shape {data.shape}"
                raise BFPSFInputError(msg, data.shape)
            flats.append(Flat(data, _as_exptime(override, name), name))
    return flats


def group_amplifiers(flats):
    """The flats of each amplifier, ``{name: [Flat, ...]}`` in order of first appearance."""
    groups = {}
    for flat in flats:
        groups.setdefault(flat.amplifier, []).append(flat)
    return groups


# ---------------------------------------------------------------------------------------------
# Pairing


def pair_flats(flats, *, mean_tolerance=0.05):
    """Pair flats by equal exposure time.

    Flats of one amplifier and one EXPTIME are paired in the order given: (1st, 2nd),
    (3rd, 4th), ... The means are compared here for flats in memory, and by `check_pair`
    once they are read for flats read lazily.

    Parameters
    ----------
    flats : sequence of Flat, or anything `read_flats` accepts
        The flats to pair.
    mean_tolerance : float, optional
        Largest accepted relative difference of the two means, ``|m1 - m2| / ((m1 + m2) / 2)``.
        A larger difference means the illumination changed between the two exposures, which
        the pair difference does not cancel. Not applied at EXPTIME = 0. Default 0.05.

    Returns
    -------
    list of FlatPair
        Sorted by exposure time.

    Raises
    ------
    BFPSFInputError
        A flat has no partner at its EXPTIME (an odd number of flats there), the two flats of
        a pair differ in shape, or their means differ by more than ``mean_tolerance``.
    """
    flats = list(flats)
    if not all(isinstance(flat, Flat) for flat in flats):
        flats = read_flats(flats)
    if mean_tolerance <= 0:
        msg = f"mean_tolerance must be positive, got {mean_tolerance}"
        raise BFPSFValueError(msg, mean_tolerance)
    pairs = []
    for amplifier_flats in group_amplifiers(flats).values():
        pairs += _pair_by_exptime(amplifier_flats, mean_tolerance)
    return sorted(pairs, key=lambda pair: pair.exptime)


def _pair_by_exptime(flats, mean_tolerance):
    groups = {}
    for flat in flats:
        for exptime in groups:
            if np.isclose(flat.exptime, exptime, rtol=1e-9, atol=1e-12):
                groups[exptime].append(flat)
                break
        else:
            groups[flat.exptime] = [flat]
    pairs = []
    for exptime in sorted(groups):
        group = groups[exptime]
        if len(group) % 2:
            others = ", ".join(flat.name for flat in group[:-1])
            msg = (f"{group[-1].name} (EXPTIME={exptime:g} s) has no partner: flats are paired "
                   "by equal EXPTIME" + (f" and {others} already pair up" if others else ""))
            raise BFPSFInputError(msg, group[-1].name)
        for first, second in zip(group[0::2], group[1::2]):
            check_pair(first, second, mean_tolerance)
            pairs.append(FlatPair(first, second))
    return pairs


def check_pair(first, second, mean_tolerance):
    """Raise `BFPSFInputError` if two flats of one EXPTIME cannot be a pair: different shapes,
    or (once their pixels are read) means that differ by more than ``mean_tolerance``."""
    if first.shape != second.shape:
        msg = (f"flats {first.name} {first.shape} and {second.name} {second.shape} have the "
               "same EXPTIME but different shapes")
        raise BFPSFInputError(msg, (first.shape, second.shape))
    if first.exptime <= 0 or first.data is None or second.data is None:
        return
    mean1, mean2 = first.mean(), second.mean()
    mean = 0.5 * (mean1 + mean2)
    if not (np.isfinite(mean1) and np.isfinite(mean2)) or mean <= 0:
        msg = (f"flats {first.name} and {second.name} have non-positive or undefined means "
               f"({mean1:.6g}, {mean2:.6g} ADU) at EXPTIME={first.exptime:g} s")
        raise BFPSFInputError(msg, (mean1, mean2))
    difference = abs(mean1 - mean2) / mean
    if difference > mean_tolerance:
        msg = (f"flats {first.name} and {second.name} (EXPTIME={first.exptime:g} s) have means "
               f"{mean1:.6g} and {mean2:.6g} ADU, differing by {100 * difference:.3g} % > "
               f"mean_tolerance={100 * mean_tolerance:.3g} %: the illumination changed")
        raise BFPSFInputError(msg, difference)
