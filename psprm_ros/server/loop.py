"""The roadmap server's planning loop: one worker thread that owns the planner, the core :class:`Replanner` and
every decision about what the robot is sent.

Inputs are plain values (numpy arrays, floats, names) given through thread-safe methods: the node's callbacks
convert and validate each message once and call :meth:`PlanningLoop.target_pose`, :meth:`~PlanningLoop.obstacle_pose`,
:meth:`~PlanningLoop.robot_state`, :meth:`~PlanningLoop.goals`, :meth:`~PlanningLoop.scores`,
:meth:`~PlanningLoop.request` (services), :meth:`~PlanningLoop.stage_param` (live parameters) and
:meth:`~PlanningLoop.transition` (lifecycle). Each input only stores the latest value and wakes the worker
(:class:`~.inputs.Inputs`); the worker (:class:`~.worker.PlanningWorker`) applies the newest state, asks the
replanner whether to replan and decides what to publish. Results leave through an :class:`~.outputs.Outputs`
object: trajectories as sample arrays (the exact arrays the final collision check covered,
:class:`~.checks.FinalCheck`), stops, plan info, status, and the arrays behind markers and camera poses
(:class:`~.views.RoadmapViews`). The robot's measured motion (speed, rest point, progress along the trajectory under
way) is :class:`~.robot_motion.RobotMotion`; what it executes, :class:`~.executing.Executing`.

No ROS import here: the roadmap server builds and publishes the messages, and tests drive the loop directly.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Callable, Optional, Sequence

import numpy as np

from .. import core, planner_setup
from ..heap import release_free_heap
from .diagnostics import loop_diagnostics
from .executing import Executing
from .inputs import Inputs
from .outputs import Outputs
from .params import TRANSITIONS, default_params, live_replan
from .robot_motion import RobotMotion
from .views import RoadmapViews, SideJobs
from .worker import PlanningWorker


class PlanningLoop:
    """Plans and decides on its own worker thread; see the module docstring.

    ``params`` is read live (a parameter change reaches the loop through the same dict, which the caller keeps
    updating); keys it lacks get their :func:`~.params.default_params` values. ``clock`` gives the time the input
    stamps are on (s; the node's clock). ``q0`` is the roadmap build's template and the configuration planned from
    until a robot state arrives; ``goals`` (G, dof) the goals used until a goal input arrives; ``ready`` the event
    set while a roadmap is built or loaded (one of the caller's, so that it can be waited on before the loop exists).
    The threads start here; :meth:`close` ends them.
    """

    def __init__(self, scene, robot, targets: Sequence[str], spec: planner_setup.PlannerSpec, outputs: Outputs, *,
                 obstacles: Sequence[str] = (), q0: Optional[np.ndarray] = None,
                 goals: Optional[np.ndarray] = None, params: Optional[dict] = None,
                 clock: Callable[[], float] = time.time, ready: Optional[threading.Event] = None):
        self.robot, self.spec, self.outputs = robot, spec, outputs
        self.names = list(robot.joint_names)
        self.p = params if params is not None else {}
        for k, v in default_params(spec.replan_settings).items():
            self.p.setdefault(k, v)
        self.clock = clock
        self.inputs = Inputs(clock)  # shared between the callers' threads and the worker
        self.motion = RobotMotion(robot)  # every robot state at its receipt
        self.counts = {"plans": 0, "kept": 0, "stops": 0, "failed": 0, "refused_unsafe": 0, "late_splices": 0,
                       "stale_starts": 0, "guard_stops": 0, "spliced": 0}
        self.executing = Executing(robot, outputs, self.p, clock, self.counts)  # what the robot executes
        self._running = True
        self.ready = ready if ready is not None else threading.Event()  # set while a roadmap is built or loaded
        self.ready.clear()
        self.active = False  # lifecycle: plan and publish only while active
        self.idle = threading.Event()  # set while the worker waits for input: side jobs (markers) run then
        self.idle.set()
        self.side = SideJobs(self.idle, self.outputs.status)
        self.views = RoadmapViews(robot, outputs, self.p, self.side)
        q0 = q0 if q0 is not None else core.start_configuration(robot, scene)
        self.worker = PlanningWorker(self, scene, targets, spec, obstacles, q0, goals, lambda: self.active)
        self.heap_trims, self.heap_trim_ms = 0, None
        self._thread = threading.Thread(target=self._run, name="psprm-planner", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------------ state
    @property
    def rp(self):
        """The core :class:`~psprm_core.planning.replanner.Replanner` (None while unconfigured)."""
        return self.worker.rp

    @property
    def planner(self):
        return self.worker.planner

    @property
    def build_info(self) -> dict:
        return self.worker.build_info

    @property
    def waiting(self) -> str:
        """Why nothing is planned now ("" = not waiting)."""
        return self.worker.waiting

    @property
    def safety_scene(self):
        """The scene with the newest obstacle and target poses the loop has applied."""
        return self.worker.safety_scene

    @property
    def current(self) -> Optional[dict]:
        """What the robot executes (:attr:`.executing.Executing.current`)."""
        return self.executing.current

    @property
    def last_latency_ms(self) -> Optional[float]:
        return self.executing.last_latency_ms

    @property
    def markers_dirty(self) -> bool:
        return self.views.dirty

    @markers_dirty.setter
    def markers_dirty(self, value: bool) -> None:
        self.views.dirty = bool(value)

    # ------------------------------------------------------------------------------------------------ inputs
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
        p, q = np.asarray(p, float), np.asarray(q, float)
        self.inputs.pose(kind, name, p, q, stamp, received)
        self._guard(kind, name, p, q)
        self.inputs.wake.set()

    def robot_state(self, q: np.ndarray, base_velocity: Optional[np.ndarray] = None) -> None:
        """The measured robot configuration (every planning joint, the base pose included) and, where measured
        (odometry, tf), the base's velocity (v, omega). Every state, at its receipt, feeds the robot's measured
        motion (the worker takes only the newest state of each cycle, which may be seconds apart while it
        plans)."""
        q = np.array(q, float)
        self.motion.add(q, self.inputs.robot_state(q), base_velocity)
        self.inputs.wake.set()

    def goals(self, G: np.ndarray) -> None:
        """Candidate goal configurations (G, dof), G >= 1; the best one wins."""
        self.inputs.goals(np.asarray(G, float).reshape(-1, len(self.names)))
        self.inputs.wake.set()

    def scores(self, s: np.ndarray) -> None:
        """The perception scorer's normalised scores of the roadmap node slots (coloured in the markers)."""
        self.views.ext_scores = np.asarray(s, float)
        self.views.dirty = True

    def request(self, kind: str, timeout: float) -> tuple:
        """Service request ``plan`` (plan now), ``rebuild`` (the roadmap around the current scene) or ``stop`` (a
        stop, held until the next goal or plan request); waits at most ``timeout`` s for the worker's answer.
        Returns (ok, message); the message of a plan is its info JSON."""
        return self.inputs.request(kind, timeout, lambda: self._running)

    def stage_param(self, name: str, value) -> None:
        """A live parameter change: checked here (a replan setting the replanner refuses, or planner settings that
        do not go together, raise :class:`~psprm_core.errors.PsprmError`), applied by the worker before its next
        cycle."""
        rp, planner = self.worker.rp, self.worker.planner
        if name in live_replan() and rp is not None:
            dataclasses.replace(rp.settings, **{name: value})  # ReplanSettings refuses bad values
        if name in self.spec.settings and planner is not None:
            planner_setup.resolve_live_settings(planner.settings, {name: value},
                                                self.spec.variant).validate("ROS parameter")
        self.inputs.live(name, value)
        self.inputs.wake.set()

    def transition(self, kind: str, timeout: Optional[float] = None) -> bool:
        """A lifecycle step: ``configure`` (build or load the roadmap; blocks until it is ready), ``activate``,
        ``deactivate`` (a stop, then no planning), ``cleanup`` (drop the roadmap), ``shutdown``. The steps that
        touch the planner run on the worker; waits at most ``timeout`` s for them. True when the step succeeded."""
        if kind not in TRANSITIONS:
            raise ValueError(f"unknown transition '{kind}' (one of {', '.join(TRANSITIONS)})")
        if kind == "activate":
            self.active = True
            self.outputs.status("active")
            with self.inputs.lock:
                resume = self.current is not None  # re-activated after a deactivation: plan again
                self.worker.hold = False
                if self.worker.goal_configs is not None and (self.p["plan_on_start"] or resume):
                    self.inputs.ask("plan")
            self.inputs.wake.set()
            return True
        if kind == "shutdown":
            if self.active:
                self.inputs.run_step("deactivate", timeout=10.0 if timeout is None else timeout)
            self.active = False
            return True
        ok = self.inputs.run_step(kind, timeout)
        if kind == "deactivate":
            self.active = False
        return ok

    def close(self) -> None:
        """End the worker and the side thread (waits for them)."""
        self._running = False
        self.inputs.wake.set()
        self._thread.join(timeout=10.0)
        self.side.close()

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
        old trajectory meanwhile (MoveIt's plan execution likewise stops a trajectory whose remaining path the
        planning scene invalidates)."""
        cur, horizon, guard = self.current, self.p["stop_horizon_s"], self.worker.guard
        if horizon <= 0 or guard is None or cur is None or cur.get("samples") is None:
            return
        try:
            box = guard.body(kind, name, p, q)
            if box is None:
                return
            q_now = self.motion.newest()
            q_now = self.worker.q if q_now is None else q_now
            if not guard.hits(box, q_now, cur["positions"], horizon, self.p["trajectory_dt"], self.p["safety_step"]):
                return
        except Exception as exc:  # never lose the caller's thread to the guard
            self.outputs.status(f"stop guard failed: {exc}", "warning")
            return
        with self.executing.lock:
            if self.current is not cur:  # a newer trajectory went out meanwhile: the next pose checks that one
                return
            self.counts["guard_stops"] += 1
            self.worker.publish_stop(f"{kind} {name} moved into the next {horizon:g} s of the trajectory")
        self.inputs.guard_stopped(f"{kind} {name}")

    # ------------------------------------------------------------------------------------------------ worker
    def _run(self) -> None:
        """The worker thread: each wake-up takes a lifecycle step, then everything pending, into one cycle of
        :class:`~.worker.PlanningWorker`."""
        worker = self.worker
        while self._running:
            self.inputs.wake.wait(0.1)
            self.inputs.wake.clear()
            if not self._running:
                break
            tr = self.inputs.take_step()
            if tr is not None:
                worker.do_transition(*tr)
            if worker.rp is None:  # not configured: inputs wait (goals are latched, poses keep coming)
                self.inputs.answer(self.inputs.take_requests(), False, "the roadmap is not ready (node not configured)")
                continue
            pend, reqs, live = self.inputs.take()
            self.idle.clear()
            try:
                if live:
                    worker.apply_live(live)
                worker.cycle(pend, reqs)
            except Exception as exc:  # a bug or a core error must not end the worker
                self.outputs.status(f"planning cycle failed: {exc}", "error")
                self.inputs.answer(reqs, False, f"error: {exc}")
            finally:
                self.idle.set()

    # ------------------------------------------------------------------------------------------------ side jobs
    def submit_side(self, what: str, fn, *args) -> None:
        """Queue a job for the side thread (:class:`~.views.SideJobs`)."""
        self.side.submit(what, fn, *args)

    def trim_heap(self) -> None:
        """Side job: return the C heap's free pages to the system (:mod:`psprm_ros.heap`)."""
        ms = release_free_heap()
        if ms is not None:
            self.heap_trims, self.heap_trim_ms = self.heap_trims + 1, ms

    # ------------------------------------------------------------------------------------------------ diagnostics
    def diagnostics(self, lifecycle: str) -> tuple:
        """(level, message, values) of the loop's diagnostic status (:func:`~.diagnostics.loop_diagnostics`);
        ``lifecycle`` is the node's state label."""
        return loop_diagnostics(self, lifecycle)
