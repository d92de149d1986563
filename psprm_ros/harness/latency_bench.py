"""``latency_bench``: pose-message -> replanned-JointTrajectory latency of the all-in-one suite, in one process.

    latency_bench [--params config/ros/dynamic_person.yaml] [--nodes 3000] [--changes 60] [--gap 0.3] [--json]

Starts roadmap_server, perception_scorer and replan_monitor plus a client node in one process (each
node on its own executor, the all-in-one configuration), loads the cached roadmap (or builds it once), plans a first
trajectory, then publishes ``--changes`` target pose changes (the person turning through eight headings, each beyond
the replan thresholds), one at a time, and measures for each the time from publishing the PoseStamped to receiving
the replanned JointTrajectory. Prints one JSON object: median / p95 / mean / max latency, the core's replan time and
the server's own receipt-to-publish time (medians), successes and stops.

``--blocks N``: the stop guard's reaction instead. N times the person's body steps (streamed at 120 Hz) onto a spot
that collides with the next second of the trajectory of the standing robot but not with the robot itself; measured
is the time from the first such pose to the first trajectory message that keeps the robot out of the body: a stop,
or a trajectory clear of the body (judged by the bench's own collision check at the pose it sent). Compare with
``--stop-horizon 0`` (no guard: the robot is only told once the replan is published).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from psprm_core.collision import CollisionChecker
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene

from ..core import start_configuration
from ..interfaces import conversions as cv
from ..runner import self_check
from .probe import InProcessSuite, claim_domain_id

HEADINGS = [2.8, 2.2, 1.5, 0.8, 0.3, -0.6, -1.6, -2.4]


def run(params_file: str, n_nodes: int, changes: int, gap: float, timeout: float, domain_id: int,
        log=print, blocks: int = 0, stop_horizon: float = -1.0) -> dict:
    import torch

    torch.set_num_threads(2)
    # the benchmark's protocol: every target move beyond the thresholds replans at once
    overrides = {"roadmap.n_nodes": int(n_nodes), "stale_timeout_s": 3600.0, "deviation_tolerance": 1000.0,
                 "replan_settings": "replan_reactive"}
    if stop_horizon >= 0:
        overrides["stop_horizon_s"] = float(stop_horizon)
    with InProcessSuite(overrides, domain_id=domain_id, params_file=params_file,
                        nodes=("server", "scorer", "monitor")) as s:
        t0 = time.perf_counter()
        if not s.server.ready.wait(1800):
            raise RuntimeError("roadmap not ready")
        log(f"roadmap {s.server.build_info.get('source')} ({s.server.build_info.get('n_nodes')} nodes) "
            f"in {time.perf_counter() - t0:.1f} s")
        scene = load_scene(resolve_named("scene", s.server.p["scene"]))
        face, body = scene.target("person_face"), scene.obstacle("person_body")
        off = float(np.linalg.norm((face.center - body.center)[:2]))
        s.probe.wait_subscribers("/mocap/person_face/pose")
        s.probe.wait_subscribers("psprm/goal_regions")

        robot = s.server.robot  # a robot standing at the start: its /joint_states and /odom
        state = s.probe.hold_robot_state(start_configuration(robot, scene, s.server.p["start_problem"]),
                                         robot.joint_names)
        n0 = len(s.probe.trajectories)
        s.probe.publish_pose("person_face", face.center, face.quat)
        s.probe.publish_regions([g.name for g in scene.goals])
        if s.probe.wait_trajectory(n0, 120) is None:
            raise RuntimeError("no first trajectory")
        time.sleep(1.0)
        if blocks:
            out = block_reactions(s, scene, robot, blocks, timeout, log)
            state.stop()
            return out
        lat, infos, stops, misses = [], [], 0, 0
        for i in range(changes):
            yaw = HEADINGS[(i + 1) % len(HEADINGS)]
            p = np.r_[body.center[:2] + off * np.array([np.cos(yaw), np.sin(yaw)]), face.center[2]]
            stamp = s.probe.node.get_clock().now().to_msg()
            t_pub = s.probe.publish_pose("person_face", p, cv.yaw_quat(yaw), stamp=stamp)
            key = cv.stamp_to_sec(stamp)

            def mine():  # the plan whose first input was this pose (other plans, e.g. score triggers, are skipped)
                return [(t, x) for t, x in s.probe.infos if x.get("input_stamp") is not None
                        and abs(x["input_stamp"] - key) < 1e-6]
            got = s.probe.wait_for(mine, timeout)
            if not got:
                recent = [f"{n}: {txt[:120]}" for t, n, txt in s.probe.statuses if t >= t_pub and "summary" not in txt]
                log(f"change {i}: no plan for this pose within {timeout} s; statuses since: {recent[-5:]}")
                misses += 1
                continue
            t_info, info = got[0]
            infos.append(info)
            if info.get("stop") or not info.get("success"):
                stops += int(bool(info.get("stop")))
            rx = [t for t, _ in s.probe.trajectories if t_pub < t <= t_info + 1e-6]
            if not rx:
                log(f"change {i}: plan without a new trajectory ({info.get('reason')})")
                continue
            lat.append((rx[-1] - t_pub) * 1e3)
            time.sleep(gap)
        state.stop()
        lat_a = np.array(lat) if lat else np.full(1, np.nan)

        def med(key):
            v = [x[key] for x in infos if x.get(key) is not None]
            return _r(np.median(v)) if v else None
        return {
            "n_nodes": int(s.server.planner.n_roadmap_nodes), "changes": changes, "received": len(lat), "missed": misses,
            "stops": stops, "successes": sum(1 for x in infos if x.get("success")),
            "median_ms": _r(np.median(lat_a)), "p95_ms": _r(np.percentile(lat_a, 95)), "mean_ms": _r(lat_a.mean()),
            "min_ms": _r(lat_a.min()), "max_ms": _r(lat_a.max()),
            "server_receipt_to_publish_median_ms": med("latency_ms"), "apply_median_ms": med("apply_ms"),
            "triggers_median_ms": med("triggers_ms"), "core_replan_median_ms": med("replan_ms"),
            "msg_median_ms": med("msg_ms"), "final_check_median_ms": med("check_ms"),
            "gap_s": gap, "torch_threads": torch.get_num_threads(), "cpus": os.cpu_count(),
            "load_avg_1min": _r(os.getloadavg()[0]),
        }


def block_reactions(s, scene, robot, n: int, timeout: float, log=print) -> dict:
    """The ``--blocks`` protocol (module docstring); the robot stands at the start of the current trajectory."""
    import torch

    body = scene.obstacle("person_body")
    checker = CollisionChecker(robot, workspace=scene.workspace)

    def hits(box_xy, P) -> bool:
        box = scene.with_obstacle_pose("person_body", np.r_[box_xy, body.center[2]], body.quat).obstacle("person_body")
        P = np.vstack([P, 0.5 * (P[1:] + P[:-1])]) if len(P) > 1 else P
        return bool(checker.env_hits(torch.as_tensor(P, dtype=torch.float32), [box]).any())

    rng = np.random.default_rng(0)
    reactions, kinds, skipped = [], [], 0
    for i in range(n):
        msg = s.probe.trajectories[-1][1]
        P = cv.joint_trajectory_positions(msg, robot.joint_names)
        t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
        near = P[t <= 1.0]
        cands = [P[0, :2] + r * np.array([np.cos(a), np.sin(a)]) for r in (0.4, 0.6, 0.8, 1.0)
                 for a in rng.uniform(-np.pi, np.pi, 12)]
        spot = next((xy for xy in cands if len(near) > 1 and hits(xy, near) and not hits(xy, P[:1])), None)
        if spot is None:
            skipped += 1
            continue
        n0 = len(s.probe.trajectories)
        t_pub = time.perf_counter()
        got = None
        while got is None and time.perf_counter() - t_pub < timeout:
            s.probe.publish_pose("person_body", np.r_[spot, body.center[2]], body.quat)
            time.sleep(1 / 120)
            for tt, m in s.probe.trajectories[n0:]:
                Q = cv.joint_trajectory_positions(m, robot.joint_names)
                if len(m.points) == 1 or not hits(spot, Q):
                    got = (tt, "stop" if len(m.points) == 1 else "clear trajectory")
                    break
        if got is None:
            log(f"block {i}: nothing kept the robot out of the body within {timeout} s")
            reactions.append(np.nan)
            kinds.append("none")
        else:
            reactions.append((got[0] - t_pub) * 1e3)
            kinds.append(got[1])
        # the person steps back home; the next trajectory (a replan) is the next block's
        n1 = len(s.probe.trajectories)
        t_back = time.perf_counter()
        while time.perf_counter() - t_back < 3.0:
            s.probe.publish_pose("person_body", body.center, body.quat)
            time.sleep(1 / 120)
        s.probe.publish_regions([g.name for g in scene.goals])
        s.probe.wait_for(lambda: [1 for tt, m in s.probe.trajectories[n1:] if tt > t_back and len(m.points) > 10]
                         and len(s.probe.trajectories[-1][1].points) > 10, timeout)
        time.sleep(0.5)
    r = np.array(reactions, float)
    ok = r[np.isfinite(r)] if np.isfinite(r).any() else np.full(1, np.nan)
    return {"blocks": n, "measured": int(np.isfinite(r).sum()), "skipped_no_spot": skipped,
            "stop_horizon_s": float(s.server.p["stop_horizon_s"]),
            "reaction_median_ms": _r(np.median(ok)), "reaction_p95_ms": _r(np.percentile(ok, 95)),
            "reaction_max_ms": _r(ok.max()), "stops": kinds.count("stop"),
            "clear_trajectories": kinds.count("clear trajectory"), "none": kinds.count("none"),
            "guard_stops": int(s.server.counts["guard_stops"]), "cpus": os.cpu_count(),
            "load_avg_1min": _r(os.getloadavg()[0])}


def _r(x) -> float:
    return round(float(x), 1)


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    from rclpy.utilities import remove_ros_args

    root = Path(__file__).resolve().parents[2]
    ap = argparse.ArgumentParser(prog="latency_bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", default=str(root / "config" / "ros" / "dynamic_person.yaml"))
    ap.add_argument("--nodes", type=int, default=3000, help="roadmap nodes (default 3000)")
    ap.add_argument("--changes", type=int, default=60, help="target pose changes (default 60)")
    ap.add_argument("--gap", type=float, default=0.3, help="pause after each received trajectory (s)")
    ap.add_argument("--timeout", type=float, default=20.0, help="max wait per trajectory (s)")
    ap.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID (default random 100..200)")
    ap.add_argument("--blocks", type=int, default=0,
                    help="measure the stop guard's reaction to N body poses just ahead instead (module docstring)")
    ap.add_argument("--stop-horizon", type=float, default=-1.0,
                    help="the server's stop_horizon_s (< 0: the params file's; 0: no stop guard)")
    ap.add_argument("--json", action="store_true", help="print only the JSON line")
    ap.add_argument("--self-check", action="store_true")
    a = ap.parse_args(remove_ros_args(argv)[1:])
    if a.self_check:
        print(json.dumps(self_check()))
        return 0
    import logging

    logging.basicConfig(level=logging.WARNING)
    log = (lambda *_: None) if a.json else (lambda m: print(m, file=sys.stderr))
    out = run(a.params, a.nodes, a.changes, a.gap, a.timeout, a.domain_id or claim_domain_id(100, 200), log,
              blocks=a.blocks, stop_horizon=a.stop_horizon)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
