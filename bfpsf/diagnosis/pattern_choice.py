"""What a refined calibration does to the held-out stars' pixels, and the EMPIRICAL pattern
kind those pixels prefer.

The loop fits sizes; it never fits the stars' pixels. `refined_star_residual` stacks the
held-out exposures' stars against P(F) from the flats' calibration and from a refined one,
each through the user's path (`bfpsf.diagnosis.star_residual.star_residual_with`). The sizes
cannot tell the EMPIRICAL term's pattern kinds apart (`bfpsf.model.empirical_patterns`: a
transfer of each pixel's charge to its neighbours, a smear growing with the star's flux, each
also to a Gaussian reach of pixels); the pixels can, and `keep_the_pattern_the_pixels_prefer`
keeps the kind whose refined calibration leaves the stars' own chi2 per pixel the lowest
(each star against its P(F), averaged over the stars), every kind on the sky the flats'
P(F) found (one P0 fit each, where the user's path makes three with its sky). The stack's
chi2 had chosen before: the mean residual over the stars, of which P0 takes the
flux-independent part, and on a new user's halo of the brightest pixels it kept the
neighbours' transfer (1.03 against 1.06 for the reach of 4 px, whose held-out photometry
drift is the smaller; see docs/undeclared_effects.md).
"""

import dataclasses

from .refine import refine_calibration
from .star_residual import star_residual_with

__all__ = ["refined_star_residual", "keep_the_pattern_the_pixels_prefer"]


def refined_star_residual(observables, refined, heldout, *, flats=None, amp=None,
                          background=None, saturation=None, cache=None):
    """The stacked star residual of the held-out exposures (every exposure without a split)
    against P(F) from the flats' calibration (``flats``: one computed before) and from the
    refined one (None: the flats' alone): {``exposures``, ``heldout``, ``flats``,
    ``refined``}, each of the last two
    {``chi2_per_pixel``, ``stars_chi2_per_pixel``, ``rms_over_peak``, ``n_stars``} or
    None. ``amp``, ``background``, ``saturation``: as ``bfpsf diagnose``; ``cache``: kept
    between calls on the same images (`bfpsf.diagnosis.star_residual.star_residual_with`)."""
    paths = observables.meta["image_paths"]
    exposures = list(heldout or range(len(paths)))
    out = {"exposures": exposures, "heldout": bool(heldout)}
    if flats is not None:
        out["flats"] = flats
    for label, calibration in (("flats", observables.meta["calibration"]),
                               ("refined", refined)):
        if label in out or calibration is None:
            continue
        star = star_residual_with(calibration, paths, exposures, amp=amp,
                                  background=background, saturation=saturation, cache=cache)
        out[label] = None if star is None else {key: star[key] for key in (
            "chi2_per_pixel", "stars_chi2_per_pixel", "rms_over_peak", "n_stars")}
    return out


def keep_the_pattern_the_pixels_prefer(result, observables, **options):
    """The loop's result with the EMPIRICAL term of the pattern kind whose refined calibration
    leaves the lowest stars' own chi2 per pixel on the held-out exposures, each kind's P0
    fitted on the sky that the flats' P(F) found there, and what was compared ({``kind``,
    ``chi2_per_pixel`` (the stars' own) by kind, ``star_residual`` of the kind kept, through
    the user's path: `refined_star_residual`});
    (result, None) where there is nothing to choose (no term, or one kind validated).

    Parameters
    ----------
    result : DiagnosisResult
        `bfpsf.diagnosis.diagnose`'s, of images (``observables.meta`` holds the image paths
        and the flats' calibration).
    observables : Observables
    **options
        ``amp``, ``background``, ``saturation``, ``cache``, as `refined_star_residual`.
    """
    if not result.empirical or not result.empirical_alternatives:
        return result, None
    heldout = (result.holdout or {}).get("heldout_exposures")
    paths = observables.meta["image_paths"]
    options = dict(options, cache={} if options.get("cache") is None else options["cache"])
    # the flats' P(F) through the user's path first: every kind is then compared on the sky
    # its fit found (one P0 fit per image and kind, where the path makes three)
    path = refined_star_residual(observables, None, heldout, **options)
    flats, exposures = path["flats"], path["exposures"]
    tried = {}
    for record in (result.empirical, *result.empirical_alternatives.values()):
        candidate = dataclasses.replace(result, empirical=record)
        refined = refine_calibration(observables.meta["calibration"], candidate)
        if "empirical" not in refined.refinement["applied"]:
            continue  # not validated out of sample: not applied whatever its pixels say
        star = star_residual_with(refined, paths, exposures, same_sky=True, **options)
        if star is not None:
            tried[record["pattern"]] = (star["stars_chi2_per_pixel"], candidate, refined)
    if len(tried) < 2:
        return result, None
    kind = min(tried, key=lambda name: tried[name][0])
    others = {name: tried[name][1].empirical for name in tried if name != kind}
    chosen = dataclasses.replace(tried[kind][1], empirical_alternatives=others)
    # the kind kept, through the user's path
    star = refined_star_residual(observables, tried[kind][2], heldout, flats=flats, **options)
    return chosen, {"kind": kind, "star_residual": star,
                    "chi2_per_pixel": {name: value[0] for name, value in tried.items()}}
