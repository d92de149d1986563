"""``psprm demo``: the end-to-end run on a shipped scene (the README's main job).

It loads the scene and its robot, samples configurations and checks them with the batched collision checker, checks
every named problem's start and goal, writes a top-view picture with the robot at a start configuration, then builds a
neural PS-PRM roadmap for the first problem's target, plans it, compares with the same roadmap at alpha = 0 (shortest
path) and writes the plan figure.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the library end to end on a shipped scene (default: home)")
    p.add_argument("--scene", default="home", help="scene name (config/scenes) or YAML path")
    p.add_argument("--samples", type=int, default=20000, help="random configurations to check")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out", help="output folder for the picture")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--planner", default="neural-psprm-line", help="PS-PRM variant for the planning step")
    p.add_argument("--nodes", type=int, default=3000, help="roadmap size for the planning step (0: skip planning)")
    p.add_argument("--problem", default=None, help="named problem for the planning step (default: the first)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    import torch

    from ..collision import CollisionChecker
    from ..paths import resolve_named
    from ..evaluation.reference import sample_uniform
    from ..robot import RobotModel
    from ..scene import load_scene
    from ..evaluation.viz import new_figure, plot_scene_top, plot_spheres_top

    t0 = time.perf_counter()
    scene = load_scene(resolve_named("scene", args.scene))
    robot = RobotModel.load(scene.robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    t_load = time.perf_counter() - t0
    rng = np.random.default_rng(args.seed)
    qs = torch.as_tensor(sample_uniform(robot, args.samples, rng, base_box=scene.workspace), dtype=torch.float32)
    checker.valid(qs[:64])  # warm-up (lazy tensor caches), so the rate below is the steady-state one
    t1 = time.perf_counter()
    free = checker.valid(qs)
    t_check = time.perf_counter() - t1
    cams = robot.camera_poses(qs[free])
    problems = []
    for prob in scene.problems:
        row = {"problem": prob.name, "target": prob.target}
        for key, values in (("start", prob.start), ("goal", prob.goal)):
            if not values:
                continue
            try:
                q = torch.as_tensor(robot.configuration(values)[None], dtype=torch.float32)
            except KeyError as exc:
                row[key] = f"invalid: {exc}"
                continue
            d = {k: bool(v[0]) for k, v in checker.check_detailed(q).items()}
            row[key] = "free" if not any(d.values()) else "in collision (" + ", ".join(k for k, v in d.items() if v) + ")"
        problems.append(row)
    # picture: scene, free base positions, robot at the first problem's start
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = new_figure(figsize=(9, 7))
    plot_scene_top(ax, scene, show_labels=True, show_problems=True)
    fq = qs[free].numpy()
    ax.scatter(fq[:2000, 0], fq[:2000, 1], s=2, c="tab:green", alpha=0.35, label="collision-free base samples")
    if scene.problems:
        q0 = torch.as_tensor(robot.configuration(scene.problems[0].start)[None], dtype=torch.float32)
        plot_spheres_top(ax, robot.sphere_centers(q0)[0].numpy(), robot.spheres.radii)
        cam = robot.camera_poses(q0)[0].numpy()
        ax.arrow(cam[0, 3], cam[1, 3], 0.6 * cam[0, 2], 0.6 * cam[1, 2], width=0.02, color="k")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_title(f"{scene.name}: {robot.name}, {int(free.sum())}/{len(qs)} random configurations collision-free")
    fig.tight_layout()
    picture = out / f"demo_{scene.name}.png"
    fig.savefig(picture)
    planning = _plan(args, scene, robot, out) if args.nodes > 0 and scene.problems else None
    summary = {
        "scene": scene.name, "robot": robot.name, "dof": robot.dof, "joints": robot.joint_names,
        "obstacles": len(scene.obstacles), "targets": scene.target_names,
        "samples": len(qs), "collision_free": int(free.sum()),
        "checks_per_s": round(len(qs) / t_check), "load_s": round(t_load, 3),
        "camera_height_range_m": [round(float(cams[:, 2, 3].min()), 3), round(float(cams[:, 2, 3].max()), 3)]
        if len(cams) else None,
        "problems": problems, "picture": str(picture), "planning": planning,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"scene {scene.name} with robot {robot.name} ({robot.dof} DoF: {', '.join(robot.joint_names)})")
        print(f"  {len(scene.obstacles)} obstacles, targets: {', '.join(scene.target_names)}")
        print(f"  {summary['collision_free']}/{len(qs)} random configurations collision-free "
              f"({summary['checks_per_s']} checks/s, batched torch on CPU)")
        for row in problems:
            print(f"  problem {row['problem']:24s} target {row['target']:14s} start {row.get('start', '-')}, "
                  f"goal {row.get('goal', '-')}")
        print(f"  picture: {picture}")
        if planning:
            if "skipped" in planning:
                print(f"  planning skipped: {planning['skipped']}")
            else:
                print(f"  {planning['planner']} on problem {planning['problem']} (target {planning['target']}): "
                      f"{planning['n_nodes']} nodes / {planning['n_edges']} edges built in {planning['build_s']:.1f} s")
                for key in ("psprm", "shortest_path_alpha0"):
                    r = planning[key]
                    print(f"    {key:22s} success {r['success']}, path length {r['path_length_rad']:.2f}, "
                          f"mean predicted score {r['mean_perception_score']:.3f}, query {r['query_ms']:.0f} ms")
                print(f"  plan figure: {planning['figure']}")
    return 0


def _plan(args, scene, robot, out: Path) -> dict:
    """Plan the scene's first problem with PS-PRM and with the same roadmap at alpha = 0."""
    from ..errors import PsprmError
    from ..planning.factory import make_planner, problem_configurations
    from .planning import plot_plan

    try:
        prob = scene.problem(args.problem) if args.problem else scene.problems[0]
    except KeyError as exc:
        raise PsprmError(str(exc).strip("'\"")) from None
    try:
        planner = make_planner(args.planner, scene, prob.all_targets, robot=robot,
                               options={"roadmap.n_nodes": args.nodes, "seed": args.seed})
    except PsprmError as exc:
        return {"skipped": str(exc)}
    start, goals = problem_configurations(robot, scene, prob)
    stats = planner.build(template=start)
    if not stats.get("success"):
        return {"skipped": stats.get("reason", "roadmap build failed")}
    res = planner.plan(start, goals)
    figure = out / f"plan_{scene.name}.png"
    if res.success:
        plot_plan(planner, res, str(figure), title=f"{args.planner} on {scene.name}/{prob.name}")
    alpha = planner.settings.scoring.alpha
    planner.set_alpha(0.0)
    res0 = planner.plan(start, goals, timing=False)
    planner.set_alpha(alpha)
    keep = ("success", "reason", "path_length_rad", "mean_perception_score", "query_ms")
    return {"planner": args.planner, "problem": prob.name, "target": prob.target, "n_nodes": stats["n_nodes"],
            "n_edges": stats["n_edges"], "build_s": stats["build_s"], "figure": str(figure),
            "psprm": {k: v for k, v in res.to_dict().items() if k in keep},
            "shortest_path_alpha0": {k: v for k, v in res0.to_dict().items() if k in keep}}
