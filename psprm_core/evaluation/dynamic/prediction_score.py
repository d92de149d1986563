"""How well :class:`~psprm_core.prediction.TargetPredictor` forecasts the people of the shipped scenarios.

Each scenario's people move as its keyframes (or its recording) say, varied per episode
(:func:`~..scenarios.draw_variation`, the same variations as the dynamic benchmark for the same seed and episode
indices). The predictor is fed their target poses
at ``rate_hz`` (a mocap stream) and asked, every ``every_s``, for the predicted pose at the horizons ``horizons``;
each forecast is judged against the pose the target then has:

* **heading**: the continuous ranked probability score of the predicted mixture on the circle,
  ``CRPS = E|Y - y| - E|Y - Y'| / 2`` (``Y``, ``Y'`` drawn from the mixture, ``y`` the true heading, distances the
  shorter way round). A proper score: lower is better, and a mixture whose spread matches its error scores better
  than an over- or under-confident one. For a single pose it is the absolute heading error;
* **position**: the distance (xy) between the mixture's mean position and the true one.

``psprm perf prediction`` prints both per scenario and horizon, for the shipped settings, the latest pose alone
(prediction off) and, with ``--change``, changed settings.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ...errors import InputError
from ...geometry import wrap_angle
from ...paths import resolve_named
from ...prediction import PredictionSettings, TargetPredictor, quat_yaw
from ...scene import load_scene
from ..scenario_world import World
from ..scenarios import draw_variation, load_scenario

DEFAULT_SCENARIOS = ("rotating_person", "walking_person", "nursing_turning_walking")


def circular_crps(weights: Sequence[float], yaws: Sequence[float], truth: float) -> float:
    """CRPS of a discrete heading mixture (weights summing to 1, headings in rad) at the true heading ``truth``, with
    angular distances (module docstring)."""
    w = np.asarray(weights, float)
    y = np.asarray(yaws, float)
    if w.shape != y.shape or w.ndim != 1 or len(w) == 0 or not np.isclose(w.sum(), 1.0):
        raise InputError("a mixture needs as many weights as headings, summing to 1")
    e1 = float(w @ np.abs(wrap_angle(y - truth)))
    e2 = float(w @ np.abs(wrap_angle(y[:, None] - y[None, :])) @ w)
    return e1 - 0.5 * e2


def prediction_scores(variants: Mapping[str, PredictionSettings], scenarios: Sequence[str] = DEFAULT_SCENARIOS,
                      episodes: Sequence[int] = (0, 1, 2, 3, 4), horizons: Sequence[float] = (1.0, 2.0, 4.0, 8.0),
                      seed: int = 0, rate_hz: float = 30.0, every_s: float = 0.5, warm_up_s: float = 2.0,
                      max_duration_s: float = 60.0) -> dict:
    """Mean heading CRPS and position error per variant, scenario and horizon (module docstring), and each
    variant's mean over the scenarios and horizons. ``variants``: name -> settings."""
    if not variants or not scenarios or not episodes or not horizons:
        raise InputError("prediction_scores needs variants, scenarios, episodes and horizons")
    horizons = [float(h) for h in horizons]
    out = {"horizons_s": horizons, "episodes": [int(e) for e in episodes], "seed": int(seed), "rate_hz": rate_hz,
           "every_s": every_s, "variants": {}}
    acc = {v: {} for v in variants}
    for name in scenarios:
        sc = load_scenario(resolve_named("scenario", name))
        scene = load_scene(resolve_named("scene", sc.scene))
        yaw = {v: {h: [] for h in horizons} for v in variants}
        pos = {v: {h: [] for h in horizons} for v in variants}
        T = min(float(sc.duration_s), max_duration_s)
        every = max(1, int(round(every_s * rate_hz)))
        for ep in episodes:  # one pose stream per episode, fed to every variant's predictors
            world = World(sc, scene, None, draw_variation(sc, int(ep), seed))
            targets = [p.target for p in world.people] + [b for b, (kind, _) in world.recorded.items()
                                                          if kind == "target"]
            if not targets:
                raise InputError(f"scenario {name} has no people to predict")
            preds = {v: {t: TargetPredictor(settings, t) for t in targets} for v, settings in variants.items()}
            for k, t in enumerate(np.arange(0.0, T, 1.0 / rate_hz)):
                now = world.poses(float(t))["targets"]
                for v in variants:
                    for tg in targets:
                        preds[v][tg].add(float(t), *now[tg])
                if k % every or t < warm_up_s:
                    continue
                for h in horizons:
                    if t + h > T:
                        continue
                    later = world.poses(float(t + h))["targets"]
                    for v in variants:
                        for tg in targets:
                            mix = preds[v][tg].mixture(float(t + h))
                            yaw[v][h].append(circular_crps([m[0] for m in mix], [quat_yaw(m[2]) for m in mix],
                                                           quat_yaw(np.asarray(later[tg][1]))))
                            mean_p = sum(m[0] * m[1] for m in mix)
                            pos[v][h].append(float(np.linalg.norm((mean_p - np.asarray(later[tg][0]))[:2])))
        for v in variants:
            acc[v][name] = {"yaw_crps_rad": [float(np.mean(yaw[v][h])) for h in horizons],
                            "position_error_m": [float(np.mean(pos[v][h])) for h in horizons],
                            "forecasts": sum(len(yaw[v][h]) for h in horizons)}
    for v in variants:
        rows = acc[v]
        out["variants"][v] = {"scenarios": rows,
                              "mean_yaw_crps_rad": float(np.mean([np.mean(r["yaw_crps_rad"]) for r in rows.values()])),
                              "mean_position_error_m": float(np.mean([np.mean(r["position_error_m"])
                                                                      for r in rows.values()]))}
    return out


def format_table(res: dict) -> str:
    """The scores as a text table: one row per variant and scenario."""
    hs = ", ".join(f"{h:g}" for h in res["horizons_s"])
    lines = [f"heading CRPS (rad) and position error (m) at {hs} s; episodes {res['episodes']}"]
    for v, r in res["variants"].items():
        for name, s in r["scenarios"].items():
            lines.append(f"{v:12s} {name:26s} heading " + " ".join(f"{x:5.2f}" for x in s["yaw_crps_rad"])
                         + "  position " + " ".join(f"{x:5.2f}" for x in s["position_error_m"]))
        lines.append(f"{v:12s} {'mean':26s} heading {r['mean_yaw_crps_rad']:.3f}  position "
                     f"{r['mean_position_error_m']:.3f}")
    return "\n".join(lines)
