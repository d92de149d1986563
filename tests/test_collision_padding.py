"""The collision padding (the clearance a planner keeps from obstacles) and the start fix, judged by pybullet's
distances between the robot's meshes and the boxes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.errors import ConfigError
from psprm_core.evaluation.reference import PybulletWorld, sample_uniform
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene

PAD = 0.05


@pytest.mark.parametrize("robot_name", ["stretch2", "fetchlike", "ur5_mobile"])
def test_padded_checker_keeps_the_clearance_judged_by_pybullet(robot_name, load_robot):
    robot = load_robot(robot_name)
    scene = load_scene(resolve_named("scene", "home"))
    boxes = scene.collision_boxes()
    qs = sample_uniform(robot, 1000, np.random.default_rng(5), base_box=scene.workspace)
    q32 = torch.as_tensor(qs, dtype=torch.float32)
    padded, plain = CollisionChecker(robot, boxes, padding=PAD), CollisionChecker(robot, boxes)
    env = padded.check_detailed(q32)["environment"].numpy()
    world = PybulletWorld(robot, boxes)
    try:
        clear = np.array([world.clearance(q) for q in qs])
    finally:
        world.close()
    # free of the padded boxes => at least PAD from every mesh
    assert clear[~env].min() >= PAD - 1e-4, clear[~env].min()
    near = (clear > 1e-3) & (clear < PAD - 1e-3)  # clear of the boxes but within the padding
    assert near.sum() >= 20 and env[near].all()
    # the compiled small-batch path (one row at a time) flags the same rows as the batched torch path
    rows = np.concatenate([np.nonzero(near)[0][:10], np.nonzero(clear >= PAD)[0][:10]])
    one = np.array([bool(padded.check(q32[i:i + 1])[0]) for i in rows])
    assert (one == padded.check(q32[rows]).numpy()).all()
    # unpadded checks are the plain checker's; padding only adds flags
    assert (padded.check_unpadded(q32).numpy() == plain.check(q32).numpy()).all()
    assert (padded.check(q32).numpy() >= plain.check(q32).numpy()).all()


def test_a_start_inside_the_padding_is_moved_out_and_the_motion_never_touches_an_obstacle(home_tv_planner):
    scene, robot, planner, start, goals, _ = home_tv_planner(**{"roadmap.n_nodes": 700, "seed": 1,
                                                                "edges.collision_padding": PAD})
    ck = planner.ctx.checker
    world = PybulletWorld(robot, scene.collision_boxes())
    rng = np.random.default_rng(2)
    tried = 0
    try:
        for _ in range(3000):
            q = start.copy()
            q[:2] = rng.uniform(scene.workspace[:, 0], scene.workspace[:, 1])
            q[2] = rng.uniform(-np.pi, np.pi)
            c = world.clearance(q)
            if not 0.005 < c < PAD - 0.01:  # pybullet: clear of every box, but within the padding
                continue
            assert bool(ck.check(torch.as_tensor(q[None], dtype=torch.float32))[0])
            res = planner.plan(q, goals)
            if not res.success:  # a start boxed in by the roadmap may still fail, but not for its start
                assert "start" not in res.reason, res.reason
                continue
            tried += 1
            assert np.allclose(res.waypoints[0], q, atol=1e-5)  # the path starts where the robot is
            clear = np.array([world.clearance(x) for x in res.dense])
            assert clear.min() > 0, f"the executed motion touches an obstacle (clearance {clear.min():.4f} m)"
            # the timed trajectory too (its smooth phases leave the checked pieces)
            timed = np.array([world.clearance(x) for x in res.trajectory.positions])
            assert timed.min() > 0, f"the timed trajectory touches an obstacle ({timed.min():.4f} m)"
            inside = np.nonzero(clear < PAD - 1e-3)[0]
            # only the motion out of the padding is inside it: a run of configurations from the start
            assert len(inside) and (inside == np.arange(len(inside))).all(), inside
            if tried >= 5:
                break
    finally:
        world.close()
    assert tried >= 5
    # a start that touches an obstacle is refused, not moved
    for _ in range(3000):
        q = start.copy()
        q[:2] = rng.uniform(scene.workspace[:, 0], scene.workspace[:, 1])
        t = torch.as_tensor(q[None], dtype=torch.float32)
        det = ck.check_detailed(t)
        if bool(ck.check_unpadded(t)[0]) and bool(det["environment"][0]) and not bool(det["self"][0] | det["limits"][0]):
            res = planner.plan(q, goals)
            assert not res.success and res.reason == "start configuration invalid (environment)"
            break
    else:
        pytest.fail("no start in collision found")


def test_the_padding_is_validated_and_fixed_when_the_planner_is_made(home_tv_planner):
    from psprm_core.planning.psprm import PSPRMSettings

    with pytest.raises(ConfigError, match="collision_padding"):
        PSPRMSettings().changed({"edges.collision_padding": -0.01}).validate()
    _, _, planner, _, _, _ = home_tv_planner(**{"roadmap.n_nodes": 700, "seed": 1,
                                                "edges.collision_padding": PAD})
    with pytest.raises(ConfigError, match="collision_padding"):
        planner.update_settings(**{"edges.collision_padding": 0.0})
    with pytest.raises(ValueError, match="padding"):
        CollisionChecker(planner.ctx.robot, padding=float("nan"))
