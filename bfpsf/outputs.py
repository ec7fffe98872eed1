"""How every bfpsf output is written: atomically, all or nothing, one JSON writer.

Every file is written to a temporary file in the destination's directory and renamed over the
destination only once complete (`atomic_path`): a write that fails (a full disk, an error
half-way) leaves the previous file byte for byte and no partial file. A command run inside
`all_or_nothing` removes the outputs it made when it fails or is interrupted. The checks made
before a command writes anything (no overwrite without asking, an input is never an output)
are in `bfpsf.files`.
"""

import json
import math
import os
import tempfile
from contextlib import contextmanager, suppress
from pathlib import Path

import numpy as np

from . import __version__
from .errors import BFPSFError, BFPSFOutputError
from .files import refuse_overwrite

__all__ = ["atomic_path", "make_directory", "all_or_nothing", "json_safe", "write_text",
           "write_fits", "TABLE_SCHEMA_VERSION", "product_table", "write_table",
           "save_figure", "write_json"]


@contextmanager
def atomic_path(path):
    """A temporary path beside ``path`` to write to; renamed onto ``path`` on success.

    The temporary file is created in the same directory (so `os.replace` is an atomic rename
    on the same file system) with the same suffix (writers that choose a format by suffix,
    e.g. astropy and matplotlib, still do). If the block raises, the temporary file is removed
    and ``path`` is left as it was.

    Yields
    ------
    pathlib.Path
        Where to write.
    """
    path = Path(path)
    try:
        handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.",
                                             suffix=f".tmp{path.suffix}",
                                             dir=path.parent if str(path.parent) else ".")
    except OSError as error:
        raise _output_error(path, error) from error
    os.close(handle)
    temporary = Path(temporary)
    try:
        temporary.unlink()  # writers that refuse an existing file (astropy) see none
        yield temporary
        new = not path.exists()
        os.replace(temporary, path)
        if new and _NEW_OUTPUTS is not None:
            _NEW_OUTPUTS.append(path)
    except BaseException as error:
        temporary.unlink(missing_ok=True)
        if isinstance(error, OSError) and not isinstance(error, BFPSFError):
            raise _output_error(path, error) from error
        raise


def _output_error(path, error):
    """A one-line `BFPSFOutputError` for an OS error while writing ``path`` (full disk,
    permissions, file too large)."""
    reason = error.strerror or str(error) or type(error).__name__
    previous = "; the previous file is unchanged" if Path(path).exists() else ""
    msg = f"cannot write {path}: {reason}{previous}"
    return BFPSFOutputError(msg, str(path))


def make_directory(directory):
    """``mkdir -p`` with a one-line `BFPSFOutputError` on failure."""
    directory = Path(directory)
    missing = [directory, *directory.parents]
    missing = [folder for folder in missing if not folder.exists()]
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise _output_error(directory, error) from error
    if _NEW_OUTPUTS is not None:
        _NEW_OUTPUTS.extend(reversed(missing))  # parents first


#: The files and directories the running command has created (`all_or_nothing`), or None.
_NEW_OUTPUTS = None


@contextmanager
def all_or_nothing():
    """A command's outputs, all or none: the files (`atomic_path`) and directories
    (`make_directory`) created in the block are removed again if it raises (an error, an
    interrupt), so a command that stops leaves none of its new outputs beside complete
    earlier ones. A file it replaced (``--overwrite``) keeps its new, complete content."""
    global _NEW_OUTPUTS
    outer, _NEW_OUTPUTS = _NEW_OUTPUTS, []
    try:
        yield
    except BaseException:
        for path in reversed(_NEW_OUTPUTS):
            with suppress(OSError):  # a directory that holds other files stays
                path.rmdir() if path.is_dir() else path.unlink()
        raise
    else:
        if outer is not None:
            outer.extend(_NEW_OUTPUTS)
    finally:
        _NEW_OUTPUTS = outer


def json_safe(value):
    """Plain JSON types: arrays to lists, numpy scalars to Python ones, NaN and infinities
    (not JSON) to null; dataclass instances are left out of dicts, other objects become str."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()
                if not hasattr(item, "__dataclass_fields__")}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [json_safe(item) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if value is None or isinstance(value, str):
        return value
    return str(value)


def write_text(path, text, *, overwrite=False):
    """Write a text file atomically (refused if it exists unless ``overwrite``)."""
    path = Path(path)
    refuse_overwrite(path, overwrite)
    with atomic_path(path) as temporary:
        temporary.write_text(text)
    return path


def write_fits(hdus, path, *, overwrite=False):
    """Write an `astropy.io.fits.HDUList` atomically (refused if it exists unless
    ``overwrite``)."""
    path = Path(path)
    refuse_overwrite(path, overwrite)
    with atomic_path(path) as temporary:
        hdus.writeto(temporary)
    return path


#: Version of the layout of the tables bfpsf writes (ECSV meta ``bfpsf_schema``).
TABLE_SCHEMA_VERSION = 1


def _plain(value):
    """Plain YAML-able copy of a meta value; objects that are not data are left out (None)."""
    if isinstance(value, dict):
        items = {str(key): _plain(item) for key, item in value.items()}
        return {key: item for key, item in items.items() if item is not None
                or value.get(key) is None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(item) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if value is None or isinstance(value, str):
        return value
    return None


def product_table(table):
    """A copy of ``table`` as bfpsf writes it: each ``X_err`` column without a unit takes the
    unit of ``X``, the meta holds only plain values (no object reprs), plus ``bfpsf_schema``
    and ``bfpsf_version``."""
    table = table.copy(copy_data=False)
    for name in table.colnames:
        base = name[:-len("_err")] if name.endswith("_err") else None
        if base in table.colnames and table[name].unit is None:
            table[name].unit = table[base].unit
    meta = {str(key): _plain(value) for key, value in table.meta.items()
            if value is None or _plain(value) is not None}
    table.meta.clear()
    table.meta.update(meta)
    table.meta["bfpsf_schema"] = TABLE_SCHEMA_VERSION
    table.meta["bfpsf_version"] = __version__
    return table


def write_table(table, path, *, overwrite=False, format="ascii.ecsv"):  # noqa: A002
    """Write an `astropy.table.Table` (`product_table`) atomically (refused if it exists unless
    ``overwrite``)."""
    path = Path(path)
    refuse_overwrite(path, overwrite)
    table = product_table(table)
    with atomic_path(path) as temporary:
        table.write(temporary, format=format)
    return path


def save_figure(figure, path, *, overwrite=False, close=True, **savefig_kwargs):
    """Save a matplotlib figure atomically (refused if it exists unless ``overwrite``)."""
    path = Path(path)
    refuse_overwrite(path, overwrite)
    try:
        with atomic_path(path) as temporary:
            figure.savefig(temporary, **savefig_kwargs)
    finally:
        if close:
            import matplotlib.pyplot as plt

            plt.close(figure)
    return path


def write_json(path, summary, *, overwrite=False):
    """Write a machine-readable summary as strict JSON (NaN as null), atomically.

    Refuses to replace an existing file unless ``overwrite``. Returns the path.
    """
    path = Path(path)
    refuse_overwrite(path, overwrite)
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(json_safe(summary), indent=1, allow_nan=False) + "\n")
    return path
