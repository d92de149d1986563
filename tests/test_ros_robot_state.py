"""Robot state and frames, in process with real rclpy: nothing is planned without a fresh base pose (odometry or a
mocap body on the base), a pose in ``world`` with a ``world -> map`` transform parameter is used (the forwarded pose
is checked against the test's own matrix product), a pose in an unknown frame is dropped with a warning."""

from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros.core import resolve_scene  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

N_NODES = 500
BASE = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "roadmap.n_nodes": N_NODES, "seed": 0,
        "stale_timeout_s": 60.0, "publish_markers": False}


def matrix(p, q) -> np.ndarray:
    return cv.compose(np.asarray(p, float)[None], np.asarray(q, float)[None])[0]


def yaw_matrix(x, y, z, yaw) -> np.ndarray:
    return matrix([x, y, z], cv.yaw_quat(yaw))


def start_q(robot, scene):
    from psprm_core.planning.factory import problem_configurations

    return problem_configurations(robot, scene, scene.problem("south_to_either"))[0]


def _subscribe(node, msg_type, topic, qos=10):
    got, lock = [], threading.Lock()

    def cb(m):
        with lock:
            got.append((time.perf_counter(), m))
    sub = node.create_subscription(msg_type, topic, cb, qos)
    return got, sub


def test_no_plan_without_a_fresh_base_pose(load_robot):
    """/joint_states alone: the goal gives no trajectory and "waiting for base pose"; odometry arriving gives the
    plan; odometry stopping (joints still live) blocks the next plan again."""
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    params = dict(BASE, input_frames=["odom"], robot_state_timeout_s=0.5)
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        assert s.probe.wait_subscribers("/psprm/goal_regions")
        q = start_q(robot, scene)
        from diagnostic_msgs.msg import DiagnosticArray

        diags, dsub = _subscribe(s.probe.node, DiagnosticArray, "/diagnostics")
        state = s.probe.hold_robot_state(q, robot.joint_names)
        state.pub_odom_saved, state.pub_odom = state.pub_odom, _Null()  # joints only
        try:
            t0 = time.perf_counter()
            n0 = len(s.probe.trajectories)
            s.probe.publish_regions(["at_cabinet"])
            assert s.probe.wait_status("waiting for base pose", t0, timeout=10, level="warning")
            time.sleep(1.0)
            assert len(s.probe.trajectories) == n0, "a trajectory was planned without a base pose"

            def diag(name, needle):
                for t, m in reversed(diags):
                    for st in m.status:
                        if st.name == f"psprm: /{name}" and needle in st.message and t > t0:
                            return st
                return None
            st = s.probe.wait_for(lambda: diag("roadmap_server", "waiting for base pose"), 5)
            assert st is not None and st.level == bytes([1])  # WARN on /diagnostics too
            assert {kv.key: kv.value for kv in st.values}["lifecycle"] == "active"
            assert s.probe.wait_for(lambda: diag("replan_monitor", "waiting for base pose"), 5)
            state.pub_odom = state.pub_odom_saved  # odometry now arrives
            msg = s.probe.wait_trajectory(n0, 30)
            assert msg is not None and len(msg.points) > 1
            P = cv.joint_trajectory_positions(msg, robot.joint_names)
            assert np.allclose(P[0], q, atol=1e-6)  # starts at the measured state (base from the odometry)
            # the base pose goes stale; the joints keep coming
            state.pub_odom = _Null()
            time.sleep(1.2)
            t1 = time.perf_counter()
            n1 = len(s.probe.trajectories)
            s.probe.publish_regions(["at_shelf"])
            assert s.probe.wait_status("waiting for base pose", t1, timeout=10, level="warning")
            time.sleep(1.0)
            assert len(s.probe.trajectories) == n1
        finally:
            state.stop()
            s.probe.node.destroy_subscription(dsub)


class _Null:
    def publish(self, msg):
        pass


def test_world_pose_is_transformed_into_the_map_and_an_unknown_frame_is_dropped(load_robot):
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import qos_profile_sensor_data

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    T_map_world = yaw_matrix(1.5, -0.5, 0.1, math.pi / 2)  # the mocap frame's pose in the map
    wq = cv.matrices_to_quats(T_map_world[None, :3, :3])[0]
    params = dict(BASE, input_frames=["world"], **{"input_frame.world.xyz": T_map_world[:3, 3].tolist(),
                                                   "input_frame.world.quat": wq.tolist()},
                  relay_deadband_m=0.0, relay_deadband_rad=0.0)
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("monitor",)) as s:
        assert s.probe.wait_subscribers("/mocap/person_face/pose")
        got, sub = _subscribe(s.probe.node, PoseStamped, "/psprm/state/targets/person_face", qos_profile_sensor_data)
        _wait_active(s.monitor)
        face = scene.target("person_face")
        T_map_face = matrix(face.center, face.quat)
        T_world_face = np.linalg.inv(T_map_world) @ T_map_face  # what vrpn_mocap would stream
        p_w = T_world_face[:3, 3]
        q_w = cv.matrices_to_quats(T_world_face[None, :3, :3])[0]
        t0 = time.perf_counter()
        for _ in range(5):
            s.probe.publish_pose("person_face", p_w, q_w, frame="world")
            time.sleep(0.05)
        assert s.probe.wait_for(lambda: got, 5), "the world pose was not forwarded"
        m = got[-1][1]
        assert m.header.frame_id == "map"
        T = cv.pose_to_matrix(m.pose)
        assert np.allclose(T[:3, 3], face.center, atol=1e-6) and np.allclose(T[:3, :3], T_map_face[:3, :3], atol=1e-6)
        n = len(got)
        s.probe.publish_pose("person_face", p_w, q_w, frame="vicon")
        assert s.probe.wait_status("frame 'vicon'", t0, timeout=5, level="warning")
        time.sleep(0.3)
        assert len(got) == n, "a pose in an unknown frame was forwarded"
        s.probe.node.destroy_subscription(sub)


def _wait_active(owner, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not owner.active:
        time.sleep(0.05)
    assert owner.active


def test_base_pose_from_a_mocap_body_with_its_offset(load_robot):
    """base_pose_source pose: the robot's rigid body in ``world`` (offset 0.2 m behind base_link, 0.3 m up); the
    forwarded robot state's base is the test's own composition T_map_world T_world_body T_body_base."""
    from sensor_msgs.msg import JointState
    from rclpy.qos import qos_profile_sensor_data

    robot = load_robot("stretch2")
    T_map_world = yaw_matrix(0.5, 0.25, 0.0, -0.3)
    wq = cv.matrices_to_quats(T_map_world[None, :3, :3])[0]
    T_body_base = yaw_matrix(0.2, 0.0, -0.3, 0.0)
    params = dict(BASE, input_frames=["world"], base_pose_source="pose", robot_pose_topic="/mocap/robot/pose",
                  **{"input_frame.world.xyz": T_map_world[:3, 3].tolist(), "input_frame.world.quat": wq.tolist(),
                     "base_body_offset.xyz": T_body_base[:3, 3].tolist(), "base_body_offset.quat": [0, 0, 0, 1]})
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("monitor",)) as s:
        got, sub = _subscribe(s.probe.node, JointState, "/psprm/state/robot", qos_profile_sensor_data)
        _wait_active(s.monitor)
        T_map_base = yaw_matrix(3.0, 1.0, 0.0, 1.1)
        T_world_body = np.linalg.inv(T_map_world) @ T_map_base @ np.linalg.inv(T_body_base)
        q = robot.default_configuration()
        state = s.probe.hold_robot_state(q, robot.joint_names)
        state.pub_odom = _Null()
        try:
            for _ in range(20):
                s.probe.publish_pose("robot", T_world_body[:3, 3],
                                     cv.matrices_to_quats(T_world_body[None, :3, :3])[0], frame="world",
                                     topic="/mocap/robot/pose")
                time.sleep(0.05)
            assert s.probe.wait_for(lambda: got, 5), s.probe.statuses[-3:]
            m = got[-1][1]
            base = [m.position[list(m.name).index(n)] for n in ("base_x", "base_y", "base_theta")]
            assert np.allclose(base[:2], [3.0, 1.0], atol=1e-6)
            assert abs(math.remainder(base[2] - 1.1, 2 * math.pi)) < 1e-6
        finally:
            state.stop()
            s.probe.node.destroy_subscription(sub)


@pytest.mark.parametrize("params_file", ["dynamic_person.yaml", "fetchlike_nursing.yaml",
                                         "ur5_mobile_blind_spot_alley.yaml"])
def test_params_files_of_the_three_robots_configure_every_node(params_file, load_robot):
    """Each shipped params file: all nodes are constructed from it; the monitor, the adapter (topic interface)
    and sim_robot configure and activate; the server and scorer take its parameters (the roadmap build itself is
    the server's configure, covered elsewhere)."""
    from psprm_ros.core import autostart

    path = ROOT / "config" / "ros" / params_file
    with InProcessSuite({"interface": "topic"}, domain_id=claim_domain_id(), params_file=str(path),
                        nodes=("server", "scorer", "monitor", "adapter", "sim"), autostart=False) as s:
        robot = load_robot(s.server.robot_name)
        assert s.monitor.robot.name == s.adapter.robot.name == s.sim.robot.name == robot.name
        for owner in (s.monitor, s.adapter):
            assert autostart(owner), s.probe.statuses[-3:]
        assert s.adapter.cfg.robot == robot.name
        scene = load_scene(resolve_scene(s.server.p["scene"]))
        assert scene.robot == robot.name or s.server.p["robot"] == robot.name
        for t in s.server.p["targets"]:
            scene.target(t)
        # the simulated robot reports, the adapter measures the robot from /joint_states + /odom
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and s.adapter.measured()[0] is None:
            time.sleep(0.1)
        q, why = s.adapter.measured()
        assert q is not None, why
        d = q - s.sim.q
        d[2] = np.remainder(d[2] + np.pi, 2 * np.pi) - np.pi  # a heading of pi may come back as -pi
        assert np.abs(d).max() < 0.05


def test_sim_robot_mocap_pose_of_its_base(load_robot):
    """sim_robot's optional mocap pose: a body 0.2 m behind and 0.3 m above base_link, in ``world`` (the map's pose
    in world: 1 m east, turned 90 deg); the test recomputes it from the robot's own /odom (odom = map)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data

    T_map_world = yaw_matrix(1.0, 0.0, 0.0, math.pi / 2)
    wq = cv.matrices_to_quats(T_map_world[None, :3, :3])[0]
    T_body_base = yaw_matrix(0.2, 0.0, -0.3, 0.0)
    params = {"scene": "dynamic_person", "mocap_topic": "/mocap/robot/pose", "mocap_frame": "world",
              "mocap_world.xyz": T_map_world[:3, 3].tolist(), "mocap_world.quat": wq.tolist(),
              "mocap_body_offset.xyz": T_body_base[:3, 3].tolist(), "initial_base": [2.0, 1.5, 0.7]}
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("sim",)) as s:
        mocap, s1 = _subscribe(s.probe.node, PoseStamped, "/mocap/robot/pose", qos_profile_sensor_data)
        odom, s2 = _subscribe(s.probe.node, Odometry, "/odom")
        assert s.probe.wait_for(lambda: mocap and odom, 10)
        m = mocap[-1][1]
        o = odom[-1][1]
        assert m.header.frame_id == "world" and o.header.frame_id == "odom"
        T_map_base = cv.pose_to_matrix(o.pose.pose)
        expect = np.linalg.inv(T_map_world) @ T_map_base @ np.linalg.inv(T_body_base)
        T = cv.pose_to_matrix(m.pose)
        assert np.allclose(T, expect, atol=1e-6)
        assert np.allclose(T_map_base[:2, 3], [2.0, 1.5], atol=1e-6)
        s.probe.node.destroy_subscription(s1)
        s.probe.node.destroy_subscription(s2)


def test_the_forwarded_robot_state_carries_the_odometry_velocity_of_the_base(load_robot):
    """The monitor forwards the base's measured velocity with its pose (the roadmap server's braking model uses the
    odometry the adapter uses): base_x / base_y / base_theta velocities are the scene-frame rates of the twist the
    test publishes at the heading it publishes, the other joints' velocities are not measured (NaN); an odometry
    with a non-finite twist forwards no velocity."""
    from sensor_msgs.msg import JointState

    from psprm_ros import core

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    with InProcessSuite(dict(BASE, input_frames=["odom"]), domain_id=claim_domain_id(), nodes=("monitor",)) as s:
        q = start_q(robot, scene)
        q[2] = 0.7
        from rclpy.qos import qos_profile_sensor_data

        got, sub = _subscribe(s.probe.node, JointState, "/" + core.ROBOT_STATE_TOPIC, qos=qos_profile_sensor_data)
        state = s.probe.hold_robot_state(q, robot.joint_names)
        state.twist = (0.3, -0.2)
        try:
            last = s.probe.wait_for(lambda: next((m for _, m in reversed(got) if len(m.velocity)), None), 20)
            assert last is not None, "no robot state with velocities"
            vel = dict(zip(last.name, last.velocity))
            assert vel["base_x"] == pytest.approx(0.3 * math.cos(0.7), abs=1e-9)
            assert vel["base_y"] == pytest.approx(0.3 * math.sin(0.7), abs=1e-9)
            assert vel["base_theta"] == pytest.approx(-0.2, abs=1e-9)
            assert all(math.isnan(vel[n]) for n in robot.joint_names[3:])
            assert cv.base_velocity_of(last, 0.7) == pytest.approx([0.3, -0.2], abs=1e-9)
            state.twist = (float("nan"), 0.0)
            t0 = time.perf_counter()
            later = s.probe.wait_for(lambda: [m for t, m in got if t > t0 + 0.3], 10)
            assert later and all(len(m.velocity) == 0 for m in later)
        finally:
            state.stop()
            s.probe.node.destroy_subscription(sub)
