"""Files of the commands: FITS images in, outputs never overwritten without ``--overwrite``."""

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


def read_image(path):
    """The first 2-D image HDU of a FITS file (float ADU), its header and its CATALOG table.

    Returns
    -------
    data : ndarray [y, x]
    header : astropy.io.fits.Header
    catalog : astropy.table.Table or None
        The ``CATALOG`` extension when present (e.g. colours of simulated stars).
    """
    from astropy.io import fits

    if not Path(path).exists():
        msg = f"image {path} does not exist"
        raise BFPSFInputError(msg, str(path))
    with fits.open(path) as hdus:
        for hdu in hdus:
            if hdu.is_image and hdu.data is not None and hdu.data.ndim == 2:
                data = np.asarray(hdu.data, dtype=float)
                header = hdu.header.copy()
                break
        else:
            msg = f"{path} holds no 2-D image"
            raise BFPSFInputError(msg, str(path))
        catalog = None
        if "CATALOG" in hdus:
            from astropy.table import Table

            catalog = Table.read(hdus["CATALOG"])
    return data, header, catalog
