"""The verdict of a validation run (`bfpsf.validation.validate.validate`): the simulation
holds brighter-fatter alone, so the user path must predict its slopes, P(F) must leave no
residual beyond its errors, the loop must name nothing, and P(F) must beat a static PSF in
photometry. ``bfpsf validate`` ends on it (a new user read the table without knowing what to
expect) and exits 1 when it fails.
"""

import numpy as np

__all__ = ["verdict_failures", "VERDICT_CHECKS", "VERDICT_NSIGMA"]

#: What `verdict_failures` asks, in words (the PASS line).
VERDICT_CHECKS = ("the flats' predicted BF slopes within 3 sigma of the measured ones, P(F)'s "
                  "residual within 3 sigma of its errors (the calibration's included), the "
                  "loop named no instrument effect, P(F)'s photometry bias below the static "
                  "PSF's")

#: A prediction or a residual beyond this many of its errors fails the verdict.
VERDICT_NSIGMA = 3.0


def verdict_failures(result):
    """What a validation run (``validate``'s result) fails of `VERDICT_CHECKS`, in words;
    empty: it passes (the module docstring)."""
    failures = []
    slopes = result["slopes"]
    row = next((row for row in result["prediction"].get("rows", [])
                if row["shifts"] == result["model_shifts"]), None)
    calibration = {}
    for axis in "xy":
        if row is None or f"pull_{axis}" not in row:
            continue
        if abs(row[f"pull_{axis}"]) > VERDICT_NSIGMA:
            failures.append(f"{axis.upper()} slope predicted from the {row['shifts']} "
                            f"{row[f'pull_{axis}']:+.1f} sigma from the measured one")
        error = row.get(f"predicted_slope_{axis}_err")
        if error is not None:
            calibration[axis] = 100 * error / abs(slopes[f"slope_{axis}"])
    psf = result["psf"]
    if psf.get("available"):
        for axis in "xy":
            value = psf[f"residual_slope_{axis}_percent"]
            error = np.hypot(psf[f"residual_slope_{axis}_percent_err"], calibration.get(axis, 0))
            if abs(value) > VERDICT_NSIGMA * error:
                failures.append(f"P(F) leaves {value:+.1f} % of the raw {axis.upper()} slope, "
                                f"beyond {VERDICT_NSIGMA:g} x {error:.1f} %")
        static, flux_dependent = (abs(psf[f"photometry_bias_{key}_mmag"])
                                  for key in ("static", "flux_dependent"))
        if not flux_dependent < static:
            failures.append(f"P(F)'s photometry bias {flux_dependent:.2f} mmag is not below "
                            f"the static PSF's {static:.2f}")
    else:
        failures.append(f"P(F) not available ({psf.get('reason')})")
    selected = result["diagnose"]["selected"]
    if selected:
        failures.append(f"the loop named {', '.join(selected)} (a false detection)")
    return failures
