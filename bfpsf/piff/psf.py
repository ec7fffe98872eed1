"""A brighter-fatter PSF type for Piff: ``type: BrighterFatter`` around any Piff PSF.

Loaded with Piff's own ``modules:`` key::

    modules: [bfpsf.piff]
    psf:
      type: BrighterFatter
      calib: CALIB.fits        # bfpsf calibrate, or diagnose --output-calib
      psf: {type: Simple, model: {type: PixelGrid, scale: 0.26, size: 17},
            interp: {type: BasisPolynomial, order: 1}}

The inner PSF describes P0, the PSF without brighter-fatter (BF). A star of flux F (image units,
as Piff's fluxes) is the inner model drawn at F on the star's own pixels, then redistributed
with G15's operator (eq. scrambling_model, `bfpsf.model.redistribution.redistribute`) acting on
g F P0 electrons, g the calibration's gain (of the star's amplifier, by position, when the
calibration has several and ``amplifiers`` gives their sections). So ``draw(x, y, chipnum,
flux=F)`` returns P(F) = P0 + g F R[P0] to first order, for every inner model and interp.

Fit: Piff's own iteration (reflux, outlier rejection, reserve stars, stats) runs on the full
model; in each iteration after the first, the inner PSF is fitted to the stars with the BF term
of the current model at each star's flux subtracted from its pixels, so every star, faint or
bright, constrains the same P0 and none needs ``max_pixel_cut``. The BF term subtracted is a
deterministic model term; the pixel noise is left as it is.

I/O: the gain, boundary shifts and amplifier sections are written into the Piff file; after
``import bfpsf.piff``, ``piff.read(file)`` draws the same images without the calibration file.
"""

import copy
import json

import galsim
import numpy as np
import piff

from ..calibration.detector import amplifiers_of, read_calibration
from ..errors import BFPSFInputError, BFPSFValueError
from ..io.amplifiers import parse_section
from ..model.empirical import EmpiricalTerm, empirical_of
from ..model.redistribution import redistribute
from ..shifts import BoundaryShifts

__all__ = ["BrighterFatterPSF", "AmplifierBF"]

#: Iterations of the fit whose BF term comes from the previous iteration's P0, at least. The
#: first iteration's P0 is the plain fit (BF at the stars' mean flux in it); the BF term taken
#: from it is wrong by that BF fraction of itself (~1e-2), and each further iteration multiplies
#: the error by it again, so one corrected iteration leaves ~1 % of the BF slope.
MIN_CORRECTED_ITERATIONS = 1


class AmplifierBF:
    """The BF operator of one amplifier: its gain, boundary shifts and pixel section.

    Parameters
    ----------
    name : str
        Amplifier name ('' for a one-amplifier calibration).
    gain : float
        e- per image unit (e-/ADU).
    shifts : BoundaryShifts
        Boundary shifts a^X, 1/e- (G15 eq. def-a).
    section : (int, int, int, int) or None
        x1, x2, y1, y2: the amplifier's pixels in Piff's image coordinates, 1-based inclusive
        (an IRAF DETSEC); None for the whole chip.
    empirical : bfpsf.model.empirical.EmpiricalTerm or None
        The EMPIRICAL term of a calibration refined by ``bfpsf diagnose --output-calib``:
        added to every star after the redistribution, at the star's flux (the stamp's
        charge) and column, as `bfpsf.model.psf.FluxDependentPSF` applies it.
    """

    def __init__(self, name, gain, shifts, section=None, empirical=None):
        self.empirical = empirical
        self.name = str(name)
        self.gain = float(gain)
        if not (np.isfinite(self.gain) and self.gain > 0):
            msg = f"amplifier {self.name!r}: gain must be a positive number of e-/ADU, got {gain}"
            raise BFPSFValueError(msg, gain)
        if shifts is None:
            msg = (f"amplifier {self.name!r}: the calibration has no boundary shifts (run bfpsf "
                   "calibrate with its shift solver)")
            raise BFPSFInputError(msg, self.name)
        self.shifts = shifts
        self.section = None if section is None else tuple(int(value) for value in section)

    def contains(self, x, y):
        """Whether image position (x, y) (pixel centres at integers) is on this amplifier."""
        if self.section is None:
            return True
        x1, x2, y1, y2 = self.section
        return x1 - 0.5 <= x < x2 + 0.5 and y1 - 0.5 <= y < y2 + 0.5

    def apply(self, image, x=None):
        """Redistribute a model image of one star in place (image units): g^-1
        redistribute(g image), plus the EMPIRICAL term of a refined calibration at the
        star's charge and at Piff column ``x`` (1-based; bfpsf's columns are 0-based)."""
        charge = np.asarray(image.array, dtype=float) * self.gain
        collected = redistribute(charge, self.shifts, workers=1)
        if self.empirical is not None:
            collected = collected + self.empirical.delta(
                collected, abs(charge.sum()), None if x is None else x - 1.0)
        image.array[:, :] = collected / self.gain
        return image


def _amplifiers_from(calibration, sections):
    """`AmplifierBF` list from a Calibration or DetectorCalibration (or a path to one)."""
    if isinstance(calibration, (str, bytes)) or hasattr(calibration, "__fspath__"):
        calibration = read_calibration(calibration)
    amplifiers = amplifiers_of(calibration)
    sections = dict(sections or {})
    if len(amplifiers) > 1:
        missing = [name for name in amplifiers if name not in sections]
        if missing:
            msg = (f"the calibration has {len(amplifiers)} amplifiers: give the section of each "
                   f"in 'amplifiers' ({', '.join(map(repr, missing))} missing)")
            raise BFPSFInputError(msg, missing)
    unknown = [name for name in sections if name not in amplifiers and len(amplifiers) > 1]
    if unknown:
        msg = f"'amplifiers' names {unknown}, which the calibration does not have ({list(amplifiers)})"
        raise BFPSFInputError(msg, unknown)
    result = []
    for name, calib in amplifiers.items():
        text = sections.get(name)
        section = None
        if text is not None:
            parsed = parse_section(text, keyword=f"amplifiers[{name!r}]", where="bfpsf.piff")
            section = (parsed.x.start + 1, parsed.x.stop, parsed.y.start + 1, parsed.y.stop)
        result.append(AmplifierBF(name, calib.gain, calib.shifts, section,
                                  empirical_of(calib)))
    return result


class BrighterFatterPSF(piff.PSF):
    """A Piff PSF that is an inner Piff PSF (P0) with brighter-fatter at each star's flux.

    Config type ``BrighterFatter``.

    Parameters
    ----------
    psf : piff.PSF
        The inner PSF (any type: Simple with PixelGrid or GSObject models and any interp,
        SingleChip, Convolve, Sum).
    calib : str, Calibration, DetectorCalibration or dict
        The calibration (a file from ``bfpsf calibrate`` or ``bfpsf diagnose --output-calib``,
        or the object), used for every chip; or a dict {chipnum: calibration} for several.
    amplifiers : dict, optional
        {amplifier name: section} for a calibration of several amplifiers: each section an
        IRAF ``'[x1:x2,y1:y2]'`` in the image coordinates Piff uses (1-based, inclusive; the
        DETSEC of the amplifier). A star's gain and shifts are those of the amplifier under
        its centre.
    """

    _type_name = "BrighterFatter"

    def __init__(self, psf, calib, amplifiers=None):
        self.psf = psf
        self.calib_name = ""
        self.amplifiers = {}  # chipnum (None: every chip) -> [AmplifierBF]
        if isinstance(calib, dict) and all(isinstance(value, list) for value in calib.values()):
            self.amplifiers = calib  # already built (SingleChip fits, reading)
        elif isinstance(calib, dict):
            self.amplifiers = {chip: _amplifiers_from(value, amplifiers)
                               for chip, value in calib.items()}
            self.calib_name = repr({chip: str(value) for chip, value in calib.items()})
        elif calib is not None and not (isinstance(calib, (int, np.integer)) and calib == 0):
            self.amplifiers = {None: _amplifiers_from(calib, amplifiers)}
            self.calib_name = str(calib) if isinstance(calib, str) else ""
        # 0: placeholders of piff.PSF._read, filled by _finish_read
        self.kwargs = {"psf": 0, "calib": 0}
        self.chisq = 0.0
        self.last_delta_chisq = 0.0
        self.dof = 0
        self.nremoved = 0
        self.niter = 0
        self._corrected_iterations = 0
        self.set_num(None)

    # -- configuration ------------------------------------------------------------------------
    @classmethod
    def parseKwargs(cls, config, base, logger=None):
        """Keys ``calib`` (a file, or {chipnum: file}), ``psf`` (the inner PSF config) and
        optional ``amplifiers`` ({name: '[x1:x2,y1:y2]'})."""
        for key in ("calib", "psf"):
            if key not in config:
                msg = f"psf type BrighterFatter needs the key {key!r}"
                raise BFPSFInputError(msg, key)
        known = {"type", "calib", "psf", "amplifiers"}
        unknown = sorted(set(config) - known - {"_get", "current"})
        if unknown:
            msg = f"psf type BrighterFatter has no key(s) {unknown}; it takes {sorted(known)}"
            raise BFPSFInputError(msg, unknown)
        calib = config["calib"]
        if not isinstance(calib, dict):
            calib = galsim.config.ParseValue(config, "calib", base, str)[0]
        amplifiers = config.get("amplifiers")
        if amplifiers is not None and not isinstance(amplifiers, dict):
            msg = f"amplifiers must be a mapping name: '[x1:x2,y1:y2]', got {amplifiers!r}"
            raise BFPSFInputError(msg, amplifiers)
        inner = piff.PSF.process(config["psf"], base, logger)
        return {"psf": inner, "calib": calib, "amplifiers": amplifiers}

    def set_num(self, num):
        self._num = num
        if isinstance(self.psf, piff.PSF):
            self.psf.set_num(num)

    def set_context(self, wcs, pointing=None, bandpass=None):
        super().set_context(wcs, pointing, bandpass)
        if isinstance(self.psf, piff.PSF):
            self.psf.set_context(wcs, pointing, bandpass)

    @property
    def interp_property_names(self):
        return self.psf.interp_property_names

    @property
    def fit_center(self):
        return self.psf.fit_center

    @property
    def include_model_centroid(self):
        return self.psf.include_model_centroid

    # the iteration settings of Piff's fit loop are those of the inner PSF
    @property
    def outliers(self):
        return getattr(self.psf, "outliers", None)

    @property
    def chisq_thresh(self):
        return getattr(self.psf, "chisq_thresh", 0.1)

    @property
    def min_iter(self):
        return max(getattr(self.psf, "min_iter", 2), MIN_CORRECTED_ITERATIONS + 1)

    @property
    def max_iter(self):
        return max(getattr(self.psf, "max_iter", 30), self.min_iter)

    @property
    def degenerate_points(self):
        return getattr(self.psf, "degenerate_points", False)

    # -- the operator ------------------------------------------------------------------------
    def amplifier_at(self, chipnum, x, y):
        """The `AmplifierBF` of image position (x, y) on chip ``chipnum``."""
        amplifiers = self.amplifiers.get(chipnum, self.amplifiers.get(None))
        if amplifiers is None:
            msg = f"the BrighterFatter PSF has no calibration for chip {chipnum!r}"
            raise BFPSFValueError(msg, chipnum)
        for amplifier in amplifiers:
            if amplifier.contains(x, y):
                return amplifier
        msg = (f"position ({x:g}, {y:g}) of chip {chipnum!r} is on none of the amplifiers "
               f"{[amp.name for amp in amplifiers]}")
        raise BFPSFValueError(msg, (x, y))

    def _star_amplifier(self, star):
        return self.amplifier_at(star.data.properties.get("chipnum"), star.image_pos.x,
                                 star.image_pos.y)

    def _with_bf(self, model_star, star):
        """The inner model star with its pixels redistributed at the star's flux."""
        image = model_star.image
        self._star_amplifier(star).apply(image, star.image_pos.x)
        return model_star

    # -- fitting ------------------------------------------------------------------------------
    def fit(self, stars, wcs=None, pointing=None, logger=None, convert_funcs=None,
            draw_method=None):
        """Fit P0 with every star at its own flux (see the module docstring).

        Piff's fit loop (`piff.PSF.fit`) with this PSF's draws (BF at each star's flux) for
        reflux, Poisson weights and outlier rejection; a SingleChip inner PSF is fitted chip by
        chip, each chip with its own BrighterFatter loop.
        """
        if isinstance(self.psf, piff.SingleChipPSF):
            self._fit_by_chip(stars, wcs, pointing, logger, convert_funcs, draw_method)
            return
        self._corrected_iterations = 0
        self.niter = 0
        super().fit(stars, wcs=wcs, pointing=pointing, logger=logger,
                    convert_funcs=convert_funcs, draw_method=draw_method)

    def _fit_by_chip(self, stars, wcs, pointing, logger, convert_funcs, draw_method):
        single_chip = self.psf
        if self.wcs is None:
            self.set_context(wcs, pointing)
        single_chip.psf_by_chip = {}
        fitted = []
        for chipnum in self.wcs:
            chip = BrighterFatterPSF(copy.deepcopy(single_chip.single_psf), self.amplifiers)
            chip.set_context({chipnum: self.wcs[chipnum]}, self.pointing, self.bandpass)
            chip_stars = [star for star in stars if star["chipnum"] == chipnum]
            chip.fit(chip_stars, logger=logger, convert_funcs=convert_funcs,
                     draw_method=draw_method)
            single_chip.psf_by_chip[chipnum] = chip.psf
            fitted += chip.stars
            self.chisq += chip.chisq
            self.dof += chip.dof
            self.nremoved += chip.nremoved
            self.niter = max(self.niter, chip.niter)
        self.stars = fitted

    def initialize_params(self, stars, logger=None, default_init=None):
        return self.psf.initialize_params(stars, logger=logger, default_init=default_init)

    def single_iteration(self, stars, logger, convert_funcs, draw_method):
        """One iteration of the inner PSF on the stars with the current BF term removed.

        The first iteration has no P0 yet and fits the raw pixels; each later one subtracts
        from every fitted star the BF term of the previous iteration's model at the star's
        flux, BF(F P0) - F P0, and hands the stars back with their own pixels.
        """
        if self.niter > 0:
            fitted = [self._without_bf(star) if not (star.is_flagged or star.is_reserve)
                      else star for star in stars]
            self._corrected_iterations += 1
        else:
            fitted = stars
        new_stars, nremoved = self.psf.single_iteration(fitted, logger, convert_funcs,
                                                        draw_method)
        restored = [piff.Star(new.data.withNew(image=old.data.image), new.fit)
                    for old, new in zip(stars, new_stars)]
        return restored, nremoved

    def _without_bf(self, star):
        """The star with the BF term of the current model at its flux subtracted."""
        model = self.psf.drawStar(star).image
        bf_term = (self._star_amplifier(star).apply(model.copy(), star.image_pos.x).array
                   - model.array)
        image = star.data.image.copy()
        image.array[:, :] -= bf_term
        return piff.Star(star.data.withNew(image=image), star.fit)

    # -- drawing ------------------------------------------------------------------------------
    def interpolateStarList(self, stars, inplace=False):
        return self.psf.interpolateStarList(stars, inplace=inplace)

    def interpolateStar(self, star, inplace=False):
        return self.psf.interpolateStar(star, inplace=inplace)

    def _drawStar(self, star):
        return self._with_bf(self.psf._drawStar(star), star)  # noqa: SLF001 (Piff's API)

    def _getRawProfile(self, star):
        # P0: Piff's reflux uses it for the derivatives with respect to centre and flux only
        return self.psf._getRawProfile(star)  # noqa: SLF001

    def _getProfile(self, star):
        """P(F) of the star as a GalSim profile: its BF pixel image as an InterpolatedImage.

        The image is P(F) pixelised at the pixel phase of the star's position (x, y) on its
        chip (the redistribution acts on those pixels); it includes the pixel response, so
        it is drawn with method 'no_pixel'. Drawn centred at (x, y) on the chip's pixel grid
        it gives `draw`'s pixel values; at another phase it is an interpolation of them, not
        P(F) at that phase (use `draw` there).
        """
        drawn = self._drawStar(star)
        image = drawn.image
        local = image.wcs.local(star.image_pos)
        pixels = galsim.Image(image.array.copy(), wcs=local)
        profile = galsim.InterpolatedImage(pixels, x_interpolant="lanczos7", flux=None,
                                           normalization="flux", use_true_center=True)
        centre = image.true_center - star.image_pos
        profile = profile.shift(local.toWorld(galsim.PositionD(centre.x, centre.y)))
        return profile, "no_pixel"

    def draw(self, x, y, chipnum=None, flux=1.0, center=None, offset=None, stamp_size=48,
             image=None, logger=None, **kwargs):
        """The PSF at (x, y) for a star of ``flux`` (image units), as `piff.PSF.draw`.

        The inner PSF is drawn at ``flux`` on the stamp and the stamp is redistributed with the
        gain and shifts of the amplifier under (x, y): P(F) at the phase of the drawn centre,
        exactly. An ``image`` whose pixels are not the chip's (another WCS) gets the profile of
        `get_profile` instead (see `_getProfile`).
        """
        chipnum = self._check_chipnum(chipnum)
        if image is not None and image.wcs is not None and not _same_pixels(
                image.wcs, self.wcs[chipnum], x, y):
            return super().draw(x, y, chipnum=chipnum, flux=flux, center=center, offset=offset,
                                stamp_size=stamp_size, image=image, logger=logger, **kwargs)
        drawn = self.psf.draw(x, y, chipnum=chipnum, flux=flux, center=center, offset=offset,
                              stamp_size=stamp_size, image=image, logger=logger, **kwargs)
        return self.amplifier_at(chipnum, x, y).apply(drawn, x)

    # -- I/O ----------------------------------------------------------------------------------
    def _finish_write(self, writer, logger):
        writer.write_struct("chisq", {"chisq": self.chisq, "last_delta_chisq":
                                      self.last_delta_chisq, "dof": self.dof,
                                      "nremoved": self.nremoved, "niter": self.niter})
        rows = [(chip, amp) for chip, amps in self.amplifiers.items() for amp in amps]
        size = max(amp.shifts.north.shape[0] for _, amp in rows)
        # the EMPIRICAL term of each amplifier, as JSON ('' without one)
        terms = ["" if amp.empirical is None else json.dumps(amp.empirical.to_dict())
                 for _, amp in rows]
        table = np.zeros(len(rows), dtype=[
            ("chip", "U64"), ("has_chip", bool), ("chip_is_int", bool), ("amplifier", "U64"),
            ("gain", "f8"), ("section", "i8", (4,)), ("north", "f8", (size, size)),
            ("east", "f8", (size, size)),
            ("empirical", f"U{max(1, max(len(term) for term in terms))}")])
        for row, (chip, amp), term in zip(table, rows, terms):
            row["chip"] = "" if chip is None else str(chip)
            row["has_chip"] = chip is not None
            row["chip_is_int"] = isinstance(chip, (int, np.integer))
            row["amplifier"] = amp.name
            row["gain"] = amp.gain
            row["section"] = amp.section if amp.section is not None else (-1, -1, -1, -1)
            pad = (size - amp.shifts.north.shape[0]) // 2
            row["north"] = np.pad(amp.shifts.north, pad)
            row["east"] = np.pad(amp.shifts.east, pad)
            row["empirical"] = term
        writer.write_table("bf_calib", table, metadata={"calibfil": self.calib_name[:60]})
        self.psf._write(writer, "inner", logger)  # noqa: SLF001 (Piff's composite API)

    def _finish_read(self, reader, logger):
        chisq = reader.read_struct("chisq") or {}
        for key, value in chisq.items():
            setattr(self, key, value)
        table = reader.read_table("bf_calib")
        if table is None:
            msg = f"{reader.get_full_name('bf_calib')}: the Piff file holds no BF calibration"
            raise BFPSFInputError(msg)
        self.amplifiers = {}
        for row in table:
            chip = None
            if row["has_chip"]:
                chip = int(row["chip"]) if row["chip_is_int"] else str(row["chip"])
            section = tuple(int(value) for value in row["section"])
            shifts = BoundaryShifts(np.array(row["north"], dtype=float),
                                    np.array(row["east"], dtype=float), check=False)
            term = (str(row["empirical"]).strip() if "empirical" in table.dtype.names
                    else "")
            self.amplifiers.setdefault(chip, []).append(
                AmplifierBF(str(row["amplifier"]).strip(), float(row["gain"]), shifts,
                            None if section[0] < 0 else section,
                            EmpiricalTerm.from_dict(json.loads(term)) if term else None))
        self.psf = piff.PSF._read(reader, "inner", logger)  # noqa: SLF001
        self.set_num(None)
        if self.wcs is not None:
            self.psf.set_context(self.wcs, self.pointing, self.bandpass)


def _same_pixels(wcs, chip_wcs, x, y):
    """Whether ``wcs`` has the chip's local pixel geometry at (x, y) (to 1e-9 relative)."""
    position = galsim.PositionD(x, y)
    ours = wcs.jacobian(image_pos=position).getMatrix()
    chips = chip_wcs.jacobian(image_pos=position).getMatrix()
    return np.allclose(ours, chips, rtol=1e-9, atol=1e-12 * np.abs(chips).max())
