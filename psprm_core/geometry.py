"""Rigid-transform helpers (numpy for configuration-time work, torch for batched hot paths).

Quaternions are (x, y, z, w), as in ROS and pybullet.
"""

from __future__ import annotations

import math

import numpy as np
import torch

#: ray-direction components smaller than this are treated as parallel to a slab (ray casting, both backends)
EPS_DIR = 1e-12


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(x, y, z, w)`` (normalised first)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=float)
    tr = np.trace(r)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def rpy_to_matrix(rpy) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton products ``a b`` of quaternions xyzw (``a`` then ``b`` applied in the body frame: R(a) R(b)): each
    of ``a``, ``b`` one quaternion (4,) or N of them (N, 4). One pair costs what a scalar expression does (a pose
    message's frame change calls it)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ax, ay, az, aw = a.T
    bx, by, bz, bw = b.T
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz]).T


def yaw_to_quat(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def turn_about_z(qa, qb) -> float:
    """How far (rad, in [0, pi]) orientation ``qb`` is turned from ``qa`` about ``qa``'s own z axis (quaternions
    [x, y, z, w]): the heading of the relative rotation's x axis in ``qa``'s xy plane; a tilt alone turns nothing."""
    r = quat_to_matrix(qa).T @ quat_to_matrix(qb)
    if math.hypot(r[0, 0], r[1, 0]) < 1e-9:  # x axis tilted onto z: measured by the y axis instead
        return abs(math.atan2(-r[0, 1], r[1, 1]))
    return abs(math.atan2(r[1, 0], r[0, 0]))


def make_transform(rotation: np.ndarray, translation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = translation
    return t


def wrap_angle(a):
    """Wrap angles to (-pi, pi]; works on floats, numpy arrays and torch tensors."""
    if isinstance(a, torch.Tensor):
        return torch.remainder(a + math.pi, 2 * math.pi) - math.pi
    return np.remainder(np.asarray(a) + math.pi, 2 * math.pi) - math.pi


def axis_angle_matrix_torch(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Batched Rodrigues rotation: ``axis`` (3,) unit vector, ``angle`` (B,) -> (B, 3, 3)."""
    c, s = torch.cos(angle), torch.sin(angle)
    x, y, z = axis[0], axis[1], axis[2]
    one_c = 1 - c
    rows = [
        c + x * x * one_c, x * y * one_c - z * s, x * z * one_c + y * s,
        y * x * one_c + z * s, c + y * y * one_c, y * z * one_c - x * s,
        z * x * one_c - y * s, z * y * one_c + x * s, c + z * z * one_c,
    ]
    return torch.stack(rows, dim=-1).reshape(angle.shape + (3, 3))


def obb_overlap(ca: torch.Tensor, Ra: torch.Tensor, ha: torch.Tensor, cb: torch.Tensor, Rb: torch.Tensor,
                hb: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Separating-axis test for pairs of oriented boxes: (n,3), (n,3,3), (n,3) each -> overlap flags (n,).

    Axes: the 3 face normals of A, the 3 of B, and the 9 cross products (Gottschalk, Lin, Manocha 1996).
    ``eps`` is added to |R| to stay robust for near-parallel edges (conservative: may report touching boxes).
    """
    R = Ra.transpose(-1, -2) @ Rb  # B's axes in A's frame
    t = (Ra.transpose(-1, -2) @ (cb - ca).unsqueeze(-1)).squeeze(-1)
    AR = R.abs() + eps
    sep = (t.abs() > ha + (AR * hb.unsqueeze(-2)).sum(-1)).any(-1)  # A's axes
    tb = (t.unsqueeze(-2) @ R).squeeze(-2)
    sep |= (tb.abs() > (AR * ha.unsqueeze(-1)).sum(-2) + hb).any(-1)  # B's axes
    # the 9 edge-edge axes A_i x B_j at once, as (n, 3, 3) grids over (i, j); rolling an axis by -1 / -2 gives the
    # entries at i+1 / i+2 (mod 3), e.g. R.roll(-1, 1)[:, i, j] = R[:, i+1, j]
    def nxt(x, k, dim):
        return x.roll(-k, dims=dim)

    lhs = nxt(t, 2, 1).unsqueeze(-1) * nxt(R, 1, 1) - nxt(t, 1, 1).unsqueeze(-1) * nxt(R, 2, 1)
    ra = nxt(ha, 1, 1).unsqueeze(-1) * nxt(AR, 2, 1) + nxt(ha, 2, 1).unsqueeze(-1) * nxt(AR, 1, 1)
    rb = nxt(hb, 1, 1).unsqueeze(-2) * nxt(AR, 2, 2) + nxt(hb, 2, 1).unsqueeze(-2) * nxt(AR, 1, 2)
    sep |= (lhs.abs() > ra + rb).flatten(1).any(-1)
    return ~sep
