"""The planner's hop table (Eq. 3 without a BFS per query): the multi-source bit-mask BFS gives the exact hop
distances, a query's hop counts are the hop distances over the edges it can use (lower bounds once edges are
removed), the heuristic stays consistent, the paths are those of the BFS heuristic, and a roadmap that grows drops
the table."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csr_array
from scipy.sparse.csgraph import shortest_path

from psprm_core.problems import random_problems
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.search import graph_search, search_kernels
from psprm_core.planning.search.graph import Roadmap
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.scene import load_scene

pytestmark = pytest.mark.skipif(not search_kernels.available(), reason="numba not installed")


def _hops(g: Roadmap, sources, finite_only: bool = True) -> np.ndarray:
    """Reference hop distances (n_sources, n_nodes) over the valid (finite-weight) edges."""
    e = g.valid_edge_ids()
    if finite_only:
        e = e[np.isfinite(g.weights[e])]
    n = g.n_nodes
    A = csr_array((np.ones(2 * len(e)), (np.r_[g.edge_u[e], g.edge_v[e]], np.r_[g.edge_v[e], g.edge_u[e]])),
                  shape=(n, n))
    return shortest_path(A, unweighted=True, indices=list(sources), directed=False)


def test_bit_mask_bfs_gives_every_hop_distance():
    """Random sparse graph with several components and more than 64 nodes (several source batches, split in
    uneven column ranges as the worker threads do): every entry is the hop distance, 255 where unreachable."""
    rng = np.random.default_rng(0)
    n = 150
    edges = {(int(a), int(b)) for a, b in rng.integers(0, 120, (260, 2)) if a != b}  # nodes 120.. stay isolated
    edges |= {(130, 131), (131, 132)}
    g = Roadmap.from_edges(n, np.array(sorted(edges)), np.ones(len(edges)))
    nbr, _, deg = g.array_adjacency()
    T = np.empty((n, n), dtype=np.uint8)
    K = search_kernels.kernels()
    for lo, hi in ((0, 70), (70, 71), (71, n)):
        K.hop_columns(nbr, deg, n, lo, hi, T)
    ref = _hops(g, range(n))
    assert np.array_equal(T == 255, ~np.isfinite(ref))
    assert np.array_equal(T[T != 255], ref[np.isfinite(ref)].astype(np.uint8))
    assert (T == T.T).all() and T[130, 132] == 2 and T[0, 130] == 255


def test_query_hop_counts_are_the_hop_distances_and_keep_the_paths(load_robot):
    """On a built roadmap, every query's hop counts from the table are the hop distances to its goal over the edges
    of finite weight (its own included, the retired queries' excluded), lower bounds of them once the searches have
    removed colliding edges, consistent along every finite edge; the paths and costs are those of the BFS
    heuristic. A roadmap that grows (a repair) drops the table; the queries then run the BFS."""
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot(scene.robot)
    target = scene.problems[0].target
    focus = scene.target(target).center
    settings = PSPRMSettings().changed({"roadmap.n_nodes": 500, "seed": 2, "recovery.query_repair_nodes": 0})
    a = PSPRM(robot, scene, GeometricScorer(scene, target, robot.config.intrinsics), focus, settings)
    stats = a.build()
    assert stats["success"] and a.pipeline.rm.hop_table is not None and stats["hop_table_s"] < stats["build_s"]
    R, T = a.pipeline.rm.hop_table
    assert T.shape == (R, R) and R == a.n_roadmap_nodes
    probs = random_problems(robot, scene, a.checker, 10, np.random.default_rng(3), robot.default_configuration(),
                            focus, aimed_only=True, aim_restarts=4)
    seen = []
    real = graph_search.lazy_astar

    def spy(g, start, goals, verify, **kw):
        hops = kw.get("hops")
        ref = _hops(g, goals).min(0)
        seen.append((hops is not None, np.array_equal(hops, ref, equal_nan=False) if hops is not None else False))
        assert hops is not None and (hops[np.isfinite(ref)] <= ref[np.isfinite(ref)]).all()
        assert np.isinf(hops[~np.isfinite(ref)]).sum() <= (~np.isfinite(ref)).sum()
        h = hops * graph_search.min_edge_cost(g)
        w = np.asarray(g.weights)
        assert graph_search.heuristic_consistency_gap(g, h, np.where(np.isfinite(w), w, np.inf)) <= 1e-9
        return real(g, start, goals, verify, **kw)

    import psprm_core.planning.query as P

    results = []
    P.lazy_astar = spy
    try:
        for start, goal in probs:
            results.append(a.plan(start, goal, timing=False))
    finally:
        P.lazy_astar = real
    assert seen and all(used for used, _ in seen)
    assert sum(exact for _, exact in seen) >= len(seen) // 2  # exact until edges are found colliding
    b = PSPRM(robot, scene, GeometricScorer(scene, target, robot.config.intrinsics), focus, settings)
    b.build()
    b.pipeline.rm.hop_table = None  # the BFS heuristic
    for (start, goal), ra in zip(probs, results):
        rb = b.plan(start, goal, timing=False)
        assert ra.success == rb.success
        if ra.success:
            assert ra.cost == pytest.approx(rb.cost, rel=1e-9, abs=1e-12)
    assert sum(r.success for r in results) >= len(results) // 2
    a.grow(20, center=probs[0][0][:3])
    assert a.pipeline.heuristics.query_hops([a.roadmap_node_ids()[0]], [0]) is None  # the roadmap grew: back to the BFS
