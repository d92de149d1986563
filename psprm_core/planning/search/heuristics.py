"""A* heuristics of a query: the hop heuristic h = H_min * c_min (Eqs. 3-6) from a precomputed hop table or a BFS, and
the motion lower bound of the motion-weighted objective."""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np
import torch

from ...kernels.runtime import worker_pool
from ..state import PlannerContext, QueryContext, ReadsQuerySettings
from . import search_kernels
from .graph_search import motion_heuristic

if TYPE_CHECKING:
    from ..roadmap.roadmap_state import RoadmapState


HOP_TABLE_MAX_NODES = 5000  # roadmaps up to this many nodes keep all their hop distances (uint8, 25 MB at most)


def resolve(settings) -> str:
    """The A* heuristic of ``settings``, with ``auto`` resolved (hop for Eq. 2, distance for the motion-weighted
    objective)."""
    if settings.query.heuristic == "auto":
        return "distance" if settings.scoring.objective == "motion" else "hop"
    return settings.query.heuristic


class Heuristics(ReadsQuerySettings):
    """Heuristics of the roadmap search (Eqs. 3-6) and the hop table."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, qc: QueryContext):
        self.ctx = ctx
        self.rm = rm
        self.qc = qc

    def build_hop_table(self) -> None:
        """Hop distances between all roadmap nodes (uint8, :data:`HOP_TABLE_MAX_NODES` nodes at most), one BFS per
        node on the bulk worker threads, so that a query gets the hop counts of Eq. 3 from the table rows of its
        goals' neighbours (:meth:`query_hops`) instead of a BFS over the whole roadmap. Kept while the roadmap only
        loses edges (the table's counts are then lower bounds, and the heuristic stays consistent); roadmap nodes
        added later (:meth:`~.builder.Builder.grow`) drop it, and queries go back to the BFS. Built when the
        planner's own heuristic is hop (a query that asks for hop otherwise runs the BFS)."""
        self.rm.hop_table = None
        R = len(self.rm.is_roadmap)
        if (self.rm.graph is None or not 2 <= R <= HOP_TABLE_MAX_NODES or resolve(self.ctx.settings) != "hop"
                or not search_kernels.available()):
            return
        nbr, _, deg = self.rm.graph.array_adjacency()
        T = np.empty((R, R), dtype=np.uint8)
        K = search_kernels.kernels()
        workers = max(1, min(torch.get_num_threads(), 8))
        step = 64 * max(1, -(-R // (64 * 2 * workers)))  # whole 64-source batches, two chunks per worker
        chunks = [(lo, min(lo + step, R)) for lo in range(0, R, step)]
        list(worker_pool(workers).map(lambda c: K.hop_columns(nbr, deg, R, c[0], c[1], T), chunks))
        self.rm.hop_table = (R, T)

    def query_hops(self, search_goals: Sequence[int], added_edges: Sequence[int]) -> Optional[np.ndarray]:
        """Hop counts (n_nodes,) to ``search_goals`` for Eq. 3 from the hop table: 0 at the goals, for a roadmap node
        1 + its table distance to the nearest roadmap neighbour of a goal-side query node (plus that node's own count),
        then lowered along the query's edges ``added_edges`` (FIFO label correcting, which the start's edges need).
        Over every edge of finite weight the counts change by at most 1 (table edges: the table's own distances,
        lower bounds once edges are removed; query edges: the correction), so the hop heuristic stays consistent; a
        retired query's edges (weight inf) are never relaxed by the search and may be ignored. None without a valid
        table (then the search runs the BFS)."""
        tab = self.rm.hop_table
        if tab is None or tab[0] != len(self.rm.is_roadmap) or not added_edges:
            return None
        R, T = tab
        g = self.rm.graph
        e = np.asarray(added_edges, dtype=np.int64)
        e = e[g.edge_valid[e] & np.isfinite(g.weights[e])]
        nbr, _, deg = g.array_adjacency()
        hops = search_kernels.kernels().query_hops(T, R, nbr, deg, np.ascontiguousarray(g.edge_u[e]),
                                                   np.ascontiguousarray(g.edge_v[e]),
                                                   np.asarray(search_goals, dtype=np.int64))
        return hops[: g.n_nodes]

    @property
    def name(self) -> str:
        """The A* heuristic queries use: the setting, with ``auto`` resolved (hop for Eq. 2, distance for the
        motion-weighted objective)."""
        return resolve(self.qs)

    def distance(self, goal_ids: Sequence[int], sink: Optional[int]) -> np.ndarray:
        """Per-node :func:`~.objectives.motion_heuristic` to the goals ``goal_ids``: (1 - alpha) times the motion
        lower bound |dxy| + ||d joints|| (every local motion costs at least that, :mod:`psprm_core.motion`) to the
        nearest goal, over the roadmap's longest edge; 0 at the virtual ``sink`` of a multi-goal query."""
        g = self.rm.graph
        Q = g.configs[: g.n_nodes]
        G = g.configs[np.asarray(goal_ids, dtype=np.int64)]
        lb = np.full(len(Q), np.inf)
        for q in G:
            if self.ctx.robot.mobile:
                d = np.linalg.norm(Q[:, :2] - q[:2], axis=1) + np.linalg.norm(Q[:, 3:] - q[3:], axis=1)
            else:
                d = np.linalg.norm(Q - q, axis=1)
            np.minimum(lb, d, out=lb)
        if sink is not None:
            lb[sink] = 0.0
        return motion_heuristic(lb, self.qs.scoring.alpha, self.rm.max_motion)
