"""The kernels protocol: the batched operations whose implementation a :class:`~.compute.Compute` chooses, and the
torch implementation of it.

Every domain object that computes in batches (robot FK, the collision checker, the visibility projection, the
surrogate, ray-cast occlusion, the motion metric) keeps its torch code as a public ``*_torch`` method, its reference
(any device, autograd), and calls ``self.compute.ops.<verb>(self, ...)`` from its public method. Two implementations
answer those verbs:

- :class:`TorchKernels` (``kernels="torch"``, any device): each object's torch method;
- :class:`~.fastpath.NumbaKernels` (``kernels="numba"``, CPU): the compiled kernels for the batches its ``Compute``
  lets them serve, the torch method otherwise.

The planner's stages and the baselines use the verbs on arrays and local motions (knots, pieces, nearest nodes, the
metric of numpy batches) in the same way; neither they nor the domain classes test which implementation runs. These
verbs reach the metric, interpolation and checks through the implementation's own verbs, so the torch
implementation computes in torch whatever ``Compute`` the motion or checker was built with.
"""

from __future__ import annotations

from typing import Callable, Optional, Protocol

import numpy as np
import torch


class Kernels(Protocol):
    """The verbs of a kernels implementation, built by a :class:`~.compute.Compute` (its ``compute``, whose batch
    policy it follows); the first argument of a verb is the domain object whose data it reads."""

    name: str
    compute: object

    # ---- domain objects ---------------------------------------------------------------------------------------------
    def camera_poses(self, robot, q: torch.Tensor, body_poses: Optional[tuple] = None) -> torch.Tensor: ...
    def element_corners(self, robot, Q: np.ndarray) -> np.ndarray: ...
    def project(self, constraint, q: torch.Tensor, settings, lo: torch.Tensor, hi: torch.Tensor,
                cols: torch.Tensor) -> tuple: ...
    def check(self, checker, q: torch.Tensor) -> torch.Tensor: ...
    def check_detailed(self, checker, q: torch.Tensor) -> dict: ...
    def env_hits(self, checker, q: torch.Tensor, boxes, return_aabb: bool): ...
    def robot_aabb(self, checker, q: torch.Tensor) -> torch.Tensor: ...
    def pose_scores(self, model, cam: torch.Tensor, target_pose, class_name, chunk_size) -> torch.Tensor: ...
    def occlusion_scores(self, occ, pos: torch.Tensor) -> torch.Tensor: ...
    def distance(self, motion, qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor: ...
    def interpolate(self, motion, qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> torch.Tensor: ...

    # ---- local motions of the planner --------------------------------------------------------------------------------
    def edge_knot_seeds(self, motion, qa: torch.Tensor, qb: torch.Tensor, n_interp: int) -> tuple: ...
    def pieces(self, motion, a: torch.Tensor, b: torch.Tensor, resolution: float, max_steps: int,
               include_start: bool) -> tuple: ...
    def nearest(self, motion, qq: torch.Tensor, pool: torch.Tensor, k: int,
                pool_f64: Optional[Callable] = None) -> torch.Tensor: ...

    # ---- numpy batches -----------------------------------------------------------------------------------------------
    def metric_arrays(self, motion, qa: np.ndarray, qb: np.ndarray) -> np.ndarray: ...
    def interpolate_arrays(self, motion, qa: np.ndarray, qb: np.ndarray, s: np.ndarray) -> np.ndarray: ...
    def pieces_arrays(self, motion, a: np.ndarray, b: np.ndarray, resolution: float, max_steps: int,
                      include_start: bool) -> tuple: ...
    def check_arrays(self, checker, Q: np.ndarray) -> dict: ...


class TorchKernels:
    """Every verb in torch on the objects' devices (the reference; what a GPU runs)."""

    name = "torch"

    def __init__(self, compute):
        self.compute = compute

    # ---- domain objects ---------------------------------------------------------------------------------------------
    def camera_poses(self, robot, q, body_poses=None):
        return robot.camera_poses_torch(q, body_poses)

    def element_corners(self, robot, Q):
        return robot.element_corners_torch(Q)

    def project(self, constraint, q, settings, lo, hi, cols):
        return constraint.gauss_newton_torch(q, settings, lo, hi, cols)

    def check(self, checker, q):
        return checker.check_torch(q)

    def check_detailed(self, checker, q):
        return checker.check_detailed_torch(q)

    def env_hits(self, checker, q, boxes, return_aabb):
        return checker.env_hits_torch(q, boxes, return_aabb)

    def robot_aabb(self, checker, q):
        return checker.robot_aabb_torch(q)

    def pose_scores(self, model, cam, target_pose, class_name, chunk_size):
        return model.pose_scores_torch(cam, target_pose, class_name, chunk_size)

    def occlusion_scores(self, occ, pos):
        return occ.score_positions_torch(pos)

    def distance(self, motion, qa, qb):
        return motion.distance_torch(qa, qb)

    def interpolate(self, motion, qa, qb, s):
        return motion.interpolate_torch(qa, qb, s)

    # ---- local motions of the planner --------------------------------------------------------------------------------
    def edge_knot_seeds(self, motion, qa, qb, n_interp):
        """Knots (E, M, dof) of the local motions qa -> qb before the camera joints re-aim (the ends, the drive
        corners and the ``n_interp`` Eq. 1 samples sorted along the motion), and the positions (E, N) of the samples
        among them."""
        E, n = qa.shape[0], int(n_interp)
        dt, dev = qa.dtype, qa.device
        if motion.mobile:
            _, r1, d, r2 = motion.base_plan(qa, qb)
            l1, l2, l3 = motion.w_rot * r1.abs(), d, motion.w_rot * r2.abs()
            tot = (l1 + l2 + l3).clamp_min(1e-12)
            corners = torch.stack([l1 / tot, (l1 + l2) / tot], -1)
        else:
            corners = torch.zeros(E, 0, dtype=dt, device=dev)
        samples = (torch.arange(1, n + 1, dtype=dt, device=dev) / (n + 1)).expand(E, n)
        s_all = torch.cat([torch.zeros(E, 1, dtype=dt, device=dev), samples, corners,
                           torch.ones(E, 1, dtype=dt, device=dev)], -1)
        order = torch.argsort(s_all, dim=-1, stable=True)
        s_sorted = torch.gather(s_all, 1, order)
        interior_idx = torch.argsort(order, dim=-1)[:, 1:1 + n]
        M = s_all.shape[1]
        knots = self.interpolate(motion, qa.repeat_interleave(M, 0), qb.repeat_interleave(M, 0), s_sorted.reshape(-1))
        return knots.reshape(E, M, -1), interior_idx

    def pieces(self, motion, a, b, resolution, max_steps, include_start):
        """(piece index, points every ``resolution`` on the straight pieces a[i] -> b[i], at most ``max_steps``
        each; the first point of each piece with ``include_start``)."""
        diff = b - a
        if motion.mobile:
            diff[:, 2] = torch.remainder(diff[:, 2] + np.pi, 2 * np.pi) - np.pi
        n = torch.ceil(self.distance(motion, a, b) / resolution).long().clamp(1, max_steps)
        count = n if include_start else n - 1
        seg = torch.repeat_interleave(torch.arange(len(a), device=a.device), count)
        k = torch.arange(len(seg), device=a.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
        frac = ((k + (0 if include_start else 1)).to(a.dtype) / n[seg].to(a.dtype)).unsqueeze(-1)
        return seg, a[seg] + diff[seg] * frac

    def nearest(self, motion, qq, pool, k, pool_f64=None):
        """Indices (Q, k) of the ``k`` configurations of ``pool`` nearest to each of ``qq`` under the motion metric,
        sorted by distance (``pool_f64``: a callable giving the pool as float64 numpy, for the compiled pass)."""
        pool = torch.as_tensor(pool, dtype=qq.dtype, device=qq.device)
        d = self.distance(motion, qq.repeat_interleave(pool.shape[0], 0), pool.repeat(len(qq), 1))
        return d.reshape(len(qq), -1).topk(k, largest=False).indices

    # ---- numpy batches -----------------------------------------------------------------------------------------------
    def metric_arrays(self, motion, qa, qb):
        """The motion metric of numpy batches (E, dof), in their dtype."""
        with torch.no_grad():
            return self.distance(motion, torch.from_numpy(qa), torch.from_numpy(qb)).numpy()

    def interpolate_arrays(self, motion, qa, qb, s):
        """Configurations at fractions ``s`` (E,) of the local motions qa -> qb (numpy batches (E, dof))."""
        with torch.no_grad():
            return self.interpolate(motion, torch.from_numpy(qa), torch.from_numpy(qb), torch.from_numpy(s)).numpy()

    def pieces_arrays(self, motion, a, b, resolution, max_steps, include_start):
        """:meth:`pieces` of numpy batches: (piece index, points)."""
        with torch.no_grad():
            seg, pts = self.pieces(motion, torch.from_numpy(a), torch.from_numpy(b), resolution, max_steps,
                                   include_start)
        return seg.numpy(), pts.numpy()

    def check_arrays(self, checker, Q):
        """Collision flags {"limits", "environment", "self"} (numpy bool) of configurations ``Q`` (numpy)."""
        q = torch.from_numpy(Q).to(checker.device)
        return {k: v.cpu().numpy() for k, v in self.check_detailed(checker, q).items()}
