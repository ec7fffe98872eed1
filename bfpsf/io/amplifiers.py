"""Camera input: the amplifiers of a FITS file, overscan-subtracted and trimmed.

One reader for every command. A file is either

* a single image HDU (primary or one extension): an already bias-subtracted image, read as
  it is (the amplifier is named by its EXTNAME, or ``''``); or
* a multi-extension file with one image HDU per amplifier, each named by EXTNAME.

Each amplifier HDU may carry IRAF-style sections, 1-based and inclusive, ``[x1:x2,y1:y2]``
(as DECam, HSC and lab test stands write them):

* ``DATASEC``: the imaging pixels of the HDU; the amplifier is trimmed to it;
* ``BIASSEC``: the serial overscan; where present its level is measured row by row (median of
  the overscan columns of each row, or the sigma-clipped mean) and subtracted from the row
  before trimming (requires DATASEC);
* ``DETSEC``: where the trimmed pixels sit on the detector, so that a star can be assigned to
  the amplifier it falls on. A reversed range (x1 > x2, or y1 > y2) says the amplifier is read
  out in the other direction: its trimmed pixels are flipped into detector orientation (as
  IRAF and LSST assembly do; the section keeps ``flip_x`` / ``flip_y``), so every amplifier's
  pixels, positions and sides are in detector orientation.

Boundary shifts under a flip: a^X(dx, dy) is measured in readout orientation. Flipping x swaps
the E and W boundaries and dx -> -dx; the G15 shifts are mirror-symmetric (a^N even in dx,
a^W(dx, dy) = -a^E(-dx, dy), which `BoundaryShifts.west` builds), so the redistribution of the
flipped image with the same shift arrays is the flip of the redistribution: the arrays are used
unchanged (likewise for y, N and S). Tested in ``tests/test_amplifiers.py``.

Header-only HDUs (an empty primary) and a ``CATALOG`` table (colours of simulated stars) are
allowed; anything else the package cannot interpret (a cube, another table, several images
without EXTNAME, two amplifiers of one name) is a `BFPSFInputError` naming the file and HDU.
"""

import re
from dataclasses import dataclass

import numpy as np
from astropy.io import fits

from ..errors import BFPSFInputError
from ..files import check_input, reading
from .saturation import SATURATION_KEYWORDS

__all__ = ["Amplifier", "AmplifierLayout", "parse_section", "amplifier_layout",
           "read_amplifiers", "read_amplifier", "subtract_overscan", "shared_sides",
           "near_shared_side", "detector_offset", "OVERSCAN_METHODS"]

#: Row-by-row estimators of the overscan level.
OVERSCAN_METHODS = ("median", "clipped_mean")

#: Table extensions that belong to the image format (read by `bfpsf.cli._files`).
ALLOWED_TABLES = ("CATALOG",)

_SECTION = re.compile(r"^\s*\[\s*(\d+)\s*:\s*(\d+)\s*,\s*(\d+)\s*:\s*(\d+)\s*\]\s*$")


@dataclass(frozen=True)
class Section:
    """A 1-based inclusive IRAF section as 0-based half-open slices.

    Attributes
    ----------
    x, y : slice
        Columns and rows, 0-based, half-open, ascending.
    flip_x, flip_y : bool
        True when the section was written with x1 > x2 (or y1 > y2).
    """

    x: slice
    y: slice
    flip_x: bool = False
    flip_y: bool = False

    @property
    def shape(self):
        """(ny, nx) of the section."""
        return (self.y.stop - self.y.start, self.x.stop - self.x.start)


def parse_section(text, *, keyword="section", where=""):
    """Parse an IRAF section ``[x1:x2,y1:y2]`` (1-based, inclusive) into a `Section`.

    Parameters
    ----------
    text : str
        The keyword value, e.g. ``'[1:512,1:2048]'``.
    keyword : str, optional
        Name of the keyword, for the message.
    where : str, optional
        File and HDU, for the message.

    Raises
    ------
    BFPSFInputError
        The text is not of the form ``[x1:x2,y1:y2]`` with positive integers.
    """
    match = _SECTION.match(str(text))
    if match is None:
        msg = f"{where}: {keyword} = {text!r} is not an IRAF section [x1:x2,y1:y2]"
        raise BFPSFInputError(msg, text)
    x1, x2, y1, y2 = (int(value) for value in match.groups())
    if min(x1, x2, y1, y2) < 1:
        msg = f"{where}: {keyword} = {text!r}: IRAF sections are 1-based"
        raise BFPSFInputError(msg, text)
    return Section(x=slice(min(x1, x2) - 1, max(x1, x2)), y=slice(min(y1, y2) - 1, max(y1, y2)),
                   flip_x=x1 > x2, flip_y=y1 > y2)


@dataclass(frozen=True)
class AmplifierLayout:
    """Where an amplifier is in its file, read from the headers alone (no pixels).

    Attributes
    ----------
    path : str
    hdu : int
        Index of the HDU in the file.
    name : str
        EXTNAME ('' for a lone unnamed image).
    shape : (int, int)
        Shape after trimming, (ny, nx).
    exptime : object
        Header EXPTIME of the HDU, else of the primary header; None if neither has one.
    datasec, biassec, detsec : Section or None
    """

    path: str
    hdu: int
    name: str
    shape: tuple
    exptime: object
    datasec: Section = None
    biassec: Section = None
    detsec: Section = None

    @property
    def label(self):
        """``path[NAME]`` (or ``path[HDU n]``), for messages and flat names."""
        return f"{self.path}[{self.name or f'HDU {self.hdu}'}]" if self.name else self.path


@dataclass(frozen=True, eq=False)
class Amplifier:
    """The pixels of one amplifier, overscan-subtracted and trimmed.

    Attributes
    ----------
    layout : AmplifierLayout
    data : ndarray [y, x]
        ADU (float64), overscan-subtracted where the HDU has a BIASSEC.
    header : astropy.io.fits.Header
        The HDU header (EXPTIME and the saturation level copied from the primary header when
        only that has them).
    overscan_adu : ndarray or None
        The level subtracted from each row of the trimmed image, ADU.
    """

    layout: AmplifierLayout
    data: np.ndarray
    header: object
    overscan_adu: np.ndarray = None

    @property
    def name(self):
        return self.layout.name

    @property
    def label(self):
        return self.layout.label


def _hdu_name(index, hdu):
    return f"HDU {index} ({hdu.name})" if hdu.name and hdu.name != "PRIMARY" else f"HDU {index}"


def _image_hdus(path, hdus):
    """(index, hdu) of the amplifier images; raises on HDUs the package cannot interpret."""
    images = []
    for key, what in (("BFPSFVER", "PSF product (bfpsf psf)"),
                      ("BFSCHEMA", "calibration (bfpsf calibrate)")):
        if key in hdus[0].header:  # a product of bfpsf given as an image
            msg = f"{path} is a bfpsf {what}, not an image"
            raise BFPSFInputError(msg, str(path))
    for index, hdu in enumerate(hdus):
        if not hdu.is_image:
            if hdu.name in ALLOWED_TABLES:
                continue
            msg = (f"{path}: {_hdu_name(index, hdu)} is a table, not an amplifier image "
                   f"(bfpsf reads image HDUs and a {' or '.join(ALLOWED_TABLES)} table)")
            raise BFPSFInputError(msg, str(path))
        if hdu.header.get("NAXIS", 0) == 0:
            continue  # header only (e.g. the primary of a multi-extension file)
        shape = tuple(hdu.header[f"NAXIS{axis}"] for axis in range(hdu.header["NAXIS"], 0, -1))
        if len(shape) != 2:
            msg = (f"{path}: {_hdu_name(index, hdu)} is a {len(shape)}-D array of shape {shape}, "
                   "not a 2-D amplifier image")
            raise BFPSFInputError(msg, shape)
        images.append((index, hdu))
    if not images:
        msg = f"{path}: no 2-D image HDU"
        raise BFPSFInputError(msg, str(path))
    if len(images) > 1:
        seen = {}
        for index, hdu in images:
            name = str(hdu.header.get("EXTNAME", "")).strip()
            if not name:
                msg = (f"{path}: HDU {index} has no EXTNAME; a file with several images needs "
                       "one EXTNAME per amplifier")
                raise BFPSFInputError(msg, index)
            if name in seen:
                msg = f"{path}: HDUs {seen[name]} and {index} are both named {name!r}"
                raise BFPSFInputError(msg, name)
            seen[name] = index
    return images


def _layout(path, index, hdu, primary_header):
    header = hdu.header
    name = str(header.get("EXTNAME", "")).strip() if index > 0 else ""
    where = f"{path}: {_hdu_name(index, hdu)}"
    full = (header["NAXIS2"], header["NAXIS1"])
    sections = {}
    for keyword in ("DATASEC", "BIASSEC", "DETSEC"):
        if keyword in header:
            section = parse_section(header[keyword], keyword=keyword, where=where)
            if keyword != "DETSEC" and (section.y.stop > full[0] or section.x.stop > full[1]):
                msg = f"{where}: {keyword} {header[keyword]} lies outside the {full} image"
                raise BFPSFInputError(msg, header[keyword])
            sections[keyword] = section
    datasec, biassec = sections.get("DATASEC"), sections.get("BIASSEC")
    if biassec is not None:
        if datasec is None:
            msg = f"{where}: BIASSEC without DATASEC; bfpsf cannot tell the pixels from the overscan"
            raise BFPSFInputError(msg, str(path))
        if _overlap(biassec, datasec):
            msg = (f"{where}: BIASSEC {header['BIASSEC']} overlaps DATASEC {header['DATASEC']} "
                   "(the overscan must lie outside the imaging pixels)")
            raise BFPSFInputError(msg, header["BIASSEC"])
        if biassec.y.start > datasec.y.start or biassec.y.stop < datasec.y.stop:
            msg = (f"{where}: BIASSEC {header['BIASSEC']} does not cover the rows of DATASEC "
                   f"{header['DATASEC']} (the overscan is subtracted row by row)")
            raise BFPSFInputError(msg, header["BIASSEC"])
    shape = datasec.shape if datasec is not None else full
    detsec = sections.get("DETSEC")
    if detsec is not None and detsec.shape != shape:
        msg = f"{where}: DETSEC {header['DETSEC']} is {detsec.shape}, the data {shape}"
        raise BFPSFInputError(msg, header["DETSEC"])
    exptime = header.get("EXPTIME", primary_header.get("EXPTIME"))
    return AmplifierLayout(path=str(path), hdu=index, name=name, shape=tuple(shape),
                           exptime=exptime, datasec=datasec, biassec=biassec, detsec=detsec)


def _overlap(first, second):
    """True when two sections share a pixel."""
    return (first.x.start < second.x.stop and second.x.start < first.x.stop
            and first.y.start < second.y.stop and second.y.start < first.y.stop)


def _refuse_overlapping_amplifiers(path, layouts):
    """Two amplifiers whose DETSECs share detector pixels cannot both be right."""
    placed = [layout for layout in layouts if layout.detsec is not None]
    for index, layout in enumerate(placed):
        for other in placed[index + 1:]:
            if _overlap(layout.detsec, other.detsec):
                msg = (f"{path}: the DETSECs of amplifiers {layout.name!r} and {other.name!r} "
                       "overlap on the detector")
                raise BFPSFInputError(msg, (layout.name, other.name))


def _select(path, layouts, amps):
    if amps is None:
        return layouts
    amps = [amps] if isinstance(amps, str) else list(amps)
    repeated = sorted({name for name in amps if amps.count(name) > 1})
    if repeated:  # its stars or pairs would be counted twice
        msg = f"{path}: amplifier {', '.join(map(repr, repeated))} selected more than once (--amp)"
        raise BFPSFInputError(msg, repeated)
    by_name = {layout.name: layout for layout in layouts}
    missing = [name for name in amps if name not in by_name]
    if missing:
        msg = (f"{path}: no amplifier {', '.join(map(repr, missing))}; it has "
               f"{', '.join(repr(name) for name in by_name)}")
        raise BFPSFInputError(msg, missing)
    return [by_name[name] for name in amps]


def amplifier_layout(path, amps=None, *, what="FITS file"):
    """The amplifiers of a FITS file, from the headers alone.

    Parameters
    ----------
    path : str or path-like
    amps : str or sequence of str, optional
        Amplifier names (EXTNAME) to keep, in that order. Default: all.
    what : str, optional
        What the file is, in error messages (``'flat file'``, ``'image'``).

    Returns
    -------
    list of AmplifierLayout

    Raises
    ------
    BFPSFInputError
        Missing or unreadable file, a cube, a table HDU other than CATALOG, several images not
        all named, a duplicate EXTNAME, a bad section, or an unknown amplifier in ``amps``.
    """
    check_input(path, what)
    with reading(path, _readable(what)), fits.open(path, memmap=False,
                                                  lazy_load_hdus=True) as hdus:
        images = _image_hdus(path, hdus)
        primary = hdus[0].header
        layouts = [_layout(path, index, hdu, primary) for index, hdu in images]
    _refuse_overlapping_amplifiers(path, layouts)
    return _select(path, layouts, amps)


def _readable(what):
    """The file kind in `bfpsf.files.reading` messages: 'flat file' -> 'flat FITS file',
    'image' -> 'FITS image'."""
    return {"flat file": "flat FITS file", "image": "FITS image"}.get(what, what)


def subtract_overscan(data, datasec, biassec, *, method="median", clip_nsigma=3.0):
    """Subtract the serial overscan row by row and trim to the data section.

    Parameters
    ----------
    data : ndarray [y, x]
        The raw HDU, ADU.
    datasec, biassec : Section
    method : {'median', 'clipped_mean'}, optional
        Estimator of each row's overscan level: the median of its overscan pixels (default),
        or their mean after ``clip_nsigma`` clipping around the median (robust scatter from the
        median absolute deviation of the whole overscan).
    clip_nsigma : float, optional
        Clipping threshold of ``'clipped_mean'``. Default 3.

    Returns
    -------
    trimmed : ndarray, shape of DATASEC
        Overscan-subtracted data, ADU.
    level : ndarray, one value per row of ``trimmed``
        The subtracted levels, ADU.
    """
    if method not in OVERSCAN_METHODS:
        msg = f"overscan method must be one of {OVERSCAN_METHODS}, got {method!r}"
        raise BFPSFInputError(msg, method)
    overscan = np.asarray(data[datasec.y, biassec.x], dtype=np.float64)
    if method == "median":
        level = np.median(overscan, axis=1)
    else:
        centre = np.median(overscan, axis=1, keepdims=True)
        sigma = 1.4826 * np.median(np.abs(overscan - centre))
        kept = np.abs(overscan - centre) <= clip_nsigma * sigma
        count = np.sum(kept, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            level = np.where(count > 0, np.sum(overscan * kept, axis=1) / count, centre[:, 0])
    trimmed = np.asarray(data[datasec.y, datasec.x], dtype=np.float64) - level[:, None]
    return trimmed, level


def _pixels(layout, hdu, overscan):
    data = hdu.data
    if layout.biassec is not None:
        return subtract_overscan(data, layout.datasec, layout.biassec, method=overscan)
    if layout.datasec is not None:
        data = data[layout.datasec.y, layout.datasec.x]
    return np.array(data, dtype=np.float64), None


def read_amplifiers(path, amps=None, *, overscan="median", what="FITS file"):
    """Read the amplifiers of a FITS file: overscan-subtracted, trimmed, in ADU.

    Parameters
    ----------
    path : str or path-like
    amps : str or sequence of str, optional
        Amplifier names (EXTNAME) to read. Default: all.
    overscan : {'median', 'clipped_mean'}, optional
        Row-by-row overscan estimator (`subtract_overscan`), where a BIASSEC is given.

    Returns
    -------
    list of Amplifier

    Raises
    ------
    BFPSFInputError
        As `amplifier_layout`.
    """
    layouts = amplifier_layout(path, amps, what=what)
    amplifiers = []
    with reading(path, _readable(what)), fits.open(path, memmap=False) as hdus:
        for layout in layouts:
            amplifiers.append(_amplifier(layout, hdus, overscan))
    return amplifiers


def _amplifier(layout, hdus, overscan):
    hdu = hdus[layout.hdu]
    data, level = _pixels(layout, hdu, overscan)
    if layout.detsec is not None and layout.detsec.flip_x:
        data = data[:, ::-1]  # readout order -> detector orientation
    if layout.detsec is not None and layout.detsec.flip_y:
        data = data[::-1]
        level = None if level is None else level[::-1]
    header = hdu.header.copy()
    for keyword in ("EXPTIME", *SATURATION_KEYWORDS):  # the primary's, where the HDU has none
        if keyword not in header and keyword in hdus[0].header:
            header[keyword] = hdus[0].header[keyword]
    return Amplifier(layout=layout, data=data, header=header, overscan_adu=level)


def read_amplifier(layout, *, overscan="median"):
    """One amplifier given its layout (as a worker of `bfpsf.parallel` reads one flat)."""
    with reading(layout.path, "FITS file"), fits.open(layout.path, memmap=False) as hdus:
        return _amplifier(layout, hdus, overscan)


def shared_sides(layouts):
    """Sides of each amplifier that touch another amplifier on the detector (by DETSEC).

    Returns
    -------
    dict of str to set
        ``{name: {'left', 'right', 'bottom', 'top'}}`` (left: x = 0 side of the trimmed image);
        empty for amplifiers without DETSEC, whose neighbours are unknown.
    """
    sides = {layout.name: set() for layout in layouts}
    placed = [layout for layout in layouts if layout.detsec is not None]
    for layout in placed:
        box = layout.detsec
        for other in placed:
            if other is layout:
                continue
            theirs = other.detsec
            rows = box.y.start < theirs.y.stop and theirs.y.start < box.y.stop
            columns = box.x.start < theirs.x.stop and theirs.x.start < box.x.stop
            # the pixels are in detector orientation (flips undone on reading)
            if rows and theirs.x.stop == box.x.start:
                sides[layout.name].add("left")
            if rows and theirs.x.start == box.x.stop:
                sides[layout.name].add("right")
            if columns and theirs.y.stop == box.y.start:
                sides[layout.name].add("bottom")
            if columns and theirs.y.start == box.y.stop:
                sides[layout.name].add("top")
    return sides


def near_shared_side(x, y, shape, sides, margin):
    """True where (x, y) (pixels of the trimmed amplifier) lies within ``margin`` pixels of a
    side in ``sides`` (`shared_sides`): a star whose light falls on two amplifiers."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ny, nx = shape
    near = np.zeros(np.broadcast(x, y).shape, dtype=bool)
    if "left" in sides:
        near |= x < margin - 0.5
    if "right" in sides:
        near |= x > nx - 0.5 - margin
    if "bottom" in sides:
        near |= y < margin - 0.5
    if "top" in sides:
        near |= y > ny - 0.5 - margin
    return near


def shared_side_depth(x, y, shape, sides):
    """How far (x, y) (pixels of the trimmed amplifier) lies inside the amplifier from its
    nearest side in ``sides``, pixels (negative beyond it; inf with no shared side): of two
    fits of one star from the two amplifiers of a shared side, the deeper holds its centre."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ny, nx = shape
    depth = np.full(np.broadcast(x, y).shape, np.inf)
    for side, inside in (("left", x + 0.5), ("right", nx - 0.5 - x), ("bottom", y + 0.5),
                         ("top", ny - 0.5 - y)):
        if side in sides:
            depth = np.minimum(depth, inside)
    return depth


def detector_offset(layout):
    """(x0, y0): add to the trimmed amplifier's pixel coordinates for detector coordinates
    (0 without DETSEC; the pixels of a reversed DETSEC are flipped into detector orientation
    on reading, so this offset is all there is)."""
    if layout.detsec is None:
        return 0, 0
    return layout.detsec.x.start, layout.detsec.y.start
