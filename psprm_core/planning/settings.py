"""Settings of PS-PRM (one frozen dataclass, read from ``config/planners/psprm.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .constraints import ProjectionSettings
from .objectives import OBJECTIVES


# settings one query may override (PSPRM.plan's ``options``)
QUERY_OPTIONS = ("heuristic", "shortcut", "shortcut_rounds", "smooth_timing", "route_searches", "route_length_ratio")

# settings that only affect queries (weights are recomputed from c_p and c_m on load): not part of the fingerprint
QUERY_SETTINGS = ("alpha", "objective", "heuristic", "shortcut", "shortcut_rounds", "connect_k", "build_timeout_s",
                  "query_repair_nodes", "query_repair_radius",
                  "query_repair_budget", "query_repair_connect_k", "query_repair_rounds", "query_repair_failures",
                  "query_wide_k", "query_untracked_fallback", "query_escape_s", "query_escape_nodes",
                  "query_escape_radius", "query_escape_step", "query_escape_connect_k",
                  "smooth_timing", "route_searches", "route_length_ratio")

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
    kinematics: str = "native"  # camera FK + Jacobian of the Newton projection and the collision checker's body FK:
    # native (the robot model; compiled kernels for small CPU batches) | pytorch_kinematics (psprm_core.kinematics_pk:
    # the projection always on the torch path; the checker's torch path, its small CPU batches still compiled)
    shortcut_rounds: int = 2  # greedy shortcut passes over the path
    route_searches: str = ""  # more searches of each query, "objective@alpha" or "alt" (another route) separated by
    # commas (e.g. "eq2@0.8,alt"); the route that sees most (motion-weighted mean Eq. 1 along the path) is returned when it is at
    # most route_length_ratio times as long as the planner's own (selection.RouteSelection); "" = one search
    route_length_ratio: float = 1.5  # longest alternative route taken, relative to the length of the planner's own
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
        self.route_search_list(source)
        if not (self.route_length_ratio >= 1.0 and np.isfinite(self.route_length_ratio)):
            raise ConfigError(source, "route_length_ratio",
                              f"must be a finite ratio >= 1, got {self.route_length_ratio}")
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


    def route_search_list(self, source: str = "settings") -> tuple:
        """The extra searches of ``route_searches`` as ``((objective, alpha), ...)`` (empty when unset); ``alt``
        (another route: the motion-weighted form at alpha = 1 with the edges of the routes found before weighted
        more, :data:`~.selection.ALT_PENALTY`) is ``("alt", 1.0)``.

        Raises
        ------
        ConfigError
            An entry that is not ``alt`` or ``objective@alpha`` with a known objective and alpha in [0, 1]."""
        out = []
        for item in (x.strip() for x in self.route_searches.split(",")):
            if not item:
                continue
            if item == "alt":
                out.append(("alt", 1.0))
                continue
            objective, _, alpha = item.partition("@")
            try:
                a = float(alpha)
            except ValueError:
                a = float("nan")
            if objective not in OBJECTIVES or not 0.0 <= a <= 1.0:
                raise ConfigError(source, "route_searches", f"'{item}' is neither 'alt' nor objective@alpha with an "
                                                            f"objective of {', '.join(OBJECTIVES)} and alpha in [0, 1]")
            out.append((objective, a))
        return tuple(out)
