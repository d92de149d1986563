"""mocap_replay and recordings: the shipped recording (person turning side to side at a human pace, 120 Hz, 40 s), CSV and rosbag2
round trips, and replay at the recorded rate as PoseStamped topics with sensor-data QoS."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_ros.harness.probe import claim_domain_id  # noqa: E402

from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.interfaces.recordings import Recording, load_recording, save_csv, save_rosbag  # noqa: E402

SHIPPED = ROOT / "config" / "recordings" / "person_turning.csv"


def test_shipped_recording_is_a_person_turning_side_to_side_at_120_hz():
    rec = load_recording(SHIPPED)
    assert set(rec.bodies) == {"person_face", "person_body"} and rec.frames == ["map", "map"]
    assert 39.9 <= rec.duration <= 40.1 and 115 <= rec.rate_hz("person_face") <= 121
    t, P, Q = rec.track("person_face")
    yaw = np.unwrap([cv.yaw_of(q) for q in Q])
    assert yaw.max() - yaw.min() > 3.0  # from facing the shelf side to facing the cabinet side, through south
    smooth = np.convolve(yaw, np.ones(60) / 60, "valid")
    turns = np.sum(np.abs(np.diff(np.sign(np.diff(smooth)))) > 0)
    assert turns >= 3  # back and forth, twice
    rate = np.abs(np.diff(smooth)) / np.diff(np.convolve(t, np.ones(60) / 60, "valid"))
    assert rate.max() < 1.0  # a human pace: under 57 deg/s at the fastest
    jitter = np.std(np.diff(P[:, 2], 2))  # mocap noise: sub-millimetre, not zero
    assert 1e-5 < jitter < 2e-3
    body_xy = rec.track("person_body")[1][:, :2]
    assert np.linalg.norm(body_xy - [4.0, 3.2], axis=1).max() < 0.05  # turning on the spot


def test_csv_and_rosbag_round_trip(tmp_path):
    rec = load_recording(SHIPPED)
    short = Recording(times=rec.times[:400], body=rec.body[:400], bodies=rec.bodies, P=rec.P[:400], Q=rec.Q[:400],
                      frames=rec.frames)
    a = load_recording(save_csv(short, tmp_path / "r.csv"))
    b = load_recording(save_rosbag(short, tmp_path / "bag"))
    for r in (a, b):
        assert r.bodies == short.bodies and len(r.times) == 400
        assert np.allclose(r.P, short.P, atol=1e-5) and np.allclose(r.times, short.times, atol=1e-5)
    with pytest.raises(ValueError, match="missing CSV columns"):
        (tmp_path / "bad.csv").write_text("time,body,x\n0,a,1\n")
        load_recording(tmp_path / "bad.csv")


@pytest.mark.parametrize("kind", ["csv", "rosbag"])
def test_replay_publishes_pose_stamped_at_the_recorded_rate(kind, tmp_path):
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from psprm_ros.spinning import NodeSpinner
    from rclpy.qos import qos_profile_sensor_data

    from psprm_ros.mocap_replay import Replayer

    rec = load_recording(SHIPPED)
    n = int(np.searchsorted(rec.times, 1.5))  # the first 1.5 s
    short = Recording(times=rec.times[:n], body=rec.body[:n], bodies=rec.bodies, P=rec.P[:n], Q=rec.Q[:n],
                      frames=rec.frames)
    path = save_csv(short, tmp_path / "r.csv") if kind == "csv" else save_rosbag(short, tmp_path / "bag")
    loaded = load_recording(path)
    ctx = rclpy.Context()
    ctx.init(domain_id=claim_domain_id())
    pub_node = rclpy.create_node("replay", context=ctx)
    sub_node = rclpy.create_node("listener", context=ctx)
    got = {b: [] for b in rec.bodies}
    for b in rec.bodies:
        sub_node.create_subscription(PoseStamped, f"/mocap/{b}/pose",
                                     lambda m, b=b: got[b].append((time.perf_counter(), m)), qos_profile_sensor_data)
    ex = NodeSpinner(ctx)
    ex.add(pub_node)
    ex.add(sub_node)
    ex.start()
    try:
        rp = Replayer(pub_node, loaded)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and sub_node.count_publishers("/mocap/person_face/pose") < 1:
            time.sleep(0.05)
        time.sleep(0.5)
        t0 = time.perf_counter()
        rp.start()
        rp.join(10)
        elapsed = time.perf_counter() - t0
        time.sleep(0.3)
    finally:
        ex.shutdown(timeout_sec=1.0)
        ctx.try_shutdown()
    assert rp.published == n
    # paced at the recorded rate (1.5 s of data), not as fast as possible; the upper bound leaves room for a
    # heavily loaded 2-core machine (the pacing thread catches up on late samples)
    assert 1.4 < elapsed < 8.0
    face = got["person_face"]
    n_face = int(np.sum(short.body == short.bodies.index("person_face")))
    assert 0 < len(face) <= n_face  # best effort: a starved subscriber may miss samples, never gets extra ones
    m = face[len(face) // 2][1]
    assert m.header.frame_id == "map"
    p, q = cv.validated_pose(m, "map")
    assert np.isfinite(p).all() and abs(np.linalg.norm(q) - 1) < 1e-6
    # the recorded poses arrive unchanged: each received pose is one of the recorded face samples
    _, P, _ = short.track("person_face")
    assert np.min(np.linalg.norm(P - p, axis=1)) < 1e-4


def test_mocap_replay_executable_rejects_a_missing_file(tmp_path):
    import subprocess

    r = subprocess.run([sys.executable, "-m", "psprm_ros.mocap_replay", str(tmp_path / "nope.csv")], cwd=str(ROOT),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "not found" in r.stderr


def test_keep_stamps_with_clock_is_coherent_with_use_sim_time(tmp_path):
    """A rosbag recorded an hour ago: ``--keep-stamps`` publishes its recorded stamps; a monitor on wall time refuses
    them as stale, one with ``use_sim_time`` driven by the replay's ``/clock`` forwards them."""
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from psprm_ros.spinning import NodeSpinner
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data

    from psprm_ros.mocap_replay import Replayer
    from psprm_ros.replan_monitor import ReplanMonitor

    rec = load_recording(SHIPPED)
    n = int(np.searchsorted(rec.times, 2.0))
    t_rec = time.time() - 3600.0
    short = Recording(times=rec.times[:n], body=rec.body[:n], bodies=rec.bodies, P=rec.P[:n], Q=rec.Q[:n],
                      frames=rec.frames, t0=t_rec)
    loaded = load_recording(save_rosbag(short, tmp_path / "bag"))
    assert abs(loaded.t0 - t_rec) < 1e-3
    results = {}
    for sim_time in (False, True):
        ctx = rclpy.Context()
        ctx.init(domain_id=claim_domain_id())
        over = [Parameter("use_sim_time", value=sim_time), Parameter("stale_timeout_s", value=60.0),
                Parameter("relay_deadband_m", value=0.0), Parameter("relay_deadband_rad", value=0.0)]
        mon = ReplanMonitor(context=ctx, parameter_overrides=over)
        pub_node = rclpy.create_node("replay", context=ctx)
        stamps, clocks = [], []
        pub_node.create_subscription(PoseStamped, "/psprm/state/targets/person_face",
                                     lambda m: stamps.append(cv.stamp_to_sec(m.header.stamp)), qos_profile_sensor_data)
        pub_node.create_subscription(PoseStamped, "/mocap/person_face/pose",
                                     lambda m: clocks.append(cv.stamp_to_sec(m.header.stamp)), qos_profile_sensor_data)
        ex = NodeSpinner(ctx)
        ex.add(mon.node)
        ex.add(pub_node)
        ex.start()
        try:
            from psprm_ros.core import autostart

            assert autostart(mon)
            rp = Replayer(pub_node, loaded, keep_stamps=True, clock=True)
            time.sleep(0.5)
            rp.start()
            rp.join(10)
            time.sleep(0.3)
            results[sim_time] = (list(stamps), list(clocks), mon.counts["refused"])
        finally:
            ex.shutdown(timeout_sec=1.0)
            mon.destroy()
            ctx.try_shutdown()
    fwd, seen, refused = results[True]
    assert seen and abs(seen[0] - t_rec) < 0.1  # the recorded stamps, kept
    assert fwd and refused == 0 and abs(fwd[-1] - (t_rec + short.times[-1])) < 0.1
    fwd, seen, refused = results[False]
    assert not fwd and refused > 0  # an hour old on the wall clock: stale
