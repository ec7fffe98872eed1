"""Fitted stars whose image is not the PSF's (`unlike_psf`): two stars too close for detection
to split, a galaxy, or a cosmic ray (sharper than the PSF), fitted as one star.
`psf_photometry` flags them ``UNLIKE_PSF`` in ``source_flags``.

A new user's crowded E2V field (880 true stars, 740 detections) had 55 stars with a neighbour
closer than 5 pixels; detection merged them and the fit returned the pair's light as one star,
190-285 mmag too bright, with every flag 0. Each fitted star's pixels with every other star's
model subtracted are measured with the adaptive-moment estimator and compared with its own
model (the PSF at its flux, position and phase, `bfpsf.moments.shapes.model_stamps`): beyond
`MISFIT_SIGMA` of the star's statistical errors (`bfpsf.moments.moment_errors`) and beyond
`UNLIKE_SIZE` of the size T (larger only: a blend is never smaller) or `UNLIKE_SHAPE` of e1
or e2, once the straight line in flux that all the stars share is taken out.
"""

import numpy as np
from scipy.stats import siegelslopes

from ..model.psf_fit_stars import MISFIT_SIGMA
from ..moments.adaptive import adaptive_moments_batch
from ..moments.moment_errors import moment_errors
from ..moments.shapes import distortion, model_stamps, star_stamps

__all__ = ["UNLIKE_SIZE", "UNLIKE_SHAPE", "unlike_psf", "misfit_outliers"]

#: A star is unlike the PSF beyond `MISFIT_SIGMA` of its errors and beyond this change of its
#: size T (relative, larger only) ...
UNLIKE_SIZE = 0.08
#: ... or of its e1 or e2, after the line in flux all the stars share is taken out. Lower than
#: the P0 fit's floors (`bfpsf.model.psf_fit_stars.MISFIT_SIZE`, compared with the neighbours):
#: here each star meets the model at its own flux; a pair 2 pixels apart with fluxes 1:0.35
#: (326 mmag too bright) is 0.09 in e.
UNLIKE_SHAPE = 0.05
#: ... or sharper than the PSF: its brightest pixel near the centre this much above the
#: model's, as a fraction of the model's (a cosmic ray or a hot pixel fitted as a star: the
#: adaptive moments of one pixel stop at the size of their smallest weight, the PSF's).
UNLIKE_PEAK = 0.5
#: `_common_trend` is fitted on at most this many stars
TREND_STARS = 400
#: A star whose fit's reduced chi2 is this many times its flux peers' median (and above
#: `MISFIT_FLOOR`) is unlike the PSF (`misfit_outliers`) ...
MISFIT_FACTOR = 5.0
MISFIT_FLOOR = 3.0
#: ... its peers the stars nearest it in flux, this many at most.
MISFIT_PEERS = 10


def unlike_psf(residual_e, x, y, flux, psf, background_variance):
    """Which fitted stars are unlike the PSF.

    Parameters
    ----------
    residual_e : ndarray (ny, nx)
        The image less the sky and every fitted star's model, e- (NaN: masked pixels).
    x, y, flux : array_like
        The fitted positions (pixels) and fluxes (the PSF's flux, before any total-flux
        correction) of the stars.
    psf : bfpsf.model.base.BFPSFModel
    background_variance : float
        Variance of a pixel without star light (sky and read noise), e-^2.

    Returns
    -------
    ndarray of bool
        True for a star unlike the PSF; False too where it cannot be told (its stamp leaves
        the image, a masked pixel, a non-finite or non-positive flux).
    """
    x, y, flux = (np.asarray(value, dtype=float).ravel() for value in (x, y, flux))
    out = np.zeros(x.size, dtype=bool)
    usable = np.flatnonzero(np.isfinite(flux) & (flux > 0))
    residual, inside = star_stamps(residual_e, x[usable], y[usable], psf.half_size)
    rows = usable[inside]
    if rows.size == 0:
        return out
    model = model_stamps(psf, flux[rows], x[rows], y[rows])
    stamps = residual + flux[rows, None, None] * model
    star = adaptive_moments_batch(stamps)
    errors = moment_errors(stamps, star, background_variance=background_variance)
    expected = adaptive_moments_batch(model)
    good = (star.flags == 0) & (expected.flags == 0)
    size = star.mxx + star.myy
    offsets = [size / (expected.mxx + expected.myy) - 1.0]
    offsets += [measured - predicted for measured, predicted in zip(
        distortion(star.mxx, star.myy, star.mxy),
        distortion(expected.mxx, expected.myy, expected.mxy))]
    errors = [np.hypot(errors["mxx_err"], errors["myy_err"]) / size, errors["e1_err"],
              errors["e2_err"]]
    beyond = np.zeros(rows.size, dtype=bool)
    for index, (offset, error) in enumerate(zip(offsets, errors)):
        # what every star shares (a P0 a little wrong, a BF amplitude a little off, an
        # effect that grows with flux) is not a star unlike the others
        offset = offset - _common_trend(offset, flux[rows], good)
        # a blend or a galaxy is larger than a star, never smaller
        beyond |= (offset if index == 0 else np.abs(offset)) > np.maximum(
            UNLIKE_SIZE if index == 0 else UNLIKE_SHAPE, MISFIT_SIGMA * error)
    out[rows] = (good & beyond) | _sharper(stamps, model, flux[rows], background_variance)
    return out


def _sharper(stamps, model, flux, background_variance):
    """Stamps whose brightest pixel of the central 3 x 3 is `UNLIKE_PEAK` of the model's and
    `MISFIT_SIGMA` of its noise above the model's (the model at the star's flux)."""
    centre = model.shape[-1] // 2
    core = (slice(None), slice(centre - 1, centre + 2), slice(centre - 1, centre + 2))
    peak = stamps[core].reshape(len(stamps), -1).max(axis=1)
    predicted = flux * model[core].reshape(len(model), -1).max(axis=1)
    noise = np.sqrt(np.clip(predicted, 0.0, None) + background_variance)
    return peak - predicted > np.maximum(UNLIKE_PEAK * predicted, MISFIT_SIGMA * noise)


def _common_trend(offset, flux, good):
    """A straight line in flux through the offsets of the ``good`` stars: Siegel's repeated
    medians (`scipy.stats.siegelslopes`: half the stars may be pairs; at most
    `TREND_STARS` of them, evenly in flux, as its cost grows with their square), zero with
    fewer than 6 stars."""
    keep = np.flatnonzero(good & np.isfinite(offset) & np.isfinite(flux))
    if keep.size < 6 or np.ptp(flux[keep]) == 0:
        return np.zeros(offset.shape)
    keep = keep[np.argsort(flux[keep])]
    keep = keep[np.linspace(0, keep.size - 1, min(keep.size, TREND_STARS)).astype(int)]
    slope, intercept = siegelslopes(offset[keep], flux[keep])
    return intercept + slope * flux


def misfit_outliers(reduced_chi2, flux):
    """The fitted stars whose reduced chi2 is `MISFIT_FACTOR` times the median of their peers
    in flux (the `MISFIT_PEERS` nearest in log flux, itself left out) and above
    `MISFIT_FLOOR`: a misfit the moments do not see. A new user's isolated 8.8e5 e- star
    beside a source detected on its diffraction spike 18 px away, which took its light, was
    fitted 160 mmag faint with every flag 0 and a reduced chi2 of 52 (the others <= 1.2). A
    bright star's own model error is its peers' too."""
    chi2 = np.asarray(reduced_chi2, dtype=float)
    level = np.log(np.clip(np.asarray(flux, dtype=float), 1e-30, None))
    good = np.flatnonzero(np.isfinite(chi2) & np.isfinite(level) & (np.asarray(flux) > 0))
    out = np.zeros(chi2.shape, dtype=bool)
    if good.size < 3:
        return out
    order = good[np.argsort(level[good])]
    half = MISFIT_PEERS // 2
    for rank, index in enumerate(order):
        start = int(np.clip(rank - half, 0, max(order.size - MISFIT_PEERS - 1, 0)))
        window = order[start:start + MISFIT_PEERS + 1]  # itself and its peers
        typical = float(np.median(chi2[window[window != index]]))
        out[index] = chi2[index] > max(MISFIT_FACTOR * typical, MISFIT_FLOOR)
    return out
