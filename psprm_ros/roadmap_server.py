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

All planning runs on the :class:`~psprm_ros.server.PlanningLoop`'s worker thread: callbacks convert and
validate each message once and hand the values to the loop (which keeps only the latest, so a 120 Hz stream never
queues); the loop applies the newest state to the core :class:`Replanner`, asks it whether to replan and decides
what to publish. Every trajectory is re-checked with a :class:`CollisionChecker` holding the latest obstacle poses
before it is published (the exact samples this node turns into the message); when no safe trajectory exists the last
safe one is kept, or a stop trajectory is published.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Optional

import numpy as np

from psprm_core.errors import ConfigError, PsprmError
from psprm_core.paths import resolve_named
from psprm_core.planning.psprm import PSPRMSettings
from psprm_core.planning.replanner import ReplanSettings

from . import core, planner_setup
from .interfaces import conversions as cv, markers as mk
from .runner import run_nodes
from .server import LOOP_PARAMS, Outputs, PlanningLoop, TrajectorySamples, live_replan

__all__ = ["RoadmapServer", "SERVER_PARAMS", "main"]

P = core.Param
SERVER_PARAMS = {
    "start_problem": P("", "scene problem whose start is the template of the roadmap build; planning waits for the "
                           "measured robot state (/psprm/state/robot)"),
    "goal_regions": P([], "goals used before any goal message arrives ([] = wait for a goal)"),
    "max_pose_age_s": P(1.0, "refuse pose messages older than this (0 = no check)", live=True, lo=0.0),
    "marker_max_edges": P(5000, "roadmap edges drawn (an evenly spread subset; ~9 ms per 1000)", live=True, lo=0),
    "service_timeout_s": P(120.0, "longest wait of a service call for the planner", live=True, lo=1.0),
    "diagnostics_period_s": P(1.0, "period of /diagnostics", lo=0.1),
    "heap_trim_period_s": P(60.0, "give the C heap's free memory back to the system this often, while the planner "
                                  "is idle (0 = never; psprm_ros.heap)", lo=0.0),
    **LOOP_PARAMS,  # what the planning loop reads
}
PLANNER_DESCRIPTIONS = {"variant": "PS-PRM variant (neural-psprm-line, psprm-line, ...)",
                        "planner_settings": "PSPRMSettings YAML ('' = config/planners/psprm.yaml): the defaults of "
                                            "the planner-setting parameters (scoring.alpha, roadmap.n_nodes, ...)",
                        "replan_settings": "ReplanSettings: a name in config/planners/ or a YAML path",
                        "roadmap_file": "'' = cache under ~/.cache/psprm/roadmaps; 'none' = always build",
                        "checkpoint": "surrogate checkpoint ('' = the shipped one)"}


def planner_params() -> dict:
    return {k: P(v, PLANNER_DESCRIPTIONS.get(k, ""), rebuild=True) for k, v in planner_setup.PLANNER_PARAMS.items()}


def planner_setting_params(defaults: dict) -> dict:
    """The planner settings the server declares (:func:`~psprm_ros.planner_setup.server_setting_specs`), by dotted
    path, made from their specs (:func:`~psprm_ros.core.setting_param`) with ``defaults`` (dotted path -> value:
    :func:`~psprm_ros.planner_setup.server_setting_values`); the live ones are applied to the running planner, the
    others are read-only."""
    return {spec.name: core.setting_param(spec, defaults[spec.name]) for spec in planner_setup.server_setting_specs()}


def replan_params(settings_name: str) -> dict:
    """The live replan settings (:func:`~psprm_ros.server.params.live_replan`), made from their specs with the
    settings file's values as defaults."""
    rs = ReplanSettings.from_yaml(resolve_named("planner", settings_name)) if settings_name else ReplanSettings()
    return {name: core.setting_param(spec, getattr(rs, name)) for name, spec in live_replan().items()}


class RoadmapServer:
    """The node (composition over inheritance keeps construction order explicit; ``.node`` is the rclpy Node,
    ``.loop`` the :class:`PlanningLoop` that plans and decides, made at configure and closed at cleanup).

    Construction declares the parameters (the planner settings' defaults from ``planner_settings`` for the robot the
    parameters name), the publishers and the services; configure loads the scene and the robot model, makes the
    planning loop and the input subscriptions and builds or loads the roadmap; cleanup closes the loop and destroys
    the subscriptions and timers configure made."""

    def __init__(self, node_name: str = core.SERVER_NAME, **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from geometry_msgs.msg import PoseArray
        from std_msgs.msg import String
        from std_srvs.srv import Trigger
        from trajectory_msgs.msg import JointTrajectory
        from visualization_msgs.msg import MarkerArray
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Path
        import torch

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        common = {**core.common_params(), **planner_params(), **SERVER_PARAMS}
        refusals: list = []  # parameters given values they refuse: the node stays up and refuses to configure
        self.p = core.declare_params(node, common, refusals)
        replan = replan_params(self.p["replan_settings"])
        self.p.update(core.declare_params(node, replan, refusals))
        torch.set_num_threads(max(1, self.p["torch_threads"]))
        self.robot_name = self._robot_name(refusals)
        settings = self._planner_setting_params(refusals)
        self.p.update(core.declare_params(node, settings, refusals))
        self.spec_params = {**common, **replan, **settings}
        self.setting_names = list(settings)
        if refusals:
            node.refuse_configure("; ".join(filter(None, [node.configure_refusal,
                                                          f"parameters refused: {'; '.join(refusals)}"])))
        # made at configure, dropped at cleanup
        self.loop: Optional[PlanningLoop] = None
        self.spec: Optional[planner_setup.PlannerSpec] = None
        self.scene = self.robot = None
        self.frame: Optional[str] = None
        self.targets: list = []
        self.names: list = []
        self._made = core.ConfigureScope(node)
        self._unset = threading.Event()  # idle while unconfigured: never set
        self.ready = threading.Event()  # set while a roadmap is built or loaded (the loop sets and clears it)

        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
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

        srv = ReentrantCallbackGroup()
        node.create_service(Trigger, "~/plan", self._srv("plan"), callback_group=srv)
        node.create_service(Trigger, "~/rebuild", self._srv("rebuild"), callback_group=srv)
        node.create_service(Trigger, "~/stop", self._srv("stop"), callback_group=srv)
        core.install_param_callback(node, self.spec_params, self.p, self._stage_param)
        node.create_timer(self.p["diagnostics_period_s"], self._diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())

    def _robot_name(self, refusals: list) -> str:
        """The robot the parameters name (``robot``, or the scene's robot, read from the scene file without loading
        the scene); '' with a refusal when the scene cannot be read."""
        if self.p["robot"]:
            return str(self.p["robot"])
        try:
            return core.scene_robot_name(self.p["scene"])
        except PsprmError as exc:
            refusals.append(f"scene: {exc}")
            return ""

    def _configure(self) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32MultiArray
        from trajectory_msgs.msg import JointTrajectory

        node, p = self.node, self.p
        scene, robot = core.load_configured_scene_and_robot(node, dict(p))
        spec = planner_setup.PlannerSpec(**{k: p[k] for k in planner_setup.PLANNER_PARAMS},
                                         settings={k: p[k] for k in self.setting_names})
        targets = core.scene_targets(scene, p["targets"])
        obstacles = list(p["dynamic_obstacles"])
        for o in obstacles:
            scene.obstacle(o)
        q0 = core.start_configuration(robot, scene, p["start_problem"])
        goals: Optional[np.ndarray] = None
        if p["goal_regions"]:
            goals = core.goal_region_configurations(robot, scene, p["goal_regions"])
        self.scene, self.robot, self.frame, self.spec = scene, robot, scene.frame, spec
        self.targets, self.names = targets, list(robot.joint_names)
        self.loop = PlanningLoop(scene, robot, targets, spec, _Publications(self), obstacles=obstacles, q0=q0,
                                 goals=goals, params=p, clock=self._now, ready=self.ready)

        cb = MutuallyExclusiveCallbackGroup()
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for t in targets:
            self._made.subscription(PoseStamped, core.target_topic(t), self._pose_cb("target", t),
                                    qos_profile_sensor_data, callback_group=cb)
        for o in obstacles:
            self._made.subscription(PoseStamped, core.obstacle_topic(o), self._pose_cb("obstacle", o),
                                    qos_profile_sensor_data, callback_group=cb)
        self._made.subscription(JointState, core.ROBOT_STATE_TOPIC, self._robot_cb, qos_profile_sensor_data,
                                callback_group=cb)
        self._made.subscription(JointTrajectory, core.GOALS_TOPIC, self._goals_cb, latched, callback_group=cb)
        self._made.subscription(Float32MultiArray, core.ROADMAP_SCORES_TOPIC, self._scores_cb, 1, callback_group=cb)
        if p["heap_trim_period_s"] > 0:
            loop = self.loop
            self._made.timer(p["heap_trim_period_s"], lambda: loop.submit_side("heap trim", loop.trim_heap),
                             callback_group=MutuallyExclusiveCallbackGroup())

    def _release(self, cleanup: bool = True) -> None:
        """Close the planning loop (its roadmap and threads; ``cleanup``: after its cleanup step, which reports the
        server unconfigured) and destroy what configure made."""
        self._made.release()
        loop, self.loop = self.loop, None
        if loop is not None:
            if cleanup:
                loop.transition("cleanup")
            loop.close()
        self.ready.clear()
        self.scene = self.robot = self.frame = self.spec = None
        self.targets, self.names = [], []

    def _stage_param(self, name: str, value) -> None:
        """A live parameter change: checked and applied by the planning loop when configured (the values dict the
        loop reads is updated by the parameter callback either way)."""
        if self.loop is not None:
            self.loop.stage_param(name, value)

    def _planner_setting_params(self, refusals: list) -> dict:
        """The planner-setting parameters (:func:`planner_setting_params`) with the defaults of the settings file for
        this robot; a file that cannot be read is a refusal (the specs' defaults stand in)."""
        try:
            settings = planner_setup.planner_file_settings(self.p["planner_settings"], self.robot_name)
        except ConfigError as exc:
            refusals.append(f"planner_settings: {exc}")
            settings = PSPRMSettings()
        return planner_setting_params(planner_setup.server_setting_values(settings))

    # ------------------------------------------------------------------------------------------------ the loop's state
    # read by the launchers, benchmarks and tests (probe, latency_bench, the node tests)
    # (unconfigured: no roadmap, no replanner, no counts)
    @property
    def rp(self):
        """The core Replanner (None while unconfigured)."""
        return None if self.loop is None else self.loop.rp

    @property
    def planner(self):
        return None if self.loop is None else self.loop.planner

    @property
    def build_info(self) -> dict:
        return {} if self.loop is None else self.loop.build_info

    @property
    def counts(self) -> dict:
        return {} if self.loop is None else self.loop.counts

    @property
    def last_latency_ms(self) -> Optional[float]:
        return None if self.loop is None else self.loop.last_latency_ms

    @property
    def current(self) -> Optional[dict]:
        return None if self.loop is None else self.loop.current

    @property
    def _idle(self):
        """Set while the planner waits for input (threading.Event)."""
        return self._unset if self.loop is None else self.loop.idle

    @property
    def _markers_dirty(self) -> bool:
        return False if self.loop is None else self.loop.markers_dirty

    @_markers_dirty.setter
    def _markers_dirty(self, value: bool) -> None:
        if self.loop is not None:
            self.loop.markers_dirty = bool(value)

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        """Load the scene and robot model, make the planning loop and the subscriptions, then build or load the
        roadmap (blocks until it is ready). A missing file or a failed build: the configure fails with the reason on
        ``~/status``, the node stays unconfigured with nothing made and can be configured again."""
        self._made.configure(self._configure, self._release)
        if self.loop.transition("configure"):
            return True
        self._release(cleanup=False)  # the loop's latched "error: ..." state stays
        return False

    def on_activate(self, state) -> bool:
        return self.loop.transition("activate")

    def on_deactivate(self, state) -> bool:
        """Stop the robot (a stop trajectory), then stop planning."""
        return self.loop.transition("deactivate")

    def on_cleanup(self, state) -> bool:
        """Drop the roadmap, end the planning loop and destroy the subscriptions and timers configure made."""
        self._release()
        self.status("unconfigured: roadmap, planning loop and subscriptions released")
        return True

    def on_shutdown(self, state) -> bool:
        return True if self.loop is None else self.loop.transition("shutdown")

    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    def set_state(self, text: str) -> None:
        """The latched server state (late subscribers see it too)."""
        from std_msgs.msg import String

        self.pub_state.publish(String(data=text))

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    # ------------------------------------------------------------------------------------------------ callbacks
    def _pose_cb(self, kind: str, name: str):
        loop = self.loop
        put = loop.target_pose if kind == "target" else loop.obstacle_pose

        def cb(msg):
            t = time.perf_counter()
            try:
                p, q = cv.validated_pose(msg, self.frame, self._now(), self.p["max_pose_age_s"], f"{kind} {name}")
                stamp = cv.stamp_to_sec(msg.header.stamp)
            except cv.InputError as exc:
                self.status(f"ignored {exc}", "warning")
                return
            except Exception as exc:  # never let a message kill the node
                self.status(f"ignored malformed {kind} {name}: {exc}", "warning")
                return
            put(name, p, q, stamp, received=t)
        return cb

    def _robot_cb(self, msg) -> None:
        loop, robot = self.loop, self.robot
        if loop is None or robot is None:  # released by a cleanup
            return
        try:
            q, found = cv.joint_state_to_planning(msg, robot)
            if set(found) != set(self.names):
                missing = sorted(set(self.names) - set(found))
                raise cv.InputError(f"robot state: missing planning joints {', '.join(missing)}")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        loop.robot_state(q, cv.base_velocity_of(msg, float(q[2])) if robot.mobile else None)

    def _goals_cb(self, msg) -> None:
        loop = self.loop
        if loop is None:
            return
        try:
            cv.check_frame(msg.header.frame_id, self.frame, "goals")
            G = cv.joint_trajectory_positions(msg, self.names)
            if len(G) == 0:
                raise cv.InputError("goals: no candidate configuration")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        loop.goals(G)

    def _scores_cb(self, msg) -> None:
        loop = self.loop
        if loop is None:
            return
        try:
            s = np.asarray(msg.data, float)
            if not np.isfinite(s).all():
                raise cv.InputError("roadmap scores: non-finite values")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        loop.scores(s)

    def _srv(self, kind: str):
        def handler(request, response):
            loop = self.loop
            if loop is None:
                ok, message = False, "not configured"
            else:
                ok, message = loop.request(kind, self.p["service_timeout_s"])
            response.success, response.message = bool(ok), str(message)
            return response
        return handler

    # ------------------------------------------------------------------------------------------------ diagnostics
    def _diagnostics(self) -> None:
        state, loop = core.lifecycle_state(self.node), self.loop
        if loop is None:
            level, msg, vals = core.DIAG_WARN, "not configured", {"lifecycle": state}
        else:
            level, msg, vals = loop.diagnostics(state)
        name = f"psprm: {self.node.get_fully_qualified_name()}"
        core.publish_diagnostics(self.pub_diag, self.node,
                                 [core.diagnostic_status(name, self.robot_name, level, msg, vals)])

    def destroy(self) -> None:
        if self.loop is not None:
            self.loop.close()
        self.node.destroy_node()


class _Publications(Outputs):
    """The loop's outputs as this node's messages: what is published is built from exactly the values the loop
    hands over (trajectory samples unchanged, one point each)."""

    def __init__(self, server: RoadmapServer):
        self.s = server

    def _stamp(self):
        return self.s.node.get_clock().now().to_msg()

    def trajectory(self, samples: TrajectorySamples) -> None:
        s = self.s
        s.pub_traj.publish(cv.joint_trajectory_msg(*samples, s.names, s.frame, self._stamp()))

    def stop(self, q: np.ndarray, hold_s: float) -> None:
        s = self.s
        s.pub_traj.publish(cv.stop_trajectory(q, s.names, s.frame, hold_s=hold_s))

    def info(self, info: dict) -> None:
        from std_msgs.msg import String

        self.s.pub_info.publish(String(data=json.dumps(info)))

    def status(self, text: str, level: str = "info") -> None:
        self.s.status(text, level)

    def state(self, text: str) -> None:
        self.s.set_state(text)

    def roadmap_cameras(self, cameras: np.ndarray) -> None:
        self.s.pub_rm_cams.publish(cv.pose_array(cameras, self.s.frame, self._stamp()))

    def roadmap_markers(self, scene, cam_xyz, scores, base_xy, edges) -> None:
        s, stamp = self.s, self._stamp()
        ms = mk.scene_markers(scene, stamp)
        ms += mk.roadmap_markers(s.frame, cam_xyz, scores, base_xy, edges, stamp, s.p["marker_max_edges"])
        s.pub_markers.publish(mk.marker_array(ms))

    def path(self, cameras, base_xy, scores, scene) -> None:
        s, stamp = self.s, self._stamp()
        s.pub_path_cams.publish(cv.pose_array(cameras, s.frame, stamp))
        if s.p["publish_markers"]:
            ms = mk.scene_markers(scene, stamp) + mk.path_markers(s.frame, base_xy, cameras[:, :3, 3], scores, stamp)
            s.pub_path_markers.publish(mk.marker_array(ms))

    def base_path(self, positions: np.ndarray) -> None:
        self.s.pub_base_path.publish(cv.base_path_msg(positions, self.s.frame, self._stamp()))


def main(args=None) -> int:
    return run_nodes([RoadmapServer], args, description=__doc__)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
