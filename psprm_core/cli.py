"""``psprm``: the library's command line.

Each subcommand lives in its own module exposing ``register(subparsers)``; this file only collects them.
Errors caused by bad input (:class:`~psprm_core.errors.PsprmError`) are printed as one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from .errors import PsprmError

# Modules that contribute subcommands (imported lazily so ``psprm --help`` stays fast).
SUBCOMMAND_MODULES = [
    "psprm_core.commands.demo",
    "psprm_core.commands.robot",
    "psprm_core.commands.perf",
    "psprm_core.commands.perception",
    "psprm_core.commands.planning",
    "psprm_core.commands.surrogate",
    "psprm_core.commands.bench",
    "psprm_core.commands.simulate",
    "psprm_core.commands.dynbench",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="psprm",
        description=(
            "Perception-score-guided probabilistic roadmaps (PS-PRM) for mobile manipulators with a camera.\n"
            "Subcommands load robots and scenes by name from config/ (or a YAML path)."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # that command group is not part of this build
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except PsprmError as exc:
        print(f"psprm {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
