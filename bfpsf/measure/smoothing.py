"""The detection's smoothed image: one Gaussian kernel for detection
(`bfpsf.measure.sources.measure_sources`), the peaks merged segments hide
(`bfpsf.measure.neighbours.smoothed_peaks`), the search of a fit's residual
(`bfpsf.measure.residual_sources`) and the lines (`bfpsf.measure.line_features`)."""

import numpy as np
from astropy.convolution import convolve

__all__ = ["detection_kernel", "smoothed_image"]


def detection_kernel(detection_fwhm):
    """The Gaussian of FWHM ``detection_fwhm`` pixels the detection smooths with
    (photutils' ``make_2dgaussian_kernel``, on 2 * int(2 FWHM) + 1 pixels)."""
    from photutils.segmentation import make_2dgaussian_kernel

    return make_2dgaussian_kernel(detection_fwhm, size=2 * int(2 * detection_fwhm) + 1)


def smoothed_image(image_e, detection_fwhm=3.0):
    """``image_e`` smoothed by `detection_kernel` (normalised), its non-finite pixels as 0."""
    return convolve(np.where(np.isfinite(image_e), image_e, 0.0),
                    detection_kernel(detection_fwhm), normalize_kernel=True)
