"""The C heap's free memory goes back to the system: judged by the kernel's count of the process's resident pages."""

from __future__ import annotations

import gc

import pytest

from psprm_ros.heap import _malloc_trim, release_free_heap


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0


def test_release_free_heap_returns_fragmented_free_memory():
    """150 MB of 1 kB buffers with every 64th kept alive: freeing the rest leaves free holes that glibc keeps
    (the kept buffers pin the heap's top); one release gives most of them back."""
    if _malloc_trim() is None:
        pytest.skip("no glibc malloc_trim on this system")
    keep, junk = [], []
    for i in range(150_000):
        (keep if i % 64 == 0 else junk).append(bytearray(1000))
    del junk
    gc.collect()
    before = _rss_mb()
    ms = release_free_heap()
    after = _rss_mb()
    assert ms is not None and ms >= 0.0
    assert before - after > 80.0, (before, after)
    assert len(keep) == 150_000 // 64 + 1 and all(len(b) == 1000 for b in keep)
