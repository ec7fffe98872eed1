"""Shapes from adaptive moments: size, ellipticity and the fourth-order moment.

The ellipticity is the distortion of HSM (``galsim.hsm.ShapeData.observed_shape``, a
`galsim.Shear` whose ``e1``, ``e2`` are)::

    e1 = (Mxx - Myy) / T,   e2 = 2 Mxy / T,   T = Mxx + Myy

and ``rho4`` is HSM's weighted fourth moment, ``sum w I rho^4 / sum w I`` with
``rho^2 = (r - x0)^T M^-1 (r - x0)`` and the matched weight ``w = exp(-rho^2 / 2)``: 2 for a
Gaussian, larger for profiles with wings. Stars (`bfpsf.measure.sources.measure_sources`) and
the PSF model (`psf_shape`, ``FluxDependentPSF.shape``) use the same estimator
(`bfpsf.moments.adaptive.adaptive_moments_batch`), so model and stars compare directly.
"""

from dataclasses import dataclass

import numpy as np
from scipy.stats import median_abs_deviation

from ..errors import BFPSFValueError
from ..least_squares import clipped_least_squares
from .adaptive import adaptive_moments_batch

__all__ = ["PSFShape", "distortion", "fourth_moment", "psf_shape", "psf_shapes",
           "calibration_shape_error",
           "model_shapes", "shape_residuals", "size_offset", "size_ratios", "size_across",
           "stars_beside_psf",
           "star_stamps", "model_stamps"]

#: Magnitudes per relative size error of the template: a PSF fit with a template of width
#: sigma on a star of width sigma (1 + eps) finds its flux low by about eps (Gaussians).
MAG_PER_SIZE_ERROR = 2.5 / np.log(10.0)


@dataclass(frozen=True)
class PSFShape:
    """Adaptive-moment shape of a PSF at one flux and position.

    Attributes
    ----------
    sigma : float
        ``(Mxx Myy - Mxy^2)^(1/4)``, pixels: G15's IQ, HSM's ``moments_sigma``.
    T : float
        ``Mxx + Myy``, pixel^2.
    e1, e2 : float
        Distortion (module docstring).
    rho4 : float
        Weighted fourth moment (module docstring); 2 for a Gaussian.
    mxx, myy, mxy : float
        Second moments of the matched elliptical Gaussian, pixel^2.
    flux : float
        The flux the model was rendered at, in its ``flux_unit``.
    flags : int
        `bfpsf.moments.result.MomentsFlag` bits; 0 is a clean measurement.
    """

    sigma: float
    T: float
    e1: float
    e2: float
    rho4: float
    mxx: float
    myy: float
    mxy: float
    flux: float
    flags: int


def distortion(mxx, myy, mxy):
    """``(e1, e2)`` of second moments, HSM's distortion convention (module docstring)."""
    trace = np.asarray(mxx) + np.asarray(myy)
    return (np.asarray(mxx) - np.asarray(myy)) / trace, 2.0 * np.asarray(mxy) / trace


def fourth_moment(stamps, moments):
    """HSM's ``rho4`` of stamps at their adaptive moments (module docstring).

    Parameters
    ----------
    stamps : ndarray (n, ny, nx)
    moments : bfpsf.moments.result.Moments
        Their batch result.

    Returns
    -------
    ndarray (n,)
    """
    stack = np.asarray(stamps, dtype=float)
    _, ny, nx = stack.shape
    x0, y0, mxx, myy, mxy = (np.asarray(getattr(moments, name), dtype=float)[:, None, None]
                             for name in ("x", "y", "mxx", "myy", "mxy"))
    det = mxx * myy - mxy**2
    dx = np.arange(nx)[None, None, :] - x0
    dy = np.arange(ny)[None, :, None] - y0
    rho2 = (myy * dx**2 - 2 * mxy * dx * dy + mxx * dy**2) / det
    weighted = np.where(np.isfinite(stack), stack, 0.0) * np.exp(-0.5 * rho2)
    return np.sum(weighted * rho2**2, axis=(1, 2)) / np.sum(weighted, axis=(1, 2))


#: The flux, in the model's unit, at which `psf_shapes` renders a flux of 0: the model's BF
#: and EMPIRICAL terms there are 1e-9 of those at unit flux, its shape is P0's.
FAINT_LIMIT = 1e-9


def psf_shape(psf, flux, *, x=None, y=None):
    """Adaptive moments of a flux-dependent PSF's pixelised model at a flux.

    The model is evaluated (``psf.evaluate``) on the pixels of a stamp around a star at the
    phase of ``(x, y)``, normalised to unit flux, and measured: the implementation of
    ``BFPSFModel.shape``; `psf_shapes` measures many stars at once.

    Parameters
    ----------
    psf : FluxDependentPSF
    flux : float
        Flux, the model's ``flux_unit``; >= 0 (0: the limit of faint sources, P0 itself).
    x, y : float, optional
        Image position, pixels: the star is rendered at its sub-pixel phase
        (``x - round(x)``); default phase 0.

    Returns
    -------
    PSFShape
    """
    if np.ndim(flux) != 0:
        msg = (f"flux must be one number, got an array of shape {np.shape(flux)}: the shapes "
               f"of many stars are bfpsf.moments.shapes.psf_shapes(psf, flux, x, y)")
        raise BFPSFValueError(msg, flux)
    if not (np.isfinite(flux) and flux >= 0):
        msg = f"flux must be a finite number >= 0, got {flux!r}"
        raise BFPSFValueError(msg, flux)
    # every PSF kind (bfpsf.model.base): a field-varying one is evaluated at (x, y) itself,
    # by default at its reference position (the grid's centre), never at the stamp's corner
    x, y = psf.position_or_reference(x, y)
    shapes = psf_shapes(psf, [flux], [x], [y])
    return PSFShape(**{name: (int(value[0]) if name == "flags" else float(value[0]))
                       for name, value in shapes.items()})


def psf_shapes(psf, flux, x, y):
    """`psf_shape` of many stars: the model's adaptive moments at each star's own flux,
    image position and sub-pixel phase.

    Each star's model (``psf.evaluate`` on the pixels around ``(x, y)``: BF at its flux, the
    pixel response at its phase and, for a field-varying model, the model at its position) is
    normalised to unit flux and measured with the estimator of the star measurements.

    Parameters
    ----------
    psf : bfpsf.model.base.BFPSFModel
    flux, x, y : array_like
        Fluxes (the model's ``flux_unit``) and image positions, pixels, one per star. A
        flux of 0 gives the limit of faint sources (P0); non-finite or negative fluxes and
        non-finite positions give NaN.

    Returns
    -------
    dict of ndarray
        The `PSFShape` fields (``sigma``, ``T``, ``e1``, ``e2``, ``rho4``, ``mxx``, ``myy``,
        ``mxy``, ``flux``, ``flags``), one value per star.
    """
    flux, x, y = np.broadcast_arrays(*(np.asarray(value, dtype=float).ravel()
                                       for value in (flux, x, y)))
    good = np.isfinite(flux) & (flux >= 0) & np.isfinite(x) & np.isfinite(y)
    names = ("sigma", "T", "e1", "e2", "rho4", "mxx", "myy", "mxy")
    result = {name: np.full(flux.shape, np.nan) for name in names}
    result["flux"] = flux.copy()
    result["flags"] = np.zeros(flux.shape, dtype=int)
    if not good.any():
        return result
    stamps = model_stamps(psf, flux[good], x[good], y[good])
    moments = adaptive_moments_batch(stamps)
    values = dict(mxx=moments.mxx, myy=moments.myy, mxy=moments.mxy, sigma=moments.sigma,
                  T=moments.mxx + moments.myy, rho4=fourth_moment(stamps, moments))
    values["e1"], values["e2"] = distortion(moments.mxx, moments.myy, moments.mxy)
    for name, value in values.items():
        result[name][good] = value
    result["flags"][good] = moments.flags
    return result


def calibration_shape_error(psf, reference_flux, flux=1.0, *, x=None, y=None):
    """The error of a fitted PSF's size and distortion at ``flux`` that its calibration's
    boundary shifts carry.

    P0 is fitted from stars of every flux: where the shifts predict too much BF it comes out
    small, and the stars' fit keeps the model right where they weigh, near
    ``reference_flux``. The model at ``flux`` is then off by the error of the BF change
    between the two: the spread, over the calibration's shift samples (``psf.shift_samples``),
    of [S(flux) - S(reference_flux)] for S the sigma, e1 and e2 of the model with those
    shifts. At ``flux`` -> 0 it is the error of P0 itself, the PSF of faint galaxies (a new
    user's flats, their BF amplitude known to 34 %, gave P0's sigma 0.55 % small, unsaid).

    Parameters
    ----------
    psf : BFPSFModel
        With ``shift_samples`` (every product of ``bfpsf psf``); a field-varying model is
        taken at (x, y), by default its reference position.
    reference_flux : float
        The flux the fitted stars weigh in at (``bfpsf psf``: their fluxes weighted as the P0
        fit weighs them), the model's ``flux_unit``.
    flux : float, optional
        Default 1 (P0: F -> 0).

    Returns
    -------
    dict or None
        ``sigma_percent`` (of the model's sigma at ``flux``), ``e1``, ``e2`` (distortion) and
        ``n_samples``; None with fewer than 2 shift samples.
    """
    samples = list(getattr(psf, "shift_samples", ()) or ())
    if len(samples) < 2:
        return None
    position = psf.position_or_reference(x, y)
    single = psf.at(*position)
    # at the sub-pixel phase of (x, y) when given: an undersampled model has no adaptive
    # moments at phase 0, on a pixel centre (`bfpsf.moments.adaptive`)
    at = {} if x is None and y is None else dict(x=position[0], y=position[1])

    def change(model):
        low, high = psf_shape(model, flux, **at), psf_shape(model, reference_flux, **at)
        return low.sigma - high.sigma, low.e1 - high.e1, low.e2 - high.e2

    changes = np.array([change(single.with_shifts(shifts)) for shifts in samples])
    spread = np.std(changes, axis=0, ddof=1)
    return {"sigma_percent": float(100 * spread[0] / psf_shape(single, flux, **at).sigma),
            "e1": float(spread[1]), "e2": float(spread[2]), "n_samples": len(samples)}


def model_shapes(psf, flux, *, n_grid=12):
    """Size and ellipticity of a PSF model at many fluxes (one per star), interpolated.

    `psf_shape` on ``n_grid`` fluxes spaced logarithmically over the range of ``flux``, then
    interpolated linearly in flux: the BF changes are linear in F to first order.

    Parameters
    ----------
    psf : FluxDependentPSF
    flux : array_like
        Fluxes, the model's ``flux_unit``; non-finite or non-positive ones give NaN.
    n_grid : int, optional
        Default 12.

    Returns
    -------
    dict of ndarray
        ``sigma``, ``T``, ``e1``, ``e2``, ``rho4``, one value per flux.
    """
    flux = np.asarray(flux, dtype=float)
    good = np.isfinite(flux) & (flux > 0)
    names = ("sigma", "T", "e1", "e2", "rho4")
    result = {name: np.full(flux.shape, np.nan) for name in names}
    if not good.any():
        return result
    low, high = flux[good].min(), flux[good].max()
    grid = np.geomspace(low, max(high, low * 1.001), n_grid)
    shapes = [psf_shape(psf, value) for value in grid]
    for name in names:
        result[name][good] = np.interp(flux[good], grid,
                                       [getattr(shape, name) for shape in shapes])
    return result


def shape_residuals(stars, psf, *, flux=None):
    """Star minus model: relative size, e1 and e2 of each star against a PSF model.

    The model is taken at each star's own position and sub-pixel phase (`psf_shapes`: a
    field-varying model there, not at its centre) when the table has ``x``, ``y``.

    Parameters
    ----------
    stars : astropy.table.Table
        Star table (``flux_e``, ``iq``, ``e1``, ``e2``; ``x``, ``y`` optional).
    psf : bfpsf.model.base.BFPSFModel
        In electrons.
    flux : float, optional
        Compare every star with the model at this one flux (a static PSF frozen there);
        default each star's own ``flux_e`` (P(F)).

    Returns
    -------
    dict of ndarray
        ``sigma`` ((star - model) / model), ``e1``, ``e2`` (star - model).
    """
    star_flux = np.asarray(stars["flux_e"], dtype=float)
    at = star_flux if flux is None else np.full(star_flux.shape, float(flux))
    x, y = psf.reference_position
    if "x" in stars.colnames and "y" in stars.colnames:
        x, y = np.asarray(stars["x"], dtype=float), np.asarray(stars["y"], dtype=float)
    model = psf_shapes(psf, at, x, y)
    return {"sigma": np.asarray(stars["iq"], dtype=float) / model["sigma"] - 1.0,
            "e1": np.asarray(stars["e1"], dtype=float) - model["e1"],
            "e2": np.asarray(stars["e2"], dtype=float) - model["e2"]}


def size_offset(ratio):
    """How much larger an image's stars are than a PSF model: the median of `size_ratios`
    (star / model - 1 of the adaptive sigma, each star against the model at its own flux,
    position and phase, on the same pixels; NaN left out).

    A seeing different from the P0's: PSF photometry of the image is then biased by about
    ``-offset`` in flux (`MAG_PER_SIZE_ERROR` offset magnitudes, fainter for larger stars).

    Returns
    -------
    (float, float, int)
        The offset, its error (from the scatter: 1.2533 x 1.4826 MAD / sqrt(n)) and the
        number of stars; NaN, NaN, n with fewer than 3 stars.
    """
    ratio = np.asarray(ratio, dtype=float)
    ratio = ratio[np.isfinite(ratio)]
    if ratio.size < 3:
        return np.nan, np.nan, int(ratio.size)
    median = float(np.median(ratio))
    error = 1.2533 * float(median_abs_deviation(ratio, scale="normal")) / np.sqrt(ratio.size)
    return median, error, int(ratio.size)


def size_ratios(beside):
    """Each star's adaptive sigma over its model's at its flux, position and phase, less 1
    (``beside``: `stars_beside_psf`'s); NaN where either is not measured."""
    ratio = beside["measured"].sigma / beside["model"]["sigma"] - 1.0
    return np.where(np.isfinite(ratio) & (beside["measured"].flags == 0), ratio, np.nan)


def size_across(beside, psf, shape):
    """How the stars' size against their model changes across an image: a plane fitted to
    each star's adaptive sigma over the model's at its flux and position, at a pixel's
    centre (one clipping at 3 robust sigma), its range over the image's corners. (The model
    at each star's own phase, `size_ratios`, is no measure of this: one P0 fitted on a
    varying field takes some of the variation into its sub-pixel phases, 1.54-1.82 px at
    three phases of the same flux on a field of 3.0 -> 3.9 px FWHM, and hid most of it.)

    One P(F) fitted on a field whose PSF varies leaves its stars larger on one side and
    smaller on the other (a new user's FWHM 3.2 -> 3.9 px across 400 px: photometry 50-73
    mmag off from one side to the other, false ``unlike_psf`` flags, no word); a gridded
    P(F) follows the field.

    Returns
    -------
    dict or None
        ``change`` (the plane's highest minus lowest value at the corners, a fraction of
        sigma) and ``change_err`` (from the scatter about the plane); ``along_x`` and
        ``along_y`` (the plane's change from one side to the other along each axis, signed)
        with ``along_x_err``, ``along_y_err``; ``n`` stars; None with fewer than 6 stars.
    """
    x, y = beside["x"], beside["y"]
    centred = psf_shapes(psf, beside["flux"], np.floor(x + 0.5), np.floor(y + 0.5))
    ratio = beside["measured"].sigma / centred["sigma"] - 1.0
    good = np.isfinite(ratio) & (beside["measured"].flags == 0) & (centred["flags"] == 0)
    ratio, x, y = ratio[good], x[good], y[good]
    if ratio.size < 6:
        return None
    ny, nx = shape
    design = np.column_stack([np.ones(ratio.size), x / nx - 0.5, y / ny - 0.5])
    fit = clipped_least_squares(ratio, design, nsigma=3.0, max_iterations=2, min_kept=6)
    if fit.keep.sum() < 6:
        return None
    plane, covariance, kept = fit.params, fit.covariance, fit.keep
    signs = np.sign(plane[1:])
    change = float(np.abs(plane[1:]).sum())  # the corners: x and y each half the frame away
    change_err = float(np.sqrt(signs @ covariance[1:, 1:] @ signs))
    errors = np.sqrt(np.diag(covariance)[1:])
    return {"change": change, "change_err": change_err, "along_x": float(plane[1]),
            "along_x_err": float(errors[0]), "along_y": float(plane[2]),
            "along_y_err": float(errors[1]), "n": int(kept.sum())}


def stars_beside_psf(image, x, y, flux, psf):
    """An image's stars measured beside their models: the stars of finite positive flux whose
    stamp (`star_stamps`, the model's size) lies inside the image, their adaptive moments and
    the model's at each one's flux, position and phase (`psf_shapes`).

    Returns
    -------
    dict
        ``stamps`` (n, side, side), ``measured`` (`Moments`), ``model`` (`psf_shapes`'s dict),
        and the stars' ``x``, ``y``, ``flux`` (n,).
    """
    x, y, flux = (np.asarray(value, dtype=float).ravel() for value in (x, y, flux))
    usable = np.isfinite(flux) & (flux > 0)
    stamps, inside = star_stamps(image, x[usable], y[usable], psf.half_size)
    x, y, flux = x[usable][inside], y[usable][inside], flux[usable][inside]
    return {"stamps": stamps, "measured": adaptive_moments_batch(stamps),
            "model": psf_shapes(psf, flux, x, y), "x": x, "y": y, "flux": flux}


def star_stamps(image, x, y, half):
    """The stamps of side ``2 half + 1`` centred on the pixels of ``(x, y)`` (the model's
    stamps, `psf_shapes`), of the stars whose stamp lies inside the image.

    Returns
    -------
    (ndarray (n, 2 half + 1, 2 half + 1), ndarray of bool)
        The stamps and which of the stars they are (``inside``; non-finite positions are not).
    """
    image = np.asarray(image, dtype=float)
    x, y = (np.asarray(value, dtype=float).ravel() for value in (x, y))
    finite = np.isfinite(x) & np.isfinite(y)
    left = np.floor(np.where(finite, x, 0.0) + 0.5).astype(int) - half
    bottom = np.floor(np.where(finite, y, 0.0) + 0.5).astype(int) - half
    inside = (finite & (left >= 0) & (bottom >= 0) & (left + 2 * half < image.shape[1])
              & (bottom + 2 * half < image.shape[0]))
    stamps = np.array([image[b:b + 2 * half + 1, a:a + 2 * half + 1]
                       for a, b in zip(left[inside], bottom[inside])]).reshape(
                           -1, 2 * half + 1, 2 * half + 1)
    return stamps, inside


def model_stamps(psf, flux, x, y):
    """The model of each star at unit flux on the stamp `star_stamps` cuts around it (side
    ``2 psf.half_size + 1``): ``psf.evaluate`` at its flux (0: `FAINT_LIMIT`, P0), position
    and sub-pixel phase, as a fitter sees it (mode 'table': the stored table; 'exact': R at
    the phase). Fluxes >= 0 and finite positions.

    Returns
    -------
    ndarray (n, 2 half + 1, 2 half + 1)
    """
    flux, x, y = (np.asarray(value, dtype=float).ravel() for value in (flux, x, y))
    half = psf.half_size
    rows, columns = np.mgrid[:2 * half + 1, :2 * half + 1]
    return np.array([psf.evaluate(columns + np.floor(x_0 + 0.5) - half,
                                  rows + np.floor(y_0 + 0.5) - half, value, x_0, y_0) / value
                     for value, x_0, y_0 in zip(np.where(flux > 0, flux, FAINT_LIMIT), x, y)
                     ]).reshape(-1, 2 * half + 1, 2 * half + 1)
