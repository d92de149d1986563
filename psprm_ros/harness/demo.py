"""``demo``: the node suite in closed loop with a simulated robot, on a params file's scene and a mocap recording.

    python -m psprm_ros.harness.demo [--params config/ros/dynamic_person.yaml] [--recording config/recordings/person_turning.csv]
                             [--out out] [--nodes 3000] [--timeout 120] [--suite processes|one-process]
                             [--in-process] [--no-oracle] [--fresh-roadmap]

Everything comes from the params file (:mod:`psprm_ros.harness.demo_config`): scene, robot, adapter, targets, dynamic
obstacles, the robot's start, the goals (the server's goal regions, else its start problem's goal regions or goal
pose) and the topic and input frame of every body; ``--recording`` defaults to the shipped recording of a shipped
params file (:data:`psprm_ros.interfaces.recordings.SHIPPED`).

1. starts the suite (roadmap server, perception scorer, replan monitor and robot adapter; ``scripts/run_nodes.sh``,
   a process per node, or ``scripts/run_all_in_one.sh`` with ``--suite one-process``) and ``sim_robot`` (a kinematic
   model of the params file's robot behind the interfaces its adapter drives: its controllers' JointTrajectory
   topics and cmd_vel, publishing /joint_states and /odom) as their own processes (``--in-process``: all in this
   one). Apart, the planner does not share its interpreter lock with the monitor's 120 Hz mocap input and the
   adapter's control loop: in the same closed loop its replans take about half as long (docs/benchmarks.md);
2. once the roadmap is ready (built, or loaded from the cache), replays the recorded bodies (PoseStamped on the
   monitor's topics, looped) and sends the goal (goal regions by name, or a goal pose);
3. the robot adapter executes every planned trajectory on the simulated robot; this process records what the robot
   reports (/odom, /joint_states, the adapter's /diagnostics) and every pose it replayed, until the robot rests at a
   goal (or ``--timeout``);
4. prints every plan and replan (triggers, latency from the pose message to the trajectory), the executed motion, the
   executed configurations in collision with the replayed bodies (poses at that instant), and the oracle's verdict
   (rendered views + the real detector, every target of the params file) along the executed motion and along the
   first plan alone; writes ``<out>/ros_demo.json`` (strict JSON: ``reached_goal``, ``goal``, ``time_to_goal_s``,
   ``executed_collisions``, ``pose_to_trajectory_ms_median`` / ``_p95``, ``first_plan_s``,
   ``first_plan_duration_s``, ``adopted_replans``, ``declined_replans``, ``goal_switches``, ``stops``,
   ``adapter_refusals``, ``oracle_detected_fraction``, ``cpu_s_during_run``: the CPU seconds of this process, the
   suite, sim_robot, the whole machine and everything else while the robot drove, ...) and ``<out>/ros_demo.png``.
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
from typing import Optional
from pathlib import Path

import numpy as np

from ..interfaces import conversions as cv
from .probe import claim_domain_id

ROOT = Path(__file__).resolve().parents[2]


class Record:
    """What the demo saw: the robot's reports, the poses it replayed, with perf_counter times."""

    def __init__(self, node, robot, adapter_name: str, frames, to_scene=None):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

        from .. import core
        from ..robots.adapters import load_adapter
        from ..robots.robot_state import RobotStateTracker

        self.lock = threading.Lock()
        self.tracker = RobotStateTracker(robot, frames, "odom", load_adapter(adapter_name, robot).name_map(),
                                         timeout_s=1.0)
        self.to_scene = to_scene  # (body, p, q) in its recorded frame -> (p, q) in the scene frame
        self.executed: list = []  # (t, q)
        self.poses: list = []  # (t, body, p, q) as replayed, in the scene frame
        self.adapter_diagnostics: list = []  # (t, {key: value}) of the robot adapter's /diagnostics
        node.create_subscription(Odometry, "odom", self._odom, 50)
        node.create_subscription(JointState, "joint_states", self._joints, 50)
        node.create_subscription(DiagnosticArray, core.DIAGNOSTICS_TOPIC, self._diagnostics, 20)

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

    def _diagnostics(self, m):
        t = time.perf_counter()
        for st in m.status:
            if st.name.endswith("robot_adapter"):
                with self.lock:
                    self.adapter_diagnostics.append((t, {kv.key: kv.value for kv in st.values}))

    def on_sample(self, body, t_rec, p, q):
        if self.to_scene is not None:
            p, q = self.to_scene(body, p, q)
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


def cpu_s(pid: int) -> float:
    """CPU time (user + system, s) a process and all its descendants have used so far (NaN when it is gone)."""
    children: dict = {}
    stats: dict = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        p = int(stat.parent.name)
        children.setdefault(int(fields[1]), []).append(p)
        stats[p] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    total, todo, found = 0.0, [pid], False
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        if p in stats:
            total += stats[p]
            found = True
    return total if found else float("nan")


def machine_busy_s() -> float:
    """CPU time (s, all cores) this machine has spent busy since boot, from ``/proc/stat`` (NaN where unreadable)."""
    try:
        f = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return float("nan")
    return (sum(f[:8]) - f[3] - f[4]) / os.sysconf("SC_CLK_TCK")  # all but idle and iowait (guest is in user)


#: How the closed loop starts the node suite: one process (``run_all_in_one.sh``) or a process per node
#: (``run_nodes.sh``).
SUITE_SCRIPTS = {"one-process": "run_all_in_one.sh", "processes": "run_nodes.sh"}


class ClosedLoop:
    """The suite (``run_all_in_one.sh``, or ``run_nodes.sh`` with ``suite="processes"``) and ``sim_robot``
    (``run_sim_robot.sh``) as their own processes, and a client node (:class:`~psprm_ros.harness.probe.Probe`) spinning in this
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

        from ..spinning import NodeSpinner
        from .probe import Probe

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
    from .demo_config import params_frames, read_params

    return params_frames(read_params(params_file)["roadmap_server"], scene_frame, str(params_file))


def at_goal(scene, q) -> str:
    """Name of the scene goal region whose tolerances contain the base of ``q`` ("" = none)."""
    for g in scene.goals:
        if math.hypot(q[0] - g.base[0], q[1] - g.base[1]) <= g.xy_tolerance and \
                abs(math.remainder(q[2] - g.base[2], 2 * math.pi)) <= g.theta_tolerance:
            return g.name
    return ""


def rest_arrival(T: np.ndarray, Q: np.ndarray, eps: float = 5e-3) -> Optional[float]:
    """The earliest time since which the base (``Q[:, :3]``, heading modulo a turn) has stayed within ``eps`` of its
    last pose: when the robot came to rest where it ended (None without samples)."""
    if not len(T):
        return None
    d = np.abs(np.asarray(Q, float)[:, :3] - np.asarray(Q, float)[-1, :3])
    d[:, 2] = np.abs(np.remainder(d[:, 2] + np.pi, 2 * np.pi) - np.pi)
    moved = np.nonzero(d.max(axis=1) >= eps)[0]
    return float(T[moved[-1] + 1]) if len(moved) else float(T[0])


def strict_json(value):
    """``value`` with every non-finite float (NaN, inf) replaced by None, recursively: strict JSON."""
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def goal_switches(goal_indices) -> int:
    """Changes of the goal between successive adopted plans (``goal_indices`` in plan order; None entries skipped)."""
    seq = [g for g in goal_indices if g is not None]
    return int(sum(1 for a, b in zip(seq, seq[1:]) if a != b))


def adapter_stops(statuses, t0: float, t1: float) -> dict:
    """The robot adapter's stops reported on its ``~/status`` between ``t0`` and ``t1`` (perf_counter), by reason,
    except the execution of the server's stop trajectory (counted as the server's stop)."""
    out: dict = {}
    for t, node, text in statuses:
        if node != "robot_adapter" or not t0 <= t <= t1 or "robot stopped: " not in text:
            continue
        why = text.split("robot stopped: ", 1)[1]
        if why.startswith("stop trajectory received"):
            continue
        key = why.split(":", 1)[0].strip()
        out[key] = out.get(key, 0) + 1
    return out


def main(args=None) -> int:
    """Run the closed loop (see the module docstring); exit status 0 when the robot rests at a goal with no executed
    configuration in collision, 1 otherwise, 2 for bad input (params file, recording)."""
    argv = list(sys.argv if args is None else args)
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", default=str(ROOT / "config" / "ros" / "dynamic_person.yaml"))
    ap.add_argument("--recording", default="",
                    help="CSV or rosbag2 of the moving bodies (default: the shipped recording of the params file)")
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

    from psprm_core.errors import PsprmError

    from ..heap import freeze_long_lived
    from ..interfaces.recordings import load_recording
    from ..mocap_replay import Replayer
    from .demo_config import default_recording, demo_config
    from .probe import InProcessSuite

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    a.recording = a.recording or default_recording(a.params) or ""
    try:
        if not Path(a.params).is_file():
            raise PsprmError(f"params file not found: {a.params}")
        if not a.recording:
            raise PsprmError(f"{a.params}: no shipped recording for this params file; pass --recording")
        rec = load_recording(a.recording)
        cfg = demo_config(a.params, rec)
    except (PsprmError, OSError, ValueError) as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    scene, robot = cfg.scene, cfg.robot
    domain = a.domain_id or claim_domain_id(100, 200)
    overrides = {"roadmap_server:roadmap.n_nodes": a.nodes, "robot_adapter:interface": "topic"}
    if a.fresh_roadmap:
        overrides["roadmap_server:roadmap_file"] = "none"
    say = lambda m: print(m, flush=True)  # noqa: E731
    say(f"[demo] params {a.params}: scene {scene.name}, robot {robot.name}, adapter {cfg.adapter}, targets "
        f"{', '.join(cfg.targets)}, dynamic obstacles {', '.join(cfg.dynamic_obstacles) or '-'}; start "
        f"{cfg.start_problem or scene.problems[0].name if scene.problems else '-'}; recording {Path(a.recording).name} "
        f"({rec.duration:.1f} s, bodies {', '.join(rec.bodies)}, {rec.rate_hz(rec.bodies[0]):.0f} Hz, looped)")
    loop, suite, replay = None, None, None
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
        record = Record(probe.node, robot, cfg.adapter, cfg.frames, to_scene=cfg.to_scene)
        wall_minus_perf = time.time() - time.perf_counter()
        ready = probe.wait_ready(timeout=1200)
        if not ready:
            raise RuntimeError("the suite did not become ready (see the suite log)")
        t_ready = time.perf_counter()
        say(f"[demo] suite ready {t_ready - t_start:.1f} s after start: {ready.split(': ', 1)[-1]}")
        for b in rec.bodies:
            probe.wait_subscribers(cfg.body_topics[b], timeout=30)
        probe.wait_subscribers("psprm/goal_regions" if cfg.goal_regions else "psprm/goal", timeout=30)
        if not probe.wait_for(lambda: record.latest() is not None, 30):
            raise RuntimeError("no /joint_states + /odom from the simulated robot")
        replay = Replayer(probe.node, rec, loop=True, on_sample=record.on_sample, topics=cfg.body_topics)
        freeze_long_lived()  # as the nodes do: no full collection walks the start-up's objects while it measures
        n0 = len(probe.trajectories)
        procs = {} if loop is None else {n: pr.pid for n, pr in loop.procs.items()}
        cpu0 = {n: cpu_s(pid) for n, pid in procs.items()}
        cpu0["demo"] = sum(os.times()[:2])  # this process alone (the suite and sim_robot are its children)
        cpu0["machine"] = machine_busy_s()
        t_replay = time.perf_counter()
        replay.start()
        time.sleep(0.2)
        if cfg.goal_regions:
            probe.publish_regions(cfg.goal_regions)
        else:
            probe.publish_goal(*cfg.goals[0].base, frame=scene.frame)
        say(f"[demo] replaying {', '.join(rec.bodies)} at {rec.rate_hz(rec.bodies[0]):.0f} Hz (looped); goal: "
            f"{' or '.join(cfg.goal_names)} ({'goal regions' if cfg.goal_regions else 'goal pose'} "
            f"{', '.join(str([round(v, 3) for v in g.base]) for g in cfg.goals)})")
        got = probe.wait_for(lambda: [(t, m) for t, m in probe.trajectories[n0:] if len(m.points) > 1], 60)
        if not got:
            raise RuntimeError("no trajectory within 60 s of the goal")
        t_first, first = got[0]
        first_plan_s = t_first - t_start
        first_duration = cv.duration_to_sec(first.points[-1].time_from_start)
        say(f"[demo] first plan {first_plan_s:.1f} s after start ({t_first - t_ready:.1f} s after ready): "
            f"{len(first.points)} points, {first_duration:.1f} s")
        reached = ""
        deadline = time.perf_counter() + a.timeout
        rest_since = None
        while time.perf_counter() < deadline:
            time.sleep(0.2)
            last = record.latest()
            if last is None:
                continue
            g = cfg.at_goal(last[1])
            with record.lock:
                recent = [q[:3] for t, q in record.executed if t > last[0] - 1.0]
            # the base at rest (the camera joints may keep re-aiming at a moving target)
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
        # where the machine's time went during the run: CPU seconds per process tree (2 cores give 2 s per second)
        cpu = {n: round(cpu_s(pid) - cpu0[n], 1) for n, pid in procs.items()}
        cpu["demo"] = round(sum(os.times()[:2]) - cpu0["demo"], 1)
        cpu["machine"] = round(machine_busy_s() - cpu0["machine"], 1)
        cpu["others"] = round(cpu["machine"] - sum(v for k, v in cpu.items() if k != "machine"), 1)
        time_to_goal = None
        if reached:
            with record.lock:
                ex = [(t, q) for t, q in record.executed if t_replay <= t <= t_end]
            t_arrive = rest_arrival(np.array([t for t, _ in ex]), np.array([q for _, q in ex]))
            time_to_goal = None if t_arrive is None else round(t_arrive - t_replay, 2)
        say(f"[demo] {'robot at rest at goal ' + reached if reached else 'goal NOT reached'} "
            f"{t_end - t_replay:.1f} s after the replay started"
            + (f" (at rest there since {time_to_goal} s)" if time_to_goal is not None else ""))
        result = analyse(a, cfg, probe, record, first, t_first, t_replay, t_end, wall_minus_perf, say)
        result.update(reached_goal=bool(reached), goal=reached, time_to_goal_s=time_to_goal,
                      first_plan_s=round(first_plan_s, 2), first_plan_duration_s=round(first_duration, 2),
                      ready_s=round(t_ready - t_start, 2), suite="in-process" if a.in_process else a.suite,
                      suite_rss_mb=None if loop is None else round(rss_mb(loop.procs["suite"].pid)),
                      load_avg_1min=round(os.getloadavg()[0], 2), cpus=os.cpu_count(),
                      fresh_roadmap=bool(a.fresh_roadmap), recording=str(a.recording),
                      cpu_s_during_run={**cpu, "wall_s": round(t_end - t_replay, 1)}, **cfg.describe())
        with probe.cond:
            statuses = list(probe.statuses)
        result["adapter_refusals"] = sum(1 for _, n, t in statuses if n == "robot_adapter" and "refused" in t)
        result["controller_refusals"] = sum(1 for _, n, t in statuses if n == "sim_robot" and "refused" in t)
        by_reason = adapter_stops(statuses, t_replay, t_end)
        with probe.cond:  # the stop trajectories themselves (a stop on request may come without plan info)
            stop_msgs = sum(1 for t, m in probe.trajectories if t_replay <= t <= t_end and len(m.points) <= 1)
        result["server_stops"] = max(result["stops"], stop_msgs)
        result["adapter_stops"] = sum(by_reason.values())
        result["adapter_stop_reasons"] = by_reason
        result["stops"] = result["server_stops"] + result["adapter_stops"]
        with record.lock:
            diag = record.adapter_diagnostics[-1][1] if record.adapter_diagnostics else {}
        result["adapter_diagnostics"] = diag
        say(f"[demo] result: reached_goal {result['reached_goal']} ({reached or '-'}, time to goal "
            f"{result['time_to_goal_s']} s), executed collisions {result['executed_collisions']}, pose->trajectory "
            f"median {result['pose_to_trajectory_ms_median']} ms / p95 {result['pose_to_trajectory_ms_p95']} ms, "
            f"first plan {result['first_plan_s']} s (duration {result['first_plan_duration_s']} s), "
            f"{result['adopted_replans']} replans adopted, {result['declined_replans']} declined, "
            f"{result['goal_switches']} goal switches, {result['stops']} stops ({result['server_stops']} server, "
            f"{result['adapter_stops']} adapter), {result['adapter_refusals']} adapter refusals "
            f"(load average {result['load_avg_1min']} on {result['cpus']} cores)")
    except (PsprmError, RuntimeError) as exc:
        say(f"[demo] failed: {exc}")
    finally:
        if replay is not None:
            replay.stop()  # before the node it publishes through goes
        if suite is not None:
            suite.__exit__(None, None, None)
        if loop is not None:
            loop.close()
    if result:
        (out / "ros_demo.json").write_text(json.dumps(strict_json(result), indent=1, allow_nan=False))
        say(f"[demo] wrote {out / 'ros_demo.png'} and {out / 'ros_demo.json'}")
    return 0 if result.get("reached_goal") and result.get("executed_collisions") == 0 else 1


GOAL_REASONS = ("goal_received", "goal_changed", "no_plan", "plan requested")


def _goal_triggered(row) -> bool:
    """Whether a plan was made for a goal (or on request) rather than triggered by a pose."""
    return any(r in GOAL_REASONS for r in (row.get("reasons") or []))


def _scene_with(scene, poses: dict):
    """``scene`` with each body of ``poses`` (name -> (p, q)) moved there."""
    s = scene
    for b, (p, q) in poses.items():
        s = s.with_target_pose(b, p, q) if b in scene.target_names else s.with_obstacle_pose(b, p, q)
    return s


def bodies_at(record: Record, t: float) -> dict:
    """The latest replayed pose (scene frame) of each body at time ``t`` (perf_counter)."""
    out = {}
    with record.lock:
        for tt, b, p, q in record.poses:
            if tt > t:
                break
            out[b] = (p, q)
    return out


def analyse(a, cfg, probe, record, first, t_first, t_replay, t_end, wall_minus_perf, say) -> dict:
    """Plans, latencies, the executed motion against the replayed bodies, and the oracle's verdict on every target
    of the params file along the executed motion and along the first plan alone; writes the figure."""
    import torch

    from psprm_core.collision import CollisionChecker

    scene, robot = cfg.scene, cfg.robot
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
                     "predicted_score": info.get("mean_score"), "reason": info.get("reason"),
                     "route": info.get("route", "")})
    goal_names = cfg.goal_names
    say("[demo] plans (t = seconds since the replay started):")
    for r in rows:
        what = "STOP" if r["stop"] else ("kept" if r["kept"] else "plan" if r["success"] else "FAILED")
        gi = r["goal_index"]
        goal = goal_names[gi] if r["success"] and gi is not None and 0 <= gi < len(goal_names) else "-"
        lat = "" if r["pose_to_trajectory_ms"] is None else f", pose->trajectory {r['pose_to_trajectory_ms']:.0f} ms"
        rp = "" if r["replan_ms"] is None else f", replan {r['replan_ms']:.0f} ms"
        sc = "" if r["predicted_score"] is None else f", predicted score {r['predicted_score']:.3f}"
        route = f", route: {r['route']}" if r["route"] else ""
        say(f"  t={r['t']:6.2f}  {what:6s} -> {goal:10s} triggers: {', '.join(r['reasons'] or [])}{lat}{rp}{sc}{route}")
    # pose -> trajectory: plans a pose triggered (a move, a score or collision trigger after it); plans for a new
    # goal or on request are goal -> trajectory (their first input is the goal, not a pose)
    lat = np.array([r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                    and not _goal_triggered(r)], float)
    goal_lat = [r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                and _goal_triggered(r)]
    client = np.array([r["at_client_ms"] for r in rows if r["at_client_ms"] is not None and not _goal_triggered(r)],
                      float)
    # the executed motion against the replayed bodies at each instant
    with record.lock:
        ex = [(t, q) for t, q in record.executed if t_replay <= t <= t_end]
    T = np.array([t for t, _ in ex])
    Q = np.array([q for _, q in ex]).reshape(-1, robot.dof)
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
    if len(Q):
        say(f"[demo] executed motion: {len(Q)} configurations over {T[-1] - T[0]:.1f} s (reported at "
            f"{len(Q) / max(1e-9, T[-1] - T[0]):.0f} Hz), base drove {dist:.2f} m from ({Q[0, 0]:.2f}, {Q[0, 1]:.2f}) "
            f"to ({Q[-1, 0]:.2f}, {Q[-1, 1]:.2f}, yaw {Q[-1, 2]:.2f}); {collided} configurations in collision with "
            f"the replayed bodies ({', '.join(cfg.recorded_bodies)})")
    # oracle along the executed motion
    ts = np.arange(T[0], T[-1] + 1e-9, a.oracle_every) if len(T) else np.zeros(0)
    Qs = np.array([Q[min(np.searchsorted(T, t), len(T) - 1)] for t in ts]).reshape(-1, robot.dof)
    seen = [bodies_at(record, t) for t in ts]
    # first plan only: where the robot would have been, had it executed the first trajectory without replanning,
    # judged against the same replayed bodies at the same instants
    ts0, Q0 = first_plan_samples(first, robot, t_first, a.oracle_every)
    seen0 = [bodies_at(record, t) for t in ts0]
    targets = list(cfg.targets)
    oracle = {n: [] for n in targets}  # target -> scores along the executed motion
    detected = {n: [] for n in targets}
    oracle0 = {n: [] for n in targets}  # ... along the first plan alone
    detected0 = {n: [] for n in targets}
    if not a.no_oracle and len(ts):
        try:
            from psprm_core.perception.oracle import Oracle

            t0 = time.perf_counter()
            with Oracle(scene, intrinsics=robot.config.intrinsics) as orc:
                for views, who, score, det in ((Qs, seen, oracle, detected), (Q0, seen0, oracle0, detected0)):
                    with torch.no_grad():
                        cams = robot.camera_poses(torch.as_tensor(views, dtype=torch.float32)).double().numpy()
                    for i in range(len(views)):
                        for b, (p, q) in who[i].items():
                            (orc.set_target_pose if b in scene.target_names else orc.set_obstacle_pose)(b, p, q)
                        for n in targets:
                            r = orc.score(cams[i], n, keep_image=False)
                            score[n].append(float(r.score))
                            det[n].append(bool(r.detected))
            say(f"[demo] oracle: {len(ts)} rendered views along the executed motion and {len(ts0)} along the first "
                f"plan alone (no replanning), each scored for {', '.join(targets)} by the real detector in "
                f"{time.perf_counter() - t0:.1f} s: " + "; ".join(
                    f"{n} detected in {_share(detected[n])} / {_share(detected0[n])} of them, mean score "
                    f"{_mean(oracle[n], 3)} / {_mean(oracle0[n], 3)}" for n in targets))
        except Exception as exc:  # detectors not installed: report and continue without
            say(f"[demo] oracle evaluation skipped: {exc}")
    adopted = [r for r in rows if r["success"] and not r["stop"] and not r["kept"]]
    n_ok = len(adopted)
    summary = {
        "plans_ok": n_ok, "replans": max(0, n_ok - 1), "kept": sum(r["kept"] for r in rows),
        "adopted_replans": max(0, n_ok - 1), "declined_replans": sum(r["kept"] for r in rows),
        "goal_switches": goal_switches(r["goal_index"] for r in adopted),
        "adopted_goals": [goal_names[r["goal_index"]] if r["goal_index"] is not None and
                          0 <= r["goal_index"] < len(goal_names) else None for r in adopted],
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
        "executed_distance_m": round(dist, 3),
        "final_base": [round(float(v), 3) for v in Q[-1, :3]] if len(Q) else None,
        # every target of the params file in every view: the share of (view, target) pairs detected (one target:
        # the share of views), then per target, and the share of views that saw all of them at once
        "oracle_detected_fraction": _pooled(detected), "oracle_mean": _pooled(oracle, 4),
        "oracle_views": len(ts) if any(oracle.values()) else 0,
        "oracle_detected_fraction_by_target": {n: _mean(detected[n], 3) for n in targets},
        "oracle_all_detected_fraction": _all(detected),
        "first_plan_only_detected_fraction": _pooled(detected0), "first_plan_only_oracle_mean": _pooled(oracle0, 4),
        "first_plan_only_views": len(ts0) if any(oracle0.values()) else 0,
        "first_plan_only_detected_fraction_by_target": {n: _mean(detected0[n], 3) for n in targets},
        "first_plan_only_all_detected_fraction": _all(detected0),
    }
    say(f"[demo] {n_ok} plans ({summary['adopted_replans']} replans adopted, {summary['goal_switches']} goal "
        f"switches), {summary['declined_replans']} replans not adopted (no better than the trajectory under way), "
        f"{summary['stops']} stops by the server, {summary['failed']} failed; "
        f"pose->trajectory latency median {summary['pose_to_trajectory_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_ms_p95']} ms, max {summary['pose_to_trajectory_ms_max']} ms "
        f"({len(lat)} plans triggered by a pose; goal -> trajectory {summary['goal_to_trajectory_ms']} ms); as "
        f"received by this client: median {summary['pose_to_trajectory_at_client_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_at_client_ms_p95']} ms")
    try:
        _figure(Path(a.out) / "ros_demo.png", cfg, record, first, Q, ts, oracle, rows, t_replay)
    except Exception as exc:  # the figure is a report, never a reason to lose the result
        say(f"[demo] figure failed: {exc}")
    scored = any(oracle.values())
    return {**summary, "plans": rows,
            # per view: the mean score over the targets (one target: its score), and each target's
            "oracle": np.mean([oracle[n] for n in targets], axis=0).round(4).tolist() if scored else [],
            "oracle_by_target": oracle, "oracle_t": (ts - t_replay).round(2).tolist() if scored else []}


def _mean(values, digits: int = 3) -> Optional[float]:
    return round(float(np.mean(values)), digits) if len(values) else None


def _share(flags) -> str:
    return f"{np.mean(flags):.0%}" if len(flags) else "-"


def _pooled(by_target: dict, digits: int = 3) -> Optional[float]:
    """Mean over every (view, target) pair (None without any)."""
    vals = [v for vs in by_target.values() for v in vs]
    return _mean(vals, digits)


def _all(detected: dict) -> Optional[float]:
    """Share of the views in which every target was detected (None without views)."""
    cols = [np.asarray(v, bool) for v in detected.values()]
    if not cols or not len(cols[0]):
        return None
    return round(float(np.mean(np.logical_and.reduce(cols))), 3)


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


def _figure(path, cfg, record, first, Q, ts, oracle, rows, t_replay) -> None:
    """Top view (scene, first plan, executed motion, the recorded targets' headings) and, over time, each target's
    heading and distance from its first pose, the oracle's scores and the plans."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from psprm_core.evaluation import viz

    scene, robot = cfg.scene, cfg.robot
    fig = Figure(figsize=(14, 5.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    viz.plot_scene_top(ax, scene, show_labels=True)
    P0 = cv.joint_trajectory_positions(first, robot.joint_names)
    ax.plot(P0[:, 0], P0[:, 1], "--", color="0.4", lw=1.2, label="first plan")
    if len(Q):
        ax.plot(Q[:, 0], Q[:, 1], color="k", lw=1.5, label="executed (sim_robot /odom)")
    for g in cfg.goals:
        ax.plot(g.base[0], g.base[1], "*", color="tab:green", ms=10)
    with record.lock:
        poses = list(record.poses)
    recorded_targets = [n for n in cfg.targets if n in cfg.recorded_bodies]
    colours = ["tab:orange", "tab:purple", "tab:brown", "tab:pink"]
    tracks = {n: [(t, p, q) for t, b, p, q in poses if b == n] for n in recorded_targets}
    for c, (n, tr) in zip(colours * 4, tracks.items()):
        for t, p, q in tr[::240]:
            yaw = cv.yaw_of(q)
            ax.arrow(p[0], p[1], 0.35 * np.cos(yaw), 0.35 * np.sin(yaw), width=0.01, color=c, alpha=0.5)
    ax.set_title(f"{scene.name}: closed loop ({robot.name}, adapter {cfg.adapter} + sim_robot)\n"
                 f"replayed: {', '.join(cfg.recorded_bodies)}", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    for c, (n, tr) in zip(colours * 4, tracks.items()):
        if not tr:
            continue
        tf = np.array([t for t, _, _ in tr]) - t_replay
        ax2.plot(tf, np.unwrap([cv.yaw_of(q) for _, _, q in tr]), color=c, lw=1, label=f"{n} yaw (rad)")
        P = np.array([p for _, p, _ in tr])
        ax2.plot(tf, np.linalg.norm(P[:, :2] - P[0, :2], axis=1), color=c, lw=1, ls="--",
                 label=f"{n} moved (m)")
    ax2.set_xlabel("time since the replay started (s)")
    ax2.set_ylabel("target yaw (rad) / distance moved (m)")
    for r in rows:
        ax2.axvline(r["t"], color="red" if r["stop"] else "0.6", lw=0.8, ls=":" if r["success"] else "-")
    ax2.legend(fontsize=7, loc="upper left")
    if any(oracle.values()):
        ax3 = ax2.twinx()
        for c, (n, sc) in zip(["tab:blue", "tab:cyan", "tab:olive", "tab:gray"] * 4, oracle.items()):
            ax3.plot(ts[:len(sc)] - t_replay, sc, color=c, label=f"oracle score of {n} along the executed motion")
        ax3.set_ylim(0, 1.05)
        ax3.set_ylabel("oracle score")
        ax3.legend(fontsize=7, loc="upper right")
    ax2.set_title("targets as replayed; dotted lines = plans/replans, red = stops", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
