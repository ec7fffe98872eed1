"""Input files of the commands: FITS images (outputs: `bfpsf.files`)."""

import numpy as np

from ..errors import BFPSFInputError
from ..files import check_input, reading


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

    check_input(path, "image")
    with reading(path, "FITS image"), fits.open(path, memmap=False) as hdus:
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
