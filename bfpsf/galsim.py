"""bfpsf's GalSim config plug-in: ``modules: [bfpsf.galsim]`` registers the sensor type
``BrighterFatter``.

::

    modules: [bfpsf.galsim]
    image:
      sensor: {type: BrighterFatter, calib: CALIB.fits}

builds a `bfpsf.BFSensor` with the calibration's boundary shifts (and the EMPIRICAL term of a
calibration refined by ``bfpsf diagnose --output-calib``, added to each stamp's charge), so ``galsim scene.yaml``
draws every photon-shot object (``draw_method: phot``) with bfpsf's fast brighter-fatter
(G15 eq. scrambling_model on the photons landed in each stamp) instead of tracking each photon
through distorted pixels as ``type: Silicon`` does.

Keys
----
calib : str (required)
    A calibration file from ``bfpsf calibrate`` or ``bfpsf diagnose --output-calib``.
amp : str (optional)
    The amplifier whose shifts to use, for a calibration of several (required there).
gain : float (optional)
    e- per unit of the drawn image (default 1: GalSim config draws in photons = electrons;
    the calibration's own gain, e-/ADU of the flats, plays no part).
nsteps : int (optional)
    1 (default): G15's one-step model; K > 1: the build-up integrated in K steps.

FFT-drawn objects (``draw_method`` auto, fft, real_space, no_pixel) need no special path:
GalSim hands a sensor the drawn image as photons, one per sub-pixel with the pixel's flux
(`galsim.PhotonArray.makeFromImage`), and `BFSensor` lands them in their pixels and
redistributes, so an FFT-drawn object gets exactly the redistribution of its noiseless
drawn image -- what `bfpsf.draw_with_bf` applies, without its Poisson step (add noise with
the config's ``noise`` field). Each object is redistributed on its own stamp, as GalSim's
SiliconSensor is in a config: the BF cross terms of overlapping stamps are not included.
"""

import functools
import os

import galsim

from .calibration.detector import amplifiers_of, calibration_of_amplifier, read_calibration
from .errors import BFPSFInputError
from .interop.galsim_sensor import BFSensor
from .model.empirical import empirical_of

__all__ = ["BrighterFatterSensorBuilder", "build_sensor"]


@functools.lru_cache(maxsize=8)
def _read(path, modified):  # keyed by the file's modification time: a rewritten file is reread
    return read_calibration(path)


def build_sensor(calib, *, amp=None, gain=1.0, nsteps=1):
    """The `BFSensor` of a calibration file (one amplifier of it).

    Raises
    ------
    BFPSFInputError
        The file is missing or no calibration, has no shifts, or has several amplifiers and
        ``amp`` names none of them.
    """
    path = os.fspath(calib)
    if not os.path.exists(path):
        msg = f"sensor type BrighterFatter: calib {path} does not exist"
        raise BFPSFInputError(msg, path)
    calibration = _read(path, os.path.getmtime(path))
    amplifiers = amplifiers_of(calibration)
    if amp is None and len(amplifiers) > 1:
        msg = (f"sensor type BrighterFatter: {path} holds {len(amplifiers)} amplifiers "
               f"({', '.join(amplifiers)}); choose one with amp: NAME")
        raise BFPSFInputError(msg, path)
    one = calibration_of_amplifier(calibration, amp, where=path) if amp is not None else \
        next(iter(amplifiers.values()))
    if one.shifts is None:
        msg = f"sensor type BrighterFatter: {path} has no boundary shifts (not solved)"
        raise BFPSFInputError(msg, path)

    # a refined calibration's EMPIRICAL term, as every consumer of a calibration applies it
    return BFSensor(one.shifts, gain=gain, nsteps=nsteps, empirical=empirical_of(one))


class BrighterFatterSensorBuilder(galsim.config.SensorBuilder):
    """Builds `bfpsf.BFSensor` for ``sensor: {type: BrighterFatter, calib: FILE, ...}``."""

    _req = {"calib": str}
    _opt = {"amp": str, "gain": float, "nsteps": int}

    def buildSensor(self, config, base, logger):  # noqa: N802 (GalSim's API)
        kwargs, _ = galsim.config.GetAllParams(config, base, req=self._req, opt=self._opt)
        sensor = build_sensor(kwargs.pop("calib"), **kwargs)
        if logger:
            logger.debug("obj %d: BrighterFatter sensor %r", base.get("obj_num", 0), sensor)
        return sensor


galsim.config.RegisterSensorType("BrighterFatter", BrighterFatterSensorBuilder())
