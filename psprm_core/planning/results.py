"""Outcomes of the planner: :class:`PlanResult` of a query (a reason instead of an exception) and
:class:`EscapeResult` of the escape search from one query end."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np
import torch


class Failure(str, enum.Enum):
    """What kind of failure a query ended with (beside its human ``reason``); control flow reads this, never the
    reason's text. ``NONE`` for a success."""

    NONE = "none"
    NOT_BUILT = "not_built"  # no roadmap yet
    INVALID_INPUT = "invalid_input"  # NaN/inf, no robot state, no goal
    START_BLOCKED = "start_blocked"  # the start is invalid, inside the padding, or boxed in
    GOAL_BLOCKED = "goal_blocked"  # every goal is invalid, or no goal end gets out to the roadmap
    UNREACHABLE = "unreachable"  # no route on the roadmap (disconnected, or every connecting edge invalid)
    SEARCH_LIMIT = "search_limit"  # the search's expansion or iteration limit
    TIMEOUT = "timeout"  # a planner's time budget ran out
    COMMITTED_COLLISION = "committed_collision"  # the motion already under way collides: the robot must stop
    NO_SOLUTION = "no_solution"  # a baseline found none (optimisation failed, no valid trajectory, ...)
    INTERNAL = "internal"  # a defect: an exception or a path failing the final check


class Keep(str, enum.Enum):
    """Why a replanner kept its current plan (:attr:`PlanResult.kept_because`, beside the human ``reason``)."""

    NONE = "none"  # not kept: the result is a new plan (or a failure)
    AT_GOAL = "at_goal"  # the trajectory under way already ends at the best goal
    NO_BETTER = "no_better"  # the new plan is predicted to see no more, nor is it shorter and seeing no less
    LATE = "late"  # the new plan would arrive beyond the arrival budget and after the current one


class Adopt(str, enum.Enum):
    """Why a replanner adopted a new plan (:attr:`PlanResult.adopted_because`, beside ``judgement``)."""

    NONE = "none"  # not an adopted replan: a kept plan, a failure, a query outside a replanner
    UNJUDGED = "unjudged"  # the keep decision does not apply: no plan under way (or it has ended), a trigger other
    # than the view (the goal, an obstacle, a collision, no plan), or ``keep_unless_better`` off
    UNSAFE = "unsafe"  # the remaining path of the current plan collides with the latest obstacle poses
    SEES_MORE = "sees_more"  # predicted to see more than the remaining path, by ``keep_score_margin``
    SHORTER = "shorter"  # shorter by ``keep_length_margin`` and predicted to see no less (nor less than the floor)


@dataclass
class PlanResult:
    """Outcome of a query (``success`` False comes with a ``reason``; never an exception for bad problems).

    ``dense_scores`` (the planner's perception score along ``dense``) and their mean ``mean_score`` are a report, not
    part of the search: they are computed on first access with ``score_fn`` (the planner's scorer, i.e. the scene at
    that moment: read them before moving targets or obstacles) and are not included in ``query_ms``.
    """

    success: bool
    reason: str = "ok"
    failure: Failure = Failure.NONE  # with ``success`` False: the kind (control flow reads this, not ``reason``)
    path_nodes: list = field(default_factory=list)
    waypoints: Optional[np.ndarray] = None  # (M, dof) roadmap path incl. diff-drive corners
    dense: Optional[np.ndarray] = None  # (K, dof) configurations every ``edge_resolution`` along the path
    trajectory: object = None  # timing.Trajectory
    cost: float = float("inf")
    path_length: float = float("nan")
    query_ms: float = float("nan")
    goal_index: int = -1
    route: str = ""  # with route selection: the search whose route this is ("motion@1", ...)
    route_candidates: dict = field(default_factory=dict, repr=False)  # search -> (route perception, path length)
    kept: bool = False  # a replanner kept its current plan: the new one was no better (no path, no trajectory here)
    declined: Optional["PlanResult"] = field(default=None, repr=False, compare=False)  # with ``kept``: that new plan
    kept_because: Keep = Keep.NONE  # with ``kept``: why (control flow and counters read this, not ``reason``)
    adopted_because: Adopt = Adopt.NONE  # a replan's adopted plan: why it replaced the current one ...
    judgement: str = ""  # ... and, when the keep decision judged it, both plans' predicted perception and arrival
    start_offset_s: float = 0.0  # a replan of a robot in motion: time 0 of ``trajectory`` is this far along the
    # previous trajectory (planning.execution), 0 for a plan from the robot's state
    committed_s: float = 0.0  # ... and its first this many seconds are the previous trajectory's (the commitment)
    score_fn: Optional[Callable[[np.ndarray], np.ndarray]] = field(default=None, repr=False, compare=False)
    _dense_scores: Optional[np.ndarray] = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        if not self.success and self.failure is Failure.NONE:  # a failure always has a kind
            self.failure = Failure.NO_SOLUTION

    @property
    def dense_scores(self) -> Optional[np.ndarray]:
        """(K,) planner's perception score along ``dense`` (scored on first access)."""
        if self._dense_scores is None and self.dense is not None and self.score_fn is not None:
            self._dense_scores = np.asarray(self.score_fn(self.dense), dtype=float)
            self.score_fn = None
        return self._dense_scores

    @property
    def mean_score(self) -> float:
        """Mean of :attr:`dense_scores` (NaN without a path)."""
        ds = self.dense_scores
        return float(ds.mean()) if ds is not None and len(ds) else float("nan")

    def to_dict(self, joint_names: Sequence[str] | None = None) -> dict:
        d = {"success": self.success, "reason": self.reason, "failure": self.failure.value, "cost": self.cost,
             "path_length_rad": self.path_length, "mean_perception_score": self.mean_score,
             "query_ms": self.query_ms, "goal_index": self.goal_index, "n_waypoints": 0}
        if self.route:
            d["route"] = self.route
        if self.waypoints is not None:
            d["n_waypoints"] = int(len(self.waypoints))
            d["waypoints"] = np.round(self.waypoints, 5).tolist()
            if joint_names is not None:
                d["joint_names"] = list(joint_names)
        if self.trajectory is not None:
            d["duration_s"] = float(self.trajectory.times[-1])
        return d


@dataclass
class EscapeResult:
    """Outcome of the escape search from one query end (:meth:`.recovery.Recovery.escape`).

    ``configs`` (n, dof) are the configurations of the kept tree branches (the end itself excluded). ``tree`` lists
    their edges as (a, b) indices into ``configs`` (-1: the end), ``conn`` the connections (a, roadmap node id); the
    untracked knots (E, M, dof) and Eq. 1 sample positions (E, N) of both, in the a -> b direction, are the ones
    that were collision-checked (densely) and are the ones executed.
    """

    configs: torch.Tensor
    tree: list
    tree_knots: tuple
    conn: list
    conn_knots: tuple
    explored: int = 1  # configurations in the tree (the end included)
    tried: int = 0  # motions tried from the tree (extensions)
    seconds: float = 0.0
    base_reach: float = 0.0  # m: farthest base position of the tree from the end's

    @property
    def success(self) -> bool:
        return len(self.conn) > 0
