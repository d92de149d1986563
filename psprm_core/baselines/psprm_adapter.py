"""Thin :class:`~psprm_core.baselines.base.BenchPlanner` adapter around the four PS-PRM variants (paper Alg. 1).

``prepare()`` builds the roadmap (its time is the preprocessing time of Table II: oracle scoring for ``psprm-*``,
the surrogate for ``neural-psprm-*``); ``plan()`` answers one query with :meth:`PSPRM.plan`; ``reset()`` returns the
planner to the roadmap ``prepare()`` built (queries change it: lazily verified edge weights, repair nodes that are
kept, escape and repair counters), so that a query's path does not depend on the queries answered before it.
"""

from __future__ import annotations

import copy
import logging
import time
from typing import Optional, Sequence

import numpy as np

from ..planning.factory import make_planner
from ..planning.psprm import PlanResult
from ..planning.results import Failure
from .base import failure, path_length

log = logging.getLogger(__name__)


class PSPRMBenchPlanner:
    """PS-PRM variant ``name`` (``psprm-line``, ``psprm-frustum``, ``neural-psprm-line``, ``neural-psprm-frustum``).

    Parameters
    ----------
    name, scene, targets, robot, seed : as for every benchmark planner.
    n_nodes : roadmap size (default: ``config/planners/psprm.yaml``).
    **overrides : other :class:`~psprm_core.planning.psprm.PSPRMSettings` fields.
    """

    def __init__(self, name: str, scene, targets: Sequence[str], robot=None, seed: int = 0,
                 n_nodes: Optional[int] = None, **overrides):
        self.name = name
        self.targets = list(targets)
        self.planner = make_planner(name, scene, self.targets, robot=robot,
                                    options={"roadmap.n_nodes": n_nodes, "seed": seed, **overrides})
        self.robot = self.planner.robot
        self._built = False
        self._snapshot: Optional[dict] = None  # the planner's state after prepare() (see reset)
        self._fresh = True  # no query since prepare() or the last reset

    #: PS-PRM attributes that queries do not change (shared by the snapshot, never copied): models, geometry, settings
    SHARED = ("robot", "scene", "scorer", "checker", "motion", "constraint", "settings", "device", "dtype")

    def _shared_memo(self) -> dict:
        memo = {}
        for k in self.SHARED:
            if k in vars(self.planner):
                v = vars(self.planner)[k]
                memo[id(v)] = v
        return memo

    def _state(self) -> dict:
        return {k: v for k, v in vars(self.planner).items() if k not in self.SHARED}

    def prepare(self) -> dict:
        t0 = time.perf_counter()
        stats = self.planner.build()
        self._built = bool(stats.get("success", True))
        if self._built:  # compiling the query kernels is preprocessing too, not the first problem's planning time
            stats["warm_up_s"] = self.planner.warm_up()
            t1 = time.perf_counter()
            self._snapshot = copy.deepcopy(self._state(), self._shared_memo())
            stats["snapshot_s"] = time.perf_counter() - t1
        self._fresh = True
        return {"preprocess_s": time.perf_counter() - t0, **{k: v for k, v in stats.items()
                                                              if isinstance(v, (int, float, bool, str))}}

    def reset(self, query: int = 0) -> None:
        """Return to the roadmap and planner state ``prepare()`` left (a deep copy of the snapshot taken then; the
        models, scene and settings are shared). ``query`` is accepted for the bench's interface (PS-PRM's queries
        are deterministic given the roadmap)."""
        if self._snapshot is None or self._fresh:
            return
        vars(self.planner).update(copy.deepcopy(self._snapshot, self._shared_memo()))
        self._fresh = True

    @property
    def built(self) -> bool:
        """Whether ``prepare()`` built a roadmap."""
        return self._built

    def queried(self) -> None:
        """Note a query made on :attr:`planner` directly (the next :meth:`reset` restores the snapshot)."""
        self._fresh = False

    def plan(self, start: np.ndarray, goals: np.ndarray, timeout_s: float = 60.0) -> PlanResult:
        t0 = time.perf_counter()
        if not self._built:
            return failure("roadmap not built", t0, Failure.NOT_BUILT)
        self._fresh = False
        res = self.planner.plan(start, goals, timing=False)
        if res.success and res.dense is not None:
            res.path_length = path_length(self.planner.motion, res.dense)
        if res.success and (time.perf_counter() - t0) > timeout_s:
            log.info("%s query exceeded the %.1f s cap", self.name, timeout_s)
            return failure(f"timeout ({timeout_s:.1f} s)", t0, Failure.TIMEOUT)
        return res
