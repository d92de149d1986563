"""``psprm plan``: build a PS-PRM roadmap for a scene and target and answer one query."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    from ..planning.psprm import VARIANTS

    p = sub.add_parser("plan", help="plan a perception-aware path with PS-PRM on a shipped scene")
    p.add_argument("--scene", required=True, help="scene name (config/scenes) or YAML path")
    p.add_argument("--target", default=None,
                   help="target name, or several separated by commas (midpoint + averaged scores); "
                        "default: the problem's target")
    p.add_argument("--problem", default=None, help="named problem of the scene (default: the first one with "
                                                   "the target)")
    p.add_argument("--planner", default="neural-psprm-line", choices=sorted(VARIANTS))
    p.add_argument("--preset", default="psprm", choices=["psprm", "psprm_paper"],
                   help="settings preset in config/planners/: the shipped configuration or the paper's")
    p.add_argument("--nodes", type=int, default=None, help="roadmap size (default: the preset's)")
    p.add_argument("--alpha", type=float, default=None,
                   help="Eq. 2 weight (default: the variant's for the settings' objective, settings.default_alpha)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint", default=None, help="surrogate checkpoint (default: the shipped one)")
    p.add_argument("--multi", default="mean", choices=["mean", "priority"], help="several targets: how to combine")
    p.add_argument("--roadmap", default=None, help="load this roadmap file if it matches, else build and save it")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, help="write a figure (top view with roadmap and path, score along it)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..errors import PsprmError
    from ..paths import resolve_named
    from ..planning.factory import make_planner, problem_configurations
    from ..robot import RobotModel
    from ..scene import load_scene

    scene = load_scene(resolve_named("scene", args.scene))
    robot = RobotModel.load(scene.robot)
    targets = [t.strip() for t in args.target.split(",")] if args.target else None
    problems = [p for p in scene.problems if args.problem in (None, p.name) and
                (targets is None or set(p.all_targets) & set(targets))]
    if args.problem and not problems:
        raise PsprmError(f"scene '{scene.name}' has no problem '{args.problem}' for that target")
    if not problems:
        raise PsprmError(f"scene '{scene.name}' has no problem for target(s) {targets}")
    prob = problems[0]
    targets = targets or prob.all_targets
    planner = make_planner(args.planner, scene, targets, robot=robot, checkpoint=args.checkpoint,
                           multi_mode=args.multi, preset=args.preset,
                           options={"roadmap.n_nodes": args.nodes, "seed": args.seed, "scoring.alpha": args.alpha})
    start, goals = problem_configurations(robot, scene, prob)
    loaded = False
    if args.roadmap and Path(args.roadmap).is_file():
        try:
            planner.load(args.roadmap)
            loaded = True
        except PsprmError as exc:
            log.warning("not using %s: %s", args.roadmap, exc)
    if not loaded:
        stats = planner.build(template=start)
        if not stats.get("success"):
            out = {"success": False, "reason": stats.get("reason", "roadmap build failed")}
            print(json.dumps(out) if args.json else out["reason"])
            return 1
        if args.roadmap:
            planner.save(args.roadmap)
    res = planner.plan(start, goals)
    out = {"planner": args.planner, "scene": scene.name, "problem": prob.name, "targets": targets,
           "seed": args.seed, "n_nodes": planner.stats.get("n_nodes"), "n_edges": planner.stats.get("n_edges"),
           "build_s": planner.stats.get("build_s"), "roadmap_loaded": loaded}
    out.update(res.to_dict(robot.joint_names))
    if args.plot and res.success:
        plot_plan(planner, res, args.plot, title=f"{args.planner} on {scene.name}/{prob.name}")
        out["plot"] = args.plot
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{args.planner} on {scene.name} ({prob.name}, target {', '.join(targets)}): "
              f"{'success' if res.success else 'FAILED: ' + res.reason}")
        print(f"  roadmap {out['n_nodes']} nodes / {out['n_edges']} edges, built in {out['build_s']:.2f} s")
        if res.success:
            print(f"  path length {res.path_length:.2f}, mean predicted perception score {res.mean_score:.3f}, "
                  f"query {res.query_ms:.1f} ms, {len(res.waypoints)} waypoints, "
                  f"duration {res.trajectory.times[-1]:.1f} s" if res.trajectory is not None else "")
    return 0 if res.success else 1


def plot_plan(planner, res, path: str, title: str = "") -> None:
    """Top view (scene, roadmap base positions and edges, path coloured by score) + score along the path."""
    import numpy as np
    import torch
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ..evaluation.viz import plot_path_top, plot_roadmap_top, plot_scene_top

    fig = Figure(figsize=(9, 10))
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, 1, height_ratios=[3, 1])
    ax, ax2 = fig.add_subplot(gs[0]), fig.add_subplot(gs[1])
    plot_scene_top(ax, planner.scene, show_labels=True)
    g = planner.graph
    n = planner.n_roadmap_nodes
    e = g.valid_edge_ids()
    e = e[(g.edge_u[e] < n) & (g.edge_v[e] < n)]
    plot_roadmap_top(ax, g.configs[:n, :2], np.stack([g.edge_u[e], g.edge_v[e]], 1))
    plot_path_top(ax, res.dense[:, :2], res.dense_scores, label="path")
    ax.set_title(title, fontsize=10)
    s = np.concatenate([[0], np.cumsum(planner.motion.distance(
        torch.as_tensor(res.dense[:-1]), torch.as_tensor(res.dense[1:])).numpy())])
    ax2.plot(s, res.dense_scores, color="tab:blue")
    ax2.set_xlabel("path length (motion cost)")
    ax2.set_ylabel("perception score")
    ax2.set_ylim(-0.02, 1.02)
    ax2.grid(True, alpha=0.4)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
