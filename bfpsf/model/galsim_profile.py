"""GalSim views of the flux-dependent PSF, and BF applied to rendered models.

* `to_galsim` turns P(F) at a given flux and sub-pixel phase into a `galsim.InterpolatedImage`
  of the pixelised PSF. As Piff's ``get_profile`` does, it says that the pixel response is
  already included: draw it with ``method='no_pixel'``.
* `apply_bf_to_rendered` applies the flux-dependent redistribution (G15 eq. scrambling_model)
  to any rendered model in electrons (a galaxy convolved with the PSF and the pixel), for
  shear pipelines that forward-model their sources.
* `render_stars` draws pixelised stars of a GalSim profile and applies the redistribution to
  the whole image: test data with an exactly known brighter-fatter effect.
"""

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError
from .bf_term import star_phases
from .redistribution import redistribute

__all__ = ["to_galsim", "apply_bf_to_rendered", "render_stars"]


def to_galsim(psf, flux, x=None, y=None, *, x_phase=None, y_phase=None, normalise=True,
              position=None):
    """The pixelised PSF of a star of flux F as a GalSim object.

    Parameters
    ----------
    psf : FluxDependentPSF or GriddedFluxDependentPSF
    flux : float
        Flux of the star, in the PSF's ``flux_unit``.
    x, y : float, optional
        Image position of the star, pixels (as every call of every kind:
        ``psf.to_galsim(flux, x, y)``); or give ``position``.
    x_phase, y_phase : float, optional
        Star centre minus the centre of its pixel, pixels: R depends on it (and a fitted P0
        on its phases). Default the phase of ``position``, 0 without one.
    normalise : bool, optional
        True (default): unit flux, i.e. P(F) = p + F R[p]; False: flux F.
    position : (float, float), optional
        (x, y) of the star on the image, pixels: a model that varies over the field
        (``psf.varies_over_field``, a `GriddedFluxDependentPSF`) is taken there; default its
        ``reference_position`` (the grid's centre), as every call of every kind
        (`bfpsf.model.base.BFPSFModel.star_image`). A `FluxDependentPSF` is the same
        everywhere.

    Returns
    -------
    profile : galsim.InterpolatedImage
        Centred on the star (the phase is removed); scale 1 (pixel units).
    pixel_included : bool
        Always True: the pixel response is in the profile; draw with ``method='no_pixel'``
        at the same pixel scale and the same sub-pixel phase.
    """
    import galsim

    if np.ndim(flux) != 0 or not np.isfinite(flux) or flux <= 0:
        msg = (f"flux must be one positive finite number (one profile per star), "
               f"got {flux!r}")
        raise BFPSFValueError(msg, flux)
    if position is not None:
        if x is not None or y is not None:
            msg = "give the star's image position as x, y or as position=(x, y), not both"
            raise BFPSFValueError(msg, position)
        if np.shape(position) != (2,):
            msg = f"position must be (x, y), got {position!r}"
            raise BFPSFValueError(msg, position)
        x, y = position
    for name, value in (("x", x), ("y", y)):
        if value is not None and not (np.ndim(value) == 0 and np.isfinite(value)):
            msg = f"{name} must be one finite image position, pixels, got {value!r}"
            raise BFPSFValueError(msg, value)
    x_phase, y_phase = star_phases(x, y, x_phase, y_phase)
    # every PSF kind (bfpsf.model.base): a field-varying one is taken at (x, y)
    stamp = psf.star_image(flux, x, y, x_phase=x_phase, y_phase=y_phase)
    if normalise:
        stamp = stamp / flux
    image = galsim.ImageD(stamp, scale=1.0)
    # The stamp's star sits at (x_phase, y_phase) from the true centre: undo it.
    profile = galsim.InterpolatedImage(image, x_interpolant="lanczos5", normalization="flux",
                                       use_true_center=True, calculate_stepk=True,
                                       calculate_maxk=True)
    profile = profile.shift(-x_phase, -y_phase)
    return profile, True


def apply_bf_to_rendered(image_e, shifts, **redistribution_options):
    """Apply the brighter-fatter redistribution to a rendered model image.

    Parameters
    ----------
    image_e : array_like [y, x] or galsim.Image
        Model rendered with the pixel response (e.g. ``galaxy * psf`` drawn with the default
        method), in electrons, on a stamp large enough to hold the source (no charge crosses
        its edge).
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    **redistribution_options
        Passed to `bfpsf.model.redistribution.redistribute`.

    Returns
    -------
    ndarray or galsim.Image
        The image after redistribution (G15 eq. perturbPTC), same type as the input, total
        charge unchanged.
    """
    array = getattr(image_e, "array", image_e)
    result = redistribute(np.asarray(array, dtype=float), shifts, **redistribution_options)
    if array is image_e:
        return result
    import galsim

    return galsim.Image(result, bounds=image_e.bounds, wcs=image_e.wcs)


def render_stars(profile, positions, fluxes, shape, *, shifts=None, **redistribution_options):
    """Pixelised stars of a GalSim profile on an image, optionally with brighter-fatter.

    Parameters
    ----------
    profile : galsim.GSObject
        PSF without the pixel, in pixel units.
    positions : (N, 2) array_like
        (x, y) of the star centres, pixels (pixel centres at integers).
    fluxes : (N,) array_like
        Fluxes, e-.
    shape : (int, int)
        (ny, nx) of the image.
    shifts : BoundaryShifts or Calibration, optional
        If given, the whole image is redistributed once the stars are drawn.

    Returns
    -------
    ndarray [y, x]
        Noiseless charge image, e-.
    """
    import galsim

    positions = np.atleast_2d(np.asarray(positions, dtype=float))
    fluxes = np.atleast_1d(np.asarray(fluxes, dtype=float))
    if positions.shape != (fluxes.size, 2):
        msg = f"positions must be ({fluxes.size}, 2) to match the fluxes, got {positions.shape}"
        raise BFPSFInputError(msg, positions.shape)
    ny, nx = (int(n) for n in shape)
    image = galsim.ImageD(nx, ny, xmin=0, ymin=0, scale=1.0)
    for (x_0, y_0), flux in zip(positions, fluxes):
        star = profile.withFlux(float(flux))
        stamp_size = int(np.ceil(star.getGoodImageSize(1.0) / 2)) * 2 + 1
        centre = galsim.PositionI(int(np.rint(x_0)), int(np.rint(y_0)))
        full = galsim.BoundsI(centre.x - stamp_size // 2, centre.x + stamp_size // 2,
                              centre.y - stamp_size // 2, centre.y + stamp_size // 2)
        bounds = full & image.bounds
        if not bounds.isDefined():
            continue
        stamp = galsim.ImageD(full, scale=1.0)
        # The stamp's true centre is the pixel `centre`; the offset adds the star's phase.
        star.drawImage(stamp, offset=(x_0 - centre.x, y_0 - centre.y))
        image[bounds] += stamp[bounds]
    array = image.array.copy()
    if shifts is not None:
        array = redistribute(array, shifts, **redistribution_options)
    return array
