"""bfpsf's Piff plug-in: ``modules: [bfpsf.piff]`` registers the PSF type ``BrighterFatter``.

Importing this package registers `BrighterFatterPSF` with Piff (``piff.PSF.valid_psf_types``),
so a Piff config names it after ``modules: [bfpsf.piff]``, and ``piff.read`` reads files
that hold one (Piff's ``read`` does not import ``modules:``: import this package first).
See docs/plugins.md.
"""

from .psf import AmplifierBF, BrighterFatterPSF

__all__ = ["BrighterFatterPSF", "AmplifierBF"]
