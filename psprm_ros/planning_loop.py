"""The roadmap server's planning loop: one worker thread that owns the planner, the core :class:`Replanner` and
every decision about what the robot is sent.

Inputs are plain values (numpy arrays, floats, names) given through thread-safe methods: the node's callbacks
convert and validate each message once and call :meth:`PlanningLoop.target_pose`, :meth:`~PlanningLoop.obstacle_pose`,
:meth:`~PlanningLoop.robot_state`, :meth:`~PlanningLoop.goals`, :meth:`~PlanningLoop.scores`,
:meth:`~PlanningLoop.request` (services), :meth:`~PlanningLoop.stage_param` (live parameters) and
:meth:`~PlanningLoop.transition` (lifecycle). Each input only stores the latest value and wakes the worker, so a
120 Hz pose stream never queues; the worker applies the newest state, asks the replanner whether to replan and
decides what to publish. Results leave through an :class:`Outputs` object: trajectories as sample arrays (the exact
arrays the final collision check covered), stops, plan info, status, and the arrays behind markers and camera poses.

No ROS import here: the roadmap server builds and publishes the messages, and tests drive the loop directly.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple, Optional, Sequence

import numpy as np

from . import conversions as cv
from . import core
from .heap import release_free_heap

P = core.Param
#: a spliced trajectory reaches the robot this long after the loop is done with it (publication, the adapter's
#: checks) at most, on top of the age of the robot state the splice was measured from
SPLICE_DELIVERY_S = 0.25
# the robot states a braking base's speed is measured over (s)
REST_VELOCITY_SPAN_S = 0.1
#: the adapter starts a trajectory that does not continue the one under way this long after its publication (s)
ADAPTER_LEAD_S = 0.15
#: the parameters the loop reads (the roadmap server declares them; live ones are read at each use)
LOOP_PARAMS = {
    "plan_on_start": P(False, "plan to goal_regions as soon as the node is active"),
    "auto_replan": P(True, "ask the replanner's triggers after every state update", live=True),
    "trajectory_dt": P(0.1, "sample spacing of the published trajectory (s)", live=True, lo=0.01, hi=1.0),
    "robot_state_timeout_s": P(1.0, "plan only with a robot state (joints and base pose) at most this old", live=True,
                               lo=0.05),
    "publish_markers": P(True, "RViz markers of the scene, roadmap and path", live=True),
    "markers_period_s": P(5.0, "roadmap markers at most this often, built while the planner is idle", live=True,
                          lo=0.1),
    "path_camera_samples": P(200, "camera poses along the path sent to the perception scorer", live=True, lo=2),
    "robot_trigger_period_s": P(0.5, "re-evaluate the triggers on robot progress at most this often", live=True,
                                lo=0.0),
    "safety_step": P(0.05, "spacing (m / rad) of the final collision check along the published trajectory",
                     live=True, lo=0.005, hi=0.2),
    "stop_hold_s": P(0.25, "time_from_start of the stop trajectory's one point", live=True, lo=0.01),
    "stop_horizon_s": P(1.5, "the stop guard: an obstacle pose that collides with the next this-many seconds of the "
                             "trajectory being executed stops the robot at once, on the message's arrival, before the "
                             "replan (0 = off: the robot follows the old trajectory until a new one is planned)",
                        live=True, lo=0.0),
    "alpha": P(-1.0, "Eq. 2 weight of perception against motion cost (< 0: the planner variant's default)",
               live=True, lo=-1.0, hi=1.0),
    "commit_horizon_min_s": P(0.25, "a replan of a robot in motion commits at least this far ahead (s): planning "
                                    "and delivery, measured from recent replans, clamped to [min, max]", live=True,
                              lo=0.0),
    "commit_horizon_max_s": P(1.5, "... and at most this far", live=True, lo=0.0),
    "progress_tolerance_m": P(0.025, "the robot counts as following the trajectory under way (and a replan starts "
                                     "from its committed state) while no point of its collision boxes is further "
                                     "than this from where the trajectory has it (m; below the adapter's path "
                                     "tolerance) and it moves when the trajectory does; otherwise a replan starts "
                                     "from where it is", live=True, lo=0.0),
    "start_tolerance_m": P(0.035, "a plan that starts from the robot's state (not spliced) is not published when the "
                                  "robot, braking from its newest state, has meanwhile come further than this from "
                                  "the trajectory's configurations near its start (m; below the adapter's path "
                                  "tolerance, which would refuse it and stop the robot): a replan from the newest "
                                  "state follows at once while the robot keeps what it executes (0 = off)",
                           live=True, lo=0.0),
}
#: how a heading or joint difference (per rad / m) counts against base distance (m) in finding where along a
#: published trajectory the robot is
TURN_M_PER_RAD = 0.3
#: plans withdrawn in a row for a stale start before one is handed to the robot anyway (the adapter decides)
MAX_STALE_STARTS = 2
#: the replanner's settings a running server changes live (their defaults come from the replan settings file)
LIVE_REPLAN = {"target_move_m": "target translation that counts as a move (m)",
               "target_turn_rad": "target rotation that counts as a move (rad)",
               "obstacle_move_m": "obstacle translation that counts as a move (m)",
               "obstacle_turn_rad": "obstacle rotation that counts as a move (rad)",
               "replan_on_move": "a target/obstacle move alone triggers a replan",
               "score_min": "replan when the predicted normalised score along the remaining path falls below this",
               "score_drop": "... or drops by more than this since the plan",
               "goal_switch_margin": "goal hysteresis (fraction of the current plan's cost)",
               "goal_commit_s": "keep a chosen goal this long (s) unless no path reaches it",
               "goal_commit_growth": "each goal switch multiplies the next commitment by this (>= 1)",
               "final_approach_m": "no score-triggered replan within this base path length of the goal (m)",
               "min_interval_s": "at most one score/move-triggered replan per interval (s)",
               "keep_unless_better": "a replan the view alone triggered replaces the trajectory only when it sees more "
                                     "or is shorter (else the robot keeps driving it)",
               "keep_score_margin": "normalised mean score along the path a new plan must add to replace the current",
               "keep_length_margin": "fraction of the remaining path's motion cost a new plan must save to replace "
                                     "the current",
               "commit": "a robot in motion replans from its committed state: the trajectory under way is kept to its "
                         "first rest instant after planning and delivery, the new plan is spliced on there"}
TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")
REQUESTS = ("plan", "rebuild", "stop")


class TrajectorySamples(NamedTuple):
    """A trajectory as published: one row per point, times from its start (s); the last point at rest."""

    times: np.ndarray  # (M,)
    positions: np.ndarray  # (M, dof), planning joint order
    velocities: np.ndarray  # (M, dof)
    accelerations: np.ndarray  # (M, dof)


class Outputs:
    """Where the loop's results go; every method does nothing here. The roadmap server's implementation builds and
    publishes the messages, a test records the calls. Methods run on the worker thread, except :meth:`stop` (also
    on the thread that delivered an obstacle pose, for the stop guard), :meth:`status` (any thread) and
    :meth:`roadmap_markers`, :meth:`path`, :meth:`base_path` (the loop's side thread, while the planner is idle)."""

    def trajectory(self, samples: TrajectorySamples) -> None:
        """Publish these samples as the robot's trajectory (called only after the final check passed them)."""

    def stop(self, q: np.ndarray, hold_s: float) -> None:
        """Publish a trajectory that holds ``q`` at rest for ``hold_s`` seconds."""

    def info(self, info: dict) -> None:
        """Publish one plan's record (JSON-serialisable: floats, ints, strings, lists, None)."""

    def status(self, text: str, level: str = "info") -> None:
        """Report a line (level info, warning or error)."""

    def state(self, text: str) -> None:
        """The server's state ("building", "ready: ...", "inactive: ...", "unconfigured", "error: ...")."""

    def roadmap_cameras(self, cameras: np.ndarray) -> None:
        """Camera poses (N, 4, 4) of every roadmap node slot, in slot order (the perception scorer's order)."""

    def roadmap_markers(self, scene, cam_xyz: np.ndarray, scores: np.ndarray, base_xy: np.ndarray,
                        edges: np.ndarray) -> None:
        """The roadmap drawn in ``scene``: valid nodes' camera positions (N, 3), normalised scores (N,), base
        positions (N, 2) and edges (E, 2) as row indices into them."""

    def path(self, cameras: np.ndarray, base_xy: np.ndarray, scores: np.ndarray, scene) -> None:
        """Camera poses (K, 4, 4) along the planned path, its base positions (K, 2) and normalised scores (K,)."""

    def base_path(self, positions: np.ndarray) -> None:
        """The base route of a published trajectory (its positions (M, dof))."""


def default_params(replan_settings: str = "") -> dict:
    """Values of :data:`LOOP_PARAMS` and of the live replan settings (defaults from ``replan_settings``, a name in
    config/planners/ or a YAML path; '' = the ReplanSettings defaults)."""
    from psprm_core.paths import resolve_named
    from psprm_core.planning.replanner import ReplanSettings

    rs = ReplanSettings.from_yaml(resolve_named("planner", replan_settings)) if replan_settings else ReplanSettings()
    return {**{k: v.default for k, v in LOOP_PARAMS.items()}, **{k: getattr(rs, k) for k in LIVE_REPLAN}}


class PlanningLoop:
    """Plans and decides on its own worker thread; see the module docstring.

    ``params`` is read live (a parameter change reaches the loop through the same dict, which the caller keeps
    updating); keys it lacks get their :func:`default_params` values. ``clock`` gives the time the input stamps are
    on (s; the node's clock). ``q0`` is the roadmap build's template and the configuration planned from until a
    robot state arrives; ``goals`` (G, dof) the goals used until a goal input arrives. The threads start here;
    :meth:`close` ends them.
    """

    def __init__(self, scene, robot, targets: Sequence[str], spec: core.PlannerSpec, outputs: Outputs, *,
                 obstacles: Sequence[str] = (), q0: Optional[np.ndarray] = None,
                 goals: Optional[np.ndarray] = None, params: Optional[dict] = None,
                 clock: Callable[[], float] = time.time):
        self.scene, self.robot, self.spec, self.outputs = scene, robot, spec, outputs
        self.targets, self.obstacles = list(targets), list(obstacles)
        self.names = list(robot.joint_names)
        self.p = params if params is not None else {}
        for k, v in default_params(spec.replan_settings).items():
            self.p.setdefault(k, v)
        self.clock = clock
        self.q = np.asarray(q0 if q0 is not None else core.start_configuration(robot, scene), float).copy()
        self.goal_configs: Optional[np.ndarray] = None if goals is None else np.asarray(goals, float)

        # shared between the callers' threads and the worker
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._done = threading.Condition(self._lock)
        self._pending = self._empty_pending()
        self._requests: list = []  # (kind, id)
        self._responses: dict = {}
        self._next_id = 0
        self._running = True
        self._live: dict = {}  # parameter changes for the worker to apply
        self._transition: Optional[tuple] = None  # (kind, Event, result list) run by the worker
        self._robot_rx: Optional[float] = None  # monotonic receipt time of the last robot state
        self._input_t: dict = {}  # input label -> monotonic receipt time
        self._pub_lock = threading.RLock()  # a trajectory and a stop are published one at a time
        self.ready = threading.Event()  # set while a roadmap is built or loaded
        self.active = False  # lifecycle: plan and publish only while active
        self.ext_scores: Optional[np.ndarray] = None  # the perception scorer's normalised roadmap node scores
        self.markers_dirty = False  # the roadmap markers are to be rebuilt at the next chance
        # worker-only state
        self.rp = None
        self.planner = None
        self.safety = None  # CollisionChecker with the latest obstacle poses (the final check)
        self.guard = None  # CollisionChecker of the stop guard (its own: the guard runs on the callers' threads)
        self.safety_scene = scene
        self.current: Optional[dict] = None  # result, samples, t_pub, positions, t_zero of what the robot executes
        self._along: Optional[tuple] = None  # (trajectory, time along it, perf_counter) of the last estimate
        self._plan_s: deque = deque(maxlen=20)  # recent replans' time from their start to publication (s)
        self._q_hist: deque = deque()  # (monotonic receipt, q) of every robot state of about the last 0.3 s (lock)
        self.hold = False
        self._robot_check_t = 0.0
        self._waiting_t = 0.0  # last "waiting for base pose" report
        self.waiting = ""  # why nothing is planned now ("" = not waiting)
        self.seq = 0
        self._markers_t = 0.0
        self._rm_ids = np.zeros(0, dtype=np.int64)  # roadmap node slots whose camera poses were last published
        self._rm_cams = np.zeros((0, 4, 4))
        self.build_info: dict = {}
        self.last_latency_ms: Optional[float] = None
        self.counts = {"plans": 0, "kept": 0, "stops": 0, "failed": 0, "refused_unsafe": 0, "late_splices": 0,
                       "stale_starts": 0, "guard_stops": 0, "spliced": 0}
        self._stale_run = 0  # plans withdrawn in a row for a stale start
        self._replan_stale = False  # the next cycle replans: a plan was withdrawn for a stale start
        self.heap_trims, self.heap_trim_ms = 0, None

        self._side = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psprm-publish")
        self._side_jobs: dict = {}  # kind -> (fn, args) of the newest job waiting for the side thread
        self.idle = threading.Event()  # set while the worker waits for input: side jobs (markers) run then
        self.idle.set()
        self._thread = threading.Thread(target=self._worker, name="psprm-planner", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------------ inputs
    @staticmethod
    def _empty_pending() -> dict:
        return {"targets": {}, "obstacles": {}, "robot": None, "robot_t": None, "goals": None, "t_first": None,
                "stamp": None, "guard": None, "target_stamps": {}}

    def target_pose(self, name: str, p: np.ndarray, q: np.ndarray, stamp: float,
                    received: Optional[float] = None) -> None:
        """A target's pose (position (3,), unit quaternion xyzw (4,)) stamped ``stamp`` (s on the clock; the
        target's motion prediction uses it); ``received``: perf_counter at its receipt (the plan latency's start)."""
        self._pose("target", name, p, q, stamp, received)

    def obstacle_pose(self, name: str, p: np.ndarray, q: np.ndarray, stamp: Optional[float] = None,
                      received: Optional[float] = None) -> None:
        """An obstacle's pose. The stop guard runs on the caller's thread before this returns: a pose that collides
        with the next ``stop_horizon_s`` of the trajectory under way has the stop published already."""
        self._pose("obstacle", name, p, q, stamp, received)

    def _pose(self, kind: str, name: str, p, q, stamp: Optional[float], received: Optional[float]) -> None:
        t = time.perf_counter() if received is None else received
        p, q = np.asarray(p, float), np.asarray(q, float)
        with self._lock:
            self._input_t[f"{kind} {name}"] = time.monotonic()
            pend = self._pending
            pend["targets" if kind == "target" else "obstacles"][name] = (p, q)
            if kind == "target":
                pend["target_stamps"][name] = stamp
            if pend["t_first"] is None:
                pend["t_first"] = t
                pend["stamp"] = stamp
                pend["input_age_ms"] = (self.clock() - stamp) * 1e3 if stamp is not None else None
        self._guard(kind, name, p, q)
        self._wake.set()

    def robot_state(self, q: np.ndarray) -> None:
        """The measured robot configuration (every planning joint, the base pose included)."""
        q = np.array(q, float)
        with self._lock:
            self._pending["robot"] = q
            now = self._robot_rx = self._pending["robot_t"] = time.monotonic()
            # every state, at its receipt: a braking base's speed is measured over them (the worker takes only the
            # newest state of each cycle, which may be seconds apart while it plans)
            h = self._q_hist
            h.append((now, q))
            while len(h) > 2 and now - h[1][0] >= 0.3:
                h.popleft()
        self._wake.set()

    def _states(self) -> list:
        """The robot states of about the last 0.3 s, (monotonic receipt time, q), oldest first."""
        with self._lock:
            return list(self._q_hist)

    def goals(self, G: np.ndarray) -> None:
        """Candidate goal configurations (G, dof), G >= 1; the best one wins."""
        with self._lock:
            self._pending["goals"] = np.asarray(G, float).reshape(-1, len(self.names))
            if self._pending["t_first"] is None:
                self._pending["t_first"] = time.perf_counter()
        self._wake.set()

    def scores(self, s: np.ndarray) -> None:
        """The perception scorer's normalised scores of the roadmap node slots (coloured in the markers)."""
        with self._lock:
            self.ext_scores = np.asarray(s, float)
            self.markers_dirty = True

    def request(self, kind: str, timeout: float) -> tuple:
        """Service request ``plan`` (plan now), ``rebuild`` (the roadmap around the current scene) or ``stop`` (a
        stop, held until the next goal or plan request); waits at most ``timeout`` s for the worker's answer.
        Returns (ok, message); the message of a plan is its info JSON."""
        if kind not in REQUESTS:
            raise ValueError(f"unknown request '{kind}' (one of {', '.join(REQUESTS)})")
        with self._lock:
            rid = self._next_id
            self._next_id += 1
            self._requests.append((kind, rid))
        self._wake.set()
        deadline = time.monotonic() + timeout
        with self._done:
            while rid not in self._responses and time.monotonic() < deadline and self._running:
                self._done.wait(0.1)
            return self._responses.pop(rid, (False, "timed out"))

    def stage_param(self, name: str, value) -> None:
        """A live parameter change: checked here (a replan setting the replanner refuses raises ValueError), applied
        by the worker before its next cycle."""
        if name in LIVE_REPLAN and self.rp is not None:
            dataclasses.replace(self.rp.settings, **{name: value})  # ReplanSettings refuses bad values
        with self._lock:
            self._live[name] = value
        self._wake.set()

    def transition(self, kind: str, timeout: Optional[float] = None) -> bool:
        """A lifecycle step: ``configure`` (build or load the roadmap; blocks until it is ready), ``activate``,
        ``deactivate`` (a stop, then no planning), ``cleanup`` (drop the roadmap), ``shutdown``. The steps that
        touch the planner run on the worker; waits at most ``timeout`` s for them. True when the step succeeded."""
        if kind not in TRANSITIONS:
            raise ValueError(f"unknown transition '{kind}' (one of {', '.join(TRANSITIONS)})")
        if kind == "activate":
            self.active = True
            self.outputs.status("active")
            with self._lock:
                resume = self.current is not None  # re-activated after a deactivation: plan again
                self.hold = False
                if self.goal_configs is not None and (self.p["plan_on_start"] or resume):
                    self._requests.append(("plan", -1))
            self._wake.set()
            return True
        if kind == "shutdown":
            if self.active:
                self._run_on_worker("deactivate", timeout=10.0 if timeout is None else timeout)
            self.active = False
            return True
        ok = self._run_on_worker(kind, timeout)
        if kind == "deactivate":
            self.active = False
        return ok

    def _run_on_worker(self, kind: str, timeout: Optional[float] = None) -> bool:
        """Run a lifecycle step on the planner thread (which owns the planner) and wait for it."""
        done, out = threading.Event(), []
        with self._lock:
            self._transition = (kind, done, out)
        self._wake.set()
        done.wait(timeout)
        return bool(out and out[0])

    def close(self) -> None:
        """End the worker and the side thread (waits for them)."""
        self._running = False
        self._wake.set()
        self._thread.join(timeout=10.0)
        self._side.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "PlanningLoop":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ the stop guard
    def _guard(self, kind: str, name: str, p: np.ndarray, q: np.ndarray) -> None:
        """The stop guard, on the caller's thread as each body pose arrives: when the body (an obstacle, or a target
        that is one) at its new pose collides with the robot's newest measured configuration or the next
        ``stop_horizon_s`` of the trajectory being executed, a stop is published at once and a replan is asked for.
        The planner may be busy for a second with a replan; without the guard the robot would drive on along the
        old trajectory meanwhile (MoveIt's plan execution
        likewise stops a trajectory whose remaining path the planning scene invalidates)."""
        cur, horizon, guard = self.current, self.p["stop_horizon_s"], self.guard
        if horizon <= 0 or guard is None or cur is None or cur.get("samples") is None:
            return
        try:
            import torch

            if kind == "target":
                t = self.safety_scene.target(name)
                if not t.obstacle:
                    return
                box = dataclasses.replace(t.as_box(), center=p, quat=q)
            else:
                box = dataclasses.replace(self.safety_scene.obstacle(name), center=p, quat=q)
            states = self._states()
            q_now = states[-1][1] if states else self.q
            ahead = self._remaining(cur["positions"], q_now)
            ahead = ahead[: int(np.ceil(horizon / self.p["trajectory_dt"])) + 1]
            # and where the robot is now: a robot that lags its trajectory or has left it (a turn on the spot behind
            # a spliced start, a push) stands where no sample of it lies
            D = np.vstack([np.asarray(q_now, float)[None], cv.densify_linear(ahead, self.p["safety_step"])])
            if not bool(guard.env_hits(torch.as_tensor(D, dtype=torch.float32), [box]).any()):
                return
        except Exception as exc:  # never lose the caller's thread to the guard
            self.outputs.status(f"stop guard failed: {exc}", "warning")
            return
        with self._pub_lock:
            if self.current is not cur:  # a newer trajectory went out meanwhile: the next pose checks that one
                return
            self.counts["guard_stops"] += 1
            self._publish_stop(f"{kind} {name} moved into the next {horizon:g} s of the trajectory")
        with self._lock:
            self._pending["guard"] = f"{kind} {name}"

    # ------------------------------------------------------------------------------------------------ worker
    def _worker(self) -> None:
        while self._running:
            self._wake.wait(0.1)
            self._wake.clear()
            if not self._running:
                break
            with self._lock:
                tr, self._transition = self._transition, None
            if tr is not None:
                self._do_transition(*tr)
            if self.rp is None:  # not configured: inputs wait (goals are latched, poses keep coming)
                with self._lock:
                    reqs, self._requests = self._requests, []
                self._answer(reqs, False, "the roadmap is not ready (node not configured)")
                continue
            with self._lock:
                pend, self._pending = self._pending, self._empty_pending()
                reqs, self._requests = self._requests, []
                live, self._live = self._live, {}
            self.idle.clear()
            try:
                if live:
                    self._apply_live(live)
                self._cycle(pend, reqs)
            except Exception as exc:  # a bug or a core error must not end the worker
                self.outputs.status(f"planning cycle failed: {exc}", "error")
                self._answer(reqs, False, f"error: {exc}")
            finally:
                self.idle.set()

    def _do_transition(self, kind: str, done: threading.Event, out: list) -> None:
        ok = False
        try:
            if kind == "configure":
                self._build(initial=True)
                if self.p["alpha"] >= 0:
                    self._apply_live({"alpha": self.p["alpha"]})
                self._apply_live({k: self.p[k] for k in LIVE_REPLAN})
                ok = True
            elif kind == "deactivate":
                if self.rp is not None:
                    self.hold = True
                    self._publish_stop("node deactivated")
                self.outputs.state("inactive: " + (self.build_info and f"{self.build_info.get('n_nodes', 0)} nodes"
                                                   or ""))
                ok = True
            elif kind == "cleanup":
                self.rp = self.planner = self.safety = None
                self.current = None
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

    def _apply_live(self, live: dict) -> None:
        rp_changes = {k: v for k, v in live.items() if k in LIVE_REPLAN}
        if rp_changes and self.rp is not None:
            self.rp.update_settings(**rp_changes)
        a = live.get("alpha")
        if a is not None and a >= 0 and self.planner is not None and hasattr(self.planner, "set_alpha"):
            self.planner.set_alpha(float(a))
        if live:
            self.outputs.status(f"parameters applied: {', '.join(f'{k}={v}' for k, v in sorted(live.items()))}")

    def _answer(self, reqs, ok: bool, message: str, kinds=None) -> None:
        with self._done:
            for kind, rid in reqs:
                if rid >= 0 and (kinds is None or kind in kinds):
                    self._responses[rid] = (ok, message)
            self._done.notify_all()

    def _build(self, initial: bool = False) -> None:
        from psprm_core.collision import CollisionChecker

        scene = self.safety_scene
        self.outputs.status(f"{'building' if initial else 'rebuilding'} the {self.spec.variant} roadmap "
                            f"({self.spec.n_nodes} nodes) for scene '{scene.name}'")
        self.outputs.state("building" if initial else "rebuilding")
        planner = core.make_planner_for(scene, self.robot, self.targets, self.spec)
        spec = self.spec if initial else core.PlannerSpec(**{**vars(self.spec), "roadmap_file": "none"})
        info = core.build_or_load(planner, scene, spec, template=self.q, force_build=not initial)
        if info["source"] == "failed":
            raise RuntimeError(info.get("reason", "roadmap build failed"))
        self.planner, self.build_info = planner, info
        self.rp = core.make_replanner(planner, self.spec.replan_settings)
        # re-apply the scene state the new replanner has not seen (targets/obstacles moved since the YAML)
        for t in scene.targets:
            if t.name in self.targets:
                self.rp.update_target(t.name, t.center, t.quat, stamp=self.clock())
        for o in self.obstacles:
            b = scene.obstacle(o)
            self.rp.update_obstacle(o, b.center, b.quat)
        self.rp.set_robot_state(self.q)
        if self.goal_configs is not None:
            self.rp.set_goals(self.goal_configs)
        self.safety = CollisionChecker(self.robot, scene.collision_boxes(), workspace=scene.workspace)
        self.guard = CollisionChecker(self.robot, workspace=scene.workspace)
        text = f"roadmap {info['source']} in {info['seconds']:.1f} s: {info.get('n_nodes', 0)} nodes; ready"
        self.outputs.status(text)
        self.outputs.state(f"ready: {text}")
        self._publish_roadmap()
        self.ready.set()

    def _cycle(self, pend: dict, reqs: list) -> None:
        from psprm_core.errors import PsprmError

        kinds = {k for k, _ in reqs}
        if "rebuild" in kinds:
            try:
                self._build()
                self._answer(reqs, True, json.dumps(self.build_info), kinds={"rebuild"})
            except Exception as exc:
                self.outputs.status(f"rebuild failed, keeping the old roadmap: {exc}", "error")
                self._answer(reqs, False, str(exc), kinds={"rebuild"})
        if self.rp is None:
            self._answer(reqs, False, "roadmap not ready")
            return
        reasons: list = []
        t0 = time.perf_counter()
        boxes_changed = moved = False  # any collision box updated / moved beyond the core's thresholds
        for name, (p, q) in pend["targets"].items():
            try:
                moved |= self.rp.update_target(name, p, q, stamp=pend["target_stamps"].get(name)) is not False
                self.safety_scene = self.safety_scene.with_target_pose(name, p, q)
                boxes_changed |= self.safety_scene.target(name).obstacle
            except (PsprmError, KeyError, ValueError) as exc:
                self.outputs.status(f"target {name} refused by the planner: {exc}", "warning")
        for name, (p, q) in pend["obstacles"].items():
            try:
                moved |= self.rp.update_obstacle(name, p, q) is not False
                self.safety_scene = self.safety_scene.with_obstacle_pose(name, p, q)
                boxes_changed = True
            except (PsprmError, KeyError, ValueError) as exc:
                self.outputs.status(f"obstacle {name} refused by the planner: {exc}", "warning")
        if boxes_changed:
            self.safety.set_boxes(self.safety_scene.collision_boxes())
        try:
            if pend["robot"] is not None:
                q_now = pend["robot"]
                along = self._time_along(q_now)
                # a base that moves with no trajectory under way brakes from a stop: plan from where it will rest
                q_plan = q_now if along is not None else self._rest_point(q_now)
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
            self._publish_stop("stop requested")
            self._answer(reqs, True, "stopped", kinds={"stop"})
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
            self._answer(reqs, False, "no goal", kinds={"plan"})
            return
        if self.hold:
            return
        if not self.active:
            self._answer(reqs, False, "node inactive", kinds={"plan"})
            return
        waiting = self._robot_state_problem()
        if waiting:
            self.waiting = waiting
            if time.monotonic() - self._waiting_t > 2.0 or reasons:
                self._waiting_t = time.monotonic()
                self.outputs.status(f"not planning: {waiting}", "warning")
            self._answer(reqs, False, waiting, kinds={"plan"})
            return
        if self.waiting:
            self.outputs.status("robot state live: planning resumes")
            self.waiting = ""
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
        if reasons:
            pend["timing"] = {"apply_ms": _f((t1 - t0) * 1e3), "triggers_ms": _f((t2 - t1) * 1e3)}
            ok, msg = self._plan(reasons, pend)
            self._answer(reqs, ok, msg, kinds={"plan"})
        self._maybe_republish_markers()

    def _robot_state_problem(self) -> str:
        """Why no plan may start now ("" = none): the measured robot state (joints + base pose, forwarded by the
        monitor only while both are fresh) is missing or older than robot_state_timeout_s."""
        with self._lock:
            rx = self._robot_rx
        if rx is None:
            return "waiting for base pose (no robot state received yet)"
        age = time.monotonic() - rx
        if age > self.p["robot_state_timeout_s"]:
            return f"waiting for base pose (the last robot state is {age:.1f} s old)"
        return ""

    # ------------------------------------------------------------------------------------------------ the robot's motion
    def _commits_to_the_end(self, res) -> bool:
        """Whether the spliced ``res`` keeps the whole rest of the trajectory under way (its commitment ends where
        that trajectory ends, at rest)."""
        cur = self.current
        old = None if cur is None or cur.get("result") is None else cur["result"].trajectory
        return old is not None and res.start_offset_s + res.committed_s >= float(old.duration) - 1e-6

    def _time_along(self, q: np.ndarray) -> Optional[float]:
        """Where the robot is along the trajectory under way (s from its start; its configuration nearest the
        measured ``q``, searched forward from the last estimate), or None: no trajectory under way, it has ended, or
        the robot is further than ``progress_tolerance`` from it (stopped, refused, pushed off): a replan then starts
        where the robot is."""
        from psprm_core.planning.execution import progress_time
        from psprm_core.tracking import displacement

        cur = self.current
        res = None if cur is None else cur.get("result")
        traj = None if res is None else res.trajectory
        # the replanner's plan must be the trajectory under way (a replan not handed to the robot is withdrawn)
        held = None if self.rp is None or self.rp.result is None else self.rp.result.trajectory
        if traj is None or held is not traj:
            self._along = None
            return None
        now = time.perf_counter()
        prev = self._along
        if prev is None or prev[0] is not traj:
            guess = max(0.0, now - cur.get("t_zero", cur["t_pub"]))
        else:
            guess = prev[1] + (now - prev[2])
        t = progress_time(traj, q, guess, window_s=1.5, scale=self.robot.velocity, angle_cols=[2] if self.robot.mobile
                          else [])
        if prev is not None and prev[0] is traj:
            t = max(t, prev[1])  # the robot does not go back along its trajectory
        Pt, Vt, _ = (a[0] for a in traj.evaluate([t]))
        off = float(displacement(self.robot, q, Pt[None])[0])
        # a robot that stands while its trajectory moves (stopped by the adapter, held) does not follow it: a plan
        # spliced on there would start it at speed
        vmax = np.maximum(self.robot.velocity, 1e-6)
        moving = float((np.abs(Vt) / vmax).max()) > 0.2
        standing = self._measured_speed() < 0.02
        if off > self.p["progress_tolerance_m"] or (moving and standing) or t >= float(traj.duration) - 1e-6:
            self._along = None
            return None
        self._along = (traj, t, now)
        return t

    def _rest_point(self, q: np.ndarray) -> np.ndarray:
        """Where a mobile base moving at the velocity of its newest robot states (the newest and the newest one at
        least ``REST_VELOCITY_SPAN_S`` older) comes to rest braking at the robot config's base accelerations
        (:func:`psprm_ros.adapters.braking_configurations`); ``q`` itself for a fixed base or a base at rest. A base
        braking from a stop slows all the while: the speed over the span is its speed at the span's middle, so it is
        brought forward to the newest state at the braking deceleration (a longer average would overstate the speed
        and put the rest point beyond where the base stops)."""
        from .adapters import braking_configurations
        from .base_follower import Limits

        h = self._states()
        if not self.robot.mobile or len(h) < 2:
            return q
        older = [e for e in h[:-1] if h[-1][0] - e[0] >= REST_VELOCITY_SPAN_S]
        if not older:
            return q
        (ta, a), (tb, b) = older[-1], h[-1]
        dt = tb - ta
        th = 0.5 * (a[2] + b[2])
        v = ((b[0] - a[0]) * np.cos(th) + (b[1] - a[1]) * np.sin(th)) / dt
        w = float((b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi) / dt
        if abs(v) < 0.02 and abs(w) < 0.05:
            return q
        lim = Limits.for_robot(self.robot)
        v = np.sign(v) * max(0.0, abs(v) - 0.5 * dt * lim.linear_acceleration)
        w = np.sign(w) * max(0.0, abs(w) - 0.5 * dt * lim.angular_acceleration)
        return braking_configurations(q, (v, w), lim)[-1]

    def _measured_speed(self) -> float:
        """How fast the robot moved over its last robot states (the largest joint speed over its velocity limit; a
        fraction of full speed), from the robot states of the last 0.3 s (at least 0.1 s apart); 1 until known."""
        h = self._states()
        if len(h) < 2 or h[-1][0] - h[0][0] < 0.1:
            return 1.0
        d = np.abs(h[-1][1] - h[0][1])
        if self.robot.mobile:
            d[2] = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
            d[0] = d[1] = float(np.hypot(*(h[-1][1][:2] - h[0][1][:2])))
        return float((d / np.maximum(self.robot.velocity, 1e-6)).max()) / (h[-1][0] - h[0][0])

    def _stale_start(self, samples: TrajectorySamples) -> str:
        """Why a plan from the robot's state no longer starts where the robot is ("" = it does, or no newer state
        came): the robot's newest state, and where it comes to rest braking from it, against the published samples'
        configurations within the adapter's path window of their start
        (:meth:`psprm_core.tracking.CheckedPath.deviation`, the measure the adapter refuses
        by)."""
        from psprm_core.tracking import CheckedPath

        tol = self.p["start_tolerance_m"]
        if tol <= 0:
            return ""
        with self._lock:
            q = self._pending["robot"]
        if q is None:
            return ""
        q = np.asarray(q, float)
        probe = [q]
        if self.robot.mobile:
            probe.append(self._rest_point(q))
        checked = CheckedPath(self.robot, samples.times, samples.positions)
        d = max(checked.deviation(x, 0.0, 2.0)[0] for x in probe)
        if d <= tol:
            return ""
        return (f"the robot moved while planning: braking from its newest state it comes {d:.3f} m from the "
                f"trajectory's start (start tolerance {tol:g} m)")

    def _commit_horizon(self) -> float:
        """Planning and delivery time of a replan (s): 1.5x the 90th percentile of the recent replans' time from
        their start to the trajectory's publication, plus the adapter's lead time, clamped to
        [commit_horizon_min_s, commit_horizon_max_s]."""
        lo, hi = self.p["commit_horizon_min_s"], self.p["commit_horizon_max_s"]
        if not self._plan_s:
            return max(lo, min(hi, 0.5))
        return max(lo, min(hi, 1.5 * float(np.percentile(list(self._plan_s), 90)) + ADAPTER_LEAD_S))

    # ------------------------------------------------------------------------------------------------ planning
    def _samples(self, traj, spliced: bool) -> tuple:
        """(the samples to publish, the start move's duration): the trajectory sampled every ``trajectory_dt`` (plus
        its corners and end); a trajectory not spliced onto the one under way starts at the measured state it was
        planned from (the planner re-aims the camera joints at its start), so that a controller never jumps (a
        spliced one starts on the trajectory under way, where the robot was when the replan began: the adapter
        joins it at the robot's progress)."""
        t, pos, vel, acc = cv.published_samples(traj, self.p["trajectory_dt"])
        shift = 0.0
        if not spliced:
            t, pos, vel, acc, shift = cv.prepend_start_samples(t, pos, vel, acc, self.rp.q, self.robot.velocity,
                                                               self.robot.acceleration,
                                                               [2] if self.robot.mobile else [])
        return TrajectorySamples(t, pos, vel, acc), shift

    def _plan(self, reasons: list, pend: dict) -> tuple:
        """Replan and decide: kept (the robot keeps driving), already at the goal (a stop), refused by the final
        check or ready too late for its splice (withdrawn), published; on failure the last safe trajectory is kept,
        else a stop. Returns (ok, the info JSON)."""
        t0 = time.perf_counter()
        stale_run, self._stale_run = self._stale_run, 0
        horizon = self._commit_horizon()
        res = self.rp.replan(triggers=reasons, horizon_s=horizon)
        t1 = time.perf_counter()
        info = {"seq": self.seq, "reasons": reasons, "success": bool(res.success), "reason": res.reason,
                "failure": res.failure.value,
                "query_ms": _f(res.query_ms), "goal_index": int(res.goal_index),
                "input_stamp": pend["stamp"], "input_age_ms": _f(pend.get("input_age_ms")), **pend.get("timing", {}),
                "replan_ms": _f((t1 - t0) * 1e3), "spliced": bool(res.success and res.committed_s > 0),
                "committed_s": _f(res.committed_s), "commit_horizon_s": _f(horizon)}
        self.seq += 1
        if res.kept:  # the new plan saw no more and was no shorter: the robot keeps driving the current trajectory
            self.counts["kept"] += 1
            info.update(kept=True, stop=False)
            self.outputs.info(info)
            self.outputs.status(f"plan {info['seq']} ({', '.join(reasons)}): {res.reason}")
            return True, json.dumps(info)
        traj = res.trajectory if res.success else None
        if res.success and traj is None:  # already at the goal
            self._publish_stop("already at the goal", info)
            return True, json.dumps(info)
        if traj is not None:
            samples, shift = self._samples(traj, info["spliced"])
            info["start_shift_s"] = _f(shift)
            t2 = time.perf_counter()
            # what is checked is what is published: exactly these positions, against the newest obstacle poses
            self._take_fresh_obstacles()
            unsafe = self._unsafe(samples.positions)
            info.update(msg_ms=_f((t2 - t1) * 1e3), check_ms=_f((time.perf_counter() - t2) * 1e3))
            # a splice the robot may pass before it arrives; not one committed to the end of the trajectory under
            # way: the robot rests there, and the plan starts from that rest whenever it arrives
            late = (info["spliced"] and not self._commits_to_the_end(res)
                    and time.perf_counter() - t0 + SPLICE_DELIVERY_S > res.committed_s)
            stale = ("" if unsafe or late or info["spliced"] or stale_run >= MAX_STALE_STARTS
                     else self._stale_start(samples))
            if unsafe or late or stale:
                # not handed to the robot: the replanner goes back to the trajectory the robot executes, so that the
                # next replan commits along that one
                self.rp.withdraw(res)
            if unsafe:
                info.update(success=False, reason="planner output in collision with the latest obstacles: refused")
                self.counts["refused_unsafe"] += 1
            elif late:
                # the robot passes the splice instant before the trajectory reaches it: it keeps what it executes
                self._plan_s.append(time.perf_counter() - t0)  # the next commitment covers a replan this slow
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
                self._wake.set()
                return False, json.dumps(info)
            else:
                with self._pub_lock:
                    self.outputs.trajectory(samples)
                    t_pub = time.perf_counter()
                    # when the robot is at the trajectory's time 0: the replan's start for a splice (the trajectory
                    # begins where the robot was then), else the adapter's start, its lead time after publication
                    self.current = {"result": res, "samples": samples, "t_pub": t_pub, "positions": samples.positions,
                                    "t_zero": t0 if info["spliced"] else t_pub + ADAPTER_LEAD_S}
                t_pub = self.current["t_pub"]
                self._plan_s.append(t_pub - t0)
                self._along = None
                info["published_stamp"] = self.clock()  # the inputs' stamps are on this clock too
                if self.robot.mobile:  # built on the side thread: ~400 PoseStamped are pure Python
                    self.submit_side("base path", self.outputs.base_path, samples.positions)
                self.counts["plans"] += 1
                self.counts["spliced"] += int(info["spliced"])
                if pend["t_first"]:
                    self.last_latency_ms = (t_pub - pend["t_first"]) * 1e3
                info.update(latency_ms=_f((t_pub - pend["t_first"]) * 1e3) if pend["t_first"] else None,
                            duration_s=_f(traj.duration), n_points=len(samples.times), stop=False)
                self._after_publish(res, info, reasons)
                return True, json.dumps(info)
        # nothing new and safe: keep the last safe trajectory, else stop
        self.counts["failed"] += 1
        self.outputs.status(f"planning failed ({info['reason']})", "warning")
        if self.current is not None and not self._unsafe(self._remaining(self.current["positions"])):
            info.update(stop=False, kept_last=True)
            self.outputs.info(info)
            self.outputs.status("keeping the last safe trajectory", "warning")
        else:
            self._publish_stop(f"no safe trajectory ({info['reason']})", info)
        return False, json.dumps(info)

    def _after_publish(self, res, info: dict, reasons: list) -> None:
        """Plan info and status at once; path camera poses and markers on the side thread (off the latency path)."""
        info["mean_score"] = _f(res.mean_score)  # the planner's score along the path: after publication
        self.outputs.info(info)
        start = (f"spliced {info['committed_s']:.2f} s ahead" if info["spliced"] else "from the robot's state")
        self.outputs.status(f"plan {info['seq']} ({', '.join(reasons)}): {info['n_points']} points, "
                            f"{info['duration_s']:.1f} s, {start}, predicted score {res.mean_score:.3f}, query "
                            f"{res.query_ms:.0f} ms")
        self.submit_side("path markers", self._publish_path, res, self.safety_scene)

    def _publish_stop(self, why: str, info: Optional[dict] = None) -> None:
        with self._pub_lock:
            self.outputs.stop(self.q.copy(), self.p["stop_hold_s"])
            self.counts["stops"] += 1
            self.current = {"result": None, "samples": None, "t_pub": time.perf_counter(),
                            "positions": self.q[None].copy()}
        info = dict(info or {"seq": self.seq, "reasons": [why]})
        info.update(stop=True, stop_reason=why)
        self.outputs.info(info)
        self.outputs.status(f"stop trajectory published: {why}", "warning")

    # ------------------------------------------------------------------------------------------------ the final check
    def _take_fresh_obstacles(self) -> None:
        """Obstacle poses that arrived while the planner was running go into the final check at once (the planner
        sees them in the next cycle): a trajectory is never published unchecked against a pose the loop already
        has."""
        with self._lock:
            fresh = dict(self._pending["obstacles"])
            fresh_t = dict(self._pending["targets"])
        changed = False
        for name, (p, q) in fresh.items():
            try:
                self.safety_scene = self.safety_scene.with_obstacle_pose(name, p, q)
                changed = True
            except (KeyError, ValueError):
                pass
        for name, (p, q) in fresh_t.items():
            try:
                if self.safety_scene.target(name).obstacle:
                    self.safety_scene = self.safety_scene.with_target_pose(name, p, q)
                    changed = True
            except (KeyError, ValueError):
                pass
        if changed:
            self.safety.set_boxes(self.safety_scene.collision_boxes())

    def _unsafe(self, positions: np.ndarray) -> bool:
        """True when any configuration along ``positions`` (densified to ``safety_step``, as a controller
        interpolating linearly between them moves) collides with the latest obstacle poses (or leaves the joint
        limits / workspace)."""
        import torch

        Q = np.asarray(positions, float).reshape(-1, len(self.names))
        if len(Q) == 0:
            return False
        if not np.isfinite(Q).all():
            return True
        Q = cv.densify_linear(Q, self.p["safety_step"])
        bad = self.safety.check(torch.as_tensor(Q, dtype=torch.float32))
        return bool(bad.any())

    def _remaining(self, positions: np.ndarray, q: Optional[np.ndarray] = None) -> np.ndarray:
        """The part of a published trajectory the robot has not traversed yet (from its sample nearest to the robot
        state ``q``, default the one the planner last took). For a mobile base the nearness counts the heading and
        the joints too (``TURN_M_PER_RAD``): a turn on the spot keeps the base where it is, and by position alone
        its first sample would be the nearest however far the turn has gone."""
        Q = np.asarray(positions)
        q = self.q if q is None else q
        if len(Q) <= 1:
            return Q
        if self.robot.mobile:
            turn = np.abs((Q[:, 2] - q[2] + np.pi) % (2 * np.pi) - np.pi)
            d = (np.linalg.norm(Q[:, :2] - q[:2], axis=1) + TURN_M_PER_RAD * turn
                 + TURN_M_PER_RAD * np.abs(Q[:, 3:] - q[3:]).max(axis=1, initial=0.0))
        else:
            d = np.linalg.norm(Q - q, axis=1)
        return Q[int(np.argmin(d)):]

    # ------------------------------------------------------------------------------------------------ side jobs
    def submit_side(self, what: str, fn, *args) -> None:
        """Queue a job for the side thread; a job of the same kind still waiting is replaced (only the newest path
        or roadmap matters: while the planner replans back to back, jobs would otherwise pile up faster than they
        run)."""
        with self._lock:
            queued = what in self._side_jobs
            self._side_jobs[what] = (fn, args)
        if not queued:
            self._side.submit(self._side_job, what)

    def _side_job(self, what: str) -> None:
        """Run the newest job of kind ``what`` once the planner is idle (waits at most 1 s): building markers is pure
        Python and would otherwise compete with a replan for the interpreter."""
        self.idle.wait(1.0)
        with self._lock:
            fn, args = self._side_jobs.pop(what)
        try:
            fn(*args)
        except Exception as exc:  # never lose the side thread
            self.outputs.status(f"{what} failed: {exc}", "warning")

    def trim_heap(self) -> None:
        """Side job: return the C heap's free pages to the system (:mod:`.heap`)."""
        ms = release_free_heap()
        if ms is not None:
            self.heap_trims, self.heap_trim_ms = self.heap_trims + 1, ms

    # ------------------------------------------------------------------------------------------------ markers
    def _camera_poses(self, Q: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.robot.camera_poses(torch.as_tensor(np.asarray(Q), dtype=torch.float32)).double().numpy()

    def _publish_roadmap(self) -> None:
        """Camera poses of every roadmap node slot (pruned ones too: the perception scorer's scores follow this order),
        then the markers. Called after a build and whenever the roadmap has grown (repair)."""
        pl = self.planner
        ids = np.nonzero(pl.roadmap_mask())[0]
        T = self._camera_poses(pl.graph.configs[ids])
        self._rm_ids, self._rm_cams = ids, T
        self.outputs.roadmap_cameras(T)
        self.markers_dirty = True
        self._maybe_republish_markers(force=True)

    def _node_scores(self) -> np.ndarray:
        """Normalised scores of the published roadmap nodes: the perception scorer's when they match, else the
        planner's."""
        pl, ids = self.planner, self._rm_ids
        s = self.ext_scores
        if s is None or len(s) != len(ids):
            s = np.full(len(ids), np.nan)
            have = ids < len(pl.node_scores)
            s[have] = np.asarray(pl.node_scores, float)[ids[have]]
        return s * float(getattr(pl, "score_scale", 1.0))

    def _maybe_republish_markers(self, force: bool = False) -> None:
        """Roadmap markers: a snapshot of the roadmap taken here (worker thread, cheap array copies), the markers built
        and published on the side thread while the planner is idle."""
        if not self.p["publish_markers"] or self.planner is None:
            return
        now = time.monotonic()
        if not force and (not self.markers_dirty or now - self._markers_t < self.p["markers_period_s"]):
            return
        pl, g = self.planner, self.planner.graph
        if len(self._rm_ids) != pl.n_roadmap_nodes:  # the roadmap grew (repair): camera poses of its slots first
            self._publish_roadmap()  # (calls back with force=True)
            return
        self._markers_t, self.markers_dirty = now, False
        ids = self._rm_ids
        keep = g.node_valid[ids]
        pos = np.full(g.n_nodes, -1, dtype=np.int64)
        pos[ids[keep]] = np.arange(int(keep.sum()))
        eids = pl.roadmap_edge_ids()
        e = np.stack([pos[g.edge_u[eids]], pos[g.edge_v[eids]]], 1)
        e = e[(e >= 0).all(1)]
        snap = (self.safety_scene, self._rm_cams[keep, :3, 3].copy(), self._node_scores()[keep].copy(),
                g.configs[ids[keep], :2].copy(), e)
        self.submit_side("roadmap markers", self.outputs.roadmap_markers, *snap)

    def _publish_path(self, res, scene) -> None:
        """Side job: camera poses along the path (for the perception scorer), its base positions and scores."""
        D = res.dense if res.dense is not None else res.waypoints
        k = max(1, int(np.ceil(len(D) / max(2, self.p["path_camera_samples"]))))
        idx = np.unique(np.r_[np.arange(0, len(D), k), len(D) - 1])
        T = self._camera_poses(D[idx])
        scores = res.dense_scores[idx] if res.dense_scores is not None else np.zeros(len(idx))
        scores = scores * float(getattr(self.planner, "score_scale", 1.0))
        self.outputs.path(T, np.asarray(D[idx, :2], float), scores, scene)

    # ------------------------------------------------------------------------------------------------ diagnostics
    def diagnostics(self, lifecycle: str) -> tuple:
        """(level, message, values) of the loop's diagnostic status; ``lifecycle`` is the node's state label."""
        if self.rp is None:
            level, msg = core.DIAG_WARN, f"{lifecycle}: roadmap not ready"
        elif not self.active:
            level, msg = core.DIAG_WARN, f"{lifecycle}"
        elif self.waiting:
            level, msg = core.DIAG_WARN, self.waiting
        else:
            level, msg = core.DIAG_OK, "planning" if not self.idle.is_set() else "ready"
        now = time.monotonic()
        with self._lock:
            rx = self._robot_rx
            ages = {f"age_s {k}": now - t for k, t in self._input_t.items()}
        vals = {"lifecycle": lifecycle,
                "roadmap_nodes": int(self.planner.n_roadmap_nodes) if self.planner else 0,
                **self.counts, "last_latency_ms": self.last_latency_ms if self.last_latency_ms is not None else "",
                "robot_state_age_s": (now - rx) if rx is not None else "never", **ages,
                "heap_trims": self.heap_trims, "last_heap_trim_ms": self.heap_trim_ms if self.heap_trim_ms is not None
                else ""}
        rp = self.rp
        if rp is not None:  # the replanner's decisions: replans adopted / declined (kept), goal switches
            vals.update(adopted_replans=rp.adopted, declined_replans=rp.declined, goal_switches=rp.goal_switches)
        return level, msg, vals


def _f(x) -> Optional[float]:
    """A finite float, else None (JSON has no NaN)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None
