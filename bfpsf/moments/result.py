"""The result of an adaptive-moments measurement: `Moments`, its bit flags, and the conversion
from GalSim's HSM (``galsim.hsm.FindAdaptiveMom``); the estimator is `bfpsf.moments.adaptive`."""

from dataclasses import dataclass

import numpy as np

__all__ = ["Moments", "MomentsFlag", "flag_string", "moments_from_hsm"]


class MomentsFlag:
    """Bit flags of an adaptive-moments measurement (combine with ``|``).

    ``NO_CONVERGENCE`` : not converged within ``max_iter`` iterations (values are those of the
    last iteration). ``EDGE`` : the 3-sigma ellipse of the matched Gaussian crosses the stamp
    edge, or the centroid left the stamp. ``NONPOSITIVE_FLUX`` : the weighted flux ``A`` is not
    positive (empty or negative stamp). ``SATURATED`` : a pixel inside the 3-sigma ellipse is at
    or above ``saturation``. ``TOO_FEW_PIXELS`` : fewer than 6 usable pixels (6 parameters:
    amplitude, centroid, three moments). ``BAD_PIXELS`` : the stamp holds non-finite pixels
    (they are masked, the measurement uses the others). ``NOT_POSITIVE_DEFINITE`` : the moment
    matrix became non-positive-definite or grew beyond the stamp (measurement failed).
    ``UNDERSAMPLED`` : the weight collapsed onto one pixel (minor semi-axis^2 below 0.01
    pixel^2): an object narrower than ~0.7 pixel centred near a pixel centre has no
    adaptive-moment solution (HSM fails there too; `bfpsf.moments.adaptive`, "Undersampled
    objects"); measurement failed. Bit 32768: 128-16384 are `SourceFlag`'s.
    """

    NO_CONVERGENCE = 1
    EDGE = 2
    NONPOSITIVE_FLUX = 4
    SATURATED = 8
    TOO_FEW_PIXELS = 16
    BAD_PIXELS = 32
    NOT_POSITIVE_DEFINITE = 64
    UNDERSAMPLED = 32768

    #: flags after which the moments are NaN (no measurement at all)
    FATAL = NONPOSITIVE_FLUX | TOO_FEW_PIXELS | NOT_POSITIVE_DEFINITE | UNDERSAMPLED

    NAMES = {
        1: "no_convergence",
        2: "edge",
        4: "nonpositive_flux",
        8: "saturated",
        16: "too_few_pixels",
        32: "bad_pixels",
        64: "not_positive_definite",
        32768: "undersampled",
    }


def flag_string(flags):
    """Readable form of moment flags: names joined by ``'|'``, ``'ok'`` for 0.

    Parameters
    ----------
    flags : int or array of int

    Returns
    -------
    str or ndarray of str
    """
    flags_array = np.asarray(flags)
    if flags_array.ndim == 0:
        value = int(flags_array)
        if value == 0:
            return "ok"
        names = [name for bit, name in MomentsFlag.NAMES.items() if value & bit]
        unknown = value & ~sum(MomentsFlag.NAMES)
        if unknown:
            names.append(f"unknown({unknown})")
        return "|".join(names)
    return np.array([flag_string(value) for value in flags_array.ravel()],
                    dtype=object).reshape(flags_array.shape)


@dataclass(frozen=True)
class Moments:
    """Adaptive moments of one stamp (scalars) or of a stack (arrays of equal length).

    Attributes
    ----------
    mxx, myy, mxy : float or ndarray
        Second moments of the matched elliptical Gaussian, pixel^2 (x = column, y = row).
    x, y : float or ndarray
        Centroid, pixels, 0-based stamp coordinates with pixel centres at integers.
    amplitude : float or ndarray
        Central value of the matched Gaussian, ``flux / (2 pi sigma^2)``, stamp units per pixel.
    flux : float or ndarray
        Total flux of the matched Gaussian, ``2 sum w I`` (HSM's ``moments_amp``), stamp units.
    sigma : float or ndarray
        ``(Mxx Myy - Mxy^2)^(1/4)``, pixels: G15's image quality IQ.
    n_iter : int or ndarray
        Iterations used.
    flags : int or ndarray
        `MomentsFlag` bits; 0 is a clean measurement.
    """

    mxx: object
    myy: object
    mxy: object
    x: object
    y: object
    amplitude: object
    flux: object
    sigma: object
    n_iter: object
    flags: object

    @property
    def flag_string(self):
        """Readable flags (`flag_string`)."""
        return flag_string(self.flags)

    @property
    def sigma_x(self):
        """sqrt(Mxx), pixels: the width along x (G15 section 3.2)."""
        return np.sqrt(self.mxx)

    @property
    def sigma_y(self):
        """sqrt(Myy), pixels: the width along y (G15 section 3.2)."""
        return np.sqrt(self.myy)

    @property
    def ok(self):
        """True where no flag is set."""
        return np.asarray(self.flags) == 0

    def __getitem__(self, index):
        """Select objects of a batch result (index, slice or mask)."""
        return Moments(**{name: np.asarray(getattr(self, name))[index]
                          for name in self.__dataclass_fields__})

    def __len__(self):
        return np.size(self.flags)


def moments_from_hsm(shape_data, bounds_origin=(1, 1)):
    """Convert a `galsim.hsm.ShapeData` to ``(mxx, myy, mxy, x, y)`` in bfpsf conventions.

    Parameters
    ----------
    shape_data : galsim.hsm.ShapeData
        Output of ``galsim.hsm.FindAdaptiveMom``.
    bounds_origin : tuple of int, optional
        ``(xmin, ymin)`` of the GalSim image measured (default (1, 1), GalSim's default for an
        image made from a numpy array).

    Returns
    -------
    tuple of float
        ``mxx, myy, mxy`` (pixel^2) and ``x, y`` (0-based pixels).
    """
    sigma = shape_data.moments_sigma
    e1 = shape_data.observed_shape.e1
    e2 = shape_data.observed_shape.e2
    scale = sigma**2 / np.sqrt(1.0 - e1**2 - e2**2)
    return (scale * (1.0 + e1), scale * (1.0 - e1), scale * e2,
            shape_data.moments_centroid.x - bounds_origin[0],
            shape_data.moments_centroid.y - bounds_origin[1])
