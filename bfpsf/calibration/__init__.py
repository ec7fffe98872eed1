"""Flat-field calibration (the first stage of the data flow in DESIGN.md; G15 sections 4 and 6.1).

`calibrate` runs the whole stage: ingest and pair the flats (`flats`), mask them and measure
the covariances of each pair difference (`covariance`), measure and subtract the readout
pedestal (`pedestal`), fit the photon transfer curve and the area coefficients a(dx, dy)
(`ptc`), check linearity (`linearity`), solve the boundary shifts a^X(dx, dy)
(`coefficients`), and return a `~bfpsf.calibration.product.Calibration`.
"""

import functools
import os
from dataclasses import dataclass, replace

import numpy as np

from ..errors import BFPSFCovarianceError, BFPSFInputError, BFPSFValueError
from ..files import refuse_duplicates

__all__ = ["calibrate", "calibrate_detectors", "calibrate_from_ptc", "fit_amplifier",
           "fit_measured_pairs", "measure_pair", "PairTask", "FitTask"]

#: Largest maxlag of the full PTC model: its convolution tensor holds 8 (maxlag + 1)^6 bytes and
#: the fit's time grows as fast (maxlag 8: 1.3 s; 16: 106 s and 190 MB; 60: 384 GiB).
MAX_FULL_MODEL_MAXLAG = 12

#: Fewest flat pairs for the full PTC model (a, b and the noise at every lag): with fewer the
#: fit is under-constrained (4 levels at maxlag 8 gave a gain 13 % high and 27 e- read noise).
MIN_PAIRS_FULL_MODEL = 8


def calibrate(sources, *, exptimes=None, maxlag="auto", ptc_model="full", fit_b="off-origin",
              saturation=None, mean_tolerance=0.05, clip_nsigma=4.0, pedestal_nsigma=4.0,
              pedestal_degree=2, linearity_threshold=None, solve_shifts=True,
              shift_method="electrostatic", thickness=10.0, n_monte_carlo=100, seed=0,
              progress=False, amps=None, overscan="median", workers=1, scheduler=None):
    """Calibrate brighter-fatter from flat-field pairs, each amplifier on its own.

    Returns a `~bfpsf.calibration.product.Calibration` when the flats have one amplifier
    (single-image files or arrays, or ``amps`` naming one), else a
    `~bfpsf.calibration.product.DetectorCalibration` of one per amplifier.

    Parameters
    ----------
    sources : sequence of str, path, ndarray or Flat
        Flats in ADU: FITS files with header EXPTIME (single-image bias-subtracted, or one
        HDU per amplifier with EXTNAME and optional BIASSEC / DATASEC / DETSEC:
        `bfpsf.io.amplifiers`), or arrays with ``exptimes``. Flats of one amplifier and equal
        EXPTIME are paired in the order given.
    exptimes : sequence of float, optional
        Exposure times, s, one per source (required for arrays; overrides EXPTIME).
    maxlag : 'auto' or int, optional
        Largest lag |dx|, |dy| of the covariances and of a(dx, dy). Default ``'auto'``: the
        largest lag the flats constrain, chosen per amplifier from the significance of the
        measured correlations ring by ring (`bfpsf.calibration.maxlag.choose_maxlag`; the
        covariances are measured to `MAX_FULL_MODEL_MAXLAG` or the image size first). The
        choice and the significance of each ring are recorded in ``parameters``.
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
    amps : str or sequence of str, optional
        Amplifiers (EXTNAME) to calibrate. Default: all.
    overscan : {'median', 'clipped_mean'}, optional
        Row-by-row overscan estimator where the files give a BIASSEC. Default ``'median'``.
    workers : int, optional
        Processes measuring the pairs (`bfpsf.parallel.parallel_map`; Dask above 1).
        Default 1: in this process.
    scheduler : str, optional
        Address of an existing Dask scheduler.

    Returns
    -------
    Calibration or DetectorCalibration
        Gain (e-/ADU), read noise (e-), a and a_err (1/e-), shifts, PTC table, linearity,
        pedestal; see `~bfpsf.calibration.product.Calibration`.
    """
    return calibrate_detectors({"": sources}, exptimes={"": exptimes}, maxlag=maxlag,
                               ptc_model=ptc_model, fit_b=fit_b, saturation=saturation,
                               mean_tolerance=mean_tolerance, clip_nsigma=clip_nsigma,
                               pedestal_nsigma=pedestal_nsigma, pedestal_degree=pedestal_degree,
                               linearity_threshold=linearity_threshold,
                               solve_shifts=solve_shifts, shift_method=shift_method,
                               thickness=thickness, n_monte_carlo=n_monte_carlo,
                               seed=seed, progress=progress, amps=amps, overscan=overscan,
                               workers=workers, scheduler=scheduler)[""]


def calibrate_detectors(detectors, *, exptimes=None, maxlag="auto", ptc_model="full",
                        fit_b="off-origin", saturation=None, mean_tolerance=0.05,
                        clip_nsigma=4.0, pedestal_nsigma=4.0, pedestal_degree=2,
                        linearity_threshold=None, solve_shifts=True,
                        shift_method="electrostatic", thickness=10.0, n_monte_carlo=100, seed=0,
                        progress=False, amps=None, overscan="median", workers=1,
                        scheduler=None):
    """Calibrate several detectors: every pair of every amplifier of every detector in one
    map (`bfpsf.parallel.ParallelSession.map_groups`), and one fit per amplifier, started as
    soon as its pairs are measured.

    Parameters
    ----------
    detectors : dict of str to sequence
        Detector name -> its flat sources (as `calibrate`).
    exptimes : dict of str to sequence, optional
        Detector name -> exposure times of its sources.
    Others
        As `calibrate`.

    Returns
    -------
    dict of str to Calibration or DetectorCalibration
        Per detector, in the order given.
    """
    from ..parallel import parallel_session
    from .flats import group_amplifiers, pair_flats, read_flats
    from .product import DetectorCalibration

    parameters, options = _settings(
        maxlag=maxlag, ptc_model=ptc_model, fit_b=fit_b, saturation=saturation,
        mean_tolerance=mean_tolerance, clip_nsigma=clip_nsigma, pedestal_nsigma=pedestal_nsigma,
        pedestal_degree=pedestal_degree, linearity_threshold=linearity_threshold,
        solve_shifts=solve_shifts, shift_method=shift_method, thickness=thickness,
        n_monte_carlo=n_monte_carlo, seed=seed)
    exptimes = exptimes or {}

    def blocks():
        # one detector at a time: its headers are read while the workers measure the pairs
        # of the detectors before
        for detector, sources in detectors.items():
            if not isinstance(sources, (str, os.PathLike, np.ndarray)):
                refuse_duplicates([source for source in sources
                                   if isinstance(source, (str, os.PathLike))], "flat")
            flats = read_flats(sources, exptimes.get(detector), amps=amps, lazy=True,
                               overscan=overscan)
            measured_lag = _measured_lag(flats, parameters["maxlag"])
            tasks, owners = [], []
            for amplifier, amplifier_flats in group_amplifiers(flats).items():
                for pair in pair_flats(amplifier_flats, mean_tolerance=mean_tolerance):
                    tasks.append(PairTask(pair, saturation, measured_lag, clip_nsigma,
                                          mean_tolerance, overscan))
                    owners.append((detector, amplifier))
            yield tasks, owners

    # each amplifier is fitted as soon as its pairs are measured, while the others' are
    with parallel_session(workers, scheduler) as session:
        _, fits = session.map_groups(measure_pair, blocks(),
                                     functools.partial(_fit_task, parameters, options),
                                     fit_measured_pairs, progress=progress,
                                     description="flat pairs")
    results = {}
    for detector in detectors:
        fitted = {owner[1]: fit for owner, fit in fits.items() if owner[0] == detector}
        results[detector] = (next(iter(fitted.values())) if len(fitted) == 1 else
                             DetectorCalibration(fitted, detector=detector))
    return results


def _settings(*, maxlag, ptc_model, fit_b, saturation, mean_tolerance, clip_nsigma,
              pedestal_nsigma, pedestal_degree, linearity_threshold, solve_shifts,
              shift_method, thickness, n_monte_carlo, seed):
    """Validated parameters (recorded in the product) and the options of `fit_amplifier`."""
    from .boundary_shifts import SHIFT_METHODS
    from .linearity import DEFAULT_LINEARITY_THRESHOLD
    from .maxlag import check_maxlag
    from .ptc import PTC_MODELS, _b_mask

    maxlag = check_maxlag(maxlag)
    if ptc_model not in PTC_MODELS:
        msg = f"ptc_model must be one of {PTC_MODELS}, got {ptc_model!r}"
        raise BFPSFValueError(msg, ptc_model)
    if ptc_model == "full" and maxlag != "auto" and maxlag > MAX_FULL_MODEL_MAXLAG:
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
        "mean_tolerance": None if mean_tolerance is None else float(mean_tolerance),
        "clip_nsigma": None if clip_nsigma is None else float(clip_nsigma),
        "pedestal_nsigma": float(pedestal_nsigma), "pedestal_degree": int(pedestal_degree),
        "linearity_threshold": float(linearity_threshold), "solve_shifts": bool(solve_shifts),
        "shift_method": str(shift_method), "thickness": float(thickness),
        "n_monte_carlo": int(n_monte_carlo), "seed": int(seed),
    }
    options = {"ptc_model": ptc_model, "fit_b": fit_b, "pedestal_nsigma": pedestal_nsigma,
               "pedestal_degree": pedestal_degree, "linearity_threshold": linearity_threshold,
               "solve_shifts": solve_shifts, "shift_method": shift_method,
               "thickness": thickness, "n_monte_carlo": n_monte_carlo, "seed": seed}
    return parameters, options


def calibrate_from_ptc(path, *, amps=None, maxlag="auto", ptc_model="full", fit_b="off-origin",
                       pedestal_nsigma=4.0, pedestal_degree=2, linearity_threshold=None,
                       solve_shifts=True, shift_method="electrostatic", thickness=10.0,
                       n_monte_carlo=100, seed=0):
    """Calibrate from an LSST cp_pipe PTC dataset instead of flats (`bfpsf.io.cp_pipe`).

    The per-pair means and covariances cp_pipe measured (the pairs its EXP_ID_MASK keeps) go
    through the same fit as flats do (`fit_amplifier`: pedestal, the PTC model, linearity, the
    boundary-shift solver with its Monte Carlo errors), so the product is what `calibrate`
    would make from the same covariances. cp_pipe's own a(0, 0) and gain are kept in
    ``parameters`` (``cp_pipe_a00``, ``cp_pipe_gain``) for comparison.

    Parameters
    ----------
    path : str or path
        The PhotonTransferCurveDataset FITS file.
    amps : str or sequence of str, optional
        Amplifiers to calibrate. Default: all.
    maxlag : 'auto' or int, optional
        Largest lag fitted, at most cp_pipe's COV_MATRIX_SIDE - 1. Default ``'auto'``: chosen
        from cp_pipe's covariances as `calibrate` does.
    Others
        As `calibrate`.

    Returns
    -------
    Calibration or DetectorCalibration
        One amplifier, or several.
    """
    from ..io.cp_pipe import read_ptc_dataset
    from .maxlag import check_maxlag
    from .product import DetectorCalibration

    maxlag = check_maxlag(maxlag)
    dataset = read_ptc_dataset(path)
    if amps is not None:
        amps = [amps] if isinstance(amps, str) else list(amps)
        missing = [name for name in amps if name not in dataset]
        if missing:
            msg = (f"{path}: no amplifier {', '.join(map(repr, missing))}; it has "
                   f"{', '.join(map(repr, dataset))}")
            raise BFPSFValueError(msg, missing)
        dataset = {name: dataset[name] for name in amps}
    fitted = {}
    for name, amplifier in dataset.items():
        side = amplifier.a.shape[0]
        parameters, options = _settings(
            maxlag=maxlag if maxlag == "auto" else min(maxlag, side - 1),
            ptc_model=ptc_model, fit_b=fit_b, saturation=None,
            mean_tolerance=None, clip_nsigma=None,
            pedestal_nsigma=pedestal_nsigma, pedestal_degree=pedestal_degree,
            linearity_threshold=linearity_threshold, solve_shifts=solve_shifts,
            shift_method=shift_method, thickness=thickness, n_monte_carlo=n_monte_carlo,
            seed=seed)
        parameters.update({"from_ptc": str(path), "cp_pipe_gain": amplifier.gain,
                           "cp_pipe_a00": float(amplifier.a[0, 0]),
                           "cp_pipe_fit_type": amplifier.fit_type})
        data = amplifier.data
        if maxlag != "auto":
            data = data.to_maxlag(parameters["maxlag"])
        count = data.mean_adu.size
        ids = amplifier.pair_ids or [(2 * index, 2 * index + 1) for index in range(count)]
        fitted[name] = fit_amplifier(data, parameters, amplifier=name,
                                     names=[(f"{path}:{first}", f"{path}:{second}")
                                            for first, second in ids],
                                     n_masked=[0] * count, n_clipped=[0] * count, **options)
    return next(iter(fitted.values())) if len(fitted) == 1 else DetectorCalibration(fitted)


@dataclass(frozen=True, eq=False)
class PairTask:
    """What a worker needs to measure one flat pair (`measure_pair`)."""

    pair: object
    saturation: object
    maxlag: int
    clip_nsigma: float
    mean_tolerance: float
    overscan: str


def measure_pair(task):
    """Read a pair (if not in memory), check it, mask it and measure its covariances.

    Returns
    -------
    ((str, str), PairCovariance, MaskReport)
        The names of the two flats and their measurements: an entry of `FitTask`.
    """
    from .covariance import pair_covariance
    from .flats import check_pair, pair_mask

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
    mask, report = pair_mask(flat1, flat2, saturation=task.saturation)
    covariance = pair_covariance(flat1, flat2, mask=mask, maxlag=task.maxlag,
                                 clip_nsigma=task.clip_nsigma)
    if not covariance.var_adu > 0:
        msg = (f"flats {flat1.name} and {flat2.name} are identical (their difference "
               "has zero variance): a pair needs two exposures")
        raise BFPSFInputError(msg, (flat1.name, flat2.name))
    return task.pair.names, covariance, report


def _measured_lag(flats, maxlag):
    """The lag to measure the covariances to: ``maxlag``, or for ``'auto'`` the largest the
    flats and the full model allow (`MAX_FULL_MODEL_MAXLAG`); `BFPSFInputError` if a flat is
    too small."""
    if maxlag == "auto":
        smallest = min(flats, key=lambda flat: min(flat.shape), default=None)
        if smallest is None:
            return 1
        maxlag = max(1, min(MAX_FULL_MODEL_MAXLAG, min(smallest.shape) // 2 - 1))
    for flat in flats:
        _check_size(flat, maxlag)
    return maxlag


def _check_size(flat, maxlag):
    """Raise `BFPSFInputError` if ``flat`` is too small for the lags ``maxlag``."""
    ny, nx = flat.shape
    if ny < 2 * maxlag + 2 or nx < 2 * maxlag + 2:
        msg = (f"flat {flat.name} ({nx} x {ny} pixels) is too small for maxlag {maxlag}: "
               f"give maxlag < {min(ny, nx) // 2}")
        raise BFPSFInputError(msg, flat.name)


def _fit_task(parameters, options, owner, measured):
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
    from .ptc import stack_pairs

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
    from .linearity import measure_linearity
    from .pedestal import measure_pedestal, subtract_pedestal
    from .product import Calibration
    from .ptc import covariance_errors, detect_turnoff, fit_ptc, ptc_table

    # The pedestal is the zero-flux intercept of R = C / V, measured below the PTC extremum.
    below, _ = detect_turnoff(data.mean_adu, data.var_adu,
                              covariance_errors(data.cov_adu, data.npix)[:, 0, 0])
    data = _fitted_lags(data, below, parameters, ptc_model)
    pedestal = measure_pedestal(data.mean_adu[below], data.cov_adu[below], data.npix[below],
                                nsigma=pedestal_nsigma, degree=pedestal_degree)
    corrected = data.with_covariances(subtract_pedestal(data.cov_adu, pedestal))
    fit = fit_ptc(corrected, model=ptc_model, fit_b=fit_b, pedestal=pedestal)
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


def _fitted_lags(data, below, parameters, ptc_model):
    """``data`` to the lags fitted: for ``maxlag='auto'`` those the flats constrain
    (`bfpsf.calibration.maxlag.choose_maxlag`, on the pairs below the turnoff), recorded in
    ``parameters`` (``maxlag``, ``maxlag_auto``, ``maxlag_ring_sigma``, ``maxlag_reason``)."""
    from .maxlag import choose_maxlag

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
