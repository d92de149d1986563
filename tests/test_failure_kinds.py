"""Failure kinds: every failed query carries a :class:`~psprm_core.planning.results.Failure` beside its reason, and
the planner's recovery decisions follow the kind, never the reason's text.

Judged from the test's own constructions: a start the test put inside the table (pybullet confirms it collides), a
graph the test built with two components, a NaN the test wrote; and for the dispatch, query outcomes the test
substitutes whose text and kind disagree."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from psprm_core.evaluation.reference import PybulletWorld
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.search.graph import Roadmap
from psprm_core.planning.search.graph_search import astar, lazy_astar
from psprm_core.planning.results import Failure, PlanResult
from psprm_core.planning.search.search_types import EdgeCheck

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def home(home_tv_planner):
    scene, robot, planner, _, _, stats = home_tv_planner(**{"roadmap.n_nodes": 700, "seed": 1})
    assert stats["success"]
    return scene, robot, planner


def test_bad_queries_carry_their_kind(home):
    scene, robot, planner = home
    start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
    inside = start.copy()
    inside[:2] = scene.obstacle("table").center[:2]
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        assert "table" in world.contacts(inside)[0], "the test's start inside the table must touch it (pybullet)"
    finally:
        world.close()
    ok = planner.plan(start, goals, timing=False)
    assert ok.success and ok.failure is Failure.NONE
    assert planner.plan(inside, goals).failure is Failure.START_BLOCKED
    assert planner.plan(start, inside).failure is Failure.GOAL_BLOCKED
    nan = start.copy()
    nan[0] = math.nan
    assert planner.plan(nan, goals).failure is Failure.INVALID_INPUT
    assert ok.to_dict()["failure"] == "none"


def test_search_failures_carry_their_kind():
    # two components: {0, 1, 2} and {3, 4}
    g = Roadmap.from_edges(5, np.array([[0, 1], [1, 2], [3, 4]], dtype=np.int64), np.array([1.0, 1.0, 1.0]))
    for backend in ("auto", "python"):
        assert astar(g, 0, [4], heuristic="zero", backend=backend).failure is Failure.UNREACHABLE
        assert astar(g, 0, [4], heuristic="hop", backend=backend).failure is Failure.UNREACHABLE
        assert astar(g, 0, [2], heuristic="zero", max_expansions=1, backend=backend).failure is Failure.SEARCH_LIMIT
        assert astar(g, 0, [2], heuristic="zero", backend=backend).failure is Failure.NONE
    # every edge rejected by the lazy check: the goal is unreachable
    res = lazy_astar(g, 0, [2], lambda e, p: EdgeCheck(invalid=[int(x) for x in e]), heuristic="zero")
    assert not res.success and res.failure is Failure.UNREACHABLE


def test_recovery_follows_the_kind_not_the_text(home, monkeypatch):
    """The local repair runs for an UNREACHABLE outcome whatever its text says, and not for another kind whose text
    says "not reachable"."""
    scene, robot, planner = home
    start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
    q = planner.plan(start, goals, timing=False).dense[len(goals) // 2]
    grown = []
    real_grow = planner.pipeline.builder.grow

    def counting_grow(*a, **k):
        out = real_grow(*a, **k)
        grown.append(out["added_nodes"])
        return out

    monkeypatch.setattr(planner.pipeline.builder, "grow", counting_grow)
    settings = planner.settings
    planner.update_settings(settings.changed({
        "recovery.query_escape_s": 0.0, "recovery.query_wide_k": 0,
        "recovery.query_repair_failures": planner.pipeline.rm.repair_failed + 10}))
    try:
        monkeypatch.setattr(planner.pipeline.query, "plan_once",
                            lambda *a, **k: PlanResult(False, "goal not reachable on the roadmap", Failure.SEARCH_LIMIT))
        assert not planner.plan(q, goals, timing=False).success
        assert grown == [], "a search limit is not repaired, whatever its text"
        monkeypatch.setattr(planner.pipeline.query, "plan_once",
                            lambda *a, **k: PlanResult(False, "zzz", Failure.UNREACHABLE))
        assert not planner.plan(q, goals, timing=False).success
        assert len(grown) > 0, "an unreachable goal is repaired, whatever its text"
    finally:
        monkeypatch.undo()
        planner.update_settings(settings)


def test_no_control_flow_reads_a_reason_text():
    """No ``"..." in x.reason`` / ``x.reason.startswith(...)`` in the library or the nodes: decisions read ``failure``."""
    found = []
    for pkg in ("psprm_core", "psprm_ros"):
        for path in (ROOT / pkg).rglob("*.py"):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Compare) and any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops):
                    rhs = node.comparators[-1]
                    if isinstance(rhs, ast.Attribute) and rhs.attr == "reason":
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr in ("startswith", "endswith")
                        and isinstance(node.func.value, ast.Attribute) and node.func.value.attr == "reason"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, found
