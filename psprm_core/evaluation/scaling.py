"""What the bench and the oracle labelling cost per task, what the execution backends add, and what a paper-scale job
would take on N Ray nodes (``psprm perf backends``).

Measured here (:func:`backend_overheads`):

* dispatch: how long a pool takes to start (local worker processes; a local Ray cluster and its actors) and the
  per-task cost of the dispatch itself (no-op tasks through the pool: one worker in turn = the round trip, all
  workers at once = the driver's throughput);
* PS-PRM's ``reset`` (the roadmap restored before every bench problem) on a built roadmap;
* the oracle's cost of labelling one view, per detector class (render + real detector, in this process).

From a bench run (:func:`task_costs`, the rows of ``results.csv`` or ``rows.jsonl``): per planner the mean seconds of
one problem's task (planning + judging the executed path by the oracle) and of one preparation.

Projection (:func:`project`): a job of ``tasks`` tasks of mean ``t`` seconds, ``instances`` planner instances of mean
``b`` seconds to prepare, on ``W = nodes x cores`` workers::

    wall = start + b x max(1, ceil(instances / W)) + tasks x (t + overhead) / W

(every worker prepares the instances it works on: with more workers than instances each instance is prepared by
``W / instances`` workers, each once; with fewer, the affinity scheduler keeps an instance's problems on the worker
that prepared it). The model assumes tasks of equal cost and nodes like the measuring machine's cores; it is a plan,
not a measurement.
"""

from __future__ import annotations

import csv
import json
import math
import statistics
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..baselines import make_baseline
from ..executors import BackendSettings, Executor, Task
from ..paths import resolve_named
from ..perception.dataset import OracleFactory, SamplingConfig, sample_camera_poses
from ..robot import RobotModel
from ..scene import load_scene
from .bench import make_problems

#: the paper's protocol: 2,500 home problems per planner (Table II)
PAPER_PROBLEMS = 2500


def noop(cache) -> int:
    """A task that does nothing (dispatch cost)."""
    return 0


def dispatch_overheads(backend: str, workers: int = 2, tasks: int = 200, address: Optional[str] = None) -> dict:
    """Start-up and per-task dispatch cost of a backend with no-op tasks: ``start_s`` (pool ready), ``round_trip_ms``
    (median over one worker's tasks in turn), ``throughput_per_s`` (all workers, ``tasks`` at once)."""
    t0 = time.perf_counter()
    with Executor(BackendSettings(backend=backend, workers=workers, address=address)) as ex:
        ex.worker_pids()  # starts the pool
        started = time.perf_counter() - t0
        list(ex.run([Task(("warm", i), noop) for i in range(workers * 2)]))
        trips = []
        for i in range(min(50, tasks)):
            t1 = time.perf_counter()
            list(ex.run([Task(("one", i), noop)]))
            trips.append(time.perf_counter() - t1)
        t2 = time.perf_counter()
        list(ex.run([Task(("many", i), noop) for i in range(tasks)]))
        many = time.perf_counter() - t2
    closed = time.perf_counter() - t0 - started
    return {"start_s": started, "round_trip_ms": 1e3 * statistics.median(trips),
            "throughput_per_s": tasks / many, "dispatch_ms_per_task": 1e3 * many / tasks,
            "workers": workers, "run_and_shutdown_s": closed}


def reset_cost(scene_name: str = "home", planner: str = "neural-psprm-line", nodes: int = 3000, target: str = "tv",
               problems: int = 3, seed: int = 0) -> dict:
    """Seconds of the PS-PRM snapshot (once, after the build) and of a ``reset`` after a query (median over
    ``problems`` queries), next to the build and query times of the same planner."""
    import torch

    torch.set_num_threads(1)
    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    probs = make_problems(scene, robot, [[target]], problems, seed)
    p = make_baseline(planner, scene, [target], robot=robot, seed=seed, n_nodes=nodes)
    prep = p.prepare()
    plans, resets = [], []
    for prob in probs:
        t0 = time.perf_counter()
        p.plan(prob["start"], prob["goal"], timeout_s=10.0)
        plans.append(time.perf_counter() - t0)
        t1 = time.perf_counter()
        p.reset(int(prob["index"]))
        resets.append(time.perf_counter() - t1)
    return {"planner": planner, "nodes": nodes, "preprocess_s": float(prep["preprocess_s"]),
            "snapshot_s": float(prep.get("snapshot_s", float("nan"))), "plan_s": statistics.median(plans),
            "reset_s": statistics.median(resets)}


def labelling_cost(scene_name: str = "surrogate_studio", views: int = 5, seed: int = 0) -> dict:
    """Seconds per oracle-labelled view (render + the class's real detector), per target of the scene, over ``views``
    sampled views each (the oracle built first; its build time reported apart)."""
    path = resolve_named("scene", scene_name)
    scene = load_scene(path)
    t0 = time.perf_counter()
    oracle = OracleFactory(str(path))()
    out = {"oracle_build_s": time.perf_counter() - t0, "per_view_s": {}}
    try:
        rng = np.random.default_rng(seed)
        for name in scene.target_names:
            poses, _ = sample_camera_poses(scene.target(name), views, SamplingConfig(), rng)
            oracle.score(poses[0], name)  # the class's detector loaded
            t1 = time.perf_counter()
            for pose in poses:
                oracle.score(pose, name)
            out["per_view_s"][scene.target(name).detector_class] = (time.perf_counter() - t1) / views
    finally:
        oracle.close()
    return out


def backend_overheads(workers: int = 2, tasks: int = 200, nodes: int = 3000, views: int = 5,
                      address: Optional[str] = None) -> dict:
    """Everything :func:`dispatch_overheads`, :func:`reset_cost` and :func:`labelling_cost` measure, in one run."""
    return {"local": dispatch_overheads("local", workers, tasks),
            "ray": dispatch_overheads("ray", workers, tasks, address),
            "reset": reset_cost(nodes=nodes), "labelling": labelling_cost(views=views)}


def read_rows(path: str | Path) -> list:
    """Bench rows from ``results.csv`` or the journal ``rows.jsonl`` (numbers as floats)."""
    path = Path(path)
    if path.suffix == ".jsonl":
        return [json.loads(line)["row"] for line in path.read_text().splitlines()[1:] if line.strip()]
    rows = []
    with open(path) as fh:
        for r in csv.DictReader(fh):
            for k, v in r.items():
                try:
                    r[k] = float(v)
                except (TypeError, ValueError):
                    pass
            r["success"] = str(r.get("success")) in ("True", "1.0", "true")
            rows.append(r)
    return rows


def task_costs(rows: Sequence[dict]) -> dict:
    """Per planner from bench rows: problems, mean seconds of a task (plan + oracle judging of the executed path),
    its median, mean planning and judging seconds, the mean preparation of an instance (one per target group and
    placement and run seed) and the success rate."""
    out = {}
    for pl in sorted({r["planner"] for r in rows}):
        rs = [r for r in rows if r["planner"] == pl]

        def f(r, k):
            v = r.get(k)
            return float(v) if v is not None and v == v else 0.0
        task = [f(r, "plan_s") + f(r, "eval_s") for r in rs]
        inst: dict = {}  # instance -> its preparation times (one per worker that prepared it)
        for r in rs:
            inst.setdefault(f'{r["targets"]}|{r.get("placement", 0)}|{r.get("run_seed", "")}', set()).add(
                f(r, "preprocess_s"))
        out[pl] = {"problems": len(rs), "task_s": float(np.mean(task)), "task_median_s": float(np.median(task)),
                   "plan_s": float(np.mean([f(r, "plan_s") for r in rs])),
                   "eval_s": float(np.mean([f(r, "eval_s") for r in rs])),
                   "prepare_s": float(np.mean([v for vs in inst.values() for v in vs])), "instances": len(inst),
                   "success_rate": float(np.mean([bool(r["success"]) for r in rs]))}
    return out


def project(tasks: int, task_s: float, instances: int, prepare_s: float, nodes: int, cores: int,
            overhead_s: float = 0.0, start_s: float = 0.0) -> float:
    """Wall seconds of a job on ``nodes`` x ``cores`` workers (the model of the module docstring)."""
    w = max(1, nodes * cores)
    return start_s + prepare_s * max(1, math.ceil(instances / w)) + tasks * (task_s + overhead_s) / w


def projection_table(costs: dict, per_view_s: float, nodes: Sequence[int] = (1, 4, 16, 64), cores: int = 2,
                     problems: int = PAPER_PROBLEMS, views: int = 100_000, overhead_s: float = 0.0,
                     start_s: float = 0.0, instances: Optional[int] = None) -> dict:
    """Projected hours of the ``problems``-problem protocol per planner (and all of them together) and of a
    ``views``-view labelling on each node count."""
    out = {}
    for n in nodes:
        row = {}
        for pl, c in costs.items():
            k = instances if instances is not None else c["instances"]
            row[pl] = project(problems, c["task_s"], k, c["prepare_s"], n, cores, overhead_s, start_s) / 3600
        tot_tasks = problems * len(costs)
        mean_t = float(np.mean([c["task_s"] for c in costs.values()])) if costs else 0.0
        k_all = sum(instances if instances is not None else c["instances"] for c in costs.values())
        mean_b = float(np.mean([c["prepare_s"] for c in costs.values()])) if costs else 0.0
        row["all"] = project(tot_tasks, mean_t, k_all, mean_b, n, cores, overhead_s, start_s) / 3600
        row["views"] = project(views, per_view_s, 1, 0.0, n, cores, overhead_s, start_s) / 3600
        out[n] = row
    return out
