"""``psprm bench``: every planner on the same random problems, judged by the real detector (paper Tables II and III).

Problems (:func:`make_problems`): random collision-free start and goal base poses with the camera joints aimed at the
target, each one a short manoeuvre can leave (no boxed-in ends; :func:`psprm_core.problems.random_problems`),
spread round-robin over target groups (by default each scene
target the surrogate knows; on ``nursing`` both nurses' faces together, the paper's two-face task).

Each (planner, problem) pair is one task (:func:`run_task`) on a worker of the run's backend
(:mod:`psprm_core.executors`: local worker processes, or actors on a Ray cluster; one torch thread each): the worker
prepares the planner for the problem's target group and placement once and keeps it for its later problems, plans
the problem with the per-problem time cap, and evaluates the executed path (:func:`evaluate_path`): camera frames
rendered along ``dense`` at a fixed spacing, the oracle detector on each frame (detection rate: frames at or above
the detector's calibrated threshold; mean confidence), and the maintained multi-object tracker `norfair` over the
frames' detections (track rate: frames in which a confirmed track covers the target). Every problem is planned from
the state the planner's preparation left (``reset``), so a row does not depend on which worker ran it or what it ran
before: runs with the same seed give the same rows on any backend and worker count (up to the timings, and to
planners that stop at a time cap). A planner that raises becomes a failure row; a task whose worker dies is run again
(``max_retries``), then becomes a failure row; never a crashed benchmark.

Every finished task is journalled in the output directory (``rows.jsonl``: a header with the configuration, then one
line per task); ``resume`` (``psprm bench --resume``) skips the tasks an interrupted run of the same configuration
finished.

Scenario mode (``--scenario NAME``, :func:`scenario_problems`): the scene's named problem repeated as independent
runs, the paper's Table III protocol ("100 independent runs" of one nursing scenario): every run has the same start
and goal, and every planner is built anew for each run with the run's seed (PS-PRM samples a new roadmap, so its
preprocessing is part of each run's time).

Outputs (:func:`write_outputs`): ``results.csv`` (one row per planner and problem), ``table.md`` (the layout of the
paper's Table II, or Table III for two-target groups), ``summary.json``, a bar chart per metric and a plot of example
paths over the scene (plus the journal ``rows.jsonl``, written while the run goes).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from ..errors import InputError

log = logging.getLogger(__name__)

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


@dataclass
class BenchConfig:
    """What ``psprm bench`` runs (all fields have CLI flags)."""

    scene: str = "home"
    planners: Sequence[str] = ()
    problems: int = 100
    seed: int = 0
    out: str = "out/bench"
    timeout_s: float = 10.0
    workers: Optional[int] = 2  # concurrent workers (local: <= 1 runs in this process; None: the backend's default)
    nodes: Optional[int] = None  # PS-PRM roadmap size (None: config/planners/psprm.yaml)
    oracle_nodes: Optional[int] = None  # roadmap size of the oracle PS-PRM variants (None: ``nodes``)
    frame_spacing: float = 0.5  # motion-cost units between evaluated camera frames
    max_frames: int = 20  # per path (the spacing grows for longer paths)
    target_groups: Optional[list] = None  # [[target, ...], ...]; None: default_target_groups(scene)
    scenario: Optional[str] = None  # a scene problem's name: ``problems`` independent runs of it (Table III protocol)
    placements: int = 1  # target poses per group (the first K of each target's; paper: 5 per object)
    # judge the reference routes of every problem (headroom; :mod:`psprm_core.evaluation.headroom`)
    reference: bool = True
    planner_kwargs: dict = field(default_factory=dict)  # {planner: {setting: value}} (tests, tuning)
    backend: str = "local"  # where the tasks run: "local" worker processes, or "ray" (psprm_core.executors)
    address: Optional[str] = None  # ray: the cluster to use (None: a local one started for the run)
    max_retries: int = 2  # times a task whose worker died is run again
    resume: bool = False  # skip the tasks journalled in ``out`` by an earlier run of the same configuration


# ---- problems ---------------------------------------------------------------------------------------------------------
#: Classes left out of the default target groups (none at present). The cup is included: an aimed, upright Stretch
#: camera detects it from 55 % of the home room (``psprm perf viewmap``), so it is benchmarked like the paper's other
#: objects (its tiled CenterNet costs ~0.45 s per judged frame).
DEFAULT_EXCLUDED_CLASSES: frozenset = frozenset()


def default_target_groups(scene) -> list:
    """Target groups the problems are spread over: ``nursing`` -> both nurses' faces together (paper Table III);
    otherwise every target whose class the shipped surrogate knows (the neural variants refuse the others), each on
    its own, except :data:`DEFAULT_EXCLUDED_CLASSES`."""
    names = scene.target_names
    if "nurse_1_face" in names and "nurse_2_face" in names:
        return [["nurse_1_face", "nurse_2_face"]]
    try:
        from ..perception.surrogate import load_surrogate
        from ..planning.factory import default_checkpoint

        classes = set(load_surrogate(default_checkpoint()).classes)
    except Exception:  # pragma: no cover - no checkpoint: every target
        classes = set()
    groups = [[t] for t in names if (not classes or scene.target(t).detector_class in classes)
              and scene.target(t).detector_class not in DEFAULT_EXCLUDED_CLASSES]
    return groups or [[t] for t in names]


def make_problems(scene, robot, groups: list, n: int, seed: int, placements: int = 1) -> list:
    """``n`` problems spread round-robin over ``groups`` x target placements ``0..placements-1``: dicts with index,
    targets, placement, start, goal (numpy).

    Placement ``k`` moves every target of the group to its ``k``-th pose (:meth:`Scene.with_placement`; the paper's
    "five variations in the object's poses" per object); the problems of a placement are generated in that scene.
    Ends are collision-free, aimed at the group's centroid and not boxed in (a short turn or drive leaves them,
    :func:`psprm_core.problems.can_move_away`).
    With ``placements=1`` every problem uses the targets' scene poses (placement 0).

    Raises
    ------
    PsprmError
        ``placements`` < 1, or a target of a group with fewer placements.
    """
    from ..problems import random_problems
    from ..collision import CollisionChecker
    from ..errors import PsprmError

    if placements < 1:
        raise PsprmError(f"placements must be at least 1, got {placements}")
    for g in groups:
        for t in g:
            if scene.target(t).n_placements < placements:
                raise PsprmError(f"target '{t}' of scene '{scene.name}' has {scene.target(t).n_placements} "
                                 f"placement(s), fewer than the {placements} asked for")
    cells = [(gi, k) for gi in range(len(groups)) for k in range(placements)]
    per = [n // len(cells) + (1 if i < n % len(cells) else 0) for i in range(len(cells))]
    pairs = []
    for (gi, k), m in zip(cells, per):
        if m == 0:
            pairs.append([])
            continue
        g = groups[gi]
        placed = scene.with_placement(g, k)
        checker = CollisionChecker(robot, placed.collision_boxes(), workspace=placed.workspace)
        focus = np.mean([placed.target(t).center for t in g], axis=0)
        rng = np.random.default_rng([seed, gi] if k == 0 else [seed, gi, k])
        pairs.append(random_problems(robot, placed, checker, m, rng, robot.default_configuration(), focus,
                                     aimed_only=True, aim_restarts=8, mobile_only=True))
    out, used = [], [0] * len(cells)
    for i in range(n):
        ci = i % len(cells)
        while used[ci] >= per[ci]:
            ci = (ci + 1) % len(cells)
        a, b = pairs[ci][used[ci]]
        used[ci] += 1
        gi, k = cells[ci]
        out.append({"index": i, "targets": list(groups[gi]), "placement": k, "start": np.asarray(a, float),
                    "goal": np.asarray(b, float)})
    return out


def scenario_problems(scene, robot, name: str, n: int, seed: int, targets: Optional[list] = None) -> list:
    """``n`` independent runs of the scene's named problem ``name`` (the paper's Table III protocol).

    Every run has the problem's start and (first) goal, with the camera joints aimed at the monitoring point of
    ``targets`` (default: the problem's own targets; their centroids' mean), as in :func:`make_problems`; run ``i``
    carries ``run_seed = seed + i``, the seed every planner is built with for that run.

    Raises
    ------
    PsprmError
        Unknown problem (the known names are listed), or a start or goal in collision.
    """
    from ..baselines.base import aim_camera
    from ..problems import aim_joints
    from ..collision import CollisionChecker
    from ..errors import PsprmError
    from ..planning.constraints import VisibilityConstraint
    from ..planning.factory import problem_configurations

    try:
        prob = scene.problem(name)
    except KeyError:
        known = ", ".join(p.name for p in scene.problems) or "none"
        raise PsprmError(f"scene '{scene.name}' has no problem '{name}' (problems: {known})") from None
    group = list(targets or prob.all_targets)
    focus = np.mean([scene.target(t).center for t in group], axis=0)
    start, goals = problem_configurations(robot, scene, prob)
    ends = np.stack([start, goals[0]])
    cols, lo, hi = aim_joints(robot)
    aimed, ok = aim_camera(VisibilityConstraint(robot, "line", focus), ends, cols, lo, hi, iters=10, restarts=8,
                           seed=seed)
    ends = np.asarray(aimed, float)  # unconverged: as close to the target as the joint limits allow
    import torch

    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    valid = checker.valid(torch.as_tensor(ends, dtype=torch.float32)).cpu().numpy()
    for which, v in zip(("start", "goal"), valid):
        if not v:
            raise PsprmError(f"problem '{name}' of scene '{scene.name}': the {which} is in collision")
    if not np.asarray(ok, bool).all():
        log.warning("problem '%s': the camera joints cannot face %s at the %s (aimed as close as the limits allow)",
                    name, "+".join(group), " and ".join(w for w, k in zip(("start", "goal"), ok) if not k))
    return [{"index": i, "targets": group, "start": ends[0].copy(), "goal": ends[1].copy(), "run_seed": seed + i,
             "scenario": name} for i in range(n)]


# ---- evaluation -------------------------------------------------------------------------------------------------------
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
    from ..perception.oracle import box_iou

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


# ---- workers ----------------------------------------------------------------------------------------------------------
ROW_FIELDS = ["planner", "problem", "run_seed", "targets", "placement", "success", "reason", "preprocess_s", "plan_s",
              "total_s", "path_length_rad", "frames", "det_rate", "det_rate_strict", "mean_confidence", "track_rate",
              "det_rate_any", "det_rate_all", "unseen_head", "unseen_tail", "route", "best_det_rate",
              "unseeable_frame_rate", "headroom", "eval_s"]


def _failure_row(planner: str, prob: dict, reason: str, preprocess_s: float = float("nan"),
                 plan_s: float = float("nan")) -> dict:
    row = {k: float("nan") for k in ROW_FIELDS}
    row.update(planner=planner, problem=int(prob["index"]), run_seed=prob.get("run_seed", float("nan")),
               targets="+".join(prob["targets"]), placement=int(prob.get("placement", 0)), success=False,
               reason=reason, preprocess_s=preprocess_s, plan_s=plan_s, total_s=preprocess_s + plan_s
               if not math.isnan(plan_s) else float("nan"), frames=0)
    return row


#: The pseudo-planner whose rows are each problem's best judged reference route
#: (:mod:`psprm_core.evaluation.headroom`), and the variant whose roadmap it searches (its ``--set`` settings apply to
#: the reference too).
REFERENCE = "reference"
REFERENCE_VARIANT = "neural-psprm-line"


def base_name(planner: str) -> str:
    """The registered planner of a bench entry: ``NAME~LABEL`` is planner NAME run under its own label (so one run can
    compare settings of one planner, each ``--set NAME~LABEL.KEY=VALUE``)."""
    return planner.split("~", 1)[0]


def _reference_row(ref, prob: dict, oracle, robot, motion, cfg: dict, placement: int, pre: float) -> dict:
    """The reference row of one problem: every candidate route of ``ref`` (:class:`~psprm_core.evaluation.headroom.
    ReferenceRoutes`) judged by the oracle; the row carries the best one's metrics (detection rate, then mean
    confidence), its label as ``route``, and the shortest unseen stretches at the start and the goal over all
    candidates."""
    from ..baselines.base import path_length

    t1 = time.perf_counter()
    try:
        cands = ref.routes(prob["start"], prob["goal"])
    except Exception as exc:
        log.error("reference routes failed on problem %d: %s", prob["index"], traceback.format_exc())
        return _failure_row(REFERENCE, prob, f"reference raised {type(exc).__name__}: {exc}", pre,
                            time.perf_counter() - t1)
    plan_s = time.perf_counter() - t1
    if not cands:
        return _failure_row(REFERENCE, prob, "no candidate route", pre, plan_s)
    t2 = time.perf_counter()
    judged = []
    for label, res in cands:
        ev = evaluate_path(oracle, robot, motion, np.asarray(res.dense, float), prob["targets"],
                           cfg["frame_spacing"], cfg["max_frames"])
        judged.append((label, res, ev))
    label, res, ev = max(judged, key=lambda x: (x[2]["det_rate"], x[2]["mean_confidence"]))
    row = {"planner": REFERENCE, "problem": int(prob["index"]), "run_seed": prob.get("run_seed", float("nan")),
           "targets": "+".join(prob["targets"]), "placement": placement, "success": True, "reason": "ok",
           "preprocess_s": pre, "plan_s": plan_s, "total_s": pre + plan_s,
           "path_length_rad": path_length(motion, res.dense), "eval_s": time.perf_counter() - t2,
           **{k: ev[k] for k in ev if k in ROW_FIELDS}, "route": f"{label} (best of {len(judged)})",
           "unseen_head": min(e["unseen_head"] for _, _, e in judged),
           "unseen_tail": min(e["unseen_tail"] for _, _, e in judged)}
    return row


def _worker_init() -> None:
    import torch

    torch.set_num_threads(1)


def _placed_scene(scene_name: str, targets: Sequence[str], placement: int) -> tuple:
    """(scene with the group's targets at ``placement``, robot, motion)."""
    from ..motion import DiffDriveMotion
    from ..paths import resolve_named
    from ..robot import RobotModel
    from ..scene import load_scene

    scene = load_scene(resolve_named("scene", scene_name)).with_placement(list(targets), placement)
    robot = RobotModel.load(scene.robot)
    return scene, robot, DiffDriveMotion(robot)


def run_task(planner: str, targets: list, problems: list, cfg: dict, q=None, keep_paths: int = 1,
             cache=None) -> dict:
    """Prepare one planner for one target group (at one placement) and run + evaluate its problems.

    ``cache`` (a :class:`psprm_core.executors.WorkerCache`): the worker's cache; the scene, the prepared planner
    (per planner, group, placement, build seed and settings) and the oracle come from it when an earlier task built
    them, so a worker prepares each planner instance once. Before each problem a planner that can (``reset``) goes
    back to the state its preparation left and numbers the query by the problem's index, so a row depends on the
    problem alone, not on the problems the worker planned before it. Without a cache everything is built for this
    call and released at its end.

    Rows go to the queue ``q`` as ``("row", row)`` as soon as they exist; ``("start", planner, index)`` announces a
    problem. Returns {"rows": [...], "paths": [...] (at most ``keep_paths`` successful paths), "prepares": [the
    preparation records of the instances built in this call]}.
    """
    import torch

    torch.set_num_threads(1)
    from ..baselines import make_baseline
    from ..executors import WorkerCache

    def emit(kind, payload):
        if q is not None:
            q.put((kind, payload))

    own_cache = cache is None
    cache = WorkerCache() if own_cache else cache
    rows, paths, prepares = [], [], []
    placement = {int(p.get("placement", 0)) for p in problems}
    if len(placement) > 1:
        raise InputError(f"one task, one placement: got {sorted(placement)}")
    placement = placement.pop() if placement else 0
    where = (cfg["scene"], tuple(targets), placement)
    scene, robot, motion = cache.get("scene", where, lambda: _placed_scene(*where))
    base = base_name(planner)
    reference = planner == REFERENCE
    kw = dict(cfg.get("planner_kwargs", {}).get(REFERENCE_VARIANT if reference else planner, {}))
    if reference or base.startswith(("psprm", "neural-psprm")):
        n = cfg.get("oracle_nodes") if base.startswith("psprm") and cfg.get("oracle_nodes") else cfg.get("nodes")
        if n:
            kw.setdefault("n_nodes", int(n))
    settings_key = json.dumps(kw, sort_keys=True, default=str)

    def build(seed: int) -> tuple:
        """(planner or None, prepare stats, preprocess seconds, error or None); a planner that cannot be built
        gives its error (cached like an instance, so that its other problems fail at once)."""
        t0 = time.perf_counter()
        try:
            if reference:
                from .headroom import ReferenceRoutes

                p = ReferenceRoutes(scene, targets, robot=robot, seed=seed, variant=REFERENCE_VARIANT, **kw)
            else:
                p = make_baseline(base, scene, targets, robot=robot, seed=seed, **kw)
            prep = dict(p.prepare())
        except Exception as exc:  # a planner that cannot be built: its problems fail
            log.error("%s could not be prepared: %s", planner, exc)
            err = f"prepare failed: {type(exc).__name__}: {exc}"
            prepares.append({"error": err})
            return None, {"error": err}, float("nan"), err
        prep.setdefault("preprocess_s", time.perf_counter() - t0)
        prepares.append({k: v for k, v in prep.items() if isinstance(v, (int, float, str, bool))})
        return p, prep, float(prep.get("preprocess_s", float("nan"))), None

    def oracle_of():
        from ..perception.oracle import Oracle

        return cache.get("oracle", where, lambda: Oracle(scene, intrinsics=robot.config.intrinsics),
                         close=lambda o: o.close())

    # one instance per build seed (the bench's seed, or in scenario runs the run's), built when first needed
    checker = None
    try:
        from ..collision import CollisionChecker

        for prob in problems:
            seed = int(prob.get("run_seed", cfg["seed"]))
            p, prep, pre, build_error = cache.get("planner", (planner, *where, seed, settings_key),
                                                  lambda: build(seed))
            if p is None:
                row = _failure_row(planner, prob, build_error)
                rows.append(row)
                emit("row", row)
                continue
            oracle = oracle_of()
            reset = getattr(p, "reset", None)
            if callable(reset):
                reset(int(prob["index"]))
            emit("start", (planner, int(prob["index"])))
            if reference:
                row = _reference_row(p, prob, oracle, robot, motion, cfg, placement, pre)
                rows.append(row)
                emit("row", row)
                continue
            t1 = time.perf_counter()
            try:
                res = p.plan(prob["start"], prob["goal"], timeout_s=cfg["timeout_s"])
            except Exception as exc:
                log.error("%s crashed on problem %d: %s", planner, prob["index"], traceback.format_exc())
                row = _failure_row(planner, prob, f"planner raised {type(exc).__name__}: {exc}", pre,
                                   time.perf_counter() - t1)
                rows.append(row)
                emit("row", row)
                continue
            plan_s = time.perf_counter() - t1
            claim = ""
            if res.success and res.dense is not None and len(res.dense):
                if checker is None:
                    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
                claim = verify_success(robot, checker, motion, prob["start"], prob["goal"], res.dense)
            if claim:
                log.error("%s claimed success on problem %d: %s", planner, prob["index"], claim)
                row = _failure_row(planner, prob, f"claimed success rejected: {claim}", pre, plan_s)
            elif not res.success or res.dense is None or len(res.dense) == 0:
                row = _failure_row(planner, prob, res.reason or "failed", pre, plan_s)
            else:
                from ..baselines.base import path_length

                t2 = time.perf_counter()
                try:
                    ev = evaluate_path(oracle, robot, motion, np.asarray(res.dense, float), prob["targets"],
                                       cfg["frame_spacing"], cfg["max_frames"])
                except Exception as exc:
                    log.error("evaluation failed: %s", traceback.format_exc())
                    ev = {"frames": 0, "det_rate": float("nan"), "mean_confidence": float("nan"),
                          "track_rate": float("nan"), "det_rate_any": float("nan"), "det_rate_all": float("nan"),
                          "eval_error": str(exc)}
                row = {"planner": planner, "problem": int(prob["index"]),
                       "run_seed": prob.get("run_seed", float("nan")),
                       "targets": "+".join(prob["targets"]), "placement": placement, "success": True, "reason": "ok",
                       "preprocess_s": pre,
                       "plan_s": plan_s, "total_s": pre + plan_s, "path_length_rad": path_length(motion, res.dense),
                       "eval_s": time.perf_counter() - t2, **{k: ev[k] for k in ev if k in ROW_FIELDS}}
                if len(paths) < keep_paths:
                    paths.append({"planner": planner, "problem": int(prob["index"]), "placement": placement,
                                  "dense": np.asarray(res.dense, float)[:, :3].tolist()})
            rows.append(row)
            emit("row", row)
    finally:
        if own_cache:
            cache.close()
    return {"rows": rows, "paths": paths, "prepares": prepares}


def bench_task(cache, planner: str, targets: list, problem: dict, cfg: dict, keep_path: bool) -> dict:
    """The executor's task: one planner on one problem (:func:`run_task` with the worker's cache)."""
    return run_task(planner, targets, [problem], cfg, keep_paths=int(keep_path), cache=cache)


# ---- driver -----------------------------------------------------------------------------------------------------------
def run_bench(cfg: BenchConfig, progress: bool = True, on_start=None) -> dict:
    """Run every planner of ``cfg`` on the same problems; returns {"rows", "summary", "paths", "problems", ...}.

    ``on_start(key, worker)``: called when the task ``key`` = (planner, problem index) is sent to a worker
    (``pid@host``; ``inline`` in this process)."""
    from ..baselines import BASELINES, planner_names
    from ..errors import PsprmError
    from ..paths import resolve_named
    from ..robot import RobotModel
    from ..scene import load_scene

    for name in cfg.planners:  # unknown names fail before any work; a missing module becomes failure rows
        if base_name(name) not in BASELINES or name == REFERENCE:
            raise PsprmError(f"unknown planner '{name}' (choose from {', '.join(BASELINES)}; NAME~LABEL runs "
                             "planner NAME under its own label)")
    scene = load_scene(resolve_named("scene", cfg.scene))
    robot = RobotModel.load(scene.robot)
    groups = cfg.target_groups or default_target_groups(scene)
    for g in groups:
        for t in g:
            if t not in scene.target_names:
                raise PsprmError(f"scene '{scene.name}' has no target '{t}' (targets: {', '.join(scene.target_names)})")
    t_start = time.perf_counter()
    if cfg.scenario:
        if cfg.target_groups and len(cfg.target_groups) != 1:
            raise PsprmError("--scenario takes one target group (e.g. --targets 'a,b'), not several")
        if cfg.placements != 1:
            raise PsprmError("--scenario runs the scene's problem as written: no --placements")
        problems = scenario_problems(scene, robot, cfg.scenario, cfg.problems, cfg.seed,
                                     cfg.target_groups[0] if cfg.target_groups else None)
        groups = [problems[0]["targets"]]
    else:
        problems = make_problems(scene, robot, groups, cfg.problems, cfg.seed, cfg.placements)
    by_group = {}  # one planner instance per planner, target group and placement (and run seed)
    for prob in problems:
        by_group.setdefault((tuple(prob["targets"]), int(prob.get("placement", 0))), []).append(prob)
    order = {n: i for i, n in enumerate(planner_names())}
    planners = sorted(dict.fromkeys(cfg.planners), key=lambda n: (order.get(base_name(n), 99), n))
    if cfg.reference:
        planners.append(REFERENCE)
    cfgd = {k: v for k, v in asdict(cfg).items() if k != "planners"}
    # one task per planner and problem; the slow preparations first (oracle roadmaps, RL training, the reference
    # routes) so they overlap with the rest
    slow = {"psprm-line": 0, "psprm-frustum": 0, "rl-ppo": 1, REFERENCE: 1}
    tasks = []
    for pl in sorted(planners, key=lambda n: slow.get(base_name(n), 2)):
        for (g, k), probs in by_group.items():
            for j, prob in enumerate(probs):
                tasks.append(BenchTask(pl, list(g), prob, keep_path=j < EXAMPLE_PATH_CANDIDATES))
    rows, paths, prepares = _run_tasks(tasks, cfgd, cfg, progress, planners, on_start=on_start)
    annotate_headroom(rows)
    summary = summarize(rows, planners)
    return {"config": {**cfgd, "planners": planners, "target_groups": groups}, "rows": rows, "summary": summary,
            "paths": paths, "prepare": prepares, "problems": problems, "wall_s": time.perf_counter() - t_start,
            "scene": scene, "robot": robot}


#: successful paths of the first problems of each planner instance kept for the example-path plot (the lowest
#: problem index among them is drawn)
EXAMPLE_PATH_CANDIDATES = 3
#: the row journal in the output directory: one JSON line per finished task after a header with the configuration
JOURNAL_FILE = "rows.jsonl"
#: configuration fields that do not change the rows (a run may resume with other values)
_RUN_ONLY_FIELDS = ("out", "workers", "backend", "address", "max_retries", "resume", "planners")


@dataclass(frozen=True)
class BenchTask:
    """One (planner, problem) task of a run."""

    planner: str
    targets: list
    problem: dict
    keep_path: bool = False

    @property
    def key(self) -> tuple:
        return (self.planner, int(self.problem["index"]))

    @property
    def affinity(self) -> tuple:
        """The planner instance the task needs (what a worker builds once and keeps)."""
        p = self.problem
        return (self.planner, tuple(self.targets), int(p.get("placement", 0)), p.get("run_seed"))


def backend_settings(cfg: BenchConfig):
    """The :class:`~psprm_core.executors.BackendSettings` of a run: ``workers`` <= 1 on the local backend runs the
    tasks in this process."""
    from ..executors import BackendSettings

    workers = cfg.workers
    if cfg.backend == "local" and workers is not None and workers <= 1:
        workers = 0
    return BackendSettings(backend=cfg.backend, workers=workers, address=cfg.address, max_retries=cfg.max_retries)


def _journal_header(cfgd: dict) -> dict:
    return json.loads(json.dumps({k: v for k, v in cfgd.items() if k not in _RUN_ONLY_FIELDS}, default=str))


def read_journal(out_dir: str | Path, cfgd: dict) -> list:
    """The task records of an earlier run of the same configuration in ``out_dir`` (``[]`` without a journal).

    Raises
    ------
    PsprmError
        The journal is of another configuration (the fields that differ are named).
    """
    from ..errors import PsprmError

    path = Path(out_dir) / JOURNAL_FILE
    if not path.is_file():
        return []
    want = _journal_header(cfgd)
    records = []
    with open(path) as fh:
        lines = fh.read().splitlines()
    if not lines:
        return []
    try:
        head = json.loads(lines[0]).get("config", {})
    except json.JSONDecodeError:
        raise PsprmError(f"{path}: not a bench journal (first line is not JSON)") from None
    if head != want:
        diff = sorted(k for k in set(head) | set(want) if head.get(k) != want.get(k))
        raise PsprmError(f"{path} is the journal of a run with another configuration (differs in: "
                         f"{', '.join(diff)}); use another --out, or run without --resume to start afresh")
    for i, line in enumerate(lines[1:], 2):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:  # a line cut short by an interruption: its task runs again
            log.warning("%s: line %d is incomplete; its task runs again", path, i)
    return records


def _run_tasks(tasks: list, cfgd: dict, cfg: BenchConfig, progress: bool, planners: Sequence[str],
               on_start=None) -> tuple:
    """Run the (planner, problem) tasks on the configured backend, journal every finished task in the output
    directory (``--resume`` skips those already journalled) and return (rows, example paths, prepare records).

    A task that fails as a whole (its worker died ``max_retries`` + 1 times, or it raised) becomes a failure row;
    such rows are journalled as failed tasks, which a resumed run runs again.
    """
    from tqdm import tqdm

    from ..executors import Executor, Task

    rows: dict = {}  # (planner, problem) -> row
    paths, prepares = [], []
    done = {}
    out = Path(cfg.out)
    if cfg.resume:
        for rec in read_journal(out, cfgd):
            key = (rec["row"]["planner"], int(rec["row"]["problem"]))
            if not rec.get("task_failed"):
                done[key] = rec
            else:
                done.pop(key, None)
    wanted = {t.key for t in tasks}
    for key, rec in done.items():
        if key in wanted:
            rows[key] = rec["row"]
            paths += rec.get("paths", [])
            prepares += rec.get("prepares", [])
    todo = [t for t in tasks if t.key not in rows]
    if cfg.resume:
        log.info("bench: %d of %d tasks already in %s; %d to run", len(rows), len(tasks), out / JOURNAL_FILE,
                 len(todo))
    out.mkdir(parents=True, exist_ok=True)
    journal_path = out / JOURNAL_FILE
    if not (cfg.resume and journal_path.is_file()):
        journal_path.write_text(json.dumps({"config": _journal_header(cfgd)}) + "\n")
    by_key = {t.key: t for t in todo}
    bar = tqdm(total=len(tasks), initial=len(rows), desc="bench", unit="plan", disable=not progress,
               dynamic_ncols=True)
    ex_tasks = [Task(t.key, bench_task, (t.planner, t.targets, t.problem, cfgd, t.keep_path), affinity=t.affinity)
                for t in todo]
    try:
        with open(journal_path, "a") as journal, Executor(backend_settings(cfg), init=_worker_init) as ex:
            for res in ex.run(ex_tasks, on_start=on_start):
                t = by_key[res.key]
                if res.ok:
                    value = res.value
                    rec = {"row": value["rows"][0], "paths": value["paths"], "prepares": [
                        {"planner": t.planner, "targets": t.targets, **_placement_of([t.problem]), **p}
                        for p in value["prepares"]]}
                else:
                    why = res.error.strip().splitlines()[-1] if res.error.strip() else "unknown error"
                    reason = (f"worker process died ({res.error})" if res.error.startswith("worker died")
                              else f"task failed: {why}")
                    log.error("bench task %s failed: %s", res.key, res.error)
                    rec = {"row": _failure_row(t.planner, t.problem, reason), "paths": [], "prepares": [],
                           "task_failed": True}
                rec["worker"], rec["attempts"] = res.worker, res.attempts
                journal.write(json.dumps(rec, default=_json_default) + "\n")
                journal.flush()
                rows[res.key] = rec["row"]
                paths += rec["paths"]
                prepares += rec["prepares"]
                bar.update(1)
                bar.set_postfix_str(t.planner)
    finally:
        bar.close()
    out_rows = sorted(rows.values(), key=lambda r: (r["planner"], r["problem"]))
    return out_rows, sorted(paths, key=lambda p: (p["planner"], p["problem"])), prepares


def _json_default(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def _placement_of(problems: list) -> dict:
    return {"placement": int(problems[0].get("placement", 0))} if problems else {}


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
