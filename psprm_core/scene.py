"""Scene model: obstacles (oriented boxes), perception targets, goal regions and named problems.

Scenes are YAML files under ``config/scenes`` (format: ``docs/scenes.md``). Everything is expressed in the scene's
``frame`` (``map`` by default), z up, metres and radians.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Optional

import numpy as np

from .errors import ConfigError, OutOfRangeError, UnknownNameError
from .geometry import obb_overlap, quat_to_matrix, yaw_to_quat
from .yamlio import Fields, load_yaml


@dataclass(frozen=True)
class Box:
    """An oriented box obstacle.

    Attributes
    ----------
    name : str
    center : (3,) ndarray
        Box centre in the scene frame.
    size : (3,) ndarray
        Full extents along the box's own x, y, z axes.
    quat : (4,) ndarray
        Orientation ``(x, y, z, w)``.
    color : (4,) ndarray
        RGBA used by renderers and plots.
    mesh : str or None
        Optional visual mesh (resource path); collision always uses the box.
    turning : bool
        The box turns about its own z axis (a person's body): planners keep clear of every heading it can take,
        :meth:`swept` (a collision checker plans with that box and keeps this one as the real one).
    """

    name: str
    center: np.ndarray
    size: np.ndarray
    quat: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    color: np.ndarray = field(default_factory=lambda: np.array([0.6, 0.6, 0.6, 1.0]))
    mesh: Optional[str] = None
    turning: bool = False

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation matrix of :attr:`quat` (a copy of the one worked out once per box)."""
        return self._rotation.copy()

    @property
    def half_extents(self) -> np.ndarray:
        return 0.5 * np.asarray(self.size)

    @cached_property
    def _rotation(self) -> np.ndarray:
        return quat_to_matrix(self.quat)

    def swept(self) -> "Box":
        """The box that holds this one at every heading about its own z axis: x and y extents grown to the diameter
        of its footprint's circumscribed circle (the footprint's corners sweep that circle as it turns)."""
        r = math.hypot(self.size[0], self.size[1])
        return replace(self, size=np.array([r, r, self.size[2]], dtype=float), turning=False)

    def planned(self) -> "Box":
        """The box a planner keeps clear of: :meth:`swept` for a turning box, else this one."""
        return self.swept() if self.turning else self

    def corners(self) -> np.ndarray:
        """The 8 corners in the scene frame, shape (8, 3)."""
        s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
        return (s * self.half_extents) @ self.rotation.T + self.center


@dataclass(frozen=True)
class Target:
    """Something the camera must perceive (a face, a cup, a monitor...).

    The target frame's +x axis is the direction the target *faces* (a person's gaze, a monitor's screen normal);
    its appearance (a photo texture) is on that side.

    Attributes
    ----------
    name : str
    detector_class : str
        Class the oracle detector looks for (``face``, or a COCO class such as ``cup``, ``tv``).
    center : (3,) ndarray
        Centroid (the point line-of-sight constraints aim at).
    quat : (4,) ndarray
        Orientation ``(x, y, z, w)``.
    size : (3,) ndarray
        Extent of the target's bounding box (x = depth along the facing direction).
    appearance : str
        Name of the texture/photo the renderer puts on the facing side.
    obstacle : bool
        Whether the target's box is also a collision obstacle.
    placements : tuple of ((3,) ndarray, (4,) ndarray)
        Other poses ``(center, quat)`` the target may stand at (the paper's "five variations in the object's poses"
        per benchmark object); placement 0 is the pose above, placement ``k`` the ``k``-th of these. See
        :meth:`pose` and :meth:`Scene.with_placement`.
    """

    name: str
    detector_class: str
    center: np.ndarray
    size: np.ndarray
    quat: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    appearance: str = ""
    obstacle: bool = True
    placements: tuple = ()

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation matrix of :attr:`quat` (a copy of the one worked out once per target)."""
        return self._rotation.copy()

    @cached_property
    def _rotation(self) -> np.ndarray:
        return quat_to_matrix(self.quat)

    @property
    def n_placements(self) -> int:
        """Number of poses the target can be placed at (its own plus :attr:`placements`)."""
        return 1 + len(self.placements)

    def pose(self, placement: int = 0) -> tuple:
        """``(center, quat)`` of placement ``placement`` (0: the target's own pose).

        Raises
        ------
        IndexError
            Unknown placement (the number of placements is given).
        """
        if not 0 <= placement < self.n_placements:
            raise OutOfRangeError(f"target '{self.name}' has {self.n_placements} placement(s) (0..{self.n_placements - 1}), "
                             f"not {placement}")
        if placement == 0:
            return self.center, self.quat
        c, q = self.placements[placement - 1]
        return np.asarray(c, float), np.asarray(q, float)

    @property
    def facing(self) -> np.ndarray:
        """Unit vector the target faces (its +x axis) in the scene frame."""
        return self.rotation[:, 0]

    def as_box(self) -> Box:
        """The target's box (one per target: boxes are immutable)."""
        return self._box

    @cached_property
    def _box(self) -> Box:
        return Box(name=self.name, center=self.center, size=self.size, quat=self.quat,
                   color=np.array([0.9, 0.7, 0.2, 1.0]))


@dataclass(frozen=True)
class GoalRegion:
    """A goal for the mobile base: a pose (x, y, theta) with tolerances, plus optional joint values."""

    name: str
    base: np.ndarray  # (3,) x, y, theta
    xy_tolerance: float = 0.1
    theta_tolerance: float = math.pi
    joints: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Problem:
    """A named start/goal query. ``start``/``goal`` map joint names (and base_x/base_y/base_theta) to values;
    ``goal_regions`` names goal regions instead of (or in addition to) a goal configuration.

    ``target`` is the monitored target; a problem written with ``targets: [a, b]`` keeps several in view together
    (their centroids' midpoint is the monitoring point, as in the paper's two-nurse task), and ``target`` is then
    the first of them."""

    name: str
    target: str
    start: dict
    goal: dict = field(default_factory=dict)
    goal_regions: tuple = ()
    targets: tuple = ()

    @property
    def all_targets(self) -> list:
        """Every monitored target: ``targets`` if the problem names several, else ``[target]``."""
        return list(self.targets) if self.targets else [self.target]


@dataclass(frozen=True)
class Scene:
    """A planning scene. Use :func:`load_scene` to read one from YAML."""

    name: str
    robot: str
    frame: str
    workspace: np.ndarray  # (2, 2): [[xmin, xmax], [ymin, ymax]] for the base
    obstacles: tuple
    targets: tuple
    goals: tuple = ()
    problems: tuple = ()
    source: str = ""

    # ---- queries -------------------------------------------------------------------------------------------------
    def target(self, name: str) -> Target:
        for t in self.targets:
            if t.name == name:
                return t
        raise UnknownNameError(f"scene '{self.name}' has no target '{name}' (targets: {', '.join(self.target_names)})")

    @property
    def target_names(self) -> list:
        return [t.name for t in self.targets]

    def obstacle(self, name: str) -> Box:
        for b in self.obstacles:
            if b.name == name:
                return b
        raise UnknownNameError(f"scene '{self.name}' has no obstacle '{name}'")

    def goal(self, name: str) -> GoalRegion:
        for g in self.goals:
            if g.name == name:
                return g
        raise UnknownNameError(f"scene '{self.name}' has no goal region '{name}'")

    def problem(self, name: str) -> Problem:
        for p in self.problems:
            if p.name == name:
                return p
        raise UnknownNameError(f"scene '{self.name}' has no problem '{name}'")

    def collision_boxes(self) -> list:
        """All boxes the robot must not touch: obstacles plus targets flagged as obstacles."""
        return list(self.obstacles) + [t.as_box() for t in self.targets if t.obstacle]

    # ---- updates (scenes are immutable; updates return a new scene) ----------------------------------------------
    def with_obstacle_pose(self, name: str, center, quat=None, turning: Optional[bool] = None) -> "Scene":
        """The scene with obstacle ``name`` at a new pose (``turning``: set :attr:`Box.turning`; None keeps it)."""
        self.obstacle(name)
        obs = tuple(
            replace(b, center=np.asarray(center, float), quat=b.quat if quat is None else np.asarray(quat, float),
                    turning=b.turning if turning is None else bool(turning))
            if b.name == name else b
            for b in self.obstacles
        )
        return replace(self, obstacles=obs)

    def with_target_pose(self, name: str, center, quat=None) -> "Scene":
        self.target(name)
        tgs = tuple(
            replace(t, center=np.asarray(center, float), quat=t.quat if quat is None else np.asarray(quat, float))
            if t.name == name else t
            for t in self.targets
        )
        return replace(self, targets=tgs)

    def with_placement(self, names, placement: int) -> "Scene":
        """The scene with each target of ``names`` moved to its placement ``placement`` (:meth:`Target.pose`).

        Raises
        ------
        KeyError
            Unknown target.
        IndexError
            A target without that placement.
        """
        scene = self
        for n in names:
            if placement:
                scene = scene.with_target_pose(n, *self.target(n).pose(placement))
            else:
                self.target(n)
        return scene

    def copy(self) -> "Scene":
        return copy.deepcopy(self)


# ------------------------------------------------------------------------------------------------------------------
# YAML loading
# ------------------------------------------------------------------------------------------------------------------
def _orientation(f: Fields) -> np.ndarray:
    if f.has("quat") and f.has("yaw"):
        raise f.error("quat", "give either 'yaw' or 'quat', not both")
    if f.has("quat"):
        q = np.array(f.vec("quat", 4))
        n = np.linalg.norm(q)
        if n < 1e-9:
            raise f.error("quat", "quaternion has zero norm")
        return q / n
    return yaw_to_quat(f.float("yaw", 0.0))


def _color(f: Fields, default) -> np.ndarray:
    c = f.vec("color", None, default=None)
    if c is None:
        return np.array(default, dtype=float)
    if len(c) == 3:
        c = tuple(c) + (1.0,)
    if len(c) != 4 or any(v < 0.0 or v > 1.0 for v in c):
        raise f.error("color", f"expected [r, g, b] or [r, g, b, a] in 0..1, got {list(c)}")
    return np.array(c)


def _parse_box(f: Fields) -> Box:
    f.check_keys(["name", "center", "size", "yaw", "quat", "color", "mesh", "turning"])
    return Box(
        name=f.str("name"),
        center=np.array(f.vec("center", 3)),
        size=np.array(f.vec("size", 3, positive=True)),
        quat=_orientation(f),
        color=_color(f, (0.6, 0.6, 0.6, 1.0)),
        mesh=f.str("mesh", None),
        turning=f.bool("turning", False),
    )


def _parse_placement(f: Fields) -> tuple:
    f.check_keys(["center", "yaw", "quat"])
    return np.array(f.vec("center", 3)), _orientation(f)


def _parse_target(f: Fields) -> Target:
    f.check_keys(["name", "class", "center", "size", "yaw", "quat", "appearance", "obstacle", "placements"])
    return Target(
        name=f.str("name"),
        detector_class=f.str("class"),
        center=np.array(f.vec("center", 3)),
        size=np.array(f.vec("size", 3, positive=True)),
        quat=_orientation(f),
        appearance=f.str("appearance", ""),
        obstacle=f.bool("obstacle", True),
        placements=tuple(_parse_placement(p) for p in f.sub_list("placements", [])),
    )


#: Depth (m) by which a target placement may sink into an obstacle: a box standing on a table top or hung on a wall
#: touches it.
PLACEMENT_CONTACT = 0.01


def _check_placements(path: str, targets: tuple, obstacles: tuple, workspace: np.ndarray) -> None:
    """Every extra placement of a target has its centre within 0.5 m of the workspace's footprint (walls stand just
    outside it) and overlaps no obstacle and no other target (at its own pose) by more than
    :data:`PLACEMENT_CONTACT`."""
    if not any(t.placements for t in targets):
        return  # nothing to check: no torch import for the common scene
    import torch

    others_all = list(obstacles) + [t.as_box() for t in targets]
    lo, hi = workspace[:, 0] - 0.5, workspace[:, 1] + 0.5
    for i, t in enumerate(targets):
        for k, (c, q) in enumerate(t.placements):
            key = f"targets[{i}].placements[{k}]"
            if np.any(c[:2] < lo) or np.any(c[:2] > hi):
                raise ConfigError(path, key, f"center {c.tolist()} is outside the workspace")
            others = [b for b in others_all if b.name != t.name]
            if not others:
                continue
            n = len(others)
            ca = torch.as_tensor(np.tile(c, (n, 1)))
            Ra = torch.as_tensor(np.tile(quat_to_matrix(q), (n, 1, 1)))
            ha = torch.as_tensor(np.tile(np.maximum(t.size / 2 - PLACEMENT_CONTACT, 1e-4), (n, 1)))
            cb = torch.as_tensor(np.stack([b.center for b in others]))
            Rb = torch.as_tensor(np.stack([b.rotation for b in others]))
            hb = torch.as_tensor(np.stack([b.half_extents for b in others]))
            hit = obb_overlap(ca, Ra, ha, cb, Rb, hb, eps=0.0).numpy()
            if hit.any():
                names = ", ".join(b.name for b, h in zip(others, hit) if h)
                raise ConfigError(path, key, f"target '{t.name}' placed at {c.tolist()} intersects {names}")


def _joint_map(f: Fields, key: str) -> dict:
    if not f.has(key):
        return {}
    raw = f.raw(key)
    if not isinstance(raw, dict):
        raise f.error(key, "expected a mapping of joint name -> value")
    sub = Fields(raw, f.source, f"{f.prefix}.{key}" if f.prefix else key)
    for k in raw:
        if not isinstance(k, str):
            raise sub.error(str(k), "joint names must be strings")
    return {k: sub.float(k) for k in raw}


def load_scene(path: str | Path) -> Scene:
    """Load and validate a scene YAML file.

    Raises
    ------
    ConfigError
        Naming the file and the field for malformed YAML, missing or non-finite values, duplicate names,
        and problems that refer to unknown targets or goal regions.
    """
    path = Path(path)
    f = Fields(load_yaml(path), str(path))
    f.check_keys(["name", "robot", "frame", "workspace", "obstacles", "targets", "goals", "problems", "description"])
    ws = f.sub("workspace")
    ws.check_keys(["x", "y"])
    workspace = np.array([ws.vec("x", 2), ws.vec("y", 2)])
    if np.any(workspace[:, 1] <= workspace[:, 0]):
        raise f.error("workspace", "each range must be [min, max] with min < max")
    obstacles = tuple(_parse_box(b) for b in f.sub_list("obstacles", []))
    targets = tuple(_parse_target(t) for t in f.sub_list("targets", []))
    goals = []
    for g in f.sub_list("goals", []):
        g.check_keys(["name", "base", "xy_tolerance", "theta_tolerance", "joints"])
        goals.append(GoalRegion(name=g.str("name"), base=np.array(g.vec("base", 3)),
                                xy_tolerance=g.float("xy_tolerance", 0.1, lo=0.0),
                                theta_tolerance=g.float("theta_tolerance", math.pi, lo=0.0),
                                joints=_joint_map(g, "joints")))
    problems = []
    for p in f.sub_list("problems", []):
        p.check_keys(["name", "target", "targets", "start", "goal", "goal_regions"])
        p.raw("start")  # required (may be an empty mapping only if written explicitly as {})
        regions = p.raw("goal_regions", [])
        if not isinstance(regions, list) or not all(isinstance(r, str) for r in regions):
            raise p.error("goal_regions", "expected a list of goal region names")
        several = p.raw("targets", None)
        if several is not None:
            if p.raw("target", None) is not None:
                raise p.error("targets", "give either 'target' or 'targets', not both")
            if not isinstance(several, list) or not several or not all(isinstance(t, str) for t in several):
                raise p.error("targets", "expected a non-empty list of target names")
            if len(set(several)) != len(several):
                raise p.error("targets", "a target is named twice")
        problems.append(Problem(name=p.str("name"), target=several[0] if several else p.str("target"),
                                start=_joint_map(p, "start"), goal=_joint_map(p, "goal"),
                                goal_regions=tuple(regions), targets=tuple(several or ())))
    for kind, items in (("obstacles", obstacles), ("targets", targets), ("goals", goals), ("problems", problems)):
        names = [i.name for i in items]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise f.error(kind, f"duplicate names: {', '.join(sorted(dup))}")
    shared = {b.name for b in obstacles} & {t.name for t in targets}
    if shared:  # collision_boxes() puts both in one list, looked up by name
        raise f.error("targets", f"names also used by obstacles: {', '.join(sorted(shared))}")
    _check_placements(str(path), targets, obstacles, workspace)
    target_names = {t.name for t in targets}
    goal_names = {g.name for g in goals}
    for i, p in enumerate(problems):
        for t in p.all_targets:
            if t not in target_names:
                key = "targets" if p.targets else "target"
                raise ConfigError(str(path), f"problems[{i}].{key}", f"unknown target '{t}'")
        for r in p.goal_regions:
            if r not in goal_names:
                raise ConfigError(str(path), f"problems[{i}].goal_regions", f"unknown goal region '{r}'")
        if not p.goal and not p.goal_regions:
            raise ConfigError(str(path), f"problems[{i}]", "needs a 'goal' or 'goal_regions'")
    return Scene(name=f.str("name"), robot=f.str("robot"), frame=f.str("frame", "map"), workspace=workspace,
                 obstacles=obstacles, targets=targets, goals=tuple(goals), problems=tuple(problems), source=str(path))
