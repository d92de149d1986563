"""The ``psprm`` command line: help, the kinematics benchmark's JSON, the demo, and one-line errors."""

from __future__ import annotations

import json

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


def test_perf_transfer_scores_roadmap_nodes_with_both(capsys):
    """perf transfer scores the same roadmap nodes with the neural scorer and the oracle: the distance bins partition
    the samples, correlations are proper numbers, and the oracle's time is measured."""
    from psprm_core.planning.factory import default_checkpoint

    ck = str(default_checkpoint())
    assert main(["perf", "transfer", "--scene", "home", "--target", "tv", "--nodes", "80", "--samples", "12",
                 "--threads", "1", "--checkpoints", ck, "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["samples"] == res["n"] == 12 and sum(b["n"] for b in res["by_distance"]) == 12
    assert -1.0 <= res["spearman"] <= 1.0 and 0.0 <= res["neural_mean"] <= 1.0 and 0.0 <= res["oracle_mean"] <= 1.0
    assert res["oracle_s"] > 0 and res["by_distance"][-1]["to_m"] is None
    # a further checkpoint is scored on the same views against the same labels: the planner's own one agrees exactly
    again = res["checkpoints"][ck]
    assert again["neural_mean"] == res["neural_mean"] and again["spearman"] == res["spearman"]
    assert [b["n"] for b in again["by_distance"]] == [b["n"] for b in res["by_distance"]]

