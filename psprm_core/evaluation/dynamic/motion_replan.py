"""``psprm perf replan-motion``: what replanning a robot in motion costs, with and without target prediction and the
routes of the predicted headings.

The replanner on a built roadmap of ``dynamic_person``; the person turns side to side as in the shipped recording
(dwelling at each side, 20 s a cycle, poses at 30 Hz); the robot follows its trajectory and every 0.5 s replans from
its committed state (:mod:`psprm_core.planning.execution`) with a view trigger. Rounds alternate the variants,
each from the same saved roadmap, so that all see the same load: prediction off (``off``), prediction with the
search of the extrapolated pose alone (``prediction``, the shipped settings), the same without the periodic
component (``no_period``: ``prediction.period_window_s`` 0), and prediction with the routes of the other predicted
headings (``predicted_routes``). ``history_s`` of the person's poses come before the first plan: with a turn of
``turn_period_s`` and more than about 1.6 periods of history, the predictor has found the turn's period and the
``prediction`` variant scores each stretch of a path at the periodic component's heading. Reports, per round, the
median time of the remaining path's predicted score (the trigger evaluation) and of the replan (commitment, search,
splice, keep decision), and how many replans were adopted.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ...errors import InputError
from ...geometry import yaw_to_quat
from ...paths import resolve_named
from ...planning.factory import make_planner, problem_configurations
from ...planning.replanner import Replanner, ReplanSettings
from ...scene import load_scene

log = logging.getLogger(__name__)


VARIANTS = ("off", "prediction", "no_period", "predicted_routes")


def _yaw(t: float, period_s: float = 20.0) -> float:
    """The shipped recording's heading profile (``psprm_ros.interfaces.recordings.person_turning``'s defaults: a
    20 s period)."""
    return -math.pi / 2 - (math.pi / 2) * math.tanh(1.5 * math.cos(2 * math.pi * t / period_s)) / math.tanh(1.5)


def _settings(base: ReplanSettings, variant: str) -> ReplanSettings:
    pred = dataclasses.replace(base.prediction, enabled=variant != "off")
    if variant == "no_period":
        pred = dataclasses.replace(pred, period_window_s=0.0)
    return dataclasses.replace(base, prediction=pred, predicted_routes=variant == "predicted_routes")


def motion_replan_benchmark(nodes: int = 3000, replans: int = 30, rounds: int = 2, seed: int = 0,
                            threads: int = 1, history_s: float = 4.0, turn_period_s: float = 20.0,
                            variants: tuple = VARIANTS) -> dict:
    if not (history_s > 0 and turn_period_s > 0):
        raise InputError(f"history_s and turn_period_s must be > 0, got {history_s}, {turn_period_s}")
    for v in variants:
        if v not in VARIANTS:
            raise InputError(f"unknown variant {v!r}; one of {', '.join(VARIANTS)}")
    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    planner = make_planner("neural-psprm-line", scene, ["person_face"],
                           options={"roadmap.n_nodes": nodes, "seed": seed})
    planner.build()
    start, goals = problem_configurations(planner.robot, scene, scene.problem("south_to_either"))
    face = scene.target("person_face")
    base = ReplanSettings.from_yaml(resolve_named("planner", "replan"))
    out = {"nodes": nodes, "replans": replans, "history_s": history_s, "turn_period_s": turn_period_s, "rounds": []}
    yaw = lambda t: _yaw(t, turn_period_s)  # noqa: E731
    t_first = history_s
    with tempfile.TemporaryDirectory() as tmp:
        saved = planner.save(Path(tmp) / "roadmap.npz")
        for r in range(rounds):
            for variant in variants:
                planner.set_scene(scene)
                planner.load(saved, check=False)
                rp = Replanner(planner, _settings(base, variant), targets=["person_face"])
                for k in range(int(round(history_s * 30))):
                    rp.update_target("person_face", face.center, yaw_to_quat(yaw(k / 30)), stamp=k / 30)
                rp.set_robot_state(start)
                rp.set_goals(goals)
                res = rp.replan(now=t_first)
                traj, t0, score_ms, replan_ms = res.trajectory, t_first, [], []
                for k in range(replans):
                    t = t_first + 0.5 * k
                    for j in range(15):
                        tt = t - 0.5 + j / 30
                        if tt > t_first - 1.0 / 60:  # the history before the first plan was fed above
                            rp.update_target("person_face", face.center, yaw_to_quat(yaw(tt)), stamp=tt)
                    ta = min(t - t0, traj.duration)
                    rp.set_robot_state(traj.evaluate([ta])[0][0], t_along=ta)
                    a = time.perf_counter()
                    rp.path_score(normalized=True)
                    b = time.perf_counter()
                    res = rp.replan(now=t, triggers=["score_drop"], horizon_s=0.4)
                    c = time.perf_counter()
                    score_ms.append((b - a) * 1e3)
                    replan_ms.append((c - b) * 1e3)
                    if res.success and not res.kept:
                        traj, t0 = res.trajectory, t
                period = rp.predictors["person_face"].period() if "person_face" in rp.predictors else None
                out["rounds"].append({"variant": variant, "period_s": None if period is None else float(period[0]),
                                      "path_score_ms_median": float(np.median(score_ms)),
                                      "replan_ms_median": float(np.median(replan_ms)),
                                      "replan_ms_p95": float(np.percentile(replan_ms, 95)),
                                      "adopted": rp.adopted - 1, "declined": rp.declined})
    return out
