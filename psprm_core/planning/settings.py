"""Settings of PS-PRM: one frozen dataclass per stage of the pipeline, grouped in :class:`PSPRMSettings` (read from
``config/planners/psprm.yaml``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..yamlio import Fields, dataclass_kwargs, load_yaml, replace_settings, setting_value
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
                  "start_fix_radius", "start_fix_samples", "smooth_timing", "route_searches", "route_length_ratio")

VARIANTS = {
    "psprm-line": ("line", "oracle"),
    "psprm-frustum": ("frustum", "oracle"),
    "neural-psprm-line": ("line", "neural"),
    "neural-psprm-frustum": ("frustum", "neural"),
}


@dataclass(frozen=True)
class RoadmapSettings:
    """Alg. 1: the nodes on the visibility manifold and their neighbours (``sampling``, ``neighbours``, ``builder``)."""

    n_nodes: int = 3000
    k_neighbors: int = 15
    k_long: int = 10  # extra random neighbours within max_edge_length (long edges: fewer hops per path, Eq. 2)
    max_edge_length: float = 2.0  # motion-cost units (m + weighted rad), the geodesic radius delta of Alg. 1
    sample_joints: str = "camera"  # camera: sample only joints that move the camera (others at default) | all
    sample_spread: float = field(default=-1.0, metadata={"signed": True})  # >= 0: non-base joints sampled within
    # +-spread (rad/m) of the template, else uniform
    biased_share: float = 0.0  # share of the nodes drawn where the scorer predicts good views (accepted with
    # probability c_p, the normalised score); the others uniform on the manifold
    biased_tries: float = 6.0  # at most this many manifold samples scored per biased node wanted
    expand_rounds: int = 0  # > 0: after the build, rounds of sampling between the largest component and the others
    expand_nodes: int = 30  # nodes sampled per disconnected component and round
    expand_components: int = 12  # components (of >= 3 nodes, largest first) bridged per round
    sample_batch: int = 2048
    build_timeout_s: float = 120.0


@dataclass(frozen=True)
class VisibilitySettings:
    """The visibility manifold h_M (Sec. III-A, ``constraints``); fixed when a planner is made."""

    constraint: str = "line"  # visibility model: line | frustum
    min_view_distance: float = 0.5
    frustum_margin: float = 0.05
    kinematics: str = "native"  # camera FK + Jacobian of the Newton projection and the collision checker's body FK:
    # native (the robot model; compiled kernels for small CPU batches) | pytorch_kinematics (psprm_core.kinematics_pk:
    # the projection always on the torch path; the checker's torch path, its small CPU batches still compiled)


@dataclass(frozen=True)
class EdgeSettings:
    """Edges: Eq. 1's knots, their re-aiming and the dense collision checks (``edges``, ``knots``, ``verification``)."""

    n_interp: int = 5  # N of Eq. 1
    edge_resolution: float = 0.05  # collision-check spacing along edges (motion-cost units)
    edge_view_slack: float = field(default=-1.0, metadata={"signed": True})  # >= 0: interior configurations must keep
    # the target within the frustum (+slack m); < 0: no such filter (Eq. 1 already scores interiors that lose it)
    track_iters: int = 6  # Newton steps that re-aim the non-base camera joints at the knots of an edge
    lazy_collision: bool = True  # Lazy PRM: check an edge's dense interior when a search first uses it
    lazy_edges: bool = False  # score edge interiors (Eq. 1) only for edges on candidate paths (slow scorers)
    collision_padding: float = 0.0  # m kept from every obstacle box by nodes and edges (the boxes grown by this much,
    # CollisionChecker.padding); a start inside that clearance, but clear of the boxes themselves, is first moved out
    # of it (recovery.start_fix_*); 0: the planner may graze obstacles, and a robot off its path by 1 cm may hit one


@dataclass(frozen=True)
class ScoringSettings:
    """Edge weights from Eq. 1's perception and the motion cost (Eq. 2 and the other forms, ``scoring``)."""

    alpha: float = 0.8  # Eq. 2 (paper: 0.75 with the oracle, 0.8 with the surrogate)
    objective: str = "eq2"  # edge weight: eq2 (the paper's 1 - alpha c_p + (1 - alpha) c_m) | motion (c_m times
    # ((1 - alpha) + alpha (1 - c_p)): perception loss per unit of motion; objectives.motion_weighted)
    normalize_scores: bool = True  # c_p = min(1, score / q99(node scores)): the paper's normalised score in [0, 1]


@dataclass(frozen=True)
class QuerySettings:
    """One query: connecting its ends, the A* search (Eqs. 3-6), shortcuts, route selection and timing."""

    connect_k: int = 12  # neighbours tried when connecting a start or goal
    heuristic: str = "auto"  # A* heuristic: hop (Eq. 3, the paper's) | distance (motion lower bound, for the motion
    # objective) | exact (cost-to-go from a compiled Dijkstra) | auto (hop for eq2, distance for motion)
    shortcut: bool = False  # shorten the found path where a direct motion is free, on the manifold and sees as well
    shortcut_rounds: int = 2  # greedy shortcut passes over the path
    route_searches: str = ""  # more searches of each query, "objective@alpha" or "alt" (another route) separated by
    # commas (e.g. "eq2@0.8,alt"); the route that sees most (motion-weighted mean Eq. 1 along the path) is returned
    # when it is at most route_length_ratio times as long as the planner's own (selection.RouteSelection); "" = one
    route_length_ratio: float = 1.5  # longest alternative route taken, relative to the length of the planner's own
    smooth_timing: bool = True  # trajectories pass the knots of a base phase without stopping (timing.smooth)


@dataclass(frozen=True)
class RecoverySettings:
    """A query that finds no path: the escape search, the local repair and the wide connection (``recovery``)."""

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
    start_fix_radius: float = 0.25  # a start within the collision padding (edges.collision_padding) is moved out of it
    # to the nearest padded-free configuration found within this offset (m for the base and prismatic joints, rad
    # for the revolute ones) by a motion free of the unpadded boxes; 0: such a start is refused
    start_fix_samples: int = 64  # random offsets tried per ring (four rings, up to start_fix_radius)


@dataclass(frozen=True)
class PSPRMSettings:
    """Settings of PS-PRM, one group per stage of the pipeline. The field defaults are the paper's configuration
    (Eq. 2, uniform nodes, no shortcuts); ``config/planners/psprm.yaml``, which :func:`~.factory.make_planner` and
    everything built on it (CLI, bench, ROS nodes) load, ships the configuration that saw most in the benchmarks
    (motion objective, biased nodes, shortcuts).

    A setting is named by its dotted path (``scoring.alpha``) or, since no two groups share a field name, by its
    own name (``alpha``): :meth:`changed`, :meth:`value`, a query's ``options``, ``--set`` and
    ``PSPRM.update_settings`` take either. YAML files nest the groups."""

    roadmap: RoadmapSettings = field(default_factory=RoadmapSettings)
    visibility: VisibilitySettings = field(default_factory=VisibilitySettings)
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    edges: EdgeSettings = field(default_factory=EdgeSettings)
    scoring: ScoringSettings = field(default_factory=ScoringSettings)
    query: QuerySettings = field(default_factory=QuerySettings)
    recovery: RecoverySettings = field(default_factory=RecoverySettings)
    seed: int = 0

    def changed(self, changes: dict | None = None, **more) -> "PSPRMSettings":
        """These settings with ``changes`` (names or dotted paths) applied; not validated
        (:func:`~psprm_core.yamlio.replace_settings`)."""
        return replace_settings(self, changes, **more)

    def value(self, name: str):
        """One setting by name or dotted path."""
        return setting_value(self, name)

    def flat(self) -> dict:
        """Every setting by its own name, the projection settings as one mapping (what a roadmap's fingerprint
        hashes)."""
        out = {}
        for group in dataclasses.fields(self):
            v = getattr(self, group.name)
            if group.name == "projection" or not dataclasses.is_dataclass(v):
                out[group.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
            else:
                out.update(dataclasses.asdict(v))
        return out

    @classmethod
    def from_yaml(cls, path: str | Path, robot: str | None = None, **overrides) -> "PSPRMSettings":
        """Settings from YAML (one mapping per group); a ``robots: {name: {group: {field: value}}}`` section
        overrides fields for one robot; ``overrides`` (names or dotted paths, :meth:`changed`) that are not None
        win."""
        data = load_yaml(path)
        per_robot = data.pop("robots", None) or {}
        if not isinstance(per_robot, dict):
            raise ConfigError(str(path), "robots", "expected a mapping robot name -> settings")
        for name, extra in per_robot.items():  # every robot's section is checked, not only the one in use
            dataclass_kwargs(cls, Fields(extra, str(path), f"robots.{name}"))
        if robot is not None and robot in per_robot:
            extra = per_robot[robot]
            if not isinstance(extra, dict):
                raise ConfigError(str(path), f"robots.{robot}", "expected a mapping of settings")
            data = {**data, **{k: ({**data[k], **v} if isinstance(v, dict) and isinstance(data.get(k), dict) else v)
                               for k, v in extra.items()}}
        s = cls(**dataclass_kwargs(cls, Fields(data, str(path))))
        s = s.changed({k: v for k, v in overrides.items() if v is not None})
        s.validate(str(path))
        return s

    def validate(self, source: str = "settings") -> None:
        """Check every group; a bad value is a :class:`~psprm_core.errors.ConfigError` naming ``source`` and the
        setting's dotted path."""
        v, r, sc, q, rc = self.visibility, self.roadmap, self.scoring, self.query, self.recovery
        pad = self.edges.collision_padding
        if not (np.isfinite(pad) and 0 <= pad <= 0.5):
            raise ConfigError(source, "edges.collision_padding", f"must be a distance in [0, 0.5] m, got {pad}")
        if v.constraint not in ("line", "frustum"):
            raise ConfigError(source, "visibility.constraint",
                              f"unknown visibility model '{v.constraint}' (line, frustum)")
        if v.kinematics not in ("native", "pytorch_kinematics"):
            raise ConfigError(source, "visibility.kinematics", f"unknown kinematics '{v.kinematics}' (native, "
                                                               "pytorch_kinematics)")
        if q.heuristic not in ("hop", "exact", "distance", "auto"):
            raise ConfigError(source, "query.heuristic", f"unknown A* heuristic '{q.heuristic}' (hop, distance, "
                                                         "exact, auto)")
        if sc.objective not in OBJECTIVES:
            raise ConfigError(source, "scoring.objective",
                              f"unknown objective '{sc.objective}' ({', '.join(OBJECTIVES)})")
        self.route_search_list(source)
        if not (q.route_length_ratio >= 1.0 and np.isfinite(q.route_length_ratio)):
            raise ConfigError(source, "query.route_length_ratio",
                              f"must be a finite ratio >= 1, got {q.route_length_ratio}")
        if r.sample_joints not in ("camera", "all"):
            raise ConfigError(source, "roadmap.sample_joints", "must be 'camera' or 'all'")
        if not 0.0 <= sc.alpha <= 1.0:
            raise ConfigError(source, "scoring.alpha", f"must lie in [0, 1], got {sc.alpha}")
        if not 0.0 <= r.biased_share <= 1.0:
            raise ConfigError(source, "roadmap.biased_share", f"must lie in [0, 1], got {r.biased_share}")
        if r.n_nodes < 2 or r.k_neighbors < 1:
            raise ConfigError(source, "roadmap.n_nodes", "need at least 2 nodes and 1 neighbour")
        if not (rc.query_escape_s >= 0 and np.isfinite(rc.query_escape_s)):
            raise ConfigError(source, "recovery.query_escape_s",
                              f"must be a finite time >= 0, got {rc.query_escape_s}")
        if not (np.isfinite(rc.start_fix_radius) and rc.start_fix_radius >= 0) or rc.start_fix_samples < 1:
            raise ConfigError(source, "recovery.start_fix_radius",
                              f"needs a finite radius >= 0 and start_fix_samples >= 1, got {rc.start_fix_radius} and "
                              f"{rc.start_fix_samples}")
        if rc.query_escape_s > 0:
            for name in ("query_escape_radius", "query_escape_step"):
                x = getattr(rc, name)
                if not (x > 0 and np.isfinite(x)):
                    raise ConfigError(source, f"recovery.{name}", f"must be > 0 when query_escape_s > 0, got {x}")
            for name in ("query_escape_nodes", "query_escape_connect_k"):
                if getattr(rc, name) < 1:
                    raise ConfigError(source, f"recovery.{name}",
                                      f"must be >= 1 when query_escape_s > 0, got {getattr(rc, name)}")

    def route_search_list(self, source: str = "settings") -> tuple:
        """The extra searches of ``route_searches`` as ``((objective, alpha), ...)`` (empty when unset); ``alt``
        (another route: the motion-weighted form at alpha = 1 with the edges of the routes found before weighted
        more, :data:`~.selection.ALT_PENALTY`) is ``("alt", 1.0)``.

        Raises
        ------
        ConfigError
            An entry that is not ``alt`` or ``objective@alpha`` with a known objective and alpha in [0, 1]."""
        out = []
        for item in (x.strip() for x in self.query.route_searches.split(",")):
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
                raise ConfigError(source, "query.route_searches", f"'{item}' is neither 'alt' nor objective@alpha with an "
                                                            f"objective of {', '.join(OBJECTIVES)} and alpha in [0, 1]")
            out.append((objective, a))
        return tuple(out)
