"""Configuration-space metric and local motions for robots on a differential-drive base.

A differential drive cannot move sideways, so the base moves between two poses by *rotate, translate, rotate*:
turn to the heading of the segment (or its reverse, whichever turns less), drive straight, turn to the final
heading. The other joints move linearly while the base does so. The motion cost of a segment is

    c = w_rot (|dtheta_1| + |dtheta_2|) + |dxy| + ||dq_joints||_2

with ``w_rot`` the robot's ``base.rotation_weight`` (metres per radian). All functions are batched in torch and
follow the device of their inputs.
"""

from __future__ import annotations

import math

import torch

from .geometry import wrap_angle
from .kernels._fast_packs import MotionPack
from .kernels.compute import Compute, Computing
from .robot import RobotModel


class DiffDriveMotion(Computing):
    """Metric, interpolation and motion validation for one robot (fixed-base robots interpolate linearly); its
    batched methods follow ``compute`` (default: the robot model's)."""

    def __init__(self, robot: RobotModel, compute: Compute | None = None):
        self.robot = robot
        self._compute = robot.compute if compute is None else compute
        self.mobile = robot.mobile
        self.w_rot = robot.config.base.rotation_weight
        self.continuous = torch.as_tensor(robot.continuous)

    def kernel_pack(self):
        """The metric's parameters as the compiled kernels take them (:mod:`psprm_core.kernels.fastpath`): a
        :class:`~psprm_core.kernels._fast_packs.MotionPack` (w_rot, mobile) of :meth:`distance`."""
        return MotionPack(float(self.w_rot), bool(self.mobile))

    # ---- base decomposition ----------------------------------------------------------------------------------------
    def base_plan(self, qa: torch.Tensor, qb: torch.Tensor) -> tuple:
        """Heading φ of the straight part and the three phase lengths (rot1, trans, rot2), each (E,)."""
        dxy = qb[:, :2] - qa[:, :2]
        d = dxy.norm(dim=-1)
        fwd = torch.atan2(dxy[:, 1], dxy[:, 0])
        rev = wrap_angle(fwd + math.pi)
        cost_f = wrap_angle(fwd - qa[:, 2]).abs() + wrap_angle(qb[:, 2] - fwd).abs()
        cost_r = wrap_angle(rev - qa[:, 2]).abs() + wrap_angle(qb[:, 2] - rev).abs()
        phi = torch.where(cost_r < cost_f, rev, fwd)
        still = d < 1e-6
        phi = torch.where(still, qa[:, 2], phi)
        r1 = wrap_angle(phi - qa[:, 2])
        r2 = wrap_angle(qb[:, 2] - phi)
        return phi, r1, d, r2

    def distance(self, qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
        """Motion cost between configurations (E, dof) and (E, dof) -> (E,) (see module docstring)."""
        return self.compute.ops.distance(self, qa, qb)

    def distance_torch(self, qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
        """:meth:`distance` in torch (any device, broadcasting, autograd)."""
        qa, qb = torch.broadcast_tensors(qa, qb)
        if not self.mobile:
            return (qb - qa).norm(dim=-1)
        _, r1, d, r2 = self.base_plan(qa, qb)
        return self.w_rot * (r1.abs() + r2.abs()) + d + (qb[:, 3:] - qa[:, 3:]).norm(dim=-1)

    def interpolate(self, qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """Configurations at fractions ``s`` (E,) in [0, 1] of the local motion from ``qa`` to ``qb`` (E, dof).

        The base fraction follows the three phases in proportion to their weighted lengths; joints move linearly.
        """
        return self.compute.ops.interpolate(self, qa, qb, s)

    def interpolate_torch(self, qa: torch.Tensor, qb: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """:meth:`interpolate` in torch (any device, autograd)."""
        if not self.mobile:
            return qa + (qb - qa) * s.unsqueeze(-1)
        phi, r1, d, r2 = self.base_plan(qa, qb)
        l1, l2, l3 = self.w_rot * r1.abs(), d, self.w_rot * r2.abs()
        total = (l1 + l2 + l3).clamp_min(1e-12)
        u = s * total  # arc length along the base path
        f1 = (u / l1.clamp_min(1e-12)).clamp(0, 1)
        f2 = ((u - l1) / l2.clamp_min(1e-12)).clamp(0, 1)
        f3 = ((u - l1 - l2) / l3.clamp_min(1e-12)).clamp(0, 1)
        f1 = torch.where(l1 > 0, f1, torch.ones_like(f1))
        f2 = torch.where(l2 > 0, f2, torch.ones_like(f2))
        f3 = torch.where(l3 > 0, f3, torch.zeros_like(f3) + (s >= 1).to(s.dtype))
        theta = qa[:, 2] + r1 * f1 + r2 * f3
        xy = qa[:, :2] + (qb[:, :2] - qa[:, :2]) * f2.unsqueeze(-1)
        joints = qa[:, 3:] + (qb[:, 3:] - qa[:, 3:]) * s.unsqueeze(-1)
        out = torch.cat([xy, wrap_angle(theta).unsqueeze(-1), joints], dim=-1)
        return out

    # ---- validation ------------------------------------------------------------------------------------------------
    def steps(self, qa: torch.Tensor, qb: torch.Tensor, resolution: float, max_steps: int = 200) -> torch.Tensor:
        """Number of interior checks per motion so that consecutive checks are at most ``resolution`` apart."""
        n = torch.ceil(self.distance(qa, qb) / resolution).long()
        return n.clamp(1, max_steps)

    def dense(self, qa: torch.Tensor, qb: torch.Tensor, resolution: float, max_steps: int = 200) -> tuple:
        """All intermediate configurations of a batch of motions: (edge index (M,), s (M,), q (M, dof)).

        Endpoints are excluded (they are checked as nodes).
        """
        n = self.steps(qa, qb, resolution, max_steps)
        edge = torch.repeat_interleave(torch.arange(len(n), device=qa.device), n)
        k = torch.arange(len(edge), device=qa.device) - torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
        s = (k + 1).to(qa.dtype) / (n[edge] + 1).to(qa.dtype)
        keep = n[edge] > 0
        edge, s = edge[keep], s[keep]
        return edge, s, self.interpolate(qa[edge], qb[edge], s)

    def motion_valid(self, checker, qa: torch.Tensor, qb: torch.Tensor, resolution: float = 0.05,
                     max_steps: int = 200) -> torch.Tensor:
        """Collision-free flags (E,) of local motions, checking interior points ``resolution`` apart (motion-cost
        units); endpoints are assumed checked."""
        qa = qa.to(checker.device, checker.dtype)
        qb = qb.to(checker.device, checker.dtype)
        edge, _, q = self.dense(qa, qb, resolution, max_steps)
        bad = checker.check(q)
        out = torch.ones(qa.shape[0], dtype=torch.bool, device=qa.device)
        out[edge[bad]] = False
        return out
