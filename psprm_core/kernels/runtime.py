"""What the compiled kernels need from the process: whether numba imports, the :func:`bulk` scope of large batches and
the worker threads that run their row chunks. Nothing here imports numba at import time."""

from __future__ import annotations

import contextlib
import contextvars
import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator, Optional

import torch

log = logging.getLogger(__name__)

_BULK_WORKERS: contextvars.ContextVar[int] = contextvars.ContextVar("psprm_bulk_workers", default=0)


@functools.lru_cache(maxsize=1)
def numba_importable() -> bool:
    """Whether numba can be imported (checked once). The compiled small-batch paths and the compiled roadmap searches
    (:mod:`psprm_core.planning.search.search_kernels`) need it."""
    try:
        import numba  # noqa: F401
    except Exception as exc:  # pragma: no cover - numba is a pinned requirement
        log.warning("numba unavailable (%s): batches use torch, graph searches Python", exc)
        return False
    return True


@contextlib.contextmanager
def bulk(workers: Optional[int] = None) -> Iterator[None]:
    """Run a block in which CPU batches of any size take the compiled kernels (of objects whose ``Compute`` chose
    them), their rows split into chunks of at least ``bulk_chunk`` over ``workers`` threads (default
    ``torch.get_num_threads()``). The results are those of the small-batch path (row by row, float64). Holds for the
    calling thread only (a :class:`contextvars.ContextVar`): a query on another thread keeps its small-batch rules."""
    token = _BULK_WORKERS.set(max(1, int(torch.get_num_threads() if workers is None else workers)))
    try:
        yield
    finally:
        _BULK_WORKERS.reset(token)


def bulk_workers() -> int:
    """The worker threads of the enclosing :func:`bulk` block (0 outside one)."""
    return _BULK_WORKERS.get()


@functools.lru_cache(maxsize=4)
def worker_pool(workers: int) -> ThreadPoolExecutor:
    """The worker threads of bulk calls and of the hop table (created on first use, one pool per worker count; the
    kernels release the GIL)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="psprm-kernels")
