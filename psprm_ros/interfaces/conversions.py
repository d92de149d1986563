"""Message <-> numpy conversions and input validation for the psprm ROS 2 nodes.

Everything here is plain functions on message objects (no node, no executor), so it is cheap to test. Validation
raises :class:`InputError` with a one-line message; nodes catch it, log a warning and publish it on ``~/status``.

Quaternions are ``[x, y, z, w]`` (ROS and psprm_core agree).

Here: time stamps, poses and pose arrays, joint states and the base's velocity, the base route and score arrays. The
joint trajectory messages (and durations) are in :mod:`.trajectories`, re-exported here: the nodes reach every
conversion as ``cv.<name>``.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from psprm_core.errors import InputError  # a message that must not reach the planner (non-finite, wrong frame, ...)
from psprm_core.geometry import matrix_to_quat, quat_to_matrix

from .trajectories import (configs_to_joint_trajectory, densify_linear, duration_msg, duration_to_sec,
                           joint_trajectory_msg, joint_trajectory_positions, joint_trajectory_velocities,
                           prepend_start, prepend_start_samples, published_samples, start_move, stop_trajectory,
                           trajectory_samples, trajectory_to_msg)

#: re-exported: InputError (the nodes catch cv.InputError: the library's error of bad input, a ValueError) and the
#: joint trajectory messages of :mod:`.trajectories`
__all__ = ["InputError", "configs_to_joint_trajectory", "densify_linear", "duration_msg", "duration_to_sec",
           "joint_trajectory_msg", "joint_trajectory_positions", "joint_trajectory_velocities", "prepend_start",
           "prepend_start_samples", "published_samples", "start_move", "stop_trajectory", "trajectory_samples",
           "trajectory_to_msg"]


# ---------------------------------------------------------------------------------------------------------- time
def stamp_to_sec(stamp) -> float:
    """``builtin_interfaces/Time`` -> seconds (float)."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def sec_to_stamp(t: float, stamp=None):
    """Seconds -> ``builtin_interfaces/Time`` (filled into ``stamp`` when given)."""
    from builtin_interfaces.msg import Time

    stamp = stamp if stamp is not None else Time()
    sec = int(math.floor(t))
    stamp.sec = sec
    stamp.nanosec = int(round((t - sec) * 1e9)) % 1_000_000_000
    return stamp


# ---------------------------------------------------------------------------------------------------------- poses
def pose_to_numpy(pose) -> tuple:
    """``geometry_msgs/Pose`` -> (position (3,), quaternion (4,) xyzw), unvalidated."""
    p, o = pose.position, pose.orientation
    return np.array([p.x, p.y, p.z], float), np.array([o.x, o.y, o.z, o.w], float)


def numpy_to_pose(position, quat_xyzw=(0.0, 0.0, 0.0, 1.0), pose=None):
    """(position, quaternion xyzw) -> ``geometry_msgs/Pose``."""
    from geometry_msgs.msg import Pose

    pose = pose if pose is not None else Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in quat_xyzw)
    return pose


def matrix_to_pose(T: np.ndarray, pose=None):
    """4x4 homogeneous transform -> ``geometry_msgs/Pose``."""
    return numpy_to_pose(T[:3, 3], matrix_to_quat(T[:3, :3]), pose)


def pose_to_matrix(pose) -> np.ndarray:
    p, q = pose_to_numpy(pose)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = p
    return T


def yaw_of(quat_xyzw) -> float:
    """Heading (rotation about z) of a quaternion xyzw."""
    x, y, z, w = quat_xyzw
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quat(yaw: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # a non-finite yaw gives a non-finite quaternion (refused by validation)
        return np.array([0.0, 0.0, np.sin(yaw / 2.0), np.cos(yaw / 2.0)])


def check_frame(frame_id: str, expected: str, what: str = "pose") -> None:
    """Raise unless ``frame_id`` names the scene's frame (a leading '/' is ignored; empty is refused)."""
    got = (frame_id or "").lstrip("/")
    if got != expected.lstrip("/"):
        raise InputError(f"{what}: frame '{frame_id}' is not the scene frame '{expected}'")


def check_stamp(stamp_sec: float, now_sec: float, max_age_s: float, what: str = "pose") -> None:
    """Raise when a stamped message is older than ``max_age_s`` (<= 0 disables the check; a zero stamp is allowed:
    many drivers leave it empty)."""
    if max_age_s <= 0 or stamp_sec == 0.0:
        return
    age = now_sec - stamp_sec
    if age > max_age_s:
        raise InputError(f"{what}: stale by {age:.2f} s (max {max_age_s:.2f} s)")


def validated_pose(msg, frame: str, now_sec: Optional[float] = None, max_age_s: float = 0.0,
                   what: str = "pose") -> tuple:
    """``geometry_msgs/PoseStamped`` -> (position (3,), unit quaternion (4,)) after checking it.

    Refuses non-finite values, a zero quaternion, a frame other than ``frame`` and (with ``now_sec``) stamps older
    than ``max_age_s``. Returns the normalised quaternion.
    """
    check_frame(msg.header.frame_id, frame, what)
    p, q = pose_to_numpy(msg.pose)
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise InputError(f"{what}: non-finite values (position {p.tolist()}, orientation {q.tolist()})")
    n = float(np.linalg.norm(q))
    if n < 1e-6:
        raise InputError(f"{what}: zero quaternion")
    if now_sec is not None:
        check_stamp(stamp_to_sec(msg.header.stamp), now_sec, max_age_s, what)
    return p, q / n


def pose_stamped(position, quat_xyzw, frame: str, stamp=None):
    from geometry_msgs.msg import PoseStamped

    m = PoseStamped()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    numpy_to_pose(position, quat_xyzw, m.pose)
    return m


def pose_array(matrices: np.ndarray, frame: str, stamp=None):
    """(N, 4, 4) transforms -> ``geometry_msgs/PoseArray`` (vectorised quaternion extraction)."""
    from geometry_msgs.msg import Pose, PoseArray

    T = np.asarray(matrices, float).reshape(-1, 4, 4)
    quats = matrices_to_quats(T[:, :3, :3])
    m = PoseArray()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    poses = []
    for t, q in zip(T[:, :3, 3].tolist(), quats.tolist()):
        p = Pose()
        p.position.x, p.position.y, p.position.z = t
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
        poses.append(p)
    m.poses = poses
    return m


def pose_array_to_matrices(msg) -> np.ndarray:
    """``geometry_msgs/PoseArray`` -> (N, 4, 4); raises on non-finite values."""
    n = len(msg.poses)
    P = np.empty((n, 3))
    Q = np.empty((n, 4))
    for i, p in enumerate(msg.poses):
        P[i] = (p.position.x, p.position.y, p.position.z)
        Q[i] = (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise InputError("pose array: non-finite values")
    return compose(P, Q)


def matrices_to_quats(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N, 4) quaternions xyzw."""
    return np.array([matrix_to_quat(r) for r in R]).reshape(-1, 4)


def compose(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Positions (N, 3) and quaternions (N, 4) xyzw -> (N, 4, 4)."""
    Q = Q / np.clip(np.linalg.norm(Q, axis=1, keepdims=True), 1e-12, None)
    x, y, z, w = Q.T
    T = np.zeros((len(P), 4, 4))
    T[:, 0, 0] = 1 - 2 * (y * y + z * z)
    T[:, 0, 1] = 2 * (x * y - z * w)
    T[:, 0, 2] = 2 * (x * z + y * w)
    T[:, 1, 0] = 2 * (x * y + z * w)
    T[:, 1, 1] = 1 - 2 * (x * x + z * z)
    T[:, 1, 2] = 2 * (y * z - x * w)
    T[:, 2, 0] = 2 * (x * z - y * w)
    T[:, 2, 1] = 2 * (y * z + x * w)
    T[:, 2, 2] = 1 - 2 * (x * x + y * y)
    T[:, :3, 3] = P
    T[:, 3, 3] = 1.0
    return T


# ---------------------------------------------------------------------------------------------------------- joints
def joint_state_to_planning(msg, robot, base: Optional[np.ndarray] = None, template: Optional[np.ndarray] = None
                            ) -> tuple:
    """``sensor_msgs/JointState`` -> (planning configuration (dof,), names found).

    Accepts planning joint names (``base_x``, ``arm_extension``, ...) as well as the URDF joints they drive (Stretch's
    four ``joint_arm_l*`` -> ``arm_extension``, least squares over the driven joints). The base comes from ``base``
    ((x, y, theta), e.g. a mocap pose) unless the message carries ``base_x/base_y/base_theta``. Joints missing from
    the message keep their ``template`` value (default configuration when None). Non-finite values raise.
    """
    if len(msg.position) != len(msg.name):
        raise InputError(f"joint state: {len(msg.name)} names but {len(msg.position)} positions")
    vals = dict(zip(msg.name, (float(v) for v in msg.position)))
    bad = [k for k, v in vals.items() if not math.isfinite(v)]
    if bad:
        raise InputError(f"joint state: non-finite values for {', '.join(bad)}")
    q = np.array(template if template is not None else robot.default_configuration(), float).copy()
    found = []
    if base is not None and robot.mobile:
        q[:3] = base
    drives = {}  # planning index -> [(urdf value, coeff)]
    for name, items in robot.urdf_drives.items():
        if name in vals:
            for i, c in items:
                drives.setdefault(int(i), []).append((vals[name], float(c)))
    for i, jn in enumerate(robot.joint_names):
        if jn in vals:
            q[i] = vals[jn]
            found.append(jn)
        elif i in drives:
            v = np.array(drives[i])
            q[i] = float((v[:, 0] * v[:, 1]).sum() / max((v[:, 1] ** 2).sum(), 1e-12))
            found.append(jn)
    return q, found


def planning_joint_state(q: np.ndarray, names: Sequence[str], stamp=None, frame: str = "",
                         velocity: Optional[np.ndarray] = None):
    """Planning configuration -> ``sensor_msgs/JointState`` with planning joint names; ``velocity`` (dof,), NaN
    where a joint's velocity is not measured, fills the message's velocities (left empty when None)."""
    from sensor_msgs.msg import JointState

    m = JointState()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.name = list(names)
    m.position = [float(v) for v in q]
    if velocity is not None:
        m.velocity = [float(v) for v in velocity]
    return m


def base_world_rates(q: np.ndarray, base_velocity, dof: int) -> np.ndarray:
    """(dof,) joint velocities of a mobile base moving at ``base_velocity`` (v along its heading, omega) at ``q``:
    ``base_x``, ``base_y``, ``base_theta`` as scene-frame rates, NaN for every other joint (not measured here)."""
    v, w = (float(x) for x in base_velocity)
    out = np.full(dof, np.nan)
    out[:3] = (v * math.cos(float(q[2])), v * math.sin(float(q[2])), w)
    return out


def base_velocity_of(msg, theta: float) -> Optional[np.ndarray]:
    """(v, omega) of the base from a planning ``sensor_msgs/JointState`` whose velocities carry finite
    ``base_x``, ``base_y``, ``base_theta`` rates (:func:`base_world_rates`), at heading ``theta``; None when the
    message has no such velocities."""
    if len(msg.velocity) != len(msg.name):
        return None
    vel = dict(zip(msg.name, msg.velocity))
    try:
        dx, dy, dth = (float(vel[n]) for n in ("base_x", "base_y", "base_theta"))
    except KeyError:
        return None
    if not all(math.isfinite(x) for x in (dx, dy, dth)):
        return None
    return np.array([dx * math.cos(theta) + dy * math.sin(theta), dth])


def base_path_msg(P: np.ndarray, frame: str, stamp=None):
    """Planning-joint positions (M, dof; base_x, base_y, base_theta first) -> ``nav_msgs/Path`` of the base route."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    m = Path()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    poses = []
    for x, y, th in np.asarray(P, float).reshape(-1, np.shape(P)[-1] if np.ndim(P) == 2 else 3)[:, :3]:
        ps = PoseStamped()
        ps.header = m.header
        numpy_to_pose([x, y, 0.0], yaw_quat(th), ps.pose)
        poses.append(ps)
    m.poses = poses
    return m


def float_array(values) -> object:
    """1-D values -> ``std_msgs/Float32MultiArray`` (one dimension labelled ``scores``)."""
    from std_msgs.msg import Float32MultiArray, MultiArrayDimension

    v = np.asarray(values, np.float32).reshape(-1)
    m = Float32MultiArray()
    m.layout.dim = [MultiArrayDimension(label="scores", size=int(v.size), stride=int(v.size))]
    m.data = v.tolist()
    return m
