"""The planning loop's worker side: the planner, the replanner and every decision about what the robot is sent, run
on the loop's worker thread only (:class:`~.loop.PlanningLoop` owns the thread and the inputs). Each cycle applies
the newest poses, robot state and goals, asks the replanner whether to replan, replans, and hands a trajectory out
only after the final check passed exactly its samples."""

from __future__ import annotations

import json
import threading
import time
from typing import Callable, Optional, Sequence

import numpy as np

from psprm_core.errors import PsprmError

from .. import planner_setup
from .checks import FinalCheck, StopGuard, remaining
from .params import MAX_STALE_STARTS, SETTLED_M, SPLICE_DELIVERY_S, finite_or_none as _f, live_replan


class PlanningWorker:
    """The worker-only state: the planner and replanner (``rp``), the final check with the newest poses
    (``final``), the stop guard's checker (``guard``, used on the callers' threads), the configuration planned
    from (``q``), the goals, and whether the robot is held. ``loop``'s shared parts (its inputs, the robot's
    measured motion, what the robot executes, the views, the side thread, the counters, the live parameters and the
    outputs) are used, never replaced; ``is_active`` tells whether the node is active."""

    def __init__(self, loop, scene, targets: Sequence[str], spec: planner_setup.PlannerSpec, obstacles: Sequence[str],
                 q0: np.ndarray, goals: Optional[np.ndarray], is_active: Callable[[], bool]):
        self.scene, self.spec, self.targets, self.obstacles = scene, spec, list(targets), list(obstacles)
        self.robot, self.p, self.outputs, self.clock = loop.robot, loop.p, loop.outputs, loop.clock
        self.inputs, self.motion, self.executing = loop.inputs, loop.motion, loop.executing
        self.views, self.side, self.counts, self.ready = loop.views, loop.side, loop.counts, loop.ready
        self.is_active = is_active
        self.q = np.asarray(q0, float).copy()
        self.goal_configs: Optional[np.ndarray] = None if goals is None else np.asarray(goals, float)
        self.rp = None
        self.planner = None
        self.final: Optional[FinalCheck] = None  # the scene with the newest poses, and the check before publishing
        self.guard: Optional[StopGuard] = None  # the stop guard's own checker (it runs on the callers' threads)
        self.hold = False
        self._robot_check_t = 0.0
        self._waiting_t = 0.0  # last "waiting for base pose" report
        self.waiting = ""  # why nothing is planned now ("" = not waiting)
        self.seq = 0
        self.build_info: dict = {}
        self._stale_run = 0  # plans withdrawn in a row for a stale start
        self._replan_stale = False  # the next cycle replans: a plan was withdrawn for a stale start
        self._deferred: list = []  # the reasons of a plan that waits for the braking base to rest
        self._settle_t0: Optional[float] = None  # when that wait began (monotonic)
        self._along: Optional[float] = None  # the robot's time along the trajectory under way, at its newest state

    @property
    def safety_scene(self):
        """The scene with the newest obstacle and target poses applied."""
        return self.final.scene if self.final is not None else self.scene

    @property
    def current(self) -> Optional[dict]:
        return self.executing.current

    def do_transition(self, kind: str, done: threading.Event, out: list) -> None:
        """Run a lifecycle step (``configure``, ``deactivate``, ``cleanup``) and report: ``out`` gets whether it
        succeeded, then ``done`` is set. A failed step is reported and leaves the loop running."""
        ok = False
        try:
            if kind == "configure":
                self._build(initial=True)
                ok = True
            elif kind == "deactivate":
                if self.rp is not None:
                    self.hold = True
                    self.publish_stop("node deactivated")
                self.outputs.state("inactive: " + (self.build_info and f"{self.build_info.get('n_nodes', 0)} nodes"
                                                   or ""))
                ok = True
            elif kind == "cleanup":
                self.scene = self.safety_scene  # a later configure builds around the poses the loop has
                self.rp = self.planner = self.final = None
                self.executing.current = None
                self.ready.clear()
                self.outputs.state("unconfigured")
                ok = True
        except Exception as exc:  # configuration errors end up here: report, keep the loop alive
            self.outputs.status(f"{kind} failed: {exc}", "error")
            if kind == "configure":
                self.outputs.state(f"error: roadmap build failed: {exc}")
        finally:
            out.append(ok)
            done.set()

    def apply_live(self, live: dict) -> None:
        """Live parameter changes: the replanner's settings (:func:`~.params.live_replan`), and the planner's
        (dotted paths of ``spec.settings``) through its settings (``scoring.alpha`` None: the variant's default)."""
        rp_changes = {k: v for k, v in live.items() if k in live_replan()}
        if rp_changes and self.rp is not None:
            self.rp.update_settings(**rp_changes)
        planner_changes = {k: v for k, v in live.items() if k in self.spec.settings}
        if planner_changes and "scoring.alpha" in self.spec.settings and self.p.get("scoring.alpha") is None:
            planner_changes["scoring.alpha"] = None  # unset: the variant's default for the objective now in use
        if planner_changes and self.planner is not None:
            self.planner.update_settings(planner_setup.resolve_live_settings(self.planner.settings, planner_changes,
                                                                    self.spec.variant))
        if live:
            self.outputs.status(f"parameters applied: {', '.join(f'{k}={v}' for k, v in sorted(live.items()))}")

    def _build(self, initial: bool = False) -> None:
        scene = self.safety_scene
        # the planner settings as their parameters have them now (live changes included)
        settings = {k: self.p.get(k, v) for k, v in self.spec.settings.items()}
        spec = planner_setup.PlannerSpec(**{**vars(self.spec), "settings": settings,
                                   **({} if initial else {"roadmap_file": "none"})})
        planner = planner_setup.make_planner_for(scene, self.robot, self.targets, spec)
        self.outputs.status(f"{'building' if initial else 'rebuilding'} the {spec.variant} roadmap "
                            f"({planner.settings.roadmap.n_nodes} nodes) for scene '{scene.name}'")
        self.outputs.state("building" if initial else "rebuilding")
        info = planner_setup.build_or_load(planner, scene, spec, template=self.q, force_build=not initial)
        if info["source"] == "failed":
            raise RuntimeError(info.get("reason", "roadmap build failed"))
        self.planner, self.build_info = planner, info
        self.rp = planner_setup.make_replanner(planner, self.spec.replan_settings)
        # the live replan settings as their parameters have them (the file's values until changed)
        self.rp.update_settings(**{k: self.p[k] for k in live_replan() if k in self.p})
        # re-apply the scene state the new replanner has not seen (targets/obstacles moved since the YAML)
        for t in scene.targets:
            if t.name in self.targets:
                self.rp.update_target(t.name, t.center, t.quat, stamp=self.clock())
        for o in self.obstacles:
            b = scene.obstacle(o)
            self.rp.update_obstacle(o, b.center, b.quat, stamp=self.clock())
        self.rp.set_robot_state(self.q)
        if self.goal_configs is not None:
            self.rp.set_goals(self.goal_configs)
        self.final = FinalCheck(self.robot, scene)
        self.guard = StopGuard(self.robot, scene)
        text = f"roadmap {info['source']} in {info['seconds']:.1f} s: {info.get('n_nodes', 0)} nodes; ready"
        self.outputs.status(text)
        self.outputs.state(f"ready: {text}")
        self.views.publish_roadmap(self.planner, self.safety_scene)
        self.ready.set()

    def cycle(self, pend: dict, reqs: list) -> None:
        answer = self.inputs.answer
        kinds = {k for k, _ in reqs}
        if "rebuild" in kinds:
            try:
                self._build()
                answer(reqs, True, json.dumps(self.build_info), kinds={"rebuild"})
            except Exception as exc:
                self.outputs.status(f"rebuild failed, keeping the old roadmap: {exc}", "error")
                answer(reqs, False, str(exc), kinds={"rebuild"})
        if self.rp is None:
            answer(reqs, False, "roadmap not ready")
            return
        reasons, self._deferred = self._deferred, []
        t0 = time.perf_counter()
        moved, boxes_changed = self._apply_bodies(pend)
        try:
            # the newest state even when none came this cycle: an adopted plan drops the replanner's progress along
            # the trajectory, and a cycle soon after (a burst of goals) would otherwise plan a moving robot from its
            # state instead of splicing
            q_now = pend["robot"] if pend["robot"] is not None else self.motion.newest()
            if q_now is not None:
                along = self._along = self._time_along(q_now)
                # a base that moves with no trajectory under way brakes from a stop: plan from where it will rest
                q_plan = q_now if along is not None else self.motion.rest_point(q_now)
                self.rp.set_robot_state(q_plan, along)
                self.q = q_plan
            if pend["goals"] is not None:
                self.rp.set_goals(pend["goals"])
                self.goal_configs = pend["goals"]
                self.hold = False
                reasons.append("goal_received")
        except (PsprmError, ValueError) as exc:
            self.outputs.status(f"robot state or goal refused by the planner: {exc}", "warning")
        if "stop" in kinds:
            self.hold = True
            self.publish_stop("stop requested")
            answer(reqs, True, "stopped", kinds={"stop"})
        if "plan" in kinds:
            self.hold = False
            reasons.append("plan requested")
        if pend["guard"]:
            reasons.append(f"stopped: {pend['guard']} in the path ahead")
        if self._replan_stale:
            self._replan_stale = False
            reasons.append("start moved while planning")
        if self.goal_configs is None:
            if reasons:
                self.outputs.status("no goal yet: publish one on the goal topic", "warning")
            answer(reqs, False, "no goal", kinds={"plan"})
            return
        if self.hold:
            return
        if not self.is_active():
            answer(reqs, False, "node inactive", kinds={"plan"})
            return
        if self._waiting(reasons):
            answer(reqs, False, self.waiting, kinds={"plan"})
            return
        t1 = time.perf_counter()
        # the core's triggers change only when something moved beyond its thresholds, the goal changed, or the robot
        # advanced along the path (checked at most every robot_trigger_period_s); keep-alive poses cost nothing
        now = time.monotonic()
        robot_due = pend["robot"] is not None and now - self._robot_check_t >= self.p["robot_trigger_period_s"]
        if self.p["auto_replan"] and (moved or reasons or robot_due or self.rp.result is None):
            if robot_due:
                self._robot_check_t = now
            reasons += [r for r in self.rp.needs_replan() if r not in reasons]
        if boxes_changed and moved and self.current is not None and not reasons:
            if self._unsafe(self._remaining(self.current["positions"])):
                reasons.append("current trajectory in collision with a moved obstacle")
        t2 = time.perf_counter()
        if reasons and self._settling():
            # a plan from a base still braking would start where it is predicted to rest, and the adapter refuses a
            # start that prediction missed: wait (the loop wakes every 0.1 s at most) and plan from where it rests
            self._deferred = reasons
            answer(reqs, True, "planning once the braking base rests", kinds={"plan"})
            return
        if reasons:
            pend["timing"] = {"apply_ms": _f((t1 - t0) * 1e3), "triggers_ms": _f((t2 - t1) * 1e3)}
            ok, msg = self._plan(reasons, pend)
            answer(reqs, ok, msg, kinds={"plan"})
        self.views.republish(self.planner, self.safety_scene)

    def _apply_bodies(self, pend: dict) -> tuple:
        """The cycle's target and obstacle poses into the replanner and the final check; (moved beyond the core's
        thresholds, a collision box changed)."""
        moved = boxes_changed = False
        for name, (p, q) in pend["targets"].items():
            try:
                moved |= self.rp.update_target(name, p, q, stamp=pend["target_stamps"].get(name)) is not False
                boxes_changed |= self.safety_scene.target(name).obstacle
            except (PsprmError, KeyError, ValueError) as exc:
                self.outputs.status(f"target {name} refused by the planner: {exc}", "warning")
        for name, (p, q) in pend["obstacles"].items():
            try:
                moved |= self.rp.update_obstacle(name, p, q, stamp=self.clock()) is not False
                boxes_changed = True
            except (PsprmError, KeyError, ValueError) as exc:
                self.outputs.status(f"obstacle {name} refused by the planner: {exc}", "warning")
        self.final.with_poses(pend["obstacles"], pend["targets"])
        return moved, boxes_changed

    def _waiting(self, reasons: list) -> bool:
        """Whether no plan may start now (:meth:`~.inputs.Inputs.robot_state_problem`; reported every 2 s at
        most, and at once when something asked for a plan)."""
        waiting = self.inputs.robot_state_problem(self.p["robot_state_timeout_s"])
        if waiting:
            self.waiting = waiting
            if time.monotonic() - self._waiting_t > 2.0 or reasons:
                self._waiting_t = time.monotonic()
                self.outputs.status(f"not planning: {waiting}", "warning")
            return True
        if self.waiting:
            self.outputs.status("robot state live: planning resumes")
            self.waiting = ""
        return False

    # ------------------------------------------------------------------------------------------------ planning
    def _settling(self) -> bool:
        """Whether a plan waits for the base to rest: the robot follows nothing the loop handed out (a stop, the
        adapter's stop after a refusal, no trajectory) and its newest state still moves more than
        :data:`~.params.SETTLED_M` braking; for at most ``settle_timeout_s`` from the first such cycle."""
        q = self.motion.newest()
        limit = self.p["settle_timeout_s"]
        if (limit <= 0 or not self.robot.mobile or q is None or self._along is not None
                or self.motion.rest_distance(np.asarray(q, float)) <= SETTLED_M):
            self._settle_t0 = None
            return False
        now = time.monotonic()
        if self._settle_t0 is None:
            self._settle_t0 = now
            self.outputs.status("the base is braking with nothing under way: planning once it rests")
        return now - self._settle_t0 <= limit

    def _time_along(self, q: np.ndarray) -> Optional[float]:
        """Where the robot is along the trajectory under way (:meth:`~.robot_motion.RobotMotion.time_along`), or
        None."""
        traj, t_zero = self.executing.trajectory(self.rp)
        return self.motion.time_along(traj, t_zero, q, self.p["progress_tolerance_m"])

    def _plan(self, reasons: list, pend: dict) -> tuple:
        """Replan and decide: kept (the robot keeps driving), already at the goal (a stop), refused by the final
        check or ready too late for its splice (withdrawn), published; on failure the last safe trajectory is kept,
        else a stop. Returns (ok, the info JSON)."""
        t0 = time.perf_counter()
        stale_run, self._stale_run = self._stale_run, 0
        horizon = self.executing.commit_horizon()
        res = self.rp.replan(triggers=reasons, horizon_s=horizon)
        t1 = time.perf_counter()
        info = {"seq": self.seq, "reasons": reasons, "success": bool(res.success), "reason": res.reason,
                "failure": res.failure.value,
                "query_ms": _f(res.query_ms), "goal_index": int(res.goal_index),
                "input_stamp": pend["stamp"], "input_age_ms": _f(pend.get("input_age_ms")), **pend.get("timing", {}),
                "replan_ms": _f((t1 - t0) * 1e3), "spliced": bool(res.success and res.committed_s > 0),
                "committed_s": _f(res.committed_s), "commit_horizon_s": _f(horizon), "route": res.route,
                "adopted_because": res.adopted_because.value, "judgement": res.judgement}
        self.seq += 1
        if res.kept:  # the new plan was no better or would arrive late: the robot keeps driving the current trajectory
            self.counts["kept"] += 1
            info.update(kept=True, kept_because=res.kept_because.value, stop=False)
            self.outputs.info(info)
            self.outputs.status(f"plan {info['seq']} ({', '.join(reasons)}): {res.reason}")
            return True, json.dumps(info)
        traj = res.trajectory if res.success else None
        if res.success and traj is None:  # already at the goal
            self.publish_stop("already at the goal", info)
            return True, json.dumps(info)
        if traj is not None:
            samples, shift = self.executing.samples(traj, info["spliced"], self.rp.q)
            info["start_shift_s"] = _f(shift)
            t2 = time.perf_counter()
            # what is checked is what is published: exactly these positions, against the newest obstacle poses
            self._take_fresh_obstacles()
            unsafe = self._unsafe(samples.positions)
            info.update(msg_ms=_f((t2 - t1) * 1e3), check_ms=_f((time.perf_counter() - t2) * 1e3))
            # a splice the robot may pass before it arrives; not one committed to the end of the trajectory under
            # way: the robot rests there, and the plan starts from that rest whenever it arrives
            late = (info["spliced"] and not self.executing.commits_to_the_end(res)
                    and time.perf_counter() - t0 + SPLICE_DELIVERY_S > res.committed_s)
            stale = ("" if unsafe or late or info["spliced"] or stale_run >= MAX_STALE_STARTS
                     else self.motion.stale_start(samples.times, samples.positions, self.p["start_tolerance_m"],
                                                   self.p["start_joint_tolerance"]))
            if unsafe or late or stale:
                # not handed to the robot: the replanner goes back to the trajectory the robot executes, so that the
                # next replan commits along that one
                self.rp.withdraw(res)
            if unsafe:
                info.update(success=False, reason="planner output in collision with the latest obstacles: refused")
                self.counts["refused_unsafe"] += 1
            elif late:
                # the robot passes the splice instant before the trajectory reaches it: it keeps what it executes
                self.executing.plan_s.append(time.perf_counter() - t0)  # the next commitment covers a replan this slow
                info.update(success=False, failure="late_splice",
                            reason=f"ready {time.perf_counter() - t0:.2f} s after the replan began, too late for its "
                                   f"splice {res.committed_s:.2f} s ahead: not published")
                self.counts["late_splices"] += 1
            elif stale:
                # the robot moved on while this plan was made (a slow query, a stop in between): the adapter would
                # refuse it and stop the robot; the robot keeps what it executes and the next cycle replans from
                # its newest state
                self._stale_run, self._replan_stale = stale_run + 1, True
                self.counts["stale_starts"] += 1
                info.update(success=False, failure="stale_start", reason=f"{stale}: not published")
                self.outputs.info(info)
                self.outputs.status(f"plan {info['seq']} ({', '.join(reasons)}): {stale}; replanning from the "
                                    f"newest robot state", "warning")
                self.inputs.wake.set()
                return False, json.dumps(info)
            else:
                msg = self.executing.publish(res, samples, info, reasons, pend["t_first"], t0)
                self.motion.forget_progress()
                if self.robot.mobile:  # built on the side thread: ~400 PoseStamped are pure Python
                    self.side.submit("base path", self.outputs.base_path, samples.positions)
                self.side.submit("path markers", self.views.publish_path, res, self.safety_scene, self.planner)
                return True, msg
        # nothing new and safe: keep the last safe trajectory, else stop
        self.counts["failed"] += 1
        self.outputs.status(f"planning failed ({info['reason']})", "warning")
        if self.current is not None and not self._unsafe(self._remaining(self.current["positions"])):
            info.update(stop=False, kept_last=True)
            self.outputs.info(info)
            self.outputs.status("keeping the last safe trajectory", "warning")
        else:
            self.publish_stop(f"no safe trajectory ({info['reason']})", info)
        return False, json.dumps(info)

    def publish_stop(self, why: str, info: Optional[dict] = None) -> None:
        self.executing.stop(self.q, why, info, self.seq)

    # ------------------------------------------------------------------------------------------------ the final check
    def _take_fresh_obstacles(self) -> None:
        """Obstacle poses that arrived while the planner was running go into the final check at once (the planner
        sees them in the next cycle): a trajectory is never published unchecked against a pose the loop already
        has."""
        self.final.with_poses(*self.inputs.bodies())

    def _unsafe(self, positions: np.ndarray) -> bool:
        """True when any configuration along ``positions`` (densified to ``safety_step``, as a controller
        interpolating linearly between them moves) collides with the latest obstacle poses (or leaves the joint
        limits / workspace) (:meth:`~.checks.FinalCheck.unsafe`)."""
        return self.final.unsafe(positions, self.p["safety_step"])

    def _remaining(self, positions: np.ndarray) -> np.ndarray:
        """The part of a published trajectory the robot has not traversed yet, from its sample nearest to the
        configuration the planner last took (:func:`~.checks.remaining`)."""
        return remaining(self.robot, positions, self.q)
