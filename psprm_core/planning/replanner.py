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

import copy
import dataclasses
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError, PsprmError
from ..kernels import fastpath
from ..prediction import PredictionSettings, TargetPredictor, quat_yaw
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .execution import commit_time, progress_time, splice
from .psprm import PSPRM, PlanResult
from .results import Failure
from .settings import field_specs, setting

log = logging.getLogger(__name__)


HEURISTICS = ("exact", "hop", "planner")
#: triggers that say only that the view changed (the current path is still collision-free and leads to the goal)
VIEW_TRIGGERS = frozenset({"score_low", "score_drop", "score_low_retry", "target_moved"})
HISTORY = 1000  # replans kept in Replanner.history (a long-running node must not keep them all)


def _wrap_angle(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class ReplanSettings:
    """Replanning triggers and repair (``config/planners/replan.yaml``). Each field carries its metadata
    (:func:`~.settings.setting`: description, range or choices; ``live``: a running server changes it through its
    parameter of the field's name), listed by :meth:`specs`."""

    target_move_m: float = setting(0.05, "target translation that counts as a move (m; re-score, replan)", live=True)
    target_turn_rad: float = setting(0.15, "target rotation that counts as a move (rad)", live=True)
    obstacle_move_m: float = setting(0.03, "obstacle translation that counts as a move (m; re-check, replan)",
                                     live=True)
    obstacle_turn_rad: float = setting(0.1, "obstacle rotation that counts as a move (rad)", live=True)
    focus_move_m: float = setting(0.25, "the visibility focus follows a target that moved further than this (m)")
    replan_on_move: bool = setting(False, "a target/obstacle move alone triggers a replan (else it triggers the "
                                          "score and collision checks, and those decide)", live=True)
    score_min: float = setting(0.1, "replan when the predicted normalised score along the remaining path falls below "
                                    "this (and, for a plan made below it, whenever the target moved)", live=True)
    score_drop: float = setting(0.15, "... or drops by more than this since the plan (scores normalised as in "
                                      "Eq. 1)", live=True)
    goal_switch_margin: float = setting(0.2, "goal hysteresis: switch to another goal only when it is cheaper by "
                                             "this fraction of the current plan's cost", live=True)
    final_approach_m: float = setting(1.0, "no score-triggered replan within this base path length of the goal (m); "
                                           "a collision or a new goal still replans", live=True)
    goal_commit_s: float = setting(10.0, "keep a chosen goal this long (s) unless no path reaches it (0: off)",
                                   live=True)
    goal_commit_growth: float = setting(2.0, "each goal switch multiplies the next commitment by this (1: constant); "
                                             "a new goal set starts again at goal_commit_s", range=(1.0, None),
                                        live=True)
    keep_unless_better: bool = setting(True, "a replan the view alone triggered replaces the trajectory only when it "
                                             "sees more or is shorter (else the robot keeps driving it)", live=True)
    keep_score_margin: float = setting(0.05, "normalised mean score along the path a new plan must add to replace "
                                             "the current", live=True)
    keep_length_margin: float = setting(0.1, "fraction of the remaining path's motion cost a new plan must save to "
                                             "replace the current", live=True)
    min_interval_s: float = setting(1.0, "at most one score/move-triggered replan per interval (s)", live=True)
    score_samples: int = setting(200, "configurations of the remaining path scored for the score trigger",
                                 range=(1, None))
    repair_rounds: int = setting(2, "roadmap repair attempts when no goal is reachable")
    repair_nodes: int = setting(150, "nodes sampled per repair round")
    repair_radius_m: float = setting(1.5, "repair nodes around the moved obstacles and the start within this (m)")
    repair_budget_nodes: int = setting(1500, "at most this many nodes added by repair over the replanner's life")
    heuristic: str = setting("exact", "A* heuristic of the replans: exact (cost-to-go from one compiled Dijkstra over "
                                      "the current weights) | hop (Eq. 3) | planner (the planner's query.heuristic)",
                             choices=HEURISTICS)
    smooth_timing: bool = setting(True, "replanned trajectories pass the knots of a base phase without stopping "
                                        "(about a third shorter to execute, about +25 ms per replan)")
    shortcut: bool = setting(False, "perception-preserving shortcuts of replanned paths (query.shortcut; tens of ms "
                                    "per replan)")
    route_selection: bool = setting(False, "the planner's route selection (query.route_searches) in replans (each "
                                           "extra search adds a search's time)")
    commit: bool = setting(True, "a robot in motion replans from its committed state: the trajectory under way is "
                                 "kept to its first rest instant after planning and delivery, the new plan is spliced "
                                 "on there", live=True)
    commit_horizon_s: float = setting(0.3, "planning and delivery time when the caller gives none (s)")
    predict_lead_s: float = setting(1.5, "the roadmap is scored against the target pose extrapolated this far ahead "
                                         "(s)")
    score_bins: int = setting(4, "a path's predicted score: its duration split into this many stretches, each scored "
                                 "against the targets' predicted poses at its middle", range=(1, None))
    predict_samples: int = setting(48, "... at this many configurations of the path, evenly in time",
                                   range=(1, None))
    predicted_routes: bool = setting(False, "a replan also searches the roadmap scored against each other heading of "
                                           "the targets' predicted mixture and keeps the route of the best predicted "
                                           "objective (a re-scoring and a search per heading)", live=True)
    predicted_route_turn_rad: float = setting(0.5, "... the headings that differ by more than this (rad) from the "
                                                   "extrapolated one and from each other", range=(0.0, None),
                                              live=True)
    prediction: PredictionSettings = field(default_factory=PredictionSettings)

    def __post_init__(self):
        for spec in self.specs():
            spec.check(getattr(self, spec.name), "replan settings")

    @staticmethod
    def specs() -> tuple:
        """Every field but ``prediction`` as a :class:`~.settings.SettingSpec` (named by the field's name)."""
        return field_specs(ReplanSettings)

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


# what adopting a plan changes, restored by Replanner.withdraw
_ADOPTION_STATE = ("result", "_progress", "_t_along", "_goal_cfg", "_goal_since", "_switches", "goal_switches",
                   "_plan_score", "_pending", "_moved_obstacles", "adopted")


def _snapshot(value):
    """A container (set, dict, array) copied, anything else (a PlanResult, a number) as it is."""
    return copy.copy(value) if isinstance(value, (set, dict, list, np.ndarray)) else value


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
        self._rescore_all = False  # the roadmap was scored against another heading: every edge is estimated again
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
        self.adopted = 0  # replans whose plan replaced the current one
        self.declined = 0  # replans that kept the current plan (kept)
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
        """Predicted mean perception score along the remaining path (``normalized``: divided by the roadmap's
        99th-percentile node score and clipped to [0, 1], as c_p in Eq. 1), each stretch of it judged against the
        targets' poses predicted for the time the robot passes there (:meth:`predicted_score`). Cached per (plan,
        progress, time along it, planner scene): the trigger evaluation and the keep decision of the replan that
        follows it in the same cycle score the path once."""
        rem = self.remaining()
        if rem is None or len(rem) == 0:
            return float("nan")
        self._sync_scene()
        key = (self.result, self._progress, self.planner.scene, normalized, self._t_along)
        c = self._score_cache
        if c is not None and all(a is b for a, b in zip(c[0][:3], key[:3])) and c[0][3:] == key[3:]:
            return c[1]
        traj = self.result.trajectory
        if traj is not None:
            out = self.predicted_score(traj, self._time_along(), normalized=normalized)
        else:
            step = max(1, len(rem) // max(1, self.settings.score_samples))
            sc = self.planner.score_configs(torch.as_tensor(rem[::step], dtype=torch.float32))
            out = float((self.planner.normalized_scores(sc) if normalized else sc).mean())
        self._score_cache = (key, out)
        return out

    def _time_along(self) -> float:
        """The robot's time along the current trajectory: the caller's (:meth:`set_robot_state`), else estimated
        from its progress along the dense path."""
        traj = self.result.trajectory
        if self._t_along is not None:
            return min(self._t_along, float(traj.duration))
        c = self._along_cache
        if c is not None and c[0] is self.result and c[1] == self._progress:
            return c[2]
        n = len(self.result.dense) if self.result.dense is not None else 0
        guess = float(traj.duration) * (self._progress / max(1, n - 1))
        t = guess if self.q is None else progress_time(traj, self.q, guess, window_s=float(traj.duration),
                                                       scale=self.robot.velocity,
                                                       angle_cols=[2] if self.robot.mobile else [])
        self._along_cache = (self.result, self._progress, t)
        return t

    def predicted_score(self, traj, t0: float = 0.0, lead_s: float = 0.0, normalized: bool = True) -> float:
        """Time-integrated predicted perception of ``traj`` from its time ``t0`` to its end: the mean score of
        configurations every 50 ms (at most ``predict_samples``, evenly in time), each stretch of ``score_bins`` scored against the
        targets' predicted pose mixture (:meth:`~psprm_core.prediction.TargetPredictor.mixture`) at the time the robot
        will be there (now + ``lead_s`` + (t - ``t0``), "now" being the latest pose's stamp). Without prediction, the
        targets' latest poses."""
        T = float(traj.duration)
        t0 = min(max(0.0, float(t0)), T)
        n = int(max(2, min(self.settings.predict_samples, (T - t0) / 0.05 + 1)))
        ts = np.linspace(t0, T, n)
        Q = traj.evaluate(ts)[0]
        now = self._stamp if self._stamp is not None else 0.0
        sc = self._score_timed(Q, now + lead_s + (ts - t0))
        return float((self.planner.normalized_scores(sc) if normalized else sc).mean())

    def _predicting(self) -> bool:
        return self.settings.prediction.enabled and self._stamp is not None and \
            any(pr.ready for pr in self.predictors.values())

    def _score_timed(self, Q: np.ndarray, stamps: np.ndarray) -> torch.Tensor:
        """Scores (K,) of configurations ``Q`` (K, dof), each against the targets' predicted mixture at its stamp
        (expected score over the mixture), the mixture taken at the middle of each of ``score_bins`` stretches of
        consecutive configurations. Each distinct set of predicted poses is scored once, on the configurations of
        the stretches that use it (a standing person's history components are the same in every stretch), in
        batches the compiled scorer takes."""
        p = self.planner
        self._sync_scene()
        Qt = torch.as_tensor(np.asarray(Q), dtype=torch.float32)
        if not self._predicting():
            return p.score_configs(Qt).double()
        groups: dict = {}  # pose key -> [scene, [(rows, weight), ...]]
        for idx in np.array_split(np.arange(len(Q)), min(self.settings.score_bins, len(Q))):
            if len(idx):
                for w, key, scene in self._mixture_scenes(float(np.mean(stamps[idx]))):
                    groups.setdefault(key, [scene, []])[1].append((idx, w))
        out = torch.zeros(len(Q), dtype=torch.float64)
        restore = p.scene
        try:
            for scene, parts in groups.values():
                rows = np.concatenate([idx for idx, _ in parts])
                p.set_scorer_scene(scene)
                sc = torch.cat([p.score_configs(Qt[rows[i:i + fastpath.MLP_MAX_ROWS]]).double()
                                for i in range(0, len(rows), fastpath.MLP_MAX_ROWS)])
                k = 0
                for idx, w in parts:
                    out[idx] += w * sc[k:k + len(idx)]
                    k += len(idx)
        finally:
            p.set_scene(restore)  # the scorer back on the planning scene (the checker never left it)
        return out

    def _mixture_scenes(self, t: float) -> list:
        """[(weight, key, scene)]: the scene with every predicted target at its k-th mixture component at time ``t``
        (the components of all targets taken together by index; the weights of the target with the most); ``key``
        identifies the poses (3 cm, 0.02 rad)."""
        mixes = {n: pr.mixture(t) for n, pr in self.predictors.items() if pr.ready}
        if not mixes:
            return [(1.0, (), self.scene)]
        k_max = max(len(m) for m in mixes.values())
        weights = next(m for m in mixes.values() if len(m) == k_max)
        out = []
        for k in range(k_max):
            scene, key = self.scene, []
            for name, m in mixes.items():
                _, pos, quat = m[min(k, len(m) - 1)]
                scene = scene.with_target_pose(name, pos, quat)
                key.append((name, *np.round(np.asarray(pos) / 0.03).astype(int).tolist(),
                            int(round(quat_yaw(quat) / 0.02))))
            out.append((weights[k][0], tuple(key), scene))
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
    def planning_scene(self):
        """The scene the roadmap is scored with: the latest poses, every target that is not a collision box moved to
        its pose extrapolated ``predict_lead_s`` ahead (the mixture's first component; with prediction off, the
        latest pose). Collision boxes always stay where they were measured."""
        key = (self.scene, self._stamp)
        if self._planning_scene is not None and self._planning_scene[0][0] is key[0] and \
                self._planning_scene[0][1] == key[1]:
            return self._planning_scene[1]
        scene = self.scene
        if self._predicting():
            t = self._stamp + self.settings.predict_lead_s
            for name, pr in self.predictors.items():
                if pr.ready and not scene.target(name).obstacle:
                    _, pos, quat = pr.mixture(t)[0]
                    scene = scene.with_target_pose(name, pos, quat)
        self._planning_scene = (key, scene)
        return scene

    def _sync_scene(self) -> None:
        """Push the planning scene (:meth:`planning_scene`) to the planner (scorer occluders, collision boxes,
        focus)."""
        p = self.planner
        scene = self.planning_scene()
        if p.scene is not scene:
            p.set_scene(scene)
            focus = np.mean([self.scene.target(t).center for t in self.targets], axis=0)
            if np.linalg.norm(focus - p.constraint.target.numpy()) > self.settings.focus_move_m:
                p.set_focus(focus)

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
        replans (the reasons of :meth:`needs_replan`); when they are all :data:`VIEW_TRIGGERS` and
        ``keep_unless_better`` is on, a new plan no better than the current one is not adopted (the result has
        ``kept`` set, no trajectory, and the new plan as ``declined``; the module's docstring). Runs with torch's
        intra-op parallelism off, like a query (:func:`~psprm_core.kernels.fastpath.one_thread`): its re-scoring batches
        are a few thousand rows, where a second thread gains little and can wait a scheduler slice on a busy machine."""
        with fastpath.one_thread(self.planner.device):
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
                             goal_index=self.result.goal_index, cost=self.result.cost, kept=True)
        elif commit is not None and res.success:
            fresh = res
            res = self._splice(res, commit)
            kept = self._keep_current(fresh, triggers, commit) if res.success else None
            if kept is not None:
                res = PlanResult(True, kept[0], goal_index=self.result.goal_index, cost=self.result.cost, kept=True,
                                 declined=res)
                self._plan_score = kept[1]
        elif res.success:
            kept = self._keep_current(res, triggers, None)
            if kept is not None:
                res = PlanResult(True, kept[0], goal_index=self.result.goal_index, cost=self.result.cost, kept=True,
                                 declined=res)
                self._plan_score = kept[1]
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
                             "repair_rounds": rounds, "kept": res.kept, "spliced": commit is not None,
                             "route": res.route,
                             **{k: v for k, v in info.items() if k == "rescore"}})
        self.replans += 1
        self._last_failed = not res.success
        if res.kept:
            self.declined += 1
            log.info("%s", res.reason)
        elif res.success:
            # the plan objects themselves (callers compare them by identity), copies of the containers adoption clears
            self._adopted_over = (res, {k: _snapshot(getattr(self, k)) for k in _ADOPTION_STATE})
            self.adopted += 1
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

    def _keep_current(self, res: PlanResult, triggers: tuple, commit: Optional[dict]) -> Optional[tuple]:
        """(why, the current plan's predicted score) when the new plan ``res`` (from the committed state, or from
        the robot's state) should not replace the current one (the module's docstring), else None. Both are judged
        from the same instant on, against the targets' predicted poses (:meth:`predicted_score`): the current plan
        from the commit instant (or the robot's progress), the new one from its start."""
        s = self.settings
        if not (s.keep_unless_better and triggers and set(triggers) <= VIEW_TRIGGERS) \
                or "goal_changed" in self._pending:
            return None
        cur = self.result
        if cur is None or cur.dense is None or res.dense is None or self._goal_cfg is None or res.trajectory is None:
            return None
        if not 0 <= res.goal_index < len(self.goals):
            return None
        if self.remaining_path_collides():
            return None
        if commit is not None:
            t_c, lead = commit["t_commit"], commit["t_commit"] - commit["t_from"]
            if t_c >= float(cur.trajectory.duration) - 1e-6:
                return None
            rem = cur.trajectory.evaluate(np.linspace(t_c, float(cur.trajectory.duration), 200))[0]
        elif cur.trajectory is not None:
            t_c, lead = self._time_along(), 0.0
            rem = self.remaining()
        else:
            return None
        if rem is None or len(rem) < 2:
            return None
        current = self.predicted_score(cur.trajectory, t_c)
        plan_score = self.predicted_score(res.trajectory, 0.0, lead_s=lead)
        motion = self.planner.motion
        rem_len, new_len = (float(motion.distance(q[:-1], q[1:]).sum()) if len(q) > 1 else 0.0
                            for q in (torch.as_tensor(np.asarray(d), dtype=torch.float64) for d in (rem, res.dense)))
        self._new_plan_score = plan_score
        if plan_score > current + s.keep_score_margin or new_len < (1.0 - s.keep_length_margin) * rem_len:
            return None
        return (f"kept the current plan: the new one sees {plan_score:.3f} (predicted) along {new_len:.2f} against "
                f"the remaining path's {current:.3f} along {rem_len:.2f}", current)

    def _predicted_routes(self, res: PlanResult, start: np.ndarray, commit: Optional[dict]) -> PlanResult:
        """The route of the best predicted objective among ``res`` (the search over the roadmap scored against the
        targets' extrapolated poses) and one search per other heading of their predicted mixture
        (:meth:`_mixture_scenes` halfway along ``res``): each heading that differs by more than
        ``predicted_route_turn_rad`` from the extrapolated one and from the headings searched before re-scores the
        roadmap, and the goals are searched again from ``start``. A person turned away while the plan is made is
        predicted to look back where they looked before; a route that sees those views is a candidate beside the one
        that sees the extrapolated view (not for a collision: that replan must be quick). A route of another heading
        must be predicted to see more than the extrapolated one (P, the perception predicted along the route's
        timing, :meth:`predicted_score`, by ``keep_score_margin``); among those and the extrapolated one the
        motion-weighted objective over the whole route (:func:`~.objectives.motion_weighted`),
        L ((1 - alpha) + alpha (1 - P)), decides. The roadmap's scores stay on the last heading until the next replan
        re-scores every node and edge."""
        s = self.settings
        if not (s.predicted_routes and self._predicting()):
            return res
        lead = 0.0 if commit is None else commit["t_commit"] - commit["t_from"]
        t_mid = self._stamp + lead + 0.5 * float(res.trajectory.duration)
        base = self.planning_scene()
        heads = [self._target_yaws(base)]
        alts = []
        for _, _, scene in self._mixture_scenes(t_mid):
            yaws = self._target_yaws(scene)
            if all(max(abs(_wrap_angle(yaws[n] - h[n])) for n in yaws) > s.predicted_route_turn_rad for h in heads):
                heads.append(yaws)
                alts.append(scene)
        if not alts:
            return res
        p = self.planner
        judged = [(self._route_objective(res, lead), res)]
        try:
            for scene in alts:
                p.set_scorer_scene(scene)
                p.rescore()
                cand = self._plan_goals(self._last_plan_time, start)
                if cand.success and cand.trajectory is not None:
                    judged.append((self._route_objective(cand, lead), cand))
        finally:
            p.set_scene(base)
            self._rescore_all = True
        # another heading's route replaces the extrapolated one only when it is predicted to see more (by the keep
        # margin): the mixture blurs every route's perception, and judged by the objective alone the shortest would win
        seen = judged[0][0][1] + s.keep_score_margin
        best = min((i for i in range(len(judged)) if i == 0 or judged[i][0][1] > seen), key=lambda i: judged[i][0][0])
        names = ["extrapolated"] + [f"predicted heading {i}" for i in range(1, len(judged))]
        out = judged[best][1]
        out.route = names[best]
        out.route_candidates = {n: (j[1], j[2]) for n, (j, _) in zip(names, judged)}
        return out

    def _target_yaws(self, scene) -> dict:
        """Heading (rad) of every predicted target of ``scene``."""
        return {n: quat_yaw(scene.target(n).quat) for n, pr in self.predictors.items() if pr.ready}

    def _route_objective(self, res: PlanResult, lead: float) -> tuple:
        """(L ((1 - alpha) + alpha (1 - P)), P, L) of a planned route: P its predicted perception from the time its
        start is reached (``lead`` s from now), L its motion length (:meth:`_predicted_routes`)."""
        P = self.predicted_score(res.trajectory, 0.0, lead_s=lead)
        d = torch.as_tensor(np.asarray(res.dense), dtype=torch.float64)
        L = float(self.planner.motion.distance(d[:-1], d[1:]).sum()) if len(d) > 1 else 0.0
        a = float(self.planner.settings.scoring.alpha)
        return L * ((1.0 - a) + a * (1.0 - P)), P, L

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

    def _plan_goals(self, now: float, start: np.ndarray) -> PlanResult:
        """One search from ``start`` over the candidate goals: only the committed goal while its commitment lasts
        (all of them if no path reaches it), otherwise all with the switching margin (:meth:`_goal_costs`)."""
        p = self.planner
        keep = self._committed_goal(now)
        if keep is not None:
            res = p.plan(start, self.goals[keep], options=self.plan_options)
            if res.success:
                res.goal_index = int(np.nonzero(keep)[0][res.goal_index]) if res.goal_index >= 0 else -1
                return res
        return p.plan(start, self.goals, goal_costs=self._goal_costs(), options=self.plan_options)

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
