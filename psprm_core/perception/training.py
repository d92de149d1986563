"""Training, evaluation and benchmarking of the neural perception surrogate.

Training follows the paper (Sec. "Neural Surrogate Perception Score Models" / experimental set-up): Adam, learning
rate 1e-4, batch size 512, 200 epochs; we add early stopping on the validation RMSE (patience configurable) and keep
the best weights.

Loss: ``"bce"`` (default) is the binary cross-entropy between the predicted score and the *soft* label
:math:`y \\in [0, 1]` (``BCEWithLogitsLoss`` on the pre-sigmoid output). Like the MSE it is minimised by
:math:`\\hat y = y`, but its gradient w.r.t. the logit, :math:`\\hat y - y`, does not vanish when the sigmoid
saturates, which matters because detector confidences pile up near 0 and near 1. ``"mse"`` is available too, and
``"log-mse"``, the squared error of :math:`\\log(\\hat y + c)` against :math:`\\log(y + c)` (``log_offset`` c): training
on the logarithm of the confidence, which weighs an error on a small label by about :math:`1 / (y + c)^2` instead of
BCE's :math:`1 / (y (1 - y))`, while the network still outputs the confidence itself. ``class_weights`` scales the
loss of each class's samples.

Evaluation (:func:`perception_metrics`) reports what the paper's Table "benchmark-results" reports: RMSE, MAE,
Spearman's rho, and accuracy/precision/recall/F1 of the binary decision ``score >= threshold`` (threshold 0.75 in
the paper) applied to both prediction and label. :func:`occlusion_metrics` evaluates an occluded subset with and
without zeroing by ray casting (Alg. 2, lines 5-7).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch
from torch import nn

from .dataset import PerceptionDataset, load_dataset, split_dataset
from .metrics import DEFAULT_THRESHOLD, occlusion_metrics, perception_metrics
from .occlusion import OcclusionChecker
from .surrogate import PerceptionSurrogate, pose_features
from ..errors import InputError

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Surrogate training settings (paper defaults: Adam, lr 1e-4, batch 512, 200 epochs).

    Attributes
    ----------
    epochs, lr, batch_size : int, float, int
    loss : {"bce", "mse", "log-mse"}
        See the module docstring.
    log_offset : float
        ``c`` of the ``"log-mse"`` loss (default: the detectors' reporting floor, 0.05).
    class_weights : dict
        ``{class: weight}``: each sample's loss is multiplied by its class's weight (absent classes: 1), and each
        batch's loss divided by the sum of its weights.
    patience : int or None
        Stop after this many epochs without a validation-RMSE improvement larger than ``min_delta``
        (``None``: never stop early). The best weights are restored at the end.
    min_delta : float
    weight_decay : float
        Adam weight decay (0 in the paper).
    schedule : {"constant", "cosine"}
        Learning rate over the epochs: ``lr`` throughout (the paper), or cosine-annealed from ``lr`` to 1 % of it
        at the last epoch.
    seed : int
        Seeds the weight initialisation and the batch order.
    derived_features, hidden, layers
        Model options (see :class:`~psprm_core.perception.surrogate.PerceptionSurrogate`).
    split_fractions, n_azimuth_cells, n_distance_cells, split_seed
        Train/val/test split by viewpoint (see :func:`~psprm_core.perception.dataset.split_by_viewpoint`).
    threshold : float
        Score threshold for the classification metrics.
    threads : int or None
        ``torch.set_num_threads`` during training (``None``: leave as is).
    device : str
        Training device (``"cpu"``, ``"cuda"``, ...).
    max_seconds : float or None
        Wall-clock budget; training stops after the epoch that exceeds it.
    """

    epochs: int = 200
    lr: float = 1e-4
    batch_size: int = 512
    loss: str = "bce"
    log_offset: float = 0.05
    class_weights: dict = dataclasses.field(default_factory=dict)
    patience: Optional[int] = 20
    min_delta: float = 1e-5
    weight_decay: float = 0.0
    schedule: str = "constant"
    seed: int = 0
    derived_features: bool = True
    hidden: int = 256
    layers: int = 5
    split_fractions: tuple = (0.8, 0.1, 0.1)
    n_azimuth_cells: int = 24
    n_distance_cells: int = 6
    split_seed: int = 0
    threshold: float = DEFAULT_THRESHOLD
    threads: Optional[int] = None
    device: str = "cpu"
    max_seconds: Optional[float] = None

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["split_fractions"] = [float(v) for v in self.split_fractions]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in d.items() if k in known}
        if "split_fractions" in kw:
            kw["split_fractions"] = tuple(kw["split_fractions"])
        return cls(**kw)


# ------------------------------------------------------------------------------------------------------------------
# Training
# ------------------------------------------------------------------------------------------------------------------
def dataset_tensors(ds: PerceptionDataset, derived: bool = True) -> tuple:
    """Un-normalised pose features (N, F) float32, class indices (N,) long and labels (N,) float32 of a dataset."""
    feats = pose_features(ds.camera_poses, ds.target_poses, derived).float()
    cls = torch.as_tensor(ds.class_index, dtype=torch.long)
    y = torch.as_tensor(ds.scores, dtype=torch.float32)
    return feats, cls, y


@torch.no_grad()
def _predict_features(model: PerceptionSurrogate, feats: torch.Tensor, cls: torch.Tensor,
                      chunk: int = 8192) -> torch.Tensor:
    model.eval()
    if not feats.shape[0]:
        return torch.zeros(0)
    return model.predict_features(feats, cls, chunk_size=chunk).cpu()


def fit_surrogate(train: tuple, val: Optional[tuple], classes: Sequence[str], config: Optional[TrainConfig] = None,
                  progress: bool = False, metadata: Optional[dict] = None) -> tuple:
    """Train a :class:`PerceptionSurrogate` on feature tensors.

    Parameters
    ----------
    train, val : (features (N, F), class_idx (N,), labels (N,)) tuples
        As returned by :func:`dataset_tensors`; ``val`` may be ``None`` (no early stopping then).
    classes : sequence of str
        Class names (the one-hot order of ``class_idx``).
    config : TrainConfig
    progress : bool
        Show a tqdm bar over epochs.

    Returns
    -------
    model : PerceptionSurrogate
        With the best validation weights (or the last ones without ``val``), in eval mode, on ``config.device``.
    history : dict
        ``train_loss``, ``val_rmse`` per epoch, ``best_epoch``, ``epochs_run``, ``seconds``, ``stopped_early``.
    """
    cfg = config or TrainConfig()
    if cfg.loss not in ("bce", "mse", "log-mse"):
        raise InputError(f"loss must be 'bce', 'mse' or 'log-mse', got {cfg.loss!r}")
    unknown = sorted(set(cfg.class_weights) - set(classes))
    if unknown:
        raise InputError(f"class weights for classes not in the data: {unknown} (classes: {list(classes)})")
    if any(not float(w) > 0 for w in cfg.class_weights.values()):
        raise InputError(f"class weights must be positive, got {cfg.class_weights}")
    if cfg.loss == "log-mse" and not cfg.log_offset > 0:
        raise InputError(f"log_offset must be positive, got {cfg.log_offset}")
    old_threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    try:
        torch.manual_seed(cfg.seed)
        gen = torch.Generator().manual_seed(cfg.seed)
        device = torch.device(cfg.device)
        xf, xc, y = train
        model = PerceptionSurrogate(classes, derived=cfg.derived_features, hidden=cfg.hidden, layers=cfg.layers,
                                    metadata=metadata)
        if xf.shape[1] != model.n_pose_features:
            raise InputError(f"features have {xf.shape[1]} columns, model expects {model.n_pose_features}")
        model.fit_normalization(xf)
        model.to(device)
        xf, xc, y = xf.to(device), xc.to(device), y.to(device)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        if cfg.schedule not in ("constant", "cosine"):
            raise InputError(f"unknown learning-rate schedule '{cfg.schedule}' (constant, cosine)")
        sched = (torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.epochs), eta_min=0.01 * cfg.lr)
                 if cfg.schedule == "cosine" else None)
        class_w = torch.tensor([float(cfg.class_weights.get(c, 1.0)) for c in classes], device=device)
        weighted = bool(cfg.class_weights)

        def batch_loss(logits: torch.Tensor, target: torch.Tensor, cls_idx: torch.Tensor) -> torch.Tensor:
            if cfg.loss == "bce":
                if not weighted:  # the mean reduction of BCEWithLogitsLoss, as the shipped checkpoint was trained
                    return nn.functional.binary_cross_entropy_with_logits(logits, target)
                per = nn.functional.binary_cross_entropy_with_logits(logits, target, reduction="none")
            elif cfg.loss == "mse":
                per = (torch.sigmoid(logits) - target) ** 2
            else:
                per = (torch.log(torch.sigmoid(logits) + cfg.log_offset) - torch.log(target + cfg.log_offset)) ** 2
            if not weighted:
                return per.mean()
            w = class_w[cls_idx]
            return (w * per).sum() / w.sum()
        n = xf.shape[0]
        hist = {"train_loss": [], "val_rmse": [], "best_epoch": -1, "epochs_run": 0, "stopped_early": False}
        best, best_state, since_best = math.inf, None, 0
        t0 = time.perf_counter()
        epochs = range(cfg.epochs)
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(epochs, desc="training", unit="epoch", dynamic_ncols=True)
            epochs = bar
        for epoch in epochs:
            model.train()
            perm = torch.randperm(n, generator=gen).to(device)
            total = 0.0
            for s in range(0, n, cfg.batch_size):
                idx = perm[s:s + cfg.batch_size]
                logits = model.forward_logits(xf[idx], xc[idx])
                loss = batch_loss(logits, y[idx], xc[idx])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.detach().item() * idx.shape[0]
            hist["train_loss"].append(total / max(n, 1))
            hist["epochs_run"] = epoch + 1
            if sched is not None:
                sched.step()
            if val is not None and val[0].shape[0]:
                vp = _predict_features(model, val[0], val[1])
                rmse = float(torch.sqrt(torch.mean((vp - val[2].cpu()) ** 2)))
                hist["val_rmse"].append(rmse)
                if rmse < best - cfg.min_delta:
                    best, since_best, hist["best_epoch"] = rmse, 0, epoch
                    best_state = copy.deepcopy(model.state_dict())
                else:
                    since_best += 1
                if bar is not None:
                    bar.set_postfix(loss=f"{hist['train_loss'][-1]:.4f}", val_rmse=f"{rmse:.4f}")
                if cfg.patience is not None and since_best > cfg.patience:
                    hist["stopped_early"] = True
                    log.info("early stopping after epoch %d (best val RMSE %.4f at epoch %d)", epoch, best,
                             hist["best_epoch"])
                    break
            if cfg.max_seconds is not None and time.perf_counter() - t0 > cfg.max_seconds:
                log.info("training time budget of %.0f s reached after epoch %d", cfg.max_seconds, epoch)
                break
        if bar is not None:
            bar.close()
        if best_state is not None:
            model.load_state_dict(best_state)
        hist["seconds"] = time.perf_counter() - t0
        return model.eval(), hist
    finally:
        torch.set_num_threads(old_threads)


def _as_dataset(dataset: Union[str, Path, PerceptionDataset]) -> PerceptionDataset:
    return dataset if isinstance(dataset, PerceptionDataset) else load_dataset(dataset)


def _splits(ds: PerceptionDataset, cfg: TrainConfig) -> dict:
    parts = ds.metadata.get("pooled")
    if not parts:
        return split_dataset(ds, cfg.split_fractions, cfg.n_azimuth_cells, cfg.n_distance_cells, cfg.split_seed)
    out = {"train": [], "val": [], "test": []}
    for part in parts:  # each source split by its own viewpoint cells, then pooled
        lo, hi = part["start"], part["stop"]
        sub = ds.subset(np.arange(lo, hi))
        sub.metadata = {"sampling": part.get("sampling", {})}
        for k, idx in split_dataset(sub, cfg.split_fractions, cfg.n_azimuth_cells, cfg.n_distance_cells,
                                    cfg.split_seed).items():
            out[k].append(idx + lo)
    return {k: np.concatenate(v) for k, v in out.items()}


def pool_datasets(datasets: Sequence[Union[str, Path, PerceptionDataset]]) -> PerceptionDataset:
    """One dataset of several (e.g. the studio views and views of the scenes' roadmaps).

    Targets are kept per source (the same name in two sources may sit at different poses); classes are the union.
    ``metadata["pooled"]`` records each source's index range, directory and sampling, so that training splits each
    source by its own viewpoint cells (:func:`train_surrogate`) and reports test metrics per source.
    """
    dss = [_as_dataset(d) for d in datasets]
    if not dss:
        raise InputError("pool_datasets needs at least one dataset")
    if len(dss) == 1:
        return dss[0]
    keys = set.intersection(*(set(d.params) for d in dss))
    targets, tidx, parts, start = [], [], [], 0
    for d in dss:
        tidx.append(d.target_index + len(targets))
        targets.extend(d.targets)
        parts.append({"dir": d.path, "start": start, "stop": start + len(d), "sampling": d.metadata.get("sampling", {}),
                      "scorer": d.metadata.get("scorer", "")})
        start += len(d)
    return PerceptionDataset(
        camera_poses=np.concatenate([d.camera_poses for d in dss]), target_index=np.concatenate(tidx),
        scores=np.concatenate([d.scores for d in dss]),
        params={k: np.concatenate([d.params[k] for d in dss]) for k in sorted(keys)}, targets=targets,
        classes=sorted(set().union(*(d.classes for d in dss))),
        metadata={"pooled": parts, "scorer": "; ".join(sorted({p["scorer"] for p in parts}))},
        path=",".join(d.path for d in dss))


def train_surrogate(dataset: Union[str, Path, PerceptionDataset], out_path: Union[str, Path, None] = None,
                    config: Optional[TrainConfig] = None, progress: bool = True) -> tuple:
    """Train the surrogate on a dataset built by :func:`~psprm_core.perception.dataset.build_dataset`.

    Splits the data by viewpoint (train/val/test), trains with early stopping on the validation split, evaluates on
    all three splits and, if ``out_path`` is given, saves a checkpoint whose metadata holds the training config, the
    dataset hash and directory, the split sizes and the metrics.

    Parameters
    ----------
    dataset : path, PerceptionDataset, or a sequence of them
        Several are pooled (:func:`pool_datasets`): each is split by its own viewpoint cells.
    out_path : path, optional
        Where to save the checkpoint (``.pt``).
    config : TrainConfig
    progress : bool

    Returns
    -------
    model : PerceptionSurrogate
    report : dict
        ``dataset_hash``, ``split_sizes``, ``history``, ``metrics`` (``train``/``val``/``test``, see
        :func:`perception_metrics`), ``checkpoint`` (path or None).
    """
    cfg = config or TrainConfig()
    ds = pool_datasets(dataset) if isinstance(dataset, (list, tuple)) else _as_dataset(dataset)
    splits = _splits(ds, cfg)
    feats, cls, y = dataset_tensors(ds, cfg.derived_features)
    parts = {k: (feats[v], cls[v], y[v]) for k, v in splits.items()}
    if parts["train"][0].shape[0] == 0:
        raise InputError("the training split is empty")
    dhash = ds.content_hash()
    log.info("training surrogate on %d samples (val %d, test %d), classes %s, dataset %s", len(splits["train"]),
             len(splits["val"]), len(splits["test"]), ds.classes, dhash)
    model, hist = fit_surrogate(parts["train"], parts["val"] if len(splits["val"]) else None, ds.classes, cfg,
                                progress=progress)
    metrics = {k: perception_metrics(_predict_features(model, *v[:2]), v[2], cfg.threshold) for k, v in parts.items()}
    for src in ds.metadata.get("pooled", []):  # test metrics of each pooled source
        idx = splits["test"][(splits["test"] >= src["start"]) & (splits["test"] < src["stop"])]
        if len(idx):
            metrics.setdefault("test_by_source", {})[src["dir"]] = perception_metrics(
                _predict_features(model, feats[idx], cls[idx]), y[idx], cfg.threshold)
    report = {"dataset_hash": dhash, "dataset_dir": ds.path,
              "split_sizes": {k: int(len(v)) for k, v in splits.items()}, "history": hist, "metrics": metrics,
              "checkpoint": None}
    model.metadata.update({"training": cfg.to_dict(), "dataset_hash": dhash, "dataset_dir": ds.path,
                           "split_sizes": report["split_sizes"],
                           "metrics": metrics, "scorer": ds.metadata.get("scorer", ""),
                           "best_epoch": hist["best_epoch"], "epochs_run": hist["epochs_run"], "history": hist})
    if out_path is not None:
        report["checkpoint"] = str(model.save(out_path))
    return model, report


def evaluate_surrogate(model: Union[str, Path, PerceptionSurrogate], dataset: Union[str, Path, PerceptionDataset],
                       split: str = "test", threshold: float = DEFAULT_THRESHOLD, scene=None, tau: float = 0.5,
                       config: Optional[TrainConfig] = None) -> dict:
    """Evaluate a surrogate on a dataset split, optionally with ray-cast occlusion in a scene.

    Parameters
    ----------
    model : path or PerceptionSurrogate
    dataset : path or PerceptionDataset
    split : {"train", "val", "test", "all"}
        Which viewpoint split to use; the split settings come from ``config``, else from the model's
        ``metadata["training"]``, else the defaults (a dataset other than the training one can use ``"all"``).
    threshold : float
        Classification threshold (paper: 0.75).
    scene : Scene, optional
        If given (a scene containing the dataset's targets by name), every sample is ray cast against the scene's
        other boxes (:class:`~psprm_core.perception.occlusion.OcclusionChecker`); samples with occlusion score
        ``> tau`` form the occluded subset and the result gains ``occlusion`` (:func:`occlusion_metrics`, zeroing by
        the same ray casting) and ``occlusion_scores_mean``.
    tau : float
        Occlusion threshold.

    Returns
    -------
    dict
        ``split``, ``n``, ``metrics`` (:func:`perception_metrics`), and ``occlusion`` if ``scene`` is given.
    """
    if not isinstance(model, PerceptionSurrogate):
        model = PerceptionSurrogate.load(model)
    ds = _as_dataset(dataset)
    if split != "all":
        cfg = config or TrainConfig.from_dict(model.metadata.get("training", {}))
        splits = _splits(ds, cfg)
        if split not in splits:
            raise InputError(f"unknown split {split!r} (train, val, test, all)")
        ds = ds.subset(splits[split])
    missing = sorted({t.detector_class for t in ds.targets} - set(model.classes))
    if missing:
        raise InputError(f"model was not trained on classes {missing} (classes: {model.classes})")
    cls_names = [t.detector_class for t in ds.targets]
    cls = torch.as_tensor([model.class_index(cls_names[i]) for i in ds.target_index], dtype=torch.long)
    feats = pose_features(ds.camera_poses, ds.target_poses, model.derived).float()
    pred = _predict_features(model, feats, cls).numpy()
    out = {"split": split, "n": len(ds), "metrics": perception_metrics(pred, ds.scores, threshold)}
    if scene is not None:
        occ_scores = np.zeros(len(ds))
        for ti, t in enumerate(ds.targets):
            sel = ds.target_index == ti
            if sel.any():
                checker = OcclusionChecker.from_scene(scene, t.name, tau=tau)
                occ_scores[sel] = checker.score(torch.as_tensor(ds.camera_poses[sel])).numpy()
        flags = occ_scores > tau
        out["occlusion"] = occlusion_metrics(pred, ds.scores, flags, None, threshold)
        out["occlusion_scores_mean"] = float(occ_scores.mean()) if len(ds) else float("nan")
    return out


# ------------------------------------------------------------------------------------------------------------------
# Throughput
# ------------------------------------------------------------------------------------------------------------------
def evals_per_s(model: Optional[PerceptionSurrogate] = None, batch: int = 65536, threads: Optional[int] = 2,
                repeats: int = 5, include_features: bool = True, chunk_size: Optional[int] = None,
                seed: int = 0) -> float:
    """Surrogate throughput in evaluations per second (best of ``repeats``), batched, in inference mode.

    Parameters
    ----------
    model : PerceptionSurrogate, optional
        Default: an untrained model of the paper's size with one class (the architecture sets the cost).
    batch : int
        Camera poses per call.
    threads : int or None
        ``torch.set_num_threads`` for the measurement (restored afterwards); the target is >= 150,000 evals/s on
        2 CPU threads.
    include_features : bool
        Time :meth:`PerceptionSurrogate.predict` from camera poses (features included); otherwise only the network
        on precomputed features.
    chunk_size : int, optional
        Rows per forward pass (default: the model's CPU/GPU default).
    """
    old = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        if model is None:
            torch.manual_seed(seed)
            model = PerceptionSurrogate(["object"])
        model.eval()
        dev = model.device
        g = torch.Generator().manual_seed(seed)
        poses = torch.eye(4).repeat(batch, 1, 1)
        q, _ = torch.linalg.qr(torch.randn(batch, 3, 3, generator=g))
        poses[:, :3, :3] = q
        poses[:, :3, 3] = torch.rand(batch, 3, generator=g) * 4
        poses = poses.to(dev)
        target = torch.eye(4, device=dev)
        cls0 = model.classes[0]
        feats = pose_features(poses, target, model.derived).float()
        chunk = chunk_size or (4096 if dev.type == "cpu" else batch)

        def run() -> None:
            if include_features:
                model.predict(poses, target, cls0, chunk_size=chunk)
            else:
                model.predict_features(feats, cls0, chunk_size=chunk)

        best = math.inf
        with torch.inference_mode():
            run()
            for _ in range(max(1, repeats)):
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                t0 = time.perf_counter()
                run()
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                best = min(best, time.perf_counter() - t0)
        return batch / best
    finally:
        torch.set_num_threads(old)
