"""What the robot adapter does with the planned trajectories and at every control step, without ROS.

:class:`Execution` holds the adapter's execution state: the trajectory under way (its configurations for the path
tolerance, the trajectory as received for recognising a splice), the base follower's clock, a plan held while the
base brakes, the replan pending until the base rests, the Stretch driver's mode and runstop. It decides with
:class:`psprm_ros.robots.acceptance.TrajectoryAcceptance` whether and how a trajectory runs and sends it through the
node's controller links (:class:`psprm_ros.interfaces.controllers.ControllerLinks`, or any object with the same
methods); at every control step (:meth:`Execution.tick`) it releases goals held back by their goal interval, steps
the base follower and checks the path tolerance. A stop holds every controller at the measured configuration,
sends a zero twist and cancels the action goals; a refusal, an off-path stop or a failed goal asks for a new plan,
for a mobile base once it has come to rest.

The node is the ``port``: ``active``, ``now()``, ``measured()`` -> (q or None, why), ``base_velocity()`` (v, omega),
``last_joints()`` (the last measured configuration), ``status(text, level)``, ``request_replan(why)`` -> bool
(False when held back) and ``call_driver(service)`` (None when unavailable).
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Optional

import numpy as np

from psprm_core.tracking import CheckedPath

from .. import core
from . import adapters as ad
from . import stretch
from .acceptance import REST_WAIT_S, RestWatch, TrajectoryAcceptance, UnderWay, path_check
from .base_follower import BaseFollower, BaseReference

DRIVER_CONTROL_MODES = ("navigation", "position", "trajectory")
SWITCH_INTERVAL_S = 1.0  # at most one mode switch request per this long


class Execution:
    """The adapter's execution for ``robot`` (planning joints ``names``), reading the live parameters ``params``
    (path_tolerance_m, path_window_s) and counting in ``counts``; ``lock`` guards the state shared with the node's
    callbacks. :meth:`configure` gives it the adapter config, the controller links and the base follower."""

    def __init__(self, port, robot, names, params: dict, counts: dict, lock):
        self.port, self.robot, self.names = port, robot, list(names)
        self.p, self.counts, self._lock = params, counts, lock
        self.cfg: Optional[ad.AdapterConfig] = None
        self.links = None
        self.follower: Optional[BaseFollower] = None
        self.acceptance: Optional[TrajectoryAcceptance] = None
        self.grace: Optional[core.StallGrace] = None  # the follower step's stall grace
        # after a refusal or an off-path stop: the replan is asked for once the base has come to rest, so that the
        # new plan starts where the robot stands, not where it was while braking (which it has passed by then)
        self.rest = RestWatch()
        self.held = None  # (trajectory, velocities, when) held until the braking base rests
        self.zero_sent = 0
        self.speed_scaling = 1.0  # the controllers' speed scaling (0..1), which the base's path clock follows
        self.last_tick: Optional[float] = None
        self.last_refusal = ""
        self.last_state_problem = ""
        self.last_controller_error = ""
        self.max_tracking_error = np.zeros(2)  # (m, rad) over the current path
        self.checked: Optional[CheckedPath] = None  # the current trajectory's configurations, for path_tolerance_m
        # the current trajectory as received (before its start was trimmed to the robot's progress) and the time on
        # it at the follower's t0: a splice may begin before the point where this adapter joined the trajectory
        self.splice_ref: Optional[tuple] = None
        self.path_deviation = 0.0  # m, last measured (psprm_core.tracking.CheckedPath.deviation)
        self.max_path_deviation = 0.0  # m, over the current trajectory
        # the robot's driver, when it has modes (Stretch): the mode it reports, the one found at activation, runstop
        self.driver_mode = ""
        self.found_mode = ""
        self.runstopped = False
        self.replan_when_ready = ""
        self.last_switch_request = -1e9
        # one trajectory is accepted at a time (the node's acceptance thread, or a held plan released by a control
        # step); the control steps go on meanwhile
        self._accepting = threading.Lock()
        self.accept_ms_max = 0.0  # the longest acceptance of a trajectory (ms)
        self.control_gap_ms_max = 0.0  # the longest interval between two control steps while following (ms)

    def configure(self, cfg: ad.AdapterConfig, links, follower: Optional[BaseFollower]) -> None:
        """Execute on ``links`` (the controllers of ``cfg``) and ``follower`` (None for a robot without a base)."""
        self.cfg, self.links, self.follower = cfg, links, follower
        self.acceptance = TrajectoryAcceptance(self.robot, cfg, self.names,
                                               follower.limits if follower is not None else None)
        self.grace = core.StallGrace(1.0 / cfg.base.rate_hz)
        self.warm_up()

    def warm_up(self) -> float:
        """Run the checks a trajectory's acceptance and a control step make once, on a short made-up path: their
        first call loads the robot's collision elements (about 0.9 s on a 2-core machine), which the first
        trajectory's check would otherwise pay. Returns the seconds it took."""
        t0 = time.perf_counter()
        q = np.where(np.isfinite(self.robot.lower), self.robot.lower, 0.0) * 0.5 \
            + np.where(np.isfinite(self.robot.upper), self.robot.upper, 0.0) * 0.5
        path = CheckedPath(self.robot, np.array([0.0, 1.0]), np.stack([q, q]))
        path.deviation(q, 0.5, 1.0)
        path.path_distances(q[None], np.array([0.5]), 1.0)
        path.latest_time_of(q, 1.0, 1.0, 0.01)
        return time.perf_counter() - t0

    def cleanup(self) -> None:
        """Forget the adapter config, the links and the follower."""
        self.cfg = self.links = self.follower = self.acceptance = None

    # ------------------------------------------------------------------------------------------------ driver modes
    def driver_ready(self) -> tuple:
        """(ready, why not): the driver reports the configured mode and no runstop."""
        d = self.cfg.driver
        if d.kind == "none":
            return True, ""
        if self.runstopped:
            return False, "the robot is runstopped"
        if self.driver_mode != d.mode:
            return False, (f"the driver is in mode '{self.driver_mode or 'unknown'}', not '{d.mode}'"
                           f"{' (waiting for ' + d.mode_topic + ')' if not self.driver_mode else ''}")
        return True, ""

    def activate(self) -> None:
        """At activation: the driver in the configured mode (switched there first, the replan asked for once it
        reports it), then a replan."""
        d = self.cfg.driver
        if d.kind != "none":
            self.found_mode = self.driver_mode
            if self.driver_mode != d.mode:
                self.switch_mode(d.mode)
                self.replan_when_ready = "adapter activated"
                return
        self.port.request_replan("adapter activated")

    def on_mode(self, mode: str) -> None:
        """The mode the driver reports: a driver switched away is stopped and switched back; once it is ready, the
        replan waiting for it is asked for."""
        if mode != self.driver_mode:
            self.port.status(f"driver mode: {mode}")
        self.driver_mode = mode
        if self.cfg is None or not self.port.active:
            return
        d = self.cfg.driver
        if mode != d.mode and mode != "runstopped" and not self.runstopped:
            # someone switched the driver away: stop what runs (it would be refused) and switch back
            if self.follower is not None and not self.follower.done:
                self.stop(f"the driver left {d.mode} mode (now {mode})")
            self.switch_mode(d.mode)
            self.replan_when_ready = self.replan_when_ready or f"driver mode {mode}"
        elif self.replan_when_ready and self.driver_ready()[0]:
            if self.port.request_replan(self.replan_when_ready):
                self.replan_when_ready = ""

    def on_runstop(self, on: bool) -> None:
        """The driver's runstop: pressed stops everything; released asks for a new plan once the driver is ready."""
        if on == self.runstopped:
            return
        self.runstopped = on
        if on:
            self.counts["runstops"] += 1
            if self.cfg is not None:
                self.stop("runstop pressed")
            self.port.status("runstopped: no trajectory is executed until the runstop is released", "error")
        else:
            self.port.status("runstop released: asking for a new plan")
            self.replan_when_ready = "runstop released"

    def switch_mode(self, mode: str) -> None:
        """Ask the driver for ``mode`` (at most once a second)."""
        now = time.monotonic()
        if now - self.last_switch_request < SWITCH_INTERVAL_S:
            return
        if self.port.call_driver(self.cfg.driver.switch_name(mode)) is None:
            return
        self.last_switch_request = now
        self.counts["mode_switches"] += 1
        self.port.status(f"switching the driver to {mode} mode")

    def restore_driver_mode(self) -> None:
        """Put the driver back in the mode found at activation (when it was one of the driver's control modes)."""
        if self.cfg is None or self.cfg.driver.kind == "none":
            return
        found, want = self.found_mode, self.cfg.driver.mode
        if found and found != want and found in DRIVER_CONTROL_MODES:
            if self.port.call_driver(self.cfg.driver.switch_name(found)) is not None:
                self.port.status(f"driver returned to {found} mode")

    # ------------------------------------------------------------------------------------------------ execution
    def execute(self, t: np.ndarray, P: np.ndarray, velocities: Callable[[], Optional[np.ndarray]]) -> bool:
        """Check a planned trajectory (times ``t``, positions ``P`` of the planning joints; ``velocities()`` gives
        its velocities or None, read once it gets that far) against the measured state and send it to the
        controllers and the base. One at a time; the control steps (:meth:`tick`) go on while it runs, so the base
        keeps following the trajectory under way (which a splice continues) however long the check takes."""
        t_start = time.perf_counter()
        with self._accepting:
            try:
                return self._execute(t, P, velocities)
            finally:
                self.accept_ms_max = max(self.accept_ms_max, (time.perf_counter() - t_start) * 1e3)

    def wait_accepted(self, timeout: float) -> bool:
        """Wait (at most ``timeout`` s) until no trajectory is being accepted; False if one still is."""
        if not self._accepting.acquire(timeout=timeout):
            return False
        self._accepting.release()
        return True

    def _execute(self, t: np.ndarray, P: np.ndarray, velocities: Callable[[], Optional[np.ndarray]]) -> bool:
        q, why = self.port.measured()
        if q is None:
            self.stop(f"trajectory not executed: {why}")
            return False
        if len(P) <= 1:
            self.held = None
            self.stop("stop trajectory received")
            return False
        if self.robot.mobile and self._braking():
            # a plan that arrives while the base still brakes from a stop was made from where the base was, which it
            # has passed by now: it waits until the base rests (at most REST_WAIT_S), then starts from there
            if self.held is None:
                self.counts["held_until_rest"] += 1
                self.port.status("trajectory held until the base rests (it is braking from a stop)")
            self.held = (t, P, velocities, self.port.now())
            return True
        self.held = None
        ready, why_not = self.driver_ready()
        if not ready:
            self.stop(f"trajectory not executed: {why_not}")
            self.replan_when_ready = self.replan_when_ready or why_not
            if not self.runstopped:
                self.switch_mode(self.cfg.driver.mode)
            return False
        refusal = self.acceptance.navigation_refusal(P, q)
        if refusal:
            return self.refuse(refusal)
        missing = self.links.missing()
        if missing:
            return self.refuse("; ".join(missing))
        V = velocities()
        vel, under_way = None, None
        if self.robot.mobile:
            with self._lock:
                vel = np.asarray(self.port.base_velocity(), float).copy()
                under_way = UnderWay(self.checked, self.splice_ref, self.port.now() - self.follower.t0,
                                     not self.follower.done)
        v = self.acceptance.decide(t, P, V, q, vel, under_way, self.p["path_tolerance_m"], self.p["path_window_s"])
        if v.spliced:
            self.counts["spliced"] += 1
        if v.stop:
            self.stop(v.stop)
            return False
        if not v.accepted:
            return self.refuse(v.reason)
        t, P, V = v.times, v.positions, v.velocities
        now = self.port.now()
        start_at = now + v.lead
        if self.cfg.base.mode == "stretch_trajectory":
            ok = self._execute_trajectory_mode(t, P, V, q, now)
            if ok:
                with self._lock:
                    self.splice_ref = v.received
            return ok
        with self._lock:
            for c in self.cfg.controllers:
                if self.cfg.driver.mode == "navigation":
                    continue  # the arm and head stay where they are (checked above)
                out = self.links.offer(c, (t, P, V, start_at), now)
                if out is not None:
                    self._send(c, *out, now=now)
            if self.robot.mobile:
                self.follower.set_path(BaseReference(t, P[:, :3]), start_at)
                self.max_tracking_error = np.zeros(2)
                self.checked, self.max_path_deviation = v.checked, 0.0
                self.splice_ref = v.received
                self.zero_sent = 0
        self.counts["executed"] += 1
        self.last_refusal = ""
        self.rest.clear()  # a new plan came meanwhile
        return True

    def _execute_trajectory_mode(self, t, P, V, q, now: float) -> bool:
        """Stretch's trajectory mode: the trajectory from now on as one goal with the base
        (:func:`psprm_ros.robots.stretch.checked_goal`), its first waypoint where the joints are; what the driver
        makes of it must stay within ``max_goal_deviation_m`` of the planned trajectory. Goals closer than the goal
        interval wait for it (trimmed to the moment they leave)."""
        c = self.cfg.controllers[0]
        with self._lock:
            out = self.links.offer(c, (t, P, V, now), now)
            if out is None:
                self.counts["executed"] += 1
                return True
        ok = self._send_trajectory_mode(c, *out, now=now, q=q)
        if ok:
            self.counts["executed"] += 1
            self.last_refusal = ""
            self.rest.clear()
        return ok

    def _send_trajectory_mode(self, c, t, P, V, start_at: float, now: float, q=None) -> bool:
        late = now - start_at
        if late > 1e-6:
            t, P, V = ad.trim_from(np.asarray(t, float) - t[0], P, V, late)
            if len(t) <= 1:
                return True
        if q is None:  # a goal released by the goal interval: the state now (execute passes the one it checked)
            q, why = self.port.measured()
            if q is None:
                self.stop(f"trajectory not executed: {why}")
                return False
        goal, ts, Pg, checked, refusal = stretch.checked_goal(self.robot, c, self.names, np.asarray(t, float) - t[0],
                                                              P, V, q, self.cfg.base, self.p["path_window_s"])
        if refusal:
            return self.refuse(refusal)
        if self.p["path_tolerance_m"] <= 0:
            checked = None
        with self._lock:
            self.links.send_goal(c, goal)
            self.follower.set_path(BaseReference(ts, Pg[:, :3]), now)
            self.checked, self.max_path_deviation = checked, 0.0
            self.max_tracking_error = np.zeros(2)
        return True

    def _braking(self) -> bool:
        """The base moves (measured) while no trajectory runs: it brakes after a stop."""
        if self.follower is None or not self.follower.done:
            return False
        with self._lock:
            return RestWatch.moving(self.port.base_velocity())

    def _release_held(self, now: float) -> None:
        t, P, velocities, since = self.held
        if self._braking() and now - since < REST_WAIT_S:
            return
        if self._accepting.locked():  # a newer trajectory is being accepted: it decides, not this step
            return
        self.held = None
        try:
            self.execute(t, P, velocities)
        except Exception as exc:
            self.stop(f"cannot execute the trajectory: {exc}")

    def _send(self, c: ad.ControllerConfig, t, P, V, start_at: float, now: float) -> None:
        self.links.send(c, ad.controller_command(c, self.names, t, P, V, now=now, start_at=start_at))

    def controller_failed(self, name: str, why: str) -> None:
        """A controller rejected or aborted its newest goal (or its action server is gone): stop, ask for a plan."""
        self.counts["goals_failed"] += 1
        self.last_controller_error = f"{name}: {why}"
        if not self.port.active:
            return
        self.stop(f"{name}: {why}")
        if self.follower is not None:
            self.rest.pending = why
        else:
            self.port.request_replan(why)

    def refuse(self, why: str) -> bool:
        """Refuse a trajectory: stop and ask for a new plan (a base: once it rests). False."""
        self.counts["refused"] += 1
        self.last_refusal = why
        self.stop(f"trajectory refused: {why}")
        if self.follower is not None:  # a base: asked for once it rests (_ask_when_at_rest)
            self.rest.pending = why
        else:
            self.port.request_replan(why)
        return False

    def stop(self, why: str) -> None:
        """Stop every interface: zero twist, a hold at the measured configuration on every topic controller, cancel
        every active action goal."""
        if self.cfg is None:
            return
        q, _ = self.port.measured()
        now = self.port.now()
        self.held = None
        with self._lock:
            self.checked = self.splice_ref = None
            if self.follower is not None:
                self.follower.stop()
            self.links.publish_twist(0.0, 0.0)
            if q is None:
                q = self.port.last_joints()  # the last measured joints: hold there
            self.links.halt(self.names, q, now)
        d = self.cfg.driver
        if d.kind == "stretch":
            # the driver's own stop; a trajectory-mode goal ignores cancels, and re-entering trajectory mode drops
            # the waypoint trajectories under way
            self.port.call_driver(d.stop_service)
            if d.mode == "trajectory" and self.driver_mode == "trajectory":
                self.port.call_driver(d.switch_name("trajectory"))
        self.counts["stops"] += 1
        self.port.status(f"robot stopped: {why}", "warning")

    # ------------------------------------------------------------------------------------------------ control step
    def tick(self) -> None:
        """Follower step (and goals released by their interval) at the base rate."""
        if not self.port.active or self.cfg is None:
            return
        now = self.port.now()
        with self._lock:
            due = self.links.due(now)
        for c, item in due:
            if self.cfg.base.mode == "stretch_trajectory":
                self._send_trajectory_mode(c, *item, now=now)
            else:
                with self._lock:
                    self._send(c, *item, now=now)
        if self.follower is None:
            return
        following = not self.follower.done
        dt, self.last_tick = (0.0 if self.last_tick is None else now - self.last_tick), now
        if following and 0.0 < dt < 10.0:
            self.control_gap_ms_max = max(self.control_gap_ms_max, dt * 1e3)
        if following and self.speed_scaling < 1.0 and 0.0 < dt < 1.0:
            # the path clock runs at the controllers' speed scaling: the base stays in step with a slowed arm
            with self._lock:
                self.follower.t0 += dt * (1.0 - self.speed_scaling)
        self.follower.rate = self.speed_scaling
        late = self.grace.step()
        q, why = self.port.measured()
        if q is None:
            self.last_state_problem = why
            # a late step (this process stalled) may find the state messages still queued: decide at the next step,
            # after they are taken; a second stale step in a row stops
            if following and self.grace.forgive(late):
                return
            if following:
                self.stop(why)
            return
        self.grace.clear()
        self.last_state_problem = ""
        if self.held is not None:
            self._release_held(now)
        if self.rest.pending:
            self._ask_when_at_rest(now)
        with self._lock:
            v, w = self.follower.command(now, q[:3])
            if following:
                e = self.follower.error
                self.max_tracking_error = np.maximum(self.max_tracking_error, [np.hypot(e[0], e[1]), abs(e[2])])
            if following or self.zero_sent < 3:  # after the end: a few zero twists, then quiet
                self.links.publish_twist(v, w)
                self.zero_sent = 0 if following else self.zero_sent + 1
            checked, t0 = self.checked, self.follower.t0
        if following and checked is not None:
            self._check_path(checked, q, now - t0)

    def _ask_when_at_rest(self, now: float) -> None:
        """Ask for the pending replan once the base has come to rest (:meth:`RestWatch.due`); a request the
        interval holds back is tried again at the next step."""
        with self._lock:
            vel = np.asarray(self.port.base_velocity(), float).copy()
        if self.rest.due(now, vel) and self.port.request_replan(self.rest.pending):
            self.rest.clear()

    def _check_path(self, checked: CheckedPath, q: np.ndarray, tau: float) -> None:
        """The path tolerance (:func:`psprm_ros.robots.acceptance.path_check`): beyond ``path_tolerance_m`` the
        robot stops and a new plan is asked for, from where it is."""
        try:
            d, why = path_check(checked, q, tau, self.p["path_tolerance_m"], self.p["path_window_s"])
        except Exception as exc:  # never lose the control loop to the check; a check that fails stops the robot
            self.stop(f"path check failed: {exc}")
            return
        self.path_deviation = d
        self.max_path_deviation = max(self.max_path_deviation, d)
        if why:
            self.counts["off_path_stops"] += 1
            self.stop(why)
            self.rest.pending = why
