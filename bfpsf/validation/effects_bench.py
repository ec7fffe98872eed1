"""A test bench of effects the catalogue does not hold (and of the null and catalogue effects).

Spots are drawn once per exposure (noise-free, with brighter-fatter) and every bench case
applies its effect to the same electrons before the noise, so the cases differ only by the
effect. Two renderings of the BF:

* ``sensor=None`` (quick): a Moffat drawn by GalSim (pixel-integrated) at each sub-pixel phase,
  redistributed by bfpsf's own forward operator (`bfpsf.redistribute`, G15 eq.
  scrambling_model) with given boundary shifts;
* ``sensor='lsst_e2v_50_8'`` (full): GalSim SiliconSensor photon shooting
  (`bfpsf.validation.simulate_spots`), a BF truth independent of G15.

The effects outside the catalogue (`OUTSIDE_EFFECTS`, ``strength`` a in fraction of a pixel's
charge per 1e5 e- in it; charge conserving):

``one_axis``
    Charge-dependent smear along X only: each pixel passes a fraction k = a Q / 1e5 of its
    charge Q to each X neighbour. Even parity, sigma_x grows with flux, sigma_y does not.
``position``
    The same smear on both axes with a strength growing with the distance from the amplifier
    (column 0): a 2 x / width, mean a over the detector.
``centroid``
    A charge-dependent trail along Y (deferred charge): each pixel passes k = a Q / 1e5 of its
    charge to the next row (+y). Odd parity: centroids move to +y with flux, sigma_y grows.
``night``
    The isotropic smear with a strength growing over the exposures of the night: a 2 t,
    t = exposure / (n - 1).
``diagonal``
    Charge-dependent smear along the diagonal x = y: each pixel passes a Q / 1e5 of its
    charge to each of its (+1, +1) and (-1, -1) neighbours: the stars grow on both axes, as
    from a size effect, and their e2 grows with flux (a new user's invented effect, which
    the flats' size scale had taken).
``halo``
    A halo of the brightest pixels only: a pixel holding Q above `HALO_THRESHOLD` passes a
    fraction a (Q - Q_T) / 1e5 of its charge into a Gaussian of `HALO_SIGMA` pixels about it.
    Even, isotropic, nothing below the threshold and faster than linear above it (a new
    user's well-filling halo, named second_order at a negative t, then a diffusion).

Catalogue effects applied to the electrons as the flats simulator applies them
(`bfpsf.validation.simulate_flats`): ``gain_nonlinearity`` (v -> v (1 + c v)) and
``serial_readout`` (q[:, i] + c q[:, i - 1]).

`bench_sizes` measures every spot (adaptive moments, `bfpsf.moments.adaptive`) and its
third moments (odd parity), and bins them per exposure, level and detector column into a
`SizeTable` with the detector position (``x_detector``), the skewness columns and the cross
moment e2 (``cross``), one intercept
group per detector column (the spots of a column share their sub-pixel phase).
"""

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..diagnosis.odd_moments import skewness
from ..diagnosis.tables import SizeTable
from ..errors import BFPSFValueError
from ..model.redistribution import redistribute
from ..moments.adaptive import adaptive_moments_batch
from ..moments.shapes import distortion
from .simulate_spots import simulate_spots

__all__ = ["OUTSIDE_EFFECTS", "CATALOGUE_CASES", "BenchSpots", "draw_bench_spots",
           "apply_effect", "bench_sizes"]

#: Effects no catalogue entry describes.
OUTSIDE_EFFECTS = ("one_axis", "position", "centroid", "night", "diagonal", "halo")
#: The null and the catalogue effects injected into the electrons.
CATALOGUE_CASES = ("null", "gain_nonlinearity", "serial_readout")

#: The halo's threshold (e- in a pixel) and width (pixels).
HALO_THRESHOLD = 3e4
HALO_SIGMA = 3.0

#: Detector width the spots are spread over (pixels): columns 0, 1, 2 of the grid of phases
#: sit at x = (column + 1/2) / 3 of it.
DETECTOR_WIDTH = 2000.0


@dataclass(frozen=True)
class BenchSpots:
    """Noise-free spots of a night, e-.

    Attributes
    ----------
    stamps : ndarray (n, size, size)
    exposure : ndarray of int (n,)
    level : ndarray of int (n,)
        Index into ``peaks_e``.
    column : ndarray of int (n,)
        Detector column of the spot (0, 1, 2); it is also the X sub-pixel phase index.
    x_detector : ndarray (n,)
        Position on the detector along X (distance from the amplifier), pixels.
    peaks_e : tuple of float
        Requested peak levels (without BF), e-.
    n_exposures : int
    """

    stamps: np.ndarray
    exposure: np.ndarray
    level: np.ndarray
    column: np.ndarray
    x_detector: np.ndarray
    peaks_e: tuple
    n_exposures: int


def _phases():
    grid = (np.arange(3) + 0.5) / 3 - 0.5
    return np.array([(x, y) for y in grid for x in grid])


def draw_bench_spots(*, n_exposures, shifts=None, sensor=None,
                     peaks_e=(3e3, 2.5e4, 5e4, 7.5e4, 1e5, 1.2e5), fwhm=3.0, beta=3.0,
                     stamp_size=24, seed=10):
    """Noise-free Moffat spots with brighter-fatter, 9 sub-pixel phases per level and exposure.

    Parameters
    ----------
    n_exposures : int
    shifts : BoundaryShifts, optional
        Quick rendering (``sensor=None``): the BF is `bfpsf.redistribute` with these.
    sensor : str, optional
        A SiliconSensor name: photon shooting through it (`simulate_spots`).
    peaks_e : sequence of float
        Peak levels, e- (the flux is peak / the peak-pixel fraction at the spot's phase).
    fwhm, beta : float
        Moffat FWHM (pixels) and index.
    stamp_size : int
    seed : int
        Seed of exposure k is ``seed + k`` (photons of the SiliconSensor draws).

    Returns
    -------
    BenchSpots
    """
    import galsim

    if (sensor is None) == (shifts is None):
        msg = "give either shifts (quick rendering) or a SiliconSensor name, not both"
        raise BFPSFValueError(msg, sensor)
    phases = _phases()
    peaks = np.asarray(peaks_e, float)
    stamps, exposure, level, column = [], [], [], []
    profile = galsim.Moffat(fwhm=fwhm, beta=beta)
    for index in range(int(n_exposures)):
        if sensor is not None:
            spots = simulate_spots(sensor=sensor, fwhm=fwhm, beta=beta, peaks_e=peaks,
                                   n_per_level=9, stamp_size=stamp_size, seed=seed + index,
                                   offsets=phases)
            stamps.append(spots.stamps)
        else:
            drawn = []
            for peak in peaks:
                for offset in phases:
                    image = profile.drawImage(nx=stamp_size, ny=stamp_size, scale=1.0,
                                              offset=tuple(offset)).array
                    drawn.append(redistribute(image * peak / image.max(), shifts, workers=1))
            stamps.append(np.array(drawn))
        exposure.append(np.full(peaks.size * 9, index))
        level.append(np.repeat(np.arange(peaks.size), 9))
        column.append(np.tile(np.arange(9) % 3, peaks.size))
    column = np.concatenate(column)
    return BenchSpots(stamps=np.concatenate(stamps), exposure=np.concatenate(exposure),
                      level=np.concatenate(level), column=column,
                      x_detector=(column + 0.5) / 3 * DETECTOR_WIDTH, peaks_e=tuple(peaks),
                      n_exposures=int(n_exposures))


def _smear(stamps, strength, axes):
    """Charge-dependent smear: each pixel passes k = strength Q / 1e5 of its charge Q to each
    neighbour along ``axes`` (2: y, 1: x of a (n, y, x) stack); ``strength`` per stamp."""
    strength = np.asarray(strength, float).reshape(-1, 1, 1)
    out = stamps.copy()
    for axis in axes:
        passed = np.clip(strength * stamps / 1e5, 0.0, 0.2) * stamps
        out = out - 2 * passed + np.roll(passed, 1, axis=axis) + np.roll(passed, -1, axis=axis)
    return out


def apply_effect(spots, name, strength):
    """The stamps of ``spots`` with one bench effect applied to their electrons.

    Parameters
    ----------
    spots : BenchSpots
    name : str
        One of `OUTSIDE_EFFECTS` or `CATALOGUE_CASES`.
    strength : float
        a of the outside effects (per 1e5 e-), c of ``gain_nonlinearity`` (1/e-), the serial
        correlation c of ``serial_readout``; ignored by ``null``.

    Returns
    -------
    ndarray (n, size, size), e-
    """
    stamps = spots.stamps
    if name == "null":
        return stamps.copy()
    if name == "one_axis":
        return _smear(stamps, np.full(len(stamps), strength), axes=(2,))
    if name == "position":
        return _smear(stamps, 2 * strength * spots.x_detector / DETECTOR_WIDTH, axes=(1, 2))
    if name == "night":
        late = spots.exposure / max(spots.n_exposures - 1, 1)
        return _smear(stamps, 2 * strength * late, axes=(1, 2))
    if name == "centroid":
        passed = np.clip(strength * stamps / 1e5, 0.0, 0.2) * stamps
        return stamps - passed + np.roll(passed, 1, axis=1)
    if name == "diagonal":
        passed = np.clip(strength * stamps / 1e5, 0.0, 0.2) * stamps
        return (stamps - 2 * passed + np.roll(passed, (1, 1), axis=(1, 2))
                + np.roll(passed, (-1, -1), axis=(1, 2)))
    if name == "halo":
        passed = np.clip(strength * (stamps - HALO_THRESHOLD) / 1e5, 0.0, 0.2) * stamps
        return stamps - passed + ndimage.gaussian_filter(passed, (0, HALO_SIGMA, HALO_SIGMA),
                                                         mode="wrap")
    if name == "gain_nonlinearity":
        return stamps * (1.0 + strength * stamps)
    if name == "serial_readout":
        out = stamps.copy()
        out[:, :, 1:] += strength * stamps[:, :, :-1]
        return out
    msg = f"unknown bench effect {name!r}; expected one of {OUTSIDE_EFFECTS + CATALOGUE_CASES}"
    raise BFPSFValueError(msg, name)


def bench_sizes(spots, stamps_e, *, sky_e=50.0, read_noise_e=5.0, seed=0):
    """Noise added, every spot measured, binned per exposure, level and detector column.

    Returns
    -------
    (SizeTable, dict)
        The table (``group`` = detector column, ``exposure``, ``x_detector``, skewness
        columns); peaks are the mean measured peak pixel of each bin. The dict holds
        ``peak_e`` and ``flux_e`` (stamp sums) of every spot, for `flux_of_peak`.
    """
    rng = np.random.default_rng(seed)
    noisy = stamps_e + rng.poisson(np.clip(stamps_e, 0, None) + sky_e) - stamps_e - sky_e
    noisy = noisy + read_noise_e * rng.standard_normal(stamps_e.shape)
    moments = adaptive_moments_batch(noisy)
    good = np.asarray(moments.flags) == 0
    sigma_x, sigma_y = np.sqrt(np.asarray(moments.mxx)), np.sqrt(np.asarray(moments.myy))
    skew_x, skew_y = skewness(noisy, moments)
    peak = noisy.max(axis=(1, 2))
    flux = noisy.sum(axis=(1, 2))
    values = {"sigma_x": sigma_x, "sigma_y": sigma_y, "skew_x": skew_x, "skew_y": skew_y,
              "cross": distortion(moments.mxx, moments.myy, moments.mxy)[1]}
    # errors pooled per level: the scatter of each spot about its bin mean, over all bins
    key = (spots.exposure * 1000 + spots.level * 10 + spots.column)
    rows = np.unique(key[good])
    table = {name: [] for name in ("peak", "exposure", "column", "x", *values)}
    errors = {name: [] for name in values}
    pooled = {}
    for name, value in values.items():
        deviations = np.zeros(value.size)
        for row in rows:
            members = good & (key == row)
            deviations[members] = value[members] - value[members].mean()
        pooled[name] = {lev: np.sqrt(np.sum(deviations[good & (spots.level == lev)] ** 2)
                                     / max(np.sum(good & (spots.level == lev))
                                           - len(np.unique(key[good & (spots.level == lev)])), 1))
                        for lev in np.unique(spots.level)}
    for row in rows:
        members = good & (key == row)
        first = np.flatnonzero(members)[0]
        table["peak"].append(peak[members].mean())
        table["exposure"].append(spots.exposure[first])
        table["column"].append(spots.column[first])
        table["x"].append(spots.x_detector[first])
        for name, value in values.items():
            table[name].append(value[members].mean())
            errors[name].append(pooled[name][spots.level[first]] / np.sqrt(members.sum()))
    sizes = SizeTable(np.array(table["peak"]), np.array(table["sigma_x"]),
                      np.array(table["sigma_y"]), np.array(errors["sigma_x"]),
                      np.array(errors["sigma_y"]), group=np.array(table["column"]),
                      label="bench", exposure=np.array(table["exposure"]),
                      x_detector=np.array(table["x"]), skew_x=np.array(table["skew_x"]),
                      skew_y=np.array(table["skew_y"]), skew_x_err=np.array(errors["skew_x"]),
                      skew_y_err=np.array(errors["skew_y"]), cross=np.array(table["cross"]),
                      cross_err=np.array(errors["cross"]))
    return sizes, {"peak_e": peak[good], "flux_e": flux[good]}
