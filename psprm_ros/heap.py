"""Heap hygiene for long-running node processes: give the C heap's free memory back to the system (glibc
``malloc_trim``), and keep the start-up's objects out of the cyclic collector's full passes (``gc.freeze``).

A node that plans for hours allocates and frees numpy and torch buffers of many sizes on several threads. glibc keeps
what is freed inside its arenas for reuse; fragmented, that memory is never handed back, and the process's resident
size climbs in steps although the live data do not grow. ``malloc_trim(0)`` returns every free page of every arena.
Measured on the closed-loop soak (``python -m psprm_ros.harness.soak``): the suite process held 1,138 MB after 40 minutes;
one trim brought it to 965 MB with nothing else changed.

A node process holds several hundred thousand objects that live as long as it does (the modules of torch, numpy and
rclpy, the robot and scene models, the roadmap). Python's cyclic collector walks all of them at each full
(generation 2) collection: in the closed-loop demo every node process stopped for 200-430 ms at such a pass while
it ran (up to 880 ms), the roadmap server about every 30 s. A robot adapter stopped that long leaves the base
driving on its last twist. :func:`freeze_long_lived` moves what is alive after start-up into the collector's
permanent generation, so the full passes walk only what the node allocates while it runs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import time
from typing import Optional


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's ``malloc_trim``, or None (another C library, e.g. musl or macOS: nothing to do)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        fn = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def release_free_heap() -> Optional[float]:
    """Return the C heap's free pages to the system; the milliseconds it took, or None where glibc's
    ``malloc_trim`` is not available."""
    fn = _malloc_trim()
    if fn is None:
        return None
    t0 = time.perf_counter()
    fn(0)
    return (time.perf_counter() - t0) * 1e3


def freeze_long_lived() -> dict:
    """Collect once, then move every object still alive into the cyclic collector's permanent generation
    (``gc.freeze``): later full collections no longer walk them (they stay reference-counted, and are freed when their
    last reference goes unless they sit in a cycle). Call once a process has finished starting (modules imported,
    models loaded, nodes configured). Returns ``{"frozen": objects frozen, "collect_ms": the collection's time}``;
    :func:`gc.unfreeze` undoes it."""
    t0 = time.perf_counter()
    gc.collect()
    ms = (time.perf_counter() - t0) * 1e3
    gc.freeze()
    return {"frozen": gc.get_freeze_count(), "collect_ms": ms}
