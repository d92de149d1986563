"""Batched ray-cast occlusion checking against oriented boxes (the second tier of Alg. 2).

The paper (Sec. "Neural Surrogate Perception Score Models", Alg. 2, lines 5-7) refines the surrogate's perception
score by casting rays from the camera towards the target and zeroing the score when the *occlusion score* -- the
fraction of rays that are blocked before reaching the target -- exceeds a threshold :math:`\\tau`.

This module implements that test in torch so that it runs batched on the CPU or the GPU:

* :func:`ray_hits` -- generic segment-vs-oriented-box test (slab method in each box's frame).
* :func:`occlusion_scores` -- rays from ``B`` camera positions to ``M`` sample points on the target, against ``K``
  occluder boxes; returns the fraction of blocked rays per camera, shape ``(B,)``.
* :class:`OcclusionChecker` -- convenience wrapper holding the occluders and the target sample points of one target
  in one scene (build it with :meth:`OcclusionChecker.from_scene`).
* :func:`zero_occluded` -- Alg. 2 lines 5-7: ``c_p <- 0`` where the occlusion score exceeds ``tau``.

Conventions
-----------
A ray is the closed segment from ``origin`` (``t = 0``) to ``end`` (``t = 1``). It is *blocked* by a box when the
segment passes through the box's interior strictly between the two end points, i.e. the box's entry/exit interval
``[t_in, t_out]`` (from the slab test) overlaps the open interval ``(0, 1)`` with ``t_in <= t_out``.

* A segment that *ends* inside a box is blocked by it (it enters the box before reaching its end) -- the same as
  pybullet's ``rayTestBatch``.
* A segment that *starts* inside a box (a camera inside an obstacle) is blocked by it when ``count_inside=True``
  (the default: a camera inside furniture sees nothing). pybullet's ``rayTestBatch`` ignores the box the ray starts
  in; ``count_inside=False`` reproduces that behaviour exactly (tested in ``tests/test_occlusion.py``).
* Grazing contacts (``t_in == t_out``, ray touching an edge or a face tangentially) count as hits; they have measure
  zero for random rays.

The paper casts rays against the axis-aligned bounding boxes of nearby objects; oriented boxes are used here (an
AABB is the special case of an identity rotation), which is exact for rotated furniture.

The target's own box and any box the target is part of (a face on a person's body box, a screen inside a monitor
box) must not be passed as occluders: :meth:`OcclusionChecker.from_scene` excludes the target, boxes with the
target's name, any names passed in ``exclude``, and (by default) every box that contains the target's centroid.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Iterable, Optional, Sequence, Union

import numpy as np
import torch

from ..errors import InputError
from ..geometry import EPS_DIR as _EPS_DIR, quat_to_matrix
from ..kernels._fast_packs import OcclusionPack
from ..kernels.arrays import as_f64
from ..kernels.compute import Computing
from ..scene import Box, Scene, Target
from .appearance import get_appearance

log = logging.getLogger(__name__)

#: Default occlusion threshold tau of Alg. 2 (a camera is "occluded" when more than half of its rays are blocked).
DEFAULT_TAU = 0.5
#: Default number of ray-box pairs processed per chunk (bounds peak memory: ~40 bytes x this x a few temporaries).
DEFAULT_CHUNK_ELEMENTS = 1 << 18


# ------------------------------------------------------------------------------------------------------------------
# Box tensors
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BoxTensors:
    """A batch of ``K`` oriented boxes as tensors.

    Attributes
    ----------
    centers : (K, 3) tensor
        Box centres in the scene frame.
    rotations : (K, 3, 3) tensor
        Box orientations (columns are the box axes in the scene frame).
    half_extents : (K, 3) tensor
        Half sizes along the box's own axes.
    names : tuple of str
        Names of the boxes (for logging and exclusion); may be empty strings.
    """

    centers: torch.Tensor
    rotations: torch.Tensor
    half_extents: torch.Tensor
    names: tuple = ()

    @property
    def count(self) -> int:
        return int(self.centers.shape[0])

    @property
    def device(self) -> torch.device:
        return self.centers.device

    @property
    def dtype(self) -> torch.dtype:
        return self.centers.dtype

    def to(self, device: Union[str, torch.device, None] = None, dtype: Optional[torch.dtype] = None) -> "BoxTensors":
        """Copy to another device and/or dtype (no copy when nothing changes)."""
        kw = {}
        if device is not None:
            kw["device"] = device
        if dtype is not None:
            kw["dtype"] = dtype
        if not kw:
            return self
        return BoxTensors(self.centers.to(**kw), self.rotations.to(**kw), self.half_extents.to(**kw), self.names)

    def contains(self, points: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Whether each point (N, 3) lies inside each box (grown by ``margin``), shape (N, K)."""
        local = _to_local(points.to(self.dtype), self)  # (N, K, 3)
        return (local.abs() <= self.half_extents + margin).all(dim=-1)

    @staticmethod
    def empty(device: Union[str, torch.device, None] = None, dtype: torch.dtype = torch.float32) -> "BoxTensors":
        return BoxTensors(torch.zeros(0, 3, device=device, dtype=dtype),
                          torch.zeros(0, 3, 3, device=device, dtype=dtype),
                          torch.zeros(0, 3, device=device, dtype=dtype), ())


def boxes_to_tensors(boxes: Sequence[Union[Box, Target]], exclude: Iterable[str] = (),
                     device: Union[str, torch.device, None] = None, dtype: torch.dtype = torch.float32) -> BoxTensors:
    """Stack :class:`~psprm_core.scene.Box` (or :class:`~psprm_core.scene.Target`) objects into :class:`BoxTensors`.

    Parameters
    ----------
    boxes : sequence of Box or Target
        Anything with ``name``, ``center``, ``rotation`` and ``half_extents`` (targets are converted with
        ``as_box()``).
    exclude : iterable of str
        Names of boxes to leave out (e.g. the target and the boxes it is part of).
    device, dtype
        Where to put the tensors.
    """
    excl = set(exclude)
    kept = [b.as_box() if isinstance(b, Target) else b for b in boxes]
    kept = [b for b in kept if b.name not in excl]
    if not kept:
        return BoxTensors.empty(device, dtype)
    centers = np.stack([np.asarray(b.center, float) for b in kept])
    rots = np.stack([np.asarray(b.rotation, float) for b in kept])
    halves = np.stack([np.asarray(b.half_extents, float) for b in kept])
    as_t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
    return BoxTensors(as_t(centers), as_t(rots), as_t(halves), tuple(b.name for b in kept))


def occluder_boxes(scene: Scene, target_name: str, exclude: Iterable[str] = (), exclude_containing: bool = True,
                   device: Union[str, torch.device, None] = None, dtype: torch.dtype = torch.float32) -> BoxTensors:
    """The boxes that can occlude ``target_name`` in ``scene``.

    All obstacles and all *other* targets (whether or not they are collision obstacles, they are visible geometry),
    minus the target itself, minus ``exclude``, and -- if ``exclude_containing`` -- minus every box containing the
    target's centroid (the target is part of it, e.g. a face on a body box).
    """
    target = scene.target(target_name)
    candidates = list(scene.obstacles) + [t.as_box() for t in scene.targets if t.name != target_name]
    excl = set(exclude) | {target_name}
    if exclude_containing:
        for b in candidates:
            local = np.asarray(b.rotation).T @ (np.asarray(target.center, float) - np.asarray(b.center, float))
            if np.all(np.abs(local) <= np.asarray(b.half_extents) + 1e-9):
                log.debug("occluders for '%s': excluding '%s' (contains the target centroid)", target_name, b.name)
                excl.add(b.name)
    return boxes_to_tensors(candidates, exclude=excl, device=device, dtype=dtype)


# ------------------------------------------------------------------------------------------------------------------
# Target sample points
# ------------------------------------------------------------------------------------------------------------------
def is_front_facing(target: Union[Target, Box]) -> bool:
    """Whether the target's appearance is a picture on its facing (+x) side (a face, a screen, a photo board),
    i.e. what a camera must see is that side, not the whole box. 3-D appearances (a plant) are seen all round."""
    if not isinstance(target, Target):
        return False

    try:
        app = get_appearance(target.appearance, target.detector_class)
    except (KeyError, ValueError):
        return False
    return any(part.kind == "quad" for part in app.parts)


def front_face_points(target: Union[Target, Box], n: int = 3, shrink: float = 0.9) -> np.ndarray:
    """An ``n x n`` grid on the target's facing (+x) side, just inside the box, in the scene frame."""
    half = np.asarray(target.size, float) / 2
    ys = np.linspace(-1, 1, n) * half[1] * shrink if n > 1 else np.zeros(1)
    zs = np.linspace(-1, 1, n) * half[2] * shrink if n > 1 else np.zeros(1)
    local = np.array([[half[0] * 0.98, y, z] for y in ys for z in zs])
    return local @ np.asarray(target.rotation, float).T + np.asarray(target.center, float)


def target_sample_points(target: Union[Target, Box], shrink: float = 0.9, grid: Optional[int] = None) -> np.ndarray:
    """Points on/in the target's box that rays are cast to, in the scene frame.

    Parameters
    ----------
    target : Target or Box
    shrink : float
        Scale factor (0, 1] applied to the half extents so that points sit slightly inside the box and rays are not
        stopped by boxes the target merely touches (a cup on a table).
    grid : int, optional
        If given, an ``grid x grid x grid`` lattice over the shrunk box (``grid >= 2``; ``grid = 1`` is the centroid).
        Otherwise the default 15 points: the 8 shrunk corners, the 6 shrunk face centres and the centroid.

    Returns
    -------
    (M, 3) ndarray
    """
    if not 0 < shrink <= 1:
        raise InputError(f"shrink must be in (0, 1], got {shrink}")
    half = np.asarray(target.size, float) / 2 * shrink
    if grid is not None:
        if grid < 1:
            raise InputError(f"grid must be >= 1, got {grid}")
        ticks = np.linspace(-1, 1, grid) if grid > 1 else np.zeros(1)
        unit = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 3)
    else:
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        faces = np.concatenate([np.eye(3), -np.eye(3)])
        unit = np.concatenate([corners, faces, np.zeros((1, 3))])
    rot = np.asarray(target.rotation, float)
    return (unit * half) @ rot.T + np.asarray(target.center, float)


# ------------------------------------------------------------------------------------------------------------------
# Core slab test
# ------------------------------------------------------------------------------------------------------------------
def _to_local(points: torch.Tensor, boxes: BoxTensors) -> torch.Tensor:
    """Points (..., 3) -> coordinates in every box frame (..., K, 3): R_k^T (p - c_k)."""
    rel = points.unsqueeze(-2) - boxes.centers  # (..., K, 3)
    return torch.einsum("...kj,kji->...ki", rel, boxes.rotations)


def _slab_hits(o_local: torch.Tensor, d_local: torch.Tensor, half: torch.Tensor, count_inside: bool) -> torch.Tensor:
    """Slab test on broadcast local origins/directions (..., K, 3); returns hit flags (..., K)."""
    # Parallel direction components: nudge to a tiny value so that 0 * inf never happens (either sign gives the same
    # answer: the slab is either the whole line or empty).
    d_safe = torch.where(d_local.abs() < _EPS_DIR, _EPS_DIR, d_local)
    inv = d_safe.reciprocal()
    mid = -o_local * inv  # parameter of the slab's mid-plane crossing
    spread = half * inv.abs()  # half the parameter width of the slab
    t_in = (mid - spread).amax(dim=-1)
    t_out = (mid + spread).amin(dim=-1)
    hit = (t_in <= t_out) & (t_out > 0) & (t_in < 1)
    if not count_inside:
        hit = hit & (t_in > 0)  # the box the segment starts in is ignored (pybullet's rayTest behaviour)
    return hit


def _chunk_rows(total_rows: int, per_row: int, chunk_elements: int) -> int:
    return max(1, min(total_rows, chunk_elements // max(1, per_row)))


def ray_hits(origins: torch.Tensor, ends: torch.Tensor, boxes: BoxTensors, count_inside: bool = True,
             chunk_elements: int = DEFAULT_CHUNK_ELEMENTS) -> torch.Tensor:
    """Whether each segment ``origins[i] -> ends[i]`` is blocked by any box.

    Parameters
    ----------
    origins, ends : (R, 3) tensors
        Segment end points in the scene frame. The boxes are moved to their device/dtype.
    boxes : BoxTensors
        ``K`` oriented boxes.
    count_inside : bool
        Whether a segment starting inside a box is blocked by it (see the module docstring).
    chunk_elements : int
        Maximum number of ray-box pairs evaluated at once.

    Returns
    -------
    (R,) bool tensor on the device of ``origins``.
    """
    origins = torch.as_tensor(origins)
    if not origins.is_floating_point():
        origins = origins.double()
    ends = torch.as_tensor(ends, dtype=origins.dtype, device=origins.device)
    if origins.shape != ends.shape or origins.shape[-1] != 3 or origins.dim() != 2:
        raise InputError(f"origins and ends must both be (R, 3); got {tuple(origins.shape)} and {tuple(ends.shape)}")
    r = origins.shape[0]
    out = torch.zeros(r, dtype=torch.bool, device=origins.device)
    if boxes.count == 0 or r == 0:
        return out
    boxes = boxes.to(origins.device, origins.dtype)
    step = _chunk_rows(r, boxes.count, chunk_elements)
    for s in range(0, r, step):
        o = _to_local(origins[s:s + step], boxes)
        e = _to_local(ends[s:s + step], boxes)
        out[s:s + step] = _slab_hits(o, e - o, boxes.half_extents, count_inside).any(dim=-1)
    return out


def camera_positions(cameras: torch.Tensor) -> torch.Tensor:
    """Accept camera positions (B, 3) or camera poses (B, 4, 4) and return positions (B, 3)."""
    cameras = torch.as_tensor(cameras)
    if cameras.dim() == 3 and cameras.shape[-2:] == (4, 4):
        return cameras[:, :3, 3]
    if cameras.dim() == 2 and cameras.shape[-1] == 3:
        return cameras
    raise InputError(f"expected camera positions (B, 3) or poses (B, 4, 4), got {tuple(cameras.shape)}")


def occlusion_scores(cameras: torch.Tensor, target_points: torch.Tensor, boxes: BoxTensors, count_inside: bool = True,
                     chunk_elements: int = DEFAULT_CHUNK_ELEMENTS) -> torch.Tensor:
    """Occlusion score of Alg. 2: the fraction of rays from each camera to the target's sample points that are blocked.

    Parameters
    ----------
    cameras : (B, 3) or (B, 4, 4) tensor
        Camera positions or optical-frame poses in the scene frame.
    target_points : (M, 3) tensor or ndarray
        Sample points on the target (see :func:`target_sample_points`).
    boxes : BoxTensors
        The ``K`` occluders (the target and the boxes it is part of must be excluded).
    count_inside, chunk_elements
        See :func:`ray_hits`. Cameras are processed in chunks of ``chunk_elements // (M K)``.

    Returns
    -------
    (B,) tensor in [0, 1] with the dtype/device of ``cameras``.
    """
    pos = camera_positions(cameras)
    if not pos.is_floating_point():
        pos = pos.double()
    pts = torch.as_tensor(target_points, dtype=pos.dtype, device=pos.device)
    b, m = pos.shape[0], pts.shape[0]
    if boxes.count == 0 or b == 0 or m == 0:
        return torch.zeros(b, dtype=pos.dtype, device=pos.device)
    boxes = boxes.to(pos.device, pos.dtype)
    pts_local = _to_local(pts, boxes).unsqueeze(0)  # (1, M, K, 3)
    # broad phase: every ray camera -> p_i stays within r = max |p_i - centre| of the segment camera -> centre
    # (the point at parameter s is s |p_i - centre| away), so a box the centre segment misses once inflated by r
    # (half extents + r contain the box's Minkowski sum with that ball) blocks none of the camera's rays
    centre = pts.mean(0)
    r = (pts - centre).norm(dim=-1).max()
    centre_local = _to_local(centre, boxes)  # (K, 3)
    fat_half = boxes.half_extents + r
    out = torch.zeros(b, dtype=pos.dtype, device=pos.device)
    step = _chunk_rows(b, m * boxes.count, chunk_elements)
    for s in range(0, b, step):
        o = _to_local(pos[s:s + step], boxes)  # (b, K, 3)
        near = _slab_hits(o, centre_local - o, fat_half, True)  # (b, K)
        ci, ki = torch.nonzero(near, as_tuple=True)
        if len(ci) == 0:
            continue
        # narrow phase: the M rays of each candidate (camera, box) pair against that box only
        oc = o[ci, ki].unsqueeze(1)  # (P, 1, 3)
        hit = _slab_hits(oc, pts_local[0, :, ki].transpose(0, 1) - oc, boxes.half_extents[ki].unsqueeze(1),
                         count_inside)  # (P, M)
        blocked = torch.zeros(o.shape[0], m, dtype=torch.int32, device=pos.device)
        blocked.index_add_(0, ci, hit.to(torch.int32))
        out[s:s + o.shape[0]] = (blocked > 0).to(pos.dtype).mean(dim=1)
    return out


def zero_occluded(scores: torch.Tensor, occ_scores: torch.Tensor, tau: float = DEFAULT_TAU) -> torch.Tensor:
    """Alg. 2, lines 5-7: set the perception score to 0 where the occlusion score exceeds ``tau``."""
    return torch.where(occ_scores > tau, torch.zeros_like(scores), scores)


# ------------------------------------------------------------------------------------------------------------------
# Convenience wrapper
# ------------------------------------------------------------------------------------------------------------------
class OcclusionChecker(Computing):
    """Occluders and target sample points for one target; scores batches of camera poses (Alg. 2, lines 5-7).

    Parameters
    ----------
    boxes : BoxTensors
        Occluder boxes (without the target).
    target_points : (M, 3) array-like
        Points rays are cast to.
    tau : float
        Occlusion threshold: a camera is occluded when its occlusion score is ``> tau``.
    count_inside : bool
        See :func:`ray_hits`.
    chunk_elements : int
        Ray-box pairs per chunk.
    """

    def __init__(self, boxes: BoxTensors, target_points, tau: float = DEFAULT_TAU, count_inside: bool = True,
                 chunk_elements: int = DEFAULT_CHUNK_ELEMENTS) -> None:
        self.boxes = boxes
        if not isinstance(target_points, torch.Tensor):
            target_points = torch.as_tensor(np.asarray(target_points, dtype=float))
        self.target_points = target_points
        self.tau = float(tau)
        self.count_inside = count_inside
        self.chunk_elements = int(chunk_elements)
        self._cache: dict = {}

    @classmethod
    def from_scene(cls, scene: Scene, target_name: str, tau: float = DEFAULT_TAU, shrink: float = 0.9,
                   grid: Optional[int] = None, exclude: Iterable[str] = (), exclude_containing: bool = True,
                   front: Optional[bool] = None, boxes: Optional[BoxTensors] = None, **kw) -> "OcclusionChecker":
        """Build the checker for ``target_name`` (see :func:`occluder_boxes` and :func:`target_sample_points`);
        ``boxes``: the occluders when the caller has them (:func:`occluder_boxes`, float64), else found here.

        ``front`` (default: :func:`is_front_facing`) casts the rays to a 3 x 3 grid on the target's facing side
        instead of its whole box: for a face on a body, rays to the back of the face box graze the body (the
        shoulders) although the face itself is in view. On the nursing views this brought the RMSE on occluded views
        from 0.18 to 0.10 (docs/benchmarks.md).
        """
        boxes = boxes if boxes is not None else occluder_boxes(scene, target_name, exclude, exclude_containing,
                                                               dtype=torch.float64)
        target = scene.target(target_name)
        if front is None:
            front = is_front_facing(target)
        pts = front_face_points(target, shrink=shrink) if front else target_sample_points(target, shrink=shrink,
                                                                                         grid=grid)
        log.debug("occlusion checker for '%s': %d occluders, %d rays per camera", target_name, boxes.count, len(pts))
        return cls(boxes, pts, tau=tau, **kw)

    def _on(self, device: torch.device, dtype: torch.dtype):
        key = (str(device), dtype)
        if key not in self._cache:
            self._cache[key] = (self.boxes.to(device, dtype), self.target_points.to(device=device, dtype=dtype))
        return self._cache[key]

    def kernel_pack(self):
        """The occluders and target points as the compiled kernels take them: an
        :class:`~psprm_core.kernels._fast_packs.OcclusionPack` (target points and centre in every box frame, boxes grown
        by the points' radius, box centres, rotations, half extents, ``count_inside``, the direction eps). Kept until
        the boxes, the points or ``count_inside`` are replaced."""
        key = (self.boxes, self.target_points, bool(self.count_inside))
        got = self.__dict__.get("_kernel_pack")
        if got is None or any(a is not b for a, b in zip(got[0][:2], key[:2])) or got[0][2] != key[2]:
            bx, pts = self.boxes, as_f64(self.target_points).reshape(-1, 3)
            c, R, h = (as_f64(bx.centers).reshape(-1, 3), as_f64(bx.rotations).reshape(-1, 3, 3),
                       as_f64(bx.half_extents).reshape(-1, 3))
            centre = pts.mean(0)
            r = np.linalg.norm(pts - centre, axis=1).max() if len(pts) else 0.0
            local = lambda p: np.einsum("...kj,kji->...ki", p[..., None, :] - c, R)  # noqa: E731 - R_k^T (p - c_k)
            got = self._kernel_pack = (key, OcclusionPack(np.ascontiguousarray(local(pts)),
                                                          np.ascontiguousarray(local(centre)), h + r, c, R, h,
                                                          key[2], float(_EPS_DIR)))
        return got[1]

    def score(self, cameras: torch.Tensor) -> torch.Tensor:
        """Occlusion scores (B,) for camera positions (B, 3) or poses (B, 4, 4), on their device."""
        pos = camera_positions(torch.as_tensor(cameras))
        return self.score_positions(pos if pos.is_floating_point() else pos.double())

    def score_positions(self, pos: torch.Tensor) -> torch.Tensor:
        """Occlusion scores (B,) of camera positions (B, 3), on their device."""
        return self.compute.ops.occlusion_scores(self, pos)

    def score_positions_torch(self, pos: torch.Tensor) -> torch.Tensor:  # the torch implementation
        boxes, pts = self._on(pos.device, pos.dtype)
        return occlusion_scores(pos, pts, boxes, self.count_inside, self.chunk_elements)

    def occluded(self, cameras: torch.Tensor) -> torch.Tensor:
        """``score > tau`` as a bool tensor (B,)."""
        return self.score(cameras) > self.tau

    def apply(self, scores: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        """Zero the perception ``scores`` (B,) of occluded cameras (Alg. 2, lines 5-7)."""
        return zero_occluded(scores, self.score(cameras).to(scores.dtype), self.tau)


# ------------------------------------------------------------------------------------------------------------------
# Benchmark
# ------------------------------------------------------------------------------------------------------------------
def benchmark_rays_per_s(n_cameras: int = 10_000, n_points: int = 15, n_boxes: int = 30, repeats: int = 3,
                         device: Union[str, torch.device] = "cpu", dtype: torch.dtype = torch.float32,
                         threads: Optional[int] = None, seed: int = 0) -> float:
    """Throughput of :func:`occlusion_scores` in rays per second (a ray = one camera-point pair against all boxes).

    Random cameras in a 10 m cube, random boxes, ``n_points`` target points; best of ``repeats`` timed runs.
    ``threads`` sets ``torch.set_num_threads`` for the duration of the run.
    """
    old = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        g = torch.Generator().manual_seed(seed)
        cams = (torch.rand(n_cameras, 3, generator=g) * 10 - 5).to(device=device, dtype=dtype)
        pts = (torch.rand(n_points, 3, generator=g) * 0.4).to(device=device, dtype=dtype)
        q = torch.randn(n_boxes, 4, generator=g, dtype=torch.float64)
        q = q / q.norm(dim=1, keepdim=True)
        rots = torch.as_tensor(np.stack([quat_to_matrix(qq) for qq in q.numpy()]))
        boxes = BoxTensors((torch.rand(n_boxes, 3, generator=g) * 8 - 4).to(device, dtype), rots.to(device, dtype),
                           (torch.rand(n_boxes, 3, generator=g) * 0.5 + 0.05).to(device, dtype))
        best = math.inf
        with torch.inference_mode():
            occlusion_scores(cams[:64], pts, boxes)
            for _ in range(max(1, repeats)):
                if cams.is_cuda:
                    torch.cuda.synchronize(cams.device)
                t0 = time.perf_counter()
                occlusion_scores(cams, pts, boxes)
                if cams.is_cuda:
                    torch.cuda.synchronize(cams.device)
                best = min(best, time.perf_counter() - t0)
        return n_cameras * n_points / best
    finally:
        torch.set_num_threads(old)

