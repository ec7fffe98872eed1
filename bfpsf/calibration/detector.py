"""The calibration of a whole detector: one `Calibration` per amplifier, in one file.

`DetectorCalibration` writes the primary header and then each amplifier's HDU group
(`Calibration.group_hdus`, EXTVER 1, 2, ...; the layout is in `bfpsf.calibration.product`);
`read_calibration` reads any calibration file, `amplifiers_of` and `calibration_of_amplifier`
give the calibration that applies to each amplifier of an image.
"""

import logging
from dataclasses import dataclass

from astropy.io import fits

from .. import __version__
from ..errors import BFPSFInputError
from ..files import open_product, refuse_overwrite
from ..outputs import write_fits
from .product import SCHEMA_VERSION, Calibration, group_names

log = logging.getLogger(__name__)

__all__ = ["DetectorCalibration", "read_calibration", "amplifiers_of",
           "calibration_of_amplifier"]


@dataclass(frozen=True, eq=False)
class DetectorCalibration:
    """The calibrations of the amplifiers of one detector: one file, one HDU group each.

    Attributes
    ----------
    amplifiers : dict of str to Calibration
        In readout (file) order.
    detector : str
        Detector name ('' when not known).
    """

    amplifiers: dict
    detector: str = ""

    def __post_init__(self):
        object.__setattr__(self, "amplifiers", dict(self.amplifiers))
        if not self.amplifiers:
            msg = "a DetectorCalibration needs at least one amplifier"
            raise BFPSFInputError(msg)

    @property
    def names(self):
        """Amplifier names, in order."""
        return list(self.amplifiers)

    def __getitem__(self, name):
        return self.amplifiers[name]

    def __len__(self):
        return len(self.amplifiers)

    def __repr__(self):
        return (f"DetectorCalibration(detector={self.detector!r}, amplifiers="
                f"{', '.join(f'{name}: gain {cal.gain:.4g}' for name, cal in self.amplifiers.items())})")

    @property
    def warnings(self):
        """The warnings of every amplifier, each prefixed by its amplifier's name."""
        return tuple(f"{name}: {text}" for name, calibration in self.amplifiers.items()
                     for text in calibration.warnings)

    def to_json_dict(self):
        """``{'detector', 'warnings', 'amplifiers': [{'name', <the keys of
        Calibration.to_json_dict>}]}`` (each amplifier with its own ``warnings`` and
        ``shift_method``; the detector's ``warnings`` are all of them, prefixed by amplifier)."""
        return {"detector": self.detector, "n_amplifiers": len(self),
                "schema_version": SCHEMA_VERSION, "bfpsf_version": __version__,
                "warnings": list(self.warnings),
                "amplifiers": [{"name": name, **calibration.to_json_dict()}
                               for name, calibration in self.amplifiers.items()]}

    def write(self, path, *, overwrite=False):
        """Write one file: the primary header, then the HDU group of each amplifier
        (`Calibration.group_hdus`, EXTVER 1, 2, ...)."""
        refuse_overwrite(path, overwrite)
        primary = fits.PrimaryHDU()
        primary.header["BFSCHEMA"] = (SCHEMA_VERSION, "bfpsf calibration schema version")
        primary.header["BFVERSIO"] = (__version__, "bfpsf version that wrote the file")
        primary.header["NAMP"] = (len(self), "amplifiers (HDU groups) in the file")
        primary.header["DETECTOR"] = (self.detector, "detector name")
        first = next(iter(self.amplifiers.values()))
        primary.header["MODEL"] = (first.model, "PTC model of the first amplifier")
        hdus = [primary]
        for extver, calibration in enumerate(self.amplifiers.values(), start=1):
            hdus += calibration.group_hdus(extver)
        write_fits(fits.HDUList(hdus), path, overwrite=overwrite)

    @classmethod
    def read(cls, path):
        """Read a calibration file of any number of amplifiers (schema 1 files: one)."""
        with open_product(path, keyword="BFSCHEMA", version=SCHEMA_VERSION,
                          kind="calibration") as hdul:
            groups = group_names(hdul)
            return cls({name: Calibration.from_group(hdul, extver)
                        for name, extver in groups.items()},
                       detector=str(hdul[0].header.get("DETECTOR", "")))


def amplifiers_of(calibration):
    """``{amplifier name: Calibration}`` of a `Calibration` (one) or a `DetectorCalibration`."""
    if isinstance(calibration, DetectorCalibration):
        return dict(calibration.amplifiers)
    return {calibration.amplifier: calibration}


#: (calibration, amplifier) pairs already warned about (`calibration_of_amplifier`): once
#: per run, not once per image. The calibrations themselves are held: an id is reused once
#: its object is gone.
_WARNED = []


def calibration_of_amplifier(calibration, name, where="", n_amplifiers=1):
    """The `Calibration` that applies to amplifier ``name`` of an image holding
    ``n_amplifiers`` (after any ``--amp``): the one of that name in a `DetectorCalibration`;
    a one-amplifier calibration for an amplifier of its own name, for a single-HDU image, or,
    made from single-HDU flats (no name), for the one amplifier chosen of a detector.

    A one-amplifier calibration is never spread over a detector's amplifiers: each has its own
    gain and shifts (a new user's single-HDU calibration on four amplifiers gave photometry
    off by -157 to +99 mmag, without a word).

    Raises
    ------
    BFPSFInputError
        A calibration of several amplifiers has none named ``name``; a one-amplifier
        calibration given for another amplifier, or for several.
    """
    amplifiers = amplifiers_of(calibration)
    prefix = f"{where}{': ' if where else ''}"
    if len(amplifiers) == 1:
        own = next(iter(amplifiers))
        if own and name and own != name:
            msg = (f"{prefix}amplifier {name!r} with a calibration of amplifier {own!r}: give "
                   f"the detector's calibration, or --amp {own}")
            raise BFPSFInputError(msg, name)
        if not own and n_amplifiers > 1:
            msg = (f"{prefix}{n_amplifiers} amplifiers with a calibration of one (from "
                   "single-HDU flats): each amplifier has its own gain and shifts; calibrate "
                   "the detector's multi-extension flats, or choose the amplifier with --amp")
            raise BFPSFInputError(msg, n_amplifiers)
        if not own and name and not any(known is calibration and named == name
                                        for known, named in _WARNED):
            _WARNED.append((calibration, name))
            log.warning("%sa calibration without an amplifier name (from single-HDU flats) "
                        "is used for amplifier %r: right only if its flats were that "
                        "amplifier's", prefix, name)
        return amplifiers[own]
    if name not in amplifiers:
        msg = (f"{prefix}amplifier {name!r} is not in the calibration "
               f"(it has {', '.join(map(repr, amplifiers))})")
        raise BFPSFInputError(msg, name)
    return amplifiers[name]


def read_calibration(path):
    """A `Calibration` for a one-amplifier file, a `DetectorCalibration` for several."""
    detector = DetectorCalibration.read(path)
    return detector if len(detector) > 1 else next(iter(detector.amplifiers.values()))
