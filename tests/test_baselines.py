"""The bench baselines: Post, Rejection, Manifold-line/-frustum behind the common BenchPlanner interface."""

import numpy as np
import pytest
import torch

from psprm_core.baselines import BASELINES, make_baseline, planner_names
from psprm_core.baselines.base import BaselineSettings, BenchPlanner, CameraFK, settings_from_yaml
from psprm_core.errors import ConfigError, PsprmError
from psprm_core.paths import resolve_named
from psprm_core.robot import RobotModel
from psprm_core.scene import load_scene

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def home():
    scene = load_scene(resolve_named("scene", "home"))
    return scene, RobotModel.load(scene.robot)


def _aimed(p, base):
    """A configuration at base pose (x, y, theta) with the camera aimed at the planner's focus."""
    q = p.robot.default_configuration()
    q[:3] = base
    q, ok = p.ctx.aim(q[None], "line")
    assert ok[0]
    return q[0]


def _easy(p):
    # two poses south of the TV, both facing it: a short drive along the room
    return _aimed(p, (5.0, 3.4, 1.57)), _aimed(p, (6.0, 3.5, 1.57))


def _executed_ok(p, res, start, goal):
    assert res.success, res.reason
    d = res.dense
    np.testing.assert_allclose(d[0], start, atol=1e-9)
    np.testing.assert_allclose(d[-1], goal, atol=1e-9)
    assert p.ctx.valid(d).all()  # the densified executed motion is collision-free
    # consecutive executed configurations are close (densified at the resolution: no teleporting base or head)
    assert np.linalg.norm(np.diff(d[:, :2], axis=0), axis=1).max() <= 0.05 + 1e-9
    assert np.abs(np.diff(d[:, p.ctx.aim_cols], axis=0)).max() <= 0.1 + 1e-9
    # base moves like a differential drive: lateral motion in the robot frame stays ~0
    dxy = np.diff(d[:, :2], axis=0)
    lateral = -np.sin(d[:-1, 2]) * dxy[:, 0] + np.cos(d[:-1, 2]) * dxy[:, 1]
    assert np.abs(lateral).max() < 1e-6
    assert res.path_length > 0


def test_registry_and_interface(home):
    assert planner_names() == ["post", "rejection", "manifold-line", "manifold-frustum", "trajopt", "rl-ppo",
                               "psprm-line", "psprm-frustum", "neural-psprm-line", "neural-psprm-frustum"]
    assert set(planner_names()) == set(BASELINES)
    scene, robot = home
    p = make_baseline("post", scene, ["tv"], robot=robot)
    assert isinstance(p, BenchPlanner) and p.name == "post"
    assert p.prepare()["preprocess_s"] == 0.0
    with pytest.raises(PsprmError):
        make_baseline("nope", scene, ["tv"], robot=robot)


def test_settings_yaml(tmp_path):
    s = settings_from_yaml(BaselineSettings, "manifold", timeout_s=3.0)
    assert s.timeout_s == 3.0 and s.delta == 0.3  # from config/planners/baselines.yaml
    bad = tmp_path / "b.yaml"
    bad.write_text("post: {rnage: 1.0}\n")
    with pytest.raises(ConfigError, match="rnage"):
        settings_from_yaml(BaselineSettings, "post", path=bad)


def test_numpy_camera_fk_matches_torch(home):
    _, robot = home
    rng = np.random.default_rng(0)
    lo = np.where(np.isfinite(robot.lower), robot.lower, -3)
    hi = np.where(np.isfinite(robot.upper), robot.upper, 3)
    q = rng.uniform(lo, hi, (20, robot.dof))
    T = robot.camera_poses(torch.as_tensor(q)).numpy()
    R, t = CameraFK(robot)(q)
    assert np.abs(T[:, :3, :3] - R).max() < 1e-9 and np.abs(T[:, :3, 3] - t).max() < 1e-9


def test_post_aims_camera_along_the_path(home):
    scene, robot = home
    p = make_baseline("post", scene, ["tv"], robot=robot)
    a, b = _aimed(p, (1.0, 1.0, 0.0)), _aimed(p, (6.8, 3.0, 1.57))
    res = p.plan(a, b, timeout_s=20.0)
    _executed_ok(p, res, a, b)
    err = p.ctx.view_error(res.dense, "line")
    # wherever the head's joint limits can reach the target (Stretch's pan misses a ~50 deg wedge behind-left), the
    # optical axis passes within 2 cm of it
    reachable = p.ctx.aim(res.dense, "line")[1]
    assert reachable.sum() >= 20
    # (except inside the head's sweeps between its joint limits, which fill_joint_jumps inserts)
    assert (err[reachable] <= 0.02 + 1e-6).mean() >= 0.9
    # and the aiming is what does it: the planned (un-aimed) head angles would not point there
    unaimed = res.dense.copy()
    unaimed[:, p.ctx.aim_cols] = a[p.ctx.aim_cols]
    assert np.median(p.ctx.view_error(unaimed[reachable], "line")) > 0.1


def test_rejection_keeps_target_in_frustum(home):
    scene, robot = home
    p = make_baseline("rejection", scene, ["tv"], robot=robot)
    a, b = _easy(p)
    res = p.plan(a, b, timeout_s=20.0)
    _executed_ok(p, res, a, b)
    assert p.ctx.in_view(res.dense).all()


@pytest.mark.parametrize("name", ["manifold-line", "manifold-frustum"])
def test_manifold_paths_stay_on_the_manifold(home, name):
    scene, robot = home
    p = make_baseline(name, scene, ["tv"], robot=robot)
    a, b = _easy(p)
    res = p.plan(a, b, timeout_s=20.0)
    _executed_ok(p, res, a, b)
    if name == "manifold-line":
        assert (p.ctx.view_error(res.waypoints, "line") <= 0.04).all()
        assert (p.ctx.view_error(res.dense, "line") <= 0.04).all()
    else:
        assert p.ctx.in_view(res.waypoints).all() and p.ctx.in_view(res.dense).all()


@pytest.mark.parametrize("name", ["post", "rejection", "manifold-line"])
def test_bad_problems_fail_with_a_reason(home, name):
    scene, robot = home
    p = make_baseline(name, scene, ["tv"], robot=robot)
    a, b = _easy(p)
    inside = a.copy()
    inside[:2] = scene.obstacle("table").center[:2]  # base inside the table
    res = p.plan(inside, b, timeout_s=1.0)
    assert not res.success and "start" in res.reason
    res = p.plan(a, np.vstack([inside]), timeout_s=1.0)
    assert not res.success and "goal" in res.reason
    res = p.plan(a * np.nan, b, timeout_s=1.0)
    assert not res.success
