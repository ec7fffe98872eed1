"""model layer of bfpsf (see DESIGN.md data flow).

Every PSF kind is imported here, so that a product of any kind reads back
(`bfpsf.model.product` knows the kinds by their registration, not by import).
"""

from . import gridded, psf  # registers the kinds with bfpsf.model.product

__all__ = ["gridded", "psf"]
