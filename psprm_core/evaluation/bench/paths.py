"""How ``psprm bench`` judges an executed path: camera frames at a fixed spacing along it, the oracle detector and the
`norfair` tracker on them (:func:`evaluate_path`), and the check that a claimed success holds
(:func:`verify_success`)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from ...perception.oracle import box_iou


def arc_lengths(motion, dense: np.ndarray) -> np.ndarray:
    """Motion cost (:class:`~psprm_core.motion.DiffDriveMotion`) from the start to each configuration of ``dense``."""
    import torch

    if len(dense) < 2:
        return np.zeros(len(dense))
    q = torch.as_tensor(dense, dtype=torch.float64)
    return np.concatenate([[0.0], np.cumsum(motion.distance(q[:-1], q[1:]).numpy())])


def frame_indices(motion, dense: np.ndarray, spacing: float, max_frames: int) -> np.ndarray:
    """Indices of ``dense`` about ``spacing`` apart along the path (at most ``max_frames``; both ends included)."""
    if len(dense) < 2:
        return np.zeros(len(dense), dtype=int)
    s = arc_lengths(motion, dense)
    n = int(min(max_frames, max(2, math.floor(s[-1] / spacing) + 1)))
    marks = np.linspace(0.0, s[-1], n)
    return np.unique(np.clip(np.searchsorted(s, marks), 0, len(dense) - 1))


def unseen_ends(arc: np.ndarray, seen: np.ndarray) -> tuple:
    """Motion along a path before its first and after its last seen frame: (head, tail). ``arc`` (F,) the frames'
    arc lengths (increasing, from 0), ``seen`` (F,) their flags; a path that never sees gives its whole length twice.
    """
    arc, seen = np.asarray(arc, float), np.asarray(seen, bool)
    if len(arc) == 0:
        return 0.0, 0.0
    if not seen.any():
        return float(arc[-1]), float(arc[-1])
    i = np.nonzero(seen)
    return float(arc[i[0][0]]), float(arc[-1] - arc[i[0][-1]])


def _box_iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(box_iou(np.asarray(a, float).reshape(4), np.asarray(b, float).reshape(4)))


def track_flags(results: list, min_iou: float = 0.1) -> np.ndarray:
    """Frames (N,) in which a confirmed `norfair` track covers the target.

    The tracker sees, per frame, every detection of the target's class at or above the detector's threshold (boxes
    as two corner points, IoU distance); a frame counts as tracked when one of the tracks it returns (tracks are
    returned once initialised, and are kept through short gaps) overlaps the target's projected box.
    """
    from norfair import Detection, Tracker

    tracker = Tracker(distance_function="iou", distance_threshold=0.95, initialization_delay=1, hit_counter_max=3)
    flags = np.zeros(len(results), dtype=bool)
    for i, r in enumerate(results):
        dets = [Detection(points=np.asarray(d.box_xyxy, float).reshape(2, 2), scores=np.array([d.score, d.score]))
                for d in (r.detections or []) if d.label == r.detector_class and d.score >= r.threshold]
        objs = tracker.update(detections=dets)
        if r.projected_box is not None:
            flags[i] = any(_box_iou(o.estimate.reshape(4), r.projected_box) >= min_iou for o in objs)
    return flags


def evaluate_path(oracle, robot, motion, dense: np.ndarray, targets: Sequence[str], spacing: float = 0.5,
                  max_frames: int = 40, per_frame: bool = False) -> dict:
    """Oracle metrics of an executed path, from the oracle's verdict on camera frames about ``spacing`` apart:

    - ``det_rate``: frames whose matched confidence reaches the detector's calibrated threshold
      (:data:`~psprm_core.perception.oracle.DETECTION_THRESHOLDS`); ``det_rate_strict``: frames with a confident
      detection (:data:`~psprm_core.perception.oracle.STRICT_THRESHOLDS`); ``mean_confidence``; ``track_rate``
      (:func:`track_flags`); each averaged over the targets;
    - ``det_rate_any`` / ``det_rate_all``: frames where at least one / every target is detected;
    - ``unseen_head`` / ``unseen_tail``: the motion before the first and after the last frame in which a target is
      detected (:func:`unseen_ends`), the stretches no route from the same start to the same goal may avoid if no
      other route sees there either.

    ``per_frame``: also the frames' arc lengths (``frame_arc``) and per-target detection flags and confidences."""
    import torch

    idx = frame_indices(motion, dense, spacing, max_frames)
    cams = robot.camera_poses(torch.as_tensor(dense[idx], dtype=torch.float64)).numpy()
    det, conf, trk, strict = [], [], [], []
    for t in targets:
        res = oracle.score_many(list(cams), t)
        det.append([r.detected for r in res])
        conf.append([r.score for r in res])
        trk.append(track_flags(res))
        strict.append(np.asarray(conf[-1]) >= oracle.strict_threshold(t))
    det, conf, trk, strict = (np.asarray(det, bool), np.asarray(conf, float), np.asarray(trk, bool),
                              np.asarray(strict, bool))
    arc = arc_lengths(motion, dense)[idx]
    head, tail = unseen_ends(arc, det.any(0))
    out = {"frames": int(len(idx)), "det_rate": float(det.mean()), "mean_confidence": float(conf.mean()),
           "track_rate": float(trk.mean()), "det_rate_any": float(det.any(0).mean()),
           "det_rate_all": float(det.all(0).mean()), "det_rate_strict": float(strict.mean()),
           "unseen_head": head, "unseen_tail": tail}
    if per_frame:
        out.update(frame_arc=arc, frame_detected=det, frame_confidence=conf)
    return out


def verify_success(robot, checker, motion, start: np.ndarray, goal: np.ndarray, dense: np.ndarray,
                   tol: float = 1e-3, max_step: float = 0.25) -> str:
    """Why a planner's claimed success does not hold ("" when it does): the executed path ``dense`` must start at
    ``start`` and end at ``goal`` (or at one of several goals (G, dof)), every joint within ``tol`` and the base
    heading modulo a turn, advance in steps of at most ``max_step`` (the motion metric; the planners' paths step
    0.05-0.13) and be collision-free under ``checker``, a collision checker of the bench's own scene. The bench counts
    a success only when this holds."""
    import torch

    d = np.asarray(dense, float)
    if d.ndim != 2 or len(d) < 2 or not np.isfinite(d).all():
        return "the path is not a finite sequence of configurations"
    for what, q, want in (("start", d[0], start), ("goal", d[-1], goal)):
        off = q - np.atleast_2d(np.asarray(want, float))
        if robot.mobile:
            off[:, 2] = (off[:, 2] + np.pi) % (2 * np.pi) - np.pi
        if np.abs(off).max(1).min() > tol:
            return f"the path's {'end' if what == 'goal' else what} is {np.abs(off).max(1).min():.3g} away from " \
                   f"the problem's {what}"
    q = torch.as_tensor(d, dtype=torch.float64)
    step = float(motion.distance(q[:-1], q[1:]).max())
    if step > max_step:
        return f"the path jumps {step:.3g} between two of its configurations (at most {max_step:g})"
    hit = checker.check(q.to(torch.float32)).cpu().numpy()
    if hit.any():
        return f"the path collides at {int(hit.sum())} of its {len(d)} configurations"
    return ""
