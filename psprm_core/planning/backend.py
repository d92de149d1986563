"""Where the planner's batched stage operations run: one object per planner, chosen from its
:class:`~psprm_core.kernels.compute.Compute`.

Both backends call the verbs of the ``Compute``'s kernels implementation (``ctx.compute.ops``,
:mod:`psprm_core.kernels.ops`) for the knots, pieces and nearest nodes of local motions, the metric and the checks of
numpy batches; they differ in the fused calls of a query:

- :class:`TorchBackend`: none (a GPU, a CPU without numba, or a ``Compute`` with ``kernels="torch"``);
- :class:`CompiledBackend` (``kernels="numba"``): a query's few edges knotted, checked and scored in one compiled call
  each (:mod:`psprm_core.kernels.edges`). The kernels give the torch results (``tests/test_fastpath.py``).

The stages call these verbs and never test the device themselves.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import numpy as np
import torch

from ..kernels import edges


def backend_for(ctx) -> "TorchBackend":
    """The backend of a planner's :class:`~.state.PlannerContext`: compiled when its ``Compute`` chose the numba
    kernels, else torch."""
    if ctx.compute.compiled:
        return CompiledBackend(ctx)
    return TorchBackend(ctx)


class TorchBackend:
    """The planner's stage operations through its ``Compute``'s kernels (``ctx.compute.ops``), without fused calls:
    what a GPU, a CPU without numba or a torch-only ``Compute`` runs."""

    compiled = False  # whether compiled kernels serve this planner (their warm-up is then worth doing)

    def __init__(self, ctx):
        self.ctx = ctx

    @property
    def fused(self) -> bool:
        """Whether the fused verification kernel of a lazy search serves this planner now."""
        return False

    # ---- knots of local motions ----------------------------------------------------------------------------------
    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool) -> tuple:
        """(knots (E, M, dof), Eq. 1 positions (E, N)) of the local motions qa -> qb (:meth:`.edges.Edges.edge_knots`):
        the ends, the drive corners and the N samples sorted along the motion, re-aimed with ``track``."""
        c = self.ctx
        knots, interior_idx = c.compute.ops.edge_knot_seeds(c.motion, qa, qb, c.settings.edges.n_interp)
        return (self.track_knots(knots) if track else knots), interior_idx

    def track_knots(self, knots: torch.Tensor) -> torch.Tensor:
        """Knots with the non-base camera joints of the interior ones re-projected onto the visibility manifold
        (``track_iters`` Gauss-Newton steps of Alg. 1, line 7)."""
        c = self.ctx
        E, M, dof = knots.shape
        if len(c.track_cols) and M > 2:
            inner = knots[:, 1:-1].reshape(-1, dof)
            ps = dataclasses.replace(c.settings.projection, max_iters=c.settings.edges.track_iters)
            proj, _ = c.constraint.project(inner, ps, c.lo, c.hi, joints=c.track_cols)
            knots = torch.cat([knots[:, :1], proj.reshape(E, M - 2, -1), knots[:, -1:]], 1)
        return knots

    # ---- the motion metric -------------------------------------------------------------------------------------
    def motion_distance(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """The motion metric of numpy batches (E, dof) in the planner's dtype, same dtype out."""
        return self.ctx.compute.ops.metric_arrays(self.ctx.motion, qa, qb)

    def pieces(self, a: torch.Tensor, b: torch.Tensor, max_steps: int, include_start: bool) -> tuple:
        """(piece index, points) every ``edge_resolution`` on the straight pieces a[i] -> b[i]
        (:meth:`.edges.Edges.pieces`)."""
        c = self.ctx
        return c.compute.ops.pieces(c.motion, a, b, c.settings.edges.edge_resolution, max_steps, include_start)

    def dense_path(self, W: np.ndarray) -> tuple:
        """(configurations every ``edge_resolution`` along the knot path ``W`` (K, dof) float64, its length)."""
        if len(W) < 2:
            return W, 0.0
        c = self.ctx
        ops, a, b = c.compute.ops, W[:-1], W[1:]
        _, pts = ops.pieces_arrays(c.motion, a, b, c.settings.edges.edge_resolution, 1000, True)
        return np.concatenate([pts, W[-1:]]), float(ops.metric_arrays(c.motion, a, b).sum())

    def nearest(self, qq: torch.Tensor, pool: torch.Tensor, k: int, pool_f64: Optional[Callable] = None):
        """Indices (Q, k) of the ``k`` configurations of ``pool`` nearest to each of ``qq`` under the motion metric
        (``pool_f64``: a callable giving the pool as float64 numpy, for the compiled pass)."""
        return self.ctx.compute.ops.nearest(self.ctx.motion, qq, pool, k, pool_f64)

    # ---- checks and scores of a query's few configurations -------------------------------------------------------
    def check_detailed(self, Q: np.ndarray) -> dict:
        """Collision flags {"limits", "environment", "self"} (numpy bool) of configurations ``Q`` (numpy)."""
        return self.ctx.compute.ops.check_arrays(self.ctx.checker, Q)

    def few_scores(self, q, scorer_args: Callable) -> Optional[torch.Tensor]:
        """Raw neural scores of a few configurations ``q`` in one compiled call, or None (the caller's torch path);
        ``scorer_args(dtype)`` gives the compiled scorer's arguments (None for another scorer)."""
        return None


class CompiledBackend(TorchBackend):
    """:class:`TorchBackend` with the fused compiled calls of a query's few edges and views."""

    compiled = True

    @property
    def fused(self) -> bool:
        return True

    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool) -> tuple:
        c, cp = self.ctx, self.ctx.compute
        if cp.pair_takes(qa, qb) and qa.shape[0] * (c.settings.edges.n_interp + 4) <= cp.max_batch:
            return edges.query_knots(c.edge_kit(), qa, qb, track)  # a query's few edges: one call
        return super().edge_knots(qa, qb, track)

    def few_scores(self, q, scorer_args: Callable) -> Optional[torch.Tensor]:
        cp = self.ctx.compute
        if not (len(q) <= cp.mlp_max_rows and (isinstance(q, np.ndarray) or cp.takes(q))):
            return None
        args = scorer_args(self.ctx.dtype if isinstance(q, np.ndarray) else q.dtype)
        return None if args is None else edges.neural_config_scores(self.ctx.robot, args, q)
