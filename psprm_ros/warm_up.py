"""``python -m psprm_ros.warm_up``: compile the planner's numba kernels into their on-disk cache (a set-up step).

Builds a small throw-away roadmap of a scene (not saved), loads its query kernels and runs one replan with the
replanning settings the nodes use, so that every compiled path the roadmap server takes (build, warm-up, exact-
heuristic replans) is in the cache before the nodes start. Prints one JSON line with the times.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from . import core, planner_setup


def main(args=None) -> int:
    ap = argparse.ArgumentParser(prog="warm_up", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="dynamic_person")
    ap.add_argument("--nodes", type=int, default=200)
    ap.add_argument("--replan-settings", default="replan_reactive")
    a = ap.parse_args(sys.argv[1:] if args is None else args)
    import logging

    logging.basicConfig(level=logging.ERROR)
    import torch

    torch.set_num_threads(2)

    t0 = time.perf_counter()
    scene, robot = core.load_scene_and_robot(a.scene)
    targets = core.scene_targets(scene, [])
    spec = planner_setup.PlannerSpec(settings={"roadmap.n_nodes": a.nodes}, roadmap_file="none",
                            replan_settings=a.replan_settings)
    planner = planner_setup.make_planner_for(scene, robot, targets, spec)
    info = planner_setup.build_or_load(planner, scene, spec)
    rp = planner_setup.make_replanner(planner, a.replan_settings)
    rp.set_robot_state(core.start_configuration(robot, scene))
    if scene.goals:
        rp.set_goals(core.goal_region_configurations(robot, scene, [g.name for g in scene.goals]))
        res = rp.replan()
        ok = bool(res.success)
    else:
        ok = None
    print(json.dumps({"scene": a.scene, "nodes": a.nodes, "build_s": round(info.get("seconds", 0.0), 2),
                      "warm_up_s": round(info.get("warm_up_s", 0.0), 2), "replan_ok": ok,
                      "total_s": round(time.perf_counter() - t0, 2)}))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
