"""Bodies that turn in place (a person's body): the swept box holds the body at every heading, the turning watch
tells a turn in place from a walk or a carried chair, and once a body has turned in place the planner accepts no
configuration that its next turn would hit (judged by pybullet with the body rotated through every heading), while
paths are still judged against the body where it is, and the rule lets go after its hold time."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.geometry import quat_to_matrix, yaw_to_quat
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.replanner import Replanner, ReplanSettings
from psprm_core.prediction import TurningWatch
from psprm_core.scene import Box, load_scene

from judges import Judge, SentPoses  # noqa: E402

HEADINGS = np.linspace(0.0, np.pi, 25)  # a box's footprint repeats every half turn


def _corners(center, size, rot) -> np.ndarray:
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return (0.5 * s * np.asarray(size)) @ np.asarray(rot).T + np.asarray(center)


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_a_swept_box_holds_the_box_at_every_heading_and_no_more_than_its_diagonal():
    rng = np.random.default_rng(4)
    for _ in range(20):
        size = rng.uniform(0.1, 1.5, 3)
        q = rng.normal(size=4)
        box = Box("b", rng.uniform(-2, 2, 3), size, q / np.linalg.norm(q), turning=True)
        sw = box.swept()
        assert not sw.turning and np.allclose(sw.center, box.center)
        R0 = quat_to_matrix(box.quat)
        reach = np.zeros(3)
        for a in np.linspace(0.0, 2 * np.pi, 361):
            pts = _corners(box.center, size, R0 @ _rot_z(a))  # the box turned about its own z axis
            local = (pts - sw.center) @ quat_to_matrix(sw.quat)  # in the swept box's frame
            assert (np.abs(local) <= 0.5 * sw.size + 1e-9).all()
            reach = np.maximum(reach, np.abs(local).max(0))
        # tight: the corners reach the swept box's faces (the footprint's circumscribed circle touches them)
        assert np.allclose(reach, 0.5 * sw.size, rtol=1e-3)
    plain = Box("c", np.zeros(3), np.ones(3))
    assert plain.planned() is plain


def test_the_turning_watch_tells_a_turn_in_place_from_a_walk_and_a_carried_chair():
    watch = TurningWatch(turn_rad=0.1, hold_s=10.0, in_place_m=0.15)
    c = np.array([1.0, 2.0, 0.75])
    # a person turns 0.6 rad in place over a second (30 Hz, a few cm of sway)
    states = [watch.update("p", c + [0.01 * np.sin(k), 0.0, 0.0], yaw_to_quat(0.02 * k), k / 30) for k in range(31)]
    first = states.index(True)
    assert not any(states[:first]) and all(states[first:])
    assert 0.1 < 0.02 * first <= 0.1 + 0.02  # from the first pose beyond the turn threshold on
    # standing still: turning until the hold time after the last turn has passed
    assert watch.update("p", c, yaw_to_quat(0.6), 1.0 + 9.0)
    assert not watch.update("p", c, yaw_to_quat(0.6), 1.0 + 10.5)
    # a slow turn in steps below the threshold still adds up to a turn
    slow = [watch.update("s", c, yaw_to_quat(0.01 * k), float(k)) for k in range(20)]
    assert slow.index(True) == 11
    # a person walking 2 m while the heading drifts 0.3 rad: no turn in place
    walk = [watch.update("w", c + [0.05 * k, 0.0, 0.0], yaw_to_quat(0.0075 * k), k / 30) for k in range(41)]
    assert not any(walk)
    # a chair carried 1 m and set down at another heading
    assert not watch.update("chair", c, yaw_to_quat(0.0), 0.0)
    assert not watch.update("chair", c + [1.0, 0.0, 0.0], yaw_to_quat(1.2), 5.0)
    assert not watch.update("chair", c + [1.0, 0.0, 0.0], yaw_to_quat(1.2), 6.0)


SETTINGS = {"roadmap.n_nodes": 300, "seed": 5}


@pytest.fixture(scope="module")
def saved_person_roadmap(load_robot, tmp_path_factory):
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    planner = PSPRM(robot, scene, GeometricScorer(scene, "person_face", robot.config.intrinsics),
                    scene.target("person_face").center, PSPRMSettings().changed(SETTINGS))
    assert planner.build()["success"]
    return planner.save(tmp_path_factory.mktemp("roadmap") / "person.npz")


def _fresh_planner(scene, robot, saved) -> PSPRM:
    """A planner on a copy of the built roadmap (replanners change it)."""
    planner = PSPRM(robot, scene, GeometricScorer(scene, "person_face", robot.config.intrinsics),
                    scene.target("person_face").center, PSPRMSettings().changed(SETTINGS))
    planner.load(saved)
    return planner


@pytest.fixture()
def person_world(load_robot, saved_person_roadmap):
    """The dynamic_person scene, Stretch 2 and a fresh planner."""
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    return scene, robot, _fresh_planner(scene, robot, saved_person_roadmap)


def _near_person(scene, robot, n: int, rng) -> np.ndarray:
    """Configurations with the base 0.3-0.8 m from the person's centre at random headings, the arm and head at
    random joint values."""
    start, _ = problem_configurations(robot, scene, scene.problem("south_to_either"))
    body = scene.obstacle("person_body")
    Q = np.repeat(start[None], n, 0)
    a, d = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.3, 0.8, n)
    Q[:, 0], Q[:, 1] = body.center[0] + d * np.cos(a), body.center[1] + d * np.sin(a)
    Q[:, 2] = rng.uniform(-np.pi, np.pi, n)
    lo, hi = np.asarray(robot.lower, float)[3:], np.asarray(robot.upper, float)[3:]
    Q[:, 3:] = rng.uniform(np.where(np.isfinite(lo), lo, -np.pi), np.where(np.isfinite(hi), hi, np.pi), (n, len(lo)))
    return Q


def _hit_at_some_heading(judge: Judge, sent: SentPoses, Q: np.ndarray, center) -> np.ndarray:
    """(N,) the configurations the body, turned to any of :data:`HEADINGS` in place, collides with (the test's own
    record of the body's pose, pybullet and a fresh box model)."""
    hit = np.zeros(len(Q), bool)
    for h in HEADINGS:
        sent.sent("person_body", center, yaw_to_quat(h))
        hit |= judge.colliding(Q)
    return hit


def test_once_a_body_turns_in_place_the_planner_accepts_nothing_its_next_turn_would_hit(person_world):
    scene, robot, planner = person_world
    rp = Replanner(planner, targets=["person_face"], settings=ReplanSettings(turning_hold_s=10.0))
    body = scene.obstacle("person_body")
    yaw0 = float(np.arctan2(body.rotation[1, 0], body.rotation[0, 0]))
    Q = _near_person(scene, robot, 400, np.random.default_rng(0))
    sent = SentPoses("dynamic_person")
    judge = Judge(robot, sent)
    try:
        swept_hit = _hit_at_some_heading(judge, sent, Q, body.center)
        sent.sent("person_body", body.center, body.quat)
        here_hit = judge.colliding(Q)
        ambush = swept_hit & ~here_hit  # clear of the body as it stands, hit when it turns
        assert ambush.sum() >= 20, "the sample must probe the body's sweep"

        def accepted() -> np.ndarray:
            return ~rp.planner.checker.check(torch.as_tensor(Q, dtype=torch.float32)).numpy()

        # standing still: the planner accepts configurations its turn would hit (the rule has nothing to go on)
        assert (accepted() & ambush).any()
        # it turns in place, 0.5 rad over a second at 30 Hz: from then on nothing it accepts is hit at any heading
        for k in range(31):
            yaw = yaw0 + 0.5 * k / 30
            rp.update_obstacle("person_body", body.center, yaw_to_quat(yaw), stamp=k / 30)
            sent.sent("person_body", body.center, yaw_to_quat(yaw))
        assert not (accepted() & swept_hit).any()
        # a plan made now keeps clear of the body at every heading (its dense path and its timed trajectory)
        start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
        rp.set_robot_state(start)
        rp.set_goals(goals)
        res = rp.replan(now=2.0)
        assert res.success, res.reason
        path = np.vstack([res.dense, res.trajectory.positions])
        assert not _hit_at_some_heading(judge, sent, path, body.center).any()
        # paths are still judged against the body where it stands (a start in its sweep is moved out, not refused):
        # the final check's verdicts are the judge's with the body at the heading the test sent last
        sent.sent("person_body", body.center, yaw_to_quat(yaw))
        here_hit = judge.colliding(Q)
        real = rp.planner.checker.check_unpadded(torch.as_tensor(Q, dtype=torch.float32)).numpy()
        assert not (here_hit & ~real).any() and (real & ~here_hit).mean() < 0.1
        # it stands at that heading for longer than the hold time: the rule lets go
        rp.update_obstacle("person_body", body.center, yaw_to_quat(yaw), stamp=1.0 + 10.5)
        assert (accepted() & swept_hit & ~here_hit).any()
        assert not (accepted() & here_hit).any()
    finally:
        judge.close()


def test_without_the_rule_or_for_a_carried_body_nothing_is_swept(person_world, saved_person_roadmap):
    scene, robot, _ = person_world
    body = scene.obstacle("person_body")
    Q = _near_person(scene, robot, 200, np.random.default_rng(1))
    sent = SentPoses("dynamic_person")
    judge = Judge(robot, sent)
    try:
        swept_hit = _hit_at_some_heading(judge, sent, Q, body.center)
        for settings, moves in ((ReplanSettings(turning_hull=False), [(body.center, 0.02 * k) for k in range(31)]),
                                (ReplanSettings(), [(body.center + [0.02 * k, 0.0, 0.0], 0.01 * k)
                                                    for k in range(31)])):
            rp = Replanner(_fresh_planner(scene, robot, saved_person_roadmap), targets=["person_face"],
                           settings=settings)
            for k, (c, dyaw) in enumerate(moves):
                yaw = float(np.arctan2(body.rotation[1, 0], body.rotation[0, 0])) + dyaw
                rp.update_obstacle("person_body", c, yaw_to_quat(yaw), stamp=k / 30)
            sent.sent("person_body", c, yaw_to_quat(yaw))
            here_hit = judge.colliding(Q)
            acc = ~rp.planner.checker.check(torch.as_tensor(Q, dtype=torch.float32)).numpy()
            assert not (acc & here_hit).any()
            assert (acc & swept_hit & ~here_hit).any()  # configurations in the sweep stay open
    finally:
        judge.close()


def test_a_scene_may_declare_a_turning_body(tmp_path, load_robot):
    """A body the scene file marks ``turning`` is planned against swept from the start, by any collision checker."""
    src = resolve_named("scene", "dynamic_person").read_text()
    marked = src.replace("    yaw: 2.8\n    color: [0.20, 0.55, 0.65, 1.0]",
                         "    yaw: 2.8\n    turning: true\n    color: [0.20, 0.55, 0.65, 1.0]", 1)
    assert marked != src
    path = tmp_path / "scene.yaml"
    path.write_text(marked)
    scene = load_scene(path)
    assert scene.obstacle("person_body").turning
    assert not scene.obstacle("shelf").turning
    swept = dataclasses.replace(scene.obstacle("person_body"), turning=False).swept()
    assert np.allclose(swept.size[:2], np.hypot(0.3, 0.45))
    robot = load_robot("stretch2")
    Q = _near_person(scene, robot, 200, np.random.default_rng(2))
    sent = SentPoses("dynamic_person")
    judge = Judge(robot, sent)
    try:
        body = scene.obstacle("person_body")
        swept_hit = _hit_at_some_heading(judge, sent, Q, body.center)
        acc = ~CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace).check(
            torch.as_tensor(Q, dtype=torch.float32)).numpy()
        assert acc.any() and not (acc & swept_hit).any()
    finally:
        judge.close()
