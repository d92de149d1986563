"""Perception scorers used by the planners: camera poses (B, 4, 4) -> scores (B,) in [0, 1].

Scorers work on camera poses, not configurations, so they are robot-agnostic (the paper's SE(3) formulation); the
planner obtains camera poses from batched FK.

* :class:`NeuralScorer` — the surrogate MLP with ray-cast occlusion (Alg. 2): ``neural-psprm-*`` variants.
* :class:`OracleScorer` — render + real detector (ground truth, slow): ``psprm-*`` variants and evaluation.
* :class:`GeometricScorer` — a closed-form proxy (in view, distance, viewing angle, occlusion): the RL baseline's
  "geometric perception proxy", and a fast stand-in in unit tests of the planner. It is not used by any PS-PRM variant.
* :class:`MultiTargetScorer` — several targets: averaged scores, or distance-based priority (paper Sec. "Conflicting
  target placements").
"""

from __future__ import annotations

import copy
import logging
import math
from typing import Sequence

import numpy as np
import torch

from ..camera import CameraIntrinsics
from ..scene import Scene
from ..errors import InputError
from .occlusion import OcclusionChecker, occluder_boxes

log = logging.getLogger(__name__)


class Scorer:
    """Interface: ``score(cameras (B,4,4) tensor) -> (B,) tensor`` on the cameras' device."""

    name = "scorer"
    cost_per_call_s = 0.0  # rough wall time per camera pose (lets planners decide what to evaluate lazily)

    def score(self, cameras: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def score_pose(self, camera: np.ndarray) -> float:
        """The score of one camera pose (4, 4) (default: :meth:`score` of a batch of one; scorers may do it
        without a tensor batch)."""
        with torch.no_grad():
            return float(self.score(torch.as_tensor(np.asarray(camera, dtype=np.float64)[None]))[0])

    def set_scene(self, scene: Scene) -> None:
        """Update target/obstacle poses (default: rebuild nothing)."""
        self.scene = scene

    _compute = None  # the Compute given to :meth:`using` (None: each part keeps its own)

    def using(self, compute) -> "Scorer":
        """A copy of this scorer whose batched parts (the surrogate, the occlusion checker, the scorers it combines)
        compute with ``compute`` (:class:`~psprm_core.kernels.compute.Compute`); this scorer unchanged."""
        out = copy.copy(self)
        out._compute = compute
        for name in ("model", "occ"):
            part = getattr(self, name, None)
            if hasattr(part, "using"):
                setattr(out, name, part.using(compute))
        if isinstance(getattr(self, "scorers", None), list):
            out.scorers = [s.using(compute) for s in self.scorers]
        return out

    def _computing(self, part):
        """``part`` (an occlusion checker built by :meth:`set_scene`) following the scorer's Compute, if given."""
        return part if part is None or self._compute is None else part.using(self._compute)

    def _occlusion_checker(self, scene: Scene, **kw) -> OcclusionChecker:
        """:meth:`OcclusionChecker.from_scene` for the scorer's target, following the scorer's Compute. The occluders
        of the last scene are reused while the obstacles and the other targets are the same objects and the target's
        centre has not moved (a target turned in place: what-if scoring of its predicted headings); the rays' target
        points always follow the target."""
        target = scene.target(self.target_name)
        others = tuple(t for t in scene.targets if t.name != self.target_name)
        key = (scene.obstacles, others, tuple(np.asarray(target.center, float).tolist()), tuple(sorted(kw.items())))
        memo = self.__dict__.get("_occluders")
        same = memo is not None and memo[0][0] is key[0] and len(memo[0][1]) == len(others) and \
            all(a is b for a, b in zip(memo[0][1], others)) and memo[0][2:] == key[2:]
        if not same:
            memo = self._occluders = (key, occluder_boxes(scene, self.target_name, dtype=torch.float64))
        return self._computing(OcclusionChecker.from_scene(scene, self.target_name, boxes=memo[1], **kw))


def _target_pose(scene: Scene, name: str) -> np.ndarray:
    t = scene.target(name)
    T = np.eye(4)
    T[:3, :3] = t.rotation
    T[:3, 3] = t.center
    return T


class GeometricScorer(Scorer):
    """Closed-form perception proxy for one target.

    score = in_view * exp(-((d - d_best) / d_width)^2) * clip((cos(angle) - cos_min) / (1 - cos_min), 0, 1)

    where d is the camera-target distance, ``angle`` the angle between the target's facing direction and the
    direction to the camera, ``in_view`` whether the centroid projects inside the image in front of the camera;
    occluded views (ray casting, Alg. 2) score 0.
    """

    name = "geometric"

    def __init__(self, scene: Scene, target: str, intrinsics: CameraIntrinsics = CameraIntrinsics(),
                 d_best: float = 1.5, d_width: float = 2.5, cos_min: float = 0.0, occlusion: bool = True):
        self.intr = intrinsics
        self.target_name = target
        self.d_best, self.d_width, self.cos_min = d_best, d_width, cos_min
        self.occlusion = occlusion
        self.set_scene(scene)

    def set_scene(self, scene: Scene) -> None:
        self.scene = scene
        t = scene.target(self.target_name)
        self.center = torch.as_tensor(t.center, dtype=torch.float64)
        self.facing = torch.as_tensor(t.facing, dtype=torch.float64)
        self.occ = self._occlusion_checker(scene) if self.occlusion else None

    def score(self, cameras: torch.Tensor) -> torch.Tensor:
        dt = cameras.dtype
        p = self.center.to(cameras.device, dt)
        f = self.facing.to(cameras.device, dt)
        pc = ((p - cameras[:, :3, 3]).unsqueeze(1) @ cameras[:, :3, :3]).squeeze(1)
        z = pc[:, 2]
        in_view = (z > self.intr.near) & (pc[:, 0].abs() <= self.intr.tan_half_h * z) & (
            pc[:, 1].abs() <= self.intr.tan_half_v * z) & (z < self.intr.far)
        to_cam = cameras[:, :3, 3] - p
        d = to_cam.norm(dim=-1).clamp_min(1e-9)
        cos = (to_cam @ f) / d
        s = torch.exp(-((d - self.d_best) / self.d_width) ** 2) * ((cos - self.cos_min) / (1 - self.cos_min)).clamp(0, 1)
        s = torch.where(in_view, s, torch.zeros_like(s))
        if self.occ is not None:
            s = self.occ.apply(s, cameras)
        return s

    def score_pose(self, camera: np.ndarray) -> float:
        """:meth:`score` of one camera pose (4, 4) float64 with numpy and the compiled ray casting (an RL
        environment's step scores one view: no tensor batch). The same formula; the occlusion rays only for a view
        that scores above 0."""
        p, f = self.center.numpy(), self.facing.numpy()
        pc = camera[:3, :3].T @ (p - camera[:3, 3])
        z = pc[2]
        if not (self.intr.near < z < self.intr.far and abs(pc[0]) <= self.intr.tan_half_h * z
                and abs(pc[1]) <= self.intr.tan_half_v * z):
            return 0.0
        to_cam = camera[:3, 3] - p
        d = max(float(np.linalg.norm(to_cam)), 1e-9)
        cos = float(to_cam @ f) / d
        v = math.exp(-((d - self.d_best) / self.d_width) ** 2) * min(max((cos - self.cos_min) / (1 - self.cos_min),
                                                                         0.0), 1.0)
        if v > 0.0 and self.occ is not None:
            pos = torch.from_numpy(np.ascontiguousarray(camera[None, :3, 3], dtype=np.float64))
            occ = self.occ.score_positions(pos)
            if float(occ[0]) > self.occ.tau:
                return 0.0
        return v


class NeuralScorer(Scorer):
    """Surrogate MLP + ray-cast occlusion for one target (Alg. 2).

    Parameters
    ----------
    surrogate : PerceptionSurrogate
    scene : Scene
    target : str
    occlusion : bool
        Zero the score when the occlusion score exceeds ``tau``.
    """

    name = "neural"

    def __init__(self, surrogate, scene: Scene, target: str, occlusion: bool = True, tau: float = 0.5):
        self.model = surrogate
        self.target_name = target
        self.occlusion = occlusion
        self.tau = tau
        self.set_scene(scene)

    def set_scene(self, scene: Scene) -> None:
        self.scene = scene
        t = scene.target(self.target_name)
        self.class_name = t.detector_class
        self.model.class_index(self.class_name)  # raises a clear error for classes the model was not trained on
        self.target_pose = torch.as_tensor(_target_pose(scene, self.target_name))
        self.occ = self._occlusion_checker(scene, tau=self.tau) if self.occlusion else None

    def score(self, cameras: torch.Tensor) -> torch.Tensor:
        s = self.model.predict(cameras, self.target_pose.to(cameras.device, cameras.dtype), self.class_name)
        s = s.to(cameras.dtype)
        if self.occ is not None:
            s = self.occ.apply(s, cameras)
        return s


class OracleScorer(Scorer):
    """Ground truth: render each camera view and run the real detector (slow: ~0.1 s per pose on a CPU)."""

    name = "oracle"
    cost_per_call_s = 0.1

    def __init__(self, oracle, target: str):
        self.oracle = oracle
        self.target_name = target
        self.scene = oracle.scene

    def set_scene(self, scene: Scene) -> None:
        for t in scene.targets:
            self.oracle.set_target_pose(t.name, t.center, t.quat)
        for b in scene.obstacles:
            self.oracle.set_obstacle_pose(b.name, b.center, b.quat)
        self.scene = scene

    def score(self, cameras: torch.Tensor) -> torch.Tensor:
        poses = cameras.detach().cpu().double().numpy()
        s = self.oracle.scores(list(poses), self.target_name)
        return torch.as_tensor(np.asarray(s), dtype=cameras.dtype, device=cameras.device)


class MultiTargetScorer(Scorer):
    """Combine per-target scorers.

    mode ``"mean"``: the average of the targets' scores (the paper's nursing experiment). mode ``"priority"``:
    a distance-based priority that shifts attention to the nearest target, weights w_i ∝ exp(-d_i / length).
    """

    def __init__(self, scorers: Sequence[Scorer], centers: Sequence[np.ndarray], mode: str = "mean",
                 length: float = 1.0):
        if mode not in ("mean", "priority"):
            raise InputError(f"unknown multi-target mode '{mode}' (mean or priority)")
        self.scorers = list(scorers)
        self.centers = torch.as_tensor(np.stack(centers), dtype=torch.float64)
        self.mode = mode
        self.length = length
        self.name = f"{mode}({','.join(s.name for s in self.scorers)})"

    def set_scene(self, scene: Scene) -> None:
        for s in self.scorers:
            s.set_scene(scene)
        self.centers = torch.as_tensor(np.stack([scene.target(s.target_name).center for s in self.scorers]))

    def score(self, cameras: torch.Tensor) -> torch.Tensor:
        S = torch.stack([s.score(cameras) for s in self.scorers], -1)
        if self.mode == "mean":
            return S.mean(-1)
        d = (cameras[:, None, :3, 3] - self.centers.to(cameras.device, cameras.dtype)).norm(dim=-1)
        w = torch.softmax(-d / self.length, dim=-1)
        return (w * S).sum(-1)
