"""Size-colour correction (G15 section 3.2 and 3.3; Astier et al. 2013, section 10).

Blue stars are broader than red ones, and on a field flux correlates with colour, so a
size-colour relation can mimic (or hide) the brighter-fatter slope. G15 fits the second moments
``Mxx`` and ``Myy`` against colour on low-flux stars (where BF is negligible) with a polynomial
(linear in practice), evaluates it for every star and subtracts it.

Here the fitted polynomial is subtracted *relative to the reference colour* (the median colour
of the fit sample): ``M_corrected = M - (p(c) - p(c_ref))``. This removes the colour
dependence exactly as G15 does while keeping the moments at the size of a star of the
reference colour, so that ``sigma_x = sqrt(Mxx)`` and the relative slopes stay meaningful.
``Mxy`` is corrected the same way when ``fit_mxy=True``.

BF leaks into a colour-only fit: within the fit sample, brighter stars are both redder and
(by BF) broader, which biases the colour coefficient and, after subtraction, the BF slope
(by ~0.002 pixel per 100 ke- in ``tests/test_colour.py``). By default the fit therefore
includes a nuisance term linear in peak flux, ``M = p(c) + k peak``, whose ``k`` absorbs the BF
of the fit sample; only ``p`` is subtracted. ``peak_term=False`` gives G15's colour-only fit.

The coefficient errors move every corrected size coherently; pass the fit to
`bfpsf.measure.slopes.bf_slopes` (``colour_fit=``) to include them in the slope errors (in
``tests/test_colour.py`` they are 1.5 times the statistical slope error, and the pulls of the
corrected slope over 30 realisations have a spread of 1.08).
"""

from dataclasses import dataclass, field

import numpy as np

from ..errors import BFPSFInputError, BFPSFValueError, integer_at_least
from ..moments.result import MomentsFlag

__all__ = ["SizeColourFit", "fit_size_colour", "apply_size_colour", "correct_size_colour"]


@dataclass(frozen=True)
class SizeColourFit:
    """Polynomial fits of second moments against colour.

    Attributes
    ----------
    colour_column : str
        Name of the colour column.
    degree : int
        Polynomial degree.
    coefficients : dict
        ``{'mxx': array, 'myy': array[, 'mxy': array]}``, highest power first (`numpy.polyval`
        order), pixel^2 per mag^k.
    covariance : dict
        Covariance of each coefficient vector, from the residual scatter.
    errors : dict
        ``sqrt(diag(covariance))`` of each.
    colour_reference : float
        Median colour of the fit sample, mag: the correction vanishes there.
    n_stars : int
        Stars used in the fit.
    max_peak_e : float
        Peak limit of the fit sample, electrons.
    residual_rms : dict
        RMS of the fit residuals, pixel^2.
    peak_coefficients : dict
        ``{moment: (k, k_err)}`` of the nuisance peak term, pixel^2 per 100 ke- (empty when
        fitted without it).
    """

    colour_column: str
    degree: int
    coefficients: dict
    covariance: dict
    errors: dict
    colour_reference: float
    n_stars: int
    max_peak_e: float
    residual_rms: dict = field(default_factory=dict)
    peak_coefficients: dict = field(default_factory=dict)

    def correction(self, colour, moment="mxx"):
        """``p(c) - p(c_ref)`` for ``moment`` at ``colour``, pixel^2."""
        coefficients = self.coefficients[moment]
        return (np.polyval(coefficients, np.asarray(colour, dtype=float))
                - np.polyval(coefficients, self.colour_reference))

    def as_dict(self):
        """JSON-friendly summary."""
        return {
            "colour_column": self.colour_column, "degree": self.degree,
            "coefficients": {key: list(map(float, value))
                             for key, value in self.coefficients.items()},
            "errors": {key: list(map(float, value)) for key, value in self.errors.items()},
            "colour_reference": float(self.colour_reference), "n_stars": int(self.n_stars),
            "max_peak_e": float(self.max_peak_e),
            "residual_rms": {key: float(value) for key, value in self.residual_rms.items()},
            "peak_coefficients": {key: list(value)
                                  for key, value in self.peak_coefficients.items()},
        }


def _column(table, name):
    if name not in table.colnames:
        msg = f"the star table has no column {name!r} (columns: {table.colnames})"
        raise BFPSFInputError(msg, name)
    return np.asarray(table[name], dtype=float)


def fit_size_colour(table, colour_column, *, max_peak_e=None, low_flux_fraction=0.5,
                    degree=1, fit_mxy=False, peak_term=True, flag_mask=None):
    """Fit Mxx and Myy against colour on low-flux stars (G15 section 3.3).

    Parameters
    ----------
    table : astropy.table.Table
        Star table with ``mxx``, ``myy``, ``peak_e``, the colour column and ``flags``.
    colour_column : str
        Colour column, mag (e.g. ``'g_i'``).
    max_peak_e : float, optional
        Stars with peak at or below this (electrons) form the fit sample. Default: the
        ``low_flux_fraction`` quantile of the clean stars' peaks.
    low_flux_fraction : float, optional
        Fraction of the stars (faintest first) used when ``max_peak_e`` is None (default 0.5).
        BF on those stars adds to the correction a term correlated with colour only through
        flux, which is small when the sample is faint.
    degree : int, optional
        Polynomial degree (default 1: linear, as G15).
    fit_mxy : bool, optional
        Also fit Mxy (default False).
    peak_term : bool, optional
        Fit a nuisance term linear in peak jointly (default True, module docstring); it is
        reported in ``peak_coefficients`` (pixel^2 per 100 ke-) and not subtracted.
    flag_mask : int, optional
        Stars with these flag bits are left out (default: all bits except ``BAD_PIXELS``).

    Returns
    -------
    SizeColourFit
    """
    integer_at_least("degree", degree, 0)
    if not 0 < low_flux_fraction <= 1:
        msg = f"low_flux_fraction must be in (0, 1], got {low_flux_fraction!r}"
        raise BFPSFValueError(msg, low_flux_fraction)
    colour = _column(table, colour_column)
    peak = _column(table, "peak_e")
    flag_mask = ~MomentsFlag.BAD_PIXELS if flag_mask is None else flag_mask
    flags = (np.asarray(table["flags"], dtype=np.int64) if "flags" in table.colnames
             else np.zeros(len(table), dtype=np.int64))
    moments = {name: _column(table, name) for name in
               (("mxx", "myy", "mxy") if fit_mxy else ("mxx", "myy"))}
    clean = ((flags & flag_mask) == 0) & np.isfinite(colour) & np.isfinite(peak)
    for values in moments.values():
        clean &= np.isfinite(values)
    if max_peak_e is None:
        if not np.any(clean):
            msg = "no clean star with a finite colour to fit the size-colour relation"
            raise BFPSFValueError(msg, colour_column)
        max_peak_e = float(np.quantile(peak[clean], low_flux_fraction))
    sample = clean & (peak <= max_peak_e)
    n_stars = int(sample.sum())
    n_needed = degree + 3 + int(peak_term)
    if n_stars < n_needed:
        msg = (f"the size-colour fit of degree {degree} needs at least {n_needed} clean "
               f"stars with peak <= {max_peak_e:g} e-, got {n_stars}")
        raise BFPSFValueError(msg, n_stars)
    coefficients, covariance, errors, residual_rms, peak_coefficients = {}, {}, {}, {}, {}
    # design: colour powers (highest first, numpy.polyval order) [+ peak / 100 ke-]
    columns = [colour[sample]**power for power in range(int(degree), -1, -1)]
    if peak_term:
        columns.append(peak[sample] / 1e5)
    design = np.stack(columns, axis=1)
    normal_inverse = np.linalg.inv(design.T @ design)
    n_colour = int(degree) + 1
    for name, values in moments.items():
        solution = normal_inverse @ design.T @ values[sample]
        residual = values[sample] - design @ solution
        scatter2 = residual @ residual / (n_stars - design.shape[1])
        cov = normal_inverse * scatter2
        coefficients[name] = solution[:n_colour]
        covariance[name] = cov[:n_colour, :n_colour]
        errors[name] = np.sqrt(np.diag(cov))[:n_colour]
        residual_rms[name] = float(np.sqrt(np.mean(residual**2)))
        if peak_term:
            peak_coefficients[name] = (float(solution[-1]), float(np.sqrt(cov[-1, -1])))
    return SizeColourFit(colour_column=colour_column, degree=int(degree),
                         coefficients=coefficients, covariance=covariance, errors=errors,
                         colour_reference=float(np.median(colour[sample])), n_stars=n_stars,
                         max_peak_e=float(max_peak_e), residual_rms=residual_rms,
                         peak_coefficients=peak_coefficients)


def apply_size_colour(table, fit):
    """Subtract a size-colour fit from every star; returns a new table.

    ``mxx``, ``myy`` (and ``mxy`` if fitted) become ``M - (p(c) - p(c_ref))``; ``sigma_x``,
    ``sigma_y`` and ``iq`` are recomputed from them; the uncorrected moments are kept as
    ``mxx_raw`` etc. Stars without a finite colour are left uncorrected (their colour is NaN,
    so their corrected moments would be NaN; they keep the raw value and ``colour_corrected``
    is False).
    """
    corrected = table.copy()
    colour = _column(table, fit.colour_column)
    has_colour = np.isfinite(colour)
    for name in fit.coefficients:
        raw = _column(table, name)
        corrected[f"{name}_raw"] = raw
        shift = np.where(has_colour, fit.correction(np.where(has_colour, colour, 0.0), name),
                         0.0)
        corrected[name] = raw - shift
    mxx, myy, mxy = (np.asarray(corrected[name], dtype=float) for name in ("mxx", "myy", "mxy"))
    with np.errstate(invalid="ignore"):
        corrected["sigma_x"] = np.sqrt(mxx)
        corrected["sigma_y"] = np.sqrt(myy)
        corrected["iq"] = (mxx * myy - mxy**2) ** 0.25
    corrected["colour_corrected"] = has_colour
    corrected.meta["size_colour_fit"] = fit.as_dict()
    return corrected


def correct_size_colour(table, colour_column, **kwargs):
    """Fit (`fit_size_colour`) and subtract (`apply_size_colour`) in one call.

    Returns
    -------
    tuple
        ``(corrected_table, SizeColourFit)``.
    """
    fit = fit_size_colour(table, colour_column, **kwargs)
    return apply_size_colour(table, fit), fit
