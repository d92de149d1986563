"""Numba kernels behind :mod:`psprm_core.kernels.fastpath` (imported only through its
:func:`~psprm_core.kernels.fastpath.kernels`).

Small-batch CPU versions of the batched torch code a query runs (a few dozen to a few hundred configurations per
call, where torch's per-operator overhead dominates): forward kinematics of the body tree, camera poses, the damped
Gauss-Newton projection onto the visibility manifold, and the oriented-box collision check. They follow the torch
implementations step by step (same formulas, same order of tests) in float64; the callers cast the results back to
the torch dtype. Compiled on the first call of each kernel and cached on disk (``cache=True``).

The kernels live in modules by domain and are re-exported here: :mod:`~psprm_core.kernels._fast_kinematics` (FK, camera
poses, collision checks; the ``jit`` decorator and the joint type codes), :mod:`~psprm_core.kernels._fast_projection`
(projection onto the visibility manifold), :mod:`~psprm_core.kernels._fast_motion` (the motion metric, local motions,
pieces, nearest nodes, edge knots), :mod:`~psprm_core.kernels._fast_scoring` (occlusion, pose features, the surrogate
MLP),
:mod:`~psprm_core.kernels._fast_query` (the fused kernels of a query's edges) and
:mod:`~psprm_core.kernels._fast_tracking` (the corners of the robot's collision boxes, for the path tolerance).
The kernels take their inputs grouped in
the named tuples of :mod:`~psprm_core.kernels._fast_packs` (one per object: robot, collision checker, visibility
constraint, surrogate, occlusion checker, motion), each built by the object's class. numba's disk cache checks only the
source file of the kernel it loads, so a module that imports from the others records their SHA-256 (``CALLEES_SHA256``,
checked by ``tests/test_fastpath.py``): a change to a called kernel changes the caller's file too.
"""

from ._fast_kinematics import (PRISMATIC, REVOLUTE, ROOT, _camera, _centre, _env_hit, _fk, _obb_overlap,
                               _point_box_sqdist, _self_hit, _world_box, camera_poses, check, env_hits, jit)
from ._fast_motion import _base_plan, _distance, _wrap, distance, edge_knot_seeds, interpolate, nearest, pieces
from ._fast_projection import _residual, _solve, project
from ._fast_query import _round32, check_score_knots, neural_scores, query_knots, verify_edges
from ._fast_scoring import _slab, mlp, occlusion, pose_features
from ._fast_tracking import element_corners

__all__ = ["ROOT", "REVOLUTE", "PRISMATIC", "jit", "camera_poses", "project", "check", "env_hits", "occlusion",
           "distance", "interpolate", "pieces", "nearest", "edge_knot_seeds", "pose_features", "mlp", "query_knots",
           "neural_scores", "check_score_knots", "verify_edges", "element_corners"]
