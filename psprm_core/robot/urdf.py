"""A small URDF reader: links, joints and collision geometry, with ``package://`` and relative mesh resolution.

Only what planning needs is parsed (kinematic tree, limits, collision elements). Visual geometry is left to pybullet.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import RobotModelError
from ..geometry import make_transform, rpy_to_matrix


@dataclass
class CollisionGeom:
    """One ``<collision>`` element: ``kind`` in {box, cylinder, sphere, mesh}; ``origin`` 4x4 in the link frame."""

    kind: str
    origin: np.ndarray
    size: Optional[np.ndarray] = None  # box full extents
    radius: float = 0.0  # cylinder / sphere
    length: float = 0.0  # cylinder (along z)
    mesh: Optional[Path] = None
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))


@dataclass
class Joint:
    name: str
    type: str  # fixed, revolute, continuous, prismatic, floating, planar
    parent: str
    child: str
    origin: np.ndarray  # 4x4 parent-link -> joint frame
    axis: np.ndarray
    lower: float = -np.inf
    upper: float = np.inf
    velocity: float = np.inf
    mimic: Optional[tuple] = None  # (joint, multiplier, offset)

    @property
    def movable(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


@dataclass
class Urdf:
    name: str
    path: Path
    links: dict  # name -> list[CollisionGeom]
    joints: dict  # name -> Joint
    root: str

    def child_joints(self, link: str) -> list:
        return [j for j in self.joints.values() if j.parent == link]

    def parent_joint(self, link: str) -> Optional[Joint]:
        for j in self.joints.values():
            if j.child == link:
                return j
        return None

    def topological_joints(self) -> list:
        """Joints ordered so that every joint comes after the joint of its parent link."""
        out, stack = [], [self.root]
        while stack:
            link = stack.pop()
            for j in sorted(self.child_joints(link), key=lambda j: j.name):
                out.append(j)
                stack.append(j.child)
        return out


def _origin(el) -> np.ndarray:
    o = el.find("origin") if el is not None else None
    if o is None:
        return np.eye(4)
    xyz = [float(v) for v in o.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in o.get("rpy", "0 0 0").split()]
    return make_transform(rpy_to_matrix(rpy), xyz)


def resolve_mesh(filename: str, urdf_path: Path) -> Path:
    """Resolve ``package://pkg/rest`` (walking up from the URDF for a folder named ``pkg``) or a relative path."""
    if filename.startswith("file://"):
        return Path(filename[len("file://"):])
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://"):].partition("/")
        for parent in urdf_path.resolve().parents:
            if parent.name == pkg:
                return parent / rest
            if (parent / pkg).is_dir():
                return parent / pkg / rest
        raise RobotModelError(f"{urdf_path}: cannot resolve mesh '{filename}' (no folder '{pkg}' above the URDF)")
    p = Path(filename)
    return p if p.is_absolute() else (urdf_path.parent / p).resolve()


def find_mesh(filename: str, urdf_path: Path) -> Optional[Path]:
    """The existing file a mesh URI of a URDF at ``urdf_path`` names, or None (never raises).

    Tried in order: ``file://`` and absolute paths; ``package://pkg/rest`` by :func:`resolve_mesh` (a folder
    ``pkg`` above the URDF), then under ``share/pkg`` of every prefix on ``AMENT_PREFIX_PATH`` (a ROS 2 install;
    read from the environment, nothing of ROS imported) and in every ``pkg`` folder on ``ROS_PACKAGE_PATH``; a
    relative path next to the URDF."""
    import os

    candidates = []
    try:
        candidates.append(resolve_mesh(filename, urdf_path))
    except RobotModelError:
        pass
    if filename.startswith("package://"):
        pkg, _, rest = filename[len("package://"):].partition("/")
        for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
            if prefix:
                candidates.append(Path(prefix) / "share" / pkg / rest)
        for root in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep):
            if root:
                candidates.append(Path(root) / pkg / rest)
                if Path(root).name == pkg:
                    candidates.append(Path(root) / rest)
    for c in candidates:
        try:
            if c.is_file():
                return c
        except OSError:
            continue
    return None


def parse_urdf(path: str | Path) -> Urdf:
    """Parse a URDF file. Raises :class:`RobotModelError` naming the file on malformed input."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise RobotModelError(f"{path}: cannot read URDF: {exc}") from None
    links: dict = {}
    for link in root.findall("link"):
        geoms = []
        for col in link.findall("collision"):
            g = col.find("geometry")
            if g is None or len(g) == 0:
                continue
            shape = g[0]
            origin = _origin(col)
            if shape.tag == "box":
                geoms.append(CollisionGeom("box", origin, size=np.array([float(v) for v in shape.get("size").split()])))
            elif shape.tag == "cylinder":
                geoms.append(CollisionGeom("cylinder", origin, radius=float(shape.get("radius")),
                                           length=float(shape.get("length"))))
            elif shape.tag == "sphere":
                geoms.append(CollisionGeom("sphere", origin, radius=float(shape.get("radius"))))
            elif shape.tag == "mesh":
                scale = np.array([float(v) for v in shape.get("scale", "1 1 1").split()])
                geoms.append(CollisionGeom("mesh", origin, mesh=resolve_mesh(shape.get("filename"), path),
                                           scale=scale))
        links[link.get("name")] = geoms
    joints = {}
    for j in root.findall("joint"):
        axis_el = j.find("axis")
        axis = np.array([float(v) for v in axis_el.get("xyz").split()]) if axis_el is not None else np.array([1.0, 0, 0])
        if np.linalg.norm(axis) > 0:
            axis = axis / np.linalg.norm(axis)
        lim = j.find("limit")
        mimic = j.find("mimic")
        jt = Joint(
            name=j.get("name"), type=j.get("type"), parent=j.find("parent").get("link"),
            child=j.find("child").get("link"), origin=_origin(j), axis=axis,
            lower=float(lim.get("lower", "-inf")) if lim is not None else -np.inf,
            upper=float(lim.get("upper", "inf")) if lim is not None else np.inf,
            velocity=float(lim.get("velocity", "inf")) if lim is not None else np.inf,
            mimic=(mimic.get("joint"), float(mimic.get("multiplier", 1)), float(mimic.get("offset", 0)))
            if mimic is not None else None,
        )
        if jt.type == "continuous" or (jt.type == "revolute" and lim is None):
            jt.lower, jt.upper = -np.inf, np.inf
        joints[jt.name] = jt
    children = {j.child for j in joints.values()}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise RobotModelError(f"{path}: expected one root link, found {roots}")
    return Urdf(name=root.get("name", path.stem), path=path, links=links, joints=joints, root=roots[0])
