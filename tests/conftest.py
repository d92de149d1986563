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
