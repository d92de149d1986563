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

This module runs a bench (configuration, tasks on the backend, journal) and re-exports the names of its parts:
:mod:`~psprm_core.evaluation.bench.problems` (problems), :mod:`~psprm_core.evaluation.bench.tasks` (rows and the
worker's task), :mod:`~psprm_core.evaluation.bench.paths` (judging an executed path) and
:mod:`~psprm_core.evaluation.bench.report` (headroom, summaries, tables, plots).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ...baselines import BASELINES, planner_names
from ...errors import PsprmError
from ...executors import BackendSettings, Executor, Task
from ...paths import resolve_named
from .paths import arc_lengths, evaluate_path, frame_indices, track_flags, unseen_ends, verify_success
from .problems import DEFAULT_EXCLUDED_CLASSES, default_target_groups, make_problems, scenario_problems
from .report import (HEADROOM_MIN_GAIN, METRICS, PAPER_TABLE2, PAPER_TABLE3, annotate_headroom, cells_table,
                     json_summary, markdown_table, summarize, summarize_cells, write_outputs)
from .tasks import (REFERENCE, REFERENCE_VARIANT, ROW_FIELDS, _failure_row, _worker_init, base_name, bench_task,
                    run_task)
from ...robot import RobotModel
from ...scene import load_scene

log = logging.getLogger(__name__)

__all__ = ["BenchConfig", "BenchTask", "run_bench", "backend_settings", "read_journal", "JOURNAL_FILE",
           "EXAMPLE_PATH_CANDIDATES",
           # problems (bench_problems)
           "DEFAULT_EXCLUDED_CLASSES", "default_target_groups", "make_problems", "scenario_problems",
           # path evaluation (bench_paths)
           "arc_lengths", "frame_indices", "unseen_ends", "track_flags", "evaluate_path", "verify_success",
           # rows and the worker's task (bench_tasks)
           "ROW_FIELDS", "REFERENCE", "REFERENCE_VARIANT", "base_name", "run_task", "bench_task",
           # summaries, tables, plots (bench_report)
           "PAPER_TABLE2", "PAPER_TABLE3", "METRICS", "HEADROOM_MIN_GAIN", "annotate_headroom", "summarize",
           "summarize_cells", "cells_table", "markdown_table", "write_outputs", "json_summary"]


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


# ---- driver -----------------------------------------------------------------------------------------------------------
def run_bench(cfg: BenchConfig, progress: bool = True, on_start=None) -> dict:
    """Run every planner of ``cfg`` on the same problems; returns {"rows", "summary", "paths", "problems", ...}.

    ``on_start(key, worker)``: called when the task ``key`` = (planner, problem index) is sent to a worker
    (``pid@host``; ``inline`` in this process)."""
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
