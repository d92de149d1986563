"""PS-PRM: perception-score-guided probabilistic roadmap (paper Alg. 1, Eqs. 1-6).

Build:
  1. sample configurations (base uniform over the scene's workspace, joints uniform within limits), project them onto
     the visibility manifold h_M(q) = 0 (batched Gauss-Newton, :mod:`.constraints`), keep the converged,
     collision-free ones until ``n_nodes`` or the timeout;
  2. connect each node to its k nearest neighbours under the differential-drive metric (:mod:`psprm_core.motion`)
     within ``max_edge_length``; keep an edge when its local motion is collision-free and its interior keeps the
     target in the camera frustum (the edge stays near the manifold);
  3. score every node and the N interpolated configurations of every edge (batched FK -> scorer), and weight each edge
     c = 1 - alpha * c_p + (1 - alpha) * c_m  (Eq. 2) with c_p the Eq. 1 mean and c_m the motion cost normalised by the
     roadmap's longest edge.
Query: connect start and goal(s) to the roadmap, A* with the hop heuristic h = H_min * c_min (Eqs. 3-6), expand
the node path into differential-drive corners and time-parameterise it within the joint limits.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from .. import fastpath
from ..collision import BoxTensors, CollisionChecker
from ..errors import ConfigError
from ..motion import DiffDriveMotion
from ..robot import RobotModel
from ..scene import Scene
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .constraints import ProjectionSettings, VisibilityConstraint, camera_joint_mask
from . import search_kernels
from .graph import Roadmap
from .graph_search import (OBJECTIVES, EdgeCheck, astar, edge_perception, edge_weight, lazy_astar, min_edge_cost,
                           motion_heuristic)
from ..errors import InputError

log = logging.getLogger(__name__)

COMPACT_EVERY = 64  # queries between removals of retired query nodes/edges (each removal rebuilds the adjacency)
QUERY_KNOT_CACHE = 512  # start/goal query edges whose knots are kept (by end configurations)
QUERY_FALLBACK_K = 3  # nearest roadmap nodes a start/goal with none within 2 max_edge_length is still tried with
HOP_TABLE_MAX_NODES = 5000  # roadmaps up to this many nodes keep all their hop distances (uint8, 25 MB at most)
SMALL_BATCH = 64  # edges checked in one collision call (knots + dense pieces together) when verifying few edges
ESCAPE_BATCH = 32  # random extensions per round of the escape search (PSPRM._escape)
ESCAPE_CONNECT = 32  # connections to the roadmap an escape round checks at most (the shortest)
ESCAPE_LONG = 4  # the escape search's long extensions, in steps
ESCAPE_STUCK_ROUNDS = 16  # escape rounds after which an end with no free motion out of it is given up
ESCAPE_MANOEUVRES = 8  # of the ESCAPE_BATCH extensions per round: drive/back-up/turn manoeuvres from tree nodes
ESCAPE_KEEP = 4  # connections to the roadmap (and their tree branches) an escape search keeps
SHORTCUT_CANDIDATES = 8  # later path nodes a shortcut from one node tries at most (the farthest ones)

_NP_DTYPE = {torch.float32: np.float32, torch.float64: np.float64}  # the planner's dtype on the host

# settings that only affect queries (weights are recomputed from c_p and c_m on load): not part of the fingerprint
QUERY_SETTINGS = ("alpha", "objective", "heuristic", "shortcut", "shortcut_rounds", "connect_k", "build_timeout_s", "query_repair_nodes", "query_repair_radius",
                  "query_repair_budget", "query_repair_connect_k", "query_repair_rounds", "query_repair_failures",
                  "query_wide_k", "query_untracked_fallback", "query_escape_s", "query_escape_nodes",
                  "query_escape_radius", "query_escape_step", "query_escape_connect_k",
                  "smooth_timing")

VARIANTS = {
    "psprm-line": ("line", "oracle"),
    "psprm-frustum": ("frustum", "oracle"),
    "neural-psprm-line": ("line", "neural"),
    "neural-psprm-frustum": ("frustum", "neural"),
}


@dataclass(frozen=True)
class PSPRMSettings:
    """Settings of PS-PRM. The field defaults are the paper's configuration (Eq. 2, uniform nodes, no shortcuts);
    ``config/planners/psprm.yaml``, which :func:`~.factory.make_planner` and everything built on it (CLI, bench, ROS
    nodes) load, ships the configuration that saw most in the benchmarks (motion objective, biased nodes,
    shortcuts)."""

    n_nodes: int = 3000
    k_neighbors: int = 15
    k_long: int = 10  # extra random neighbours within max_edge_length (long edges: fewer hops per path, Eq. 2)
    max_edge_length: float = 2.0  # motion-cost units (m + weighted rad), the geodesic radius delta of Alg. 1
    alpha: float = 0.8  # Eq. 2 (paper: 0.75 with the oracle, 0.8 with the surrogate)
    objective: str = "eq2"  # edge weight: eq2 (the paper's 1 - alpha c_p + (1 - alpha) c_m) | motion (c_m times
    # ((1 - alpha) + alpha (1 - c_p)): perception loss per unit of motion; graph_search.motion_weighted)
    lazy_edges: bool = False  # score edge interiors (Eq. 1) only for edges on candidate paths (slow scorers)
    lazy_collision: bool = True  # Lazy PRM: check an edge's dense interior when a search first uses it
    normalize_scores: bool = True  # c_p = min(1, score / q99(node scores)): the paper's normalised score in [0, 1]
    n_interp: int = 5  # N of Eq. 1
    constraint: str = "line"  # visibility model: line | frustum
    sample_joints: str = "camera"  # camera: sample only joints that move the camera (others at default) | all
    sample_spread: float = -1.0  # >= 0: non-base joints sampled within +-spread (rad/m) of the template, else uniform
    biased_share: float = 0.0  # share of the nodes drawn where the scorer predicts good views (accepted with
    # probability c_p, the normalised score); the others uniform on the manifold
    biased_tries: float = 6.0  # at most this many manifold samples scored per biased node wanted
    expand_rounds: int = 0  # > 0: after the build, rounds of sampling between the largest component and the others
    expand_nodes: int = 30  # nodes sampled per disconnected component and round
    expand_components: int = 12  # components (of >= 3 nodes, largest first) bridged per round
    query_repair_nodes: int = 120  # a query that finds no path grows this many nodes around its start and goals
    query_repair_radius: float = 0.8  # m around the start/goal base (half of them along its heading)
    query_repair_budget: int = 1500  # at most this many nodes grown by query repairs per built/loaded roadmap
    query_repair_connect_k: int = 48  # neighbours tried per start / goal in the repaired query (>= connect_k)
    query_repair_rounds: int = 3  # repair rounds of a failing query (radius x 1.5 each round), within the budget
    query_repair_failures: int = 25  # failed (rolled back) repairs per built/loaded roadmap; then no more repairs
    query_wide_k: int = 0  # last resort (after the escape): each end tries its k nearest nodes, however far (0: off)
    query_untracked_fallback: bool = True  # escape/wide queries keep a connection with untracked camera joints
    # when its re-aimed version collides
    query_escape_s: float = 0.0  # > 0: time (s) of the escape search of a failed query, before the repair (0: off)
    query_escape_nodes: int = 1500  # at most this many configurations in an end's escape tree
    query_escape_radius: float = 2.5  # m: half the escape samples put the base within this distance of the end,
    # the others within twice that
    query_escape_step: float = 0.4  # motion-cost units: the escape tree's short extensions (long ones: ESCAPE_LONG x)
    query_escape_connect_k: int = 6  # nearest roadmap nodes each new escape configuration tries to connect to
    edge_resolution: float = 0.05  # collision-check spacing along edges (motion-cost units)
    edge_view_slack: float = -1.0  # >= 0: interior configurations must keep the target within the frustum (+slack m);
    # < 0: no such filter (Eq. 1 already scores interiors that lose the target)
    connect_k: int = 12  # neighbours tried when connecting a start or goal
    heuristic: str = "auto"  # A* heuristic: hop (Eq. 3, the paper's) | distance (motion lower bound, for the motion
    # objective) | exact (cost-to-go from a compiled Dijkstra) | auto (hop for eq2, distance for motion)
    shortcut: bool = False  # shorten the found path where a direct motion is free, on the manifold and sees as well
    kinematics: str = "native"  # camera FK + Jacobian of the Newton projection: native (the robot model; compiled
    # kernels for small CPU batches) | pytorch_kinematics (psprm_core.kinematics_pk, always the torch path)
    shortcut_rounds: int = 2  # greedy shortcut passes over the path
    track_iters: int = 6  # Newton steps that re-aim the non-base camera joints at the knots of an edge
    smooth_timing: bool = True  # trajectories pass the knots of a base phase without stopping (timing.smooth)
    sample_batch: int = 2048
    build_timeout_s: float = 120.0
    min_view_distance: float = 0.5
    frustum_margin: float = 0.05
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    seed: int = 0

    @classmethod
    def from_yaml(cls, path: str | Path, robot: str | None = None, **overrides) -> "PSPRMSettings":
        """Settings from YAML; a ``robots: {name: {field: value}}`` section overrides fields for one robot."""
        data = load_yaml(path)
        per_robot = data.pop("robots", None) or {}
        if not isinstance(per_robot, dict):
            raise ConfigError(str(path), "robots", "expected a mapping robot name -> settings")
        if robot is not None and robot in per_robot:
            extra = per_robot[robot]
            if not isinstance(extra, dict):
                raise ConfigError(str(path), f"robots.{robot}", "expected a mapping of settings")
            data = {**data, **extra}
        f = Fields(data, str(path))
        kw = dataclass_kwargs(cls, f, skip=("projection",), signed=("edge_view_slack", "sample_spread"))
        if f.has("projection"):
            p = f.sub("projection")
            kw["projection"] = ProjectionSettings(**dataclass_kwargs(ProjectionSettings, p, float_lo=None, int_lo=1))
        kw.update({k: v for k, v in overrides.items() if v is not None})
        s = cls(**kw)
        s.validate(str(path))
        return s

    def validate(self, source: str = "settings") -> None:
        if self.constraint not in ("line", "frustum"):
            raise ConfigError(source, "constraint", f"unknown visibility model '{self.constraint}' (line, frustum)")
        if self.heuristic not in ("hop", "exact", "distance", "auto"):
            raise ConfigError(source, "heuristic", f"unknown A* heuristic '{self.heuristic}' (hop, distance, exact, "
                                                   "auto)")
        if self.objective not in OBJECTIVES:
            raise ConfigError(source, "objective", f"unknown objective '{self.objective}' ({', '.join(OBJECTIVES)})")
        if self.kinematics not in ("native", "pytorch_kinematics"):
            raise ConfigError(source, "kinematics", f"unknown kinematics '{self.kinematics}' (native, "
                                                    "pytorch_kinematics)")
        if self.sample_joints not in ("camera", "all"):
            raise ConfigError(source, "sample_joints", "must be 'camera' or 'all'")
        if not 0.0 <= self.alpha <= 1.0:
            raise ConfigError(source, "alpha", f"must lie in [0, 1], got {self.alpha}")
        if not 0.0 <= self.biased_share <= 1.0:
            raise ConfigError(source, "biased_share", f"must lie in [0, 1], got {self.biased_share}")
        if self.n_nodes < 2 or self.k_neighbors < 1:
            raise ConfigError(source, "n_nodes", "need at least 2 nodes and 1 neighbour")
        if not (self.query_escape_s >= 0 and np.isfinite(self.query_escape_s)):
            raise ConfigError(source, "query_escape_s", f"must be a finite time >= 0, got {self.query_escape_s}")
        if self.query_escape_s > 0:
            for name in ("query_escape_radius", "query_escape_step"):
                v = getattr(self, name)
                if not (v > 0 and np.isfinite(v)):
                    raise ConfigError(source, name, f"must be > 0 when query_escape_s > 0, got {v}")
            for name in ("query_escape_nodes", "query_escape_connect_k"):
                if getattr(self, name) < 1:
                    raise ConfigError(source, name, f"must be >= 1 when query_escape_s > 0, got {getattr(self, name)}")


@dataclass
class PlanResult:
    """Outcome of a query (``success`` False comes with a ``reason``; never an exception for bad problems).

    ``dense_scores`` (the planner's perception score along ``dense``) and their mean ``mean_score`` are a report, not
    part of the search: they are computed on first access with ``score_fn`` (the planner's scorer, i.e. the scene at
    that moment: read them before moving targets or obstacles) and are not included in ``query_ms``.
    """

    success: bool
    reason: str = "ok"
    path_nodes: list = field(default_factory=list)
    waypoints: Optional[np.ndarray] = None  # (M, dof) roadmap path incl. diff-drive corners
    dense: Optional[np.ndarray] = None  # (K, dof) configurations every ``edge_resolution`` along the path
    trajectory: object = None  # timing.Trajectory
    cost: float = float("inf")
    path_length: float = float("nan")
    query_ms: float = float("nan")
    goal_index: int = -1
    score_fn: Optional[Callable[[np.ndarray], np.ndarray]] = field(default=None, repr=False, compare=False)
    _dense_scores: Optional[np.ndarray] = field(default=None, init=False, repr=False, compare=False)

    @property
    def dense_scores(self) -> Optional[np.ndarray]:
        """(K,) planner's perception score along ``dense`` (scored on first access)."""
        if self._dense_scores is None and self.dense is not None and self.score_fn is not None:
            self._dense_scores = np.asarray(self.score_fn(self.dense), dtype=float)
            self.score_fn = None
        return self._dense_scores

    @property
    def mean_score(self) -> float:
        """Mean of :attr:`dense_scores` (NaN without a path)."""
        ds = self.dense_scores
        return float(ds.mean()) if ds is not None and len(ds) else float("nan")

    def to_dict(self, joint_names: Sequence[str] | None = None) -> dict:
        d = {"success": self.success, "reason": self.reason, "cost": self.cost,
             "path_length_rad": self.path_length, "mean_perception_score": self.mean_score,
             "query_ms": self.query_ms, "goal_index": self.goal_index, "n_waypoints": 0}
        if self.waypoints is not None:
            d["n_waypoints"] = int(len(self.waypoints))
            d["waypoints"] = np.round(self.waypoints, 5).tolist()
            if joint_names is not None:
                d["joint_names"] = list(joint_names)
        if self.trajectory is not None:
            d["duration_s"] = float(self.trajectory.times[-1])
        return d


def _one_thread(method: Callable) -> Callable:
    """Run a planner method (a query: small batches) with torch's intra-op parallelism off
    (:func:`fastpath.one_thread`)."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with fastpath.one_thread(self.device):
            return method(self, *args, **kwargs)

    return run


def _large_batches(method: Callable) -> Callable:
    """Run a planner method whose batches can be large (build, re-scoring, invalidation near moved obstacles, repair
    growth) with the compiled kernels for any batch size, rows split over torch's thread count
    (:func:`fastpath.bulk`; inside a query that is one thread)."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with fastpath.bulk():
            return method(self, *args, **kwargs)

    return run


@dataclass
class EscapeResult:
    """Outcome of the escape search from one query end (:meth:`PSPRM._escape`).

    ``configs`` (n, dof) are the configurations of the kept tree branches (the end itself excluded). ``tree`` lists
    their edges as (a, b) indices into ``configs`` (-1: the end), ``conn`` the connections (a, roadmap node id); the
    untracked knots (E, M, dof) and Eq. 1 sample positions (E, N) of both, in the a -> b direction, are the ones
    that were collision-checked (densely) and are the ones executed.
    """

    configs: torch.Tensor
    tree: list
    tree_knots: tuple
    conn: list
    conn_knots: tuple
    explored: int = 1  # configurations in the tree (the end included)
    tried: int = 0  # motions tried from the tree (extensions)
    seconds: float = 0.0
    base_reach: float = 0.0  # m: farthest base position of the tree from the end's

    @property
    def success(self) -> bool:
        return len(self.conn) > 0


def _no_knots(planner) -> tuple:
    """Empty (knots (0, M, dof), Eq. 1 positions (0, N)) of a planner's edges."""
    n = planner.settings.n_interp
    return (torch.zeros(0, n + 4, planner.robot.dof, dtype=planner.dtype, device=planner.device),
            torch.zeros(0, n, dtype=torch.long, device=planner.device))


def _flags(have: np.ndarray, ids) -> np.ndarray:
    """``have[ids]`` with False for ids beyond the array."""
    ids = np.asarray(ids, dtype=np.int64)
    out = np.zeros(len(ids), dtype=bool)
    inside = ids < len(have)
    out[inside] = have[ids[inside]]
    return out


class KnotStore:
    """Knots of the roadmap's edges (:meth:`PSPRM.edge_knots`, in the stored u -> v direction), by edge id.

    The same knots serve the collision check, the Eq. 1 interior scores and the executed path, so what is checked
    is exactly what runs (a path traversing an edge v -> u uses the flipped knots)."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        self.data: Optional[torch.Tensor] = None  # (capacity, M, dof)
        self.interior: Optional[torch.Tensor] = None  # (capacity, N) positions of the Eq. 1 samples among the knots
        self.have = np.zeros(0, dtype=bool)
        self.cams: Optional[torch.Tensor] = None  # (capacity, N + 2, 4, 4) camera poses of the Eq. 1 points
        self.cams_have = np.zeros(0, dtype=bool)
        # (capacity, M, 6) world bounds of the robot at each knot (NaN = not computed yet): once a knot has been
        # checked, an obstacle move is tested against its bounds first and needs no kinematics when they miss
        self.aabb: Optional[torch.Tensor] = None
        # start/goal query edges' knots by their end configurations: a goal's (and a still robot's) edges recur on
        # every replan, and re-projecting the knots onto the manifold is a query's largest fixed cost
        self.query: dict = {}

    def put(self, ids: np.ndarray, knots: torch.Tensor, interior: torch.Tensor) -> None:
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        need = int(ids.max()) + 1
        if self.data is None or self.data.shape[1:] != knots.shape[1:]:
            self.data = knots.new_zeros((0,) + tuple(knots.shape[1:]))
            self.interior = interior.new_zeros((0,) + tuple(interior.shape[1:]))
            self.have = np.zeros(0, dtype=bool)
        if need > self.data.shape[0]:
            cap = max(need, int(self.data.shape[0] * 1.5) + 1024)
            grown = knots.new_zeros((cap,) + tuple(knots.shape[1:]))
            grown[: self.data.shape[0]] = self.data
            gi = interior.new_zeros((cap,) + tuple(interior.shape[1:]))
            gi[: self.interior.shape[0]] = self.interior
            self.data, self.interior = grown, gi
            self.have = np.concatenate([self.have, np.zeros(cap - len(self.have), dtype=bool)])
        idx = torch.as_tensor(ids, device=knots.device)
        self.data[idx] = knots
        self.interior[idx] = interior
        self.written(ids)

    def trim_query_cache(self) -> None:
        """Keep the :data:`QUERY_KNOT_CACHE` newest entries of :attr:`query` (dicts keep insertion order)."""
        while len(self.query) > QUERY_KNOT_CACHE:
            self.query.pop(next(iter(self.query)))

    def reserve(self, n: int) -> None:
        """Room for edge ids below ``n`` (the arrays must exist: after a first :meth:`put`)."""
        if n > self.data.shape[0]:
            self.put(np.asarray([n - 1]), self.data[:1].clone(), self.interior[:1].clone())
            self.have[n - 1] = False

    def written(self, ids: np.ndarray) -> None:
        """Mark the knots of edges ``ids`` as stored after they were written into :attr:`data` / :attr:`interior`
        directly (as :meth:`put` does: their camera poses and robot bounds are reset)."""
        self.have[ids] = True
        if len(self.cams_have):
            self.cams_have[ids[ids < len(self.cams_have)]] = False
        if self.aabb is not None:
            inside = ids[ids < self.aabb.shape[0]]
            if self.aabb.device.type == "cpu":
                self.aabb.numpy()[inside] = np.nan
            else:
                self.aabb[torch.as_tensor(inside, device=self.aabb.device)] = float("nan")

    def knot_aabb(self, ids: np.ndarray) -> torch.Tensor:
        """(E, M, 6) cached robot bounds at the knots of edges ``ids`` (NaN where not computed yet)."""
        ids = np.asarray(ids, dtype=np.int64)
        cap, M = self.data.shape[0], self.data.shape[1]
        if self.aabb is None or self.aabb.shape[0] < cap or self.aabb.shape[1] != M:
            grown = self.data.new_full((cap, M, 6), float("nan"))
            if self.aabb is not None and self.aabb.shape[1] == M:
                grown[: self.aabb.shape[0]] = self.aabb
            self.aabb = grown
        return self.aabb[torch.as_tensor(ids, device=self.data.device)]

    def put_aabb(self, ids: np.ndarray, knot: np.ndarray, bounds: torch.Tensor) -> None:
        """Store robot bounds (K, 6) at knot positions ``knot`` (K,) of edges ``ids`` (K,)."""
        self.knot_aabb(ids[:0])  # allocate
        dev = self.aabb.device
        self.aabb[torch.as_tensor(ids, device=dev), torch.as_tensor(knot, device=dev)] = bounds.to(self.aabb.dtype)

    def put_cams(self, ids: np.ndarray, cams: torch.Tensor | np.ndarray) -> None:
        """Camera poses (E, N + 2, 4, 4) of the Eq. 1 points of edges whose knots are stored (fixed while the
        roadmap's geometry is: a target move re-scores them without forward kinematics); a numpy array is written
        straight into a CPU store."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        cap = self.data.shape[0]
        if isinstance(cams, np.ndarray):
            c = self.cams
            if (c is not None and c.device.type == "cpu" and c.shape[0] >= cap and c.shape[1:] == cams.shape[1:]
                    and c.numpy().dtype == cams.dtype):
                c.numpy()[ids] = cams
                self.cams_have[ids] = True
                return
            cams = torch.from_numpy(cams).to(self.data.device)
        if self.cams is None or self.cams.shape[0] < cap or self.cams.shape[1:] != cams.shape[1:]:
            # uninitialised (rows are read only where cams_have says so): a roadmap's first query does not zero
            # tens of MB
            grown = cams.new_empty((cap,) + tuple(cams.shape[1:]))
            keep = np.zeros(cap, dtype=bool)
            if self.cams is not None and self.cams.shape[1:] == cams.shape[1:]:
                grown[: self.cams.shape[0]] = self.cams
                keep[: len(self.cams_have)] = self.cams_have
            self.cams, self.cams_have = grown, keep
        self.cams[torch.as_tensor(ids, device=cams.device)] = cams
        self.cams_have[ids] = True

    def known_cams(self, ids: np.ndarray) -> np.ndarray:
        """(E,) bool: the Eq. 1 camera poses of these edges are stored."""
        return _flags(self.cams_have, ids)

    def known(self, ids: np.ndarray) -> np.ndarray:
        """(E,) bool: the knots of these edges are stored."""
        return _flags(self.have, ids)

    def get(self, ids: np.ndarray) -> tuple:
        idx = torch.as_tensor(np.asarray(ids, dtype=np.int64), device=self.data.device)
        return self.data[idx], self.interior[idx]


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
    device : torch device for all batched work.
    """

    def __init__(self, robot: RobotModel, scene: Scene, scorer, focus, settings: PSPRMSettings = PSPRMSettings(),
                 device="cpu", checker: Optional[CollisionChecker] = None):
        settings.validate()
        self.robot, self.scene, self.scorer, self.settings = robot, scene, scorer, settings
        self.device = torch.device(device)
        self.dtype = torch.float32
        self.motion = DiffDriveMotion(robot)
        self.checker = checker or CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace,
                                                   device=self.device)
        kin = None
        if settings.kinematics == "pytorch_kinematics":
            from ..kinematics_pk import PKCameraKinematics

            kin = PKCameraKinematics(robot, device=self.device)
        self.constraint = VisibilityConstraint(robot, settings.constraint, focus, margin=settings.frustum_margin,
                                               min_distance=settings.min_view_distance, kinematics=kin)
        mask = camera_joint_mask(robot)
        mask[: robot.base_dof] = False
        self.track_cols = np.nonzero(mask)[0]  # joints that re-aim the camera along an edge
        lo = self._t(np.where(np.isfinite(robot.lower), robot.lower, -1e9))
        hi = self._t(np.where(np.isfinite(robot.upper), robot.upper, 1e9))
        if robot.mobile:
            lo[:2], hi[:2] = self._t(scene.workspace[:, 0]), self._t(scene.workspace[:, 1])
        self._lo, self._hi = lo, hi
        self.graph: Optional[Roadmap] = None
        self._dead_edges: list = []
        self._dead_nodes: list = []
        # query repairs, the nodes they grew and kept, the failed (rolled back) repairs; reset with the roadmap
        self._repairs, self._repair_added, self._repair_failed = 0, 0, 0
        self.node_scores: Optional[np.ndarray] = None  # per node slot (NaN for query nodes)
        self._roadmap_mask = np.zeros(0, dtype=bool)  # node slots that are roadmap nodes (not start/goal queries)
        self.stats: dict = {}
        self.max_motion = 1.0
        self._unverified = False  # some roadmap edges carry endpoint-only perception estimates (after rescore)
        self.knots = KnotStore()
        self._hop_table: Optional[tuple] = None  # (roadmap node slots, (R, R) uint8 hop distances), see _build_hop_table
        self._pending_query_knots = None  # (edge ids, start ends, qa, qb) of a query's not yet needed edge knots
        self._pending_rows: dict = {}  # their rows by edge id
        self._pending_np = None  # ((qa, qb) in the planner's dtype, start ends, qa, qb float64) as numpy
        self._query_args: Optional[dict] = None  # during a query: its compiled-scorer arguments by dtype
        self._untracked_fallback = False  # set during the escape and wide queries (query_untracked_fallback)
        self._escapes = 0  # escape searches run (their random streams)
        self.template = robot.default_configuration()  # joints that are not sampled (build() may override)
        self._index = None  # spatial index of roadmap nodes/edges (obstacle updates), built on first use
        self._blocked_nodes: set = set()  # roadmap nodes / edges removed because a moved obstacle blocked them
        self._blocked_edges: set = set()
        self._recheck = np.zeros(0, dtype=bool)  # edges unchecked because an obstacle moved near them

    # ---- helpers -----------------------------------------------------------------------------------------------------
    def _t(self, a) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)

    def _neural_args(self, dtype: torch.dtype) -> Optional[tuple]:
        """:func:`fastpath.neural_args` of the scorer, kept for the rest of a query (:meth:`_plan_once` clears them:
        the scorer does not change during a query, but may between queries)."""
        if self._query_args is None:
            return fastpath.neural_args(self.scorer, dtype)
        if dtype not in self._query_args:
            self._query_args[dtype] = fastpath.neural_args(self.scorer, dtype)
        return self._query_args[dtype]

    def _query_scores(self, Q: np.ndarray) -> np.ndarray:
        """:meth:`score_configs` (float64 out) of a query's few configurations ``Q`` (numpy, planner's dtype)."""
        if self.device.type == "cpu" and len(Q) <= fastpath.MLP_MAX_ROWS and fastpath.enabled():
            args = self._neural_args(self.dtype)
            if args is not None:
                return fastpath.neural_config_scores(self.robot, args, Q).astype(np.float64)
        return self.score_configs(torch.from_numpy(Q).to(self.device)).double().cpu().numpy()

    def score_configs(self, q: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """Perception scores (B,) of configurations: FK -> camera poses -> scorer (a query's few configurations with
        a neural scorer: one compiled call, the same values)."""
        if q.shape[0] <= fastpath.MLP_MAX_ROWS and fastpath.applies(q):
            args = self._neural_args(q.dtype)
            if args is not None:
                return fastpath.neural_config_scores(self.robot, args, q).to(self.dtype)
        out = []
        for s in range(0, q.shape[0], chunk):
            qc = q[s:s + chunk]
            out.append(self.scorer.score(self.robot.camera_poses(qc)).to(self.dtype))
        return torch.cat(out) if out else torch.zeros(0, dtype=self.dtype, device=self.device)

    def _sample(self, n: int, rng: np.random.Generator, template: np.ndarray) -> torch.Tensor:
        r = self.robot
        lo, hi = r.lower.copy(), r.upper.copy()
        if r.mobile:
            lo[:2], hi[:2] = self.scene.workspace[:, 0], self.scene.workspace[:, 1]
            lo[2], hi[2] = -np.pi, np.pi
        lo = np.where(np.isfinite(lo), lo, -np.pi)
        hi = np.where(np.isfinite(hi), hi, np.pi)
        if self.settings.sample_spread >= 0:  # keep an arm near its camera-ready template pose
            b = r.base_dof
            lo[b:] = np.maximum(lo[b:], template[b:] - self.settings.sample_spread)
            hi[b:] = np.minimum(hi[b:], template[b:] + self.settings.sample_spread)
        q = lo + rng.random((n, r.dof)) * (hi - lo)
        if self.settings.sample_joints == "camera":
            mask = camera_joint_mask(r)
            q[:, ~mask] = template[~mask]
        return self._t(q)

    # ---- build (Alg. 1) --------------------------------------------------------------------------------------------
    def build(self, template: Optional[np.ndarray] = None) -> dict:
        """Sample, project, connect and score the roadmap; returns build statistics.

        On the CPU the large batches of the build (projection, knot tracking, collision checks, FK and ray casting of
        Alg. 2) run the compiled kernels of :mod:`psprm_core.fastpath` in bulk, row chunks over
        ``torch.get_num_threads()`` threads; the surrogate's GEMMs stay in torch. The kernels are loaded (or, once
        per install, compiled) by :meth:`warm_up` first; that one-time start-up of the process is reported as
        ``warm_up_s`` and is not part of ``build_s``."""
        self.template = self.robot.default_configuration() if template is None else np.asarray(template, float)
        warm = self.warm_up(score=False)
        with fastpath.bulk():
            stats = self._build(self.template)
        stats["warm_up_s"] = warm
        return stats

    def _build(self, template: Optional[np.ndarray]) -> dict:
        s = self.settings
        rng = np.random.default_rng(s.seed)
        torch.manual_seed(s.seed)
        template = self.robot.default_configuration() if template is None else np.asarray(template, float)
        self.template = template
        t0 = time.perf_counter()
        nodes, tried = [], 0
        have = 0
        n_biased = int(round(s.biased_share * s.n_nodes))
        n_uniform = s.n_nodes - n_biased
        while have < n_uniform:
            if time.perf_counter() - t0 > s.build_timeout_s:
                log.warning("node sampling timed out with %d/%d nodes", have, s.n_nodes)
                break
            q = self._manifold_samples(rng, template)
            tried += s.sample_batch
            nodes.append(q)
            have += len(q)
        t_sample = time.perf_counter() - t0
        if have < 2:
            self.stats = {"success": False, "reason": "could not sample configurations on the visibility manifold"}
            return self.stats
        Q = torch.cat(nodes)[: n_uniform]
        t2 = time.perf_counter()
        node_scores = self.score_configs(Q)
        biased = {}
        if n_biased:
            t5 = time.perf_counter()
            Q, node_scores, biased = self._biased_nodes(Q, node_scores, n_biased, rng, template, t0)
            t_sample += time.perf_counter() - t5
        self.score_scale = 1.0
        if s.normalize_scores:  # the normalised score of Eq. 1 (c_p in [0, 1]) is relative to this roadmap
            self.score_scale = 1.0 / max(float(torch.quantile(node_scores.double(), 0.99)), 1e-3)
        t_score = time.perf_counter() - t2
        t1 = time.perf_counter()
        eu, ev, dist = self._neighbours(Q, Q, s.k_neighbors, exclude_self=True, k_long=s.k_long, rng=rng)
        valid, p_edge, knots = self._edges_valid(Q[eu], Q[ev], end_scores=(node_scores[eu], node_scores[ev]))
        eu, ev, dist, p_edge = eu[valid], ev[valid], dist[valid], p_edge[valid]
        if s.lazy_edges:  # endpoints only for now; interiors are scored when a search first uses the edge
            p_edge = edge_perception(self._normalized(node_scores[eu]), self._normalized(node_scores[ev]))
        t_edges = time.perf_counter() - t1
        self.max_motion = float(dist.max()) if len(dist) else 1.0
        c_m = (dist / self.max_motion).clamp(0, 1)
        g = Roadmap(dof=self.robot.dof, node_capacity=len(Q) + 64, edge_capacity=len(eu) + 1024)
        g.add_nodes(Q.double().cpu().numpy())
        self.knots.clear()
        edge_ids = g.add_edges(eu.cpu().numpy(), ev.cpu().numpy(),
                    self._weight(p_edge, c_m).double().cpu().numpy(),
                    c_m=c_m.double().cpu().numpy(), c_p=p_edge.double().cpu().numpy(),
                    verified=np.full(len(eu), 0.0 if s.lazy_edges else 1.0),
                    checked=np.full(len(eu), 0.0 if s.lazy_collision else 1.0))
        self.graph = g
        self._rm_cache_key = None  # a new roadmap: the same node ids may hold other configurations
        self._put_knots(edge_ids, eu.cpu().numpy(), *knots)
        self._dead_edges, self._dead_nodes = [], []
        self._repairs, self._repair_added, self._repair_failed = 0, 0, 0
        self._blocked_nodes, self._blocked_edges, self._recheck = set(), set(), np.zeros(0, dtype=bool)
        self._unverified, self._index = False, None
        self.node_scores = node_scores.double().cpu().numpy()
        self._roadmap_mask = np.ones(len(Q), dtype=bool)
        t3 = time.perf_counter()
        expand = self._expand(rng) if s.expand_rounds > 0 else {}
        t4 = time.perf_counter()
        self._build_hop_table()
        if self.knots.data is not None:  # room for the queries' edges now: the first query does not copy the store
            self.knots.reserve(self.graph.n_edges + 1)
        build_s = time.perf_counter() - t0
        self.stats = {
            "success": True, "n_nodes": int(self.n_roadmap_nodes), "n_edges": int(len(self.roadmap_edge_ids())),
            "samples_tried": int(tried), "sample_s": t_sample, "edges_s": t_edges, "score_s": t_score,
            "hop_table_s": time.perf_counter() - t4, "build_s": build_s, "mean_node_score": float(node_scores.mean()),
            **biased,
            **({"expand_s": time.perf_counter() - t3, **expand} if expand else {}),
        }
        log.info("PS-PRM built: %s", self.stats)
        return self.stats

    def _manifold_samples(self, rng: np.random.Generator, template: np.ndarray) -> torch.Tensor:
        """One batch of ``sample_batch`` samples projected onto the visibility manifold; the converged, valid ones."""
        s = self.settings
        q = self._sample(s.sample_batch, rng, template)
        q, ok = self.constraint.project(q, s.projection, self._lo, self._hi)
        q = q[ok]
        return q[self.checker.valid(q)]

    def _biased_nodes(self, Q: torch.Tensor, scores: torch.Tensor, n: int, rng: np.random.Generator,
                      template: np.ndarray, t0: float) -> tuple:
        """Perception-biased sampling: ``n`` more manifold nodes, each manifold sample kept with probability equal to
        its normalised score (its score over the 99th-percentile score of the uniform nodes, at most 1), so that
        regions with good predicted views (the surrogate with occlusion) are dense enough to route through; at most
        ``biased_tries * n`` samples are scored. Returns the nodes and scores with the new ones appended, and stats."""
        s = self.settings
        ref = max(float(torch.quantile(scores.double(), 0.99)), 1e-3) if len(scores) else 1.0
        keep_q, keep_s, tried = [Q], [scores], 0
        got = 0
        while got < n and tried < s.biased_tries * n:
            if time.perf_counter() - t0 > s.build_timeout_s:
                log.warning("biased sampling timed out with %d/%d nodes", got, n)
                break
            q = self._manifold_samples(rng, template)
            if not len(q):
                tried += s.sample_batch
                continue
            sc = self.score_configs(q)
            tried += len(q)
            accept = torch.as_tensor(rng.random(len(q)), dtype=sc.dtype, device=sc.device) < (sc / ref).clamp(0, 1)
            q, sc = q[accept][: n - got], sc[accept][: n - got]
            keep_q.append(q)
            keep_s.append(sc)
            got += len(q)
        if got < n:
            log.info("biased sampling kept %d of %d nodes within %d tries", got, n, tried)
        return torch.cat(keep_q), torch.cat(keep_s), {"biased_nodes": int(got), "biased_tried": int(tried)}

    def _build_hop_table(self) -> None:
        """Hop distances between all roadmap nodes (uint8, :data:`HOP_TABLE_MAX_NODES` nodes at most), one BFS per
        node on the bulk worker threads, so that a query gets the hop counts of Eq. 3 from the table rows of its
        goals' neighbours (:meth:`_query_hops`) instead of a BFS over the whole roadmap. Kept while the roadmap only
        loses edges (the table's counts are then lower bounds, and the heuristic stays consistent); roadmap nodes
        added later (:meth:`grow`) drop it, and queries go back to the BFS."""
        self._hop_table = None
        R = len(self._roadmap_mask)
        if (self.graph is None or not 2 <= R <= HOP_TABLE_MAX_NODES or self.heuristic_name != "hop"
                or not search_kernels.available()):
            return
        nbr, _, deg = self.graph.array_adjacency()
        T = np.empty((R, R), dtype=np.uint8)
        K = search_kernels.kernels()
        workers = max(1, min(torch.get_num_threads(), 8))
        step = 64 * max(1, -(-R // (64 * 2 * workers)))  # whole 64-source batches, two chunks per worker
        chunks = [(lo, min(lo + step, R)) for lo in range(0, R, step)]
        list(fastpath._pool(workers).map(lambda c: K.hop_columns(nbr, deg, R, c[0], c[1], T), chunks))
        self._hop_table = (R, T)

    def _query_hops(self, search_goals: Sequence[int], added_edges: Sequence[int]) -> Optional[np.ndarray]:
        """Hop counts (n_nodes,) to ``search_goals`` for Eq. 3 from the hop table: 0 at the goals, for a roadmap node
        1 + its table distance to the nearest roadmap neighbour of a goal-side query node (plus that node's own count),
        then lowered along the query's edges ``added_edges`` (FIFO label correcting, which the start's edges need).
        Over every edge of finite weight the counts change by at most 1 (table edges: the table's own distances,
        lower bounds once edges are removed; query edges: the correction), so the hop heuristic stays consistent; a
        retired query's edges (weight inf) are never relaxed by the search and may be ignored. None without a valid
        table (then the search runs the BFS)."""
        tab = getattr(self, "_hop_table", None)
        if tab is None or tab[0] != len(self._roadmap_mask) or not added_edges:
            return None
        R, T = tab
        g = self.graph
        e = np.asarray(added_edges, dtype=np.int64)
        e = e[g.edge_valid[e] & np.isfinite(g.weights[e])]
        nbr, _, deg = g.array_adjacency()
        hops = search_kernels.kernels().query_hops(T, R, nbr, deg, np.ascontiguousarray(g.edge_u[e]),
                                                   np.ascontiguousarray(g.edge_v[e]),
                                                   np.asarray(search_goals, dtype=np.int64))
        return hops[: g.n_nodes]

    def warm_up(self, score: bool = True) -> float:
        """Compile (first run after an install or a change of the kernels' source) or load from numba's disk cache
        every small-batch kernel a query uses (:mod:`psprm_core.fastpath`), on two template configurations, and the
        roadmap searches' kernels (:func:`~psprm_core.planning.graph_search.warm_up`), so that the first query does
        not pay for it; also times a three-knot path, which imports TOPP-RA (and matplotlib through it, about 1.4 s)
        now rather than in the first plan. ``score=False`` leaves out the scorer (the build's own warm-up: it must
        not score views of its own, e.g. with the oracle). Returns the seconds it took."""
        from .graph_search import warm_up as warm_up_search

        t0 = time.perf_counter()
        W = np.stack([self.template] * 3)
        if self.robot.mobile:  # drive 0.2 m and 0.4 m straight ahead
            W[1:, :2] += np.outer([0.2, 0.4], [np.cos(W[0, 2]), np.sin(W[0, 2])])
        else:
            W[1:, -1] += (0.05, 0.1)
        try:
            self._timed(W)
        except Exception as exc:  # the warm-up must never stop a build; the first plan then loads TOPP-RA itself
            log.debug("trajectory timing warm-up failed: %s", exc)
        warm_up_search()
        if self.device.type != "cpu" or not fastpath.available():
            return time.perf_counter() - t0
        q = self._t(np.stack([self.template, self.template]))
        qb = q.clone()
        qb[1, 0] += 0.1
        self.checker.check(q)
        self.checker.check_detailed(q)
        self.checker.robot_aabb(q)  # the env_hits kernel of obstacle moves
        args = fastpath.neural_args(self.scorer, self.dtype)
        if score or args is not None:  # a neural scorer is the surrogate (one compiled call), not a rendered view
            self.score_configs(q)
        kn, ki = self.edge_knots(q, qb)  # a query's connection edges (one compiled call)
        self._track_knots(fastpath.edge_knot_seeds(self.motion, q, qb, self.settings.n_interp)[0])  # step by step
        if args is not None:  # the lazy verification's compiled calls
            fastpath.check_score_knots(self.motion, self.checker, self.robot, args, kn, ki, np.ones(2, bool),
                                       np.ones(2, bool), self.settings.edge_resolution, 200)
            # a two-edge knot store of its own: edge 1's knots computed into it, both checked and scored
            one = np.ones(1, bool)
            fastpath.verify_edges(self.motion, self.constraint, self.checker, args, kn.numpy().copy(),
                                  ki.numpy().copy(), np.arange(2), np.array([False, True]),
                                  q.double().numpy()[1:], qb.double().numpy()[1:], one, self.settings.n_interp, True,
                                  self.settings.projection, self._lo, self._hi, self.track_cols,
                                  self.settings.track_iters, np.ones(2, bool), np.ones(2, bool),
                                  self.settings.edge_resolution, 200)
        self._pieces(q, qb, max_steps=200, include_start=False)
        self.motion.distance(q, qb)
        fastpath.nearest(self.motion, q, qb, 1)
        return time.perf_counter() - t0

    def components(self) -> tuple:
        """Connected components of the roadmap: (valid roadmap node ids, component label of each)."""
        from scipy.sparse.csgraph import connected_components

        from .graph_search import _scipy_matrix

        ids = self.roadmap_node_ids()
        _, lab = connected_components(_scipy_matrix(self.graph, None), directed=False)
        return ids, lab[ids]

    def _expand(self, rng: np.random.Generator) -> dict:
        """PRM expansion step: bridge disconnected components to the largest one. Each round, for the largest other
        components (``expand_components``, at least 3 nodes), ``expand_nodes`` manifold nodes are sampled (:meth:`grow`)
        with their base within reach of the gap: around the midpoint between the component's node nearest (base
        position) to the largest component and that nearest node. Narrow passages of the visibility manifold (a
        wrist camera that must look over shelves) leave a uniform roadmap in pieces; this is where samples help."""
        s = self.settings
        added, rounds = 0, 0
        for _ in range(s.expand_rounds):
            ids, lab = self.components()
            cnt = np.bincount(lab)
            main = int(np.argmax(cnt))
            others = [int(c) for c in np.argsort(-cnt, kind="stable") if c != main and cnt[c] >= 3][:s.expand_components]
            if not others:
                break
            rounds += 1
            main_xy = self._t(self.graph.configs[ids[lab == main], :2])
            for c in others:
                xy = self._t(self.graph.configs[ids[lab == c], :2])
                d = torch.cdist(xy, main_xy)
                i = int(d.min(1).values.argmin())
                a, b = xy[i].cpu().numpy(), main_xy[int(d[i].argmin())].cpu().numpy()
                got = self.grow(s.expand_nodes, center=(a + b) / 2, radius=float(np.linalg.norm(a - b)) / 2 + 0.3,
                                rng=rng)
                added += got["added_nodes"]
        ids, lab = self.components()
        return {"expand_rounds": rounds, "expand_added_nodes": int(added),
                "largest_component": float(np.bincount(lab).max() / max(len(ids), 1))}

    def _embed(self, q: torch.Tensor) -> torch.Tensor:
        if not self.robot.mobile:
            return q
        w = self.motion.w_rot
        return torch.cat([q[:, :2], w * torch.cos(q[:, 2:3]), w * torch.sin(q[:, 2:3]), q[:, 3:]], -1)

    def _neighbours(self, A: torch.Tensor, B: torch.Tensor, k: int, exclude_self: bool = False, k_long: int = 0,
                    rng: Optional[np.random.Generator] = None) -> tuple:
        """k nearest nodes of B for each row of A under the motion metric (candidates from a Euclidean embedding),
        plus ``k_long`` random nodes within ``max_edge_length`` (embedding distance). Returns unique undirected pairs
        (u in A, v in B) and their motion costs."""
        ea, eb = self._embed(A), self._embed(B)
        kk = min(2 * k + (1 if exclude_self else 0), B.shape[0])
        rows, cols, lrows, lcols = [], [], [], []
        gen = torch.Generator(device="cpu").manual_seed(int(rng.integers(2**31)) if rng is not None else 0)
        for s in range(0, A.shape[0], 2048):
            d = torch.cdist(ea[s:s + 2048], eb)
            idx = d.topk(kk, largest=False).indices
            rows.append(torch.arange(s, s + idx.shape[0], device=A.device).repeat_interleave(kk))
            cols.append(idx.reshape(-1))
            if k_long > 0:  # random long edges: random keys, masked to the radius, take the k_long smallest keys
                key = torch.rand(d.shape, generator=gen).to(d.device)
                key[d > self.settings.max_edge_length] = 2.0
                lidx = key.topk(min(k_long, d.shape[1]), largest=False).indices
                okl = torch.gather(key, 1, lidx) < 2.0
                r = torch.arange(s, s + idx.shape[0], device=A.device).unsqueeze(1).expand_as(lidx)
                lrows.append(r[okl])
                lcols.append(lidx[okl])
        u, v = torch.cat(rows), torch.cat(cols)
        if exclude_self:
            keep = u != v
            u, v = u[keep], v[keep]
        dist = self.motion.distance(A[u], B[v])
        # keep the k best by the true metric per row, within the connection radius
        order = torch.argsort(u * (dist.max() + 1) + dist)
        u, v, dist = u[order], v[order], dist[order]
        first = torch.ones_like(u, dtype=torch.bool)
        rank = torch.arange(len(u), device=u.device) - torch.searchsorted(u, u, right=False)
        keep = (rank < k) & (dist <= self.settings.max_edge_length) & first
        u, v, dist = u[keep], v[keep], dist[keep]
        if lrows:
            lu, lv = torch.cat(lrows), torch.cat(lcols)
            if exclude_self:
                m = lu != lv
                lu, lv = lu[m], lv[m]
            ld = self.motion.distance(A[lu], B[lv])
            m = ld <= self.settings.max_edge_length
            u, v, dist = torch.cat([u, lu[m]]), torch.cat([v, lv[m]]), torch.cat([dist, ld[m]])
        if exclude_self:  # undirected, unique
            a, b = torch.minimum(u, v), torch.maximum(u, v)
            key = torch.unique(a * B.shape[0] + b)
            u, v = key // B.shape[0], key % B.shape[0]
            dist = self.motion.distance(A[u], B[v])
        return u, v, dist

    # ---- edges: knots on the manifold ---------------------------------------------------------------------------
    def edge_knots(self, qa: torch.Tensor, qb: torch.Tensor, track: bool = True) -> tuple:
        """Knots of the local motions qa -> qb (E, dof): (knots (E, M, dof), interior index (E, N)).

        The base follows its differential-drive path (rotate, translate, rotate); the knots are the endpoints, the
        two drive corners and the N Eq. 1 samples s = i / (N + 1), sorted along the motion, and at every interior
        knot the non-base camera joints are re-projected onto the visibility manifold (a few Newton steps from the
        interpolated value), so the camera keeps tracking the target along the edge. Consecutive knots always lie in
        the same drive phase, so joint-space interpolation between them is a motion the base can execute.

        ``track=False``: the *untracked* knots: the non-base joints are interpolated plainly (no re-aiming), i.e. the
        knots lie on the local motion itself (the fallback of connection edges whose re-aimed version collides, and
        the edges of the escape search).
        """
        E, n = qa.shape[0], self.settings.n_interp
        dt, dev = qa.dtype, qa.device
        if fastpath.motion_applies(qa, qb) and E * (n + 4) <= fastpath.MAX_BATCH:  # a query's few edges: one call
            ps = self.settings.projection
            return fastpath.query_knots(self.motion, self.constraint, qa, qb, n, track, ps, self._lo, self._hi,
                                        self.track_cols, self.settings.track_iters)
        if fastpath.motion_applies(qa, qb) and fastpath.fits(E * (n + 4)):  # bulk: compiled, in row chunks
            knots, interior_idx = fastpath.edge_knot_seeds(self.motion, qa, qb, n)
            return (self._track_knots(knots) if track else knots), interior_idx
        if self.robot.mobile:
            _, r1, d, r2 = self.motion._base_plan(qa, qb)
            l1, l2, l3 = self.motion.w_rot * r1.abs(), d, self.motion.w_rot * r2.abs()
            tot = (l1 + l2 + l3).clamp_min(1e-12)
            corners = torch.stack([l1 / tot, (l1 + l2) / tot], -1)
        else:
            corners = torch.zeros(E, 0, dtype=dt, device=dev)
        samples = (torch.arange(1, n + 1, dtype=dt, device=dev) / (n + 1)).expand(E, n)
        s_all = torch.cat([torch.zeros(E, 1, dtype=dt, device=dev), samples, corners,
                           torch.ones(E, 1, dtype=dt, device=dev)], -1)
        order = torch.argsort(s_all, dim=-1, stable=True)
        s_sorted = torch.gather(s_all, 1, order)
        inv = torch.argsort(order, dim=-1)
        interior_idx = inv[:, 1:1 + n]
        M = s_all.shape[1]
        knots = self.motion.interpolate(qa.repeat_interleave(M, 0), qb.repeat_interleave(M, 0), s_sorted.reshape(-1))
        knots = knots.reshape(E, M, -1)
        return (self._track_knots(knots) if track else knots), interior_idx

    def _track_knots(self, knots: torch.Tensor) -> torch.Tensor:
        """Knots (E, M, dof) with the non-base camera joints of the interior ones re-projected onto the visibility
        manifold (``track_iters`` Gauss-Newton steps of Alg. 1, line 7, from the interpolated values)."""
        E, M, dof = knots.shape
        if len(self.track_cols) and M > 2:
            inner = knots[:, 1:-1].reshape(-1, dof)
            ps = dataclasses.replace(self.settings.projection, max_iters=self.settings.track_iters)
            proj, _ = self.constraint.project(inner, ps, self._lo, self._hi, joints=self.track_cols)
            knots = torch.cat([knots[:, :1], proj.reshape(E, M - 2, -1), knots[:, -1:]], 1)
        return knots

    def _query_knots(self, qa: torch.Tensor, qb: torch.Tensor) -> tuple:
        """:meth:`edge_knots` of start/goal query edges, cached by their end configurations (the cache is cleared
        with the knot store: new roadmap, new visibility focus). Misses are computed in one batch."""
        cache = self.knots.query
        A, B = qa.detach().cpu().numpy(), qb.detach().cpu().numpy()
        keys = [a.tobytes() + b.tobytes() for a, b in zip(A, B)]
        miss = [i for i, k in enumerate(keys) if k not in cache]
        if miss:
            kn, ki = self.edge_knots(qa[miss], qb[miss])
            for j, i in enumerate(miss):
                cache[keys[i]] = (kn[j], ki[j])
        out = (torch.stack([cache[k][0] for k in keys]), torch.stack([cache[k][1] for k in keys]))
        self.knots.trim_query_cache()
        return out

    def _put_knots(self, edge_ids: np.ndarray, u_given: np.ndarray, knots: torch.Tensor,
                   interior: torch.Tensor) -> None:
        """Keep knots computed from ``u_given`` to the other end, flipped where the graph stores the edge the other
        way round (the roadmap keeps undirected edges as (min id, max id))."""
        edge_ids = np.asarray(edge_ids, dtype=np.int64)
        flip = torch.as_tensor(self.graph.edge_u[edge_ids] != np.asarray(u_given), device=knots.device)
        M = knots.shape[1]
        knots = torch.where(flip[:, None, None], knots.flip(1), knots)
        interior = torch.where(flip[:, None], (M - 1 - interior).flip(1), interior)
        self.knots.put(edge_ids, knots, interior)

    def stored_knots(self, edge_ids: np.ndarray) -> torch.Tensor:
        """Knots (E, M, dof) and Eq. 1 sample positions (E, N) of graph edges in their stored u -> v direction,
        computed once and kept."""
        g = self.graph
        edge_ids = np.asarray(edge_ids, dtype=np.int64)
        miss = edge_ids[~self.knots.known(edge_ids)]
        if len(miss) and self._pending_query_knots is not None:  # the current query's own edges, from their ends
            peids, ua, qa, qb = self._pending_query_knots
            sel = np.nonzero((peids[:, None] == miss[None, :]).any(1))[0]  # a few dozen x a few: cheaper than isin
            if len(sel):
                self._put_knots(peids[sel], ua[sel], *self._query_knots(qa[sel], qb[sel]))
                miss = edge_ids[~self.knots.known(edge_ids)]
        if len(miss):
            miss = np.unique(miss)
            self.knots.put(miss, *self.edge_knots(self._t(g.configs[g.edge_u[miss]]), self._t(g.configs[g.edge_v[miss]])))
        return self.knots.get(edge_ids)

    def _knots_valid(self, knots: torch.Tensor, dense: bool = True) -> torch.Tensor:
        """Collision-free flags (E,) of knot sequences: the knots, and with ``dense`` every ``edge_resolution``
        between them (only for sequences whose knots are free)."""
        E, M, dof = knots.shape
        if dense and E <= SMALL_BATCH and M > 2:
            # a few edges (a lazy search verifying its path): one checker call for the knots and the dense pieces,
            # since a call's fixed cost dominates at this size (large batches check the knots first, as a filter)
            inner = knots[:, 1:-1].reshape(-1, dof)
            a, b = knots[:, :-1].reshape(-1, dof), knots[:, 1:].reshape(-1, dof)
            seg, pts = self._pieces(a, b, max_steps=200, include_start=False)
            bad = self.checker.check(torch.cat([inner, pts]))
            ok = ~bad[:len(inner)].reshape(E, M - 2).any(-1)
            seg_ok = torch.ones(len(a), dtype=torch.bool, device=a.device)
            seg_ok[seg[bad[len(inner):]]] = False
            return ok & seg_ok.reshape(E, M - 1).all(-1)
        ok = self.checker.valid(knots[:, 1:-1].reshape(-1, dof)).reshape(E, M - 2).all(-1) if M > 2 else \
            torch.ones(E, dtype=torch.bool, device=knots.device)
        if not dense or not ok.any():
            return ok
        idx = torch.nonzero(ok, as_tuple=True)[0]
        ok[idx] = self._dense_valid(knots[idx])
        return ok

    def _dense_valid(self, knots: torch.Tensor) -> torch.Tensor:
        """Collision-free flags (E,) of the straight pieces between consecutive knots (endpoints excluded)."""
        E, M, dof = knots.shape
        ok = torch.ones(E, dtype=torch.bool, device=knots.device)
        a, b = knots[:, :-1].reshape(-1, dof), knots[:, 1:].reshape(-1, dof)
        seg, pts = self._pieces(a, b, max_steps=200, include_start=False)
        if len(seg):
            bad = self.checker.check(pts)
            seg_ok = torch.ones(len(a), dtype=torch.bool, device=a.device)
            seg_ok[seg[bad]] = False
            ok &= seg_ok.reshape(E, M - 1).all(-1)
        return ok

    def _edges_valid(self, qa: torch.Tensor, qb: torch.Tensor, chunk: int = 4096,
                     end_scores: Optional[tuple] = None) -> tuple:
        """Valid flags (E,), Eq. 1 perception (E,) of local motions (NaN where invalid) and the knots of the valid
        ones (V, M, dof). ``end_scores``: raw scores (E,) of ``qa`` and ``qb`` when known (the roadmap's node
        scores), so that only the N interior samples of each edge are scored."""
        ok = torch.zeros(qa.shape[0], dtype=torch.bool, device=self.device)
        p = torch.full((qa.shape[0],), float("nan"), dtype=self.dtype, device=self.device)
        kept, kept_i = [], []
        for s0 in range(0, qa.shape[0], chunk):
            a, b = qa[s0:s0 + chunk], qb[s0:s0 + chunk]
            knots, interior = self.edge_knots(a, b)
            v = self._knots_valid(knots, dense=not self.settings.lazy_collision)
            if self.settings.edge_view_slack >= 0:
                inner = torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, knots.shape[-1]))
                v &= self.constraint.in_view(inner.reshape(-1, knots.shape[-1]),
                                             slack=self.settings.edge_view_slack).reshape(v.shape[0], -1).all(-1)
            ok[s0:s0 + chunk] = v
            kept.append(knots[v])
            kept_i.append(interior[v])
            if not self.settings.lazy_edges and v.any():
                ends = None if end_scores is None else \
                    tuple(e[s0:s0 + chunk][v].to(self.device, self.dtype) for e in end_scores)
                p[s0:s0 + chunk][v] = self._knots_perception(knots[v], interior[v], ends=ends)
        dof = self.robot.dof
        if not kept:
            return ok, p, (torch.zeros(0, 2, dof, dtype=self.dtype, device=self.device),
                           torch.zeros(0, self.settings.n_interp, dtype=torch.long, device=self.device))
        return ok, p, (torch.cat(kept), torch.cat(kept_i))

    def _weight(self, p, c_m):
        """Edge weight of the configured objective (:func:`~.graph_search.edge_weight`): Eq. 2 or the motion-weighted
        form, from the Eq. 1 perception ``p`` and the normalised motion cost ``c_m`` (numpy or torch)."""
        return edge_weight(p, c_m, self.settings.alpha, self.settings.objective)

    @property
    def heuristic_name(self) -> str:
        """The A* heuristic queries use: the setting, with ``auto`` resolved (hop for Eq. 2, distance for the
        motion-weighted objective)."""
        h = self.settings.heuristic
        if h == "auto":
            return "distance" if self.settings.objective == "motion" else "hop"
        return h

    def _distance_heuristic(self, goal_ids: Sequence[int], sink: Optional[int]) -> np.ndarray:
        """Per-node :func:`~.graph_search.motion_heuristic` to the goals ``goal_ids``: (1 - alpha) times the motion
        lower bound |dxy| + ||d joints|| (every local motion costs at least that, :mod:`psprm_core.motion`) to the
        nearest goal, over the roadmap's longest edge; 0 at the virtual ``sink`` of a multi-goal query."""
        g = self.graph
        Q = g.configs[: g.n_nodes]
        G = g.configs[np.asarray(goal_ids, dtype=np.int64)]
        lb = np.full(len(Q), np.inf)
        for q in G:
            if self.robot.mobile:
                d = np.linalg.norm(Q[:, :2] - q[:2], axis=1) + np.linalg.norm(Q[:, 3:] - q[3:], axis=1)
            else:
                d = np.linalg.norm(Q - q, axis=1)
            np.minimum(lb, d, out=lb)
        if sink is not None:
            lb[sink] = 0.0
        return motion_heuristic(lb, self.settings.alpha, self.max_motion)

    def _normalized(self, scores: torch.Tensor) -> torch.Tensor:
        """Normalised perception score c_p in [0, 1] (scores divided by the roadmap's 99th-percentile node score)."""
        return (scores * getattr(self, "score_scale", 1.0)).clamp(0.0, 1.0)

    def _eq1_cameras(self, knots: torch.Tensor, interior: torch.Tensor) -> torch.Tensor:
        """Camera poses (E, N + 2, 4, 4) of an edge's Eq. 1 points: both ends and the N interior samples."""
        E, M, dof = knots.shape
        n = interior.shape[1]
        pts = torch.cat([knots[:, :1], torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, dof)),
                         knots[:, -1:]], 1)
        return self.robot.camera_poses(pts.reshape(-1, dof)).reshape(E, n + 2, 4, 4)

    def _knots_perception(self, knots: torch.Tensor, interior: torch.Tensor,
                          cams: Optional[torch.Tensor] = None, ends: Optional[tuple] = None) -> torch.Tensor:
        """Eq. 1 from knots (or their cached Eq. 1 camera poses): mean normalised score of both ends and the N
        interior samples. ``ends``: the raw scores (E,) of both ends when already known (only the interior samples
        are then scored)."""
        if ends is not None and cams is None:
            E, M, dof = knots.shape
            inner = torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, dof)).reshape(-1, dof)
            sc = self.scorer.score(self.robot.camera_poses(inner)).to(self.dtype).reshape(E, -1)
            return edge_perception(self._normalized(ends[0]), self._normalized(ends[1]), self._normalized(sc))
        if cams is None:
            cams = self._eq1_cameras(knots, interior)
        E, P = cams.shape[:2]
        sc = self._normalized(self.scorer.score(cams.reshape(-1, 4, 4)).to(self.dtype).reshape(E, P))
        return edge_perception(sc[:, 0], sc[:, -1], sc[:, 1:-1])

    def _stored_perception(self, edge_ids: np.ndarray) -> torch.Tensor:
        """Eq. 1 of graph edges from their stored knots; camera poses are computed once and kept."""
        knots, interior = self.stored_knots(edge_ids)
        have = self.knots.known_cams(edge_ids)
        if not have.all():
            miss = np.unique(np.asarray(edge_ids)[~have])
            k, i = self.knots.get(miss)
            self.knots.put_cams(miss, self._eq1_cameras(k, i))
        return self._knots_perception(knots, interior, cams=self.knots.cams[
            torch.as_tensor(np.asarray(edge_ids, dtype=np.int64), device=knots.device)])

    # ---- query -----------------------------------------------------------------------------------------------------
    def set_alpha(self, alpha: float) -> None:
        """Re-weight every edge with a new alpha (Eq. 2) without rebuilding (alpha = 0: shortest-path PRM)."""
        self.reweight(alpha=alpha)

    def reweight(self, alpha: Optional[float] = None, objective: Optional[str] = None) -> None:
        """Re-weight every edge from its stored Eq. 1 perception and motion cost with a new ``alpha`` and/or objective
        form (:data:`~.graph_search.OBJECTIVES`) without rebuilding; ``None`` keeps the current one."""
        changes = {k: v for k, v in (("alpha", alpha), ("objective", objective)) if v is not None}
        new = dataclasses.replace(self.settings, **changes)
        new.validate()
        self._compact()
        g = self.graph
        ids = g.valid_edge_ids()
        c_m = g.edge_attribute("c_m")[ids]
        if new.objective == "eq2":
            c_m = np.clip(c_m, 0, 1)
        g.set_weights(ids, edge_weight(g.edge_attribute("c_p")[ids], c_m, new.alpha, new.objective))
        self.settings = new  # last: a reader that sees the new settings sees the new weights

    @_one_thread
    def plan(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
             goal_costs: Optional[np.ndarray] = None) -> PlanResult:
        """Plan from ``start`` to the cheapest of ``goals`` (one configuration (dof,) or several (G, dof)); see
        :meth:`_plan_once`.

        When no goal is reachable (a start or goal whose connecting edges all collide, e.g. next to a wall where the
        base cannot turn), an escape search runs first (``query_escape_s`` > 0, below); if it does not succeed, the
        roadmap is repaired locally: ``query_repair_nodes`` manifold nodes are grown around the
        start and each goal (up to 4), half of them along its heading (reachable by driving straight), and the query
        is repeated, connecting each end to every node grown for it and to its ``query_repair_connect_k`` nearest
        nodes. Up to ``query_repair_rounds`` rounds, each with 1.5 times the previous radius. The nodes of a repair
        that succeeds stay in the roadmap, within ``query_repair_budget``; those of a repair that fails are removed
        again, so that they do not use up the budget of later queries; after ``query_repair_failures`` such failed
        repairs (their removed node slots stay allocated) a failing query is no longer repaired, so a goal that stays
        unreachable cannot make a long-running planner grow without end.

        The two other stages (not once ``query_repair_failures`` is reached, like the repair):

        - escape (``query_escape_s`` > 0), before the repair: a bounded RRT-like search of differential-drive motions
          with the arm moving (turn in place, drive or back up, joints interpolated, untracked) from each end to the
          roadmap's largest component (:meth:`_escape`, ``query_escape_*``); its configurations and densely checked
          edges join the query as query nodes and edges, scored (Eq. 1) like any other edge, and the query is
          searched once more. An end it cannot get out of is named in the reason of a query that fails ("start is boxed
          in: no collision-free motion out of it was found ..." when not one short motion out of it is free);
        - wide (``query_wide_k`` > 0), when the escape and the repair did not succeed: each end tries its
          ``query_wide_k`` nearest roadmap nodes, however far (long connections, checked and scored like any other),
          for ends whose few free motions lead beyond the repair's neighbours (a robot across a shelf aisle).

        In the escape's and the wide query (``query_untracked_fallback``), a connection edge whose re-aimed knots
        collide (the arm re-aiming the camera sweeps a shelf) is kept with its untracked knots (the camera joints
        interpolated plainly) when those are collision-free; the first query and the repaired ones are unchanged."""
        res = self._plan_once(start, goals, timing, goal_costs)
        if res.success or "reachable" not in res.reason or self.graph is None:
            return res
        t0 = time.perf_counter()
        s = self.settings
        k = s.query_wide_k
        # after query_repair_failures failed repairs an unreachable goal is given up cheaply (a replanner may ask again
        # and again): no escape, repair or wide attempt
        escaped = None
        out = res
        if s.query_escape_s > 0 and self._repair_failed < s.query_repair_failures:
            escaped = self._escape_query(start, goals, timing, goal_costs)
            if escaped.success:
                out = escaped
        if not out.success:
            out = self._repair_query(start, goals, timing, goal_costs, res)
        if (not out.success and "reachable" in out.reason and k > s.query_repair_connect_k
                and self._repair_failed < s.query_repair_failures):
            wide = self._plan_once(start, goals, timing, goal_costs, extra_candidates={}, connect_k=k,
                                   untracked=s.query_untracked_fallback)
            if wide.success or "reachable" not in wide.reason:
                out = wide
                if wide.success:
                    out.reason = f"ok after connecting to the {k} nearest roadmap nodes"
        if not out.success and escaped is not None:  # the escape search says which end could not get out
            out = escaped
        out.query_ms = (res.query_ms or 0.0) + (time.perf_counter() - t0) * 1e3
        return out

    def _escape_query(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool,
                      goal_costs: Optional[np.ndarray]) -> PlanResult:
        """The escape stage of :meth:`plan`: an :meth:`_escape` search from each end (start, up to 4 goals) to the
        roadmap's largest component within ``query_escape_s`` in total, then the query with the found
        configurations and edges added. Ends with a direct connection need no tree (their connections are added)."""
        s = self.settings
        t0 = time.perf_counter()
        ends = [np.asarray(start, float).reshape(-1)] + list(np.asarray(goals, float).reshape(-1, self.robot.dof))[:4]
        self._compact()
        ids, lab = self.components()
        if len(ids) == 0:
            return PlanResult(False, "goal not reachable on the roadmap (empty roadmap)")
        targets = ids[lab == int(np.argmax(np.bincount(lab)))]
        q_end = self._t(np.stack(ends))
        bad = self.checker.check(q_end).cpu().numpy()
        self._escapes += 1
        rng = np.random.default_rng([s.seed, self._escapes, 7])
        # first the direct connections of every end (no tree), then the time is shared by the ends that need one
        escapes = {k: self._escape(q_end[k], targets, rng, 0.0) for k in range(len(ends)) if not bad[k]}
        order = [k for k, e in escapes.items() if not e.success]
        why = []
        for j, k in enumerate(order):
            left = s.query_escape_s - (time.perf_counter() - t0)
            deadline = time.perf_counter() + max(left, 0.0) / (len(order) - j)  # unused time goes to later ends
            esc = self._escape(q_end[k], targets, rng, deadline)
            escapes[k] = esc
            if not esc.success:
                name = "start" if k == 0 else (f"goal {k - 1}" if len(ends) > 2 else "goal")
                if esc.explored <= 1:
                    why.append(f"{name} is boxed in: no collision-free motion out of it was found "
                               f"({esc.tried} short motions tried in {esc.seconds:.2f} s)")
                else:
                    where = f", bases within {esc.base_reach:.2f} m of it" if self.robot.mobile else ""
                    why.append(f"{name}: the escape search found no way to the roadmap's largest component "
                               f"({esc.explored} configurations reached in {esc.seconds:.1f} s{where})")
        res = self._plan_once(start, goals, timing, goal_costs, untracked=s.query_untracked_fallback,
                              escapes={k: e for k, e in escapes.items() if e.success})
        if res.success:
            n = sum(len(e.configs) for e in escapes.values())
            res.reason = f"ok after an escape search ({n} intermediate configurations)"
        elif why:  # the ends that could not get out say why the query fails
            res.reason = "; ".join(why)
        log.debug("escape search: %s", res.reason)
        return res

    def _nearest_ids(self, qq: torch.Tensor, pool: torch.Tensor, k: int) -> torch.Tensor:
        """Indices (Q, k) of the ``k`` configurations of ``pool`` nearest to each of ``qq`` (motion metric)."""
        k = min(k, pool.shape[0])
        if fastpath.motion_applies(qq, qq) and pool.device.type == "cpu" and k > 0:
            if pool is getattr(self, "_rm_cache", None):  # the roadmap: its float64 copy is kept with it
                if getattr(self, "_rm_f64", None) is None:
                    self._rm_f64 = self._rm_numpy.astype(np.float64)
                pool = self._rm_f64
            return fastpath.nearest(self.motion, qq, pool, k)  # one compiled pass that skips far nodes early
        d = self.motion.distance(qq.repeat_interleave(pool.shape[0], 0), pool.repeat(len(qq), 1))
        return d.reshape(len(qq), -1).topk(k, largest=False).indices

    @_large_batches
    def _escape(self, q0: torch.Tensor, targets: np.ndarray, rng: np.random.Generator,
                deadline: float) -> EscapeResult:
        """Bounded RRT-like escape search from a query end ``q0`` (dof,) to the roadmap nodes ``targets``.

        For ends the first query could not connect (a mobile manipulator boxed in between shelves, facing a wall,
        its arm over a shelf): a tree of collision-free local motions grows from the end. Each round draws
        ``ESCAPE_BATCH`` random configurations (the base within ``query_escape_radius`` of the end for half of them,
        within twice that for the others, so that the tree can follow a long aisle out; any heading; the
        other joints uniform within their limits or those of a nearby target node; some are target nodes
        themselves) and extends the nearest tree node towards each along the local motion (differential drive: turn
        in place, drive straight forwards or backwards, turn; the joints move at the same time, untracked), by
        ``query_escape_step`` and by ``ESCAPE_LONG`` times that (kept when free). ``ESCAPE_MANOEUVRES`` of them are
        manoeuvres from random tree nodes instead: drive or back up along the heading, or turn in place by 90 degrees,
        the other joints kept or moving towards the template pose, so that a robot in a dead end backs out and then
        turns. Extensions are kept when their end configuration and their motion are collision-free (the motion
        checked densely, as every edge). An end from which not one extension is free after ``ESCAPE_STUCK_ROUNDS``
        rounds is given up early (boxed in). Every new configuration tries a direct connection to its
        ``query_escape_connect_k`` nearest target nodes. The search stops at the first round with a free connection,
        at ``query_escape_nodes`` tree nodes or at ``deadline``; the branches leading to the found connections are
        kept, shortened greedily (:meth:`_shortcut`)."""
        s, r = self.settings, self.robot
        t0 = time.perf_counter()
        dof = r.dof
        if r.mobile:  # every tree configuration lies within the radius: farther nodes are beyond a connection
            xy = np.linalg.norm(self.graph.configs[targets, :2] - q0[:2].cpu().numpy(), axis=1)
            targets = targets[xy <= 2 * s.query_escape_radius + 2 * s.max_edge_length]
            if len(targets) == 0:
                return EscapeResult(q0[None][:0], [], _no_knots(self), [], _no_knots(self),
                                    seconds=time.perf_counter() - t0)
        rm = self._t(self.graph.configs[targets])
        lo = np.where(np.isfinite(r.lower), r.lower, -np.pi)
        hi = np.where(np.isfinite(r.upper), r.upper, np.pi)
        if r.mobile:
            lo[:2], hi[:2] = self.scene.workspace[:, 0], self.scene.workspace[:, 1]
        parent = [-1]
        knots_of: list = [None]  # (knots, interior) of the edge parent -> node
        T = q0[None]
        tried = 0

        def connect(new_idx: np.ndarray) -> list:
            """Free connections (tree index, target index, knots, interior) of tree nodes ``new_idx``."""
            qn = T[torch.as_tensor(new_idx, device=self.device)]
            pool = torch.arange(len(rm), device=self.device)
            if r.mobile:  # the motion cost is at least the base's xy distance: farther nodes are no candidates
                pool = torch.nonzero((torch.cdist(qn[:, :2], rm[:, :2]) <= 2 * s.max_edge_length).any(0),
                                     as_tuple=True)[0]
                if len(pool) == 0:
                    return []
            cand = pool[self._nearest_ids(qn, rm[pool], s.query_escape_connect_k).to(self.device)]
            kk = cand.shape[1]
            src = torch.arange(len(qn), device=self.device).repeat_interleave(kk)
            dst = cand.reshape(-1)
            qa, qb = qn[src], rm[dst]
            d = self.motion.distance(qa, qb)
            near = torch.nonzero(d <= 2 * s.max_edge_length, as_tuple=True)[0]
            if len(near) == 0:
                return []
            if len(near) > ESCAPE_CONNECT:  # the shortest candidates of the round (the likeliest to be free)
                near = near[d[near].topk(ESCAPE_CONNECT, largest=False).indices]
            kn, ki = self.edge_knots(qa[near], qb[near], track=False)
            ok = self._escape_free(kn)
            out = []
            for j in torch.nonzero(ok, as_tuple=True)[0].tolist():
                i = int(near[j])
                out.append((int(new_idx[int(src[i])]), int(dst[i]), kn[j], ki[j]))
            return out

        found = connect(np.array([0]))
        near_t = np.zeros(0, dtype=np.int64)
        if r.mobile:
            near_t = np.nonzero(np.linalg.norm(self.graph.configs[targets, :2] - q0[:2].cpu().numpy(), axis=1)
                                <= s.query_escape_radius)[0]
        rounds = 0
        while not found and len(parent) < s.query_escape_nodes and time.perf_counter() < deadline:
            if len(parent) == 1 and rounds >= ESCAPE_STUCK_ROUNDS:  # not one motion out of the end is free
                break
            rounds += 1
            B = ESCAPE_BATCH
            q = lo + rng.random((B, dof)) * (hi - lo)
            pick = near_t if len(near_t) else np.arange(len(targets))
            like = rng.choice(pick, B)  # configurations of nearby target nodes
            u = rng.random(B)
            q[u < 0.5, r.base_dof:] = self.graph.configs[targets[like[u < 0.5]], r.base_dof:]
            if r.mobile:
                ang = rng.uniform(-np.pi, np.pi, B)
                rad = s.query_escape_radius * np.sqrt(rng.random(B)) * np.where(np.arange(B) % 2, 2.0, 1.0)
                q[:, :2] = q0[:2].cpu().numpy() + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
                q[:, 2] = rng.uniform(-np.pi, np.pi, B)
            goal_bias = u < 0.15
            q[goal_bias] = self.graph.configs[targets[like[goal_bias]]]
            nn = self._nearest_ids(self._t(np.clip(q, lo, hi)), T, 1)[:, 0].cpu().numpy()
            if r.mobile:  # manoeuvres from random tree nodes: drive / back up along the heading, or turn in place,
                # the other joints kept or moving towards the template (a tucked, camera-ready pose)
                m = ESCAPE_MANOEUVRES
                src = rng.integers(0, len(parent), m)
                qm = T[torch.as_tensor(src, device=self.device)].cpu().numpy().astype(float)
                sign = rng.choice([-1.0, 1.0], m)
                drive = rng.random(m) < 0.5
                L = ESCAPE_LONG * s.query_escape_step
                qm[drive, 0] += sign[drive] * L * np.cos(qm[drive, 2])
                qm[drive, 1] += sign[drive] * L * np.sin(qm[drive, 2])
                qm[~drive, 2] = np.angle(np.exp(1j * (qm[~drive, 2] + sign[~drive] * np.pi / 2)))
                tuck = rng.random(m) < 0.5
                qm[tuck, r.base_dof:] = self.template[r.base_dof:]
                q[-m:], nn[-m:] = qm, src
            q_rand = self._t(np.clip(q, lo, hi))
            nn = torch.as_tensor(nn, device=self.device)
            q_near = T[nn]
            d = self.motion.distance(q_near, q_rand).clamp_min(1e-9)
            # a short and a long extension of each (the long one, ESCAPE_LONG steps, is kept where it is free: the
            # tree follows an open aisle in few steps)
            frac = torch.cat([(s.query_escape_step / d).clamp(max=1.0),
                              (ESCAPE_LONG * s.query_escape_step / d).clamp(max=1.0)])
            q_from = torch.cat([q_near, q_near])
            q_new = self.motion.interpolate(q_from, torch.cat([q_rand, q_rand]), frac)
            tried += B
            ok = self.checker.valid(q_new)
            if not ok.any():
                continue
            sel = torch.nonzero(ok, as_tuple=True)[0]
            kn, ki = self.edge_knots(q_from[sel], q_new[sel], track=False)
            free = self._escape_free(kn)
            okf = torch.zeros(2 * B, dtype=torch.bool, device=self.device)
            okf[sel[free]] = True
            use_long = okf[B:] & (frac[B:] > frac[:B])
            pick = torch.nonzero(use_long | okf[:B], as_tuple=True)[0]
            pick = torch.where(use_long[pick], pick + B, pick)
            if len(pick) == 0:
                continue
            row = {int(j): n for n, j in enumerate(sel.tolist())}
            first = len(parent)
            for j in pick.tolist():
                parent.append(int(nn[j % B]))
                knots_of.append((kn[row[j]], ki[row[j]]))
            T = torch.cat([T, q_new[pick]])
            found = connect(np.arange(first, len(parent)))
        seconds = time.perf_counter() - t0
        dof_zero = _no_knots(self)
        reach = float((T[:, :2] - q0[:2]).norm(dim=-1).max()) if r.mobile else 0.0
        if not found:
            return EscapeResult(self._t(np.zeros((0, dof))), [], dof_zero, [], dof_zero, explored=len(parent),
                                tried=tried, seconds=seconds, base_reach=reach)
        # keep the branches to the (at most ESCAPE_KEEP) found connections, shortened
        found = found[:ESCAPE_KEEP]
        keep_nodes, tree_edges = {}, {}
        for a, _, _, _ in found:
            chain = [a]
            while parent[chain[-1]] >= 0:
                chain.append(parent[chain[-1]])
            chain = chain[::-1]  # root ... a
            for i, j, kn, ki in self._shortcut(T, chain, knots_of):
                tree_edges[(i, j)] = (kn, ki)
                keep_nodes.update({i: None, j: None})
        keep_nodes.pop(0, None)
        remap = {old: n for n, old in enumerate(sorted(keep_nodes))}
        remap[0] = -1
        configs = T[torch.as_tensor(sorted(keep_nodes), dtype=torch.long, device=self.device)] if keep_nodes \
            else T[:0]
        tree = [(remap[i], remap[j]) for i, j in tree_edges]
        conn = [(remap[a], int(targets[b])) for a, b, _, _ in found]

        def stack(items):
            if not items:
                return dof_zero
            return torch.stack([k for k, _ in items]), torch.stack([i for _, i in items])

        return EscapeResult(configs, tree, stack(list(tree_edges.values())), conn,
                            stack([(kn, ki) for _, _, kn, ki in found]), explored=len(parent), tried=tried,
                            seconds=time.perf_counter() - t0, base_reach=reach)

    def _escape_free(self, knots: torch.Tensor) -> torch.Tensor:
        """Collision-free flags (E,) of the escape search's candidate edges, densely checked like
        :meth:`_knots_valid`, but always the knots first: most candidates collide, and their few knots are cheap."""
        ok = self._knots_valid(knots, dense=False)
        if ok.any():
            idx = torch.nonzero(ok, as_tuple=True)[0]
            ok[idx] = self._dense_valid(knots[idx])
        return ok

    def _shortcut(self, T: torch.Tensor, chain: list, knots_of: list) -> list:
        """Greedy shortcut of a tree branch ``chain`` (tree indices, root first): from each kept node, the farthest
        later node of the branch reachable by one collision-free untracked local motion (checked densely; all
        candidates of a node in one batch). Returns the kept edges (i, j, knots, interior), i -> j along the branch."""
        out, i = [], 0
        while i < len(chain) - 1:
            later = list(range(i + 2, len(chain)))
            j = i + 1
            if later:
                qa = T[chain[i]][None].expand(len(later), -1)
                qb = T[torch.as_tensor([chain[x] for x in later], device=self.device)]
                kn, ki = self.edge_knots(qa, qb, track=False)
                ok = torch.nonzero(self._escape_free(kn), as_tuple=True)[0]
                if len(ok):
                    m = int(ok.max())
                    j = later[m]
                    out.append((chain[i], chain[j], kn[m], ki[m]))
                    i = j
                    continue
            kn, ki = knots_of[chain[j]]
            out.append((chain[i], chain[j], kn, ki))
            i = j
        return out

    def _add_escapes(self, escapes: dict, end_node: dict, added_nodes: list) -> list:
        """Add the escape searches' configurations (as query nodes, appended to ``added_nodes``) and their checked
        edges (scored with Eq. 1 on their stored untracked knots) to the graph; returns the new edge ids."""
        g = self.graph
        eids = []
        for k, esc in escapes.items():
            if k not in end_node or not esc.success:
                continue
            nid = np.zeros(0, dtype=np.int64)
            if len(esc.configs):
                nid = np.asarray(g.add_nodes(esc.configs.double().cpu().numpy()), dtype=np.int64)
                added_nodes.extend(int(n) for n in nid)
                scores = self._node_score_slots()
                scores[nid] = self.score_configs(esc.configs).double().cpu().numpy()

            def node(i):
                return end_node[k] if i < 0 else int(nid[i])

            for pairs, (kn, ki), rm_end in ((esc.tree, esc.tree_knots, False), (esc.conn, esc.conn_knots, True)):
                if not pairs:
                    continue
                ua = np.asarray([node(a) for a, _ in pairs])
                vb = np.asarray([b if rm_end else node(b) for _, b in pairs])
                p = self._knots_perception(kn, ki).cpu().numpy()
                d = self._motion_distance(kn[:, 0].cpu().numpy(), kn[:, -1].cpu().numpy())
                new = self._add_query_edges(ua, vb, p, d, verified=True)
                self._put_knots(np.asarray(new), ua, kn, ki)
                eids.extend(new)
        return eids

    def _repair_query(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool,
                      goal_costs: Optional[np.ndarray], res: PlanResult) -> PlanResult:
        """The local roadmap repair of :meth:`plan` after the failed query ``res``."""
        s = self.settings
        ends = [np.asarray(start, float).reshape(-1)] + list(np.asarray(goals, float).reshape(-1, self.robot.dof))[:4]
        added, grown, again = 0, {}, None
        mobile = self.robot.mobile
        for r in range(max(1, s.query_repair_rounds)):
            if (s.query_repair_budget - self._repair_added <= 0 or s.query_repair_nodes <= 0
                    or self._repair_failed >= s.query_repair_failures):
                break
            self._repairs += 1
            rng = np.random.default_rng([s.seed, self._repairs])
            for k, q in enumerate(ends):
                n = min(s.query_repair_nodes, s.query_repair_budget - self._repair_added)
                if n <= 0:
                    break
                out = self.grow(n, center=q[:2] if mobile else None, radius=s.query_repair_radius * 1.5 ** r,
                                rng=rng, timeout_s=1.0, heading=float(q[2]) if mobile else None)
                added += out["added_nodes"]
                self._repair_added += out["added_nodes"]
                grown[k] = np.concatenate([grown.get(k, np.zeros(0, dtype=np.int64)), out["node_ids"]])
            # an end in a tight spot (a goal grazing a table, reachable only by turning one way) may have its few
            # valid edges beyond the connect_k nearest nodes; the nodes grown on its heading line are reachable by
            # driving straight but can rank far away under the motion metric (the camera joints re-aim on the way)
            again = self._plan_once(start, goals, timing, goal_costs, extra_candidates=grown,
                                    connect_k=max(s.connect_k, s.query_repair_connect_k))
            if again.success or "reachable" not in again.reason:
                break
        if again is None:
            return res
        if not again.success and grown:  # a failed repair leaves no trace (nor a used-up budget)
            ids = np.unique(np.concatenate(list(grown.values())))
            self._compact()
            self.graph.remove_nodes(ids)
            self._repair_added -= added
            self._repair_failed += 1
            self._index = None
            added = 0
        if again.success:
            again.reason = f"ok after a local roadmap repair ({added} nodes)"
        log.debug("query repair: %d nodes grown, %s", added, again.reason)
        return again

    def _plan_once(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
                   goal_costs: Optional[np.ndarray] = None, extra_candidates: Optional[dict] = None,
                   connect_k: Optional[int] = None, untracked: bool = False,
                   escapes: Optional[dict] = None) -> PlanResult:
        """One query: connect start and goals to the roadmap and search (no repair).

        ``connect_k`` (default: the setting): nearest roadmap nodes each end tries. ``extra_candidates``: roadmap
        node ids tried in addition, per end (key 0: the start, 1 + k: goal k). ``untracked``: a connection edge whose
        re-aimed knots collide is kept with its untracked knots when those are free
        (:meth:`_untracked_query_edges`). ``escapes``: per end (same keys), the :class:`EscapeResult` of the escape
        search, whose configurations and checked edges are added as query nodes and edges.

        ``goal_costs`` (G,), optional: a non-negative terminal cost added to the path cost (Eq. 2 units) of reaching
        each goal, so one search picks the goal minimising path cost + terminal cost (the replanner's goal hysteresis).
        The goals are joined to one virtual sink node by zero-length edges weighted c_min (Eq. 4) + terminal cost;
        the common c_min offset leaves the choice unchanged and keeps the hop heuristic informative. The returned
        ``cost`` is the path cost alone.
        """
        t0 = time.perf_counter()
        if self.graph is None:
            return PlanResult(False, "roadmap not built")
        start = np.asarray(start, float).reshape(-1)
        goals = np.asarray(goals, float).reshape(-1, self.robot.dof)
        # the query's small arrays stay numpy (rounded to the planner's dtype as torch would); only the batched
        # work (metric, collision, scores) goes through the tensor paths
        Q = np.vstack([start, goals]).astype(_NP_DTYPE[self.dtype])
        if not np.isfinite(Q).all():
            return PlanResult(False, "start or goal contains NaN/inf")
        qs = torch.from_numpy(Q).to(self.device)
        if self.device.type == "cpu" and fastpath.enabled() and len(Q) <= fastpath.MAX_BATCH:
            f = fastpath.check(self.checker, Q, detailed=True)  # CollisionChecker.check_detailed, compiled
            det = {"limits": f[:, 0], "environment": f[:, 1], "self": f[:, 2]}
        else:
            det = {k: v.cpu().numpy() for k, v in self.checker.check_detailed(qs).items()}
        bad = det["limits"] | det["environment"] | det["self"]
        if bad[0]:
            why = ", ".join(k for k in ("limits", "environment", "self") if det[k][0])
            return PlanResult(False, f"start configuration invalid ({why})")
        if bad[1:].all():
            return PlanResult(False, "every goal configuration is in collision or outside the limits")
        g = self.graph
        added_nodes, added_edges = [], []
        try:
            self._query_args = {}
            ids = g.add_nodes(Q.astype(np.float64))
            added_nodes = list(ids)
            s_id, goal_ids = int(ids[0]), [int(i) for i, b in zip(ids[1:], bad[1:].tolist()) if not b]
            rm_ids = self.roadmap_node_ids()
            rm, rm_np = self._roadmap_tensor(rm_ids), self._rm_numpy
            # candidate edges of the start and every goal, plus start-goal, checked in one batch
            queries = [(0, s_id)] + [(1 + k, int(gid)) for k, gid in enumerate(ids[1:]) if int(gid) in goal_ids]
            qq = Q[[i for i, _ in queries]]
            # candidates: the connect_k nearest roadmap nodes under the motion metric itself (one batched evaluation;
            # the Euclidean embedding used for the roadmap's own neighbours can rank arm-heavy motions poorly)
            kk = min(connect_k or self.settings.connect_k, rm.shape[0])
            cand = self._nearest_ids(torch.from_numpy(qq).to(self.device), rm, kk).cpu().numpy()  # (Q, kk)
            src = np.repeat(np.arange(len(queries)), kk)
            dst = cand.reshape(-1)
            qend = np.asarray([q for _, q in queries], dtype=np.int64)
            # direct start -> goal motions last
            qa = np.concatenate([qq[src], np.repeat(Q[:1], len(goal_ids), 0)])
            qb = np.concatenate([rm_np[dst], g.configs[goal_ids].astype(Q.dtype).reshape(-1, Q.shape[1])])
            u_ids = np.concatenate([qend[src], np.full(len(goal_ids), s_id, dtype=np.int64)])
            v_ids = np.concatenate([rm_ids[dst], np.asarray(goal_ids, dtype=np.int64)])
            dist = self._motion_distance(qa, qb)
            within = dist <= 2 * self.settings.max_edge_length
            # a start or goal far from the manifold (e.g. the arm folded away) has no roadmap node within 2 delta:
            # it still gets its QUERY_FALLBACK_K nearest candidates (longer edges, checked like any other)
            cand_d = dist[: len(src)].reshape(len(queries), kk)
            lonely = ~within[: len(src)].reshape(len(queries), kk).any(1)
            if extra_candidates is not None:
                # a repaired query: the end sits where the roadmap is sparse (an aisle); a longer connection to one of
                # its connect_k nearest nodes is a candidate like any other (checked and scored the same way)
                within[:] = True
            elif lonely.any():
                nk = min(QUERY_FALLBACK_K, kk)
                pick = np.argsort(cand_d[lonely], axis=1, kind="stable")[:, :nk] + np.nonzero(lonely)[0][:, None] * kk
                within[pick.reshape(-1)] = True
            if extra_candidates:
                pos = {int(nid): i for i, nid in enumerate(rm_ids)}
                taken = set(zip(u_ids[: len(src)].tolist(), v_ids[: len(src)].tolist()))
                ex_q, ex_r = [], []
                for qi, (k, qid) in enumerate(queries):
                    for nid in np.asarray(extra_candidates.get(k, ()), dtype=np.int64).tolist():
                        if nid in pos and (qid, nid) not in taken:
                            ex_q.append(qi)
                            ex_r.append(pos[nid])
                            taken.add((qid, nid))
                if ex_q:
                    qa, qb = np.concatenate([qa, qq[ex_q]]), np.concatenate([qb, rm_np[ex_r]])
                    u_ids = np.concatenate([u_ids, qend[ex_q]])
                    v_ids = np.concatenate([v_ids, rm_ids[np.asarray(ex_r)]])
                    within = np.concatenate([within, np.ones(len(ex_q), dtype=bool)])
            near = np.nonzero(within)[0]
            ta, tb = torch.from_numpy(qa[near]).to(self.device), torch.from_numpy(qb[near]).to(self.device)
            if len(near) and self.settings.lazy_collision:
                # Lazy PRM for the query edges too: endpoint estimate of Eq. 1 now, the dense collision check and the
                # interior scores only for the edges the search wants to use (usually one at each end)
                scores = self._node_score_slots()
                scores[ids] = self._query_scores(Q)
                ua, vb = u_ids[near], v_ids[near]
                scale = getattr(self, "score_scale", 1.0)
                pe = edge_perception(np.clip(scores[ua] * scale, 0, 1), np.clip(scores[vb] * scale, 0, 1))
                eids = self._add_query_edges(ua, vb, pe.astype(Q.dtype), verified=False,
                                             dist=dist[near] if len(dist) == len(qa) else self._motion_distance(
                                                 qa[near], qb[near]))  # extras: unknown
                added_edges.extend(eids)
                # the knots (re-aimed interior knots) of a candidate edge are computed when the search first
                # verifies it (usually one or two at each end): stored_knots() takes them from here
                self._pending_query_knots = (np.asarray(eids, dtype=np.int64), ua, ta, tb)
                self._pending_rows = {int(e): i for i, e in enumerate(eids)}
                pa, pb = qa[near], qb[near]
                self._pending_np = ((pa, pb), ua, pa.astype(np.float64), pb.astype(np.float64))
            elif len(near):
                ok, pe, kn, ki = self._query_edges(ta, tb, untracked=untracked)
                okn = ok.cpu().numpy()
                if okn.any():
                    keep = near[okn]
                    ua = u_ids[keep]
                    eids = self._add_query_edges(ua, v_ids[keep], pe[ok].cpu().numpy(),
                                                 dist=self._motion_distance(qa[keep], qb[keep]))
                    self._put_knots(np.asarray(eids), ua, kn[ok], ki[ok])
                    added_edges.extend(eids)
            if escapes:
                added_edges.extend(self._add_escapes(escapes, dict(queries), added_nodes))
            search_goals, sink_w = goal_ids, None
            if goal_costs is not None and len(goal_ids) > 1:
                tc = np.asarray(goal_costs, float).reshape(-1)
                if tc.shape != (len(goals),) or not (np.isfinite(tc).all() and (tc >= 0).all()):
                    raise InputError(f"goal_costs must be {len(goals)} finite non-negative values")
                sink = int(g.add_nodes(g.configs[goal_ids[0]][None])[0])
                added_nodes.append(sink)
                k_of = {int(n): k for k, n in enumerate(ids[1:])}
                c_min = min_edge_cost(g)
                sink_w = {gid: c_min + tc[k_of[gid]] for gid in goal_ids}
                se = g.add_edges(np.asarray(goal_ids), np.full(len(goal_ids), sink), np.asarray(list(sink_w.values())),
                                 c_m=0.0, c_p=np.nan, verified=1.0, checked=1.0)  # nothing to verify: no motion
                added_edges.extend(int(e) for e in se)
                search_goals = [sink]
            self._untracked_fallback = bool(untracked)
            if not goal_ids:
                res = None
            else:
                heur = self.heuristic_name
                if heur == "distance":
                    heur = self._distance_heuristic(goal_ids, search_goals[0] if sink_w is not None else None)
                if self.settings.lazy_edges or self.settings.lazy_collision or self._unverified:
                    hops = self._query_hops(search_goals, added_edges) if isinstance(heur, str) and heur == "hop" \
                        else None
                    res = lazy_astar(g, s_id, search_goals, self._verify_edges, heuristic=heur, apply_to_graph=True,
                                     hops=hops)
                else:
                    res = astar(g, s_id, search_goals, heuristic=heur)
            if res is None or not res.success:
                return PlanResult(False, "goal not reachable on the roadmap" if res is None else res.reason,
                                  query_ms=(time.perf_counter() - t0) * 1e3)
            path, cost, goal = res.path, res.cost, res.goal
            if sink_w is not None:  # drop the virtual sink and its terminal edge
                path, goal = path[:-1], path[-2]
                cost -= sink_w[goal]
            if self.settings.shortcut and len(path) > 2:
                path, cost = self._shortcut_path(path, cost, added_edges)
            result = self._finish(path, cost, timing)
            result.goal_index = int(np.nonzero(np.asarray(ids[1:]) == goal)[0][0])
            result.query_ms = (time.perf_counter() - t0) * 1e3
            return result
        finally:
            self._pending_query_knots = None
            self._pending_rows, self._pending_np = {}, None
            self._untracked_fallback = False
            self._query_args = None
            # retire the query's nodes and edges: blocking the edges (weight inf) is a weight change, which keeps
            # the adjacency lists and the hop-distance caches; removal (a full rebuild) is batched in _compact
            if added_edges:
                g.set_weights(np.asarray(added_edges), np.inf)
            self._dead_edges.extend(int(e) for e in added_edges)
            self._dead_nodes.extend(int(n) for n in added_nodes)
            if len(self._dead_nodes) >= 2 * COMPACT_EVERY:
                self._compact()

    def _shortcut_path(self, path: list, cost: float, added_edges: list) -> tuple:
        """Perception-preserving shortcuts of a found path (``shortcut_rounds`` greedy passes): from each kept node,
        the farthest later node (of the :data:`SHORTCUT_CANDIDATES` farthest within twice the roadmap's longest edge)
        joined by one direct local motion that is shorter than the stretch it replaces, is
        collision-free (checked densely, like every edge), keeps every interior knot on the visibility manifold
        (|h_M| within the projection tolerance after re-aiming) and whose Eq. 1 perception is at least the
        motion-weighted mean Eq. 1 perception of the replaced edges. Every candidate of a node is checked in one
        batch. The shortcut edges join the query's edges (``added_edges``) with their knots stored, so the path that
        runs is the one checked. Returns the new path and its cost."""
        g = self.graph
        tol = float(self.settings.projection.tolerance)
        for _ in range(max(1, self.settings.shortcut_rounds)):
            eids = g.edge_ids_of_path(path)
            cm = g.edge_attribute("c_m")[eids] * self.max_motion  # motion cost of each edge
            cp = g.edge_attribute("c_p")[eids]
            arc = np.concatenate([[0.0], np.cumsum(cm)])
            seen = np.concatenate([[0.0], np.cumsum(cm * np.nan_to_num(cp))])
            out, i, changed = [path[0]], 0, False
            while i < len(path) - 1:
                later = np.arange(i + 2, len(path))
                j = i + 1
                if len(later):
                    qa = np.repeat(g.configs[path[i]][None], len(later), 0)
                    qb = g.configs[np.asarray(path)[later]]
                    d = self._motion_distance(qa, qb)
                    span = arc[later] - arc[i]
                    need = (seen[later] - seen[i]) / np.maximum(span, 1e-12)  # mean Eq. 1 of the replaced edges
                    # an existing edge between the two was the search's to take (and must not be overwritten)
                    joined = np.asarray([g.edge_id(path[i], path[x]) is not None for x in later])
                    # at most SHORTCUT_CANDIDATES of the farthest, within twice the roadmap's edge length
                    cand = np.nonzero((d < span - 1e-9) & ~joined & (d <= 2 * self.max_motion))[0]
                    cand = cand[-SHORTCUT_CANDIDATES:]
                    if len(cand):
                        ta, tb = self._t(qa[cand]), self._t(qb[cand])
                        kn, ki = self.edge_knots(ta, tb)
                        M = kn.shape[1]
                        on = self.constraint.error(kn[:, 1:-1].reshape(-1, kn.shape[-1])).reshape(len(cand), M - 2)
                        ok = (on <= tol).all(-1) if M > 2 else torch.ones(len(cand), dtype=torch.bool)
                        ok &= self._knots_valid(kn, dense=True)
                        p = torch.zeros(len(cand), dtype=self.dtype, device=self.device)
                        if ok.any():
                            p[ok] = self._knots_perception(kn[ok], ki[ok])
                        good = ok.cpu().numpy() & (p.double().cpu().numpy() >= need[cand] - 1e-9)
                        if good.any():
                            m = int(np.nonzero(good)[0].max())
                            jj = int(later[cand[m]])
                            e = self._add_query_edges(np.asarray([path[i]]), np.asarray([path[jj]]),
                                                      p[m:m + 1].cpu().numpy(), d[cand[m]:cand[m] + 1])
                            self._put_knots(np.asarray(e), np.asarray([path[i]]), kn[m:m + 1], ki[m:m + 1])
                            added_edges.extend(e)
                            out.append(path[jj])
                            i, changed = jj, True
                            continue
                out.append(path[j])
                i = j
            path = out
            if not changed:
                break
        eids = g.edge_ids_of_path(path)
        return path, float(g.weights[eids].sum())

    def _compact(self) -> None:
        """Remove the retired query nodes and edges from the graph (one adjacency rebuild for many queries)."""
        if self._dead_edges:
            self.graph.remove_edges(np.asarray(self._dead_edges))
        if self._dead_nodes:
            self.graph.remove_nodes(np.asarray(self._dead_nodes))
        self._dead_edges, self._dead_nodes = [], []

    def _verify_edges(self, edge_ids: np.ndarray, path) -> "EdgeCheck":
        """Lazy evaluation of the edges a search wants to use: dense collision check (Lazy PRM) and the Eq. 1
        interior scores; colliding edges are invalidated, scored ones get their Eq. 2 weight."""
        g = self.graph
        ver, chk = g.edge_attribute("verified"), g.edge_attribute("checked")
        todo = np.asarray([e for e in edge_ids if ver[e] < 0.5 or chk[e] < 0.5], dtype=np.int64)
        if len(todo) == 0:
            return EdgeCheck()
        fused = self._verify_compiled(todo)
        if fused is not None:
            return fused
        knots, interior = self.stored_knots(todo)
        ok = torch.ones(len(todo), dtype=torch.bool, device=self.device)
        need = torch.as_tensor(chk[todo] < 0.5, device=self.device)
        if need.any():  # interior knots and the dense pieces between them (obstacles may have moved since build)
            ok[need] = self._knots_valid(knots[need], dense=True)
        if self._untracked_fallback and not bool(ok.all()):
            ok |= self._untracked_query_edges(todo, ok)
        return self._record_verification(todo, ok.cpu().numpy(),
                                         lambda m: self._stored_perception(todo[m]).double().cpu().numpy())

    def _record_verification(self, todo: np.ndarray, ok: np.ndarray, perception: Callable) -> EdgeCheck:
        """Write a verification of edges ``todo`` into the roadmap: all are checked now, the colliding ones (``ok``
        (E,) false) are removed, and those still to be scored get their Eq. 1 perception ``perception(mask)`` (of
        ``todo[mask]``) and Eq. 2 weight, which the search is told."""
        g = self.graph
        ver = g.edge_attribute("verified")
        g.edge_attribute("checked")[todo] = 1.0
        invalid = todo[~ok]
        if len(invalid):
            g.remove_edges(invalid)
            rc = invalid[invalid < len(self._recheck)]
            self._blocked_edges.update(rc[self._recheck[rc]].tolist())
        weights = {}
        score = (ver[todo] < 0.5) & ok
        if score.any():
            sel = todo[score]
            p = perception(score)
            g.edge_attribute("c_p")[sel] = p
            ver[sel] = 1.0
            w = self._weight(p, g.edge_attribute("c_m")[sel])
            weights = {int(e): float(x) for e, x in zip(sel, w)}
        return EdgeCheck(invalid=[int(e) for e in invalid], weights=weights)

    def _verify_compiled(self, todo: np.ndarray) -> Optional[EdgeCheck]:
        """:meth:`_verify_edges` of a search's few edges in one compiled call: the knots of the query's connection
        edges not computed yet, then the dense collision check, Eq. 1 camera poses and surrogate scores with occlusion
        (:func:`~psprm_core.fastpath.verify_edges`), with the same results; None when it does not apply (another
        scorer, a GPU, a large batch, the untracked fallback)."""
        g = self.graph
        store = self.knots
        if (self._untracked_fallback or len(todo) > SMALL_BATCH or self.device.type != "cpu" or store.data is None
                or store.data.shape[1] <= 2 or not fastpath.applies(store.data[:1])):
            return None
        args = self._neural_args(self.dtype)
        if args is None:
            return None
        ver, chk = g.edge_attribute("verified"), g.edge_attribute("checked")
        compute = ~store.known(todo)
        rows = np.zeros(0, dtype=np.int64)
        if compute.any():
            pend = self._pending_rows
            rows = np.asarray([pend.get(int(e), -1) for e in todo[compute]], dtype=np.int64)
            if (rows < 0).any():  # not a connection edge of this query: computed the step-by-step way first
                self.stored_knots(todo[compute][rows < 0])
                compute = ~store.known(todo)
                rows = np.asarray([pend[int(e)] for e in todo[compute]], dtype=np.int64)
            hit = self._cached_query_knots(todo[compute], rows)
            if hit.any():
                compute = ~store.known(todo)
                rows = rows[~hit]
        store.reserve(int(todo.max()) + 1)
        _, ua, qa, qb = self._pending_np if len(rows) else (None, rows, np.zeros((0, self.robot.dof)),
                                                            np.zeros((0, self.robot.dof)))
        cid = todo[compute]
        flip = g.edge_u[cid] != ua[rows]
        do_check, do_score = chk[todo] < 0.5, ver[todo] < 0.5
        ok, cams, raw = fastpath.verify_edges(
            self.motion, self.constraint, self.checker, args, store.data.numpy(), store.interior.numpy(), todo,
            compute, np.ascontiguousarray(qa[rows]), np.ascontiguousarray(qb[rows]), flip, self.settings.n_interp,
            True, self.settings.projection, self._lo, self._hi, self.track_cols, self.settings.track_iters, do_check,
            do_score, self.settings.edge_resolution, 200)
        if len(cid):
            store.written(cid)
            self._cache_query_knots(cid, rows, flip)

        def perception(mask: np.ndarray) -> np.ndarray:  # Eq. 1 from the kernel's raw scores; camera poses kept
            self.knots.put_cams(todo[mask], cams[mask])
            # _normalized in the planner's dtype (numpy rounds like torch: a float32 array times a Python float stays
            # float32), Eq. 1 in numpy (its sum may round differently from torch's in the last bit)
            sc = raw[mask].astype(_NP_DTYPE[self.dtype], copy=False) * getattr(self, "score_scale", 1.0)
            sc = np.clip(sc, 0.0, 1.0)
            return edge_perception(sc[:, 0], sc[:, -1], sc[:, 1:-1]).astype(np.float64)

        return self._record_verification(todo, ok, perception)

    def _cached_query_knots(self, eids: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Store the knots of the query's connection edges ``eids`` (rows ``rows`` of the pending ends) found in the
        query-knot cache (:meth:`_query_knots`); returns the (E,) hit flags."""
        cache = self.knots.query
        keys = self._pending_keys(rows)
        hit = np.asarray([k in cache for k in keys], dtype=bool)
        if hit.any():
            _, ua, _, _ = self._pending_np
            kn = torch.stack([cache[k][0] for k, h in zip(keys, hit) if h])
            ki = torch.stack([cache[k][1] for k, h in zip(keys, hit) if h])
            self._put_knots(eids[hit], ua[rows[hit]], kn, ki)
        return hit

    def _cache_query_knots(self, eids: np.ndarray, rows: np.ndarray, flip: np.ndarray) -> None:
        """Keep the knots just computed for connection edges in the query-knot cache (in their ends' direction)."""
        cache = self.knots.query
        M = self.knots.data.shape[1]
        kn, ki = self.knots.data.numpy()[eids], self.knots.interior.numpy()[eids]  # copies (CPU store)
        if flip.any():
            kn[flip], ki[flip] = kn[flip, ::-1], (M - 1 - ki[flip])[:, ::-1]
        kn, ki = torch.from_numpy(kn), torch.from_numpy(ki)
        for j, key in enumerate(self._pending_keys(rows)):
            cache[key] = (kn[j], ki[j])
        self.knots.trim_query_cache()

    def _pending_keys(self, rows: np.ndarray) -> list:
        """Query-knot cache keys (:meth:`_query_knots`) of pending connection edges (rows of the pending ends)."""
        (qa, qb), _, _, _ = self._pending_np  # in the planner's dtype, as _query_knots keys them
        return [qa[i].tobytes() + qb[i].tobytes() for i in rows]

    def _untracked_query_edges(self, edge_ids: np.ndarray, ok: torch.Tensor) -> torch.Tensor:
        """Fallback of a repaired query: its connection edges (an end is a start/goal node) whose re-aimed knots
        collide get their untracked knots (camera joints interpolated plainly, :meth:`edge_knots` with
        ``track=False``), which replace the stored ones when they are collision-free (densely checked like every
        edge). Returns (E,) bool: the edges rescued this way (their Eq. 1 score is then recomputed from those knots).
        """
        g = self.graph
        out = torch.zeros(len(edge_ids), dtype=torch.bool, device=self.device)
        mask = self.roadmap_mask()
        ids = np.asarray(edge_ids, dtype=np.int64)
        query = ~(mask[g.edge_u[ids]] & mask[g.edge_v[ids]])
        cand = np.nonzero(~ok.cpu().numpy() & query)[0]
        if len(cand) == 0:
            return out
        e = ids[cand]
        knots, interior = self.edge_knots(self._t(g.configs[g.edge_u[e]]), self._t(g.configs[g.edge_v[e]]), track=False)
        free = self._knots_valid(knots, dense=True)
        if free.any():
            fi = free.cpu().numpy()
            self.knots.put(e[fi], knots[free], interior[free])  # stored u -> v direction; camera poses reset
            g.edge_attribute("verified")[e[fi]] = 0.0  # score the new knots (Eq. 1) below
            out[torch.as_tensor(cand[fi], device=self.device)] = True
        return out

    @property
    def n_roadmap_nodes(self) -> int:
        """Number of roadmap node slots (valid or pruned; start/goal query nodes excluded)."""
        return int(self._roadmap_mask.sum())

    def roadmap_mask(self) -> np.ndarray:
        """(n_node_slots,) bool: slot holds a roadmap node (valid or not), not a start/goal query node."""
        g = self.graph
        m = np.zeros(g.n_nodes, dtype=bool)
        m[: len(self._roadmap_mask)] = self._roadmap_mask
        return m

    def roadmap_node_ids(self) -> np.ndarray:
        """Ids of the valid roadmap nodes."""
        g = self.graph
        return np.nonzero(self.roadmap_mask() & g.node_valid[: g.n_nodes])[0]

    def roadmap_edge_ids(self) -> np.ndarray:
        """Ids of the valid edges between roadmap nodes (start/goal query edges excluded)."""
        g = self.graph
        e = g.valid_edge_ids()
        m = self.roadmap_mask()
        return e[m[g.edge_u[e]] & m[g.edge_v[e]]]

    def _roadmap_tensor(self, ids: np.ndarray) -> torch.Tensor:
        """Roadmap node configurations as a tensor on the planner's device (cached until the node set changes or a
        new roadmap is built or loaded)."""
        key = hash(ids.tobytes())
        if getattr(self, "_rm_cache_key", None) != key:
            self._rm_numpy = self.graph.configs[ids].astype(_NP_DTYPE[self.dtype])  # the same values, host copy
            self._rm_cache = torch.from_numpy(self._rm_numpy).to(self.device)
            self._rm_f64 = None  # float64 of the same values, made when first needed (_nearest_ids)
            self._rm_cache_key = key
        return self._rm_cache

    def _add_query_edges(self, ua: np.ndarray, vb: np.ndarray, p: np.ndarray, dist: np.ndarray,
                         verified: bool = True) -> list:
        """Add query edges ``ua`` -> ``vb`` with their Eq. 1 perception ``p`` (E,) and motion cost ``dist`` (E,), both
        numpy in the planner's dtype: validated and fully scored (``verified``), or unchecked with an endpoint
        estimate (verified lazily by the search). The Eq. 2 weight is computed in that dtype, as on the roadmap."""
        c_m = dist / np.asarray(self.max_motion, dist.dtype)
        if self.settings.objective == "eq2":  # Eq. 2 keeps c_m in [0, 1]; the motion form's heuristic needs it whole
            c_m = np.clip(c_m, 0, 1)
        w = self._weight(p, c_m)
        return list(self.graph.add_edges(np.asarray(ua), np.asarray(vb), w.astype(np.float64),
                                         c_m=c_m.astype(np.float64), c_p=p.astype(np.float64),
                                         verified=float(verified), checked=float(verified)))

    def _motion_distance(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """:meth:`DiffDriveMotion.distance` of numpy batches (E, dof) in the planner's dtype, same dtype out."""
        if len(qa) == 0:
            return np.zeros(0, dtype=qa.dtype)
        if self.device.type == "cpu" and fastpath.enabled() and len(qa) <= fastpath.MOTION_MAX_BATCH:
            m = self.motion  # the compiled metric of DiffDriveMotion.distance, without the tensor round trip
            d = fastpath.kernels().distance(qa.astype(np.float64), qb.astype(np.float64), float(m.w_rot),
                                            bool(m.mobile))
            return d.astype(qa.dtype)
        d = self.motion.distance(torch.from_numpy(qa).to(self.device), torch.from_numpy(qb).to(self.device))
        return d.cpu().numpy()

    def _query_edges(self, qa: torch.Tensor, qb: torch.Tensor, untracked: bool = False) -> tuple:
        """Validity and Eq. 1 perception of query edges (always scored in full, never lazily); with ``untracked``,
        edges whose re-aimed knots collide are tried with their untracked knots."""
        knots, interior = self._query_knots(qa, qb)
        ok = self._knots_valid(knots)
        if untracked and not bool(ok.all()):
            bad = torch.nonzero(~ok, as_tuple=True)[0]
            kp, ip = self.edge_knots(qa[bad], qb[bad], track=False)
            free = self._knots_valid(kp)
            if free.any():
                knots, interior = knots.clone(), interior.clone()
                knots[bad[free]], interior[bad[free]] = kp[free], ip[free]
                ok[bad[free]] = True
        p = torch.zeros(qa.shape[0], dtype=self.dtype, device=self.device)
        if ok.any():
            p[ok] = self._knots_perception(knots[ok], interior[ok])
        return ok, p, knots, interior

    def _finish(self, path: list, cost: float, timing: bool) -> PlanResult:
        if self.device.type == "cpu" and fastpath.enabled() and self.knots.data is not None:
            return self._finish_numpy(path, cost, timing)
        g = self.graph
        Q = self._t(g.configs[path])
        if len(Q) > 1:  # the knots the edges were checked and scored with, in traversal direction
            eids = g.edge_ids_of_path(path)
            knots, _ = self.stored_knots(eids)
            flip = torch.as_tensor(g.edge_u[eids] != np.asarray(path[:-1]), device=knots.device)
            knots = torch.where(flip[:, None, None], knots.flip(1), knots)
            W = torch.cat([Q[0:1], knots[:, 1:].reshape(-1, Q.shape[1])]).double()
        else:
            W = Q.double()
        keep = torch.ones(len(W), dtype=torch.bool)
        keep[1:] = (W[1:] - W[:-1]).abs().max(-1).values > 1e-7
        W = W[keep]
        dense = self.densify(W)
        length = float(self.motion.distance(W[:-1], W[1:]).sum()) if len(W) > 1 else 0.0
        traj = None
        if timing and len(W) > 1:
            traj = self._timed(W.numpy())
        return PlanResult(True, "ok", path_nodes=list(path), waypoints=W.numpy(), dense=dense.numpy(),
                          trajectory=traj, cost=float(cost), path_length=length, score_fn=self._score_numpy)

    def _finish_numpy(self, path: list, cost: float, timing: bool) -> PlanResult:
        """:meth:`_finish` on the CPU with numpy and the compiled metric (a query's result: no torch calls)."""
        g = self.graph
        Q = g.configs[path].astype(np.float32 if self.dtype == torch.float32 else np.float64)
        if len(Q) > 1:  # the knots the edges were checked and scored with, in traversal direction
            eids = g.edge_ids_of_path(path)
            if not self.knots.known(eids).all():
                self.stored_knots(eids)
            knots = self.knots.data.numpy()[eids]
            flip = g.edge_u[eids] != np.asarray(path[:-1])
            knots[flip] = knots[flip, ::-1]
            W = np.concatenate([Q[:1], knots[:, 1:].reshape(-1, Q.shape[1])]).astype(np.float64)
        else:
            W = Q.astype(np.float64)
        keep = np.ones(len(W), dtype=bool)
        keep[1:] = np.abs(W[1:] - W[:-1]).max(-1) > 1e-7
        W = np.ascontiguousarray(W[keep])
        m, K = self.motion, fastpath.kernels()
        if len(W) > 1:
            _, pts = K.pieces(W[:-1], W[1:], float(self.settings.edge_resolution), 1000, True, float(m.w_rot),
                              bool(m.mobile))
            dense = np.concatenate([pts, W[-1:]])
            length = float(K.distance(W[:-1], W[1:], float(m.w_rot), bool(m.mobile)).sum())
        else:
            dense, length = W, 0.0
        traj = self._timed(W) if timing and len(W) > 1 else None
        return PlanResult(True, "ok", path_nodes=list(path), waypoints=W, dense=dense, trajectory=traj,
                          cost=float(cost), path_length=length, score_fn=self._score_numpy)

    def _timed(self, W: np.ndarray):
        """Time-parameterised trajectory through the knots ``W`` (K, dof) within the joint limits
        (:func:`~psprm_core.planning.timing.time_parameterize`). With ``smooth_timing`` on a mobile robot the knots of
        each base phase are passed without stopping; those samples leave the checked straight pieces, so they are
        collision-checked, and a smooth trajectory with any colliding sample is replaced by the stop-at-every-knot one
        (which follows the checked pieces exactly)."""
        from .timing import time_parameterize

        r = self.robot
        kw = dict(dt=0.05, joint_names=r.joint_names, continuous_joints=[i for i in range(r.dof) if r.continuous[i]],
                  base_indices=(0, 1, 2) if r.mobile else None,
                  base_linear_limits=(r.config.base.linear_velocity, r.config.base.linear_acceleration)
                  if r.mobile else None, method="analytic")
        if not (self.settings.smooth_timing and r.mobile and len(W) > 2):
            return time_parameterize(W, r.velocity, r.acceleration, **kw)
        traj = time_parameterize(W, r.velocity, r.acceleration, smooth=True, **kw)
        curved = traj.off_segment_mask()  # samples off the checked straight pieces
        if curved.any() and bool(self.checker.check(self._t(traj.positions[curved])).any()):
            log.debug("smooth trajectory grazes an obstacle between knots: stopping at every knot instead")
            return time_parameterize(W, r.velocity, r.acceleration, **kw)
        return traj

    def _score_numpy(self, q: np.ndarray) -> np.ndarray:
        """Perception scores of configurations given as numpy (the lazy report of :class:`PlanResult`)."""
        return self.score_configs(self._t(q)).double().cpu().numpy()

    def densify(self, W: torch.Tensor) -> torch.Tensor:
        """Configurations every ``edge_resolution`` along the piecewise-linear knot path ``W`` (K, dof)."""
        if len(W) < 2:
            return W
        _, pts = self._pieces(W[:-1], W[1:], max_steps=1000, include_start=True)
        return torch.cat([pts, W[-1:]])

    def _pieces(self, a: torch.Tensor, b: torch.Tensor, max_steps: int, include_start: bool) -> tuple:
        """Points every ``edge_resolution`` on the straight pieces a[i] -> b[i] (theta interpolated the short way).

        Each piece is split into n = ceil(length / resolution) steps (at most ``max_steps``); the points are at
        fractions k / n for k = 0 .. n-1 (``include_start``) or k = 1 .. n-1. Returns (piece index, points).
        """
        if fastpath.motion_applies(a, b):  # CPU: one compiled pass (same lengths, same points)
            return fastpath.pieces(self.motion, a, b, self.settings.edge_resolution, max_steps, include_start)
        diff = b - a
        if self.robot.mobile:
            diff[:, 2] = torch.remainder(diff[:, 2] + np.pi, 2 * np.pi) - np.pi
        n = torch.ceil(self.motion.distance(a, b) / self.settings.edge_resolution).long().clamp(1, max_steps)
        count = n if include_start else n - 1
        seg = torch.repeat_interleave(torch.arange(len(a), device=a.device), count)
        k = torch.arange(len(seg), device=a.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
        frac = ((k + (0 if include_start else 1)).to(a.dtype) / n[seg].to(a.dtype)).unsqueeze(-1)
        return seg, a[seg] + diff[seg] * frac

    # ---- dynamic scenes (used by the replanner) ----------------------------------------------------------------------
    def set_scene(self, scene: Scene) -> None:
        """Adopt moved targets/obstacles: the scorer's occluders and the collision checker's boxes follow ``scene``.

        Nothing is re-scored or re-checked here; see :meth:`rescore` and :meth:`invalidate_near`."""
        self.scene = scene
        self.scorer.set_scene(scene)
        self.checker.set_boxes(scene.collision_boxes())

    def set_focus(self, focus) -> None:
        """Move the point the visibility constraint aims at. Edges re-aim their camera joints at it, so every edge's
        knots are recomputed, re-checked and re-scored lazily when a search next uses it."""
        self.constraint.set_target(np.asarray(focus, float))
        self.knots.clear()
        g = self.graph
        if g is not None:
            e = g.valid_edge_ids()
            g.edge_attribute("checked")[e] = 0.0
            g.edge_attribute("verified")[e] = 0.0
            self._unverified = True

    def _node_score_slots(self) -> np.ndarray:
        g = self.graph
        if len(self.node_scores) < g.n_nodes:
            self.node_scores = np.concatenate([self.node_scores, np.full(g.n_nodes - len(self.node_scores), np.nan)])
        return self.node_scores

    @_large_batches
    def rescore(self, full: bool = False, tol: float = 1e-4) -> dict:
        """Re-score the roadmap after the target or an occluder moved.

        Every valid roadmap node is scored in one batch (FK -> scorer). ``full=False`` (lazy): the edges at a node
        whose score changed by more than ``tol`` get the Eq. 1 estimate from their two ends only and are marked
        unverified; a search then scores the N interior configurations (Eq. 1) only for the edges on its candidate
        paths (:meth:`_verify_edges` via :func:`lazy_astar`). ``full=True`` scores the interiors of every edge now
        (what a planner without lazy evaluation pays on every replan).
        Returns counts and timings.
        """
        t0 = time.perf_counter()
        g = self.graph
        ids = self.roadmap_node_ids()
        scores = self._node_score_slots()
        key = hash(ids.tobytes())
        if getattr(self, "_node_cams_key", None) != key:  # node camera poses only change with the node set
            Q = self._roadmap_tensor(ids)
            self._node_cams = torch.cat([self.robot.camera_poses(Q[i:i + 65536]) for i in range(0, len(Q), 65536)])
            self._node_cams_key = key
        new = self.scorer.score(self._node_cams).double().cpu().numpy()
        changed = np.abs(new - scores[ids]) > tol
        scores[ids] = new
        e = self.roadmap_edge_ids()
        if not full:
            flag = np.zeros(g.n_nodes, dtype=bool)
            flag[ids[changed]] = True
            e = e[flag[g.edge_u[e]] | flag[g.edge_v[e]]]
        t_nodes = time.perf_counter() - t0
        if len(e):
            c_p, ver = g.edge_attribute("c_p"), g.edge_attribute("verified")
            if full:
                p = np.empty(len(e))
                for s0 in range(0, len(e), 4096):
                    p[s0:s0 + 4096] = self._stored_perception(e[s0:s0 + 4096]).double().cpu().numpy()
                ver[e] = 1.0
            else:
                scale = getattr(self, "score_scale", 1.0)
                p = edge_perception(np.clip(scores[g.edge_u[e]] * scale, 0, 1), np.clip(scores[g.edge_v[e]] * scale, 0, 1))
                ver[e] = 0.0
                self._unverified = True
            c_p[e] = p
            g.set_weights(e, self._weight(p, g.edge_attribute("c_m")[e]))
        return {"nodes": int(len(ids)), "changed_nodes": int(changed.sum()), "edges": int(len(e)),
                "nodes_ms": t_nodes * 1e3, "total_ms": (time.perf_counter() - t0) * 1e3}

    def _spatial_index(self):
        """KD-trees over the roadmap's base positions (nodes) and edge midpoints, plus the robot's reach radius
        (largest xy distance of a collision sphere from the base over the roadmap's nodes) and the longest edge's
        half length. Built on first use and after :meth:`grow`; removals keep it valid (stale ids are filtered)."""
        if self._index is None:
            from scipy.spatial import cKDTree

            g = self.graph
            ids, e = self.roadmap_node_ids(), self.roadmap_edge_ids()
            Q = self._roadmap_tensor(ids)
            reach = 0.0
            if self.robot.mobile and len(ids):
                r = torch.as_tensor(self.robot.spheres.radii, dtype=self.dtype, device=self.device)
                for s0 in range(0, len(Q), 4096):
                    c = self.robot.sphere_centers(Q[s0:s0 + 4096])
                    d = (c[..., :2] - Q[s0:s0 + 4096, None, :2]).norm(dim=-1) + r
                    reach = max(reach, float(d.max()))
            xy = g.configs[:, :2] if self.robot.mobile else np.zeros((g.n_nodes, 2))
            a, b = xy[g.edge_u[e]], xy[g.edge_v[e]]
            half = 0.5 * np.linalg.norm(b - a, axis=1)
            self._index = {"node_ids": ids, "node_tree": cKDTree(xy[ids]), "edge_ids": e,
                           "edge_tree": cKDTree(0.5 * (a + b)) if len(e) else None,
                           "max_half": float(half.max()) if len(e) else 0.0, "reach": reach}
        return self._index

    def _near(self, boxes: Sequence, margin: float = 0.05) -> tuple:
        """Roadmap node ids and edge ids within the robot's reach of ``boxes`` (spatial index; everything for a
        fixed-base robot)."""
        g = self.graph
        if not self.robot.mobile:
            return self.roadmap_node_ids(), self.roadmap_edge_ids()
        idx = self._spatial_index()
        nsel, esel = set(), set()
        for b in boxes:
            c = np.asarray(b.center, float)[:2]
            rad = float(np.linalg.norm(np.asarray(b.size, float)[:2]) / 2) + idx["reach"] + margin
            nsel.update(idx["node_tree"].query_ball_point(c, rad))
            if idx["edge_tree"] is not None:
                cand = np.asarray(idx["edge_tree"].query_ball_point(c, rad + idx["max_half"]), dtype=np.int64)
                if len(cand):
                    ee = idx["edge_ids"][cand]
                    pa, pb = g.configs[g.edge_u[ee], :2], g.configs[g.edge_v[ee], :2]
                    d = pb - pa
                    t = np.clip(((c - pa) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0, 1)
                    dist = np.linalg.norm(pa + t[:, None] * d - c, axis=1)
                    esel.update(ee[dist <= rad].tolist())
        nodes = idx["node_ids"][np.asarray(sorted(nsel), dtype=np.int64)] if nsel else np.zeros(0, np.int64)
        return nodes, np.asarray(sorted(esel), dtype=np.int64)

    def _knots_hit(self, edges: np.ndarray, boxes) -> np.ndarray:
        """(E,) bool: some stored interior knot of the edges collides with ``boxes`` (environment check only).

        Knots whose base lies beyond the robot's reach of every box are skipped before any kinematics."""
        knots, _ = self.knots.get(edges)
        E, M, dof = knots.shape
        if M <= 2:
            return np.zeros(E, dtype=bool)
        inner = knots[:, 1:-1].reshape(-1, dof)
        near = torch.ones(len(inner), dtype=torch.bool, device=inner.device)
        if self.robot.mobile:
            box_list = list(boxes) if not hasattr(boxes, "center") else None
            if box_list is not None:
                reach = self._spatial_index()["reach"]
                near = torch.zeros(len(inner), dtype=torch.bool, device=inner.device)
                for b in box_list:
                    r = float(np.linalg.norm(np.asarray(b.size, float)[:2]) / 2) + reach + 0.05
                    c = torch.as_tensor(np.asarray(b.center, float)[:2], dtype=inner.dtype, device=inner.device)
                    near |= (inner[:, :2] - c).norm(dim=-1) <= r
        hit = torch.zeros(len(inner), dtype=torch.bool, device=inner.device)
        # knots checked before: their cached robot bounds must overlap a box's bounds, else no kinematics is needed
        bounds = self.knots.knot_aabb(edges)[:, 1:-1].reshape(-1, 6)
        known = ~torch.isnan(bounds[:, 0])
        bt = boxes if isinstance(boxes, BoxTensors) else BoxTensors.from_boxes(list(boxes), self.device, self.dtype)
        if len(bt):
            bb = bt.aabb().to(bounds.dtype)
            overlap = ((bounds[:, None, :3] <= bb[None, :, 3:]) & (bounds[:, None, 3:] >= bb[None, :, :3])).all(-1)
            near &= ~known | overlap.any(-1)
        else:
            near &= False
        idx = torch.nonzero(near & known, as_tuple=True)[0]
        if len(idx):
            hit[idx] = self.checker.env_hits(inner[idx], bt)
        idx = torch.nonzero(near & ~known, as_tuple=True)[0]
        if len(idx):
            hit[idx], aabb = self.checker.env_hits(inner[idx], bt, return_aabb=True)
            e_pos = (idx // (M - 2)).cpu().numpy()
            self.knots.put_aabb(np.asarray(edges, dtype=np.int64)[e_pos], (idx % (M - 2)).cpu().numpy() + 1, aabb)
        return hit.reshape(E, M - 2).any(-1).cpu().numpy()

    @_large_batches
    def invalidate_near(self, boxes: Sequence, old_boxes: Sequence = (), margin: float = 0.05) -> dict:
        """Obstacle update (after :meth:`set_scene`): re-check only what the moved ``boxes`` (new poses) can touch.

        Roadmap nodes whose base lies within reach of a box are checked against the moved boxes and blocked (removed
        from the graph) when in collision; edges whose base segment passes within reach have their stored knots
        checked in one batch (blocked when in collision) and are marked unchecked, so a search re-checks their dense
        interior before using them (Lazy PRM). Only the moved boxes are tested: everything else about a node or edge
        that was valid before is unchanged. Nodes and edges blocked earlier that lie near ``old_boxes`` (where an
        obstacle left) are restored, unchecked, when free at the current poses, so an obstacle moving through the
        roadmap does not erase it. A fixed-base robot re-checks everything.
        """
        g = self.graph
        restored = self._restore_unblocked(old_boxes, margin) if old_boxes else {"restored_nodes": 0,
                                                                                  "restored_edges": 0}
        nodes, edges = self._near(boxes, margin)
        nodes = nodes[g.node_valid[nodes]]
        removed = np.zeros(0, dtype=np.int64)
        if len(nodes):
            removed = nodes[self.checker.env_hits(self._t(g.configs[nodes]), list(boxes)).cpu().numpy()]
            if len(removed):
                gone = g.remove_nodes(removed)
                self._blocked_nodes.update(removed.tolist())
                self._blocked_edges.update(gone.tolist())
        edges = edges[g.edge_valid[edges]] if len(edges) else edges
        # one batched check of the near edges' stored knots prunes most newly blocked edges at once (a lazy search
        # would otherwise discover them one path at a time); the dense pieces between knots are checked lazily
        pruned = 0
        have = edges[self.knots.known(edges)]
        if len(have):
            bad = self._knots_hit(have, list(boxes))
            if bad.any():
                g.remove_edges(have[bad])
                self._blocked_edges.update(have[bad].tolist())
                pruned = int(bad.sum())
            edges = edges[g.edge_valid[edges]]
        self._mark_recheck(edges)
        return {"checked_nodes": int(len(nodes)), "removed_nodes": int(len(removed)), "pruned_edges": pruned,
                "unchecked_edges": int(len(edges)), **restored}

    def _mark_recheck(self, edges: np.ndarray) -> None:
        """Edges to re-check densely before use because an obstacle moved near them."""
        g = self.graph
        g.edge_attribute("checked")[edges] = 0.0
        if len(self._recheck) < g.n_edges:
            self._recheck = np.concatenate([self._recheck, np.zeros(g.n_edges - len(self._recheck), dtype=bool)])
        self._recheck[edges] = True

    def _restore_unblocked(self, old_boxes: Sequence, margin: float = 0.05) -> dict:
        """Give back the blocked nodes and edges near where obstacles were (``old_boxes``) that are free of every
        current obstacle (edges come back unchecked: their dense interior is re-checked lazily)."""
        g = self.graph
        back_n = back_e = 0
        if not (self._blocked_nodes or self._blocked_edges):
            return {"restored_nodes": 0, "restored_edges": 0}
        near_n, near_e = self._near(old_boxes, margin)
        boxes = self.scene.collision_boxes()  # the poses the checker holds (set_scene)
        nodes = np.asarray(sorted(self._blocked_nodes.intersection(near_n.tolist())), dtype=np.int64)
        if len(nodes):
            free = nodes[~self.checker.env_hits(self._t(g.configs[nodes]), boxes).cpu().numpy()]
            if len(free):
                g.restore_nodes(free)
                self._blocked_nodes.difference_update(free.tolist())
                back_n = len(free)
        e = np.asarray(sorted(self._blocked_edges.intersection(near_e.tolist())), dtype=np.int64)
        if len(e):
            e = e[g.node_valid[g.edge_u[e]] & g.node_valid[g.edge_v[e]] & ~g.edge_valid[e]]
            e = e[self.knots.known(e)]
            if len(e):
                free = e[~self._knots_hit(e, boxes)]
                if len(free):
                    got = g.restore_edges(free)
                    self._blocked_edges.difference_update(got.tolist())
                    self._mark_recheck(got)
                    back_e = len(got)
        return {"restored_nodes": int(back_n), "restored_edges": int(back_e)}

    @_large_batches
    def grow(self, n: int, center: Optional[np.ndarray] = None, radius: float = 1.5,
             rng: Optional[np.random.Generator] = None, timeout_s: float = 2.0,
             heading: Optional[float] = None) -> dict:
        """Roadmap repair: add up to ``n`` collision-free manifold nodes (base within ``radius`` of ``center`` when
        given; with ``heading``, half of them on the line through ``center`` along that base heading and facing it,
        i.e. reachable by driving straight) and connect them to their neighbours among all roadmap nodes, as in
        :meth:`build`. Existing nodes are kept. Returns the number of nodes and edges added."""
        s, g = self.settings, self.graph
        rng = rng or np.random.default_rng()
        t0 = time.perf_counter()
        got = []
        have = 0
        while have < n and time.perf_counter() - t0 < timeout_s:
            q = self._sample(max(4 * n, 256), rng, self.template)
            if center is not None and self.robot.mobile:
                ang = rng.uniform(-np.pi, np.pi, len(q))
                rr = radius * np.sqrt(rng.random(len(q)))
                xy = np.asarray(center, float)[:2] + np.stack([rr * np.cos(ang), rr * np.sin(ang)], 1)
                h = 0
                if heading is not None:  # half on the heading line, facing along it
                    h = len(q) // 2
                    t = rng.uniform(-radius, radius, h)
                    xy[:h] = np.asarray(center, float)[:2] + t[:, None] * np.array([np.cos(heading), np.sin(heading)])
                    q[:h, 2] = heading
                q[:, :2] = self._t(xy)
                if h and len(self.track_cols):  # those keep their base pose: only the camera joints re-aim
                    qa, oka = self.constraint.project(q[:h], s.projection, self._lo, self._hi, joints=self.track_cols)
                    qb, okb = self.constraint.project(q[h:], s.projection, self._lo, self._hi)
                    q, ok = torch.cat([qa, qb]), torch.cat([oka, okb])
                else:
                    q, ok = self.constraint.project(q, s.projection, self._lo, self._hi)
            else:
                q, ok = self.constraint.project(q, s.projection, self._lo, self._hi)
            q = q[ok]
            q = q[self.checker.valid(q)]
            got.append(q)
            have += len(q)
        if have == 0:
            return {"added_nodes": 0, "added_edges": 0, "node_ids": np.zeros(0, dtype=np.int64)}
        Qn = torch.cat(got)[:n]
        old_ids = self.roadmap_node_ids()
        new_ids = g.add_nodes(Qn.double().cpu().numpy())
        mask = self.roadmap_mask()
        mask[new_ids] = True
        self._roadmap_mask = mask
        scores = self._node_score_slots()
        scores[new_ids] = self.score_configs(Qn).double().cpu().numpy()
        all_ids = np.concatenate([old_ids, new_ids])
        Qall = self._t(g.configs[all_ids])
        eu, ev, dist = self._neighbours(Qn, Qall, s.k_neighbors, k_long=s.k_long, rng=rng)
        u_ids, v_ids = new_ids[eu.cpu().numpy()], all_ids[ev.cpu().numpy()]
        keep = u_ids != v_ids
        eu, ev, dist, u_ids, v_ids = eu[keep], ev[keep], dist[keep], u_ids[keep], v_ids[keep]
        pairs = set()
        sel = []
        for i, (a, b) in enumerate(zip(u_ids.tolist(), v_ids.tolist())):  # unique undirected, not already joined
            k = (min(a, b), max(a, b))
            if k not in pairs and g.edge_id(a, b) is None:
                pairs.add(k)
                sel.append(i)
        sel = np.asarray(sel, dtype=np.int64)
        added = 0
        if len(sel):
            qa, qb = Qn[eu[sel]], Qall[ev[sel]]
            valid, p_edge, knots = self._edges_valid(qa, qb)  # old nodes' scores may predate a scene change
            if s.lazy_edges:
                sc = self._t(scores)
                p_edge = edge_perception(self._normalized(sc[u_ids[sel]]), self._normalized(sc[v_ids[sel]]))
            v = valid.cpu().numpy()
            c_m = dist[sel] / self.max_motion
            c_m = (c_m.clamp(0, 1) if s.objective == "eq2" else c_m)[valid]
            p_edge = p_edge[valid]
            eids = g.add_edges(u_ids[sel][v], v_ids[sel][v],
                               self._weight(p_edge, c_m).double().cpu().numpy(),
                               c_m=c_m.double().cpu().numpy(), c_p=p_edge.double().cpu().numpy(),
                               verified=np.full(int(v.sum()), 0.0 if s.lazy_edges else 1.0),
                               checked=np.full(int(v.sum()), 0.0 if s.lazy_collision else 1.0))
            self._put_knots(eids, u_ids[sel][v], *knots)
            added = int(v.sum())
        self._index = None
        return {"added_nodes": int(len(new_ids)), "added_edges": added, "grow_ms": (time.perf_counter() - t0) * 1e3,
                "node_ids": np.asarray(new_ids, dtype=np.int64)}

    # ---- persistence -----------------------------------------------------------------------------------------------
    def fingerprint(self) -> str:
        """Hash of the robot, scene geometry, focus point and settings the roadmap was built for."""
        h = hashlib.sha256(self.robot.hash().encode())
        for b in self.scene.collision_boxes():
            h.update(np.concatenate([b.center, b.size, b.quat]).astype(np.float64).tobytes())
        h.update(self.constraint.target.numpy().tobytes())
        build = {k: v for k, v in dataclasses.asdict(self.settings).items() if k not in QUERY_SETTINGS}
        h.update(json.dumps(build, sort_keys=True, default=str).encode())
        return h.hexdigest()[:20]

    def save(self, path: str | Path) -> Path:
        self._compact()
        g = self.graph
        keep, e = self.roadmap_node_ids(), self.roadmap_edge_ids()
        remap = np.full(g.n_nodes, -1, dtype=np.int64)
        remap[keep] = np.arange(len(keep))
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, configs=g.configs[keep], node_valid=np.ones(len(keep), dtype=bool),
                            eu=remap[g.edge_u[e]], ev=remap[g.edge_v[e]],
                            c_m=g.edge_attribute("c_m")[e], c_p=g.edge_attribute("c_p")[e],
                            verified=g.edge_attribute("verified")[e], checked=g.edge_attribute("checked")[e],
                            node_scores=self.node_scores[keep], max_motion=self.max_motion,
                            score_scale=getattr(self, "score_scale", 1.0),
                            fingerprint=self.fingerprint(), stats=json.dumps(self.stats))
        return path

    def load(self, path: str | Path, check: bool = True) -> None:
        data = np.load(path, allow_pickle=False)
        if check and str(data["fingerprint"]) != self.fingerprint():
            raise ConfigError(str(path), "fingerprint", "roadmap was built for another robot, scene or settings")
        g = Roadmap(dof=self.robot.dof, node_capacity=len(data["configs"]) + 64, edge_capacity=len(data["eu"]) + 1024)
        g.add_nodes(data["configs"])
        bad = np.nonzero(~data["node_valid"])[0]
        w = self._weight(data["c_p"], data["c_m"])
        g.add_edges(data["eu"], data["ev"], w, c_m=data["c_m"], c_p=data["c_p"], verified=data["verified"],
                    checked=data["checked"])
        if len(bad):
            g.remove_nodes(bad)
        self.graph, self.node_scores = g, data["node_scores"]
        self._rm_cache_key = None  # (see build)
        self._dead_edges, self._dead_nodes = [], []
        self._repairs, self._repair_added, self._repair_failed = 0, 0, 0
        self._blocked_nodes, self._blocked_edges, self._recheck = set(), set(), np.zeros(0, dtype=bool)
        self._roadmap_mask = np.ones(len(data["configs"]), dtype=bool)
        self._unverified = bool((data["verified"] < 0.5).any()) and not self.settings.lazy_edges
        self._index = None
        self.knots.clear()
        self.max_motion = float(data["max_motion"])
        self.score_scale = float(data["score_scale"])
        self.stats = json.loads(str(data["stats"]))
        self._build_hop_table()
