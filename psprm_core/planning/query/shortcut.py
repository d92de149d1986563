"""Perception-preserving shortcutting of a found path: a direct local motion replaces a stretch of the path only when
it is shorter, collision-free, stays on the visibility manifold and its Eq. 1 score is not lower."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from ...kernels.compute import bulk
from ..state import PlannerContext, QueryContext, ReadsQuerySettings

if TYPE_CHECKING:
    from ..roadmap.edges import Edges
    from ..roadmap.roadmap_state import RoadmapState
    from ..roadmap.scoring import Scoring


SHORTCUT_CANDIDATES = 8  # later path nodes a shortcut from one node tries at most (the farthest ones)


class QueryEdges(Protocol):
    """What :class:`Shortcut` uses of :class:`~.query.Query`: adding a query edge (a taken shortcut joins the
    query's edges). A protocol, not the class: ``query`` imports this module."""

    def add_query_edges(self, ua: np.ndarray, vb: np.ndarray, p: np.ndarray, dist: np.ndarray,
                        verified: bool = True) -> list: ...


class Shortcut(ReadsQuerySettings):
    """Shortcuts found paths without losing perception."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, qc: QueryContext, edges: Edges, scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.qc = qc
        self.edges = edges
        self.scoring = scoring
        self.query: QueryEdges  # bound by bind_query: the query stage is made from this one

    def bind_query(self, query: QueryEdges) -> None:
        """The query stage (:class:`~.query.Query`), made from this one: the query shortcuts the path it found
        (:meth:`shortcut_path`), and a shortcut taken joins the query's edges (:meth:`~.query.Query.add_query_edges`).
        :class:`~.pipeline.Pipeline` binds it right after making both."""
        self.query = query

    def shortcut_path(self, path: list, cost: float, added_edges: list) -> tuple:
        """Perception-preserving shortcuts of a found path (``shortcut_rounds`` greedy passes): from each kept node,
        the farthest later node (of the :data:`SHORTCUT_CANDIDATES` farthest within twice the roadmap's longest edge)
        joined by one direct local motion that is shorter than the stretch it replaces, is
        collision-free (checked densely, like every edge), keeps every interior knot on the visibility manifold
        (|h_M| within the projection tolerance after re-aiming) and whose Eq. 1 perception is at least the
        motion-weighted mean Eq. 1 perception of the replaced edges. The candidates of every node of the path are
        checked in one batch per pass (:meth:`_candidates`), then taken greedily from the start. The shortcut edges
        join the query's edges (``added_edges``) with their knots stored, so the path that runs is the one checked.
        Returns the new path and its cost."""
        g = self.rm.graph
        checked: dict = {}  # (node, node) -> what _candidates found for that motion (later passes reuse it)
        for _ in range(max(1, self.qs.query.shortcut_rounds)):
            path, changed = self._round(path, added_edges, checked)
            if not changed:
                break
        eids = g.edge_ids_of_path(path)
        return path, float(g.weights[eids].sum())

    def _candidates(self, path: list, checked: dict) -> tuple:
        """Every shortcut candidate of ``path`` (per node, the :data:`SHORTCUT_CANDIDATES` farthest later nodes
        within twice the roadmap's longest edge whose direct motion is shorter than the stretch it replaces, not
        already joined by an edge), checked in one batch: (from, to) path positions, motion costs, whether each is
        taken (on the manifold, collision-free, Eq. 1 not lower than the replaced edges' motion-weighted mean), and
        the Eq. 1 perception, knots and Eq. 1 sample positions of each. ``checked`` keeps each motion's check by its
        two nodes (a motion is checked once however many passes consider it)."""
        g = self.rm.graph
        tol = float(self.ctx.settings.projection.tolerance)
        eids = g.edge_ids_of_path(path)
        cm = g.edge_attribute("c_m")[eids] * self.rm.max_motion  # motion cost of each edge
        cp = g.edge_attribute("c_p")[eids]
        arc = np.concatenate([[0.0], np.cumsum(cm)])
        seen = np.concatenate([[0.0], np.cumsum(cm * np.nan_to_num(cp))])
        P = np.asarray(path)
        src, dst, dist, need = [], [], [], []
        I, J = np.triu_indices(len(path), 2)  # every (i, j) with j >= i + 2, by i then j
        D = self.edges.motion_distance(g.configs[P[I]], g.configs[P[J]]) if len(I) else np.zeros(0)
        for i in range(len(path) - 2):
            later, d = J[I == i], D[I == i]
            span = arc[later] - arc[i]
            # an existing edge between the two was the search's to take (and must not be overwritten)
            joined = np.asarray([g.edge_id(path[i], path[x]) is not None for x in later])
            cand = np.nonzero((d < span - 1e-9) & ~joined & (d <= 2 * self.rm.max_motion))[0][-SHORTCUT_CANDIDATES:]
            src.extend([i] * len(cand))
            dst.extend(later[cand].tolist())
            dist.append(d[cand])
            need.append((seen[later[cand]] - seen[i]) / np.maximum(span[cand], 1e-12))  # the replaced edges' mean
        src, dst = np.asarray(src, dtype=np.int64), np.asarray(dst, dtype=np.int64)
        if not len(src):
            return src, dst, None, np.zeros(0, bool), None, None, None
        dist, need = np.concatenate(dist), np.concatenate(need)
        keys = list(zip(P[src].tolist(), P[dst].tolist()))
        new = [k for k in dict.fromkeys(keys) if k not in checked]
        if new:
            a, b = np.asarray([k[0] for k in new]), np.asarray([k[1] for k in new])
            with bulk():  # a few hundred edges' knots and dense pieces: the compiled kernels at any size
                kn, ki = self.edges.edge_knots(self.ctx.t(g.configs[a]), self.ctx.t(g.configs[b]))
                M = kn.shape[1]
                on = self.ctx.constraint.error(kn[:, 1:-1].reshape(-1, kn.shape[-1])).reshape(len(new), M - 2)
                ok = (on <= tol).all(-1) if M > 2 else torch.ones(len(new), dtype=torch.bool)
                ok &= self.edges.knots_valid(kn, dense=True)
                p = torch.zeros(len(new), dtype=self.ctx.dtype, device=self.ctx.device)
                if ok.any():
                    p[ok] = self.scoring.knots_perception(kn[ok], ki[ok])
            for r, k in enumerate(new):
                checked[k] = (bool(ok[r]), p[r:r + 1], kn[r:r + 1], ki[r:r + 1])
        rows = [checked[k] for k in keys]
        ok = np.asarray([r[0] for r in rows])
        p, kn, ki = (torch.cat([r[j] for r in rows]) for j in (1, 2, 3))
        good = ok & (p.double().cpu().numpy() >= need - 1e-9)
        return src, dst, dist, good, p, kn, ki

    def _round(self, path: list, added_edges: list, checked: dict) -> tuple:
        """One greedy pass: from each kept node, the farthest taken candidate (:meth:`_candidates`), else the next
        node. Returns the new path and whether it changed."""
        src, dst, dist, good, p, kn, ki = self._candidates(path, checked)
        out, i, changed = [path[0]], 0, False
        while i < len(path) - 1:
            mine = np.nonzero((src == i) & good)[0]
            if len(mine):
                m = int(mine[np.argmax(dst[mine])])
                jj = int(dst[m])
                e = self.query.add_query_edges(np.asarray([path[i]]), np.asarray([path[jj]]),
                                               p[m:m + 1].cpu().numpy(), dist[m:m + 1])
                self.edges.put_knots(np.asarray(e), np.asarray([path[i]]), kn[m:m + 1], ki[m:m + 1])
                added_edges.extend(e)
                out.append(path[jj])
                i, changed = jj, True
                continue
            out.append(path[i + 1])
            i += 1
        return out, changed
