"""Edges: knots of a local motion (differential-drive corners and the N Eq. 1 samples), re-aiming of the camera
joints at every interior knot (Alg. 1, line 7), dense collision checks between knots, and the knots kept in the knot
store, so that what is checked and scored is what runs."""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional, Protocol

import numpy as np
import torch

from ..state import PlannerContext, QueryContext

if TYPE_CHECKING:
    from .knots import KnotStore
    from .roadmap_state import RoadmapState


SMALL_BATCH = 64  # edges checked in one collision call (knots + dense pieces together) when verifying few edges


class KnotScorer(Protocol):
    """What :class:`Edges` uses of :class:`~.scoring.Scoring`: Eq. 1 of knots (:meth:`Edges.edges_valid` scores the
    edges it checks unless they are scored lazily). A protocol, not the class: ``scoring`` imports this module."""

    def knots_perception(self, knots: torch.Tensor, interior: torch.Tensor, cams: Optional[torch.Tensor] = None,
                         ends: Optional[tuple] = None) -> torch.Tensor: ...


class Edges:
    """Computes, checks and stores the knots of local motions."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, qc: QueryContext):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.qc = qc
        self.scoring: KnotScorer  # bound by bind_scoring: the scoring stage is made from this one

    def bind_scoring(self, scoring: KnotScorer) -> None:
        """The scoring stage (:class:`~.scoring.Scoring`), made from this one: edges and scoring use each other
        (scoring reads stored knots and motion distances, :meth:`edges_valid` scores the edges it checks).
        :class:`~.pipeline.Pipeline` binds it right after making both."""
        self.scoring = scoring

    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool = True) -> tuple:
        """Knots of the local motions qa -> qb (E, dof): (knots (E, M, dof), interior index (E, N)).

        The base follows its differential-drive path (rotate, translate, rotate); the knots are the endpoints, the
        two drive corners and the N Eq. 1 samples s = i / (N + 1), sorted along the motion, and at every interior
        knot the non-base camera joints are re-projected onto the visibility manifold (a few Newton steps from the
        interpolated value), so the camera keeps tracking the target along the edge. Consecutive knots always lie in
        the same drive phase, so joint-space interpolation between them is a motion the base can execute.

        ``track=False``: the *untracked* knots: the non-base joints are interpolated plainly (no re-aiming), i.e. the
        knots lie on the local motion itself (the fallback of connection edges whose re-aimed version collides, and
        the edges of the escape search).
        """
        return self.ctx.backend.edge_knots(qa, qb, track)

    def track_knots(self, knots: torch.Tensor) -> torch.Tensor:
        """Knots (E, M, dof) with the non-base camera joints of the interior ones re-projected onto the visibility
        manifold (``track_iters`` Gauss-Newton steps of Alg. 1, line 7, from the interpolated values)."""
        return self.ctx.backend.track_knots(knots)

    def query_knots(self, qa: torch.Tensor, qb: torch.Tensor) -> tuple:
        """:meth:`edge_knots` of start/goal query edges, cached by their end configurations (the cache is cleared
        with the knot store: new roadmap, new visibility focus). Misses are computed in one batch."""
        cache = self.knots.query
        A, B = qa.detach().cpu().numpy(), qb.detach().cpu().numpy()
        keys = [a.tobytes() + b.tobytes() for a, b in zip(A, B)]
        miss = [i for i, k in enumerate(keys) if k not in cache]
        if miss:
            kn, ki = self.edge_knots(qa[miss], qb[miss])
            for j, i in enumerate(miss):
                cache[keys[i]] = (kn[j], ki[j])
        out = (torch.stack([cache[k][0] for k in keys]), torch.stack([cache[k][1] for k in keys]))
        self.knots.trim_query_cache()
        return out

    def put_knots(self, edge_ids: np.ndarray, u_given: np.ndarray, knots: torch.Tensor,
                  interior: torch.Tensor) -> None:
        """Keep knots computed from ``u_given`` to the other end, flipped where the graph stores the edge the other
        way round (the roadmap keeps undirected edges as (min id, max id))."""
        edge_ids = np.asarray(edge_ids, dtype=np.int64)
        flip = torch.as_tensor(self.rm.graph.edge_u[edge_ids] != np.asarray(u_given), device=knots.device)
        M = knots.shape[1]
        knots = torch.where(flip[:, None, None], knots.flip(1), knots)
        interior = torch.where(flip[:, None], (M - 1 - interior).flip(1), interior)
        self.knots.put(edge_ids, knots, interior)

    def stored_knots(self, edge_ids: np.ndarray) -> torch.Tensor:
        """Knots (E, M, dof) and Eq. 1 sample positions (E, N) of graph edges in their stored u -> v direction,
        computed once and kept."""
        g = self.rm.graph
        edge_ids = np.asarray(edge_ids, dtype=np.int64)
        miss = edge_ids[~self.knots.known(edge_ids)]
        if len(miss) and self.qc.pending_knots is not None:  # the current query's own edges, from their ends
            peids, ua, qa, qb = self.qc.pending_knots
            sel = np.nonzero((peids[:, None] == miss[None, :]).any(1))[0]  # a few dozen x a few: cheaper than isin
            if len(sel):
                self.put_knots(peids[sel], ua[sel], *self.query_knots(qa[sel], qb[sel]))
                miss = edge_ids[~self.knots.known(edge_ids)]
        if len(miss):
            miss = np.unique(miss)
            qa, qb = self.ctx.t(g.configs[g.edge_u[miss]]), self.ctx.t(g.configs[g.edge_v[miss]])
            self.knots.put(miss, *self.edge_knots(qa, qb))
        return self.knots.get(edge_ids)

    def knots_valid(self, knots: torch.Tensor, dense: bool = True, check=None) -> torch.Tensor:
        """Collision-free flags (E,) of knot sequences: the interior knots, and with ``dense`` every
        ``edge_resolution`` between them (only for sequences whose knots are free); the end knots are the caller's.
        ``check``: the in-collision test of a batch of configurations (default the checker's ``check``, e.g.
        ``check_unpadded`` for the obstacles without the collision padding)."""
        check = check or self.ctx.checker.check
        E, M, dof = knots.shape
        if dense and E <= SMALL_BATCH and M > 2:
            # a few edges (a lazy search verifying its path): one checker call for the knots and the dense pieces,
            # since a call's fixed cost dominates at this size (large batches check the knots first, as a filter)
            inner = knots[:, 1:-1].reshape(-1, dof)
            a, b = knots[:, :-1].reshape(-1, dof), knots[:, 1:].reshape(-1, dof)
            seg, pts = self.pieces(a, b, max_steps=200, include_start=False)
            bad = check(torch.cat([inner, pts]))
            ok = ~bad[:len(inner)].reshape(E, M - 2).any(-1)
            seg_ok = torch.ones(len(a), dtype=torch.bool, device=a.device)
            seg_ok[seg[bad[len(inner):]]] = False
            return ok & seg_ok.reshape(E, M - 1).all(-1)
        ok = ~check(knots[:, 1:-1].reshape(-1, dof)).reshape(E, M - 2).any(-1) if M > 2 else \
            torch.ones(E, dtype=torch.bool, device=knots.device)
        if not dense or not ok.any():
            return ok
        idx = torch.nonzero(ok, as_tuple=True)[0]
        ok[idx] = self.dense_valid(knots[idx], check)
        return ok

    def dense_valid(self, knots: torch.Tensor, check=None) -> torch.Tensor:
        """Collision-free flags (E,) of the straight pieces between consecutive knots (endpoints excluded), by
        ``check`` (default the checker's ``check``)."""
        check = check or self.ctx.checker.check
        E, M, dof = knots.shape
        ok = torch.ones(E, dtype=torch.bool, device=knots.device)
        a, b = knots[:, :-1].reshape(-1, dof), knots[:, 1:].reshape(-1, dof)
        seg, pts = self.pieces(a, b, max_steps=200, include_start=False)
        if len(seg):
            bad = check(pts)
            seg_ok = torch.ones(len(a), dtype=torch.bool, device=a.device)
            seg_ok[seg[bad]] = False
            ok &= seg_ok.reshape(E, M - 1).all(-1)
        return ok

    def edges_valid(self, qa: torch.Tensor, qb: torch.Tensor, chunk: int = 4096,
                    end_scores: Optional[tuple] = None) -> tuple:
        """Valid flags (E,), Eq. 1 perception (E,) of local motions (NaN where invalid) and the knots of the valid
        ones (V, M, dof). ``end_scores``: raw scores (E,) of ``qa`` and ``qb`` when known (the roadmap's node
        scores), so that only the N interior samples of each edge are scored."""
        ok = torch.zeros(qa.shape[0], dtype=torch.bool, device=self.ctx.device)
        p = torch.full((qa.shape[0],), float("nan"), dtype=self.ctx.dtype, device=self.ctx.device)
        kept, kept_i = [], []
        for s0 in range(0, qa.shape[0], chunk):
            a, b = qa[s0:s0 + chunk], qb[s0:s0 + chunk]
            knots, interior = self.edge_knots(a, b)
            v = self.knots_valid(knots, dense=not self.ctx.settings.edges.lazy_collision)
            if self.ctx.settings.edges.edge_view_slack >= 0:
                inner = torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, knots.shape[-1]))
                seen = self.ctx.constraint.in_view(inner.reshape(-1, knots.shape[-1]),
                                                   slack=self.ctx.settings.edges.edge_view_slack)
                v &= seen.reshape(v.shape[0], -1).all(-1)
            ok[s0:s0 + chunk] = v
            kept.append(knots[v])
            kept_i.append(interior[v])
            if not self.ctx.settings.edges.lazy_edges and v.any():
                ends = None if end_scores is None else \
                    tuple(e[s0:s0 + chunk][v].to(self.ctx.device, self.ctx.dtype) for e in end_scores)
                p[s0:s0 + chunk][v] = self.scoring.knots_perception(knots[v], interior[v], ends=ends)
        dof = self.ctx.robot.dof
        if not kept:
            return ok, p, (torch.zeros(0, 2, dof, dtype=self.ctx.dtype, device=self.ctx.device),
                           torch.zeros(0, self.ctx.settings.edges.n_interp, dtype=torch.long, device=self.ctx.device))
        return ok, p, (torch.cat(kept), torch.cat(kept_i))

    def knots_free(self, knots: torch.Tensor) -> torch.Tensor:
        """Collision-free flags (E,) of the escape search's candidate edges, densely checked like
        :meth:`knots_valid`, but always the knots first: most candidates collide, and their few knots are cheap."""
        ok = self.knots_valid(knots, dense=False)
        if ok.any():
            idx = torch.nonzero(ok, as_tuple=True)[0]
            ok[idx] = self.dense_valid(knots[idx])
        return ok

    def motion_distance(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """:meth:`DiffDriveMotion.distance` of numpy batches (E, dof) in the planner's dtype, same dtype out."""
        if len(qa) == 0:
            return np.zeros(0, dtype=qa.dtype)
        return self.ctx.backend.motion_distance(qa, qb)

    def densify(self, W: torch.Tensor) -> torch.Tensor:
        """Configurations every ``edge_resolution`` along the piecewise-linear knot path ``W`` (K, dof)."""
        if len(W) < 2:
            return W
        _, pts = self.pieces(W[:-1], W[1:], max_steps=1000, include_start=True)
        return torch.cat([pts, W[-1:]])

    def pieces(self, a: torch.Tensor, b: torch.Tensor, max_steps: int, include_start: bool) -> tuple:
        """Points every ``edge_resolution`` on the straight pieces a[i] -> b[i] (theta interpolated the short way).

        Each piece is split into n = ceil(length / resolution) steps (at most ``max_steps``); the points are at
        fractions k / n for k = 0 .. n-1 (``include_start``) or k = 1 .. n-1. Returns (piece index, points).
        """
        return self.ctx.backend.pieces(a, b, max_steps, include_start)
