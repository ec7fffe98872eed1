"""End-to-end calibration of GalSim SiliconSensor flats against GalSim's own truth.

Truth: `bfpsf.interop.silicon_truth.silicon_area_coefficients`, the pixel-area response to a small
charge in one pixel of an empty sensor, i.e. the zero-flux a(dx, dy) that the Astier+19 model
fits (its b term carries the flux dependence of a, which is large in GalSim: a(1, 0) of
lsst_e2v_50_8 falls by a third between 0 and 1e5 e-).

Simulation artefact, corrected exactly in the expected values: `simulate_flats` builds a flat
in ``nsteps`` increments with the pixel areas evaluated at the middle of each step; the first
step sees an empty sensor, so the covariances build up as sum_{k=1}^{n-1} (k + 1/2) = (n^2 - 1)/2
steps^2 instead of n^2 / 2: every a is low by the factor 1 - 1 / nsteps^2 at first order (4 % at
nsteps = 5, 0.25 % at 20). The quick test uses 5 steps to afford enough pixels; the slow test
uses 20.

Statistics: the gain and a(0, 0) come from the curvature of the variance, whose error per pair
is sqrt(2 / N) (0.55 % for 256 x 256). 54 pairs of 256 x 256 up to 3e5 e- (the slow ITL test)
give sigma(gain) ~ 0.2 % and sigma(a00) ~ 1 %, the least that makes "gain within 0.5 %, a(0, 0)
within 3 %" a 2.5-3 sigma requirement; the quick fixture's 27 pairs of 192 x 192 give 0.35 % and
3 %, so the quick tests ask for 3 sigma. A 100 e- pair pins the read noise, which is otherwise
degenerate with the gain.
"""

import numpy as np
import pytest

from bfpsf.calibration import calibrate
from bfpsf.calibration.ptc import PTCData, fit_ptc, summed_covariance_ptc
from bfpsf.interop.silicon_truth import silicon_area_coefficients
from bfpsf.validation.simulate_flats import simulate_flats

GAIN = 1.5
READ_NOISE = 5.0


def expected_area(sensor, nsteps, maxlag):
    """GalSim truth scaled by the midpoint-rule build-up of the simulation (module docstring)."""
    return silicon_area_coefficients(sensor, maxlag=maxlag) * (1.0 - 1.0 / nsteps**2)


def run(sensor, levels, *, pairs, size, nsteps, maxlag, seed=0, n_monte_carlo=20,
        solve_shifts=True, edge=None, **options):
    """Simulate flats with `simulate_flats` (``options`` inject effects) and calibrate them
    (``edge``: the calibration's border, default its own)."""
    flats = simulate_flats(sensor, levels, pairs=pairs, size=size, nsteps=nsteps, gain=GAIN,
                           read_noise_e=READ_NOISE, seed=seed, **options)
    return calibrate([image for image, _, _ in flats],
                     exptimes=[exptime for _, exptime, _ in flats], maxlag=maxlag,
                     n_monte_carlo=n_monte_carlo, solve_shifts=solve_shifts, edge=edge)


def assert_matches_truth(calibration, truth, lags, label, *, absolute=True):
    """Every a(dx, dy), dx, dy <= lags, the gain and a(0, 0) within 3 sigma; with
    ``absolute``, also a(0, 0) within 3 % and the gain within 0.5 % (the acceptance, which
    needs the pixels of the slow tests)."""
    measured = calibration.a[:lags + 1, :lags + 1]
    errors = calibration.a_err[:lags + 1, :lags + 1]
    pulls = (measured - truth[:lags + 1, :lags + 1]) / errors
    gain_pull = (calibration.gain - GAIN) / calibration.gain_err
    report = (f"{label}: pulls [dy, dx]\n{np.array2string(pulls, precision=2)}\n"
              f"a00 {100 * (measured[0, 0] / truth[0, 0] - 1):+.2f} % "
              f"(+- {100 * errors[0, 0] / abs(truth[0, 0]):.2f} %), "
              f"gain {100 * (calibration.gain / GAIN - 1):+.3f} % "
              f"(+- {100 * calibration.gain_err / GAIN:.3f} %)")
    print(report)
    assert np.all(np.abs(pulls) < 3), report
    assert abs(gain_pull) < 3, report
    if absolute:
        assert abs(measured[0, 0] / truth[0, 0] - 1) < 0.03, report
        assert abs(calibration.gain / GAIN - 1) < 0.005, report


# -- ITL ------------------------------------------------------------------------------------
ITL_NSTEPS = 5
ITL_LEVELS = [100.0, *np.linspace(3e5 / 26, 3e5, 26)]


@pytest.fixture(scope="module")
def itl_calibration():
    # 27 levels x 1 pair of 192 x 192, all of them used (edge 0: simulate_flats draws a
    # margin around the image and crops it, so these flats have no sensor edge; the default
    # border is tested in test_simulate_flats -k edge_border): about 17 s of GalSim on one
    # core. The gain to about
    # 0.4 % and a(0, 0) to about 2 % (1 sigma): the tests here ask for 3 sigma; the slow
    # variant has the pixels for the acceptance's 0.5 % and 3 %.
    # (4 Monte Carlo refits of the shifts: their errors are only checked to exist here)
    return run("lsst_itl_50_8", ITL_LEVELS, pairs=1, size=192, nsteps=ITL_NSTEPS, maxlag=4,
               n_monte_carlo=4, edge=0)


@pytest.mark.slow
def test_itl_area_coefficients_match_galsim_full():
    # 27 levels x 2 pairs of 256 x 256, all used (edge 0, as `itl_calibration`): about 70 s
    # of GalSim on one core. sigma(gain) ~ 0.2 % and sigma(a00) ~ 1 %, the least that makes
    # "gain within 0.5 %, a(0, 0) within 3 %" a 2.5-3 sigma requirement
    calibration = run("lsst_itl_50_8", ITL_LEVELS, pairs=2, size=256, nsteps=ITL_NSTEPS,
                      maxlag=4, edge=0)
    assert_matches_truth(calibration, expected_area("lsst_itl_50_8", ITL_NSTEPS, 4), 2,
                         "lsst_itl_50_8")


def test_itl_area_coefficients_match_galsim(itl_calibration):
    truth = expected_area("lsst_itl_50_8", ITL_NSTEPS, 4)
    assert_matches_truth(itl_calibration, truth, 2, "lsst_itl_50_8", absolute=False)
    assert itl_calibration.noise_e == pytest.approx(READ_NOISE, rel=0.1)


def test_itl_flags_are_quiet(itl_calibration):
    """No readout pedestal, no non-linearity beyond GalSim's own (< 0.3 per mil)."""
    assert not itl_calibration.pedestal.any_detected
    assert not itl_calibration.linearity.flagged
    assert itl_calibration.linearity.peak_to_peak < 1e-3
    assert not itl_calibration.turnoff_detected  # GalSim flats do not saturate


def test_itl_summed_covariances_restore_poisson(itl_calibration):
    """G15 appendix A on SiliconSensor flats: V + sum C grows as the Poisson mean."""
    table = itl_calibration.ptc
    data = PTCData(np.asarray(table["exptime"]), np.asarray(table["mean_adu"]),
                   itl_calibration.covariances_adu, itl_calibration.npix)
    result = summed_covariance_ptc(data, itl_calibration.gain)
    # raw PTC: bent by the brighter-fatter anti-correlation of the variance, many sigma
    assert result["slope_raw"] < 0.9
    # summing lags |dx|, |dy| <= 4 (all GalSim moves) restores slope 1; the sum of 81 noisy
    # lags has sigma ~ 1 %, so allow 3 sigma here (the 1 % requirement is in the slow test)
    assert abs(result["slope_summed"] - 1) < 3 * result["slope_summed_err"]


def test_itl_shifts_are_solved_and_consistent(itl_calibration):
    shifts = itl_calibration.shifts
    assert shifts is not None
    residuals = shifts.symmetry_residuals()
    assert max(residuals.values()) < 1e-12 * np.abs(itl_calibration.a).max() + 1e-20
    # the electrostatic model (6 parameters) describes every measured a within its errors
    area = shifts.area_quadrant(itl_calibration.maxlag)
    assert np.all(np.abs(area - itl_calibration.a) <= 3 * itl_calibration.a_err)
    fit = itl_calibration.shift_fit
    assert fit["electrostatic_chi2"] / fit["electrostatic_dof"] < 3
    # both solvers ran; the N/S and E/W boundaries of a charged pixel move in (physics)
    assert "ei_chi2" in fit
    m = shifts.radius
    assert shifts.north[m, m] < 0 and shifts.east[m, m] < 0
    assert np.all(np.isfinite(itl_calibration.shifts_north_err))
    assert itl_calibration.shift_samples_north.shape[1:] == shifts.shape


# -- injected effects -----------------------------------------------------------------------
EFFECT_LEVELS = np.linspace(1e4, 1.5e5, 10)


def test_injected_nonlinearity_is_flagged():
    # signal = q (1 - 1e-7 q): 1.5 % compression at 150 ke-, about 4 per mil peak to peak
    # about the best line, above the 3 per mil threshold (GalSim alone: < 0.3 per mil)
    options = dict(pairs=1, size=96, nsteps=4, maxlag=2, seed=1, solve_shifts=False)
    bent = run("lsst_itl_50_8", EFFECT_LEVELS, nonlinearity=-1e-7, **options)
    assert bent.linearity.flagged
    assert bent.linearity.peak_to_peak > 3e-3
    straight = run("lsst_itl_50_8", EFFECT_LEVELS, **options)
    assert not straight.linearity.flagged


def test_injected_readout_correlation_is_detected():
    # q'[x] = q[x] + c q[x - 1] (G15's "pedestal"): R(1, 0) = c / (1 + c^2) at every flux.
    # The intercept of a degree-2 fit over 10 pairs of 192 x 192 has sigma ~ 0.005, so
    # c = -0.05 is a 9 sigma detection (G15's -0.003 needs their ~100 pairs of 1 Mpix).
    correlation = -0.05
    calibration = run("lsst_itl_50_8", EFFECT_LEVELS, pairs=1, size=192, nsteps=4, maxlag=2,
                      seed=2, readout_correlation=correlation, solve_shifts=False)
    pedestal = calibration.pedestal
    expected = correlation / (1 + correlation**2)
    assert pedestal.detected[0, 1]
    assert abs(pedestal.value[0, 1] - expected) < 3 * pedestal.error[0, 1]
    assert pedestal.detected.sum() == 1  # and at no other lag
    assert np.all(pedestal.applied[pedestal.detected] == pedestal.value[pedestal.detected])


def test_saturation_turnoff_is_detected():
    """Wells that clip at full well: the PTC extremum is found and the pairs above it dropped."""
    rng = np.random.default_rng(5)
    full_well = 1.2e5
    levels = np.linspace(1e4, 1.6e5, 12)
    images, exptimes = [], []
    for level in levels:
        for _ in range(2):
            charge = np.minimum(rng.poisson(level, (128, 128)), full_well)
            images.append((charge + rng.normal(0, READ_NOISE, charge.shape)) / GAIN)
            exptimes.append(level * 1e-3)
    calibration = calibrate(images, exptimes=exptimes, maxlag=2, solve_shifts=False)
    assert calibration.turnoff_detected
    # in ADU: the gain of the full model on 8 pairs of 108^2 pixels is known to 3 %, and the
    # turnoff's last level is 0.4 % below the well
    assert calibration.turnoff_e / calibration.gain < full_well / GAIN
    used = np.asarray(calibration.ptc["used"])
    assert not used[levels > full_well].any() and used[levels < 0.9 * full_well].all()
    # pure Poisson below the turnoff: gain within 3 sigma (~1 % for 8 pairs of 128 x 128)
    assert abs(calibration.gain - GAIN) < 3 * calibration.gain_err


# -- E2V, slow ------------------------------------------------------------------------------
E2V_NSTEPS = 20
E2V_LEVELS = [100.0, *np.linspace(1.5e5 / 20, 1.5e5, 20)]  # a00 mu = -0.33 at the top


@pytest.mark.slow
def test_e2v_area_coefficients_match_galsim():
    """A thick sensor (a00 mu = -0.33 at 150 ke-): the full model, not the first-order fit."""
    # 21 levels x 2 pairs of 384 x 384, all used (edge 0, as `itl_calibration`), 20 steps:
    # about 10 minutes of GalSim on one core
    calibration = run("lsst_e2v_50_8", E2V_LEVELS, pairs=2, size=384, nsteps=E2V_NSTEPS,
                      maxlag=8, edge=0)
    truth = expected_area("lsst_e2v_50_8", E2V_NSTEPS, 4)
    assert_matches_truth(calibration, truth, 4, "lsst_e2v_50_8")
    table = calibration.ptc
    data = PTCData(np.asarray(table["exptime"]), np.asarray(table["mean_adu"]),
                   calibration.covariances_adu, calibration.npix)
    # G15 appendix A: V + sum of C over |dx|, |dy| <= 4 grows as the Poisson mean
    result = summed_covariance_ptc(data, calibration.gain, maxlag=4)
    assert abs(result["slope_summed"] - 1) < 0.01
    # the first-order (G15 quadratic) fit of the same pairs is biased, as the issue says
    quadratic = fit_ptc(data, model="quadratic")
    assert abs(quadratic.a[0, 0] / truth[0, 0] - 1) > 0.05
