"""How well scores predict detections (:func:`perception_metrics`: Spearman, Pearson, RMSE, F1 at a threshold) and
how occluded views are scored (:func:`occlusion_metrics`): the surrogate's evaluation and the label checks use them."""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError

#: score at and above which a view counts as a detection, and the oracle's threshold for detectors missing from
#: :data:`~psprm_core.perception.oracle.DETECTION_THRESHOLDS` (the paper's YOLO threshold)
DEFAULT_THRESHOLD = 0.75


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=float)


def perception_metrics(pred, label, threshold: float = DEFAULT_THRESHOLD) -> dict:
    """Regression, ranking and detection metrics of predicted vs. true perception scores.

    Parameters
    ----------
    pred, label : (N,) array-like
        Predicted and true scores.
    threshold : float
        Classification threshold: a sample is *positive* when its score is ``>= threshold`` (applied to both).

    Returns
    -------
    dict of plain floats/ints
        ``n, rmse, mae, spearman, accuracy, precision, recall, f1, positive_rate`` (label positive rate).
        Precision/recall/F1 are 0 when undefined (no predicted / no true positives); Spearman is NaN when either
        side is constant or ``n < 2``; everything is NaN for ``n = 0``.
    """
    p, y = _np(pred).ravel(), _np(label).ravel()
    if p.shape != y.shape:
        raise InputError(f"pred and label differ in size: {p.shape} vs {y.shape}")
    n = int(p.size)
    nan = float("nan")
    if n == 0:
        return {"n": 0, "rmse": nan, "mae": nan, "spearman": nan, "accuracy": nan, "precision": nan, "recall": nan,
                "f1": nan, "positive_rate": nan}
    err = p - y
    if n >= 2 and np.ptp(p) > 0 and np.ptp(y) > 0:
        from scipy.stats import spearmanr
        rho = float(spearmanr(p, y).statistic)
    else:
        rho = nan
    pp, yp = p >= threshold, y >= threshold
    tp = int(np.sum(pp & yp))
    fp = int(np.sum(pp & ~yp))
    fn = int(np.sum(~pp & yp))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"n": n, "rmse": float(np.sqrt(np.mean(err ** 2))), "mae": float(np.mean(np.abs(err))), "spearman": rho,
            "accuracy": float(np.mean(pp == yp)), "precision": float(precision), "recall": float(recall),
            "f1": float(f1), "positive_rate": float(np.mean(yp))}


def occlusion_metrics(pred, label, occluded, raycast_occluded=None, threshold: float = DEFAULT_THRESHOLD) -> dict:
    """Metrics on occluded configurations, with and without zeroing by ray casting (Alg. 2, lines 5-7).

    Parameters
    ----------
    pred, label : (N,) array-like
        Surrogate predictions and true scores (the true scores include the effect of occlusion).
    occluded : (N,) bool array-like
        Which samples form the "occluded" subset (e.g. ground-truth visibility from the renderer, or ray casting).
    raycast_occluded : (N,) bool array-like, optional
        Ray-casting decision ``occlusion_score > tau`` used for zeroing; defaults to ``occluded``.
    threshold : float

    Returns
    -------
    dict
        ``n, n_occluded, fraction_occluded``, ``occluded_raw`` / ``occluded_zeroed`` (metrics on the subset),
        ``all_raw`` / ``all_zeroed`` (on everything), ``occluded_mean_error_raw`` / ``occluded_mean_error_zeroed``
        (mean signed error on the subset; positive = overestimation) and, if ``raycast_occluded`` is given,
        ``raycast_agreement`` (fraction where it equals ``occluded``).
    """
    p, y = _np(pred).ravel(), _np(label).ravel()
    occ = np.asarray(_np(occluded) if isinstance(occluded, torch.Tensor) else occluded, dtype=bool).ravel()
    rc = occ if raycast_occluded is None else np.asarray(
        _np(raycast_occluded) if isinstance(raycast_occluded, torch.Tensor) else raycast_occluded, dtype=bool).ravel()
    zeroed = np.where(rc, 0.0, p)
    out = {"n": int(p.size), "n_occluded": int(occ.sum()), "fraction_occluded": float(occ.mean()) if occ.size else 0.0,
           "occluded_raw": perception_metrics(p[occ], y[occ], threshold),
           "occluded_zeroed": perception_metrics(zeroed[occ], y[occ], threshold),
           "all_raw": perception_metrics(p, y, threshold), "all_zeroed": perception_metrics(zeroed, y, threshold),
           "occluded_mean_error_raw": float(np.mean(p[occ] - y[occ])) if occ.any() else float("nan"),
           "occluded_mean_error_zeroed": float(np.mean(zeroed[occ] - y[occ])) if occ.any() else float("nan")}
    if raycast_occluded is not None:
        out["raycast_agreement"] = float(np.mean(rc == occ)) if occ.size else float("nan")
    return out


