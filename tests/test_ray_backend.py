"""Execution backends (psprm_core.executors) on real worker processes and a real local 2-CPU Ray cluster: the bench's
rows are the same on every backend, a killed worker's task is run again, failing tasks are reported, runs resume.

Judged from independent records: the rows of the same bench run on the local backend (worker processes that share
nothing with the Ray actors), the real oracle's scores computed in this process, process ids the workers report.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from psprm_core.executors import BackendSettings, Executor, Task, WorkerCache

RAY_CPUS = 2
#: row fields that are measured times (the rest of a row must be identical between runs)
TIMINGS = ("preprocess_s", "plan_s", "total_s", "eval_s")


# ---- task functions (module level: local workers import them; Ray gets this module by value) ------------------------
def square(cache, x):
    return x * x


def pid_of_builder(cache, affinity, pause):
    """The pid of the process that built ``affinity`` (built once per worker) and this task's pid."""
    built = cache.get("thing", affinity, os.getpid)
    time.sleep(pause)
    return built, os.getpid()


def raise_error(cache):
    raise ValueError("this task always fails")


def kill_own_worker(cache):
    os.kill(os.getpid(), signal.SIGKILL)


def slow_square(cache, x, pause):
    for _ in range(int(pause / 0.05)):
        cache.report(0)
        time.sleep(0.05)
    return x * x


def _process_state(pid: int) -> str:
    """'' when the process is gone, else its state letter (Z: a zombie, i.e. dead)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return ""


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray cluster of 2 CPUs for this module (no dashboard, no usage statistics); shut down afterwards, and
    its processes checked gone."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_worker_niceness", "0")
    import ray
    import ray.cloudpickle

    from psprm_core.executors import ray_init_kwargs

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    ray.init(**ray_init_kwargs(BackendSettings(backend="ray"), RAY_CPUS))
    node = ray._private.worker._global_node
    pids = [p.process.pid for procs in node.all_processes.values() for p in procs if p.process is not None]
    assert ray.cluster_resources()["CPU"] == RAY_CPUS
    yield ray
    ray.shutdown()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_process_state(p) not in ("", "Z") for p in pids):
        time.sleep(0.2)
    assert [p for p in pids if _process_state(p) not in ("", "Z")] == []  # no raylet, GCS or worker left


def _kill_after(delay: float, pid: int, killed: list) -> None:
    def kill():
        try:
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        except ProcessLookupError:
            pass
    threading.Timer(delay, kill).start()


# ---- the executor on both backends ------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["local", "ray"])
def test_failures_are_reported_and_a_dying_task_is_retried_then_given_up(backend, request):
    if backend == "ray":
        request.getfixturevalue("ray_cluster")
    tasks = [Task(("sq", i), square, (i,)) for i in range(6)]
    tasks += [Task("raises", raise_error), Task("dies", kill_own_worker)]
    with Executor(BackendSettings(backend=backend, workers=2, max_retries=1)) as ex:
        pids_before = set(ex.worker_pids().values())
        outs = {o.key: o for o in ex.run(tasks)}
        pids_after = set(ex.worker_pids().values())
    assert {k: o.value for k, o in outs.items() if o.ok} == {("sq", i): i * i for i in range(6)}
    assert not outs["raises"].ok and "ValueError: this task always fails" in outs["raises"].error
    assert outs["raises"].attempts == 1  # an exception is not retried
    dies = outs["dies"]
    assert not dies.ok and dies.attempts == 2 and dies.error.startswith("worker died 2 time(s)")
    assert len(pids_after - pids_before) >= 1  # the dead workers were replaced by new processes


@pytest.mark.parametrize("backend", ["local", "ray"])
def test_a_killed_worker_has_its_task_run_again(backend, request):
    if backend == "ray":
        request.getfixturevalue("ray_cluster")
    killed = []
    tasks = [Task(i, slow_square, (i, 1.0), weight=3) for i in range(4)]
    progress = []

    def on_start(key, worker):
        if key == 1 and not killed:  # kill the worker half-way through task 1
            _kill_after(0.5, int(worker.split("@")[0]), killed)
    with Executor(BackendSettings(backend=backend, workers=2, max_retries=2)) as ex:
        outs = {o.key: o for o in ex.run(tasks, on_start=on_start, on_progress=progress.append)}
    assert len(killed) == 1
    assert all(o.ok for o in outs.values()) and {k: o.value for k, o in outs.items()} == {i: i * i for i in range(4)}
    assert outs[1].attempts == 2 and all(outs[k].attempts == 1 for k in (0, 2, 3))
    assert sum(progress) == 3 * len(tasks)  # the progress bar ends at the total


def test_workers_build_once_per_affinity(ray_cluster):
    """Tasks of one affinity stay on the worker that built it: 2 affinities x 6 tasks build at most 4 times (each
    worker builds its own affinity, and may help with the other's last tasks)."""
    tasks = [Task((a, i), pid_of_builder, (a, 0.05), affinity=a) for a in ("A", "B") for i in range(6)]
    with Executor(BackendSettings(backend="ray", workers=2)) as ex:
        outs = [o for o in ex.run(tasks)]
    assert all(o.ok for o in outs)
    builds = {(o.key[0], o.value[0]) for o in outs}
    assert all(built == ran for built, ran in (o.value for o in outs))  # built in the worker that used it
    assert len(builds) <= 4
    cache = WorkerCache(size=1)
    closed = []
    cache.get("x", 1, lambda: "one", close=closed.append)
    cache.get("x", 2, lambda: "two", close=closed.append)  # pushes out "one"
    assert closed == ["one"] and ("x", 2) in cache and ("x", 1) not in cache
    cache.close()
    assert closed == ["one", "two"]


def test_an_idle_worker_helps_only_where_building_again_pays():
    """All pending affinities have a worker: an idle one builds one again only when the split of its pending tasks
    saves more than the build costs (from the recorded times of first tasks, which include the build, and later
    ones)."""
    from psprm_core.executors import _Pending

    pending = _Pending([Task(("roadmap", i), square, (i,), affinity="roadmap") for i in range(4)] +
                       [Task(("cheap", i), square, (i,), affinity="cheap") for i in range(4)])
    assert pending.pick(None, set()).affinity == "roadmap"
    assert pending.pick(None, {"roadmap"}).affinity == "cheap"
    assert pending.pick(None, {"roadmap", "cheap"}).affinity == "roadmap"  # no times yet: help the largest
    pending.record("roadmap", 301.0, first=True)  # a 300 s build, 1 s tasks: 2 pending tasks never pay for it
    pending.record("roadmap", 1.0, first=False)
    pending.record("cheap", 12.0, first=True)  # a 2 s build, 10 s tasks: even 1 pending task does (5 s saved)
    pending.record("cheap", 10.0, first=False)
    assert len(pending.groups["roadmap"]) == 2 and len(pending.groups["cheap"]) == 3
    assert [pending.pick(None, {"roadmap", "cheap"}).affinity for _ in range(3)] == ["cheap"] * 3
    assert pending.pick(None, {"roadmap", "cheap"}) is None  # only roadmap tasks left: wait for their worker
    assert pending.pick("roadmap", {"cheap"}).affinity == "roadmap"  # the worker that built it takes them


def test_bad_backend_settings_are_clear_errors():
    from psprm_core.errors import PsprmError

    with pytest.raises(PsprmError, match="unknown backend 'spark'"):
        BackendSettings(backend="spark").validate()
    with pytest.raises(PsprmError, match="needs --backend ray"):
        BackendSettings(address="auto").validate()
    with pytest.raises(PsprmError, match="at least one worker"):
        BackendSettings(backend="ray", workers=0).validate()


# ---- the bench -------------------------------------------------------------------------------------------------------
def _bench_cfg(tmp_path, backend, **kw):
    from psprm_core.evaluation.bench import BenchConfig

    base = dict(scene="home", planners=["post", "neural-psprm-line"], problems=3, seed=3, nodes=300, max_frames=3,
                frame_spacing=1.0, target_groups=[["tv"]], out=str(tmp_path / backend), workers=2, backend=backend,
                reference=False)
    base.update(kw)
    return BenchConfig(**base)


def _without_timings(rows) -> dict:
    return {(r["planner"], r["problem"]): json.dumps({k: v for k, v in r.items() if k not in TIMINGS},
                                                      sort_keys=True, default=str) for r in rows}


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    """The reference: the bench on the local backend's worker processes (rows, and the run's journal)."""
    from psprm_core.evaluation.bench import JOURNAL_FILE, run_bench

    cfg = _bench_cfg(tmp_path_factory.mktemp("bench"), "local")
    res = run_bench(cfg, progress=False)
    assert len(res["rows"]) == 6
    return res["rows"], Path(cfg.out) / JOURNAL_FILE


def test_bench_rows_are_the_same_on_local_processes_and_ray_with_a_worker_killed(local_run, ray_cluster, tmp_path):
    """A fixed-seed run gives the same rows (all but the measured times) on the local worker processes and on the Ray
    cluster, although the tasks land on other workers in another order, and although one actor is killed while it
    works: its task runs again on a new actor."""
    from psprm_core.evaluation.bench import JOURNAL_FILE, run_bench

    local_rows, _ = local_run
    workers, killed = {}, []

    def on_start(key, worker):
        workers.setdefault(key, worker)
        if key == ("post", 1) and not killed:
            _kill_after(0.2, int(worker.split("@")[0]), killed)
    cfg = _bench_cfg(tmp_path, "ray")
    res = run_bench(cfg, progress=False, on_start=on_start)
    assert len(killed) == 1
    assert len(set(workers.values())) == 2  # both actors planned
    assert sum(r["success"] for r in res["rows"]) >= 4  # the comparison is about real paths, not failures
    assert _without_timings(res["rows"]) == _without_timings(local_rows)
    recs = [json.loads(line) for line in (Path(cfg.out) / JOURNAL_FILE).read_text().splitlines()[1:]]
    assert sorted(r["attempts"] for r in recs) == [1] * 5 + [2]  # the killed actor's task, once more
    assert not any(r.get("task_failed") for r in recs)


def test_an_interrupted_bench_resumes_on_another_backend(local_run, ray_cluster, tmp_path):
    """The local run's journal, cut short as by an interruption (two tasks lost, one line half written), resumed on
    the Ray cluster: only the missing tasks run, and the rows are the local run's."""
    from psprm_core.errors import PsprmError
    from psprm_core.evaluation.bench import JOURNAL_FILE, run_bench

    local_rows, journal = local_run
    lines = journal.read_text().splitlines()
    lost = {tuple(json.loads(x)["row"][k] for k in ("planner", "problem")) for x in lines[-3:]}
    cfg = _bench_cfg(tmp_path, "ray", resume=True)
    Path(cfg.out).mkdir(parents=True)
    (Path(cfg.out) / JOURNAL_FILE).write_text("\n".join(lines[:-3] + [lines[-3][:25]]) + "\n")
    ran = []
    again = run_bench(cfg, progress=False, on_start=lambda k, w: ran.append(k))
    assert set(ran) == lost and len(ran) == 3
    assert _without_timings(again["rows"]) == _without_timings(local_rows)
    with pytest.raises(PsprmError, match="another configuration .*differs in: seed"):
        run_bench(_bench_cfg(tmp_path, "ray", resume=True, seed=4), progress=False)


# ---- the oracle labelling --------------------------------------------------------------------------------------------
def test_labelling_on_ray_survives_a_killed_worker_and_matches_the_oracle(ray_cluster, tmp_path, caplog):
    """Oracle labelling of studio views on the Ray cluster, one worker killed while it labels: the chunk is labelled
    again and every score is the real oracle's, computed here in this process."""
    from psprm_core.paths import config_dir
    from psprm_core.perception.dataset import OracleFactory, build_dataset, load_dataset
    from psprm_core.scene import load_scene

    path = config_dir() / "scenes" / "surrogate_studio.yaml"
    scene = load_scene(path)
    targets = [scene.target("tv"), scene.target("face")]
    killed = []

    def on_start(chunk, worker):
        if chunk == 1 and not killed:
            _kill_after(0.8, int(worker.split("@")[0]), killed)
    factory = OracleFactory(str(path))
    with caplog.at_level("WARNING", logger="psprm_core.executors"):
        build_dataset(tmp_path / "ds", targets, factory, n_samples=12, chunk_size=3, seed=5, progress=False,
                      backend=BackendSettings(backend="ray", workers=2), on_start=on_start)
    assert len(killed) == 1
    assert any("running it again" in r.getMessage() for r in caplog.records)
    ds = load_dataset(tmp_path / "ds")
    oracle = factory()
    try:
        ref = np.array([oracle.score(p, n).score for p, n in zip(ds.camera_poses, ds.target_names)])
    finally:
        oracle.close()
    assert np.array_equal(ds.scores, ref)
    assert ds.metadata["complete"]


def test_cli_bench_and_dataset_on_ray(ray_cluster, tmp_path, capsys):
    """``psprm bench --backend ray`` and ``psprm dataset --backend ray`` on the running cluster; ``--resume`` of a
    finished run runs nothing and prints the same summary."""
    from psprm_core.cli import main
    from psprm_core.evaluation.bench import JOURNAL_FILE

    out = tmp_path / "bench"
    args = ["bench", "--backend", "ray", "--no-reference", "--scene", "home", "--planners", "post", "--problems", "2",
            "--targets", "tv",
            "--max-frames", "2", "--seed", "3", "--out", str(out), "--no-progress", "--json"]
    assert main(args) == 0
    first = json.loads(capsys.readouterr().out)
    journal = (out / JOURNAL_FILE).read_text()
    assert first["post"]["problems"] == 2 and len(journal.splitlines()) == 3
    assert main(args + ["--resume"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert (out / JOURNAL_FILE).read_text() == journal  # nothing ran again
    assert again == first  # the same rows, the same times

    ds = tmp_path / "views"
    assert main(["dataset", "--backend", "ray", "--workers", "1", "--scene", "surrogate_studio", "--targets", "tv",
                 "--samples", "4", "--chunk", "2", "--out", str(ds)]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["samples"] == 4
    meta = json.loads((ds / "metadata.json").read_text())
    assert meta["complete"] and meta["chunks_done"] == 2
    assert main(["dataset", "--backend", "local", "--address", "auto", "--out", str(ds)]) == 2  # a clear error
    assert "needs --backend ray" in capsys.readouterr().err
