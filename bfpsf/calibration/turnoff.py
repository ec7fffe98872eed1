"""The PTC turnoff: the pairs below the variance extremum (G15 section 4.3.2), found from data."""

import numpy as np

__all__ = ["detect_turnoff"]


def detect_turnoff(mean_adu, var_adu, var_err, *, nsigma=3.0):
    """Pairs below the PTC extremum (G15 section 4.3.2), found from the data.

    The variance maximum is located; pairs at a higher mean whose variance lies more than
    ``nsigma`` errors below it are past the turnoff, and so is every pair above the first of them.
    If the variance never falls significantly, every pair is kept (no turnoff in the data).

    Parameters
    ----------
    mean_adu, var_adu, var_err : ndarray (n,)
        Mean (ADU), single-image variance and its error (ADU^2).
    nsigma : float, optional
        Significance of the fall. Default 3.

    Returns
    -------
    used : ndarray of bool (n,)
        True below the turnoff.
    detected : bool
        True if a turnoff was found inside the data.
    """
    mean_adu = np.asarray(mean_adu, dtype=float)
    var_adu = np.asarray(var_adu, dtype=float)
    finite = np.isfinite(mean_adu) & np.isfinite(var_adu)
    used = finite.copy()
    if not finite.any():
        return used, False
    peak = np.nanargmax(np.where(finite, var_adu, -np.inf))
    fallen = finite & (mean_adu > mean_adu[peak]) & (
        var_adu < var_adu[peak] - nsigma * np.asarray(var_err)[peak])
    if not fallen.any():
        return used, False
    first_fallen = mean_adu[fallen].min()
    used &= mean_adu < first_fallen
    return used, True


# ---------------------------------------------------------------------------------------------
# G15 quadratic and A+19 exponential fits of the variance
# ---------------------------------------------------------------------------------------------
