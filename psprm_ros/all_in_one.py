"""``all_in_one``: ``roadmap_server``, ``perception_scorer``, ``replan_monitor`` and ``robot_adapter`` in one
process, each on its own single-threaded executor: one copy of the core, the least memory, no inter-process hop. The
nodes share one interpreter lock, though: under a 120 Hz mocap stream the monitor's and the adapter's callbacks hold
it while the server plans, and in the README's closed loop the replans take about twice as long as with a process
per node (``scripts/run_nodes.sh``, docs/benchmarks.md). The adapter drives the robot's controllers (``adapter``
parameter); set ``robot_adapter:autostart:=false`` to plan without executing.

Same parameters and topics as the separate nodes; one params file (``/**`` section shared, one section per node).
"""

from __future__ import annotations

from .perception_scorer import PerceptionScorer
from .replan_monitor import ReplanMonitor
from .roadmap_server import RoadmapServer
from .robot_adapter import RobotAdapter
from .runner import run_nodes


def factories() -> list:
    return [RoadmapServer, PerceptionScorer, ReplanMonitor, RobotAdapter]


def main(args=None) -> int:
    return run_nodes(factories(), args, description=__doc__, prog="all_in_one")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
