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
   goal (or ``--timeout``, at least what the server's arrival budget allows the first plan);
4. prints every plan and replan (triggers, latency from the pose message to the trajectory), the executed motion, the
   executed configurations in collision with the replayed bodies (poses at that instant), and the oracle's verdict
   (rendered views + the real detector, every target of the params file) along the executed motion and along the
   first plan alone; writes ``<out>/ros_demo.json`` (strict JSON: ``reached_goal``, ``goal``, ``time_to_goal_s``,
   ``executed_collisions``, ``pose_to_trajectory_ms_median`` / ``_p95``, ``first_plan_s``,
   ``first_plan_duration_s``, ``adopted_replans``, ``declined_replans`` (``declined_late_replans`` of them beyond the
   arrival budget), ``goal_switches``, ``stops``,
   ``adapter_refusals``, ``oracle_detected_fraction``, ``cpu_s_during_run``: the CPU seconds of this process, the
   suite, sim_robot, the whole machine and everything else while the robot drove, ...) and ``<out>/ros_demo.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from psprm_core.errors import PsprmError

from .. import core
from ..heap import freeze_long_lived
from ..interfaces import conversions as cv
from ..interfaces.recordings import load_recording
from ..mocap_replay import Replayer
from ..robots.adapters import load_adapter
from ..robots.robot_state import RobotStateTracker
from ..spinning import NodeSpinner
from .demo_analysis import adapter_stops, analyse, rest_arrival, strict_json
from .demo_config import default_recording, demo_config, params_frames, read_params
from .probe import InProcessSuite, Probe, claim_domain_id
from .soak_report import save_record

ROOT = Path(__file__).resolve().parents[2]


class Record:
    """What the demo saw: the robot's reports, the poses it replayed, with perf_counter times."""

    def __init__(self, node, robot, adapter_name: str, frames, to_scene=None):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

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
    return params_frames(read_params(params_file)["roadmap_server"], scene_frame, str(params_file))


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
    ap.add_argument("--timeout", type=float, default=120.0,
                    help="longest closed-loop run after the first plan (s); at least what the server's arrival "
                         "budget allows a replanning robot, (1 + arrival_budget) x the first plan's duration + 10 s")
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
        patience = cfg.patience_s(first_duration, a.timeout)
        if patience > a.timeout:
            say(f"[demo] waiting up to {patience:.0f} s for the goal: the arrival budget "
                f"({cfg.arrival_budget:g}) of a {first_duration:.1f} s first plan")
        deadline = time.perf_counter() + patience
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
            f"{result['adopted_replans']} replans adopted, {result['declined_replans']} declined "
            f"({result['declined_late_replans']} beyond the arrival budget), "
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
        if not result.get("reached_goal") or result.get("executed_collisions"):
            # what went wrong, for a post-mortem: the executed motion, the trajectories and the replayed poses
            with record.lock:
                ex, poses = list(record.executed), list(record.poses)
            save_record(out / "ros_demo_record.npz", ex, list(probe.trajectories), list(cfg.robot.joint_names),
                        poses=poses)
            say(f"[demo] wrote {out / 'ros_demo_record.npz'} (executed motion, trajectories, replayed poses)")
    return 0 if result.get("reached_goal") and result.get("executed_collisions") == 0 else 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
