"""Joint trajectory messages of the psprm ROS 2 nodes: a planned trajectory sampled for publishing as
``trajectory_msgs/JointTrajectory`` (with the move from the robot's configuration to its first point put first),
trajectories read back, densified as a controller executes them, the stop trajectory, goal candidates as trajectory
points, and the ``builtin_interfaces/Duration`` of a point's ``time_from_start``.

Plain functions on message objects, like :mod:`.conversions` (which re-exports them); bad input raises
:class:`InputError` with a one-line message.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from psprm_core.errors import InputError


def duration_msg(t: float):
    """Seconds -> ``builtin_interfaces/Duration``."""
    from builtin_interfaces.msg import Duration

    sec = int(math.floor(t))
    return Duration(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def duration_to_sec(d) -> float:
    return float(d.sec) + 1e-9 * float(d.nanosec)


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
    return _by_name(msg, names, "positions")


def joint_trajectory_velocities(msg, names: Sequence[str]) -> Optional[np.ndarray]:
    """``JointTrajectory`` -> (M, dof) velocities reordered to ``names``, or None when a point carries none (or not
    one per joint); raises on missing joints / non-finite."""
    if not all(len(p.velocities) == len(msg.joint_names) for p in msg.points):
        return None
    return _by_name(msg, names, "velocities")


def _by_name(msg, names: Sequence[str], field: str) -> np.ndarray:
    idx = []
    for n in names:
        if n not in msg.joint_names:
            raise InputError(f"joint trajectory: missing joint '{n}'")
        idx.append(list(msg.joint_names).index(n))
    rows = [getattr(p, field) for p in msg.points]
    P = np.array([[r[i] for i in idx] if len(r) == len(msg.joint_names) else [np.nan] * len(idx) for r in rows],
                 float).reshape(-1, len(names))
    if not np.isfinite(P).all():
        raise InputError(f"joint trajectory: non-finite or incomplete {field}")
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
