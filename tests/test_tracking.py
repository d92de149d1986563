"""How far an executed configuration is from the checked ones (psprm_core.tracking), judged by geometry the test
computes itself and by pybullet's mesh check: a configuration whose collision boxes lie within the planner's padding
of a configuration that clears the padded obstacles touches nothing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.evaluation.reference import PybulletWorld
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene
from psprm_core.tracking import CheckedPath, displacement

SCENES = {"stretch2": "home", "fetchlike": "nursing", "ur5_mobile": "blind_spot_alley"}
ROBOTS = sorted(SCENES)


def _random_configurations(robot, scene, rng, n):
    lo, hi = robot.lower.copy(), robot.upper.copy()
    lo[:2], hi[:2] = scene.workspace[:, 0], scene.workspace[:, 1]
    lo[2], hi[2] = -np.pi, np.pi
    return rng.uniform(lo, hi, size=(n, robot.dof))


@pytest.mark.parametrize("name", ROBOTS)
def test_a_base_translation_moves_the_robot_by_its_length(name, load_robot):
    """Every point of a rigid body moves by the same vector under a translation: the displacement is its length."""
    robot = load_robot(name)
    rng = np.random.default_rng(0)
    scene = load_scene(resolve_named("scene", SCENES[name]))
    for q in _random_configurations(robot, scene, rng, 5):
        d = rng.normal(size=(4, 2)) * 0.05
        Q = np.repeat(q[None], 4, 0)
        Q[:, :2] += d
        assert np.allclose(displacement(robot, q, Q), np.hypot(d[:, 0], d[:, 1]), atol=1e-6)


@pytest.mark.parametrize("name", ROBOTS)
def test_within_the_padding_of_a_configuration_clear_of_the_padded_obstacles_nothing_is_touched(name, load_robot):
    """Configurations that clear the scene's boxes grown by ``pad`` but not by 2 ``pad`` (close to an obstacle),
    each moved at random (base pose and joints): those whose displacement is below ``pad`` touch no box, neither in
    a box model built afresh nor in pybullet's mesh check; among those moved by more, some do (the moves reach the
    obstacles, so the first count could have failed)."""
    robot = load_robot(name)
    scene = load_scene(resolve_named("scene", SCENES[name]))
    boxes = scene.collision_boxes()
    pad = 0.05
    clear = CollisionChecker(robot, boxes, padding=pad, workspace=scene.workspace)
    near = CollisionChecker(robot, boxes, padding=2 * pad, workspace=scene.workspace)
    truth = CollisionChecker(robot, boxes, workspace=scene.workspace)
    rng = np.random.default_rng(1)
    base = []
    while len(base) < 60:
        Q = torch.as_tensor(_random_configurations(robot, scene, rng, 4000), dtype=torch.float32)
        ok = ~clear.check(Q) & near.env_hits(Q, near.boxes)
        base.extend(Q[ok].double().numpy())
    world = PybulletWorld(robot, boxes)
    try:
        inside, beyond_hits, beyond = 0, 0, 0
        for q in base[:60]:
            moves = np.repeat(q[None], 12, 0)
            scale = rng.uniform(0.0, 0.12, size=(12, 1))
            step = rng.normal(size=(12, robot.dof))
            step[:, 3:] *= 0.5  # joints up to a few centimetres or degrees, the base more
            step[:4, [0, 1]] = 0.0  # a third turns the base in place (the far corners move most) ...
            step[:4, 3:] = 0.0
            step[4:8, :3] = 0.0  # ... a third moves only the joints
            moves += scale * step
            moves[:, 3:] = np.clip(moves[:, 3:], robot.lower[3:], robot.upper[3:])
            d = displacement(robot, q, moves)
            hit_box = truth.env_hits(torch.as_tensor(moves, dtype=torch.float32), truth.boxes).numpy()
            hit_mesh = np.array([bool(world.contacts(m)[0]) for m in moves])
            assert not (hit_box | hit_mesh)[d < pad].any(), d[(hit_box | hit_mesh) & (d < pad)]
            inside += int((d < pad).sum())
            beyond += int((d >= pad).sum())
            beyond_hits += int(((hit_box | hit_mesh) & (d >= pad)).sum())
    finally:
        world.close()
    assert inside > 100 and beyond > 100
    assert beyond_hits > 0, "no move beyond the padding touched a box: the sample is not near any obstacle"


def test_deviation_finds_the_path_within_its_window_and_measures_a_sideways_offset(load_robot):
    """A straight drive along x: a configuration on the path at a time within the window is on it (0); the same
    configuration queried at a time whose window does not reach it is as far as the drive between them; shifted
    sideways by 3 cm it is 3 cm off (a translation)."""
    robot = load_robot("stretch2")
    q0 = robot.default_configuration()
    q0[:3] = [1.0, 1.0, 0.0]
    t = np.linspace(0.0, 10.0, 101)
    P = np.repeat(q0[None], len(t), 0)
    P[:, 0] += 0.3 * t  # 0.3 m/s along x
    path = CheckedPath(robot, t, P)
    q = q0.copy()
    q[0] += 0.3 * 4.0  # where the path is at 4 s
    d, t_best = path.deviation(q, 4.5, window_s=1.0)
    assert d < 1e-5 and abs(t_best - 4.0) < 1e-6
    d, _ = path.deviation(q, 8.0, window_s=1.0)  # the window reaches back to 7 s: 0.9 m ahead of q
    assert abs(d - 0.3 * 3.0) < 1e-4
    q[1] += 0.03
    d, _ = path.deviation(q, 4.0, window_s=1.0)
    assert abs(d - 0.03) < 1e-5


def test_path_distances_measure_from_the_path_between_its_samples(load_robot):
    """A base turning at 1 rad/s while it drives, sampled every 0.05 s: configurations the test puts between two
    samples (its own linear interpolation of the path) are on the path (within what 16 steps per segment leave),
    while their nearest sample is centimetres away; configurations 2 cm to the side are as far from the path as the
    test's brute force over the path sampled every 0.5 ms says."""
    robot = load_robot("stretch2")
    q0 = robot.default_configuration()
    q0[:3] = [2.0, 2.0, 0.0]
    t = np.linspace(0.0, 4.0, 41)  # the trajectory's points, 0.1 s apart
    P = np.repeat(q0[None], len(t), 0)
    P[:, 0] += 0.3 * t
    P[:, 2] += 1.0 * t
    path = CheckedPath(robot, t, P, step_s=0.05)
    taus = np.array([1.025, 2.025, 3.025])  # halfway between two samples
    Q = np.stack([np.interp(taus, t, P[:, j]) for j in range(robot.dof)], 1)
    nearest = path.deviations(Q, taus, window_s=0.5)
    assert nearest.min() > 0.01, nearest  # precondition: the samples are centimetres apart at this speed
    on = path.path_distances(Q, taus, window_s=0.5)
    spacing = displacement(robot, P[10], P[11][None])[0] / 2  # the samples' spacing: two per 0.1 s
    assert np.all(on <= spacing / 16 + 1e-6), (on, spacing)
    side = Q.copy()
    side[:, 0] -= 0.02 * np.sin(side[:, 2])
    side[:, 1] += 0.02 * np.cos(side[:, 2])
    got = path.path_distances(side, taus, window_s=0.5)
    for i in range(len(taus)):
        fine = np.arange(taus[i] - 0.5, taus[i] + 0.5, 5e-4)
        dense = np.stack([np.interp(fine, t, P[:, j]) for j in range(robot.dof)], 1)
        ref = displacement(robot, side[i], dense).min()
        assert ref > 0.01  # precondition: off the path
        assert abs(got[i] - ref) < spacing / 16 + 1e-4, (got[i], ref)
