"""Charge redistribution (G15 eq. scrambling_model): conservation, symmetries, the analytic
single-pixel case, a literal per-pixel reference, the inverse, the exact boundary density and
the build-up integration."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bfpsf.errors import BFPSFConvergenceError, BFPSFInputError, BFPSFValueError
from bfpsf.model.buildup import redistribute_buildup
from bfpsf.model.density import exact_boundary_density
from bfpsf.model.inverse import correct
from bfpsf.model.redistribution import (
    boundary_fluxes,
    redistribute,
    redistribution_delta,
    single_pixel_delta,
)
from bfpsf.shifts import BoundaryShifts


def exponential_shifts(scale, length, radius):
    return BoundaryShifts.from_radial_profile(lambda r: scale * np.exp(-r / length), radius)


def with_anisotropy(shifts, north0, east0, north_diagonal):
    """Add nearest-boundary terms that keep parity and the sum rule exact.

    a^N(0,0) += north0 with a^N(0,1) -= north0 (parity pair (dx,dy) <-> (-dx,1-dy));
    a^E(0,0) += east0 with a^E(1,0) -= east0; a^N(+-1,0) += north_diagonal with
    a^N(-+1,1) -= north_diagonal.
    """
    m = shifts.radius
    north = shifts.north.copy()
    east = shifts.east.copy()
    north[m, m] += north0
    north[m + 1, m] -= north0
    east[m, m] += east0
    east[m, m + 1] -= east0
    for dx in (-1, 1):
        north[m, m + dx] += north_diagonal
        north[m + 1, m - dx] -= north_diagonal
    return BoundaryShifts(north, east)


def e2v_like_shifts():
    """a(0,0) = -2.2e-6 /e- (lsst_e2v_50_8 at 1e3 e-), stronger along columns (a^N > a^E)."""
    base = exponential_shifts(8.3e-7, 1.2, 4)
    return with_anisotropy(base, north0=-1.5e-7, east0=1.5e-7, north_diagonal=2e-8)


def moffat(shape, peak, fwhm=2.5, beta=2.5, centre=None):
    ny, nx = shape
    yc, xc = centre if centre is not None else ((ny - 1) / 2 + 0.17, (nx - 1) / 2 - 0.31)
    alpha = fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
    y, x = np.mgrid[:ny, :nx]
    image = (1.0 + ((x - xc) ** 2 + (y - yc) ** 2) / alpha ** 2) ** -beta
    return image * (peak / image.max())


def literal_delta(image, shifts):
    """G15 eq. scrambling_model written out: dQ_00 = 1/4 sum_X (a^X * Q)(Q_00 + Q_X) over the
    four boundaries of each pixel, the correlations as explicit shifted sums (no FFT), and the
    image border closed (no term across it)."""
    ny, nx = image.shape
    m = shifts.radius
    padded = np.zeros((ny + 2 * m, nx + 2 * m))
    padded[m:m + ny, m:m + nx] = image
    neighbour_padded = np.pad(image, 1)
    delta = np.zeros_like(image)
    for label, (dx, dy) in {"N": (0, 1), "S": (0, -1), "E": (1, 0), "W": (-1, 0)}.items():
        kernel = shifts.boundary(label)
        shift = np.zeros_like(image)
        for iy in range(2 * m + 1):
            for ix in range(2 * m + 1):
                shift += kernel[iy, ix] * padded[iy:iy + ny, ix:ix + nx]
        neighbour = neighbour_padded[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
        inside = np.zeros((ny + 2, nx + 2), dtype=bool)
        inside[1:-1, 1:-1] = True
        inside = inside[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
        delta += np.where(inside, 0.25 * shift * (image + neighbour), 0.0)
    return delta


# -- conservation and symmetries -----------------------------------------------------------------
shift_sets = st.builds(
    lambda scale, length, radius, n0, e0, nd: with_anisotropy(
        exponential_shifts(scale, length, radius), n0 * scale, e0 * scale, nd * scale),
    scale=st.floats(1e-9, 1e-6), length=st.floats(0.3, 3.0), radius=st.integers(1, 5),
    n0=st.floats(-0.5, 0.5), e0=st.floats(-0.5, 0.5), nd=st.floats(-0.1, 0.1))


# Strong shifts on noisy random images can leave a pixel below zero (beyond first order):
# redistribute says so with a BFPSFWarning; conservation and parity must hold all the same.
@pytest.mark.filterwarnings("ignore::bfpsf.errors.BFPSFWarning")
@settings(max_examples=60, deadline=None)
@given(shifts=shift_sets, ny=st.integers(2, 40), nx=st.integers(2, 40),
       level=st.floats(1.0, 2e5), seed=st.integers(0, 2**32 - 1))
def test_charge_is_conserved_and_parity_is_respected(shifts, ny, nx, level, seed):
    rng = np.random.default_rng(seed)
    # Random images with negative pixels too (bias-subtracted noise).
    image = level * (rng.random((ny, nx)) - 0.1)
    result = redistribute(image, shifts)
    assert abs(result.sum() - image.sum()) <= 1e-12 * np.abs(image).sum()
    delta = redistribution_delta(image, shifts)
    # The shifts obey parity a^X(dx,dy) = a^-X(-dx,-dy): the operator commutes with a
    # rotation by 180 degrees.
    rotated = redistribution_delta(image[::-1, ::-1], shifts)
    scale = np.abs(delta).max() + 1e-300
    assert np.abs(rotated[::-1, ::-1] - delta).max() <= 1e-10 * scale
    # The anisotropic terms added are mirror-symmetric in x: so is the operator.
    mirrored = redistribution_delta(image[:, ::-1], shifts)
    assert np.abs(mirrored[:, ::-1] - delta).max() <= 1e-10 * scale
    # Quadratic in the image.
    np.testing.assert_allclose(redistribution_delta(3.0 * image, shifts), 9.0 * delta,
                               rtol=0, atol=1e-10 * 9.0 * scale)


@settings(max_examples=20, deadline=None)
@given(scale=st.floats(1e-9, 1e-6), length=st.floats(0.3, 3.0), radius=st.integers(1, 4),
       seed=st.integers(0, 2**32 - 1))
def test_radial_shifts_commute_with_transposition(scale, length, radius, seed):
    # For a^X = -f(r) cos(theta), a^E(dx, dy) = a^N(dy, dx): swapping x and y swaps N and E.
    shifts = exponential_shifts(scale, length, radius)
    image = np.random.default_rng(seed).random((17, 23)) * 1e5
    delta = redistribution_delta(image, shifts)
    transposed = redistribution_delta(image.T, shifts)
    assert np.abs(transposed.T - delta).max() <= 1e-10 * np.abs(delta).max()


def test_float32_keeps_charge_exact():
    shifts = e2v_like_shifts()
    image = np.random.default_rng(1).random((300, 520)) * 1e5
    single = redistribute(image, shifts, dtype=np.float32)
    double = redistribute(image, shifts)
    assert abs(single.sum() - image.sum()) <= 1e-12 * image.sum()
    # float32 FFTs: the boundary shifts are good to ~1e-7 of their range, the fluxes to ~1e-6.
    delta = double - image
    assert np.abs(single - double).max() <= 1e-5 * np.abs(delta).max()


# -- against independent computations ------------------------------------------------------------
@pytest.mark.parametrize("shape", [(1, 1), (2, 7), (9, 9), (20, 13)])
def test_matches_literal_formula(shape):
    shifts = e2v_like_shifts()
    image = np.random.default_rng(2).random(shape) * 1e5
    expected = literal_delta(image, shifts)
    delta = redistribution_delta(image, shifts)
    np.testing.assert_allclose(delta, expected, rtol=0,
                               atol=1e-12 * max(np.abs(expected).max(), 1e-300))


def test_matches_literal_formula_across_fft_tiles():
    # 300 x 530 spans two and three overlap-save tiles (blocks of 184 pixels for radius 4 in
    # double precision).
    shifts = e2v_like_shifts()
    image = np.random.default_rng(3).random((300, 530)) * 1e5
    expected = literal_delta(image, shifts)
    np.testing.assert_allclose(redistribution_delta(image, shifts), expected, rtol=0,
                               atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("charge", [1.0, 1e5])
def test_single_charged_pixel_matches_closed_form(charge):
    shifts = e2v_like_shifts()
    image = np.zeros((11, 11))
    image[5, 6] = charge
    delta = redistribution_delta(image, shifts)
    expected = np.zeros_like(image)
    expected[4:7, 5:8] = single_pixel_delta(charge, shifts)
    np.testing.assert_allclose(delta, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    # dQ(0,0) = Q^2/4 a(0,0): the charged pixel loses charge (a(0,0) < 0).
    m = shifts.radius
    assert delta[5, 6] == pytest.approx(0.25 * charge**2 * shifts.area[m, m], rel=1e-12)


def divergence(flux_north, flux_east):
    """Charge each pixel gains from the fluxes through its four boundaries."""
    delta = np.zeros((flux_east.shape[0], flux_north.shape[1]))
    delta[:-1] += flux_north
    delta[1:] -= flux_north
    delta[:, :-1] += flux_east
    delta[:, 1:] -= flux_east
    return delta


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_threads_do_not_change_the_numbers(dtype):
    # 700 x 450: four bands of tiles in double precision, three in single; every band and tile
    # is computed the same way whichever thread runs it, so the results are identical.
    shifts = e2v_like_shifts()
    rng = np.random.default_rng(4)
    image = rng.random((700, 450)) * 1e5
    one = redistribute(image, shifts, dtype=dtype, workers=1)
    assert abs(one.sum() - image.sum()) <= 1e-12 * image.sum()
    for workers in (2, 3, None, -1):
        np.testing.assert_array_equal(redistribute(image, shifts, dtype=dtype, workers=workers),
                                      one)
    fluxes = boundary_fluxes(image, shifts, dtype=dtype, workers=1)
    for single, threaded in zip(fluxes, boundary_fluxes(image, shifts, dtype=dtype, workers=2)):
        np.testing.assert_array_equal(threaded, single)
    # The tile-wise accumulation equals the divergence of the boundary fluxes.
    delta = divergence(*(np.asarray(flux, dtype=float) for flux in fluxes))
    np.testing.assert_allclose(one - image, delta, rtol=0, atol=1e-12 * np.abs(delta).max())


def test_given_density_across_tiles_is_the_divergence_of_the_fluxes():
    shifts = e2v_like_shifts()
    rng = np.random.default_rng(5)
    image = rng.random((420, 400)) * 1e5
    density = (rng.random((419, 400)) * 1e5, rng.random((420, 399)) * 1e5)
    delta = divergence(*boundary_fluxes(image, shifts, density=density))
    result = redistribution_delta(image, shifts, density=density, workers=2)
    np.testing.assert_allclose(result, delta, rtol=0, atol=1e-12 * np.abs(delta).max())
    assert abs(result.sum()) <= 1e-12 * np.abs(delta).sum()


# -- edges and masked pixels ---------------------------------------------------------------------
def test_border_is_closed():
    shifts = e2v_like_shifts()
    # A bright star centred on the corner pixel: half its charge would leave an open border.
    image = moffat((30, 30), 1.5e5, centre=(0.2, 0.4))
    result = redistribute(image, shifts)
    assert abs(result.sum() - image.sum()) <= 1e-14 * image.sum()
    # No flux leaves through the border: the fluxes only exist between image pixels.
    flux_north, flux_east = boundary_fluxes(image, shifts)
    assert flux_north.shape == (29, 30) and flux_east.shape == (30, 29)
    # With an empty border ring the outside never matters: same as inside a larger image.
    framed = np.zeros((30, 30))
    framed[1:-1, 1:-1] = image[1:-1, 1:-1]
    big = np.pad(framed, 7)
    np.testing.assert_allclose(redistribute(framed, shifts), redistribute(big, shifts)[7:-7, 7:-7],
                               rtol=0, atol=1e-9)


def test_non_finite_pixels_are_refused_with_their_count():
    shifts = e2v_like_shifts()
    image = np.ones((20, 20)) * 1e4
    image[3, 4] = np.nan
    image[7, 7] = np.inf
    with pytest.raises(BFPSFInputError, match="image has 2 non-finite pixels"):
        redistribute(image, shifts)
    with pytest.raises(BFPSFInputError, match="image has 2 non-finite pixels"):
        correct(image, shifts)


def test_interpolate_fills_masked_pixels_and_keeps_them_masked():
    shifts = e2v_like_shifts()
    image = moffat((31, 31), 1e5)
    damaged = image.copy()
    damaged[15, 14:17] = np.nan  # three pixels across the core
    result = redistribute(damaged, shifts, nan_policy="interpolate")
    assert np.isnan(result[15, 14:17]).all()
    assert np.isfinite(np.delete(result.ravel(), np.ravel_multi_index(([15] * 3, [14, 15, 16]),
                                                                      result.shape))).all()
    # Far from the hole the result is that of the undamaged image.
    exact = redistribute(image, shifts)
    np.testing.assert_allclose(result[:5], exact[:5], rtol=1e-9)
    # A flat image with a hole is filled flat: same result as without the hole.
    flat = np.full((12, 12), 5e4)
    holed = flat.copy()
    holed[4:6, 4:6] = np.nan
    small = exponential_shifts(1e-7, 1.0, 3)
    out = redistribute(holed, small, nan_policy="interpolate")
    good = np.isfinite(out)
    np.testing.assert_allclose(out[good], redistribute(flat, small)[good], rtol=1e-12)


def test_all_nan_image_cannot_be_interpolated():
    with pytest.raises(BFPSFInputError, match="no finite neighbour"):
        redistribute(np.full((4, 4), np.nan), e2v_like_shifts(), nan_policy="interpolate")


def test_harmonic_fill_is_exact_on_a_harmonic_image_and_leaves_other_nans():
    """The one fill of the package (NaN pixels before redistribution, cosmic rays before a
    measurement): inside the image a plane and x^2 - y^2 are harmonic, so filled exactly; a
    NaN outside the mask is neither filled nor a boundary value; a masked group without a
    finite neighbour raises, or is NaN with ``isolated='nan'``."""
    from bfpsf.model.nanfill import harmonic_fill

    y, x = np.mgrid[:12, :14].astype(float)
    mask = np.zeros(x.shape, dtype=bool)
    mask[4:7, 5:9] = mask[9, 2] = True
    for image in (3.0 + 0.5 * x - 2.0 * y, (x - 6.0) ** 2 - (y - 5.0) ** 2):
        np.testing.assert_allclose(harmonic_fill(image, mask)[mask], image[mask], atol=1e-9)
    holed = 3.0 + 0.5 * x - 2.0 * y
    holed[7, 5:9] = np.nan  # beside the mask's bottom row: not used, left NaN
    filled = harmonic_fill(holed, mask)
    assert np.isnan(filled[7, 5:9]).all() and np.all(np.isfinite(filled[mask]))
    # (a maximum principle: within the finite values around the mask, the missing row's
    # plane values beyond them)
    around = holed[3:8, 4:10]
    hole = filled[4:7, 5:9]
    assert np.nanmin(around) <= hole.min() and hole.max() <= np.nanmax(around)
    assert hole.min() > (3.0 + 0.5 * x - 2.0 * y)[6, 5:9].min()
    alone = np.full(x.shape, np.nan)
    alone[:, :3] = 1.0
    lonely = np.zeros(x.shape, dtype=bool)
    lonely[5, 8] = lonely[2, 1] = True
    with pytest.raises(BFPSFInputError, match="no finite neighbour"):
        harmonic_fill(alone, lonely)
    filled = harmonic_fill(alone, lonely, isolated="nan")
    assert np.isnan(filled[5, 8]) and filled[2, 1] == pytest.approx(1.0)


def test_bad_arguments_are_named():
    shifts = e2v_like_shifts()
    with pytest.raises(BFPSFInputError, match="image must be 2-D"):
        redistribute(np.ones(5), shifts)
    with pytest.raises(BFPSFValueError, match="nan_policy must be one of"):
        redistribute(np.ones((5, 5)), shifts, nan_policy="zero")
    with pytest.raises(BFPSFValueError, match="expected BoundaryShifts"):
        redistribute(np.ones((5, 5)), np.ones((3, 3)))
    with pytest.raises(BFPSFValueError, match="dtype must be float64 or float32"):
        redistribute(np.ones((5, 5)), shifts, dtype=np.int32)
    with pytest.raises(BFPSFValueError, match="density_north must have shape"):
        redistribute(np.ones((5, 5)), shifts, density=(np.ones((5, 5)), np.ones((5, 4))))
    with pytest.raises(BFPSFValueError, match="method must be"):
        correct(np.ones((5, 5)), shifts, method="newton")
    with pytest.raises(BFPSFValueError, match="workers must not be 0"):
        redistribute(np.ones((5, 5)), shifts, workers=0)
    with pytest.raises(BFPSFValueError, match="workers must be an integer or None"):
        redistribute(np.ones((5, 5)), shifts, workers=1.5)


# -- inverse -------------------------------------------------------------------------------------
def test_iterative_inverse_round_trip_150ke():
    shifts = e2v_like_shifts()
    truth = moffat((41, 41), 1.5e5)
    observed = redistribute(truth, shifts)
    result = correct(observed, shifts, full_output=True)
    assert result.converged and result.method == "iterative"
    assert np.abs(result.image - truth).max() <= 1e-8 * truth.max()
    # The stopping rule bounds the error of the returned image from its residual.
    assert result.error_bound <= 1e-10
    assert np.abs(result.image - truth).max() / truth.max() <= 2 * result.error_bound + 1e-14
    assert result.residual == result.residual_history[-1]
    # Linear convergence at a rate ~ |a(0,0)| Q_peak / 2 (0.17 here): residuals fall geometrically.
    history = np.array(result.residual_history)
    assert np.all(history[1:] < history[:-1])
    assert 0.02 < result.contraction < 0.4
    assert result.iterations == len(history) < 30
    # Plain call returns the image.
    np.testing.assert_array_equal(correct(observed, shifts), result.image)


def test_convergence_and_shift_figures_show_the_data():
    import matplotlib.pyplot as plt

    from bfpsf.plotting.redistribution import plot_boundary_shifts, plot_correction_convergence

    shifts = e2v_like_shifts()
    result = correct(redistribute(moffat((31, 31), 1e5), shifts), shifts, full_output=True)
    fig = plot_correction_convergence(result)
    np.testing.assert_allclose(fig.axes[0].lines[0].get_ydata(), result.residual_history)
    plt.close(fig)
    fig = plot_boundary_shifts(shifts)
    np.testing.assert_allclose(fig.axes[0].images[0].get_array(), shifts.north)
    np.testing.assert_allclose(fig.axes[1].images[0].get_array(), shifts.east)
    plt.close(fig)


def test_first_order_inverse_is_the_sign_flip():
    shifts = e2v_like_shifts()
    truth = moffat((41, 41), 1.5e5)
    observed = redistribute(truth, shifts)
    first = correct(observed, shifts, method="first_order")
    np.testing.assert_allclose(first, redistribute(observed, shifts.scaled(-1.0)), rtol=1e-13)
    # It removes most, not all, of the BF: the error is second order in a Q.
    bf = np.abs(observed - truth).max()
    error = np.abs(first - truth).max()
    assert error < 0.3 * bf
    assert error > 1e-4 * bf


def test_non_convergence_is_reported():
    shifts = e2v_like_shifts()
    observed = redistribute(moffat((41, 41), 1.5e5), shifts)
    with pytest.raises(BFPSFConvergenceError, match="did not converge: residual"):
        correct(observed, shifts, max_iter=2)
    result = correct(observed, shifts, max_iter=2, strict=False, full_output=True)
    assert not result.converged and result.iterations == 2


@pytest.mark.slow
def test_iterative_inverse_round_trip_with_silicon_e2v_shifts():
    from bfpsf.interop.silicon_truth import silicon_boundary_shifts

    shifts = silicon_boundary_shifts("lsst_e2v_50_8")
    truth = moffat((61, 61), 1.5e5, fwhm=2.0)
    result = correct(redistribute(truth, shifts), shifts, full_output=True)
    assert np.abs(result.image - truth).max() <= 1e-8 * truth.max()


# -- exact boundary density ----------------------------------------------------------------------
def test_exact_density_of_a_flat_image_is_the_charge():
    sub = np.full((12 * 4, 10 * 4), 10.0)
    image, (north, east) = exact_boundary_density(sub, 4)
    np.testing.assert_allclose(image, 160.0)
    np.testing.assert_allclose(north, 160.0)
    np.testing.assert_allclose(east, 160.0)


def test_exact_density_is_exact_for_cubic_profiles():
    # Sub-pixel charges of f(x, y) = 1 + x + x^2 y - y^3 (cubic), integrated exactly on the
    # sub-pixel grid; the density along a boundary y = y_b is int f(x, y_b) dx.
    n, ny, nx = 4, 5, 6
    f_integral = lambda x0, x1, y0, y1: (
        (x1 - x0) * (y1 - y0) + (x1**2 - x0**2) / 2 * (y1 - y0)
        + (x1**3 - x0**3) / 3 * (y1**2 - y0**2) / 2 - (x1 - x0) * (y1**4 - y0**4) / 4)
    edges_y = np.arange(ny * n + 1) / n
    edges_x = np.arange(nx * n + 1) / n
    sub = f_integral(edges_x[None, :-1], edges_x[None, 1:], edges_y[:-1, None], edges_y[1:, None])
    image, (north, _) = exact_boundary_density(sub, n)
    y_b = np.arange(1, ny)[:, None]
    x0, x1 = np.arange(nx)[None, :], np.arange(1, nx + 1)[None, :]
    line = (x1 - x0) * (1 - y_b**3) + (x1**2 - x0**2) / 2 + (x1**3 - x0**3) / 3 * y_b
    np.testing.assert_allclose(north, line, rtol=1e-12, atol=1e-12)


def test_exact_density_converges_and_exceeds_mean_for_undersampled_spots():
    from bfpsf.validation.approximations import moffat_charge

    shifts = e2v_like_shifts()
    results = {}
    for n in (4, 8, 16):
        image, sub = moffat_charge(1.2, 1e5, oversampling=n, size=21)
        _, density = exact_boundary_density(sub, n)
        results[n] = redistribution_delta(image, shifts, density=density)
    scale = np.abs(results[16]).max()
    # Fourth-order interpolation: 8 -> 16 changes the result far less than 4 -> 8.
    assert np.abs(results[8] - results[16]).max() < 1e-3 * scale
    assert np.abs(results[8] - results[16]).max() < 0.2 * np.abs(results[4] - results[16]).max()
    # The density on the boundaries of the peak pixel is larger than (Q_p + Q_q)/2 for a
    # cuspy undersampled spot, so the exact redistribution moves more charge out of the core.
    mean = redistribution_delta(image, shifts)
    assert results[16][10, 10] < mean[10, 10] < 0


def test_exact_density_rejects_bad_oversampling():
    with pytest.raises(BFPSFValueError, match="oversampling must be an integer of at least 2"):
        exact_boundary_density(np.ones((4, 4)), 1)
    with pytest.raises(BFPSFInputError, match="sides multiple of oversampling=3"):
        exact_boundary_density(np.ones((4, 6)), 3)


# -- build-up ------------------------------------------------------------------------------------
def test_one_step_buildup_is_the_g15_model():
    shifts = e2v_like_shifts()
    image = moffat((31, 31), 1e5)
    np.testing.assert_allclose(redistribute_buildup(image, shifts, nsteps=1),
                               redistribute(image, shifts), rtol=0, atol=1e-9)


def test_buildup_converges_and_differs_at_second_order():
    shifts = e2v_like_shifts()
    unit = moffat((31, 31), 1.0)
    differences = {}
    for peak in (5e4, 1e5):
        image = unit * peak
        one = redistribute(image, shifts)
        by_steps = {k: redistribute_buildup(image, shifts, nsteps=k) for k in (8, 16, 32)}
        for result in by_steps.values():
            assert abs(result.sum() - image.sum()) <= 1e-12 * image.sum()
        # Midpoint rule: the error falls as 1/K^2.
        e8 = np.abs(by_steps[8] - by_steps[32]).max()
        e16 = np.abs(by_steps[16] - by_steps[32]).max()
        assert 3.0 < e8 / e16 < 6.0
        differences[peak] = np.abs(one - by_steps[32]).max() / np.abs(by_steps[32] - image).max()
    # The feedback of redistributed charge is second order: relative difference ~ peak.
    assert differences[1e5] / differences[5e4] == pytest.approx(2.0, rel=0.1)
    assert differences[1e5] < 0.1
