"""Kinematics from pytorch-kinematics: a robot's URDF as ``pk`` chains, a second, independent implementation of the
robot model's FK (whose URDF reader and chain code are psprm's own), device- and dtype-agnostic like the rest of the
torch code.

* :class:`PKCameraKinematics`: the camera chain, ``pk.SerialChain`` from the URDF's root link to the camera link
  (``pk.build_serial_chain_from_urdf``): :meth:`RobotModel.camera_poses` and :meth:`RobotModel.camera_jacobian`;
* :class:`PKBodyKinematics`: the whole tree (``pk.build_chain_from_urdf``): :meth:`RobotModel.body_poses`, the
  world poses of the rigid bodies the collision model is attached to (a
  :class:`~psprm_core.collision.CollisionChecker` made with ``kinematics=`` runs its torch path on them).

Both are built from the same URDF file the robot model parses and share :class:`PKChainMap`:

* planning joints drive chain joints through the robot's drive couplings (Stretch's four telescoping arm joints,
  mimic joints): chain value = ``q @ M + offset``; chain joints no planning joint drives sit at the robot config's
  ``fixed_joints`` values (:func:`chain_coupling`);
* a mobile base's ``x, y, theta`` place the URDF root in the scene: a prismatic x / y along the world axes and a
  revolute theta about z through ``(x, y, 0)``.

The camera's optical frame is the camera link turned by the config's image roll (a rotation: same origin). Its
Jacobian is ``chain.jacobian`` (linear and angular velocity of the camera link's origin per chain joint, in the
root frame), mapped to planning joints by ``M`` and expressed as the spatial twists ``[omega, v0]`` that
:meth:`RobotModel.camera_jacobian` returns (``v0 = v_p - omega x p``: the velocity of the world point at the origin
moving with the camera).
"""

from __future__ import annotations

import contextlib
import io
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import InputError, RobotModelError
from . import add_base_twists, image_roll


def chain_coupling(robot, joint_names: list) -> tuple:
    """``(M, offset)`` (numpy, (dof, n) and (n,)) that give the values of the chain joints ``joint_names`` from
    planning configurations: ``q @ M + offset``. A driven joint follows its planning joints' drive coefficients (a
    mimic follower's offset added); any other joint is held at its ``fixed_joints`` value (a mimic follower of a held
    joint at the leader's value times the multiplier plus the offset)."""
    cfg, urdf = robot.config, robot.urdf
    M = np.zeros((robot.dof, len(joint_names)))
    off = np.zeros(len(joint_names))
    for k, name in enumerate(joint_names):
        j = urdf.joints[name]
        if name in robot.urdf_drives:
            for i, c in robot.urdf_drives[name]:
                M[i, k] += c
            if j.mimic:
                off[k] = j.mimic[2]
        elif j.mimic:
            off[k] = cfg.fixed_joints.get(j.mimic[0], 0.0) * j.mimic[1] + j.mimic[2]
        else:
            off[k] = cfg.fixed_joints.get(name, 0.0)
    return M, off


class PKChainMap:
    """A pytorch-kinematics chain of ``robot``'s URDF on ``device`` / ``dtype`` and the map from planning
    configurations to its joint values (:func:`chain_coupling`) and to the pose of its root in the scene.

    ``build(pk, urdf_bytes)`` makes the chain; ``what`` names it in the error raised when it cannot be built."""

    def __init__(self, robot, build: Callable, what: str, device="cpu", dtype: torch.dtype = torch.float64):
        try:
            import pytorch_kinematics as pk
        except ImportError as exc:  # pragma: no cover - a pinned requirement
            raise RobotModelError(f"pytorch-kinematics is not installed: {exc}") from exc
        self.robot, self.device, self.dtype = robot, torch.device(device), dtype
        urdf = robot.urdf
        try:
            # its URDF parser reports every tag it does not model (transmissions, gazebo) on stderr: not errors
            with contextlib.redirect_stderr(io.StringIO()):
                chain = build(pk, urdf.path.read_bytes())
        except Exception as exc:
            raise RobotModelError(f"{urdf.path.name}: pytorch-kinematics cannot build the chain {what}: {exc}") from exc
        self.chain = chain.to(dtype=dtype, device=self.device)
        self.joint_names = list(self.chain.get_joint_parameter_names())
        M, off = chain_coupling(robot, self.joint_names)
        self.M = torch.as_tensor(M, dtype=dtype, device=self.device)
        self.offset = torch.as_tensor(off, dtype=dtype, device=self.device)

    def _chain_values(self, q: torch.Tensor) -> torch.Tensor:
        return q.to(self.device, self.dtype) @ self.M + self.offset

    def _base(self, q: torch.Tensor) -> Optional[torch.Tensor]:
        """(B, 4, 4) pose of the URDF root in the scene (None for a fixed base: the root is the scene frame)."""
        if not self.robot.mobile:
            return None
        q = q.to(self.device, self.dtype)
        c, s = torch.cos(q[:, 2]), torch.sin(q[:, 2])
        T = torch.zeros(q.shape[0], 4, 4, dtype=self.dtype, device=self.device)
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
        T[:, 2, 2] = T[:, 3, 3] = 1.0
        T[:, 0, 3], T[:, 1, 3] = q[:, 0], q[:, 1]
        return T


class PKCameraKinematics(PKChainMap):
    """``kin = PKCameraKinematics(robot, device, dtype)``; ``kin.camera_poses(q)``, ``kin.camera_jacobian(q)``."""

    def __init__(self, robot, device="cpu", dtype: torch.dtype = torch.float64):
        cfg, root = robot.config, robot.urdf.root
        super().__init__(robot, lambda pk, data: pk.build_serial_chain_from_urdf(
            data, end_link_name=cfg.camera_link, root_link_name=root), f"{root} -> {cfg.camera_link}", device, dtype)
        self.roll = torch.as_tensor(image_roll(cfg.camera_roll_deg), dtype=dtype, device=self.device)

    def camera_poses(self, q: torch.Tensor) -> torch.Tensor:
        """Camera optical-frame poses (B, 4, 4) in the scene frame (computed in the chain's dtype, returned in
        ``q``'s dtype and device)."""
        T = self.chain.forward_kinematics(self._chain_values(q)).get_matrix()
        base = self._base(q)
        if base is not None:
            T = base @ T
        return (T @ self.roll).to(q.device, q.dtype)

    def camera_jacobian(self, q_in: torch.Tensor) -> tuple:
        """``(T, W)`` as :meth:`RobotModel.camera_jacobian`: poses (B, 4, 4) and world twists (B, dof, 6)
        ``[omega, v0]`` per planning joint (in ``q``'s dtype and device)."""
        q = q_in.to(self.device, self.dtype)
        th = self._chain_values(q)
        T_root = self.chain.forward_kinematics(th).get_matrix()
        J = self.chain.jacobian(th)  # (B, 6, n): [v; omega] of the camera link origin, root frame
        Jq = J @ self.M.T.unsqueeze(0)  # (B, 6, dof)
        base = self._base(q)
        R = base[:, :3, :3] if base is not None else torch.eye(3, dtype=self.dtype, device=self.device).expand(
            q.shape[0], 3, 3)
        T = (base @ T_root) if base is not None else T_root
        p = T[:, :3, 3]
        v = R @ Jq[:, :3, :]
        w = R @ Jq[:, 3:, :]
        v0 = v - torch.linalg.cross(w.transpose(1, 2), p.unsqueeze(1).expand(-1, q.shape[1], -1)).transpose(1, 2)
        W = torch.cat([w, v0], 1).transpose(1, 2).contiguous()  # (B, dof, 6)
        if self.robot.mobile:
            add_base_twists(W, q)
        return (T @ self.roll).to(q_in.device, q_in.dtype), W.to(q_in.device, q_in.dtype)


class PKBodyKinematics(PKChainMap):
    """``kin = PKBodyKinematics(robot, device, dtype)``; ``kin.body_poses(q, only=None)`` as
    :meth:`RobotModel.body_poses`: the world poses of the robot model's rigid bodies (:attr:`RobotModel.bodies`, each
    the frame of its first link, where the collision model's boxes and spheres are attached) from one pass over the
    whole tree (``pk.build_chain_from_urdf``)."""

    def __init__(self, robot, device="cpu", dtype: torch.dtype = torch.float64):
        super().__init__(robot, lambda pk, data: pk.build_chain_from_urdf(data), "(the whole tree)", device, dtype)
        names = set(self.chain.get_frame_names(exclude_fixed=False))
        missing = [b for b in robot.bodies if b not in names]
        if missing or int(self.chain.get_frame_indices(robot.urdf.root)[0]) != 0:
            raise RobotModelError(f"{robot.urdf.path.name}: pytorch-kinematics' tree is not rooted at "
                                  f"'{robot.urdf.root}' or lacks the links {', '.join(missing)}")
        self.body_frames = self.chain.get_frame_indices(*robot.bodies)

    def body_poses(self, q: torch.Tensor, only: Optional[list] = None) -> tuple:
        """World rotations (B, NB, 3, 3) and translations (B, NB, 3) of every body for configurations ``q`` (B, dof),
        computed in the chain's dtype and returned in ``q``'s dtype and device. With ``only`` (a list of body
        indices), the other bodies are zeros."""
        if q.dim() != 2 or q.shape[1] != self.robot.dof:
            raise InputError(f"expected q of shape (B, {self.robot.dof}), got {tuple(q.shape)}")
        frames = self.body_frames if only is None else self.body_frames[list(only)]
        T = self.chain.forward_kinematics_tensor(self._chain_values(q))[frames].transpose(0, 1)  # (B, n, 4, 4)
        base = self._base(q)
        if base is not None:
            T = base.unsqueeze(1) @ T
        T = T.to(q.device, q.dtype)
        if only is None:
            return T[..., :3, :3].contiguous(), T[..., :3, 3].contiguous()
        R = torch.zeros(q.shape[0], len(self.body_frames), 3, 3, dtype=q.dtype, device=q.device)
        t = torch.zeros(q.shape[0], len(self.body_frames), 3, dtype=q.dtype, device=q.device)
        R[:, list(only)], t[:, list(only)] = T[..., :3, :3], T[..., :3, 3]
        return R, t
