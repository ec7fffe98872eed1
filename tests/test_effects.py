"""The candidate effects: each extension obeys the physics it claims (conservation, symmetry,
invisibility in flats, agreement with an independent implementation)."""

import galsim
import numpy as np
import pytest
from scipy.special import exp1

from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.model.density import exact_boundary_density
from bfpsf.model.redistribution import redistribute
from bfpsf.shifts import BoundaryShifts
from bfpsf.diagnosis.catalogue import (CATALOGUE, add_shifts, effect_names, get_effect,
                                       quadrupole_shifts)
from bfpsf.diagnosis.tables import (CorrelationTable, LinearityTable, Observables, PTCTable,
                                    SizeTable)
from bfpsf.diagnosis.spot_model import SpotForwardModel


@pytest.fixture(scope="module")
def shifts():
    return BoundaryShifts.from_radial_profile(lambda r: 2e-7 * exp1(0.8 * r), 4)


def test_quadrupole_is_invisible_to_flats(shifts):
    """The X/Y anisotropy extension changes no pixel area (so the flats cannot see it) and
    obeys parity and the sum rule exactly."""
    mode = quadrupole_shifts(shifts, 1.0)
    assert np.abs(mode.area).max() == 0.0
    residuals = mode.symmetry_residuals()
    assert max(residuals.values()) < 1e-20
    m = mode.radius
    scale = 0.5 * (abs(shifts.north[m, m]) + abs(shifts.east[m, m]))
    # source pixel: E/W boundaries out by q s, N/S boundaries in by q s
    assert mode.east[m, m] == pytest.approx(scale)
    assert mode.north[m, m] == pytest.approx(-scale)


def test_quadrupole_moves_bf_from_x_to_y(shifts):
    """q > 0 moves the E/W boundaries of a charged pixel out (it shrinks less in x, more in
    y): sigma_x grows slower with flux, sigma_y faster, by the same amount for a round spot."""
    model = SpotForwardModel(galsim.Gaussian(sigma=1.2), shifts, phases=2)
    peaks = np.array([1e5])
    base_x, base_y = model.sizes(peaks)
    new_x, new_y = model.sizes(peaks, shifts=add_shifts(shifts, quadrupole_shifts(shifts, 0.5)))
    assert new_x[0] < base_x[0] and new_y[0] > base_y[0]
    # round spot, x/y symmetric base shifts: opposite changes of equal size (to 2 %: the
    # moments respond to second order too)
    assert base_x[0] - new_x[0] == pytest.approx(new_y[0] - base_y[0], rel=0.02)


def test_forward_model_is_the_engine(shifts):
    """The forward model's stamps are the model layer's redistribution of the same pixels, with
    G15's density and with the exact (4th-order) boundary density, to rounding."""
    profile = galsim.Gaussian(sigma=0.8)
    model = SpotForwardModel(profile, shifts, phases=1, stamp_size=15, oversampling=8)
    fine = profile.drawImage(nx=120, ny=120, scale=1 / 8, method="no_pixel").array
    pixels, density = exact_boundary_density(fine, 8)
    peak = 1e5
    flux = model.fluxes([peak])[0]
    for option, expected in (("approx", redistribute(flux * pixels, shifts)),
                             ("exact", redistribute(flux * pixels, shifts,
                                                    density=tuple(flux * d for d in density)))):
        stamp = model.stamps([peak], density=option)[0, 0]
        assert np.abs(stamp - expected).max() < 1e-9 * flux
    # the exact density differs from G15's: a real option, not a no-op
    change = model.stamps([peak], density="exact") - model.stamps([peak])
    assert np.abs(change).max() > 1e-3 * np.abs(expected - flux * pixels).max()


def test_exact_density_increases_bf_of_undersampled_spots(shifts):
    """G15 fig. bva: (Q00 + QX)/2 underestimates the BF of small spots, less so of large ones."""
    gains = []
    for sigma in (0.8, 2.0):
        model = SpotForwardModel(galsim.Gaussian(sigma=sigma), shifts, phases=3)
        peaks = np.array([1e4, 1e5])
        approx = np.diff(model.sizes(peaks)[0])[0]
        exact = np.diff(model.sizes(peaks, density="exact")[0])[0]
        gains.append(exact / approx - 1)
    assert gains[0] > 0.05
    assert 0 <= gains[1] < gains[0] / 3


def test_forward_model_quadratic_in_flux(shifts):
    """Without options the size change is the moments of Q + F^2 R: linear in peak to first
    order, so equal steps in peak give nearly equal steps in size."""
    model = SpotForwardModel(galsim.Gaussian(sigma=1.5), shifts, phases=2)
    sx, sy = model.sizes(np.array([0.5e5, 1e5, 1.5e5]))
    steps = np.diff(sx)
    assert steps[0] > 0
    assert steps[1] == pytest.approx(steps[0], rel=0.05)


def test_templates_and_testability(shifts):
    peaks = np.linspace(1e4, 1e5, 5)
    model = SpotForwardModel(galsim.Gaussian(sigma=1.2), shifts, phases=2)
    sx, sy = model.sizes(peaks)
    sizes = SizeTable(peaks, sx, sy, np.full(5, 1e-4), np.full(5, 1e-4))
    observables = Observables(sizes=sizes, spot_model=model)
    names = {effect.name: effect.templates(observables) for effect in CATALOGUE}
    # no colour, no correlation table, no area table: these cannot be tested
    assert names["chromatic_size"] == {} and names["readout_pedestal"] == {}
    assert names["sum_rule_tail"] == {}
    for name in ("gain_nonlinearity", "xy_anisotropy", "second_order", "boundary_density",
                 "flux_diffusion"):
        template = names[name]["sizes"]
        assert template.shape == (10, 1) and np.all(np.isfinite(template))
    # diffusion: d sigma = d peak / (2 sigma) per 1e5 e- of peak
    diffusion = names["flux_diffusion"]["sizes"][:, 0]
    assert diffusion[:5] == pytest.approx(peaks / 1e5 / (2 * sx))
    # second order grows faster than linearly with the peak
    second = names["second_order"]["sizes"][:5, 0]
    assert second[-1] / second[0] > 1.5 * peaks[-1] / peaks[0]


def test_pedestal_template():
    table = CorrelationTable(np.array([1e4, 5e4, 1e5]), ((1, 0), (0, 1)), np.zeros((3, 2)),
                             np.full((3, 2), 1e-3))
    observables = Observables(correlations=table)
    design = get_effect("readout_pedestal").templates(observables)["correlations"]
    assert design.shape == (6, 2)
    assert np.array_equal(design[:3, 0], np.ones(3)) and np.array_equal(design[3:, 1], np.ones(3))


def test_catalogue_and_errors():
    assert set(effect_names()) >= {"gain_nonlinearity", "readout_pedestal", "xy_anisotropy",
                                   "second_order", "boundary_density", "chromatic_size",
                                   "flux_diffusion"}
    with pytest.raises(BFPSFValueError, match="unknown effect 'tree_rings'"):
        get_effect("tree_rings")
    with pytest.raises(BFPSFInputError, match="no observable given"):
        Observables()
    with pytest.raises(BFPSFInputError, match="a size table needs a spot_model"):
        Observables(sizes=SizeTable([1, 2, 3], [1, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]))
    with pytest.raises(BFPSFInputError, match="mean_err_e must be positive"):
        LinearityTable([1, 2], [1, 2], [0, 1])
    with pytest.raises(BFPSFValueError, match="profile must be a galsim.GSObject"):
        SpotForwardModel("gaussian", BoundaryShifts.from_radial_profile(lambda r: 1e-7 / r, 2))


def test_ptc_table_and_nonlinearity_ptc_template():
    """The gain non-linearity's PTC template is the first-order change of the variance at a
    fixed measured mean: for V = m + a m^2, (3 m^2 + 2 a m^3) / 1e5 (analytic)."""
    a = -1e-6
    mean = np.linspace(1e4, 1.2e5, 6)
    model = mean + a * mean ** 2
    table = PTCTable(mean, model, np.full(6, 100.0), model, 1 + 2 * a * mean, sum_rule_err=1e-7)
    templates = get_effect("gain_nonlinearity").templates(Observables(ptc=table))
    assert set(templates) == {"ptc"}
    np.testing.assert_allclose(templates["ptc"][:, 0],
                               (3 * mean ** 2 + 2 * a * mean ** 3) / 1e5, rtol=1e-12)
    assert get_effect("readout_pedestal").templates(Observables(ptc=table)) == {}
    with pytest.raises(BFPSFInputError, match="var_err_e must be positive"):
        PTCTable(mean, model, np.zeros(6), model, np.ones(6))
    with pytest.raises(BFPSFValueError, match="sum_rule_err must be finite"):
        PTCTable(mean, model, np.ones(6), model, np.ones(6), sum_rule_err=-1.0)
