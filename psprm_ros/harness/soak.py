"""``soak``: the closed loop under a long, hostile input stream.

    python -m psprm_ros.harness.soak [--duration 600] [--params config/ros/dynamic_person.yaml] [--nodes 3000] [--out out]
                             [--suite processes|one-process] [--seed 0] [--path-tolerance M] [--json]

Starts the suite (server, scorer, monitor, robot adapter: ``run_nodes.sh``, a process per node, or
``run_all_in_one.sh`` with ``--suite one-process``) and ``sim_robot``, then for ``--duration`` seconds streams the
person (face + body) at 120 Hz from the shipped recording, looped, with:

* dropouts: the stream stops for 0.2-1.2 s (longer than the monitor's stale timeout: the robot must stop);
* NaN bursts: 10-60 poses with NaN positions;
* wrong frames: bursts in an unknown frame (dropped) and in ``world`` (a known input frame: transformed, used);
* goal spam: 5 s bursts of goals at 20 Hz (goal regions, goal poses, some in collision or outside the room);
* an obstacle walking into the path: every ``--walk-every`` s the person walks (0.5 m/s) to a point of the robot's
  current base path 2-3.5 m ahead of the robot, stays there, and walks back; on both ways the person yields as
  pedestrians do (waits while its next step would take it within ``YIELD_M`` of the robot's base and closer to it,
  at most ``YIELD_MAX_S``, then walks on), so that a collision judges the robot's motion, not a person walking into
  the robot. Every collision with the person also says who closed the gap;

while the robot drives between the two goal regions (the other one once it rests at one). It records every pose it
sent (the true world), what the robot reported (/odom, /joint_states), every trajectory and plan, and the memory
(RSS) of the suite's processes and of sim_robot. Reports trajectories published, executed configurations in
collision with the true world (the person at that instant), pose -> trajectory latency percentiles, memory growth,
and restarts (a process that exited or a lifecycle node that left the active state). One JSON object with ``--json`` (stdout carries it only).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from psprm_core.paths import resolve_named
from psprm_core.robot import RobotModel
from psprm_core.scene import load_scene

from ..heap import freeze_long_lived
from ..interfaces import conversions as cv
from ..interfaces.recordings import load_recording
from ..robots.adapters import load_adapter
from .demo import SUITE_SCRIPTS, ClosedLoop, Record, ROOT, _params_frames, rss_mb
from .demo_analysis import at_goal
from .probe import claim_domain_id
from .soak_report import report


WALK_MPS = 0.5  # the person's walking speed into the path and back
YIELD_M = 1.0  # the walking person does not step closer to the robot's base than this ...
YIELD_MAX_S = 20.0  # ... but after waiting this long in one walk it walks on


class Stream:
    """The hostile 120 Hz person stream (its own thread). Everything it sends that a correct mocap would also have
    sent (finite, known frame) is the true world, logged with the send time."""

    def __init__(self, probe, rec, scene, rng, record: Record, walk_every: float):
        self.probe, self.rec, self.scene, self.rng, self.record = probe, rec, scene, rng, record
        self.walk_every = walk_every
        self.stop_ev = threading.Event()
        self.counts = {"sent": 0, "dropout_s": 0.0, "dropouts": 0, "nan": 0, "unknown_frame": 0, "world_frame": 0,
                       "walks": 0, "yield_s": 0.0}
        self.offset = np.zeros(2)  # walking displacement of the person (x, y)
        self.walk = None  # the walk under way: phase (go, hold, back), offsets, hold time, time waited
        self.home = np.zeros(2)  # the person's own spot (the scene's), which the offset is added to
        self.t_last = 0.0
        self.path_xy = None  # the robot's latest base path (set by the main loop)
        self.robot_xy = None

    def start(self):
        self.thread = threading.Thread(target=self.run, daemon=True, name="soak-stream")
        self.thread.start()
        return self

    def _walk_offset(self, t: float) -> np.ndarray:
        """The person's displacement at time ``t``: walking at ``WALK_MPS`` to the walk's target, holding there, and
        back, yielding to the robot on both ways (module docstring)."""
        w = self.walk
        if w is None:
            self.t_last = t
            return self.offset
        dt, self.t_last = max(0.0, t - self.t_last), t
        if w["phase"] == "hold":
            if t >= w["until"]:
                w["phase"] = "back"
            return self.offset
        goal = w["to"] if w["phase"] == "go" else w["home"]
        d = goal - self.offset
        n = float(np.linalg.norm(d))
        if n < 1e-6:
            if w["phase"] == "go":
                w["phase"], w["until"] = "hold", t + w["hold"]
            else:
                self.walk = None
            return self.offset
        step = self.offset + d * min(1.0, WALK_MPS * dt / n)
        r = self.robot_xy
        if r is not None:
            here = self.home + self.offset
            nxt = self.home + step
            if np.linalg.norm(nxt - r) < YIELD_M and np.linalg.norm(nxt - r) < np.linalg.norm(here - r):
                w["waited"] += dt
                if w["waited"] < YIELD_MAX_S:
                    self.counts["yield_s"] += dt
                    return self.offset
        return step

    def _maybe_walk(self, t: float) -> None:
        if self.walk is not None or self.path_xy is None or self.robot_xy is None:
            return
        P, r = self.path_xy, self.robot_xy
        d = np.linalg.norm(P - r, axis=1)
        k0 = int(np.argmin(d))
        ahead = np.cumsum(np.r_[0.0, np.linalg.norm(np.diff(P[k0:], axis=0), axis=1)])
        home = self.scene.obstacle("person_body").center[:2]
        start = home + self.offset
        # a point of the path 2-3.5 m ahead of the robot, reached on a line that keeps 1 m from the robot: the person
        # steps into the robot's way in front of it, never onto the robot itself
        ok = []
        for k in np.nonzero((ahead > 2.0) & (ahead < 3.5))[0]:
            tgt = P[k0 + k]
            seg = tgt - start
            f = np.clip(np.dot(r - start, seg) / max(float(np.dot(seg, seg)), 1e-9), 0.0, 1.0)
            if np.linalg.norm(start + f * seg - r) >= 1.0 and np.linalg.norm(tgt - r) >= 1.5:
                ok.append(tgt)
        if not ok:
            return
        target = ok[int(self.rng.integers(0, len(ok)))]
        self.home = home
        self.walk = {"phase": "go", "home": self.offset.copy(), "to": target - home,
                     "hold": float(self.rng.uniform(3.0, 6.0)), "waited": 0.0, "until": 0.0}
        self.t_last = t
        self.counts["walks"] += 1

    def run(self):
        rec, rng = self.rec, self.rng
        t_start = time.monotonic()
        next_walk = t_start + 10.0
        i = 0
        period = 1.0 / 120.0 / max(1, len(rec.bodies))
        burst = None  # ("nan" | "frame" | "world", remaining samples)
        while not self.stop_ev.is_set():
            now = time.monotonic()
            if now >= next_walk:
                self._maybe_walk(now)
                next_walk = now + self.walk_every
            self.offset = self._walk_offset(now)
            if rng.random() < 1.0 / (120 * 20):  # a dropout about every 20 s
                d = float(rng.uniform(0.2, 1.2))
                self.counts["dropouts"] += 1
                self.counts["dropout_s"] += d
                if self.stop_ev.wait(d):
                    return
                continue
            if burst is None and rng.random() < 1.0 / (120 * 8):  # a burst about every 8 s
                burst = [str(rng.choice(["nan", "frame", "world"])), int(rng.integers(10, 60))]
            k = i % len(rec.times)
            body = rec.bodies[int(rec.body[k])]
            p = rec.P[k].copy()
            q = rec.Q[k].copy()
            p[:2] += self.offset
            frame = "map"
            if burst is not None:
                if burst[0] == "nan":
                    p[int(rng.integers(0, 3))] = np.nan
                    self.counts["nan"] += 1
                elif burst[0] == "frame":
                    frame = "vicon"
                    self.counts["unknown_frame"] += 1
                else:
                    frame = "world"  # identity transform in the params file: a good pose
                    self.counts["world_frame"] += 1
                burst[1] -= 1
                if burst[1] <= 0:
                    burst = None
            self.probe.publish_pose(body, p, q, frame=frame)
            if np.isfinite(p).all() and frame != "vicon":
                self.record.on_sample(body, 0.0, p, q)
            self.counts["sent"] += 1
            i += 1
            self.stop_ev.wait(max(0.0, period - (time.monotonic() - now)))

    def stop(self):
        self.stop_ev.set()
        self.thread.join(2.0)


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    ap = argparse.ArgumentParser(prog="soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of hostile stream (default 600)")
    ap.add_argument("--params", default=str(ROOT / "config" / "ros" / "dynamic_person.yaml"))
    ap.add_argument("--recording", default=str(ROOT / "config" / "recordings" / "person_turning.csv"))
    ap.add_argument("--nodes", type=int, default=3000)
    ap.add_argument("--suite", choices=sorted(SUITE_SCRIPTS), default="processes",
                    help="the node suite as a process per node (run_nodes.sh) or in one process (run_all_in_one.sh)")
    ap.add_argument("--walk-every", type=float, default=40.0, help="the person walks into the path this often (s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--path-tolerance", type=float, default=None,
                    help="the robot adapter's path_tolerance_m (default: the params file's; 0 = off)")
    ap.add_argument("--out", default="out")
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    ap.add_argument("--domain-id", type=int, default=0)
    a = ap.parse_args(argv[1:])
    say = (lambda m: print(m, file=sys.stderr, flush=True)) if a.json else (lambda m: print(m, flush=True))
    import logging

    logging.basicConfig(level=logging.ERROR)

    rng = np.random.default_rng(a.seed)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = load_recording(a.recording)
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = RobotModel.load(scene.robot)
    domain = a.domain_id or claim_domain_id(100, 200)
    overrides = {"roadmap_server:roadmap.n_nodes": a.nodes, "robot_adapter:interface": "topic"}
    if a.path_tolerance is not None:
        overrides["robot_adapter:path_tolerance_m"] = a.path_tolerance
    loop = ClosedLoop(a.params, overrides, out, "soak", domain, suite=a.suite).start()
    procs, probe = loop.procs, loop.probe
    record = Record(probe.node, robot, "stretch2", _params_frames(a.params, scene.frame))
    from diagnostic_msgs.msg import DiagnosticArray

    from trajectory_msgs.msg import JointTrajectory

    # what the adapter sent the controllers (t, points): which trajectories it executed, which it refused (a hold)
    commands, commands_lock = [], threading.Lock()

    def on_command(m):
        with commands_lock:
            commands.append((time.perf_counter(), len(m.points)))
    for c in load_adapter("stretch2", robot).with_interface("topic").controllers:
        probe.node.create_subscription(JointTrajectory, c.topic, on_command, 50)
    diags: dict = {}
    probe.node.create_subscription(DiagnosticArray, "/diagnostics",
                                   lambda m: diags.update({s.name: (time.perf_counter(), s) for s in m.status}), 50)
    wall_minus_perf = time.time() - time.perf_counter()
    result = {}
    stream = None
    try:
        ready = probe.wait_ready(timeout=1200)
        if not ready:
            raise RuntimeError("the suite did not become ready")
        say(f"[soak] suite ready: {ready.split(': ', 1)[-1]}; streaming for {a.duration:.0f} s")
        probe.wait_subscribers("/mocap/person_face/pose", timeout=30)
        probe.wait_for(lambda: record.latest() is not None, 30)
        mem = {n: [] for n in procs}
        freeze_long_lived()  # as the nodes do: no full collection walks the start-up's objects while it streams
        stream = Stream(probe, rec, scene, rng, record, a.walk_every).start()
        goals = [g.name for g in scene.goals]
        cur_goal = 1  # at_cabinet first
        probe.publish_regions([goals[cur_goal]])
        t0 = time.perf_counter()
        next_mem, next_spam, next_report = t0, t0 + 15.0, t0 + 30.0
        spam_until = 0.0
        n_spam = 0
        rest_since = None
        reached = []
        exits = {}
        while time.perf_counter() - t0 < a.duration:
            time.sleep(0.05)
            now = time.perf_counter()
            for n, p in procs.items():
                if p.poll() is not None and n not in exits:
                    exits[n] = p.returncode
                    say(f"[soak] {n} exited with {p.returncode}")
            last = record.latest()
            with probe.cond:
                lastt = [m for _, m in probe.trajectories if len(m.points) > 1]
            if lastt:
                stream.path_xy = cv.joint_trajectory_positions(lastt[-1], robot.joint_names)[:, :2]
            if last is not None:
                stream.robot_xy = last[1][:2]
                g = at_goal(scene, last[1])
                with record.lock:
                    recent = [q[:3] for t, q in record.executed if t > last[0] - 1.0]
                still = len(recent) > 5 and np.ptp(np.array(recent), axis=0).max() < 5e-3
                if g == goals[cur_goal] and still:
                    rest_since = rest_since or now
                    if now - rest_since > 1.0:
                        reached.append((round(now - t0, 1), g))
                        cur_goal = 1 - cur_goal
                        probe.publish_regions([goals[cur_goal]])
                        rest_since = None
                else:
                    rest_since = None
            if now >= next_spam:
                spam_until = now + 5.0
                next_spam = now + 45.0
            if now < spam_until and int(now * 20) != int((now - 0.05) * 20):
                n_spam += 1
                r = rng.random()
                if r < 0.4:
                    probe.publish_regions([goals[int(rng.integers(0, 2))]])
                elif r < 0.7:
                    probe.publish_goal(float(rng.uniform(0.5, 7.5)), float(rng.uniform(0.5, 5.5)),
                                       float(rng.uniform(-np.pi, np.pi)))
                elif r < 0.85:
                    probe.publish_goal(0.25, 3.2, np.pi)  # inside the shelf: refused
                else:
                    probe.publish_goal(12.0, -3.0, 0.0)  # outside the room: refused
                if now + 0.05 >= spam_until:  # the burst ends: back to the current goal
                    probe.publish_regions([goals[cur_goal]])
            if now >= next_mem:
                for n, p in procs.items():
                    mem[n].append((now - t0, rss_mb(p.pid)))
                next_mem = now + 10.0
            if now >= next_report:
                with probe.cond:
                    nt = len(probe.trajectories)
                say(f"[soak] t={now - t0:5.0f} s: {nt} trajectories, goals reached {len(reached)}, "
                    f"stream {stream.counts['sent']} poses, RSS suite {mem['suite'][-1][1]:.0f} MB")
                next_report = now + 30.0
        stream.stop()
        t_end = time.perf_counter()
        result = report(a, scene, robot, probe, record, procs, exits, mem, stream, n_spam, reached, diags, t0, t_end,
                        wall_minus_perf, commands, commands_lock)
    finally:
        if stream is not None:
            stream.stop()
        loop.close()
    if result:
        (out / "soak.json").write_text(json.dumps(result, indent=1))
        if a.json:
            print(json.dumps(result))
        else:
            for k, v in result.items():
                say(f"  {k:34s} {v}")
    return 0 if result and result["executed_collisions"] == 0 and result["restarts"] == 0 else 1


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
