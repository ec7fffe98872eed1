"""The EMPIRICAL term of a refined calibration (`bfpsf.model.empirical`) in the P0 fit
(`bfpsf.model.psf_fit.fit_psf`): its part of every star's model, and its amplitude, which the
stars' pixels set.

The term's coefficients are learned from the stars' adaptive (Gaussian-weighted) sizes
(`bfpsf.diagnosis.empirical_fit`), which see how a pattern changes a star's core, not where
it puts the charge. P0 takes whatever of the bright stars the term leaves out, and gives it to
the faint ones. The fit therefore multiplies the coefficients by one amplitude, fitted with
P0 to the stars' pixels, and the PSF it returns holds the term so scaled
(`EmpiricalTerm.amplitude`). On a new user's halo of the brightest pixels (5 px) with the
broad pattern of the squared charge of reach 4 px, the sizes' coefficients moved too much
charge and the faint stars came out 3.07 mmag faint against the same stars without the halo;
at the amplitude the pixels gave (0.60-0.66) +0.05 mmag (docs/undeclared_effects.md,
"Broad patterns").
"""

import numpy as np

from .empirical import PATTERNS, pattern_series

__all__ = ["with_empirical", "amplitude_step"]


def with_empirical(term, model, d_flux, stars, amplitude=1.0):
    """Every star's table-mode model and flux derivative with the EMPIRICAL term of a
    refined calibration (`bfpsf.model.empirical`) at its flux, column and row, times
    ``amplitude``: a sum_k v_k(F, x, y) B_k[model], as `FluxDependentPSF` applies it (its
    position derivative neglected); and the term's part per unit amplitude."""
    flux = np.abs(stars.flux)
    step = 1e-3 * np.maximum(flux, 1.0)
    changes = term.variance_change(flux, x=stars.x_0, y=stars.y_0)
    slopes = [(after - before) / step for after, before in
              zip(term.variance_change(flux + step, x=stars.x_0, y=stars.y_0), changes)]
    signs = np.sign(stars.flux)[:, None, None]
    part, derivative = np.zeros_like(model), np.zeros_like(d_flux)
    for pattern, change, slope in zip(PATTERNS, changes, slopes):
        change = np.broadcast_to(change, flux.shape)[:, None, None]
        slope = np.broadcast_to(slope, flux.shape)[:, None, None]
        # the star's flux normalises the pattern (its cutout may cut the wings)
        pattern_model, along_flux = pattern_series(model, d_flux, pattern, total=stars.flux,
                                                   total_change=1.0, order=1, kind=term.kind)
        part += change * pattern_model
        derivative += change * along_flux + signs * slope * pattern_model
    return model + amplitude * part, d_flux + amplitude * derivative, part


def amplitude_step(amplitude, unit, residual, variance, used, model, flux, damping):
    """The EMPIRICAL term's amplitude after one weighted least-squares step on the stars'
    residuals after their own step, jointly with P0's: (amplitude, the residuals less the
    change of the term's part, for P0's step, the amplitude's statistical error). ``unit``
    is the term's part of every star's model per unit amplitude (None without a term:
    nothing changes, error 0); ``model`` and ``flux`` every star's.

    P0's step takes the mean per unit flux of what is left in every pixel, and each star's
    flux its share along its model, so the amplitude is fitted to the part of the term
    neither can take (the Schur complement of the blocks): stepped in turn without it, the
    two traded the term back and forth (0.02, 0.84, 0.20, 0.77, ...) and P0 settled with the
    amplitude still 0.2 short (the bench's smear: 0.67 for 0.85). Held at >= 0."""
    if unit is None:
        return amplitude, residual, 0.0
    weight = np.where(used[:, None, None], 1.0 / variance, 0.0)
    flux = np.reshape(flux, (-1, 1, 1))
    of_p0 = weight * flux**2
    total = of_p0.sum(axis=0)
    share = np.divide((of_p0 * unit / flux).sum(axis=0), total, out=np.zeros_like(total),
                      where=total > 0)
    regressor = unit - flux * share
    # and what each star's own flux takes (its model's direction)
    own = (weight * model**2).sum(axis=(1, 2))
    along = np.divide((weight * model * regressor).sum(axis=(1, 2)), own,
                      out=np.zeros_like(own), where=own > 0)
    regressor = regressor - along[:, None, None] * model
    normal = float(np.sum(weight * regressor**2))
    if not normal > 0:
        return amplitude, residual, 0.0
    new = max(amplitude + damping * float(np.sum(weight * regressor * residual)) / normal, 0.0)
    return new, residual - (new - amplitude) * unit, normal ** -0.5
