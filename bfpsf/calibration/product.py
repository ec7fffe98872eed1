"""The calibration product: everything the flats tell about a sensor, in one versioned FITS file.

`Calibration` holds the gain, read noise, area coefficients a(dx, dy) with errors, the A+19 b
coefficients, the boundary shifts a^X(dx, dy) with per-element errors, the per-pair PTC table,
the linearity fit and the readout pedestal, together with the inputs, the parameters and the
bfpsf version that made them. ``write`` / ``read`` round-trip every number exactly (binary
tables and float64 images, never header keywords, hold the values).

File layout (schema version `SCHEMA_VERSION`)::

    PRIMARY      header only: BFSCHEMA, BFVERSIO, MODEL, NAMP, readable GAIN / NOISE / MAXLAG

then, per amplifier, one HDU group (every HDU has EXTVER = 1, 2, ... and AMPNAME; the SUMMARY
header holds the amplifier's MODEL and SHIFTMTH, the solver of its shifts):

    SUMMARY      one-row table of the scalars (gain, errors, turnoff, linearity, ...)
    A, A_ERR     a(dx, dy) and error, [dy, dx], 1/electron
    B, B_ERR     A+19 b(dx, dy), [dy, dx], 1/electron
    NOISE        zero-flux covariances n(dx, dy), [dy, dx], electron^2
    PEDESTAL, PEDESTAL_ERR   zero-flux correlations R0(dx, dy), [dy, dx], dimensionless
    SHIFT_N, SHIFT_E, SHIFT_S, SHIFT_W        a^X(dx, dy), [dy + m, dx + m], 1/electron
    SHIFT_N_ERR, SHIFT_E_ERR                  their errors (when solved)
    SHIFT_N_SAMP, SHIFT_E_SAMP                samples of a^N, a^E drawn from the calibration
                                              error, [sample, dy + m, dx + m] (schema >= 2)
    WARNINGS     one string per warning of this amplifier (schema >= 2)
    COV, NPIX    per-pair covariances [pair, dy, dx] (adu^2, before pedestal subtraction), counts
    SHIFTFIT     key / value table of the shift solvers' scalars (chi2 of each, parameters)
    PTC          per-pair table (`bfpsf.calibration.ptc.ptc_table` columns and more)
    LINEARITY    exptime, mean_adu, frac_residual, used
    INPUTS       input file names;  PARAMS  key / JSON value of the calibrate() parameters
    REFINE       (optional) one JSON string: the closed loop's refinement and its provenance
                 (`bfpsf.diagnosis.refine`)
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

from .. import __version__
from ..errors import BFPSFInputError
from ..files import open_product, refuse_overwrite
from ..outputs import write_fits
from ..shifts import BoundaryShifts
from .linearity import Linearity
from .pedestal import Pedestal

__all__ = ["Calibration", "SCHEMA_VERSION"]

#: Version of the FITS layout written by `Calibration.write`; `Calibration.read` refuses newer.
#: 2: the shift solver (header SHIFTMTH), samples of the shifts and the warnings (single
#:    amplifier; issue 10) -- or per-amplifier HDU groups (EXTVER, AMPNAME; issue 12).
#: 3: both: per-amplifier HDU groups, each with its solver (SUMMARY header SHIFTMTH), shift
#:    samples (SHIFT_N_SAMP, SHIFT_E_SAMP) and WARNINGS. Schema 1 and 2 files read.
SCHEMA_VERSION = 3

_SUMMARY_FLOATS = ("gain", "gain_err", "noise_e", "noise_e_err", "turnoff_e", "chi2")
_SUMMARY_INTS = ("maxlag", "n_pairs", "ndof")


def _frozen(array):
    if array is None:
        return None
    array = np.array(array, dtype=float)
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Calibration:
    """Flat-field calibration of one sensor (amplifier).

    Attributes
    ----------
    gain, gain_err : float
        e-/ADU.
    noise_e, noise_e_err : float
        Read noise, e- rms.
    a, a_err : ndarray [dy, dx]
        Area coefficients a(dx, dy), 1/e- (a(0, 0) < 0), dx, dy = 0..maxlag.
    b, b_err : ndarray [dy, dx]
        A+19 b(dx, dy), 1/e- (zero unless the full model with b was fitted).
    noise_matrix_e2 : ndarray [dy, dx]
        Zero-flux covariances n(dx, dy), e-^2.
    shifts : BoundaryShifts or None
        Boundary shifts a^X(dx, dy), 1/e- (None if they were not solved).
    shifts_north_err, shifts_east_err : ndarray or None
        Errors of ``shifts.north`` and ``shifts.east``, 1/e-.
    shift_samples_north, shift_samples_east : ndarray (S, 2m + 1, 2m + 1) or None
        Shifts drawn from the calibration's uncertainty (1/e-): every prediction made from
        the shifts propagates them (`shift_samples`).
    shift_method : str or None
        The solver of the shifts (`bfpsf.calibration.boundary_shifts.SHIFT_METHODS`).
    warnings : tuple of str
        What the calibration could not determine well, in words (``--json`` ``warnings``).
    covariances_adu, npix : ndarray (n_pairs, L, L) or None
        Measured single-image covariances of every pair (ADU^2, before pedestal subtraction)
        and the pixel products behind them, [pair, dy, dx] in PTC-table order.
    shift_fit : dict
        Scalars of the shift solvers, when solved: the chi2 and dof of each solver on the
        measured a (``electrostatic_chi2``, ``ei_chi2``, ...), the electrostatic geometry, and
        the G15 smoothing model f(r) = p0 Ei(p1 r) (``ei_p1``, ``ei_sensitivity_...``).
    ptc : astropy.table.Table
        Per-pair table (see `bfpsf.calibration.ptc.ptc_table`).
    linearity : Linearity
    pedestal : Pedestal
    model : str
        PTC model (``'full'``, ``'exponential'`` or ``'quadratic'``).
    turnoff_e : float
        Mean of the brightest pair used in the fit, e-.
    turnoff_detected : bool
    chi2, ndof : float, int
        Goodness of the PTC fit.
    inputs : tuple of str
        Input flats.
    parameters : dict
        Parameters of `bfpsf.calibrate` (JSON-serialisable).
    refinement : dict
        Empty, or what the closed loop folded into this calibration and how, with the data it
        came from (`bfpsf.diagnosis.refine.refine_calibration`; JSON-serialisable).
    bfpsf_version : str
    schema_version : int
    amplifier : str
        Amplifier name (EXTNAME of the flats), ``''`` for a single-image sensor.
    """

    gain: float
    gain_err: float
    noise_e: float
    noise_e_err: float
    a: np.ndarray
    a_err: np.ndarray
    b: np.ndarray
    b_err: np.ndarray
    noise_matrix_e2: np.ndarray
    ptc: object
    linearity: Linearity
    pedestal: Pedestal
    model: str = "full"
    turnoff_e: float = float("nan")
    turnoff_detected: bool = False
    chi2: float = float("nan")
    ndof: int = 0
    shifts: BoundaryShifts = None
    shifts_north_err: np.ndarray = None
    shifts_east_err: np.ndarray = None
    shift_fit: dict = field(default_factory=dict)
    shift_samples_north: np.ndarray = None
    shift_samples_east: np.ndarray = None
    shift_method: str = None
    warnings: tuple = ()
    covariances_adu: np.ndarray = None
    npix: np.ndarray = None
    inputs: tuple = ()
    parameters: dict = field(default_factory=dict)
    refinement: dict = field(default_factory=dict)
    bfpsf_version: str = __version__
    schema_version: int = SCHEMA_VERSION
    amplifier: str = ""

    def __post_init__(self):
        for name in ("a", "a_err", "b", "b_err", "noise_matrix_e2", "shifts_north_err",
                     "shifts_east_err", "shift_samples_north", "shift_samples_east",
                     "covariances_adu", "npix"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        object.__setattr__(self, "inputs", tuple(str(name) for name in self.inputs))
        object.__setattr__(self, "warnings", tuple(str(text) for text in self.warnings))
        object.__setattr__(self, "shift_fit", {key: float(value)
                                               for key, value in dict(self.shift_fit).items()})

    # -- convenience -------------------------------------------------------------------------
    @property
    def maxlag(self):
        """Largest lag of ``a``."""
        return self.a.shape[0] - 1

    @property
    def read_noise_determined(self):
        """Whether the PTC measured the read noise: beyond 2 errors of zero (flats far above
        it leave its intercept loose; a new user's 10.5 +- 6.8 e- against a true 4.5)."""
        noise, error = float(self.noise_e), float(self.noise_e_err)
        return bool(np.isfinite(noise) and np.isfinite(error) and noise > 2 * error)

    @property
    def n_pairs(self):
        """Number of flat pairs in the PTC table."""
        return len(self.ptc)

    def shift_samples(self, limit=None):
        """The shift samples as `BoundaryShifts` (at most ``limit``; empty without samples)."""
        if self.shift_samples_north is None:
            return []
        count = len(self.shift_samples_north) if limit is None else int(limit)
        return [BoundaryShifts(north, east, check=False) for north, east in
                zip(self.shift_samples_north[:count], self.shift_samples_east[:count])]

    def __repr__(self):
        return (f"Calibration(model={self.model!r}, gain={self.gain:.5g}+-{self.gain_err:.2g} "
                f"e-/ADU, noise={self.noise_e:.3g} e-, a00={self.a[0, 0]:.4g}/e-, "
                f"maxlag={self.maxlag}, n_pairs={self.n_pairs})")

    # -- JSON --------------------------------------------------------------------------------
    def to_json_dict(self):
        """Machine-readable summary (the ``bfpsf calibrate --json`` keys).

        Arrays are lists of lists indexed [dy][dx]; NaN becomes None. Units: gain e-/ADU,
        noise e-, a and a_err 1/e-, turnoff_e e-, pedestal dimensionless.
        """
        def clean(value):
            if isinstance(value, np.ndarray):
                return clean(value.tolist())
            if isinstance(value, dict):
                return {key: clean(item) for key, item in value.items()}
            if isinstance(value, (list, tuple)):
                return [clean(item) for item in value]
            if isinstance(value, (float, np.floating)):
                return None if not np.isfinite(value) else float(value)
            if isinstance(value, np.integer):
                return int(value)
            if isinstance(value, np.bool_):
                return bool(value)
            return value

        summary = {
            "gain": self.gain, "gain_err": self.gain_err,
            "noise_e": self.noise_e, "noise_e_err": self.noise_e_err,
            "a": self.a, "a_err": self.a_err,
            "maxlag": self.maxlag, "n_pairs": self.n_pairs,
            "turnoff_e": self.turnoff_e, "turnoff_detected": self.turnoff_detected,
            "linearity_max_frac_residual": self.linearity.max_frac_residual,
            "linearity_peak_to_peak": self.linearity.peak_to_peak,
            "linearity_flagged": self.linearity.flagged,
            "pedestal": self.pedestal.value, "pedestal_err": self.pedestal.error,
            "pedestal_detected": self.pedestal.detected,
            "model": self.model, "b": self.b, "b_err": self.b_err,
            "chi2": self.chi2, "ndof": self.ndof,
            "n_pairs_used": int(np.count_nonzero(self.ptc["used"])),
            "units": {"gain": "electron/adu", "noise_e": "electron", "a": "1/electron",
                      "turnoff_e": "electron", "pedestal": "dimensionless"},
            "shifts_solved": self.shifts is not None,
            "shift_method": self.shift_method,
            "warnings": list(self.warnings),
            "parameters": dict(self.parameters), "refinement": dict(self.refinement),
            "inputs": list(self.inputs), "bfpsf_version": self.bfpsf_version,
            "schema_version": self.schema_version,
        }
        if self.shifts is not None:
            summary["shifts_north"] = self.shifts.north
            summary["shifts_east"] = self.shifts.east
            summary["shifts_north_err"] = self.shifts_north_err
            summary["shifts_east_err"] = self.shifts_east_err
            summary.update({f"shift_{key}": value for key, value in self.shift_fit.items()})
        return {key: clean(value) for key, value in summary.items()}

    # -- FITS --------------------------------------------------------------------------------
    def write(self, path, *, overwrite=False):
        """Write the versioned multi-extension FITS file.

        Parameters
        ----------
        path : str or path
        overwrite : bool, optional
            Replace an existing file. Default False: raise `BFPSFFileExistsError`.
        """
        path = Path(path)
        refuse_overwrite(path, overwrite)
        primary = fits.PrimaryHDU()
        header = primary.header
        header["BFSCHEMA"] = (SCHEMA_VERSION, "bfpsf calibration schema version")
        header["BFVERSIO"] = (self.bfpsf_version, "bfpsf version that wrote the file")
        header["MODEL"] = (self.model, "PTC model")
        header["GAIN"] = (round(self.gain, 6), "[e-/ADU] (exact value in SUMMARY)")
        header["NOISE"] = (round(self.noise_e, 4), "[e-] read noise (exact in SUMMARY)")
        header["MAXLAG"] = (self.maxlag, "largest lag of A")
        header["NAMP"] = (1, "amplifiers (HDU groups) in the file")
        header["SHIFTMTH"] = (str(self.shift_method or ""), "solver of the boundary shifts")
        write_fits(fits.HDUList([primary, *self.group_hdus()]), path, overwrite=overwrite)

    def group_hdus(self, extver=1):
        """The HDUs of this calibration, one group of a (per-amplifier) calibration file.

        Every HDU carries EXTVER = ``extver`` (the group) and AMPNAME = `amplifier`.
        """
        hdus = []

        summary = Table()
        for name in _SUMMARY_FLOATS:
            summary[name] = [float(getattr(self, name))]
        for name in _SUMMARY_INTS:
            summary[name] = [int(getattr(self, name))]
        summary["turnoff_detected"] = [bool(self.turnoff_detected)]
        summary["lin_slope"] = [self.linearity.slope]
        summary["lin_intercept"] = [self.linearity.intercept]
        summary["lin_threshold"] = [self.linearity.threshold]
        summary["lin_measured"] = [bool(self.linearity.measured)]
        summary["ped_nsigma"] = [self.pedestal.nsigma]
        summary["ped_degree"] = [int(self.pedestal.degree)]
        # units (FITS has no electron unit): gain e-/ADU, noise_e and turnoff_e e-
        hdus.append(_table_hdu(summary, "SUMMARY"))

        images = [("A", self.a, "1/electron"), ("A_ERR", self.a_err, "1/electron"),
                  ("B", self.b, "1/electron"), ("B_ERR", self.b_err, "1/electron"),
                  ("NOISE", self.noise_matrix_e2, "electron2"),
                  ("PEDESTAL", self.pedestal.value, ""), ("PEDESTAL_ERR", self.pedestal.error, "")]
        if self.shifts is not None:
            images += [("SHIFT_N", self.shifts.north, "1/electron"),
                       ("SHIFT_E", self.shifts.east, "1/electron"),
                       ("SHIFT_S", self.shifts.south, "1/electron"),
                       ("SHIFT_W", self.shifts.west, "1/electron")]
            if self.shifts_north_err is not None:
                images.append(("SHIFT_N_ERR", self.shifts_north_err, "1/electron"))
            if self.shifts_east_err is not None:
                images.append(("SHIFT_E_ERR", self.shifts_east_err, "1/electron"))
            if self.shift_samples_north is not None:
                images += [("SHIFT_N_SAMP", self.shift_samples_north, "1/electron"),
                           ("SHIFT_E_SAMP", self.shift_samples_east, "1/electron")]
        if self.covariances_adu is not None:
            images.append(("COV", self.covariances_adu, "adu2"))
        if self.npix is not None:
            images.append(("NPIX", self.npix, ""))
        for name, array, unit in images:
            hdu = fits.ImageHDU(np.asarray(array, dtype=np.float64), name=name)
            hdu.header["BUNIT"] = unit  # a comment string: FITS knows no electron unit
            hdu.header["INDEXING"] = ("[sample, dy+m, dx+m]" if name.endswith("SAMP") else
                                      "[dy+m, dx+m]" if name.startswith("SHIFT") else
                                      "[pair, dy, dx]" if name in ("COV", "NPIX") else "[dy, dx]")
            hdus.append(hdu)

        shift_fit = Table({"key": list(self.shift_fit) or [""],
                           "value": list(self.shift_fit.values()) or [np.nan]})
        if not self.shift_fit:
            shift_fit = shift_fit[:0]
        hdus.append(_table_hdu(shift_fit, "SHIFTFIT"))
        hdus.append(_table_hdu(Table({"text": np.array(self.warnings, dtype=str)})
                               if self.warnings else Table({"text": np.array([], dtype="U1")}),
                               "WARNINGS"))
        hdus.append(_table_hdu(Table(self.ptc, copy=True), "PTC"))
        linearity = Table()
        linearity["exptime"] = np.asarray(self.linearity.exptime, dtype=float)
        linearity["exptime"].unit = "s"
        linearity["mean_adu"] = np.asarray(self.linearity.mean_adu, dtype=float)
        linearity["mean_adu"].unit = "adu"
        linearity["frac_residual"] = np.asarray(self.linearity.frac_residual, dtype=float)
        linearity["used"] = np.asarray(self.linearity.used, dtype=bool)
        hdus.append(_table_hdu(linearity, "LINEARITY"))
        hdus.append(_table_hdu(Table({"name": np.array(self.inputs, dtype=str)})
                               if self.inputs else Table({"name": np.array([], dtype="U1")}),
                               "INPUTS"))
        params = Table({"key": np.array(list(self.parameters), dtype=str),
                        "value": np.array([json.dumps(v) for v in self.parameters.values()],
                                          dtype=str)})
        if not self.parameters:
            params = Table({"key": np.array([], dtype="U1"), "value": np.array([], dtype="U1")})
        hdus.append(_table_hdu(params, "PARAMS"))
        if self.refinement:
            hdus.append(_table_hdu(Table({"json": [json.dumps(self.refinement)]}), "REFINE"))
        for hdu in hdus:
            hdu.ver = int(extver)
            hdu.header["AMPNAME"] = (self.amplifier, "amplifier of this HDU group")
        hdus[0].header["MODEL"] = (self.model, "PTC model")
        hdus[0].header["SHIFTMTH"] = (str(self.shift_method or ""),
                                      "solver of the boundary shifts")
        return hdus

    @classmethod
    def read(cls, path, *, amp=None):
        """Read a file written by `write` (or one amplifier of a `DetectorCalibration` file).

        Parameters
        ----------
        path : str or path
        amp : str, optional
            Amplifier to read from a file of several (required there).

        Raises
        ------
        BFPSFInputError
            The file is missing, is not a bfpsf calibration, was written with a newer schema
            than this bfpsf understands, or holds several amplifiers and ``amp`` names none.
        """
        with open_product(path, keyword="BFSCHEMA", version=SCHEMA_VERSION,
                          kind="calibration") as hdul:
            groups = group_names(hdul)
            if amp is None and len(groups) > 1:
                msg = (f"{path} holds {len(groups)} amplifiers ({', '.join(groups)}); choose "
                       "one with amp=NAME, or read them all with DetectorCalibration.read")
                raise BFPSFInputError(msg, str(path))
            if amp is not None and amp not in groups:
                msg = f"{path} has no amplifier {amp!r}; it has {', '.join(map(repr, groups))}"
                raise BFPSFInputError(msg, amp)
            return cls.from_group(hdul, groups[amp] if amp is not None else 1)

    @classmethod
    def from_group(cls, hdul, extver=1):
        """The calibration held by HDU group ``extver`` of an open calibration file."""
        header = hdul[0].header
        names = {hdu.name for hdu in hdul if hdu.ver == extver}

        def image(name):
            return np.array(hdul[name, extver].data, dtype=np.float64) if name in names else None

        def table(name):
            if name not in names:  # `bfpsf.files.reading` turns this into a one-line error
                raise KeyError(f"Extension {name!r} not found.")
            # mask_invalid=False: NaN (e.g. a turnoff not reached) reads back as NaN, not masked
            return Table.read(hdul[name, extver], mask_invalid=False)

        summary = table("SUMMARY")[0]
        ptc = table("PTC")
        lin = table("LINEARITY")
        inputs = tuple(str(name) for name in table("INPUTS")["name"])
        parameters = {str(row["key"]): json.loads(str(row["value"])) for row in table("PARAMS")}
        shift_table = table("SHIFTFIT")
        shift_fit = {str(row["key"]): float(row["value"]) for row in shift_table}
        shifts = None
        if "SHIFT_N" in names:
            shifts = BoundaryShifts(image("SHIFT_N"), image("SHIFT_E"), check=False)
        group = hdul["SUMMARY", extver].header
        # schema 1 files had only the Ei solver and no SHIFTMTH
        default_method = "ei" if shifts is not None else ""
        pedestal = Pedestal(value=_frozen(image("PEDESTAL")),
                            error=_frozen(image("PEDESTAL_ERR")),
                            nsigma=float(summary["ped_nsigma"]),
                            degree=int(summary["ped_degree"]))
        linearity = Linearity(
            exptime=np.array(lin["exptime"], dtype=float),
            mean_adu=np.array(lin["mean_adu"], dtype=float),
            slope=float(summary["lin_slope"]), intercept=float(summary["lin_intercept"]),
            frac_residual=np.array(lin["frac_residual"], dtype=float),
            used=np.array(lin["used"], dtype=bool),
            threshold=float(summary["lin_threshold"]), measured=bool(summary["lin_measured"]))
        return cls(
            gain=float(summary["gain"]), gain_err=float(summary["gain_err"]),
            noise_e=float(summary["noise_e"]), noise_e_err=float(summary["noise_e_err"]),
            a=image("A"), a_err=image("A_ERR"), b=image("B"), b_err=image("B_ERR"),
            noise_matrix_e2=image("NOISE"), ptc=ptc, linearity=linearity, pedestal=pedestal,
            model=str(group.get("MODEL", header["MODEL"])),
            turnoff_e=float(summary["turnoff_e"]),
            turnoff_detected=bool(summary["turnoff_detected"]),
            chi2=float(summary["chi2"]), ndof=int(summary["ndof"]), shifts=shifts,
            shifts_north_err=image("SHIFT_N_ERR"), shifts_east_err=image("SHIFT_E_ERR"),
            shift_fit=shift_fit, shift_samples_north=image("SHIFT_N_SAMP"),
            shift_samples_east=image("SHIFT_E_SAMP"),
            shift_method=str(group.get("SHIFTMTH", header.get("SHIFTMTH", default_method)))
            or None,
            warnings=(tuple(str(text) for text in table("WARNINGS")["text"])
                      if "WARNINGS" in names else ()),
            covariances_adu=image("COV"), npix=image("NPIX"),
            inputs=inputs, parameters=parameters,
            refinement=(json.loads(str(table("REFINE")["json"][0])) if "REFINE" in names else {}),
            bfpsf_version=str(header["BFVERSIO"]),
            schema_version=int(header["BFSCHEMA"]),
            amplifier=str(group.get("AMPNAME", "")))


def group_names(hdul):
    """``{amplifier name: EXTVER}`` of the HDU groups of a calibration file (schema 1: one);
    each group has a SUMMARY HDU, so a file without one is incomplete (a KeyError, that
    `bfpsf.files.reading` turns into one line naming the file and the HDU)."""
    groups = {str(hdu.header.get("AMPNAME", "")): hdu.ver for hdu in hdul
              if hdu.name == "SUMMARY"}
    if not groups:
        raise KeyError("Extension 'SUMMARY' not found.")
    return groups


def _table_hdu(table, name):
    """A binary-table HDU; text columns as UTF-8 bytes (FITS text is ASCII only; astropy
    reads the bytes back as the same text), so non-ASCII file names survive."""
    table = table.copy(copy_data=False)
    for column in table.colnames:
        if table[column].dtype.kind == "U":
            table[column] = np.char.encode(np.asarray(table[column]), "utf-8")
    hdu = fits.table_to_hdu(table)
    hdu.name = name
    return hdu
