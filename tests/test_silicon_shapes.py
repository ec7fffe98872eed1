"""The BF change of e1 of an elliptical PSF at one position: P(F) against SiliconSensor.

No grid and no fit: the model's P0 is the profile the spots are drawn from (Moffat, beta 3.5,
FWHM 3.45 px, sheared to e1 = -0.04, 0, +0.04, convolved with SiliconSensor's diffusion), so
what is left is the model's own. Spots are photon-shot through SiliconSensor ``lsst_e2v_50_8``
with their BF-free twins (`simulate_spots`); the measured BF change of e1 is spot minus twin,
the model's P(F) minus P(0) at each spot's flux and phase, and their slopes against peak are
compared (per 100 ke- of peak).

Measured (slow variant, 96 spots per e1, landing shifts, one-step model):

    PSF e1    raw e1 slope        residual e1 slope    model / raw: sigma_x, sigma_y, e1
    -0.04     -2.55e-3 +- 4e-5    -4.7e-4 +- 4e-5      1.000  0.978  0.82
     0.00     -3.14e-3            -4.4e-4              1.007  0.980  0.86
    +0.04     -3.77e-3            -4.5e-4              1.008  0.986  0.88

The PSF's own ellipticity changes the raw e1 slope by 40 % and the model follows it: the
residual does not depend on e1. The residual is the X/Y split of the slopes (Y 2 % short
of X with the landing shifts), which the gridded acceptance (test_gridded_silicon.py) finds
too: it is not made by the grid. The same spots with the shifts calibrated from the small flat
set leave -1.0e-3 (X +3 %, Y -3 %), within its calibration error.
"""

import os

import numpy as np
import pytest

from test_gridded_silicon import shape_measures

SENSOR = "lsst_e2v_50_8"
FWHM, BETA = 3.45, 3.5


def reduced_shear(e1):
    return e1 / (1 + np.sqrt(1 - e1**2))


def e1_slopes(e1, shifts, peaks, n_per_level, seed=11):
    """Slopes (per 100 ke- of peak) of the measured BF change of e1 and of the measured minus
    the model's; and the model / measured slope ratios of sigma_x, sigma_y and e1."""
    import galsim

    os.environ["OMP_NUM_THREADS"] = "1"
    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma
    from bfpsf.measure.slopes import fit_bf_slope
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.validation.simulate_spots import simulate_spots

    spots = simulate_spots(sensor=SENSOR, fwhm=FWHM, beta=BETA, peaks_e=peaks,
                           n_per_level=n_per_level, stamp_size=25, g1=reduced_shear(e1),
                           seed=seed, bf_free_twin=True)
    profile = galsim.Convolve(galsim.Moffat(fwhm=FWHM, beta=BETA).shear(g1=reduced_shear(e1)),
                              galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))
    psf = FluxDependentPSF.from_galsim(profile, shifts, oversampling=2, size=25)
    rows, columns = np.mgrid[:25, :25]
    flux = spots.twin.sum(axis=(1, 2))
    bright = [psf.evaluate(columns, rows, f, x, y) for f, x, y in zip(flux, spots.x, spots.y)]
    faint = [psf.evaluate(columns, rows, 1.0, x, y) for x, y in zip(spots.x, spots.y)]
    model = shape_measures(np.array(bright)) - shape_measures(np.array(faint))
    measured = shape_measures(spots.stamps) - shape_measures(spots.twin)
    raw = fit_bf_slope(spots.peaks, measured[2])
    left = fit_bf_slope(spots.peaks, measured[2] - model[2])
    ratios = [fit_bf_slope(spots.peaks, model[axis]).slope
              / fit_bf_slope(spots.peaks, measured[axis]).slope for axis in range(3)]
    print(f"PSF e1 {e1:+.2f}: raw e1 slope {raw.slope:+.3e} +- {raw.slope_err:.1e}, residual "
          f"{left.slope:+.3e} +- {left.slope_err:.1e}; model/raw sigma_x {ratios[0]:.4f} "
          f"sigma_y {ratios[1]:.4f} e1 {ratios[2]:.4f}")
    return raw, left, ratios


def check_ellipticity_coupling(results):
    """The raw e1 slope changes with the PSF's e1; the residual does not."""
    (raw_low, left_low, _), (raw_high, left_high, _) = results[0], results[-1]
    assert raw_high.slope - raw_low.slope < -5 * np.hypot(raw_high.slope_err,
                                                           raw_low.slope_err)
    assert abs(left_high.slope - left_low.slope) < 3 * np.hypot(left_high.slope_err,
                                                                left_low.slope_err)


def test_e1_slope_of_an_elliptical_psf_quick():
    """CI variant: e1 = -0.04 and +0.04, 3 levels of 6 spots, landing shifts."""
    from bfpsf.interop.silicon_truth import silicon_boundary_shifts

    shifts = silicon_boundary_shifts(SENSOR)
    results = [e1_slopes(e1, shifts, (1e4, 4e4, 1.2e5), 6) for e1 in (-0.04, 0.04)]
    check_ellipticity_coupling(results)
    for _, _, ratios in results:
        # Y 2 % short of X leaves 15 % of the e1 slope (module notes); without BF term: 0
        assert ratios[2] == pytest.approx(0.85, abs=0.1)


@pytest.mark.slow
@pytest.mark.parametrize("source", ["landing", "from flats"])
def test_e1_slope_of_an_elliptical_psf(source, e2v_flats_calibration):
    from bfpsf.interop.silicon_truth import silicon_boundary_shifts

    shifts = (silicon_boundary_shifts(SENSOR) if source == "landing"
              else e2v_flats_calibration.shifts)
    results = [e1_slopes(e1, shifts, np.geomspace(3e3, 1.2e5, 6), 16)
               for e1 in (-0.04, 0.0, 0.04)]
    check_ellipticity_coupling(results)
    if source == "landing":
        for _, _, ratios in results:
            assert ratios[0] == pytest.approx(1.0, abs=0.015)
            assert ratios[1] == pytest.approx(0.98, abs=0.015)
