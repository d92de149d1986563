"""``psprm dynbench``: the dynamic benchmark in simulated time (psprm_core.evaluation.dynamic.dynamic_bench): every
scenario's episodes, each with a seeded variation of the people's motion, in every mode (replanning in motion with and
without prediction, from rest, the static first plan, the hindsight reference), judged by the oracle."""

from __future__ import annotations

import argparse
import json
import sys

from .bench import add_backend_arguments


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dynbench", help="dynamic benchmark: scenarios x varied episodes x replanning modes in "
                                        "simulated time, oracle-judged; detection rates, ratios, reached, collisions, "
                                        "stops, goal switches; --json")
    p.add_argument("--scenarios", default=None,
                   help="comma-separated scenario names (config/scenarios) or YAML paths (default: "
                        "rotating_person, moving_obstacle_and_goal, nursing_turning_walking, walking_person, "
                        "rolling_monitor)")
    p.add_argument("--episodes", type=int, default=20, help="episodes per scenario (each a seeded variation of the "
                                                            "people's motion, the same for every mode)")
    p.add_argument("--seed", type=int, default=0, help="seed of the episodes' variations")
    p.add_argument("--modes", default=None,
                   help="comma-separated modes (default: motion, motion_no_prediction, from_rest, static, hindsight)")
    p.add_argument("--latency", type=float, default=0.3,
                   help="replan latency in s: the commit horizon of the motion modes, the wait of from_rest")
    p.add_argument("--history", type=float, default=0.0, metavar="S",
                   help="seconds of the people's poses given to the replanner before the first plan (a motion-capture "
                        "stream running before the goal is given; default 0)")
    p.add_argument("--nodes", type=int, default=None, help="override every scenario's roadmap size")
    p.add_argument("--duration", type=float, default=None, help="override every scenario's time limit (s)")
    p.add_argument("--camera-fps", type=float, default=None,
                   help="override every scenario's oracle frames per simulated second")
    p.add_argument("--no-oracle", action="store_true",
                   help="do not judge the frames (no detection rates and no hindsight reference; a quick check)")
    p.add_argument("--hindsight-searches", default=None,
                   help="candidate searches per goal of the hindsight reference (default own,motion@1.0,eq2@0.8,alt; "
                        "psprm_core.evaluation.dynamic.hindsight): own (the "
                        "planner's objective and alpha), OBJECTIVE@ALPHA, alt (another route)")
    p.add_argument("--hindsight-variants", default=None,
                   help="roadmap scorings of the hindsight candidates (default start,mid): the world at t = 0, "
                        "and the people halfway through the first plan with the obstacles at their final poses")
    p.add_argument("--hindsight-judged", type=int, default=0, metavar="K",
                   help="oracle-judge only the first plan and the K hindsight candidates the planner's scorer predicts "
                        "to see best against the actual motion (default 0: every valid candidate)")
    add_backend_arguments(p, "a task is one episode of one scenario in every mode; each worker builds a scenario's "
                             "roadmap once and loads a copy of it for every mode")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="change one setting of the scenarios' planner (repeatable), e.g. "
                        "--set scoring.alpha=1.0 (PS-PRM settings by dotted path)")
    p.add_argument("--replan", action="append", default=[], metavar="KEY=VALUE",
                   help="change one replanning setting (ReplanSettings; repeatable)")
    p.add_argument("--out", default="out/dynbench.json", help="where the whole result goes (strict JSON)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--json", action="store_true", help="print the whole result as one strict JSON object")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pathlib import Path

    from ..baselines import parse_settings, settings_class
    from ..evaluation.dynamic.dynamic_bench import (DEFAULT_SCENARIOS, DynBenchConfig, load_scenarios, run_dynbench,
                                                    table)
    from ..evaluation.simulation import MODES
    from ..planning.replanner import ReplanSettings

    names = [s.strip() for s in args.scenarios.split(",") if s.strip()] if args.scenarios else DEFAULT_SCENARIOS
    modes = [s.strip() for s in args.modes.split(",") if s.strip()] if args.modes else list(MODES)
    cfg = DynBenchConfig(scenarios=names, episodes=args.episodes, seed=args.seed, modes=modes,
                         latency_s=args.latency, history_s=args.history, nodes=args.nodes, duration_s=args.duration,
                         camera_fps=args.camera_fps, oracle=not args.no_oracle,
                         hindsight_judged=args.hindsight_judged,
                         **{k: v for k, v in (("hindsight_searches", args.hindsight_searches),
                                              ("hindsight_variants", args.hindsight_variants)) if v is not None},
                         backend=args.backend, workers=args.workers if args.workers is not None or
                         args.backend == "ray" else 2, address=args.address, max_retries=args.max_retries)
    cfg.validate()
    planner = load_scenarios(cfg)[0].planner
    cfg.planner_overrides = parse_settings(args.settings, settings_class(planner), planner)
    cfg.replan_overrides = parse_settings(args.replan, ReplanSettings, "replanning", flag="--replan")
    res = run_dynbench(cfg, progress=not args.no_progress)
    text = json.dumps(res, allow_nan=False)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    if args.json:
        print(text)
    else:
        print(table(res))
        if args.out:
            print(f"wrote {args.out}", file=sys.stderr)
    return 0
