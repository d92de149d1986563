"""Camera kinematics from pytorch-kinematics (psprm_core/robot/kinematics_pk.py), the second implementation of the
camera chain: its FK against pybullet's, its Jacobian against finite differences of its own FK and against the
robot model's analytic camera Jacobian, on the three robots."""

import numpy as np
import pytest
import torch

from psprm_core.kernels.compute import Compute
from psprm_core.evaluation.benchmarks import rotation_angle_error
from psprm_core.evaluation.reference import PybulletWorld, sample_uniform
from psprm_core.robot.kinematics_pk import PKCameraKinematics

TORCH = Compute.make("cpu", kernels="torch")  # torch operators at every batch size

ROBOTS = ["stretch2", "fetchlike", "ur5_mobile"]
WORKSPACE = np.array([[-3.0, -3.0], [3.0, 3.0]])


def _configs(robot, n, seed=0):
    return sample_uniform(robot, n, np.random.default_rng(seed), base_box=WORKSPACE if robot.mobile else None)


def _twists_by_finite_differences(kin, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(dof, 6) world twists [omega, v0] of the camera per planning joint, from central differences of the pose."""
    out = np.zeros((len(q), 6))
    for i in range(len(q)):
        qp, qm = q.copy(), q.copy()
        qp[i] += h
        qm[i] -= h
        Tp, Tm = kin.camera_poses(torch.as_tensor(np.stack([qp, qm]))).numpy()
        T = kin.camera_poses(torch.as_tensor(q[None])).numpy()[0]
        dR = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h)
        dp = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
        S = dR @ T[:3, :3].T  # skew(omega)
        omega = np.array([S[2, 1], S[0, 2], S[1, 0]])
        out[i, :3] = omega
        out[i, 3:] = dp - np.cross(omega, T[:3, 3])
    return out


@pytest.mark.parametrize("name", ROBOTS)
def test_pytorch_kinematics_camera_fk_matches_pybullet(name, load_robot):
    robot = load_robot(name)
    kin = PKCameraKinematics(robot)
    qs = _configs(robot, 60)
    T = kin.camera_poses(torch.as_tensor(qs)).numpy()
    world = PybulletWorld(robot, [])
    try:
        ref = np.stack([world.camera_pose(q) for q in qs])
    finally:
        world.close()
    assert np.abs(T[:, :3, 3] - ref[:, :3, 3]).max() < 1e-5
    assert rotation_angle_error(T[:, :3, :3], ref[:, :3, :3]).max() < 1e-5


@pytest.mark.parametrize("name", ROBOTS)
def test_pytorch_kinematics_jacobian_matches_finite_differences_and_the_analytic_one(name, load_robot):
    robot = load_robot(name)
    kin = PKCameraKinematics(robot)
    qs = _configs(robot, 8, seed=1)
    T, W = kin.camera_jacobian(torch.as_tensor(qs))
    assert W.shape == (len(qs), robot.dof, 6)
    for q, w in zip(qs, W.numpy()):
        assert np.abs(w - _twists_by_finite_differences(kin, q)).max() < 1e-5
    T0, W0 = robot.using(TORCH).camera_jacobian(torch.as_tensor(qs))
    assert np.abs(W.numpy() - W0.numpy()).max() < 1e-6
    assert np.abs(T.numpy() - T0.numpy()).max() < 1e-6


def test_pytorch_kinematics_runs_in_float32(load_robot):
    robot = load_robot("stretch2")
    qs = torch.as_tensor(_configs(robot, 16, seed=2))
    T64 = PKCameraKinematics(robot).camera_poses(qs)
    T32 = PKCameraKinematics(robot, dtype=torch.float32).camera_poses(qs.float())
    assert T32.dtype == torch.float32 and torch.allclose(T32.double(), T64, atol=1e-4)


def test_projection_with_pytorch_kinematics_matches_the_native_one(load_robot):
    """The Newton projection (Alg. 1, line 7) gives the same configurations with either kinematics (both the torch
    iteration), and they are on the manifold by the other implementation's FK."""
    from psprm_core.planning.constraints import ProjectionSettings, VisibilityConstraint

    robot = load_robot("stretch2")
    target = np.array([2.0, 1.0, 1.1])
    q = torch.as_tensor(_configs(robot, 64, seed=3), dtype=torch.float64)
    q[:, :2] = torch.as_tensor(np.random.default_rng(4).uniform(-1.0, 1.0, (64, 2)))
    robot = robot.using(TORCH)  # the torch iteration on both
    native = VisibilityConstraint(robot, "line", target)
    pkc = VisibilityConstraint(robot, "line", target, kinematics=PKCameraKinematics(robot))
    qn, okn = native.project(q, ProjectionSettings())
    qp, okp = pkc.project(q, ProjectionSettings())
    assert okp.float().mean() > 0.5 and torch.equal(okn, okp)
    assert (qn - qp).abs().max() < 1e-4  # iterations stop at |h| < tolerance: FK differences of 1e-7 stay small
    assert native.error(qp[okp]).max() < ProjectionSettings().tolerance


def test_planner_built_with_pytorch_kinematics_plans_collision_free(load_robot):
    """A PS-PRM with ``kinematics: pytorch_kinematics`` builds, and its plan is free under pybullet's exact check
    and its nodes lie on the manifold by the robot model's own FK."""
    from psprm_core.paths import resolve_named
    from psprm_core.planning.factory import make_planner, problem_configurations
    from psprm_core.scene import load_scene

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    p = make_planner("neural-psprm-line", scene, ["person_face"], robot=robot,
                     options={"roadmap.n_nodes": 300, "seed": 0, "visibility.kinematics": "pytorch_kinematics",
                              "roadmap.biased_share": 0.0})
    assert isinstance(p.constraint.kin, PKCameraKinematics)
    p.build()
    ids = p.graph.valid_node_ids()[:200]
    err = p.constraint.__class__(robot.using(TORCH), "line", p.constraint.target.numpy()).error(
        torch.as_tensor(p.graph.configs[ids], dtype=torch.float64))
    assert err.max() < 5 * p.settings.projection.tolerance
    start, goals = problem_configurations(robot, scene, scene.problems[0])
    res = p.plan(start, goals)
    assert res.success
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        assert not world.in_collision(res.dense).any()
    finally:
        world.close()
