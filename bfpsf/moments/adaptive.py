"""Adaptive second moments: the size estimator of G15 section 3.2.

G15 measures the apparent size of spots and stars with elliptical Gaussian weights matched to
the object (Bernstein & Jarvis 2002, section 3; Astier et al. 2013, section 3). The estimator
finds the centroid ``x0`` and covariance ``M`` such that the image weighted by
``w(r) = exp(-rho^2 / 2)``, ``rho^2 = (r - x0)^T M^{-1} (r - x0)``, has

    sum w I (r - x0)                  = 0          (weighted centroid = x0)
    sum w I (r - x0)(r - x0)^T / sum w I = M / 2   (weighted covariance = M / 2)

These are the stationary conditions of a least-squares fit of an elliptical Gaussian to the
image with uniform pixel weights, which is why G15 calls the estimator "equivalent to fitting an
elliptical Gaussian"; for a Gaussian image ``M`` is its covariance exactly. The size is
``IQ = sigma = (Mxx Myy - Mxy^2)^(1/4)`` (G15 section 3.2, equation for IQ).

Iteration and convergence
-------------------------
The update is the one of GalSim's HSM ``find_ellipmom_2`` (Hirata & Seljak 2003)::

    x0  <- x0 + 2 B / A
    M   <- M + 4 (C / A - M / 2)

with ``A = sum w I``, ``B = sum w I (r - x0)``, ``C = sum w I (r - x0)(r - x0)^T``. For a
Gaussian image it converges quadratically (the doubled step cancels the first-order error).
Each step is expressed in units of the minor semi-axis ``b`` of the weight (``dx = 2 B / (A b)``,
``dM = 4 (C / A - M / 2) / b^2``) and clipped to +-0.25 (HSM's ``bound_correct_wt``), which keeps
the iteration stable from a poor first guess. The iteration stops when every scaled step is
below ``tolerance`` (default 1e-6, HSM's ``convergence_threshold``), and gives up after
``max_iter`` iterations (default 400, HSM's ``max_mom2_iter``) with the ``NO_CONVERGENCE`` flag.
Pixels where the weight is below ``tolerance / 10`` are left out, as in HSM.

Undersampled objects
--------------------
On a pixelised image the equations above have, besides the object's solution ``M_s``, a
spurious one at ``M = 0`` when the centroid sits on a pixel centre: a weight much narrower
than a pixel sees only the central pixel, whose moment about ``x0`` is zero, so ``C / A``
vanishes and the clipped step shrinks ``M`` by 0.25 of itself at every iteration. Along the
radius the two are separated by an unstable solution ``M_u``; started below ``M_u`` the
iteration collapses. For round Gaussians (Moffats, beta 3.5, of the same FWHM) centred on a
pixel, ``M_u`` is 0.30 (0.27) pixel^2 at sigma 0.75 pixel and 0.19 (0.19) pixel^2 at 1.2 pixel,
and ``M_s`` is 0.58 (0.75) and 1.52 (1.88) pixel^2; for a centred Gaussian of sigma 0.70
pixel no ``M_s`` exists at all and HSM fails too ("collapsed to singular moment matrix").
Started between ``M_u`` and ``M_s`` a round iteration grows towards ``M_s``; started above, it
never falls below ``max(2 M_s - M, 0.75 M) >= 0.86 M_s`` (the weighted second moment grows
with ``M``, and the clip bounds the step), which is above ``M_u`` in all these cases. HSM
starts from sigma = 5 pixels for this reason, at the cost of ~15 more iterations; the default
guess here (from the pixels above half maximum: one to four for such objects, i.e. sigma 0.5
to 1 pixel) is floored at 1 pixel, above ``M_u``. A weight whose minor semi-axis^2 falls below
0.01 pixel^2 has collapsed: the stamp is flagged ``UNDERSAMPLED`` (no solution) instead of
iterating to ``max_iter``. Stars of a double Gaussian of FWHM 1.7 pixels (GalSim
SiliconSensor) at random phases: 88 of 253 (35 %) collapse, of every flux up to 2.3e5 e-
(42 of the 44 within 0.1 pixel of a pixel centre in x); the others' sigma depends on the
phase by +-8 % (0.69 to 0.82 pixel), far more than brighter-fatter. An explicit
``guess_sigma`` is used as given.

Conventions
-----------
Stamps are arrays ``stamp[y, x]`` with pixel centres at integer coordinates, 0-based
(photutils). ``x``, ``y`` of the result are in that frame. Moments are in pixel^2.

Conversion from ``galsim.hsm.FindAdaptiveMom``: HSM returns ``moments_sigma = sigma`` and
``observed_shape`` as a `galsim.Shear` whose distortion ``(e1, e2)`` is
``e1 = (Mxx - Myy) / (Mxx + Myy)``, ``e2 = 2 Mxy / (Mxx + Myy)``. Then, with
``e^2 = e1^2 + e2^2``::

    Mxx = sigma^2 (1 + e1) / sqrt(1 - e^2)
    Myy = sigma^2 (1 - e1) / sqrt(1 - e^2)
    Mxy = sigma^2 e2 / sqrt(1 - e^2)

(see `moments_from_hsm`). HSM's ``moments_amp`` is our ``flux`` (= 2 A), and its
``moments_centroid`` is in GalSim image coordinates: subtract ``image.bounds.origin()`` to get
our 0-based ``x``, ``y``.

Noise bias
----------
Adaptive moments are a non-linear function of the pixels, so pixel noise biases them at second
order in 1/(S/N). G15 states that the mean size does not depend on S/N. For Moffat spots
(FWHM 4 pixels, beta 3.5, 32 x 32 stamps, white noise, S/N = sqrt(sum I^2) / noise as in
GalSim's ``addNoiseSNR``) we measure the mean ``sigma`` relative to the noiseless value as
(-0.63 +- 0.13)e-3 at S/N 20, (-0.10 +- 0.02)e-3 at S/N 50, (-0.025 +- 0.005)e-3 at S/N 100,
(-0.006 +- 0.001)e-3 at S/N 200 and -2.5e-7 at S/N 1000 (10^4 antithetic noise pairs each,
seed 1, ``tests/test_moments.py::_snr_bias``): a bias of -0.25 / (S/N)^2, real but below
1e-3 at every S/N from 20 up (``test_sigma_independent_of_snr_full``, 3 x 10^4 pairs at
S/N <= 30, checks bias + 3 sigma < 1e-3). No correction
is applied; below S/N ~ 15 the bias exceeds 1e-3 and should be calibrated by simulation.
"""

import numpy as np

from ..errors import BFPSFConvergenceError, BFPSFInputError, BFPSFValueError
from .result import Moments, MomentsFlag, flag_string

__all__ = ["adaptive_moments", "adaptive_moments_batch", "validate_stack"]


# ------------------------------------------------------------------------------------------
# input checks

def _validate_positive(name, value):
    if value is not None and not (np.isfinite(value) and value > 0):
        msg = f"{name} must be a positive finite number, got {value!r}"
        raise BFPSFValueError(msg, value)


def validate_stack(stamps, name="stamps"):
    try:
        stack = np.asarray(stamps, dtype=float)
    except (TypeError, ValueError):
        msg = f"{name} must be a numeric array"
        raise BFPSFInputError(msg, stamps) from None
    if stack.ndim != 3:
        msg = f"{name} must be a 3-D stack [n, y, x] of stamps, got shape {stack.shape}"
        raise BFPSFInputError(msg, stack.shape)
    if stack.shape[1] < 3 or stack.shape[2] < 3:
        msg = f"stamps must be at least 3 x 3 pixels, got {stack.shape[1:]}"
        raise BFPSFInputError(msg, stack.shape)
    return stack


def _per_stamp(value, n_stamps, name, width=1):
    """Broadcast a scalar / (width,) / (n, width) option to shape (n, width)."""
    array = np.asarray(value, dtype=float)
    try:
        array = np.broadcast_to(array.reshape(-1, width) if array.ndim else array,
                                (n_stamps, width))
    except ValueError:
        msg = f"{name} must be one value or one per stamp, got shape {np.shape(value)}"
        raise BFPSFInputError(msg, value) from None
    return np.array(array, dtype=float)


# ------------------------------------------------------------------------------------------
# the measurement

#: fraction of the matched Gaussian checked against the stamp edge and saturation, in sigma
_CHECK_NSIGMA2 = 9.0
#: clip of every scaled step (HSM bound_correct_wt)
_STEP_BOUND = 0.25
#: minimum number of usable pixels (amplitude, centroid, three moments, plus one)
_MIN_PIXELS = 6
#: floor of the default starting sigma, pixels: above the spurious M = 0 basin of undersampled
#: objects (see "Undersampled objects" in the module docstring)
_GUESS_SIGMA_MIN = 1.0
#: minor semi-axis^2 of the weight (pixel^2) below which the iteration has collapsed: pixel
#: centres 1 px away along the minor axis get weight < exp(-50), so the moment along it is 0
#: and can only shrink further (no legitimate solution is that narrow, module docstring)
_COLLAPSE_B2 = 0.01
#: stamps measured together by adaptive_moments_batch
_CHUNK = 2048


def _chunk_option(name, value, part):
    """The slice ``part`` of a per-stamp option; options shared by all stamps pass unchanged."""
    per_stamp_ndim = {"guess_sigma": 1, "saturation": 1, "centroid": 2, "weight": 3}
    if name in per_stamp_ndim and value is not None \
            and np.ndim(value) == per_stamp_ndim[name]:
        return np.asarray(value)[part]
    return value


def _initial_guess(stack, usable, guess_sigma, centroid):
    """Starting centroid (smoothed peak) and circular size (half-maximum area) per stamp."""
    n_stamps, ny, nx = stack.shape
    clean = np.where(usable, stack, 0.0)
    if centroid is None:
        # 3x3 box sum: a noise spike is less likely than the source to be the maximum
        box = clean.copy()                      # separable 3x3 box sum (edges: 2x3, 2x2)
        box[:, :, 1:] += clean[:, :, :-1]
        box[:, :, :-1] += clean[:, :, 1:]
        rows = box.copy()
        box[:, 1:, :] += rows[:, :-1, :]
        box[:, :-1, :] += rows[:, 1:, :]
        flat_index = np.argmax(box.reshape(n_stamps, -1), axis=1)
        y0, x0 = np.unravel_index(flat_index, (ny, nx))
        x0, y0 = x0.astype(float), y0.astype(float)
    else:
        position = _per_stamp(centroid, n_stamps, "centroid", width=2)
        x0, y0 = position[:, 0], position[:, 1]
    if guess_sigma is None:
        peak = clean.reshape(n_stamps, -1).max(axis=1)
        n_half = np.sum(clean > 0.5 * peak[:, None, None], axis=(1, 2))
        # a Gaussian covers 2 pi ln(2) sigma^2 pixels above half its maximum
        sigma0 = np.sqrt(np.maximum(n_half, 1) / (2.0 * np.pi * np.log(2.0)))
        # never start below 1 px: an undersampled object (1 to 4 pixels above half maximum)
        # started smaller falls into the spurious M = 0 solution (module docstring)
        sigma0 = np.clip(sigma0, _GUESS_SIGMA_MIN,
                         max(min(nx, ny) / 4.0, _GUESS_SIGMA_MIN))
    else:
        sigma0 = _per_stamp(guess_sigma, n_stamps, "guess_sigma")[:, 0]
        if np.any(~(sigma0 > 0)):
            msg = f"guess_sigma must be positive, got {guess_sigma!r}"
            raise BFPSFValueError(msg, guess_sigma)
    return x0, y0, sigma0


def _weighted_sums(image, xgrid, ygrid, x0, y0, mxx, myy, mxy, cut2):
    """A, B and C sums of HSM ``find_ellipmom_1`` for a stack (vectorised over stamps).

    Written for few passes over the (n, ny, nx) arrays, in place where possible.
    """
    det = mxx * myy - mxy**2
    dx = xgrid[None, :] - x0[:, None]                       # [n, x]
    dy = ygrid[None, :] - y0[:, None]                       # [n, y]
    # rho^2 = Minv_xx dx^2 + 2 Minv_xy dx dy + Minv_yy dy^2
    rho2 = np.multiply(dy[:, :, None], dx[:, None, :])
    rho2 *= (-2.0 * mxy / det)[:, None, None]
    rho2 += ((myy / det)[:, None] * dx**2)[:, None, :]
    rho2 += ((mxx / det)[:, None] * dy**2)[:, :, None]
    # the HSM cut: weights below tolerance / 10 are dropped (where rho2 > cut2)
    np.minimum(rho2, 2.0 * cut2, out=rho2)
    rho2 *= -0.5
    weighted = np.exp(rho2, out=rho2)
    weighted[weighted < np.exp(-0.5 * cut2)] = 0.0
    weighted *= image
    row_sum = weighted.sum(axis=1)                         # [n, x]
    projections = weighted @ np.stack([np.ones_like(xgrid), xgrid], axis=1)   # [n, y, 2]
    col_sum = projections[:, :, 0]                         # [n, y]
    amp = row_sum.sum(axis=1)
    sum_x = row_sum @ xgrid
    sum_y = col_sum @ ygrid
    sum_xx = row_sum @ xgrid**2
    sum_yy = col_sum @ ygrid**2
    sum_xy = projections[:, :, 1] @ ygrid
    # moments about (x0, y0) from the moments about the origin
    bx = sum_x - x0 * amp
    by = sum_y - y0 * amp
    cxx = sum_xx - 2.0 * x0 * sum_x + x0**2 * amp
    cyy = sum_yy - 2.0 * y0 * sum_y + y0**2 * amp
    cxy = sum_xy - x0 * sum_y - y0 * sum_x + x0 * y0 * amp
    return amp, bx, by, cxx, cyy, cxy


def adaptive_moments_batch(stamps, *, guess_sigma=None, centroid=None, weight=None,
                           saturation=None, max_iter=400, tolerance=1e-6, strict=False):
    """Adaptive second moments of a stack of stamps (G15 section 3.2), vectorised.

    See the module docstring for the estimator, the iteration and its convergence.

    Parameters
    ----------
    stamps : array_like, shape (n, ny, nx)
        Background-subtracted stamps, any flux unit (electrons in bfpsf).
    guess_sigma : float or array_like of shape (n,), optional
        Starting Gaussian sigma, pixels. Default: from the number of pixels above half the
        maximum, at least 1 pixel (a guess far below the object's size can collapse onto
        one pixel on undersampled objects; module docstring).
    centroid : array_like of shape (2,) or (n, 2), optional
        Starting ``(x, y)``, 0-based pixels. Default: the maximum of the 3x3 box-summed stamp.
    weight : array_like, shape (ny, nx) or (n, ny, nx), optional
        Non-negative per-pixel weights multiplying the Gaussian weight; 0 masks a bad pixel
        (as the HSM ``badpix`` / ``weight`` mask). Non-finite pixels are always masked.
    saturation : float or array_like of shape (n,), optional
        Pixels at or above this value (stamp units) inside the 3-sigma ellipse set
        ``SATURATED``. They are still used (as HSM would).
    max_iter : int, optional
        Iteration limit (default 400, HSM's ``max_mom2_iter``).
    tolerance : float, optional
        Convergence threshold on every step scaled by the weight's minor axis (default 1e-6,
        HSM's ``convergence_threshold``).
    strict : bool, optional
        Raise `BFPSFConvergenceError` (no convergence) or `BFPSFValueError` (any other flag
        except ``BAD_PIXELS``, ``EDGE`` and ``SATURATED``, which are informative) instead of
        returning flags. Default False.

    Returns
    -------
    Moments
        Fields are arrays of length n; moments of stamps with a `MomentsFlag.FATAL` flag are
        NaN.
    """
    stack = validate_stack(stamps)
    _validate_positive("tolerance", tolerance)
    n_stamps, ny, nx = stack.shape
    if n_stamps > _CHUNK:
        # bounded memory (a few arrays of the chunk's size) and better cache use
        options = dict(guess_sigma=guess_sigma, centroid=centroid, weight=weight,
                       saturation=saturation, max_iter=max_iter, tolerance=tolerance,
                       strict=strict)
        parts = []
        for start in range(0, n_stamps, _CHUNK):
            part = slice(start, start + _CHUNK)
            chunk_options = {key: _chunk_option(key, value, part)
                             for key, value in options.items()}
            parts.append(adaptive_moments_batch(stack[part], **chunk_options))
        return Moments(**{name: np.concatenate([getattr(part, name) for part in parts])
                          for name in Moments.__dataclass_fields__})
    if saturation is not None:
        saturation = _per_stamp(saturation, n_stamps, "saturation")[:, 0]
        if np.any(~np.isfinite(saturation)):
            msg = f"saturation must be finite, got {saturation!r}"
            raise BFPSFValueError(msg, saturation)
    if not (int(max_iter) == max_iter and max_iter >= 1):
        msg = f"max_iter must be a positive integer, got {max_iter!r}"
        raise BFPSFValueError(msg, max_iter)

    usable = np.isfinite(stack)
    flags = np.where(usable.all(axis=(1, 2)), 0, MomentsFlag.BAD_PIXELS)
    if weight is not None:
        pixel_weight = np.asarray(weight, dtype=float)
        if pixel_weight.shape not in (stack.shape[1:], stack.shape):
            msg = (f"weight must have the stamp shape {stack.shape[1:]} or the stack shape "
                   f"{stack.shape}, got {pixel_weight.shape}")
            raise BFPSFInputError(msg, pixel_weight.shape)
        if np.any(~np.isfinite(pixel_weight)) or np.any(pixel_weight < 0):
            msg = "weight must be finite and non-negative"
            raise BFPSFInputError(msg, weight)
        pixel_weight = np.broadcast_to(pixel_weight, stack.shape)
        usable = usable & (pixel_weight > 0)
        with np.errstate(invalid="ignore"):  # inf * 0 where unusable: not used
            image = np.where(usable, stack * np.where(usable, pixel_weight, 0.0), 0.0)
    else:
        image = np.where(usable, stack, 0.0)
    flags = flags | np.where(usable.sum(axis=(1, 2)) < _MIN_PIXELS, MomentsFlag.TOO_FEW_PIXELS, 0)

    x0, y0, sigma0 = _initial_guess(stack, usable, guess_sigma, centroid)
    mxx, myy, mxy = sigma0**2, sigma0**2, np.zeros(n_stamps)
    amp = np.zeros(n_stamps)
    n_iter = np.zeros(n_stamps, dtype=int)
    xgrid = np.arange(nx, dtype=float)
    ygrid = np.arange(ny, dtype=float)
    cut2 = -2.0 * np.log(tolerance / 10.0)
    max_moment = float(max(nx, ny)) ** 2            # the weight cannot outgrow the stamp

    active = np.flatnonzero(flags & MomentsFlag.FATAL == 0)
    converged = np.zeros(n_stamps, dtype=bool)
    shiftscale0 = None
    for iteration in range(int(max_iter)):
        if active.size == 0:
            break
        # only the pixels inside the weight cut of some active stamp matter (exactly)
        reach_x = np.sqrt(cut2 * np.clip(mxx[active], 0.0, max_moment))
        reach_y = np.sqrt(cut2 * np.clip(myy[active], 0.0, max_moment))
        x_lo = int(np.clip(np.floor(np.min(x0[active] - reach_x)), 0, nx - 1))
        x_hi = int(np.clip(np.ceil(np.max(x0[active] + reach_x)) + 1, x_lo + 1, nx))
        y_lo = int(np.clip(np.floor(np.min(y0[active] - reach_y)), 0, ny - 1))
        y_hi = int(np.clip(np.ceil(np.max(y0[active] + reach_y)) + 1, y_lo + 1, ny))
        window = image[active] if active.size < n_stamps else image
        sums = _weighted_sums(window[:, y_lo:y_hi, x_lo:x_hi], xgrid[x_lo:x_hi],
                              ygrid[y_lo:y_hi], x0[active], y0[active], mxx[active],
                              myy[active], mxy[active], cut2)
        a_sum, bx, by, cxx, cyy, cxy = sums
        amp[active] = a_sum
        n_iter[active] = iteration + 1
        bad_flux = ~(a_sum > 0)
        # minor semi-axis^2 of the weight ellipse (HSM semi_b2)
        m_xx, m_yy, m_xy = mxx[active], myy[active], mxy[active]
        half_trace = 0.5 * (m_xx + m_yy)
        semi_b2 = half_trace - np.sqrt((0.5 * (m_xx - m_yy))**2 + m_xy**2)
        shiftscale = np.sqrt(np.maximum(semi_b2, 0.0))
        if iteration == 0:
            shiftscale0 = np.zeros(n_stamps)
            shiftscale0[active] = shiftscale
        with np.errstate(divide="ignore", invalid="ignore"):
            step_x = np.clip(2.0 * bx / (a_sum * shiftscale), -_STEP_BOUND, _STEP_BOUND)
            step_y = np.clip(2.0 * by / (a_sum * shiftscale), -_STEP_BOUND, _STEP_BOUND)
            step_xx = np.clip(4.0 * (cxx / a_sum - 0.5 * m_xx) / semi_b2, -_STEP_BOUND, _STEP_BOUND)
            step_yy = np.clip(4.0 * (cyy / a_sum - 0.5 * m_yy) / semi_b2, -_STEP_BOUND, _STEP_BOUND)
            step_xy = np.clip(4.0 * (cxy / a_sum - 0.5 * m_xy) / semi_b2, -_STEP_BOUND, _STEP_BOUND)
            factor = np.max(np.abs([step_x, step_y, step_xx, step_yy, step_xy]), axis=0)
            factor = factor * np.maximum(shiftscale0[active] / shiftscale, 1.0)
        x0[active] += step_x * shiftscale
        y0[active] += step_y * shiftscale
        mxx[active] += step_xx * semi_b2
        myy[active] += step_yy * semi_b2
        mxy[active] += step_xy * semi_b2
        new_det = mxx[active] * myy[active] - mxy[active]**2
        not_pd = ~((mxx[active] > 0) & (myy[active] > 0) & (new_det > 0)
                   & (mxx[active] < max_moment) & (myy[active] < max_moment)
                   & np.isfinite(factor))
        # semi_b2 <= _COLLAPSE_B2: a weight narrower than the pixel has collapsed onto one
        # pixel, the undersampled object has no solution (module docstring): named as such
        collapsed = ~not_pd & ~(semi_b2 > _COLLAPSE_B2)
        flags[active] |= np.where(collapsed & ~bad_flux, MomentsFlag.UNDERSAMPLED, 0)
        outside = ((x0[active] < -0.5) | (x0[active] > nx - 0.5)
                   | (y0[active] < -0.5) | (y0[active] > ny - 0.5))
        flags[active] |= np.where(bad_flux, MomentsFlag.NONPOSITIVE_FLUX, 0)
        flags[active] |= np.where(not_pd & ~bad_flux, MomentsFlag.NOT_POSITIVE_DEFINITE, 0)
        flags[active] |= np.where(outside & ~bad_flux & ~not_pd & ~collapsed,
                                  MomentsFlag.EDGE, 0)
        done = (factor <= tolerance) & ~bad_flux & ~not_pd & ~collapsed & ~outside
        converged[active[done]] = True
        active = active[~(done | bad_flux | not_pd | collapsed | outside)]
    flags[active] |= MomentsFlag.NO_CONVERGENCE
    flags[~converged & (flags & MomentsFlag.EDGE > 0)] |= MomentsFlag.NO_CONVERGENCE

    fatal = (flags & MomentsFlag.FATAL) > 0
    with np.errstate(invalid="ignore"):
        det = mxx * myy - mxy**2
        sigma = det ** 0.25
    for values in (mxx, myy, mxy, x0, y0, sigma):
        values[fatal] = np.nan
    flux = np.where(fatal, np.nan, 2.0 * amp)
    amplitude = flux / (2.0 * np.pi * sigma**2)

    flags |= _final_checks(stack, usable, x0, y0, mxx, myy, mxy, saturation, fatal)
    result = Moments(mxx=mxx, myy=myy, mxy=mxy, x=x0, y=y0, amplitude=amplitude, flux=flux,
                     sigma=sigma, n_iter=n_iter, flags=flags)
    if strict:
        _raise_if_flagged(result)
    return result


def _final_checks(stack, usable, x0, y0, mxx, myy, mxy, saturation, fatal):
    """EDGE, SATURATED and TOO_FEW_PIXELS inside the 3-sigma ellipse of the result."""
    n_stamps, ny, nx = stack.shape
    flags = np.zeros(n_stamps, dtype=int)
    good = ~fatal
    if not np.any(good):
        return flags
    index = np.flatnonzero(good)
    reach_x = np.sqrt(_CHECK_NSIGMA2 * mxx[index])
    reach_y = np.sqrt(_CHECK_NSIGMA2 * myy[index])
    crosses = ((x0[index] - reach_x < -0.5) | (x0[index] + reach_x > nx - 0.5)
               | (y0[index] - reach_y < -0.5) | (y0[index] + reach_y > ny - 0.5))
    flags[index] |= np.where(crosses, MomentsFlag.EDGE, 0)
    det = mxx[index] * myy[index] - mxy[index]**2
    dx = np.arange(nx)[None, None, :] - x0[index, None, None]
    dy = np.arange(ny)[None, :, None] - y0[index, None, None]
    rho2 = (myy[index, None, None] * dx**2 - 2.0 * mxy[index, None, None] * dx * dy
            + mxx[index, None, None] * dy**2) / det[:, None, None]
    inside = rho2 < _CHECK_NSIGMA2
    n_inside = np.sum(inside & usable[index], axis=(1, 2))
    flags[index] |= np.where(n_inside < _MIN_PIXELS, MomentsFlag.TOO_FEW_PIXELS, 0)
    if saturation is not None:
        with np.errstate(invalid="ignore"):
            hot = np.any(inside & usable[index]
                         & (stack[index] >= saturation[index, None, None]), axis=(1, 2))
        flags[index] |= np.where(hot, MomentsFlag.SATURATED, 0)
    return flags


_INFORMATIVE = MomentsFlag.BAD_PIXELS | MomentsFlag.EDGE | MomentsFlag.SATURATED


def _raise_if_flagged(result):
    flags = np.atleast_1d(result.flags)
    for index, value in enumerate(flags):
        value = int(value)
        if value & MomentsFlag.NO_CONVERGENCE:
            msg = (f"adaptive moments did not converge for stamp {index} "
                   f"after {int(np.atleast_1d(result.n_iter)[index])} iterations "
                   f"(flags: {flag_string(value)})")
            raise BFPSFConvergenceError(msg)
        if value & ~_INFORMATIVE:
            msg = f"adaptive moments failed for stamp {index}: {flag_string(value)}"
            raise BFPSFValueError(msg, value)


def adaptive_moments(stamp, *, guess_sigma=None, centroid=None, weight=None, saturation=None,
                     max_iter=400, tolerance=1e-6, strict=False):
    """Adaptive second moments of one stamp (G15 section 3.2; Bernstein & Jarvis 2002).

    Parameters are those of `adaptive_moments_batch` for a single 2-D ``stamp[y, x]``.

    Returns
    -------
    Moments
        Scalar fields. ``sigma`` is G15's IQ = (Mxx Myy - Mxy^2)^(1/4), pixels.

    Raises
    ------
    BFPSFInputError
        If ``stamp`` is not a 2-D numeric array.
    BFPSFConvergenceError, BFPSFValueError
        Only with ``strict=True``, for a flagged measurement.

    Notes
    -----
    For many stamps use `adaptive_moments_batch`: it is vectorised over the stack (about 1.7
    times the throughput of a Python loop over ``galsim.hsm.FindAdaptiveMom`` on 32 x 32
    stamps, ``benchmarks/bench_moments.py``), while a loop over this function pays the numpy
    overhead per stamp (about 10 times slower than HSM).

    Examples
    --------
    >>> import numpy as np
    >>> y, x = np.mgrid[:32, :32]
    >>> stamp = np.exp(-((x - 15.3)**2 / 4.0 + (y - 16.1)**2 / 2.25) / 2)
    >>> m = adaptive_moments(stamp)
    >>> print(f"{m.mxx:.4f} {m.myy:.4f} {m.x:.3f} {m.flag_string}")
    4.0000 2.2500 15.300 ok
    """
    array = np.asarray(stamp, dtype=float) if not isinstance(stamp, np.ndarray) else stamp
    if np.ndim(array) != 2:
        msg = f"stamp must be a 2-D array [y, x], got shape {np.shape(array)}"
        raise BFPSFInputError(msg, np.shape(array))
    if weight is not None and np.ndim(weight) != 2:
        msg = f"weight must be a 2-D array like the stamp, got shape {np.shape(weight)}"
        raise BFPSFInputError(msg, np.shape(weight))
    result = adaptive_moments_batch(array[None], guess_sigma=guess_sigma, centroid=centroid,
                                    weight=weight, saturation=saturation, max_iter=max_iter,
                                    tolerance=tolerance, strict=strict)
    values = {}
    for name in Moments.__dataclass_fields__:
        value = np.asarray(getattr(result, name))[0]
        values[name] = int(value) if name in ("n_iter", "flags") else float(value)
    return Moments(**values)
