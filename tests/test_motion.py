"""Differential-drive local motions: endpoints, no sideways motion, metric, and motion validity."""

from __future__ import annotations

import math

import numpy as np
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.motion import DiffDriveMotion
from psprm_core.scene import Box


def _pair(robot, rng, n):
    qa = np.stack([robot.default_configuration()] * n)
    qb = qa.copy()
    qa[:, :3] = rng.uniform([-2, -2, -math.pi], [2, 2, math.pi], (n, 3))
    qb[:, :3] = rng.uniform([-2, -2, -math.pi], [2, 2, math.pi], (n, 3))
    qb[:, 3] = rng.uniform(0.2, 1.0, n)
    return torch.as_tensor(qa), torch.as_tensor(qb)


def test_interpolation_endpoints_and_no_sideways_motion(load_robot):
    robot = load_robot("stretch2")
    m = DiffDriveMotion(robot)
    qa, qb = _pair(robot, np.random.default_rng(0), 50)
    for s, ref in ((0.0, qa), (1.0, qb)):
        q = m.interpolate(qa, qb, torch.full((50,), s, dtype=torch.float64))
        d = q - ref
        d[:, 2] = torch.remainder(d[:, 2] + math.pi, 2 * math.pi) - math.pi
        assert d.abs().max() < 1e-9
    s = torch.linspace(0, 1, 401, dtype=torch.float64)
    for e in range(50):
        q = m.interpolate(qa[e].expand(401, -1), qb[e].expand(401, -1), s)
        step = q[1:, :2] - q[:-1, :2]
        lat = []
        for th in (q[:-1, 2], q[1:, 2]):  # a step across a phase boundary is along one of its two headings
            lat.append((step[:, 0] * torch.sin(th) - step[:, 1] * torch.cos(th)).abs())
        assert torch.minimum(*lat).max() < 1e-9  # the base only moves along its heading
        moving = step.norm(dim=-1) > 1e-12
        turning = (q[1:, 2] - q[:-1, 2]).abs() > 1e-12
        assert int((moving & turning).sum()) <= 2  # rotate OR translate; only the two phase boundaries mix


def test_distance_is_symmetric_and_counts_turns(load_robot):
    robot = load_robot("stretch2")
    m = DiffDriveMotion(robot)
    qa, qb = _pair(robot, np.random.default_rng(1), 200)
    assert torch.allclose(m.distance(qa, qb), m.distance(qb, qa))
    q0 = torch.as_tensor(robot.default_configuration()[None])
    q1 = q0.clone()
    q1[0, 2] = math.pi / 2  # pure rotation
    assert abs(float(m.distance(q0, q1)) - robot.config.base.rotation_weight * math.pi / 2) < 1e-9
    q2 = q0.clone()
    q2[0, 1] = 1.0  # sideways goal: must turn, drive, turn back
    assert abs(float(m.distance(q0, q2)) - (1.0 + robot.config.base.rotation_weight * math.pi)) < 1e-9


def test_motion_validity_catches_obstacle_between_free_endpoints(load_robot):
    robot = load_robot("stretch2")
    m = DiffDriveMotion(robot)
    wall = Box("wall", center=np.array([1.5, 0.0, 0.5]), size=np.array([0.1, 2.0, 1.0]))
    checker = CollisionChecker(robot, [wall])
    q0 = robot.default_configuration()
    qa, qb, qc = q0.copy(), q0.copy(), q0.copy()
    qb[0] = 3.0  # straight through the wall
    qc[1] = -2.5  # away from it
    a = torch.as_tensor(np.stack([qa, qa]), dtype=torch.float32)
    b = torch.as_tensor(np.stack([qb, qc]), dtype=torch.float32)
    assert not checker.check(a).any() and not checker.check(b).any()
    assert m.motion_valid(checker, a, b, resolution=0.05).tolist() == [False, True]
