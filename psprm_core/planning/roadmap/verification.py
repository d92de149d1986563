"""Lazy verification (Lazy PRM): the edges a search wants to use are checked densely and get their Eq. 1 interior
scores when first used; colliding ones leave the roadmap."""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Optional

import numpy as np
import torch

from ...kernels import edges
from ..search.graph_search import EdgeCheck, edge_perception
from ..state import NP_DTYPE, PlannerContext, QueryContext
from .edges import SMALL_BATCH

if TYPE_CHECKING:
    from .edges import Edges
    from .knots import KnotStore
    from .roadmap_state import RoadmapState
    from .scoring import Scoring


class Verification:
    """Verifies the edges a lazy search wants to use."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, qc: QueryContext, edges: Edges,
                 scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.qc = qc
        self.edges = edges
        self.scoring = scoring

    def verify_edges(self, edge_ids: np.ndarray, path) -> "EdgeCheck":
        """Lazy evaluation of the edges a search wants to use: dense collision check (Lazy PRM) and the Eq. 1
        interior scores; colliding edges are invalidated, scored ones get their Eq. 2 weight."""
        g = self.rm.graph
        ver, chk = g.edge_attribute("verified"), g.edge_attribute("checked")
        todo = np.asarray([e for e in edge_ids if ver[e] < 0.5 or chk[e] < 0.5], dtype=np.int64)
        if len(todo) == 0:
            return EdgeCheck()
        fused = self.verify_compiled(todo)
        if fused is not None:
            return fused
        knots, interior = self.edges.stored_knots(todo)
        ok = torch.ones(len(todo), dtype=torch.bool, device=self.ctx.device)
        need = torch.as_tensor(chk[todo] < 0.5, device=self.ctx.device)
        if need.any():  # interior knots and the dense pieces between them (obstacles may have moved since build)
            ok[need] = self.edges.knots_valid(knots[need], dense=True)
        if self.qc.untracked and not bool(ok.all()):
            ok |= self.untracked_query_edges(todo, ok)
        return self.record(todo, ok.cpu().numpy(),
                           lambda m: self.scoring.stored_perception(todo[m]).double().cpu().numpy())

    def record(self, todo: np.ndarray, ok: np.ndarray, perception: Callable) -> EdgeCheck:
        """Write a verification of edges ``todo`` into the roadmap: all are checked now, the colliding ones (``ok``
        (E,) false) are removed, and those still to be scored get their Eq. 1 perception ``perception(mask)`` (of
        ``todo[mask]``) and Eq. 2 weight, which the search is told."""
        g = self.rm.graph
        ver = g.edge_attribute("verified")
        g.edge_attribute("checked")[todo] = 1.0
        invalid = todo[~ok]
        if len(invalid):
            g.remove_edges(invalid)
            rc = invalid[invalid < len(self.rm.recheck)]
            self.rm.blocked_edges.update(rc[self.rm.recheck[rc]].tolist())
        weights = {}
        score = (ver[todo] < 0.5) & ok
        if score.any():
            sel = todo[score]
            p = perception(score)
            g.edge_attribute("c_p")[sel] = p
            ver[sel] = 1.0
            w = self.scoring.weight(p, g.edge_attribute("c_m")[sel])
            weights = {int(e): float(x) for e, x in zip(sel, w)}
        return EdgeCheck(invalid=[int(e) for e in invalid], weights=weights)

    def verify_compiled(self, todo: np.ndarray) -> Optional[EdgeCheck]:
        """:meth:`verify_edges` of a search's few edges in one compiled call: the knots of the query's connection
        edges not computed yet, then the dense collision check, Eq. 1 camera poses and surrogate scores with occlusion
        (:func:`~psprm_core.kernels.edges.verify_edges`), with the same results; None when it does not apply (another
        scorer, a GPU, a large batch, the untracked fallback)."""
        g = self.rm.graph
        store = self.knots
        if (self.qc.untracked or len(todo) > SMALL_BATCH or not self.ctx.backend.fused or store.data is None
                or store.data.shape[1] <= 2 or not self.ctx.compute.takes(store.data[:1])):
            return None
        args = self.scoring.neural_args(self.ctx.dtype)
        if args is None:
            return None
        ver, chk = g.edge_attribute("verified"), g.edge_attribute("checked")
        compute = ~store.known(todo)
        rows = np.zeros(0, dtype=np.int64)
        if compute.any():
            pend = self.qc.pending_rows
            rows = np.asarray([pend.get(int(e), -1) for e in todo[compute]], dtype=np.int64)
            if (rows < 0).any():  # not a connection edge of this query: computed the step-by-step way first
                self.edges.stored_knots(todo[compute][rows < 0])
                compute = ~store.known(todo)
                rows = np.asarray([pend[int(e)] for e in todo[compute]], dtype=np.int64)
            hit = self.cached_query_knots(todo[compute], rows)
            if hit.any():
                compute = ~store.known(todo)
                rows = rows[~hit]
        store.reserve(int(todo.max()) + 1)
        _, ua, qa, qb = self.qc.pending_np if len(rows) else (None, rows, np.zeros((0, self.ctx.robot.dof)),
                                                              np.zeros((0, self.ctx.robot.dof)))
        cid = todo[compute]
        flip = g.edge_u[cid] != ua[rows]
        do_check, do_score = chk[todo] < 0.5, ver[todo] < 0.5
        batch = edges.EdgeBatch(todo, compute, np.ascontiguousarray(qa[rows]), np.ascontiguousarray(qb[rows]), flip,
                                do_check, do_score)
        ok, cams, raw = edges.verify_edges(self.ctx.edge_kit(), args, store.data.numpy(), store.interior.numpy(), batch,
                                           200)
        if len(cid):
            store.written(cid)
            self.cache_query_knots(cid, rows, flip)

        def perception(mask: np.ndarray) -> np.ndarray:  # Eq. 1 from the kernel's raw scores; camera poses kept
            self.knots.put_cams(todo[mask], cams[mask])
            # Scoring.normalized in the planner's dtype (numpy rounds like torch: a float32 array times a Python float
            # stays float32), Eq. 1 in numpy (its sum may round differently from torch's in the last bit)
            sc = raw[mask].astype(NP_DTYPE[self.ctx.dtype], copy=False) * self.rm.score_scale
            sc = np.clip(sc, 0.0, 1.0)
            return edge_perception(sc[:, 0], sc[:, -1], sc[:, 1:-1]).astype(np.float64)

        return self.record(todo, ok, perception)

    def cached_query_knots(self, eids: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Store the knots of the query's connection edges ``eids`` (rows ``rows`` of the pending ends) found in the
        query-knot cache (:meth:`~.edges.Edges.query_knots`); returns the (E,) hit flags."""
        cache = self.knots.query
        keys = self.pending_keys(rows)
        hit = np.asarray([k in cache for k in keys], dtype=bool)
        if hit.any():
            _, ua, _, _ = self.qc.pending_np
            kn = torch.stack([cache[k][0] for k, h in zip(keys, hit) if h])
            ki = torch.stack([cache[k][1] for k, h in zip(keys, hit) if h])
            self.edges.put_knots(eids[hit], ua[rows[hit]], kn, ki)
        return hit

    def cache_query_knots(self, eids: np.ndarray, rows: np.ndarray, flip: np.ndarray) -> None:
        """Keep the knots just computed for connection edges in the query-knot cache (in their ends' direction)."""
        cache = self.knots.query
        M = self.knots.data.shape[1]
        kn, ki = self.knots.data.numpy()[eids], self.knots.interior.numpy()[eids]  # copies (CPU store)
        if flip.any():
            kn[flip], ki[flip] = kn[flip, ::-1], (M - 1 - ki[flip])[:, ::-1]
        kn, ki = torch.from_numpy(kn), torch.from_numpy(ki)
        for j, key in enumerate(self.pending_keys(rows)):
            cache[key] = (kn[j], ki[j])
        self.knots.trim_query_cache()

    def pending_keys(self, rows: np.ndarray) -> list:
        """Query-knot cache keys (:meth:`~.edges.Edges.query_knots`) of pending connection edges (rows of the pending
        ends)."""
        (qa, qb), _, _, _ = self.qc.pending_np  # in the planner's dtype, as _query_knots keys them
        return [qa[i].tobytes() + qb[i].tobytes() for i in rows]

    def untracked_query_edges(self, edge_ids: np.ndarray, ok: torch.Tensor) -> torch.Tensor:
        """Fallback of a repaired query: its connection edges (an end is a start/goal node) whose re-aimed knots
        collide get their untracked knots (camera joints interpolated plainly, :meth:`~.edges.Edges.edge_knots` with
        ``track=False``), which replace the stored ones when they are collision-free (densely checked like every
        edge). Returns (E,) bool: the edges rescued this way (their Eq. 1 score is then recomputed from those knots).
        """
        g = self.rm.graph
        out = torch.zeros(len(edge_ids), dtype=torch.bool, device=self.ctx.device)
        mask = self.rm.roadmap_mask()
        ids = np.asarray(edge_ids, dtype=np.int64)
        query = ~(mask[g.edge_u[ids]] & mask[g.edge_v[ids]])
        cand = np.nonzero(~ok.cpu().numpy() & query)[0]
        if len(cand) == 0:
            return out
        e = ids[cand]
        qa, qb = self.ctx.t(g.configs[g.edge_u[e]]), self.ctx.t(g.configs[g.edge_v[e]])
        knots, interior = self.edges.edge_knots(qa, qb, track=False)
        free = self.edges.knots_valid(knots, dense=True)
        if free.any():
            fi = free.cpu().numpy()
            self.knots.put(e[fi], knots[free], interior[free])  # stored u -> v direction; camera poses reset
            g.edge_attribute("verified")[e[fi]] = 0.0  # score the new knots (Eq. 1) below
            out[torch.as_tensor(cand[fi], device=self.ctx.device)] = True
        return out
