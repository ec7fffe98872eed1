"""Data shipped with bfpsf: published laboratory measurements of brighter-fatter.

Each data set is a folder of ``bfpsf/data/measured`` with the tables and a ``SOURCE.md`` that
says where they come from (repository, commit, units, sensor, licence); ``INDEX.md`` there
summarises them. They are installed with the package, so they are found without a checkout.

>>> from bfpsf.data import measured_path, measured_sets
>>> sorted(measured_sets())[:2]
['bot_r22_s11', 'cp_pipe_r22_s11']
>>> measured_path("itl3800c002", "corr_meas_VBB60_7_2_3500flats.txt").is_file()
True
"""

from importlib import resources
from pathlib import Path

from ..errors import BFPSFInputError

__all__ = ["MEASURED", "measured_path", "measured_sets"]

#: Short name -> (folder under bfpsf/data/measured, what it holds).
MEASURED = {
    "itl3800c002": ("lage_BF_Kernel_ITL3800C002",
                    "ITL STA3800C #002 (UC Davis, Lage): flat-pair correlations at 80 ke- and "
                    "spot sizes vs flux of the same CCD; closed loop (diagnose)"),
    "bot_r22_s11": ("lage_LSSTCam_BOT_spots_2019",
                    "LSSTCam BOT (Lage): spot moments vs flux of R22_S11 (E2V) and R02_S02 "
                    "(ITL), per-amplifier PTC fits; closed loop (diagnose) with cp_pipe_r22_s11"),
    "poisson_ccd": ("lage_Poisson_CCD_measurements",
                    "Poisson_CCD (Lage): measured 9x9 a(dx, dy) with errors of an E2V CCD250 and "
                    "an ITL STA3800C"),
    "cp_pipe_r22_s11": ("lsst_cp_pipe_LSSTCam_R22_S11_amatrix",
                        "LSST cp_pipe: 5x5 empirical a-matrix of LSSTCam R22_S11 "
                        "(E2V-CCD250-382)"),
    "sitcomtn148": ("lsstcam_sitcomtn148_run7",
                    "SITCOMTN-148: LSSTCam focal-plane medians of a00, gain and turnoff (run 7)"),
}


def measured_sets():
    """Short names of the shipped measured data sets, with what each holds.

    Returns
    -------
    dict
        Short name -> one-line description.
    """
    return {name: description for name, (_, description) in MEASURED.items()}


def measured_path(name, filename=None):
    """Path of a shipped measured data set (its folder), or of one of its files.

    Parameters
    ----------
    name : str
        Short name (`measured_sets`), or the folder name (e.g. ``'lage_BF_Kernel_ITL3800C002'``).
    filename : str, optional
        A file of the set (e.g. ``'SOURCE.md'``).

    Raises
    ------
    BFPSFInputError
        Unknown name, or no such file in the set.
    """
    folders = {folder: folder for folder, _ in MEASURED.values()}
    folder = MEASURED[name][0] if name in MEASURED else folders.get(name)
    if folder is None:
        msg = (f"unknown measured data set {name!r}; known: {', '.join(MEASURED)} "
               "(bfpsf diagnose --list-measured)")
        raise BFPSFInputError(msg, name)
    path = Path(str(resources.files(__name__).joinpath("measured", folder)))
    if filename is None:
        return path
    path = path / filename
    if not path.is_file():
        msg = f"measured data set {name!r} has no file {filename!r}"
        raise BFPSFInputError(msg, filename)
    return path
