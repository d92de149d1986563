"""How the replanner judges (:class:`PlanJudging`, a base of :class:`~.replanner.Replanner` working on its state):
when to replan, what a plan is predicted to see, whether a new plan replaces the current one, the routes searched
for the targets' predicted headings and the choice between goals.

Triggers (:meth:`PlanJudging.needs_replan`): the remaining path collides with the latest obstacle poses; the predicted
mean perception score along the remaining path is below ``score_min`` or has dropped by more than ``score_drop``
since the plan; the target or an obstacle moved beyond its threshold; the goal changed.

A replan that only the view triggered (:data:`VIEW_TRIGGERS`) replaces the current plan (whichever goal it leads to)
only when it is better for the robot: it sees more along its path (``keep_score_margin``, normalised as c_p in Eq.
1), or it is shorter (``keep_length_margin`` of the remaining path's motion cost) without being predicted to see
less (nor less than ``keep_length_min_score``, 0 as shipped); and it arrives within the arrival budget (the
duration of the fastest route to the goals, from where their first plan started, times 1 + ``arrival_budget`` after
that plan was made; ``arrival_reference``) or no later than the current plan, so that views are never bought with
an unbounded delay, even when the first plan for a goal is itself a long route that sees.
A shorter route that sees less is not taken on a view trigger: a person turning away predicts little to see on every
route, and the shortest would win although the person turns back. Otherwise the robot keeps driving its trajectory
(:attr:`PlanResult.kept`), and a person turning away every few seconds does not restart the robot towards views that
are gone before it gets there.
"""

from __future__ import annotations

import logging
import math
import time
from typing import NamedTuple, Optional

import numpy as np
import torch

from ..geometry import wrap_angle
from ..prediction import quat_yaw
from .execution import progress_time
from .psprm import PlanResult
from .results import Adopt, Keep

log = logging.getLogger(__name__)

#: triggers that say only that the view changed (the current path is still collision-free and leads to the goal)
VIEW_TRIGGERS = frozenset({"score_low", "score_drop", "score_low_retry", "target_moved"})


class Verdict(NamedTuple):
    """The keep decision on a replan's new plan (:meth:`PlanJudging._keep_current`): ``keep`` is not
    :attr:`~.results.Keep.NONE` when the current plan stays, else ``adopt`` says why the new one replaces it; ``why``
    gives both plans' predicted perception and arrival when they were judged, ``current`` the remaining path's
    predicted score then."""

    keep: Keep
    adopt: Adopt
    why: str = ""
    current: Optional[float] = None


class PlanJudging:
    """The replanner's judgement of plans (the module's docstring). Its methods read and keep the state of the
    :class:`~.replanner.Replanner` they are part of (the current result, the robot's progress, the predictors, the
    caches of the path's score and collision state)."""

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

    def predicted_score(self, traj, t0: float = 0.0, lead_s: float = 0.0, normalized: bool = True,
                        per_component: bool = False):
        """Time-integrated predicted perception of ``traj`` from its time ``t0`` to its end: the mean score of
        configurations every 50 ms (at most ``predict_samples``, evenly in time), each of ``score_bins`` stretches
        scored against the targets' predicted pose mixture (:meth:`~psprm_core.prediction.TargetPredictor.mixture`)
        at the time the robot will be there (now + ``lead_s`` + (t - ``t0``), "now" being the latest pose's stamp).
        Without prediction, the targets' latest poses. ``per_component``: (that mean, (C,) the mean under each
        mixture component alone: the extrapolation, the periodic heading when a turn repeats, then each heading of
        the history)."""
        T = float(traj.duration)
        t0 = min(max(0.0, float(t0)), T)
        n = int(max(2, min(self.settings.predict_samples, (T - t0) / 0.05 + 1)))
        ts = np.linspace(t0, T, n)
        Q = traj.evaluate(ts)[0]
        now = self._stamp if self._stamp is not None else 0.0
        sc, comp = self._score_timed(Q, now + lead_s + (ts - t0))
        norm = self.planner.normalized_scores if normalized else (lambda x: x)
        mean = float(norm(sc).mean())
        return (mean, norm(comp).mean(dim=1).numpy()) if per_component else mean

    def _predicting(self) -> bool:
        return self.settings.prediction.enabled and self._stamp is not None and \
            any(pr.ready for pr in self.predictors.values())

    def _score_timed(self, Q: np.ndarray, stamps: np.ndarray) -> tuple:
        """Scores (K,) of configurations ``Q`` (K, dof), each against the targets' predicted mixture at its stamp
        (expected score over the mixture), the mixture taken at the middle of each of ``score_bins`` stretches of
        consecutive configurations; and (C, K) the scores under each mixture component alone (a stretch with fewer
        components repeats its last). Each distinct set of predicted poses is scored once, on the configurations of
        the stretches that use it (a standing person's history components are the same in every stretch), in
        batches the compiled scorer takes."""
        p = self.planner
        self._sync_scene()
        Qt = torch.as_tensor(np.asarray(Q), dtype=torch.float32)
        if not self._predicting():
            sc = p.score_configs(Qt).double()
            return sc, sc[None]
        groups: dict = {}  # pose key -> [scene, [(rows, weight, component), ...]]
        bins = []  # (rows, number of components)
        for idx in np.array_split(np.arange(len(Q)), min(self.settings.score_bins, len(Q))):
            if len(idx):
                mix = self._mixture_scenes(float(np.mean(stamps[idx])))
                bins.append((idx, len(mix)))
                for k, (w, key, scene) in enumerate(mix):
                    groups.setdefault(key, [scene, []])[1].append((idx, w, k))
        out = torch.zeros(len(Q), dtype=torch.float64)
        comp = torch.zeros(max(c for _, c in bins), len(Q), dtype=torch.float64)
        restore = p.scene
        try:
            for scene, parts in groups.values():
                rows = np.concatenate([idx for idx, *_ in parts])
                p.set_scorer_scene(scene)
                step = p.compute.mlp_max_rows
                sc = torch.cat([p.score_configs(Qt[rows[i:i + step]]).double() for i in range(0, len(rows), step)])
                j = 0
                for idx, w, k in parts:
                    out[idx] += w * sc[j:j + len(idx)]
                    comp[k, idx] = sc[j:j + len(idx)]
                    j += len(idx)
        finally:
            p.set_scorer_scene(restore)  # the scorer back on the planning scene (the checker never left it)
        for idx, c in bins:
            comp[c:, idx] = comp[c - 1, idx]
        return out, comp

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

    def _keep_current(self, res: PlanResult, triggers: tuple, commit: Optional[dict]) -> Verdict:
        """Whether the new plan ``res`` (from the committed state, or from the robot's state) replaces the current
        one (the module's docstring), and why. Both are judged from the same instant on, against the targets'
        predicted poses (:meth:`predicted_score`): the current plan from the commit instant (or the robot's
        progress), the new one from its start."""
        s = self.settings
        unjudged = Verdict(Keep.NONE, Adopt.UNJUDGED)
        if not (s.keep_unless_better and triggers and set(triggers) <= VIEW_TRIGGERS) \
                or "goal_changed" in self._pending:
            return unjudged
        cur = self.result
        if cur is None or cur.dense is None or res.dense is None or self._goal_cfg is None or res.trajectory is None:
            return unjudged
        if not 0 <= res.goal_index < len(self.goals):
            return unjudged
        if self.remaining_path_collides():
            return Verdict(Keep.NONE, Adopt.UNSAFE, "the remaining path collides")
        if commit is not None:
            t_c, lead = commit["t_commit"], commit["t_commit"] - commit["t_from"]
            if t_c >= float(cur.trajectory.duration) - 1e-6:
                return unjudged
            rem = cur.trajectory.evaluate(np.linspace(t_c, float(cur.trajectory.duration), 200))[0]
        elif cur.trajectory is not None:
            t_c, lead = self._time_along(), 0.0
            rem = self.remaining()
        else:
            return unjudged
        if rem is None or len(rem) < 2:
            return unjudged
        current, cur_k = self.predicted_score(cur.trajectory, t_c, per_component=True)
        plan_score, new_k = self.predicted_score(res.trajectory, 0.0, lead_s=lead, per_component=True)
        motion = self.planner.motion
        rem_len, new_len = (float(motion.distance(q[:-1], q[1:]).sum()) if len(q) > 1 else 0.0
                            for q in (torch.as_tensor(np.asarray(d), dtype=torch.float64) for d in (rem, res.dense)))
        self._new_plan_score = plan_score
        shorter = new_len < (1.0 - s.keep_length_margin) * rem_len
        # arrival, both from the instant the replan began: the current plan from where it was then, the new one after
        # the commitment it starts from
        cur_arrival = float(cur.trajectory.duration) - (commit["t_from"] if commit is not None else t_c)
        new_arrival = lead + float(res.trajectory.duration)
        budget = self.arrival_budget_left()
        late = new_arrival > max(budget, cur_arrival) + 1e-6
        sees_more = plan_score > current + s.keep_score_margin
        shorter_seeing_no_less = shorter and plan_score >= max(current, s.keep_length_min_score)
        heads = (lambda v: "" if len(v) < 2 else f" ({'/'.join(f'{x:.2f}' for x in v)} by heading)")
        both = (f"the new one sees {plan_score:.3f} (predicted){heads(new_k)} along {new_len:.2f} and arrives in "
                f"{new_arrival:.1f} s (budget {budget:.1f} s); the remaining path sees {current:.3f}{heads(cur_k)} "
                f"along {rem_len:.2f} and arrives in {cur_arrival:.1f} s")
        if not late and (sees_more or shorter_seeing_no_less):
            return Verdict(Keep.NONE, Adopt.SEES_MORE if sees_more else Adopt.SHORTER, both, current)
        return Verdict(Keep.LATE if late else Keep.NO_BETTER, Adopt.NONE, f"kept the current plan: {both}", current)

    def arrival_budget_left(self) -> float:
        """Seconds from the latest replan's instant to the end of the arrival budget: the first plan for the current
        goals, made at t0, ends its budget at t0 + T (1 + ``arrival_budget``), T its reference duration
        (``arrival_reference``: the fastest route's, at most the plan's own); inf without a budget."""
        b = self.settings.arrival_budget
        if b <= 0 or self._first_plan is None:
            return math.inf
        return self._first_plan[0] + (1.0 + b) * self._arrival_reference() - self._last_plan_time

    def _set_arrival_reference(self, res: PlanResult, start: np.ndarray) -> None:
        """``res``, just adopted as the first plan for the current goals from ``start`` (the committed state in
        motion), is the arrival budget's reference: its instant, its time to the goal from then (its time 0 is the
        instant, or the robot's time along the trajectory it continues, ``committed_s`` before its start), and what
        the fastest route needs, searched when the budget is first asked for (a replan that follows a goal change
        does not wait for it)."""
        lead = float(res.committed_s or 0.0)
        self._first_plan = (self._last_plan_time, float(res.trajectory.duration),
                            (np.array(start, float), np.array(self.goals, float), lead), None)

    def _arrival_reference(self) -> float:
        """The arrival budget's reference duration (:meth:`arrival_budget_left`)."""
        t0, T, pending, fastest = self._first_plan
        if self.settings.arrival_reference == "plan":
            return T
        if fastest is None:
            start, goals, lead = pending
            fast = self.planner.fastest(start, goals, self.plan_options)
            if fast.success and fast.trajectory is not None:
                fastest = lead + float(fast.trajectory.duration)
            else:
                log.info("no fastest route for the arrival budget (%s): the first plan's duration is its reference",
                         fast.reason)
                fastest = T
            self._first_plan = (t0, T, pending, fastest)
        return min(T, fastest)

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
            if all(max(abs(wrap_angle(yaws[n] - h[n])) for n in yaws) > s.predicted_route_turn_rad for h in heads):
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

    def _remaining_base_length(self) -> float:
        """Length (m) of the base's path still ahead (inf for a robot without a mobile base)."""
        rem = self.remaining()
        if rem is None or not self.robot.mobile:
            return math.inf
        return float(np.linalg.norm(np.diff(rem[:, :2], axis=0), axis=1).sum()) if len(rem) > 1 else 0.0

    def needs_replan(self, now: Optional[float] = None) -> list:
        """Reasons to replan now ([] = keep the current plan). ``now``: the caller's clock (default: monotonic);
        apart from a collision, a goal change or a body starting to turn beside the path, at most one replan per
        ``min_interval_s``."""
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
        if "turning_obstacle" in self._pending:
            reasons.append("turning_obstacle")
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
