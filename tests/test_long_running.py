"""A long-running planner (a ROS node replans every second for hours): its memory stays bounded and the plans made
on reused node and edge slots are sound. Judged by tracemalloc's count of the bytes numpy holds, pybullet's exact
collision check of every path, and each path's own start, goal and drivable pieces."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from psprm_core.collision import CollisionChecker
from psprm_core.evaluation.reference import PybulletWorld
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.timing import check_base_segments
from psprm_core.problems import random_problems
from psprm_core.scene import load_scene


@pytest.fixture(scope="module")
def planner_and_problems(load_robot):
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    planner = PSPRM(robot, scene, GeometricScorer(scene, "tv", robot.config.intrinsics), scene.target("tv").center,
                    PSPRMSettings().changed({"roadmap.n_nodes": 600, "seed": 3, "scoring.objective": "motion",
                                             "scoring.alpha": 0.9, "query.shortcut": True}))
    assert planner.build()["success"]
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    pairs = random_problems(robot, scene, checker, 20, np.random.default_rng(9), robot.default_configuration(),
                            scene.target("tv").center, aimed_only=True, aim_restarts=8, mobile_only=True)
    return scene, robot, planner, pairs


def _numpy_bytes() -> int:
    return tracemalloc.get_traced_memory()[0]


def test_memory_stays_bounded_over_many_queries(planner_and_problems):
    """A thousand queries (each adds its start, goal and connection edges, retired afterwards): the bytes numpy
    holds after 1,000 queries are within 1 MB of those after 200 (kept for good, the retired slots of 800 queries
    hold about 4 MB of graph arrays, besides the knots stored for them)."""
    scene, robot, planner, pairs = planner_and_problems
    tracemalloc.start()
    try:
        marks = []
        for q in range(1000):
            a, b = pairs[q % len(pairs)]
            assert planner.plan(a, b, timing=False).success
            if q + 1 in (200, 1000):
                marks.append(_numpy_bytes())
    finally:
        tracemalloc.stop()
    assert marks[1] - marks[0] < 1_000_000, marks


def test_plans_on_reused_slots_are_sound(planner_and_problems):
    """After the slots of retired queries have been reused many times, every plan still starts and ends where asked,
    drives in straight pieces and turns, and is free under pybullet: no edge reads knots stored for an earlier
    edge of the same id."""
    scene, robot, planner, pairs = planner_and_problems
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        for _ in range(3):
            for a, b in pairs:
                r = planner.plan(a, b, timing=False)
                assert r.success, r.reason
                for q, want in ((r.waypoints[0], a), (r.waypoints[-1], b)):
                    d = q - want
                    d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi
                    assert np.abs(d).max() < 1e-5
                assert check_base_segments(r.waypoints, (0, 1, 2), 1e-5) == []
                assert not world.in_collision(r.dense[::3]).any()
    finally:
        world.close()
