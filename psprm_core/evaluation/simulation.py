"""Dynamic episodes in simulated time: a scenario (:mod:`.scenarios`) moves the people, obstacles and goals on a
timeline while the robot executes its plan at its velocity limits, the
:class:`~psprm_core.planning.replanner.Replanner` replans as its triggers say, and every camera frame along the
executed motion is judged by the oracle (the real detector).

Modes of an episode (:func:`run_episode`; every mode of an episode sees the same world timeline and starts from the
same roadmap, a copy loaded from one build):

``motion``
    Replanning in motion with target prediction (:mod:`psprm_core.planning.execution`): the robot's time along its
    trajectory goes to :meth:`~psprm_core.planning.replanner.Replanner.set_robot_state`, every pose is stamped with
    the simulated time, and a replan keeps the trajectory under way up to its first rest instant at or after
    ``now + latency``; the spliced trajectory continues exactly where the robot is (its time 0 is
    ``res.start_offset_s`` along the old one). A replan of a robot at rest starts there after the latency.
``motion_no_prediction``
    The same with :attr:`~psprm_core.prediction.PredictionSettings.enabled` off.
``from_rest``
    ``commit`` off, as the replanner worked before: a new plan starts from the robot's state at rest, so the robot
    stops where it is when one is adopted, waits the replan latency at rest, then executes the new trajectory from its
    start (one stop per adopted replan of a moving robot).
``static``
    The first plan executed unchanged (no replanning).
``hindsight``
    The dynamic headroom (:mod:`.hindsight`): the best of several routes of the same roadmap executed unchanged
    against the actual motion, judged by the oracle.

The replan latency (``latency_s``, default 0.3 s) is the replanner's commit horizon in the motion modes and the wait
at rest of ``from_rest``; replans themselves take no simulated time. Executed configurations in collision are counted
against the world as it was at each instant (:func:`~.episodes.count_collisions`), moving boxes included.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import PsprmError
from ..motion import DiffDriveMotion
from ..paths import resolve_named
from ..perception.oracle import Oracle
from ..planning.constraints import ProjectionSettings
from ..planning.execution import SplicedTrajectory
from ..planning.factory import make_planner
from ..planning.replanner import Replanner, ReplanSettings
from ..planning.results import Keep
from ..prediction import quat_yaw
from ..robot import RobotModel
from ..scene import load_scene
from ..yamlio import replace_settings
from .dynamic.episodes import (FrameJudge, count_collisions, count_self_collisions, detection_metrics, execute_fixed,
                               frame_every, frames_of, json_safe, judge_record, speed_ratio, wrap_heading)
from .dynamic.hindsight import SEARCHES, VARIANTS, run_hindsight
from .scenario_world import World, at_goal, goal_configurations
from .scenarios import (Keyframe, MotionVariation, PersonMotion, PoseKeyframe, Scenario, draw_variation,
                        load_scenario, person_pose)
from .viz import plot_scene_top

__all__ = ["MODES", "REPLANNING_MODES", "DEFAULT_LATENCY_S", "run_episode", "mode_settings", "judge_frames",
           "summarize", "plot_episodes", "simulate", "json_safe",
           # re-exported from .scenarios and .scenario_world
           "Keyframe", "MotionVariation", "PersonMotion", "PoseKeyframe", "Scenario", "World", "draw_variation",
           "goal_configurations", "load_scenario", "person_pose"]

MODES = ("motion", "motion_no_prediction", "from_rest", "static", "hindsight")
REPLANNING_MODES = ("motion", "motion_no_prediction", "from_rest")
#: planning and delivery of a replan (s): the motion modes' commit horizon, the wait of ``from_rest``
DEFAULT_LATENCY_S = 0.3


def mode_settings(mode: str, base):
    """The :class:`~psprm_core.planning.replanner.ReplanSettings` of a mode, from the run's ``base`` settings."""
    if mode not in MODES:
        raise PsprmError(f"unknown mode '{mode}' (choose from {', '.join(MODES)})")
    if mode == "motion_no_prediction":
        return dataclasses.replace(base, prediction=dataclasses.replace(base.prediction, enabled=False))
    if mode == "from_rest":
        return dataclasses.replace(base, commit=False)
    return base


def _aimer(planner):
    def aim(Q: np.ndarray) -> np.ndarray:
        if len(planner.track_cols) == 0:
            return Q
        qt = torch.as_tensor(Q, dtype=torch.float32)
        out, ok = planner.constraint.project(qt, ProjectionSettings(max_iters=15), *planner.joint_bounds,
                                             joints=planner.track_cols)
        ok &= planner.checker.valid(out)  # keep the given joints where aiming fails or collides
        return torch.where(ok[:, None], out, qt).double().numpy()

    return aim


def _angle_gap(a: np.ndarray, b: np.ndarray, robot) -> float:
    d = np.abs(np.asarray(a, float) - np.asarray(b, float))
    if robot.mobile:
        d[2] = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
    return float(d.max())


def run_episode(scenario: Scenario, mode: str = "motion", planner=None, oracle=None, progress=None,
                replan_settings=None, latency_s: float = DEFAULT_LATENCY_S, variation: Optional[dict] = None,
                replanning: Optional[bool] = None, judge: Optional[FrameJudge] = None,
                hindsight_searches: Optional[str] = None, hindsight_variants: Optional[str] = None,
                hindsight_judged: int = 0, history_s: float = 0.0) -> dict:
    """Execute one episode in ``mode`` (:data:`MODES`, the module docstring) on ``planner`` (a built or loaded
    roadmap that the episode changes; default: built from the scenario). ``variation``: the episode's
    ``{target: MotionVariation}`` (:func:`~.scenarios.draw_variation`). ``replanning=False`` is ``mode="static"``
    (the former flag). ``oracle`` / ``judge`` (a :class:`~.episodes.FrameJudge` of this episode's world, shared by its
    modes): judge the camera frames. ``hindsight_*``: the candidates of mode ``hindsight``
    (:func:`~.hindsight.run_hindsight`). ``history_s``: seconds of the world's poses, one per control step, given
    to the replanner before the first plan (a motion-capture stream that runs before the goal is given; the same in
    every mode).

    Returns a dict with the executed configurations on the control clock (``times``, ``executed``), the camera frames
    (``frames_t``, ``frames_q``, ``frames_scene``: the poses sent at those instants) and, when judged, ``detected`` /
    ``confidence`` (frames x targets); the replanning log and counters (``adopted``, ``declined``, ``goal_switches``,
    ``stops``, ``failed_replans``), ``adoptions`` (each adopted replan: the old and new trajectory, their time
    origins), ``waits`` (the stops' waits at rest), ``reached_goal`` / ``arrival_s``, ``first_plan_s``,
    ``collision_steps``, ``max_jump`` and summary inputs (see :func:`summarize`)."""
    if replanning is not None and not replanning:
        mode = "static"
    if not (math.isfinite(latency_s) and latency_s >= 0):
        raise PsprmError(f"replan latency must be a finite time >= 0 s, got {latency_s}")
    if not (math.isfinite(history_s) and history_s >= 0):
        raise PsprmError(f"history must be a finite time >= 0 s, got {history_s}")
    settings = mode_settings(mode, replan_settings or ReplanSettings())
    scene = load_scene(resolve_named("scene", scenario.scene))  # the scenario's world, as the file has it
    if planner is None:
        planner = make_planner(scenario.planner, scene, list(scenario.targets), robot=RobotModel.load(scene.robot),
                               options={"roadmap.n_nodes": scenario.nodes, "seed": scenario.seed})
        planner.build()
    robot = planner.robot
    world = World(scenario, scene, robot, variation)
    if judge is None and oracle is not None:
        judge = FrameJudge(oracle, robot, world, scenario.targets)
    aim = _aimer(planner)
    start = aim(robot.configuration(scenario.start)[None])[0]
    rp = Replanner(planner, settings, targets=list(scenario.targets))

    def apply_world(t: float) -> dict:
        poses = world.poses(t)
        for name, (c, q) in poses["targets"].items():
            rp.update_target(name, c, q, stamp=t)
        for name, (c, q) in poses["obstacles"].items():
            rp.update_obstacle(name, c, q, stamp=t)
        return poses

    for k in range(int(round(history_s / scenario.control_dt)), 0, -1):  # the stream before the goal is given
        apply_world(-k * scenario.control_dt)
    poses0 = apply_world(0.0)
    specs = world.goal_specs(0.0)
    rp.set_robot_state(start)
    rp.set_goals(goal_configurations(robot, scene, specs, start, aim))
    first = rp.replan(now=0.0)
    traj = first.trajectory if first.success else None
    out = {"mode": mode, "latency_s": float(latency_s),
           "variation": {k: v.as_dict() for k, v in world.variation.items()},
           "first_plan_s": float(traj.duration) if traj is not None else None, "first_plan_ms": first.query_ms,
           "latencies_ms": [first.query_ms], "replans": [], "adoptions": [], "waits": [], "stops": 0,
           "failed_replans": 0 if first.success else 1, "max_jump": 0.0, "scene": scene, "robot": robot,
           "planner": planner, "replanner": rp, "world": world, "start": start}
    if mode == "static":
        rec = execute_fixed(traj, scenario, world, robot, start=start)
        k = frame_every(scenario)
        rec["frames_scene"] = [world.poses(float(t)) for t in rec["times"][::k]]
        out.update(rec)
    elif mode == "hindsight":
        h = run_hindsight(scenario, world, planner, settings, start, aim, first_traj=traj, judge=judge,
                          searches=hindsight_searches or SEARCHES, variants=hindsight_variants or VARIANTS,
                          judged=hindsight_judged)
        best = h["best"]
        rec = best if best is not None else {"times": np.zeros(1), "executed": start[None].copy(),
                                             "reached_goal": False, "arrival_s": None}
        out.update(rec)
        out.update(candidates=h["candidates"], n_valid=h["n_valid"], route=best["label"] if best else None)
        out["frames_scene"] = [world.poses(float(t)) for t in frames_of(out, scenario)[0]]
    else:
        out.update(_replanning_loop(scenario, world, rp, settings, traj, start, specs, aim, latency_s, poses0,
                                    progress))
        out["failed_replans"] += out.pop("replan_failures")
        out["latencies_ms"] += [e["ms"] for e in out["replans"]]
    out["collision_steps"] = int(count_collisions(robot, world, out["times"], out["executed"]).sum())
    out["self_collision_steps"] = int(count_self_collisions(robot, out["executed"]).sum())
    out["speed_ratio"] = speed_ratio(out["times"], out["executed"], robot)
    out["sim_time_s"] = float(out["times"][-1])
    # the first plan is not a replan
    out["adopted"] = rp.adopted - (1 if first.success else 0) if mode in REPLANNING_MODES else 0
    out["declined"] = rp.declined if mode in REPLANNING_MODES else 0
    # of those, kept because the new plan would have arrived beyond the arrival budget
    out["declined_late"] = rp.declined_by.get(Keep.LATE, 0) if mode in REPLANNING_MODES else 0
    out["goal_switches"] = rp.goal_switches if mode in REPLANNING_MODES else 0
    out["n_plans"] = (1 if first.success else 0) + out["adopted"]
    out["kept_replans"] = out["declined"]
    if judge is not None and mode != "hindsight":
        judge_record(out, judge, scenario)
    elif "frames_t" not in out:
        out["frames_t"], out["frames_q"] = frames_of(out, scenario)
    return out


def _replanning_loop(scenario, world, rp, settings, traj, start, specs, aim, latency_s, poses0, progress) -> dict:
    """The control loop of the replanning modes (module docstring): the world moves, the robot follows its
    trajectory (``traj``'s time origin ``t0``), the triggers are evaluated every control step and a replan is
    adopted as its mode says."""
    robot, scene = rp.robot, world.scene0
    dt = scenario.control_dt
    k_frame = frame_every(scenario)
    t0, q = 0.0, start.copy()
    times, executed, frames_scene = [0.0], [q.copy()], [poses0]
    log, adoptions, waits = [], [], []
    stops = failures = 0
    max_jump, reached, arrival, t = 0.0, False, None, 0.0
    for step in range(1, int(math.floor(scenario.duration_s / dt + 1e-9)) + 1):
        t = round(step * dt, 9)
        poses = world.poses(t)
        for name, (c, qq) in poses["targets"].items():
            rp.update_target(name, c, qq, stamp=t)
        for name, (c, qq) in poses["obstacles"].items():
            rp.update_obstacle(name, c, qq, stamp=t)
        new_specs = world.goal_specs(t)
        if new_specs != specs:
            specs = new_specs
            rp.set_goals(goal_configurations(robot, rp.scene, specs, q, aim))
        if traj is not None:
            q = wrap_heading(traj.evaluate(t - t0)[0][0], robot)
            rp.set_robot_state(q, t_along=max(0.0, t - t0))
        else:
            rp.set_robot_state(q)
        times.append(t)
        executed.append(q.copy())
        if step % k_frame == 0:
            frames_scene.append(poses)
        tau = t - t0
        if (traj is None or tau >= traj.duration - 1e-9) and at_goal(q, scene, specs, scenario.goal_tolerance):
            reached, arrival = True, t
            break
        why = rp.needs_replan(now=t)
        if why:
            moving = traj is not None and 0.0 < tau < traj.duration
            r = rp.replan(now=t, triggers=why, horizon_s=latency_s if settings.commit else None)
            log.append({"t": t, "reasons": why, "success": r.success, "reason": r.reason, "ms": r.query_ms,
                        "kept": r.kept, "spliced": isinstance(r.trajectory, SplicedTrajectory)})
            if r.kept:
                pass
            elif r.success:
                if isinstance(r.trajectory, SplicedTrajectory):
                    new_t0 = t0 + r.start_offset_s
                else:  # from rest: the robot stops where it is and waits while the plan is made and delivered
                    new_t0 = t + latency_s
                    stops += int(moving)
                    waits.append((t, new_t0))
                adoptions.append({"t": t, "old": traj, "old_t0": t0, "new": r.trajectory, "new_t0": new_t0,
                                  "spliced": isinstance(r.trajectory, SplicedTrajectory),
                                  "start_offset_s": r.start_offset_s, "committed_s": r.committed_s})
                if r.trajectory is not None:
                    max_jump = max(max_jump, _angle_gap(r.trajectory.evaluate(t - new_t0)[0][0], q, robot))
                traj, t0 = r.trajectory, new_t0
            else:
                failures += 1
                if rp.result is None:  # no safe plan: stop where we are
                    stops += int(moving)
                    traj = None
        if progress is not None:
            progress(t)
    return {"times": np.asarray(times), "executed": np.asarray(executed), "frames_scene": frames_scene,
            "replans": log, "adoptions": adoptions, "waits": waits, "stops": stops, "replan_failures": failures,
            "max_jump": max_jump, "reached_goal": reached, "arrival_s": arrival}


def judge_frames(ep: dict, oracle, target=None) -> None:
    """Oracle confidence and detection of every recorded camera frame of ``ep`` with the world as it was at that time
    (``detected`` / ``confidence``: frames x targets); ``target``: a name or names (default: the scenario's)."""
    targets = [target] if isinstance(target, str) else list(target or ep["world"].sc.targets)
    judge = FrameJudge(oracle, ep["robot"], ep["world"], targets)
    ep["detected"], ep["confidence"] = judge.judge(ep["frames_t"], ep["frames_q"])


def summarize(ep: dict) -> dict:
    """Summary numbers of an episode (the keys of ``psprm simulate --json``; None where a number does not exist)."""
    ex = ep["executed"]
    motion = DiffDriveMotion(ep["robot"])
    length = float(motion.distance(torch.as_tensor(ex[:-1]), torch.as_tensor(ex[1:])).sum()) if len(ex) > 1 else 0.0
    lat = np.asarray(ep["latencies_ms"][1:] if len(ep["latencies_ms"]) > 1 else [], dtype=float)
    first = ep.get("first_plan_s")
    out = {"mode": ep.get("mode"), "n_plans": int(ep["n_plans"]), "adopted": int(ep.get("adopted", 0)),
           "kept_replans": int(ep.get("kept_replans", 0)), "goal_switches": int(ep.get("goal_switches", 0)),
           "stops": int(ep.get("stops", 0)), "failed_replans": int(ep["failed_replans"]),
           **detection_metrics(ep), "path_length_rad": length, "reached_goal": bool(ep["reached_goal"]),
           "time_s": float(ep["sim_time_s"]), "first_plan_s": first,
           "time_ratio": (ep["arrival_s"] / first) if ep.get("arrival_s") is not None and first else None,
           "collision_steps": int(ep["collision_steps"]), "self_collision_steps": ep.get("self_collision_steps"),
           "frames": int(len(ep["frames_t"])),
           "speed_ratio": ep.get("speed_ratio"), "max_jump": ep.get("max_jump"),
           "first_plan_ms": float(ep["latencies_ms"][0]) if ep["latencies_ms"] else None,
           "replan_ms_median": float(np.median(lat)) if len(lat) else None,
           "replan_ms_p95": float(np.percentile(lat, 95)) if len(lat) else None,
           "replan_ms_max": float(lat.max()) if len(lat) else None}
    return json_safe(out)


def plot_episodes(episodes: dict, scenario: Scenario, path: str | Path) -> Path:
    """Top view with each executed path coloured by time and the people's facing over time, plus the oracle
    confidence (mean over the targets) over time per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [1.2, 1]})
    any_ep = next(iter(episodes.values()))
    plot_scene_top(ax, any_ep["scene"])
    cmaps = ["viridis", "autumn", "winter", "spring", "cool"]
    sc = None
    for i, (label, ep) in enumerate(episodes.items()):
        ex = ep["executed"]
        sc = ax.scatter(ex[:, 0], ex[:, 1], c=ep["times"], cmap=cmaps[i % len(cmaps)], s=6, label=label)
        conf = ep.get("confidence")
        ax2.plot(ep["frames_t"], conf.mean(1) if conf is not None and len(conf) else np.zeros(len(ep["frames_t"])),
                 label=label)
    if sc is not None:
        fig.colorbar(sc, ax=ax, label="time (s)")
    frames = any_ep.get("frames_scene") or []
    for p in scenario.people:
        for poses in frames[:: max(1, len(frames) // 12)]:
            c, q = poses["targets"][p.target]
            yaw = quat_yaw(q)
            ax.arrow(c[0], c[1], 0.5 * math.cos(yaw), 0.5 * math.sin(yaw), head_width=0.08, color="k", alpha=0.4)
    ax.legend(loc="upper right")
    ax.set_title(f"{scenario.name}: executed paths (colour = time), people's facing (arrows)")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("oracle confidence")
    ax2.set_ylim(0, 1)
    ax2.legend()
    ax2.set_title("perception along the executed motion")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def simulate(scenario_path: str | Path, compare_static: bool = True, plot: Optional[str | Path] = None,
             threads: int = 2, nodes: Optional[int] = None, duration_s: Optional[float] = None,
             planner_overrides: Optional[dict] = None, replan_overrides: Optional[dict] = None,
             mode: str = "motion", latency_s: float = DEFAULT_LATENCY_S) -> dict:
    """``psprm simulate``: run the scenario (as written, no episode variation) in ``mode`` (a replanning mode), and a
    static single plan on the same timeline from the same roadmap; judge both with the oracle; return the summary
    (strict JSON values: None, never NaN) and write the figure. ``planner_overrides``: settings of the scenario's
    planner; ``replan_overrides``: :class:`~psprm_core.planning.replanner.ReplanSettings` fields (both episodes use
    them: the static one for its single plan)."""
    import tempfile

    if mode not in REPLANNING_MODES:
        raise PsprmError(f"simulate runs a replanning mode ({', '.join(REPLANNING_MODES)}), not '{mode}'")
    torch.set_num_threads(threads)
    sc = load_scenario(scenario_path)
    if nodes is not None:
        sc = dataclasses.replace(sc, nodes=nodes)
    if duration_s is not None:
        sc = dataclasses.replace(sc, duration_s=duration_s)
    t0 = time.perf_counter()
    scene = load_scene(resolve_named("scene", sc.scene))
    robot = RobotModel.load(scene.robot)

    def fresh():
        return make_planner(sc.planner, scene, list(sc.targets), robot=robot,
                            options={"roadmap.n_nodes": sc.nodes, "seed": sc.seed, **(planner_overrides or {})})

    rs = replace_settings(ReplanSettings(), replan_overrides)  # names or dotted paths (prediction.revert_s)
    planner = fresh()
    build_s = planner.build().get("build_s")
    oracle = Oracle(scene, intrinsics=robot.config.intrinsics)
    try:
        with tempfile.TemporaryDirectory() as tmp:  # the static run gets an untouched copy of the same roadmap
            saved = planner.save(Path(tmp) / "roadmap.npz")
            ep = run_episode(sc, mode=mode, planner=planner, replan_settings=rs, latency_s=latency_s)
            judge = FrameJudge(oracle, robot, ep["world"], sc.targets)
            judge_record(ep, judge, sc)
            episodes = {mode: ep}
            if compare_static:
                p2 = fresh()
                p2.load(saved)
                episodes["static"] = run_episode(sc, mode="static", planner=p2, replan_settings=rs, judge=judge)
    finally:
        oracle.close()
    out = {"scenario": sc.name, "scene": sc.scene, "planner": sc.planner, "nodes": sc.nodes, "build_s": build_s,
           "mode": mode, "latency_s": latency_s, "planner_overrides": dict(planner_overrides or {}),
           "replan_overrides": dict(replan_overrides or {})}
    out.update(summarize(ep))
    out["replan_log"] = ep["replans"]
    if compare_static:
        out["static"] = summarize(episodes["static"])
    out["wall_s"] = time.perf_counter() - t0
    if plot:
        out["plot"] = str(plot_episodes(episodes, sc, plot))
    return json_safe(out)
