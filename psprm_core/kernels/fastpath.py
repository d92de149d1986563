"""Small-batch CPU fast paths: compiled (numba) kernels for the few-dozen-configuration batches of a query.

A PS-PRM query makes about ten batched calls (FK, the Gauss-Newton re-aiming of Alg. 1 line 7 at the knots of its
connection edges, the collision checks of Lazy PRM) on a few dozen to a few hundred configurations each. In torch each
such call costs 1-10 ms of per-operator overhead, far more than its arithmetic. The kernels of
:mod:`psprm_core.kernels._fast_numba` compute the same quantities row by row in float64:

* ``camera_poses``, ``element_corners`` - :meth:`RobotModel.camera_poses`, :meth:`RobotModel.element_corners`;
* ``project`` - :meth:`VisibilityConstraint.project` (Alg. 1, line 7; line and frustum models);
* ``check``, ``check_detailed``, ``env_hits``, ``robot_aabb``, ``check_arrays`` - :class:`CollisionChecker`;
* ``occlusion_scores``, ``pose_scores`` - the neural score of Alg. 2 (:class:`OcclusionChecker`,
  :meth:`PerceptionSurrogate.predict`);
* ``distance``, ``interpolate``, ``pieces``, ``nearest``, ``edge_knot_seeds`` and their numpy forms - the diff-drive
  metric and local motions (:class:`DiffDriveMotion`, ``Edges.pieces``, the query's nearest roadmap nodes, the knots
  of Eq. 1 edges).

The kernels take their inputs grouped in the named tuples of :mod:`psprm_core.kernels._fast_packs`, one per object, each
built (and kept) by that object's class: ``RobotModel.kernel_pack``, ``CollisionChecker.kernel_pack``,
``VisibilityConstraint.kernel_pack``, ``PerceptionSurrogate.kernel_layers``, ``OcclusionChecker.kernel_pack``,
``DiffDriveMotion.kernel_pack``; this module adds the per-call ones (:func:`solver_pack`), and :mod:`.edges`
the options of the fused calls of a query's edges.

:class:`NumbaKernels` is the ``kernels="numba"`` implementation of the kernels protocol (:mod:`.ops`): each verb runs
its compiled kernel when the call fits the policy of its :class:`~psprm_core.kernels.compute.Compute` (a CPU tensor
outside autograd, at most ``max_batch`` rows, the metric up to ``motion_max_batch``), or at any size inside
:func:`~psprm_core.kernels.runtime.bulk`, which the planner's large-batch methods enter (build,
re-scoring, invalidation near moved obstacles, repair growth): their rows are split into chunks run on a small thread
pool (the kernels release the GIL). At that size the kernels are 3-8x faster than torch's batched operators on 2
cores (collision checks, projection, knot tracking, ray casting), mostly because torch materialises (rows x spheres x
boxes) intermediates where a kernel stops a row at its first hit; camera FK alone is about as fast in torch, and the
surrogate's GEMMs stay in torch. CUDA tensors keep the torch path. Nothing is compiled at import: numba compiles a
kernel on its first call (cached on disk with ``cache=True``); ``PSPRM.warm_up`` loads them before the build.
Otherwise a verb runs the object's torch method, as :class:`~.ops.TorchKernels` does. Without numba
``Compute.make`` chooses torch. An object built with a torch-only ``Compute`` (``obj.using(compute.torch_only())``)
runs the torch code at every size (tests compare both). Queries run with torch's intra-op parallelism off
(:meth:`Compute.one_thread`).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch

from ._fast_packs import BoxPack, SolverPack
from .arrays import as_f64, as_i64, const_f64
from .ops import TorchKernels
from .runtime import bulk_workers, numba_importable, worker_pool


@functools.lru_cache(maxsize=1)
def kernels() -> Any:
    """The jitted kernels (:mod:`psprm_core.kernels._fast_numba`), imported on first use."""
    from . import _fast_numba

    return _fast_numba


def available() -> bool:
    """Whether the compiled kernels can run here (numba importable); a :class:`Compute` chooses them per object."""
    return numba_importable()


def _rows(compute, kernel, n_row_args: int, *args):
    """``kernel(*args)``, whose first ``n_row_args`` arguments are per-row arrays and whose results are per-row
    arrays (or a tuple of them): inside a bulk block, split into chunks of at least ``compute.bulk_chunk`` rows run
    on the worker threads."""
    n, w, chunk = args[0].shape[0], bulk_workers(), compute.bulk_chunk
    if w < 2 or n < 2 * chunk:
        return kernel(*args)
    step = max(chunk, -(-n // (4 * w)))
    rest = args[n_row_args:]
    parts = list(worker_pool(w).map(lambda i: kernel(*(a[i:i + step] for a in args[:n_row_args]), *rest),
                                    range(0, n, step)))
    if isinstance(parts[0], tuple):
        return tuple(np.concatenate(p) for p in zip(*parts))
    return np.concatenate(parts)


def solver_pack(settings, lo: torch.Tensor, hi: torch.Tensor, cols: np.ndarray, max_iters: int) -> SolverPack:
    """The Gauss-Newton iteration's inputs (:class:`~psprm_core.kernels._fast_packs.SolverPack`): the joints ``cols``,
    the bounds, the tolerance, damping and step cap of ``settings`` (:class:`ProjectionSettings`) and ``max_iters``."""
    return SolverPack(as_i64(cols), const_f64(lo), const_f64(hi), float(settings.tolerance), int(max_iters),
                      float(settings.damping), float(settings.max_step))


def collision_flags(checker, q: torch.Tensor | np.ndarray, detailed: bool = False) -> np.ndarray:
    """Collision flags (B, 3) of ``q`` (B, dof, a tensor or a numpy array): limits, environment, self
    (:meth:`CollisionChecker.check_detailed`), compiled. Without ``detailed`` a row stops at its first violation:
    only the OR over a row is meaningful."""
    if isinstance(q, np.ndarray):
        q64 = as_f64(q.astype(np.float32) if checker.dtype == torch.float32 else q)  # rounded as the checker's dtype
    else:
        q64 = as_f64(q.to(checker.dtype))
    return _rows(checker.compute, kernels().check, 1, q64, bool(detailed), checker.robot.kernel_pack,
                 checker.kernel_pack())


def pose_features(compute, cam: torch.Tensor, target_pose, derived: bool) -> torch.Tensor:
    """The surrogate's pose features (B, 9 or 14) of camera poses (B, 4, 4) and one target pose (4, 4)
    (:func:`~psprm_core.perception.surrogate.relative_pose_features` and ``derived_features``), compiled."""
    return torch.from_numpy(_rows(compute, kernels().pose_features, 1, as_f64(cam), as_f64(target_pose), bool(derived)))


def _one_class(model, class_name) -> int | None:
    """The class index of a single class (a name, an index or a 0-d index tensor;
    :meth:`PerceptionSurrogate.class_index` checks names and indices), None for per-row classes."""
    if isinstance(class_name, torch.Tensor):
        return int(class_name) if class_name.dim() == 0 else None
    if isinstance(class_name, (str, int, np.integer)):
        return int(model.class_index(class_name))
    return None


class NumbaKernels(TorchKernels):
    """The compiled CPU kernels for the calls the ``Compute``'s batch policy lets them serve, each object's torch
    method otherwise (:class:`~.ops.TorchKernels`)."""

    name = "numba"

    def _on_cpu(self, obj, x: torch.Tensor) -> bool:
        """A batch ``x`` of an object that keeps its tensors on ``obj.device``: only a CPU one, as the policy allows."""
        return obj.device.type == "cpu" and self.compute.takes(x)

    # ---- robot --------------------------------------------------------------------------------------------------
    def camera_poses(self, robot, q, body_poses=None):
        if body_poses is None and q.dim() == 2 and q.shape[1] == robot.dof and self.compute.takes(q):
            out = _rows(self.compute, kernels().camera_poses, 1, as_f64(q), robot.kernel_pack)
            return torch.from_numpy(out).to(q.dtype)
        return super().camera_poses(robot, q, body_poses)

    def element_corners(self, robot, Q):
        if len(Q) > 0:
            local, body = robot.element_corners_local
            return kernels().element_corners(Q, robot.kernel_pack, body, local)
        return super().element_corners(robot, Q)

    # ---- projection (Alg. 1, line 7) ----------------------------------------------------------------------------
    def project(self, constraint, q, settings, lo, hi, cols):
        if constraint.kin is constraint.robot and self.compute.takes(q):  # the robot model's own kinematics
            cols = cols.cpu().numpy() if isinstance(cols, torch.Tensor) else np.asarray(cols)
            qn, err = _rows(self.compute, kernels().project, 1, as_f64(q), constraint.robot.kernel_pack,
                            constraint.kernel_pack(q.dtype), solver_pack(settings, lo, hi, cols, settings.max_iters))
            return torch.from_numpy(qn).to(q.dtype), torch.from_numpy(err < settings.tolerance)
        return super().project(constraint, q, settings, lo, hi, cols)

    # ---- collision ----------------------------------------------------------------------------------------------
    def check(self, checker, q):
        if self._on_cpu(checker, q):
            return torch.from_numpy(collision_flags(checker, q).any(-1))
        return super().check(checker, q)

    def check_detailed(self, checker, q):
        if self._on_cpu(checker, q):
            f = torch.from_numpy(collision_flags(checker, q, detailed=True))
            return {"limits": f[:, 0], "environment": f[:, 1], "self": f[:, 2]}
        return super().check_detailed(checker, q)

    def env_hits(self, checker, q, boxes, return_aabb):
        if not self._on_cpu(checker, q):
            return super().env_hits(checker, q, boxes, return_aabb)
        if boxes is None:  # no boxes: the bounds only
            box = BoxPack(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6)))
        else:
            box = boxes.kernel_pack()
        hit, aabb = _rows(self.compute, kernels().env_hits, 1, as_f64(q.to(checker.dtype)), bool(return_aabb),
                          checker.robot.kernel_pack, checker.kernel_pack()._replace(boxes=box))
        hit = torch.from_numpy(hit)
        return (hit, torch.from_numpy(aabb).to(checker.dtype)) if return_aabb else hit

    def robot_aabb(self, checker, q):
        if self._on_cpu(checker, q):
            return self.env_hits(checker, q, None, True)[1]
        return super().robot_aabb(checker, q)

    # ---- perception (Alg. 2) ------------------------------------------------------------------------------------
    def pose_scores(self, model, cam, target_pose, class_name, chunk_size):
        """Camera poses (B, 4, 4) of one target pose (4, 4) and one class, a model on the CPU, at most ``max_batch``
        rows (torch's GEMMs are faster beyond, even in bulk): numpy features and the compiled MLP up to
        ``mlp_max_rows`` rows (a query scores 2-14 views per call), torch's GEMM above."""
        cls = None
        if (cam.shape[-2:] == (4, 4) and model.device.type == "cpu" and self.compute.takes(cam, bulk_ok=False)
                and isinstance(target_pose, (torch.Tensor, np.ndarray)) and tuple(target_pose.shape) == (4, 4)):
            cls = _one_class(model, class_name)
        if cls is None:
            return super().pose_scores(model, cam, target_pose, class_name, chunk_size)
        feats = pose_features(self.compute, cam, target_pose, model.derived)
        layers, compiled = model.kernel_layers(cls)
        if compiled is not None and feats.shape[0] <= self.compute.mlp_max_rows:  # no per-layer dispatch
            return torch.from_numpy(kernels().mlp(feats.numpy().astype(np.float32), compiled))
        h = feats.to(layers[0][0].dtype)
        with torch.no_grad():
            for i, (w, b) in enumerate(layers):
                if i:
                    h.relu_()
                h = torch.addmm(b, h, w)
            return torch.sigmoid(h).squeeze(-1)

    def occlusion_scores(self, occ, pos):
        if not self.compute.takes(pos):
            return super().occlusion_scores(occ, pos)
        pack = occ.kernel_pack()
        if len(pack.c) == 0 or pack.pts_local.shape[0] == 0:
            return torch.zeros(pos.shape[0], dtype=pos.dtype)
        return torch.from_numpy(_rows(self.compute, kernels().occlusion, 1, as_f64(pos), pack)).to(pos.dtype)

    # ---- motion metric and local motions ------------------------------------------------------------------------
    def distance(self, motion, qa, qb):
        if self.compute.pair_takes(qa, qb):  # cheaper compiled at any size: a query ranks every node with it
            out = _rows(self.compute, kernels().distance, 2, as_f64(qa), as_f64(qb), float(motion.w_rot),
                        bool(motion.mobile))
            return torch.from_numpy(out).to(qa.dtype)
        return super().distance(motion, qa, qb)

    def interpolate(self, motion, qa, qb, s):
        cp = self.compute
        if cp.pair_takes(qa, qb) and s.shape == qa.shape[:1] and cp.takes(s.unsqueeze(-1)):
            out = _rows(cp, kernels().interpolate, 3, as_f64(qa), as_f64(qb), as_f64(s).reshape(-1),
                        float(motion.w_rot), bool(motion.mobile))
            return torch.from_numpy(out).to(qa.dtype)
        return super().interpolate(motion, qa, qb, s)

    def edge_knot_seeds(self, motion, qa, qb, n_interp):
        cp = self.compute
        if cp.pair_takes(qa, qb) and cp.fits(qa.shape[0] * (int(n_interp) + 4)):
            kn, ki = _rows(cp, kernels().edge_knot_seeds, 2, as_f64(qa), as_f64(qb), int(n_interp),
                           float(motion.w_rot), bool(motion.mobile))
            return torch.from_numpy(kn).to(qa.dtype), torch.from_numpy(ki)
        return super().edge_knot_seeds(motion, qa, qb, n_interp)

    def pieces(self, motion, a, b, resolution, max_steps, include_start):
        if self.compute.pair_takes(a, b):  # one compiled pass (same lengths, same points)
            seg, pts = self.pieces_arrays(motion, as_f64(a), as_f64(b), resolution, max_steps, include_start)
            return torch.from_numpy(seg), torch.from_numpy(pts).to(a.dtype)
        return super().pieces(motion, a, b, resolution, max_steps, include_start)

    def nearest(self, motion, qq, pool, k, pool_f64=None):
        if self.compute.pair_takes(qq, qq) and k > 0:  # one compiled pass that skips far nodes early
            rm = pool if pool_f64 is None else pool_f64()
            return torch.from_numpy(kernels().nearest(as_f64(qq), as_f64(rm), int(k), float(motion.w_rot),
                                                      bool(motion.mobile)))
        return super().nearest(motion, qq, pool, k)

    # ---- numpy batches --------------------------------------------------------------------------------------------
    def metric_arrays(self, motion, qa, qb):
        if len(qa) <= self.compute.motion_max_batch:
            d = kernels().distance(np.ascontiguousarray(qa, dtype=np.float64),
                                   np.ascontiguousarray(qb, dtype=np.float64), float(motion.w_rot), bool(motion.mobile))
            return d.astype(qa.dtype)
        return super().metric_arrays(motion, qa, qb)

    def interpolate_arrays(self, motion, qa, qb, s):
        if len(qa) <= self.compute.motion_max_batch:
            return kernels().interpolate(as_f64(qa), as_f64(qb), as_f64(s).reshape(-1), float(motion.w_rot),
                                         bool(motion.mobile)).astype(qa.dtype)
        return super().interpolate_arrays(motion, qa, qb, s)

    def pieces_arrays(self, motion, a, b, resolution, max_steps, include_start):
        return kernels().pieces(as_f64(a), as_f64(b), float(resolution), int(max_steps), bool(include_start),
                                float(motion.w_rot), bool(motion.mobile))

    def check_arrays(self, checker, Q):
        if len(Q) <= self.compute.max_batch:
            f = collision_flags(checker, Q, detailed=True)
            return {"limits": f[:, 0], "environment": f[:, 1], "self": f[:, 2]}
        return super().check_arrays(checker, Q)
