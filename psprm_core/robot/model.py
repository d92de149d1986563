"""The robot model (:class:`RobotModel`): a robot config with its URDF, the bodies forward kinematics walks, their
collision spheres and boxes, batched forward kinematics of bodies, camera and links, and the camera's Jacobian. The
package's docstring says what a planning configuration is."""

from __future__ import annotations

import hashlib
import math
from functools import cached_property
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import ConfigError, InputError, RobotModelError, UnknownNameError
from ..geometry import axis_angle_matrix_torch
from ..kernels._fast_packs import PRISMATIC, REVOLUTE, ROOT, RobotPack
from ..kernels.arrays import as_f64, as_i64
from ..kernels.compute import Computing
from ..yamlio import load_yaml
from .bodies import ElementModel, SphereModel, _geom_local_box, _grid_spheres
from .config import BASE_JOINTS, RobotConfig, description_urdf, image_roll, load_robot_config, urdf_path_for
from .urdf import Urdf, parse_urdf


def add_base_twists(W: torch.Tensor, q: torch.Tensor) -> None:
    """Add a differential-drive base's world twists ``[omega, v0]`` to camera twists ``W`` (B, dof, 6) in place: x and
    y are prismatic along the world axes, theta revolute about z through ``(x, y, 0)``."""
    W[:, 0, 3] += 1.0
    W[:, 1, 4] += 1.0
    W[:, 2, 2] += 1.0
    W[:, 2, 3] += q[:, 1]  # (x, y, 0) x e_z = (y, -x, 0)
    W[:, 2, 4] -= q[:, 0]


def load_acm(robot: RobotModel) -> set:
    """Allowed self-collision link pairs (frozensets) from the robot's ACM file; empty set if none is configured."""
    cfg = robot.config.collision
    if not cfg.acm_file:
        return set()
    path = Path(robot.config.source).parent / cfg.acm_file
    if not path.is_file():
        raise ConfigError(robot.config.source, "collision.acm_file",
                          f"{path} not found (generate it with `psprm robot acm --robot {robot.name}`)")
    data = load_yaml(path)
    return {frozenset(p) for p in data.get("allowed_pairs", [])}


class RobotModel(Computing):
    """Kinematic + collision model of one robot. Build with :meth:`load`; cheap to query, heavy to build.

    Attributes
    ----------
    config : RobotConfig
    urdf : Urdf
    joint_names : list[str]
        Planning joint names in ``q`` order (base joints first for a mobile base).
    lower, upper : ndarray (dof,)
        Joint limits (base x/y: +-inf here, bounded by the scene's workspace; theta: +-inf, wrapped).
    """

    def __init__(self, config: RobotConfig, urdf: Urdf):
        self.config = config
        self.urdf = urdf
        self.name = config.name
        self.mobile = config.base.type == "diff_drive"
        self.base_dof = 3 if self.mobile else 0
        self.joint_names = (list(BASE_JOINTS) if self.mobile else []) + [j.name for j in config.joints]
        self.dof = len(self.joint_names)
        lo = ([-np.inf] * 3 if self.mobile else []) + [j.lower for j in config.joints]
        hi = ([np.inf] * 3 if self.mobile else []) + [j.upper for j in config.joints]
        self.lower = np.array(lo, dtype=float)
        self.upper = np.array(hi, dtype=float)
        self.continuous = np.array(([False, False, True] if self.mobile else []) + [j.continuous for j in config.joints])
        self.velocity = np.array(([config.base.linear_velocity] * 2 + [config.base.angular_velocity] if self.mobile
                                  else []) + [j.velocity for j in config.joints])
        self.acceleration = np.array(([config.base.linear_acceleration] * 2 + [config.base.angular_acceleration]
                                      if self.mobile else []) + [j.acceleration for j in config.joints])
        self._build_bodies()
        if config.camera_link not in urdf.links:
            raise RobotModelError(
                f"{config.source}: field 'camera.link': URDF {urdf.path.name} has no link '{config.camera_link}'")
        self.camera_body = self.link_body[config.camera_link]
        self.camera_offset = self.link_in_body[config.camera_link] @ image_roll(config.camera_roll_deg)
        self._tensor_cache: dict = {}

    # ---- construction ------------------------------------------------------------------------------------------
    @classmethod
    def load(cls, name_or_path: str, urdf_text: Optional[str] = None,
             origin: str = "robot description") -> "RobotModel":
        """Load a robot by config name (``stretch2``) or YAML path; raises PsprmError subclasses on bad input.

        With ``urdf_text`` (a robot's own URDF, e.g. from ``/robot_description``), the model is built from that text
        instead of the config's packaged URDF: :meth:`from_description`."""
        cfg = load_robot_config(name_or_path)
        if urdf_text is not None:
            return cls.from_description(cfg, urdf_text, origin)
        urdf = parse_urdf(urdf_path_for(cfg))
        return cls(cfg, urdf)

    @classmethod
    def from_description(cls, config: RobotConfig, urdf_text: str,
                         origin: str = "robot description") -> "RobotModel":
        """The robot model of ``config`` built from a URDF given as text (a calibrated unit's own description).

        The text is checked against the config before anything is built (planning joints' URDF joints, fixed
        joints, camera link, the collision model's links, the root link): a mismatch raises
        :class:`RobotModelError` naming what is missing and the config field that asked for it. Mesh URIs are
        resolved from the packaged URDF's location or by file name among its meshes; visual meshes that are not
        found are left out, a collision mesh that is not found is an error (the collision model needs it).
        ``origin`` names the text in messages (a topic name). See
        :func:`~psprm_core.robot.config.description_urdf`."""
        path = description_urdf(config, urdf_text, origin)
        try:
            urdf = parse_urdf(path)
        except (AttributeError, TypeError, ValueError) as exc:  # a tag without its attributes / a bad number
            raise RobotModelError(f"{origin}: malformed URDF ({path}): {exc!r}") from None
        return cls(config, urdf)

    def _build_bodies(self) -> None:
        cfg, urdf = self.config, self.urdf
        drive = {}  # urdf joint -> list of (planning index, coeff)
        for i, pj in enumerate(cfg.joints):
            for uj, coeff in pj.drives:
                if uj not in urdf.joints:
                    raise ConfigError(cfg.source, f"joints[{i}].drives",
                                      f"URDF {urdf.path.name} has no joint '{uj}'")
                if not urdf.joints[uj].movable:
                    raise ConfigError(cfg.source, f"joints[{i}].drives", f"URDF joint '{uj}' is not movable")
                drive.setdefault(uj, []).append((self.base_dof + i, coeff))
        for k in cfg.fixed_joints:
            if k not in urdf.joints:
                raise ConfigError(cfg.source, f"fixed_joints.{k}", f"URDF {urdf.path.name} has no joint '{k}'")
        for j in urdf.joints.values():  # mimic joints follow their leader
            if j.mimic and j.mimic[0] in drive:
                drive[j.name] = [(i, c * j.mimic[1]) for i, c in drive[j.mimic[0]]]
        self.urdf_drives = drive
        bodies = [urdf.root]
        parent_body, joint_of_body = [-1], [None]
        link_body = {urdf.root: 0}
        link_in_body = {urdf.root: np.eye(4)}
        body_joint_offset = [np.eye(4)]
        for j in urdf.topological_joints():
            pb = link_body[j.parent]
            t_pb_parent = link_in_body[j.parent]
            if j.name in drive:
                bodies.append(j.child)
                parent_body.append(pb)
                joint_of_body.append(j)
                body_joint_offset.append(t_pb_parent @ j.origin)
                link_body[j.child] = len(bodies) - 1
                link_in_body[j.child] = np.eye(4)
            else:
                value = cfg.fixed_joints.get(j.name, 0.0)
                if j.mimic:
                    value = cfg.fixed_joints.get(j.mimic[0], 0.0) * j.mimic[1] + j.mimic[2]
                link_body[j.child] = pb
                link_in_body[j.child] = t_pb_parent @ j.origin @ _joint_motion_np(j, value)
        self.bodies = bodies
        self.parent_body = parent_body
        self.body_joint = joint_of_body
        self.body_joint_offset = body_joint_offset
        self.link_body = link_body
        self.link_in_body = link_in_body
        # drive matrix: urdf joint value of body b = q @ D[:, b] + offset[b]
        D = np.zeros((self.dof, len(bodies)))
        off = np.zeros(len(bodies))
        for b, j in enumerate(joint_of_body):
            if j is None:
                continue
            for i, c in drive[j.name]:
                D[i, b] += c
            if j.mimic and j.mimic[0] in drive:
                off[b] = j.mimic[2]
        self.drive_matrix, self.drive_offset = D, off

    def urdf_joint_values(self, q: np.ndarray) -> dict:
        """URDF joint name -> value for one planning configuration (all movable URDF joints)."""
        q = np.asarray(q, float)
        out = {}
        for j in self.urdf.joints.values():
            if not j.movable:
                continue
            if j.name in self.urdf_drives:
                out[j.name] = float(sum(q[i] * c for i, c in self.urdf_drives[j.name]))
                if j.mimic:
                    out[j.name] += j.mimic[2]
            else:
                out[j.name] = self.config.fixed_joints.get(j.name, 0.0)
        return out

    # ---- defaults and sampling -----------------------------------------------------------------------------------
    def default_configuration(self) -> np.ndarray:
        q = np.zeros(self.dof)
        for i, name in enumerate(self.joint_names):
            if i >= self.base_dof:
                q[i] = np.clip(0.0, self.lower[i], self.upper[i])
            if name in self.config.default:
                q[i] = self.config.default[name]
        return q

    def configuration(self, values: dict, base: Optional[np.ndarray] = None) -> np.ndarray:
        """Planning vector from a partial ``{joint: value}`` mapping (others from the default configuration)."""
        q = self.default_configuration()
        for k, v in values.items():
            if k not in self.joint_names:
                raise UnknownNameError(f"robot '{self.name}' has no planning joint '{k}' (joints: {', '.join(self.joint_names)})")
            q[self.joint_names.index(k)] = v
        return q

    def index(self, joint: str) -> int:
        return self.joint_names.index(joint)

    # ---- spheres -------------------------------------------------------------------------------------------------
    @cached_property
    def spheres(self) -> SphereModel:
        cfg = self.config.collision
        names, link_body, centers, radii, sl = [], [], [], [], []
        for link, geoms in self.urdf.links.items():
            if not geoms or link in cfg.ignore_links or link not in self.link_body:
                continue
            li = len(names)
            names.append(link)
            link_body.append(self.link_body[link])
            for g in geoms:
                t = self.link_in_body[link] @ g.origin
                if g.kind == "sphere":
                    c, r = np.zeros((1, 3)), np.array([g.radius + cfg.padding])
                else:
                    lo, hi = _geom_local_box(g)
                    c, r = _grid_spheres(lo, hi, cfg.max_sphere_radius, cfg.padding)
                centers.append(c @ t[:3, :3].T + t[:3, 3])
                radii.append(r)
                sl.append(np.full(len(r), li))
        centers = np.concatenate(centers)
        radii = np.concatenate(radii)
        sl = np.concatenate(sl)
        order = np.argsort(sl, kind="stable")
        return SphereModel(names, np.array(link_body), centers[order], radii[order], sl[order])

    @cached_property
    def elements(self) -> ElementModel:
        cfg = self.config.collision
        names, el_link, el_body, centers, rots, halves = [], [], [], [], [], []
        for link, geoms in self.urdf.links.items():
            if not geoms or link in cfg.ignore_links or link not in self.link_body:
                continue
            names.append(link)
            for g in geoms:
                t = self.link_in_body[link] @ g.origin
                if g.kind == "sphere":
                    lo, hi = -np.full(3, g.radius), np.full(3, g.radius)
                else:
                    lo, hi = _geom_local_box(g)
                el_link.append(len(names) - 1)
                el_body.append(self.link_body[link])
                centers.append(t[:3, :3] @ (0.5 * (lo + hi)) + t[:3, 3])
                rots.append(t[:3, :3])
                halves.append(0.5 * (hi - lo) + cfg.padding)
        return ElementModel(names, np.array(el_link), np.array(el_body), np.array(centers), np.array(rots),
                            np.array(halves))

    # ---- batched FK ----------------------------------------------------------------------------------------------
    def tensors(self, device, dtype=torch.float32) -> dict:
        """Constant tensors of the model on ``device`` (cached per device/dtype)."""
        key = (str(device), dtype)
        if key not in self._tensor_cache:
            t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
            offs = np.stack(self.body_joint_offset)
            axes = np.stack([j.axis if j is not None else np.zeros(3) for j in self.body_joint])
            self._tensor_cache[key] = {
                "R_off": t(offs[:, :3, :3]), "t_off": t(offs[:, :3, 3]), "axis": t(axes),
                "D": t(self.drive_matrix), "off": t(self.drive_offset),
                "cam_R": t(self.camera_offset[:3, :3]), "cam_t": t(self.camera_offset[:3, 3]),
            }
        return self._tensor_cache[key]

    @cached_property
    def kernel_pack(self):
        """The body tree and camera as the compiled kernels take them (:mod:`psprm_core.kernels.fastpath`): a
        :class:`~psprm_core.kernels._fast_packs.RobotPack` of the bodies in FK order (root excluded), the camera chain
        (root excluded), parent bodies, joint types, joint origins, axes, drive matrix and offset (float64, int64; the
        quantities of :meth:`tensors` and :meth:`_poses`), the mobile-base flag and the camera body with its offset
        (:meth:`_camera_from_body`). Built on first use and kept: the body tree does not change."""
        jtype = np.array([ROOT if j is None else (PRISMATIC if j.type == "prismatic" else REVOLUTE)
                          for j in self.body_joint], dtype=np.int64)
        offs = np.stack(self.body_joint_offset)
        axes = np.stack([j.axis if j is not None else np.zeros(3) for j in self.body_joint])
        f64, i64 = as_f64, as_i64
        return RobotPack(np.arange(1, len(self.bodies), dtype=np.int64), i64(self.camera_chain[1:]),
                         i64(self.parent_body), jtype, f64(offs[:, :3, :3]), f64(offs[:, :3, 3]), f64(axes),
                         f64(self.drive_matrix), f64(self.drive_offset), bool(self.mobile), int(self.camera_body),
                         f64(self.camera_offset[:3, :3]), f64(self.camera_offset[:3, 3]))

    @cached_property
    def camera_chain(self) -> list:
        """Bodies from the root to the camera's body (the only ones camera-only FK needs)."""
        chain, b = [], self.camera_body
        while b >= 0:
            chain.append(b)
            b = self.parent_body[b]
        return chain[::-1]

    def body_poses(self, q: torch.Tensor, only: Optional[list] = None) -> tuple:
        """World rotation (B, NB, 3, 3) and translation (B, NB, 3) of every body for configurations ``q`` (B, dof).

        The base pose composes T = Trans(x, y, 0) Rz(theta) with the URDF root; every driven joint then applies
        ``T_child = T_parent T_origin Motion(axis, value)`` (a rotation for revolute/continuous joints, a translation
        for prismatic ones). With ``only`` (a root-first chain of bodies, e.g. :attr:`camera_chain`), only those
        bodies are computed; the others are left as zeros.
        """
        Rs, ts = self._poses(q, only)
        if only is not None:
            zR = torch.zeros(q.shape[0], 3, 3, dtype=q.dtype, device=q.device)
            zt = torch.zeros(q.shape[0], 3, dtype=q.dtype, device=q.device)
            Rs = [r if r is not None else zR for r in Rs]
            ts = [x if x is not None else zt for x in ts]
        return torch.stack(Rs, 1), torch.stack(ts, 1)

    @cached_property
    def element_corners_local(self) -> tuple:
        """(corners (E, 8, 3) of every collision box (:attr:`elements`) in its body's frame, float64; each box's
        body (E,), int64): the constant inputs of :meth:`element_corners`."""
        el = self.elements
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        local = el.center[:, None, :] + np.einsum("eij,ekj->eki", el.rotation, signs[None] * el.half[:, None, :])
        return np.ascontiguousarray(local), as_i64(el.element_body)

    def element_corners(self, Q) -> np.ndarray:
        """World positions (M, 8E, 3), float64, of the corners of every collision box at configurations ``Q``
        (M, dof): box e's corners are rows 8e .. 8e + 7 (:attr:`element_corners_local` moved by its body's pose,
        :meth:`body_poses`), by this model's :class:`~psprm_core.kernels.compute.Compute` (compiled: the path
        tolerance (:mod:`psprm_core.tracking`) asks for a few to a few hundred configurations at a time, where torch's
        per-operator cost dominates)."""
        Q = np.ascontiguousarray(np.asarray(Q, dtype=np.float64).reshape(-1, self.dof))
        if not np.isfinite(Q).all():
            raise InputError("configurations for the corner positions must be finite")
        return self.compute.ops.element_corners(self, Q)

    def element_corners_torch(self, Q: np.ndarray) -> np.ndarray:
        """:meth:`element_corners` of finite configurations ``Q`` (M, dof) float64, in torch on the CPU."""
        local, body = self.element_corners_local
        with torch.no_grad():
            R, t = self.body_poses(torch.as_tensor(Q, dtype=torch.float64))
        R, t = R.numpy(), t.numpy()
        # (M, E, 8, 3): each box's body rotation (M, E, 3, 3) applied to its corners, plus the body's position
        world = np.einsum("meij,ekj->meki", R[:, body], local) + t[:, body][:, :, None, :]
        return world.reshape(len(Q), -1, 3)

    def _poses(self, q: torch.Tensor, only: Optional[list] = None) -> tuple:
        """Lists of world rotations (B, 3, 3) and translations (B, 3) per body (None outside ``only``)."""
        if q.dim() != 2 or q.shape[1] != self.dof:
            raise InputError(f"expected q of shape (B, {self.dof}), got {tuple(q.shape)}")
        T = self.tensors(q.device, q.dtype)
        B = q.shape[0]
        if self.mobile:
            c, s = torch.cos(q[:, 2]), torch.sin(q[:, 2])
            z, o = torch.zeros_like(c), torch.ones_like(c)
            R0 = torch.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(B, 3, 3)
            t0 = torch.stack([q[:, 0], q[:, 1], z], -1)
        else:
            R0 = torch.eye(3, dtype=q.dtype, device=q.device).expand(B, 3, 3)
            t0 = torch.zeros(B, 3, dtype=q.dtype, device=q.device)
        values = q @ T["D"] + T["off"]
        Rs, ts = [R0] + [None] * (len(self.bodies) - 1), [t0] + [None] * (len(self.bodies) - 1)
        for b in (only[1:] if only is not None else range(1, len(self.bodies))):
            j = self.body_joint[b]
            Rp, tp = Rs[self.parent_body[b]], ts[self.parent_body[b]]
            Rj = Rp @ T["R_off"][b]
            tj = tp + (Rp @ T["t_off"][b].unsqueeze(-1)).squeeze(-1)
            v = values[:, b]
            if j.type == "prismatic":
                Rs[b], ts[b] = Rj, tj + (Rj @ T["axis"][b]) * v.unsqueeze(-1)
            else:
                Rs[b], ts[b] = Rj @ axis_angle_matrix_torch(T["axis"][b], v), tj
        return Rs, ts

    def camera_poses(self, q: torch.Tensor, body_poses: Optional[tuple] = None) -> torch.Tensor:
        """Camera optical-frame poses (B, 4, 4) in the scene frame of configurations ``q`` (B, dof), or from the
        body poses of :meth:`body_poses` when given; by this model's ``compute``."""
        return self.compute.ops.camera_poses(self, q, body_poses)

    def camera_poses_torch(self, q: torch.Tensor, body_poses: Optional[tuple] = None) -> torch.Tensor:
        """:meth:`camera_poses` in torch (any device, autograd)."""
        if body_poses is not None:
            Rb, tb = body_poses[0][:, self.camera_body], body_poses[1][:, self.camera_body]
        else:  # the camera chain only
            Rs, ts = self._poses(q, only=self.camera_chain)
            Rb, tb = Rs[self.camera_body], ts[self.camera_body]
        return self._camera_from_body(Rb, tb)

    def _camera_from_body(self, Rb: torch.Tensor, tb: torch.Tensor) -> torch.Tensor:
        """Optical-frame poses (B, 4, 4) from the camera body's world rotation (B, 3, 3) and translation (B, 3)."""
        T = self.tensors(Rb.device, Rb.dtype)
        out = torch.zeros(Rb.shape[0], 4, 4, dtype=Rb.dtype, device=Rb.device)
        out[:, :3, :3] = Rb @ T["cam_R"]
        out[:, :3, 3] = tb + (Rb @ T["cam_t"].unsqueeze(-1)).squeeze(-1)
        out[:, 3, 3] = 1
        return out

    def camera_jacobian(self, q: torch.Tensor) -> tuple:
        """Camera pose and its spatial Jacobian from one camera-chain forward kinematics pass.

        Column i of the Jacobian is the world twist ``(omega_i, v0_i)`` that a unit rate of planning joint i gives
        the camera's body: a world point x rigidly attached to the camera moves with ``omega_i x x + v0_i``. A
        revolute joint with world axis a through o contributes ``(a, o x a)``, a prismatic one ``(0, a)``; the
        mobile base's x / y are prismatic along the world axes and theta revolute about z through (x, y, 0). Mimic
        couplings enter through the drive matrix D (body value = q D + offset).

        Returns
        -------
        T : (B, 4, 4) camera optical-frame poses (as :meth:`camera_poses`).
        W : (B, dof, 6) twists ``[omega, v0]`` per planning joint (zero for joints that do not move the camera).
        """
        Rs, ts = self._poses(q, only=self.camera_chain)
        tens = self.tensors(q.device, q.dtype)
        B, dev, dt = q.shape[0], q.device, q.dtype
        T = self._camera_from_body(Rs[self.camera_body], ts[self.camera_body])
        chain = [b for b in self.camera_chain[1:] if self.body_joint[b] is not None]
        W = torch.zeros(B, self.dof, 6, dtype=dt, device=dev)
        if chain:
            idx = torch.as_tensor(chain, device=dev)
            a = (torch.stack([Rs[b] for b in chain], 1) @ tens["axis"][idx].unsqueeze(-1)).squeeze(-1)  # world axes
            prism = torch.as_tensor([self.body_joint[b].type == "prismatic" for b in chain], device=dev)
            omega = torch.where(prism[:, None], torch.zeros_like(a), a)
            v0 = torch.where(prism[:, None], a, torch.linalg.cross(torch.stack([ts[b] for b in chain], 1), a))
            # planning joint i drives body b with rate D[i, b]
            W = W + torch.einsum("ib,Bbk->Bik", tens["D"][:, idx], torch.cat([omega, v0], -1))
        if self.mobile:
            add_base_twists(W, q)
        return T, W

    def link_poses(self, q: torch.Tensor, links: list) -> torch.Tensor:
        """Poses (B, len(links), 4, 4) of named links (any link of the URDF)."""
        R, t = self.body_poses(q)
        out = torch.zeros(q.shape[0], len(links), 4, 4, dtype=q.dtype, device=q.device)
        for i, name in enumerate(links):
            if name not in self.link_body:
                raise RobotModelError(f"robot '{self.name}' has no link '{name}'")
            b = self.link_body[name]
            off = torch.as_tensor(self.link_in_body[name], dtype=q.dtype, device=q.device)
            out[:, i, :3, :3] = R[:, b] @ off[:3, :3]
            out[:, i, :3, 3] = t[:, b] + (R[:, b] @ off[:3, 3].unsqueeze(-1)).squeeze(-1)
            out[:, i, 3, 3] = 1
        return out

    def sphere_centers(self, q: torch.Tensor, body_poses: Optional[tuple] = None) -> torch.Tensor:
        """World centres (B, S, 3) of all collision spheres (radii: ``self.spheres.radii``)."""
        R, t = body_poses if body_poses is not None else self.body_poses(q)
        sm = self.spheres
        c = torch.as_tensor(sm.centers, dtype=q.dtype, device=q.device)
        body = torch.as_tensor(sm.link_body[sm.sphere_link], device=q.device)
        return torch.einsum("bsij,sj->bsi", R[:, body], c) + t[:, body]

    def hash(self) -> str:
        """Hash of the robot config and URDF (for caches and saved roadmaps)."""
        h = hashlib.sha256(Path(self.config.source).read_bytes())
        h.update(self.urdf.path.read_bytes())
        return h.hexdigest()[:16]


def _joint_motion_np(j, value: float) -> np.ndarray:
    t = np.eye(4)
    if j.type == "prismatic":
        t[:3, 3] = j.axis * value
    elif j.type in ("revolute", "continuous"):
        a = j.axis
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        t[:3, :3] = np.eye(3) + math.sin(value) * K + (1 - math.cos(value)) * K @ K
    return t
