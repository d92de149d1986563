"""Controller commands from a planned trajectory of the planning joints (no ROS): what each controller of an adapter
config (:mod:`psprm_ros.robots.adapters`) is sent, and where the robot is along a trajectory.

:func:`controller_command` builds a controller's goal (:class:`Command`: its joints only, under the robot's names,
times strictly increasing, the first point ``lead_time_s`` ahead); :func:`hold_command` the stop every JTC accepts;
:func:`check_start` / :func:`check_base_start` the start checks against the measured state; :class:`GoalGate` at most
one goal per ``min_goal_interval_s``. :func:`progress_offset`, :func:`splice_progress`, :func:`join_along`,
:func:`sample_at`, :func:`trim_from` and :func:`braking_configurations` place the robot along a trajectory (its
progress, its time along a splice, the way to a splice ahead of it, what it passes while braking).
:func:`to_joint_trajectory`, :func:`action_goal_fields` and :func:`fill_goal` turn a command into ROS messages,
importing the message packages inside;
:func:`stretch_base_steps` / :func:`stretch_base_command` are Stretch's position-mode base goals.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, List, Optional, Sequence

import numpy as np

from psprm_core.errors import InputError
from psprm_core.geometry import wrap_angle

from ..interfaces.conversions import duration_msg, sec_to_stamp

if TYPE_CHECKING:  # the adapter config's types, for the annotations only
    from .adapters import BaseConfig, ControllerConfig

BASE_JOINTS = ("base_x", "base_y", "base_theta")


@dataclasses.dataclass
class Command:
    """One controller goal, message-independent: joint names (robot names), ``stamp`` (seconds; 0 = start now),
    point times (s from the stamp), positions and velocities (M, n)."""

    controller: str
    joint_names: list
    stamp: float
    times: np.ndarray
    positions: np.ndarray
    velocities: Optional[np.ndarray] = None


def columns(names: Sequence[str], wanted: Sequence[str]) -> list:
    idx = []
    for j in wanted:
        if j not in names:
            raise InputError(f"trajectory has no joint '{j}' (has {', '.join(names)})")
        idx.append(list(names).index(j))
    return idx


def controller_command(ctrl: ControllerConfig, names: Sequence[str], times, positions, velocities=None,
                       now: float = 0.0, start_at: Optional[float] = None) -> Command:
    """The goal for ``ctrl`` from a planned trajectory (``names`` = its planning joints, ``times`` from 0):
    the controller's joints only, under their robot names, the trajectory starting at ``start_at`` (the caller's
    clock; default ``now + lead_time_s``, so the first point lies in the future and the controller blends from
    where the robot is). ``stamp: lead`` gives stamp = start_at with the planned times; ``stamp: zero`` gives stamp 0
    with the times shifted by ``start_at - now``; a start already past (a goal held back by the goal interval)
    drops the part of the trajectory before ``now + lead_time_s``, its first point interpolated there."""
    t = np.asarray(times, float).reshape(-1)
    P = np.asarray(positions, float).reshape(len(t), -1)
    if len(t) == 0 or not np.isfinite(t).all() or np.any(np.diff(t) <= 0) or not np.isfinite(P).all():
        raise InputError("trajectory times must be finite and strictly increasing, positions finite")
    idx = columns(names, ctrl.joints)
    P = P[:, idx]
    V = None if velocities is None else np.asarray(velocities, float).reshape(len(t), -1)[:, idx]
    t = t - t[0]
    start_at = now + ctrl.lead_time_s if start_at is None else float(start_at)
    late = now + ctrl.lead_time_s - start_at  # > 0: the planned start is (nearly) past
    if late > 1e-9:
        t, P, V = trim_from(t, P, V, late)
        start_at = now + ctrl.lead_time_s
    if ctrl.stamp == "zero":
        stamp, t = 0.0, t + (start_at - now)
    else:
        stamp = start_at
    return Command(ctrl.name, ctrl.robot_joints, stamp, t, P.copy(), None if V is None else V.copy())


def progress_offset(times, positions, measured: np.ndarray, velocity=(0.0, 0.0), lead: float = 0.0,
                    horizon_s: float = 1.5, velocity_limits: Optional[np.ndarray] = None) -> float:
    """Where along a new trajectory the robot will be when it starts: the time (within ``horizon_s`` of its start)
    whose configuration is nearest to the measured one, the base moved ``lead`` seconds on at the measured
    ``velocity`` (v, omega). Nearness is time-like: the largest joint difference divided by that joint's velocity
    limit (``velocity_limits``; base x, y, theta first). A replan starts from the robot's state when planning began;
    by the time it is executed the robot has moved on, and starting the new trajectory at its beginning would pull
    the robot back. 0 for a robot at rest at the trajectory's start."""
    t = np.asarray(times, float)
    P = np.asarray(positions, float)
    pred = np.asarray(measured, float).copy()
    x, y, th = (float(v) for v in pred[:3])
    v, w = (float(a) for a in velocity)
    th_m = th + 0.5 * w * lead
    pred[:3] = [x + v * lead * math.cos(th_m), y + v * lead * math.sin(th_m), th + w * lead]
    sel = np.nonzero(t - t[0] <= horizon_s)[0]
    if len(sel) == 0:
        return 0.0
    vl = np.ones(P.shape[1]) if velocity_limits is None else np.maximum(np.asarray(velocity_limits, float), 1e-6)
    d = np.abs(P[sel] - pred)
    d[:, 2] = np.abs(np.remainder(P[sel, 2] - pred[2] + math.pi, 2 * math.pi) - math.pi)
    lin = np.hypot(P[sel, 0] - pred[0], P[sel, 1] - pred[1])
    cost = np.maximum((d[:, 2:] / vl[2:]).max(1), lin / vl[0])
    return float(t[sel[int(np.argmin(cost))]] - t[0])


def splice_progress(executing, tau: float, times, positions, lookback_s: float, tol: float) -> Optional[float]:
    """The robot's time along a splice: a splice repeats the trajectory under way (``executing``, a
    :class:`psprm_core.tracking.CheckedPath` of it as received, the robot ``tau`` seconds along it) from where the
    replan began up to its commit instant, so the robot is as far along the splice as it is along ``executing``
    beyond the splice's first configuration. That configuration is found on ``executing`` at its latest pass
    within ``lookback_s`` before ``tau`` (up to 1 s after it: the server's estimate of the robot's progress may lead
    this one), within ``tol`` (:meth:`~psprm_core.tracking.CheckedPath.latest_time_of`). None when it lies there
    nowhere; negative (minus the time from the robot to it on ``executing``) when the splice begins ahead of the
    robot. A nearest-configuration search over the splice (:func:`progress_offset`) is ambiguous where the splice
    comes back on itself (a turn on the spot reversed after the commit instant): it may place the robot beyond the
    commit instant, on motion it has not made."""
    t = np.asarray(times, float)
    s0 = executing.latest_time_of(np.asarray(positions, float)[0], tau + 1.0, lookback_s + 1.0, tol)
    return None if s0 is None else float(min(tau - s0, t[-1] - t[0]))


def sample_at(times, positions, taus) -> np.ndarray:
    """Configurations (len(taus), dof) of a trajectory, linear between its points, at times ``taus`` from its start."""
    t = np.asarray(times, float)
    t = t - t[0]
    P = np.asarray(positions, float)
    return np.stack([np.interp(taus, t, P[:, j]) for j in range(P.shape[1])], axis=1)


def join_along(path, t_from: float, t_to: float, times, positions, velocities=None) -> tuple:
    """(times, positions, velocities): the configurations of ``path`` (a :class:`psprm_core.tracking.CheckedPath`,
    linear between its samples) from its time ``t_from`` to ``t_to``, then the trajectory ``times`` (from its
    first, which lies on ``path`` at ``t_to``), ``positions`` and ``velocities`` (None, or finite differences along
    the joined part); times from 0."""
    t = np.asarray(times, float) - float(times[0])
    P = np.asarray(positions, float)
    inner = path.ts[(path.ts > t_from) & (path.ts < t_to)]
    tj = np.concatenate([[t_from], inner])
    Pj = sample_at(path.ts, path.Q, tj)
    gap = float(t_to - t_from)
    T = np.concatenate([tj - t_from, t + gap])
    X = np.concatenate([Pj, P])
    V = None
    if velocities is not None:
        Vj = np.diff(np.vstack([Pj, P[:1]]), axis=0) / np.diff(np.concatenate([tj, [t_to]]))[:, None]
        V = np.concatenate([Vj, np.asarray(velocities, float)])
    return T, X, V


def trim_from(t: np.ndarray, P: np.ndarray, V: Optional[np.ndarray], tau: float) -> tuple:
    """The trajectory from time ``tau`` on, re-based to start at 0 (its first point interpolated at ``tau``)."""
    if tau >= t[-1]:
        return np.zeros(1), P[-1:].copy(), None if V is None else np.zeros_like(V[-1:])
    k = int(np.searchsorted(t, tau, side="right"))
    f = (tau - t[k - 1]) / (t[k] - t[k - 1])
    p0 = P[k - 1] + f * (P[k] - P[k - 1])
    tt = np.r_[0.0, t[k:] - tau]
    PP = np.vstack([p0, P[k:]])
    VV = None if V is None else np.vstack([V[k - 1] + f * (V[k] - V[k - 1]), V[k:]])
    if len(tt) > 1 and tt[1] - tt[0] < 1e-6:  # tau fell on a sample
        tt, PP = tt[1:] - tt[1], PP[1:]
        VV = None if VV is None else VV[1:]
    return tt, PP, VV


def hold_command(ctrl: ControllerConfig, names: Sequence[str], measured: np.ndarray) -> Command:
    """The stop every JTC accepts: one point at the measured configuration, zero velocity, a positive
    ``time_from_start`` (``hold_time_s``) and stamp 0 (start now; never 'in the past')."""
    idx = columns(names, ctrl.joints)
    q = np.asarray(measured, float).reshape(-1)[idx]
    return Command(ctrl.name, ctrl.robot_joints, 0.0, np.array([ctrl.hold_time_s]), q[None].copy(),
                   np.zeros((1, len(idx))))


def check_start(ctrl: ControllerConfig, names: Sequence[str], first: np.ndarray, measured: np.ndarray,
                commanded: Optional[np.ndarray] = None) -> tuple:
    """(ok, joint, error): the largest |first point - measured| over the controller's joints against
    ``start_tolerance``; with ``commanded`` (the configuration the controller follows now, for a trajectory that
    continues it), each joint's error is the smaller of that and |first point - commanded|."""
    idx = columns(names, ctrl.joints)
    d = np.abs(np.asarray(first, float)[idx] - np.asarray(measured, float)[idx])
    if commanded is not None:
        d = np.minimum(d, np.abs(np.asarray(first, float)[idx] - np.asarray(commanded, float)[idx]))
    k = int(np.argmax(d))
    return bool(d[k] <= ctrl.start_tolerance), ctrl.joints[k], float(d[k])


def check_base_start(base: BaseConfig, first: np.ndarray, measured: np.ndarray) -> tuple:
    """(ok, what, error) for the base's (x, y, theta) against start_tolerance_m / _rad."""
    d_xy = float(np.hypot(first[0] - measured[0], first[1] - measured[1]))
    d_th = abs(wrap_angle(float(first[2] - measured[2])))
    if d_xy > base.start_tolerance_m:
        return False, "base position", d_xy
    if d_th > base.start_tolerance_rad:
        return False, "base heading", d_th
    return True, "base", max(d_xy, d_th)


def braking_configurations(q: np.ndarray, velocity, limits, n: int = 4) -> np.ndarray:
    """Configurations (n, dof) the base passes through when it brakes from ``velocity`` (v, omega) at the
    ``limits``' accelerations (``linear_acceleration``, ``angular_acceleration``), the other joints held: a unicycle
    decelerating uniformly on both axes, sampled at n equal fractions of the braking time, the last one where it
    rests. A base that is sent a trajectory starting behind it, or that is stopped, first travels this far."""
    q = np.asarray(q, float)
    v, w = (float(x) for x in velocity)
    tv = abs(v) / max(limits.linear_acceleration, 1e-9)
    tw = abs(w) / max(limits.angular_acceleration, 1e-9)
    T = max(tv, tw)
    out = np.repeat(q[None], n, 0)
    if T <= 0.0:
        return out
    for i, t in enumerate(np.linspace(T / n, T, n)):
        # distance and turn after t of uniform deceleration on each axis (each stops at its own time)
        a, b = min(t, tv), min(t, tw)
        s = v * a - np.sign(v) * 0.5 * limits.linear_acceleration * a * a
        phi = w * b - np.sign(w) * 0.5 * limits.angular_acceleration * b * b
        th = q[2] + 0.5 * phi  # the chord's heading (exact for a uniform turn, close for a decelerating one)
        out[i, 0] = q[0] + s * math.cos(th)
        out[i, 1] = q[1] + s * math.sin(th)
        out[i, 2] = q[2] + phi
    return out


def to_joint_trajectory(cmd: Command, frame_id: str = ""):
    """:class:`Command` -> ``trajectory_msgs/JointTrajectory``."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.header.frame_id = frame_id
    m.header.stamp = sec_to_stamp(cmd.stamp)
    m.joint_names = list(cmd.joint_names)
    pts = []
    for k in range(len(cmd.times)):
        p = JointTrajectoryPoint()
        p.positions = [float(v) for v in cmd.positions[k]]
        if cmd.velocities is not None:
            p.velocities = [float(v) for v in cmd.velocities[k]]
        p.time_from_start = duration_msg(float(cmd.times[k]))
        pts.append(p)
    m.points = pts
    return m


def action_goal_fields(cmd: Command, goal_time_tolerance_s: float = 1.0) -> dict:
    """The fields of a ``control_msgs/FollowJointTrajectory`` goal for ``cmd``: ``trajectory`` (JointTrajectory) and
    ``goal_time_tolerance`` (builtin_interfaces/Duration). Tolerances are left at their defaults (the controller's
    own)."""
    return {"trajectory": to_joint_trajectory(cmd), "goal_time_tolerance": duration_msg(goal_time_tolerance_s)}


def fill_goal(goal, fields: dict):
    """Set ``fields`` on a FollowJointTrajectory goal object (refuses a field the goal type does not have)."""
    for k, v in fields.items():
        if not hasattr(goal, k):
            raise AttributeError(f"{type(goal).__name__} has no field '{k}'")
        setattr(goal, k, v)
    return goal


def import_follow_joint_trajectory():
    """``control_msgs.action.FollowJointTrajectory`` or None when control_msgs is not installed (it comes with a
    robot's ROS install, ``apt install ros-jazzy-control-msgs``; it is not on PyPI)."""
    try:
        from control_msgs.action import FollowJointTrajectory
    except ImportError:
        return None
    return FollowJointTrajectory


class GoalGate:
    """At most one goal per ``interval`` seconds: a goal offered too early is kept (the newest one) and released by
    :meth:`due` once the interval has passed. Stops pass at once."""

    def __init__(self, interval: float):
        self.interval = float(interval)
        self.last_sent: Optional[float] = None
        self.pending = None

    def offer(self, item, now: float, urgent: bool = False):
        """Returns the item to send now, or None (kept as pending)."""
        if urgent or self.last_sent is None or now - self.last_sent >= self.interval:
            self.pending = None
            self.last_sent = now
            return item
        self.pending = item
        return None

    def due(self, now: float):
        if self.pending is not None and now - self.last_sent >= self.interval:
            item, self.pending = self.pending, None
            self.last_sent = now
            return item
        return None


# --------------------------------------------------------------------------------------------------------- Stretch base
def stretch_base_steps(base_waypoints: np.ndarray, min_step_m: float = 0.005, min_step_rad: float = 0.01) -> list:
    """Stretch position-mode base goals for a diff-drive path: ``[("rotate_mobile_base", dtheta) |
    ("translate_mobile_base", d), ...]``, one joint per goal (the driver refuses both in one goal). Each path segment
    is rotate to the driving heading, drive straight (negative = backwards), and the final heading is reached by a
    last rotation. Increments below the minimum steps are skipped."""
    W = np.asarray(base_waypoints, float).reshape(-1, 3)
    steps: List[tuple] = []
    heading = float(W[0, 2])

    def rot(target):
        nonlocal heading
        d = wrap_angle(target - heading)
        if abs(d) > 1e-9:
            steps.append(("rotate_mobile_base", d))
            heading = heading + d

    for a, b in zip(W[:-1], W[1:]):
        dxy = b[:2] - a[:2]
        dist = float(np.hypot(*dxy))
        if dist > 1e-4:
            drive = math.atan2(dxy[1], dxy[0])
            # drive backwards when that needs less turning (as the planner's local motions do)
            if abs(wrap_angle(drive - heading)) > math.pi / 2:
                rot(drive + math.pi)
                steps.append(("translate_mobile_base", -dist))
            else:
                rot(drive)
                steps.append(("translate_mobile_base", dist))
    rot(float(W[-1, 2]))
    merged: List[tuple] = []
    for j, d in steps:  # a path sampled densely gives runs of the same motion: one goal each
        if merged and merged[-1][0] == j and (j == "rotate_mobile_base" or np.sign(merged[-1][1]) == np.sign(d)):
            merged[-1] = (j, merged[-1][1] + d)
        else:
            merged.append((j, d))
    return [(j, d) for j, d in merged
            if abs(d) >= (min_step_m if j == "translate_mobile_base" else min_step_rad)]


def stretch_base_command(step: tuple, base: BaseConfig, linear_velocity: float, angular_velocity: float) -> Command:
    """One position-mode base goal: the joint ``translate_mobile_base`` or ``rotate_mobile_base`` with its increment,
    timed at the base's velocity limit, stamp 0 (the driver requires it)."""
    joint, inc = step
    speed = linear_velocity if joint == "translate_mobile_base" else angular_velocity
    dur = max(0.2, abs(inc) / max(speed, 1e-6))
    return Command("base", [joint], 0.0, np.array([dur]), np.array([[inc]]), np.zeros((1, 1)))


def base_columns(names: Sequence[str]) -> list:
    return columns(names, BASE_JOINTS)
