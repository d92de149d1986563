"""Perception-preserving shortcutting of a found path: a direct local motion replaces a stretch of the path only when
it is shorter, collision-free, stays on the visibility manifold and its Eq. 1 score is not lower."""

from __future__ import annotations

import logging

import numpy as np
import torch

from .state import Stage

log = logging.getLogger(__name__)

SHORTCUT_CANDIDATES = 8  # later path nodes a shortcut from one node tries at most (the farthest ones)


class Shortcut(Stage):
    """Shortcuts found paths without losing perception."""

    def shortcut_path(self, path: list, cost: float, added_edges: list) -> tuple:
        """Perception-preserving shortcuts of a found path (``shortcut_rounds`` greedy passes): from each kept node,
        the farthest later node (of the :data:`SHORTCUT_CANDIDATES` farthest within twice the roadmap's longest edge)
        joined by one direct local motion that is shorter than the stretch it replaces, is
        collision-free (checked densely, like every edge), keeps every interior knot on the visibility manifold
        (|h_M| within the projection tolerance after re-aiming) and whose Eq. 1 perception is at least the
        motion-weighted mean Eq. 1 perception of the replaced edges. Every candidate of a node is checked in one
        batch. The shortcut edges join the query's edges (``added_edges``) with their knots stored, so the path that
        runs is the one checked. Returns the new path and its cost."""
        g = self.rm.graph
        tol = float(self.ctx.settings.projection.tolerance)
        for _ in range(max(1, self.qs.shortcut_rounds)):
            eids = g.edge_ids_of_path(path)
            cm = g.edge_attribute("c_m")[eids] * self.rm.max_motion  # motion cost of each edge
            cp = g.edge_attribute("c_p")[eids]
            arc = np.concatenate([[0.0], np.cumsum(cm)])
            seen = np.concatenate([[0.0], np.cumsum(cm * np.nan_to_num(cp))])
            out, i, changed = [path[0]], 0, False
            while i < len(path) - 1:
                later = np.arange(i + 2, len(path))
                j = i + 1
                if len(later):
                    qa = np.repeat(g.configs[path[i]][None], len(later), 0)
                    qb = g.configs[np.asarray(path)[later]]
                    d = self.pl.edges.motion_distance(qa, qb)
                    span = arc[later] - arc[i]
                    need = (seen[later] - seen[i]) / np.maximum(span, 1e-12)  # mean Eq. 1 of the replaced edges
                    # an existing edge between the two was the search's to take (and must not be overwritten)
                    joined = np.asarray([g.edge_id(path[i], path[x]) is not None for x in later])
                    # at most SHORTCUT_CANDIDATES of the farthest, within twice the roadmap's edge length
                    cand = np.nonzero((d < span - 1e-9) & ~joined & (d <= 2 * self.rm.max_motion))[0]
                    cand = cand[-SHORTCUT_CANDIDATES:]
                    if len(cand):
                        ta, tb = self.ctx.t(qa[cand]), self.ctx.t(qb[cand])
                        kn, ki = self.pl.edges.edge_knots(ta, tb)
                        M = kn.shape[1]
                        on = self.ctx.constraint.error(kn[:, 1:-1].reshape(-1, kn.shape[-1])).reshape(len(cand), M - 2)
                        ok = (on <= tol).all(-1) if M > 2 else torch.ones(len(cand), dtype=torch.bool)
                        ok &= self.pl.edges.knots_valid(kn, dense=True)
                        p = torch.zeros(len(cand), dtype=self.ctx.dtype, device=self.ctx.device)
                        if ok.any():
                            p[ok] = self.pl.scoring.knots_perception(kn[ok], ki[ok])
                        good = ok.cpu().numpy() & (p.double().cpu().numpy() >= need[cand] - 1e-9)
                        if good.any():
                            m = int(np.nonzero(good)[0].max())
                            jj = int(later[cand[m]])
                            e = self.pl.query.add_query_edges(np.asarray([path[i]]), np.asarray([path[jj]]),
                                                      p[m:m + 1].cpu().numpy(), d[cand[m]:cand[m] + 1])
                            self.pl.edges.put_knots(np.asarray(e), np.asarray([path[i]]), kn[m:m + 1], ki[m:m + 1])
                            added_edges.extend(e)
                            out.append(path[jj])
                            i, changed = jj, True
                            continue
                out.append(path[j])
                i = j
            path = out
            if not changed:
                break
        eids = g.edge_ids_of_path(path)
        return path, float(g.weights[eids].sum())
