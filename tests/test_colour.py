"""Size-colour correction (G15 section 3.3): an injected relation is removed (issue 4)."""

import numpy as np
import pytest
from astropy.table import Table

from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.measure.colour import apply_size_colour, correct_size_colour, fit_size_colour
from bfpsf.measure.slopes import bf_slopes


def synthetic_table(rng, n=600, bf_slope=0.03, colour_slope_m=-0.25, colour_flux=0.6):
    """Stars with a BF slope and a size-colour relation correlated with flux.

    Colour rises with log peak (``colour_flux`` mag per dex), Mxx and Myy change by
    ``colour_slope_m`` pixel^2 per mag: blue (small colour) stars are broader.
    """
    peak = np.exp(rng.uniform(np.log(2e3), np.log(1.3e5), n))
    colour = 1.0 + colour_flux * np.log10(peak / 1e4) + 0.3 * rng.standard_normal(n)
    sigma_true = 1.9 + bf_slope * peak / 1e5
    noise = 0.004
    mxx = (sigma_true + noise * rng.standard_normal(n))**2 + colour_slope_m * (colour - 1.0)
    myy = (sigma_true + noise * rng.standard_normal(n))**2 + colour_slope_m * (colour - 1.0)
    table = Table({"peak_e": peak, "mxx": mxx, "myy": myy, "mxy": np.zeros(n),
                   "flags": np.zeros(n, dtype=int), "g_i": colour})
    table["sigma_x"] = np.sqrt(mxx)
    table["sigma_y"] = np.sqrt(myy)
    table["iq"] = (mxx * myy)**0.25
    return table


def test_fit_recovers_the_injected_relation():
    table = synthetic_table(np.random.default_rng(0))
    fit = fit_size_colour(table, "g_i", max_peak_e=1e4)
    slope, slope_err = fit.coefficients["mxx"][0], fit.errors["mxx"][0]
    assert slope == pytest.approx(-0.25, abs=3 * slope_err)
    # the nuisance peak term absorbs the BF of the fit sample: 2 sigma dsigma/dpeak
    k, k_err = fit.peak_coefficients["mxx"]
    assert k == pytest.approx(2 * 1.9 * 0.03, abs=3 * k_err)
    assert fit.n_stars == np.sum(table["peak_e"] <= 1e4)
    summary = fit.as_dict()
    assert summary["degree"] == 1 and len(summary["errors"]["myy"]) == 2


def test_correction_restores_the_true_slope():
    rng = np.random.default_rng(1)
    table = synthetic_table(rng)
    raw = bf_slopes(table)
    corrected, fit = correct_size_colour(table, "g_i", max_peak_e=1e4)
    slopes = bf_slopes(corrected, colour_fit=fit)
    # the colour-fit errors move all corrected sizes together: they dominate the slope error
    assert slopes["x"].slope_err_colour > bf_slopes(corrected)["x"].slope_err
    # the colour term fakes a negative slope (bright stars are red, hence narrow)
    assert raw["x"].slope < 0.03 - 10 * raw["x"].slope_err
    for axis in ("x", "y"):
        assert slopes[axis].slope == pytest.approx(0.03, abs=3 * slopes[axis].slope_err)
    # corrected sizes stay at the zero-flux size of a star of the reference colour
    expected = np.sqrt(1.9**2 - 0.25 * (fit.colour_reference - 1.0))
    assert slopes["x"].intercept == pytest.approx(expected, abs=3 * slopes["x"].intercept_err)
    assert "mxx_raw" in corrected.colnames and corrected.meta["size_colour_fit"]["n_stars"] > 0


def test_colour_only_fit_is_biased_by_bf():
    # G15's colour-only fit: BF of the fit sample leaks into the colour coefficient (bright
    # stars are redder and broader), so it comes out less negative than the truth
    fits = [fit_size_colour(synthetic_table(np.random.default_rng(seed)), "g_i",
                            max_peak_e=1e4, peak_term=False) for seed in range(5)]
    mean_slope = np.mean([fit.coefficients["mxx"][0] for fit in fits])
    assert mean_slope > -0.25
    assert not fits[0].peak_coefficients


def test_star_without_colour_is_kept_uncorrected():
    table = synthetic_table(np.random.default_rng(2), n=100)
    table["g_i"][0] = np.nan
    fit = fit_size_colour(table, "g_i")
    corrected = apply_size_colour(table, fit)
    assert len(corrected) == len(table)
    assert corrected["mxx"][0] == table["mxx"][0]
    assert not corrected["colour_corrected"][0] and corrected["colour_corrected"][1]


def test_bad_input_raises():
    table = synthetic_table(np.random.default_rng(3), n=20)
    with pytest.raises(BFPSFInputError, match="no column 'u_g'"):
        fit_size_colour(table, "u_g")
    with pytest.raises(BFPSFValueError, match="needs at least 5 clean stars"):
        fit_size_colour(table, "g_i", max_peak_e=1.0)
    with pytest.raises(BFPSFValueError, match="degree must be a non-negative integer"):
        fit_size_colour(table, "g_i", degree=1.5)
