"""Node sampling on the visibility manifold (Alg. 1, lines 2-4): uniform samples projected by Gauss-Newton
(:mod:`.constraints`), and perception-biased samples kept with probability equal to their normalised predicted score."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..constraints import camera_joint_mask
from ..state import PlannerContext

if TYPE_CHECKING:
    from .scoring import Scoring

log = logging.getLogger(__name__)


class Sampling:
    """Draws roadmap nodes: uniform on the manifold, or perception-biased."""

    def __init__(self, ctx: PlannerContext, scoring: Scoring):
        self.ctx = ctx
        self.scoring = scoring

    def sample(self, n: int, rng: np.random.Generator, template: np.ndarray) -> torch.Tensor:
        """``n`` uniform configurations (not yet projected): the base over the scene's workspace and any heading, the
        other joints within their limits (within ``sample_spread`` of ``template`` when set); with ``sample_joints``
        "camera" the joints that do not move the camera stay at ``template``."""
        r = self.ctx.robot
        lo, hi = r.lower.copy(), r.upper.copy()
        if r.mobile:
            lo[:2], hi[:2] = self.ctx.scene.workspace[:, 0], self.ctx.scene.workspace[:, 1]
            lo[2], hi[2] = -np.pi, np.pi
        lo = np.where(np.isfinite(lo), lo, -np.pi)
        hi = np.where(np.isfinite(hi), hi, np.pi)
        if self.ctx.settings.roadmap.sample_spread >= 0:  # keep an arm near its camera-ready template pose
            b = r.base_dof
            lo[b:] = np.maximum(lo[b:], template[b:] - self.ctx.settings.roadmap.sample_spread)
            hi[b:] = np.minimum(hi[b:], template[b:] + self.ctx.settings.roadmap.sample_spread)
        q = lo + rng.random((n, r.dof)) * (hi - lo)
        if self.ctx.settings.roadmap.sample_joints == "camera":
            mask = camera_joint_mask(r)
            q[:, ~mask] = template[~mask]
        return self.ctx.t(q)

    def manifold_samples(self, rng: np.random.Generator, template: np.ndarray) -> torch.Tensor:
        """One batch of ``sample_batch`` samples projected onto the visibility manifold; the converged, valid ones."""
        s = self.ctx.settings
        q = self.sample(s.roadmap.sample_batch, rng, template)
        q, ok = self.ctx.constraint.project(q, s.projection, self.ctx.lo, self.ctx.hi)
        q = q[ok]
        return q[self.ctx.checker.valid(q)]

    def biased_nodes(self, Q: torch.Tensor, scores: torch.Tensor, n: int, rng: np.random.Generator,
                     template: np.ndarray, t0: float) -> tuple:
        """Perception-biased sampling: ``n`` more manifold nodes, each manifold sample kept with probability equal to
        its normalised score (its score over the 99th-percentile score of the uniform nodes, at most 1), so that
        regions with good predicted views (the surrogate with occlusion) are dense enough to route through; at most
        ``biased_tries * n`` samples are scored. Returns the nodes and scores with the new ones appended, and stats."""
        s = self.ctx.settings
        ref = max(float(torch.quantile(scores.double(), 0.99)), 1e-3) if len(scores) else 1.0
        keep_q, keep_s, tried = [Q], [scores], 0
        got = 0
        while got < n and tried < s.roadmap.biased_tries * n:
            if time.perf_counter() - t0 > s.roadmap.build_timeout_s:
                log.warning("biased sampling timed out with %d/%d nodes", got, n)
                break
            q = self.manifold_samples(rng, template)
            if not len(q):
                tried += s.roadmap.sample_batch
                continue
            sc = self.scoring.score_configs(q)
            tried += len(q)
            accept = torch.as_tensor(rng.random(len(q)), dtype=sc.dtype, device=sc.device) < (sc / ref).clamp(0, 1)
            q, sc = q[accept][: n - got], sc[accept][: n - got]
            keep_q.append(q)
            keep_s.append(sc)
            got += len(q)
        if got < n:
            log.info("biased sampling kept %d of %d nodes within %d tries", got, n, tried)
        return torch.cat(keep_q), torch.cat(keep_s), {"biased_nodes": int(got), "biased_tried": int(tried)}
