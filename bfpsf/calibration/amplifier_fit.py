"""One amplifier's calibration: measure each flat pair (`measure_pair`, a parallel task) and fit
the PTC, pedestal, linearity and boundary shifts of its pairs (`fit_measured_pairs`,
`fit_amplifier`)."""

from dataclasses import dataclass, replace

import numpy as np

from ..errors import BFPSFCovarianceError, BFPSFInputError, BFPSFValueError
from .boundary_shifts import SHIFT_METHODS, shift_warnings, solve_boundary_shifts
from .covariance import pair_covariance
from .flat_mask import pair_mask
from .flats import check_pair
from .linearity import measure_linearity
from .maxlag import choose_maxlag
from .pedestal import measure_pedestal, subtract_pedestal
from .product import Calibration
from .ptc import covariance_errors, detect_turnoff, fit_ptc, ptc_table, stack_pairs
from .ptc_full import MAX_FULL_MODEL_MAXLAG, MIN_PAIRS_FULL_MODEL

__all__ = ["PairTask", "FitTask", "measure_pair", "fit_measured_pairs", "fit_amplifier"]


@dataclass(frozen=True, eq=False)
class PairTask:
    """What a worker needs to measure one flat pair (`measure_pair`)."""

    pair: object
    saturation: object
    maxlag: int
    clip_nsigma: float
    mean_tolerance: float
    overscan: str
    edge: int


def measure_pair(task):
    """Read a pair (if not in memory), check it, mask it and measure its covariances.

    Returns
    -------
    ((str, str), PairCovariance, MaskReport)
        The names of the two flats and their measurements: an entry of `FitTask`.
    """
    flat1 = task.pair.flat1.load(overscan=task.overscan)
    flat2 = task.pair.flat2.load(overscan=task.overscan)
    for flat in (flat1, flat2):
        low, high = flat.data.min(), flat.data.max()
        if not (np.isfinite(low) and np.isfinite(high)):  # rare: look at the finite pixels
            finite = flat.data[np.isfinite(flat.data)]
            low, high = (finite.min(), finite.max()) if finite.size else (np.nan, np.nan)
        if not high > low:
            msg = f"flat {flat.name} has zero variance (a constant image), not a flat-field exposure"
            raise BFPSFInputError(msg, flat.name)
    check_pair(flat1, flat2, task.mean_tolerance)
    mask, report = pair_mask(flat1, flat2, saturation=task.saturation, edge=task.edge)
    covariance = pair_covariance(flat1, flat2, mask=mask, maxlag=task.maxlag,
                                 clip_nsigma=task.clip_nsigma)
    if not covariance.var_adu > 0:
        msg = (f"flats {flat1.name} and {flat2.name} are identical (their difference "
               "has zero variance): a pair needs two exposures")
        raise BFPSFInputError(msg, (flat1.name, flat2.name))
    return task.pair.names, covariance, report


def lags_to_measure(flats, maxlag, edge=0):
    """The lag to measure the covariances to: ``maxlag``, or for ``'auto'`` the largest the
    flats (inside their ``edge`` border) and the full model allow (`MAX_FULL_MODEL_MAXLAG`);
    `BFPSFInputError` if a flat is too small."""
    if maxlag == "auto":
        smallest = min(flats, key=lambda flat: min(flat.shape), default=None)
        if smallest is None:
            return 1
        maxlag = max(1, min(MAX_FULL_MODEL_MAXLAG, (min(smallest.shape) - 2 * edge) // 2 - 1))
    for flat in flats:
        _check_size(flat, maxlag, edge)
    return maxlag


def _check_size(flat, maxlag, edge):
    """Raise `BFPSFInputError` if ``flat`` is too small for the lags ``maxlag`` inside its
    ``edge`` border."""
    ny, nx = flat.shape
    inner = min(ny, nx) - 2 * edge
    if inner < 2 * maxlag + 2:
        border = f" inside its {edge}-pixel edge border (--edge)" if edge else ""
        msg = (f"flat {flat.name} ({nx} x {ny} pixels) is too small for maxlag {maxlag}"
               f"{border}: give maxlag < {max(inner, 0) // 2}"
               + (" or a smaller edge" if edge else ""))
        raise BFPSFInputError(msg, flat.name)


def fit_task(parameters, options, owner, measured):
    """The `FitTask` of amplifier ``owner`` = (detector, amplifier) from its measured pairs."""
    return FitTask(owner[1], list(measured), dict(parameters), options)


@dataclass(frozen=True, eq=False)
class FitTask:
    """What a worker needs to fit one amplifier (`fit_measured_pairs`): its name, its
    ((name1, name2), PairCovariance, MaskReport) entries, the parameters and the fit
    options."""

    amplifier: str
    entries: list
    parameters: dict
    options: dict


def fit_measured_pairs(task):
    """`fit_amplifier` of the measured pairs of one amplifier (a `FitTask`)."""
    amplifier, entries, parameters, options = (task.amplifier, task.entries, task.parameters,
                                               task.options)
    covariances = [covariance for _, covariance, _ in entries]
    result = fit_amplifier(
        stack_pairs(covariances), parameters, amplifier=amplifier,
        names=[names for names, _, _ in entries],
        n_masked=[report.total for _, _, report in entries],
        n_clipped=[int(getattr(covariance, "n_clipped", 0)) for covariance in covariances],
        **options)
    # non-finite pixels are masked, and said so (a NaN block is a damaged flat, not noise)
    nonfinite = [(names, report.nonfinite) for names, _, report in entries if report.nonfinite]
    if nonfinite:
        (first, second), count = max(nonfinite, key=lambda item: item[1])
        note = (f"non-finite pixels masked in {len(nonfinite)} flat pair(s), the most ({count}) "
                f"in {first} and {second}")
        result = replace(result, warnings=(*result.warnings, note))
    return result


def fit_amplifier(data, parameters, *, amplifier="", names, n_masked, n_clipped, ptc_model,
                  fit_b, pedestal_nsigma, pedestal_degree, linearity_threshold, solve_shifts,
                  shift_method="electrostatic", thickness=10.0, n_monte_carlo, seed):
    """The PTC fit, linearity, pedestal and shifts of one amplifier from its pair statistics.

    Parameters
    ----------
    data : bfpsf.calibration.ptc.PTCData
        Per-pair exposure times, means and covariances (ADU).
    parameters : dict
        The parameters to record in the product (completed here).
    amplifier : str
    names : sequence of (str, str)
        The two flats of each pair.
    n_masked, n_clipped : sequence of int
        Pixels masked and clipped in each pair.
    Others
        As `calibrate`.

    Returns
    -------
    Calibration
    """
    # The pedestal is the zero-flux intercept of R = C / V, measured below the PTC extremum.
    below, _ = detect_turnoff(data.mean_adu, data.var_adu,
                              covariance_errors(data.cov_adu, data.npix)[:, 0, 0])
    data = _fitted_lags(data, below, parameters, ptc_model)
    pedestal = measure_pedestal(data.mean_adu[below], data.cov_adu[below], data.npix[below],
                                nsigma=pedestal_nsigma, degree=pedestal_degree)
    corrected = data.with_covariances(subtract_pedestal(data.cov_adu, pedestal))
    fit = fit_ptc(corrected, model=ptc_model, fit_b=fit_b, pedestal=pedestal)
    _check_gain(fit.gain, data.exptime, names, amplifier)
    linearity = measure_linearity(data.exptime, data.mean_adu, used=fit.used,
                                  threshold=linearity_threshold)

    table = ptc_table(data, fit.gain, fit.used)
    table["name1"] = [str(pair[0]) for pair in names]
    table["name2"] = [str(pair[1]) for pair in names]
    table["n_masked"] = np.array(n_masked, dtype=np.int64)
    table["n_clipped"] = np.array(n_clipped, dtype=np.int64)

    solved = _solve_shifts(fit, shift_method, thickness, n_monte_carlo, seed,
                           parameters) if solve_shifts else None
    parameters["shifts_solved"] = solved is not None
    warnings = [] if solved is None else list(solved["warnings"])
    if solve_shifts and solved is None:
        warnings.append("no measurable brighter-fatter in these flats: the calibration has no "
                        f"boundary shifts ({parameters['shifts_failure']})")
    if fit.model == "full" and len(names) < MIN_PAIRS_FULL_MODEL:
        warnings.insert(0, f"the full PTC model is under-constrained by {len(names)} flat "
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
        inputs=[str(name) for pair in names for name in pair], parameters=parameters,
        amplifier=amplifier)


#: Exposure levels the photon transfer curve needs: its gain, read noise and a(0, 0) are three
#: parameters of the variance against the mean (G15 eq. ptc).
MIN_PTC_LEVELS = 3


def _check_gain(gain, exptimes, names, amplifier):
    """A PTC fit that cannot give the gain is refused, not written: flats at fewer than
    `MIN_PTC_LEVELS` exposure levels, or whose variance does not grow with their mean, give
    any gain (a new user's two levels gave -0.046 e-/ADU, another pair 0.005 for a true 1.5),
    and every electron count made with it would be wrong."""
    levels = np.unique(np.asarray(exptimes, float)).size
    if levels >= MIN_PTC_LEVELS and np.isfinite(gain) and gain > 0:
        return
    where = f" of amplifier {amplifier}" if amplifier else ""
    msg = (f"the photon transfer curve of flats {names[0][0]} ... {names[-1][-1]}{where} "
           f"({len(names)} pairs at {levels} exposure level(s)) gives a gain of {gain:.4g} "
           f"e-/ADU: the flats do not constrain it (it needs pairs at {MIN_PTC_LEVELS} or more "
           f"levels over the flux range, their variance growing with their mean)")
    raise BFPSFInputError(msg, gain)


def _fitted_lags(data, below, parameters, ptc_model):
    """``data`` to the lags fitted: for ``maxlag='auto'`` those the flats constrain
    (`bfpsf.calibration.maxlag.choose_maxlag`, on the pairs below the turnoff), recorded in
    ``parameters`` (``maxlag``, ``maxlag_auto``, ``maxlag_ring_sigma``, ``maxlag_reason``)."""
    parameters["maxlag_auto"] = parameters["maxlag"] == "auto"
    if not parameters["maxlag_auto"]:
        parameters["maxlag"] = data.maxlag
        return data
    data = data.to_maxlag(min(data.maxlag, MAX_FULL_MODEL_MAXLAG))
    choice = choose_maxlag(data.mean_adu[below], data.cov_adu[below], data.npix[below],
                           model=ptc_model, min_pairs_full_model=MIN_PAIRS_FULL_MODEL)
    parameters.update(maxlag=choice.maxlag, maxlag_reason=choice.reason,
                      maxlag_ring_sigma=[round(float(value), 2)
                                         for value in choice.significance])
    return data.to_maxlag(choice.maxlag)


def _solve_shifts(fit, method, thickness, n_samples, seed, parameters):
    """Solve a^X with the chosen method, and the other one for its chi2 on the same a.

    Returns a dict (shifts, errors, samples, scalars, warnings), or None with the reason in
    ``parameters['shifts_failure']`` when the flats show no brighter-fatter signal (a(0, 0)
    >= 0): a measurement failure, not a usage error, so the calibration is still returned.
    """
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
