"""Linearity fit and readout pedestal on analytic inputs.

Detection of an injected non-linearity and readout correlation in simulated flats is in
test_calibrate.py.
"""

import numpy as np
import pytest

from bfpsf.calibration import ptc
from bfpsf.calibration.linearity import DEFAULT_LINEARITY_THRESHOLD, measure_linearity
from bfpsf.calibration.pedestal import measure_pedestal, subtract_pedestal
from bfpsf.errors import BFPSFInputError, BFPSFValueError

EXPTIME = np.linspace(1.0, 60.0, 12)


def test_linear_response_is_not_flagged():
    mean = 20.0 + 1500.0 * EXPTIME  # a shutter offset is absorbed by the intercept
    linearity = measure_linearity(EXPTIME, mean)
    assert linearity.slope == pytest.approx(1500.0)
    assert linearity.intercept == pytest.approx(20.0)
    assert linearity.max_frac_residual < 1e-12
    assert not linearity.flagged


def test_quadratic_nonlinearity_is_flagged_with_the_right_size():
    signal = 1500.0 * EXPTIME
    beta = 1e-2 / signal.max()  # 1 % compression at the top
    linearity = measure_linearity(EXPTIME, signal * (1 - beta * signal))
    # the residual of a parabola about its best line: a few per mil for 1 % curvature
    assert 1e-3 < linearity.peak_to_peak < 1e-2
    assert linearity.flagged
    assert linearity.threshold == DEFAULT_LINEARITY_THRESHOLD


def test_points_past_the_turnoff_are_ignored():
    mean = 1500.0 * EXPTIME
    mean[-2:] *= 0.9  # saturated pairs
    used = np.ones(EXPTIME.size, dtype=bool)
    used[-2:] = False
    linearity = measure_linearity(EXPTIME, mean, used=used)
    assert not linearity.flagged
    assert linearity.frac_residual[-1] == pytest.approx(-0.1, rel=1e-6)


def test_linearity_needs_three_exposure_times():
    linearity = measure_linearity([5.0, 5.0, 10.0], [1e4, 1e4, 2e4])
    assert not linearity.measured and not linearity.flagged
    assert np.isnan(linearity.max_frac_residual)
    with pytest.raises(BFPSFValueError, match="threshold must be positive"):
        measure_linearity(EXPTIME, EXPTIME, threshold=0)


def correlation_data(pedestal_10, *, seed=0, npix=1e6):
    """Covariances with brighter-fatter growth and a constant correlation at (dx=1, dy=0)."""
    area = np.zeros((3, 3))
    area[0, 0], area[0, 1], area[1, 0], area[1, 1] = -2.2e-6, 0.9e-7, 3.7e-7, 1.1e-7
    gain = 1.5
    mean_adu = np.linspace(5e3, 1.2e5, 15) / gain
    noise = np.zeros_like(area)
    noise[0, 0] = 25.0
    cov = ptc.full_covariance_model(mean_adu, area, np.zeros_like(area), noise, gain)
    cov[:, 0, 1] += pedestal_10 * cov[:, 0, 0]
    counts = np.full(cov.shape, npix)
    rng = np.random.default_rng(seed)
    noisy = cov + rng.standard_normal(cov.shape) * ptc.covariance_errors(cov, counts)
    return mean_adu, noisy, counts, cov


def test_pedestal_is_measured_at_its_lag_only():
    """A degree-1 fit would be biased by the curvature of R(0, 1) (2 sigma here); degree 2
    is not."""
    # G15's R(1, 0) on the E2V-250; 15 pairs of a 2k x 2k amplifier give an error of 4e-4
    mean_adu, cov, npix, _ = correlation_data(-0.003, npix=4e6)
    pedestal = measure_pedestal(mean_adu, cov, npix)
    assert abs(pedestal.value[0, 1] + 0.003) < 3 * pedestal.error[0, 1]
    assert pedestal.detected[0, 1]
    assert pedestal.detected.sum() == 1  # no false detections at the brighter-fatter lags
    assert pedestal.value[0, 0] == 0 and not pedestal.detected[0, 0]


def test_no_pedestal_no_detection():
    mean_adu, cov, npix, _ = correlation_data(0.0, seed=3, npix=4e6)
    pedestal = measure_pedestal(mean_adu, cov, npix)
    assert not pedestal.any_detected
    np.testing.assert_array_equal(subtract_pedestal(cov, pedestal), cov)


def test_subtraction_restores_the_brighter_fatter_covariances():
    mean_adu, cov, npix, truth = correlation_data(-0.003, npix=1e12)  # (nearly) noise-free
    pedestal = measure_pedestal(mean_adu, cov, npix)
    clean = subtract_pedestal(cov, pedestal)
    without = truth.copy()
    without[:, 0, 1] -= -0.003 * truth[:, 0, 0]
    # the degree-2 fit leaves a small curvature residual of the brighter-fatter growth
    np.testing.assert_allclose(clean[:, 0, 1], without[:, 0, 1], rtol=0,
                               atol=2e-3 * np.abs(without[:, 0, 1]).max())


def test_pedestal_needs_enough_levels():
    mean_adu, cov, npix, _ = correlation_data(0.0)
    with pytest.raises(BFPSFInputError, match="needs at least 4 flux levels, got 3"):
        measure_pedestal(mean_adu[:3], cov[:3], npix[:3])


def test_pedestal_error_is_propagated_into_a():
    """Subtracting p V with p uncertain moves a(1, 0): its error must include that."""
    truth = -2.2e-6, 0.9e-7  # a(0, 0), a(1, 0) of correlation_data
    with_propagation, without = [], []
    for seed in range(20):
        mean_adu, cov, npix, _ = correlation_data(-0.01, seed=seed)
        pedestal = measure_pedestal(mean_adu, cov, npix)
        assert pedestal.detected[0, 1]  # -0.01 is a 6 sigma pedestal here
        data = ptc.PTCData(np.zeros_like(mean_adu), mean_adu, subtract_pedestal(cov, pedestal),
                           npix)
        for fit, pulls in ((ptc.fit_ptc(data, pedestal=pedestal), with_propagation),
                           (ptc.fit_ptc(data), without)):
            pulls.append((fit.a[0, 1] - truth[1]) / fit.a_err[0, 1])
    # without propagation the errors are about half the scatter (pull rms ~ 2)
    assert np.std(without) > 1.5
    assert np.std(with_propagation) < 1.4
