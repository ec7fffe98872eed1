"""The one weighted and the one clipped linear fit (`bfpsf.least_squares`), against their
analytic truths."""

import numpy as np
import pytest

from bfpsf.least_squares import clipped_least_squares, weighted_least_squares


def test_weighted_least_squares_recovers_a_line_and_its_errors():
    """400 draws of a line with known errors: the parameters' pulls have unit width, and the
    chi-square its degrees of freedom."""
    rng = np.random.default_rng(1)
    x = np.linspace(-1.0, 1.0, 30)
    sigma = 0.1 + 0.2 * np.abs(x)
    design = np.column_stack([np.ones_like(x), x])
    pulls, chi2s = [], []
    for _ in range(400):
        params, covariance, chi2, _ = weighted_least_squares(
            2.0 - 0.5 * x + rng.normal(0.0, sigma), sigma, design)
        pulls.append((params - (2.0, -0.5)) / np.sqrt(np.diag(covariance)))
        chi2s.append(chi2)
    assert np.std(pulls, axis=0) == pytest.approx(1.0, abs=0.1)
    assert np.mean(chi2s) == pytest.approx(28, rel=0.05)


def test_clipped_least_squares_leaves_out_the_outliers_and_states_its_error():
    """A plane over 200 points with 10 % of them 50 sigma off (cosmic rays, blends): the fit
    clips them all and the plane is the truth within its stated error; over 300 draws
    without outliers the pulls have unit width (the covariance from the kept points'
    scatter). A constant is the clipped median. Non-finite points are never kept."""
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-1.0, 1.0, (2, 200))
    design = np.column_stack([np.ones_like(x), x, y])
    truth = np.array([1.0, 0.3, -0.2])
    values = design @ truth + rng.normal(0.0, 0.05, 200)
    bad = rng.choice(200, 20, replace=False)
    values[bad] += 2.5
    values[0] = np.nan
    fit = clipped_least_squares(values, design)
    assert not fit.keep[bad].any() and not fit.keep[0]
    good = 200 - len(set(bad) | {0})
    assert 0.97 * good <= fit.keep.sum() <= good  # 3-sigma clipping: 0.3 % of good points
    assert np.all(np.abs(fit.params - truth) < 4 * np.sqrt(np.diag(fit.covariance)))
    assert fit.scale == pytest.approx(0.05, rel=0.2)
    unclipped = np.linalg.lstsq(design[1:], values[1:], rcond=None)[0]
    assert abs(unclipped[0] - truth[0]) > 0.15  # what the outliers do to a plain fit
    pulls = []
    for _ in range(300):
        values = design @ truth + rng.normal(0.0, 0.05, 200)
        fit = clipped_least_squares(values, design)
        pulls.append((fit.params - truth) / np.sqrt(np.diag(fit.covariance)))
    assert np.std(pulls, axis=0) == pytest.approx(1.0, abs=0.12)
    level = clipped_least_squares(np.array([1.0, 2.0, 3.0, 4.0, 100.0, 2.5, 3.5] * 3),
                                  np.ones((21, 1)), min_kept=3)
    assert level.params[0] == pytest.approx(2.75) and not level.keep[4]  # the median of the rest
