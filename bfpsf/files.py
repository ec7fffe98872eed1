"""The files a command reads and the ones it is about to write: the checks made first.

No output is overwritten without asking, an input is never an output (even with
``--overwrite``), and bad input gets one line naming the file (`reading`, `read_table`).
Products (`bfpsf.Calibration`, the PSF product of `bfpsf.model.product`) are FITS files whose
primary header carries a schema keyword; a file written by a newer bfpsf is refused rather than
misread (`open_product`). How outputs are written (atomically, all or nothing) is in
`bfpsf.outputs`.
"""

import logging
import os
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.io.registry import IORegistryError
from astropy.table import Table
from astropy.utils.exceptions import AstropyUserWarning

from . import __version__
from .errors import BFPSFError, BFPSFFileExistsError, BFPSFInputError

__all__ = ["refuse_overwrite", "check_outputs", "refuse_inputs", "input_files", "check_input",
           "reading", "about", "refuse_duplicates",
           "read_table", "open_product"]


def refuse_overwrite(path, overwrite, *, how="overwrite=True (--overwrite)"):
    """Raise `BFPSFFileExistsError` if ``path`` exists and ``overwrite`` is false.

    Parameters
    ----------
    path : str or path-like
    overwrite : bool
    how : str, optional
        How the caller asks for an overwrite, quoted in the message.
    """
    if Path(path).exists() and not overwrite:
        msg = f"{path} exists; pass {how} to replace it"
        raise BFPSFFileExistsError(msg, str(path))


def input_files(*groups):
    """The files among ``groups`` (paths, lists of paths or None; a directory stands for the
    ``*.fits`` files in it), for `check_outputs`' ``inputs``."""
    files = []
    for group in groups:
        if group is None:
            continue
        for path in [group] if isinstance(group, (str, os.PathLike)) else group:
            if not isinstance(path, (str, os.PathLike)):
                continue  # an array given to a library function, not a file
            path = Path(path)
            files.extend(sorted(path.glob("*.fits")) if path.is_dir() else [path])
    return files


def _identity(path):
    """(device, inode) of an existing file (links and relative paths give the same), else
    None."""
    try:
        status = os.stat(path)
    except (OSError, ValueError):
        return None
    return (status.st_dev, status.st_ino)


def refuse_inputs(outputs, inputs):
    """Raise `BFPSFInputError` if an output is one of the inputs.

    Outputs and inputs are compared as files (device and inode), so a symbolic or hard link
    to an input, or the input under another relative path, counts as the input. This holds
    with ``overwrite`` too: an overwrite replaces an earlier output, never an input.

    Parameters
    ----------
    outputs, inputs : iterable of str, path-like or None
    """
    known = {}
    for path in inputs:
        if path is None:
            continue
        identity = _identity(path)
        if identity is not None:
            known.setdefault(identity, path)
    for path in outputs:
        if path is None:
            continue
        identity = _identity(path)
        if identity in known:
            same = "" if str(known[identity]) == str(path) else f" ({known[identity]})"
            msg = (f"output {path} is an input{same}: give the output another path "
                   "(--overwrite replaces earlier outputs, never an input)")
            raise BFPSFInputError(msg, str(path))


def check_outputs(paths, overwrite, *, how="--overwrite", directories=(), inputs=(),
                  folders=()):
    """Check every output before any work: distinct, not an input, in a writable directory,
    free.

    Parameters
    ----------
    paths : iterable of str, path-like or None
        Output files (None: an output not requested).
    overwrite : bool
        Whether existing files may be replaced.
    how : str, optional
        How the caller asks for an overwrite, quoted in the message.
    directories : iterable of str, path-like or None, optional
        Output directories the command creates (e.g. a report folder): they must not be
        files, and their nearest existing parent must be writable. Files inside them are
        checked as if the directory existed.
    inputs : iterable of str, path-like or None, optional
        The command's input files: no output may be one of them, even with ``overwrite``
        (`refuse_inputs`).
    folders : iterable of (str or path-like or None, tuple of str), optional
        Output folders whose files are named only as they are written (plots, reports), each
        with the glob patterns of those files (e.g. ``("*.png", "*/*.png")``): checked as
        ``directories``, and one that already holds such a file is refused unless
        ``overwrite`` (so a long run does not stop at its end on an earlier run's figure).

    Raises
    ------
    BFPSFInputError
        Two outputs with the same path, an output that is an input, a missing or unwritable
        directory, or an output that is a directory.
    BFPSFFileExistsError
        An output exists and ``overwrite`` is false.
    """
    paths = [path for path in paths if path is not None]
    refuse_inputs(paths, inputs)
    folders = [(Path(folder), patterns) for folder, patterns in folders if folder is not None]
    for folder, patterns in folders:
        earlier = sorted(path for pattern in patterns for path in folder.glob(pattern)
                         if path.is_file()) if folder.is_dir() else []
        if earlier and not overwrite:
            msg = (f"{folder} already holds {earlier[0].relative_to(folder)} (an earlier run's); "
                   f"pass {how} to replace it or give another folder")
            raise BFPSFFileExistsError(msg, str(earlier[0]))
    created = []
    for directory in [*directories, *(folder for folder, _ in folders)]:
        if directory is None:
            continue
        directory = Path(directory)
        if directory.exists() and not directory.is_dir():
            msg = f"output directory {directory} is a file"
            raise BFPSFInputError(msg, str(directory))
        parent = directory
        while not parent.exists():
            parent = parent.parent
        if not os.access(parent, os.W_OK | os.X_OK):
            msg = f"cannot create output directory {directory}: {parent} is not writable"
            raise BFPSFInputError(msg, str(directory))
        created.append(directory.resolve())
    seen = {}
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        resolved = path.resolve()
        if resolved in seen:
            msg = f"{seen[resolved]} and {path} are the same file: give each output its own path"
            raise BFPSFInputError(msg, str(path))
        seen[resolved] = path
        if path.is_dir():
            msg = f"output {path} is a directory"
            raise BFPSFInputError(msg, str(path))
        if path.exists() and not path.is_file():  # a device, a pipe, a socket
            msg = (f"output {path} is not a regular file (a device or a pipe); --overwrite "
                   "would replace it: give a file path")
            raise BFPSFInputError(msg, str(path))
        parent = resolved.parent
        if any(parent == directory or directory in parent.parents for directory in created):
            continue
        if not parent.is_dir():
            msg = f"cannot write {path}: directory {path.parent} does not exist"
            raise BFPSFInputError(msg, str(path))
        if not os.access(parent, os.W_OK | os.X_OK):
            msg = f"cannot write {path}: directory {path.parent} is not writable"
            raise BFPSFInputError(msg, str(path))
        refuse_overwrite(path, overwrite, how=how)


def check_input(path, what):
    """Raise a one-line `BFPSFInputError` if the input ``path`` is missing or a directory.

    ``what`` names the input in the message (e.g. ``'image'``, ``'star table'``).
    """
    path = Path(path)
    if path.is_dir():
        msg = f"{what} {path} is a directory, not a file"
        raise BFPSFInputError(msg, str(path))
    if not path.exists():
        msg = f"{what} {path} does not exist"
        raise BFPSFInputError(msg, str(path))
    if not os.access(path, os.R_OK):
        msg = f"{what} {path} is not readable (permission denied)"
        raise BFPSFInputError(msg, str(path))
    return path


@contextmanager
def reading(path, what):
    """Turn the low-level errors of reading ``path`` into one-line `BFPSFInputError` s.

    A file that is truncated, damaged or of another format makes astropy and numpy raise
    OSError, ValueError, TypeError, UnicodeDecodeError or IORegistryError (or astropy only
    warn that the file is shorter than its header says), and a missing extension or column a
    KeyError; inside this block each becomes a message naming the file. bfpsf's own errors
    pass through, and other warnings are passed on.
    """
    unreadable = f"{path} is not a readable {what} (truncated, damaged or another format)"
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    except BFPSFError:
        raise
    except KeyError as error:
        detail = error.args[0] if error.args else error
        if not str(detail).endswith("not found."):  # astropy's missing extension says so
            detail = f"no column or extension {detail!r}"
        msg = f"{path} is an incomplete {what} ({str(detail).rstrip('.')})"
        raise BFPSFInputError(msg, str(path)) from None
    except PermissionError as error:
        msg = f"cannot read {path}: permission denied"
        raise BFPSFInputError(msg, str(path)) from error
    except (OSError, ValueError, TypeError, EOFError,  # UnicodeDecodeError included
            IORegistryError) as error:
        raise BFPSFInputError(unreadable, str(path)) from error
    finally:
        truncated = False
        for warning in caught:
            if issubclass(warning.category, AstropyUserWarning) and "truncated" in str(
                    warning.message):
                truncated = True
            else:
                warnings.warn_explicit(warning.message, warning.category, warning.filename,
                                       warning.lineno)
    if truncated:
        raise BFPSFInputError(unreadable, str(path))


@contextmanager
def about(path, name_warnings=True):
    """Within this block, a `BFPSFInputError` (a problem of the data, not of an option) whose
    message does not name ``path`` is raised again with ``path: `` in front, and, with
    ``name_warnings``, a warning logged by the package gets it too (library functions on
    arrays do not know the file: of three images, which one's sky is not a plane)."""
    naming = _NamingPath(path)
    handlers = logging.getLogger("bfpsf").handlers if name_warnings else []
    for handler in handlers:
        handler.addFilter(naming)
    try:
        yield
    except BFPSFInputError as error:
        if str(path) in str(error):
            raise
        msg = f"{path}: {error}"
        raise type(error)(msg, error.value) from None
    finally:
        for handler in handlers:
            handler.removeFilter(naming)


class _NamingPath(logging.Filter):
    """Puts ``path: `` in front of a warning that does not name it."""

    def __init__(self, path):
        super().__init__()
        self.path = str(path)

    def filter(self, record):
        message = record.getMessage()
        if record.levelno >= logging.WARNING and self.path not in message:
            record.msg, record.args = f"{self.path}: {message}", None
        return True


def read_table(path, what, *, format=None, numeric=()):  # noqa: A002
    """An `astropy.table.Table` read from ``path``, with one-line errors naming the file.

    ``numeric``: columns that must hold numbers where present (a column of text is refused
    naming the file, the column and a value, not found later as a failed conversion)."""
    path = check_input(path, what)
    with reading(path, what):
        table = Table.read(path, format=format)
    for name in numeric:
        if name in table.colnames and table[name].dtype.kind not in "biuf":
            values = np.asarray(table[name])
            try:
                values.astype(float)
            except (TypeError, ValueError):
                example = next((value for value in values.ravel()
                                if not _is_number(value)), values.ravel()[0])
                msg = f"{path}: column {name} holds {str(example)!r}, not numbers"
                raise BFPSFInputError(msg, name) from None
    return table


def _is_number(value):
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


def refuse_duplicates(paths, what):
    """Raise `BFPSFInputError` if a file is given twice (it would be counted twice)."""
    seen = {}
    for path in paths:
        key = Path(path).resolve() if isinstance(path, (str, os.PathLike)) else id(path)
        if key in seen:
            same = "" if str(seen[key]) == str(path) else f" ({seen[key]} is the same file)"
            msg = f"{what} {path} is given twice{same}: each file may be used once"
            raise BFPSFInputError(msg, str(path))
        seen[key] = path


@contextmanager
def open_product(path, *, keyword, version, kind):
    """Open a bfpsf product FITS file after checking that it is one this bfpsf can read.

    Parameters
    ----------
    path : str or path-like
    keyword : str
        Primary-header keyword holding the schema version (e.g. ``'BFSCHEMA'``).
    version : int
        Newest schema this bfpsf reads.
    kind : str
        What the file should be, for the messages (e.g. ``'calibration'``).

    Yields
    ------
    astropy.io.fits.HDUList
        Opened without memory mapping; closed on exit.

    Raises
    ------
    BFPSFInputError
        The file is missing, lacks ``keyword``, or has a newer schema.
    """
    path = check_input(path, f"{kind} file")
    try:
        hdul = fits.open(path, memmap=False)
    except (OSError, ValueError) as error:
        msg = f"{path} is not a bfpsf {kind} file (not FITS)"
        raise BFPSFInputError(msg, str(path)) from error
    with hdul, reading(path, f"bfpsf {kind} file"):
        header = hdul[0].header
        if keyword not in header:
            msg = f"{path} is not a bfpsf {kind} file (no {keyword} keyword)"
            raise BFPSFInputError(msg, str(path))
        schema = int(header[keyword])
        if schema > version:
            msg = (f"{path} has {kind} schema version {schema}, newer than the {version} this "
                   f"bfpsf {__version__} reads; upgrade bfpsf")
            raise BFPSFInputError(msg, schema)
        yield hdul
