"""Give the C heap's free memory back to the system (glibc ``malloc_trim``).

A node that plans for hours allocates and frees numpy and torch buffers of many sizes on several threads. glibc keeps
what is freed inside its arenas for reuse; fragmented, that memory is never handed back, and the process's resident
size climbs in steps although the live data do not grow. ``malloc_trim(0)`` returns every free page of every arena.
Measured on the closed-loop soak (``python -m psprm_ros.soak``): the suite process held 1,138 MB after 40 minutes;
one trim brought it to 965 MB with nothing else changed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
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
