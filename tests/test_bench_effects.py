"""The bench's effects outside the catalogue do what they claim, on the electrons: charge
conserved, the right axis, parity, position and exposure dependence (`bfpsf.validation.effects_bench`).
"""

import numpy as np
import pytest

from bfpsf.validation.effects_bench import DETECTOR_WIDTH, OUTSIDE_EFFECTS, apply_effect, draw_bench_spots
from bfpsf.diagnosis.odd_moments import skewness, star_skewness
from bfpsf.errors import BFPSFValueError
from bfpsf.moments.adaptive import adaptive_moments_batch
from bfpsf.shifts import BoundaryShifts


@pytest.fixture(scope="module")
def spots():
    from scipy.special import exp1

    shifts = BoundaryShifts.from_radial_profile(lambda r: 2e-7 * exp1(0.8 * r), 3)
    return draw_bench_spots(n_exposures=3, shifts=shifts, peaks_e=(1e4, 1e5))


def _moments(stamps):
    moments = adaptive_moments_batch(stamps)
    return moments, np.asarray(moments.mxx), np.asarray(moments.myy)


@pytest.mark.parametrize("name", OUTSIDE_EFFECTS)
def test_charge_is_conserved(spots, name):
    changed = apply_effect(spots, name, 0.05)
    np.testing.assert_allclose(changed.sum(axis=(1, 2)), spots.stamps.sum(axis=(1, 2)),
                               rtol=1e-12)
    # and the effect is real on bright spots
    assert np.abs(changed - spots.stamps).max() > 1e-3 * spots.stamps.max()


def test_signatures_on_the_electrons(spots):
    """Per effect, the change of the bright spots' moments (noise-free): the axis, the
    parity, the position and the exposure dependence the bench documents."""
    bright = spots.level == 1
    base, mxx0, myy0 = _moments(spots.stamps)
    skew0 = np.array(skewness(spots.stamps, base))
    changes = {}
    for name in OUTSIDE_EFFECTS:
        moments, mxx, myy = _moments(apply_effect(spots, name, 0.05))
        skew = np.array(skewness(apply_effect(spots, name, 0.05), moments))
        changes[name] = (mxx - mxx0, myy - myy0, skew - skew0,
                         np.asarray(moments.y) - np.asarray(base.y))
    dxx, dyy, dskew, _ = changes["one_axis"]
    # X only: the plain (unweighted) second moment along y is untouched exactly; the adaptive
    # Myy of a Moffat follows its re-shaped weight by a fraction of the X change
    changed = apply_effect(spots, "one_axis", 0.05)
    y = np.arange(changed.shape[1])[None, :, None]
    for stamps in (changed, spots.stamps):
        total = stamps.sum(axis=(1, 2))
        mean = (stamps * y).sum(axis=(1, 2)) / total
        plain = (stamps * (y - mean[:, None, None]) ** 2).sum(axis=(1, 2)) / total
        if stamps is changed:
            changed_plain = plain
    np.testing.assert_allclose(changed_plain, plain, rtol=1e-12)
    assert np.all(dxx[bright] > 1e-2) and np.all(np.abs(dyy[bright]) < 0.25 * dxx[bright])
    # position: the smear grows with the distance from the amplifier (x_detector)
    dxx, dyy, _, _ = changes["position"]
    far = spots.x_detector > DETECTOR_WIDTH / 2
    near = spots.x_detector < DETECTOR_WIDTH / 4
    assert dxx[bright & far].mean() > 3 * dxx[bright & near].mean() > 0
    # night: none on the first exposure, growing after
    dxx, dyy, _, _ = changes["night"]
    assert np.abs(dxx[bright & (spots.exposure == 0)]).max() < 1e-9
    assert dyy[bright & (spots.exposure == 2)].mean() > 1.5 * dyy[bright & (spots.exposure == 1)].mean()
    # centroid: the trail moves the centroid to +y with flux and skews the star along y only
    _, _, dskew, dy = changes["centroid"]
    assert dy[bright].min() > 0.01 and dy[bright].mean() > 5 * dy[~bright].mean()
    # (the core moves more than the wings: under the re-centred weight the skew is negative)
    assert abs(dskew[1][bright].mean()) > 100 * np.abs(dskew[0][bright]).max()
    # the even effects leave the odd moments alone
    assert np.abs(changes["one_axis"][2][:, bright]).max() < 0.01 * abs(dskew[1][bright].mean())


def test_bench_input_errors(spots):
    with pytest.raises(BFPSFValueError, match="unknown bench effect 'tree_rings'"):
        apply_effect(spots, "tree_rings", 1.0)
    with pytest.raises(BFPSFValueError, match="either shifts"):
        draw_bench_spots(n_exposures=1)


def test_star_skewness_matches_the_stamp_measurement(spots):
    """On an image of two spots, the table-driven skewness equals that of the stamps."""
    from astropy.table import Table

    stamps = apply_effect(spots, "centroid", 0.05)[[9, 17]]
    image = np.zeros((30, 60))
    image[3:27, 3:27], image[3:27, 33:57] = stamps
    moments = adaptive_moments_batch(stamps)
    table = Table({"x": np.asarray(moments.x) + [3, 33], "y": np.asarray(moments.y) + 3,
                   "mxx": moments.mxx, "myy": moments.myy, "mxy": moments.mxy})
    expected = skewness(stamps, moments)
    got = star_skewness(image, table, half_size=11)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-9)
    # a star too close to the edge has none
    table["x"][0] = 2.0
    assert np.isnan(star_skewness(image, table, half_size=11)[0][0])
