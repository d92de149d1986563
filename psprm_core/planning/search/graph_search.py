"""Graph searches of the roadmap: Dijkstra, A* and lazy A* with the hop heuristic of Eqs. 3-6.

Dijkstra and A* (:func:`dijkstra`, :func:`astar`) are in :mod:`.astar_search`, the edge weights (Eq. 1
:func:`edge_perception`, Eq. 2 :func:`combined_weight`, the motion-weighted form) in :mod:`.objectives`, the hop
heuristic and its consistency check (Eqs. 3-6) in :mod:`.hops`, the search results and shared helpers (Eq. 4
:func:`min_edge_cost`) in :mod:`.search_types`; all are re-exported here. This module holds :func:`lazy_astar` and
the warm-up of the compiled search kernels.

:func:`lazy_astar` evaluates expensive edge data (perception scores of the interpolated configurations, collision
checks) only for edges on candidate paths: it searches, asks a callback to verify the unverified edges of the path,
applies the returned invalidations / weight updates and searches again until the returned path is fully verified.

A* and the hop BFS run as compiled numba kernels (:mod:`~psprm_core.planning.search.search_kernels`) over the cached
padded array adjacency of :class:`~psprm_core.planning.search.graph.Roadmap` (``backend="auto"``); ``backend="python"``
selects the reference pure-Python ``heapq`` loop over the per-node adjacency lists (same expansion order, ties broken by
node id). Both terminate at the first goal popped. The all-nodes :func:`dijkstra` uses ``scipy.sparse.csgraph``.
Unreachable goals give ``SearchResult(success=False, reason=...)``, never an exception.
"""

from __future__ import annotations

import logging
import math
from typing import Iterable

import numpy as np

from ...errors import InputError
from . import search_kernels
from .astar_search import _fail, _run_astar, astar, dijkstra
from .graph import Roadmap
from .hops import heuristic_consistency_gap, hop_distances, hop_heuristic
from ..objectives import (_CMIN_SAFETY, OBJECTIVES, combined_weight, edge_perception, edge_weight, motion_heuristic,
                          motion_weighted)
from ..results import Failure
from .search_types import (ArrayLike, Backend, EdgeCheck, SearchResult, VerifyCallback, _compiled, _node_ids,
                           _weights_array, min_edge_cost, path_cost)

logger = logging.getLogger(__name__)

__all__ = [
    "OBJECTIVES",
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
        :func:`motion_heuristic`, a bound that holds for any perception score). The hop heuristic stays consistent
        across iterations: invalid edges get weight ``inf`` (hop distances on the unchanged structure remain lower
        bounds) and :math:`c^{\\min}` (Eq. 4) is lowered when an update goes below it.
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
        ``(n_nodes,)`` hop counts to the goals to scale by :math:`c^{\\min}` (Eq. 3) instead of the BFS of
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
    result = _fail("max_iterations is 0", Failure.SEARCH_LIMIT)
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
        result = _fail(f"lazy A* did not converge in {max_iterations} iterations", Failure.SEARCH_LIMIT, total_expanded)
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
