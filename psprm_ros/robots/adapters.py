"""Execution adapters: what a robot's controllers take, built from a planned trajectory of the planning joints.

A planned trajectory (``/psprm/trajectory``) holds the virtual base joints ``base_x, base_y, base_theta`` (scene
frame) and every planning joint on one message. Real controllers each own a few joints under their own names and
enforce rules. An adapter config (``config/ros/adapters/<robot>.yaml``) says, per controller, which planning joints it
owns, how they are named on the robot (``name_map``, ``prefix``), and how it is reached:

* ``interface: topic`` -- a ``trajectory_msgs/JointTrajectory`` topic (ros2_control's joint_trajectory_controller,
  UR's scaled JTC): the exact joint set it owns (``allow_partial_joints_goal`` false), ``header.stamp`` 0 (start now)
  or now + a lead time;
* ``interface: action`` -- a ``control_msgs/FollowJointTrajectory`` action client (Stretch's driver; every JTC offers
  it too). control_msgs is not on PyPI: the node imports it only when the action interface is used; the goal's
  fields are built here (:func:`action_goal_fields`) and filled into the real goal by :func:`fill_goal`.

and the base, either a closed-loop follower publishing ``geometry_msgs/Twist`` or ``TwistStamped`` on a cmd_vel
topic (:mod:`psprm_ros.robots.base_follower`), or Stretch's position-mode goals (``translate_mobile_base`` /
``rotate_mobile_base``, one per goal: :func:`stretch_base_steps`).

Rules every command obeys (:func:`controller_command`): only the controller's joints, all of them; times strictly
increasing and the first point reached ``lead_time_s`` after sending (so the controller blends from where the robot
is instead of jumping); at most one goal per ``min_goal_interval_s`` (:class:`GoalGate`); the first point within
``start_tolerance`` of the measured state (:func:`check_start`, else the trajectory is refused and a replan
requested, as MoveIt validates a trajectory's start). A stop (:func:`hold_command`) is a one-point trajectory at the
measured configuration with a positive ``time_from_start`` and stamp 0, which every JTC accepts; the base stops with a
zero twist, an action goal is cancelled.

The commands are built in :mod:`psprm_ros.robots.commands` (importable from here as well). No ROS import at module
level; the message builders import the message packages inside.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict

from psprm_core.errors import ConfigError, InputError, UnknownNameError
from psprm_core.yamlio import Fields, load_yaml

# the commands of a controller, with the config they are made for (importable from here)
from .commands import (BASE_JOINTS, Command, GoalGate, action_goal_fields, base_columns,  # noqa: F401
                       braking_configurations, check_base_start, check_start, columns, controller_command, fill_goal,
                       hold_command, import_follow_joint_trajectory, join_along, progress_offset, sample_at,
                       splice_progress, stretch_base_command, stretch_base_steps, to_joint_trajectory, trim_from)

INTERFACES = ("topic", "action")
STAMP_MODES = ("zero", "lead")
BASE_MODES = ("cmd_vel", "stretch_trajectory", "stretch_translate_rotate", "none")
DRIVER_KINDS = ("none", "stretch")
STRETCH_MODES = ("trajectory", "navigation")


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """One controller of the robot (fields as in the adapter YAML)."""

    name: str
    joints: tuple  # planning joint names this controller owns (config order = message order)
    interface: str = "topic"
    topic: str = ""  # JointTrajectory topic (interface topic; also what sim_robot subscribes to)
    action: str = ""  # FollowJointTrajectory action (interface action)
    name_map: tuple = ()  # ((planning name, robot name), ...)
    prefix: str = ""  # prepended to every robot joint name (ur_robot_driver's tf_prefix, multi-robot set-ups)
    stamp: str = "lead"  # zero: header.stamp 0 ("start now"); lead: header.stamp = now + lead_time_s
    lead_time_s: float = 0.1  # the first point is reached this long after sending
    min_goal_interval_s: float = 0.0  # at most one goal per interval (Stretch: 0.2 s, i.e. 5 goals/s)
    start_tolerance: float = 0.15  # max |first point - measured| over the controller's joints (rad or m)
    hold_time_s: float = 0.25  # time_from_start of the stop (hold) point
    goal_time_tolerance_s: float = 1.0  # FollowJointTrajectory goal_time_tolerance
    # a controller that slows its trajectories by a speed scaling (UR's scaled_joint_trajectory_controller): the
    # std_msgs/Float64 (percent) the driver publishes; the base then follows its path at the same rate
    speed_scaling_topic: str = ""

    def robot_name(self, planning_name: str) -> str:
        return self.prefix + dict(self.name_map).get(planning_name, planning_name)

    @property
    def robot_joints(self) -> list:
        return [self.robot_name(j) for j in self.joints]


@dataclasses.dataclass(frozen=True)
class BaseConfig:
    """How the base is driven (``mode``) and the follower's settings."""

    mode: str = "cmd_vel"
    topic: str = "cmd_vel"
    stamped: bool = False  # geometry_msgs/TwistStamped (Jazzy's diff_drive_controller) instead of Twist
    frame_id: str = "base_link"  # header.frame_id of a TwistStamped
    rate_hz: float = 30.0  # follower rate (>= 20 Hz)
    k_x: float = 1.5  # along-track gain (1/s)
    k_y: float = 6.0  # cross-track gain (1/m^2, scaled by the reference speed)
    k_theta: float = 3.0  # heading gain (1/s)
    lead_time_s: float = 0.1  # as the controllers': the base path starts this long after sending
    start_tolerance_m: float = 0.15
    start_tolerance_rad: float = 0.3
    goal_tolerance_m: float = 0.02  # after the end of the path: stop once within these
    goal_tolerance_rad: float = 0.03
    settle_s: float = 2.0  # ... or this long after the end of the path
    preview_s: float = 0.1  # feed-forward velocities taken this far ahead (command -> wheel delay)
    linear_velocity: float = 0.0  # limits; 0 = the robot config's base limits
    angular_velocity: float = 0.0
    linear_acceleration: float = 0.0
    angular_acceleration: float = 0.0
    action: str = ""  # stretch_translate_rotate: the FollowJointTrajectory action taking the base joints
    min_step_m: float = 0.005  # stretch_translate_rotate: smaller increments are skipped
    min_step_rad: float = 0.01
    # stretch_trajectory: the base rides on the (single) action controller's goal as the multi-DOF joint 'position'
    min_waypoint_interval_s: float = 0.9  # waypoints at least this far apart (the driver refuses <= 0.8 s)
    max_goal_deviation_m: float = 0.02  # what the driver makes of the goal, this close to the planned trajectory


@dataclasses.dataclass(frozen=True)
class DriverConfig:
    """The robot's driver, when it has modes of its own (``kind: stretch``: stretch_ros2's stretch_driver).

    ``mode`` is the mode the adapter puts the driver in at activation (and leaves again at deactivation, back to the
    one it found); goals and cmd_vel wait until ``mode_topic`` reports it. The stop calls ``stop_service`` (and, in
    trajectory mode, re-enters trajectory mode, which drops the waypoint trajectories under way); a runstop reported
    on ``runstop_topic`` stops everything until it is released."""

    kind: str = "none"
    mode: str = ""
    mode_topic: str = "/mode"
    runstop_topic: str = "/is_runstopped"
    switch_service: str = "/switch_to_{mode}_mode"
    stop_service: str = "/stop_the_robot"
    mode_timeout_s: float = 5.0  # the driver must report the mode this long after the switch

    def switch_name(self, mode: str) -> str:
        return self.switch_service.replace("{mode}", mode)


@dataclasses.dataclass(frozen=True)
class AdapterConfig:
    robot: str
    source: str
    controllers: tuple  # ControllerConfig
    base: BaseConfig
    description: str = ""
    driver: DriverConfig = DriverConfig()

    def controller(self, name: str) -> ControllerConfig:
        for c in self.controllers:
            if c.name == name:
                return c
        raise UnknownNameError(f"adapter {self.source}: no controller '{name}' "
                               f"(have {[c.name for c in self.controllers]})")

    def name_map(self) -> dict:
        """Robot joint name -> planning joint name over every controller (for reading /joint_states)."""
        out = {}
        for c in self.controllers:
            for j in c.joints:
                r = c.robot_name(j)
                if r != j:
                    out[r] = j
        return out

    def with_interface(self, interface: str) -> "AdapterConfig":
        """The same adapter with every controller on ``interface`` (e.g. ``topic`` for sim_robot, which offers
        the JTC topics: control_msgs is not installed here)."""
        if interface not in INTERFACES:
            raise InputError(f"interface must be one of {', '.join(INTERFACES)}, got '{interface}'")
        cs = []
        for c in self.controllers:
            if interface == "topic" and not c.topic:
                raise InputError(f"adapter {self.source}: controller '{c.name}' has no topic")
            if interface == "action" and not c.action:
                raise InputError(f"adapter {self.source}: controller '{c.name}' has no action")
            cs.append(dataclasses.replace(c, interface=interface))
        base, driver = self.base, self.driver
        if interface == "topic" and base.mode in ("stretch_translate_rotate", "stretch_trajectory"):
            base = dataclasses.replace(base, mode="cmd_vel")
        if interface == "topic":
            driver = DriverConfig()  # the JointTrajectory topics of a ros2_control robot: no driver modes
        return dataclasses.replace(self, controllers=tuple(cs), base=base, driver=driver)


# ---------------------------------------------------------------------------------------------------------- loading
def adapter_dirs() -> list:
    """Where adapter configs are looked up by name: the installed package's share/ (colcon), then the repository."""
    dirs = []
    try:
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("psprm_ros")) / "config" / "adapters")
    except Exception:  # not installed with colcon, or ament_index not importable
        pass
    dirs.append(Path(__file__).resolve().parents[2] / "config" / "ros" / "adapters")
    return dirs


def resolve_adapter(name_or_path: str) -> Path:
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml"):
        if not p.is_file():
            raise ConfigError(str(p), "", "adapter file not found")
        return p
    for d in adapter_dirs():
        if (d / f"{name_or_path}.yaml").is_file():
            return d / f"{name_or_path}.yaml"
    known = sorted({x.stem for d in adapter_dirs() if d.is_dir() for x in d.glob("*.yaml")})
    raise ConfigError(str(adapter_dirs()[-1] / f"{name_or_path}.yaml"), "",
                      f"unknown adapter '{name_or_path}' (known: {', '.join(known) or 'none'})")


_CTRL_KEYS = [f.name for f in dataclasses.fields(ControllerConfig)]
_BASE_KEYS = [f.name for f in dataclasses.fields(BaseConfig)]


def load_adapter(name_or_path: str, robot=None) -> AdapterConfig:
    """Load and check an adapter config; with ``robot`` (a RobotModel) every non-base planning joint must belong to
    exactly one controller. Errors are :class:`psprm_core.errors.ConfigError` naming the file and the field."""
    path = resolve_adapter(name_or_path)
    src = str(path)
    f = Fields(load_yaml(path), src)
    f.check_keys(["robot", "description", "controllers", "base", "driver"])
    ctrls = []
    for i, c in enumerate(f.sub_list("controllers")):
        c.check_keys(_CTRL_KEYS)
        joints = c.raw("joints")
        if not isinstance(joints, list) or not joints or not all(isinstance(j, str) for j in joints):
            raise c.error("joints", "must be a non-empty list of planning joint names")
        nm = c.raw("name_map", {})
        if not isinstance(nm, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in nm.items()):
            raise c.error("name_map", "must map planning joint names to robot joint names")
        for k in nm:
            if k not in joints:
                raise c.error("name_map", f"'{k}' is not one of this controller's joints {joints}")
        interface = c.str("interface", "topic")
        if interface not in INTERFACES:
            raise c.error("interface", f"must be one of {', '.join(INTERFACES)}")
        stamp = c.str("stamp", "lead")
        if stamp not in STAMP_MODES:
            raise c.error("stamp", f"must be one of {', '.join(STAMP_MODES)}")
        cc = ControllerConfig(
            name=c.str("name"), joints=tuple(joints), interface=interface, topic=c.str("topic", ""),
            action=c.str("action", ""), name_map=tuple(nm.items()), prefix=c.str("prefix", ""), stamp=stamp,
            lead_time_s=c.float("lead_time_s", 0.1, lo=0.0), min_goal_interval_s=c.float("min_goal_interval_s", 0.0,
                                                                                            lo=0.0),
            start_tolerance=c.float("start_tolerance", 0.15, lo=0.0), hold_time_s=c.float("hold_time_s", 0.25, lo=1e-3),
            goal_time_tolerance_s=c.float("goal_time_tolerance_s", 1.0, lo=0.0),
            speed_scaling_topic=c.str("speed_scaling_topic", ""))
        if interface == "topic" and not cc.topic:
            raise c.error("topic", "required with interface: topic")
        if interface == "action" and not cc.action:
            raise c.error("action", "required with interface: action")
        if cc.stamp == "zero" and cc.lead_time_s <= 0:
            raise c.error("lead_time_s", "must be > 0 with stamp: zero (the first point must lie in the future)")
        ctrls.append(cc)
    names = [c.name for c in ctrls]
    if len(set(names)) != len(names):
        raise f.error("controllers", f"controller names must be unique, got {names}")
    b = f.sub("base") if f.has("base") else Fields({}, src, "base")
    b.check_keys(_BASE_KEYS)
    kw = {}
    for k in _BASE_KEYS:
        if not b.has(k):
            continue
        default = getattr(BaseConfig, k)
        if isinstance(default, bool):
            kw[k] = b.bool(k)
        elif isinstance(default, float):
            kw[k] = b.float(k, lo=0.0)
        else:
            kw[k] = b.str(k)
    base = BaseConfig(**kw)
    if base.mode not in BASE_MODES:
        raise b.error("mode", f"must be one of {', '.join(BASE_MODES)}")
    if base.rate_hz < 20.0 and base.mode == "cmd_vel":
        raise b.error("rate_hz", f"the base follower runs at >= 20 Hz, got {base.rate_hz}")
    if base.mode == "stretch_translate_rotate" and not base.action:
        raise b.error("action", "required with mode: stretch_translate_rotate")
    driver = _load_driver(f, src)
    if base.mode == "stretch_trajectory":
        acts = [c for c in ctrls if c.interface == "action"]
        if len(ctrls) != 1 or not acts:
            raise b.error("mode", "stretch_trajectory needs exactly one controller, on interface: action (the "
                                  "driver's FollowJointTrajectory, which takes the base too)")
        if base.min_waypoint_interval_s <= 0.8:
            raise b.error("min_waypoint_interval_s", "must exceed 0.8 s (the driver refuses closer waypoints)")
        if driver.kind != "stretch" or driver.mode != "trajectory":
            raise b.error("mode", "stretch_trajectory needs driver: {kind: stretch, mode: trajectory}")
    if driver.kind == "stretch" and driver.mode == "navigation" and base.mode != "cmd_vel":
        raise b.error("mode", "in navigation mode the Stretch driver moves the base by cmd_vel only")
    cfg = AdapterConfig(robot=f.str("robot"), source=src, controllers=tuple(ctrls), base=base,
                        description=f.str("description", ""), driver=driver)
    if robot is not None:
        check_against_robot(cfg, robot)
    return cfg


def _load_driver(f, src: str) -> DriverConfig:
    if not f.has("driver"):
        return DriverConfig()
    d = f.sub("driver")
    keys = [x.name for x in dataclasses.fields(DriverConfig)]
    d.check_keys(keys)
    kind = d.str("kind", "none")
    if kind not in DRIVER_KINDS:
        raise d.error("kind", f"must be one of {', '.join(DRIVER_KINDS)}")
    kw = {"kind": kind}
    for k in keys[1:]:
        if d.has(k):
            kw[k] = d.float(k, lo=0.1) if k == "mode_timeout_s" else d.str(k)
    out = DriverConfig(**kw)
    if kind == "stretch" and out.mode not in STRETCH_MODES:
        raise d.error("mode", f"the Stretch adapter runs the driver in {' or '.join(STRETCH_MODES)} mode")
    if "{mode}" not in out.switch_service:
        raise d.error("switch_service", "must contain {mode} (e.g. /switch_to_{mode}_mode)")
    return out


def check_against_robot(cfg: AdapterConfig, robot) -> None:
    owned: Dict[str, str] = {}
    for c in cfg.controllers:
        for j in c.joints:
            if j in BASE_JOINTS:
                raise ConfigError(cfg.source, f"controllers.{c.name}.joints",
                                  f"'{j}' is a base joint: the base is driven by the 'base' section")
            if j not in robot.joint_names:
                raise ConfigError(cfg.source, f"controllers.{c.name}.joints",
                                  f"robot '{robot.name}' has no planning joint '{j}' "
                                  f"(joints: {', '.join(robot.joint_names)})")
            if j in owned:
                raise ConfigError(cfg.source, f"controllers.{c.name}.joints",
                                  f"'{j}' is already owned by controller '{owned[j]}'")
            owned[j] = c.name
    missing = [j for j in robot.joint_names[robot.base_dof:] if j not in owned]
    if missing:
        raise ConfigError(cfg.source, "controllers", f"no controller owns {', '.join(missing)}")
    if robot.mobile and cfg.base.mode == "none":
        raise ConfigError(cfg.source, "base.mode", f"robot '{robot.name}' has a mobile base: cmd_vel, "
                                                   "stretch_trajectory or stretch_translate_rotate")
