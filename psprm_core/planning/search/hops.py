"""The hop heuristic of the roadmap search (Eqs. 3-6).

* Eq. 3, :func:`hop_heuristic`: :math:`h(q) = H_{\\min}(q) \\cdot c^{\\min}` with :math:`H_{\\min}` the hop
  distance to the goal set (:func:`hop_distances`, cached per goal set) and
* Eq. 4, :func:`~.search_types.min_edge_cost`: :math:`c^{\\min} = \\min_{(u,v) \\in E} c(q_u, q_v)`.
* Eqs. 5-6 show :math:`h(q_u) \\le c(q_u, q_v) + h(q_v)` (consistency) for non-negative weights, hence A* returns
  the optimal cost; :func:`heuristic_consistency_gap` checks this numerically on every edge.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Iterable

import numpy as np

from ..objectives import _CMIN_SAFETY
from . import search_kernels
from .graph import Roadmap
from .search_types import ArrayLike, _compiled, _node_ids, _scipy_matrix, _weights_array, min_edge_cost

_HOP_CACHE_SIZE = 16


def hop_distances(graph: Roadmap, goals: int | Iterable[int] | np.ndarray, use_cache: bool = True) -> np.ndarray:
    """Hop distance :math:`H_{\\min}(q)` of every node to the goal set (multi-source BFS), used by Eq. 3.

    Parameters
    ----------
    graph : Roadmap
    goals : int or iterable of int
        Goal node(s) (a goal region).
    use_cache : bool
        Reuse the result for the same goal set (cached in ``graph.search_cache``, LRU of 16 goal sets).  Weight
        updates keep it; node/edge additions (start/goal connection, repair) update it incrementally (hop distances
        can only decrease, propagated from the new edges); removals keep it: the cached distances were exact on a
        superset of the remaining edges, so they stay lower bounds of the true hop distances and differ by at most 1
        across every remaining edge, i.e. Eq. 3 stays admissible and consistent (Eqs. 5-6), only less tight;
        restorations trigger a full recomputation.

    Returns
    -------
    np.ndarray
        ``(n_nodes,)`` float64 minimum number of edges to reach any goal; ``inf`` when no goal is reachable (after
        removals, a cached entry may be a finite lower bound for a node that has become unreachable).  The returned
        array is shared with the cache and read-only.
    """
    g = _node_ids(graph, goals, "goal")
    cache: dict[Any, Any] = graph.search_cache
    key = ("hop", g.tobytes())
    entry = cache.pop(key, None) if use_cache else None
    if entry is not None and entry[0] == graph.restore_version:
        _, n_cov, e_cov, hops = entry
        if n_cov != graph.n_nodes or e_cov != graph.n_edges:
            hops = _hops_after_additions(graph, hops, e_cov)
    else:
        hops = _hops_full(graph, g)
    hops.flags.writeable = False
    if use_cache:
        hop_keys = [k for k in cache if isinstance(k, tuple) and k and k[0] == "hop"]
        for k in [k for k in hop_keys if cache[k][0] != graph.restore_version]:
            del cache[k]
        hop_keys = [k for k in hop_keys if k in cache]
        while len(hop_keys) >= _HOP_CACHE_SIZE:  # dicts keep insertion order: evict the least recently used
            del cache[hop_keys.pop(0)]
        cache[key] = (graph.restore_version, graph.n_nodes, graph.n_edges, hops)
    return hops


def _hops_full(graph: Roadmap, goal_ids: np.ndarray) -> np.ndarray:
    """Multi-source unweighted shortest paths from the goals (numba BFS, else ``scipy.sparse.csgraph``)."""
    from scipy.sparse.csgraph import dijkstra as _sp_dijkstra

    n = graph.n_nodes
    if goal_ids.size == 0 or n == 0:
        return np.full(n, np.inf)
    if _compiled():
        nbr, _, deg = graph.array_adjacency()
        return search_kernels.kernels().bfs_hops(nbr, deg, goal_ids.astype(np.int64), n)
    hops = _sp_dijkstra(_scipy_matrix(graph, None), directed=True, indices=goal_ids, unweighted=True, min_only=True)
    return np.array(hops, dtype=np.float64)


def _hops_after_additions(graph: Roadmap, old: np.ndarray, e_cov: int) -> np.ndarray:
    """Update hop distances after nodes/edges were only added: decrease propagation from the new edges."""
    n = graph.n_nodes
    valid = np.asarray(graph.edge_valid)
    new = np.arange(e_cov, graph.n_edges)
    new = new[valid[new]]
    if _compiled():
        nbr, _, deg = graph.array_adjacency()
        hops_arr = np.full(max(n, deg.shape[0]), np.inf)
        hops_arr[: old.shape[0]] = old
        eu = np.ascontiguousarray(graph.edge_u[new])
        ev = np.ascontiguousarray(graph.edge_v[new])
        return search_kernels.kernels().hops_decrease(nbr, deg, hops_arr, eu, ev)[:n].copy()
    hops = old.tolist() + [math.inf] * (n - old.shape[0])
    nbrs, _ = graph.python_adjacency()
    eu = np.asarray(graph.edge_u)[new].tolist()
    ev = np.asarray(graph.edge_v)[new].tolist()
    queue: deque[int] = deque()
    for a, b in zip(eu, ev):
        if hops[a] + 1 < hops[b]:
            hops[b] = hops[a] + 1
            queue.append(b)
        elif hops[b] + 1 < hops[a]:
            hops[a] = hops[b] + 1
            queue.append(a)
    while queue:  # FIFO label correcting: exact once no label decreases
        u = queue.popleft()
        hu = hops[u] + 1
        for v in nbrs[u]:
            if hu < hops[v]:
                hops[v] = hu
                queue.append(v)
    return np.asarray(hops, dtype=np.float64)


def hop_heuristic(
    graph: Roadmap,
    goals: int | Iterable[int] | np.ndarray,
    weights: ArrayLike | None = None,
    c_min: float | None = None,
) -> np.ndarray:
    """Per-node hop heuristic, Eq. 3: :math:`h(q) = H_{\\min}(q) \\cdot c^{\\min}` (``inf`` where no goal is reachable).

    ``c_min`` defaults to Eq. 4 over the valid edges and is shrunk by a relative ``1e-12`` so that the consistency
    inequality (Eqs. 5-6) also holds under floating-point rounding.
    """
    hops = hop_distances(graph, goals)
    c = min_edge_cost(graph, weights) if c_min is None else float(c_min)
    c *= _CMIN_SAFETY
    if c > 0:
        return hops * c  # inf stays inf
    with np.errstate(invalid="ignore"):
        h = hops * c
    h[~np.isfinite(hops)] = np.inf
    return h


def heuristic_consistency_gap(
    graph: Roadmap, h: np.ndarray, weights: ArrayLike | None = None
) -> float:
    """Largest violation :math:`\\max_{(u,v)} h(q_u) - c(q_u, q_v) - h(q_v)` over valid edges, both directions.

    A value <= 0 means the heuristic is consistent (Eqs. 5-6).  Pairs where both ``h`` are ``inf`` are ignored.
    """
    w = _weights_array(graph, weights)
    eids = graph.valid_edge_ids()
    if eids.size == 0:
        return -np.inf
    u = np.asarray(graph.edge_u)[eids]
    v = np.asarray(graph.edge_v)[eids]
    hu, hv, we = h[u], h[v], w[eids]
    with np.errstate(invalid="ignore"):
        gaps = np.concatenate([hu - we - hv, hv - we - hu])
    gaps = gaps[~np.isnan(gaps)]  # inf - inf
    return float(gaps.max()) if gaps.size else -np.inf
