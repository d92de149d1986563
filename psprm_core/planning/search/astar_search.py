"""A* and Dijkstra over the roadmap: the A* of the hop heuristic (Eqs. 3-6) or any consistent per-node heuristic,
the pure-Python reference loop it is checked against, and the all-nodes multi-source Dijkstra.

:func:`astar` runs as a compiled numba kernel (:mod:`~psprm_core.planning.search.search_kernels`) over the cached
padded array adjacency of :class:`~psprm_core.planning.search.graph.Roadmap` (``backend="auto"``); ``backend="python"``
selects the reference pure-Python ``heapq`` loop over the per-node adjacency lists (same expansion order, ties broken by
node id). Both terminate at the first goal popped. The all-nodes :func:`dijkstra` uses ``scipy.sparse.csgraph``.
Unreachable goals give ``SearchResult(success=False, reason=...)``, never an exception. The lazy search built on them
is :func:`~psprm_core.planning.search.graph_search.lazy_astar`; :mod:`.graph_search` re-exports both.
"""

from __future__ import annotations

import heapq
import logging
import math
from typing import Iterable, Union

import numpy as np

from ...errors import InputError
from . import search_kernels
from .graph import Roadmap
from .hops import hop_heuristic
from ..results import Failure
from .search_types import (ArrayLike, Backend, SearchResult, _compiled, _node_ids, _scipy_matrix, _weights_array,
                           _weights_list)

logger = logging.getLogger(__name__)

HeuristicSpec = Union[str, np.ndarray]


# ====================================================================== all-nodes searches (compiled)
def dijkstra(
    graph: Roadmap,
    sources: int | Iterable[int] | np.ndarray,
    weights: ArrayLike | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-source Dijkstra over the valid edges (``scipy.sparse.csgraph``).

    Parameters
    ----------
    graph : Roadmap
    sources : int or iterable of int
        Source node(s); the distance of a node is to its nearest source.
    weights : array-like, optional
        ``(n_edges,)`` non-negative weights indexed by edge id (Eq. 2); the roadmap's weights when omitted.
        ``inf`` marks an unusable edge.

    Returns
    -------
    dist : np.ndarray
        ``(n_nodes,)`` float64 cost to the nearest source, ``inf`` when unreachable.
    parent : np.ndarray
        ``(n_nodes,)`` int64 predecessor towards the nearest source, ``-1`` for sources and unreachable nodes.
    """
    from scipy.sparse.csgraph import dijkstra as _sp_dijkstra

    src = _node_ids(graph, sources, "source")
    n = graph.n_nodes
    dist = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    if src.size == 0 or n == 0:
        return dist, parent
    w = _weights_array(graph, weights)
    if np.any(w < 0):
        raise InputError("Dijkstra requires non-negative weights")
    csr = graph.csr()
    mat = _scipy_matrix(graph, w[csr.edge_ids])
    d, pred, _ = _sp_dijkstra(mat, directed=True, indices=src, return_predecessors=True, min_only=True)
    dist[:] = d
    parent[:] = np.where(pred < 0, -1, pred)
    # Removed source nodes have no edges; they still get distance 0 from scipy, which is right (they are sources).
    return dist, parent


# ====================================================================== A*
def _resolve_heuristic(
    graph: Roadmap, goals: np.ndarray, w: np.ndarray, heuristic: HeuristicSpec | None
) -> np.ndarray | None:
    """Per-node heuristic array (or ``None`` for h = 0)."""
    if heuristic is None or (isinstance(heuristic, str) and heuristic in ("zero", "none", "dijkstra")):
        return None
    if isinstance(heuristic, str):
        if heuristic == "hop":
            return hop_heuristic(graph, goals, w)
        if heuristic == "exact":  # cost-to-go from a compiled Dijkstra from the goals: perfect heuristic
            return dijkstra(graph, goals, w)[0]
        raise InputError(f"unknown heuristic {heuristic!r}; use 'hop', 'zero', 'exact' or an array")
    h = np.asarray(heuristic, dtype=np.float64).reshape(-1)
    if h.shape[0] != graph.n_nodes:
        raise InputError("heuristic array must have one entry per node slot")
    return h


def _astar_core(
    nbrs: list[list[int]],
    eids: list[list[int]],
    w: list[float],
    h: list[float] | None,
    start: int,
    goal_set: set[int] | frozenset[int],
    max_expansions: int | None,
) -> tuple[int | None, dict[int, int], dict[int, int], float, int, bool]:
    """Heapq A* (h = None is Dijkstra).  Returns (goal, parent, parent_edge, cost, expanded, hit_limit).

    With a consistent heuristic a closed node is final, so closed neighbours are skipped (Eqs. 5-6).
    """
    inf = math.inf
    g: dict[int, float] = {start: 0.0}
    parent: dict[int, int] = {}
    pedge: dict[int, int] = {}
    closed: set[int] = set()
    heap: list[tuple[float, int]] = [((h[start] if h is not None else 0.0), start)]
    push, pop = heapq.heappush, heapq.heappop
    expanded = 0
    limit = max_expansions if max_expansions is not None else -1
    while heap:
        _, u = pop(heap)
        if u in closed:
            continue
        closed.add(u)
        expanded += 1
        if u in goal_set:
            return u, parent, pedge, g[u], expanded, False
        if expanded == limit:
            return None, parent, pedge, inf, expanded, True
        gu = g[u]
        for v, e in zip(nbrs[u], eids[u]):
            if v in closed:
                continue
            nd = gu + w[e]
            if nd < g.get(v, inf):
                if h is None:
                    g[v] = nd
                    parent[v] = u
                    pedge[v] = e
                    push(heap, (nd, v))
                else:
                    hv = h[v]
                    if hv == inf:  # cannot reach any goal (different component): prune
                        continue
                    g[v] = nd
                    parent[v] = u
                    pedge[v] = e
                    push(heap, (nd + hv, v))
    return None, parent, pedge, inf, expanded, False


def _fail(reason: str, failure: Failure, expanded: int = 0) -> SearchResult:
    logger.debug("search failed: %s", reason)
    return SearchResult(path=[], cost=math.inf, expanded=expanded, success=False, reason=reason, failure=failure)


def _run_astar(
    graph: Roadmap,
    start: int,
    goal_ids: np.ndarray,
    w_arr: np.ndarray,
    w_list: list[float] | None,
    h_arr: np.ndarray | None,
    max_expansions: int | None,
) -> SearchResult:
    """Validate endpoints, run the compiled kernel (``w_list`` None) or :func:`_astar_core`, assemble the
    :class:`SearchResult`."""
    node_valid = np.asarray(graph.node_valid)
    if not node_valid[start]:
        return _fail(f"start node {start} has been removed from the roadmap", Failure.START_BLOCKED)
    goal_ids = goal_ids[node_valid[goal_ids]]
    if goal_ids.size == 0:
        return _fail("goal set is empty (or all goal nodes were removed)", Failure.GOAL_BLOCKED)
    goal_set = set(goal_ids.tolist())
    if start in goal_set:
        return SearchResult(path=[start], cost=0.0, expanded=1, success=True, reason="ok: start is a goal",
                            goal=start)
    if h_arr is not None and not np.isfinite(h_arr[start]):
        return _fail(f"no goal is reachable from start {start}: different connected component",
                     Failure.UNREACHABLE)
    if w_list is None:
        nbr, eid, deg = graph.array_adjacency()
        rows = deg.shape[0]
        goal_mask = np.zeros(rows, dtype=bool)
        goal_mask[goal_ids] = True
        h_k = np.zeros(1) if h_arr is None else h_arr
        if h_arr is not None and h_k.shape[0] < rows:  # spare adjacency rows have no edges: never reached
            h_k = np.concatenate([h_k, np.full(rows - h_k.shape[0], np.inf)])
        goal, cost, expanded, hit_limit, par, pe, g_arr, closed = search_kernels.kernels().astar(
            nbr, eid, deg, np.ascontiguousarray(w_arr, dtype=np.float64), np.ascontiguousarray(h_k, dtype=np.float64),
            h_arr is not None, start, goal_mask, -1 if max_expansions is None else int(max_expansions))
        if goal == -2:
            return _fail("heap capacity exceeded by reopened nodes (inconsistent heuristic)", Failure.INTERNAL,
                         int(expanded))
        goal = None if goal < 0 else int(goal)
        parent, pedge = par, pe
    else:
        nbrs, eids = graph.python_adjacency()
        h_list = h_arr.tolist() if h_arr is not None else None
        goal, parent, pedge, cost, expanded, hit_limit = _astar_core(
            nbrs, eids, w_list, h_list, start, goal_set, max_expansions
        )
    if goal is None:
        if hit_limit:
            return _fail(f"expansion limit {max_expansions} reached", Failure.SEARCH_LIMIT, int(expanded))
        return _fail(f"no goal is reachable from start {start} (disconnected or all connecting edges invalid)",
                     Failure.UNREACHABLE, int(expanded))
    path = [goal]
    edges: list[int] = []
    while path[-1] != start:
        edges.append(int(pedge[path[-1]]))
        path.append(int(parent[path[-1]]))
    path.reverse()
    edges.reverse()
    out = SearchResult(path=path, cost=float(cost), expanded=int(expanded), success=True, reason="ok", edges=edges,
                       goal=goal)
    if w_list is None:
        out.g, out.closed = g_arr, closed
    return out


def astar(
    graph: Roadmap,
    start: int,
    goals: int | Iterable[int] | np.ndarray,
    weights: ArrayLike | None = None,
    heuristic: HeuristicSpec = "hop",
    max_expansions: int | None = None,
    backend: Backend = "auto",
) -> SearchResult:
    """A* from ``start`` to the nearest (cheapest) node of a goal set, with the PS-PRM hop heuristic (Eqs. 3-6).

    Parameters
    ----------
    graph : Roadmap
    start : int
        Start node id.
    goals : int or iterable of int
        Goal node id(s); several ids form a goal region (the search stops at the first goal closed, which is the
        cheapest one since the heuristic is consistent).
    weights : array-like, optional
        ``(n_edges,)`` non-negative edge weights by edge id (Eq. 2; ``inf`` = unusable edge).  Default: the
        roadmap's weights (their Python-list form is cached, which saves ~1 ms per query on 10^5 edges).
    heuristic : {"hop", "zero", "exact"} or np.ndarray
        ``"hop"``: :math:`h = H_{\\min} c^{\\min}` (Eqs. 3-4; the hop BFS is cached per goal set), consistent for any
        non-negative weights (Eqs. 5-6), so the returned cost is optimal.  ``"zero"``: Dijkstra.  ``"exact"``:
        exact cost-to-go from a compiled multi-source Dijkstra from the goals (expands only optimal-path nodes; useful
        when several queries share the same weights and goals).  An array gives a custom per-node heuristic (it must
        be consistent for the result to be optimal).
    max_expansions : int, optional
        Give up (``success=False``) after this many expansions.
    backend : {"auto", "python"}
        ``"auto"``: the compiled kernel (numba; the Python loop when numba is missing); ``"python"``: the reference
        ``heapq`` loop. Same result and expansion order.

    Returns
    -------
    SearchResult
        ``success=False`` with a ``reason`` when no goal is reachable; never raises for unreachable goals.
    """
    start = int(start)
    if not 0 <= start < graph.n_nodes:
        raise InputError(f"start node {start} out of range [0, {graph.n_nodes})")
    goal_ids = _node_ids(graph, goals, "goal")
    w_arr = _weights_array(graph, weights)
    w_list = None if _compiled(backend) else _weights_list(graph, weights)
    h_arr = _resolve_heuristic(graph, goal_ids, w_arr, heuristic) if goal_ids.size else None
    return _run_astar(graph, start, goal_ids, w_arr, w_list, h_arr, max_expansions)
