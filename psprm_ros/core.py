"""Shared set-up of the psprm ROS 2 nodes: typed parameters, scene/robot loading, the planner and its roadmap cache.

Nothing here creates a node or touches the middleware at import time; rclpy is imported inside the functions that
need it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from psprm_core.errors import ConfigError, InputError, PsprmError, RobotModelError
from psprm_core.paths import resolve_named
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.settings import PSPRMSettings
from psprm_core.robot import RobotModel
from psprm_core.scene import load_scene
from psprm_core.yamlio import Fields, load_yaml

# the nodes use these as core.<name>
from .lifecycle import (DIAG_ERROR, DIAG_OK, DIAG_STALE, DIAG_WARN, DIAGNOSTICS_TOPIC, StallGrace,  # noqa: F401
                        autostart, bare_setting_names, diagnostic_status, lifecycle_node, lifecycle_state,
                        publish_diagnostics)
from .robots.robot_description import robot_from_params

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Param:
    """A node parameter: its default, what it means, and whether a running node applies a change (``live``) or the
    change needs a rebuild (``rebuild``: read-only while the node runs; set it in the params file and restart or
    reconfigure). ``lo``/``hi``: range of a number; ``choices``: the values a string may take. A None ``default`` is
    declared typed (``type``) but unset. ``check``: called with a coerced value, raises
    :class:`~psprm_core.errors.PsprmError` (or ValueError) with the reason a value is refused."""

    default: Any
    description: str = ""
    live: bool = False
    rebuild: bool = False
    lo: Optional[float] = None
    hi: Optional[float] = None
    choices: Optional[tuple] = None
    type: Optional[type] = None
    check: Optional[Callable[[Any], None]] = dataclasses.field(default=None, compare=False)

    @property
    def exemplar(self) -> Any:
        """A value of the parameter's type (its default, else one made from :attr:`type`) for :func:`coerce`."""
        return self.default if self.default is not None or self.type is None else self.type()


def setting_param(spec, default: Any = dataclasses.MISSING, source: str = "ROS parameter") -> Param:
    """The node parameter of a setting (a :class:`~psprm_core.planning.settings_groups.SettingSpec`: a planner setting
    by its dotted path, a replanner setting by its name): description, range, choices, type and ``live`` from the spec,
    a setting that is not live needs a rebuild; ``default`` (the spec's default unless given) None declares it typed but
    unset. A tuple setting (``query.route_searches``) is a string parameter in its text form. Its ``check`` refuses what
    the spec refuses, with the :class:`~psprm_core.errors.ConfigError` naming the setting."""
    default = spec.default if default is dataclasses.MISSING else default
    kind = spec.type
    if kind is tuple:
        kind, default = str, ",".join(str(x) for x in (default or ()))
    lo, hi = spec.range if spec.range is not None else (None, None)

    def check(value):
        if spec.type is tuple:
            value = PSPRMSettings.coerce(spec.name, value, source)
        spec.check(value, source)

    return Param(default, spec.description, live=spec.live, rebuild=not spec.live, lo=lo, hi=hi,
                 choices=spec.choices, type=kind, check=check)


#: topics shared by the nodes (absolute, so the nodes can be started in any namespace layout)
STATE_PREFIX = "psprm/state"
TRAJECTORY_TOPIC = "psprm/trajectory"
ROADMAP_CAMERAS_TOPIC = "psprm/roadmap/camera_poses"
ROADMAP_SCORES_TOPIC = "psprm/roadmap/scores"
PATH_CAMERAS_TOPIC = "psprm/path/camera_poses"
PATH_SCORE_TOPIC = "psprm/path/score"
PLAN_INFO_TOPIC = "psprm/plan_info"
SERVER_STATE_TOPIC = "psprm/server_state"  # latched std_msgs/String: "building ...", "ready: ...", "error: ..."
SERVER_NAME = "roadmap_server"

BASE_PATH_TOPIC = "psprm/base_path"  # nav_msgs/Path of the planned base route (latched)


def _common_params() -> dict:
    P = Param
    return {
        "scene": P("dynamic_person", "scene name under config/scenes or a YAML path", rebuild=True),
        "robot": P("", "robot name or YAML path; '' = the scene's robot", rebuild=True),
        "targets": P([], "targets kept in view; [] = the targets of the scene's problems", rebuild=True),
        "dynamic_obstacles": P([], "scene obstacles whose poses arrive on topics", rebuild=True),
        "torch_threads": P(2, "torch intra-op threads", lo=1),
        "autostart": P(True, "configure and activate the lifecycle node at start-up (as a lifecycle manager with "
                             "autostart would)"),
        "robot_description": P("package", "the URDF the robot model is built from: 'package' (the URDF the robot "
                                          "config names, installed with psprm), 'topic' (the robot's own URDF, e.g. "
                                          "its calibrated one from robot_state_publisher, on robot_description_topic; "
                                          "the node waits for it at start-up and stays unconfigured without one or "
                                          "with one that does not match the robot config), 'auto' (the topic's URDF "
                                          "when one arrives within robot_description_timeout_s, else the packaged "
                                          "one)", rebuild=True),
        "robot_description_topic": P("robot_description", "std_msgs/String topic of the robot's URDF (transient "
                                                          "local, reliable, as robot_state_publisher publishes it); "
                                                          "a relative name follows the node's namespace",
                                     rebuild=True),
        "robot_description_timeout_s": P(10.0, "longest start-up wait for the robot's URDF on the topic (s; "
                                               "robot_description 'topic' or 'auto')", rebuild=True, lo=0.0),
    }


#: parameters every node reads (scene and robot), with defaults
COMMON_PARAMS = {k: v.default for k, v in _common_params().items()}


def report(log, publisher, text: str, level: str = "info") -> None:
    """Log ``text`` at ``level`` (info, warning, error) and publish it as ``"<level>: <text>"`` on a node's
    ``~/status`` (std_msgs/String); a publish during shutdown is ignored."""
    from std_msgs.msg import String

    # one call site per severity: rclpy refuses a call site whose severity changes between calls
    if level == "error":
        log.error(text)
    elif level == "warning":
        log.warning(text)
    else:
        log.info(text)
    try:
        publisher.publish(String(data=f"{level}: {text}"))
    except Exception:  # the context may already be shut down
        pass


def target_topic(name: str) -> str:
    return f"{STATE_PREFIX}/targets/{name}"


def obstacle_topic(name: str) -> str:
    return f"{STATE_PREFIX}/obstacles/{name}"


ROBOT_STATE_TOPIC = f"{STATE_PREFIX}/robot"
GOALS_TOPIC = f"{STATE_PREFIX}/goals"


# ---------------------------------------------------------------------------------------------------------- params
def declare_params(node, spec: dict, refusals: Optional[list] = None) -> dict:
    """Declare ``spec`` (name -> default or :class:`Param`) with dynamic typing and descriptors (description,
    read-only for rebuild parameters, ranges, choices as a described constraint) and return the values coerced to the
    defaults' types (a YAML ``4`` for a float parameter is accepted; ``[]`` defaults accept any list). A
    :class:`Param` whose default is None is declared statically typed (its ``type``) and unset; its value is None.

    With ``refusals`` (a list), a value the node is given that the parameter refuses (type, range, choices, its
    ``check``) does not raise: the reason is appended (``"name: why"``) and a value rclpy refused is replaced by the
    default."""
    from rclpy.exceptions import ParameterException

    out = {}
    for name, item in spec.items():
        prm = item if isinstance(item, Param) else Param(item)
        if node.has_parameter(name):
            p = node.get_parameter(name)
        else:
            try:
                p = _declare(node, name, prm)
            except (ParameterException, ValueError, TypeError) as exc:
                if refusals is None:
                    raise
                refusals.append(f"{name}: {exc}")
                p = _declare(node, name, prm, ignore_override=True)
        try:
            out[name] = coerce(name, p.value, prm.exemplar) if p.value is not None else None
            if out[name] is not None:
                check_value(prm, out[name])
        except (PsprmError, ValueError, TypeError) as exc:
            if refusals is None:
                raise
            refusals.append(_reason(name, exc))
            out[name] = prm.default
    return out


def param_descriptor(prm: Param):
    """The ``rcl_interfaces/ParameterDescriptor`` of ``prm``: description, read-only for rebuild parameters, range
    (FloatingPointRange / IntegerRange), choices (additional_constraints); dynamic typing unless the default is None
    (statically typed, its ``type``)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

    d = ParameterDescriptor(dynamic_typing=prm.default is not None, description=prm.description,
                            read_only=prm.rebuild)
    if prm.default is None:
        d.type = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
                  float: ParameterType.PARAMETER_DOUBLE}.get(prm.type, ParameterType.PARAMETER_STRING)
    if prm.choices is not None:
        d.additional_constraints = f"one of: {', '.join(map(str, prm.choices))}"
    if prm.lo is not None or prm.hi is not None:
        lo = -1e300 if prm.lo is None else prm.lo
        hi = 1e300 if prm.hi is None else prm.hi
        example = prm.exemplar
        if isinstance(example, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi))]
        elif isinstance(example, int) and not isinstance(example, bool):
            d.integer_range = [IntegerRange(from_value=int(max(lo, -2**62)), to_value=int(min(hi, 2**62)))]
    return d


def _declare(node, name: str, prm: Param, ignore_override: bool = False):
    from rclpy.parameter import Parameter

    d = param_descriptor(prm)
    if prm.default is None:
        return node.declare_parameter(name, Parameter.Type(d.type), d, ignore_override=ignore_override)
    return node.declare_parameter(name, prm.default, d, ignore_override=ignore_override)


def check_value(prm: Param, value: Any) -> None:
    """Raise when ``prm``'s ``check`` refuses ``value`` (coerced) or it lies outside ``prm``'s choices."""
    if prm.check is not None:
        prm.check(value)
    if prm.choices is not None and value not in prm.choices:
        raise InputError(f"unknown value {value!r} (one of: {', '.join(map(str, prm.choices))})")


def coerce(name: str, value: Any, default: Any) -> Any:
    if value is None:
        return default
    if isinstance(default, bool):
        if isinstance(value, str):
            return value.strip().lower() in ("1", "true", "yes", "on")
        return bool(value)
    if isinstance(default, float):
        return float(value)
    if isinstance(default, int):
        return int(value)
    if isinstance(default, str):
        return str(value)
    if isinstance(default, (list, tuple)):
        if isinstance(value, str):
            return [v.strip() for v in value.split(",") if v.strip()]
        return list(value)
    return value


def common_params() -> dict:
    """:data:`COMMON_PARAMS` with descriptions (scene, robot, targets and obstacles need a rebuild)."""
    return _common_params()


def default_of(item) -> Any:
    return item.default if isinstance(item, Param) else item


def install_param_callback(node, spec: dict, values: dict, apply) -> None:
    """Set-parameters callback: a change to a ``live`` parameter is checked (type, range, finite) and handed to
    ``apply(name, value)`` (which may raise ValueError to refuse it); any other change is refused with the reason.
    ``values`` (the dict :func:`declare_params` returned) is updated for accepted changes."""
    from rcl_interfaces.msg import SetParametersResult

    def cb(params):
        staged = {}
        for prm in params:
            item = spec.get(prm.name)
            if item is None:
                continue  # parameters of other parts of the node (use_sim_time, input frames) are not ours
            p = item if isinstance(item, Param) else Param(item)
            if not p.live:
                why = "needs a rebuild: set it in the params file and reconfigure the node" if p.rebuild else \
                    "is read when the node is configured: deactivate, cleanup and configure to change it"
                return SetParametersResult(successful=False, reason=f"{prm.name} {why}")
            try:
                if prm.value is None:
                    raise InputError("cannot be unset while the node runs")
                v = coerce(prm.name, prm.value, p.exemplar)
                if isinstance(v, float) and not math.isfinite(v):
                    raise InputError("must be finite")
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    if (p.lo is not None and v < p.lo) or (p.hi is not None and v > p.hi):
                        raise InputError(f"must lie in [{p.lo}, {p.hi}]")
                check_value(p, v)
                staged[prm.name] = v
            except (TypeError, ValueError, PsprmError) as exc:
                return SetParametersResult(successful=False, reason=_reason(prm.name, exc))
        for k, v in staged.items():
            try:
                apply(k, v)
            except (ValueError, PsprmError) as exc:
                return SetParametersResult(successful=False, reason=_reason(k, exc))
            values[k] = v
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(cb)


def _reason(name: str, exc: Exception) -> str:
    """Why a parameter change is refused: a configuration error as it is (it names the setting), others after the
    parameter's name."""
    return str(exc) if isinstance(exc, ConfigError) else f"{name}: {exc}"


# ---------------------------------------------------------------------------------------------------------- scene
class _SpecWhileUnconfigured(dict):
    """A node's parameter spec as :func:`install_param_callback` sees it: while the node is unconfigured every
    parameter may be set (a configure reads them all), once configured only the ``live`` ones are applied and the
    others are refused with their reason (read when the node is configured / needs a rebuild)."""

    def __init__(self, spec: dict, node):
        super().__init__(spec)
        self._node = node

    def get(self, name, default=None):
        item = super().get(name, default)
        if item is None or lifecycle_state(self._node) != "unconfigured":
            return item
        p = item if isinstance(item, Param) else Param(item)
        return dataclasses.replace(p, live=True)


def declare_reconfigurable_params(node, spec: dict, apply) -> dict:
    """Declare ``spec`` on a lifecycle node that reads its parameters at configure and return their values (the
    dict is kept up to date by the set-parameters callback, which hands accepted changes to ``apply(name, value)``).

    Set while the node is unconfigured (before its first configure, or after a cleanup), any of them is taken and
    used by the next configure; that is why the ``rebuild`` ones are not declared read-only here. While the node is
    configured (inactive or active), live ones are applied and the others are refused with the reason."""
    declared = {k: dataclasses.replace(v, rebuild=False) if isinstance(v, Param) else v for k, v in spec.items()}
    values = declare_params(node, declared)
    install_param_callback(node, _SpecWhileUnconfigured(spec, node), values, apply)
    return values


def load_configured_scene_and_robot(node, p: dict):
    """The scene and robot model of a node's parameters ``p``, loaded at configure. A robot description the node
    cannot use (robot_description ``topic``/``auto``) fails this configure with the reason; the next configure
    checks the description again."""
    scene, robot = load_scene_and_robot(p["scene"], p["robot"], node=node, params=p)
    refusal = getattr(node, "configure_refusal", "")
    if refusal:
        node.configure_refusal = ""
        raise RobotModelError(refusal)
    return scene, robot


class ConfigureScope:
    """The subscriptions, publishers and timers a lifecycle node's configure makes, destroyed together by its cleanup
    (so that a configure after it follows changed parameters)."""

    def __init__(self, node):
        self.node = node
        self._subs: list = []
        self._pubs: list = []
        self._timers: list = []

    @staticmethod
    def configure(make, release) -> bool:
        """Run ``make`` (a node's set-up); when it raises, ``release`` what it made so far and raise on (the node
        stays unconfigured with nothing made, and can be configured again)."""
        try:
            make()
        except Exception:
            release()
            raise
        return True

    def subscription(self, *args, **kwargs):
        s = self.node.create_subscription(*args, **kwargs)
        self._subs.append(s)
        return s

    def publisher(self, *args, **kwargs):
        pub = self.node.create_publisher(*args, **kwargs)
        self._pubs.append(pub)
        return pub

    def timer(self, *args, **kwargs):
        t = self.node.create_timer(*args, **kwargs)
        self._timers.append(t)
        return t

    def own(self, subscriptions) -> None:
        """Subscriptions made elsewhere (e.g. :func:`psprm_ros.interfaces.tf_tree.subscribe_tf`), released with the
        rest."""
        self._subs.extend(subscriptions)

    def release(self) -> None:
        for t in self._timers:
            self.node.destroy_timer(t)
        for s in self._subs:
            self.node.destroy_subscription(s)
        for pub in self._pubs:
            self.node.destroy_publisher(pub)
        self._subs, self._pubs, self._timers = [], [], []


def resolve_scene(scene_name: str):
    """A scene by path, by name among psprm_core's scenes, or by name among the scenes installed with the colcon
    package (``share/psprm_ros/scenes``)."""
    try:
        return resolve_named("scene", scene_name)
    except ConfigError:
        share = share_dir()
        if share is not None and (share / "scenes" / f"{scene_name}.yaml").is_file():
            return share / "scenes" / f"{scene_name}.yaml"
        raise


def share_dir() -> Optional[Path]:
    """``share/psprm_ros`` of the installed colcon package, or None when it is not installed."""
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("psprm_ros"))
    except Exception:
        return None


def load_scene_and_robot(scene_name: str, robot_name: str = "", node=None, params: Optional[dict] = None):
    """The scene and its robot model (``robot_name``, or the scene's robot). With ``node`` and its parameter values
    ``params``, the robot model is built as the node's ``robot_description`` parameters say
    (:func:`psprm_ros.robots.robot_description.robot_from_params`: the packaged URDF, or the robot's own from its
    topic)."""
    scene = load_scene(resolve_scene(scene_name))
    if node is not None:
        return scene, robot_from_params(node, {**(params or {}), "robot": robot_name}, scene)
    robot = RobotModel.load(robot_name or scene.robot)
    return scene, robot


class ConfiguredRobot:
    """The ``robot`` of a node that builds its robot model in configure (into ``_robot``) from the parameters
    ``scene`` and ``robot`` (``p``). Before configure (or after cleanup) the node holds none: asked then (a caller
    comparing the nodes' robots), the packaged model the parameters name is loaded for the caller and not kept."""

    _robot = None

    @property
    def robot(self):
        if self._robot is not None:
            return self._robot
        return load_scene_and_robot(self.p["scene"], self.p["robot"])[1]


def scene_robot_name(scene_name: str) -> str:
    """The robot a scene file names (its ``robot`` field), read without loading the scene."""
    path = resolve_scene(scene_name)
    return Fields(load_yaml(path), str(path)).str("robot")


def scene_targets(scene, targets) -> list:
    """The requested targets, or the targets named by the scene's problems (all targets when none is)."""
    if targets:
        for t in targets:
            scene.target(t)
        return list(targets)
    named = []
    for p in scene.problems:
        if p.target not in named:
            named.append(p.target)
    return named or scene.target_names[:1]


def start_configuration(robot, scene, problem: str = "") -> np.ndarray:
    """Start configuration of a scene problem (the first one by default; the robot's default pose without one)."""
    if not scene.problems:
        return robot.default_configuration()
    p = scene.problem(problem) if problem else scene.problems[0]
    return problem_configurations(robot, scene, p)[0]


def goal_region_configurations(robot, scene, names) -> np.ndarray:
    """Centre configurations (G, dof) of named goal regions (other joints at their defaults)."""
    out = []
    for n in names:
        g = scene.goal(n)
        vals = dict(g.joints)
        if robot.mobile:
            vals.update(base_x=g.base[0], base_y=g.base[1], base_theta=g.base[2])
        out.append(robot.configuration(vals))
    return np.array(out).reshape(-1, robot.dof)
