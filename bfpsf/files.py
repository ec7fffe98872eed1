"""What every bfpsf product file shares: no overwrite without asking, a schema check on reading.

Products (`bfpsf.Calibration`, the PSF product of `bfpsf.psf_product`) are FITS files whose
primary header carries a schema keyword; a file written by a newer bfpsf is refused rather than
misread.
"""

from contextlib import contextmanager
from pathlib import Path

from .errors import BFPSFFileExistsError, BFPSFInputError

__all__ = ["refuse_overwrite", "open_product"]


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
