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
