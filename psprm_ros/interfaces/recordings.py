"""Recorded rigid-body poses (motion capture): write CSV and rosbag2 files (loaded by :mod:`psprm_core.recording`,
whose names this module also gives), and generate the shipped recordings, one per shipped params file
(:data:`SHIPPED`): a person turning side to side (``dynamic_person``), two nurses turning and walking (``nursing``), a
monitor on a rolling cart pushed along the back aisle (``blind_spot_alley``). ``python -m
psprm_ros.interfaces.recordings [NAME ...]`` regenerates them.

The file formats: :mod:`psprm_core.recording`. No ROS import here: :mod:`psprm_ros.mocap_replay` publishes what this
module loads.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from psprm_core.paths import resolve_named
from psprm_core.recording import (COLUMNS, Recording, load_csv, load_recording, load_rosbag,  # noqa: F401
                                  make_recording)
from psprm_core.scene import load_scene


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
    return _assemble(t, {"person_face": (face_p, face_q), "person_body": (body_p, body_q)},
                     {"person_face": scene.frame, "person_body": scene.frame}, rng)


def _assemble(t: np.ndarray, tracks: dict, frames: dict, rng, drop: float = 0.005, sigma_p: float = 0.0004,
              sigma_deg: float = 0.15) -> Recording:
    """A :class:`Recording` of ``tracks`` (body -> (P (N, 3), Q (N, 4)) sampled at ``t``) as a motion-capture system
    streams them: ``sigma_p`` m position and ``sigma_deg`` deg orientation jitter (Gaussian), and a share ``drop``
    of the samples missing (marker occlusion), drawn from ``rng`` body by body in the order of ``tracks``."""
    times, names, P, Q = [], [], [], []
    for name, (pos, quat) in tracks.items():
        keep = rng.random(len(t)) > drop
        pos = pos + rng.normal(0.0, sigma_p, pos.shape)
        quat = _perturb(quat, rng, math.radians(sigma_deg))
        times.append(t[keep])
        names += [name] * int(keep.sum())
        P.append(pos[keep])
        Q.append(quat[keep])
    return make_recording(np.concatenate(times), names, np.vstack(P), np.vstack(Q), frames)


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


def _scene(scene, name: str):
    """``scene`` itself, or the shipped scene ``name`` loaded when it is None."""
    if scene is not None:
        return scene

    return load_scene(resolve_named("scene", name))


def _yaw_of(q) -> float:
    """Heading (rotation about z) of a quaternion xyzw."""
    x, y, z, w = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _keyframes(t: np.ndarray, keys) -> np.ndarray:
    """(N, d) values at times ``t`` of a motion through ``keys`` [(time, value), ...] (a number or a vector each):
    held between equal neighbouring keys, moved with a minimum-jerk profile (at rest at both keys) between different
    ones, held at the first / last key outside them."""
    kt = np.array([k[0] for k in keys], float)
    kv = np.array([np.atleast_1d(np.asarray(k[1], float)) for k in keys])
    i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, len(kt) - 2)
    u = np.clip((t - kt[i]) / (kt[i + 1] - kt[i]), 0.0, 1.0)
    s = u ** 3 * (10.0 - 15.0 * u + 6.0 * u ** 2)
    return kv[i] + s[:, None] * (kv[i + 1] - kv[i])


def _loop_hz(f: float, duration: float) -> float:
    """The frequency nearest ``f`` with a whole number of periods in ``duration``: the looped replay has no seam."""
    return max(1.0, round(f * duration)) / duration


def _walker(t: np.ndarray, duration: float, xy_keys, yaw_keys, face_offset: float, face_z: float, body_z: float,
            phase: float, fidget_rad: float = math.radians(6.0), body_lag_s: float = 0.15) -> tuple:
    """Face and body tracks ((P, Q), (P, Q)) of a person whose body stands on or walks through the ``xy_keys`` and
    faces the ``yaw_keys`` (both :func:`_keyframes`).

    The body's yaw follows the face's ``body_lag_s`` later (the head leads a turn); the head also glances about by
    ``fidget_rad`` and nods by 3 deg. Standing, the head sways by about 1 cm and breathes by 5 mm; walking (at the
    speed of the keyframed motion), it bobs 2 cm per step (1.8 steps/s) and sways 1.5 cm sideways per stride. Every
    periodic term has a whole number of periods in ``duration``, so a looped replay continues smoothly."""
    hz = lambda f: 2.0 * math.pi * _loop_hz(f, duration)  # noqa: E731
    xy = _keyframes(t, xy_keys)
    yaw = _keyframes(t, yaw_keys)[:, 0]
    yaw_body = _keyframes(t - body_lag_s, yaw_keys)[:, 0]
    speed = np.linalg.norm(np.gradient(xy, t, axis=0), axis=1)
    walking = np.clip(speed / 0.6, 0.0, 1.0)
    heading = np.c_[np.cos(yaw_body), np.sin(yaw_body)]
    side = np.c_[-heading[:, 1], heading[:, 0]]
    stride = 0.015 * walking * np.sin(hz(0.9) * t + phase)
    sway = 0.01 * (1.0 - walking)[:, None] * np.c_[np.sin(hz(0.3) * t + phase), np.sin(hz(0.23) * t + 1.0 + phase)]
    body_xy = xy + 0.5 * sway + stride[:, None] * side
    glance = fidget_rad * (0.6 * np.sin(hz(0.11) * t + phase) + 0.4 * np.sin(hz(0.23) * t + 2.0 * phase))
    yaw_face = yaw + glance * (1.0 - walking)
    bob = 0.005 * np.sin(hz(0.25) * t + phase) + 0.02 * walking * np.sin(hz(1.8) * t + phase)
    face_xy = body_xy + 0.5 * sway + face_offset * np.c_[np.cos(yaw_face), np.sin(yaw_face)]
    face_p = np.c_[face_xy, face_z + bob]
    body_p = np.c_[body_xy, body_z + 0.5 * bob]
    face_q = _yaw_quat(yaw_face, pitch=math.radians(3.0) * np.sin(hz(0.4) * t + phase))
    return (face_p, face_q), (body_p, _yaw_quat(yaw_body))


def nurses_turning_walking(scene=None, duration: float = 40.0, rate: float = 120.0, seed: int = 0,
                           frame: str = "world") -> Recording:
    """The two nurses of the ``nursing`` scene at work, looped every ``duration`` (40) s; both start and end standing
    at their scene poses, facing the medication cart (south).

    ``nurse_1`` stays at her place and turns: at 10 s she turns through west (3 s, at most about 115 deg/s) to look
    at the patient in the bed behind her, back to the cart at 19-22 s, and at 30-32 s turns a quarter west (towards
    the door and the robot's start) for 3 s. ``nurse_2`` walks: at 5 s she walks 1 m south to the cart's east end
    (2.2 s, at most 0.85 m/s), works there, turns round through east (15-17.5 s, at most about 140 deg/s), walks
    back to her place (17.5-19.7 s), turns further to face the patient, and at 27-29.5 s turns through west back to
    the cart. Head motion as :func:`_walker`; motion-capture noise as :func:`person_turning`. Poses in ``frame``
    (``world``, as vrpn_mocap publishes; the params file maps it onto the scene frame)."""
    scene = _scene(scene, "nursing")
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    f = lambda x: x * duration / 40.0  # noqa: E731  (the timeline scales with the duration)
    south, north, west = -math.pi / 2, math.pi / 2, -math.pi
    tracks = {}
    plans = {
        "nurse_1": (None, [(0, south), (f(10), south), (f(13), -3 * math.pi / 2), (f(19), -3 * math.pi / 2),
                           (f(22), south), (f(30), south), (f(32), west), (f(35), west), (f(37), south),
                           (duration, south)]),
        "nurse_2": ([(0, (0.0, 0.0)), (f(5), (0.0, 0.0)), (f(7.2), (0.0, -1.0)), (f(17.5), (0.0, -1.0)),
                     (f(19.7), (0.0, 0.0)), (duration, (0.0, 0.0))],
                    [(0, south), (f(15), south), (f(17.5), north), (f(19.7), north), (f(20.7), 2.1), (f(27), 2.1),
                     (f(29.5), 3 * math.pi / 2), (duration, 3 * math.pi / 2)]),
    }
    for k, (name, (moves, turns)) in enumerate(plans.items()):
        face, body = scene.target(f"{name}_face"), scene.obstacle(f"{name}_body")
        home = body.center[:2]
        xy_keys = [(tt, home + np.asarray(d)) for tt, d in moves] if moves else [(0, home), (duration, home)]
        offset = float(np.linalg.norm((face.center - body.center)[:2]))
        (fp, fq), (bp, bq) = _walker(t, duration, xy_keys, turns, offset, float(face.center[2]),
                                     float(body.center[2]), phase=1.7 * k)
        tracks[f"{name}_face"] = (fp, fq)
        tracks[f"{name}_body"] = (bp, bq)
    return _assemble(t, tracks, {b: frame for b in tracks}, rng)


def monitor_cart_rolling(scene=None, duration: float = 40.0, rate: float = 120.0, seed: int = 0,
                         frame: str = "world") -> Recording:
    """The ``blind_spot_alley`` monitor on its stand, a rolling cart, pushed along the back aisle and back, looped
    every ``duration`` (40) s: parked against the north wall at the end of the cross lane until 8 s, pulled 0.3 m
    out (1.5 s), pushed 2 m west behind the low shelves (5 s, at most 0.75 m/s), left there for 11.5 s, pushed back
    (26-31 s) and parked again (31-32.5 s). The screen keeps facing south; the casters make it yaw by up to 3 deg
    and shake by 2 mm while it rolls. ``crate_east`` (streamed too: the params file tracks it) stands still.
    Motion-capture noise as :func:`person_turning`; poses in ``frame`` (``world``, as vrpn_mocap publishes)."""
    scene = _scene(scene, "blind_spot_alley")
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration + 1e-9, 1.0 / rate)
    f = lambda x: x * duration / 40.0  # noqa: E731
    monitor, stand, crate = scene.target("monitor"), scene.obstacle("monitor_stand"), scene.obstacle("crate_east")
    stand_yaw, monitor_yaw = _yaw_of(stand.quat), _yaw_of(monitor.quat)
    park = stand.center[:2]
    out, away = park + [0.0, -0.3], park + [-2.0, -0.3]
    xy = _keyframes(t, [(0, park), (f(8), park), (f(9.5), out), (f(14.5), away), (f(26), away), (f(31), out),
                        (f(32.5), park), (duration, park)])
    speed = np.linalg.norm(np.gradient(xy, t, axis=0), axis=1)
    rolling = np.clip(speed / 0.3, 0.0, 1.0)
    yaw = stand_yaw + math.radians(3.0) * rolling * np.sin(2.0 * math.pi * _loop_hz(0.7, duration) * t)
    shake = 0.002 * rolling * np.sin(2.0 * math.pi * _loop_hz(6.0, duration) * t)
    # the screen sits on the stand: its offset from the stand's centre turns with the cart
    d = monitor.center[:2] - stand.center[:2]
    c, s_ = np.cos(yaw - stand_yaw), np.sin(yaw - stand_yaw)
    mon_xy = xy + np.c_[c * d[0] - s_ * d[1], s_ * d[0] + c * d[1]]
    tracks = {
        "monitor": (np.c_[mon_xy, monitor.center[2] + shake], _yaw_quat(yaw + (monitor_yaw - stand_yaw))),
        "monitor_stand": (np.c_[xy, np.full_like(t, stand.center[2])], _yaw_quat(yaw)),
        "crate_east": (np.tile(crate.center, (len(t), 1)), np.tile(crate.quat, (len(t), 1))),
    }
    return _assemble(t, tracks, {b: frame for b in tracks}, rng)


#: The shipped recordings: name -> (generator, path under the repository, the params file it is replayed with).
SHIPPED = {
    "person_turning": (person_turning, "config/recordings/person_turning.csv", "config/ros/dynamic_person.yaml"),
    "nurses_turning_walking": (nurses_turning_walking, "config/recordings/nurses_turning_walking.csv",
                               "config/ros/fetchlike_nursing.yaml"),
    "monitor_cart_rolling": (monitor_cart_rolling, "config/recordings/monitor_cart_rolling.csv",
                             "config/ros/ur5_mobile_blind_spot_alley.yaml"),
}


def main(argv=None) -> int:
    """Regenerate shipped recordings (all by default) under the repository root, or one at ``--out``."""
    import argparse

    root = Path(__file__).resolve().parents[2]
    ap = argparse.ArgumentParser(description="Regenerate the shipped recordings (config/recordings/*.csv)")
    ap.add_argument("names", nargs="*", default=[], help=f"recordings to write (default all: {', '.join(SHIPPED)})")
    ap.add_argument("--out", default="", help="write here instead of the shipped path (one recording only)")
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bag", default="", help="also write a rosbag2 directory here (one recording only)")
    a = ap.parse_args(argv)
    names = a.names or list(SHIPPED)
    unknown = sorted(set(names) - set(SHIPPED))
    if unknown:
        ap.error(f"unknown recording(s) {', '.join(unknown)} (shipped: {', '.join(SHIPPED)})")
    if (a.out or a.bag) and len(names) != 1:
        ap.error("--out and --bag take one recording name")
    for name in names:
        make, shipped, _ = SHIPPED[name]
        rec = make(duration=a.duration, rate=a.rate, seed=a.seed)
        print(save_csv(rec, a.out or root / shipped), len(rec.times), "samples,", f"{rec.duration:.2f} s")
        if a.bag:
            print(save_rosbag(rec, a.bag))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
