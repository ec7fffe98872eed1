"""Flat ingest, pairing by EXPTIME and pixel masks (G15 section 4.2.3)."""

import logging

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration.covariance import pair_covariance
from bfpsf.calibration.flat_mask import DEFAULT_EDGE, _band_tests, pair_mask
from bfpsf.calibration.flats import Flat, FlatPair, pair_flats, read_flats
from bfpsf.errors import BFPSFInputError

LEVEL = 10_000.0  # ADU
NOISE = 100.0  # ADU rms: Poisson-like at this level


def gaussian_flat(rng, shape=(128, 128), level=LEVEL, noise=NOISE):
    return rng.normal(level, noise, shape)


def write_fits(path, data, **header):
    hdu = fits.PrimaryHDU(np.asarray(data, dtype=np.float32))
    for key, value in header.items():
        hdu.header[key] = value
    hdu.writeto(path)
    return path


# ---------------------------------------------------------------------------------------------
# Ingest


def test_read_flats_from_fits_and_arrays(tmp_path):
    rng = np.random.default_rng(0)
    data = gaussian_flat(rng)
    path = write_fits(tmp_path / "a.fits", data, EXPTIME=2.5)
    (flat,) = read_flats([path])
    assert isinstance(flat, Flat)
    assert flat.exptime == 2.5 and flat.name == str(path)
    assert flat.header["EXPTIME"] == 2.5
    np.testing.assert_allclose(flat.data, data.astype(np.float32))
    flats = read_flats([data, data], exptimes=[1.0, 1.0])
    assert [f.name for f in flats] == ["array[0]", "array[1]"]


def test_read_flats_finds_image_extension_and_primary_exptime(tmp_path):
    data = np.ones((16, 16))
    primary = fits.PrimaryHDU()
    primary.header["EXPTIME"] = 4.0
    path = tmp_path / "ext.fits"
    fits.HDUList([primary, fits.ImageHDU(data)]).writeto(path)
    (flat,) = read_flats(path)
    assert flat.exptime == 4.0 and flat.shape == (16, 16)


def test_missing_exptime_names_the_file(tmp_path):
    path = write_fits(tmp_path / "noexp.fits", np.ones((8, 8)))
    with pytest.raises(BFPSFInputError, match=r"noexp\.fits: header keyword EXPTIME is missing"):
        read_flats([path])


def test_arrays_need_exptimes_and_counts_must_match():
    with pytest.raises(BFPSFInputError, match=r"array\[0\]: flats given as arrays need exptimes"):
        read_flats([np.ones((4, 4))])
    with pytest.raises(BFPSFInputError, match="got 1 exptimes for 2 flats"):
        read_flats([np.ones((4, 4)), np.ones((4, 4))], exptimes=[1.0])
    with pytest.raises(BFPSFInputError, match="must be a 2-D image"):
        read_flats([np.ones(4)], exptimes=[1.0])


def test_missing_file_is_named(tmp_path):
    with pytest.raises(BFPSFInputError, match="flat file .*nothere.fits does not exist"):
        read_flats([tmp_path / "nothere.fits"])


# ---------------------------------------------------------------------------------------------
# Pairing


def test_pairs_by_exptime_in_order_and_sorted():
    rng = np.random.default_rng(1)
    images = [gaussian_flat(rng, (16, 16), level, 1.0) for level in (200, 100, 100, 200, 200, 200)]
    flats = read_flats(images, exptimes=[2, 1, 1, 2, 2, 2])
    pairs = pair_flats(flats)
    assert [pair.exptime for pair in pairs] == [1, 2, 2]
    assert isinstance(pairs[0], FlatPair)
    # more than two at one EXPTIME: consecutive pairs, in the order given
    assert pairs[1].names == ("array[0]", "array[3]")
    assert pairs[2].names == ("array[4]", "array[5]")


def test_unpaired_flat_is_named():
    rng = np.random.default_rng(2)
    flats = read_flats([gaussian_flat(rng, (16, 16)) for _ in range(3)], exptimes=[1, 1, 1])
    with pytest.raises(BFPSFInputError, match=r"array\[2\] \(EXPTIME=1 s\) has no partner"):
        pair_flats(flats)


def test_shape_mismatch_is_an_error():
    rng = np.random.default_rng(3)
    flats = read_flats([gaussian_flat(rng, (16, 16)), gaussian_flat(rng, (16, 17))],
                       exptimes=[1, 1])
    with pytest.raises(BFPSFInputError, match="have the same EXPTIME but different shapes"):
        pair_flats(flats)


def test_means_differing_beyond_tolerance_is_an_error():
    rng = np.random.default_rng(4)
    flats = read_flats([gaussian_flat(rng, level=LEVEL), gaussian_flat(rng, level=1.1 * LEVEL)],
                       exptimes=[1, 1])
    with pytest.raises(BFPSFInputError, match=r"differing by 9.\d+ % > mean_tolerance=5 %"):
        pair_flats(flats)
    assert len(pair_flats(flats, mean_tolerance=0.2)) == 1


# ---------------------------------------------------------------------------------------------
# Masks


def test_nonfinite_pixels_are_masked_counted_and_reported(caplog):
    rng = np.random.default_rng(5)
    flat1, flat2 = gaussian_flat(rng), gaussian_flat(rng)
    flat1[3, 4] = np.nan
    flat1[10, 10] = np.inf
    flat2[3, 4] = np.nan  # the same pixel in both counts once
    flat2[20, 30] = -np.inf
    with caplog.at_level(logging.INFO, logger="bfpsf.calibration.flat_mask"):
        mask, report = pair_mask(flat1, flat2)
    assert report.nonfinite == 3
    assert mask[3, 4] and mask[10, 10] and mask[20, 30]
    assert "masked 3 non-finite pixels" in caplog.text
    result = pair_covariance(flat1, flat2, mask=mask, maxlag=2)
    assert np.isfinite(result.cov_adu).all()
    # without the mask, non-finite pixels are still excluded (never an exception)
    bare = pair_covariance(flat1, flat2, maxlag=2, clip_nsigma=None)
    assert bare.n_masked == 3 and np.isfinite(bare.var_adu)


def test_clean_flat_is_hardly_masked():
    rng = np.random.default_rng(6)
    flats = gaussian_flat(rng, (256, 256)), gaussian_flat(rng, (256, 256))
    mask, report = pair_mask(*flats, edge=0)
    # Column test at 5 robust sigma and defects needing three 2.6-sigma neighbours: the
    # expected false-positive count on a clean Gaussian pair is far below one pixel.
    assert report.total == mask.sum() == 0
    # by default, a border of DEFAULT_EDGE pixels and nothing else
    mask, report = pair_mask(*flats)
    inner = slice(DEFAULT_EDGE, -DEFAULT_EDGE)
    assert not mask[inner, inner].any()
    assert report.total == report.edge == mask.sum() == 256**2 - (256 - 2 * DEFAULT_EDGE) ** 2
    with pytest.raises(BFPSFInputError, match="edge border"):
        pair_mask(*flats, edge=128)


def test_hot_column_and_defect_cluster_are_masked():
    rng = np.random.default_rng(7)
    flat1, flat2 = gaussian_flat(rng, (256, 256)), gaussian_flat(rng, (256, 256))
    for flat in (flat1, flat2):
        flat[:, 77] += 0.02 * LEVEL          # hot column: +2 sigma per pixel, 36 sigma in mean
        flat[:, 190] -= 0.02 * LEVEL         # dark column
        flat[140:143, 30:33] += 6 * NOISE    # a 3 x 3 defect cluster, 6 sigma high
    flat2[60:62, 200:202] += 8 * NOISE       # a 2 x 2 cluster in one image only
    mask, report = pair_mask(flat1, flat2, edge=0)
    assert mask[:, 77].all() and mask[:, 190].all()
    assert report.columns == 2 * 256
    assert mask[140:143, 30:33].all()
    assert mask[60:62, 200:202].all()
    # nothing else: the clusters are exactly what was injected
    others = mask.copy()
    others[:, [77, 190]] = False
    assert others.sum() == report.defects == 9 + 4
    assert report.total == 2 * 256 + 13


def test_isolated_or_linear_features_are_not_defects():
    rng = np.random.default_rng(8)
    flat1, flat2 = gaussian_flat(rng), gaussian_flat(rng)
    flat1[50, 50] += 20 * NOISE              # a single hot pixel: no 3 neighbours
    flat1[70, 40:44] += 20 * NOISE           # a short trail: each pixel has at most 2
    mask, report = pair_mask(flat1, flat2)
    assert report.defects == 0


def test_saturation_masks_either_image():
    rng = np.random.default_rng(9)
    flat1, flat2 = gaussian_flat(rng), gaussian_flat(rng)
    flat1[5, 5] = 65535
    flat2[6, 6] = 65535
    mask, report = pair_mask(flat1, flat2, saturation=60000)
    assert report.saturated == 2 and mask[5, 5] and mask[6, 6]


def test_mask_follows_a_smooth_illumination_gradient():
    rng = np.random.default_rng(10)
    ramp = np.linspace(0.8, 1.2, 256)[None, :]  # +-20 % across the image: not bad columns
    flat1 = gaussian_flat(rng, (256, 256)) * ramp
    flat2 = gaussian_flat(rng, (256, 256)) * ramp
    # (the edge border's columns are left out of the neighbours, not filled: they had bent
    # the running median near both edges, and 7 columns were flagged)
    for edge in (0, DEFAULT_EDGE, 40):
        _, report = pair_mask(flat1, flat2, edge=edge)
        assert report.columns == 0, edge


def _reference_band_tests(band, good, box, defect_nsigma, column_clip=5.0):
    """G15's two-step tile estimate written plainly, tile by tile, in double precision."""
    rows, nx = band.shape
    level_sums, level_counts, high = np.zeros(nx), np.zeros(nx), []
    for start in range(0, nx, box):
        tile, tile_good = band[:, start:start + box].astype(float), good[:, start:start + box]
        values = tile[tile_good]
        if values.size < 2:
            continue
        kept = values[np.abs(values - values.mean()) <= 2 * values.std()]
        if kept.size < 2:
            continue
        mean, sigma = kept.mean(), kept.std()
        rows_high, columns_high = np.nonzero(tile_good & (tile > mean + defect_nsigma * sigma))
        high.extend(rows_high * nx + columns_high + start)
        inside = tile_good & (np.abs(tile - mean) <= column_clip * sigma)
        level_sums[start:start + box] = np.where(inside, tile, 0).sum(axis=0)
        level_counts[start:start + box] = inside.sum(axis=0)
    return level_sums, level_counts, np.sort(high)


@pytest.mark.parametrize("with_bad", [False, True])
def test_compiled_band_tests_match_the_plain_reference(with_bad):
    """The compiled tile tests (numba) give G15's estimate: the same high pixels and column
    levels as a plain per-tile implementation, with bad pixels, defects, a tile of another
    level and a last tile narrower than the box."""
    rng = np.random.default_rng(12)
    band = rng.normal(0.0, 200.0, (64, 300)).astype(np.float32)
    band[:, 128:256] += 900.0                   # a tile at another level
    band[10:13, 40:43] += 1500.0                # a defect cluster
    band[:, 280] += 700.0                       # a bright column in the narrow last tile
    good = rng.random(band.shape) > (0.05 if with_bad else 0.0)
    if with_bad:
        good[:, 295:] = False                   # columns without a good pixel
    band[~good] = 0.0
    level_sums, level_counts, high = _band_tests(band, None if good.all() else good, 64, 3.0)
    ref_sums, ref_counts, ref_high = _reference_band_tests(band, good, 64, 3.0)
    assert high.size > 50  # the 2.6-sigma tail and the cluster
    np.testing.assert_array_equal(high, ref_high)
    np.testing.assert_array_equal(level_counts, ref_counts)
    np.testing.assert_allclose(level_sums, ref_sums, rtol=1e-5, atol=1e-2)


def test_big_endian_flats_as_read_from_fits_give_the_same_mask_and_covariances():
    """FITS pixels are big-endian (and often single precision): Flats holding them straight
    from astropy give what native arrays give."""
    rng = np.random.default_rng(13)
    first, second = gaussian_flat(rng, (128, 128)), gaussian_flat(rng, (128, 128))
    first[40:43, 50:53] += 8 * NOISE  # a defect cluster
    second = second.astype(np.float32).astype(float)  # what single precision holds
    native = [Flat(first, 1.0, "a"), Flat(second, 1.0, "b")]
    swapped = [Flat(first.astype(">f8"), 1.0, "a"), Flat(second.astype(">f4"), 1.0, "b")]
    mask, report = pair_mask(*native)
    swapped_mask, swapped_report = pair_mask(*swapped)
    assert mask[40:43, 50:53].all()
    np.testing.assert_array_equal(swapped_mask, mask)
    assert swapped_report == report
    np.testing.assert_allclose(pair_covariance(*swapped, mask=mask).cov_adu,
                               pair_covariance(*native, mask=mask).cov_adu, rtol=1e-12)
