"""Shared test configuration: the ``slow`` marker and ``--runslow``, and the hypothesis profiles.

Slow tests run the full-size physics (GalSim SiliconSensor flats and spots); each has a quick
variant that runs in CI.

`galsim_bf_stars`: stars drawn by GalSim and redistributed by GalSim's own CDModel, not by
bfpsf: the truth of the tests of bfpsf's model and photometry (issue 24: a test whose stars
are drawn with the operator it tests cannot find an error in it).

``e2v_flats_calibration``: the user's calibration of the E2V SiliconSensor, `bfpsf.calibrate` on
a small simulated flat set (seed 203), shared by the tests that start from flats
(test_flats_to_psf.py, test_gridded_silicon.py, ...) so that CI simulates it once, in one
of the test processes of ``pytest -n 2`` (`computed_once_per_run`).

Hypothesis: with the ``CI`` environment variable set, the derandomized ``ci`` profile draws the
same examples on every run (a CI failure is reproducible, never random); locally the ``dev``
profile searches new random examples each run. ``HYPOTHESIS_PROFILE`` chooses explicitly.
"""

import collections
import fcntl
import os
import pickle

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev")
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE",
                                     "ci" if os.environ.get("CI") else "dev"))

def galsim_bf_stars(profile, positions, fluxes, shape, shifts):
    """Pixelised stars of a GalSim profile (`bfpsf.model.galsim_profile.render_stars` without
    shifts: GalSim's drawImage), redistributed by GalSim's CDModel (src/CDModel.cpp, G15's
    first-order operator implemented independently of bfpsf's `redistribution_delta`;
    `bfpsf.interop.cdmodel.shifts_to_cdmodel` converts the shifts), e-. Agrees with
    ``bfpsf.redistribute`` to 7e-11 e- on 8e5 e- stars away from the border (GalSim drops
    terms within the shifts' radius of it)."""
    from bfpsf.model.galsim_profile import render_stars

    return galsim_redistribute(render_stars(profile, positions, fluxes, shape), shifts)


def galsim_redistribute(charge_e, shifts):
    """``charge_e`` redistributed by GalSim's CDModel (`galsim_bf_stars`), e-."""
    import galsim

    from bfpsf.interop.cdmodel import shifts_to_cdmodel

    image = galsim.ImageD(np.asarray(charge_e, dtype=float), scale=1.0)
    return shifts_to_cdmodel(shifts).applyForward(image).array


# SiliconSensor uses OpenMP; on a 2-core machine keep it from oversubscribing (one thread in
# each of the two processes of ``pytest -n 2``).
os.environ.setdefault("OMP_NUM_THREADS", "1" if os.environ.get("PYTEST_XDIST_WORKER") else "2")
os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(autouse=True)
def _interrupt_state_is_left_alone():
    """Every test leaves this process's SIGINT disposition and signal mask as it found them:
    a child process inherits both, so a test that left SIGINT ignored or blocked would make a
    later test's subprocess deaf to Ctrl-C (tests/test_parallel.py), and a bfpsf call that
    leaked either would do the same to a user's program."""
    import signal

    before = (signal.getsignal(signal.SIGINT), signal.pthread_sigmask(signal.SIG_BLOCK, []))
    yield
    after = (signal.getsignal(signal.SIGINT), signal.pthread_sigmask(signal.SIG_BLOCK, []))
    assert after == before, f"SIGINT (handler, blocked signals) {before} -> {after}"


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run tests marked slow (full-size physics)")


#: The test files whose quick tests take longest (measured: 20-70 s of one core each), in
#: the order ``pytest -n 2`` starts them. With ``--dist loadfile`` a file is one unit of work
#: and the units go out in collection order (``--no-loadscope-reorder`` in pyproject.toml:
#: xdist's own order, by number of tests, left these files, which hold few tests, for the
#: end, and started two users of `e2v_flats_calibration` together, one waiting 26 s for the
#: other's flats). test_gridded_silicon.py computes that calibration first; the other users
#: come after the heavy files that do not need it.
HEAVY_FILES = ("test_gridded_silicon.py", "test_outside_effects.py", "test_validate.py",
               "test_calibrate.py", "test_loop_to_psf.py", "test_amplifiers.py",
               "test_defaults_matrix.py", "test_flats_to_psf.py", "test_piff_plugin.py",
               "test_silicon_shapes.py", "test_photometry.py", "test_diagnose.py",
               "test_galsim_config.py", "test_silicon_psf.py", "test_hostile_input.py")


def pytest_collection_modifyitems(config, items):
    # the heavy files first, the others by number of tests (xdist's order): module fixtures
    # and the order of the tests within a file are kept (a stable sort)
    counts = collections.Counter(item.path.name for item in items)
    rank = {name: index for index, name in enumerate(HEAVY_FILES)}
    items.sort(key=lambda item: (rank.get(item.path.name, len(rank)), -counts[item.path.name],
                                 item.path.name))
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow physics test: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


#: The quick flat set of `e2v_flats_calibration`: 12 levels from 2 to 100 ke-, 3 pairs each of
#: 128^2 pixels (0.6 Mpixel of pairs), gain 1.5 e-/ADU, read noise 5 e-.
E2V_FLAT_LEVELS = np.geomspace(2e3, 1e5, 12)
E2V_FLAT_SEED = 203


def computed_once_per_run(name, compute, tmp_path_factory):
    """``compute()``, computed by one test process of the run and read by the others.

    Under ``pytest -n 2`` each process has its own session fixtures: a session fixture used
    by test files on both processes would be computed twice. The first process to get here
    computes it and pickles it into the run's shared temporary directory, under a lock; the
    other one waits and reads it. Without xdist it is simply computed.
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return compute()
    path = tmp_path_factory.getbasetemp().parent / f"{name}.pickle"
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if path.is_file():
            return pickle.loads(path.read_bytes())
        result = compute()
        partial = path.with_suffix(".partial")
        partial.write_bytes(pickle.dumps(result))
        partial.replace(path)
        return result


@pytest.fixture(scope="session")
def e2v_flats_calibration(tmp_path_factory):
    """`bfpsf.calibrate` (electrostatic shifts, 12 shift samples) of SiliconSensor
    ``lsst_e2v_50_8`` flats simulated from seed `E2V_FLAT_SEED` (about 50 s on one core),
    computed once per run (`computed_once_per_run`)."""
    from bfpsf import calibrate
    from bfpsf.validation.simulate_flats import simulate_flats

    def compute():
        flats = simulate_flats("lsst_e2v_50_8", E2V_FLAT_LEVELS, pairs=3, size=128, nsteps=10,
                               gain=1.5, read_noise_e=5.0, seed=E2V_FLAT_SEED)
        return calibrate([image for image, _, _ in flats], exptimes=[t for _, t, _ in flats],
                         maxlag=6, fit_b=False, n_monte_carlo=12)

    return computed_once_per_run("e2v_flats_calibration", compute, tmp_path_factory)
