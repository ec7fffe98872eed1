"""Covariances of flat-pair differences: exactness against direct sums, the quadrant
convention of DESIGN.md, and the sigma-clipping bias correction."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import correlate

from bfpsf.calibration.covariance import (
    PairCovariance,
    clip_variance_factor,
    covariance_map,
    fold_quadrants,
    pair_covariance,
)
from bfpsf.calibration.flats import pair_flats, read_flats
from bfpsf.errors import BFPSFInputError, BFPSFValueError


def direct_covariance_map(image, good, maxlag):
    """C(dx, dy) = Cov(d[y, x], d[y + dy, x + dx]) over pairs of good pixels, by explicit
    shifted products (no FFT); indexed [dy + m, dx + m]."""
    ny, nx = image.shape
    m = maxlag
    cov = np.zeros((2 * m + 1, 2 * m + 1))
    npix = np.zeros((2 * m + 1, 2 * m + 1), dtype=int)
    for dy in range(-m, m + 1):
        for dx in range(-m, m + 1):
            ys, xs = slice(max(0, -dy), ny - max(0, dy)), slice(max(0, -dx), nx - max(0, dx))
            ys2 = slice(ys.start + dy, ys.stop + dy)
            xs2 = slice(xs.start + dx, xs.stop + dx)
            both = good[ys, xs] & good[ys2, xs2]
            first, second = image[ys, xs][both], image[ys2, xs2][both]
            cov[dy + m, dx + m] = np.mean(first * second) - first.mean() * second.mean()
            npix[dy + m, dx + m] = both.sum()
    return cov, npix


def correlated_noise(rng, shape, kernel):
    """White noise correlated by ``kernel``: out[y, x] = sum_ij kernel[i, j] n[y + i - 1, x + j - 1]."""
    return correlate(rng.normal(size=shape), kernel, mode="wrap")


#: Anisotropic kernel: out[y, x] = n[y, x] + 0.3 n[y, x + 1] + 0.6 n[y + 1, x + 1].
#: Then, in units of var(n): C(1, 1) = 0.6 (n[y+1, x+1] shared), C(1, -1) = 0 (nothing
#: shared), C(1, 0) = 0.3, C(0, 1) = 0.3 * 0.6 = 0.18, C(0, 0) = 1 + 0.09 + 0.36:
#: (dx, dy) and (dx, -dy) differ, and so do (1, 0) and (0, 1).
DIAGONAL_KERNEL = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.3], [0.0, 0.0, 0.6]])
DIAGONAL_TRUTH = {(1, 1): 0.6, (1, -1): 0.0, (-1, 1): 0.0, (1, 0): 0.3, (0, 1): 0.18,
                  (0, 0): 1.45}


@pytest.mark.parametrize("sparse", [True, False])
def test_covariance_map_equals_direct_sums_with_mask(sparse):
    rng = np.random.default_rng(0)
    image = 5.0 + correlated_noise(rng, (70, 83), DIAGONAL_KERNEL)
    good = rng.random(image.shape) > 0.03
    good[:, 17] = False
    good[40:44, 50:53] = False
    cov, npix = covariance_map(image, good, 6, sparse=sparse, precision="double")
    expected_cov, expected_npix = direct_covariance_map(image, good, 6)
    np.testing.assert_array_equal(npix, expected_npix)
    np.testing.assert_allclose(cov, expected_cov, rtol=0, atol=1e-10 * expected_cov[6, 6])


def test_single_precision_is_accurate_to_1e6_of_the_variance():
    rng = np.random.default_rng(1)
    image = 1e4 + 100 * correlated_noise(rng, (256, 256), DIAGONAL_KERNEL)
    good = rng.random(image.shape) > 0.01
    double, double_npix = covariance_map(image, good, 8, precision="double")
    single, single_npix = covariance_map(image, good, 8, precision="single")
    np.testing.assert_array_equal(single_npix, double_npix)  # counts stay exact
    # float32 FFT of the centred image: rounding ~1e-7 of the variance, far below the
    # statistical error 1/sqrt(N) = 4e-3 of the variance here.
    np.testing.assert_allclose(single, double, rtol=0, atol=1e-6 * double[8, 8])


def test_quadrant_sign_convention_on_anisotropic_noise():
    rng = np.random.default_rng(2)
    image = correlated_noise(rng, (512, 512), DIAGONAL_KERNEL)
    good = np.ones(image.shape, dtype=bool)
    cov, npix = covariance_map(image, good, 2, precision="double")
    m = 2
    # the FFT map against one explicit product, DESIGN.md: Cov(d[y, x], d[y + dy, x + dx])
    centred = image - image.mean()
    explicit_11 = np.mean(centred[:-1, :-1] * centred[1:, 1:])   # (dx, dy) = (1, 1)
    explicit_1m1 = np.mean(centred[1:, :-1] * centred[:-1, 1:])  # (dx, dy) = (1, -1)
    assert cov[m + 1, m + 1] == pytest.approx(explicit_11, rel=1e-2)
    assert cov[m - 1, m + 1] == pytest.approx(explicit_1m1, abs=1e-2 * explicit_11)
    # and both against the analytic truth, within 4 statistical errors (1/sqrt(N) * var)
    error = 4 * DIAGONAL_TRUTH[(0, 0)] / np.sqrt(image.size)
    for (dx, dy), value in DIAGONAL_TRUTH.items():
        assert abs(cov[m + dy, m + dx] - value) < error, (dx, dy)
    # the folded table combines (1, 1) and (1, -1); the axes are not mixed: R(1,0) != R(0,1)
    folded, folded_npix = fold_quadrants(cov, npix)
    expected = (cov[m + 1, m + 1] * npix[m + 1, m + 1] + cov[m - 1, m + 1] * npix[m - 1, m + 1]) \
        / (npix[m + 1, m + 1] + npix[m - 1, m + 1])
    assert folded[1, 1] == pytest.approx(expected, rel=1e-12)
    assert folded_npix[1, 1] == npix[m + 1, m + 1] + npix[m - 1, m + 1]
    assert folded[0, 1] == pytest.approx(cov[m, m + 1]) and folded[1, 0] == cov[m + 1, m]
    assert abs(folded[1, 1] - (0.6 + 0.0) / 2) < error


def test_pair_covariance_equals_direct_computation():
    rng = np.random.default_rng(3)
    shape = (96, 80)
    flat1 = 2.0e4 + 140 * correlated_noise(rng, shape, DIAGONAL_KERNEL)
    flat2 = 2.04e4 + 140 * correlated_noise(rng, shape, DIAGONAL_KERNEL)
    mask = rng.random(shape) < 0.02
    result = pair_covariance(flat1, flat2, mask=mask, maxlag=5, clip_nsigma=None,
                             precision="double")
    good = ~mask
    mean1, mean2 = flat1[good].mean(), flat2[good].mean()
    mean = 0.5 * (mean1 + mean2)
    diff = (mean2 * flat1 - mean1 * flat2) / mean
    cov_map, npix_map = direct_covariance_map(diff, good, 5)
    expected, expected_npix = fold_quadrants(cov_map, npix_map)
    np.testing.assert_allclose(result.cov_adu, expected / 2, rtol=1e-10)
    np.testing.assert_array_equal(result.npix, expected_npix)
    assert result.var_adu == result.cov_adu[0, 0]
    assert result.mean_adu == pytest.approx(mean, rel=1e-14)
    assert (result.mean1_adu, result.mean2_adu) == pytest.approx((mean1, mean2), rel=1e-14)
    assert result.n_masked == mask.sum() and result.n_clipped == 0


def test_pair_covariance_of_a_flat_pair_and_its_errors():
    rng = np.random.default_rng(4)
    images = [rng.poisson(5000, (128, 128)).astype(float) for _ in range(2)]
    (pair,) = pair_flats(read_flats(images, exptimes=[3.0, 3.0]))
    result = pair_covariance(pair, maxlag=3)
    assert isinstance(result, PairCovariance)
    assert result.exptime == 3.0 and result.names == ("array[0]", "array[1]")
    assert result.cov_adu.shape == result.npix.shape == (4, 4)
    # Poisson: V = mu within sqrt(2/N); off-origin covariances consistent with zero
    assert abs(result.var_adu / result.mean_adu - 1) < 4 * np.sqrt(2 / 128**2)
    pulls = result.cov_adu / result.cov_err_adu
    pulls[0, 0] = 0
    assert np.all(np.abs(pulls) < 4)


@pytest.mark.parametrize("nsigma", [2.5, 3.0, 4.0])
def test_clipping_correction_restores_gaussian_variance(nsigma):
    rng = np.random.default_rng(5)
    shape = (512, 512)
    flat1, flat2 = rng.normal(1000, 10, shape), rng.normal(1000, 10, shape)
    result = pair_covariance(flat1, flat2, maxlag=1, clip_nsigma=nsigma)
    assert result.n_clipped > 0
    # var(d)/2 of two N(., 10) images is 100 ADU^2 (the symmetric difference rescales it by
    # mu1 mu2 / mu^2, one part in 1e10 here); its error is 100 sqrt(2 / N).
    error = 100 * np.sqrt(2 / flat1.size)
    assert abs(result.var_adu - 100) < 3 * error
    uncorrected = result.var_adu * result.clip_factor
    if nsigma < 3.5:  # the bias being corrected is many sigma there
        assert abs(uncorrected - 100) > 5 * error


def test_clipping_correction_restores_correlations():
    rng = np.random.default_rng(6)
    shape = (512, 512)
    kernel = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 0.0]])  # R(1,0) = 0.099
    images = [correlated_noise(rng, shape, kernel) for _ in range(2)]
    result = pair_covariance(images[0] + 100, images[1] + 100, maxlag=1, clip_nsigma=2.5)
    # Clipping at ~2.4 sigma scales a small correlation by v = 0.89; corrected by v**2 / v.
    assert result.corr[0, 1] == pytest.approx(0.1 / 1.01, abs=3 / np.sqrt(images[0].size))
    assert abs(result.corr[0, 1] * result.clip_factor - 0.099) > 3 / np.sqrt(images[0].size)


def test_clip_variance_factor_matches_cp_pipe_formula():
    from scipy.stats import norm

    for t in (2.0, 3.0, 4.0):
        expected = 1 - 2 * t * norm.pdf(t) / (norm.cdf(t) - norm.cdf(-t))
        assert clip_variance_factor(t) == pytest.approx(expected, rel=1e-12)
    assert clip_variance_factor(np.inf) == 1.0


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), ny=st.integers(12, 40), nx=st.integers(12, 40),
       maxlag=st.integers(0, 5), bad_fraction=st.floats(0.0, 0.3), offset=st.floats(-1e3, 1e3))
def test_covariance_map_property(seed, ny, nx, maxlag, bad_fraction, offset):
    rng = np.random.default_rng(seed)
    image = offset + rng.normal(size=(ny, nx))
    good = rng.random((ny, nx)) >= bad_fraction
    good[0, 0] = good[-1, -1] = True
    cov, npix = covariance_map(image, good, maxlag, precision="double")
    expected, expected_npix = direct_covariance_map(image, good, maxlag)
    np.testing.assert_array_equal(npix, expected_npix)
    valid = expected_npix > 0
    np.testing.assert_allclose(cov[valid], expected[valid], rtol=0, atol=1e-9)
    np.testing.assert_allclose(cov, cov[::-1, ::-1], rtol=0, atol=1e-12)  # C(-k) = C(k)


def test_bad_arguments_are_named():
    image = np.zeros((10, 10))
    with pytest.raises(BFPSFValueError, match="maxlag=5 is too large for an image of shape"):
        pair_covariance(image, image, maxlag=5)
    with pytest.raises(BFPSFInputError, match=r"mask shape \(9, 10\) differs"):
        pair_covariance(image, image, mask=np.zeros((9, 10), bool), maxlag=1)
    with pytest.raises(BFPSFValueError, match="precision must be 'single' or 'double'"):
        covariance_map(image, image == 0, 1, precision="half")
    with pytest.raises(BFPSFInputError, match="fewer than two good pixels"):
        pair_covariance(image, image, mask=np.ones((10, 10), bool), maxlag=1)
    with pytest.raises(BFPSFValueError, match="clip_nsigma must be at least 2"):
        pair_covariance(image, image, maxlag=1, clip_nsigma=1.5)


def test_bias_pair_uses_the_plain_difference():
    # Means near zero (bias frames): scaling by the means would be meaningless; the plain
    # difference gives var = read noise^2 whatever the offsets.
    rng = np.random.default_rng(7)
    bias1, bias2 = rng.normal(0.3, 4.0, (256, 256)), rng.normal(-0.2, 4.0, (256, 256))
    result = pair_covariance(bias1, bias2, maxlag=1, clip_nsigma=None)
    assert abs(result.var_adu - 16.0) < 3 * 16.0 * np.sqrt(2 / bias1.size)
