"""Dynamic episodes in simulated time: a scenario moves the person, obstacles and goals on a timeline while the robot
executes its plan at its velocity limits, the :class:`~psprm_core.planning.replanner.Replanner` replans as its
triggers say, and every camera frame along the executed motion is judged by the oracle (the real detector).

Scenario files (``config/scenarios/<name>.yaml``)::

    name: rotating_person
    scene: dynamic_person
    planner: neural-psprm-line        # any PS-PRM variant
    nodes: 3000
    seed: 0
    target: person_face
    start: {base_x: 4.0, base_y: 0.7, base_theta: 1.5708}   # planning-joint values (others: robot default)
    goals: [at_shelf, at_cabinet]     # goal-region names, or {base: [x, y, theta]} entries
    duration_s: 60                    # give up after this much simulated time
    control_dt: 0.1                   # robot state / trigger period (s)
    camera_fps: 4                     # oracle frames per simulated second
    person:                           # the person turns side to side: yaw(t) = yaw0 + amplitude * sin(2 pi t / period)
      target: person_face
      body: person_body               # obstacle that turns with the face (optional)
      amplitude_rad: 1.2
      period_s: 12
    obstacles:                        # keyframes per obstacle, linearly interpolated (held before/after)
      cabinet: [{t: 0, center: [7.75, 3.2, 0.5]}, {t: 6, center: [7.75, 2.0, 0.5], yaw: 0.0}]
    goal_changes:                     # the goal set changes at time t
      - {t: 6, goals: [{base: [6.9, 2.0, 0.0]}]}
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import ConfigError
from ..geometry import yaw_to_quat
from ..yamlio import Fields, load_yaml

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PersonMotion:
    target: str
    body: Optional[str] = None
    amplitude_rad: float = 1.0
    period_s: float = 12.0
    phase_rad: float = 0.0
    yaw0: Optional[float] = None  # default: the scene's initial yaw of the target


@dataclass(frozen=True)
class Keyframe:
    t: float
    center: np.ndarray
    yaw: Optional[float] = None


@dataclass(frozen=True)
class Scenario:
    name: str
    scene: str
    target: str
    start: dict
    goals: tuple
    planner: str = "neural-psprm-line"
    nodes: int = 3000
    seed: int = 0
    duration_s: float = 60.0
    control_dt: float = 0.1
    camera_fps: float = 4.0
    goal_tolerance: float = 0.1  # m (base) / rad (other joints, max abs) to count as arrived
    person: Optional[PersonMotion] = None
    obstacles: dict = field(default_factory=dict)  # name -> tuple of Keyframe
    goal_changes: tuple = ()  # ((t, goals), ...)
    source: str = ""


def _list(f: Fields, key: str) -> list:
    v = f.raw(key, [])
    if not isinstance(v, list):
        raise f.error(key, "expected a list")
    return v


def _goal_spec(f: Fields, item, where: str):
    if isinstance(item, str):
        return item
    if isinstance(item, dict) and "base" in item:
        b = item["base"]
        if not (isinstance(b, list) and len(b) == 3 and all(isinstance(x, (int, float)) for x in b)):
            raise ConfigError(f.source, where, "goal 'base' must be [x, y, theta]")
        return tuple(float(x) for x in b)
    raise ConfigError(f.source, where, "a goal is a goal-region name or {base: [x, y, theta]}")


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML (errors name the file and the field)."""
    f = Fields(load_yaml(path), str(path))
    f.check_keys(["name", "description", "scene", "planner", "nodes", "seed", "target", "start", "goals", "duration_s",
                  "control_dt", "camera_fps", "goal_tolerance", "person", "obstacles", "goal_changes"])
    goals = _list(f, "goals")
    if not goals:
        raise ConfigError(str(path), "goals", "at least one goal is needed")
    person = None
    if f.has("person"):
        pf = f.sub("person")
        pf.check_keys(["target", "body", "amplitude_rad", "period_s", "phase_rad", "yaw0"])
        person = PersonMotion(target=pf.str("target"), body=pf.str("body") if pf.has("body") else None,
                              amplitude_rad=pf.float("amplitude_rad", 1.0), period_s=pf.float("period_s", 12.0, lo=1e-3),
                              phase_rad=pf.float("phase_rad", 0.0),
                              yaw0=pf.float("yaw0", lo=None) if pf.has("yaw0") else None)
    obstacles = {}
    if f.has("obstacles"):
        of = f.sub("obstacles")
        for name in of.data:
            frames = []
            for i, kf in enumerate(_list(of, name)):
                where = f"obstacles.{name}[{i}]"
                if not isinstance(kf, dict) or "t" not in kf or "center" not in kf:
                    raise ConfigError(str(path), where, "a keyframe needs 't' and 'center'")
                c = np.asarray(kf["center"], dtype=float)
                if c.shape != (3,) or not np.isfinite(c).all():
                    raise ConfigError(str(path), where + ".center", "must be 3 finite numbers")
                frames.append(Keyframe(float(kf["t"]), c, None if kf.get("yaw") is None else float(kf["yaw"])))
            obstacles[name] = tuple(sorted(frames, key=lambda k: k.t))
    changes = []
    for i, ch in enumerate(_list(f, "goal_changes")):
        if not isinstance(ch, dict) or "t" not in ch or "goals" not in ch:
            raise ConfigError(str(path), f"goal_changes[{i}]", "needs 't' and 'goals'")
        changes.append((float(ch["t"]), tuple(_goal_spec(f, g, f"goal_changes[{i}].goals") for g in ch["goals"])))
    start = f.data.get("start")
    if not isinstance(start, dict):
        raise ConfigError(str(path), "start", "expected a mapping of planning-joint values")
    return Scenario(
        name=f.str("name"), scene=f.str("scene"), target=f.str("target"), start=dict(start),
        goals=tuple(_goal_spec(f, g, f"goals[{i}]") for i, g in enumerate(goals)),
        planner=f.str("planner", "neural-psprm-line"), nodes=f.int("nodes", 3000, lo=2), seed=f.int("seed", 0),
        duration_s=f.float("duration_s", 60.0, lo=0.1), control_dt=f.float("control_dt", 0.1, lo=1e-3),
        camera_fps=f.float("camera_fps", 4.0, lo=0.01), goal_tolerance=f.float("goal_tolerance", 0.1, lo=1e-4),
        person=person, obstacles=obstacles, goal_changes=tuple(sorted(changes, key=lambda c: c[0])),
        source=str(path))


# ---- world timeline ----------------------------------------------------------------------------------------------
def person_pose(scene, motion: PersonMotion, yaw: float) -> dict:
    """Poses of the person's face target (and body obstacle) turned to ``yaw`` about the body's vertical axis.

    The face keeps its offset from the body centre (rotated with the body). Returns
    ``{"target": (center, quat), "body": (center, quat) or None}``."""
    face0 = scene.target(motion.target)
    if motion.body:
        body0 = scene.obstacle(motion.body)
        pivot = body0.center
    else:
        body0, pivot = None, face0.center
    yaw_face0 = math.atan2(face0.rotation[1, 0], face0.rotation[0, 0])
    d = yaw - yaw_face0
    c, s = math.cos(d), math.sin(d)
    off = face0.center - pivot
    face_c = pivot + np.array([c * off[0] - s * off[1], s * off[0] + c * off[1], off[2]])
    out = {"target": (face_c, yaw_to_quat(yaw)), "body": None}
    if body0 is not None:
        yaw_b0 = math.atan2(body0.rotation[1, 0], body0.rotation[0, 0])
        out["body"] = (body0.center.copy(), yaw_to_quat(yaw_b0 + d))
    return out


class World:
    """The scenario's time-varying scene: ``at(t)`` gives the target/obstacle poses and goal set at time t."""

    def __init__(self, scenario: Scenario, scene, robot):
        self.sc, self.scene0, self.robot = scenario, scene, robot
        for name in scenario.obstacles:
            scene.obstacle(name)  # clear error for unknown names
        if scenario.person:
            scene.target(scenario.person.target)
            if scenario.person.body:
                scene.obstacle(scenario.person.body)
        p = scenario.person
        if p is not None:
            t0 = scene.target(p.target)
            self.yaw0 = p.yaw0 if p.yaw0 is not None else math.atan2(t0.rotation[1, 0], t0.rotation[0, 0])

    def person_yaw(self, t: float) -> float:
        p = self.sc.person
        return self.yaw0 + p.amplitude_rad * math.sin(2 * math.pi * t / p.period_s + p.phase_rad)

    def obstacle_pose(self, name: str, t: float) -> tuple:
        frames = self.sc.obstacles[name]
        b = self.scene0.obstacle(name)
        yaw_init = math.atan2(b.rotation[1, 0], b.rotation[0, 0])
        if t <= frames[0].t:
            k = frames[0]
            return k.center, yaw_to_quat(k.yaw if k.yaw is not None else yaw_init)
        for a, bk in zip(frames[:-1], frames[1:]):
            if a.t <= t <= bk.t:
                w = (t - a.t) / max(bk.t - a.t, 1e-9)
                ya = a.yaw if a.yaw is not None else yaw_init
                yb = bk.yaw if bk.yaw is not None else ya
                return (1 - w) * a.center + w * bk.center, yaw_to_quat((1 - w) * ya + w * yb)
        k = frames[-1]
        return k.center, yaw_to_quat(k.yaw if k.yaw is not None else yaw_init)

    def goal_specs(self, t: float) -> tuple:
        specs = self.sc.goals
        for tc, g in self.sc.goal_changes:
            if t >= tc:
                specs = g
        return specs

    def poses(self, t: float) -> dict:
        """``{"targets": {name: (c, q)}, "obstacles": {name: (c, q)}}`` of everything the scenario moves."""
        out = {"targets": {}, "obstacles": {}}
        if self.sc.person is not None:
            pp = person_pose(self.scene0, self.sc.person, self.person_yaw(t))
            out["targets"][self.sc.person.target] = pp["target"]
            if pp["body"] is not None:
                out["obstacles"][self.sc.person.body] = pp["body"]
        for name in self.sc.obstacles:
            out["obstacles"][name] = self.obstacle_pose(name, t)
        return out


def goal_configurations(robot, scene, specs, template: np.ndarray, aim=None) -> np.ndarray:
    """Goal configurations (G, dof) from goal-region names or explicit base poses; camera joints aimed with ``aim``
    (a callable (G, dof) -> (G, dof), e.g. the planner's line-of-sight projection of the non-base joints)."""
    qs = []
    for g in specs:
        q = template.copy()
        if isinstance(g, str):
            gr = scene.goal(g)
            vals = dict(gr.joints)
            vals.update(base_x=gr.base[0], base_y=gr.base[1], base_theta=gr.base[2])
            q = robot.configuration(vals)
        else:
            q[:3] = g
        qs.append(q)
    Q = np.stack(qs)
    return aim(Q) if aim is not None else Q


# ---- episode ------------------------------------------------------------------------------------------------------
def _aimer(planner):
    from ..planning.constraints import ProjectionSettings

    def aim(Q: np.ndarray) -> np.ndarray:
        if len(planner.track_cols) == 0:
            return Q
        qt = torch.as_tensor(Q, dtype=torch.float32)
        out, ok = planner.constraint.project(qt, ProjectionSettings(max_iters=15), *planner.joint_bounds,
                                             joints=planner.track_cols)
        ok &= planner.checker.valid(out)  # keep the given joints where aiming fails or collides
        return torch.where(ok[:, None], out, qt).double().numpy()

    return aim


def run_episode(scenario: Scenario, replanning: bool = True, planner=None, oracle=None, progress=None,
                replan_settings=None) -> dict:
    """Execute one episode; ``replanning=False`` is the static baseline (one plan at t = 0, then only execution).

    Returns a dict with the executed configurations, camera-frame times, oracle confidences and detections, the
    replanning log and summary numbers (see :func:`summarize`)."""
    from ..paths import resolve_named
    from ..planning.factory import make_planner
    from ..planning.replanner import Replanner, ReplanSettings
    from ..robot import RobotModel
    from ..scene import load_scene

    scene = load_scene(resolve_named("scene", scenario.scene))
    robot = RobotModel.load(scene.robot)
    world = World(scenario, scene, robot)
    if planner is None:
        planner = make_planner(scenario.planner, scene, [scenario.target], robot=robot, n_nodes=scenario.nodes,
                               seed=scenario.seed)
        planner.build()
    rp = Replanner(planner, replan_settings or ReplanSettings(), targets=[scenario.target])
    aim = _aimer(planner)
    start = robot.configuration(scenario.start)
    start = aim(start[None])[0]

    def apply_world(t: float) -> None:
        poses = world.poses(t)
        for name, (c, q) in poses["targets"].items():
            rp.update_target(name, c, q)
        for name, (c, q) in poses["obstacles"].items():
            rp.update_obstacle(name, c, q)

    dt, t = scenario.control_dt, 0.0
    apply_world(0.0)
    specs = world.goal_specs(0.0)
    rp.set_robot_state(start)
    rp.set_goals(goal_configurations(robot, scene, specs, start, aim))
    res = rp.replan(now=0.0)
    q = start.copy()
    traj, traj_t0 = (res.trajectory, 0.0) if res.success else (None, 0.0)
    executed, frames_t, frames_q, frames_scene = [q.copy()], [], [], []
    collisions, n_plans, failures, latencies, reasons_log = 0, 1 if res.success else 0, 0 if res.success else 1, [res.query_ms], []
    kept = 0  # replans whose new plan was no better: the robot kept its trajectory
    next_frame = 0.0
    reached = False
    checker = planner.checker
    while t < scenario.duration_s - 1e-9:
        t = round(t + dt, 9)
        apply_world(t)
        new_specs = world.goal_specs(t)
        if new_specs != specs:
            specs = new_specs
            rp.set_goals(goal_configurations(robot, rp.scene, specs, q, aim))
        if traj is not None:
            q = traj.evaluate(t - traj_t0)[0][0]
            if robot.mobile:
                q[2] = (q[2] + np.pi) % (2 * np.pi) - np.pi
        rp.set_robot_state(q)
        executed.append(q.copy())
        if bool(checker.check(torch.as_tensor(q[None], dtype=torch.float32))[0]):
            collisions += 1
        while next_frame <= t + 1e-9:
            frames_t.append(next_frame)
            frames_q.append(q.copy())
            frames_scene.append(world.poses(next_frame))
            next_frame += 1.0 / scenario.camera_fps
        dist_goal = np.abs(rp.goals - q)
        if robot.mobile:
            dist_goal[:, 2] = np.abs((rp.goals[:, 2] - q[2] + np.pi) % (2 * np.pi) - np.pi)
        if (dist_goal.max(1) <= scenario.goal_tolerance).any() and (traj is None or t - traj_t0 >= traj.duration):
            reached = True
            break
        if replanning:
            why = rp.needs_replan(now=t)
            if why:
                r = rp.replan(now=t, triggers=why)
                latencies.append(r.query_ms)
                reasons_log.append({"t": t, "reasons": why, "success": r.success, "reason": r.reason,
                                    "ms": r.query_ms, "kept": r.kept})
                if r.kept:
                    kept += 1
                elif r.success:
                    traj, traj_t0 = r.trajectory, t
                    n_plans += 1
                else:
                    failures += 1
                    if rp.result is None:  # no safe plan: stop where we are
                        traj = None
        elif traj is not None and t - traj_t0 >= traj.duration:
            traj = None  # static plan finished (its goal may have moved away)
        if progress is not None:
            progress(t)
    out = {"executed": np.asarray(executed), "frames_t": np.asarray(frames_t), "frames_q": np.asarray(frames_q),
           "frames_scene": frames_scene, "n_plans": n_plans, "kept_replans": kept, "failed_replans": failures,
           "latencies_ms": latencies, "replans": reasons_log, "reached_goal": reached, "collision_steps": collisions, "sim_time_s": t,
           "scene": scene, "robot": robot, "planner": planner, "replanner": rp}
    if oracle is not None:
        judge_frames(out, oracle, scenario.target)
    return out


def judge_frames(ep: dict, oracle, target: str) -> None:
    """Oracle confidence and detection of every recorded camera frame, with the world as it was at that time."""
    robot = ep["robot"]
    cams = robot.camera_poses(torch.as_tensor(ep["frames_q"], dtype=torch.float64)).numpy() if len(ep["frames_q"]) \
        else np.zeros((0, 4, 4))
    conf, det = [], []
    for cam, poses in zip(cams, ep["frames_scene"]):
        for name, (c, q) in poses["targets"].items():
            oracle.set_target_pose(name, c, q)
        for name, (c, q) in poses["obstacles"].items():
            oracle.set_obstacle_pose(name, c, q)
        r = oracle.score(cam, target, keep_image=False)
        conf.append(r.score)
        det.append(r.detected)
    ep["confidence"] = np.asarray(conf)
    ep["detected"] = np.asarray(det, dtype=bool)


def summarize(ep: dict) -> dict:
    """Summary numbers of an episode (the keys of ``psprm simulate --json``)."""
    from ..motion import DiffDriveMotion

    ex = ep["executed"]
    motion = DiffDriveMotion(ep["robot"])
    length = float(motion.distance(torch.as_tensor(ex[:-1]), torch.as_tensor(ex[1:])).sum()) if len(ex) > 1 else 0.0
    lat = np.asarray(ep["latencies_ms"][1:] if len(ep["latencies_ms"]) > 1 else [], dtype=float)
    out = {
        "n_plans": int(ep["n_plans"]), "kept_replans": int(ep.get("kept_replans", 0)),
        "failed_replans": int(ep["failed_replans"]),
        "det_rate": float(ep["detected"].mean()) if "detected" in ep and len(ep["detected"]) else float("nan"),
        "mean_confidence": float(ep["confidence"].mean()) if "confidence" in ep and len(ep["confidence"]) else float("nan"),
        "path_length_rad": length, "reached_goal": bool(ep["reached_goal"]), "time_s": float(ep["sim_time_s"]),
        "collision_steps": int(ep["collision_steps"]), "frames": int(len(ep["frames_t"])),
        "first_plan_ms": float(ep["latencies_ms"][0]) if ep["latencies_ms"] else float("nan"),
        "replan_ms_median": float(np.median(lat)) if len(lat) else float("nan"),
        "replan_ms_p95": float(np.percentile(lat, 95)) if len(lat) else float("nan"),
        "replan_ms_max": float(lat.max()) if len(lat) else float("nan"),
    }
    return out


def plot_episodes(episodes: dict, scenario: Scenario, path: str | Path) -> Path:
    """Top view with each executed path coloured by time and the person's orientation over time, plus the oracle
    confidence over time per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .viz import plot_scene_top

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 6), gridspec_kw={"width_ratios": [1.2, 1]})
    any_ep = next(iter(episodes.values()))
    plot_scene_top(ax, any_ep["scene"])
    cmaps = {"replanning": "viridis", "static": "autumn"}
    for label, ep in episodes.items():
        ex = ep["executed"]
        tt = np.arange(len(ex)) * scenario.control_dt
        sc = ax.scatter(ex[:, 0], ex[:, 1], c=tt, cmap=cmaps.get(label, "viridis"), s=6, label=label)
        ax2.plot(ep["frames_t"], ep.get("confidence", np.zeros(len(ep["frames_t"]))), label=label)
    fig.colorbar(sc, ax=ax, label="time (s)")
    if scenario.person is not None and len(any_ep["frames_scene"]):
        for poses in any_ep["frames_scene"][:: max(1, len(any_ep["frames_scene"]) // 12)]:
            c, q = poses["targets"][scenario.person.target]
            yaw = 2 * math.atan2(q[2], q[3])
            ax.arrow(c[0], c[1], 0.5 * math.cos(yaw), 0.5 * math.sin(yaw), head_width=0.08, color="k", alpha=0.4)
    ax.legend(loc="upper right")
    ax.set_title(f"{scenario.name}: executed paths (colour = time), person's facing (arrows)")
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
             planner_overrides: Optional[dict] = None, replan_overrides: Optional[dict] = None) -> dict:
    """``psprm simulate``: run the scenario with replanning (and a static single plan on the same timeline), judge
    both with the oracle, return the summary (and write the figure). ``planner_overrides``: settings of the
    scenario's planner; ``replan_overrides``: :class:`~psprm_core.planning.replanner.ReplanSettings` fields (both
    episodes use them: the static one for its single plan)."""
    from ..perception.oracle import Oracle

    torch.set_num_threads(threads)
    import tempfile

    from ..paths import resolve_named
    from ..planning.factory import make_planner
    from ..planning.replanner import ReplanSettings
    from ..robot import RobotModel
    from ..scene import load_scene

    sc = load_scenario(scenario_path)
    if nodes is not None:
        sc = dataclasses.replace(sc, nodes=nodes)
    if duration_s is not None:
        sc = dataclasses.replace(sc, duration_s=duration_s)
    t0 = time.perf_counter()
    scene = load_scene(resolve_named("scene", sc.scene))
    robot = RobotModel.load(scene.robot)

    def fresh():
        return make_planner(sc.planner, scene, [sc.target], robot=robot,
                            **{"n_nodes": sc.nodes, "seed": sc.seed, **(planner_overrides or {})})

    rs = ReplanSettings(**(replan_overrides or {}))

    planner = fresh()
    build_s = planner.build().get("build_s", float("nan"))
    with tempfile.TemporaryDirectory() as tmp:  # the static run gets an untouched copy of the same roadmap
        saved = planner.save(Path(tmp) / "roadmap.npz")
        ep = run_episode(sc, replanning=True, planner=planner, replan_settings=rs)
        episodes = {"replanning": ep}
        if compare_static:
            p2 = fresh()
            p2.load(saved)
            episodes["static"] = run_episode(sc, replanning=False, planner=p2, replan_settings=rs)
    oracle = Oracle(ep["scene"], intrinsics=ep["robot"].config.intrinsics)
    try:
        for e in episodes.values():
            judge_frames(e, oracle, sc.target)
    finally:
        oracle.close()
    out = {"scenario": sc.name, "scene": sc.scene, "planner": sc.planner, "nodes": sc.nodes, "build_s": build_s,
           "planner_overrides": dict(planner_overrides or {}), "replan_overrides": dict(replan_overrides or {})}
    out.update(summarize(ep))
    out["replan_log"] = ep["replans"]
    if compare_static:
        out["static"] = summarize(episodes["static"])
    out["wall_s"] = time.perf_counter() - t0
    if plot:
        out["plot"] = str(plot_episodes(episodes, sc, plot))
    return out
