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
`distributed.Client.map` each) as chunks complete (`distributed.as_completed`), and their
results gathered a batch at a time, so the memory in use is a few tasks per worker,
never the whole set (a task that carries file references holds no pixels until it runs). A
chunk that holds all of a key's items runs the key's follow-up too (`map_groups`), whose items
come in blocks (one detector's pairs), read while the workers measure the blocks before. Each task
costs the client, the scheduler and the worker's event loop about 10 ms of CPU, on the same
cores as the workers of a local cluster: chunks keep that a small share (issue 12). The tasks
themselves should carry file references, not pixels
(`bfpsf.calibration.flats.read_flats(..., lazy=True)`), so each worker reads only the pair it
measures. Results come back in the order of the inputs, identical to the in-process ones (the
same function runs on the same inputs).
"""

import contextlib
import logging
import os
import signal
from multiprocessing import resource_tracker

from tqdm import tqdm

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
    return tqdm(total=total, desc=description, unit="task")


def _grow_bar(bar, total):
    """Set the progress bar's total (it grows as the blocks of a map are read)."""
    if bar is not None and bar.total != total:
        bar.total = total
        bar.refresh()


def _in_process(function, blocks, bar, follow_up):
    """`_on_dask` in this process: every block read first (a bad input stops the run before
    any work), then the items, then the follow-ups."""
    chunks = _Blocks(blocks, 1)
    while chunks.read():
        pass
    _grow_bar(bar, len(chunks.items))
    results = []
    for item in chunks.items:
        results.append(function(item))
        if bar is not None:
            bar.update(1)
    grouped = {}
    if follow_up is not None:
        make_task, group_function = follow_up
        grouped = {key: group_function(make_task(key, [results[i] for i in positions]))
                   for key, positions in chunks.positions.items()}
    return results, grouped, chunks.positions


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
        # silence_logs: the nannies' and workers' messages when an interrupt or an error
        # stops the run ("worker still alive, killing", cancelled tasks) are not the user's
        with _interrupts_held():
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                   processes=True, dashboard_address=None,
                                   silence_logs=logging.CRITICAL,
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
    try:
        return Client(cluster), cluster
    except BaseException:
        cluster.close()
        raise


@contextlib.contextmanager
def _interrupts_held():
    """Hold SIGINT (Ctrl-C) back from this thread while the local workers are spawned.

    A terminal's Ctrl-C goes to every process of the foreground group, the workers included:
    each one printed a KeyboardInterrupt traceback of its own (issue 25) while this process
    stopped with its one line. The workers inherit the signal mask of the thread that spawns
    them (the cluster's event-loop thread, started here, inherits it from this one), so SIGINT
    stays blocked in them and only this process answers it: its interrupt closes the cluster.
    An interrupt that arrives while the workers start is held, not lost: it is delivered here
    as soon as the mask is restored.
    """
    if not hasattr(signal, "pthread_sigmask"):  # not on POSIX
        yield
        return
    # multiprocessing starts its resource tracker on first use and unblocks SIGINT in the
    # calling thread when it has: started first, it leaves the mask alone
    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


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


class _Blocks:
    """The items of a map, read a block at a time, and cut into chunks as they are submitted.

    ``blocks``: an iterable of (items, keys) (keys None for a plain map); a key's items are all
    in one block. `read` takes the next block (the caller decides when: on Dask, while the
    workers measure the blocks before). A chunk is 1 / (`CHUNKS_PER_WORKER` x workers) of the
    items read and not yet submitted, never across two keys, and while blocks remain unread
    (what remains is not known yet) at least that share of all the items read; so the last
    chunks of the last block hold one item each and the workers finish together.
    """

    def __init__(self, blocks, workers):
        self.blocks = iter(blocks)
        self.workers = max(1, int(workers))
        self.items, self.keys = [], []
        self.positions = {}  # key -> positions of its items (the whole key: one block)
        self.runs = []  # positions still to submit, one list per key, the next one last
        self.remaining = 0
        self.exhausted = False

    def read(self):
        """Take the next block; False when there is none."""
        if self.exhausted:
            return False
        try:
            items, keys = next(self.blocks)
        except StopIteration:
            self.exhausted = True
            return False
        items = list(items)
        keys = [None] * len(items) if keys is None else list(keys)
        if len(keys) != len(items):
            msg = f"give one key per item: {len(keys)} keys for {len(items)} items"
            raise BFPSFValueError(msg, (len(keys), len(items)))
        start = len(self.items)
        self.items += items
        self.keys += keys
        runs = {}
        for offset, key in enumerate(keys):
            runs.setdefault(key, []).append(start + offset)
        if keys and keys[0] is not None:
            repeated = [key for key in runs if key in self.positions]
            if repeated:
                msg = f"key {repeated[0]!r} is in two blocks; give each key's items in one block"
                raise BFPSFValueError(msg, repeated[0])
            self.positions.update(runs)
        self.runs = [list(run) for run in runs.values()][::-1] + self.runs
        self.remaining += len(items)
        return True

    def __bool__(self):
        """True while items read are still to submit."""
        return self.remaining > 0

    def next(self):
        """The next chunk: positions of one key, in input order (call when true)."""
        run = self.runs[-1]
        share = CHUNKS_PER_WORKER * self.workers
        size = -(-self.remaining // share)
        if not self.exhausted:  # more may come: not below the share of all the items read
            size = max(size, -(-len(self.items) // share))
        chunk, self.runs[-1] = run[:size], run[size:]
        if not self.runs[-1]:
            self.runs.pop()
        self.remaining -= len(chunk)
        return chunk

    def whole_key(self, chunk):
        key = self.keys[chunk[0]]
        return key is not None and len(chunk) == len(self.positions[key])


def _on_dask(client, function, blocks, max_in_flight, bar, follow_up=None):
    """`ParallelSession.map_groups` (or ``map``, ``follow_up`` None) on Dask.

    The items go in chunks (`_Blocks`), each one task. ``follow_up``: (make_task,
    group_function). A chunk that holds all of a key's items runs its follow-up
    ``group_function(make_task(key, results))`` in the same task, on the worker; otherwise the
    follow-up is submitted when the key's last chunk is done. Either way it runs while the
    other items are still being measured (no barrier between the two stages). The blocks are
    read one per batch of results, while the workers measure (two before the first).
    """
    from distributed import as_completed

    n_workers = max(1, len(client.scheduler_info()["workers"]))
    limit = max(1, max_in_flight or 8 * n_workers)
    chunks = _Blocks(blocks, n_workers)
    results, group_results = {}, {}
    positions_of, group_of, fused, waiting = {}, {}, set(), {}
    stream = as_completed()
    if follow_up is not None:
        make_task, group_function = follow_up

    def submit(count):
        # one client.map per batch of chunks (and kind): a message per batch, not per task
        while not chunks and not positions_of and chunks.read():
            pass  # nothing in flight and nothing read to submit: read on
        _grow_bar(bar, len(chunks.items))
        parts, wholes = [], []  # a plain map's items have no key: never whole
        for chunk in (chunks.next() for _ in range(count) if chunks):
            (wholes if chunks.whole_key(chunk) else parts).append(chunk)
        futures = []
        if parts:
            futures += client.map(_apply, [function] * len(parts),
                                  [[chunks.items[i] for i in chunk] for chunk in parts],
                                  pure=False)
        if wholes:
            # a key's items and its follow-up in one task (one round trip, not two)
            futures += client.map(_apply_with_follow_up, [function] * len(wholes),
                                  [[chunks.items[i] for i in chunk] for chunk in wholes],
                                  [chunks.keys[chunk[0]] for chunk in wholes],
                                  make_task=make_task, group_function=group_function,
                                  pure=False)
            fused.update(future.key for future in futures[len(parts):])
        for chunk, future in zip(parts + wholes, futures):
            positions_of[future.key] = chunk
        stream.update(futures)

    # two blocks before the first submission: with one block (one detector), it is then
    # known to be the last, and its keys are cut from the start
    chunks.read()
    chunks.read()
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
            key = chunks.keys[chunk[0]]
            if future.key in fused:
                fused.discard(future.key)
                result, group_results[key] = result
            results.update(zip(chunk, result))
            free += 1
            if bar is not None:
                bar.update(len(chunk))
            if follow_up is not None and key not in group_results:
                waiting[key] = waiting.get(key, len(chunks.positions[key])) - len(chunk)
                if not waiting[key]:
                    task = make_task(key, [results[i] for i in chunks.positions[key]])
                    follow = client.submit(group_function, task, pure=False)
                    group_of[follow.key] = key
                    stream.add(follow)
        # the next block, read while the workers measure; then the next chunks, cut now from
        # what remains (at most ``limit`` in flight)
        chunks.read()
        submit(free)
    return [results[i] for i in range(len(chunks.items))], group_results, chunks.positions


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
        items = list(items)
        return self._run(function, [(items, None)], None, progress, description,
                         self.on_dask and len(items) > 1)[0]

    def map_groups(self, function, blocks, make_task, group_function, *, progress=False,
                   description="tasks"):
        """For each block (items, keys) of ``blocks``, ``results = [function(item) for item in
        items]``, then for each key (one per item) ``group_function(make_task(key, [its
        items' results, in order]))``.

        ``blocks`` may be a generator: on Dask it is read one block at a time while the workers
        measure the blocks before (e.g. a detector's file headers while the pairs of the
        detectors before are measured). A key's items must all be in one block.

        On Dask a key's follow-up starts as soon as its last item is done, while the other
        items run (e.g. an amplifier's fit while the next amplifiers' pairs are measured): in
        the same task as the items when one chunk holds them all, so ``make_task`` and
        ``group_function`` must pickle (cloudpickle: closures and lambdas do). Returns
        ``(results, {key: follow-up result})``, results in the order of the items, keys in
        order of first appearance.
        """
        results, grouped, positions = self._run(function, blocks, (make_task, group_function),
                                                progress, description, self.on_dask)
        return results, {key: grouped[key] for key in positions}

    def _run(self, function, blocks, follow_up, progress, description, on_dask):
        bar = _progress_bar(None, description, progress)  # its total grows as blocks are read
        try:
            if on_dask:
                if self._client is None:  # started at the first map that needs it
                    self._client, self._cluster = _client(self.workers, self.scheduler)
                return _on_dask(self._client, function, blocks, self.max_in_flight, bar,
                                follow_up)
            return _in_process(function, blocks, bar, follow_up)
        finally:
            if bar is not None:
                bar.close()


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
