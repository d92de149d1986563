"""The ``psprm`` command line: help, the kinematics benchmark's JSON, the demo, and one-line errors."""

from __future__ import annotations

import json
import time

import pytest

from psprm_core.cli import main


def test_help_lists_subcommands(capsys):
    try:
        main(["--help"])
    except SystemExit:
        pass
    out = capsys.readouterr().out
    for cmd in ("demo", "perf", "robot"):
        assert cmd in out


def test_perf_kinematics_json(capsys):
    assert main(["perf", "kinematics", "--robot", "ur5_mobile", "--scene", "blind_spot_alley", "--n", "400",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("fk_per_s", "collision_per_s", "pybullet_collision_per_s", "speedup", "missed_collisions",
                "false_positive_rate"):
        assert key in res
    assert res["missed_collisions"] == 0
    assert abs(res["speedup"] - res["collision_per_s"] / res["pybullet_collision_per_s"]) < 1e-6 * res["speedup"]


def test_demo_writes_picture(tmp_path, capsys):
    assert main(["demo", "--scene", "cup_table", "--samples", "2000", "--nodes", "0", "--out", str(tmp_path),
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["collision_free"] > 0 and (tmp_path / "demo_cup_table.png").stat().st_size > 10000
    assert all(p["start"] == "free" for p in res["problems"])


def test_bad_input_gives_one_line_error(capsys):
    assert main(["perf", "kinematics", "--robot", "nope", "--scene", "home", "--n", "10"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown robot 'nope'" in err[0]
    for bad, words in ((["--variants", "prediction,nope"], "unknown variant 'nope'"),
                       (["--history-s", "0"], "history_s and turn_period_s must be > 0")):
        assert main(["perf", "replan-motion", "--nodes", "50", *bad]) == 2, bad
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert main(["dynbench", "--scenarios", "recorded_person", "--history", "-1", "--no-oracle"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "history must be a finite time >= 0 s" in err[0], err


def test_plan_json_and_plot(tmp_path, capsys):
    plot = tmp_path / "plan.png"
    code = main(["plan", "--scene", "cup_table", "--planner", "neural-psprm-line", "--nodes", "400", "--seed", "0",
                 "--json", "--plot", str(plot)])
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and res["success"], res.get("reason")
    for key in ("path_length_rad", "mean_perception_score", "build_s", "query_ms", "n_nodes", "n_edges", "waypoints"):
        assert key in res
    assert res["n_nodes"] == 400 and len(res["waypoints"][0]) == len(res["joint_names"]) == 8
    assert plot.stat().st_size > 20000


def test_plan_unknown_target_is_a_clear_error(capsys):
    assert main(["plan", "--scene", "home", "--target", "unicorn"]) == 2
    assert "unicorn" in capsys.readouterr().err


def test_perf_planner_json(capsys):
    assert main(["perf", "planner", "--scene", "cup_table", "--nodes", "300", "--queries", "3", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("build_s", "query_ms", "query_p95_ms", "success_rate", "n_nodes", "n_edges"):
        assert key in res
    assert res["n_nodes"] == 300 and res["queries"] == 3


def test_perf_preprocess_oracle_vs_neural(capsys):
    """Both scorers build a roadmap with every edge scored; each build scores its nodes once and the N = 5 interior
    samples of every kept edge (edge ends reuse the node scores), and the oracle (render + real detector) costs
    far more per view than the surrogate with ray casting."""
    assert main(["perf", "preprocess", "--scene", "home", "--target", "tv", "--nodes", "120", "--oracle-nodes", "6",
                 "--threads", "1", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["neural_views"] == res["neural_nodes"] + 5 * res["neural_edges"]
    assert res["small_oracle_views"] == res["small_oracle_nodes"] + 5 * res["small_edges"]
    assert res["oracle_s_per_view"] > 100 * res["neural_s_per_view"]
    assert res["ratio_measured_small"] > 1 and res["oracle_build_s_extrapolated"] > res["neural_build_s"]


def test_perf_transfer_scores_roadmap_nodes_with_both(capsys, tmp_path):
    """perf transfer scores the same roadmap nodes with the neural scorer and the oracle. Judged from its per-view
    record: the test re-scores every reported camera pose with the surrogate and some with its own oracle, recomputes
    the correlations and the distance bins, and finds the shipped surrogate ranking the views like the detector; a
    second checkpoint (the shipped one with its tv and potted plant classes swapped) is scored on the same views."""
    import numpy as np
    import torch
    from scipy.stats import spearmanr

    from psprm_core.paths import resolve_named
    from psprm_core.perception.oracle import Oracle
    from psprm_core.perception.scoring import NeuralScorer
    from psprm_core.perception.surrogate import load_surrogate
    from psprm_core.planning.factory import default_checkpoint
    from psprm_core.robot import RobotModel
    from psprm_core.scene import load_scene

    ck = str(default_checkpoint())
    swapped = load_surrogate(ck)
    i, j = swapped.classes.index("tv"), swapped.classes.index("potted plant")
    swapped.classes[i], swapped.classes[j] = swapped.classes[j], swapped.classes[i]
    other = str(swapped.save(tmp_path / "swapped.pt"))
    t0 = time.perf_counter()
    assert main(["perf", "transfer", "--scene", "home", "--target", "tv", "--nodes", "80", "--samples", "12",
                 "--threads", "1", "--checkpoints", other, "--json"]) == 0
    wall = time.perf_counter() - t0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    views = res["views"]
    cams = torch.as_tensor(views["camera_poses"], dtype=torch.float64)
    oracle_scores, neural = np.asarray(views["oracle"]), np.asarray(views["neural"])
    assert res["samples"] == res["n"] == len(cams) == 12
    scene = load_scene(resolve_named("scene", "home"))
    robot = RobotModel.load(scene.robot)
    # the views are the line-manifold roadmap's: proper camera frames with the tv on the optical axis, in front
    # (the test's own pinhole geometry on the reported poses)
    T = cams.numpy()
    assert np.allclose(np.einsum("nij,nkj->nik", T[:, :3, :3], T[:, :3, :3]), np.eye(3), atol=1e-5)
    assert np.allclose(np.linalg.det(T[:, :3, :3]), 1.0, atol=1e-5) and np.allclose(T[:, 3], [0, 0, 0, 1])
    pc = np.einsum("nji,nj->ni", T[:, :3, :3], scene.target("tv").center - T[:, :3, 3])
    assert (pc[:, 2] > 0.3).all() and (np.hypot(pc[:, 0], pc[:, 1]) < 0.05 * pc[:, 2]).all(), pc
    mine = NeuralScorer(load_surrogate(ck), scene, "tv").score(cams).double().numpy()
    np.testing.assert_allclose(neural, mine, atol=1e-6)
    with Oracle(scene, intrinsics=robot.config.intrinsics) as oracle:  # every view, re-scored by the test's oracle
        seen = np.array([oracle.score(T[k], "tv", keep_image=False).score for k in range(len(T))])
    np.testing.assert_allclose(oracle_scores, seen, atol=1e-6)
    assert seen.std() > 0 and mine.std() > 0  # precondition: both rankings are informative
    own = spearmanr(mine, seen).statistic  # from the test's own scores of the views
    assert res["spearman"] == pytest.approx(own, abs=1e-9)
    assert res["neural_mean"] == pytest.approx(mine.mean()) and res["oracle_mean"] == pytest.approx(seen.mean())
    assert own >= 0.5  # the shipped surrogate ranks the planner's views like the detector
    dist = np.linalg.norm(cams[:, :3, 3].numpy() - scene.target("tv").center, axis=1)
    for b in res["by_distance"]:
        hi = np.inf if b["to_m"] is None else b["to_m"]
        assert b["n"] == int(((dist >= b["from_m"]) & (dist < hi)).sum())
    assert 12 * 0.02 <= res["oracle_s"] <= wall  # twelve renders and detector passes, within the command's time
    # the swapped checkpoint: its own predictions on the same views, correlated with the same oracle scores
    again = res["checkpoints"][other]
    theirs = NeuralScorer(load_surrogate(other), scene, "tv").score(cams).double().numpy()
    np.testing.assert_allclose(again["neural"], theirs, atol=1e-6)
    assert not np.allclose(theirs, neural, atol=1e-3)
    assert again["spearman"] == pytest.approx(spearmanr(theirs, seen).statistic, abs=1e-9)
