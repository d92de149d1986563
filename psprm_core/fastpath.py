"""Small-batch CPU fast paths: compiled (numba) kernels for the few-dozen-configuration batches of a query.

A PS-PRM query makes about ten batched calls (FK, the Gauss-Newton re-aiming of Alg. 1 line 7 at the knots of its
connection edges, the collision checks of Lazy PRM) on a few dozen to a few hundred configurations each. In torch each
such call costs 1-10 ms of per-operator overhead, far more than its arithmetic. The kernels of
:mod:`psprm_core._fast_numba` compute the same quantities row by row in float64:

* :func:`camera_poses` - :meth:`RobotModel.camera_poses`;
* :func:`project` - :meth:`VisibilityConstraint.project` (line and frustum models);
* :func:`check` - :meth:`CollisionChecker.check` / :meth:`~CollisionChecker.check_detailed`.

The callers use them only for CPU tensors of at most :data:`MAX_BATCH` rows outside autograd (:func:`applies`); large
batches (the roadmap build) and CUDA tensors keep the torch path. Nothing is compiled at import: numba compiles a
kernel on its first call (cached on disk with ``cache=True``). Without numba (:func:`available` false) every call takes
the torch path. :func:`disabled` turns the fast paths off in a block (tests compare both).
"""

from __future__ import annotations

import contextlib
import functools
import logging
from typing import Any, Iterator

import numpy as np
import torch

log = logging.getLogger(__name__)

MAX_BATCH = 1024  # rows up to which a CPU call uses the compiled kernels
_state = {"enabled": True}


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """Whether numba is importable (otherwise every call takes the torch path)."""
    try:
        import numba  # noqa: F401
    except Exception as exc:  # pragma: no cover - numba is a pinned requirement
        log.warning("numba unavailable (%s): small batches use the torch path", exc)
        return False
    return True


@functools.lru_cache(maxsize=1)
def kernels() -> Any:
    """The jitted kernels (:mod:`psprm_core._fast_numba`), imported on first use."""
    from . import _fast_numba

    return _fast_numba


@contextlib.contextmanager
def disabled() -> Iterator[None]:
    """Run a block with the fast paths off (the torch path everywhere)."""
    old = _state["enabled"]
    _state["enabled"] = False
    try:
        yield
    finally:
        _state["enabled"] = old


def applies(x: torch.Tensor, max_batch: int = MAX_BATCH) -> bool:
    """Whether a batch ``x`` (B, ...) takes the compiled path: a CPU tensor of 1..max_batch rows that needs no
    gradient, fast paths enabled, numba available."""
    return (_state["enabled"] and x.device.type == "cpu" and 0 < x.shape[0] <= max_batch
            and not (x.requires_grad and torch.is_grad_enabled()) and available())


def _f64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64))


def _i64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.int64))


# ---------------------------------------------------------------------------------------------- robot
def robot_arrays(robot) -> tuple:
    """The body tree of a :class:`~psprm_core.robot.RobotModel` as arrays (cached on the model): (all bodies in FK
    order, camera chain order, parent, joint type, R_off, t_off, axis, D, offset, mobile)."""
    arr = getattr(robot, "_fast_arrays", None)
    if arr is None:
        K = kernels()
        NB = len(robot.bodies)
        jtype = np.array([K.ROOT if j is None else (K.PRISMATIC if j.type == "prismatic" else K.REVOLUTE)
                          for j in robot.body_joint], dtype=np.int64)
        offs = np.stack(robot.body_joint_offset)
        axes = np.stack([j.axis if j is not None else np.zeros(3) for j in robot.body_joint])
        arr = (np.arange(1, NB, dtype=np.int64), _i64(robot.camera_chain[1:]), _i64(robot.parent_body), jtype,
               _f64(offs[:, :3, :3]), _f64(offs[:, :3, 3]), _f64(axes), _f64(robot.drive_matrix),
               _f64(robot.drive_offset), bool(robot.mobile))
        robot._fast_arrays = arr
    return arr


def _camera_args(robot) -> tuple:
    _, chain, parent, jtype, R_off, t_off, axis, D, off, mobile = robot_arrays(robot)
    return (chain, parent, jtype, R_off, t_off, axis, D, off, mobile, int(robot.camera_body),
            _f64(robot.camera_offset[:3, :3]), _f64(robot.camera_offset[:3, 3]))


def camera_poses(robot, q: torch.Tensor) -> torch.Tensor:
    """Camera optical-frame poses (B, 4, 4) of ``q`` (B, dof), as :meth:`RobotModel.camera_poses`."""
    out = kernels().camera_poses(_f64(q), *_camera_args(robot))
    return torch.from_numpy(out).to(q.dtype)


# ---------------------------------------------------------------------------------------------- projection
def project(constraint, q: torch.Tensor, settings, lo: torch.Tensor, hi: torch.Tensor, cols: np.ndarray) -> tuple:
    """:meth:`VisibilityConstraint.project` of ``q`` (B, dof) over the joints ``cols``: (projected q, converged)."""
    intr = constraint.intr
    target = _f64(constraint.target.to(q.dtype))
    qn, err = kernels().project(
        _f64(q), *_camera_args(constraint.robot), target, _i64(cols), constraint.kind == "line",
        float(constraint.min_distance), float(intr.far), float(intr.tan_half_h), float(intr.tan_half_v),
        float(constraint.margin), _f64(lo), _f64(hi), float(settings.tolerance), int(settings.max_iters),
        float(settings.damping), float(settings.max_step))
    return torch.from_numpy(qn).to(q.dtype), torch.from_numpy(err < settings.tolerance)


# ---------------------------------------------------------------------------------------------- collision
def _checker_arrays(checker) -> tuple:
    """Collision model and obstacle arrays of a :class:`~psprm_core.collision.CollisionChecker` (cached on it; the
    obstacle part is rebuilt when its box set is replaced)."""
    cache = getattr(checker, "_fast_arrays", None)
    if cache is None:
        cache = checker._fast_arrays = {
            "model": (_i64(checker.bodies_with_elements), _f64(checker.body_c), _f64(checker.body_r),
                      _f64(checker.body_box_c), _f64(checker.body_box_h), _i64(checker.body_el_start),
                      _i64(checker.body_el_count), _i64(checker.body_el_order), _i64(checker.el_body),
                      _f64(checker.el_c), _f64(checker.el_R), _f64(checker.el_h), _f64(checker.el_r),
                      _i64(checker.self_pairs).reshape(-1, 2)),
            "boxes": None, "boxes_of": None}
    bx = checker.boxes
    if cache["boxes_of"] is not bx:
        cache["boxes"] = (_f64(bx.center).reshape(-1, 3), _f64(bx.rotation).reshape(-1, 3, 3),
                          _f64(bx.half).reshape(-1, 3), _f64(bx.aabb()).reshape(-1, 6))
        cache["boxes_of"] = bx
    return cache["model"], cache["boxes"]


def check(checker, q: torch.Tensor, detailed: bool = False) -> np.ndarray:
    """Collision flags (B, 3) of ``q`` (B, dof): limits, environment, self (:meth:`CollisionChecker.check_detailed`).
    Without ``detailed`` a row stops at its first violation: only the OR over a row is meaningful."""
    all_bodies, _, parent, jtype, R_off, t_off, axis, D, off, mobile = robot_arrays(checker.robot)
    (bodies, body_c, body_r, box_c_b, box_h_b, el_start, el_count, el_order, el_body, el_c, el_R, el_h, el_r,
     pairs), (box_c, box_R, box_h, box_aabb) = _checker_arrays(checker)
    return kernels().check(_f64(q.to(checker.dtype)), bool(detailed), all_bodies, parent, jtype, R_off, t_off, axis,
                           D, off, mobile, _f64(checker.lower), _f64(checker.upper), bodies, body_c, body_r, box_c_b,
                           box_h_b, el_start, el_count, el_order, el_body, el_c, el_R, el_h, el_r, pairs, box_c,
                           box_R, box_h, box_aabb, 1e-6)
