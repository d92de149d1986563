"""Camera-pose sampling of the perception datasets (:mod:`psprm_core.perception.dataset` re-exports it): the
sampler's ranges (:class:`SamplingConfig`), the poses that see a target's centroid (:func:`sample_camera_poses`, as
the dataset module's docstring describes), all the poses of a dataset (:func:`generate_samples`), the field-of-view
test and the sampler's parameters of arbitrary poses (:func:`view_parameters`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..camera import CameraIntrinsics
from ..errors import InputError
from ..scene import Target

_MAX_ELEVATION = math.radians(85.0)


# ------------------------------------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SamplingConfig:
    """Ranges of the camera-pose sampler (see the module docstring).

    Attributes
    ----------
    distance : (float, float)
        Camera-to-target-centroid distance range, metres (must start beyond the near plane).
    camera_height : (float, float)
        Camera height range in the scene frame, metres.
    azimuth : (float, float)
        Azimuth range around the target, radians, relative to its facing direction (0 = in front).
    image_margin : float
        Fraction of the image width/height kept free on each side when drawing the target's pixel (0 = anywhere).
    roll_deg : float
        Maximum absolute roll about the line of sight, degrees.
    intrinsics : CameraIntrinsics
        Camera model (field of view, image size, clipping planes).
    """

    distance: tuple = (0.4, 4.0)
    camera_height: tuple = (0.3, 1.6)
    azimuth: tuple = (-math.pi, math.pi)
    image_margin: float = 0.05
    roll_deg: float = 5.0
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics)

    def validate(self) -> None:
        d0, d1 = self.distance
        h0, h1 = self.camera_height
        a0, a1 = self.azimuth
        if not 0 < d0 <= d1:
            raise InputError(f"distance range must satisfy 0 < min <= max, got {self.distance}")
        if d0 < self.intrinsics.near or d1 > self.intrinsics.far:
            raise InputError(f"distance range {self.distance} must lie within the clipping range "
                             f"[{self.intrinsics.near}, {self.intrinsics.far}]")
        if not h0 <= h1:
            raise InputError(f"camera_height range must satisfy min <= max, got {self.camera_height}")
        if not a0 <= a1:
            raise InputError(f"azimuth range must satisfy min <= max, got {self.azimuth}")
        if not 0 <= self.image_margin < 0.5:
            raise InputError(f"image_margin must be in [0, 0.5), got {self.image_margin}")
        if not 0 <= self.roll_deg <= 180:
            raise InputError(f"roll_deg must be in [0, 180], got {self.roll_deg}")

    def to_dict(self) -> dict:
        return {"distance": [float(v) for v in self.distance], "camera_height": [float(v) for v in self.camera_height],
                "azimuth": [float(v) for v in self.azimuth], "image_margin": float(self.image_margin),
                "roll_deg": float(self.roll_deg), "intrinsics": dataclasses.asdict(self.intrinsics)}

    @classmethod
    def from_dict(cls, d: dict) -> "SamplingConfig":
        d = dict(d)
        intr = CameraIntrinsics.from_dict(d.pop("intrinsics", {}))
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}, intrinsics=intr)


# ------------------------------------------------------------------------------------------------------------------
# Pose sampling
# ------------------------------------------------------------------------------------------------------------------
def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Batched rotation matrices (n, 3, 3) about unit axes (n, 3) by angles (n,)."""
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    c, s = np.cos(angle), np.sin(angle)
    C = 1 - c
    return np.stack([
        np.stack([c + x * x * C, x * y * C - z * s, x * z * C + y * s], -1),
        np.stack([y * x * C + z * s, c + y * y * C, y * z * C - x * s], -1),
        np.stack([z * x * C - y * s, z * y * C + x * s, c + z * z * C], -1),
    ], 1)


def _pan_tilt_for_pixel(w: np.ndarray, ray: np.ndarray) -> tuple:
    """Pan/tilt (yaw, pitch) of a roll-free optical frame that sees world direction ``w`` (n, 3) along camera ray
    ``ray`` (n, 3) (both unit). Returns ``(yaw, pitch, feasible)``; infeasible when the target is too steep for that
    pixel column."""
    a = np.hypot(ray[:, 1], ray[:, 2])
    ratio = w[:, 2] / a
    feasible = np.abs(ratio) <= 1.0
    pitch = np.arctan2(ray[:, 1], ray[:, 2]) + np.arcsin(np.clip(ratio, -1.0, 1.0))
    b = ray[:, 1] * np.sin(pitch) + ray[:, 2] * np.cos(pitch)
    yaw = np.arctan2(w[:, 1], w[:, 0]) - np.arctan2(-ray[:, 0], b)
    return yaw, pitch, feasible & (np.abs(pitch) < math.pi / 2)


def _pan_tilt_matrix(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Optical-frame rotations (n, 3, 3) with optical axis at (yaw, pitch) and a horizontal image x axis."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    x = np.stack([sy, -cy, np.zeros_like(yaw)], 1)
    y = np.stack([sp * cy, sp * sy, -cp], 1)
    z = np.stack([cp * cy, cp * sy, sp], 1)
    return np.stack([x, y, z], axis=2)


def _pixel_rays(u: np.ndarray, v: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    ray = np.stack([(u - intr.width / 2) / intr.fx, (v - intr.height / 2) / intr.fy, np.ones_like(u)], axis=1)
    return ray / np.linalg.norm(ray, axis=1, keepdims=True)


def _aim_with_pixel(to_target: np.ndarray, u: np.ndarray, v: np.ndarray, roll: np.ndarray, intr: CameraIntrinsics,
                    rng: np.random.Generator, margin: float) -> np.ndarray:
    """Camera rotations that put the target (direction ``to_target``) on pixel (u, v), then roll about the line of
    sight. ``u``/``v`` are redrawn in place (from ``rng``) where a roll-free pan/tilt camera cannot do it (views
    steeper than the pixel's column allows)."""
    w = to_target / np.linalg.norm(to_target, axis=1, keepdims=True)
    yaw, pitch, ok = _pan_tilt_for_pixel(w, _pixel_rays(u, v, intr))
    for _ in range(1000):
        bad = np.flatnonzero(~ok)
        if bad.size == 0:
            break
        u[bad] = rng.uniform(margin, 1 - margin, size=bad.size) * intr.width
        v[bad] = rng.uniform(margin, 1 - margin, size=bad.size) * intr.height
        yaw[bad], pitch[bad], ok[bad] = _pan_tilt_for_pixel(w[bad], _pixel_rays(u[bad], v[bad], intr))
    if not ok.all():  # practically unreachable with the 85-degree elevation cap: centre the target instead
        bad = np.flatnonzero(~ok)
        u[bad], v[bad] = intr.width / 2, intr.height / 2
        yaw[bad], pitch[bad], ok[bad] = _pan_tilt_for_pixel(w[bad], _pixel_rays(u[bad], v[bad], intr))
    return _rodrigues(w, roll) @ _pan_tilt_matrix(yaw, pitch)


def sample_camera_poses(target: Target, n: int, config: SamplingConfig, rng: np.random.Generator) -> tuple:
    """Sample ``n`` optical-frame camera poses that see ``target``'s centroid (see the module docstring).

    Parameters
    ----------
    target : Target
    n : int
    config : SamplingConfig
    rng : numpy Generator
        Consumed in a fixed order (one vectorised draw per quantity, then redraws of the pixels of steep views), so
        results depend only on its state.

    Returns
    -------
    poses : (n, 4, 4) ndarray
        Optical-frame poses in the scene frame.
    params : dict of (n,) ndarrays
        ``distance``, ``azimuth`` (relative to the target's facing, radians), ``height``, ``u``, ``v`` (pixel of the
        target centroid), ``roll`` (radians).

    Raises
    ------
    ValueError
        If no camera height in range can see the target from some distance in range.
    """
    config.validate()
    intr = config.intrinsics
    centre = np.asarray(target.center, float)
    tz = centre[2]
    d = rng.uniform(*config.distance, size=n)
    az = rng.uniform(*config.azimuth, size=n)
    # heights reachable from distance d: |h - tz| <= d sin(85 deg), intersected with the configured height range
    reach = d * math.sin(_MAX_ELEVATION)
    lo = np.maximum(config.camera_height[0], tz - reach)
    hi = np.minimum(config.camera_height[1], tz + reach)
    if np.any(lo > hi):
        raise InputError(f"target '{target.name}' at height {tz:.2f} m cannot be seen from camera heights "
                         f"{config.camera_height} at distances {config.distance}")
    h = lo + (hi - lo) * rng.uniform(size=n)
    u = rng.uniform(config.image_margin, 1 - config.image_margin, size=n) * intr.width
    v = rng.uniform(config.image_margin, 1 - config.image_margin, size=n) * intr.height
    roll = np.radians(rng.uniform(-config.roll_deg, config.roll_deg, size=n))

    facing = np.asarray(target.facing, float)
    yaw0 = math.atan2(facing[1], facing[0]) if np.hypot(facing[0], facing[1]) > 1e-9 else 0.0
    dz = h - tz
    r = np.sqrt(np.clip(d ** 2 - dz ** 2, 0.0, None))
    cam = np.stack([centre[0] + r * np.cos(yaw0 + az), centre[1] + r * np.sin(yaw0 + az), h], axis=1)

    rot = _aim_with_pixel(centre - cam, u, v, roll, intr, rng, config.image_margin)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rot
    poses[:, :3, 3] = cam
    return poses, {"distance": d, "azimuth": az, "height": h, "u": u, "v": v, "roll": roll}


def target_in_fov(poses: np.ndarray, point: np.ndarray, intrinsics: CameraIntrinsics,
                  tol_px: float = 1e-6) -> np.ndarray:
    """Whether ``point`` (3,) is inside the viewing frustum of each optical-frame pose (n, 4, 4)."""
    rel = np.einsum("nji,nj->ni", poses[:, :3, :3], np.asarray(point, float) - poses[:, :3, 3])
    z = rel[:, 2]
    px = intrinsics.project(rel)
    inside = (px[:, 0] >= -tol_px) & (px[:, 0] <= intrinsics.width + tol_px)
    inside &= (px[:, 1] >= -tol_px) & (px[:, 1] <= intrinsics.height + tol_px)
    return inside & (z >= intrinsics.near) & (z <= intrinsics.far)


def view_parameters(poses: np.ndarray, target_index: np.ndarray, targets: Sequence[Target],
                    intrinsics: CameraIntrinsics) -> dict:
    """The sampler's parameters of arbitrary optical-frame camera poses (views not drawn by
    :func:`sample_camera_poses`, e.g. a planner's roadmap nodes), so that such views can be split by viewpoint.

    Returns a dict of (n,) arrays: ``distance`` (camera to target centroid), ``azimuth`` (around the target,
    relative to its facing direction, in (-pi, pi]), ``height`` (camera z), ``u``/``v`` (pixel of the target
    centroid, unclipped) and ``roll`` (angle of the image x axis below the horizontal, about the line of sight).
    """
    poses = np.asarray(poses, float)
    centres = np.stack([np.asarray(t.center, float) for t in targets])[target_index]
    yaw0 = np.array([math.atan2(t.facing[1], t.facing[0]) if np.hypot(t.facing[0], t.facing[1]) > 1e-9 else 0.0
                     for t in targets])[target_index]
    cam = poses[:, :3, 3]
    off = cam - centres
    rel = np.einsum("nji,nj->ni", poses[:, :3, :3], centres - cam)
    px = intrinsics.project(rel)
    x_axis = poses[:, :3, 0]
    roll = np.arcsin(np.clip(-x_axis[:, 2], -1.0, 1.0))
    az = np.angle(np.exp(1j * (np.arctan2(off[:, 1], off[:, 0]) - yaw0)))
    return {"distance": np.linalg.norm(off, axis=1), "azimuth": az, "height": cam[:, 2].copy(), "u": px[:, 0],
            "v": px[:, 1], "roll": roll}


def _per_target_counts(n_samples: int, n_targets: int) -> list:
    base, extra = divmod(n_samples, n_targets)
    return [base + (1 if i < extra else 0) for i in range(n_targets)]


def generate_samples(targets: Sequence[Target], n_samples: int, config: SamplingConfig, seed: int) -> dict:
    """All camera poses of a dataset, in dataset order (targets in the given order, ``n_samples`` split evenly).

    Returns a dict with ``camera_poses`` (N, 4, 4), ``target_index`` (N,) and the sampling parameters (N,) each.
    """
    rng = np.random.default_rng(seed)
    counts = _per_target_counts(n_samples, len(targets))
    poses, params, tidx = [], [], []
    for i, (t, k) in enumerate(zip(targets, counts)):
        p, prm = sample_camera_poses(t, k, config, rng)
        poses.append(p)
        params.append(prm)
        tidx.append(np.full(k, i, dtype=np.int32))
    out = {"camera_poses": np.concatenate(poses), "target_index": np.concatenate(tidx)}
    for key in params[0]:
        out[key] = np.concatenate([p[key] for p in params])
    return out
