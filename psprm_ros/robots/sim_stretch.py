"""The rules of Stretch 2's ROS 2 driver (stretch_ros2 ``stretch_core``: ``stretch_driver.py``,
``joint_trajectory_server.py``, and Stretch Body's ``trajectories.py`` / ``base.py`` under it), over ``sim_robot``'s
kinematic model, so that an adapter is tested against what the real driver accepts and does.

Modes (``/mode``, std_msgs/String; switched by the std_srvs/Trigger services ``/switch_to_{navigation, position,
trajectory}_mode``; the driver starts in ``position``):

* ``navigation``: ``cmd_vel`` (geometry_msgs/Twist) drives the base (zero after 0.5 s without one); a
  FollowJointTrajectory goal is accepted and then aborted ("only accepts goals in position or trajectory mode").
* ``position``: ``cmd_vel`` is dropped (logged as an error by the driver); a goal's points are reached one after the
  other at the joints' own speed, ``time_from_start`` ignored; the base only by ``translate_mobile_base`` or
  ``rotate_mobile_base`` increments.
* ``trajectory``: ``cmd_vel`` is dropped; a goal must carry ``header.stamp`` 0 (else aborted), its joint waypoints
  and the base's multi-DOF joint ``position`` (relative to the base's pose at the start, first waypoint the
  identity) at least 0.8 s apart, starting at time 0 at the joints' present positions, each base segment a pure
  rotation or a translation along the heading (one that does both moves by nothing, as ``get_pose_diff`` makes it).
  Waypoints with velocities give cubic segments. A cancel is accepted but does not halt the motion.
* ``runstopped`` (``/runstop`` std_srvs/SetBool, ``/is_runstopped`` std_msgs/Bool): everything halts, goals are
  aborted with INVALID_GOAL, cmd_vel dropped; releasing returns to the mode before.

Goals: a new goal within 0.2 s of the last accepted one, while that one is active, is rejected; an accepted goal
preempts the one under way (aborted with an empty result; the motion continues from where it is into the new goal).
``/stop_the_robot`` (Trigger) halts every joint and the base at once.

The base in trajectory mode is integrated from its wheels' motion (the segment's driving distance or turn, cubic in
time), not set from poses: what the robot does follows from the waypoints as the driver reads them.

No ROS import here: the ROS side is in :mod:`psprm_ros.sim_robot`.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

MODES = ("navigation", "position", "trajectory")
GOAL_WINDOW_S = 0.2
WAYPOINT_ATOL = 0.8  # stretch_body.trajectories.WAYPOINT_ISCLOSE_ATOL
TRANSLATION_ATOL = 2e-3  # hello_utils.get_pose_diff
ROTATION_ATOL = 2e-2
DISTANCE_TOL = 0.05  # a joint's first waypoint this close to where it is (m or rad)
BASE_JOINT = "position"
BASE_POSITION_JOINTS = ("translate_mobile_base", "rotate_mobile_base")
# FollowJointTrajectory.Result error codes (control_msgs)
SUCCESSFUL, INVALID_GOAL, INVALID_JOINTS, OLD_HEADER_TIMESTAMP = 0, -1, -2, -3
PATH_TOLERANCE_VIOLATED, GOAL_TOLERANCE_VIOLATED = -4, -5
DRIVER_ERROR = -100


def _hermite(t0, t1, x0, x1, v0, v1, t):
    h = t1 - t0
    s = min(max((t - t0) / h, 0.0), 1.0)
    return ((2 * s ** 3 - 3 * s ** 2 + 1) * x0 + (s ** 3 - 2 * s ** 2 + s) * h * v0
            + (-2 * s ** 3 + 3 * s ** 2) * x1 + (s ** 3 - s ** 2) * h * v1)


def pose_diff(p0, p1) -> tuple:
    """(translation, rotation) from pose p0 to p1 as Stretch Body reads a base segment (``get_pose_diff``): a pure
    rotation, a translation along (or against) the heading, or nothing."""
    x0, y0, th0 = p0
    x1, y1, th1 = p1
    th0, th1 = math.atan2(math.sin(th0), math.cos(th0)), math.atan2(math.sin(th1), math.cos(th1))
    if abs(x1 - x0) <= TRANSLATION_ATOL and abs(y1 - y0) <= TRANSLATION_ATOL:
        return 0.0, th1 - th0
    if abs(th1 - th0) <= ROTATION_ATOL:
        drive = math.atan2(y1 - y0, x1 - x0)
        dist = math.hypot(x1 - x0, y1 - y0)
        if abs(drive - th0) <= ROTATION_ATOL:
            return dist, 0.0
        opp = math.atan2(math.sin(th0 + math.pi), math.cos(th0 + math.pi))
        if abs(drive - opp) <= ROTATION_ATOL:
            return -dist, 0.0
    return 0.0, 0.0


class Goal:
    """An accepted goal: its id, what the driver made of it, its end time and outcome."""

    def __init__(self, gid: int, start: float):
        self.id, self.start = gid, start
        self.duration = 0.0
        self.joints: dict = {}  # planning index -> (times, positions, velocities or None)
        self.base: list = []  # [(t0, t1, translation, rotation, v0, v1)] (v: the segment's own axis)
        self.sequence: list = []  # position mode: [(planning indices, targets)] one point after the other
        self.outcome: Optional[tuple] = None  # (state, error_code, error_string): succeeded / aborted / canceled
        self.cancel_requested = False


class StretchDriver:
    """The driver's rules over a :class:`psprm_ros.robots.sim_model.SimModel` (its robot, joint positions ``q``, base
    velocity and twist input)."""

    def __init__(self, sim, mode: str = "position", wheel_separation_m: float = 0.3153):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got '{mode}'")
        self.sim = sim
        self.mode = mode
        self.prerunstop_mode = mode
        self.wheel_separation_m = wheel_separation_m
        r = sim.robot
        self.index = {}  # robot joint name -> planning index
        for c in sim.adapter.controllers:
            for j in c.joints:
                self.index[c.robot_name(j)] = r.joint_names.index(j)
        self.goal: Optional[Goal] = None
        self.last_accept = -math.inf
        self.next_id = 0
        self.counts = {"goals_accepted": 0, "goals_rejected": 0, "goals_aborted": 0, "cmd_vel_taken": 0,
                       "cmd_vel_dropped": 0, "stops": 0, "cancels_ignored": 0, "preempted": 0}
        self.aborts: list = []  # (error_code, error_string)
        self._base_done = (0.0, 0.0)  # the active base segment's translation and rotation made so far
        self._pos_base_done = 0.0  # position mode: the base increment made so far

    # ------------------------------------------------------------------------------------------------ modes
    def switch_mode(self, mode: str, now: float) -> tuple:
        if mode not in MODES:
            return False, f"unknown mode {mode}"
        if self.mode == "runstopped":
            return False, "runstopped"
        if mode == "trajectory":
            self._halt()  # turn_on_trajectory_mode: robot.stop_trajectory()
        self.mode = mode
        if mode == "navigation":
            self.sim.twist = np.zeros(2)
        return True, f"Now in {mode} mode."

    def set_runstop(self, on: bool, now: float) -> None:
        if on and self.mode != "runstopped":
            self.prerunstop_mode = self.mode
            self.mode = "runstopped"
            self._halt()
            self.sim.v = np.zeros(2)
        elif not on and self.mode == "runstopped":
            self.mode = self.prerunstop_mode

    @property
    def runstopped(self) -> bool:
        return self.mode == "runstopped"

    # ------------------------------------------------------------------------------------------------ inputs
    def cmd_vel(self, v: float, w: float, now: float) -> bool:
        if self.mode != "navigation":
            self.counts["cmd_vel_dropped"] += 1
            return False
        self.sim.set_twist(v, w, now)
        self.counts["cmd_vel_taken"] += 1
        return True

    def goal_request(self, now: float) -> bool:
        """``goal_cb``: a goal within 0.2 s of the last accepted one while that one is active is rejected."""
        if self.goal is not None and self.goal.outcome is None and now - self.last_accept < GOAL_WINDOW_S:
            self.counts["goals_rejected"] += 1
            return False
        self.last_accept = now
        return True

    def stop_the_robot(self, now: float) -> None:
        self.counts["stops"] += 1
        self._halt()
        self.sim.v = np.zeros(2)
        self.sim.twist = np.zeros(2)

    def cancel(self, now: float) -> None:
        g = self.goal
        if g is None or g.outcome is not None:
            return
        if self.mode == "position":
            self._halt()
            g.outcome = ("canceled", SUCCESSFUL, "")
        else:  # trajectory mode: the cancel is accepted, the motion goes on
            g.cancel_requested = True
            self.counts["cancels_ignored"] += 1

    def _halt(self) -> None:
        self.sim.active.clear()
        if self.goal is not None:
            self.goal.joints, self.goal.base, self.goal.sequence = {}, [], []
        self._base_done = (0.0, 0.0)

    # ------------------------------------------------------------------------------------------------ goals
    def execute(self, stamp_sec: float, joint_names, points, base_names, base_points, now: float) -> Goal:
        """An accepted goal: ``points`` [(t, positions, velocities)], ``base_points`` [(t, (x, y, theta),
        (v, w) or None)]. Returns the goal (its ``outcome`` set when refused at once)."""
        self.next_id += 1
        g = Goal(self.next_id, now)
        prev = self.goal
        if prev is not None and prev.outcome is None:
            prev.outcome = ("aborted", SUCCESSFUL, "preempted by a newer goal")
            self.counts["preempted"] += 1
        self.goal = g
        self.counts["goals_accepted"] += 1
        if self.mode not in ("position", "trajectory", "navigation"):
            return self._abort(g, INVALID_GOAL, f"Cannot execute goals while in mode={self.mode}")
        if self.mode == "navigation":
            return self._abort(g, DRIVER_ERROR, "Joint Trajectory Server only accepts goals in position or "
                                                "trajectory mode")
        if self.mode == "position":
            return self._position_goal(g, joint_names, points)
        return self._trajectory_goal(g, stamp_sec, joint_names, points, base_names, base_points)

    def _abort(self, g: Goal, code: int, text: str) -> Goal:
        g.outcome = ("aborted", code, text)
        self.counts["goals_aborted"] += 1
        self.aborts.append((code, text))
        return g

    def _position_goal(self, g: Goal, names, points) -> Goal:
        unknown = [n for n in names if n not in self.index and n not in BASE_POSITION_JOINTS]
        if unknown or not names:
            return self._abort(g, INVALID_JOINTS, f"joint names violated one of command group's requirements: "
                                                  f"{unknown or 'none'}")
        if sum(n in BASE_POSITION_JOINTS for n in names) > 1:
            return self._abort(g, INVALID_JOINTS, "only one of translate_mobile_base / rotate_mobile_base per goal")
        for _, pos, _ in points:
            idx, tgt, base = [], [], None
            for n, x in zip(names, pos):
                if n in BASE_POSITION_JOINTS:
                    base = (n, float(x))
                else:
                    idx.append(self.index[n])
                    tgt.append(float(x))
            g.sequence.append((idx, np.array(tgt), base))
        self.sim.active.clear()
        return g

    def _trajectory_goal(self, g: Goal, stamp_sec: float, names, points, base_names, base_points) -> Goal:
        if stamp_sec != 0.0:
            return self._abort(g, SUCCESSFUL, "Trajectory mode does not currently allow execution of goal with "
                                              "start time in the " + ("future" if stamp_sec > 0 else "past"))
        trajs = [x for x in (points, base_points) if len(x) >= 2]
        if not trajs:
            return self._abort(g, INVALID_JOINTS, "no trajectory in goal contains enough waypoints")
        for n in list(names) + list(base_names):
            if n not in self.index and n != BASE_JOINT:
                return self._abort(g, INVALID_GOAL, repr(n))
        self._halt()  # robot.stop_trajectory() before the new waypoints are loaded
        q = self.sim.q
        joints = {}
        if len(points) >= 2:
            t = np.array([p[0] for p in points], float)
            ok, why = _times_valid(t)
            if not ok:
                return self._abort(g, DRIVER_ERROR, "hardware failed to start trajectory: " + why)
            for k, n in enumerate(names):
                i = self.index[n]
                x = np.array([p[1][k] for p in points], float)
                v = None
                if all(len(p[2]) > k for p in points):
                    v = np.array([p[2][k] for p in points], float)
                if abs(x[0] - q[i]) > DISTANCE_TOL:
                    return self._abort(g, DRIVER_ERROR, f"hardware failed to start trajectory: {n}: first waypoint "
                                                        f"{x[0]:.3f} doesn't match current position {q[i]:.3f}")
                joints[i] = (t, x, v)
        base = []
        if base_names and len(base_points) >= 2:
            t = np.array([p[0] for p in base_points], float)
            ok, why = _times_valid(t)
            P = np.array([p[1] for p in base_points], float)
            if ok and np.any(np.abs(P[0]) > WAYPOINT_ATOL):
                ok, why = False, "first base waypoint must have pose zero"
            for k in range(1, len(P)):
                d = P[k] - P[k - 1]
                if ok and (abs(d[0]) > WAYPOINT_ATOL or abs(d[1]) > WAYPOINT_ATOL) and abs(d[2]) > WAYPOINT_ATOL:
                    ok, why = False, "DiffDriveTrajectory waypoint cannot both translate and rotate"
            if not ok:
                return self._abort(g, DRIVER_ERROR, "hardware failed to start trajectory: base: " + why)
            for k in range(1, len(P)):
                trans, rot = pose_diff(P[k - 1], P[k])
                v0, v1 = base_points[k - 1][2], base_points[k][2]
                axis = 0 if trans != 0.0 else 1
                vv0 = 0.0 if v0 is None else float(v0[axis])
                vv1 = 0.0 if v1 is None else float(v1[axis])
                base.append((t[k - 1], t[k], trans, rot, vv0, vv1))
        g.joints, g.base = joints, base
        g.duration = max([tr[0][-1] for tr in joints.values()] + [b[1] for b in base] + [0.0])
        self._base_done = (0.0, 0.0)
        return g

    # ------------------------------------------------------------------------------------------------ motion
    def step(self, t: float, dt: float) -> None:
        """Advance the goal under way (the caller then runs the model's own step for cmd_vel in navigation
        mode)."""
        g = self.goal
        if g is None or g.outcome is not None and not g.joints and not g.base and not g.sequence:
            return
        tau = t - g.start
        r = self.sim.robot
        q = self.sim.q
        if g.sequence:
            idx, tgt, base = g.sequence[0]
            cur = q[idx]
            vmax = r.velocity[idx]
            q[idx] = np.clip(cur + np.clip(tgt - cur, -vmax * dt, vmax * dt), r.lower[idx], r.upper[idx])
            if base is not None:
                self._position_base(base, dt)
            if np.allclose(q[idx], tgt, atol=1e-4) and base is None:
                g.sequence.pop(0)
            if not g.sequence and g.outcome is None:
                g.outcome = ("succeeded", SUCCESSFUL, "Achieved all target points.")
            return
        for i, (tk, xk, vk) in g.joints.items():
            k = int(np.clip(np.searchsorted(tk, tau, side="right") - 1, 0, len(tk) - 2))
            if vk is None:
                x = float(np.interp(tau, tk, xk))
            else:
                x = _hermite(tk[k], tk[k + 1], xk[k], xk[k + 1], vk[k], vk[k + 1], tau)
            q[i] = min(max(x, r.lower[i]), r.upper[i])
        if g.base:
            self._trajectory_base(g, tau, dt)
        if g.outcome is None and tau >= g.duration:
            g.outcome = ("succeeded", SUCCESSFUL, "traj succeeded!")
        if tau >= g.duration:
            g.joints, g.base = {}, []
            self.sim.v = np.zeros(2)

    def _trajectory_base(self, g: Goal, tau: float, dt: float) -> None:
        """The base integrated from the wheel motion of the segment under way: its driving distance or its turn,
        cubic in time, applied as an increment to the present pose."""
        while g.base and tau >= g.base[0][1]:
            t0, t1, trans, rot, v0, v1 = g.base.pop(0)
            self._advance(trans - self._base_done[0], rot - self._base_done[1])
            self._base_done = (0.0, 0.0)
        if not g.base:
            self.sim.v = np.zeros(2)
            return
        t0, t1, trans, rot, v0, v1 = g.base[0]
        if tau < t0:
            return
        s_tr = _hermite(t0, t1, 0.0, trans, v0, v1, tau) if trans != 0.0 else 0.0
        s_rot = _hermite(t0, t1, 0.0, rot, v0, v1, tau) if rot != 0.0 else 0.0
        d_tr, d_rot = s_tr - self._base_done[0], s_rot - self._base_done[1]
        self._advance(d_tr, d_rot)
        self._base_done = (s_tr, s_rot)
        self.sim.v = np.array([d_tr / dt if dt > 0 else 0.0, d_rot / dt if dt > 0 else 0.0])

    def _advance(self, d_tr: float, d_rot: float) -> None:
        q = self.sim.q
        th = q[2] + 0.5 * d_rot
        q[0] += d_tr * math.cos(th)
        q[1] += d_tr * math.sin(th)
        q[2] += d_rot

    def _position_base(self, base: tuple, dt: float) -> None:
        name, inc = base
        b = self.sim.robot.config.base
        done = self._pos_base_done
        speed = b.linear_velocity if name == "translate_mobile_base" else b.angular_velocity
        step = float(np.clip(inc - done, -speed * dt, speed * dt))
        if name == "translate_mobile_base":
            self._advance(step, 0.0)
        else:
            self._advance(0.0, step)
        done += step
        if abs(inc - done) < 1e-6:
            done = 0.0
            g = self.goal
            g.sequence[0] = (g.sequence[0][0], g.sequence[0][1], None)
        self._pos_base_done = done


def _times_valid(t: np.ndarray) -> tuple:
    if abs(t[0]) > WAYPOINT_ATOL:
        return False, "first waypoint must be planned for time zero"
    for a, b in zip(t[:-1], t[1:]):
        if np.isclose(b, a, atol=WAYPOINT_ATOL):
            return False, "two waypoints cannot be planned for the same time"
        if b < a:
            return False, "time must increase for each subsequent waypoint"
    return True, ""
