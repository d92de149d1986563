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
* **goal moved / several goals**: start and goals are reconnected and the goal with the best composite (Eq. 2) cost
  wins.

Triggers (:meth:`Replanner.needs_replan`): the remaining path collides with the latest obstacle poses; the predicted
mean perception score along the remaining path is below ``score_min`` or has dropped by more than ``score_drop``
since the plan; the target or an obstacle moved beyond its threshold; the goal changed. Every returned path is
checked densely against the latest obstacle poses before it is handed out.

A replan that only the view triggered (:data:`VIEW_TRIGGERS`) replaces the current plan only when it is better for
the robot: it sees more along its path (``keep_score_margin``, normalised as c_p in Eq. 1) or it is shorter
(``keep_length_margin`` of the remaining path's motion cost), or it leads to another goal (which the goal hysteresis
allowed). Otherwise the robot keeps driving its trajectory (:attr:`PlanResult.kept`): a new trajectory starts from
rest, and a person turning away every few seconds would otherwise restart the robot every second towards views
that are gone before it gets there.
"""

from __future__ import annotations

import logging
import math
import time
import dataclasses
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from .. import fastpath
from ..errors import PsprmError
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .psprm import PSPRM, PlanResult

log = logging.getLogger(__name__)


HEURISTICS = ("exact", "hop", "planner")
#: triggers that say only that the view changed (the current path is still collision-free and leads to the goal)
VIEW_TRIGGERS = frozenset({"score_low", "score_drop", "score_low_retry", "target_moved"})
HISTORY = 1000  # replans kept in Replanner.history (a long-running node must not keep them all)


@dataclass(frozen=True)
class ReplanSettings:
    """Replanning triggers and repair (``config/planners/replan.yaml``)."""

    target_move_m: float = 0.05  # target translation that counts as a move (re-score, replan)
    target_turn_rad: float = 0.15  # target rotation that counts as a move
    obstacle_move_m: float = 0.03  # obstacle translation that counts as a move (re-check, replan)
    obstacle_turn_rad: float = 0.1
    focus_move_m: float = 0.25  # the visibility focus follows a target that moved further than this
    replan_on_move: bool = False  # a target/obstacle move alone triggers a replan (default: it triggers the score and
    # collision checks, and those decide)
    score_min: float = 0.1  # replan when the normalised predicted mean score along the remaining path falls below this
    # (and, for a plan made below it, whenever the target moved: another route may see it now)
    score_drop: float = 0.15  # ... or falls by more than this since the plan was made (scores normalised as in Eq. 1)
    goal_switch_margin: float = 0.2  # switch to another goal only when it is cheaper by this fraction of the current
    # plan's cost (a terminal cost on the other goals, one search)
    final_approach_m: float = 1.0  # no score-triggered replan once the remaining base path is shorter than this (m):
    # the robot finishes its approach; a collision or a new goal still replans
    goal_commit_s: float = 10.0  # keep a chosen goal this long (s, the caller's clock) before another may replace it;
    # earlier only when no path reaches it (0: off). A person turning back and forth makes the cheapest goal alternate
    # faster than the robot can drive to either
    goal_commit_growth: float = 2.0  # each switch between the candidate goals multiplies the next commitment by this
    # (1: constant); a new goal set starts again at goal_commit_s. Bounds the switching: a person who keeps turning
    # cannot keep the robot away from both goals
    keep_unless_better: bool = True  # a replan triggered by the view alone (VIEW_TRIGGERS) is adopted only when it
    # sees more (keep_score_margin) or is shorter (keep_length_margin) than the remaining path, or goes to another goal
    keep_score_margin: float = 0.05  # normalised mean score along the path (c_p, Eq. 1) a new plan must add
    keep_length_margin: float = 0.1  # fraction of the remaining path's motion cost a new plan must save
    min_interval_s: float = 1.0  # at most one replan per interval, except when the path collides or the goal changed
    score_samples: int = 200  # configurations of the remaining path scored for the score trigger
    repair_rounds: int = 2  # roadmap repair attempts when no goal is reachable
    repair_nodes: int = 150  # nodes sampled per repair round
    repair_radius_m: float = 1.5  # around the moved obstacles and the start
    repair_budget_nodes: int = 1500  # at most this many nodes added by repair over the replanner's life
    heuristic: str = "exact"  # A* heuristic of the replans: "exact" (cost-to-go from one compiled Dijkstra over the
    # current weights; every update changes weights, and A* then expands little more than the path), "hop" (Eq. 3,
    # the paper's), or "planner" (keep the planner's setting)
    smooth_timing: bool = True  # replanned trajectories pass the knots of a base phase without stopping: about a
    # third shorter to execute, for about +25 ms per replan (per-phase TOPP-RA); within the latency goals
    # (docs/benchmarks.md, "Replanning latency")
    shortcut: bool = False  # perception-preserving shortcuts of replanned paths (PSPRMSettings.query.shortcut): off, since
    # checking the candidate shortcuts costs tens of ms per replan
    route_selection: bool = False  # the planner's route selection (PSPRMSettings.query.route_searches) in replans: off,
    # since every extra search adds a search's time to each replan

    def __post_init__(self):
        if not (self.goal_commit_growth >= 1.0 and math.isfinite(self.goal_commit_growth)):
            raise PsprmError(f"goal_commit_growth must be a finite factor >= 1, got {self.goal_commit_growth}")
        if self.heuristic not in HEURISTICS:
            raise PsprmError(f"replan heuristic must be one of {', '.join(HEURISTICS)}, got {self.heuristic!r}")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "ReplanSettings":
        return cls(**dataclass_kwargs(cls, Fields(load_yaml(path), str(path))))


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


class Replanner:
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
        self._moved_obstacles: dict = {}  # name -> Box (new pose) since the last plan, for repair sampling
        self._score_stale = False
        self._pending: set = set()
        self.q: Optional[np.ndarray] = None
        self.goals: Optional[np.ndarray] = None
        self.result: Optional[PlanResult] = None
        self._progress = 0  # index into result.dense of the robot's position along the current path
        self._plan_score = float("nan")  # normalised predicted score of the current plan
        self._last_plan_time = -math.inf
        self._goal_cfg: Optional[np.ndarray] = None  # the current plan's goal configuration
        self._goal_since = -math.inf  # when the current plan's goal was chosen (the clock of replan's ``now``)
        self._switches = 0  # switches between the candidate goals since they were set (goal_commit_growth)
        self._last_failed = False
        self._repaired_nodes = 0  # nodes added by repair so far (bounded by repair_budget_nodes)
        self.history: deque = deque(maxlen=HISTORY)  # the latest replans: reasons, timings, success
        self.replans = 0  # replans so far
        self._collides_cache: Optional[tuple] = None  # (result, progress, planner scene, remaining path collides)
        self._score_cache: Optional[tuple] = None  # ((result, progress, planner scene, normalized), path score)

    def update_settings(self, settings: Optional[ReplanSettings] = None, **changes) -> ReplanSettings:
        """Adopt new settings (``settings``, else the current ones with ``changes``; validated as they are built) and
        the query options the replans pass to the planner (:attr:`plan_options`: heuristic, smooth timing,
        shortcuts, route selection; the planner's own settings are left as they are). Returns the settings now in
        use."""
        new = dataclasses.replace(settings or self.settings, **changes)
        options = {"smooth_timing": new.smooth_timing, "shortcut": new.shortcut}
        if not new.route_selection:
            options["route_searches"] = ""
        if new.heuristic != "planner":
            options["heuristic"] = new.heuristic
        self.settings, self.plan_options = new, options
        return new

    # ---- inputs ------------------------------------------------------------------------------------------------------
    @staticmethod
    def _known(lookup, name: str) -> None:
        """Unknown target/obstacle names become a :class:`PsprmError` naming what the scene has."""
        try:
            lookup(name)
        except KeyError as e:
            raise PsprmError(str(e.args[0])) from None

    def set_robot_state(self, q) -> None:
        """Current configuration (dof,) of the planning joints; advances the progress along the current path."""
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (self.robot.dof,) or not np.isfinite(q).all():
            raise PsprmError(f"robot state must be {self.robot.dof} finite values")
        self.q = q
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

    def update_target(self, name: str, position, quat=None) -> bool:
        """New pose of a target. Returns True when it moved beyond the thresholds (``target_move_m`` /
        ``target_turn_rad``) since the last pose that returned True: a target turning steadily reports one step per
        threshold, not every pose after the first step. The roadmap's scores are stale once the target is beyond the
        thresholds from where they were computed. A target that is also a collision box is re-checked near the
        roadmap like an obstacle: when its box moved beyond ``obstacle_move_m`` / ``obstacle_turn_rad`` from where the
        roadmap last saw it."""
        self._known(self.scene.target, name)
        p, q = _pose(position, quat, f"target '{name}'")
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

    def update_obstacle(self, name: str, position, quat=None) -> bool:
        """New pose of an obstacle; when it moved beyond the thresholds the roadmap near it is re-checked now.
        Returns True in that case."""
        self._known(self.scene.obstacle, name)
        p, q = _pose(position, quat, f"obstacle '{name}'")
        self.scene = self.scene.with_obstacle_pose(name, p, q)
        if not self._beyond(p, q, self._obstacle_ref[name], self.settings.obstacle_move_m,
                            self.settings.obstacle_turn_rad):
            return False
        box = self.scene.obstacle(name)
        ref = self._obstacle_ref[name]  # where the roadmap last saw it (re-checked there; the planner's scene may
        # have been synced to a later pose below the thresholds by a trigger evaluation since)
        old_box = dataclasses.replace(box, center=ref[0], quat=ref[1])
        self.planner.set_scene(self.scene)
        self.planner.invalidate_near([box], old_boxes=[old_box])
        self._obstacle_ref[name] = (p.copy(), q.copy())
        self._moved_obstacles[name] = box
        self._score_stale = True  # occlusion changed
        self._pending.add("obstacle_moved")
        if self.remaining_path_collides():
            self._pending.add("collision")
        return True

    # ---- triggers ----------------------------------------------------------------------------------------------------
    def remaining(self) -> Optional[np.ndarray]:
        """The part of the current path still ahead of the robot (K, dof), or None."""
        if self.result is None or self.result.dense is None:
            return None
        return self.result.dense[self._progress:]

    def remaining_path_collides(self) -> bool:
        """The remaining path collides with the obstacle poses the planner holds (not with their padding). Cached per
        (plan, progress, planner scene): an update and the trigger check that follows it in the same cycle pay for one
        check."""
        rem = self.remaining()
        if rem is None or len(rem) == 0:
            return False
        c = self._collides_cache
        if c is not None and c[0] is self.result and c[1] == self._progress and c[2] is self.planner.scene:
            return c[3]
        # the obstacles as they are (a path that starts inside the collision padding, moving out of it, is sound)
        hit = bool(self.planner.checker.check_unpadded(torch.as_tensor(rem, dtype=torch.float32)).any())
        self._collides_cache = (self.result, self._progress, self.planner.scene, hit)
        return hit

    def path_score(self, normalized: bool = False) -> float:
        """Predicted mean perception score along the remaining path under the latest target/obstacle poses
        (``normalized``: divided by the roadmap's 99th-percentile node score and clipped to [0, 1], as c_p in Eq. 1).
        Cached per (plan, progress, planner scene): the trigger evaluation and the keep decision of the replan that
        follows it in the same cycle score the path once."""
        rem = self.remaining()
        if rem is None or len(rem) == 0:
            return float("nan")
        self._sync_scene()
        key = (self.result, self._progress, self.planner.scene, normalized)
        c = self._score_cache
        if c is not None and all(a is b for a, b in zip(c[0][:3], key[:3])) and c[0][3] == normalized:
            return c[1]
        step = max(1, len(rem) // max(1, self.settings.score_samples))
        q = torch.as_tensor(rem[::step], dtype=torch.float32)
        sc = self.planner.score_configs(q)
        out = float((self.planner.normalized_scores(sc) if normalized else sc).mean())
        self._score_cache = (key, out)
        return out

    def _remaining_base_length(self) -> float:
        """Length (m) of the base's path still ahead (inf for a robot without a mobile base)."""
        rem = self.remaining()
        if rem is None or not self.robot.mobile:
            return math.inf
        return float(np.linalg.norm(np.diff(rem[:, :2], axis=0), axis=1).sum()) if len(rem) > 1 else 0.0

    def needs_replan(self, now: Optional[float] = None) -> list:
        """Reasons to replan now ([] = keep the current plan). ``now``: the caller's clock (default: monotonic);
        apart from a collision or a goal change, at most one replan per ``min_interval_s``."""
        if self.goals is None:
            return []
        now = time.monotonic() if now is None else now
        since = now - self._last_plan_time
        if self._last_failed and since < self.settings.min_interval_s:
            return []  # a failed replan is retried at most once per interval
        if self.result is None:
            return ["no_plan"]
        reasons = []
        if "collision" in self._pending or self.remaining_path_collides():
            reasons.append("collision")
        if "goal_changed" in self._pending:
            reasons.append("goal_changed")
        if not reasons and since < self.settings.min_interval_s:
            return []
        if self.settings.replan_on_move:
            reasons += [r for r in ("target_moved", "obstacle_moved") if r in self._pending]
        if not reasons and (self._pending & {"target_moved", "obstacle_moved"} or self._score_stale) \
                and self._remaining_base_length() >= self.settings.final_approach_m:
            # (scored only when it decides: with a reason already, the replan happens anyway)
            sc = self.path_score(normalized=True)
            if sc < self.settings.score_min <= self._plan_score:  # fell below
                reasons.append("score_low")
            elif self._plan_score - sc > self.settings.score_drop:
                reasons.append("score_drop")
            elif (self._plan_score < self.settings.score_min and sc < self.settings.score_min
                  and "target_moved" in self._pending):
                # a plan made while nothing could be seen: look again once the target has moved (another route may
                # see it now), at most once per min_interval_s
                reasons.append("score_low_retry")
        return reasons

    # ---- planning ----------------------------------------------------------------------------------------------------
    def _sync_scene(self) -> None:
        """Push the latest scene to the planner (scorer occluders, collision boxes, focus)."""
        p = self.planner
        if p.scene is not self.scene:
            p.set_scene(self.scene)
            focus = np.mean([self.scene.target(t).center for t in self.targets], axis=0)
            if np.linalg.norm(focus - p.constraint.target.numpy()) > self.settings.focus_move_m:
                p.set_focus(focus)

    def replan(self, now: Optional[float] = None, triggers: Sequence[str] = ()) -> PlanResult:
        """Plan from the robot's state to the best goal under the latest poses (never a colliding path).
        ``now``: the caller's clock for the replanning interval (default: monotonic). ``triggers``: why the caller
        replans (the reasons of :meth:`needs_replan`); when they are all :data:`VIEW_TRIGGERS` and
        ``keep_unless_better`` is on, a new plan no better than the current one is not adopted (the result has
        ``kept`` set, no trajectory, and the new plan as ``declined``; the module's docstring). Runs with torch's
        intra-op parallelism off, like a query (:func:`~psprm_core.fastpath.one_thread`): its re-scoring batches are a
        few thousand rows, where a second thread gains little and can wait a scheduler slice on a busy machine."""
        with fastpath.one_thread(self.planner.device):
            return self._replan(now, tuple(triggers))

    def _replan(self, now: Optional[float], triggers: tuple = ()) -> PlanResult:
        t0 = time.perf_counter()
        self._last_plan_time = time.monotonic() if now is None else now
        reasons = sorted(self._pending) if self.result is not None else ["no_plan"]
        if self.q is None:
            return PlanResult(False, "robot state unknown: call set_robot_state first")
        if self.goals is None:
            return PlanResult(False, "no goal: call set_goals first")
        p = self.planner
        self._sync_scene()
        info = {}
        if self._score_stale:
            info["rescore"] = p.rescore()
            for t in self.scene.targets:
                self._target_ref[t.name] = (t.center.copy(), t.quat.copy())
            self._score_stale = False
        res = self._plan_goals(self._last_plan_time)
        rounds = 0
        while (not res.success and "reachable" in res.reason and rounds < self.settings.repair_rounds
               and self._repaired_nodes < self.settings.repair_budget_nodes):
            rounds += 1
            centers = ([b.center[:2] for b in self._moved_obstacles.values()] + [self.q[:2]]
                       + [g[:2] for g in self.goals])
            rng = np.random.default_rng(self.replans * 7 + rounds)
            for c in centers:
                got = p.grow(self.settings.repair_nodes, center=np.asarray(c), radius=self.settings.repair_radius_m,
                             rng=rng)
                self._repaired_nodes += got["added_nodes"]
                info.setdefault("repair", []).append(got)
            res = self._plan_goals(self._last_plan_time)
        if res.success and res.dense is not None:
            # against the obstacles as they are: the planner's collision padding is a margin it plans with (a start
            # inside it is moved out of it by the path's first motion), not what makes a path unsafe
            bad = p.checker.check_unpadded(torch.as_tensor(res.dense, dtype=torch.float32)).cpu().numpy()
            if bad.any():  # defence in depth: the lazy checks make this unreachable; never hand out such a path
                log.error("replanned path collides at %d of %d dense configurations; rejected", bad.sum(), len(bad))
                res = PlanResult(False, "internal: path failed the final collision check")
        plan_score = None
        if res.success:  # the plan's score feeds the hysteresis: scored inside the measured replan
            plan_score = float(np.mean(np.clip(res.dense_scores * getattr(p, "score_scale", 1.0), 0, 1)))
        kept = self._keep_current(res, plan_score, triggers) if res.success else None
        ms = (time.perf_counter() - t0) * 1e3
        if kept is not None:
            why, current_score = kept
            res = PlanResult(True, why, goal_index=self.result.goal_index, cost=self.result.cost, kept=True,
                             declined=res)
            self._plan_score = current_score  # the current plan, valued under the latest poses
            self._pending.clear()
            self._moved_obstacles.clear()
        res.query_ms = ms
        self.history.append({"reasons": reasons, "success": res.success, "reason": res.reason, "ms": ms,
                             "repair_rounds": rounds, "kept": res.kept,
                             **{k: v for k, v in info.items() if k == "rescore"}})
        self.replans += 1
        self._last_failed = not res.success
        if res.kept:
            log.info("%s", res.reason)
        elif res.success:
            self.result, self._progress = res, 0
            new_goal = self.goals[res.goal_index].copy() if 0 <= res.goal_index < len(self.goals) else None
            old_goal = self._goal_cfg
            if new_goal is None or old_goal is None or old_goal.shape != new_goal.shape or \
                    np.abs(old_goal - new_goal).max() >= 1e-6:
                if self._current_goal_mask() is not None:  # from one candidate goal to another
                    self._switches += 1
                self._goal_since = self._last_plan_time
            self._goal_cfg = new_goal
            self._plan_score = plan_score
            self._pending.clear()
            self._moved_obstacles.clear()
        else:
            log.warning("replan failed: %s", res.reason)
            if self.result is not None and self.remaining_path_collides():
                self.result = None  # the old plan is no longer safe: the caller must stop
        return res

    def _keep_current(self, res: PlanResult, plan_score: float, triggers: tuple) -> Optional[tuple]:
        """(why, the remaining path's normalised score) when the new plan ``res`` should not replace the current one
        (the module's docstring), else None."""
        s = self.settings
        if not (s.keep_unless_better and triggers and set(triggers) <= VIEW_TRIGGERS) \
                or "goal_changed" in self._pending:
            return None
        rem = self.remaining()
        if self.result is None or rem is None or len(rem) < 2 or res.dense is None or self._goal_cfg is None:
            return None
        if not 0 <= res.goal_index < len(self.goals) or self.goals[res.goal_index].shape != self._goal_cfg.shape \
                or np.abs(self.goals[res.goal_index] - self._goal_cfg).max() >= 1e-6:
            return None  # another goal: the goal hysteresis has decided
        if self.remaining_path_collides():
            return None
        current = self.path_score(normalized=True)
        motion = self.planner.motion
        rem_len, new_len = (float(motion.distance(q[:-1], q[1:]).sum()) if len(q) > 1 else 0.0
                            for q in (torch.as_tensor(np.asarray(d), dtype=torch.float64) for d in (rem, res.dense)))
        if plan_score > current + s.keep_score_margin or new_len < (1.0 - s.keep_length_margin) * rem_len:
            return None
        return (f"kept the current plan: the new one sees {plan_score:.3f} along {new_len:.2f} against the remaining "
                f"path's {current:.3f} along {rem_len:.2f}", current)

    def _committed_goal(self, now: float) -> Optional[np.ndarray]:
        """Mask (G,) of the current plan's goal while it is committed (``goal_commit_s`` times
        ``goal_commit_growth`` to the power of the switches so far), else None."""
        window = self.settings.goal_commit_s * self.settings.goal_commit_growth ** self._switches
        if (self.settings.goal_commit_s <= 0 or self.result is None or self.goals is None or len(self.goals) < 2
                or now - self._goal_since >= window):
            return None
        return self._current_goal_mask()

    def _current_goal_mask(self) -> Optional[np.ndarray]:
        """Mask (G,) of the candidate goals equal to the current plan's goal; None if none is."""
        cur = self._goal_cfg
        if cur is None or self.goals is None or cur.shape != self.goals.shape[1:]:
            return None
        same = np.abs(self.goals - cur).max(1) < 1e-6
        return same if same.any() else None

    def _plan_goals(self, now: float) -> PlanResult:
        """One search over the candidate goals: only the committed goal while its commitment lasts (all of them if no
        path reaches it), otherwise all with the switching margin (:meth:`_goal_costs`)."""
        p = self.planner
        keep = self._committed_goal(now)
        if keep is not None:
            res = p.plan(self.q, self.goals[keep], options=self.plan_options)
            if res.success:
                res.goal_index = int(np.nonzero(keep)[0][res.goal_index]) if res.goal_index >= 0 else -1
                return res
        return p.plan(self.q, self.goals, goal_costs=self._goal_costs(), options=self.plan_options)

    def _goal_costs(self) -> Optional[np.ndarray]:
        """Goal hysteresis as terminal costs (one search): with several candidate goals, every goal but the current
        plan's costs ``goal_switch_margin`` x the current plan's cost (Eq. 2 units) extra, so the robot switches goals
        only when another one is cheaper by more than that margin (a person turning back and forth must not make it
        oscillate between goals). None when there is nothing to keep."""
        if self.result is None or self.goals is None or len(self.goals) < 2 or self.settings.goal_switch_margin <= 0:
            return None
        same = self._current_goal_mask()
        if same is None or not np.isfinite(self.result.cost):
            return None
        return np.where(same, 0.0, self.settings.goal_switch_margin * max(self.result.cost, 0.0))

    def step(self) -> Optional[PlanResult]:
        """Replan when a trigger fires; returns the replan's result (``kept`` when the current plan stays) or None
        when nothing triggered."""
        why = self.needs_replan()
        return self.replan(triggers=why) if why else None
