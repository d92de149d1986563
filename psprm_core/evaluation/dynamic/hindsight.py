"""The dynamic headroom (mode ``hindsight`` of :func:`~psprm_core.evaluation.simulation.run_episode`): how well a
single route of the episode's roadmap sees the target when it is executed unchanged against the target's actual
motion, the best of several such routes being the reference a replanning robot is measured against.

From the episode's start, candidate routes of the same roadmap (a fresh copy of the one every mode starts from) lead
to every goal the scenario names at some time. Like the bench's reference routes
(:class:`~psprm_core.evaluation.headroom.ReferenceRoutes`) they come from the planner's own searches with other
objectives and alpha, and from alternatives found with the edges of the routes found so far penalised; each is timed
with the planner's timing (:meth:`~psprm_core.planning.query.trajectory.Trajectory.timed`). The roadmap is scored once
with the world at t = 0, and once more with hindsight (``variants``): the people where they are halfway through the
first plan's duration and the moving obstacles where they end up. The first plan (the static mode's route) is a
candidate too. Each candidate is executed unchanged from t = 0 on the control clock (:func:`~.episodes.execute_fixed`);
it is valid when it arrives at a goal valid at its arrival and no executed configuration touches the world as it was at
that instant (:func:`~.episodes.count_collisions`); the oracle judges the valid ones, and the best detection rate
(then mean confidence) among them is the reference. With ``judged`` = K > 0 the oracle judges only the first plan
and the K other valid candidates that the planner's own scorer (the surrogate, with occlusion) rates best along
their camera frames against the actual motion (:func:`predicted_perception`): a cheaper reference, which can only
be lower than the full one.
"""

from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np

from ...errors import PsprmError
from ...planning.replanner import Replanner
from ..scenario_world import World, goal_configurations
from .episodes import FrameJudge, count_collisions, detection_metrics, execute_fixed, frames_of, judge_record

log = logging.getLogger(__name__)

#: The candidate searches per goal and planning scene: ``own`` (the planner's objective and alpha),
#: ``objective@alpha``, ``alt`` (motion-weighted at alpha 1, the edges of the routes found before weighted ``PENALTY``
#: times).
SEARCHES = "own,motion@1.0,eq2@0.8,alt"
#: The planning scenes: ``start`` (the world at t = 0), ``mid`` (people halfway through the first plan, moving
#: obstacles at their final poses).
VARIANTS = "start,mid"
PENALTY = 3.0


def parse_searches(text: str) -> list:
    """``"own,motion@1.0,alt"`` -> [("own", None), ("motion", 1.0), ("alt", None)]; a bad entry is a PsprmError."""
    out = []
    for item in (s.strip() for s in str(text).split(",")):
        if not item:
            continue
        if item in ("own", "alt"):
            out.append((item, None))
            continue
        objective, _, alpha = item.partition("@")
        try:
            a = float(alpha)
        except ValueError:
            a = float("nan")
        if objective not in ("eq2", "motion") or not 0.0 <= a <= 1.0:
            raise PsprmError(f"hindsight search '{item}': expected own, alt or OBJECTIVE@ALPHA (eq2 or motion, alpha "
                             "in [0, 1])")
        out.append((objective, a))
    if not out:
        raise PsprmError("hindsight searches: at least one entry is needed")
    return out


def parse_variants(text: str) -> list:
    out = [s.strip() for s in str(text).split(",") if s.strip()]
    bad = [v for v in out if v not in ("start", "mid")]
    if bad or not out:
        raise PsprmError(f"hindsight variants: expected 'start' and/or 'mid', got {text!r}")
    return out


def candidate_routes(planner, start: np.ndarray, goals: np.ndarray, searches: Sequence[tuple],
                     options: Optional[dict] = None, penalty: float = PENALTY) -> list:
    """Timed routes ``[(label, PlanResult), ...]`` from ``start`` to each of ``goals`` (G, dof) on the planner's
    roadmap as it is scored now (:data:`SEARCHES`). The planner's objective, alpha and weights are restored
    afterwards (as :meth:`~psprm_core.evaluation.headroom.ReferenceRoutes.routes` does)."""
    saved = planner.settings.scoring
    opts = {**(options or {}), "query.shortcut": False, "query.route_searches": ()}
    out, used = [], []
    try:
        for gi, goal in enumerate(np.atleast_2d(goals)):
            for objective, alpha in searches:
                if objective == "alt":
                    planner.reweight(alpha=1.0, objective="motion")
                    g = planner.graph
                    e = np.unique(np.asarray([x for x in used if g.edge_valid[x]], dtype=np.int64))
                    if len(e):
                        g.set_weights(e, g.weights[e] * penalty)
                    label = "alt"
                elif objective == "own":
                    planner.reweight(alpha=saved.alpha, objective=saved.objective)
                    label = f"{saved.objective}@{saved.alpha:g}"
                else:
                    planner.reweight(alpha=alpha, objective=objective)
                    label = f"{objective}@{alpha:g}"
                res = planner.plan(start, goal, timing=False, options=opts)
                if not res.success or res.waypoints is None or len(res.waypoints) < 2:
                    continue
                res.trajectory = planner.pipeline.trajectory.timed(res.waypoints)
                used.extend(planner.path_roadmap_edges(res.path_nodes).tolist())
                out.append((f"goal{gi}:{label}", res))
    finally:
        planner.reweight(alpha=saved.alpha, objective=saved.objective)
    return out


def predicted_perception(planner, world: World, scenario, records: list) -> list:
    """The planner's own prediction (its scorer: the surrogate with occlusion, normalised as c_p in Eq. 1) of each
    executed record's camera frames (:func:`~.episodes.frames_of`), every frame scored with the world as it was at
    that instant; the mean per record. Changes the planner's scene."""
    import torch

    frames = [frames_of(r, scenario) for r in records]
    by_t: dict = {}
    for i, (ts, qs) in enumerate(frames):
        for t, q in zip(ts, qs):
            by_t.setdefault(round(float(t), 6), []).append((i, q))
    sums, counts = np.zeros(len(records)), np.zeros(len(records))
    for t, items in sorted(by_t.items()):
        planner.set_scene(world.scene_at(t))
        sc = planner.normalized_scores(planner.score_configs(torch.as_tensor(np.stack([q for _, q in items]),
                                                                             dtype=torch.float32))).double().numpy()
        for (i, _), v in zip(items, sc):
            sums[i] += v
            counts[i] += 1
    return [float(s / c) if c else 0.0 for s, c in zip(sums, counts)]


def run_hindsight(scenario, world: World, planner, rp_settings, start: np.ndarray, aim, first_traj=None,
                  judge: Optional[FrameJudge] = None, searches: str = SEARCHES, variants: str = VARIANTS,
                  judged: int = 0) -> dict:
    """Mode ``hindsight`` (module docstring) on ``planner`` (a fresh copy of the episode's roadmap, changed here).
    ``judged``: oracle-judge only the first plan and the ``judged`` best valid candidates by
    :func:`predicted_perception` (0: every valid candidate).

    Returns ``{"candidates": [{label, variant, reached_goal, collision_steps, valid, duration_s, judged, det_rate,
    ...}], "best": the best judged candidate's executed record (or None), "n_valid"}``; without a ``judge`` (the
    oracle) nothing is ranked and ``best`` is None."""
    import dataclasses

    robot = planner.robot
    settings = dataclasses.replace(rp_settings, prediction=dataclasses.replace(rp_settings.prediction,
                                                                                 enabled=False))
    rp = Replanner(planner, settings, targets=list(scenario.targets))
    specs = world.all_goal_specs()
    goals = goal_configurations(robot, world.scene0, specs, start, aim)
    search_list = parse_searches(searches)
    routes, seen = [], set()

    def add(label: str, variant: str, traj) -> None:
        key = np.round(np.asarray(traj.waypoints, float), 4).tobytes()
        if key not in seen:
            seen.add(key)
            routes.append((label, variant, traj))

    if first_traj is not None:
        add("first_plan", "start", first_traj)
    half = 0.5 * float(first_traj.duration) if first_traj is not None else 0.0
    for k, variant in enumerate(parse_variants(variants)):
        t = 0.0 if variant == "start" else half
        poses = world.poses(t)
        for name, (c, q) in poses["targets"].items():
            rp.update_target(name, c, q, stamp=float(k))
        for name, (c, q) in poses["obstacles"].items():
            if name in scenario.obstacles and variant == "mid":
                c, q = world.obstacle_pose(name, max(kf.t for kf in scenario.obstacles[name]))
            rp.update_obstacle(name, c, q, stamp=float(k))
        rp.set_robot_state(start)
        rp.set_goals(goals)
        first = rp.replan(now=float(k))  # syncs the roadmap with these poses (re-scored, re-checked)
        if not first.success:
            log.info("hindsight: no route in the %s scene (%s)", variant, first.reason)
            continue
        for label, res in candidate_routes(planner, start, goals, search_list, rp.plan_options):
            add(label, variant, res.trajectory)
    rows, recs = [], []
    for label, variant, traj in routes:
        rec = execute_fixed(traj, scenario, world, robot)
        hits = count_collisions(robot, world, rec["times"], rec["executed"])
        rec.update(label=label, variant=variant, trajectory=traj, collision_steps=int(hits.sum()))
        valid = bool(rec["reached_goal"] and not hits.any())
        rows.append({"label": label, "variant": variant, "reached_goal": rec["reached_goal"],
                     "collision_steps": rec["collision_steps"], "valid": valid, "duration_s": float(traj.duration),
                     "judged": False})
        recs.append(rec)
    valid = [i for i, r in enumerate(rows) if r["valid"]]
    chosen = list(valid)
    if judge is not None and judged > 0 and len(valid) > judged + 1:
        pred = predicted_perception(planner, world, scenario, [recs[i] for i in valid])
        for i, v in zip(valid, pred):
            rows[i]["predicted"] = v
        others = sorted((i for i in valid if rows[i]["label"] != "first_plan"), key=lambda i: -rows[i]["predicted"])
        chosen = [i for i in valid if rows[i]["label"] == "first_plan"] + others[:judged]
    best, best_key = None, None
    if judge is not None:
        for i in chosen:
            judge_record(recs[i], judge, scenario)
            rows[i].update(judged=True, **detection_metrics(recs[i]))
            key = (rows[i]["det_rate"], rows[i]["mean_confidence"])
            if best_key is None or key > best_key:
                best, best_key = recs[i], key
    return {"candidates": rows, "best": best, "n_valid": len(valid)}
