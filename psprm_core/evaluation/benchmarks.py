"""Benchmarks that print numbers (``psprm perf ...``). Ratios are always measured in the same process and run."""

from __future__ import annotations

import logging
import math
import time
from typing import Callable, Sequence

import numpy as np
import torch

from ..collision import CollisionChecker
from ..geometry import yaw_to_quat
from ..paths import config_dir, resolve_named
from ..perception.oracle import Oracle
from ..planning.factory import default_alpha, make_planner, make_scorer, problem_configurations
from ..planning.psprm import PSPRM, PSPRMSettings
from ..planning.replanner import Replanner, ReplanSettings
from ..problems import random_problems
from ..robot import RobotModel
from ..scene import load_scene
from .reference import PybulletWorld, sample_uniform
from .simulation import PersonMotion, person_pose

log = logging.getLogger(__name__)


def best_time(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` calls (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def rotation_angle_error(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (rad) of the relative rotation Ra^T Rb for stacks of rotations (..., 3, 3)."""
    rel = np.einsum("...ji,...jk->...ik", Ra, Rb)
    c = np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    # arccos is ill-conditioned near 0: use the skew part for small angles
    skew = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), c)


def kinematics_benchmark(robot_name: str, scene_name: str, n: int = 10000, seed: int = 0, threads: int = 2,
                         fk_check: int = 1000) -> dict:
    """Batched torch FK and collision checking against pybullet's exact check on the same ``n`` configurations.

    Configurations are uniform within joint limits, with the base uniform over the scene's workspace.
    Returns throughputs, their ratio, missed collisions (torch free but pybullet in collision: must be 0),
    the false-positive rate (torch in collision but pybullet free, over pybullet-free configurations) and the FK
    agreement with pybullet on ``fk_check`` configurations.
    """
    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(robot_name)
    boxes = scene.collision_boxes()
    rng = np.random.default_rng(seed)
    qs = sample_uniform(robot, n, rng, base_box=scene.workspace)
    checker = CollisionChecker(robot, boxes, workspace=None)
    q32 = torch.as_tensor(qs, dtype=torch.float32)

    def fk():
        poses = robot.body_poses(q32)
        return robot.camera_poses(q32, poses)

    t_fk = best_time(fk)
    t_col = best_time(lambda: checker.check(q32))
    flags = checker.check(q32).numpy()
    world = PybulletWorld(robot, boxes)
    try:
        t0 = time.perf_counter()
        ref = world.in_collision(qs)
        t_pb = time.perf_counter() - t0
        m = min(fk_check, n)
        cam = robot.camera_poses(q32[:m]).double().numpy()
        ref_cam = np.stack([world.camera_pose(q) for q in qs[:m]])
    finally:
        world.close()
    pos_err = float(np.abs(cam[:, :3, 3] - ref_cam[:, :3, 3]).max())
    rot_err = float(rotation_angle_error(cam[:, :3, :3], ref_cam[:, :3, :3]).max())
    missed = int(np.sum(ref & ~flags))
    free = int(np.sum(~ref))
    fp = int(np.sum(flags & ~ref))
    return {
        "robot": robot.name, "scene": scene.name, "n": n, "threads": threads, "device": "cpu",
        "collision_elements": int(len(robot.elements.element_link)), "self_pairs": int(checker.self_pairs.shape[0]),
        "fk_per_s": n / t_fk,
        "collision_per_s": n / t_col,
        "pybullet_collision_per_s": n / t_pb,
        "speedup": t_pb / t_col,
        "missed_collisions": missed,
        "false_positive_rate": fp / free if free else math.nan,
        "in_collision_fraction": float(ref.mean()),
        "fk_max_position_error_m": pos_err,
        "fk_max_rotation_error_rad": rot_err,
    }


def _built_planner(scene_name: str, planner: str, nodes: int, problems: int, seed: int, threads: int,
                   target: str | None, heuristic: str | None = None, aimed: bool = True,
                   overrides: dict | None = None) -> tuple:
    """Scene, robot, target name, built planner, its build stats and ``problems`` random (start, goal) pairs.

    ``aimed`` (default): both ends face the target, as in ``psprm bench`` (camera joints projected onto the
    line-of-sight manifold with restarts, unconverged configurations dropped). ``aimed=False``: the camera joints
    are only pushed towards the target from the default pose (10 Gauss-Newton steps, converged or not); on the mobile
    UR5, whose whole arm aims the wrist camera, 9 in 10 such ends then lie off the visibility manifold.
    ``overrides``: planner settings (as ``psprm bench --set``)."""
    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    target = target or (scene.problems[0].target if scene.problems else scene.target_names[0])
    p = make_planner(planner, scene, [target], robot=robot,
                     options={"roadmap.n_nodes": nodes, "seed": seed, "query.heuristic": heuristic,
                              **(overrides or {})})
    stats = p.build()
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    probs = random_problems(robot, scene, checker, problems, np.random.default_rng(seed + 1),
                            robot.default_configuration(), scene.target(target).center, aimed_only=aimed,
                            aim_restarts=8 if aimed else 0)
    return scene, robot, target, p, stats, probs


def planner_benchmark(scene_name: str, planner: str = "neural-psprm-line", nodes: int = 3000, queries: int = 50,
                      seed: int = 0, threads: int = 2, target: str | None = None, heuristic: str | None = None,
                      aimed: bool = True, overrides: dict | None = None) -> dict:
    """Build time (sampling, projection, collision, neural scoring with occlusion) and query times of PS-PRM;
    with route selection (``route_searches`` in ``overrides``) also the share of queries that returned another
    search's route (``other_route_rate``)."""
    scene, robot, target, p, stats, probs = _built_planner(scene_name, planner, nodes, queries, seed, threads, target,
                                                           heuristic, aimed=aimed, overrides=overrides)
    times, ok, scores, other = [], 0, [], 0
    own = f"{p.settings.scoring.objective}@{p.settings.scoring.alpha:g}"
    for a, b in probs:
        res = p.plan(a, b, timing=False)
        times.append(res.query_ms)
        ok += res.success
        if res.success:
            scores.append(res.mean_score)
            other += bool(res.route) and res.route != own
    return {
        "scene": scene.name, "planner": planner, "target": target, "threads": threads, "aimed": aimed,
        "heuristic": p.settings.query.heuristic, "n_nodes": stats.get("n_nodes"), "n_edges": stats.get("n_edges"),
        "build_s": stats.get("build_s"), "sample_s": stats.get("sample_s"), "edges_s": stats.get("edges_s"),
        "score_s": stats.get("score_s"), "warm_up_s": stats.get("warm_up_s"),
        "queries": len(probs), "success_rate": ok / len(probs),
        "query_ms": float(np.median(times)), "query_p95_ms": float(np.percentile(times, 95)),
        "mean_perception_score": float(np.mean(scores)) if scores else float("nan"),
        "route_searches": ",".join(map(str, p.settings.query.route_searches)), "other_route_rate": other / max(ok, 1),
    }


class _TimedScorer:
    """Wraps a scorer: counts the views it scores and the seconds spent in it (the planner sees the same scorer)."""

    def __init__(self, inner):
        self.inner, self.views, self.seconds = inner, 0, 0.0

    def score(self, cameras):
        t0 = time.perf_counter()
        out = self.inner.score(cameras)
        self.seconds += time.perf_counter() - t0
        self.views += int(cameras.shape[0])
        return out

    def __getattr__(self, name):
        return getattr(self.inner, name)


def preprocess_benchmark(scene_name: str = "home", target: str | None = None, nodes: int = 3000,
                         oracle_nodes: int = 30, seed: int = 0, threads: int = 2) -> dict:
    """Preprocessing of oracle-free (neural) PS-PRM against oracle PS-PRM (the paper's ~10x, Sec. V).

    Both variants build the same kind of roadmap with every edge scored at build time (Eq. 1 over both ends and the
    N interior samples; ``lazy_edges`` off): the neural scorer (surrogate + ray-cast occlusion) and the oracle
    (render + real detector). The oracle roadmap is built for real at ``oracle_nodes`` nodes and compared with a
    neural build of the same size (same seed, same node count: a measured ratio). At ``nodes`` the oracle build
    is extrapolated from the measured geometry time of the neural build plus the views it scored times the
    oracle's measured seconds per view.
    """

    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    target = target or (scene.problems[0].target if scene.problems else scene.target_names[0])
    base = PSPRMSettings.from_yaml(config_dir() / "planners" / "psprm.yaml", robot=robot.name)
    focus = scene.target(target).center

    def build(kind: str, n: int) -> dict:
        # the same uniform roadmap for both scorers (perception-biased sampling would score thousands of extra
        # oracle views)
        settings = base.changed({"visibility.constraint": "line",
                                 "scoring.alpha": default_alpha(base.scoring.objective, kind),
                                 "edges.lazy_edges": False, "roadmap.n_nodes": n, "seed": seed,
                                 "roadmap.expand_rounds": 0, "roadmap.biased_share": 0.0})
        scorer = _TimedScorer(make_scorer(kind, scene, [target], robot.config.intrinsics))
        p = PSPRM(robot, scene, scorer, focus, settings)
        st = p.build()
        if not st.get("success"):
            raise RuntimeError(f"{kind} roadmap of {n} nodes failed: {st.get('reason')}")
        return {"build_s": st["build_s"], "views": scorer.views, "scoring_s": scorer.seconds,
                "n_nodes": st["n_nodes"], "n_edges": st["n_edges"]}

    neural = build("neural", nodes)
    neural_small = build("neural", oracle_nodes)
    oracle_small = build("oracle", oracle_nodes)
    per_view = oracle_small["scoring_s"] / max(1, oracle_small["views"])
    oracle_full_est = neural["build_s"] - neural["scoring_s"] + neural["views"] * per_view
    return {
        "scene": scene.name, "target": target, "threads": threads, "nodes": nodes, "oracle_nodes": oracle_nodes,
        "neural_build_s": neural["build_s"], "neural_views": neural["views"], "neural_scoring_s": neural["scoring_s"],
        "neural_nodes": neural["n_nodes"], "neural_edges": neural["n_edges"],
        "small_oracle_nodes": oracle_small["n_nodes"],
        "small_neural_build_s": neural_small["build_s"], "small_oracle_build_s": oracle_small["build_s"],
        "small_oracle_views": oracle_small["views"], "small_edges": oracle_small["n_edges"],
        "oracle_s_per_view": per_view,
        "neural_s_per_view": neural["scoring_s"] / max(1, neural["views"]),
        "ratio_measured_small": oracle_small["build_s"] / max(neural_small["build_s"], 1e-9),
        "oracle_build_s_extrapolated": oracle_full_est,
        "ratio_extrapolated": oracle_full_est / max(neural["build_s"], 1e-9),
    }


def surrogate_transfer(scene_name: str = "home", target: str | None = None, samples: int = 200, nodes: int = 3000,
                       seed: int = 0, threads: int = 2,
                       distance_bins: tuple = (0.0, 1.5, 3.0, 5.0, float("inf")),
                       checkpoints: Sequence[str] = ()) -> dict:
    """Does the neural scorer rank the planner's own configurations like the real detector does?

    Builds the neural-psprm-line roadmap of the scene, draws ``samples`` of its nodes and scores their camera poses
    with the neural scorer (surrogate + ray casting, what the planner optimises) and with the oracle (render + real
    detector, what judges the paths). Reports Spearman's and Pearson's correlation overall and per camera-to-target
    distance bin, and both means. The surrogate's held-out test set is drawn around the target; this measures it on
    the distribution PS-PRM actually plans over (occluders, distances and headings of the scene).

    ``checkpoints``: further surrogate checkpoints scored on the same views against the same oracle labels (reported
    under ``checkpoints``, keyed by path), e.g. a studio-only and a fine-tuned surrogate side by side. ``views`` holds
    the per-view record (camera poses, neural and oracle scores) the correlations are computed from."""
    from scipy.stats import spearmanr

    scene, robot, target, p, stats, _ = _built_planner(scene_name, "neural-psprm-line", nodes, 0, seed, threads,
                                                       target)
    ids = p.roadmap_node_ids()
    sel = np.random.default_rng(seed).choice(ids, min(samples, len(ids)), replace=False)
    cams = robot.camera_poses(p.ctx.t(p.graph.configs[sel]))
    neural = p.scorer.score(cams).double().cpu().numpy()
    t0 = time.perf_counter()
    oracle = make_scorer("oracle", scene, [target], robot.config.intrinsics).score(cams).double().cpu().numpy()
    oracle_s = time.perf_counter() - t0
    dist = np.linalg.norm(cams[:, :3, 3].double().cpu().numpy() - scene.target(target).center, axis=1)

    def corr(a, b) -> dict:
        if len(a) < 4 or np.std(a) == 0 or np.std(b) == 0:
            return {"n": int(len(a)), "spearman": float("nan"), "pearson": float("nan")}
        return {"n": int(len(a)), "spearman": float(spearmanr(a, b).statistic),
                "pearson": float(np.corrcoef(a, b)[0, 1]), "neural_mean": float(a.mean()),
                "oracle_mean": float(b.mean())}

    def report(pred) -> dict:
        bins = []
        for lo, hi in zip(distance_bins[:-1], distance_bins[1:]):
            m = (dist >= lo) & (dist < hi)
            bins.append({"from_m": lo, "to_m": hi if np.isfinite(hi) else None, **corr(pred[m], oracle[m])})
        return {**corr(pred, oracle), "by_distance": bins}

    out = {"scene": scene.name, "target": target, "n_nodes": stats.get("n_nodes"), "samples": int(len(sel)),
           **report(neural), "oracle_s": oracle_s,
           "views": {"camera_poses": cams.double().cpu().numpy().tolist(), "neural": neural.tolist(),
                     "oracle": oracle.tolist()}}
    for ck in checkpoints:
        sc = make_scorer("neural", scene, [target], robot.config.intrinsics, checkpoint=ck)
        pred = sc.score(cams).double().cpu().numpy()
        out.setdefault("checkpoints", {})[str(ck)] = {**report(pred), "neural": pred.tolist()}
    return out


def oracle_path_metrics(oracle, robot, dense: np.ndarray, targets: list, frames: int = 12) -> dict:
    """Judge an executed path with the real detector: ``frames`` camera frames evenly spaced along ``dense``.

    Returns the mean confidence and the detection rate (frames at or above the detector's calibrated threshold),
    averaged over the targets (several targets: the nursing-style average), and the per-frame record: the frames'
    configurations and each target's scores of them.
    """
    idx = np.unique(np.linspace(0, len(dense) - 1, frames).round().astype(int))
    cams = robot.camera_poses(torch.as_tensor(dense[idx], dtype=torch.float64)).numpy()
    conf, det = [], []
    for t in targets:
        res = oracle.score_many(list(cams), t)
        conf.append([r.score for r in res])
        det.append([r.detected for r in res])
    return {"oracle_confidence": float(np.mean(conf)), "oracle_detection_rate": float(np.mean(det)),
            "frames": int(len(idx)), "frame_configs": dense[idx].tolist(), "frame_scores": conf}


def compare_with_shortest_path(scene_name: str, planner: str = "neural-psprm-line", nodes: int = 3000,
                               problems: int = 100, frames: int = 12, seed: int = 0, threads: int = 2,
                               target: str | None = None, oracle_problems: int | None = None,
                               aimed: bool = True) -> dict:
    """Success over random problems, and oracle-measured perception along the paths of PS-PRM
    vs. a plain shortest-path PRM on the same roadmap (alpha = 0, Eq. 2). Both search the roadmap alone: the
    path shortcuts are off, so the shortest-path paths are the roadmap's shortest. ``rows`` holds the per-problem
    record (start, goal, success, length, predicted score and the judged frames) the summaries are computed from."""

    scene, robot, target, p, stats, probs = _built_planner(scene_name, planner, nodes, problems, seed, threads,
                                                           target, aimed=aimed)
    alpha = p.settings.scoring.alpha
    oracle = Oracle(scene, intrinsics=robot.config.intrinsics)
    n_oracle = len(probs) if oracle_problems is None else min(oracle_problems, len(probs))
    rows = {"psprm": [], "shortest": []}
    try:
        for i, (a, b) in enumerate(probs):
            for key, al in (("psprm", alpha), ("shortest", 0.0)):
                p.set_alpha(al)
                res = p.plan(a, b, timing=False, options={"query.shortcut": False})  # this comparison is of the searches
                row = {"success": res.success, "length": res.path_length, "predicted": res.mean_score,
                       "start": np.asarray(a, float).tolist(), "goal": np.asarray(b, float).tolist()}
                if res.success and i < n_oracle:
                    row.update(oracle_path_metrics(oracle, robot, res.dense, [target], frames))
                rows[key].append(row)
    finally:
        oracle.close()
        p.set_alpha(alpha)

    def summary(rs):
        ok = [r for r in rs if r["success"]]
        judged = [r for r in ok if "oracle_confidence" in r]
        return {
            "success_rate": len(ok) / len(rs),
            "path_length": float(np.mean([r["length"] for r in ok])) if ok else float("nan"),
            "predicted_score": float(np.mean([r["predicted"] for r in ok])) if ok else float("nan"),
            "oracle_confidence": float(np.mean([r["oracle_confidence"] for r in judged])) if judged else float("nan"),
            "oracle_detection_rate": float(np.mean([r["oracle_detection_rate"] for r in judged]))
            if judged else float("nan"),
            "judged_paths": len(judged),
        }

    return {"scene": scene.name, "planner": planner, "target": target, "alpha": alpha, "aimed": aimed,
            "problems": len(probs),
            "frames_per_path": frames, "build_s": stats.get("build_s"), "n_nodes": stats.get("n_nodes"),
            "n_edges": stats.get("n_edges"), planner: summary(rows["psprm"]), "shortest_path_alpha0":
            summary(rows["shortest"]), "rows": rows}


def replan_benchmark(scene_name: str = "dynamic_person", planner: str = "neural-psprm-line", nodes: int = 3000,
                     updates: int = 50, seed: int = 0, threads: int = 2, target: str | None = None,
                     heuristic: str | None = None) -> dict:
    """Latency of (update + re-search until a verified path) for target, obstacle and goal moves
    on one roadmap, and the time a full re-score of every node and edge takes (what lazy evaluation avoids).

    * ``target_move``: the person (target + the obstacle it stands in, if any) turns to a random yaw within +-1.2 rad
      of its initial facing (the robot holds still at the start); ``target_move_moving_robot``: the same while the
      robot drives along its current plan (1/30 of it per update; back to the start every 10 updates);
    * ``obstacle_move``: a random piece of furniture (not a wall, not the person) moves by up to 0.6 m and 0.5 rad
      (moves that would put it onto the robot's start are redrawn);
    * ``goal_move``: a new random collision-free goal (base pose anywhere in the workspace, camera aimed).
    """
    import dataclasses

    torch.set_num_threads(threads)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    prob = scene.problems[0]
    target = target or prob.target
    p = make_planner(planner, scene, [target], robot=robot, options={"roadmap.n_nodes": nodes, "seed": seed})
    stats = p.build()
    rng = np.random.default_rng(seed + 7)
    start, goals = problem_configurations(robot, scene, prob)
    rs = ReplanSettings() if heuristic is None else ReplanSettings(heuristic=heuristic)
    rp = Replanner(p, rs, targets=[target])
    rp.set_robot_state(start)
    rp.set_goals(goals)
    first = rp.replan()
    tgt = scene.target(target)
    body = None
    for b in scene.obstacles:  # the obstacle the target is part of (a person's body), if any
        if np.all(np.abs(tgt.center[:2] - b.center[:2]) <= b.size[:2] / 2 + 0.1) and b.center[2] < tgt.center[2]:
            body = b.name
    motion = PersonMotion(target=target, body=body)
    yaw0 = float(np.arctan2(tgt.rotation[1, 0], tgt.rotation[0, 0]))
    movable = [b.name for b in scene.obstacles if not b.name.startswith("wall") and b.name != body]
    out = {"scene": scene.name, "planner": planner, "target": target, "threads": threads,
           "heuristic": rp.plan_options.get("query.heuristic", p.settings.query.heuristic), "n_nodes": stats.get("n_nodes"),
           "n_edges": stats.get("n_edges"), "build_s": stats.get("build_s"), "first_plan_ms": first.query_ms, "updates": updates}

    def timed(kind: str, update) -> None:
        times, ok = [], 0
        for i in range(updates):
            t0 = time.perf_counter()
            update(i)
            r = rp.replan()
            times.append((time.perf_counter() - t0) * 1e3)
            ok += r.success
        out[kind] = {"median_ms": float(np.median(times)), "p95_ms": float(np.percentile(times, 95)),
                     "success_rate": ok / updates}

    def turn(i):
        pp = person_pose(scene, motion, yaw0 + rng.uniform(-1.2, 1.2))
        rp.update_target(target, *pp["target"])
        if body:
            rp.update_obstacle(body, *pp["body"])

    timed("target_move", turn)
    # the same with the robot driving along its current plan between updates (the start's query edges, and with them
    # their knots, are new on every replan; the robot returns to the start every 10 updates)
    def turn_while_driving(i):
        if i % 10 == 0:
            rp.set_robot_state(start)
        elif rp.result is not None and rp.result.dense is not None and len(rp.remaining()) > 1:
            rem = rp.remaining()
            rp.set_robot_state(rem[min(len(rem) - 1, max(1, len(rp.result.dense) // 30))])
        turn(i)

    timed("target_move_moving_robot", turn_while_driving)
    rp.set_robot_state(start)
    start_checker = CollisionChecker(robot, [], workspace=None)
    q_start = torch.as_tensor(start[None], dtype=torch.float32)

    def shift(i):
        for _ in range(50):
            name = movable[int(rng.integers(len(movable)))]
            b0 = scene.obstacle(name)
            c = b0.center + np.r_[rng.uniform(-0.6, 0.6, 2), 0.0]
            yaw = float(np.arctan2(b0.rotation[1, 0], b0.rotation[0, 0])) + rng.uniform(-0.5, 0.5)
            moved = dataclasses.replace(b0, center=c, quat=yaw_to_quat(yaw))
            start_checker.set_boxes([moved])
            if not bool(start_checker.check(q_start)[0]):
                break
        rp.update_obstacle(name, c, yaw_to_quat(yaw))

    timed("obstacle_move", shift)
    goal_pool = random_problems(robot, rp.scene, p.checker, updates, rng, robot.default_configuration(),
                                tgt.center)

    def new_goal(i):
        rp.set_goals(goal_pool[i][1])

    timed("goal_move", new_goal)
    # what lazy evaluation avoids: every node and every edge's N interior configurations scored after a move
    pp = person_pose(scene, motion, yaw0 + 0.7)
    p.set_scene(p.scene.with_target_pose(target, *pp["target"]))
    t0 = time.perf_counter()
    full = p.rescore(full=True)
    out["full_rescore_cold_ms"] = (time.perf_counter() - t0) * 1e3  # incl. FK of edge interiors never scored yet
    pp = person_pose(scene, motion, yaw0 + 0.3)
    p.set_scene(p.scene.with_target_pose(target, *pp["target"]))
    t0 = time.perf_counter()
    full = p.rescore(full=True)
    out["full_rescore_ms"] = (time.perf_counter() - t0) * 1e3  # every camera pose cached: scorer only
    out["full_rescore_edges"] = full["edges"]
    pp = person_pose(scene, motion, yaw0 - 0.7)
    p.set_scene(p.scene.with_target_pose(target, *pp["target"]))
    lazy = p.rescore(full=False)
    out["lazy_rescore_ms"] = lazy["total_ms"]
    out["speedup_lazy_vs_full_rescore"] = out["full_rescore_ms"] / max(lazy["total_ms"], 1e-9)
    return out
