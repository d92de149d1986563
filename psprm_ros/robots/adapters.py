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

No ROS import at module level; the message builders import the message packages inside.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from psprm_core.errors import InputError, UnknownNameError

BASE_JOINTS = ("base_x", "base_y", "base_theta")
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
        raise UnknownNameError(f"adapter {self.source}: no controller '{name}' (have {[c.name for c in self.controllers]})")

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
    from psprm_core.errors import ConfigError

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
    from psprm_core.yamlio import Fields, load_yaml

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
    from psprm_core.errors import ConfigError

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


# ---------------------------------------------------------------------------------------------------------- commands
@dataclasses.dataclass
class Command:
    """One controller goal, message-independent: joint names (robot names), ``stamp`` (seconds; 0 = start now),
    point times (s from the stamp), positions and velocities (M, n)."""

    controller: str
    joint_names: list
    stamp: float
    times: np.ndarray
    positions: np.ndarray
    velocities: Optional[np.ndarray] = None


def columns(names: Sequence[str], wanted: Sequence[str]) -> list:
    idx = []
    for j in wanted:
        if j not in names:
            raise InputError(f"trajectory has no joint '{j}' (has {', '.join(names)})")
        idx.append(list(names).index(j))
    return idx


def controller_command(ctrl: ControllerConfig, names: Sequence[str], times, positions, velocities=None,
                       now: float = 0.0, start_at: Optional[float] = None) -> Command:
    """The goal for ``ctrl`` from a planned trajectory (``names`` = its planning joints, ``times`` from 0):
    the controller's joints only, under their robot names, the trajectory starting at ``start_at`` (the caller's
    clock; default ``now + lead_time_s``, so the first point lies in the future and the controller blends from
    where the robot is). ``stamp: lead`` gives stamp = start_at with the planned times; ``stamp: zero`` gives stamp 0
    with the times shifted by ``start_at - now``; a start already past (a goal held back by the goal interval)
    drops the part of the trajectory before ``now + lead_time_s``, its first point interpolated there."""
    t = np.asarray(times, float).reshape(-1)
    P = np.asarray(positions, float).reshape(len(t), -1)
    if len(t) == 0 or not np.isfinite(t).all() or np.any(np.diff(t) <= 0) or not np.isfinite(P).all():
        raise InputError("trajectory times must be finite and strictly increasing, positions finite")
    idx = columns(names, ctrl.joints)
    P = P[:, idx]
    V = None if velocities is None else np.asarray(velocities, float).reshape(len(t), -1)[:, idx]
    t = t - t[0]
    start_at = now + ctrl.lead_time_s if start_at is None else float(start_at)
    late = now + ctrl.lead_time_s - start_at  # > 0: the planned start is (nearly) past
    if late > 1e-9:
        t, P, V = trim_from(t, P, V, late)
        start_at = now + ctrl.lead_time_s
    if ctrl.stamp == "zero":
        stamp, t = 0.0, t + (start_at - now)
    else:
        stamp = start_at
    return Command(ctrl.name, ctrl.robot_joints, stamp, t, P.copy(), None if V is None else V.copy())


def progress_offset(times, positions, measured: np.ndarray, velocity=(0.0, 0.0), lead: float = 0.0,
                    horizon_s: float = 1.5, velocity_limits: Optional[np.ndarray] = None) -> float:
    """Where along a new trajectory the robot will be when it starts: the time (within ``horizon_s`` of its start)
    whose configuration is nearest to the measured one, the base moved ``lead`` seconds on at the measured
    ``velocity`` (v, omega). Nearness is time-like: the largest joint difference divided by that joint's velocity
    limit (``velocity_limits``; base x, y, theta first). A replan starts from the robot's state when planning began;
    by the time it is executed the robot has moved on, and starting the new trajectory at its beginning would pull
    the robot back. 0 for a robot at rest at the trajectory's start."""
    t = np.asarray(times, float)
    P = np.asarray(positions, float)
    pred = np.asarray(measured, float).copy()
    x, y, th = (float(v) for v in pred[:3])
    v, w = (float(a) for a in velocity)
    th_m = th + 0.5 * w * lead
    pred[:3] = [x + v * lead * math.cos(th_m), y + v * lead * math.sin(th_m), th + w * lead]
    sel = np.nonzero(t - t[0] <= horizon_s)[0]
    if len(sel) == 0:
        return 0.0
    vl = np.ones(P.shape[1]) if velocity_limits is None else np.maximum(np.asarray(velocity_limits, float), 1e-6)
    d = np.abs(P[sel] - pred)
    d[:, 2] = np.abs(np.remainder(P[sel, 2] - pred[2] + math.pi, 2 * math.pi) - math.pi)
    lin = np.hypot(P[sel, 0] - pred[0], P[sel, 1] - pred[1])
    cost = np.maximum((d[:, 2:] / vl[2:]).max(1), lin / vl[0])
    return float(t[sel[int(np.argmin(cost))]] - t[0])


def splice_progress(executing, tau: float, times, positions, lookback_s: float, tol: float) -> Optional[float]:
    """The robot's time along a splice: a splice repeats the trajectory under way (``executing``, a
    :class:`psprm_core.tracking.CheckedPath` of it as received, the robot ``tau`` seconds along it) from where the
    replan began up to its commit instant, so the robot is as far along the splice as it is along ``executing``
    beyond the splice's first configuration. That configuration is found on ``executing`` at its latest pass
    within ``lookback_s`` before ``tau`` (up to 1 s after it: the server's estimate of the robot's progress may lead
    this one), within ``tol`` (:meth:`~psprm_core.tracking.CheckedPath.latest_time_of`). None when it lies there
    nowhere. A nearest-configuration search over the splice (:func:`progress_offset`) is ambiguous where the splice
    comes back on itself (a turn on the spot reversed after the commit instant): it may place the robot beyond the
    commit instant, on motion it has not made."""
    t = np.asarray(times, float)
    s0 = executing.latest_time_of(np.asarray(positions, float)[0], tau + 1.0, lookback_s + 1.0, tol)
    return None if s0 is None else float(np.clip(tau - s0, 0.0, t[-1] - t[0]))


def sample_at(times, positions, taus) -> np.ndarray:
    """Configurations (len(taus), dof) of a trajectory, linear between its points, at times ``taus`` from its start."""
    t = np.asarray(times, float)
    t = t - t[0]
    P = np.asarray(positions, float)
    return np.stack([np.interp(taus, t, P[:, j]) for j in range(P.shape[1])], axis=1)


def trim_from(t: np.ndarray, P: np.ndarray, V: Optional[np.ndarray], tau: float) -> tuple:
    """The trajectory from time ``tau`` on, re-based to start at 0 (its first point interpolated at ``tau``)."""
    if tau >= t[-1]:
        return np.zeros(1), P[-1:].copy(), None if V is None else np.zeros_like(V[-1:])
    k = int(np.searchsorted(t, tau, side="right"))
    f = (tau - t[k - 1]) / (t[k] - t[k - 1])
    p0 = P[k - 1] + f * (P[k] - P[k - 1])
    tt = np.r_[0.0, t[k:] - tau]
    PP = np.vstack([p0, P[k:]])
    VV = None if V is None else np.vstack([V[k - 1] + f * (V[k] - V[k - 1]), V[k:]])
    if len(tt) > 1 and tt[1] - tt[0] < 1e-6:  # tau fell on a sample
        tt, PP = tt[1:] - tt[1], PP[1:]
        VV = None if VV is None else VV[1:]
    return tt, PP, VV


def hold_command(ctrl: ControllerConfig, names: Sequence[str], measured: np.ndarray) -> Command:
    """The stop every JTC accepts: one point at the measured configuration, zero velocity, a positive
    ``time_from_start`` (``hold_time_s``) and stamp 0 (start now; never 'in the past')."""
    idx = columns(names, ctrl.joints)
    q = np.asarray(measured, float).reshape(-1)[idx]
    return Command(ctrl.name, ctrl.robot_joints, 0.0, np.array([ctrl.hold_time_s]), q[None].copy(),
                   np.zeros((1, len(idx))))


def check_start(ctrl: ControllerConfig, names: Sequence[str], first: np.ndarray, measured: np.ndarray) -> tuple:
    """(ok, joint, error): the largest |first point - measured| over the controller's joints against
    ``start_tolerance``."""
    idx = columns(names, ctrl.joints)
    d = np.abs(np.asarray(first, float)[idx] - np.asarray(measured, float)[idx])
    k = int(np.argmax(d))
    return bool(d[k] <= ctrl.start_tolerance), ctrl.joints[k], float(d[k])


def check_base_start(base: BaseConfig, first: np.ndarray, measured: np.ndarray) -> tuple:
    """(ok, what, error) for the base's (x, y, theta) against start_tolerance_m / _rad."""
    d_xy = float(np.hypot(first[0] - measured[0], first[1] - measured[1]))
    d_th = abs(_wrap(float(first[2] - measured[2])))
    if d_xy > base.start_tolerance_m:
        return False, "base position", d_xy
    if d_th > base.start_tolerance_rad:
        return False, "base heading", d_th
    return True, "base", max(d_xy, d_th)


def braking_configurations(q: np.ndarray, velocity, limits, n: int = 4) -> np.ndarray:
    """Configurations (n, dof) the base passes through when it brakes from ``velocity`` (v, omega) at the
    ``limits``' accelerations (``linear_acceleration``, ``angular_acceleration``), the other joints held: a unicycle
    decelerating uniformly on both axes, sampled at n equal fractions of the braking time, the last one where it
    rests. A base that is sent a trajectory starting behind it, or that is stopped, first travels this far."""
    q = np.asarray(q, float)
    v, w = (float(x) for x in velocity)
    tv = abs(v) / max(limits.linear_acceleration, 1e-9)
    tw = abs(w) / max(limits.angular_acceleration, 1e-9)
    T = max(tv, tw)
    out = np.repeat(q[None], n, 0)
    if T <= 0.0:
        return out
    for i, t in enumerate(np.linspace(T / n, T, n)):
        # distance and turn after t of uniform deceleration on each axis (each stops at its own time)
        a, b = min(t, tv), min(t, tw)
        s = v * a - np.sign(v) * 0.5 * limits.linear_acceleration * a * a
        phi = w * b - np.sign(w) * 0.5 * limits.angular_acceleration * b * b
        th = q[2] + 0.5 * phi  # the chord's heading (exact for a uniform turn, close for a decelerating one)
        out[i, 0] = q[0] + s * math.cos(th)
        out[i, 1] = q[1] + s * math.sin(th)
        out[i, 2] = q[2] + phi
    return out


def to_joint_trajectory(cmd: Command, frame_id: str = ""):
    """:class:`Command` -> ``trajectory_msgs/JointTrajectory``."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from ..interfaces.conversions import duration_msg, sec_to_stamp

    m = JointTrajectory()
    m.header.frame_id = frame_id
    m.header.stamp = sec_to_stamp(cmd.stamp)
    m.joint_names = list(cmd.joint_names)
    pts = []
    for k in range(len(cmd.times)):
        p = JointTrajectoryPoint()
        p.positions = [float(v) for v in cmd.positions[k]]
        if cmd.velocities is not None:
            p.velocities = [float(v) for v in cmd.velocities[k]]
        p.time_from_start = duration_msg(float(cmd.times[k]))
        pts.append(p)
    m.points = pts
    return m


def action_goal_fields(cmd: Command, goal_time_tolerance_s: float = 1.0) -> dict:
    """The fields of a ``control_msgs/FollowJointTrajectory`` goal for ``cmd``: ``trajectory`` (JointTrajectory) and
    ``goal_time_tolerance`` (builtin_interfaces/Duration). Tolerances are left at their defaults (the controller's
    own)."""
    from ..interfaces.conversions import duration_msg

    return {"trajectory": to_joint_trajectory(cmd), "goal_time_tolerance": duration_msg(goal_time_tolerance_s)}


def fill_goal(goal, fields: dict):
    """Set ``fields`` on a FollowJointTrajectory goal object (refuses a field the goal type does not have)."""
    for k, v in fields.items():
        if not hasattr(goal, k):
            raise AttributeError(f"{type(goal).__name__} has no field '{k}'")
        setattr(goal, k, v)
    return goal


def import_follow_joint_trajectory():
    """``control_msgs.action.FollowJointTrajectory`` or None when control_msgs is not installed (it comes with a
    robot's ROS install, ``apt install ros-jazzy-control-msgs``; it is not on PyPI)."""
    try:
        from control_msgs.action import FollowJointTrajectory
    except ImportError:
        return None
    return FollowJointTrajectory


class GoalGate:
    """At most one goal per ``interval`` seconds: a goal offered too early is kept (the newest one) and released by
    :meth:`due` once the interval has passed. Stops pass at once."""

    def __init__(self, interval: float):
        self.interval = float(interval)
        self.last_sent: Optional[float] = None
        self.pending = None

    def offer(self, item, now: float, urgent: bool = False):
        """Returns the item to send now, or None (kept as pending)."""
        if urgent or self.last_sent is None or now - self.last_sent >= self.interval:
            self.pending = None
            self.last_sent = now
            return item
        self.pending = item
        return None

    def due(self, now: float):
        if self.pending is not None and now - self.last_sent >= self.interval:
            item, self.pending = self.pending, None
            self.last_sent = now
            return item
        return None


# ---------------------------------------------------------------------------------------------------------- Stretch base
def stretch_base_steps(base_waypoints: np.ndarray, min_step_m: float = 0.005, min_step_rad: float = 0.01) -> list:
    """Stretch position-mode base goals for a diff-drive path: ``[("rotate_mobile_base", dtheta) |
    ("translate_mobile_base", d), ...]``, one joint per goal (the driver refuses both in one goal). Each path segment
    is rotate to the driving heading, drive straight (negative = backwards), and the final heading is reached by a
    last rotation. Increments below the minimum steps are skipped."""
    W = np.asarray(base_waypoints, float).reshape(-1, 3)
    steps: List[tuple] = []
    heading = float(W[0, 2])

    def rot(target):
        nonlocal heading
        d = _wrap(target - heading)
        if abs(d) > 1e-9:
            steps.append(("rotate_mobile_base", d))
            heading = heading + d

    for a, b in zip(W[:-1], W[1:]):
        dxy = b[:2] - a[:2]
        dist = float(np.hypot(*dxy))
        if dist > 1e-4:
            drive = math.atan2(dxy[1], dxy[0])
            # drive backwards when that needs less turning (as the planner's local motions do)
            if abs(_wrap(drive - heading)) > math.pi / 2:
                rot(drive + math.pi)
                steps.append(("translate_mobile_base", -dist))
            else:
                rot(drive)
                steps.append(("translate_mobile_base", dist))
    rot(float(W[-1, 2]))
    merged: List[tuple] = []
    for j, d in steps:  # a path sampled densely gives runs of the same motion: one goal each
        if merged and merged[-1][0] == j and (j == "rotate_mobile_base" or np.sign(merged[-1][1]) == np.sign(d)):
            merged[-1] = (j, merged[-1][1] + d)
        else:
            merged.append((j, d))
    return [(j, d) for j, d in merged
            if abs(d) >= (min_step_m if j == "translate_mobile_base" else min_step_rad)]


def stretch_base_command(step: tuple, base: BaseConfig, linear_velocity: float, angular_velocity: float) -> Command:
    """One position-mode base goal: the joint ``translate_mobile_base`` or ``rotate_mobile_base`` with its increment,
    timed at the base's velocity limit, stamp 0 (the driver requires it)."""
    joint, inc = step
    speed = linear_velocity if joint == "translate_mobile_base" else angular_velocity
    dur = max(0.2, abs(inc) / max(speed, 1e-6))
    return Command("base", [joint], 0.0, np.array([dur]), np.array([[inc]]), np.zeros((1, 1)))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def base_columns(names: Sequence[str]) -> list:
    return columns(names, BASE_JOINTS)
