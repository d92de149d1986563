"""Fused numba kernels of a query's edges (re-exported by :mod:`psprm_core.kernels._fast_numba`): an edge's knots with
the camera joints re-aimed, the neural scores of configurations, and the lazy verification (collision checks and
scoring) of a few edges in one call. They call the kernels of the other modules, imported at module level
(numba resolves them when it compiles).
"""

import numpy as np

from ._fast_kinematics import camera_poses, check, jit
from ._fast_motion import edge_knot_seeds, pieces
from ._fast_projection import project
from ._fast_scoring import mlp, occlusion, pose_features

#: SHA-256 of the kernel modules this one imports from, directly or through them (their sources with this line
#: blanked; checked by tests/test_fastpath.py). numba's disk cache checks only the source file of the kernel it
#: loads, not those of the kernels and the decorator it was compiled with: a change there must change this file
#: too, or the cached kernels here would keep the old code.
CALLEES_SHA256 = "61159535db4c79172bfd6f4c38c36ed3518555260baceb741a20d54d6c497ab1"


# ---------------------------------------------------------------------------------------------- a query's edges
@jit
def _round32(a):  # pragma: no cover - compiled
    """Round a C-contiguous float64 array to float32 values in place: the torch paths hold the planner's float32
    tensors between the kernels, so the fused kernels below round where those paths cast."""
    flat = a.reshape(-1)
    for i in range(flat.shape[0]):
        flat[i] = np.float64(np.float32(flat[i]))


@jit
def query_knots(qa, qb, opts, robot, view, solver):  # pragma: no cover - compiled
    """PSPRM.edge_knots of a few edges in one call (EdgeOpts ``opts``): :func:`edge_knot_seeds`, then (``track``)
    the interior knots' non-base camera joints re-aimed by :func:`project` of the RobotPack ``robot``, the ViewPack
    ``view`` and the SolverPack ``solver`` (``max_iters`` = track_iters); with ``r32`` rounded to float32 after each
    stage, as the float32 torch path is. Returns (knots (E, M, dof), interior (E, N))."""
    track, r32, cols = opts.track, opts.r32, solver.cols
    knots, interior = edge_knot_seeds(qa, qb, opts.n_interp, opts.motion.w_rot, opts.motion.mobile)
    if r32:
        _round32(knots)
    E, M, dof = knots.shape
    if track and M > 2 and cols.shape[0] > 0:
        inner = np.empty((E * (M - 2), dof))
        for e in range(E):
            for m in range(M - 2):
                inner[e * (M - 2) + m] = knots[e, m + 1]
        qn, _ = project(inner, robot, view, solver)
        if r32:
            _round32(qn)
        for e in range(E):
            for m in range(M - 2):
                knots[e, m + 1] = qn[e * (M - 2) + m]
    return knots, interior


@jit
def neural_scores(q, r32, mlp_rows, robot, scorer):  # pragma: no cover - compiled
    """Camera poses (B, 4, 4) of configurations q (B, dof) of the RobotPack ``robot`` and their raw neural scores (B,)
    float32 of the ScorerPack ``scorer`` (NeuralScorer.score of RobotModel.camera_poses: pose features, :func:`mlp`
    on chunks of ``mlp_rows`` views, zero where the ray-cast occlusion score exceeds ``tau``; Alg. 2, lines 4-7),
    rounded to float32 after the poses with ``r32``."""
    tgt, derived, net, has_occ, tau = scorer.tgt, scorer.derived, scorer.mlp, scorer.has_occ, scorer.tau
    cp = camera_poses(q, robot)
    if r32:
        _round32(cp)
    feats = pose_features(cp, tgt, derived)
    f32 = feats.astype(np.float32)
    sc = np.empty(f32.shape[0], np.float32)
    for c0 in range(0, f32.shape[0], mlp_rows):  # the scorer's calls: one per batch of at most mlp_rows views
        c1 = min(c0 + mlp_rows, f32.shape[0])
        sc[c0:c1] = mlp(f32[c0:c1], net)
    if has_occ:
        pos = np.empty((cp.shape[0], 3))
        for r in range(cp.shape[0]):
            for i in range(3):
                pos[r, i] = cp[r, i, 3]
        occ = occlusion(pos, scorer.occ)
        for r in range(cp.shape[0]):
            if (np.float32(occ[r]) > np.float32(tau)) if r32 else (occ[r] > tau):
                sc[r] = np.float32(0.0)
    return cp, sc


@jit
def check_score_knots(knots, interior, flags, opts, robot, col, scorer):  # pragma: no cover - compiled
    """The lazy verification of a few edges from their knots (E, M, dof), in one call (Verification.verify_edges),
    with the EdgeOpts ``opts``, the RobotPack ``robot``, the CollisionPack ``col`` and the ScorerPack ``scorer``;
    ``flags`` = (do_check, do_score):

    - ``do_check`` (E,): collision flags of the interior knots and of the points every ``resolution`` on the
      pieces between consecutive knots (Edges.knots_valid, dense);
    - ``do_score`` (E,), for edges found free: the camera poses of the Eq. 1 points (both ends and the N interior
      samples, Scoring.eq1_cameras) and their raw surrogate scores (pose features, :func:`mlp`), zeroed where the
      ray-cast occlusion score exceeds ``tau`` (Alg. 2, lines 4-7; NeuralScorer.score); the MLP runs on chunks of
      ``mlp_rows`` views, edge-aligned (the rows the compiled scorer takes per call).

    With ``r32``, rounded to float32 where the float32 torch path casts. Returns (free (E,), cameras
    (E, N + 2, 4, 4), raw scores (E, N + 2) float32; rows not scored are zero)."""
    do_check, do_score = flags
    r32, resolution, max_steps, mlp_rows = opts.r32, opts.resolution, opts.max_steps, opts.mlp_rows
    w_rot, mobile = opts.motion.w_rot, opts.motion.mobile
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
        hits = check(q, False, robot, col)
        for r in range(q.shape[0]):
            if hits[r, 0] or hits[r, 1] or hits[r, 2]:
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
            hits = check(pts, False, robot, col)
            for r in range(pts.shape[0]):
                if hits[r, 0] or hits[r, 1] or hits[r, 2]:
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
    cp, sc = neural_scores(pts_q, r32, mlp_rows, robot, scorer)
    for j in range(ns):
        e = edge_s[j]
        for p in range(N + 2):
            cams[e, p] = cp[j * (N + 2) + p]
            raw[e, p] = sc[j * (N + 2) + p]
    return free, cams, raw


@jit
def verify_edges(store, ids, new, flags, opts, robot, col, view, solver, scorer):  # pragma: no cover - compiled
    """A lazy search's verification of edges ``ids`` (E,) in one call (Verification.verify_edges): first the knots of
    the ``compute`` ones (``new`` = (compute (E,), qa, qb, flip): the query's connection edges, from their ends qa -> qb
    (C, dof), :func:`query_knots`) are written into the knot store (``store`` = (store_k (cap, M, dof), store_i
    (cap, N)): the planner's tensors), reversed where ``flip`` (C,) (the store keeps an edge's knots in its u -> v
    direction), then every edge is checked and scored from the store by :func:`check_score_knots` (``flags`` =
    (do_check, do_score)). Returns (free (E,), cameras (E, N + 2, 4, 4), raw scores (E, N + 2))."""
    store_k, store_i = store
    compute, qa, qb, flip = new
    E = ids.shape[0]
    M, dof, N = store_k.shape[1], store_k.shape[2], store_i.shape[1]
    if qa.shape[0] > 0:
        kn, ki = query_knots(qa, qb, opts, robot, view, solver)
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
    return check_score_knots(knots, interior, flags, opts, robot, col, scorer)

