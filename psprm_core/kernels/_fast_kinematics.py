"""Numba kernels of the robot's body tree (re-exported by :mod:`psprm_core.kernels._fast_numba`): forward kinematics,
camera poses and the oriented-box collision check (joint limits, environment, self-collision), and the kernels'
decorator ``jit`` (compiled on first call, cached on disk with ``cache=True``) and joint type codes shared by the
other kernel modules. They follow the torch implementations step by step in float64.
"""

import math

import numpy as np
from numba import njit

from ._fast_packs import PRISMATIC, REVOLUTE, ROOT  # noqa: F401 - the joint type codes, re-exported

#: SHA-256 of the kernel modules this one imports from, directly or through them (their sources with this line
#: blanked; checked by tests/test_fastpath.py). numba's disk cache checks only the source file of the kernel it
#: loads, not those of the kernels and the decorator it was compiled with: a change there must change this file
#: too, or the cached kernels here would keep the old code.
CALLEES_SHA256 = "d49585621181d5aa8386f25dd136da3ec759b526e82aca6f2c6f7bef20b84ac3"

jit = njit(cache=True, nogil=True)


# ---------------------------------------------------------------------------------------------- kinematics
@jit
def _fk(q, order, robot, R, t):  # pragma: no cover - compiled
    """World rotations R (NB, 3, 3) and translations t (NB, 3) of the bodies in ``order`` (root-first, root
    excluded) for one configuration of the body tree ``robot`` (a RobotPack): T_child = T_parent T_origin
    Motion(axis, q D + off) (RobotModel._poses). R[NB] and R[NB + 1] are scratch (the callers allocate NB + 2
    rotations)."""
    parent, jtype, R_off, t_off, axis = robot.parent, robot.jtype, robot.R_off, robot.t_off, robot.axis
    D, off, mobile = robot.D, robot.off, robot.mobile
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
def _camera(R, t, robot, Rc, tc):  # pragma: no cover - compiled
    """Optical-frame pose (Rc, tc) from the camera body's world pose (RobotModel._camera_from_body) of the RobotPack
    ``robot``."""
    cam_body, cam_R, cam_t = robot.cam_body, robot.cam_R, robot.cam_t
    for i in range(3):
        for j in range(3):
            Rc[i, j] = R[cam_body, i, 0] * cam_R[0, j] + R[cam_body, i, 1] * cam_R[1, j] + \
                R[cam_body, i, 2] * cam_R[2, j]
        tc[i] = t[cam_body, i] + R[cam_body, i, 0] * cam_t[0] + R[cam_body, i, 1] * cam_t[1] + \
            R[cam_body, i, 2] * cam_t[2]


@jit
def camera_poses(q, robot):  # pragma: no cover - compiled
    """Camera optical-frame poses (B, 4, 4) of configurations q (B, dof) (RobotModel.camera_poses) of the RobotPack
    ``robot`` (FK along its camera chain)."""
    order = robot.chain
    B, NB = q.shape[0], robot.parent.shape[0]
    out = np.zeros((B, 4, 4))
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    Rc, tc = np.empty((3, 3)), np.empty(3)
    for r in range(B):
        _fk(q[r], order, robot, R, t)
        _camera(R, t, robot, Rc, tc)
        for i in range(3):
            for j in range(3):
                out[r, i, j] = Rc[i, j]
            out[r, i, 3] = tc[i]
        out[r, 3, 3] = 1.0
    return out



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
def _env_hit(R, t, col, bc, c, Rw, eye, W):  # pragma: no cover - compiled
    """Robot (body poses R, t) against the obstacle boxes of the CollisionPack ``col`` (CollisionChecker._env): robot
    bounds vs box bounds, body spheres, body boxes, element spheres, then the exact element-box overlap. bc, c, Rw,
    eye, W: scratch."""
    bodies, body_c, body_r, body_box_c, body_box_h = col.bodies, col.body_c, col.body_r, col.body_box_c, col.body_box_h
    el_start, el_count, el_order, el_c, el_R = col.el_start, col.el_count, col.el_order, col.el_c, col.el_R
    el_h, el_r, eps = col.el_h, col.el_r, col.eps
    box_c, box_R, box_h, box_aabb = col.boxes.c, col.boxes.R, col.boxes.h, col.boxes.aabb
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
def _self_hit(R, t, col, ec, ca, cb, Ra, Rb, W):  # pragma: no cover - compiled
    """Self-collision of the element pairs of the CollisionPack ``col`` (CollisionChecker._pairs_hits): bounding
    spheres of the element centres (computed once, for the elements in ``pair_els``), then the exact overlap. ec, ca,
    cb, Ra, Rb, W: scratch."""
    pairs, pair_els, el_body, el_c, el_R = col.pairs, col.pair_els, col.el_body, col.el_c, col.el_R
    el_h, el_r, eps = col.el_h, col.el_r, col.eps
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
def check(q, detailed, robot, col):  # pragma: no cover - compiled
    """Collision flags (B, 3): joint limits, environment, self (CollisionChecker.check_detailed) of the RobotPack
    ``robot`` and the CollisionPack ``col``. Without ``detailed`` a row stops at its first violation (only the OR of
    the three is meaningful then)."""
    order, lower, upper, bodies = robot.bodies, col.lower, col.upper, col.bodies
    B, dof, NB, E = q.shape[0], q.shape[1], robot.parent.shape[0], col.el_c.shape[0]
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
        _fk(qr, order, robot, R, t)
        out[r, 1] = _env_hit(R, t, col, bc, c, Rw, eye, W)
        if out[r, 1] and not detailed:
            continue
        out[r, 2] = _self_hit(R, t, col, ec, c, c2, Rw, Rw2, W)
    return out


@jit
def env_hits(q, want_aabb, robot, col):  # pragma: no cover - compiled
    """Environment flags (B,) against the boxes of the CollisionPack ``col`` only (no limits, no self-collision:
    CollisionChecker.env_hits) and, with ``want_aabb``, the robot's world bounds (B, 6) = [min xyz, max xyz] of
    every element box (CollisionChecker._aabb: half extents sum_j |(R_b R_e)_ij| h_j), from the same FK."""
    order, bodies, el_body, el_c, el_R, el_h = robot.bodies, col.bodies, col.el_body, col.el_c, col.el_R, col.el_h
    B, NB, E = q.shape[0], robot.parent.shape[0], el_c.shape[0]
    hit = np.zeros(B, np.bool_)
    aabb = np.zeros((B if want_aabb else 0, 6))
    R, t = np.zeros((NB + 2, 3, 3)), np.zeros((NB, 3))
    bc = np.empty((bodies.shape[0], 3))
    c = np.empty(3)
    Rw, eye = np.empty((3, 3)), np.eye(3)
    W = np.empty((3, 3, 3))
    for r in range(B):
        _fk(q[r], order, robot, R, t)
        hit[r] = _env_hit(R, t, col, bc, c, Rw, eye, W)
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

