"""Baseline *Post* (paper Sec. "Baselines"): plan without perception, then aim the camera.

RRT-Connect (OMPL) plans a collision-free motion of the base (and of any other joint that differs between start
and goal) without looking at the target; along the executed differential-drive motion the free camera joints
(Stretch's head pan/tilt, TIAGo's torso + head, the UR5's arm) are then set so the optical axis points at the target
(Newton projection onto the line-of-sight manifold h_line(q) = 0 with only those joints,
:class:`~psprm_core.planning.constraints.VisibilityConstraint`). Where the joint limits cannot reach the target
the camera points as close to it as the limits allow.
"""

from __future__ import annotations

import logging

import numpy as np

from ..planning.psprm import PlanResult
from ._ompl import ActiveSpace, plan_to_goals
from ..planning.results import Failure
from .base import ContextPlanner, failure

log = logging.getLogger(__name__)


class PostPlanner(ContextPlanner):
    """Perception-unaware RRT-Connect + post-hoc camera aiming.

    Parameters
    ----------
    name, scene, targets, robot, seed : as for every benchmark planner.
    **overrides : :class:`~psprm_core.baselines.base.BaselineSettings` fields (section ``post`` of
        ``config/planners/baselines.yaml``).
    """

    section = "post"

    def _cols(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Planned joints: base + joints that differ between start and goal, minus the aimed camera joints."""
        b = self.robot.base_dof
        moving = np.abs(goal - start) > 1e-9
        moving[:b] = True
        moving[self.ctx.aim_cols] = False
        return np.nonzero(moving)[0]

    def _plan(self, start: np.ndarray, goals: np.ndarray, ok_goals: np.ndarray, timeout_s: float,
              t0: float) -> PlanResult:
        ctx, s = self.ctx, self.settings
        W, reason, gi, stats = plan_to_goals(
            lambda g: ActiveSpace(start, self._cols(start, g), ctx.lower, ctx.upper), start, goals,
            timeout_s, ctx.motion,
            state_valid=lambda q: bool(ctx.valid(q)[0]),
            motion_valid=lambda a, b: ctx.motion_ok(a, b),
            range_=s.range, seed=s.seed + self._queries, simplify=s.simplify)
        if W is None:
            return failure(reason, t0, Failure.TIMEOUT if stats.get("timed_out") else Failure.NO_SOLUTION)
        res = ctx.execute(W, aim="line", aim_iters=s.aim_iters, view_tolerance=s.aim_tolerance, t0=t0)
        res.goal_index = gi if res.success else -1
        return res
