"""``roadmap_server``: builds or loads the PS-PRM roadmap, plans and publishes joint trajectories.

Inputs (validated again here: scene frame, finite values, age):
  ``/psprm/state/targets/<name>``, ``/psprm/state/obstacles/<name>`` (geometry_msgs/PoseStamped, sensor-data QoS),
  ``/psprm/state/robot`` (sensor_msgs/JointState with planning joint names), ``/psprm/state/goals``
  (trajectory_msgs/JointTrajectory whose points are candidate goal configurations; the best one wins). The
  ``replan_monitor`` publishes all of them from the raw mocap, ``/joint_states`` and goal topics.
Outputs:
  ``/psprm/trajectory`` (trajectory_msgs/JointTrajectory: planning joints of the robot config, time-parameterised),
  ``/psprm/plan_info`` (std_msgs/String, JSON per plan), ``/psprm/roadmap/camera_poses`` and
  ``/psprm/path/camera_poses`` (geometry_msgs/PoseArray, for the perception scorer), ``~/markers`` (scene and
  roadmap) and ``~/path_markers`` (scene and the current path; visualization_msgs/MarkerArray, latched separately so
  a late RViz sees both), ``~/status`` (std_msgs/String).
Services (std_srvs/Trigger): ``~/plan`` (plan now), ``~/rebuild`` (rebuild the roadmap around the current scene),
``~/stop`` (publish a stop trajectory and hold until the next goal or plan request).

All planning runs on one worker thread: callbacks only store the latest message (so a 120 Hz stream never queues),
and the worker applies the newest state to the core :class:`Replanner`, asks it whether to replan and publishes.
Every trajectory is re-checked with a :class:`CollisionChecker` holding the latest obstacle poses before it is
published; when no safe trajectory exists the last safe one is kept, or a stop trajectory is published.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections import deque
from typing import Optional

import numpy as np

from . import conversions as cv
from . import core
from .heap import release_free_heap

P = core.Param
# a spliced trajectory reaches the robot this long after the server is done with it (publication, the adapter's
# checks) at most, on top of the age of the robot state the splice was measured from
SPLICE_DELIVERY_S = 0.25
SERVER_PARAMS = {
    "start_problem": P("", "scene problem whose start is the template of the roadmap build; planning waits for the "
                           "measured robot state (/psprm/state/robot)"),
    "goal_regions": P([], "goals used before any goal message arrives ([] = wait for a goal)"),
    "plan_on_start": P(False, "plan to goal_regions as soon as the node is active"),
    "auto_replan": P(True, "ask the replanner's triggers after every state update", live=True),
    "trajectory_dt": P(0.1, "sample spacing of the published trajectory (s)", live=True, lo=0.01, hi=1.0),
    "max_pose_age_s": P(1.0, "refuse pose messages older than this (0 = no check)", live=True, lo=0.0),
    "robot_state_timeout_s": P(1.0, "plan only with a robot state (joints and base pose) at most this old", live=True,
                               lo=0.05),
    "publish_markers": P(True, "RViz markers of the scene, roadmap and path", live=True),
    "marker_max_edges": P(5000, "roadmap edges drawn (an evenly spread subset; ~9 ms per 1000)", live=True, lo=0),
    "markers_period_s": P(5.0, "roadmap markers at most this often, built while the planner is idle", live=True,
                          lo=0.1),
    "path_camera_samples": P(200, "camera poses along the path sent to the perception scorer", live=True, lo=2),
    "service_timeout_s": P(120.0, "longest wait of a service call for the planner", live=True, lo=1.0),
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
    "diagnostics_period_s": P(1.0, "period of /diagnostics", lo=0.1),
    "commit_horizon_min_s": P(0.25, "a replan of a robot in motion commits at least this far ahead (s): planning "
                                    "and delivery, measured from recent replans, clamped to [min, max]", live=True,
                              lo=0.0),
    "commit_horizon_max_s": P(1.5, "... and at most this far", live=True, lo=0.0),
    "progress_tolerance_m": P(0.025, "the robot counts as following the trajectory under way (and a replan starts "
                                     "from its committed state) while no point of its collision boxes is further "
                                     "than this from where the trajectory has it (m; below the adapter's path "
                                     "tolerance) and it moves when the trajectory does; otherwise a replan starts "
                                     "from where it is", live=True, lo=0.0),
    "heap_trim_period_s": P(60.0, "give the C heap's free memory back to the system this often, while the planner "
                                  "is idle (0 = never; psprm_ros.heap)", lo=0.0),
}
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
PLANNER_DESCRIPTIONS = {"variant": "PS-PRM variant (neural-psprm-line, psprm-line, ...)",
                        "n_nodes": "roadmap nodes", "seed": "roadmap sampling seed",
                        "planner_settings": "PSPRMSettings YAML ('' = config/planners/psprm.yaml)",
                        "collision_padding": "clearance (m) the planner keeps from every obstacle, so that a robot "
                                             "tracking its path a few cm off stays clear (overrides the settings "
                                             "file's edges.collision_padding; a start inside it is moved out first)",
                        "replan_settings": "ReplanSettings: a name in config/planners/ or a YAML path",
                        "roadmap_file": "'' = cache under ~/.cache/psprm/roadmaps; 'none' = always build",
                        "checkpoint": "surrogate checkpoint ('' = the shipped one)"}


def planner_params() -> dict:
    return {k: P(v, PLANNER_DESCRIPTIONS.get(k, ""), rebuild=True) for k, v in core.PLANNER_PARAMS.items()}


def replan_params(settings_name: str) -> dict:
    """Live replanning thresholds with the settings file's values as defaults."""
    from psprm_core.paths import resolve_named
    from psprm_core.planning.replanner import ReplanSettings

    rs = ReplanSettings.from_yaml(resolve_named("planner", settings_name)) if settings_name else ReplanSettings()
    out = {}
    for k, d in LIVE_REPLAN.items():
        v = getattr(rs, k)
        lo = 1.0 if k == "goal_commit_growth" else 0.0  # a factor: below 1 the commitment would shrink
        out[k] = P(v, d, live=True) if isinstance(v, bool) else P(float(v), d, live=True, lo=lo)
    return out


class RoadmapServer:
    """The node (composition over inheritance keeps construction order explicit; ``.node`` is the rclpy Node)."""

    def __init__(self, node_name: str = core.SERVER_NAME, **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseArray, PoseStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32MultiArray, String
        from std_srvs.srv import Trigger
        from trajectory_msgs.msg import JointTrajectory
        from visualization_msgs.msg import MarkerArray
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Path
        import torch

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        common = {**core.common_params(), **planner_params(), **SERVER_PARAMS}
        self.p = core.declare_params(node, common)
        self.spec_params = {**common, **replan_params(self.p["replan_settings"])}
        self.p.update(core.declare_params(node, self.spec_params))
        torch.set_num_threads(max(1, self.p["torch_threads"]))
        self.spec = core.PlannerSpec(**{k: self.p[k] for k in core.PLANNER_PARAMS})
        self.scene, self.robot = core.load_scene_and_robot(self.p["scene"], self.p["robot"], node=node, params=self.p)
        self.frame = self.scene.frame
        self.targets = core.scene_targets(self.scene, self.p["targets"])
        for o in self.p["dynamic_obstacles"]:
            self.scene.obstacle(o)
        self.names = list(self.robot.joint_names)
        self.q = core.start_configuration(self.robot, self.scene, self.p["start_problem"])
        self.goals: Optional[np.ndarray] = None
        if self.p["goal_regions"]:
            self.goals = core.goal_region_configurations(self.robot, self.scene, self.p["goal_regions"])

        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_traj = node.create_publisher(JointTrajectory, core.TRAJECTORY_TOPIC, latched)
        self.pub_info = node.create_publisher(String, core.PLAN_INFO_TOPIC, 10)
        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_state = node.create_publisher(String, core.SERVER_STATE_TOPIC, latched)
        self.pub_markers = node.create_publisher(MarkerArray, "~/markers", latched)
        self.pub_path_markers = node.create_publisher(MarkerArray, "~/path_markers", latched)
        self.pub_rm_cams = node.create_publisher(PoseArray, core.ROADMAP_CAMERAS_TOPIC, latched)
        self.pub_path_cams = node.create_publisher(PoseArray, core.PATH_CAMERAS_TOPIC, latched)
        self.pub_base_path = node.create_publisher(Path, core.BASE_PATH_TOPIC, latched)
        self.pub_diag = node.create_publisher(DiagnosticArray, core.DIAGNOSTICS_TOPIC, 10)

        cb = MutuallyExclusiveCallbackGroup()
        for t in self.targets:
            node.create_subscription(PoseStamped, core.target_topic(t), self._pose_cb("target", t),
                                     qos_profile_sensor_data, callback_group=cb)
        for o in self.p["dynamic_obstacles"]:
            node.create_subscription(PoseStamped, core.obstacle_topic(o), self._pose_cb("obstacle", o),
                                     qos_profile_sensor_data, callback_group=cb)
        node.create_subscription(JointState, core.ROBOT_STATE_TOPIC, self._robot_cb, qos_profile_sensor_data,
                                 callback_group=cb)
        node.create_subscription(JointTrajectory, core.GOALS_TOPIC, self._goals_cb, latched, callback_group=cb)
        node.create_subscription(Float32MultiArray, core.ROADMAP_SCORES_TOPIC, self._scores_cb, 1, callback_group=cb)
        srv = ReentrantCallbackGroup()
        node.create_service(Trigger, "~/plan", self._srv("plan"), callback_group=srv)
        node.create_service(Trigger, "~/rebuild", self._srv("rebuild"), callback_group=srv)
        node.create_service(Trigger, "~/stop", self._srv("stop"), callback_group=srv)

        # state shared between callbacks and the worker
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._done = threading.Condition(self._lock)
        self._pending = self._empty_pending()
        self._requests: list = []  # (kind, id)
        self._responses: dict = {}
        self._next_id = 0
        self._running = True
        self.ready = threading.Event()
        # worker-only state
        self.rp = None
        self.planner = None
        self.safety = None  # CollisionChecker with the latest obstacle poses
        self.safety_scene = self.scene
        self.current = None  # dict: result, msg, t_pub, positions
        self._along: Optional[tuple] = None  # (trajectory, time along it, perf_counter) of the last estimate
        self._plan_s: deque = deque(maxlen=20)  # recent replans' time from their start to publication (s)
        self._q_hist: deque = deque()  # (monotonic, q) of the robot states of about the last 0.3 s
        self.hold = False
        self._robot_check_t = 0.0
        self.seq = 0
        self.ext_scores: Optional[np.ndarray] = None
        self._markers_dirty = False
        self._markers_t = 0.0
        self._rm_ids = np.zeros(0, dtype=np.int64)  # roadmap node slots whose camera poses were last published
        self.build_info: dict = {}
        self.active = False  # lifecycle: plan and publish only while active
        self._robot_rx: Optional[float] = None  # monotonic receipt time of the last robot state
        self._waiting_t = 0.0  # last "waiting for base pose" report
        self.waiting = ""  # why nothing is planned now ("" = not waiting)
        self._live: dict = {}  # parameter changes for the worker to apply
        self._transition: Optional[tuple] = None  # (kind, Event, result list) run by the worker
        self.last_latency_ms: Optional[float] = None
        self.counts = {"plans": 0, "kept": 0, "stops": 0, "failed": 0, "refused_unsafe": 0, "late_splices": 0, "guard_stops": 0,
                       "spliced": 0}
        self.guard = None  # CollisionChecker of the stop guard (its own: the guard runs on the executor thread)
        self._pub_lock = threading.RLock()  # a trajectory and a stop are published one at a time
        self._input_t: dict = {}  # input label -> monotonic receipt time
        from concurrent.futures import ThreadPoolExecutor

        self._side = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psprm-publish")
        self._side_jobs: dict = {}  # kind -> (fn, args) of the newest job waiting for the side thread
        self._idle = threading.Event()  # set while the worker waits for input: side jobs (markers) run then
        self._idle.set()
        self._thread = threading.Thread(target=self._worker, name="psprm-planner", daemon=True)
        self._thread.start()
        core.install_param_callback(node, self.spec_params, self.p, self._stage_param)
        node.create_timer(self.p["diagnostics_period_s"], self._diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.heap_trims, self.heap_trim_ms = 0, None
        if self.p["heap_trim_period_s"] > 0:
            node.create_timer(self.p["heap_trim_period_s"], lambda: self._submit_side("heap trim", self._trim_heap),
                              callback_group=MutuallyExclusiveCallbackGroup())

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        """Build or load the roadmap (blocks until it is ready)."""
        return self._run_on_worker("configure")

    def on_activate(self, state) -> bool:
        self.active = True
        self.status("active")
        with self._lock:
            resume = self.current is not None  # re-activated after a deactivation: plan again
            self.hold = False
            if self.goals is not None and (self.p["plan_on_start"] or resume):
                self._requests.append(("plan", -1))
        self._wake.set()
        return True

    def on_deactivate(self, state) -> bool:
        """Stop the robot (a stop trajectory), then stop planning."""
        ok = self._run_on_worker("deactivate")
        self.active = False
        return ok

    def on_cleanup(self, state) -> bool:
        return self._run_on_worker("cleanup")

    def on_shutdown(self, state) -> bool:
        if self.active:
            self._run_on_worker("deactivate", timeout=10.0)
        self.active = False
        return True

    def _run_on_worker(self, kind: str, timeout: Optional[float] = None) -> bool:
        """Run a lifecycle step on the planner thread (which owns the planner) and wait for it."""
        done, out = threading.Event(), []
        with self._lock:
            self._transition = (kind, done, out)
        self._wake.set()
        done.wait(timeout)
        return bool(out and out[0])

    def _stage_param(self, name: str, value) -> None:
        """Set-parameters callback (executor thread): check, then hand the change to the worker."""
        if name in LIVE_REPLAN and self.rp is not None:
            import dataclasses

            dataclasses.replace(self.rp.settings, **{name: value})  # ReplanSettings refuses bad values
        with self._lock:
            self._live[name] = value
        self._wake.set()

    # ------------------------------------------------------------------------------------------------ callbacks
    @staticmethod
    def _empty_pending() -> dict:
        return {"targets": {}, "obstacles": {}, "robot": None, "goals": None, "t_first": None, "stamp": None,
                "guard": None, "target_stamps": {}}

    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    def set_state(self, text: str) -> None:
        """The latched server state (late subscribers see it too)."""
        from std_msgs.msg import String

        self.pub_state.publish(String(data=text))

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _pose_cb(self, kind: str, name: str):
        def cb(msg):
            t = time.perf_counter()
            try:
                p, q = cv.validated_pose(msg, self.frame, self._now(), self.p["max_pose_age_s"], f"{kind} {name}")
            except cv.InputError as exc:
                self.status(f"ignored {exc}", "warning")
                return
            except Exception as exc:  # never let a message kill the node
                self.status(f"ignored malformed {kind} {name}: {exc}", "warning")
                return
            with self._lock:
                self._input_t[f"{kind} {name}"] = time.monotonic()
                pend = self._pending
                pend["targets" if kind == "target" else "obstacles"][name] = (p, q)
                if kind == "target":  # the pose's own time, for the target's motion prediction
                    pend["target_stamps"][name] = cv.stamp_to_sec(msg.header.stamp)
                if pend["t_first"] is None:
                    pend["t_first"] = t
                    pend["stamp"] = cv.stamp_to_sec(msg.header.stamp)
                    pend["input_age_ms"] = (self._now() - pend["stamp"]) * 1e3  # stamp -> receipt here
            self._guard(kind, name, p, q)
            self._wake.set()
        return cb

    def _guard(self, kind: str, name: str, p: np.ndarray, q: np.ndarray) -> None:
        """The stop guard, on the executor thread as each body pose arrives: when the body (an obstacle, or a target
        that is one) at its new pose collides with the next ``stop_horizon_s`` of the trajectory being executed, a
        stop is published at once and a replan is asked for. The planner may be busy for a second with a replan;
        without the guard the robot would drive on along the old trajectory meanwhile (MoveIt's plan execution
        likewise stops a trajectory whose remaining path the planning scene invalidates)."""
        cur, horizon, guard = self.current, self.p["stop_horizon_s"], self.guard
        if horizon <= 0 or guard is None or cur is None or cur.get("msg") is None:
            return
        try:
            import torch

            if kind == "target":
                t = self.safety_scene.target(name)
                if not t.obstacle:
                    return
                box = dataclasses.replace(t.as_box(), center=np.asarray(p, float), quat=np.asarray(q, float))
            else:
                box = dataclasses.replace(self.safety_scene.obstacle(name), center=np.asarray(p, float),
                                          quat=np.asarray(q, float))
            with self._lock:
                q_now = self._pending["robot"]
            ahead = self._remaining(cur["positions"], self.q if q_now is None else q_now)
            ahead = ahead[: int(np.ceil(horizon / self.p["trajectory_dt"])) + 1]
            P = cv.densify_linear(ahead, self.p["safety_step"])
            if not bool(guard.env_hits(torch.as_tensor(P, dtype=torch.float32), [box]).any()):
                return
        except Exception as exc:  # never lose the executor thread to the guard
            self.status(f"stop guard failed: {exc}", "warning")
            return
        with self._pub_lock:
            if self.current is not cur:  # a newer trajectory went out meanwhile: the next pose checks that one
                return
            self.counts["guard_stops"] += 1
            self._publish_stop(f"{kind} {name} moved into the next {horizon:g} s of the trajectory")
        with self._lock:
            self._pending["guard"] = f"{kind} {name}"

    def _robot_cb(self, msg) -> None:
        try:
            q, found = cv.joint_state_to_planning(msg, self.robot)
            if set(found) != set(self.names):
                missing = sorted(set(self.names) - set(found))
                raise cv.InputError(f"robot state: missing planning joints {', '.join(missing)}")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        with self._lock:
            self._pending["robot"] = q
            self._robot_rx = time.monotonic()
        self._wake.set()

    def _goals_cb(self, msg) -> None:
        try:
            cv.check_frame(msg.header.frame_id, self.frame, "goals")
            G = cv.joint_trajectory_positions(msg, self.names)
            if len(G) == 0:
                raise cv.InputError("goals: no candidate configuration")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        with self._lock:
            self._pending["goals"] = G
            if self._pending["t_first"] is None:
                self._pending["t_first"] = time.perf_counter()
        self._wake.set()

    def _scores_cb(self, msg) -> None:
        try:
            s = np.asarray(msg.data, float)
            if not np.isfinite(s).all():
                raise cv.InputError("roadmap scores: non-finite values")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        with self._lock:
            self.ext_scores = s
            self._markers_dirty = True

    def _srv(self, kind: str):
        def handler(request, response):
            with self._lock:
                rid = self._next_id
                self._next_id += 1
                self._requests.append((kind, rid))
            self._wake.set()
            deadline = time.monotonic() + self.p["service_timeout_s"]
            with self._done:
                while rid not in self._responses and time.monotonic() < deadline and self._running:
                    self._done.wait(0.1)
                ok, message = self._responses.pop(rid, (False, "timed out"))
            response.success, response.message = bool(ok), str(message)
            return response
        return handler

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
            self._idle.clear()
            try:
                if live:
                    self._apply_live(live)
                self._cycle(pend, reqs)
            except Exception as exc:  # a bug or a core error must not end the worker
                self.log.error(f"planning cycle failed: {exc!r}")
                self.status(f"planning cycle failed: {exc}", "error")
                self._answer(reqs, False, f"error: {exc}")
            finally:
                self._idle.set()

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
                self.set_state("inactive: " + (self.build_info and f"{self.build_info.get('n_nodes', 0)} nodes" or ""))
                ok = True
            elif kind == "cleanup":
                self.rp = self.planner = self.safety = None
                self.current = None
                self.ready.clear()
                self.set_state("unconfigured")
                ok = True
        except Exception as exc:  # configuration errors end up here: report, keep the node alive
            self.status(f"{kind} failed: {exc}", "error")
            if kind == "configure":
                self.set_state(f"error: roadmap build failed: {exc}")
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
            self.status(f"parameters applied: {', '.join(f'{k}={v}' for k, v in sorted(live.items()))}")

    def _answer(self, reqs, ok: bool, message: str, kinds=None) -> None:
        with self._done:
            for kind, rid in reqs:
                if rid >= 0 and (kinds is None or kind in kinds):
                    self._responses[rid] = (ok, message)
            self._done.notify_all()

    def _build(self, initial: bool = False) -> None:
        from psprm_core.collision import CollisionChecker

        scene = self.safety_scene
        self.status(f"{'building' if initial else 'rebuilding'} the {self.spec.variant} roadmap "
                    f"({self.spec.n_nodes} nodes) for scene '{scene.name}'")
        self.set_state("building" if initial else "rebuilding")
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
                self.rp.update_target(t.name, t.center, t.quat, stamp=self._now())
        for o in self.p["dynamic_obstacles"]:
            b = scene.obstacle(o)
            self.rp.update_obstacle(o, b.center, b.quat)
        self.rp.set_robot_state(self.q)
        if self.goals is not None:
            self.rp.set_goals(self.goals)
        self.safety = CollisionChecker(self.robot, scene.collision_boxes(), workspace=scene.workspace)
        self.guard = CollisionChecker(self.robot, workspace=scene.workspace)
        text = f"roadmap {info['source']} in {info['seconds']:.1f} s: {info.get('n_nodes', 0)} nodes; ready"
        self.status(text)
        self.set_state(f"ready: {text}")
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
                self.status(f"rebuild failed, keeping the old roadmap: {exc}", "error")
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
                self.status(f"target {name} refused by the planner: {exc}", "warning")
        for name, (p, q) in pend["obstacles"].items():
            try:
                moved |= self.rp.update_obstacle(name, p, q) is not False
                self.safety_scene = self.safety_scene.with_obstacle_pose(name, p, q)
                boxes_changed = True
            except (PsprmError, KeyError, ValueError) as exc:
                self.status(f"obstacle {name} refused by the planner: {exc}", "warning")
        if boxes_changed:
            self.safety.set_boxes(self.safety_scene.collision_boxes())
        try:
            if pend["robot"] is not None:
                now_q = time.monotonic()
                self._q_hist.append((now_q, pend["robot"].copy()))
                while len(self._q_hist) > 2 and now_q - self._q_hist[1][0] >= 0.3:
                    self._q_hist.popleft()
                q_now = pend["robot"]
                along = self._time_along(q_now)
                # a base that moves with no trajectory under way brakes from a stop: plan from where it will rest
                q_plan = q_now if along is not None else self._rest_point(q_now)
                self.rp.set_robot_state(q_plan, along)
                self.q = q_plan
            if pend["goals"] is not None:
                self.rp.set_goals(pend["goals"])
                self.goals = pend["goals"]
                self.hold = False
                reasons.append("goal_received")
        except (PsprmError, ValueError) as exc:
            self.status(f"robot state or goal refused by the planner: {exc}", "warning")
        if "stop" in kinds:
            self.hold = True
            self._publish_stop("stop requested")
            self._answer(reqs, True, "stopped", kinds={"stop"})
        if "plan" in kinds:
            self.hold = False
            reasons.append("plan requested")
        if pend["guard"]:
            reasons.append(f"stopped: {pend['guard']} in the path ahead")
        if self.goals is None:
            if reasons:
                self.status("no goal yet: publish one on the goal topic", "warning")
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
                self.status(f"not planning: {waiting}", "warning")
            self._answer(reqs, False, waiting, kinds={"plan"})
            return
        if self.waiting:
            self.status("robot state live: planning resumes")
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

    # ------------------------------------------------------------------------------------------------ planning
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
        if traj is None or self.rp is None or self.rp.result is not res:
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
        P, V, _ = (a[0] for a in traj.evaluate([t]))
        off = float(displacement(self.robot, q, P[None])[0])
        # a robot that stands while its trajectory moves (stopped by the adapter, held) does not follow it: a plan
        # spliced on there would start it at speed
        vmax = np.maximum(self.robot.velocity, 1e-6)
        moving = float((np.abs(V) / vmax).max()) > 0.2
        standing = self._measured_speed() < 0.02
        if off > self.p["progress_tolerance_m"] or (moving and standing) or t >= float(traj.duration) - 1e-6:
            self._along = None
            return None
        self._along = (traj, t, now)
        return t

    def _rest_point(self, q: np.ndarray) -> np.ndarray:
        """Where a mobile base moving at the velocity of its last robot states (at least 0.1 s apart) comes to rest
        braking at the robot config's base accelerations (:func:`psprm_ros.adapters.braking_configurations`); ``q``
        itself for a fixed base or a base at rest."""
        from .adapters import braking_configurations
        from .base_follower import Limits

        h = self._q_hist
        if not self.robot.mobile or len(h) < 2 or h[-1][0] - h[0][0] < 0.1:
            return q
        dt = h[-1][0] - h[0][0]
        a, b = h[0][1], h[-1][1]
        th = 0.5 * (a[2] + b[2])
        v = ((b[0] - a[0]) * np.cos(th) + (b[1] - a[1]) * np.sin(th)) / dt
        w = float((b[2] - a[2] + np.pi) % (2 * np.pi) - np.pi) / dt
        if abs(v) < 0.02 and abs(w) < 0.05:
            return q
        return braking_configurations(q, (v, w), Limits.for_robot(self.robot))[-1]

    def _measured_speed(self) -> float:
        """How fast the robot moved over its last robot states (the largest joint speed over its velocity limit; a
        fraction of full speed), from the states the worker took (at least 0.1 s apart); 1 until known."""
        h = self._q_hist
        if len(h) < 2 or h[-1][0] - h[0][0] < 0.1:
            return 1.0
        d = np.abs(h[-1][1] - h[0][1])
        if self.robot.mobile:
            d[2] = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
            d[0] = d[1] = float(np.hypot(*(h[-1][1][:2] - h[0][1][:2])))
        return float((d / np.maximum(self.robot.velocity, 1e-6)).max()) / (h[-1][0] - h[0][0])

    def _commit_horizon(self) -> float:
        """Planning and delivery time of a replan (s): 1.5x the 90th percentile of the recent replans' time from
        their start to the trajectory's publication, plus the adapter's lead time (0.15 s), clamped to
        [commit_horizon_min_s, commit_horizon_max_s]."""
        lo, hi = self.p["commit_horizon_min_s"], self.p["commit_horizon_max_s"]
        if not self._plan_s:
            return max(lo, min(hi, 0.5))
        return max(lo, min(hi, 1.5 * float(np.percentile(list(self._plan_s), 90)) + 0.15))

    def _plan(self, reasons: list, pend: dict) -> tuple:
        t0 = time.perf_counter()
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
            self._publish_info(info)
            self.status(f"plan {info['seq']} ({', '.join(reasons)}): {res.reason}")
            return True, json.dumps(info)
        traj = res.trajectory if res.success else None
        if res.success and traj is None:  # already at the goal
            self._publish_stop("already at the goal", info)
            return True, json.dumps(info)
        if traj is not None:
            stamp = self.node.get_clock().now().to_msg()
            msg, P = cv.trajectory_to_msg(traj, self.names, self.frame, stamp, self.p["trajectory_dt"],
                                          with_positions=True)
            # the trajectory starts at the measured state it was planned from (the planner re-aims the camera joints
            # at its start): a controller then never jumps, and the connecting move is checked below with the rest
            cont = [2] if self.robot.mobile else []
            # (a spliced trajectory starts on the one under way, where the robot was when the replan began: the
            # adapter joins it at the robot's progress)
            shift = 0.0 if info["spliced"] else cv.prepend_start(msg, self.rp.q, self.robot.velocity,
                                                                 self.robot.acceleration, cont)
            info["start_shift_s"] = _f(shift)
            if shift > 0:
                P = np.vstack([np.asarray(msg.points[0].positions, float), P])
            t2 = time.perf_counter()
            self._take_fresh_obstacles()
            unsafe = self._unsafe(P)
            info.update(msg_ms=_f((t2 - t1) * 1e3), check_ms=_f((time.perf_counter() - t2) * 1e3))
            late = info["spliced"] and time.perf_counter() - t0 + SPLICE_DELIVERY_S > res.committed_s
            if unsafe or late:
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
            else:
                with self._pub_lock:
                    self.pub_traj.publish(msg)
                    t_pub = time.perf_counter()
                    # when the robot is at the trajectory's time 0: the replan's start for a splice (the trajectory
                    # begins where the robot was then), else the adapter's start, its lead time after publication
                    self.current = {"result": res, "msg": msg, "t_pub": t_pub, "positions": P,
                                    "t_zero": t0 if info["spliced"] else t_pub + 0.15}
                t_pub = self.current["t_pub"]
                self._plan_s.append(t_pub - t0)
                self._along = None
                info["published_stamp"] = self._now()  # node clock (the inputs' stamps are on it too)
                if self.robot.mobile:  # built on the side thread: ~400 PoseStamped are pure Python
                    self._submit_side("base path", lambda P=P, stamp=stamp: self.pub_base_path.publish(
                        cv.base_path_msg(P, self.frame, stamp)))
                self.counts["plans"] += 1
                self.counts["spliced"] += int(info["spliced"])
                if pend["t_first"]:
                    self.last_latency_ms = (t_pub - pend["t_first"]) * 1e3
                info.update(latency_ms=_f((t_pub - pend["t_first"]) * 1e3) if pend["t_first"] else None,
                            duration_s=_f(traj.duration), n_points=len(msg.points), stop=False)
                self._after_publish(res, info, reasons)
                return True, json.dumps(info)
        # nothing new and safe: keep the last safe trajectory, else stop
        self.counts["failed"] += 1
        self.status(f"planning failed ({info['reason']})", "warning")
        if self.current is not None and not self._unsafe(self._remaining(self.current["positions"])):
            info.update(stop=False, kept_last=True)
            self._publish_info(info)
            self.status("keeping the last safe trajectory", "warning")
        else:
            self._publish_stop(f"no safe trajectory ({info['reason']})", info)
        return False, json.dumps(info)

    def _after_publish(self, res, info: dict, reasons: list) -> None:
        """Plan info and status now; path camera poses and markers on the side thread (off the latency path)."""
        info["mean_score"] = _f(res.mean_score)  # the planner's score along the path: after publication
        self._publish_info(info)
        start = (f"spliced {info['committed_s']:.2f} s ahead" if info["spliced"] else "from the robot's state")
        self.status(f"plan {info['seq']} ({', '.join(reasons)}): {info['n_points']} points, "
                    f"{info['duration_s']:.1f} s, {start}, predicted score {res.mean_score:.3f}, query "
                    f"{res.query_ms:.0f} ms")
        self._submit_side("path markers", self._publish_path, res, self.safety_scene)

    def _submit_side(self, what: str, fn, *args) -> None:
        """Queue a side job; a job of the same kind still waiting is replaced (only the newest path or roadmap
        matters: while the planner replans back to back, jobs would otherwise pile up faster than they run)."""
        with self._lock:
            queued = what in self._side_jobs
            self._side_jobs[what] = (fn, args)
        if not queued:
            self._side.submit(self._side_job, what)

    def _side_job(self, what: str) -> None:
        """Run the newest job of kind ``what`` on the side thread once the planner is idle (waits at most 1 s):
        publishing markers is pure Python and would otherwise compete with a replan for the interpreter."""
        self._idle.wait(1.0)
        with self._lock:
            fn, args = self._side_jobs.pop(what)
        try:
            fn(*args)
        except Exception as exc:  # never lose the side thread
            self.status(f"{what} failed: {exc}", "warning")

    def _trim_heap(self) -> None:
        """Side job: return the C heap's free pages to the system (:mod:`.heap`)."""
        ms = release_free_heap()
        if ms is not None:
            self.heap_trims, self.heap_trim_ms = self.heap_trims + 1, ms

    def _publish_stop(self, why: str, info: Optional[dict] = None) -> None:
        with self._pub_lock:
            self.pub_traj.publish(cv.stop_trajectory(self.q, self.names, self.frame, hold_s=self.p["stop_hold_s"]))
            self.counts["stops"] += 1
            self.current = {"result": None, "msg": None, "t_pub": time.perf_counter(),
                            "positions": self.q[None].copy()}
        info = dict(info or {"seq": self.seq, "reasons": [why]})
        info.update(stop=True, stop_reason=why)
        self._publish_info(info)
        self.status(f"stop trajectory published: {why}", "warning")

    def _publish_info(self, info: dict) -> None:
        from std_msgs.msg import String

        self.pub_info.publish(String(data=json.dumps(info)))

    def _take_fresh_obstacles(self) -> None:
        """Obstacle poses that arrived while the planner was running go into the final check now (the planner sees
        them in the next cycle): a trajectory is never published unchecked against a pose the server already has."""
        with self._lock:
            fresh = dict(self._pending["obstacles"])
            fresh_t = {n: v for n, v in self._pending["targets"].items()}
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
        """True when any configuration along ``positions`` (densified to the planner's edge resolution) collides
        with the latest obstacle poses (or leaves the joint limits / workspace)."""
        import torch

        P = np.asarray(positions, float).reshape(-1, len(self.names))
        if len(P) == 0:
            return False
        if not np.isfinite(P).all():
            return True
        P = cv.densify_linear(P, self.p["safety_step"])
        bad = self.safety.check(torch.as_tensor(P, dtype=torch.float32))
        return bool(bad.any())

    def _remaining(self, positions: np.ndarray, q: Optional[np.ndarray] = None) -> np.ndarray:
        """The part of a published trajectory the robot has not traversed yet (from its sample nearest to the robot
        state ``q``, default the one the planner last took)."""
        P = np.asarray(positions)
        q = self.q if q is None else q
        if len(P) <= 1:
            return P
        d = np.linalg.norm(P[:, :2] - q[:2], axis=1) if self.robot.mobile else np.linalg.norm(P - q, axis=1)
        return P[int(np.argmin(d)):]

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
        stamp = self.node.get_clock().now().to_msg()
        self.pub_rm_cams.publish(cv.pose_array(T, self.frame, stamp))
        self._markers_dirty = True
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
        if not force and (not self._markers_dirty or now - self._markers_t < self.p["markers_period_s"]):
            return
        pl, g = self.planner, self.planner.graph
        if len(self._rm_ids) != pl.n_roadmap_nodes:  # the roadmap grew (repair): new camera poses first
            self._publish_roadmap()  # (calls back with force=True)
            return
        self._markers_t, self._markers_dirty = now, False
        ids = self._rm_ids
        keep = g.node_valid[ids]
        pos = np.full(g.n_nodes, -1, dtype=np.int64)
        pos[ids[keep]] = np.arange(int(keep.sum()))
        eids = pl.roadmap_edge_ids()
        e = np.stack([pos[g.edge_u[eids]], pos[g.edge_v[eids]]], 1)
        e = e[(e >= 0).all(1)]
        snap = (self.safety_scene, self._rm_cams[keep, :3, 3].copy(), self._node_scores()[keep].copy(),
                g.configs[ids[keep], :2].copy(), e)
        self._submit_side("roadmap markers", self._publish_roadmap_markers, *snap)

    def _publish_roadmap_markers(self, scene, cam_xyz, scores, base_xy, edges) -> None:
        from . import markers as mk

        stamp = self.node.get_clock().now().to_msg()
        ms = mk.scene_markers(scene, stamp)
        ms += mk.roadmap_markers(self.frame, cam_xyz, scores, base_xy, edges, stamp, self.p["marker_max_edges"])
        self.pub_markers.publish(mk.marker_array(ms))

    def _publish_path(self, res, scene) -> None:
        """Camera poses along the new path (for the perception scorer) and the path markers; runs on the side
        thread and touches only the robot model and the result."""
        from . import markers as mk

        D = res.dense if res.dense is not None else res.waypoints
        k = max(1, int(np.ceil(len(D) / max(2, self.p["path_camera_samples"]))))
        idx = np.unique(np.r_[np.arange(0, len(D), k), len(D) - 1])
        T = self._camera_poses(D[idx])
        stamp = self.node.get_clock().now().to_msg()
        self.pub_path_cams.publish(cv.pose_array(T, self.frame, stamp))
        if self.p["publish_markers"]:
            scores = res.dense_scores[idx] if res.dense_scores is not None else np.zeros(len(idx))
            scores = scores * float(getattr(self.planner, "score_scale", 1.0))
            ms = mk.scene_markers(scene, stamp) + mk.path_markers(self.frame, D[idx, :2], T[:, :3, 3],
                                                                             scores, stamp)
            self.pub_path_markers.publish(mk.marker_array(ms))

    # ------------------------------------------------------------------------------------------------ diagnostics
    def _diagnostics(self) -> None:
        state = core.lifecycle_state(self.node)
        if self.rp is None:
            level, msg = core.DIAG_WARN, f"{state}: roadmap not ready"
        elif not self.active:
            level, msg = core.DIAG_WARN, f"{state}"
        elif self.waiting:
            level, msg = core.DIAG_WARN, self.waiting
        else:
            level, msg = core.DIAG_OK, "planning" if not self._idle.is_set() else "ready"
        now = time.monotonic()
        with self._lock:
            rx = self._robot_rx
            ages = {f"age_s {k}": now - t for k, t in self._input_t.items()}
        vals = {"lifecycle": state, "roadmap_nodes": int(self.planner.n_roadmap_nodes) if self.planner else 0,
                **self.counts, "last_latency_ms": self.last_latency_ms if self.last_latency_ms is not None else "",
                "robot_state_age_s": (now - rx) if rx is not None else "never", **ages,
                "heap_trims": self.heap_trims, "last_heap_trim_ms": self.heap_trim_ms if self.heap_trim_ms is not None
                else ""}
        rp = self.rp
        if rp is not None:  # the replanner's decisions: replans adopted / declined (kept), goal switches
            vals.update(adopted_replans=rp.adopted, declined_replans=rp.declined, goal_switches=rp.goal_switches)
        core.publish_diagnostics(self.pub_diag, self.node, [
            core.diagnostic_status(f"psprm: {self.node.get_fully_qualified_name()}", self.robot.name, level, msg, vals)])

    # ------------------------------------------------------------------------------------------------ lifecycle
    def destroy(self) -> None:
        self._running = False
        self._wake.set()
        self._thread.join(timeout=10.0)
        self._side.shutdown(wait=True, cancel_futures=True)
        self.node.destroy_node()


def _f(x) -> Optional[float]:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None


def main(args=None) -> int:
    from .runner import run_nodes

    return run_nodes([RoadmapServer], args, description=__doc__)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
