"""``replan_monitor``: the input gate and supervisor of the node suite.

Subscribes to the mocap rigid bodies (geometry_msgs/PoseStamped, one topic per target/obstacle named in its
parameters, sensor-data QoS: best effort, keep last 1), to ``/joint_states`` (+ the robot's own mocap pose for the
base), and to the goal (``/psprm/goal`` PoseStamped base pose, or ``/psprm/goal_regions`` std_msgs/String with goal
region names of the scene). Every message is checked (finite, scene frame, age); good ones are forwarded to the
server and the scorer on ``/psprm/state/...``, bad ones produce a warning on ``~/status`` and are dropped.

Triggers applied here (the geometric triggers of the core ReplanSettings run inside the server on every forwarded
state): a new goal, a predicted path score (``/psprm/path/score`` from the perception scorer) below
``min_path_score_ratio`` x its value at plan time, the robot deviating from the trajectory by more than
``deviation_tolerance`` m, a periodic replan (``replan_period_s``), and stale inputs: an obstacle silent for
``stale_timeout_s`` makes the server stop (``~/stop``), a silent target only warns (the last plan stays safe).
It reports a JSON summary on ``~/status`` once per second (plans, stops, latencies, stale bodies).
"""

from __future__ import annotations

import json
import threading
import time
from typing import Optional

import numpy as np

from psprm_core.collision import CollisionChecker
from psprm_core.errors import InputError

from . import core
from .interfaces.frames import declare_frame_params
from .interfaces.tf_tree import TfTree, subscribe_tf
from .monitor.inputs import InputGate
from .monitor.triggers import Triggers
from .robots.adapters import load_adapter
from .robots.robot_state import RobotStateTracker, offset_from_params
from .runner import run_nodes

P = core.Param
MONITOR_PARAMS = {
    "mocap_prefix": P("/mocap", "default topic of a rigid body: <prefix>/<name>/pose"),
    "target_topics": P([], "one per target (same order); [] = defaults from mocap_prefix"),
    "obstacle_topics": P([], "one per dynamic obstacle (same order)"),
    "base_pose_source": P("odom", "where the base pose comes from: odom (nav_msgs/Odometry on odom_topic), pose (a "
                                  "mocap PoseStamped of a body on the base, robot_pose_topic), joint_states "
                                  "(base_x/base_y/base_theta in /joint_states) or tf (the pose of base_frame in the "
                                  "scene frame from the topics tf and tf_static)"),
    "base_frame": P("base_link", "the robot's base frame in tf (base_pose_source tf)"),
    "input_frames_from_tf": P(False, "a pose in a frame input_frames has no transform for is mapped into the scene "
                                     "frame through tf (topics tf and tf_static), when tf links the two"),
    "odom_topic": P("odom", "nav_msgs/Odometry of the base (base_pose_source odom)"),
    "robot_pose_topic": P("", "the robot's own rigid body (base_pose_source pose)"),
    "base_body_offset.xyz": P([0.0, 0.0, 0.0], "pose of base_link in the mocap body's frame: xyz"),
    "base_body_offset.quat": P([0.0, 0.0, 0.0, 1.0], "... and quaternion (x, y, z, w)"),
    "adapter": P("", "adapter config whose name maps translate /joint_states names ('' = the robot's, 'none')"),
    "joint_states_topic": P("joint_states", "sensor_msgs/JointState of the robot"),
    "robot_state_timeout_s": P(0.5, "a base pose or joint state older than this is stale: no robot state is "
                                    "forwarded (nothing is planned)", live=True, lo=0.01),
    "robot_state_rate_hz": P(20.0, "forward the robot state at most this often (0 = every /joint_states message)",
                             live=True, lo=0.0),
    "goal_topic": P("psprm/goal", "PoseStamped base goal (x, y, yaw)"),
    "goal_regions_topic": P("psprm/goal_regions", "String: comma-separated goal regions of the scene"),
    "max_pose_age_s": P(1.0, "refuse poses older than this (0 = no check)", live=True, lo=0.0),
    # forwarding of the mocap stream: a pose that moved more than the deadband since the last forwarded one goes out
    # at once; otherwise at most relay_keepalive_hz (keeps the downstream nodes' CPU for planning; the core's move
    # thresholds are 3-5 cm / 0.1-0.15 rad, so nothing that matters is held back). 0 / 0 = forward everything.
    "relay_deadband_m": P(0.01, "forward at once when moved more than this (m)", live=True, lo=0.0),
    "relay_deadband_rad": P(0.02, "... or turned more than this (rad)", live=True, lo=0.0),
    "relay_keepalive_hz": P(10.0, "otherwise forward at most this often", live=True, lo=0.0),
    "stale_timeout_s": P(0.5, "a rigid body silent this long is stale (obstacle: stop)", live=True, lo=0.01),
    "stop_on_stale_obstacle": P(True, "stop the robot when an obstacle's stream goes silent", live=True),
    "check_rate_hz": P(10.0, "watchdog rate", lo=0.5),
    "min_path_score_ratio": P(0.5, "ask for a plan when the path score < ratio x plan score (0 = off)", live=True,
                              lo=0.0, hi=1.0),
    "deviation_tolerance": P(0.3, "ask for a plan when the base is this far (m) off the trajectory's path (its "
                                  "points within 3 s of the trajectory's clock)", live=True,
                             lo=0.0),
    "replan_period_s": P(0.0, "periodic replan (0 = off)", live=True, lo=0.0),
    "min_request_interval_s": P(1.0, "at most one plan request per interval", live=True, lo=0.0),
    "warning_period_s": P(1.0, "the same kind of warning at most once per period (a 120 Hz stream of bad poses "
                               "does not flood the log)", live=True, lo=0.0),
    "start_problem": P("", "scene problem whose start fills joints /joint_states does not carry"),
    "diagnostics_period_s": P(1.0, "period of /diagnostics", lo=0.1),
}


class ReplanMonitor(InputGate, Triggers, core.ConfiguredRobot):
    """The monitor as a lifecycle node. Construction declares the parameters and makes ``~/status``, the
    ``/diagnostics`` publisher, the plan/stop service clients and the 1 Hz summary; configure reads the parameters,
    loads the scene and robot model, and makes the input subscriptions, the forwarding publishers and the watchdog
    and diagnostics timers; activate/deactivate gate forwarding; cleanup destroys what configure made and drops the
    models, so a configure after it follows changed parameters. Until configure, the scene, robot model, tracker and
    frame table are None (``robot``: see :attr:`robot`). The input callbacks are its base class
    :class:`~psprm_ros.monitor.inputs.InputGate`, the server-output callbacks, watchdog and requests its base class
    :class:`~psprm_ros.monitor.triggers.Triggers`."""

    def __init__(self, node_name: str = "replan_monitor", **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import String
        from std_srvs.srv import Trigger

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        self.spec = {**core.common_params(), **MONITOR_PARAMS}
        self.active = False
        self._lock = threading.Lock()
        # made at configure, dropped at cleanup
        self.scene = None
        self._robot = None
        self.frame: Optional[str] = None
        self.frames = None
        self.targets: list = []
        self.obstacles: list = []
        self.names: list = []
        self.checker = None
        self.q: Optional[np.ndarray] = None
        self.tracker = None
        self.relay: dict = {}
        self.topics: dict = {}
        self.pub_goals = self.pub_robot = None
        self._grace: Optional[core.StallGrace] = None
        self._made = core.ConfigureScope(node)  # what configure makes, released by cleanup
        self.p = core.declare_reconfigurable_params(node, self.spec, self._apply_param)
        try:
            declare_frame_params(node, "")  # the parameters only: the frame table is made at configure
        except Exception:  # a malformed transform: configure reports it
            pass
        self.robot_state_problem = "not configured"
        self._robot_fwd_t = 0.0
        self._warned: dict = {}  # warning kind -> monotonic time of its last report
        self.base: Optional[np.ndarray] = None
        self.last_seen: dict = {}  # body -> monotonic time of the last good pose
        self.stale: set = set()
        self.counts = {"forwarded": 0, "refused": 0, "plans": 0, "kept": 0, "stops": 0, "failed": 0, "requests": 0,
                       "robot_states": 0}
        self.latencies: list = []
        self.plan_score: Optional[float] = None
        self.path_score: Optional[float] = None
        self.traj: Optional[dict] = None
        self.last_plan_t = time.monotonic()
        self.last_request_t = 0.0
        self.last_warning = ""
        self._last_fwd: dict = {}  # (kind, name) -> (monotonic t, p, q) of the last forwarded pose

        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_diag = node.create_publisher(DiagnosticArray, core.DIAGNOSTICS_TOPIC, 10)
        srv_cb = MutuallyExclusiveCallbackGroup()
        self.cli_plan = node.create_client(Trigger, f"{core.SERVER_NAME}/plan", callback_group=srv_cb)
        self.cli_stop = node.create_client(Trigger, f"{core.SERVER_NAME}/stop", callback_group=srv_cb)
        node.create_timer(1.0, self._report, callback_group=MutuallyExclusiveCallbackGroup())

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        """Read the parameters, load the scene and robot model, make the subscriptions, publishers and timers. A
        bad parameter or a missing file raises: the configure fails with the reason on ``~/status``, the node stays
        unconfigured with nothing made, and can be configured again."""
        return self._made.configure(self._configure, self._release)

    def _configure(self) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32, String
        from trajectory_msgs.msg import JointTrajectory

        node, p = self.node, dict(self.p)
        scene, robot = core.load_configured_scene_and_robot(node, p)
        frames = declare_frame_params(node, scene.frame)
        targets = core.scene_targets(scene, p["targets"])
        obstacles = list(p["dynamic_obstacles"])
        for o in obstacles:
            scene.obstacle(o)
        q = core.start_configuration(robot, scene, p["start_problem"])
        name_map = {}
        if p["adapter"] != "none":
            try:
                name_map = load_adapter(p["adapter"] or robot.name, robot).name_map()
            except Exception as exc:  # no adapter config for this robot: planning/URDF names only
                if p["adapter"]:
                    raise
                self.log.info(f"no adapter name map ({exc})")
        tracker = RobotStateTracker(
            robot, frames, p["base_pose_source"], name_map,
            offset_from_params(p["base_body_offset.xyz"], p["base_body_offset.quat"]),
            p["robot_state_timeout_s"], template=q, base_frame=p["base_frame"])
        pairs = self._topics("target", targets, p["target_topics"]) + \
            self._topics("obstacle", obstacles, p["obstacle_topics"])
        src = p["base_pose_source"]
        if robot.mobile and src == "pose" and not p["robot_pose_topic"]:
            raise InputError("base_pose_source 'pose' needs robot_pose_topic (the mocap body on the base)")
        checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
        with self._lock:
            self.scene, self._robot, self.frame, self.frames = scene, robot, scene.frame, frames
            self.targets, self.obstacles, self.names = targets, obstacles, list(robot.joint_names)
            self.checker, self.q, self.tracker = checker, q, tracker
            self.robot_state_problem = "waiting for base pose"
            self.base, self.traj, self.plan_score, self.path_score = None, None, None, None
            self.last_seen, self.stale, self._last_fwd, self._warned = {}, set(), {}, {}
            self.last_plan_t = time.monotonic()

        sensor = qos_profile_sensor_data
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_goals = self._made.publisher(JointTrajectory, core.GOALS_TOPIC, latched)
        self.pub_robot = self._made.publisher(JointState, core.ROBOT_STATE_TOPIC, sensor)
        cb = MutuallyExclusiveCallbackGroup()
        for kind, name, topic in pairs:
            out = core.target_topic(name) if kind == "target" else core.obstacle_topic(name)
            self.relay[(kind, name)] = self._made.publisher(PoseStamped, out, sensor)
            self._made.subscription(PoseStamped, topic, self._pose_cb(kind, name), sensor, callback_group=cb)
        self.topics = {f"{k}:{n}": t for k, n, t in pairs}
        if robot.mobile and src == "pose":
            self._made.subscription(PoseStamped, p["robot_pose_topic"], self._base_cb, sensor, callback_group=cb)
        if robot.mobile and src == "odom":
            self._made.subscription(Odometry, p["odom_topic"], self._odom_cb, 10, callback_group=cb)
        if (robot.mobile and src == "tf") or p["input_frames_from_tf"]:
            # one tree: the tracker's when the base pose comes from tf
            frames.tf = tracker.tf if tracker.tf is not None else TfTree()
            self._made.own(subscribe_tf(node, self._tf_cb, cb))
        self._made.subscription(JointState, p["joint_states_topic"], self._joints_cb, 10, callback_group=cb)
        self._made.subscription(PoseStamped, p["goal_topic"], self._goal_cb, 10, callback_group=cb)
        self._made.subscription(String, p["goal_regions_topic"], self._regions_cb, 10, callback_group=cb)
        self._made.subscription(String, core.PLAN_INFO_TOPIC, self._info_cb, 10, callback_group=cb)
        self._made.subscription(Float32, core.PATH_SCORE_TOPIC, self._score_cb, 10, callback_group=cb)
        self._made.subscription(JointTrajectory, core.TRAJECTORY_TOPIC, self._traj_cb, latched, callback_group=cb)
        self._grace = core.StallGrace(1.0 / max(0.5, p["check_rate_hz"]))
        self._made.timer(1.0 / max(0.5, p["check_rate_hz"]), self._check,
                         callback_group=MutuallyExclusiveCallbackGroup())
        self._made.timer(p["diagnostics_period_s"], self._diagnostics, callback_group=MutuallyExclusiveCallbackGroup())
        bodies = ", ".join(f"{k} {n} on {t}" for k, n, t in pairs) or "no bodies"
        self.status(f"configured: scene {scene.name}, robot {robot.name}; {bodies}; base pose from {src}")

    def _release(self) -> None:
        """Destroy the subscriptions, publishers and timers configure made and drop the models."""
        self._made.release()
        with self._lock:
            self.relay, self.topics = {}, {}
            self.pub_goals = self.pub_robot = None
            self.scene = self._robot = self.frame = self.frames = None
            self.targets, self.obstacles, self.names = [], [], []
            self.checker = self.q = self.tracker = self._grace = None
            self.base = self.traj = None
            self.last_seen, self.stale, self._last_fwd = {}, set(), {}
            self.robot_state_problem = "not configured"

    def on_activate(self, state) -> bool:
        self.active = True
        self.status("active: forwarding inputs")
        return True

    def on_deactivate(self, state) -> bool:
        self.active = False
        self.status("inactive: inputs are no longer forwarded")
        return True

    def on_cleanup(self, state) -> bool:
        self._release()
        self.status("unconfigured: subscriptions, publishers and models released")
        return True

    def on_shutdown(self, state) -> bool:
        self.active = False
        self._release()
        return True

    def _apply_param(self, name: str, value) -> None:
        if name == "robot_state_timeout_s" and self.tracker is not None:
            self.tracker.timeout_s = float(value)

    def warn_limited(self, kind: str, text: str) -> None:
        """A warning, at most once per ``warning_period_s`` for each ``kind`` (others are counted only)."""
        now = time.monotonic()
        if now - self._warned.get(kind, -1e9) >= self.p["warning_period_s"]:
            self._warned[kind] = now
            self.status(text, "warning")

    def _diagnostics(self) -> None:
        now = time.monotonic()
        with self._lock:
            seen = {f"{k} {n}": now - t for (k, n), t in self.last_seen.items()}
            counts = dict(self.counts)
            stale = sorted(self.stale)
            problem = self.robot_state_problem
        bt = self.tracker.base_t
        level = core.DIAG_OK
        msg = "inputs live"
        if problem:
            level, msg = core.DIAG_WARN, problem
        elif stale:
            level, msg = core.DIAG_WARN, f"stale: {', '.join(stale)}"
        vals = {"lifecycle": core.lifecycle_state(self.node), **counts,
                "base_pose_age_s": (now - bt) if bt is not None else "never",
                **{f"age_s {k}": v for k, v in seen.items()}}
        core.publish_diagnostics(self.pub_diag, self.node, [core.diagnostic_status(
            f"psprm: {self.node.get_fully_qualified_name()}", self._robot.name, level, msg, vals)])

    def _topics(self, kind, names, topics) -> list:
        if topics and len(topics) != len(names):
            raise InputError(f"{kind}_topics has {len(topics)} entries for {len(names)} {kind}s")
        return [(kind, n, topics[i] if topics else f"{self.p['mocap_prefix']}/{n}/pose") for i, n in enumerate(names)]

    # ------------------------------------------------------------------------------------------------ reporting
    def status(self, text: str, level: str = "info") -> None:
        if level == "warning":
            self.last_warning = text
        core.report(self.log, self.pub_status, text, level)

    def summary(self) -> dict:
        with self._lock:
            lat = np.array(self.latencies[-200:], float)
            return {**self.counts, "stale": sorted(self.stale), "plan_score": self.plan_score,
                    "path_score": self.path_score,
                    "latency_ms_median": float(np.median(lat)) if len(lat) else None,
                    "robot_state": self.robot_state_problem or "ok",
                    "last_warning": self.last_warning}

    def _report(self) -> None:
        from std_msgs.msg import String

        self.pub_status.publish(String(data="summary: " + json.dumps(self.summary())))

    def destroy(self) -> None:
        self.node.destroy_node()


def main(args=None) -> int:
    return run_nodes([ReplanMonitor], args, description=__doc__, prog="replan_monitor")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
