"""The planning loop's inputs, thread-safe: each stores only the newest value and wakes the worker, so that a 120 Hz
pose stream never queues. The worker takes everything pending at the start of a cycle (:meth:`Inputs.take`)."""

from __future__ import annotations

import threading
import time
from typing import Callable, Optional

import numpy as np

from .params import REQUESTS


def _empty() -> dict:
    return {"targets": {}, "obstacles": {}, "robot": None, "robot_t": None, "goals": None, "t_first": None,
            "stamp": None, "guard": None, "target_stamps": {}}


class Inputs:
    """Pending poses, robot state, goals, service requests (with their answers), live parameter changes and a
    lifecycle step for the worker. ``clock``: the time the input stamps are on (s)."""

    def __init__(self, clock: Callable[[], float]):
        self.clock = clock
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self._done = threading.Condition(self.lock)
        self._pending = _empty()
        self._requests: list = []  # (kind, id); id -1: asked for by the loop itself (no answer awaited)
        self._responses: dict = {}
        self._next_id = 0
        self._live: dict = {}  # parameter changes for the worker to apply
        self._transition: Optional[tuple] = None  # (kind, Event, result list) run by the worker
        self.robot_rx: Optional[float] = None  # monotonic receipt time of the last robot state
        self._input_t: dict = {}  # input label -> monotonic receipt time

    # ------------------------------------------------------------------------------------------------ callers' side
    def pose(self, kind: str, name: str, p: np.ndarray, q: np.ndarray, stamp: Optional[float],
             received: Optional[float]) -> None:
        """A target's or an obstacle's pose; ``received``: perf_counter at its receipt (a plan's latency starts at
        the first input of its cycle)."""
        t = time.perf_counter() if received is None else received
        with self.lock:
            self._input_t[f"{kind} {name}"] = time.monotonic()
            pend = self._pending
            pend["targets" if kind == "target" else "obstacles"][name] = (p, q)
            if kind == "target":
                pend["target_stamps"][name] = stamp
            if pend["t_first"] is None:
                pend["t_first"] = t
                pend["stamp"] = stamp
                pend["input_age_ms"] = (self.clock() - stamp) * 1e3 if stamp is not None else None

    def robot_state(self, q: np.ndarray) -> float:
        """The measured configuration; returns its monotonic receipt time."""
        with self.lock:
            self._pending["robot"] = q
            now = self.robot_rx = self._pending["robot_t"] = time.monotonic()
        return now

    def goals(self, G: np.ndarray) -> None:
        with self.lock:
            self._pending["goals"] = G
            if self._pending["t_first"] is None:
                self._pending["t_first"] = time.perf_counter()

    def guard_stopped(self, label: str) -> None:
        """The stop guard stopped the robot for body ``label``: the next cycle replans."""
        with self.lock:
            self._pending["guard"] = label

    def request(self, kind: str, timeout: float, running: Callable[[], bool]) -> tuple:
        """A service request; waits at most ``timeout`` s for the worker's answer (ok, message)."""
        if kind not in REQUESTS:
            raise ValueError(f"unknown request '{kind}' (one of {', '.join(REQUESTS)})")
        with self.lock:
            rid = self._next_id
            self._next_id += 1
            self._requests.append((kind, rid))
        self.wake.set()
        deadline = time.monotonic() + timeout
        with self._done:
            while rid not in self._responses and time.monotonic() < deadline and running():
                self._done.wait(0.1)
            return self._responses.pop(rid, (False, "timed out"))

    def ask(self, kind: str) -> None:
        """A request of the loop's own (no answer awaited); call with :attr:`lock` held."""
        self._requests.append((kind, -1))

    def live(self, name: str, value) -> None:
        with self.lock:
            self._live[name] = value

    def run_step(self, kind: str, timeout: Optional[float]) -> bool:
        """Hand a lifecycle step to the worker and wait for it; True when it succeeded."""
        done, out = threading.Event(), []
        with self.lock:
            self._transition = (kind, done, out)
        self.wake.set()
        done.wait(timeout)
        return bool(out and out[0])

    # ------------------------------------------------------------------------------------------------ worker's side
    def take_step(self) -> Optional[tuple]:
        with self.lock:
            tr, self._transition = self._transition, None
        return tr

    def take_requests(self) -> list:
        with self.lock:
            reqs, self._requests = self._requests, []
        return reqs

    def take(self) -> tuple:
        """(pending inputs, requests, live parameter changes), each cleared."""
        with self.lock:
            pend, self._pending = self._pending, _empty()
            reqs, self._requests = self._requests, []
            live, self._live = self._live, {}
        return pend, reqs, live

    def bodies(self) -> tuple:
        """Copies of the obstacle and target poses that arrived since the cycle began."""
        with self.lock:
            return dict(self._pending["obstacles"]), dict(self._pending["targets"])

    def answer(self, reqs, ok: bool, message: str, kinds=None) -> None:
        """Answer the requests (of ``kinds``, default all) among ``reqs``."""
        with self._done:
            for kind, rid in reqs:
                if rid >= 0 and (kinds is None or kind in kinds):
                    self._responses[rid] = (ok, message)
            self._done.notify_all()

    def robot_state_problem(self, timeout_s: float) -> str:
        """Why no plan may start now ("" = none): the measured robot state (joints + base pose, forwarded by the
        monitor only while both are fresh) is missing or older than ``timeout_s``."""
        with self.lock:
            rx = self.robot_rx
        if rx is None:
            return "waiting for base pose (no robot state received yet)"
        age = time.monotonic() - rx
        return f"waiting for base pose (the last robot state is {age:.1f} s old)" if age > timeout_s else ""

    def ages(self) -> tuple:
        """(the robot state's receipt time, {"age_s <input>": seconds since each input's last receipt})."""
        now = time.monotonic()
        with self.lock:
            return self.robot_rx, {f"age_s {k}": now - t for k, t in self._input_t.items()}
