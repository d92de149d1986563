"""The planner's stages composed over its shared state (see :mod:`.state`)."""

from __future__ import annotations

from .backend import backend_for
from .builder import Builder
from .dynamics import Dynamics
from .edges import Edges
from .heuristics import Heuristics
from .knots import KnotStore
from .neighbours import Neighbours
from .persistence import Persistence
from .query import Query
from .recovery import Recovery
from .roadmap_state import RoadmapState
from .sampling import Sampling
from .scoring import Scoring
from .shortcut import Shortcut
from .state import PlannerContext, QueryContext
from .trajectory import Trajectory
from .verification import Verification


class Pipeline:
    """One planner's state objects and stages, in the order of the paper's pipeline.

    State: ``ctx`` (:class:`~.state.PlannerContext`), ``rm`` (:class:`~.roadmap_state.RoadmapState`), ``knots``
    (:class:`~.knots.KnotStore`), ``qc`` (:class:`~.state.QueryContext`). Stages: ``sampling`` (nodes on the
    visibility manifold), ``neighbours`` (candidate edges), ``edges`` (knots, re-aiming, dense checks), ``scoring``
    (Eq. 1, Eq. 2), ``builder`` (Alg. 1, growth), ``heuristics`` (Eqs. 3-6), ``verify`` (lazy checks), ``query``
    (connection and search), ``shortcut`` (path shortcuts), ``recovery`` (escape, repair), ``trajectory`` (waypoints
    and timing), ``dynamics`` (moved targets and obstacles), ``persistence`` (save, load).

    Calls go downwards: ``builder``, ``query``, ``recovery``, ``shortcut`` and ``dynamics`` use the lower stages
    (``sampling``, ``neighbours``, ``edges``, ``scoring``, ``heuristics``, ``verify``, ``trajectory``), which use
    each other only for knots and scores (``edges`` <-> ``scoring``). ``query.plan`` runs one search
    (``query.plan_once``) and, when no goal is reachable, the strategies of ``recovery``, which search again through
    ``query.plan_once``."""

    def __init__(self, ctx: PlannerContext):
        self.ctx = ctx
        if ctx.backend is None:
            ctx.backend = backend_for(ctx)
        self.rm = RoadmapState(ctx)
        self.knots = KnotStore()
        self.qc = QueryContext()
        self.sampling = Sampling(self)
        self.neighbours = Neighbours(self)
        self.edges = Edges(self)
        self.scoring = Scoring(self)
        self.builder = Builder(self)
        self.heuristics = Heuristics(self)
        self.verify = Verification(self)
        self.query = Query(self)
        self.shortcut = Shortcut(self)
        self.recovery = Recovery(self)
        self.trajectory = Trajectory(self)
        self.dynamics = Dynamics(self)
        self.persistence = Persistence(self)
