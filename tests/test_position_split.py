"""The per-star test of a position dependence of the BF slope (`bfpsf.diagnosis.position_split`),
on sizes drawn from an analytic model: sigma = s0 + b p + c p^2 (+ d p y / H) + noise."""

import numpy as np
import pytest

from bfpsf.diagnosis.position_split import SPLIT_NSIGMA, describe_split, star_slope_split


def _stars(seed, *, change=0.0, rows_follow_peak=False, n_exposures=8, n_stars=55):
    rng = np.random.default_rng(seed)
    n = n_exposures * n_stars
    peak = 10 ** rng.uniform(np.log10(2e3), np.log10(1.5e5), n)
    exposure = np.repeat(np.arange(n_exposures), n_stars)
    x, y = rng.uniform(0, 300, n), rng.uniform(0, 300, n)
    if rows_follow_peak:  # spots laid out in rows of one level, faint at the bottom
        y = 300 * np.argsort(np.argsort(peak)) / n + rng.uniform(0, 3, n)
    p = peak / 1e5
    # a BF slope that runs with flux (the quadratic), the seeing of each exposure, noise
    base = 1.2 + 0.01 * exposure + 0.02 * p + 0.004 * p ** 2
    sigma_x = base + rng.normal(0, 0.002, n)
    sigma_y = base + change * p * (y / 300 - 0.5) + rng.normal(0, 0.002, n)
    return peak, sigma_x, sigma_y, exposure, x, y


def test_a_slope_growing_with_the_row_is_found_on_its_axis_alone():
    split = star_slope_split(*_stars(1, change=0.01))
    assert split["row"]["y"]["significance"] > 5
    # the change over the span of the stars' rows (about 300 px)
    assert abs(split["row"]["y"]["change"] - 0.01) < 3 * split["row"]["y"]["change_err"]
    for along, axis in (("row", "x"), ("column", "x"), ("column", "y")):
        assert split[along][axis]["significance"] < 3, (along, axis, split[along][axis])
    lines = describe_split(split)
    assert len(lines) == 1 and "Y BF slope" in lines[0] and "rises with the row" in lines[0]


def test_no_dependence_is_found_where_there_is_none():
    """Over seeds, the significance of a null is about |N(0, 1)|; a layout whose rows follow
    the peak (the bench's spots) gives no spurious row dependence from the slope's run with
    flux: the quadratic takes it (a split into halves at the median row read it as one)."""
    values = []
    for seed in range(20):
        for rows_follow_peak in (False, True):
            split = star_slope_split(*_stars(100 + seed, rows_follow_peak=rows_follow_peak))
            values += [entry["significance"] for along in split.values()
                       for entry in along.values()]
            # and the report says it was tested and found nothing (not silence)
            quiet = max(values[-4:]) <= SPLIT_NSIGMA
            assert ("depends on neither" in describe_split(split)[0]) == quiet
    values = np.array(values)
    assert values.max() < 4, values.max()
    assert 0.5 < np.sqrt(np.mean(values ** 2)) < 1.5, np.sqrt(np.mean(values ** 2))


def test_a_binned_none_gives_way_to_the_test_of_every_star():
    """The unexplained report's position dependence: where the bins' mean positions read
    none (a new user's 2 x 1 cells: 2.9 sigma) but every star's slope shows it (10.8 sigma),
    the report says the stars' (per 1000 pixels, as the binned one); a binned finding, or a
    per-star one below 3 sigma, is kept as it is."""
    from types import SimpleNamespace

    from bfpsf.diagnosis.unexplained import _each_star

    split = {"column": {"x": {"slope": 0.0437, "change": 0.0284, "change_err": 0.0026,
                              "significance": 10.9, "span": 245.0},
                        "y": {"slope": 0.04, "change": 0.001, "change_err": 0.002,
                              "significance": 0.5, "span": 245.0}}}
    observables = SimpleNamespace(meta={"position_split": split})
    labels = ("rising with distance from the amplifier", "falling with distance from the "
              "amplifier")
    none = {"kind": "none", "per_1e5_per_unit": 0.05, "error": 0.017, "significance": 2.9}
    found = _each_star(none, observables, "column", "x", labels)
    assert found["kind"] == labels[0] and found["source"] == "each star"
    assert found["per_1e5_per_unit"] == pytest.approx(0.0284 * 1000 / 245.0, rel=1e-12)
    assert found["significance"] == 10.9
    assert _each_star(none, observables, "column", "y", labels) is none
    assert _each_star(none, observables, "row", "x", labels) is none
    binned = dict(none, kind=labels[1], significance=4.0)
    assert _each_star(binned, observables, "column", "x", labels) is binned
    assert _each_star(None, observables, "column", "x", labels)["kind"] == labels[0]
