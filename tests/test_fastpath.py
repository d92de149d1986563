"""Small-batch CPU fast paths (``psprm_core.kernels.fastpath``): the compiled kernels give the torch path's results
(camera poses, manifold projection, collision flags) on random inputs, the planner returns the same paths with them on
and off, and without numba (or for large batches, gradients) every call takes the torch path."""

from __future__ import annotations

import threading
from unittest import mock

import numpy as np
import pytest
import torch

from psprm_core.kernels import edges, fastpath
from psprm_core.kernels.compute import Compute, bulk, bulk_workers
from psprm_core.evaluation.reference import sample_uniform
from psprm_core.problems import random_problems
from psprm_core.collision import CollisionChecker
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.search import search_kernels
from psprm_core.planning.constraints import ProjectionSettings, VisibilityConstraint
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.pipeline import Pipeline
from psprm_core.planning.state import PlannerContext
from psprm_core.planning.roadmap.verification import Verification
from psprm_core.scene import load_scene

ROBOT_SCENES = {"stretch2": "home", "fetchlike": "nursing", "ur5_mobile": "blind_spot_alley"}
TORCH = Compute.make("cpu", kernels="torch")  # the reference: torch operators at every batch size


def _configs(robot, scene, n: int, seed: int) -> np.ndarray:
    """Uniform configurations over the joint limits and the scene's workspace, some outside the limits."""
    rng = np.random.default_rng(seed)
    q = sample_uniform(robot, n, rng, base_box=scene.workspace)
    q[:, 2] = rng.uniform(-4, 4, n)  # theta beyond (-pi, pi]
    q[::37, -1] += 5.0  # beyond the limit
    return q


def _robot_scene(name, load_robot):
    robot = load_robot(name)
    scene = load_scene(resolve_named("scene", ROBOT_SCENES[name]))
    assert scene.robot == name
    return robot, scene


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_camera_poses_match_torch(name, dtype, load_robot):
    robot, scene = _robot_scene(name, load_robot)
    q = torch.as_tensor(_configs(robot, scene, 300, 0), dtype=dtype)
    fast = robot.camera_poses(q)
    ref = robot.using(TORCH).camera_poses(q)
    assert fast.dtype == ref.dtype == dtype and fast.shape == ref.shape
    assert (fast - ref).abs().max() < (1e-12 if dtype == torch.float64 else 1e-5)


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
def test_element_corners_match_torch(name, load_robot):
    """The corners of the collision boxes (the path tolerance's measure): the compiled kernel against torch's body
    poses in float64, box by box and corner by corner."""
    robot, scene = _robot_scene(name, load_robot)
    q = _configs(robot, scene, 200, 3)
    fast = robot.element_corners(q)
    ref = robot.using(TORCH).element_corners(q)
    assert fast.shape == ref.shape == (200, 8 * len(robot.elements.element_body), 3)
    assert np.abs(fast - ref).max() < 1e-12
    assert np.abs(robot.element_corners(q[:1]) - ref[:1]).max() < 1e-12


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("kind", ["line", "frustum"])
def test_projection_matches_torch(name, kind, load_robot):
    """Same iterates in float64 (same steps, same stopping, same converged flags), with all camera joints and with
    the non-base ones only (the edge knots' re-aiming)."""
    robot, scene = _robot_scene(name, load_robot)
    target = scene.target(scene.target_names[0]).center
    c = VisibilityConstraint(robot, kind, target, margin=0.05, min_distance=0.5)
    q = torch.as_tensor(_configs(robot, scene, 150, 1), dtype=torch.float64)
    lo = torch.as_tensor(np.where(np.isfinite(robot.lower), robot.lower, -1e9))
    hi = torch.as_tensor(np.where(np.isfinite(robot.upper), robot.upper, 1e9))
    joints = np.nonzero(c._camera_joints())[0]
    unconverged = 0
    for cols in (None, joints[joints >= 3]):
        for iters in (3, 20):
            ps = ProjectionSettings(max_iters=iters)
            qf, okf = c.project(q, ps, lo, hi, joints=cols)
            qr, okr = c.using(TORCH).project(q, ps, lo, hi, joints=cols)
            assert okf.dtype == torch.bool and torch.equal(okf, okr)
            assert int(okr.sum()) > 0
            unconverged += int((~okr).sum())
            assert (qf - qr).abs().max() < 1e-6  # float rounding, amplified by ill-conditioned steps
    assert unconverged > 0  # both outcomes occur


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_collision_flags_match_torch(name, dtype, load_robot):
    robot, scene = _robot_scene(name, load_robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace, dtype=dtype)
    q = torch.as_tensor(_configs(robot, scene, 600, 2), dtype=dtype)
    q[5, 0] = float("nan")
    fast, bad = checker.check_detailed(q), checker.check(q)
    ref, ref_bad = checker.using(TORCH).check_detailed(q), checker.using(TORCH).check(q)
    for k in ("limits", "environment", "self"):
        assert fast[k].dtype == torch.bool and torch.equal(fast[k], ref[k]), k
        assert 0 < int(ref[k].sum()) < len(q), k  # each kind of collision occurs, and free rows too
    assert torch.equal(bad, ref_bad) and bool(bad[5])
    # a moved obstacle set is picked up (the compiled path caches the boxes by their tensors)
    checker.set_boxes([])
    free = checker.check_detailed(q)
    free_ref = checker.using(TORCH).check_detailed(q)
    assert not free["environment"].any() and torch.equal(free["self"], free_ref["self"])


def _near_contact(checker, q: torch.Tensor, kind: str, n_pairs: int, rng, steps: int = 16) -> tuple:
    """Configurations on both sides of the torch checker's ``kind`` boundary: ``n_pairs`` segments from a free
    configuration (no flag at all) to one flagged ``kind`` (within the limits), bisected ``steps`` times with the
    torch path's flag, both final ends kept. Returns (configurations (2 n_pairs, dof), the final gaps (n_pairs,))."""
    det = checker.using(TORCH).check_detailed(q)
    free = ~(det["limits"] | det["environment"] | det["self"])
    hit = det[kind] & ~det["limits"]
    fi, hi = torch.nonzero(free).flatten().numpy(), torch.nonzero(hit).flatten().numpy()
    assert len(fi) and len(hi), kind  # precondition: both ends exist
    lo_q = q[rng.choice(fi, n_pairs)].clone()
    hi_q = q[rng.choice(hi, n_pairs)].clone()
    for _ in range(steps):
        mid = 0.5 * (lo_q + hi_q)
        m = checker.using(TORCH).check_detailed(mid)[kind]
        hi_q[m], lo_q[~m] = mid[m], mid[~m]
    return torch.cat([lo_q, hi_q]), (hi_q - lo_q).norm(dim=1)


NEAR_CONTACT_N = 20000


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
def test_collision_flags_match_torch_near_contact(name, load_robot):
    """The compiled check against the torch path (the reference) on 20,000 configurations per robot and scene, half
    of them uniform and half within a fraction of a millimetre (in configuration space) of the torch checker's
    environment and self-collision boundaries, where a one-in-thousands disagreement (a tolerance, a skipped axis,
    a shrunk radius) shows. Every flag equal; and no pybullet (exact mesh) collision among the near-contact
    configurations missed by the compiled check."""
    from psprm_core.evaluation.reference import PybulletWorld

    robot, scene = _robot_scene(name, load_robot)
    boxes = scene.collision_boxes()
    checker = CollisionChecker(robot, boxes, workspace=scene.workspace, dtype=torch.float64)
    rng = np.random.default_rng(7)
    half = NEAR_CONTACT_N // 2
    uniform = torch.as_tensor(_configs(robot, scene, half, 3), dtype=torch.float64)
    pool = torch.as_tensor(sample_uniform(robot, 4000, rng, base_box=scene.workspace), dtype=torch.float64)
    env_q, env_gap = _near_contact(checker, pool, "environment", half // 4, rng)
    self_q, self_gap = _near_contact(checker, pool, "self", half // 4, rng)
    near = torch.cat([env_q, self_q])
    assert float(torch.cat([env_gap, self_gap]).max()) < 1e-3  # precondition: within 1 mm of the boundary
    q = torch.cat([uniform, near])
    assert len(q) == NEAR_CONTACT_N
    with bulk():
        fast = checker.check_detailed(q)
    ref = checker.using(TORCH).check_detailed(q)
    for k in ("limits", "environment", "self"):
        bad = torch.nonzero(fast[k] != ref[k]).flatten().tolist()
        assert not bad, f"{k}: compiled and torch disagree on {len(bad)} configurations, e.g. {bad[:5]}"
    for k, part in (("environment", slice(half, half + len(env_q))), ("self", slice(half + len(env_q), None))):
        flags = ref[k][part]  # precondition: both sides of the boundary present
        assert 0.4 < float(flags.double().mean()) < 0.6, k
    world = PybulletWorld(robot, boxes)
    try:
        exact = world.in_collision(near.numpy())
    finally:
        world.close()
    flagged = (fast["environment"] | fast["self"] | fast["limits"])[half:].numpy()
    assert not (exact & ~flagged).any(), "a pybullet collision near contact is not flagged by the compiled check"


@pytest.mark.parametrize("name", sorted(ROBOT_SCENES))
def test_env_hits_and_robot_bounds_match_torch(name, load_robot):
    """Flags against a subset of the obstacles (what an obstacle move re-checks) and the robot's world bounds (the
    spatial index of the edge knots), compiled vs torch."""
    from psprm_core.collision import BoxTensors

    robot, scene = _robot_scene(name, load_robot)
    boxes = scene.collision_boxes()
    checker = CollisionChecker(robot, boxes, workspace=scene.workspace)
    q = torch.as_tensor(_configs(robot, scene, 800, 3), dtype=torch.float32)
    for subset in (boxes[::2], boxes[1:4], []):
        bt = BoxTensors.from_boxes(subset)
        hit, aabb = checker.env_hits(q, bt, return_aabb=True)
        ref, ref_aabb = checker.using(TORCH).env_hits(q, bt, return_aabb=True)
        assert hit.dtype == torch.bool and torch.equal(hit, ref)
        assert torch.equal(checker.env_hits(q, subset), ref)
        assert aabb.shape == (len(q), 6) and (aabb - ref_aabb).abs().max() < 1e-4
        if len(subset) >= 3:
            assert 0 < int(ref.sum()) < len(q)
    ref_bounds = checker.using(TORCH).robot_aabb(q)
    assert (checker.robot_aabb(q) - ref_bounds).abs().max() < 1e-4


def test_fast_path_only_for_small_cpu_batches_without_gradients(load_robot):
    robot = load_robot("stretch2")
    cp = robot.compute
    assert cp.compiled and cp.device.type == "cpu"  # the default on a CPU with numba
    q = torch.zeros(4, robot.dof)
    assert cp.takes(q)
    assert not cp.takes(torch.zeros(cp.max_batch + 1, robot.dof))
    assert not cp.takes(torch.zeros(0, robot.dof))
    assert not cp.takes(q.clone().requires_grad_())
    assert not TORCH.takes(q)
    small = Compute.make("cpu", max_batch=3)  # the batch policy is the Compute's
    assert small.takes(q[:3]) and not small.takes(q)
    with mock.patch.object(fastpath, "kernels", side_effect=AssertionError("compiled path used")):
        T = robot.using(TORCH).camera_poses(q)
        robot.using(small).camera_poses(q)  # 4 rows > 3: the torch path
    assert torch.allclose(T, robot.camera_poses(q), atol=1e-6)
    # autograd still flows through the torch path
    qg = torch.zeros(3, robot.dof, dtype=torch.float64, requires_grad=True)
    robot.camera_poses(qg)[:, :3, 3].sum().backward()
    assert qg.grad is not None and qg.grad.abs().sum() > 0


def test_bulk_mode_splits_large_batches_over_threads_with_the_same_results(load_robot):
    """Inside ``bulk`` (the roadmap build) batches beyond ``max_batch`` take the kernels too, split into row
    chunks run on worker threads; the results are the torch path's (collision flags identical, projection and camera
    poses within float rounding), in row order."""
    robot, scene = _robot_scene("stretch2", load_robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    cp = checker.compute
    n = 3 * cp.bulk_chunk + 17  # several chunks and a ragged last one
    q = torch.as_tensor(_configs(robot, scene, n, 7), dtype=torch.float32)
    assert not cp.takes(q)
    calls = []
    real = fastpath.kernels()

    class Spy:  # counts the kernel calls (one per chunk) and the rows each got
        def __getattr__(self, name):
            fn = getattr(real, name)
            return lambda *a: (calls.append((name, a[0].shape[0])), fn(*a))[1]

    target = scene.target(scene.target_names[0]).center
    con = VisibilityConstraint(robot, "line", target)
    ref_bad, ref_T = checker.using(TORCH).check(q), robot.using(TORCH).camera_poses(q)
    ref_q, ref_ok = con.using(TORCH).project(q.double(), ProjectionSettings(max_iters=5))
    with bulk(workers=2), mock.patch.object(fastpath, "kernels", lambda: Spy()):
        assert cp.takes(q)
        bad, T = checker.check(q), robot.camera_poses(q)
        pq, ok = con.project(q.double(), ProjectionSettings(max_iters=5))
    assert not cp.takes(q)  # back to small batches only
    chunks = [r for name, r in calls if name == "check"]
    assert len(chunks) > 1 and sum(chunks) == n
    assert torch.equal(bad, ref_bad) and 0 < int(bad.sum()) < n
    assert (T - ref_T).abs().max() < 1e-5
    assert torch.equal(ok, ref_ok) and (pq - ref_q).abs().max() < 1e-6
    with bulk(workers=2):
        assert not TORCH.takes(q)
        seen = []  # the bulk policy holds for the thread that entered it, not for others
        t = threading.Thread(target=lambda: seen.append((bulk_workers(), cp.takes(q))))
        t.start()
        t.join()
        assert seen == [(0, False)] and bulk_workers() == 2


def test_planner_same_paths_with_fast_path_on_and_off(load_robot, tmp_path):
    """One roadmap, queried by two planners (one loaded from the other's file): with and without the compiled
    small-batch paths every query gives the same path and cost (the re-aimed knots agree up to float32 rounding of
    the torch path's Gauss-Newton iterates)."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.problems[0].target
    scorer = GeometricScorer(scene, target, robot.config.intrinsics)
    # repairs grow nodes: not compared
    settings = PSPRMSettings().changed({"roadmap.n_nodes": 400, "seed": 3, "recovery.query_repair_nodes": 0})
    focus = scene.target(target).center
    a = PSPRM(robot, scene, scorer, focus, settings)
    assert a.build()["success"]
    b = PSPRM(robot, scene, scorer, focus, settings, compute=TORCH)
    b.load(a.save(tmp_path / "roadmap.npz"))
    assert a.ctx.backend.compiled and not b.ctx.backend.compiled
    probs = random_problems(robot, scene, a.checker, 8, np.random.default_rng(4), robot.default_configuration(),
                            focus, aimed_only=True, aim_restarts=4)
    assert len(probs) >= 6
    solved = 0
    for start, goal in probs:
        ra = a.plan(start, goal, timing=False)
        rb = b.plan(start, goal, timing=False)
        assert ra.success == rb.success
        if ra.success:
            solved += 1
            assert ra.path_nodes == rb.path_nodes
            assert ra.cost == pytest.approx(rb.cost, rel=1e-4)
            assert np.abs(ra.waypoints - rb.waypoints).max() < 1e-2  # float32 re-aimed knots
    assert solved >= len(probs) // 2


@pytest.mark.parametrize("scene_name", ["home", "nursing"])
def test_occlusion_scores_match_torch(scene_name):
    """Ray-cast occlusion (Alg. 2) of cameras spread over the scene, some of them behind occluders."""
    from psprm_core.perception.occlusion import OcclusionChecker

    scene = load_scene(resolve_named("scene", scene_name))
    rng = np.random.default_rng(5)
    for target in scene.target_names[:3]:
        occ = OcclusionChecker.from_scene(scene, target)
        pos = np.concatenate([rng.uniform(scene.workspace[:, 0], scene.workspace[:, 1], (500, 2)),
                              rng.uniform(0.3, 1.8, (500, 1))], 1)
        for dtype in (torch.float64, torch.float32):
            cams = torch.as_tensor(pos, dtype=dtype)
            fast = occ.score(cams)
            ref = occ.using(TORCH).score(cams)
            assert fast.dtype == dtype and torch.equal(fast, ref)
            assert 0 < int((ref > 0).sum()) < len(ref)  # some rays blocked, some not


def test_surrogate_scores_match_torch(load_robot):
    """The numpy MLP (normalisation folded into the first layer) and pose features give the torch scores; a
    changed weight is picked up (the folded layers are cached by the tensors' versions)."""
    from psprm_core.perception.surrogate import PerceptionSurrogate

    torch.manual_seed(0)
    robot, scene = _robot_scene("stretch2", load_robot)
    m = PerceptionSurrogate(["cup", "face", "tv"])
    m.fit_normalization(torch.randn(500, m.n_pose_features, dtype=torch.float64) * 2 + 0.5)
    with torch.no_grad():  # larger weights than the initialisation's: scores spread over (0, 1)
        for p in m.net.parameters():
            p *= 2.5
        m.net[-1].bias.zero_()
    cams = robot.camera_poses(torch.as_tensor(_configs(robot, scene, 200, 6), dtype=torch.float32))
    target = torch.as_tensor(np.eye(4))
    target[:3, 3] = torch.tensor([2.0, 1.0, 0.9])
    for cls in ("cup", "tv", 1):
        for rows in (3, m.compute.mlp_max_rows, 200):  # the compiled MLP, and torch's GEMM above mlp_max_rows
            fast = m.predict(cams[:rows], target, cls)
            ref = m.using(TORCH).predict(cams[:rows], target, cls)
            assert fast.dtype == ref.dtype and fast.shape == (rows,)
            assert (fast - ref).abs().max() < 1e-5
        assert ref.std() > 0.05
    with torch.no_grad():
        m.net[-1].bias += 1.0
    fast = m.predict(cams, target, "cup")
    ref = m.using(TORCH).predict(cams, target, "cup")
    assert (fast - ref).abs().max() < 1e-5


@pytest.mark.parametrize("name", ["stretch2", "fetchlike"])
def test_motion_metric_interpolation_and_pieces_match_torch(name, load_robot):
    """Diff-drive metric and interpolation (rotate, translate, rotate; including pure turns and standing still) and
    the planner's dense pieces: same lengths, same number of points, same points."""
    from psprm_core.motion import DiffDriveMotion

    robot, scene = _robot_scene(name, load_robot)
    m = DiffDriveMotion(robot)
    qa = torch.as_tensor(_configs(robot, scene, 400, 7), dtype=torch.float64)
    qb = torch.as_tensor(_configs(robot, scene, 400, 8), dtype=torch.float64)
    qb[:50, :2] = qa[:50, :2]  # turns in place
    qb[50:60] = qa[50:60]  # no motion
    s = torch.as_tensor(np.random.default_rng(9).uniform(0, 1, 400))
    s[:20] = 1.0
    s[20:40] = 0.0
    ref_d, ref_i = m.using(TORCH).distance(qa, qb), m.using(TORCH).interpolate(qa, qb, s)
    assert (m.distance(qa, qb) - ref_d).abs().max() < 1e-12
    assert (m.interpolate(qa, qb, s) - ref_i).abs().max() < 1e-12
    assert (m.distance(qa.float(), qb.float()) - ref_d).abs().max() < 1e-4  # float32 inputs, float32 result
    # only the motion, robot and settings are needed by the edges' pieces
    def stage_edges(compute):
        ctx = PlannerContext(robot=robot, scene=None, scorer=None, settings=PSPRMSettings(),
                             device=torch.device("cpu"), dtype=torch.float64, motion=m.using(compute), checker=None,
                             constraint=None, track_cols=np.zeros(0, int), compute=compute)
        return Pipeline(ctx).edges

    edges, ref_edges = stage_edges(m.compute), stage_edges(TORCH)
    for include_start in (True, False):
        seg, pts = edges.pieces(qa[:100], qb[:100], max_steps=200, include_start=include_start)
        rseg, rpts = ref_edges.pieces(qa[:100], qb[:100], max_steps=200, include_start=include_start)
        assert torch.equal(seg, rseg) and len(seg) > 1000
        assert (pts - rpts).abs().max() < 1e-12


@pytest.mark.parametrize("name", ["stretch2", "fetchlike"])
def test_edge_knots_and_nearest_nodes_match_torch(name, load_robot):
    """A query's connection edges: the knots (drive corners and Eq. 1 samples, sorted; re-aimed camera joints) and
    the connect_k nearest roadmap nodes under the motion metric."""
    robot, scene = _robot_scene(name, load_robot)
    target = scene.target(scene.target_names[0]).center
    planner = PSPRM(robot, scene, GeometricScorer(scene, scene.target_names[0], robot.config.intrinsics), target,
                    PSPRMSettings(), dtype=torch.float64)
    qa = torch.as_tensor(_configs(robot, scene, 40, 10), dtype=torch.float64)
    qb = torch.as_tensor(_configs(robot, scene, 40, 11), dtype=torch.float64)
    qb[:5, :2] = qa[:5, :2]  # turns in place: a drive corner at s = 0 or 1
    qb[5:8, 2] = qa[5:8, 2]
    kn, ki = planner.edge_knots(qa, qb)
    reference = PSPRM(robot, scene, planner.scorer, target, PSPRMSettings(), dtype=torch.float64, compute=TORCH)
    rkn, rki = reference.edge_knots(qa, qb)
    assert kn.shape == rkn.shape and torch.equal(ki, rki)
    assert (kn - rkn).abs().max() < 1e-6
    rm = torch.as_tensor(_configs(robot, scene, 3000, 12), dtype=torch.float64)
    d = planner.motion.distance(qa[:6].repeat_interleave(len(rm), 0), rm.repeat(6, 1)).reshape(6, -1)
    want = d.topk(12, largest=False).indices
    for ops in (planner.compute.ops, TORCH.ops):  # compiled, and the torch implementation of the same verb
        assert torch.equal(ops.nearest(planner.motion, qa[:6], rm, 12), want), ops.name


def test_warm_up_loads_the_query_kernels(load_robot):
    """After ``warm_up`` the kernels a query uses are compiled for the planner's argument types (no compilation in
    the first query); on CPU without numba it does nothing."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.target_names[0]
    planner = PSPRM(robot, scene, GeometricScorer(scene, target, robot.config.intrinsics),
                    scene.target(target).center, PSPRMSettings())
    assert planner.warm_up() > 0
    K = fastpath.kernels()
    for name in ("check", "camera_poses", "project", "occlusion", "query_knots", "edge_knot_seeds", "pieces", "distance",
                 "nearest"):
        assert getattr(K, name).signatures, name
    S = search_kernels.kernels()
    for name in ("astar", "bfs_hops", "hops_decrease", "hop_columns", "query_hops"):  # the roadmap searches' kernels too
        assert getattr(S, name).signatures, name
    assert K.env_hits.signatures  # obstacle moves' re-checks
    torch_only = PSPRM(robot, scene, planner.scorer, scene.target(target).center, PSPRMSettings(), compute=TORCH)
    with mock.patch.object(fastpath, "kernels", side_effect=AssertionError("compiled path used")):
        assert torch_only.warm_up() > 0  # the search kernels still load
        with mock.patch.object(search_kernels, "available", lambda: False):
            torch_only.warm_up()  # nothing compiled without numba
    # the first plan's trajectory timing (TOPP-RA) is loaded too: a three-knot drive is timed, within the limits
    with mock.patch.object(planner.pipeline.trajectory, "timed", wraps=planner.pipeline.trajectory.timed) as timed:
        planner.warm_up()
    (W,), _ = timed.call_args
    assert timed.call_count == 1 and W.shape == (3, robot.dof)
    traj = planner.pipeline.trajectory.timed(W)
    assert traj.times[-1] > 0 and np.allclose(traj.positions[-1], W[-1], atol=1e-6)


def test_constant_inputs_follow_in_place_changes(load_robot):
    """Limits kept between calls are refreshed when the tensor changes in place (or is a copy)."""
    import copy

    robot, scene = _robot_scene("stretch2", load_robot)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    q = torch.as_tensor(_configs(robot, scene, 50, 13), dtype=torch.float32)
    before = checker.check_detailed(q)["limits"]
    checker.upper[-1] = -10.0  # every configuration now violates the last joint's limit
    assert checker.check_detailed(q)["limits"].all() and not before.all()
    other = copy.deepcopy(checker)
    other.upper[-1] = 10.0
    ref = other.using(TORCH).check_detailed(q)["limits"]
    assert torch.equal(other.check_detailed(q)["limits"], ref)


def test_queries_run_with_one_intra_op_thread(load_robot):
    """A query's small batches run with torch's intra-op parallelism off (a parallel region of a few microseconds
    can wait a whole scheduler slice for its second thread on a busy machine); the thread count is restored after
    the query, also when it fails."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.problems[0].target
    focus = scene.target(target).center
    seen = []

    class Recording(GeometricScorer):
        def score(self, cameras):
            seen.append(torch.get_num_threads())
            return super().score(cameras)

    p = PSPRM(robot, scene, Recording(scene, target, robot.config.intrinsics), focus,
              PSPRMSettings().changed({"roadmap.n_nodes": 200, "seed": 1, "recovery.query_repair_nodes": 0}))
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert p.build()["success"]
        assert seen and max(seen) == 2  # the build keeps torch's threads (large GEMMs)
        seen.clear()
        q = p.graph.configs[p.roadmap_node_ids()[:2]]
        p.plan(q[0], q[1], timing=False)
        assert seen and set(seen) == {1}
        assert torch.get_num_threads() == 2
        bad = q[0].copy()
        bad[0] = float("nan")
        assert not p.plan(bad, q[1]).success and torch.get_num_threads() == 2
        with Compute.make("cpu").one_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(old)


def _neural_scorer(scene, target: str, seed: int = 0):
    """A NeuralScorer (with ray-cast occlusion) on a random surrogate whose scores spread over (0, 1)."""
    from psprm_core.perception.scoring import NeuralScorer
    from psprm_core.perception.surrogate import PerceptionSurrogate

    torch.manual_seed(seed)
    m = PerceptionSurrogate(sorted({scene.target(target).detector_class, "face", "tv"}))
    m.fit_normalization(torch.randn(500, m.n_pose_features, dtype=torch.float64) * 2 + 0.5)
    with torch.no_grad():
        for p in m.net.parameters():
            p *= 2.5
        m.net[-1].bias.zero_()
    return NeuralScorer(m, scene, target)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_query_edge_kernels_match_the_step_by_step_path(dtype, load_robot):
    """A lazy search's edges in one compiled call each: the knots (seeds, then the camera joints re-aimed) and the
    verification (dense collision check, Eq. 1 camera poses, surrogate scores zeroed where occluded) are exactly
    those of the kernels called one by one through the torch glue, in float32 (rounded between stages) and float64;
    so are the start and goal scores (one call)."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.target_names[0]
    scorer = _neural_scorer(scene, target)
    planner = PSPRM(robot, scene, scorer, scene.target(target).center, PSPRMSettings(), dtype=dtype)
    rng = np.random.default_rng(21)
    qa = torch.as_tensor(_configs(robot, scene, 1500, 20), dtype=dtype)
    qa = qa[planner.checker.valid(qa)][:90]
    qb = qa + torch.as_tensor(rng.normal(0, 0.15, qa.shape), dtype=dtype)  # short edges, some colliding
    kn, ki = planner.edge_knots(qa, qb)
    seeds, seed_i = planner.compute.ops.edge_knot_seeds(planner.motion, qa, qb, planner.settings.edges.n_interp)
    assert torch.equal(kn, planner.pipeline.edges.track_knots(seeds)) and torch.equal(ki, seed_i) and kn.dtype == dtype
    args = edges.neural_args(scorer, dtype)
    # a query's start and goal scores: one compiled call, the scorer's values
    rows = planner.compute.mlp_max_rows
    assert torch.equal(planner.score_configs(qa[:rows]), scorer.score(robot.camera_poses(qa[:rows])).to(dtype))
    n_free = n_zero = 0
    for s0 in range(0, len(qa), 3):  # batches of three edges, as a lazy search verifies its path
        k, i = kn[s0:s0 + 3], ki[s0:s0 + 3]
        free, cams, raw = edges.check_score_knots(planner.pipeline.ctx.edge_kit(), args, k, i,
                                                  np.ones(len(k), bool), np.ones(len(k), bool), 200)
        assert np.array_equal(free, planner.pipeline.edges.knots_valid(k, dense=True).numpy())
        if free.any():
            ref_cams = planner.pipeline.scoring.eq1_cameras(k[free], i[free])
            assert torch.equal(cams[free], ref_cams)
            ref = scorer.score(ref_cams.reshape(-1, 4, 4)).reshape(int(free.sum()), -1)
            assert torch.equal(raw[free].to(ref.dtype), ref)
            n_free += int(free.sum())
            n_zero += int((ref == 0).sum())
        assert (raw[~free] == 0).all()
    assert 5 <= n_free < len(qa) and n_zero > 0  # colliding and free edges, occluded (zeroed) views among them


def test_planner_same_paths_with_the_fused_verification_on_and_off(load_robot, tmp_path):
    """A neural planner's lazy searches verify their paths with the fused kernel; without it (the step-by-step
    path) every query gives the same path, knots and cost (the step-by-step path scores more than four edges' views
    with torch's GEMM, the fused one with the compiled MLP four edges at a time: float32 rounding apart)."""
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.problems[0].target
    focus = scene.target(target).center
    settings = PSPRMSettings().changed({"roadmap.n_nodes": 400, "seed": 5, "recovery.query_repair_nodes": 0})
    a = PSPRM(robot, scene, _neural_scorer(scene, target), focus, settings)
    assert a.build()["success"]
    b = PSPRM(robot, scene, _neural_scorer(scene, target), focus, settings)
    b.load(a.save(tmp_path / "roadmap.npz"))
    probs = random_problems(robot, scene, a.checker, 8, np.random.default_rng(6), robot.default_configuration(),
                            focus, aimed_only=True, aim_restarts=4)
    fused = []
    real = Verification.verify_compiled

    def spy(self, *args):
        out = real(self, *args)
        fused.append(out is not None)
        return out

    solved = 0
    for start, goal in probs:
        with mock.patch.object(Verification, "verify_compiled", spy):
            ra = a.plan(start, goal, timing=False)
        with mock.patch.object(Verification, "verify_compiled", return_value=None):
            rb = b.plan(start, goal, timing=False)
        assert ra.success == rb.success
        if ra.success:
            solved += 1
            assert ra.path_nodes == rb.path_nodes and ra.cost == pytest.approx(rb.cost, rel=1e-6)
            assert np.array_equal(ra.waypoints, rb.waypoints)
    assert solved >= len(probs) // 2 and fused and all(fused)


def test_kernel_modules_record_the_sources_of_the_kernels_they_call():
    """numba's disk cache checks only the source file of the kernel it loads: every kernel module that imports from
    other kernel modules records their SHA-256 (``CALLEES_SHA256``, over the modules it reaches through its imports,
    with that line blanked), so that a change to a called kernel or to the decorator changes the caller's file too
    and its cached kernels are compiled again."""
    import ast
    import hashlib
    import importlib
    import re
    from pathlib import Path

    root = Path(fastpath.__file__).parent
    line = re.compile(r'^CALLEES_SHA256 = ".*"$', re.M)
    files = {p.stem: p.read_text(encoding="utf-8") for p in root.glob("_fast_*.py") if p.stem != "_fast_numba"}  # numba: re-exports
    imports = {m: {n.module for n in ast.walk(ast.parse(t)) if isinstance(n, ast.ImportFrom) and n.level == 1
                   and n.module in files} for m, t in files.items()}

    def reached(m, seen):
        for c in imports[m] - seen:
            seen.add(c)
            reached(c, seen)
        return seen

    wrong = []
    for m in sorted(files):
        closure = sorted(reached(m, set()))
        got = getattr(importlib.import_module(f"psprm_core.kernels.{m}"), "CALLEES_SHA256", None)
        if not closure:
            assert got is None, f"{m} imports no kernel module: no CALLEES_SHA256"
            continue
        h = hashlib.sha256()
        for c in closure:
            h.update(line.sub('CALLEES_SHA256 = ""', files[c]).encode())
        if got != h.hexdigest():
            wrong.append(f'{m}.py: CALLEES_SHA256 = "{h.hexdigest()}" (from {", ".join(closure)})')
    assert not wrong, "set\n" + "\n".join(wrong)


def test_a_compute_is_checked_where_it_is_made(load_robot):
    """``Compute.make`` refuses what cannot run (numba kernels off the CPU, an unknown kernels name, a batch limit
    below 1, an unknown policy field) with a ConfigError naming the field; a planner refuses a Compute for another
    device than its own; ``using`` takes only a Compute."""
    from psprm_core.errors import ConfigError

    for kw, field in ((dict(device="cuda", kernels="numba"), "kernels"), (dict(kernels="warp"), "kernels"),
                      (dict(max_batch=0), "max_batch"), (dict(mlp_max_rows=-3), "mlp_max_rows")):
        with pytest.raises(ConfigError) as e:
            Compute.make(**kw)
        assert e.value.field == field, kw
    with pytest.raises(ConfigError, match="unknown batch policy"):
        Compute.make(chunk=3)
    assert Compute.make("cuda").kernels == "torch"  # auto: torch off the CPU, whether or not CUDA is here
    robot, scene = _robot_scene("stretch2", load_robot)
    target = scene.target_names[0]
    scorer = GeometricScorer(scene, target, robot.config.intrinsics)
    with pytest.raises(ConfigError, match="device"):
        PSPRM(robot, scene, scorer, scene.target(target).center, PSPRMSettings(), compute=Compute.make("cuda"))
    with pytest.raises(ConfigError, match="expected a Compute"):
        robot.using("torch")
    copy = robot.using(TORCH)  # the original keeps its own
    assert copy.compute is TORCH and robot.compute.compiled and copy.camera_body == robot.camera_body


def test_both_kernels_implementations_answer_every_verb_of_the_protocol():
    """The kernels protocol (``psprm_core.kernels.ops.Kernels``) is implemented twice, torch and numba, with the
    protocol's parameters; a ``Compute`` carries the implementation its ``kernels`` names."""
    import inspect

    from psprm_core.kernels.fastpath import NumbaKernels
    from psprm_core.kernels.ops import Kernels, TorchKernels

    verbs = [n for n, f in vars(Kernels).items() if inspect.isfunction(f) and not n.startswith("_")]
    assert len(verbs) >= 18
    for impl in (TorchKernels, NumbaKernels):
        for verb in verbs:
            want = list(inspect.signature(getattr(Kernels, verb)).parameters)
            got = list(inspect.signature(getattr(impl, verb)).parameters)
            assert got == want, (impl.__name__, verb)
    assert type(TORCH.ops) is TorchKernels and TORCH.ops.compute is TORCH
    cp = Compute.make("cpu")
    assert type(cp.ops) is NumbaKernels and cp.ops.compute is cp and cp.torch_only().ops.name == "torch"


@pytest.mark.parametrize("name", ["stretch2", "ur5_mobile"])
def test_numpy_verbs_match_an_independent_metric_and_the_torch_implementation(name, load_robot):
    """The numpy verbs the planner's dense paths and the baselines use: the metric of pure joint moves is their
    Euclidean norm and of a pure drive its length (computed here), interpolation ends at both ends, pieces are
    ``ceil(d / resolution)`` points apart at most ``resolution`` each; compiled and torch agree on random pairs, and
    the collision flags of ``check_arrays`` are the checker's torch flags."""
    from psprm_core.motion import DiffDriveMotion

    robot, scene = _robot_scene(name, load_robot)
    motion = DiffDriveMotion(robot)
    a = _configs(robot, scene, 200, 30)
    a[:, 2] = np.remainder(a[:, 2] + np.pi, 2 * np.pi) - np.pi
    b = _configs(robot, scene, 200, 31)
    b[:, 2] = np.remainder(b[:, 2] + np.pi, 2 * np.pi) - np.pi
    joints = a.copy()
    joints[:, 3:] = b[:, 3:]
    drive = a.copy()
    drive[:, :2] += 0.7 * np.stack([np.cos(a[:, 2]), np.sin(a[:, 2])], -1)  # straight ahead: no turn
    s = np.random.default_rng(32).uniform(0, 1, len(a))
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    ref_flags = checker.using(TORCH).check_detailed(torch.as_tensor(a, dtype=torch.float32))
    for ops in (Compute.make("cpu").ops, TORCH.ops):
        assert np.allclose(ops.metric_arrays(motion, a, joints), np.linalg.norm(b[:, 3:] - a[:, 3:], axis=1),
                           atol=1e-9), ops.name
        if robot.mobile:
            assert np.allclose(ops.metric_arrays(motion, a, drive), 0.7, atol=1e-9), ops.name
        assert np.allclose(ops.interpolate_arrays(motion, a, b, np.zeros(len(a))), a, atol=1e-9)
        end = ops.interpolate_arrays(motion, a, b, np.ones(len(a)))
        assert np.allclose(end[:, 3:], b[:, 3:], atol=1e-9) and np.allclose(end[:, :2], b[:, :2], atol=1e-9)
        seg, pts = ops.pieces_arrays(motion, a[:20], b[:20], 0.05, 1000, True)
        n = np.maximum(1, np.ceil(ops.metric_arrays(motion, a[:20], b[:20]) / 0.05)).astype(int)
        assert np.array_equal(np.bincount(seg, minlength=20), n), ops.name
        flags = ops.check_arrays(checker, a.astype(np.float32))
        for k in ("limits", "environment", "self"):
            assert np.array_equal(flags[k], ref_flags[k].numpy()), (ops.name, k)
    fast, ref = Compute.make("cpu").ops, TORCH.ops
    assert np.allclose(fast.metric_arrays(motion, a, b), ref.metric_arrays(motion, a, b), atol=1e-9)
    assert np.allclose(fast.interpolate_arrays(motion, a, b, s), ref.interpolate_arrays(motion, a, b, s), atol=1e-9)
    assert any(ref_flags[k].any() for k in ref_flags)  # some configurations collide or leave the limits
