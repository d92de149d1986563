"""One single-threaded executor per node, each spinning on its own thread, all in one rclpy context.

Why not rclpy's ``MultiThreadedExecutor``: with a node whose subscriptions share a mutually exclusive callback
group, it leaves that group out of the wait set while one of its callbacks runs on a worker thread, and on an idle
multi-core machine the wait is then not always woken when the callback ends. Measured with the robot adapter and
``sim_robot`` on an idle 2-core machine (``/odom`` at 50 Hz from the other process, steady stamps): messages reached
the adapter up to 1.0 s late and in bursts, the base follower overshot corners by 0.3-0.7 rad; the same nodes on
single-threaded executors received every message within 4 ms and tracked within 0.01 m / 0.03 rad. A busy second
core hid the fault (the two Python threads then ran one after the other).

A node's callbacks therefore run one at a time, in arrival order; nodes run side by side (the GIL is released while
an executor waits), so a long callback of one node (a lifecycle transition that builds the roadmap) never delays
another node's messages. Work that takes long inside a node belongs on that node's own worker thread (the roadmap
server's planner, the robot adapter's trajectory checks), not in a callback.
"""

from __future__ import annotations

import threading
from typing import List, Optional


class NodeSpinner:
    """``spinner = NodeSpinner(context); spinner.add(node); spinner.start(); ...; spinner.shutdown()``."""

    def __init__(self, context=None):
        self.context = context
        self._executors: list = []
        self._threads: List[threading.Thread] = []
        self.errors: list = []  # (node name, exception) of an executor that stopped on an error

    def add(self, node) -> None:
        """Give ``node`` (an ``rclpy.node.Node``) its own executor; it spins from :meth:`start` (or at once if
        already started)."""
        from rclpy.executors import SingleThreadedExecutor

        ex = SingleThreadedExecutor(context=self.context)
        ex.add_node(node)
        self._executors.append((node.get_name(), ex))
        if self._threads:
            self._spawn(node.get_name(), ex)

    def start(self) -> "NodeSpinner":
        for name, ex in self._executors:
            self._spawn(name, ex)
        return self

    def _spawn(self, name: str, ex) -> None:
        t = threading.Thread(target=self._spin, args=(name, ex), name=f"spin-{name}", daemon=True)
        t.start()
        self._threads.append(t)

    def _spin(self, name: str, ex) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            ex.spin()
        except ExternalShutdownException:
            pass
        except Exception as exc:  # an executor that stops on an error is reported, not silent
            self.errors.append((name, exc))

    def alive(self) -> bool:
        """True while every executor still spins."""
        return bool(self._threads) and all(t.is_alive() for t in self._threads)

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Block until an executor stops (shutdown, an error) or ``timeout`` passes; True if one stopped."""
        import time

        deadline = None if timeout is None else time.monotonic() + timeout
        while self.alive():
            if deadline is not None and time.monotonic() >= deadline:
                return False
            time.sleep(0.1)
        return True

    def shutdown(self, timeout_sec: float = 2.0) -> None:
        """Stop every executor and join its thread (callbacks in flight finish first)."""
        for _, ex in self._executors:
            try:
                ex.shutdown(timeout_sec=timeout_sec)
            except Exception:
                pass
        for t in self._threads:
            t.join(timeout=timeout_sec + 3.0)
