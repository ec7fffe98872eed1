"""Break each physics operator by a sign or a factor of two and check that a quick test fails.

A test suite that passes with a broken operator cannot catch an error in it (issue 24). For
each mutation below, a copy of the package is made with one line changed, the quick tests that
exercise the operator are run against it (``-x``, first failure stops), and the first failing
test is reported. A mutation that no quick test catches is listed as SURVIVED and the script
exits 1.

Usage (from the repository root, about 10-20 minutes on 2 cores)::

    OMP_NUM_THREADS=1 python tools/mutation_check.py [--only NAME] [--list]
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# name, file, exact text, replacement, what it breaks, the quick tests that should catch it
MUTATIONS = [
    ("redistribution factor x2", "bfpsf/model/redistribution.py",
     "        kernel_factor = 0.5 * factor", "        kernel_factor = 1.0 * factor",
     "G15 eq. scrambling_model: the (Q_p + Q_q) / 2 density doubled",
     ["tests/test_redistribution.py", "tests/test_galsim_sensor.py", "tests/test_psf_model.py"]),
    ("redistribution sign", "bfpsf/model/redistribution.py",
     "    kernels = [shifts.north * kernel_factor, shifts.east * kernel_factor]",
     "    kernels = [-shifts.north * kernel_factor, -shifts.east * kernel_factor]",
     "boundaries move the wrong way (charge attracts)",
     ["tests/test_redistribution.py", "tests/test_galsim_sensor.py", "tests/test_psf_model.py"]),
    ("redistribution east only x2", "bfpsf/model/redistribution.py",
     "    kernels = [shifts.north * kernel_factor, shifts.east * kernel_factor]",
     "    kernels = [shifts.north * kernel_factor, 2 * shifts.east * kernel_factor]",
     "the serial boundaries' shifts doubled (x/y balance)",
     ["tests/test_redistribution.py", "tests/test_galsim_sensor.py", "tests/test_psf_model.py"]),
    ("exact density weights", "bfpsf/model/density.py",
     "    line = (7.0 * (sub[r - 1] + sub[r]) - (sub[r - 2] + sub[r + 1])) / 12.0",
     "    line = (7.0 * (sub[r - 1] + sub[r]) - (sub[r - 2] + sub[r + 1])) / 6.0",
     "the boundary density of an oversampled image doubled along y",
     ["tests/test_redistribution.py", "tests/test_psf_model.py"]),
    ("inverse sign", "bfpsf/model/inverse.py",
     "        x = image - forward_delta(image)", "        x = image + forward_delta(image)",
     "the first-order inverse adds the BF instead of removing it",
     ["tests/test_redistribution.py"]),
    ("inverse iteration", "bfpsf/model/inverse.py",
     "            x = x + residual", "            x = x + 2 * residual",
     "the fixed-point update over-steps",
     ["tests/test_redistribution.py"]),
    ("build-up source", "bfpsf/model/buildup.py",
     "source=collected + 0.5 * (arriving + moved)", "source=collected + 1.0 * (arriving + moved)",
     "the charge collected during a step counted whole",
     ["tests/test_redistribution.py", "tests/test_galsim_sensor.py", "tests/test_psf_model.py"]),
    ("cdmodel halving", "bfpsf/interop/cdmodel.py",
     "    return galsim.cdmodel.BaseCDModel(shifts.west / 2.0, shifts.east / 2.0,",
     "    return galsim.cdmodel.BaseCDModel(shifts.west / 1.0, shifts.east / 1.0,",
     "GalSim's a_t = a^N / 2 conversion",
     ["tests/test_galsim_sensor.py", "tests/test_redistribution.py"]),
    ("moments centroid step", "bfpsf/measure/moments.py",
     "            step_x = np.clip(2.0 * bx / (a_sum * shiftscale), -_STEP_BOUND, _STEP_BOUND)",
     "            step_x = np.clip(-2.0 * bx / (a_sum * shiftscale), -_STEP_BOUND, _STEP_BOUND)",
     "the adaptive centroid update walks away along x",
     ["tests/test_moments.py"]),
    ("moments size step", "bfpsf/measure/moments.py",
     "            step_xx = np.clip(4.0 * (cxx / a_sum - 0.5 * m_xx) / semi_b2, -_STEP_BOUND, _STEP_BOUND)",
     "            step_xx = np.clip(4.0 * (cxx / a_sum - 0.25 * m_xx) / semi_b2, -_STEP_BOUND, _STEP_BOUND)",
     "the weighted-covariance condition M / 2 broken along x",
     ["tests/test_moments.py"]),
    ("single-image variance", "bfpsf/calibration/covariance.py",
     "    cov = cov / 2.0 / clip_factor**2", "    cov = cov / 1.0 / clip_factor**2",
     "var(difference) taken as the single-image variance",
     ["tests/test_covariance.py", "tests/test_ptc.py"]),
    ("A+19 second order", "bfpsf/calibration/ptc_full.py",
     "    model = mu * delta + 2.0 / 3.0 * mu**3 * c.ravel() + 5.0 / 6.0 * mu**4 * ac",
     "    model = mu * delta + 4.0 / 3.0 * mu**3 * c.ravel() + 5.0 / 6.0 * mu**4 * ac",
     "the b term of A+19 eq. 20 doubled",
     ["tests/test_ptc.py"]),
    ("electrostatic area", "bfpsf/calibration/shifts_electrostatic.py",
     "    return alpha * (north[:-1] - north[1:] + east[:, :-1] - east[:, 1:])",
     "    return alpha * (north[:-1] - north[1:] + 2 * (east[:, :-1] - east[:, 1:]))",
     "the area of the electrostatic model counts the E/W boundaries twice",
     ["tests/test_shifts_electrostatic.py"]),
]


def apply(tree, mutation):
    name, relative, old, new = mutation[:4]
    path = tree / relative
    text = path.read_text()
    if text.count(old) != 1:
        raise SystemExit(f"{name}: the text to mutate is not found once in {relative}; "
                         "update tools/mutation_check.py")
    path.write_text(text.replace(old, new))


def run(mutation, tree):
    name, relative, _, _, _, tests = mutation
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    command = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
               "--rootdir", str(tree), *[str(tree / test) for test in tests]]
    result = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    failed = re.findall(r"^FAILED (\S+)", result.stdout, flags=re.M)
    caught = result.returncode != 0
    return caught, (failed[0].split("/")[-1] if failed else result.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="run the mutations whose name contains this text")
    parser.add_argument("--list", action="store_true", help="list the mutations and stop")
    args = parser.parse_args(argv)
    chosen = [m for m in MUTATIONS if args.only is None or args.only in m[0]]
    if args.list:
        for name, relative, _, _, what, _ in chosen:
            print(f"{name:32s} {relative}: {what}")
        return 0
    survived = 0
    print("| mutation | file | breaks | first quick test failing |")
    print("|---|---|---|---|")
    for mutation in chosen:
        with tempfile.TemporaryDirectory() as scratch:
            tree = Path(scratch) / "repo"
            shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(
                ".git", ".venv*", "__pycache__", ".pytest_cache", ".hypothesis", "*.egg-info"))
            apply(tree, mutation)
            caught, test = run(mutation, tree)
        survived += not caught
        print(f"| {mutation[0]} | {mutation[1]} | {mutation[4]} | "
              f"{test if caught else 'SURVIVED: ' + test} |", flush=True)
    return 1 if survived else 0


if __name__ == "__main__":
    sys.exit(main())
