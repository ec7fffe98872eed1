"""P0 from a crowded field: stars with a neighbour that detection does not split are left out.

A new user's crowded field (160 Kolmogorov stars on 300^2 pixels, a third of the "isolated"
stars with a neighbour 4-7 px away) gave a P0 22 % too large and double-peaked, reported as
converged: weighted by their flux, the unresolved pairs were half of it. Here GalSim draws
an Airy x Gaussian field (not the model's operator, not a Moffat) in which the brightest
stars have a companion 3.5-5 px away, and the same field without the companions; P0 is fitted
by the user's path (`isolated_stars`, then `fit_psf`) and compared with the profile GalSim
draws.
"""

import galsim
import numpy as np
import pytest

from bfpsf.measure.neighbours import isolated_stars
from bfpsf.model.psf_fit import fit_psf
from bfpsf.moments.adaptive import adaptive_moments
from bfpsf.shifts import BoundaryShifts

PROFILE = galsim.Convolve(galsim.Airy(lam_over_diam=1.3), galsim.Gaussian(sigma=1.1))
SKY_E = 100.0
SIDE = 240
SPACING = 40


def _field(companions, seed=17):
    """The field (e-, sky subtracted, Poisson noise) and the positions of the stars that have
    a companion."""
    rng = np.random.default_rng(seed)
    image = galsim.ImageD(SIDE, SIDE, scale=1.0)
    centres = np.arange(SPACING / 2, SIDE, SPACING)
    xs, ys = np.meshgrid(centres, centres)
    xs = xs.ravel() + rng.uniform(-3, 3, xs.size)
    ys = ys.ravel() + rng.uniform(-3, 3, ys.size)
    fluxes = np.exp(rng.uniform(np.log(3e4), np.log(2e6), xs.size))
    paired = np.argsort(fluxes)[-8:]  # the brightest stars weigh most in P0
    for index, (x, y, flux) in enumerate(zip(xs, ys, fluxes)):
        stamp = PROFILE.withFlux(flux).drawImage(nx=41, ny=41, scale=1.0,
                                                 center=galsim.PositionD(x + 1, y + 1))
        bounds = stamp.bounds & image.bounds
        image[bounds] += stamp[bounds]
        if companions and index in paired:
            angle, distance = rng.uniform(0, np.pi), rng.uniform(3.5, 5.0)
            dx, dy = distance * np.cos(angle), distance * np.sin(angle)
            stamp = PROFILE.withFlux(rng.uniform(0.4, 0.8) * flux).drawImage(
                nx=41, ny=41, scale=1.0, center=galsim.PositionD(x + dx + 1, y + dy + 1))
            bounds = stamp.bounds & image.bounds
            image[bounds] += stamp[bounds]
    noisy = rng.poisson(np.clip(image.array + SKY_E, 0, None)).astype(float) - SKY_E
    return noisy, np.column_stack([xs[paired], ys[paired]])


def _truth():
    """Adaptive moments of GalSim's pixelised profile."""
    return adaptive_moments(PROFILE.drawImage(nx=41, ny=41, scale=1.0).array)


def _p0_moments(psf, half=12):
    """Adaptive moments of P(F) for a faint star at a pixel centre, through the model."""
    y, x = np.mgrid[-half:half + 1, -half:half + 1].astype(float)
    return adaptive_moments(psf.evaluate(x, y, 1.0, 0.0, 0.0))


@pytest.mark.parametrize("companions", [True, False], ids=["blends", "null"])
def test_p0_leaves_out_unresolved_blends(companions):
    """With the 8 brightest of 36 stars blended 3.5-5 px away (40-80 % of their flux), P0's
    size and ellipticity match GalSim's profile within 0.3 % and 0.003 (+0.01 %, e1 +0.001
    when written) and every blend is flagged (16); on the same field without the companions
    no star is left out (-0.05 %). Without `misfits` the blended P0 was 38 % too large, e1
    -0.18."""
    image, blended = _field(companions)
    xy, _, others = isolated_stars(image, 25)
    zero = BoundaryShifts(np.zeros((3, 3)), np.zeros((3, 3)))
    result = fit_psf(image, xy, zero, neighbours=others, sky_e=SKY_E)
    truth, fitted = _truth(), _p0_moments(result.psf)
    print(truth.sigma, fitted.sigma, np.bincount(np.asarray(result.stars["flags"])))
    assert fitted.sigma == pytest.approx(truth.sigma, rel=0.003)
    size = fitted.mxx + fitted.myy
    assert abs((fitted.mxx - fitted.myy) / size) < 0.003 and abs(2 * fitted.mxy / size) < 0.003
    left_out = np.asarray(result.stars["flags"]) & 16 > 0
    if not companions:
        assert not left_out.any(), result.stars[left_out]
        return
    stars = np.column_stack([result.stars["x_init"], result.stars["y_init"]])
    for x, y in blended:
        near = np.hypot(*(stars - [x, y]).T) < 4
        assert not near.any() or left_out[near].all(), (x, y)
    assert left_out.sum() <= 8 + 3


def test_psf_command_says_how_many_stars_it_left_out(tmp_path, capsys):
    """``bfpsf psf`` on the blended field (FITS, ADU) names the stars it left out, in its line
    and in its JSON (``n_unlike``), and P0's size is GalSim's. Its flux correction is
    GalSim's light in the drawn stamps over the light in P0's support, within 3 of its
    errors and 0.005: the stars left out are modelled as neighbours are, and their glow is in
    the sky and wings fit (1.0086 +- 0.0032 against GalSim's 1.0079 when written; 1.0430 +-
    0.0131 without them, and a new user's crowded field 1.0226 +- 0.0047 for a true
    1.0173)."""
    import json

    from test_photometry import make_calibration

    from bfpsf.cli import main
    from bfpsf.model.product import read_psf
    from bfpsf.validation.simulate_spots import write_image_adu

    image, _ = _field(True)
    # a calibration's PTC needs some BF: a^X 1e4 times below a sensor's changes nothing here
    faint = BoundaryShifts.from_radial_profile(lambda r: 1e-11 / r**1.2, 4)
    write_image_adu(tmp_path / "field.fits", image + SKY_E, gain=1.5)
    make_calibration(faint, 1.5, 5.0).write(tmp_path / "calib.fits")
    assert main(["psf", str(tmp_path / "field.fits"), "--calib", str(tmp_path / "calib.fits"),
                 "-o", str(tmp_path / "psf.fits"), "--json", str(tmp_path / "psf.json")]) == 0
    assert "8 left out as unlike the other stars" in capsys.readouterr().out
    assert json.loads((tmp_path / "psf.json").read_text())["n_unlike"] == 8
    psf = read_psf(tmp_path / "psf.fits")
    assert _p0_moments(psf).sigma == pytest.approx(_truth().sigma, rel=0.003)
    drawn = PROFILE.drawImage(nx=41, ny=41, scale=1.0).array  # the field's stamps
    truth = drawn.sum() / drawn[8:-8, 8:-8].sum()
    print(f"flux correction {psf.flux_correction:.4f} +- {psf.flux_correction_err:.4f}, "
          f"GalSim {truth:.4f}")
    assert psf.flux_correction == pytest.approx(truth, abs=min(3 * psf.flux_correction_err,
                                                                0.005))


def _light_within(image, radius):
    """The fraction of a centred stamp's light within ``radius`` pixels of its centre."""
    half = image.shape[0] // 2
    y, x = np.mgrid[-half:half + 1, -half:half + 1]
    return image[np.hypot(x, y) < radius].sum() / image.sum()


#: (flux ratio range, distance range) of the companions of `test_p0_companions_beyond_moments`
COMPANIONS = {"companions": ((0.25, 0.5), (6.0, 9.0)), "faint": ((0.01, 0.04), (6.0, 10.0)),
              "null": None}


@pytest.mark.parametrize("companions", list(COMPANIONS))
def test_p0_companions_beyond_moments(companions):
    """A new user's crowded field left a fifth of its "isolated" stars with a neighbour 4-14 px
    away that detection had not split: too far to move their adaptive moments (`misfits`),
    they gave P0 10 % of its light beyond 4 px that the stars do not have. Here 12 of 36
    stars, the brightest among them, have a companion 6-9 px away at 25-50 % of their flux,
    or 6-10 px away at 1-4 % ("faint": another new user's field, 250 stars per 350^2, gave P0
    1 % too much light beyond 6 px from such companions), and P0 is fitted from the
    primaries' positions alone (as if detection had missed every companion): P0's light
    within 4 px of its centre is GalSim's within 0.003 (0.0012 low when written, 0.0009
    without the companions; 0.28 low with them in P0, `hidden_companions` disabled; faint:
    0.0013 low, 0.022 low with `companion_pixels` disabled). The bright companions' stars are
    left out (16), at most 3 others (none when written); the faint companions' pixels are
    masked in 10 of those 12 stars or more (all 12 and 11 others when written: a P0 that
    holds the companions leaves its lumps in the other stars' residuals) and no star is left
    out; without companions none is left out and at most 2 stars have pixels masked (1, the
    brightest, when written: P0's own errors at 5 sigma)."""
    rng = np.random.default_rng(29)
    image = galsim.ImageD(SIDE, SIDE, scale=1.0)
    centres = np.arange(SPACING / 2, SIDE, SPACING)
    xs, ys = (grid.ravel() + rng.uniform(-3, 3, grid.size) for grid in np.meshgrid(centres,
                                                                                  centres))
    fluxes = np.exp(rng.uniform(np.log(3e4), np.log(2e6), xs.size))
    paired = np.argsort(fluxes)[-12:]
    for index, (x, y, flux) in enumerate(zip(xs, ys, fluxes)):
        sources = [(x, y, flux)]
        if COMPANIONS[companions] and index in paired:
            ratio, reach = COMPANIONS[companions]
            angle, distance = rng.uniform(0, 2 * np.pi), rng.uniform(*reach)
            sources.append((x + distance * np.cos(angle), y + distance * np.sin(angle),
                            rng.uniform(*ratio) * flux))
        for x_0, y_0, value in sources:
            stamp = PROFILE.withFlux(value).drawImage(nx=41, ny=41, scale=1.0,
                                                      center=galsim.PositionD(x_0 + 1, y_0 + 1))
            bounds = stamp.bounds & image.bounds
            image[bounds] += stamp[bounds]
    noisy = rng.poisson(np.clip(image.array + SKY_E, 0, None)).astype(float) - SKY_E
    zero = BoundaryShifts(np.zeros((3, 3)), np.zeros((3, 3)))
    result = fit_psf(noisy, np.column_stack([xs, ys]), zero, sky_e=SKY_E)
    y, x = np.mgrid[-12:13, -12:13].astype(float)
    fitted = _light_within(result.psf.evaluate(x, y, 1.0, 0.0, 0.0), 4.0)
    truth = _light_within(PROFILE.drawImage(nx=25, ny=25, scale=1.0).array, 4.0)
    left_out = np.asarray(result.stars["flags"]) & 16 > 0
    masked = np.asarray(result.stars["masked"]) > 0
    print(f"light within 4 px: P0 {fitted:.4f}, GalSim {truth:.4f}; left out "
          f"{np.flatnonzero(left_out)}, masked {np.flatnonzero(masked)}, paired "
          f"{np.sort(paired)}")
    assert fitted == pytest.approx(truth, abs=0.003)
    if companions == "companions":
        assert left_out[paired].all() and left_out.sum() <= len(paired) + 3
        return
    assert not left_out.any()
    if companions == "faint":
        assert masked[paired].sum() >= len(paired) - 2
    else:
        assert masked.sum() <= 2
