"""The parts of a job that the driver and its workers share (:mod:`psprm_core.executors` re-exports them): where the
tasks run (:class:`BackendSettings`), a task and what became of it (:class:`Task`, :class:`Outcome`), the cache a
worker keeps between its tasks (:class:`WorkerCache`) and the call of one task in a worker.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Hashable, Optional

from ..errors import PsprmError

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
