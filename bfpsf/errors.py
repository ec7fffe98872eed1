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
    "BFPSFOutputError",
    "BFPSFResourceError",
    "BFPSFConvergenceError",
    "BFPSFCovarianceError",
    "BFPSFWarning",
    "integer_at_least",
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


class _OutputError(BFPSFError):
    """An error about one output file: ``str(error)`` is exactly the message (without an
    ``[Errno]`` prefix) and ``.filename`` the output."""

    def __init__(self, message, path=None):
        super().__init__(message)
        self.filename = path

    def __str__(self):
        return self.args[0]


class BFPSFFileExistsError(_OutputError, FileExistsError):
    """An output file exists and ``overwrite`` was not requested.

    Parameters
    ----------
    message : str
        The whole message (``str(error)`` is exactly it, without an ``[Errno]`` prefix).
    path : str, optional
        The output, kept in ``.filename``.
    """


class BFPSFOutputError(_OutputError, OSError):
    """An output could not be written (full disk, no permission, file too large); the
    previous file, if any, is left as it was. Parameters as `BFPSFFileExistsError`."""


class BFPSFResourceError(BFPSFValueError):
    """The options and inputs would need more memory or time than the limit allows; refused
    before the work starts. ``.value`` is the estimate (bytes or seconds)."""


class BFPSFConvergenceError(BFPSFError, RuntimeError):
    """An iterative computation did not converge (raised only where ``strict=True``)."""


class BFPSFCovarianceError(BFPSFValueError):
    """A covariance matrix given as input is not a usable covariance (wrong shape, not finite,
    not symmetric or not positive semi-definite)."""


class BFPSFWarning(UserWarning):
    """A result was computed but may be wrong: the user should look (e.g. fluxes beyond the
    first-order brighter-fatter model)."""


def integer_at_least(name, value, minimum, unit=""):
    """``value`` as an int, when it is a whole number of at least ``minimum``.

    The one check of the package's integer arguments (sizes, counts, steps, lags): anything
    else, a fraction, a string or None included, is a `BFPSFValueError` such as
    "pairs must be a positive integer, got 0". ``unit`` follows the bound in the message.
    """
    try:
        whole = int(value)
        valid = whole == value and whole >= minimum
    except (TypeError, ValueError, OverflowError):
        valid = False
    if not valid:
        wording = {0: "a non-negative integer", 1: "a positive integer"}.get(
            minimum, f"an integer >= {minimum}")
        msg = f"{name} must be {wording}{' ' + unit if unit else ''}, got {value!r}"
        raise BFPSFValueError(msg, value)
    return whole
