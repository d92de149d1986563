"""Measure detector confidences on rendered views and choose each detector's "detected" threshold.

Run ``psprm calibrate-detectors`` (a few minutes on 2 cores) to reproduce the tables in ``docs/detectors.md``.

Method. For each appearance a single target stands alone at 1 m height (camera at the target's height, looking at
it). *Positive* views should be detected: frontal and up to 40 deg off-axis, at the case's four distances, unoccluded. *Negative*
views should not: seen from 90-180 deg (the target's back; skipped for view-independent objects such as plants)
and frontal views with a box hiding 80 % of the target. A threshold maximises Youden's J = TPR - FPR (ties: the
middle of the best interval), never below :data:`MIN_THRESHOLD`; it is computed per appearance/class and pooled over
all detectable appearances a detector serves.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import numpy as np
from . import default_detector_name
from ...errors import InputError
from ...geometry import yaw_to_quat
from ...scene import Box, Scene, Target
from ..oracle import Oracle
from ..render import look_at_pose

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrationCase:
    """One appearance to measure: class, target size (x depth, y width, z height), whether it has a front, and the
    camera distances of the positive views."""

    appearance: str
    detector_class: str
    size: tuple
    has_front: bool = True
    detectable: bool = True  # False: measured for the record, kept out of the pooled thresholds
    distances: tuple = (1.0, 1.5, 2.0, 2.5)


#: Sizes follow the shipped scenes (config/scenes): faces 0.12 x 0.16 x 0.22, cups 0.08 x 0.08 x 0.1, screens
#: 0.08 x 0.9 x 0.55, plant 0.5 x 0.5 x 1.0, suitcase 0.25 x 0.45 x 0.7, fork 0.02 x 0.03 x 0.19.
DEFAULT_CASES = (
    CalibrationCase("astronaut", "face", (0.12, 0.16, 0.22)),
    CalibrationCase("grace_hopper", "face", (0.12, 0.16, 0.22)),
    CalibrationCase("coffee", "cup", (0.08, 0.08, 0.1), distances=(0.6, 0.9, 1.2, 1.5)),
    CalibrationCase("monitor", "tv", (0.08, 0.9, 0.55), distances=(1.5, 2.5, 4.0, 6.0)),
    CalibrationCase("monitor_stand", "tv", (0.25, 0.6, 0.45)),
    CalibrationCase("potted_plant", "potted plant", (0.5, 0.5, 1.0), has_front=False, distances=(1.5, 2.0, 3.0, 4.0)),
    CalibrationCase("suitcase", "suitcase", (0.25, 0.45, 0.7), detectable=False),
    CalibrationCase("fork", "fork", (0.02, 0.03, 0.19), detectable=False, distances=(0.5, 0.8, 1.0, 1.5)),
)

POS_YAWS = (0.0, 20.0, -20.0, 40.0, -40.0)
NEG_YAWS = (90.0, 120.0, 150.0, 180.0)


def measure_case(case: CalibrationCase, oracle_factory=None) -> Dict[str, List[float]]:
    """Confidences of ``case`` on the positive and negative views, plus a per-view table.

    Returns
    -------
    dict
        ``{"pos": [...], "neg": [...], "views": {view_name: score}, "ms_render": float, "ms_detect": float}``
    """
    z = 1.0
    size = np.asarray(case.size, float)
    target = Target(name="t", detector_class=case.detector_class, center=np.array([0.0, 0.0, z]), size=size,
                    quat=yaw_to_quat(0.0), appearance=case.appearance)
    # occluder parked far away; moved in front of the target for the occlusion views
    occ = Box(name="occ", center=np.array([0.0, 0.0, -50.0]), size=np.array([0.02, size[1] * 1.2, size[2] * 0.8]),
              color=np.array([0.45, 0.45, 0.5, 1.0]))
    scene = Scene(name="calib", robot="", frame="map", workspace=np.array([[-5.0, 5.0], [-5.0, 5.0]]),
                  obstacles=(occ,), targets=(target,))
    oracle = (oracle_factory or Oracle)(scene)
    out = {"pos": [], "neg": [], "views": {}, "ms_render": [], "ms_detect": []}

    def view(d, yaw_deg):
        a = math.radians(yaw_deg)
        return look_at_pose([d * math.cos(a), d * math.sin(a), z], [0.0, 0.0, z])

    def run(name, pose, bucket):
        r = oracle.score(pose, "t", keep_image=False)
        out["views"][name] = round(r.score, 3)
        if bucket:
            out[bucket].append(r.score)
        if r.timings:
            out["ms_render"].append(1000 * r.timings["render"])
            out["ms_detect"].append(1000 * r.timings["detect"])

    try:
        for d in case.distances:
            for yaw in POS_YAWS:
                run(f"d{d:g}_yaw{yaw:g}", view(d, yaw), "pos")
        d_mid = case.distances[1]
        run(f"d{1.5 * case.distances[-1]:g}_yaw0", view(1.5 * case.distances[-1], 0.0), None)
        run(f"d{d_mid:g}_yaw60", view(d_mid, 60.0), None)
        run(f"d{d_mid:g}_yaw75", view(d_mid, 75.0), None)
        for yaw in NEG_YAWS:
            run(f"d{d_mid:g}_yaw{yaw:g}", view(d_mid, yaw), "neg" if case.has_front else None)
        # a board (0.8 x the target's height) 0.3 m in front of the target hides its lower 80 % / 50 %
        for frac in (0.8, 0.5):
            top = z - size[2] / 2 + frac * size[2]
            oracle.set_obstacle_pose("occ", [size[0] / 2 + 0.3, 0.0, top - 0.4 * size[2]])
            run(f"d{d_mid:g}_occluded{int(frac * 100)}", view(d_mid, 0.0), "neg" if frac == 0.8 else None)
        oracle.set_obstacle_pose("occ", [0.0, 0.0, -50.0])
    finally:
        oracle.close()
    out["ms_render"] = float(np.median(out["ms_render"])) if out["ms_render"] else 0.0
    out["ms_detect"] = float(np.median(out["ms_detect"])) if out["ms_detect"] else 0.0
    return out


#: Never trust confidences below this: CenterNet's spurious peaks on renders reach 0.1-0.4 for *other* classes
#: (a red mug scores 'traffic light' 0.57), and both detectors drop everything under 0.05.
MIN_THRESHOLD = 0.1


def youden_threshold(pos: Sequence[float], neg: Sequence[float], floor: float = MIN_THRESHOLD) -> tuple:
    """Threshold maximising TPR - FPR (middle of the best interval, at least ``floor``), with its TPR and FPR."""
    pos, neg = np.asarray(pos, float), np.asarray(neg, float)
    cands = np.unique(np.concatenate([pos, neg, [0.0, 1.0]]))
    mids = np.concatenate([[cands[0]], 0.5 * (cands[1:] + cands[:-1])])
    best_j, best = -2.0, []
    for t in mids:
        tpr = float(np.mean(pos >= t)) if pos.size else 0.0
        fpr = float(np.mean(neg >= t)) if neg.size else 0.0
        j = tpr - fpr
        if j > best_j + 1e-12:
            best_j, best = j, [t]
        elif abs(j - best_j) <= 1e-12:
            best.append(t)
    t = float(np.round(np.median(best), 2)) if best else 0.5
    t = max(t, floor)
    return t, float(np.mean(pos >= t)) if pos.size else 0.0, float(np.mean(neg >= t)) if neg.size else 0.0


def strict_threshold(pos: Sequence[float], threshold: float) -> float:
    """A confident detection: the median confidence of the positive views (rounded to 0.01), at least
    ``threshold`` (the oracle's ``STRICT_THRESHOLDS``)."""
    pos = np.asarray(pos, float)
    return max(float(threshold), float(np.round(np.median(pos), 2)) if pos.size else float(threshold))


def calibrate(appearances: Optional[Sequence[str]] = None, measure=None) -> dict:
    """Measure every case of :data:`DEFAULT_CASES` (or those whose appearance is in ``appearances``) and choose the
    thresholds: each case's own (Youden's J on its views) and, per detector and per ``detector:class``, one pooled
    over the detectable cases.

    Returns
    -------
    dict
        ``{appearance: {"class", "detector", "threshold", "tpr", "fpr", "pos", "neg", "views", ...},
        "pooled:<detector>": {"threshold", "tpr", "fpr", "n_pos", "n_neg", "strict"}, ...}``

    Raises
    ------
    ValueError
        An unknown appearance name (the known ones are listed).
    """
    known = [c.appearance for c in DEFAULT_CASES]
    unknown = sorted(set(appearances or ()) - set(known))
    if unknown:
        raise InputError(f"unknown calibration case(s) {', '.join(unknown)} (known: {', '.join(known)})")
    measure = measure or measure_case
    results, pooled = {}, {}
    for case in DEFAULT_CASES:
        if appearances and case.appearance not in appearances:
            continue
        t0 = time.perf_counter()
        m = measure(case)
        det = default_detector_name(case.detector_class)
        thr, tpr, fpr = youden_threshold(m["pos"], m["neg"])
        results[case.appearance] = {"class": case.detector_class, "detector": det, "detectable": case.detectable,
                                    "threshold": thr, "tpr": tpr, "fpr": fpr, "s": time.perf_counter() - t0, **m}
        log.info("calibration case %s measured in %.1f s", case.appearance, time.perf_counter() - t0)
        if case.detectable:
            for key in (det, f"{det}:{case.detector_class}"):
                pooled.setdefault(key, {"pos": [], "neg": []})
                pooled[key]["pos"] += list(m["pos"])
                pooled[key]["neg"] += list(m["neg"])
    for key, d in pooled.items():
        thr, tpr, fpr = youden_threshold(d["pos"], d["neg"])
        results[f"pooled:{key}"] = {"threshold": thr, "tpr": tpr, "fpr": fpr, "n_pos": len(d["pos"]),
                                    "n_neg": len(d["neg"]), "strict": strict_threshold(d["pos"], thr)}
    return results


def report_lines(results: dict) -> list:
    """The human-readable table of :func:`calibrate`'s results (one line per case, its views, the pooled ones)."""

    def fmt(v):
        return f"{v:.2f}" if v == v else "nan"

    lines = []
    for name, r in results.items():
        if name.startswith("pooled:"):
            continue
        pos, neg = np.asarray(r["pos"], float), np.asarray(r["neg"], float)
        lines.append(f"{name:14s} {r['class']:13s} pos median {fmt(np.median(pos) if pos.size else float('nan'))} "
                     f"(min {fmt(pos.min() if pos.size else float('nan'))}, max "
                     f"{fmt(pos.max() if pos.size else float('nan'))})  neg max "
                     f"{fmt(neg.max() if neg.size else float('nan'))}  own threshold {r['threshold']:.2f} "
                     f"(TPR {r['tpr']:.2f}, FPR {r['fpr']:.2f})  render {r.get('ms_render', 0.0):.0f} ms, detect "
                     f"{r.get('ms_detect', 0.0):.0f} ms [{r['s']:.1f} s]")
        lines.append("    " + "  ".join(f"{k}={v:.2f}" for k, v in r.get("views", {}).items()))
    for name, r in results.items():
        if name.startswith("pooled:"):
            lines.append(f"POOLED {name[len('pooled:'):]}: threshold {r['threshold']:.2f}  TPR {r['tpr']:.2f}  "
                         f"FPR {r['fpr']:.2f}  strict {r['strict']:.2f}  (n_pos={r['n_pos']}, n_neg={r['n_neg']})")
    return lines
