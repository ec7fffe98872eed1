"""Trails and hot columns are no stars (`bfpsf.measure.line_features`), against GalSim stars
of a non-Moffat profile: detection and PSF photometry leave their pixels out."""

import galsim
import numpy as np
import pytest

from bfpsf.measure.line_features import line_mask
from bfpsf.measure.neighbours import isolated_stars, sources_with_companions
from bfpsf.measure.photometry import psf_photometry
from bfpsf.measure.sources import DETECTION_THRESHOLD, SourceFlag, measure_sources
from bfpsf.model.psf import FluxDependentPSF
from bfpsf.shifts import BoundaryShifts

SHIFTS = BoundaryShifts.from_radial_profile(lambda r: 2.5e-7 / r**1.2, 4)
#: Kolmogorov seeing through an obscured pupil: wings a Moffat lacks
PROFILE = galsim.Convolve(galsim.Kolmogorov(fwhm=3.0),
                          galsim.Airy(lam_over_diam=1.2, obscuration=0.3))
SHAPE = (200, 300)
SKY = 300.0
#: A trail at 37 degrees (between two of the directions tested), through (40, 30), Gaussian
#: across (sigma 1.2 px, 250 e- at its centre); a hot column of 400 e- at x = 231.
ANGLE, ORIGIN, TRAIL_SIGMA, TRAIL_PEAK = np.radians(37.0), (40.0, 30.0), 1.2, 250.0
COLUMN, COLUMN_E = 231, 400.0


def _trail_distance(x, y):
    """Distance of (x, y) from the trail's centre line, pixels."""
    return np.abs(-(x - ORIGIN[0]) * np.sin(ANGLE) + (y - ORIGIN[1]) * np.cos(ANGLE))


def _stars(n, rng, shape=SHAPE, low=3e4, high=5e5, clear=5.0):
    """Positions (x, y) at least ``clear`` px from the trail and the column and 9 px from each
    other, and fluxes log-uniform in [low, high] e-."""
    xy = []
    while len(xy) < n:
        x, y = rng.uniform(8, shape[1] - 8), rng.uniform(8, shape[0] - 8)
        if (clear and (_trail_distance(x, y) < clear or abs(x - COLUMN) < clear)) or any(
                np.hypot(x - a, y - b) < 9 for a, b in xy):
            continue
        xy.append((x, y))
    return np.array(xy), np.exp(rng.uniform(np.log(low), np.log(high), n))


def _draw(xy, fluxes, rng, shape=SHAPE, lines=True):
    """GalSim stars on the sky, with the trail and the column (``lines``), Poisson and 5 e- of
    read noise; the sky subtracted."""
    image = galsim.ImageD(shape[1], shape[0], xmin=0, ymin=0)
    for (x, y), flux in zip(xy, fluxes):
        stamp = PROFILE.withFlux(flux).drawImage(nx=64, ny=64, scale=1.0,
                                                  center=galsim.PositionD(x, y))
        bounds = stamp.bounds & image.bounds
        image[bounds] += stamp[bounds]
    light = image.array.copy()
    if lines:
        y, x = np.mgrid[:shape[0], :shape[1]].astype(float)
        light += TRAIL_PEAK * np.exp(-0.5 * (_trail_distance(x, y) / TRAIL_SIGMA) ** 2)
        light[:, COLUMN] += COLUMN_E
    return rng.poisson(light + SKY) - SKY + rng.normal(0.0, 5.0, shape)


@pytest.fixture(scope="module")
def field():
    rng = np.random.default_rng(41)
    xy, fluxes = _stars(40, rng)
    return _draw(xy, fluxes, rng), _draw(xy, fluxes, rng, lines=False), xy, fluxes


def test_a_trail_and_a_hot_column_are_masked_and_no_star(field):
    """The mask covers the trail's and the column's centres away from the stars (not beside
    a bright star, whose light falls along the line: the column's first 43 rows pass a star
    of 3e5 e- 6 px away: 82 % of the column is masked, 96 % of the trail), and no star's
    core; the same stars without them leave no mask."""
    image, clean, xy, _ = field
    mask = line_mask(image, DETECTION_THRESHOLD)
    y, x = np.mgrid[:SHAPE[0], :SHAPE[1]].astype(float)
    near_star = np.min([np.hypot(x - sx, y - sy) for sx, sy in xy], axis=0) < 12
    on_trail = (_trail_distance(x, y) < 1.0) & ~near_star
    on_column = (np.abs(x - COLUMN) < 0.5) & ~near_star
    assert mask[on_trail].mean() > 0.95, mask[on_trail].mean()
    assert mask[on_column].mean() > 0.75, mask[on_column].mean()
    cores = np.rint(xy).astype(int)
    assert not mask[cores[:, 1], cores[:, 0]].any()
    assert not line_mask(clean, DETECTION_THRESHOLD).any()


def test_a_crowded_field_of_bright_stars_holds_no_line():
    """Bright stars 9 px apart and more, up to 3e6 e- (their halos bright along their
    tangents, bridges between them): no line."""
    rng = np.random.default_rng(43)
    xy, fluxes = _stars(220, rng, shape=(200, 200), low=5e4, high=3e6, clear=0.0)
    assert not line_mask(_draw(xy, fluxes, rng, shape=(200, 200), lines=False),
                         DETECTION_THRESHOLD).any()


#: A clump of 35 bright stars from a new user's crowded field (x, y in a 160^2 cut-out, total
#: flux e-; Kolmogorov 0.75" x Airy 0.25", obscuration 0.35, at 0.2"/px), whose saddles of
#: light between the stars were masked as a line (328 pixels) and its stars flagged on_line.
CLUMP = [(110.8, 113.7, 7300.0), (31.7, 42.0, 13600.0), (-18.1, 114.3, 13400.0),
         (143.7, 106.7, 237000.0), (68.4, -16.9, 945000.0), (123.9, 5.8, 806000.0),
         (171.3, 6.5, 549000.0), (85.7, 28.7, 106000.0), (160.7, 99.3, 738000.0),
         (67.9, 59.3, 210000.0), (5.7, -12.7, 338000.0), (36.5, 178.1, 515000.0),
         (143.6, 172.5, 667000.0), (127.9, 168.8, 235000.0), (69.5, 168.8, 419000.0),
         (75.1, 70.8, 123000.0), (125.2, 173.3, 189000.0), (67.0, 10.4, 427000.0),
         (146.7, -10.0, 246000.0), (156.4, 88.2, 289000.0), (81.2, 60.2, 301000.0),
         (77.6, 90.7, 700000.0), (115.8, 154.9, 195000.0), (156.0, 160.5, 569000.0),
         (33.3, -9.6, 139000.0), (58.1, 21.1, 735000.0), (13.7, 136.3, 100000.0),
         (29.7, 83.3, 130000.0), (140.1, -11.1, 691000.0), (97.6, 99.1, 538000.0),
         (93.6, 26.3, 873000.0), (171.7, 117.2, 126000.0), (118.3, 141.9, 115000.0),
         (82.2, 68.2, 251000.0), (136.3, 34.7, 347000.0)]


def test_the_light_between_clumped_bright_stars_is_no_line():
    """The light between the clump's stars passes a line's tests along and across (bright
    along the gap, falling on one side), but it is a saddle, a star on its other side: a line
    is a ridge over at least half its length (`RIDGE_SHARE`)."""
    profile = galsim.Convolve(galsim.Kolmogorov(fwhm=3.75),
                              galsim.Airy(lam_over_diam=1.25, obscuration=0.35))
    canvas = galsim.ImageF(160, 160, scale=1.0)
    for x, y, flux in CLUMP:
        stamp = profile.withFlux(flux).drawImage(nx=129, ny=129, scale=1.0,
                                                 center=galsim.PositionD(x + 1, y + 1))
        bounds = stamp.bounds & canvas.bounds
        canvas[bounds] += stamp[bounds]
    rng = np.random.default_rng(1)
    image = (rng.poisson(canvas.array + 800.0) - 800.0
             + 5.0 * rng.standard_normal(canvas.array.shape))
    assert not line_mask(image, DETECTION_THRESHOLD).any()


def test_photometry_leaves_the_lines_out(field):
    """Detection takes the trail and the column for strings of stars (without the mask, PSF
    photometry fitted 97 sources for these 40 stars, in 95 s); PSF photometry at its defaults
    fits the stars (45 sources, 1.6 s: what is left is the lines' last pixels at the image's
    corner and edge, and their crossing), each within its error of its flux, and flags
    ``ON_LINE`` the stars whose fit box holds masked pixels."""
    image, _, xy, fluxes = field
    assert len(sources_with_companions(image, lines=False)) > len(xy) + 10  # strings of peaks
    psf = FluxDependentPSF.from_galsim(PROFILE, SHIFTS.scaled(0.0), oversampling=2, size=25)
    result = psf_photometry(image + SKY, psf)
    assert result.meta["line_pixels"] > 0
    distance = np.hypot(result["x_fit"][:, None] - xy[:, 0], result["y_fit"][:, None]
                        - xy[:, 1])
    nearest = np.argmin(distance, axis=1)
    matched = distance[np.arange(len(result)), nearest] < 1.0
    assert np.unique(nearest[matched]).size == len(xy)  # every star, once
    assert len(result) - matched.sum() <= 6, len(result) - matched.sum()
    on_line = (np.asarray(result["source_flags"]) & SourceFlag.ON_LINE) > 0
    assert on_line[matched].sum() >= 2
    # the flag is the fit box's (its half diagonal, about 8 px, beyond the mask's half width
    # of up to 7 px): none of the stars beyond 16 px of both lines has it
    star_x, star_y = xy[nearest, 0], xy[nearest, 1]
    far = (_trail_distance(star_x, star_y) > 16) & (np.abs(star_x - COLUMN) > 16)
    assert not on_line[matched & far].any()
    good = matched & (np.asarray(result["flags"]) == 0)
    pull = ((result["flux_fit"][good] - fluxes[nearest[good]]) / result["flux_err"][good])
    assert np.median(np.abs(pull)) < 1.0, np.sort(pull)
    assert np.all(np.abs(pull) < 5), np.sort(pull)


def test_measure_and_the_psf_stars_leave_the_lines_out(field):
    """`measure_sources` (``bfpsf measure``) replaces the lines' pixels by the sky: every
    star is measured and no source lies on a line away from the stars; a star with a line
    within its moments' reach is flagged ``ON_LINE``. `isolated_stars` (the P0 fit's stars,
    ``bfpsf psf``) keeps no star with a line in its cutout, and no piece of a line among the
    neighbours the P0 fit models."""
    image, _, xy, _ = field
    table = measure_sources(image + SKY)
    assert table.meta["line_pixels"] > 0
    x, y = np.asarray(table["x"]), np.asarray(table["y"])
    distance = np.hypot(x[:, None] - xy[:, 0], y[:, None] - xy[:, 1]).min(axis=1)
    assert np.sum(distance < 1.0) == len(xy)
    assert np.sum(distance >= 1.0) <= 3, np.column_stack([x, y])[distance >= 1.0]
    on_line = (np.asarray(table["flags"]) & SourceFlag.ON_LINE) > 0
    line_distance = np.minimum(_trail_distance(x, y), np.abs(x - COLUMN))
    sigma = np.asarray(table["iq"])
    assert on_line[line_distance < 3.0].all()  # what is left of the lines is flagged
    assert on_line.sum() >= 4
    # the mask is a few pixels wide: none beyond its half width and the star's reach
    assert not np.any(on_line & (line_distance > 4.0 * sigma + 8.0))
    stars, _, others = isolated_stars(image, 25)
    star_distance = np.minimum(_trail_distance(*stars.T), np.abs(stars[:, 0] - COLUMN))
    assert star_distance.min() > 12.0, star_distance.min()
    # 18 stars, none with a line in its cutout, and 26 other sources to model beside them;
    # without the mask 23 (5 with a line in the cutout) and 69, the lines' pieces among them
    assert len(stars) >= 15
    assert len(others) < len(isolated_stars(image, 25, lines=False, cosmic_rays=False)[2]) - 30


def test_a_dead_column_is_masked_too():
    """A column at 10 % response (a new user's dead column was not masked: stars on it read
    +170-180 mmag, those 4-6 px away +5-23 mmag with no flag) is a dark line: masked away
    from the stars, no star's core."""
    rng = np.random.default_rng(47)
    xy, fluxes = _stars(30, rng)
    image = _draw(xy, fluxes, rng, lines=False)
    dead = 80
    image[:, dead] = 0.1 * (image[:, dead] + SKY) - SKY
    mask = line_mask(image, DETECTION_THRESHOLD)
    rows = np.arange(SHAPE[0])
    clear = np.min(np.hypot(dead - xy[:, 0][:, None], rows - xy[:, 1][:, None]), axis=0) > 12
    assert mask[clear, dead].mean() > 0.8, mask[clear, dead].mean()
    cores = np.rint(xy).astype(int)
    assert not mask[cores[:, 1], cores[:, 0]].any()
