"""Neighbour connection (Alg. 1, line 5): the k nearest nodes under the differential-drive metric (candidates from a
Euclidean embedding of (x, y, heading, joints)), plus random long edges within the connection radius delta."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..state import PlannerContext


class Neighbours:
    """Finds candidate edges: k nearest neighbours plus random long edges within delta."""

    def __init__(self, ctx: PlannerContext):
        self.ctx = ctx

    def embed(self, q: torch.Tensor) -> torch.Tensor:
        """Euclidean embedding (x, y, w cos theta, w sin theta, joints) whose distances rank neighbour candidates
        (w: the motion metric's weight of rotation); the configurations themselves for a fixed base."""
        if not self.ctx.robot.mobile:
            return q
        w = self.ctx.motion.w_rot
        return torch.cat([q[:, :2], w * torch.cos(q[:, 2:3]), w * torch.sin(q[:, 2:3]), q[:, 3:]], -1)

    def neighbours(self, A: torch.Tensor, B: torch.Tensor, k: int, exclude_self: bool = False, k_long: int = 0,
                   rng: Optional[np.random.Generator] = None) -> tuple:
        """k nearest nodes of B for each row of A under the motion metric (candidates from a Euclidean embedding),
        plus ``k_long`` random nodes within ``max_edge_length`` (embedding distance). Returns unique undirected pairs
        (u in A, v in B) and their motion costs."""
        ea, eb = self.embed(A), self.embed(B)
        kk = min(2 * k + (1 if exclude_self else 0), B.shape[0])
        rows, cols, lrows, lcols = [], [], [], []
        gen = torch.Generator(device="cpu").manual_seed(int(rng.integers(2**31)) if rng is not None else 0)
        for s in range(0, A.shape[0], 2048):
            d = torch.cdist(ea[s:s + 2048], eb)
            idx = d.topk(kk, largest=False).indices
            rows.append(torch.arange(s, s + idx.shape[0], device=A.device).repeat_interleave(kk))
            cols.append(idx.reshape(-1))
            if k_long > 0:  # random long edges: random keys, masked to the radius, take the k_long smallest keys
                key = torch.rand(d.shape, generator=gen).to(d.device)
                key[d > self.ctx.settings.roadmap.max_edge_length] = 2.0
                lidx = key.topk(min(k_long, d.shape[1]), largest=False).indices
                okl = torch.gather(key, 1, lidx) < 2.0
                r = torch.arange(s, s + idx.shape[0], device=A.device).unsqueeze(1).expand_as(lidx)
                lrows.append(r[okl])
                lcols.append(lidx[okl])
        u, v = torch.cat(rows), torch.cat(cols)
        if exclude_self:
            keep = u != v
            u, v = u[keep], v[keep]
        dist = self.ctx.motion.distance(A[u], B[v])
        # keep the k best by the true metric per row, within the connection radius
        order = torch.argsort(u * (dist.max() + 1) + dist)
        u, v, dist = u[order], v[order], dist[order]
        first = torch.ones_like(u, dtype=torch.bool)
        rank = torch.arange(len(u), device=u.device) - torch.searchsorted(u, u, right=False)
        keep = (rank < k) & (dist <= self.ctx.settings.roadmap.max_edge_length) & first
        u, v, dist = u[keep], v[keep], dist[keep]
        if lrows:
            lu, lv = torch.cat(lrows), torch.cat(lcols)
            if exclude_self:
                m = lu != lv
                lu, lv = lu[m], lv[m]
            ld = self.ctx.motion.distance(A[lu], B[lv])
            m = ld <= self.ctx.settings.roadmap.max_edge_length
            u, v, dist = torch.cat([u, lu[m]]), torch.cat([v, lv[m]]), torch.cat([dist, ld[m]])
        if exclude_self:  # undirected, unique
            a, b = torch.minimum(u, v), torch.maximum(u, v)
            key = torch.unique(a * B.shape[0] + b)
            u, v = key // B.shape[0], key % B.shape[0]
            dist = self.ctx.motion.distance(A[u], B[v])
        return u, v, dist
