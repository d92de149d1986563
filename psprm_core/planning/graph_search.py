"""Edge weights (Eqs. 1-2) and graph searches (Dijkstra, hop BFS, A* with the hop heuristic of Eqs. 3-6).

Paper, section "PRM construction and scoring":

* Eq. 1, :func:`edge_perception`: :math:`c_p(q_u, q_v) = (c_p(q_u) + c_p(q_v) + \\sum_{i=1}^N c_p(q_i)) / (N + 2)`.
* Eq. 2, :func:`combined_weight`: :math:`c(q_u, q_v) = 1 - \\alpha c_p(q_u, q_v) + (1 - \\alpha) c_m(q_u, q_v)`.
* Eq. 3, :func:`astar` default heuristic: :math:`h(q) = H_{\\min}(q) \\cdot c^{\\min}` with :math:`H_{\\min}` the hop
  distance to the goal set (:func:`hop_distances`, cached per goal set) and
* Eq. 4, :func:`min_edge_cost`: :math:`c^{\\min} = \\min_{(u,v) \\in E} c(q_u, q_v)`.
* Eqs. 5-6 show :math:`h(q_u) \\le c(q_u, q_v) + h(q_v)` (consistency) for non-negative weights, hence A* returns the
  optimal cost; :func:`heuristic_consistency_gap` checks this numerically on every edge.
* Beside Eq. 2, :func:`motion_weighted` charges the perception loss per unit of motion,
  :math:`c = c_m ((1 - \\alpha) + \\alpha (1 - c_p))`, with the consistent heuristic :func:`motion_heuristic`.

:func:`lazy_astar` evaluates expensive edge data (perception scores of the interpolated configurations, collision
checks) only for edges on candidate paths: it searches, asks a callback to verify the unverified edges of the path,
applies the returned invalidations / weight updates and searches again until the returned path is fully verified.

A* and the hop BFS run as compiled numba kernels (:mod:`~psprm_core.planning.search_kernels`) over the cached padded
array adjacency of :class:`~psprm_core.planning.graph.Roadmap` (``backend="auto"``); ``backend="python"`` selects
the reference pure-Python ``heapq`` loop over the per-node adjacency lists (same expansion order, ties broken by node
id). Both terminate at the first goal popped. The all-nodes :func:`dijkstra` uses ``scipy.sparse.csgraph``.
Unreachable goals give ``SearchResult(success=False, reason=...)``, never an exception.
"""

from __future__ import annotations

import heapq
import logging
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence, Union

import numpy as np

from psprm_core.planning import search_kernels
from psprm_core.planning.graph import Roadmap
from ..errors import InputError

logger = logging.getLogger(__name__)

__all__ = [
    "EdgeCheck",
    "SearchResult",
    "astar",
    "combined_weight",
    "dijkstra",
    "edge_weight",
    "edge_perception",
    "heuristic_consistency_gap",
    "hop_distances",
    "hop_heuristic",
    "lazy_astar",
    "min_edge_cost",
    "motion_heuristic",
    "motion_weighted",
    "path_cost",
]

ArrayLike = Any  # numpy array, torch tensor or Python float
HeuristicSpec = Union[str, np.ndarray]
Backend = str  # "auto" (compiled when numba is available) or "python"
_HOP_CACHE_SIZE = 16
#: Relative shrink of :math:`c^{\min}` in Eq. 3 so that floating-point rounding cannot break Eqs. 5-6.
_CMIN_SAFETY = 1.0 - 1e-12


# ====================================================================== edge weights (Eqs. 1-2)
def edge_perception(scores_u: ArrayLike, scores_v: ArrayLike, interior: ArrayLike | None = None) -> ArrayLike:
    """Normalised perception score of edges, Eq. 1.

    .. math:: c_p(q_u, q_v) = \\frac{c_p(q_u) + c_p(q_v) + \\sum_{i=1}^{N} c_p(q_i)}{N + 2}

    Parameters
    ----------
    scores_u, scores_v : array-like, shape (E,)
        Normalised perception scores :math:`c_p \\in [0, 1]` of the edge endpoints (numpy or torch).
    interior : array-like, shape (E, N), optional
        Scores of the :math:`N` interpolated intermediate configurations of each edge (``N`` may be 0);
        same library as the endpoint scores.

    Returns
    -------
    array-like, shape (E,)
        :math:`c_p(q_u, q_v)`, same type (numpy / torch) as the inputs.
    """
    if interior is None:
        return (scores_u + scores_v) / 2.0
    n_interior = interior.shape[-1]
    return (scores_u + scores_v + interior.sum(-1)) / float(n_interior + 2)


def combined_weight(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float) -> ArrayLike:
    """Combined PS-PRM edge weight, Eq. 2: :math:`c = 1 - \\alpha c_p + (1 - \\alpha) c_m`.

    Parameters
    ----------
    p_edge : array-like
        Normalised edge perception score :math:`c_p(q_u, q_v) \\in [0, 1]` (Eq. 1); numpy, torch or float.
    c_motion : array-like
        Normalised motion cost :math:`c_m(q_u, q_v) \\in [0, 1]`.
    alpha : float
        Trade-off :math:`\\alpha \\in [0, 1]` (1 = perception only, 0 = motion only).

    Returns
    -------
    array-like
        Edge weight in :math:`[0, 2]` (non-negative as required by the consistency proof, Eqs. 5-6).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha must lie in [0, 1], got {alpha}")
    return 1.0 - alpha * p_edge + (1.0 - alpha) * c_motion


#: Edge-weight forms: ``eq2`` (the paper's Eq. 2) and ``motion`` (perception loss per unit of motion).
OBJECTIVES = ("eq2", "motion")


def motion_weighted(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float) -> ArrayLike:
    """Motion-weighted edge weight: :math:`c = c_m \left((1 - \alpha) + \alpha (1 - c_p)\right)`.

    The perception loss :math:`1 - c_p` (Eq. 1) is charged per unit of motion, so a path's cost is
    :math:`(1 - \alpha) L + \alpha U` with :math:`L` its motion length and :math:`U` the length along which the target is
    not seen (both in units of the roadmap's longest edge). Unlike Eq. 2 it charges nothing per edge: the cost does not
    grow with the hop count, and a long edge pays for every part of it that sees poorly. Every weight is at least
    :math:`(1 - \alpha) c_m`, which makes a lower bound of the motion to the goal an admissible, consistent heuristic
    (:func:`motion_heuristic`).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha must lie in [0, 1], got {alpha}")
    return c_motion * ((1.0 - alpha) + alpha * (1.0 - p_edge))


def edge_weight(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float, objective: str = "eq2") -> ArrayLike:
    """Edge weight of the objective form ``objective`` (:data:`OBJECTIVES`): :func:`combined_weight` (Eq. 2) or
    :func:`motion_weighted`."""
    if objective == "eq2":
        return combined_weight(p_edge, c_motion, alpha)
    if objective == "motion":
        return motion_weighted(p_edge, c_motion, alpha)
    raise InputError(f"unknown objective {objective!r} (one of {', '.join(OBJECTIVES)})")


def motion_heuristic(lower_bound: np.ndarray, alpha: float, scale: float) -> np.ndarray:
    """Consistent A* heuristic of the :func:`motion_weighted` form: :math:`h(q) = (1 - \alpha) d(q) / s`.

    ``lower_bound`` (n,): for each node a lower bound :math:`d(q)` of the motion cost of any path from it to the goal
    set, which is a metric's distance to the nearest goal (so :math:`d(q_u) \le m(q_u, q_v) + d(q_v)` on every edge
    whose motion cost is :math:`m`); ``scale`` the motion cost that :math:`c_m = 1` stands for. Every edge weighs at
    least :math:`(1 - \alpha) m / s`, hence :math:`h(q_u) \le c(q_u, q_v) + h(q_v)` (Eqs. 5-6). ``inf`` stays
    ``inf``. Shrunk by a relative 1e-12 against rounding, like Eq. 3."""
    return np.asarray(lower_bound, dtype=np.float64) * ((1.0 - float(alpha)) / float(scale) * _CMIN_SAFETY)


# ====================================================================== results
@dataclass
class SearchResult:
    """Outcome of :func:`astar` / :func:`lazy_astar`.

    Attributes
    ----------
    path : list of int
        Node ids from the start to the reached goal (empty on failure).
    cost : float
        Sum of the edge weights along ``path`` (``inf`` on failure).
    expanded : int
        Nodes expanded (popped and closed), summed over all searches for :func:`lazy_astar`.
    success : bool
        Whether a path was found.
    reason : str
        Human-readable status (why it failed, or ``"ok"``).
    edges : list of int
        Edge ids along ``path``.
    goal : int or None
        The goal node reached.
    iterations : int
        Number of searches run (1 for :func:`astar`).
    invalidated_edges : list of int
        Edges the :func:`lazy_astar` callback rejected.
    updated_edges : dict
        ``{edge id: new weight}`` reported by the :func:`lazy_astar` callback.
    verified_edges : list of int
        Edges the :func:`lazy_astar` callback checked (accepted or rejected).
    """

    path: list[int]
    cost: float
    expanded: int
    success: bool
    reason: str
    edges: list[int] = field(default_factory=list)
    goal: int | None = None
    iterations: int = 1
    invalidated_edges: list[int] = field(default_factory=list)
    updated_edges: dict[int, float] = field(default_factory=dict)
    verified_edges: list[int] = field(default_factory=list)
    g: np.ndarray | None = field(default=None, repr=False)  # compiled search: cost from the start of every node
    closed: np.ndarray | None = field(default=None, repr=False)  # and which nodes it closed (g exact there)


@dataclass
class EdgeCheck:
    """Answer of a :func:`lazy_astar` verification callback.

    Attributes
    ----------
    invalid : sequence of int
        Edge ids that must not be used (collision, invalid projection, ...).
    weights : mapping int -> float, optional
        Updated (verified) weights of some edges, e.g. Eq. 2 recomputed with the Eq. 1 perception score of the
        interpolated configurations.  Edges passed to the callback and absent from both fields keep their weight.
    """

    invalid: Sequence[int] = ()
    weights: Mapping[int, float] | None = None


VerifyCallback = Callable[[np.ndarray, list[int]], Union[EdgeCheck, Iterable[int], None]]


# ====================================================================== helpers
def _weights_array(graph: Roadmap, weights: ArrayLike | None) -> np.ndarray:
    """Edge weights indexed by edge id as float64 numpy (``None`` = the roadmap's own weights)."""
    if weights is None:
        return np.asarray(graph.weights)
    if hasattr(weights, "detach"):  # torch tensor
        weights = weights.detach().cpu().numpy()
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape[0] != graph.n_edges:
        raise InputError(f"weights has {w.shape[0]} entries, the roadmap has {graph.n_edges} edge slots")
    return w


def _weights_list(graph: Roadmap, weights: ArrayLike | None) -> list[float]:
    """Edge weights as a Python list (cached for the roadmap's own weights)."""
    if weights is None:
        return graph.python_weights()
    return _weights_array(graph, weights).tolist()


def _node_ids(graph: Roadmap, nodes: int | Iterable[int] | np.ndarray, what: str) -> np.ndarray:
    arr = np.unique(np.asarray(list(nodes) if not isinstance(nodes, (int, np.integer, np.ndarray)) else nodes,
                               dtype=np.int64).reshape(-1))
    if arr.size and (arr.min() < 0 or arr.max() >= graph.n_nodes):
        raise InputError(f"{what} node id out of range [0, {graph.n_nodes})")
    return arr


def _compiled(backend: Backend = "auto") -> bool:
    """Whether to run the numba kernels (``backend`` "auto" with numba importable) or the Python loops."""
    if backend not in ("auto", "python"):
        raise InputError(f"unknown search backend {backend!r}; use 'auto' or 'python'")
    return backend == "auto" and search_kernels.available()


def _scipy_matrix(graph: Roadmap, data: np.ndarray | None) -> Any:
    """``scipy.sparse.csr_array`` of the valid edges (both directions); ``data`` per CSR entry (ones if None)."""
    from scipy.sparse import csr_array

    csr = graph.csr()
    n = graph.n_nodes
    vals = np.ones(csr.nnz, dtype=np.float64) if data is None else data
    # Explicit zero entries are kept as zero-weight edges by scipy.sparse.csgraph (zero weights are legal, Eq. 2).
    return csr_array((vals, csr.indices, csr.indptr), shape=(n, n))


def min_edge_cost(graph: Roadmap, weights: ArrayLike | None = None) -> float:
    """Minimum finite edge weight over the valid edges, Eq. 4 (0 when the roadmap has no finite edge)."""
    w = _weights_array(graph, weights)
    valid = np.asarray(graph.edge_valid)
    c = float(np.min(w, where=valid, initial=np.inf)) if w.size else np.inf  # no copy of the weights
    if not np.isfinite(c):  # no finite edge (NaN weights are rejected when set)
        return 0.0
    if c < 0:
        raise InputError("edge weights must be non-negative for the hop heuristic (Eqs. 5-6)")
    return c


def path_cost(graph: Roadmap, path: Sequence[int], weights: ArrayLike | None = None) -> float:
    """Sum of the weights along a node path (``KeyError`` when consecutive nodes are not connected)."""
    w = _weights_array(graph, weights)
    return float(w[graph.edge_ids_of_path(path)].sum()) if len(path) > 1 else 0.0


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


def _fail(reason: str, expanded: int = 0) -> SearchResult:
    logger.debug("search failed: %s", reason)
    return SearchResult(path=[], cost=math.inf, expanded=expanded, success=False, reason=reason)


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
        return _fail(f"start node {start} has been removed from the roadmap")
    goal_ids = goal_ids[node_valid[goal_ids]]
    if goal_ids.size == 0:
        return _fail("goal set is empty (or all goal nodes were removed)")
    goal_set = set(goal_ids.tolist())
    if start in goal_set:
        return SearchResult(path=[start], cost=0.0, expanded=1, success=True, reason="ok: start is a goal",
                            goal=start)
    if h_arr is not None and not np.isfinite(h_arr[start]):
        return _fail(f"no goal is reachable from start {start}: different connected component")
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
            return _fail("heap capacity exceeded by reopened nodes (inconsistent heuristic)", int(expanded))
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
            return _fail(f"expansion limit {max_expansions} reached", int(expanded))
        return _fail(f"no goal is reachable from start {start} (disconnected or all connecting edges invalid)",
                     int(expanded))
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


def warm_up() -> bool:
    """Compile, or load from numba's disk cache, the search kernels (A*, hop BFS, hop update after additions) on a
    four-node roadmap, so that the first real query does not pay for it. Returns whether the kernels are in use."""
    if not _compiled():
        return False
    g = Roadmap.from_edges(4, np.array([[0, 1], [1, 2]]), np.array([1.0, 1.0]))
    astar(g, 0, [2], heuristic="hop")  # bfs_hops + astar
    g.add_edges(np.array([2]), np.array([3]), np.array([1.0]))
    astar(g, 0, [2], heuristic="hop")  # cached hops updated after the addition: hops_decrease
    # a lazy search (its own writable copy of the weights: another signature than the roadmap's read-only view) whose
    # verification raises a weight: the forward search and the backward re-search
    lazy_astar(g, 0, [3], lambda e, path: EdgeCheck(weights={int(x): 2.0 for x in e}))
    nbr, _, deg = g.array_adjacency()
    table = np.empty((4, 4), dtype=np.uint8)
    search_kernels.kernels().hop_columns(nbr, deg, 4, 0, 4, table)  # a planner's hop table, and a query's counts
    search_kernels.kernels().query_hops(table, 3, nbr, deg, np.array([2]), np.array([3]), np.array([3]))
    return True


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


def _backward_search(graph: Roadmap, start: int, goal: int, w_arr: np.ndarray, first: tuple, decreased: float,
                     max_expansions: int | None) -> SearchResult:
    """A lazy search's re-search after a verification: A* from the goal back to the start, with the first (forward)
    search's costs as the heuristic.

    Under the first search's weights, its cost g1(x) of a closed node x is the cost from the start to x, and
    C1 - h1(x) a lower bound of it for the others (C1: the first path's cost; a node the first search did not close
    has g1(x) + h1(x) >= C1, with its consistent heuristic h1). Verification raises weights, rejects edges (inf) and
    may lower some, by ``decreased`` in total, which no path's cost can drop by more: the bound less ``decreased``
    (at least 0) stays admissible. While nothing went down it is also consistent (each part is, and across a
    closed-open edge it holds by the same two inequalities); otherwise the kernel reopens the nodes it improves.
    Either way the search is exact, and it expands little more than the nodes whose detour costs less than the
    verified path, where a forward re-search expands again the whole region the first one did."""
    g1, closed1, c1, h1 = first
    rows = g1.shape[0]
    h = np.zeros(rows) if h1 is None else h1
    if h.shape[0] < rows:
        h = np.concatenate([h, np.full(rows - h.shape[0], np.inf)])
    with np.errstate(invalid="ignore"):
        hb = np.maximum(np.where(closed1, g1, c1 - h[:rows]) - decreased, 0.0)
    back = _run_astar(graph, goal, np.asarray([start], dtype=np.int64), w_arr, None, hb, max_expansions)
    if back.success:
        back.path.reverse()
        back.edges.reverse()
        back.goal = goal
    back.g = back.closed = None
    return back


def _normalise_check(answer: EdgeCheck | Iterable[int] | None) -> EdgeCheck:
    if answer is None:
        return EdgeCheck()
    if isinstance(answer, EdgeCheck):
        return answer
    return EdgeCheck(invalid=[int(e) for e in answer])


def lazy_astar(
    graph: Roadmap,
    start: int,
    goals: int | Iterable[int] | np.ndarray,
    verify: VerifyCallback,
    weights: ArrayLike | None = None,
    heuristic: str = "hop",
    max_iterations: int = 1000,
    max_expansions: int | None = None,
    apply_to_graph: bool = False,
    backend: Backend = "auto",
    hops: np.ndarray | None = None,
) -> SearchResult:
    """Lazy A*: search, verify the unverified edges of the path, update, re-search until the path is verified.

    No re-search follows a verification that rejected no edge and changed only weights of the path itself, none of
    them upwards: the path is still optimal (any other path gains at most the decreases on the edges it shares).
    With the compiled kernels and one goal, the re-searches run from the goal back to the start with the first
    search's costs as their heuristic (:func:`_backward_search`): the same optimum, a few nodes expanded instead of
    the first search's region again.

    The replanner uses it to evaluate the edge perception score (Eq. 1, expensive: N interpolated configurations)
    and hence the final Eq. 2 weight only for edges on candidate paths; the unverified edges keep their current
    (e.g. optimistic, endpoint-only) weights.

    Parameters
    ----------
    graph : Roadmap
    start, goals :
        As in :func:`astar`.
    verify : callable ``(edge_ids: np.ndarray, path: list[int]) -> EdgeCheck | iterable of int | None``
        Called with the not-yet-verified edges of the current candidate path (in path order).  Returns the invalid
        edges (an iterable of ids, or :class:`EdgeCheck` which can also carry updated weights).  Every edge passed in
        counts as verified afterwards and is never passed again.
    weights : array-like, optional
        Initial weights (default: the roadmap's weights).  A private copy is updated; the roadmap is only modified
        when ``apply_to_graph`` is True.
    heuristic : {"hop", "exact", "zero"} or np.ndarray
        A per-node array is used as it is (it must stay consistent for the weights verification can give, e.g.
        :func:`motion_heuristic`, a bound that holds for any perception score). The hop heuristic stays consistent across iterations: invalid edges get weight ``inf`` (hop distances on the
        unchanged structure remain lower bounds) and :math:`c^{\\min}` (Eq. 4) is lowered when an update goes below it.
        ``exact`` uses the true cost-to-go of the current working weights (one compiled multi-source Dijkstra from the
        goals), recomputed only after a verified weight went down; A* then expands little more than the path.
    max_iterations : int
        Maximum number of searches.
    max_expansions : int, optional
        Per-search expansion limit.
    apply_to_graph : bool
        If True, remove the invalid edges from the roadmap and write the updated weights into it.
    backend : {"auto", "python"}
        As in :func:`astar`.
    hops : np.ndarray, optional
        ``(n_nodes,)`` hop counts to the goals to scale by :math:`c^{\min}` (Eq. 3) instead of the BFS of
        :func:`hop_distances`: any labelling that is 0 at the goals and changes by at most 1 along every edge of finite
        weight (a lower bound of the hop distance over those edges) keeps the heuristic consistent.

    Returns
    -------
    SearchResult
        Optimal path with respect to the final working weights (verified weights on the returned path, current
        weights elsewhere) avoiding every rejected edge; ``expanded`` sums all searches; ``iterations``,
        ``invalidated_edges``, ``updated_edges`` and ``verified_edges`` record the lazy evaluation.  If the
        unverified weights are lower bounds of the verified ones, the path is optimal for the verified weights.
    """
    start = int(start)
    if not 0 <= start < graph.n_nodes:
        raise InputError(f"start node {start} out of range [0, {graph.n_nodes})")
    goal_ids = _node_ids(graph, goals, "goal")
    w_arr = _weights_array(graph, weights).copy()
    w_list = None if _compiled(backend) else w_arr.tolist()
    verified = np.zeros(graph.n_edges, dtype=bool)
    invalidated: list[int] = []
    updated: dict[int, float] = {}
    checked: list[int] = []
    fixed_h = None
    if not isinstance(heuristic, str):  # a fixed per-node heuristic, consistent for every weight verification gives
        fixed_h = np.asarray(heuristic, dtype=np.float64).reshape(-1)
        if fixed_h.shape[0] != graph.n_nodes:
            raise InputError("heuristic array must have one entry per node slot")
        heuristic = "fixed"
    use_hop = heuristic == "hop"
    use_exact = heuristic == "exact"
    if heuristic not in ("hop", "exact", "zero", "none", "dijkstra", "fixed"):
        raise InputError("lazy_astar supports heuristic 'hop', 'exact', 'zero' or a per-node array")
    c_min = min_edge_cost(graph, w_arr) if use_hop else 0.0
    total_expanded = 0
    result = _fail("max_iterations is 0")
    h_arr = fixed_h
    h_cmin = None  # the c_min the hop heuristic was scaled with: hop distances found once stay lower bounds (the
    # structure only loses edges while the search runs), so the heuristic is only rescaled when c_min drops
    stale = True  # exact heuristic: recompute after a weight decreased (increases keep it a consistent lower bound)
    first = None  # the first search's (g, closed, cost, heuristic): the later ones run backwards, see _backward_search
    decreased = 0.0  # the verified weights' decreases since, summed (path costs dropped by at most that much)
    for it in range(1, max_iterations + 1):
        if use_hop and goal_ids.size:
            if h_cmin != c_min:
                if hops is None:
                    h_arr = hop_heuristic(graph, goal_ids, c_min=c_min)
                else:
                    h_arr = hops * (c_min * _CMIN_SAFETY) if c_min > 0 else np.where(np.isfinite(hops), 0.0, np.inf)
                h_cmin = c_min
        elif use_exact and goal_ids.size and stale:
            h_arr = dijkstra(graph, goal_ids, w_arr)[0]
            stale = False
        if first is not None:
            result = _backward_search(graph, start, int(goal_ids[0]), w_arr, first, decreased, max_expansions)
            if not result.success:  # the forward search is authoritative (and says why)
                result = _run_astar(graph, start, goal_ids, w_arr, w_list, h_arr, max_expansions)
        else:
            result = _run_astar(graph, start, goal_ids, w_arr, w_list, h_arr, max_expansions)
            if it == 1 and result.success and result.g is not None and goal_ids.size == 1:
                first = (result.g, result.closed, result.cost, h_arr)
        total_expanded += result.expanded
        result.expanded = total_expanded
        result.iterations = it
        if not result.success:
            break
        path_e = np.asarray(result.edges, dtype=np.int64)
        todo = path_e[~verified[path_e]] if path_e.size else path_e
        if todo.size == 0:
            result.reason = "ok" if it == 1 else f"ok after {it} lazy searches"
            break
        check = _normalise_check(verify(todo.copy(), list(result.path)))
        verified[todo] = True
        checked.extend(todo.tolist())
        # the path stays optimal, without another search, when no edge was rejected and the verification changed
        # only weights of this path, none of them upwards: any other path gains at most the decreases on the edges
        # it shares with this one
        on_path = set(todo.tolist())
        kept = not check.invalid
        for e, val in (check.weights or {}).items():
            e, val = int(e), float(val)
            if not (val >= 0):
                raise InputError(f"verified weight of edge {e} must be non-negative, got {val}")
            if val < w_arr[e]:
                stale = True
                decreased += float(w_arr[e]) - val
            if val > w_arr[e] or e not in on_path:
                kept = False
            w_arr[e] = val
            if w_list is not None:
                w_list[e] = val
            updated[e] = val
            if use_hop and val < c_min:
                c_min = val  # Eq. 4 over the updated weights: keeps Eqs. 5-6 valid
        for e in check.invalid:
            e = int(e)
            w_arr[e] = math.inf
            if w_list is not None:
                w_list[e] = math.inf
            invalidated.append(e)
            updated.pop(e, None)
        logger.debug("lazy A* iteration %d: %d edges verified, %d invalid", it, todo.size, len(check.invalid))
        if kept and not (~verified[path_e]).any():
            cost = 0.0
            for e in path_e.tolist():  # in path order, as the search accumulates it
                cost += float(w_arr[e])
            result.cost = cost
            result.reason = "ok" if it == 1 else f"ok after {it} lazy searches"
            break
    else:
        result = _fail(f"lazy A* did not converge in {max_iterations} iterations", total_expanded)
        result.iterations = max_iterations
    result.invalidated_edges = invalidated
    result.updated_edges = updated
    result.verified_edges = checked
    if apply_to_graph:
        if updated:
            ids = np.fromiter(updated.keys(), dtype=np.int64)
            graph.set_weights(ids, np.fromiter(updated.values(), dtype=np.float64))
        if invalidated:
            graph.remove_edges(invalidated)
    return result
