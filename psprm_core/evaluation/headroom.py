"""The best-perceived routes a PS-PRM roadmap admits: the benchmark's reference for "how much more was possible".

A planner's detection rate alone does not say whether a route that sees more existed. :class:`ReferenceRoutes` builds
the roadmap the neural PS-PRM variant plans on (same settings and seed) and, for each problem, gives several distinct
routes over it: searches with both objective forms (Eq. 2 and the motion-weighted one) at several alpha up to 1 (the
route that only minimises what is not seen), with and without shortcutting, and alternative routes found by
penalising the edges of the routes already found. ``psprm bench`` judges every candidate with the oracle; the best of
them and of the planners' own paths is the problem's reference
(:func:`psprm_core.evaluation.bench.report.annotate_headroom`).
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np
from ..baselines.psprm_adapter import PSPRMBenchPlanner

log = logging.getLogger(__name__)

#: (objective, alpha) searches of the candidate routes.
SEARCHES = (("eq2", 0.8), ("motion", 0.95), ("motion", 1.0))
#: Alternative routes: re-searches (motion objective, alpha = 1) with the edges of every route found so far weighted
#: ``PENALTY`` times.
ALTERNATIVES = 1
PENALTY = 3.0


class ReferenceRoutes:
    """Candidate routes over the roadmap of ``variant`` for the bench's per-problem reference.

    Parameters
    ----------
    scene, targets, robot, seed : as for every benchmark planner.
    variant : the PS-PRM variant whose roadmap is searched (default: the neural line-of-sight one).
    searches, alternatives, penalty : see :data:`SEARCHES`, :data:`ALTERNATIVES`, :data:`PENALTY`.
    **overrides : :class:`~psprm_core.planning.psprm.PSPRMSettings` fields of the variant (the bench passes that
        planner's own, so the roadmap is the one it plans on).
    """

    def __init__(self, scene, targets: Sequence[str], robot=None, seed: int = 0, variant: str = "neural-psprm-line",
                 searches: Sequence[tuple] = SEARCHES, alternatives: int = ALTERNATIVES, penalty: float = PENALTY,
                 **overrides):
        self._bench = PSPRMBenchPlanner(variant, scene, list(targets), robot=robot, seed=seed, **overrides)
        self.planner = self._bench.planner
        self.robot = self.planner.robot
        self.searches = list(searches)
        self.alternatives = int(alternatives)
        self.penalty = float(penalty)

    def prepare(self) -> dict:
        return self._bench.prepare()

    def reset(self, query: int = 0) -> None:
        """Back to the roadmap ``prepare()`` left (searches verify edges and re-weight the roadmap), so a problem's
        routes do not depend on the problems searched before it."""
        self._bench.reset(query)

    def routes(self, start: np.ndarray, goal: np.ndarray) -> list:
        """Distinct successful routes ``[(label, PlanResult), ...]`` from ``start`` to ``goal`` (configurations).

        Labels name the search (``motion@1.0``, ``eq2@0.8+shortcut``, ``alt2``); each is one search (no route
        selection). Routes with the same waypoints are given once. The planner's settings and weights are restored
        afterwards."""
        if not self._bench.built:
            return []
        self._bench.queried()
        p = self.planner
        saved = p.settings  # alpha and objective, restored with reweight
        out, seen, used_edges = [], set(), []

        def add(label, res):
            if not res.success or res.waypoints is None:
                return
            key = np.round(np.asarray(res.waypoints, float), 4).tobytes()
            if key in seen:
                return
            seen.add(key)
            out.append((label, res))
            used_edges.extend(self.planner.path_roadmap_edges(res.path_nodes).tolist())

        try:
            for objective, alpha in self.searches:
                for shortcut in (False, True):
                    p.reweight(alpha=alpha, objective=objective)
                    add(f"{objective}@{alpha:g}" + ("+shortcut" if shortcut else ""),
                        p.plan(start, goal, timing=False,
                               options={"query.shortcut": shortcut, "query.route_searches": ()}))
            for k in range(self.alternatives):
                p.reweight(alpha=1.0, objective="motion")
                g = p.graph
                e = np.unique(np.asarray([x for x in used_edges if g.edge_valid[x]], dtype=np.int64))
                if len(e):
                    g.set_weights(e, g.weights[e] * self.penalty)
                add(f"alt{k + 1}", p.plan(start, goal, timing=False,
                                          options={"query.shortcut": False, "query.route_searches": ()}))
        finally:
            p.reweight(alpha=saved.scoring.alpha, objective=saved.scoring.objective)
        return out
