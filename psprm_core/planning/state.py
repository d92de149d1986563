"""The state the planner's stages share, as explicit objects.

- :class:`PlannerContext`: what a planner plans with (robot, scene, scorer, settings, device and dtype, the motion
  model, the collision checker, the visibility constraint); the planner replaces its scene, settings or focus only
  through its own verbs (``set_scene``, ``reweight``, ``set_focus``).
- :class:`~.roadmap_state.RoadmapState`: the roadmap graph and everything kept with it (node scores, score scale,
  retired query nodes, blocked nodes and edges, the hop table, caches).
- :class:`~.knots.KnotStore`: the knots of the roadmap's edges.
- :class:`QueryContext`: what one query keeps while it runs (its connection edges' pending knots, the compiled
  scorer's arguments), cleared when it ends.

Each stage is given the state objects it reads, and the other stages it calls, in its constructor (the
:class:`~.pipeline.Pipeline` makes them); :class:`ReadsQuerySettings` gives a stage that holds ``ctx`` and ``qc``
the settings of the running query.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np
import torch

from ..kernels.compute import Compute, bulk
from ..kernels.edges import EdgeKit

if TYPE_CHECKING:  # the types of the context's fields (the modules import this one)
    from ..collision import CollisionChecker
    from ..motion import DiffDriveMotion
    from ..perception.scoring import Scorer
    from ..robot import RobotModel
    from ..scene import Scene
    from .backend import TorchBackend
    from .constraints import VisibilityConstraint
    from .settings import PSPRMSettings

NP_DTYPE = {torch.float32: np.float32, torch.float64: np.float64}  # the planner's dtype on the host


@dataclass
class PlannerContext:
    """Robot, scene, scorer and settings of a planner, with the device and dtype of its batched work.

    ``track_cols``: the non-base joints that re-aim the camera along an edge; ``lo``/``hi``: joint limits as tensors
    (the base's x, y within the scene's workspace); ``compute``: the planner's
    :class:`~psprm_core.kernels.compute.Compute`; ``backend``: the :mod:`.backend` it chooses."""

    robot: RobotModel
    scene: Scene
    scorer: Scorer
    settings: PSPRMSettings
    device: torch.device
    dtype: torch.dtype
    motion: DiffDriveMotion
    checker: CollisionChecker
    constraint: VisibilityConstraint
    track_cols: np.ndarray
    lo: Optional[torch.Tensor] = None
    hi: Optional[torch.Tensor] = None
    compute: Optional[Compute] = None  # device, kernels and batch policy of the planner's batches
    backend: Optional[TorchBackend] = None  # where the stages' batched operations run (:mod:`.backend`), set by the
    # pipeline

    def t(self, a) -> torch.Tensor:
        """``a`` as a tensor in the planner's dtype on its device."""
        return torch.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)

    def edge_kit(self) -> EdgeKit:
        """What the fused edge calls compute with (:class:`~psprm_core.kernels.edges.EdgeKit`), from the planner's
        objects and its current settings."""
        s = self.settings
        return EdgeKit(self.motion, self.robot, self.checker, self.constraint, s.projection, self.lo, self.hi,
                       self.track_cols, int(s.edges.track_iters), int(s.edges.n_interp), float(s.edges.edge_resolution))


@dataclass
class QueryContext:
    """Per-query state, reset by :meth:`clear` when a query ends.

    ``pending_knots``: (edge ids, start ends, qa, qb) of the query's connection edges whose knots are not computed
    yet (a lazy query computes them when the search first uses an edge); ``pending_rows``: their rows by edge id;
    ``pending_np``: ((qa, qb) in the planner's dtype, start ends, qa, qb float64) as numpy; ``scorer_args``: the
    compiled scorer's arguments by dtype; ``untracked``: connection edges may fall back to untracked knots;
    ``settings``: the planner's settings with the query's own options (kept over the whole query, recovery stages
    included; None outside a query)."""

    pending_knots: Optional[tuple] = None
    pending_rows: dict = field(default_factory=dict)
    pending_np: Optional[tuple] = None
    scorer_args: Optional[dict] = None
    untracked: bool = False
    settings: Optional[object] = None

    def clear(self) -> None:
        """End of one search attempt (:meth:`~.query.Query.plan_once`): everything but ``settings``, which
        :meth:`~.pipeline.Pipeline.plan` holds over the whole query and its recovery stages."""
        self.pending_knots, self.pending_rows, self.pending_np = None, {}, None
        self.scorer_args, self.untracked = None, False


class ReadsQuerySettings:
    """For a stage that holds ``ctx`` (:class:`PlannerContext`) and ``qc`` (:class:`QueryContext`): :attr:`qs`, the
    settings the running query plans with."""

    ctx: PlannerContext
    qc: QueryContext

    @property
    def qs(self) -> PSPRMSettings:
        """The settings of the running query (the planner's, with the query's options), else the planner's."""
        return self.qc.settings if self.qc.settings is not None else self.ctx.settings


def one_thread(method: Callable) -> Callable:
    """Run a planner method (a query: small batches) with torch's intra-op parallelism off
    (:meth:`~psprm_core.kernels.compute.Compute.one_thread` of the planner's Compute)."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self.ctx.compute.one_thread():
            return method(self, *args, **kwargs)

    return run


def large_batches(method: Callable) -> Callable:
    """Run a planner method whose batches can be large (build, re-scoring, invalidation near moved obstacles, repair
    growth) with the compiled kernels for any batch size, rows split over torch's thread count
    (:func:`~psprm_core.kernels.compute.bulk`; inside a query that is one thread)."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with bulk():
            return method(self, *args, **kwargs)

    return run
