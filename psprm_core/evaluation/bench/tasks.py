"""The rows of ``psprm bench`` and the task a worker runs: one planner prepared for one target group and placement,
its problems planned and their executed paths judged (:func:`run_task`, :func:`bench_task`); the reference rows of
the best judged routes (:data:`REFERENCE`)."""

from __future__ import annotations

import json
import logging
import math
import time
import traceback
from typing import Sequence

import numpy as np

from ...baselines import make_baseline
from ...baselines.base import path_length
from ...collision import CollisionChecker
from ...errors import InputError
from ...executors import WorkerCache
from ...motion import DiffDriveMotion
from ...paths import resolve_named
from ...perception.oracle import Oracle
from ...robot import RobotModel
from ...scene import load_scene
from ..headroom import ReferenceRoutes
from .paths import evaluate_path, verify_success

log = logging.getLogger(__name__)


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
        return cache.get("oracle", where, lambda: Oracle(scene, intrinsics=robot.config.intrinsics),
                         close=lambda o: o.close())

    # one instance per build seed (the bench's seed, or in scenario runs the run's), built when first needed
    checker = None
    try:
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
