"""Check the tensor pipeline on a device (``cuda``, ``cuda:1``, ``cpu``) against independent references.

    python -m psprm_core.evaluation.device_check --device cuda  # full environment (scripts/check_device.sh)
    python -m psprm_core.evaluation.device_check --device cpu --torch-path  # here: the same torch code, CPU kernels off
    python -m psprm_core.evaluation.device_check --record psprm_core/data/device_check/references.npz
    python -m psprm_core.evaluation.device_check --device cuda --references psprm_core/data/device_check/references.npz

On a CPU the planner runs small batches through compiled numba kernels (:mod:`psprm_core.kernels.fastpath`); on any
other device, and on the CPU with ``--torch-path``, every call takes the torch operators the paper's GPU pipeline uses.
Each stage is judged by something the device code does not compute:

* FK: camera poses on the device against pybullet's forward kinematics (same configurations);
* collision: flags on the device against pybullet's exact mesh check (a configuration pybullet finds in collision
  and the device calls free is a missed collision: must be 0);
* neural scoring: the surrogate with ray-cast occlusion on the device against the same model on the CPU in float64
  with the compiled paths off (the same code on another device and in another precision);
* planning: the same PS-PRM (settings, seed) built on the CPU with its compiled kernels and on the device; both
  answer the same random queries and replan after the same target turns (replans time their trajectories by
  stopping at every knot, the analytic profile, on both sides). Judged: every device path collision-free and ending at
  a goal; the device planner's scores of the CPU roadmap's nodes against the CPU planner's scores of them; path
  lengths, build, query and replan times side by side (roadmaps built in another precision may differ, so paths are
  compared by length, not node by node).

The references come from one of two places:

* computed in this process (no ``--references``): pybullet and the CPU planner run here, and device paths are judged
  by pybullet's exact check. This needs the project's full environment.
* carried in a file (``--references FILE``, written by ``--record FILE`` in the full environment): the
  configurations, pybullet's camera poses and collision flags of them, the float64 CPU scores, the CPU planner's
  node scores, queries, path lengths and timings, and the robot model's planning description (its URDF with each
  collision mesh replaced by the mesh's bounding box, which is all the robot model takes from a mesh; the record
  step verifies that the model built from it equals the packaged one). The check then evaluates the recorded
  configurations and queries (a prefix of them with ``--configs``/``--queries``/``--replans``) and imports nothing
  but torch, numpy, scipy, numba, pyyaml and this package: no pybullet, robot-description package, trimesh, toppra
  or ROS. Device paths are judged by the project's own collision checker on the CPU in float64 with the compiled
  kernels off (itself verified against pybullet by ``tests/test_collision_reference.py``; it is conservative, so a
  path it finds free pybullet finds free too). The CPU timings are the recording machine's (the header names it).

Tolerances (:data:`TOLERANCES`, printed with the figures): camera position 1e-3 m and rotation 1e-3 rad of pybullet's;
0 missed collisions; neural scores and node scores within 0.02 of the CPU's (float32 against float64); every query
and replan solved; 0 path collisions; path ends within 1e-3 of a goal (heading wrapped); with carried references the
robot model built from them within 1e-9 m of the recorded sphere model.

Prints one JSON object with the figures (timings of the CPU and the device side by side), ``failed`` (the names of
the checks that failed) and ``ok``; exits 1 if a check fails. Asked for CUDA where there is none, it says so
(``"checked": false``) and exits 0.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ...commands.perf import print_json, stdout_to_stderr
from ...errors import InputError, PsprmError
from ...paths import resolve_named
from .references import (DEFAULT_REFERENCES, DEFAULTS, TOLERANCES, References, carried_robot,
                                compute_references, planner_options, record, replan_settings, sphere_table)



def run(device: str = "cuda", torch_path: bool = False, scene_name: str | None = None, target: str | None = None,
        configs: int | None = None, nodes: int | None = None, queries: int | None = None,
        replans: int | None = None, seed: int | None = None, references: str | Path | None = None) -> dict:
    """The check of the module docstring: references computed here (``references`` None; None sizes take
    :data:`DEFAULTS`) or read from the file ``references`` (then the scene, target, nodes and seed are the file's,
    and ``configs``, ``queries``, ``replans`` take a prefix of its own)."""
    from ...scene import load_scene

    if references is None:
        from ...robot import RobotModel
        from ..reference import PybulletWorld

        a = {k: DEFAULTS[k] if v is None else v for k, v in (("scene", scene_name), ("target", target),
                                                               ("configs", configs), ("nodes", nodes),
                                                               ("queries", queries), ("replans", replans),
                                                               ("seed", seed))}
        scene = load_scene(resolve_named("scene", a["scene"]))
        robot = RobotModel.load(scene.robot)
        world = PybulletWorld(robot, scene.collision_boxes())
        try:
            refs = compute_references(scene, robot, a["target"], a["configs"], a["nodes"], a["queries"],
                                      a["replans"], a["seed"], world)
            out = check(device, torch_path, scene, robot, refs, world.in_collision, "pybullet")
        finally:
            world.close()
        return out

    refs = References.load(references)
    h = refs.header
    given = {"scene": scene_name, "target": target, "nodes": nodes, "seed": seed}
    other = {k: v for k, v in given.items() if v is not None and v != h[k]}
    if other:
        raise InputError(f"{references} holds references of {', '.join(f'{k}={h[k]!r}' for k in other)}: record "
                         f"others with --record for {', '.join(f'{k}={v!r}' for k, v in other.items())}")
    refs = refs.prefix(configs, queries, replans)
    scene = load_scene(resolve_named("scene", h["scene"]))
    with tempfile.TemporaryDirectory() as tmp:
        robot = carried_robot(refs, scene, Path(tmp))
        out = check(device, torch_path, scene, robot, refs, _cpu_collision_judge(robot, scene),
                    "cpu collision checker, float64, compiled kernels off")
    out["references"] = {"file": str(references), **{k: h[k] for k in ("torch", "python", "cpu", "configs",
                                                                        "queries", "replans")}}
    return out


def _cpu_collision_judge(robot, scene):
    """Collision flags (B,) of configurations (B, dof) by the project's collision checker on the CPU in float64 with
    the compiled kernels off: environment (the scene's boxes as they are, no workspace bounds) or self-collision, as
    pybullet's check. Joint limits are not judged (as pybullet does not): a knot the device clamped to a limit in
    float32 lies a rounding step past it in float64."""
    import torch

    from ...collision import CollisionChecker
    from ...kernels.compute import Compute

    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=None, device="cpu", dtype=torch.float64,
                               compute=Compute.make("cpu", torch.float64, kernels="torch"))

    def judge(qs: np.ndarray) -> np.ndarray:
        det = checker.check_detailed(torch.as_tensor(np.asarray(qs), dtype=torch.float64))
        return (det["environment"] | det["self"]).cpu().numpy()

    return judge


def check(device: str, torch_path: bool, scene, robot, refs: References, path_judge, judge_name: str) -> dict:
    """Evaluate the references' configurations, views and queries on ``device`` and compare (module docstring);
    ``path_judge`` gives the collision flags of the device's paths."""
    import torch

    from ...collision import CollisionChecker
    from ...kernels.compute import Compute
    from ...perception.scoring import NeuralScorer
    from ...perception.surrogate import load_surrogate
    from ...planning.factory import default_checkpoint
    from ..benchmarks import rotation_angle_error

    dev = torch.device(device)
    compute = Compute.make(dev, kernels="torch" if torch_path else "auto")  # the device under test
    robot = robot.using(compute)
    h = refs.header
    out: dict = {"device": str(dev), "torch_path": not compute.compiled, "kernels": compute.kernels, "scene": scene.name,
                 "robot": robot.name, "torch": torch.__version__}
    if dev.type == "cuda":
        out["device_name"] = torch.cuda.get_device_name(dev)
    out["robot_model_max_difference_m"] = (float(np.abs(sphere_table(robot) - refs.robot_spheres).max())
                                           if sphere_table(robot).shape == refs.robot_spheres.shape else float("inf"))

    q = torch.as_tensor(refs.configs, dtype=torch.float32, device=dev)
    m = len(refs.camera_poses)
    cam = robot.camera_poses(q[:m]).double().cpu().numpy()
    ref_cam = refs.camera_poses
    out["fk_max_position_error_m"] = float(np.abs(cam[:, :3, 3] - ref_cam[:, :3, 3]).max())
    out["fk_max_rotation_error_rad"] = float(rotation_angle_error(cam[:, :3, :3], ref_cam[:, :3, :3]).max())

    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=None, device=dev, compute=compute)
    t0 = time.perf_counter()
    flags = checker.check(q)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    out["collision_s"] = time.perf_counter() - t0
    flags = flags.cpu().numpy()
    ref = refs.collision
    out["configs"] = int(len(ref))
    out["missed_collisions"] = int(np.sum(ref & ~flags))
    out["false_positive_rate"] = float(np.sum(flags & ~ref) / max(1, np.sum(~ref)))

    scorer = NeuralScorer(load_surrogate(default_checkpoint()), scene, h["target"]).using(compute)
    free = torch.as_tensor(refs.configs[refs.score_index], dtype=torch.float32, device=dev)
    s_dev = scorer.score(robot.camera_poses(free)).double().cpu().numpy()
    out["score_max_abs_difference"] = float(np.abs(s_dev - refs.scores).max()) if len(s_dev) else 0.0
    out["score_views"] = int(len(s_dev))

    out.update(_planning(compute, scene, robot, refs, path_judge))
    out["path_collision_judge"] = judge_name
    t = TOLERANCES
    checks = {"robot_model": out["robot_model_max_difference_m"] <= t["robot_model_m"],
              "fk_position": out["fk_max_position_error_m"] < t["fk_position_m"],
              "fk_rotation": out["fk_max_rotation_error_rad"] < t["fk_rotation_rad"],
              "missed_collisions": out["missed_collisions"] <= t["missed_collisions"],
              "scores": out["score_max_abs_difference"] < t["score_abs"],
              "node_scores": out["node_score_max_abs_difference"] < t["node_score_abs"],
              "queries_solved": out["queries_solved"] == out["queries"],
              "replans_solved": out["replans_solved"] == out["replans"],
              "path_collisions": out["path_collisions"] <= t["path_collisions"],
              "path_goal_error": out["path_goal_error_max"] < t["path_goal_error"]}
    out["tolerances"] = TOLERANCES
    out["failed"] = [k for k, v in checks.items() if not v]
    out["ok"] = not out["failed"]
    return out


def _planning(compute, scene, robot, refs: References, path_judge) -> dict:
    """The PS-PRM of the references (settings, nodes, seed) built on ``device``; it answers the references' queries
    and replans after their target turns, and scores the CPU roadmap's nodes. Judged: every device path free under
    ``path_judge`` and ending at a goal, node scores against the CPU planner's; path lengths and timings beside the
    CPU planner's."""
    import torch

    from ...planning.factory import make_planner
    from ...planning.replanner import Replanner

    h = refs.header
    target = h["target"]
    dut = make_planner("neural-psprm-line", scene, [target], robot=robot, device=str(compute.device),
                       options=planner_options(h["nodes"], h["seed"]), compute=compute)
    t0 = time.perf_counter()
    dut.build()
    dut_build = time.perf_counter() - t0
    nq = len(refs.query_starts)
    out = {"backend": type(dut.ctx.backend).__name__, "queries": nq, "queries_solved": 0, "path_collisions": 0, "path_goal_error_max": 0.0,
           "build_s": {"cpu_reference": float(refs.build_s), "device": dut_build}}
    q_ms = []
    cost_diff = []

    def judge(res, goals):
        dense = np.asarray(res.dense)
        out["path_collisions"] += int(np.sum(path_judge(dense)))
        diff = np.atleast_2d(goals) - dense[-1]
        if robot.mobile:  # base heading: the same pose a turn apart
            diff[:, 2] = (diff[:, 2] + np.pi) % (2 * np.pi) - np.pi
        err = float(np.min(np.linalg.norm(diff, axis=1)))
        out["path_goal_error_max"] = max(out["path_goal_error_max"], err)

    for i in range(nq):
        a, b = refs.query_starts[i], refs.goals(i)
        b = b[0] if len(b) == 1 else b
        t0 = time.perf_counter()
        r_dut = dut.plan(a, b, timing=False)
        q_ms.append((time.perf_counter() - t0) * 1e3)
        if r_dut.success:
            out["queries_solved"] += 1
            judge(r_dut, b)
            if refs.query_success[i]:
                ref_len = float(refs.query_path_length[i])
                cost_diff.append(abs(r_dut.path_length - ref_len) / max(ref_len, 1e-9))
    nodes = torch.as_tensor(refs.node_configs, dtype=torch.float32)
    s_dut = dut.score_configs(nodes.to(dut.device)).double().cpu().numpy()
    out["node_score_max_abs_difference"] = float(np.abs(s_dut - refs.node_scores).max())
    out["query_ms_median"] = {"cpu_reference": float(np.median(refs.query_ms)), "device": float(np.median(q_ms))}
    out["path_length_relative_difference_median"] = float(np.median(cost_diff)) if cost_diff else float("nan")

    tgt = scene.target(target)
    r_ms = []
    out.update(replans=int(len(refs.replan_yaws)), replans_solved=0)
    rp = Replanner(dut, replan_settings(), targets=[target])
    rp.set_robot_state(refs.replan_start)
    rp.set_goals(refs.replan_goals)
    rp.replan()
    for yaw in refs.replan_yaws:
        quat = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
        t0 = time.perf_counter()
        rp.update_target(target, tgt.center, quat)
        res = rp.replan()
        r_ms.append((time.perf_counter() - t0) * 1e3)
        if res.success:
            out["replans_solved"] += 1
            judge(res, refs.replan_goals)
    out["replan_ms_median"] = {"cpu_reference": float(np.median(refs.replan_ms)) if len(refs.replan_ms) else None,
                               "device": float(np.median(r_ms)) if r_ms else None}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m psprm_core.evaluation.device_check",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help="torch device (default cuda)")
    ap.add_argument("--torch-path", action="store_true", help="CPU: compiled kernels off (the path a GPU runs)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--references", nargs="?", const=str(DEFAULT_REFERENCES), metavar="FILE",
                      help="judge against references carried in FILE (default "
                           f"{DEFAULT_REFERENCES.relative_to(DEFAULT_REFERENCES.parents[3])}): no pybullet needed")
    mode.add_argument("--record", metavar="FILE",
                      help="compute the references here (full environment) and write them to FILE; checks nothing")
    ap.add_argument("--scene", help=f"scene (default {DEFAULTS['scene']}; with --references: the file's)")
    ap.add_argument("--target", help=f"target (default {DEFAULTS['target']}; with --references: the file's)")
    ap.add_argument("--configs", type=int, help=f"configurations for FK and collision (default {DEFAULTS['configs']};"
                                                " with --references: the first this many of the file's)")
    ap.add_argument("--nodes", type=int, help=f"roadmap nodes of the planning check (default {DEFAULTS['nodes']};"
                                              " with --references: the file's)")
    ap.add_argument("--queries", type=int, help=f"random queries on both planners (default {DEFAULTS['queries']})")
    ap.add_argument("--replans", type=int, help=f"target turns replanned on both (default {DEFAULTS['replans']})")
    ap.add_argument("--seed", type=int, help=f"default {DEFAULTS['seed']}; with --references: the file's")
    a = ap.parse_args(argv)
    import torch

    if a.record:
        sizes = {k: DEFAULTS[k] if getattr(a, k) is None else getattr(a, k) for k in DEFAULTS}
        with stdout_to_stderr():  # stdout carries the JSON object only
            out = record(Path(a.record), sizes["scene"], sizes["target"], sizes["configs"], sizes["nodes"],
                         sizes["queries"], sizes["replans"], sizes["seed"])
        print_json(out)
        return 0
    dev = torch.device(a.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(json.dumps({"device": a.device, "checked": False, "ok": True,
                          "note": f"CUDA is not available to this torch build ({torch.__version__}): nothing checked"}))
        return 0
    try:
        with stdout_to_stderr():  # stdout carries the JSON object only
            out = run(a.device, a.torch_path, a.scene, a.target, a.configs, a.nodes, a.queries, a.replans, a.seed,
                      a.references)
    except (PsprmError, OSError) as exc:  # a references file that is missing, of another layout or too small
        ap.error(str(exc))
    out["checked"] = True
    print_json(out)
    return 0 if out["ok"] else 1

