"""Last resorts of a failing PS-PRM query: the escape search (diff-drive manoeuvres with the arm moving, from a
boxed-in end to the roadmap) and untracked connection edges. Small synthetic scenes for the mobile UR5: a 3 m deep
dead end of low walls, 0.6 m wide (the 0.6 x 0.45 m base cannot turn inside it), the robot inside facing its
closed end; the same dead end closed behind the robot (trapped)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.errors import ConfigError
from psprm_core.evaluation.reference import PybulletWorld
from psprm_core.geometry import wrap_angle, yaw_to_quat
from psprm_core.paths import config_dir
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.timing import check_base_segments
from psprm_core.scene import Box, Scene, Target

N_NODES = 400
POCKET_END = 3.0  # the dead end spans x in [0, 3] around y = 2 (inner width 0.6 m)
# the shipped repair and wide settings of the mobile UR5 (config/planners/psprm.yaml), with the escape on
SETTINGS = {"roadmap.n_nodes": N_NODES, "seed": 1, "roadmap.sample_spread": 0.8, "recovery.query_repair_nodes": 60,
            "recovery.query_repair_rounds": 3, "recovery.query_wide_k": 200, "recovery.query_escape_s": 2.0}


def _pocket_scene(closed: bool = False) -> Scene:
    h, w = 0.3, 0.6  # walls below the base's top (0.4 m): only the base can touch them
    walls = [Box("pocket_n", np.array([1.5, 2.0 + w / 2 + 0.05, h / 2]), np.array([3.0, 0.1, h])),
             Box("pocket_s", np.array([1.5, 2.0 - w / 2 - 0.05, h / 2]), np.array([3.0, 0.1, h])),
             Box("pocket_end", np.array([-0.05, 2.0, h / 2]), np.array([0.1, w + 0.2, h]))]
    if closed:  # 2 cm behind and in front of the robot's base (0.6 m long, centred at x = 0.6)
        walls.append(Box("pocket_door", np.array([0.97, 2.0, h / 2]), np.array([0.1, w + 0.2, h])))
        walls.append(Box("pocket_front", np.array([0.23, 2.0, h / 2]), np.array([0.1, w + 0.2, h])))
    monitor = Target("monitor", "tv", np.array([5.6, 2.0, 1.0]), np.array([0.08, 0.6, 0.4]), quat=yaw_to_quat(np.pi))
    return Scene(name="pocket", robot="ur5_mobile", frame="map", workspace=np.array([[0.0, 6.0], [0.0, 4.0]]),
                 obstacles=tuple(walls), targets=(monitor,))


def _planner(robot, scene: Scene, overrides: dict | None = None) -> PSPRM:
    scorer = GeometricScorer(scene, "monitor", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("monitor").center, PSPRMSettings().changed({**SETTINGS, **(overrides or {})}))
    assert p.build()["success"]
    return p


def _ends(robot) -> tuple:
    start = robot.default_configuration().copy()
    start[:3] = [0.6, 2.0, np.pi]  # deep in the dead end, facing its closed end
    goal = robot.default_configuration().copy()
    goal[:3] = [4.5, 1.0, 0.0]
    return start, goal


@pytest.fixture(scope="module")
def pocket(load_robot):
    robot = load_robot("ur5_mobile")
    scene = _pocket_scene()
    return scene, robot, _planner(robot, scene)


def _free(robot, scene, q) -> bool:
    """Independent judge: a fresh checker built from the scene's boxes."""
    ch = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    return not bool(ch.check(torch.as_tensor(q, dtype=torch.float32)).any())


def test_dead_end_is_left_by_backing_out_then_turning(pocket, monkeypatch):
    """The first query cannot leave the dead end: the base cannot turn inside it and no roadmap node lies on its
    heading line. The escape search runs first after that failure (the slower local repair is not needed); it backs
    the robot out along its heading, and the base turns only once outside. The path is
    collision-free (pybullet's exact check), drivable and starts and ends at the query's ends."""
    scene, robot, p = pocket
    start, goal = _ends(robot)
    order = []
    for name in ("repair_query", "escape_query"):
        real = getattr(p.pipeline.recovery, name)
        monkeypatch.setattr(p.pipeline.recovery, name, lambda *a, _r=real, _n=name, **k: order.append(_n) or _r(*a, **k))
    assert not p.pipeline.query.plan_once(start, goal, timing=False).success  # what the old planner had
    res = p.plan(start, goal)
    assert res.success, res.reason
    assert order == ["escape_query"] and "escape search" in res.reason
    W = res.waypoints
    assert np.allclose(W[0], start, atol=1e-5) and np.allclose(W[-1], goal, atol=1e-5)
    assert check_base_segments(W, (0, 1, 2), 1e-5) == []
    assert check_base_segments(res.trajectory.positions, (0, 1, 2), 1e-5) == []
    inside = res.dense[:, 0] < POCKET_END + 0.3  # some part of the base is still within the dead end
    assert inside[0] and not inside[-1]
    leave = int(np.argmin(inside))
    assert inside[:leave].all()  # it leaves once, without driving back in
    # inside, the heading stays along the dead end (turning in place there collides); it drives backwards out
    assert np.abs(wrap_angle(torch.as_tensor(res.dense[:leave, 2] - np.pi))).max() < 0.3
    assert res.dense[leave, 0] > start[0] + 2.0
    assert _free(robot, scene, res.dense)
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        assert not world.in_collision(res.dense).any()
        assert not world.in_collision(res.trajectory.positions).any()
    finally:
        world.close()
    # the escape's configurations were query nodes: nothing stays in the roadmap
    ids0 = p.roadmap_node_ids()
    assert p.plan(start, goal, timing=False).success and np.array_equal(p.roadmap_node_ids(), ids0)


def test_escape_is_off_and_never_runs_for_queries_that_succeed(pocket, monkeypatch):
    """Without the escape and the untracked fallback (the planner before them) the dead end stays unsolved; a query
    solved without a repair never starts an escape search."""
    scene, robot, p = pocket
    start, goal = _ends(robot)
    calls = []
    real = p.pipeline.recovery.escape
    monkeypatch.setattr(p.pipeline.recovery, "escape", lambda *a, **k: calls.append(1) or real(*a, **k))
    s0 = p.settings
    try:
        p.update_settings(s0.changed({"recovery.query_escape_s": 0.0, "recovery.query_untracked_fallback": False,
                                      "recovery.query_repair_failures": 10**6}))
        res = p.plan(start, goal, timing=False)
        assert not res.success and "reachable" in res.reason and not calls
    finally:
        p.update_settings(s0)
    other = goal.copy()
    other[:3] = [4.0, 3.0, 1.0]
    res = p.plan(other, goal, timing=False)
    assert res.success and res.reason == "ok" and not calls


def test_trapped_start_fails_with_a_clear_reason(load_robot):
    """A start closed in on all sides (2 cm in front of and behind the base) cannot be left: not one short motion out
    of it is free. The query fails saying that the start is boxed in, and the escape gives up after a few rounds
    instead of spending its time budget."""
    robot = load_robot("ur5_mobile")
    scene = _pocket_scene(closed=True)
    p = _planner(robot, scene)
    start, goal = _ends(robot)
    res = p.plan(start, goal, timing=False)
    assert not res.success
    assert res.reason.startswith("start is boxed in: no collision-free motion out of it was found"), res.reason
    ends = p.ctx.t(np.stack([start, goal]))
    ids, lab = p.components()
    t0 = time.perf_counter()
    esc = p.pipeline.recovery.escape(ends[0], ids[lab == np.argmax(np.bincount(lab))], np.random.default_rng(0), t0 + 10.0)
    assert not esc.success and esc.explored == 1 and esc.tried > 0 and time.perf_counter() - t0 < 1.0
    assert esc.base_reach == 0.0
    # the open dead end's start is not boxed in: its escape search reaches out of it
    open_p = _planner(robot, _pocket_scene(), {"recovery.query_escape_s": 0.3})
    ids, lab = open_p.components()
    esc = open_p.pipeline.recovery.escape(ends[0], ids[lab == np.argmax(np.bincount(lab))], np.random.default_rng(0),
                         time.perf_counter() + 5.0)
    assert esc.success and esc.explored > 1 and esc.base_reach > 2.0


def test_untracked_connection_is_kept_when_the_reaimed_one_collides(pocket):
    """From deep in the dead end one long connection backs the robot straight out to a roadmap node almost on its
    heading line; re-aiming the camera on the way (the arm turns towards the monitor while the base is between the
    walls) collides, moving the arm plainly does not. The wide query keeps that connection with its untracked knots
    (``query_untracked_fallback``); the same query without the fallback (and the first query, never with it) fails.
    What is executed is exactly the untracked motion, collision-free."""
    scene, robot, p = pocket
    start, goal = _ends(robot)
    wide = dict(extra_candidates={}, connect_k=200)
    assert not p.pipeline.query.plan_once(start, goal, timing=False, **wide).success
    res = p.pipeline.query.plan_once(start, goal, timing=False, untracked=True, **wide)
    assert res.success, res.reason
    assert np.allclose(res.waypoints[0], start, atol=1e-5) and _free(robot, scene, res.dense)
    assert check_base_segments(res.waypoints, (0, 1, 2), 1e-5) == []
    # the first edge's executed knots are its untracked local motion, and its re-aimed knots collide
    a, b = p.ctx.t(start[None]), p.ctx.t(p.graph.configs[res.path_nodes[1]][None])
    plain = p.edge_knots(a, b, track=False)[0][0].double().numpy()
    plain = plain[np.r_[True, np.abs(np.diff(plain, axis=0)).max(1) > 1e-7]]  # as the path drops repeated knots
    diff = res.waypoints[:len(plain)] - plain
    diff[:, 2] = np.angle(np.exp(1j * diff[:, 2]))  # headings: the same angle
    assert np.abs(diff).max() < 1e-5
    aimed, _ = p.edge_knots(a, b)
    assert not bool(p.pipeline.edges.knots_valid(aimed)[0])
    # roadmap edges are never swapped for their untracked motion
    e = p.roadmap_edge_ids()[:5]
    assert not p.pipeline.verify.untracked_query_edges(e, torch.zeros(len(e), dtype=torch.bool)).any()


def test_escape_settings_are_query_settings_and_validated(pocket, tmp_path):
    scene, robot, p = pocket
    fp = p.fingerprint()
    s0 = p.settings
    try:
        p.update_settings(s0.changed({"recovery.query_escape_s": 0.5, "recovery.query_escape_nodes": 10,
                                      "recovery.query_escape_radius": 1.0, "recovery.query_escape_step": 0.2,
                                      "recovery.query_escape_connect_k": 2,
                                      "recovery.query_untracked_fallback": False}))
        assert p.fingerprint() == fp  # a saved roadmap stays valid
    finally:
        p.update_settings(s0)
    for name, value in (("query_escape_s", -1.0), ("query_escape_s", float("nan")), ("query_escape_step", 0.0),
                        ("query_escape_radius", -1.0), ("query_escape_nodes", 0), ("query_escape_connect_k", 0)):
        with pytest.raises(ConfigError):
            PSPRMSettings().changed({"recovery.query_escape_s": 1.0, f"recovery.{name}": value}).validate()
    shipped = PSPRMSettings.from_yaml(config_dir() / "planners" / "psprm.yaml", robot="ur5_mobile")
    assert shipped.recovery.query_escape_s > 0 and shipped.recovery.query_untracked_fallback
    y = tmp_path / "p.yaml"
    y.write_text("recovery:\n  query_escape_step: 0.0\n  query_escape_s: 1.0\n")
    with pytest.raises(ConfigError, match="query_escape_step"):
        PSPRMSettings.from_yaml(y)
    y.write_text("recovery:\n  query_escape_s: soon\n")
    with pytest.raises(ConfigError, match="query_escape_s"):
        PSPRMSettings.from_yaml(y)
