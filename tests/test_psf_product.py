"""The PSF product keeps every constructor option of FluxDependentPSF (schema 3)."""

import inspect

import galsim
import numpy as np
import pytest
from astropy.io import fits

from bfpsf.model.psf import FluxDependentPSF
from bfpsf.shifts import BoundaryShifts

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 3)
MOFFAT = galsim.Moffat(beta=3.0, fwhm=3.0)
#: A star bright enough that the BF term is 1e-2 of P0 (any dropped option shows).
FLUX = 3e6


@pytest.fixture(scope="module")
def base():
    return FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=2, size=11)


def _custom_table(base):
    rng = np.random.default_rng(0)
    return base.bf_table * (1.0 + 0.1 * rng.standard_normal(base.bf_table.shape))


#: One case per constructor option (and the combinations the options require).
CASES = {
    "default": {},
    "origin": {"origin": (10.5, 11.0)},
    "oversampling": {"oversampling": (2, 1)},
    "adu": {"flux_unit": "adu", "gain": 1.7},
    "gain recorded": {"flux_unit": "electron", "gain": 1.7},
    "exact": {"mode": "exact"},
    "buildup_steps": {"mode": "exact", "buildup_steps": 16},
    "buildup in adu": {"mode": "exact", "buildup_steps": 4, "flux_unit": "adu", "gain": 2.5},
    "fill_value": {"fill_value": 1e-3},
    "density_oversampling": {"density_oversampling": 4},
    "parameters": {"flux": 5e4, "x_0": 3.25, "y_0": -1.5},
    "bf_table": "custom",
}


def _options_equal(first, second):
    assert first.keys() == second.keys()
    for key, value in first.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, second[key])
        else:
            assert value == second[key], key


def test_every_constructor_option_is_in_options(base):
    """A new constructor option must reach `options` (and so the product)."""
    names = set(inspect.signature(FluxDependentPSF.__init__).parameters)
    names -= {"self", "data", "shifts", "kwargs", "density_profile"}
    table_options = base.options
    assert names == set(table_options)


@pytest.mark.parametrize("case", list(CASES))
def test_product_round_trips_each_option(base, case, tmp_path):
    options = CASES[case]
    if options == "custom":
        options = {"bf_table": _custom_table(base)}
    data = base.data if "oversampling" not in options else base.data[:, ::2][:, :-1]
    if "origin" in options or "oversampling" in options:
        data = np.ascontiguousarray(data[:21, :21])
    psf = FluxDependentPSF(data, SHIFTS, **options)
    path = tmp_path / "psf.fits"
    psf.write(path)
    back = FluxDependentPSF.read(path)
    _options_equal(back.options, psf.options)
    np.testing.assert_array_equal(back.data, psf.data)
    assert back.shifts == SHIFTS
    y, x = np.mgrid[-8:9, -8:9]
    # Off the data too (fill_value), at an off-grid phase.
    np.testing.assert_array_equal(back.evaluate(x + 0.3, y - 0.2, FLUX, 0.0, 0.0),
                                  psf.evaluate(x + 0.3, y - 0.2, FLUX, 0.0, 0.0))
    assert back(2.0, 1.0) == psf(2.0, 1.0)  # the parameter defaults


def test_buildup_model_reads_back_with_its_bf_term(tmp_path):
    """The issue's case: a 16-step build-up model read back as one-step was 27 % off."""
    psf = FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=2, size=11, mode="exact",
                                       buildup_steps=16)
    one_step = FluxDependentPSF(psf.data, SHIFTS, oversampling=2, mode="exact")
    psf.write(tmp_path / "psf.fits")
    back = FluxDependentPSF.read(tmp_path / "psf.fits")
    static = FLUX * one_step.star_image(1.0)
    bf_back = back.star_image(FLUX) - static
    np.testing.assert_array_equal(bf_back, psf.star_image(FLUX) - static)
    # the one-step term differs by tens of percent: the round trip is not trivially equal
    bf_one = one_step.star_image(FLUX) - static
    assert np.abs(bf_one - bf_back).max() > 0.1 * np.abs(bf_back).max()


def test_schema_2_product_reads_as_a_model_in_electrons(base, tmp_path):
    """Schema 2 kept the images' gain in GAIN for a model in e-: it still means that."""
    path = tmp_path / "old.fits"
    FluxDependentPSF(base.data, SHIFTS, oversampling=2, flux_unit="electron",
                     gain=1.5).write(path)
    with fits.open(path, mode="update") as hdul:
        header = hdul[0].header
        header["BFPSFVER"] = 2
        for key in ("FLUXUNIT", "BUILDUP", "FILLVAL", "DENSOVER", "FLUX", "X_0", "Y_0"):
            del header[key]
    back = FluxDependentPSF.read(path)
    assert back.flux_unit == "electron" and back.gain == 1.5 and back.electrons_per_unit == 1.0


def test_exact_mode_override_drops_the_stored_table(base, tmp_path):
    base.write(tmp_path / "psf.fits")
    exact = FluxDependentPSF.read(tmp_path / "psf.fits", mode="exact")
    assert exact.mode == "exact" and exact.bf_table is None


def test_per_amplifier_shifts_round_trip_and_evaluate_each_amplifier(base, tmp_path):
    """A P0 fitted on two amplifiers keeps each one's shifts (AMPSHIFT, schema 5); the model of
    an amplifier's stars is P0 with its own shifts, the BF term scaling with them."""
    model = base.with_shifts(SHIFTS)
    model.amplifier_shifts = {"C00": SHIFTS.scaled(0.6),
                              "C01": SHIFTS.scaled(1.4).padded(4)}  # another radius
    model.write(tmp_path / "psf.fits")
    back = FluxDependentPSF.read(tmp_path / "psf.fits")
    assert sorted(back.amplifier_shifts) == ["C00", "C01"]
    np.testing.assert_array_equal(back.amplifier_shifts["C00"].padded(4).north,
                                  SHIFTS.scaled(0.6).padded(4).north)
    y, x = np.mgrid[-6:7, -6:7].astype(float)
    static = FLUX * back.evaluate_base(x, y)
    bf = {name: back.for_amplifier(name).evaluate(x, y, FLUX, 0.0, 0.0) - static
          for name in ("C00", "C01")}
    # G15's first-order BF term is linear in the shifts: 0.6 and 1.4 of one profile
    np.testing.assert_allclose(bf["C01"] / 1.4, bf["C00"] / 0.6, atol=1e-9 * FLUX)
    with pytest.raises(ValueError, match="it has none for amplifier 'C02'"):
        back.for_amplifier("C02")
    # an amplifier's model keeps them (as the gridded model does): chaining gives the same
    chained = back.for_amplifier("C00").for_amplifier("C01")
    np.testing.assert_allclose(chained.evaluate(x, y, FLUX, 0.0, 0.0) - static, bf["C01"],
                               atol=1e-12 * FLUX)
    # a single-amplifier product has none: every amplifier gets the model itself
    assert base.for_amplifier("C02") is base
