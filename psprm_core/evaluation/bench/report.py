"""What ``psprm bench`` makes of its rows: the per-problem headroom (:func:`annotate_headroom`), per-planner
summaries (:func:`summarize`, :func:`summarize_cells`), the Markdown tables next to the paper's values, the CSV,
JSON and plots (:func:`write_outputs`) and the ``--json`` object (:func:`json_summary`)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .tasks import ROW_FIELDS


#: Paper Table II (home, Stretch; 2,500 problems) and Table III (nursing) for the Markdown comparison.
PAPER_TABLE2 = {
    "post": dict(preprocess_s=None, plan_s=0.051, path_length_rad=6.277, success_rate=0.997, det_rate=0.209,
                 mean_confidence=0.531, track_rate=0.579),
    "rejection": dict(preprocess_s=None, plan_s=1.264, path_length_rad=10.379, success_rate=0.989, det_rate=0.297,
                      mean_confidence=0.599, track_rate=0.740),
    "manifold-frustum": dict(preprocess_s=None, plan_s=0.495, path_length_rad=11.141, success_rate=0.988,
                             det_rate=0.410, mean_confidence=0.597, track_rate=0.809),
    "manifold-line": dict(preprocess_s=None, plan_s=2.859, path_length_rad=7.478, success_rate=0.901, det_rate=0.489,
                          mean_confidence=0.482, track_rate=0.674),
    "trajopt": dict(preprocess_s=None, plan_s=0.152, path_length_rad=5.62, success_rate=0.930, det_rate=0.357,
                    mean_confidence=0.561, track_rate=0.644),
    "rl-ppo": dict(preprocess_s=169.8, plan_s=0.404, path_length_rad=21.75, success_rate=0.573, det_rate=0.755,
                   mean_confidence=0.634, track_rate=0.800),
    "psprm-frustum": dict(preprocess_s=291.7, plan_s=0.014, path_length_rad=16.688, success_rate=0.964,
                          det_rate=0.737, mean_confidence=0.761, track_rate=0.898),
    "psprm-line": dict(preprocess_s=341.5, plan_s=0.018, path_length_rad=15.007, success_rate=0.957, det_rate=0.801,
                       mean_confidence=0.792, track_rate=0.910),
    "neural-psprm-frustum": dict(preprocess_s=32.08, plan_s=0.017, path_length_rad=15.814, success_rate=0.971,
                                 det_rate=0.728, mean_confidence=0.759, track_rate=0.898),
    "neural-psprm-line": dict(preprocess_s=31.79, plan_s=0.021, path_length_rad=13.518, success_rate=0.963,
                              det_rate=0.796, mean_confidence=0.771, track_rate=0.904),
}
PAPER_TABLE3 = {
    "manifold-line": dict(plan_s=5.31, path_length_rad=6.89, det_rate_any=0.3153, det_rate_all=0.0,
                          mean_confidence=0.49),
    "neural-psprm-line": dict(plan_s=32.91, path_length_rad=11.51, det_rate_any=0.9840, det_rate_all=0.6329,
                              mean_confidence=0.81),
}

METRICS = ["success_rate", "det_rate", "mean_confidence", "track_rate", "path_length_rad", "preprocess_s", "plan_s",
           "total_s"]


def _nanmean(xs) -> float:
    a = np.asarray([x for x in xs if x is not None], dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else float("nan")


#: A problem counts towards "headroom captured" when its best judged route detects the target in at least this share
#: of frames more than Post's path does.
HEADROOM_MIN_GAIN = 0.10


def _finite(x) -> bool:
    return isinstance(x, (int, float, np.floating)) and math.isfinite(float(x))


def annotate_headroom(rows: list) -> None:
    """Add the per-problem reference to every row (in place), from all rows of its problem (every planner's path and
    the reference candidates, all judged by the oracle):

    - ``best_det_rate``: the best detection rate of any judged route;
    - ``unseeable_frame_rate`` (successful rows): the share of the row's path that no judged route saw, i.e. the
      shortest unseen stretch after the start plus the shortest before the goal over all routes (the start and goal
      views behind the target), over the row's path length, at most 1;
    - ``headroom`` (successful rows, where Post solved the problem and ``best - post >= HEADROOM_MIN_GAIN``):
      ``(det_rate - post) / (best - post)``, the share of the possible gain over Post the row's route captured.
    """
    by: dict = {}
    for r in rows:
        by.setdefault(r["problem"], []).append(r)
        for k in ("best_det_rate", "unseeable_frame_rate", "headroom"):
            r.setdefault(k, float("nan"))
    for rs in by.values():
        ok = [r for r in rs if r["success"] and _finite(r.get("det_rate"))]
        if not ok:
            continue
        best = max(float(r["det_rate"]) for r in ok)
        heads = [float(r["unseen_head"]) for r in ok if _finite(r.get("unseen_head"))]
        tails = [float(r["unseen_tail"]) for r in ok if _finite(r.get("unseen_tail"))]
        unseen = (min(heads) if heads else 0.0) + (min(tails) if tails else 0.0)
        post = next((float(r["det_rate"]) for r in ok if r["planner"] == "post"), None)
        for r in rs:
            r["best_det_rate"] = best
            if r not in ok:
                continue
            L = float(r["path_length_rad"]) if _finite(r.get("path_length_rad")) else float("nan")
            r["unseeable_frame_rate"] = min(1.0, unseen / L) if L > 0 else float(unseen > 0)
            if post is not None and best - post >= HEADROOM_MIN_GAIN:
                r["headroom"] = (float(r["det_rate"]) - post) / (best - post)


def summarize(rows: list, planners: Sequence[str]) -> dict:
    """Per planner: success rate over all problems; perception metrics and path length over the successful ones;
    preprocessing = mean build time per prepared instance; planning time = mean over all attempts;
    total = preprocessing + planning; ``headroom_captured`` the mean ``headroom`` (:func:`annotate_headroom`) over
    the problems that have one (``headroom_problems`` of them), ``unseeable_frame_rate`` and ``best_det_rate`` means
    over the successful ones. Plus ``ratios`` of neural-psprm-line's detection rates (calibrated and strict) and
    mean confidence to Post's and Manifold-line's when those ran."""
    out = {}
    for pl in planners:
        rs = [r for r in rows if r["planner"] == pl]
        if not rs:
            continue
        ok = [r for r in rs if r["success"]]
        # one preprocessing per built instance: per target group and placement, or per run in scenario mode
        pre = _nanmean({f'{r["targets"]}|{r.get("placement", 0)}|{r.get("run_seed", "")}': r["preprocess_s"]
                        for r in rs}.values())
        pre = 0.0 if math.isnan(pre) else pre
        plan = _nanmean(r["plan_s"] for r in rs)
        out[pl] = {
            "problems": len(rs), "successes": len(ok), "success_rate": len(ok) / len(rs),
            "det_rate": _nanmean(r["det_rate"] for r in ok),
            "det_rate_strict": _nanmean(r.get("det_rate_strict") for r in ok),
            "mean_confidence": _nanmean(r["mean_confidence"] for r in ok),
            "track_rate": _nanmean(r["track_rate"] for r in ok),
            "det_rate_any": _nanmean(r["det_rate_any"] for r in ok),
            "det_rate_all": _nanmean(r["det_rate_all"] for r in ok),
            "path_length_rad": _nanmean(r["path_length_rad"] for r in ok),
            "median_path_length_rad": float(np.median([r["path_length_rad"] for r in ok])) if ok else float("nan"),
            "headroom_captured": _nanmean(r.get("headroom") for r in ok),
            "headroom_problems": sum(1 for r in ok if _finite(r.get("headroom"))),
            "unseeable_frame_rate": _nanmean(r.get("unseeable_frame_rate") for r in ok),
            "best_det_rate": _nanmean(r.get("best_det_rate") for r in ok),
            "preprocess_s": pre, "plan_s": plan, "total_s": pre + plan,
        }
    ratios = {}
    n = out.get("neural-psprm-line")
    if n is not None:
        for base, suffix in (("post", "post"), ("manifold-line", "manifold_line")):
            b = out.get(base)
            if b is not None:
                for m in ("det_rate", "det_rate_strict", "mean_confidence"):
                    ratios[f"{m}_vs_{suffix}"] = n[m] / b[m] if b[m] and b[m] > 0 else float("nan")
                ratios[f"median_path_length_vs_{suffix}"] = (
                    n["median_path_length_rad"] / b["median_path_length_rad"] if b["median_path_length_rad"] and
                    b["median_path_length_rad"] > 0 else float("nan"))
        b = out.get("manifold-line")
        if b is not None and any("+" in str(r["targets"]) for r in rows):  # several targets: Table III's columns
            for key in ("det_rate_any", "det_rate_all", "mean_confidence"):
                ratios[f"{key}_vs_manifold_line"] = (n[key] / b[key] if b[key] and b[key] > 0
                                                     else float("nan"))
        o = out.get("psprm-line")
        if o is not None and n["preprocess_s"] > 0:
            ratios["oracle_preprocess_vs_neural"] = o["preprocess_s"] / n["preprocess_s"]
    if ratios:
        out["ratios"] = ratios
    return out


def summarize_cells(rows: list, planners: Sequence[str]) -> dict:
    """Per target group and placement (``"cup@2"``), per planner: problems, success rate and the detection rate over
    the successful ones; shows whether a ratio comes from a few placements or from all."""
    groups: dict = {}
    for r in sorted(rows, key=lambda r: (str(r["targets"]), int(r.get("placement", 0) or 0))):
        cell = f'{r["targets"]}@{int(r.get("placement", 0) or 0)}'
        groups.setdefault(cell, {}).setdefault(r["planner"], []).append(r)
    out: dict = {}
    for cell, per in groups.items():
        out[cell] = {}
        for pl in planners:
            if pl in per:
                rs = per[pl]
                ok = [r for r in rs if r["success"]]
                out[cell][pl] = {"problems": len(rs), "success_rate": len(ok) / len(rs),
                                 "det_rate": _nanmean(r["det_rate"] for r in ok)}
    return out


def cells_table(cells: dict, planners: Sequence[str]) -> str:
    """Markdown: one row per target group and placement, the detection rate of each planner (success rate in
    parentheses)."""
    planners = [pl for pl in planners if any(pl in c for c in cells.values())]
    lines = ["| target@placement | problems | " + " | ".join(planners) + " |",
             "|---|---|" + "---|" * len(planners)]
    for cell, per in cells.items():
        n = max((v["problems"] for v in per.values()), default=0)
        vals = [f'{_fmt(per[pl]["det_rate"], True)} ({_fmt(per[pl]["success_rate"], True)})' if pl in per else "–"
                for pl in planners]
        lines.append(f"| {cell} | {n} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


# ---- outputs ----------------------------------------------------------------------------------------------------------
def _fmt(v, pct=False, digits=3) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{100 * v:.1f} %" if pct else f"{v:.{digits}g}" if abs(v) >= 100 else f"{v:.{digits}f}"


def markdown_table(summary: dict, multi_target: bool = False, settings: Optional[dict] = None) -> str:
    """The paper's Table II layout (or Table III's for two-target groups), ours next to the paper's value; settings
    changed for the run (``{planner: {key: value}}``, ``psprm bench --set``) are listed under the table."""
    lines = []
    if multi_target:
        lines.append("| method | plan. time (s) | path len. | det. rate (1 target) | det. rate (all targets) | "
                     "conf. score | success |")
        lines.append("|---|---|---|---|---|---|---|")
        for pl, s in summary.items():
            if pl == "ratios":
                continue
            p = PAPER_TABLE3.get(pl, {})

            def c(key, pct=False):
                return f"{_fmt(s[key], pct)} ({_fmt(p.get(key), pct)})" if key in p else _fmt(s[key], pct)
            lines.append(f"| {pl} | {_fmt(s['total_s'])} ({_fmt(p.get('plan_s'))}) | {c('path_length_rad')} | "
                         f"{c('det_rate_any', True)} | {c('det_rate_all', True)} | {c('mean_confidence')} | "
                         f"{_fmt(s['success_rate'], True)} |")
    else:
        lines.append("| method | preprocess time (s) | plan. time (s) | total time (s) | path len. | succ. rate | "
                     "det. rate | conf. score | track rate |")
        lines.append("|---|---|---|---|---|---|---|---|---|")
        for pl, s in summary.items():
            if pl == "ratios":
                continue
            p = PAPER_TABLE2.get(pl, {})

            def c(key, pct=False):
                return f"{_fmt(s[key], pct)} ({_fmt(p.get(key), pct)})"
            lines.append(f"| {pl} | {c('preprocess_s')} | {c('plan_s')} | {_fmt(s['total_s'])} | "
                         f"{c('path_length_rad')} | {c('success_rate', True)} | {c('det_rate', True)} | "
                         f"{c('mean_confidence')} | {c('track_rate', True)} |")
    lines.append("")
    lines.append("Ours first, the paper's value in parentheses (– where the paper has none).")
    changed = [f"{pl}.{k}={v}" for pl, kv in (settings or {}).items() for k, v in kv.items()]
    if changed:
        lines.append("")
        lines.append("Settings changed for this run: " + ", ".join(changed) + " (the others as configured).")
    if any(_finite(s.get("best_det_rate")) for k, s in summary.items() if k != "ratios"):
        lines += ["", "Perception against each problem's best judged route (the reference routes and every planner's "
                  f"path); headroom captured = (planner - Post) / (best - Post) over the problems where best - Post "
                  f">= {100 * HEADROOM_MIN_GAIN:.0f} points; unseeable = share of the path no judged route saw:", "",
                  "| method | det. rate | det. rate (strict) | conf. score | best route's det. rate | headroom captured "
                  "(problems) | unseeable frames | median path len. |", "|---|---|---|---|---|---|---|---|"]
        for pl, s in summary.items():
            if pl == "ratios":
                continue
            lines.append(f"| {pl} | {_fmt(s['det_rate'], True)} | {_fmt(s.get('det_rate_strict'), True)} | "
                         f"{_fmt(s['mean_confidence'])} | {_fmt(s.get('best_det_rate'), True)} | "
                         f"{_fmt(s.get('headroom_captured'), True)} ({s.get('headroom_problems', 0)}) | "
                         f"{_fmt(s.get('unseeable_frame_rate'), True)} | {_fmt(s.get('median_path_length_rad'))} |")
    if "ratios" in summary:
        lines.append("")
        lines.append("Ratios: " + ", ".join(f"{k} = {_fmt(v)}" for k, v in summary["ratios"].items()))
    return "\n".join(lines) + "\n"


def write_outputs(result: dict, out_dir: str | Path) -> dict:
    """results.csv, table.md, summary.json, bar charts (``bars_<metric>.png``) and ``paths.png``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    with open(out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=ROW_FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in result["rows"]:
            w.writerow(r)
    files["csv"] = out / "results.csv"
    multi = any(len(g) > 1 for g in result["config"]["target_groups"])
    table = markdown_table(result["summary"], multi, result["config"].get("planner_kwargs"))
    cells = summarize_cells(result["rows"], result["config"]["planners"])
    if len(cells) > 1:
        table += ("\nDetection rate per target and placement (success rate in parentheses):\n\n"
                  + cells_table(cells, result["config"]["planners"]))
    (out / "table.md").write_text(table)
    files["table"] = out / "table.md"
    (out / "summary.json").write_text(json.dumps(
        {"config": result["config"], "summary": result["summary"], "cells": cells, "prepare": result["prepare"],
         "wall_s": result["wall_s"]}, indent=2, default=str))
    files["summary"] = out / "summary.json"
    files.update(_plots(result, out, multi))
    return files


def _plots(result: dict, out: Path, multi: bool) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = {}
    summ = {k: v for k, v in result["summary"].items() if k != "ratios"}
    names = list(summ)
    metrics = METRICS + (["det_rate_any", "det_rate_all"] if multi else [])
    for m in metrics:
        fig, ax = plt.subplots(figsize=(max(4, 0.8 * len(names) + 2), 3.2))
        vals = [summ[n][m] for n in names]
        ax.bar(range(len(names)), [v if math.isfinite(v) else 0 for v in vals], color="tab:blue")
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
        ax.set_title(m)
        fig.tight_layout()
        f = out / f"bars_{m}.png"
        fig.savefig(f, dpi=100)
        plt.close(fig)
        files[f"bars_{m}"] = f
    # example paths over the scene (top view): the first successful path of each planner
    scene = result["scene"]
    fig, ax = plt.subplots(figsize=(7, 5.5))
    for b in scene.collision_boxes():
        c = b.corners()[:, :2] if hasattr(b, "corners") else None
        if c is not None:
            from scipy.spatial import ConvexHull

            try:
                h = ConvexHull(c)
                ax.fill(c[h.vertices, 0], c[h.vertices, 1], color="0.75", zorder=1)
            except Exception:
                pass
    for t in scene.target_names:
        x, y = scene.target(t).center[:2]
        ax.plot(x, y, "r*", ms=10, zorder=3)
        ax.annotate(t, (x, y), fontsize=7)
        for k in range(1, min(int(result["config"].get("placements", 1)), scene.target(t).n_placements)):
            x, y = scene.target(t).pose(k)[0][:2]  # the other placements benchmarked: hollow stars
            ax.plot(x, y, "*", mfc="none", mec="r", ms=9, zorder=3)
            ax.annotate(f"{t}@{k}", (x, y), fontsize=6)
    cmap = plt.get_cmap("tab10")
    first = {}
    for p in result["paths"]:
        first.setdefault(p["planner"], p)
    for i, (pl, p) in enumerate(sorted(first.items())):
        d = np.asarray(p["dense"])
        ax.plot(d[:, 0], d[:, 1], "-", color=cmap(i % 10), lw=1.5, label=f"{pl} (#{p['problem']})", zorder=2)
        ax.plot(d[0, 0], d[0, 1], "o", color=cmap(i % 10), ms=4)
        ax.plot(d[-1, 0], d[-1, 1], "s", color=cmap(i % 10), ms=4)
    ws = scene.workspace
    ax.set_xlim(ws[0][0] - 0.2, ws[0][1] + 0.2)
    ax.set_ylim(ws[1][0] - 0.2, ws[1][1] + 0.2)
    ax.set_aspect("equal")
    if first:
        ax.legend(fontsize=6, loc="upper right")
    ax.set_title(f"example paths ({scene.name})")
    fig.tight_layout()
    f = out / "paths.png"
    fig.savefig(f, dpi=110)
    plt.close(fig)
    files["paths"] = f
    return files


def json_summary(summary: dict) -> dict:
    """The ``--json`` object: one entry per planner with the metric keys of Tables II-III, the strict detection rate
    and the headroom keys (+ ``ratios``)."""
    keys = ["success_rate", "det_rate", "det_rate_strict", "mean_confidence", "track_rate", "path_length_rad",
            "median_path_length_rad", "preprocess_s", "plan_s", "total_s", "det_rate_any", "det_rate_all",
            "headroom_captured", "headroom_problems", "unseeable_frame_rate", "best_det_rate", "problems",
            "successes"]

    def clean(v):
        return None if isinstance(v, float) and not math.isfinite(v) else v
    out = {pl: {k: clean(s[k]) for k in keys if k in s} for pl, s in summary.items() if pl != "ratios"}
    if "ratios" in summary:
        out["ratios"] = {k: clean(v) for k, v in summary["ratios"].items()}
    return out
