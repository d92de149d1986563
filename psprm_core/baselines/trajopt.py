"""Baseline 5, visibility-aware trajectory optimisation (``trajopt``; paper Sec. "Evaluated Methods", after
Wang et al. 2021, "visibility-aware TrajOpt").

The path is a sequence of N waypoints ``Q_0 .. Q_{N-1}`` (``Q_0`` = start, fixed); it starts as the straight line from
the start to the goal in configuration space, and the free waypoints ``Q_1 .. Q_{N-1}`` are optimised by non-linear
least squares with Levenberg-Marquardt (:func:`scipy.optimize.least_squares`, ``method="lm"``; MINPACK). Optimised
joints: the base, the joints that move the camera and any joint that differs between start and goal (``joints:
active``; ``all`` optimises every joint). The residual vector stacks these blocks, each multiplied by its weight
(:class:`TrajOptSettings`):

``goal``
    ``Q_{N-1} - q_goal`` (the goal heading unwrapped next to the start's).
``smoothness``
    first finite differences ``W (Q_{i+1} - Q_i)``, with ``W`` = 1 for positions/joints and the base's rotation weight
    (metres per radian) for the heading: the squared motion cost of the path.
``limits``
    hinges ``max(0, q - upper) + max(0, lower - q)`` on every waypoint and bounded joint (base x/y: the scene's
    workspace).
``velocity``
    hinges on the per-segment motion against the velocity limits times the segment duration
    ``dt = duration_factor * T_line / (N - 1)``, with ``T_line`` the fastest straight-line duration: forward base
    motion against the linear speed, heading change against the angular speed, joints against their speeds.
``collision``
    for every robot collision sphere (centre c, radius r) and scene box, the hinge ``max(0, margin + r - sd(c, box))``
    with ``sd`` the box's signed distance; the hinges are aggregated per (evaluation point, rigid body) as
    ``sqrt(sum hinge^2)`` (same cost, fewer rows). Evaluation points are the free waypoints and ``collision_substeps``
    points on every segment.
``view``
    the angle between the camera's optical axis and the direction from the camera to the target (the targets'
    centroid) at every free waypoint.
``nonholonomic``
    the differential-drive constraint: no sideways base motion, ``-sin(th_m) dx + cos(th_m) dy`` per segment with
    ``th_m`` the segment's mean heading. When it is zero the segment is a constant-curvature arc the base can drive.

Constraint blocks (limits, collision, nonholonomic, goal) are penalties; when a solution is rejected and still
violates them, their weights are multiplied by ``penalty_growth`` and the solve is warm-started again (at most
``penalty_rounds`` times), as TrajOpt's penalty method does. If the straight-line initialisation fails, up to
``restarts`` initialisations bent sideways through a via point are tried (TrajOpt's multiple initialisations).
Jacobians: closed form for goal, smoothness, limits, velocity and nonholonomic blocks; batched forward differences
through forward kinematics (float64) for collision and view, with a broad phase (bounding sphere per rigid body) so
only sphere/box pairs near their margin are evaluated.

The result is accepted only if the final waypoint reaches the goal (``goal_tolerance``), every segment is drivable
(lateral error below ``lateral_tolerance``) and the executed motion passes the exact collision checker
(:meth:`~psprm_core.baselines.base.PlanningContext.execute`: between waypoints the base turns, drives the chord and
turns, which for a drivable segment is half the heading change, the chord, the other half; configurations
``resolution`` apart, self-collision and limits included); otherwise ``success`` is False with a reason.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import ConfigError, InputError
from ..geometry import wrap_angle
from ..planning.results import Failure
from .base import PlanningContext, failure, resolve_settings
from .trajopt_problem import TrajOptProblem, arc_segments

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------------------
# Settings
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrajOptSettings:
    """Settings of the trajopt baseline (section ``trajopt:`` of ``config/planners/baselines.yaml``)."""

    n_waypoints: int = 30  # N, including the start and the final waypoint
    collision_substeps: int = 1  # collision evaluation points inside every segment
    margin: float = 0.05  # clearance (m) the collision hinge asks of every sphere
    w_goal: float = 10.0
    w_smooth: float = 1.0
    w_limits: float = 10.0
    w_velocity: float = 1.0
    w_collision: float = 10.0
    w_view: float = 0.3
    w_nonholonomic: float = 10.0
    duration_factor: float = 3.0  # segment duration for the velocity limits, relative to the straight line's
    min_duration_s: float = 2.0
    restarts: int = 2  # bent initialisations tried after the straight line fails (0: straight line only)
    restart_offset: float = 1.0  # sideways offset (m) of the first restart's via point
    penalty_rounds: int = 4  # solves with growing constraint weights
    penalty_growth: float = 10.0
    max_nfev: int = 300  # function evaluations per solve (MINPACK's budget)
    ftol: float = 1e-4
    xtol: float = 1e-4
    fd_eps: float = 1e-6
    goal_tolerance: float = 0.02  # max |Q_{N-1} - goal| per joint (m / rad) to accept (then snapped to the goal)
    lateral_tolerance: float = 0.02  # max sideways base displacement per segment (m)
    view_tolerance_deg: float = -1.0  # >= 0: also fail if the mean view angle stays above this
    resolution: float = 0.05  # spacing of the dense output and final collision check (motion-cost units)
    timeout_s: float = 60.0  # default for plan() when the caller gives none
    joints: str = "active"  # active: base, camera joints and joints that differ between start and goal | all
    seed: int = 0  # unused (the optimisation is deterministic); part of the common settings

    def validate(self, source: str = "trajopt settings") -> None:
        if self.n_waypoints < 3:
            raise ConfigError(source, "n_waypoints", "need at least 3 waypoints")
        if self.collision_substeps < 0 or self.penalty_rounds < 1 or self.max_nfev < 1:
            raise ConfigError(source, "penalty_rounds", "collision_substeps >= 0, penalty_rounds >= 1, max_nfev >= 1")
        if self.joints not in ("active", "all"):
            raise ConfigError(source, "joints", f"must be 'active' or 'all', got '{self.joints}'")
        if self.resolution <= 0 or self.fd_eps <= 0:
            raise ConfigError(source, "resolution", "resolution and fd_eps must be > 0")


# ------------------------------------------------------------------------------------------------------------------
# Differential-drive helpers
# ------------------------------------------------------------------------------------------------------------------
def path_cost(W: np.ndarray, w_rot: float, mobile: bool = True) -> float:
    """Motion cost of a waypoint path (sum of :func:`arc_segments` costs)."""
    W = np.asarray(W, float)
    if len(W) < 2:
        return 0.0
    if not mobile:
        return float(np.linalg.norm(np.diff(W, axis=0), axis=1).sum())
    return float(arc_segments(W[:-1], W[1:], w_rot)["cost"].sum())


def view_angles(robot, q: np.ndarray, focus: np.ndarray) -> np.ndarray:
    """Angle (rad) between the optical axis and the direction from the camera to ``focus`` for configurations
    (B, dof)."""
    T = robot.camera_poses(torch.as_tensor(np.atleast_2d(q), dtype=torch.float64))
    d = torch.as_tensor(focus, dtype=torch.float64) - T[:, :3, 3]
    z = T[:, :3, 2]
    return torch.atan2(torch.linalg.cross(z, d).norm(dim=-1), (z * d).sum(-1)).numpy()


def index_of_goal(given, goal: np.ndarray) -> int:
    """Index of ``goal`` among the goals the caller passed (some may have been dropped as invalid)."""
    g = np.asarray(given, float).reshape(-1, len(goal))
    match = np.nonzero(np.all(np.isclose(g, goal), axis=1))[0]
    return int(match[0]) if len(match) else 0


# ------------------------------------------------------------------------------------------------------------------
# Planner
# ------------------------------------------------------------------------------------------------------------------
class TrajOptPlanner:
    """Visibility-aware trajectory optimisation baseline (see the module docstring for the residuals).

    Parameters
    ----------
    name, scene, targets, robot, seed : as for every benchmark planner (the view residual aims the optical axis at
        the targets' centroid; the optimisation itself is deterministic).
    settings : TrajOptSettings, optional
        Default: sections ``common`` and ``trajopt`` of ``config/planners/baselines.yaml``.
    **overrides : :class:`TrajOptSettings` fields (``n_waypoints=...``) applied on top.
    """

    section = "trajopt"

    def __init__(self, name: str = "trajopt", scene=None, targets: Sequence[str] = (), robot=None, seed: int = 0,
                 settings: Optional[TrajOptSettings] = None, **overrides):
        if scene is None or not targets:
            raise InputError("TrajOptPlanner needs a scene and at least one target")
        self.name = name
        self.settings = settings = resolve_settings(TrajOptSettings, self.section, settings, seed=seed, **overrides)
        self.ctx = PlanningContext(scene, targets, robot=robot, resolution=settings.resolution)
        self.scene, self.targets, self.robot = scene, list(targets), self.ctx.robot
        self.focus = self.ctx.focus
        r = self.robot
        self.w_rot = r.config.base.rotation_weight if r.mobile else 1.0
        lo = np.where(np.isfinite(r.lower), r.lower, -np.inf)
        hi = np.where(np.isfinite(r.upper), r.upper, np.inf)
        if r.mobile:
            lo[:2], hi[:2] = scene.workspace[:, 0], scene.workspace[:, 1]
        self.lo, self.hi = lo, hi
        # collision model (float64): boxes and the rigid body of every sphere
        boxes = scene.collision_boxes()
        dt = torch.float64
        if boxes:
            self._box_c = torch.as_tensor(np.stack([b.center for b in boxes]), dtype=dt)
            self._box_R = torch.as_tensor(np.stack([b.rotation for b in boxes]), dtype=dt)
            self._box_h = torch.as_tensor(np.stack([b.half_extents for b in boxes]), dtype=dt)
        else:
            self._box_c, self._box_R, self._box_h = (torch.zeros(0, 3, dtype=dt), torch.zeros(0, 3, 3, dtype=dt),
                                                     torch.zeros(0, 3, dtype=dt))
        sm = r.spheres
        body = sm.link_body[sm.sphere_link]
        ub, inv = np.unique(body, return_inverse=True)
        self._sphere_group = torch.as_tensor(inv, dtype=torch.long)  # rigid body ("group") of every sphere
        self._sphere_body = torch.as_tensor(body, dtype=torch.long)
        self._sphere_c = torch.as_tensor(sm.centers, dtype=dt)
        self._n_groups = len(ub)
        self._radii = torch.as_tensor(sm.radii, dtype=dt)
        # a bounding sphere per group (body frame) for the broad phase
        gc, gr, order, count = [], [], [], []
        for g in range(len(ub)):
            idx = np.nonzero(inv == g)[0]
            c = 0.5 * (sm.centers[idx].min(0) + sm.centers[idx].max(0))
            gc.append(c)
            gr.append(float((np.linalg.norm(sm.centers[idx] - c, axis=1) + sm.radii[idx]).max()))
            order.append(idx)
            count.append(len(idx))
        self._grp_body = torch.as_tensor(ub, dtype=torch.long)
        self._grp_c = torch.as_tensor(np.array(gc), dtype=dt)
        self._grp_r = torch.as_tensor(np.array(gr), dtype=dt)
        self._grp_order = torch.as_tensor(np.concatenate(order), dtype=torch.long)
        self._grp_count = torch.as_tensor(np.array(count), dtype=torch.long)
        self._grp_start = torch.cumsum(self._grp_count, 0) - self._grp_count
        self._focus_t = torch.as_tensor(self.focus, dtype=dt)

    # ---- interface -----------------------------------------------------------------------------------------------
    def prepare(self) -> dict:
        """Nothing to precompute (the optimisation runs per query)."""
        return {"preprocess_s": 0.0}

    def plan(self, start: np.ndarray, goals: np.ndarray, timeout_s: Optional[float] = None):
        """Optimise a path from ``start`` to the nearest reachable of ``goals`` ((dof,) or (G, dof)).

        Goals are tried in order of motion cost from the start until one succeeds or the time runs out.
        Returns a :class:`~psprm_core.planning.psprm.PlanResult` whose ``dense`` is the executed motion (the base
        turns by half the heading change, drives the chord and turns again between waypoints; for a solution of the
        nonholonomic residual the chord follows the mean heading, so this is the optimised arc up to the
        discretisation). Failures come with a reason, never an exception.
        """
        t0 = time.perf_counter()
        timeout_s = self.settings.timeout_s if timeout_s is None else float(timeout_s)
        given = goals
        start, goals, fail = self.ctx.check_problem(start, goals)
        if fail is not None:
            return fail
        cost = [path_cost(np.stack([start, g]), self.w_rot, self.robot.mobile) for g in goals]
        reasons, kind = [], Failure.NO_SOLUTION
        for gi in np.argsort(cost):
            if time.perf_counter() - t0 >= timeout_s:
                reasons.append("timeout")
                kind = Failure.TIMEOUT
                break
            try:
                res = self._solve(start, goals[gi], t0, t0 + timeout_s)
            except (np.linalg.LinAlgError, ValueError, RuntimeError) as exc:  # numerical breakdown of MINPACK
                log.warning("trajopt solve failed: %s", exc)
                res = failure(f"optimisation failed numerically ({exc})", t0)
            if res.success:
                res.goal_index = index_of_goal(given, goals[gi])
                res.query_ms = (time.perf_counter() - t0) * 1e3
                return res
            reasons.append(res.reason)
            kind = res.failure
        reason = reasons[0] if len(set(reasons)) == 1 else "; ".join(f"goal {i}: {r}" for i, r in enumerate(reasons))
        return failure(reason, t0, kind)

    # ---- optimisation --------------------------------------------------------------------------------------------
    def initial_path(self, start: np.ndarray, goal: np.ndarray, attempt: int = 0) -> np.ndarray:
        """Initial waypoints (N, dof). ``attempt`` 0: the straight line from start to goal in configuration space
        (heading the short way round). Restart ``k >= 1`` (mobile robots): the base's x/y bent through a via point
        at the middle, offset sideways by ``restart_offset * ceil(k / 2)`` metres to the left (odd k) or right (even
        k) of the start-goal line; everything else as for the straight line."""
        goal = self._unwrap_goal(start, goal)
        s = np.linspace(0.0, 1.0, self.settings.n_waypoints)[:, None]
        Q = start[None] + (goal - start)[None] * s
        if attempt > 0 and self.robot.mobile:
            d = goal[:2] - start[:2]
            n = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-9)
            off = self.settings.restart_offset * math.ceil(attempt / 2) * (1 if attempt % 2 else -1)
            bump = 1.0 - np.abs(2.0 * s[:, 0] - 1.0)  # 0 at the ends, 1 in the middle (piecewise linear)
            Q[:, :2] += bump[:, None] * off * n[None]
            Q[:, :2] = np.clip(Q[:, :2], self.lo[:2], self.hi[:2])
        return Q

    def _unwrap_goal(self, start, goal):
        goal = goal.copy()
        if self.robot.mobile:
            goal[2] = start[2] + wrap_angle(goal[2] - start[2])
        for i in np.nonzero(self.robot.continuous)[0]:
            if i >= self.robot.base_dof:
                goal[i] = start[i] + wrap_angle(goal[i] - start[i])
        return goal

    def _segment_dt(self, start, goal) -> float:
        r = self.robot
        d = np.abs(goal - start)
        t = d[r.base_dof:] / r.velocity[r.base_dof:]
        tmax = float(t.max()) if len(t) else 0.0
        if r.mobile:
            tmax = max(tmax, np.hypot(d[0], d[1]) / r.velocity[0] + d[2] / r.velocity[2])
        T = max(self.settings.duration_factor * tmax, self.settings.min_duration_s)
        return T / (self.settings.n_waypoints - 1)

    def optimised_joints(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Indices of the optimised joints: every joint (``joints: all``), or the base, the joints that move the
        camera and the joints that differ between start and goal (``joints: active``; the others stay put)."""
        if self.settings.joints == "all":
            return np.arange(self.robot.dof)
        m = self.ctx.camera_mask.copy()
        m[: self.robot.base_dof] = True
        m |= np.abs(goal - start) > 1e-9
        return np.nonzero(m)[0]

    def _solve(self, start: np.ndarray, goal: np.ndarray, t0: float, deadline: float):
        """Straight-line initialisation first, then up to ``restarts`` bent initialisations (first success wins)."""
        res = failure("optimisation not run", t0)
        reasons = []
        for attempt in range(1 + (self.settings.restarts if self.robot.mobile else 0)):
            res = self._solve_from(start, goal, attempt, t0, deadline)
            if res.success or res.failure is Failure.TIMEOUT:
                break
            reasons.append(res.reason)
        if not res.success and len(reasons) > 1:
            res.reason = f"{reasons[0]} (and {len(reasons) - 1} restarts failed)"
        return res

    def _solve_from(self, start: np.ndarray, goal: np.ndarray, attempt: int, t0: float, deadline: float):
        from scipy.optimize import least_squares

        s = self.settings
        goal_u = self._unwrap_goal(start, goal)
        Q0 = self.initial_path(start, goal, attempt)
        cols = self.optimised_joints(start, goal_u)
        problem = TrajOptProblem(self, start, goal_u, self._segment_dt(start, goal_u), cols)
        x = Q0[1:, cols].reshape(-1).copy()
        scale = np.ones(4)  # multipliers of the limits, collision, nonholonomic and goal weights
        self.last_info = {"attempt": attempt, "rounds": 0, "nfev": 0}
        res = failure("optimisation not run", t0)
        for rnd in range(s.penalty_rounds):
            problem.set_penalty_scale(scale)
            nfev = 0
            while nfev < s.max_nfev:
                if time.perf_counter() > deadline:
                    return failure("timeout before the optimisation converged", t0, Failure.TIMEOUT)
                chunk = min(25, s.max_nfev - nfev)
                sol = least_squares(problem.fun, x, jac=problem.jac, method="lm", max_nfev=chunk, ftol=s.ftol,
                                    xtol=s.xtol, gtol=1e-10)
                x = sol.x
                nfev += sol.nfev
                if sol.status != 0:  # converged (0: this chunk's evaluation budget used up)
                    break
            viol = problem.violations(x)
            self.last_info = {"attempt": attempt, "rounds": rnd + 1, "nfev": self.last_info["nfev"] + nfev, **viol}
            log.debug("trajopt attempt %d round %d: nfev %d, violations %s", attempt, rnd, nfev, viol)
            res = self._accept(problem.full_path(x), goal, goal_u, t0)
            if res.success:
                return res
            grow = [viol["limits"] >= 1e-6, viol["collision"] >= 1e-6, viol["lateral"] >= 0.1 * s.lateral_tolerance,
                    viol["goal"] >= 0.1 * s.goal_tolerance]
            if not any(grow):
                break
            scale = scale * np.where(grow, s.penalty_growth, 1.0)
        return res

    def _accept(self, Q: np.ndarray, goal: np.ndarray, goal_u: np.ndarray, t0: float):
        s, r = self.settings, self.robot
        err = np.abs(Q[-1] - goal_u)
        if err.max() > s.goal_tolerance:
            return failure(f"optimisation did not reach the goal (max joint error {err.max():.3f})", t0)
        Q = Q.copy()
        Q[-1] = goal_u  # snap the last waypoint onto the goal
        Q[:, r.base_dof:] = np.clip(Q[:, r.base_dof:], self.lo[r.base_dof:], self.hi[r.base_dof:])
        if r.mobile:  # round-off at the workspace border
            Q[:, :2] = np.clip(Q[:, :2], self.lo[:2], self.hi[:2])
        if r.mobile:
            lat = np.abs(arc_segments(Q[:-1], Q[1:], self.w_rot)["lateral"])
            if lat.max() > s.lateral_tolerance:
                return failure(f"path needs sideways base motion (max {lat.max():.3f} m per segment; the "
                               "differential-drive constraint is violated)", t0)
            Q[:, 2] = wrap_angle(Q[:, 2])
        Q[-1] = goal
        res = self.ctx.execute(Q, t0=t0)
        if not res.success:
            res.reason = f"optimised path rejected: {res.reason}"
            return res
        if s.view_tolerance_deg >= 0:
            ang = float(np.degrees(view_angles(r, res.dense, self.focus).mean()))
            if ang > s.view_tolerance_deg:
                return failure(f"mean view angle {ang:.1f} deg above {s.view_tolerance_deg} deg", t0)
        return res

    # ---- per-configuration terms (collision per body, view angle) --------------------------------------------------
    def box_signed_distance(self, points: torch.Tensor, box: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Signed distance of points (n, 3) to every scene box (n, K), or to the paired boxes ``box`` (n,) -> (n,).

        ``sd = ||max(|l| - h, 0)|| + min(max_i(|l_i| - h_i), 0)`` with ``l`` the point in the box frame and ``h`` the
        half extents (exact inside and outside)."""
        if box is None:
            K = self._box_c.shape[0]
            Rcat = self._box_R.transpose(0, 1).reshape(3, 3 * K)
            off = (self._box_c.unsqueeze(1) @ self._box_R).reshape(3 * K)
            local = (points @ Rcat - off).reshape(-1, K, 3)
            h = self._box_h
        else:
            local = ((points - self._box_c[box]).unsqueeze(-2) @ self._box_R[box]).squeeze(-2)
            h = self._box_h[box]
        d = local.abs() - h
        return d.clamp_min(0).norm(dim=-1) + d.amax(-1).clamp_max(0)

    def view_angle_of(self, cams: torch.Tensor) -> torch.Tensor:
        """Angle (rad) between the optical axis and the direction to the focus, for camera poses (B, 4, 4)."""
        dvec = self._focus_t - cams[:, :3, 3]
        z = cams[:, :3, 2]
        return torch.atan2(torch.linalg.cross(z, dvec).norm(dim=-1), (z * dvec).sum(-1))

    def config_terms(self, Q: torch.Tensor, jacobian: bool = False, eps: float = 1e-6,
                     cols: Optional[np.ndarray] = None):
        """Per-configuration residual terms for configurations Q (B, dof), float64.

        Columns: for every rigid body with collision spheres ``sqrt(sum hinge^2)`` over its spheres and the scene
        boxes, ``hinge = max(0, margin + r - sd(c, box))``; then the view angle (rad). With ``jacobian`` also the
        forward-difference Jacobian (B, len(cols), n_terms) over the joints ``cols`` (default: all); only sphere/box
        pairs within 1 mm of their hinge's support at ``Q`` are re-evaluated for the perturbations (the others stay
        exactly zero).
        """
        r = self.robot
        B, dof = Q.shape
        G = self._n_groups
        cols = np.arange(dof) if cols is None else np.asarray(cols)
        P = Q.unsqueeze(1).repeat(1, len(cols) + 1 if jacobian else 1, 1)
        if jacobian:
            P[:, 1:, cols] += eps * torch.eye(len(cols), dtype=Q.dtype)
        V = P.shape[1]
        Pf = P.reshape(-1, dof)
        R, t = r.body_poses(Pf)
        ang = self.view_angle_of(r.camera_poses(Pf, (R, t))).reshape(B, V)
        coll = torch.zeros(B, V, G, dtype=Q.dtype)
        if self._box_c.shape[0]:
            R = R.reshape(B, V, *R.shape[1:])
            t = t.reshape(B, V, *t.shape[1:])
            margin = self.settings.margin
            slack = 1e-3 if jacobian else 0.0
            # broad phase: group bounding spheres against the boxes at the unperturbed configurations
            gb = self._grp_body
            cg = (R[:, 0][:, gb] @ self._grp_c.unsqueeze(-1)).squeeze(-1) + t[:, 0][:, gb]  # (B, G, 3)
            sdg = self.box_signed_distance(cg.reshape(-1, 3)).reshape(B, G, -1)
            e_g, g_g, k_g = torch.nonzero(sdg < self._grp_r[None, :, None] + margin + slack, as_tuple=True)
            if len(e_g):
                cnt = self._grp_count[g_g]
                rows = torch.repeat_interleave(torch.arange(len(g_g)), cnt)
                off = torch.arange(len(rows)) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
                s_i = self._grp_order[self._grp_start[g_g][rows] + off]
                e_i, k_i = e_g[rows], k_g[rows]
                # narrow phase at the unperturbed configurations, then the perturbations of the active pairs
                b_i = self._sphere_body[s_i]
                c0 = (R[e_i, 0, b_i] @ self._sphere_c[s_i].unsqueeze(-1)).squeeze(-1) + t[e_i, 0, b_i]
                act = margin + self._radii[s_i] - self.box_signed_distance(c0, k_i) > -slack
                e_i, s_i, k_i, b_i = e_i[act], s_i[act], k_i[act], b_i[act]
            else:
                e_i = torch.zeros(0, dtype=torch.long)
            if len(e_i):
                Rs, ts = R[e_i, :, b_i], t[e_i, :, b_i]  # (n, V, 3, 3), (n, V, 3)
                Cp = (Rs @ self._sphere_c[s_i][:, None, :, None]).squeeze(-1) + ts  # (n, V, 3)
                sd = self.box_signed_distance(Cp.reshape(-1, 3), k_i.repeat_interleave(V)).reshape(-1, V)
                h = (margin + self._radii[s_i][:, None] - sd).clamp_min(0)
                idx = e_i * G + self._sphere_group[s_i]
                coll = torch.zeros(B * G, V, dtype=Q.dtype).index_add_(0, idx, h * h)
                coll = coll.reshape(B, G, V).transpose(1, 2)
        F = torch.cat([coll.sqrt(), ang.unsqueeze(-1)], -1)  # (B, V, G + 1)
        if not jacobian:
            return F[:, 0]
        return F[:, 0], (F[:, 1:] - F[:, :1]) / eps
