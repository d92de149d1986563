"""Whole-body FK side by side (``psprm perf kinematics --kinematics pytorch_kinematics``): the robot model's torch
FK, pytorch-kinematics' (:class:`~psprm_core.robot.kinematics_pk.PKBodyKinematics`) and pybullet's, on the
configurations of :func:`~psprm_core.evaluation.benchmarks.kinematics_benchmark` (same seed, same workspace), with the
agreement of the two torch implementations with pybullet and the torch-path collision checks run on each."""

from __future__ import annotations

import logging
import time

import numpy as np
import torch

from ..collision import CollisionChecker
from ..kernels.compute import Compute
from ..paths import resolve_named
from ..robot import RobotModel
from ..robot.kinematics_pk import PKBodyKinematics
from ..scene import load_scene
from .benchmarks import best_time, rotation_angle_error
from .reference import PybulletWorld, sample_uniform

log = logging.getLogger(__name__)


def body_fk_comparison(robot_name: str, scene_name: str, n: int = 10000, seed: int = 0, threads: int = 2,
                       fk_check: int = 1000) -> dict:
    """Throughputs (configurations per second) of the body poses of ``n`` configurations in float32 by the robot
    model (``RobotModel.body_poses``) and by pytorch-kinematics, of pybullet's link poses of the same bodies (one
    configuration at a time, on ``min(fk_check, n)`` of them), and of the collision checker's torch path on either
    FK; the largest body position / rotation differences from pybullet (float64, on those configurations) and the
    number of configurations whose collision flags differ between the two checkers."""
    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(robot_name)
    boxes = scene.collision_boxes()
    qs = sample_uniform(robot, n, np.random.default_rng(seed), base_box=scene.workspace)
    q32, m = torch.as_tensor(qs, dtype=torch.float32), min(fk_check, n)
    pk32 = PKBodyKinematics(robot, dtype=torch.float32)
    t_native = best_time(lambda: robot.body_poses(q32))
    t_pk = best_time(lambda: pk32.body_poses(q32))
    torch_only = Compute.make("cpu", kernels="torch")  # the torch path at any batch size
    native = CollisionChecker(robot, boxes, workspace=None, compute=torch_only)
    with_pk = CollisionChecker(robot, boxes, workspace=None, kinematics=pk32, compute=torch_only)
    t_col_native = best_time(lambda: native.check(q32))
    t_col_pk = best_time(lambda: with_pk.check(q32))
    flags_native, flags_pk = native.check(q32).numpy(), with_pk.check(q32).numpy()
    world = PybulletWorld(robot, boxes)
    try:
        t0 = time.perf_counter()
        ref = np.stack([world.link_poses(q, robot.bodies) for q in qs[:m]])
        t_pb = time.perf_counter() - t0
    finally:
        world.close()
    q64 = torch.as_tensor(qs[:m])
    out = {"body_fk_bodies": len(robot.bodies),
           "body_fk_native_per_s": n / t_native, "body_fk_pk_per_s": n / t_pk, "body_fk_pybullet_per_s": m / t_pb,
           "collision_torch_native_per_s": n / t_col_native, "collision_torch_pk_per_s": n / t_col_pk,
           "collision_flags_differing": int(np.sum(flags_native != flags_pk))}
    for key, kin in (("native", robot), ("pk", PKBodyKinematics(robot))):
        R, t = (x.numpy() for x in kin.body_poses(q64))
        out[f"body_fk_{key}_max_position_error_m"] = float(np.abs(t - ref[..., :3, 3]).max())
        out[f"body_fk_{key}_max_rotation_error_rad"] = float(rotation_angle_error(R, ref[..., :3, :3]).max())
    log.info("body FK %s/%s: %s", robot.name, scene.name, out)
    return out
