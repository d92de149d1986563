"""The robot's measured state: joints from ``sensor_msgs/JointState`` and the base pose from ``nav_msgs/Odometry``,
a motion-capture rigid body (``geometry_msgs/PoseStamped``) or tf (``tf2_msgs/TFMessage`` of ``/tf`` and
``/tf_static``: the pose of ``base_frame`` in the scene frame, e.g. ``map -> odom -> base_link``), combined into a
planning configuration.

The joint names a robot publishes may differ from the planning names (Stretch: ``wrist_extension`` for the planning
joint ``arm_extension``); the adapter config's name maps give the inverse mapping used here. A mocap body is not the
robot's ``base_link``: ``body_offset`` is the pose of base_link in the body's frame. Poses in another frame than the
scene's go through a :class:`~psprm_ros.interfaces.frames.FrameTable`.

:meth:`RobotStateTracker.state` gives the configuration only when the base pose (for a mobile robot) and the joints
are fresh; otherwise ``None`` and the reason ("waiting for base pose", "base pose stale ..."), which the nodes report.
No ROS import here: the update methods take message objects and read their fields.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from psprm_core.errors import InputError
from psprm_core.geometry import wrap_angle

from ..interfaces import conversions as cv
from ..interfaces.frames import FrameTable, compose_pose
from ..interfaces.tf_tree import TfTree

BASE_SOURCES = ("odom", "pose", "joint_states", "tf")
#: the same discarded tf link is reported at most once per this many seconds (a 50 Hz /tf does not flood the log)
TF_REPORT_PERIOD_S = 5.0

WAITING_FOR_BASE = "waiting for base pose"
WAITING_FOR_JOINTS = "waiting for joint states"


class RobotStateTracker:
    """Latest measured joints and base pose (receipt times from the caller's monotonic clock).

    Parameters
    ----------
    robot : RobotModel
    frames : FrameTable
    base_source : ``odom`` (nav_msgs/Odometry), ``pose`` (a mocap PoseStamped of a body on the base),
        ``joint_states`` (the base as planning joints ``base_x, base_y, base_theta`` in /joint_states) or ``tf``
        (the pose of ``base_frame`` in the scene frame from /tf and /tf_static,
        :class:`~psprm_ros.interfaces.tf_tree.TfTree`; stale when the newest dynamic link of the chain is older than
        ``timeout_s``; the base velocity is the difference of the lowest dynamic link's successive transforms, e.g. odom
        -> base_link)
    name_map : robot joint name -> planning joint name (from the adapter config; planning and URDF names need none)
    body_offset : (xyz, quat) pose of base_link in the mocap body's frame (``pose`` source)
    timeout_s : a base pose or joint state older than this (receipt time) is stale
    base_frame : the robot's base frame in tf (``tf`` source)
    tf : the tree to use (``tf`` source; a node that receives /tf_static before it builds the tracker passes the
        tree it filled); by default one of its own
    """

    def __init__(self, robot, frames: FrameTable, base_source: str = "odom", name_map: Optional[dict] = None,
                 body_offset: Optional[tuple] = None, timeout_s: float = 0.5, template: Optional[np.ndarray] = None,
                 base_frame: str = "base_link", tf: Optional[TfTree] = None):
        if base_source not in BASE_SOURCES:
            raise InputError(f"base_pose_source must be one of {', '.join(BASE_SOURCES)}, got '{base_source}'")
        self.robot, self.frames, self.base_source = robot, frames, base_source
        self.name_map = dict(name_map or {})
        self.body_offset = body_offset
        self.timeout_s = float(timeout_s)
        self.q = np.array(template if template is not None else robot.default_configuration(), float)
        self.base: Optional[np.ndarray] = None  # (x, y, theta) in the scene frame
        self.base_t: Optional[float] = None
        self.joints_t: Optional[float] = None
        self.base_velocity = np.zeros(2)  # (v, omega) from odometry when given
        self.base_velocity_measured = False  # a velocity came from odometry or tf (a mocap pose has none)
        self.base_frame = str(base_frame or "").strip().lstrip("/")
        self.tf: Optional[TfTree] = None
        self.base_problem = ""  # why there is no base pose yet (tf source: the missing link)
        self._base_fixed = False  # tf source: the base pose comes from static links only (never stale)
        self._tf_reported: dict = {}  # (parent, child) -> t of its last reported discard
        self._odo_prev: Optional[tuple] = None  # (stamp, x, y, yaw) of the lowest dynamic link's last transform
        if base_source == "tf":
            if not self.base_frame:
                raise InputError("base_frame: empty frame name (the robot's base frame in tf, e.g. base_link)")
            self.tf = tf if tf is not None else TfTree()

    # ------------------------------------------------------------------------------------------------ updates
    def update_joints(self, msg, t: float) -> list:
        """``sensor_msgs/JointState`` -> planning joints (found names returned); raises InputError on bad input."""
        renamed = _Renamed(msg, self.name_map)
        q, found = cv.joint_state_to_planning(renamed, self.robot, template=self.q)
        if self.robot.mobile and self.base_source != "joint_states":
            q[:3] = self.q[:3]  # the base comes from its own source
            found = [f for f in found if f not in ("base_x", "base_y", "base_theta")]
        elif self.robot.mobile and {"base_x", "base_y", "base_theta"} <= set(found):
            self.base, self.base_t = q[:3].copy(), t
        self.q = q
        if found:
            self.joints_t = t
        return found

    def update_odometry(self, msg, t: float, now_sec: Optional[float] = None, max_age_s: float = 0.0) -> np.ndarray:
        """``nav_msgs/Odometry`` -> base (x, y, theta) in the scene frame (``header.frame_id`` through the frame
        table); raises InputError on a non-finite pose, an unknown frame or a stale stamp."""
        p, q = _checked_pose(msg.pose.pose, msg.header, now_sec, max_age_s, "odometry")
        p, q = self.frames.to_scene(msg.header.frame_id, p, q, "odometry")
        tw = msg.twist.twist
        v = np.array([tw.linear.x, tw.angular.z], float)
        self.base_velocity = v if np.isfinite(v).all() else np.zeros(2)
        self.base_velocity_measured = bool(np.isfinite(v).all())
        return self._set_base(p, q, t)

    def update_pose(self, msg, t: float, now_sec: Optional[float] = None, max_age_s: float = 0.0) -> np.ndarray:
        """A mocap ``geometry_msgs/PoseStamped`` of the body on the base -> base (x, y, theta) in the scene frame
        (the body -> base_link offset applied)."""
        p, q = _checked_pose(msg.pose, msg.header, now_sec, max_age_s, "base pose")
        p, q = self.frames.to_scene(msg.header.frame_id, p, q, "base pose")
        if self.body_offset is not None:
            p, q = compose_pose((p, q), self.body_offset)
        return self._set_base(p, q, t)

    def update_tf(self, msg, static: bool, t: float) -> list:
        """A ``tf2_msgs/TFMessage`` (``static``: from /tf_static) received at ``t`` -> the base pose, when the tree
        connects the scene frame and ``base_frame``. Returns the discarded transforms to report (each link at most
        once per :data:`TF_REPORT_PERIOD_S`); raises nothing for message content."""
        if self.tf is None:
            return []
        dropped = self.tf.update(msg, static, t)
        report = []
        for d in dropped:
            key = (d.parent, d.child)
            if t - self._tf_reported.get(key, -math.inf) >= TF_REPORT_PERIOD_S:
                self._tf_reported[key] = t
                report.append(str(d))
        found, why = self.tf.find(self.frames.scene_frame, self.base_frame)
        if found is None:
            if self.base is None:
                self.base_problem = why
            return report
        self.base_problem = ""
        self._tf_velocity()
        received = found.received
        self._base_fixed = received is None
        self._set_base(found.xyz, found.quat, t if received is None else received)
        return report

    def _tf_velocity(self) -> None:
        """(v, omega) from successive transforms of the lowest dynamic link at or above ``base_frame`` (its stamps
        as the time base): the odometry's own motion, which a correction of map -> odom does not enter."""
        up = self.tf.chain_up(self.base_frame)
        link = next((self.tf.links[f] for f in up[:-1] if not self.tf.links[f].static), None)
        if link is None:
            return
        pose = self.tf.lookup(link.parent, self.base_frame)
        x, y, yaw = float(pose.xyz[0]), float(pose.xyz[1]), cv.yaw_of(pose.quat)
        prev, self._odo_prev = self._odo_prev, (link.stamp, x, y, yaw)
        if prev is None or link.stamp == prev[0]:
            return
        dt = link.stamp - prev[0]
        if not 1e-4 < dt <= 1.0:  # time went back or a gap: no velocity from this pair
            self.base_velocity, self.base_velocity_measured = np.zeros(2), False
            return
        dyaw = wrap_angle(yaw - prev[3])
        mid = prev[3] + 0.5 * dyaw
        v = (math.cos(mid) * (x - prev[1]) + math.sin(mid) * (y - prev[2])) / dt
        vel = np.array([v, dyaw / dt])
        self.base_velocity = vel if np.isfinite(vel).all() else np.zeros(2)
        self.base_velocity_measured = bool(np.isfinite(vel).all())

    def _set_base(self, p: np.ndarray, q: np.ndarray, t: float) -> np.ndarray:
        base = np.array([p[0], p[1], cv.yaw_of(q)])
        if self.base is not None:  # keep theta continuous with the last value (the planner unwraps it)
            base[2] = self.base[2] + wrap_angle(base[2] - self.base[2])
        self.base, self.base_t = base, t
        return base

    # ------------------------------------------------------------------------------------------------ output
    def state(self, t: float) -> tuple:
        """(configuration or None, reason): the configuration when the joints and (mobile robots) the base pose are
        fresh at time ``t``."""
        if self.robot.mobile:
            if self.base_t is None:
                return None, f"{WAITING_FOR_BASE}: {self.base_problem}" if self.base_problem else WAITING_FOR_BASE
            age = t - self.base_t
            if age > self.timeout_s and not (self.base_source == "tf" and self._base_fixed):
                return None, f"{WAITING_FOR_BASE}: the last one is {age:.2f} s old (max {self.timeout_s:.2f} s)"
        if self.joints_t is None:
            return None, WAITING_FOR_JOINTS
        if t - self.joints_t > self.timeout_s:
            return None, f"{WAITING_FOR_JOINTS}: the last one is {t - self.joints_t:.2f} s old"
        q = self.q.copy()
        if self.robot.mobile:
            q[:3] = self.base
        return q, "ok"


class _Renamed:
    """A JointState view with robot names mapped to planning names (the message itself is not changed)."""

    def __init__(self, msg, name_map: dict):
        self.name = [name_map.get(n, n) for n in msg.name]
        self.position = msg.position
        self.header = msg.header


def _checked_pose(pose, header, now_sec, max_age_s, what) -> tuple:
    p, q = cv.pose_to_numpy(pose)
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise cv.InputError(f"{what}: non-finite values (position {p.tolist()}, orientation {q.tolist()})")
    n = float(np.linalg.norm(q))
    if n < 1e-6:
        raise cv.InputError(f"{what}: zero quaternion")
    if now_sec is not None:
        cv.check_stamp(cv.stamp_to_sec(header.stamp), now_sec, max_age_s, what)
    return p, q / n


def offset_from_params(xyz, quat) -> Optional[tuple]:
    """(xyz, quat) parameters -> a pose, or None for the identity."""
    xyz = np.asarray(xyz, float).reshape(3)
    quat = np.asarray(quat, float).reshape(4)
    quat = quat / np.linalg.norm(quat)
    if np.allclose(xyz, 0) and np.allclose(quat, [0, 0, 0, 1]):
        return None
    return xyz, quat
