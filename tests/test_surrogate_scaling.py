"""The pure parts of ``psprm perf surrogate-scaling``: the judged figures against a rank correlation the test
computes itself, and the views a straight line in log2(views) needs, against the line the test made the rows from."""

from __future__ import annotations

import math

import numpy as np
import pytest

from psprm_core.evaluation.surrogate_scaling import judge, views_needed


def _ranks_corr(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))  # no ties in the test's data
    return float(np.corrcoef(ra, rb)[0, 1])


def test_judge_gives_pooled_and_per_class_rank_correlations():
    rng = np.random.default_rng(0)
    label = rng.uniform(size=300)
    pred = label + rng.normal(scale=0.2, size=300)
    cls = rng.integers(0, 3, size=300)
    got = judge(pred, label, cls, ["a", "b", "c"])
    assert got["spearman"] == pytest.approx(_ranks_corr(pred, label), abs=1e-12)
    assert got["rmse"] == pytest.approx(math.sqrt(np.mean((pred - label) ** 2)), abs=1e-12)
    for i, c in enumerate("abc"):
        m = cls == i
        assert got["spearman_by_class"][c] == pytest.approx(_ranks_corr(pred[m], label[m]), abs=1e-12)


def test_views_needed_reads_the_target_off_the_fitted_line():
    # rows on the line rho = 0.80 + 0.01 log2(n), two seeds scattered symmetrically about it
    rows = [{"train_views": n, "spearman": 0.80 + 0.01 * math.log2(n) + d}
            for n in (256, 512, 1024) for d in (-0.003, 0.003)]
    g = views_needed(rows, target=0.95)
    assert g["gain_per_doubling"] == pytest.approx(0.01, abs=1e-12)
    assert g["views_for_target"] == pytest.approx(2.0 ** 15, rel=1e-9)
    assert g["times_today"] == pytest.approx(2.0 ** 15 / 1024, rel=1e-9)
    assert views_needed(rows[:2], target=0.95) is None  # one fraction: no line
    flat = [{"train_views": n, "spearman": 0.9} for n in (256, 512)]
    assert "views_for_target" not in views_needed(flat, target=0.95)
