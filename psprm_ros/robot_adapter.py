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

The node converts the messages and owns the ROS objects. Whether and how a trajectory runs is decided by
:mod:`psprm_ros.robots.acceptance`; the execution state, stops and the control step are
:mod:`psprm_ros.robots.execution`'s; :mod:`psprm_ros.interfaces.controllers` holds the controllers' publishers and
action clients and the Stretch driver's services.
"""

from __future__ import annotations

import threading
import time
from typing import Optional

import numpy as np

from psprm_core.errors import InputError

from . import core
from .interfaces import conversions as cv
from .interfaces.controllers import ControllerLinks, DriverLink, retrieve
from .interfaces.frames import declare_frame_params
from .interfaces.tf_tree import TfTree, subscribe_tf
from .robots import adapters as ad
from .robots.acceptance import (REST_MPS, REST_RADPS, REST_S, REST_WAIT_S, SPLICE_CHECK_S, SPLICE_LOOKBACK_S,
                                SPLICE_TOL_M)
from .robots.base_follower import BaseFollower, Gains, Limits
from .robots.execution import Execution
from .robots.inbox import TrajectoryInbox
from .robots.robot_state import RobotStateTracker, offset_from_params
from .runner import run_nodes

__all__ = ["ADAPTER_PARAMS", "RobotAdapter", "main", "REST_MPS", "REST_RADPS", "REST_S", "REST_WAIT_S",
           "SPLICE_CHECK_S", "SPLICE_LOOKBACK_S", "SPLICE_TOL_M"]

P = core.Param
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


class RobotAdapter(core.ConfiguredRobot):
    """The ``robot_adapter`` lifecycle node: parameters, subscriptions, publishers, clients and timers. What becomes
    of each trajectory and what happens at every control step is :class:`psprm_ros.robots.execution.Execution`'s;
    the node is its port (clock, measured state, replan requests, driver services, status)."""

    def __init__(self, node_name: str = "robot_adapter", **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from diagnostic_msgs.msg import DiagnosticArray
        from std_msgs.msg import String

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        self.spec = {**core.common_params(), **ADAPTER_PARAMS}
        self.p = core.declare_reconfigurable_params(node, self.spec, self._apply_param)
        try:
            declare_frame_params(node, "")  # the parameters only: the frame table is made at configure
        except Exception:  # a malformed transform: configure reports it
            pass
        self.active = False
        # made at configure, dropped at cleanup
        self.scene = None
        self._robot = None
        self.frame: Optional[str] = None
        self.frames = None
        self.names: list = []
        self.execution: Optional[Execution] = None
        self.cfg: Optional[ad.AdapterConfig] = None
        self.links: Optional[ControllerLinks] = None
        self.driver_link: Optional[DriverLink] = None
        self.tracker = None
        self.tf_tree = None  # base_pose_source tf: the links received, kept for the tracker made at configure
        self.follower: Optional[BaseFollower] = None
        self._made = core.ConfigureScope(node)  # what configure makes, released by cleanup
        self._lock = threading.RLock()
        # trajectories are checked on their own thread (see _traj_cb), which lives from configure to cleanup
        self._inbox = TrajectoryInbox(self._accept, self.stop, self._wait_accepted)
        self._last_replan_request = -1e9
        self.counts = {"trajectories": 0, "executed": 0, "refused": 0, "stops": 0, "goals_sent": 0, "spliced": 0,
                       "goals_deferred": 0, "twists": 0, "off_path_stops": 0, "goals_rejected": 0, "goals_failed": 0,
                       "runstops": 0, "mode_switches": 0, "held_until_rest": 0}
        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_diag = node.create_publisher(DiagnosticArray, core.DIAGNOSTICS_TOPIC, 10)
        self.cb = MutuallyExclusiveCallbackGroup()
        self.cli_plan = None
        node.create_timer(self.p["diagnostics_period_s"], self._diagnostics,
                          callback_group=MutuallyExclusiveCallbackGroup())

    @property
    def speed_scaling(self) -> float:
        """The controllers' speed scaling (0..1), which the base's path clock follows (1 while unconfigured)."""
        return 1.0 if self.execution is None else self.execution.speed_scaling

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        """Read the parameters, load the scene, robot model and adapter config, make the subscriptions, controller
        links, the driver's services, the control timer and the acceptance thread. A bad parameter or a missing file
        raises: the configure fails with the reason on ``~/status``, the node stays unconfigured with nothing made,
        and can be configured again."""
        return self._made.configure(self._configure, self._release)

    def _configure(self) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger
        from trajectory_msgs.msg import JointTrajectory

        node, p = self.node, self.p
        scene, robot = core.load_configured_scene_and_robot(node, dict(p))
        frames = declare_frame_params(node, scene.frame)
        cfg = ad.load_adapter(p["adapter"] or robot.name, robot)
        if p["interface"]:
            cfg = cfg.with_interface(p["interface"])
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
        src = p["base_pose_source"]
        if robot.mobile and src == "pose" and not p["robot_pose_topic"]:
            raise InputError("base_pose_source 'pose' needs robot_pose_topic (the mocap body on the base)")
        tf_tree = None
        if robot.mobile and src == "tf":
            tf_tree = TfTree()
        tracker = RobotStateTracker(
            robot, frames, src, cfg.name_map(),
            offset_from_params(p["base_body_offset.xyz"], p["base_body_offset.quat"]),
            p["state_timeout_s"], template=core.start_configuration(robot, scene, p["start_problem"]),
            base_frame=p["base_frame"], tf=tf_tree)
        with self._lock:
            self.scene, self._robot, self.frame, self.frames = scene, robot, scene.frame, frames
            self.names = list(robot.joint_names)
            self.tf_tree, self.tracker = tf_tree, tracker
            self.execution = Execution(self, robot, self.names, p, self.counts, self._lock)
        cb = self.cb
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._made.subscription(JointTrajectory, p["trajectory_topic"], self._traj_cb, latched, callback_group=cb)
        self._made.subscription(JointState, p["joint_states_topic"], self._joints_cb, 10, callback_group=cb)
        if robot.mobile and src == "odom":
            self._made.subscription(Odometry, p["odom_topic"], self._odom_cb, 10, callback_group=cb)
        if robot.mobile and src == "pose":
            self._made.subscription(PoseStamped, p["robot_pose_topic"], self._pose_cb, qos_profile_sensor_data,
                                    callback_group=cb)
        if tf_tree is not None:
            self._made.own(subscribe_tf(node, self._tf_cb, cb))
        self.cli_plan = node.create_client(Trigger, p["plan_service"], callback_group=MutuallyExclusiveCallbackGroup())
        self.links = ControllerLinks(node, cfg, robot.mobile, fjt, cb, self._lock, self.counts,
                                     self.execution.controller_failed, self.status)
        b = cfg.base
        if cfg.driver.kind == "stretch":
            self.driver_link = DriverLink(node, cfg.driver, self._mode_cb, self._runstop_cb, cb, self.status)
        scaling = sorted({c.speed_scaling_topic for c in cfg.controllers if c.speed_scaling_topic})
        if len(scaling) > 1:
            raise InputError(f"controllers name different speed scaling topics {scaling}: one robot, one scaling")
        if scaling:
            from std_msgs.msg import Float64

            self._made.subscription(Float64, scaling[0], self._scaling_cb, 10, callback_group=cb)
        follower = None
        if robot.mobile:
            # in trajectory mode the driver moves the base; the follower then only keeps the path's clock (t0, done)
            follower = BaseFollower(Limits.for_robot(robot, b), Gains(b.k_x, b.k_y, b.k_theta),
                                    b.goal_tolerance_m, b.goal_tolerance_rad, b.settle_s, b.preview_s)
        self.execution.configure(cfg, self.links, follower)
        self.cfg, self.follower = cfg, follower
        # the follower runs on its own callback group: a burst of state messages never delays a control step
        self._made.timer(1.0 / b.rate_hz, self.execution.tick, callback_group=MutuallyExclusiveCallbackGroup())
        self._inbox.start(f"{node.get_name()}-accept")
        self.status(f"configured: scene {scene.name}, robot {robot.name}; adapter {cfg.robot} ({len(cfg.controllers)} "
                    f"controllers: {', '.join(f'{c.name} [{c.interface}]' for c in cfg.controllers)}; "
                    f"base {b.mode} on {b.topic})")

    def _release(self) -> None:
        """End the acceptance thread; destroy the subscriptions, timers, controller links, driver services and the plan
        client configure made; drop the models."""
        self._inbox.end()
        self._made.release()
        with self._lock:
            if self.links is not None:
                self.links.destroy()
            if self.driver_link is not None:
                self.driver_link.destroy()
            if self.cli_plan is not None:
                self.node.destroy_client(self.cli_plan)
            if self.execution is not None:
                self.execution.cleanup()
            self.cfg = self.follower = self.links = self.driver_link = self.cli_plan = None
            self.scene = self._robot = self.frame = self.frames = self.tracker = self.tf_tree = None
            self.execution, self.names = None, []

    def on_activate(self, state) -> bool:
        self.active = True
        self.status("active: executing trajectories")
        missing = self.missing_controllers()
        if missing:  # reported before anything is sent; trajectories are refused while it lasts
            self.status("; ".join(missing), "warning")
        self.execution.activate()
        return True

    def on_deactivate(self, state) -> bool:
        self.active = False  # the acceptance thread takes nothing more
        self._inbox.quiesce()
        self.stop("adapter deactivated")
        self.execution.restore_driver_mode()
        self.active = False
        return True

    def on_cleanup(self, state) -> bool:
        self._release()
        self.status("unconfigured: subscriptions, controller links and models released")
        return True

    def on_shutdown(self, state) -> bool:
        was_active, self.active = self.active, False
        if was_active:
            self._inbox.quiesce()
        if self.cfg is not None:
            self.stop("shutting down")
            self.execution.restore_driver_mode()
        self.active = False
        return True

    # ------------------------------------------------------------------------------------------------ the port
    def missing_controllers(self) -> list:
        """What cannot take a command now: a JointTrajectory topic no controller subscribes to, an action server
        that is not there, the base's cmd_vel without a subscriber."""
        return [] if self.cfg is None else self.links.missing()

    def driver_ready(self) -> tuple:
        """(ready, why not): the driver reports the configured mode and no runstop."""
        return self.execution.driver_ready()

    def measured(self) -> tuple:
        """(q, why): the measured configuration (None and the reason when a state is stale or missing)."""
        with self._lock:
            return self.tracker.state(self._now())

    def base_velocity(self) -> np.ndarray:
        """The measured base velocity (v, omega)."""
        with self._lock:
            return self.tracker.base_velocity.copy()

    def last_joints(self):
        """The last measured configuration, stale or not."""
        return self.tracker.q

    def now(self) -> float:
        """The node's clock (s)."""
        return self._now()

    def stop(self, why: str) -> None:
        """Stop every interface: zero twist, a hold at the measured configuration on every topic controller, cancel
        every active action goal."""
        self.execution.stop(why)

    def request_replan(self, why: str) -> bool:
        """Ask the roadmap server for a plan; False when the request interval or a missing server held it back."""
        from std_srvs.srv import Trigger

        if not self.p["replan_on_refusal"]:
            return True
        now = time.monotonic()
        interval = self.p["replan_request_interval_s"]
        if now - self._last_replan_request < interval or self.cli_plan is None or not self.cli_plan.service_is_ready():
            return False
        self._last_replan_request = now
        fut = self.cli_plan.call_async(Trigger.Request())
        fut.add_done_callback(retrieve)
        return True

    def call_driver(self, name: str):
        """Call the driver's Trigger service ``name``: its future, or None (reported) when it is not available."""
        if self.driver_link is None:
            self.status(f"driver service {name} not available", "error")
            return None
        return self.driver_link.call(name)

    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    # ------------------------------------------------------------------------------------------------ reporting
    def _apply_param(self, name: str, value) -> None:
        if name == "state_timeout_s" and self.tracker is not None:
            self.tracker.timeout_s = float(value)

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _diagnostics(self) -> None:
        ex = self.execution
        if self.cfg is None or ex is None:
            level, msg = core.DIAG_WARN, "not configured"
            vals = {"lifecycle": core.lifecycle_state(self.node), **self.counts}
            name = f"psprm: {self.node.get_fully_qualified_name()}"
            core.publish_diagnostics(self.pub_diag, self.node, [
                core.diagnostic_status(name, self.p["robot"] or self.p["scene"], level, msg, vals)])
            return
        if ex.last_state_problem:
            level, msg = core.DIAG_WARN, ex.last_state_problem
        elif ex.last_refusal:
            level, msg = core.DIAG_WARN, f"last refusal: {ex.last_refusal}"
        else:
            level, msg = core.DIAG_OK, "following" if self.follower and not self.follower.done else "idle"
        vals = {"lifecycle": core.lifecycle_state(self.node), **self.counts,
                "max_tracking_error_m": float(ex.max_tracking_error[0]),
                "max_tracking_error_rad": float(ex.max_tracking_error[1]),
                "path_deviation_m": float(ex.path_deviation), "max_path_deviation_m": float(ex.max_path_deviation),
                "accept_ms_max": round(float(ex.accept_ms_max), 1),
                "control_gap_ms_max": round(float(ex.control_gap_ms_max), 1)}
        name = f"psprm: {self.node.get_fully_qualified_name()}"
        core.publish_diagnostics(self.pub_diag, self.node,
                                 [core.diagnostic_status(name, self._robot.name, level, msg, vals)])

    # ------------------------------------------------------------------------------------------------ inputs
    def _mode_cb(self, msg) -> None:
        if self.execution is not None:
            self.execution.on_mode(str(msg.data))

    def _runstop_cb(self, msg) -> None:
        if self.execution is not None:
            self.execution.on_runstop(bool(msg.data))

    def _scaling_cb(self, msg) -> None:
        """UR's speed scaling in percent: the scaled controllers run their trajectories at that rate."""
        v = float(msg.data)
        if not np.isfinite(v) or v < 0.0:
            self.status(f"ignored speed scaling {v}", "warning")
            return
        if self.execution is not None:
            self.execution.speed_scaling = min(v / 100.0, 1.0)

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
            if self.tracker is None:  # released by a cleanup
                return
            dropped = self.tracker.update_tf(msg, static, self._now())
        for text in dropped:
            self.status(f"ignored {text}", "warning")

    def _traj_cb(self, msg) -> None:
        """A trajectory goes to the acceptance thread, in arrival order: its check (tens of ms, more on a busy
        machine) must not hold up the control steps, which run on this node's executor, while the base is following
        the trajectory under way."""
        self.counts["trajectories"] += 1
        if not self.active or self.cfg is None:  # an inactive adapter drives nothing (activation asks for a new plan)
            return
        self._inbox.put(msg)

    def _accept(self, msg) -> None:
        if self.active and self.cfg is not None:
            self.execute(msg)

    def _wait_accepted(self, timeout: float) -> None:
        if self.execution is not None:
            self.execution.wait_accepted(timeout)

    def execute(self, msg) -> bool:
        """Check a planned trajectory against the measured state and send it to the controllers and the base
        (:meth:`psprm_ros.robots.execution.Execution.execute`)."""
        P = cv.joint_trajectory_positions(msg, self.names)
        t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
        return self.execution.execute(t, P, lambda: cv.joint_trajectory_velocities(msg, self.names))

    def destroy(self) -> None:
        was_active, self.active = self.active, False  # the acceptance thread takes nothing more
        self._inbox.end()
        try:
            if was_active:
                self.stop("node destroyed")
                self.wait_stop_delivered()
        except Exception:
            pass
        self.node.destroy_node()

    def wait_stop_delivered(self, timeout_s: float = 1.0) -> bool:
        """Wait (at most ``timeout_s``) until the subscribers acknowledged what the command publishers sent: a stop
        published just before the process ends is otherwise still in the middleware's queue and lost with it."""
        return True if self.links is None else self.links.wait_acked(timeout_s)


def main(args=None) -> int:
    return run_nodes([RobotAdapter], args, description=__doc__, prog="robot_adapter")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
