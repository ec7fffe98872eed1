"""Brighter-fatter integrated over the exposure: the boundary shifts build up as charge arrives."""

import numpy as np

from ..errors import BFPSFValueError
from ..shifts import as_shifts
from .redistribution import add_redistribution, as_image, validate_density, validate_dtype

__all__ = ["redistribute_buildup"]


def redistribute_buildup(image_e, shifts, *, nsteps=16, density=None, dtype=np.float64,
                         workers=None, full_output=False):
    """Forward BF integrated over the exposure: charge arrives in ``nsteps`` equal steps.

    The one-step model (`~bfpsf.model.redistribution.redistribute`) moves the charge with the end-of-exposure shifts
    halved, assuming the boundaries move linearly in time with the *ideal* collected charge.
    Here the collected charge C (redistributed charge included) sets the boundary shifts
    a^X * C at the middle of each step, and the charge arriving in the step, Q / K, is moved
    with them:

        C_k = C_{k-1} + Q/K + M_k,   M_k = div[ (a^X * (C_{k-1} + (Q/K + M_{k-1})/2)) rho(Q) / K ]

    For K = 1 this is exactly the one-step model (midpoint rule on a linear build-up); the
    difference for K > 1 comes from the redistributed charge acting back on the boundaries,
    second order in a (error of the integration O(1/K^2)).

    Parameters
    ----------
    image_e : array_like [y, x]
        Charge without BF at the end of the exposure, e-.
    shifts : BoundaryShifts or Calibration
        End-of-exposure boundary shifts a^X, 1/e-.
    nsteps : int, optional
        K. Default 16.
    density : (ndarray, ndarray), optional
        Boundary density of the full exposure (`~bfpsf.model.density.exact_boundary_density`); default G15's mean.
    full_output : bool, optional
        Also return the list of the collected images after each step.

    Returns
    -------
    ndarray [y, x] (and list of ndarray if ``full_output``)
        Collected charge at the end of the exposure, e-; total charge equals ``image_e``'s.
    """
    image, _ = as_image(image_e)
    shifts = as_shifts(shifts)
    dtype = validate_dtype(dtype)
    k_steps = int(nsteps)
    if k_steps < 1 or k_steps != nsteps:
        msg = f"nsteps must be a positive integer, got {nsteps}"
        raise BFPSFValueError(msg, nsteps)
    if density is not None:
        density = validate_density(density, image.shape)
    arriving = image / k_steps
    collected = np.zeros_like(image)
    moved = np.zeros_like(image)
    steps = []
    for _ in range(k_steps):
        # Shifts at mid-step from the charge collected so far (the charge moved during this
        # step estimated by the previous step's, for O(1/K^2)); density of the arriving charge.
        moved = add_redistribution(np.zeros(image.shape), image, shifts, density, dtype, workers,
                               source=collected + 0.5 * (arriving + moved),
                               factor=1.0 / k_steps)
        collected = collected + arriving + moved
        if full_output:
            steps.append(collected)
    return (collected, steps) if full_output else collected
