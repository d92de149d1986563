"""What the robot executes: the trajectory the planning loop last handed out (or the stop it published), how it was
sampled, and the record of recent publications that sets how far ahead the next replan commits."""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Optional

import numpy as np

from ..interfaces import conversions as cv
from .outputs import TrajectorySamples
from .params import ADAPTER_LEAD_S, finite_or_none as _f


class Executing:
    """The trajectory under way (:attr:`current`: result, samples, t_pub, positions, t_zero; None before the first),
    published one at a time under :attr:`lock` (the worker publishes trajectories, the stop guard stops on the
    callers' threads). ``counts``: the loop's counters (plans, stops, spliced are counted here)."""

    def __init__(self, robot, outputs, params: dict, clock, counts: dict):
        self.robot, self.outputs, self.p, self.clock, self.counts = robot, outputs, params, clock, counts
        self.lock = threading.RLock()
        self.current: Optional[dict] = None
        self.plan_s: deque = deque(maxlen=20)  # recent replans' time from their start to publication (s)
        self.last_latency_ms: Optional[float] = None

    def commit_horizon(self) -> float:
        """Planning and delivery time of a replan (s): 1.5x the 90th percentile of the recent replans' time from
        their start to the trajectory's publication, plus the adapter's lead time, clamped to
        [commit_horizon_min_s, commit_horizon_max_s]."""
        lo, hi = self.p["commit_horizon_min_s"], self.p["commit_horizon_max_s"]
        if not self.plan_s:
            return max(lo, min(hi, 0.5))
        return max(lo, min(hi, 1.5 * float(np.percentile(list(self.plan_s), 90)) + ADAPTER_LEAD_S))

    def commits_to_the_end(self, res) -> bool:
        """Whether the spliced ``res`` keeps the whole rest of the trajectory under way (its commitment ends where
        that trajectory ends, at rest)."""
        cur = self.current
        old = None if cur is None or cur.get("result") is None else cur["result"].trajectory
        return old is not None and res.start_offset_s + res.committed_s >= float(old.duration) - 1e-6

    def trajectory(self, rp) -> tuple:
        """(the trajectory under way, the perf_counter time the robot was at its start), when it is also the
        replanner ``rp``'s plan (a replan not handed to the robot is withdrawn); else (None, 0)."""
        cur = self.current
        res = None if cur is None else cur.get("result")
        traj = None if res is None else res.trajectory
        held = None if rp is None or rp.result is None else rp.result.trajectory
        if traj is None or held is not traj:
            return None, 0.0
        return traj, cur.get("t_zero", cur["t_pub"])

    def samples(self, traj, spliced: bool, q_from: np.ndarray) -> tuple:
        """(the samples to publish, the start move's duration): the trajectory sampled every ``trajectory_dt`` (plus
        its corners and end); a trajectory not spliced onto the one under way starts at the measured state
        ``q_from`` it was planned from (the planner re-aims the camera joints at its start), so that a controller
        never jumps (a spliced one starts on the trajectory under way, where the robot was when the replan began:
        the adapter joins it at the robot's progress)."""
        t, pos, vel, acc = cv.published_samples(traj, self.p["trajectory_dt"])
        shift = 0.0
        if not spliced:
            t, pos, vel, acc, shift = cv.prepend_start_samples(t, pos, vel, acc, q_from, self.robot.velocity,
                                                               self.robot.acceleration,
                                                               [2] if self.robot.mobile else [])
        return TrajectorySamples(t, pos, vel, acc), shift

    def publish(self, res, samples: TrajectorySamples, info: dict, reasons: list, t_first: Optional[float],
                t0: float) -> str:
        """Hand checked samples to the robot; the plan's info and status. ``t_first``: perf_counter receipt of the
        cycle's first input (the latency's start); ``t0``: the replan's start. Returns the info JSON."""
        with self.lock:
            self.outputs.trajectory(samples)
            t_pub = time.perf_counter()
            # when the robot is at the trajectory's time 0: the replan's start for a splice (the trajectory begins
            # where the robot was then), else the adapter's start, its lead time after publication
            self.current = {"result": res, "samples": samples, "t_pub": t_pub, "positions": samples.positions,
                            "t_zero": t0 if info["spliced"] else t_pub + ADAPTER_LEAD_S}
        self.plan_s.append(t_pub - t0)
        info["published_stamp"] = self.clock()  # the inputs' stamps are on this clock too
        self.counts["plans"] += 1
        self.counts["spliced"] += int(info["spliced"])
        if t_first:
            self.last_latency_ms = (t_pub - t_first) * 1e3
        info.update(latency_ms=_f((t_pub - t_first) * 1e3) if t_first else None,
                    duration_s=_f(res.trajectory.duration), n_points=len(samples.times), stop=False)
        info["mean_score"] = _f(res.mean_score)  # the planner's score along the path: after publication
        self.outputs.info(info)
        start = (f"spliced {info['committed_s']:.2f} s ahead" if info["spliced"] else "from the robot's state")
        self.outputs.status(f"plan {info['seq']} ({', '.join(reasons)}): {info['n_points']} points, "
                            f"{info['duration_s']:.1f} s, {start}, path score {res.mean_score:.3f}, query "
                            f"{res.query_ms:.0f} ms, adopted ({res.adopted_because.value})"
                            + (f": {res.judgement}" if res.judgement else ""))
        return json.dumps(info)

    def stop(self, q: np.ndarray, why: str, info: Optional[dict], seq: int) -> None:
        """Publish a stop at ``q`` (held ``stop_hold_s``); it becomes what the robot executes."""
        with self.lock:
            self.outputs.stop(q.copy(), self.p["stop_hold_s"])
            self.counts["stops"] += 1
            self.current = {"result": None, "samples": None, "t_pub": time.perf_counter(), "positions": q[None].copy()}
        info = dict(info or {"seq": seq, "reasons": [why]})
        info.update(stop=True, stop_reason=why)
        self.outputs.info(info)
        self.outputs.status(f"stop trajectory published: {why}", "warning")
