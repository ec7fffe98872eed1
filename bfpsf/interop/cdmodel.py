"""Conversion of boundary shifts to and from `galsim.cdmodel`.

Coefficient conventions
-----------------------
`galsim.cdmodel` (src/CDModel.cpp, ``ApplyCD``) adds to each pixel
``sum_{ix,iy} Q(x+ix, y+iy) a_t(ix, iy) (Q_00 + Q_top) / 2`` (and likewise for b, l, r),
i.e. the boundary shift times the *mean* of the two pixels. G15 (eq. scrambling_model) writes
``1/4 a^X Q (Q_00 + Q_X)``, so a^X(G15) = 2 a_X(cdmodel): GalSim's coefficients are *half*
bfpsf's (the cdmodel docstring's Antilogus et al. 2014 convention, with the sum, would be a
quarter). The mapping is a_t = a^N / 2, a_b = a^S / 2, a_r = a^E / 2, a_l = a^W / 2, all
indexed [dy + n, dx + n] as in bfpsf, with the same sign (positive: the pixel grows).
"""

import numpy as np
import galsim

from ..errors import BFPSFValueError
from ..shifts import BoundaryShifts, as_shifts

__all__ = ["shifts_to_cdmodel", "shifts_from_cdmodel"]


def shifts_to_cdmodel(shifts):
    """The `galsim.cdmodel.BaseCDModel` applying the same redistribution as ``shifts``.

    a_t = a^N / 2, a_b = a^S / 2, a_r = a^E / 2, a_l = a^W / 2 (module docstring). GalSim
    treats the image border differently (it drops a term when the pixel mirrored through the
    boundary is outside the image), so the two agree where the charge is at least radius + 1
    pixels from the border.
    """
    shifts = as_shifts(shifts)
    return galsim.cdmodel.BaseCDModel(shifts.west / 2.0, shifts.east / 2.0,
                                      shifts.south / 2.0, shifts.north / 2.0)


def shifts_from_cdmodel(cdmodel, *, rtol=1e-9):
    """`BoundaryShifts` from a `galsim.cdmodel.BaseCDModel` (e.g. `galsim.cdmodel.PowerLawCD`).

    a^N = 2 a_t and a^E = 2 a_r; a_b and a_l must follow by translation invariance
    (a_b(dx, dy) = -a_t(dx, dy + 1), a_l(dx, dy) = -a_r(dx + 1, dy)), which is what makes the
    model conserve charge.

    Raises
    ------
    BFPSFValueError
        If a_b or a_l violate translation invariance, or a_t / a_r violate parity, by more
        than ``rtol`` times the largest coefficient.
    """
    arrays = {name: np.asarray(getattr(cdmodel, name).array, dtype=float)
              for name in ("a_l", "a_r", "a_b", "a_t")}
    north, east = 2.0 * arrays["a_t"], 2.0 * arrays["a_r"]
    scale = max(np.abs(north).max(), np.abs(east).max(), 1e-300)
    shifts = BoundaryShifts(north, east, check=False)
    for name, derived in (("a_b", shifts.south), ("a_l", shifts.west)):
        worst = float(np.abs(2.0 * arrays[name] - derived).max())
        if worst > rtol * scale:
            msg = (f"cdmodel {name} is not the translation of the opposite boundary's "
                   f"coefficients (worst difference {worst / 2:.3g}); it does not conserve charge")
            raise BFPSFValueError(msg, worst)
    return BoundaryShifts(north, east, rtol=rtol)
