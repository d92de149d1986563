"""Perception scores of configurations and edges: the scorer on FK camera poses, Eq. 1 (the mean normalised score
of both ends and the N interior samples of an edge) and the edge weight of the configured objective (Eq. 2 or
the motion-weighted form)."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from ...kernels import edges
from ..search.graph_search import edge_perception, edge_weight
from ..settings import ScoringSettings
from ..state import PlannerContext, QueryContext, ReadsQuerySettings

if TYPE_CHECKING:
    from .edges import Edges
    from .knots import KnotStore
    from .roadmap_state import RoadmapState


class Scoring(ReadsQuerySettings):
    """Scores configurations and edges (Eq. 1) and weights edges (Eq. 2 / motion-weighted)."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, qc: QueryContext, edges: Edges):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.qc = qc
        self.edges = edges

    def neural_args(self, dtype: torch.dtype) -> Optional[tuple]:
        """:func:`edges.neural_args` of the scorer, kept for the rest of a query (:meth:`~.query.Query.plan_once`
        clears them: the scorer does not change during a query, but may between queries)."""
        if self.qc.scorer_args is None:
            return edges.neural_args(self.ctx.scorer, dtype)
        if dtype not in self.qc.scorer_args:
            self.qc.scorer_args[dtype] = edges.neural_args(self.ctx.scorer, dtype)
        return self.qc.scorer_args[dtype]

    def query_scores(self, Q: np.ndarray) -> np.ndarray:
        """:meth:`score_configs` (float64 out) of a query's few configurations ``Q`` (numpy, planner's dtype)."""
        sc = self.ctx.backend.few_scores(Q, self.neural_args)
        if sc is not None:
            return sc.astype(np.float64)
        return self.score_configs(torch.from_numpy(Q).to(self.ctx.device)).double().cpu().numpy()

    def score_configs(self, q: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """Perception scores (B,) of configurations: FK -> camera poses -> scorer (a query's few configurations with
        a neural scorer: one compiled call, the same values)."""
        sc = self.ctx.backend.few_scores(q, self.neural_args)
        if sc is not None:
            return sc.to(self.ctx.dtype)
        out = []
        for s in range(0, q.shape[0], chunk):
            qc = q[s:s + chunk]
            out.append(self.ctx.scorer.score(self.ctx.robot.camera_poses(qc)).to(self.ctx.dtype))
        return torch.cat(out) if out else torch.zeros(0, dtype=self.ctx.dtype, device=self.ctx.device)

    def weight(self, p, c_m):
        """Edge weight of the configured objective (:func:`~.graph_search.edge_weight`): Eq. 2 or the motion-weighted
        form, from the Eq. 1 perception ``p`` and the normalised motion cost ``c_m`` (numpy or torch); the running
        query's alpha and objective (:attr:`~.state.ReadsQuerySettings.qs`), else the planner's."""
        return edge_weight(p, c_m, self.qs.scoring.alpha, self.qs.scoring.objective)

    def apply_weights(self, settings) -> None:
        """Weight every valid edge of finite weight from its stored Eq. 1 perception and motion cost with the alpha
        and objective of ``settings``; edges of infinite weight (a retired query's, blocked ones) stay so."""
        g = self.rm.graph
        ids = g.valid_edge_ids()
        ids = ids[np.isfinite(g.weights[ids])]
        g.set_weights(ids, self._weights_of(ids, settings))

    def _weights_of(self, ids: np.ndarray, settings) -> np.ndarray:
        g = self.rm.graph
        c_m = g.edge_attribute("c_m")[ids]
        if settings.scoring.objective == "eq2":
            c_m = np.clip(c_m, 0, 1)
        return edge_weight(g.edge_attribute("c_p")[ids], c_m, settings.scoring.alpha, settings.scoring.objective)

    @contextlib.contextmanager
    def weighted_for(self, settings, penalize: Optional[tuple] = None):
        """The roadmap weighted with the alpha and objective of ``settings`` inside the block (one search of route
        selection), the edges ``penalize[0]`` weighted ``penalize[1]`` times that, and the planner's weights after
        it: the saved weight of every edge the block left as it was, and the planner's weight of the edges the
        block verified and scored (Eq. 1) meanwhile; edges found colliding in the block stay removed."""
        g = self.rm.graph
        ids = g.valid_edge_ids()
        ids = ids[np.isfinite(g.weights[ids])]
        saved, c_p = g.weights[ids].copy(), g.edge_attribute("c_p")[ids].copy()
        w = self._weights_of(ids, settings)
        if penalize is not None and len(penalize[0]):
            w[np.isin(ids, penalize[0])] *= penalize[1]
        g.set_weights(ids, w)
        try:
            yield
        finally:
            keep = g.edge_valid[ids] & np.isfinite(g.weights[ids])
            ids, saved, c_p = ids[keep], saved[keep], c_p[keep]
            same = (g.edge_attribute("c_p")[ids] == c_p) | (np.isnan(c_p) & np.isnan(g.edge_attribute("c_p")[ids]))
            w = saved.copy()
            if not same.all():
                w[~same] = self._weights_of(ids[~same], self.qs)
            g.set_weights(ids, w)

    def route_perception(self, dense: np.ndarray, scores: np.ndarray) -> float:
        """Perception of a whole route: the motion-weighted mean normalised score c_p along its dense configurations
        ``dense`` (K, dof) with raw scores ``scores`` (K,) (Eq. 1's mean, taken over the route by motion, as a
        camera frame every so much motion sees it); the one configuration of a route that does not move: its c_p."""
        c = np.clip(np.asarray(scores, float) * self.rm.score_scale, 0.0, 1.0)
        if len(c) < 2:
            return float(c.mean()) if len(c) else float("nan")
        d = self.edges.motion_distance(np.asarray(dense[:-1]), np.asarray(dense[1:])).astype(np.float64)
        if d.sum() <= 0:
            return float(c.mean())
        return float(((c[:-1] + c[1:]) * 0.5 * d).sum() / d.sum())

    def normalized(self, scores: torch.Tensor) -> torch.Tensor:
        """Normalised perception score c_p in [0, 1] (scores divided by the roadmap's 99th-percentile node score)."""
        return (scores * self.rm.score_scale).clamp(0.0, 1.0)

    def eq1_cameras(self, knots: torch.Tensor, interior: torch.Tensor) -> torch.Tensor:
        """Camera poses (E, N + 2, 4, 4) of an edge's Eq. 1 points: both ends and the N interior samples."""
        E, M, dof = knots.shape
        n = interior.shape[1]
        pts = torch.cat([knots[:, :1], torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, dof)),
                         knots[:, -1:]], 1)
        return self.ctx.robot.camera_poses(pts.reshape(-1, dof)).reshape(E, n + 2, 4, 4)

    def knots_perception(self, knots: torch.Tensor, interior: torch.Tensor,
                         cams: Optional[torch.Tensor] = None, ends: Optional[tuple] = None) -> torch.Tensor:
        """Eq. 1 from knots (or their cached Eq. 1 camera poses): mean normalised score of both ends and the N
        interior samples. ``ends``: the raw scores (E,) of both ends when already known (only the interior samples
        are then scored)."""
        if ends is not None and cams is None:
            E, M, dof = knots.shape
            inner = torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, dof)).reshape(-1, dof)
            sc = self.ctx.scorer.score(self.ctx.robot.camera_poses(inner)).to(self.ctx.dtype).reshape(E, -1)
            return edge_perception(self.normalized(ends[0]), self.normalized(ends[1]), self.normalized(sc))
        if cams is None:
            cams = self.eq1_cameras(knots, interior)
        E, P = cams.shape[:2]
        sc = self.normalized(self.ctx.scorer.score(cams.reshape(-1, 4, 4)).to(self.ctx.dtype).reshape(E, P))
        return edge_perception(sc[:, 0], sc[:, -1], sc[:, 1:-1])

    def stored_perception(self, edge_ids: np.ndarray) -> torch.Tensor:
        """Eq. 1 of graph edges from their stored knots; camera poses are computed once and kept."""
        knots, interior = self.edges.stored_knots(edge_ids)
        have = self.knots.known_cams(edge_ids)
        if not have.all():
            miss = np.unique(np.asarray(edge_ids)[~have])
            k, i = self.knots.get(miss)
            self.knots.put_cams(miss, self.eq1_cameras(k, i))
        return self.knots_perception(knots, interior, cams=self.knots.cams[
            torch.as_tensor(np.asarray(edge_ids, dtype=np.int64), device=knots.device)])

    def reweight(self, alpha: Optional[float] = None, objective: Optional[str] = None,
                 scoring: Optional[ScoringSettings] = None) -> None:
        """Re-weight every edge from its stored Eq. 1 perception and motion cost with a new ``alpha`` and/or objective
        form (:data:`~.objectives.OBJECTIVES`), or a whole new ``scoring`` group, without rebuilding; ``None`` keeps
        the current one."""
        changes = {k: v for k, v in (("scoring.alpha", alpha), ("scoring.objective", objective),
                                     ("scoring", scoring)) if v is not None}
        new = self.ctx.settings.changed(changes)
        new.validate()
        self.rm.compact()
        self.apply_weights(new)
        self.ctx.settings = new  # last: a reader that sees the new settings sees the new weights

    def score_numpy(self, q: np.ndarray) -> np.ndarray:
        """Perception scores of configurations given as numpy (the lazy report of :class:`PlanResult`)."""
        return self.score_configs(self.ctx.t(q)).double().cpu().numpy()
