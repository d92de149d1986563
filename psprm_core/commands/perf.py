"""``psprm perf``: benchmarks that print numbers (kinematics, planner, replanning, perception, execution backends)."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import os
import sys


@contextlib.contextmanager
def stdout_to_stderr():
    """Everything written to stdout inside the block, by Python or by C code (pybullet's URDF warnings), goes to
    stderr; what Python prints is collected in the yielded buffer instead."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            yield buf
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def print_json(obj) -> None:
    """One JSON object on stdout, non-finite numbers as null."""
    print(json.dumps(_finite(obj), allow_nan=False))


def _json_only(fn):
    """With ``--json``, stdout carries the JSON object only: anything else written there while the benchmark runs
    (pybullet's C-level URDF warnings included) goes to stderr, and non-finite numbers become null."""
    def run(args):
        if not getattr(args, "json", False):
            return fn(args)
        with stdout_to_stderr() as buf:
            rc = fn(args)
        for line in buf.getvalue().splitlines():
            if line.strip():
                print_json(json.loads(line))
        return rc
    return run


def _finite(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("perf", help="benchmarks (print numbers; ratios measured in the same run)")
    ps = p.add_subparsers(dest="perf_command", metavar="BENCH")
    k = ps.add_parser("kinematics", help="batched FK + collision vs pybullet's exact check (same configurations)")
    k.add_argument("--robot", required=True)
    k.add_argument("--scene", required=True)
    k.add_argument("--n", type=int, default=10000, help="number of random configurations (default 10000)")
    k.add_argument("--seed", type=int, default=0)
    k.add_argument("--threads", type=int, default=2)
    k.add_argument("--kinematics", choices=["native", "pytorch_kinematics"], default="native",
                   help="pytorch_kinematics: also the whole-body FK of the robot model, pytorch-kinematics and "
                        "pybullet side by side (throughput, agreement with pybullet, torch-path collision checks)")
    k.add_argument("--json", action="store_true", help="print one JSON object")
    k.set_defaults(func=_json_only(_kinematics))
    pl = ps.add_parser("planner", help="PS-PRM build time (incl. neural scoring, occlusion, collision) and query time")
    pl.add_argument("--scene", required=True)
    pl.add_argument("--planner", default="neural-psprm-line")
    pl.add_argument("--target", default=None)
    pl.add_argument("--nodes", type=int, default=3000)
    pl.add_argument("--queries", type=int, default=50)
    pl.add_argument("--seed", type=int, default=0)
    pl.add_argument("--heuristic", choices=["hop", "exact"], default=None, help="A* heuristic (default: settings)")
    pl.add_argument("--threads", type=int, default=2)
    pl.add_argument("--unaimed", action="store_true", help="ends not required to face the target (see benchmarks)")
    pl.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                    help="change one planner setting (repeatable), e.g. "
                         "--set query.route_searches=eq2@0.8,motion@1.0 (by dotted path)")
    pl.add_argument("--json", action="store_true")
    pl.set_defaults(func=_json_only(_planner))
    cp = ps.add_parser("compare", help="success over random problems and oracle-judged perception: PS-PRM vs the "
                                       "same roadmap with alpha = 0 (shortest path)")
    cp.add_argument("--scene", required=True)
    cp.add_argument("--planner", default="neural-psprm-line")
    cp.add_argument("--target", default=None)
    cp.add_argument("--nodes", type=int, default=3000)
    cp.add_argument("--problems", type=int, default=100)
    cp.add_argument("--oracle-problems", type=int, default=None, help="judge only the first N paths with the oracle")
    cp.add_argument("--frames", type=int, default=12, help="oracle frames per path")
    cp.add_argument("--seed", type=int, default=0)
    cp.add_argument("--threads", type=int, default=2)
    cp.add_argument("--unaimed", action="store_true", help="ends not required to face the target (see benchmarks)")
    cp.add_argument("--json", action="store_true")
    cp.set_defaults(func=_json_only(_compare))
    pp = ps.add_parser("preprocess", help="preprocessing of neural vs oracle PS-PRM (every edge scored at build): "
                                          "a measured ratio at --oracle-nodes, extrapolated to --nodes")
    pp.add_argument("--scene", default="home")
    pp.add_argument("--target", default=None)
    pp.add_argument("--nodes", type=int, default=3000)
    pp.add_argument("--oracle-nodes", type=int, default=30, help="size of the roadmaps built with both scorers")
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument("--threads", type=int, default=2)
    pp.add_argument("--json", action="store_true")
    pp.set_defaults(func=_json_only(_preprocess))
    tr = ps.add_parser("transfer", help="neural scorer vs the real detector on the planner's own roadmap nodes: "
                                        "rank correlation overall and by distance to the target")
    tr.add_argument("--scene", default="home")
    tr.add_argument("--target", default=None)
    tr.add_argument("--samples", type=int, default=200, help="roadmap nodes scored by both (oracle: ~0.17 s each)")
    tr.add_argument("--nodes", type=int, default=3000)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--threads", type=int, default=2)
    tr.add_argument("--checkpoints", default="", help="further surrogate checkpoints (comma-separated) scored on "
                                                      "the same views against the same oracle labels")
    tr.add_argument("--json", action="store_true")
    tr.set_defaults(func=_json_only(_transfer))
    ln = ps.add_parser("label-noise", help="test-retest reliability of the oracle labels: held-out test views of "
                                           "the surrogate's dataset relabelled after a pose change no planner "
                                           "resolves, against the surrogate on the same views")
    from .surrogate import DEFAULT_DATASET

    ln.add_argument("--checkpoint", default="psprm_core/data/surrogate.pt",
                    help="surrogate whose held-out test split is used and which is judged on the same views")
    ln.add_argument("--dataset", default=DEFAULT_DATASET, help="dataset directories, comma-separated (as the "
                                                              "checkpoint was trained on)")
    ln.add_argument("--per-class", type=int, default=200, help="test views drawn per class (the cup's tiled "
                                                               "detector: ~0.5 s a view, the others ~0.1 s)")
    ln.add_argument("--translation", type=float, default=0.01, help="camera moved by this many metres")
    ln.add_argument("--rotation-deg", type=float, default=0.5, help="and turned by this many degrees")
    ln.add_argument("--seed", type=int, default=0, help="seeds the views drawn and the directions of the change")
    ln.add_argument("--threads", type=int, default=1, help="detector and torch threads")
    ln.add_argument("--checkpoints", default="", help="further surrogate checkpoints (comma-separated) judged on "
                                                      "the same views against the same labels")
    ln.add_argument("--no-reproduce", action="store_true", help="skip relabelling the unperturbed views (the "
                                                                "check that this oracle reproduces the stored labels)")
    ln.add_argument("--allow-incomplete", action="store_true", help="a dataset whose build was stopped")
    ln.add_argument("--out", default=None, help="also write the full record (per-view labels) as JSON here")
    ln.add_argument("--record", default=None, help="judge the views and labels of an earlier run's --out record "
                                                   "again (no oracle; e.g. with other --checkpoints)")
    ln.add_argument("--json", action="store_true")
    ln.set_defaults(func=_json_only(_label_noise))
    sc = ps.add_parser("surrogate-scaling", help="the surrogate's held-out figures against the share of its "
                                                 "training data used, several seeds, an ensemble and a wider "
                                                 "network: what more labelled views would buy")
    sc.add_argument("--dataset", default=DEFAULT_DATASET, help="dataset directories, comma-separated")
    sc.add_argument("--fractions", default="0.25,0.5,1", help="shares of the training split, comma-separated")
    sc.add_argument("--seeds", default="0,1", help="training seeds per share, comma-separated")
    sc.add_argument("--ensemble", type=int, default=0, help="also average this many full-data models")
    sc.add_argument("--hidden", type=int, default=0, help="also train a network this wide on the full split")
    sc.add_argument("--target", type=float, default=0.946, help="pooled Spearman to extrapolate the views for")
    sc.add_argument("--threads", type=int, default=2)
    sc.add_argument("--allow-incomplete", action="store_true", help="a dataset whose build was stopped")
    sc.add_argument("--json", action="store_true")
    sc.set_defaults(func=_json_only(_surrogate_scaling))
    pr = ps.add_parser("prediction", help="how well the target predictor forecasts the scenarios' people: heading "
                                          "CRPS and position error per horizon, shipped settings vs the latest pose")
    pr.add_argument("--scenarios", default="rotating_person,walking_person,nursing_turning_walking")
    pr.add_argument("--episodes", default="100-104", help="episode indices, FIRST-LAST or comma-separated (the "
                                                          "dynamic benchmark runs 0..N-1 with the same seed)")
    pr.add_argument("--seed", type=int, default=0, help="seed of the episodes' variations")
    pr.add_argument("--horizons", default="1,2,4,8", help="forecast horizons in s, comma-separated")
    pr.add_argument("--change", action="append", default=[], metavar="KEY=VALUE",
                    help="also score the shipped prediction settings with this change (PredictionSettings; "
                         "repeatable)")
    pr.add_argument("--json", action="store_true")
    pr.set_defaults(func=_json_only(_prediction))
    vm = ps.add_parser("viewmap", help="where the real detector sees a target: the robot's camera aimed at it from a "
                                       "grid of base positions (share detected, mean confidence, the grid)")
    vm.add_argument("--scene", default="home")
    vm.add_argument("--target", default=None,
                    help="target name (default: the scene's first); 'a,b': several, aimed at their midpoint")
    vm.add_argument("--spacing", type=float, default=0.5, help="grid spacing in metres")
    vm.add_argument("--placement", type=int, default=0,
                    help="move the target(s) to this placement of the scene's first (0: their own pose)")
    vm.add_argument("--extra-roll-deg", type=float, default=0.0,
                    help="roll the image about the line of sight (90: what a sideways camera shows the detector)")
    vm.add_argument("--json", action="store_true")
    vm.set_defaults(func=_json_only(_viewmap))
    be = ps.add_parser("backends", help="execution backends (local processes, Ray): start-up and per-task dispatch "
                                        "cost, PS-PRM reset cost, oracle seconds per labelled view; with --results "
                                        "the per-task cost of each planner of a bench run and the projected hours "
                                        "of the 2,500-problem protocol and a 100,000-view dataset on N nodes")
    be.add_argument("--workers", type=int, default=2)
    be.add_argument("--tasks", type=int, default=200, help="no-op tasks for the dispatch throughput")
    be.add_argument("--nodes", type=int, default=3000, help="roadmap size for the reset cost")
    be.add_argument("--views", type=int, default=5, help="views per studio target for the labelling cost")
    be.add_argument("--address", default=None, help="a running Ray cluster (default: a local one)")
    be.add_argument("--results", default=None, help="a bench run's results.csv or rows.jsonl: per-task costs and "
                                                    "the projection")
    be.add_argument("--cores", type=int, default=2, help="cores (workers) per node in the projection")
    be.add_argument("--instances", type=int, default=None, help="planner instances per planner in the projection "
                                                                "(default: the run's; the paper's protocol: 3 "
                                                                "objects x 5 poses = 15)")
    be.add_argument("--view-s", type=float, default=None, help="seconds per labelled view for the projection "
                                                               "(default: measured)")
    be.add_argument("--projection-only", action="store_true", help="only --results (no measurements)")
    be.add_argument("--json", action="store_true")
    be.set_defaults(func=_json_only(_backends))
    rp = ps.add_parser("replan", help="online replanning latency: target / obstacle / goal moves (update + re-search "
                                      "until a verified path), and the cost of a full re-score")
    rp.add_argument("--scene", default="dynamic_person")
    rp.add_argument("--planner", default="neural-psprm-line")
    rp.add_argument("--target", default=None)
    rp.add_argument("--nodes", type=int, default=3000)
    rp.add_argument("--updates", type=int, default=50, help="updates per kind (default 50)")
    rp.add_argument("--heuristic", choices=["hop", "exact"], default=None,
                    help="A* heuristic of the replans (default: ReplanSettings.heuristic, exact)")
    rp.add_argument("--seed", type=int, default=0)
    rp.add_argument("--threads", type=int, default=2)
    rp.add_argument("--json", action="store_true")
    rp.set_defaults(func=_json_only(_replan))
    rm = ps.add_parser("replan-motion", help="replans of a robot in motion (committed state, splice, keep decision) "
                                             "with target prediction off, on, on without the periodic component, "
                                             "and on with the routes of the predicted headings, alternated")
    rm.add_argument("--nodes", type=int, default=3000)
    rm.add_argument("--replans", type=int, default=30)
    rm.add_argument("--rounds", type=int, default=2)
    rm.add_argument("--seed", type=int, default=0)
    rm.add_argument("--threads", type=int, default=1)
    rm.add_argument("--history-s", type=float, default=4.0,
                    help="seconds of the person's poses before the first plan (default 4; a period is found after "
                         "about 1.6 turns)")
    rm.add_argument("--turn-period-s", type=float, default=20.0, help="the person's turn (default 20 s, the "
                                                                      "shipped recording's)")
    rm.add_argument("--variants", default=None, help="comma-separated: off, prediction, no_period, "
                                                     "predicted_routes (default: all)")
    rm.add_argument("--json", action="store_true")
    rm.set_defaults(func=_json_only(_replan_motion))
    tk = ps.add_parser("tracking", help="the path tolerance's measure (a splice check, a control step): compiled "
                                        "corner kernel vs torch FK, same inputs")
    tk.add_argument("--robot", default="stretch2")
    tk.add_argument("--rounds", type=int, default=20)
    tk.add_argument("--seed", type=int, default=0)
    tk.add_argument("--threads", type=int, default=1)
    tk.add_argument("--json", action="store_true", help="print one JSON object")
    tk.set_defaults(func=_json_only(_tracking))
    dg = ps.add_parser("digest", help="fixed-seed plans and replans on every shipped scene, written to a file or "
                                      "compared with an earlier one (identical paths, costs within --tol)")
    dg.add_argument("--out", default=None, help="write the record here")
    dg.add_argument("--against", default=None, help="compare with this earlier record (exit 1 on a difference)")
    dg.add_argument("--scenes", default=None, help="comma-separated scene names (default: all shipped)")
    dg.add_argument("--nodes", type=int, default=400)
    dg.add_argument("--seed", type=int, default=3)
    dg.add_argument("--tol", type=float, default=1e-6)
    dg.set_defaults(func=_digest)


def _backends(args) -> int:
    from ..evaluation.scaling import backend_overheads, projection_table, read_rows, task_costs

    out = {}
    if not args.projection_only:
        out = backend_overheads(workers=args.workers, tasks=args.tasks, nodes=args.nodes, views=args.views,
                                address=args.address)
    if args.results:
        costs = task_costs(read_rows(args.results))
        out["task_costs"] = costs
        view_s = args.view_s if args.view_s else (
            float(sum(out["labelling"]["per_view_s"].values()) / len(out["labelling"]["per_view_s"]))
            if "labelling" in out else 0.0)
        over = out["ray"]["dispatch_ms_per_task"] / 1e3 if "ray" in out else 0.0
        start = out["ray"]["start_s"] if "ray" in out else 0.0
        out["projection_hours"] = projection_table(costs, view_s, cores=args.cores, overhead_s=over, start_s=start,
                                                   instances=args.instances)
        out["projection_inputs"] = {"per_view_s": view_s, "overhead_s": over, "start_s": start, "cores": args.cores}
    print(json.dumps(out, indent=None if args.json else 2, default=float))
    return 0


def _digest(args) -> int:
    from .digest import run

    return run(args)


def _replan(args) -> int:
    from ..evaluation.benchmarks import replan_benchmark

    _print(replan_benchmark(args.scene, args.planner, nodes=args.nodes, updates=args.updates, seed=args.seed,
                            threads=args.threads, target=args.target, heuristic=args.heuristic), args.json)
    return 0


def _replan_motion(args) -> int:
    from ..evaluation.dynamic.motion_replan import VARIANTS, motion_replan_benchmark

    variants = tuple(v.strip() for v in args.variants.split(",") if v.strip()) if args.variants else VARIANTS
    _print(motion_replan_benchmark(nodes=args.nodes, replans=args.replans, rounds=args.rounds, seed=args.seed,
                                   threads=args.threads, history_s=args.history_s, turn_period_s=args.turn_period_s,
                                   variants=variants), args.json)
    return 0


def _tracking(args) -> int:
    from ..evaluation.tracking_bench import tracking_benchmark

    _print(tracking_benchmark(args.robot, rounds=args.rounds, seed=args.seed, threads=args.threads), args.json)
    return 0


def _kinematics(args) -> int:
    from ..evaluation.benchmarks import kinematics_benchmark

    res = kinematics_benchmark(args.robot, args.scene, n=args.n, seed=args.seed, threads=args.threads)
    if args.kinematics == "pytorch_kinematics":
        from ..evaluation.fk_compare import body_fk_comparison

        res.update(body_fk_comparison(args.robot, args.scene, n=args.n, seed=args.seed, threads=args.threads))
    _print(res, args.json)
    return 0


def _print(res: dict, as_json: bool) -> None:
    """One JSON object, or one ``key value`` line per entry."""
    if as_json:
        print(json.dumps(res))
        return
    for k, v in res.items():
        print(f"{k:28s} {v:.6g}" if isinstance(v, float) else f"{k:28s} {v}")


def _planner(args) -> int:
    from ..baselines import parse_planner_settings
    from ..evaluation.benchmarks import planner_benchmark

    overrides = parse_planner_settings([f"{args.planner}.{s}" for s in args.settings], [args.planner]).get(
        args.planner, {})
    _print(planner_benchmark(args.scene, args.planner, nodes=args.nodes, queries=args.queries, seed=args.seed,
                             threads=args.threads, target=args.target, heuristic=args.heuristic,
                             aimed=not args.unaimed, overrides=overrides), args.json)
    return 0


def _compare(args) -> int:
    from ..evaluation.benchmarks import compare_with_shortest_path

    res = compare_with_shortest_path(args.scene, args.planner, nodes=args.nodes, problems=args.problems,
                                     frames=args.frames, seed=args.seed, threads=args.threads, target=args.target,
                                     oracle_problems=args.oracle_problems, aimed=not args.unaimed)
    print(json.dumps(res) if args.json else json.dumps(res, indent=2))
    return 0


def _viewmap(args) -> int:
    from ..evaluation.viewmap import detection_map

    res = detection_map(args.scene, args.target, spacing=args.spacing, extra_roll_deg=args.extra_roll_deg,
                        placement=args.placement)
    if args.json:
        print(json.dumps(res))
        return 0
    at = f" (placement {res['placement']})" if res["placement"] else ""
    head = (f"{res['scene']} / {res['target']}{at}: camera at {res['camera_height_m']:.2f} m, image "
            f"{res['intrinsics'][0]}x{res['intrinsics'][1]}, extra roll {res['extra_roll_deg']:g} deg; ")
    if "detected" not in res:  # one target
        print(head + f"detected (>= {res['threshold']:.2f}) from {100 * res['detected_share']:.1f} % of "
              f"{res['points']} points, mean confidence {res['mean_confidence']:.3f} ('#' detected, '+' seen below "
              f"threshold, '.' not seen, blank: obstacle)")
        for y, row in zip(res["y"], res["grid"]):
            print(f"y {y:5.2f} " + "".join(" " if v is None else "#" if v >= res["threshold"] else "+" if v > 0
                                          else "." for v in row))
        return 0
    n = len(res["targets"])
    print(head + f"aimed at their midpoint: all {n} detected from {100 * res['detected_share']:.1f} %, at least one "
          f"from {100 * res['detected_share_any']:.1f} % of {res['points']} points, mean confidence "
          f"{res['mean_confidence']:.3f} ('#' all detected, digit: how many, '.' none, blank: obstacle)")
    for y, row in zip(res["y"], res["detected"]):
        print(f"y {y:5.2f} " + "".join(" " if h is None else "#" if h == n else "." if h == 0 else str(h)
                                      for h in row))
    return 0


def _transfer(args) -> int:
    from ..evaluation.benchmarks import surrogate_transfer

    _print(surrogate_transfer(args.scene, args.target, samples=args.samples, nodes=args.nodes, seed=args.seed,
                              threads=args.threads, checkpoints=[c for c in args.checkpoints.split(",") if c]),
           args.json)
    return 0


def _preprocess(args) -> int:
    from ..evaluation.benchmarks import preprocess_benchmark

    _print(preprocess_benchmark(args.scene, args.target, nodes=args.nodes, oracle_nodes=args.oracle_nodes,
                                seed=args.seed, threads=args.threads), args.json)
    return 0


def _surrogate_scaling(args) -> int:
    from ..evaluation.surrogate_scaling import format_table, surrogate_scaling

    res = surrogate_scaling([d for d in args.dataset.split(",") if d],
                            fractions=[float(f) for f in args.fractions.split(",") if f],
                            seeds=[int(s) for s in args.seeds.split(",") if s], ensemble=args.ensemble,
                            hidden=args.hidden or None, threads=args.threads, target=args.target,
                            allow_incomplete=args.allow_incomplete)
    if args.json:
        print_json(_finite(res))
    else:
        print(format_table(res))
    return 0


def _prediction(args) -> int:
    import dataclasses

    from ..baselines import parse_settings
    from ..evaluation.dynamic.prediction_score import format_table, prediction_scores
    from ..prediction import PredictionSettings

    first, dash, last = args.episodes.partition("-")
    episodes = (list(range(int(first), int(last) + 1)) if dash else [int(e) for e in args.episodes.split(",") if e])
    variants = {"shipped": PredictionSettings(), "latest_pose": PredictionSettings(enabled=False)}
    if args.change:
        changed = parse_settings(args.change, PredictionSettings, "prediction", flag="--change")
        variants["changed"] = dataclasses.replace(PredictionSettings(), **changed)
    res = prediction_scores(variants, [s for s in args.scenarios.split(",") if s], episodes,
                            [float(h) for h in args.horizons.split(",") if h], seed=args.seed)
    if args.change:
        res["change"] = list(args.change)
    if args.json:
        print_json(_finite(res))
    else:
        print(format_table(res))
    return 0


def _label_noise(args) -> int:
    from pathlib import Path

    from ..evaluation.label_noise import label_noise

    res = label_noise(args.checkpoint, args.dataset, per_class=args.per_class, translation=args.translation,
                      rotation_deg=args.rotation_deg, seed=args.seed, threads=args.threads,
                      checkpoints=[c for c in args.checkpoints.split(",") if c], reproduce=not args.no_reproduce,
                      allow_incomplete=args.allow_incomplete,
                      record=json.loads(Path(args.record).read_text()) if args.record else None)
    if args.out:
        Path(args.out).write_text(json.dumps(_finite(res), allow_nan=False))
    res.pop("views")
    if args.json:
        print_json(res)
        return 0
    print(("labels of " + args.record + ": " if args.record else "") +
          f"{res['views_relabelled']} held-out test views relabelled after a {100 * res['translation_m']:g} cm / "
          f"{res['rotation_deg']:g} deg camera change ({res['target_left_view']} moved out of the image, "
          f"{res['target_out_of_view_before']} out of it before), oracle "
          f"{res['oracle_s']:.0f} s")
    if "reproduction" in res:
        r = res["reproduction"]
        print(f"unperturbed views relabelled: {100 * r['identical_fraction']:.1f} % identical to the stored labels, "
              f"max difference {r['max_abs_diff']:.3g}")
    preds = [k for k in res["per_class"]["pooled"] if k not in ("n", "positive_rate", "zero_fraction", "retest")]
    print(f"{'class':14s} {'n':>4s} {'pos':>5s} {'zero':>5s} | {'retest rho':>10s} {'ceiling':>7s} {'rmse':>6s} "
          f"{'f1':>5s} | " + " | ".join(f"{k[-24:]:>24s}" for k in preds))
    for c, st in res["per_class"].items():
        rt = st["retest"]
        cells = " | ".join(f"rho {st[k]['spearman']:.3f} rmse {st[k]['rmse']:.3f} f1 {st[k]['f1']:.2f}".rjust(24)
                           for k in preds)
        print(f"{c:14s} {st['n']:4d} {st['positive_rate']:5.2f} {st['zero_fraction']:5.2f} | "
              f"{rt['spearman']:10.3f} {rt['ceiling_spearman']:7.3f} {rt['rmse']:6.3f} {rt['f1']:5.2f} | {cells}")
    return 0
