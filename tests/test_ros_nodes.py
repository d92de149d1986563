"""ROS 2 node suite, in process: the three nodes on their own executors, poses and goals published like a mocap
system, a standing robot's /joint_states and /odom published by the test, trajectories received and checked against
the poses the test itself sent (collision-free, target in view), replans after the target turns and after an
obstacle moves into the path (a path around it, never a stop in its place), bad input answered with warnings."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_core.collision import CollisionChecker  # noqa: E402
from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

N_NODES = 500
PARAMS = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "roadmap.n_nodes": N_NODES, "seed": 0,
          "stale_timeout_s": 60.0, "publish_markers": True, "rescore_rate_hz": 5.0, "markers_period_s": 0.5,
          "input_frames": ["odom"]}


class Sent:
    """The test's own record of the poses it published (what every collision judgement here is built from)."""

    def __init__(self, scene):
        self.scene = scene

    def publish(self, suite, body, position, quat):
        t = suite.probe.publish_pose(body, position, quat)
        if body in self.scene.target_names:
            self.scene = self.scene.with_target_pose(body, np.asarray(position, float), np.asarray(quat, float))
        else:
            self.scene = self.scene.with_obstacle_pose(body, np.asarray(position, float), np.asarray(quat, float))
        return t


def start_configuration(robot, scene):
    from psprm_core.planning.factory import problem_configurations

    return problem_configurations(robot, scene, scene.problem("south_to_either"))[0]


def yaw_q(yaw: float) -> np.ndarray:
    return cv.yaw_quat(yaw)


@pytest.fixture(scope="module")
def suite(load_robot):
    with InProcessSuite(PARAMS, domain_id=claim_domain_id()) as s:
        assert s.server.ready.wait(180), "roadmap not ready"
        assert s.probe.wait_subscribers("/mocap/person_face/pose")
        scene = load_scene(resolve_named("scene", "dynamic_person"))
        robot = load_robot("stretch2")
        s.state = s.probe.hold_robot_state(start_configuration(robot, scene), robot.joint_names)
        s.sent = Sent(scene)
        yield s
        s.state.stop()


@pytest.fixture(scope="module")
def world(load_robot):
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    return scene, load_robot("stretch2")


def traj_positions(msg, names) -> np.ndarray:
    P = cv.joint_trajectory_positions(msg, names)
    if len(P) > 1:  # midpoints too: consecutive samples are at most a few cm apart
        P = np.vstack([P, 0.5 * (P[1:] + P[:-1])])
    return P


def traj_positions_of(P: np.ndarray) -> np.ndarray:
    """Positions (M, dof) with their midpoints."""
    return np.vstack([P, 0.5 * (P[1:] + P[:-1])]) if len(P) > 1 else P


def collides(robot, scene, P) -> np.ndarray:
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    return checker.check(torch.as_tensor(P, dtype=torch.float32)).numpy()


def in_view_fraction(robot, scene, P, target="person_face") -> float:
    T = robot.camera_poses(torch.as_tensor(P, dtype=torch.float32)).double().numpy()
    c = scene.target(target).center
    pc = np.einsum("nji,nj->ni", T[:, :3, :3], c - T[:, :3, 3])
    intr = robot.config.intrinsics
    z = pc[:, 2]
    ok = (z > 0.1) & (np.abs(pc[:, 0]) <= intr.tan_half_h * z) & (np.abs(pc[:, 1]) <= intr.tan_half_v * z)
    return float(ok.mean())


def next_plan(s, n_before: int, timeout: float = 60.0):
    msg = s.probe.wait_trajectory(n_before, timeout)
    assert msg is not None, f"no trajectory; statuses: {[x[2] for x in s.probe.statuses[-8:]]}"
    return msg


def settle(s, quiet_s: float = 2.5, limit_s: float = 30.0) -> None:
    """Wait until the server has published no plan information and no trajectory for ``quiet_s`` (a replan asked
    for by an earlier pose, still under way, would otherwise replace the trajectory a test reads)."""
    deadline = time.perf_counter() + limit_s
    while time.perf_counter() < deadline:
        stamps = [tt for tt, _ in s.probe.infos] + [tt for tt, _ in s.probe.trajectories]
        if not stamps or time.perf_counter() - max(stamps) >= quiet_s:
            return
        time.sleep(0.1)


def test_goal_and_target_give_a_safe_trajectory_that_keeps_the_target_in_view(suite, world):
    scene, robot = world
    face = scene.target("person_face")
    n0 = len(suite.probe.trajectories)
    suite.sent.publish(suite, "person_face", face.center, face.quat)
    suite.probe.publish_regions(["at_shelf", "at_cabinet"])
    msg = next_plan(suite, n0)
    assert list(msg.joint_names) == robot.joint_names and msg.header.frame_id == "map"
    assert len(msg.points) > 10
    t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
    assert np.all(np.diff(t) > 0) and np.allclose(msg.points[-1].velocities, 0.0)
    P = traj_positions(msg, robot.joint_names)
    assert not collides(robot, suite.sent.scene, P).any()
    assert in_view_fraction(robot, scene, cv.joint_trajectory_positions(msg, robot.joint_names)) >= 0.8
    # the planned base route as nav_msgs/Path: the trajectory's base poses
    from nav_msgs.msg import Path as PathMsg
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    paths = []
    q = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    sub = suite.probe.node.create_subscription(PathMsg, "/psprm/base_path", paths.append, q)
    try:
        assert suite.probe.wait_for(lambda: paths, 5)
        B = cv.joint_trajectory_positions(suite.probe.trajectories[-1][1], robot.joint_names)[:, :3]
        xy = np.array([[p.pose.position.x, p.pose.position.y] for p in paths[-1].poses])
        yaw = np.array([cv.yaw_of([p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                                   p.pose.orientation.w]) for p in paths[-1].poses])
        assert paths[-1].header.frame_id == "map" and xy.shape == (len(B), 2)
        assert np.allclose(xy, B[:, :2], atol=1e-6)
        assert np.allclose(np.remainder(yaw - B[:, 2] + np.pi, 2 * np.pi) - np.pi, 0.0, atol=1e-6)
    finally:
        suite.probe.node.destroy_subscription(sub)
    # the perception scorer re-scores the roadmap and the path
    assert suite.probe.wait_for(lambda: suite.probe.path_scores, 20)


def test_turning_target_gives_a_replanned_trajectory(suite, world):
    scene, robot = world
    face, body = scene.target("person_face"), scene.obstacle("person_body")
    if not suite.probe.trajectories:
        test_goal_and_target_give_a_safe_trajectory_that_keeps_the_target_in_view(suite, world)
    n0 = len(suite.probe.trajectories)
    yaw = 0.3  # the person turns from west-south-west towards the cabinet (east)
    c = body.center[:2]
    face_c = np.r_[c + 0.06 * np.array([np.cos(yaw), np.sin(yaw)]), face.center[2]]
    t_pub = suite.sent.publish(suite, "person_face", face_c, yaw_q(yaw))
    suite.sent.publish(suite, "person_body", body.center, yaw_q(yaw))
    msg = next_plan(suite, n0)
    info = suite.probe.wait_for(lambda: [i for t, i in suite.probe.infos if t >= t_pub and "success" in i], 10)
    assert info and any("target" in r for r in info[0]["reasons"]), info
    turned = suite.sent.scene
    P = traj_positions(msg, robot.joint_names)
    assert not collides(robot, turned, P).any()
    assert in_view_fraction(robot, turned, cv.joint_trajectory_positions(msg, robot.joint_names)) >= 0.8


def test_obstacle_moved_into_the_path_gives_a_trajectory_around_it(suite, world):
    scene, robot = world
    if not suite.probe.trajectories:
        test_goal_and_target_give_a_safe_trajectory_that_keeps_the_target_in_view(suite, world)
    time.sleep(0.5)
    n0 = len(suite.probe.trajectories)
    old = suite.probe.trajectories[-1][1]
    P_old = cv.joint_trajectory_positions(old, robot.joint_names)
    # a point of the current base path at least 1.2 m from its start and end, away from the person
    xy = P_old[:, :2]
    d_ends = np.minimum(np.linalg.norm(xy - xy[0], axis=1), np.linalg.norm(xy - xy[-1], axis=1))
    cand = np.nonzero(d_ends > 1.2)[0]
    assert len(cand), "path too short for this test"
    k = cand[len(cand) // 2]
    box = scene.obstacle("person_body")
    center = np.array([xy[k, 0], xy[k, 1], box.center[2]])
    suite.sent.publish(suite, "person_body", center, box.quat)
    blocked = suite.sent.scene
    assert collides(robot, blocked, P_old).any(), "the moved obstacle must block the old path"
    msg = next_plan(suite, n0)
    P = traj_positions(msg, robot.joint_names)
    assert not collides(robot, blocked, P).any()
    # a path around the obstacle (there is one: the room is open on both sides of it), not a stop
    assert len(msg.points) > 1, "a stop trajectory was published instead of a path around the obstacle"
    assert np.linalg.norm(P[:, :2] - center[:2], axis=1).min() > 0.2
    goals = core_goals(robot, scene, ["at_shelf", "at_cabinet"])
    end = cv.joint_trajectory_positions(msg, robot.joint_names)[-1]
    assert np.min(np.linalg.norm(goals[:, :2] - end[:2], axis=1)) < 0.2, "the detour does not reach a goal"
    # put the person back where the scene has it
    suite.sent.publish(suite, "person_body", box.center, box.quat)


def test_obstacle_moved_into_the_path_just_ahead_stops_the_robot_before_the_replan(suite, world):
    """The stop guard: a body pose that collides with the next stop_horizon_s (1.5 s) of the trajectory being
    executed is answered by a stop at once, before the planner's replan. The test reads the trajectory under way and
    puts the body just ahead on it; when the server replaced that trajectory before the pose reached it (a replan
    the monitor asked for), the test puts the body back and tries again (at most three times): only a stop by the
    guard passes."""
    scene, robot = world
    box = scene.obstacle("person_body")

    def guard_stop(t_pub):
        return [(tt, i) for tt, i in suite.probe.infos
                if tt >= t_pub and i.get("stop") and "person_body" in i.get("stop_reason", "")]

    try:
        for attempt in range(3):
            settle(suite)  # the trajectory read below is the one under way when the pose arrives
            if not suite.probe.trajectories or len(suite.probe.trajectories[-1][1].points) < 20:
                n0 = len(suite.probe.trajectories)
                suite.probe.publish_regions(["at_shelf", "at_cabinet"])
                next_plan(suite, n0)
                settle(suite)
            t_read = time.perf_counter()
            msg = suite.probe.trajectories[-1][1]
            P = cv.joint_trajectory_positions(msg, robot.joint_names)
            t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
            near = P[t <= 1.0]  # well inside the horizon (the robot is held at the trajectory's start)
            here = suite.sent.scene
            spot = None
            # a spot on the path, else around the robot (the first second may be a turn in place: the arm sweeps),
            # whose body blocks the next second of the motion but does not touch the robot where it stands
            around = [P[0, :2] + r * np.array([np.cos(a), np.sin(a)]) for r in (0.4, 0.6, 0.8, 1.0)
                      for a in np.linspace(-np.pi, np.pi, 24, endpoint=False)]
            for xy in list(P[1:len(near) + 5, :2]) + around:
                trial = here.with_obstacle_pose("person_body", np.r_[xy, box.center[2]], box.quat)
                if collides(robot, trial, traj_positions_of(near)).any() and not collides(robot, trial, P[:1]).any():
                    spot = np.r_[xy, box.center[2]]
                    break
            assert spot is not None, "no spot just ahead of the robot for this test"
            n0 = len(suite.probe.trajectories)
            t_pub = suite.sent.publish(suite, "person_body", spot, box.quat)
            # the body stands there, streamed as mocap does, until the guard's stop arrives
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not guard_stop(t_pub):
                suite.probe.publish_pose("person_body", spot, box.quat)
                time.sleep(0.03)
            got = guard_stop(t_pub)
            if got:
                break
            replaced = [tt for tt, m in suite.probe.trajectories if t_read <= tt < t_pub + 1.0 and len(m.points) > 1]
            assert replaced and attempt < 2, \
                f"no stop: {[i for tt, i in suite.probe.infos if tt >= t_pub][:3]}"
            suite.sent.publish(suite, "person_body", box.center, box.quat)
        t_stop = got[0][0]
        assert t_stop - t_pub < 1.0, f"stop {t_stop - t_pub:.2f} s after the pose"
        stops = [m for tt, m in suite.probe.trajectories[n0:] if len(m.points) == 1 and tt >= t_stop - 0.05]
        assert stops and np.allclose(stops[0].points[0].velocities, 0.0)
        assert np.allclose(cv.joint_trajectory_positions(stops[0], robot.joint_names)[0], P[0], atol=1e-3)
        # then the replan the guard asked for: clear of the body where it now stands (as is every trajectory
        # that went out after the pose had reached the server)
        replan = suite.probe.wait_for(lambda: [i for tt, i in suite.probe.infos if tt > t_stop and any(
            "stopped: obstacle person_body" in r for r in i.get("reasons", []))], 60)
        assert replan, f"no replan after the stop: {[i for tt, i in suite.probe.infos if tt > t_stop][:3]}"
        later = [m for tt, m in suite.probe.trajectories[n0:] if tt > t_stop and len(m.points) > 1]
        for m in later:
            assert not collides(robot, suite.sent.scene, traj_positions(m, robot.joint_names)).any()
    finally:
        suite.sent.publish(suite, "person_body", box.center, box.quat)


def core_goals(robot, scene, names):
    from psprm_ros import core

    return core.goal_region_configurations(robot, scene, names)


def test_nan_and_unknown_frame_poses_warn_and_the_suite_keeps_serving(suite, world):
    scene, robot = world
    face = scene.target("person_face")
    t0 = time.perf_counter()
    suite.probe.publish_pose("person_face", [np.nan, 3.2, 1.6], face.quat)
    assert suite.probe.wait_status("non-finite", t0, level="warning"), suite.probe.statuses[-5:]
    suite.probe.publish_pose("person_face", face.center, face.quat, frame="camera_link")
    assert suite.probe.wait_status("frame 'camera_link'", t0, level="warning")
    suite.probe.publish_pose("person_face", face.center, [0.0, 0.0, 0.0, 0.0])
    assert suite.probe.wait_status("zero quaternion", t0, level="warning")
    suite.probe.publish_goal(1.05, 3.2, np.inf)
    assert suite.probe.wait_status("goal: non-finite", t0, level="warning")
    # a goal inside the shelf is refused before it reaches the planner
    suite.probe.publish_goal(0.25, 3.2, np.pi)
    assert suite.probe.wait_status("in collision", t0, level="warning")
    # still serving: a valid goal gives a new, safe trajectory
    n0 = len(suite.probe.trajectories)
    suite.probe.publish_goal(6.9, 3.2, 0.0)
    msg = next_plan(suite, n0)
    assert len(msg.points) >= 1
    assert not collides(robot, suite.sent.scene, traj_positions(msg, robot.joint_names)).any()


def test_stale_obstacle_stops_the_robot(load_robot):
    """A separate suite whose monitor times out fast: the obstacle goes silent -> stop trajectory + warning."""
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    params = dict(PARAMS, stale_timeout_s=0.4, publish_markers=False)
    with InProcessSuite(params, domain_id=claim_domain_id(), nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        assert s.probe.wait_subscribers("/mocap/person_body/pose")
        robot = load_robot("stretch2")
        state = s.probe.hold_robot_state(start_configuration(robot, scene), robot.joint_names)
        body = scene.obstacle("person_body")
        n0 = len(s.probe.trajectories)
        s.probe.publish_regions(["at_cabinet"])
        assert next_plan(s, n0) is not None
        t0 = time.perf_counter()
        s.probe.publish_pose("person_body", body.center, body.quat)  # once, then silence
        assert s.probe.wait_status("stale", t0, timeout=10, level="warning")
        stop = s.probe.wait_for(lambda: [m for t, m in s.probe.trajectories if t > t0 and len(m.points) == 1], 10)
        assert stop, "no stop trajectory"
        assert np.allclose(stop[0].points[0].velocities, 0.0)
        # the stop a joint_trajectory_controller accepts: stamp 0 (start now), its point in the future
        assert cv.stamp_to_sec(stop[0].header.stamp) == 0.0
        assert cv.duration_to_sec(stop[0].points[0].time_from_start) > 0.0
        state.stop()


def test_the_monitor_forgives_its_own_stall_but_stops_when_the_obstacle_stream_stops(load_robot):
    """The person's body streamed at 120 Hz by ``mocap_replay`` in its own process (as a mocap system is: it does not
    wait for this one). A stall of the monitor's own process (every thread of it stopped for longer than
    ``stale_timeout_s``) leaves the body's poses waiting in its queue: no stale warning, no stop. When the stream
    really stops (the replay's process frozen), the server publishes a stop within ``stale_timeout_s`` and a few
    watchdog periods of the last pose. Judged from the test's own record of the stream and of the trajectories."""
    import os
    import signal
    import subprocess

    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import qos_profile_sensor_data
    from stalls import freeze_this_process

    from psprm_core.paths import config_dir

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    stale = 0.4
    params = dict(PARAMS, stale_timeout_s=stale, publish_markers=False)
    domain = claim_domain_id()
    with InProcessSuite(params, domain_id=domain, nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        robot = load_robot("stretch2")
        state = s.probe.hold_robot_state(start_configuration(robot, scene), robot.joint_names)
        seen = []  # the test's own record of the stream: receipt times
        s.probe.node.create_subscription(PoseStamped, "/mocap/person_body/pose",
                                         lambda m: seen.append(time.perf_counter()), qos_profile_sensor_data)
        root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1",
                   PYTHONPATH=f"{root}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
        replay = subprocess.Popen([sys.executable, "-m", "psprm_ros.mocap_replay",
                                   str(config_dir() / "recordings" / "person_turning.csv"), "--loop", "--bodies",
                                   "person_body", "--wait-subscribers", "20"], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            assert s.probe.wait_for(lambda: len(seen) > 120, 30), "no stream from mocap_replay"
            n0 = len(s.probe.trajectories)
            s.probe.publish_regions(["at_cabinet"])
            assert next_plan(s, n0) is not None
            time.sleep(1.0)
            t_stall = time.perf_counter()
            assert freeze_this_process(stale + 0.4) > stale
            time.sleep(1.0)
            assert not [x for x in s.probe.statuses if x[0] >= t_stall and "person_body stale" in x[2]], \
                "the monitor called the body stale after its own stall"
            assert not [m for t, m in s.probe.trajectories if t >= t_stall and len(m.points) == 1], "stopped"
            # the stream stops for real
            os.killpg(replay.pid, signal.SIGSTOP)
            try:
                time.sleep(stale + 1.5)
                last = seen[-1]
                stops = [t for t, m in s.probe.trajectories if t > last and len(m.points) == 1]
            finally:
                os.killpg(replay.pid, signal.SIGCONT)
            assert stops, "no stop after the obstacle's stream stopped"
            period = 1.0 / s.monitor.p["check_rate_hz"]
            assert stops[0] - last <= stale + 3 * period + 0.3, stops[0] - last
        finally:
            state.stop()
            os.killpg(replay.pid, signal.SIGTERM)
            replay.wait(15)


def test_server_keeps_the_last_safe_trajectory_when_a_goal_cannot_be_reached(suite, world):
    """Goal candidates straight to the server (past the monitor's collision filter), all inside the shelf: the
    planner fails, the server warns and keeps the last trajectory, which is still collision-free."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from trajectory_msgs.msg import JointTrajectory

    scene, robot = world
    if not suite.probe.trajectories:
        test_goal_and_target_give_a_safe_trajectory_that_keeps_the_target_in_view(suite, world)
    time.sleep(0.5)
    n0 = len(suite.probe.trajectories)
    q = robot.configuration({"base_x": 0.25, "base_y": 3.2, "base_theta": np.pi})
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = suite.probe.node.create_publisher(JointTrajectory, "/psprm/state/goals", latched)
    assert suite.probe.wait_subscribers("/psprm/state/goals")
    t0 = time.perf_counter()
    pub.publish(cv.configs_to_joint_trajectory(q[None], robot.joint_names, "map"))
    assert suite.probe.wait_status("planning failed", t0, timeout=30, level="warning")
    assert suite.probe.wait_status("keeping the last safe trajectory", t0, timeout=10, level="warning")
    t_kept = min(t for t, _, text in suite.probe.statuses if t >= t0 and "keeping the last safe trajectory" in text)
    time.sleep(0.3)
    # nothing for the unreachable goal: a trajectory received meanwhile can only be a replan of the earlier goals that
    # was in flight when the goal was sent (it ends elsewhere, free of the test's obstacles), and none comes after
    # the server said it keeps the last one
    for t, msg in suite.probe.trajectories[n0:]:
        P = traj_positions(msg, robot.joint_names)
        assert np.linalg.norm(P[-1, :2] - q[:2]) > 0.3 and not collides(robot, suite.sent.scene, P).any()
        assert t < t_kept


def test_roadmap_markers_match_the_roadmap_also_after_it_grew(suite, world):
    """The roadmap markers (built off the planning thread) show every valid roadmap node, one colour each, and are
    rebuilt with new camera poses when the roadmap grows (a repair adds nodes after query nodes)."""
    from visualization_msgs.msg import MarkerArray

    scene, _ = world
    got = []
    sub = suite.probe.node.create_subscription(MarkerArray, "/roadmap_server/markers", got.append, 10)
    try:
        pl = suite.server.planner

        def roadmap_marker(n_valid):
            for m in reversed(got):
                nodes = [x for x in m.markers if x.ns == "roadmap_nodes"]
                if nodes and len(nodes[0].points) == n_valid:
                    return nodes[0], [x for x in m.markers if x.ns == "roadmap_edges"][0]
            return None

        face = scene.target("person_face")

        def republished(n_valid):  # mark the markers stale and give the worker a cycle (a keep-alive pose)
            suite.server._markers_dirty = True
            suite.probe.publish_pose("person_face", face.center, face.quat)
            return roadmap_marker(n_valid)

        n_valid = len(pl.roadmap_node_ids())
        found = suite.probe.wait_for(lambda: republished(n_valid), 30)
        assert found, f"no roadmap markers with {n_valid} nodes"
        nodes, edges = found
        assert len(nodes.colors) == len(nodes.points)
        assert 0 < len(edges.points) <= 2 * suite.server.p["marker_max_edges"]
        # grow the roadmap (as a repair does) while the planner is idle; the next cycles republish
        assert suite.server._idle.wait(30)
        added = pl.grow(15, center=scene.target("person_face").center[:2], radius=2.0,
                        rng=np.random.default_rng(3))["added_nodes"]
        assert added > 0
        n_valid = len(pl.roadmap_node_ids())
        found = suite.probe.wait_for(lambda: republished(n_valid), 30)
        assert found, f"markers were not rebuilt for the grown roadmap ({n_valid} nodes)"
        assert len(found[0].colors) == len(found[0].points) == n_valid
    finally:
        suite.probe.node.destroy_subscription(sub)
