"""pybullet reference model: the exact (mesh) collision check and FK that the batched torch code is tested against.

pybullet is also used to compute a robot's allowed self-collision matrix (ACM) by sampling, following the usual
rule (MoveIt setup assistant): a link pair is *allowed* (never checked) when the links are adjacent, when they touch
in the default configuration, when they touch in (almost) every sample, or when they never touch in any sample.
"""

from __future__ import annotations

import hashlib
import logging
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch

from ..collision import CollisionChecker
from ..geometry import matrix_to_quat
from ..paths import cache_dir
from ..robot import RobotModel, image_roll, load_acm
from ..robot.urdf import resolve_mesh
from ..yamlio import load_yaml

log = logging.getLogger(__name__)


def pybullet_urdf(robot: RobotModel) -> Path:
    """Derived URDF for pybullet: absolute mesh paths and virtual planar base joints (base_x, base_y, base_theta).

    Cached under the robot's hash and the URDF's location (the mesh paths written depend on it); a cached file that
    names a mesh no longer on disk (an install since moved or removed) is written again."""
    key = hashlib.sha256(f"{robot.hash()}\n{robot.urdf.path.resolve()}".encode()).hexdigest()[:16]
    out = cache_dir() / "urdf" / f"{robot.name}_{key}_pybullet.urdf"
    if out.is_file() and _meshes_on_disk(out):
        return out
    tree = ET.parse(robot.urdf.path)
    root = tree.getroot()
    for mesh in root.iter("mesh"):
        mesh.set("filename", str(resolve_mesh(mesh.get("filename"), robot.urdf.path)))
    for tag in ("gazebo", "transmission"):
        for el in list(root.findall(tag)):
            root.remove(el)
    if robot.mobile:
        inertial = ('<inertial><mass value="0.001"/><origin xyz="0 0 0"/>'
                    '<inertia ixx="1e-6" ixy="0" ixz="0" iyy="1e-6" iyz="0" izz="1e-6"/></inertial>')
        for name in ("psprm_world", "psprm_base_x", "psprm_base_y"):
            root.insert(0, ET.fromstring(f'<link name="{name}">{inertial}</link>'))
        chain = [("base_x", "psprm_world", "psprm_base_x", "prismatic", "1 0 0"),
                 ("base_y", "psprm_base_x", "psprm_base_y", "prismatic", "0 1 0"),
                 ("base_theta", "psprm_base_y", robot.urdf.root, "continuous", "0 0 1")]
        for name, parent, child, jtype, axis in chain:
            root.append(ET.fromstring(
                f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/><child link="{child}"/>'
                f'<origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="{axis}"/>'
                f'<limit lower="-1000" upper="1000" effort="1" velocity="1"/></joint>'))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tree.write(tmp)
    tmp.replace(out)
    return out


def _meshes_on_disk(path: Path) -> bool:
    """Whether every mesh a derived URDF names is a file (False for an unreadable URDF)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return False
    return all(Path(m.get("filename") or "").is_file() for m in root.iter("mesh"))


class PybulletWorld:
    """A pybullet DIRECT client holding one robot (with its meshes) and a scene's boxes.

    Parameters
    ----------
    robot : RobotModel
    boxes : iterable of psprm_core.scene.Box
        Collision obstacles (created as static box bodies).
    allowed_pairs : set of frozenset, optional
        Allowed self-collision pairs; defaults to the robot's ACM file.
    """

    def __init__(self, robot: RobotModel, boxes: Iterable = (), allowed_pairs: Optional[set] = None):
        import pybullet as p

        self.p = p
        self.robot = robot
        self.cid = p.connect(p.DIRECT)
        self.body = p.loadURDF(str(pybullet_urdf(robot)), useFixedBase=True,
                               flags=p.URDF_USE_SELF_COLLISION, physicsClientId=self.cid)
        n = p.getNumJoints(self.body, physicsClientId=self.cid)
        self.link_name = {-1: p.getBodyInfo(self.body, physicsClientId=self.cid)[0].decode()}
        self.joint_index = {}
        for i in range(n):
            info = p.getJointInfo(self.body, i, physicsClientId=self.cid)
            self.link_name[i] = info[12].decode()
            if info[2] != p.JOINT_FIXED:
                self.joint_index[info[1].decode()] = i
        self.link_index = {v: k for k, v in self.link_name.items()}
        self.allowed = load_acm(robot) if allowed_pairs is None else allowed_pairs
        # let pybullet skip allowed pairs itself (its fastest loop); contacts are still filtered below
        for pair in self.allowed:
            a, b = tuple(pair)
            if a in self.link_index and b in self.link_index:
                p.setCollisionFilterPair(self.body, self.body, self.link_index[a], self.link_index[b], 0,
                                         physicsClientId=self.cid)
        self.box_bodies = {}
        for b in boxes:
            self.add_box(b)
        self._order = list(self.joint_index)

    def add_box(self, box) -> None:
        p = self.p
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(box.half_extents), physicsClientId=self.cid)
        self.box_bodies[p.createMultiBody(0, shape, basePosition=list(box.center),
                                          baseOrientation=list(box.quat), physicsClientId=self.cid)] = box.name

    def close(self) -> None:
        if self.cid is not None:
            self.p.disconnect(self.cid)
            self.cid = None

    def __del__(self):  # pragma: no cover
        try:
            self.close()
        except Exception:
            pass

    def set_configuration(self, q: np.ndarray) -> None:
        values = self.robot.urdf_joint_values(q)
        if self.robot.mobile:
            values.update(base_x=q[0], base_y=q[1], base_theta=q[2])
        idx = [self.joint_index[k] for k in self._order]
        self.p.resetJointStatesMultiDof(self.body, idx, [[values[k]] for k in self._order], physicsClientId=self.cid)

    def contacts(self, q: np.ndarray) -> tuple:
        """(environment contact box names, self-contact link pairs not allowed) at configuration ``q``."""
        p = self.p
        self.set_configuration(q)
        p.performCollisionDetection(physicsClientId=self.cid)
        env, selfc = set(), set()
        for c in p.getContactPoints(bodyA=self.body, physicsClientId=self.cid):
            if c[8] >= 0:  # near miss inside the contact margin
                continue
            if c[2] == self.body:
                pair = frozenset((self.link_name[c[3]], self.link_name[c[4]]))
                if len(pair) == 2 and pair not in self.allowed:
                    selfc.add(pair)
            else:
                env.add(self.box_bodies.get(c[2], str(c[2])))
        return env, selfc

    def clearance(self, q: np.ndarray, up_to: float = 0.5) -> float:
        """Smallest distance (m) between the robot's collision meshes and the boxes at configuration ``q`` (negative:
        penetration), capped at ``up_to``."""
        p = self.p
        self.set_configuration(q)
        p.performCollisionDetection(physicsClientId=self.cid)
        d = up_to
        for b in self.box_bodies:
            for c in p.getClosestPoints(self.body, b, up_to, physicsClientId=self.cid):
                d = min(d, c[8])
        return float(d)

    def in_collision(self, qs: np.ndarray) -> np.ndarray:
        """Exact collision flags (B,) for configurations (B, dof): environment or non-allowed self contact."""
        out = np.zeros(len(qs), dtype=bool)
        for i, q in enumerate(qs):
            env, selfc = self.contacts(q)
            out[i] = bool(env or selfc)
        return out

    def camera_pose(self, q: np.ndarray) -> np.ndarray:
        """4x4 camera pose from pybullet's own FK: the camera link's frame turned by the configured image roll."""
        self.set_configuration(q)
        li = self.link_index[self.robot.config.camera_link]
        st = self.p.getLinkState(self.body, li, computeForwardKinematics=True, physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, :3] = np.array(self.p.getMatrixFromQuaternion(st[5])).reshape(3, 3)
        T[:3, 3] = st[4]
        return T @ image_roll(self.robot.config.camera_roll_deg)

    def link_poses(self, q: np.ndarray, links: Iterable[str]) -> np.ndarray:
        """4x4 world poses (L, 4, 4) of the URDF frames of ``links`` at configuration ``q``, from pybullet's own FK."""
        p = self.p
        self.set_configuration(q)
        links = list(links)
        idx = [self.link_index[name] for name in links]
        states = dict(zip([i for i in idx if i >= 0], p.getLinkStates(
            self.body, [i for i in idx if i >= 0], computeForwardKinematics=True, physicsClientId=self.cid) or []))
        out = np.tile(np.eye(4), (len(links), 1, 1))
        for k, i in enumerate(idx):
            if i >= 0:
                pos, quat = states[i][4:6]
            else:  # the base: pybullet places its inertial frame, the URDF frame is that times the inverse offset
                pos, quat = p.getBasePositionAndOrientation(self.body, physicsClientId=self.cid)
                inertial = p.getDynamicsInfo(self.body, -1, physicsClientId=self.cid)[3:5]
                pos, quat = p.multiplyTransforms(pos, quat, *p.invertTransform(*inertial))
            out[k, :3, :3] = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
            out[k, :3, 3] = pos
        return out


def compute_acm(robot: RobotModel, samples: int, seed: int = 0, always_fraction: float = 0.95) -> dict:
    """Sample ``samples`` random configurations and classify every colliding link pair (see module docstring).

    Returns a dict ready to be written as the robot's ACM YAML file (allowed pairs with their reason, statistics).
    """
    rng = np.random.default_rng(seed)
    world = PybulletWorld(robot, allowed_pairs=set())
    try:
        links = [l for l, g in robot.urdf.links.items() if g]
        adjacent = set()
        for j in robot.urdf.joints.values():  # adjacent = connected by a joint, looking through geometry-less links
            adjacent.add(frozenset((j.parent, j.child)))
        counts: dict = {}
        q0 = robot.default_configuration()
        _, default_pairs = world.contacts(q0)
        qs = sample_uniform(robot, samples, rng, base_box=np.array([[-1.0, 1.0], [-1.0, 1.0]]))
        for q in qs:
            _, pairs = world.contacts(q)
            for pr in pairs:
                counts[pr] = counts.get(pr, 0) + 1
    finally:
        world.close()
    allowed, checked = [], []
    import itertools

    for a, b in itertools.combinations(sorted(links), 2):
        pr = frozenset((a, b))
        n = counts.get(pr, 0)
        if pr in adjacent:
            reason = "adjacent"
        elif pr in default_pairs:
            reason = "default"
        elif n >= always_fraction * samples:
            reason = "always"
        elif n == 0:
            reason = "never"
        else:
            # the conservative box model must be able to check the pair: a pair whose bounding boxes already
            # overlap in the default configuration (parts nested in one assembly, e.g. a camera inside its
            # head bracket) would make every configuration invalid, so it is allowed instead.
            only = {frozenset(x) for x in itertools.combinations(links, 2)} - {pr}
            probe = CollisionChecker(robot, [], allowed_pairs=only)
            if bool(probe.check_detailed(torch.as_tensor(q0[None], dtype=torch.float64))["self"][0]):
                reason = "box model overlaps at default"
            else:
                checked.append({"pair": sorted(pr), "collision_rate": round(n / samples, 5)})
                continue
        allowed.append((sorted(pr), reason))
    return {
        "robot": robot.name,
        "samples": samples,
        "seed": seed,
        "rule": ("allowed = adjacent | colliding at default | colliding in >= 95% of samples | never colliding"
                 " | oriented bounding boxes overlap at default"),
        "allowed_pairs": [p for p, _ in allowed],
        "allowed_reasons": {f"{p[0]} {p[1]}": r for p, r in allowed},
        "checked_pairs": checked,
    }


def sample_uniform(robot: RobotModel, n: int, rng: np.random.Generator, base_box: Optional[np.ndarray] = None):
    """Uniform configurations within joint limits; base (x, y) in ``base_box`` [[xmin,xmax],[ymin,ymax]]."""
    lo, hi = robot.lower.copy(), robot.upper.copy()
    if robot.mobile:
        box = base_box if base_box is not None else np.array([[-1.0, 1.0], [-1.0, 1.0]])
        lo[:2], hi[:2] = box[:, 0], box[:, 1]
        lo[2], hi[2] = -np.pi, np.pi
    fin = np.isfinite(lo) & np.isfinite(hi)
    lo = np.where(fin, lo, -np.pi)
    hi = np.where(fin, hi, np.pi)
    return lo + rng.random((n, robot.dof)) * (hi - lo)


def pose_to_pos_quat(T: np.ndarray) -> tuple:
    return T[:3, 3].copy(), matrix_to_quat(T[:3, :3])
