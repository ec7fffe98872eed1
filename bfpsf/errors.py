"""Exceptions raised by bfpsf.

As in GalSim, every error class also derives from the matching builtin, so callers may catch
either ``bfpsf.errors.BFPSFValueError`` or a plain ``ValueError``. Errors that concern one
value carry it in ``.value`` so that scripts can report it.
"""

__all__ = [
    "BFPSFError",
    "BFPSFValueError",
    "BFPSFInputError",
    "BFPSFFileExistsError",
    "BFPSFConvergenceError",
]


class BFPSFError(Exception):
    """Base class of every error raised by bfpsf."""


class BFPSFValueError(BFPSFError, ValueError):
    """An argument has a value outside what the function accepts.

    Parameters
    ----------
    message : str
        What was expected.
    value : object, optional
        The offending value, kept in ``.value``.
    """

    def __init__(self, message, value=None):
        super().__init__(message)
        self.value = value


class BFPSFInputError(BFPSFValueError):
    """Input data (FITS files, images, tables) cannot be used as given: missing header keyword,
    unpaired flat, shape mismatch, non-finite pixels where none are allowed, ..."""


class BFPSFFileExistsError(BFPSFError, FileExistsError):
    """An output file exists and ``overwrite`` was not requested."""


class BFPSFConvergenceError(BFPSFError, RuntimeError):
    """An iterative computation did not converge (raised only where ``strict=True``)."""
