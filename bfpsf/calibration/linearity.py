"""Linearity of the flat-field response: mean signal against exposure time (G15 section 4.3.2),
and the correction of a gain non-linearity v = q (1 + c q / 1e5) (`linearise`, the
``gain_nonlinearity`` of a calibration refined by `bfpsf diagnose --output-calib`).

Brighter-fatter moves charge between pixels but conserves it, so the flat mean stays linear in
the exposure time; G15 found departures below 2 per mil peak to peak from 0 to 130 ke- on the
LSST E2V-250. A larger departure means the gain conversion itself is non-linear, which biases
the PTC (the variance is then not that of the collected charge).
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFValueError

__all__ = ["Linearity", "measure_linearity", "linearise", "DEFAULT_LINEARITY_THRESHOLD"]

#: Default flag threshold on the peak-to-peak fractional residual: 3 per mil, above G15's
#: < 2 per mil on a good sensor, leaving room for GalSim's SiliconSensor, whose mean pixel area
#: itself shrinks by 0.2 per mil (lsst_itl_50_8) to 1.7 per mil (lsst_e2v_50_8) at 150 ke-.
DEFAULT_LINEARITY_THRESHOLD = 3e-3


@dataclass(frozen=True)
class Linearity:
    """Linear fit of the flat mean against exposure time.

    Attributes
    ----------
    exptime : ndarray (n,)
        s.
    mean_adu : ndarray (n,)
        ADU.
    slope : float
        ADU/s.
    intercept : float
        ADU (a shutter delay or bias residual shows up here).
    frac_residual : ndarray (n,)
        mean / fit - 1 (NaN when the fit could not be made).
    used : ndarray of bool (n,)
        Points in the fit (below the PTC turnoff).
    threshold : float
        Peak-to-peak fractional residual above which ``flagged`` is set.
    measured : bool
        False when fewer than 3 distinct exposure times were available.
    """

    exptime: np.ndarray
    mean_adu: np.ndarray
    slope: float
    intercept: float
    frac_residual: np.ndarray
    used: np.ndarray
    threshold: float
    measured: bool

    @property
    def max_frac_residual(self):
        """Largest |fractional residual| of the points used (NaN if not measured)."""
        if not self.measured:
            return float("nan")
        return float(np.max(np.abs(self.frac_residual[self.used])))

    @property
    def peak_to_peak(self):
        """Peak-to-peak fractional residual of the points used (NaN if not measured)."""
        if not self.measured:
            return float("nan")
        return float(np.ptp(self.frac_residual[self.used]))

    @property
    def flagged(self):
        """True if the response departs from linear by more than ``threshold`` peak to peak."""
        return bool(self.measured and self.peak_to_peak > self.threshold)


def measure_linearity(exptime, mean_adu, *, used=None, threshold=DEFAULT_LINEARITY_THRESHOLD):
    """Fit mean = intercept + slope * exptime and report the fractional residuals.

    Parameters
    ----------
    exptime : array_like (n,)
        Exposure times, s.
    mean_adu : array_like (n,)
        Mean flat levels, ADU.
    used : array_like of bool (n,), optional
        Points to fit (default: all finite points). Use the pairs below the PTC turnoff.
    threshold : float, optional
        Flag threshold on the peak-to-peak fractional residual. Default
        `DEFAULT_LINEARITY_THRESHOLD` (3e-3).

    Returns
    -------
    Linearity
        ``measured`` is False (and the residuals NaN) with fewer than 3 distinct exposure times.
    """
    exptime = np.asarray(exptime, dtype=float)
    mean_adu = np.asarray(mean_adu, dtype=float)
    if exptime.shape != mean_adu.shape:
        msg = (f"exptime and mean_adu must have the same shape, got {exptime.shape} and "
               f"{mean_adu.shape}")
        raise BFPSFValueError(msg)
    if not threshold > 0:
        msg = f"threshold must be positive, got {threshold}"
        raise BFPSFValueError(msg, threshold)
    finite = np.isfinite(exptime) & np.isfinite(mean_adu)
    used = finite if used is None else (np.asarray(used, dtype=bool) & finite)
    if np.unique(exptime[used]).size < 3:
        nan = np.full(exptime.shape, np.nan)
        return Linearity(exptime, mean_adu, float("nan"), float("nan"), nan, used,
                         float(threshold), False)
    # Minimise the fractional residuals (weights 1 / mean), as the flag is on those.
    weight = 1.0 / np.abs(mean_adu[used])
    design = np.column_stack([np.ones(used.sum()), exptime[used]]) * weight[:, None]
    (intercept, slope), *_ = np.linalg.lstsq(design, mean_adu[used] * weight, rcond=None)
    frac_residual = mean_adu / (intercept + slope * exptime) - 1.0
    return Linearity(exptime, mean_adu, float(slope), float(intercept), frac_residual, used,
                     float(threshold), True)


def linearise(image_e, c_per_1e5):
    """Undo v = q (1 + c q / 1e5): the linear charge q of measured values v, e-.

    Parameters
    ----------
    image_e : ndarray
        Measured values, e-.
    c_per_1e5 : float
        The ``gain_nonlinearity`` parameter c (relative change per 1e5 e-).

    Returns
    -------
    ndarray
        q, e- (the root of c q^2 / 1e5 + q - v = 0 that tends to v as c -> 0).
    """
    image = np.asarray(image_e, dtype=float)
    k = float(c_per_1e5) / 1e5
    if k == 0:
        return image.copy()
    discriminant = 1.0 + 4.0 * k * image
    if np.any(discriminant < 0):
        msg = (f"the linearity correction c = {c_per_1e5:g} per 1e5 e- has no solution above "
               f"{-1 / (4 * k):.4g} e-")
        raise BFPSFValueError(msg, c_per_1e5)
    # 2 v / (1 + sqrt(1 + 4 k v)): the stable form of (-1 + sqrt(1 + 4 k v)) / (2 k)
    return 2.0 * image / (1.0 + np.sqrt(discriminant))
