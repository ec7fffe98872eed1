"""FluxDependentPSF against the exact G15 operator applied to pixelised stars."""

import galsim
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bfpsf.errors import BFPSFValueError
from bfpsf.model.psf import FluxDependentPSF, bf_response_table, pixelised_stamp
from bfpsf.model.redistribution import redistribute
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_spots import peak_fraction

#: E2V-like shifts: a(0,0) = -2.3e-6 /e- as GalSim's lsst_e2v_50_8 (-2.2e-6).
SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
MOFFAT = galsim.Moffat(beta=3.0, fwhm=3.5)
#: Flux of a star with a 120 ke- peak.
BRIGHT = 1.2e5 / peak_fraction(MOFFAT)


@pytest.fixture(scope="module")
def psf():
    return FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25)


@pytest.fixture(scope="module")
def psf_exact():
    return FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25, mode="exact")


def exact_star(model, flux, x_phase, y_phase, half=13):
    """The operator applied to the model's own pixelised P0: the truth for the BF term."""
    stamp = flux * pixelised_stamp(model, x_phase=x_phase, y_phase=y_phase, half_size=half)
    return stamp, redistribute(stamp, SHIFTS)


def evaluate_on_stamp(model, flux, x_phase, y_phase, half=13):
    y, x = np.mgrid[:2 * half + 1, :2 * half + 1]
    return model.evaluate(x, y, flux, half + x_phase, half + y_phase)


@settings(max_examples=20, deadline=None)
@given(x_phase=st.floats(-0.5, 0.5), y_phase=st.floats(-0.5, 0.5))
def test_exact_mode_is_the_operator(psf_exact, x_phase, y_phase):
    stamp, truth = exact_star(psf_exact, BRIGHT, x_phase, y_phase)
    model = evaluate_on_stamp(psf_exact, BRIGHT, x_phase, y_phase)
    # Rounding only, away from the edge of the P0 support (where the two stamps differ by
    # which empty border pixel charge may move into).
    inner = slice(2, -2)
    np.testing.assert_allclose(model[inner, inner], truth[inner, inner], rtol=0,
                               atol=1e-9 * truth.max())


@settings(max_examples=20, deadline=None)
@given(x_phase=st.floats(-0.5, 0.5), y_phase=st.floats(-0.5, 0.5))
def test_table_mode_interpolates_the_bf_term(psf, x_phase, y_phase):
    stamp, truth = exact_star(psf, BRIGHT, x_phase, y_phase)
    model = evaluate_on_stamp(psf, BRIGHT, x_phase, y_phase)
    inner = slice(2, -2)  # away from the edge of the P0 support
    bf_true = (truth - stamp)[inner, inner]
    bf_model = (model - stamp)[inner, inner]
    # Spline interpolation of R between the 4x4 phases: measured 5.5e-5 of the largest BF
    # pixel at oversampling 4 (1e-3 at 2, 3e-6 at 8); 2e-4 leaves room.
    assert np.abs(bf_model - bf_true).max() < 2e-4 * np.abs(bf_true).max()


def test_table_is_exact_at_table_phases(psf):
    table = bf_response_table(psf.data, SHIFTS, psf.oversampling)
    # Origin (50, 50) of a 101-sample grid: phase 1/4 of a pixel is one node to the right.
    stamp, truth = exact_star(psf, 1.0, 0.25, -0.5)
    model = evaluate_on_stamp(psf, 1.0, 0.25, -0.5)
    # Exact up to the edge of the P0 support (the table's stamps end there): 1e-6 of the peak.
    np.testing.assert_allclose(model - stamp, truth - stamp, atol=1e-6 * np.abs(table).max())
    for a in range(4):
        for b in range(4):
            assert abs(table[a::4, b::4].sum()) < 1e-12 * np.abs(table).max()


def test_charge_conservation_and_quadratic_scaling(psf):
    y, x = np.mgrid[:41, :41]
    one = psf.evaluate(x, y, 1.0, 20.2, 19.7)
    base = psf.evaluate_base(x - 20.2, y - 19.7)
    # the BF term per F |F|, from a star bright enough that P(F) - F P0 loses no digits (at
    # F = 1 the term is 1e-10 of P0, and the difference keeps 6 of its digits)
    reference = 1e5
    bf_unit = (psf.evaluate(x, y, reference, 20.2, 19.7) - reference * base) / reference**2
    for flux in (1e4, 1e6, -1e6):
        model = psf.evaluate(x, y, flux, 20.2, 19.7)
        # The BF term moves charge, it creates none (G15 eq. scrambling_model conserves Q);
        # the spline between table phases conserves it to 1.2e-9 of the flux (measured).
        assert model.sum() == pytest.approx(flux * one.sum(), rel=1e-8)
        bf = model - flux * base
        # F |F| scaling: odd in F, quadratic in |F|.
        np.testing.assert_allclose(bf, flux * abs(flux) * bf_unit, atol=1e-12 * abs(flux))


def test_bf_term_broadens_the_star(psf):
    stamp, _ = exact_star(psf, 1.0, 0.0, 0.0)
    bright = evaluate_on_stamp(psf, BRIGHT, 0.0, 0.0) / BRIGHT
    centre = 13
    # The peak loses charge to its neighbours (a(0,0) < 0): fatter when brighter.
    assert bright[centre, centre] < stamp[centre, centre]
    # Symmetric shifts and a centred symmetric PSF: the BF term is symmetric.
    bf = bright - stamp
    np.testing.assert_allclose(bf, bf[::-1, :], atol=1e-9 * np.abs(bf).max())
    np.testing.assert_allclose(bf, bf[:, ::-1], atol=1e-9 * np.abs(bf).max())


def test_evaluate_uses_its_arguments_and_is_vectorised(psf):
    model = psf.copy()
    model.flux = 123.0
    model.x_0 = -7.0
    y, x = np.mgrid[:21, :21]
    grid = model.evaluate(x, y, 5e5, 10.3, 9.9)
    flat = model.evaluate(x.ravel(), y.ravel(), 5e5, 10.3, 9.9)
    np.testing.assert_array_equal(grid.ravel(), flat)
    np.testing.assert_array_equal(grid, psf.evaluate(x, y, 5e5, 10.3, 9.9))
    # The astropy call path uses the instance parameters.
    model.flux, model.x_0, model.y_0 = 5e5, 10.3, 9.9
    np.testing.assert_allclose(model(x, y), grid)
    # copy() shares the big arrays; parameters are independent.
    assert model.data is psf.data and model.bf_table is psf.bf_table
    assert psf.flux.value == 1.0


def test_trial_values_are_tolerated(psf):
    y, x = np.mgrid[:11, :11]
    assert np.all(psf.evaluate(x, y, 0.0, 5, 5) == 0)
    assert np.all(np.isnan(psf.evaluate(x, y, np.nan, 5, 5)))
    assert np.all(np.isnan(psf.evaluate(x, y, 1e5, np.nan, 5)))
    negative = psf.evaluate(x, y, -1e5, 5.2, 5.1)
    np.testing.assert_allclose(negative, -psf.evaluate(x, y, 1e5, 5.2, 5.1))
    # Far from the star: fill_value.
    assert psf.evaluate(100.0, 100.0, 1e5, 0.0, 0.0) == 0.0


def test_bounding_box_covers_the_data(psf):
    model = psf.copy()
    model.x_0, model.y_0 = 10.0, 20.0
    (y_low, y_high), (x_low, x_high) = model.bounding_box.bounding_box(order="C")
    assert x_low == pytest.approx(10 - 12.625) and x_high == pytest.approx(10 + 12.625)
    assert y_low == pytest.approx(20 - 12.625) and y_high == pytest.approx(20 + 12.625)


def test_gain_scales_the_bf_term_of_an_adu_model_only(psf):
    adu = FluxDependentPSF(psf.data, SHIFTS, oversampling=4, flux_unit="adu", gain=2.0)
    assert adu.electrons_per_unit == 2.0
    # A gain recorded on a model in electrons leaves the BF term alone.
    recorded = FluxDependentPSF(psf.data, SHIFTS, oversampling=4, flux_unit="electron",
                                gain=2.0)
    y, x = np.mgrid[:31, :31]
    np.testing.assert_array_equal(recorded.evaluate(x, y, 2e5, 15.1, 15.3),
                                  psf.evaluate(x, y, 2e5, 15.1, 15.3))
    # with_flux_unit converts both ways.
    np.testing.assert_array_equal(recorded.with_flux_unit("adu").evaluate(x, y, 2e5, 15.1, 15.3),
                                  adu.evaluate(x, y, 2e5, 15.1, 15.3))
    back = adu.with_flux_unit("electron")
    assert back.gain == 2.0 and back.electrons_per_unit == 1.0
    flux_adu = 2e5
    # A star of 2e5 ADU at 2 e-/ADU is 4e5 e-; the ADU model is the e- model / gain.
    np.testing.assert_allclose(adu.evaluate(x, y, flux_adu, 15.1, 15.3),
                               psf.evaluate(x, y, 2 * flux_adu, 15.1, 15.3) / 2,
                               rtol=1e-9, atol=1e-12 * flux_adu)


def test_from_image_psf_matches_image_psf_without_bf(psf):
    from photutils.psf import ImagePSF

    image_psf = ImagePSF(np.array(psf.data), oversampling=4)
    no_bf = FluxDependentPSF.from_image_psf(image_psf, SHIFTS.scaled(0.0))
    y, x = np.mgrid[:25, :25]
    np.testing.assert_allclose(no_bf.evaluate(x, y, 1e5, 12.3, 11.8),
                               image_psf.evaluate(x, y, 1e5, 12.3, 11.8), rtol=1e-12,
                               atol=1e-12)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"mode": "fast"}, "mode must be one of"),
    ({"oversampling": 0}, "oversampling must be"),
    ({"oversampling": 2.5}, "oversampling must be"),
    ({"gain": -1.0, "flux_unit": "adu"}, "gain must be a positive"),
    ({"gain": 1.5}, "gain given without flux_unit"),
    ({"flux_unit": "adu"}, "flux_unit='adu' needs the gain"),
    ({"flux_unit": "ADU", "gain": 1.5}, "flux_unit must be one of"),
    ({"buildup_steps": 8}, "requires mode='exact'"),
    ({"buildup_steps": 0, "mode": "exact"}, "buildup_steps must be a positive integer"),
    ({"bf_table": np.zeros((3, 3))}, "bf_table must have the shape"),
    ({"origin": (1.0, np.nan)}, "origin must be two finite"),
])
def test_bad_arguments(psf, kwargs, match):
    with pytest.raises(BFPSFValueError, match=match):
        FluxDependentPSF(psf.data, SHIFTS, **kwargs)


def test_bad_data():
    with pytest.raises(BFPSFValueError, match="non-finite"):
        FluxDependentPSF(np.full((9, 9), np.nan), SHIFTS)
    with pytest.raises(BFPSFValueError, match="at least 4 x 4"):
        FluxDependentPSF(np.ones((3, 9)), SHIFTS)


def test_plots(psf):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bfpsf.plotting.psf import plot_bf_difference, plot_psf, plot_residuals

    figure = plot_psf(psf)
    assert len(figure.axes) == 2  # image and colour bar
    figure = plot_bf_difference(psf, [1e5, BRIGHT])
    assert len(figure.axes) == 3
    # The difference panels show the core losing charge to the wings (a(0,0) < 0).
    centre = figure.axes[1].images[0].get_array()
    assert centre[6, 6] < 0 and centre.sum() == pytest.approx(0.0, abs=1e-6)
    image = psf.star_image(BRIGHT, half_size=10)
    figure = plot_residuals(image, image * 0.99, error=np.sqrt(image + 100))
    assert "rms" in figure.axes[0].get_title()
    plt.close("all")


def test_exact_boundary_density_table():
    """density='exact' tabulates the engine's exact boundary density (G15 eq. density-approx
    replaced by the density integrated along each boundary)."""
    from bfpsf.model.density import exact_boundary_density

    model = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25,
                                         density="exact")
    mean = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25)
    # The exact density changes the BF term of a FWHM 3.5 star by ~7 % (measured 6.9 %).
    change = np.abs(model.bf_table - mean.bf_table).max() / np.abs(mean.bf_table).max()
    assert 0.02 < change < 0.2
    flux, x_phase, y_phase, sub, size = 2e6, 0.3, -0.2, 8, 27
    fine = MOFFAT.withFlux(flux).drawImage(nx=size * sub, ny=size * sub, scale=1 / sub,
                                           offset=(x_phase * sub, y_phase * sub),
                                           dtype=np.float64).array
    image, density = exact_boundary_density(fine, sub)
    truth = redistribute(image, SHIFTS, density=density) - image
    y, x = np.mgrid[:size, :size]
    half = size // 2
    bf = (model.evaluate(x, y, flux, half + x_phase, half + y_phase)
          - flux * model.evaluate_base(x - half - x_phase, y - half - y_phase))
    inner = slice(2, -2)
    # Phase interpolation of the table: 4e-5 of the largest BF pixel measured.
    assert np.abs(bf - truth)[inner, inner].max() < 2e-4 * np.abs(truth).max()


def test_exact_density_in_exact_mode_with_and_without_buildup():
    """density='exact' in mode='exact': the density at every evaluation phase, also inside the
    build-up integration."""
    from bfpsf.model.buildup import redistribute_buildup
    from bfpsf.model.density import exact_boundary_density

    table = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25,
                                         density="exact")
    exact = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25,
                                         density="exact", mode="exact")
    static = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS.scaled(0.0), oversampling=4, size=25)
    y, x = np.mgrid[:27, :27]
    # at a phase of the table (x 0.25, y -0.5) both modes are the operator: the same to the
    # spline interpolation of P0 (measured 1e-5 of the largest BF pixel)
    bf = [model.evaluate(x, y, BRIGHT, 13.25, 12.5) - static.evaluate(x, y, BRIGHT, 13.25, 12.5)
          for model in (table, exact)]
    assert np.abs(bf[0] - bf[1]).max() < 1e-4 * np.abs(bf[0]).max()
    # one build-up step is the one-step model, to rounding
    one = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25,
                                       density="exact", mode="exact", buildup_steps=1)
    np.testing.assert_allclose(one.evaluate(x, y, BRIGHT, 13.3, 12.9),
                               exact.evaluate(x, y, BRIGHT, 13.3, 12.9), rtol=0,
                               atol=1e-12 * BRIGHT)
    # K steps: the engine's build-up with the exact density of this star at this phase
    steps = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25,
                                         density="exact", mode="exact", buildup_steps=8)
    sub, phase = 8, (0.3, -0.1)
    fine = MOFFAT.withFlux(BRIGHT).drawImage(nx=27 * sub, ny=27 * sub, scale=1 / sub,
                                             offset=(phase[0] * sub, phase[1] * sub),
                                             dtype=np.float64).array
    density = exact_boundary_density(fine, sub)[1]
    stamp = BRIGHT * pixelised_stamp(steps, x_phase=phase[0], y_phase=phase[1], half_size=13)
    truth = redistribute_buildup(stamp, SHIFTS, nsteps=8, density=density)
    model_image = steps.star_image(BRIGHT, x_phase=phase[0], y_phase=phase[1], half_size=13)
    np.testing.assert_allclose(model_image, truth, rtol=0, atol=1e-9 * truth.max())
    # the table mode builds its exact-density table from the same profile
    rebuilt = FluxDependentPSF(table.data, SHIFTS, oversampling=4, density_profile=MOFFAT)
    np.testing.assert_array_equal(rebuilt.bf_table, table.bf_table)
    with pytest.raises(BFPSFValueError, match="density_oversampling"):
        FluxDependentPSF(table.data, SHIFTS, oversampling=4, density_profile=MOFFAT,
                         density_oversampling=1)


def test_buildup_mode_is_the_engine(psf):
    from bfpsf.model.buildup import redistribute_buildup

    model = FluxDependentPSF(psf.data, SHIFTS, oversampling=4, mode="exact", buildup_steps=8)
    stamp = pixelised_stamp(psf, x_phase=0.2, y_phase=0.1, half_size=13)
    truth = redistribute_buildup(BRIGHT * stamp, SHIFTS, nsteps=8)
    model_image = model.star_image(BRIGHT, x_phase=0.2, y_phase=0.1, half_size=13)
    np.testing.assert_allclose(model_image, truth, atol=1e-9 * truth.max())
    one_step = exact_star(psf, BRIGHT, 0.2, 0.1)[1]
    # Build-up differs from the one-step model at second order in a: small but not zero.
    difference = np.abs(model_image - one_step).max() / np.abs(one_step - BRIGHT * stamp).max()
    assert 0 < difference < 0.1


def test_flux_beyond_first_order_warns():
    """Fluxes of 1e9 e- break G15's first order (pixels of P(F) go negative): said, in every
    mode; a bright but real star (1e6 e-) is not."""
    import galsim

    from bfpsf.errors import BFPSFWarning
    from bfpsf.model.psf import FluxDependentPSF
    from bfpsf.shifts import BoundaryShifts

    shifts = BoundaryShifts.from_radial_profile(lambda r: 1.2e-6 * np.exp(-r / 0.8), 5)
    for mode in ("table", "exact"):
        psf = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.5, fwhm=3.5), shifts, mode=mode)
        # the limit is where P0 + F R reaches -1 % of the peak
        limit = psf.first_order_flux
        assert 1e7 < limit < 1e8
        image = psf.star_image(1e6)
        assert image.min() > -1e-3 * image.max()
        with pytest.warns(BFPSFWarning, match="beyond the first-order BF model"):
            image = psf.star_image(1e9)
        assert image.min() < -0.01 * image.max()
        with pytest.warns(BFPSFWarning, match="beyond the first-order BF model"):
            psf.evaluate(0.0, 0.0, 1e9, 0.0, 0.0)
