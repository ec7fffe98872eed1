"""Truth from GalSim's SiliconSensor: its pixel-area coefficients, its boundary shifts and its
lateral diffusion.

GalSim's `galsim.SiliconSensor` simulates brighter-fatter from Poisson_CCD pixel-boundary
solutions, physics independent of G15, so bfpsf validates against it (DESIGN.md).

GalSim has two rules, and they differ at the percent level that PSF ellipticity needs:

* Pixel areas (`silicon_area_coefficients`, ``calculate_pixel_areas``) are the areas of its
  pixel polygons. Flat fields are built from them (`bfpsf.validation.simulate_flats`, as in
  GalSim's own tests): photon-shooting a flat is too slow.
* Stars are drawn by landing photons (``accumulate``), which tests each photon against the
  polygons of its nominal pixel first. The landing response to one charged pixel
  (`silicon_boundary_shifts`) differs from the polygon areas by up to 40 % for the nearest
  neighbours, and it is not additive: under a star's charge the boundaries sit where the sum
  of the single-pixel responses does not put them (`landing_under`).

Measured for ``lsst_e2v_50_8`` (tests/test_silicon_shapes.py): a P(F) given the single-pixel
landing shifts leaves 14 % of a star's BF change of e1; scaled to the landing under a star,
3 %; the electrostatic solver on the polygon areas (what flats of infinite statistics can
know) 17 %.
"""

import glob
import os
from typing import NamedTuple

import galsim
import numpy as np
from scipy.signal import correlate

from ..errors import BFPSFValueError, integer_at_least
from ..shifts import BoundaryShifts

__all__ = [
    "silicon_sensor",
    "silicon_sensor_names",
    "silicon_area_coefficients",
    "silicon_boundary_shifts",
    "landing_under",
    "LandingUnder",
    "silicon_diffusion_sigma",
]


def silicon_sensor_names():
    """Names of the SiliconSensor models GalSim ships (its ``share/sensors/*.cfg``)."""
    pattern = os.path.join(galsim.meta_data.share_dir, "sensors", "*.cfg")
    return sorted(os.path.basename(path)[:-len(".cfg")] for path in glob.glob(pattern))


def silicon_sensor(name, **sensor_kwargs):
    """`galsim.SiliconSensor` by name, refusing an unknown name with the list of known ones."""
    names = silicon_sensor_names()
    if name not in names:
        msg = f"unknown GalSim SiliconSensor {name!r}; GalSim has {', '.join(names)}"
        raise BFPSFValueError(msg, name)
    return galsim.SiliconSensor(name=name, **sensor_kwargs)


def silicon_area_coefficients(sensor="lsst_itl_50_8", *, charge=1000.0, maxlag=4, level=0.0,
                              **sensor_kwargs):
    """Truth area coefficients a(dx, dy) of a GalSim SiliconSensor, 1/e-.

    The pixel-area response to ``charge`` electrons in one pixel, minus the response of an
    empty image, divided by the charge (DESIGN.md, "GalSim as the reference physics").

    Parameters
    ----------
    sensor : str or galsim.SiliconSensor
        Sensor name (e.g. ``'lsst_itl_50_8'``, ``'lsst_e2v_50_8'``) or a sensor instance.
    charge : float, optional
        Electrons in the source pixel. Flats probe the response to small fluctuations, so keep
        it small: the response is not linear in the charge (a(1, 0) of lsst_e2v_50_8 drops
        from 0.92e-7 at 1e3 e- to 0.67e-7 at 1e5 e-). Default 1000.
    maxlag : int, optional
        Largest lag returned. Default 4 (GalSim moves boundaries only within 4 pixels).
    level : float, optional
        Uniform charge (e-) of the image the extra ``charge`` sits on: the response about a
        flat-field level. Default 0 (an empty image); up to 100 ke- it differs by < 0.6 % of
        a(0, 0) for lsst_itl_50_8 and < 1.6 % for lsst_e2v_50_8 (a(1, 0) -7 % and -37 % at
        100 ke-).
    **sensor_kwargs
        Passed to `galsim.SiliconSensor` when ``sensor`` is a name.

    Returns
    -------
    ndarray, shape (maxlag + 1, maxlag + 1)
        a(dx, dy) indexed [dy, dx] for dx, dy = 0..maxlag, quadrant-averaged over the four
        signs of (dx, dy) as the flats measure it.

    Notes
    -----
    These are the areas of GalSim's pixel polygons, from which flats are built. Where photons
    land (`SiliconSensor.accumulate`, which draws stars) differs from them for the nearest
    neighbours: by about 20 % for a(1, 0) and a(1, 1) of lsst_itl_50_8, +44 % and -31 % for
    lsst_e2v_50_8, because a photon is tested against the polygon of its nominal pixel first
    (module notes); sums over square blocks centred on the charge agree (see
    `silicon_boundary_shifts`).
    """
    if charge <= 0:
        msg = f"charge must be positive, got {charge}"
        raise BFPSFValueError(msg, charge)
    if not (np.isfinite(level) and level >= 0):
        msg = f"level must be a finite charge >= 0 e-, got {level}"
        raise BFPSFValueError(msg, level)
    if isinstance(sensor, str):
        sensor = silicon_sensor(sensor, **sensor_kwargs)
    size = 2 * (int(maxlag) + 6) + 1
    centre = size // 2
    image = galsim.ImageD(size, size, init_value=float(level))
    empty_area = sensor.calculate_pixel_areas(image).array.copy()
    image.array[centre, centre] += charge
    charged_area = sensor.calculate_pixel_areas(image).array
    response = (charged_area - empty_area) / charge
    window = response[centre - maxlag:centre + maxlag + 1, centre - maxlag:centre + maxlag + 1]
    folded = (window + window[::-1, :] + window[:, ::-1] + window[::-1, ::-1]) / 4.0
    return folded[maxlag:, maxlag:].copy()


# -- boundary shifts of a SiliconSensor ----------------------------------------------------------
def _measurement_sensor(sensor, sensor_kwargs, seed=0):
    """A SiliconSensor like ``sensor`` with diffusion off, no tree rings, no recalculation, and
    its own random numbers (where it places a photon found in no pixel) seeded from ``seed``."""
    if isinstance(sensor, str):
        params = dict(name=sensor, **sensor_kwargs)
    elif isinstance(sensor, galsim.SiliconSensor):
        if sensor_kwargs:
            msg = ("sensor keywords are only accepted with a sensor name, got "
                   f"{sorted(sensor_kwargs)}")
            raise BFPSFValueError(msg, sorted(sensor_kwargs))
        params = dict(name=sensor.name, strength=sensor.strength, qdist=sensor.qdist,
                      transpose=sensor.transpose)
    else:
        msg = f"sensor must be a name or a galsim.SiliconSensor, got {type(sensor).__name__}"
        raise BFPSFValueError(msg, sensor)
    # nrecalc=0: the boundaries are computed once from the image given to accumulate.
    params.update(diffusion_factor=0.0, nrecalc=0, rng=galsim.BaseDeviate(int(seed) + 1))
    return galsim.SiliconSensor(**params)


def _strip_photons(strips, widths, ncol, nrow, rng):
    """Photon positions filling a thin strip across each boundary.

    ``strips`` holds (px, py, label) of the pixel below (N) or left of (E) the boundary. Along
    the boundary: ``ncol`` columns at the midpoints of equal segments; across it: ``nrow``
    rows spread evenly over (-w, w) with a random sub-row offset per column (stratified), so
    the mean count gives the boundary position to ~ 2 w / (nrow sqrt(12 ncol)).
    """
    along = (np.arange(ncol) + 0.5) / ncol - 0.5
    xs, ys = [], []
    for (px, py, label), width in zip(strips, widths):
        offset = rng.uniform(0.0, 1.0, ncol)
        across = ((np.arange(nrow)[None, :] + offset[:, None]) / nrow * 2.0 - 1.0) * width
        along_all = np.repeat(along, nrow)
        across = across.ravel()
        if label == "N":
            xs.append(px + along_all)
            ys.append(py + 0.5 + across)
        else:
            xs.append(px + 0.5 + across)
            ys.append(py + along_all)
    return np.concatenate(xs), np.concatenate(ys)


def _landing_gain(sensor, x, y, charge_image):
    """Photons of flux 1 at (x, y) landed on ``charge_image`` (e-, pixel (0, 0) at the origin;
    with nrecalc=0 they do not move the boundaries): the count each pixel received minus the
    count of its square nominal pixel."""
    photons = galsim.PhotonArray(len(x), x=x, y=y, flux=np.ones(len(x)))
    target = galsim.ImageD(np.array(charge_image, dtype=float), xmin=0, ymin=0)
    sensor.accumulate(photons, target)
    gained = target.array - charge_image
    np.add.at(gained, (np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)), -1.0)
    return gained


def _measure_displacements(sensor, charge, strips, widths, ncol, nrow, size, centre, rng):
    """Boundary displacement (px, outward for the lower/left pixel) of each strip's boundary.

    Strips must not share pixels. Photons land on an image holding ``charge`` in the centre
    pixel (with nrecalc=0 they do not move the boundaries); the landed counts minus the counts
    of square pixels give the area swept by each boundary.
    """
    x, y = _strip_photons(strips, widths, ncol, nrow, rng)
    charge_image = np.zeros((size, size))
    charge_image[centre, centre] = charge
    gained = _landing_gain(sensor, x, y, charge_image)
    per_strip = ncol * nrow
    displacements = []
    for (px, py, label), width in zip(strips, widths):
        qx, qy = (px, py + 1) if label == "N" else (px + 1, py)
        # Photon density is per_strip / (2 w) per unit area: d = (gain_p - gain_q) / 2 * 2w / n.
        displacements.append((gained[py, px] - gained[qy, qx]) * width / per_strip)
    return np.array(displacements)


def silicon_boundary_shifts(sensor="lsst_itl_50_8", *, charge=1000.0, radius=4,
                            photons_per_boundary=40000, symmetrize=True, seed=0, under=None,
                            **sensor_kwargs):
    """Boundary shifts a^N, a^E of a GalSim SiliconSensor, measured by landing photons.

    GalSim's Python interface does not expose the pixel-boundary polygons, so they are
    measured where it matters, in `SiliconSensor.accumulate`: ``charge`` electrons sit in one
    pixel, diffusion is switched off, and a thin strip of photons (deterministic stratified
    positions, flux 1, no boundary recalculation) is laid across every boundary within
    ``radius`` of the charge. The photons that cross to the other side of the nominal boundary
    measure its displacement averaged along the boundary; the same count on square pixels is
    subtracted. One number per shared boundary makes translation invariance exact.

    A first pass uses strips of half-width 2 |a(0,0)| charge; a second pass narrows each strip
    to 8 times its measured displacement (at least 1/64 of the first width), which makes the
    far, small shifts as precise as the near ones; a boundary whose second-pass value
    disagrees with the first by more than 5 first-pass errors keeps the first-pass value.

    Parameters
    ----------
    sensor : str or galsim.SiliconSensor
        Sensor name or instance (its name, strength, qdist and transpose are used; tree rings
        are not part of brighter-fatter and are left out).
    charge : float, optional
        Electrons in the source pixel. GalSim's boundaries move linearly with the charge; keep
        it small, because a strip that a moving side boundary cuts loses photons sideways,
        which are then taken for crossings (a^N(+-1, 0) of lsst_e2v_50_8 is 30 % low at
        29 ke-; `landing_under` counts crossings without that error). Default 1000.
    radius : int, optional
        Offsets -radius..radius. Default 4: with GalSim's default qdist=3 the boundaries
        between pixels 3 and 4 away are the last that move.
    photons_per_boundary : int, optional
        Photons per strip and pass (default 40000: a displacement precision of about
        1e-4 of the strip width).
    symmetrize : bool, optional
        Impose parity, a^N(dx, dy) = -a^N(-dx, 1 - dy) and a^E(dx, dy) = -a^E(1 - dx, -dy), by
        averaging each pair (the LSST sensors obey it to the measurement precision).
        Default True; with False the raw measurement is returned (``check=False``).
    seed : int, optional
        Seed of the sub-row offsets.
    under : array_like, optional
        A charge image (e.g. a star, any amplitude) the shifts are meant for. GalSim's landing
        is not additive: the boundaries under a star's charge sit where the sum of the
        single-pixel shifts does not put them. With ``under``, the boundaries within ``radius``
        of the image's centre are measured with its charge present (`landing_under`) and
        a^N and a^E are each scaled by one factor, the least-squares ratio of the measured to
        the predicted displacements (`LandingUnder.factors`). Default None: single-pixel
        shifts.
    **sensor_kwargs
        Passed to `galsim.SiliconSensor` when ``sensor`` is a name.

    Returns
    -------
    BoundaryShifts
        a^X in pixels per electron, end of exposure. Their sum a(dx, dy) is the landing-area
        response of `SiliconSensor.accumulate`; it equals `silicon_area_coefficients` for
        a(0, 0) and for sums over square blocks centred on the charge, while the individual
        nearest neighbours differ by up to ~20 % (see the notes there).
    """
    sensor = _measurement_sensor(sensor, sensor_kwargs, seed)
    if charge <= 0:
        msg = f"charge must be positive, got {charge}"
        raise BFPSFValueError(msg, charge)
    m = integer_at_least("radius", radius, 1)
    ncol = 64
    nrow = max(int(photons_per_boundary) // ncol, 4)
    area00 = abs(silicon_area_coefficients(sensor, charge=charge, maxlag=0)[0, 0])
    first_width = 2.0 * area00 * charge
    if not 0 < first_width <= 0.25:
        msg = (f"charge {charge} e- moves the boundaries by {area00 * charge:.3g} px; the strips "
               "need it below 0.12 px: use a smaller charge")
        raise BFPSFValueError(msg, charge)
    size = 2 * (m + 3) + 1
    centre = size // 2
    rng = np.random.default_rng(seed)
    # Pixel (0, 0) of a^X(dx, dy) sits at -(dx, dy) from the charge. Strips in one call must
    # not share pixels: north boundaries by the parity of the row, east ones of the column.
    groups = []
    for label in ("N", "E"):
        for parity in (0, 1):
            strips, offsets = [], []
            for dy in range(-m, m + 1):
                for dx in range(-m, m + 1):
                    if (label == "N" and dy == -m) or (label == "E" and dx == -m):
                        continue  # outside the grid by parity (BoundaryShifts convention)
                    px, py = centre - dx, centre - dy
                    if (py if label == "N" else px) % 2 != parity:
                        continue
                    strips.append((px, py, label))
                    offsets.append((label, dy + m, dx + m))
            groups.append((strips, offsets))
    north = np.zeros((2 * m + 1, 2 * m + 1))
    east = np.zeros_like(north)
    # Quantisation error of a strip (one row spacing 2w/nrow, uniform, averaged over ncol).
    first_error = 2.0 * first_width / (nrow * np.sqrt(12.0 * ncol))
    for strips, offsets in groups:
        widths = np.full(len(strips), first_width)
        first = _measure_displacements(sensor, charge, strips, widths, ncol, nrow, size,
                                       centre, rng)
        narrow = np.clip(8.0 * np.abs(first) + 20.0 * first_error, first_width / 64.0,
                         first_width)
        second = _measure_displacements(sensor, charge, strips, narrow, ncol, nrow, size,
                                        centre, rng)
        value = np.where(np.abs(second - first) <= 5.0 * first_error, second, first)
        for (label, iy, ix), displacement in zip(offsets, value):
            (north if label == "N" else east)[iy, ix] = displacement / charge
    if not symmetrize:
        shifts = BoundaryShifts(north, east, check=False)
    else:
        mirrored_north = np.zeros_like(north)
        mirrored_north[1:, :] = north[::-1, ::-1][:-1, :]
        mirrored_east = np.zeros_like(east)
        mirrored_east[:, 1:] = east[::-1, ::-1][:, :-1]
        shifts = BoundaryShifts(0.5 * (north - mirrored_north), 0.5 * (east - mirrored_east))
    if under is None:
        return shifts
    factor_north, factor_east = landing_under(sensor, under, shifts, radius=m,
                                              photons_per_boundary=photons_per_boundary,
                                              seed=seed).factors
    return BoundaryShifts(shifts.north * factor_north, shifts.east * factor_east,
                          check=symmetrize)


class LandingUnder(NamedTuple):
    """Boundary displacements of a SiliconSensor under a charge image (`landing_under`).

    ``measured_north[y, x]`` is the displacement (px, positive up) of the boundary between
    pixels (x, y) and (x, y + 1) of the padded image, ``measured_east[y, x]`` that between
    (x, y) and (x + 1, y) (positive right); NaN where not measured. ``predicted_*`` are the
    sums of the single-pixel shifts over the charge (G15's linear superposition) and
    ``factors`` the least-squares ratios (north, east) of measured to predicted.
    """

    measured_north: np.ndarray
    measured_east: np.ndarray
    predicted_north: np.ndarray
    predicted_east: np.ndarray
    factors: tuple


def landing_under(sensor, image, shifts, *, radius=4, photons_per_boundary=40000, seed=0):
    """Where SiliconSensor's photons land with a charge image present, against the sum of shifts.

    GalSim moves its pixel boundaries linearly with the charge, but where a photon lands also
    depends on which pixel polygons it is tested against first, and that part is not additive:
    under a star's charge the boundaries of ``lsst_e2v_50_8`` sit 2.9 % (N) and 0.8 % (E)
    further out than the sum of its single-pixel landing shifts puts them, the same for any
    star shape and amplitude (FWHM 3-4.5 px, e1 -0.04..+0.04, any sub-pixel offset: within
    0.1 %). On a uniform flat-field level the response to a small extra charge is erratic:
    +1 % to +4 % (N) and -12 % to +2 % (E) against the single-pixel shifts, depending on the
    level and the size of the extra charge (measured with 10-100 ke- levels and 0.5-3 ke-
    charges). This measures it.

    Parameters
    ----------
    sensor : str or galsim.SiliconSensor
        Sensor name or instance (diffusion off and no recalculation, as in
        `silicon_boundary_shifts`).
    image : array_like
        Charge, electrons, any amplitude: it is rescaled so that the largest predicted
        displacement is 0.02 px (the response scales with the charge).
    shifts : BoundaryShifts
        The single-pixel shifts whose sum is compared (`silicon_boundary_shifts`).
    radius : int, optional
        Boundaries of the pixels within ``radius`` of the image centre are measured.
    photons_per_boundary : int, optional
        Photons per strip: one boundary's error is about 14 / photons_per_boundary of the
        largest displacement, plus GalSim's random placing of photons it finds in no pixel.
    seed : int, optional
        Seed of the strips' sub-row offsets and of the sensor's random numbers.

    Returns
    -------
    LandingUnder

    Notes
    -----
    Strips of photons are laid across the boundaries as in `silicon_boundary_shifts`, three
    columns and four rows apart (north; the transpose for east). A crossing is counted as the
    change of the photon count in the rows above the boundary within its strip's three columns,
    so that a photon leaving sideways through a moving east boundary is not taken for one.
    """
    image = np.asarray(image, dtype=float)
    if image.ndim != 2 or not np.all(np.isfinite(image)) or np.any(image < 0) or image.max() <= 0:
        msg = f"image must be a 2-D charge image >= 0 with some charge, got shape {image.shape}"
        raise BFPSFValueError(msg, image.shape)
    r = int(radius)
    if not 1 <= r <= min(image.shape) // 2:
        msg = f"radius must be between 1 and half the image size, got {radius}"
        raise BFPSFValueError(msg, radius)
    padded = np.pad(image, shifts.radius + 3)
    # G15's superposition: the boundary of pixel p moves by sum_d a^X(d) Q(p + d)
    predicted = (correlate(padded, shifts.north, mode="same"),
                 correlate(padded, shifts.east, mode="same"))
    scale = 0.02 / max(np.abs(predicted[0]).max(), np.abs(predicted[1]).max())
    padded = padded * scale
    predicted = tuple(p * scale for p in predicted)
    sensor = _measurement_sensor(sensor, {}, seed)
    cy, cx = (size // 2 for size in padded.shape)
    width = 0.06  # three times the largest displacement
    ncol = 64
    nrow = max(int(photons_per_boundary) // ncol, 4)
    rng = np.random.default_rng(seed)
    measured = (np.full(padded.shape, np.nan), np.full(padded.shape, np.nan))
    for axis, label in enumerate(("N", "E")):
        along, across = (3, 4) if label == "N" else (4, 3)  # strip spacing in x, y
        for ox in range(along):
            for oy in range(across):
                strips = [(px, py, label) for py in range(cy - r, cy + r + 1)
                          for px in range(cx - r, cx + r + 1)
                          if (px - ox) % along == 0 and (py - oy) % across == 0]
                x, y = _strip_photons(strips, [width] * len(strips), ncol, nrow, rng)
                gained = _landing_gain(sensor, x, y, padded)
                for px, py, _ in strips:
                    beyond = (gained[py + 1:py + 3, px - 1:px + 2] if label == "N"
                              else gained[py - 1:py + 2, px + 1:px + 3])
                    # photon density per_strip / (2 w): d = -2 w (net photons beyond) / n
                    measured[axis][py, px] = -2.0 * width * beyond.sum() / (ncol * nrow)
    factors = []
    for axis in range(2):
        seen = np.isfinite(measured[axis])
        model = predicted[axis][seen]
        factors.append(float((measured[axis][seen] * model).sum() / (model * model).sum()))
    return LandingUnder(measured[0] / scale, measured[1] / scale, predicted[0] / scale,
                        predicted[1] / scale, tuple(factors))


def silicon_diffusion_sigma(sensor="lsst_itl_50_8", *, diffusion_factor=None):
    """Lateral charge-diffusion RMS of a GalSim SiliconSensor, pixels.

    SiliconSensor moves each photon's charge by a Gaussian random step as it drifts to the
    collecting wells, before the (BF-distorted) pixel boundaries decide where it lands. The
    base PSF P0 that brighter-fatter acts on is therefore the optical PSF convolved with this
    Gaussian: a P0 without it is too sharp (for lsst_e2v_50_8 and a Moffat of FWHM 3.5 px it
    lacks 4 % of the Gaussian-weighted second moment) and over-predicts the BF slope by about
    as much again. A P0 fitted from the stars (`bfpsf.model.psf_fit.fit_psf`) includes it
    without being told.

    Parameters
    ----------
    sensor : str or galsim.SiliconSensor
        Sensor name or instance.
    diffusion_factor : float, optional
        GalSim's multiplier of the diffusion (default: the instance's own, or 1 for a name).

    Returns
    -------
    float
        The diffusion sigma for photons without wavelengths, which convert at the surface and
        drift the full thickness (GalSim's ``diff_step``, in the pixel unit; about 0.44 px for
        the LSST sensors at 173 K). Photons with wavelengths convert deeper and diffuse less.
    """
    if isinstance(sensor, str):
        sensor = galsim.SiliconSensor(name=sensor)
    elif not isinstance(sensor, galsim.SiliconSensor):
        msg = f"sensor must be a name or a galsim.SiliconSensor, got {type(sensor).__name__}"
        raise BFPSFValueError(msg, sensor)
    factor = sensor.diffusion_factor if diffusion_factor is None else float(diffusion_factor)
    if not factor >= 0:
        msg = f"diffusion_factor must be >= 0, got {diffusion_factor!r}"
        raise BFPSFValueError(msg, diffusion_factor)
    return factor * _galsim_diffusion_step(sensor) / float(sensor.config["PixelSizeX"])


def _galsim_diffusion_step(sensor):
    """GalSim's diffusion step of a SiliconSensor for the full thickness, microns.

    GalSim computes it from the sensor's temperature and voltages in the private
    ``SiliconSensor._calculate_diff_step`` and offers no public accessor; this is the one place
    bfpsf calls it, so a GalSim that renames it fails here with a clear message.
    """
    method = getattr(sensor, "_calculate_diff_step", None)
    if method is None:
        msg = (f"GalSim {galsim.__version__} SiliconSensor has no _calculate_diff_step: the "
               "diffusion sigma cannot be read from this GalSim version")
        raise BFPSFValueError(msg, galsim.__version__)
    return float(method())
