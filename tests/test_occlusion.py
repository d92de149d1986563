"""Ray-cast occlusion (Alg. 2, lines 5-7): agreement with pybullet's rayTestBatch and hand-made cases."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from psprm_core.geometry import quat_to_matrix, yaw_to_quat
from psprm_core.perception.occlusion import (
    BoxTensors,
    OcclusionChecker,
    benchmark_rays_per_s,
    boxes_to_tensors,
    occluder_boxes,
    occlusion_scores,
    ray_hits,
    target_sample_points,
    zero_occluded,
)
from psprm_core.scene import Box, Scene, Target


def _random_boxes(rng: np.random.Generator, k: int) -> list:
    boxes = []
    for i in range(k):
        q = rng.normal(size=4)
        boxes.append(Box(name=f"b{i}", center=rng.uniform(-2, 2, 3), size=rng.uniform(0.1, 1.2, 3),
                         quat=q / np.linalg.norm(q)))
    return boxes


def _pybullet_hits(boxes: list, origins: np.ndarray, ends: np.ndarray) -> np.ndarray:
    pybullet = pytest.importorskip("pybullet")
    cid = pybullet.connect(pybullet.DIRECT)
    try:
        for b in boxes:
            col = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=list(b.half_extents),
                                                physicsClientId=cid)
            pybullet.createMultiBody(0, col, basePosition=list(b.center), baseOrientation=list(b.quat),
                                     physicsClientId=cid)
        out = []
        for s in range(0, len(origins), 1000):
            res = pybullet.rayTestBatch(origins[s:s + 1000].tolist(), ends[s:s + 1000].tolist(), physicsClientId=cid)
            out.extend(r[0] != -1 for r in res)
        return np.array(out)
    finally:
        pybullet.disconnect(cid)


@pytest.fixture(scope="module")
def random_case():
    rng = np.random.default_rng(1234)
    boxes = _random_boxes(rng, 25)
    n = 4000
    origins = rng.uniform(-3, 3, (n, 3))
    ends = rng.uniform(-3, 3, (n, 3))
    # a share of short rays so that "ends before the box" cases are well represented
    ends[: n // 4] = origins[: n // 4] + rng.normal(scale=0.5, size=(n // 4, 3))
    return boxes, origins, ends, _pybullet_hits(boxes, origins, ends)


def _inside_any(boxes: list, pts: np.ndarray) -> np.ndarray:
    bt = boxes_to_tensors(boxes, dtype=torch.float64)
    return bt.contains(torch.as_tensor(pts)).any(dim=1).numpy()


def test_matches_pybullet_when_ignoring_start_box(random_case):
    boxes, origins, ends, pb = random_case
    ours = ray_hits(torch.as_tensor(origins), torch.as_tensor(ends), boxes_to_tensors(boxes, dtype=torch.float64),
                    count_inside=False).numpy()
    assert 0.2 < pb.mean() < 0.8  # the case is informative
    assert np.array_equal(ours, pb), f"{(ours != pb).sum()} mismatches out of {len(pb)}"


def test_default_convention_rays_starting_inside_are_blocked(random_case):
    boxes, origins, ends, pb = random_case
    bt = boxes_to_tensors(boxes, dtype=torch.float64)
    ours = ray_hits(torch.as_tensor(origins), torch.as_tensor(ends), bt).numpy()
    inside = _inside_any(boxes, origins)
    assert inside.sum() > 20
    assert ours[inside].all()
    assert np.array_equal(ours[~inside], pb[~inside])
    # pybullet does not report the box a ray starts in: some of those rays are "free" for it
    assert not pb[inside].all()


def test_float32_and_chunking_agree(random_case):
    boxes, origins, ends, _ = random_case
    bt = boxes_to_tensors(boxes, dtype=torch.float64)
    ref = ray_hits(torch.as_tensor(origins), torch.as_tensor(ends), bt)
    small = ray_hits(torch.as_tensor(origins), torch.as_tensor(ends), bt, chunk_elements=7)
    assert torch.equal(ref, small)
    f32 = ray_hits(torch.as_tensor(origins, dtype=torch.float32), torch.as_tensor(ends, dtype=torch.float32), bt)
    assert (f32 != ref).float().mean() < 1e-3  # only grazing rays may flip


def _scene(obstacles, targets) -> Scene:
    return Scene(name="t", robot="r", frame="map", workspace=np.array([[-5, 5], [-5, 5]]), obstacles=tuple(obstacles),
                 targets=tuple(targets))


TARGET = Target(name="cube", detector_class="cup", center=np.array([0.0, 0.0, 0.5]), size=np.array([1.0, 1.0, 1.0]))


def test_hand_made_half_wall():
    # Camera on +x looking at a unit cube; a thin wall covers only y < -0.01 halfway between them.
    wall = Box(name="wall", center=np.array([2.5, -1.51, 0.5]), size=np.array([0.05, 3.0, 3.0]))
    checker = OcclusionChecker.from_scene(_scene([wall], [TARGET]), "cube", front=False)
    assert checker.target_points.shape == (15, 3)
    cams = torch.tensor([[5.0, 0.0, 0.5], [-5.0, 0.0, 0.5], [5.0, -3.0, 0.5], [5.0, 3.0, 0.5]])
    s = checker.score(cams)
    # 4 corners + the -y face centre have y < 0 -> 5 of 15 rays blocked; behind the target nothing blocks;
    # from y = -3 every ray crosses the wall; from y = +3 the rays cross x = 2.5 at y > 0.
    assert s[0].item() == pytest.approx(5 / 15)
    assert s[1].item() == 0.0
    assert s[2].item() == 1.0
    assert s[3].item() == 0.0
    assert checker.occluded(cams).tolist() == [False, False, True, False]
    scores = torch.ones(4)
    assert checker.apply(scores, cams).tolist() == [1.0, 1.0, 0.0, 1.0]
    assert zero_occluded(scores, s, tau=0.2).tolist() == [0.0, 1.0, 0.0, 1.0]


def test_oriented_box_is_not_its_aabb():
    # A 45-degree rotated thin slab: a ray through its AABB corner region misses the box itself.
    slab = Box(name="slab", center=np.zeros(3), size=np.array([2.0, 0.1, 2.0]), quat=yaw_to_quat(math.pi / 4))
    bt = boxes_to_tensors([slab], dtype=torch.float64)
    o = torch.tensor([[0.6, -0.6, -3.0], [0.0, 0.0, -3.0]], dtype=torch.float64)
    e = torch.tensor([[0.6, -0.6, 3.0], [0.0, 0.0, 3.0]], dtype=torch.float64)
    assert ray_hits(o, e, bt).tolist() == [False, True]
    # the segment stopping before the box is not blocked
    assert not ray_hits(o[1:], torch.tensor([[0.0, 0.0, -1.1]], dtype=torch.float64), bt).item()


def test_exclusion_of_target_and_containing_boxes():
    body = Box(name="body", center=np.array([0.0, 0.0, 0.5]), size=np.array([1.5, 1.5, 1.5]))
    other = Target(name="other", detector_class="tv", center=np.array([2.5, 0.0, 0.5]), size=np.array([0.1, 3.0, 3.0]))
    scene = _scene([body], [TARGET, other])
    bt = occluder_boxes(scene, "cube")
    assert bt.names == ("other",)  # the target and the body containing it are gone, the other target occludes
    checker = OcclusionChecker.from_scene(scene, "cube", exclude=["other"])
    assert checker.boxes.count == 0
    assert checker.score(torch.tensor([[5.0, 0.0, 0.5]])).item() == 0.0
    checker = OcclusionChecker.from_scene(scene, "cube")
    assert checker.score(torch.tensor([[5.0, 0.0, 0.5]])).item() == 1.0


def test_camera_inside_obstacle_is_occluded():
    cupboard = Box(name="cupboard", center=np.array([4.0, 0.0, 0.5]), size=np.array([1.0, 1.0, 1.0]))
    checker = OcclusionChecker.from_scene(_scene([cupboard], [TARGET]), "cube")
    assert checker.score(torch.tensor([[4.0, 0.0, 0.5]])).item() == 1.0
    relaxed = OcclusionChecker.from_scene(_scene([cupboard], [TARGET]), "cube", count_inside=False)
    assert relaxed.score(torch.tensor([[4.0, 0.0, 0.5]])).item() == 0.0


def test_scores_shapes_dtypes_poses_and_chunks():
    rng = np.random.default_rng(0)
    boxes = boxes_to_tensors(_random_boxes(rng, 12))
    pts = target_sample_points(TARGET, grid=3)
    assert pts.shape == (27, 3)
    cams = torch.as_tensor(rng.uniform(-4, 4, (300, 3)), dtype=torch.float32)
    s = occlusion_scores(cams, pts, boxes)
    assert s.shape == (300,) and s.dtype == torch.float32 and s.device == cams.device
    assert torch.equal(s, occlusion_scores(cams, pts, boxes, chunk_elements=100))
    poses = torch.eye(4).repeat(300, 1, 1)
    poses[:, :3, 3] = cams
    assert torch.equal(s, occlusion_scores(poses, pts, boxes))
    # agrees with per-ray ray_hits
    o = cams.repeat_interleave(len(pts), 0)
    e = torch.as_tensor(pts, dtype=torch.float32).repeat(300, 1)
    assert torch.allclose(s, ray_hits(o, e, boxes).float().reshape(300, -1).mean(1))
    assert occlusion_scores(cams, pts, BoxTensors.empty()).eq(0).all()


def test_default_points_lie_inside_the_target_box():
    t = Target(name="t", detector_class="face", center=np.array([1.0, 2.0, 1.5]), size=np.array([0.2, 0.3, 0.4]),
               quat=yaw_to_quat(0.7))
    pts = target_sample_points(t, shrink=0.9)
    local = (pts - t.center) @ quat_to_matrix(t.quat)
    assert np.all(np.abs(local) <= t.size / 2 * 0.9 + 1e-12)
    assert np.allclose(pts[-1], t.center)


def test_benchmark_runs():
    """Rays per second of this clock: the timed run (200 cameras x 15 points, twice) fits in the call's own time."""
    t0 = time.perf_counter()
    rate = benchmark_rays_per_s(n_cameras=200, n_points=15, n_boxes=10, repeats=2)
    wall = time.perf_counter() - t0
    assert 2 * 200 * 15 / rate <= wall


def test_front_facing_targets_cast_rays_to_their_front():
    """A face on a body: rays go to the facing side, so the body behind the face never counts as an occluder,
    while a wall in front still does; a 3-D appearance (a plant) keeps the whole-box points."""
    face = Target(name="face", detector_class="face", center=np.array([0.06, 0.0, 1.6]),
                  size=np.array([0.12, 0.16, 0.22]), appearance="face_astronaut")
    body = Box(name="body", center=np.array([-0.1, 0.0, 0.8]), size=np.array([0.2, 0.45, 1.6]))
    checker = OcclusionChecker.from_scene(_scene([body], [face]), "face")
    assert checker.target_points.shape == (9, 3)
    assert np.allclose(checker.target_points[:, 0].numpy(), 0.06 + 0.06 * 0.98)
    low_front = torch.tensor([[1.2, 0.3, 1.0]])  # below and in front: rays pass above the shoulders
    assert checker.score(low_front).item() == 0.0
    wall = Box(name="wall", center=np.array([0.6, 0.0, 1.5]), size=np.array([0.05, 2.0, 2.0]))
    assert OcclusionChecker.from_scene(_scene([body, wall], [face]), "face").score(low_front).item() == 1.0
    plant = Target(name="plant", detector_class="potted plant", center=np.array([2.0, 0.0, 0.5]),
                   size=np.array([0.5, 0.5, 1.0]), appearance="potted_plant")
    assert OcclusionChecker.from_scene(_scene([], [plant]), "plant").target_points.shape == (15, 3)


@pytest.mark.parametrize("count_inside", [True, False])
def test_broad_phase_scores_equal_ray_by_ray(count_inside):
    """occlusion_scores skips boxes that the camera -> target-centre segment misses once inflated by the target
    points' radius. The scores must equal the fraction of blocked rays computed ray by ray (ray_hits), for cameras
    all around a target among random boxes: near the target, behind boxes, inside boxes."""
    rng = np.random.default_rng(7)
    boxes = _random_boxes(rng, 20)
    bt = boxes_to_tensors(boxes, dtype=torch.float64)
    target = Target(name="t", detector_class="cup", center=np.array([0.3, -0.2, 0.4]), size=np.array([0.6, 0.3, 0.5]))
    pts = torch.as_tensor(target_sample_points(target))
    cams = torch.as_tensor(rng.uniform(-3, 3, (1500, 3)))
    got = occlusion_scores(cams, pts, bt, count_inside=count_inside)
    o = cams.repeat_interleave(len(pts), 0)
    e = pts.repeat(len(cams), 1)
    ref = ray_hits(o, e, bt, count_inside=count_inside).reshape(len(cams), len(pts)).double().mean(1)
    assert torch.equal(got, ref)
    assert 0.1 < (ref == 0).double().mean() < 0.9 and 0.05 < ((ref > 0) & (ref < 1)).double().mean()  # informative


def test_a_scorer_moved_from_scene_to_scene_scores_as_one_built_for_each():
    """A scorer keeps its occluders while only its target turns in place (what-if scoring of predicted headings);
    after each kind of change from the same scene (the target turned, an obstacle moved, another target moved, the
    target moved into the box of its body) its occlusion and its scores equal those of a scorer built for that scene
    alone, over cameras all round the target."""
    from psprm_core.perception.scoring import GeometricScorer

    face = Target(name="face", detector_class="face", center=np.array([0.06, 0.0, 1.6]),
                  size=np.array([0.12, 0.16, 0.22]), appearance="face_astronaut")
    body = Box(name="body", center=np.array([-0.1, 0.0, 0.8]), size=np.array([0.2, 0.45, 1.6]))
    wall = Box(name="wall", center=np.array([1.2, -0.4, 1.5]), size=np.array([0.05, 0.8, 2.0]))
    other = Target(name="other", detector_class="tv", center=np.array([0.0, 1.5, 1.5]), size=np.array([0.1, 0.6, 0.4]))
    base = _scene([body, wall], [face, other]).with_target_pose("face", face.center, yaw_to_quat(0.7))
    changes = {"turned": base.with_target_pose("face", face.center, yaw_to_quat(-0.9)),
               "obstacle moved": base.with_obstacle_pose("wall", np.array([1.2, 0.4, 1.5])),
               "other target moved": base.with_target_pose("other", np.array([0.7, 0.1, 1.6])),
               "into its body": base.with_target_pose("face", np.array([-0.1, 0.0, 1.2]))}
    rng = np.random.default_rng(3)
    az, r = rng.uniform(-np.pi, np.pi, 400), rng.uniform(0.6, 3.0, 400)
    pos = np.stack([r * np.cos(az), r * np.sin(az), rng.uniform(0.8, 2.0, 400)], 1)
    cams = torch.zeros(400, 4, 4, dtype=torch.float64)
    for i, p in enumerate(pos):  # looking at the face's centre (z forward)
        z = (face.center - p) / np.linalg.norm(face.center - p)
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        cams[i, :3, :3] = torch.as_tensor(np.stack([x, np.cross(z, x), z], 1))
        cams[i, :3, 3], cams[i, 3, 3] = torch.as_tensor(p), 1.0
    moved = GeometricScorer(base, "face")
    base_occ = GeometricScorer(base, "face").occ.score(cams[:, :3, 3])
    for what, sc in changes.items():
        moved.set_scene(base)
        moved.set_scene(sc)
        fresh = GeometricScorer(sc, "face")
        occ = fresh.occ.score(cams[:, :3, 3])
        assert torch.equal(moved.occ.score(cams[:, :3, 3]), occ), what
        assert torch.equal(moved.score(cams), fresh.score(cams)), what
        assert not torch.equal(occ, base_occ), what  # each change changes what occludes the face somewhere
