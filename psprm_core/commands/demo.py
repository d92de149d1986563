"""``psprm demo``: the end-to-end run on a shipped scene (the README's main job).

Today it loads the scene and its robot, samples configurations and checks them with the batched collision checker,
checks every named problem's start and goal, and writes a top-view picture with the robot at a start configuration.
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
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    import torch

    from ..collision import CollisionChecker
    from ..paths import resolve_named
    from ..reference import sample_uniform
    from ..robot import RobotModel
    from ..scene import load_scene
    from ..viz import new_figure, plot_scene_top, plot_spheres_top

    t0 = time.perf_counter()
    scene = load_scene(resolve_named("scene", args.scene))
    robot = RobotModel.load(scene.robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    t_load = time.perf_counter() - t0
    rng = np.random.default_rng(args.seed)
    qs = torch.as_tensor(sample_uniform(robot, args.samples, rng, base_box=scene.workspace), dtype=torch.float32)
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
    summary = {
        "scene": scene.name, "robot": robot.name, "dof": robot.dof, "joints": robot.joint_names,
        "obstacles": len(scene.obstacles), "targets": scene.target_names,
        "samples": len(qs), "collision_free": int(free.sum()),
        "checks_per_s": round(len(qs) / t_check), "load_s": round(t_load, 3),
        "camera_height_range_m": [round(float(cams[:, 2, 3].min()), 3), round(float(cams[:, 2, 3].max()), 3)]
        if len(cams) else None,
        "problems": problems, "picture": str(picture),
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
    return 0
