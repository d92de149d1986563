"""Benchmarks that print numbers (``psprm perf ...``). Ratios are always measured in the same process and run."""

from __future__ import annotations

import logging
import math
import time
from typing import Callable

import numpy as np
import torch

log = logging.getLogger(__name__)


def best_time(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def rotation_angle_error(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (rad) of the relative rotation Ra^T Rb for stacks of rotations (..., 3, 3)."""
    rel = np.einsum("...ji,...jk->...ik", Ra, Rb)
    c = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    # arccos is ill-conditioned near 0: use the skew part for small angles
    skew = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), c)


def kinematics_benchmark(robot_name: str, scene_name: str, n: int = 10000, seed: int = 0, threads: int = 2,
                         fk_check: int = 1000) -> dict:
    """Batched torch FK and collision checking against pybullet's exact check on the same ``n`` configurations.

    Configurations are uniform within joint limits, with the base uniform over the scene's workspace.
    Returns throughputs, their ratio, missed collisions (torch free but pybullet in collision: must be 0),
    the false-positive rate (torch in collision but pybullet free, over pybullet-free configurations) and the FK
    agreement with pybullet on ``fk_check`` configurations.
    """
    from .collision import CollisionChecker
    from .paths import resolve_named
    from .reference import PybulletWorld, sample_uniform
    from .robot import RobotModel
    from .scene import load_scene

    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(robot_name)
    boxes = scene.collision_boxes()
    rng = np.random.default_rng(seed)
    qs = sample_uniform(robot, n, rng, base_box=scene.workspace)
    checker = CollisionChecker(robot, boxes, workspace=None)
    q32 = torch.as_tensor(qs, dtype=torch.float32)

    def fk():
        poses = robot.body_poses(q32)
        return robot.camera_poses(q32, poses)

    t_fk = best_time(fk)
    t_col = best_time(lambda: checker.check(q32))
    flags = checker.check(q32).numpy()
    world = PybulletWorld(robot, boxes)
    try:
        t0 = time.perf_counter()
        ref = world.in_collision(qs)
        t_pb = time.perf_counter() - t0
        m = min(fk_check, n)
        cam = robot.camera_poses(q32[:m]).double().numpy()
        ref_cam = np.stack([world.camera_pose(q) for q in qs[:m]])
    finally:
        world.close()
    pos_err = float(np.abs(cam[:, :3, 3] - ref_cam[:, :3, 3]).max())
    rot_err = float(rotation_angle_error(cam[:, :3, :3], ref_cam[:, :3, :3]).max())
    missed = int(np.sum(ref & ~flags))
    free = int(np.sum(~ref))
    fp = int(np.sum(flags & ~ref))
    return {
        "robot": robot.name, "scene": scene.name, "n": n, "threads": threads, "device": "cpu",
        "collision_elements": int(len(robot.elements.element_link)), "self_pairs": int(checker.self_pairs.shape[0]),
        "fk_per_s": n / t_fk,
        "collision_per_s": n / t_col,
        "pybullet_collision_per_s": n / t_pb,
        "speedup": t_pb / t_col,
        "missed_collisions": missed,
        "false_positive_rate": fp / free if free else math.nan,
        "in_collision_fraction": float(ref.mean()),
        "fk_max_position_error_m": pos_err,
        "fk_max_rotation_error_rad": rot_err,
    }


def random_problems(robot, scene, checker, n: int, rng: np.random.Generator, template: np.ndarray,
                    target_center: np.ndarray, min_distance: float = 1.0) -> list:
    """``n`` random collision-free (start, goal) pairs: base poses uniform over the workspace, the camera joints
    aimed at the target (projection onto the line-of-sight manifold with the non-base joints), others at
    ``template``; start and goal at least ``min_distance`` apart."""
    from .planning.constraints import ProjectionSettings, VisibilityConstraint
    from .planning.psprm import camera_joint_mask

    mask = camera_joint_mask(robot)
    mask[: robot.base_dof] = False
    cols = np.nonzero(mask)[0]
    con = VisibilityConstraint(robot, "line", target_center)
    out = []
    while len(out) < n:
        q = np.tile(template, (4 * n, 1))
        q[:, 0] = rng.uniform(*scene.workspace[0], 4 * n)
        q[:, 1] = rng.uniform(*scene.workspace[1], 4 * n)
        q[:, 2] = rng.uniform(-np.pi, np.pi, 4 * n)
        qt = torch.as_tensor(q, dtype=torch.float32)
        qt, _ = con.project(qt, ProjectionSettings(max_iters=10), joints=cols)
        qt = qt[checker.valid(qt)]
        qs = qt.double().numpy()
        for a, b in zip(qs[0::2], qs[1::2]):
            if np.linalg.norm(a[:2] - b[:2]) >= min_distance and len(out) < n:
                out.append((a, b))
    return out


def planner_benchmark(scene_name: str, planner: str = "neural-psprm-line", nodes: int = 3000, queries: int = 50,
                      seed: int = 0, threads: int = 2, target: str | None = None) -> dict:
    """Build time (sampling, projection, collision, neural scoring with occlusion) and query times of PS-PRM."""
    from .collision import CollisionChecker
    from .paths import resolve_named
    from .planning.factory import make_planner
    from .robot import RobotModel
    from .scene import load_scene

    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    target = target or (scene.problems[0].target if scene.problems else scene.target_names[0])
    p = make_planner(planner, scene, [target], robot=robot, n_nodes=nodes, seed=seed)
    stats = p.build()
    rng = np.random.default_rng(seed + 1)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    probs = random_problems(robot, scene, checker, queries, rng, robot.default_configuration(),
                            scene.target(target).center)
    times, ok, scores = [], 0, []
    for a, b in probs:
        res = p.plan(a, b, timing=False)
        times.append(res.query_ms)
        ok += res.success
        if res.success:
            scores.append(res.mean_score)
    return {
        "scene": scene.name, "planner": planner, "target": target, "threads": threads,
        "n_nodes": stats.get("n_nodes"), "n_edges": stats.get("n_edges"),
        "build_s": stats.get("build_s"), "sample_s": stats.get("sample_s"), "edges_s": stats.get("edges_s"),
        "score_s": stats.get("score_s"),
        "queries": len(probs), "success_rate": ok / len(probs),
        "query_ms": float(np.median(times)), "query_p95_ms": float(np.percentile(times, 95)),
        "mean_perception_score": float(np.mean(scores)) if scores else float("nan"),
    }
