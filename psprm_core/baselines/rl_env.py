"""Gymnasium environment of the RL baseline (Baseline 6, goal-conditioned active perception trained with PPO).

One episode drives the robot from a start to a goal configuration in a fixed scene while a target (or the centroid of
several targets) should stay well perceived.

Action (``Box(-1, 1, 2 + n_camera_joints)``)
    ``a[0]``: forward base motion (x ``step_forward`` metres, negative = reverse), ``a[1]``: base turn
    (x ``step_turn`` rad), ``a[2:]``: changes of the non-base joints that move the camera (x ``step_joint``; Stretch's
    head pan and tilt), clipped to their limits. One step is a differential-drive motion: turn by half the turn,
    drive, turn by the other half. Joints that neither move the camera nor are actions (arm, lift, ...) move towards
    their goal values at their velocity limit.
Observation (float32, clipped to +-10)
    the configuration (base x, y normalised to the workspace, sin/cos of the heading, joints normalised to their
    limits), the goal in the same form plus its position and heading relative to the base frame, the target position
    (world, normalised) and its direction and distance in the camera frame, and the episode progress ``t / max_steps``.
    Optional (``goal_bearing``): the goal position relative to the base again in polar form, the sine and cosine
    of its bearing from the base heading and its (scaled) distance, so that "turn towards the goal" is a linear
    function of the observation.
    Optional (``scan_beams > 0``; not part of the base observation, off by default): a horizontal range scan of
    the scene boxes from the base (``scan_beams`` rays, ranges / ``scan_range``) and whether the last action was
    rejected (with ``streak_cap > 0``: the number of consecutive rejected actions / ``streak_cap``, at most 1, so
    that a deterministic policy that keeps driving into an obstacle sees a changing observation).
Reward (per step)
    ``w_perception * (p(q') - perception_offset)`` (geometric perception proxy of the new camera pose in [0, 1],
    :class:`~psprm_core.perception.scoring.GeometricScorer` with ray-cast occlusion; offset 0 by default, 1 turns it
    into the paper's perception cost ``-(1 - p)``, which also stops rewarding long episodes)
    ``- w_motion * c_m(q, q')`` (differential-drive motion cost of the step, :mod:`psprm_core.motion`)
    ``+ w_progress * (d(q) - d(q'))`` (goal progress; d = base distance to the goal: straight-line with
    ``progress_metric: euclidean``, or with ``geodesic`` the shortest 8-connected path on a ``geodesic_cell`` grid
    of the base positions where the robot fits at some heading, which does not reward driving into the furniture
    between start and goal), plus with ``w_heading > 0`` that many metres per radian between the base heading and
    the direction to the goal position (faded out within 0.5 m of it), so that turning towards the goal pays at once
    ``- collision_penalty`` when the step is rejected, ``+ goal_bonus`` when the goal is reached.
Invalid actions
    a step whose motion collides (environment, self, limits or workspace; checked every ``resolution`` along the
    motion with :class:`~psprm_core.collision.CollisionChecker`) is rejected: the state does not change and the step
    earns the collision penalty.
Curriculum (optional, ``curriculum_steps > 0``)
    during the first ``curriculum_steps`` environment steps a random training episode whose start is farther from
    its goal than ``curriculum_start`` + (workspace diagonal - ``curriculum_start``) x steps / ``curriculum_steps``
    starts instead from a pool configuration within that distance (short problems first).
Termination
    the goal counts as reached when the base is within ``goal_tolerance`` of the goal position and the final
    differential-drive motion to the exact goal configuration is collision-free (it is then executed); episodes are
    truncated after ``max_steps`` steps.
"""

from __future__ import annotations

import logging
import math
from typing import Optional, Sequence

import gymnasium as gym
import numpy as np
import torch

from ..errors import InputError
from ..geometry import wrap_angle
from ..kernels.compute import bulk
from ..planning.factory import make_scorer
from ..problems import random_problems
from .base import PlanningContext
from .rl_settings import PPOSettings

log = logging.getLogger(__name__)

#: Version of the environment's dynamics, observation and reward; part of the policy cache key (a policy trained on
#: an older environment is not reused).
ENV_VERSION = 2



class ActivePerceptionEnv(gym.Env):
    """Goal-conditioned active-perception environment for one scene, robot and target set (see the module docstring).

    Parameters
    ----------
    scene : Scene
    targets : sequence of str
    robot : RobotModel, optional
    settings : PPOSettings, optional (:mod:`psprm_core.baselines.rl_ppo`; step sizes, reward weights, episode length)
    problems : list of (start, goal), optional
        Episodes draw their start and goal from this pool (default: ``settings.problems`` random collision-free
        pairs from :func:`psprm_core.problems.random_problems`, camera joints aimed at the target).
    seed : int
    """

    metadata = {"render_modes": []}

    def __init__(self, scene, targets: Sequence[str], robot=None, settings=None, problems: Optional[list] = None,
                 seed: int = 0, context=None):
        super().__init__()
        self.settings = settings if settings is not None else PPOSettings()
        s = self.settings
        self.ctx = context or PlanningContext(scene, targets, robot=robot, resolution=s.resolution)
        self.scene, self.robot = scene, self.ctx.robot
        r = self.robot
        if not r.mobile:
            raise InputError(f"the RL baseline needs a differential-drive robot ('{r.name}' has a fixed base)")
        self.targets = list(targets)
        # the score's occlusion check follows the robot model's Compute, as the context's checker and metric do
        self.scorer = make_scorer("geometric", scene, self.targets, r.config.intrinsics).using(r.compute)
        self.focus = self.ctx.focus
        self.w_rot = r.config.base.rotation_weight
        self.act_cols = self.ctx.aim_cols  # non-base camera joints, driven by actions
        others = np.ones(r.dof, dtype=bool)
        others[:3] = False
        others[self.act_cols] = False
        self.auto_cols = np.nonzero(others)[0]  # joints that move towards their goal values by themselves
        self.dt = s.step_forward / r.config.base.linear_velocity  # duration of one step at full speed (s)
        lo, hi = self.ctx.lower.copy(), self.ctx.upper.copy()
        self.lo, self.hi = lo, hi
        self._jlo, self._jhi = lo[3:], hi[3:]
        ws = np.asarray(scene.workspace, float)
        self._ws_c, self._ws_h = ws.mean(1), np.maximum(0.5 * (ws[:, 1] - ws[:, 0]), 1e-6)
        self._scale = float(np.linalg.norm(ws[:, 1] - ws[:, 0]))
        n_act = 2 + len(self.act_cols)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(n_act,), dtype=np.float32)
        n_q = 4 + (r.dof - 3)
        n_obs = 2 * n_q + 4 + 3 + 4 + 1
        if s.goal_bearing:  # optional: the goal's direction and distance from the base in polar form
            n_obs += 3
        if s.scan_beams > 0:  # optional obstacle awareness: range scan + "last action rejected"
            n_obs += s.scan_beams + 1
            boxes = scene.collision_boxes()
            self._box_c = np.array([b.center for b in boxes], float).reshape(-1, 3)
            self._box_R = np.array([b.rotation for b in boxes], float).reshape(-1, 3, 3)
            self._box_h = np.array([b.half_extents for b in boxes], float).reshape(-1, 3)
            self._beams = 2 * np.pi * np.arange(s.scan_beams) / s.scan_beams
        self.observation_space = gym.spaces.Box(-10.0, 10.0, shape=(n_obs,), dtype=np.float32)
        self._rng = np.random.default_rng(seed)
        self._problems = problems
        self._seed = seed
        self.q = r.default_configuration()
        self.goal = self.q.copy()
        self.t = 0
        self.path: list = []
        self.last_rejected = False
        self.rejected_streak = 0  # consecutive rejected actions
        self._cam_key, self._cam = None, None
        self._grid_cache: Optional[tuple] = None
        self._pool: Optional[np.ndarray] = None  # every start and goal of the problem pool (curriculum)
        self.total_steps = 0  # environment steps over all episodes (curriculum)
        self._fields: dict = {}

    # ---- goal distance for the progress reward -------------------------------------------------------------------
    def _grid(self) -> tuple:
        """Base-position grid of the workspace (cell centres (nx, ny, 2), free (nx, ny): the robot in its default
        joint configuration fits at one of 8 headings) and the 8-connected edges (rows, cols, lengths) between free cells
        (built once)."""
        if self._grid_cache is None:
            h = self.settings.geodesic_cell
            ws = np.asarray(self.scene.workspace, float)
            xs = np.arange(ws[0, 0] + 0.5 * h, ws[0, 1], h)
            ys = np.arange(ws[1, 0] + 0.5 * h, ws[1, 1], h)
            X, Y = np.meshgrid(xs, ys, indexing="ij")
            heads = np.linspace(-np.pi, np.pi, 8, endpoint=False)
            q = np.tile(self.robot.default_configuration(), (X.size * len(heads), 1))
            q[:, 0] = np.repeat(X.ravel(), len(heads))
            q[:, 1] = np.repeat(Y.ravel(), len(heads))
            q[:, 2] = np.tile(heads, X.size)
            with bulk(1):
                free = self.ctx.valid(q).reshape(X.shape + (len(heads),)).any(-1)
            nx, ny = X.shape
            idx = np.arange(nx * ny).reshape(nx, ny)
            rows, cols, w = [], [], []
            for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
                a = idx[max(0, -dx):nx - max(0, dx), max(0, -dy):ny - max(0, dy)]
                b = idx[max(0, dx):nx - max(0, -dx) or None, max(0, dy):ny - max(0, -dy) or None]
                a, b = a.ravel(), b.ravel()
                ok = free.ravel()[a] & free.ravel()[b]
                rows.append(a[ok])
                cols.append(b[ok])
                w.append(np.full(int(ok.sum()), h * math.hypot(dx, dy)))
            r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
            graph = (np.concatenate([r, c]), np.concatenate([c, r]), np.concatenate([w, w]))  # both directions
            self._grid_cache = (np.stack([X, Y], -1), free, graph)
        return self._grid_cache

    def _near_cells(self, xy: np.ndarray, k: int = 2) -> tuple:
        """Indices (i, j) of the grid cells within ``k`` cells of position ``xy``."""
        centres = self._grid()[0]
        h = self.settings.geodesic_cell
        nx, ny = centres.shape[:2]
        ws = np.asarray(self.scene.workspace, float)
        i0 = int(np.clip((xy[0] - ws[0, 0]) // h, 0, nx - 1))
        j0 = int(np.clip((xy[1] - ws[1, 0]) // h, 0, ny - 1))
        ii, jj = np.meshgrid(np.arange(max(0, i0 - k), min(nx, i0 + k + 1)),
                             np.arange(max(0, j0 - k), min(ny, j0 + k + 1)), indexing="ij")
        return ii.ravel(), jj.ravel()

    def _distance_field(self) -> Optional[np.ndarray]:
        """Geodesic distances (nx, ny) of the grid cells to the current goal (inf: unreachable), or None when no
        free cell is near the goal (the progress then uses the straight-line distance)."""
        key = self.goal[:2].tobytes()
        if key in self._fields:
            return self._fields[key]
        from scipy.sparse.csgraph import dijkstra

        centres, free, graph = self._grid()
        ii, jj = self._near_cells(self.goal[:2])
        ok = free[ii, jj]
        field = None
        if ok.any():  # a virtual source node linked to the free cells near the goal by their straight distance
            from scipy.sparse import coo_matrix

            ii, jj = ii[ok], jj[ok]
            off = np.linalg.norm(centres[ii, jj] - self.goal[:2], axis=-1)
            r, c, w = graph
            n = free.size
            g = coo_matrix((np.concatenate([w, off]),
                            (np.concatenate([r, np.full(len(off), n)]),
                             np.concatenate([c, np.ravel_multi_index((ii, jj), free.shape)]))),
                           shape=(n + 1, n + 1)).tocsr()
            field = dijkstra(g, indices=n)[:n].reshape(free.shape)
        if len(self._fields) > 1024:
            self._fields.clear()
        self._fields[key] = field
        return field

    def progress_distance(self, q: np.ndarray) -> float:
        """The goal distance d of the progress reward (``progress_metric``): straight-line, or geodesic on the
        grid (the shortest field value plus straight-line offset over the free cells within 2 cells of ``q``; the
        straight-line distance within 2 cells of the goal or where no free cell is near)."""
        s = self.settings
        e = self.goal_distance(q)
        m = e
        field = self._distance_field() if s.progress_metric == "geodesic" else None
        if field is not None:
            ii, jj = self._near_cells(q[:2])
            v = float((field[ii, jj] + np.linalg.norm(self._grid()[0][ii, jj] - q[:2], axis=-1)).min())
            if e <= 2.0 * s.geodesic_cell:  # next to the goal: straight to it (0 at the goal)
                v = min(v, e)
            m = v if math.isfinite(v) else e
        if s.w_heading > 0.0 and e > 1e-9:  # turning towards the goal counts as progress (faded out near it)
            d = self.goal[:2] - q[:2]
            m += s.w_heading * abs(wrap_angle(math.atan2(d[1], d[0]) - q[2])) * min(1.0, e / 0.5)
        return m

    # ---- problems ----------------------------------------------------------------------------------------------------
    @property
    def problems(self) -> list:
        """The pool of (start, goal) pairs episodes are drawn from (generated on first use)."""
        if self._problems is None:
            s = self.settings
            rng = np.random.default_rng(self._seed + 7919)
            self._problems = random_problems(self.robot, self.scene, self.ctx.checker, s.problems, rng,
                                             self.robot.default_configuration(), self.focus,
                                             min_distance=s.min_problem_distance)
        return self._problems

    # ---- observation ------------------------------------------------------------------------------------------------
    def _qfeat(self, q: np.ndarray) -> np.ndarray:
        xy = (q[:2] - self._ws_c) / self._ws_h
        j = 2.0 * (q[3:] - self._jlo) / np.maximum(self._jhi - self._jlo, 1e-6) - 1.0
        return np.concatenate([xy, [math.sin(q[2]), math.cos(q[2])], j])

    def _obs(self) -> np.ndarray:
        q, g = self.q, self.goal
        c, s_ = math.cos(q[2]), math.sin(q[2])
        d = g[:2] - q[:2]
        rel = np.array([c * d[0] + s_ * d[1], -s_ * d[0] + c * d[1]]) / self._scale * 4.0
        dth = g[2] - q[2]
        cam = self.camera(q)
        pc = cam[:3, :3].T @ (self.focus - cam[:3, 3])
        dist = float(np.linalg.norm(pc))
        tgt = np.concatenate([(self.focus[:2] - self._ws_c) / self._ws_h, [self.focus[2]]])
        o = np.concatenate([self._qfeat(q), self._qfeat(g), rel, [math.sin(dth), math.cos(dth)], tgt,
                            pc / max(dist, 1e-6), [dist / self._scale * 4.0], [self.t / self.settings.max_steps]])
        if self.settings.goal_bearing:
            r = float(np.hypot(rel[0], rel[1]))
            o = np.concatenate([o, [rel[1] / r, rel[0] / r] if r > 1e-9 else [0.0, 1.0], [min(r, 4.0)]])
        if self.settings.scan_beams > 0:
            flag = min(self.rejected_streak, self.settings.streak_cap) / self.settings.streak_cap \
                if self.settings.streak_cap > 0 else float(self.last_rejected)
            o = np.concatenate([o, self.scan(q) / self.settings.scan_range, [flag]])
        return np.clip(o, -10.0, 10.0).astype(np.float32)

    def scan(self, q: np.ndarray) -> np.ndarray:
        """Ranges (m, at most ``scan_range``) from the base centre to the scene boxes along ``scan_beams`` horizontal
        rays at ``scan_height``, evenly spaced from the base heading (a laser scanner; slab ray/box intersection)."""
        s = self.settings
        ang = q[2] + self._beams
        d = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)  # (n, 3)
        o = np.array([q[0], q[1], s.scan_height])
        o_l = np.einsum("kji,kj->ki", self._box_R, o - self._box_c)  # (K, 3) origin in the box frames
        d_l = np.einsum("kji,nj->kni", self._box_R, d)  # (K, n, 3)
        d_l = np.where(np.abs(d_l) < 1e-12, 1e-12, d_l)
        t1 = (-self._box_h[:, None] - o_l[:, None]) / d_l
        t2 = (self._box_h[:, None] - o_l[:, None]) / d_l
        t_in, t_out = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
        hit = t_out >= np.maximum(t_in, 0.0)
        r = np.where(hit, np.maximum(t_in, 0.0), np.inf).min(0) if len(self._box_c) else np.full(len(ang), np.inf)
        return np.minimum(r, s.scan_range)

    # ---- motion -----------------------------------------------------------------------------------------------------
    def propose(self, q: np.ndarray, action: np.ndarray) -> np.ndarray:
        """The configuration one step of ``action`` leads to (before validity checks)."""
        s = self.settings
        a = np.clip(np.asarray(action, float).reshape(-1), -1.0, 1.0)
        f, tau = a[0] * s.step_forward, a[1] * s.step_turn
        qn = q.copy()
        h = q[2] + 0.5 * tau
        qn[0] += f * math.cos(h)
        qn[1] += f * math.sin(h)
        qn[2] = wrap_angle(q[2] + tau)
        if len(self.act_cols):
            qn[self.act_cols] = np.clip(q[self.act_cols] + a[2:] * s.step_joint, self.lo[self.act_cols],
                                        self.hi[self.act_cols])
        if len(self.auto_cols):
            vmax = self.robot.velocity[self.auto_cols] * self.dt
            qn[self.auto_cols] = q[self.auto_cols] + np.clip(self.goal[self.auto_cols] - q[self.auto_cols], -vmax, vmax)
        return qn

    def step_cost(self, qa: np.ndarray, qb: np.ndarray) -> float:
        """Differential-drive motion cost of one step (:class:`~psprm_core.motion.DiffDriveMotion`)."""
        m = self.ctx.motion
        qa, qb = np.asarray(qa, np.float64)[None], np.asarray(qb, np.float64)[None]
        return float(m.compute.ops.metric_arrays(m, qa, qb)[0])

    def motion_points(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """The configurations checked along the differential-drive motion qa -> qb: every ``resolution`` after
        ``qa``, ``qb`` included (:meth:`PlanningContext.densify` without its first row)."""
        return self.ctx.densify(np.vstack([qa, qb]))[1:]

    def motion_valid(self, qa: np.ndarray, qb: np.ndarray) -> bool:
        """Is the differential-drive motion qa -> qb (end included) collision-free and within the limits?

        Checked every ``resolution`` along the motion with the scene's
        :class:`~psprm_core.collision.CollisionChecker` (its compiled small-batch check when numba is available)."""
        return bool(self.ctx.valid(self.motion_points(qa, qb)).all())

    def goal_distance(self, q: np.ndarray) -> float:
        return float(np.linalg.norm(q[:2] - self.goal[:2]))

    def camera(self, q: np.ndarray) -> np.ndarray:
        """Camera optical-frame pose (4, 4) of configuration ``q`` (the last one is cached: a step scores the new
        configuration and then observes it)."""
        key = q.tobytes()
        if self._cam_key != key:
            qt = torch.as_tensor(q[None], dtype=torch.float64)
            self._cam = self.robot.camera_poses(qt)[0].numpy()
            self._cam_key = key
        return self._cam

    def score(self, q: np.ndarray) -> float:
        """Geometric perception proxy of configuration ``q`` in [0, 1] (:class:`GeometricScorer`: distance and
        viewing-angle terms inside the camera frustum, 0 when the target is occluded), of one pose with numpy."""
        return self.scorer.score_pose(self.camera(q))

    def curriculum_distance(self) -> float:
        """The largest start-goal distance (m) of a training episode now: ``curriculum_start`` at the first step,
        growing linearly with the environment steps taken to no limit (inf) after ``curriculum_steps``."""
        s = self.settings
        if s.curriculum_steps <= 0 or self.total_steps >= s.curriculum_steps:
            return math.inf
        return s.curriculum_start + (self._scale - s.curriculum_start) * self.total_steps / s.curriculum_steps

    def _curriculum_start(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The start for goal ``b``: ``a``, or during the curriculum, when ``a`` is too far from ``b``, a random
        pool configuration within the current :meth:`curriculum_distance` of ``b`` (``a`` if there is none)."""
        dmax = self.curriculum_distance()
        if np.linalg.norm(a[:2] - b[:2]) <= dmax:
            return a
        if self._pool is None:
            self._pool = np.array([q for pair in self.problems for q in pair], float)
        d = np.linalg.norm(self._pool[:, :2] - b[:2], axis=1)
        near = np.nonzero((d <= dmax) & (d >= self.settings.goal_tolerance + 0.1))[0]
        return self._pool[self._rng.choice(near)] if len(near) else a

    # ---- gymnasium API ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Start an episode: ``options={"start": q, "goal": q}`` for a given problem, else a random pool problem."""
        super().reset(seed=seed)
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        if options and "start" in options:
            self.q = np.asarray(options["start"], float).reshape(-1).copy()
            self.goal = np.asarray(options["goal"], float).reshape(-1).copy()
        else:
            a, b = self.problems[int(self._rng.integers(len(self.problems)))]
            if self._rng.random() < 0.5:
                a, b = b, a
            a = self._curriculum_start(a, b)
            self.q, self.goal = np.asarray(a, float).copy(), np.asarray(b, float).copy()
        self.q[2] = wrap_angle(self.q[2])
        self.t = 0
        self.path = [self.q.copy()]
        self.reached = False
        self.last_rejected = False
        self.rejected_streak = 0
        return self._obs(), {"goal_distance": self.goal_distance(self.q)}

    def step(self, action):
        s = self.settings
        self.t += 1
        self.total_steps += 1
        q = self.q
        qn = self.propose(q, action)
        info = {"rejected": False, "success": False}
        self.last_rejected = not self.motion_valid(q, qn)
        self.rejected_streak = self.rejected_streak + 1 if self.last_rejected else 0
        if self.last_rejected:
            info["rejected"] = True
            terms = {"perception": s.w_perception * (self.score(q) - s.perception_offset),
                     "collision": -s.collision_penalty}
            reward = float(sum(terms.values()))
        else:
            d0, d1 = self.progress_distance(q), self.progress_distance(qn)
            p = self.score(qn)
            terms = {"perception": s.w_perception * (p - s.perception_offset),
                     "motion": -s.w_motion * self.step_cost(q, qn),
                     "progress": s.w_progress * (d0 - d1)}
            self.q = qn
            self.path.append(qn.copy())
            if self.goal_distance(qn) <= s.goal_tolerance and self.motion_valid(qn, self.goal):
                self.q = self.goal.copy()
                self.path.append(self.q.copy())
                self.reached = True
                terms["goal"] = s.goal_bonus
                info["success"] = True
            reward = float(sum(terms.values()))
        info["terms"] = terms
        info["goal_distance"] = self.goal_distance(self.q)
        terminated = bool(self.reached)
        truncated = bool(self.t >= s.max_steps and not terminated)
        return self._obs(), float(reward), terminated, truncated, info
