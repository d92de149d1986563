"""The fused compiled calls of a query's edges: knots and re-aiming of a few edges in one call
(:func:`query_knots`), their lazy verification with the neural score (:func:`check_score_knots`,
:func:`verify_edges`, the knot store written in place) and the neural score of configurations
(:func:`neural_config_scores`), with the scorer's inputs (:func:`neural_args`). Per-call helpers and the small-batch
policy are :mod:`.fastpath`'s."""

from __future__ import annotations

import numpy as np
import torch

from .fastpath import as_f64, as_i64, const_f64, kernels, solver_pack


def _edge_opts(motion, n_interp: int, track: bool, r32: bool, resolution: float = 0.0, max_steps: int = 0,
               mlp_rows: int = 1) -> tuple:
    """The options of the fused edge kernels (:class:`~psprm_core.kernels._fast_packs.EdgeOpts`), typed as the kernels
    were compiled for (the motion's :meth:`DiffDriveMotion.kernel_pack`, int, bool, bool, float, int, int)."""
    from ._fast_packs import EdgeOpts

    return EdgeOpts(motion.kernel_pack(), int(n_interp), bool(track), bool(r32), float(resolution), int(max_steps),
                    int(mlp_rows))


def query_knots(motion, constraint, qa: torch.Tensor, qb: torch.Tensor, n_interp: int, track: bool, settings,
                lo: torch.Tensor, hi: torch.Tensor, cols: np.ndarray, max_iters: int) -> tuple:
    """``PSPRM.edge_knots`` of a few edges (E, dof) in one compiled call: knots (E, M, dof) in the dtype of ``qa``
    and the Eq. 1 sample positions (E, N) (same values as :func:`edge_knot_seeds` followed by :func:`project` of
    the interior knots over ``cols``)."""
    kn, ki = kernels().query_knots(as_f64(qa), as_f64(qb),
                                   _edge_opts(motion, n_interp, track and len(cols), qa.dtype == torch.float32),
                                   constraint.robot.kernel_pack, constraint.kernel_pack(qa.dtype),
                                   solver_pack(settings, lo, hi, cols, max_iters))
    return torch.from_numpy(kn).to(qa.dtype), torch.from_numpy(ki)


def neural_args(scorer, dtype: torch.dtype) -> tuple | None:
    """The inputs of the compiled neural scoring (:class:`~psprm_core.kernels._fast_packs.ScorerPack`) of a
    single-target neural scorer (``NeuralScorer``: ``model``, ``target_pose``, ``class_name``, ``occ``, ``tau``) for
    :func:`check_score_knots` of cameras in ``dtype``, or None when the compiled scoring does not apply (another
    scorer, a model off the CPU or not float32)."""
    from ..geometry import EPS_DIR as _EPS_DIR
    from ._fast_packs import OcclusionPack, ScorerPack

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


def check_score_knots(motion, checker, robot, scorer_args: tuple, knots: torch.Tensor, interior: torch.Tensor,
                      do_check: np.ndarray, do_score: np.ndarray, resolution: float, max_steps: int) -> tuple:
    """The lazy verification of a few edges in one compiled call (``Verification.verify_edges``): collision-free flags
    (E,) of their knots (E, M, dof) and dense pieces (where ``do_check``), and for the free ones (where
    ``do_score``) the camera poses (E, N + 2, 4, 4) of their Eq. 1 points and the raw scores (E, N + 2) of the
    neural scorer (``scorer_args`` from :func:`neural_args`; the MLP in chunks of whole edges within
    ``mlp_max_rows`` views of the motion's Compute). Free flags are True for rows not checked."""
    n = interior.shape[1]
    free, cams, raw = kernels().check_score_knots(
        as_f64(knots), as_i64(interior),
        (np.ascontiguousarray(do_check, dtype=np.bool_), np.ascontiguousarray(do_score, dtype=np.bool_)),
        _edge_opts(motion, n, False, knots.dtype == torch.float32, resolution, max_steps,
                   _mlp_rows(n + 2, motion.compute.mlp_max_rows)),
        robot.kernel_pack, checker.kernel_pack(), scorer_args)
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


def verify_edges(motion, constraint, checker, scorer_args: tuple, store_k: np.ndarray, store_i: np.ndarray,
                 ids: np.ndarray, compute: np.ndarray, qa: np.ndarray, qb: np.ndarray, flip: np.ndarray,
                 n_interp: int, track: bool, settings, lo: torch.Tensor, hi: torch.Tensor, cols: np.ndarray,
                 max_iters: int, do_check: np.ndarray, do_score: np.ndarray, resolution: float,
                 max_steps: int) -> tuple:
    """A lazy search's verification of edges ``ids`` in one compiled call (``Verification.verify_edges``): the knots of
    the ``compute`` ones from their ends ``qa``, ``qb`` (C, dof) float64 of the planner's values, written into the
    knot store's arrays ``store_k`` (cap, M, dof) / ``store_i`` (cap, N) (numpy views of its tensors; reversed where
    ``flip``), then :func:`check_score_knots` of all of them from the store. Returns numpy arrays (free (E,),
    cameras (E, N + 2, 4, 4) in the store's dtype, raw scores (E, N + 2) float32)."""
    dtype = torch.float32 if store_k.dtype == np.float32 else torch.float64
    free, cams, raw = kernels().verify_edges(
        (store_k, store_i), ids, (compute, qa, qb, flip), (do_check, do_score),
        _edge_opts(motion, n_interp, track and len(cols), dtype == torch.float32, resolution, max_steps,
                   _mlp_rows(n_interp + 2, motion.compute.mlp_max_rows)),
        checker.robot.kernel_pack, checker.kernel_pack(), constraint.kernel_pack(dtype),
        solver_pack(settings, lo, hi, cols, max_iters), scorer_args)
    return free, cams.astype(store_k.dtype, copy=False), raw
