"""The roadmap and what is kept with it: node scores, the score scale of Eq. 1's normalisation, retired query nodes and
edges, nodes and edges blocked by moved obstacles, the hop table, the spatial index and tensor caches."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..search.graph import Roadmap
from ..search.search_types import _scipy_matrix
from ..state import NP_DTYPE, PlannerContext


class RoadmapState:
    """The roadmap graph of a planner (roadmap nodes and the current query's nodes and edges) and its bookkeeping."""

    def __init__(self, ctx: PlannerContext, knots=None):
        self.ctx = ctx
        self.knots = knots  # the KnotStore of the roadmap's edges (by edge id): told when edge slots are given back
        self.template = ctx.robot.default_configuration()  # joints that are not sampled (build() may override)
        self.stats: dict = {}
        self.escapes = 0  # escape searches run (their random streams)
        self.adopt(None, None)

    def adopt(self, graph: Optional[Roadmap], node_scores: Optional[np.ndarray], max_motion: float = 1.0,
              score_scale: float = 1.0, unverified: bool = False) -> None:
        """Take a new roadmap (built or loaded): every node slot of ``graph`` a roadmap node; the bookkeeping of the
        previous one is dropped."""
        self.graph = graph
        self.node_scores = node_scores  # per node slot (NaN for query nodes)
        # node slots that are roadmap nodes (not start/goal query nodes)
        self.is_roadmap = np.ones(0 if node_scores is None else len(node_scores), dtype=bool)
        self.max_motion = max_motion  # the longest roadmap edge's motion cost (c_m = motion / max_motion)
        self.score_scale = score_scale  # Eq. 1's normalisation: 1 / the 99th-percentile node score
        self.unverified = unverified  # some edges carry endpoint-only perception estimates (after rescore)
        self.dead_edges: list = []  # retired query edges and nodes, removed in batches by compact()
        self.dead_nodes: list = []
        # query repairs, the nodes they grew and kept, the failed (rolled back) repairs
        self.repairs, self.repair_added, self.repair_failed = 0, 0, 0
        self.blocked_nodes: set = set()  # roadmap nodes / edges removed because a moved obstacle blocked them
        self.blocked_edges: set = set()
        self.recheck = np.zeros(0, dtype=bool)  # edges unchecked because an obstacle moved near them
        self.hop_table: Optional[tuple] = None  # (roadmap node slots, (R, R) uint8 hop distances)
        self.index = None  # spatial index of roadmap nodes/edges (obstacle updates), built on first use
        self.tensor_key = None  # roadmap node tensor cache (tensor()): key, host copy, tensor, float64 copy
        self.tensor_numpy = self.tensor_cache = self.tensor_f64 = None
        self.node_cams_key = self.node_cams = None  # camera poses of the roadmap nodes (rescore)

    def components(self) -> tuple:
        """Connected components of the roadmap: (valid roadmap node ids, component label of each)."""
        from scipy.sparse.csgraph import connected_components

        ids = self.roadmap_node_ids()
        _, lab = connected_components(_scipy_matrix(self.graph, None), directed=False)
        return ids, lab[ids]

    def compact(self) -> None:
        """Remove the retired query nodes and edges from the graph (one adjacency rebuild for many queries), and give
        their slots back where they are the last ones (:meth:`~.graph.Roadmap.truncate`), so that a long-running
        planner's graph and per-edge stores (the knot store, the node scores, the re-check flags) keep the size of
        the roadmap and one batch of queries instead of growing with every query. A retired slot below a live one
        (a node a repair kept after it) stays allocated."""
        g = self.graph
        dead_e = np.asarray(self.dead_edges, dtype=np.int64)
        dead_n = np.asarray(self.dead_nodes, dtype=np.int64)
        if len(dead_e):
            g.remove_edges(dead_e)
        if len(dead_n):
            g.remove_nodes(dead_n)
            gone = np.zeros(g.n_nodes, dtype=bool)
            gone[dead_n] = True
            touching = np.flatnonzero(gone[g.edge_u] | gone[g.edge_v])  # every edge of a retired node, valid or not
            dead_e = np.concatenate([dead_e, touching])
        self.dead_edges, self.dead_nodes = [], []
        if not len(dead_n) and not len(dead_e):
            return
        n_keep = _kept_prefix(g.n_nodes, dead_n)
        e_keep = _kept_prefix(g.n_edges, dead_e)
        if n_keep == g.n_nodes and e_keep == g.n_edges:
            return
        g.truncate(n_keep, e_keep)
        if self.node_scores is not None and len(self.node_scores) > n_keep:
            self.node_scores[n_keep:] = np.nan
        self.recheck[e_keep:] = False
        if self.knots is not None:
            self.knots.forget_from(e_keep)

    @property
    def n_roadmap_nodes(self) -> int:
        """Number of roadmap node slots (valid or pruned; start/goal query nodes excluded)."""
        return int(self.is_roadmap.sum())

    def roadmap_mask(self) -> np.ndarray:
        """(n_node_slots,) bool: slot holds a roadmap node (valid or not), not a start/goal query node."""
        g = self.graph
        m = np.zeros(g.n_nodes, dtype=bool)
        m[: len(self.is_roadmap)] = self.is_roadmap
        return m

    def roadmap_node_ids(self) -> np.ndarray:
        """Ids of the valid roadmap nodes."""
        g = self.graph
        return np.nonzero(self.roadmap_mask() & g.node_valid[: g.n_nodes])[0]

    def path_roadmap_edges(self, path_nodes) -> np.ndarray:
        """Ids of the roadmap edges (between two roadmap nodes, not a query's own: no connection or shortcut edge)
        along a node path."""
        g, mask, retired = self.graph, self.roadmap_mask(), set(self.dead_edges)
        ids = [g.edge_id(int(a), int(b)) for a, b in zip(path_nodes[:-1], path_nodes[1:])
               if a < len(mask) and b < len(mask) and mask[a] and mask[b]]
        return np.asarray([e for e in ids if e is not None and e not in retired], dtype=np.int64)

    def roadmap_edge_ids(self) -> np.ndarray:
        """Ids of the valid edges between roadmap nodes (start/goal query edges excluded)."""
        g = self.graph
        e = g.valid_edge_ids()
        m = self.roadmap_mask()
        return e[m[g.edge_u[e]] & m[g.edge_v[e]]]

    def tensor(self, ids: np.ndarray) -> torch.Tensor:
        """Roadmap node configurations as a tensor on the planner's device (cached until the node set changes or a
        new roadmap is built or loaded)."""
        key = hash(ids.tobytes())
        if self.tensor_key != key:
            self.tensor_numpy = self.graph.configs[ids].astype(NP_DTYPE[self.ctx.dtype])  # the same values, host copy
            self.tensor_cache = torch.from_numpy(self.tensor_numpy).to(self.ctx.device)
            self.tensor_f64 = None  # float64 of the same values, made when first needed (Query.nearest_ids)
            self.tensor_key = key
        return self.tensor_cache

    def node_score_slots(self) -> np.ndarray:
        """The raw node scores, one per node slot (extended with NaN for slots added since, e.g. query nodes)."""
        g = self.graph
        if len(self.node_scores) < g.n_nodes:
            self.node_scores = np.concatenate([self.node_scores, np.full(g.n_nodes - len(self.node_scores), np.nan)])
        return self.node_scores


def _kept_prefix(n: int, retired: np.ndarray) -> int:
    """The slots ``0 .. k - 1`` to keep of ``n``: ``k`` is one past the last slot that is not in ``retired``."""
    dead = np.zeros(n, dtype=bool)
    retired = retired[(retired >= 0) & (retired < n)]
    dead[retired] = True
    live = np.nonzero(~dead)[0]
    return int(live[-1]) + 1 if len(live) else 0
