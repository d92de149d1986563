"""How the surrogate's held-out figures grow with its training data and its capacity (``psprm perf
surrogate-scaling``): what more labelled views, more seeds averaged (an ensemble) or a wider network would buy.

The pooled dataset is split by viewpoint exactly as ``psprm train`` splits it (same split settings, same test split
as ``psprm eval-surrogate``). For each fraction of the training split (a random subset, drawn once per fraction),
a surrogate is trained per seed with the training defaults and judged on the whole test split: pooled Spearman and
RMSE, and the Spearman of each class. With ``ensemble`` > 1 the full-data models of the first ``ensemble`` seeds are
also averaged; with ``hidden`` a wider network is trained on the full split too.

The growth per doubling of the data is fitted as a straight line in log2(training views) over the seeds' means;
:func:`views_needed` reads off where that line would reach a target figure. The returns diminish with the data, so
the straight line is optimistic and the views it names are a lower bound.
"""

from __future__ import annotations

import itertools
import logging
import math
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError
from ..perception.dataset import load_dataset
from ..perception.training import TrainConfig, _predict_features, _splits, dataset_tensors, fit_surrogate, pool_datasets

log = logging.getLogger(__name__)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b).correlation)


def judge(pred: np.ndarray, label: np.ndarray, cls: np.ndarray, classes: Sequence[str]) -> dict:
    """Pooled Spearman and RMSE of ``pred`` against ``label``, and the Spearman of each class."""
    pred, label, cls = np.asarray(pred, float), np.asarray(label, float), np.asarray(cls)
    return {"spearman": _spearman(pred, label), "rmse": float(np.sqrt(np.mean((pred - label) ** 2))),
            "spearman_by_class": {c: _spearman(pred[cls == i], label[cls == i]) for i, c in enumerate(classes)}}


def views_needed(rows: list, target: float, key: str = "spearman") -> Optional[dict]:
    """Straight line of ``key`` (mean over seeds) against log2(training views), and the training views at which it
    reaches ``target`` (None with fewer than two fractions, or a line that does not rise)."""
    by_n: dict = {}
    for r in rows:
        by_n.setdefault(r["train_views"], []).append(r[key])
    if len(by_n) < 2:
        return None
    n = np.array(sorted(by_n), float)
    y = np.array([np.mean(by_n[k]) for k in sorted(by_n)])
    slope, icept = np.polyfit(np.log2(n), y, 1)
    out = {"gain_per_doubling": float(slope), "target": float(target)}
    if slope > 1e-9:  # a line that rises (a flat one fits a slope of ~1e-16)
        out["views_for_target"] = float(2.0 ** ((target - icept) / slope))
        out["times_today"] = out["views_for_target"] / float(n.max())
    return out


def surrogate_scaling(dataset: Sequence[str], fractions: Sequence[float] = (0.25, 0.5, 1.0),
                      seeds: Sequence[int] = (0, 1), ensemble: int = 0, hidden: Optional[int] = None,
                      threads: Optional[int] = 2, target: float = 0.946, subset_seed: int = 0,
                      allow_incomplete: bool = False) -> dict:
    """Train and judge the surrogates described in the module docstring; returns the rows and the fitted growth."""
    ds = pool_datasets([load_dataset(d, allow_incomplete=allow_incomplete) for d in dataset])
    base = TrainConfig(threads=threads)
    splits = _splits(ds, base)
    feats, cls, y = dataset_tensors(ds, base.derived_features)
    te, va = splits["test"], splits["val"]
    val = (feats[va], cls[va], y[va])
    y_te, c_te = y[te].numpy(), cls[te].numpy()
    rng = np.random.default_rng(subset_seed)
    rows, full_preds = [], []

    def fit(train_idx: np.ndarray, cfg: TrainConfig):
        model, hist = fit_surrogate((feats[train_idx], cls[train_idx], y[train_idx]), val, ds.classes, cfg)
        return np.asarray(_predict_features(model, feats[te], cls[te]), float), hist

    for frac in sorted(fractions):
        if not 0 < frac <= 1:
            raise InputError(f"fractions must lie in (0, 1], got {frac}")
        idx = splits["train"]
        if frac < 1:
            idx = np.sort(rng.choice(idx, max(1, int(round(frac * len(idx)))), replace=False))
        for seed in seeds:
            pred, hist = fit(idx, TrainConfig(threads=threads, seed=seed))
            row = {"fraction": float(frac), "train_views": int(len(idx)), "seed": int(seed),
                   "best_epoch": int(hist["best_epoch"]), "seconds": round(float(hist["seconds"]), 1),
                   **judge(pred, y_te, c_te, ds.classes)}
            rows.append(row)
            log.info("fraction %.2f seed %d: Spearman %.3f", frac, seed, row["spearman"])
            if frac == 1.0:
                full_preds.append((seed, pred))
    out = {"test_views": int(len(te)), "classes": list(ds.classes), "rows": rows,
           "growth": views_needed(rows, target)}
    if ensemble > 1:
        preds = [p for _, p in full_preds[:ensemble]]
        spare = (s for s in itertools.count() if s not in seeds)  # seeds for models beyond the full-data rows
        while len(preds) < ensemble:
            preds.append(fit(splits["train"], TrainConfig(threads=threads, seed=next(spare)))[0])
        out["ensemble"] = {"models": len(preds), **judge(np.mean(preds, axis=0), y_te, c_te, ds.classes)}
    if hidden:
        pred, _ = fit(splits["train"], TrainConfig(threads=threads, seed=int(seeds[0]), hidden=int(hidden)))
        out["wide"] = {"hidden": int(hidden), **judge(pred, y_te, c_te, ds.classes)}
    return out


def format_table(res: dict) -> str:
    """The rows and the fitted growth as plain text."""
    classes = res["classes"]
    lines = [f"test split: {res['test_views']} views; Spearman pooled and per class ({', '.join(classes)})"]
    lines.append(f"{'fraction':>8s} {'views':>6s} {'seed':>4s} {'rho':>6s} {'rmse':>6s} " +
                 " ".join(f"{c[:8]:>8s}" for c in classes))
    for r in res["rows"]:
        lines.append(f"{r['fraction']:8.2f} {r['train_views']:6d} {r['seed']:4d} {r['spearman']:6.3f} {r['rmse']:6.3f} "
                     + " ".join(f"{r['spearman_by_class'][c]:8.3f}" for c in classes))
    for key, name in (("ensemble", "ensemble of {models}"), ("wide", "hidden {hidden}")):
        if key in res:
            e = res[key]
            lines.append(f"{name.format(**e):>20s} {e['spearman']:6.3f} {e['rmse']:6.3f} " +
                         " ".join(f"{e['spearman_by_class'][c]:8.3f}" for c in classes))
    g = res.get("growth")
    if g:
        msg = f"pooled Spearman grows {g['gain_per_doubling']:+.4f} per doubling of the training views"
        if "views_for_target" in g and math.isfinite(g["views_for_target"]):
            msg += (f"; a straight line in log(views) reaches {g['target']:.3f} at {g['views_for_target']:,.0f} "
                    f"views ({g['times_today']:.0f}x today's; a lower bound: the returns diminish)")
        lines.append(msg)
    return "\n".join(lines)
