"""Stretch 2's driver rules (stretch_ros2 ``stretch_core`` and Stretch Body, written out here from their public
sources as numbers and cases, not taken from psprm's code) and the trajectory-mode goals the adapter builds.

The driver model (:mod:`psprm_ros.robots.sim_stretch`) is judged against those rules case by case; the goals
(:mod:`psprm_ros.robots.stretch`) against the rules too, and by what the driver model makes of them: the robot, its base
integrated from the wheels' motion, must stay within the path tolerance of a real planned trajectory (the planner's
own output on the main job's scene, compared with the robot's collision boxes, :class:`psprm_core.tracking.
CheckedPath`) and end where it ends."""

from __future__ import annotations

import math

import numpy as np
import pytest

from psprm_core.tracking import CheckedPath
from psprm_ros.robots import adapters as ad
from psprm_ros.robots import stretch as st
from psprm_ros.robots.sim_model import SimModel
from psprm_ros.robots.sim_stretch import (DRIVER_ERROR, INVALID_GOAL, StretchDriver, pose_diff)

DT = 0.02


@pytest.fixture(scope="module")
def robot(load_robot):
    return load_robot("stretch2")


@pytest.fixture(scope="module")
def planned(robot):
    """A real plan of the main job's scene (dynamic_person, south_to_either) from the planner."""
    from psprm_core.paths import resolve_named
    from psprm_core.perception.scoring import GeometricScorer
    from psprm_core.planning.factory import problem_configurations
    from psprm_core.planning.psprm import PSPRM, PSPRMSettings
    from psprm_core.planning.replanner import Replanner, ReplanSettings
    from psprm_core.scene import load_scene

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    scorer = GeometricScorer(scene, "person_face", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("person_face").center,
              PSPRMSettings().changed({"roadmap.n_nodes": 600, "seed": 5}))
    assert p.build()["success"]
    rp = Replanner(p, ReplanSettings(), targets=["person_face"])
    start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
    face = scene.target("person_face")
    rp.update_target("person_face", face.center, face.quat, stamp=0.0)
    rp.set_robot_state(start)
    rp.set_goals(goals)
    res = rp.replan(now=0.0)
    assert res.success
    return res.trajectory.times - res.trajectory.times[0], res.trajectory.positions


def _driver(robot, mode="trajectory", q0=None):
    cfg = ad.load_adapter("stretch2", robot)
    sim = SimModel(robot, cfg, robot.default_configuration() if q0 is None else q0)
    return StretchDriver(sim, mode), sim, cfg


def _points(goal):
    pts = [(goal.times[k], list(goal.positions[k]), list(goal.velocities[k])) for k in range(len(goal.times))]
    bp = [(goal.times[k], tuple(goal.base[k]), tuple(goal.base_twist[k])) for k in range(len(goal.times))]
    return pts, bp


def _run(drv, sim, until, t0=0.0):
    T, X = [], []
    for t in np.arange(t0, until, DT):
        drv.step(t, DT)
        sim.step(t, DT, base=drv.mode == "navigation")
        T.append(t)
        X.append(sim.q.copy())
    return np.array(T), np.array(X)


# ---------------------------------------------------------------------------------------------------------- the rules
def test_pose_diff_reads_segments_as_stretch_body_does():
    # hello_utils.get_pose_diff: (x, y) within 2 mm -> a rotation; heading within 0.02 rad and driving along it
    # (or against it) -> a translation; anything else -> no motion at all
    assert pose_diff((0, 0, 0), (0.001, 0.0, 0.5)) == (0.0, 0.5)
    assert pose_diff((0, 0, 0), (0.3, 0.0, 0.0)) == (0.3, 0.0)
    assert pose_diff((0, 0, math.pi / 2), (0.0, -0.2, math.pi / 2)) == pytest.approx((-0.2, 0.0))
    assert pose_diff((0, 0, 0), (0.3, 0.1, 0.2)) == (0.0, 0.0)  # drives and turns: nothing
    assert pose_diff((0, 0, 0), (0.3, 0.1, 0.0)) == (0.0, 0.0)  # drives sideways: nothing


def test_cmd_vel_only_in_navigation_mode(robot):
    drv, sim, _ = _driver(robot, "position")
    assert not drv.cmd_vel(0.2, 0.0, 0.0) and drv.counts["cmd_vel_dropped"] == 1
    drv.switch_mode("trajectory", 0.0)
    assert not drv.cmd_vel(0.2, 0.0, 0.1) and drv.counts["cmd_vel_dropped"] == 2
    x0 = sim.q[:2].copy()
    drv.switch_mode("navigation", 0.2)
    assert drv.cmd_vel(0.2, 0.0, 0.2)
    _run(drv, sim, 1.2, 0.2)
    assert np.hypot(*(sim.q[:2] - x0)) > 0.1  # it drove


def test_goals_within_the_window_are_rejected_and_a_newer_goal_preempts(robot):
    drv, sim, _ = _driver(robot)
    q = sim.q.copy()
    hold = st.hold_goal(["joint_lift"], q[[3]], hold_s=2.0)
    pts, bp = _points(hold)
    assert drv.goal_request(0.0)
    g1 = drv.execute(0.0, ["joint_lift"], pts, [], [], 0.0)
    assert g1.outcome is None
    assert not drv.goal_request(0.1)  # active and < 0.2 s after the last accepted one
    assert drv.counts["goals_rejected"] == 1
    assert drv.goal_request(0.25)
    g2 = drv.execute(0.0, ["joint_lift"], pts, [], [], 0.25)
    assert g1.outcome[0] == "aborted" and g2.outcome is None  # preempted, not failed
    del bp


@pytest.mark.parametrize("case", ["stamp", "close_waypoints", "far_start", "unknown_joint"])
def test_trajectory_mode_refuses_what_stretch_body_refuses(robot, case):
    drv, sim, _ = _driver(robot)
    q = sim.q
    lift = float(q[3])
    pts = [(0.0, [lift], [0.0]), (1.0, [lift + 0.05], [0.0])]
    stamp, names = 0.0, ["joint_lift"]
    if case == "stamp":
        stamp = 100.0  # a stamp other than 0
    elif case == "close_waypoints":
        pts = [(0.0, [lift], [0.0]), (0.5, [lift + 0.05], [0.0])]  # 0.5 s apart: "the same time"
    elif case == "far_start":
        pts = [(0.0, [lift + 0.2], [0.0]), (1.0, [lift + 0.25], [0.0])]
    else:
        names = ["joint_elbow"]
    g = drv.execute(stamp, names, pts, [], [], 0.0)
    assert g.outcome is not None and g.outcome[0] == "aborted"
    _run(drv, sim, 1.5)
    assert sim.q[3] == pytest.approx(lift)  # nothing moved


def test_navigation_mode_aborts_goals_and_runstop_halts_everything(robot):
    drv, sim, _ = _driver(robot, "navigation")
    lift = float(sim.q[3])
    g = drv.execute(0.0, ["joint_lift"], [(0.0, [lift], [0.0]), (1.0, [lift + 0.1], [0.0])], [], [], 0.0)
    assert g.outcome[:2] == ("aborted", DRIVER_ERROR)
    drv.switch_mode("trajectory", 0.0)
    g = drv.execute(0.0, ["joint_lift"], [(0.0, [lift], [0.0]), (2.0, [lift + 0.2], [0.0])], [], [], 0.0)
    _run(drv, sim, 0.5)
    moved = float(sim.q[3])
    assert moved > lift
    drv.set_runstop(True, 0.5)
    _run(drv, sim, 1.5, 0.5)
    assert sim.q[3] == pytest.approx(moved)  # halted at once
    g = drv.execute(0.0, ["joint_lift"], [(0.0, [moved], [0.0]), (1.0, [lift], [0.0])], [], [], 1.5)
    assert g.outcome[:2] == ("aborted", INVALID_GOAL)
    drv.set_runstop(False, 2.0)
    assert drv.mode == "trajectory"


def test_a_cancel_does_not_halt_trajectory_mode_but_stop_the_robot_does(robot):
    drv, sim, _ = _driver(robot)
    lift = float(sim.q[3])
    drv.execute(0.0, ["joint_lift"], [(0.0, [lift], [0.0]), (2.0, [lift + 0.2], [0.0])], [], [], 0.0)
    _run(drv, sim, 0.5)
    drv.cancel(0.5)
    _, X = _run(drv, sim, 1.0, 0.5)
    assert X[-1, 3] > X[0, 3] + 0.01  # still moving after the cancel
    drv.stop_the_robot(1.0)
    _, X = _run(drv, sim, 1.6, 1.0)
    assert np.ptp(X[:, 3]) == 0.0  # the first step after the stop already stands still


# ---------------------------------------------------------------------------------------------------------- goals
def test_goal_obeys_the_driver_rules(robot, planned):
    t, P = planned
    cfg = ad.load_adapter("stretch2", robot)
    g = st.goal_for_controller(cfg.controllers[0], robot.joint_names, t, P)
    # stretch_body: first waypoint at 0 and identity; waypoints > 0.8 s apart; each base segment pure
    assert g.times[0] == 0.0 and np.allclose(g.base[0], 0.0)
    assert np.diff(g.times).min() > 0.8
    for a, b in zip(g.base[:-1], g.base[1:]):
        tr, rot = pose_diff(a, b)
        moved = np.hypot(*(b[:2] - a[:2])) > 2e-3 or abs(b[2] - a[2]) > 2e-2
        assert not moved or (tr, rot) != (0.0, 0.0), (a, b)
    assert g.joint_names == ["joint_lift", "wrist_extension", "joint_wrist_yaw", "joint_head_pan", "joint_head_tilt"]
    # the robot's own time stretched by at most a few percent (short base phases take 0.9 s)
    assert t[-1] <= g.duration <= 1.1 * t[-1]


def test_the_driver_executes_a_real_plan_within_the_path_tolerance(robot, planned):
    t, P = planned
    drv, sim, cfg = _driver(robot, q0=P[0].copy())
    g = st.goal_for_controller(cfg.controllers[0], robot.joint_names, t, P)
    pts, bp = _points(g)
    assert drv.goal_request(0.0)
    G = drv.execute(0.0, g.joint_names, pts, [st.BASE_JOINT], bp, 0.0)
    T, X = _run(drv, sim, g.duration + 0.5)
    assert G.outcome[0] == "succeeded" and not drv.aborts
    # judged against the plan: every configuration the robot passed lies within 2 cm (the adapter's
    # max_goal_deviation_m; the path tolerance is 4 cm) of the planned configurations near the same instant
    Pg = st.planned_positions(t, P, g.planned_time(T))
    dev = CheckedPath(robot, T, Pg).deviations(X, T, 2.0)
    assert dev.max() < 0.02, dev.max()
    assert np.allclose(X[-1], P[-1], atol=1e-3)
    # and the adapter's own prediction of it is what the driver did
    B, J = st.executed(g, P[0, :3], T)
    assert np.abs(B[:, :2] - X[:, :2]).max() < 1e-6 and np.abs(J - X[:, 3:]).max() < 1e-6


def test_a_base_segment_that_drives_and_turns_moves_nothing(robot):
    # what happens to a goal built without the rules: the driver reads the curved base segment as no motion
    drv, sim, _ = _driver(robot)
    x0 = sim.q[:3].copy()
    bp = [(0.0, (0.0, 0.0, 0.0), (0.0, 0.0)), (2.0, (0.4, 0.1, 0.3), (0.0, 0.0))]
    g = drv.execute(0.0, [], [], [st.BASE_JOINT], bp, 0.0)
    _run(drv, sim, 2.5)
    assert g.outcome[0] == "succeeded" and np.allclose(sim.q[:3], x0)
