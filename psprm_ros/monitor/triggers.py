"""The replan monitor's triggers: what makes it ask the server for a plan or a stop. It follows the server's outputs
(plan info, the perception scorer's predicted path score, the trajectory published), and asks for a plan when the
robot is off the trajectory by more than ``deviation_tolerance``, when the path score falls below
``min_path_score_ratio`` x its value at plan time, periodically (``replan_period_s``) and when a stale obstacle is live
again; a stale obstacle makes it ask for a stop (a stale target only warns). Requests are rate-limited
(``min_request_interval_s``) unless forced."""

from __future__ import annotations

import json
import time

import numpy as np

from ..interfaces import conversions as cv


class Triggers:
    """The server-output callbacks, the watchdog and the plan/stop requests of
    :class:`~psprm_ros.replan_monitor.ReplanMonitor` (a base class of it: they read and write the node's state under
    its lock, and report through its ``status``)."""

    # ------------------------------------------------------------------------------------------------ server outputs
    def _info_cb(self, msg) -> None:
        try:
            info = json.loads(msg.data)
        except ValueError:
            return
        with self._lock:
            if info.get("stop"):
                self.counts["stops"] += 1
            elif info.get("kept"):
                self.counts["kept"] += 1
            elif info.get("success"):
                self.counts["plans"] += 1
                self.plan_score = info.get("mean_score")
                self.path_score = None
                self.last_plan_t = time.monotonic()
                if info.get("latency_ms") is not None:
                    self.latencies.append(float(info["latency_ms"]))
                    del self.latencies[:-200]  # the status reports the latest 200
            else:
                self.counts["failed"] += 1

    def _score_cb(self, msg) -> None:
        with self._lock:
            self.path_score = float(msg.data)

    def _traj_cb(self, msg) -> None:
        try:
            P = cv.joint_trajectory_positions(msg, self.names)
            t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
        except Exception as exc:
            self.status(f"ignored trajectory: {exc}", "warning")
            return
        with self._lock:
            self.traj = {"P": P, "t": t, "t0": time.monotonic()} if len(P) > 1 else None

    # ------------------------------------------------------------------------------------------------ triggers
    def _check_deviation(self, q: np.ndarray) -> None:
        with self._lock:
            tr, robot = self.traj, self._robot
        if tr is None or robot is None or not robot.mobile:
            return
        # off the path, not behind its schedule: the nearest point of the base's path within 3 s of the time the
        # trajectory's clock says (a replan spliced onto the trajectory under way starts where the robot was when
        # planning began, behind the receipt time; the robot running late is no reason to replan)
        el = min(time.monotonic() - tr["t0"], tr["t"][-1])
        near = (tr["t"] >= el - 3.0) & (tr["t"] <= el + 3.0)
        if not near.any():
            near = np.ones(len(tr["t"]), dtype=bool)
        dev = float(np.linalg.norm(tr["P"][near][:, :2] - q[:2], axis=1).min())
        if dev > self.p["deviation_tolerance"]:
            self._request("plan", f"robot {dev:.2f} m off the trajectory")

    def _check(self) -> None:
        now = time.monotonic()
        late = self._grace.step(now)
        with self._lock:
            seen = dict(self.last_seen)
            plan_score, path_score = self.plan_score, self.path_score
        newly = [key for key, t in seen.items()
                 if now - t > self.p["stale_timeout_s"] and f"{key[0]} {key[1]}" not in self.stale]
        if not newly:
            self._grace.clear()
        elif self._grace.forgive(late):
            # this check runs late (the process stalled): the poses that arrived meanwhile may still wait in the
            # queue; a body silent again at the next check is stale
            newly = []
        self.stale.update(f"{k[0]} {k[1]}" for k in newly)
        for key, t in seen.items():
            label = f"{key[0]} {key[1]}"
            if now - t > self.p["stale_timeout_s"]:
                continue
            if label in self.stale:
                self.stale.discard(label)
                self.status(f"{label} is live again")
                if key[0] == "obstacle" and self.p["stop_on_stale_obstacle"]:
                    self._request("plan", f"{label} live again", force=True)
        for kind, name in newly:
            if kind == "obstacle" and self.p["stop_on_stale_obstacle"]:
                self.status(f"obstacle {name} stale (no pose for {self.p['stale_timeout_s']:.1f} s): stopping",
                            "warning")
                self._request("stop", f"obstacle {name} stale", force=True)
            else:
                self.status(f"{kind} {name} stale (no pose for {self.p['stale_timeout_s']:.1f} s): "
                            "keeping the last plan", "warning")
        settled = now - self.last_plan_t > self.p["min_request_interval_s"]  # the scorer has seen the new path
        if settled and plan_score and path_score is not None and \
                path_score < self.p["min_path_score_ratio"] * plan_score:
            self._request("plan", f"predicted path score {path_score:.3f} < "
                                  f"{self.p['min_path_score_ratio']:.2f} x {plan_score:.3f}")
        if self.p["replan_period_s"] > 0 and now - self.last_plan_t > self.p["replan_period_s"]:
            self._request("plan", "periodic replan")

    def _request(self, kind: str, why: str, force: bool = False) -> None:
        from std_srvs.srv import Trigger

        now = time.monotonic()
        if not force and now - self.last_request_t < self.p["min_request_interval_s"]:
            return
        cli = self.cli_plan if kind == "plan" else self.cli_stop
        if not cli.service_is_ready():
            self.status(f"cannot request {kind} ({why}): server not available", "warning")
            return
        self.last_request_t = now
        with self._lock:
            self.counts["requests"] += 1
            if kind == "plan":
                self.path_score = None
                self.last_plan_t = now
        self.status(f"requesting {kind}: {why}")
        fut = cli.call_async(Trigger.Request())
        fut.add_done_callback(lambda f: self._done(kind, f))

    def _done(self, kind, fut) -> None:
        try:
            r = fut.result()
            if not r.success:
                self.status(f"{kind} request failed: {r.message}", "warning")
        except Exception as exc:
            self.status(f"{kind} request error: {exc}", "warning")
