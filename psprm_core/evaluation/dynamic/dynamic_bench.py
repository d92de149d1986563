"""``psprm dynbench``: the dynamic benchmark in simulated time. Every scenario (:mod:`.scenarios`) runs ``episodes``
episodes, each with a seeded variation of the people's motion (:func:`~.scenarios.draw_variation`: phase, period,
amplitude, walking speed), and every episode runs each mode of :func:`~.simulation.run_episode` (replanning in motion
with and without target prediction, replanning from rest with stops, the static first plan, and the hindsight
reference) on the same world timeline, each from a copy of the same roadmap.

One task is one (scenario, episode) on a worker of the run's backend (:mod:`psprm_core.executors`, as ``psprm
bench`` distributes its tasks: local worker processes or Ray actors, one torch thread each). A worker builds a
scenario's roadmap once (builds are deterministic per seed), saves it, and loads a fresh copy for every mode of its
episodes; it keeps one oracle per scene. The modes of an episode share one :class:`~.episodes.FrameJudge`: the oracle
(the real detector on rendered views) judges every camera frame once, with the world as it was at that instant.

Per episode and mode (:func:`episode_metrics`): reached, arrival time over the first plan's duration, executed
configurations in collision with the world at that instant (moving boxes included; self-collisions and joint limits
of the box model counted apart), stops, adopted and declined
replans, goal switches, detection rate over the frames and targets (as the bench's ``det_rate``). Per scenario
(:func:`summarize_scenario`): each mode's mean detection rate, the ratios motion / static, motion_no_prediction /
static, motion / motion_no_prediction, motion / hindsight and the share of the dynamic headroom
``(motion - static) / (hindsight - static)`` (when hindsight sees more than static), % reached, total collisions.
Everything is strict JSON: a number that does not exist is null, never NaN.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ...errors import PsprmError
from ...executors import BackendSettings, Executor, Task, WorkerCache, one_torch_thread
from ...paths import resolve_named
from ...perception.detectors import default_detector_name, make_detector
from ...perception.oracle import Oracle
from ...planning.factory import make_planner
from ...planning.replanner import ReplanSettings
from ...robot import RobotModel
from ...scene import load_scene
from ...yamlio import replace_settings
from ..scenario_world import World
from ..scenarios import draw_variation, load_scenario
from ..simulation import DEFAULT_LATENCY_S, MODES, REPLANNING_MODES, run_episode
from .episodes import FrameJudge, detection_metrics, json_safe
from .hindsight import SEARCHES, VARIANTS, parse_searches, parse_variants

log = logging.getLogger(__name__)

#: The shipped scenarios of the benchmark (``config/scenarios``).
DEFAULT_SCENARIOS = ("rotating_person", "moving_obstacle_and_goal", "nursing_turning_walking", "walking_person",
                     "rolling_monitor")


@dataclass
class DynBenchConfig:
    """What ``psprm dynbench`` runs (all fields have CLI flags)."""

    scenarios: Sequence[str] = DEFAULT_SCENARIOS  # names of config/scenarios/*.yaml or paths
    episodes: int = 20
    seed: int = 0  # the variations' seed (with the scenario's own and the episode's index)
    modes: Sequence[str] = MODES
    latency_s: float = DEFAULT_LATENCY_S
    history_s: float = 0.0  # the people's poses given to the replanner before the first plan
    nodes: Optional[int] = None  # override every scenario's roadmap size
    duration_s: Optional[float] = None  # override every scenario's time limit
    camera_fps: Optional[float] = None  # override every scenario's oracle frames per simulated second
    oracle: bool = True  # judge the frames (off: no detection rates, no hindsight reference)
    hindsight_searches: str = SEARCHES
    hindsight_variants: str = VARIANTS
    hindsight_judged: int = 0  # > 0: the oracle judges the first plan and this many best-predicted candidates
    planner_overrides: dict = field(default_factory=dict)  # settings of the scenarios' planner
    replan_overrides: dict = field(default_factory=dict)  # ReplanSettings fields
    backend: str = "local"
    workers: Optional[int] = 2  # local: <= 1 runs in this process
    address: Optional[str] = None
    max_retries: int = 1

    def validate(self) -> None:
        if self.episodes < 1:
            raise PsprmError(f"episodes must be at least 1, got {self.episodes}")
        bad = [m for m in self.modes if m not in MODES]
        if bad or not self.modes:
            raise PsprmError(f"unknown mode(s) {', '.join(bad) or '(none given)'} (choose from {', '.join(MODES)})")
        if not (np.isfinite(self.latency_s) and self.latency_s >= 0):
            raise PsprmError(f"latency must be a finite time >= 0 s, got {self.latency_s}")
        if not (np.isfinite(self.history_s) and self.history_s >= 0):
            raise PsprmError(f"history must be a finite time >= 0 s, got {self.history_s}")
        for name, v in (("nodes", self.nodes), ("duration", self.duration_s), ("camera fps", self.camera_fps)):
            if v is not None and not v > 0:
                raise PsprmError(f"{name} must be positive, got {v}")
        if self.hindsight_judged < 0:
            raise PsprmError(f"hindsight_judged must be at least 0, got {self.hindsight_judged}")
        parse_searches(self.hindsight_searches)
        parse_variants(self.hindsight_variants)
        self.backend_settings().validate()

    def backend_settings(self):
        workers = self.workers
        if self.backend == "local" and workers is not None and workers <= 1:
            workers = 0
        return BackendSettings(backend=self.backend, workers=workers, address=self.address,
                               max_retries=self.max_retries)


def load_scenarios(cfg: DynBenchConfig) -> list:
    """The run's scenarios with the config's overrides applied."""
    out = []
    for name in cfg.scenarios:
        p = Path(name)
        sc = load_scenario(p if p.is_file() else resolve_named("scenario", name))
        changes = {k: v for k, v in (("nodes", cfg.nodes), ("duration_s", cfg.duration_s),
                                     ("camera_fps", cfg.camera_fps)) if v is not None}
        out.append(dataclasses.replace(sc, **changes))
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise PsprmError(f"a scenario is named twice: {', '.join(names)}")
    return out


# ---- the worker's task --------------------------------------------------------------------------------------------
def _roadmap(cache, scenario, overrides: dict) -> tuple:
    """(path of the saved roadmap, build stats, scene, robot) of a scenario, built once per worker."""
    import shutil
    import tempfile

    key = (scenario.name, scenario.scene, tuple(scenario.targets), scenario.planner, scenario.nodes, scenario.seed,
           json.dumps(overrides, sort_keys=True, default=str))

    def build():
        scene = load_scene(resolve_named("scene", scenario.scene))
        robot = RobotModel.load(scene.robot)
        p = make_planner(scenario.planner, scene, list(scenario.targets), robot=robot,
                         options={"roadmap.n_nodes": scenario.nodes, "seed": scenario.seed, **overrides})
        t0 = time.perf_counter()
        stats = p.build()
        tmp = tempfile.mkdtemp(prefix="psprm_dynbench_")
        path = p.save(Path(tmp) / "roadmap.npz")
        stats = {k: v for k, v in stats.items() if isinstance(v, (int, float, str, bool))}
        stats.setdefault("build_s", time.perf_counter() - t0)
        return path, stats, scene, robot, tmp

    entry = cache.get("roadmap", key, build, close=lambda e: shutil.rmtree(e[4], ignore_errors=True))
    return entry[:4]


def _oracle(scene, robot, targets: Sequence[str], threads: int):
    """The oracle of a scene, its detectors (the built-in ones of the targets' classes) with ``threads`` intra-op
    threads each (0: onnxruntime's default, every core; a worker of a pool runs one, as it runs one torch thread:
    two workers with a detector thread per core each judge about 1.5x the frames that two all-core detectors do)."""
    classes = {scene.target(t).detector_class for t in targets}
    dets = {c: make_detector(default_detector_name(c), threads=threads) for c in classes}
    return Oracle(scene, dets, intrinsics=robot.config.intrinsics)


def run_episode_modes(scenario, episode: int, cfg: dict, cache=None) -> dict:
    """Every mode of one episode (module docstring): the episode's variation, a roadmap copy per mode, one frame
    judge for all. ``cfg``: :class:`DynBenchConfig` as a dict. Returns the episode's record (strict-JSON values)."""
    own = cache is None
    cache = WorkerCache() if own else cache
    try:
        t_start = time.perf_counter()
        path, stats, scene, robot = _roadmap(cache, scenario, cfg["planner_overrides"])
        variation = draw_variation(scenario, episode, cfg["seed"])
        judge = None
        if cfg["oracle"]:
            threads = int(cfg.get("detector_threads", 0))
            oracle = cache.get("oracle", (scenario.scene, tuple(scenario.targets), threads),
                               lambda: _oracle(scene, robot, scenario.targets, threads), close=lambda o: o.close())
            judge = FrameJudge(oracle, robot, World(scenario, scene, robot, variation), scenario.targets)
        rs = replace_settings(ReplanSettings(), cfg["replan_overrides"])  # names or dotted paths
        modes, walls = {}, {}
        for mode in cfg["modes"]:
            t0 = time.perf_counter()
            planner = make_planner(scenario.planner, scene, list(scenario.targets), robot=robot,
                                   options={"roadmap.n_nodes": scenario.nodes, "seed": scenario.seed,
                                            **cfg["planner_overrides"]})
            planner.load(path)
            ep = run_episode(scenario, mode=mode, planner=planner, replan_settings=rs, latency_s=cfg["latency_s"],
                             variation=variation, judge=judge, hindsight_searches=cfg["hindsight_searches"],
                             hindsight_variants=cfg["hindsight_variants"],
                             hindsight_judged=cfg["hindsight_judged"], history_s=cfg["history_s"])
            modes[mode] = episode_metrics(ep)
            walls[mode] = time.perf_counter() - t0
        return json_safe({"scenario": scenario.name, "episode": int(episode),
                          "variation": {k: v.as_dict() for k, v in variation.items()}, "modes": modes,
                          "wall_s": time.perf_counter() - t_start, "mode_wall_s": walls,
                          "frames_rendered": judge.rendered if judge is not None else 0, "build": stats})
    finally:
        if own:
            cache.close()


def dynbench_task(cache, scenario, episode: int, cfg: dict) -> dict:
    """The executor's task: :func:`run_episode_modes` with the worker's cache."""
    return run_episode_modes(scenario, episode, cfg, cache=cache)


def episode_metrics(ep: dict) -> dict:
    """The numbers of one mode of one episode (strict-JSON values; the module docstring)."""
    first = ep.get("first_plan_s")
    arrival = ep.get("arrival_s")
    lat = np.asarray(ep["latencies_ms"][1:], float) if len(ep.get("latencies_ms", [])) > 1 else np.zeros(0)
    out = {"reached": bool(ep["reached_goal"]), "arrival_s": arrival, "first_plan_s": first,
           "time_ratio": arrival / first if arrival is not None and first else None,
           "collisions": int(ep["collision_steps"]), "self_collisions": int(ep.get("self_collision_steps") or 0),
           "stops": int(ep.get("stops", 0)),
           "adopted": int(ep.get("adopted", 0)), "declined": int(ep.get("declined", 0)),
           "declined_late": int(ep.get("declined_late", 0)),
           "goal_switches": int(ep.get("goal_switches", 0)), "failed_replans": int(ep.get("failed_replans", 0)),
           **detection_metrics(ep), "frames": int(len(ep.get("frames_t", []))), "sim_time_s": ep.get("sim_time_s"),
           "speed_ratio": ep.get("speed_ratio"), "max_jump": ep.get("max_jump"),
           "replan_ms_median": float(np.median(lat)) if len(lat) else None}
    if ep.get("mode") == "hindsight":
        out.update(route=ep.get("route"), candidates=ep.get("candidates", []), n_valid=ep.get("n_valid", 0))
    return json_safe(out)


# ---- summaries ----------------------------------------------------------------------------------------------------
def _mean(xs) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return float(np.mean(xs)) if xs else None


def _ratio(a: Optional[float], b: Optional[float]) -> Optional[float]:
    return a / b if a is not None and b is not None and b > 0 else None


def summarize_scenario(episodes: list, modes: Sequence[str]) -> dict:
    """Per mode: mean detection rate (episodes with judged frames), % reached, total and mean collisions, stops,
    adopted and declined replans, goal switches, mean time ratio (reached episodes); then the ratios of the mode
    means and the share of the dynamic headroom (module docstring), over the episodes where both modes have a
    detection rate."""
    eps = [e for e in episodes if "modes" in e]
    per = {}
    for m in modes:
        rows = [e["modes"][m] for e in eps if m in e["modes"]]
        n = len(rows)
        per[m] = {"episodes": n, "det_rate": _mean(r["det_rate"] for r in rows),
                  "det_rate_any": _mean(r["det_rate_any"] for r in rows),
                  "reached_pct": 100.0 * sum(r["reached"] for r in rows) / n if n else None,
                  "collisions": sum(r["collisions"] for r in rows),
                  "episodes_with_collisions": sum(r["collisions"] > 0 for r in rows),
                  "self_collisions": sum(r.get("self_collisions", 0) for r in rows),
                  "stops": sum(r["stops"] for r in rows), "stops_mean": _mean(r["stops"] for r in rows),
                  "adopted_mean": _mean(r["adopted"] for r in rows),
                  "declined_mean": _mean(r["declined"] for r in rows),
                  "declined_late_mean": _mean(r.get("declined_late", 0) for r in rows),
                  "goal_switches": sum(r["goal_switches"] for r in rows),
                  "time_ratio": _mean(r["time_ratio"] for r in rows if r["reached"])}
        if m == "hindsight":
            per[m]["valid_reference_pct"] = 100.0 * sum(r["det_rate"] is not None for r in rows) / n if n else None

    def paired(a: str, b: str) -> tuple:
        xs = [(e["modes"][a]["det_rate"], e["modes"][b]["det_rate"]) for e in eps
              if a in e["modes"] and b in e["modes"] and e["modes"][a]["det_rate"] is not None
              and e["modes"][b]["det_rate"] is not None]
        return _mean(x for x, _ in xs), _mean(y for _, y in xs), len(xs)

    ratios = {}
    for key, (a, b) in {"motion_over_static": ("motion", "static"),
                        "no_prediction_over_static": ("motion_no_prediction", "static"),
                        "motion_over_no_prediction": ("motion", "motion_no_prediction"),
                        "from_rest_over_static": ("from_rest", "static"),
                        "motion_over_hindsight": ("motion", "hindsight")}.items():
        ma, mb, n = paired(a, b)
        ratios[key] = _ratio(ma, mb)
        ratios[key + "_episodes"] = n
    share, n_share = None, 0
    if {"motion", "static", "hindsight"} <= set(modes):
        three = ("motion", "static", "hindsight")
        trip = [tuple(e["modes"][m]["det_rate"] for m in three) for e in eps
                if all(e["modes"][m]["det_rate"] is not None for m in three)]
        n_share = len(trip)
        if trip:
            a, d, h = (float(np.mean([t[i] for t in trip])) for i in range(3))
            share = (a - d) / (h - d) if h > d else None
    ratios["headroom_share"] = share
    ratios["headroom_share_episodes"] = n_share
    return json_safe({"modes": per, "ratios": ratios, "episodes": len(eps),
                      "failed_episodes": len(episodes) - len(eps)})


# ---- driver -------------------------------------------------------------------------------------------------------
def run_dynbench(cfg: DynBenchConfig, progress: bool = True, on_start=None) -> dict:
    """Run every episode of every scenario of ``cfg`` on its backend; returns ``{"config", "scenarios": {name:
    {"summary", "episodes"}}, "wall_s"}`` (strict-JSON values)."""
    from tqdm import tqdm

    cfg.validate()
    scenarios = load_scenarios(cfg)
    for sc in scenarios:  # names checked against the scenes before any work
        World(sc, load_scene(resolve_named("scene", sc.scene)))
    cfgd = {k: v for k, v in asdict(cfg).items()}
    cfgd["modes"] = list(cfg.modes)
    cfgd["detector_threads"] = 0 if cfg.backend_settings().workers == 0 else 1  # a pool: one per worker
    cfgd["scenarios"] = [s.name for s in scenarios]
    by_name = {s.name: s for s in scenarios}
    tasks = [Task((sc.name, ep), dynbench_task, (sc, ep, cfgd), affinity=sc.name)
             for ep in range(cfg.episodes) for sc in scenarios]
    results: dict = {s.name: [] for s in scenarios}
    t0 = time.perf_counter()
    bar = tqdm(total=len(tasks), desc="dynbench", unit="episode", disable=not progress, dynamic_ncols=True)
    try:
        with Executor(cfg.backend_settings(), init=one_torch_thread) as ex:
            for res in ex.run(tasks, on_start=on_start):
                name, ep = res.key
                if res.ok:
                    results[name].append(res.value)
                else:
                    why = res.error.strip().splitlines()[-1] if res.error.strip() else "unknown error"
                    log.error("dynbench episode %s/%d failed: %s", name, ep, res.error)
                    results[name].append({"scenario": name, "episode": ep, "error": why})
                bar.update(1)
                bar.set_postfix_str(name)
    finally:
        bar.close()
    out = {"config": cfgd, "scenarios": {}, "wall_s": time.perf_counter() - t0}
    for name, eps in results.items():
        eps = sorted(eps, key=lambda e: e["episode"])
        out["scenarios"][name] = {"scene": by_name[name].scene, "targets": list(by_name[name].targets),
                                  "summary": summarize_scenario(eps, cfg.modes), "episodes": eps}
    return json_safe(out)


def table(result: dict) -> str:
    """A short human-readable table of a run's summaries."""
    lines = []
    fmt = lambda v, p="{:.3f}": "-" if v is None else p.format(v)  # noqa: E731
    for name, s in result["scenarios"].items():
        summ = s["summary"]
        lines.append(f"{name} ({s['scene']}; {summ['episodes']} episodes"
                     + (f", {summ['failed_episodes']} failed" if summ["failed_episodes"] else "") + ")")
        lines.append(f"  {'mode':22s} {'det rate':>8s} {'reached':>8s} {'collide':>8s} {'stops':>6s} "
                     f"{'adopted':>8s} {'declined':>8s} {'switches':>8s} {'time/first':>10s}")
        for m, r in summ["modes"].items():
            lines.append(f"  {m:22s} {fmt(r['det_rate']):>8s} {fmt(r['reached_pct'], '{:.0f}%'):>8s} "
                         f"{r['collisions']:>8d} {r['stops']:>6d} {fmt(r['adopted_mean'], '{:.1f}'):>8s} "
                         f"{fmt(r['declined_mean'], '{:.1f}'):>8s} {r['goal_switches']:>8d} "
                         f"{fmt(r['time_ratio'], '{:.2f}'):>10s}")
        q = summ["ratios"]
        lines.append(f"  motion/static {fmt(q['motion_over_static'], '{:.2f}')}, no-prediction/static "
                     f"{fmt(q['no_prediction_over_static'], '{:.2f}')}, motion/no-prediction "
                     f"{fmt(q['motion_over_no_prediction'], '{:.2f}')}, from-rest/static "
                     f"{fmt(q['from_rest_over_static'], '{:.2f}')}, motion/hindsight "
                     f"{fmt(q['motion_over_hindsight'], '{:.2f}')}, share of the dynamic headroom "
                     f"{fmt(q['headroom_share'], '{:.2f}')}")
        lines.append("")
    lines.append(f"wall time {result['wall_s']:.0f} s")
    return "\n".join(lines)


__all__ = ["DEFAULT_SCENARIOS", "DynBenchConfig", "load_scenarios", "run_episode_modes", "dynbench_task",
           "episode_metrics", "summarize_scenario", "run_dynbench", "table", "REPLANNING_MODES"]
