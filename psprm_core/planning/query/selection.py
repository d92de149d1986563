"""Route selection: more than one search per query, and the route that sees most.

One objective and one alpha do not find the best-seen route of a roadmap on every problem: Eq. 2 at the paper's
alpha trades views for fewer edges, the motion-weighted form at alpha < 1 trades a little perception for length, and
at alpha = 1 it ignores length entirely. With ``route_searches`` (e.g. ``"motion@1.0"``) a query searches the same
roadmap once more per entry, the edges weighted with that entry's objective and alpha for the search and weighted
back afterwards, and returns the route whose perception along the whole path (:meth:`~.scoring.Scoring.
route_perception`: the motion-weighted mean c_p of its dense configurations, Eq. 1 taken over the route) is highest
among the routes at most ``route_length_ratio`` times as long as the planner's own route. An ``alt`` entry searches
for another route: the motion-weighted form at alpha = 1 with the roadmap edges of every route found before weighted
:data:`ALT_PENALTY` times, so it leaves them where another way sees comparably (e.g. round the other side of a table
whose near side hides the target). Every candidate is a complete query result (connected, verified, shortcut,
timed), so what is returned is what was checked.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np

from ..results import PlanResult
from ..state import PlannerContext, QueryContext, ReadsQuerySettings

if TYPE_CHECKING:
    from ..roadmap.roadmap_state import RoadmapState
    from ..roadmap.scoring import Scoring
    from . import Query


#: Weight factor of the edges of the routes found before in an ``alt`` search.
ALT_PENALTY = 3.0
#: A route's perception is taken from every this many of its dense configurations (``edge_resolution`` apart).
PERCEPTION_STRIDE = 4


class RouteSelection(ReadsQuerySettings):
    """Runs a query's extra searches and picks the route that sees most."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, qc: QueryContext, query: Query, scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.qc = qc
        self.query = query
        self.scoring = scoring

    def choose(self, first: PlanResult, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool,
               goal_costs: Optional[np.ndarray]) -> PlanResult:
        """``first`` (the planner's own route, a success) or the extra search's route that sees more, within the
        length bound. The returned result names its search in ``route`` and carries every candidate's perception
        in ``route_candidates`` ({label: (perception, length)})."""
        base = self.qs
        searches = base.route_search_list()
        if not searches or not first.success:
            return first
        t0 = time.perf_counter()
        own = f"{base.scoring.objective}@{base.scoring.alpha:g}"
        best, best_p = first, self.perception(first)
        first.route = own
        cands = {own: (best_p, first.path_length)}
        limit = base.query.route_length_ratio * first.path_length
        saved = self.qc.settings
        used = self.rm.path_roadmap_edges(first.path_nodes)
        for objective, alpha in searches:
            other = objective == "alt"
            label = "alt" if other else f"{objective}@{alpha:g}"
            if label in cands:
                continue
            alt = base.changed({"scoring.objective": "motion" if other else objective, "scoring.alpha": alpha,
                                "query.route_searches": ()})
            with self.scoring.weighted_for(alt, penalize=(used, ALT_PENALTY) if other else None):
                self.qc.settings = alt
                try:
                    res = self.query.plan_once(start, goals, timing, goal_costs)
                finally:
                    self.qc.settings = saved
            if not res.success:
                continue
            used = np.union1d(used, self.rm.path_roadmap_edges(res.path_nodes))
            p = self.perception(res)
            cands[label] = (p, res.path_length)
            if res.path_length <= limit and p > best_p + 1e-9:
                res.route, best, best_p = label, res, p
        best.route_candidates = cands
        best.query_ms = float(np.nan_to_num(first.query_ms)) + (time.perf_counter() - t0) * 1e3
        return best

    def perception(self, res: PlanResult) -> float:
        """:meth:`~.scoring.Scoring.route_perception` of a result's dense path, every :data:`PERCEPTION_STRIDE`-th
        configuration and the last (scored now: the scene as it is)."""
        d = np.asarray(res.dense)
        idx = np.unique(np.r_[np.arange(0, len(d), PERCEPTION_STRIDE), len(d) - 1])
        return self.scoring.route_perception(d[idx], self.scoring.score_numpy(d[idx]))
