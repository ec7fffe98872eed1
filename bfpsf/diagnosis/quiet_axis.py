"""The flats' BF scale fitted on the axis an undeclared effect leaves alone.

The size scale (`bfpsf.diagnosis.nuisances.SCALE`) is the flats' error, the same in every
exposure, at every position and on both axes. An effect outside the catalogue that grows over
the night (or with the row, or the column) on one axis makes the scale fitted on both axes
change with it, so its signature is contradicted (`bfpsf.diagnosis.signature`) and the loop
drops it. Without it, the flats' own error is left to the EMPIRICAL term in the shape of its
patterns, and on the other axis it reads as a second undeclared effect: a new user's
SiliconSensor stars (34-48 % less BF than their flats predict, which the scale took on the
control set) with a Y smear growing over the night were reported with an X effect of 9.4
sigma "falling with flux", and their PSF photometry drifted by +0.63 mmag faint to bright
against the control (+1.20 on the last exposure), the faint stars too bright.

Where the unexplained residual's dependence that contradicted the scale lies on one axis
only, the other axis is quiet: the loop is run again with the dependent axis's sizes given no
weight, the scale free (its X / Y split, which one axis cannot tell from the scale, held at the
flats'), and the scale's signature tested on the quiet axis in every dimension. Where it
matches there, the scale is kept, fitted beside the undeclared effect; the held-out residual,
the unexplained report and the EMPIRICAL term are then those of both axes with it.
"""

import dataclasses

import numpy as np

from .empirical_fit import adaptive_response, fit_empirical, predicted_size_change
from .heldout import _evaluate, _kept_step, _size_residual, with_heldout
from .nuisances import SCALE, SPLIT, without_priors
from .problem import summarise

__all__ = ["quiet_axis", "scale_beside_the_effect", "DEPENDENCES"]

#: The signature dimensions of a dependence on where or when a star was taken: the
#: unexplained report's key for each, and the EMPIRICAL term's (`bfpsf.model.empirical`:
#: its coefficients ``name`` and ``flux2_name``).
DEPENDENCES = {"exposure_order": ("exposure_dependence", "exposure"),
               "position": ("position_dependence", "position"),
               "row": ("row_dependence", "row")}

#: How much the dependent axis's size errors are inflated: no weight in the fit.
_NO_WEIGHT = 1e6


def quiet_axis(unexplained, dimension):
    """The axis ('x' or 'y') whose size residual shows no dependence of the kind
    ``dimension`` names (a key of `DEPENDENCES`) where the other axis's does; None
    otherwise (both axes or neither, or a contradiction of another kind)."""
    if dimension not in DEPENDENCES:
        return None
    key = DEPENDENCES[dimension][0]
    dependent = [entry["axis"] for entry in unexplained if entry["observable"] == "sizes"
                 and (entry.get(key) or {}).get("kind", "none") != "none"]
    if len(dependent) != 1:
        return None
    return "y" if dependent[0] == "x" else "x"


def _one_axis(observables, axis, leak=None):
    """``observables`` with the sizes of the axis other than ``axis`` given no weight, and
    those of ``axis`` less ``leak`` (pixels) where given."""
    sizes = observables.sizes
    error = "sigma_y_err" if axis == "x" else "sigma_x_err"
    changes = {error: getattr(sizes, error) * _NO_WEIGHT}
    if leak is not None:
        name = f"sigma_{axis}"
        changes[name] = getattr(sizes, name) - leak
    return dataclasses.replace(observables, sizes=dataclasses.replace(sizes, **changes))


def _leak(result, state, axis, dimension):
    """What the effect on the other axis does to the quiet axis's measured sizes: a function
    of a part of the observables, giving pixels.

    The loop measures adaptive (Gaussian-weighted) sizes: where a star grows along one axis,
    its weight grows too, and a profile that is not a Gaussian then reads another size along
    the other axis (a Moffat's X size follows a Y smear by about 8 % of its Y change). An
    EMPIRICAL term with the other axis's pattern alone, and the dependence the report gives
    it, is fitted to the residual without the scale; the change of the quiet axis's measured
    size (`adaptive_response`) by its dependent part is the leak. Its constant part holds the
    scale's own error on that axis too, whose leak the scale's template already has: it is
    left, and with it the leak of the effect's mean level, which the scale then takes. On
    the bench (stars with 0.9 of the flats' BF, a scale of -0.1), with a charge-dependent
    transfer along Y growing over the night: contradicted on X too without the leak
    (exposure order, p = 4e-5), -0.039 +- 0.015 with it (-0.088 +- 0.016 for half the
    transfer); with a smear whose variance grows with the flux, -0.046 +- 0.016. Taking out
    all of the term's leak instead (-0.143 and, fitted again beside that scale, -0.151 for
    the smear) overshoots: the term's pattern has the transfer's shape, not the smear's
    (`bfpsf.model.empirical`), and its response is the pattern's."""
    part = state["observables"]
    model = part.spot_model
    response = adaptive_response(model, float(np.median(part.sizes.peak_e)))
    name = DEPENDENCES[dimension][1]
    term = fit_empirical(part.sizes, model.fluxes(part.sizes.peak_e),
                         model.sizes(part.sizes.peak_e),
                         _size_residual(state, part, _kept_step(result, state,
                                                                result.confirmed)),
                         response=response, **{name: True})
    other = "yy" if axis == "x" else "xx"
    dependent = (name, f"flux2_{name}")
    term = dataclasses.replace(term, coefficients={
        pattern: {key: (value if pattern == other and key in dependent else 0.0)
                  for key, value in terms.items()}
        for pattern, terms in term.coefficients.items()})

    def leak(observables):
        sizes = observables.sizes
        return predicted_size_change(term, sizes, model.fluxes(sizes.peak_e),
                                     model.sizes(sizes.peak_e), response)["xy".index(axis)]

    return leak


def scale_beside_the_effect(result, state, contradicted, given, run_loop, fraction):
    """The loop run again with the scale fitted on the quiet axis, where the scale was
    contradicted by a dependence on one axis (module docstring).

    Parameters
    ----------
    result, state
        The loop's result and state run without the contradicted nuisances, the result with
        its held-out residual (`with_heldout`: its unexplained entries).
    contradicted : dict
        The contradicted global nuisances' entries, by name.
    given : (Observables, Observables, Observables)
        All the observables, the fit part and the held-out part as the user gave them (the
        scale's and split's priors in their ``meta``).
    run_loop : callable
        ``run_loop(fit_part) -> (result, state)``, the loop.
    fraction : float
        The held-out fraction.

    Returns
    -------
    (result, state, observables, heldout) or None
        The result of the loop on the quiet axis: its scale entry says where it was fitted,
        its in-sample before and after and its held-out residual are on both axes, and the
        scale is confirmed on the held-out quiet axis (the other holds the undeclared effect,
        which the scale does not claim to explain); its state, holding both axes of the fit
        part; and the observables and held-out part without the split's prior, as the
        EMPIRICAL term and the verdict take them. None where the rule does not apply or the
        scale's signature is contradicted on the quiet axis too.
    """
    against = (contradicted.get(SCALE.name) or {}).get("contradicted_by")
    axis = quiet_axis(result.unexplained, against)
    if axis is None or given[1].sizes is None:
        return None
    # the split moves one axis against the other: from one axis it is the scale's twin
    observables, both, heldout = (without_priors(part, (SPLIT.error_key,)) for part in given)
    leak = _leak(result, state, axis, against)
    quiet, state = run_loop(_one_axis(both, axis, leak(both)))
    entry = quiet.nuisance.get(SCALE.name)
    if entry is None or entry.get("contradicted_by"):
        return None
    other = "y" if axis == "x" else "x"
    entry = dict(entry, fitted_on=f"the {axis.upper()} sizes alone",
                 why=(f"on both axes it was contradicted by {against}: the {other.upper()} "
                      f"residual depends on it, the {axis.upper()} residual does not"))
    others = {name: value for name, value in contradicted.items() if name != SCALE.name}
    quiet = dataclasses.replace(quiet, nuisance=dict(quiet.nuisance, **others,
                                                     **{SCALE.name: entry}))
    # the held-out evaluation and the EMPIRICAL term see both axes, with the split at the
    # flats' (no column for it)
    state = dict(state, observables=both)
    quiet = _in_sample(quiet, state, both)
    if heldout is None:
        return quiet, state, observables, None
    judged = with_heldout(quiet, state, _one_axis(heldout, axis, leak(heldout)), fraction)
    quiet = with_heldout(quiet, state, heldout, fraction, confirmed=judged.confirmed)
    return quiet, state, observables, heldout


def _in_sample(result, state, fit_part):
    """``result`` with its in-sample before and after measured on both axes of
    ``fit_part`` (the loop fitted one)."""
    summaries = []
    for step in (state["steps"][0], state["steps"][-1]):
        problem, model, _ = _evaluate(state, fit_part, step)
        summaries.append(summarise(problem, fit_part, model))
    return dataclasses.replace(result, residual_before=summaries[0],
                               residual_after=summaries[1])
