"""``demo``: the node suite end to end on the default scene with the shipped mocap recording.

    python -m psprm_ros.demo [--params config/ros/dynamic_person.yaml] [--recording config/recordings/person_turning.csv]
                             [--out out] [--nodes 3000] [--sim-speed 3] [--in-process] [--no-oracle]

1. starts the suite (``scripts/run_all_in_one.sh`` as a separate process; ``--in-process`` runs it in this process),
   waits until the roadmap is ready (built once, ~2 min on 2 cores, then loaded from the cache);
2. sends the goal (either goal region of the scene) and the person's first recorded pose, receives the first plan;
3. replays the recording (a person turning side to side, 120 Hz) as PoseStamped topics while a simulated robot
   executes the latest trajectory (``--sim-speed`` x faster than its timing, so it gets somewhere within the 20 s)
   and reports its joint states to the monitor;
4. prints every plan and replan (triggers, latency from the pose message to the trajectory, predicted score) and
   compares the predicted perception score with the oracle (rendered view + real face detector) along the executed
   motion, also against executing the first plan without replanning; writes ``<out>/ros_demo.png`` and
   ``<out>/ros_demo.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import conversions as cv

ROOT = Path(__file__).resolve().parent.parent


class SimRobot:
    """Executes the latest trajectory from the probe (linear interpolation between its points, ``speed`` x faster)
    and publishes ``/joint_states`` with planning joint names at ``rate`` Hz."""

    def __init__(self, probe, names, q0, speed: float = 3.0, rate: float = 20.0):
        from sensor_msgs.msg import JointState
        from rclpy.qos import qos_profile_sensor_data

        self.probe, self.names, self.speed, self.rate = probe, list(names), speed, rate
        self.q = np.asarray(q0, float).copy()
        self.pub = probe.node.create_publisher(JointState, "/joint_states", qos_profile_sensor_data)
        self.log: list = []  # (t_wall_since_start, q)
        self._n = 0
        self._traj = None
        self._stop = threading.Event()
        self.t_start = time.monotonic()

    def start(self):
        self.t_start = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def stop(self):
        self._stop.set()
        self._thread.join(2.0)

    def _run(self):
        period = 1.0 / self.rate
        while not self._stop.wait(period):
            now = time.monotonic()
            with self.probe.cond:
                n = len(self.probe.trajectories)
                msg = self.probe.trajectories[-1][1] if n else None
            if n != self._n and msg is not None:
                self._n = n
                P = cv.joint_trajectory_positions(msg, self.names)
                t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
                self._traj = (now, t, P)
            if self._traj is not None:
                t0, t, P = self._traj
                el = min((now - t0) * self.speed, t[-1])
                self.q = np.array([np.interp(el, t, P[:, j]) for j in range(P.shape[1])]) if len(t) > 1 else P[0]
            self.log.append((now - self.t_start, self.q.copy()))
            self.pub.publish(cv.planning_joint_state(self.q, self.names, self.probe.node.get_clock().now().to_msg()))


def pose_at(rec, body: str, t: float) -> tuple:
    ts, P, Q = rec.track(body)
    i = int(np.clip(np.searchsorted(ts, t), 0, len(ts) - 1))
    return P[i], Q[i]


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", default=str(ROOT / "config" / "ros" / "dynamic_person.yaml"))
    ap.add_argument("--recording", default=str(ROOT / "config" / "recordings" / "person_turning.csv"))
    ap.add_argument("--out", default="out")
    ap.add_argument("--nodes", type=int, default=3000)
    ap.add_argument("--sim-speed", type=float, default=3.0)
    ap.add_argument("--in-process", action="store_true", help="run the suite in this process")
    ap.add_argument("--no-oracle", action="store_true", help="skip the oracle evaluation (no detector needed)")
    ap.add_argument("--oracle-every", type=float, default=0.5, help="oracle sample spacing along the motion (s)")
    ap.add_argument("--domain-id", type=int, default=0)
    a = ap.parse_args(argv[1:])
    import logging

    import torch

    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(2)
    import rclpy

    from psprm_core.paths import resolve_named
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    from .probe import InProcessSuite, Probe
    from .recordings import load_recording

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = load_recording(a.recording)
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = RobotModel.load(scene.robot)
    names = robot.joint_names
    domain = a.domain_id or random.randint(100, 200)
    # the simulated robot runs faster than its trajectories are timed: no deviation trigger
    overrides = {"roadmap_server:n_nodes": a.nodes, "replan_monitor:deviation_tolerance": 1000.0}
    say = lambda m: print(m, flush=True)  # noqa: E731
    say(f"[demo] scene {scene.name}, robot {robot.name}, recording {Path(a.recording).name} "
        f"({rec.duration:.1f} s, bodies {', '.join(rec.bodies)}, {rec.rate_hz(rec.bodies[0]):.0f} Hz)")
    proc = suite = None
    if a.in_process:
        suite = InProcessSuite({k.split(":")[-1]: v for k, v in overrides.items()}, domain_id=domain,
                               params_file=a.params).__enter__()
        probe, ctx = suite.probe, suite.context
    else:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
        cmd = ["bash", str(ROOT / "scripts" / "run_all_in_one.sh"), a.params]
        for k, v in overrides.items():
            cmd += ["-p", f"{k}:={v}"]
        log_path = out / "ros_demo_suite.log"
        proc = subprocess.Popen(cmd, env=env, stdout=open(log_path, "w"), stderr=subprocess.STDOUT,
                                start_new_session=True)
        say(f"[demo] started the suite: {' '.join(cmd[1:])} (log {log_path})")
        ctx = rclpy.Context()
        ctx.init(domain_id=domain)
        probe = Probe(context=ctx)
        from rclpy.executors import MultiThreadedExecutor

        ex = MultiThreadedExecutor(num_threads=3, context=ctx)
        ex.add_node(probe.node)
        threading.Thread(target=lambda: _spin(ex), daemon=True).start()
    wall_minus_perf = time.time() - time.perf_counter()
    result = {}
    try:
        t0 = time.perf_counter()
        ready = probe.wait_ready(timeout=1200)
        if not ready:
            raise RuntimeError("the suite did not become ready (see the suite log)")
        say(f"[demo] suite ready after {time.perf_counter() - t0:.1f} s: {ready.split(': ', 1)[-1]}")
        probe.wait_subscribers("/mocap/person_face/pose", timeout=30)
        probe.wait_subscribers("/psprm/goal_regions", timeout=30)
        from .core import start_configuration

        q0 = start_configuration(robot, scene, "south_to_either")
        sim = SimRobot(probe, names, q0, speed=a.sim_speed)
        from .mocap_replay import Replayer

        replay = Replayer(probe.node, rec)
        t_replay_perf = time.perf_counter()
        n0 = len(probe.trajectories)
        sim.start()
        replay.start()  # the mocap stream runs from now on (the monitor stops the robot when it goes silent)
        goals = [g.name for g in scene.goals]
        time.sleep(0.2)
        probe.publish_regions(goals)
        say(f"[demo] replaying {rec.duration:.0f} s of mocap at 120 Hz; goal: {' or '.join(goals)}; "
            f"robot simulated at x{a.sim_speed:g}")
        got = probe.wait_for(lambda: [m for _, m in probe.trajectories[n0:] if len(m.points) > 1], 60)
        if not got:
            raise RuntimeError("no trajectory within 60 s of the goal")
        first = got[0]
        say(f"[demo] first plan: {len(first.points)} points, "
            f"{cv.duration_to_sec(first.points[-1].time_from_start):.1f} s")
        replay.join(rec.duration + 30)
        time.sleep(1.0)
        sim.stop()
        result = analyse(a, rec, scene, robot, probe, sim, first, t_replay_perf, wall_minus_perf, say)
    finally:
        if suite is not None:
            suite.__exit__(None, None, None)
        if proc is not None:
            try:
                ex.shutdown(timeout_sec=1.0)
                probe.destroy()
                ctx.try_shutdown()
            except Exception:
                pass
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
    if result:
        (out / "ros_demo.json").write_text(json.dumps(result, indent=1))
        say(f"[demo] wrote {out / 'ros_demo.png'} and {out / 'ros_demo.json'}")
    return 0 if result.get("plans_ok", 0) > 0 else 1


def _spin(ex):
    try:
        ex.spin()
    except Exception:
        pass


def analyse(a, rec, scene, robot, probe, sim, first, t_replay_perf, wall_minus_perf, say) -> dict:
    import torch

    names = robot.joint_names
    with probe.cond:
        infos = list(probe.infos)
        trajs = list(probe.trajectories)
        statuses = list(probe.statuses)
    rows = []
    for t, info in infos:
        if t < t_replay_perf - 5:
            continue
        rx = [tt for tt, _ in trajs if tt <= t + 1e-6]
        e2e = None
        if info.get("input_stamp") and rx and not info.get("kept_last"):
            e2e = (rx[-1] + wall_minus_perf - info["input_stamp"]) * 1e3
        rows.append({"t": round(t - t_replay_perf, 2), "reasons": info.get("reasons"), "success": info.get("success"),
                     "stop": bool(info.get("stop")), "goal_index": info.get("goal_index"),
                     "pose_to_trajectory_ms": None if e2e is None else round(e2e, 1),
                     "server_ms": info.get("latency_ms"), "replan_ms": info.get("replan_ms"),
                     "predicted_score": info.get("mean_score"), "reason": info.get("reason")})
    goal_names = [g.name for g in scene.goals]
    say("[demo] plans (t = seconds since the replay started):")
    for r in rows:
        what = "STOP" if r["stop"] else ("plan" if r["success"] else "FAILED")
        goal = goal_names[r["goal_index"]] if r["success"] and r["goal_index"] is not None and r["goal_index"] >= 0 \
            and r["goal_index"] < len(goal_names) else "-"
        lat = "" if r["pose_to_trajectory_ms"] is None else f", pose->trajectory {r['pose_to_trajectory_ms']:.0f} ms"
        rp = "" if r["replan_ms"] is None else f", replan {r['replan_ms']:.0f} ms"
        sc = "" if r["predicted_score"] is None else f", predicted score {r['predicted_score']:.3f}"
        say(f"  t={r['t']:6.2f}  {what:6s} -> {goal:10s} triggers: {', '.join(r['reasons'] or [])}{lat}{rp}{sc}")
    warnings = [s for s in statuses if s[2].startswith("warning") and s[0] >= t_replay_perf]
    lat = [r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None and r["t"] > 0]
    # the executed motion, sampled every --oracle-every seconds, with the person's recorded pose at that time
    log_t = np.array([t for t, _ in sim.log])
    log_q = np.array([q for _, q in sim.log])
    ts = np.arange(0.0, min(rec.duration, log_t[-1]) + 1e-9, a.oracle_every)
    Qexec = np.array([log_q[min(np.searchsorted(log_t, t), len(log_t) - 1)] for t in ts])
    P0 = cv.joint_trajectory_positions(first, names)
    t_first = np.array([cv.duration_to_sec(p.time_from_start) for p in first.points])
    Qnoreplan = np.array([[np.interp(t * a.sim_speed, t_first, P0[:, j]) for j in range(len(names))] for t in ts])
    person = [{b: pose_at(rec, b, t) for b in rec.bodies} for t in ts]

    def camera(Q):
        with torch.no_grad():
            return robot.camera_poses(torch.as_tensor(Q, dtype=torch.float32)).double().numpy()

    from psprm_core.planning.factory import make_scorer

    def scene_at(k):
        s = scene
        for b, (p, q) in person[k].items():
            s = s.with_target_pose(b, p, q) if b in scene.target_names else s.with_obstacle_pose(b, p, q)
        return s

    scorer = make_scorer("neural", scene, ["person_face"], robot.config.intrinsics)
    pred = {"replanning": [], "first_plan_only": []}
    for k in range(len(ts)):
        scorer.set_scene(scene_at(k))
        for key, Q in (("replanning", Qexec), ("first_plan_only", Qnoreplan)):
            with torch.no_grad():
                pred[key].append(float(scorer.score(torch.as_tensor(camera(Q[k:k + 1]), dtype=torch.float32))[0]))
    oracle, detected = {}, {}
    if not a.no_oracle:
        try:
            from psprm_core.perception.oracle import Oracle

            t0 = time.perf_counter()
            with Oracle(scene, intrinsics=robot.config.intrinsics) as orc:
                for key, Q in (("replanning", Qexec), ("first_plan_only", Qnoreplan)):
                    T = camera(Q)
                    vals, det = [], []
                    for k in range(len(ts)):
                        for b, (p, q) in person[k].items():
                            (orc.set_target_pose if b in scene.target_names else orc.set_obstacle_pose)(b, p, q)
                        r = orc.score(T[k], "person_face", keep_image=False)
                        vals.append(float(r.score))
                        det.append(bool(r.detected))
                    oracle[key], detected[key] = vals, det
            say(f"[demo] oracle: {2 * len(ts)} rendered views scored by the face detector in "
                f"{time.perf_counter() - t0:.1f} s")
        except Exception as exc:  # detectors not installed: report and continue without
            say(f"[demo] oracle evaluation skipped: {exc}")
    collided = _collisions(robot, scene, rec, log_t, log_q)
    n_ok = sum(1 for r in rows if r["success"] and not r["stop"])
    summary = {
        "plans_ok": n_ok, "replans": max(0, n_ok - 1), "stops": sum(r["stop"] for r in rows),
        "failed": sum(1 for r in rows if not r["success"] and not r["stop"]), "warnings": len(warnings),
        "pose_to_trajectory_ms_median": round(float(np.median(lat)), 1) if lat else None,
        "pose_to_trajectory_ms_max": round(float(np.max(lat)), 1) if lat else None,
        "predicted_mean": {k: round(float(np.mean(v)), 4) for k, v in pred.items()},
        "oracle_mean": {k: round(float(np.mean(v)), 4) for k, v in oracle.items()},
        "oracle_detected_fraction": {k: round(float(np.mean(v)), 3) for k, v in detected.items()},
        "executed_collisions": int(collided), "final_base": [round(float(v), 3) for v in log_q[-1][:3]],
    }
    say(f"[demo] {summary['plans_ok']} plans ({summary['replans']} replans), {summary['stops']} stops, "
        f"{summary['failed']} failed, {summary['warnings']} warnings; pose->trajectory latency median "
        f"{summary['pose_to_trajectory_ms_median']} ms, max {summary['pose_to_trajectory_ms_max']} ms")
    say(f"[demo] along the executed motion (every {a.oracle_every:g} s): predicted score {summary['predicted_mean']}")
    if oracle:
        say(f"[demo] oracle score (face detector on the rendered view): {summary['oracle_mean']}; "
            f"detected fraction {summary['oracle_detected_fraction']}")
    say(f"[demo] executed configurations in collision with the recorded person: {collided}; "
        f"robot ended at base {summary['final_base']}")
    _figure(Path(a.out) / "ros_demo.png", scene, rec, rows, ts, Qexec, P0, log_q, pred, oracle)
    return {**summary, "plans": rows, "t": ts.tolist(), "predicted": pred, "oracle": oracle,
            "warnings_text": [w[2] for w in warnings[:20]]}


def _collisions(robot, scene, rec, log_t, log_q) -> int:
    import torch

    from psprm_core.collision import CollisionChecker

    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    n = 0
    for t, q in zip(log_t[::4], log_q[::4]):
        s = scene
        for b in rec.bodies:
            p, qq = pose_at(rec, b, min(t, rec.duration))
            s = s.with_target_pose(b, p, qq) if b in scene.target_names else s.with_obstacle_pose(b, p, qq)
        checker.set_boxes(s.collision_boxes())
        n += int(checker.check(torch.as_tensor(q[None], dtype=torch.float32))[0])
    return n


def _figure(path, scene, rec, rows, ts, Qexec, P0, log_q, pred, oracle) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from psprm_core import viz

    fig = Figure(figsize=(14, 5.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    viz.plot_scene_top(ax, scene, show_labels=True)
    ax.plot(P0[:, 0], P0[:, 1], "--", color="0.4", lw=1.2, label="first plan")
    sc = np.array(oracle.get("replanning", pred["replanning"]))
    viz.plot_path_top(ax, Qexec[:, :2], sc, label="executed (replanning)", vmin=0, vmax=max(0.05, float(sc.max())))
    ax.plot(log_q[:, 0], log_q[:, 1], color="k", lw=0.6, alpha=0.6)
    tf, Pf, Qf = rec.track("person_face")
    for t in np.arange(0, rec.duration, 2.5):
        i = int(np.searchsorted(tf, t))
        i = min(i, len(tf) - 1)
        yaw = cv.yaw_of(Qf[i])
        ax.arrow(Pf[i, 0], Pf[i, 1], 0.35 * np.cos(yaw), 0.35 * np.sin(yaw), width=0.01, color="tab:orange",
                 alpha=0.5)
    ax.set_title("dynamic_person: executed motion coloured by " + ("oracle" if oracle else "predicted") + " score")
    ax.legend(loc="lower right", fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    yaw = np.unwrap([cv.yaw_of(q) for q in Qf])
    ax2.plot(tf, yaw, color="tab:orange", lw=1, label="face yaw (rad)")
    ax2.set_xlabel("time since replay start (s)")
    ax2.set_ylabel("face yaw (rad)")
    for r in rows:
        if r["t"] >= -0.5:
            ax2.axvline(r["t"], color="red" if r["stop"] else "0.6", lw=0.8, ls=":" if r["success"] else "-")
    ax3 = ax2.twinx()
    for key, st in (("replanning", "-"), ("first_plan_only", "--")):
        if key in oracle:
            ax3.plot(ts, oracle[key], st, color="tab:blue", label=f"oracle, {key}")
        ax3.plot(ts, pred[key], st, color="tab:green", alpha=0.7, label=f"predicted, {key}")
    ax3.set_ylabel("perception score")
    ax3.set_ylim(0, 1.05)
    h1, l1 = ax2.get_legend_handles_labels()
    h2, l2 = ax3.get_legend_handles_labels()
    ax3.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper right")
    ax2.set_title("person turning; dotted lines = plans/replans")
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
