"""The LSST cp_pipe PTC dataset: read it as the input of the calibration, write bfpsf's.

LSST's calibration pipeline (cp_pipe) writes its photon transfer curve as the FITS table of
``lsst.ip.isr.PhotonTransferCurveDataset`` (`toTable` / `fromTable`, schema ``PTC_VERSION``
1.4): one row per amplifier, columns ``AMPLIFIER_NAME``, ``PTC_FIT_TYPE``,
``COV_MATRIX_SIDE``, ``INPUT_EXP_ID_PAIRS``, ``EXP_ID_MASK``, ``RAW_EXP_TIMES``,
``RAW_MEANS``, ``RAW_VARS``, ``GAIN``, ``GAIN_ERR``, ``NOISE``, ``NOISE_ERR``, ``A_MATRIX``,
``B_MATRIX``, ``NOISE_MATRIX``, ``COVARIANCES``, ``COVARIANCES_SQRT_WEIGHTS``, ... (all in
`PTC_COLUMNS`), and the metadata OBSTYPE = 'PTC'.

Units and layout (Astier et al. 2019, the cp_pipe FULLCOVARIANCE fit): means in ADU,
covariances in ADU^2, gain in e-/ADU, noise in e-, a and b in 1/e-, the noise matrix in e-^2.
The matrices are flattened from ``[i, j]`` with i the lag in x (serial) and j the lag in y,
the transpose of bfpsf's ``[dy, dx]``; `read_ptc_dataset` and `write_ptc_dataset` transpose.
``COVARIANCES_SQRT_WEIGHTS`` is 1 / sigma of each covariance; bfpsf writes
1 / `bfpsf.calibration.ptc.covariance_errors` and reads the pixel counts back from it.
"""

from dataclasses import dataclass

import numpy as np
from astropy.io import fits
from astropy.table import Table

from ..errors import BFPSFInputError
from ..files import check_input, reading
from ..outputs import write_fits
from .detector import amplifiers_of
from .ptc import PTCData, covariance_errors

__all__ = ["PTC_COLUMNS", "PTC_VERSION", "PTCAmplifier", "read_ptc_dataset",
           "write_ptc_dataset", "ptc_dataset_table", "ptc_table_hdu"]

#: PhotonTransferCurveDataset schema version written (lsst.ip.isr ptcDataset.py).
PTC_VERSION = 1.4

#: Columns of the cp_pipe table, in the order ``toTable`` writes them.
PTC_COLUMNS = ("AMPLIFIER_NAME", "PTC_FIT_TYPE", "COV_MATRIX_SIDE", "INPUT_EXP_ID_PAIRS",
               "EXP_ID_MASK", "RAW_EXP_TIMES", "RAW_MEANS", "RAW_VARS", "GAIN", "GAIN_ERR",
               "NOISE", "NOISE_ERR", "HIST_VARS", "HIST_CHI2_DOFS", "KS_PVALUES",
               "PTC_FIT_PARS", "PTC_FIT_PARS_ERROR", "PTC_FIT_CHI_SQ", "PTC_TURNOFF",
               "A_MATRIX", "B_MATRIX", "A_MATRIX_NO_B", "NOISE_MATRIX", "NOISE_MATRIX_NO_B",
               "BAD_AMPS", "PHOTO_CHARGE", "COVARIANCES", "COVARIANCES_MODEL",
               "COVARIANCES_SQRT_WEIGHTS", "COVARIANCES_MODEL_NO_B", "FINAL_VARS",
               "FINAL_MODEL_VARS", "FINAL_MEANS")

_NEEDED = ("AMPLIFIER_NAME", "COV_MATRIX_SIDE", "EXP_ID_MASK", "RAW_EXP_TIMES", "RAW_MEANS",
           "GAIN", "GAIN_ERR", "NOISE", "NOISE_ERR", "A_MATRIX", "B_MATRIX", "NOISE_MATRIX",
           "COVARIANCES", "COVARIANCES_SQRT_WEIGHTS")


@dataclass(frozen=True, eq=False)
class PTCAmplifier:
    """One amplifier of a cp_pipe PTC dataset, in bfpsf's conventions.

    Attributes
    ----------
    name : str
    fit_type : str
        cp_pipe's PTC_FIT_TYPE (e.g. ``'FULLCOVARIANCE'``).
    gain, gain_err : float
        e-/ADU.
    noise_e, noise_e_err : float
        Read noise, e-.
    a, b : ndarray [dy, dx]
        cp_pipe's a and b matrices, 1/e-.
    noise_matrix_e2 : ndarray [dy, dx]
        e-^2.
    data : bfpsf.calibration.ptc.PTCData
        The pairs cp_pipe kept (EXP_ID_MASK): exposure times, means (ADU), covariances
        [pair, dy, dx] (ADU^2) and the pixel counts implied by their weights.
    pair_ids : list of (int, int)
        Exposure ids of those pairs.
    """

    name: str
    fit_type: str
    gain: float
    gain_err: float
    noise_e: float
    noise_e_err: float
    a: np.ndarray
    b: np.ndarray
    noise_matrix_e2: np.ndarray
    data: object
    pair_ids: list


def _square(values, side, where):
    values = np.asarray(values, dtype=float).ravel()
    if values.size != side * side:
        msg = f"{where}: {values.size} values, expected {side} x {side}"
        raise BFPSFInputError(msg, values.size)
    return values.reshape(side, side).T  # cp_pipe [i = dx, j = dy] -> bfpsf [dy, dx]


def _pixel_counts(cov_adu, sqrt_weights):
    """Invert `covariance_errors`: N = (V w)^2 off the origin, 2 (V w)^2 at it."""
    variance = cov_adu[:, :1, :1]
    with np.errstate(invalid="ignore"):
        npix = (variance * sqrt_weights) ** 2
    npix[:, 0, 0] *= 2.0
    return np.nan_to_num(npix)


def _amplifier(row, path):
    name = str(row["AMPLIFIER_NAME"]).strip()
    where = f"{path}: amplifier {name}"
    side = int(row["COV_MATRIX_SIDE"])
    mask = np.asarray(row["EXP_ID_MASK"], dtype=bool).ravel()
    exptime = np.asarray(row["RAW_EXP_TIMES"], dtype=float).ravel()
    mean = np.asarray(row["RAW_MEANS"], dtype=float).ravel()
    count = mean.size
    covariances = np.asarray(row["COVARIANCES"], dtype=float).ravel()
    weights = np.asarray(row["COVARIANCES_SQRT_WEIGHTS"], dtype=float).ravel()
    if covariances.size != count * side * side or weights.size != covariances.size:
        msg = (f"{where}: COVARIANCES hold {covariances.size} values, expected "
               f"{count} pairs x {side} x {side}")
        raise BFPSFInputError(msg, covariances.size)
    if mask.size != count or exptime.size != count:
        msg = f"{where}: EXP_ID_MASK / RAW_EXP_TIMES / RAW_MEANS lengths differ"
        raise BFPSFInputError(msg, (mask.size, exptime.size, count))
    cov = covariances.reshape(count, side, side).transpose(0, 2, 1)[mask]
    sqrt_weights = weights.reshape(count, side, side).transpose(0, 2, 1)[mask]
    data = PTCData(exptime[mask], mean[mask], cov, _pixel_counts(cov, sqrt_weights))
    pair_ids = [tuple(int(value) for value in pair)
                for pair, used in zip(np.asarray(row["INPUT_EXP_ID_PAIRS"]).reshape(-1, 2), mask)
                if used] if "INPUT_EXP_ID_PAIRS" in row.colnames else []
    return PTCAmplifier(
        name=name, fit_type=str(row["PTC_FIT_TYPE"]).strip() if "PTC_FIT_TYPE" in row.colnames
        else "", gain=float(row["GAIN"]), gain_err=float(row["GAIN_ERR"]),
        noise_e=float(row["NOISE"]), noise_e_err=float(row["NOISE_ERR"]),
        a=_square(row["A_MATRIX"], side, f"{where} A_MATRIX"),
        b=_square(row["B_MATRIX"], side, f"{where} B_MATRIX"),
        noise_matrix_e2=_square(row["NOISE_MATRIX"], side, f"{where} NOISE_MATRIX"),
        data=data, pair_ids=pair_ids)


def read_ptc_dataset(path):
    """Read a cp_pipe PhotonTransferCurveDataset FITS file.

    Returns
    -------
    dict of str to PTCAmplifier
        In file order.

    Raises
    ------
    BFPSFInputError
        The file is missing, is not a PTC dataset (OBSTYPE), or lacks a needed column.
    """
    path = check_input(path, "PTC dataset")
    try:
        with reading(path, "cp_pipe PTC dataset (FITS)"):
            table = Table.read(path, hdu=1, format="fits")
    except IndexError as error:
        msg = f"{path}: cannot read a PTC table from HDU 1 ({error})"
        raise BFPSFInputError(msg, str(path)) from error
    obstype = str(table.meta.get("OBSTYPE", "")).strip()
    if obstype != "PTC":
        msg = f"{path}: OBSTYPE is {obstype!r}, not 'PTC': not a cp_pipe PTC dataset"
        raise BFPSFInputError(msg, obstype)
    missing = [name for name in _NEEDED if name not in table.colnames]
    if missing:
        msg = f"{path}: PTC table lacks column(s) {', '.join(missing)}"
        raise BFPSFInputError(msg, missing)
    with reading(path, "cp_pipe PTC dataset"):
        return {amplifier.name: amplifier
                for amplifier in (_amplifier(row, path) for row in table)}


def _flat(matrix):
    return np.asarray(matrix, dtype=float).T.ravel()  # bfpsf [dy, dx] -> cp_pipe [dx, dy]


def _row(name, calibration):
    cov = np.asarray(calibration.covariances_adu, dtype=float)
    npix = np.asarray(calibration.npix, dtype=float)
    with np.errstate(divide="ignore"):
        sqrt_weights = 1.0 / covariance_errors(cov, npix)
    side = calibration.a.shape[0]
    ptc = calibration.ptc
    used = np.asarray(ptc["used"], dtype=bool)
    mean = np.asarray(ptc["mean_adu"], dtype=float)
    count = len(ptc)
    nan_pairs = np.full(count, np.nan)
    nan_matrix = np.full(side * side, np.nan)
    cp_cov = cov.transpose(0, 2, 1).ravel()
    return {
        "AMPLIFIER_NAME": name or "AMP", "PTC_FIT_TYPE": "FULLCOVARIANCE",
        "COV_MATRIX_SIDE": side,
        "INPUT_EXP_ID_PAIRS": np.column_stack([np.arange(0, 2 * count, 2),
                                               np.arange(1, 2 * count, 2)]).astype(np.int64),
        "EXP_ID_MASK": used, "RAW_EXP_TIMES": np.asarray(ptc["exptime"], dtype=float),
        "RAW_MEANS": mean, "RAW_VARS": cov[:, 0, 0], "GAIN": calibration.gain,
        "GAIN_ERR": calibration.gain_err, "NOISE": calibration.noise_e,
        "NOISE_ERR": calibration.noise_e_err, "HIST_VARS": nan_pairs,
        "HIST_CHI2_DOFS": nan_pairs, "KS_PVALUES": np.zeros(count),
        "PTC_FIT_PARS": np.full(3, np.nan), "PTC_FIT_PARS_ERROR": np.full(3, np.nan),
        "PTC_FIT_CHI_SQ": (calibration.chi2 / calibration.ndof if calibration.ndof else np.nan),
        "PTC_TURNOFF": calibration.turnoff_e / calibration.gain,
        "A_MATRIX": _flat(calibration.a), "B_MATRIX": _flat(calibration.b),
        "A_MATRIX_NO_B": nan_matrix, "NOISE_MATRIX": _flat(calibration.noise_matrix_e2),
        "NOISE_MATRIX_NO_B": nan_matrix, "BAD_AMPS": np.array([], dtype="U8"),
        "PHOTO_CHARGE": nan_pairs, "COVARIANCES": cp_cov,
        "COVARIANCES_MODEL": np.full(cp_cov.size, np.nan),
        "COVARIANCES_SQRT_WEIGHTS": sqrt_weights.transpose(0, 2, 1).ravel(),
        "COVARIANCES_MODEL_NO_B": np.full(cp_cov.size, np.nan),
        "FINAL_VARS": np.where(used, cov[:, 0, 0], np.nan), "FINAL_MODEL_VARS": nan_pairs,
        "FINAL_MEANS": np.where(used, mean, np.nan),
    }


def ptc_dataset_table(calibration):
    """bfpsf's calibration as a cp_pipe PTC table (astropy Table, one row per amplifier).

    Parameters
    ----------
    calibration : Calibration or DetectorCalibration
        Must hold the per-pair covariances (``covariances_adu``, ``npix``), as `calibrate`
        stores them.
    """
    amplifiers = amplifiers_of(calibration)
    for name, one in amplifiers.items():
        if one.covariances_adu is None or one.npix is None:
            msg = (f"amplifier {name or '(single)'}: the calibration holds no per-pair "
                   "covariances; cp_pipe's table needs them")
            raise BFPSFInputError(msg, name)
    rows = [_row(name, one) for name, one in amplifiers.items()]
    table = Table(rows=[[row[column] for column in PTC_COLUMNS] for row in rows],
                  names=PTC_COLUMNS)
    table.meta.update({"OBSTYPE": "PTC", "PTC_VERSION": PTC_VERSION,
                       "PTC_FIT_TYPE": "FULLCOVARIANCE", "CALIB_CREATION_SOFTWARE": "bfpsf"})
    return table


def ptc_table_hdu(table):
    """A PTC table as the binary-table HDU cp_pipe writes: its metadata in the header, long
    keywords (PTC_VERSION, ...) as HIERARCH cards."""
    bare = Table(table, copy=False)
    bare.meta = {}
    hdu = fits.table_to_hdu(bare)
    for key, value in table.meta.items():
        hdu.header[f"HIERARCH {key}" if len(key) > 8 else key] = value
    return hdu


def write_ptc_dataset(path, calibration, *, overwrite=False):
    """Write `ptc_dataset_table` as cp_pipe does: the table in HDU 1, metadata in its header."""
    hdus = fits.HDUList([fits.PrimaryHDU(), ptc_table_hdu(ptc_dataset_table(calibration))])
    write_fits(hdus, path, overwrite=overwrite)  # atomic
