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

This module holds the driver (:class:`Executor`, the scheduling of pending tasks); the settings, tasks, outcomes and
the workers' cache are in :mod:`~psprm_core.executors.tasks`, the local and Ray worker pools in
:mod:`~psprm_core.executors.pools`; their names are re-exported here.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict, deque
from typing import Callable, Hashable, Iterable, Iterator, Optional
from ..errors import InputError
from .pools import _LocalPool, _RayPool, _RayWorkerBody, _local_worker_main, ray_init_kwargs
from .tasks import (BACKENDS, DEFAULT_LOCAL_WORKERS, LOCAL_RAY_OBJECT_STORE_BYTES, BackendSettings, Outcome,
                    Task, WorkerCache, _release, _run_one)

log = logging.getLogger(__name__)


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
