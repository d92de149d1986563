"""``robot_adapter``: executes the planned trajectories on a robot's own controllers (lifecycle node).

    robot_adapter --ros-args --params-file config/ros/dynamic_person.yaml [-p robot_adapter:adapter:=stretch2]

Subscribes to ``/psprm/trajectory`` (planning joints, scene frame), ``/joint_states`` and the base pose
(``nav_msgs/Odometry``, or a mocap rigid body with a body -> base_link offset; poses in another frame go through
the ``input_frames`` transforms). Each new trajectory is checked against the measured state (first point within
each controller's ``start_tolerance``, the base within ``start_tolerance_m`` / ``_rad``); a mismatch stops the
robot and requests a replan from the roadmap server (as MoveIt refuses a trajectory whose start is not the current
state). An accepted trajectory goes to every controller of the adapter config (``config/ros/adapters/<robot>.yaml``,
:mod:`psprm_ros.robots.adapters`): a JointTrajectory topic or a FollowJointTrajectory action (control_msgs, imported
only then), the exact joint set under the robot's names, stamped 0 or now + lead, at most one goal per
``min_goal_interval_s``; the base follows the planned base path in closed loop from the measured pose at the
adapter's ``rate_hz`` (Twist or TwistStamped on cmd_vel, within the base's velocity and acceleration limits;
:mod:`psprm_ros.robots.base_follower`). A one-point trajectory (the server's stop), a stale base pose or joint state, a
deactivation and shutdown stop the robot: zero twist, a hold at the measured configuration with a positive
time_from_start on every topic controller, and a cancel of every active action goal.

The path tolerance keeps what the robot executes within the clearance of what the server checked: at every control
step the measured configuration is compared with the trajectory's configurations within ``path_window_s`` of now
(:class:`psprm_core.tracking.CheckedPath`: the largest distance any point of the robot's collision boxes lies apart);
beyond ``path_tolerance_m`` (below the server's ``collision_padding``) the robot stops and a new plan is asked for,
as a joint_trajectory_controller aborts a goal whose path tolerance is violated. A new trajectory whose start is
already that far from the measured configuration is refused.
"""

from __future__ import annotations

import threading
import time
from typing import Optional

import numpy as np

from psprm_core.errors import InputError
from psprm_core.tracking import CheckedPath, displacement

from . import core
from .interfaces import conversions as cv
from .robots import adapters as ad
from .robots.base_follower import BaseFollower, BaseReference, Gains, Limits

P = core.Param
REST_MPS, REST_RADPS = 0.01, 0.02  # a base slower than this on both axes ...
REST_S = 0.1  # ... for this long is at rest
REST_WAIT_S = 2.0  # a replan pending "at rest" is asked for this long after the stop at the latest
SPLICE_TOL_M = 0.01  # a new trajectory this close to the one executing (whole robot) ...
# how far back along the trajectory under way a splice may begin: a splice starts where the robot was when the
# replan began, which it may have passed by seconds when a replan is slow (the server withdraws a splice it has
# passed altogether, so this bounds the planning and delivery time a splice can take)
SPLICE_LOOKBACK_S = 6.0
SPLICE_CHECK_S = 0.3  # ... over its first this many seconds continues it: a splice
ADAPTER_PARAMS = {
    "adapter": P("", "adapter config name (config/ros/adapters, or share/psprm_ros/config/adapters when installed) "
                     "or YAML path ('' = the robot's name)", rebuild=True),
    "interface": P("", "'' = each controller's interface from the adapter config; 'topic' = JointTrajectory topics "
                       "for every controller (what sim_robot offers); 'action' = FollowJointTrajectory actions",
                   rebuild=True),
    "trajectory_topic": P(core.TRAJECTORY_TOPIC, "the planned trajectories", rebuild=True),
    "base_pose_source": P("odom", "odom (nav_msgs/Odometry on odom_topic), pose (mocap PoseStamped on "
                                  "robot_pose_topic), joint_states or tf (the pose of base_frame in the scene frame "
                                  "from the topics tf and tf_static)", rebuild=True),
    "base_frame": P("base_link", "the robot's base frame in tf (base_pose_source tf)", rebuild=True),
    "odom_topic": P("odom", "nav_msgs/Odometry of the base", rebuild=True),
    "robot_pose_topic": P("", "mocap rigid body on the base (base_pose_source pose)", rebuild=True),
    "base_body_offset.xyz": P([0.0, 0.0, 0.0], "pose of base_link in the mocap body's frame: xyz", rebuild=True),
    "base_body_offset.quat": P([0.0, 0.0, 0.0, 1.0], "... and quaternion (x, y, z, w)", rebuild=True),
    "joint_states_topic": P("joint_states", "sensor_msgs/JointState of the robot", rebuild=True),
    "state_timeout_s": P(0.5, "a base pose or joint state older than this is stale: the robot stops", live=True,
                         lo=0.01),
    "max_pose_age_s": P(1.0, "refuse base poses whose stamp is older than this (0 = no check)", live=True, lo=0.0),
    "replan_on_refusal": P(True, "request a replan (roadmap_server ~/plan) after refusing a trajectory", live=True),
    "replan_request_interval_s": P(1.0, "at most one replan request per interval", live=True, lo=0.0),
    "plan_service": P(f"{core.SERVER_NAME}/plan", "std_srvs/Trigger of the roadmap server", rebuild=True),
    "start_problem": P("", "scene problem whose start fills joints /joint_states does not carry"),
    "path_tolerance_m": P(0.04, "stop and ask for a new plan when some point of the robot's collision boxes is this "
                                "far (m) from where it was in every configuration of the trajectory within "
                                "path_window_s of now (psprm_core.tracking); below the roadmap server's "
                                "collision_padding, what executes stays clear of every obstacle (0 = off)",
                          live=True, lo=0.0),
    "path_window_s": P(2.0, "the trajectory's configurations this close in time count for path_tolerance_m (a "
                            "base lagging its reference on the path is not off it)", live=True, lo=0.0),
    "diagnostics_period_s": P(1.0, "period of /diagnostics", lo=0.1),
}


class RobotAdapter:
    def __init__(self, node_name: str = "robot_adapter", **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from trajectory_msgs.msg import JointTrajectory

        from .interfaces.frames import declare_frame_params

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        self.spec = {**core.common_params(), **ADAPTER_PARAMS}
        self.p = core.declare_params(node, self.spec)
        self.scene, self.robot = core.load_scene_and_robot(self.p["scene"], self.p["robot"], node=node, params=self.p)
        self.frame = self.scene.frame
        self.frames = declare_frame_params(node, self.frame)
        self.names = list(self.robot.joint_names)
        self.active = False
        self.cfg: Optional[ad.AdapterConfig] = None
        self.tracker = None
        self.tf_tree = None  # base_pose_source tf: the links received, kept for the tracker made at configure
        self.follower: Optional[BaseFollower] = None
        self._lock = threading.RLock()
        self._pubs: dict = {}  # controller -> JointTrajectory publisher
        self._clients: dict = {}  # controller -> ActionClient
        self._goal_handles: dict = {}  # controller -> active ClientGoalHandle
        self._gates: dict = {}
        self._pending: dict = {}  # controller -> (t, P, V, start_at) waiting for its goal interval
        self._twist_pub = None
        self._zero_sent = 0
        self._grace: Optional[core.StallGrace] = None  # the follower step's stall grace (made at configure)
        self._last_replan_request = -1e9
        # after a refusal or an off-path stop: the replan is asked for once the base has come to rest, so that the
        # new plan starts where the robot stands, not where it was while braking (which it has passed by then)
        self._replan_at_rest = ""
        self._stop_t: Optional[float] = None
        self._still_since: Optional[float] = None
        self.counts = {"trajectories": 0, "executed": 0, "refused": 0, "stops": 0, "goals_sent": 0, "spliced": 0,
                       "goals_deferred": 0, "twists": 0, "off_path_stops": 0, "goals_rejected": 0, "goals_failed": 0,
                       "runstops": 0, "mode_switches": 0, "held_until_rest": 0}
        # the robot's driver, when it has modes (Stretch): the mode it reports, the one found at activation, runstop
        self.driver_mode = ""
        self.found_mode = ""
        self.runstopped = False
        self._replan_when_ready = ""
        self._last_switch_request = -1e9
        self._driver_clients: dict = {}  # service name -> Trigger client
        self._goal_seq: dict = {}  # controller -> sequence number of the newest goal sent
        self.last_controller_error = ""
        self._held = None  # (trajectory message, when) held until the braking base rests
        self.speed_scaling = 1.0  # the controllers' speed scaling (0..1), which the base's path clock follows
        self._last_tick: Optional[float] = None
        self.last_refusal = ""
        self.last_state_problem = ""
        self.max_tracking_error = np.zeros(2)  # (m, rad) over the current path
        self.checked: Optional[CheckedPath] = None  # the current trajectory's configurations, for path_tolerance_m
        # the current trajectory as received (before its start was trimmed to the robot's progress) and the time on
        # it at the follower's t0: a splice may begin before the point where this adapter joined the trajectory
        self._splice_ref: Optional[tuple] = None
        self.path_deviation = 0.0  # m, last measured (psprm_core.tracking.CheckedPath.deviation)
        self.max_path_deviation = 0.0  # m, over the current trajectory
        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_diag = node.create_publisher(DiagnosticArray, core.DIAGNOSTICS_TOPIC, 10)
        self.cb = MutuallyExclusiveCallbackGroup()
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(JointTrajectory, self.p["trajectory_topic"], self._traj_cb, latched,
                                 callback_group=self.cb)
        node.create_subscription(JointState, self.p["joint_states_topic"], self._joints_cb, 10, callback_group=self.cb)
        if self.robot.mobile and self.p["base_pose_source"] == "odom":
            node.create_subscription(Odometry, self.p["odom_topic"], self._odom_cb, 10, callback_group=self.cb)
        if self.robot.mobile and self.p["base_pose_source"] == "pose":
            node.create_subscription(PoseStamped, self.p["robot_pose_topic"], self._pose_cb, qos_profile_sensor_data,
                                     callback_group=self.cb)
        if self.robot.mobile and self.p["base_pose_source"] == "tf":
            from .interfaces.tf_tree import TfTree, subscribe_tf

            self.tf_tree = TfTree()
            subscribe_tf(node, self._tf_cb, self.cb)
        from std_srvs.srv import Trigger

        self.cli_plan = node.create_client(Trigger, self.p["plan_service"],
                                           callback_group=MutuallyExclusiveCallbackGroup())
        self._timer = None
        node.create_timer(self.p["diagnostics_period_s"], self._diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())
        core.install_param_callback(node, self.spec, self.p, self._apply_param)

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        from geometry_msgs.msg import Twist, TwistStamped
        from trajectory_msgs.msg import JointTrajectory

        from .robots.robot_state import RobotStateTracker, offset_from_params

        cfg = ad.load_adapter(self.p["adapter"] or self.robot.name, self.robot)
        if self.p["interface"]:
            cfg = cfg.with_interface(self.p["interface"])
        if cfg.base.mode == "stretch_translate_rotate":
            raise InputError("base.mode stretch_translate_rotate: its goals are built by "
                             "psprm_ros.robots.adapters.stretch_base_steps / stretch_base_command; this node drives "
                             "the base with cmd_vel or in Stretch's trajectory mode (base.mode stretch_trajectory)")
        fjt = None
        if any(c.interface == "action" for c in cfg.controllers):
            fjt = ad.import_follow_joint_trajectory()
            if fjt is None:
                raise RuntimeError("control_msgs is not importable (it comes with the robot's ROS install: apt install "
                                   "ros-jazzy-control-msgs); or set the parameter interface:=topic")
        self.cfg = cfg
        self._fjt = fjt
        self.tracker = RobotStateTracker(
            self.robot, self.frames, self.p["base_pose_source"], cfg.name_map(),
            offset_from_params(self.p["base_body_offset.xyz"], self.p["base_body_offset.quat"]),
            self.p["state_timeout_s"],
            template=core.start_configuration(self.robot, self.scene, self.p["start_problem"]),
            base_frame=self.p["base_frame"], tf=self.tf_tree)
        for c in cfg.controllers:
            self._gates[c.name] = ad.GoalGate(c.min_goal_interval_s)
            if c.interface == "topic":
                self._pubs[c.name] = self.node.create_publisher(JointTrajectory, c.topic, 10)
            else:
                from rclpy.action import ActionClient

                self._clients[c.name] = ActionClient(self.node, fjt, c.action, callback_group=self.cb)
        b = cfg.base
        if cfg.driver.kind == "stretch":
            self._driver_interfaces(cfg.driver)
        scaling = sorted({c.speed_scaling_topic for c in cfg.controllers if c.speed_scaling_topic})
        if len(scaling) > 1:
            raise InputError(f"controllers name different speed scaling topics {scaling}: one robot, one scaling")
        if scaling:
            from std_msgs.msg import Float64

            self.node.create_subscription(Float64, scaling[0], self._scaling_cb, 10, callback_group=self.cb)
        if self.robot.mobile:
            if b.mode == "cmd_vel":
                self._twist_pub = self.node.create_publisher(TwistStamped if b.stamped else Twist, b.topic, 10)
            # in trajectory mode the driver moves the base; the follower then only keeps the path's clock (t0, done)
            self.follower = BaseFollower(Limits.for_robot(self.robot, b), Gains(b.k_x, b.k_y, b.k_theta),
                                         b.goal_tolerance_m, b.goal_tolerance_rad, b.settle_s, b.preview_s)
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

        # the follower runs on its own callback group: a burst of state messages never delays a control step
        self._grace = core.StallGrace(1.0 / b.rate_hz)
        self._timer = self.node.create_timer(1.0 / b.rate_hz, self._tick,
                                             callback_group=MutuallyExclusiveCallbackGroup())
        self.status(f"configured: adapter {cfg.robot} ({len(cfg.controllers)} controllers: "
                    f"{', '.join(f'{c.name} [{c.interface}]' for c in cfg.controllers)}; base {b.mode} on {b.topic})")
        return True

    def on_activate(self, state) -> bool:
        self.active = True
        self.status("active: executing trajectories")
        missing = self.missing_controllers()
        if missing:  # reported before anything is sent; trajectories are refused while it lasts
            self.status("; ".join(missing), "warning")
        d = self.cfg.driver
        if d.kind != "none":
            self.found_mode = self.driver_mode
            if self.driver_mode != d.mode:
                self._switch_mode(d.mode)
                self._replan_when_ready = "adapter activated"
                return True
        self._request_replan("adapter activated")
        return True

    def on_deactivate(self, state) -> bool:
        self.stop("adapter deactivated")
        self.restore_driver_mode()
        self.active = False
        return True

    def on_cleanup(self, state) -> bool:
        with self._lock:
            for pub in self._pubs.values():
                self.node.destroy_publisher(pub)
            for cl in self._clients.values():
                cl.destroy()
            if self._twist_pub is not None:
                self.node.destroy_publisher(self._twist_pub)
            if self._timer is not None:
                self.node.destroy_timer(self._timer)
            self._pubs, self._clients, self._gates, self._pending = {}, {}, {}, {}
            self._twist_pub = self._timer = None
            self.cfg = self.follower = None
        return True

    def on_shutdown(self, state) -> bool:
        if self.cfg is not None:
            self.stop("shutting down")
            self.restore_driver_mode()
        self.active = False
        return True

    # ------------------------------------------------------------------------------------------------ driver modes
    def _driver_interfaces(self, d) -> None:
        """Stretch: the driver's mode and runstop topics, its mode switches and its stop (std_srvs/Trigger)."""
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from std_msgs.msg import Bool, String
        from std_srvs.srv import Trigger

        self.node.create_subscription(String, d.mode_topic, self._mode_cb, 10, callback_group=self.cb)
        self.node.create_subscription(Bool, d.runstop_topic, self._runstop_cb, 10, callback_group=self.cb)
        grp = MutuallyExclusiveCallbackGroup()
        for name in [d.switch_name(m) for m in ("navigation", "position", "trajectory")] + [d.stop_service]:
            self._driver_clients[name] = self.node.create_client(Trigger, name, callback_group=grp)

    def missing_controllers(self) -> list:
        """What cannot take a command now: a JointTrajectory topic no controller subscribes to, an action server
        that is not there, the base's cmd_vel without a subscriber."""
        if self.cfg is None:
            return []
        out = []
        for c in self.cfg.controllers:
            if self.cfg.driver.mode == "navigation":
                continue  # nothing is sent to them
            if c.interface == "topic" and self._pubs[c.name].get_subscription_count() == 0:
                out.append(f"no controller listens on {c.topic} ({c.name})")
            if c.interface == "action" and not self._clients[c.name].server_is_ready():
                out.append(f"action server {c.action} not available ({c.name})")
        if self._twist_pub is not None and self._twist_pub.get_subscription_count() == 0:
            out.append(f"no base controller listens on {self.cfg.base.topic}")
        return out

    def driver_ready(self) -> tuple:
        """(ready, why not): the driver reports the configured mode and no runstop."""
        d = self.cfg.driver
        if d.kind == "none":
            return True, ""
        if self.runstopped:
            return False, "the robot is runstopped"
        if self.driver_mode != d.mode:
            return False, (f"the driver is in mode '{self.driver_mode or 'unknown'}', not '{d.mode}'"
                           f"{' (waiting for ' + d.mode_topic + ')' if not self.driver_mode else ''}")
        return True, ""

    def _mode_cb(self, msg) -> None:
        mode = str(msg.data)
        if mode != self.driver_mode:
            self.status(f"driver mode: {mode}")
        self.driver_mode = mode
        if self.cfg is None or not self.active:
            return
        d = self.cfg.driver
        if mode != d.mode and mode != "runstopped" and not self.runstopped:
            # someone switched the driver away: stop what runs (it would be refused) and switch back
            if self.follower is not None and not self.follower.done:
                self.stop(f"the driver left {d.mode} mode (now {mode})")
            self._switch_mode(d.mode)
            self._replan_when_ready = self._replan_when_ready or f"driver mode {mode}"
        elif self._replan_when_ready and self.driver_ready()[0]:
            if self._request_replan(self._replan_when_ready):
                self._replan_when_ready = ""

    def _scaling_cb(self, msg) -> None:
        """UR's speed scaling in percent: the scaled controllers run their trajectories at that rate."""
        v = float(msg.data)
        if not np.isfinite(v) or v < 0.0:
            self.status(f"ignored speed scaling {v}", "warning")
            return
        self.speed_scaling = min(v / 100.0, 1.0)

    def _runstop_cb(self, msg) -> None:
        on = bool(msg.data)
        if on == self.runstopped:
            return
        self.runstopped = on
        if on:
            self.counts["runstops"] += 1
            if self.cfg is not None:
                self.stop("runstop pressed")
            self.status("runstopped: no trajectory is executed until the runstop is released", "error")
        else:
            self.status("runstop released: asking for a new plan")
            self._replan_when_ready = "runstop released"

    def _switch_mode(self, mode: str) -> None:
        """Ask the driver for ``mode`` (at most once a second)."""
        now = time.monotonic()
        if now - self._last_switch_request < 1.0:
            return
        if self._call_driver(self.cfg.driver.switch_name(mode)) is None:
            return
        self._last_switch_request = now
        self.counts["mode_switches"] += 1
        self.status(f"switching the driver to {mode} mode")

    def _call_driver(self, name: str):
        from std_srvs.srv import Trigger

        cl = self._driver_clients.get(name)
        if cl is None or not cl.service_is_ready():
            self.status(f"driver service {name} not available", "error")
            return None
        fut = cl.call_async(Trigger.Request())
        fut.add_done_callback(_retrieve)
        return fut

    def restore_driver_mode(self) -> None:
        """Put the driver back in the mode found at activation (when it was one of the driver's control modes)."""
        if self.cfg is None or self.cfg.driver.kind == "none":
            return
        found, want = self.found_mode, self.cfg.driver.mode
        if found and found != want and found in ("navigation", "position", "trajectory"):
            if self._call_driver(self.cfg.driver.switch_name(found)) is not None:
                self.status(f"driver returned to {found} mode")

    def _apply_param(self, name: str, value) -> None:
        if name == "state_timeout_s" and self.tracker is not None:
            self.tracker.timeout_s = float(value)

    # ------------------------------------------------------------------------------------------------ reporting
    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _diagnostics(self) -> None:
        if self.cfg is None:
            level, msg = core.DIAG_WARN, "not configured"
        elif self.last_state_problem:
            level, msg = core.DIAG_WARN, self.last_state_problem
        elif self.last_refusal:
            level, msg = core.DIAG_WARN, f"last refusal: {self.last_refusal}"
        else:
            level, msg = core.DIAG_OK, "following" if self.follower and not self.follower.done else "idle"
        vals = {"lifecycle": core.lifecycle_state(self.node), **self.counts,
                "max_tracking_error_m": float(self.max_tracking_error[0]),
                "max_tracking_error_rad": float(self.max_tracking_error[1]),
                "path_deviation_m": float(self.path_deviation), "max_path_deviation_m": float(self.max_path_deviation)}
        core.publish_diagnostics(self.pub_diag, self.node, [
            core.diagnostic_status(f"psprm: {self.node.get_fully_qualified_name()}", self.robot.name, level, msg, vals)])

    # ------------------------------------------------------------------------------------------------ inputs
    def _joints_cb(self, msg) -> None:
        if self.tracker is None:
            return
        try:
            with self._lock:
                self.tracker.update_joints(msg, self._now())
        except Exception as exc:
            self.status(f"ignored joint state: {exc}", "warning")

    def _odom_cb(self, msg) -> None:
        if self.tracker is None:
            return
        try:
            with self._lock:
                self.tracker.update_odometry(msg, self._now(), self._now(), self.p["max_pose_age_s"])
        except Exception as exc:
            self.status(f"ignored odometry: {exc}", "warning")

    def _pose_cb(self, msg) -> None:
        if self.tracker is None:
            return
        try:
            with self._lock:
                self.tracker.update_pose(msg, self._now(), self._now(), self.p["max_pose_age_s"])
        except Exception as exc:
            self.status(f"ignored base pose: {exc}", "warning")

    def _tf_cb(self, msg, static: bool) -> None:
        with self._lock:
            if self.tracker is None:  # not configured yet: the tree keeps the links (tf_static comes once)
                self.tf_tree.update(msg, static, self._now())
                return
            dropped = self.tracker.update_tf(msg, static, self._now())
        for text in dropped:
            self.status(f"ignored {text}", "warning")

    def _traj_cb(self, msg) -> None:
        self.counts["trajectories"] += 1
        if not self.active or self.cfg is None:  # an inactive adapter drives nothing (activation asks for a new plan)
            return
        try:
            self.execute(msg)
        except Exception as exc:  # never die on a message; a trajectory we cannot execute stops the robot
            self.stop(f"cannot execute the trajectory: {exc}")

    # ------------------------------------------------------------------------------------------------ execution
    def measured(self) -> tuple:
        with self._lock:
            return self.tracker.state(self._now())

    def execute(self, msg) -> bool:
        """Check a planned trajectory against the measured state and send it to the controllers and the base."""
        P = cv.joint_trajectory_positions(msg, self.names)
        t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
        q, why = self.measured()
        if q is None:
            self.stop(f"trajectory not executed: {why}")
            return False
        if len(P) <= 1:
            self._held = None
            self.stop("stop trajectory received")
            return False
        if self.robot.mobile and self._braking():
            # a plan that arrives while the base still brakes from a stop was made from where the base was, which it
            # has passed by now: it waits until the base rests (at most REST_WAIT_S), then starts from there
            if self._held is None:
                self.counts["held_until_rest"] += 1
                self.status("trajectory held until the base rests (it is braking from a stop)")
            self._held = (msg, self._now())
            return True
        self._held = None
        ready, why_not = self.driver_ready()
        if not ready:
            self.stop(f"trajectory not executed: {why_not}")
            self._replan_when_ready = self._replan_when_ready or why_not
            if not self.runstopped:
                self._switch_mode(self.cfg.driver.mode)
            return False
        if self.cfg.driver.kind == "stretch" and self.cfg.driver.mode == "navigation":
            # the driver aborts arm and head goals in navigation mode: only a plan that keeps them still runs
            moved = np.abs(P[:, 3:] - q[None, 3:]).max(0) if self.robot.mobile else np.abs(P - q[None]).max(0)
            k = int(np.argmax(moved))
            tol = min(c.start_tolerance for c in self.cfg.controllers)
            if moved[k] > tol:
                j = self.names[(3 if self.robot.mobile else 0) + k]
                return self._refuse(f"navigation mode moves the base only, the plan moves {j} by {moved[k]:.3f} "
                                    f"(use the trajectory-mode adapter)")
        missing = self.missing_controllers()
        if missing:
            return self._refuse("; ".join(missing))
        V = None
        if all(len(p.velocities) == len(msg.joint_names) for p in msg.points):
            V = cv.joint_trajectory_positions(_Velocities(msg), self.names)
        lead = max([c.lead_time_s for c in self.cfg.controllers] + [self.cfg.base.lead_time_s])
        if self.cfg.base.mode == "stretch_trajectory":
            lead = 0.0  # a trajectory-mode goal starts when the driver receives it
        # a splice (the new trajectory continues the one the robot executes): the base goes on from where it is now,
        # and only the controllers' goals start a lead time ahead (controller_command trims them there)
        splice_d, not_splice, splice_tau = self._splice_deviation(t, P, q) if self.robot.mobile else (None, "", None)
        base_lead = 0.0 if splice_d is not None else lead
        received, tau0 = (np.asarray(t, float) - t[0], P.copy()), 0.0
        if self.robot.mobile:
            with self._lock:
                vel = self.tracker.base_velocity.copy()
            # the robot drove on since the plan started from its state: start at its progress, not back at the start
            tau0 = ad.progress_offset(t, P, q, vel, base_lead, velocity_limits=self.robot.velocity,
                                      horizon_s=SPLICE_LOOKBACK_S if splice_d is not None else 1.5)
            if splice_tau is not None:
                # a splice repeats the trajectory under way up to its commit instant: the robot's time along it is
                # its time along the trajectory under way, less where the splice began on it; taken unless the
                # nearest configuration lies more than the splice tolerance nearer the robot
                d_s, d_n = displacement(self.robot, q, ad.sample_at(t, P, [splice_tau, tau0]))
                if d_s <= d_n + SPLICE_TOL_M:
                    tau0 = splice_tau
            if tau0 > 0:
                t, P, V = ad.trim_from(t - t[0], P, V, tau0)
                if len(t) <= 1:
                    self.stop("the robot is already at the end of the new trajectory")
                    return False
        for c in self.cfg.controllers:
            ok, joint, err = ad.check_start(c, self.names, P[0], q)
            if not ok:
                return self._refuse(f"first point {err:.3f} from the measured {joint} ({c.name}: tolerance "
                                    f"{c.start_tolerance})")
        if self.robot.mobile:
            ok, what, err = ad.check_base_start(self.cfg.base, P[0, :3], q[:3])
            if not ok:
                return self._refuse(f"first point {err:.3f} from the measured {what}")
        checked, tol = None, self.p["path_tolerance_m"]
        if tol > 0 and self.robot.mobile:
            checked = CheckedPath(self.robot, t, P)
            d = splice_d
            if d is not None:
                # a splice: the robot keeps following the trajectory it executes, which the new one continues; only
                # its distance from that one counts (as at every control step)
                self.counts["spliced"] += 1
            else:
                # where the robot is and where it would brake to: a base still moving on its last command overshoots
                # a trajectory that starts behind it (planned from where it was when planning began) by that much
                probe = np.vstack([q[None], ad.braking_configurations(q, vel, self.follower.limits)])
                d = max(checked.deviation(x, 0.0, self.p["path_window_s"])[0] for x in probe)
            if d > tol:
                return self._refuse(f"the robot, braking from where it is, comes {d:.3f} m from the trajectory's "
                                    f"configurations near its start (path tolerance {tol:g} m; not a continuation "
                                    f"of the motion under way: {not_splice})")
        now = self._now()
        start_at = now + base_lead
        splice_ref = (CheckedPath(self.robot, *received), tau0) if self.robot.mobile else None
        if self.cfg.base.mode == "stretch_trajectory":
            ok = self._execute_trajectory_mode(t, P, V, q, now)
            if ok:
                with self._lock:
                    self._splice_ref = splice_ref
            return ok
        with self._lock:
            for c in self.cfg.controllers:
                if self.cfg.driver.mode == "navigation":
                    continue  # the arm and head stay where they are (checked above)
                item = (t, P, V, start_at)
                out = self._gates[c.name].offer(item, now)
                if out is None:
                    self._pending[c.name] = item
                    self.counts["goals_deferred"] += 1
                else:
                    self._pending.pop(c.name, None)
                    self._send(c, *out, now=now)
            if self.robot.mobile:
                self.follower.set_path(BaseReference(t, P[:, :3]), start_at)
                self.max_tracking_error = np.zeros(2)
                self.checked, self.max_path_deviation = checked, 0.0
                self._splice_ref = splice_ref
                self._zero_sent = 0
        self.counts["executed"] += 1
        self.last_refusal = ""
        self._replan_at_rest, self._stop_t, self._still_since = "", None, None  # a new plan came meanwhile
        return True

    def _execute_trajectory_mode(self, t, P, V, q, now: float) -> bool:
        """Stretch's trajectory mode: the trajectory from now on as one goal with the base
        (:func:`psprm_ros.robots.stretch.goal_for_controller`), its first waypoint where the joints are; what the driver
        makes of it must stay within ``max_goal_deviation_m`` of the planned trajectory. Goals closer than the goal
        interval wait for it (trimmed to the moment they leave)."""
        c = self.cfg.controllers[0]
        item = (t, P, V, now)
        with self._lock:
            out = self._gates[c.name].offer(item, now)
            if out is None:
                self._pending[c.name] = item
                self.counts["goals_deferred"] += 1
                self.counts["executed"] += 1
                return True
            self._pending.pop(c.name, None)
        ok = self._send_trajectory_mode(c, *out, now=now, q=q)
        if ok:
            self.counts["executed"] += 1
            self.last_refusal = ""
            self._replan_at_rest, self._stop_t, self._still_since = "", None, None
        return ok

    def _send_trajectory_mode(self, c, t, P, V, start_at: float, now: float, q=None) -> bool:
        from .robots import stretch

        late = now - start_at
        if late > 1e-6:
            t, P, V = ad.trim_from(np.asarray(t, float) - t[0], P, V, late)
            if len(t) <= 1:
                return True
        if q is None:  # a goal released by the goal interval: the state now (execute passes the one it checked)
            q, why = self.measured()
            if q is None:
                self.stop(f"trajectory not executed: {why}")
                return False
        b = self.cfg.base
        t = np.asarray(t, float) - t[0]
        try:
            goal = stretch.goal_for_controller(c, self.names, t, P, V, b.min_waypoint_interval_s)
        except InputError as exc:
            return self._refuse(str(exc))
        idx = [self.names.index(j) for j in c.joints]
        goal.positions[0] = q[idx]  # the driver starts a joint only from where it is
        # one CheckedPath of the planned trajectory on the goal's clock: for the goal's check and the path tolerance
        ts, Pg = stretch.planned_on_goal_clock(goal, t, P)
        checked = CheckedPath(self.robot, ts, Pg)
        dev = stretch.deviation_check(self.robot, goal, self.names, c.joints, t, P, P[0, :3], step_s=0.1,
                                      window_s=self.p["path_window_s"], checked=checked)
        if dev > b.max_goal_deviation_m:
            return self._refuse(f"the driver's waypoints would take the robot {dev:.3f} m from the planned "
                                f"trajectory (max_goal_deviation_m {b.max_goal_deviation_m:g})")
        if self.p["path_tolerance_m"] <= 0:
            checked = None
        with self._lock:
            self._send_goal(c, goal)
            self.follower.set_path(BaseReference(ts, Pg[:, :3]), now)
            self.checked, self.max_path_deviation = checked, 0.0
            self.max_tracking_error = np.zeros(2)
        return True

    def _send_goal(self, c, goal) -> None:
        """A trajectory-mode goal (joints and the base) on ``c``'s action."""
        from .robots import stretch

        cl = self._clients[c.name]
        if not cl.server_is_ready():
            self._controller_failed(c.name, f"action server {c.action} not available")
            return
        jt, mt = stretch.goal_messages(goal)
        g = self._fjt.Goal()
        ad.fill_goal(g, {"trajectory": jt, "multi_dof_trajectory": mt,
                         "goal_time_tolerance": cv.duration_msg(c.goal_time_tolerance_s)})
        self._dispatch(c, cl, g)

    def _dispatch(self, c, cl, goal) -> None:
        seq = self._goal_seq.get(c.name, 0) + 1
        self._goal_seq[c.name] = seq
        fut = cl.send_goal_async(goal)
        fut.add_done_callback(lambda f, name=c.name, n=seq: self._goal_response(name, f, n))
        self.counts["goals_sent"] += 1

    def _braking(self) -> bool:
        """The base moves (measured) while no trajectory runs: it brakes after a stop."""
        if self.follower is None or not self.follower.done:
            return False
        with self._lock:
            v, w = (abs(float(x)) for x in self.tracker.base_velocity)
        return v >= REST_MPS or w >= REST_RADPS

    def _release_held(self, now: float) -> None:
        msg, since = self._held
        if self._braking() and now - since < REST_WAIT_S:
            return
        self._held = None
        try:
            self.execute(msg)
        except Exception as exc:
            self.stop(f"cannot execute the trajectory: {exc}")

    def _splice_deviation(self, t: np.ndarray, P: np.ndarray, q: np.ndarray) -> tuple:
        """(deviation, why not, time along it): when a new trajectory continues the one being executed (each of its
        configurations over its first ``SPLICE_CHECK_S`` within ``SPLICE_TOL_M``, whole robot, of the executing
        trajectory's configurations near the robot's time along it): the measured configuration's deviation from the
        executing trajectory there, "" and the robot's time along the new trajectory (its time along the executing
        one less the latest time the new one's start lies on it; None if it lies on it nowhere); else None, the
        reason and None. The roadmap server's replans of a robot in
        motion are such splices (psprm_core.planning.execution): the trajectory under way up to a rest instant at
        least the planning and delivery time ahead, then the new plan."""
        with self._lock:
            cur, ref, t0, following = self.checked, self._splice_ref, self.follower.t0, not self.follower.done
        if ref is None:
            return None, "no trajectory under way", None
        if not following:
            return None, "the trajectory under way has ended or was stopped", None
        ref_path, ref_offset = ref
        tau = self._now() - t0
        w = self.p["path_window_s"]
        ts = np.linspace(0.0, min(SPLICE_CHECK_S, float(t[-1])), 6)
        X = np.stack([np.interp(ts, t, P[:, j]) for j in range(P.shape[1])], 1)
        # the splice's start lies behind the robot by the replan's planning and delivery time (possibly before the
        # point where this adapter joined the trajectory under way): look for it on that trajectory as received,
        # from SPLICE_LOOKBACK_S back to 1 s ahead (the server's estimate of the robot's progress may lead this one)
        half = 0.5 * (SPLICE_LOOKBACK_S + 1.0)
        off = float(ref_path.path_distances(X, tau + ref_offset + ts + 1.0 - half, max(w, half)).max())
        if off > SPLICE_TOL_M:
            return None, f"its first {ts[-1]:.1f} s lie {off:.3f} m from it (splice tolerance {SPLICE_TOL_M:g} m)", None
        at = ad.splice_progress(ref_path, tau + ref_offset, t, P, SPLICE_LOOKBACK_S, SPLICE_TOL_M)
        d = cur.deviation(q, tau, w)[0] if cur is not None else ref_path.deviation(q, tau + ref_offset, w)[0]
        return d, "", at

    def _send(self, c: ad.ControllerConfig, t, P, V, start_at: float, now: float) -> None:
        cmd = ad.controller_command(c, self.names, t, P, V, now=now, start_at=start_at)
        self._send_command(c, cmd)

    def _send_command(self, c: ad.ControllerConfig, cmd: ad.Command) -> None:
        if c.interface == "topic":
            self._pubs[c.name].publish(ad.to_joint_trajectory(cmd))
        else:
            cl = self._clients[c.name]
            if not cl.server_is_ready():
                self._controller_failed(c.name, f"action server {c.action} not available")
                return
            goal = ad.fill_goal(self._fjt.Goal(), ad.action_goal_fields(cmd, c.goal_time_tolerance_s))
            self._dispatch(c, cl, goal)
            return
        self.counts["goals_sent"] += 1

    def _goal_response(self, name: str, fut, seq: int) -> None:
        try:
            gh = fut.result()
        except Exception as exc:
            self.status(f"{name}: goal failed: {exc}", "warning")
            return
        if not gh.accepted:
            self.counts["goals_rejected"] += 1
            if seq == self._goal_seq.get(name):
                self._controller_failed(name, "goal rejected by the controller")
            return
        with self._lock:
            self._goal_handles[name] = gh
        gh.get_result_async().add_done_callback(lambda f: self._goal_result(name, f, seq))

    def _goal_result(self, name: str, fut, seq: int) -> None:
        """The controller's verdict on a goal: an abort of the newest goal (a tolerance violated, a runstop, a goal
        the driver could not start) stops the robot and asks for a new plan; aborts of goals that a newer one
        replaced are the controllers' way of preempting and say nothing."""
        from action_msgs.msg import GoalStatus

        try:
            r = fut.result()
        except Exception as exc:
            self.status(f"{name}: no result: {exc}", "warning")
            return
        if r is None or seq != self._goal_seq.get(name):
            return
        code, text = int(getattr(r.result, "error_code", 0)), str(getattr(r.result, "error_string", ""))
        if r.status == GoalStatus.STATUS_ABORTED or code != 0:
            self._controller_failed(name, f"goal aborted (error_code {code}{': ' + text if text else ''})")

    def _controller_failed(self, name: str, why: str) -> None:
        self.counts["goals_failed"] += 1
        self.last_controller_error = f"{name}: {why}"
        if not self.active:
            return
        self.stop(f"{name}: {why}")
        if self.follower is not None:
            self._replan_at_rest = why
        else:
            self._request_replan(why)

    def _refuse(self, why: str) -> bool:
        self.counts["refused"] += 1
        self.last_refusal = why
        self.stop(f"trajectory refused: {why}")
        if self.follower is not None:  # a base: asked for once it rests (_ask_when_at_rest)
            self._replan_at_rest = why
        else:
            self._request_replan(why)
        return False

    def _request_replan(self, why: str) -> bool:
        """Ask the roadmap server for a plan; False when the request interval or a missing server held it back."""
        from std_srvs.srv import Trigger

        if not self.p["replan_on_refusal"]:
            return True
        now = time.monotonic()
        if now - self._last_replan_request < self.p["replan_request_interval_s"] or not self.cli_plan.service_is_ready():
            return False
        self._last_replan_request = now
        fut = self.cli_plan.call_async(Trigger.Request())
        fut.add_done_callback(_retrieve)
        return True

    def stop(self, why: str) -> None:
        """Stop every interface: zero twist, a hold at the measured configuration on every topic controller, cancel
        every active action goal."""
        if self.cfg is None:
            return
        q, _ = self.measured() if self.tracker is not None else (None, "")
        now = self._now()
        self._held = None
        with self._lock:
            self._pending.clear()
            self.checked = self._splice_ref = None
            if self.follower is not None:
                self.follower.stop()
            self._publish_twist(0.0, 0.0)
            for c in self.cfg.controllers:
                if c.interface == "topic":
                    if q is None and self.tracker is not None:
                        q = self.tracker.q  # the last measured joints: hold there
                    if q is not None:
                        self._pubs[c.name].publish(ad.to_joint_trajectory(ad.hold_command(c, self.names, q)))
                        self._gates[c.name].offer(None, now, urgent=True)
                else:
                    self._goal_seq[c.name] = self._goal_seq.get(c.name, 0) + 1  # what ends now is no failure
                    gh = self._goal_handles.pop(c.name, None)
                    if gh is not None:
                        gh.cancel_goal_async()
        d = self.cfg.driver
        if d.kind == "stretch" and self._driver_clients:
            # the driver's own stop; a trajectory-mode goal ignores cancels, and re-entering trajectory mode drops
            # the waypoint trajectories under way
            self._call_driver(d.stop_service)
            if d.mode == "trajectory" and self.driver_mode == "trajectory":
                self._call_driver(d.switch_name("trajectory"))
        self.counts["stops"] += 1
        self.status(f"robot stopped: {why}", "warning")

    def _publish_twist(self, v: float, w: float) -> None:
        if self._twist_pub is None:
            return
        from geometry_msgs.msg import Twist, TwistStamped

        if self.cfg.base.stamped:
            m = TwistStamped()
            m.header.stamp = self.node.get_clock().now().to_msg()
            m.header.frame_id = self.cfg.base.frame_id
            tw = m.twist
        else:
            m = tw = Twist()
        tw.linear.x, tw.angular.z = float(v), float(w)
        self._twist_pub.publish(m)
        self.counts["twists"] += 1

    def _tick(self) -> None:
        """Follower step (and goals released by their interval) at the base rate."""
        if not self.active or self.cfg is None:
            return
        now = self._now()
        with self._lock:
            due = []
            for c in self.cfg.controllers:
                item = self._gates[c.name].due(now) if c.name in self._pending else None
                if item is not None:
                    self._pending.pop(c.name, None)
                    due.append((c, item))
        for c, item in due:
            if self.cfg.base.mode == "stretch_trajectory":
                self._send_trajectory_mode(c, *item, now=now)
            else:
                with self._lock:
                    self._send(c, *item, now=now)
        if self.follower is None:
            return
        following = not self.follower.done
        dt, self._last_tick = (0.0 if self._last_tick is None else now - self._last_tick), now
        if following and self.speed_scaling < 1.0 and 0.0 < dt < 1.0:
            # the path clock runs at the controllers' speed scaling: the base stays in step with a slowed arm
            with self._lock:
                self.follower.t0 += dt * (1.0 - self.speed_scaling)
        self.follower.rate = self.speed_scaling
        late = self._grace.step()
        q, why = self.measured()
        if q is None:
            self.last_state_problem = why
            # a late step (this process stalled) may find the state messages still queued: decide at the next step,
            # after they are taken; a second stale step in a row stops
            if following and self._grace.forgive(late):
                return
            if following:
                self.stop(why)
            return
        self._grace.clear()
        self.last_state_problem = ""
        if self._held is not None:
            self._release_held(now)
        if self._replan_at_rest:
            self._ask_when_at_rest(now)
        with self._lock:
            v, w = self.follower.command(now, q[:3])
            if following:
                e = self.follower.error
                self.max_tracking_error = np.maximum(self.max_tracking_error, [np.hypot(e[0], e[1]), abs(e[2])])
            if following or self._zero_sent < 3:  # after the end: a few zero twists, then quiet
                self._publish_twist(v, w)
                self._zero_sent = 0 if following else self._zero_sent + 1
            checked, t0 = self.checked, self.follower.t0
        if following and checked is not None:
            self._check_path(checked, q, now - t0)

    def _ask_when_at_rest(self, now: float) -> None:
        """Ask for the pending replan once the measured base velocity has stayed near zero for ``REST_S`` (or
        ``REST_WAIT_S`` after the stop, for a base that does not settle); a request the interval holds back is
        tried again at the next step."""
        with self._lock:
            v, w = (abs(float(x)) for x in self.tracker.base_velocity)
        if self._stop_t is None:
            self._stop_t = now
        if v < REST_MPS and w < REST_RADPS:
            self._still_since = now if self._still_since is None else self._still_since
        else:
            self._still_since = None
        if (self._still_since is not None and now - self._still_since >= REST_S) or now - self._stop_t >= REST_WAIT_S:
            if self._request_replan(self._replan_at_rest):
                self._replan_at_rest, self._stop_t, self._still_since = "", None, None

    def _check_path(self, checked: CheckedPath, q: np.ndarray, tau: float) -> None:
        """The path tolerance: the measured configuration against the trajectory's configurations near ``tau``
        (:meth:`psprm_core.tracking.CheckedPath.deviation`); beyond ``path_tolerance_m`` the robot stops and a new
        plan is asked for, from where it is."""
        tol = self.p["path_tolerance_m"]
        try:
            d, _ = checked.deviation(q, tau, self.p["path_window_s"])
        except Exception as exc:  # never lose the control loop to the check; a check that fails stops the robot
            self.stop(f"path check failed: {exc}")
            return
        self.path_deviation = d
        self.max_path_deviation = max(self.max_path_deviation, d)
        if tol > 0 and d > tol:
            self.counts["off_path_stops"] += 1
            why = f"off the checked path: {d:.3f} m from the trajectory's configurations (path tolerance {tol:g} m)"
            self.stop(why)
            self._replan_at_rest = why

    def destroy(self) -> None:
        try:
            if self.active:
                self.stop("node destroyed")
                self.wait_stop_delivered()
        except Exception:
            pass
        self.node.destroy_node()

    def wait_stop_delivered(self, timeout_s: float = 1.0) -> bool:
        """Wait (at most ``timeout_s``) until the subscribers acknowledged what the command publishers sent: a stop
        published just before the process ends is otherwise still in the middleware's queue and lost with it."""
        from rclpy.duration import Duration

        pubs = list(self._pubs.values()) + ([self._twist_pub] if self._twist_pub is not None else [])
        deadline = time.monotonic() + timeout_s
        ok = True
        for pub in pubs:
            left = max(0.0, deadline - time.monotonic())
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        return ok


def _retrieve(fut) -> None:
    """Take a finished service call's result or exception (an unanswered call is cut off at shutdown)."""
    try:
        fut.result()
    except Exception:
        pass


class _Velocities:
    """A JointTrajectory view whose point positions are the velocities (for reordering them by name)."""

    def __init__(self, msg):
        self.joint_names = msg.joint_names
        self.points = [_VP(p.velocities) for p in msg.points]


class _VP:
    def __init__(self, v):
        self.positions = v


def main(args=None) -> int:
    from .runner import run_nodes

    return run_nodes([RobotAdapter], args, description=__doc__, prog="robot_adapter")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
