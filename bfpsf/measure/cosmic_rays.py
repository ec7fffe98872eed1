"""Cosmic rays on the stars: found in the residual of the PSF fit and left out of a refit.

A cosmic ray is charge deposited in one exposure, sharper than any star: one to a few pixels
of hundreds to thousands of e-. Detection fits one far from the stars as a source (flagged
``unlike_psf``, `bfpsf.measure.psf_likeness`), but one that lands in a star's fit box went
into the star's flux unflagged: 40 hits of 300-3000 e- per pixel 1.5-5 px from the centres
of 120 Kolmogorov x Airy stars on 768^2 pixels read those stars -14 mmag at the median, 17
of them beyond 20 mmag and up to -360 (a 19 ke- star), with no flag.

L.A.Cosmic (van Dokkum 2001, `astroscrappy`) finds cosmic rays by their Laplacian against
the noise and against the image's fine structure. Run on the image itself it takes the
cores of undersampled stars for cosmic rays (33 core pixels of 120 stars of 1.6 px FWHM);
run on the residual of the PSF fit, with the variance the fitted stars and the sky predict,
the stars are gone from what it reads, whatever their sampling. A set of touching pixels is
kept as a cosmic ray's only where its brightest carries a tenth or more of the fitted model
there (`MODEL_SHARE`): at the core of a bright star, the PSF model's own misfit is sharp too
(and L.A.Cosmic grows it into the pixels beside it, whose own model is faint), and a deposit
below a tenth of the core's light moves the star's flux by less than a few mmag. And only
where that pixel is sharper than a star (`SHARPER` times the PSF's own share of its 3 x 3
pixels in its brightest, `psf_sharpness`): the residual of two stars fitted as one, a star
itself, had been taken for a cosmic ray in 13 pairs of 17. The pixels kept,
grown by one (a track's faint edges), are left out of the refit of the stars whose fit box
they touch, and those stars are flagged ``cosmic_ray``.
"""

import astroscrappy
import numpy as np
from scipy import ndimage

__all__ = ["cosmic_ray_mask", "psf_sharpness", "SIGMA_CLIP", "OBJECT_LIMIT", "MODEL_SHARE",
           "SHARPER"]

#: L.A.Cosmic's detection limit, in noise sigma of the Laplacian (astroscrappy's default
#: 4.5: the noise of a crowded field of 80 stars on 320^2 pixels then put a few false ones in
#: the stars' fit boxes; a cosmic ray of 300 e- on 300 e- of sky is at 17).
SIGMA_CLIP = 6.0
#: L.A.Cosmic's contrast of a cosmic ray's Laplacian over the fine structure about it.
OBJECT_LIMIT = 5.0
#: A cosmic ray's pixel carries at least this share of the fitted stars' model there.
MODEL_SHARE = 0.1
#: A cosmic ray's brightest pixel holds this many times the share of its 3 x 3 pixels that
#: a star's holds at its sharpest (`psf_sharpness`).
SHARPER = 1.5


def psf_sharpness(model, x_0=0.0, y_0=0.0):
    """The share of a star's 3 x 3 central pixels in its brightest, centred on a pixel (its
    sharpest phase), of a photutils PSF model (flux, x_0, y_0) at (x_0, y_0)."""
    model = model.copy()
    model.flux, model.x_0, model.y_0 = 1.0, float(x_0), float(y_0)
    y, x = np.mgrid[-1:2, -1:2].astype(float)
    values = np.asarray(model(x + x_0, y + y_0), dtype=float)
    return float(values[1, 1] / values.sum())


def cosmic_ray_mask(residual_e, variance_e2, model_e, *, read_noise_e, excluded=None,
                    sharpness=0.0):
    """The pixels of cosmic rays in the residual of a PSF fit (module docstring).

    Parameters
    ----------
    residual_e : ndarray [y, x]
        Image minus its sky and its fitted stars' models, e-.
    variance_e2 : ndarray [y, x]
        The variance of each pixel the sky and the fitted models predict, e-^2.
    model_e : ndarray [y, x]
        The fitted stars' models, e-.
    read_noise_e : float
    excluded : ndarray of bool, optional
        Pixels not to read (non-finite, trails, saturated cores).

    Returns
    -------
    ndarray of bool [y, x]
        True on a cosmic ray's pixels and the pixels beside them.
    """
    residual = np.asarray(residual_e, dtype=float)
    finite = np.isfinite(residual) & np.isfinite(variance_e2)
    left_out = ~finite if excluded is None else ~finite | np.asarray(excluded, dtype=bool)
    variance = np.where(finite, variance_e2, 1.0)
    found, _ = astroscrappy.detect_cosmics(
        np.where(finite, residual, 0.0).astype(np.float32), inmask=left_out,
        invar=np.maximum(variance, 1.0).astype(np.float32), sigclip=SIGMA_CLIP,
        objlim=OBJECT_LIMIT, gain=1.0, readnoise=float(read_noise_e), satlevel=1e30)
    found &= ~left_out
    # each connected set of pixels judged at its brightest: a misfit at a bright core
    # grows into its neighbours, whose own model is faint
    labels, count = ndimage.label(found, structure=np.ones((3, 3), dtype=bool))
    if count:
        peaks = tuple(np.array(ndimage.maximum_position(residual, labels,
                                                        np.arange(1, count + 1))).T)
        share = residual[peaks] > MODEL_SHARE * np.clip(model_e, 0.0, None)[peaks]
        # sharper than a star: the brightest pixel's share of its 3 x 3 (their positive
        # part) against the PSF's own at its sharpest phase
        positive = np.clip(np.where(finite, residual, 0.0), 0.0, None)
        around = ndimage.uniform_filter(positive, size=3, mode="constant") * 9.0
        sharp = residual[peaks] > SHARPER * sharpness * around[peaks]
        found = np.r_[False, share & sharp][labels]
    return ndimage.binary_dilation(found, iterations=1) & ~left_out
