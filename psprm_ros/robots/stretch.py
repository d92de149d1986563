"""Stretch 2 trajectory mode: a planned whole-body trajectory as one goal the driver (stretch_ros2 ``stretch_core``,
``joint_trajectory_server.py``) executes.

In trajectory mode the driver hands every joint's waypoints to Stretch Body, which checks them
(``stretch_body.trajectories``) before it moves anything:

* ``header.stamp`` 0 (a stamp in the past or the future is aborted);
* every joint's first waypoint at ``time_from_start`` 0 and at the joint's present position;
* consecutive waypoints more than 0.8 s apart (``WAYPOINT_ISCLOSE_ATOL``; closer ones "cannot be planned for the
  same time");
* the base is the multi-DOF joint ``position`` of ``multi_dof_trajectory``: (x, y, theta) relative to where the base
  is when the goal starts (the first waypoint is the identity), each segment either a pure rotation or a pure
  translation along the heading (``get_pose_diff``: a segment that both translates and rotates moves by nothing);
* waypoint velocities (``JointTrajectoryPoint.velocities``, the base's ``Twist`` linear.x / angular.z) make the
  segments cubic; without them they are linear.

The planner's base paths are made of exactly such motions (``psprm_core.motion``: rotate, translate, rotate; the
timing stops where the base changes its motion), so :func:`trajectory_mode_goal` places waypoints at the base's
phase changes and inside each phase at least ``min_interval_s`` apart, stretching a phase shorter than that in
time (the path stays the same; the robot only takes longer over it). :func:`executed` gives the configurations the
driver produces from those waypoints (cubic Hermite segments), which the adapter compares with the planned
trajectory before it sends anything: what the driver executes must stay within the path tolerance of what was
checked (:func:`checked_goal`: a controller's goal and that check).

No ROS import at module level.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import numpy as np

from psprm_core.errors import InputError
from psprm_core.geometry import wrap_angle
from psprm_core.tracking import CheckedPath

from ..interfaces.conversions import duration_msg, yaw_quat

BASE_JOINT = "position"  # the driver's multi-DOF base joint in trajectory mode
DRIVER_MIN_INTERVAL_S = 0.8  # Stretch Body refuses waypoints this close (or closer) in time
TRANSLATION_ATOL_M = 2e-3  # a base segment moving (x, y) less than this is a rotation (stretch_body get_pose_diff)
TRANSLATING, ROTATING, STILL = 0, 1, 2


@dataclasses.dataclass
class TrajectoryModeGoal:
    """One trajectory-mode goal: the joints (robot names) and the base, each with its own waypoints.

    ``times`` (K,) from 0; ``positions`` / ``velocities`` (K, n) of the joints; ``base`` (K, 3) the base's (x, y,
    theta) relative to its pose at the start; ``base_twist`` (K, 2) its (forward, turn) velocity; ``warp`` maps the
    planned trajectory's times to the goal's (``planned_times`` (K,) beside ``times``)."""

    joint_names: list
    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    base: np.ndarray
    base_twist: np.ndarray
    planned_times: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def planned_time(self, t_goal) -> np.ndarray:
        """The planned trajectory's time at goal time(s) ``t_goal`` (the inverse of the stretch)."""
        return np.interp(t_goal, self.times, self.planned_times)


def relative_pose(origin: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(x, y, theta) of ``pose`` (..., 3) in the frame of ``origin`` (3,); theta continuous (not wrapped)."""
    c, s = math.cos(origin[2]), math.sin(origin[2])
    d = np.asarray(pose, float)[..., :2] - origin[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1],
                     np.asarray(pose, float)[..., 2] - origin[2]], -1)


def compose(origin: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """The inverse of :func:`relative_pose`: ``rel`` (..., 3) in the frame of ``origin`` -> the outer frame."""
    c, s = math.cos(origin[2]), math.sin(origin[2])
    rel = np.asarray(rel, float)
    return np.stack([origin[0] + c * rel[..., 0] - s * rel[..., 1], origin[1] + s * rel[..., 0] + c * rel[..., 1],
                     origin[2] + rel[..., 2]], -1)


def base_phases(times: np.ndarray, base: np.ndarray, tol_m: float = 1e-4, tol_rad: float = 1e-4) -> list:
    """The base's motion split into phases ``[(kind, i0, i1), ...]`` over sample indices (inclusive ends):
    ``TRANSLATING`` (moving along a line, heading constant), ``ROTATING`` (turning in place) or ``STILL``. A sample
    interval that both translates and rotates (beyond ``tol_m`` / ``tol_rad``) is an error: the driver cannot
    execute it."""
    d_xy = np.hypot(*np.diff(base[:, :2], axis=0).T)
    d_th = np.abs(wrap_angle(np.diff(base[:, 2])))
    kinds = np.full(len(d_xy), STILL)
    kinds[d_th > tol_rad] = ROTATING
    kinds[d_xy > tol_m] = TRANSLATING
    bad = np.nonzero((d_xy > tol_m) & (d_th > tol_rad))[0]
    if len(bad):
        k = int(bad[0])
        raise InputError(f"the base both drives ({d_xy[k]:.4f} m) and turns ({d_th[k]:.4f} rad) between "
                         f"t = {times[k]:.3f} s and {times[k + 1]:.3f} s: Stretch's trajectory mode executes a "
                         "segment that does both as no motion")
    # a pause of the base belongs to the motion before it (to the one after it at the start): a segment that rests
    # for part of its time is still a pure translation or rotation
    for i in range(len(kinds)):
        if kinds[i] == STILL and i > 0:
            kinds[i] = kinds[i - 1]
    moving = np.nonzero(kinds != STILL)[0]
    if len(moving):
        kinds[:moving[0]] = kinds[moving[0]]
    phases = []
    i0 = 0
    for i in range(1, len(kinds) + 1):
        if i == len(kinds) or kinds[i] != kinds[i0]:
            phases.append((int(kinds[i0]), i0, i))
            i0 = i
    return phases


def trajectory_mode_goal(joint_names: Sequence[str], times, positions, velocities=None,
                         min_interval_s: float = 0.9) -> TrajectoryModeGoal:
    """The goal for a planned trajectory (``times`` from 0, ``positions`` (N, 3 + n): the base (x, y, theta) then
    the n joints the driver knows as ``joint_names``; ``velocities`` alike, or None for finite differences). The
    goal's ``positions`` / ``velocities`` hold the n joints. See the module docstring for the rules."""
    if min_interval_s <= DRIVER_MIN_INTERVAL_S:
        raise InputError(f"min_interval_s must exceed the driver's {DRIVER_MIN_INTERVAL_S} s, got {min_interval_s}")
    t = np.asarray(times, float).reshape(-1)
    P = np.asarray(positions, float).reshape(len(t), -1)
    if len(t) < 2 or not np.isfinite(t).all() or np.any(np.diff(t) <= 0) or not np.isfinite(P).all():
        raise InputError("trajectory times must be finite and strictly increasing, positions finite, >= 2 points")
    t = t - t[0]
    V = np.gradient(P, t, axis=0) if velocities is None else np.asarray(velocities, float).reshape(P.shape)
    base = P[:, :3]
    # breakpoints: the phase changes (where the base rests), and inside each phase evenly spaced points at least
    # min_interval_s apart; a phase shorter than that is stretched in time to min_interval_s
    tp, te, kinds = [0.0], [0.0], []
    for kind, i0, i1 in base_phases(t, base):
        a, b = t[i0], t[i1]
        n = max(1, int((b - a) // min_interval_s))
        for k in range(1, n + 1):
            tp.append(a + (b - a) * k / n)
            te.append(te[-1] + max((b - a) / n, min_interval_s))
            kinds.append(kind)
    tp, te = np.array(tp), np.array(te)
    slope = np.ones(len(tp))  # d(planned time) / d(goal time) at each breakpoint
    seg = np.diff(tp) / np.diff(te)
    # at a breakpoint between two pieces of different stretch the base rests (a phase change): either slope serves
    slope[1:] = seg
    slope[0] = seg[0]
    Pk = np.stack([np.interp(tp, t, P[:, j]) for j in range(P.shape[1])], 1)
    Vk = np.stack([np.interp(tp, t, V[:, j]) for j in range(P.shape[1])], 1) * slope[:, None]
    rel = relative_pose(Pk[0, :3], Pk[:, :3])
    heading = Pk[:, 2]
    fwd = Vk[:, 0] * np.cos(heading) + Vk[:, 1] * np.sin(heading)
    twist = np.stack([fwd, Vk[:, 2]], 1)
    # exact pure motions (the planned ones within the phase tolerances): a rotation keeps (x, y); a translation
    # keeps theta and moves along the heading (the planned end projected on that line)
    for k, kind in enumerate(kinds, start=1):
        if kind == TRANSLATING:
            th = rel[k - 1, 2]
            d = (rel[k, 0] - rel[k - 1, 0]) * math.cos(th) + (rel[k, 1] - rel[k - 1, 1]) * math.sin(th)
            rel[k] = [rel[k - 1, 0] + d * math.cos(th), rel[k - 1, 1] + d * math.sin(th), th]
        else:
            rel[k, :2] = rel[k - 1, :2]
            if kind == STILL:
                rel[k, 2] = rel[k - 1, 2]
    return TrajectoryModeGoal(list(joint_names), te, Pk[:, 3:], Vk[:, 3:], rel, twist, tp)


def hermite(t_knots: np.ndarray, x: np.ndarray, v: np.ndarray, ts) -> np.ndarray:
    """Cubic Hermite interpolation of knots (K,) / (K, n) with velocities at times ``ts`` (clamped to the ends)."""
    t_knots = np.asarray(t_knots, float)
    ts = np.clip(np.asarray(ts, float), t_knots[0], t_knots[-1])
    k = np.clip(np.searchsorted(t_knots, ts, side="right") - 1, 0, len(t_knots) - 2)
    h = t_knots[k + 1] - t_knots[k]
    s = (ts - t_knots[k]) / h
    x, v = np.asarray(x, float), np.asarray(v, float)
    squeeze = x.ndim == 1
    if squeeze:
        x, v = x[:, None], v[:, None]
    s = s[:, None]
    h = h[:, None]
    h00, h10, h01, h11 = 2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s, -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2
    out = h00 * x[k] + h10 * h * v[k] + h01 * x[k + 1] + h11 * h * v[k + 1]
    return out[:, 0] if squeeze else out


def executed(goal: TrajectoryModeGoal, start_base: np.ndarray, ts) -> tuple:
    """(base (M, 3) in the outer frame, joints (M, n)) the driver produces at goal times ``ts`` from the base pose
    ``start_base`` at the goal's start: cubic segments through the waypoints, the base turning in place or driving
    along its heading within each segment."""
    ts = np.asarray(ts, float)
    J = hermite(goal.times, goal.positions, goal.velocities, ts)
    rel = goal.base
    k = np.clip(np.searchsorted(goal.times, ts, side="right") - 1, 0, len(goal.times) - 2)
    out = np.empty((len(ts), 3))
    # per segment: the driving distance or the turn, cubic in time from the waypoints' twists
    d_xy = np.hypot(*np.diff(rel[:, :2], axis=0).T)
    for i in range(len(goal.times) - 1):
        m = k == i
        if not m.any():
            continue
        a, b = rel[i], rel[i + 1]
        tk = goal.times[i:i + 2]
        if d_xy[i] > TRANSLATION_ATOL_M:
            sign = 1.0 if math.cos(math.atan2(b[1] - a[1], b[0] - a[0]) - a[2]) >= 0 else -1.0
            s = hermite(tk, np.array([0.0, sign * d_xy[i]]), goal.base_twist[i:i + 2, 0], ts[m])
            out[m] = np.stack([a[0] + s * math.cos(a[2]), a[1] + s * math.sin(a[2]), np.full(m.sum(), a[2])], 1)
        else:
            th = hermite(tk, np.array([a[2], b[2]]), goal.base_twist[i:i + 2, 1], ts[m])
            out[m] = np.stack([np.full(m.sum(), a[0]), np.full(m.sum(), a[1]), th], 1)
    return compose(np.asarray(start_base, float), out), J


def goal_messages(goal: TrajectoryModeGoal) -> tuple:
    """(``trajectory_msgs/JointTrajectory``, ``trajectory_msgs/MultiDOFJointTrajectory``) of the goal, both stamped
    0 (the driver's rule)."""
    from geometry_msgs.msg import Transform, Twist
    from trajectory_msgs.msg import (JointTrajectory, JointTrajectoryPoint, MultiDOFJointTrajectory,
                                     MultiDOFJointTrajectoryPoint)

    jt = JointTrajectory()
    jt.joint_names = list(goal.joint_names)
    mt = MultiDOFJointTrajectory()
    mt.joint_names = [BASE_JOINT]
    for k, tk in enumerate(goal.times):
        p = JointTrajectoryPoint()
        p.positions = [float(x) for x in goal.positions[k]]
        p.velocities = [float(x) for x in goal.velocities[k]]
        p.time_from_start = duration_msg(float(tk))
        jt.points.append(p)
        mp = MultiDOFJointTrajectoryPoint()
        tf = Transform()
        tf.translation.x, tf.translation.y = float(goal.base[k, 0]), float(goal.base[k, 1])
        qx, qy, qz, qw = yaw_quat(float(goal.base[k, 2]))
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = float(qx), float(qy), float(qz), float(qw)
        tw = Twist()
        tw.linear.x, tw.angular.z = float(goal.base_twist[k, 0]), float(goal.base_twist[k, 1])
        mp.transforms = [tf]
        mp.velocities = [tw]
        mp.time_from_start = duration_msg(float(tk))
        mt.points.append(mp)
    return jt, mt


def hold_goal(joint_names: Sequence[str], positions: np.ndarray, hold_s: float = 1.0) -> TrajectoryModeGoal:
    """A trajectory-mode goal that keeps every joint and the base where they are for ``hold_s`` (two waypoints, the
    driver's minimum): sent as a stop, it replaces the goal under way."""
    hold_s = max(float(hold_s), DRIVER_MIN_INTERVAL_S + 0.1)
    q = np.asarray(positions, float).reshape(-1)
    return TrajectoryModeGoal(list(joint_names), np.array([0.0, hold_s]), np.stack([q, q]), np.zeros((2, len(q))),
                              np.zeros((2, 3)), np.zeros((2, 2)), np.array([0.0, hold_s]))


def planned_positions(times, positions, ts) -> np.ndarray:
    """The planned trajectory (linear between its points) at times ``ts``."""
    t = np.asarray(times, float)
    P = np.asarray(positions, float)
    return np.stack([np.interp(ts, t, P[:, j]) for j in range(P.shape[1])], 1)


def controller_columns(planning_names: Sequence[str], joints: Sequence[str]) -> list:
    return [list(planning_names).index(j) for j in joints]


def goal_for_controller(ctrl, planning_names: Sequence[str], times, positions, velocities=None,
                        min_interval_s: float = 0.9) -> TrajectoryModeGoal:
    """The goal of ``ctrl``'s joints (its robot names) plus the base, from a planned trajectory over
    ``planning_names`` (``times`` from 0)."""
    t = np.asarray(times, float)
    P = np.asarray(positions, float)
    V = None if velocities is None else np.asarray(velocities, float)
    cols = [0, 1, 2] + controller_columns(planning_names, ctrl.joints)
    return trajectory_mode_goal(ctrl.robot_joints, t, P[:, cols], None if V is None else V[:, cols], min_interval_s)


def planned_on_goal_clock(goal: TrajectoryModeGoal, times, positions, step_s: float = 0.05) -> tuple:
    """(ts, positions (M, dof)): the planned trajectory sampled every ``step_s`` on the goal's (stretched) clock."""
    ts = np.arange(0.0, goal.duration + 1e-9, step_s)
    return ts, planned_positions(times, positions, goal.planned_time(ts))


def deviation_check(robot, goal: TrajectoryModeGoal, planning_names: Sequence[str], ctrl_joints: Sequence[str],
                    times, positions, start_base: np.ndarray, step_s: float = 0.05, window_s: float = 2.0,
                    checked=None) -> float:
    """The largest distance (m) any point of the robot's collision boxes lies, along what the driver executes from
    ``goal`` (base starting at ``start_base``, sampled every ``step_s``), from every planned configuration within
    ``window_s`` of the same instant (``checked``: a :class:`psprm_core.tracking.CheckedPath` of the planned
    trajectory on the goal's clock, built here when not given)."""
    ts, planned = planned_on_goal_clock(goal, times, positions, step_s)
    if checked is None:
        checked = CheckedPath(robot, ts, planned)
    B, J = executed(goal, start_base, ts)
    X = planned.copy()
    X[:, :3] = B
    X[:, controller_columns(planning_names, ctrl_joints)] = J
    return float(checked.deviations(X, ts, window_s).max())


def checked_goal(robot, ctrl, planning_names: Sequence[str], times, positions, velocities, measured: np.ndarray,
                 base, window_s: float) -> tuple:
    """The trajectory-mode goal of a planned trajectory (``times`` from 0) and its check: (goal, ts, planned, checked,
    why). Its first waypoint is where the joints are (``measured``: the driver starts a joint only from where it
    is); ``ts`` / ``planned`` the planned trajectory on the goal's clock and ``checked`` its
    :class:`~psprm_core.tracking.CheckedPath` (for the path tolerance). ``why`` is the refusal: a goal the driver
    cannot take, or waypoints that would take the robot more than ``base.max_goal_deviation_m`` (an adapter
    :class:`~psprm_ros.robots.adapters.BaseConfig`) from the planned trajectory; "" when it may be sent."""
    t, P = np.asarray(times, float), np.asarray(positions, float)
    try:
        goal = goal_for_controller(ctrl, planning_names, t, P, velocities, base.min_waypoint_interval_s)
    except InputError as exc:
        return None, None, None, None, str(exc)
    goal.positions[0] = np.asarray(measured, float)[controller_columns(planning_names, ctrl.joints)]
    # one CheckedPath of the planned trajectory on the goal's clock: for the goal's check and the path tolerance
    ts, Pg = planned_on_goal_clock(goal, t, P)
    checked = CheckedPath(robot, ts, Pg)
    dev = deviation_check(robot, goal, planning_names, ctrl.joints, t, P, P[0, :3], step_s=0.1, window_s=window_s,
                          checked=checked)
    if dev > base.max_goal_deviation_m:
        return goal, ts, Pg, checked, (f"the driver's waypoints would take the robot {dev:.3f} m from the planned "
                                       f"trajectory (max_goal_deviation_m {base.max_goal_deviation_m:g})")
    return goal, ts, Pg, checked, ""
