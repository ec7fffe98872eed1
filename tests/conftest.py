"""Shared test configuration: the ``slow`` marker and ``--runslow``.

Slow tests run the full-size physics (GalSim SiliconSensor flats and spots); each has a quick
variant that runs in CI.
"""

import os

import pytest

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
