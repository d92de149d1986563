"""Shared pytest set-up: two torch threads (the target machine), quiet pybullet, cached robot models."""

from __future__ import annotations

import functools

import pytest
import torch

torch.set_num_threads(2)


@functools.lru_cache(maxsize=None)
def _robot(name: str):
    from psprm_core.robot import RobotModel

    return RobotModel.load(name)


@pytest.fixture(scope="session")
def load_robot():
    """Factory fixture: ``load_robot('stretch2')`` returns a cached RobotModel."""
    return _robot


@pytest.fixture(scope="session")
def home_tv_planner(load_robot):
    """Factory fixture: ``home_tv_planner(**{"roadmap.n_nodes": 700, "seed": 1})`` builds a PS-PRM of Stretch in the home scene
    with a geometric scorer of the tv, templated on the start of ``tv_west_to_southeast``; returns (scene, robot,
    planner, start, goals, build stats) of that problem. Settings by dotted path (``PSPRMSettings.changed``), given
    as ``**{"roadmap.n_nodes": 700}``."""
    from psprm_core.paths import resolve_named
    from psprm_core.perception.scoring import GeometricScorer
    from psprm_core.planning.factory import problem_configurations
    from psprm_core.planning.psprm import PSPRM, PSPRMSettings
    from psprm_core.scene import load_scene

    def make(**settings):
        scene = load_scene(resolve_named("scene", "home"))
        robot = load_robot("stretch2")
        prob = scene.problem("tv_west_to_southeast")
        planner = PSPRM(robot, scene, GeometricScorer(scene, prob.target, robot.config.intrinsics),
                        scene.target(prob.target).center, PSPRMSettings().changed(settings))
        start, goals = problem_configurations(robot, scene, prob)
        stats = planner.build(template=start)
        assert stats["success"], stats
        return scene, robot, planner, start, goals, stats

    return make
