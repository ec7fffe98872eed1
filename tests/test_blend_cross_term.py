"""The blend cross term of psf_photometry uses the model's own operator, in every mode."""

import gc

import galsim
import numpy as np
import pytest
from astropy.table import Table

from bfpsf.measure.cross_terms import cross_term_image
from bfpsf.measure.photometry import psf_photometry
from bfpsf.model.psf import FluxDependentPSF
from bfpsf.model.density import exact_boundary_density
from bfpsf.model.redistribution import redistribution_delta
from bfpsf.shifts import BoundaryShifts

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 3)
#: Undersampled (FWHM 2.2 px): exact and mean densities differ by several percent.
PROFILE = galsim.Moffat(beta=3.0, fwhm=2.2)
FLUX = 1.5e6
SHAPE = (36, 44)
#: mode name -> from_galsim options
MODES = {
    "table": {},
    "table, exact density": {"density": "exact"},
    "exact": {"mode": "exact"},
    "exact, exact density": {"mode": "exact", "density": "exact"},
    "build-up": {"mode": "exact", "buildup_steps": 8},
    "build-up, exact density": {"mode": "exact", "buildup_steps": 8, "density": "exact"},
}


@pytest.fixture(scope="module", params=list(MODES))
def psf(request):
    return FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=15,
                                        **MODES[request.param])


def _stars(*rows):
    return Table(rows=rows, names=("x_fit", "y_fit", "flux_fit"))


def test_an_isolated_star_has_no_cross_term(psf):
    """The spurious term the one-step mean-density operator left (6-8 % of the star's own BF
    for exact-density and build-up models) is gone: below 2e-5 of it (measured 0.5-2e-6)."""
    table = _stars((20.25, 17.5, FLUX))
    half = psf.half_size
    y, x = np.mgrid[:2 * half + 1, :2 * half + 1]
    own = (psf.evaluate(x, y, FLUX, half + 0.25, half - 0.5)
           - FLUX * psf.evaluate_base(x - half - 0.25, y - half + 0.5))
    cross = cross_term_image(psf, table, SHAPE)
    assert np.abs(cross).max() < 2e-5 * np.abs(own).max()


@pytest.mark.parametrize("mode", [name for name in MODES if name not in ("table", "exact")])
def test_the_old_operator_was_wrong_for_these_models(mode):
    """The check above can fail: the one-step mean-density operator on the same star leaves
    6.5 % (exact density) to 8 % (build-up) of its own BF term (max pixel, FWHM 2.2 px)."""
    psf = FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=15, **MODES[mode])
    half = psf.half_size + 1
    y, x = np.mgrid[:2 * half + 1, :2 * half + 1]
    static = FLUX * psf.evaluate_base(x - half - 0.25, y - half + 0.5)
    own = psf.evaluate(x, y, FLUX, half + 0.25, half - 0.5) - static
    spurious = redistribution_delta(static, SHIFTS) - own
    assert np.abs(spurious).max() > 0.02 * np.abs(own).max()


def _galsim_truth(psf, stars):
    """Charges and exact densities of stars drawn by GalSim on one fine image (no bfpsf
    stamps involved), in the layout of the image."""
    sub = 8
    ny, nx = SHAPE
    total = None
    for x_0, y_0, flux in stars:
        shifted = PROFILE.withFlux(flux).shift(x_0 - (nx / 2 - 0.5), y_0 - (ny / 2 - 0.5))
        total = shifted if total is None else total + shifted
    fine = total.drawImage(nx=nx * sub, ny=ny * sub, scale=1.0 / sub, dtype=np.float64).array
    charge, density = exact_boundary_density(fine, sub)
    return charge, (density if psf.density_profile is not None else None)


def test_blend_cross_term_matches_the_operator_on_the_summed_charge(psf):
    """Two stars 4 px apart: the cross term equals the model's operator on the pair's charge
    minus the same on each star alone, all drawn by GalSim."""
    pair = [(18.25, 17.0, FLUX), (22.0, 19.75, 0.6 * FLUX)]
    truth = psf.charge_delta(*_galsim_truth(psf, pair))
    for star in pair:
        truth -= psf.charge_delta(*_galsim_truth(psf, [star]))
    cross = cross_term_image(psf, _stars(*pair), SHAPE)
    # GalSim's drawing of P0 (FFT, 1e-5) and the spline of the oversampled P0 differ slightly.
    np.testing.assert_allclose(cross, truth, atol=1e-2 * np.abs(truth).max())
    assert np.abs(truth).max() > 1e-3 * FLUX * 0.1  # a real term


@pytest.mark.parametrize("mode", ["build-up", "table, exact density"])
def test_photometry_of_a_blend_with_cross_terms(mode):
    """A noiseless pair with the BF of the model's operator on its summed charge: without
    the cross term the fainter star is 1e-3 too bright; two refits bring both to 1e-5."""
    psf = FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=15,
                                       **MODES[mode])
    pair = [(18.25, 17.0, FLUX), (22.0, 19.75, 0.6 * FLUX)]
    y, x = np.mgrid[:SHAPE[0], :SHAPE[1]]
    # the model's own P0 (so that only the BF is tested), GalSim's density
    static = sum(flux * psf.evaluate_base(x - x_0, y - y_0) for x_0, y_0, flux in pair)
    image = static + psf.charge_delta(static, _galsim_truth(psf, pair)[1])
    errors = {}
    for refits in (0, 2):
        result = psf_photometry(image, psf, positions=np.array(pair)[:, :2],
                                background_e=0.0, read_noise_e=5.0, cross_terms=refits)
        assert result.meta["cross_term_refits"] == refits
        errors[refits] = np.abs(np.array(result["flux_fit"]) / [FLUX, 0.6 * FLUX] - 1)
    assert errors[0].max() > 5e-4
    assert errors[2].max() < 1e-5


def test_a_second_model_of_the_same_class_fits_its_own_groups():
    """photutils caches its group model around the first PSF of a class: a blend fitted
    with one FluxDependentPSF and then with another must give the second model's fluxes,
    the same as when it is fitted first."""
    psf = FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=15)
    other = FluxDependentPSF.from_galsim(galsim.Moffat(beta=3.0, fwhm=2.6), SHIFTS,
                                         oversampling=4, size=15)
    pair = [(18.25, 17.0, FLUX), (22.0, 19.75, 0.6 * FLUX)]
    y, x = np.mgrid[:SHAPE[0], :SHAPE[1]]
    static = sum(flux * psf.evaluate_base(x - x_0, y - y_0) for x_0, y_0, flux in pair)
    image = static + psf.charge_delta(static)

    def fluxes(model):
        result = psf_photometry(image, model, positions=np.array(pair)[:, :2],
                                background_e=0.0, read_noise_e=5.0, cross_terms=0)
        assert list(result["group_size"]) == [2, 2]
        return np.array(result["flux_fit"])

    # photutils' cache holds its classes weakly: without garbage collection they stay
    # cached between the fits, as in a long session (and as the bug needs to show).
    gc.disable()
    try:
        first = fluxes(psf)
        wrong = fluxes(other)  # a broader PSF: different fluxes
        again = fluxes(psf)
    finally:
        gc.enable()
    assert np.abs(wrong / first - 1).max() > 1e-3
    np.testing.assert_array_equal(again, first)


def test_a_read_back_exact_density_table_gets_no_spurious_term(tmp_path):
    """The product keeps the exact-density table but not its GalSim profile: the cross term
    falls back to the mean density for the sum and for each star alike."""
    psf = FluxDependentPSF.from_galsim(PROFILE, SHIFTS, oversampling=4, size=15,
                                       density="exact")
    psf.write(tmp_path / "psf.fits")
    back = FluxDependentPSF.read(tmp_path / "psf.fits")
    assert back.density_profile is None
    half = back.half_size
    y, x = np.mgrid[:2 * half + 1, :2 * half + 1]
    own = (back.evaluate(x, y, FLUX, half + 0.25, half - 0.5)
           - FLUX * back.evaluate_base(x - half - 0.25, y - half + 0.5))
    cross = cross_term_image(back, _stars((20.25, 17.5, FLUX)), SHAPE)
    assert np.abs(cross).max() < 1e-6 * np.abs(own).max()
