"""Pinhole camera model shared by constraints, renderers, ray casting and the surrogate.

Convention: camera poses are 4x4 transforms of the *optical* frame in the scene frame: +z along the optical axis,
+x to the right of the image, +y down the image (ROS ``*_optical_frame`` convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Image size, vertical field of view and clipping planes (defaults: the paper's 640x480, 42.5 deg, 0.3-10 m)."""

    width: int = 640
    height: int = 480
    vfov_deg: float = 42.5
    near: float = 0.3
    far: float = 10.0

    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def tan_half_v(self) -> float:
        return math.tan(math.radians(self.vfov_deg) / 2)

    @property
    def tan_half_h(self) -> float:
        return self.tan_half_v * self.aspect

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2 * math.atan(self.tan_half_h))

    @property
    def fy(self) -> float:
        return (self.height / 2) / self.tan_half_v

    @property
    def fx(self) -> float:
        return self.fy  # square pixels

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.width / 2], [0, self.fy, self.height / 2], [0, 0, 1.0]])

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Project (N, 3) points in the optical frame to pixel coordinates (N, 2) (no clipping)."""
        p = np.asarray(points_cam, float)
        z = np.clip(p[:, 2], 1e-9, None)
        return np.stack([self.fx * p[:, 0] / z + self.width / 2, self.fy * p[:, 1] / z + self.height / 2], axis=1)

    @classmethod
    def from_dict(cls, d: dict) -> "CameraIntrinsics":
        return cls(**d)
