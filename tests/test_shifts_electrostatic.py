"""The electrostatic model of the boundary shifts (Astier & Regnault 2023) and its fit.

Truth: the analytic field of a point charge between two conducting planes (integrated
numerically), the symmetries of a^X (G15 eq. par, trans, sum-rule), closure on the model's own
areas, and GalSim's SiliconSensor (its noise-free small-charge area response, fitted, against
the boundary shifts its photons land with).
"""

import numpy as np
import pytest
from scipy import integrate

from bfpsf.calibration.boundary_shifts import shift_warnings, solve_boundary_shifts
from bfpsf.calibration.electrostatic_fit import fit_electrostatic
from bfpsf.calibration.shifts_electrostatic import (ElectrostaticGeometry, _unit_shift,
                                                    electrostatic_area, electrostatic_shifts)
from bfpsf.errors import BFPSFValueError

#: An E2V-like geometry (pixels): N/S boundaries fixed close to the charge, E/W ones higher.
GEOMETRY = ElectrostaticGeometry(thickness=10.0, charge_height=0.01, horizontal_height=0.02,
                                 vertical_height=0.25, half_width_x=0.4, half_width_y=0.2)


def test_unit_shift_matches_quadrature_of_the_image_series():
    """A point-like sheet: the field E_n of the image series integrated over z and along a
    unit boundary by adaptive quadrature, against the compiled kernel's Gauss-Legendre sum."""
    geometry = ElectrostaticGeometry(thickness=10.0, charge_height=0.5, horizontal_height=1.0,
                                     vertical_height=1.0, half_width_x=1e-4, half_width_y=1e-4)
    normal, centre = 1.3, 0.4

    def field(z, along):
        total = 0.0
        for n in range(-60, 61):
            for height, sign in ((2 * n * 10.0 + 0.5, 1.0), (2 * n * 10.0 - 0.5, -1.0)):
                total += sign * normal / (normal**2 + along**2 + (z - height)**2) ** 1.5
        return total

    expected, _ = integrate.dblquad(field, centre - 0.5, centre + 0.5, 1.0, 10.0,
                                    epsabs=1e-12)
    value = _unit_shift(np.array([centre]), np.array([normal]), 1.0, geometry, 1e-4, 1e-4)
    # six image pairs: the truncation is (1.4 / 120)^3 of the field; 8 nodes along the
    # boundary: 1e-4
    assert -value[0] == pytest.approx(expected, rel=1e-4)


def test_shifts_are_physical_and_symmetric():
    shifts = electrostatic_shifts(GEOMETRY, 1e-6, 5)
    residuals = shifts.symmetry_residuals()
    assert residuals["parity_N"] < 1e-20 and residuals["parity_E"] < 1e-20
    m = shifts.radius
    # a repulsive charge pushes all four boundaries of its pixel in, and its neighbours grow
    assert shifts.north[m, m] < 0 and shifts.east[m, m] < 0
    area = shifts.area_quadrant(3)
    assert area[0, 0] < 0 and np.all(area.ravel()[1:] > 0)
    # boundaries fixed lower (N/S here) see more of the drift: they move more, and the
    # neighbour across them, (0, 1), gains more area than (1, 0)
    assert shifts.north[m, m] < shifts.east[m, m]
    assert area[1, 0] > area[0, 1]
    # mirror symmetry x -> -x of the N shifts and y -> -y of the E shifts
    np.testing.assert_allclose(shifts.north, shifts.north[:, ::-1], rtol=1e-12, atol=1e-22)
    np.testing.assert_allclose(shifts.east, shifts.east[::-1, :], rtol=1e-12, atol=1e-22)
    # the area of the quadrant table is the divergence of the shifts
    np.testing.assert_allclose(electrostatic_area(GEOMETRY, 1e-6, 4), shifts.area_quadrant(4),
                               rtol=1e-12, atol=1e-22)


def test_geometry_is_validated():
    with pytest.raises(BFPSFValueError, match="must lie below both boundary heights"):
        ElectrostaticGeometry(10.0, 1.0, 0.5, 2.0, 0.3, 0.3)
    with pytest.raises(BFPSFValueError, match="inside its pixel"):
        ElectrostaticGeometry(10.0, 0.1, 0.5, 2.0, 0.6, 0.3)
    with pytest.raises(BFPSFValueError, match="a\\(0, 0\\) must be negative"):
        fit_electrostatic(np.ones((3, 3)))
    with pytest.raises(BFPSFValueError, match="method must be one of"):
        solve_boundary_shifts(-np.eye(3), method="nosuch")


def test_fit_closes_on_the_model_own_areas():
    """Noise-free areas of a known geometry: the fit returns its shifts."""
    truth = electrostatic_shifts(GEOMETRY, 2e-6, 5)
    area = truth.area_quadrant(4)
    fit = fit_electrostatic(area, 1e-3 * abs(area[0, 0]) * np.ones_like(area), n_samples=0)
    m = truth.radius
    # The polish stops on relative tolerances (ftol = xtol = gtol = 1e-10), so the residual it
    # leaves scales with the data, not with the errors: chi2 from 2e-8 to 3.6e-6 has been seen
    # across machines and library versions (whitened data norm ~1e3). Closing means a residual
    # below 1e-5 of the data's norm: 25x above the worst seen, and 1e-3 of one error per lag
    # summed over the 25 lags, far below what would move the shifts by the tolerance below.
    data_norm = np.linalg.norm(area / (1e-3 * abs(area[0, 0])))
    assert np.sqrt(fit.chi2) < 1e-5 * data_norm
    np.testing.assert_allclose(fit.shifts.north[m - 2:m + 3, m - 2:m + 3],
                               truth.north[m - 2:m + 3, m - 2:m + 3], atol=2e-3 * 2e-6)
    np.testing.assert_allclose(fit.shifts.east[m - 2:m + 3, m - 2:m + 3],
                               truth.east[m - 2:m + 3, m - 2:m + 3], atol=2e-3 * 2e-6)


def test_errors_come_from_refits_and_cover_the_truth():
    """Refits of redrawn areas: the truth lies within the errors; the amplitude's error grows
    with the noise, while the N/E split's is bounded by the physical range of the geometry."""
    truth = electrostatic_shifts(GEOMETRY, 2e-6, 3)
    area = truth.area_quadrant(2)
    rng = np.random.default_rng(3)
    amplitude_errors = {}
    for scale in (0.005, 0.03):
        area_err = scale * abs(area[0, 0]) * np.ones_like(area)
        noisy = area + rng.standard_normal(area.shape) * area_err
        fit = fit_electrostatic(noisy, area_err, n_samples=8, seed=1)
        m = fit.shifts.radius
        assert fit.samples_north.shape == (8,) + fit.shifts.shape
        for name in ("north", "east"):
            value = getattr(fit.shifts, name)[m, m]
            error = getattr(fit, f"{name}_err")[m, m]
            assert abs(value - getattr(truth, name)[m, m]) < 4 * error, (scale, name)
        amplitude = fit.samples_north[:, m, m] + fit.samples_east[:, m, m]
        amplitude_errors[scale] = np.std(amplitude, ddof=1) / abs(np.mean(amplitude))
    # six times the noise: several times the error of the amplitude (8 refits each)
    assert 2 < amplitude_errors[0.03] / amplitude_errors[0.005] < 15


@pytest.mark.parametrize("sensor", ["lsst_e2v_50_8", "lsst_itl_50_8"])
def test_fit_to_galsim_areas_recovers_the_landing_shifts(sensor):
    """SiliconSensor's noise-free area response to 1e3 e- (calculate_pixel_areas), fitted:
    a^N(0,0), a^E(0,0) and the boundaries of the nearest neighbours against the shifts
    SiliconSensor's photons land with (`silicon_boundary_shifts`, independent)."""
    from bfpsf.interop.silicon_truth import silicon_area_coefficients, silicon_boundary_shifts

    area = silicon_area_coefficients(sensor, charge=1e3, maxlag=3)
    landing = silicon_boundary_shifts(sensor, charge=1e3, radius=4)
    fit = fit_electrostatic(area, n_samples=0)
    m, k = fit.shifts.radius, landing.radius

    def ratio(name, dx, dy):
        return (getattr(fit.shifts, name)[m + dy, m + dx]
                / getattr(landing, name)[k + dy, k + dx])

    # the N/E split of a(0, 0), which flat-field areas cannot see: within 10 %
    for name in ("north", "east"):
        assert ratio(name, 0, 0) == pytest.approx(1.0, abs=0.10), name
    # the far boundaries of the nearest neighbours, a^N(0,2) and a^E(2,0): within 10 %
    for name, dx, dy in (("north", 0, 2), ("east", 2, 0)):
        assert ratio(name, dx, dy) == pytest.approx(1.0, abs=0.10), (name, dx, dy)
    # Their side boundaries a^E(1,1) (measured +9 to +10 %) and a^N(1,1) (+26 %) are where
    # SiliconSensor's landing and its pixel areas disagree: the landing shifts' own a(1, 0) is
    # 30-45 % above the area response the fit is given and their a(1, 1) 30 % below, and a^N(1,1)
    # and a^E(1,1) both enter a(1, 1); no area-faithful solution can match the landing there.
    landing_area = landing.area_quadrant(1)
    assert landing_area[0, 1] / area[0, 1] > 1.2
    assert landing_area[1, 1] / area[1, 1] < 0.8
    assert ratio("east", 1, 1) == pytest.approx(1.0, abs=0.12)
    assert ratio("north", 1, 1) == pytest.approx(1.0, abs=0.35)


def test_warnings_name_an_unphysical_or_poorly_determined_split():
    """`shift_warnings` says in words when a boundary of the charged pixel moves outward (what
    the G15 Ei solver returned on small E2V flats) and when the split is poorly determined."""
    import dataclasses

    from bfpsf.shifts import BoundaryShifts

    truth = electrostatic_shifts(GEOMETRY, 2e-6, 4)
    area = truth.area_quadrant(3)
    fit = fit_electrostatic(area, 1e-3 * abs(area[0, 0]) * np.ones_like(area), n_samples=4)
    assert not [text for text in shift_warnings(fit) if "split" in text or "unphysical" in text]
    m = truth.radius
    # the E/W boundaries moved outward, N/S inward by the same amount: a(0, 0) unchanged
    north, east = truth.north.copy(), truth.east.copy()
    shift = 1.5 * abs(east[m, m])
    north[m, m] -= shift
    north[m + 1, m] += shift
    east[m, m] += shift
    east[m, m + 1] -= shift
    unphysical = BoundaryShifts(north, east)
    assert unphysical.area[m, m] == pytest.approx(truth.area[m, m], rel=1e-12)
    text = shift_warnings(dataclasses.replace(fit, shifts=unphysical))
    assert any(line.startswith("unphysical boundary shifts: a^E(0,0) = ") for line in text)
    # samples that disagree on the split by 50 %
    spread = dataclasses.replace(fit, samples_north=np.array([truth.north, north]),
                                 samples_east=np.array([truth.east, east]))
    assert any(line.startswith("N/E split of a(0,0) poorly determined")
               for line in shift_warnings(spread))


@pytest.mark.slow
@pytest.mark.parametrize("sensor, maxlag, north, east", [
    ("lsst_e2v_50_8", 2, 0.95, 1.13), ("lsst_e2v_50_8", 4, 0.96, 1.13),
    ("lsst_e2v_50_8", 6, 0.96, 1.13), ("lsst_itl_50_8", 2, 0.99, 1.01),
    ("lsst_itl_50_8", 4, 0.96, 1.07), ("lsst_itl_50_8", 6, 0.96, 1.07)])
def test_split_of_noise_free_areas_against_maxlag(sensor, maxlag, north, east):
    """The N/E split of a(0, 0) from noise-free areas at other maxlags than the 3 of
    `test_fit_to_galsim_areas_recovers_the_landing_shifts`: deeper lags do not sharpen it
    (measured ratios to the landing truth, as the README and `bfpsf.calibration.maxlag` quote
    them, to 0.01)."""
    from bfpsf.interop.silicon_truth import silicon_area_coefficients, silicon_boundary_shifts

    area = silicon_area_coefficients(sensor, charge=1e3, maxlag=maxlag)
    landing = silicon_boundary_shifts(sensor, charge=1e3, radius=4)
    fit = fit_electrostatic(area, n_samples=0)
    m, k = fit.shifts.radius, landing.radius
    assert fit.shifts.north[m, m] / landing.north[k, k] == pytest.approx(north, abs=0.01)
    assert fit.shifts.east[m, m] / landing.east[k, k] == pytest.approx(east, abs=0.01)


def test_fits_stopped_by_their_evaluation_bound_are_reported():
    """Every fit is bounded; one that stops on the bound is counted and warned about, never
    passed off as converged (issue 25)."""
    truth = electrostatic_shifts(GEOMETRY, 2e-6, 3)
    area = truth.area_quadrant(2)
    area_err = 0.01 * abs(area[0, 0]) * np.ones_like(area)
    converged = fit_electrostatic(area, area_err, n_samples=3, seed=1)
    assert converged.n_unconverged == 0
    assert not [w for w in shift_warnings(converged) if "evaluation bound" in w]
    bounded = fit_electrostatic(area, area_err, n_samples=3, seed=1, max_evaluations=2)
    assert bounded.n_unconverged >= 1
    assert any("stopped on their evaluation bound" in w for w in shift_warnings(bounded))
