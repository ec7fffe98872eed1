"""The signature test's statistic has the null distribution it states (`bfpsf.diagnosis.signature`):
when the data hold exactly the template (plus Gaussian noise of the stated errors), its
p-values are uniform, so it rejects a true effect at the rate alpha; when the template is
wrong in one part, it rejects it there."""

import numpy as np
import pytest

from bfpsf.diagnosis.signature import contradiction, parity_test, signature_test
from bfpsf.diagnosis.tables import SizeTable


def _problem(rng, n=40):
    """A residual of 2n points (two 'axes'), an intercept per axis, and a template."""
    template = np.concatenate([np.linspace(0.1, 1.0, n), 0.6 * np.linspace(0.1, 1.0, n)])
    base = np.zeros((2 * n, 2))
    base[:n, 0] = base[n:, 1] = 1.0
    sigma = np.full(2 * n, 0.05)
    parts = {"axis": [("x", np.arange(2 * n) < n), ("y", np.arange(2 * n) >= n)]}
    return template[:, None], base, sigma, parts


def test_p_values_are_uniform_under_the_null():
    """1000 data sets with the template's own shape: the fraction of p-values below 0.05,
    0.2 and 0.5 is that level within 3 binomial sigma (tau = 0: the exact chi-square)."""
    rng = np.random.default_rng(0)
    template, base, sigma, parts = _problem(rng)
    p_values = []
    for _ in range(1000):
        residual = 0.3 + 0.8 * template[:, 0] + sigma * rng.standard_normal(sigma.size)
        test = signature_test(residual, sigma, base, template, parts, tolerance={})
        p_values.append(test["axis"]["p_value"])
    p_values = np.array(p_values)
    for level in (0.05, 0.2, 0.5):
        assert np.mean(p_values < level) == pytest.approx(
            level, abs=3 * np.sqrt(level * (1 - level) / p_values.size))


def test_a_one_axis_residual_is_rejected_by_axis():
    rng = np.random.default_rng(1)
    template, base, sigma, parts = _problem(rng)
    n = sigma.size // 2
    residual = np.concatenate([0.8 * template[:n, 0], np.zeros(n)])
    residual = residual + sigma * rng.standard_normal(sigma.size)
    test = signature_test(residual, sigma, base, template, parts)
    assert contradiction(test) == "axis"
    assert test["axis"]["dof"] == 1 and test["axis"]["p_value"] < 1e-6
    # a part the template does not reach is no test
    only_x = template * (np.arange(sigma.size) < n)[:, None]
    assert signature_test(residual, sigma, base, only_x, parts) == {}


def test_a_part_tests_a_candidate_only_where_it_measures_its_prediction():
    """A candidate measured in the flats' linearity whose star sizes it changes by a fraction
    of their errors (a new user's flats' non-linearity of 4e-4: 0.2 errors) is not
    contradicted "by axis" by an effect outside the catalogue in the X sizes: neither axis
    measures what it predicts (before: p = 4e-22, and the same flats without the smear named
    it). A candidate that predicts measurable sizes is still rejected by the same data."""
    rng = np.random.default_rng(3)
    n = 30
    ramp = np.linspace(0.1, 1.0, n)
    rows = np.arange(3 * n)
    linearity, x, y = rows < n, (rows >= n) & (rows < 2 * n), rows >= 2 * n
    base = np.stack([linearity, x, y], axis=1).astype(float)  # an intercept per part
    sigma = np.where(linearity, 0.001, 0.05)
    parts = {"observable": [("linearity", linearity), ("sizes", x | y)],
             "axis": [("x", x), ("y", y)]}
    outside = np.where(x, np.tile(ramp, 3), 0.0)  # along X only
    for size_share, named in ((0.01, True), (1.0, False)):
        template = np.tile(ramp, 3) * np.where(linearity, 1.0, size_share)
        residual = 0.5 * template + outside + sigma * rng.standard_normal(sigma.size)
        test = signature_test(residual, sigma, base, template[:, None], parts)
        assert (contradiction(test) is None) == named, test
        if not named:
            assert contradiction(test) == "axis"
        # the linearity alone measures the named candidate, and finds it where it was fitted
        assert ("observable" in test) == named and "axis" not in test or not named


def test_a_candidate_fitted_on_parts_that_cannot_measure_it_is_contradicted():
    """The converse (a row smear in a new user's star sizes fitted a gain non-linearity the
    flats' linearity, the part that measures it, did not hold): the star sizes hold an
    effect outside the catalogue 40 of their errors large, where the candidate predicts 1.6
    of their errors; the whole template's fit, pulled by them, is 8 errors of the linearity
    from what the linearity reads, so the candidate is contradicted by the observable (its
    support), where no dimension had tested it."""
    rng = np.random.default_rng(5)
    n = 30
    ramp = np.linspace(0.1, 1.0, n)
    rows = np.arange(2 * n)
    linearity, sizes = rows < n, rows >= n
    base = np.stack([linearity, sizes], axis=1).astype(float)
    sigma = np.where(linearity, 0.001, 0.05)
    parts = {"observable": [("linearity", linearity), ("sizes", sizes)]}
    template = np.tile(ramp, 2) * np.where(linearity, 0.1, 1.0)
    # 40 errors of the sizes' amplitude (an intercept per part is fitted beside it)
    outside = np.where(sizes, np.tile(ramp, 2), 0.0) * 40 * 0.05 / np.sqrt(
        np.sum((ramp - ramp.mean()) ** 2))
    residual = outside + sigma * rng.standard_normal(sigma.size)
    test = signature_test(residual, sigma, base, template[:, None], parts)
    entry = test["observable"]
    print(entry["support"])
    assert entry["measured_in"] == ["linearity"] and entry["dof"] == 1
    assert abs(entry["support"]["amplitude"][0]) < 4 * entry["support"]["error"][0]
    assert contradiction(test) == "observable" and entry["p_value"] < 1e-4


def test_parity_null_and_signal():
    """Skewness slopes of pure noise: p-values uniform (chi-square, 2 dof); a skewness that
    grows with peak: rejected."""
    rng = np.random.default_rng(2)
    peak = np.tile(np.linspace(1e4, 1.2e5, 6), 4)
    flat = np.full(peak.size, 1.5)
    p_values = []
    for _ in range(400):
        table = SizeTable(peak, flat, flat, flat * 0.01, flat * 0.01,
                          skew_x=0.01 * rng.standard_normal(peak.size),
                          skew_y=0.01 * rng.standard_normal(peak.size),
                          skew_x_err=np.full(peak.size, 0.01),
                          skew_y_err=np.full(peak.size, 0.01))
        p_values.append(parity_test(table)["p_value"])
    assert np.mean(np.array(p_values) < 0.1) == pytest.approx(0.1, abs=3 * np.sqrt(0.09 / 400))
    table = SizeTable(peak, flat, flat, flat * 0.01, flat * 0.01, skew_x=np.zeros(peak.size),
                      skew_y=0.05 * peak / 1e5, skew_x_err=np.full(peak.size, 0.01),
                      skew_y_err=np.full(peak.size, 0.01))
    assert not parity_test(table)["matches"]
    assert parity_test(SizeTable(peak, flat, flat, flat * 0.01, flat * 0.01)) is None


def test_flux_shape_tells_a_flux_squared_effect_from_a_linear_residual():
    """`flux_shape_test`, tau = 0: with the data holding the flux^2 template, its amplitude
    beside a linear term stays put and the p-values are uniform (500 sets: the fraction
    below 0.05 within 3 binomial sigma); a residual linear in flux, which the flux^2
    template also fits, moves it and is rejected in every set."""
    from bfpsf.diagnosis.signature import flux_shape_test

    rng = np.random.default_rng(4)
    x = np.linspace(0.05, 1.5, 30)
    base = np.ones((x.size, 1))
    template, linear, sigma = (x ** 2)[:, None], x, np.full(x.size, 0.01)
    p_true, p_linear = [], []
    for _ in range(500):
        noise = sigma * rng.standard_normal(x.size)
        p_true.append(flux_shape_test(0.2 + 0.5 * x ** 2 + noise, sigma, base, template,
                                      linear, tolerance=0.0)["p_value"])
        p_linear.append(flux_shape_test(0.2 + 0.5 * x + noise, sigma, base, template,
                                        linear, tolerance=0.0)["p_value"])
    assert np.mean(np.array(p_true) < 0.05) == pytest.approx(0.05, abs=3 * np.sqrt(
        0.05 * 0.95 / 500))
    assert max(p_linear) < 1e-3


def test_template_tolerance_is_a_factor_not_a_licence():
    """`one_amplitude_chi2`: parts whose templates scatter by a factor exp(eta), eta ~
    N(0, tau^2), give p-values near uniform (300 sets, 2 and 3 parts: the fraction below 0.05
    within 3 binomial sigma of 0.05 plus 0.02 for the asymptotic distribution); a part at
    0 +- 0.002 beside one at 0.12 +- 0.001 is rejected far beyond 3.3 sigma at tau = 0.3 (the
    Gaussian tolerance tau |a| had let it pass at chi2 13.4: a gain non-linearity named from
    stars without brighter-fatter beside linear flats), as is a part of the other sign."""
    from scipy.stats import chi2

    from bfpsf.diagnosis.signature import one_amplitude_chi2

    rng = np.random.default_rng(3)
    for parts in (2, 3):
        p_values = []
        for _ in range(300):
            values = 0.5 * np.exp(0.3 * rng.standard_normal(parts))
            values = values + 0.01 * rng.standard_normal(parts)
            statistic = one_amplitude_chi2(values, np.eye(parts) * 1e-4, 0.3)
            p_values.append(chi2.sf(statistic, parts - 1))
        assert np.mean(np.array(p_values) < 0.05) < 0.05 + 0.02 + 3 * np.sqrt(0.05 * 0.95 / 300)
    errors = np.diag([0.0012, 0.0022]) ** 2
    assert one_amplitude_chi2([0.12, -0.0015], errors, 0.3) > chi2.isf(1e-6, 1)
    assert one_amplitude_chi2([0.12, -0.05], errors, 0.3) > chi2.isf(1e-6, 1)
    assert one_amplitude_chi2([0.12, 0.10], errors, 0.3) < chi2.isf(0.05, 1)
    # tau = 0: the weighted chi2 about the weighted mean
    assert one_amplitude_chi2([1.0, 3.0], np.eye(2), 0.0) == pytest.approx(2.0)


def test_the_dropped_size_scale_is_named_on_the_axis_it_may_cover():
    """`with_scale_parts`: the scale contradicted by axis (X part +1.05 +- 0.21, Y +2.0 +-
    0.2, prior 0.56, as a new user's Y smear on ITL stars): the X entry says the flats' BF
    amplitude may hold it, the Y entry (the effect) does not; an X-only effect (Y part near
    0) leaves its X entry alone, and a scale that was kept changes nothing."""
    from bfpsf.diagnosis.signature import describe_entry
    from bfpsf.diagnosis.unexplained import with_scale_parts

    def entries():
        return [{"observable": "sizes", "axis": axis, "significance": 5.0} for axis in "xy"]

    def nuisance(x, y, against="axis"):
        return {"calibration_scale": {"prior": 0.56, "contradicted_by": against, "signature": {
            "axis": {"parts": ["x", "y"], "amplitudes": [[x], [y]],
                     "errors": [[0.21], [0.2]]}}}}

    x_entry, y_entry = with_scale_parts(entries(), nuisance(1.05, 2.0))
    assert x_entry["scale_part"] == {"value": 1.05, "error": 0.21, "prior": 0.56}
    assert "it may be the calibration" in describe_entry(x_entry)
    assert "scale_part" not in y_entry
    assert "scale_part" not in with_scale_parts(entries()[:1], nuisance(1.4, 0.02))[0]
    assert with_scale_parts(entries(), nuisance(1.05, 2.0, against=None)) == entries()
    # beyond 3 sigma of the prior: not the calibration's
    assert all("scale_part" not in entry
               for entry in with_scale_parts(entries(), nuisance(1.8, 3.0)))
    # a residual that changes over the night (or over the detector) is no calibration error
    # (a new user's night-growing smear read "rising over the night" and "it may be the
    # calibration" in one line)
    growing = [dict(entry, exposure_dependence={"kind": "rising over the night"})
               for entry in entries()]
    assert all("scale_part" not in entry
               for entry in with_scale_parts(growing, nuisance(1.05, 2.0)))


def test_odd_residuals_of_both_axes_are_said_to_lie_along_a_diagonal():
    """`_odd_direction`: X and Y odd with skewness slopes of one sign and within a factor 3
    lie along x = y (opposite signs: x = -y); a single odd axis, or slopes a factor 5 apart,
    give no diagonal (a new user's trail toward (+1, +1) was read as two odd axes)."""
    from bfpsf.diagnosis.signature import describe_entry
    from bfpsf.diagnosis.unexplained import _odd_direction

    def entries(x, y):
        return [{"observable": "sizes", "axis": axis, "parity": "odd", "significance": 10.0,
                 "skew": {"slope_per_1e5": value, "error": 3e-4}}
                for axis, value in (("x", x), ("y", y)) if value is not None]

    both = entries(-0.0040, -0.0037)
    _odd_direction(both)
    assert [entry["odd_direction"] for entry in both] == ["along the x = y diagonal"] * 2
    assert "along the x = y diagonal" in describe_entry(both[0])
    crossed = entries(0.004, -0.003)
    _odd_direction(crossed)
    assert crossed[1]["odd_direction"] == "along the x = -y diagonal"
    for case in (entries(0.004, None), entries(0.005, 0.001)):
        _odd_direction(case)
        assert not any("odd_direction" in entry for entry in case)


def test_a_rejection_says_what_the_parts_read():
    """A rejected candidate's line gives the parts of the dimension that contradicts it (a
    new user's serial trail: "contradicted by parity (p = 5.6e-04)" and nothing of what
    parity saw)."""
    from bfpsf.diagnosis.signature import describe_rejection

    entry = {"delta_bic": -11.2, "contradicted_by": "parity", "p_value": 5.6e-4,
             "signature": {"parity": {"parts": ["skew x", "skew y"],
                                      "amplitudes": [[-0.00215], [-0.00315]],
                                      "errors": [[0.00106], [0.00096]]}}}
    assert describe_rejection("calibration_scale", entry) == (
        "calibration_scale (Delta BIC -11): its signature is contradicted by parity "
        "(p = 5.6e-04; skew x -0.00215 +- 0.0011; skew y -0.00315 +- 0.00096)")
