"""TrajOpt baseline: a drivable, collision-free path that ends at the goal and looks at the target better than the
straight-line initialisation; clear failures for bad problems; residual Jacobians; settings from YAML."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from psprm_core.baselines.trajopt import TrajOptPlanner, TrajOptSettings, view_angles
from psprm_core.baselines.trajopt_problem import TrajOptProblem, arc_segments
from psprm_core.errors import ConfigError
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene


@pytest.fixture(scope="module")
def planner(load_robot):
    scene = load_scene(resolve_named("scene", "home"))
    return TrajOptPlanner("trajopt", scene, ["cup"], robot=load_robot("stretch2"))


def _problem(p, start_pose, goal_pose):
    """Start and goal with the head aimed at the target (as the benchmark's random problems are)."""
    r = p.robot
    q = np.stack([r.configuration({"base_x": x, "base_y": y, "base_theta": th})
                  for x, y, th in (start_pose, goal_pose)])
    q, ok = p.ctx.aim(q)
    assert ok.all() and p.ctx.valid(q).all()
    return q[0], q[1]


def _lateral(dense: np.ndarray) -> np.ndarray:
    """Sideways base displacement between consecutive executed configurations (heading of the earlier one)."""
    th, dx, dy = dense[:-1, 2], np.diff(dense[:, 0]), np.diff(dense[:, 1])
    return -np.sin(th) * dx + np.cos(th) * dy


def test_path_is_collision_free_drivable_reaches_goal_and_looks_better(planner):
    p = planner
    start, goal = _problem(p, (1.0, 1.0, 0.0), (2.2, 1.4, 0.6))  # the goal lies sideways of the start heading
    res = p.plan(start, goal, timeout_s=30)
    assert res.success, res.reason
    D = res.dense
    assert np.allclose(D[0], start, atol=1e-9) and np.allclose(D[-1], goal, atol=1e-9)
    assert p.ctx.valid(D).all()
    # executed steps are small and never sideways (differential drive)
    step = np.hypot(np.diff(D[:, 0]), np.diff(D[:, 1]))
    assert step.max() <= 0.051
    assert np.abs(_lateral(D)).max() < 1e-6
    # the optimised waypoints themselves satisfy the nonholonomic residual (chord along the mean heading)
    W = res.waypoints
    assert np.abs(arc_segments(W[:-1], W[1:], 0.25)["lateral"]).max() <= p.settings.lateral_tolerance
    # the straight-line initialisation drives sideways, and the optimised path looks at the cup more directly
    init = p.initial_path(start, goal)
    assert np.abs(arc_segments(init[:-1], init[1:], 0.25)["lateral"]).max() > 0.01
    ang_init = view_angles(p.robot, p.ctx.densify(init), p.focus).mean()
    ang = view_angles(p.robot, D, p.focus).mean()
    assert ang < ang_init
    assert res.path_length > np.linalg.norm(goal[:2] - start[:2])


def test_goal_in_collision_is_a_failure_not_an_exception(planner):
    p = planner
    start, _ = _problem(p, (1.0, 1.0, 0.0), (2.2, 1.4, 0.6))
    bad = start.copy()
    bad[:2] = [3.0, 3.0]  # inside the dining table
    res = p.plan(start, bad, timeout_s=5)
    assert not res.success and "collision" in res.reason
    start2, goal = _problem(p, (1.0, 1.0, 0.0), (2.2, 1.4, 0.6))
    res = p.plan(start2, np.stack([bad, goal]), timeout_s=30)  # the valid one of several goals
    assert res.success and res.goal_index == 1 and np.allclose(res.dense[-1], goal)
    res = p.plan(start, np.full_like(start, np.nan), timeout_s=5)
    assert not res.success and "NaN" in res.reason
    res = p.plan(bad, start, timeout_s=5)
    assert not res.success and "start configuration invalid" in res.reason


def test_residual_jacobian_matches_finite_differences(planner):
    p = planner
    r = p.robot
    q = np.stack([r.configuration({"base_x": x, "base_y": 1.55, "base_theta": 0.0}) for x in (2.2, 3.7)])
    start, goal = p.ctx.aim(q)[0]  # the straight line passes just south of the chair: collision terms are active
    saved = p.settings
    p.settings = dataclasses.replace(saved, n_waypoints=8)
    try:
        cols = p.optimised_joints(start, goal)
        prob = TrajOptProblem(p, start, goal, 0.05, cols)
        prob.set_penalty_scale([2.0, 3.0, 4.0, 5.0])
        x = p.initial_path(start, goal)[1:, cols].reshape(-1)
        with torch.no_grad():
            terms = p.config_terms(torch.as_tensor(prob.A @ prob.full_path(x)))
        assert terms[:, :-1].max() > 0  # some sphere is inside the clearance margin
        x = x + np.random.default_rng(0).normal(0, 0.02, x.shape)
        r0, J = prob.fun(x), prob.jac(x)
    finally:
        p.settings = saved
    assert J.shape == (len(r0), len(x))
    eps = 1e-7
    Jn = np.stack([(prob.fun(x + eps * e) - r0) / eps for e in np.eye(len(x))], 1)
    assert np.abs(Jn - J).max() <= 1e-4 * np.abs(J).max()


def test_settings_from_yaml(tmp_path, load_robot):
    scene = load_scene(resolve_named("scene", "home"))
    cfg = tmp_path / "baselines.yaml"
    cfg.write_text("common: {timeout_s: 7.0, range: 2.0}\ntrajopt: {n_waypoints: 12, w_view: 0.5}\n")
    from psprm_core.baselines.base import settings_from_yaml

    s = settings_from_yaml(TrajOptSettings, "trajopt", path=cfg)
    assert (s.n_waypoints, s.w_view, s.timeout_s) == (12, 0.5, 7.0)
    cfg.write_text("trajopt: {n_waypoint: 12}\n")
    with pytest.raises(ConfigError, match="n_waypoint"):
        settings_from_yaml(TrajOptSettings, "trajopt", path=cfg)
    with pytest.raises(ConfigError, match="joints"):
        TrajOptPlanner("trajopt", scene, ["cup"], robot=load_robot("stretch2"), joints="some")
