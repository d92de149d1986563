"""Recorded rigid-body poses (motion capture): load CSV and rosbag2 files, write them, and generate the shipped
recording of a person turning side to side.

CSV format (one row per body and sample, header required; ``frame`` optional, default ``map``)::

    time,body,frame,x,y,z,qx,qy,qz,qw
    0.000000,person_face,map,3.9398,3.2215,1.6003,0.0012,-0.0004,0.9854,0.1700

rosbag2 (sqlite3 or mcap, read with the ``rosbags`` package): every ``geometry_msgs/msg/PoseStamped`` topic is one
body; the body name is the topic's middle part (``/mocap/<body>/pose``), else the topic without its leading slash.

No ROS import here: :mod:`psprm_ros.mocap_replay` publishes what this module loads.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psprm_core.errors import InputError

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


def _finish(times, body_names, P, Q, frames_by_body) -> Recording:
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
    return _finish(times, names, P, Q, frames)


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
    return _finish(times, names, P, Q, frames)


def load_recording(path) -> Recording:
    """CSV (``.csv``) or rosbag2 (a directory with ``metadata.yaml``, or a ``.db3``/``.mcap`` file)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"recording not found: {path}")
    if path.suffix.lower() == ".csv":
        return load_csv(path)
    return load_rosbag(path)


def save_csv(rec: Recording, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for t, b, p, q in zip(rec.times, rec.body, rec.P, rec.Q):
            w.writerow([f"{rec.t0 + t:.6f}", rec.bodies[b], rec.frames[b]] + [f"{v:.5f}" for v in p] +
                       [f"{v:.6f}" for v in q])
    return path


def save_rosbag(rec: Recording, path, prefix: str = "/mocap") -> Path:
    """Write ``rec`` as a rosbag2 (sqlite3) directory, one PoseStamped topic ``<prefix>/<body>/pose`` per body."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    PoseStamped = ts.types["geometry_msgs/msg/PoseStamped"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Pose = ts.types["geometry_msgs/msg/Pose"]
    Point = ts.types["geometry_msgs/msg/Point"]
    Quaternion = ts.types["geometry_msgs/msg/Quaternion"]
    path = Path(path)
    t0 = int(round(rec.t0 * 1e9)) if rec.t0 > 0 else 1_700_000_000 * 10**9
    with Writer(path, version=8) as w:
        conns = [w.add_connection(f"{prefix}/{b}/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
                 for b in rec.bodies]
        for t, b, p, q in zip(rec.times, rec.body, rec.P, rec.Q):
            ns = t0 + int(round(t * 1e9))
            msg = PoseStamped(header=Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=rec.frames[b]),
                              pose=Pose(position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                        orientation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                               w=float(q[3]))))
            w.write(conns[b], ns, ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
    return path


# ------------------------------------------------------------------------------------------------------------------
# the shipped recording
# ------------------------------------------------------------------------------------------------------------------
def _yaw_quat(yaw, roll=0.0, pitch=0.0) -> np.ndarray:
    """Quaternions xyzw of R = Rz(yaw) Ry(pitch) Rx(roll) (arrays)."""
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    return np.stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy], -1)


def person_turning(scene=None, duration: float = 40.0, rate: float = 120.0, period: float = 20.0,
                   amplitude: float = math.pi / 2, sharpness: float = 1.5, seed: int = 0) -> Recording:
    """A standing person turning side to side around the scene's pose (``dynamic_person`` by default), at a human
    pace.

    The face turns between west (towards the shelf) and east (towards the cabinet) through south (``amplitude`` rad
    either side of south), with a dwell at each side (tanh-shaped profile of ``sharpness``, ``period`` s per cycle;
    by default 180 deg in 10 s, at most about 47 deg/s);
    the head bobs and sways by about 1 cm, the body follows the face's yaw 0.15 s later with 80 % of its
    amplitude. Motion-capture noise: 0.4 mm position and 0.15 deg orientation jitter (Gaussian), plus dropped
    frames (0.5 % of samples, marker occlusion).
    """
    if scene is None:
        from psprm_core.paths import resolve_named
        from psprm_core.scene import load_scene

        scene = load_scene(resolve_named("scene", "dynamic_person"))
    rng = np.random.default_rng(seed)
    face, body = scene.target("person_face"), scene.obstacle("person_body")
    centre = -math.pi / 2  # facing south (towards the robot's start)
    amp = float(amplitude)
    offset = float(np.linalg.norm((face.center - body.center)[:2]))
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    k = float(sharpness)

    def yaw_at(tt, a=1.0):
        return centre - a * amp * np.tanh(k * np.cos(2 * np.pi * tt / period)) / np.tanh(k)

    yaw_f = yaw_at(t)
    yaw_b = yaw_at(t - 0.15, 0.8)
    sway = 0.01 * np.stack([np.sin(2 * np.pi * 0.3 * t), np.sin(2 * np.pi * 0.23 * t + 1.0)], -1)
    bob = 0.008 * np.sin(2 * np.pi * 0.5 * t)
    face_p = np.c_[body.center[0] + sway[:, 0] + offset * np.cos(yaw_f),
                   body.center[1] + sway[:, 1] + offset * np.sin(yaw_f), face.center[2] + bob]
    body_p = np.c_[body.center[0] + 0.5 * sway[:, 0], body.center[1] + 0.5 * sway[:, 1], np.full_like(t, body.center[2])]
    nod = 0.05 * np.sin(2 * np.pi * 0.4 * t)
    face_q = _yaw_quat(yaw_f, pitch=nod)
    body_q = _yaw_quat(yaw_b)
    times, names, P, Q = [], [], [], []
    for name, pos, quat in (("person_face", face_p, face_q), ("person_body", body_p, body_q)):
        keep = rng.random(len(t)) > 0.005
        pos = pos + rng.normal(0.0, 0.0004, pos.shape)
        quat = _perturb(quat, rng, math.radians(0.15))
        times.append(t[keep])
        names += [name] * int(keep.sum())
        P.append(pos[keep])
        Q.append(quat[keep])
    return _finish(np.concatenate(times), names, np.vstack(P), np.vstack(Q),
                   {"person_face": scene.frame, "person_body": scene.frame})


def _perturb(q: np.ndarray, rng, sigma: float) -> np.ndarray:
    """Multiply unit quaternions by small random rotations (angle ~ N(0, sigma) per axis)."""
    v = rng.normal(0.0, sigma, (len(q), 3)) / 2
    dq = np.c_[v, np.ones(len(q))]
    dq /= np.linalg.norm(dq, axis=1, keepdims=True)
    x1, y1, z1, w1 = dq.T
    x2, y2, z2, w2 = q.T
    out = np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                    w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2], -1)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description="Regenerate the shipped recording config/recordings/person_turning.csv")
    ap.add_argument("--out", default="config/recordings/person_turning.csv")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bag", default="", help="also write a rosbag2 directory here")
    a = ap.parse_args(argv)
    rec = person_turning(duration=a.duration, rate=a.rate, seed=a.seed)
    print(save_csv(rec, a.out), len(rec.times), "samples,", f"{rec.duration:.2f} s")
    if a.bag:
        print(save_rosbag(rec, a.bag))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
