"""The common interface of every benchmark planner and the helpers the baselines share.

Every planner of ``psprm bench`` (the paper's baselines Post, Rejection, Manifold-line/-frustum, TrajOpt, RL-PPO and
the four PS-PRM variants, paper Table II) follows :class:`BenchPlanner`:

* ``prepare()`` does the preprocessing (roadmap build, RL training; nothing for the sampling-based baselines) and
  returns ``{"preprocess_s": float, ...}``;
* ``plan(start, goals, timeout_s)`` returns a :class:`~psprm_core.planning.psprm.PlanResult` whose ``dense`` holds the
  *executed* configurations about every ``resolution`` (0.05 motion-cost units) along a motion the differential-drive
  base can follow (rotate, translate, rotate between consecutive waypoints, :mod:`psprm_core.motion`). Bad problems
  (start or goal in collision, timeout, unreachable) give ``success=False`` with a ``reason``, never an exception.
* ``reset(query)`` (optional) returns the planner to the state ``prepare()`` left and numbers the next query, so that
  a query's result depends on the query alone (the bench calls it before every problem; PS-PRM restores its roadmap,
  the OMPL baselines number their per-query seeds).

Planner classes are registered in :data:`psprm_core.baselines.BASELINES` and constructed as
``cls(name=..., scene=..., targets=[...], robot=None, seed=0, **settings_overrides)``.

The helpers of :mod:`.context` (re-exported here) turn a waypoint list into such a result
(:meth:`~.context.PlanningContext.execute`); :class:`ContextPlanner` is the shared set-up of the sampling baselines
on a :class:`~.context.PlanningContext`.

Settings of the baselines are typed dataclasses read from ``config/planners/baselines.yaml``
(:func:`settings_from_yaml`): a ``common`` section applies to every baseline that has the field, one section per
baseline overrides it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Protocol, Sequence, Type, TypeVar, runtime_checkable

import numpy as np

from ..errors import ConfigError
from ..paths import config_dir
from ..planning.psprm import PlanResult
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .context import CameraFK, PlanningContext, aim_camera, failure, path_length

log = logging.getLogger(__name__)

__all__ = ["BenchPlanner", "PlanResult", "BaselineSettings", "PlanningContext", "settings_from_yaml",
           "baselines_yaml", "failure", "path_length", "aim_camera", "CameraFK"]


@runtime_checkable
class BenchPlanner(Protocol):
    """What ``psprm bench`` needs from a planner (one instance per scene, target set and robot)."""

    name: str

    def prepare(self) -> dict:
        """Preprocessing (roadmap build, RL training); returns ``{"preprocess_s": float, ...}``."""
        ...

    def plan(self, start: np.ndarray, goals: np.ndarray, timeout_s: float = 60.0) -> PlanResult:
        """Plan from ``start`` (dof,) to one of ``goals`` ((dof,) or (G, dof)); ``dense`` is the executed motion
        (configurations every ~0.05 motion-cost units). Never raises for bad problems."""
        ...

    # Optional: ``reset(query: int) -> None`` returns the planner to the state ``prepare()`` left (what queries
    # change: lazily verified edges, repaired roadmap nodes, query counters) and numbers the next query, so that a
    # query's result does not depend on the queries before it. The bench calls it before every problem (with the
    # problem's index) when a planner has it; planners whose queries change nothing need none.


@dataclass(frozen=True)
class BaselineSettings:
    """Settings shared by the sampling-based baselines (``config/planners/baselines.yaml``).

    Attributes
    ----------
    timeout_s : per-problem planning time cap (the paper capped its nursing runs at 60 s; the bench's default is
        10 s to stay affordable on 2 cores; ``psprm bench --timeout`` overrides it).
    resolution : spacing (motion-cost units) of the executed ``dense`` configurations and of collision checks.
    range : RRT-Connect's maximum extension per step (OMPL's ``range``; units of the real-vector state space).
    simplify : shortcut the RRT-Connect path (OMPL's path simplifier, which re-checks motions with our validator).
    frustum_margin, min_view_distance : visibility model (as in PS-PRM).
    aim_tolerance, aim_iters : Newton projection of the camera joints onto the line of sight (Post, tracking).
    view_slack : metres the target centroid may be outside the frustum along a validated motion (Rejection).
    constraint_tolerance : |h(q)| tolerance of the Manifold-* planners (metres; OMPL's tolerance for the frustum).
    angle_tolerance : OMPL's tolerance (rad) of the angular line-of-sight constraint (Manifold-line).
    projection_iters : OMPL's maximum Newton iterations per projection (Manifold-*).
    delta, lambda_ : ProjectedStateSpace step size and maximum geodesic stretch (Manifold-*).
    seed : seed of OMPL's RNG (``ou.RNG.setSeed``).
    """

    timeout_s: float = 10.0
    resolution: float = 0.05
    range: float = 1.0
    simplify: bool = True
    frustum_margin: float = 0.05
    min_view_distance: float = 0.5
    aim_tolerance: float = 0.02
    aim_iters: int = 20
    view_slack: float = 0.0
    constraint_tolerance: float = 0.02
    angle_tolerance: float = 0.005
    projection_iters: int = 15
    delta: float = 0.1
    lambda_: float = 2.0
    seed: int = 0


S = TypeVar("S")


def baselines_yaml() -> Path:
    """``config/planners/baselines.yaml``."""
    return config_dir() / "planners" / "baselines.yaml"


def settings_from_yaml(cls: Type[S], section: str, path: str | Path | None = None, **overrides) -> S:
    """A settings dataclass ``cls`` from the ``common`` section and the ``section`` of a YAML file.

    ``common`` fields apply only when ``cls`` has them (other planners' settings differ); fields in ``section`` must
    exist in ``cls``. Types follow the dataclass defaults (bool, int, float, str). ``overrides`` that are not None
    win. A missing file or section gives the defaults.
    """
    path = Path(path) if path is not None else baselines_yaml()
    names = {f.name: f for f in dataclasses.fields(cls)}
    kw: dict = {}
    if path.is_file():
        data = load_yaml(path)
        for sec, strict in (("common", False), (section, True)):
            if data.get(sec) is None:
                continue
            kw.update(dataclass_kwargs(cls, Fields(data[sec], str(path), sec), strict=strict, float_lo=None))
    kw.update({k: v for k, v in overrides.items() if v is not None and k in names})
    unknown = [k for k, v in overrides.items() if v is not None and k not in names]
    if unknown:
        raise ConfigError(str(path), section, f"unknown setting(s) {unknown} for {cls.__name__}")
    return cls(**kw)


def resolve_settings(cls: Type[S], section: str, settings: Optional[S] = None, seed: int = 0, **overrides) -> S:
    """A baseline's settings: ``settings`` as given (with ``overrides`` applied), or read from ``section`` of
    ``config/planners/baselines.yaml``; validated when the class has ``validate()``."""
    if settings is None:
        settings = settings_from_yaml(cls, section, seed=seed, **overrides)
    elif overrides:
        settings = dataclasses.replace(settings, **overrides)
    if hasattr(settings, "validate"):
        settings.validate()
    return settings


class ContextPlanner:
    """Shared set-up of the sampling baselines (post, rejection, manifold-*): :class:`BaselineSettings` from the
    ``section`` of ``config/planners/baselines.yaml`` (plus overrides) and a :class:`PlanningContext`. They need no
    preprocessing."""

    section = "common"

    def __init__(self, name: str, scene, targets: Sequence[str], robot=None, seed: int = 0, **overrides):
        self.name = name
        self.settings: BaselineSettings = settings_from_yaml(BaselineSettings, self.section, seed=seed, **overrides)
        s = self.settings
        self.ctx = PlanningContext(scene, targets, robot=robot, resolution=s.resolution,
                                   frustum_margin=s.frustum_margin, min_view_distance=s.min_view_distance)
        self.robot = self.ctx.robot
        self._queries = 0

    def prepare(self) -> dict:
        return {"preprocess_s": 0.0}

    def reset(self, query: int) -> None:
        """Number the next query ``query`` (its OMPL solve is seeded with ``settings.seed + query + 1`` by the
        baselines that vary their seed per query): a problem planned after ``reset(i)`` gives the same path whatever
        the instance planned before."""
        self._queries = int(query)

    def plan(self, start: np.ndarray, goals: np.ndarray, timeout_s: float = 60.0) -> PlanResult:
        """Check the problem (valid start and goals), keep the goals :meth:`_admissible` allows (a failure with its
        reason when it refuses), count the query and run the baseline's :meth:`_plan`."""
        t0 = time.perf_counter()
        start, goals, bad = self.ctx.check_problem(start, goals)
        if bad is not None:
            return bad
        ok, why = self._admissible(start, goals)
        if why:
            return failure(why, t0)
        self._queries += 1
        return self._plan(start, goals, goals[ok], timeout_s, t0)

    def _admissible(self, start: np.ndarray, goals: np.ndarray) -> tuple:
        """(mask of the goals a query may use, failure reason or ""). Baselines with a view requirement refuse a start
        or goals that do not meet it; by default everything is admissible."""
        return np.ones(len(goals), dtype=bool), ""

    def _plan(self, start: np.ndarray, goals: np.ndarray, ok_goals: np.ndarray, timeout_s: float,
              t0: float) -> PlanResult:
        raise NotImplementedError
