"""PTC fits on covariances generated from the models themselves (analytic truth).

The end-to-end checks against GalSim SiliconSensor flats are in test_calibrate.py.
"""

import numpy as np
import pytest

from bfpsf.calibration import ptc
from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.interop.silicon_truth import silicon_area_coefficients

GAIN = 1.5          # e-/ADU
READ_NOISE = 5.0    # e-


@pytest.fixture(scope="module")
def e2v_area():
    """GalSim's lsst_e2v_50_8 a(dx, dy), 1/e-, [dy, dx] for dx, dy <= 4."""
    return silicon_area_coefficients("lsst_e2v_50_8", maxlag=4)


def model_data(area, *, b=None, levels_e=None, npix=1e6, noise_seed=None, gain=GAIN):
    """PTCData from A+19 eq. 20 with optional Gaussian shot noise of the right size."""
    nlag = area.shape[0]
    levels_e = np.linspace(5e3, 1.2e5, 20) if levels_e is None else np.asarray(levels_e)
    c = np.zeros_like(area) if b is None else area * b
    noise = np.zeros_like(area)
    noise[0, 0] = READ_NOISE**2
    mean_adu = levels_e / gain
    cov = ptc.full_covariance_model(mean_adu, area, c, noise, gain)
    counts = np.full(cov.shape, float(npix))
    counts[:, 1:, 1:] *= 2  # off-axis lags average two quadrants
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        cov = cov + rng.standard_normal(cov.shape) * ptc.covariance_errors(cov, counts)
    return ptc.PTCData(np.arange(len(mean_adu), dtype=float), mean_adu, cov, counts)


def test_full_model_exact_on_noise_free_data(e2v_area):
    b = np.zeros_like(e2v_area)
    b[0, 1] = -3.4e-6  # a(1, 0) falls by a third at 1e5 e-, as GalSim's E2V sensor does
    fit = ptc.fit_ptc(model_data(e2v_area, b=b), model="full")
    assert fit.gain == pytest.approx(GAIN, rel=1e-6)
    assert fit.noise_e == pytest.approx(READ_NOISE, rel=1e-4)
    np.testing.assert_allclose(fit.a, e2v_area, rtol=1e-4, atol=1e-12)
    assert fit.b[0, 1] == pytest.approx(-3.4e-6, rel=1e-3)
    assert not fit.turnoff_detected and fit.used.all()


def test_first_order_fit_is_biased_on_a_thick_sensor(e2v_area):
    """The issue's statement: a00 mu ~ -0.2 at 100 ke- biases G15's quadratic a00 and gain."""
    data = model_data(e2v_area)
    full = ptc.fit_ptc(data, model="full")
    quadratic = ptc.fit_ptc(data, model="quadratic")
    exponential = ptc.fit_ptc(data, model="exponential")
    assert full.a[0, 0] == pytest.approx(e2v_area[0, 0], rel=1e-4)
    # the quadratic ignores the mu^3 term: > 10 % off in a00 and ~1 % in gain here
    assert abs(quadratic.a[0, 0] / e2v_area[0, 0] - 1) > 0.1
    assert 0.005 < abs(quadratic.gain / GAIN - 1) < 0.03
    # A+19 eq. 16 resums a00 but not the neighbours' a*a terms: close, but not exact
    assert abs(exponential.gain / GAIN - 1) < 3e-3
    assert abs(exponential.a[0, 0] / e2v_area[0, 0] - 1) < 0.03


@pytest.mark.parametrize("seed", [1, 2])
def test_full_model_errors_cover_the_scatter(e2v_area, seed):
    """With shot noise of the right size every a lies within 4 sigma and chi2/ndof ~ 1."""
    fit = ptc.fit_ptc(model_data(e2v_area, npix=2.5e5, noise_seed=seed), model="full")
    pulls = (fit.a - e2v_area) / fit.a_err
    assert np.all(np.abs(pulls) < 4), pulls
    assert abs(fit.gain - GAIN) < 4 * fit.gain_err
    assert 0.8 < fit.chi2 / fit.ndof < 1.2


def test_exponential_model_recovers_its_own_curve():
    a00, gain, noise_e2 = -2.2e-6, 1.3, 30.0
    mean_adu = np.linspace(1e3, 1.2e5, 15) / gain
    variance = ptc.exponential_variance(mean_adu, a00, gain, noise_e2)
    fit = ptc.fit_exponential_ptc(mean_adu, variance, variance * 1e-3)
    assert fit["gain"] == pytest.approx(gain, rel=1e-6)
    assert fit["a00"] == pytest.approx(a00, rel=1e-5)
    assert fit["noise_e2"] == pytest.approx(noise_e2, rel=1e-3)


def test_turnoff_is_detected_from_the_variance_drop(e2v_area):
    data = model_data(e2v_area, levels_e=np.linspace(5e3, 1.8e5, 24))
    full_well = 1.4e5
    cov = data.cov_adu.copy()
    # Past full well the wells clip: the variance collapses (and correlations with it).
    above = data.mean_adu * GAIN > full_well
    cov[above] *= np.exp(-(data.mean_adu[above] * GAIN - full_well) / 5e3)[:, None, None]
    fit = ptc.fit_ptc(data.with_covariances(cov), model="full")
    assert fit.turnoff_detected
    assert not fit.used[above].any()
    assert fit.turnoff_e <= full_well
    assert fit.a[0, 0] == pytest.approx(e2v_area[0, 0], rel=1e-3)


def test_no_turnoff_without_a_fall():
    used, detected = ptc.detect_turnoff([1, 2, 3, 4], [1.0, 2.0, 3.0, 2.999], [0.01] * 4)
    assert used.all() and not detected


def test_summed_covariances_restore_a_linear_ptc(e2v_area):
    """G15 appendix A: with the sum rule, V + sum C is the Poisson variance."""
    # e2v truth a sums to zero over the full plane (charge conservation) to ~1e-11 of a00
    data = model_data(e2v_area)
    result = ptc.summed_covariance_ptc(data, GAIN)
    assert result["slope_raw"] < 0.85  # the raw PTC bends strongly
    assert result["slope_summed"] == pytest.approx(1.0, abs=0.01)
    assert result["max_frac_deviation"] < 0.01


def test_ptc_table_units_and_lags(e2v_area):
    data = model_data(e2v_area)
    table = ptc.ptc_table(data, GAIN)
    assert table["mean_e"].description == "electron"
    assert str(table["mean_adu"].unit) == "adu"
    np.testing.assert_array_equal(table["cov10_adu"], data.cov_adu[:, 0, 1])  # dx=1, dy=0
    np.testing.assert_array_equal(table["cov01_adu"], data.cov_adu[:, 1, 0])
    np.testing.assert_allclose(table["mean_e"], data.mean_adu * GAIN)


def test_bad_inputs_raise_clear_errors(e2v_area):
    data = model_data(e2v_area, levels_e=[1e4, 2e4, 3e4])
    with pytest.raises(BFPSFValueError, match="model must be one of"):
        ptc.fit_ptc(data, model="linear")
    with pytest.raises(BFPSFInputError, match="needs at least 4 pairs below the turnoff, got 3"):
        ptc.fit_ptc(data, model="full")
    with pytest.raises(BFPSFInputError, match="no flat pairs"):
        ptc.stack_pairs([])


def exact_build_up(area, mean_e, size=64):
    """C(dx, dy) of the b = 0 build-up dC/dmu = 1 + 2 a*C: C = (exp(2 a mu) - 1) / (2 a) per
    Fourier mode, on a torus big enough for the lags to decay; [pair, dy, dx] in e-^2."""
    nlag = area.shape[0]
    plane = np.zeros((size, size))
    for dy in range(-nlag + 1, nlag):
        for dx in range(-nlag + 1, nlag):
            plane[dy % size, dx % size] = area[abs(dy), abs(dx)]
    spectrum = np.real(np.fft.fft2(plane))
    exact = []
    for mu in mean_e:
        modes = mu * np.expm1(2 * spectrum * mu) / (2 * spectrum * mu)
        exact.append(np.real(np.fft.ifft2(modes))[:nlag, :nlag])
    return np.array(exact)


def test_full_model_sums_the_exact_build_up(e2v_area):
    """A+19 eq. 20 printed to a*a*a misses ~1e-3 of C00 at a00 mu = -0.33; six powers do not."""
    mean_e = np.array([5e4, 1e5, 1.5e5])
    exact = exact_build_up(e2v_area, mean_e)
    zero = np.zeros_like(e2v_area)
    series = ptc.full_covariance_model(mean_e, e2v_area, zero, zero, 1.0)
    printed = ptc.full_covariance_model(mean_e, e2v_area, zero, zero, 1.0, order=3)
    assert np.max(np.abs(series / exact - 1)[:, 0, 0]) < 1e-5
    # off the origin the powers of a are truncated at maxlag (as in A+19 and cp_pipe): a*a
    # beyond lag 4 is dropped before the next power, a 1e-3 effect on C(dx, dy) at 150 ke-,
    # far below its shot noise (C(1, 0) / V ~ 1e-2 measured to ~1e-3 per Mpix pair)
    np.testing.assert_allclose(series[:, :3, :3], exact[:, :3, :3], rtol=2e-3)
    assert np.abs(printed / exact - 1)[-1, 0, 0] > 5e-4


def _full_plane(quadrant):
    """The full plane of lags (-n..n)^2 of a quadrant-averaged [dy, dx] table (mirror-symmetric)."""
    n = quadrant.shape[0] - 1
    index = np.abs(np.arange(-n, n + 1))
    return quadrant[np.ix_(index, index)]


def test_full_model_is_a19_eq20_as_printed(e2v_area):
    """A+19 eq. 20 written out literally, with its convolutions as 2-D convolutions of the full
    planes of lags (scipy), independent of the model's convolution tensor and series:

        C = mu/g [delta + a mu g + 2/3 (a*a + ab) (mu g)^2 + 1/6 (2 a*a*a + 5 a*ab) (mu g)^3]
            + n / g^2

    At ``order=3`` the model is that expression to rounding. The model keeps each power of a
    to the measured lags (a*a beyond them is not carried into a*a*a), so a is non-zero here
    only at lags <= 1 of a table to lag 3: no power reaches beyond the table."""
    from scipy.signal import convolve2d

    rng = np.random.default_rng(11)
    area = np.zeros((4, 4))
    area[:2, :2] = e2v_area[:2, :2]
    b = np.zeros_like(area)
    b[:2, :2] = rng.uniform(-2e-6, 2e-6, (2, 2))
    noise = np.zeros_like(area)
    noise[0, 0], noise[0, 1] = READ_NOISE**2, 3.0
    n = area.shape[0] - 1

    def quadrant_of(plane):
        centre = (plane.shape[0] - 1) // 2
        return plane[centre:centre + n + 1, centre:centre + n + 1]

    full_a, full_ab = _full_plane(area), _full_plane(area * b)
    a_a = convolve2d(full_a, full_a)
    a_a_a = convolve2d(a_a, full_a)
    a_ab = convolve2d(full_a, full_ab)
    delta = np.zeros_like(area)
    delta[0, 0] = 1.0
    mean_e = np.array([2e4, 6e4, 1.2e5])
    literal = np.array([
        mu * delta + area * mu**2
        + 2.0 / 3.0 * (quadrant_of(a_a) + area * b) * mu**3
        + 1.0 / 6.0 * (2.0 * quadrant_of(a_a_a) + 5.0 * quadrant_of(a_ab)) * mu**4
        + noise for mu in mean_e]) / GAIN**2
    model = ptc.full_covariance_model(mean_e / GAIN, area, area * b, noise, GAIN, order=3)
    np.testing.assert_allclose(model, literal, rtol=1e-12, atol=1e-12 * literal[:, 0, 0].max())
    # the b part is visible at this precision: 0.5 % of C(1, 0) at 1.2e5 e-
    without_b = ptc.full_covariance_model(mean_e / GAIN, area, 0 * area, noise, GAIN, order=3)
    assert np.abs(model - without_b)[-1].max() > 1e-3 * np.abs(model[-1, 0, 1])


def test_full_model_jacobian_matches_finite_differences(e2v_area):
    """The analytic Jacobian of the fit against central differences of the model itself, so
    a factor changed in one and not the other cannot pass."""
    from bfpsf.calibration.ptc_full import _full_model_jacobian, b_term_mask

    area = e2v_area[:3, :3]
    c = area * 1e-6
    noise = np.zeros_like(area)
    noise[0, 0] = READ_NOISE**2
    mean_adu = np.array([1e4, 5e4, 8e4]) / GAIN
    mask = b_term_mask("all", area.shape[0])
    jac_a, jac_c, jac_n, jac_g = _full_model_jacobian(mean_adu, area, c, noise, GAIN, mask)

    def model(a=area, c=c, gain=GAIN):
        return ptc.full_covariance_model(mean_adu, a, c, noise, gain).reshape(len(mean_adu), -1)

    for k in range(area.size):
        step = np.zeros(area.size)
        step[k] = 1e-3 * np.abs(area).max()
        step = step.reshape(area.shape)
        numeric = (model(a=area + step) - model(a=area - step)) / (2 * step.max())
        np.testing.assert_allclose(jac_a[:, :, k], numeric, rtol=1e-5,
                                   atol=1e-6 * np.abs(numeric).max())
        numeric_c = (model(c=c + step * 1e-6) - model(c=c - step * 1e-6)) / (2e-6 * step.max())
        np.testing.assert_allclose(jac_c[:, :, k], numeric_c, rtol=1e-5,
                                   atol=1e-6 * np.abs(numeric_c).max())
