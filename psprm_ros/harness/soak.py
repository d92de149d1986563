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
import os
import sys
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

from ..heap import freeze_long_lived
from ..interfaces import conversions as cv
from .demo import GOAL_REASONS, SUITE_SCRIPTS, ClosedLoop, Record, ROOT, _params_frames, _scene_with, at_goal, rss_mb
from .probe import claim_domain_id


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
    from psprm_core.paths import resolve_named
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    from ..interfaces.recordings import load_recording

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

    from ..robots.adapters import load_adapter

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


CLOSING_WINDOW_S = 0.25  # the motion before a collision over which the closing speeds are measured
CLOSING_MPS = 0.02  # a robot closing in faster than this counts the collision as the robot's (else the person's)


def _followed(t: float, q: np.ndarray, trajs: list, names: list, checker) -> Optional[dict]:
    """The trajectory the robot was following at ``t`` (the last one received before it) and how far the executed
    configuration ``q`` is from its path: the base distance to the nearest of its points, that point's heading and
    joint differences, whether that point itself collides with the boxes ``checker`` holds now, and how many of the
    trajectory's points do. Tells a collision of the plan from one of the tracking. None before any trajectory."""
    import torch

    prev = [(tt, m) for tt, m in trajs if tt <= t]
    if not prev:
        return None
    t_m, m = prev[-1]
    try:
        idx = [list(m.joint_names).index(n) for n in names]
    except ValueError:
        return {"received_s_before": round(t - t_m, 2), "joint_names": list(m.joint_names)}
    P = np.array([np.asarray(p.positions, float)[idx] for p in m.points])
    i = int(np.argmin(np.hypot(P[:, 0] - q[0], P[:, 1] - q[1])))
    bad = checker.check(torch.as_tensor(P, dtype=torch.float32)).cpu().numpy()
    return {"received_s_before": round(t - t_m, 2), "points": len(P),
            "base_off_m": round(float(np.hypot(*(P[i, :2] - q[:2]))), 3),
            "heading_off_rad": round(abs(float((q[2] - P[i, 2] + np.pi) % (2 * np.pi) - np.pi)), 3),
            "joints_off_max": round(float(np.abs(P[i, 3:] - q[3:]).max()), 3) if P.shape[1] > 3 else 0.0,
            "nearest_point_collides": bool(bad[i]), "points_in_collision": int(bad.sum())}


def _closing_speeds(t: float, q: np.ndarray, ex: list, ex_t: np.ndarray, body_tp: list, body_t: np.ndarray) -> tuple:
    """(robot, person) closing speeds (m/s) at an executed configuration ``q`` at time ``t`` in collision with the
    person: how fast the robot's base motion alone, and the person's walk alone, shrank the distance between the base
    and the body over the preceding :data:`CLOSING_WINDOW_S`."""
    t_b = t - CLOSING_WINDOW_S
    i = int(np.clip(np.searchsorted(ex_t, t_b), 0, len(ex_t) - 1))
    j0 = int(np.clip(np.searchsorted(body_t, ex_t[i], side="right") - 1, 0, len(body_t) - 1))
    j1 = int(np.clip(np.searchsorted(body_t, t, side="right") - 1, 0, len(body_t) - 1))
    r0, r1 = np.asarray(ex[i][1][:2], float), np.asarray(q[:2], float)
    p0, p1 = np.asarray(body_tp[j0][1][:2], float), np.asarray(body_tp[j1][1][:2], float)
    dt = max(t - ex_t[i], 1e-3)
    d0 = np.linalg.norm(r0 - p0)
    return (d0 - np.linalg.norm(r1 - p0)) / dt, (d0 - np.linalg.norm(r0 - p1)) / dt


TRACK_WINDOW_S = 3.0


def executed_trajectories(trajs: list, commands: list) -> list:
    """The server's trajectories the robot adapter executed, as (t, msg, t_hold): those followed by a controller
    command of more than one point (a refused trajectory is followed by a hold instead), and when the first hold
    after it stopped the robot (inf if none did), judged from the messages on the controller's topic
    (``commands``: (t, number of points))."""
    t_tr = np.array([t for t, _ in trajs])
    out, seen = [], set()
    for tc, n in commands:
        j = int(np.searchsorted(t_tr, tc, side="right") - 1)
        if n == 1 and out and out[-1][2] == np.inf:
            out[-1] = (*out[-1][:2], tc)
        elif n > 1 and j >= 0 and j not in seen:
            seen.add(j)
            out.append((*trajs[j], np.inf))
    return out


def tracking_report(ex: list, trajs: list, robot, checker, static_boxes: list) -> dict:
    """How closely the robot executed the trajectories it was sent, judged from the record alone: for every executed
    configuration, the trajectory it was following (the last of ``trajs``, those executed, (t, msg) or (t, msg,
    t_hold), received before it; the motion after a hold at ``t_hold`` counts against where it stopped), the
    base's distance to that trajectory's base path (point to segment), and the deviation of the whole robot
    (:class:`psprm_core.tracking.CheckedPath`: how far a point of its collision boxes is from where it was in the
    nearest of the trajectory's configurations within ``TRACK_WINDOW_S`` of the time since it was received);
    percentiles of both, and how often the deviation exceeded the padding, which is the clearance the plan kept.
    Then the executed configurations inside the collision padding of the static boxes
    (``checker`` pads them), split by whether the nearest point of the followed trajectory is inside it too (the plan
    itself came that close, e.g. from a start inside the padding) or clear of it (the tracking error carried the
    robot in)."""
    import torch

    from psprm_core.tracking import CheckedPath

    names = list(robot.joint_names)
    if not ex or not trajs:
        return {}
    t_tr = np.array([tr[0] for tr in trajs])
    paths = []
    for tr in trajs:
        m = tr[1]
        try:
            paths.append(cv.joint_trajectory_positions(m, names))
        except Exception:
            paths.append(np.zeros((0, len(names))))
    ex_t = np.array([t for t, _ in ex])
    Q = np.array([q for _, q in ex], float)
    which = np.searchsorted(t_tr, ex_t, side="right") - 1
    base_off = np.full(len(Q), np.nan)
    nearest = np.full((len(Q), len(names)), np.nan)
    deviation = np.full(len(Q), np.nan)
    for j in np.unique(which[which >= 0]):
        P = paths[j]
        if len(P) < 2:  # a stop: the robot holds, nothing to follow
            continue
        sel = np.nonzero(which == j)[0]
        m = trajs[j][1]
        T = np.array([cv.duration_to_sec(p.time_from_start) for p in m.points])
        if np.all(np.diff(T) > 0):
            # the robot's collision boxes against the trajectory's configurations within TRACK_WINDOW_S of the time
            # since it was received (the adapter starts it a lead time later, spliced up to 1.5 s in)
            path = CheckedPath(robot, T, P)
            # after a hold the robot is no longer following: it is measured against where it was stopped
            t_hold = trajs[j][2] if len(trajs[j]) > 2 else np.inf
            deviation[sel] = path.deviations(Q[sel], np.minimum(ex_t[sel], t_hold) - t_tr[j], TRACK_WINDOW_S)
        a, b = P[:-1, :2], P[1:, :2]  # base path segments
        d = b - a
        L2 = np.maximum((d * d).sum(1), 1e-12)
        x = Q[sel, None, :2]
        f = np.clip(((x - a) * d).sum(2) / L2, 0.0, 1.0)  # (n, segments)
        dist = np.linalg.norm(a + f[..., None] * d - x, axis=2)
        k = np.argmin(dist, axis=1)
        fk = f[np.arange(len(sel)), k][:, None]
        near = P[k] + fk * (P[k + 1] - P[k])
        nearest[sel] = near
        base_off[sel] = dist[np.arange(len(sel)), k]
    ok = np.isfinite(base_off)
    if not ok.any():
        return {}
    bt = checker.box_tensors(static_boxes)
    inside = np.zeros(len(Q), bool)
    near_inside = np.zeros(len(Q), bool)
    for s in range(0, len(Q), 4096):
        qt = torch.as_tensor(Q[s:s + 4096], dtype=torch.float32)
        inside[s:s + 4096] = checker.env_hits(qt, bt).cpu().numpy()
    idx = np.nonzero(inside & ok)[0]
    if len(idx):
        near_inside[idx] = checker.env_hits(torch.as_tensor(nearest[idx], dtype=torch.float32), bt).cpu().numpy()
    pct = (lambda v, p: round(float(np.percentile(v[ok], p)), 3))
    return {
        "configurations_following": int(ok.sum()),
        "base_off_m": {f"p{p}": pct(base_off, p) for p in (50, 95, 99)} | {"max": round(float(base_off[ok].max()), 3)},
        # psprm_core.tracking: how far a point of the robot's boxes is from where it was in the nearest
        # configuration of the followed trajectory (within TRACK_WINDOW_S of its receipt time)
        "deviation_m": {f"p{p}": round(float(np.nanpercentile(deviation[ok], p)), 3) for p in (50, 95, 99)}
        | {"max": round(float(np.nanmax(deviation[ok])), 3),
           "over_padding": int(np.sum(deviation[ok] > checker.padding)),
           "trajectories_over_padding": int(len(np.unique(which[ok & (deviation > checker.padding)])))},
        "padding_m": float(checker.padding),
        "inside_static_padding": int((inside & ok).sum()),
        "inside_static_padding_plan_too": int((inside & near_inside).sum()),
        "inside_static_padding_by_tracking": int((inside & ok & ~near_inside).sum()),
        "base_off_when_inside_m_max": round(float(base_off[inside & ok].max()), 3) if (inside & ok).any() else None,
    }


def _params_padding(params_file: str) -> float:
    """The roadmap server's ``edges.collision_padding`` in the params file, as a dotted key or nested (0 when it sets
    none)."""
    import yaml

    data = yaml.safe_load(Path(params_file).read_text()) or {}
    params = (data.get("roadmap_server") or {}).get("ros__parameters") or {}
    if "edges.collision_padding" in params:
        return float(params["edges.collision_padding"])
    return float((params.get("edges") or {}).get("collision_padding", 0.0))


def save_record(path: Path, ex: list, trajs: list, names: list, commands: list = ()) -> None:
    """The soak's record for a replay: executed configurations (t, q), every trajectory received (t, times from its
    start, positions in the robot's joint order) and the controller commands (t, number of points), times in seconds
    from the first executed configuration."""
    t_ref = ex[0][0] if ex else 0.0
    tt, off, P, T = [], [0], [], []
    for t, m in trajs:
        try:
            pos = cv.joint_trajectory_positions(m, names)
        except Exception:
            continue
        tt.append(t - t_ref)
        P.append(pos)
        T.append([cv.duration_to_sec(p.time_from_start) for p in m.points])
        off.append(off[-1] + len(pos))
    np.savez_compressed(path, joint_names=np.array(names), executed_t=np.array([t - t_ref for t, _ in ex]),
                        executed_q=np.array([q for _, q in ex]).reshape(-1, len(names)),
                        trajectory_t=np.array(tt), trajectory_offsets=np.array(off),
                        trajectory_q=np.vstack(P) if P else np.zeros((0, len(names))),
                        trajectory_time_from_start=np.concatenate(T) if T else np.zeros(0),
                        command_t=np.array([t - t_ref for t, _ in commands]),
                        command_points=np.array([n for _, n in commands], int))


def report(a, scene, robot, probe, record, procs, exits, mem, stream, n_spam, reached, diags, t0, t_end,
           wall_minus_perf, commands: list, commands_lock) -> dict:
    import torch

    from psprm_core.collision import CollisionChecker

    with probe.cond:
        trajs = [(t, m) for t, m in probe.trajectories if t0 <= t <= t_end]
        infos = [(t, i) for t, i in probe.infos if t0 <= t <= t_end]
        statuses = [(t, n, s) for t, n, s in probe.statuses if t0 <= t <= t_end]
    lat = []
    for t, info in infos:
        if info.get("input_stamp") and info.get("success") and not info.get("stop") and not info.get("kept_last") \
                and not info.get("kept") \
                and not any(r in GOAL_REASONS for r in info.get("reasons") or []):
            if info.get("published_stamp"):  # the suite's: pose stamp to the trajectory's publication
                lat.append((info["published_stamp"] - info["input_stamp"]) * 1e3)
    lat = np.array(lat, float)
    with record.lock:
        ex = [(t, q) for t, q in record.executed if t0 <= t <= t_end]
        poses = list(record.poses)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    collided, k, cur = 0, 0, {}
    version, checked_version = 0, -1
    events = []
    # who closed the gap at each collision with the person: the robot's own motion or the person's walk
    ex_t = np.array([t for t, _ in ex]) if ex else np.zeros(0)
    body_tp = [(t, p) for t, b, p, _ in poses if b == "person_body"]
    body_t = np.array([t for t, _ in body_tp]) if body_tp else np.zeros(0)
    by = {"robot_closing": 0, "person_closing": 0, "static_obstacle": 0}
    for t, q in ex:
        while k < len(poses) and poses[k][0] <= t:
            cur[poses[k][1]] = (poses[k][2], poses[k][3])
            k += 1
            version += 1
        if version != checked_version:
            checker.set_boxes(_scene_with(scene, cur).collision_boxes())
            checked_version = version
        qt = torch.as_tensor(q[None], dtype=torch.float32)
        hit = bool(checker.check(qt)[0])
        collided += int(hit)
        closing = None
        if hit:
            hit_boxes = [b.name for b in _scene_with(scene, cur).collision_boxes()
                         if bool(checker.env_hits(qt, [b])[0])]  # the boxes this configuration touches
            if "person_body" in hit_boxes and len(body_t):
                closing = _closing_speeds(t, q, ex, ex_t, body_tp, body_t)
                by["robot_closing" if closing[0] > CLOSING_MPS else "person_closing"] += 1
            else:
                by["static_obstacle"] += 1
        if hit and len(events) < 10:
            body = cur.get("person_body", (np.full(3, np.nan), None))[0]
            det = checker.check_detailed(qt)
            events.append({"t": round(t - t0, 2), "base": [round(float(v), 3) for v in q[:3]],
                           "person": [round(float(v), 3) for v in body[:2]],
                           "q": [round(float(v), 4) for v in q],  # the whole configuration, for a replay
                           "why": [k for k in ("limits", "environment", "self") if bool(det[k][0])],
                           "boxes": hit_boxes,
                           # m/s by which the robot's motion / the person's walk shrank their distance over the last
                           # CLOSING_WINDOW_S
                           "closing_mps": None if closing is None else [round(float(c), 3) for c in closing],
                           # the trajectory the robot was following, and how far off it the robot was
                           "followed": _followed(t, q, trajs, list(robot.joint_names), checker)})
    moving = {b for _, b, _, _ in poses}
    padded = CollisionChecker(robot, workspace=scene.workspace, padding=_params_padding(a.params))
    with commands_lock:
        cmds = [(t, n) for t, n in commands if t0 <= t <= t_end]
    tracking = tracking_report(ex, executed_trajectories(trajs, cmds), robot, padded,
                               [b for b in scene.collision_boxes() if b.name not in moving])
    save_record(Path(a.out) / "soak_record.npz", ex, trajs, list(robot.joint_names), cmds)
    growth = {}
    for n, m in mem.items():
        v = [x for _, x in m if np.isfinite(x)]
        if len(v) >= 4:
            first = float(np.median(v[: max(2, len(v) // 6)]))
            last = float(np.median(v[-max(2, len(v) // 6):]))
            growth[n] = {"first_mb": round(first, 1), "last_mb": round(last, 1), "growth_mb": round(last - first, 1),
                         "max_mb": round(max(v), 1),
                         # one sample a minute (s, MB): whether the memory levels off over a long run
                         "series": [[round(t), round(x, 1)] for t, x in m[::6] if np.isfinite(x)]}
    left_active = sum(1 for _, n, s in statuses if "inactive" in s or "configure failed" in s)
    errors = [s for _, n, s in statuses if s.startswith("error")]
    pct = (lambda p: round(float(np.percentile(lat, p)), 1) if len(lat) else None)
    return {
        "duration_s": round(t_end - t0, 1), "trajectories_published": len(trajs),
        "plans_ok": sum(1 for _, i in infos if i.get("success") and not i.get("stop") and not i.get("kept")),
        "kept": sum(1 for _, i in infos if i.get("kept")),
        "stops": sum(1 for _, i in infos if i.get("stop")), "failed": sum(1 for _, i in infos if not i.get("success")),
        "refused_unsafe": sum(1 for _, i in infos if "refused" in str(i.get("reason"))),
        "late_splices": sum(1 for _, i in infos if i.get("failure") == "late_splice"),
        "stale_starts": sum(1 for _, i in infos if i.get("failure") == "stale_start"),
        "goals_reached": len(reached), "executed_configurations": len(ex), "executed_collisions": int(collided),
        "executed_collisions_by": by, "collision_events": events, "tracking": tracking,
        "latency_ms_p50": pct(50), "latency_ms_p90": pct(90), "latency_ms_p95": pct(95), "latency_ms_p99": pct(99),
        "latency_ms_max": round(float(lat.max()), 1) if len(lat) else None, "latency_samples": int(len(lat)),
        "suite": a.suite, "memory": growth, "restarts": len(exits) + left_active, "process_exits": exits,
        "error_statuses": len(errors),
        "first_errors": errors[:5], "stream": stream.counts, "goal_spam_messages": n_spam,
        "adapter_refusals": sum(1 for _, n, s in statuses if n == "robot_adapter" and "refused" in s),
        "adapter_refusal_examples": [s for _, n, s in statuses if n == "robot_adapter" and "refused" in s][:5],
        "controller_refusals": sum(1 for _, n, s in statuses if n == "sim_robot" and "refused" in s),
        "load_avg_1min": round(os.getloadavg()[0], 2), "cpus": os.cpu_count(),
    }


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
