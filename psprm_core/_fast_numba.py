"""Numba kernels behind :mod:`psprm_core.fastpath` (imported only through its :func:`~psprm_core.fastpath.kernels`).

Small-batch CPU versions of the batched torch code a query runs (a few dozen to a few hundred configurations per
call, where torch's per-operator overhead dominates): forward kinematics of the body tree, camera poses, the damped
Gauss-Newton projection onto the visibility manifold, and the oriented-box collision check. They follow the torch
implementations step by step (same formulas, same order of tests) in float64; the callers cast the results back to
the torch dtype. Compiled on the first call of each kernel and cached on disk (``cache=True``).
"""

import math

import numpy as np
from numba import njit

jit = njit(cache=True, nogil=True)

ROOT, REVOLUTE, PRISMATIC = 0, 1, 2


# ---------------------------------------------------------------------------------------------- kinematics
@jit
def _fk(q, order, parent, jtype, R_off, t_off, axis, D, off, mobile, R, t):  # pragma: no cover - compiled
    """World rotations R (NB, 3, 3) and translations t (NB, 3) of the bodies in ``order`` (root-first, root
    excluded) for one configuration: T_child = T_parent T_origin Motion(axis, q D + off) (RobotModel._poses).
    R[NB] and R[NB + 1] are scratch (the callers allocate NB + 2 rotations)."""
    for i in range(3):
        for j in range(3):
            R[0, i, j] = 0.0
        t[0, i] = 0.0
    if mobile:
        c, s = math.cos(q[2]), math.sin(q[2])
        R[0, 0, 0], R[0, 0, 1], R[0, 1, 0], R[0, 1, 1], R[0, 2, 2] = c, -s, s, c, 1.0
        t[0, 0], t[0, 1] = q[0], q[1]
    else:
        R[0, 0, 0], R[0, 1, 1], R[0, 2, 2] = 1.0, 1.0, 1.0
    NB = parent.shape[0]
    Rj = R[NB]
    M = R[NB + 1]
    for n in range(order.shape[0]):
        b = order[n]
        p = parent[b]
        v = off[b]
        for i in range(q.shape[0]):
            v += q[i] * D[i, b]
        for i in range(3):
            for j in range(3):
                Rj[i, j] = R[p, i, 0] * R_off[b, 0, j] + R[p, i, 1] * R_off[b, 1, j] + R[p, i, 2] * R_off[b, 2, j]
            t[b, i] = t[p, i] + R[p, i, 0] * t_off[b, 0] + R[p, i, 1] * t_off[b, 1] + R[p, i, 2] * t_off[b, 2]
        x, y, z = axis[b, 0], axis[b, 1], axis[b, 2]
        if jtype[b] == PRISMATIC:
            for i in range(3):
                t[b, i] += (Rj[i, 0] * x + Rj[i, 1] * y + Rj[i, 2] * z) * v
                for j in range(3):
                    R[b, i, j] = Rj[i, j]
        else:  # Rodrigues (geometry.axis_angle_matrix_torch)
            c, s = math.cos(v), math.sin(v)
            oc = 1.0 - c
            M[0, 0], M[0, 1], M[0, 2] = c + x * x * oc, x * y * oc - z * s, x * z * oc + y * s
            M[1, 0], M[1, 1], M[1, 2] = y * x * oc + z * s, c + y * y * oc, y * z * oc - x * s
            M[2, 0], M[2, 1], M[2, 2] = z * x * oc - y * s, z * y * oc + x * s, c + z * z * oc
            for i in range(3):
                for j in range(3):
                    R[b, i, j] = Rj[i, 0] * M[0, j] + Rj[i, 1] * M[1, j] + Rj[i, 2] * M[2, j]


@jit
def _camera(R, t, cam_body, cam_R, cam_t, Rc, tc):  # pragma: no cover - compiled
    """Optical-frame pose (Rc, tc) from the camera body's world pose (RobotModel._camera_from_body)."""
    for i in range(3):
        for j in range(3):
            Rc[i, j] = R[cam_body, i, 0] * cam_R[0, j] + R[cam_body, i, 1] * cam_R[1, j] + \
                R[cam_body, i, 2] * cam_R[2, j]
        tc[i] = t[cam_body, i] + R[cam_body, i, 0] * cam_t[0] + R[cam_body, i, 1] * cam_t[1] + \
            R[cam_body, i, 2] * cam_t[2]


@jit
def camera_poses(q, order, parent, jtype, R_off, t_off, axis, D, off, mobile, cam_body, cam_R,
                 cam_t):  # pragma: no cover - compiled
    """Camera optical-frame poses (B, 4, 4) of configurations q (B, dof) (RobotModel.camera_poses)."""
    B, NB = q.shape[0], parent.shape[0]
    out = np.zeros((B, 4, 4))
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    Rc, tc = np.empty((3, 3)), np.empty(3)
    for r in range(B):
        _fk(q[r], order, parent, jtype, R_off, t_off, axis, D, off, mobile, R, t)
        _camera(R, t, cam_body, cam_R, cam_t, Rc, tc)
        for i in range(3):
            for j in range(3):
                out[r, i, j] = Rc[i, j]
            out[r, i, 3] = tc[i]
        out[r, 3, 3] = 1.0
    return out


# ---------------------------------------------------------------------------------------------- projection
@jit
def _residual(q, order, parent, jtype, R_off, t_off, axis, D, off, mobile, cam_body, cam_R, cam_t, target, cols,
              line, min_distance, far, th, tv, margin, R, t, Rc, tc, h, J):  # pragma: no cover - compiled
    """h_M(q) (m,) and its Jacobian J (m, k) over the planning joints ``cols`` for one configuration
    (VisibilityConstraint.residual_jacobian with RobotModel.camera_jacobian): d p_c / d q_i = -R_c^T (omega_i x p
    + v0_i). Returns m (3 for the line model, 1 for the frustum model)."""
    _fk(q, order, parent, jtype, R_off, t_off, axis, D, off, mobile, R, t)
    _camera(R, t, cam_body, cam_R, cam_t, Rc, tc)
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
def project(q0, order, parent, jtype, R_off, t_off, axis, D, off, mobile, cam_body, cam_R, cam_t, target, cols,
            line, min_distance, far, th, tv, margin, lo, hi, tol, max_iters, damping,
            max_step):  # pragma: no cover - compiled
    """Damped Gauss-Newton projection onto h_M = 0 (Alg. 1, line 7; VisibilityConstraint.project): per row,
    q[cols] <- q[cols] - J^T (J J^T + damping I)^-1 h with the step norm capped at ``max_step``, clamped to [lo, hi]
    (base theta wrapped), until |h| < tol or ``max_iters`` steps. Returns (q (B, dof), |h| at the result (B,))."""
    B, dof, NB = q0.shape[0], q0.shape[1], parent.shape[0]
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
            m = _residual(qr, order, parent, jtype, R_off, t_off, axis, D, off, mobile, cam_body, cam_R, cam_t,
                          target, cols, line, min_distance, far, th, tv, margin, R, t, Rc, tc, h, J)
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
        m = _residual(qr, order, parent, jtype, R_off, t_off, axis, D, off, mobile, cam_body, cam_R, cam_t,
                      target, cols, line, min_distance, far, th, tv, margin, R, t, Rc, tc, h, J)
        e = 0.0
        for i in range(m):
            e += h[i] * h[i]
        err_out[r] = math.sqrt(e)
    return q, err_out


# ---------------------------------------------------------------------------------------------- collision
@jit
def _point_box_sqdist(p, bc, bR, bh):  # pragma: no cover - compiled
    """Squared distance from point p to the oriented box (centre, rotation box->world, half extents)."""
    s = 0.0
    for j in range(3):
        loc = (p[0] - bc[0]) * bR[0, j] + (p[1] - bc[1]) * bR[1, j] + (p[2] - bc[2]) * bR[2, j]
        cl = max(min(loc, bh[j]), -bh[j])
        s += (loc - cl) * (loc - cl)
    return s


@jit
def _obb_overlap(ca, Ra, ha, cb, Rb, hb, eps, W):  # pragma: no cover - compiled
    """Separating-axis test of two oriented boxes (collision.obb_overlap: 15 axes, |R| + eps); W: scratch (3, 3, 3)."""
    Rm, AR, tt = W[0], W[1], W[2, 0]
    for i in range(3):
        for j in range(3):
            Rm[i, j] = Ra[0, i] * Rb[0, j] + Ra[1, i] * Rb[1, j] + Ra[2, i] * Rb[2, j]
            AR[i, j] = abs(Rm[i, j]) + eps
        tt[i] = Ra[0, i] * (cb[0] - ca[0]) + Ra[1, i] * (cb[1] - ca[1]) + Ra[2, i] * (cb[2] - ca[2])
    for i in range(3):  # A's axes
        if abs(tt[i]) > ha[i] + AR[i, 0] * hb[0] + AR[i, 1] * hb[1] + AR[i, 2] * hb[2]:
            return False
    for j in range(3):  # B's axes
        tb = tt[0] * Rm[0, j] + tt[1] * Rm[1, j] + tt[2] * Rm[2, j]
        if abs(tb) > AR[0, j] * ha[0] + AR[1, j] * ha[1] + AR[2, j] * ha[2] + hb[j]:
            return False
    for i in range(3):  # A_i x B_j
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            lhs = tt[i2] * Rm[i1, j] - tt[i1] * Rm[i2, j]
            ra = ha[i1] * AR[i2, j] + ha[i2] * AR[i1, j]
            rb = hb[j1] * AR[i, j2] + hb[j2] * AR[i, j1]
            if abs(lhs) > ra + rb:
                return False
    return True


@jit
def _world_box(R, t, b, c_local, R_local, c, Rw):  # pragma: no cover - compiled
    """World centre c and rotation Rw of a box given in body b's frame."""
    for i in range(3):
        c[i] = R[b, i, 0] * c_local[0] + R[b, i, 1] * c_local[1] + R[b, i, 2] * c_local[2] + t[b, i]
        for j in range(3):
            Rw[i, j] = R[b, i, 0] * R_local[0, j] + R[b, i, 1] * R_local[1, j] + R[b, i, 2] * R_local[2, j]


@jit
def _centre(R, t, b, c_local, c):  # pragma: no cover - compiled
    """World position c of a point given in body b's frame."""
    for i in range(3):
        c[i] = R[b, i, 0] * c_local[0] + R[b, i, 1] * c_local[1] + R[b, i, 2] * c_local[2] + t[b, i]


@jit
def _env_hit(R, t, bodies, body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_c, el_R, el_h,
             el_r, box_c, box_R, box_h, box_aabb, eps, bc, c, Rw, eye, W):  # pragma: no cover - compiled
    """Robot (body poses R, t) against the obstacle boxes (CollisionChecker._env): robot bounds vs box bounds, body
    spheres, body boxes, element spheres, then the exact element-box overlap. bc, c, Rw, eye, W: scratch."""
    K, nb = box_c.shape[0], bodies.shape[0]
    if K == 0:
        return False
    lo0 = lo1 = lo2 = np.inf
    hi0 = hi1 = hi2 = -np.inf
    for n in range(nb):
        b = bodies[n]
        _centre(R, t, b, body_c[b], bc[n])
        r = body_r[b]
        lo0, lo1, lo2 = min(lo0, bc[n, 0] - r), min(lo1, bc[n, 1] - r), min(lo2, bc[n, 2] - r)
        hi0, hi1, hi2 = max(hi0, bc[n, 0] + r), max(hi1, bc[n, 1] + r), max(hi2, bc[n, 2] + r)
    for kb in range(K):
        if not (lo0 <= box_aabb[kb, 3] and lo1 <= box_aabb[kb, 4] and lo2 <= box_aabb[kb, 5]
                and hi0 >= box_aabb[kb, 0] and hi1 >= box_aabb[kb, 1] and hi2 >= box_aabb[kb, 2]):
            continue
        for n in range(nb):
            b = bodies[n]
            if not _point_box_sqdist(bc[n], box_c[kb], box_R[kb], box_h[kb]) < body_r[b] * body_r[b]:
                continue
            _world_box(R, t, b, body_box_c[b], eye, c, Rw)
            if not _obb_overlap(c, Rw, body_box_h[b], box_c[kb], box_R[kb], box_h[kb], eps, W):
                continue
            for m in range(el_count[b]):
                e = el_order[el_start[b] + m]
                _centre(R, t, b, el_c[e], c)
                if not _point_box_sqdist(c, box_c[kb], box_R[kb], box_h[kb]) < el_r[e] * el_r[e]:
                    continue
                _world_box(R, t, b, el_c[e], el_R[e], c, Rw)
                if _obb_overlap(c, Rw, el_h[e], box_c[kb], box_R[kb], box_h[kb], eps, W):
                    return True
    return False


@jit
def _self_hit(R, t, pairs, pair_els, el_body, el_c, el_R, el_h, el_r, eps, ec, ca, cb, Ra, Rb,
              W):  # pragma: no cover - compiled
    """Self-collision of the element pairs (CollisionChecker._pairs_hits): bounding spheres of the element centres
    (computed once, for the elements in ``pair_els``), then the exact overlap. ec, ca, cb, Ra, Rb, W: scratch."""
    for n in range(pair_els.shape[0]):
        e = pair_els[n]
        _centre(R, t, el_body[e], el_c[e], ec[e])
    for p in range(pairs.shape[0]):
        a, b = pairs[p, 0], pairs[p, 1]
        d2 = (ec[a, 0] - ec[b, 0]) ** 2 + (ec[a, 1] - ec[b, 1]) ** 2 + (ec[a, 2] - ec[b, 2]) ** 2
        if not d2 < (el_r[a] + el_r[b]) ** 2:
            continue
        _world_box(R, t, el_body[a], el_c[a], el_R[a], ca, Ra)
        _world_box(R, t, el_body[b], el_c[b], el_R[b], cb, Rb)
        if _obb_overlap(ca, Ra, el_h[a], cb, Rb, el_h[b], eps, W):
            return True
    return False


@jit
def check(q, detailed, order, parent, jtype, R_off, t_off, axis, D, off, mobile, lower, upper, bodies, body_c,
          body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c, el_R, el_h, el_r, pairs,
          pair_els, box_c, box_R, box_h, box_aabb, eps):  # pragma: no cover - compiled
    """Collision flags (B, 3): joint limits, environment, self (CollisionChecker.check_detailed). Without
    ``detailed`` a row stops at its first violation (only the OR of the three is meaningful then)."""
    B, dof, NB, E = q.shape[0], q.shape[1], parent.shape[0], el_c.shape[0]
    out = np.zeros((B, 3), np.bool_)
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    bc, ec = np.empty((bodies.shape[0], 3)), np.empty((E, 3))
    c, c2 = np.empty(3), np.empty(3)
    Rw, Rw2, eye = np.empty((3, 3)), np.empty((3, 3)), np.eye(3)
    W = np.empty((3, 3, 3))
    for r in range(B):
        qr = q[r]
        lim = False
        for i in range(dof):
            if not (qr[i] >= lower[i] and qr[i] <= upper[i]):  # outside, or NaN
                lim = True
        out[r, 0] = lim
        if lim and not detailed:
            continue
        _fk(qr, order, parent, jtype, R_off, t_off, axis, D, off, mobile, R, t)
        out[r, 1] = _env_hit(R, t, bodies, body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order,
                             el_c, el_R, el_h, el_r, box_c, box_R, box_h, box_aabb, eps, bc, c, Rw, eye, W)
        if out[r, 1] and not detailed:
            continue
        out[r, 2] = _self_hit(R, t, pairs, pair_els, el_body, el_c, el_R, el_h, el_r, eps, ec, c, c2, Rw, Rw2, W)
    return out


@jit
def env_hits(q, want_aabb, order, parent, jtype, R_off, t_off, axis, D, off, mobile, bodies, body_c, body_r,
             body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c, el_R, el_h, el_r, box_c, box_R, box_h,
             box_aabb, eps):  # pragma: no cover - compiled
    """Environment flags (B,) against the given boxes only (no limits, no self-collision:
    CollisionChecker.env_hits) and, with ``want_aabb``, the robot's world bounds (B, 6) = [min xyz, max xyz] of
    every element box (CollisionChecker._aabb: half extents sum_j |(R_b R_e)_ij| h_j), from the same FK."""
    B, NB, E = q.shape[0], parent.shape[0], el_c.shape[0]
    hit = np.zeros(B, np.bool_)
    aabb = np.zeros((B if want_aabb else 0, 6))
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    bc = np.empty((bodies.shape[0], 3))
    c = np.empty(3)
    Rw, eye = np.empty((3, 3)), np.eye(3)
    W = np.empty((3, 3, 3))
    for r in range(B):
        _fk(q[r], order, parent, jtype, R_off, t_off, axis, D, off, mobile, R, t)
        hit[r] = _env_hit(R, t, bodies, body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_c,
                          el_R, el_h, el_r, box_c, box_R, box_h, box_aabb, eps, bc, c, Rw, eye, W)
        if want_aabb:
            for i in range(3):
                aabb[r, i] = np.inf
                aabb[r, 3 + i] = -np.inf
            for e in range(E):
                _world_box(R, t, el_body[e], el_c[e], el_R[e], c, Rw)
                for i in range(3):
                    ext = abs(Rw[i, 0]) * el_h[e, 0] + abs(Rw[i, 1]) * el_h[e, 1] + abs(Rw[i, 2]) * el_h[e, 2]
                    aabb[r, i] = min(aabb[r, i], c[i] - ext)
                    aabb[r, 3 + i] = max(aabb[r, 3 + i], c[i] + ext)
    return hit, aabb


# ---------------------------------------------------------------------------------------------- occlusion
@jit
def _slab(o, d, half, count_inside, eps):  # pragma: no cover - compiled
    """Slab test of the segment o -> o + d against a box centred at the origin with half extents ``half`` (box
    frame; perception.occlusion._slab_hits)."""
    t_in, t_out = -np.inf, np.inf
    for j in range(3):
        dj = d[j] if abs(d[j]) >= eps else eps
        inv = 1.0 / dj
        mid = -o[j] * inv
        spread = half[j] * abs(inv)
        t_in = max(t_in, mid - spread)
        t_out = min(t_out, mid + spread)
    hit = t_in <= t_out and t_out > 0.0 and t_in < 1.0
    if not count_inside:
        hit = hit and t_in > 0.0
    return hit


@jit
def occlusion(pos, pts_local, centre_local, fat_half, box_c, box_R, box_h, count_inside,
              eps):  # pragma: no cover - compiled
    """Occlusion scores of Alg. 2 (B,): the fraction of the rays from each camera position (B, 3) to the target's M
    sample points (given in every box frame, (M, K, 3)) that a box blocks (perception.occlusion.occlusion_scores:
    the camera -> centre segment against the boxes inflated by the points' radius first, then the M rays against
    the candidate boxes)."""
    B, M, K = pos.shape[0], pts_local.shape[0], box_c.shape[0]
    out = np.zeros(B)
    o, d = np.empty(3), np.empty(3)
    blocked = np.zeros(M, np.bool_)
    for b in range(B):
        blocked[:] = False
        for k in range(K):
            for i in range(3):
                o[i] = box_R[k, 0, i] * (pos[b, 0] - box_c[k, 0]) + box_R[k, 1, i] * (pos[b, 1] - box_c[k, 1]) + \
                    box_R[k, 2, i] * (pos[b, 2] - box_c[k, 2])
                d[i] = centre_local[k, i] - o[i]
            if not _slab(o, d, fat_half[k], True, eps):
                continue
            for m in range(M):
                if blocked[m]:
                    continue
                for i in range(3):
                    d[i] = pts_local[m, k, i] - o[i]
                if _slab(o, d, box_h[k], count_inside, eps):
                    blocked[m] = True
        n = 0
        for m in range(M):
            n += blocked[m]
        out[b] = n / M
    return out


# ---------------------------------------------------------------------------------------------- motion
@jit
def _wrap(a):  # pragma: no cover - compiled
    return ((a + math.pi) % (2.0 * math.pi)) - math.pi


@jit
def _base_plan(qa, qb):  # pragma: no cover - compiled
    """Heading of the straight part and the phase lengths (rot1, trans, rot2) of the rotate-translate-rotate base
    motion qa -> qb (motion.DiffDriveMotion._base_plan)."""
    dx, dy = qb[0] - qa[0], qb[1] - qa[1]
    d = math.sqrt(dx * dx + dy * dy)
    fwd = math.atan2(dy, dx)
    rev = _wrap(fwd + math.pi)
    cost_f = abs(_wrap(fwd - qa[2])) + abs(_wrap(qb[2] - fwd))
    cost_r = abs(_wrap(rev - qa[2])) + abs(_wrap(qb[2] - rev))
    phi = rev if cost_r < cost_f else fwd
    if d < 1e-6:
        phi = qa[2]
    return phi, _wrap(phi - qa[2]), d, _wrap(qb[2] - phi)


@jit
def _distance(qa, qb, w_rot, mobile):  # pragma: no cover - compiled
    s, j0 = 0.0, 3 if mobile else 0
    for i in range(j0, qa.shape[0]):
        s += (qb[i] - qa[i]) ** 2
    if not mobile:
        return math.sqrt(s)
    _, r1, d, r2 = _base_plan(qa, qb)
    return w_rot * (abs(r1) + abs(r2)) + d + math.sqrt(s)


@jit
def distance(qa, qb, w_rot, mobile):  # pragma: no cover - compiled
    """Motion cost (E,) of the local motions qa -> qb (E, dof): w_rot (|dtheta_1| + |dtheta_2|) + |dxy| +
    ||dq_joints|| on a differential-drive base, the Euclidean distance otherwise (DiffDriveMotion.distance)."""
    out = np.empty(qa.shape[0])
    for r in range(qa.shape[0]):
        out[r] = _distance(qa[r], qb[r], w_rot, mobile)
    return out


@jit
def interpolate(qa, qb, s, w_rot, mobile):  # pragma: no cover - compiled
    """Configurations at fractions s (E,) of the local motions qa -> qb (E, dof): the base runs through its three
    phases in proportion to their weighted lengths, the joints linearly (DiffDriveMotion.interpolate)."""
    E, dof = qa.shape
    out = np.empty((E, dof))
    for r in range(E):
        a, b, f = qa[r], qb[r], s[r]
        if not mobile:
            for i in range(dof):
                out[r, i] = a[i] + (b[i] - a[i]) * f
            continue
        _, r1, d, r2 = _base_plan(a, b)
        l1, l2, l3 = w_rot * abs(r1), d, w_rot * abs(r2)
        total = max(l1 + l2 + l3, 1e-12)
        u = f * total
        f1 = min(max(u / max(l1, 1e-12), 0.0), 1.0) if l1 > 0 else 1.0
        f2 = min(max((u - l1) / max(l2, 1e-12), 0.0), 1.0) if l2 > 0 else 1.0
        f3 = min(max((u - l1 - l2) / max(l3, 1e-12), 0.0), 1.0) if l3 > 0 else (1.0 if f >= 1 else 0.0)
        out[r, 0] = a[0] + (b[0] - a[0]) * f2
        out[r, 1] = a[1] + (b[1] - a[1]) * f2
        out[r, 2] = _wrap(a[2] + r1 * f1 + r2 * f3)
        for i in range(3, dof):
            out[r, i] = a[i] + (b[i] - a[i]) * f
    return out


@jit
def pieces(a, b, resolution, max_steps, include_start, w_rot, mobile):  # pragma: no cover - compiled
    """Points every ``resolution`` (motion cost) on the straight joint-space pieces a[i] -> b[i] (theta the short
    way): n = ceil(length / resolution) steps clamped to [1, max_steps], points at k / n for k = 0 (or 1) .. n - 1.
    Returns (piece index (P,), points (P, dof)) (Edges.pieces)."""
    E, dof = a.shape
    n = np.empty(E, np.int64)
    total = 0
    for r in range(E):
        n[r] = min(max(int(math.ceil(_distance(a[r], b[r], w_rot, mobile) / resolution)), 1), max_steps)
        total += n[r] if include_start else n[r] - 1
    seg = np.empty(total, np.int64)
    pts = np.empty((total, dof))
    diff = np.empty(dof)
    p = 0
    for r in range(E):
        for i in range(dof):
            diff[i] = b[r, i] - a[r, i]
        if mobile:
            diff[2] = _wrap(diff[2])
        for k in range(0 if include_start else 1, n[r]):
            frac = k / n[r]
            seg[p] = r
            for i in range(dof):
                pts[p, i] = a[r, i] + diff[i] * frac
            p += 1
    return seg, pts


@jit
def nearest(qq, rm, k, w_rot, mobile):  # pragma: no cover - compiled
    """The k roadmap configurations rm (N, dof) nearest to each query configuration qq (Q, dof) under the motion
    metric (DiffDriveMotion.distance): indices (Q, k) sorted by distance (ties by index). Rows whose lower bound
    |dxy| + ||dq_joints|| (the metric without its base rotations) exceeds the current k-th distance are skipped, so
    only a few exact distances are evaluated."""
    Q, N, dof = qq.shape[0], rm.shape[0], rm.shape[1]
    out = np.empty((Q, k), np.int64)
    bd = np.empty(k)
    bi = np.empty(k, np.int64)
    j0 = 3 if mobile else 0
    for qi in range(Q):
        a = qq[qi]
        n = 0
        for r in range(N):
            b = rm[r]
            s = 0.0
            for i in range(j0, dof):
                s += (b[i] - a[i]) ** 2
            lb = math.sqrt(s)
            if mobile:
                lb += math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2)
            if n == k and lb > bd[k - 1]:
                continue
            d = _distance(a, b, w_rot, mobile)
            if n == k and d >= bd[k - 1]:
                continue
            p = n if n < k else k - 1  # insert, keeping (distance, index) order; ties keep the earlier index first
            while p > 0 and bd[p - 1] > d:
                if p < k:
                    bd[p], bi[p] = bd[p - 1], bi[p - 1]
                p -= 1
            bd[p], bi[p] = d, r
            if n < k:
                n += 1
        for j in range(k):
            out[qi, j] = bi[j]
    return out


@jit
def edge_knot_seeds(qa, qb, n_interp, w_rot, mobile):  # pragma: no cover - compiled
    """Knots of the local motions qa -> qb (E, dof) before the camera joints re-aim (PSPRM.edge_knots): the ends,
    the base's two drive corners and the N Eq. 1 samples s = i / (N + 1), sorted along the motion (stable), and the
    positions (E, N) of the N samples among them. Returns (knots (E, M, dof), interior (E, N))."""
    E, dof = qa.shape
    nc = 2 if mobile else 0
    M = n_interp + nc + 2
    knots = np.empty((E, M, dof))
    interior = np.empty((E, n_interp), np.int64)
    s_all = np.empty(M)
    order = np.empty(M, np.int64)
    for r in range(E):
        a, b = qa[r], qb[r]
        s_all[0] = 0.0
        for i in range(n_interp):
            s_all[1 + i] = (i + 1) / (n_interp + 1)
        if mobile:
            _, r1, d, r2 = _base_plan(a, b)
            l1, l2, l3 = w_rot * abs(r1), d, w_rot * abs(r2)
            tot = max(l1 + l2 + l3, 1e-12)
            s_all[1 + n_interp] = l1 / tot
            s_all[2 + n_interp] = (l1 + l2) / tot
        s_all[M - 1] = 1.0
        for i in range(M):  # stable insertion sort of the fractions
            order[i] = i
            p = i
            while p > 0 and s_all[order[p - 1]] > s_all[i]:
                order[p] = order[p - 1]
                p -= 1
            order[p] = i
        for p in range(M):
            if 1 <= order[p] <= n_interp:
                interior[r, order[p] - 1] = p
        ar, br = np.empty((M, dof)), np.empty((M, dof))
        sr = np.empty(M)
        for p in range(M):
            ar[p] = a
            br[p] = b
            sr[p] = s_all[order[p]]
        knots[r] = interpolate(ar, br, sr, w_rot, mobile)
    return knots, interior


# ---------------------------------------------------------------------------------------------- surrogate features
@jit
def pose_features(cam, tgt, derived):  # pragma: no cover - compiled
    """The surrogate's pose features (B, 9 or 14) of camera poses (B, 4, 4) and one target pose (4, 4): the
    target's position t = R_c^T (p_t - p_c) and first two axes R_c^T R_t[:, :2] in the optical frame, then distance,
    bearing cosine, facing cosine and the clipped image-plane coordinates (perception.surrogate
    relative_pose_features / derived_features)."""
    B = cam.shape[0]
    F = 14 if derived else 9
    out = np.empty((B, F))
    for b in range(B):
        for i in range(3):
            s = 0.0
            for j in range(3):
                s += cam[b, j, i] * (tgt[j, 3] - cam[b, j, 3])
            out[b, i] = s
            for c in range(2):
                s = 0.0
                for j in range(3):
                    s += cam[b, j, i] * tgt[j, c]
                out[b, 3 + 3 * c + i] = s
        if derived:
            tx, ty, tz = out[b, 0], out[b, 1], out[b, 2]
            dist = max(math.sqrt(tx * tx + ty * ty + tz * tz), 1e-9)
            out[b, 9] = dist
            out[b, 10] = tz / dist
            out[b, 11] = -(out[b, 3] * tx + out[b, 4] * ty + out[b, 5] * tz) / dist
            tzc = max(tz, 1e-3)
            out[b, 12] = min(max(tx / tzc, -4.0), 4.0)
            out[b, 13] = min(max(ty / tzc, -4.0), 4.0)
    return out


# ---------------------------------------------------------------------------------------------- surrogate MLP
@jit
def mlp(x, w1, b1, ws, bs, wo, bo):  # pragma: no cover - compiled
    """Surrogate MLP (Alg. 2, line 4) on a few rows, float32: h = relu(x W1 + b1), then relu(h W_l + b_l) per hidden
    layer, score = sigmoid(h w_o + b_o). Rows are processed together so each weight row is read once per layer;
    inputs a ReLU zeroed are skipped."""
    B, F = x.shape
    H = b1.shape[0]
    h = np.empty((B, H), np.float32)
    h2 = np.empty((B, H), np.float32)
    for r in range(B):
        h[r, :] = b1
    for k in range(F):
        wk = w1[k]
        for r in range(B):
            xk = x[r, k]
            for j in range(H):
                h[r, j] += xk * wk[j]
    for r in range(B):
        for j in range(H):
            h[r, j] = max(h[r, j], np.float32(0.0))
    for layer in range(ws.shape[0]):
        for r in range(B):
            h2[r, :] = bs[layer]
        W = ws[layer]
        for k in range(H):
            wk = W[k]
            for r in range(B):
                hk = h[r, k]
                if hk > 0:
                    for j in range(H):
                        h2[r, j] += hk * wk[j]
        for r in range(B):
            for j in range(H):
                h[r, j] = max(h2[r, j], np.float32(0.0))
    out = np.empty(B, np.float32)
    for r in range(B):
        s = bo
        for k in range(H):
            s += h[r, k] * wo[k]
        out[r] = 1.0 / (1.0 + math.exp(-s))
    return out


# ---------------------------------------------------------------------------------------------- a query's edges
@jit
def _round32(a):  # pragma: no cover - compiled
    """Round a C-contiguous float64 array to float32 values in place: the torch paths hold the planner's float32
    tensors between the kernels, so the fused kernels below round where those paths cast."""
    flat = a.reshape(-1)
    for i in range(flat.shape[0]):
        flat[i] = np.float64(np.float32(flat[i]))


@jit
def query_knots(qa, qb, n_interp, w_rot, mobile, track, r32, order, parent, jtype, R_off, t_off, axis, D, off,
                rmobile, cam_body, cam_R, cam_t, target, cols, line, min_distance, far, th, tv, margin, lo, hi, tol,
                max_iters, damping, max_step):  # pragma: no cover - compiled
    """PSPRM.edge_knots of a few edges in one call: :func:`edge_knot_seeds`, then (``track``) the interior knots'
    non-base camera joints re-aimed by :func:`project` (``max_iters`` = track_iters); with ``r32`` rounded to float32
    after each stage, as the float32 torch path is. Returns (knots (E, M, dof), interior (E, N))."""
    knots, interior = edge_knot_seeds(qa, qb, n_interp, w_rot, mobile)
    if r32:
        _round32(knots)
    E, M, dof = knots.shape
    if track and M > 2 and cols.shape[0] > 0:
        inner = np.empty((E * (M - 2), dof))
        for e in range(E):
            for m in range(M - 2):
                inner[e * (M - 2) + m] = knots[e, m + 1]
        qn, _ = project(inner, order, parent, jtype, R_off, t_off, axis, D, off, rmobile, cam_body, cam_R, cam_t,
                        target, cols, line, min_distance, far, th, tv, margin, lo, hi, tol, max_iters, damping,
                        max_step)
        if r32:
            _round32(qn)
        for e in range(E):
            for m in range(M - 2):
                knots[e, m + 1] = qn[e * (M - 2) + m]
    return knots, interior


@jit
def neural_scores(q, r32, chain, parent, jtype, R_off, t_off, axis, D, off, rmobile, cam_body, cam_R, cam_t, tgt,
                  derived, w1, b1, ws, bs, wo, bo, has_occ, pts_local, centre_local, fat_half, oc, oR, oh, count_inside,
                  eps_dir, tau, mlp_rows):  # pragma: no cover - compiled
    """Camera poses (B, 4, 4) of configurations q (B, dof) and their raw neural scores (B,) float32 (NeuralScorer.score
    of RobotModel.camera_poses: pose features, :func:`mlp` on chunks of ``mlp_rows`` views, zero where the ray-cast
    occlusion score exceeds ``tau``; Alg. 2, lines 4-7), rounded to float32 after the poses with ``r32``."""
    cp = camera_poses(q, chain, parent, jtype, R_off, t_off, axis, D, off, rmobile, cam_body, cam_R, cam_t)
    if r32:
        _round32(cp)
    feats = pose_features(cp, tgt, derived)
    f32 = feats.astype(np.float32)
    sc = np.empty(f32.shape[0], np.float32)
    for c0 in range(0, f32.shape[0], mlp_rows):  # the scorer's calls: one per batch of at most mlp_rows views
        c1 = min(c0 + mlp_rows, f32.shape[0])
        sc[c0:c1] = mlp(f32[c0:c1], w1, b1, ws, bs, wo, bo)
    if has_occ:
        pos = np.empty((cp.shape[0], 3))
        for r in range(cp.shape[0]):
            for i in range(3):
                pos[r, i] = cp[r, i, 3]
        occ = occlusion(pos, pts_local, centre_local, fat_half, oc, oR, oh, count_inside, eps_dir)
        for r in range(cp.shape[0]):
            if (np.float32(occ[r]) > np.float32(tau)) if r32 else (occ[r] > tau):
                sc[r] = np.float32(0.0)
    return cp, sc


@jit
def check_score_knots(knots, interior, do_check, do_score, r32, resolution, max_steps, w_rot, mobile,
                      all_bodies, parent, jtype, R_off, t_off, axis, D, off, rmobile, lower, upper, bodies, body_c,
                      body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c, el_R, el_h, el_r,
                      pairs, pair_els, box_c, box_R, box_h, box_aabb, eps,
                      chain, cam_body, cam_R, cam_t, tgt, derived, w1, b1, ws, bs, wo, bo,
                      has_occ, pts_local, centre_local, fat_half, oc, oR, oh, count_inside, eps_dir,
                      tau, mlp_rows):  # pragma: no cover - compiled
    """The lazy verification of a few edges from their knots (E, M, dof), in one call (Verification.verify_edges):

    - ``do_check`` (E,): collision flags of the interior knots and of the points every ``resolution`` on the
      pieces between consecutive knots (Edges.knots_valid, dense);
    - ``do_score`` (E,), for edges found free: the camera poses of the Eq. 1 points (both ends and the N interior
      samples, Scoring.eq1_cameras) and their raw surrogate scores (pose features, :func:`mlp`), zeroed where the
      ray-cast occlusion score exceeds ``tau`` (Alg. 2, lines 4-7; NeuralScorer.score); the MLP runs on chunks of
      ``mlp_rows`` views, edge-aligned (the rows the compiled scorer takes per call).

    With ``r32``, rounded to float32 where the float32 torch path casts. Returns (free (E,), cameras
    (E, N + 2, 4, 4), raw scores (E, N + 2) float32; rows not scored are zero)."""
    E, M, dof = knots.shape
    N = interior.shape[1]
    free = np.ones(E, np.bool_)
    # collision (Edges.knots_valid): the edges to check, their interior knots and then their dense pieces
    nck = 0
    for e in range(E):
        if do_check[e]:
            nck += 1
    if nck > 0:
        # first the interior knots of every edge to check, then the dense pieces of the edges whose knots are free
        # (an obstacle that moved onto a path blocks most of its edges at a knot already)
        edge_of = np.empty(nck, np.int64)
        j = 0
        for e in range(E):
            if do_check[e]:
                edge_of[j] = e
                j += 1
        q = np.empty((nck * (M - 2), dof))
        for j in range(nck):
            for m in range(M - 2):
                q[j * (M - 2) + m] = knots[edge_of[j], m + 1]
        flags = check(q, False, all_bodies, parent, jtype, R_off, t_off, axis, D, off, rmobile, lower, upper, bodies,
                      body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c, el_R, el_h,
                      el_r, pairs, pair_els, box_c, box_R, box_h, box_aabb, eps)
        for r in range(q.shape[0]):
            if flags[r, 0] or flags[r, 1] or flags[r, 2]:
                free[edge_of[r // (M - 2)]] = False
        nd = 0
        for j in range(nck):
            if free[edge_of[j]]:
                nd += 1
        if nd > 0:
            a = np.empty((nd * (M - 1), dof))
            b = np.empty((nd * (M - 1), dof))
            dense_of = np.empty(nd, np.int64)
            i = 0
            for j in range(nck):
                e = edge_of[j]
                if free[e]:
                    dense_of[i] = e
                    for m in range(M - 1):
                        a[i * (M - 1) + m] = knots[e, m]
                        b[i * (M - 1) + m] = knots[e, m + 1]
                    i += 1
            seg, pts = pieces(a, b, resolution, max_steps, False, w_rot, mobile)
            if r32:
                _round32(pts)
            flags = check(pts, False, all_bodies, parent, jtype, R_off, t_off, axis, D, off, rmobile, lower, upper,
                          bodies, body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c,
                          el_R, el_h, el_r, pairs, pair_els, box_c, box_R, box_h, box_aabb, eps)
            for r in range(pts.shape[0]):
                if flags[r, 0] or flags[r, 1] or flags[r, 2]:
                    free[dense_of[seg[r] // (M - 1)]] = False
    cams = np.zeros((E, N + 2, 4, 4))
    raw = np.zeros((E, N + 2), np.float32)
    ns = 0
    for e in range(E):
        if do_score[e] and free[e]:
            ns += 1
    if ns == 0:
        return free, cams, raw
    pts_q = np.empty((ns * (N + 2), dof))
    edge_s = np.empty(ns, np.int64)
    j = 0
    for e in range(E):
        if do_score[e] and free[e]:
            edge_s[j] = e
            base = j * (N + 2)
            pts_q[base] = knots[e, 0]
            for i in range(N):
                pts_q[base + 1 + i] = knots[e, interior[e, i]]
            pts_q[base + N + 1] = knots[e, M - 1]
            j += 1
    cp, sc = neural_scores(pts_q, r32, chain, parent, jtype, R_off, t_off, axis, D, off, rmobile, cam_body, cam_R,
                           cam_t, tgt, derived, w1, b1, ws, bs, wo, bo, has_occ, pts_local, centre_local, fat_half, oc,
                           oR, oh, count_inside, eps_dir, tau, mlp_rows)
    for j in range(ns):
        e = edge_s[j]
        for p in range(N + 2):
            cams[e, p] = cp[j * (N + 2) + p]
            raw[e, p] = sc[j * (N + 2) + p]
    return free, cams, raw


@jit
def verify_edges(store_k, store_i, ids, compute, qa, qb, flip, n_interp, w_rot, mobile, track, r32, order, parent,
                 jtype, R_off, t_off, axis, D, off, rmobile, cam_body, cam_R, cam_t, target, cols, line, min_distance,
                 far, th, tv, margin, lo, hi, tol, max_iters, damping, max_step, do_check, do_score, resolution,
                 max_steps, all_bodies, lower, upper, bodies, body_c, body_r, body_box_c, body_box_h, el_start,
                 el_count, el_order, el_body, el_c, el_R, el_h, el_r, pairs, pair_els, box_c, box_R, box_h, box_aabb,
                 eps, tgt, derived, w1, b1, ws, bs, wo, bo, has_occ, pts_local, centre_local, fat_half, oc, oR, oh,
                 count_inside, eps_dir, tau, mlp_rows):  # pragma: no cover - compiled
    """A lazy search's verification of edges ``ids`` (E,) in one call (Verification.verify_edges): first the knots of the
    ``compute`` ones (the query's connection edges, from their ends qa -> qb (C, dof), :func:`query_knots`) are
    written into the knot store (``store_k`` (cap, M, dof), ``store_i`` (cap, N): the planner's tensors), reversed
    where ``flip`` (C,) (the store keeps an edge's knots in its u -> v direction), then every edge is checked and
    scored from the store by :func:`check_score_knots` (the camera chain is ``order``; ``all_bodies`` the collision
    bodies' FK order). Returns (free (E,), cameras (E, N + 2, 4, 4), raw scores (E, N + 2))."""
    E = ids.shape[0]
    M, dof, N = store_k.shape[1], store_k.shape[2], store_i.shape[1]
    if qa.shape[0] > 0:
        kn, ki = query_knots(qa, qb, n_interp, w_rot, mobile, track, r32, order, parent, jtype, R_off, t_off, axis,
                             D, off, rmobile, cam_body, cam_R, cam_t, target, cols, line, min_distance, far, th, tv,
                             margin, lo, hi, tol, max_iters, damping, max_step)
        j = 0
        for e in range(E):
            if compute[e]:
                row = ids[e]
                for m in range(M):
                    src = M - 1 - m if flip[j] else m
                    for d in range(dof):
                        store_k[row, m, d] = kn[j, src, d]
                for i in range(N):
                    store_i[row, i] = M - 1 - ki[j, N - 1 - i] if flip[j] else ki[j, i]
                j += 1
    knots = np.empty((E, M, dof))
    interior = np.empty((E, N), np.int64)
    for e in range(E):
        for m in range(M):
            for d in range(dof):
                knots[e, m, d] = store_k[ids[e], m, d]
        for i in range(N):
            interior[e, i] = store_i[ids[e], i]
    return check_score_knots(knots, interior, do_check, do_score, r32, resolution, max_steps, w_rot, mobile,
                             all_bodies, parent, jtype, R_off, t_off, axis, D, off, rmobile, lower, upper, bodies,
                             body_c, body_r, body_box_c, body_box_h, el_start, el_count, el_order, el_body, el_c, el_R,
                             el_h, el_r, pairs, pair_els, box_c, box_R, box_h, box_aabb, eps, order, cam_body, cam_R,
                             cam_t, tgt, derived, w1, b1, ws, bs, wo, bo, has_occ, pts_local, centre_local, fat_half,
                             oc, oR, oh, count_inside, eps_dir, tau, mlp_rows)
