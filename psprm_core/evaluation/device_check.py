"""Check the tensor pipeline on a device (``cuda``, ``cuda:1``, ``cpu``) against independent references.

    python -m psprm_core.evaluation.device_check --device cuda  # on a CUDA machine (scripts/check_device.sh)
    python -m psprm_core.evaluation.device_check --device cpu --torch-path  # here: the same torch code, CPU kernels off

On a CPU the planner runs small batches through compiled numba kernels (:mod:`psprm_core.kernels.fastpath`); on any
other device, and on the CPU with ``--torch-path``, every call takes the torch operators the paper's GPU pipeline uses.
Each stage is judged by something the device code does not compute:

* FK: camera poses on the device against pybullet's forward kinematics (same configurations);
* collision: flags on the device against pybullet's exact mesh check (a configuration pybullet finds in collision
  and the device calls free is a missed collision: must be 0);
* neural scoring: the surrogate with ray-cast occlusion on the device against the same model on the CPU in float64
  with the compiled paths off (the same code on another device and in another precision);
* planning: the same PS-PRM built on the CPU (compiled kernels) and on the device, the same random queries and
  replans after target turns on both: every device path collision-free under pybullet and ending at a goal, node
  scores against the CPU planner's, path lengths, build, query and replan times side by side.

Prints one JSON object with the figures (timings of the CPU and the device side by side) and ``ok``; exits 1 if a
check fails. Asked for CUDA where there is none, it says so (``"checked": false``) and exits 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def run(device: str = "cuda", torch_path: bool = False, scene_name: str = "dynamic_person",
        target: str = "person_face", configs: int = 2000, nodes: int = 600, queries: int = 10, replans: int = 5,
        seed: int = 0) -> dict:
    import torch

    from ..collision import CollisionChecker
    from ..kernels.compute import Compute
    from ..paths import resolve_named
    from ..perception.scoring import NeuralScorer
    from ..perception.surrogate import load_surrogate
    from ..planning.factory import default_checkpoint
    from ..robot import RobotModel
    from ..scene import load_scene
    from .benchmarks import rotation_angle_error
    from .reference import PybulletWorld, sample_uniform

    dev = torch.device(device)
    compute = Compute.make(dev, kernels="torch" if torch_path else "auto")  # the device under test
    reference = Compute.make("cpu", kernels="torch")  # float64 reference scores: the torch code on the CPU
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    boxes = scene.collision_boxes()
    rng = np.random.default_rng(seed)
    qs = sample_uniform(robot, configs, rng, base_box=scene.workspace)
    out: dict = {"device": str(dev), "torch_path": not compute.compiled, "kernels": compute.kernels, "scene": scene.name,
                 "robot": robot.name, "torch": torch.__version__}
    if dev.type == "cuda":
        out["device_name"] = torch.cuda.get_device_name(dev)
    world = PybulletWorld(robot, boxes)
    try:
        q = torch.as_tensor(qs, dtype=torch.float32, device=dev)
        m = min(500, configs)
        cam = robot.using(compute).camera_poses(q[:m]).double().cpu().numpy()
        ref_cam = np.stack([world.camera_pose(x) for x in qs[:m]])
        out["fk_max_position_error_m"] = float(np.abs(cam[:, :3, 3] - ref_cam[:, :3, 3]).max())
        out["fk_max_rotation_error_rad"] = float(rotation_angle_error(cam[:, :3, :3], ref_cam[:, :3, :3]).max())

        checker = CollisionChecker(robot, boxes, workspace=None, device=dev, compute=compute)
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
        dut = scorer.using(compute)
        s_dev = dut.score(robot.using(compute).camera_poses(free.to(dev))).double().cpu().numpy()
        s_ref = scorer.using(reference).score(robot.using(reference).camera_poses(free.double()))
        s_ref = s_ref.double().cpu().numpy()
        out["score_max_abs_difference"] = float(np.abs(s_dev - s_ref).max())
        out["score_views"] = int(len(s_ref))

        out.update(_planning(compute, scene, robot, target, nodes, queries, replans, seed, world))
    finally:
        world.close()
    out["ok"] = bool(out["missed_collisions"] == 0 and out["fk_max_position_error_m"] < 1e-3
                     and out["fk_max_rotation_error_rad"] < 1e-3 and out["score_max_abs_difference"] < 0.02
                     and out["node_score_max_abs_difference"] < 0.02
                     and out["queries_solved"] == out["queries"] and out["replans_solved"] == out["replans"]
                     and out["path_collisions_pybullet"] == 0 and out["path_goal_error_max"] < 1e-3)
    return out


def _planning(compute, scene, robot, target, nodes, queries, replans, seed, world) -> dict:
    """The same PS-PRM (settings, seed) built on the CPU with its compiled kernels and on ``device``; both answer
    the same random queries and replan after the same target turns. Judged: every device path collision-free under
    pybullet and ending at a goal; the device's node scores against the CPU planner's scores of the same
    configurations; path costs and timings side by side (roadmaps built in another precision may differ, so paths
    are compared by cost, not node by node)."""
    import torch

    from ..collision import CollisionChecker
    from ..kernels.compute import Compute
    from ..planning.factory import make_planner, problem_configurations
    from ..planning.replanner import Replanner, ReplanSettings
    from ..problems import random_problems

    def build(cp):
        p = make_planner("neural-psprm-line", scene, [target], robot=robot, device=str(cp.device),
                         options={"roadmap.n_nodes": nodes, "seed": seed}, compute=cp)
        t0 = time.perf_counter()
        p.build()
        return p, time.perf_counter() - t0

    ref, ref_build = build(Compute.make("cpu"))
    dut, dut_build = build(compute)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    probs = random_problems(robot, scene, checker, queries, np.random.default_rng(seed + 1),
                            robot.default_configuration(), scene.target(target).center, aimed_only=True,
                            aim_restarts=8)
    out = {"backend": {"cpu_reference": type(ref.ctx.backend).__name__, "device": type(dut.ctx.backend).__name__},
           "queries": len(probs), "queries_solved": 0, "path_collisions_pybullet": 0, "path_goal_error_max": 0.0,
           "build_s": {"cpu_reference": ref_build, "device": dut_build}}
    q_ms = {"cpu_reference": [], "device": []}
    cost_diff = []

    def judge(res, goals):
        dense = np.asarray(res.dense)
        out["path_collisions_pybullet"] += int(world.in_collision(dense).sum())
        diff = np.atleast_2d(goals) - dense[-1]
        if robot.mobile:  # base heading: the same pose a turn apart
            diff[:, 2] = (diff[:, 2] + np.pi) % (2 * np.pi) - np.pi
        err = float(np.min(np.linalg.norm(diff, axis=1)))
        out["path_goal_error_max"] = max(out["path_goal_error_max"], err)

    for a, b in probs:
        r_ref = ref.plan(a, b, timing=False)
        t0 = time.perf_counter()
        r_dut = dut.plan(a, b, timing=False)
        q_ms["device"].append((time.perf_counter() - t0) * 1e3)
        q_ms["cpu_reference"].append(r_ref.query_ms)
        if r_dut.success:
            out["queries_solved"] += 1
            judge(r_dut, b)
            if r_ref.success:
                cost_diff.append(abs(r_dut.path_length - r_ref.path_length) / max(r_ref.path_length, 1e-9))
    nq = torch.as_tensor(dut.graph.configs[:500], dtype=torch.float32)
    s_dut = dut.score_configs(nq.to(dut.device)).double().cpu().numpy()
    s_ref = ref.score_configs(nq).double().cpu().numpy()
    out["node_score_max_abs_difference"] = float(np.abs(s_dut - s_ref).max())
    out["query_ms_median"] = {k: float(np.median(v)) for k, v in q_ms.items()}
    out["path_length_relative_difference_median"] = float(np.median(cost_diff)) if cost_diff else float("nan")

    # replans after target turns, both planners from the scene's first problem
    prob = scene.problems[0]
    start, goals = problem_configurations(robot, scene, prob)
    tgt = scene.target(target)
    rng = np.random.default_rng(seed + 7)
    yaws = rng.uniform(-1.0, 1.0, replans)
    r_ms = {"cpu_reference": [], "device": []}
    out.update(replans=replans, replans_solved=0)
    for name, planner in (("cpu_reference", ref), ("device", dut)):
        rp = Replanner(planner, ReplanSettings(), targets=[target])
        rp.set_robot_state(start)
        rp.set_goals(goals)
        rp.replan()
        for yaw in yaws:
            quat = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
            t0 = time.perf_counter()
            rp.update_target(target, tgt.center, quat)
            res = rp.replan()
            r_ms[name].append((time.perf_counter() - t0) * 1e3)
            if name == "device" and res.success:
                out["replans_solved"] += 1
                judge(res, goals)
    out["replan_ms_median"] = {k: float(np.median(v)) for k, v in r_ms.items()}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m psprm_core.evaluation.device_check",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help="torch device (default cuda)")
    ap.add_argument("--torch-path", action="store_true", help="CPU: compiled kernels off (the path a GPU runs)")
    ap.add_argument("--scene", default="dynamic_person")
    ap.add_argument("--target", default="person_face")
    ap.add_argument("--configs", type=int, default=2000, help="configurations for FK and collision (default 2000)")
    ap.add_argument("--nodes", type=int, default=600, help="roadmap nodes of the planning check (default 600)")
    ap.add_argument("--queries", type=int, default=10, help="random queries on both planners (default 10)")
    ap.add_argument("--replans", type=int, default=5, help="target turns replanned on both (default 5)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    import torch

    dev = torch.device(a.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(json.dumps({"device": a.device, "checked": False, "ok": True,
                          "note": f"CUDA is not available to this torch build ({torch.__version__}): nothing checked"}))
        return 0
    from ..commands.perf import print_json, stdout_to_stderr

    with stdout_to_stderr():  # stdout carries the JSON object only
        out = run(a.device, a.torch_path, a.scene, a.target, a.configs, a.nodes, a.queries, a.replans, a.seed)
    out["checked"] = True
    print_json(out)
    return 0 if out["ok"] else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
