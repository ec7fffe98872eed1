"""The BF change of e1 of an elliptical PSF at one position: P(F) against SiliconSensor.

No grid and no fit: the model's P0 is the profile the spots are drawn from (Moffat, beta 3.5,
FWHM 3.45 px, sheared to e1 = -0.04, 0, +0.04, convolved with SiliconSensor's diffusion), so
what is left is the model's own. Spots are photon-shot through SiliconSensor ``lsst_e2v_50_8``
with their BF-free twins (`simulate_spots`); the measured BF change of e1 is spot minus twin,
the model's P(F) minus P(0) at each spot's flux and phase, and their slopes against peak are
compared (per 100 ke- of peak). Every shift set is applied to the same spots, so the
differences between them carry no photon noise.

Measured (slow variant, 96 spots per PSF e1 = -0.04, 0, +0.04, one-step model): the residual
e1 slope per 100 ke- (raw -2.5e-3 to -3.8e-3 +- 4e-5) and the model / raw slopes of sigma_x,
sigma_y and e1:

    shifts                                      residual e1          sigma_x    sigma_y    e1
    landing under a star (diagnostic)           -0.9e-4 to -1.3e-4   1.01-1.02  1.00-1.01  0.95-0.97
    single-pixel landing (diagnostic)           -4.4e-4 to -4.6e-4   1.00-1.01  0.98-0.99  0.82-0.88
    solver on the landing areas (diagnostic)    -0.8e-4 to -1.1e-4   1.03-1.04  1.02-1.03  0.96-0.98
    solver on the polygon areas (flats limit)   -5.9e-4 to -6.6e-4   1.08-1.09  1.04-1.05  0.74-0.84
    from flats (user path, calibration +-8 %)   -1.0e-3              1.02-1.03  0.97       0.60-0.73

GalSim's landing is not additive (`bfpsf.interop.silicon_truth.landing_under`): under a
star's charge its N boundaries sit 2.9 % and its E boundaries 0.8 % further out than the sum
of its single-pixel landing shifts. The single-pixel shifts therefore leave Y 2 % short of X
and 14 % of the e1 slope; scaled to where the boundaries sit under a star, the model follows
SiliconSensor's e1 slope to 3-5 %. The calibration's electrostatic solver keeps that balance
when given the landing areas; given the polygon areas, from which GalSim builds its flats, it
leaves 16-26 % of the e1 slope: the user path's limit on this simulator. The PSF's own
ellipticity changes the raw e1 slope by 40 % and the model follows it: the residual does not
depend on e1.
"""

import os

import numpy as np
import pytest

from test_gridded_silicon import shape_measures, star_charge

SENSOR = "lsst_e2v_50_8"
FWHM, BETA = 3.45, 3.5


def reduced_shear(e1):
    return e1 / (1 + np.sqrt(1 - e1**2))


def draw_spots(e1, peaks, n_per_level, seed=11):
    """Spots of PSF ellipticity ``e1`` with their BF-free twins, and the measured changes of
    sigma_x, sigma_y, e1, e2 (spot minus twin)."""
    os.environ["OMP_NUM_THREADS"] = "1"
    from bfpsf.validation.simulate_spots import simulate_spots

    spots = simulate_spots(sensor=SENSOR, fwhm=FWHM, beta=BETA, peaks_e=peaks,
                           n_per_level=n_per_level, stamp_size=25, g1=reduced_shear(e1),
                           seed=seed, bf_free_twin=True)
    return spots, shape_measures(spots.stamps) - shape_measures(spots.twin)


def e1_slopes(e1, spots, measured, shifts, label):
    """Slopes (per 100 ke- of peak) of the measured BF change of e1 and of the measured minus
    the model's; and the model / measured slope ratios of sigma_x, sigma_y and e1."""
    import galsim

    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma
    from bfpsf.measure.slopes import fit_bf_slope
    from bfpsf.model.psf import FluxDependentPSF

    profile = galsim.Convolve(galsim.Moffat(fwhm=FWHM, beta=BETA).shear(g1=reduced_shear(e1)),
                              galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))
    psf = FluxDependentPSF.from_galsim(profile, shifts, oversampling=2, size=25)
    rows, columns = np.mgrid[:25, :25]
    flux = spots.twin.sum(axis=(1, 2))
    bright = [psf.evaluate(columns, rows, f, x, y) for f, x, y in zip(flux, spots.x, spots.y)]
    faint = [psf.evaluate(columns, rows, 1.0, x, y) for x, y in zip(spots.x, spots.y)]
    model = shape_measures(np.array(bright)) - shape_measures(np.array(faint))
    raw = fit_bf_slope(spots.peaks, measured[2])
    left = fit_bf_slope(spots.peaks, measured[2] - model[2])
    ratios = [fit_bf_slope(spots.peaks, model[axis]).slope
              / fit_bf_slope(spots.peaks, measured[axis]).slope for axis in range(3)]
    print(f"PSF e1 {e1:+.2f}, {label}: raw e1 slope {raw.slope:+.3e} +- {raw.slope_err:.1e}, "
          f"residual {left.slope:+.3e} +- {left.slope_err:.1e}; model/raw sigma_x "
          f"{ratios[0]:.4f} sigma_y {ratios[1]:.4f} e1 {ratios[2]:.4f}")
    return raw, left, ratios


def landing_shifts():
    """Single-pixel landing shifts, and the same scaled to a star's charge (`landing_under`)."""
    from bfpsf.interop.silicon_truth import silicon_boundary_shifts

    return {"single-pixel landing": silicon_boundary_shifts(SENSOR),
            "landing under a star": silicon_boundary_shifts(SENSOR, under=star_charge())}


def check_ellipticity_coupling(results):
    """The raw e1 slope changes with the PSF's e1; the residual does not."""
    (raw_low, left_low, _), (raw_high, left_high, _) = results[0], results[-1]
    assert raw_high.slope - raw_low.slope < -5 * np.hypot(raw_high.slope_err,
                                                           raw_low.slope_err)
    assert abs(left_high.slope - left_low.slope) < 3 * np.hypot(left_high.slope_err,
                                                                left_low.slope_err)


def test_e1_slope_of_an_elliptical_psf_quick():
    """CI variant: e1 = -0.04 and +0.04, 3 levels of 6 spots, both landing shift sets."""
    shifts = landing_shifts()
    results = {label: [] for label in shifts}
    for e1 in (-0.04, 0.04):
        spots, measured = draw_spots(e1, (1e4, 4e4, 1.2e5), 6)
        for label, value in shifts.items():
            results[label].append(e1_slopes(e1, spots, measured, value, label))
    check_ellipticity_coupling(results["landing under a star"])
    for (_, left, ratios), (_, _, single) in zip(results["landing under a star"],
                                                  results["single-pixel landing"]):
        # the same spots: the two models' e1 slopes differ by the 2 % of Y (module notes)
        assert ratios[2] == pytest.approx(1.0, abs=0.08)
        assert single[2] == pytest.approx(0.86, abs=0.05)
        assert abs(left.slope) <= 2e-4 + 2 * left.slope_err


@pytest.mark.slow
def test_e1_slope_of_an_elliptical_psf(e2v_flats_calibration):
    """Three PSF ellipticities, 6 levels of 16 spots. Diagnostics: both landing shift sets; the
    electrostatic solver (the user path's calibration step) on the areas of the landing under
    a star and on SiliconSensor's polygon areas, from which its flats are built (the user
    path's limit). The user path itself: the shifts calibrated from the small flat set (its
    X/Y balance is known to +-8 %, so its e1 is not held to 2e-4 here, see
    test_gridded_silicon.py)."""
    from bfpsf.calibration.boundary_shifts import solve_boundary_shifts
    from bfpsf.interop.silicon_truth import silicon_area_coefficients

    shifts = landing_shifts()
    shifts["solver on the landing areas"] = solve_boundary_shifts(
        shifts["landing under a star"].area_quadrant(4), n_samples=0).shifts
    shifts["solver on the polygon areas (flats limit)"] = solve_boundary_shifts(
        silicon_area_coefficients(SENSOR, maxlag=4), n_samples=0).shifts
    shifts["from flats (user path)"] = e2v_flats_calibration.shifts
    results = {label: [] for label in shifts}
    for e1 in (-0.04, 0.0, 0.04):
        spots, measured = draw_spots(e1, np.geomspace(3e3, 1.2e5, 6), 16)
        for label, value in shifts.items():
            results[label].append(e1_slopes(e1, spots, measured, value, label))
    for label in shifts:
        check_ellipticity_coupling(results[label])
    for label in ("landing under a star", "solver on the landing areas"):
        for _, left, ratios in results[label]:
            assert abs(left.slope) <= 2e-4
            assert ratios[2] == pytest.approx(1.0, abs=0.06)
    for _, _, ratios in results["landing under a star"]:
        assert ratios[0] == pytest.approx(1.0, abs=0.025)
        assert ratios[1] == pytest.approx(1.0, abs=0.025)
    for _, _, ratios in results["single-pixel landing"]:
        assert ratios[1] == pytest.approx(0.98, abs=0.015)
    for _, _, ratios in results["solver on the polygon areas (flats limit)"]:
        # GalSim's flats follow its polygons, its stars its landing: 16-26 % of the e1 slope
        # is left (the same solver on the landing areas leaves 2.5-4 %)
        assert ratios[2] <= 0.9
