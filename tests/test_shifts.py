"""The boundary-shift container: symmetries of G15 (eq. par, trans, sum-rule) and area."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bfpsf.errors import BFPSFValueError
from bfpsf.shifts import BoundaryShifts


def exponential_profile(scale, length):
    return lambda r: scale * np.exp(-r / length)


@settings(max_examples=40, deadline=None)
@given(radius=st.integers(1, 6), scale=st.floats(1e-9, 1e-6), length=st.floats(0.3, 3.0))
def test_radial_profile_obeys_symmetries_and_sum_rule(radius, scale, length):
    shifts = BoundaryShifts.from_radial_profile(exponential_profile(scale, length), radius)
    residuals = shifts.symmetry_residuals()
    for key, value in residuals.items():
        assert value <= 1e-12 * scale, key
    m = radius
    # Translation: a^N(dx, dy) = -a^S(dx, dy - 1); a^E(dx, dy) = -a^W(dx - 1, dy).
    np.testing.assert_array_equal(shifts.north[1:, :], -shifts.south[:-1, :])
    np.testing.assert_array_equal(shifts.east[:, 1:], -shifts.west[:, :-1])
    # Parity pairs N with S and E with W: a^N(dx, dy) = a^S(-dx, -dy).
    np.testing.assert_allclose(shifts.north, shifts.south[::-1, ::-1], rtol=0, atol=1e-15 * scale)
    np.testing.assert_allclose(shifts.east, shifts.west[::-1, ::-1], rtol=0, atol=1e-15 * scale)
    # A charge shrinks its own pixel and grows the nearest neighbours.
    assert shifts.area[m, m] < 0
    assert shifts.north[m, m] < 0 and shifts.north[m + 1, m] > 0


def test_area_is_symmetric_under_quadrant_flips():
    shifts = BoundaryShifts.from_radial_profile(exponential_profile(1e-7, 1.0), 4)
    area = shifts.area
    np.testing.assert_allclose(area, area[::-1, :], atol=1e-20)
    np.testing.assert_allclose(area, area[:, ::-1], atol=1e-20)
    assert shifts.area_quadrant(2).shape == (3, 3)
    assert shifts.area_quadrant()[0, 0] == area[4, 4]


def test_parity_violation_is_refused():
    shifts = BoundaryShifts.from_radial_profile(exponential_profile(1e-7, 1.0), 2)
    north = shifts.north.copy()
    north[2, 2] *= 1.1
    with pytest.raises(BFPSFValueError, match="violate parity"):
        BoundaryShifts(north, shifts.east)


@pytest.mark.parametrize("shape", [(4, 4), (3, 5), (3,)])
def test_bad_shapes_are_refused(shape):
    with pytest.raises(BFPSFValueError, match="square 2-D array of odd size"):
        BoundaryShifts(np.zeros(shape), np.zeros(shape))


def test_padding_and_scaling_keep_the_physics():
    shifts = BoundaryShifts.from_radial_profile(exponential_profile(1e-7, 1.0), 2)
    padded = shifts.padded(4)
    np.testing.assert_array_equal(padded.area[2:-2, 2:-2], shifts.area)
    assert padded.area.sum() == pytest.approx(0, abs=1e-20)
    assert shifts.scaled(2.0).area[2, 2] == 2 * shifts.area[2, 2]
    assert shifts.scaled(1.0) == shifts
