"""Recorded rigid-body poses (motion capture): load CSV and rosbag2 files, and sample a body's pose at any time of a
looped replay (:class:`RecordedTrack`). No ROS import: the node package's replay publishes what this module loads,
and the dynamic benchmark replays it in simulated time.

CSV format (one row per body and sample, header required; ``frame`` optional, default ``map``)::

    time,body,frame,x,y,z,qx,qy,qz,qw
    0.000000,person_face,map,3.9398,3.2215,1.6003,0.0012,-0.0004,0.9854,0.1700

rosbag2 (sqlite3 or mcap, read with the ``rosbags`` package): every ``geometry_msgs/msg/PoseStamped`` topic is one
body; the body name is the topic's middle part (``/mocap/<body>/pose``), else the topic without its leading slash.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import InputError
from .geometry import quat_multiply, quat_to_matrix

COLUMNS = ["time", "body", "frame", "x", "y", "z", "qx", "qy", "qz", "qw"]


@dataclass
class Recording:
    """Samples sorted by time: ``times`` (N,) s from the first sample, ``body`` (N,) index into ``bodies``,
    ``P`` (N, 3), ``Q`` (N, 4) quaternions xyzw, ``frames`` per body."""

    times: np.ndarray
    body: np.ndarray
    bodies: list
    P: np.ndarray
    Q: np.ndarray
    frames: list
    t0: float = 0.0  # the recorded time (stamp, s) of the first sample: recorded stamps are t0 + times

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0

    def rate_hz(self, body: str) -> float:
        t = self.times[self.body == self.bodies.index(body)]
        return float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 else 0.0

    def track(self, body: str) -> tuple:
        """(times, positions, quaternions) of one body."""
        m = self.body == self.bodies.index(body)
        return self.times[m], self.P[m], self.Q[m]


def make_recording(times, body_names, P, Q, frames_by_body) -> Recording:
    """A :class:`Recording` of samples in any order: ``times`` (N,) s, ``body_names`` (N,), ``P`` (N, 3), ``Q``
    (N, 4) xyzw, ``frames_by_body`` {body: frame}; sorted by time, times counted from the first."""
    bodies = list(dict.fromkeys(body_names))
    idx = np.array([bodies.index(b) for b in body_names], dtype=np.int64)
    times = np.asarray(times, float)
    order = np.argsort(times, kind="stable")
    t = times[order]
    t0 = float(t[0]) if len(t) else 0.0
    t = t - t0
    return Recording(times=t, body=idx[order], bodies=bodies, P=np.asarray(P, float).reshape(-1, 3)[order],
                     Q=np.asarray(Q, float).reshape(-1, 4)[order], frames=[frames_by_body[b] for b in bodies], t0=t0)


def load_csv(path) -> Recording:
    path = Path(path)
    times, names, P, Q, frames = [], [], [], [], {}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = set(COLUMNS) - {"frame"} - set(reader.fieldnames or [])
        if missing:
            raise InputError(f"{path}: missing CSV columns {', '.join(sorted(missing))}")
        for i, row in enumerate(reader, start=2):
            try:
                times.append(float(row["time"]))
                P.append([float(row["x"]), float(row["y"]), float(row["z"])])
                Q.append([float(row["qx"]), float(row["qy"]), float(row["qz"]), float(row["qw"])])
            except (TypeError, ValueError) as exc:
                raise InputError(f"{path}: line {i}: {exc}") from None
            names.append(row["body"])
            frames.setdefault(row["body"], row.get("frame") or "map")
    if not times:
        raise InputError(f"{path}: no samples")
    return make_recording(times, names, P, Q, frames)


def _body_of(topic: str) -> str:
    parts = [p for p in topic.split("/") if p]
    if len(parts) >= 3 and parts[-1] == "pose":
        return parts[-2]
    return "/".join(parts) or topic


def load_rosbag(path) -> Recording:
    """PoseStamped topics of a rosbag2 directory (or its .db3/.mcap file) via ``rosbags``."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    bag = path.parent if path.is_file() else path
    times, names, P, Q, frames = [], [], [], [], {}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.msgtype == "geometry_msgs/msg/PoseStamped"]
        if not conns:
            raise InputError(f"{bag}: no geometry_msgs/msg/PoseStamped topics")
        for conn, stamp_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            b = _body_of(conn.topic)
            times.append(stamp_ns * 1e-9)
            names.append(b)
            p, o = msg.pose.position, msg.pose.orientation
            P.append([p.x, p.y, p.z])
            Q.append([o.x, o.y, o.z, o.w])
            frames.setdefault(b, msg.header.frame_id or "map")
    return make_recording(times, names, P, Q, frames)


def load_recording(path) -> Recording:
    """CSV (``.csv``) or rosbag2 (a directory with ``metadata.yaml``, or a ``.db3``/``.mcap`` file)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"recording not found: {path}")
    if path.suffix.lower() == ".csv":
        return load_csv(path)
    return load_rosbag(path)


class RecordedTrack:
    """One body of a :class:`Recording` replayed in a loop (each pass starts one of the body's mean sample periods
    after the last one's final sample, where the body's first sample follows its last): :meth:`pose` gives the
    position (linear interpolation) and unit quaternion (normalised linear interpolation on the shorter arc) at replay
    time ``t`` s, the replay having started ``offset_s`` s into the loop. ``frame_pose``: (xyz, quaternion xyzw), the
    pose of the body's recorded frame in the frame wanted (e.g. a mocap system's ``world`` in a scene's ``map``)."""

    def __init__(self, rec: Recording, body: str, offset_s: float = 0.0, frame_pose: Optional[tuple] = None):
        if body not in rec.bodies:
            raise InputError(f"body '{body}' is not in the recording (it has {', '.join(rec.bodies)})")
        t, P, Q = rec.track(body)
        if len(t) < 2 or not (np.isfinite(P).all() and np.isfinite(Q).all()):
            raise InputError(f"recorded body '{body}': needs at least two finite samples")
        Q = Q / np.linalg.norm(Q, axis=1, keepdims=True)
        if frame_pose is not None:  # recorded in another frame: into the frame whose pose in it is given
            xyz, quat = np.asarray(frame_pose[0], float), np.asarray(frame_pose[1], float)
            quat = quat / np.linalg.norm(quat)
            P = P @ quat_to_matrix(quat).T + xyz
            Q = quat_multiply(quat, Q)
        for i in range(1, len(Q)):  # one hemisphere, so neighbours interpolate along the shorter arc
            if float(np.dot(Q[i], Q[i - 1])) < 0.0:
                Q[i] = -Q[i]
        self.body, self.offset_s = body, float(offset_s)
        span = float(t[-1] - t[0])
        if span <= 0.0:
            raise InputError(f"recorded body '{body}': its samples span no time")
        self.loop_s = span + span / (len(t) - 1)
        # the loop's last stretch goes from the final sample back to the first (at loop_s after the first)
        q_first = Q[0] if float(np.dot(Q[0], Q[-1])) >= 0.0 else -Q[0]
        self._t = np.append(t - t[0], self.loop_s)
        self._P = np.vstack([P, P[:1]])
        self._Q = np.vstack([Q, q_first[None]])

    def pose(self, t: float) -> tuple:
        """(position (3,), unit quaternion xyzw (4,)) at replay time ``t``."""
        tau = (float(t) + self.offset_s) % self.loop_s
        i = int(np.clip(np.searchsorted(self._t, tau, side="right") - 1, 0, len(self._t) - 2))
        w = (tau - self._t[i]) / max(1e-12, self._t[i + 1] - self._t[i])
        p = (1.0 - w) * self._P[i] + w * self._P[i + 1]
        q = (1.0 - w) * self._Q[i] + w * self._Q[i + 1]
        return p, q / np.linalg.norm(q)

