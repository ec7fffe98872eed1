"""Do the stars grow with flux as the calibration says? The stars' own brighter-fatter against
the one P(F) predicts, axis by axis, at `bfpsf psf` (`bf_agreement`).

A calibration from too few flats, from another sensor or setting, or missing an effect the
stars show gives a P(F) whose BF is wrong: a new user's nine 150^2 E2V flat pairs gave shifts
whose BF was 6 times (x) and 2.2 times (y) the stars' own, and `bfpsf psf` said "converged"
(only `bfpsf slope --psf` showed it, a residual of -512 % of the raw slope). Here each star's
measured size less its model's at F -> 0 (P0 at its position and phase) is fitted against the
growth P(F) predicts for it, with an intercept per image (the stars the one slope fitter,
`bfpsf.measure.slopes.fit_bf_slope`, keeps after its 5-sigma clipping; the stars' moment
errors) and, where the Bayesian information criterion asks for it, a level under the stars
per image (an error of the sky makes the faint stars large by ``4 pi level sigma^2 / F``):
the slope is the ratio of the stars' BF to the model's, 1 when the calibration describes them.
On a new user's BF-free stars (SiliconSensor at strength 1e-6, four exposures) it read
0.10 +- 0.08 (x) and 0.13 +- 0.05 (y) on average: a floor well below `BF_AGREEMENT_TOLERANCE`.
"""

import numpy as np

from ..errors import BFPSFValueError
from ..least_squares import weighted_least_squares
from ..moments.moment_errors import moment_errors
from ..moments.shapes import psf_shapes, stars_beside_psf
from .slopes import PEAK_UNIT_E, fit_bf_slope

__all__ = ["BF_AGREEMENT_SIGMA", "BF_AGREEMENT_TOLERANCE", "bf_agreement", "disagreeing_axes"]

#: `disagreeing_axes`: the stars' BF differs from the model's beyond this many errors of the
#: ratio ...
BF_AGREEMENT_SIGMA = 5.0
#: ... and by more than this fraction of the model's. Measured: 1.02 +- 0.04 with the true
#: shifts (`tests/test_photometry.py`, GalSim CDModel); 1.07 +- 0.15 (x) and 1.09 +- 0.10 (y)
#: on a new user's crowded control field with one 150^2 flat pair per level; 2.04 +- 0.39 and
#: 1.64 +- 0.16 with a smear outside the catalogue of +165 % and +64 % of BF's slope.
BF_AGREEMENT_TOLERANCE = 0.3


def bf_agreement(images, stars, psf, *, beside=None):
    """The stars' brighter-fatter over the model's, along x and y.

    Parameters
    ----------
    images : list of bfpsf.measure.prepare.PreparedImage
        The images the stars lie on (their ``sky_subtracted`` pixels are measured; the sky's
        ``rms`` is the background noise of the moment errors).
    stars : astropy.table.Table
        ``image`` (index into ``images``), ``x_fit``, ``y_fit``, ``flux_fit`` (e-): the stars
        P0 was fitted from.
    psf : bfpsf.model.base.BFPSFModel
        The fitted model, in electrons.
    beside : list of dict, optional
        Per image, ``stars`` measured beside ``psf`` already
        (`bfpsf.moments.shapes.stars_beside_psf`, as `bfpsf.workflow.psf_from_images` keeps
        them); default measured here.

    Returns
    -------
    dict or None
        Per axis ``'x'``, ``'y'``: ``ratio`` and ``ratio_err`` (the stars' BF over the model's,
        with the fit's error scaled by its chi2), ``measured_px`` and ``predicted_px`` (the
        growth of sigma along the axis from F -> 0 to the brightest star fitted: the ratio
        times the model's, and the model's), ``n`` stars fitted, ``n_clipped`` and
        ``sky_level_fitted`` (whether a level under the stars was fitted). None with fewer
        than 3 measurable stars, or a model whose BF changes nothing (``--no-bf``).
    """
    rows = {key: [] for key in ("image", "grow_x", "grow_y", "meas_x", "meas_y", "err_x",
                                "err_y", "light_x", "light_y")}
    for index, prepared in enumerate(images):
        mine = stars[np.asarray(stars["image"], dtype=int) == index]
        measured_here = beside[index] if beside is not None else stars_beside_psf(
            prepared.sky_subtracted, mine["x_fit"], mine["y_fit"], mine["flux_fit"], psf)
        x, y, flux = measured_here["x"], measured_here["y"], measured_here["flux"]
        if not flux.size:
            continue
        measured, bright = measured_here["measured"], measured_here["model"]
        noise = prepared.sky.rms if np.isfinite(prepared.sky.rms) else 0.0
        errors = moment_errors(measured_here["stamps"], measured,
                               background_variance=noise**2)
        faint = psf_shapes(psf, np.zeros(flux.size), x, y)
        good = (measured.flags == 0) & (bright["flags"] == 0) & (faint["flags"] == 0)
        rows["image"].append(np.full(int(good.sum()), index))
        for axis, name in (("x", "mxx"), ("y", "myy")):
            base = np.sqrt(faint[name][good])
            rows[f"grow_{axis}"].append(np.sqrt(bright[name][good]) - base)
            rows[f"meas_{axis}"].append(np.sqrt(getattr(measured, name)[good]) - base)
            rows[f"err_{axis}"].append(errors[f"sigma_{axis}_err"][good])
            # a level under the star (the sky's error) makes it larger by this per e-
            rows[f"light_{axis}"].append(np.sqrt(getattr(measured, name)[good])
                                         * 4 * np.pi * measured.sigma[good]**2 / flux[good])
    if not rows["image"]:
        return None
    values = {key: np.concatenate(parts) for key, parts in rows.items()}
    if values["image"].size < 3:
        return None
    result = {}
    labels = np.unique(values["image"], return_inverse=True)[1]
    for axis in "xy":
        grow, light = values[f"grow_{axis}"], values[f"light_{axis}"]
        try:
            # the stars to fit: those the slope fitter keeps (5-sigma clipping); its abscissa
            # is in PEAK_UNIT_E, the model's growth in pixels
            rows_fit = fit_bf_slope(grow * PEAK_UNIT_E, values[f"meas_{axis}"],
                                    size_err=values[f"err_{axis}"], group=labels).rows
        except BFPSFValueError:  # no growth to compare with (a static model), too few stars
            return None
        # the stars' size against the model's growth, with an intercept per image and, where
        # the stars ask for it (Bayesian information criterion), a level under them per image
        # (the sky's error, which makes the faint stars large: 3 e- of it had moved the ratio
        # by 0.1-0.4 on a new user's BF-free stars)
        groups = range(labels.max() + 1)
        chosen = None
        for columns in ((1.0,), (1.0, light)):
            design = np.column_stack([grow] + [np.where(labels == k, column, 0.0)
                                               for k in groups for column in columns])[rows_fit]
            dof = design.shape[0] - design.shape[1]
            if dof < 1:
                break
            params, covariance, chi2, _ = weighted_least_squares(
                values[f"meas_{axis}"][rows_fit], values[f"err_{axis}"][rows_fit], design)
            score = chi2 + design.shape[1] * np.log(design.shape[0])
            if chosen is None or score < chosen[0]:
                chosen = (score, params, covariance, chi2, dof, len(columns) > 1)
        if chosen is None:
            return None
        _, params, covariance, chi2, dof, levels = chosen
        scale = max(1.0, np.sqrt(chi2 / dof))
        top = float(np.max(grow[rows_fit]))
        result[axis] = {"ratio": float(params[0]),
                        "ratio_err": float(np.sqrt(covariance[0, 0]) * scale),
                        "measured_px": float(params[0]) * top, "predicted_px": top,
                        "n": int(rows_fit.sum()), "n_clipped": int(np.sum(~rows_fit)),
                        "sky_level_fitted": bool(levels)}
    return result


def disagreeing_axes(agreement):
    """The axes (``'x'``, ``'y'``) where the stars' BF is not the model's: the ratio differs
    from 1 by more than `BF_AGREEMENT_SIGMA` errors and `BF_AGREEMENT_TOLERANCE`."""
    if agreement is None:
        return []
    return [axis for axis, entry in agreement.items()
            if abs(entry["ratio"] - 1.0) > max(BF_AGREEMENT_SIGMA * entry["ratio_err"],
                                               BF_AGREEMENT_TOLERANCE)]
