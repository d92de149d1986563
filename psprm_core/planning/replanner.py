"""Online replanning on a built PS-PRM roadmap (moving targets, obstacles and goals).

Only the work an update makes necessary is done:

* **target moved** (beyond ``target_move_m`` / ``target_turn_rad``): the roadmap's nodes are re-scored in one batch;
  edges at changed nodes get the Eq. 1 estimate from their two ends and are verified lazily: the search scores an
  edge's N interior configurations only when the edge lies on a candidate path, and re-searches until the returned
  path is fully verified (:meth:`PSPRM.rescore`, :func:`lazy_astar`);
* **obstacle moved** (beyond ``obstacle_move_m`` / ``obstacle_turn_rad``): the collision checker and the occlusion
  ray caster take the new box; a spatial index finds the roadmap nodes and edges within the robot's reach of it; the
  nodes are re-checked (colliding ones pruned), the edges re-checked densely when a search uses them
  (:meth:`PSPRM.invalidate_near`); nodes are re-scored (occlusion). When no goal is reachable any more, the roadmap is
  repaired by sampling new nodes around the moved obstacles and the start, keeping every valid node
  (:meth:`PSPRM.grow`);
* **obstacle turning** (``turning_hull``: turned about its vertical axis beyond ``obstacle_turn_rad`` from its first
  pose, as a person's body does): from then on it is planned against at every heading it can take
  (:meth:`~psprm_core.scene.Box.swept`), so that a robot passing or resting beside it is not swept by its next turn;
  a remaining path through the swept box replans (``turning_obstacle``). Paths are still judged against its real box;
  a start inside the swept box is moved out of it as one inside the collision padding is;
* **goal moved / several goals**: start and goals are reconnected and the goal with the best composite (Eq. 2) cost
  wins.

When to replan, what a plan is predicted to see and whether a new plan replaces the current one:
:mod:`.replan_judging`. Settings: :mod:`.replan_settings`. Every returned path is checked densely against the latest
obstacle poses before it is handed out.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from collections import deque
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError, PsprmError
from ..prediction import TargetPredictor, TurningWatch
from .execution import commit_time, splice
from .psprm import PSPRM, PlanResult
from .replan_judging import PlanJudging
from .replan_settings import ReplanSettings
from .results import Failure, Keep

log = logging.getLogger(__name__)


HISTORY = 1000  # replans kept in Replanner.history (a long-running node must not keep them all)


def _rotation_angle(qa: np.ndarray, qb: np.ndarray) -> float:
    """Angle (rad) between two orientations given as [x, y, z, w] quaternions."""
    d = abs(float(np.dot(qa / np.linalg.norm(qa), qb / np.linalg.norm(qb))))
    return 2.0 * math.acos(min(1.0, d))


def _pose(position, quat, what: str) -> tuple:
    p = np.asarray(position, dtype=float).reshape(-1)
    q = np.asarray([0.0, 0.0, 0.0, 1.0] if quat is None else quat, dtype=float).reshape(-1)
    if p.shape != (3,) or q.shape != (4,):
        raise PsprmError(f"{what}: position must have 3 values and quaternion 4 ([x, y, z, w])")
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise PsprmError(f"{what}: pose contains NaN/inf")
    n = np.linalg.norm(q)
    if n < 1e-9:
        raise PsprmError(f"{what}: quaternion has zero norm")
    return p, q / n


# what adopting a plan changes, restored by Replanner.withdraw
_ADOPTION_STATE = ("result", "_progress", "_t_along", "_goal_cfg", "_goal_since", "_switches", "goal_switches",
                   "_plan_score", "_pending", "_moved_obstacles", "adopted", "_first_plan")


def _snapshot(value):
    """A container (set, dict, array) copied, anything else (a PlanResult, a number) as it is."""
    return copy.copy(value) if isinstance(value, (set, dict, list, np.ndarray)) else value


class Replanner(PlanJudging):
    """Keeps a PS-PRM plan valid while the world changes.

    Parameters
    ----------
    planner : PSPRM
        A built (or loaded) roadmap; the replanner updates its scene, scores and graph in place.
    settings : ReplanSettings
    targets : names of the targets the planner keeps in view (default: the planner's ``targets`` attribute set by
        :func:`make_planner`, else every scene target). The visibility focus is their mean centre.
    """

    def __init__(self, planner: PSPRM, settings: ReplanSettings = ReplanSettings(),
                 targets: Optional[Sequence[str]] = None):
        if planner.graph is None:
            raise PsprmError("the replanner needs a built or loaded roadmap (call planner.build() or load())")
        self.planner = planner
        self.update_settings(settings)
        self.robot = planner.robot
        self.scene = planner.scene
        self.targets = list(targets or getattr(planner, "targets", None) or self.scene.target_names)
        # poses the roadmap's scores / collision state currently reflect
        self._target_ref = {t.name: (t.center.copy(), t.quat.copy()) for t in self.scene.targets}
        # where each target was when a move of it was last reported (update_target's steps), and where the roadmap
        # last saw the box of a target that is also an obstacle
        self._target_step_ref = dict(self._target_ref)
        self._target_box_ref = dict(self._target_ref)
        self._obstacle_ref = {b.name: (b.center.copy(), b.quat.copy()) for b in self.scene.obstacles}
        self.turning = TurningWatch(self.settings.obstacle_turn_rad, self.settings.turning_hold_s,
                                    self.settings.turning_in_place_m)
        self._declared_turning = {b.name for b in self.scene.obstacles if b.turning}  # the scene says so: always
        self._moved_obstacles: dict = {}  # name -> Box (new pose) since the last plan, for repair sampling
        self._score_stale = False
        self._rescore_all = False  # the roadmap was scored against another heading: every edge is estimated again
        self._pending: set = set()
        self.q: Optional[np.ndarray] = None
        self.goals: Optional[np.ndarray] = None
        self.result: Optional[PlanResult] = None
        self._progress = 0  # index into result.dense of the robot's position along the current path
        self._plan_score = float("nan")  # normalised predicted score of the current plan
        self._last_plan_time = -math.inf
        self._goal_cfg: Optional[np.ndarray] = None  # the current plan's goal configuration
        self._first_plan: Optional[tuple] = None  # the first plan for the goals (arrival budget): instant, duration
        self._goal_since = -math.inf  # when the current plan's goal was chosen (the clock of replan's ``now``)
        self._switches = 0  # switches between the candidate goals since they were set (goal_commit_growth)
        self._last_failed = False
        self._repaired_nodes = 0  # nodes added by repair so far (bounded by repair_budget_nodes)
        self.history: deque = deque(maxlen=HISTORY)  # the latest replans: reasons, timings, success
        self.replans = 0  # replans so far
        self.adopted = 0  # replans whose plan replaced the current one
        self.declined = 0  # replans that kept the current plan (kept)
        self.declined_by: dict = {}  # Keep -> how many of those kept it for that reason
        self.goal_switches = 0  # adopted plans that went to another of the candidate goals
        self._collides_cache: Optional[tuple] = None  # (result, progress, planner scene, remaining path collides)
        self._score_cache: Optional[tuple] = None  # ((result, progress, planner scene, normalized), path score)
        # target motion prediction: one predictor per target, fed by update_target; the latest pose stamp is the
        # prediction's "now"
        self.predictors = {t.name: TargetPredictor(self.settings.prediction, t.name) for t in self.scene.targets}
        self._stamp: Optional[float] = None
        self._t_along: Optional[float] = None  # the robot's time along the current trajectory (set_robot_state)
        self._planning_scene = None  # (scene, stamp) -> the scene the roadmap is scored with (predicted targets)
        self._new_plan_score: Optional[float] = None  # the keep decision's score of the replan's new plan
        self._along_cache: Optional[tuple] = None  # (result, progress, time along it) estimated from the progress
        self._adopted_over: Optional[tuple] = None  # (the latest adopted plan, the state it replaced): withdraw()
        self.withdrawn = 0  # adopted plans the caller withdrew (refused by its own check, or too late to splice)

    def update_settings(self, settings: Optional[ReplanSettings] = None, **changes) -> ReplanSettings:
        """Adopt new settings (``settings``, else the current ones with ``changes``; validated as they are built) and
        the query options the replans pass to the planner (:attr:`plan_options`: heuristic, smooth timing,
        shortcuts, route selection; the planner's own settings are left as they are). Returns the settings now in
        use."""
        new = dataclasses.replace(settings or self.settings, **changes)
        options = {"query.smooth_timing": new.smooth_timing, "query.shortcut": new.shortcut}
        if not new.route_selection:
            options["query.route_searches"] = ()
        if new.heuristic != "planner":
            options["query.heuristic"] = new.heuristic
        self.settings, self.plan_options = new, options
        for pr in getattr(self, "predictors", {}).values():
            pr.settings = new.prediction
        if hasattr(self, "turning"):
            t = self.turning
            t.turn_rad, t.hold_s, t.in_place_m = new.obstacle_turn_rad, new.turning_hold_s, new.turning_in_place_m
        return new

    # ---- inputs ------------------------------------------------------------------------------------------------------
    @staticmethod
    def _known(lookup, name: str) -> None:
        """Unknown target/obstacle names become a :class:`PsprmError` naming what the scene has."""
        try:
            lookup(name)
        except KeyError as e:
            raise PsprmError(str(e.args[0])) from None

    def set_robot_state(self, q, t_along: Optional[float] = None) -> None:
        """Current configuration (dof,) of the planning joints; advances the progress along the current path.
        ``t_along``: where the robot is along the current plan's trajectory (s from its start; the caller's
        measurement, e.g. :func:`~.execution.progress_time`), which lets a replan start from the committed state
        (:mod:`.execution`); None: the robot is taken to be at rest, and a replan starts where it is."""
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (self.robot.dof,) or not np.isfinite(q).all():
            raise PsprmError(f"robot state must be {self.robot.dof} finite values")
        if t_along is not None and not math.isfinite(t_along):
            raise PsprmError(f"time along the trajectory must be finite, got {t_along}")
        self.q = q
        self._t_along = None if t_along is None else max(0.0, float(t_along))
        if self.result is not None and self.result.dense is not None and len(self.result.dense):
            d = self.result.dense
            lo = self._progress
            hi = min(len(d), lo + 400)
            diff = d[lo:hi] - q
            if self.robot.mobile:
                diff[:, 2] = (diff[:, 2] + np.pi) % (2 * np.pi) - np.pi
            self._progress = lo + int(np.argmin(np.abs(diff).sum(1)))

    def set_goals(self, goals) -> None:
        """One goal configuration (dof,) or several candidates (G, dof): the best composite cost wins."""
        g = np.asarray(goals, dtype=float).reshape(-1, self.robot.dof) if np.size(goals) else None
        if g is None or not np.isfinite(g).all():
            raise PsprmError(f"goals must be finite configurations of {self.robot.dof} values")
        if self.goals is None or self.goals.shape != g.shape or not np.allclose(self.goals, g, atol=1e-6):
            self._pending.add("goal_changed")
            self._switches = 0
        self.goals = g

    def update_target(self, name: str, position, quat=None, stamp: Optional[float] = None) -> bool:
        """New pose of a target. Returns True when it moved beyond the thresholds (``target_move_m`` /
        ``target_turn_rad``) since the last pose that returned True: a target turning steadily reports one step per
        threshold, not every pose after the first step. The roadmap's scores are stale once the target is beyond the
        thresholds from where they were computed. A target that is also a collision box is re-checked near the
        roadmap like an obstacle: when its box moved beyond ``obstacle_move_m`` / ``obstacle_turn_rad`` from where the
        roadmap last saw it. ``stamp``: the pose's time (s; default: monotonic), for the target's motion prediction
        (:mod:`psprm_core.prediction`): a pose the predictor discards (a jump, time not advancing) still moves the
        target here, but not its prediction."""
        self._known(self.scene.target, name)
        p, q = _pose(position, quat, f"target '{name}'")
        stamp = time.monotonic() if stamp is None else float(stamp)
        self.predictors[name].add(stamp, p, q)
        if self._stamp is None or stamp > self._stamp:
            self._stamp = stamp
        self.scene = self.scene.with_target_pose(name, p, q)
        s = self.settings
        if self._beyond(p, q, self._target_ref[name], s.target_move_m, s.target_turn_rad):
            self._score_stale = True
            self._pending.add("target_moved")
        step = self._beyond(p, q, self._target_step_ref[name], s.target_move_m, s.target_turn_rad)
        if step:
            self._target_step_ref[name] = (p.copy(), q.copy())
        if self.scene.target(name).obstacle and self._beyond(p, q, self._target_box_ref[name], s.obstacle_move_m,
                                                              s.obstacle_turn_rad):
            ref = self._target_box_ref[name]  # where the roadmap last saw it (re-checked there)
            old_box = dataclasses.replace(self.scene.target(name), center=ref[0], quat=ref[1]).as_box()
            self.planner.set_scene(self.scene)
            self.planner.invalidate_near([self.scene.target(name).as_box()], old_boxes=[old_box])
            self._target_box_ref[name] = (p.copy(), q.copy())
            if self.remaining_path_collides():
                self._pending.add("collision")
                step = True
        return step

    @staticmethod
    def _beyond(p: np.ndarray, q: np.ndarray, ref: tuple, move_m: float, turn_rad: float) -> bool:
        return bool(np.linalg.norm(p - ref[0]) > move_m or _rotation_angle(q, ref[1]) > turn_rad)

    def update_obstacle(self, name: str, position, quat=None, stamp: Optional[float] = None) -> bool:
        """New pose of an obstacle; when it moved beyond the thresholds, or started or stopped turning in place
        (``turning_hull``, :class:`~psprm_core.prediction.TurningWatch`), the roadmap near it is re-checked now.
        Returns True in that case. ``stamp``: the pose's time (s; default: monotonic)."""
        self._known(self.scene.obstacle, name)
        p, q = _pose(position, quat, f"obstacle '{name}'")
        s = self.settings
        stamp = time.monotonic() if stamp is None else float(stamp)
        was = self.scene.obstacle(name).turning
        seen = self.turning.update(name, p, q, stamp)
        turning = name in self._declared_turning or (s.turning_hull and seen)
        self.scene = self.scene.with_obstacle_pose(name, p, q, turning=turning)
        if turning == was and not self._beyond(p, q, self._obstacle_ref[name], s.obstacle_move_m,
                                               s.obstacle_turn_rad):
            return False
        box = self.scene.obstacle(name)
        ref = self._obstacle_ref[name]  # where the roadmap last saw it (re-checked there; the planner's scene may
        # have been synced to a later pose below the thresholds by a trigger evaluation since)
        old_box = dataclasses.replace(box, center=ref[0], quat=ref[1], turning=was)
        self.planner.set_scene(self.scene)
        self.planner.invalidate_near([box], old_boxes=[old_box])
        self._obstacle_ref[name] = (p.copy(), q.copy())
        self._moved_obstacles[name] = box
        self._score_stale = True  # occlusion changed
        self._pending.add("obstacle_moved")
        if self.remaining_path_collides():
            self._pending.add("collision")
        elif turning and not was and self._remaining_enters(box):
            self._pending.add("turning_obstacle")  # the path passes where the box sweeps when it turns
        return True

    def _remaining_enters(self, box) -> bool:
        """The remaining path enters ``box`` as the planner checks it (a turning box swept, the padding)."""
        rem = self.remaining()
        return rem is not None and len(rem) > 0 and bool(
            self.planner.checker.env_hits(torch.as_tensor(rem, dtype=torch.float32), [box]).any())

    # ---- triggers ----------------------------------------------------------------------------------------------------
    def remaining(self) -> Optional[np.ndarray]:
        """The part of the current path still ahead of the robot (K, dof), or None."""
        if self.result is None or self.result.dense is None:
            return None
        return self.result.dense[self._progress:]

    def replan(self, now: Optional[float] = None, triggers: Sequence[str] = (),
               horizon_s: Optional[float] = None) -> PlanResult:
        """Plan to the best goal under the latest poses (never a colliding path).

        A robot in motion (its time along the current trajectory given to :meth:`set_robot_state`) replans from its
        committed state (:mod:`.execution`): the trajectory under way is kept up to its first rest instant at or after
        ``horizon_s`` from now (planning and delivery; default ``commit_horizon_s``), the new plan starts there, and
        the result's trajectory is the two spliced (:class:`~.execution.SplicedTrajectory`, time 0 = the robot's
        time along the old one, :attr:`PlanResult.start_offset_s`). A committed stretch that an obstacle has moved
        into fails the replan and drops the current plan: the caller must stop. A robot at rest replans from where
        it is.

        ``now``: the caller's clock for the replanning interval (default: monotonic). ``triggers``: why the caller
        replans (the reasons of :meth:`needs_replan`); when they are all :data:`~.replan_judging.VIEW_TRIGGERS` and
        ``keep_unless_better`` is on, a new plan no better than the current one is not adopted (the result has
        ``kept`` set, no trajectory, and the new plan as ``declined``; the module's docstring). Runs with torch's
        intra-op parallelism off, like a query (:meth:`~psprm_core.kernels.compute.Compute.one_thread`): its
        re-scoring batches are a few thousand rows, where a second thread gains little and can wait a scheduler slice
        on a busy machine."""
        with self.planner.compute.one_thread():
            return self._replan(now, tuple(triggers), horizon_s)

    def _commitment(self, horizon_s: Optional[float]) -> Optional[dict]:
        """Where a replan of the robot in motion starts (:mod:`.execution`), or None (at rest, or no trajectory):
        ``t_from`` (the robot's time along the current trajectory), ``t_commit``, ``q`` (the committed state, base
        heading wrapped), and ``prefix`` (the committed configurations every 20 ms, for the safety check)."""
        cur = self.result
        if not (self.settings.commit and cur is not None and cur.trajectory is not None and self._t_along is not None):
            return None
        traj = cur.trajectory
        T = float(traj.duration)
        t_from = min(self._t_along, T)
        if t_from >= T - 1e-6:
            return None
        h = self.settings.commit_horizon_s if horizon_s is None else max(0.0, float(horizon_s))
        t_c = commit_time(traj, t_from, h)
        ts = np.append(np.arange(t_from, t_c, 0.02), t_c)
        prefix = traj.evaluate(ts)[0]
        q = prefix[-1].copy()
        if self.robot.mobile:
            q[2] = (q[2] + np.pi) % (2 * np.pi) - np.pi
        return {"t_from": t_from, "t_commit": t_c, "q": q, "prefix": prefix}

    def _splice(self, res: PlanResult, commit: dict) -> PlanResult:
        """``res`` (planned from the committed state) joined to the trajectory under way (:func:`~.execution.splice`):
        a plan whose first knot is not the committed state (the planner re-aims the camera at a start) gets a move
        there first, timed and densified like its edges."""
        p = self.planner
        q_c = commit["q"]
        W, dense, traj = res.waypoints, res.dense, res.trajectory
        if np.abs(W[0] - q_c).max() > 1e-6:
            W = np.vstack([q_c, W])
            lead, _ = p.pipeline.ctx.backend.dense_path(np.ascontiguousarray(W[:2]))
            dense = np.vstack([lead, dense[1:]])
            traj = p.pipeline.trajectory.timed(W)
        cont = [i for i in range(self.robot.dof) if self.robot.continuous[i]]
        if self.robot.mobile and 2 not in cont:
            cont.append(2)
        try:
            spliced = splice(self.result.trajectory, commit["t_from"], commit["t_commit"], traj, cont)
        except InputError as exc:
            return PlanResult(False, f"internal: {exc}", Failure.INTERNAL)
        off = spliced.offset
        out = dataclasses.replace(res, waypoints=np.vstack([commit["prefix"][:1], W + off]),
                                  dense=np.vstack([commit["prefix"][:-1], dense + off]), trajectory=spliced,
                                  start_offset_s=commit["t_from"], committed_s=commit["t_commit"] - commit["t_from"])
        out.declined = None
        return out

    def _replan(self, now: Optional[float], triggers: tuple = (), horizon_s: Optional[float] = None) -> PlanResult:
        t0 = time.perf_counter()
        self._last_plan_time = time.monotonic() if now is None else now
        reasons = sorted(self._pending) if self.result is not None else ["no_plan"]
        if self.q is None:
            return PlanResult(False, "robot state unknown: call set_robot_state first", Failure.INVALID_INPUT)
        if self.goals is None:
            return PlanResult(False, "no goal: call set_goals first", Failure.INVALID_INPUT)
        p = self.planner
        self._sync_scene()
        info = {}
        if self._score_stale or self._rescore_all:
            info["rescore"] = p.rescore(tol=-1.0 if self._rescore_all else 1e-4)
            self._rescore_all = False
            for t in self.scene.targets:
                self._target_ref[t.name] = (t.center.copy(), t.quat.copy())
            self._score_stale = False
        commit = self._commitment(horizon_s)
        if commit is not None and bool(p.checker.check_unpadded(
                torch.as_tensor(commit["prefix"], dtype=torch.float32)).any()):
            # the motion the controllers already execute collides with the latest poses: no new plan can help
            log.warning("the committed motion collides with a moved obstacle: the robot must stop")
            self.result = None
            self._last_failed = True
            self.replans += 1
            res = PlanResult(False, "the committed motion collides with the latest obstacle poses: stop",
                             Failure.COMMITTED_COLLISION)
            res.query_ms = (time.perf_counter() - t0) * 1e3
            return res
        start = self.q if commit is None else commit["q"]
        self._new_plan_score = None
        res = self._plan_goals(self._last_plan_time, start)
        rounds = 0
        while (not res.success and res.failure is Failure.UNREACHABLE and rounds < self.settings.repair_rounds
               and self._repaired_nodes < self.settings.repair_budget_nodes):
            rounds += 1
            centers = ([b.center[:2] for b in self._moved_obstacles.values()] + [start[:2]]
                       + [g[:2] for g in self.goals])
            rng = np.random.default_rng(self.replans * 7 + rounds)
            for c in centers:
                got = p.grow(self.settings.repair_nodes, center=np.asarray(c), radius=self.settings.repair_radius_m,
                             rng=rng)
                self._repaired_nodes += got["added_nodes"]
                info.setdefault("repair", []).append(got)
            res = self._plan_goals(self._last_plan_time, start)
        if res.success and res.trajectory is not None and "collision" not in triggers \
                and "collision" not in self._pending:
            res = self._predicted_routes(res, start, commit)
        if commit is not None and res.success and res.trajectory is None:
            # the committed state is the goal: the trajectory under way already ends there
            res = PlanResult(True, "kept the current plan: the trajectory under way ends at the best goal",
                             goal_index=self.result.goal_index, cost=self.result.cost, kept=True,
                             kept_because=Keep.AT_GOAL)
        elif res.success:
            fresh = res  # judged from where it starts (the committed state in motion)
            if commit is not None:
                res = self._splice(res, commit)
            verdict = self._keep_current(fresh, triggers, commit) if res.success else None
            if verdict is not None and verdict.keep is not Keep.NONE:
                res = PlanResult(True, verdict.why, goal_index=self.result.goal_index, cost=self.result.cost,
                                 kept=True, declined=res, kept_because=verdict.keep)
                self._plan_score = verdict.current
            elif verdict is not None:
                res.adopted_because, res.judgement = verdict.adopt, verdict.why
        if res.success and not res.kept and res.dense is not None:
            # against the obstacles as they are: the planner's collision padding is a margin it plans with (a start
            # inside it is moved out of it by the path's first motion), not what makes a path unsafe
            check = res.dense if res.trajectory is None else np.vstack([res.dense, res.trajectory.positions])
            bad = p.checker.check_unpadded(torch.as_tensor(check, dtype=torch.float32)).cpu().numpy()
            if bad.any():  # defence in depth: the lazy checks make this unreachable; never hand out such a path
                log.error("replanned path collides at %d of %d dense configurations; rejected", bad.sum(), len(bad))
                res = PlanResult(False, "internal: path failed the final collision check", Failure.INTERNAL)
        ms = (time.perf_counter() - t0) * 1e3
        if res.kept:
            self._pending.clear()
            self._moved_obstacles.clear()
        res.query_ms = ms
        self.history.append({"reasons": reasons, "success": res.success, "reason": res.reason, "ms": ms,
                             "repair_rounds": rounds, "kept": res.kept, "kept_because": res.kept_because.value,
                             "spliced": commit is not None, "route": res.route,
                             "adopted_because": res.adopted_because.value, "judgement": res.judgement,
                             **{k: v for k, v in info.items() if k == "rescore"}})
        self.replans += 1
        self._last_failed = not res.success
        if res.kept:
            self.declined += 1
            self.declined_by[res.kept_because] = self.declined_by.get(res.kept_because, 0) + 1
            log.info("%s", res.reason)
        elif res.success:
            # the plan objects themselves (callers compare them by identity), copies of the containers adoption clears
            self._adopted_over = (res, {k: _snapshot(getattr(self, k)) for k in _ADOPTION_STATE})
            self.adopted += 1
            log.info("new plan adopted (%s)%s", res.adopted_because.value, res.judgement and f": {res.judgement}")
            self.result, self._progress = res, 0
            self._t_along = None  # until the caller reports the robot's progress along the new trajectory
            new_goal = self.goals[res.goal_index].copy() if 0 <= res.goal_index < len(self.goals) else None
            old_goal = self._goal_cfg
            if new_goal is None or old_goal is None or old_goal.shape != new_goal.shape or \
                    np.abs(old_goal - new_goal).max() >= 1e-6:
                if self._current_goal_mask() is not None:  # from one candidate goal to another
                    self._switches += 1
                    self.goal_switches += 1
                self._goal_since = self._last_plan_time
            self._goal_cfg = new_goal
            if ("no_plan" in reasons or "goal_changed" in reasons) and res.trajectory is not None:
                self._set_arrival_reference(res, start)
            # the hysteresis' reference: the adopted plan's predicted perception (outside the measured replan)
            if self._new_plan_score is not None:  # scored by the keep decision (from the commit on)
                self._plan_score = self._new_plan_score
            elif res.trajectory is not None:
                self._plan_score = self.predicted_score(res.trajectory)
            else:
                self._plan_score = float(np.mean(np.clip(res.dense_scores * getattr(p, "score_scale", 1.0), 0, 1)))
            self._pending.clear()
            self._moved_obstacles.clear()
        else:
            log.warning("replan failed: %s", res.reason)
            if self.result is not None and self.remaining_path_collides():
                self.result = None  # the old plan is no longer safe: the caller must stop
        return res

    def withdraw(self, res: PlanResult) -> bool:
        """Undo the adoption of ``res``, the latest replan's plan, when the caller could not hand it to the robot
        (its own final check refused it, or it was ready too late to splice onto the motion under way): the plan the
        robot executes stays the current one (the next replan commits along it), and the reasons that asked for the
        replan stay pending. False when ``res`` is not the latest adopted plan (nothing changes)."""
        if self._adopted_over is None or self._adopted_over[0] is not res or self.result is not res:
            return False
        for k, v in self._adopted_over[1].items():
            setattr(self, k, v)
        self._adopted_over = None
        self.withdrawn += 1
        return True

    def step(self) -> Optional[PlanResult]:
        """Replan when a trigger fires; returns the replan's result (``kept`` when the current plan stays) or None
        when nothing triggered."""
        why = self.needs_replan()
        return self.replan(triggers=why) if why else None
