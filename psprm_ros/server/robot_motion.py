"""The robot's measured motion as the planning loop sees it: every robot state at its receipt, how fast the robot
moves, where a braking base comes to rest, where along the trajectory under way the robot is, and whether a plan
from an older state still starts where the robot is."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Optional

import numpy as np

from psprm_core.planning.execution import progress_time
from psprm_core.tracking import CheckedPath, displacement

from ..robots.adapters import braking_configurations
from ..robots.base_follower import Limits

#: the robot states a braking base's speed is measured over (s)
REST_VELOCITY_SPAN_S = 0.1
#: the robot states kept (s)
KEEP_S = 0.3
#: configurations of the trajectory under way within this much (s of motion at the velocity limits) of the nearest
#: one are the same pass for the progress estimate: the one nearest the clock is taken (progress_time's ``tie``)
PASS_TIE_S = 0.1
#: a base slower than this on both axes (m/s, rad/s) brakes over a negligible distance: its rest point is where it is
BRAKING_MIN_MPS, BRAKING_MIN_RADPS = 0.02, 0.05


def _moving(v: float, w: float) -> bool:
    return abs(v) >= BRAKING_MIN_MPS or abs(w) >= BRAKING_MIN_RADPS


class RobotMotion:
    """The robot states of about the last :data:`KEEP_S` (thread-safe: states arrive on the callers' threads, the
    worker and the stop guard read them), and the estimate of the robot's progress along the trajectory under way
    (worker only)."""

    def __init__(self, robot):
        self.robot = robot
        self._lock = threading.Lock()
        self._hist: deque = deque()  # (monotonic receipt, q, measured base velocity (v, omega) or None)
        self._along: Optional[tuple] = None  # (trajectory, time along it, perf_counter) of the last estimate

    def add(self, q: np.ndarray, now: float, base_velocity: Optional[np.ndarray] = None) -> None:
        """A robot state received at ``now`` (monotonic s), with the base's measured velocity (v, omega) where the
        robot reports one (odometry, tf)."""
        v = None if base_velocity is None else np.asarray(base_velocity, float).reshape(2)
        with self._lock:
            h = self._hist
            h.append((now, q, v if v is not None and np.isfinite(v).all() else None))
            while len(h) > 2 and now - h[1][0] >= KEEP_S:
                h.popleft()

    def states(self) -> list:
        """The robot states of about the last :data:`KEEP_S`, (monotonic receipt time, q), oldest first."""
        with self._lock:
            return [(t, q) for t, q, _ in self._hist]

    def newest(self) -> Optional[np.ndarray]:
        """The newest robot state (None before the first)."""
        with self._lock:
            return self._hist[-1][1] if self._hist else None

    def speed(self) -> float:
        """How fast the robot moved over its last robot states (the largest joint speed over its velocity limit; a
        fraction of full speed), from the robot states of the last :data:`KEEP_S` (at least 0.1 s apart); 1 until
        known."""
        h = self.states()
        if len(h) < 2 or h[-1][0] - h[0][0] < 0.1:
            return 1.0
        d = np.abs(h[-1][1] - h[0][1])
        if self.robot.mobile:
            d[2] = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
            d[0] = d[1] = float(np.hypot(*(h[-1][1][:2] - h[0][1][:2])))
        return float((d / np.maximum(self.robot.velocity, 1e-6)).max()) / (h[-1][0] - h[0][0])

    def rest_point(self, q: np.ndarray) -> np.ndarray:
        """Where a mobile base comes to rest braking at the robot config's base accelerations
        (:func:`psprm_ros.robots.adapters.braking_configurations`, the model the robot adapter refuses by); ``q`` itself
        for a fixed base or a base at rest. Its velocity is the one the robot measured with its newest state (odometry,
        tf: the adapter's own), else the velocity of its newest robot states (the newest and the newest one at
        least :data:`REST_VELOCITY_SPAN_S` older): a base braking from a stop slows all the while, so the speed over
        the span, its speed at the span's middle, is brought forward to the newest state at the braking
        deceleration. Receipt times jitter on a busy machine; a measured velocity does not."""
        if not self.robot.mobile:
            return q
        lim = Limits.for_robot(self.robot)
        with self._lock:
            measured = self._hist[-1][2] if self._hist else None
        if measured is not None:
            vel = (float(measured[0]), float(measured[1]))
            vel = vel if _moving(*vel) else None
        else:
            vel = self._states_velocity(lim)
        return q if vel is None else braking_configurations(q, vel, lim)[-1]

    def rest_distance(self, q: np.ndarray) -> float:
        """How far (m, the largest displacement of a point of the robot's collision boxes) a braking base still goes
        from ``q`` before it rests (:meth:`rest_point`); 0 for a fixed base or a base at rest."""
        if not self.robot.mobile:
            return 0.0
        rest = self.rest_point(q)
        return 0.0 if rest is q else float(displacement(self.robot, q, np.asarray(rest, float)[None])[0])

    def _states_velocity(self, lim: Limits) -> Optional[tuple]:
        """(v, omega) from the newest robot states' receipt times, brought forward to the newest state at the
        braking deceleration (:meth:`rest_point`); None without two states a span apart, or at rest."""
        h = self.states()
        older = [e for e in h[:-1] if h[-1][0] - e[0] >= REST_VELOCITY_SPAN_S]
        if not older:
            return None
        (ta, a), (tb, b) = older[-1], h[-1]
        dt = tb - ta
        th = 0.5 * (a[2] + b[2])
        v = ((b[0] - a[0]) * np.cos(th) + (b[1] - a[1]) * np.sin(th)) / dt
        w = float((b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi) / dt
        if not _moving(v, w):
            return None
        return (float(np.sign(v) * max(0.0, abs(v) - 0.5 * dt * lim.linear_acceleration)),
                float(np.sign(w) * max(0.0, abs(w) - 0.5 * dt * lim.angular_acceleration)))

    def stale_start(self, times: np.ndarray, positions: np.ndarray, tol: float, joint_tol: float = 0.0,
                    window_s: float = 2.0) -> str:
        """Why a plan from the robot's state no longer starts where the robot is ("" = it does, or no state came):
        the robot's newest state, and where it comes to rest braking from it, against the published samples'
        configurations (``times``, ``positions``) within ``window_s`` of their start
        (:meth:`psprm_core.tracking.CheckedPath.deviation`, the measure the adapter refuses by), and each joint
        other than the base's against the sample nearest the newest state (the adapter's controllers compare their
        joints there, each with its own start tolerance); ``tol`` / ``joint_tol`` <= 0: that check off."""
        q = self.newest()
        if q is None:
            return ""
        q = np.asarray(q, float)
        checked = CheckedPath(self.robot, times, positions)
        d, tau = checked.deviation(q, 0.0, window_s)
        if tol > 0:
            if self.robot.mobile:
                d = max(d, checked.deviation(self.rest_point(q), 0.0, window_s)[0])
            if d > tol:
                return (f"the robot moved while planning: braking from its newest state it comes {d:.3f} m from "
                        f"the trajectory's start (start tolerance {tol:g} m)")
        if joint_tol > 0:
            k0 = 3 if self.robot.mobile else 0
            i = min(int(np.searchsorted(np.asarray(times, float), tau)), len(times) - 1)
            err = np.abs(np.asarray(positions, float)[i, k0:] - q[k0:])
            j = int(np.argmax(err)) if len(err) else 0
            if len(err) and err[j] > joint_tol:
                return (f"the robot moved while planning: its {self.robot.joint_names[k0 + j]} lies {err[j]:.3f} "
                        f"from the trajectory's (joint start tolerance {joint_tol:g})")
        return ""

    def forget_progress(self) -> None:
        """A new trajectory went out: the next progress estimate starts afresh."""
        self._along = None

    def time_along(self, traj, t_zero: float, q: np.ndarray, tolerance_m: float) -> Optional[float]:
        """Where the robot is along the trajectory under way ``traj`` (s from its start; its configuration nearest
        the measured ``q``, searched forward from the last estimate, the first one from ``t_zero``, the perf_counter
        time the robot was at its start), or None: no trajectory, it has ended, or the robot is further than
        ``tolerance_m`` from it (stopped, refused, pushed off) or stands while it moves: a replan then starts where
        the robot is."""
        if traj is None:
            self._along = None
            return None
        now = time.perf_counter()
        prev = self._along
        if prev is None or prev[0] is not traj:
            guess = max(0.0, now - t_zero)
        else:
            guess = prev[1] + (now - prev[2])
        t = progress_time(traj, q, guess, window_s=1.5, scale=self.robot.velocity,
                          angle_cols=[2] if self.robot.mobile else [], tie=PASS_TIE_S)
        if prev is not None and prev[0] is traj:
            t = max(t, prev[1])  # the robot does not go back along its trajectory
        Pt, Vt, _ = (a[0] for a in traj.evaluate([t]))
        off = float(displacement(self.robot, q, Pt[None])[0])
        # a robot that stands while its trajectory moves (stopped by the adapter, held) does not follow it: a plan
        # spliced on there would start it at speed
        vmax = np.maximum(self.robot.velocity, 1e-6)
        moving = float((np.abs(Vt) / vmax).max()) > 0.2
        standing = self.speed() < 0.02
        if off > tolerance_m or (moving and standing) or t >= float(traj.duration) - 1e-6:
            self._along = None
            return None
        self._along = (traj, t, now)
        return t
