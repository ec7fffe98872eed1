"""bfpsf: brighter-fatter aware PSF models.

Flat-field pairs are turned into pixel-boundary shifts a^X_ij (Guyonnet et al. 2015, "G15"),
and the charge redistribution they imply is folded into a flux-dependent PSF
P(F) = P0 + F R[P0] usable in photutils and GalSim.

The public names below are imported lazily, so ``import bfpsf`` stays fast and does not load
GalSim or photutils until they are needed.
"""

import importlib

__version__ = "0.1.0.dev0"

# public name -> module that defines it
_EXPORTS = {
    "BoundaryShifts": "bfpsf.shifts",
    "calibrate": "bfpsf.calibration",
    "Calibration": "bfpsf.calibration.product",
    "redistribute": "bfpsf.model.redistribution",
    "correct": "bfpsf.model.redistribution",
    "adaptive_moments": "bfpsf.measure.moments",
    "Moments": "bfpsf.measure.moments",
    "FluxDependentPSF": "bfpsf.model.psf",
    "GriddedFluxDependentPSF": "bfpsf.model.gridded",
    "solve_boundary_shifts": "bfpsf.calibration.coefficients",
    "adaptive_moments_batch": "bfpsf.measure.moments",
    "measure_sources": "bfpsf.measure.sources",
    "BFSensor": "bfpsf.interop.galsim",
    "silicon_boundary_shifts": "bfpsf.interop.galsim",
    "draw_with_bf": "bfpsf.interop.galsim",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name):
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'bfpsf' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
