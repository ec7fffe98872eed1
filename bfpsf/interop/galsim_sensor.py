"""A GalSim Sensor applying bfpsf's charge redistribution (`BFSensor`), and `draw_with_bf`, which
draws a profile with photon noise and brighter-fatter without shooting photons."""

import threading

import numpy as np
import galsim

from ..errors import BFPSFInputError, BFPSFValueError
from ..model.buildup import redistribute_buildup
from ..model.empirical import empirical_of
from ..model.redistribution import redistribute
from ..model.tiles import correlate
from ..shifts import as_shifts

__all__ = ["BFSensor", "draw_with_bf"]


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
        the time-stepped build-up, `bfpsf.model.buildup.redistribute_buildup`.
    empirical : bfpsf.model.empirical.EmpiricalTerm, optional
        The EMPIRICAL term of a calibration refined by ``bfpsf diagnose --output-calib``
        (default that of ``shifts`` when it is such a calibration): the new charge of each
        stamp gets
        it at the stamp's total charge and charge-weighted column, as one star's image in
        `bfpsf.model.psf.FluxDependentPSF`; a stamp holding several objects gets the term
        of their summed charge.

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

    def __init__(self, shifts, *, gain=1.0, nsteps=1, empirical=None):
        self.shifts = as_shifts(shifts)
        #: The EMPIRICAL term of a refined calibration (`bfpsf.model.empirical`), or None:
        #: added to the new charge of each call's image as to one star's (its total and
        #: its charge-weighted column), so draw one object per stamp, as GalSim does
        if empirical is None and getattr(shifts, "refinement", None):
            empirical = empirical_of(shifts)  # a refined calibration's
        self.empirical = empirical
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
        collected = collected + self._empirical_delta(collected - self._base, self._landed,
                                                      image.bounds.xmin, image.bounds.ymin)
        image.array[:, :] = collected / self.gain
        return added_flux

    def _empirical_delta(self, collected_e, landed_e, xmin, ymin):
        """The EMPIRICAL term of one stamp's star (0 without a term): its pattern on the
        star's collected charge ``collected_e``, at the landed charge's total and
        charge-weighted column and row (GalSim's 1-based ``xmin``, ``ymin`` -> bfpsf's
        0-based pixels)."""
        total = float(landed_e.sum())
        if self.empirical is None or total <= 0:
            return 0.0
        columns = np.arange(landed_e.shape[1]) + xmin - 1.0
        rows = np.arange(landed_e.shape[0]) + ymin - 1.0
        column = float((landed_e.sum(axis=0) * columns).sum() / total)
        row = float((landed_e.sum(axis=1) * rows).sum() / total)
        return self.empirical.delta(collected_e, total, column, total=total, y=row)

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
        (area,) = correlate(charge, [self.shifts.area])
        area_image.array[:, :] = 1.0 + area
        return area_image

    def __repr__(self):
        term = "" if self.empirical is None else f", empirical={self.empirical!r}"
        return (f"bfpsf.BFSensor({self.shifts!r}, gain={self.gain!r}, "
                f"nsteps={self.nsteps!r}{term})")

    def __eq__(self, other):
        return (self is other or
                (isinstance(other, BFSensor) and self.shifts == other.shifts
                 and self.gain == other.gain and self.nsteps == other.nsteps
                 and self.empirical == other.empirical))

    def __setstate__(self, state):
        state.setdefault("empirical", None)  # pickled before the EMPIRICAL term
        self.__dict__.update(state)

    __hash__ = None

    def __getstate__(self):
        state = self.__dict__.copy()
        for key in ("_last_image", "_base", "_landed", "_base_delta"):
            state[key] = None
        return state


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
        Boundary shifts a^X, 1/e- (G15 eq. def-a); a calibration refined by ``bfpsf
        diagnose --output-calib`` adds its EMPIRICAL term to the drawn object (`BFSensor`).
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
    collected = sensor._forward(counts)  # pylint: disable=protected-access
    # a refined calibration's EMPIRICAL term, as BFSensor adds it to a stamp's star
    collected = collected + sensor._empirical_delta(collected, counts, image.bounds.xmin,
                                                    image.bounds.ymin)
    image.array[:, :] = collected / gain
    return image
