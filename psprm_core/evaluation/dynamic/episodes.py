"""What the dynamic episodes share (:mod:`.simulation`, :mod:`.hindsight`, :mod:`.dynamic_bench`): a trajectory
executed unchanged on the control clock, the executed configurations in collision with the world as it was at each
instant, the oracle's verdict on the camera frames (cached within an episode), speed ratios by finite differences, and
strict JSON (no NaN)."""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np
import torch

from ...collision import CollisionChecker
from ..scenario_world import World, at_goal


def wrap_heading(q: np.ndarray, robot) -> np.ndarray:
    """``q`` (dof,) or (N, dof) with a mobile base's heading wrapped into [-pi, pi)."""
    q = np.array(q, float)
    if robot.mobile:
        q[..., 2] = (q[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return q


def frame_every(scenario) -> int:
    """Control steps between two camera frames (the frames lie on the control clock, so every mode of an episode
    judges the same instants)."""
    return max(1, int(round(1.0 / (scenario.camera_fps * scenario.control_dt))))


def execute_fixed(traj, scenario, world: World, robot, t_end: Optional[float] = None,
                  start: Optional[np.ndarray] = None) -> dict:
    """A trajectory executed unchanged from t = 0 on the control clock (``control_dt``) until it ends (or
    ``duration_s``): the record of a static plan or a hindsight route. Reached: its last configuration at one of
    the goals valid at that time (:func:`~..scenario_world.at_goal`) with the trajectory finished. Without a trajectory
    (no plan) the robot stays at ``start``."""
    dt = scenario.control_dt
    T = float(traj.duration) if traj is not None else 0.0
    limit = scenario.duration_s if t_end is None else t_end
    n = int(min(math.ceil(T / dt - 1e-9), math.floor(limit / dt + 1e-9)))
    steps = np.arange(n + 1)
    times = np.round(steps * dt, 9)
    if traj is None:
        executed = np.zeros((1, robot.dof)) if start is None else np.asarray(start, float)[None].copy()
        return {"times": np.zeros(1), "executed": executed, "reached_goal": False, "arrival_s": None}
    executed = wrap_heading(traj.evaluate(times)[0], robot)
    done = times[-1] >= T - 1e-9
    reached = bool(done and at_goal(executed[-1], world.scene0, world.goal_specs(times[-1]), scenario.goal_tolerance))
    return {"times": times, "executed": executed, "reached_goal": reached,
            "arrival_s": float(times[-1]) if reached else None}


def frames_of(record: dict, scenario) -> tuple:
    """(frame times, frame configurations) of an executed record: every :func:`frame_every`-th control step."""
    k = frame_every(scenario)
    idx = np.arange(0, len(record["times"]), k)
    return record["times"][idx], record["executed"][idx]


def count_collisions(robot, world: World, times: np.ndarray, executed: np.ndarray) -> np.ndarray:
    """(N,) flags: executed configuration i in collision with the scenario's boxes (obstacles, and targets that are
    obstacles) posed as the world has them at ``times[i]``, moving ones included, or outside the workspace; the
    boxes as they are (no planning padding), checked with the planner's box model. Self-collision and joint limits
    are not the world's: :func:`count_self_collisions`."""
    moving = set(world.poses(0.0)["targets"]) | set(world.poses(0.0)["obstacles"])
    fixed = [b for b in world.scene0.collision_boxes() if b.name not in moving]
    checker = CollisionChecker(robot, fixed, workspace=world.scene0.workspace)
    q = torch.as_tensor(np.asarray(executed), dtype=torch.float32)
    out = checker.env_hits(q, checker.boxes).numpy().copy() if len(fixed) else np.zeros(len(q), bool)
    if robot.mobile:
        lo, hi = np.asarray(world.scene0.workspace, float).T
        xy = np.asarray(executed, float)[:, :2]
        out |= ((xy < lo) | (xy > hi)).any(1)
    for i, t in enumerate(times):  # the moving boxes at each instant (the fixed ones were checked above)
        scene = world.scene_at(float(t))
        boxes = [b for b in scene.collision_boxes() if b.name in moving]
        if boxes:
            out[i] |= bool(checker.env_hits(q[i:i + 1], boxes)[0])
    return out


def count_self_collisions(robot, executed: np.ndarray) -> np.ndarray:
    """(N,) flags: executed configuration i outside a joint limit or in self-collision under the planner's box model
    (conservative: pybullet's exact meshes may find it free)."""
    det = CollisionChecker(robot, []).check_detailed(torch.as_tensor(np.asarray(executed), dtype=torch.float32))
    return (det["limits"] | det["self"]).numpy()


def speed_ratio(times: np.ndarray, executed: np.ndarray, robot) -> float:
    """Largest speed between consecutive executed configurations (finite differences over the control steps) as a
    fraction of the robot's limits: the base's (x, y) speed against its linear limit, its heading and every other
    joint against their own. Above 1: the executed motion jumped."""
    if len(times) < 2:
        return 0.0
    dt = np.diff(times)[:, None]
    d = np.diff(np.asarray(executed, float), axis=0)
    vmax = np.asarray(robot.velocity, float)
    if robot.mobile:
        d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
        lin = np.hypot(d[:, 0], d[:, 1]) / dt[:, 0] / vmax[0]
        rest = np.abs(d[:, 2:]) / dt / vmax[2:]
        return float(max(lin.max(), rest.max()))
    return float((np.abs(d) / dt / vmax).max())


class FrameJudge:
    """The oracle's verdict on the camera frames of one episode's world (the real detector on rendered views, as
    ``judge_frames``): each frame judged with the world as it was at that instant, per target. Cached by (instant,
    configuration): frames that several modes share (the start, the first plan up to the first replan, a static plan
    that is also a hindsight route) are rendered once.

    The oracle may have judged another scenario of the same scene before (a worker keeps one per scene): every
    target and obstacle is put back where the scene file has it first, so that only this world's moves are seen."""

    def __init__(self, oracle, robot, world: World, targets: Sequence[str]):
        self.oracle, self.robot, self.world, self.targets = oracle, robot, world, list(targets)
        self._cache: dict = {}
        self.rendered = 0  # frames judged (not taken from the cache)
        for t in world.scene0.targets:
            oracle.set_target_pose(t.name, t.center, t.quat)
        for b in world.scene0.obstacles:
            oracle.set_obstacle_pose(b.name, b.center, b.quat)

    def judge(self, times: np.ndarray, qs: np.ndarray) -> tuple:
        """(detected (F, T) bool, confidence (F, T)) of frames at ``times`` (F,) from configurations ``qs``
        (F, dof), T the targets."""
        F, T = len(times), len(self.targets)
        det, conf = np.zeros((F, T), bool), np.zeros((F, T))
        keys = [(round(float(t), 6), np.round(np.asarray(q, float), 6).tobytes()) for t, q in zip(times, qs)]
        todo = [i for i, k in enumerate(keys) if k not in self._cache]
        if todo:
            cams = self.robot.camera_poses(torch.as_tensor(np.asarray(qs)[todo], dtype=torch.float64)).numpy()
            for i, cam in zip(todo, cams):
                poses = self.world.poses(float(times[i]))
                for name, (c, q) in poses["targets"].items():
                    self.oracle.set_target_pose(name, c, q)
                for name, (c, q) in poses["obstacles"].items():
                    self.oracle.set_obstacle_pose(name, c, q)
                res = [self.oracle.score(cam, tg, keep_image=False) for tg in self.targets]
                self._cache[keys[i]] = (np.array([r.detected for r in res]), np.array([r.score for r in res]))
                self.rendered += 1
        for i, k in enumerate(keys):
            det[i], conf[i] = self._cache[k]
        return det, conf


def judge_record(record: dict, judge: FrameJudge, scenario) -> None:
    """Adds the frames of an executed record and the oracle's verdict on them: ``frames_t``, ``frames_q``,
    ``detected`` (F, T), ``confidence`` (F, T)."""
    ft, fq = frames_of(record, scenario)
    record["frames_t"], record["frames_q"] = ft, fq
    record["detected"], record["confidence"] = judge.judge(ft, fq)


def detection_metrics(record: dict) -> dict:
    """Detection rate (frames and targets: the bench's ``det_rate``), the share of frames where any / every target
    is detected, and the mean confidence; None without judged frames."""
    det = record.get("detected")
    if det is None or len(det) == 0:
        return {"det_rate": None, "det_rate_any": None, "det_rate_all": None, "mean_confidence": None}
    return {"det_rate": float(det.mean()), "det_rate_any": float(det.any(1).mean()),
            "det_rate_all": float(det.all(1).mean()), "mean_confidence": float(record["confidence"].mean())}


def json_safe(v):
    """``v`` with every NaN / inf float replaced by None and numpy scalars and arrays made plain, recursively: what
    ``json.dumps(..., allow_nan=False)`` accepts (strict JSON)."""
    if isinstance(v, dict):
        return {str(k): json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_safe(x) for x in v]
    if isinstance(v, np.ndarray):
        return json_safe(v.tolist())
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer, int)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(float(v)) else None
    return v
