"""Mutation check: each physics operator broken by a sign or a factor of two must fail a quick test.

For every mutation below, the quick tests named beside it run with the operator replaced
(``pytest -x -p mutation_check``, the mutation chosen by ``BFPSF_MUTATION``); the mutation is
*caught* when at least one of them fails. A mutation that every test survives is a physics
error the suite cannot see (issue 24: a test that cannot fail is a defect).

The replacement is made in every bfpsf module that holds the operator (``from .x import f``
copies the name), before the tests are collected.

Run: ``OMP_NUM_THREADS=1 python tools/mutation_check.py [--only NAME]`` (a few minutes:
``-x`` stops each run at its first failure). Prints one line per mutation (caught by which
test, or SURVIVED) and exits 1 if any survived.
"""

import argparse
import dataclasses
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _scaled_delta(original, factor):
    """An operator image -> image returning image + factor * (its change of the image)."""
    def mutated(image, *args, **kwargs):
        out = original(image, *args, **kwargs)
        return np.asarray(image, dtype=float) + factor * (out - np.asarray(image, dtype=float))
    return mutated


def _redistribution_factor(original, factor):
    def mutated(*args, **kwargs):
        kwargs["factor"] = factor * kwargs.get("factor", 0.5)
        return original(*args, **kwargs)
    return mutated


def _moments(original, **changes):
    def mutated(*args, **kwargs):
        result = original(*args, **kwargs)
        return dataclasses.replace(result, **{name: change(getattr(result, name))
                                              for name, change in changes.items()})
    return mutated


def _covariance_x2(original):
    def mutated(*args, **kwargs):
        cov, npix = original(*args, **kwargs)
        return 2.0 * cov, npix
    return mutated


def _gain_x2(original):
    def mutated(*args, **kwargs):
        fit = original(*args, **kwargs)
        return dataclasses.replace(fit, gain=2.0 * fit.gain)
    return mutated


def _density_x2(original):
    def mutated(*args, **kwargs):
        pixels, (north, east) = original(*args, **kwargs)
        return pixels, (2.0 * north, 2.0 * east)
    return mutated


def _negated(original):
    def mutated(*args, **kwargs):
        return -original(*args, **kwargs)
    return mutated


def _doubled(original):
    def mutated(*args, **kwargs):
        return 2.0 * original(*args, **kwargs)
    return mutated


def _cdmodel_x2(original):
    def mutated(shifts, *args, **kwargs):
        return original(shifts.scaled(2.0), *args, **kwargs)
    return mutated


def _b_term_x2(original):
    def mutated(mean_e, a, c, *args, **kwargs):
        return original(mean_e, a, 2.0 * c, *args, **kwargs)
    return mutated


def _sky_high(original):
    def mutated(*args, **kwargs):
        sky = original(*args, **kwargs)
        coefficients = (sky.coefficients[0] + 5.0 * max(sky.rms, 1.0),) + sky.coefficients[1:]
        return dataclasses.replace(sky, coefficients=coefficients)
    return mutated


def _wings_x2(original):
    def mutated(*args, **kwargs):
        skies, wings = original(*args, **kwargs)
        return skies, dataclasses.replace(
            wings, coefficients=tuple(2 * value for value in wings.coefficients),
            fraction=2 * wings.fraction)
    return mutated


#: name -> (module, function, how it is broken, the quick tests that must catch it)
MUTATIONS = {
    "redistribution x2": ("bfpsf.model.redistribution", "add_redistribution",
                          lambda f: _redistribution_factor(f, 2.0),
                          ["tests/test_galsim_sensor.py", "tests/test_photometry.py"]),
    "redistribution sign": ("bfpsf.model.redistribution", "add_redistribution",
                            lambda f: _redistribution_factor(f, -1.0),
                            ["tests/test_galsim_sensor.py", "tests/test_photometry.py"]),
    "inverse x2": ("bfpsf.model.inverse", "correct", lambda f: _scaled_delta(f, 2.0),
                   ["tests/test_redistribution.py"]),
    "build-up x2": ("bfpsf.model.buildup", "redistribute_buildup",
                    lambda f: _scaled_delta(f, 2.0),
                    ["tests/test_psf_model.py", "tests/test_redistribution.py"]),
    "exact density x2": ("bfpsf.model.density", "exact_boundary_density", _density_x2,
                         ["tests/test_psf_model.py", "tests/test_redistribution.py"]),
    "R table sign": ("bfpsf.model.bf_term", "bf_response_table", _negated,
                     ["tests/test_psf_model.py"]),
    "moments mxx x2": ("bfpsf.moments.adaptive", "adaptive_moments_batch",
                       lambda f: _moments(f, mxx=lambda v: 2.0 * v), ["tests/test_moments.py"]),
    "moments mxy sign": ("bfpsf.moments.adaptive", "adaptive_moments_batch",
                         lambda f: _moments(f, mxy=lambda v: -v), ["tests/test_moments.py"]),
    "covariance x2": ("bfpsf.calibration.covariance", "covariance_map", _covariance_x2,
                      ["tests/test_covariance.py"]),
    "PTC gain x2": ("bfpsf.calibration.ptc", "fit_ptc", _gain_x2, ["tests/test_ptc.py"]),
    "sky high by 5 rms": ("bfpsf.measure.sky", "estimate_sky", _sky_high,
                          ["tests/test_defaults_matrix.py"]),
    "wings x2": ("bfpsf.measure.total_flux", "fit_sky_and_wings", _wings_x2,
                 ["tests/test_total_flux_wings.py"]),
    "cdmodel a_t x2": ("bfpsf.interop.cdmodel", "shifts_to_cdmodel", _cdmodel_x2,
                       ["tests/test_galsim_sensor.py", "tests/test_redistribution.py"]),
    "A+19 b term x2": ("bfpsf.calibration.ptc_full", "_model_electrons", _b_term_x2,
                       ["tests/test_ptc.py"]),
    "electrostatic area x2": ("bfpsf.calibration.shifts_electrostatic", "electrostatic_area",
                              _doubled, ["tests/test_shifts_electrostatic.py"]),
}


def _all_bfpsf_modules():
    import importlib
    import pkgutil

    import bfpsf

    for info in pkgutil.walk_packages(bfpsf.__path__, "bfpsf."):
        if ".piff" in info.name or info.name.endswith("__main__"):
            continue
        importlib.import_module(info.name)


def pytest_configure(config):
    """The pytest plug-in side: break the operator named by ``BFPSF_MUTATION``."""
    import importlib

    module_name, function, mutate, _ = MUTATIONS[os.environ["BFPSF_MUTATION"]]
    _all_bfpsf_modules()
    original = getattr(importlib.import_module(module_name), function)
    mutated = mutate(original)
    for name, module in list(sys.modules.items()):
        if name.startswith("bfpsf") and getattr(module, function, None) is original:
            setattr(module, function, mutated)


def run(name):
    """(caught, first failing test or None, seconds)."""
    *_, tests = MUTATIONS[name]
    env = dict(os.environ, BFPSF_MUTATION=name, OMP_NUM_THREADS="1", MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join([str(ROOT / "tools"), str(ROOT),
                                           os.environ.get("PYTHONPATH", "")]))
    start = time.perf_counter()
    process = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "mutation_check",
                              "-p", "no:cacheprovider", *tests], cwd=ROOT, env=env,
                             capture_output=True, text=True)
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", process.stdout, re.M)
    if process.returncode != 0 and not failed:  # the run itself broke: not a catch
        tail = (process.stdout + process.stderr).strip().splitlines()[-3:]
        raise RuntimeError(f"{name}: pytest exited {process.returncode} without a failing "
                           f"test: {' / '.join(tail)}")
    return bool(failed), (failed[0] if failed else None), time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="one mutation (default: all)")
    args = parser.parse_args()
    names = [args.only] if args.only else list(MUTATIONS)
    survived = []
    for name in names:
        caught, test, seconds = run(name)
        where = f"{MUTATIONS[name][0]}.{MUTATIONS[name][1]}"
        print(f"{name:22s} ({where}): "
              f"{'caught by ' + str(test) if caught else 'SURVIVED'} ({seconds:.0f} s)", flush=True)
        if not caught:
            survived.append(name)
    print(f"{len(names) - len(survived)} of {len(names)} mutations caught")
    sys.exit(1 if survived else 0)


if __name__ == "__main__":
    main()
