"""The robot adapter's trajectory acceptance without ROS: :class:`psprm_ros.robots.acceptance.TrajectoryAcceptance`
driven directly with trajectories this file builds (a base driving straight at 0.3 m/s, the other joints held), the
shipped Stretch adapter on its JointTrajectory topics (base on cmd_vel). Each verdict is judged against the arrays
the test made: where the robot stands on them, how far it is off them. :class:`psprm_ros.robots.execution.Execution`
runs on a recording port and recording controller links: what it sent, held and asked for."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from psprm_core.tracking import CheckedPath
from psprm_ros.robots import adapters as ad
from psprm_ros.robots.acceptance import (REST_S, REST_WAIT_S, SPLICE_TOL_M, RestWatch, TrajectoryAcceptance,
                                         UnderWay, path_check)
from psprm_ros.robots.base_follower import BaseFollower, Gains, Limits
from psprm_ros.robots.execution import Execution

SPEED = 0.3  # m/s along x
DT = 0.05
TOL = 0.04  # path_tolerance_m (the adapter's default)
WINDOW = 2.0  # path_window_s


@pytest.fixture
def stretch(load_robot):
    robot = load_robot("stretch2")
    cfg = ad.load_adapter("stretch2", robot).with_interface("topic")
    acc = TrajectoryAcceptance(robot, cfg, robot.joint_names, Limits.for_robot(robot, cfg.base))
    q0 = np.asarray(robot.default_configuration(), float).copy()
    q0[:3] = [1.0, 1.0, 0.0]
    return robot, cfg, acc, q0


def drive(q0: np.ndarray, duration: float, t_from: float = 0.0) -> tuple:
    """(t, P): the base driving along +x at SPEED from ``q0`` (its position at time 0), from ``t_from`` on, times
    from 0; the other joints held."""
    t = np.arange(0.0, duration - t_from + 1e-9, DT)
    P = np.repeat(q0[None], len(t), 0)
    P[:, 0] = q0[0] + SPEED * (t + t_from)
    return t, P


def test_a_trajectory_starting_10_cm_beside_the_measured_base_is_refused_by_the_path_tolerance(stretch):
    robot, cfg, acc, q0 = stretch
    t, P = drive(q0, 3.0)
    q = q0.copy()
    q[1] += 0.10  # the robot stands 10 cm to the side of the whole path: no progress along it brings it nearer
    v = acc.decide(t, P, None, q, (0.0, 0.0), None, TOL, WINDOW)
    assert not v.accepted and not v.spliced and not v.stop
    assert "path tolerance 0.04 m" in v.reason, v.reason
    assert "no trajectory under way" in v.reason, v.reason
    # the distance named is at least the base's offset (every point of the robot is moved by it)
    d = float(v.reason.split(" comes ")[1].split(" m ")[0])
    assert d >= 0.10 - 1e-3, v.reason


def test_the_same_trajectory_from_the_measured_base_is_accepted_from_its_start(stretch):
    robot, cfg, acc, q0 = stretch
    t, P = drive(q0, 3.0)
    v = acc.decide(t, P, None, q0, (0.0, 0.0), None, TOL, WINDOW)
    assert v.accepted and not v.reason and not v.spliced
    assert v.progress == 0.0 and np.allclose(v.positions, P) and np.allclose(v.times, t)
    assert v.lead == pytest.approx(max([c.lead_time_s for c in cfg.controllers] + [cfg.base.lead_time_s]))
    assert v.checked is not None and v.received is not None


def test_a_trajectory_repeating_the_one_under_way_for_its_first_0_3_s_is_a_splice_started_where_the_robot_is(stretch):
    robot, cfg, acc, q0 = stretch
    t1, P1 = drive(q0, 4.0)  # under way; the robot is 1.0 s along it, moving at SPEED
    tau = 1.0
    q = q0.copy()
    q[0] = q0[0] + SPEED * tau
    under_way = UnderWay(CheckedPath(robot, t1, P1), (CheckedPath(robot, t1, P1), 0.0), tau, True)
    # the replan began 0.7 s into the trajectory under way: the splice repeats it from there (its first 0.3 s and
    # more), then goes on
    t2, P2 = drive(q0, 4.0, t_from=0.7)
    assert np.abs(P2[:7] - np.stack([np.interp(t2[:7] + 0.7, t1, P1[:, j]) for j in range(P1.shape[1])], 1)).max() \
        < 1e-9, "precondition: the new trajectory repeats the one under way over its first 0.3 s"
    v = acc.decide(t2, P2, None, q, (SPEED, 0.0), under_way, TOL, WINDOW)
    assert v.accepted and v.spliced and not v.stop and not v.reason, v.reason
    assert v.lead == 0.0  # the base goes on from where it is: no lead, no restart
    assert v.progress == pytest.approx(tau - 0.7, abs=0.05)
    # the accepted trajectory starts where the robot stands
    assert abs(v.positions[0, 0] - q[0]) < SPLICE_TOL_M and abs(v.positions[0, 1] - q[1]) < 1e-9


def test_a_trajectory_leaving_the_one_under_way_at_once_is_no_splice(stretch):
    robot, cfg, acc, q0 = stretch
    t1, P1 = drive(q0, 4.0)
    q = q0.copy()
    q[0] += SPEED * 1.0
    under_way = UnderWay(CheckedPath(robot, t1, P1), (CheckedPath(robot, t1, P1), 0.0), 1.0, True)
    t2, P2 = drive(q, 3.0)
    P2[:, 1] = q[1] + 0.2 * t2  # drifts sideways from its first instant: within 0.3 s 6 cm off the path under way
    d, why, at = acc.splice(t2, P2, q, under_way, WINDOW)
    assert d is None and at is None and f"splice tolerance {SPLICE_TOL_M:g} m" in why, why
    stopped = UnderWay(under_way.checked, under_way.received, 1.0, False)
    assert acc.splice(t2, P2, q, stopped, WINDOW)[1] == "the trajectory under way has ended or was stopped"


def test_a_controller_joint_off_by_more_than_its_start_tolerance_is_refused_naming_the_joint(stretch):
    robot, cfg, acc, q0 = stretch
    t, P = drive(q0, 3.0)
    lift = robot.joint_names.index("joint_lift")
    c = cfg.controller("stretch_controller")
    P[:, lift] = q0[lift] + c.start_tolerance + 0.05  # the whole plan holds the lift this far from the measured one
    v = acc.decide(t, P, None, q0, (0.0, 0.0), None, TOL, WINDOW)
    assert not v.accepted
    assert v.reason == (f"first point {c.start_tolerance + 0.05:.3f} from the measured joint_lift "
                        f"(stretch_controller: tolerance {c.start_tolerance})"), v.reason


def test_a_splice_starting_ahead_of_the_robot_is_joined_along_the_trajectory_under_way(stretch):
    """The server's estimate of the robot's progress may lead the adapter's: a splice that begins 0.2 s (6 cm) ahead
    of the robot on the trajectory under way. What is executed leads from the robot along the trajectory under way
    to the splice's start and then follows the splice, and the path tolerance at the robot's first control step
    holds (the splice alone starts 6 cm ahead of it)."""
    robot, cfg, acc, q0 = stretch
    t1, P1 = drive(q0, 4.0)
    tau = 1.0
    q = q0.copy()
    q[0] = q0[0] + SPEED * tau
    under_way = UnderWay(CheckedPath(robot, t1, P1), (CheckedPath(robot, t1, P1), 0.0), tau, True)
    t2, P2 = drive(q0, 4.0, t_from=1.2)  # the splice: the trajectory under way from 1.2 s on
    assert P2[0, 0] - q[0] == pytest.approx(0.06), "precondition: the splice starts 6 cm ahead of the robot"
    assert path_check(CheckedPath(robot, t2, P2), q, 0.0, TOL, WINDOW)[1], "precondition: off the splice alone"
    v = acc.decide(t2, P2, None, q, (SPEED, 0.0), under_way, TOL, WINDOW)
    assert v.accepted and v.spliced and not v.reason, v.reason
    assert abs(v.positions[0, 0] - q[0]) < SPLICE_TOL_M and np.abs(v.positions[0, 1:] - q[1:]).max() < 1e-9
    # it reaches the splice's start 0.2 s later, on the trajectory under way, and then is the splice
    k = int(np.argmin(np.abs(v.times - v.times[0] - 0.2)))
    assert abs(v.times[k] - v.times[0] - 0.2) < 1e-6 and np.abs(v.positions[k] - P2[0]).max() < 1e-9
    assert np.abs(v.positions[k:] - P2[:len(v.positions) - k]).max() < 1e-9
    assert np.all(np.diff(v.times) > 0)
    d, why = path_check(v.checked, q, 0.0, TOL, WINDOW)
    assert not why and d < SPLICE_TOL_M, why


def test_a_splice_from_the_clock_of_a_robot_lagging_its_trajectory_is_joined_from_where_the_robot_is(stretch):
    """A robot that lags its trajectory's clock (0.2 s, 6 cm, as a base turning on the spot slower than planned): a
    splice that begins at the clock's configuration lies ahead of it. What is executed leads from the robot's
    configuration along the trajectory under way to the splice, and the path tolerance holds at the robot."""
    robot, cfg, acc, q0 = stretch
    t1, P1 = drive(q0, 4.0)
    tau = 1.0  # the clock
    q = q0.copy()
    q[0] = q0[0] + SPEED * 0.8  # where the robot is
    under_way = UnderWay(CheckedPath(robot, t1, P1), (CheckedPath(robot, t1, P1), 0.0), tau, True)
    t2, P2 = drive(q0, 4.0, t_from=1.0)
    v = acc.decide(t2, P2, None, q, (SPEED, 0.0), under_way, TOL, WINDOW)
    assert v.accepted and v.spliced and not v.reason, v.reason
    assert np.abs(v.positions[0] - q).max() < SPLICE_TOL_M
    k = int(np.argmin(np.abs(v.times - v.times[0] - 0.2)))
    assert np.abs(v.positions[k] - P2[0]).max() < SPLICE_TOL_M
    d, why = path_check(v.checked, q, 0.0, TOL, WINDOW)
    assert not why and d < SPLICE_TOL_M, why


def test_a_splice_is_taken_while_the_head_lags_the_trajectory_under_way_and_a_new_start_is_not(stretch):
    """The head pans at 0.5 rad/s while the base drives; the measured head lags the trajectory under way by more than
    the controller's start tolerance. A splice (repeating that trajectory) continues what the controller follows and
    is taken; a trajectory from the commanded head angle that is no splice, and a splice whose head leaves the
    trajectory under way, are refused for the head's start."""
    robot, cfg, acc, q0 = stretch
    pan = robot.joint_names.index("joint_head_pan")
    c = next(c for c in cfg.controllers if "joint_head_pan" in c.joints)
    lag = c.start_tolerance + 0.15
    t1, P1 = drive(q0, 4.0)
    P1[:, pan] = q0[pan] - 0.5 * t1  # the head pans on at 0.5 rad/s
    tau = 1.0
    q = np.array([np.interp(tau, t1, P1[:, j]) for j in range(robot.dof)])
    q[pan] += lag  # the measured head lags the one commanded at the robot's time
    under_way = UnderWay(CheckedPath(robot, t1, P1), (CheckedPath(robot, t1, P1), 0.0), tau, True)
    t2 = t1[t1 <= 3.3]
    P2 = np.stack([np.interp(t2 + 0.7, t1, P1[:, j]) for j in range(robot.dof)], 1)  # the splice, from 0.7 s on
    v = acc.decide(t2, P2, None, q, (SPEED, 0.0), under_way, 0.1, WINDOW)
    assert v.accepted and v.spliced and not v.reason, v.reason
    # it starts at the robot's time on the trajectory under way: the head lags it as much as before
    assert abs(v.positions[0, pan] - (q[pan] - lag)) < 0.05
    assert abs(v.positions[0, pan] - q[pan]) > c.start_tolerance
    # not a splice (nothing under way): the same start is refused for the head
    w = acc.decide(t2, P2, None, q, (SPEED, 0.0), None, 0.1, WINDOW)
    assert not w.accepted and "joint_head_pan" in w.reason and "from the measured joint_head_pan" in w.reason, w.reason
    # a splice whose head is 0.3 rad beyond the trajectory under way at once: neither measured nor commanded is near
    P3 = P2.copy()
    P3[:, pan] -= 0.3
    x = acc.decide(t2, P3, None, q, (SPEED, 0.0), under_way, 0.1, WINDOW)
    assert not x.accepted and "joint_head_pan" in x.reason, x.reason


def test_the_path_check_stops_a_robot_off_the_checked_path_and_the_rest_watch_waits_for_rest(stretch):
    robot, cfg, acc, q0 = stretch
    t, P = drive(q0, 3.0)
    checked = CheckedPath(robot, t, P)
    q = np.interp(1.0, t, P[:, 0])
    on = P[0].copy()
    on[0] = q
    assert path_check(checked, on, 1.0, TOL, WINDOW)[1] == ""
    off = on.copy()
    off[1] += 0.06
    d, why = path_check(checked, off, 1.0, TOL, WINDOW)
    assert d >= 0.06 - 1e-3 and why.startswith("off the checked path") and "path tolerance 0.04 m" in why
    assert path_check(checked, off, 1.0, 0.0, WINDOW)[1] == ""  # tolerance 0: off
    rest = RestWatch()
    rest.pending = why
    assert RestWatch.moving((0.2, 0.0)) and not RestWatch.moving((0.0, 0.0))
    assert not rest.due(10.0, (0.2, 0.0))  # still braking
    assert not rest.due(10.05, (0.0, 0.0))  # at rest, not yet for REST_S
    assert rest.due(10.05 + REST_S + 1e-6, (0.0, 0.0))
    rest.clear()
    assert rest.pending == "" and not rest.due(20.0, (0.3, 0.0)) and rest.due(20.0 + REST_WAIT_S, (0.3, 0.0))


class Port:
    """The node's side of :class:`Execution`, recorded: a robot standing at ``q`` at rest."""

    active = True

    def __init__(self, q):
        self.q, self.t, self.vel = np.asarray(q, float), 100.0, np.zeros(2)
        self.replans, self.statuses = [], []

    def now(self):
        return self.t

    def measured(self):
        return self.q.copy(), ""

    def base_velocity(self):
        return self.vel.copy()

    def last_joints(self):
        return self.q.copy()

    def status(self, text, level="info"):
        self.statuses.append((level, text))

    def request_replan(self, why):
        self.replans.append(why)
        return True

    def call_driver(self, name):
        return None


class Links:
    """Controller links that record what they are given (every controller listening, no goal interval)."""

    def __init__(self):
        self.sent, self.holds, self.twists = [], [], []

    def missing(self):
        return []

    def offer(self, c, item, now):
        return item

    def due(self, now):
        return []

    def send(self, c, cmd):
        self.sent.append(cmd)

    def halt(self, names, q, now):
        self.holds.append(None if q is None else np.asarray(q, float).copy())

    def publish_twist(self, v, w):
        self.twists.append((v, w))


def _execution(robot, cfg, q):
    counts = {k: 0 for k in ("trajectories", "executed", "refused", "stops", "goals_sent", "spliced", "goals_deferred",
                             "twists", "off_path_stops", "goals_rejected", "goals_failed", "runstops",
                             "mode_switches", "held_until_rest")}
    port, links = Port(q), Links()
    ex = Execution(port, robot, robot.joint_names, {"path_tolerance_m": TOL, "path_window_s": WINDOW}, counts,
                   threading.RLock())
    b = cfg.base
    follower = BaseFollower(Limits.for_robot(robot, b), Gains(b.k_x, b.k_y, b.k_theta), b.goal_tolerance_m,
                            b.goal_tolerance_rad, b.settle_s, b.preview_s)
    ex.configure(cfg, links, follower)
    return ex, port, links, counts


def test_an_accepted_trajectory_goes_to_every_controller_and_the_base_follower(stretch):
    robot, cfg, acc, q0 = stretch
    ex, port, links, counts = _execution(robot, cfg, q0)
    t, P = drive(q0, 3.0)
    assert ex.execute(t, P, lambda: None)
    assert counts["executed"] == 1 and counts["refused"] == 0 and not links.holds
    assert [c.controller for c in links.sent] == [c.name for c in cfg.controllers]
    lift = robot.joint_names.index("joint_lift")
    cmd = links.sent[0]
    assert np.allclose(cmd.positions[:, cmd.joint_names.index("joint_lift")], P[:, lift])
    assert not ex.follower.done and ex.follower.t0 == pytest.approx(port.t + acc.lead())


def test_a_refused_trajectory_stops_the_robot_and_asks_for_a_plan_once_the_base_rests(stretch):
    robot, cfg, acc, q0 = stretch
    q = q0.copy()
    q[1] += 0.10
    ex, port, links, counts = _execution(robot, cfg, q)
    t, P = drive(q0, 3.0)
    assert not ex.execute(t, P, lambda: None)
    assert counts["refused"] == 1 and counts["stops"] == 1 and not links.sent
    assert len(links.holds) == 1 and np.allclose(links.holds[0], q)  # held where the robot stands
    assert links.twists == [(0.0, 0.0)]
    assert "path tolerance" in ex.last_refusal and ex.rest.pending == ex.last_refusal
    assert port.replans == []  # not while the base may still brake
    for _ in range(10):  # the base at rest: the plan is asked for after REST_S
        port.t += 0.05
        ex.tick()
    assert port.replans == [ex.last_refusal] and ex.rest.pending == ""
