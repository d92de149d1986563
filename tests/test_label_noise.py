"""``psprm perf label-noise``: the camera-pose change (its size measured by the test from the poses, the target kept
in the image by the test's own pinhole projection), the retest statistics on synthetic labels with a known answer
(hand-computed ranks; a noise model whose ceiling is known), the labelling oracle rebuilt from each shipped dataset's
metadata (intrinsics equal to the scene robot's own), and the command judged from its per-view record re-scored by
the test's own oracle."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import spearmanr

from psprm_core.cli import main
from psprm_core.errors import InputError
from psprm_core.evaluation.label_noise import labelling_oracle_factory, perturb_poses, retest_statistics
from psprm_core.perception.dataset import load_dataset, split_dataset

STUDIO = "psprm_core/data/surrogate_dataset"


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Rotation angle between rotation matrices (trace formula)."""
    c = (np.einsum("nij,nij->n", Ra, Rb) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def _pixels(poses: np.ndarray, point: np.ndarray, width=640, height=480, vfov_deg=42.5) -> np.ndarray:
    """The test's own pinhole projection of a scene point into optical-frame cameras (+z forward, +y down)."""
    rel = np.einsum("nji,nj->ni", poses[:, :3, :3], point - poses[:, :3, 3])
    f = (height / 2) / math.tan(math.radians(vfov_deg) / 2)
    return np.stack([f * rel[:, 0] / rel[:, 2] + width / 2, f * rel[:, 1] / rel[:, 2] + height / 2], 1), rel[:, 2]


def test_perturbation_has_the_requested_size_in_random_directions_and_keeps_the_target_in_view():
    ds = load_dataset(STUDIO)
    idx = np.random.default_rng(1).choice(len(ds), 400, replace=False)
    poses = ds.camera_poses[idx]
    moved = perturb_poses(poses, translation=0.01, rotation_deg=0.5, seed=3)
    shift = moved[:, :3, 3] - poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), 0.01, rtol=1e-9)
    np.testing.assert_allclose(_angle_deg(moved[:, :3, :3], poses[:, :3, :3]), 0.5, atol=1e-5)
    R = moved[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(moved[:, 3], poses[:, 3])
    # random directions: every axis moved both ways, no common direction
    assert np.all((shift > 0).mean(0) > 0.35) and np.all((shift < 0).mean(0) > 0.35)
    assert np.linalg.norm((shift / 0.01).mean(0)) < 0.15
    # fixed seed: the same change again, another seed another one
    np.testing.assert_array_equal(perturb_poses(poses, 0.01, 0.5, seed=3), moved)
    assert not np.allclose(perturb_poses(poses, 0.01, 0.5, seed=4), moved)
    # the target stays in the image, and its image moves by a few pixels only
    for ti, t in enumerate(ds.targets):
        sel = ds.target_index[idx] == ti
        assert sel.sum() >= 50
        before, _ = _pixels(poses[sel], t.center)
        after, z = _pixels(moved[sel], t.center)
        assert np.all((before >= 0) & (before <= [640, 480]))  # precondition: in view before the change
        assert np.all((after >= 0) & (after <= [640, 480])) and np.all(z > 0.3), t.name
        # 0.5 deg is 5.7 px at this focal length; 1 cm sideways at >= 0.4 m at most 15 px more
        assert np.max(np.linalg.norm(after - before, axis=1)) < 22.0
        assert np.median(np.linalg.norm(after - before, axis=1)) > 1.0


def test_retest_statistics_on_hand_computed_ranks():
    y = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    r = np.array([0.2, 0.1, 0.3, 0.4, 0.5])  # two neighbours swapped: sum d^2 = 2
    st = retest_statistics(y, r, 0.15, {"same": y, "reversed": y[::-1]})
    rho = 1 - 6 * 2 / (5 * 24)
    assert st["n"] == 5 and st["positive_rate"] == pytest.approx(0.8)
    assert st["retest"]["spearman"] == pytest.approx(rho)
    assert st["retest"]["rmse"] == pytest.approx(math.sqrt(0.02 / 5))
    assert st["retest"]["noise_rmse"] == pytest.approx(math.sqrt(0.02 / 5) / math.sqrt(2))
    assert st["retest"]["ceiling_spearman"] == pytest.approx(math.sqrt(rho))
    # at 0.15 the flags are y: F T T T T, retest: T F T T T -> tp 3, fp 1, fn 1
    assert st["retest"]["f1"] == pytest.approx(0.75) and st["retest"]["flag_flips"] == pytest.approx(0.4)
    assert st["same"]["spearman"] == pytest.approx(1.0) and st["same"]["rmse"] == 0.0 and st["same"]["f1"] == 1.0
    assert st["reversed"]["spearman"] == pytest.approx(-1.0)
    assert st["zero_fraction"] == 0.0
    assert retest_statistics([0.0, 0.0, 0.3], [0.0, 0.2, 0.3], 0.1)["zero_fraction"] == pytest.approx(2 / 3)


def test_ceilings_match_a_noise_model_with_a_known_answer():
    """Labels = a score plus noise independent between the labellings: the score itself correlates with a label at
    about sqrt(retest correlation) and misses it by the noise's standard deviation = retest RMSE / sqrt 2."""
    rng = np.random.default_rng(0)
    n, sigma = 200_000, 0.1
    f = rng.uniform(0.0, 0.4, n)  # variance 0.04 / 3
    y, r = f + rng.normal(0, sigma, n), f + rng.normal(0, sigma, n)
    st = retest_statistics(y, r, 0.2, {"score": f})
    r_true = (0.16 / 12) / (0.16 / 12 + sigma ** 2)  # var f / (var f + sigma^2)
    assert st["retest"]["spearman"] == pytest.approx(r_true, abs=0.02)
    assert st["retest"]["ceiling_spearman"] == pytest.approx(st["score"]["spearman"], abs=0.01)
    assert st["retest"]["noise_rmse"] == pytest.approx(sigma, rel=0.01)
    assert st["score"]["rmse"] == pytest.approx(sigma, rel=0.01)
    assert st["score"]["spearman"] > st["retest"]["spearman"] + 0.1  # the ceiling lies above the retest figure


def test_labelling_oracle_rebuilt_from_each_shipped_dataset(load_robot):
    from psprm_core.camera import CameraIntrinsics
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene

    for d in (STUDIO, "psprm_core/data/scene_views/home", "psprm_core/data/scene_views/cup_table",
              "psprm_core/data/scene_views/nursing", "psprm_core/data/scene_views/blind_spot_alley"):
        meta = json.loads((Path(d) / "metadata.json").read_text())
        f = labelling_oracle_factory(meta["scorer"])
        if meta["sampling"].get("source") == "roadmap":  # views of a robot's roadmap: that robot's camera
            scene = load_scene(resolve_named("scene", meta["sampling"]["scene"]))
            assert f.oracle_kwargs["intrinsics"] == load_robot(scene.robot).config.intrinsics, d
            assert f.scene_path.endswith(f"{meta['sampling']['scene']}.yaml")
        else:  # the studio's views: the sampler's intrinsics, the oracle's default
            assert f.oracle_kwargs == {} and CameraIntrinsics() == CameraIntrinsics(**meta["sampling"]["intrinsics"])
    for bad in ("", "Scorer(x)", "Oracle(scene=a.yaml, {'detectors': None})",
                "Oracle(scene=a.yaml, {'intrinsics': CameraIntrinsics(width=1)}, x)"):
        with pytest.raises(InputError):
            labelling_oracle_factory(bad)


def test_command_judged_from_its_record_by_the_tests_own_oracle(capsys, tmp_path):
    from psprm_core.paths import resolve_named
    from psprm_core.perception.oracle import Oracle
    from psprm_core.scene import load_scene

    out = tmp_path / "record.json"
    assert main(["perf", "label-noise", "--dataset", STUDIO, "--per-class", "2", "--seed", "5", "--json",
                 "--out", str(out)]) == 0
    res = json.loads(capsys.readouterr().out)  # stdout is the JSON object only
    rec = json.loads(out.read_text())
    v = rec["views"]
    assert "views" not in res and res["per_class"] == rec["per_class"]
    ds = load_dataset(STUDIO)
    idx = np.asarray(v["index"])
    assert set(idx) <= set(split_dataset(ds)["test"])  # held-out views (the checkpoint's split settings: defaults)
    assert sorted(v["class"]) == ["cup", "cup", "face", "face", "potted plant", "potted plant", "tv", "tv"]
    np.testing.assert_array_equal(v["original"], ds.scores[idx])
    moved = np.asarray(v["perturbed_poses"])
    np.testing.assert_allclose(np.linalg.norm(moved[:, :3, 3] - ds.camera_poses[idx, :3, 3], axis=1), 0.01)
    np.testing.assert_allclose(_angle_deg(moved[:, :3, :3], ds.camera_poses[idx, :3, :3]), 0.5, atol=1e-5)
    with Oracle(load_scene(resolve_named("scene", "surrogate_studio"))) as oracle:
        for k, i in enumerate(idx):
            name = ds.targets[ds.target_index[i]].name
            assert oracle.score(moved[k], name, keep_image=False).score == pytest.approx(v["retest"][k], abs=1e-6)
            assert oracle.score(ds.camera_poses[i], name, keep_image=False).score == pytest.approx(
                v["relabelled"][k], abs=1e-6)
    y, r = np.asarray(v["original"]), np.asarray(v["retest"])
    assert res["per_class"]["pooled"]["retest"]["rmse"] == pytest.approx(np.sqrt(np.mean((y - r) ** 2)))
    assert np.ptp(y) > 0 and np.ptp(r) > 0  # precondition of a rank correlation
    assert res["per_class"]["pooled"]["retest"]["spearman"] == pytest.approx(spearmanr(y, r).statistic)
    assert res["thresholds"] == {"cup": 0.10, "face": 0.34, "potted plant": 0.10, "tv": 0.23}
    # the record judged again without the oracle, with a second checkpoint (the shipped one, tv and plant swapped)
    import torch

    from psprm_core.perception.surrogate import load_surrogate, target_pose_matrix

    swapped = load_surrogate("psprm_core/data/surrogate.pt")
    i, j = swapped.classes.index("tv"), swapped.classes.index("potted plant")
    swapped.classes[i], swapped.classes[j] = swapped.classes[j], swapped.classes[i]
    other = str(swapped.save(tmp_path / "swapped.pt"))
    assert main(["perf", "label-noise", "--dataset", STUDIO, "--record", str(out), "--checkpoints", other,
                 "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["labels_from_record"] and again["oracle_s"] == res["oracle_s"]
    assert again["per_class"]["pooled"]["retest"] == res["per_class"]["pooled"]["retest"]
    mine = np.array([swapped.predict(torch.as_tensor(ds.camera_poses[i:i + 1]),
                                     torch.as_tensor(target_pose_matrix(ds.targets[ds.target_index[i]])),
                                     ds.targets[ds.target_index[i]].detector_class).item() for i in idx])
    tv = np.asarray(v["class"]) == "tv"
    assert again["per_class"]["tv"][other]["rmse"] == pytest.approx(np.sqrt(np.mean((mine[tv] - y[tv]) ** 2)))
    assert again["per_class"]["pooled"][other]["spearman"] == pytest.approx(spearmanr(mine, y).statistic)
    assert not np.allclose(mine, v["surrogate"], atol=1e-3)
