"""Neural perception surrogate: features, model I/O, training on an analytic scorer, the loss options and class
weights against closed-form optima, metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from psprm_core.geometry import make_transform
from psprm_core.perception.dataset import build_dataset, load_dataset
from psprm_core.perception.occlusion import OcclusionChecker
from psprm_core.perception.surrogate import (
    PerceptionSurrogate,
    derived_features,
    load_surrogate,
    perception_scores,
    pose_features,
    relative_pose_features,
    target_pose_matrix,
)
from psprm_core.perception.training import (
    TrainConfig,
    evals_per_s,
    evaluate_surrogate,
    occlusion_metrics,
    perception_metrics,
    train_surrogate,
)
from psprm_core.scene import Box, Scene

from synthetic_targets import CUP, FACE, AnalyticScorer  # noqa: E402


class Factory:
    description = "analytic"

    def __init__(self, targets):
        self.targets = targets

    def __call__(self):
        return AnalyticScorer(self.targets)


def _random_poses(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.linalg.det(q))[:, None, None]
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, :3, :3] = q
    poses[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2
    return poses


def test_relative_pose_features_match_matrix_algebra():
    cams = _random_poses(50)
    tp = target_pose_matrix(FACE)
    f = relative_pose_features(cams, tp)
    assert f.shape == (50, 9) and f.dtype == torch.float64
    rel = np.linalg.inv(cams.numpy()) @ tp
    assert np.allclose(f[:, :3].numpy(), rel[:, :3, 3])
    assert np.allclose(f[:, 3:6].numpy(), rel[:, :3, 0]) and np.allclose(f[:, 6:9].numpy(), rel[:, :3, 1])
    # per-sample target poses give the same answer
    f2 = relative_pose_features(cams, torch.as_tensor(tp).repeat(50, 1, 1))
    assert torch.allclose(f, f2)
    # derived features: a camera 2 m in front of the face, looking at it
    z = -FACE.facing
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    cam = make_transform(np.stack([x, np.cross(z, x), z], 1), FACE.center + 2 * FACE.facing)
    d = derived_features(relative_pose_features(cam, tp))[0]
    assert d.tolist() == pytest.approx([2.0, 1.0, 1.0, 0.0, 0.0], abs=1e-9)
    assert pose_features(cams, tp).shape == (50, 14) and pose_features(cams, tp, derived=False).shape == (50, 9)


def test_architecture_shapes_and_device_following():
    m = PerceptionSurrogate(["cup", "face"])
    linears = [l for l in m.net if isinstance(l, torch.nn.Linear)]
    assert [l.out_features for l in linears] == [256] * 5 + [1]
    assert linears[0].in_features == 14 + 2
    assert PerceptionSurrogate(["cup"], derived=False).net[0].in_features == 10
    cams = _random_poses(37)
    for inp in (cams, cams.float(), cams.numpy()):
        out = m.predict(inp, target_pose_matrix(CUP), "cup")
        assert out.shape == (37,) and out.dtype == torch.float32 and out.device.type == "cpu"
        assert ((out >= 0) & (out <= 1)).all()
    m.fit_normalization(pose_features(cams, target_pose_matrix(CUP)).float() * 2 + 0.5)
    out = m.predict(cams, target_pose_matrix(CUP), "cup")
    assert torch.allclose(out, m.predict(cams, target_pose_matrix(CUP), "cup", chunk_size=5))
    # the folded inference path equals the plain forward pass
    ref = m(pose_features(cams, target_pose_matrix(CUP)).float(), torch.zeros(37, dtype=torch.long))
    assert torch.allclose(out, ref, atol=1e-6)
    ref_face = m(pose_features(cams, target_pose_matrix(CUP)).float(), 1)
    mixed = m.predict(cams, target_pose_matrix(CUP), ["cup", "face"] * 18 + ["cup"])
    assert torch.allclose(mixed[0::2], out[0::2], atol=1e-6) and torch.allclose(mixed[1::2], ref_face[1::2], atol=1e-6)
    per_row = m.predict(cams, target_pose_matrix(CUP), ["cup"] * 37)
    assert torch.allclose(out, per_row)
    assert torch.allclose(out, m.predict(cams, target_pose_matrix(CUP), 0))
    with pytest.raises(KeyError, match="not trained on class 'tv'"):
        m.predict(cams, target_pose_matrix(CUP), "tv")
    out[0] = 0.0  # no_grad, not inference mode: results are ordinary tensors
    if torch.cuda.is_available():  # pragma: no cover - CPU-only CI
        mc = m.to("cuda")
        oc = mc.predict(cams.cuda(), torch.as_tensor(target_pose_matrix(CUP)).cuda(), "cup")
        assert oc.device.type == "cuda"


def test_normalisation_round_trip():
    m = PerceptionSurrogate(["cup"])
    feats = pose_features(_random_poses(500), target_pose_matrix(CUP)).float() * 3 + 1
    m.fit_normalization(feats)
    z = m.normalize(feats)
    assert torch.allclose(z.mean(0), torch.zeros(14), atol=1e-4)
    assert torch.allclose(z.std(0), torch.ones(14), atol=1e-3)
    assert torch.allclose(m.denormalize(z), feats, atol=1e-4)
    assert "feature_mean" in m.state_dict() and "feature_std" in m.state_dict()


def test_save_load_identical_outputs(tmp_path):
    torch.manual_seed(0)
    m = PerceptionSurrogate(["cup", "face"], metadata={"note": "x"})
    m.fit_normalization(pose_features(_random_poses(300), target_pose_matrix(FACE)).float())
    path = m.save(tmp_path / "s.pt", dataset_hash="abc", metrics={"rmse": np.float64(0.1)},
                  training=TrainConfig(epochs=3).to_dict())
    ckpt = torch.load(path, weights_only=True)  # plain content only
    assert ckpt["metadata"]["metrics"]["rmse"] == 0.1 and ckpt["config"]["classes"] == ["cup", "face"]
    assert len(ckpt["metadata"]["normalization"]["mean"]) == 14
    m2 = load_surrogate(path)
    cams = _random_poses(100, seed=3)
    tp = target_pose_matrix(FACE)
    assert torch.equal(m.predict(cams, tp, "face"), m2.predict(cams, tp, "face"))
    assert m2.classes == ["cup", "face"] and m2.metadata["dataset_hash"] == "abc" and m2.metadata["note"] == "x"
    assert torch.equal(m2.feature_std, m.feature_std)


def test_training_on_analytic_scorer(tmp_path):
    targets = [FACE, CUP]
    build_dataset(tmp_path / "ds", targets, Factory(targets), n_samples=4000, chunk_size=1000, seed=2, workers=0,
                  progress=False)
    # faster than the paper's lr 1e-4 / 200 epochs so that the test takes seconds; one thread because OpenMP with
    # 2 threads degrades badly when other processes share the 2 cores
    cfg = TrainConfig(epochs=20, lr=2e-3, batch_size=256, patience=8, seed=0, threads=1, max_seconds=30)
    model, report = train_surrogate(tmp_path / "ds", tmp_path / "model.pt", cfg, progress=False)
    test = report["metrics"]["test"]
    assert test["n"] > 200
    assert test["rmse"] < 0.06, report["metrics"]
    assert test["spearman"] > 0.9, report["metrics"]
    assert report["history"]["best_epoch"] >= 0
    assert model.metadata["dataset_hash"] == report["dataset_hash"] == load_dataset(tmp_path / "ds").content_hash()
    # evaluating the saved checkpoint reproduces the test metrics (same split settings from the metadata)
    ev = evaluate_surrogate(tmp_path / "model.pt", tmp_path / "ds", split="test")
    assert ev["metrics"]["rmse"] == pytest.approx(test["rmse"], rel=1e-5)
    # a scene with a wall in front of the cup: ray casting finds an occluded subset, zeroing helps there
    wall = Box(name="wall", center=CUP.center + np.array([0.6, 0.0, 0.0]),
               size=np.array([0.05, 4.0, 4.0]))
    scene = Scene(name="s", robot="r", frame="map", workspace=np.array([[-5, 5], [-5, 5]]), obstacles=(wall,),
                  targets=tuple(targets))
    ev = evaluate_surrogate(model, tmp_path / "ds", split="all", scene=scene)
    occ = ev["occlusion"]
    # the independent record: the samples whose camera-to-target segment crosses the wall (a slab test on the
    # dataset's own poses)
    ds = load_dataset(tmp_path / "ds")
    cam = ds.camera_poses[:, :3, 3]
    tgt = np.stack([t.center for t in ds.targets])[ds.target_index]
    lo, hi = wall.center - wall.size / 2, wall.center + wall.size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - cam) / (tgt - cam), (hi - cam) / (tgt - cam)
    enter = np.nanmax(np.minimum(t0, t1), axis=1)
    leave = np.nanmin(np.maximum(t0, t1), axis=1)
    behind = (enter <= leave) & (leave >= 0) & (enter <= 1)
    assert 0.05 < behind.mean() < 0.95
    assert abs(occ["n_occluded"] - behind.sum()) <= 0.02 * len(ds) and occ["n"] == len(ds)
    # the analytic labels ignore the wall: zeroing there gives exactly minus the mean label, and the raw error is the
    # model's own prediction error on those views (predicted here from the same poses)
    pred = model.predict(ds.camera_poses, ds.target_poses, [ds.targets[i].detector_class for i in ds.target_index])
    pred = pred.double().numpy()
    assert occ["occluded_mean_error_zeroed"] == pytest.approx(-ds.scores[behind].mean(), abs=0.02)
    assert occ["occluded_mean_error_raw"] == pytest.approx((pred - ds.scores)[behind].mean(), abs=0.02)
    assert occ["occluded_mean_error_zeroed"] < -0.1  # the views behind the wall are well seen by the labels
    # zeroed, no view behind the wall is called detected although the labels call some so
    assert occ["occluded_zeroed"]["positive_rate"] == pytest.approx((ds.scores[behind] >= 0.75).mean(), abs=0.02)
    assert occ["occluded_zeroed"]["positive_rate"] > 0 and occ["occluded_zeroed"]["recall"] == 0.0
    assert occ["occluded_raw"]["recall"] > 0.5


def test_metrics_on_hand_made_arrays():
    pred = [0.9, 0.8, 0.2, 0.76, 0.1]
    label = [1.0, 0.5, 0.1, 0.8, 0.9]
    m = perception_metrics(pred, label, threshold=0.75)
    err = np.array(pred) - np.array(label)
    assert m["n"] == 5
    assert m["rmse"] == pytest.approx(np.sqrt(np.mean(err ** 2)))
    assert m["mae"] == pytest.approx(np.mean(np.abs(err)))
    assert m["spearman"] == pytest.approx(0.3)  # 1 - 6 * 14 / (5 * 24)
    assert m["accuracy"] == pytest.approx(3 / 5)  # tp=2 (0, 3), fp=1 (1), fn=1 (4), tn=1 (2)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(2 / 3)
    assert m["f1"] == pytest.approx(2 / 3)
    assert all(isinstance(v, (int, float)) for v in m.values())
    # threshold is inclusive; degenerate cases
    m = perception_metrics([0.75, 0.1], [0.75, 0.2])
    assert m["precision"] == 1.0 and m["recall"] == 1.0 and m["accuracy"] == 1.0
    m = perception_metrics([0.1, 0.2], [0.1, 0.1])
    assert m["precision"] == 0.0 and m["recall"] == 0.0 and m["f1"] == 0.0 and math.isnan(m["spearman"])
    assert perception_metrics([], [])["n"] == 0


def test_occlusion_metrics():
    pred = np.array([0.9, 0.8, 0.7, 0.9])
    label = np.array([0.0, 0.1, 0.7, 0.9])
    occ = np.array([True, True, False, False])
    out = occlusion_metrics(pred, label, occ, raycast_occluded=np.array([True, False, False, False]))
    assert out["n_occluded"] == 2 and out["fraction_occluded"] == 0.5
    assert out["occluded_raw"]["mae"] == pytest.approx(0.8)
    assert out["occluded_zeroed"]["mae"] == pytest.approx((0.0 + 0.7) / 2)
    assert out["occluded_mean_error_raw"] == pytest.approx(0.8)
    assert out["raycast_agreement"] == 0.75
    assert out["all_zeroed"]["mae"] == pytest.approx(0.7 / 4)


def test_throughput_benchmark_runs():
    assert evals_per_s(batch=2048, repeats=1) > 1000
    assert evals_per_s(batch=2048, repeats=1, include_features=False) > 1000


def test_alg2_zeroes_occluded_cameras():
    m = PerceptionSurrogate(["cup"])
    wall = Box(name="wall", center=CUP.center + np.array([1.0, 0.0, 0.0]), size=np.array([0.05, 0.5, 0.5]))
    scene = Scene(name="s", robot="r", frame="map", workspace=np.array([[-5, 5], [-5, 5]]), obstacles=(wall,),
                  targets=(CUP,))
    cams = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    cams[0, :3, 3] = torch.as_tensor(CUP.center + [2.0, 0.0, 0.0])  # behind the wall
    cams[1, :3, 3] = torch.as_tensor(CUP.center + [-2.0, 0.0, 0.0])  # free view
    raw = m.predict(cams, CUP, "cup")  # a Target is accepted as the target pose
    out = perception_scores(m, cams, CUP, "cup", OcclusionChecker.from_scene(scene, "cup1"))
    assert out[0].item() == 0.0 and out[1].item() == raw[1].item() > 0
    assert torch.equal(perception_scores(m, cams, CUP, "cup"), raw)


def test_pooled_datasets_are_split_per_source(tmp_path):
    """Studio views plus views of a second source whose target of the same name stands elsewhere (a scene's
    roadmap views): each source keeps its own target poses and viewpoint split; metrics are reported per source."""
    import dataclasses

    from psprm_core.perception.dataset import SamplingConfig, generate_samples, view_parameters
    from psprm_core.perception.training import _splits, pool_datasets

    build_dataset(tmp_path / "a", [FACE, CUP], Factory([FACE, CUP]), n_samples=2000, chunk_size=1000, seed=2,
                  workers=0, progress=False)
    moved = dataclasses.replace(CUP, center=CUP.center + np.array([3.0, -2.0, 0.1]))
    s = generate_samples([moved], 1000, SamplingConfig(distance=(0.4, 6.0), camera_height=(0.3, 1.2)), seed=3)
    s.update(view_parameters(s["camera_poses"], s["target_index"], [moved], SamplingConfig().intrinsics))
    build_dataset(tmp_path / "b", [moved], Factory([moved]), chunk_size=500, workers=0, progress=False, samples=s,
                  source={"source": "moved cup", "distance": [0.4, 6.0]})
    pooled = pool_datasets([tmp_path / "a", tmp_path / "b"])
    assert len(pooled) == 3000 and pooled.classes == ["cup", "face"] and len(pooled.targets) == 3
    assert np.allclose(pooled.target_poses[2500][:3, 3], moved.center)  # second source: its own cup pose
    cfg = TrainConfig(epochs=15, lr=2e-3, batch_size=256, patience=8, seed=0, threads=1, max_seconds=20)
    sp = _splits(pooled, cfg)
    idx = np.concatenate(list(sp.values()))
    assert np.array_equal(np.sort(idx), np.arange(3000))
    for k in sp:  # both sources contribute to every split
        assert (sp[k] < 2000).any() and (sp[k] >= 2000).any(), k
    model, report = train_surrogate([tmp_path / "a", tmp_path / "b"], None, cfg, progress=False)
    by_src = report["metrics"]["test_by_source"]
    assert set(by_src) == {str(tmp_path / "a"), str(tmp_path / "b")}
    assert sum(m["n"] for m in by_src.values()) == report["metrics"]["test"]["n"]
    assert by_src[str(tmp_path / "b")]["spearman"] > 0.9, by_src


def _uninformative(n: int = 4000, seed: int = 0):
    """Features that carry no information (noise) and labels drawn independently of them: a trained model can only
    learn each class's optimal constant, which each loss defines in closed form."""
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn(n, len(PerceptionSurrogate(["a"]).feature_names), generator=g)
    cls = (torch.arange(n) % 2).long()  # class 0 "a", class 1 "b"
    y = torch.where(torch.rand(n, generator=g) < 0.5, 0.0, 0.5)  # half 0, half 0.5
    y = torch.where(cls == 1, 0.1, y)  # class "b": always 0.1
    return feats, cls, y


@pytest.mark.parametrize("loss, optimum", [
    ("bce", 0.25),  # the mean label
    ("log-mse", math.sqrt(0.05 * 0.55) - 0.05),  # exp(mean log(y + c)) - c, c = 0.05: 0.116
])
def test_loss_options_reach_their_closed_form_optimum(loss, optimum):
    from psprm_core.perception.training import fit_surrogate

    feats, cls, y = _uninformative()
    cfg = TrainConfig(epochs=40, lr=3e-3, batch_size=500, loss=loss, patience=None, seed=0, threads=1, hidden=16,
                      layers=2, weight_decay=1e-2)
    model, _ = fit_surrogate((feats, cls, y), None, ["a", "b"], cfg)
    pred = model.predict_features(feats, cls).double().numpy()
    assert pred[cls.numpy() == 0].mean() == pytest.approx(optimum, abs=0.03)
    assert pred[cls.numpy() == 1].mean() == pytest.approx(0.1, abs=0.03)


def test_class_weights_scale_each_class_loss():
    from psprm_core.errors import InputError
    from psprm_core.perception.training import fit_surrogate

    feats, cls, y = _uninformative()

    def class_b_mean(weights):
        cfg = TrainConfig(epochs=15, lr=3e-3, batch_size=500, patience=None, seed=0, threads=1, hidden=16, layers=2,
                          class_weights=weights)
        model, _ = fit_surrogate((feats, cls, y), None, ["a", "b"], cfg)
        return float(model.predict_features(feats, cls).double().numpy()[cls.numpy() == 1].mean())

    assert class_b_mean({"b": 1.0}) == pytest.approx(0.1, abs=0.03)
    assert abs(class_b_mean({"b": 1e-6}) - 0.1) > 0.07  # class "b" barely trained: far from its label (0.22)
    for bad in ({"c": 2.0}, {"b": 0.0}):
        with pytest.raises(InputError):
            fit_surrogate((feats, cls, y), None, ["a", "b"], TrainConfig(epochs=1, class_weights=bad))
