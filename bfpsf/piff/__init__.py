"""bfpsf's Piff plug-in: ``modules: [bfpsf.piff]`` registers the PSF type ``BrighterFatter``.

Importing this package registers `BrighterFatterPSF` with Piff (``piff.PSF.valid_psf_types``),
so a Piff config names it after ``modules: [bfpsf.piff]``, and ``piff.read`` reads files
that hold one (Piff's ``read`` does not import ``modules:``: import this package first).
See docs/plugins.md.
"""

try:
    import piff  # noqa: F401
except ImportError as error:  # bfpsf works without Piff; only this plug-in needs it
    msg = "bfpsf.piff needs Piff: pip install 'bfpsf[piff]' (or piff itself)"
    raise ImportError(msg) from error

from .psf import AmplifierBF, BrighterFatterPSF  # noqa: E402

__all__ = ["BrighterFatterPSF", "AmplifierBF"]
