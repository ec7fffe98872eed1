"""The map over pairs, amplifiers and detectors: in process, or on Dask (dask.distributed).

The covariance measurement of a flat pair is independent of every other pair, amplifier and
detector, so a focal plane is one flat list of tasks. `parallel_map` runs them

* in this process when ``workers == 1`` and no scheduler is given, or when dask.distributed
  is not installed (``pip install bfpsf[dask]``; a warning is logged);
* on a `distributed.LocalCluster` of ``workers`` single-threaded worker processes; or
* on an existing cluster, ``scheduler='tcp://host:8786'``.

Tasks stream: the items go in chunks, one task each, cut by guided self-scheduling (a chunk
is a quarter of what remains on two workers, never across two keys of `map_groups`, so the
last chunks hold one item and the workers finish together); at most ``max_in_flight`` chunks
(default eight per worker) are in flight at a time; they are submitted in batches (one
`distributed.Client.map` each) as half the window completes (`distributed.as_completed`), and
their results gathered a batch at a time, so the memory in use is a few tasks per worker,
never the whole set (a task that carries file references holds no pixels until it runs). A
chunk that holds all of a key's items runs the key's follow-up too (`map_groups`). Each task
costs the client, the scheduler and the worker's event loop about 10 ms of CPU, on the same
cores as the workers of a local cluster: chunks keep that a small share (issue 12). The tasks
themselves should carry file references, not pixels
(`bfpsf.calibration.flats.read_flats(..., lazy=True)`), so each worker reads only the pair it
measures. Results come back in the order of the inputs, identical to the in-process ones (the
same function runs on the same inputs).
"""

import logging
import os

from .errors import BFPSFValueError

__all__ = ["parallel_map", "parallel_session", "ParallelSession", "default_workers",
           "dask_available"]

log = logging.getLogger(__name__)


def default_workers():
    """The CPUs this process may use (the default ``--workers``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def dask_available():
    """True if dask.distributed can be imported."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


def _progress_bar(total, description, enabled):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=description, unit="task")


def _in_process(function, items, bar):
    results = []
    for item in items:
        results.append(function(item))
        if bar is not None:
            bar.update(1)
    return results


#: Environment variables of Dask's worker defaults left out of the local workers. Dask sets
#: MALLOC_TRIM_THRESHOLD_ (65536) to return freed memory to the system; setting any glibc malloc
#: threshold also turns off glibc's dynamic mmap threshold, so every temporary above 128 kB of
#: the pair mask and covariances is mapped afresh and page-faulted on each use: a worker
#: measured a pair with 12 times the page faults and twice the CPU time of this process
#: (issue 12). Without it the workers allocate as this process does (memory stays bounded: a
#: few pairs per worker).
WORKER_ENVIRON_DROPPED = ("MALLOC_TRIM_THRESHOLD_",)


#: Dask's statistical profiler samples each worker's task thread every 10 ms (it takes the GIL
#: to read the stack): a worker measured the same 1024^2 pairs with 1.5 times the CPU time of
#: this process with it on (issue 12). Off for the local workers; a cluster given by address
#: keeps its own settings.
WORKER_PROFILER = False


def _client(workers, scheduler):
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        return Client(scheduler), None
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    for name in WORKER_ENVIRON_DROPPED:
        environ.pop(name, None)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                          "distributed.worker.profile.enabled": WORKER_PROFILER}):
        # no dashboard; the scheduler's HTTP routes on a free local port (the default 8787
        # may be taken by another cluster, and Dask then warns)
        cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                               dashboard_address=None,
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
    return Client(cluster), cluster


def _group_positions(keys):
    """Key -> the positions of its items, keys in order of first appearance."""
    positions = {}
    for index, key in enumerate(keys):
        positions.setdefault(key, []).append(index)
    return positions


#: Chunks cut per worker from the items still to submit (guided self-scheduling: a chunk is
#: 1 / (CHUNKS_PER_WORKER x workers) of what remains, never across two keys). Each task costs
#: the client, the scheduler and the worker's event loop about 10 ms of CPU on the cores of a
#: local cluster (issue 12: 80 one-pair tasks of a 4 x 4 x 4 focal plane of 1024^2 pairs took
#: 1.1 s of it, against 3.3 s of measuring), so the first chunks hold several items; the last
#: ones hold one, so the workers finish together.
CHUNKS_PER_WORKER = 2


def _apply(function, items):
    """One task: ``[function(item) for item in items]`` (a chunk)."""
    return [function(item) for item in items]


def _apply_with_follow_up(function, items, key, make_task, group_function):
    """One task for all of a key's items and its follow-up: (results, follow-up result)."""
    results = _apply(function, items)
    return results, group_function(make_task(key, results))


class _Chunks:
    """The item positions, cut into chunks as they are submitted (`CHUNKS_PER_WORKER`)."""

    def __init__(self, count, keys, workers):
        runs = (_group_positions(keys).values() if keys is not None
                else [list(range(count))] if count else [])
        self.runs = [list(run) for run in runs][::-1]  # popped from the end
        self.remaining = count
        self.workers = max(1, int(workers))

    def __bool__(self):
        return self.remaining > 0

    def next(self):
        """The next chunk: positions of one key, in input order."""
        size = -(-self.remaining // (CHUNKS_PER_WORKER * self.workers))
        run = self.runs[-1]
        chunk, self.runs[-1] = run[:size], run[size:]
        if not self.runs[-1]:
            self.runs.pop()
        self.remaining -= len(chunk)
        return chunk


def _on_dask(client, function, items, max_in_flight, bar, groups=None):
    """`ParallelSession.map` (``groups`` None) or `ParallelSession.map_groups` on Dask.

    The items go in chunks (`_Chunks`), each one task.
    ``groups``: (keys, make_task, group_function). A chunk that holds all of a key's items
    runs its follow-up ``group_function(make_task(key, results))`` in the same task, on the
    worker; otherwise the follow-up is submitted when the key's last chunk is done. Either way
    it runs while the other items are still being measured (no barrier between the two
    stages).
    """
    from distributed import as_completed

    n_workers = max(1, len(client.scheduler_info()["workers"]))
    limit = max(1, max_in_flight or 8 * n_workers)
    chunks = _Chunks(len(items), None if groups is None else groups[0], n_workers)
    results = [None] * len(items)
    positions_of, group_of = {}, {}
    if groups is not None:
        keys, make_task, group_function = groups
        positions = _group_positions(keys)
        waiting = {key: len(indices) for key, indices in positions.items()}
    group_results, fused = {}, set()
    stream = as_completed()

    def whole_key(chunk):
        return groups is not None and len(chunk) == len(positions[keys[chunk[0]]])

    def submit(count):
        # one client.map per batch of chunks (and kind): a message per batch, not per task
        batch = [chunks.next() for _ in range(count) if chunks]
        parts = [chunk for chunk in batch if not whole_key(chunk)]
        wholes = [chunk for chunk in batch if whole_key(chunk)]
        futures = []
        if parts:
            futures += client.map(_apply, [function] * len(parts),
                                  [[items[i] for i in chunk] for chunk in parts], pure=False)
        if wholes:
            # a key's items and its follow-up in one task (one round trip, not two)
            futures += client.map(_apply_with_follow_up, [function] * len(wholes),
                                  [[items[i] for i in chunk] for chunk in wholes],
                                  [keys[chunk[0]] for chunk in wholes],
                                  make_task=make_task, group_function=group_function,
                                  pure=False)
            fused.update(future.key for future in futures[len(parts):])
        for chunk, future in zip(parts + wholes, futures):
            positions_of[future.key] = chunk
        stream.update(futures)

    submit(limit)
    for batch in stream.batches():
        # one gather per batch (a result() per future is a round trip through the client)
        free = 0
        for future, result in zip(batch, client.gather(batch)):
            future.release()
            if future.key in group_of:
                group_results[group_of.pop(future.key)] = result
                continue
            chunk = positions_of.pop(future.key)
            if future.key in fused:
                fused.discard(future.key)
                result, group_results[keys[chunk[0]]] = result
            for index, value in zip(chunk, result):
                results[index] = value
            free += 1
            if bar is not None:
                bar.update(len(chunk))
            if groups is not None:
                key = keys[chunk[0]]
                waiting[key] -= len(chunk)
                if not waiting[key] and key not in group_results:
                    task = make_task(key, [results[i] for i in positions[key]])
                    follow_up = client.submit(group_function, task, pure=False)
                    group_of[follow_up.key] = key
                    stream.add(follow_up)
        # the next chunks, cut now from what remains: at most ``limit`` in flight
        submit(free)
    return results, group_results


class ParallelSession:
    """Runs maps in this process or on one Dask client, kept for the whole session.

    Use as a context manager (`parallel_session`); ``map`` as `parallel_map`.
    """

    def __init__(self, workers=1, scheduler=None, max_in_flight=None):
        self.workers = int(workers)
        self.scheduler = scheduler
        self.max_in_flight = max_in_flight
        self._client = self._cluster = None
        self.on_dask = scheduler is not None or self.workers > 1
        if self.on_dask and not dask_available():
            log.warning("dask.distributed is not installed (pip install bfpsf[dask]): running "
                        "in this process")
            self.on_dask = False

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.close()

    def close(self):
        """Close the client and the local cluster (if this session started them)."""
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._client = self._cluster = None

    def map(self, function, items, *, progress=False, description="tasks"):
        """``[function(item) for item in items]``; see `parallel_map`."""
        return self._run(function, list(items), None, progress, description)[0]

    def map_groups(self, function, items, keys, make_task, group_function, *, progress=False,
                   description="tasks"):
        """``results = [function(item) for item in items]``, then for each key of ``keys``
        (one per item) ``group_function(make_task(key, [its items' results, in order]))``.

        On Dask a key's follow-up starts as soon as its last item is done, while the other
        items run (e.g. an amplifier's fit while the next amplifiers' pairs are measured): in
        the same task as the items when one chunk holds them all, so ``make_task`` and
        ``group_function`` must pickle (cloudpickle: closures and lambdas do). Returns
        ``(results, {key: follow-up result})``, keys in order of first appearance.
        """
        items, keys = list(items), list(keys)
        if len(keys) != len(items):
            msg = f"give one key per item: {len(keys)} keys for {len(items)} items"
            raise BFPSFValueError(msg, (len(keys), len(items)))
        results, grouped = self._run(function, items, (keys, make_task, group_function),
                                     progress, description)
        return results, {key: grouped[key] for key in _group_positions(keys)}

    def _run(self, function, items, groups, progress, description):
        bar = _progress_bar(len(items), description, progress)
        try:
            if self.on_dask and len(items) > 1:
                if self._client is None:  # started at the first map that needs it
                    self._client, self._cluster = _client(self.workers, self.scheduler)
                return _on_dask(self._client, function, items, self.max_in_flight, bar, groups)
            results = _in_process(function, items, bar)
        finally:
            if bar is not None:
                bar.close()
        if groups is None:
            return results, {}
        keys, make_task, group_function = groups
        return results, {key: group_function(make_task(key, [results[i] for i in indices]))
                         for key, indices in _group_positions(keys).items()}


def parallel_session(workers=1, scheduler=None, max_in_flight=None):
    """A `ParallelSession`: several maps on one cluster (``with parallel_session(...) as s``).

    Parameters as `parallel_map`.
    """
    return ParallelSession(workers, scheduler, max_in_flight)


def parallel_map(function, items, *, workers=1, scheduler=None, max_in_flight=None,
                 progress=False, description="tasks"):
    """``[function(item) for item in items]``, in process or on Dask.

    Parameters
    ----------
    function : callable
        A module-level function (workers import it); it must not rely on global state.
    items : sequence
        Its inputs (pickled to the workers: keep them small, e.g. file references).
    workers : int, optional
        Worker processes of a local cluster; 1 (default) runs in this process.
        `default_workers` gives the CPU count.
    scheduler : str, optional
        Address of an existing Dask scheduler (then ``workers`` is ignored).
    max_in_flight : int, optional
        Tasks (chunks of items) in flight at once. Default eight per worker.
    progress : bool, optional
        Show a tqdm progress bar. Default False.
    description : str, optional
        Label of the progress bar.

    Returns
    -------
    list
        The results, in the order of ``items``. An exception raised by a task is re-raised.
    """
    with parallel_session(workers, scheduler, max_in_flight) as session:
        return session.map(function, items, progress=progress, description=description)
