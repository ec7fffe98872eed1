"""Shared test configuration: the ``slow`` marker and ``--runslow``, and the hypothesis profiles.

Slow tests run the full-size physics (GalSim SiliconSensor flats and spots); each has a quick
variant that runs in CI.

Hypothesis: with the ``CI`` environment variable set, the derandomized ``ci`` profile draws the
same examples on every run (a CI failure is reproducible, never random); locally the ``dev``
profile searches new random examples each run. ``HYPOTHESIS_PROFILE`` chooses explicitly.
"""

import os

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev")
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE",
                                     "ci" if os.environ.get("CI") else "dev"))

# SiliconSensor uses OpenMP; on a 2-core machine keep it from oversubscribing.
os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("MPLBACKEND", "Agg")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run tests marked slow (full-size physics)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow physics test: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)
