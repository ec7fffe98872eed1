"""Brighter-fatter slope fits: units, error calibration, peak range, flags (issue 4)."""

import numpy as np
import pytest
from astropy.table import Table

from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.measure.slopes import PEAK_UNIT_E, bf_slopes, fit_bf_slope


def linear_data(rng, n=200, slope=0.04, intercept=1.8, noise=0.01, peak_max=1.5e5):
    peak = rng.uniform(1e3, peak_max, n)
    size = intercept + slope * peak / PEAK_UNIT_E + noise * rng.standard_normal(n)
    return peak, size


def test_units_and_relative_percent():
    peak = np.array([0.0, 1e5, 2e5])
    size = np.array([2.0, 2.05, 2.10])
    fit = fit_bf_slope(peak, size, size_err=np.full(3, 1e-3))
    # 0.05 pixel per 100 ke- of peak; relative: 100 * 0.05 / 2 = 2.5 % per 100 ke-
    assert fit.slope == pytest.approx(0.05)
    assert fit.intercept == pytest.approx(2.0)
    assert fit.relative_percent == pytest.approx(2.5)
    assert fit.range_percent == pytest.approx(5.0)        # over the 200 ke- fitted
    assert fit.predict(1e5) == pytest.approx(2.05)
    assert set(fit.as_dict(short=True)) == {"slope", "slope_err", "intercept",
                                            "relative_percent"}


def test_errors_are_calibrated():
    # over 400 realisations the pulls (fit - truth) / error have unit spread, weighted and not
    rng = np.random.default_rng(0)
    pulls_weighted, pulls_unweighted = [], []
    for _ in range(400):
        peak, _ = linear_data(rng, n=50)
        errors = 0.005 + 0.02 * rng.uniform(size=50)
        size = 1.8 + 0.04 * peak / PEAK_UNIT_E + errors * rng.standard_normal(50)
        weighted = fit_bf_slope(peak, size, size_err=errors, scale_errors=False)
        unweighted = fit_bf_slope(peak, size)
        pulls_weighted.append((weighted.slope - 0.04) / weighted.slope_err)
        pulls_unweighted.append((unweighted.slope - 0.04) / unweighted.slope_err)
    # 400 pulls: the spread is known to 3.5 %, the mean to 0.05
    assert np.std(pulls_weighted) == pytest.approx(1.0, abs=0.1)
    assert np.std(pulls_unweighted) == pytest.approx(1.0, abs=0.1)
    assert abs(np.mean(pulls_weighted)) < 0.15


def test_peak_range_and_nonfinite_values_are_left_out():
    rng = np.random.default_rng(1)
    peak, size = linear_data(rng, noise=0.002)
    # blooming above 1.3e5 e-: sizes jump; NaN sizes of failed measurements
    size = np.where(peak > 1.3e5, size + 0.3, size)
    size[:5] = np.nan
    fit = fit_bf_slope(peak, size, max_peak_e=1.3e5)
    assert fit.slope == pytest.approx(0.04, abs=4 * fit.slope_err)
    assert fit.n_points == np.sum((peak <= 1.3e5) & np.isfinite(size))
    assert fit.peak_max_e <= 1.3e5


def test_bad_input_raises():
    with pytest.raises(BFPSFValueError, match="at least 3 usable objects, got 2$"):
        fit_bf_slope([1e4, 2e4], [1.0, 1.1])
    # a range is named only when one is given, open ends as 0 and inf ("[None, None]" before)
    with pytest.raises(BFPSFValueError, match=r"in the peak range \[0, 15000\] e-, got 1$"):
        fit_bf_slope([1e4, 2e4, 3e4], [1.0, 1.1, 1.2], max_peak_e=1.5e4)
    with pytest.raises(BFPSFInputError, match="differ in length"):
        fit_bf_slope([1e4, 2e4, 3e4], [1.0, 1.1])
    with pytest.raises(BFPSFValueError, match="span no range"):
        fit_bf_slope([1e4] * 4, [1.0, 1.1, 1.2, 1.0])


def test_bf_slopes_on_table_uses_flags_and_errors():
    rng = np.random.default_rng(2)
    peak, sigma_x = linear_data(rng, slope=0.03, noise=0.003)
    sigma_y = 1.8 + 0.05 * peak / PEAK_UNIT_E + 0.003 * rng.standard_normal(peak.size)
    flags = np.zeros(peak.size, dtype=int)
    flags[:20] = 8                                  # saturated: left out
    sigma_x[:20] = 5.0
    table = Table({"peak_e": peak, "sigma_x": sigma_x, "sigma_y": sigma_y,
                   "iq": np.sqrt(sigma_x * sigma_y), "flags": flags,
                   "sigma_x_err": np.full(peak.size, 0.003),
                   "sigma_y_err": np.full(peak.size, 0.003),
                   "iq_err": np.full(peak.size, 0.003)})
    result = bf_slopes(table)
    assert result["n_stars"] == peak.size - 20
    assert result["x"].slope == pytest.approx(0.03, abs=4 * result["x"].slope_err)
    assert result["y"].slope == pytest.approx(0.05, abs=4 * result["y"].slope_err)
    assert result["x"].slope < result["iq"].slope < result["y"].slope
    with pytest.raises(BFPSFInputError, match="lacks columns"):
        bf_slopes(Table({"peak_e": peak}))


def test_stars_of_one_flux_give_a_slope_with_a_warning(caplog):
    """A frame whose stars share one flux (peaks within 5 %): the slope is returned with its
    (large) error, and a warning says the flux span cannot set it; stars of many fluxes
    give no warning."""
    import logging

    rng = np.random.default_rng(4)
    peak = 5e4 * (1 + 0.01 * rng.standard_normal(60))
    size = 1.3 + 0.01 * rng.standard_normal(60)
    table = Table({"peak_e": peak, "sigma_x": size, "sigma_y": size, "iq": size})
    with caplog.at_level(logging.WARNING, logger="bfpsf"):
        result = bf_slopes(table)
    assert result["x"].slope_err > 0.1
    assert "a factor 1.0" in caplog.text and "too short a lever arm" in caplog.text
    caplog.clear()
    peak, size = linear_data(rng)
    with caplog.at_level(logging.WARNING, logger="bfpsf"):
        bf_slopes(Table({"peak_e": peak, "sigma_x": size, "sigma_y": size, "iq": size}))
    assert "lever arm" not in caplog.text


def test_images_of_different_seeing_get_their_own_intercept():
    """Stars of three exposures whose seeing differs by 1 % and whose bright stars fall in
    the sharper one: one intercept turned the seeing into a slope (a new user's IQ slope
    0.0091 beside sigma_x 0.0136 and sigma_y 0.0164); an intercept per ``image`` gives the
    slope within 3 sigma, and every fit keeps the rows it used."""
    rng = np.random.default_rng(4)
    tables = []
    for image, (seeing, top) in enumerate(((1.00, 4e4), (0.99, 1.5e5), (1.01, 8e4))):
        peak = rng.uniform(3e3, top, 80)
        size = 1.6 * seeing + 0.015 * peak / PEAK_UNIT_E + 0.002 * rng.standard_normal(80)
        tables.append(Table({"image": np.full(80, image), "peak_e": peak, "sigma_x": size,
                             "sigma_y": size, "iq": size, "sigma_x_err": np.full(80, 0.002),
                             "sigma_y_err": np.full(80, 0.002), "iq_err": np.full(80, 0.002)}))
    from astropy.table import vstack

    table = vstack(tables)
    fits = bf_slopes(table)
    assert abs(fits["iq"].slope - 0.015) < 3 * fits["iq"].slope_err
    single = bf_slopes(table[[name for name in table.colnames if name != "image"]])
    assert abs(single["iq"].slope - 0.015) > 5 * single["iq"].slope_err
    assert fits["x"].rows.shape == (len(table),) and fits["x"].rows.sum() == fits["x"].n_points
    # fitted again on those rows, without clipping: the same slope
    again = bf_slopes(table, rows={"x": fits["x"].rows})
    assert again["x"].slope == pytest.approx(fits["x"].slope, abs=1e-12)
