"""Cosmic rays on the stars (`bfpsf.measure.cosmic_rays`): found in the residual of the PSF
fit, left out of the refit of the stars they touch, those stars flagged ``cosmic_ray``; and
the other misfit photometry flags from the fit itself, a reduced chi2 far above its flux
peers' (`bfpsf.measure.psf_likeness.misfit_outliers`)."""

import galsim
import numpy as np
import pytest

import bfpsf
from bfpsf.measure.cosmic_rays import cosmic_ray_mask
from bfpsf.measure.photometry import psf_photometry
from bfpsf.measure.sources import SourceFlag, measure_sources, ray_mask
from bfpsf.shifts import BoundaryShifts
from bfpsf.validation.simulate_fields import simulate_field


KOLMOGOROV_AIRY = galsim.Convolve(galsim.Kolmogorov(fwhm=2.6),
                                  galsim.Airy(lam_over_diam=0.9, obscuration=0.4))


def _field(n, sky_e, *, seed):
    """n^2 pixels of 40 Kolmogorov x obscured Airy stars (no BF, peaks 500-1.2e5 e-) on a
    flat sky."""
    return simulate_field(KOLMOGOROV_AIRY, n_images=1, shape=(n, n), n_stars=40,
                          peak_range_e=(5e2, 1.2e5), min_separation=20.0, sensor=None,
                          sky_surface=lambda x, y: sky_e + 0.0 * x, seed=seed, stamp=128)


@pytest.fixture(scope="module")
def hit_field():
    """384^2 pixels of 40 Kolmogorov x obscured Airy stars (no BF) on 300 e-, 14 of them hit
    by a cosmic ray of 1-3 pixels of 300-3000 e- each, 1.5-5 px from the centre: (data, x,
    y, flux, hit, psf, the image without them)."""
    n = 384
    profile = KOLMOGOROV_AIRY
    field = _field(n, 300.0, seed=4)
    x, y, flux = (np.asarray(field.truth[0][name], float) for name in ("x", "y", "flux_e"))
    data = field.images[0].copy()
    rng = np.random.default_rng(14)
    hit = np.zeros(len(x), dtype=bool)
    hit[rng.choice(len(x), 14, replace=False)] = True
    for index in np.flatnonzero(hit):
        angle, radius = rng.uniform(0.0, 2 * np.pi), rng.uniform(1.5, 5.0)
        row = int(round(y[index] + radius * np.sin(angle)))
        column = int(round(x[index] + radius * np.cos(angle)))
        length = int(rng.integers(1, 4))
        data[row, column:column + length] += rng.uniform(300.0, 3000.0, length)
    psf = bfpsf.FluxDependentPSF.from_galsim(
        profile, BoundaryShifts.from_radial_profile(lambda r: 0 * r, 2))
    return data, x, y, flux, hit, psf, field.images[0]


def _offsets(table, x, y, flux):
    """Each true star's fit: m_fit - m_true (mmag), its flux error (mmag), its flags."""
    distance = np.hypot(table["x_fit"][None] - x[:, None], table["y_fit"][None] - y[:, None])
    nearest = np.argmin(distance, axis=1)
    assert distance[np.arange(len(x)), nearest].max() < 1.0  # every star found
    fitted = np.asarray(table["flux_fit"], float)[nearest]
    error = 1085.7 * np.asarray(table["flux_err"], float)[nearest] / fitted
    return (1e3 * 2.5 * np.log10(flux / fitted), error,
            np.asarray(table["source_flags"])[nearest])


def test_photometry_leaves_cosmic_rays_out_of_the_stars_they_hit(hit_field):
    """Without the mask the 14 hit stars read -30.9 mmag at the median, 11 of them beyond 5
    flux errors, none flagged; with it (the default) -3.4, none beyond 3 errors (one is
    allowed), every one flagged ``cosmic_ray`` and none of the 26 others."""
    data, x, y, flux, hit, psf, _ = hit_field
    masked = psf_photometry(data, psf, read_noise_e=5.0)
    kept = psf_photometry(data, psf, read_noise_e=5.0, mask_cosmic_rays=False)
    offset, error, flags = _offsets(masked, x, y, flux)
    before, before_error, before_flags = _offsets(kept, x, y, flux)
    flagged = (flags & SourceFlag.COSMIC_RAY) > 0
    print(f"masked: median {np.median(offset[hit]):+.1f}, beyond 3 errors "
          f"{np.sum(np.abs(offset[hit]) > 3 * error[hit])}; without: median "
          f"{np.median(before[hit]):+.1f}, beyond 5 errors "
          f"{np.sum(np.abs(before[hit]) > 5 * before_error[hit])}")
    assert np.all(flagged[hit]) and not np.any(flagged[~hit])
    assert np.sum(np.abs(offset[hit]) > 3 * error[hit]) <= 1
    assert np.sum(np.abs(before[hit]) > 5 * before_error[hit]) >= 4
    assert not np.any(before_flags & SourceFlag.COSMIC_RAY)
    assert masked.meta["cosmic_ray_pixels"] > 0 and kept.meta["cosmic_ray_pixels"] == 0


def test_a_hit_brighter_than_the_star_s_peak_leaves_one_row_at_the_star():
    """Faint stars (peaks 500-3000 e-) hit 2-2.5 px from their centres by two pixels of
    1.5-3 times their peak each: each star comes out as one row at the star, flagged
    ``cosmic_ray``, at its flux (a new user's stars of 8e3-4e4 e- so hit came out as two rows
    each, a row beside the star of a tenth of its flux and one found in the residual, or
    the star split in two halves with errors of 1.4e6 e-: the fit, pulled by the hit, had
    left the star in its residual before the cosmic rays were looked for)."""
    field = _field(256, 300.0, seed=9)
    x, y, flux = (np.asarray(field.truth[0][name], float) for name in ("x", "y", "flux_e"))
    peak = np.asarray(field.truth[0]["peak_e"], float)
    data = field.images[0].copy()
    rng = np.random.default_rng(16)
    hit = (peak > 500) & (peak < 3000)
    for index in np.flatnonzero(hit):
        angle = rng.uniform(0.0, 2 * np.pi)
        row = int(round(y[index] + 2.2 * np.sin(angle)))
        column = int(round(x[index] + 2.2 * np.cos(angle)))
        data[row, column:column + 2] += peak[index] * rng.uniform(1.5, 3.0, 2)
    psf = bfpsf.FluxDependentPSF.from_galsim(
        KOLMOGOROV_AIRY, BoundaryShifts.from_radial_profile(lambda r: 0 * r, 2))
    table = psf_photometry(data, psf, read_noise_e=5.0)
    distance = np.hypot(table["x_fit"][:, None] - x[None], table["y_fit"][:, None] - y[None])
    print(f"{hit.sum()} hit; {len(table)} rows for {len(x)} stars; rows beyond 1 px of a "
          f"star {np.sum(distance.min(axis=1) > 1.0)}")
    assert len(table) == len(x) and distance.min(axis=1).max() < 1.0
    offset, error, flags = _offsets(table, x, y, flux)
    assert hit.sum() >= 6 and np.all(flags[hit] & SourceFlag.COSMIC_RAY)
    assert np.sum(np.abs(offset[hit]) > 3 * error[hit]) <= 1, (offset[hit], error[hit])


def test_cosmic_rays_on_the_sky_are_no_stars(hit_field):
    """Hits and tracks on the sky, 15 px or more from every star: detection finds them as
    cosmic rays, and the search of the fit's residual takes them for no stars (a new user's
    40 hits and 15 tracks on the sky came back as 35 stars "missed by detection", flagged
    cosmic_ray, some of negative flux: 38 rows beyond the 100 stars; 10 after)."""
    data, x, y, flux, hit, psf, _ = hit_field
    data = data.copy()
    rng = np.random.default_rng(15)
    placed = 0
    while placed < 20:
        # a single hit of 800-5000 e-, or a track 8-30 px long at any angle, 300-2000 e- a
        # pixel (the new user's)
        length, angle = (1, 0.0) if placed % 2 else (rng.uniform(8, 30), rng.uniform(0, np.pi))
        start = rng.uniform(10, data.shape[0] - 40, 2)
        steps = np.linspace(0.0, length, int(3 * length) + 1)
        rows, columns = (np.unique(np.round(start[:, None] + steps[None] * np.array(
            [[np.sin(angle)], [np.cos(angle)]])).astype(int).T, axis=0).T)
        if np.hypot(x[:, None] - columns[None], y[:, None] - rows[None]).min() < 15:
            continue
        data[rows, columns] += rng.uniform(800.0, 5000.0, rows.size) if length == 1 else \
            rng.uniform(300.0, 2000.0) * rng.uniform(0.6, 1.4, rows.size)
        placed += 1
    table = psf_photometry(data, psf, read_noise_e=5.0)
    distance = np.hypot(table["x_fit"][:, None] - x[None], table["y_fit"][:, None] - y[None])
    spurious = distance.min(axis=1) > 1.5
    print(len(table), np.sum(spurious))
    assert np.all(distance.min(axis=0) < 1.0)  # every star found
    assert np.sum(spurious) <= 2


def test_psf_says_the_stars_a_cosmic_ray_hit(hit_field, tmp_path, capsys):
    """``bfpsf psf`` leaves the hit stars out of P0 and says why, with the rays' pixels per
    image in its JSON (a new user's 52 hit stars were "blended, near an edge or with bad
    pixels" alone)."""
    import json

    from test_photometry import SHIFTS, make_calibration

    from bfpsf.cli import main
    from bfpsf.validation.simulate_spots import write_image_adu

    data = hit_field[0]
    write_image_adu(tmp_path / "hit.fits", data + 300.0, gain=1.0)
    make_calibration(SHIFTS, 1.0, 5.0).write(tmp_path / "cal.fits")
    assert main(["psf", str(tmp_path / "hit.fits"), "--calib", str(tmp_path / "cal.fits"),
                 "-o", str(tmp_path / "p.fits"), "--no-bf", "--json",
                 str(tmp_path / "p.json")]) == 0
    assert "or hit by a cosmic ray" in capsys.readouterr().out
    assert json.loads((tmp_path / "p.json").read_text())["images"][0]["cosmic_ray_pixels"] > 0


def test_cosmic_ray_mask_reads_the_residual_not_the_stars():
    """An undersampled star (a Gaussian of 0.6 px sigma, 2e5 e-) is sharp enough for
    L.A.Cosmic on the image; in the residual of its fit it is gone, and a cosmic ray beside
    it is found, grown by a pixel; a deposit below a tenth of the model there is not."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[:64, :64]
    model = 2e5 * np.exp(-((x - 32.3) ** 2 + (y - 31.8) ** 2) / (2 * 0.6 ** 2)) / (
        2 * np.pi * 0.6 ** 2)
    variance = 100.0 + model + 25.0
    residual = rng.normal(0.0, np.sqrt(variance))
    residual[41, 30] += 1500.0  # a cosmic ray 9 px from the star
    residual[32, 32] += 0.05 * model[32, 32]  # the model's own misfit at the core
    found = cosmic_ray_mask(residual, variance, model, read_noise_e=5.0)
    assert found[41, 30] and found[40, 30] and found[41, 31]
    assert not found[28:37, 28:37].any()
    assert found.sum() <= 12


def test_a_fit_far_worse_than_its_flux_peers_is_unlike_the_psf():
    """`misfit_outliers`: 200 stars whose reduced chi2 grows with flux (a bright star's own
    model error, shared by its peers: 1 at 1e4 e-, 5 at 1e6) and noise; one bright star at
    52 (a new user's star robbed by a source on its diffraction spike, every flag 0) and one
    faint one at 2.9 (below the floor of 3) : only the first is an outlier, and a field of
    bright stars all at 8 has none."""
    from bfpsf.measure.psf_likeness import misfit_outliers

    rng = np.random.default_rng(9)
    flux = np.exp(rng.uniform(np.log(1e4), np.log(1e6), 200))
    chi2 = (1.0 + 4.0 * (np.log10(flux) - 4.0) / 2.0) * rng.chisquare(300, 200) / 300
    robbed, faint = np.argmax(flux), np.argmin(flux)
    chi2[robbed], chi2[faint] = 52.0, 2.9
    found = misfit_outliers(chi2, flux)
    assert np.flatnonzero(found).tolist() == [robbed]
    assert not misfit_outliers(np.full(50, 8.0), np.geomspace(1e5, 1e6, 50)).any()


def _matched(table, x, y):
    """Each true star's row of a source table, and how many rows match no star."""
    distance = np.hypot(np.asarray(table["x"])[None] - x[:, None],
                        np.asarray(table["y"])[None] - y[:, None])
    nearest = np.argmin(distance, axis=1)
    assert distance[np.arange(len(x)), nearest].max() < 1.5  # every star found
    return table[nearest], len(table) - len(np.unique(nearest))


def test_measure_fills_cosmic_rays_and_flags_the_stars_they_hit(hit_field):
    """Without a PSF model (``measure``, ``psf``'s stars, ``diagnose``): the 14 hits and 40
    rays on the sky. Not searched, the rays were 40 sources of their own, 4 stars were
    flagged blended with one, and 11 unflagged stars' sizes moved by more than 1 % (up to
    14 %). Searched (the default), no ray is a source, no star is blended, the 12 stars they
    reach are flagged ``cosmic_ray``, and two unflagged stars' sizes moved by more than 1 %
    (2.4 % at most: a ray on a bright star's wing, below a quarter more than a star's core
    in sharpness, is not told from a companion's core there)."""
    data, x, y, _, _, _, clean = hit_field
    data = data.copy()
    rng = np.random.default_rng(15)
    placed = 0
    while placed < 40:  # on the sky, 8 px or more from every star
        row, column = rng.integers(5, data.shape[0] - 8, 2)
        if np.hypot(x - column, y - row).min() >= 8.0:
            length = int(rng.integers(1, 4))
            data[row, column:column + length] += rng.uniform(300.0, 3000.0, length)
            placed += 1
    reference, _ = _matched(measure_sources(clean), x, y)
    assert reference.meta["cosmic_ray_pixels"] == 0
    for search in (False, True):
        table = measure_sources(data, cosmic_rays=search)
        stars, spurious = _matched(table, x, y)
        flags = np.asarray(stars["flags"])
        usable = (flags == 0) & (np.asarray(reference["flags"]) == 0)
        moved = np.abs(np.r_[np.asarray(stars["sigma_x"])[usable]
                             / np.asarray(reference["sigma_x"])[usable],
                             np.asarray(stars["sigma_y"])[usable]
                             / np.asarray(reference["sigma_y"])[usable]] - 1.0)
        print(f"searched {search}: {spurious} spurious sources, "
              f"{np.sum((flags & SourceFlag.BLENDED) != 0)} stars blended, "
              f"{np.sum((flags & SourceFlag.COSMIC_RAY) != 0)} flagged cosmic_ray, "
              f"{np.sum(moved > 0.01)} unflagged sizes moved > 1 % (max {moved.max():.3f}), "
              f"{table.meta['cosmic_ray_pixels']} ray pixels")
    assert spurious == 0 and moved.max() < 0.03 and np.sum(moved > 0.01) <= 2
    assert not np.any((flags & SourceFlag.BLENDED) != 0)
    assert table.meta["cosmic_ray_pixels"] > 0


@pytest.mark.parametrize("profile", [galsim.Gaussian(fwhm=1.6), galsim.Convolve(
    galsim.Kolmogorov(fwhm=1.2), galsim.Airy(lam_over_diam=0.4, obscuration=0.4))])
def test_measure_takes_no_undersampled_core_for_a_cosmic_ray(profile):
    """Stars of 1.2-1.6 px FWHM up to 1.5e5 e- of peak: L.A.Cosmic on the image itself takes
    their cores for cosmic rays; judged against the stars' own sharpness, no pixel is."""
    field = simulate_field(profile, n_images=1, shape=(256, 256), n_stars=40,
                           peak_range_e=(3e2, 1.5e5), min_separation=12.0, sensor=None,
                           sky_surface=lambda x, y: 300.0 + 0.2 * x, seed=3, stamp=64)
    table = measure_sources(field.images[0])
    assert table.meta["cosmic_ray_pixels"] == 0
    assert not np.any((np.asarray(table["flags"]) & SourceFlag.COSMIC_RAY) != 0)


def _deposit(image, x, y, charge):
    """Charge spread bilinearly over the four pixels about each (x, y)."""
    column, row = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - column, y - row
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                           (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        inside = ((column + dx >= 0) & (column + dx < image.shape[1]) & (row + dy >= 0)
                  & (row + dy < image.shape[0]))
        np.add.at(image, (row[inside] + dy, column[inside] + dx), (charge * weight)[inside])


def test_measure_finds_tracks_among_rays_it_took_for_stars():
    """Rays as real ones are: spots, straight tracks of 2-30 px at any angle and curling
    worms, 2 px wide where they cross pixels at a slant, 150 of them on 384^2 pixels of 40
    stars. Some are detected as clean sources of a star's size; their sharpness had put the
    stars' 90th percentile at three times its median, and the search found a quarter of the
    rays (a new user's image: 858 of 2899 pixels, 115 spurious sources; here a star was
    lost). With the stars' sharpness clipped at 3 robust sigma above the median, 93 % of the
    rays' pixels are filled, and the 16 remnants detected beside them are all flagged."""
    n = 384
    field = _field(n, 600.0, seed=6)
    x, y = (np.asarray(field.truth[0][name], float) for name in ("x", "y"))
    rng = np.random.default_rng(16)
    rays = np.zeros((n, n))
    for index in range(150):
        start = rng.uniform(5, n - 5, 2)
        kind = ("spot", "track", "track", "worm")[index % 4]
        if kind == "spot":
            _deposit(rays, start[:1], start[1:], rng.uniform(500.0, 5000.0, 1))
            continue
        length = rng.uniform(2.0, 30.0) if kind == "track" else rng.uniform(4.0, 15.0)
        steps = int(length / 0.05)
        angle = rng.uniform(0.0, np.pi) + (np.cumsum(rng.normal(0.0, 0.15, steps))
                                          if kind == "worm" else 0.0)
        along = 0.05 * np.arange(steps) if kind == "track" else None
        px = start[0] + (along * np.cos(angle) if kind == "track"
                         else np.cumsum(0.05 * np.cos(angle)))
        py = start[1] + (along * np.sin(angle) if kind == "track"
                         else np.cumsum(0.05 * np.sin(angle)))
        charge = rng.uniform(200.0, 1500.0) * (2.0 if kind == "worm" else 1.0) * 0.05
        _deposit(rays, px, py, np.full(steps, charge))
    table = measure_sources(field.images[0] + rays)
    _matched(table, x, y)  # every star found
    distance = np.hypot(np.asarray(table["x"])[:, None] - x,
                        np.asarray(table["y"])[:, None] - y).min(axis=1)
    flags = np.asarray(table["flags"])[distance > 1.5]
    deposited = rays > 50.0
    share = np.sum(ray_mask(table, (n, n)) & deposited) / np.sum(deposited)
    print(f"{len(flags)} sources on rays ({np.sum(flags == 0)} unflagged), {share:.2f} of "
          "the rays' pixels filled")
    assert share > 0.8 and not np.any(flags == 0)
