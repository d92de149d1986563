"""Synthetic targets and an analytic stand-in for the rendering oracle, shared by the perception tests."""

from __future__ import annotations

import math

import numpy as np

from psprm_core.geometry import yaw_to_quat
from psprm_core.scene import Target

FACE = Target(name="alice", detector_class="face", center=np.array([1.0, 2.0, 1.5]), size=np.array([0.1, 0.2, 0.25]),
              quat=yaw_to_quat(2.0))
CUP = Target(name="cup1", detector_class="cup", center=np.array([-1.0, 0.5, 0.8]), size=np.array([0.08, 0.08, 0.1]))


class AnalyticScorer:
    """Falls with distance; for faces also with the angle between the facing direction and the camera."""

    def __init__(self, targets):
        self.targets = {t.name: t for t in targets}

    def score(self, pose: np.ndarray, target_name: str) -> float:
        t = self.targets[target_name]
        to_cam = pose[:3, 3] - t.center
        d = float(np.linalg.norm(to_cam))
        logit = 4 * float(t.facing @ to_cam) / d - 1.5 * d + 2 if t.detector_class == "face" else 3.0 - 1.5 * d
        return 1 / (1 + math.exp(-logit))
