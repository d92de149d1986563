"""Numba kernels of the neural perception score (Alg. 2; re-exported by :mod:`psprm_core.kernels._fast_numba`): ray-cast
occlusion scores, the surrogate's pose features and its MLP.
"""

import math

import numpy as np

from ._fast_kinematics import jit

#: SHA-256 of the kernel modules this one imports from, directly or through them (their sources with this line
#: blanked; checked by tests/test_fastpath.py). numba's disk cache checks only the source file of the kernel it
#: loads, not those of the kernels and the decorator it was compiled with: a change there must change this file
#: too, or the cached kernels here would keep the old code.
CALLEES_SHA256 = "d3f9d53d952a5c1aa7c8e20a6dc88410f853ae68eef61a98e4bb7b643a605a1d"


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
def occlusion(pos, occ):  # pragma: no cover - compiled
    """Occlusion scores of Alg. 2 (B,): the fraction of the rays from each camera position (B, 3) to the target's M
    sample points (given in every box frame, (M, K, 3)) that a box blocks, of the OcclusionPack ``occ``
    (perception.occlusion.occlusion_scores: the camera -> centre segment against the boxes inflated by the points'
    radius first, then the M rays against the candidate boxes)."""
    pts_local, centre_local, fat_half, box_c, box_R = occ.pts_local, occ.centre_local, occ.fat_half, occ.c, occ.R
    box_h, count_inside, eps = occ.h, occ.count_inside, occ.eps
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
def mlp(x, net):  # pragma: no cover - compiled
    """Surrogate MLP (Alg. 2, line 4) of the MlpPack ``net`` on a few rows, float32: h = relu(x W1 + b1), then
    relu(h W_l + b_l) per hidden layer, score = sigmoid(h w_o + b_o). Rows are processed together so each weight row
    is read once per layer; inputs a ReLU zeroed are skipped."""
    w1, b1, ws, bs, wo, bo = net.w1, net.b1, net.ws, net.bs, net.wo, net.bo
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

