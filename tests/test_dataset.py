"""Perception dataset: pose sampling inside the field of view, resumable parallel labelling, viewpoint splits."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from psprm_core.camera import CameraIntrinsics
from psprm_core.perception.dataset import (
    OracleFactory,
    SamplingConfig,
    build_dataset,
    generate_samples,
    load_dataset,
    sample_camera_poses,
    split_by_viewpoint,
    split_dataset,
    target_in_fov,
    view_parameters,
    viewpoint_cells,
)
from psprm_core.scene import Target

from synthetic_targets import CUP, FACE, AnalyticScorer  # noqa: E402


class AnalyticScorerFactory:
    """Picklable factory: each worker builds its own scorer."""

    description = "analytic test scorer (distance + facing)"

    def __init__(self, targets):
        self.targets = list(targets)

    def __call__(self) -> AnalyticScorer:
        return AnalyticScorer(self.targets)


class ResultScorerFactory:
    """Returns result objects with a ``score`` attribute, like the oracle's ``OracleResult``."""

    def __call__(self):
        class Result:
            def __init__(self, score):
                self.score = score

        return lambda pose, name: Result(0.25)


class FailingFactory:
    def __call__(self):
        return lambda pose, name: 1 / 0


@pytest.mark.parametrize("target", [FACE, CUP])
def test_sampled_poses_see_the_target(target):
    cfg = SamplingConfig(intrinsics=CameraIntrinsics())
    poses, prm = sample_camera_poses(target, 3000, cfg, np.random.default_rng(3))
    assert poses.shape == (3000, 4, 4)
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(rot), 1.0)
    assert target_in_fov(poses, target.center, cfg.intrinsics).all()
    # the centroid lands on the drawn pixel, which covers the image (not only its centre)
    rel = np.einsum("nji,nj->ni", rot, target.center - poses[:, :3, 3])
    px = cfg.intrinsics.project(rel)
    assert np.allclose(px, np.stack([prm["u"], prm["v"]], 1), atol=1e-6)
    assert px[:, 0].min() < 60 and px[:, 0].max() > 580 and px[:, 1].min() < 45 and px[:, 1].max() > 435
    dist = np.linalg.norm(poses[:, :3, 3] - target.center, axis=1)
    assert np.allclose(dist, prm["distance"]) and dist.min() >= 0.4 and dist.max() <= 4.0
    assert poses[:, 2, 3].min() >= 0.3 - 1e-12 and poses[:, 2, 3].max() <= 1.6 + 1e-12
    # all around the target, including behind it
    to_cam = poses[:, :3, 3] - target.center
    facing_cos = (to_cam @ target.facing) / dist
    assert facing_cos.min() < -0.9 and facing_cos.max() > 0.9
    # roll stays within the configured jitter: without jitter the image x axis is horizontal, y points down
    flat, prm0 = sample_camera_poses(target, 500, SamplingConfig(roll_deg=0.0), np.random.default_rng(4))
    assert np.abs(flat[:, 2, 0]).max() < 1e-9 and (flat[:, 2, 1] < 0).all()
    assert target_in_fov(flat, target.center, cfg.intrinsics).all()
    assert np.abs(np.degrees(prm["roll"])).max() <= 5.0


def test_sampling_is_seeded_and_validated():
    a = generate_samples([FACE, CUP], 101, SamplingConfig(), seed=5)
    b = generate_samples([FACE, CUP], 101, SamplingConfig(), seed=5)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert np.bincount(a["target_index"]).tolist() == [51, 50]
    with pytest.raises(ValueError):
        sample_camera_poses(FACE, 5, SamplingConfig(distance=(0.1, 2.0)), np.random.default_rng(0))
    high = Target(name="high", detector_class="cup", center=np.array([0.0, 0.0, 9.0]), size=np.ones(3))
    with pytest.raises(ValueError, match="cannot be seen"):
        sample_camera_poses(high, 5, SamplingConfig(), np.random.default_rng(0))


def _arrays(ds):
    return [ds.camera_poses, ds.target_index, ds.scores] + [ds.params[k] for k in sorted(ds.params)]


def test_resume_matches_one_shot(tmp_path):
    targets = [FACE, CUP]
    factory = AnalyticScorerFactory(targets)
    kw = dict(targets=targets, scorer_factory=factory, n_samples=130, chunk_size=25, seed=11, progress=False)
    one = build_dataset(tmp_path / "one", workers=0, **kw)
    part = tmp_path / "resumed"
    build_dataset(part, workers=0, max_chunks=2, **kw)  # "interrupted" after two chunks
    meta = json.loads((part / "metadata.json").read_text())
    assert meta["chunks_done"] == 2 and not meta["complete"]
    with pytest.raises(ValueError, match="incomplete"):
        load_dataset(part)
    assert len(load_dataset(part, allow_incomplete=True)) == 50
    build_dataset(part, workers=2, **kw)  # resumed with two worker processes
    a, b = load_dataset(one), load_dataset(part)
    assert len(a) == 130
    for x, y in zip(_arrays(a), _arrays(b)):
        assert np.array_equal(x, y)
    assert a.content_hash() == b.content_hash()
    meta = json.loads((part / "metadata.json").read_text())
    assert meta["complete"] and meta["classes"] == ["cup", "face"] and meta["seed"] == 11
    assert meta["counts"]["per_target"] == {"alice": 65, "cup1": 65}
    assert meta["scorer"] == factory.description
    assert meta["sampling"]["distance"] == [0.4, 4.0]
    # scores are the scorer's
    ref = AnalyticScorer(targets)
    names = a.target_names
    assert np.allclose(a.scores, [ref.score(p, n) for p, n in zip(a.camera_poses, names)])

    # a corrupt chunk is relabelled; a changed configuration is refused
    (one / "chunk_00001.npz").write_bytes(b"garbage")
    build_dataset(one, workers=0, **kw)
    assert np.array_equal(load_dataset(one).scores, a.scores)
    with pytest.raises(ValueError, match="different configuration"):
        build_dataset(one, workers=0, **{**kw, "seed": 12})


def test_result_objects_and_oracle_factory(tmp_path):
    build_dataset(tmp_path / "r", [CUP], ResultScorerFactory(), n_samples=7, chunk_size=5, workers=0, progress=False)
    assert load_dataset(tmp_path / "r").scores.tolist() == [0.25] * 7
    f = OracleFactory("config/scenes/x.yaml", {"detectors": None})
    assert "x.yaml" in f.description and pickle.loads(pickle.dumps(f)) == f


def test_worker_errors_are_reported(tmp_path):
    with pytest.raises(RuntimeError, match="ZeroDivisionError"):
        build_dataset(tmp_path / "bad", [CUP], FailingFactory(), n_samples=10, chunk_size=5, workers=1, progress=False)


def test_split_by_viewpoint_has_no_leakage():
    s = generate_samples([FACE, CUP], 4000, SamplingConfig(), seed=1)
    splits = split_by_viewpoint(s["azimuth"], s["distance"], (0.7, 0.15, 0.15), seed=3, distance_range=(0.4, 4.0))
    idx = np.concatenate(list(splits.values()))
    assert np.array_equal(np.sort(idx), np.arange(4000))  # disjoint and complete
    cells = viewpoint_cells(s["azimuth"], s["distance"], distance_range=(0.4, 4.0))
    owner = {}
    for name, ix in splits.items():
        for c in np.unique(cells[ix]):
            assert owner.setdefault(int(c), name) == name  # every cell belongs to one split only
    sizes = {k: len(v) / 4000 for k, v in splits.items()}
    assert abs(sizes["train"] - 0.7) < 0.05 and abs(sizes["val"] - 0.15) < 0.05 and abs(sizes["test"] - 0.15) < 0.05
    # deterministic
    again = split_by_viewpoint(s["azimuth"], s["distance"], (0.7, 0.15, 0.15), seed=3, distance_range=(0.4, 4.0))
    assert all(np.array_equal(splits[k], again[k]) for k in splits)


def test_split_dataset_on_loaded_data(tmp_path):
    build_dataset(tmp_path / "d", [CUP], AnalyticScorerFactory([CUP]), n_samples=300, chunk_size=100, workers=0,
                  progress=False)
    ds = load_dataset(tmp_path / "d")
    sp = split_dataset(ds)
    assert sum(len(v) for v in sp.values()) == 300
    sub = ds.subset(sp["test"])
    assert len(sub) == len(sp["test"]) and sub.target_poses.shape == (len(sub), 4, 4)
    assert sub.class_index.tolist() == [0] * len(sub)


def test_view_parameters_recover_the_samplers_draws():
    cfg = SamplingConfig(intrinsics=CameraIntrinsics())
    s = generate_samples([FACE, CUP], 500, cfg, seed=4)
    prm = view_parameters(s["camera_poses"], s["target_index"], [FACE, CUP], cfg.intrinsics)
    for k in ("distance", "azimuth", "height", "u", "v"):
        err = np.abs(prm[k] - s[k])
        if k == "azimuth":
            err = np.abs(np.angle(np.exp(1j * (prm[k] - s[k]))))
        assert err.max() < 1e-6, (k, err.max())
    # the sampler rolls about the line of sight by up to 5 degrees; the recovered roll is that tilt of the x axis
    assert np.abs(prm["roll"]).max() <= np.radians(5.0) + 1e-9
    assert np.corrcoef(prm["roll"], s["roll"])[0, 1] > 0.9


def test_given_views_are_labelled_resumed_and_split(tmp_path):
    targets = [FACE, CUP]
    s = generate_samples(targets, 120, SamplingConfig(), seed=5)
    s = {k: v[::-1].copy() for k, v in s.items()}  # any order and mix of targets
    s["origin"] = np.arange(120, dtype=np.int8) % 2
    source = {"source": "test views", "distance": [0.4, 4.0]}
    kw = dict(targets=targets, scorer_factory=AnalyticScorerFactory(targets), chunk_size=50, seed=0, progress=False,
              samples=s, source=source)
    build_dataset(tmp_path / "g", workers=0, max_chunks=1, **kw)
    build_dataset(tmp_path / "g", workers=0, **kw)  # resumed: only the two missing chunks are labelled
    ds = load_dataset(tmp_path / "g")
    meta = json.loads((tmp_path / "g" / "metadata.json").read_text())
    assert meta["complete"] and meta["n_samples"] == 120 and meta["sampling"] == source
    assert sum(meta["counts"]["per_target"].values()) == 120
    assert meta["counts"]["per_target"]["alice"] == int((s["target_index"] == 0).sum())
    assert np.allclose(ds.camera_poses, s["camera_poses"]) and np.array_equal(ds.target_index, s["target_index"])
    ref = AnalyticScorer(targets)
    assert np.allclose(ds.scores, [ref.score(p, n) for p, n in zip(ds.camera_poses, ds.target_names)])
    assert sum(len(v) for v in split_dataset(ds).values()) == 120
    with pytest.raises(ValueError, match="different configuration"):
        build_dataset(tmp_path / "g", workers=0, **{**kw, "source": {"source": "other views"}})
