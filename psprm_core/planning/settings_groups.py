"""The settings groups of PS-PRM, one frozen dataclass per stage of the pipeline (roadmap, visibility, edges,
scoring, query, recovery; the metadata of the projection group, whose dataclass lives in ``constraints``), and what
their fields are made with: :func:`setting` (a dataclass field with its metadata: description, range or choices,
per-query, live, build) and :class:`SettingSpec` (one setting as a parameter), which the replanner's settings share
(:func:`field_specs`). :class:`~.settings.PSPRMSettings` groups them."""

from __future__ import annotations

import builtins
import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from ..errors import ConfigError
from .objectives import OBJECTIVES


def setting(default, description: str, *, range: tuple | None = (0, None), choices: tuple | None = None,
            query: bool = False, live: bool = False, build: bool = False, type: type | None = None):
    """A settings field with its metadata (read by :func:`~.settings.parameter_specs` and
    :meth:`~.settings.PSPRMSettings.validate`).

    ``description``: one line for users (parameter descriptions, ``--help``); ``range``: inclusive ``(lo, hi)``
    bounds of a number, either None for no bound (default ``(0, None)``: non-negative); ``choices``: the values a
    string may take; ``query``: one query may override it (``PSPRM.plan``'s ``options``); ``live``: a running
    planner takes a change (``PSPRM.update_settings``) without being made again; ``build``: it shapes the built
    roadmap (part of the roadmap's fingerprint); ``type``: the value's type where the default is None (unset: the
    planner chooses the value, e.g. :func:`~.settings.default_alpha`), else the default's type."""
    kind = builtins.type(default) if type is None else type
    numeric = kind in (int, float)
    meta = {"description": description, "range": tuple(range) if numeric and range is not None else None,
            "choices": tuple(choices) if choices is not None else None, "query": query, "live": live,
            "build": build, "type": kind}
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class SettingSpec:
    """One setting of :class:`~.settings.PSPRMSettings` as a parameter: what a ROS node needs to declare it."""

    name: str  #: dotted path (``"scoring.alpha"``)
    type: type  #: bool, int, float or str
    default: Any  #: the dataclass default; None: unset, the planner chooses the value (scoring.alpha: default_alpha)
    range: tuple | None  #: inclusive (lo, hi) of a number, either None for no bound; None for other types
    choices: tuple | None  #: the values a string may take; None for any
    description: str
    live: bool  #: a running planner takes a change without being made again (``PSPRM.update_settings``)
    query: bool  #: one query may override it (``PSPRM.plan``'s ``options``)
    build: bool  #: it shapes the built roadmap (hashed into the roadmap's fingerprint)

    def check(self, value: Any, source: str = "settings") -> None:
        """A :class:`~psprm_core.errors.ConfigError` naming ``source`` and :attr:`name` when ``value`` has the
        wrong type, lies outside :attr:`range` or is not one of :attr:`choices`."""
        if value is None and self.default is None:
            return  # unset: the planner chooses (e.g. scoring.alpha, default_alpha)
        if self.type is bool:
            ok = isinstance(value, (bool, np.bool_))
        elif self.type is int:
            ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
        elif self.type is float:
            ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
        else:
            ok = isinstance(value, self.type)
        if not ok:
            kind = {bool: "true or false", int: "an integer", float: "a number",
                    tuple: "a list"}.get(self.type, "a string")
            raise ConfigError(source, self.name, f"takes {kind}, got {value!r}")
        if self.range is not None:
            lo, hi = self.range
            if not np.isfinite(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
                raise ConfigError(source, self.name, f"must lie in [{'-inf' if lo is None else f'{lo:g}'}, "
                                                     f"{'inf' if hi is None else f'{hi:g}'}], got {value}")
        if self.choices is not None and value not in self.choices:
            raise ConfigError(source, self.name, f"unknown value {value!r} (choices: "
                                                 f"{', '.join(map(str, self.choices))})")


def _spec(name: str, fl, meta: dict) -> SettingSpec:
    """The :class:`SettingSpec` named ``name`` of field ``fl`` with :func:`setting`'s metadata ``meta``."""
    return SettingSpec(name=name, type=meta["type"], default=fl.default, range=meta["range"],
                       choices=meta["choices"], description=meta["description"], live=meta["live"],
                       query=meta["query"], build=meta["build"])


@functools.lru_cache(maxsize=None)
def field_specs(cls) -> tuple:
    """The fields of a settings dataclass ``cls`` made with :func:`setting` (e.g. the replanner's ``ReplanSettings``)
    as :class:`SettingSpec` named by the field's name, in field order; fields without that metadata (nested
    groups) are left out."""
    return tuple(_spec(fl.name, fl, fl.metadata) for fl in dataclasses.fields(cls) if "description" in fl.metadata)


@dataclass(frozen=True)
class RoadmapSettings:
    """Alg. 1: the nodes on the visibility manifold and their neighbours (``sampling``, ``neighbours``, ``builder``).
    Used when a roadmap is built."""

    n_nodes: int = setting(3000, "roadmap nodes sampled on the visibility manifold", range=(2, None), build=True)
    k_neighbors: int = setting(15, "nearest neighbours each node tries to connect to", range=(1, None), build=True)
    k_long: int = setting(10, "extra random neighbours within max_edge_length (long edges: fewer hops per path, "
                              "Eq. 2)", build=True)
    max_edge_length: float = setting(2.0, "longest edge (motion-cost units: m + weighted rad), the geodesic radius "
                                          "delta of Alg. 1", build=True)
    sample_joints: str = setting("camera", "joints sampled: camera (only joints that move the camera, the others at "
                                           "their default) | all", choices=("camera", "all"), build=True)
    sample_spread: float = setting(-1.0, ">= 0: non-base joints sampled within +-spread (rad/m) of the template; "
                                         "< 0: uniform within their limits", range=None, build=True)
    biased_share: float = setting(0.0, "share of the nodes drawn where the scorer predicts good views (accepted with "
                                       "probability c_p, the normalised score); the others uniform on the manifold",
                                  range=(0.0, 1.0), build=True)
    biased_tries: float = setting(6.0, "at most this many manifold samples scored per biased node wanted", build=True)
    expand_rounds: int = setting(0, "> 0: after the build, rounds of sampling between the largest component and "
                                    "the others", build=True)
    expand_nodes: int = setting(30, "nodes sampled per disconnected component and expansion round", build=True)
    expand_components: int = setting(12, "components (of >= 3 nodes, largest first) bridged per expansion round",
                                     build=True)
    sample_batch: int = setting(2048, "manifold samples projected per batch", range=(1, None), build=True)
    build_timeout_s: float = setting(120.0, "a build stops after this many seconds (s)")


@dataclass(frozen=True)
class VisibilitySettings:
    """The visibility manifold h_M (Sec. III-A, ``constraints``); fixed when a planner is made."""

    constraint: str = setting("line", "visibility model: line (the target on the optical axis) | frustum (the "
                                      "target within the image)", choices=("line", "frustum"), build=True)
    min_view_distance: float = setting(0.5, "the target at least this far in front of the camera (m)", build=True)
    frustum_margin: float = setting(0.05, "frustum model: room kept around the target (m)", build=True)
    kinematics: str = setting("native", "camera FK + Jacobian of the Newton projection and the collision checker's "
                                        "body FK: native (the robot model; compiled kernels for small CPU batches) | "
                                        "pytorch_kinematics (psprm_core.robot.kinematics_pk)",
                              choices=("native", "pytorch_kinematics"), build=True)


@dataclass(frozen=True)
class EdgeSettings:
    """Edges: Eq. 1's knots, their re-aiming and the dense collision checks (``edges``, ``knots``, ``verification``)."""

    n_interp: int = setting(5, "interior samples N of an edge's Eq. 1 score", build=True, live=True)
    edge_resolution: float = setting(0.05, "collision-check spacing along edges (motion-cost units)", build=True,
                                     live=True)
    edge_view_slack: float = setting(-1.0, ">= 0: interior configurations must keep the target within the frustum "
                                           "(+slack m); < 0: no such filter (Eq. 1 already scores interiors that "
                                           "lose it)", range=None, build=True, live=True)
    track_iters: int = setting(6, "Newton steps that re-aim the non-base camera joints at the knots of an edge",
                               build=True, live=True)
    lazy_collision: bool = setting(True, "Lazy PRM: an edge's dense interior is checked when a search first uses it",
                                   build=True, live=True)
    lazy_edges: bool = setting(False, "edge interiors scored (Eq. 1) only for edges on candidate paths (slow "
                                      "scorers)", build=True, live=True)
    collision_padding: float = setting(0.0, "m kept from every obstacle box by nodes and edges (the boxes grown by "
                                            "this much); a start inside that clearance but clear of the boxes is "
                                            "first moved out of it (recovery.start_fix_*); fixed when a planner is "
                                            "made", range=(0.0, 0.5), build=True)


@dataclass(frozen=True)
class ScoringSettings:
    """Edge weights from Eq. 1's perception and the motion cost (Eq. 2 and the other forms, ``scoring``)."""

    alpha: Optional[float] = setting(None, "weight of perception against motion cost in the edge weight (Eq. 2); "
                                           "unset: the planner variant's default for the objective (default_alpha)",
                                     range=(0.0, 1.0), live=True, type=float)
    objective: str = setting("eq2", "edge weight: eq2 (1 - alpha c_p + (1 - alpha) c_m) | motion (c_m ((1 - alpha) "
                                    "+ alpha (1 - c_p)): perception loss per unit of motion)", choices=OBJECTIVES,
                             live=True)
    normalize_scores: bool = setting(True, "c_p = min(1, score / q99(node scores)): the normalised score in [0, 1]",
                                     build=True, live=True)


@dataclass(frozen=True)
class QuerySettings:
    """One query: connecting its ends, the A* search (Eqs. 3-6), shortcuts, route selection and timing."""

    connect_k: int = setting(12, "neighbours tried when connecting a start or goal", range=(1, None), live=True)
    heuristic: str = setting("auto", "A* heuristic: hop (Eq. 3) | distance (motion lower bound) | exact (cost-to-go "
                                     "from a compiled Dijkstra) | auto (hop for eq2, distance for motion)",
                             choices=("hop", "distance", "exact", "auto"), query=True, live=True)
    shortcut: bool = setting(False, "shorten the found path where a direct motion is free, on the manifold and sees "
                                    "as well", query=True, live=True)
    shortcut_rounds: int = setting(2, "greedy shortcut passes over the path", query=True, live=True)
    route_searches: tuple = setting((), "more searches of each query (RouteSearch: objective@alpha, or alt: another "
                                        "route; as text comma separated, e.g. eq2@0.8,alt); the route that sees most "
                                        "within route_length_ratio of the planner's own length is returned",
                                    query=True, live=True, type=tuple)
    route_length_ratio: float = setting(1.5, "longest alternative route taken, relative to the length of the "
                                             "planner's own", range=(1.0, None), query=True, live=True)
    smooth_timing: bool = setting(True, "trajectories pass the knots of a base phase without stopping", query=True,
                                  live=True)


@dataclass(frozen=True)
class RecoverySettings:
    """A query that finds no path: the escape search, the local repair and the wide connection (``recovery``)."""

    query_repair_nodes: int = setting(120, "a query that finds no path grows this many nodes around its start and "
                                           "goals", live=True)
    query_repair_radius: float = setting(0.8, "m around the start/goal base where repair nodes grow (half of them "
                                              "along its heading)", live=True)
    query_repair_budget: int = setting(1500, "at most this many nodes grown by query repairs per built/loaded "
                                             "roadmap", live=True)
    query_repair_connect_k: int = setting(48, "neighbours tried per start / goal in a repaired query", live=True)
    query_repair_rounds: int = setting(3, "repair rounds of a failing query (radius x 1.5 each round)", live=True)
    query_repair_failures: int = setting(25, "failed (rolled back) repairs per built/loaded roadmap; then no more "
                                             "repairs", live=True)
    query_wide_k: int = setting(0, "last resort after the escape: each end tries its k nearest nodes, however far "
                                   "(0: off)", live=True)
    query_untracked_fallback: bool = setting(True, "escape/wide queries keep a connection with untracked camera "
                                                   "joints when its re-aimed version collides", live=True)
    query_escape_s: float = setting(0.0, "> 0: time (s) of the escape search of a failed query, before the repair "
                                         "(0: off)", live=True)
    query_escape_nodes: int = setting(1500, "at most this many configurations in an end's escape tree", live=True)
    query_escape_radius: float = setting(2.5, "m: half the escape samples put the base within this distance of the "
                                              "end, the others within twice that", live=True)
    query_escape_step: float = setting(0.4, "motion-cost units: the escape tree's short extensions", live=True)
    query_escape_connect_k: int = setting(6, "nearest roadmap nodes each new escape configuration tries to connect "
                                             "to", live=True)
    start_fix_radius: float = setting(0.25, "a start within the collision padding is moved out of it to the nearest "
                                            "padded-free configuration within this offset (m / rad); 0: such a "
                                            "start is refused", live=True)
    start_fix_samples: int = setting(64, "random offsets tried per ring (four rings, up to start_fix_radius)",
                                     range=(1, None), live=True)


#: metadata (as :func:`setting` makes it) of the projection group, whose dataclass lives in ``constraints``
PROJECTION_METADATA = {
    "tolerance": dict(description="projection tolerance: line, m off the optical axis; frustum, m outside the "
                                  "frustum", range=(None, None)),
    "max_iters": dict(description="Newton iterations of one projection", range=(1, None)),
    "damping": dict(description="Levenberg-Marquardt damping of the Newton step", range=(None, None)),
    "max_step": dict(description="largest norm of one Newton step (configuration units)", range=(None, None)),
}
