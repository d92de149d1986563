"""From a node path to a :class:`~.results.PlanResult`: the stored knots in traversal direction, the dense path
every ``edge_resolution`` and the time-parameterised trajectory within the joint limits."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..results import PlanResult
from ..state import NP_DTYPE, PlannerContext, QueryContext, ReadsQuerySettings
from ..timing import ProfileCache, time_parameterize

if TYPE_CHECKING:
    from ..roadmap.edges import Edges
    from ..roadmap.knots import KnotStore
    from ..roadmap.roadmap_state import RoadmapState
    from ..roadmap.scoring import Scoring

log = logging.getLogger(__name__)


class Trajectory(ReadsQuerySettings):
    """Turns node paths into checked waypoints and timed trajectories."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, qc: QueryContext, edges: Edges,
                 scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.qc = qc
        self.edges = edges
        self.scoring = scoring
        self.profiles = ProfileCache()  # smooth phases timed before (a replanner's plans share most of them)

    def finish(self, path: list, cost: float, timing: bool) -> PlanResult:
        """The :class:`~.results.PlanResult` of a node path: the stored knots of its edges in traversal direction as
        waypoints (what was checked is what runs), the dense path every ``edge_resolution``, its length and (with
        ``timing``) the timed trajectory."""
        g = self.rm.graph
        Q = g.configs[path].astype(NP_DTYPE[self.ctx.dtype])
        if len(Q) > 1:  # the knots the edges were checked and scored with, in traversal direction
            eids = g.edge_ids_of_path(path)
            if not self.knots.known(eids).all():
                self.edges.stored_knots(eids)
            knots = self.knots.data[torch.as_tensor(eids, device=self.knots.data.device)].cpu().numpy()
            flip = g.edge_u[eids] != np.asarray(path[:-1])
            knots[flip] = knots[flip, ::-1]
            W = np.concatenate([Q[:1], knots[:, 1:].reshape(-1, Q.shape[1])]).astype(np.float64)
        else:
            W = Q.astype(np.float64)
        keep = np.ones(len(W), dtype=bool)
        keep[1:] = np.abs(W[1:] - W[:-1]).max(-1) > 1e-7
        W = np.ascontiguousarray(W[keep])
        dense, length = self.ctx.backend.dense_path(W)
        traj = self.timed(W) if timing and len(W) > 1 else None
        return PlanResult(True, "ok", path_nodes=list(path), waypoints=W, dense=dense, trajectory=traj,
                          cost=float(cost), path_length=length, score_fn=self.scoring.score_numpy)

    def timed(self, W: np.ndarray):
        """Time-parameterised trajectory through the knots ``W`` (K, dof) within the joint limits
        (:func:`~psprm_core.planning.timing.time_parameterize`). With ``smooth_timing`` on a mobile robot the knots of
        each base phase are passed without stopping; those samples leave the checked straight pieces, so they are
        collision-checked, and a smooth trajectory with any colliding sample is replaced by the stop-at-every-knot one
        (which follows the checked pieces exactly)."""
        r = self.ctx.robot
        kw = dict(dt=0.05, joint_names=r.joint_names, continuous_joints=[i for i in range(r.dof) if r.continuous[i]],
                  base_indices=(0, 1, 2) if r.mobile else None,
                  base_linear_limits=(r.config.base.linear_velocity, r.config.base.linear_acceleration)
                  if r.mobile else None, method="analytic")
        if not (self.qs.query.smooth_timing and r.mobile and len(W) > 2):
            return time_parameterize(W, r.velocity, r.acceleration, **kw)
        traj = time_parameterize(W, r.velocity, r.acceleration, smooth=True, profile_cache=self.profiles, **kw)
        curved = traj.off_segment_mask()  # samples off the checked straight pieces
        if curved.any() and not self._curves_free(traj, curved, W):
            log.debug("smooth trajectory grazes an obstacle between knots: stopping at every knot instead")
            return time_parameterize(W, r.velocity, r.acceleration, **kw)
        return traj

    def _curves_free(self, traj, curved: np.ndarray, W: np.ndarray) -> bool:
        """The samples ``curved`` of a smooth trajectory through ``W`` keep the collision padding; those before the
        first padded-free knot of a path that starts inside the padding (the start fix's motion out of it) need only
        be clear of the obstacles themselves."""
        ck = self.ctx.checker
        bad = ck.check(self.ctx.t(traj.positions[curved])).cpu().numpy()
        if not bad.any() or not ck.keeps_margin:
            return not bad.any()
        inside = ck.check(self.ctx.t(W)).cpu().numpy()
        if not inside[0] or inside.all():
            return False
        t_out = traj.waypoint_times[int(np.argmin(inside))]  # the first knot that keeps the padding again
        early = traj.times[curved] <= t_out
        if (bad & ~early).any():
            return False
        idx = np.nonzero(bad)[0]
        return not bool(ck.check_unpadded(self.ctx.t(traj.positions[curved][idx])).any())
