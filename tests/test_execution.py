"""Replanning a robot in motion (psprm_core.planning.execution and Replanner.replan with the robot's time along its
trajectory): the spliced trajectory reproduces the one under way up to the commitment, which is an instant where
that trajectory rests (finite differences of its own positions), it stays within the velocity and acceleration
limits across the splice (finite differences), never collides (pybullet and a checker built afresh from the test's
own record of the poses it sent), and ends at a goal; a robot at rest replans from where it is; an obstacle moved
into the committed motion makes the replan fail and drops the plan; progress along a trajectory against a brute-force
search."""

from __future__ import annotations

import numpy as np
import pytest

from psprm_core.errors import InputError
from psprm_core.geometry import yaw_to_quat
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.execution import Execution, commit_time, progress_time, rest_times, splice
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.replanner import Replanner, ReplanSettings
from psprm_core.scene import load_scene

from judges import Judge, SentPoses, limit_ratios, same_config  # noqa: E402

N_NODES = 600


@pytest.fixture(scope="module")
def world(load_robot):
    return load_scene(resolve_named("scene", "dynamic_person")), load_robot("stretch2")


@pytest.fixture(scope="module")
def saved_roadmap(world, tmp_path_factory):
    scene, robot = world
    scorer = GeometricScorer(scene, "person_face", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("person_face").center,
              PSPRMSettings().changed({"roadmap.n_nodes": N_NODES, "seed": 5}))
    assert p.build()["success"]
    return p.save(tmp_path_factory.mktemp("roadmap") / "dp.npz")


def _replanner(world, saved_roadmap, **settings):
    scene, robot = world
    scorer = GeometricScorer(scene, "person_face", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("person_face").center,
              PSPRMSettings().changed({"roadmap.n_nodes": N_NODES, "seed": 5}))
    p.load(saved_roadmap)
    rp = Replanner(p, ReplanSettings(**settings), targets=["person_face"])
    start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
    face = scene.target("person_face")
    rp.update_target("person_face", face.center, face.quat, stamp=0.0)
    rp.set_robot_state(start)
    rp.set_goals(goals)
    res = rp.replan(now=0.0)
    assert res.success and res.trajectory is not None, res.reason
    return rp, start, goals


def _speed(traj, t: float, h: float = 1e-3) -> float:
    """Largest joint speed of ``traj`` around ``t``, by central differences of its positions."""
    a, b = traj.evaluate([max(0.0, t - h)])[0][0], traj.evaluate([t + h])[0][0]
    return float(np.abs(b - a).max() / (2 * h))


@pytest.mark.parametrize("fraction", [0.15, 0.45])
def test_replan_in_motion_is_spliced_onto_the_trajectory_under_way(world, saved_roadmap, fraction):
    scene, robot = world
    rp, start, goals = _replanner(world, saved_roadmap)
    old = rp.result.trajectory
    t_robot = fraction * old.duration
    assert _speed(old, t_robot) > 0.05, "precondition: the robot is moving at that instant"
    q_robot = old.evaluate([t_robot])[0][0]
    rp.set_robot_state(q_robot, t_along=t_robot)
    rp.set_goals(goals[1:])  # a new goal: the replan is adopted
    res = rp.replan(now=5.0, triggers=["goal_changed"], horizon_s=0.4)
    assert res.success and not res.kept, res.reason
    new = res.trajectory
    assert res.start_offset_s == pytest.approx(t_robot)
    assert res.committed_s >= 0.4 - 1e-9
    # the committed part is the old trajectory, sample for sample, from where the robot was
    ts = np.linspace(0.0, res.committed_s, 60)
    assert np.abs(new.evaluate(ts)[0] - old.evaluate(ts + t_robot)[0]).max() < 1e-9
    # ... and the old trajectory rests at the commitment (judged from its positions)
    assert _speed(old, t_robot + res.committed_s) < 0.02
    # continuous across the splice: within the limits by finite differences (a jump or a velocity step would not be)
    ratios = limit_ratios(new, robot, dt=4e-3)
    assert max(ratios.values()) <= 1.05, ratios
    # ends at the new goal
    assert same_config(new.evaluate([new.duration])[0][0], goals[1], tol=2e-3)
    # collision-free against the poses the test sent (none moved): pybullet and a fresh checker
    judge = Judge(robot, SentPoses("dynamic_person"))
    try:
        samples = new.evaluate(np.arange(0.0, new.duration, 0.05))[0]
        assert not judge.colliding(samples, exact_every=4).any()
    finally:
        judge.close()


def test_a_robot_at_rest_replans_from_where_it_is(world, saved_roadmap):
    rp, start, goals = _replanner(world, saved_roadmap)
    old = rp.result.trajectory
    q = old.evaluate([0.3 * old.duration])[0][0]
    rp.set_robot_state(q)  # no time along the trajectory: at rest where it is
    rp.set_goals(goals[1:])
    res = rp.replan(now=5.0, triggers=["goal_changed"])
    assert res.success, res.reason
    assert res.committed_s == 0.0 and res.start_offset_s == 0.0
    assert same_config(res.trajectory.evaluate([0.0])[0][0], q, tol=0.05)
    assert _speed(res.trajectory, 0.0) < 0.05


def test_commit_off_replans_from_the_robots_state(world, saved_roadmap):
    rp, start, goals = _replanner(world, saved_roadmap, commit=False)
    old = rp.result.trajectory
    t = 0.3 * old.duration
    q = old.evaluate([t])[0][0]
    rp.set_robot_state(q, t_along=t)
    rp.set_goals(goals[1:])
    res = rp.replan(now=5.0, triggers=["goal_changed"])
    assert res.success and res.committed_s == 0.0


def test_an_obstacle_moved_into_the_committed_motion_fails_the_replan(world, saved_roadmap):
    scene, robot = world
    rp, start, goals = _replanner(world, saved_roadmap)
    old = rp.result.trajectory
    rests = rest_times(old)
    # a stretch where the base drives: put the chair on the base's path a little ahead of the robot
    t_robot = None
    for a, b in zip(rests[:-1], rests[1:]):
        qa, qb = old.evaluate([a, b])[0]
        if b - a > 1.0 and np.hypot(*(qb[:2] - qa[:2])) > 0.3:
            t_robot = a + 0.1
            break
    assert t_robot is not None, "precondition: the plan drives the base somewhere"
    t_c = commit_time(old, t_robot, 0.3)
    q_robot = old.evaluate([t_robot])[0][0]
    q_mid = old.evaluate([0.5 * (t_robot + t_c)])[0][0]
    chair = scene.obstacle("chair")
    center = np.array([q_mid[0] + 0.3 * np.cos(q_mid[2]), q_mid[1] + 0.3 * np.sin(q_mid[2]), chair.center[2]])
    sent = SentPoses("dynamic_person")
    sent.sent("chair", center, yaw_to_quat(0.0))
    judge = Judge(robot, sent)
    try:
        prefix = old.evaluate(np.linspace(t_robot, t_c, 40))[0]
        assert judge.colliding(prefix).any(), "precondition: the chair is in the committed motion"
    finally:
        judge.close()
    rp.update_obstacle("chair", center, yaw_to_quat(0.0))
    rp.set_robot_state(q_robot, t_along=t_robot)
    res = rp.replan(now=5.0, triggers=["collision"], horizon_s=0.3)
    assert not res.success and "committed" in res.reason
    assert rp.result is None  # the caller must stop


def test_progress_time_against_brute_force(world, saved_roadmap):
    scene, robot = world
    rp, _, _ = _replanner(world, saved_roadmap)
    traj = rp.result.trajectory
    rng = np.random.default_rng(0)
    grid = np.arange(0.0, traj.duration, 0.001)
    P = traj.evaluate(grid)[0]
    for t_true in rng.uniform(0.5, traj.duration - 0.5, 12):
        q = traj.evaluate([t_true])[0][0] + rng.normal(0, 0.002, robot.dof)
        t = progress_time(traj, q, t_true + rng.uniform(-0.8, 0.8), window_s=1.5, scale=robot.velocity,
                          angle_cols=[2])
        d = np.abs(P - q)
        d[:, 2] = np.abs((d[:, 2] + np.pi) % (2 * np.pi) - np.pi)
        near = (d / robot.velocity).max(1)
        best = near.min()
        # the found time is (within the search's 20 ms grid) as near as the nearest in a 1 ms brute force
        t_idx = int(np.argmin(np.abs(grid - t)))
        assert near[t_idx] <= best + 0.02 * 1.0 + 1e-6


def test_splice_refuses_trajectories_that_do_not_meet_at_rest(world, saved_roadmap):
    rp, _, _ = _replanner(world, saved_roadmap)
    traj = rp.result.trajectory
    moving = 0.3 * traj.duration
    assert _speed(traj, moving) > 0.05
    with pytest.raises(InputError):
        splice(traj, 0.0, moving, traj)  # the commitment is not a rest instant
    with pytest.raises(InputError):
        Execution(float("nan"))


def test_a_withdrawn_replan_leaves_the_trajectory_under_way_current(world, saved_roadmap):
    """A caller that cannot hand a replan to the robot (its final check refused it, or it came too late to splice)
    withdraws it: the next replan commits along the trajectory the robot executes (the one the test holds), not
    along the withdrawn one, and the goal change that asked for the replan is still pending."""
    scene, robot = world
    rp, start, goals = _replanner(world, saved_roadmap)
    current = rp.result
    old = current.trajectory
    t_robot = 0.3 * old.duration
    rp.set_robot_state(old.evaluate([t_robot])[0][0], t_along=t_robot)
    rp.set_goals(goals[1:])
    refused = rp.replan(now=5.0, triggers=["goal_changed"], horizon_s=0.4)
    assert refused.success and not refused.kept and rp.result is refused
    # the robot goes on along the old trajectory
    assert rp.withdraw(refused) and rp.withdrawn == 1
    assert rp.result is current and not rp.withdraw(refused)
    assert rp.needs_replan(now=5.1), "the goal change is still pending"
    t2 = t_robot + refused.committed_s + 1.0  # past the withdrawn plan's splice: the two have parted
    assert t2 < old.duration - 2.0
    rp.set_robot_state(old.evaluate([t2])[0][0], t_along=t2)
    res = rp.replan(now=5.5, triggers=["goal_changed"], horizon_s=0.4)
    assert res.success and not res.kept, res.reason
    ts = np.linspace(0.0, res.committed_s, 40)
    assert np.abs(res.trajectory.evaluate(ts)[0] - old.evaluate(ts + t2)[0]).max() < 1e-9
    # the withdrawn plan's own motion from that time differs (else the check above could not tell them apart)
    other = refused.trajectory.evaluate(ts + t2 - t_robot)[0]
    assert np.abs(other - old.evaluate(ts + t2)[0]).max() > 0.01
    assert same_config(res.trajectory.evaluate([res.trajectory.duration])[0][0], goals[1], tol=2e-3)


class _ForthAndBack:
    """A base driving 10 cm along y and back over 1 s (y = 0.1 sin(pi t)), drifting 3 mm along x meanwhile, the other
    joints at ``q0``: it passes each y twice, the return pass 0.7 s after the outbound one (trajectory-like:
    ``duration``, ``evaluate``)."""

    duration = 1.0

    def __init__(self, q0):
        self.q0 = np.asarray(q0, float)

    def evaluate(self, ts):
        ts = np.clip(np.atleast_1d(np.asarray(ts, float)), 0.0, self.duration)
        P = np.repeat(self.q0[None], len(ts), 0)
        V = np.zeros_like(P)
        P[:, 0] += 0.003 * ts
        P[:, 1] += 0.1 * np.sin(np.pi * ts)
        V[:, 0], V[:, 1] = 0.003, 0.1 * np.pi * np.cos(np.pi * ts)
        return P, V, np.zeros_like(P)


def test_progress_time_takes_the_pass_the_clock_points_to_on_a_trajectory_that_comes_back(world):
    """The robot on the outbound pass at 0.16 s, 1.5 mm from it and 0.5 mm from the return pass at 0.84 s (the x
    drift): the nearest configuration alone is the return pass; with ``tie`` the pass nearest the clock (0.1 s)."""
    scene, robot = world
    traj = _ForthAndBack(robot.default_configuration())
    q = traj.evaluate([0.16])[0][0]
    q[0] = traj.q0[0] + 0.002  # between the passes' x (0.00045 outbound, 0.00255 return)
    kw = dict(window_s=1.5, scale=robot.velocity, angle_cols=[2])
    assert abs(progress_time(traj, q, 0.1, **kw) - 0.84) < 0.03, "precondition: the return pass is the nearer"
    assert abs(progress_time(traj, q, 0.1, tie=0.1, **kw) - 0.16) < 0.03
    # a clock pointing past the return pass takes it
    assert abs(progress_time(traj, q, 0.9, tie=0.1, **kw) - 0.84) < 0.03


def test_the_servers_progress_estimate_takes_the_pass_the_clock_points_to(world):
    """The roadmap server's estimate of the robot's time along the trajectory under way
    (:meth:`psprm_ros.server.robot_motion.RobotMotion.time_along`) on the same forth-and-back motion: the robot 0.1 s
    after the trajectory's start by the clock, measured on the outbound pass, is placed there (a splice from the
    return pass would reverse a base still driving out)."""
    import time

    from psprm_ros.server.robot_motion import RobotMotion

    scene, robot = world
    traj = _ForthAndBack(robot.default_configuration())
    q = traj.evaluate([0.16])[0][0]
    q[0] = traj.q0[0] + 0.002
    motion = RobotMotion(robot)
    now = time.monotonic()
    motion.add(traj.evaluate([0.0])[0][0], now - 0.15)
    motion.add(q, now)
    t = motion.time_along(traj, time.perf_counter() - 0.1, q, 0.04)
    assert t is not None and abs(t - 0.16) < 0.05, t
