"""One unresolved blend must not set the brighter-fatter slope: outliers are clipped, and
reported."""

import numpy as np

from bfpsf.measure.slopes import fit_bf_slope


def test_one_blend_does_not_set_the_slope():
    rng = np.random.default_rng(4)
    peak = np.linspace(5e3, 1.2e5, 60)
    truth_slope, intercept = 0.0151, 1.2   # pixels per 100 ke-, pixels
    error = np.full(peak.size, 0.002)
    size = intercept + truth_slope * peak / 1e5 + rng.normal(0.0, 0.002, peak.size)
    size[-3] += 0.8   # an unresolved pair near the bright end: a star twice as wide
    plain = fit_bf_slope(peak, size, size_err=error, clip_nsigma=None)
    robust = fit_bf_slope(peak, size, size_err=error)
    assert abs(plain.slope - truth_slope) > 10 * plain.slope_err / plain.error_scale
    assert robust.n_clipped == 1 and robust.n_points == 59 and plain.n_clipped == 0
    assert abs(robust.slope - truth_slope) < 3 * robust.slope_err
    assert robust.as_dict()["n_clipped"] == 1


def test_clean_data_loses_no_point():
    rng = np.random.default_rng(5)
    peak = np.linspace(5e3, 1.2e5, 200)
    size = 1.2 + 0.015 * peak / 1e5 + rng.normal(0.0, 0.002, peak.size)
    fit = fit_bf_slope(peak, size, size_err=0.002)
    assert fit.n_clipped == 0 and fit.n_points == 200


def test_the_command_says_what_it_left_out(tmp_path, capsys):
    """``bfpsf slope`` names the stars each fit left out (a new user's smear growing with the
    column left 7 of 180 out of the X fit, and the command said only "173 stars fitted")."""
    from astropy.table import Table

    from bfpsf.cli import main

    rng = np.random.default_rng(6)
    peak = np.linspace(5e3, 1.2e5, 60)
    sizes = {name: 1.2 + 0.015 * peak / 1e5 + rng.normal(0.0, 0.002, peak.size)
             for name in ("sigma_x", "sigma_y", "iq")}
    sizes["sigma_x"][[-3, 10]] += 0.8  # two blends in X alone
    Table(dict(peak_e=peak, **sizes)).write(tmp_path / "stars.ecsv")
    assert main(["slope", str(tmp_path / "stars.ecsv")]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == "58 stars fitted; left out beyond 5 robust sigma of the line: 2 in x"
