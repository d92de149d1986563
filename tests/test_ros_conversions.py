"""psprm_ros.interfaces.conversions: validation of poses (finite, frame, age), /joint_states with URDF joint names ->
planning configuration, trajectory messages that follow the planned path, stop trajectories."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_ros.interfaces import conversions as cv  # noqa: E402


def test_pose_validation():
    m = cv.pose_stamped([1.0, 2.0, 3.0], [0, 0, 0, 2.0], "map", cv.sec_to_stamp(100.0))
    p, q = cv.validated_pose(m, "map", now_sec=100.5, max_age_s=1.0)
    assert np.allclose(p, [1, 2, 3]) and np.allclose(q, [0, 0, 0, 1])  # normalised
    assert cv.validated_pose(cv.pose_stamped([1, 2, 3], [0, 0, 0, 1], "/map"), "map")  # leading slash is fine
    with pytest.raises(cv.InputError, match="stale"):
        cv.validated_pose(m, "map", now_sec=102.0, max_age_s=1.0)
    with pytest.raises(cv.InputError, match="frame 'odom'"):
        cv.validated_pose(cv.pose_stamped([1, 2, 3], [0, 0, 0, 1], "odom"), "map")
    with pytest.raises(cv.InputError, match="frame ''"):
        cv.validated_pose(cv.pose_stamped([1, 2, 3], [0, 0, 0, 1], ""), "map")
    for bad in ([np.nan, 0, 0], [0, np.inf, 0]):
        with pytest.raises(cv.InputError, match="non-finite"):
            cv.validated_pose(cv.pose_stamped(bad, [0, 0, 0, 1], "map"), "map")
    with pytest.raises(cv.InputError, match="zero quaternion"):
        cv.validated_pose(cv.pose_stamped([0, 0, 0], [0, 0, 0, 0], "map"), "map")
    assert abs(cv.yaw_of(cv.yaw_quat(2.8)) - 2.8) < 1e-12


def test_joint_states_with_urdf_names_map_to_planning_joints(load_robot):
    from sensor_msgs.msg import JointState

    robot = load_robot("stretch2")
    msg = JointState()
    # what Stretch's driver publishes: the four telescoping arm joints, lift, wrist, head (plus wheels)
    msg.name = ["joint_lift", "joint_arm_l0", "joint_arm_l1", "joint_arm_l2", "joint_arm_l3", "joint_wrist_yaw",
                "joint_head_pan", "joint_head_tilt", "joint_left_wheel"]
    msg.position = [0.6, 0.05, 0.05, 0.05, 0.05, 1.0, -0.5, -0.2, 12.0]
    q, found = cv.joint_state_to_planning(msg, robot, base=np.array([1.0, 2.0, 0.5]))
    assert set(found) == set(robot.joint_names[3:])
    expect = dict(base_x=1.0, base_y=2.0, base_theta=0.5, joint_lift=0.6, arm_extension=0.2, joint_wrist_yaw=1.0,
                  joint_head_pan=-0.5, joint_head_tilt=-0.2)
    assert np.allclose(q, [expect[n] for n in robot.joint_names])
    # planning names (a simulator) are accepted too, base included
    sim = cv.planning_joint_state(q, robot.joint_names)
    q2, found2 = cv.joint_state_to_planning(sim, robot)
    assert np.allclose(q2, q) and set(found2) == set(robot.joint_names)
    msg.position[0] = float("nan")
    with pytest.raises(cv.InputError, match="non-finite"):
        cv.joint_state_to_planning(msg, robot)


def test_trajectory_message_follows_the_path_and_stops_at_rest(load_robot):
    from psprm_core.planning.timing import time_parameterize

    robot = load_robot("stretch2")
    q0 = robot.default_configuration()
    q0[:3] = [1.0, 1.0, 0.0]
    W = np.array([q0, q0 + [0, 0, 1.0, 0, 0, 0, 0, 0], q0 + [0.8 * np.cos(1.0), 0.8 * np.sin(1.0), 1.0, 0.1, 0, 0, 0,
                                                           0]])
    traj = time_parameterize(W, robot.velocity, robot.acceleration, dt=0.05, joint_names=robot.joint_names,
                             continuous_joints=[2], base_indices=(0, 1, 2), method="analytic")
    msg = cv.trajectory_to_msg(traj, robot.joint_names, "map", dt=0.5)
    P = cv.joint_trajectory_positions(msg, robot.joint_names)
    t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
    assert np.all(np.diff(t) > 0) and abs(t[-1] - traj.duration) < 1e-9
    assert np.allclose(P[0], W[0]) and np.allclose(P[-1], W[-1], atol=1e-9)
    # the rotate-then-drive corner is a published point, so linear interpolation never cuts it
    assert np.min(np.linalg.norm(P - W[1], axis=1)) < 1e-9
    assert np.allclose(msg.points[-1].velocities, 0.0)
    D = cv.densify_linear(P, 0.05)
    assert np.abs(np.diff(D, axis=0)).max() <= 0.05 + 1e-12 and np.allclose(D[-1], P[-1])
    stop = cv.stop_trajectory(q0, robot.joint_names, "map")
    assert len(stop.points) == 1 and np.allclose(stop.points[0].positions, q0)
    assert np.allclose(stop.points[0].velocities, 0.0)


def test_goal_candidates_round_trip(load_robot):
    robot = load_robot("stretch2")
    G = np.stack([robot.default_configuration(), robot.default_configuration() + 0.1])
    msg = cv.configs_to_joint_trajectory(G, robot.joint_names, "map")
    assert np.allclose(cv.joint_trajectory_positions(msg, robot.joint_names), G)
    msg.joint_names = msg.joint_names[:-1] + ["nope"]
    with pytest.raises(cv.InputError, match="missing joint"):
        cv.joint_trajectory_positions(msg, robot.joint_names)


def test_trajectory_prepended_with_the_measured_start_stays_within_the_limits(load_robot):
    """The server's published trajectory starts exactly at the measured state: a first point away from it gets a
    connecting move whose finite-difference velocities stay within every joint's limit."""
    robot = load_robot("stretch2")
    q0 = robot.default_configuration()
    q0[:3] = [1.0, 1.0, 0.2]
    first = q0.copy()
    first[robot.index("joint_head_pan")] += 0.8  # the planner re-aimed the head
    first[robot.index("joint_lift")] += 0.05
    P = np.array([first, first + 0.01])
    msg = cv.configs_to_joint_trajectory(P, robot.joint_names, "map")
    t_before = [cv.duration_to_sec(p.time_from_start) for p in msg.points]
    shift = cv.prepend_start(msg, q0, robot.velocity, robot.acceleration, [2])
    assert shift > 0 and len(msg.points) == 3
    assert np.allclose(msg.points[0].positions, q0) and cv.duration_to_sec(msg.points[0].time_from_start) == 0.0
    t_after = [cv.duration_to_sec(p.time_from_start) for p in msg.points[1:]]
    assert np.allclose(np.array(t_after) - t_before, shift)
    Q = cv.joint_trajectory_positions(msg, robot.joint_names)
    v = np.abs(Q[1] - Q[0]) / t_after[0]
    assert np.all(v <= robot.velocity + 1e-9)
    # a trajectory already at the start is left alone
    assert cv.prepend_start(msg, q0, robot.velocity, robot.acceleration, [2]) == 0.0 and len(msg.points) == 3


def test_trajectory_velocities_are_reordered_by_name_and_absent_when_a_point_lacks_them():
    """Velocities come back in the order asked for (the message's own order is another), None when a point carries
    none, an error when one is not finite."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    m = JointTrajectory()
    m.joint_names = ["b", "a", "c"]
    m.points = [JointTrajectoryPoint(positions=[1.0, 2.0, 3.0], velocities=[0.1, 0.2, 0.3]),
                JointTrajectoryPoint(positions=[4.0, 5.0, 6.0], velocities=[0.4, 0.5, 0.6])]
    assert np.array_equal(cv.joint_trajectory_velocities(m, ["a", "b", "c"]), [[0.2, 0.1, 0.3], [0.5, 0.4, 0.6]])
    assert np.array_equal(cv.joint_trajectory_positions(m, ["c", "a"]), [[3.0, 2.0], [6.0, 5.0]])
    m.points[1].velocities = []
    assert cv.joint_trajectory_velocities(m, ["a", "b", "c"]) is None
    m.points[1].velocities = [0.4, float("nan"), 0.6]
    with pytest.raises(cv.InputError, match="velocities"):
        cv.joint_trajectory_velocities(m, ["a", "b", "c"])
