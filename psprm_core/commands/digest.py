"""Fixed-seed plans on every shipped scene, written down so that two versions of the planner can be compared.

``psprm perf digest --out a.json`` builds a small roadmap per scene (fixed seed), plans the scene's problems and a few
random ones, then replans after a target move and an obstacle move; it records each plan's success, reason, node
path, waypoints, cost and predicted score. ``--against b.json`` compares with an earlier record: identical node paths
and reasons, waypoints and costs within ``--tol``. The exit code is 1 when they differ."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

SCENES = ("home", "cup_table", "nursing", "blind_spot_alley", "dynamic_person")


def _record(res) -> dict:
    out = {"success": bool(res.success), "reason": res.reason}
    if res.success:
        out.update(path=[int(i) for i in res.path_nodes], cost=float(res.cost), mean_score=float(res.mean_score),
                   waypoints=np.asarray(res.waypoints, float).round(9).tolist(),
                   duration=float(res.trajectory.times[-1]) if res.trajectory is not None else None)
    return out


def scene_digest(scene_name: str, nodes: int = 400, seed: int = 3, random: int = 3) -> dict:
    """Plans and replans of ``neural-psprm-line`` on one scene (see the module docstring)."""
    import torch

    from ..paths import resolve_named
    from ..planning.factory import make_planner, problem_configurations
    from ..planning.replanner import Replanner, ReplanSettings
    from ..problems import random_problems
    from ..robot import RobotModel
    from ..scene import load_scene

    torch.manual_seed(seed)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    prob = scene.problems[0]
    targets = prob.all_targets
    planner = make_planner("neural-psprm-line", scene, targets, robot=robot,
                           options={"roadmap.n_nodes": nodes, "seed": seed})
    start, goals = problem_configurations(robot, scene, prob)
    stats = planner.build(template=start)
    out = {"scene": scene_name, "nodes": int(stats.get("n_nodes", 0)), "edges": int(stats.get("n_edges", 0)),
           "plans": []}
    for p in scene.problems:
        s, g = problem_configurations(robot, scene, p)
        out["plans"].append({"problem": p.name, **_record(planner.plan(s, g))})
    rng = np.random.default_rng(seed)
    focus = np.mean([scene.target(t).center for t in targets], axis=0)
    for i, (s, g) in enumerate(random_problems(robot, scene, planner.checker, random, rng, start, focus)):
        out["plans"].append({"problem": f"random{i}", **_record(planner.plan(s, g[None]))})
    rp = Replanner(planner, ReplanSettings())
    rp.set_robot_state(start)
    rp.set_goals(goals)
    out["plans"].append({"problem": "replan:first", **_record(rp.replan(now=0.0))})
    t = scene.target(targets[0])
    rp.update_target(t.name, t.center + np.array([0.3, -0.2, 0.0]))
    out["plans"].append({"problem": "replan:target", **_record(rp.replan(now=10.0))})
    if scene.obstacles and rp.result is not None and rp.result.success:
        box = scene.obstacles[0]
        mid = np.asarray(rp.result.waypoints)[len(rp.result.waypoints) // 2]
        rp.update_obstacle(box.name, np.array([mid[0], mid[1], box.center[2]]), box.quat)
        out["plans"].append({"problem": "replan:obstacle", **_record(rp.replan(now=20.0))})
    return out


def digest(scenes=SCENES, nodes: int = 400, seed: int = 3) -> dict:
    return {"nodes": nodes, "seed": seed, "scenes": [scene_digest(s, nodes, seed) for s in scenes]}


def _reason(text: str) -> str:
    """A reason without the durations it quotes ("... reached in 0.3 s"): they vary from run to run."""
    return re.sub(r"\d+(\.\d+)? s\b", "<t> s", text)


def compare(new: dict, old: dict, tol: float = 1e-6) -> list:
    """Differences between two digests (empty when they agree; durations quoted in reasons are not compared)."""
    diffs = []
    olds = {s["scene"]: s for s in old["scenes"]}
    for s in new["scenes"]:
        o = olds.get(s["scene"])
        if o is None:
            diffs.append(f"{s['scene']}: not in the earlier record")
            continue
        if (s["nodes"], s["edges"]) != (o["nodes"], o["edges"]):
            diffs.append(f"{s['scene']}: roadmap {s['nodes']}/{s['edges']} vs {o['nodes']}/{o['edges']}")
        for a, b in zip(s["plans"], o["plans"]):
            name = f"{s['scene']}/{a['problem']}"
            if (a["success"], _reason(a["reason"]), a.get("path")) != (b["success"], _reason(b["reason"]), b.get("path")):
                diffs.append(f"{name}: {a['success']} {a['reason']!r} {a.get('path')} vs "
                             f"{b['success']} {b['reason']!r} {b.get('path')}")
                continue
            if a["success"]:
                if abs(a["cost"] - b["cost"]) > tol or abs(a["mean_score"] - b["mean_score"]) > tol:
                    diffs.append(f"{name}: cost {a['cost']} vs {b['cost']}, score {a['mean_score']} vs "
                                 f"{b['mean_score']}")
                wa, wb = np.asarray(a["waypoints"]), np.asarray(b["waypoints"])
                if wa.shape != wb.shape or np.abs(wa - wb).max() > tol:
                    diffs.append(f"{name}: waypoints differ")
                if (a["duration"] is None) != (b["duration"] is None) or (
                        a["duration"] is not None and abs(a["duration"] - b["duration"]) > tol):
                    diffs.append(f"{name}: duration {a['duration']} vs {b['duration']}")
        if len(s["plans"]) != len(o["plans"]):
            diffs.append(f"{s['scene']}: {len(s['plans'])} plans vs {len(o['plans'])}")
    return diffs


def run(args) -> int:
    scenes = args.scenes.split(",") if args.scenes else SCENES
    new = digest(scenes, nodes=args.nodes, seed=args.seed)
    if args.out:
        Path(args.out).write_text(json.dumps(new))
    n = sum(len(s["plans"]) for s in new["scenes"])
    ok = sum(p["success"] for s in new["scenes"] for p in s["plans"])
    print(f"{n} plans on {len(new['scenes'])} scenes, {ok} succeeded")
    if args.against:
        diffs = compare(new, json.loads(Path(args.against).read_text()), tol=args.tol)
        for d in diffs:
            print("DIFF", d)
        print("identical" if not diffs else f"{len(diffs)} differences")
        return 1 if diffs else 0
    return 0
