"""The planner's stages composed over its shared state (see :mod:`.state`)."""

from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError
from .backend import backend_for
from .query import Query
from .query.recovery import Recovery
from .query.selection import RouteSelection
from .query.shortcut import Shortcut
from .query.trajectory import Trajectory
from .results import Failure, PlanResult
from .roadmap.builder import Builder
from .roadmap.dynamics import Dynamics
from .roadmap.edges import Edges
from .roadmap.knots import KnotStore
from .roadmap.neighbours import Neighbours
from .roadmap.persistence import Persistence
from .roadmap.roadmap_state import RoadmapState
from .roadmap.sampling import Sampling
from .roadmap.scoring import Scoring
from .roadmap.verification import Verification
from .search.heuristics import Heuristics
from .settings import query_options
from .state import PlannerContext, QueryContext, one_thread


class Pipeline:
    """One planner's state objects and stages, in the order of the paper's pipeline.

    State: ``ctx`` (:class:`~.state.PlannerContext`), ``rm`` (:class:`~.roadmap_state.RoadmapState`), ``knots``
    (:class:`~.knots.KnotStore`), ``qc`` (:class:`~.state.QueryContext`). Stages: ``sampling`` (nodes on the
    visibility manifold), ``neighbours`` (candidate edges), ``edges`` (knots, re-aiming, dense checks), ``scoring``
    (Eq. 1, Eq. 2), ``builder`` (Alg. 1, growth), ``heuristics`` (Eqs. 3-6), ``verify`` (lazy checks), ``query``
    (connection and search), ``shortcut`` (path shortcuts), ``recovery`` (escape, repair), ``trajectory`` (waypoints
    and timing), ``dynamics`` (moved targets and obstacles), ``persistence`` (save, load).

    Each stage is given, in its constructor, the state objects it reads and the stages it calls, and keeps them as
    attributes of the same names; :meth:`__init__` makes the stages in an order where every stage it passes exists.
    Calls go downwards, in four layers:

    - ``edges``, ``scoring``: knots, dense checks and scores. ``scoring`` is made with ``edges``; ``edges`` gets
      ``scoring`` back by :meth:`~.edges.Edges.bind_scoring` (it scores the edges it checks);
    - ``sampling`` (uses ``scoring``), ``neighbours``, ``heuristics``, ``verify`` and ``trajectory`` (use ``edges``
      and ``scoring``);
    - ``builder`` (the stages above but ``verify``), ``shortcut`` (``edges``, ``scoring``), ``dynamics`` and
      ``persistence`` (``scoring``; ``persistence`` also ``heuristics``), ``query`` (``edges``, ``scoring``,
      ``heuristics``, ``verify``, ``shortcut``, ``trajectory``);
    - ``selection`` (``query``, ``scoring``) and ``recovery`` (``query``, ``builder``, ``edges``).

    Two calls go up, bound after the upper stage is made: a shortcut taken joins the query's edges
    (:meth:`~.shortcut.Shortcut.bind_query`: ``shortcut`` calls ``query.add_query_edges``), and a start inside the
    collision padding is moved out of it by the recovery's start fix before the search
    (:meth:`~.query.Query.bind_recovery`: ``query`` calls ``recovery.move_out``). The late-bound attributes are typed
    by the protocol of what they call (:class:`~.edges.KnotScorer`, :class:`~.shortcut.QueryEdges`,
    :class:`~.query.StartFix`): the lower module does not import the upper one.

    :meth:`plan` runs one search (``query.plan_once``) and, when no goal is reachable, the strategies of
    ``recovery``, which search again through ``query.plan_once``; with ``route_searches``, ``selection`` searches
    again with other weights and keeps the route that sees most."""

    def __init__(self, ctx: PlannerContext):
        self.ctx = ctx
        if ctx.backend is None:
            ctx.backend = backend_for(ctx)
        self.knots = KnotStore()
        self.rm = RoadmapState(ctx, self.knots)
        self.qc = QueryContext()
        rm, knots, qc = self.rm, self.knots, self.qc
        self.edges = Edges(ctx, rm, knots, qc)
        self.scoring = Scoring(ctx, rm, knots, qc, edges=self.edges)
        self.edges.bind_scoring(self.scoring)  # the one cycle: edges and scoring use each other's knots and scores
        self.sampling = Sampling(ctx, scoring=self.scoring)
        self.neighbours = Neighbours(ctx)
        self.heuristics = Heuristics(ctx, rm, qc)
        self.verify = Verification(ctx, rm, knots, qc, edges=self.edges, scoring=self.scoring)
        self.trajectory = Trajectory(ctx, rm, knots, qc, edges=self.edges, scoring=self.scoring)
        self.builder = Builder(ctx, rm, knots, sampling=self.sampling, neighbours=self.neighbours, edges=self.edges,
                               scoring=self.scoring, heuristics=self.heuristics, trajectory=self.trajectory)
        self.shortcut = Shortcut(ctx, rm, qc, edges=self.edges, scoring=self.scoring)
        self.query = Query(ctx, rm, qc, edges=self.edges, scoring=self.scoring, heuristics=self.heuristics,
                           verify=self.verify, shortcut=self.shortcut, trajectory=self.trajectory)
        self.shortcut.bind_query(self.query)  # upward: a shortcut taken joins the query's edges
        self.selection = RouteSelection(ctx, rm, qc, query=self.query, scoring=self.scoring)
        self.recovery = Recovery(ctx, rm, builder=self.builder, edges=self.edges, query=self.query)
        self.query.bind_recovery(self.recovery)  # upward: the query's start fix is a recovery strategy
        self.dynamics = Dynamics(ctx, rm, knots, scoring=self.scoring)
        self.persistence = Persistence(ctx, rm, knots, heuristics=self.heuristics, scoring=self.scoring)

    @one_thread
    def plan(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
             goal_costs: Optional[np.ndarray] = None, options: Optional[dict] = None) -> PlanResult:
        """:meth:`plan_recovering` with the query's ``options``: settings of :func:`~.settings.query_options` that
        this query uses instead of the planner's (a replanner's heuristic, timing and shortcut choice); the planner's
        settings are not changed."""
        settings = None
        if options:
            allowed = query_options()
            unknown = sorted(set(options) - set(allowed))
            if unknown:
                raise InputError(f"unknown query options {unknown} (dotted paths: {', '.join(allowed)})")
            settings = self.ctx.settings.changed(options)
            settings.validate("query options")
        self.qc.settings = settings
        try:
            res = self.plan_recovering(start, goals, timing, goal_costs)
            return self.selection.choose(res, start, goals, timing, goal_costs)
        finally:
            self.qc.settings = None

    @one_thread
    def fastest(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray,
                options: Optional[dict] = None) -> PlanResult:
        """The route of least motion cost (the motion-weighted objective at alpha 0: length alone) from ``start`` to
        the nearest of ``goals`` over the roadmap's edges, timed (a shortcut of another route may still be shorter:
        a replanner's arrival budget takes the smaller of the two durations). One search
        (no recovery, no route selection) with the edges weighted for it inside the search
        (:meth:`~.roadmap.scoring.Scoring.weighted_for`); ``options`` as in :meth:`plan` (a replanner's timing).
        The planner's weights and settings after it are as before."""
        fast = self.ctx.settings.changed({**(options or {}), "scoring.objective": "motion", "scoring.alpha": 0.0,
                                          "query.route_searches": ()})
        with self.scoring.weighted_for(fast):
            self.qc.settings = fast
            try:
                return self.query.plan_once(start, goals, True, None)
            finally:
                self.qc.settings = None

    def plan_recovering(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
                        goal_costs: Optional[np.ndarray] = None) -> PlanResult:
        """Plan from ``start`` to the cheapest of ``goals`` (one configuration (dof,) or several (G, dof)); see
        :meth:`~.query.Query.plan_once`.

        When no goal is reachable (a start or goal whose connecting edges all collide, e.g. next to a wall where the
        base cannot turn), an escape search runs first (``query_escape_s`` > 0, below); if it does not succeed, the
        roadmap is repaired locally: ``query_repair_nodes`` manifold nodes are grown around the
        start and each goal (up to 4), half of them along its heading (reachable by driving straight), and the query
        is repeated, connecting each end to every node grown for it and to its ``query_repair_connect_k`` nearest
        nodes. Up to ``query_repair_rounds`` rounds, each with 1.5 times the previous radius. The nodes of a repair
        that succeeds stay in the roadmap, within ``query_repair_budget``; those of a repair that fails are removed
        again, so that they do not use up the budget of later queries; after ``query_repair_failures`` such failed
        repairs (their removed node slots stay allocated) a failing query is no longer repaired, so a goal that stays
        unreachable cannot make a long-running planner grow without end.

        The two other stages (not once ``query_repair_failures`` is reached, like the repair):

        - escape (``query_escape_s`` > 0), before the repair: a bounded RRT-like search of differential-drive motions
          with the arm moving (turn in place, drive or back up, joints interpolated, untracked) from each end to the
          roadmap's largest component (:meth:`~.recovery.Recovery.escape`, ``query_escape_*``); its configurations and
          densely checked edges join the query as query nodes and edges, scored (Eq. 1) like any other edge, and the
          query is searched once more. An end it cannot get out of is named in the reason of a query that fails ("start
          is boxed in: no collision-free motion out of it was found ..." when not one short motion out of it is free);
        - wide (``query_wide_k`` > 0), when the escape and the repair did not succeed: each end tries its
          ``query_wide_k`` nearest roadmap nodes, however far (long connections, checked and scored like any other),
          for ends whose few free motions lead beyond the repair's neighbours (a robot across a shelf aisle).

        In the escape's and the wide query (``query_untracked_fallback``), a connection edge whose re-aimed knots
        collide (the arm re-aiming the camera sweeps a shelf) is kept with its untracked knots (the camera joints
        interpolated plainly) when those are collision-free; the first query and the repaired ones are unchanged."""
        res = self.query.plan_once(start, goals, timing, goal_costs)
        if res.success or res.failure is not Failure.UNREACHABLE or self.rm.graph is None:
            return res
        t0 = time.perf_counter()
        s = self.ctx.settings
        k = s.recovery.query_wide_k
        # after query_repair_failures failed repairs an unreachable goal is given up cheaply (a replanner may ask again
        # and again): no escape, repair or wide attempt
        escaped = None
        out = res
        if s.recovery.query_escape_s > 0 and self.rm.repair_failed < s.recovery.query_repair_failures:
            escaped = self.recovery.escape_query(start, goals, timing, goal_costs)
            if escaped.success:
                out = escaped
        if not out.success:
            out = self.recovery.repair_query(start, goals, timing, goal_costs, res)
        if (not out.success and out.failure is Failure.UNREACHABLE and k > s.recovery.query_repair_connect_k
                and self.rm.repair_failed < s.recovery.query_repair_failures):
            wide = self.query.plan_once(start, goals, timing, goal_costs, extra_candidates={}, connect_k=k,
                                  untracked=s.recovery.query_untracked_fallback)
            if wide.success or wide.failure is not Failure.UNREACHABLE:
                out = wide
                if wide.success:
                    out.reason = f"ok after connecting to the {k} nearest roadmap nodes"
        if not out.success and escaped is not None:  # the escape search says which end could not get out
            out = escaped
        out.query_ms = (res.query_ms or 0.0) + (time.perf_counter() - t0) * 1e3
        return out
