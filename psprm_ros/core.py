"""Shared set-up of the psprm ROS 2 nodes: typed parameters, scene/robot loading, the planner and its roadmap cache.

Nothing here creates a node or touches the middleware at import time; rclpy is imported inside the functions that
need it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

log = logging.getLogger(__name__)

#: topics shared by the nodes (absolute, so the nodes can be started in any namespace layout)
STATE_PREFIX = "/psprm/state"
TRAJECTORY_TOPIC = "/psprm/trajectory"
ROADMAP_CAMERAS_TOPIC = "/psprm/roadmap/camera_poses"
ROADMAP_SCORES_TOPIC = "/psprm/roadmap/scores"
PATH_CAMERAS_TOPIC = "/psprm/path/camera_poses"
PATH_SCORE_TOPIC = "/psprm/path/score"
PLAN_INFO_TOPIC = "/psprm/plan_info"
SERVER_STATE_TOPIC = "/psprm/server_state"  # latched std_msgs/String: "building ...", "ready: ...", "error: ..."
SERVER_NAME = "roadmap_server"

#: parameters every node reads (scene and robot), with defaults
COMMON_PARAMS = {
    "scene": "dynamic_person",  # scene name under config/scenes or a YAML path
    "robot": "",  # robot name or YAML path; "" = the scene's robot
    "targets": [],  # targets the planner and scorer keep in view; [] = the targets of the scene's problems
    "dynamic_obstacles": [],  # scene obstacles whose poses arrive on topics
    "torch_threads": 2,
}


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
def declare_params(node, spec: dict) -> dict:
    """Declare ``spec`` (name -> default) with dynamic typing and return the values coerced to the defaults' types
    (a YAML ``4`` for a float parameter is accepted; ``[]`` defaults accept any list)."""
    from rcl_interfaces.msg import ParameterDescriptor

    out = {}
    for name, default in spec.items():
        if node.has_parameter(name):
            p = node.get_parameter(name)
        else:
            p = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True))
        out[name] = coerce(name, p.value, default)
    return out


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


# ---------------------------------------------------------------------------------------------------------- scene
def load_scene_and_robot(scene_name: str, robot_name: str = ""):
    from psprm_core.paths import resolve_named
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(robot_name or scene.robot)
    return scene, robot


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
    from psprm_core.planning.factory import problem_configurations

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


# ---------------------------------------------------------------------------------------------------------- planner
@dataclasses.dataclass
class PlannerSpec:
    """What the roadmap server builds (node parameters of the same names)."""

    variant: str = "neural-psprm-line"
    n_nodes: int = 3000
    seed: int = 0
    planner_settings: str = ""  # PSPRMSettings YAML ("" = config/planners/psprm.yaml)
    replan_settings: str = "replan_reactive"  # ReplanSettings: a name in config/planners/ or a YAML path
    roadmap_file: str = ""  # "" = cache under ~/.cache/psprm/roadmaps; "none" = always build, never save
    checkpoint: str = ""  # surrogate checkpoint ("" = the shipped one)


PLANNER_PARAMS = {f.name: f.default for f in dataclasses.fields(PlannerSpec)}


def make_planner_for(scene, robot, targets, spec: PlannerSpec):
    from psprm_core.planning.factory import make_planner
    from psprm_core.planning.psprm import PSPRMSettings

    settings = None
    if spec.planner_settings:
        settings = PSPRMSettings.from_yaml(spec.planner_settings, robot=robot.name)
    return make_planner(spec.variant, scene, targets, robot=robot, settings=settings,
                        checkpoint=Path(spec.checkpoint) if spec.checkpoint else None,
                        n_nodes=int(spec.n_nodes), seed=int(spec.seed))


def roadmap_cache_path(planner, scene, spec: PlannerSpec) -> Optional[Path]:
    from psprm_core.paths import cache_dir

    if spec.roadmap_file.lower() == "none":
        return None
    if spec.roadmap_file:
        return Path(spec.roadmap_file)
    return cache_dir() / "roadmaps" / f"{scene.name}_{spec.variant}_{spec.n_nodes}_{planner.fingerprint()}.npz"


def build_or_load(planner, scene, spec: PlannerSpec, template=None, force_build: bool = False) -> dict:
    """Load the cached roadmap when its fingerprint matches, else build it (and save it to the cache). Then the
    planner's compiled query kernels are loaded (``warm_up``, reported as ``warm_up_s``), so that the first plan
    does not pay for them."""
    path = roadmap_cache_path(planner, scene, spec)
    t0 = time.perf_counter()
    if path is not None and path.is_file() and not force_build:
        try:
            planner.load(path)
            return {"source": "loaded", "path": str(path), "n_nodes": int(planner.n_roadmap_nodes),
                    "seconds": time.perf_counter() - t0, "warm_up_s": _warm_up(planner)}
        except Exception as exc:  # a stale or foreign roadmap file: rebuild
            log.warning("cannot use roadmap %s (%s); rebuilding", path, exc)
    stats = planner.build(template=template)
    if not stats.get("success", False):
        return {"source": "failed", "reason": stats.get("reason", "build failed"), "seconds": time.perf_counter() - t0}
    if path is not None:
        try:
            planner.save(path)
        except OSError as exc:
            log.warning("cannot save roadmap %s: %s", path, exc)
    return {"source": "built", "path": str(path) if path else "", "n_nodes": int(planner.n_roadmap_nodes),
            "seconds": time.perf_counter() - t0, "warm_up_s": _warm_up(planner)}


def _warm_up(planner) -> float:
    """Compile or load the planner's small-batch query kernels now (PSPRM.warm_up); 0 for other planners."""
    warm = getattr(planner, "warm_up", None)
    return float(warm()) if warm is not None else 0.0


def make_replanner(planner, settings_path: str = ""):
    """The core :class:`~psprm_core.planning.replanner.Replanner` around a built or loaded ``planner``."""
    from psprm_core.planning.replanner import Replanner, ReplanSettings

    from psprm_core.paths import resolve_named

    settings = ReplanSettings.from_yaml(resolve_named("planner", settings_path)) if settings_path else ReplanSettings()
    return Replanner(planner, settings)
