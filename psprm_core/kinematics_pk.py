"""Camera kinematics from pytorch-kinematics: the camera chain of a robot's URDF as a ``pk.SerialChain``.

A second, independent implementation of :meth:`RobotModel.camera_poses` and :meth:`RobotModel.camera_jacobian`
(whose URDF reader and chain code are psprm's own), device- and dtype-agnostic like the rest of the torch code:

* the chain runs from the URDF's root link to the camera link (``pk.build_serial_chain_from_urdf``), built from the
  same URDF file the robot model parses;
* planning joints drive chain joints through the robot's drive couplings (Stretch's four telescoping arm joints,
  mimic joints): chain value = ``q @ M + offset``; chain joints no planning joint drives sit at the robot config's
  ``fixed_joints`` values;
* a mobile base's ``x, y, theta`` place the URDF root in the scene: a prismatic x / y along the world axes and a
  revolute theta about z through ``(x, y, 0)``;
* the optical frame is the camera link turned by the config's image roll (a rotation: same origin).

The Jacobian is ``chain.jacobian`` (linear and angular velocity of the camera link's origin per chain joint, in the
root frame), mapped to planning joints by ``M`` and expressed as the spatial twists ``[omega, v0]`` that
:meth:`RobotModel.camera_jacobian` returns (``v0 = v_p - omega x p``: the velocity of the world point at the origin
moving with the camera).
"""

from __future__ import annotations

import contextlib
import io
from typing import Optional

import numpy as np
import torch

from .errors import RobotModelError
from .robot import add_base_twists, image_roll


class PKCameraKinematics:
    """``kin = PKCameraKinematics(robot, device, dtype)``; ``kin.camera_poses(q)``, ``kin.camera_jacobian(q)``."""

    def __init__(self, robot, device="cpu", dtype: torch.dtype = torch.float64):
        try:
            import pytorch_kinematics as pk
        except ImportError as exc:  # pragma: no cover - a pinned requirement
            raise RobotModelError(f"pytorch-kinematics is not installed: {exc}") from exc
        self.robot, self.device, self.dtype = robot, torch.device(device), dtype
        cfg, urdf = robot.config, robot.urdf
        try:
            # its URDF parser reports every tag it does not model (transmissions, gazebo) on stderr: not errors
            with contextlib.redirect_stderr(io.StringIO()):
                chain = pk.build_serial_chain_from_urdf(urdf.path.read_bytes(), end_link_name=cfg.camera_link,
                                                        root_link_name=urdf.root)
        except Exception as exc:
            raise RobotModelError(f"{urdf.path.name}: pytorch-kinematics cannot build the chain "
                                  f"{urdf.root} -> {cfg.camera_link}: {exc}") from exc
        self.chain = chain.to(dtype=dtype, device=self.device)
        self.joint_names = list(self.chain.get_joint_parameter_names())
        M = np.zeros((robot.dof, len(self.joint_names)))
        off = np.zeros(len(self.joint_names))
        for k, name in enumerate(self.joint_names):
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
        self.M = torch.as_tensor(M, dtype=dtype, device=self.device)
        self.offset = torch.as_tensor(off, dtype=dtype, device=self.device)
        self.roll = torch.as_tensor(image_roll(cfg.camera_roll_deg), dtype=dtype, device=self.device)

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
