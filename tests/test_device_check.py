"""The device check (scripts/check_device.sh) on this CPU with the compiled kernels off: the torch code a GPU runs
builds and queries a roadmap whose path pybullet finds collision-free, its FK agrees with pybullet's and its
collision flags miss none of pybullet's collisions."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_torch_path_passes_the_device_check_judged_by_pybullet():
    from psprm_core.device_check import run

    out = run("cpu", torch_path=True, configs=600, nodes=300)
    assert out["torch_path"] and out["missed_collisions"] == 0
    assert out["fk_max_position_error_m"] < 1e-3 and out["fk_max_rotation_error_rad"] < 1e-3
    assert out["plan_success"] and out["path_collisions_pybullet"] == 0 and out["path_goal_error"] < 1e-3
    assert out["ok"]


def test_check_device_script_reports_an_unavailable_device_with_status_2():
    import pytest
    import torch

    if torch.cuda.is_available():  # pragma: no cover - a CUDA machine runs the real check instead
        pytest.skip("CUDA is available here: scripts/check_device.sh runs the real check")
    r = subprocess.run(["bash", str(ROOT / "scripts" / "check_device.sh"), "cuda"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2
    assert json.loads(r.stdout.strip().splitlines()[-1])["ok"] is False
