"""Baseline *Rejection* (paper Sec. "Baselines"): RRT-Connect whose validity check also requires the target inside
the camera frustum.

A state is valid when it is collision-free *and* the target's centroid projects inside the camera's viewing frustum
(:meth:`VisibilityConstraint.in_view`); a motion is valid when every configuration along its differential-drive
execution (every ``resolution``) is, with the free camera joints (pan/tilt) doing the least needed to keep the
target in the frustum while the base turns (projection onto the frustum manifold with those joints only, as every
visibility-constrained planner here executes its motions; without it any base rotation sweeps the target out of
view). Nothing steers the samples towards the visibility region, so in most of the
configuration space the sampler is rejected, which is what makes this baseline slow in the paper.
"""

from __future__ import annotations

import logging

import numpy as np

from ..planning.psprm import PlanResult
from ._ompl import ActiveSpace, plan_to_goals
from ..planning.results import Failure
from .base import ContextPlanner, failure

log = logging.getLogger(__name__)


class RejectionPlanner(ContextPlanner):
    """RRT-Connect with a "target in the frustum" validity constraint (rejection sampling).

    Parameters
    ----------
    name, scene, targets, robot, seed : as for every benchmark planner.
    **overrides : :class:`~psprm_core.baselines.base.BaselineSettings` fields (section ``rejection``).
    """

    section = "rejection"

    def _cols(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Planned joints: the camera joints (base included) and any joint that differs between start and goal."""
        moving = (np.abs(goal - start) > 1e-9) | self.ctx.camera_mask
        return np.nonzero(moving)[0]

    def _state_ok(self, q: np.ndarray) -> bool:
        ctx = self.ctx
        return bool(ctx.in_view(q, slack=self.settings.view_slack)[0]) and bool(ctx.valid(q)[0])

    def _admissible(self, start: np.ndarray, goals: np.ndarray) -> tuple:
        ok = self.ctx.in_view(goals, slack=self.settings.view_slack)
        if not self.ctx.in_view(start, slack=self.settings.view_slack)[0]:
            return ok, "target not in the camera frustum at the start"
        return ok, "" if ok.any() else "target not in the camera frustum at any goal"

    def _plan(self, start: np.ndarray, goals: np.ndarray, ok_goals: np.ndarray, timeout_s: float,
              t0: float) -> PlanResult:
        ctx, s = self.ctx, self.settings
        W, reason, gi, stats = plan_to_goals(
            lambda g: ActiveSpace(start, self._cols(start, g), ctx.lower, ctx.upper), start, ok_goals,
            timeout_s, ctx.motion, state_valid=self._state_ok,
            motion_valid=lambda a, b: ctx.motion_ok(a, b, view="frustum", view_slack=s.view_slack, aim="frustum"),
            range_=s.range, seed=s.seed + self._queries, simplify=s.simplify)
        if W is None:
            return failure(reason, t0, Failure.TIMEOUT if stats.get("timed_out") else Failure.NO_SOLUTION)
        res = ctx.execute(W, aim="frustum", require_view="frustum", view_slack=s.view_slack, t0=t0)
        if res.success:
            res.goal_index = int(np.nonzero(np.all(np.isclose(goals, ok_goals[gi]), axis=1))[0][0])
        return res
