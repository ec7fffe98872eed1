"""Statistical errors of adaptive moments by linear error propagation (`moment_errors`)."""

import numpy as np

from ..errors import BFPSFInputError
from .adaptive import validate_stack

__all__ = ["moment_errors"]


def moment_errors(stamps, moments, *, background_variance=0.0, source_variance=True):
    """Statistical errors of adaptive moments by linear error propagation.

    The estimator solves ``psi(theta; I) = sum_p I_p w_p(theta) g_p(theta) = 0`` with
    ``g = (dx, dy, dx^2 - Mxx/2, dy^2 - Myy/2, dx dy - Mxy/2)`` and
    ``theta = (x0, y0, Mxx, Myy, Mxy)`` (module docstring). To linear order in the pixel noise
    ``d theta = -H^-1 sum_p w_p g_p dI_p`` with ``H = d psi / d theta`` (computed analytically on
    the measured stamp), so ``Cov(theta) = H^-1 S H^-T``, ``S = sum_p w_p^2 g_p g_p^T V_p``.
    The pixel variance is ``V = background_variance + max(I, 0)`` (Poisson noise of the source
    in electrons plus background). No profile is assumed: on Moffat spots these errors match
    the scatter of noise realisations to a few percent
    (``tests/test_moments.py::test_moment_errors_match_scatter``).

    Parameters
    ----------
    stamps : array_like, shape (n, ny, nx) or (ny, nx)
        The stamps measured, electrons (background subtracted).
    moments : Moments
        Their result from `adaptive_moments_batch` (or `adaptive_moments`).
    background_variance : float or array_like of shape (n,), optional
        Pixel variance of the background (sky Poisson and read noise), electrons^2.
    source_variance : bool, optional
        Include the source's Poisson variance ``max(I, 0)`` (default True).

    Returns
    -------
    dict of ndarray
        ``mxx_err, myy_err, mxy_err`` (pixel^2), ``sigma_x_err, sigma_y_err, sigma_err``
        (pixels), ``e1_err, e2_err`` (of the distortion, `bfpsf.moments.shapes.distortion`);
        NaN where the moments are NaN.
    """
    stack = np.asarray(stamps, dtype=float)
    stack = validate_stack(stack[None] if stack.ndim == 2 else stack)
    n_stamps, ny, nx = stack.shape
    fields = [np.atleast_1d(np.asarray(getattr(moments, name), dtype=float))
              for name in ("x", "y", "mxx", "myy", "mxy")]
    if any(value.size != n_stamps for value in fields):
        msg = f"moments hold {fields[0].size} objects for {n_stamps} stamps"
        raise BFPSFInputError(msg, fields[0].size)
    background = np.broadcast_to(np.asarray(background_variance, dtype=float), (n_stamps,))
    good = np.all(np.isfinite(fields), axis=0)
    errors = {name: np.full(n_stamps, np.nan) for name in
              ("mxx_err", "myy_err", "mxy_err", "sigma_x_err", "sigma_y_err", "sigma_err",
               "e1_err", "e2_err")}
    if not np.any(good):
        return errors
    x0, y0, mxx, myy, mxy = (value[good] for value in fields)
    image = stack[good]
    usable = np.isfinite(image)
    image = np.where(usable, image, 0.0)
    det = mxx * myy - mxy**2
    p_xx, p_yy, p_xy = ((myy / det)[:, None, None], (mxx / det)[:, None, None],
                        (-mxy / det)[:, None, None])
    dx = np.broadcast_to(np.arange(nx)[None, None, :] - x0[:, None, None], image.shape)
    dy = np.broadcast_to(np.arange(ny)[None, :, None] - y0[:, None, None], image.shape)
    pd_x = p_xx * dx + p_xy * dy
    pd_y = p_xy * dx + p_yy * dy
    weight = np.exp(-0.5 * (dx * pd_x + dy * pd_y)) * usable
    n_good = len(x0)
    g = np.stack([dx, dy, dx**2 - 0.5 * mxx[:, None, None], dy**2 - 0.5 * myy[:, None, None],
                  dx * dy - 0.5 * mxy[:, None, None]], axis=-1).reshape(n_good, ny * nx, 5)
    # d log(w) / d theta for theta = (x0, y0, Mxx, Myy, Mxy)
    dlogw = np.stack([pd_x, pd_y, 0.5 * pd_x**2, 0.5 * pd_y**2, pd_x * pd_y],
                     axis=-1).reshape(n_good, ny * nx, 5)
    intensity_weight = (image * weight).reshape(n_good, ny * nx)
    hessian = np.einsum("np,npk,npj->nkj", intensity_weight, g, dlogw)
    # plus sum I w d g_k / d theta_j (few non-zero terms)
    total = intensity_weight.sum(axis=1)
    sum_dx = np.einsum("np,np->n", intensity_weight, dx.reshape(n_good, -1))
    sum_dy = np.einsum("np,np->n", intensity_weight, dy.reshape(n_good, -1))
    hessian[:, 0, 0] -= total
    hessian[:, 1, 1] -= total
    hessian[:, 2, 0] -= 2.0 * sum_dx
    hessian[:, 4, 0] -= sum_dy
    hessian[:, 3, 1] -= 2.0 * sum_dy
    hessian[:, 4, 1] -= sum_dx
    for index in (2, 3, 4):
        hessian[:, index, index] -= 0.5 * total
    variance = background[good][:, None, None] + (np.maximum(image, 0.0) if source_variance
                                                  else 0.0)
    wg = weight.reshape(n_good, ny * nx, 1) * g
    scatter = np.einsum("npi,np,npj->nij", wg, variance.reshape(n_good, -1), wg)
    inverse = np.linalg.inv(hessian)
    covariance = inverse @ scatter @ np.swapaxes(inverse, 1, 2)
    var_xx, var_yy, var_xy = covariance[:, 2, 2], covariance[:, 3, 3], covariance[:, 4, 4]
    sigma = det**0.25
    gradient = np.stack([sigma * myy / (4 * det), sigma * mxx / (4 * det),
                         -sigma * mxy / (2 * det)], axis=1)
    var_sigma = np.einsum("ni,nij,nj->n", gradient, covariance[:, 2:, 2:], gradient)
    errors["mxx_err"][good] = np.sqrt(var_xx)
    errors["myy_err"][good] = np.sqrt(var_yy)
    errors["mxy_err"][good] = np.sqrt(var_xy)
    errors["sigma_x_err"][good] = np.sqrt(var_xx) / (2.0 * np.sqrt(mxx))
    errors["sigma_y_err"][good] = np.sqrt(var_yy) / (2.0 * np.sqrt(myy))
    errors["sigma_err"][good] = np.sqrt(var_sigma)
    trace = mxx + myy
    for name, gradient in (("e1_err", np.stack([2 * myy, -2 * mxx, 0 * mxy], axis=1)),
                           ("e2_err", np.stack([-2 * mxy, -2 * mxy, 2 * trace], axis=1))):
        gradient = gradient / trace[:, None]**2
        errors[name][good] = np.sqrt(np.einsum("ni,nij,nj->n", gradient,
                                               covariance[:, 2:, 2:], gradient))
    return errors
