"""Message <-> numpy conversions and input validation for the psprm ROS 2 nodes.

Everything here is plain functions on message objects (no node, no executor), so it is cheap to test. Validation
raises :class:`InputError` with a one-line message; nodes catch it, log a warning and publish it on ``~/status``.

Quaternions are ``[x, y, z, w]`` (ROS and psprm_core agree).
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from psprm_core.errors import InputError  # a message that must not reach the planner (non-finite, wrong frame, ...)

__all__ = ["InputError"]  # the nodes catch cv.InputError: the library's error of bad input, a ValueError


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


def duration_msg(t: float):
    """Seconds -> ``builtin_interfaces/Duration``."""
    from builtin_interfaces.msg import Duration

    sec = int(math.floor(t))
    return Duration(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def duration_to_sec(d) -> float:
    return float(d.sec) + 1e-9 * float(d.nanosec)


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
    from psprm_core.geometry import matrix_to_quat

    return numpy_to_pose(T[:3, 3], matrix_to_quat(T[:3, :3]), pose)


def pose_to_matrix(pose) -> np.ndarray:
    from psprm_core.geometry import quat_to_matrix

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
    from psprm_core.geometry import matrix_to_quat

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


def configs_to_joint_trajectory(Q: np.ndarray, names: Sequence[str], frame: str = "", stamp=None):
    """(G, dof) configurations -> ``trajectory_msgs/JointTrajectory`` whose points are the configurations (used for
    goal candidates, time_from_start = index)."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.joint_names = list(names)
    for i, q in enumerate(np.asarray(Q, float).reshape(-1, len(names))):
        p = JointTrajectoryPoint()
        p.positions = [float(v) for v in q]
        p.time_from_start = duration_msg(float(i))
        m.points.append(p)
    return m


def joint_trajectory_positions(msg, names: Sequence[str]) -> np.ndarray:
    """``JointTrajectory`` -> (M, dof) positions reordered to ``names``; raises on missing joints / non-finite."""
    idx = []
    for n in names:
        if n not in msg.joint_names:
            raise InputError(f"joint trajectory: missing joint '{n}'")
        idx.append(list(msg.joint_names).index(n))
    P = np.array([[p.positions[i] for i in idx] if len(p.positions) == len(msg.joint_names) else [np.nan] * len(idx)
                  for p in msg.points], float).reshape(-1, len(names))
    if not np.isfinite(P).all():
        raise InputError("joint trajectory: non-finite or incomplete positions")
    return P


def trajectory_samples(traj, dt: float = 0.1) -> tuple:
    """Samples of a :class:`psprm_core.planning.timing.Trajectory` to publish: about every ``dt`` seconds plus every
    waypoint (corner) sample and the end, so that linear interpolation between the published points follows the
    planned piecewise-linear path exactly. Returns (times, positions, velocities, accelerations)."""
    t = np.asarray(traj.times, float)
    m = len(t)
    if m == 0:
        raise InputError("empty trajectory")
    if dt > 0 and m > 1:
        step = max(1, int(round(dt / max(float(np.median(np.diff(t))), 1e-9))))
        idx = np.arange(0, m, step)
    else:
        idx = np.arange(m)
    wi = np.asarray(getattr(traj, "waypoint_indices", []), dtype=np.int64)
    idx = np.unique(np.concatenate([idx, wi[(wi >= 0) & (wi < m)], [m - 1]]))
    acc = traj.accelerations if traj.accelerations is not None else np.zeros_like(traj.positions)
    return t[idx], np.asarray(traj.positions)[idx], np.asarray(traj.velocities)[idx], np.asarray(acc)[idx]


def _f64(row: np.ndarray):
    import array

    return array.array("d", np.ascontiguousarray(row, dtype=np.float64).tobytes())


def published_samples(traj, dt: float = 0.1) -> tuple:
    """The samples of ``traj`` as the server publishes them: :func:`trajectory_samples` copied to float64 arrays,
    the last point at rest (zero velocity and acceleration). Returns (times, positions, velocities,
    accelerations)."""
    t, pos, vel, acc = trajectory_samples(traj, dt)
    t, pos = np.array(t, float), np.array(pos, float)
    vel, acc = np.array(vel, float), np.array(acc, float)
    vel[-1] = 0.0
    acc[-1] = 0.0
    return t, pos, vel, acc


def joint_trajectory_msg(times, positions, velocities, accelerations, names: Sequence[str], frame: str,
                         stamp=None):
    """Sample arrays (M,), (M, dof) x 3 -> ``trajectory_msgs/JointTrajectory``, one point per sample, unchanged."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.joint_names = list(names)
    pts = []
    for k in range(len(times)):
        p = JointTrajectoryPoint()
        p.positions, p.velocities = _f64(positions[k]), _f64(velocities[k])
        p.accelerations = _f64(accelerations[k])
        p.time_from_start = duration_msg(float(times[k]))
        pts.append(p)
    m.points = pts
    return m


def trajectory_to_msg(traj, names: Sequence[str], frame: str, stamp=None, dt: float = 0.1,
                      with_positions: bool = False):
    """A :class:`psprm_core.planning.timing.Trajectory` -> ``trajectory_msgs/JointTrajectory`` (the samples of
    :func:`published_samples`). ``with_positions``: (msg, the points' positions (M, dof)) without reading them back
    from the message."""
    t, pos, vel, acc = published_samples(traj, dt)
    m = joint_trajectory_msg(t, pos, vel, acc, names, frame, stamp)
    return (m, pos) if with_positions else m


def start_move(first: np.ndarray, q: np.ndarray, velocity_limits: np.ndarray, acceleration_limits: np.ndarray,
               continuous: Optional[Sequence[int]] = None, tol: float = 1e-3) -> Optional[tuple]:
    """The move from ``q`` to a trajectory's ``first`` configuration: None when they agree within ``tol`` (largest
    joint difference; ``continuous`` joints compared modulo 2 pi), else (duration, start) with the duration of a
    rest-to-rest move within the limits (the slowest joint's trapezoid, at least 0.05 s) and ``start`` = ``q`` with
    the continuous joints on ``first``'s branch."""
    first = np.asarray(first, float)
    d = first - np.asarray(q, float)
    for j in continuous or ():
        d[j] = (d[j] + math.pi) % (2.0 * math.pi) - math.pi
    if np.abs(d).max() <= tol:
        return None
    v = np.asarray(velocity_limits, float)
    a = np.asarray(acceleration_limits, float)
    ad = np.abs(d)
    # rest to rest: triangular when the distance is short, trapezoidal otherwise
    t = np.where(ad < v * v / a, 2.0 * np.sqrt(ad / a), ad / v + v / a)
    return float(max(t.max(), 0.05)), first - d


def prepend_start_samples(times, positions, velocities, accelerations, q: np.ndarray, velocity_limits: np.ndarray,
                          acceleration_limits: np.ndarray, continuous: Optional[Sequence[int]] = None,
                          tol: float = 1e-3) -> tuple:
    """Sample arrays that start exactly at ``q``: when the first sample differs (the planner re-aims the camera
    joints at the start), a sample at ``q`` at rest is put first, at time 0, and every other sample is shifted by
    the :func:`start_move` time. Returns (times, positions, velocities, accelerations, shift); shift 0 and the
    arrays unchanged when nothing was added. The added segment is part of what is published, so the final
    collision check covers it."""
    times, positions = np.asarray(times, float), np.asarray(positions, float)
    velocities, accelerations = np.asarray(velocities, float), np.asarray(accelerations, float)
    move = start_move(positions[0], q, velocity_limits, acceleration_limits, continuous, tol) if len(times) else None
    if move is None:
        return times, positions, velocities, accelerations, 0.0
    shift, start = move
    zero = np.zeros((1, positions.shape[1]))
    return (np.r_[0.0, times + shift], np.vstack([start[None], positions]), np.vstack([zero, velocities]),
            np.vstack([zero, accelerations]), shift)


def prepend_start(msg, q: np.ndarray, velocity_limits: np.ndarray, acceleration_limits: np.ndarray,
                  continuous: Optional[Sequence[int]] = None, tol: float = 1e-3) -> float:
    """:func:`prepend_start_samples` on a message: make ``msg`` (a JointTrajectory of all planning joints, in
    ``q``'s order) start exactly at ``q`` (a point at ``q`` first, at time 0, every other point shifted by the
    :func:`start_move` time). Returns that shift (0 when nothing was added)."""
    from trajectory_msgs.msg import JointTrajectoryPoint

    if not msg.points:
        return 0.0
    move = start_move(np.asarray(msg.points[0].positions, float), q, velocity_limits, acceleration_limits,
                      continuous, tol)
    if move is None:
        return 0.0
    shift, start = move
    for p in msg.points:
        p.time_from_start = duration_msg(duration_to_sec(p.time_from_start) + shift)
    p0 = JointTrajectoryPoint()
    p0.positions = _f64(start)
    p0.velocities = _f64(np.zeros(len(start)))
    p0.accelerations = _f64(np.zeros(len(start)))
    p0.time_from_start = duration_msg(0.0)
    msg.points = [p0] + list(msg.points)
    return shift


def densify_linear(P: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Configurations at most ``step`` apart (largest joint change, metres or radians) along the polyline through
    ``P`` (M, dof): what a controller interpolating linearly between the points executes. Vectorised numpy."""
    P = np.asarray(P, float)
    if len(P) < 2:
        return P
    d = np.abs(np.diff(P, axis=0))
    n = np.maximum(1, np.ceil(d.max(1) / step)).astype(np.int64)
    seg = np.repeat(np.arange(len(d)), n)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)
    f = (k / n[seg])[:, None]
    out = P[seg] + (P[seg + 1] - P[seg]) * f
    return np.vstack([out, P[-1:]])


def stop_trajectory(q: np.ndarray, names: Sequence[str], frame: str, stamp=None, hold_s: float = 0.25):
    """A one-point trajectory that holds ``q`` with zero velocity (what the server publishes when nothing safe
    exists). ``time_from_start`` is ``hold_s`` (> 0) and the stamp 0 ("start now", unless ``stamp`` is given): a
    joint_trajectory_controller drops a trajectory whose stamp + last time_from_start lies in the past, which a
    point at time 0 stamped now always does by the time it arrives."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    if not hold_s > 0:
        raise InputError(f"hold_s must be > 0, got {hold_s}")
    m = JointTrajectory()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.joint_names = list(names)
    p = JointTrajectoryPoint()
    p.positions = [float(v) for v in q]
    p.velocities = [0.0] * len(names)
    p.accelerations = [0.0] * len(names)
    p.time_from_start = duration_msg(float(hold_s))
    m.points = [p]
    return m


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
