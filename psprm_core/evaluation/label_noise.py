"""Test-retest reliability of the oracle's labels (``psprm perf label-noise``): how much of a label's ranking a
camera-pose change far below what a planner or the surrogate resolves leaves intact.

Held-out test views of the surrogate's dataset (the split ``psprm eval-surrogate`` evaluates on) are drawn per
class; each view's camera is moved by a tiny pose change (:func:`perturb_poses`: a fixed translation length and
rotation angle, in random directions) and scored again by the oracle that labelled the view's source (same scene,
target, renderer, detector and intrinsics, rebuilt from the source's metadata by :func:`labelling_oracle_factory`).
:func:`retest_statistics` compares the perturbed labels with the originals (Spearman, RMSE, F1 of the perturbed
"detected" flag against the original's at the detector's calibrated threshold) and the surrogate with the originals
on the same views, per class and pooled.

If the label is the noise-free score of the pose plus noise independent between the two labellings (variance
:math:`\\sigma^2`), the retest correlation is :math:`r = \\mathrm{var} f / (\\mathrm{var} f + \\sigma^2)`; a perfect
predictor of the noise-free score correlates with a label at :math:`\\sqrt r` and misses it by an RMSE of
:math:`\\sigma` = retest RMSE / :math:`\\sqrt 2`. Those two ceilings are reported beside the raw retest figures
(``ceiling_spearman``, ``noise_rmse``; for a rank correlation the square root is an approximation).
"""

from __future__ import annotations

import ast
import logging
import math
import re
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..camera import CameraIntrinsics
from ..errors import InputError
from ..paths import project_root
from ..perception.dataset import OracleFactory, load_dataset
from ..perception.dataset_sampling import target_in_fov
from ..perception.detectors import default_detector_name, make_detector
from ..perception.metrics import perception_metrics
from ..perception.oracle import Oracle
from ..perception.surrogate import load_surrogate, target_pose_matrix
from ..perception.training import TrainConfig, _splits, pool_datasets
from ..scene import load_scene

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------------------
# Pure parts
# ------------------------------------------------------------------------------------------------------------------
def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    while np.any(norm < 1e-12):  # practically never; keeps the direction well defined
        bad = norm[:, 0] < 1e-12
        v[bad] = rng.normal(size=(int(bad.sum()), 3))
        norm = np.linalg.norm(v, axis=1, keepdims=True)
    return v / norm


def _axis_angle_matrices(axes: np.ndarray, angle: float) -> np.ndarray:
    """(n, 3, 3) rotations by ``angle`` (rad) about unit ``axes`` (n, 3) (Rodrigues)."""
    k = np.zeros((len(axes), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = axes[:, 2], -axes[:, 1], axes[:, 0]
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def perturb_poses(poses: np.ndarray, translation: float = 0.01, rotation_deg: float = 0.5,
                  seed: int = 0) -> np.ndarray:
    """Each camera pose moved by exactly ``translation`` metres in a random direction and turned by exactly
    ``rotation_deg`` degrees about a random axis through the camera centre (directions and axes uniform on the
    sphere, independent per pose, from ``numpy.random.default_rng(seed)``).

    Parameters
    ----------
    poses : (n, 4, 4) array_like
        Optical-frame camera poses in the scene frame.

    Returns
    -------
    (n, 4, 4) ndarray
        The moved poses (rotation part still orthonormal).
    """
    p = np.array(poses, dtype=float, copy=True)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise InputError(f"poses must be (n, 4, 4), got {p.shape}")
    rng = np.random.default_rng(seed)
    n = len(p)
    shift = _unit_vectors(rng, n) * float(translation)
    turn = _axis_angle_matrices(_unit_vectors(rng, n), math.radians(float(rotation_deg)))
    p[:, :3, :3] = turn @ p[:, :3, :3]
    p[:, :3, 3] = p[:, :3, 3] + shift
    return p


def retest_statistics(original, retest, thresholds, predictions: Optional[dict] = None) -> dict:
    """Agreement of a relabelling with the original labels, and of predictors with the original labels.

    Parameters
    ----------
    original, retest : (n,) array_like
        The labels and the labels of the perturbed views.
    thresholds : float or (n,) array_like
        The "detected" threshold of each view (the detector's calibrated one).
    predictions : dict of (n,) array_like, optional
        Predictors' scores of the original views (e.g. ``{"surrogate": ...}``), judged against ``original``.

    Returns
    -------
    dict
        ``n``, ``positive_rate`` and ``zero_fraction`` of the original labels; ``retest``: Spearman, RMSE, MAE and F1
        of the perturbed labels against the originals (:func:`~psprm_core.perception.metrics.perception_metrics`
        with the retest as the prediction), the share of views whose "detected" flag flips, and the ceilings of the
        module docstring (``ceiling_spearman`` = sqrt(retest Spearman), ``noise_rmse`` = retest RMSE / sqrt 2);
        one entry per predictor with its Spearman, RMSE, MAE and F1 against the originals.
    """
    y = np.asarray(original, float).ravel()
    r = np.asarray(retest, float).ravel()
    thr = np.broadcast_to(np.asarray(thresholds, float), y.shape)
    keep = ("n", "spearman", "rmse", "mae", "f1", "precision", "recall")
    m = perception_metrics(r, y, thr)
    rho = m["spearman"]
    out = {"n": int(y.size), "positive_rate": m["positive_rate"],
           "zero_fraction": float(np.mean(y == 0.0)) if y.size else float("nan"),
           "retest": {**{k: m[k] for k in keep},
                      "flag_flips": float(np.mean((y >= thr) != (r >= thr))) if y.size else float("nan"),
                      "ceiling_spearman": float(math.sqrt(rho)) if math.isfinite(rho) and rho >= 0 else float("nan"),
                      "noise_rmse": m["rmse"] / math.sqrt(2.0)}}
    for name, pred in (predictions or {}).items():
        pm = perception_metrics(np.asarray(pred, float).ravel(), y, thr)
        out[name] = {k: pm[k] for k in keep}
    return out


def per_class_statistics(classes: Sequence[str], original, retest, thresholds,
                         predictions: Optional[dict] = None) -> dict:
    """:func:`retest_statistics` per class (``classes``: each view's class) and over all views (``pooled``)."""
    cls = np.asarray(classes, dtype=object)
    thr = np.broadcast_to(np.asarray(thresholds, float), cls.shape)
    y, r = np.asarray(original, float), np.asarray(retest, float)
    preds = {k: np.asarray(v, float) for k, v in (predictions or {}).items()}
    out = {}
    for c in sorted(set(cls.tolist())):
        sel = cls == c
        out[c] = retest_statistics(y[sel], r[sel], thr[sel], {k: v[sel] for k, v in preds.items()})
    out["pooled"] = retest_statistics(y, r, thr, preds)
    return out


# ------------------------------------------------------------------------------------------------------------------
# The labelling oracle of a dataset
# ------------------------------------------------------------------------------------------------------------------
_INTRINSICS = re.compile(r"CameraIntrinsics\(([^)]*)\)")


def labelling_oracle_factory(scorer: str):
    """The :class:`~psprm_core.perception.dataset.OracleFactory` whose description a dataset's metadata records as
    its ``scorer`` (``psprm dataset`` writes ``Oracle(scene=...)`` or ``Oracle(scene=..., {'intrinsics':
    CameraIntrinsics(...)})``); the rebuilt factory describes itself exactly as recorded, or this raises."""
    desc = str(scorer or "")
    m = re.fullmatch(r"Oracle\(scene=([^,)]+)(?:, (.*))?\)", desc.strip())
    if not m:
        raise InputError(f"the dataset's scorer {desc!r} is not a rendering oracle written by psprm dataset")
    kwargs = {}
    if m.group(2):
        im = _INTRINSICS.search(m.group(2))
        if not im or m.group(2) != "{'intrinsics': " + im.group(0) + "}":
            raise InputError(f"cannot rebuild the oracle's options {m.group(2)!r} (only intrinsics are known)")
        fields = {}
        for part in im.group(1).split(","):
            key, _, value = part.strip().partition("=")
            fields[key] = ast.literal_eval(value)
        kwargs["intrinsics"] = CameraIntrinsics(**fields)
    factory = OracleFactory(m.group(1), kwargs)
    if factory.description != desc:
        raise InputError(f"rebuilt oracle {factory.description!r} differs from the dataset's scorer {desc!r}")
    return factory


def _build_oracle(factory, detectors: dict):
    """The factory's oracle with the given detectors ({class: Detector}; the same models, sized to our threads)."""
    path = Path(factory.scene_path)
    if not path.is_absolute() and not path.is_file():
        path = project_root() / path
    return Oracle(load_scene(path), detectors, **factory.oracle_kwargs)


# ------------------------------------------------------------------------------------------------------------------
# The measurement
# ------------------------------------------------------------------------------------------------------------------
def _relabel(full, parts: list, chosen: np.ndarray, poses: np.ndarray, moved: np.ndarray, source: np.ndarray,
             classes: np.ndarray, reproduce: bool, threads: int) -> dict:
    """Oracle labels of the moved views (and of the unmoved ones with ``reproduce``), each by the oracle of its
    source, with the built-in detectors on ``threads`` threads."""
    n = len(chosen)
    retest, again, thr = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    left_view, out_before = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    detectors = {}
    t0 = time.perf_counter()
    for s, part in enumerate(parts):
        rows = np.flatnonzero(source == s)
        if not len(rows):
            continue
        factory = labelling_oracle_factory(part.get("scorer", ""))
        by_class = {}
        for c in sorted(set(classes[rows].tolist())):
            name = default_detector_name(c)
            if name not in detectors:  # the built-in detector of the class, on our threads
                detectors[name] = make_detector(name, threads=max(1, int(threads)))
            by_class[c] = detectors[name]
        oracle = _build_oracle(factory, by_class)
        try:
            for k in rows:
                target = full.targets[full.target_index[int(chosen[k])]]
                st = oracle.scene.target(target.name)
                if not (np.allclose(st.center, target.center, atol=1e-9)
                        and np.allclose(np.abs(np.dot(st.quat, target.quat)), 1.0, atol=1e-9)):
                    raise InputError(f"target {target.name} of {part['dir']} is not where the scene "
                                     f"{factory.scene_path} puts it")
                res = oracle.score(moved[k], target.name, keep_image=False)
                retest[k], thr[k] = res.score, res.threshold
                if reproduce:
                    again[k] = oracle.score(poses[k], target.name, keep_image=False).score
                out_before[k] = not target_in_fov(poses[k:k + 1], target.center, oracle.intrinsics)[0]
                left_view[k] = not out_before[k] and not target_in_fov(moved[k:k + 1], target.center,
                                                                        oracle.intrinsics)[0]
        finally:
            oracle.close()
    return {"retest": retest, "threshold": thr, "relabelled": again if reproduce else None,
            "target_left_view": int(left_view.sum()), "target_out_of_view_before": int(out_before.sum()),
            "oracle_s": time.perf_counter() - t0}


def select_test_views(classes: np.ndarray, per_class: int, seed: int = 0) -> np.ndarray:
    """Up to ``per_class`` positions of each class in ``classes`` (drawn without replacement with
    ``default_rng(seed)``, classes in sorted order), sorted."""
    rng = np.random.default_rng(seed)
    cls = np.asarray(classes, dtype=object)
    picks = []
    for c in sorted(set(cls.tolist())):
        idx = np.flatnonzero(cls == c)
        picks.append(np.sort(rng.choice(idx, min(int(per_class), len(idx)), replace=False)))
    return np.sort(np.concatenate(picks)) if picks else np.zeros(0, dtype=np.int64)


def label_noise(checkpoint: str, dataset: str, per_class: int = 200, translation: float = 0.01,
                rotation_deg: float = 0.5, seed: int = 0, threads: int = 1, checkpoints: Sequence[str] = (),
                reproduce: bool = True, allow_incomplete: bool = False,
                distance_bins: Sequence[float] = (0.0, 1.5, 3.0, math.inf), record: Optional[dict] = None) -> dict:
    """Test-retest reliability of the oracle labels of the surrogate's held-out test views (module docstring).

    Parameters
    ----------
    checkpoint : str
        The surrogate whose test split is used (its training settings define the split, as in ``eval-surrogate``)
        and which is compared with the labels.
    dataset : str
        Dataset directories, comma-separated (as the checkpoint was trained on).
    per_class : int
        Test views drawn per class.
    translation, rotation_deg : float
        The pose change: metres and degrees, each exactly this large, in random directions.
    seed : int
        Seeds the choice of views and the perturbation.
    threads : int
        Threads of the detectors (onnxruntime) and of torch.
    checkpoints : sequence of str
        Further surrogates judged on the same views against the same labels.
    reproduce : bool
        Also relabel the unperturbed views: how exactly this oracle reproduces the stored labels.
    distance_bins : sequence of float
        Camera-to-target distance bins (metres) of ``by_distance``.
    record : dict, optional
        The full result of an earlier run (with ``views``): its views and oracle labels are judged again (e.g. with
        other checkpoints) without the oracle; its settings replace ``per_class``, the pose change and ``seed``.

    Returns
    -------
    dict
        Settings, ``per_class`` (each class and ``pooled``: :func:`retest_statistics` with the surrogate, and the
        further checkpoints, as predictors), ``by_distance`` / ``by_source`` (the same per distance bin / per
        source dataset), ``reproduction`` (with ``reproduce``), ``target_left_view`` (views whose target centroid
        the change moved out of the image; ``target_out_of_view_before``: out of it already, as some roadmap views
        are), ``oracle_s``, and ``views`` (the per-view record).
    """
    import torch

    old_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        model = load_surrogate(checkpoint)
        dirs = [d for d in dataset.split(",") if d]
        full = pool_datasets([load_dataset(d, allow_incomplete=allow_incomplete) for d in dirs])
        test_idx = _splits(full, TrainConfig.from_dict(model.metadata.get("training", {})))["test"]
        parts = full.metadata.get("pooled") or [{"dir": full.path, "start": 0, "stop": len(full),
                                                 "scorer": full.metadata.get("scorer", "")}]
        if record is None:
            view_class = np.array([full.targets[full.target_index[i]].detector_class for i in test_idx],
                                  dtype=object)
            chosen = test_idx[select_test_views(view_class, per_class, seed)]
            poses = full.camera_poses[chosen]
            moved = perturb_poses(poses, translation, rotation_deg, seed)
        else:  # the views and labels of an earlier run
            chosen = np.asarray(record["views"]["index"], dtype=np.int64)
            if not set(chosen.tolist()) <= set(test_idx.tolist()):
                raise InputError("the record's views are not all in this checkpoint's test split")
            if not np.array_equal(np.asarray(record["views"]["original"], float), full.scores[chosen]):
                raise InputError("the record's labels are not this dataset's")
            translation, rotation_deg = record["translation_m"], record["rotation_deg"]
            seed, per_class = record["seed"], record["per_class_requested"]
            poses = full.camera_poses[chosen]
            moved = np.asarray(record["views"]["perturbed_poses"], float)
        classes = np.array([full.targets[full.target_index[i]].detector_class for i in chosen], dtype=object)
        source = np.searchsorted([p["stop"] for p in parts], chosen, side="right")
        original = full.scores[chosen].astype(float)
        if record is None:
            lab = _relabel(full, parts, chosen, poses, moved, source, classes, reproduce, threads)
        else:
            v = record["views"]
            lab = {"retest": np.asarray(v["retest"], float), "threshold": np.asarray(v["threshold"], float),
                   "relabelled": None if v.get("relabelled") is None else np.asarray(v["relabelled"], float),
                   **{k: record[k] for k in ("target_left_view", "target_out_of_view_before", "oracle_s")}}
        retest, thr, again = lab["retest"], lab["threshold"], lab["relabelled"]

        def predict(m) -> np.ndarray:
            out = np.zeros(len(chosen))
            for ti in sorted(set(full.target_index[chosen].tolist())):
                sel = full.target_index[chosen] == ti
                t = full.targets[ti]
                out[sel] = m.predict(torch.as_tensor(poses[sel]), torch.as_tensor(target_pose_matrix(t)),
                                     t.detector_class).double().numpy()
            return out

        preds = {"surrogate": predict(model)}
        for ck in checkpoints:
            preds[str(ck)] = predict(load_surrogate(ck))
        stats = per_class_statistics(classes, original, retest, thr, preds)
        dist = np.linalg.norm(poses[:, :3, 3] - np.stack([full.targets[full.target_index[i]].center
                                                          for i in chosen]), axis=1)
        by_distance = []
        for lo, hi in zip(distance_bins[:-1], distance_bins[1:]):
            sel = (dist >= lo) & (dist < hi)
            by_distance.append({"from_m": float(lo), "to_m": float(hi) if math.isfinite(hi) else None,
                                **per_class_statistics(classes[sel], original[sel], retest[sel], thr[sel],
                                                       {k: v[sel] for k, v in preds.items()})})
        by_source = {}
        for si, part in enumerate(parts):
            sel = source == si
            if sel.any():
                by_source[part["dir"]] = per_class_statistics(classes[sel], original[sel], retest[sel], thr[sel],
                                                              {k: v[sel] for k, v in preds.items()})
        result = {"checkpoint": str(checkpoint), "dataset": dataset, "translation_m": float(translation),
                  "rotation_deg": float(rotation_deg), "seed": int(seed), "per_class_requested": int(per_class),
                  "test_views": int(len(test_idx)), "views_relabelled": int(len(chosen)),
                  "thresholds": {c: float(thr[classes == c][0]) for c in sorted(set(classes.tolist()))},
                  "per_class": stats, "by_distance": by_distance, "by_source": by_source,
                  "target_left_view": lab["target_left_view"],
                  "target_out_of_view_before": lab["target_out_of_view_before"], "oracle_s": lab["oracle_s"],
                  "labels_from_record": record is not None,
                  "per_source": {parts[s]["dir"]: int(np.sum(source == s)) for s in range(len(parts))
                                 if np.any(source == s)}}
        if again is not None:
            diff = np.abs(again - original)
            result["reproduction"] = {"max_abs_diff": float(diff.max()) if len(diff) else float("nan"),
                                      "identical_fraction": float(np.mean(diff == 0.0)) if len(diff) else float("nan"),
                                      "per_class": per_class_statistics(classes, original, again, thr)}
        result["views"] = {"index": chosen.tolist(), "class": classes.tolist(), "original": original.tolist(),
                           "retest": retest.tolist(), "relabelled": None if again is None else again.tolist(),
                           "threshold": thr.tolist(), "surrogate": preds["surrogate"].tolist(),
                           "distance": dist.tolist(), "perturbed_poses": moved.tolist()}
        for ck in checkpoints:
            result["views"][str(ck)] = preds[str(ck)].tolist()
        return result
    finally:
        torch.set_num_threads(old_threads)
