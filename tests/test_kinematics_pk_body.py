"""Whole-body kinematics from pytorch-kinematics (``PKBodyKinematics`` in psprm_core/robot/kinematics_pk.py), the second
implementation of the body FK the collision checker's torch path runs on: body poses against pybullet's own FK of the
same links and against the robot model's, a checker on it flagging exactly what the native checker flags (and
missing nothing pybullet's exact mesh check finds), and a planner built with ``kinematics: pytorch_kinematics``
planning a path pybullet finds free."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psprm_core.kernels.compute import Compute
from psprm_core.collision import CollisionChecker
from psprm_core.errors import InputError
from psprm_core.evaluation.benchmarks import rotation_angle_error
from psprm_core.evaluation.reference import PybulletWorld, sample_uniform
from psprm_core.robot.kinematics_pk import PKBodyKinematics
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene

TORCH = Compute.make("cpu", kernels="torch")  # torch operators at every batch size

ROBOTS = ["stretch2", "fetchlike", "ur5_mobile"]
WORKSPACE = np.array([[-3.0, 3.0], [-3.0, 3.0]])


def _configs(robot, n, seed=0, base_box=WORKSPACE):
    return sample_uniform(robot, n, np.random.default_rng(seed), base_box=base_box if robot.mobile else None)


class CountingKinematics:
    """Passes ``body_poses`` on to ``kin`` and counts the configurations it was asked for."""

    def __init__(self, kin):
        self.kin, self.rows = kin, 0

    def body_poses(self, q, only=None):
        self.rows += q.shape[0]
        return self.kin.body_poses(q, only)


@pytest.mark.parametrize("name", ROBOTS)
def test_body_poses_match_pybullet_and_the_native_fk(name, load_robot):
    robot = load_robot(name)
    kin = PKBodyKinematics(robot)
    qs = _configs(robot, 60)
    R, t = kin.body_poses(torch.as_tensor(qs))
    assert R.shape == (len(qs), len(robot.bodies), 3, 3) and t.shape == (len(qs), len(robot.bodies), 3)
    world = PybulletWorld(robot, [])
    try:
        ref = np.stack([world.link_poses(q, robot.bodies) for q in qs])
    finally:
        world.close()
    assert np.abs(t.numpy() - ref[..., :3, 3]).max() < 1e-5
    assert rotation_angle_error(R.numpy(), ref[..., :3, :3]).max() < 1e-5
    R0, t0 = robot.body_poses(torch.as_tensor(qs))
    assert (t - t0).abs().max() < 1e-5
    assert rotation_angle_error(R.numpy(), R0.numpy()).max() < 1e-5
    # every body that carries collision elements moves with the sample (the comparison covers them all)
    moved = np.abs(ref[:1, :, :3, 3] - ref[1:, :, :3, 3]).max(axis=(0, 2))
    assert (moved[np.unique(robot.elements.element_body)] > 1e-3).all()


@pytest.mark.parametrize("name", ROBOTS)
def test_body_poses_of_a_chain_only(name, load_robot):
    """With ``only`` (the camera chain; the root and the first body), those bodies are pybullet's poses and every
    other body is zeros."""
    robot = load_robot(name)
    kin = PKBodyKinematics(robot)
    qs = _configs(robot, 12, seed=5)
    world = PybulletWorld(robot, [])
    try:
        for chain in (robot.camera_chain, [0, 1]):
            R, t = kin.body_poses(torch.as_tensor(qs), only=chain)
            ref = np.stack([world.link_poses(q, [robot.bodies[b] for b in chain]) for q in qs])
            assert np.abs(t.numpy()[:, chain] - ref[..., :3, 3]).max() < 1e-5
            assert rotation_angle_error(R.numpy()[:, chain], ref[..., :3, :3]).max() < 1e-5
            others = [b for b in range(len(robot.bodies)) if b not in chain]
            assert not R[:, others].any() and not t[:, others].any()
    finally:
        world.close()
    assert len(robot.bodies) > 2  # [0, 1] leaves bodies out


def test_body_poses_in_float32_and_bad_input(load_robot):
    robot = load_robot("fetchlike")
    qs = torch.as_tensor(_configs(robot, 16, seed=2))
    R64, t64 = PKBodyKinematics(robot).body_poses(qs)
    R32, t32 = PKBodyKinematics(robot, dtype=torch.float32).body_poses(qs.float())
    assert R32.dtype == t32.dtype == torch.float32
    assert torch.allclose(R32.double(), R64, atol=1e-4) and torch.allclose(t32.double(), t64, atol=1e-4)
    # a float32 chain given float64 configurations answers in float64
    assert PKBodyKinematics(robot, dtype=torch.float32).body_poses(qs)[1].dtype == torch.float64
    with pytest.raises(InputError):
        PKBodyKinematics(robot).body_poses(qs[:, :-1])


@pytest.mark.parametrize("name", ROBOTS)
def test_checker_on_pytorch_kinematics_flags_what_the_native_checker_flags(name, load_robot):
    """3000 configurations over the home scene's workspace, both checkers on their torch path in float64: the same
    limit, environment and self-collision flags, the same robot bounds; on the first 300, no collision pybullet's
    exact check finds is missed."""
    robot = load_robot(name)
    scene = load_scene(resolve_named("scene", "home"))
    boxes = scene.collision_boxes()
    qs = _configs(robot, 3000, seed=11, base_box=scene.workspace)
    q = torch.as_tensor(qs)
    counting = CountingKinematics(PKBodyKinematics(robot))
    pkc = CollisionChecker(robot, boxes, workspace=scene.workspace, dtype=torch.float64, kinematics=counting,
                           compute=TORCH)
    native = CollisionChecker(robot, boxes, workspace=scene.workspace, dtype=torch.float64, compute=TORCH)
    fp, fn = pkc.check_detailed(q), native.check_detailed(q)
    flags, flags_native = pkc.check(q), native.check(q)
    box_pk, box_native = pkc.robot_aabb(q), native.robot_aabb(q)
    assert counting.rows >= 3 * len(qs)  # the torch path ran on pytorch-kinematics' poses
    for k in ("limits", "environment", "self"):
        assert torch.equal(fp[k], fn[k]), k
    assert torch.equal(flags, flags_native)
    assert (box_pk - box_native).abs().max() < 1e-5
    f = flags.numpy()
    assert 0.05 < f.mean() < 0.95  # both outcomes are exercised
    assert fp["environment"].any() and fp["self"].any()
    world = PybulletWorld(robot, boxes)
    try:
        ref = world.in_collision(qs[:300])
    finally:
        world.close()
    assert ref.any() and not (ref & ~f[:300]).any()


def test_planner_built_with_pytorch_kinematics_checks_collisions_with_it(load_robot):
    """A PS-PRM with ``kinematics: pytorch_kinematics``, built and queried on the torch path, runs its collision
    checks on pytorch-kinematics' body poses, and its path is free under pybullet's exact check."""
    from psprm_core.planning.factory import make_planner, problem_configurations

    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    p = make_planner("neural-psprm-line", scene, [scene.problems[0].target], robot=robot, compute=TORCH,
                     options={"roadmap.n_nodes": 300, "seed": 0, "visibility.kinematics": "pytorch_kinematics",
                              "roadmap.biased_share": 0.0})
    assert isinstance(p.checker.kin, PKBodyKinematics)
    counting = CountingKinematics(p.checker.kin)
    p.checker.kin = counting
    start, goals = problem_configurations(robot, scene, scene.problems[0])
    p.build()
    res = p.plan(start, goals)
    assert counting.rows > 300
    assert res.success and len(res.dense) > 10
    assert np.abs(res.dense[0] - start).max() < 1e-6
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        assert not world.in_collision(res.dense).any()
    finally:
        world.close()


def test_perf_kinematics_prints_the_body_fk_side_by_side(capsys):
    """``psprm perf kinematics --kinematics pytorch_kinematics``: the three FK throughputs, the two torch FKs'
    agreement with pybullet within 1e-5, and no configuration whose flags differ between the two checkers."""
    import json

    from psprm_core.cli import main

    assert main(["perf", "kinematics", "--robot", "ur5_mobile", "--scene", "home", "--n", "300", "--threads", "1",
                 "--kinematics", "pytorch_kinematics", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("body_fk_native_per_s", "body_fk_pk_per_s", "body_fk_pybullet_per_s", "collision_torch_pk_per_s"):
        assert key in res
    for key in ("native", "pk"):
        assert res[f"body_fk_{key}_max_position_error_m"] < 1e-5
        assert res[f"body_fk_{key}_max_rotation_error_rad"] < 1e-5
    assert res["collision_flags_differing"] == 0 and res["missed_collisions"] == 0
