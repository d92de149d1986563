"""The robot adapter's acceptance thread: trajectories are checked and started on a thread of their own, in arrival
order, so that a check (tens of ms, more on a busy machine) never holds up the control steps on the node's executor
while the base follows the trajectory under way."""

from __future__ import annotations

import queue
import threading
from typing import Callable, Optional


class TrajectoryInbox:
    """Trajectories waiting for ``accept(msg)``, taken in arrival order on one thread (a stop trajectory too, so that
    nothing accepted before it runs after it). ``accept`` raising stops the robot through ``stop(why)``; the thread
    never dies on a message. ``wait_accepted(timeout)`` waits for the acceptance under way."""

    def __init__(self, accept: Callable, stop: Callable[[str], None], wait_accepted: Callable[[float], None]):
        self._accept, self._stop, self._wait_accepted = accept, stop, wait_accepted
        self._queue: queue.Queue = queue.Queue()
        self._thread: Optional[threading.Thread] = None

    def start(self, name: str) -> None:
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, msg) -> None:
        self._queue.put(msg)

    def _run(self) -> None:
        while True:
            msg = self._queue.get()
            try:
                if msg is None:
                    return
                self._accept(msg)
            except Exception as exc:  # never die on a message; a trajectory we cannot execute stops the robot
                try:
                    self._stop(f"cannot execute the trajectory: {exc}")
                except Exception:
                    pass
            finally:
                self._queue.task_done()

    def quiesce(self, timeout: float = 2.0) -> None:
        """Drop the trajectories not yet accepted and wait for the one being accepted (at most ``timeout``): what a
        deactivation, a shutdown or the node's end stops must not start after the stop."""
        while True:
            try:
                self._queue.get_nowait()
                self._queue.task_done()
            except queue.Empty:
                break
        self._wait_accepted(timeout)

    def end(self, timeout: float = 2.0) -> None:
        """Drop the unchecked trajectories and end the thread (cleanup, the node's end)."""
        self.quiesce(timeout)
        if self._thread is not None and self._thread.is_alive():
            self._queue.put(None)
            self._thread.join(timeout)
        self._thread = None
