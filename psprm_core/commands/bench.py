"""``psprm bench``: every planner on the same random problems, judged by the real detector (paper Tables II/III)."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run planners on the same random problems (or runs of a named one); "
                                     "oracle-judged detection, tracking, path length, success and times; CSV, "
                                     "Markdown table, plots, --json")
    p.add_argument("--scene", default="home")
    p.add_argument("--planners", default="all",
                   help="comma-separated names, or 'all' (see psprm_core.baselines); NAME~LABEL runs planner NAME "
                        "under its own label, e.g. neural-psprm-line~paper with --set neural-psprm-line~paper.KEY=V")
    p.add_argument("--problems", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output directory (default out/bench_<scene>)")
    p.add_argument("--timeout", type=float, default=10.0, help="per-problem planning time cap in s (paper: 60)")
    add_backend_arguments(p, "a task is one planner on one problem; each worker prepares a planner once per target "
                             "group and placement and keeps it for its later problems")
    p.add_argument("--resume", action="store_true",
                   help="skip the (planner, problem) tasks an earlier run of the same configuration finished (its "
                        "journal OUT/rows.jsonl); without it a run starts afresh")
    p.add_argument("--nodes", type=int, default=None, help="PS-PRM roadmap size (default: config/planners/psprm.yaml)")
    p.add_argument("--oracle-nodes", type=int, default=None, help="roadmap size of the oracle PS-PRM variants")
    p.add_argument("--targets", default=None,
                   help="target groups: 'a,b;c' = a and b kept in view together, c alone (default: per scene)")
    p.add_argument("--scenario", default=None, metavar="PROBLEM",
                   help="run the scene's named problem PROBLEM --problems times as independent runs (every planner "
                        "built anew per run with seed + run; the paper's Table III protocol), instead of random "
                        "problems")
    p.add_argument("--placements", type=int, default=1, metavar="K",
                   help="spread the problems over the first K poses of each target (the scene's 'placements'; the "
                        "paper: five per object), one planner instance per target and placement")
    p.add_argument("--frame-spacing", type=float, default=0.5, help="motion-cost units between judged frames")
    p.add_argument("--max-frames", type=int, default=20, help="judged frames per path at most")
    p.add_argument("--set", action="append", default=[], metavar="PLANNER.KEY=VALUE", dest="settings",
                   help="change one setting of one planner for this run (repeatable), e.g. "
                        "neural-psprm-line.scoring.alpha=0.95 (PS-PRM settings by dotted path); checked against the "
                        "planner's settings class")
    p.add_argument("--no-reference", action="store_true",
                   help="do not judge the reference routes (the best-perceived routes of the PS-PRM roadmap) that "
                        "headroom_captured and unseeable_frame_rate are measured against")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--json", action="store_true", help="print one JSON object keyed by planner")
    p.set_defaults(func=_bench)


def add_backend_arguments(p: argparse.ArgumentParser, what: str, in_process: int = 1) -> None:
    """``--backend``, ``--workers``, ``--address``, ``--max-retries`` (psprm_core.executors); ``--workers
    in_process`` (or fewer) on the local backend runs the tasks in this process."""
    p.add_argument("--backend", choices=("local", "ray"), default="local",
                   help=f"where the tasks run: local worker processes, or actors on a Ray cluster ({what})")
    p.add_argument("--workers", type=int, default=None,
                   help="concurrent workers (default: 2 local processes; ray: one per CPU of the cluster at "
                        f"--address, 2 for a local cluster); local {in_process} runs in this process")
    p.add_argument("--address", default=None,
                   help="ray: the cluster to use ('auto', HOST:6379, ray://HOST:10001); default: start a local "
                        "cluster for the run and stop it afterwards")
    p.add_argument("--max-retries", type=int, default=2,
                   help="times a task whose worker died is run again before it is reported as failed")


def _bench(args) -> int:
    from ..baselines import parse_planner_settings, planner_names
    from ..evaluation.bench import BenchConfig, backend_settings, json_summary, run_bench, write_outputs
    from ..errors import PsprmError

    names = planner_names() if args.planners == "all" else [s.strip() for s in args.planners.split(",") if s.strip()]
    if args.problems < 1:
        raise PsprmError("--problems must be at least 1")
    if args.placements < 1:
        raise PsprmError("--placements must be at least 1")
    groups = None
    if args.targets:
        groups = [[t.strip() for t in g.split(",") if t.strip()] for g in args.targets.split(";") if g.strip()]
    cfg = BenchConfig(scene=args.scene, planners=names, problems=args.problems, seed=args.seed,
                      out=args.out or f"out/bench_{args.scene}", timeout_s=args.timeout,
                      workers=args.workers if args.workers is not None or args.backend == "ray" else 2,
                      nodes=args.nodes, oracle_nodes=args.oracle_nodes, frame_spacing=args.frame_spacing,
                      max_frames=args.max_frames, target_groups=groups, scenario=args.scenario,
                      placements=args.placements, reference=not args.no_reference,
                      planner_kwargs=parse_planner_settings(args.settings, names), backend=args.backend,
                      address=args.address, max_retries=args.max_retries, resume=args.resume)
    backend_settings(cfg).validate()
    res = run_bench(cfg, progress=not args.no_progress)
    files = write_outputs(res, cfg.out)
    if args.json:
        print(json.dumps(json_summary(res["summary"])))
    else:
        print((files["table"]).read_text())
        print(f"wrote {', '.join(str(f) for f in files.values())}", file=sys.stderr)
    return 0
