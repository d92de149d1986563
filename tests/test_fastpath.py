"""Small-batch CPU fast paths (``psprm_core.fastpath``): the compiled kernels give the torch path's results (camera
poses, manifold projection, collision flags) on random inputs, the planner returns the same paths with them on and
off, and without numba (or for large batches, gradients) every call takes the torch path."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
import torch

from psprm_core import fastpath
from psprm_core.benchmarks import random_problems
from psprm_core.collision import CollisionChecker
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.constraints import ProjectionSettings, VisibilityConstraint
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.reference import sample_uniform
from psprm_core.scene import load_scene

ROBOT_SCENES = {"stretch2": "home", "fetchlike": "nursing", "ur5_mobile": "blind_spot_alley"}


def _configs(robot, scene, n: int, seed: int) -> np.ndarray:
    """Uniform configurations over the joint limits and the scene's workspace, some outside the limits."""
    rng = np.random.default_rng(seed)
    q = sample_uniform(robot, n, rng, base_box=scene.workspace)
    q[:, 2] = rng.uniform(-4, 4, n)  # theta beyond (-pi, pi]
    q[::37, -1] += 5.0  # beyond the limit
    return q


def _robot_scene(name, load_robot):
    robot = load_robot(name)
    scene = load_scene(resolve_named("scene", ROBOT_SCENES[name]))
    assert scene.robot == name
    return robot, scene


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_camera_poses_match_torch(name, dtype, load_robot):
    robot, scene = _robot_scene(name, load_robot)
    q = torch.as_tensor(_configs(robot, scene, 300, 0), dtype=dtype)
    fast = robot.camera_poses(q)
    with fastpath.disabled():
        ref = robot.camera_poses(q)
    assert fast.dtype == ref.dtype == dtype and fast.shape == ref.shape
    assert (fast - ref).abs().max() < (1e-12 if dtype == torch.float64 else 1e-5)


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("kind", ["line", "frustum"])
def test_projection_matches_torch(name, kind, load_robot):
    """Same iterates in float64 (same steps, same stopping, same converged flags), with all camera joints and with
    the non-base ones only (the edge knots' re-aiming)."""
    robot, scene = _robot_scene(name, load_robot)
    target = scene.target(scene.target_names[0]).center
    c = VisibilityConstraint(robot, kind, target, margin=0.05, min_distance=0.5)
    q = torch.as_tensor(_configs(robot, scene, 150, 1), dtype=torch.float64)
    lo = torch.as_tensor(np.where(np.isfinite(robot.lower), robot.lower, -1e9))
    hi = torch.as_tensor(np.where(np.isfinite(robot.upper), robot.upper, 1e9))
    joints = np.nonzero(c._camera_joints())[0]
    unconverged = 0
    for cols in (None, joints[joints >= 3]):
        for iters in (3, 20):
            ps = ProjectionSettings(max_iters=iters)
            qf, okf = c.project(q, ps, lo, hi, joints=cols)
            with fastpath.disabled():
                qr, okr = c.project(q, ps, lo, hi, joints=cols)
            assert okf.dtype == torch.bool and torch.equal(okf, okr)
            assert int(okr.sum()) > 0
            unconverged += int((~okr).sum())
            assert (qf - qr).abs().max() < 1e-6  # float rounding, amplified by ill-conditioned steps
    assert unconverged > 0  # both outcomes occur


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_collision_flags_match_torch(name, dtype, load_robot):
    robot, scene = _robot_scene(name, load_robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace, dtype=dtype)
    q = torch.as_tensor(_configs(robot, scene, 600, 2), dtype=dtype)
    q[5, 0] = float("nan")
    fast, bad = checker.check_detailed(q), checker.check(q)
    with fastpath.disabled():
        ref, ref_bad = checker.check_detailed(q), checker.check(q)
    for k in ("limits", "environment", "self"):
        assert fast[k].dtype == torch.bool and torch.equal(fast[k], ref[k]), k
        assert 0 < int(ref[k].sum()) < len(q), k  # each kind of collision occurs, and free rows too
    assert torch.equal(bad, ref_bad) and bool(bad[5])
    # a moved obstacle set is picked up (the compiled path caches the boxes by their tensors)
    checker.set_boxes([])
    free = checker.check_detailed(q)
    with fastpath.disabled():
        free_ref = checker.check_detailed(q)
    assert not free["environment"].any() and torch.equal(free["self"], free_ref["self"])


def test_fast_path_only_for_small_cpu_batches_without_gradients(load_robot):
    robot = load_robot("stretch2")
    q = torch.zeros(4, robot.dof)
    assert fastpath.applies(q)
    assert not fastpath.applies(torch.zeros(fastpath.MAX_BATCH + 1, robot.dof))
    assert not fastpath.applies(torch.zeros(0, robot.dof))
    assert not fastpath.applies(q.clone().requires_grad_())
    with fastpath.disabled():
        assert not fastpath.applies(q)
    with mock.patch.object(fastpath, "available", lambda: False):  # numba 'missing'
        assert not fastpath.applies(q)
        with mock.patch.object(fastpath, "kernels", side_effect=AssertionError("compiled path used")):
            T = robot.camera_poses(q)
    assert torch.allclose(T, robot.camera_poses(q), atol=1e-6)
    # autograd still flows through the torch path
    qg = torch.zeros(3, robot.dof, dtype=torch.float64, requires_grad=True)
    robot.camera_poses(qg)[:, :3, 3].sum().backward()
    assert qg.grad is not None and qg.grad.abs().sum() > 0


def test_planner_same_paths_with_fast_path_on_and_off(load_robot, tmp_path):
    """One roadmap, queried by two planners (one loaded from the other's file): with and without the compiled
    small-batch paths every query gives the same path and cost (the re-aimed knots agree up to float32 rounding of
    the torch path's Gauss-Newton iterates)."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.problems[0].target
    scorer = GeometricScorer(scene, target, robot.config.intrinsics)
    settings = PSPRMSettings(n_nodes=400, seed=3, query_repair_nodes=0)  # repairs grow nodes: not compared
    focus = scene.target(target).center
    a = PSPRM(robot, scene, scorer, focus, settings)
    assert a.build()["success"]
    b = PSPRM(robot, scene, scorer, focus, settings)
    b.load(a.save(tmp_path / "roadmap.npz"))
    probs = random_problems(robot, scene, a.checker, 8, np.random.default_rng(4), robot.default_configuration(),
                            focus, aimed_only=True, aim_restarts=4)
    assert len(probs) >= 6
    solved = 0
    for start, goal in probs:
        ra = a.plan(start, goal, timing=False)
        with fastpath.disabled():
            rb = b.plan(start, goal, timing=False)
        assert ra.success == rb.success
        if ra.success:
            solved += 1
            assert ra.path_nodes == rb.path_nodes
            assert ra.cost == pytest.approx(rb.cost, rel=1e-4)
            assert np.abs(ra.waypoints - rb.waypoints).max() < 1e-2  # float32 re-aimed knots
    assert solved >= len(probs) // 2
