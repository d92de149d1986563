"""The C heap's free memory goes back to the system: judged by the kernel's count of the process's resident pages.
The start-up's objects leave the full collections: judged by the clock."""

from __future__ import annotations

import gc
import time

import pytest

from psprm_ros.heap import _malloc_trim, freeze_long_lived, release_free_heap


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


def _full_collection_s() -> float:
    t0 = time.perf_counter()
    gc.collect()
    return time.perf_counter() - t0


def test_freeze_long_lived_keeps_the_start_ups_objects_out_of_full_collections():
    """Timed by the clock: a full collection over 600k long-lived container objects takes at least ten times longer
    than one after they are frozen. A cycle made after the freeze is still collected (its weakref callback fires),
    and one that was garbage before the freeze is collected by the freeze's own collection."""
    import weakref

    class Node:
        pass

    before_freeze = Node()
    before_freeze.me = before_freeze
    gone = []
    refs = [weakref.ref(before_freeze, lambda _: gone.append("before"))]
    held = [[[i], [i]] for i in range(200_000)]  # 600k tracked containers (lists)
    del before_freeze
    try:
        t_full = min(_full_collection_s() for _ in range(2))
        r = freeze_long_lived()
        assert gone == ["before"] and r["frozen"] >= 600_000
        t_frozen = min(_full_collection_s() for _ in range(2))
        after = Node()
        after.me = after
        refs.append(weakref.ref(after, lambda _: gone.append("after")))
        del after
        gc.collect()
        assert gone == ["before", "after"]
        assert t_frozen * 10 < t_full, (t_frozen, t_full)
    finally:
        gc.unfreeze()
    assert len(held) == 200_000 and all(r() is None for r in refs)
