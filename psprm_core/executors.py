"""Execution backends of psprm's embarrassingly parallel jobs: the benchmark's (planner, problem) tasks and the oracle
labelling's chunks (``psprm bench`` / ``psprm dataset`` with ``--backend local|ray``).

One seam for both jobs. A job is a list of :class:`Task` (a module-level function and its picklable arguments);
:meth:`Executor.run` runs them on a pool of long-lived workers and yields one :class:`Outcome` per task, in the
order they finish::

    with Executor(BackendSettings(backend="ray", workers=8)) as ex:
        for out in ex.run(tasks, on_progress=bar.update):
            ...

Backends
--------
``local``
    Worker processes on this machine (``spawn``, or ``forkserver``), one task at a time each; ``workers=0`` runs the
    tasks in this process, in order (debugging, tests that replace a component in-process).
``ray``
    One Ray actor per worker (``num_cpus=1`` each) on a Ray cluster: the running cluster at ``address`` (``"auto"``,
    ``"<head>:6379"``, ``"ray://<head>:10001"``), or, without an address, a local cluster of ``workers`` CPUs started
    for the run and shut down after it (no dashboard, no usage statistics). A cluster's nodes need psprm installed
    (``scripts/setup_env.sh``, which also installs the detector models); the actors import it, nothing is shipped.
    A running cluster gets as many actors as it has CPUs unless ``workers`` says otherwise.

Workers keep what their tasks build
-----------------------------------
Every task function is called as ``fn(cache, *args)`` with its worker's :class:`WorkerCache`: per kind of object
(scene, planner, oracle, scorer) a small LRU of built objects keyed by what they were built from, so that a worker
builds a roadmap, a policy or a detector once and reuses it for its later tasks. A task's ``affinity`` names what
it needs (e.g. one planner instance): an idle worker is given a pending task of the affinity it ran last, else one of
an affinity no other worker is on, so the tasks of one planner instance mostly run where it was built; once every
remaining affinity has a worker, an idle worker helps where that saves most, unless building the affinity again
would cost more than it saves (estimated from the measured times of workers' first and later tasks of it).

Faults
------
A task whose worker dies (killed, out of memory, a crash in native code, a lost node) runs again on a new worker, at
most ``max_retries`` times; after that its outcome is a failure naming the deaths. A task that raises becomes a failed
outcome carrying the traceback (not retried: it would raise again). Neither stops the run. The driver keeps the
results: interrupted jobs resume from what their caller stored (dataset chunks, the bench's row journal).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import time
import traceback
from collections import OrderedDict, deque
from dataclasses import dataclass
from multiprocessing.connection import wait as wait_ready
from typing import Any, Callable, Hashable, Iterable, Iterator, Optional
from .errors import InputError

log = logging.getLogger(__name__)

BACKENDS = ("local", "ray")
#: local workers when ``workers`` is not given (the 2-core target machine); a Ray cluster gets one per CPU
DEFAULT_LOCAL_WORKERS = 2
#: object store of a local Ray cluster started for a run (task results are small: rows, score arrays)
LOCAL_RAY_OBJECT_STORE_BYTES = 256 * 2 ** 20


@dataclass(frozen=True)
class BackendSettings:
    """Where the tasks of a job run (CLI: ``--backend``, ``--workers``, ``--address``, ``--max-retries``).

    Attributes
    ----------
    backend : ``"local"`` (worker processes here) or ``"ray"`` (actors on a Ray cluster).
    workers : concurrent workers. ``None``: 2 local processes, one Ray actor per CPU of a running cluster, 2 for a
        local Ray cluster started for the run. ``0`` (local): in this process.
    address : Ray cluster to connect to (``None``: start a local one for the run).
    max_retries : times a task whose worker died is run again before it is reported as failed.
    cache_size : objects of each kind a worker keeps (:class:`WorkerCache`).
    start_method : ``"spawn"`` or ``"forkserver"`` (local workers; never ``fork``: workers hold torch threads and
        renderer contexts).
    """

    backend: str = "local"
    workers: Optional[int] = None
    address: Optional[str] = None
    max_retries: int = 2
    cache_size: int = 4
    start_method: str = "spawn"

    def validate(self) -> None:
        from .errors import PsprmError

        if self.backend not in BACKENDS:
            raise PsprmError(f"unknown backend '{self.backend}' (choose from {', '.join(BACKENDS)})")
        if self.workers is not None and self.workers < 0:
            raise PsprmError(f"workers must be at least 0, got {self.workers}")
        if self.backend == "ray" and self.workers == 0:
            raise PsprmError("the ray backend needs at least one worker (0 means 'in this process': --backend local)")
        if self.address and self.backend != "ray":
            raise PsprmError("--address names a Ray cluster: it needs --backend ray")
        if self.max_retries < 0:
            raise PsprmError(f"max_retries must be at least 0, got {self.max_retries}")
        if self.cache_size < 1:
            raise PsprmError(f"cache_size must be at least 1, got {self.cache_size}")
        if self.start_method not in ("spawn", "forkserver"):
            raise PsprmError(f"start_method must be 'spawn' or 'forkserver', got '{self.start_method}'")


@dataclass
class Task:
    """One unit of work: ``fn(cache, *args)`` on some worker.

    Attributes
    ----------
    key : identifies the task in its :class:`Outcome` (hashable, unique within a run).
    fn : a module-level function (sent by reference: workers import it).
    args : its picklable arguments after the cache.
    affinity : what the task needs built (tasks with equal affinity prefer the same worker); ``None``: nothing.
    weight : progress units the task is worth (what ``on_progress`` receives in total for it).
    """

    key: Hashable
    fn: Callable
    args: tuple = ()
    affinity: Hashable = None
    weight: int = 1


@dataclass
class Outcome:
    """What became of a task: ``ok`` with the function's ``value``, or not with an ``error`` (a traceback, or the
    worker deaths); ``attempts`` counts the runs (more than one after a worker died); ``worker`` names the last
    worker (``pid@host``, or ``inline``); ``seconds`` is the last run's time inside the worker."""

    key: Hashable
    ok: bool
    value: Any = None
    error: str = ""
    attempts: int = 1
    worker: str = ""
    seconds: float = float("nan")


class WorkerCache:
    """What one worker keeps between its tasks: per kind, the ``size`` objects used last, keyed by what they were
    built from.

    ``get(kind, key, build, close)`` returns the cached object or builds it with ``build()`` (an exception is not
    cached); an object pushed out (or left when the worker stops, :meth:`close`) is released with ``close(obj)``.
    ``report(n)`` tells the driver that the running task has done ``n`` more of its progress units.
    """

    def __init__(self, size: int = 4, report: Optional[Callable[[int], None]] = None):
        self.size = int(size)
        self._kinds: dict = {}
        self._report = report
        self.builds = 0

    def get(self, kind: str, key: Hashable, build: Callable[[], Any],
            close: Optional[Callable[[Any], None]] = None) -> Any:
        items = self._kinds.setdefault(kind, OrderedDict())
        if key in items:
            items.move_to_end(key)
            return items[key][0]
        obj = build()
        self.builds += 1
        items[key] = (obj, close)
        while len(items) > self.size:
            _, (old, fin) = items.popitem(last=False)
            _release(old, fin)
        return obj

    def __contains__(self, kind_key: tuple) -> bool:
        kind, key = kind_key
        return key in self._kinds.get(kind, {})

    def report(self, n: int) -> None:
        if self._report is not None and n:
            self._report(int(n))

    def close(self) -> None:
        for items in self._kinds.values():
            while items:
                _, (obj, fin) = items.popitem(last=False)
                _release(obj, fin)


def _release(obj: Any, close: Optional[Callable[[Any], None]]) -> None:
    if close is None:
        return
    try:
        close(obj)
    except Exception:  # noqa: BLE001 - releasing must not break the worker
        log.warning("releasing a cached %s failed", type(obj).__name__, exc_info=True)


def _run_one(cache: WorkerCache, fn: Callable, args: tuple) -> tuple:
    """("done", value, seconds) or ("error", traceback, seconds)."""
    t0 = time.perf_counter()
    try:
        value = fn(cache, *args)
    except BaseException:  # noqa: BLE001 - reported to the driver
        return "error", traceback.format_exc(), time.perf_counter() - t0
    return "done", value, time.perf_counter() - t0


# ---- local worker processes --------------------------------------------------------------------------------------
def _local_worker_main(conn, cache_size: int, init: Optional[Callable[[], None]]) -> None:
    """A local worker: run ``(fn, args)`` messages from the driver until ``None`` (or the driver is gone)."""
    cache = WorkerCache(cache_size, report=lambda n: conn.send(("progress", n, 0.0)))
    try:
        if init is not None:
            init()
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg is None:
                break
            kind, value, secs = _run_one(cache, *msg)
            try:
                conn.send((kind, value, secs))
            except Exception:  # noqa: BLE001 - e.g. a result that cannot be pickled
                conn.send(("error", traceback.format_exc(), secs))
    finally:
        cache.close()


class _LocalPool:
    """Worker processes with one pipe each, so that the driver knows which task a dead worker was running."""

    def __init__(self, n: int, settings: BackendSettings, init: Optional[Callable[[], None]]):
        self.ctx = mp.get_context(settings.start_method)
        self.cache_size, self.init = settings.cache_size, init
        self.procs: dict = {}
        for wid in range(n):
            self._spawn(wid)

    def _spawn(self, wid: int) -> None:
        parent, child = self.ctx.Pipe(duplex=True)
        # not daemonic: a worker's scorer may start processes of its own (renderers)
        proc = self.ctx.Process(target=_local_worker_main, args=(child, self.cache_size, self.init),
                                name=f"psprm-worker-{wid}")
        proc.start()
        child.close()
        self.procs[wid] = (proc, parent)

    @property
    def ids(self) -> list:
        return list(self.procs)

    def describe(self, wid: int) -> str:
        return f"{self.procs[wid][0].pid}@local"

    def pid(self, wid: int) -> int:
        return int(self.procs[wid][0].pid)

    def send(self, wid: int, task: Task) -> bool:
        try:
            self.procs[wid][1].send((task.fn, task.args))
            return True
        except (BrokenPipeError, EOFError, OSError):
            return False

    def wait(self, busy: Iterable[int], timeout: float) -> list:
        """Events ``(wid, kind, payload, seconds)``: kind "progress", "done", "error" or "died"."""
        busy = list(busy)
        if not busy:
            return []
        conns = {self.procs[w][1]: w for w in busy}
        sentinels = {self.procs[w][0].sentinel: w for w in busy}
        ready = wait_ready(list(conns) + list(sentinels), timeout)
        events, dead = [], set()
        for r in ready:
            if r in conns:
                w = conns[r]
                try:
                    while r.poll():
                        kind, payload, secs = r.recv()
                        events.append((w, kind, payload, secs))
                        if kind != "progress":
                            break
                except (EOFError, OSError):
                    dead.add(w)
            else:
                dead.add(sentinels[r])
        finished = {w for w, kind, _, _ in events if kind != "progress"}
        for w in sorted(dead - finished):
            events.append((w, "died", f"exit code {self.procs[w][0].exitcode}", float("nan")))
        return events

    def replace(self, wid: int) -> None:
        proc, conn = self.procs.pop(wid)
        if proc.is_alive():
            proc.kill()
        proc.join(timeout=5)
        conn.close()
        self._spawn(wid)

    def close(self, graceful: bool = True) -> None:
        """Stop the workers: let them finish (and release their caches), or at once (``graceful=False``: the run
        was interrupted)."""
        for proc, conn in self.procs.values():
            try:
                conn.send(None)
            except (BrokenPipeError, EOFError, OSError):
                pass
        deadline = time.monotonic() + (10.0 if graceful else 0.0)
        for proc, conn in self.procs.values():
            proc.join(timeout=max(0.1, deadline - time.monotonic()))
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=5)
            conn.close()
        self.procs.clear()


# ---- Ray actors ----------------------------------------------------------------------------------------------------
class _RayWorkerBody:
    """The Ray actor of one worker (wrapped with ``ray.remote`` when a pool starts, so that importing this module does
    not import Ray)."""

    def __init__(self, cache_size: int, init: Optional[Callable[[], None]]):
        if init is not None:
            init()
        self.cache = WorkerCache(cache_size)

    def where(self) -> str:
        import socket

        return f"{os.getpid()}@{socket.gethostname()}"

    def pid(self) -> int:
        return os.getpid()

    def run(self, fn: Callable, args: tuple) -> tuple:
        return _run_one(self.cache, fn, args)

    def close(self) -> None:
        self.cache.close()


def ray_init_kwargs(settings: BackendSettings, workers: int) -> dict:
    """Keywords of ``ray.init`` for a run: the cluster at ``settings.address``, or a local one of ``workers`` CPUs
    (no dashboard, a small object store); worker output is not copied to the driver (results carry what matters;
    the workers' logs stay in Ray's log directory)."""
    kw = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    if settings.address:
        kw["address"] = settings.address
    else:  # "local": a new cluster, never one that `ray start` left on this machine (someone else's)
        kw.update(address="local", num_cpus=int(workers), object_store_memory=LOCAL_RAY_OBJECT_STORE_BYTES)
    return kw


class _RayPool:
    """One actor per worker; one task in flight per actor."""

    def __init__(self, n: Optional[int], settings: BackendSettings, init: Optional[Callable[[], None]]):
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        import ray

        self.ray = ray
        self.owned = False
        if not ray.is_initialized():
            if not settings.address:
                # Ray starts its workers at niceness 15 so that they cannot starve its own services; on a machine
                # that other processes keep busy that leaves them a small share of the cores (10-17x slower measured
                # on the 2-core target machine), which also changes what time-capped planners return. A local
                # cluster's workers get the driver's priority, like the local backend's processes.
                os.environ.setdefault("RAY_worker_niceness", "0")
            t0 = time.perf_counter()
            ray.init(**ray_init_kwargs(settings, n or DEFAULT_LOCAL_WORKERS))
            self.owned = True
            log.info("ray: %s in %.1f s", f"connected to {settings.address}" if settings.address else
                     "local cluster started", time.perf_counter() - t0)
        if n is None:
            n = DEFAULT_LOCAL_WORKERS if self.owned and not settings.address else \
                max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.cls = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(_RayWorkerBody)
        self.args = (settings.cache_size, init)
        self.actors: dict = {}
        self.names: dict = {}
        self.refs: dict = {}  # wid -> ObjectRef of the running task
        try:
            for wid in range(int(n)):
                self.actors[wid] = self.cls.remote(*self.args)
            for wid, a in self.actors.items():
                self.names[wid] = ray.get(a.where.remote())
        except BaseException:
            self.close()
            raise

    @property
    def ids(self) -> list:
        return list(self.actors)

    def describe(self, wid: int) -> str:
        return self.names.get(wid, "?")

    def pid(self, wid: int) -> int:
        return int(self.describe(wid).split("@")[0])

    def send(self, wid: int, task: Task) -> bool:
        self.refs[wid] = self.actors[wid].run.remote(task.fn, task.args)
        return True

    def wait(self, busy: Iterable[int], timeout: float) -> list:
        ray = self.ray
        refs = {self.refs[w]: w for w in busy if w in self.refs}
        if not refs:
            return []
        ready, _ = ray.wait(list(refs), num_returns=1, timeout=timeout)
        events = []
        for ref in ready:
            w = refs[ref]
            del self.refs[w]
            try:
                kind, payload, secs = ray.get(ref)
                events.append((w, kind, payload, secs))
            except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError,
                    ray.exceptions.NodeDiedError, ray.exceptions.ObjectLostError) as exc:
                events.append((w, "died", f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}", float("nan")))
            except ray.exceptions.RayError:  # e.g. arguments or a result that cannot be (un)pickled
                events.append((w, "error", traceback.format_exc(), float("nan")))
        return events

    def replace(self, wid: int) -> None:
        old = self.actors.pop(wid)
        try:
            self.ray.kill(old, no_restart=True)
        except Exception:  # noqa: BLE001 - already gone
            pass
        self.actors[wid] = self.cls.remote(*self.args)
        try:
            self.names[wid] = self.ray.get(self.actors[wid].where.remote(), timeout=120)
        except Exception:  # noqa: BLE001 - a failing new actor shows up as a death of its first task
            self.names[wid] = "?"

    def close(self, graceful: bool = True) -> None:
        ray = self.ray
        try:
            if self.actors and graceful:
                ray.wait([a.close.remote() for a in self.actors.values()], num_returns=len(self.actors), timeout=30)
            for a in self.actors.values():
                ray.kill(a, no_restart=True)
        except Exception:  # noqa: BLE001 - the cluster may be gone
            log.debug("closing ray actors failed", exc_info=True)
        finally:
            self.actors.clear()
            if self.owned:
                ray.shutdown()
                self.owned = False


# ---- the driver ----------------------------------------------------------------------------------------------------
class _Pending:
    """Pending tasks grouped by affinity, in submission order; retried tasks go first in their group.

    The driver records how long tasks take (:meth:`record`): a worker's first task of an affinity includes the build,
    its later ones do not; that gives per affinity an estimate of the build and of one task, used to decide whether an
    idle worker should build an affinity another worker is on to help with its remaining tasks."""

    def __init__(self, tasks: Iterable[Task]):
        self.groups: OrderedDict = OrderedDict()
        for t in tasks:
            self.groups.setdefault(t.affinity, deque()).append(t)
        self.first: dict = {}  # affinity -> seconds of workers' first task of it
        self.later: dict = {}  # affinity -> seconds of the later ones

    def __len__(self) -> int:
        return sum(len(q) for q in self.groups.values())

    def push_front(self, task: Task) -> None:
        self.groups.setdefault(task.affinity, deque()).appendleft(task)

    def record(self, affinity: Hashable, seconds: float, first: bool) -> None:
        if seconds == seconds:  # not NaN
            (self.first if first else self.later).setdefault(affinity, []).append(float(seconds))

    def _worth_helping(self, aff: Hashable) -> float:
        """Remaining seconds of ``aff``'s pending tasks if another worker joins and builds it again (0: not worth
        it; unknown costs count as worth it)."""
        n = len(self.groups[aff])
        if aff is None:
            return float(n)
        later, first = self.later.get(aff), self.first.get(aff)
        if not later or not first:
            return float(n)
        task = sorted(later)[len(later) // 2]
        build = max(0.0, sorted(first)[len(first) // 2] - task)
        saved = n * task / 2.0  # the pending work split in two
        return saved if saved > build else 0.0

    def pick(self, last: Hashable, claimed: set) -> Optional[Task]:
        """The next task for a worker that last ran affinity ``last`` while others run ``claimed``: one of ``last``,
        else of the first affinity nobody is on, else of the affinity where helping saves most (``None``: wait)."""
        if last in self.groups:
            return self._pop(last)
        for aff in self.groups:
            if aff is None or aff not in claimed:
                return self._pop(aff)
        gains = {aff: self._worth_helping(aff) for aff in self.groups}
        best = max(gains, key=gains.get, default=None)
        return self._pop(best) if best is not None and gains[best] > 0 else None

    def _pop(self, aff: Hashable) -> Task:
        q = self.groups[aff]
        task = q.popleft()
        if not q:
            del self.groups[aff]
        return task


class Executor:
    """A pool of workers of one backend; :meth:`run` runs tasks on it. Use as a context manager (the pool, and a
    local Ray cluster it started, are shut down on exit).

    Parameters
    ----------
    settings : BackendSettings
    init : picklable callable run once in every worker before its first task (e.g. torch thread count).
    """

    def __init__(self, settings: BackendSettings = BackendSettings(), init: Optional[Callable[[], None]] = None):
        settings.validate()
        self.settings, self.init = settings, init
        self._pool = None
        self._inline: Optional[WorkerCache] = None
        self.inline = settings.backend == "local" and settings.workers == 0

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(graceful=exc_type is None)

    def _start(self, n_tasks: Optional[int] = None) -> None:
        """Start the pool (at most ``n_tasks`` workers when that is known before the first run)."""
        if self._pool is not None or self._inline is not None:
            return
        s = self.settings
        cap = (lambda n: n) if n_tasks is None else (lambda n: max(1, min(n, n_tasks)))
        if self.inline:
            self._inline = WorkerCache(s.cache_size)
            if self.init is not None:
                self.init()
        elif s.backend == "local":
            self._pool = _LocalPool(cap(s.workers or DEFAULT_LOCAL_WORKERS), s, self.init)
        else:
            self._pool = _RayPool(None if s.workers is None else cap(s.workers), s, self.init)

    @property
    def workers(self) -> int:
        """Workers of the started pool (0: in this process)."""
        self._start()
        return 0 if self._pool is None else len(self._pool.ids)

    def worker_pids(self) -> dict:
        """{worker id: process id} of the started pool (tests that kill a worker)."""
        self._start()
        return {} if self._pool is None else {w: self._pool.pid(w) for w in self._pool.ids}

    def close(self, graceful: bool = True) -> None:
        """Stop the pool (a local Ray cluster it started too); ``graceful=False`` does not wait for running tasks."""
        if self._pool is not None:
            self._pool.close(graceful)
            self._pool = None
        if self._inline is not None:
            self._inline.close()
            self._inline = None

    def run(self, tasks: Iterable[Task], on_progress: Optional[Callable[[int], None]] = None,
            on_start: Optional[Callable[[Hashable, str], None]] = None,
            idle_timeout: Optional[float] = None) -> Iterator[Outcome]:
        """Run ``tasks``; yield an :class:`Outcome` per task as it finishes.

        ``on_progress(n)``: progress units done (a task's ``report`` calls while it runs, the rest of its ``weight``
        when it ends). ``on_start(key, worker)``: a task was sent to a worker. ``idle_timeout``: raise
        ``TimeoutError`` when no worker reported anything for that many seconds.
        """
        tasks = list(tasks)
        keys = [t.key for t in tasks]
        if len(set(keys)) != len(keys):
            raise InputError("task keys must be unique within a run")
        if not tasks:
            return
        self._start(len(tasks))
        if self._inline is not None:
            yield from self._run_inline(tasks, on_progress, on_start)
            return
        yield from self._run_pool(tasks, on_progress, on_start, idle_timeout)

    def _run_inline(self, tasks: list, on_progress, on_start) -> Iterator[Outcome]:
        cache = self._inline
        for task in tasks:
            done = [0]

            def report(n, done=done):
                done[0] += n
                if on_progress is not None:
                    on_progress(n)
            cache._report = report
            if on_start is not None:
                on_start(task.key, "inline")
            kind, value, secs = _run_one(cache, task.fn, task.args)
            cache._report = None
            if on_progress is not None and task.weight - done[0] > 0:
                on_progress(task.weight - done[0])
            yield Outcome(task.key, kind == "done", value if kind == "done" else None,
                          value if kind == "error" else "", 1, "inline", secs)

    def _run_pool(self, tasks: list, on_progress, on_start, idle_timeout) -> Iterator[Outcome]:
        pool, s = self._pool, self.settings
        pending = _Pending(tasks)
        attempts: dict = {}
        running: dict = {}  # wid -> [task, progress reported]
        last: dict = {}  # wid -> affinity it ran last
        seen: dict = {}  # wid -> affinities it ran (their builds are in its cache)
        quiet_since = time.monotonic()
        while len(pending) or running:
            for wid in pool.ids:
                if wid in running or not len(pending):
                    continue
                claimed = {running[w][0].affinity for w in running}
                task = pending.pick(last.get(wid), claimed)
                if task is None:  # every pending affinity is on a worker, and building it again would not pay
                    continue
                attempts[task.key] = attempts.get(task.key, 0) + 1
                last[wid] = task.affinity
                running[wid] = [task, 0]
                if not pool.send(wid, task):  # the worker died between tasks: this is not the task's fault
                    attempts[task.key] -= 1
                    running.pop(wid)
                    pending.push_front(task)
                    pool.replace(wid)
                    continue
                if on_start is not None:
                    on_start(task.key, pool.describe(wid))
            events = pool.wait(list(running), timeout=1.0)
            if not events:
                if idle_timeout is not None and time.monotonic() - quiet_since > idle_timeout:
                    raise TimeoutError(f"no worker reported anything for {idle_timeout:.0f} s "
                                       f"({len(running)} tasks running, {len(pending)} pending)")
                continue
            quiet_since = time.monotonic()
            for wid, kind, payload, secs in events:
                if wid not in running:
                    continue
                task, reported = running[wid]
                if kind == "progress":
                    running[wid][1] += payload
                    if on_progress is not None:
                        on_progress(payload)
                    continue
                del running[wid]
                where = pool.describe(wid)
                if kind == "died":
                    pool.replace(wid)
                    last.pop(wid, None)
                    seen.pop(wid, None)
                    if on_progress is not None and reported:
                        on_progress(-reported)  # its progress is done again by the next attempt
                    n = attempts[task.key]
                    if n <= s.max_retries:
                        log.warning("worker %s died running task %s (%s); running it again (attempt %d of %d)",
                                    where, task.key, payload, n + 1, s.max_retries + 1)
                        pending.push_front(task)
                        continue
                    log.error("task %s failed: its worker died %d time(s) (%s)", task.key, n, payload)
                    if on_progress is not None:
                        on_progress(task.weight)
                    yield Outcome(task.key, False, None, f"worker died {n} time(s), last on {where}: {payload}", n,
                                  where, secs)
                    continue
                if on_progress is not None and task.weight - reported > 0:
                    on_progress(task.weight - reported)
                pending.record(task.affinity, secs, task.affinity not in seen.setdefault(wid, set()))
                seen[wid].add(task.affinity)
                if kind == "done":
                    yield Outcome(task.key, True, payload, "", attempts[task.key], where, secs)
                else:
                    yield Outcome(task.key, False, None, str(payload), attempts[task.key], where, secs)


def run_tasks(tasks: Iterable[Task], settings: BackendSettings = BackendSettings(),
              init: Optional[Callable[[], None]] = None, **kw) -> Iterator[Outcome]:
    """:meth:`Executor.run` on a pool that lives for this one run."""
    with Executor(settings, init) as ex:
        yield from ex.run(tasks, **kw)


def one_torch_thread() -> None:
    """Worker initialiser: one torch thread per worker (the workers share the machine's cores)."""
    import torch

    torch.set_num_threads(1)


def describe(settings: BackendSettings) -> str:
    """``local (2 processes)``, ``ray (local cluster, 2 workers)``, ``ray (auto, 16 workers)``."""
    w = settings.workers
    if settings.backend == "local":
        return "local (this process)" if w == 0 else f"local ({w or DEFAULT_LOCAL_WORKERS} processes)"
    where = settings.address or "local cluster"
    return f"ray ({where}, {w if w else ('cluster CPUs' if settings.address else DEFAULT_LOCAL_WORKERS)} workers)"


__all__ = ["BACKENDS", "BackendSettings", "Task", "Outcome", "WorkerCache", "Executor", "run_tasks",
           "one_torch_thread", "describe", "ray_init_kwargs"]
