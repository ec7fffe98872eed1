"""Flat-field calibration (the first stage of the data flow in DESIGN.md; G15 sections 4 and 6.1).

`calibrate` runs the whole stage: ingest and pair the flats (`flats`), mask them and measure
the covariances of each pair difference (`covariance`), measure and subtract the readout
pedestal (`pedestal`), fit the photon transfer curve and the area coefficients a(dx, dy)
(`ptc`), check linearity (`linearity`), solve the boundary shifts a^X(dx, dy)
(`coefficients`), and return a `~bfpsf.calibration.product.Calibration`.
"""

import os

import numpy as np

from ..errors import BFPSFCovarianceError, BFPSFInputError, BFPSFValueError
from ..files import refuse_duplicates

__all__ = ["calibrate"]

#: Largest maxlag of the full PTC model: its convolution tensor holds 8 (maxlag + 1)^6 bytes and
#: the fit's time grows as fast (maxlag 8: 1.3 s; 16: 106 s and 190 MB; 60: 384 GiB).
MAX_FULL_MODEL_MAXLAG = 12

#: Fewest flat pairs for the full PTC model (a, b and the noise at every lag): with fewer the
#: fit is under-constrained (4 levels at maxlag 8 gave a gain 13 % high and 27 e- read noise).
MIN_PAIRS_FULL_MODEL = 8


def _progress(iterable, enabled, total, description):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=description, unit="pair")


def calibrate(sources, *, exptimes=None, maxlag=8, ptc_model="full", fit_b="off-origin",
              saturation=None, mean_tolerance=0.05, clip_nsigma=4.0, pedestal_nsigma=4.0,
              pedestal_degree=2, linearity_threshold=None, solve_shifts=True,
              shift_method="electrostatic", thickness=10.0, n_monte_carlo=100, seed=0,
              progress=False):
    """Calibrate brighter-fatter from flat-field pairs.

    Parameters
    ----------
    sources : sequence of str, path, ndarray or Flat
        Bias-subtracted flats in ADU (FITS files with header EXPTIME, or arrays with
        ``exptimes``). Flats of equal EXPTIME are paired in the order given.
    exptimes : sequence of float, optional
        Exposure times, s, one per source (required for arrays; overrides EXPTIME).
    maxlag : int, optional
        Largest lag |dx|, |dy| of the covariances and of a(dx, dy). Default 8.
    ptc_model : {'full', 'exponential', 'quadratic'}, optional
        PTC model (`bfpsf.calibration.ptc`). Default ``'full'``: Astier et al. 2019 eq. 20,
        free of the first-order bias of G15's slopes.
    fit_b : {'off-origin', 'all', 'none'} or bool, optional
        Lags whose A+19 b term (flux dependence of a) is fitted in the full model. Default
        ``'off-origin'`` (b(0, 0) is nearly degenerate with the gain; see
        `bfpsf.calibration.ptc.fit_full_covariance_model`).
    saturation : float, optional
        Saturation level, ADU; pixels at or above it are masked. Default None.
    mean_tolerance : float, optional
        Largest relative difference of the two means of a pair. Default 0.05.
    clip_nsigma : float, optional
        Sigma clipping of the pair differences. Default 4.
    pedestal_nsigma : float, optional
        Significance above which a readout pedestal is subtracted. Default 4.
    pedestal_degree : int, optional
        Degree in flux of the correlation fit whose intercept is the pedestal. Default 2.
    linearity_threshold : float, optional
        Peak-to-peak fractional non-linearity that raises the linearity flag. Default
        `bfpsf.calibration.linearity.DEFAULT_LINEARITY_THRESHOLD` (3e-3).
    solve_shifts : bool, optional
        Solve the boundary shifts a^X. Default True.
    shift_method : {'electrostatic', 'ei'}, optional
        Solver of the shifts (`bfpsf.calibration.boundary_shifts`). Default
        ``'electrostatic'`` (Astier & Regnault 2023); ``'ei'`` is G15's section 6.1. Both are
        run; the other's chi2 is reported in ``shift_fit``.
    thickness : float, optional
        Sensor thickness in pixels for the electrostatic model. Default 10 (100 um sensors
        with 10 um pixels).
    n_monte_carlo : int, optional
        Samples of the shifts drawn from the calibration error (kept in the product and
        propagated to every prediction). Default 100.
    seed : int, optional
        Seed of the samples. Default 0.
    progress : bool, optional
        Show a progress bar over the pairs. Default False.

    Returns
    -------
    Calibration
        Gain (e-/ADU), read noise (e-), a and a_err (1/e-), shifts, PTC table, linearity,
        pedestal; see `~bfpsf.calibration.product.Calibration`.
    """
    from .boundary_shifts import SHIFT_METHODS
    from .covariance import pair_covariance
    from .flats import pair_flats, pair_mask, read_flats
    from .linearity import DEFAULT_LINEARITY_THRESHOLD, measure_linearity
    from .pedestal import measure_pedestal, subtract_pedestal
    from .product import Calibration
    from .ptc import (PTC_MODELS, _b_mask, covariance_errors, detect_turnoff, fit_ptc,
                      ptc_table, stack_pairs)

    if int(maxlag) != maxlag or maxlag < 1:
        msg = f"maxlag must be a positive integer, got {maxlag!r}"
        raise BFPSFValueError(msg, maxlag)
    maxlag = int(maxlag)
    if ptc_model not in PTC_MODELS:
        msg = f"ptc_model must be one of {PTC_MODELS}, got {ptc_model!r}"
        raise BFPSFValueError(msg, ptc_model)
    if ptc_model == "full" and maxlag > MAX_FULL_MODEL_MAXLAG:
        msg = (f"maxlag {maxlag} is too large for the full PTC model: its memory and time grow "
               f"as (maxlag + 1)^6 ({8 * (maxlag + 1) ** 6 / 2**30:.3g} GiB here); use maxlag "
               f"<= {MAX_FULL_MODEL_MAXLAG} or the exponential PTC model")
        raise BFPSFValueError(msg, maxlag)
    _b_mask(fit_b, 1)  # validates fit_b before the work
    if shift_method not in SHIFT_METHODS:
        msg = f"shift_method must be one of {SHIFT_METHODS}, got {shift_method!r}"
        raise BFPSFValueError(msg, shift_method)
    if linearity_threshold is None:
        linearity_threshold = DEFAULT_LINEARITY_THRESHOLD
    parameters = {
        "maxlag": maxlag, "ptc_model": ptc_model,
        "fit_b": fit_b if isinstance(fit_b, str) else bool(fit_b),
        "saturation": None if saturation is None else float(saturation),
        "mean_tolerance": float(mean_tolerance), "clip_nsigma": float(clip_nsigma),
        "pedestal_nsigma": float(pedestal_nsigma), "pedestal_degree": int(pedestal_degree),
        "linearity_threshold": float(linearity_threshold), "solve_shifts": bool(solve_shifts),
        "shift_method": str(shift_method), "thickness": float(thickness),
        "n_monte_carlo": int(n_monte_carlo), "seed": int(seed),
    }

    if not isinstance(sources, (str, os.PathLike, np.ndarray)):
        refuse_duplicates([source for source in sources if isinstance(source, (str, os.PathLike))],
                          "flat")
    flats = read_flats(sources, exptimes)
    for flat in flats:
        if flat.data.shape[0] < 2 * maxlag + 2 or flat.data.shape[1] < 2 * maxlag + 2:
            msg = (f"flat {flat.name} ({flat.data.shape[1]} x {flat.data.shape[0]} pixels) is too "
                   f"small for maxlag {maxlag}: give maxlag < {min(flat.data.shape) // 2}")
            raise BFPSFInputError(msg, flat.name)
        finite = flat.data[np.isfinite(flat.data)]
        if finite.size == 0 or np.ptp(finite) == 0:
            msg = f"flat {flat.name} has zero variance (a constant image), not a flat-field exposure"
            raise BFPSFInputError(msg, flat.name)
    pairs = pair_flats(flats, mean_tolerance=mean_tolerance)
    covariances, reports = [], []
    for pair in _progress(pairs, progress, len(pairs), "flat pairs"):
        mask, report = pair_mask(pair.flat1, pair.flat2, saturation=saturation)
        covariances.append(pair_covariance(pair.flat1, pair.flat2, mask=mask, maxlag=maxlag,
                                           clip_nsigma=clip_nsigma))
        if not covariances[-1].var_adu > 0:
            msg = (f"flats {pair.names[0]} and {pair.names[1]} are identical (their difference "
                   "has zero variance): a pair needs two exposures")
            raise BFPSFInputError(msg, pair.names)
        reports.append(report)
    data = stack_pairs(covariances)

    # The pedestal is the zero-flux intercept of R = C / V, measured below the PTC extremum.
    below, _ = detect_turnoff(data.mean_adu, data.var_adu,
                              covariance_errors(data.cov_adu, data.npix)[:, 0, 0])
    pedestal = measure_pedestal(data.mean_adu[below], data.cov_adu[below], data.npix[below],
                                nsigma=pedestal_nsigma, degree=pedestal_degree)
    corrected = data.with_covariances(subtract_pedestal(data.cov_adu, pedestal))
    fit = fit_ptc(corrected, model=ptc_model, fit_b=fit_b, pedestal=pedestal)
    linearity = measure_linearity(data.exptime, data.mean_adu, used=fit.used,
                                  threshold=linearity_threshold)

    table = ptc_table(data, fit.gain, fit.used)
    table["name1"] = [pair.names[0] for pair in pairs]
    table["name2"] = [pair.names[1] for pair in pairs]
    table["n_masked"] = np.array([report.total for report in reports], dtype=np.int64)
    table["n_clipped"] = np.array([int(getattr(cov, "n_clipped", 0)) for cov in covariances],
                                  dtype=np.int64)

    solved = _solve_shifts(fit, shift_method, thickness, n_monte_carlo, seed,
                           parameters) if solve_shifts else None
    parameters["shifts_solved"] = solved is not None
    warnings = [] if solved is None else list(solved["warnings"])
    if solve_shifts and solved is None:
        warnings.append("no measurable brighter-fatter in these flats: the calibration has no "
                        f"boundary shifts ({parameters['shifts_failure']})")
    if fit.model == "full" and len(pairs) < MIN_PAIRS_FULL_MODEL:
        warnings.insert(0, f"the full PTC model is under-constrained by {len(pairs)} flat "
                           f"pairs (gain, read noise and a can be biased); give at least "
                           f"{MIN_PAIRS_FULL_MODEL} pairs over the flux range or use --model "
                           "exponential")
    solved = solved or {}

    return Calibration(
        gain=fit.gain, gain_err=fit.gain_err, noise_e=fit.noise_e, noise_e_err=fit.noise_e_err,
        a=fit.a, a_err=fit.a_err, b=fit.b, b_err=fit.b_err, noise_matrix_e2=fit.noise_matrix_e2,
        ptc=table, linearity=linearity, pedestal=pedestal, model=fit.model,
        turnoff_e=fit.turnoff_e, turnoff_detected=fit.turnoff_detected, chi2=fit.chi2,
        ndof=fit.ndof, shifts=solved.get("shifts"), shifts_north_err=solved.get("north_err"),
        shifts_east_err=solved.get("east_err"), shift_fit=solved.get("fit", {}),
        shift_samples_north=solved.get("samples_north"),
        shift_samples_east=solved.get("samples_east"),
        shift_method=shift_method if solved else None, warnings=warnings,
        covariances_adu=data.cov_adu, npix=data.npix,
        inputs=[name for pair in pairs for name in pair.names], parameters=parameters)


def _solve_shifts(fit, method, thickness, n_samples, seed, parameters):
    """Solve a^X with the chosen method, and the other one for its chi2 on the same a.

    Returns a dict (shifts, errors, samples, scalars, warnings), or None with the reason in
    ``parameters['shifts_failure']`` when the flats show no brighter-fatter signal (a(0, 0)
    >= 0): a measurement failure, not a usage error, so the calibration is still returned.
    """
    from .boundary_shifts import SHIFT_METHODS, shift_warnings, solve_boundary_shifts

    area, area_err, area_cov = np.array(fit.a), np.array(fit.a_err), fit.a_cov
    if not area[0, 0] < 0:
        parameters["shifts_failure"] = (f"the flats show no brighter-fatter effect "
                                        f"(a(0,0) = {area[0, 0]:.3g} >= 0)")
        return None
    parameters["shift_error_covariance"] = "full" if area_cov is not None else "diagonal"
    scalars = {}
    for other in SHIFT_METHODS:
        if other == method:
            continue
        try:
            alternative = solve_boundary_shifts(area, area_err, area_cov=area_cov, method=other,
                                                n_samples=0, thickness=thickness)
        except BFPSFValueError as error:
            parameters[f"{other}_failure"] = str(error)
            continue
        scalars.update(_scalar_fields(alternative, other))
    try:
        solution = solve_boundary_shifts(area, area_err, area_cov=area_cov, method=method,
                                         n_samples=n_samples, seed=seed, thickness=thickness)
    except BFPSFCovarianceError:
        if area_cov is None:
            raise
        # a PTC-fit covariance the solver cannot use (not positive semi-definite)
        parameters["shift_error_covariance"] = "diagonal"
        solution = solve_boundary_shifts(area, area_err, method=method, n_samples=n_samples,
                                         seed=seed, thickness=thickness)
    scalars.update(_scalar_fields(solution, method))
    return {"shifts": solution.shifts, "north_err": solution.north_err,
            "east_err": solution.east_err, "samples_north": solution.samples_north,
            "samples_east": solution.samples_east, "fit": scalars,
            "warnings": shift_warnings(solution)}


def _scalar_fields(solution, prefix):
    """The scalars of a shift solution worth keeping, as ``{prefix}_{name}``."""
    values = {"chi2": solution.chi2, "dof": solution.dof}
    if prefix == "electrostatic":
        values.update(solution.geometry.as_dict())
        values.update(alpha=solution.alpha, error_scale=solution.error_scale)
    else:
        values.update(p0=solution.p0, p1=solution.p1, p1_err=solution.p1_err,
                      far_scale=solution.far_scale,
                      truncation_residual=solution.truncation_residual)
        values.update({f"sensitivity_{key}": value
                       for key, value in solution.sensitivity.items() if np.ndim(value) == 0})
    return {f"{prefix}_{name}": float(value) for name, value in values.items()}
