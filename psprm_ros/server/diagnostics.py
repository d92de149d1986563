"""The planning loop's diagnostic status."""

from __future__ import annotations

import time

from .. import core


def loop_diagnostics(loop, lifecycle: str) -> tuple:
    """(level, message, values) of a :class:`~.loop.PlanningLoop`'s diagnostic status; ``lifecycle`` is the node's
    state label. The values: its counters, the latency of its last plan, the age of every input, heap trims and the
    replanner's decisions (replans adopted and declined, goal switches)."""
    if loop.rp is None:
        level, msg = core.DIAG_WARN, f"{lifecycle}: roadmap not ready"
    elif not loop.active:
        level, msg = core.DIAG_WARN, f"{lifecycle}"
    elif loop.waiting:
        level, msg = core.DIAG_WARN, loop.waiting
    else:
        level, msg = core.DIAG_OK, "planning" if not loop.idle.is_set() else "ready"
    now = time.monotonic()
    rx, ages = loop.inputs.ages()
    vals = {"lifecycle": lifecycle,
            "roadmap_nodes": int(loop.planner.n_roadmap_nodes) if loop.planner else 0,
            **loop.counts, "last_latency_ms": loop.last_latency_ms if loop.last_latency_ms is not None else "",
            "robot_state_age_s": (now - rx) if rx is not None else "never", **ages,
            "heap_trims": loop.heap_trims, "last_heap_trim_ms": loop.heap_trim_ms if loop.heap_trim_ms is not None
            else ""}
    rp = loop.rp
    if rp is not None:  # the replanner's decisions: replans adopted / declined (kept), goal switches
        vals.update(adopted_replans=rp.adopted, declined_replans=rp.declined, goal_switches=rp.goal_switches)
    return level, msg, vals
