"""Scene files: every shipped scene loads and is usable; malformed scenes fail with a ConfigError naming file and
field; the top-view plots render."""

from __future__ import annotations

import copy
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from psprm_core.errors import ConfigError
from psprm_core.geometry import quat_to_matrix, yaw_to_quat
from psprm_core.scene import load_scene

SCENE_DIR = Path(__file__).resolve().parent.parent / "config" / "scenes"
SCENE_FILES = sorted(SCENE_DIR.glob("*.yaml"))
EXPECTED_SCENES = {"home", "nursing", "dynamic_person", "blind_spot_alley", "cup_table"}

#: Minimum distance from the base centre to any obstacle footprint at a start/goal, per robot (footprint + margin).
CLEARANCE = {"stretch2": 0.40, "fetchlike": 0.50, "ur5_mobile": 0.60}
KNOWN_APPEARANCES = {"face_astronaut", "coffee_cup", "monitor", "potted_plant", "suitcase", "fork"}


# ------------------------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------------------------
def point_rect_distance(point, center, half_extents, yaw) -> float:
    """2-D distance from ``point`` to a rectangle (centre, half extents, yaw); 0 inside."""
    d = np.asarray(point, float)[:2] - np.asarray(center, float)[:2]
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])  # R(yaw)^T d
    outside = np.maximum(np.abs(local) - np.asarray(half_extents, float)[:2], 0.0)
    return float(np.linalg.norm(outside))


def footprint_rect(box):
    """(centre, half extents, yaw) of a box's footprint. Boxes rotated about z only give their exact rectangle;
    tilted boxes give the axis-aligned rectangle around their projected corners (conservative)."""
    r = quat_to_matrix(box.quat)
    if abs(r[2, 2]) > 1.0 - 1e-9:
        return box.center[:2], 0.5 * np.asarray(box.size)[:2], math.atan2(r[1, 0], r[0, 0])
    xy = box.corners()[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return 0.5 * (lo + hi), 0.5 * (hi - lo), 0.0


def base_xy(joints):
    return np.array([joints["base_x"], joints["base_y"]])


def base_poses(scene):
    """(label, (x, y), tolerance) of every start, goal and goal region base position in the scene; the
    tolerance is how far from (x, y) the base may end up (a goal region's ``xy_tolerance``, else 0)."""
    out = []
    for p in scene.problems:
        out.append((f"{p.name}.start", base_xy(p.start), 0.0))
        if p.goal:
            out.append((f"{p.name}.goal", base_xy(p.goal), 0.0))
    for g in scene.goals:
        out.append((f"goal region {g.name}", np.asarray(g.base[:2]), g.xy_tolerance))
    return out


def test_point_rect_distance_helper():
    assert point_rect_distance([0.0, 0.0], [0.0, 0.0], [1.0, 0.5], 0.3) == 0.0
    assert point_rect_distance([2.0, 0.0], [0.0, 0.0], [1.0, 0.5], 0.0) == pytest.approx(1.0)
    assert point_rect_distance([2.0, 1.5], [0.0, 0.0], [1.0, 0.5], 0.0) == pytest.approx(math.sqrt(2.0))
    # rotated by 90 deg: the long side now runs along y
    assert point_rect_distance([0.0, 2.0], [0.0, 0.0], [1.0, 0.5], math.pi / 2) == pytest.approx(1.0)
    assert point_rect_distance([2.0, 0.0], [0.0, 0.0], [1.0, 0.5], math.pi / 2) == pytest.approx(1.5)
    # 45 deg square of half side 1: the corner reaches sqrt(2) along x
    assert point_rect_distance([3.0, 0.0], [0.0, 0.0], [1.0, 1.0], math.pi / 4) == pytest.approx(3.0 - math.sqrt(2))


# ------------------------------------------------------------------------------------------------------------------
# shipped scenes
# ------------------------------------------------------------------------------------------------------------------
def test_all_expected_scenes_are_shipped():
    assert EXPECTED_SCENES <= {p.stem for p in SCENE_FILES}


@pytest.fixture(scope="module", params=SCENE_FILES, ids=[p.stem for p in SCENE_FILES])
def scene(request):
    return load_scene(request.param)


def test_scene_loads(scene):
    assert scene.name == Path(scene.source).stem
    assert scene.robot in CLEARANCE
    assert scene.frame == "map"
    assert scene.obstacles and scene.targets
    if scene.name in EXPECTED_SCENES:  # planning scenes; data-collection scenes (surrogate_studio) have no problems
        assert scene.problems
    raw = yaml.safe_load(Path(scene.source).read_text())
    assert isinstance(raw.get("description"), str) and len(raw["description"]) > 20
    for t in scene.targets:
        assert t.appearance in KNOWN_APPEARANCES, t.name
        assert np.isclose(np.linalg.norm(t.facing), 1.0)
    for p in scene.problems:
        assert {"base_x", "base_y", "base_theta"} <= set(p.start), p.name
        if p.goal:
            assert {"base_x", "base_y", "base_theta"} <= set(p.goal), p.name
        scene.target(p.target)
        for r in p.goal_regions:
            scene.goal(r)


def test_start_goal_inside_workspace(scene):
    (x0, x1), (y0, y1) = scene.workspace
    for label, xy, tol in base_poses(scene):
        assert x0 + tol <= xy[0] <= x1 - tol and y0 + tol <= xy[1] <= y1 - tol, \
            f"{scene.name}: {label} {xy} (+- {tol}) outside the workspace"


def test_start_goal_clear_of_obstacles(scene):
    need = CLEARANCE[scene.robot]
    boxes = scene.collision_boxes()
    for label, xy, tol in base_poses(scene):
        for b in boxes:
            c, half, yaw = footprint_rect(b)
            d = point_rect_distance(xy, c, half, yaw) - tol
            assert d >= need, f"{scene.name}: {label} at {xy} (+- {tol}) is {d:.3f} m from '{b.name}' (< {need} m)"


def test_targets_are_above_the_floor_and_inside_the_room(scene):
    (x0, x1), (y0, y1) = scene.workspace
    for t in scene.targets:
        for k in range(t.n_placements):  # every benchmark placement too
            c, q = t.pose(k)
            lowest = c[2] - 0.5 * np.abs(quat_to_matrix(q)[2]) @ t.size
            assert lowest >= -1e-6, (t.name, k)
            assert x0 <= c[0] <= x1 and y0 <= c[1] <= y1, (t.name, k)


# ------------------------------------------------------------------------------------------------------------------
# malformed scenes
# ------------------------------------------------------------------------------------------------------------------
VALID = {
    "name": "tiny",
    "robot": "stretch2",
    "workspace": {"x": [0.0, 4.0], "y": [0.0, 3.0]},
    "obstacles": [{"name": "table", "center": [2.0, 1.5, 0.375], "size": [1.0, 0.6, 0.75]}],
    "targets": [{"name": "cup", "class": "cup", "center": [2.0, 1.5, 0.8], "size": [0.08, 0.08, 0.1],
                 "obstacle": False}],
    "goals": [{"name": "east", "base": [3.5, 1.5, 0.0]}],
    "problems": [{"name": "p", "target": "cup", "start": {"base_x": 0.5, "base_y": 1.5, "base_theta": 0.0},
                  "goal": {"base_x": 3.5, "base_y": 1.5, "base_theta": 0.0}}],
}


def _write(tmp_path, data, name="scene.yaml") -> Path:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return path


def _expect_error(path, field, *fragments):
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    if field:
        assert info.value.field == field, msg
        assert f"'{field}'" in msg, msg
    for frag in fragments:
        assert frag in msg, msg
    return info.value


def test_valid_minimal_scene_loads(tmp_path):
    s = load_scene(_write(tmp_path, VALID))
    assert s.frame == "map" and s.target("cup").obstacle is False
    assert np.allclose(s.obstacle("table").quat, [0, 0, 0, 1])
    assert s.problem("p").goal_regions == ()


def test_target_placements(tmp_path):
    data = copy.deepcopy(VALID)
    data["targets"][0]["placements"] = [{"center": [1.7, 1.4, 0.8], "yaw": 1.0},
                                        {"center": [0.5, 2.5, 0.05], "quat": [0, 0, 1, 1]}]
    s = load_scene(_write(tmp_path, data))
    cup = s.target("cup")
    assert cup.n_placements == 3
    c, q = cup.pose(1)
    assert c.tolist() == [1.7, 1.4, 0.8] and np.allclose(q, yaw_to_quat(1.0))
    assert np.allclose(cup.pose(2)[1], [0, 0, math.sqrt(0.5), math.sqrt(0.5)])  # normalised
    assert np.array_equal(cup.pose(0)[0], cup.center)
    moved = s.with_placement(["cup"], 2)
    assert moved.target("cup").center.tolist() == [0.5, 2.5, 0.05] and s.target("cup").center[0] == 2.0
    assert moved.target("cup").placements == cup.placements  # still knows where else it may go
    assert s.with_placement(["cup"], 0) is s
    with pytest.raises(IndexError, match="3 placement"):
        cup.pose(3)
    with pytest.raises(KeyError, match="no target 'mug'"):
        s.with_placement(["mug"], 0)


@pytest.mark.parametrize("placement, field, fragment", [
    ({"center": [2.0, 1.5, 0.5], "yaw": 0.0}, "targets[0].placements[0]", "intersects table"),
    ({"center": [9.0, 1.5, 0.8]}, "targets[0].placements[0]", "outside the workspace"),
    ({"center": [2.0, 1.5, 0.8], "size": [1, 1, 1]}, "targets[0].placements[0].size", "unknown field"),
    ({"center": [2.0, 1.5, float("nan")]}, "targets[0].placements[0].center", "finite"),
], ids=["inside_an_obstacle", "outside", "unknown_key", "nan"])
def test_bad_target_placements(tmp_path, placement, field, fragment):
    data = copy.deepcopy(VALID)
    data["targets"][0]["placements"] = [placement]
    _expect_error(_write(tmp_path, data), field, fragment)


def test_malformed_yaml(tmp_path):
    path = _write(tmp_path, "name: tiny\nobstacles: [{name: a, center: [1, 2, 3]\n")
    _expect_error(path, "", "malformed YAML", "line")


def test_top_level_not_a_mapping(tmp_path):
    _expect_error(_write(tmp_path, "- just\n- a list\n"), "", "mapping")


def test_nan_in_pose_literal(tmp_path):
    text = yaml.safe_dump(VALID, sort_keys=False).replace("center:\n  - 2.0\n  - 1.5\n  - 0.375",
                                                          "center:\n  - .nan\n  - 1.5\n  - 0.375")
    assert ".nan" in text
    _expect_error(_write(tmp_path, text), "obstacles[0].center", "finite")


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d["targets"][0].__setitem__("center", [2.0, float("nan"), 0.8]), "targets[0].center"),
    (lambda d: d["targets"][0].__setitem__("yaw", float("nan")), "targets[0].yaw"),
    (lambda d: d["problems"][0]["start"].__setitem__("base_x", float("nan")), "problems[0].start.base_x"),
    (lambda d: d["problems"][0]["goal"].__setitem__("base_theta", float("inf")), "problems[0].goal.base_theta"),
    (lambda d: d["goals"][0].__setitem__("base", [3.5, float("nan"), 0.0]), "goals[0].base"),
], ids=["target_center", "target_yaw", "start_base_x", "goal_theta_inf", "goal_region_base"])
def test_non_finite_values(tmp_path, mutate, field):
    data = copy.deepcopy(VALID)
    mutate(data)
    _expect_error(_write(tmp_path, data), field, "finite")


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.pop("robot"), "robot"),
    (lambda d: d.pop("workspace"), "workspace"),
    (lambda d: d["workspace"].pop("y"), "workspace.y"),
    (lambda d: d["obstacles"][0].pop("size"), "obstacles[0].size"),
    (lambda d: d["targets"][0].pop("class"), "targets[0].class"),
    (lambda d: d["problems"][0].pop("target"), "problems[0].target"),
    (lambda d: d["problems"][0].pop("start"), "problems[0].start"),
    (lambda d: d["goals"][0].pop("base"), "goals[0].base"),
], ids=["robot", "workspace", "workspace_y", "box_size", "target_class", "problem_target", "problem_start",
        "goal_base"])
def test_missing_required_field(tmp_path, mutate, field):
    data = copy.deepcopy(VALID)
    mutate(data)
    _expect_error(_write(tmp_path, data), field, "missing")


@pytest.mark.parametrize("mutate, field", [
    (lambda d: d.__setitem__("robots", "stretch2"), "robots"),
    (lambda d: d["obstacles"][0].__setitem__("colour", [1, 0, 0]), "obstacles[0].colour"),
    (lambda d: d["targets"][0].__setitem__("facing", 0.0), "targets[0].facing"),
    (lambda d: d["problems"][0].__setitem__("goal_region", ["east"]), "problems[0].goal_region"),
    (lambda d: d["workspace"].__setitem__("z", [0, 2]), "workspace.z"),
], ids=["top", "box", "target", "problem", "workspace"])
def test_unknown_field(tmp_path, mutate, field):
    data = copy.deepcopy(VALID)
    mutate(data)
    _expect_error(_write(tmp_path, data), field, "unknown field")


@pytest.mark.parametrize("kind", ["obstacles", "targets", "goals", "problems"])
def test_duplicate_name(tmp_path, kind):
    data = copy.deepcopy(VALID)
    data[kind].append(copy.deepcopy(data[kind][0]))
    _expect_error(_write(tmp_path, data), kind, "duplicate", data[kind][0]["name"])


def test_target_and_obstacle_share_a_name(tmp_path):
    data = copy.deepcopy(VALID)
    data["targets"][0]["name"] = "table"
    data["problems"][0]["target"] = "table"
    _expect_error(_write(tmp_path, data), "targets", "table")


def test_problem_names_unknown_target(tmp_path):
    data = copy.deepcopy(VALID)
    data["problems"][0]["target"] = "mug"
    _expect_error(_write(tmp_path, data), "problems[0].target", "unknown target", "mug")


def _two_targets():
    data = copy.deepcopy(VALID)
    data["targets"].append({"name": "plate", "class": "bowl", "center": [2.3, 1.5, 0.76], "size": [0.2, 0.2, 0.03]})
    return data


def test_problem_with_several_targets(tmp_path):
    data = _two_targets()
    data["problems"][0].pop("target")
    data["problems"][0]["targets"] = ["plate", "cup"]
    p = load_scene(_write(tmp_path, data)).problems[0]
    assert p.all_targets == ["plate", "cup"] and p.target == "plate"
    single = load_scene(_write(tmp_path, VALID, "single.yaml")).problems[0]
    assert single.all_targets == ["cup"] and single.targets == ()


@pytest.mark.parametrize("value, fragment", [
    (["plate", "mug"], "unknown target"), ([], "non-empty list"), ("cup", "list"), (["cup", "cup"], "twice"),
    ("both", "either"),
], ids=["unknown", "empty", "not_a_list", "twice", "with_target"])
def test_problem_targets_errors(tmp_path, value, fragment):
    data = _two_targets()
    if value != "both":
        data["problems"][0].pop("target")
    data["problems"][0]["targets"] = ["cup", "plate"] if value == "both" else value
    _expect_error(_write(tmp_path, data), "problems[0].targets", fragment)


def test_problem_names_unknown_goal_region(tmp_path):
    data = copy.deepcopy(VALID)
    data["problems"][0]["goal_regions"] = ["west"]
    _expect_error(_write(tmp_path, data), "problems[0].goal_regions", "west")


@pytest.mark.parametrize("mutate, field, fragment", [
    (lambda d: d["obstacles"][0].__setitem__("size", [1.0, 0.0, 0.75]), "obstacles[0].size", "> 0"),
    (lambda d: d["obstacles"][0].__setitem__("color", [255, 0, 0]), "obstacles[0].color", "0..1"),
    (lambda d: d["obstacles"][0].update(yaw=0.1, quat=[0, 0, 0, 1]), "obstacles[0].quat", "either"),
    (lambda d: d["workspace"].__setitem__("x", [4.0, 0.0]), "workspace", "min < max"),
    (lambda d: d["problems"][0].pop("goal"), "problems[0]", "goal"),
    (lambda d: d["problems"][0]["start"].__setitem__("base_x", "left"), "problems[0].start.base_x", "number"),
    (lambda d: d["problems"][0]["start"].__setitem__(1, 0.5), "problems[0].start.1", "string"),
    (lambda d: d["targets"][0].__setitem__("obstacle", "no"), "targets[0].obstacle", "true/false"),
], ids=["zero_size", "color_range", "yaw_and_quat", "workspace_order", "no_goal", "joint_not_number",
        "joint_name_not_string", "obstacle_not_bool"])
def test_invalid_values(tmp_path, mutate, field, fragment):
    data = copy.deepcopy(VALID)
    mutate(data)
    _expect_error(_write(tmp_path, data), field, fragment)


def test_missing_file(tmp_path):
    _expect_error(tmp_path / "nope.yaml", "", "not found")


# ------------------------------------------------------------------------------------------------------------------
# plotting
# ------------------------------------------------------------------------------------------------------------------
def _pyplot_figures():
    plt = sys.modules.get("matplotlib.pyplot")
    return None if plt is None else list(plt.get_fignums())


def test_save_scene_figure(scene, tmp_path):
    from psprm_core.evaluation.viz import save_scene_figure

    before = _pyplot_figures()
    out = save_scene_figure(scene, tmp_path / "fig" / f"{scene.name}.png")
    assert out.is_file() and out.stat().st_size > 10_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert _pyplot_figures() == before  # nothing left open in pyplot


def test_plot_helpers(tmp_path):
    from psprm_core.evaluation.viz import (box_footprint, new_figure, plot_path_top, plot_roadmap_top, plot_scene_top,
                                           plot_spheres_top, save_scene_figure)

    scene = load_scene(SCENE_DIR / "cup_table.yaml")
    rng = np.random.default_rng(0)
    centers = np.column_stack([rng.uniform(1.0, 1.4, 20), rng.uniform(1.0, 1.4, 20), rng.uniform(0, 1.3, 20)])
    radii = rng.uniform(0.02, 0.08, 20)
    out = save_scene_figure(scene, tmp_path / "with_robot.png", robot_spheres=(centers, radii), title="robot")
    assert out.stat().st_size > 10_000

    fig, ax = new_figure()
    plot_scene_top(ax, scene, show_labels=False)
    coll = plot_spheres_top(ax, centers, radii, edgecolor="k")
    assert len(coll.get_paths()) == 20
    nodes = rng.uniform(0.5, 5.5, (30, 2))
    edges = np.array([[i, (i + 1) % 30] for i in range(30)])
    lc = plot_roadmap_top(ax, nodes, edges, color="0.5", node_size=3)
    assert len(lc.get_segments()) == 30
    xy = np.column_stack([np.linspace(2.3, 2.3, 5), np.linspace(1.0, 4.0, 5)])
    path_lc = plot_path_top(ax, xy, scores=np.linspace(0.1, 0.9, 5))
    assert len(path_lc.get_segments()) == 4 and np.allclose(path_lc.get_array(), [0.2, 0.4, 0.6, 0.8])
    plot_path_top(ax, xy, scores=None)
    assert len(fig.axes) == 2  # plot + colour bar
    fig.savefig(tmp_path / "helpers.png")
    assert (tmp_path / "helpers.png").stat().st_size > 10_000

    with pytest.raises(ValueError):
        plot_roadmap_top(ax, nodes, [[0, 30]])
    with pytest.raises(ValueError):
        plot_path_top(ax, xy, scores=[0.1, 0.2])

    # an upright rotated box gives its rotated rectangle; a tilted one a hexagon-or-rectangle hull
    poly = box_footprint([0, 0, 0], [2.0, 1.0, 1.0], yaw_to_quat(math.pi / 2))
    assert poly.shape == (4, 2) and np.allclose(np.abs(poly).max(axis=0), [0.5, 1.0])
    tilted = box_footprint([0, 0, 0], [1.0, 1.0, 1.0], [0.0, math.sin(0.3), 0.0, math.cos(0.3)])
    assert 4 <= len(tilted) <= 6


def test_box_and_target_rotations_follow_their_quaternions():
    """A box's and a target's rotation matrix is pybullet's of its quaternion, for the box itself, for a box made
    from it with another quaternion, and after a caller wrote into a rotation it was given (each caller gets its
    own array); a target's box has the target's pose."""
    from dataclasses import replace

    import pybullet

    from psprm_core.scene import Box, Target

    def reference(q):
        return np.asarray(pybullet.getMatrixFromQuaternion((np.asarray(q) / np.linalg.norm(q)).tolist())).reshape(3, 3)

    rng = np.random.default_rng(5)
    for _ in range(20):
        q1, q2 = rng.normal(size=4), rng.normal(size=4)
        box = Box(name="b", center=rng.normal(size=3), size=rng.uniform(0.1, 1.0, 3), quat=q1)
        got = box.rotation
        assert np.allclose(got, reference(q1), atol=1e-12)
        got[:] = 0.0  # the caller's copy
        assert np.allclose(box.rotation, reference(q1), atol=1e-12)
        moved = replace(box, quat=q2)
        assert np.allclose(moved.rotation, reference(q2), atol=1e-12)
        assert np.allclose(box.rotation, reference(q1), atol=1e-12)
        assert np.allclose(moved.half_extents, 0.5 * box.size)
        tgt = Target(name="t", detector_class="face", center=box.center, size=box.size, quat=q1)
        assert np.allclose(tgt.rotation, reference(q1), atol=1e-12) and np.allclose(tgt.facing, reference(q1)[:, 0])
        turned = replace(tgt, quat=q2)
        assert np.allclose(turned.as_box().rotation, reference(q2), atol=1e-12)
        assert np.allclose(turned.as_box().center, box.center) and np.allclose(tgt.as_box().rotation, reference(q1))
