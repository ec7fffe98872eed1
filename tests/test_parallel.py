"""The Dask map: the same numbers as in process; detectors x amplifiers through the CLI; the
JSON ``amplifiers`` list; schema-1 calibration files still read."""

import contextlib
import json

import numpy as np
import pytest
from astropy.io import fits

from bfpsf.calibration import calibrate_detectors
from bfpsf.calibration.detector import read_calibration
from bfpsf.calibration.product import Calibration
from bfpsf.cli import main
from bfpsf.parallel import _Blocks, dask_available, parallel_map, parallel_session
from bfpsf.validation.simulate_camera import write_amplifier_file

AMPS = ("C00", "C01")


def _square(value):
    return value * value


@pytest.fixture(scope="module")
def dask_pair():
    """One local cluster of 2 workers for the module's Dask tests (each cluster costs about
    3 s to start and stop); each test sets its own window (`_session`)."""
    if not dask_available():
        pytest.skip("dask.distributed is not installed")
    with parallel_session(workers=2) as session:
        yield session


@contextlib.contextmanager
def _session(request, workers, max_in_flight):
    """An in-process session (``workers=1``) or the module's Dask one with this window."""
    if workers == 1:
        with parallel_session(workers=1, max_in_flight=max_in_flight) as session:
            yield session
        return
    session = request.getfixturevalue("dask_pair")
    session.max_in_flight = max_in_flight
    try:
        yield session
    finally:
        session.max_in_flight = None


def _focal_plane(directory, detectors=2, levels=(2e3, 8e3, 2e4, 4e4, 6e4, 8e4), size=48,
                 seed=0):
    """Poisson flats of a sensor with a nearest-neighbour correlation (so a(1, 0) is not zero),
    two amplifiers per MEF file with overscan, ``detectors`` directories."""
    rng = np.random.default_rng(seed)
    for detector in range(detectors):
        folder = directory / f"R{detector:02d}"
        folder.mkdir()
        for number, level in enumerate(np.repeat(levels, 2)):
            images = []
            for gain in (1.4, 1.7):
                charge = rng.poisson(level, (size, size + 1)).astype(float)
                charge = charge[:, 1:] + 0.02 * (charge[:, :-1] - level)  # serial correlation
                images.append((charge + rng.normal(0, 5, charge.shape)) / gain)
            write_amplifier_file(folder / f"flat{number:02d}.fits", images, list(AMPS),
                                 bias_adu=[800.0, 1200.0], read_noise_adu=[3.0, 3.0],
                                 exptime=level / 1e3, rng=rng)
    return sorted(directory.glob("R*"))


def test_in_process_map_keeps_the_order():
    assert parallel_map(_square, [3, 1, 2]) == [9, 1, 4]


@pytest.mark.skipif(not dask_available(), reason="dask.distributed is not installed")
def test_dask_map_streams_and_keeps_the_order():
    items = list(range(12))
    assert parallel_map(_square, items, workers=2, max_in_flight=3) == [i * i for i in items]


def _joined(values):
    return "".join(str(value) for value in values)


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.skipif(
    not dask_available(), reason="dask.distributed is not installed"))])
def test_map_groups_follow_up_sees_its_items_in_order(request, workers):
    """Each key's follow-up gets its own items' results in input order (on Dask it starts while
    other items run), keys in order of first appearance, blocks read from a generator; the
    same in process and on Dask."""
    items = list(range(10))
    keys = ["b", "a", "b", "c", "a", "b", "c", "c", "a", "b"]
    with _session(request, workers, 3) as session:
        results, grouped = session.map_groups(_square, [(items, keys)],
                                              lambda key, values: [key, *values], _joined)
        with pytest.raises(ValueError, match="one key per item: 2 keys for 10 items"):
            session.map_groups(_square, [(items, keys[:2])], None, _joined)
    assert results == [i * i for i in items]
    assert list(grouped) == ["b", "a", "c"]
    assert grouped == {"b": "b042581", "a": "a11664", "c": "c93649"}


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.skipif(
    not dask_available(), reason="dask.distributed is not installed"))])
def test_map_groups_reads_blocks_from_a_generator(request, workers):
    """Blocks (a detector's pairs each) come from a generator, read as the map goes: results
    in block order, each key's follow-up from its block; a key in two blocks is refused."""
    blocks = [(list(range(start, start + 6)), [f"{name}{i % 2}" for i in range(6)])
              for start, name in ((0, "R0"), (6, "R1"), (12, "R2"))]
    with _session(request, workers, 2) as session:
        results, grouped = session.map_groups(_square, (block for block in blocks),
                                              lambda key, values: [key, *values], _joined)
        with pytest.raises(ValueError, match="key 'R00' is in two blocks"):
            session.map_groups(_square, [blocks[0], blocks[0]], lambda key, values: values,
                               _joined)
    assert results == [i * i for i in range(18)]
    assert list(grouped) == ["R00", "R01", "R10", "R11", "R20", "R21"]
    assert grouped["R11"] == "R11" + "4981121"
    assert grouped["R20"] == "R20" + "144196256"


def test_chunks_are_guided_and_never_cross_keys():
    """Guided self-scheduling: the first chunks are whole keys (several items, one task), the
    last ones single items, each chunk one key's positions in input order, every item once."""
    keys = [f"amp{number // 4}" for number in range(64)]  # 16 keys of 4, as a focal plane
    chunks = _Blocks([(range(64), keys)], workers=2)
    assert chunks.read() and not chunks.read()  # one block: now known to be the last
    cut = []
    while chunks:
        cut.append(chunks.next())
    assert sorted(index for chunk in cut for index in chunk) == list(range(64))
    for chunk in cut:
        assert len({keys[index] for index in chunk}) == 1 and chunk == sorted(chunk)
    sizes = [len(chunk) for chunk in cut]
    assert sizes[:13] == [4] * 13 and sizes[-4:] == [1] * 4
    # one key of 100 items on 4 workers: 1/8 of what remains each time, rounded up
    chunks = _Blocks([(range(100), None)], workers=4)
    assert chunks.read() and not chunks.read()
    assert [chunks.next() for _ in range(3)] == [list(range(13)), list(range(13, 24)),
                                                 list(range(24, 34))]
    # while blocks remain unread, a chunk is at least 1/4 of all the items read (two workers)
    chunks = _Blocks([(range(8), ["a"] * 8), (range(8), ["b"] * 8), (range(9), ["c"] * 9)],
                     workers=2)
    assert chunks.read() and chunks.next() == [0, 1]
    assert chunks.read() and chunks.next() == [2, 3, 4, 5]  # 16 read, 14 left
    assert chunks.read() and chunks.next() == [6, 7]  # the rest of a
    assert chunks.next() == list(range(8, 15))  # 25 read: 25/4 rounded up
    assert not chunks.read()  # all read: 1/4 of what remains
    assert [chunks.next() for _ in range(4)] == [[15], [16, 17, 18], [19, 20], [21]]


@pytest.mark.skipif(not dask_available(), reason="dask.distributed is not installed")
def test_split_key_and_whole_key_follow_ups_on_dask(request):
    """A key cut into several chunks gets its follow-up after its last chunk; a key in one
    chunk runs it in the same task: both see their items' results in order."""
    items = list(range(24))
    keys = ["long"] * 20 + ["short"] * 2 + ["long"] * 2
    with _session(request, 2, 2) as session:
        results, grouped = session.map_groups(_square, [(items, keys)],
                                              lambda key, values: [key, *values], _joined)
    assert results == [i * i for i in items]
    assert grouped == {"long": "long" + "".join(str(i * i) for i in [*range(20), 22, 23]),
                       "short": "short400441"}


def _profiler_enabled():
    import dask

    return dask.config.get("distributed.worker.profile.enabled")


@pytest.mark.skipif(not dask_available(), reason="dask.distributed is not installed")
def test_dask_window_of_one_and_local_workers_without_profiler(request):
    """A window of one task still finishes every item in order (each batch refills it); the
    local workers run without Dask's 10 ms stack sampler, which cost them 1.5x the CPU time of
    this process on the same pairs."""
    items = list(range(7))
    with _session(request, 2, 1) as session:
        assert session.map(_square, items) == [i * i for i in items]
        assert session.map(_square, items[:2]) == [0, 1]
        assert set(session._client.run(_profiler_enabled).values()) == {False}
        # SIGINT stays blocked in the workers, not in this thread (issue 25)
        assert set(session._client.run(_sigint_blocked).values()) == {True}
    assert not _sigint_blocked()


def _sigint_blocked():
    import signal

    return signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])


INTERRUPTED_MAP = """
import os, signal, sys, time
from bfpsf.parallel import parallel_session

# a terminal starts programs with SIGINT at its default; a suite started in the background
# by a non-interactive shell inherits it ignored, and Python then installs no handler
signal.signal(signal.SIGINT, signal.default_int_handler)

def slow(value):
    # one write of the whole line: the two workers' print()s once interleaved on the shared
    # pipe as "runningrunning\\n\\n", and the test, never seeing its line, waited out the map
    os.write(1, b"running\\n")
    time.sleep(60)
    return value

if __name__ == "__main__":
    try:
        with parallel_session(workers=2) as session:
            print("ready", flush=True)
            session.map(slow, [1, 2])
    except KeyboardInterrupt:
        sys.exit(130)
"""


@pytest.mark.skipif(not dask_available(), reason="dask.distributed is not installed")
@pytest.mark.parametrize("when", ["ready", "running"])
def test_ctrl_c_on_the_process_group_reaches_this_process_alone(tmp_path, when):
    """A terminal's Ctrl-C goes to the whole foreground process group: the workers stay
    silent (each printed a KeyboardInterrupt traceback before issue 25), this process stops,
    whether the workers are starting (``ready``: the cluster starts with the first map) or
    running their tasks."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "run.py").write_text(INTERRUPTED_MAP)
    environment = {**os.environ, "OMP_NUM_THREADS": "1",
                   "PYTHONPATH": str(Path(__file__).parents[1])}
    process = subprocess.Popen([sys.executable, "run.py"], cwd=tmp_path, env=environment,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    lines = []
    while not lines or lines[-1] not in (f"{when}\n", ""):
        lines.append(process.stdout.readline())
    assert lines[-1] == f"{when}\n", lines
    os.killpg(process.pid, signal.SIGINT)
    # generous: a loaded machine (the whole suite on two cores) takes its time to stop the
    # cluster's processes; a run that does not stop is killed with its group and reported
    try:
        _, err = process.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        _, err = process.communicate()
        pytest.fail(f"Ctrl-C did not stop the run in 180 s; its stderr: {err[-2000:]}")
    assert (process.returncode, err) == (130, "")


@pytest.mark.skipif(not dask_available(), reason="dask.distributed is not installed")
def test_dask_focal_plane_matches_in_process(tmp_path):
    folders = _focal_plane(tmp_path)
    detectors = {folder.name: sorted(str(path) for path in folder.glob("*.fits"))
                 for folder in folders}
    options = dict(maxlag=2, n_monte_carlo=0, solve_shifts=False, fit_b="none")
    serial = calibrate_detectors(detectors, workers=1, **options)
    on_dask = calibrate_detectors(detectors, workers=2, **options)
    for detector in detectors:
        for amp in AMPS:
            one, other = serial[detector][amp], on_dask[detector][amp]
            np.testing.assert_array_equal(one.covariances_adu, other.covariances_adu)
            assert one.gain == other.gain
            np.testing.assert_array_equal(one.a, other.a)


def test_detector_directories_write_one_product_each_with_amplifier_json(tmp_path, capsys):
    folders = _focal_plane(tmp_path, detectors=2)
    out = tmp_path / "calibs"
    code = main(["calibrate", *map(str, folders), "-o", str(out), "--maxlag", "2",
                 "--n-monte-carlo", "0", "--workers", "1", "--json", str(tmp_path / "s.json")])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "s.json").read_text())
    assert [entry["detector"] for entry in summary["detectors"]] == ["R00", "R01"]
    for entry in summary["detectors"]:
        assert [amp["name"] for amp in entry["amplifiers"]] == list(AMPS)
        for amp, gain in zip(entry["amplifiers"], (1.4, 1.7)):
            # 6 levels of 48^2: gains to 3-5 %, each amplifier its own
            assert abs(amp["gain"] - gain) < 3 * amp["gain_err"]
        for key in ("gain_err", "noise_e", "a", "a_err", "n_pairs", "shift_method", "warnings"):
            assert key in entry["amplifiers"][0]
        # few pairs: each amplifier warns, and the detector lists them by amplifier
        for amp in entry["amplifiers"]:
            assert any(text.startswith("the full PTC model is under-constrained")
                       for text in amp["warnings"])
        assert entry["warnings"] == [f"{amp['name']}: {text}" for amp in entry["amplifiers"]
                                     for text in amp["warnings"]]
        calibration = read_calibration(entry["output"])
        assert calibration["C00"].warnings == tuple(entry["amplifiers"][0]["warnings"])
        assert calibration.names == list(AMPS)
        assert calibration["C01"].gain == entry["amplifiers"][1]["gain"]


def test_unpaired_flat_in_a_later_detector_stops_the_run_and_writes_nothing(tmp_path, capsys):
    folders = _focal_plane(tmp_path, detectors=2)
    (folders[1] / "flat11.fits").unlink()  # its partner flat10.fits is left alone
    out = tmp_path / "calibs"
    code = main(["calibrate", *map(str, folders), "-o", str(out), "--maxlag", "2",
                 "--n-monte-carlo", "0", "--workers", "1"])
    error = capsys.readouterr().err.strip().splitlines()
    assert code != 0
    assert error[-1] == (f"bfpsf calibrate: error: {folders[1] / 'flat10.fits'}[C00] "
                         "(EXPTIME=80 s) has no partner: flats are paired by equal EXPTIME")
    assert not out.exists()


def test_one_amplifier_selected_reads_as_a_single_calibration(tmp_path, capsys):
    (folder,) = _focal_plane(tmp_path, detectors=1)
    files = sorted(map(str, folder.glob("*.fits")))
    code = main(["calibrate", *files, "--amp", "C01", "-o", str(tmp_path / "c.fits"),
                 "--maxlag", "2", "--n-monte-carlo", "0", "--workers", "1",
                 "--plots", str(tmp_path / "plots")])
    assert code == 0, capsys.readouterr().err
    calibration = Calibration.read(tmp_path / "c.fits")
    assert calibration.amplifier == "C01" and calibration.inputs[0].endswith("[C01]")
    assert (tmp_path / "plots" / "ptc.png").exists()


def test_two_amplifiers_plot_and_schema_one_file_reads(tmp_path, capsys):
    (folder,) = _focal_plane(tmp_path, detectors=1)
    files = sorted(map(str, folder.glob("*.fits")))
    code = main(["calibrate", *files, "-o", str(tmp_path / "c.fits"), "--maxlag", "2",
                 "--n-monte-carlo", "0", "--workers", "1", "--plots", str(tmp_path / "plots")])
    assert code == 0, capsys.readouterr().err
    assert (tmp_path / "plots" / "amplifiers.png").exists()
    assert (tmp_path / "plots" / "C01" / "ptc.png").exists()
    # a schema-1 file (before per-amplifier groups): no NAMP, AMPNAME or EXTVER
    one = read_calibration(tmp_path / "c.fits")["C00"]
    one.write(tmp_path / "single.fits")
    with fits.open(tmp_path / "single.fits", mode="update") as hdul:
        hdul[0].header["BFSCHEMA"] = 1
        del hdul[0].header["NAMP"]
        for hdu in hdul[1:]:
            del hdu.header["AMPNAME"]
            del hdu.header["EXTVER"]
    old = Calibration.read(tmp_path / "single.fits")
    assert old.schema_version == 1 and old.amplifier == ""
    assert old.gain == one.gain
    np.testing.assert_array_equal(old.a, one.a)
