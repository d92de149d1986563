"""Numba kernels of the differential-drive motion metric and local motions (re-exported by
:mod:`psprm_core.kernels._fast_numba`): distance, interpolation, the points along straight pieces, the nearest roadmap
configurations and the knots of an edge before its camera joints re-aim.
"""

import math

import numpy as np

from ._fast_kinematics import jit

#: SHA-256 of the kernel modules this one imports from, directly or through them (their sources with this line
#: blanked; checked by tests/test_fastpath.py). numba's disk cache checks only the source file of the kernel it
#: loads, not those of the kernels and the decorator it was compiled with: a change there must change this file
#: too, or the cached kernels here would keep the old code.
CALLEES_SHA256 = "d3f9d53d952a5c1aa7c8e20a6dc88410f853ae68eef61a98e4bb7b643a605a1d"


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

