"""Issue 5 acceptance: P(F) against GalSim SiliconSensor (E2V) spots.

The residual size slope after P(F) must be at most 2 % of the raw BF slope in X and in Y.

Measurement. Each spot is drawn twice with identical photons, diffusion steps and noise: through
SiliconSensor, and through the same sensor with its BF switched off (`simulate_spots`
``bf_free_twin``). The size difference of the pair is the BF change of that spot with almost no
photon noise, so the residual slope (measured minus predicted BF change against peak) is known to
about 0.2 % of the raw slope from 360 spots, against 2-3 % from the sizes alone (which estimate
the same quantity: the twin has no flux dependence).

Model. The calibration is the one the SiliconSensor flats measure, in the limit of infinite flat
statistics: GalSim's pixel-area response (`silicon_area_coefficients`, what
`simulate_flats` builds the flats from) solved into boundary shifts by
`solve_boundary_shifts`, with the build-up during the exposure integrated (16 steps). P0 is fitted
from the spots of all fluxes (`fit_psf`): it includes SiliconSensor's charge diffusion (0.44 px),
which a P0 taken from the optical Moffat lacks; that alone over-predicts the BF slope by 6-9 %.
The chain through finite simulated flats adds the statistical error of their a (see the closing
note of issue 5); `tests/test_validate.py` runs it end to end.
"""

import os

import numpy as np
import pytest

from bfpsf.model.psf import FluxDependentPSF

SENSOR = "lsst_e2v_50_8"
BUILDUP_STEPS = 16


def gaussian_sizes(stamps, x, y, sigma=2.0):
    """Second moments (Mxx, Myy) with a fixed round Gaussian weight at the true centres."""
    yy, xx = np.mgrid[:stamps.shape[1], :stamps.shape[2]]
    dx = xx[None] - x[:, None, None]
    dy = yy[None] - y[:, None, None]
    weights = stamps * np.exp(-(dx**2 + dy**2) / (2 * sigma**2))
    total = weights.sum(axis=(1, 2))
    return np.array([(weights * dx**2).sum(axis=(1, 2)) / total,
                     (weights * dy**2).sum(axis=(1, 2)) / total])


def model_sizes(psf, spots):
    yy, xx = np.mgrid[:spots.stamps.shape[1], :spots.stamps.shape[2]]
    images = np.array([psf.evaluate(xx, yy, flux, x_0, y_0)
                       for x_0, y_0, flux in zip(spots.x, spots.y, spots.fluxes)])
    return gaussian_sizes(images, spots.x, spots.y)


def residual_fractions(spots, psf):
    """Residual BF slope / raw BF slope in X and Y, and their errors (paired spots)."""
    measured = gaussian_sizes(spots.stamps, spots.x, spots.y) - gaussian_sizes(
        spots.twin, spots.x, spots.y)
    static = FluxDependentPSF(psf.data, psf.shifts.scaled(0.0), origin=psf.origin,
                              oversampling=psf.oversampling)
    predicted = model_sizes(psf, spots) - model_sizes(static, spots)
    out = []
    for axis in (0, 1):
        raw = np.polyfit(spots.peaks, measured[axis], 1)[0]
        assert raw > 0
        residual, cov = np.polyfit(spots.peaks, measured[axis] - predicted[axis], 1, cov=True)
        out.append((residual[0] / raw, np.sqrt(cov[0, 0]) / raw))
    return out


@pytest.fixture(scope="module")
def flats_limit_shifts():
    from bfpsf.calibration.shifts_ei import solve_ei_shifts
    from bfpsf.interop.silicon_truth import silicon_area_coefficients

    area = silicon_area_coefficients(SENSOR, maxlag=4)
    return solve_ei_shifts(area, n_monte_carlo=0).shifts


def twin_spots(fwhm, peaks, n_per_level, seed):
    os.environ["OMP_NUM_THREADS"] = "1"
    from bfpsf.validation.simulate_spots import simulate_spots

    return simulate_spots(sensor=SENSOR, fwhm=fwhm, beta=3.0, peaks_e=peaks,
                          n_per_level=n_per_level, stamp_size=32, seed=seed, bf_free_twin=True)


def test_residual_slope_quick(flats_limit_shifts):
    """CI variant: 24 paired spots, P0 = the Moffat convolved with SiliconSensor's diffusion."""
    import galsim

    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma

    spots = twin_spots(3.5, (1e4, 6e4, 1.2e5), 8, seed=3)
    profile = galsim.Convolve(galsim.Moffat(beta=3.0, fwhm=3.5),
                              galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))
    psf = FluxDependentPSF.from_galsim(profile, flats_limit_shifts, mode="exact",
                                       buildup_steps=BUILDUP_STEPS)
    optical = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=3.5), flats_limit_shifts,
                                           mode="exact", buildup_steps=BUILDUP_STEPS)
    for axis, ((value, error), (optical_value, _)) in enumerate(
            zip(residual_fractions(spots, psf), residual_fractions(spots, optical))):
        print(f"{'xy'[axis]}: residual / raw {value:+.4f} +- {error:.4f} "
              f"(P0 without diffusion {optical_value:+.4f})")
        # Measured (seed 3): about 1 % in both axes with a 0.5 % error; 2 % is the acceptance.
        assert abs(value) < 0.02
        # The optical P0 is too sharp and over-predicts the BF (negative residual).
        assert optical_value < value - 0.02


@pytest.mark.slow
@pytest.mark.parametrize("fwhm", [3.0, 4.0])
def test_residual_slope_fitted_p0(flats_limit_shifts, fwhm):
    """Acceptance: 240 paired spots per FWHM, peaks 3-120 ke-, P0 fitted from all of them."""
    from bfpsf.model.psf_fit import fit_psf

    spots = twin_spots(fwhm, (3e3, 1e4, 3e4, 6e4, 9e4, 1.2e5), 40, seed=1)
    fit = fit_psf(list(spots.stamps), [[xy] for xy in zip(spots.x, spots.y)],
                  flats_limit_shifts, oversampling=2, size=25)
    assert fit.converged
    psf = FluxDependentPSF(fit.psf.data, flats_limit_shifts, oversampling=2, mode="exact",
                           buildup_steps=BUILDUP_STEPS)
    for axis, (value, error) in enumerate(residual_fractions(spots, psf)):
        print(f"FWHM {fwhm} {'xy'[axis]}: residual / raw {value:+.4f} +- {error:.4f}")
        assert abs(value) < 0.02


@pytest.mark.slow
def test_residual_slope_through_simulated_flats():
    """The whole chain: E2V SiliconSensor flats -> calibrate -> shifts -> P(F) (30 min).

    21 levels x 2 pairs of 384^2 flats measure a(1, 0) to about 25 %, so the residual is known
    to 10-20 % of the raw slope only (measured with seed 11: -4 +- 17 % X, -16 +- 12 % Y on 120
    pairs at FWHM 3.5). It must agree with zero within 3 sigma of the error propagated from the
    calibration (a redrawn from its errors and re-solved).
    """
    import galsim

    from bfpsf.calibration import calibrate
    from bfpsf.calibration.shifts_ei import solve_ei_shifts
    from bfpsf.interop.silicon_truth import silicon_diffusion_sigma
    from bfpsf.validation.simulate_flats import simulate_flats

    levels = [100.0, *np.linspace(1.5e5 / 20, 1.5e5, 20)]
    flats = simulate_flats(SENSOR, levels, pairs=2, size=384, nsteps=20, gain=1.5,
                           read_noise_e=5.0, seed=11)
    cal = calibrate([image for image, _, _ in flats], exptimes=[t for _, t, _ in flats],
                    maxlag=4, n_monte_carlo=0)
    spots = twin_spots(3.5, (3e3, 1e4, 3e4, 6e4, 9e4, 1.2e5), 10, seed=1)
    profile = galsim.Convolve(galsim.Moffat(beta=3.0, fwhm=3.5),
                              galsim.Gaussian(sigma=silicon_diffusion_sigma(SENSOR)))

    def residuals(shifts):
        psf = FluxDependentPSF.from_galsim(profile, shifts, mode="exact",
                                           buildup_steps=BUILDUP_STEPS)
        return np.array([value for value, _ in residual_fractions(spots, psf)])

    central = residuals(cal.shifts)
    rng = np.random.default_rng(1)
    a, a_err = np.asarray(cal.a), np.asarray(cal.a_err)
    draws = [residuals(solve_ei_shifts(a + rng.standard_normal(a.shape) * a_err,
                                             n_monte_carlo=0).shifts) for _ in range(12)]
    error = np.std(draws, axis=0, ddof=1)
    print(f"through flats: residual / raw {central} +- {error}")
    assert np.all(np.abs(central) < 3 * error)
    assert np.all(error < 0.3)
