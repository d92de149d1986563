"""Check the tensor pipeline on a device (``cuda``, ``cuda:1``, ``cpu``) against independent references.

    python -m psprm_core.device_check --device cuda            # on a CUDA machine (scripts/check_device.sh)
    python -m psprm_core.device_check --device cpu --torch-path   # here: the same torch code, CPU kernels off

On a CPU the planner runs small batches through compiled numba kernels (:mod:`psprm_core.fastpath`); on any other
device, and on the CPU with ``--torch-path``, every call takes the torch operators the paper's GPU pipeline uses.
Each stage is judged by something the device code does not compute:

* FK: camera poses on the device against pybullet's forward kinematics (same configurations);
* collision: flags on the device against pybullet's exact mesh check (a configuration pybullet finds in collision
  and the device calls free is a missed collision: must be 0);
* neural scoring: the surrogate with ray-cast occlusion on the device against the same model on the CPU in float64
  with the compiled paths off (the same code on another device and in another precision);
* planning: a PS-PRM roadmap built and queried on the device; the returned dense path checked by pybullet
  (collision-free) and for reaching a goal.

Prints one JSON object with the figures and ``ok``; exits 1 if a check fails, 2 if the device is not available.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time

import numpy as np


def run(device: str = "cuda", torch_path: bool = False, scene_name: str = "home", target: str = "tv",
        configs: int = 2000, nodes: int = 600, seed: int = 0) -> dict:
    import torch

    from . import fastpath
    from .benchmarks import rotation_angle_error
    from .collision import CollisionChecker
    from .paths import resolve_named
    from .perception.scoring import NeuralScorer
    from .perception.surrogate import load_surrogate
    from .planning.factory import default_checkpoint, make_planner, problem_configurations
    from .reference import PybulletWorld, sample_uniform
    from .robot import RobotModel
    from .scene import load_scene

    dev = torch.device(device)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    boxes = scene.collision_boxes()
    rng = np.random.default_rng(seed)
    qs = sample_uniform(robot, configs, rng, base_box=scene.workspace)
    out: dict = {"device": str(dev), "torch_path": bool(torch_path or dev.type != "cpu"), "scene": scene.name,
                 "robot": robot.name, "torch": torch.__version__}
    if dev.type == "cuda":
        out["device_name"] = torch.cuda.get_device_name(dev)
    def guard():
        return fastpath.disabled() if torch_path else contextlib.nullcontext()

    world = PybulletWorld(robot, boxes)
    try:
        with guard():
            q = torch.as_tensor(qs, dtype=torch.float32, device=dev)
            m = min(500, configs)
            cam = robot.camera_poses(q[:m]).double().cpu().numpy()
            ref_cam = np.stack([world.camera_pose(x) for x in qs[:m]])
            out["fk_max_position_error_m"] = float(np.abs(cam[:, :3, 3] - ref_cam[:, :3, 3]).max())
            out["fk_max_rotation_error_rad"] = float(rotation_angle_error(cam[:, :3, :3], ref_cam[:, :3, :3]).max())

            checker = CollisionChecker(robot, boxes, workspace=None, device=dev)
            t0 = time.perf_counter()
            flags = checker.check(q)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            out["collision_s"] = time.perf_counter() - t0
            flags = flags.cpu().numpy()
            ref = world.in_collision(qs)
            out["missed_collisions"] = int(np.sum(ref & ~flags))
            out["false_positive_rate"] = float(np.sum(flags & ~ref) / max(1, np.sum(~ref)))

            model = load_surrogate(default_checkpoint())
            scorer = NeuralScorer(model, scene, target)
            free = torch.as_tensor(qs[~ref][:m], dtype=torch.float32)
            s_dev = scorer.score(robot.camera_poses(free.to(dev))).double().cpu().numpy()
        with fastpath.disabled():
            s_ref = scorer.score(robot.camera_poses(free.double())).double().cpu().numpy()
        out["score_max_abs_difference"] = float(np.abs(s_dev - s_ref).max())
        out["score_views"] = int(len(s_ref))

        with guard():
            planner = make_planner("neural-psprm-line", scene, [target], robot=robot, n_nodes=nodes, seed=seed,
                                   device=str(dev))
            stats = planner.build()
            prob = next(p for p in scene.problems if p.target == target) if any(
                p.target == target for p in scene.problems) else scene.problems[0]
            start, goals = problem_configurations(robot, scene, prob)
            res = planner.plan(start, goals)
        out["build_s"] = stats.get("build_s")
        out["plan_success"] = bool(res.success)
        out["plan_reason"] = res.reason
        if res.success:
            dense = np.asarray(res.dense)
            out["path_points"] = int(len(dense))
            out["path_collisions_pybullet"] = int(world.in_collision(dense).sum())
            out["path_goal_error"] = float(np.min(np.linalg.norm(goals - dense[-1], axis=1)))
    finally:
        world.close()
    out["ok"] = bool(out["missed_collisions"] == 0 and out["fk_max_position_error_m"] < 1e-3
                     and out["fk_max_rotation_error_rad"] < 1e-3 and out["score_max_abs_difference"] < 0.02
                     and out["plan_success"] and out.get("path_collisions_pybullet", 1) == 0
                     and out.get("path_goal_error", 1.0) < 1e-3)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m psprm_core.device_check", description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help="torch device (default cuda)")
    ap.add_argument("--torch-path", action="store_true", help="CPU: compiled kernels off (the path a GPU runs)")
    ap.add_argument("--scene", default="home")
    ap.add_argument("--target", default="tv")
    ap.add_argument("--configs", type=int, default=2000, help="configurations for FK and collision (default 2000)")
    ap.add_argument("--nodes", type=int, default=600, help="roadmap nodes of the planning check (default 600)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    import torch

    dev = torch.device(a.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(json.dumps({"device": a.device, "ok": False, "error": "CUDA is not available to this torch build "
                          f"({torch.__version__})"}))
        return 2
    out = run(a.device, a.torch_path, a.scene, a.target, a.configs, a.nodes, a.seed)
    sys.stdout.flush()
    print("\n" + json.dumps(out))  # on a line of its own (pybullet's loader writes to stdout without a newline)
    return 0 if out["ok"] else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
