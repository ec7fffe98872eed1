"""Multi-amplifier FITS files as a camera writes them, from simulated amplifier images.

Each amplifier image (ADU, bias-free, e.g. one of `simulate_flats`) gets a bias level, a serial
overscan of ``overscan_columns`` columns holding that bias plus read noise, and the IRAF
sections a reader needs (DATASEC, BIASSEC, DETSEC: 1-based, inclusive). The amplifiers sit side
by side along x on the detector. Used by the tests and benchmarks of `bfpsf.io.amplifiers`.
"""

import numpy as np
from astropy.io import fits

from ..errors import BFPSFValueError
from ..outputs import write_fits

__all__ = ["amplifier_hdus", "write_amplifier_file"]


def amplifier_hdus(images, names, *, bias_adu, overscan_columns=20, read_noise_adu=None,
                   exptime=None, header=None, rng=None, dtype=np.float64):
    """An HDUList: an empty primary, then one image HDU per amplifier.

    Parameters
    ----------
    images : sequence of ndarray [y, x]
        Bias-free amplifier images, ADU, all of one shape.
    names : sequence of str
        EXTNAME of each.
    bias_adu : sequence of float
        Bias level of each amplifier, ADU (added to the image and its overscan).
    overscan_columns : int, optional
        Columns of serial overscan after the data. Default 20.
    read_noise_adu : sequence of float, optional
        Read noise of the overscan pixels, ADU rms (the image is assumed to carry its own).
        Default: noiseless overscan.
    exptime : float, optional
        EXPTIME, s, written to the primary header.
    header : dict, optional
        More primary-header keywords.
    rng : numpy.random.Generator, optional
        Source of the overscan noise.
    dtype : numpy dtype, optional
        Pixel type written. Default float64; an integer type (``np.uint16``, as most CCD
        controllers write) rounds to whole ADU, as an ADC does.

    Returns
    -------
    astropy.io.fits.HDUList
    """
    if not (len(images) == len(names) == len(bias_adu)):
        msg = "give one name and one bias level per amplifier image"
        raise BFPSFValueError(msg, (len(images), len(names), len(bias_adu)))
    rng = np.random.default_rng(rng)
    primary = fits.PrimaryHDU()
    for key, value in dict(header or {}).items():
        primary.header[key] = value
    if exptime is not None:
        primary.header["EXPTIME"] = float(exptime)
    hdus = [primary]
    for index, (image, name, bias) in enumerate(zip(images, names, bias_adu)):
        ny, nx = image.shape
        raw = np.empty((ny, nx + overscan_columns))
        raw[:, :nx] = image + bias
        noise = 0.0 if read_noise_adu is None else read_noise_adu[index]
        raw[:, nx:] = bias + rng.normal(0.0, 1.0, (ny, overscan_columns)) * noise
        if np.issubdtype(dtype, np.integer):
            raw = np.rint(raw)
        hdu = fits.ImageHDU(raw.astype(dtype), name=name)
        hdu.header["DATASEC"] = f"[1:{nx},1:{ny}]"
        if overscan_columns:
            hdu.header["BIASSEC"] = f"[{nx + 1}:{nx + overscan_columns},1:{ny}]"
        # side by side: each starts where the one before ends (their widths may differ)
        start = sum(other.shape[1] for other in images[:index])
        hdu.header["DETSEC"] = f"[{start + 1}:{start + nx},1:{ny}]"
        hdus.append(hdu)
    return fits.HDUList(hdus)


def write_amplifier_file(path, images, names, *, overwrite=False, **options):
    """Write `amplifier_hdus` to ``path`` atomically (never over an existing file unless
    ``overwrite``)."""
    return write_fits(amplifier_hdus(images, names, **options), path, overwrite=overwrite)
