"""The batched torch FK and collision check against pybullet (exact meshes), on 10,000 random configurations per
robot in two shipped scenes: camera poses agree to 1e-5 m / 1e-5 rad and no collision is ever missed."""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from psprm_core.collision import CollisionChecker, obb_overlap
from psprm_core.evaluation.benchmarks import rotation_angle_error
from psprm_core.evaluation.reference import PybulletWorld, pybullet_urdf, sample_uniform
from psprm_core.scene import Box, load_scene
from psprm_core.paths import resolve_named

log = logging.getLogger(__name__)
N = 10000
CASES = [(r, s) for r in ("stretch2", "fetchlike", "ur5_mobile") for s in ("home", "nursing")]


@pytest.mark.parametrize("robot_name,scene_name", CASES)
def test_fk_and_collision_agree_with_pybullet(robot_name, scene_name, load_robot):
    robot = load_robot(robot_name)
    scene = load_scene(resolve_named("scene", scene_name))
    boxes = scene.collision_boxes()
    # a fixed seed per case (str hash() is salted per process, which made the sample differ on every run)
    qs = sample_uniform(robot, N, np.random.default_rng(zlib.crc32(f"{robot_name}/{scene_name}".encode())),
                        base_box=scene.workspace)
    q32 = torch.as_tensor(qs, dtype=torch.float32)
    flags = CollisionChecker(robot, boxes).check(q32).numpy()
    cams = robot.camera_poses(q32).double().numpy()
    world = PybulletWorld(robot, boxes)
    try:
        ref = world.in_collision(qs)
        ref_cam = np.stack([world.camera_pose(q) for q in qs])
    finally:
        world.close()
    pos = np.abs(cams[:, :3, 3] - ref_cam[:, :3, 3]).max()
    rot = rotation_angle_error(cams[:, :3, :3], ref_cam[:, :3, :3]).max()
    missed = int(np.sum(ref & ~flags))
    fp = np.sum(flags & ~ref) / max(1, np.sum(~ref))
    log.warning("%s/%s: pybullet collisions %.3f, missed %d, false-positive rate %.3f, fk err %.2e m %.2e rad",
                robot_name, scene_name, ref.mean(), missed, fp, pos, rot)
    assert pos < 1e-5 and rot < 1e-5
    assert 0.05 < ref.mean() < 0.98  # the sample really exercises both outcomes
    assert missed == 0
    assert fp < 0.5


@pytest.mark.parametrize("robot_name", ["stretch2", "fetchlike", "ur5_mobile"])
def test_no_collision_missed_within_a_millimetre_of_pybullet_contact(robot_name, load_robot):
    """Near the exact contact, where a conservative model is thinnest: 500 segments from a configuration pybullet
    finds free to one it finds colliding (home scene), bisected 16 times by pybullet, both final ends kept (within
    a fraction of a millimetre, in configuration space, of pybullet's contact). Every configuration pybullet finds
    colliding is flagged by the checker, on the compiled path and on the torch path alike."""
    from psprm_core.kernels.compute import Compute, bulk

    robot = load_robot(robot_name)
    scene = load_scene(resolve_named("scene", "home"))
    boxes = scene.collision_boxes()
    rng = np.random.default_rng(zlib.crc32(f"near/{robot_name}".encode()))
    pool = sample_uniform(robot, 1500, rng, base_box=scene.workspace)
    world = PybulletWorld(robot, boxes)
    try:
        hit = world.in_collision(pool)
        assert hit.any() and (~hit).any()
        n = 500
        lo, hi = pool[rng.choice(np.nonzero(~hit)[0], n)].copy(), pool[rng.choice(np.nonzero(hit)[0], n)].copy()
        for _ in range(16):
            mid = 0.5 * (lo + hi)
            m = world.in_collision(mid)
            hi[m], lo[~m] = mid[m], mid[~m]
        near = np.vstack([lo, hi])
        exact = world.in_collision(near)
    finally:
        world.close()
    assert np.linalg.norm(hi - lo, axis=1).max() < 1e-3  # precondition: within 1 mm of pybullet's contact
    # both sides of the contact (pybullet's answers at a contact can flip on a re-check: most ends keep theirs)
    assert exact[n:].mean() > 0.9 and (~exact[:n]).mean() > 0.9
    checker = CollisionChecker(robot, boxes)
    q32 = torch.as_tensor(near, dtype=torch.float32)
    with bulk():
        fast = checker.check(q32).numpy()
    slow = checker.using(Compute.make("cpu", kernels="torch")).check(q32).numpy()
    for name, flags in (("compiled", fast), ("torch", slow)):
        missed = np.nonzero(exact & ~flags)[0]
        assert len(missed) == 0, f"{name}: {len(missed)} of {n} pybullet contacts missed, e.g. {missed[:5]}"


def test_obb_overlap_matches_brute_force():
    """SAT against a dense point-sampling check on random box pairs (overlap found by sampling => SAT says overlap;
    SAT says separated => no sampled point of A lies in B)."""
    rng = np.random.default_rng(0)
    n = 400
    def rand_rot(k):
        q = rng.normal(size=(k, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        from psprm_core.geometry import quat_to_matrix
        return np.stack([quat_to_matrix(x) for x in q])
    ca, cb = rng.uniform(-0.5, 0.5, (n, 3)), rng.uniform(-0.5, 0.5, (n, 3))
    Ra, Rb = rand_rot(n), rand_rot(n)
    ha, hb = rng.uniform(0.05, 0.3, (n, 3)), rng.uniform(0.05, 0.3, (n, 3))
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    sat = obb_overlap(t(ca), t(Ra), t(ha), t(cb), t(Rb), t(hb), eps=0.0).numpy()
    u = rng.uniform(-1, 1, (4000, 3))
    for i in range(n):
        pts = ca[i] + (u * ha[i]) @ Ra[i].T
        local = (pts - cb[i]) @ Rb[i]
        inside = np.all(np.abs(local) <= hb[i], axis=1).any()
        if inside:
            assert sat[i], f"pair {i}: sampled overlap but SAT says separated"
    assert 0.2 < sat.mean() < 0.9


def test_checker_flags_limits_nan_and_moved_box(load_robot):
    robot = load_robot("stretch2")
    q = robot.default_configuration()
    box = Box("crate", center=np.array([0.0, 0.0, 0.3]), size=np.array([0.3, 0.3, 0.3]))
    checker = CollisionChecker(robot, [], workspace=np.array([[-2.0, 2.0], [-2.0, 2.0]]))
    qs = np.stack([q, q, q, q])
    qs[1, 3] = 5.0  # lift beyond its limit
    qs[2, 0] = np.nan
    qs[3, 0] = 3.0  # outside the workspace
    assert checker.check(torch.as_tensor(qs)).tolist() == [False, True, True, True]
    checker.set_boxes([box])  # a box moves onto the robot
    assert bool(checker.check(torch.as_tensor(q[None]))[0])


@pytest.mark.parametrize("robot_name", ["stretch2", "fetchlike", "ur5_mobile"])
def test_batch_constant_self_pairs_match_row_by_row(robot_name, load_robot):
    """Self pairs whose joints hold one value over a batch are tested once (on the first row). Batches that keep
    all joints but a few fixed (as edge knots do: base and camera joints move, the arm stays) must give exactly the
    row-by-row answer, in self-collision and out of it."""
    robot = load_robot(robot_name)
    scene = load_scene(resolve_named("scene", "home"))
    checker = CollisionChecker(robot, scene.collision_boxes())
    rng = np.random.default_rng(3)
    qs = sample_uniform(robot, 440, rng, base_box=scene.workspace)
    moving = [0, 1, 2, robot.dof - 1, robot.dof - 2]  # base and the last two joints vary within a batch
    n_self = 0
    for g in range(40):
        batch = np.repeat(qs[g:g + 1], 10, axis=0)
        batch[:, moving] = qs[40 + 10 * g:50 + 10 * g][:, moving]
        qt = torch.as_tensor(batch, dtype=torch.float32)
        together = checker.check(qt).numpy()
        alone = np.array([bool(checker.check(qt[i:i + 1])[0]) for i in range(len(qt))])
        assert np.array_equal(together, alone), f"batch {g}"
        poses = robot.body_poses(qt)
        n_self += int(checker._self(poses).sum())
    assert n_self > 0  # some batches really are in self-collision through their constant pairs or moving ones


def test_self_pair_dependencies_follow_the_tree(load_robot):
    """A pair's relative pose depends on the joints between its bodies only: never on the mobile base."""
    robot = load_robot("stretch2")
    checker = CollisionChecker(robot, [])
    dep = checker.pair_joints.numpy()
    assert not dep[:, :3].any()  # x, y, theta move both bodies alike
    assert dep.any(1).all()  # every checked pair has some joint between its bodies
    pan = robot.joint_names.index("joint_head_pan")
    em = robot.elements
    for (a, b), d in zip(checker.self_pairs.numpy(), dep):
        links = {em.link_names[em.element_link[a]], em.link_names[em.element_link[b]]}
        if any("head_tilt" in x or "head_pan" in x for x in links) and not all("head" in x for x in links):
            assert d[pan], links


def test_a_cached_pybullet_urdf_naming_meshes_no_longer_on_disk_is_written_again(tmp_path, monkeypatch, load_robot):
    """A derived URDF left in the cache by an install since removed (its mesh paths under a folder that is gone) is
    not handed to pybullet: the world loads and every mesh the URDF it loaded names is a file."""
    monkeypatch.setenv("PSPRM_CACHE_DIR", str(tmp_path / "cache"))
    robot = load_robot("stretch2")
    path = pybullet_urdf(robot)
    tree = ET.parse(path)
    meshes = list(tree.getroot().iter("mesh"))
    assert meshes, "the stretch2 URDF has meshes"
    gone = tmp_path / "removed_install"
    for m in meshes:
        m.set("filename", str(gone / "meshes" / Path(m.get("filename")).name))
    tree.write(path)  # the cache entry as an earlier install at another place left it
    world = PybulletWorld(robot, [])
    world.close()
    loaded = ET.parse(pybullet_urdf(robot)).getroot()
    assert all(Path(m.get("filename")).is_file() for m in loaded.iter("mesh"))
