"""PS-PRM: perception-score-guided probabilistic roadmap (paper Alg. 1, Eqs. 1-6), the planner's facade.

Build (:mod:`.builder`):
  1. sample configurations (base uniform over the scene's workspace, joints uniform within limits), project them onto
     the visibility manifold h_M(q) = 0 (batched Gauss-Newton, :mod:`.constraints`), keep the converged,
     collision-free ones until ``n_nodes`` or the timeout (:mod:`.sampling`, with perception-biased nodes);
  2. connect each node to its k nearest neighbours under the differential-drive metric (:mod:`psprm_core.motion`)
     within ``max_edge_length`` (:mod:`.neighbours`); keep an edge when its local motion is collision-free and its
     interior keeps the target in the camera frustum (:mod:`.edges`);
  3. score every node and the N interpolated configurations of every edge (batched FK -> scorer), and weight each edge
     c = 1 - alpha * c_p + (1 - alpha) * c_m  (Eq. 2) with c_p the Eq. 1 mean and c_m the motion cost normalised by the
     roadmap's longest edge (:mod:`.scoring`).

Query (:mod:`.query`): connect start and goal(s) to the roadmap, A* with the hop heuristic h = H_min * c_min
(Eqs. 3-6, :mod:`.heuristics`), edges verified lazily (:mod:`.verification`), the escape search and a local repair
when no goal is reachable (:mod:`.recovery`), perception-preserving shortcuts (:mod:`.shortcut`); the node path is
expanded into its checked knots and time-parameterised within the joint limits (:mod:`.trajectory`). Moved targets
and obstacles: :mod:`.dynamics`; roadmap files: :mod:`.persistence`. The stages share the explicit state objects
of :mod:`.state`, composed by :class:`~.pipeline.Pipeline`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..collision import CollisionChecker
from ..errors import ConfigError
from ..kernels.compute import Compute, compute_for
from ..motion import DiffDriveMotion
from ..robot import RobotModel
from ..robot.kinematics_pk import PKBodyKinematics, PKCameraKinematics
from ..scene import Scene
from .constraints import VisibilityConstraint, camera_joint_mask
from .pipeline import Pipeline
from .results import EscapeResult, PlanResult
from .settings import VARIANTS, PSPRMSettings
from .state import PlannerContext

__all__ = ["PSPRM", "PSPRMSettings", "PlanResult", "EscapeResult", "VARIANTS"]


class PSPRM:
    """A PS-PRM planner for one robot, scene and target (or target set).

    Parameters
    ----------
    robot : RobotModel
    scene : Scene
    scorer : psprm_core.perception.scoring.Scorer
        Perception score of camera poses (neural, oracle, or any other).
    focus : (3,) array
        Point the visibility constraint keeps in view (the target's centroid, or the midpoint of several targets).
    settings : PSPRMSettings
        ``scoring.alpha`` left unset is :func:`~.settings.default_alpha` of the objective (no scorer kind).
    device, dtype : torch device and dtype of all batched work.
    checker : the collision checker to use (default: one for ``robot`` and the scene's boxes, whose torch path runs
        the body FK of :class:`~psprm_core.robot.kinematics_pk.PKBodyKinematics` under ``kinematics:
        pytorch_kinematics``).
    compute : :class:`~psprm_core.kernels.compute.Compute`, optional
        Which kernels serve the planner's batches (default: ``Compute.make(device, dtype)``, compiled on a CPU with
        numba). Given, the robot model and the scorer are used through copies that follow it
        (:meth:`~psprm_core.kernels.compute.Computing.using`); a checker given keeps its own.
    """

    def __init__(self, robot: RobotModel, scene: Scene, scorer, focus, settings: PSPRMSettings = PSPRMSettings(),
                 device="cpu", checker: Optional[CollisionChecker] = None, dtype: torch.dtype = torch.float32,
                 compute: Optional[Compute] = None):
        settings = settings.resolved()
        settings.validate()
        device = torch.device(device)
        if compute is None:
            compute = compute_for(device, dtype)
        else:
            if compute.device != device:
                raise ConfigError("compute", "device", f"{compute.device}, but the planner's device is {device}")
            robot = robot.using(compute)
            scorer = scorer.using(compute) if hasattr(scorer, "using") else scorer
        kin = body_kin = None
        if settings.visibility.kinematics == "pytorch_kinematics":
            kin = PKCameraKinematics(robot, device=device)
            body_kin = None if checker is not None else PKBodyKinematics(robot, device=device, dtype=dtype)
        pad = settings.edges.collision_padding
        checker = checker or CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace, device=device,
                                              dtype=dtype, kinematics=body_kin, padding=pad, compute=compute)
        if checker.padding != pad:
            raise ConfigError("settings", "edges.collision_padding",
                              f"{pad} m, but the collision checker given keeps {checker.padding} m")
        constraint = VisibilityConstraint(robot, settings.visibility.constraint, focus, margin=settings.visibility.frustum_margin,
                                          min_distance=settings.visibility.min_view_distance, kinematics=kin,
                                          compute=compute)
        mask = camera_joint_mask(robot)
        mask[: robot.base_dof] = False
        ctx = PlannerContext(robot=robot, scene=scene, scorer=scorer, settings=settings, device=device, dtype=dtype,
                             motion=DiffDriveMotion(robot, compute), checker=checker, constraint=constraint,
                             compute=compute,
                             track_cols=np.nonzero(mask)[0])  # joints that re-aim the camera along an edge
        lo = ctx.t(np.where(np.isfinite(robot.lower), robot.lower, -1e9))
        hi = ctx.t(np.where(np.isfinite(robot.upper), robot.upper, 1e9))
        if robot.mobile:
            lo[:2], hi[:2] = ctx.t(scene.workspace[:, 0]), ctx.t(scene.workspace[:, 1])
        ctx.lo, ctx.hi = lo, hi
        self.ctx = ctx
        self.pipeline = Pipeline(ctx)

    # ---- what the planner plans with ---------------------------------------------------------------------------------
    robot = property(lambda self: self.ctx.robot)
    scene = property(lambda self: self.ctx.scene)
    scorer = property(lambda self: self.ctx.scorer)
    settings = property(lambda self: self.ctx.settings, doc="The planner's settings (change them with reweight).")
    device = property(lambda self: self.ctx.device)
    compute = property(lambda self: self.ctx.compute, doc="Where and how the planner's batches run.")
    dtype = property(lambda self: self.ctx.dtype)
    motion = property(lambda self: self.ctx.motion)
    checker = property(lambda self: self.ctx.checker)
    constraint = property(lambda self: self.ctx.constraint)
    track_cols = property(lambda self: self.ctx.track_cols)

    # ---- the roadmap -------------------------------------------------------------------------------------------------
    graph = property(lambda self: self.pipeline.rm.graph, doc="The roadmap (:class:`~.graph.Roadmap`), None before a "
                     "build or load.")
    node_scores = property(lambda self: self.pipeline.rm.node_scores, doc="Raw perception score per node slot.")
    stats = property(lambda self: self.pipeline.rm.stats, doc="Statistics of the last build (or the loaded one's).")
    knots = property(lambda self: self.pipeline.knots, doc="The knot store of the roadmap's edges.")
    template = property(lambda self: self.pipeline.rm.template, doc="Values of the joints that are not sampled.")
    max_motion = property(lambda self: self.pipeline.rm.max_motion)
    score_scale = property(lambda self: self.pipeline.rm.score_scale)
    n_roadmap_nodes = property(lambda self: self.pipeline.rm.n_roadmap_nodes)

    @property
    def heuristic_name(self) -> str:
        return self.pipeline.heuristics.name

    @property
    def joint_bounds(self) -> tuple:
        """(lower, upper) joint limits as tensors in the planner's dtype (the base's x, y within the workspace)."""
        return self.ctx.lo, self.ctx.hi

    def normalized_scores(self, scores: torch.Tensor) -> torch.Tensor:
        """Raw perception scores as Eq. 1's normalised c_p in [0, 1] (over this roadmap's 99th-percentile score)."""
        return self.pipeline.scoring.normalized(scores)

    def roadmap_mask(self) -> np.ndarray:
        return self.pipeline.rm.roadmap_mask()

    def roadmap_node_ids(self) -> np.ndarray:
        return self.pipeline.rm.roadmap_node_ids()

    def roadmap_edge_ids(self) -> np.ndarray:
        return self.pipeline.rm.roadmap_edge_ids()

    def path_roadmap_edges(self, path_nodes: Sequence[int]) -> np.ndarray:
        return self.pipeline.rm.path_roadmap_edges(path_nodes)

    def components(self) -> tuple:
        return self.pipeline.rm.components()

    # ---- verbs -------------------------------------------------------------------------------------------------------
    def build(self, template: Optional[np.ndarray] = None) -> dict:
        """Sample, project, connect and score the roadmap (:meth:`.builder.Builder.build`); returns build
        statistics."""
        return self.pipeline.builder.build(template)

    def warm_up(self, score: bool = True) -> float:
        """Load or compile every kernel a query uses (:meth:`.builder.Builder.warm_up`); returns the seconds."""
        return self.pipeline.builder.warm_up(score)

    def plan(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
             goal_costs: Optional[np.ndarray] = None, options: Optional[dict] = None) -> PlanResult:
        """Plan from ``start`` to the cheapest of ``goals`` (one configuration (dof,) or several (G, dof)), with the
        recovery stages when no goal is reachable (:meth:`.pipeline.Pipeline.plan`). ``goal_costs`` (G,): terminal costs
        added per goal; ``options``: settings of :func:`~.settings.query_options` for this query only (e.g.
        ``{"query.heuristic": "exact", "query.shortcut": False}``). Never raises for a bad problem: the result's ``reason`` says
        what failed."""
        return self.pipeline.plan(start, goals, timing, goal_costs, options)

    def fastest(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray,
                options: Optional[dict] = None) -> PlanResult:
        """The shortest route by motion cost from ``start`` to the nearest of ``goals``, timed
        (:meth:`.pipeline.Pipeline.fastest`; ``options`` as in :meth:`plan`); the planner's weights are unchanged."""
        return self.pipeline.fastest(start, goals, options)

    def reweight(self, alpha: Optional[float] = None, objective: Optional[str] = None) -> None:
        """Re-weight every edge with a new ``alpha`` and/or objective without rebuilding
        (:meth:`.scoring.Scoring.reweight`)."""
        self.pipeline.scoring.reweight(alpha, objective)

    def update_settings(self, settings: Optional[PSPRMSettings] = None, **changes) -> PSPRMSettings:
        """Adopt new settings (``settings``, else the current ones with ``changes``), validated. Queries use them at
        once; edges are re-weighted when the ``scoring`` group changes; when the ``edges`` or ``projection`` group
        changes (the edges' knots, their checks, their Eq. 1 samples), every stored knot is dropped and every edge
        re-checked and re-scored when a search next uses it (as after :meth:`set_focus`). The ``roadmap`` group and
        the seed take effect at the next :meth:`build` and change :meth:`fingerprint`. The ``visibility`` group is
        fixed when the planner is made: changing it raises :class:`~psprm_core.errors.ConfigError`. ``changes``:
        dotted paths (:meth:`~.settings.PSPRMSettings.changed`), given as ``**{"query.shortcut": True}``. Returns
        the settings now in use."""
        old = self.settings
        new = (settings or old).changed(changes)
        if new.scoring.alpha is None:  # unset: the planner keeps its alpha
            new = dataclasses.replace(new, scoring=dataclasses.replace(new.scoring, alpha=old.scoring.alpha))
        new.validate()
        if new.visibility != old.visibility:
            fixed = [f"visibility.{k}" for k, v in dataclasses.asdict(new.visibility).items()
                     if v != getattr(old.visibility, k)]
            raise ConfigError("settings", ", ".join(fixed), "fixed when the planner is made: make a new planner")
        if new.edges.collision_padding != old.edges.collision_padding:
            raise ConfigError("settings", "edges.collision_padding",
                              "fixed when the planner is made (its checker and every node depend on it): make a new "
                              "planner")
        reweigh = self.graph is not None and new.scoring != old.scoring
        # with new weights to make, reweight publishes the scoring settings once the weights are written
        self.ctx.settings = dataclasses.replace(new, scoring=old.scoring) if reweigh else new
        if self.graph is not None and (new.edges, new.projection) != (old.edges, old.projection):
            self.pipeline.dynamics.forget_knots()
        if reweigh:
            self.pipeline.scoring.reweight(scoring=new.scoring)
        return self.ctx.settings

    def set_alpha(self, alpha: float) -> None:
        """Re-weight every edge with a new alpha (Eq. 2) without rebuilding (alpha = 0: shortest-path PRM)."""
        self.reweight(alpha=alpha)

    def set_scene(self, scene: Scene) -> None:
        """Adopt moved targets/obstacles (:meth:`.dynamics.Dynamics.set_scene`)."""
        self.pipeline.dynamics.set_scene(scene)

    def set_scorer_scene(self, scene: Scene) -> None:
        """Score against ``scene`` from now on, the collision checker left as it is: what-if scoring (a target's
        predicted poses); :meth:`set_scene` puts both back in step."""
        self.pipeline.ctx.scorer.set_scene(scene)

    def set_focus(self, focus) -> None:
        """Move the point the visibility constraint aims at (:meth:`.dynamics.Dynamics.set_focus`)."""
        self.pipeline.dynamics.set_focus(focus)

    def rescore(self, full: bool = False, tol: float = 1e-4) -> dict:
        """Re-score the roadmap after the target or an occluder moved (:meth:`.dynamics.Dynamics.rescore`)."""
        return self.pipeline.dynamics.rescore(full, tol)

    def invalidate_near(self, boxes: Sequence, old_boxes: Sequence = (), margin: float = 0.05) -> dict:
        """Re-check what moved obstacles can touch (:meth:`.dynamics.Dynamics.invalidate_near`)."""
        return self.pipeline.dynamics.invalidate_near(boxes, old_boxes, margin)

    def grow(self, n: int, center: Optional[np.ndarray] = None, radius: float = 1.5,
             rng: Optional[np.random.Generator] = None, timeout_s: float = 2.0,
             heading: Optional[float] = None) -> dict:
        """Add up to ``n`` manifold nodes near ``center`` (:meth:`.builder.Builder.grow`)."""
        return self.pipeline.builder.grow(n, center, radius, rng, timeout_s, heading)

    def fingerprint(self) -> str:
        return self.pipeline.persistence.fingerprint()

    def save(self, path: str | Path) -> Path:
        return self.pipeline.persistence.save(path)

    def load(self, path: str | Path, check: bool = True) -> None:
        """Load a saved roadmap; with ``check``, a :class:`~psprm_core.errors.ConfigError` when it was built for
        another robot, scene, focus or settings."""
        self.pipeline.persistence.load(path, check)

    # ---- scores and knots of configurations and edges ----------------------------------------------------------------
    def score_configs(self, q: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """Perception scores (B,) of configurations (:meth:`.scoring.Scoring.score_configs`)."""
        return self.pipeline.scoring.score_configs(q, chunk)

    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool = True) -> tuple:
        """Knots of the local motions qa -> qb (:meth:`.edges.Edges.edge_knots`)."""
        return self.pipeline.edges.edge_knots(qa, qb, track)

    def stored_knots(self, edge_ids: np.ndarray) -> tuple:
        """Knots of graph edges in their stored direction (:meth:`.edges.Edges.stored_knots`)."""
        return self.pipeline.edges.stored_knots(edge_ids)

    def densify(self, W: torch.Tensor) -> torch.Tensor:
        """Configurations every ``edge_resolution`` along a knot path (:meth:`.edges.Edges.densify`)."""
        return self.pipeline.edges.densify(W)
