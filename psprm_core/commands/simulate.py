"""``psprm simulate``: a dynamic episode with online replanning, judged by the oracle, against a static plan."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="execute a dynamic scenario in simulated time with replanning; oracle-judged "
                                        "camera frames; compared with a single static plan")
    p.add_argument("--scenario", required=True, help="scenario YAML (e.g. config/scenarios/rotating_person.yaml) or "
                                                     "the name of a shipped one")
    p.add_argument("--mode", default="motion", choices=("motion", "motion_no_prediction", "from_rest"),
                   help="how the robot replans (psprm_core.evaluation.simulation): in motion from its committed state "
                        "with target prediction (default), the same without prediction, or from rest (it stops, "
                        "waits the latency, starts the new plan; --mode from_rest --latency 0 is the former "
                        "behaviour)")
    p.add_argument("--latency", type=float, default=0.3,
                   help="replan latency in s: the commit horizon of the motion modes, the wait of from_rest")
    p.add_argument("--nodes", type=int, default=None, help="override the scenario's roadmap size")
    p.add_argument("--duration", type=float, default=None, help="override the scenario's time limit (s)")
    p.add_argument("--no-static", action="store_true", help="skip the static single-plan comparison")
    p.add_argument("--plot", default=None, help="figure path (default out/simulate_<scenario>.png)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="change one setting of the scenario's planner (repeatable), e.g. "
                        "--set scoring.alpha=1.0 (PS-PRM settings by dotted path)")
    p.add_argument("--replan", action="append", default=[], metavar="KEY=VALUE",
                   help="change one replanning setting (ReplanSettings; repeatable), e.g. --replan route_selection=true")
    p.add_argument("--json", action="store_true", help="print one JSON object (strict: null, never NaN)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pathlib import Path

    from ..baselines import parse_settings, settings_class
    from ..evaluation.simulation import load_scenario, simulate
    from ..paths import resolve_named
    from ..planning.replanner import ReplanSettings

    path = Path(args.scenario)
    if not path.is_file():
        path = resolve_named("scenario", args.scenario)
    plot = args.plot or f"out/simulate_{path.stem}.png"
    planner = load_scenario(path).planner
    overrides = parse_settings(args.settings, settings_class(planner), planner)
    replan = parse_settings(args.replan, ReplanSettings, "replanning", flag="--replan")
    res = simulate(path, compare_static=not args.no_static, plot=plot, threads=args.threads, nodes=args.nodes,
                   duration_s=args.duration, planner_overrides=overrides, replan_overrides=replan, mode=args.mode,
                   latency_s=args.latency)
    if args.json:
        print(json.dumps(res, allow_nan=False))
    else:
        log = res.pop("replan_log")
        print(json.dumps(res, indent=2, allow_nan=False))
        print(f"{len(log)} replans; first: {log[:3]}")
    return 0
