"""GalSim interoperability: SiliconSensor truth, a GalSim Sensor applying bfpsf's
redistribution, conversion to and from `galsim.cdmodel`, and the G15 section 6.2 experiments.

GalSim's `galsim.SiliconSensor` simulates brighter-fatter from Poisson_CCD pixel-boundary
solutions, physics independent of G15, so bfpsf validates against it (DESIGN.md).

Coefficient conventions
-----------------------
`galsim.cdmodel` (src/CDModel.cpp, ``ApplyCD``) adds to each pixel
``sum_{ix,iy} Q(x+ix, y+iy) a_t(ix, iy) (Q_00 + Q_top) / 2`` (and likewise for b, l, r),
i.e. the boundary shift times the *mean* of the two pixels. G15 (eq. scrambling_model) writes
``1/4 a^X Q (Q_00 + Q_X)``, so a^X(G15) = 2 a_X(cdmodel): GalSim's coefficients are *half*
bfpsf's (the cdmodel docstring's Antilogus et al. 2014 convention, with the sum, would be a
quarter). The mapping is a_t = a^N / 2, a_b = a^S / 2, a_r = a^E / 2, a_l = a^W / 2, all
indexed [dy + n, dx + n] as in bfpsf, with the same sign (positive: the pixel grows).
"""

import threading

import numpy as np
import galsim

from ..errors import BFPSFInputError, BFPSFValueError
from ..model.redistribution import (
    _as_shifts,
    _correlate,
    exact_boundary_density,
    redistribute,
    redistribute_buildup,
)
from ..shifts import BoundaryShifts

__all__ = [
    "silicon_area_coefficients",
    "silicon_boundary_shifts",
    "silicon_diffusion_sigma",
    "shifts_to_cdmodel",
    "shifts_from_cdmodel",
    "BFSensor",
    "draw_with_bf",
    "moffat_charge",
    "density_approximation_error",
    "buildup_error",
]


def silicon_area_coefficients(sensor="lsst_itl_50_8", *, charge=1000.0, maxlag=4, **sensor_kwargs):
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
    **sensor_kwargs
        Passed to `galsim.SiliconSensor` when ``sensor`` is a name.

    Returns
    -------
    ndarray, shape (maxlag + 1, maxlag + 1)
        a(dx, dy) indexed [dy, dx] for dx, dy = 0..maxlag, quadrant-averaged over the four
        signs of (dx, dy) as the flats measure it.

    Notes
    -----
    These are the areas of GalSim's pixel polygons. Where photons land
    (`SiliconSensor.accumulate`) differs from them for the nearest neighbours, by about
    20 % for a(1, 0) and a(1, 1) of lsst_itl_50_8, because neighbouring polygons do not share
    their boundaries exactly and a photon is given to its nominal pixel first; sums over
    square blocks centred on the charge agree (see `silicon_boundary_shifts`).
    """
    if charge <= 0:
        msg = f"charge must be positive, got {charge}"
        raise BFPSFValueError(msg, charge)
    if isinstance(sensor, str):
        sensor = galsim.SiliconSensor(name=sensor, **sensor_kwargs)
    size = 2 * (int(maxlag) + 6) + 1
    centre = size // 2
    image = galsim.ImageD(size, size, init_value=0.0)
    empty_area = sensor.calculate_pixel_areas(image).array.copy()
    image.array[centre, centre] = charge
    charged_area = sensor.calculate_pixel_areas(image).array
    response = (charged_area - empty_area) / charge
    window = response[centre - maxlag:centre + maxlag + 1, centre - maxlag:centre + maxlag + 1]
    folded = (window + window[::-1, :] + window[:, ::-1] + window[::-1, ::-1]) / 4.0
    return folded[maxlag:, maxlag:].copy()


# -- boundary shifts of a SiliconSensor ----------------------------------------------------------
def _measurement_sensor(sensor, sensor_kwargs):
    """A SiliconSensor like ``sensor`` with diffusion off, no tree rings, no recalculation."""
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
    params.update(diffusion_factor=0.0, nrecalc=0)
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


def _measure_displacements(sensor, charge, strips, widths, ncol, nrow, size, centre, rng):
    """Boundary displacement (px, outward for the lower/left pixel) of each strip's boundary.

    Strips must not share pixels. Photons land on an image holding ``charge`` in the centre
    pixel (with nrecalc=0 they do not move the boundaries); the landed counts minus the counts
    of square pixels give the area swept by each boundary.
    """
    x, y = _strip_photons(strips, widths, ncol, nrow, rng)
    photons = galsim.PhotonArray(len(x), x=x, y=y, flux=np.ones(len(x)))
    image = galsim.ImageD(size, size, xmin=0, ymin=0)
    image.array[centre, centre] = charge
    sensor.accumulate(photons, image)
    landed = image.array.copy()
    landed[centre, centre] -= charge
    nominal = np.zeros_like(landed)
    np.add.at(nominal, (np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)), 1.0)
    gained = landed - nominal
    per_strip = ncol * nrow
    displacements = []
    for (px, py, label), width in zip(strips, widths):
        qx, qy = (px, py + 1) if label == "N" else (px + 1, py)
        # Photon density is per_strip / (2 w) per unit area: d = (gain_p - gain_q) / 2 * 2w / n.
        displacements.append((gained[py, px] - gained[qy, qx]) * width / per_strip)
    return np.array(displacements)


def silicon_boundary_shifts(sensor="lsst_itl_50_8", *, charge=1000.0, radius=4,
                            photons_per_boundary=40000, symmetrize=True, seed=0,
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
        Electrons in the source pixel. GalSim's boundaries move linearly with the charge, so
        the result depends on it only through second-order corner effects. Default 1000.
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
    sensor = _measurement_sensor(sensor, sensor_kwargs)
    if charge <= 0:
        msg = f"charge must be positive, got {charge}"
        raise BFPSFValueError(msg, charge)
    m = int(radius)
    if m < 1 or m != radius:
        msg = f"radius must be a positive integer, got {radius}"
        raise BFPSFValueError(msg, radius)
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
        return BoundaryShifts(north, east, check=False)
    mirrored_north = np.zeros_like(north)
    mirrored_north[1:, :] = north[::-1, ::-1][:-1, :]
    mirrored_east = np.zeros_like(east)
    mirrored_east[:, 1:] = east[::-1, ::-1][:, :-1]
    return BoundaryShifts(0.5 * (north - mirrored_north), 0.5 * (east - mirrored_east))


# -- galsim.cdmodel ------------------------------------------------------------------------------
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
    # pylint: disable-next=protected-access
    step = sensor._calculate_diff_step()  # microns: GalSim's own formula (temperature, voltages)
    return factor * step / float(sensor.config["PixelSizeX"])


def shifts_to_cdmodel(shifts):
    """The `galsim.cdmodel.BaseCDModel` applying the same redistribution as ``shifts``.

    a_t = a^N / 2, a_b = a^S / 2, a_r = a^E / 2, a_l = a^W / 2 (module docstring). GalSim
    treats the image border differently (it drops a term when the pixel mirrored through the
    boundary is outside the image), so the two agree where the charge is at least radius + 1
    pixels from the border.
    """
    shifts = _as_shifts(shifts)
    return galsim.cdmodel.BaseCDModel(shifts.west / 2.0, shifts.east / 2.0,
                                      shifts.south / 2.0, shifts.north / 2.0)


def shifts_from_cdmodel(cdmodel, *, rtol=1e-9):
    """`BoundaryShifts` from a `galsim.cdmodel.BaseCDModel` (e.g. `galsim.cdmodel.PowerLawCD`).

    a^N = 2 a_t and a^E = 2 a_r; a_b and a_l must follow by translation invariance
    (a_b(dx, dy) = -a_t(dx, dy + 1), a_l(dx, dy) = -a_r(dx + 1, dy)), which is what makes the
    model conserve charge.

    Raises
    ------
    BFPSFValueError
        If a_b or a_l violate translation invariance, or a_t / a_r violate parity, by more
        than ``rtol`` times the largest coefficient.
    """
    arrays = {name: np.asarray(getattr(cdmodel, name).array, dtype=float)
              for name in ("a_l", "a_r", "a_b", "a_t")}
    north, east = 2.0 * arrays["a_t"], 2.0 * arrays["a_r"]
    scale = max(np.abs(north).max(), np.abs(east).max(), 1e-300)
    shifts = BoundaryShifts(north, east, check=False)
    for name, derived in (("a_b", shifts.south), ("a_l", shifts.west)):
        worst = float(np.abs(2.0 * arrays[name] - derived).max())
        if worst > rtol * scale:
            msg = (f"cdmodel {name} is not the translation of the opposite boundary's "
                   f"coefficients (worst difference {worst / 2:.3g}); it does not conserve charge")
            raise BFPSFValueError(msg, worst)
    return BoundaryShifts(north, east, rtol=rtol)


# -- a GalSim Sensor -----------------------------------------------------------------------------
# Photons binned per call of the numpy operations in `_bin_photons`: large enough that the
# per-call overhead does not matter, small enough for the chunk to stay in cache (fastest of
# 32k..512k on the development machine).
_PHOTON_CHUNK = 131072
# Each thread keeps its chunk buffers (2 MB) between calls: fresh ones cost page faults worth
# a tenth of the binning.
_PHOTON_BUFFERS = threading.local()


def _bin_photons(photons, bounds):
    """Flux landing in each pixel of ``bounds``, as `galsim.PhotonArray.addTo` bins it.

    GalSim (``PhotonArray::addTo``) lands a photon at (x, y) in pixel
    (floor(x + 0.5), floor(y + 0.5)) (pixel centres on integer image coordinates;
    ``orig_center`` plays no part) and drops the photons whose pixel is outside the bounds.
    Here the same pixels are computed with numpy, chunk by chunk in cache (x + 0.5 in floating
    point as GalSim does, the image origin subtracted from the integer index), and the fluxes
    summed with a weighted `numpy.bincount` on a grid with one extra pixel on every side that
    collects the photons falling outside. Within a chunk each pixel sums its photons in the
    order ``addTo`` does; the chunks' sums are then added. Faster than ``addTo``
    (benchmarks/bench_redistribution.py).

    Returns
    -------
    landed : ndarray [y, x], float64
        Flux landed in each pixel.
    added_flux : float
        Total flux of the photons that landed in the image (``addTo``'s return value).
    """
    width = bounds.xmax - bounds.xmin + 3
    height = bounds.ymax - bounds.ymin + 3
    bins = width * height
    # int32 also makes the cast send every coordinate beyond +-2^31 outside (see indices).
    index_type = np.int32 if bins < 2**31 else np.int64
    x, y, flux = photons.x, photons.y, photons.flux
    count = len(photons)
    chunk = min(_PHOTON_CHUNK, max(count, 1))
    buffers = getattr(_PHOTON_BUFFERS, "arrays", None)
    if buffers is None or len(buffers[0]) < chunk or buffers[1].dtype != index_type:
        buffers = _PHOTON_BUFFERS.arrays = (np.empty(chunk), np.empty(chunk, dtype=index_type),
                                            np.empty(chunk, dtype=index_type))
    position, column, row = buffers
    landed = np.zeros(bins)

    def indices(coordinate, start, stop, origin, size, out):
        # floor(c + 0.5) - (origin - 1), then 0 and size - 1 (the outside pixels) for pixels
        # beyond the image. x + 0.5 is GalSim's float sum; the cast truncates, which is the
        # floor for the values >= 1 that land inside (for origin >= 1 every value below 1
        # lands outside whichever way it is rounded; for origin <= 0 floor first). Values
        # beyond the integer range and non-finite ones cast to the integer minimum (or
        # saturate) and are clipped outside, as GalSim's int(floor(...)) drops them.
        value = position[:stop - start]
        np.add(coordinate[start:stop], 0.5, out=value)
        if origin <= 0:
            np.floor(value, out=out, casting="unsafe")
        else:
            np.copyto(out, value, casting="unsafe")
        if origin != 1:
            out -= origin - 1
        np.clip(out, out.dtype.type(0), out.dtype.type(size - 1), out=out)
        return out

    with np.errstate(invalid="ignore"):
        for start in range(0, count, chunk):
            stop = min(start + chunk, count)
            columns = indices(x, start, stop, bounds.xmin, width, column[:stop - start])
            pixel = indices(y, start, stop, bounds.ymin, height, row[:stop - start])
            pixel *= width
            pixel += columns
            landed += np.bincount(pixel, weights=flux[start:stop], minlength=bins)
    landed = landed.reshape(height, width)[1:-1, 1:-1]
    return landed, float(landed.sum())


class BFSensor(galsim.Sensor):
    """A GalSim Sensor that lands photons in their pixels and then redistributes the charge.

    ``obj.drawImage(method='phot', sensor=BFSensor(shifts))`` simulates brighter-fatter with
    G15's model (eq. scrambling_model) instead of tracking every photon through distorted
    pixels, which is what `galsim.SiliconSensor` does: much faster for bright objects.

    Parameters
    ----------
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (e.g. `silicon_boundary_shifts` of a SiliconSensor).
    gain : float, optional
        e-/ADU of the images it accumulates into (drawImage's ``gain``); the redistribution
        acts on electrons. Default 1.
    nsteps : int, optional
        1 (default): the one-step model, `bfpsf.model.redistribution.redistribute`. K > 1:
        the time-stepped build-up, `bfpsf.model.redistribution.redistribute_buildup`.

    Notes
    -----
    Charge already in the image when ``accumulate`` starts (``resume=False``) is treated as
    collected before the new photons: the new charge is moved by the boundaries of old plus
    new charge, and the old charge is not moved again,
    ``Q = Q_old + N + dQ(Q_old + N) - dQ(Q_old)``. Successive calls with ``resume=True``
    (drawImage with ``maxN``) continue the same exposure: the photons of all calls are
    redistributed together, so the result does not depend on how the photons were split.
    Charge is conserved; photons falling outside the image are lost, and no charge crosses
    the image border. The photons are binned with numpy into exactly the pixels
    `galsim.PhotonArray.addTo` would use, faster than ``addTo`` itself. Each call
    redistributes the whole image it is given (about 0.6 s per 4k x 4k on one core, less on
    several, see `bfpsf.model.redistribution.redistribute`'s ``workers``): draw objects on
    postage stamps, as GalSim does, rather than one by one onto a full-CCD image.
    """

    def __init__(self, shifts, *, gain=1.0, nsteps=1):
        self.shifts = _as_shifts(shifts)
        self.gain = float(gain)
        if not self.gain > 0:
            msg = f"gain must be positive, got {gain}"
            raise BFPSFValueError(msg, gain)
        self.nsteps = int(nsteps)
        if self.nsteps < 1 or self.nsteps != nsteps:
            msg = f"nsteps must be a positive integer, got {nsteps}"
            raise BFPSFValueError(msg, nsteps)
        self._last_image = None
        self._base = None
        self._base_delta = None
        self._landed = None

    def _forward(self, charge):
        if self.nsteps == 1:
            return redistribute(charge, self.shifts)
        return redistribute_buildup(charge, self.shifts, nsteps=self.nsteps)

    def accumulate(self, photons, image, orig_center=galsim.PositionI(0, 0), resume=False):
        """Land the photons in their nominal pixels (as `galsim.PhotonArray.addTo` does),
        then redistribute the charge.

        Parameters
        ----------
        photons : galsim.PhotonArray
            Photons at the top of the sensor, image coordinates.
        image : galsim.Image
            Image (ADU, with this sensor's gain) to accumulate into; modified in place.
        orig_center : galsim.PositionI, optional
            Unused (the model has no position dependence); accepted for the Sensor API.
        resume : bool, optional
            Continue the exposure of the previous call on the same image.

        Returns
        -------
        float
            The total flux that fell onto the image.
        """
        if resume and image is not self._last_image:
            if self._last_image is None:
                raise galsim.GalSimError("accumulate called with resume, but accumulate has "
                                         "not been run yet.")
            raise galsim.GalSimError("accumulate called with resume, but provided image does "
                                     "not match one used in the previous accumulate call.")
        if not image.bounds.isDefined():
            raise galsim.GalSimUndefinedBoundsError(
                "Calling accumulate on image with undefined bounds")
        if not resume:
            self._base = np.asarray(image.array, dtype=float) * self.gain
            if not np.all(np.isfinite(self._base)):
                msg = (f"image has {np.count_nonzero(~np.isfinite(self._base))} non-finite "
                       "pixels before accumulate")
                raise BFPSFInputError(msg)
            self._base_delta = (self._forward(self._base) - self._base
                                if np.any(self._base) else None)
            self._landed = np.zeros_like(self._base)
        self._last_image = image
        landed, added_flux = _bin_photons(photons, image.bounds)
        landed *= self.gain
        self._landed += landed
        charge = self._base + self._landed
        collected = self._forward(charge)
        if self._base_delta is not None:
            collected -= self._base_delta
        image.array[:, :] = collected / self.gain
        return added_flux

    def calculate_pixel_areas(self, image, orig_center=galsim.PositionI(0, 0), use_flux=True):
        """Pixel areas at the end of the exposure, 1 + sum_(dx,dy) a(dx, dy) Q(x+dx, y+dy).

        Returns
        -------
        galsim.Image
            Areas in units of the nominal pixel area (G15 eq. covar's a = sum_X a^X).
        """
        area_image = image.copy()
        area_image.wcs = galsim.PixelScale(1.0)
        if not use_flux:
            area_image.fill(1.0)
            return area_image
        charge = np.asarray(image.array, dtype=float) * self.gain
        (area,) = _correlate(charge, [self.shifts.area])
        area_image.array[:, :] = 1.0 + area
        return area_image

    def __repr__(self):
        return (f"bfpsf.interop.galsim.BFSensor({self.shifts!r}, gain={self.gain!r}, "
                f"nsteps={self.nsteps!r})")

    def __eq__(self, other):
        return (self is other or
                (isinstance(other, BFSensor) and self.shifts == other.shifts
                 and self.gain == other.gain and self.nsteps == other.nsteps))

    __hash__ = None

    def __getstate__(self):
        state = self.__dict__.copy()
        for key in ("_last_image", "_base", "_landed", "_base_delta"):
            state[key] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)


def draw_with_bf(profile, shifts, *, image=None, nx=None, ny=None, scale=1.0, offset=None,
                 rng=None, gain=1.0, nsteps=1, method="auto"):
    """Draw a profile with photon noise and brighter-fatter, without shooting photons.

    Statistically the same as ``profile.drawImage(method='phot', sensor=BFSensor(shifts))``
    and about a hundred times faster for bright stars (benchmarks/bench_redistribution.py).
    Photon shooting lands N ~ Poisson(F) photons of one electron each (GalSim's default
    ``poisson_flux``), which makes the counts of the pixels independent Poisson variables with
    the pixel-integrated profile as mean; BFSensor then redistributes those counts. Here the
    means are drawn (``method``, default GalSim's 'auto': the profile convolved with the
    pixel), the Poisson counts made from them, and the same redistribution applied.

    Parameters
    ----------
    profile : galsim.GSObject
        What to draw, flux in electrons (profiles with negative regions are not photon-like:
        their negative means are set to zero before the Poisson step).
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e- (G15 eq. def-a).
    image : galsim.Image, optional
        Image to draw into (its contents are replaced); otherwise ``nx`` x ``ny`` at ``scale``.
    nx, ny : int, optional
    scale : float, optional
        Pixel scale in the profile's unit (default 1).
    offset : tuple or galsim.PositionD, optional
        Passed to drawImage.
    rng : galsim.BaseDeviate or int, optional
        Random deviate or seed of the Poisson counts (default: a new deviate).
    gain : float, optional
        e- per image unit of the output (default 1).
    nsteps : int, optional
        1 (default): the one-step model; K > 1: the build-up in K steps (as BFSensor).
    method : str, optional
        drawImage method for the means (default 'auto').

    Returns
    -------
    galsim.Image
        The drawn image, electrons / ``gain``.
    """
    if not (np.isfinite(gain) and gain > 0):
        msg = f"gain must be a positive number of e- per image unit, got {gain!r}"
        raise BFPSFValueError(msg, gain)
    sensor = BFSensor(shifts, gain=1.0, nsteps=nsteps)  # validates the shifts and nsteps
    if method == "phot":
        msg = "method='phot' shoots photons: use drawImage(method='phot', sensor=BFSensor(...))"
        raise BFPSFValueError(msg, method)
    image = profile.drawImage(image=image, nx=nx, ny=ny, scale=scale, offset=offset,
                              method=method, dtype=float if image is None else None)
    counts = np.clip(image.array, 0.0, None)  # the means, then the counts in place
    galsim.PoissonDeviate(galsim.BaseDeviate(rng)).generate_from_expectation(counts)
    image.array[:, :] = sensor._forward(counts) / gain  # pylint: disable=protected-access
    return image


# -- G15 section 6.2 experiments ----------------------------------------------------------------
def moffat_charge(fwhm, peak, *, beta=2.5, size=None, oversampling=8, offset=(0.0, 0.0)):
    """A Moffat spot drawn with GalSim on an oversampled grid, in electrons.

    Parameters
    ----------
    fwhm : float
        Image quality (FWHM of the Moffat before pixel integration), pixels.
    peak : float
        Charge of the brightest pixel, e-.
    beta : float, optional
        Moffat index. Default 2.5.
    size : int, optional
        Stamp side in pixels (odd). Default ``8 * fwhm + 17`` rounded to odd.
    oversampling : int, optional
        Sub-pixels per pixel side. Default 8.
    offset : (float, float), optional
        Sub-pixel offset of the centre from the central pixel, pixels.

    Returns
    -------
    image_e : ndarray (size, size)
        Pixel charges, e-.
    oversampled_e : ndarray (size * n, size * n)
        Sub-pixel charges, e- (for `exact_boundary_density`).
    """
    n = int(oversampling)
    if size is None:
        size = int(8 * fwhm + 17) | 1
    profile = galsim.Moffat(beta=beta, fwhm=float(fwhm))
    sub = profile.drawImage(nx=size * n, ny=size * n, scale=1.0 / n, method="auto",
                            offset=(offset[0] * n, offset[1] * n)).array.astype(float)
    # The profile is centred on the true centre of the sub-pixel grid, which (size odd) is the
    # centre of the central pixel.
    image = sub.reshape(size, n, size, n).sum(axis=(1, 3))
    factor = peak / image.max()
    return image * factor, sub * factor


def _sigma(image):
    """Adaptive-moment size (Mxx Myy - Mxy^2)^(1/4), px: G15's IQ (section 3.2), measured
    with galsim.hsm.FindAdaptiveMom (elliptical Gaussian weight matched to the object)."""
    moments = galsim.hsm.FindAdaptiveMom(galsim.ImageD(np.ascontiguousarray(image)),
                                         strict=True)
    return float(moments.moments_sigma)


def _moffat_for_iq(iq, peak, *, beta, oversampling):
    """Moffat spot whose pixelised adaptive-moment size is ``iq`` px (to 1e-4 relative)."""
    fwhm = 2.1 * iq  # close for beta = 2.5; refined by fixed-point steps below
    for _ in range(8):
        image, sub = moffat_charge(fwhm, peak, beta=beta, oversampling=oversampling)
        sigma = _sigma(image)
        if abs(sigma / iq - 1.0) < 1e-4:
            break
        fwhm *= iq / sigma
    return fwhm, sigma, image, sub


def density_approximation_error(shifts, iq=(1.0, 1.2, 1.4, 1.6, 2.0, 2.5, 3.0, 3.5), *,
                                peak=1e5, oversampling=8, beta=2.5):
    """BF size change with G15's boundary density and with the exact one (G15 fig. bva).

    For each image quality, a Moffat spot with ``peak`` electrons in its brightest pixel is
    redistributed with rho = (Q_p + Q_q)/2 (eq. density-approx) and with the density
    integrated along each boundary of the oversampled model (`exact_boundary_density`).

    Parameters
    ----------
    shifts : BoundaryShifts or Calibration
        Boundary shifts a^X, 1/e-.
    iq : sequence of float
        Image qualities, px, as G15 defines them (section 3.2): the adaptive-moment size
        (Mxx Myy - Mxy^2)^(1/4) of the pixelised spot without BF. The Moffat FWHM is adjusted
        to match.
    peak : float
        Charge of the brightest pixel, e-. Default 1e5 (G15 fig. bva).
    oversampling : int
        Sub-pixels per pixel side of the model used for the exact density. Default 8.
    beta : float
        Moffat index. Default 2.5.

    Returns
    -------
    astropy.table.Table
        Columns ``iq`` (px), ``fwhm`` (Moffat FWHM, px), ``dsigma_mean`` and ``dsigma_exact``
        (relative size increase IQ/IQ0 - 1 with each density), ``error`` (dsigma_mean -
        dsigma_exact, relative size; negative: the approximation underestimates the size) and
        ``error_fraction`` (error / dsigma_exact: the fraction of the BF effect misestimated).
    """
    from astropy.table import Table

    rows = []
    for target in iq:
        fwhm, sigma0, image, sub = _moffat_for_iq(target, peak, beta=beta,
                                                  oversampling=oversampling)
        _, density = exact_boundary_density(sub, oversampling)
        mean = _sigma(redistribute(image, shifts)) / sigma0 - 1.0
        exact = _sigma(redistribute(image, shifts, density=density)) / sigma0 - 1.0
        rows.append((target, fwhm, mean, exact, mean - exact, (mean - exact) / exact))
    return Table(rows=rows, names=("iq", "fwhm", "dsigma_mean", "dsigma_exact", "error",
                                   "error_fraction"))


def buildup_error(shifts, peaks=(2e4, 5e4, 1e5, 1.5e5), *, fwhm=4.0, nsteps=32, beta=2.5):
    """One-step BF model against the time-stepped build-up, for Moffat spots.

    Sizes are adaptive moments (G15 IQ); ``nsteps`` steps of
    `bfpsf.model.redistribution.redistribute_buildup` (K = 32: integration error ~2e-3
    of the difference).

    Returns
    -------
    astropy.table.Table
        Columns ``peak`` (e-, brightest pixel), ``dsigma_one_step`` and ``dsigma_buildup``
        (relative size increase with each model), ``size_difference`` (their difference,
        relative size), ``size_difference_fraction`` (over dsigma_buildup) and
        ``max_pixel_difference`` (max |Q_one_step - Q_buildup| / max |dQ_buildup|).
    """
    from astropy.table import Table

    rows = []
    unit, _ = moffat_charge(fwhm, 1.0, beta=beta)
    sigma0 = _sigma(unit)
    for peak in peaks:
        image = unit * peak
        one = redistribute(image, shifts)
        steps = redistribute_buildup(image, shifts, nsteps=nsteps)
        d_one = _sigma(one) / sigma0 - 1.0
        d_steps = _sigma(steps) / sigma0 - 1.0
        pixel = np.abs(one - steps).max() / np.abs(steps - image).max()
        rows.append((peak, d_one, d_steps, d_one - d_steps, (d_one - d_steps) / d_steps, pixel))
    return Table(rows=rows, names=("peak", "dsigma_one_step", "dsigma_buildup",
                                   "size_difference", "size_difference_fraction",
                                   "max_pixel_difference"))
