"""GalSim views of P(F) and BF applied to rendered models."""

import galsim
import numpy as np
import pytest

from bfpsf.errors import BFPSFInputError, BFPSFValueError
from bfpsf.model.galsim_profile import apply_bf_to_rendered, render_stars, to_galsim
from bfpsf.model.psf import FluxDependentPSF
from bfpsf.model.redistribution import redistribute
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_spots import peak_fraction

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
MOFFAT = galsim.Moffat(beta=3.0, fwhm=3.5)
BRIGHT = 1.2e5 / peak_fraction(MOFFAT)  # flux of a 120 ke- peak star, e-


@pytest.fixture(scope="module")
def psf():
    return FluxDependentPSF.from_galsim(MOFFAT, SHIFTS, oversampling=4, size=25)


def second_moment_x(image):
    ny, nx = image.shape
    x = np.arange(nx) - (nx - 1) / 2
    profile = image.sum(axis=0)
    return (profile * x**2).sum() / profile.sum()


@pytest.mark.parametrize(("x_phase", "y_phase"), [(0.0, 0.0), (0.3, -0.2)])
def test_to_galsim_draws_back_the_pixelised_psf(psf, x_phase, y_phase):
    profile, pixel_included = to_galsim(psf, BRIGHT, x_phase=x_phase, y_phase=y_phase)
    assert pixel_included
    drawn = profile.drawImage(nx=27, ny=27, scale=1.0, method="no_pixel",
                              offset=(x_phase, y_phase)).array
    expected = psf.star_image(BRIGHT, x_phase=x_phase, y_phase=y_phase, half_size=13) / BRIGHT
    # At the stamp's own phase the interpolant passes through the samples: rounding only.
    np.testing.assert_allclose(drawn, expected, atol=1e-9)
    assert profile.flux == pytest.approx(expected.sum(), rel=1e-12)


def test_to_galsim_is_fatter_when_brighter(psf):
    faint, _ = to_galsim(psf, 1e3)
    bright, _ = to_galsim(psf, BRIGHT)
    size_faint = second_moment_x(faint.drawImage(nx=25, ny=25, scale=1, method="no_pixel").array)
    size_bright = second_moment_x(bright.drawImage(nx=25, ny=25, scale=1,
                                                   method="no_pixel").array)
    # E2V-like shifts broaden a 120 ke- peak star by ~1-2 % in <x^2>.
    assert 5e-3 < size_bright / size_faint - 1 < 5e-2


def test_to_galsim_refuses_non_positive_flux(psf):
    with pytest.raises(BFPSFValueError, match="flux must be one positive finite number"):
        to_galsim(psf, 0.0)


def test_apply_bf_to_rendered_galaxy():
    galaxy = galsim.Exponential(half_light_radius=2.0).shear(g1=0.2, g2=0.1)
    model = galsim.Convolve(galaxy, MOFFAT).withFlux(3e6)
    image = model.drawImage(nx=64, ny=64, scale=1.0, dtype=np.float64)
    after = apply_bf_to_rendered(image, SHIFTS)
    assert isinstance(after, galsim.Image) and after.bounds == image.bounds
    # Charge conservation (G15 eq. scrambling_model) and exactly the forward operator.
    assert after.array.sum() == pytest.approx(image.array.sum(), rel=1e-12)
    np.testing.assert_array_equal(after.array, redistribute(image.array, SHIFTS))
    np.testing.assert_array_equal(apply_bf_to_rendered(image.array, SHIFTS), after.array)
    # Brighter-fatter: the source grows.
    assert second_moment_x(after.array) > second_moment_x(image.array)


def test_render_stars_matches_galsim_and_the_model(psf):
    positions = np.array([[20.3, 18.8], [50.0, 44.6]])
    fluxes = np.array([1e5, BRIGHT])
    plain = render_stars(MOFFAT, positions, fluxes, (64, 70))
    direct = MOFFAT.withFlux(1e5).drawImage(nx=21, ny=21, scale=1.0,
                                            offset=(0.3, -0.2)).array
    # Star 0 sits in pixel (20, 19); the other star's wings add < 1e-3 e- there.
    np.testing.assert_allclose(plain[19 - 10:19 + 11, 20 - 10:20 + 11], direct, atol=1e-3)
    with_bf = render_stars(MOFFAT, positions, fluxes, (64, 70), shifts=SHIFTS)
    y, x = np.mgrid[:64, :70]
    model = sum(psf.evaluate(x, y, flux, *xy) for xy, flux in zip(positions, fluxes))
    # The model P0 is the same Moffat drawn at 1/4 pixel: cubic-spline error 5e-4 of the peak.
    assert np.abs(model - with_bf).max() < 1e-3 * with_bf.max()


def test_render_stars_checks_its_input():
    with pytest.raises(BFPSFInputError, match="positions must be"):
        render_stars(MOFFAT, [[1.0, 2.0]], [1.0, 2.0], (10, 10))
