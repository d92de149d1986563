"""The device check (scripts/check_device.sh, scripts/check_device_bare.sh) on this CPU with the compiled kernels off:
the torch code a GPU runs builds a roadmap, answers queries and replans after target turns with paths that are
collision-free and end at a goal, path lengths equal to the compiled CPU planner's; its FK agrees with pybullet's and
its collision flags miss none of pybullet's collisions. With references carried in a file it runs in a Python that
cannot import pybullet, ompl, rclpy, ray, toppra, trimesh or the robot-description package (scripts/bare_run.py), and
it fails when a reference is perturbed."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "psprm_core" / "data" / "device_check" / "references.npz"


def _bare_check(*args, timeout=240):
    """The check of the carried references as scripts/check_device_bare.sh runs it, with this Python: (rc, JSON)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "bare_run.py"), "-m", "psprm_core.evaluation.device_check",
                        "--device", "cpu", "--torch-path", *args], capture_output=True, text=True, timeout=timeout,
                       cwd=ROOT, env=env)
    lines = r.stdout.strip().splitlines()
    assert lines, r.stderr[-3000:]
    return r.returncode, json.loads(lines[-1])


def test_torch_path_passes_the_device_check_judged_by_pybullet():
    from psprm_core.evaluation.device_check import run

    out = run("cpu", torch_path=True, configs=600, nodes=300, queries=4, replans=2)
    assert out["torch_path"] and out["kernels"] == "torch" and out["missed_collisions"] == 0
    assert out["backend"] == "TorchBackend"  # the device planner ran the torch code
    assert out["fk_max_position_error_m"] < 1e-3 and out["fk_max_rotation_error_rad"] < 1e-3
    assert out["queries_solved"] == out["queries"] == 4 and out["replans_solved"] == 2
    assert out["path_collision_judge"] == "pybullet"
    assert out["path_collisions"] == 0 and out["path_goal_error_max"] < 1e-3
    assert out["path_length_relative_difference_median"] < 1e-4  # same code, same precision: the same paths
    assert out["ok"] and out["failed"] == []


def test_check_device_script_says_when_there_is_no_cuda_and_exits_0():
    import torch

    if torch.cuda.is_available():  # pragma: no cover - a CUDA machine runs the real check instead
        pytest.skip("CUDA is available here: scripts/check_device.sh runs the real check")
    r = subprocess.run(["bash", str(ROOT / "scripts" / "check_device.sh"), "cuda"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0
    assert json.loads(r.stdout.strip().splitlines()[-1])["checked"] is False


def test_bare_launcher_makes_the_missing_requirements_unimportable():
    for module in ("pybullet", "stretch_urdf", "toppra", "trimesh"):
        r = subprocess.run([sys.executable, str(ROOT / "scripts" / "bare_run.py"), "-m", module],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode != 0 and f"No module named '{module}'" in r.stderr, (module, r.stderr[-500:])


def test_carried_references_pass_without_pybullet_and_fail_when_perturbed(tmp_path):
    """The shipped references, a prefix of them (300 configurations, 2 queries, 1 replan; the roadmap of the file's
    600 nodes), checked by the torch path with the missing requirements unimportable: it passes, its path collisions
    judged by the CPU checker in float64. A copy with a camera pose moved 1 cm, every free configuration of the
    prefix flagged in collision (so those the device calls free are missed collisions) and one node score off by 0.1
    fails on exactly those three checks."""
    sizes = ("--configs", "300", "--queries", "2", "--replans", "1")
    rc, out = _bare_check("--references", str(SHIPPED), *sizes)
    assert rc == 0 and out["ok"] and out["failed"] == [], out
    assert out["configs"] == 300 and out["queries_solved"] == 2 and out["replans_solved"] == 1
    assert out["path_collision_judge"].startswith("cpu collision checker, float64")
    assert out["path_collisions"] == 0 and out["missed_collisions"] == 0
    assert set(out["build_s"]) == set(out["query_ms_median"]) == set(out["replan_ms_median"]) \
        == {"cpu_reference", "device"}

    with np.load(SHIPPED, allow_pickle=False) as z:
        data = {k: z[k].copy() for k in z.files}
    data["camera_poses"][0, 0, 3] += 0.01
    data["collision"][:300] = True
    data["node_scores"][0] += 0.1
    bad = tmp_path / "perturbed.npz"
    np.savez_compressed(bad, **data)
    rc, out = _bare_check("--references", str(bad), *sizes)
    assert rc == 1 and not out["ok"]
    assert out["failed"] == ["fk_position", "missed_collisions", "node_scores"], out
    assert abs(out["fk_max_position_error_m"] - 0.01) < 1e-4 and out["missed_collisions"] > 0


def test_shipped_references_are_those_of_the_packaged_robot_scene_and_surrogate():
    """The carried file still describes this repository: its configurations are the seeded samples, its planning URDF
    is the packaged robot's (collision meshes as their boxes) and gives the same collision model, and its float64
    scores are what the shipped surrogate gives. A failure here means: record them again (the command in docs/benchmarks.md)."""
    import tempfile

    import torch

    from psprm_core.evaluation.device_check.references import (References, carried_robot, model_difference,
                                                         planning_urdf, sphere_table)
    from psprm_core.evaluation.reference import sample_uniform
    from psprm_core.kernels.compute import Compute
    from psprm_core.paths import resolve_named
    from psprm_core.perception.scoring import NeuralScorer
    from psprm_core.perception.surrogate import load_surrogate
    from psprm_core.planning.factory import default_checkpoint
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    refs = References.load(SHIPPED)
    h = refs.header
    assert SHIPPED.stat().st_size < 1_000_000
    scene = load_scene(resolve_named("scene", h["scene"]))
    robot = RobotModel.load(scene.robot)
    qs = sample_uniform(robot, h["configs"], np.random.default_rng(h["seed"]), base_box=scene.workspace)
    np.testing.assert_array_equal(refs.configs, qs)
    assert refs.robot_urdf.tobytes().decode() == planning_urdf(robot)
    np.testing.assert_allclose(refs.robot_spheres, sphere_table(robot), rtol=0, atol=1e-12)
    with tempfile.TemporaryDirectory() as tmp:
        assert model_difference(carried_robot(refs, scene, Path(tmp)), robot) < 1e-9
    scorer = NeuralScorer(load_surrogate(default_checkpoint()), scene, h["target"])
    torch_only = Compute.make("cpu", kernels="torch")
    free = torch.as_tensor(refs.configs[refs.score_index], dtype=torch.float64)
    s = scorer.using(torch_only).score(robot.using(torch_only).camera_poses(free)).double().numpy()
    np.testing.assert_allclose(s, refs.scores, rtol=0, atol=1e-9)
    assert not refs.collision[refs.score_index].any()


def test_record_writes_references_the_check_reads(tmp_path):
    from psprm_core.evaluation.device_check.references import References, record

    path = tmp_path / "refs.npz"
    head = record(path, configs=40, nodes=120, queries=1, replans=1, seed=3)
    assert head["bytes"] == path.stat().st_size and head["robot_model_difference_m"] < 1e-9
    refs = References.load(path)
    assert refs.header["configs"] == 40 and refs.header["seed"] == 3 and refs.configs.shape == (40, 8)
    assert refs.camera_poses.shape == (40, 4, 4) and refs.collision.shape == (40,)
    assert len(refs.query_starts) == len(refs.query_ms) == int(refs.query_goal_counts.size) == 1
    assert refs.replan_yaws.shape == refs.replan_ms.shape == (1,)
    with pytest.raises(ValueError, match="hold 40"):
        refs.prefix(41, None, None)
