"""`calibrate`: flat pairs to a calibration, for one detector (`calibrate`), several
(`calibrate_detectors`, in process or on Dask), or an LSST cp_pipe PTC dataset
(`calibrate_from_ptc`). Each amplifier's pairs are measured and fitted by
`bfpsf.calibration.amplifier_fit`."""

import functools
import os

import numpy as np

from ..errors import BFPSFValueError
from ..files import refuse_duplicates
from ..parallel import parallel_session
from .amplifier_fit import (PairTask, fit_amplifier, fit_measured_pairs, fit_task, lags_to_measure,
                            measure_pair)
from .boundary_shifts import SHIFT_METHODS
from .cp_pipe import read_ptc_dataset
from .detector import DetectorCalibration
from .flat_mask import DEFAULT_EDGE
from .flats import group_amplifiers, pair_flats, read_flats
from .linearity import DEFAULT_LINEARITY_THRESHOLD
from .maxlag import check_maxlag
from .ptc import PTC_MODELS
from .ptc_full import MAX_FULL_MODEL_MAXLAG, b_term_mask

__all__ = ["calibrate", "calibrate_detectors", "calibrate_from_ptc"]


def calibrate(sources, *, exptimes=None, maxlag="auto", ptc_model="full", fit_b="off-origin",
              saturation=None, edge=DEFAULT_EDGE, mean_tolerance=0.05, clip_nsigma=4.0,
              pedestal_nsigma=4.0, pedestal_degree=2, linearity_threshold=None, solve_shifts=True,
              shift_method="electrostatic", thickness=10.0, n_monte_carlo=100, seed=0,
              progress=False, amps=None, overscan="median", workers=1, scheduler=None):
    """Calibrate brighter-fatter from flat-field pairs, each amplifier on its own.

    Returns a `~bfpsf.calibration.product.Calibration` when the flats have one amplifier
    (single-image files or arrays, or ``amps`` naming one), else a
    `~bfpsf.calibration.detector.DetectorCalibration` of one per amplifier.

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
    edge : int, optional
        Pixels masked along each side of each amplifier's image
        (`bfpsf.calibration.flat_mask.pair_mask`). Default (or None)
        `~bfpsf.calibration.flat_mask.DEFAULT_EDGE` (10, as cp_pipe's PTC configuration):
        the edges of a sensor lose charge in a way that grows with the flux.
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
                               edge=edge, mean_tolerance=mean_tolerance, clip_nsigma=clip_nsigma,
                               pedestal_nsigma=pedestal_nsigma, pedestal_degree=pedestal_degree,
                               linearity_threshold=linearity_threshold,
                               solve_shifts=solve_shifts, shift_method=shift_method,
                               thickness=thickness, n_monte_carlo=n_monte_carlo,
                               seed=seed, progress=progress, amps=amps, overscan=overscan,
                               workers=workers, scheduler=scheduler)[""]


def calibrate_detectors(detectors, *, exptimes=None, maxlag="auto", ptc_model="full",
                        fit_b="off-origin", saturation=None, edge=DEFAULT_EDGE,
                        mean_tolerance=0.05,
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
    parameters, options = _settings(
        maxlag=maxlag, ptc_model=ptc_model, fit_b=fit_b, saturation=saturation,
        edge=DEFAULT_EDGE if edge is None else edge,
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
            measured_lag = lags_to_measure(flats, parameters["maxlag"], parameters["edge"])
            tasks, owners = [], []
            for amplifier, amplifier_flats in group_amplifiers(flats).items():
                for pair in pair_flats(amplifier_flats, mean_tolerance=mean_tolerance):
                    tasks.append(PairTask(pair, saturation, measured_lag, clip_nsigma,
                                          mean_tolerance, overscan, parameters["edge"]))
                    owners.append((detector, amplifier))
            yield tasks, owners

    # each amplifier is fitted as soon as its pairs are measured, while the others' are
    with parallel_session(workers, scheduler) as session:
        _, fits = session.map_groups(measure_pair, blocks(),
                                     functools.partial(fit_task, parameters, options),
                                     fit_measured_pairs, progress=progress,
                                     description="flat pairs")
    results = {}
    for detector in detectors:
        fitted = {owner[1]: fit for owner, fit in fits.items() if owner[0] == detector}
        results[detector] = (next(iter(fitted.values())) if len(fitted) == 1 else
                             DetectorCalibration(fitted, detector=detector))
    return results


def _settings(*, maxlag, ptc_model, fit_b, saturation, mean_tolerance, clip_nsigma, edge,
              pedestal_nsigma, pedestal_degree, linearity_threshold, solve_shifts,
              shift_method, thickness, n_monte_carlo, seed):
    """Validated parameters (recorded in the product) and the options of `fit_amplifier`."""
    maxlag = check_maxlag(maxlag)
    if ptc_model not in PTC_MODELS:
        msg = f"ptc_model must be one of {PTC_MODELS}, got {ptc_model!r}"
        raise BFPSFValueError(msg, ptc_model)
    if ptc_model == "full" and maxlag != "auto" and maxlag > MAX_FULL_MODEL_MAXLAG:
        msg = (f"maxlag {maxlag} is too large for the full PTC model: its memory and time grow "
               f"as (maxlag + 1)^6 ({8 * (maxlag + 1) ** 6 / 2**30:.3g} GiB here); use maxlag "
               f"<= {MAX_FULL_MODEL_MAXLAG} or the exponential PTC model")
        raise BFPSFValueError(msg, maxlag)
    b_term_mask(fit_b, 1)  # validates fit_b before the work
    if shift_method not in SHIFT_METHODS:
        msg = f"shift_method must be one of {SHIFT_METHODS}, got {shift_method!r}"
        raise BFPSFValueError(msg, shift_method)
    if linearity_threshold is None:
        linearity_threshold = DEFAULT_LINEARITY_THRESHOLD
    if edge is not None and (int(edge) != edge or edge < 0):
        msg = f"edge must be a whole number of pixels >= 0, got {edge!r}"
        raise BFPSFValueError(msg, edge)
    parameters = {
        "maxlag": maxlag, "ptc_model": ptc_model,
        "fit_b": fit_b if isinstance(fit_b, str) else bool(fit_b),
        "saturation": None if saturation is None else float(saturation),
        "edge": None if edge is None else int(edge),
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
    """Calibrate from an LSST cp_pipe PTC dataset instead of flats (`bfpsf.calibration.cp_pipe`).

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
            mean_tolerance=None, clip_nsigma=None, edge=None,
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
