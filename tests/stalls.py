"""A stall of the test's own process, as a machine that does not schedule it (or a long collection) makes one."""

from __future__ import annotations

import time


def freeze_this_process(seconds: float) -> float:
    """Stop every thread of this process (the middleware's too) for ``seconds``: a helper process sends SIGSTOP,
    waits and sends SIGCONT. Messages that arrive meanwhile wait in the sockets and queues, and the nodes' timers are
    overdue when the process runs again. Returns how long this process was away."""
    import os
    import subprocess

    t0 = time.perf_counter()
    pid = os.getpid()
    helper = subprocess.Popen(["/bin/sh", "-c", f"kill -STOP {pid}; sleep {seconds:.3f}; kill -CONT {pid}"])
    helper.wait()
    return time.perf_counter() - t0
