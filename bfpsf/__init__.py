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
    "DetectorCalibration": "bfpsf.calibration.detector",
    "read_calibration": "bfpsf.calibration.detector",
    "calibrate_from_ptc": "bfpsf.calibration",
    "redistribute": "bfpsf.model.redistribution",
    "correct": "bfpsf.model.inverse",
    "adaptive_moments": "bfpsf.moments.adaptive",
    "Moments": "bfpsf.moments.result",
    "FluxDependentPSF": "bfpsf.model.psf",
    "GriddedFluxDependentPSF": "bfpsf.model.gridded",
    "solve_boundary_shifts": "bfpsf.calibration.boundary_shifts",
    "adaptive_moments_batch": "bfpsf.moments.adaptive",
    "measure_sources": "bfpsf.measure.sources",
    "BFSensor": "bfpsf.interop.galsim_sensor",
    "silicon_boundary_shifts": "bfpsf.interop.silicon_truth",
    "draw_with_bf": "bfpsf.interop.galsim_sensor",
    # the path of a user's own data: flats -> calibration -> PSF -> photometry and shapes
    "fit_psf": "bfpsf.model.psf_fit",
    "prepare_image": "bfpsf.measure.prepare",
    "psf_from_images": "bfpsf.workflow",
    "estimate_sky": "bfpsf.measure.sky",
    "BFPSFModel": "bfpsf.model.base",
    "psf_photometry": "bfpsf.measure.photometry",
    "bf_slopes": "bfpsf.measure.slopes",
    "fit_bf_slope": "bfpsf.measure.slopes",
    "to_galsim": "bfpsf.model.galsim_profile",
    "render_stars": "bfpsf.model.galsim_profile",
    "make_psf_photometry": "bfpsf.interop.photutils",
    "write_psf": "bfpsf.model.product",
    "read_psf": "bfpsf.model.product",
    "read_measured_area": "bfpsf.calibration.measured",
    "measured_path": "bfpsf.data",
    "measured_sets": "bfpsf.data",
    "validate": "bfpsf.validation.validate",
    "exact_boundary_density": "bfpsf.model.density",
    "redistribute_buildup": "bfpsf.model.buildup",
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
