"""Tests of the roadmap graph and the searches (paper Eqs. 1-6).

Run ``python tests/test_graph_search.py`` for the query-time micro-benchmark (not a test).
"""

from __future__ import annotations

import heapq
import math
import statistics
import time
from contextlib import nullcontext
from typing import Any
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from psprm_core.planning.search import search_kernels
from psprm_core.planning.search.graph import Roadmap
from psprm_core.planning.search.graph_search import (
    EdgeCheck,
    astar,
    combined_weight,
    dijkstra,
    edge_perception,
    heuristic_consistency_gap,
    hop_distances,
    hop_heuristic,
    lazy_astar,
    min_edge_cost,
    path_cost,
)

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
BACKENDS = pytest.mark.parametrize("compiled", [True, False], ids=["numba", "python"])


def backend(compiled: bool) -> Any:
    """Run the block with the numba kernels (default) or with the pure-Python fallback (numba 'missing')."""
    return nullcontext() if compiled else mock.patch.object(search_kernels, "available", lambda: False)


def assert_adjacency_matches(g: Roadmap) -> None:
    """The cached Python lists and the padded arrays hold exactly the valid edges of every node (order aside)."""
    nbrs, eids = g.python_adjacency()
    nbr, eid, deg = g.array_adjacency()
    assert deg.shape[0] >= g.n_nodes and not deg[g.n_nodes:].any()
    for u in range(g.n_nodes):
        inc = sorted(g.incident_edges([u]).tolist())
        assert sorted(eids[u]) == inc and sorted(eid[u, : deg[u]].tolist()) == inc
        assert (eid[u, deg[u]:] == -1).all()
        other = {e: int(g.edge_v[e] if g.edge_u[e] == u else g.edge_u[e]) for e in inc}
        assert sorted(nbrs[u]) == sorted(other[e] for e in eids[u])
        assert nbr[u, : deg[u]].tolist() == [other[e] for e in eid[u, : deg[u]].tolist()]


# ---------------------------------------------------------------------------- reference implementation
def reference_dijkstra(n: int, edges: list[tuple[int, int, float]], sources: list[int]) -> list[float]:
    """Textbook multi-source Dijkstra on an explicit undirected edge list (independent of Roadmap/scipy)."""
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for a, b, w in edges:
        if math.isfinite(w):
            adj[a].append((b, w))
            adj[b].append((a, w))
    dist = [math.inf] * n
    heap = []
    for s in sources:
        dist[s] = 0.0
        heap.append((0.0, s))
    heapq.heapify(heap)
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for v, w in adj[u]:
            if d + w < dist[v]:
                dist[v] = d + w
                heapq.heappush(heap, (d + w, v))
    return dist


def valid_edge_list(g: Roadmap, w: np.ndarray | None = None) -> list[tuple[int, int, float]]:
    w = np.asarray(g.weights) if w is None else w
    ids = g.valid_edge_ids()
    return list(zip(np.asarray(g.edge_u)[ids].tolist(), np.asarray(g.edge_v)[ids].tolist(), w[ids].tolist()))


def assert_valid_path(g: Roadmap, res: Any, start: int, goals: set[int], w: np.ndarray | None = None) -> None:
    assert res.success, res.reason
    assert res.path[0] == start and res.path[-1] in goals and res.goal == res.path[-1]
    assert len(res.edges) == len(res.path) - 1
    for a, b, e in zip(res.path[:-1], res.path[1:], res.edges):
        assert g.edge_id(a, b) == e and g.edge_valid[e]
    assert abs(path_cost(g, res.path, w) - res.cost) <= 1e-9 * max(1.0, res.cost)


# ---------------------------------------------------------------------------- strategies
weight_st = st.one_of(st.just(0.0), st.floats(0.0, 10.0, allow_nan=False), st.sampled_from([0.5, 1.0, 2.0]))


@st.composite
def random_graphs(draw: Any, positive: bool = False) -> dict[str, Any]:
    """Random roadmap: random size, possibly disconnected, zero weights (unless ``positive``), removed edges/nodes,
    multiple goals."""
    n = draw(st.integers(1, 28))
    max_e = n * (n - 1) // 2
    pairs = draw(
        st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=min(max_e * 2, 90))
    )
    pairs = [(a, b) for a, b in pairs if a != b]
    if positive:  # strictly positive weights in [lo, lo * spread]: c_min > 0, so the hop heuristic (hops * c_min,
        # Eq. 3) is not identically 0, and nearly uniform weights (small spread) make it tight
        lo = draw(st.floats(0.25, 2.0))
        spread = draw(st.sampled_from([1.0, 1.1, 1.5, 3.0, 10.0]))
        weights = draw(st.lists(st.floats(lo, lo * spread), min_size=len(pairs), max_size=len(pairs)))
    else:
        weights = draw(st.lists(weight_st, min_size=len(pairs), max_size=len(pairs)))
    g = Roadmap.from_edges(n, np.asarray(pairs, dtype=np.int64).reshape(-1, 2), np.asarray(weights, dtype=float))
    if g.n_edges and draw(st.booleans()):
        g.remove_edges(draw(st.lists(st.integers(0, g.n_edges - 1), max_size=5)))
    if n > 2 and draw(st.booleans()):
        g.remove_nodes(draw(st.lists(st.integers(0, n - 1), max_size=2)))
    start = draw(st.integers(0, n - 1))
    goals = draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=4))
    return {"g": g, "start": start, "goals": goals}


# ---------------------------------------------------------------------------- property tests
@SETTINGS
@given(random_graphs(positive=True))
def test_astar_hop_matches_dijkstra(case: dict[str, Any]) -> None:
    """Positive weights: the hop heuristic hops * c_min is nonzero away from the goals, so A* prunes."""
    g, start, goals = case["g"], case["start"], case["goals"]
    valid_goals = [q for q in goals if g.node_valid[q]]
    res = astar(g, start, goals, heuristic="hop")
    if not g.node_valid[start] or not valid_goals:
        assert not res.success and res.reason
        return
    ref = reference_dijkstra(g.n_nodes, valid_edge_list(g), valid_goals)[start]
    if math.isfinite(ref) and ref > 0:  # precondition: the heuristic is informative at the start
        assert hop_heuristic(g, valid_goals)[start] > 0
    sp_dist, sp_parent = dijkstra(g, valid_goals)
    if math.isinf(ref):
        assert not res.success and "reachable" in res.reason and res.path == [] and math.isinf(res.cost)
        assert math.isinf(sp_dist[start])
        return
    assert_valid_path(g, res, start, set(valid_goals))
    assert abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
    assert abs(sp_dist[start] - ref) <= 1e-9 * max(1.0, ref)
    # Dijkstra parent chain leads to a goal with the same cost.
    node, acc = start, 0.0
    while sp_parent[node] >= 0:
        acc += g.weights[g.edge_id(node, sp_parent[node])]
        node = int(sp_parent[node])
    assert node in valid_goals and abs(acc - ref) <= 1e-9 * max(1.0, ref)
    res0 = astar(g, start, goals, heuristic="zero")
    assert abs(res0.cost - ref) <= 1e-9 * max(1.0, ref)
    # a consistent heuristic only expands nodes no farther from the start than the optimal cost (f = g + h <= C*
    # with h >= 0), and no node twice: bounded by the reference's count of such nodes, and never more than Dijkstra
    from_start = reference_dijkstra(g.n_nodes, valid_edge_list(g), [start])
    within = sum(d <= ref + 1e-9 * max(1.0, ref) for d in from_start)
    assert 1 <= res.expanded <= within and res0.expanded <= within
    assert res.expanded <= res0.expanded + 1  # (the goal itself may be popped at a tie)
    # the numba kernel and the reference heapq loop expand in the same order (ties broken by node id)
    for h in ("hop", "zero"):
        a, b = astar(g, start, goals, heuristic=h), astar(g, start, goals, heuristic=h, backend="python")
        assert (a.path, a.edges, a.expanded) == (b.path, b.edges, b.expanded) and a.cost == b.cost


@SETTINGS
@given(random_graphs())
def test_hop_heuristic_is_consistent(case: dict[str, Any]) -> None:
    g, goals = case["g"], [q for q in case["goals"] if case["g"].node_valid[q]]
    h = hop_heuristic(g, goals)
    assert heuristic_consistency_gap(g, h) <= 0.0  # Eqs. 5-6, exactly (c_min carries a 1e-12 safety shrink)
    hops = hop_distances(g, goals)
    for q in goals:
        assert hops[q] == 0 and h[q] == 0
    # Eq. 3 admissibility: h <= true optimal cost to go.
    true = reference_dijkstra(g.n_nodes, valid_edge_list(g), goals) if goals else [math.inf] * g.n_nodes
    for q in range(g.n_nodes):
        if math.isfinite(true[q]):
            assert h[q] <= true[q] + 1e-12
        else:
            assert math.isinf(h[q]) or not g.node_valid[q]


@BACKENDS
@SETTINGS
@given(random_graphs(), st.data())
def test_graph_additions_after_cached_search(compiled: bool, case: dict[str, Any], data: Any) -> None:
    """Adding nodes/edges after a search (start/goal connection) keeps searches exact (incremental adjacency)."""
    with backend(compiled):
        _additions_after_cached_search(case, data)
    assert_adjacency_matches(case["g"])


def _additions_after_cached_search(case: dict[str, Any], data: Any) -> None:
    g, start, goals = case["g"], case["start"], case["goals"]
    astar(g, start, goals)
    hop_distances(g, [q for q in goals if g.node_valid[q]])  # cached, then updated incrementally below
    new = g.add_node()
    k = data.draw(st.integers(0, 4))
    others = [int(x) for x in g.valid_node_ids() if x != new]
    nb = data.draw(st.lists(st.sampled_from(others), max_size=k, unique=True)) if others else []
    ws = data.draw(st.lists(weight_st, min_size=len(nb), max_size=len(nb)))
    if nb:
        g.add_edges([new] * len(nb), nb, ws)
    if len(others) > 1:  # repair edges between existing nodes
        extra = data.draw(st.lists(st.tuples(st.sampled_from(others), st.sampled_from(others)), max_size=3))
        extra = [(a, b) for a, b in extra if a != b]
        if extra:
            g.add_edges([a for a, _ in extra], [b for _, b in extra], data.draw(weight_st))
    valid_goals = [q for q in goals if g.node_valid[q]]
    if not valid_goals:
        return
    res = astar(g, new, valid_goals)
    ref = reference_dijkstra(g.n_nodes, valid_edge_list(g), valid_goals)[new]
    if math.isinf(ref):
        assert not res.success
    else:
        assert_valid_path(g, res, new, set(valid_goals))
        assert abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
    np.testing.assert_array_equal(hop_distances(g, valid_goals), hop_distances(g, valid_goals, use_cache=False))
    assert heuristic_consistency_gap(g, hop_heuristic(g, valid_goals)) <= 0.0


@BACKENDS
@SETTINGS
@given(random_graphs(), st.data())
def test_removals_and_restorations_after_cached_search(compiled: bool, case: dict[str, Any], data: Any) -> None:
    """Pruning and restoring edges/nodes after a search (a moving obstacle) patches the cached adjacency in place and
    keeps the cached hop heuristic admissible and consistent on the remaining edges, so A* stays exact."""
    with backend(compiled):
        _removals_after_cached_search(case, data)


def _removals_after_cached_search(case: dict[str, Any], data: Any) -> None:
    g, start, goals = case["g"], case["start"], case["goals"]
    astar(g, start, goals)  # caches adjacency and hop distances
    g.array_adjacency()
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["remove_edges", "remove_nodes", "restore_edges", "restore_nodes"]))
        if op.endswith("edges") and g.n_edges:
            getattr(g, op)(data.draw(st.lists(st.integers(0, g.n_edges - 1), max_size=6)))
        elif op.endswith("nodes"):
            getattr(g, op)(data.draw(st.lists(st.integers(0, g.n_nodes - 1), max_size=2)))
        valid_goals = [q for q in goals if g.node_valid[q]]
        assert_adjacency_matches(g)  # the patched lists and arrays hold exactly the valid edges
        if not valid_goals or not g.node_valid[start]:
            continue
        h = hop_heuristic(g, valid_goals)
        assert heuristic_consistency_gap(g, h) <= 0.0
        true = reference_dijkstra(g.n_nodes, valid_edge_list(g), valid_goals)
        fresh = hop_distances(g, valid_goals, use_cache=False)
        assert np.all(hop_distances(g, valid_goals) <= fresh)  # lower bounds of the true hop distances
        for q in range(g.n_nodes):
            assert h[q] <= true[q] + 1e-12 or not g.node_valid[q]
        res = astar(g, start, valid_goals)
        if math.isinf(true[start]):
            assert not res.success
        else:
            assert_valid_path(g, res, start, set(valid_goals))
            assert abs(res.cost - true[start]) <= 1e-9 * max(1.0, true[start])


@pytest.mark.parametrize("search_backend", ["auto", "python"])
@SETTINGS
@given(random_graphs(), st.data())
def test_lazy_astar_avoids_invalid_edges_and_is_optimal(search_backend: str, case: dict[str, Any], data: Any) -> None:
    g, start, goals = case["g"], case["start"], case["goals"]
    valid_goals = [q for q in goals if g.node_valid[q]]
    if not g.node_valid[start] or not valid_goals:
        return
    ne = g.n_edges
    bad = set(data.draw(st.lists(st.integers(0, max(ne - 1, 0)), max_size=ne))) if ne else set()
    extra = np.asarray(data.draw(st.lists(weight_st, min_size=ne, max_size=ne)), dtype=float)
    w0 = np.asarray(g.weights).copy()
    true_w = w0 + extra  # verified weights are >= the optimistic initial ones
    calls: list[list[int]] = []

    def verify(edge_ids: np.ndarray, path: list[int]) -> EdgeCheck:
        ids = edge_ids.tolist()
        assert not set(ids) & {e for c in calls for e in c}, "an edge was verified twice"
        calls.append(ids)
        return EdgeCheck(invalid=[e for e in ids if e in bad], weights={e: true_w[e] for e in ids if e not in bad})

    res = lazy_astar(g, start, goals, verify, backend=search_backend)
    final_w = true_w.copy()
    final_w[list(bad)] = np.inf
    ref = reference_dijkstra(g.n_nodes, valid_edge_list(g, final_w), valid_goals)[start]
    if math.isinf(ref):
        assert not res.success and res.reason
    else:
        assert_valid_path(g, res, start, set(valid_goals), final_w)
        assert not set(res.edges) & bad
        assert abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
        assert set(res.edges) <= set(res.verified_edges)
    assert set(res.invalidated_edges) <= bad
    np.testing.assert_array_equal(np.asarray(g.weights), w0)  # apply_to_graph=False leaves the roadmap alone


@SETTINGS
@given(random_graphs(), st.data())
def test_lazy_astar_optimal_for_working_weights_when_verification_lowers_them(case: dict[str, Any],
                                                                             data: Any) -> None:
    """Verified weights may also go down (an edge's interior scores beat its endpoint estimate). The result is
    optimal for the working weights (verified where verified, the estimate elsewhere, rejected edges removed),
    including when the search stops without re-searching after a verification that only lowered its path's
    weights."""
    g, start, goals = case["g"], case["start"], case["goals"]
    valid_goals = [q for q in goals if g.node_valid[q]]
    if not g.node_valid[start] or not valid_goals:
        return
    ne = g.n_edges
    bad = set(data.draw(st.lists(st.integers(0, max(ne - 1, 0)), max_size=max(ne // 4, 1)))) if ne else set()
    scale = np.asarray(data.draw(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1.5, 3.0]), min_size=ne,
                                          max_size=ne)), dtype=float)
    w0 = np.asarray(g.weights).copy()
    true_w = w0 * scale

    def verify(edge_ids: np.ndarray, path: list[int]) -> EdgeCheck:
        ids = edge_ids.tolist()
        return EdgeCheck(invalid=[e for e in ids if e in bad], weights={e: true_w[e] for e in ids if e not in bad})

    res = lazy_astar(g, start, goals, verify)
    work = w0.copy()
    for e, val in res.updated_edges.items():
        work[e] = val
    work[res.invalidated_edges] = np.inf
    ref = reference_dijkstra(g.n_nodes, valid_edge_list(g, work), valid_goals)[start]
    if math.isinf(ref):
        assert not res.success
    else:
        assert_valid_path(g, res, start, set(valid_goals), work)
        assert set(res.edges) <= set(res.verified_edges) and not set(res.edges) & bad
        assert abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
        assert abs(res.cost - sum(work[e] for e in res.edges)) <= 1e-9 * max(1.0, ref)


def test_lazy_astar_no_research_after_only_lower_weights() -> None:
    """A verification that rejects nothing and only lowers the path's weights ends the search (one search, not
    two); one that raises a weight is followed by another search, which may pick another path."""
    g = Roadmap.from_edges(4, np.array([[0, 1], [1, 3], [0, 2], [2, 3]]), np.array([1.0, 1.0, 1.2, 1.2]))
    lower = lazy_astar(g, 0, 3, lambda e, p: EdgeCheck(weights={int(x): 0.5 for x in e}))
    assert lower.success and lower.path == [0, 1, 3] and lower.iterations == 1 and lower.cost == 1.0
    higher = lazy_astar(g, 0, 3, lambda e, p: EdgeCheck(weights={int(x): 2.0 if x < 2 else 1.2 for x in e}))
    assert higher.success and higher.path == [0, 2, 3] and higher.iterations == 2
    assert higher.cost == pytest.approx(2.4)


# ---------------------------------------------------------------------------- unit tests
def _two_components() -> Roadmap:
    return Roadmap.from_edges(6, np.array([[0, 1], [1, 2], [3, 4], [4, 5]]), np.array([1.0, 1.0, 1.0, 1.0]))


def test_unreachable_returns_failure_not_exception() -> None:
    g = _two_components()
    res = astar(g, 0, [4, 5])
    assert not res.success and "component" in res.reason and res.path == [] and math.isinf(res.cost)
    assert not astar(g, 0, [4, 5], heuristic="zero").success
    assert not astar(g, 0, []).success
    g.remove_nodes([2])
    assert not astar(g, 0, [2]).success
    assert not astar(g, 2, [0]).success
    res = lazy_astar(g, 0, [1], lambda e, p: list(e))  # every edge rejected
    assert not res.success and res.invalidated_edges == [g.edge_id(0, 1)]


def test_goal_region_picks_cheapest_goal_and_zero_weights() -> None:
    # 0 -1- 1 -1- 2 (goal), 0 -0- 3 -0- 4 -5- 2, 4 is also a goal at cost 0
    g = Roadmap.from_edges(5, np.array([[0, 1], [1, 2], [0, 3], [3, 4], [4, 2]]), np.array([1, 1, 0, 0, 5.0]))
    res = astar(g, 0, [2, 4])
    assert res.success and res.goal == 4 and res.cost == 0.0 and res.path == [0, 3, 4]
    assert astar(g, 2, [2]).path == [2]


def test_roadmap_mutations() -> None:
    g = Roadmap(dof=2)
    ids = g.add_nodes(np.arange(8.0).reshape(4, 2))
    assert ids.tolist() == [0, 1, 2, 3]
    e = g.add_edges([0, 1, 2, 1], [1, 2, 3, 0], [1.0, 2.0, 3.0, 4.0])
    assert e.tolist() == [0, 1, 2, 0] and g.weights[0] == 4.0 and g.num_valid_edges == 3
    with pytest.raises(ValueError):
        g.add_edge(1, 1)
    with pytest.raises(ValueError):
        g.add_edge(0, 1, -1.0)
    assert astar(g, 0, 3).cost == 9.0
    g.set_weights([1], 0.5)
    assert astar(g, 0, 3).cost == 7.5
    removed = g.remove_nodes([1])
    assert set(removed.tolist()) == {0, 1} and g.edge_id(0, 1) is None
    assert not astar(g, 0, 3).success
    g.restore_nodes([1])
    assert g.restore_edges(removed).tolist() == [0, 1]
    assert astar(g, 0, 3).cost == 7.5
    s = g.add_node([0.5, 0.5])
    g.add_edge(s, 3, 0.25, c_m=0.1)
    g.add_edge(s, 0, 0.25)
    assert astar(g, 0, 3).path == [0, s, 3]
    assert g.edge_attribute("c_m")[g.edge_id(s, 3)] == pytest.approx(0.1)
    nb, eids = g.neighbors(s)
    assert sorted(nb.tolist()) == [0, 3] and g.degree()[s] == 2


def test_lazy_astar_updates_and_apply_to_graph() -> None:
    # Two routes 0-1-3 (cheap but 1-3 invalid) and 0-2-3.
    g = Roadmap.from_edges(4, np.array([[0, 1], [1, 3], [0, 2], [2, 3]]), np.array([0.1, 0.1, 0.5, 0.5]))
    bad = g.edge_id(1, 3)
    res = lazy_astar(g, 0, 3, lambda e, p: EdgeCheck(invalid=[x for x in e if x == bad],
                                                    weights={int(x): 0.6 for x in e if x != bad}),
                     apply_to_graph=True)
    assert res.success and res.path == [0, 2, 3] and res.iterations == 3 and res.cost == pytest.approx(1.2)
    assert g.edge_id(1, 3) is None and g.weights[g.edge_id(2, 3)] == pytest.approx(0.6)


def test_edge_weight_equations_numpy_and_torch() -> None:
    torch = pytest.importorskip("torch")
    su, sv = np.array([1.0, 0.0]), np.array([0.5, 0.0])
    interior = np.array([[0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
    cp = edge_perception(su, sv, interior)  # Eq. 1
    np.testing.assert_allclose(cp, [3.0 / 5.0, 1.0 / 5.0])
    np.testing.assert_allclose(edge_perception(su, sv, np.zeros((2, 0))), [0.75, 0.0])
    cpt = edge_perception(torch.tensor(su), torch.tensor(sv), torch.tensor(interior))
    assert isinstance(cpt, torch.Tensor) and np.allclose(cpt.numpy(), cp)
    cm = np.array([0.2, 1.0])
    w = combined_weight(cp, cm, 0.7)  # Eq. 2
    np.testing.assert_allclose(w, 1 - 0.7 * cp + 0.3 * cm)
    assert np.all((w >= 0) & (w <= 2))
    assert np.allclose(combined_weight(torch.tensor(cp), torch.tensor(cm), 0.7).numpy(), w)
    assert combined_weight(1.0, 0.0, 1.0) == 0.0
    with pytest.raises(ValueError):
        combined_weight(cp, cm, 1.5)


def test_min_edge_cost_and_hop_cache() -> None:
    g = _two_components()
    g.set_weights([2], 0.25)
    assert min_edge_cost(g) == 0.25  # Eq. 4
    h1 = hop_distances(g, [2])
    assert hop_distances(g, [2]) is h1  # cached per goal set
    np.testing.assert_array_equal(h1, [2, 1, 0, np.inf, np.inf, np.inf])
    g.add_edge(2, 3, 1.0)
    h2 = hop_distances(g, [2])  # structure changed: recomputed
    assert h2 is not h1 and h2[5] == 3


def test_benchmark_smoke() -> None:
    """The benchmark's times are milliseconds of this clock: half of each phase's queries took at least its median,
    and all four phases ran within the call."""
    t0 = time.perf_counter()
    stats = benchmark_query_time(n=400, k=8, n_queries=10)
    wall_ms = (time.perf_counter() - t0) * 1e3
    phases = ("median_ms", "median_new_goals_ms", "median_dijkstra_ms", "median_connect_ms")
    assert all(stats[k] > 0 for k in phases) and stats["median_ms"] <= stats["p90_ms"]
    assert 5 * sum(stats[k] for k in phases) <= wall_ms
    assert stats["median_expanded"] >= 1 and stats["n_edges"] >= 400


# ---------------------------------------------------------------------------- micro-benchmark (not a test)
def random_geometric_roadmap(n: int = 3000, k: int = 15, dim: int = 7, alpha: float = 0.5,
                             seed: int = 0) -> Roadmap:
    """kNN roadmap on uniform samples of [0, 1]^dim with Eq. 2 weights (random perception scores)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    x = rng.random((n, dim))
    _, idx = cKDTree(x).query(x, k + 1)
    u = np.repeat(np.arange(n), k)
    v = idx[:, 1:].reshape(-1)
    pairs = np.unique(np.stack([np.minimum(u, v), np.maximum(u, v)], axis=1), axis=0)
    c_m = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    c_m /= c_m.max()
    scores = rng.random(n)
    c_p = edge_perception(scores[pairs[:, 0]], scores[pairs[:, 1]], rng.random((len(pairs), 3)))
    return Roadmap.from_edges(n, pairs, combined_weight(c_p, c_m, alpha), configs=x)


def benchmark_query_time(n: int = 3000, k: int = 15, dim: int = 7, n_queries: int = 100, n_goals: int = 3,
                         seed: int = 0) -> dict[str, float]:
    """Median/p90 A* query times (ms) on a random geometric roadmap.

    ``median_ms``: hop-heuristic A* between roadmap nodes, same goal set (hop BFS cached);
    ``median_new_goals_ms``: a new random goal set for every query (hop BFS recomputed);
    ``median_connect_ms``: a new start node connected with k edges before every query (as the planner does), which
    changes the structure and thus recomputes the hop BFS; ``median_dijkstra_ms``: heuristic "zero".
    """
    g = random_geometric_roadmap(n, k, dim, seed=seed)
    rng = np.random.default_rng(seed + 1)
    goals = rng.choice(n, n_goals, replace=False)
    astar(g, 0, goals)  # warm caches (adjacency lists, weights list, hop BFS)

    def timed(fn: Any) -> tuple[float, int]:
        t0 = time.perf_counter()
        r = fn()
        return (time.perf_counter() - t0) * 1e3, r.expanded

    same = [timed(lambda: astar(g, int(rng.integers(n)), goals)) for _ in range(n_queries)]
    new_goals = [timed(lambda: astar(g, int(rng.integers(n)), rng.choice(n, n_goals, replace=False)))
                 for _ in range(n_queries)]
    zero = [timed(lambda: astar(g, int(rng.integers(n)), goals, heuristic="zero")) for _ in range(n_queries)]
    connect = []
    for _ in range(n_queries):
        t0 = time.perf_counter()
        s = g.add_node(rng.random(dim))
        d = np.linalg.norm(g.configs[:n] - g.configs[s], axis=1)
        nb = np.argsort(d)[:k]
        g.add_edges(np.full(k, s), nb, d[nb] / d[nb].max())
        astar(g, s, goals)
        connect.append(((time.perf_counter() - t0) * 1e3, 0))

    def med(xs: list[tuple[float, int]]) -> float:
        return statistics.median(t for t, _ in xs)

    return {
        "n_nodes": float(n),
        "n_edges": float(g.num_valid_edges),
        "median_ms": med(same),
        "p90_ms": float(np.percentile([t for t, _ in same], 90)),
        "median_expanded": statistics.median(e for _, e in same),
        "median_new_goals_ms": med(new_goals),
        "median_dijkstra_ms": med(zero),
        "median_connect_ms": med(connect),
    }


if __name__ == "__main__":
    for key, val in benchmark_query_time().items():
        print(f"{key:>22s}: {val:.3f}")


def _working_optimum(g: Roadmap, res, start: int, goal: int) -> tuple:
    """The working weights a lazy search ended with (verified where verified, rejected edges removed) and Dijkstra's
    optimal cost from ``start`` to ``goal`` under them."""
    work = np.asarray(g.weights).copy()
    for k, v in res.updated_edges.items():
        work[k] = v
    work[res.invalidated_edges] = np.inf
    return work, reference_dijkstra(g.n_nodes, valid_edge_list(g, work), [goal])[start]


def test_lazy_astar_searches_again_backwards_with_the_first_costs() -> None:
    """After a verification, the re-search runs from the goal back to the start with the first search's costs as its
    heuristic: the same optimal path as a fresh search, for a fraction of the expansions (a 30 x 30 grid with weights
    in [1, 1.5]: the hop heuristic is weak there), also when the verification lowers weights."""
    if not search_kernels.available():
        pytest.skip("numba not installed")
    n = 30
    ids = np.arange(n * n).reshape(n, n)
    e = np.concatenate([np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1),
                        np.stack([ids[:-1, :].ravel(), ids[1:, :].ravel()], 1)])
    rng = np.random.default_rng(0)
    g = Roadmap.from_edges(n * n, e, 1.0 + 0.5 * rng.random(len(e)))
    start, goal = int(ids[0, 0]), int(ids[-1, -1])
    fresh = astar(g, start, goal, heuristic="hop")
    first_edge = fresh.edges[0]
    blocked = fresh.edges[len(fresh.edges) // 2]

    def verify(edge_ids: np.ndarray, path: list[int]) -> EdgeCheck:  # the first edge costs more, one edge collides
        return EdgeCheck(invalid=[int(x) for x in edge_ids if x == blocked],
                         weights={int(x): float(g.weights[x]) + (0.3 if x == first_edge else 0.0)
                                  for x in edge_ids if x != blocked})

    res = lazy_astar(g, start, goal, verify, heuristic="hop")
    work, ref = _working_optimum(g, res, start, goal)
    assert res.success and res.iterations >= 2 and res.path[0] == start and res.path[-1] == goal
    assert abs(res.cost - ref) <= 1e-9 * ref and blocked not in res.edges
    assert abs(res.cost - sum(work[k] for k in res.edges)) <= 1e-9 * ref
    assert res.expanded - fresh.expanded < fresh.expanded / 2  # the later searches together: under half the first
    # a verification that lowers weights too (the first costs then bound the new ones only less the decrease: the
    # backward search reopens what it must) still ends on the optimum of the working weights
    for drop in (0.2, 0.9):
        def verify2(edge_ids: np.ndarray, path: list[int]) -> EdgeCheck:
            ids = [int(x) for x in edge_ids]
            return EdgeCheck(invalid=[x for x in ids if x == blocked],
                             weights={x: float(g.weights[x]) * (1 - drop if x % 3 == 0 else 1.3) for x in ids
                                      if x != blocked})

        res = lazy_astar(g, start, goal, verify2, heuristic="hop")
        work, ref = _working_optimum(g, res, start, goal)
        assert res.success and abs(res.cost - ref) <= 1e-9 * ref
        assert abs(res.cost - sum(work[k] for k in res.edges)) <= 1e-9 * ref


def test_warm_up_compiles_what_searches_call() -> None:
    """After the search warm-up, an A* on a roadmap's own weights and a lazy search that re-searches (its private,
    writable weights: another numba signature) compile nothing more (a first plan would otherwise pay ~1 s)."""
    if not search_kernels.available():
        pytest.skip("numba not installed")
    from psprm_core.planning.search.graph_search import warm_up

    warm_up()
    S = search_kernels.kernels()
    names = ("astar", "bfs_hops", "hops_decrease", "hop_columns", "query_hops")
    before = {n: len(getattr(S, n).signatures) for n in names}
    g = Roadmap.from_edges(6, np.array([[0, 1], [1, 2], [2, 5], [0, 3], [3, 4], [4, 5]]), np.ones(6))
    assert astar(g, 0, 5).success
    res = lazy_astar(g, 0, 5, lambda e, path: EdgeCheck(weights={int(x): 3.0 for x in e}))
    assert res.success and res.iterations >= 2
    assert {n: len(getattr(S, n).signatures) for n in names} == before


# ---------------------------------------------------------------------------- the motion-weighted objective
def test_motion_weighted_weight_formula():
    from psprm_core.planning.search.graph_search import edge_weight, motion_weighted

    p, cm = np.array([0.0, 0.5, 1.0, 0.25]), np.array([1.0, 0.4, 0.3, 0.0])
    for a in (0.0, 0.8, 1.0):
        expect = [c * ((1 - a) + a * (1 - q)) for q, c in zip(p, cm)]  # perception loss per unit of motion
        assert np.allclose(motion_weighted(p, cm, a), expect)
        assert np.allclose(edge_weight(p, cm, a, "motion"), expect)
        assert np.allclose(edge_weight(p, cm, a, "eq2"), [1 - a * q + (1 - a) * c for q, c in zip(p, cm)])
    with pytest.raises(ValueError, match="objective"):
        edge_weight(p, cm, 0.5, "hops")


@st.composite
def metric_graphs(draw: Any) -> dict[str, Any]:
    """Random points in the plane joined by edges whose motion is at least their distance (a detour factor >= 1),
    with random Eq. 1 scores, a start and a few goals."""
    n = draw(st.integers(2, 24))
    xy = np.asarray(draw(st.lists(st.tuples(st.floats(0, 10), st.floats(0, 10)), min_size=n, max_size=n)), float)
    pairs = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=80))
    pairs = sorted({(min(a, b), max(a, b)) for a, b in pairs if a != b})
    stretch = np.asarray(draw(st.lists(st.floats(1.0, 3.0), min_size=len(pairs), max_size=len(pairs))), float)
    p = np.asarray(draw(st.lists(st.floats(0.0, 1.0), min_size=len(pairs), max_size=len(pairs))), float)
    alpha = draw(st.sampled_from([0.0, 0.5, 0.8, 0.95, 1.0]))
    start = draw(st.integers(0, n - 1))
    goals = sorted(set(draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=3))))
    return {"xy": xy, "pairs": pairs, "stretch": stretch, "p": p, "alpha": alpha, "start": start, "goals": goals}


@SETTINGS
@given(metric_graphs())
def test_motion_heuristic_is_consistent_and_astar_optimal(case: dict[str, Any]) -> None:
    """The motion-weighted objective with the distance heuristic: consistent on every edge, and A* (plain and lazy,
    starting from optimistic weights) returns the cost of a textbook Dijkstra over the test's own weights."""
    from psprm_core.planning.search.graph_search import motion_heuristic, motion_weighted

    xy, pairs, a, scale = case["xy"], case["pairs"], case["alpha"], 2.5
    n = len(xy)
    if not pairs:
        return
    e = np.asarray(pairs, dtype=np.int64)
    motion = np.linalg.norm(xy[e[:, 0]] - xy[e[:, 1]], axis=1) * case["stretch"]
    w = [m / scale * ((1 - a) + a * (1 - q)) for m, q in zip(motion, case["p"])]  # the test's own formula
    assert np.allclose(motion_weighted(case["p"], motion / scale, a), w)
    g = Roadmap.from_edges(n, e, np.asarray(w))
    lb = np.min(np.linalg.norm(xy[:, None] - xy[case["goals"]][None], axis=-1), axis=1)
    h = motion_heuristic(lb, a, scale)
    assert heuristic_consistency_gap(g, h) <= 1e-12
    ref = reference_dijkstra(n, [(int(u), int(v), float(x)) for (u, v), x in zip(pairs, w)], case["goals"])
    ref = ref[case["start"]]
    for compiled in (True, False):
        with backend(compiled):
            res = astar(g, case["start"], case["goals"], heuristic=h)
            if math.isinf(ref):
                assert not res.success
                continue
            assert res.success and abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
            # lazy: the search starts from the optimistic weights of fully seen edges (p = 1, still >= the bound)
            low = Roadmap.from_edges(n, e, motion / scale * (1 - a))
            true_w = dict(enumerate(w))
            lazy = lazy_astar(low, case["start"], case["goals"],
                              lambda ids, path: EdgeCheck(weights={int(i): true_w[int(i)] for i in ids}), heuristic=h)
            assert lazy.success and abs(lazy.cost - ref) <= 1e-9 * max(1.0, ref)


@st.composite
def euclidean_graphs(draw: Any) -> dict[str, Any]:
    """Random points in the plane joined by edges weighing at least their length (a detour factor in [1, 3]), so the
    Euclidean distance to the nearest goal is an admissible, consistent and nonzero heuristic; removed edges, a
    start and a few goals."""
    n = draw(st.integers(2, 30))
    xy = np.asarray(draw(st.lists(st.tuples(st.floats(0, 10), st.floats(0, 10)), min_size=n, max_size=n)), float)
    # each point joined to its k nearest (a roadmap's neighbourhood), plus random long edges
    k = draw(st.integers(2, 5))
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    near = np.argsort(d, axis=1, kind="stable")[:, 1: k + 1]
    pairs = [(i, int(j)) for i in range(n) for j in near[i]]
    pairs += draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=10))
    pairs = sorted({(min(a, b), max(a, b)) for a, b in pairs if a != b})
    stretch = np.asarray(draw(st.lists(st.floats(1.0, 1.5), min_size=len(pairs), max_size=len(pairs))), float)
    e = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    w = np.linalg.norm(xy[e[:, 0]] - xy[e[:, 1]], axis=1) * stretch + 1e-3  # >= the straight-line distance
    g = Roadmap.from_edges(n, e, w)
    if g.n_edges and draw(st.booleans()):
        g.remove_edges(draw(st.lists(st.integers(0, g.n_edges - 1), max_size=4)))
    start = draw(st.integers(0, n - 1))
    goals = sorted(set(draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=3))))
    return {"g": g, "xy": xy, "start": start, "goals": goals}


@SETTINGS
@BACKENDS
@given(euclidean_graphs())
def test_astar_with_euclidean_heuristic_prunes_and_matches_dijkstra(compiled: bool, case: dict[str, Any]) -> None:
    """A* with a nonzero admissible, consistent heuristic (Euclidean distance to the nearest goal, the test's own)
    returns a valid path of the reference Dijkstra's cost, and expands only nodes with d(start, n) + h(n) <= C*
    (a consistent heuristic's bound: a search that ignored the heuristic would expand every node with
    d(start, n) <= C*)."""
    g, xy, start, goals = case["g"], case["xy"], case["start"], case["goals"]
    h = np.min(np.linalg.norm(xy[:, None] - xy[goals][None], axis=-1), axis=1)
    edges = valid_edge_list(g)
    for u, v, x in edges:  # consistency of the test's heuristic on every edge (a precondition)
        assert h[u] <= x + h[v] + 1e-9 and h[v] <= x + h[u] + 1e-9
    ref = reference_dijkstra(g.n_nodes, edges, goals)[start]
    with backend(compiled):
        res = astar(g, start, goals, heuristic=h)
        plain = astar(g, start, goals, heuristic="zero")
    if math.isinf(ref):
        assert not res.success
        return
    assert_valid_path(g, res, start, set(goals))
    assert abs(res.cost - ref) <= 1e-9 * max(1.0, ref)
    if h[start] == 0:  # the start is a goal or lies on one
        return
    from_start = reference_dijkstra(g.n_nodes, edges, [start])
    tol = 1e-9 * max(1.0, ref)
    bound = sum(d + h[q] <= ref + tol for q, d in enumerate(from_start))
    assert 1 <= res.expanded <= bound
    assert res.expanded <= plain.expanded + 1


@BACKENDS
def test_astar_with_euclidean_heuristic_expands_fewer_nodes_than_dijkstra(compiled: bool) -> None:
    """On a 21 x 21 grid (unit spacing, weights in [1, 1.2]) from its centre to a corner, the Euclidean heuristic
    confines A* to the nodes with d(start, n) + h(n) <= C* (the test's reference), well under half of what
    Dijkstra expands."""
    m = 21
    xy = np.asarray([(i, j) for i in range(m) for j in range(m)], float)
    pairs = [(i * m + j, i * m + j + 1) for i in range(m) for j in range(m - 1)]
    pairs += [(i * m + j, (i + 1) * m + j) for i in range(m - 1) for j in range(m)]
    w = np.random.default_rng(0).uniform(1.0, 1.2, len(pairs))
    g = Roadmap.from_edges(m * m, np.asarray(pairs, dtype=np.int64), w)
    start, goal = (m // 2) * m + m // 2, m * m - 1
    h = np.linalg.norm(xy - xy[goal], axis=1)
    edges = valid_edge_list(g)
    ref = reference_dijkstra(g.n_nodes, edges, [goal])[start]
    from_start = reference_dijkstra(g.n_nodes, edges, [start])
    bound = sum(d + h[q] <= ref + 1e-9 for q, d in enumerate(from_start))
    ball = sum(d <= ref + 1e-9 for d in from_start)
    assert bound < 0.5 * ball  # precondition: the heuristic can prune
    with backend(compiled):
        res = astar(g, start, [goal], heuristic=h)
        plain = astar(g, start, [goal], heuristic="zero")
    assert abs(res.cost - ref) <= 1e-9 * ref and abs(plain.cost - ref) <= 1e-9 * ref
    assert res.expanded <= bound < 0.5 * plain.expanded


# ---------------------------------------------------------------------------- the planner's search on a real roadmap
@pytest.mark.parametrize("objective", ["motion", "eq2"])  # auto heuristic: distance (motion), hop + hop table (eq2)
def test_planner_route_is_the_reference_shortest_path_on_a_real_roadmap(home_tv_planner, objective) -> None:
    """PS-PRM's query (its own heuristic, lazy collision checks, the hop table) returns, between two roadmap nodes,
    a route whose cost is the textbook Dijkstra optimum over the roadmap's own edge weights.

    Start and goal are the configurations of two roadmap nodes far apart, with ``connect_k = 1``: each end connects
    only to its own roadmap node (a zero-length motion), and no direct start-goal motion is tried, so the route's
    interior is a roadmap path between those nodes; its cost, summed by the test from the edge list, must equal the
    reference search over that edge list (read after the query: the lazy checks' verified weights and removed edges
    included)."""
    _, _, planner, _, _, _ = home_tv_planner(**{"roadmap.n_nodes": 400, "seed": 3, "scoring.objective": objective,
                                                "query.connect_k": 1, "query.shortcut": False})
    g = planner.graph
    ids = np.asarray(planner.roadmap_node_ids())
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(40):
        a, b = (int(x) for x in rng.choice(ids, 2, replace=False))
        if np.linalg.norm(g.configs[a, :2] - g.configs[b, :2]) < 4.5:  # more than 2 max_edge_length apart
            continue
        res = planner.plan(g.configs[a], g.configs[b][None], timing=False)
        # the reference: every valid roadmap edge of finite weight, after the query
        rm = set(ids.tolist())
        w = np.asarray(g.weights)
        edges = [(int(u), int(v), float(w[e])) for e, u, v in zip(range(g.n_edges), g.edge_u, g.edge_v)
                 if g.edge_valid[e] and math.isfinite(w[e]) and int(u) in rm and int(v) in rm]
        ref = reference_dijkstra(g.n_nodes, edges, [b])[a]
        if not math.isfinite(ref):
            assert not res.success
            continue
        assert res.success, res.reason
        interior = [int(n) for n in res.path_nodes[1:-1]]
        assert interior[0] == a and interior[-1] == b, res.path_nodes
        lookup = {(min(u, v), max(u, v)): x for u, v, x in edges}
        cost = sum(lookup[(min(u, v), max(u, v))] for u, v in zip(interior[:-1], interior[1:]))
        assert abs(cost - ref) <= 1e-6 * max(1.0, ref), (a, b, cost, ref)
        if objective == "motion":  # zero-length connections weigh 0: the reported cost is the route's
            assert abs(res.cost - ref) <= 1e-6 * max(1.0, ref)
        # the route is long enough for the heuristic to prune (more than one roadmap hop)
        assert len(interior) >= 3
        checked += 1
    assert checked >= 8
