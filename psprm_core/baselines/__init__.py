"""Benchmark planners: the paper's baselines and thin adapters around the PS-PRM variants (paper Table II).

``make_baseline(name, scene, targets)`` builds any planner of :func:`planner_names` behind the common
:class:`~psprm_core.baselines.base.BenchPlanner` interface. Modules are imported lazily (by ``"module:Class"``
strings), so importing this package does no work.
"""

from __future__ import annotations

import importlib
from typing import Sequence

from ..errors import PsprmError

#: Planner name -> ``"module:Class"`` (imported on first use).
BASELINES = {
    "post": "psprm_core.baselines.post:PostPlanner",
    "rejection": "psprm_core.baselines.rejection:RejectionPlanner",
    "manifold-line": "psprm_core.baselines.manifold:ManifoldLinePlanner",
    "manifold-frustum": "psprm_core.baselines.manifold:ManifoldFrustumPlanner",
    "trajopt": "psprm_core.baselines.trajopt:TrajOptPlanner",
    "rl-ppo": "psprm_core.baselines.rl_ppo:PPOPlanner",
    "psprm-line": "psprm_core.baselines.psprm_adapter:PSPRMBenchPlanner",
    "psprm-frustum": "psprm_core.baselines.psprm_adapter:PSPRMBenchPlanner",
    "neural-psprm-line": "psprm_core.baselines.psprm_adapter:PSPRMBenchPlanner",
    "neural-psprm-frustum": "psprm_core.baselines.psprm_adapter:PSPRMBenchPlanner",
}


def planner_names() -> list:
    """Every benchmark planner, in the order of the paper's Table II."""
    return list(BASELINES)


def resolve(name: str) -> type:
    """The planner class registered under ``name``."""
    if name not in BASELINES:
        raise PsprmError(f"unknown planner '{name}' (choose from {', '.join(BASELINES)})")
    mod, cls = BASELINES[name].split(":")
    try:
        module = importlib.import_module(mod)
    except ModuleNotFoundError as exc:
        if exc.name == mod:
            raise PsprmError(f"planner '{name}' is not available in this build (module {mod} missing)") from None
        raise
    return getattr(module, cls)


def make_baseline(name: str, scene, targets: Sequence[str], robot=None, seed: int = 0, **kw):
    """A benchmark planner ``name`` for ``scene`` and ``targets`` (kept in view together; focus = their centroid).

    Extra keyword arguments go to the planner (e.g. ``timeout_s``, ``n_nodes``); each planner ignores the ones it
    does not know only if it says so, so pass only settings the planner documents.
    """
    cls = resolve(name)
    return cls(name=name, scene=scene, targets=list(targets), robot=robot, seed=seed, **kw)


__all__ = ["BASELINES", "planner_names", "make_baseline", "resolve"]
