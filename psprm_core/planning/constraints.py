"""Visibility manifolds h_M(q) = 0 and their batched Newton projection (paper Sec. "Sampling with Visibility
Constraints").

Two camera models, both functions of the camera pose from batched FK and the target centroid p:

* **line of sight**: the target centroid lies on the optical axis in front of the camera. With p_c = R^T (p - t)
  the target in the optical frame, h_line(q) = (p_c,x, p_c,y) in metres: its norm is the distance from p to the
  optical axis (the paper's scalar h_M); the 2-vector form gives Gauss-Newton a well-conditioned Jacobian.
* **frustum**: the target (centroid plus a margin of its radius) lies inside the camera's viewing frustum:
  h_frustum(q) = max(0, sd_f(q, p)) with sd_f the largest signed distance of p to the four side planes and the near
  and far planes (exact inside the frustum, a lower bound outside, zero exactly on the manifold).

Projection (Alg. 1, line 7): q <- q - J^+ h(q), with J = dh/dq from autograd through batched FK and J^+ the
(damped) Moore-Penrose pseudo-inverse (J by forward differences in one batched FK call, over the
joints that move the camera), clamped to joint limits after each step, until |h| < tol or ``max_iters``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from ..camera import CameraIntrinsics
from ..errors import InputError
from ..geometry import wrap_angle
from ..kernels._fast_packs import ViewPack
from ..kernels.arrays import const_f64
from ..kernels.compute import Compute, Computing
from ..robot import RobotModel


def camera_joint_mask(robot: RobotModel) -> np.ndarray:
    """Planning joints that move the camera (base joints included)."""
    chain, b = set(), robot.camera_body
    while b > 0:
        chain.add(b)
        b = robot.parent_body[b]
    mask = np.zeros(robot.dof, dtype=bool)
    mask[: robot.base_dof] = True
    for b in chain:
        mask |= robot.drive_matrix[:, b] != 0
    return mask


@dataclass(frozen=True)
class ProjectionSettings:
    """The Newton projection onto the visibility manifold (Alg. 1, line 7)."""

    YAML_BOUNDS: ClassVar[dict] = {"int_lo": 1, "float_lo": None}  # read by yamlio.dataclass_kwargs

    tolerance: float = 0.02  # line: metres off the optical axis; frustum: metres outside the frustum
    max_iters: int = 20
    damping: float = 1e-4
    max_step: float = 0.5  # max norm of one Newton step in configuration units


class VisibilityConstraint(Computing):
    """h_M(q) for one robot, camera model and target point; batched and device-following.

    Parameters
    ----------
    robot : RobotModel
    kind : {"line", "frustum"}
    target : (3,) tensor-like
        Point to keep in view (a target centroid, or the midpoint of several targets).
    margin : float
        Frustum model: keep this much room around the point (e.g. the target's radius).
    min_distance : float
        The target must be at least this far in front of the camera (default: near plane + 0.2 m).
    kinematics : object with ``camera_poses(q)`` and ``camera_jacobian(q)``, optional
        Where the camera pose and its Jacobian come from: the robot model (default; small CPU batches then run the
        compiled iteration) or e.g. :class:`~psprm_core.robot.kinematics_pk.PKCameraKinematics` (always the torch
        iteration).
    compute : Compute, optional
        Which kernels serve the projection (default: the robot model's).
    """

    def __init__(self, robot: RobotModel, kind: str, target, margin: float = 0.0, min_distance: float | None = None,
                 kinematics=None, compute: Compute | None = None):
        if kind not in ("line", "frustum"):
            raise InputError(f"unknown visibility model '{kind}' (line or frustum)")
        self.robot = robot
        self.kin = robot if kinematics is None else kinematics
        self._compute = robot.compute if compute is None else compute
        self.kind = kind
        self.intr: CameraIntrinsics = robot.config.intrinsics
        self.target = torch.as_tensor(target, dtype=torch.float64).reshape(3)
        self.margin = float(margin)
        self.min_distance = self.intr.near + 0.2 if min_distance is None else float(min_distance)

    @property
    def dim(self) -> int:
        return 3 if self.kind == "line" else 1

    def set_target(self, target) -> None:
        self.target = torch.as_tensor(target, dtype=torch.float64).reshape(3)

    def target_in_camera(self, q: torch.Tensor) -> torch.Tensor:
        """Target position in the optical frame (B, 3)."""
        T = self.kin.camera_poses(q)
        p = self.target.to(q.device, q.dtype)
        return ((p - T[:, :3, 3]).unsqueeze(1) @ T[:, :3, :3]).squeeze(1)

    def residual(self, q: torch.Tensor) -> torch.Tensor:
        """h_M(q): (B, 3) for the line model, (B, 1) for the frustum model."""
        pc = self.target_in_camera(q)
        return self.residual_from_camera_points(pc)

    def residual_from_camera_points(self, pc: torch.Tensor) -> torch.Tensor:
        if self.kind == "line":
            # (x, y) off the axis, and how far the target is short of the minimum distance in front
            return torch.stack([pc[:, 0], pc[:, 1], (self.min_distance - pc[:, 2]).clamp_min(0)], -1)
        return self.frustum_distance(pc).clamp_min(0).unsqueeze(-1)

    def frustum_distance(self, pc: torch.Tensor) -> torch.Tensor:
        """Signed distance (B,) of the target (with margin) to the frustum: <= 0 inside."""
        th, tv = self.intr.tan_half_h, self.intr.tan_half_v
        nh, nv = math.sqrt(1 + th * th), math.sqrt(1 + tv * tv)
        x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
        d = torch.stack([
            (x - th * z) / nh, (-x - th * z) / nh, (y - tv * z) / nv, (-y - tv * z) / nv,
            self.min_distance - z, z - self.intr.far,
        ], -1)
        return d.max(-1).values + self.margin

    def residual_jacobian(self, q: torch.Tensor, cols: torch.Tensor) -> tuple:
        """h_M(q) (B, m) and its analytic Jacobian (B, m, k) with respect to the planning joints ``cols``.

        With the camera pose (R_c, t_c) and its twists (omega_i, v0_i) (:meth:`RobotModel.camera_jacobian`), the
        target's optical-frame position p_c = R_c^T (p - t_c) moves as d p_c / d q_i = -R_c^T (omega_i x p + v0_i).
        The line residual's third row (how far the target is short of the minimum distance) and the frustum
        residual (the largest face distance, Eq. of :meth:`frustum_distance`) differentiate where they are active
        and are flat elsewhere (the subgradient of the clamp / max)."""
        T, W = self.kin.camera_jacobian(q)
        Rc, tc = T[:, :3, :3], T[:, :3, 3]
        p = self.target.to(q.device, q.dtype)
        pc = ((p - tc).unsqueeze(1) @ Rc).squeeze(1)
        Wk = W[:, cols]  # (B, k, 6)
        vel = torch.linalg.cross(Wk[..., :3], p.expand_as(Wk[..., :3])) + Wk[..., 3:]  # (B, k, 3) world
        dpc = -(vel @ Rc).transpose(1, 2)  # (B, 3, k): R_c^T vel, per column
        h = self.residual_from_camera_points(pc)
        if self.kind == "line":
            active = (self.min_distance - pc[:, 2] > 0).to(q.dtype)
            J = torch.stack([dpc[:, 0], dpc[:, 1], -dpc[:, 2] * active.unsqueeze(-1)], 1)
            return h, J
        th, tv = self.intr.tan_half_h, self.intr.tan_half_v
        nh, nv = math.sqrt(1 + th * th), math.sqrt(1 + tv * tv)
        G = torch.tensor([[1 / nh, 0, -th / nh], [-1 / nh, 0, -th / nh], [0, 1 / nv, -tv / nv],
                          [0, -1 / nv, -tv / nv], [0, 0, -1.0], [0, 0, 1.0]], dtype=q.dtype, device=q.device)
        x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
        d = torch.stack([(x - th * z) / nh, (-x - th * z) / nh, (y - tv * z) / nv, (-y - tv * z) / nv,
                         self.min_distance - z, z - self.intr.far], -1)
        face = d.argmax(-1)
        active = (h[:, 0] > 0).to(q.dtype)
        J = (G[face].unsqueeze(1) @ dpc) * active[:, None, None]  # (B, 1, k)
        return h, J

    def error(self, q: torch.Tensor) -> torch.Tensor:
        """|h_M(q)| (B,)."""
        return self.residual(q).norm(dim=-1)

    def in_view(self, q: torch.Tensor, slack: float = 0.0) -> torch.Tensor:
        """Target centroid inside the frustum, up to ``slack`` metres (B,) bool (keeps edges near the manifold)."""
        return self.frustum_distance(self.target_in_camera(q)) - self.margin <= slack

    def kernel_pack(self, dtype: torch.dtype):
        """h_M's parameters as the compiled kernels take them (:mod:`psprm_core.kernels.fastpath`): a
        :class:`~psprm_core.kernels._fast_packs.ViewPack` of the target (rounded to ``dtype``, as the torch path casts
        it; kept until the target changes), the model, the minimum distance, the far plane, the half-view tangents and
        the margin (:meth:`residual_jacobian`)."""
        intr = self.intr
        return ViewPack(const_f64(self.target, dtype), self.kind == "line", float(self.min_distance),
                        float(intr.far), float(intr.tan_half_h), float(intr.tan_half_v), float(self.margin))

    def _camera_joints(self) -> np.ndarray:
        """Planning joints that move the camera (the only ones the constraint depends on)."""

        return camera_joint_mask(self.robot)

    # ---- projection --------------------------------------------------------------------------------------------------
    def project(self, q: torch.Tensor, settings: ProjectionSettings = ProjectionSettings(),
                lower: torch.Tensor | None = None, upper: torch.Tensor | None = None,
                joints: np.ndarray | None = None) -> tuple:
        """Project configurations (B, dof) onto h_M = 0 with damped Gauss-Newton steps.

        ``joints`` restricts the update to those planning-joint indices (default: every joint that moves the camera);
        edges use it to let only the non-base camera joints track the target while the base follows its path.

        Returns
        -------
        q : (B, dof) projected configurations (joint limits respected; base theta wrapped)
        converged : (B,) bool, |h_M| < tolerance
        """
        robot = self.robot
        lo = torch.as_tensor(robot.lower, dtype=q.dtype, device=q.device) if lower is None else lower
        hi = torch.as_tensor(robot.upper, dtype=q.dtype, device=q.device) if upper is None else upper
        q = q.detach().clone()
        cols = torch.as_tensor(np.nonzero(self._camera_joints())[0] if joints is None else np.asarray(joints),
                               dtype=torch.long, device=q.device)
        if len(cols) == 0:
            return q, self.error(q).detach() < settings.tolerance
        return self.compute.ops.project(self, q, settings, lo, hi, cols)

    def gauss_newton_torch(self, q: torch.Tensor, settings: ProjectionSettings, lo: torch.Tensor, hi: torch.Tensor,
                           cols: torch.Tensor) -> tuple:
        """Damped Gauss-Newton steps of :meth:`project` over the joints ``cols``, in place on ``q`` (a copy), in
        torch (any device); the compiled kernels run the same iteration."""
        robot = self.robot
        active = torch.ones(q.shape[0], dtype=torch.bool, device=q.device)
        eye = torch.eye(self.dim, dtype=q.dtype, device=q.device)
        for _ in range(settings.max_iters):
            idx = torch.nonzero(active, as_tuple=True)[0]
            if len(idx) == 0:
                break
            qa = q[idx]
            h, J = self.residual_jacobian(qa, cols)  # (n, m), (n, m, k): one camera-chain FK per step
            err = h.norm(dim=-1)
            done = err < settings.tolerance
            JJt = J @ J.transpose(1, 2) + settings.damping * eye
            step_k = (J.transpose(1, 2) @ torch.linalg.solve(JJt, h.unsqueeze(-1))).squeeze(-1)
            norm = step_k.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            step_k = step_k * (settings.max_step / norm).clamp(max=1.0)
            step_k[done] = 0
            qn = qa.clone()
            qn[:, cols] -= step_k
            qn = torch.maximum(torch.minimum(qn, hi), lo)
            if robot.mobile:
                qn[:, 2] = wrap_angle(qn[:, 2])
            q[idx] = qn
            active[idx[done]] = False
        err = self.error(q).detach()
        return q, err < settings.tolerance
