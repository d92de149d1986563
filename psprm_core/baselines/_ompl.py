"""OMPL 2.0.1 glue for the sampling-based baselines (RRT-Connect, optionally on a ``ProjectedStateSpace``).

Avoids the known traps of OMPL's Python bindings: one goal state per solve, the RNG
seeded with ``ou.RNG.setSeed`` before anything samples, a pure real-vector ambient space (the base as x, y, theta
reals), Python validity checkers and motion validators only (no Python optimisation objective). OMPL's seed
generator is re-seeded before every solve (:func:`reseed`), so that a solve's random streams depend on its seed
alone, not on the solves the process ran before (a benchmark task gives the same path on any worker). The motion validator
checks the *differential-drive* motion between two states (rotate, translate, rotate;
:class:`~psprm_core.motion.DiffDriveMotion`), which is what the robot executes, instead of OMPL's straight line.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)


def _ompl():
    from ompl import base as ob, geometric as og, util as ou

    try:
        ou.setLogLevel(ou.LogLevel.LOG_WARN)
    except AttributeError:  # pragma: no cover - binding differences
        pass
    return ob, og, ou


def reseed(seed: int) -> None:
    """Seed OMPL's seed generator: the random number generators created after this (the next solve's planner,
    samplers and path simplifier) draw their seeds from it, so a solve that creates all of its own is a function of
    ``seed``. OMPL logs an error when it is re-seeded after its first use (generators that already exist keep their
    streams; a solve uses none of those), which is silenced here."""
    _, _, ou = _ompl()
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    try:
        ou.RNG.setSeed(int(seed) + 1)  # OMPL rejects seed 0
    finally:
        ou.setLogLevel(level)


class ActiveSpace:
    """The planning joints an OMPL problem moves (others fixed at a template), with bounds.

    Parameters
    ----------
    template : (dof,) full configuration supplying the fixed joints
    cols : indices of the planned joints (base x, y, theta first when present)
    lower, upper : (dof,) bounds of the full configuration
    """

    def __init__(self, template: np.ndarray, cols: np.ndarray, lower: np.ndarray, upper: np.ndarray):
        self.template = np.asarray(template, float).copy()
        self.cols = np.asarray(cols, dtype=np.int64)
        self.lower = np.asarray(lower, float)[self.cols]
        self.upper = np.asarray(upper, float)[self.cols]
        self.n = len(self.cols)

    def full(self, x) -> np.ndarray:
        q = self.template.copy()
        q[self.cols] = x
        return q

    def reduce(self, q: np.ndarray) -> np.ndarray:
        return np.asarray(q, float)[self.cols]

    def read(self, state) -> np.ndarray:
        return np.fromiter((state[i] for i in range(self.n)), dtype=float, count=self.n)


def rrt_connect(space: ActiveSpace, start: np.ndarray, goal: np.ndarray, state_valid: Callable[[np.ndarray], bool],
                motion_valid: Callable[[np.ndarray, np.ndarray], bool], timeout_s: float, range_: float,
                seed: int, simplify: bool = True, constraint=None, delta: float = 0.1, lambda_: float = 2.0,
                simplify_s: float = 1.0) -> tuple:
    """Plan with OMPL's RRT-Connect between two full configurations.

    Parameters
    ----------
    space : ActiveSpace
    start, goal : (dof,) full configurations (only ``space.cols`` are planned)
    state_valid, motion_valid : callables on full configurations
    constraint : optional ``ob.Constraint`` over the active joints; plans on a ``ProjectedStateSpace`` then
        (step ``delta``, maximum geodesic stretch ``lambda_``).

    Returns
    -------
    (waypoints (M, dof) or None, reason str, stats dict)
    """
    ob, og, ou = _ompl()
    reseed(seed)
    rv = ob.RealVectorStateSpace(space.n)
    b = ob.RealVectorBounds(space.n)
    for i in range(space.n):
        lo, hi = float(space.lower[i]), float(space.upper[i])
        if hi - lo < 1e-9:
            hi = lo + 1e-6
        b.setLow(i, lo)
        b.setHigh(i, hi)
    rv.setBounds(b)
    if constraint is not None:
        sp = ob.ProjectedStateSpace(rv, constraint)
        si = ob.ConstrainedSpaceInformation(sp)
        sp.setDelta(float(delta))
        sp.setLambda(float(lambda_))
    else:
        sp = rv
        si = ob.SpaceInformation(sp)
    counts = {"states": 0, "motions": 0}

    def valid(state) -> bool:
        counts["states"] += 1
        try:
            return bool(state_valid(space.full(space.read(state))))
        except Exception:  # never let a Python error escape into OMPL's C++ loop
            log.exception("state validity check failed")
            return False

    class _DriveValidator(ob.MotionValidator):
        def checkMotion(self, s1, s2) -> bool:  # noqa: N802 - OMPL's name
            counts["motions"] += 1
            try:
                return bool(motion_valid(space.full(space.read(s1)), space.full(space.read(s2))))
            except Exception:
                log.exception("motion check failed")
                return False

    si.setStateValidityChecker(valid)
    mv = _DriveValidator(si)
    si.setMotionValidator(mv)
    ss = og.SimpleSetup(si)

    def alloc(q):
        st = sp.allocState()
        x = space.reduce(q)
        if constraint is not None:
            st.copy([float(v) for v in x])
        else:
            for i, v in enumerate(x):
                st[i] = float(v)
        return st

    st, gl = alloc(start), alloc(goal)
    ss.setStartAndGoalStates(st, gl)
    planner = og.RRTConnect(si)
    planner.setRange(float(range_))
    ss.setPlanner(planner)
    t0 = time.perf_counter()
    try:
        ss.setup()
        counts["setup_s"] = time.perf_counter() - t0
        ss.solve(max(float(timeout_s) - counts["setup_s"], 1e-3))
        counts["solve_s"] = time.perf_counter() - t0 - counts["setup_s"]
    except Exception as exc:  # OMPL raises for e.g. start states that violate the constraint
        return None, f"OMPL error: {exc}", counts
    plan_s = time.perf_counter() - t0
    if not ss.haveExactSolutionPath():
        log.debug("RRT-Connect failed: %s", counts)
        counts["timed_out"] = plan_s >= timeout_s * 0.95
        reason = f"timeout ({timeout_s:.1f} s) without an exact solution" if counts["timed_out"] \
            else f"no solution ({ss.getLastPlannerStatus()})"
        return None, reason, counts
    if simplify:
        left = timeout_s - (time.perf_counter() - t0)
        if left > 0.05:
            try:
                ss.simplifySolution(min(simplify_s, left))
            except Exception:  # pragma: no cover
                log.exception("path simplification failed; keeping the raw path")
    path = ss.getSolutionPath()
    W = np.stack([space.full(space.read(path.getState(i))) for i in range(path.getStateCount())])
    W[0], W[-1] = start, goal
    counts["plan_s"] = time.perf_counter() - t0
    log.debug("RRT-Connect: %s", counts)
    # keep the OMPL objects alive until here (nanobind), then drop them
    del mv, ss, planner
    return W, "ok", counts


def nearest_goals(motion, start: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """Goals sorted by differential-drive motion cost from ``start`` (OMPL is given one goal at a time)."""
    import torch

    if len(goals) == 1:
        return goals
    d = motion.distance(torch.as_tensor(start[None], dtype=torch.float64),
                        torch.as_tensor(goals, dtype=torch.float64)).numpy()
    return goals[np.argsort(d)]


def plan_to_goals(space_for: Callable[[np.ndarray], ActiveSpace], start: np.ndarray, goals: np.ndarray,
                  timeout_s: float, motion, **kw) -> tuple:
    """Try the goals nearest-first with one RRT-Connect solve each, sharing the time budget.

    Returns (waypoints or None, reason, goal index into ``goals`` or -1, stats); ``stats["timed_out"]`` when the
    time budget ended the search."""
    t0 = time.perf_counter()
    order = nearest_goals(motion, start, goals)
    reason, stats = "no goal", {}
    for g in order:
        left = timeout_s - (time.perf_counter() - t0)
        if left <= 0:
            reason, stats = f"timeout ({timeout_s:.1f} s)", {"timed_out": True}
            break
        W, reason, stats = rrt_connect(space_for(g), start, g, timeout_s=left, **kw)
        if W is not None:
            idx = int(np.nonzero(np.all(np.isclose(goals, g), axis=1))[0][0])
            return W, reason, idx, stats
    return None, reason, -1, stats


def ompl_available() -> bool:
    try:
        _ompl()
        return True
    except ImportError:  # pragma: no cover
        return False
