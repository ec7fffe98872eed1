"""What every bfpsf output file shares: no overwrite without asking, atomic writes, one JSON
writer, and a schema check on reading products.

Products (`bfpsf.Calibration`, the PSF product of `bfpsf.psf_product`) are FITS files whose
primary header carries a schema keyword; a file written by a newer bfpsf is refused rather than
misread.

Every file is written to a temporary file in the destination's directory and renamed over the
destination only once complete (`atomic_path`): a write that fails (a full disk, an error
half-way) leaves the previous file byte for byte and no partial file.
"""

import json
import math
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import BFPSFFileExistsError, BFPSFInputError

__all__ = ["refuse_overwrite", "open_product", "atomic_path", "write_json", "json_safe"]


def refuse_overwrite(path, overwrite, *, how="overwrite=True (--overwrite)"):
    """Raise `BFPSFFileExistsError` if ``path`` exists and ``overwrite`` is false.

    Parameters
    ----------
    path : str or path-like
    overwrite : bool
    how : str, optional
        How the caller asks for an overwrite, quoted in the message.
    """
    if Path(path).exists() and not overwrite:
        msg = f"{path} exists; pass {how} to replace it"
        raise BFPSFFileExistsError(msg, str(path))


@contextmanager
def open_product(path, *, keyword, version, kind):
    """Open a bfpsf product FITS file after checking that it is one this bfpsf can read.

    Parameters
    ----------
    path : str or path-like
    keyword : str
        Primary-header keyword holding the schema version (e.g. ``'BFSCHEMA'``).
    version : int
        Newest schema this bfpsf reads.
    kind : str
        What the file should be, for the messages (e.g. ``'calibration'``).

    Yields
    ------
    astropy.io.fits.HDUList
        Opened without memory mapping; closed on exit.

    Raises
    ------
    BFPSFInputError
        The file is missing, lacks ``keyword``, or has a newer schema.
    """
    from astropy.io import fits

    from . import __version__

    path = Path(path)
    if not path.exists():
        msg = f"{kind} file {path} does not exist"
        raise BFPSFInputError(msg, str(path))
    with fits.open(path, memmap=False) as hdul:
        header = hdul[0].header
        if keyword not in header:
            msg = f"{path} is not a bfpsf {kind} file (no {keyword} keyword)"
            raise BFPSFInputError(msg, str(path))
        schema = int(header[keyword])
        if schema > version:
            msg = (f"{path} has {kind} schema version {schema}, newer than the {version} this "
                   f"bfpsf {__version__} reads; upgrade bfpsf")
            raise BFPSFInputError(msg, schema)
        yield hdul


@contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` to write to; renamed onto ``path`` on success.

    The temporary file is created in the same directory (so `os.replace` is an atomic rename
    on the same file system) with the same suffix (writers that choose a format by suffix,
    e.g. astropy and matplotlib, still do). If the block raises, the temporary file is removed
    and ``path`` is left as it was.

    Yields
    ------
    pathlib.Path
        Where to write.
    """
    path = Path(path)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}",
                                         dir=path.parent if str(path.parent) else ".")
    os.close(handle)
    temporary = Path(temporary)
    try:
        temporary.unlink()  # writers that refuse an existing file (astropy) see none
        yield temporary
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def json_safe(value):
    """Plain JSON types: arrays to lists, numpy scalars to Python ones, NaN and infinities
    (not JSON) to null; dataclass instances are left out of dicts, other objects become str."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()
                if not hasattr(item, "__dataclass_fields__")}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [json_safe(item) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def write_json(path, summary, *, overwrite=False):
    """Write a machine-readable summary as strict JSON (NaN as null), atomically.

    Refuses to replace an existing file unless ``overwrite``. Returns the path.
    """
    path = Path(path)
    refuse_overwrite(path, overwrite)
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(json_safe(summary), indent=1, allow_nan=False) + "\n")
    return path
