"""Small-batch CPU fast paths: compiled (numba) kernels for the few-dozen-configuration batches of a query.

A PS-PRM query makes about ten batched calls (FK, the Gauss-Newton re-aiming of Alg. 1 line 7 at the knots of its
connection edges, the collision checks of Lazy PRM) on a few dozen to a few hundred configurations each. In torch each
such call costs 1-10 ms of per-operator overhead, far more than its arithmetic. The kernels of
:mod:`psprm_core.kernels._fast_numba` compute the same quantities row by row in float64:

* :func:`camera_poses` - :meth:`RobotModel.camera_poses`;
* :func:`project` - :meth:`VisibilityConstraint.project` (Alg. 1, line 7; line and frustum models);
* :func:`check` - :meth:`CollisionChecker.check` / :meth:`~CollisionChecker.check_detailed`;
* :func:`occlusion_scores`, :func:`pose_features`, :func:`surrogate_scores` - the neural score of Alg. 2
  (:class:`OcclusionChecker`, :meth:`PerceptionSurrogate.predict`);
* :func:`motion_distance`, :func:`motion_interpolate`, :func:`pieces`, :func:`nearest`, :func:`edge_knot_seeds` - the
  diff-drive metric and local motions (:class:`DiffDriveMotion`, ``Edges.pieces``, the query's nearest roadmap
  nodes, the knots of Eq. 1 edges).

The kernels take their inputs grouped in the named tuples of :mod:`psprm_core.kernels._fast_packs`, one per object, each
built (and kept) by that object's class: ``RobotModel.kernel_pack``, ``CollisionChecker.kernel_pack``,
``VisibilityConstraint.kernel_pack``, ``PerceptionSurrogate.kernel_layers``, ``OcclusionChecker.kernel_pack``,
``DiffDriveMotion.kernel_pack``; the functions here add the per-call ones (:func:`solver_pack`), and :mod:`.edges`
the options of the fused calls of a query's edges.

The domain methods name their twin with the :func:`twin` decorator, the one place a call is routed; the methods
themselves hold only the torch code. Whether a call goes to its twin is decided by the object's
:class:`~psprm_core.kernels.compute.Compute` (``obj.compute``), a value the object was built with: compiled kernels
chosen, a CPU tensor outside autograd, at most ``max_batch`` rows (the metric up to ``motion_max_batch``), or any
size inside :func:`~psprm_core.kernels.compute.bulk`, which the planner's large-batch methods enter (build,
re-scoring, invalidation near moved obstacles, repair growth): their rows are split into chunks run on a small thread
pool (the kernels release the GIL). At that size the kernels are 3-8x faster than torch's batched operators on 2
cores (collision checks, projection, knot tracking, ray casting), mostly because torch materialises (rows x spheres x
boxes) intermediates where a kernel stops a row at its first hit; camera FK alone is about as fast in torch, and the
surrogate's GEMMs stay in torch. CUDA tensors keep the torch path. Nothing is compiled at import: numba compiles a
kernel on its first call (cached on disk with ``cache=True``); ``PSPRM.warm_up`` loads them before the build.
Without numba (:func:`available` false) ``Compute.make`` chooses torch. An object built with a torch-only
``Compute`` (``obj.using(compute.torch_only())``) runs the torch code at every size (tests compare both). Queries
run with torch's intra-op parallelism off (:meth:`Compute.one_thread`).
"""

from __future__ import annotations

import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np
import torch

from .compute import Compute, bulk_workers, numba_importable

log = logging.getLogger(__name__)


@functools.lru_cache(maxsize=1)
def kernels() -> Any:
    """The jitted kernels (:mod:`psprm_core.kernels._fast_numba`), imported on first use."""
    from . import _fast_numba

    return _fast_numba


def available() -> bool:
    """Whether the compiled kernels can run here (numba importable); a :class:`Compute` chooses them per object."""
    return numba_importable()


def twin(compiled: Callable, when: Callable | None = None) -> Callable:
    """Decorator of a domain method (robot FK, the projection, collision checks, ray casting, the motion metric): the
    one seam where a call goes to its compiled twin. The decorated body is the torch implementation (any device,
    any batch); ``compiled(obj, *args, **kw)`` runs instead when ``when(obj, *args, **kw)`` holds, by default when
    the object's ``compute`` takes the first argument (:meth:`Compute.takes`). ``method.torch`` is the torch body alone and
    ``method.compiled`` the twin (the equivalence tests call both)."""

    def decorate(method: Callable) -> Callable:
        test = when if when is not None else (lambda obj, x, *a, **k: obj.compute.takes(x))

        @functools.wraps(method)
        def dispatch(obj, *args, **kw):
            if test(obj, *args, **kw):
                return compiled(obj, *args, **kw)
            return method(obj, *args, **kw)

        dispatch.torch, dispatch.compiled = method, compiled
        return dispatch

    return decorate


def on_cpu_applies(obj, x: torch.Tensor, *args, **kw) -> bool:
    """:meth:`Compute.takes` for the methods of an object that keeps its tensors on ``obj.device``: only a CPU one."""
    return obj.device.type == "cpu" and obj.compute.takes(x)


@functools.lru_cache(maxsize=4)
def pool(workers: int) -> ThreadPoolExecutor:
    """The worker threads of bulk calls (:func:`~psprm_core.kernels.compute.bulk`; created on first use, one pool
    per worker count)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="psprm-fastpath")


def _rows(compute: Compute, kernel, n_row_args: int, *args):
    """``kernel(*args)``, whose first ``n_row_args`` arguments are per-row arrays and whose results are per-row
    arrays (or a tuple of them): inside a bulk block, split into chunks of at least ``compute.bulk_chunk`` rows run
    on the worker threads."""
    n, w, chunk = args[0].shape[0], bulk_workers(), compute.bulk_chunk
    if w < 2 or n < 2 * chunk:
        return kernel(*args)
    step = max(chunk, -(-n // (4 * w)))
    rest = args[n_row_args:]
    parts = list(pool(w).map(lambda i: kernel(*(a[i:i + step] for a in args[:n_row_args]), *rest),
                              range(0, n, step)))
    if isinstance(parts[0], tuple):
        return tuple(np.concatenate(p) for p in zip(*parts))
    return np.concatenate(parts)


def as_f64(x) -> np.ndarray:
    """A C-contiguous float64 array of ``x`` (a tensor, detached and on the CPU, or array-like): a kernel input."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64))


def const_f64(t: torch.Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    """float64 copy of a constant tensor (limits, target point), first rounded to ``dtype`` if given (as the torch
    path casts it); kept on the tensor until it changes in place."""
    cache = getattr(t, "_fast_f64", None)
    if cache is None:
        cache = t._fast_f64 = {}
    got = cache.get(dtype)
    key = (t._version, t.data_ptr())  # in-place changes; a copied tensor (and its copied attributes) has new storage
    if got is None or got[0] != key:
        got = cache[dtype] = (key, as_f64(t if dtype is None else t.to(dtype)))
    return got[1]


def as_i64(x) -> np.ndarray:
    """A C-contiguous int64 array of ``x`` (a tensor, detached and on the CPU, or array-like): a kernel input."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.int64))


# ---------------------------------------------------------------------------------------------- robot
def camera_applies(robot, q: torch.Tensor, body_poses=None) -> bool:
    """When :meth:`RobotModel.camera_poses` runs compiled: configurations (B, dof) given (no body poses), a batch
    :func:`applies` to."""
    return body_poses is None and q.dim() == 2 and q.shape[1] == robot.dof and robot.compute.takes(q)


def camera_poses(robot, q: torch.Tensor, body_poses=None) -> torch.Tensor:
    """Camera optical-frame poses (B, 4, 4) of ``q`` (B, dof), as :meth:`RobotModel.camera_poses`."""
    out = _rows(robot.compute, kernels().camera_poses, 1, as_f64(q), robot.kernel_pack)
    return torch.from_numpy(out).to(q.dtype)


# ---------------------------------------------------------------------------------------------- projection
def project_applies(constraint, q: torch.Tensor, *args) -> bool:
    """When the Gauss-Newton iteration of :meth:`VisibilityConstraint.project` runs compiled: the robot model's own
    kinematics (not e.g. pytorch-kinematics), a batch :func:`applies` to."""
    return constraint.kin is constraint.robot and constraint.compute.takes(q)


def project(constraint, q: torch.Tensor, settings, lo: torch.Tensor, hi: torch.Tensor,
            cols: torch.Tensor | np.ndarray) -> tuple:
    """:meth:`VisibilityConstraint.project` of ``q`` (B, dof) over the joints ``cols``: (projected q, converged)."""
    cols = cols.cpu().numpy() if isinstance(cols, torch.Tensor) else np.asarray(cols)
    qn, err = _rows(constraint.compute, kernels().project, 1, as_f64(q), constraint.robot.kernel_pack, constraint.kernel_pack(q.dtype),
                    solver_pack(settings, lo, hi, cols, settings.max_iters))
    return torch.from_numpy(qn).to(q.dtype), torch.from_numpy(err < settings.tolerance)


def solver_pack(settings, lo: torch.Tensor, hi: torch.Tensor, cols: np.ndarray, max_iters: int) -> tuple:
    """The Gauss-Newton iteration's inputs (:class:`~psprm_core.kernels._fast_packs.SolverPack`): the joints ``cols``,
    the bounds, the tolerance, damping and step cap of ``settings`` (:class:`ProjectionSettings`) and ``max_iters``."""
    from ._fast_packs import SolverPack

    return SolverPack(as_i64(cols), const_f64(lo), const_f64(hi), float(settings.tolerance), int(max_iters),
                      float(settings.damping), float(settings.max_step))


# ---------------------------------------------------------------------------------------------- collision
def check_flags(checker, q: torch.Tensor) -> torch.Tensor:
    """:meth:`CollisionChecker.check`: in-collision flags (B,)."""
    return torch.from_numpy(check(checker, q).any(-1))


def check_detailed(checker, q: torch.Tensor) -> dict:
    """:meth:`CollisionChecker.check_detailed`: ``limits``, ``environment``, ``self`` flags (each (B,))."""
    f = torch.from_numpy(check(checker, q, detailed=True))
    return {"limits": f[:, 0], "environment": f[:, 1], "self": f[:, 2]}


def env_hit_flags(checker, q: torch.Tensor, boxes, return_aabb: bool = False):
    """``CollisionChecker._env_hits``: flags (B,) against ``boxes`` (:class:`BoxTensors`) and, with ``return_aabb``,
    the robot's world bounds (B, 6)."""
    hit, aabb = env_hits(checker, q, boxes, return_aabb)
    hit = torch.from_numpy(hit)
    return (hit, torch.from_numpy(aabb).to(checker.dtype)) if return_aabb else hit


def robot_aabb(checker, q: torch.Tensor) -> torch.Tensor:
    """:meth:`CollisionChecker.robot_aabb`: the robot's world bounds (B, 6)."""
    return env_hit_flags(checker, q, None, True)[1]


def check(checker, q: torch.Tensor | np.ndarray, detailed: bool = False) -> np.ndarray:
    """Collision flags (B, 3) of ``q`` (B, dof, a tensor or a numpy array): limits, environment, self
    (:meth:`CollisionChecker.check_detailed`). Without ``detailed`` a row stops at its first violation: only the OR
    over a row is meaningful."""
    if isinstance(q, np.ndarray):
        q64 = as_f64(q.astype(np.float32) if checker.dtype == torch.float32 else q)  # rounded as the checker's dtype
    else:
        q64 = as_f64(q.to(checker.dtype))
    return _rows(checker.compute, kernels().check, 1, q64, bool(detailed), checker.robot.kernel_pack, checker.kernel_pack())


def env_hits(checker, q: torch.Tensor, boxes, want_aabb: bool) -> tuple:
    """:meth:`CollisionChecker.env_hits` of ``q`` (B, dof) against ``boxes`` (:class:`BoxTensors`, or None: no box)
    only: flags (B,)
    and, with ``want_aabb``, the robot's world bounds (B, 6) (else an empty array)."""
    from ._fast_packs import BoxPack

    if boxes is None:  # no boxes: the bounds only
        box = BoxPack(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6)))
    else:
        box = boxes.kernel_pack()
    return _rows(checker.compute, kernels().env_hits, 1, as_f64(q.to(checker.dtype)), bool(want_aabb), checker.robot.kernel_pack,
                 checker.kernel_pack()._replace(boxes=box))


# ---------------------------------------------------------------------------------------------- perception
def occlusion_scores(occ, pos: torch.Tensor) -> torch.Tensor:
    """Occlusion scores (B,) of camera positions (B, 3), as :meth:`OcclusionChecker.score` (Alg. 2, line 5)."""
    pack = occ.kernel_pack()
    if len(pack.c) == 0 or pack.pts_local.shape[0] == 0:
        return torch.zeros(pos.shape[0], dtype=pos.dtype)
    out = _rows(occ.compute, kernels().occlusion, 1, as_f64(pos), pack)
    return torch.from_numpy(out).to(pos.dtype)


def surrogate_scores(model, feats: torch.Tensor, cls: int) -> torch.Tensor:
    """Surrogate scores (B,) of un-normalised pose features (B, F) for one class index, as
    :meth:`PerceptionSurrogate.predict_features` (Alg. 2, line 4: c_p = NN(T_c, O)): ReLU hidden layers, sigmoid
    output, with the folded layers kept between calls. Up to :data:`MLP_MAX_ROWS` rows a compiled float32 kernel
    (a query scores 2-14 views per call: 35-550 us, and no thread-pool hand-off that stalls on a busy machine),
    above that torch's GEMM (numpy's is 5x slower at this shape)."""
    layers, compiled = model.kernel_layers(cls)
    if compiled is not None and feats.shape[0] <= model.compute.mlp_max_rows:  # single-threaded, no per-layer dispatch
        return torch.from_numpy(kernels().mlp(feats.numpy().astype(np.float32), compiled))
    h = feats.to(layers[0][0].dtype)
    with torch.no_grad():
        for i, (w, b) in enumerate(layers):
            if i:
                h.relu_()
            h = torch.addmm(b, h, w)
        return torch.sigmoid(h).squeeze(-1)


def surrogate_applies(model, cam: torch.Tensor, target_pose, class_name, chunk_size=None) -> bool:
    """When :meth:`PerceptionSurrogate.predict` runs compiled: camera poses (B, 4, 4) of one target pose (4, 4) and
    one class, a model on the CPU, at most :data:`MAX_BATCH` rows (torch's GEMMs are faster beyond, even in bulk)."""
    if not (cam.shape[-2:] == (4, 4) and model.device.type == "cpu" and model.compute.takes(cam, bulk_ok=False)
            and isinstance(target_pose, (torch.Tensor, np.ndarray)) and tuple(target_pose.shape) == (4, 4)):
        return False
    return _one_class(model, class_name) is not None


def surrogate_pose_scores(model, cam: torch.Tensor, target_pose, class_name, chunk_size=None) -> torch.Tensor:
    """:meth:`PerceptionSurrogate.predict` of camera poses (B, 4, 4), one target pose and one class: numpy features
    and the compiled MLP."""
    feats = pose_features(model.compute, cam, target_pose, model.derived)
    return surrogate_scores(model, feats, _one_class(model, class_name))


def _one_class(model, class_name) -> int | None:
    """The class index of a single class (a name, an index or a 0-d index tensor;
    :meth:`PerceptionSurrogate.class_index` checks names and indices), None for per-row classes."""
    if isinstance(class_name, torch.Tensor):
        return int(class_name) if class_name.dim() == 0 else None
    if isinstance(class_name, (str, int, np.integer)):
        return int(model.class_index(class_name))
    return None


def pose_features(compute: Compute, cam: torch.Tensor, target_pose, derived: bool) -> torch.Tensor:
    """The surrogate's pose features (B, 9 or 14) of camera poses (B, 4, 4) and one target pose (4, 4)
    (:func:`~psprm_core.perception.surrogate.relative_pose_features` and ``derived_features``), compiled."""
    return torch.from_numpy(_rows(compute, kernels().pose_features, 1, as_f64(cam), as_f64(target_pose), bool(derived)))


# ---------------------------------------------------------------------------------------------- motion
def distance_applies(motion, qa: torch.Tensor, qb: torch.Tensor) -> bool:
    """When :meth:`DiffDriveMotion.distance` runs compiled: a pair of same-shape batches (:meth:`Compute.pair_takes`;
    the metric is cheaper compiled at any size, a query ranks every roadmap node with it)."""
    return motion.compute.pair_takes(qa, qb)


def interpolate_applies(motion, qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> bool:
    """When :meth:`DiffDriveMotion.interpolate` runs compiled: one fraction per pair (:meth:`Compute.pair_takes`)."""
    return motion.compute.pair_takes(qa, qb) and s.shape == qa.shape[:1] and motion.compute.takes(s.unsqueeze(-1))


def motion_distance(motion, qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
    """:meth:`DiffDriveMotion.distance` of same-shape CPU batches."""
    out = _rows(motion.compute, kernels().distance, 2, as_f64(qa), as_f64(qb), float(motion.w_rot), bool(motion.mobile))
    return torch.from_numpy(out).to(qa.dtype)


def motion_interpolate(motion, qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """:meth:`DiffDriveMotion.interpolate` of same-shape CPU batches."""
    out = _rows(motion.compute, kernels().interpolate, 3, as_f64(qa), as_f64(qb), as_f64(s).reshape(-1), float(motion.w_rot),
                bool(motion.mobile))
    return torch.from_numpy(out).to(qa.dtype)


def pieces(motion, a: torch.Tensor, b: torch.Tensor, resolution: float, max_steps: int,
           include_start: bool) -> tuple:
    """``Edges.pieces``: (piece index, points every ``resolution`` on the pieces a[i] -> b[i])."""
    seg, pts = kernels().pieces(as_f64(a), as_f64(b), float(resolution), int(max_steps), bool(include_start),
                                float(motion.w_rot), bool(motion.mobile))
    return torch.from_numpy(seg), torch.from_numpy(pts).to(a.dtype)


def nearest(motion, qq: torch.Tensor, rm: torch.Tensor | np.ndarray, k: int) -> torch.Tensor:
    """Indices (Q, k) of the k configurations of ``rm`` (N, dof) nearest to each of ``qq`` (Q, dof) under the
    motion metric, sorted by distance (``motion.distance`` of every pair, then ``topk``). ``rm`` may be a
    contiguous float64 array (no conversion per call)."""
    out = kernels().nearest(as_f64(qq), as_f64(rm), int(k), float(motion.w_rot), bool(motion.mobile))
    return torch.from_numpy(out)


def edge_knot_seeds(motion, qa: torch.Tensor, qb: torch.Tensor, n_interp: int) -> tuple:
    """Knots (E, M, dof) of the local motions qa -> qb before the camera joints re-aim, and the positions (E, N) of
    the Eq. 1 samples among them (the first half of ``PSPRM.edge_knots``)."""
    kn, ki = _rows(motion.compute, kernels().edge_knot_seeds, 2, as_f64(qa), as_f64(qb), int(n_interp), float(motion.w_rot),
                   bool(motion.mobile))
    return torch.from_numpy(kn).to(qa.dtype), torch.from_numpy(ki)
