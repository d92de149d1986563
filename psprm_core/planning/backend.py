"""Where the planner's batched stage operations run: one object per planner, chosen from its
:class:`~psprm_core.kernels.compute.Compute`.

- :class:`TorchBackend`: every operation in torch on the planner's device and dtype (a GPU, a CPU without numba, or a
  ``Compute`` with ``kernels="torch"``): the reference;
- :class:`CompiledBackend` (``kernels="numba"``): the compiled kernels of :mod:`psprm_core.kernels.fastpath` for the
  batch sizes the ``Compute`` lets them serve (a query's few edges in one fused call, the metric at any size, bulk
  rows inside :func:`~psprm_core.kernels.compute.bulk`), the torch code otherwise. The kernels give the torch results
  (``tests/test_fastpath.py``).

The stages call these verbs and never test the device themselves. The domain objects the planner shares with the
baselines (robot FK, collision checker, motion metric, visibility constraint) choose their own compiled paths in the
same way.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import numpy as np
import torch

from ..kernels import edges, fastpath


def backend_for(ctx) -> "TorchBackend":
    """The backend of a planner's :class:`~.state.PlannerContext`: compiled when its ``Compute`` chose the numba
    kernels, else torch."""
    if ctx.compute.compiled:
        return CompiledBackend(ctx)
    return TorchBackend(ctx)


class TorchBackend:
    """The planner's stage operations in torch (any device, any batch size)."""

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
        E, n = qa.shape[0], c.settings.edges.n_interp
        dt, dev = qa.dtype, qa.device
        if c.robot.mobile:
            _, r1, d, r2 = c.motion._base_plan(qa, qb)
            l1, l2, l3 = c.motion.w_rot * r1.abs(), d, c.motion.w_rot * r2.abs()
            tot = (l1 + l2 + l3).clamp_min(1e-12)
            corners = torch.stack([l1 / tot, (l1 + l2) / tot], -1)
        else:
            corners = torch.zeros(E, 0, dtype=dt, device=dev)
        samples = (torch.arange(1, n + 1, dtype=dt, device=dev) / (n + 1)).expand(E, n)
        s_all = torch.cat([torch.zeros(E, 1, dtype=dt, device=dev), samples, corners,
                           torch.ones(E, 1, dtype=dt, device=dev)], -1)
        order = torch.argsort(s_all, dim=-1, stable=True)
        s_sorted = torch.gather(s_all, 1, order)
        inv = torch.argsort(order, dim=-1)
        interior_idx = inv[:, 1:1 + n]
        M = s_all.shape[1]
        knots = c.motion.interpolate(qa.repeat_interleave(M, 0), qb.repeat_interleave(M, 0), s_sorted.reshape(-1))
        knots = knots.reshape(E, M, -1)
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
        c = self.ctx
        return c.motion.distance(torch.from_numpy(qa).to(c.device), torch.from_numpy(qb).to(c.device)).cpu().numpy()

    def pieces(self, a: torch.Tensor, b: torch.Tensor, max_steps: int, include_start: bool) -> tuple:
        """(piece index, points) every ``edge_resolution`` on the straight pieces a[i] -> b[i]
        (:meth:`.edges.Edges.pieces`)."""
        c = self.ctx
        diff = b - a
        if c.robot.mobile:
            diff[:, 2] = torch.remainder(diff[:, 2] + np.pi, 2 * np.pi) - np.pi
        n = torch.ceil(c.motion.distance(a, b) / c.settings.edges.edge_resolution).long().clamp(1, max_steps)
        count = n if include_start else n - 1
        seg = torch.repeat_interleave(torch.arange(len(a), device=a.device), count)
        k = torch.arange(len(seg), device=a.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
        frac = ((k + (0 if include_start else 1)).to(a.dtype) / n[seg].to(a.dtype)).unsqueeze(-1)
        return seg, a[seg] + diff[seg] * frac

    def dense_path(self, W: np.ndarray) -> tuple:
        """(configurations every ``edge_resolution`` along the knot path ``W`` (K, dof) float64, its length)."""
        Wt = torch.from_numpy(W).to(self.ctx.device)
        if len(W) < 2:
            return W, 0.0
        _, pts = self.pieces(Wt[:-1], Wt[1:], max_steps=1000, include_start=True)
        length = float(self.ctx.motion.distance(Wt[:-1], Wt[1:]).sum())
        return torch.cat([pts, Wt[-1:]]).cpu().numpy(), length

    def nearest(self, qq: torch.Tensor, pool: torch.Tensor, k: int, pool_f64: Optional[Callable] = None):
        """Indices (Q, k) of the ``k`` configurations of ``pool`` nearest to each of ``qq`` under the motion metric
        (``pool_f64``: a callable giving the pool as float64 numpy, for the compiled pass)."""
        d = self.ctx.motion.distance(qq.repeat_interleave(pool.shape[0], 0), pool.repeat(len(qq), 1))
        return d.reshape(len(qq), -1).topk(k, largest=False).indices

    # ---- checks and scores of a query's few configurations -------------------------------------------------------
    def check_detailed(self, Q: np.ndarray) -> dict:
        """Collision flags {"limits", "environment", "self"} (numpy bool) of configurations ``Q`` (numpy)."""
        q = torch.from_numpy(Q).to(self.ctx.device)
        return {k: v.cpu().numpy() for k, v in self.ctx.checker.check_detailed(q).items()}

    def few_scores(self, q, scorer_args: Callable) -> Optional[torch.Tensor]:
        """Raw neural scores of a few configurations ``q`` in one compiled call, or None (the caller's torch path);
        ``scorer_args(dtype)`` gives the compiled scorer's arguments (None for another scorer)."""
        return None


class CompiledBackend(TorchBackend):
    """The compiled CPU kernels for the batches they serve; the torch code otherwise."""

    compiled = True

    @property
    def fused(self) -> bool:
        return True

    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool) -> tuple:
        c, cp = self.ctx, self.ctx.compute
        E, n = qa.shape[0], c.settings.edges.n_interp
        if cp.pair_takes(qa, qb) and E * (n + 4) <= cp.max_batch:  # a query's few edges: one call
            return edges.query_knots(c.edge_kit(), qa, qb, track)
        if cp.pair_takes(qa, qb) and cp.fits(E * (n + 4)):  # bulk: compiled, in row chunks
            knots, interior_idx = fastpath.edge_knot_seeds(c.motion, qa, qb, n)
            return (self.track_knots(knots) if track else knots), interior_idx
        return super().edge_knots(qa, qb, track)

    def motion_distance(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        if len(qa) <= self.ctx.compute.motion_max_batch:
            m = self.ctx.motion  # the compiled metric of DiffDriveMotion.distance, without the tensor round trip
            d = fastpath.kernels().distance(qa.astype(np.float64), qb.astype(np.float64), float(m.w_rot),
                                            bool(m.mobile))
            return d.astype(qa.dtype)
        return super().motion_distance(qa, qb)

    def pieces(self, a: torch.Tensor, b: torch.Tensor, max_steps: int, include_start: bool) -> tuple:
        if self.ctx.compute.pair_takes(a, b):  # one compiled pass (same lengths, same points)
            return fastpath.pieces(self.ctx.motion, a, b, self.ctx.settings.edges.edge_resolution, max_steps, include_start)
        return super().pieces(a, b, max_steps, include_start)

    def dense_path(self, W: np.ndarray) -> tuple:
        if len(W) < 2:
            return W, 0.0
        m, K = self.ctx.motion, fastpath.kernels()
        _, pts = K.pieces(W[:-1], W[1:], float(self.ctx.settings.edges.edge_resolution), 1000, True, float(m.w_rot),
                          bool(m.mobile))
        return np.concatenate([pts, W[-1:]]), float(K.distance(W[:-1], W[1:], float(m.w_rot), bool(m.mobile)).sum())

    def nearest(self, qq: torch.Tensor, pool: torch.Tensor, k: int, pool_f64: Optional[Callable] = None):
        if self.ctx.compute.pair_takes(qq, qq) and k > 0:
            # one compiled pass that skips far nodes early
            return fastpath.nearest(self.ctx.motion, qq, pool if pool_f64 is None else pool_f64(), k)
        return super().nearest(qq, pool, k)

    def check_detailed(self, Q: np.ndarray) -> dict:
        if len(Q) <= self.ctx.compute.max_batch:
            f = fastpath.check(self.ctx.checker, Q, detailed=True)  # CollisionChecker.check_detailed, compiled
            return {"limits": f[:, 0], "environment": f[:, 1], "self": f[:, 2]}
        return super().check_detailed(Q)

    def few_scores(self, q, scorer_args: Callable) -> Optional[torch.Tensor]:
        cp = self.ctx.compute
        if not (len(q) <= cp.mlp_max_rows and (isinstance(q, np.ndarray) or cp.takes(q))):
            return None
        args = scorer_args(self.ctx.dtype if isinstance(q, np.ndarray) else q.dtype)
        return None if args is None else edges.neural_config_scores(self.ctx.robot, args, q)
