"""Numba kernels of the damped Gauss-Newton projection onto the visibility manifold (Alg. 1, line 7; re-exported by
:mod:`psprm_core.kernels._fast_numba`): the residual h_M and its Jacobian over the planning joints, a small linear
solve, and the projection of a batch of configurations.
"""

import math

import numpy as np

from ._fast_kinematics import PRISMATIC, ROOT, _camera, _fk, jit

#: SHA-256 of the kernel modules this one imports from, directly or through them (their sources with this line
#: blanked; checked by tests/test_fastpath.py). numba's disk cache checks only the source file of the kernel it
#: loads, not those of the kernels and the decorator it was compiled with: a change there must change this file
#: too, or the cached kernels here would keep the old code.
CALLEES_SHA256 = "d3f9d53d952a5c1aa7c8e20a6dc88410f853ae68eef61a98e4bb7b643a605a1d"


# ---------------------------------------------------------------------------------------------- projection
@jit
def _residual(q, robot, view, cols, R, t, Rc, tc, h, J):  # pragma: no cover - compiled
    """h_M(q) (m,) and its Jacobian J (m, k) over the planning joints ``cols`` for one configuration of the RobotPack
    ``robot`` and the ViewPack ``view`` (VisibilityConstraint.residual_jacobian with RobotModel.camera_jacobian):
    d p_c / d q_i = -R_c^T (omega_i x p + v0_i). Returns m (3 for the line model, 1 for the frustum model)."""
    order, jtype, axis, D, mobile = robot.chain, robot.jtype, robot.axis, robot.D, robot.mobile
    target, line, min_distance, far = view.target, view.line, view.min_distance, view.far
    th, tv, margin = view.th, view.tv, view.margin
    _fk(q, order, robot, R, t)
    _camera(R, t, robot, Rc, tc)
    pc = np.empty(3)
    for i in range(3):
        pc[i] = Rc[0, i] * (target[0] - tc[0]) + Rc[1, i] * (target[1] - tc[1]) + Rc[2, i] * (target[2] - tc[2])
    k = cols.shape[0]
    dpc = np.zeros((3, k))
    w = np.empty(6)
    vel = np.empty(3)
    ax = np.empty(3)
    for c in range(k):
        jc = cols[c]
        for i in range(6):
            w[i] = 0.0
        for n in range(order.shape[0]):  # twists of the chain's joints, through the drive matrix
            b = order[n]
            d = D[jc, b]
            if d == 0.0 or jtype[b] == ROOT:
                continue
            for i in range(3):
                ax[i] = R[b, i, 0] * axis[b, 0] + R[b, i, 1] * axis[b, 1] + R[b, i, 2] * axis[b, 2]
            if jtype[b] == PRISMATIC:
                for i in range(3):
                    w[3 + i] += d * ax[i]
            else:
                w[0] += d * ax[0]
                w[1] += d * ax[1]
                w[2] += d * ax[2]
                w[3] += d * (t[b, 1] * ax[2] - t[b, 2] * ax[1])
                w[4] += d * (t[b, 2] * ax[0] - t[b, 0] * ax[2])
                w[5] += d * (t[b, 0] * ax[1] - t[b, 1] * ax[0])
        if mobile:
            if jc == 0:
                w[3] += 1.0
            elif jc == 1:
                w[4] += 1.0
            elif jc == 2:
                w[2] += 1.0
                w[3] += q[1]
                w[4] -= q[0]
        vel[0] = w[1] * target[2] - w[2] * target[1] + w[3]
        vel[1] = w[2] * target[0] - w[0] * target[2] + w[4]
        vel[2] = w[0] * target[1] - w[1] * target[0] + w[5]
        for i in range(3):
            dpc[i, c] = -(Rc[0, i] * vel[0] + Rc[1, i] * vel[1] + Rc[2, i] * vel[2])
    if line:
        h[0], h[1] = pc[0], pc[1]
        gap = min_distance - pc[2]
        h[2] = gap if gap > 0.0 else 0.0
        act = 1.0 if gap > 0.0 else 0.0
        for c in range(k):
            J[0, c] = dpc[0, c]
            J[1, c] = dpc[1, c]
            J[2, c] = -dpc[2, c] * act
        return 3
    nh, nv = math.sqrt(1.0 + th * th), math.sqrt(1.0 + tv * tv)
    x, y, z = pc[0], pc[1], pc[2]
    dist = np.empty(6)
    dist[0], dist[1] = (x - th * z) / nh, (-x - th * z) / nh
    dist[2], dist[3] = (y - tv * z) / nv, (-y - tv * z) / nv
    dist[4], dist[5] = min_distance - z, z - far
    face = 0
    for i in range(1, 6):
        if dist[i] > dist[face]:
            face = i
    val = dist[face] + margin
    h[0] = val if val > 0.0 else 0.0
    g = np.zeros(3)
    if face == 0:
        g[0], g[2] = 1.0 / nh, -th / nh
    elif face == 1:
        g[0], g[2] = -1.0 / nh, -th / nh
    elif face == 2:
        g[1], g[2] = 1.0 / nv, -tv / nv
    elif face == 3:
        g[1], g[2] = -1.0 / nv, -tv / nv
    elif face == 4:
        g[2] = -1.0
    else:
        g[2] = 1.0
    act = 1.0 if h[0] > 0.0 else 0.0
    for c in range(k):
        J[0, c] = (g[0] * dpc[0, c] + g[1] * dpc[1, c] + g[2] * dpc[2, c]) * act
    return 1


@jit
def _solve(A, b, m):  # pragma: no cover - compiled
    """x = A^-1 b for a small (m, m) system, Gaussian elimination with partial pivoting (A, b overwritten)."""
    for c in range(m):
        p = c
        for r in range(c + 1, m):
            if abs(A[r, c]) > abs(A[p, c]):
                p = r
        if p != c:
            for j in range(m):
                A[c, j], A[p, j] = A[p, j], A[c, j]
            b[c], b[p] = b[p], b[c]
        for r in range(c + 1, m):
            f = A[r, c] / A[c, c]
            for j in range(c, m):
                A[r, j] -= f * A[c, j]
            b[r] -= f * b[c]
    x = np.empty(m)
    for c in range(m - 1, -1, -1):
        s = b[c]
        for j in range(c + 1, m):
            s -= A[c, j] * x[j]
        x[c] = s / A[c, c]
    return x


@jit
def project(q0, robot, view, solver):  # pragma: no cover - compiled
    """Damped Gauss-Newton projection onto h_M = 0 (Alg. 1, line 7; VisibilityConstraint.project) of the RobotPack
    ``robot`` and the ViewPack ``view``, with the SolverPack ``solver``: per row, q[cols] <- q[cols] - J^T (J J^T +
    damping I)^-1 h with the step norm capped at ``max_step``, clamped to [lo, hi] (base theta wrapped), until
    |h| < tol or ``max_iters`` steps. Returns (q (B, dof), |h| at the result (B,))."""
    cols, lo, hi, tol, max_iters = solver.cols, solver.lo, solver.hi, solver.tol, solver.max_iters
    damping, max_step, mobile = solver.damping, solver.max_step, robot.mobile
    B, dof, NB = q0.shape[0], q0.shape[1], robot.parent.shape[0]
    k = cols.shape[0]
    q = q0.copy()
    err_out = np.empty(B)
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    Rc, tc = np.empty((3, 3)), np.empty(3)
    h, J = np.empty(3), np.empty((3, k))
    A, rhs = np.empty((3, 3)), np.empty(3)
    for r in range(B):
        qr = q[r]
        for it in range(max_iters):
            m = _residual(qr, robot, view, cols, R, t, Rc, tc, h, J)
            e = 0.0
            for i in range(m):
                e += h[i] * h[i]
            done = math.sqrt(e) < tol
            if not done:
                for i in range(m):
                    for j in range(m):
                        s = 0.0
                        for c in range(k):
                            s += J[i, c] * J[j, c]
                        A[i, j] = s + (damping if i == j else 0.0)
                    rhs[i] = h[i]
                y = _solve(A, rhs, m)
                step = np.zeros(k)
                nrm = 0.0
                for c in range(k):
                    s = 0.0
                    for i in range(m):
                        s += J[i, c] * y[i]
                    step[c] = s
                    nrm += s * s
                nrm = max(math.sqrt(nrm), 1e-12)
                scale = min(max_step / nrm, 1.0)
                for c in range(k):
                    qr[cols[c]] -= step[c] * scale
            for i in range(dof):
                qr[i] = max(min(qr[i], hi[i]), lo[i])
            if mobile:
                qr[2] = ((qr[2] + math.pi) % (2.0 * math.pi)) - math.pi
            if done:
                break
        m = _residual(qr, robot, view, cols, R, t, Rc, tc, h, J)
        e = 0.0
        for i in range(m):
            e += h[i] * h[i]
        err_out[r] = math.sqrt(e)
    return q, err_out

