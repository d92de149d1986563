"""Numba kernel of the path tolerance (:mod:`psprm_core.tracking`, re-exported by
:mod:`psprm_core.kernels._fast_numba`): the world positions of the corners of the robot's collision boxes, by the
body-tree forward kinematics of :mod:`~psprm_core.kernels._fast_kinematics`, in float64 as
:meth:`psprm_core.robot.model.RobotModel.element_corners` computes them with torch.
"""

import numpy as np

from ._fast_kinematics import _fk, jit

#: SHA-256 of the kernel modules this one imports from (see :mod:`psprm_core.kernels._fast_kinematics`).
CALLEES_SHA256 = "d3f9d53d952a5c1aa7c8e20a6dc88410f853ae68eef61a98e4bb7b643a605a1d"


@jit
def element_corners(q, robot, el_body, local):  # pragma: no cover - compiled
    """World positions (B, 8E, 3) of the corners of the boxes of configurations q (B, dof) of the RobotPack
    ``robot``: box e, fixed to body ``el_body[e]`` with corners ``local[e]`` (8, 3) in that body's frame, has its
    corners at rows 8e .. 8e + 7 (RobotModel.element_corners)."""
    B, NB, E = q.shape[0], robot.parent.shape[0], el_body.shape[0]
    out = np.empty((B, 8 * E, 3))
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    order = robot.bodies
    for r in range(B):
        _fk(q[r], order, robot, R, t)
        for e in range(E):
            b = el_body[e]
            for k in range(8):
                x, y, z = local[e, k, 0], local[e, k, 1], local[e, k, 2]
                for i in range(3):
                    out[r, 8 * e + k, i] = t[b, i] + R[b, i, 0] * x + R[b, i, 1] * y + R[b, i, 2] * z
    return out
