"""The tf base pose source: :class:`psprm_ros.interfaces.tf_tree.TfTree` composing ``map -> odom -> base_link`` (judged
against the test's own 4x4 homogeneous matrices), the missing link named, bad transforms discarded; the robot state
tracker with ``base_pose_source: tf`` giving the true pose of a robot whose odometry drifts, corrected by ``map ->
odom`` (judged against the test's own ground truth); and over real rclpy the replan monitor forwarding the base pose the
test's ``/tf_static`` and ``/tf`` messages say."""

from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from psprm_core.errors import InputError  # noqa: E402
from psprm_ros.interfaces.frames import FrameTable  # noqa: E402
from psprm_ros.robots.robot_state import RobotStateTracker  # noqa: E402
from psprm_ros.interfaces.tf_tree import TfLookupError, TfTree  # noqa: E402


# ---------------------------------------------------------------------------------------------------------- the test's
# own transform algebra: 4x4 matrices from (xyz, quaternion xyzw) by the textbook rotation matrix
def mat(xyz, q) -> np.ndarray:
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, xyz
    return T


def planar(x, y, yaw) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = x, y
    return T


def xyyaw(T) -> np.ndarray:
    return np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])


def quat_of(T) -> np.ndarray:
    """Quaternion xyzw of a rotation matrix (Shepperd's method)."""
    R = T[:3, :3]
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[i], q[j], q[k], q[3] = 0.25 * s, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s, (R[k, j] - R[j, k]) / s
    return np.array(q)


def random_pose(rng) -> tuple:
    q = rng.normal(size=4)
    return rng.uniform(-5, 5, 3), q / np.linalg.norm(q)


def wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


# ---------------------------------------------------------------------------------------------------------- messages
# laid out as tf2_msgs/TFMessage (transforms: geometry_msgs/TransformStamped); the rclpy test sends the real type
def tr(parent, child, xyz, q, stamp=0.0):
    return SimpleNamespace(
        header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=int(math.floor(stamp)),
                                                                      nanosec=int(round((stamp % 1.0) * 1e9)))),
        child_frame_id=child,
        transform=SimpleNamespace(translation=SimpleNamespace(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                                  rotation=SimpleNamespace(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                           w=float(q[3]))))


def tr_T(parent, child, T, stamp=0.0):
    return tr(parent, child, T[:3, 3], quat_of(T), stamp)


def tfm(*transforms):
    return SimpleNamespace(transforms=list(transforms))


# ---------------------------------------------------------------------------------------------------------- (a) TfTree
def test_lookup_composes_the_chain_as_the_tests_own_matrices():
    rng = np.random.default_rng(7)
    for trial in range(50):
        (p1, q1), (p2, q2), (p3, q3), (p4, q4) = (random_pose(rng) for _ in range(4))
        tree = TfTree()
        # leading slashes and the order of links in messages do not matter
        assert tree.update(tfm(tr("odom", "base_link", p2, q2, 10.2)), False, 1.0) == []
        assert tree.update(tfm(tr("/map", "odom", p1, q1, 10.0)), False, 1.1) == []
        assert tree.update(tfm(tr("base_link", "camera_link", p3, q3), tr("map", "/marker", p4, q4)), True, 1.2) == []
        T_map_odom, T_odom_base, T_base_cam, T_map_marker = mat(p1, q1), mat(p2, q2), mat(p3, q3), mat(p4, q4)
        cases = {("map", "base_link"): T_map_odom @ T_odom_base,
                 ("map", "camera_link"): T_map_odom @ T_odom_base @ T_base_cam,
                 ("base_link", "map"): np.linalg.inv(T_map_odom @ T_odom_base),
                 ("/camera_link", "marker"): np.linalg.inv(T_map_odom @ T_odom_base @ T_base_cam) @ T_map_marker,
                 ("marker", "odom"): np.linalg.inv(T_map_marker) @ T_map_odom,
                 ("odom", "odom"): np.eye(4)}
        for (target, source), want in cases.items():
            got = tree.lookup(target, source)
            assert np.allclose(mat(got.xyz, got.quat), want, atol=1e-9, rtol=0), (trial, target, source)
            assert abs(np.linalg.norm(got.quat) - 1) < 1e-12
    # freshness: the newest dynamic link of the chain, static links not counted
    got = tree.lookup("map", "camera_link")
    assert got.received == pytest.approx(1.0 + 0.1) and got.oldest_received == pytest.approx(1.0)
    assert got.stamp == pytest.approx(10.2) and got.age(3.0) == pytest.approx(1.9)
    assert tree.lookup("map", "marker").received is None  # static only


def test_a_missing_link_is_named():
    tree = TfTree()
    assert "no transform received" in str(tree.find("map", "base_link")[1])
    tree.update(tfm(tr("map", "odom", [1, 0, 0], [0, 0, 0, 1])), False, 0.0)
    with pytest.raises(TfLookupError, match=r"no transform from map to base_link: odom -> base_link missing"):
        tree.lookup("map", "base_link")
    tree.update(tfm(tr("base_link", "camera_link", [0, 0, 1], [0, 0, 0, 1])), True, 0.0)  # base_link known now
    pose, why = tree.find("map", "camera_link")
    assert pose is None and "odom -> base_link missing" in why, why
    tree2 = TfTree()
    tree2.update(tfm(tr("odom", "base_link", [1, 0, 0], [0, 0, 0, 1])), False, 0.0)
    assert "map -> odom missing" in tree2.find("map", "base_link")[1]
    tree.update(tfm(tr("odom", "base_link", [2, 0, 0], [0, 0, 0, 1])), False, 0.0)
    pose, why = tree.find("map", "camera_link")
    assert why == "" and np.allclose(pose.xyz, [3, 0, 1])


def test_bad_transforms_are_discarded_with_a_reason_and_the_good_ones_kept():
    tree = TfTree()
    good = tr("map", "odom", [1.0, 2.0, 0.0], [0, 0, 0, 1])
    bad = [
        (tr("odom", "base_link", [math.nan, 0, 0], [0, 0, 0, 1]), "non-finite"),
        (tr("odom", "base_link", [0, 0, 0], [0, 0, math.inf, 1]), "non-finite"),
        (tr("odom", "base_link", [0, 0, 0], [0, 0, 0.2, 1.0]), "not a unit quaternion"),
        (tr("odom", "base_link", [0, 0, 0], [0, 0, 0, 0]), "not a unit quaternion"),
        (tr("", "base_link", [0, 0, 0], [0, 0, 0, 1]), "empty frame id"),
        (tr("odom", " / ", [0, 0, 0], [0, 0, 0, 1]), "empty frame id"),
        (tr("odom", "odom", [0, 0, 0], [0, 0, 0, 1]), "itself"),
        (tr("world", "odom", [0, 0, 0], [0, 0, 0, 1]), "already has the parent 'map'"),
        (tr("odom", "map", [0, 0, 0], [0, 0, 0, 1]), "loop"),
        (SimpleNamespace(header=None, child_frame_id="x"), "unreadable"),
    ]
    dropped = tree.update(tfm(good, *(b for b, _ in bad)), False, 0.0)
    assert len(dropped) == len(bad)
    for d, (_, why) in zip(dropped, bad):
        assert why in str(d), (str(d), why)
    assert tree.update(SimpleNamespace(), False, 0.0)[0].reason.startswith("not a TFMessage")
    # only the good one is in the tree, unchanged
    assert sorted(tree.links) == ["odom"] and np.allclose(tree.lookup("map", "odom").xyz, [1, 2, 0])
    assert "odom -> base_link missing" in tree.find("map", "base_link")[1]
    # a quaternion within the tolerance is taken, normalised
    assert tree.update(tfm(tr("odom", "base_link", [0, 0, 0], [0, 0, 0, 1.001])), False, 0.0) == []
    assert np.allclose(tree.lookup("odom", "base_link").quat, [0, 0, 0, 1], atol=1e-12)


def test_input_frames_resolve_through_tf_where_the_fixed_table_has_none():
    """A pose in ``vicon`` (tf: map -> world static, world -> vicon static) comes into the scene frame as the test's
    own matrices compose it; ``odom`` keeps its fixed transform even when tf has another; a frame tf cannot link is
    refused with the missing link named."""
    rng = np.random.default_rng(3)
    (pw, qw), (pv, qv), (po, qo), (pt, qt), (px, qx) = (random_pose(rng) for _ in range(5))
    tree = TfTree()
    tree.update(tfm(tr("map", "world", pw, qw), tr("world", "vicon", pv, qv), tr("map", "odom", pt, qt)), True, 0.0)
    table = FrameTable("map", {"odom": (po, qo)}, tf=tree)
    p, q = table.to_scene("vicon", px, qx)
    ref = mat(pw, qw) @ mat(pv, qv) @ mat(px, qx)
    assert np.abs(p - ref[:3, 3]).max() < 1e-9
    assert np.abs(mat(p, q) - ref).max() < 1e-9
    assert table.knows("vicon") and table.knows("/vicon") and not table.knows("elsewhere")
    p, q = table.to_scene("odom", px, qx)  # the fixed table wins
    ref = mat(po, qo) @ mat(px, qx)
    assert np.abs(mat(p, q) - ref).max() < 1e-9
    with pytest.raises(InputError, match="elsewhere.*tf: no transform from map to elsewhere"):
        table.to_scene("elsewhere", px, qx)
    with pytest.raises(InputError, match="neither the scene frame"):
        FrameTable("map", {}).to_scene("vicon", px, qx)  # without tf, as before: the fixed table only


def test_a_missing_tf2_msgs_is_named(monkeypatch):
    from psprm_core.errors import InputError
    from psprm_ros.interfaces.tf_tree import import_tf_message

    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)  # import fails as without the package
    with pytest.raises(InputError, match=r"tf2_msgs.*ros-jazzy-tf2-msgs.*build_interfaces"):
        import_tf_message()


# ---------------------------------------------------------------------------------------------------------- (b) tracker
def _joints(robot, q):
    names = list(robot.joint_names[3:])
    return SimpleNamespace(name=names, position=[float(v) for v in q[3:]], header=SimpleNamespace(frame_id=""))


def test_tracker_corrects_drifting_odometry_with_map_to_odom(load_robot):
    """A robot drives a curve (the test's ground truth in the map). Its odometry integrates the commanded
    velocities with a scale error and a yaw-rate bias, so odom -> base_link walks off; the localisation's map -> odom
    (truth @ inverse(odometry), as AMCL publishes it) corrects it. The tracker's base pose is the truth within 1 cm
    / 0.01 rad at every step, its velocity the odometry's."""
    robot = load_robot("stretch2")
    frames = FrameTable("map")
    tracker = RobotStateTracker(robot, frames, "tf", timeout_s=0.5, base_frame="base_link")
    q0 = np.array(robot.default_configuration(), float)
    # a static link below the dynamic ones: odom -> base_footprint (odometry), base_footprint -> base_link (fixed,
    # with an offset the pose must include)
    T_fp_base = planar(0.05, -0.02, 0.03)
    tracker.update_tf(tfm(tr_T("base_footprint", "base_link", T_fp_base)), True, 0.0)
    truth = np.array([2.0, 1.0, 0.4])  # base_footprint in map
    odo = np.array([0.0, 0.0, 0.0])  # base_footprint in odom, integrated from biased velocities
    T_map_odom0 = planar(*truth) @ np.linalg.inv(planar(*odo))
    dt, max_drift = 0.05, 0.0
    for k in range(400):
        t = 1.0 + k * dt
        v, w = 0.4, 0.3 * math.sin(0.02 * k)
        th = truth[2] + 0.5 * w * dt
        truth = truth + [v * dt * math.cos(th), v * dt * math.sin(th), w * dt]
        vo, wo = 1.05 * v, w + 0.02  # what the wheels report
        tho = odo[2] + 0.5 * wo * dt
        odo = odo + [vo * dt * math.cos(tho), vo * dt * math.sin(tho), wo * dt]
        T_odom_fp = planar(*odo)
        T_map_odom = planar(*truth) @ np.linalg.inv(T_odom_fp)
        # odometry and localisation come in their own messages, in either order
        msgs = [tfm(tr_T("odom", "base_footprint", T_odom_fp, t)), tfm(tr_T("map", "odom", T_map_odom, t))]
        for m in (msgs if k % 2 else msgs[::-1]):
            assert tracker.update_tf(m, False, t) == []
        want = xyyaw(planar(*truth) @ T_fp_base)
        got = tracker.base
        assert np.hypot(*(got[:2] - want[:2])) < 0.01 and abs(wrap(got[2] - want[2])) < 0.01, (k, got, want)
        # the uncorrected odometry (map -> odom as at the start) is off: the check above can fail
        max_drift = max(max_drift, np.hypot(*(xyyaw(T_map_odom0 @ T_odom_fp @ T_fp_base)[:2] - want[:2])))
        if k > 0:  # differenced from the odometry's own link: the wheels' velocities (1.05 x the true speed), not
            # the map pose's; base_link's point is (0.05, -0.02) off base_footprint, turned by 0.03 rad
            rx, ry, ryaw = 0.05, -0.02, 0.03
            v_bl = math.cos(ryaw) * (vo - wo * ry) + math.sin(ryaw) * (wo * rx)
            assert np.allclose(tracker.base_velocity, [v_bl, wo], atol=1e-4), (k, tracker.base_velocity, v_bl, wo)
    assert max_drift > 0.3, max_drift
    # fresh joints + fresh base -> a configuration with the true base
    tracker.update_joints(_joints(robot, q0), t)
    q, why = tracker.state(t + 0.1)
    assert why == "ok" and np.allclose(q[:2], want[:2], atol=0.01)
    # /tf stops: the base pose goes stale (the static link does not keep it alive)
    tracker.update_joints(_joints(robot, q0), t + 0.7)
    q, why = tracker.state(t + 0.7)
    assert q is None and "waiting for base pose" in why and "old" in why


def test_tracker_waits_for_the_missing_link_and_reports_bad_transforms_once(load_robot):
    robot = load_robot("stretch2")
    tracker = RobotStateTracker(robot, FrameTable("map"), "tf", timeout_s=0.5)
    q0 = np.array(robot.default_configuration(), float)
    tracker.update_joints(_joints(robot, q0), 0.0)
    assert tracker.update_tf(tfm(tr("map", "odom", [1, 0, 0], [0, 0, 0, 1], 1.0)), False, 0.0) == []
    q, why = tracker.state(0.0)
    assert q is None and why.startswith("waiting for base pose") and "odom -> base_link missing" in why, why
    bad = tfm(tr("odom", "base_link", [0, 0, 0], [0, 0, 0, 3.0], 1.0))
    first = tracker.update_tf(bad, False, 0.1)
    assert len(first) == 1 and "not a unit quaternion" in first[0]
    assert tracker.update_tf(bad, False, 0.2) == []  # reported once per period
    assert tracker.base is None
    # a base on static links only (a fixed map -> base_link) never goes stale
    fixed = RobotStateTracker(robot, FrameTable("map"), "tf", timeout_s=0.5)
    fixed.update_tf(tfm(tr_T("map", "base_link", planar(3.0, -1.0, 2.0))), True, 0.0)
    fixed.update_joints(_joints(robot, q0), 100.0)
    q, why = fixed.state(100.0)
    assert why == "ok" and np.allclose(q[:3], [3.0, -1.0, 2.0])


# ---------------------------------------------------------------------------------------------------------- (c) rclpy
def test_replan_monitor_forwards_the_base_pose_the_tf_topics_say(load_robot):
    """The replan monitor with ``base_pose_source: tf``: the test publishes base_footprint -> base_link once on
    /tf_static (transient local, right after creating the publisher: delivered without waiting for discovery),
    then map -> odom and odom -> base_footprint on /tf, and /joint_states; the robot state the monitor forwards
    carries the base pose of the test's matrix product, also after the localisation's correction jumps. The node
    subscribes to /tf and /tf_static and publishes neither."""
    pytest.importorskip("rclpy")
    from geometry_msgs.msg import TransformStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage

    from psprm_ros import core
    from psprm_ros.interfaces import conversions as cv
    from psprm_ros.harness.probe import InProcessSuite, claim_domain_id

    robot = load_robot("stretch2")

    def real(T, parent, child, stamp):
        m = TransformStamped()
        m.header.frame_id, m.child_frame_id, m.header.stamp = parent, child, stamp
        m.transform.translation.x, m.transform.translation.y, m.transform.translation.z = map(float, T[:3, 3])
        (m.transform.rotation.x, m.transform.rotation.y, m.transform.rotation.z,
         m.transform.rotation.w) = map(float, quat_of(T))
        return m

    T_fp_base = planar(0.12, 0.03, -0.05) @ mat([0, 0, 0.08], [0, 0, 0, 1])
    state = {"T_map_odom": planar(1.5, -0.5, 0.3), "T_odom_fp": planar(0.8, 0.4, -1.1)}
    params = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "stale_timeout_s": 60.0,
              "base_pose_source": "tf", "base_frame": "base_link", "robot_state_timeout_s": 1.0,
              "robot_state_rate_hz": 0.0}
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("monitor",)) as s:
        node = s.probe.node
        static_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub_static = node.create_publisher(TFMessage, "/tf_static", static_qos)
        pub_static.publish(TFMessage(transforms=[real(T_fp_base, "base_footprint", "base_link",
                                                      node.get_clock().now().to_msg())]))
        pub_tf = node.create_publisher(TFMessage, "/tf", 100)
        pub_js = node.create_publisher(JointState, "/joint_states", 10)
        got, lock = [], threading.Lock()

        def on_state(m):
            with lock:
                got.append((time.monotonic(), dict(zip(m.name, m.position))))
        sub = node.create_subscription(JointState, core.ROBOT_STATE_TOPIC, on_state, qos_profile_sensor_data)
        stop = threading.Event()
        q0 = np.array(robot.default_configuration(), float)

        def stream():
            while not stop.is_set():
                stamp = node.get_clock().now().to_msg()
                with lock:
                    T_mo, T_of = state["T_map_odom"], state["T_odom_fp"]
                pub_tf.publish(TFMessage(transforms=[real(T_of, "odom", "base_footprint", stamp)]))
                pub_tf.publish(TFMessage(transforms=[real(T_mo, "/map", "odom", stamp)]))
                pub_js.publish(cv.planning_joint_state(q0[3:], robot.joint_names[3:], stamp))
                time.sleep(0.05)
        th = threading.Thread(target=stream, daemon=True)
        th.start()

        def forwarded_after(t0, timeout=30.0):
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                with lock:
                    late = [v for t, v in got if t > t0]
                if late:
                    return late[-1]
                time.sleep(0.05)
            return None
        try:
            for T_map_odom, T_odom_fp in [(None, None), (planar(1.2, -0.3, 0.5), planar(1.4, 0.9, -0.6))]:
                if T_map_odom is not None:
                    with lock:
                        state["T_map_odom"], state["T_odom_fp"] = T_map_odom, T_odom_fp
                with lock:
                    want = xyyaw(state["T_map_odom"] @ state["T_odom_fp"] @ T_fp_base)
                time.sleep(0.3)  # the new transforms are on their way
                st = forwarded_after(time.monotonic(), timeout=20.0)
                assert st is not None, s.probe.statuses[-5:]
                got_b = np.array([st["base_x"], st["base_y"], st["base_theta"]])
                assert np.hypot(*(got_b[:2] - want[:2])) < 0.01 and abs(wrap(got_b[2] - want[2])) < 0.01, \
                    (got_b, want)
            # a target's pose in a tf frame the input_frames table has no transform for (base_footprint): forwarded
            # in the scene frame as the test's own matrices compose it
            from geometry_msgs.msg import PoseStamped

            seen = []
            sub_t = node.create_subscription(PoseStamped, core.target_topic("person_face"), seen.append,
                                             qos_profile_sensor_data)
            pub_t = node.create_publisher(PoseStamped, "/mocap/person_face/pose", qos_profile_sensor_data)
            T_fp_face = mat([0.9, -0.2, 1.5], [0.0, 0.0, 0.3826834, 0.9238795])
            try:
                for _ in range(200):
                    m = PoseStamped()
                    m.header.frame_id, m.header.stamp = "base_footprint", node.get_clock().now().to_msg()
                    m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, T_fp_face[:3, 3])
                    (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                     m.pose.orientation.w) = map(float, quat_of(T_fp_face))
                    pub_t.publish(m)
                    time.sleep(0.05)
                    if seen:
                        break
                assert seen, s.probe.statuses[-5:]
                with lock:
                    want_T = state["T_map_odom"] @ state["T_odom_fp"] @ T_fp_face
                f = seen[-1]
                got_T = mat([f.pose.position.x, f.pose.position.y, f.pose.position.z],
                            [f.pose.orientation.x, f.pose.orientation.y, f.pose.orientation.z, f.pose.orientation.w])
                assert f.header.frame_id == "map" and np.abs(got_T - want_T).max() < 1e-6, (got_T, want_T)
            finally:
                node.destroy_subscription(sub_t)
                node.destroy_publisher(pub_t)
            # relative names: the monitor's tf subscriptions are /tf and /tf_static; it publishes no transform
            mon = s.monitor.node
            subs = dict(mon.get_subscriber_names_and_types_by_node(mon.get_name(), mon.get_namespace()))
            pubs = dict(mon.get_publisher_names_and_types_by_node(mon.get_name(), mon.get_namespace()))
            assert subs.get("/tf") == ["tf2_msgs/msg/TFMessage"] and subs.get("/tf_static") == \
                ["tf2_msgs/msg/TFMessage"], subs
            assert "/tf" not in pubs and "/tf_static" not in pubs
        finally:
            stop.set()
            th.join(timeout=2.0)
            node.destroy_subscription(sub)
