"""``demo``: the node suite in closed loop with a simulated robot, on the default scene and the shipped mocap recording.

    python -m psprm_ros.demo [--params config/ros/dynamic_person.yaml] [--recording config/recordings/person_turning.csv]
                             [--out out] [--nodes 3000] [--timeout 120] [--suite processes|one-process]
                             [--in-process] [--no-oracle] [--fresh-roadmap]

1. starts the suite (roadmap server, perception scorer, replan monitor and robot adapter; ``scripts/run_nodes.sh``,
   a process per node, or ``scripts/run_all_in_one.sh`` with ``--suite one-process``) and ``sim_robot`` (a kinematic
   Stretch 2 behind the interfaces a real one offers: its controller's JointTrajectory topic and cmd_vel, publishing
   /joint_states and /odom) as their own processes (``--in-process``: all in this one). Apart, the planner does not
   share its interpreter lock with the monitor's 120 Hz mocap input and the adapter's control loop: in the same
   closed loop its replans take about half as long (docs/benchmarks.md);
2. once the roadmap is ready (built, or loaded from the cache), replays the recorded person turning side to side
   (120 Hz PoseStamped topics, looped) and sends the goal (either goal region of the scene);
3. the robot adapter executes every planned trajectory on the simulated robot; this process records what the robot
   reports (/odom, /joint_states) and every pose it replayed, until the robot rests at a goal (or ``--timeout``);
4. prints every plan and replan (triggers, latency from the pose message to the trajectory), the executed motion, the
   executed configurations in collision with the replayed person (pose at that instant), and the oracle's verdict
   (rendered views + the real face detector) along the executed motion; writes ``<out>/ros_demo.json`` (with
   ``reached_goal``, ``executed_collisions``, ``pose_to_trajectory_ms_median`` / ``_p95``, ``first_plan_s``) and
   ``<out>/ros_demo.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import conversions as cv
from .probe import claim_domain_id

ROOT = Path(__file__).resolve().parent.parent


class Record:
    """What the demo saw: the robot's reports, the poses it replayed, with perf_counter times."""

    def __init__(self, node, robot, adapter_name: str, frames):
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

        from .adapters import load_adapter
        from .robot_state import RobotStateTracker

        self.lock = threading.Lock()
        self.tracker = RobotStateTracker(robot, frames, "odom", load_adapter(adapter_name, robot).name_map(),
                                         timeout_s=1.0)
        self.executed: list = []  # (t, q)
        self.poses: list = []  # (t, body, p, q) as replayed
        node.create_subscription(Odometry, "/odom", self._odom, 50)
        node.create_subscription(JointState, "/joint_states", self._joints, 50)

    def _odom(self, m):
        with self.lock:
            try:
                self.tracker.update_odometry(m, time.perf_counter())
            except Exception:
                pass

    def _joints(self, m):
        t = time.perf_counter()
        with self.lock:
            try:
                self.tracker.update_joints(m, t)
            except Exception:
                return
            q, _ = self.tracker.state(t)
            if q is not None:
                self.executed.append((t, q))

    def on_sample(self, body, t_rec, p, q):
        with self.lock:
            self.poses.append((time.perf_counter(), body, np.array(p, float), np.array(q, float)))

    def latest(self):
        with self.lock:
            return self.executed[-1] if self.executed else None


def rss_mb(pid: int) -> float:
    """Resident memory (MB) of a process and all its descendants: the suite started as one process or as a process
    per node (``run_nodes.sh``: a shell and its four children)."""
    children: dict = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    total, todo, found = 0.0, [pid], False
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += float(line.split()[1]) / 1024.0
                    found = True
        except OSError:
            pass
    return total if found else float("nan")


#: How the closed loop starts the node suite: one process (``run_all_in_one.sh``) or a process per node
#: (``run_nodes.sh``).
SUITE_SCRIPTS = {"one-process": "run_all_in_one.sh", "processes": "run_nodes.sh"}


class ClosedLoop:
    """The suite (``run_all_in_one.sh``, or ``run_nodes.sh`` with ``suite="processes"``) and ``sim_robot``
    (``run_sim_robot.sh``) as their own processes, and a client node (:class:`~psprm_ros.probe.Probe`) spinning in this
    one; ``close()`` ends all of it."""

    def __init__(self, params_file: str, overrides: dict, out: Path, prefix: str, domain: int,
                 suite: str = "one-process"):
        if suite not in SUITE_SCRIPTS:
            raise ValueError(f"suite must be one of {', '.join(SUITE_SCRIPTS)}, got {suite!r}")
        self.params_file, self.overrides, self.out, self.prefix = params_file, overrides, out, prefix
        self.domain, self.suite = domain, suite
        self.procs: dict = {}
        self.ex = self.ctx = self.probe = None

    def start(self, say=None) -> "ClosedLoop":
        import rclpy

        from .probe import Probe
        from .spinning import NodeSpinner

        env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain), PYTHONUNBUFFERED="1")
        suite = ["bash", str(ROOT / "scripts" / SUITE_SCRIPTS[self.suite]), self.params_file]
        for k, v in self.overrides.items():
            suite += ["-p", f"{k}:={v}"]
        sim = ["bash", str(ROOT / "scripts" / "run_sim_robot.sh"), self.params_file]
        for name, cmd in (("suite", suite), ("sim_robot", sim)):
            log_path = self.out / f"{self.prefix}_{name}.log"
            self.procs[name] = subprocess.Popen(cmd, env=env, stdout=open(log_path, "w"), stderr=subprocess.STDOUT,
                                                start_new_session=True)
            if say:
                say(f"[{self.prefix}] started {name}: {' '.join(cmd[1:])} (log {log_path})")
        self.ctx = rclpy.Context()
        self.ctx.init(domain_id=self.domain)
        self.probe = Probe(context=self.ctx)
        self.ex = NodeSpinner(self.ctx)
        self.ex.add(self.probe.node)
        self.ex.start()
        return self

    def close(self) -> None:
        try:
            self.ex.shutdown(timeout_sec=1.0)
            self.probe.destroy()
            self.ctx.try_shutdown()
        except Exception:
            pass
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)  # the adapter stops the robot on its way out
        for p in self.procs.values():
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def _params_frames(params_file: str, scene_frame: str):
    """The input frames of the params file's shared section (the demo reads /odom as the nodes do)."""
    import yaml

    from .frames import FrameTable

    data = yaml.safe_load(Path(params_file).read_text()) or {}
    shared = (data.get("/**") or {}).get("ros__parameters", {})
    table = FrameTable(scene_frame)
    for n in shared.get("input_frames", []) or []:
        spec = (shared.get("input_frame") or {}).get(n, {})
        table.add(n, spec.get("xyz", [0, 0, 0]), spec.get("quat", [0, 0, 0, 1]))
    return table


def at_goal(scene, q) -> str:
    """Name of the scene goal region whose tolerances contain the base of ``q`` ("" = none)."""
    for g in scene.goals:
        if math.hypot(q[0] - g.base[0], q[1] - g.base[1]) <= g.xy_tolerance and \
                abs(math.remainder(q[2] - g.base[2], 2 * math.pi)) <= g.theta_tolerance:
            return g.name
    return ""


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", default=str(ROOT / "config" / "ros" / "dynamic_person.yaml"))
    ap.add_argument("--recording", default=str(ROOT / "config" / "recordings" / "person_turning.csv"))
    ap.add_argument("--out", default="out")
    ap.add_argument("--nodes", type=int, default=3000)
    ap.add_argument("--timeout", type=float, default=120.0, help="longest closed-loop run after the first plan (s)")
    ap.add_argument("--in-process", action="store_true", help="run the suite and the simulated robot in this process")
    ap.add_argument("--suite", choices=sorted(SUITE_SCRIPTS), default="processes",
                    help="the node suite as a process per node (run_nodes.sh; the planner does not share its "
                         "interpreter with the 120 Hz mocap input) or in one process (run_all_in_one.sh)")
    ap.add_argument("--no-oracle", action="store_true", help="skip the oracle evaluation (no detector needed)")
    ap.add_argument("--oracle-every", type=float, default=1.0, help="oracle sample spacing along the motion (s)")
    ap.add_argument("--fresh-roadmap", action="store_true", help="build the roadmap (not from the cache, not saved)")
    ap.add_argument("--domain-id", type=int, default=0)
    a = ap.parse_args(argv[1:])
    t_start = time.perf_counter()
    import logging

    logging.basicConfig(level=logging.WARNING)

    from psprm_core.paths import resolve_named
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    from .heap import freeze_long_lived
    from .mocap_replay import Replayer
    from .probe import InProcessSuite
    from .recordings import load_recording

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = load_recording(a.recording)
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = RobotModel.load(scene.robot)
    domain = a.domain_id or claim_domain_id(100, 200)
    overrides = {"roadmap_server:n_nodes": a.nodes, "robot_adapter:interface": "topic"}
    if a.fresh_roadmap:
        overrides["roadmap_server:roadmap_file"] = "none"
    say = lambda m: print(m, flush=True)  # noqa: E731
    say(f"[demo] scene {scene.name}, robot {robot.name}, recording {Path(a.recording).name} "
        f"({rec.duration:.1f} s, bodies {', '.join(rec.bodies)}, {rec.rate_hz(rec.bodies[0]):.0f} Hz, looped)")
    loop, suite = None, None
    result = {}
    try:
        if a.in_process:
            suite = InProcessSuite({k.split(":")[-1]: v for k, v in overrides.items()}, domain_id=domain,
                                   params_file=a.params, nodes=("server", "scorer", "monitor", "adapter", "sim"))
            suite.__enter__()
            probe = suite.probe
        else:
            loop = ClosedLoop(a.params, overrides, out, "ros_demo", domain, suite=a.suite).start(say)
            probe = loop.probe
        record = Record(probe.node, robot, "stretch2", _params_frames(a.params, scene.frame))
        wall_minus_perf = time.time() - time.perf_counter()
        ready = probe.wait_ready(timeout=1200)
        if not ready:
            raise RuntimeError("the suite did not become ready (see the suite log)")
        t_ready = time.perf_counter()
        say(f"[demo] suite ready {t_ready - t_start:.1f} s after start: {ready.split(': ', 1)[-1]}")
        probe.wait_subscribers("/mocap/person_face/pose", timeout=30)
        probe.wait_subscribers("/psprm/goal_regions", timeout=30)
        if not probe.wait_for(lambda: record.latest() is not None, 30):
            raise RuntimeError("no /joint_states + /odom from the simulated robot")
        replay = Replayer(probe.node, rec, loop=True, on_sample=record.on_sample)
        freeze_long_lived()  # as the nodes do: no full collection walks the start-up's objects while it measures
        n0 = len(probe.trajectories)
        t_replay = time.perf_counter()
        replay.start()
        goals = [g.name for g in scene.goals]
        time.sleep(0.2)
        probe.publish_regions(goals)
        say(f"[demo] replaying the person at 120 Hz (looped); goal: {' or '.join(goals)}")
        got = probe.wait_for(lambda: [(t, m) for t, m in probe.trajectories[n0:] if len(m.points) > 1], 60)
        if not got:
            raise RuntimeError("no trajectory within 60 s of the goal")
        t_first, first = got[0]
        first_plan_s = t_first - t_start
        say(f"[demo] first plan {first_plan_s:.1f} s after start ({t_first - t_ready:.1f} s after ready): "
            f"{len(first.points)} points, {cv.duration_to_sec(first.points[-1].time_from_start):.1f} s")
        reached = ""
        deadline = time.perf_counter() + a.timeout
        rest_since = None
        while time.perf_counter() < deadline:
            time.sleep(0.2)
            last = record.latest()
            if last is None:
                continue
            g = at_goal(scene, last[1])
            with record.lock:
                recent = [q[:3] for t, q in record.executed if t > last[0] - 1.0]
            # the base at rest (the head may keep re-aiming at the turning person)
            still = len(recent) > 5 and np.abs(np.ptp(np.array(recent), axis=0)).max() < 5e-3
            if g and still:
                rest_since = rest_since or time.perf_counter()
                if time.perf_counter() - rest_since > 1.0:
                    reached = g
                    break
            else:
                rest_since = None
        replay.stop()
        t_end = time.perf_counter()
        say(f"[demo] {'robot at rest at goal ' + reached if reached else 'goal NOT reached'} "
            f"{t_end - t_replay:.1f} s after the replay started")
        result = analyse(a, scene, robot, probe, record, first, t_first, t_replay, t_end, wall_minus_perf, say)
        result.update(reached_goal=bool(reached), goal=reached, first_plan_s=round(first_plan_s, 2),
                      ready_s=round(t_ready - t_start, 2), suite="in-process" if a.in_process else a.suite,
                      suite_rss_mb=None if loop is None else round(rss_mb(loop.procs["suite"].pid)),
                      load_avg_1min=round(os.getloadavg()[0], 2), cpus=os.cpu_count(),
                      fresh_roadmap=bool(a.fresh_roadmap))
        with probe.cond:
            statuses = list(probe.statuses)
        result["adapter_refusals"] = sum(1 for _, n, t in statuses if n == "robot_adapter" and "refused" in t)
        result["controller_refusals"] = sum(1 for _, n, t in statuses if n == "sim_robot" and "refused" in t)
        say(f"[demo] result: reached_goal {result['reached_goal']} ({reached or '-'}), executed collisions "
            f"{result['executed_collisions']}, pose->trajectory median {result['pose_to_trajectory_ms_median']} ms "
            f"/ p95 {result['pose_to_trajectory_ms_p95']} ms, first plan {result['first_plan_s']} s "
            f"(load average {result['load_avg_1min']} on {result['cpus']} cores)")
    finally:
        if suite is not None:
            suite.__exit__(None, None, None)
        if loop is not None:
            loop.close()
    if result:
        (out / "ros_demo.json").write_text(json.dumps(result, indent=1))
        say(f"[demo] wrote {out / 'ros_demo.png'} and {out / 'ros_demo.json'}")
    return 0 if result.get("reached_goal") and result.get("executed_collisions") == 0 else 1


GOAL_REASONS = ("goal_received", "goal_changed", "no_plan", "plan requested")


def _goal_triggered(row) -> bool:
    return any(r in GOAL_REASONS for r in (row.get("reasons") or []))


def _scene_with(scene, poses: dict):
    s = scene
    for b, (p, q) in poses.items():
        s = s.with_target_pose(b, p, q) if b in scene.target_names else s.with_obstacle_pose(b, p, q)
    return s


def person_at(record: Record, t: float) -> dict:
    """The latest replayed pose of each body at time ``t`` (perf_counter)."""
    out = {}
    with record.lock:
        for tt, b, p, q in record.poses:
            if tt > t:
                break
            out[b] = (p, q)
    return out


def analyse(a, scene, robot, probe, record, first, t_first, t_replay, t_end, wall_minus_perf, say) -> dict:
    import torch

    from psprm_core.collision import CollisionChecker

    with probe.cond:
        infos = list(probe.infos)
        trajs = list(probe.trajectories)
    rows = []
    for t, info in infos:
        if t < t_replay - 1.0 or t > t_end:
            continue
        rx = [tt for tt, _ in trajs if tt <= t + 1e-6]
        e2e = at_client = None
        if info.get("input_stamp") and rx and not info.get("kept_last") and not info.get("kept") \
                and not info.get("stop") and info.get("success"):
            # the suite's latency: the pose message's stamp to the trajectory's publication (the server's clock,
            # the same wall clock); and as this client received it (its own callbacks and the replay add to it)
            if info.get("published_stamp"):
                e2e = (info["published_stamp"] - info["input_stamp"]) * 1e3
            at_client = (rx[-1] + wall_minus_perf - info["input_stamp"]) * 1e3
        rows.append({"t": round(t - t_replay, 2), "reasons": info.get("reasons"), "success": info.get("success"),
                     "stop": bool(info.get("stop")), "kept": bool(info.get("kept")), "goal_index": info.get("goal_index"),
                     "pose_to_trajectory_ms": None if e2e is None else round(e2e, 1),
                     "at_client_ms": None if at_client is None else round(at_client, 1),
                     "server_ms": info.get("latency_ms"), "replan_ms": info.get("replan_ms"),
                     "apply_ms": info.get("apply_ms"), "msg_ms": info.get("msg_ms"), "check_ms": info.get("check_ms"),
                     "input_age_ms": info.get("input_age_ms"), "triggers_ms": info.get("triggers_ms"),
                     "predicted_score": info.get("mean_score"), "reason": info.get("reason")})
    goal_names = [g.name for g in scene.goals]
    say("[demo] plans (t = seconds since the replay started):")
    for r in rows:
        what = "STOP" if r["stop"] else ("kept" if r["kept"] else "plan" if r["success"] else "FAILED")
        gi = r["goal_index"]
        goal = goal_names[gi] if r["success"] and gi is not None and 0 <= gi < len(goal_names) else "-"
        lat = "" if r["pose_to_trajectory_ms"] is None else f", pose->trajectory {r['pose_to_trajectory_ms']:.0f} ms"
        rp = "" if r["replan_ms"] is None else f", replan {r['replan_ms']:.0f} ms"
        sc = "" if r["predicted_score"] is None else f", predicted score {r['predicted_score']:.3f}"
        say(f"  t={r['t']:6.2f}  {what:6s} -> {goal:10s} triggers: {', '.join(r['reasons'] or [])}{lat}{rp}{sc}")
    # pose -> trajectory: plans a pose triggered (a move, a score or collision trigger after it); plans for a new
    # goal or on request are goal -> trajectory (their first input is the goal, not a pose)
    lat = np.array([r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                    and not _goal_triggered(r)], float)
    goal_lat = [r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                and _goal_triggered(r)]
    client = np.array([r["at_client_ms"] for r in rows if r["at_client_ms"] is not None and not _goal_triggered(r)],
                      float)
    # the executed motion against the replayed person at each instant
    with record.lock:
        ex = [(t, q) for t, q in record.executed if t_replay <= t <= t_end]
    T = np.array([t for t, _ in ex])
    Q = np.array([q for _, q in ex])
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    collided, idx_bad = 0, []
    with record.lock:
        poses = list(record.poses)
    k = 0
    cur: dict = {}
    for i, t in enumerate(T):
        while k < len(poses) and poses[k][0] <= t:
            cur[poses[k][1]] = (poses[k][2], poses[k][3])
            k += 1
        checker.set_boxes(_scene_with(scene, cur).collision_boxes())
        if bool(checker.check(torch.as_tensor(Q[i:i + 1], dtype=torch.float32))[0]):
            collided += 1
            idx_bad.append(i)
    dist = float(np.sum(np.hypot(*np.diff(Q[:, :2], axis=0).T))) if len(Q) > 1 else 0.0
    say(f"[demo] executed motion: {len(Q)} configurations over {T[-1] - T[0] if len(T) else 0:.1f} s "
        f"(reported at {len(Q) / max(1e-9, T[-1] - T[0]) if len(T) > 1 else 0:.0f} Hz), base drove {dist:.2f} m "
        f"from ({Q[0, 0]:.2f}, {Q[0, 1]:.2f}) to ({Q[-1, 0]:.2f}, {Q[-1, 1]:.2f}, yaw {Q[-1, 2]:.2f}); "
        f"{collided} configurations in collision with the replayed person")
    # oracle along the executed motion
    ts = np.arange(T[0], T[-1] + 1e-9, a.oracle_every) if len(T) else np.zeros(0)
    Qs = np.array([Q[min(np.searchsorted(T, t), len(T) - 1)] for t in ts]).reshape(-1, robot.dof)
    people = [person_at(record, t) for t in ts]
    # first plan only: where the robot would have been, had it executed the first trajectory without replanning,
    # judged against the same replayed person at the same instants
    ts0, Q0 = first_plan_samples(first, robot, t_first, a.oracle_every)
    people0 = [person_at(record, t) for t in ts0]
    oracle, detected, oracle0, detected0 = [], [], [], []
    if not a.no_oracle and len(ts):
        try:
            from psprm_core.perception.oracle import Oracle

            t0 = time.perf_counter()
            with Oracle(scene, intrinsics=robot.config.intrinsics) as orc:
                for views, who, score, det in ((Qs, people, oracle, detected), (Q0, people0, oracle0, detected0)):
                    with torch.no_grad():
                        cams = robot.camera_poses(torch.as_tensor(views, dtype=torch.float32)).double().numpy()
                    for i in range(len(views)):
                        for b, (p, q) in who[i].items():
                            (orc.set_target_pose if b in scene.target_names else orc.set_obstacle_pose)(b, p, q)
                        r = orc.score(cams[i], "person_face", keep_image=False)
                        score.append(float(r.score))
                        det.append(bool(r.detected))
            say(f"[demo] oracle: {len(ts)} rendered views along the executed motion scored by the face detector in "
                f"{time.perf_counter() - t0:.1f} s: face detected in {np.mean(detected):.0%} of them, mean score "
                f"{np.mean(oracle):.3f}; along the first plan alone ({len(ts0)} views, no replanning): "
                f"{np.mean(detected0) if detected0 else float('nan'):.0%}, mean score "
                f"{np.mean(oracle0) if oracle0 else float('nan'):.3f}")
        except Exception as exc:  # detectors not installed: report and continue without
            say(f"[demo] oracle evaluation skipped: {exc}")
    n_ok = sum(1 for r in rows if r["success"] and not r["stop"] and not r["kept"])
    summary = {
        "plans_ok": n_ok, "replans": max(0, n_ok - 1), "kept": sum(r["kept"] for r in rows),
        "stops": sum(r["stop"] for r in rows),
        "failed": sum(1 for r in rows if not r["success"] and not r["stop"]),
        "pose_to_trajectory_ms_median": round(float(np.median(lat)), 1) if len(lat) else None,
        "pose_to_trajectory_ms_p95": round(float(np.percentile(lat, 95)), 1) if len(lat) else None,
        "pose_to_trajectory_ms_max": round(float(lat.max()), 1) if len(lat) else None,
        "latency_samples": int(len(lat)),
        "pose_to_trajectory_at_client_ms_median": round(float(np.median(client)), 1) if len(client) else None,
        "pose_to_trajectory_at_client_ms_p95": round(float(np.percentile(client, 95)), 1) if len(client) else None,
        "goal_to_trajectory_ms": [round(float(v), 1) for v in goal_lat],
        **{f"{k}_median": (round(float(np.median(v)), 1) if v else None) for k, v in
           ((k, [r[k] for r in rows if r.get(k) is not None]) for k in ("server_ms", "replan_ms", "apply_ms",
                                                                        "msg_ms", "check_ms", "input_age_ms", "triggers_ms"))},
        "executed_configurations": int(len(Q)), "executed_collisions": int(collided),
        "executed_distance_m": round(dist, 3), "final_base": [round(float(v), 3) for v in Q[-1, :3]] if len(Q) else None,
        "oracle_detected_fraction": round(float(np.mean(detected)), 3) if detected else None,
        "oracle_mean": round(float(np.mean(oracle)), 4) if oracle else None, "oracle_views": len(oracle),
        "first_plan_only_detected_fraction": round(float(np.mean(detected0)), 3) if detected0 else None,
        "first_plan_only_oracle_mean": round(float(np.mean(oracle0)), 4) if oracle0 else None,
        "first_plan_only_views": len(oracle0),
    }
    say(f"[demo] {n_ok} plans ({summary['replans']} replans), {summary['kept']} replans not adopted (no better than "
        f"the trajectory under way), {summary['stops']} stops, {summary['failed']} failed; "
        f"pose->trajectory latency median {summary['pose_to_trajectory_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_ms_p95']} ms, max {summary['pose_to_trajectory_ms_max']} ms "
        f"({len(lat)} plans triggered by a pose; goal -> trajectory {summary['goal_to_trajectory_ms']} ms); as "
        f"received by this client: median {summary['pose_to_trajectory_at_client_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_at_client_ms_p95']} ms")
    try:
        _figure(Path(a.out) / "ros_demo.png", scene, record, first, robot, Q, T, ts, oracle, rows, t_replay)
    except Exception as exc:  # the figure is a report, never a reason to lose the result
        say(f"[demo] figure failed: {exc}")
    return {**summary, "plans": rows, "oracle": oracle, "oracle_t": (ts - t_replay).tolist() if len(ts) else []}


def first_plan_samples(first, robot, t_first: float, every: float) -> tuple:
    """Instants (perf_counter, every ``every`` s from ``t_first`` to the end of the first trajectory) and the
    configurations (K, dof) the first trajectory holds then (linear between its points): the motion of a robot that
    executes its first plan and never replans."""
    P = cv.joint_trajectory_positions(first, robot.joint_names)
    tp = np.array([cv.duration_to_sec(p.time_from_start) for p in first.points], float)
    tau = np.arange(0.0, tp[-1] + 1e-9, every) if len(tp) else np.zeros(0)
    Q = np.stack([np.interp(tau, tp, P[:, j]) for j in range(P.shape[1])], -1) if len(tau) else P[:0]
    if robot.mobile and len(tau):  # the heading the short way between points
        Q[:, 2] = np.interp(tau, tp, np.unwrap(P[:, 2]))
    return t_first + tau, Q


def _figure(path, scene, record, first, robot, Q, T, ts, oracle, rows, t_replay) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from psprm_core.evaluation import viz

    fig = Figure(figsize=(14, 5.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    viz.plot_scene_top(ax, scene, show_labels=True)
    P0 = cv.joint_trajectory_positions(first, robot.joint_names)
    ax.plot(P0[:, 0], P0[:, 1], "--", color="0.4", lw=1.2, label="first plan")
    ax.plot(Q[:, 0], Q[:, 1], color="k", lw=1.5, label="executed (sim_robot /odom)")
    with record.lock:
        face = [(t, p, q) for t, b, p, q in record.poses if b == "person_face"]
    for t, p, q in face[::240]:
        yaw = cv.yaw_of(q)
        ax.arrow(p[0], p[1], 0.35 * np.cos(yaw), 0.35 * np.sin(yaw), width=0.01, color="tab:orange", alpha=0.5)
    ax.set_title("dynamic_person: closed loop (adapter + sim_robot), person replayed")
    ax.legend(loc="lower right", fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    tf = np.array([t for t, _, _ in face]) - t_replay
    ax2.plot(tf, np.unwrap([cv.yaw_of(q) for _, _, q in face]), color="tab:orange", lw=1, label="face yaw (rad)")
    ax2.set_xlabel("time since the replay started (s)")
    ax2.set_ylabel("face yaw (rad)")
    for r in rows:
        ax2.axvline(r["t"], color="red" if r["stop"] else "0.6", lw=0.8, ls=":" if r["success"] else "-")
    if oracle:
        ax3 = ax2.twinx()
        ax3.plot(ts - t_replay, oracle, color="tab:blue", label="oracle score along the executed motion")
        ax3.set_ylim(0, 1.05)
        ax3.set_ylabel("oracle score")
        ax3.legend(fontsize=7, loc="upper right")
    ax2.set_title("person turning; dotted lines = plans/replans")
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
