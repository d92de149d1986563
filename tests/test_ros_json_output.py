"""``--json`` commands print one valid JSON object on stdout and nothing else (strict parsing: no NaN, no library
warnings before the object): the perf benchmarks whose pybullet / numpy output used to precede or break it, and the
ROS tools' self-checks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def strict(text: str) -> dict:
    def no_constants(c):
        raise ValueError(f"non-JSON constant {c}")
    return json.loads(text, parse_constant=no_constants)


def _run(args, timeout=300):
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    r = subprocess.run(args, capture_output=True, text=True, timeout=timeout, cwd=str(ROOT), env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_perf_kinematics_json_is_the_only_stdout():
    out = _run([sys.executable, "-m", "psprm_core.cli", "perf", "kinematics", "--robot", "stretch2", "--scene",
                "home", "--n", "64", "--json"])
    d = strict(out)  # the whole of stdout is one object (pybullet's URDF warnings went to stderr)
    assert d["n"] == 64 if "n" in d else len(d) > 3


def test_perf_transfer_json_has_no_nan():
    out = _run([sys.executable, "-m", "psprm_core.cli", "perf", "transfer", "--scene", "home", "--target", "tv",
                "--samples", "6", "--nodes", "150", "--json"])
    d = strict(out)
    assert "spearman" in d


@pytest.mark.parametrize("module", ["psprm_ros.all_in_one", "psprm_ros.robot_adapter", "psprm_ros.sim_robot",
                                    "psprm_ros.harness.latency_bench", "psprm_ros.mocap_replay"])
def test_ros_executables_self_check_prints_json(module):
    d = strict(_run([sys.executable, "-m", module, "--self-check"], timeout=120))
    assert d["ok"]
