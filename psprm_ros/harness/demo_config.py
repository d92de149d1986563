"""What the closed-loop demo (:mod:`psprm_ros.harness.demo`) runs, derived from the params file the nodes are started with
and the recording it replays: scene, robot, adapter, targets, dynamic obstacles, the robot's start, the goals and
how they are sent, the topic and frame of every recorded body.

The params file is read as the nodes read it: the shared ``/**`` section overlaid by each node's own section.

* scene, robot (``""``: the scene's), targets (``[]``: the targets of the scene's problems), dynamic obstacles and
  input frames: the shared section;
* adapter: ``robot_adapter``'s ``adapter`` (``""``: the robot's name); ``sim_robot`` must simulate the same one;
* start: ``sim_robot``'s ``start_problem`` (``""``: the scene's first problem) and ``initial_base``, where the
  simulated robot starts;
* goals: ``roadmap_server``'s ``goal_regions`` when it names any, else the goals of the server's ``start_problem``
  (else the monitor's, else sim_robot's, else the scene's first problem): its goal regions, sent by name on
  ``/psprm/goal_regions``, or its goal pose, sent on ``/psprm/goal`` (base x, y, heading; a problem with both is
  sent its regions). A goal pose counts as reached within :data:`POSE_GOAL_XY_TOLERANCE_M` and
  :data:`POSE_GOAL_THETA_TOLERANCE_RAD`, a goal region within its own tolerances;
* the topic of each recorded body: ``replan_monitor``'s ``target_topics`` / ``obstacle_topics`` (same order as the
  targets / dynamic obstacles), else ``<mocap_prefix>/<body>/pose``.

No ROS import here.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Optional

import numpy as np

from psprm_core.errors import InputError
from psprm_core.paths import resolve_named
from psprm_core.planning.replan_settings import ReplanSettings
from psprm_core.robot import RobotModel
from psprm_core.scene import load_scene

from .. import core, planner_setup
from ..core import resolve_scene
from ..interfaces.frames import FrameTable
from ..interfaces.recordings import SHIPPED
from ..robots.adapters import load_adapter

#: the node sections of a params file
NODE_SECTIONS = ("roadmap_server", "perception_scorer", "replan_monitor", "robot_adapter", "sim_robot")

#: a goal pose (no tolerances of its own) is reached with the base this close to it
POSE_GOAL_XY_TOLERANCE_M = 0.10
POSE_GOAL_THETA_TOLERANCE_RAD = 0.25


@dataclasses.dataclass(frozen=True)
class DemoGoal:
    """A goal of the base: a scene goal region, or a problem's goal pose with the default tolerances."""

    name: str
    base: tuple  # (x, y, theta) in the scene frame
    xy_tolerance: float
    theta_tolerance: float

    def contains(self, q) -> bool:
        """Whether the base of configuration ``q`` (x, y, theta first) lies within the tolerances."""
        return bool(math.hypot(q[0] - self.base[0], q[1] - self.base[1]) <= self.xy_tolerance and
                    abs(math.remainder(q[2] - self.base[2], 2 * math.pi)) <= self.theta_tolerance)


@dataclasses.dataclass
class DemoConfig:
    """The closed loop of one params file (see the module docstring for where each field comes from)."""

    params_file: str
    scene: object  # psprm_core.scene.Scene
    robot: object  # psprm_core.robot.RobotModel
    adapter: str
    targets: list
    dynamic_obstacles: list
    start_problem: str  # where sim_robot starts ("" = the scene's first problem)
    start: np.ndarray  # (dof,) the simulated robot's start configuration
    goal_problem: str  # the problem whose goals are sent ("" = the server's goal_regions parameter)
    goals: list  # DemoGoal
    goal_regions: list  # names sent on /psprm/goal_regions; [] = the single goal pose goes on /psprm/goal
    body_topics: dict  # body -> mocap topic the replan monitor subscribes to
    frames: object  # psprm_ros.interfaces.frames.FrameTable of the params' input frames
    recorded_bodies: list = dataclasses.field(default_factory=list)
    recorded_frames: dict = dataclasses.field(default_factory=dict)  # body -> frame id of its recorded poses
    arrival_budget: float = 0.0  # the server's: a view-triggered replan arrives within (1 + this) x the reference

    def patience_s(self, first_duration: float, at_least: float, settle_s: float = 10.0) -> float:
        """How long after the first plan the loop is given to reach its goal: ``at_least``, and no less than the
        server's arrival budget allows a robot whose replans trade time for views ((1 + ``arrival_budget``) times
        the first plan's duration, which bounds the budget's reference), plus ``settle_s`` to come to rest."""
        if self.arrival_budget <= 0:
            return at_least
        return max(at_least, (1.0 + self.arrival_budget) * first_duration + settle_s)

    @property
    def goal_names(self) -> list:
        return [g.name for g in self.goals]

    def at_goal(self, q) -> str:
        """Name of the first goal whose tolerances contain the base of ``q`` ("" = none)."""
        for g in self.goals:
            if g.contains(q):
                return g.name
        return ""

    def to_scene(self, body: str, p, q) -> tuple:
        """A recorded pose of ``body`` (in its recorded frame) in the scene frame."""
        return self.frames.to_scene(self.recorded_frames.get(body, self.scene.frame), p, q, f"recorded {body}")

    def describe(self) -> dict:
        """The configuration as JSON-ready names and numbers."""
        return {"params": str(self.params_file), "scene": self.scene.name, "robot": self.robot.name,
                "adapter": self.adapter, "targets": list(self.targets),
                "dynamic_obstacles": list(self.dynamic_obstacles), "start_problem": self.start_problem,
                "start_base": [round(float(v), 4) for v in self.start[:3]] if self.robot.mobile else None,
                "goal_problem": self.goal_problem, "goal_regions": list(self.goal_regions),
                "goals": [{"name": g.name, "base": [round(float(v), 4) for v in g.base],
                           "xy_tolerance": g.xy_tolerance, "theta_tolerance": g.theta_tolerance}
                          for g in self.goals],
                "recorded_bodies": list(self.recorded_bodies), "body_topics": dict(self.body_topics)}


def _section(data: dict, node: str) -> dict:
    """``ros__parameters`` of a node's section (``node``, ``/node`` or ``/**/node``) of a params file."""
    for key in (node, f"/{node}", f"/**/{node}", f"**/{node}"):
        sec = data.get(key)
        if isinstance(sec, dict):
            params = sec.get("ros__parameters", {})
            if not isinstance(params, dict):
                raise InputError(f"params file: section '{key}': ros__parameters must be a mapping")
            return params
    return {}


def read_params(path) -> dict:
    """node name -> its parameters from a params file: the shared ``/**`` section overlaid by the node's own."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"params file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of node sections")
    shared = _section(data, "**")
    return {n: {**shared, **_section(data, n)} for n in NODE_SECTIONS}


def params_frames(shared: dict, scene_frame: str, where: str = "params file"):
    """The :class:`~psprm_ros.interfaces.frames.FrameTable` of a node's parameters (``input_frames`` and their
    ``input_frame.<name>`` transforms, nested or dotted)."""
    table = FrameTable(scene_frame)
    specs = shared.get("input_frame") or {}
    for n in shared.get("input_frames") or []:
        if not str(n).strip():
            continue
        spec = specs.get(n, {}) if isinstance(specs, dict) else {}
        xyz = spec.get("xyz", shared.get(f"input_frame.{n}.xyz", [0.0, 0.0, 0.0]))
        quat = spec.get("quat", shared.get(f"input_frame.{n}.quat", [0.0, 0.0, 0.0, 1.0]))
        try:
            table.add(str(n), xyz, quat)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    return table


def _goals(params: dict, scene, robot, where: str) -> tuple:
    """(problem name, goals, goal region names to send)."""
    server = params["roadmap_server"]
    regions = [str(r) for r in server.get("goal_regions") or [] if str(r).strip()]
    if regions:
        return "", [_region_goal(scene, r) for r in regions], regions
    name = next((str(params[n].get("start_problem") or "") for n in ("roadmap_server", "replan_monitor", "sim_robot")
                 if params[n].get("start_problem")), "")
    if name:
        problem = scene.problem(name)
    elif scene.problems:
        problem = scene.problems[0]
    else:
        raise InputError(f"{where}: no goal: the server names no goal_regions and scene '{scene.name}' has no problem")
    if problem.goal_regions:
        regions = list(problem.goal_regions)
        return problem.name, [_region_goal(scene, r) for r in regions], regions
    g = problem.goal
    if not robot.mobile or not {"base_x", "base_y", "base_theta"} <= set(g):
        raise InputError(f"{where}: problem '{problem.name}' of scene '{scene.name}' has no goal regions and its goal "
                         "is not a base pose (a goal message carries only the base)")
    goal = DemoGoal(f"{problem.name} goal", (float(g["base_x"]), float(g["base_y"]), float(g["base_theta"])),
                    POSE_GOAL_XY_TOLERANCE_M, POSE_GOAL_THETA_TOLERANCE_RAD)
    return problem.name, [goal], []


def _region_goal(scene, name: str) -> DemoGoal:
    r = scene.goal(name)
    return DemoGoal(r.name, tuple(float(v) for v in r.base), float(r.xy_tolerance), float(r.theta_tolerance))


def _topics(monitor: dict, names: list, key: str, where: str) -> dict:
    topics = [str(t) for t in monitor.get(key) or []]
    if topics and len(topics) != len(names):
        raise InputError(f"{where}: replan_monitor.{key} has {len(topics)} entries for {len(names)} bodies")
    prefix = str(monitor.get("mocap_prefix") or "/mocap")
    return {n: topics[i] if topics else f"{prefix}/{n}/pose" for i, n in enumerate(names)}


def demo_config(params_file, recording=None) -> DemoConfig:
    """The closed loop of ``params_file``; with ``recording`` (a :class:`~psprm_ros.interfaces.recordings.Recording`),
    its bodies are checked to be targets or dynamic obstacles the monitor subscribes to, recorded in the scene frame or
    an input frame of the params file. Raises :class:`~psprm_core.errors.InputError` naming the file and the field."""
    where = str(params_file)
    params = read_params(params_file)
    shared = params["roadmap_server"]  # the shared section as the server reads it
    scene = _load_scene(str(shared.get("scene") or core.COMMON_PARAMS["scene"]))
    robot = RobotModel.load(str(shared.get("robot") or "") or scene.robot)
    targets = core.scene_targets(scene, [str(t) for t in shared.get("targets") or []])
    obstacles = [str(o) for o in shared.get("dynamic_obstacles") or []]
    for o in obstacles:
        scene.obstacle(o)
    adapter = str(params["robot_adapter"].get("adapter") or "") or robot.name
    sim_adapter = str(params["sim_robot"].get("adapter") or "") or robot.name
    if sim_adapter != adapter:
        raise InputError(f"{where}: sim_robot simulates adapter '{sim_adapter}', robot_adapter drives '{adapter}'")
    load_adapter(adapter, robot)  # the adapter config exists and fits the robot
    sim = params["sim_robot"]
    start_problem = str(sim.get("start_problem") or "")
    start = core.start_configuration(robot, scene, start_problem)
    initial = list(sim.get("initial_base") or [])
    if len(initial) == 3 and robot.mobile:
        start[:3] = [float(v) for v in initial]
    goal_problem, goals, regions = _goals(params, scene, robot, where)
    monitor = params["replan_monitor"]
    topics = {**_topics(monitor, targets, "target_topics", where),
              **_topics(monitor, obstacles, "obstacle_topics", where)}
    replan = str(shared.get("replan_settings") or planner_setup.PLANNER_PARAMS["replan_settings"])
    budget = shared.get("arrival_budget")  # the params file's override, else the server's settings file's
    if budget is None:
        budget = ReplanSettings.from_yaml(resolve_named("planner", replan)).arrival_budget
    cfg = DemoConfig(params_file=where, scene=scene, robot=robot, adapter=adapter, targets=targets,
                     dynamic_obstacles=obstacles, start_problem=start_problem, start=start, goal_problem=goal_problem,
                     goals=goals, goal_regions=regions, body_topics=topics,
                     frames=params_frames(params["roadmap_server"], scene.frame, where), arrival_budget=float(budget))
    if recording is not None:
        unknown = [b for b in recording.bodies if b not in topics]
        if unknown:
            raise InputError(f"{where}: recorded bodies {', '.join(unknown)} are neither targets ({', '.join(targets)})"
                             f" nor dynamic obstacles ({', '.join(obstacles) or 'none'}) of the params file")
        cfg.recorded_bodies = list(recording.bodies)
        cfg.recorded_frames = dict(zip(recording.bodies, recording.frames))
        for b, f in cfg.recorded_frames.items():
            if not cfg.frames.knows(f):
                raise InputError(f"{where}: recorded body {b} is in frame '{f}', neither the scene frame "
                                 f"'{scene.frame}' nor an input frame of the params file "
                                 f"({', '.join(cfg.frames.known)})")
    return cfg


def _load_scene(name: str):
    return load_scene(resolve_scene(name))


def default_recording(params_file) -> Optional[str]:
    """The shipped recording replayed with a shipped params file (:data:`psprm_ros.interfaces.recordings.SHIPPED`), or
    None."""
    root = Path(__file__).resolve().parents[2]
    try:
        want = Path(params_file).resolve()
    except OSError:
        return None
    for _, path, params in SHIPPED.values():  # the repository's params file, or an installed copy of it
        if (root / params).resolve() == want or (Path(params).name == want.name and (root / path).is_file()):
            return str(root / path)
    return None
