"""The fused compiled calls of a query's edges: knots and re-aiming of a few edges in one call
(:func:`query_knots`), their lazy verification with the neural score (:func:`check_score_knots`,
:func:`verify_edges`, the knot store written in place) and the neural score of configurations
(:func:`neural_config_scores`), with the scorer's inputs (:func:`neural_args`). What every edge call computes with
(the motion, the robot, its collision checker and visibility constraint, the re-aiming solver's settings) is one
:class:`EdgeKit`, made by the planner's context (``PlannerContext.edge_kit``); per-call helpers and the small-batch
policy are :mod:`.fastpath`'s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

from ..geometry import EPS_DIR as _EPS_DIR
from ._fast_packs import EdgeOpts, OcclusionPack, ScorerPack
from .arrays import as_f64, as_i64, const_f64
from .fastpath import kernels, solver_pack


@dataclass(frozen=True)
class EdgeKit:
    """What the fused edge calls compute with: ``motion`` (:class:`~psprm_core.motion.DiffDriveMotion`), ``robot``,
    its ``checker`` (:class:`~psprm_core.collision.CollisionChecker`) and ``constraint``
    (:class:`~psprm_core.planning.constraints.VisibilityConstraint`); the re-aiming of the knots (Alg. 1, line 7)
    over the joints ``track_cols`` within ``lo`` / ``hi`` with the ``projection`` settings, at most ``track_iters``
    Gauss-Newton steps; ``n_interp`` interior knots per edge (Eq. 1's N) and the dense check's ``resolution``."""

    motion: Any
    robot: Any
    checker: Any
    constraint: Any
    projection: Any
    lo: torch.Tensor
    hi: torch.Tensor
    track_cols: np.ndarray
    track_iters: int
    n_interp: int
    resolution: float

    def solver(self) -> tuple:
        """The Gauss-Newton inputs (:func:`~.fastpath.solver_pack`)."""
        return solver_pack(self.projection, self.lo, self.hi, self.track_cols, self.track_iters)


class EdgeBatch(NamedTuple):
    """The edges a lazy search verifies (:func:`verify_edges`): their ids ``ids`` (E,) in the knot store, which of
    them get their knots computed (``new_knots`` (E,) bool, C of them) from the ends ``qa``, ``qb`` (C, dof) float64
    (reversed where ``flip`` (C,)), which are checked (``do_check`` (E,)) and which scored (``do_score`` (E,))."""

    ids: np.ndarray
    new_knots: np.ndarray
    qa: np.ndarray
    qb: np.ndarray
    flip: np.ndarray
    do_check: np.ndarray
    do_score: np.ndarray


def _edge_opts(motion, n_interp: int, track: bool, r32: bool, resolution: float = 0.0, max_steps: int = 0,
               mlp_rows: int = 1) -> tuple:
    """The options of the fused edge kernels (:class:`~psprm_core.kernels._fast_packs.EdgeOpts`), typed as the kernels
    were compiled for (the motion's :meth:`DiffDriveMotion.kernel_pack`, int, bool, bool, float, int, int)."""
    return EdgeOpts(motion.kernel_pack(), int(n_interp), bool(track), bool(r32), float(resolution), int(max_steps),
                    int(mlp_rows))


def query_knots(kit: EdgeKit, qa: torch.Tensor, qb: torch.Tensor, track: bool) -> tuple:
    """``PSPRM.edge_knots`` of a few edges (E, dof) in one compiled call: knots (E, M, dof) in the dtype of ``qa``
    and the Eq. 1 sample positions (E, N) (same values as :func:`edge_knot_seeds` followed by :func:`project` of
    the interior knots over ``kit.track_cols``, when ``track``)."""
    kn, ki = kernels().query_knots(as_f64(qa), as_f64(qb),
                                   _edge_opts(kit.motion, kit.n_interp, track and len(kit.track_cols),
                                              qa.dtype == torch.float32),
                                   kit.robot.kernel_pack, kit.constraint.kernel_pack(qa.dtype), kit.solver())
    return torch.from_numpy(kn).to(qa.dtype), torch.from_numpy(ki)


def neural_args(scorer, dtype: torch.dtype) -> tuple | None:
    """The inputs of the compiled neural scoring (:class:`~psprm_core.kernels._fast_packs.ScorerPack`) of a
    single-target neural scorer (``NeuralScorer``: ``model``, ``target_pose``, ``class_name``, ``occ``, ``tau``) for
    :func:`check_score_knots` of cameras in ``dtype``, or None when the compiled scoring does not apply (another
    scorer, a model off the CPU or not float32)."""
    model = getattr(scorer, "model", None)
    if getattr(scorer, "name", None) != "neural" or model is None or getattr(model, "device", None) is None or \
            model.device.type != "cpu" or not isinstance(getattr(scorer, "class_name", None), str):
        return None
    _, net = model.kernel_layers(int(model.class_index(scorer.class_name)))
    if net is None:
        return None
    tgt = const_f64(scorer.target_pose, dtype)  # the scorer casts the target pose to the cameras' dtype
    occ = scorer.occ.kernel_pack() if scorer.occ is not None else None
    has_occ = occ is not None and len(occ.c) > 0 and occ.pts_local.shape[0] > 0
    if not has_occ:  # a typed placeholder: the kernel skips the rays
        z3 = np.zeros((0, 3))
        occ = OcclusionPack(np.zeros((1, 0, 3)), z3, z3, z3, np.zeros((0, 3, 3)), z3,
                            bool(occ.count_inside) if occ is not None else False, float(_EPS_DIR))
    return ScorerPack(tgt, bool(model.derived), net, bool(has_occ), occ, float(getattr(scorer, "tau", 0.5)))


def check_score_knots(kit: EdgeKit, scorer_args: tuple, knots: torch.Tensor, interior: torch.Tensor,
                      do_check: np.ndarray, do_score: np.ndarray, max_steps: int) -> tuple:
    """The lazy verification of a few edges in one compiled call (``Verification.verify_edges``): collision-free flags
    (E,) of their knots (E, M, dof) and dense pieces (where ``do_check``, at most ``max_steps`` per edge), and for
    the free ones (where ``do_score``) the camera poses (E, N + 2, 4, 4) of their Eq. 1 points and the raw scores
    (E, N + 2) of the neural scorer (``scorer_args`` from :func:`neural_args`; the MLP in chunks of whole edges
    within ``mlp_max_rows`` views of the motion's Compute). Free flags are True for rows not checked."""
    n = interior.shape[1]
    free, cams, raw = kernels().check_score_knots(
        as_f64(knots), as_i64(interior),
        (np.ascontiguousarray(do_check, dtype=np.bool_), np.ascontiguousarray(do_score, dtype=np.bool_)),
        _edge_opts(kit.motion, n, False, knots.dtype == torch.float32, kit.resolution, max_steps,
                   _mlp_rows(n + 2, kit.motion.compute.mlp_max_rows)),
        kit.robot.kernel_pack, kit.checker.kernel_pack(), scorer_args)
    return free, torch.from_numpy(cams).to(knots.dtype), torch.from_numpy(raw)


def _mlp_rows(n_eq1: int, max_rows: int) -> int:
    """Views per compiled MLP call when scoring edges: whole edges of ``n_eq1`` Eq. 1 points, within ``max_rows``
    (the rows the compiled scorer takes per call, :attr:`Compute.mlp_max_rows`)."""
    return max(1, max_rows // n_eq1) * n_eq1


def neural_config_scores(robot, scorer_args: tuple, q: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """Raw neural scores (B,) of configurations q (B, dof), in one compiled call
    (``scorer.score(robot.camera_poses(q))`` of a single-target neural scorer, ``scorer_args`` from
    :func:`neural_args`), in the dtype of ``q`` (a tensor, or a numpy array for numpy input); at most the robot's
    ``compute.mlp_max_rows`` rows (the compiled MLP's, as the step-by-step path)."""
    is_np = isinstance(q, np.ndarray)
    f32 = q.dtype == np.float32 if is_np else q.dtype == torch.float32
    _, sc = kernels().neural_scores(as_f64(q), bool(f32), robot.compute.mlp_max_rows, robot.kernel_pack, scorer_args)
    return sc.astype(q.dtype, copy=False) if is_np else torch.from_numpy(sc).to(q.dtype)


def verify_edges(kit: EdgeKit, scorer_args: tuple, store_k: np.ndarray, store_i: np.ndarray, batch: EdgeBatch,
                 max_steps: int) -> tuple:
    """A lazy search's verification of the edges of ``batch`` in one compiled call (``Verification.verify_edges``):
    the knots of its ``new_knots`` ones from their ends (tracked over ``kit.track_cols``), written into the knot
    store's arrays ``store_k`` (cap, M, dof) / ``store_i`` (cap, N) (numpy views of its tensors; reversed where
    ``flip``), then :func:`check_score_knots` of all of them from the store. Returns numpy arrays (free (E,),
    cameras (E, N + 2, 4, 4) in the store's dtype, raw scores (E, N + 2) float32)."""
    f32 = store_k.dtype == np.float32
    free, cams, raw = kernels().verify_edges(
        (store_k, store_i), batch.ids, (batch.new_knots, batch.qa, batch.qb, batch.flip),
        (batch.do_check, batch.do_score),
        _edge_opts(kit.motion, kit.n_interp, len(kit.track_cols) > 0, f32, kit.resolution, max_steps,
                   _mlp_rows(kit.n_interp + 2, kit.motion.compute.mlp_max_rows)),
        kit.robot.kernel_pack, kit.checker.kernel_pack(), kit.constraint.kernel_pack(torch.float32 if f32 else
                                                                                      torch.float64),
        kit.solver(), scorer_args)
    return free, cams.astype(store_k.dtype, copy=False), raw
