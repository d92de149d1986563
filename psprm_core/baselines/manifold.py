"""Baselines *Manifold-line* and *Manifold-frustum* (paper Sec. "Baselines", after Kingston et al.'s projection-based
constrained planning): RRT-Connect on OMPL's ``ProjectedStateSpace`` of the visibility constraint h_M(q) = 0.

* line of sight: h(q) = (p_c,x, p_c,y), the target centroid's offset from the optical axis in the optical frame
  (co-dimension 2; its norm is the paper's scalar h_M). Valid states also need the target at least
  ``min_view_distance`` in front of the camera.
* frustum: h(q) = max(0, sd_f(q, p)) (co-dimension 1), zero inside the viewing frustum.

The constraint is evaluated with the batched FK of :class:`~psprm_core.planning.constraints.VisibilityConstraint`
(numpy in/out per state, Jacobian by forward differences over the planned joints). OMPL's ambient space is a pure
real vector over the planned joints (base x, y, theta as reals, the camera joints, and any joint that differs between
start and goal). Motions between tree states are validated as the robot executes them: the base drives rotate,
translate, rotate and the free camera joints re-project onto the manifold at every ``resolution`` (tracking); the
motion is valid when all those configurations are collision-free and on the manifold (line: |h| <= 2 x tolerance,
frustum: target inside). Each query has a time cap (paper: 60 s in its nursing runs; ``timeout_s``).
"""

from __future__ import annotations

import logging
import time
from typing import Sequence

import numpy as np
import torch

from ..planning.psprm import PlanResult
from ._ompl import ActiveSpace, _ompl, rrt_connect
from ..planning.results import Failure
from .base import ContextPlanner, PlanningContext, failure

log = logging.getLogger(__name__)


def make_ompl_constraint(ctx: PlanningContext, kind: str, space: ActiveSpace, tolerance: float,
                         max_iters: int = 15, eps: float = 1e-6):
    """An ``ob.Constraint`` over the active joints of ``space`` for the ``kind`` visibility model.

    Line of sight: h(q) = (atan2(p_c,x, p_c,z), atan2(p_c,y, p_c,z)), the target's angular offset from the optical
    axis (rad). It vanishes exactly when the target centroid lies on the axis *in front of* the camera (the metric
    offset (p_c,x, p_c,y) also vanishes with the target behind the camera, a second branch that traps Newton
    projection). ``tolerance`` is in radians for the line model and metres for the frustum model.
    """
    ob, _, _ = _ompl()
    con = ctx.constraint(kind)
    codim = 2 if kind == "line" else 1
    n = space.n

    fk = ctx.camera_fk
    focus = ctx.focus
    intr = con.intr
    th, tv = intr.tan_half_h, intr.tan_half_v
    nh, nv = np.sqrt(1 + th * th), np.sqrt(1 + tv * tv)

    def residual(Q: np.ndarray) -> np.ndarray:
        pc = fk.target_in_camera(Q, focus)
        x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
        if kind == "line":
            return np.stack([np.arctan2(x, z), np.arctan2(y, z)], -1)
        # VisibilityConstraint.frustum_distance in numpy (largest signed distance to the six planes + margin)
        d = np.stack([(x - th * z) / nh, (-x - th * z) / nh, (y - tv * z) / nv, (-y - tv * z) / nv,
                      con.min_distance - z, z - intr.far], -1).max(-1) + con.margin
        return np.maximum(d, 0.0)[:, None]

    class VisibilityOMPLConstraint(ob.Constraint):
        def __init__(self):
            super().__init__(n, codim, float(tolerance))
            self.setMaxIterations(int(max_iters))

        def function(self, x, out):
            out[:] = residual(space.full(np.asarray(x))[None])[0]

        def jacobian(self, x, out):
            q0 = space.full(np.asarray(x))
            Q = np.repeat(q0[None], n + 1, axis=0)
            Q[np.arange(1, n + 1), space.cols] += eps
            h = residual(Q)
            out[:, :] = ((h[1:] - h[0]) / eps).T

    return VisibilityOMPLConstraint()


class _ManifoldPlanner(ContextPlanner):
    """RRT-Connect on the ``kind`` visibility manifold (``ProjectedStateSpace``)."""

    kind = "line"
    section = "manifold"

    def __init__(self, name: str, scene, targets: Sequence[str], robot=None, seed: int = 0, **overrides):
        super().__init__(name, scene, targets, robot=robot, seed=seed, **overrides)
        self._constraints: list = []  # keep Python constraint objects alive while OMPL holds them

    def _cols(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        moving = (np.abs(goal - start) > 1e-9) | self.ctx.camera_mask
        return np.nonzero(moving)[0]

    def on_manifold(self, q: np.ndarray) -> np.ndarray:
        """(B,) configurations satisfying the constraint (line: |h| <= tolerance and target in front)."""
        ctx, s = self.ctx, self.settings
        q = np.atleast_2d(q)
        if self.kind == "line":
            pc = ctx.constraint("line").target_in_camera(torch.as_tensor(q, dtype=torch.float64)).numpy()
            return (np.linalg.norm(pc[:, :2], axis=1) <= 2 * s.constraint_tolerance) & \
                (pc[:, 2] >= s.min_view_distance)
        return ctx.in_view(q)

    def _state_ok(self, q: np.ndarray) -> bool:
        if self.kind == "line":
            pc = self.ctx.constraint("line").target_in_camera(torch.as_tensor(q[None], dtype=torch.float64))
            if float(pc[0, 2]) < self.settings.min_view_distance:
                return False
        return bool(self.ctx.valid(q)[0])

    def _motion_ok(self, a: np.ndarray, b: np.ndarray) -> bool:
        ctx, s = self.ctx, self.settings
        pts = ctx.densify(np.vstack([a, b]))[1:-1]
        if len(pts) == 0:
            return True
        pts, _ = ctx.aim(pts, self.kind, iters=8, tolerance=s.constraint_tolerance, restarts=0)
        return bool(self.on_manifold(pts).all()) and bool(ctx.valid(pts).all())

    def _admissible(self, start: np.ndarray, goals: np.ndarray) -> tuple:
        ok = self.on_manifold(goals)
        if not self.on_manifold(start)[0]:
            return ok, f"start configuration is not on the {self.kind} visibility manifold"
        return ok, "" if ok.any() else f"no goal configuration is on the {self.kind} visibility manifold"

    def _plan(self, start: np.ndarray, goals: np.ndarray, ok_goals: np.ndarray, timeout_s: float,
              t0: float) -> PlanResult:
        ctx, s = self.ctx, self.settings

        def space_for(g):
            sp = ActiveSpace(start, self._cols(start, g), ctx.lower, ctx.upper)
            tol = s.angle_tolerance if self.kind == "line" else s.constraint_tolerance
            con = make_ompl_constraint(ctx, self.kind, sp, tol, max_iters=s.projection_iters)
            self._constraints = [con]
            sp.constraint = con
            return sp

        # the constraint must be built per goal (it depends on the planned joints): wrap rrt_connect's keywords
        t_left = timeout_s
        W, reason, gi, timed_out, stats = None, "no goal", -1, False, {}
        for k, g in enumerate(ok_goals if len(ok_goals) == 1 else ok_goals[np.argsort(
                ctx.motion.distance(torch.as_tensor(start[None]), torch.as_tensor(ok_goals)).numpy())]):
            t_left = timeout_s - (time.perf_counter() - t0)
            if t_left <= 0:
                reason, timed_out = f"timeout ({timeout_s:.1f} s)", True
                break
            sp = space_for(g)
            W, reason, stats = rrt_connect(sp, start, g, state_valid=self._state_ok, motion_valid=self._motion_ok,
                                           timeout_s=t_left, range_=s.range, seed=s.seed, simplify=s.simplify,
                                           constraint=sp.constraint, delta=s.delta, lambda_=s.lambda_)
            if W is not None:
                gi = int(np.nonzero(np.all(np.isclose(goals, g), axis=1))[0][0])
                break
        self._constraints = []
        if W is None:
            return failure(reason, t0, Failure.TIMEOUT if timed_out or stats.get("timed_out") else Failure.NO_SOLUTION)
        res = ctx.execute(W, aim=self.kind, aim_iters=s.aim_iters, view_tolerance=s.constraint_tolerance, t0=t0)
        if res.success:
            if not self.on_manifold(res.dense).all():
                return failure(f"executed motion leaves the {self.kind} visibility manifold", t0)
            res.goal_index = gi
        return res


class ManifoldLinePlanner(_ManifoldPlanner):
    """Manifold-line: RRT-Connect on the line-of-sight manifold."""

    kind = "line"


class ManifoldFrustumPlanner(_ManifoldPlanner):
    """Manifold-frustum: RRT-Connect on the camera-frustum manifold."""

    kind = "frustum"
