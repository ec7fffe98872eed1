"""The largest lag the flats constrain: ``maxlag='auto'`` of `bfpsf.calibrate` (issue 14).

Every lag fitted adds parameters: in the A+19 full model a, b and the zero-flux covariance n at
each lag, all pinned only by the pairs' covariances at that lag. Lags where the flats measure
no correlation add nothing but noise, and through the model's shared gain and its powers of a
they bias the gain and the read noise: four flat pairs of 128^2 ITL flats fitted at maxlag 8
gave a gain 28 % high and a 68 e- read noise (true 1.5 e-/ADU and 5 e-), at maxlag 2 the gain
to 0.1 %.

`choose_maxlag` measures, ring by ring, whether the flats see a correlation there. A lag ring
is the set of lags with max(|dx|, |dy|) = r, what going from maxlag r - 1 to r adds. At each
lag the correlation rho = C(dx, dy) / V of every pair grows as a(dx, dy) times the signal
(G15 eq. covar), so its slope against the mean (ADU) through the origin, weighted by the number
of pixel products (rho's shot-noise error is 1/sqrt(N)), is the matched measurement: it gives
the bright pairs their weight. The ring's mean slope over its error is the ring's significance.
The chosen maxlag is the last ring before the first one below `RING_NSIGMA`, bounded by:

- `MIN_AUTO_MAXLAG` below (the boundary-shift solvers split a(0, 0) between the N/S and E/W
  boundaries with the ring beyond the nearest neighbours). Deeper is not better for them:
  from GalSim's noise-free areas the electrostatic fit's a^N(0, 0), a^E(0, 0) are, against
  the landing truth, 0.95 / 1.13 (E2V) and 0.99 / 1.01 (ITL) at maxlag 2, 1.02 / 1.03 and
  1.00 / 1.00 at 3, 0.96 / 1.13 and 0.96 / 1.07 at 4 and 6;
- the lags measured (the image size and `bfpsf.calibration.ptc_full.MAX_FULL_MODEL_MAXLAG`, the
  memory and time of the full model);
- for the full model with fewer pairs than `bfpsf.calibration.ptc_full.MIN_PAIRS_FULL_MODEL` (at most
  a few points per lag against its three parameters per lag), `HELD_FULL_MODEL_MAXLAG`: the
  gain and the read noise come first.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import BFPSFValueError

__all__ = ["MaxlagChoice", "ring_significance", "choose_maxlag", "RING_NSIGMA",
           "MIN_AUTO_MAXLAG", "HELD_FULL_MODEL_MAXLAG", "check_maxlag"]

#: Significance below which a lag ring counts as unmeasured (a ring of pure noise passes with
#: probability 0.3 %).
RING_NSIGMA = 3.0

#: Smallest maxlag `choose_maxlag` returns (when the flats allow it).
MIN_AUTO_MAXLAG = 2

#: The maxlag of the full PTC model on fewer than `bfpsf.calibration.ptc_full.MIN_PAIRS_FULL_MODEL` pairs.
HELD_FULL_MODEL_MAXLAG = 2


@dataclass(frozen=True)
class MaxlagChoice:
    """Result of `choose_maxlag`.

    Attributes
    ----------
    maxlag : int
        The chosen largest lag.
    significance : ndarray (L,)
        Significance of each lag ring r = 1..L measured (index r - 1), in sigma.
    reason : str
        Why the choice stops there (recorded in the calibration's parameters).
    """

    maxlag: int
    significance: np.ndarray
    reason: str


def check_maxlag(maxlag):
    """``'auto'`` or a positive int, else `BFPSFValueError`."""
    if isinstance(maxlag, str) and maxlag == "auto":
        return maxlag
    if (isinstance(maxlag, (bool, np.bool_))
            or not isinstance(maxlag, (int, np.integer, float, np.floating))
            or not float(maxlag).is_integer() or maxlag < 1):
        msg = f"maxlag must be 'auto' or a positive integer, got {maxlag!r}"
        raise BFPSFValueError(msg, maxlag)
    return int(maxlag)


def ring_significance(mean_adu, cov_adu, npix):
    """Significance, in sigma, of the correlation measured on each lag ring r = 1..L.

    Parameters
    ----------
    mean_adu : ndarray (n,)
        Mean signal of each pair, ADU.
    cov_adu, npix : ndarray (n, L + 1, L + 1)
        Single-image covariances [pair, dy, dx], ADU^2, and their pixel-product counts.

    Returns
    -------
    ndarray (L,)
        |mean over the ring of the slope of rho against the mean| over its error.
    """
    mean_adu = np.asarray(mean_adu, dtype=float)
    cov_adu = np.asarray(cov_adu, dtype=float)
    weight = np.asarray(npix, dtype=float)            # 1 / sigma(rho)^2, per pair and lag
    rho = cov_adu / cov_adu[:, :1, :1]
    mean = mean_adu[:, None, None]
    information = np.sum(weight * mean**2, axis=0)    # of the slope, per lag
    slope = np.sum(weight * mean * rho, axis=0) / information
    slope_var = 1.0 / information
    lags = cov_adu.shape[1]
    ring = np.maximum.outer(np.arange(lags), np.arange(lags))
    significance = np.empty(lags - 1)
    for radius in range(1, lags):
        members = ring == radius
        significance[radius - 1] = (abs(slope[members].mean())
                                    / (np.sqrt(slope_var[members].sum()) / members.sum()))
    return significance


def choose_maxlag(mean_adu, cov_adu, npix, *, model="full", min_pairs_full_model=8,
                  nsigma=RING_NSIGMA):
    """The largest lag the flats constrain (module docstring).

    Parameters
    ----------
    mean_adu : ndarray (n,)
        Mean signal of the pairs the PTC fit uses (below the turnoff), ADU.
    cov_adu, npix : ndarray (n, L + 1, L + 1)
        Their covariances, ADU^2, measured to the largest lag allowed, and pixel-product counts.
    model : str, optional
        PTC model; the full model with fewer than ``min_pairs_full_model`` pairs is held to
        `HELD_FULL_MODEL_MAXLAG`.
    min_pairs_full_model : int, optional
        Default 8 (`bfpsf.calibration.ptc_full.MIN_PAIRS_FULL_MODEL`).
    nsigma : float, optional
        Significance a ring needs. Default `RING_NSIGMA`.

    Returns
    -------
    MaxlagChoice
    """
    significance = ring_significance(mean_adu, cov_adu, npix)
    measured = significance.size
    floor = min(MIN_AUTO_MAXLAG, measured)
    below = np.flatnonzero(significance < nsigma)
    if below.size:
        chosen = int(below[0])       # the ring before the first unmeasured one (index r - 1)
        reason = (f"lag ring {chosen + 1} is measured at {significance[chosen]:.2f} sigma "
                  f"(< {nsigma:g})")
    else:
        chosen = measured
        reason = f"every measured ring is above {nsigma:g} sigma; largest lag measured"
    if chosen < floor:
        chosen = floor
        reason += f"; raised to the least maxlag {floor}"
    pairs = len(np.asarray(mean_adu))
    held = min(HELD_FULL_MODEL_MAXLAG, measured)
    if model == "full" and pairs < min_pairs_full_model and chosen > held:
        chosen = held
        reason += (f"; held to {held}: {pairs} pairs under-constrain the full model's "
                   "a, b and n at each further lag")
    return MaxlagChoice(maxlag=int(chosen), significance=significance, reason=reason)
