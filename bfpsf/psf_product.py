"""The PSF product: a `FluxDependentPSF` as a FITS file (``bfpsf psf -o PSF.fits``).

Layout (schema `PSF_SCHEMA_VERSION`): primary HDU = P0 data (unit flux, oversampled, pixel
response included) with ``BFPSFVER`` (schema), ``OVERSAMX``/``OVERSAMY``, ``ORIGINX``/``ORIGINY``,
``GAIN`` (e-/ADU of the images the PSF is meant for; the model itself works in e-), ``MODE``,
``CALIB``, ``PIXRESP``; HDUs ``SHIFT_N`` and ``SHIFT_E`` = a^N and a^E (1/e-, [dy+m, dx+m]);
schema 2 adds an optional ``BFTABLE`` HDU, the table-mode R when it is not the default (e.g.
built with the exact boundary density, ``density_profile``), since the profile it came from is
not stored; optional ``SHIFT_N_SAMP`` / ``SHIFT_E_SAMP`` [sample, dy+m, dx+m] hold the shift
samples of the calibration (its uncertainty, propagated by ``bfpsf slope --psf``). The calibration file is not needed to read the product back.
Schema 3 adds the grid of a `~bfpsf.model.gridded.GriddedFluxDependentPSF`: HDU ``GRID`` = the
node P0s (ny_nodes, nx_nodes, n, n) with ``NODESX``/``NODESY``, and HDUs ``GRIDX``/``GRIDY`` =
the node coordinates (pixels); the primary HDU then holds the central node (readers of
schema 2 see one P0), and ``GRIDBFT`` the nodes' BF tables when they are not the default.
"""

import numpy as np

from .errors import BFPSFValueError
from .files import open_product, refuse_overwrite, write_fits

__all__ = ["PSF_SCHEMA_VERSION", "write_psf", "read_psf"]

#: Version of the PSF product layout written by `write_psf` (2: optional BFTABLE HDU;
#: 3: optional GRID, GRIDX, GRIDY, GRIDBFT HDUs of a gridded PSF).
PSF_SCHEMA_VERSION = 3


def write_psf(psf, path, *, calibration=None, meta=None, overwrite=False):
    """Write a `~bfpsf.model.psf.FluxDependentPSF` as a PSF product.

    Parameters
    ----------
    psf : FluxDependentPSF or GriddedFluxDependentPSF
    path : str or path-like
    calibration : str, optional
        Name of the calibration file the shifts come from (kept in ``CALIB``); default
        ``psf.calibration``.
    meta : dict, optional
        Extra scalar header cards (keys of at most 8 characters).
    overwrite : bool, optional
        Replace an existing file. Default False (`~bfpsf.errors.BFPSFFileExistsError`).
    """
    from astropy.io import fits

    refuse_overwrite(path, overwrite)
    if psf.mode == "exact" and any(node.density_profile is not None
                                   for node in getattr(psf, "nodes", [psf])):
        msg = ("a mode='exact' model with a density_profile cannot be stored: the file keeps no "
               "GalSim profile and would read back with G15's mean density; write the same "
               "model in mode='table' (its exact-density table is stored)")
        raise BFPSFValueError(msg, psf.mode)
    nodes = getattr(psf, "nodes", None)
    single = psf if nodes is None else nodes[len(nodes) // 2]
    primary = fits.PrimaryHDU(np.asarray(single.data, dtype=np.float64))
    header = primary.header
    header["BFPSFVER"] = (PSF_SCHEMA_VERSION, "bfpsf PSF product schema")
    header["BUNIT"] = ("1/pixel", "unit-flux P0 per image pixel, oversampled")
    header["OVERSAMX"] = (int(psf.oversampling[1]), "oversampling along x")
    header["OVERSAMY"] = (int(psf.oversampling[0]), "oversampling along y")
    header["ORIGINX"] = (float(psf.origin[0]), "x of the star centre in the data")
    header["ORIGINY"] = (float(psf.origin[1]), "y of the star centre in the data")
    header["GAIN"] = (float(psf.image_gain), "e-/ADU of the images")
    header["MODE"] = (psf.mode, "BF term: table of phases or exact")
    header["CALIB"] = (str(calibration or psf.calibration), "calibration of the shifts")
    header["PIXRESP"] = (True, "pixel response included in P0")
    for key, value in (meta or {}).items():
        header[key] = value
    north = fits.ImageHDU(np.asarray(psf.shifts.north), name="SHIFT_N")
    east = fits.ImageHDU(np.asarray(psf.shifts.east), name="SHIFT_E")
    north.header["BUNIT"] = "1/electron"
    east.header["BUNIT"] = "1/electron"
    hdus = [primary, north, east]
    if psf.shift_samples:
        # the calibration's uncertainty, for predictions with errors (optional HDUs)
        for name, attribute in (("SHIFT_N_SAMP", "north"), ("SHIFT_E_SAMP", "east")):
            samples = fits.ImageHDU(np.array([getattr(sample, attribute)
                                              for sample in psf.shift_samples]), name=name)
            samples.header["BUNIT"] = "1/electron"
            hdus.append(samples)
    if psf.mode == "table" and single.density_profile is not None:
        table = fits.ImageHDU(np.asarray(single.bf_table, dtype=np.float64), name="BFTABLE")
        table.header["BUNIT"] = ("1/(pixel electron)", "R[P0] per unit flux squared")
        hdus.append(table)
    if nodes is not None:
        hdus.extend(_grid_hdus(psf))
    write_fits(fits.HDUList(hdus), path, overwrite=overwrite)


def _grid_hdus(psf):
    """HDUs of the grid of a `GriddedFluxDependentPSF` (schema 3)."""
    from astropy.io import fits

    grid = fits.ImageHDU(np.asarray(psf.data, dtype=np.float64), name="GRID")
    grid.header["NODESX"] = (int(psf.grid_shape[1]), "grid nodes along x")
    grid.header["NODESY"] = (int(psf.grid_shape[0]), "grid nodes along y")
    grid.header["BUNIT"] = ("1/pixel", "unit-flux P0 of each node [y, x, ...]")
    hdus = [grid, fits.ImageHDU(np.asarray(psf.x_nodes), name="GRIDX"),
            fits.ImageHDU(np.asarray(psf.y_nodes), name="GRIDY")]
    for hdu in hdus[1:]:
        hdu.header["BUNIT"] = ("pixel", "node coordinates on the image")
    if psf.mode == "table" and any(node.density_profile is not None for node in psf.nodes):
        tables = np.array([node.bf_table for node in psf.nodes]).reshape(psf.data.shape)
        hdus.append(fits.ImageHDU(tables, name="GRIDBFT"))
    return hdus


def read_psf(path, *, cls=None, **kwargs):
    """Read a PSF product written by `write_psf` (model in e-; ``image_gain`` from GAIN).

    Parameters
    ----------
    path : str or path-like
    cls : type, optional
        `FluxDependentPSF` or a subclass (default `FluxDependentPSF`).
    **kwargs
        Override the stored options (e.g. ``mode='exact'``).

    Raises
    ------
    BFPSFInputError
        The file is missing, is not a PSF product, or has a newer schema.
    """
    from .model.psf import FluxDependentPSF
    from .shifts import BoundaryShifts

    cls = FluxDependentPSF if cls is None else cls
    with open_product(path, keyword="BFPSFVER", version=PSF_SCHEMA_VERSION,
                      kind="PSF product") as hdul:
        header = hdul[0].header
        data = np.array(hdul[0].data, dtype=float)
        shifts = BoundaryShifts(np.array(hdul["SHIFT_N"].data, dtype=float),
                                np.array(hdul["SHIFT_E"].data, dtype=float), check=False)
        options = {"oversampling": (int(header["OVERSAMY"]), int(header["OVERSAMX"])),
                   "origin": (float(header["ORIGINX"]), float(header["ORIGINY"])),
                   "mode": str(header["MODE"])}
        if "BFTABLE" in hdul and options["mode"] == "table":
            options["bf_table"] = np.array(hdul["BFTABLE"].data, dtype=float)
        image_gain = float(header["GAIN"])
        calibration = str(header["CALIB"])
        samples = ()
        if "SHIFT_N_SAMP" in hdul:
            samples = tuple(BoundaryShifts(north, east, check=False) for north, east in
                            zip(np.array(hdul["SHIFT_N_SAMP"].data, dtype=float),
                                np.array(hdul["SHIFT_E_SAMP"].data, dtype=float)))
        grid = None
        if "GRID" in hdul:
            grid = (np.array(hdul["GRID"].data, dtype=float),
                    np.array(hdul["GRIDX"].data, dtype=float),
                    np.array(hdul["GRIDY"].data, dtype=float),
                    np.array(hdul["GRIDBFT"].data, dtype=float) if "GRIDBFT" in hdul
                    and options["mode"] == "table" else None)
    options.update(kwargs)
    if grid is not None:
        from .model.gridded import GriddedFluxDependentPSF

        options.pop("bf_table", None)
        if grid[3] is not None:
            options["bf_table"] = grid[3]
        psf = GriddedFluxDependentPSF.from_data(grid[0], grid[1], grid[2], shifts, **options)
        psf.image_gain = image_gain
        psf.calibration = calibration
        for node in psf.nodes:
            node.shift_samples = samples
        return psf
    psf = cls(data, shifts, **options)
    psf.image_gain = image_gain
    psf.calibration = calibration
    psf.shift_samples = samples
    return psf
