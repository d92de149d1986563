"""Compiled (numba) kernels of the roadmap searches: A* (Eqs. 3-6), the hop BFS of Eq. 3 and its update after additions.

They work on the padded array adjacency of :meth:`~psprm_core.planning.search.graph.Roadmap.array_adjacency`
(``nbr[u, :deg[u]]`` are the neighbours of ``u``, ``eid[u, :deg[u]]`` the connecting edge ids) and are the default
backend of :mod:`psprm_core.planning.search.graph_search`; its pure-Python ``heapq`` loops stay as the reference
implementation (same expansion order: ties broken by the smaller node id, as ``heapq`` does on ``(f, node)`` tuples).

Nothing is compiled at import: numba compiles a kernel on its first call (about 1-2 s, then cached on disk with
``cache=True``). :func:`available` tells whether numba can be imported.
"""

from __future__ import annotations

import functools
from typing import Any

from ...kernels.runtime import numba_importable

__all__ = ["available", "kernels"]


def available() -> bool:
    """Whether numba is importable (the searches fall back to the Python loops otherwise, with one warning)."""
    return numba_importable()


@functools.lru_cache(maxsize=1)
def kernels() -> Any:
    """The jitted kernels (module :mod:`psprm_core.planning.search._search_numba`: ``astar``, ``bfs_hops``,
    ``hops_decrease``); imported on first use, each compiled on its first call."""
    from . import _search_numba

    return _search_numba
