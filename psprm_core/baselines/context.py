"""The planning context of the sampling baselines: how a waypoint list becomes an executed, checked result.

:class:`PlanningContext` holds the robot, scene, target focus, collision checker and motion model a planner's queries
share, and turns waypoints into a :class:`~psprm_core.planning.psprm.PlanResult` (:meth:`PlanningContext.execute`):
every segment is expanded into its drive phases, densified, optionally re-aimed (the non-base camera joints projected
onto a visibility manifold, :class:`~psprm_core.planning.constraints.VisibilityConstraint`) and collision-checked; the
path length is the sum of :meth:`DiffDriveMotion.distance` over the dense configurations (:func:`path_length`). With
it: the camera's optical-frame poses in numpy (:class:`CameraFK`), the re-aiming with restarts (:func:`aim_camera`)
and failed results (:func:`failure`).
"""

from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np
import torch

from ..collision import CollisionChecker
from ..motion import DiffDriveMotion
from ..planning.constraints import ProjectionSettings, VisibilityConstraint
from ..planning.constraints import camera_joint_mask
from ..planning.psprm import PlanResult
from ..planning.results import Failure
from ..robot import RobotModel
from ..scene import Scene


def failure(reason: str, t0: Optional[float] = None, kind: Failure = Failure.NO_SOLUTION) -> PlanResult:
    """A failed :class:`PlanResult` of failure ``kind`` (query time from ``t0`` = ``time.perf_counter()`` at the
    start, if given)."""
    ms = (time.perf_counter() - t0) * 1e3 if t0 is not None else float("nan")
    return PlanResult(False, reason, kind, query_ms=ms)


def path_length(motion: DiffDriveMotion, dense: np.ndarray) -> float:
    """Length of an executed path: sum of the differential-drive motion cost between consecutive configurations
    (metres of base travel + ``w_rot`` x base rotation + joint radians/metres; :mod:`psprm_core.motion`)."""
    if dense is None or len(dense) < 2:
        return 0.0
    q = torch.as_tensor(np.asarray(dense), dtype=torch.float64)
    return float(motion.distance(q[:-1], q[1:]).sum())


class CameraFK:
    """Camera optical-frame poses in numpy (float64) for small batches: the same composition as
    :meth:`RobotModel.camera_poses` (base transform, then ``T_parent T_origin Motion(axis, value)`` along the camera's
    chain) without torch's per-call overhead, for per-state callbacks (OMPL constraints)."""

    def __init__(self, robot: RobotModel):
        T = robot.tensors("cpu", torch.float64)
        self.robot = robot
        self.chain = robot.camera_chain
        self.D, self.off = T["D"].numpy(), T["off"].numpy()
        self.R_off, self.t_off, self.axis = T["R_off"].numpy(), T["t_off"].numpy(), T["axis"].numpy()
        self.cam_R, self.cam_t = T["cam_R"].numpy(), T["cam_t"].numpy()
        self.prismatic = {b: robot.body_joint[b].type == "prismatic" for b in self.chain[1:]}

    def __call__(self, q: np.ndarray) -> tuple:
        """(R (B, 3, 3), t (B, 3)) of the optical frame for configurations (B, dof)."""
        q = np.atleast_2d(np.asarray(q, float))
        B = len(q)
        if self.robot.mobile:
            c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
            R = np.zeros((B, 3, 3))
            R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
            t = np.stack([q[:, 0], q[:, 1], np.zeros(B)], -1)
        else:
            R, t = np.broadcast_to(np.eye(3), (B, 3, 3)).copy(), np.zeros((B, 3))
        values = q @ self.D + self.off
        for b in self.chain[1:]:
            tj = t + R @ self.t_off[b]
            Rj = R @ self.R_off[b]
            v = values[:, b]
            a = self.axis[b]
            if self.prismatic[b]:
                R, t = Rj, tj + (Rj @ a) * v[:, None]
            else:
                K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
                Rm = np.eye(3) + np.sin(v)[:, None, None] * K + (1 - np.cos(v))[:, None, None] * (K @ K)
                R, t = Rj @ Rm, tj
        return R @ self.cam_R, t + R @ self.cam_t

    def target_in_camera(self, q: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Point ``p`` (3,) in the optical frame (B, 3)."""
        R, t = self(q)
        return np.einsum("bij,bi->bj", R, np.asarray(p, float) - t)


def aim_camera(constraint: VisibilityConstraint, q: np.ndarray, cols: np.ndarray, lower: np.ndarray,
               upper: np.ndarray, iters: int = 20, tolerance: float = 0.02, restarts: int = 8,
               seed: int = 0) -> tuple:
    """Project configurations (B, dof) onto a visibility manifold moving only the joints ``cols`` (e.g. head pan and
    tilt), with restarts.

    Gauss-Newton from the current joint values (paper Alg. 1 line 7, restricted to the free camera joints) gets stuck
    when the target is behind the camera (the tilt runs into its limit); configurations that do not converge are
    retried from ``restarts`` starting values spread over the joints' limits (the first joint of ``cols`` on an even
    grid, the others at random) and keep the best result. Returns (q (B, dof), converged (B,)).
    """
    q = np.atleast_2d(np.asarray(q, float))
    lo_t = torch.as_tensor(lower, dtype=torch.float64)
    hi_t = torch.as_tensor(upper, dtype=torch.float64)
    ps = ProjectionSettings(tolerance=tolerance, max_iters=iters)
    out, ok = constraint.project(torch.as_tensor(q, dtype=torch.float64), ps, lo_t, hi_t, joints=cols)
    out, ok = out.numpy(), ok.numpy()
    bad = np.nonzero(~ok)[0]
    if restarts <= 0 or len(bad) == 0:
        return out, ok
    rng = np.random.default_rng(seed)
    lo = np.clip(np.asarray(lower, float)[cols], -np.pi, None)
    hi = np.clip(np.asarray(upper, float)[cols], None, np.pi)
    R = restarts
    init = np.repeat(q[bad], R, axis=0)
    grid = lo[0] + (np.arange(R) + 0.5) / R * (hi[0] - lo[0])
    init[:, cols[0]] = np.tile(grid, len(bad))
    if len(cols) > 1:
        init[:, cols[1:]] = rng.uniform(lo[1:], hi[1:], (len(init), len(cols) - 1)) * 0.5 + init[:, cols[1:]] * 0.5
    qr, okr = constraint.project(torch.as_tensor(init, dtype=torch.float64), ps, lo_t, hi_t, joints=cols)
    err = constraint.error(qr).numpy().reshape(len(bad), R)
    best = err.argmin(1)
    qr = qr.numpy().reshape(len(bad), R, -1)[np.arange(len(bad)), best]
    old_err = constraint.error(torch.as_tensor(out[bad], dtype=torch.float64)).numpy()
    better = err[np.arange(len(bad)), best] < old_err
    out[bad[better]] = qr[better]
    ok[bad] = constraint.error(torch.as_tensor(out[bad], dtype=torch.float64)).numpy() < tolerance
    return out, ok


class PlanningContext:
    """Robot, scene, target focus, collision checker and motion model shared by a planner's queries.

    Parameters
    ----------
    scene : Scene
    targets : sequence of str
        Targets to keep in view; the focus point is their centroid (as in
        :func:`psprm_core.planning.factory.make_planner`).
    robot : RobotModel, optional (loaded from ``scene.robot``)
    resolution : spacing of executed configurations (motion-cost units)
    frustum_margin, min_view_distance : visibility model settings
    """

    def __init__(self, scene: Scene, targets: Sequence[str], robot: Optional[RobotModel] = None,
                 resolution: float = 0.05, frustum_margin: float = 0.05, min_view_distance: float = 0.5):
        self.scene = scene
        self.targets = list(targets)
        for t in self.targets:
            scene.target(t)  # clear error for unknown targets
        self.robot = robot or RobotModel.load(scene.robot)
        self.resolution = float(resolution)
        self.focus = np.mean([scene.target(t).center for t in self.targets], axis=0)
        self.checker = CollisionChecker(self.robot, scene.collision_boxes(), workspace=scene.workspace)
        self.motion = DiffDriveMotion(self.robot)
        self.frustum_margin, self.min_view_distance = frustum_margin, min_view_distance
        mask = camera_joint_mask(self.robot)
        self.camera_mask = mask.copy()  # base + joints that move the camera
        mask[: self.robot.base_dof] = False
        self.aim_cols = np.nonzero(mask)[0]  # non-base camera joints (pan/tilt, torso, arm...)
        r = self.robot
        lo = np.where(np.isfinite(r.lower), r.lower, -1e9)
        hi = np.where(np.isfinite(r.upper), r.upper, 1e9)
        if r.mobile:
            lo[:2], hi[:2] = scene.workspace[:, 0], scene.workspace[:, 1]
            lo[2], hi[2] = -np.pi, np.pi
        self.lower, self.upper = lo.astype(float), hi.astype(float)
        self._constraints: dict = {}
        self.camera_fk = CameraFK(self.robot)

    # ---- visibility ------------------------------------------------------------------------------------------------
    def constraint(self, kind: str) -> VisibilityConstraint:
        """The visibility constraint ``line`` or ``frustum`` on the focus point (cached)."""
        if kind not in self._constraints:
            self._constraints[kind] = VisibilityConstraint(self.robot, kind, self.focus, margin=self.frustum_margin,
                                                           min_distance=self.min_view_distance)
        return self._constraints[kind]

    def aim(self, q: np.ndarray, kind: str = "line", iters: int = 20, tolerance: float = 0.02,
            restarts: int = 8) -> tuple:
        """Re-aim the non-base camera joints of configurations (B, dof) at the focus (projection onto the ``kind``
        manifold with only those joints, :func:`aim_camera`). Returns (q (B, dof), converged (B,))."""
        q = np.atleast_2d(np.asarray(q, float))
        if len(self.aim_cols) == 0 or len(q) == 0:
            return q.copy(), np.ones(len(q), dtype=bool)
        return aim_camera(self.constraint(kind), q, self.aim_cols, self.lower, self.upper, iters=iters,
                          tolerance=tolerance, restarts=restarts)

    def view_error(self, q: np.ndarray, kind: str = "line") -> np.ndarray:
        """|h(q)| (B,) of the ``kind`` visibility model (line: metres off the optical axis; frustum: metres outside)."""
        qt = torch.as_tensor(np.atleast_2d(np.asarray(q, float)), dtype=torch.float64)
        return self.constraint(kind).error(qt).numpy()

    def in_view(self, q: np.ndarray, slack: float = 0.0) -> np.ndarray:
        """Target focus inside the camera frustum (B,) bool (:meth:`VisibilityConstraint.in_view`)."""
        con = self.constraint("frustum")
        pc = torch.as_tensor(self.camera_fk.target_in_camera(q, self.focus))
        return (con.frustum_distance(pc) - con.margin <= slack).numpy()

    # ---- validity --------------------------------------------------------------------------------------------------
    def valid(self, q: np.ndarray) -> np.ndarray:
        """Collision-free and within limits/workspace (B,) bool."""
        qt = torch.as_tensor(np.atleast_2d(np.asarray(q, float)), dtype=torch.float32)
        return self.checker.valid(qt).numpy()

    def check_problem(self, start, goals) -> tuple:
        """Validate a query. Returns (start (dof,), valid goals (G', dof), failure PlanResult or None)."""
        dof = self.robot.dof
        try:
            start = np.asarray(start, float).reshape(dof)
            goals = np.asarray(goals, float).reshape(-1, dof)
        except ValueError:
            return None, None, failure(f"start/goal must have {dof} joint values", kind=Failure.INVALID_INPUT)
        if not (np.isfinite(start).all() and np.isfinite(goals).all()):
            return start, goals, failure("start or goal contains NaN/inf", kind=Failure.INVALID_INPUT)
        qs = torch.as_tensor(np.vstack([start, goals]), dtype=torch.float32)
        det = self.checker.check_detailed(qs)
        bad = (det["limits"] | det["environment"] | det["self"]).numpy()
        if bad[0]:
            why = ", ".join(k for k in ("limits", "environment", "self") if bool(det[k][0]))
            return start, goals, failure(f"start configuration invalid ({why})", kind=Failure.START_BLOCKED)
        if bad[1:].all():
            return start, goals, failure("every goal configuration is in collision or outside the limits",
                                         kind=Failure.GOAL_BLOCKED)
        return start, goals[~bad[1:]], None

    # ---- execution -------------------------------------------------------------------------------------------------
    def drive_knots(self, W: np.ndarray) -> np.ndarray:
        """Insert the differential-drive corners (end of the first rotation, end of the translation) between
        consecutive waypoints, so that straight joint-space interpolation between the returned knots is exactly the
        rotate-translate-rotate motion (joints move proportionally to the motion fraction)."""
        W = np.atleast_2d(np.asarray(W, float))
        if len(W) < 2 or not self.robot.mobile:
            return W.copy()
        a = torch.as_tensor(W[:-1], dtype=torch.float64)
        b = torch.as_tensor(W[1:], dtype=torch.float64)
        _, r1, d, r2 = self.motion.base_plan(a, b)
        w = self.motion.w_rot
        l1, l2, l3 = w * r1.abs(), d, w * r2.abs()
        tot = (l1 + l2 + l3).clamp_min(1e-12)
        s = torch.stack([l1 / tot, (l1 + l2) / tot], -1)  # (E, 2)
        E = len(a)
        mid = self.motion.interpolate(a.repeat_interleave(2, 0), b.repeat_interleave(2, 0), s.reshape(-1))
        mid = mid.reshape(E, 2, -1)
        out = [W[0:1]]
        for i in range(E):
            out.append(mid[i].numpy())
            out.append(W[i + 1:i + 2])
        K = np.vstack(out)
        keep = np.ones(len(K), dtype=bool)
        keep[1:] = np.abs(np.diff(K, axis=0)).max(-1) > 1e-9
        return K[keep]

    def densify(self, W: np.ndarray, resolution: Optional[float] = None, max_steps: int = 2000) -> np.ndarray:
        """Configurations every ``resolution`` along the differential-drive motions between waypoints (K, dof)."""
        W = np.atleast_2d(np.asarray(W, float))
        if len(W) < 2:
            return W.copy()
        res = self.resolution if resolution is None else resolution
        m = self.motion
        ops, a, b = m.compute.ops, np.ascontiguousarray(W[:-1]), np.ascontiguousarray(W[1:])
        n = np.clip(np.ceil(ops.metric_arrays(m, a, b) / res).astype(np.int64), 1, max_steps)
        seg = np.repeat(np.arange(len(a)), n)
        s = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
        return np.vstack([ops.interpolate_arrays(m, a[seg], b[seg], s), W[-1:]])

    def fill_joint_jumps(self, dense: np.ndarray, max_step: float = 0.1) -> np.ndarray:
        """Insert configurations where the camera joints jump by more than ``max_step`` (rad/m) between consecutive
        executed configurations (re-aiming can swing the head from one joint limit to the other when the target
        passes behind it): the joints then sweep there in steps of at most ``max_step`` (the base barely moves)."""
        if len(dense) < 2 or len(self.aim_cols) == 0:
            return dense
        jump = np.abs(np.diff(dense[:, self.aim_cols], axis=0)).max(-1)
        big = np.nonzero(jump > max_step)[0]
        if len(big) == 0:
            return dense
        pieces, last = [], 0
        for i in big:
            pieces.append(dense[last:i + 1])
            n = int(np.ceil(jump[i] / max_step))
            f = (np.arange(1, n) / n)[:, None]
            mid = dense[i] + (dense[i + 1] - dense[i]) * f
            if self.robot.mobile:
                dth = (dense[i + 1, 2] - dense[i, 2] + np.pi) % (2 * np.pi) - np.pi
                mid[:, 2] = (dense[i, 2] + dth * f[:, 0] + np.pi) % (2 * np.pi) - np.pi
            pieces.append(mid)
            last = i + 1
        pieces.append(dense[last:])
        return np.vstack(pieces)

    def execute(self, waypoints: np.ndarray, aim: Optional[str] = None, require_view: Optional[str] = None,
                view_tolerance: float = 0.02, view_slack: float = 0.0, aim_iters: int = 20,
                t0: Optional[float] = None, check_collision: bool = True) -> PlanResult:
        """Turn waypoints into a differential-drive-feasible, collision-checked :class:`PlanResult`.

        Parameters
        ----------
        waypoints : (M, dof)
            Consecutive waypoints; the base moves rotate-translate-rotate between them, the joints linearly.
        aim : {None, "line", "frustum"}
            Re-aim the non-base camera joints at the focus at every interior dense configuration (the start and the
            goal are kept as given).
        require_view : {None, "line", "frustum"}
            Fail unless every dense configuration satisfies the visibility model (line: |h| <= ``view_tolerance``,
            frustum: target centroid within the frustum + ``view_slack``).
        t0 : ``time.perf_counter()`` at the start of the query (for ``query_ms``).
        """
        W = np.atleast_2d(np.asarray(waypoints, float))
        if not np.isfinite(W).all():
            return failure("path contains NaN/inf", t0)
        K = self.drive_knots(W)
        dense = self.densify(K)
        if aim is not None and len(dense) > 2:
            inner, _ = self.aim(dense[1:-1], aim, iters=aim_iters, tolerance=min(view_tolerance, 0.02))
            dense = np.vstack([dense[:1], inner, dense[-1:]])
            knots_inner, _ = self.aim(K[1:-1], aim, iters=aim_iters) if len(K) > 2 else (K[1:-1], None)
            K = np.vstack([K[:1], knots_inner, K[-1:]]) if len(K) > 2 else K
            dense = self.fill_joint_jumps(dense)
        if check_collision:
            ok = self.valid(dense)
            if not ok.all():
                i = int(np.nonzero(~ok)[0][0])
                return failure(f"executed motion collides at configuration {i}/{len(dense)}", t0)
        if require_view == "line":
            err = self.view_error(dense, "line")
            if (err > view_tolerance).any():
                return failure(f"line of sight lost along the executed motion (max |h| {err.max():.3f} m)", t0)
        elif require_view == "frustum":
            ok = self.in_view(dense, slack=view_slack)
            if not ok.all():
                return failure(f"target left the frustum along the executed motion ({int((~ok).sum())} configs)", t0)
        length = path_length(self.motion, dense)
        ms = (time.perf_counter() - t0) * 1e3 if t0 is not None else float("nan")
        return PlanResult(True, "ok", waypoints=K, dense=dense, cost=length, path_length=length, query_ms=ms,
                          goal_index=0)

    def motion_ok(self, qa: np.ndarray, qb: np.ndarray, view: Optional[str] = None, view_slack: float = 0.0,
                  view_tolerance: float = 0.02, aim: Optional[str] = None, aim_iters: int = 8) -> bool:
        """Is the differential-drive motion qa -> qb collision-free (and, with ``view``, in view throughout)?

        Interior configurations every ``resolution``; endpoints are assumed checked. With ``aim`` the non-base
        camera joints track the focus along the motion (as :meth:`execute` does) before the checks.
        """
        pts = self.densify(np.vstack([qa, qb]))[1:-1]
        if len(pts) == 0:
            return True
        if aim is not None:
            pts, _ = self.aim(pts, aim, iters=aim_iters, restarts=0)
        if not self.valid(pts).all():
            return False
        if view == "frustum":
            return bool(self.in_view(pts, slack=view_slack).all())
        if view == "line":
            return bool((self.view_error(pts, "line") <= view_tolerance).all())
        return True
