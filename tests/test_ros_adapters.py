"""Execution adapters of the shipped robots, judged by the rules the real controllers enforce (written out here from
their public sources, not taken from the adapter code): ros2_control's joint_trajectory_controller with
``allow_partial_joints_goal: false`` takes exactly its own joints, strictly increasing times, and drops a trajectory
whose stamp (0 = now) plus last time_from_start lies in the past; Stretch's driver wants stamp 0 and at most 5 goals
per second, one base joint per goal. In process with real rclpy: the adapter node drives ``sim_robot`` through
those interfaces; the test records what was sent on the controllers' topics and cmd_vel and what the robot reported
on /odom, and judges the base's tracking against the trajectory the test itself published."""

from __future__ import annotations

import contextlib
import gc
import math
import sys
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_ros.harness.probe import claim_domain_id  # noqa: E402
from stalls import freeze_this_process  # noqa: E402

from psprm_core.planning.timing import time_parameterize  # noqa: E402
from psprm_ros.robots import adapters as ad  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.robots.base_follower import BaseFollower, BaseReference, Gains, Limits  # noqa: E402

# the controllers' joint sets as the robots' drivers name them (robot-interfaces facts: stretch_core, TIAGo's
# tiago_controller_configuration, ur_robot_driver)
EXPECTED = {
    "stretch2": {"stretch_controller": {"joint_lift", "wrist_extension", "joint_wrist_yaw", "joint_head_pan",
                                        "joint_head_tilt"}},
    "fetchlike": {"torso_controller": {"torso_lift_joint"}, "head_controller": {"head_1_joint", "head_2_joint"},
                  "arm_controller": {f"arm_{i}_joint" for i in range(1, 8)}},
    "ur5_mobile": {"scaled_joint_trajectory_controller": {"shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                                                          "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"}},
}
SCENES = {"stretch2": "dynamic_person", "fetchlike": "nursing", "ur5_mobile": "blind_spot_alley"}


def jtc_problems(msg, own: set, now: float) -> list:
    """What a joint_trajectory_controller (allow_partial_joints_goal false) refuses in ``msg`` at time ``now``."""
    bad = []
    names = list(msg.joint_names)
    if set(names) != own or len(set(names)) != len(names):
        bad.append(f"joint set {names} != {sorted(own)}")
    if not msg.points:
        bad.append("no points")
        return bad
    t = [cv.duration_to_sec(p.time_from_start) for p in msg.points]
    if any(b <= a for a, b in zip(t, t[1:])):
        bad.append("time_from_start not strictly increasing")
    if any(len(p.positions) != len(names) for p in msg.points):
        bad.append("a point without one position per joint")
    stamp = cv.stamp_to_sec(msg.header.stamp)
    start = now if stamp == 0.0 else stamp
    if start + t[-1] < now:
        bad.append("ends in the past")
    if start + t[0] <= now - 1e-3:
        bad.append("first point in the past: the controller would jump")
    return bad


def planned_trajectory(robot, q0, turn=math.pi / 2, drive=1.0, joint_delta=0.25):
    """A diff-drive trajectory the planner could output: turn, drive straight (the other joints moving), turn;
    timed within the robot's limits."""
    q1 = q0.copy()
    q1[2] += turn
    q2 = q1.copy()
    q2[0] += drive * math.cos(q1[2])
    q2[1] += drive * math.sin(q1[2])
    q2[3:] = np.clip(q0[3:] + joint_delta, robot.lower[3:], robot.upper[3:])
    q3 = q2.copy()
    q3[2] -= turn
    b = robot.config.base
    return time_parameterize(np.array([q0, q1, q2, q3]), robot.velocity, robot.acceleration, dt=0.05,
                             base_indices=(0, 1, 2), base_linear_limits=(b.linear_velocity, b.linear_acceleration),
                             method="analytic")


# ---------------------------------------------------------------------------------------------------------- pure
def test_stall_grace_puts_off_one_stale_verdict_per_stall():
    """Steps 0.1 s apart at a 0.1 s period are on time; a step 0.5 s after the previous one is late and its stale
    verdict is put off once; a second late stale step in a row is not forgiven; after a fresh step the next stall is
    forgiven again."""
    from psprm_ros.core import StallGrace

    g = StallGrace(0.1)
    assert [g.step(t) for t in (1.0, 1.1, 1.2)] == [False, False, False]
    assert not g.forgive(False)  # stale on time: stands
    late = g.step(1.7)
    assert late and g.forgive(late)
    late = g.step(2.2)
    assert late and not g.forgive(late)  # stale again at the next step: stands
    g.clear()
    late = g.step(2.7)
    assert late and g.forgive(late)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_shipped_adapter_owns_every_joint_once_under_the_drivers_names(name, load_robot):
    robot = load_robot(name)
    cfg = ad.load_adapter(name, robot)
    got = {c.name: set(c.robot_joints) for c in cfg.controllers}
    assert got == EXPECTED[name]
    owned = [j for c in cfg.controllers for j in c.joints]
    assert sorted(owned) == sorted(robot.joint_names[3:])  # every non-base planning joint, once
    if name == "stretch2":
        # stretch_core: cmd_vel is taken only in navigation mode, whole-body goals only in trajectory mode
        assert cfg.base.mode == "stretch_trajectory" and cfg.driver.kind == "stretch"
        assert cfg.driver.mode == "trajectory" and [c.interface for c in cfg.controllers] == ["action"]
    else:
        assert cfg.base.mode == "cmd_vel" and cfg.base.rate_hz >= 20


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_controller_commands_obey_the_jtc_rules_and_carry_the_planned_positions(name, load_robot):
    robot = load_robot(name)
    cfg = ad.load_adapter(name, robot)
    q0 = robot.default_configuration()
    q0[:3] = [1.0, 1.0, 0.3]
    tr = planned_trajectory(robot, q0)
    now = 1000.0
    for c in cfg.controllers:
        cmd = ad.controller_command(c, robot.joint_names, tr.times, tr.positions, tr.velocities, now=now)
        msg = ad.to_joint_trajectory(cmd)
        assert jtc_problems(msg, EXPECTED[name][c.name], now + 0.01) == []  # as received 10 ms later
        if name == "stretch2":
            assert cv.stamp_to_sec(msg.header.stamp) == 0.0  # the driver's rule
        # the planned positions under the robot's names (Stretch: arm_extension published as wrist_extension)
        inv = {c.robot_name(j): j for j in c.joints}
        for k, rn in enumerate(msg.joint_names):
            col = robot.joint_names.index(inv[rn])
            assert np.allclose([p.positions[k] for p in msg.points], tr.positions[:, col])
        # a goal held back by the goal interval starts where the plan is by then, never in the past
        late = ad.controller_command(c, robot.joint_names, tr.times, tr.positions, tr.velocities, now=now + 1.0,
                                     start_at=now + c.lead_time_s)
        lm = ad.to_joint_trajectory(late)
        assert jtc_problems(lm, EXPECTED[name][c.name], now + 1.01) == []
        t_late = np.array([cv.duration_to_sec(p.time_from_start) for p in lm.points])
        t_abs = (now + 1.0 + t_late) if late.stamp == 0.0 else late.stamp + t_late
        j0 = robot.joint_names.index(c.joints[0])
        expect = np.interp(t_abs - (now + c.lead_time_s), tr.times, tr.positions[:, j0])
        assert np.allclose([p.positions[0] for p in lm.points], expect, atol=1e-6)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_hold_is_a_stop_every_jtc_accepts_and_a_far_start_is_refused(name, load_robot):
    robot = load_robot(name)
    cfg = ad.load_adapter(name, robot)
    q = robot.default_configuration()
    q[:3] = [2.0, 1.0, 0.5]
    for c in cfg.controllers:
        m = ad.to_joint_trajectory(ad.hold_command(c, robot.joint_names, q))
        assert jtc_problems(m, EXPECTED[name][c.name], 12345.0 + 0.5) == []  # stamp 0: accepted whenever it arrives
        assert len(m.points) == 1 and cv.duration_to_sec(m.points[0].time_from_start) > 0
        assert np.allclose(m.points[0].velocities, 0.0)
        idx = [robot.joint_names.index(j) for j in c.joints]
        assert np.allclose(m.points[0].positions, q[idx])
        first = q.copy()
        assert ad.check_start(c, robot.joint_names, first, q)[0]
        first[idx[0]] += c.start_tolerance * 1.5
        ok, joint, err = ad.check_start(c, robot.joint_names, first, q)
        assert not ok and joint == c.joints[0] and err == pytest.approx(c.start_tolerance * 1.5)
    # the server's stop trajectory is one of those too
    stop = cv.stop_trajectory(q, robot.joint_names, "map")
    assert jtc_problems(stop, set(robot.joint_names), 99.0) == []


def test_stretch_goals_at_20_hz_leave_at_most_5_per_second(load_robot):
    robot = load_robot("stretch2")
    c = ad.load_adapter("stretch2", robot).controller("stretch_controller")
    gate = ad.GoalGate(c.min_goal_interval_s)
    sent = []
    t = 0.0
    while t < 3.0:  # an offer every 50 ms, the gate polled at 100 Hz
        if gate.offer(t, t) is not None:
            sent.append(t)
        for k in range(5):
            if gate.due(t + 0.01 * k) is not None:
                sent.append(t + 0.01 * k)
        t = round(t + 0.05, 6)
    gaps = np.diff(sent)
    assert gaps.min() >= 0.2 - 1e-9 and len(sent) >= 13  # never two within 0.2 s, and no goal starves


def test_follow_joint_trajectory_goal_fields(load_robot):
    robot = load_robot("stretch2")
    c = ad.load_adapter("stretch2", robot).controller("stretch_controller")
    q0 = robot.default_configuration()
    tr = planned_trajectory(robot, q0)
    cmd = ad.controller_command(c, robot.joint_names, tr.times, tr.positions, tr.velocities, now=5.0)
    f = ad.action_goal_fields(cmd, c.goal_time_tolerance_s)
    assert set(f) == {"trajectory", "goal_time_tolerance"}
    assert jtc_problems(f["trajectory"], EXPECTED["stretch2"]["stretch_controller"], 5.0) == []
    assert cv.duration_to_sec(f["goal_time_tolerance"]) == pytest.approx(c.goal_time_tolerance_s)
    fjt = ad.import_follow_joint_trajectory()
    if fjt is None:
        pytest.skip("control_msgs is not installed here (it comes with a robot's ROS install)")
    goal = ad.fill_goal(fjt.Goal(), f)
    assert list(goal.trajectory.joint_names) == list(f["trajectory"].joint_names)


def test_stretch_translate_rotate_steps_reach_the_planned_pose():
    """Integrating the position-mode goals (one base joint each) from the start gives the path's end pose."""
    W = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.8], [1.0 * math.cos(0.8), 1.0 * math.sin(0.8), 0.8],
                  [1.0 * math.cos(0.8), 1.0 * math.sin(0.8), -0.4],  # rotate, then back up 0.5 m
                  [1.0 * math.cos(0.8) - 0.5 * math.cos(-0.4), 1.0 * math.sin(0.8) - 0.5 * math.sin(-0.4), -0.4]])
    dense = np.vstack([a + (b - a) * f for a, b in zip(W[:-1], W[1:]) for f in np.linspace(0, 1, 7)[:-1]] + [W[-1]])
    steps = ad.stretch_base_steps(dense)
    assert [j for j, _ in steps] == ["rotate_mobile_base", "translate_mobile_base", "rotate_mobile_base",
                                     "translate_mobile_base"]
    x = y = 0.0
    th = 0.0
    for j, d in steps:
        if j == "rotate_mobile_base":
            th += d
        else:
            x, y = x + d * math.cos(th), y + d * math.sin(th)
    assert np.allclose([x, y], W[-1, :2], atol=1e-6) and abs(math.remainder(th - W[-1, 2], 2 * math.pi)) < 1e-6
    base = ad.BaseConfig(mode="stretch_translate_rotate", action="/stretch_controller/follow_joint_trajectory")
    for s in steps:
        cmd = ad.stretch_base_command(s, base, 0.3, 1.0)
        m = ad.to_joint_trajectory(cmd)
        assert list(m.joint_names) == [s[0]] and cv.stamp_to_sec(m.header.stamp) == 0.0
        assert cv.duration_to_sec(m.points[0].time_from_start) >= abs(s[1]) / (0.3 if "translate" in s[0] else 1.0) - 1e-6


def test_base_follower_tracks_a_unicycle_within_its_limits(load_robot):
    """Offline: a unicycle integrating the follower's commands one control period late, clipped to the base limits,
    stays within 0.1 m / 0.1 rad of the planned base trajectory at every step."""
    robot = load_robot("stretch2")
    q0 = robot.default_configuration()
    q0[:3] = [1.0, 1.0, 0.0]
    tr = planned_trajectory(robot, q0, turn=2.0, drive=2.0)
    lim = Limits.for_robot(robot)
    f = BaseFollower(lim, Gains())
    f.set_path(BaseReference(tr.times, tr.positions[:, :3]), 0.0)
    x, y, th = 1.0, 1.0, 0.0
    v = w = 0.0
    cmd = (0.0, 0.0)
    dt = 1 / 30
    worst = np.zeros(2)
    for k in range(int((tr.times[-1] + 3) / dt)):
        t = k * dt
        target = np.clip(cmd, [-lim.linear_velocity, -lim.angular_velocity], [lim.linear_velocity,
                                                                               lim.angular_velocity])
        v += float(np.clip(target[0] - v, -lim.linear_acceleration * dt, lim.linear_acceleration * dt))
        w += float(np.clip(target[1] - w, -lim.angular_acceleration * dt, lim.angular_acceleration * dt))
        x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
        cmd = f.command(t, (x, y, th))  # applied from the next step on
        ref = np.array([np.interp(min(t, tr.times[-1]), tr.times, tr.positions[:, j]) for j in range(3)])
        worst = np.maximum(worst, [math.hypot(ref[0] - x, ref[1] - y), abs(math.remainder(ref[2] - th, 2 * math.pi))])
    assert worst[0] < 0.1 and worst[1] < 0.1, worst
    assert f.done and math.hypot(x - tr.positions[-1, 0], y - tr.positions[-1, 1]) < 0.03


@pytest.mark.parametrize("v, w", [(0.3, 0.0), (-0.2, 0.0), (0.0, -1.0), (0.25, 0.8), (0.1, -1.0)])
def test_braking_configurations_end_where_a_decelerating_base_rests(v, w):
    """The base braking from (v, omega) at its accelerations, integrated by the test in 1 ms steps (each axis
    decelerating until it rests): the last braking configuration is where it rests, the others lie on its way."""
    lim = Limits(0.3, 1.0, 0.5, 1.5)
    q = np.array([1.0, 2.0, 0.4, 0.3, 0.1])
    x, y, th, vv, ww, dt = 1.0, 2.0, 0.4, v, w, 1e-3
    track = []
    while abs(vv) > 0 or abs(ww) > 0:
        x += vv * math.cos(th) * dt
        y += vv * math.sin(th) * dt
        th += ww * dt
        vv = np.sign(vv) * max(0.0, abs(vv) - lim.linear_acceleration * dt)
        ww = np.sign(ww) * max(0.0, abs(ww) - lim.angular_acceleration * dt)
        track.append((x, y, th))
    track = np.array(track)
    B = ad.braking_configurations(q, (v, w), lim, n=4)
    assert B.shape == (4, 5) and np.allclose(B[:, 3:], q[3:])
    assert np.allclose(B[-1, :3], track[-1], atol=3e-3), (B[-1, :3], track[-1])
    for b in B:  # on the way: within a few mm of the integrated track
        assert np.min(np.hypot(track[:, 0] - b[0], track[:, 1] - b[1]) + np.abs(track[:, 2] - b[2])) < 5e-3


def test_adapter_config_errors_name_the_field(tmp_path, load_robot):
    from psprm_core.errors import ConfigError

    robot = load_robot("stretch2")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: stretch2\ncontrollers:\n  - {name: a, topic: /a, joints: [joint_lift, no_such_joint]}\n")
    with pytest.raises(ConfigError, match="no_such_joint"):
        ad.load_adapter(str(bad), robot)
    bad.write_text("robot: stretch2\ncontrollers:\n  - {name: a, topic: /a, joints: [joint_lift]}\n")
    with pytest.raises(ConfigError, match="no controller owns"):
        ad.load_adapter(str(bad), robot)
    bad.write_text("robot: stretch2\ncontrollers:\n  - {name: a, interface: action, joints: [joint_lift]}\n")
    with pytest.raises(ConfigError, match="action"):
        ad.load_adapter(str(bad), robot)
    bad.write_text("robot: [unclosed\n")
    with pytest.raises(ConfigError, match="malformed"):
        ad.load_adapter(str(bad), robot)


# ---------------------------------------------------------------------------------------------------------- in process
class Recorder:
    """The test's own subscriptions: every message on the controllers' topics and cmd_vel with receipt times (node
    clock), /odom with the time the robot measured it (its header stamp)."""

    def __init__(self, node, cfg):
        from geometry_msgs.msg import Twist, TwistStamped
        from nav_msgs.msg import Odometry
        from trajectory_msgs.msg import JointTrajectory

        self.node, self.lock = node, threading.Lock()
        self.traj = {c.name: [] for c in cfg.controllers}
        self.twists, self.odom = [], []
        self.subs = [node.create_subscription(JointTrajectory, c.topic, self._rec(self.traj[c.name]), 50)
                     for c in cfg.controllers]
        b = cfg.base
        self.subs.append(node.create_subscription(TwistStamped if b.stamped else Twist, b.topic,
                                                  self._rec(self.twists, lambda m: m.twist if b.stamped else m), 50))
        self.subs.append(node.create_subscription(Odometry, "/odom", self._rec(self.odom, _odom_pose, stamped=True),
                                                  50))

    def _now(self):
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _rec(self, store, conv=None, stamped=False):
        def cb(m):
            t = cv.stamp_to_sec(m.header.stamp) if stamped else self._now()
            with self.lock:
                store.append((t, conv(m) if conv else m))
        return cb

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)


def _odom_pose(m):
    p = m.pose.pose
    return np.array([p.position.x, p.position.y, cv.yaw_of([p.orientation.x, p.orientation.y, p.orientation.z,
                                                             p.orientation.w])])


def path_errors(tr, tau, X, window_s: float = 0.5) -> tuple:
    """Distance (m) and heading difference (rad) of each measured base pose ``X`` (at ``tau`` s after the start)
    to the planned base trajectory, at the planned instant within +-``window_s`` of ``tau`` that matches best (the
    base must be on the path with the planned heading; a lag of a few control periods on a loaded machine is not
    counted against it)."""
    ts = np.arange(0.0, tr.times[-1] + 1e-9, 0.01)
    R = np.stack([np.interp(ts, tr.times, tr.positions[:, j]) for j in range(3)], 1)
    e_xy, e_th = np.zeros(len(tau)), np.zeros(len(tau))
    for i, (t, x) in enumerate(zip(tau, X)):
        m = np.abs(ts - np.clip(t, 0, tr.times[-1])) <= window_s
        dxy = np.hypot(R[m, 0] - x[0], R[m, 1] - x[1])
        dth = np.abs(np.remainder(R[m, 2] - x[2] + np.pi, 2 * np.pi) - np.pi)
        k = int(np.argmin(dxy + 0.3 * dth))
        e_xy[i], e_th[i] = dxy[k], dth[k]
    return e_xy, e_th


def _latched_pub(node):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from trajectory_msgs.msg import JointTrajectory

    q = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return node.create_publisher(JointTrajectory, "/psprm/trajectory", q)


def _wait(pred, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        r = pred()
        if r:
            return r
        time.sleep(0.05)
    return None


@contextlib.contextmanager
def _adapter_on_sim(name: str, robot, sim_params: Optional[dict] = None):
    """The shipped adapter (forced to the topic interface) in this process, active on a ``sim_robot`` in its own
    process (as a robot is: its clock and integration do not wait for this one), with the test's recorder and a
    publisher of /psprm/trajectory. Yields (suite, adapter config, recorder, publisher, the robot's process id)."""
    from psprm_ros.heap import freeze_long_lived
    from psprm_ros.harness.probe import InProcessSuite

    cfg = ad.load_adapter(name, robot).with_interface("topic")
    params = {"scene": SCENES[name], "robot": name, "adapter": name, "interface": "topic",
              "initial_base": [1.0, 1.0, 0.3], "input_frames": ["odom"]}
    domain = claim_domain_id()
    sim = start_sim_process({**params, **(sim_params or {})}, domain)
    try:
        with InProcessSuite(params, domain_id=domain, nodes=("adapter",)) as s:
            rec = Recorder(s.probe.node, cfg)
            try:
                pub = _latched_pub(s.probe.node)
                assert _wait(lambda: s.adapter.active and s.adapter.measured()[0] is not None, 60), \
                    (s.probe.statuses[-5:], sim.poll())
                # as the adapter's own process does after start-up: the test process's heap (every earlier test's
                # modules and models) out of the full collections, which stopped it for 0.2-0.6 s mid-motion
                freeze_long_lived()
                yield s, cfg, rec, pub, sim.pid
            finally:
                gc.unfreeze()
                rec.close()
    finally:
        stop_process(sim)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_adapter_drives_sim_robot_through_the_controllers_and_tracks_the_base(name, load_robot):
    """The shipped adapter (forced to the topic interface sim_robot offers) executes a trajectory the test publishes:
    every message on every controller topic obeys that controller's rules, the base measured on /odom stays within
    0.1 m / 0.1 rad of the published trajectory's path (:func:`path_errors`), the joints end at its last point; a
    stop then gives a zero twist and a hold at the measured configuration, both accepted."""
    robot = load_robot(name)
    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        time.sleep(0.3)
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, drive=0.8)
        names = robot.joint_names
        msg = cv.trajectory_to_msg(tr, names, "map", s.probe.node.get_clock().now().to_msg(), 0.1)
        pub.publish(msg)
        got = _wait(lambda: all(rec.traj[c.name] for c in cfg.controllers), 10)
        assert got, f"controllers got nothing: {s.probe.statuses[-5:]}"
        _wait(lambda: False, tr.times[-1] + 1.5)
        with rec.lock:
            first = {c: list(v) for c, v in rec.traj.items()}
            odom = list(rec.odom)
        for c in cfg.controllers:
            t_rx, m = first[c.name][0]
            assert jtc_problems(m, EXPECTED[name][c.name], t_rx) == [], c.name
        # the trajectory's start on the robot's clock, from what the controller received
        c0 = cfg.controllers[0]
        t_rx, m0 = first[c0.name][0]
        st = cv.stamp_to_sec(m0.header.stamp)
        start = st if st > 0 else t_rx + cv.duration_to_sec(m0.points[0].time_from_start)
        T = np.array([t for t, _ in odom])
        X = np.array([x for _, x in odom])
        sel = (T >= start) & (T <= start + tr.times[-1] + 1.0)
        assert sel.sum() > 20 * tr.times[-1]  # /odom at >= 20 Hz through the motion
        e_xy, e_th = path_errors(tr, T[sel] - start, X[sel])
        tw_t = np.array([t for t, _ in rec.twists])
        tw_t = tw_t[(tw_t >= start) & (tw_t <= start + tr.times[-1])]
        k = int(np.argmax(e_xy + e_th))
        assert e_xy.max() < 0.1 and e_th.max() < 0.1, \
            {"e_xy": e_xy.max(), "e_th": e_th.max(), "at_s": (T[sel] - start)[k], "duration_s": tr.times[-1],
             "longest_cmd_vel_gap_s": np.diff(tw_t).max() if len(tw_t) > 1 else None}
        assert not [x for x in s.probe.statuses if x[1] == "sim_robot" and "refused" in x[2]]
        q_end = s.adapter.measured()[0]  # from the robot's own /joint_states and /odom
        assert np.allclose(q_end[3:], tr.positions[-1, 3:], atol=0.02)
        # stop: the server's one-point trajectory
        n_tw = len(rec.twists)
        t_stop = s.probe.node.get_clock().now().nanoseconds * 1e-9
        pub.publish(cv.stop_trajectory(q_end, names, "map"))
        assert _wait(lambda: all(len(rec.traj[c.name]) > len(first[c.name]) for c in cfg.controllers), 5)
        with rec.lock:
            for c in cfg.controllers:
                t_rx, hold = rec.traj[c.name][-1]
                assert t_rx >= t_stop and len(hold.points) == 1
                assert jtc_problems(hold, EXPECTED[name][c.name], t_rx) == []
                idx = [names.index(j) for j in c.joints]
                assert np.allclose(hold.points[0].positions, q_end[idx], atol=0.02)
            zero = [tw for t, tw in rec.twists[n_tw:] if t >= t_stop]
        assert zero and zero[0].linear.x == 0.0 and zero[0].angular.z == 0.0


def test_adapter_forgives_its_own_stall_but_stops_when_the_base_pose_goes_stale(load_robot):
    """A stall of the adapter's own process (every thread of it stopped for longer than ``state_timeout_s``, as a
    machine that does not schedule it does) leaves the robot's /odom waiting in the adapter's queue: the base keeps following the trajectory and no zero twist goes out.
    A robot whose /odom really stops (its process frozen) is stopped with a zero twist within ``state_timeout_s``
    and two control periods of its last /odom. Judged from the test's own record of /odom and cmd_vel."""
    import os
    import signal

    name = "stretch2"
    robot = load_robot(name)
    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        timeout = s.adapter.p["state_timeout_s"]
        period = 1.0 / cfg.base.rate_hz
        time.sleep(0.3)
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, turn=0.0, drive=2.5)
        msg = cv.trajectory_to_msg(tr, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1)
        pub.publish(msg)

        def base_moved():
            with rec.lock:
                return rec.odom and np.hypot(*(rec.odom[-1][1][:2] - q0[:2])) > 0.15
        assert _wait(base_moved, 20), s.probe.statuses[-5:]
        n_tw = len(rec.twists)
        held = freeze_this_process(timeout + 0.3)
        assert held > timeout
        with rec.lock:
            x_after = rec.odom[-1][1][:2].copy()
        time.sleep(1.0)
        with rec.lock:
            twists = [tw for _, tw in rec.twists[n_tw:]]
            x_later = rec.odom[-1][1][:2].copy()
        assert twists and all(abs(tw.linear.x) > 1e-6 for tw in twists), "the adapter stopped after its own stall"
        assert np.hypot(*(x_later - x_after)) > 0.05  # still driving along the trajectory
        # the robot's process frozen: its /odom stops for real
        os.kill(sim_pid, signal.SIGSTOP)
        try:
            time.sleep(timeout + 1.0)
            with rec.lock:
                last_odom = rec.odom[-1][0]
                zero = [t for t, tw in rec.twists if t > last_odom and tw.linear.x == 0.0 and tw.angular.z == 0.0]
        finally:
            os.kill(sim_pid, signal.SIGCONT)
        assert zero, "no zero twist after the base pose went stale"
        assert zero[0] - last_odom <= timeout + 2 * period + 0.1, zero[0] - last_odom


def test_a_push_off_the_path_stops_the_robot_within_the_path_tolerance(load_robot):
    """While the base drives a straight trajectory, the robot is pushed sideways (sim_robot's ``~/disturbance``,
    0.25 m/s to its left for 1.5 s: a differential drive cannot undo that with cmd_vel). The adapter stops the
    robot (a zero twist, a hold on the controller) once it is off its path by the path tolerance: judged from the
    test's own record of /odom against the trajectory it published, no zero twist comes before the push, the first
    one comes while the base is at most one push period and the tolerance off the path, and the base then stays
    where it stopped instead of driving on along the path. A robot that is not pushed drives such trajectories to
    their end (the tracking test above)."""
    from geometry_msgs.msg import Twist, Vector3

    name = "stretch2"
    robot = load_robot(name)
    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        tol = s.adapter.p["path_tolerance_m"]
        assert tol > 0
        push = s.probe.node.create_publisher(Twist, "/sim_robot/disturbance", 10)
        time.sleep(0.3)
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, turn=0.0, drive=2.5, joint_delta=0.0)
        pub.publish(cv.trajectory_to_msg(tr, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))

        def base_moved():
            with rec.lock:
                return rec.odom and np.hypot(*(rec.odom[-1][1][:2] - q0[:2])) > 0.3
        assert _wait(base_moved, 20), s.probe.statuses[-5:]
        now = lambda: s.probe.node.get_clock().now().nanoseconds * 1e-9  # noqa: E731
        n_holds = len(rec.traj[cfg.controllers[0].name])
        t_push = now()
        while now() < t_push + 1.5:
            push.publish(Twist(linear=Vector3(y=0.25)))
            time.sleep(0.05)
        time.sleep(1.0)
        with rec.lock:
            odom = list(rec.odom)
            twists = list(rec.twists)
            holds = rec.traj[cfg.controllers[0].name][n_holds:]
    T = np.array([t for t, _ in odom])
    X = np.array([x for _, x in odom])
    line = tr.positions[-1, :2] - tr.positions[0, :2]
    line /= np.linalg.norm(line)
    off = np.abs((X[:, 0] - q0[0]) * line[1] - (X[:, 1] - q0[1]) * line[0])  # the base's distance from the path
    moving = min(t for t, tw in twists if tw.linear.x != 0.0)
    zero = [t for t, tw in twists if t > moving and tw.linear.x == 0.0 and tw.angular.z == 0.0]
    assert zero and zero[0] > t_push, ("no stop after the push" if not zero else "a stop before the push", zero[:3])
    k = max(0, int(np.searchsorted(T, zero[0])) - 1)
    assert off[k] <= tol + 0.25 * 0.1, {"off_at_stop_m": off[k], "tolerance": tol, "max_off_m": off.max()}
    assert holds and len(holds[0][1].points) == 1  # the controller got a hold
    after = T > zero[0] + 0.6  # braking from 0.3 m/s at 0.5 m/s^2 takes 0.6 s
    along = (X[after, :2] - q0[:2]) @ line
    assert np.ptp(along) < 0.02, "the base drove on along the path after the stop"
    assert any("off the checked path" in st for _, n, st in s.probe.statuses if n == "robot_adapter"), \
        s.probe.statuses[-5:]


def _drive_a_straight_stretch(s, cfg, rec, pub, robot, after_s: float):
    """Publish a 2.4 m straight drive from where the robot stands and return ``after_s`` seconds after the
    controller's trajectory started: (the trajectory, its start on the node clock, a clock reader)."""
    time.sleep(0.3)
    q0 = s.adapter.measured()[0]
    tr = planned_trajectory(robot, q0, turn=0.0, drive=2.4, joint_delta=0.0)
    now = lambda: s.probe.node.get_clock().now().nanoseconds * 1e-9  # noqa: E731
    pub.publish(cv.trajectory_to_msg(tr, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
    assert _wait(lambda: rec.traj[cfg.controllers[0].name], 10)
    with rec.lock:
        t_rx, m0 = rec.traj[cfg.controllers[0].name][0]
    st = cv.stamp_to_sec(m0.header.stamp)
    start = st if st > 0 else t_rx + cv.duration_to_sec(m0.points[0].time_from_start)
    time.sleep(max(0.0, start + after_s - now()))
    return tr, start, now


@pytest.mark.parametrize("delay_s", [0.0, 2.6])
def test_a_replan_spliced_onto_the_trajectory_under_way_is_taken_without_a_stop(load_robot, delay_s):
    """While the base drives a long straight stretch, the test publishes what the roadmap server publishes for a
    replan of a robot in motion (:func:`psprm_core.planning.execution.splice`): the trajectory under way from where
    the robot is, up to the end of that stretch (a rest instant), then a new trajectory from there (a turn and a drive
    to the left); ``delay_s`` after the robot was there (a slow replan: the robot is seconds along the splice when it
    arrives). Judged from the test's own record: no zero twist (a stop) between the splice's publication and the
    end of the stretch, the base never slower there than half the planned speed of the old trajectory at the same
    place, and the base on the spliced trajectory's path within 0.1 m / 0.1 rad to its end."""
    from psprm_core.planning.execution import commit_time, splice

    name = "stretch2"
    robot = load_robot(name)
    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        tr, start, now = _drive_a_straight_stretch(s, cfg, rec, pub, robot, 2.5)  # mid-stretch, at full speed
        t_from = now() - start
        t_c = commit_time(tr, t_from, 0.5 + delay_s)
        assert t_c - t_from > 1.5 + delay_s, "precondition: the stretch goes on for a while"
        q_c = tr.evaluate([t_c])[0][0]
        q1, q2 = q_c.copy(), q_c.copy()
        q1[2] += math.pi / 2
        q2[2] = q1[2]
        q2[0] += 0.6 * math.cos(q1[2])
        q2[1] += 0.6 * math.sin(q1[2])
        b = robot.config.base
        new = time_parameterize(np.array([q_c, q1, q2]), robot.velocity, robot.acceleration, dt=0.05,
                                base_indices=(0, 1, 2), base_linear_limits=(b.linear_velocity, b.linear_acceleration),
                                method="analytic")
        sp = splice(tr, t_from, t_c, new, continuous=[2])
        time.sleep(max(0.0, start + t_from + delay_s - now()))
        t_pub = now()
        pub.publish(cv.trajectory_to_msg(sp, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
        _wait(lambda: False, sp.duration + 1.5)
        with rec.lock:
            odom = list(rec.odom)
            twists = list(rec.twists)
    t_end_stretch = start + t_c - 0.3  # (the base decelerates into the stretch's end)
    stops = [t for t, tw in twists if t_pub <= t <= t_end_stretch and tw.linear.x == 0.0 and tw.angular.z == 0.0]
    assert not stops, f"the robot was stopped at {stops[:3]} (splice published at {t_pub:.2f})"
    T = np.array([t for t, _ in odom])
    X = np.array([x for _, x in odom])
    sel = (T >= t_pub) & (T <= t_end_stretch - 0.3)
    v = np.hypot(*np.diff(X[sel, :2], axis=0).T) / np.diff(T[sel])
    # the old trajectory's own speed at the places the base passed (nearest base position along the stretch)
    ts = np.arange(0.0, tr.duration, 0.01)
    P, V, _ = tr.evaluate(ts)
    k = [int(np.argmin(np.hypot(*(P[:, :2] - x[:2]).T))) for x in X[sel][1:]]
    planned = np.hypot(V[k, 0], V[k, 1])
    assert np.all(v >= 0.5 * planned - 0.02), {"slowest_ratio": float(np.min((v + 1e-9) / (planned + 1e-9)))}
    # on the spliced path: the spliced trajectory's time 0 is the old one's t_from
    sel2 = (T >= t_pub) & (T <= start + t_from + sp.duration + 1.0)
    e_xy, e_th = path_errors(sp, T[sel2] - (start + t_from), X[sel2], window_s=1.0)
    assert e_xy.max() < 0.1 and e_th.max() < 0.1, (e_xy.max(), e_th.max())
    assert np.hypot(*(X[-1, :2] - q2[:2])) < 0.1  # it drove the new plan to its end


def test_the_base_is_controlled_while_a_slow_acceptance_runs_and_brakes_where_the_trajectory_rests(load_robot):
    """A splice reaches the adapter 1.0 s before the trajectory under way comes to rest at the end of a straight
    stretch (where the splice turns), and its acceptance takes 0.5 s longer than it does here (a busy machine: the
    test delays the adapter's real check by that much). The control steps run meanwhile: on the test's record of
    cmd_vel, no gap over 0.2 s while the check runs; on /odom, the base brakes into the stretch's end and passes
    the rest point the test planned by at most 3 cm along the drive (coasting on its last command through the
    check, it would run about 15 cm past it at 0.3 m/s)."""
    from psprm_core.planning.execution import commit_time, splice

    name = "stretch2"
    robot = load_robot(name)
    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        tr, start, now = _drive_a_straight_stretch(s, cfg, rec, pub, robot, 2.0)
        t_from = now() - start
        t_c = commit_time(tr, t_from, 0.5)
        q_c = tr.evaluate([t_c])[0][0]
        q1 = q_c.copy()
        q1[2] += math.pi / 2
        b = robot.config.base
        new = time_parameterize(np.array([q_c, q1]), robot.velocity, robot.acceleration, dt=0.05,
                                base_indices=(0, 1, 2), base_linear_limits=(b.linear_velocity, b.linear_acceleration),
                                method="analytic")
        acceptance = s.adapter.execution.acceptance
        check = acceptance.decide
        acceptance.decide = lambda *a, **k: (time.sleep(0.5), check(*a, **k))[1]  # the real check, 0.5 s late
        try:
            time.sleep(max(0.0, start + t_c - 1.0 - now()))
            sp = splice(tr, now() - start, t_c, new, continuous=[2])
            t_pub = now()
            pub.publish(cv.trajectory_to_msg(sp, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(),
                                             0.1))
            _wait(lambda: False, (t_c - (t_pub - start)) + 2.0)
        finally:
            acceptance.decide = check
        with rec.lock:
            odom = list(rec.odom)
            twists = list(rec.twists)
    T = np.array([t for t, _ in twists if t_pub - 0.1 <= t <= t_pub + 0.7])
    assert len(T) > 5 and np.diff(T).max() <= 0.2, {"largest_gap_s": float(np.diff(T).max()) if len(T) > 1 else None}
    heading = np.array([math.cos(q_c[2]), math.sin(q_c[2])])
    X = np.array([x for t, x in odom if t >= t_pub])
    past = (X[:, :2] - q_c[:2]) @ heading  # along the drive, beyond the planned rest point
    assert past.max() <= 0.03, {"past_rest_m": float(past.max())}


def test_a_splice_beginning_before_the_point_where_the_adapter_joined_the_trajectory_is_taken(load_robot):
    """Two replans in a row, as goal spam makes them: the first splice reaches the adapter 0.4 s after the robot was
    at its start, so the adapter joins it 0.4 s in; the second is spliced onto the first from 0.1 s along it (the
    server's estimate of the robot's progress lags its robot states). It continues what the robot executes and is
    taken without a stop, judged from the test's own /odom and cmd_vel record."""
    from psprm_core.planning.execution import commit_time, splice

    name = "stretch2"
    robot = load_robot(name)
    b = robot.config.base

    def turn_and_drive(q_c, turn):
        q1 = q_c.copy()
        q1[2] += turn
        q2 = q1.copy()
        q2[0] += 0.6 * math.cos(q1[2])
        q2[1] += 0.6 * math.sin(q1[2])
        return time_parameterize(np.array([q_c, q1, q2]), robot.velocity, robot.acceleration, dt=0.05,
                                 base_indices=(0, 1, 2), base_linear_limits=(b.linear_velocity, b.linear_acceleration),
                                 method="analytic")

    with _adapter_on_sim(name, robot) as (s, cfg, rec, pub, sim_pid):
        tr, start, now = _drive_a_straight_stretch(s, cfg, rec, pub, robot, 2.0)  # mid-stretch, at full speed
        t_from = now() - start
        t_c = commit_time(tr, t_from, 2.0)
        assert t_c - t_from > 2.5, "precondition: the stretch goes on for a while"
        sp1 = splice(tr, t_from, t_c, turn_and_drive(tr.evaluate([t_c])[0][0], math.pi / 2), continuous=[2])
        time.sleep(max(0.0, start + t_from + 0.4 - now()))
        pub.publish(cv.trajectory_to_msg(sp1, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
        t_pub = now()
        time.sleep(0.3)
        sp2 = splice(sp1, 0.1, t_c - t_from, turn_and_drive(sp1.evaluate([t_c - t_from])[0][0], -math.pi / 2),
                     continuous=[2])
        pub.publish(cv.trajectory_to_msg(sp2, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
        _wait(lambda: False, sp2.duration)
        with rec.lock:
            odom = list(rec.odom)
            twists = list(rec.twists)
    t_end_stretch = start + t_c - 0.3
    stops = [t for t, tw in twists if t_pub <= t <= t_end_stretch and tw.linear.x == 0.0 and tw.angular.z == 0.0]
    assert not stops, f"the robot was stopped at {stops[:3]} (second splice published about {t_pub + 0.3:.2f})"
    T = np.array([t for t, _ in odom])
    X = np.array([x for _, x in odom])
    q_end = sp2.evaluate([sp2.duration])[0][0]
    assert np.hypot(*(X[-1, :2] - q_end[:2])) < 0.1  # it drove the second plan to its end


def test_the_base_runs_at_the_speed_scaling_of_the_arms_controller(load_robot):
    """UR's scaled_joint_trajectory_controller at 50 % (sim_robot publishes the scaling on the driver's topic and
    runs the arm at it): the base follows its path at the same rate, so the whole robot stays on the published
    trajectory's configurations at the scaled time (judged from /odom and /joint_states, whole-robot distance) and
    takes twice the planned time, without an off-path stop."""
    from sensor_msgs.msg import JointState

    from psprm_core.tracking import CheckedPath

    robot = load_robot("ur5_mobile")
    with _adapter_on_sim("ur5_mobile", robot, {"speed_scaling": 50.0}) as (s, cfg, rec, pub, sim_pid):
        joints = []
        sub = s.probe.node.create_subscription(
            JointState, "/joint_states", lambda m: joints.append((cv.stamp_to_sec(m.header.stamp), m)), 50)
        try:
            assert _wait(lambda: s.adapter.speed_scaling == 0.5, 10), s.adapter.speed_scaling
            time.sleep(0.3)
            q0 = s.adapter.measured()[0]
            tr = planned_trajectory(robot, q0, turn=0.6, drive=0.6, joint_delta=0.3)
            pub.publish(cv.trajectory_to_msg(tr, robot.joint_names, "map",
                                             s.probe.node.get_clock().now().to_msg(), 0.1))
            got = _wait(lambda: rec.traj[cfg.controllers[0].name], 10)
            assert got
            t_rx, m0 = rec.traj[cfg.controllers[0].name][0]
            start = cv.stamp_to_sec(m0.header.stamp)
            _wait(lambda: False, 2.0 * tr.times[-1] + 1.0)
            with rec.lock:
                odom = list(rec.odom)
            js = list(joints)
        finally:
            s.probe.node.destroy_subscription(sub)
        assert not [x for x in s.probe.statuses if "off the checked path" in x[2]]
        names = robot.joint_names
        T = np.array([t for t, _ in odom])
        X = np.array([x for _, x in odom])
        sel = (T >= start) & (T <= start + 2.0 * tr.times[-1])
        assert sel.sum() > 20
        # the whole configuration at each odometry instant: the base from /odom, the arm from the nearest
        # /joint_states
        tj = np.array([t for t, _ in js])
        checked = CheckedPath(robot, tr.times, tr.positions)
        devs = []
        for t, x in zip(T[sel], X[sel]):
            m = js[int(np.argmin(np.abs(tj - t)))][1]
            q = np.array(q0, float)
            q[:3] = x
            for j, v in zip(m.name, m.position):
                if j in names:
                    q[names.index(j)] = v
            devs.append(checked.deviation(q, 0.5 * (t - start), 0.5)[0])
        assert max(devs) < 0.04, max(devs)  # the path tolerance
        # it took the scaled time: at the planned end it is about half way, the end is reached at twice the time
        k = int(np.argmin(np.abs(T - (start + tr.times[-1]))))
        s_half = np.hypot(*(X[k, :2] - tr.positions[0, :2]))
        s_all = np.hypot(*(tr.positions[-1, :2] - tr.positions[0, :2]))
        assert 0.2 * s_all < s_half < 0.8 * s_all, (s_half, s_all)
        assert np.hypot(*(X[-1, :2] - tr.positions[-1, :2])) < 0.05


def test_a_plan_arriving_while_the_base_brakes_waits_for_rest_instead_of_being_refused(load_robot):
    """A stop while driving at speed, then at once a plan that starts where the braking base will rest (as the server
    plans after a stop): when it arrives the base is still several centimetres short of that point, beyond the path
    tolerance. The adapter holds the plan until the base rests and runs it from there: no refusal, and the robot
    reaches the plan's end (judged from /odom)."""
    robot = load_robot("stretch2")
    with _adapter_on_sim("stretch2", robot) as (s, cfg, rec, pub, sim_pid):
        time.sleep(0.3)
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, turn=0.0, drive=2.0, joint_delta=0.0)
        names = robot.joint_names
        pub.publish(cv.trajectory_to_msg(tr, names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
        assert _wait(lambda: rec.odom and abs(s.adapter.tracker.base_velocity[0]) > 0.25, 15), "never at speed"
        q1 = s.adapter.measured()[0]
        with rec.lock:
            v = float(np.hypot(*(rec.odom[-1][1][:2] - rec.odom[-6][1][:2])) / (rec.odom[-1][0] - rec.odom[-6][0]))
        pub.publish(cv.stop_trajectory(q1, names, "map"))
        # where it will rest: uniform braking at the robot config's linear acceleration along its heading
        brake = v * v / (2.0 * robot.config.base.linear_acceleration)
        assert brake > 0.045  # beyond the 0.04 m path tolerance
        q_rest = q1.copy()
        q_rest[:2] += brake * np.array([math.cos(q1[2]), math.sin(q1[2])])
        tr2 = planned_trajectory(robot, q_rest, turn=math.pi / 2, drive=0.5, joint_delta=0.0)
        n_refused = s.adapter.counts["refused"]
        assert _wait(lambda: s.adapter.follower.done, 2)
        pub.publish(cv.trajectory_to_msg(tr2, names, "map", s.probe.node.get_clock().now().to_msg(), 0.1))
        _wait(lambda: False, tr2.times[-1] + 3.0)
        with rec.lock:
            odom = list(rec.odom)
        assert s.adapter.counts["refused"] == n_refused, [x[2] for x in s.probe.statuses[-6:]]
        assert s.adapter.counts["held_until_rest"] >= 1
        # where it stood when the stop came, and where it ended: the second plan's end
        X = np.array([x for _, x in odom])
        assert np.hypot(*(X[-1, :2] - tr2.positions[-1, :2])) < 0.05, (X[-1], tr2.positions[-1, :3])


def start_sim_process(params: dict, domain: int):
    import os
    import subprocess

    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1",
               PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    args = []
    for k, v in params.items():
        if isinstance(v, list):
            v = "[" + ",".join(str(x) if not isinstance(x, str) else f"'{x}'" for x in v) + "]"
        args += ["-p", f"{k}:={v}"]
    return subprocess.Popen([sys.executable, "-m", "psprm_ros.sim_robot", "--ros-args", *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)


def stop_process(proc):
    import os
    import signal
    import subprocess

    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)


# ---------------------------------------------------------------------------------------------------------- Stretch
OLD_STRETCH_CONFIG = """robot: stretch2
controllers:
  - name: stretch_controller
    interface: action
    action: /stretch_controller/follow_joint_trajectory
    topic: /stretch_controller/joint_trajectory
    joints: [joint_lift, arm_extension, joint_wrist_yaw, joint_head_pan, joint_head_tilt]
    name_map: {arm_extension: wrist_extension}
    stamp: zero
    lead_time_s: 0.15
    min_goal_interval_s: 0.2
base:
  mode: cmd_vel
  topic: /stretch/cmd_vel
"""


@contextlib.contextmanager
def _stretch_on_driver(adapter: str):
    """The adapter ``adapter`` (its own interfaces) in this process, on a sim_robot process with Stretch's driver
    profile started in the driver's default position mode; the test's record of /odom and of the driver's counts."""
    import json

    from std_msgs.msg import String

    from psprm_ros.heap import freeze_long_lived
    from psprm_ros.harness.probe import InProcessSuite

    params = {"scene": "dynamic_person", "robot": "stretch2", "adapter": adapter, "initial_base": [1.0, 1.0, 0.3],
              "input_frames": ["odom"]}
    domain = claim_domain_id()
    sim = start_sim_process({**params, "driver": "stretch", "driver_mode": "position"}, domain)
    try:
        with InProcessSuite(params, domain_id=domain, nodes=("adapter",)) as s:
            cfg = ad.load_adapter(adapter, s.adapter.robot).with_interface("topic")
            rec = Recorder(s.probe.node, cfg)
            counts = []
            sub = s.probe.node.create_subscription(String, "/sim_robot/driver",
                                                   lambda m: counts.append(json.loads(m.data)), 10)
            try:
                assert _wait(lambda: s.adapter.active and s.adapter.measured()[0] is not None, 60), sim.poll()
                freeze_long_lived()  # as in _adapter_on_sim: no full collection of the test's heap mid-motion
                yield s, rec, counts, _latched_pub(s.probe.node)
            finally:
                gc.unfreeze()
                s.probe.node.destroy_subscription(sub)
                rec.close()
    finally:
        stop_process(sim)


def test_stretch_adapter_runs_the_driver_in_trajectory_mode_and_its_stop_halts(load_robot):
    """The shipped Stretch adapter against sim_robot's Stretch driver profile (started in position mode, as the
    driver starts): it switches the driver to trajectory mode, the plan runs as one goal with no goal refused, no
    cmd_vel dropped and no abort (the driver's own counts), the base follows the plan (/odom), and a stop halts the
    base (/odom) at once."""
    robot = load_robot("stretch2")
    with _stretch_on_driver("stretch2") as (s, rec, counts, pub):
        assert _wait(lambda: counts and counts[-1]["mode"] == "trajectory", 15), counts[-1:] or "no counts"
        assert _wait(lambda: s.adapter.driver_ready()[0], 5), s.adapter.driver_ready()
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, turn=0.8, drive=1.2, joint_delta=0.1)
        pub.publish(cv.trajectory_to_msg(tr, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(),
                                         0.1))
        assert _wait(lambda: s.adapter.counts["goals_sent"] >= 1, 10), [x[2] for x in s.probe.statuses[-5:]]
        t_sent = s.probe.node.get_clock().now().nanoseconds * 1e-9
        # halfway through the straight drive: stop
        _wait(lambda: False, 0.55 * tr.times[-1])
        q_stop = s.adapter.measured()[0]
        t_stop = s.probe.node.get_clock().now().nanoseconds * 1e-9
        pub.publish(cv.stop_trajectory(q_stop, robot.joint_names, "map"))
        _wait(lambda: False, 1.5)
        with rec.lock:
            odom = list(rec.odom)
        c = counts[-1]
        assert c["goals_rejected"] == 0 and c["cmd_vel_dropped"] == 0 and not c["aborts"], c
        assert c["goals_accepted"] >= 1 and c["stops"] >= 1
        T = np.array([t for t, _ in odom])
        X = np.array([x for _, x in odom])
        run = (T >= t_sent) & (T < t_stop)
        e_xy, e_th = path_errors(tr, T[run] - t_sent, X[run], window_s=1.0)
        assert e_xy.max() < 0.1 and e_th.max() < 0.1, (e_xy.max(), e_th.max())
        moved = np.hypot(*(X[run][-1, :2] - X[run][0, :2]))
        assert moved > 0.2  # it was driving when the stop came
        # halted: from 0.1 s after the stop on (the stop's delivery and one service call), the base stands
        after = T >= t_stop + 0.1
        assert after.sum() > 10
        assert np.hypot(*np.ptp(X[after, :2], axis=0)) < 0.005, np.ptp(X[after, :2], axis=0)


def test_the_cmd_vel_plus_action_config_is_refused_by_the_stretch_driver(load_robot, tmp_path):
    """The same driver profile with an adapter that sends the arm by the action and the base by cmd_vel without
    switching modes: the driver, in its position mode, drops every cmd_vel (its own count), so the base never
    moves."""
    cfg_file = tmp_path / "old_stretch.yaml"
    cfg_file.write_text(OLD_STRETCH_CONFIG)
    robot = load_robot("stretch2")
    with _stretch_on_driver(str(cfg_file)) as (s, rec, counts, pub):
        time.sleep(0.5)
        q0 = s.adapter.measured()[0]
        tr = planned_trajectory(robot, q0, turn=0.0, drive=0.8, joint_delta=0.0)
        pub.publish(cv.trajectory_to_msg(tr, robot.joint_names, "map", s.probe.node.get_clock().now().to_msg(),
                                         0.1))
        _wait(lambda: False, 3.0)
        assert counts and counts[-1]["cmd_vel_dropped"] > 0, counts[-1:]
        assert np.hypot(*(s.adapter.measured()[0][:2] - q0[:2])) < 0.01


def test_a_splice_that_turns_back_on_itself_starts_the_robot_where_it_is_along_the_turn(load_robot):
    """A turn on the spot under way (with the head panning along), spliced 0.6 s in and reversed after its commit
    instant: the reversal passes the robot's configuration again. The robot stands exactly where a sample of the
    reversal lies (so the nearest sampled configuration of the whole splice is on the reversal). The adapter's time
    along the splice is the robot's time along the turn less the 0.6 s where the test began the splice; the nearest
    configuration search would place it seconds later, beyond the commit instant."""
    from psprm_core.planning.execution import splice
    from psprm_core.tracking import CheckedPath

    robot = load_robot("stretch2")
    b = robot.config.base
    pan = robot.joint_names.index("joint_head_pan")

    def turn(q_a, dtheta, dpan):
        q_b = q_a.copy()
        q_b[2] += dtheta
        q_b[pan] += dpan
        return time_parameterize(np.array([q_a, q_b]), robot.velocity, robot.acceleration, dt=0.05,
                                 base_indices=(0, 1, 2), base_linear_limits=(b.linear_velocity, b.linear_acceleration),
                                 method="analytic")

    q0 = robot.default_configuration().copy()
    q0[:3] = [2.0, 2.0, 0.0]
    current = turn(q0, 1.2, 0.8)
    t_from, t_commit = 0.6, float(current.duration)
    sp = splice(current, t_from, t_commit, turn(current.evaluate([t_commit])[0][0], -1.2, -0.8), continuous=[2])
    # the splice as a message carries it: samples every 0.1 s
    t = np.arange(0.0, float(sp.duration), 0.1)
    P = sp.evaluate(t)[0]
    # the robot stands on a sample of the reversal, 0.3 s after the commit instant, at that heading on the turn
    k_back = int(np.searchsorted(t, t_commit - t_from + 0.3 * float(current.duration)))
    assert t[k_back] > t_commit - t_from, "precondition: the chosen sample lies on the reversal"
    target = P[k_back, 2]
    lo, hi = 0.0, t_commit
    for _ in range(60):  # the time along the turn at that heading (the heading rises monotonically)
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if current.evaluate([mid])[0][0][2] < target else (lo, mid)
    tau_robot = 0.5 * (lo + hi)
    q = current.evaluate([tau_robot])[0][0]
    assert tau_robot > t_from + 0.2, "precondition: the robot is past the splice's start"
    assert np.abs(q - P[k_back]).max() < 1e-6, "precondition: the robot stands on a sample of the reversal"
    # the ambiguity: the nearest sampled configuration of the whole splice lies on the reversal
    assert ad.progress_offset(t, P, q, (0.0, 0.0), 0.0, 6.0, robot.velocity) > t_commit - t_from
    executing = CheckedPath(robot, *(lambda tt: (tt, current.evaluate(tt)[0]))(np.arange(0.0, t_commit, 0.1)))
    got = ad.splice_progress(executing, tau_robot, t, P, 6.0, 0.01)
    assert got is not None
    assert abs(got - (tau_robot - t_from)) < 0.02, (got, tau_robot - t_from)
    # the configuration there is the robot's, as near as the reversal's (the adapter takes the splice's time then)
    from psprm_core.tracking import displacement
    d_s, d_n = displacement(robot, q, ad.sample_at(t, P, [got, t[k_back]]))
    assert d_s < 0.01 and d_s <= d_n + 0.01, (d_s, d_n)
