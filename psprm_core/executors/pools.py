"""The worker pools of the execution backends (:mod:`psprm_core.executors` drives them): local worker processes with
one pipe each, and one Ray actor per worker on a Ray cluster (Ray is imported when such a pool starts). Both start,
send a task to, wait for events from, replace and close their workers.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import time
import traceback
from multiprocessing.connection import wait as wait_ready
from typing import Callable, Iterable, Optional

from .tasks import (DEFAULT_LOCAL_WORKERS, LOCAL_RAY_OBJECT_STORE_BYTES, BackendSettings, Task, WorkerCache,
                    _run_one)

log = logging.getLogger(__name__)


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
