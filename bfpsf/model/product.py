"""The PSF product: a `FluxDependentPSF` as a FITS file (``bfpsf psf -o PSF.fits``).

Layout (schema `PSF_SCHEMA_VERSION`): primary HDU = P0 data (unit flux, oversampled, pixel
response included) with ``BFPSFVER`` (schema) and one card per constructor option of
`~bfpsf.model.psf.FluxDependentPSF` (``FluxDependentPSF.options``): ``OVERSAMX``/``OVERSAMY``,
``ORIGINX``/``ORIGINY``, ``FLUXUNIT`` ('electron' or 'adu') and ``GAIN`` (e-/ADU; absent when
unknown), ``MODE``, ``BUILDUP`` (build-up steps, 0 for G15's one step), ``FILLVAL``,
``DENSOVER``, ``FLUX``/``X_0``/``Y_0``, plus ``CALIB`` and ``PIXRESP``; HDUs ``SHIFT_N`` and
``SHIFT_E`` = a^N and a^E (1/e-, [dy+m, dx+m]); ``BFTABLE``, the table-mode R (1/e-), whatever
made it (G15's mean density, the exact density of a GalSim profile, or a table of the caller's).
Optional ``SHIFT_N_SAMP`` / ``SHIFT_E_SAMP`` [sample, dy+m, dx+m] hold the shift samples of the
calibration (its uncertainty, propagated by ``bfpsf slope --psf``). Schema 2 files (no
FLUXUNIT, BUILDUP, ...) read as models in electrons with their GAIN recorded. The calibration
file is not needed to read the product back.
Schema 5 adds the optional HDU ``AMPSHIFT``, a table of the boundary shifts of each amplifier
the P0 was fitted on (columns ``AMP``, ``SHIFT_N``, ``SHIFT_E``, 1/e-, [dy+m, dx+m]; ``bfpsf
psf`` on several amplifiers), read back as ``psf.amplifier_shifts``; ``SHIFT_N``/``SHIFT_E``
are then their mean weighted by the stars used.
Schema 4 adds the grid of a `~bfpsf.model.gridded.GriddedFluxDependentPSF`: HDU ``GRID`` = the
node P0s (ny_nodes, nx_nodes, n, n) with ``NODESX``/``NODESY``, HDUs ``GRIDX``/``GRIDY`` = the
node coordinates (pixels) and, in table mode, ``GRIDBFT`` = every node's BF table; the primary
HDU and the option cards then describe the central node (readers of schema 3 see one P0).
Schema 6 adds the metadata every PSF kind carries (`bfpsf.model.base`): ``LINC`` (a refined
calibration's linearity correction c per 1e5 e-, applied to the images on input; 0 when none),
``FLUXCORR`` / ``FLUXCERR`` (total flux over the flux P0 holds in its support, and its error:
the aperture correction photometry applies; 1 and no FLUXCERR when not measured; ``STARFLUX``,
optional: the flux in e- the fitted stars weigh in at, `BFPSFModel.shape_error`; ``CONVERGD``,
optional: whether the P0 fit converged, ``psf.p0_converged``, None without it), ``WINGAMP``
/ ``WINGPOW`` (the power law A r^-p of the wings beyond the support, per pixel per unit flux
inside it; A = 0 when not measured). Files of
schema <= 5 read with those defaults.
Schema 7 adds the optional HDU ``EMPIRIC``: a one-row table whose ``json`` column holds the
EMPIRICAL term of a calibration refined by ``bfpsf diagnose --output-calib``
(`bfpsf.model.empirical.EmpiricalTerm.to_dict`, label ``'empirical'``), with the card
``EMPIRIC = T`` in the primary header; read back as ``psf.empirical`` (None without it).
Readers of schema 6 refuse these files rather than drop the term.
"""

import json

import numpy as np
from astropy.io import fits
from astropy.table import Table

from ..errors import BFPSFValueError
from ..files import open_product, refuse_overwrite
from ..outputs import write_fits
from ..shifts import BoundaryShifts
from .empirical import EmpiricalTerm
from .wings import WingModel

__all__ = ["PSF_SCHEMA_VERSION", "write_psf", "read_psf", "register_kind"]

#: Version of the PSF product layout written by `write_psf` (2: optional BFTABLE HDU;
#: 3: every constructor option, FLUXUNIT replacing the ADU meaning of GAIN; 4: optional GRID,
#: GRIDX, GRIDY, GRIDBFT HDUs of a gridded PSF; 5: optional AMPSHIFT table of per-amplifier
#: shifts; 6: LINC, FLUXCORR, FLUXCERR cards; 7: optional EMPIRIC table of the EMPIRICAL
#: term).
PSF_SCHEMA_VERSION = 7

#: The classes a product reads back as, by ``product_kind`` ('single', 'grid'): each kind
#: registers itself (`bfpsf.model.base.BFPSFModel.__init_subclass__`), so this module, which
#: the kinds import for their ``write`` and ``read``, imports none of them.
_KINDS = {}


def register_kind(name, cls):
    """Read products of kind ``name`` ('single' or 'grid') back as ``cls``."""
    _KINDS[name] = cls


def _kind(name):
    try:
        return _KINDS[name]
    except KeyError:  # bfpsf.model's __init__ imports every kind: never without a bug
        msg = f"no PSF kind {name!r} is registered (import bfpsf.model first)"
        raise BFPSFValueError(msg, name) from None


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
    refuse_overwrite(path, overwrite)
    nodes = psf.nodes if psf.product_kind == "grid" else None
    if psf.mode == "exact" and any(node.density_profile is not None
                                   for node in (nodes or [psf])):
        msg = ("a mode='exact' model with a density_profile cannot be stored: the file keeps no "
               "GalSim profile and would read back with G15's mean density; write the same "
               "model in mode='table' (its exact-density table is stored)")
        raise BFPSFValueError(msg, psf.mode)
    single = psf if nodes is None else nodes[len(nodes) // 2]
    options = single.options
    primary = fits.PrimaryHDU(np.asarray(single.data, dtype=np.float64))
    header = primary.header
    header["BFPSFVER"] = (PSF_SCHEMA_VERSION, "bfpsf PSF product schema")
    header["BUNIT"] = ("1/pixel", "unit-flux P0 per image pixel, oversampled")
    header["OVERSAMX"] = (options["oversampling"][1], "oversampling along x")
    header["OVERSAMY"] = (options["oversampling"][0], "oversampling along y")
    header["ORIGINX"] = (options["origin"][0], "x of the star centre in the data")
    header["ORIGINY"] = (options["origin"][1], "y of the star centre in the data")
    header["FLUXUNIT"] = (options["flux_unit"], "unit of fluxes and model values")
    if options["gain"] is not None:
        header["GAIN"] = (options["gain"], "e-/ADU of the images")
    header["MODE"] = (options["mode"], "BF term: table of phases or exact")
    header["BUILDUP"] = (options["buildup_steps"] or 0, "build-up steps (0: one-step G15)")
    header["FILLVAL"] = (options["fill_value"], "model value outside the P0 data")
    header["DENSOVER"] = (options["density_oversampling"], "sub-pixels of the exact density")
    for key in ("flux", "x_0", "y_0"):
        header[key.upper()] = (options[key], f"default {key} parameter")
    header["CALIB"] = (str(calibration or psf.calibration), "calibration of the shifts")
    header["PIXRESP"] = (True, "pixel response included in P0")
    header["LINC"] = (float(psf.linearity_c_per_1e5), "linearity correction c per 1e5 e-")
    header["FLUXCORR"] = (float(psf.flux_correction), "total flux / flux in the P0 support")
    header["WINGN"] = (len(psf.wing_coefficients), "wing profile nodes (model.wings.WingModel)")
    for index, value in enumerate(psf.wing_coefficients):
        header[f"WINGC{index}"] = (float(value), f"wing profile: r^3 W at node {index}")
    header["WINGPOW"] = (float(psf.wing_tail_power), "wings beyond the last node: r^-p")
    header["WINGHALF"] = (int(psf.wing_half_size), "support half-width the wings lie beyond")
    if any(psf.flux_correction_slope):  # absent: one correction for the whole image
        for key, value, comment in zip(
                ("FLUXCSX", "FLUXCSY", "FLUXCSXE", "FLUXCSYE", "FLUXCX0", "FLUXCY0"),
                (*psf.flux_correction_slope, *psf.flux_correction_slope_err,
                 *psf.flux_correction_centre),
                ("FLUXCORR change per pixel along x", "FLUXCORR change per pixel along y",
                 "error of FLUXCSX", "error of FLUXCSY", "x where FLUXCORR holds",
                 "y where FLUXCORR holds")):
            header[key] = (float(value), comment)
    if np.isfinite(psf.flux_correction_err):  # absent: unknown (too few isolated stars)
        header["FLUXCERR"] = (float(psf.flux_correction_err), "error of FLUXCORR")
    if np.isfinite(psf.star_flux_e):  # absent: not fitted from stars
        header["STARFLUX"] = (float(psf.star_flux_e), "e-: the flux the fitted stars weigh in at")
    if psf.p0_converged is not None:  # absent: not fitted from stars
        header["CONVERGD"] = (bool(psf.p0_converged), "the P0 fit converged")
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
    if options["mode"] == "table":
        table = fits.ImageHDU(np.asarray(options["bf_table"], dtype=np.float64), name="BFTABLE")
        table.header["BUNIT"] = ("1/(pixel electron)", "R[P0] per unit flux squared")
        hdus.append(table)
    if psf.amplifier_shifts:
        hdus.append(_amplifier_hdu(psf.amplifier_shifts))
    header["EMPIRIC"] = (psf.empirical is not None, "EMPIRICAL term applied (EMPIRIC HDU)")
    if psf.empirical is not None:
        hdus.append(_empirical_hdu(psf.empirical))
    if nodes is not None:
        hdus.extend(_grid_hdus(psf))
    write_fits(fits.HDUList(hdus), path, overwrite=overwrite)


def _amplifier_hdu(amplifier_shifts):
    """Table HDU ``AMPSHIFT`` of the shifts of each amplifier (one radius: the largest)."""
    radius = max(shifts.radius for shifts in amplifier_shifts.values())
    padded = [shifts.padded(radius) for shifts in amplifier_shifts.values()]
    table = Table({"AMP": list(amplifier_shifts),
                   "SHIFT_N": np.array([shifts.north for shifts in padded]),
                   "SHIFT_E": np.array([shifts.east for shifts in padded])})
    hdu = fits.table_to_hdu(table)
    hdu.name = "AMPSHIFT"
    for column in (2, 3):  # FITS has no 1/electron unit string: say it in words
        hdu.header[f"TUNIT{column}"] = "electron-1"
    return hdu


def _empirical_hdu(term):
    """Table HDU ``EMPIRIC``: the EMPIRICAL term's record as JSON (one row)."""
    hdu = fits.table_to_hdu(Table({"json": [json.dumps(term.to_dict())]}))
    hdu.name = "EMPIRIC"
    hdu.header["LABEL"] = ("empirical", "describes the stars, explains nothing")
    return hdu


def _read_empirical(hdul):
    """The EMPIRICAL term of the ``EMPIRIC`` HDU, or None without it."""
    if "EMPIRIC" not in hdul:
        return None
    return EmpiricalTerm.from_dict(json.loads(str(hdul["EMPIRIC"].data["json"][0])))


def _read_amplifier_shifts(hdul):
    """{EXTNAME: BoundaryShifts} from the ``AMPSHIFT`` HDU ({} without it)."""
    if "AMPSHIFT" not in hdul:
        return {}
    table = hdul["AMPSHIFT"].data
    return {str(name).strip(): BoundaryShifts(np.array(north, dtype=float),
                                              np.array(east, dtype=float), check=False)
            for name, north, east in zip(table["AMP"], table["SHIFT_N"], table["SHIFT_E"])}


def _grid_hdus(psf):
    """HDUs of the grid of a `GriddedFluxDependentPSF` (schema 3)."""
    grid = fits.ImageHDU(np.asarray(psf.data, dtype=np.float64), name="GRID")
    grid.header["NODESX"] = (int(psf.grid_shape[1]), "grid nodes along x")
    grid.header["NODESY"] = (int(psf.grid_shape[0]), "grid nodes along y")
    grid.header["BUNIT"] = ("1/pixel", "unit-flux P0 of each node [y, x, ...]")
    hdus = [grid, fits.ImageHDU(np.asarray(psf.x_nodes), name="GRIDX"),
            fits.ImageHDU(np.asarray(psf.y_nodes), name="GRIDY")]
    for hdu in hdus[1:]:
        hdu.header["BUNIT"] = ("pixel", "node coordinates on the image")
    if psf.mode == "table":
        tables = np.array([node.bf_table for node in psf.nodes]).reshape(psf.data.shape)
        hdus.append(fits.ImageHDU(tables, name="GRIDBFT"))
    return hdus


def read_psf(path, *, cls=None, **kwargs):
    """Read a PSF product written by `write_psf`, with every option it was built with.

    Parameters
    ----------
    path : str or path-like
    cls : type, optional
        `FluxDependentPSF` or a subclass (default `FluxDependentPSF`).
    **kwargs
        Override the stored options (e.g. ``mode='exact'``, which drops the stored table).

    Raises
    ------
    BFPSFInputError
        The file is missing, is not a PSF product, or has a newer schema.
    """
    cls = _kind("single") if cls is None else cls
    with open_product(path, keyword="BFPSFVER", version=PSF_SCHEMA_VERSION,
                      kind="PSF product") as hdul:
        header = hdul[0].header
        data = np.array(hdul[0].data, dtype=float)
        shifts = BoundaryShifts(np.array(hdul["SHIFT_N"].data, dtype=float),
                                np.array(hdul["SHIFT_E"].data, dtype=float), check=False)
        options = {"oversampling": (int(header["OVERSAMY"]), int(header["OVERSAMX"])),
                   "origin": (float(header["ORIGINX"]), float(header["ORIGINY"])),
                   "mode": str(header["MODE"]),
                   "flux_unit": str(header.get("FLUXUNIT", "electron")),
                   "gain": float(header["GAIN"]) if "GAIN" in header else None,
                   "buildup_steps": int(header.get("BUILDUP", 0)) or None,
                   "fill_value": float(header.get("FILLVAL", 0.0)),
                   "density_oversampling": int(header.get("DENSOVER", 8))}
        for key in ("flux", "x_0", "y_0"):
            if key.upper() in header:
                options[key] = float(header[key.upper()])
        if "BFTABLE" in hdul:
            options["bf_table"] = np.array(hdul["BFTABLE"].data, dtype=float)
        calibration = str(header["CALIB"])
        metadata = {"calibration": calibration,
                    "linearity_c_per_1e5": float(header.get("LINC", 0.0)),
                    "flux_correction": float(header.get("FLUXCORR", 1.0)),
                    "flux_correction_err": float(header.get("FLUXCERR", np.nan)),
                    "flux_correction_slope": tuple(float(header.get(key, 0.0))
                                                   for key in ("FLUXCSX", "FLUXCSY")),
                    "flux_correction_slope_err": tuple(float(header.get(key, np.nan))
                                                       for key in ("FLUXCSXE", "FLUXCSYE")),
                    "flux_correction_centre": tuple(float(header.get(key, 0.0))
                                                    for key in ("FLUXCX0", "FLUXCY0")),
                    "star_flux_e": float(header.get("STARFLUX", np.nan)),
                    "p0_converged": (bool(header["CONVERGD"]) if "CONVERGD" in header
                                     else None),
                    "empirical": _read_empirical(hdul)}
        wings = _read_wings(header)
        samples = ()
        if "SHIFT_N_SAMP" in hdul:
            samples = tuple(BoundaryShifts(north, east, check=False) for north, east in
                            zip(np.array(hdul["SHIFT_N_SAMP"].data, dtype=float),
                                np.array(hdul["SHIFT_E_SAMP"].data, dtype=float)))
        amplifier_shifts = _read_amplifier_shifts(hdul)
        grid = None
        if "GRID" in hdul:
            grid = (np.array(hdul["GRID"].data, dtype=float),
                    np.array(hdul["GRIDX"].data, dtype=float),
                    np.array(hdul["GRIDY"].data, dtype=float),
                    np.array(hdul["GRIDBFT"].data, dtype=float) if "GRIDBFT" in hdul
                    and options["mode"] == "table" else None)
    options.update(kwargs)
    if grid is not None:
        options.pop("bf_table", None)
        if grid[3] is not None and options.get("mode") == "table":
            options["bf_table"] = grid[3]
        psf = _kind("grid").from_data(grid[0], grid[1], grid[2], shifts, **options)
        _set_metadata(psf, {**metadata, **wings(psf.half_size)})
        psf.shift_samples = samples
        psf.amplifier_shifts = amplifier_shifts
        return psf
    if options.get("mode") != "table":
        options.pop("bf_table", None)  # an exact-mode override recomputes R
    psf = cls(data, shifts, **options)
    _set_metadata(psf, {**metadata, **wings(psf.half_size)})
    psf.shift_samples = samples
    psf.amplifier_shifts = amplifier_shifts
    return psf


def _read_wings(header):
    """The wing profile's metadata, as a function of the model's half-size: the nodes, or a
    power law A r^-p (WINGAMP, WINGPOW) of a product written before them, put on the nodes."""
    power = float(header.get("WINGPOW", 4.0))
    if "WINGN" in header:
        coefficients = tuple(float(header[f"WINGC{index}"])
                             for index in range(int(header["WINGN"])))
        half = header.get("WINGHALF")
        return lambda half_size: {"wing_coefficients": coefficients, "wing_tail_power": power,
                                  "wing_half_size": half_size if half is None else int(half)}
    amplitude = float(header.get("WINGAMP", 0.0))

    def legacy(half_size):
        if amplitude <= 0:
            return {"wing_coefficients": (), "wing_tail_power": power, "wing_half_size": half_size}
        wings = WingModel.power_law(amplitude, power, half_size)
        return {"wing_coefficients": wings.coefficients, "wing_tail_power": power,
                "wing_half_size": half_size}
    return legacy


def _set_metadata(psf, metadata):
    for name, value in metadata.items():
        setattr(psf, name, value)
