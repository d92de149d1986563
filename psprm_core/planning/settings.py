"""Settings of PS-PRM: one frozen dataclass per stage of the pipeline, grouped in :class:`PSPRMSettings` (read from
the presets in ``config/planners/``, :func:`~.factory.load_preset`). Each field carries its metadata (description,
range or choices, per-query, live, build); :func:`parameter_specs` lists them for parameter declarations."""

from __future__ import annotations

import builtins
import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Optional

import numpy as np

from ..errors import ConfigError
from ..yamlio import Fields, load_yaml, replace_settings, setting_value
from .constraints import ProjectionSettings
from .objectives import OBJECTIVES


#: alpha (Eq. 2's weight) of a planner whose settings leave it unset, per objective and scorer kind: Eq. 2 the
#: paper's (with the oracle and with the surrogate); the motion-weighted objective's measured with the surrogate
#: (docs/benchmarks.md, "Perception gain")
DEFAULT_ALPHA = {("eq2", "oracle"): 0.75, ("eq2", "neural"): 0.8, ("motion", "oracle"): 0.95,
                 ("motion", "neural"): 0.95}


def default_alpha(objective: str, kind: Optional[str] = None) -> float:
    """The alpha a planner with scorer ``kind`` (``oracle``, ``neural``; None for a planner made without a
    variant) uses for ``objective`` when its settings leave ``scoring.alpha`` unset: :data:`DEFAULT_ALPHA`, and for a
    pair the table lacks the surrogate's Eq. 2 weight."""
    return DEFAULT_ALPHA.get((objective, kind), DEFAULT_ALPHA[("eq2", "neural")])


class RouteSearch(NamedTuple):
    """One extra search of a query (``query.route_searches``): the edge weight ``objective`` at ``alpha``, or
    ``alt`` (another route: the motion-weighted form at alpha = 1 with the edges of the routes found before weighted
    more, :data:`~.selection.ALT_PENALTY`). Written ``objective@alpha`` or ``alt``."""

    objective: str
    alpha: float = 1.0

    def __str__(self) -> str:
        return "alt" if self.objective == "alt" else f"{self.objective}@{self.alpha:g}"


def parse_route_searches(value: Any, source: str = "settings") -> tuple:
    """``query.route_searches`` as a tuple of :class:`RouteSearch` from its typed form or its text forms: a comma
    separated string (``"eq2@0.8,alt"``, ``""`` for none) or a list of entries (strings or RouteSearch).

    Raises
    ------
    ConfigError
        An entry that is neither ``alt`` nor ``objective@alpha`` with an objective of :data:`OBJECTIVES` and alpha
        in [0, 1], naming ``source`` and ``query.route_searches``."""
    if isinstance(value, str):
        value = [x for x in (x.strip() for x in value.split(",")) if x]
    if not isinstance(value, (list, tuple)):
        raise ConfigError(source, "query.route_searches", f"expected a list of objective@alpha or alt, got {value!r}")
    out = []
    for item in value:
        shown = item
        if isinstance(item, str):
            text = shown = item.strip()
            objective, _, alpha = text.partition("@")
            if objective == "alt" and not alpha:
                item = RouteSearch("alt")
            else:
                try:
                    item = RouteSearch(objective, float(alpha))
                except ValueError:
                    item = RouteSearch(objective, float("nan"))
        elif not isinstance(item, RouteSearch):
            item = RouteSearch(str(item), float("nan"))
        if item.objective == "alt":
            ok = item.alpha == 1.0
        else:
            ok = item.objective in OBJECTIVES and isinstance(item.alpha, (int, float)) and 0.0 <= item.alpha <= 1.0
        if not ok:
            raise ConfigError(source, "query.route_searches", f"'{shown}' is neither 'alt' nor objective@alpha with "
                                                              f"an objective of {', '.join(OBJECTIVES)} and alpha in "
                                                              "[0, 1]")
        out.append(item)
    return tuple(out)


VARIANTS = {
    "psprm-line": ("line", "oracle"),
    "psprm-frustum": ("frustum", "oracle"),
    "neural-psprm-line": ("line", "neural"),
    "neural-psprm-frustum": ("frustum", "neural"),
}


def setting(default, description: str, *, range: tuple | None = (0, None), choices: tuple | None = None,
            query: bool = False, live: bool = False, build: bool = False, type: type | None = None):
    """A settings field with its metadata (read by :func:`parameter_specs` and :meth:`PSPRMSettings.validate`).

    ``description``: one line for users (parameter descriptions, ``--help``); ``range``: inclusive ``(lo, hi)``
    bounds of a number, either None for no bound (default ``(0, None)``: non-negative); ``choices``: the values a
    string may take; ``query``: one query may override it (``PSPRM.plan``'s ``options``); ``live``: a running
    planner takes a change (``PSPRM.update_settings``) without being made again; ``build``: it shapes the built
    roadmap (part of the roadmap's fingerprint); ``type``: the value's type where the default is None (unset: the
    planner chooses the value, e.g. :func:`default_alpha`), else the default's type."""
    kind = builtins.type(default) if type is None else type
    numeric = kind in (int, float)
    meta = {"description": description, "range": tuple(range) if numeric and range is not None else None,
            "choices": tuple(choices) if choices is not None else None, "query": query, "live": live,
            "build": build, "type": kind}
    return field(default=default, metadata=meta)


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


@dataclass(frozen=True)
class PSPRMSettings:
    """Settings of PS-PRM, one group per stage of the pipeline. Two presets (:func:`~.factory.load_preset`):
    ``config/planners/psprm.yaml``, which :func:`~.factory.make_planner` and everything built on it (CLI, bench, ROS
    nodes) load, ships the configuration that saw most in the benchmarks (motion objective, biased nodes,
    shortcuts, escape search); ``config/planners/psprm_paper.yaml`` is the paper's (Eq. 2, uniform nodes, the hop
    heuristic, no shortcuts).

    A setting is named by its dotted path (``scoring.alpha``; the seed by ``seed``): :meth:`changed`,
    :meth:`value`, a query's ``options``, ``--set`` and ``PSPRM.update_settings`` take those names only, and tell
    the dotted path of a field's own name given instead. YAML files nest the groups. Each field's metadata
    (description, range or choices, per-query, live, build) is listed by :func:`parameter_specs`."""

    roadmap: RoadmapSettings = field(default_factory=RoadmapSettings)
    visibility: VisibilitySettings = field(default_factory=VisibilitySettings)
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    edges: EdgeSettings = field(default_factory=EdgeSettings)
    scoring: ScoringSettings = field(default_factory=ScoringSettings)
    query: QuerySettings = field(default_factory=QuerySettings)
    recovery: RecoverySettings = field(default_factory=RecoverySettings)
    seed: int = setting(0, "random seed of the roadmap's sampling", build=True)

    def changed(self, changes: dict | None = None, **groups) -> "PSPRMSettings":
        """These settings with ``changes`` applied, each named by its dotted path (``{"scoring.alpha": 0.5}``; the
        seed by ``seed``); ``groups``: whole groups by name (``scoring=ScoringSettings(...)``), also allowed as keys
        of ``changes``. ``query.route_searches`` may be given in a text form (:func:`parse_route_searches`). Not
        validated; ``self`` is left as it is.

        Raises
        ------
        ConfigError
            A name that is not a dotted path of a setting (a field's own name is told its dotted path)."""
        changes = {**(changes or {}), **groups}
        for name in changes:
            _check_name(name, groups_too=True)
        if "query.route_searches" in changes:
            changes["query.route_searches"] = parse_route_searches(changes["query.route_searches"])
        return replace_settings(self, changes) if changes else self

    def resolved(self, kind: Optional[str] = None) -> "PSPRMSettings":
        """These settings with ``scoring.alpha`` set: as given, else :func:`default_alpha` of the objective and the
        scorer ``kind``."""
        if self.scoring.alpha is not None:
            return self
        return dataclasses.replace(self, scoring=dataclasses.replace(
            self.scoring, alpha=default_alpha(self.scoring.objective, kind)))

    @staticmethod
    def coerce(name: str, value: Any, source: str = "settings") -> Any:
        """``value`` (as YAML reads it: an int is taken for a float setting) typed as setting ``name`` (a dotted
        path); a :class:`~psprm_core.errors.ConfigError` naming ``source`` and the setting when it has another type
        (ranges and choices are :meth:`validate`'s)."""
        spec = {sp.name: sp for sp in parameter_specs()}.get(name)
        if spec is None:
            raise ConfigError(source, name, "unknown setting of PSPRMSettings")
        if spec.type is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if name == "query.route_searches":
            value = parse_route_searches(value, source)
        dataclasses.replace(spec, range=None, choices=None).check(value, source)
        return value

    def value(self, name: str):
        """One setting by its dotted path (``"scoring.alpha"``); a :class:`~psprm_core.errors.ConfigError` for any
        other name (:meth:`changed`)."""
        _check_name(name)
        return setting_value(self, name)

    def flat(self) -> dict:
        """Every setting by its own name, the projection settings as one mapping: the form a roadmap's fingerprint
        hashes (kept so that roadmaps cached under it still load), not a way to name settings."""
        out = {}
        for group in dataclasses.fields(self):
            v = getattr(self, group.name)
            if group.name == "projection" or not dataclasses.is_dataclass(v):
                out[group.name] = dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v
            else:
                out.update(dataclasses.asdict(v))
        return out

    @classmethod
    def from_yaml(cls, path: str | Path, robot: str | None = None, overrides: dict | None = None) -> "PSPRMSettings":
        """Settings from YAML (one mapping per group); a ``robots: {name: {group: {field: value}}}`` section
        overrides fields for one robot; ``overrides`` (dotted paths, :meth:`changed`) that are not None win."""
        data = load_yaml(path)
        per_robot = data.pop("robots", None) or {}
        if not isinstance(per_robot, dict):
            raise ConfigError(str(path), "robots", "expected a mapping robot name -> settings")
        for name, extra in per_robot.items():  # every robot's section is checked, not only the one in use
            _yaml_kwargs(Fields(extra, str(path), f"robots.{name}"))
        if robot is not None and robot in per_robot:
            extra = per_robot[robot]
            if not isinstance(extra, dict):
                raise ConfigError(str(path), f"robots.{robot}", "expected a mapping of settings")
            data = {**data, **{k: ({**data[k], **v} if isinstance(v, dict) and isinstance(data.get(k), dict) else v)
                               for k, v in extra.items()}}
        s = cls(**_yaml_kwargs(Fields(data, str(path))))
        s = s.changed({k: v for k, v in (overrides or {}).items() if v is not None})
        s.validate(str(path))
        return s

    def validate(self, source: str = "settings") -> None:
        """Check every setting against its range or choices (:func:`parameter_specs`) and the settings that depend
        on each other; a bad value is a :class:`~psprm_core.errors.ConfigError` naming ``source`` and the setting's
        dotted path."""
        for spec in parameter_specs():
            spec.check(self.value(spec.name), source)
        self.route_search_list(source)
        rc = self.recovery
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
        """The extra searches of ``query.route_searches`` (:class:`RouteSearch` each; empty when unset), checked.

        Raises
        ------
        ConfigError
            An entry that is not a :class:`RouteSearch` with a known objective (or ``alt``) and alpha in [0, 1]."""
        return parse_route_searches(self.query.route_searches, source)


@dataclass(frozen=True)
class SettingSpec:
    """One setting of :class:`PSPRMSettings` as a parameter: what a ROS node needs to declare it."""

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


def _group_fields(cls) -> list:
    """``(field, metadata)`` of every field of settings group ``cls`` (the projection group's metadata from
    :data:`PROJECTION_METADATA`)."""
    out = []
    for fl in dataclasses.fields(cls):
        meta = dict(fl.metadata)
        if cls is ProjectionSettings:
            meta = {"choices": None, "query": False, "live": True, "build": True, "type": type(fl.default),
                    **PROJECTION_METADATA[fl.name]}
        out.append((fl, meta))
    return out


@functools.lru_cache(maxsize=None)
def parameter_specs() -> tuple:
    """Every setting of :class:`PSPRMSettings` as a :class:`SettingSpec`, in the order of the groups and their
    fields: the source from which parameter declarations (a ROS node's, with their descriptions, ranges and
    whether they are live) are made."""
    out = []
    for group in dataclasses.fields(PSPRMSettings):
        cls = _nested(group)
        members = [(group.name, fl, meta) for fl, meta in _group_fields(cls)] if cls is not None else \
            [("", group, dict(group.metadata))]
        for prefix, fl, meta in members:
            out.append(_spec(f"{prefix}.{fl.name}" if prefix else fl.name, fl, meta))
    return tuple(out)


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


def _nested(fl) -> type | None:
    """The settings group a field of :class:`PSPRMSettings` holds, else None."""
    if fl.default_factory is dataclasses.MISSING:
        return None
    made = fl.default_factory()
    return type(made) if dataclasses.is_dataclass(made) else None


def query_options() -> tuple:
    """Dotted names of the settings one query may override (``PSPRM.plan``'s ``options``)."""
    return tuple(s.name for s in parameter_specs() if s.query)


def query_only_settings() -> tuple:
    """Own names (:meth:`PSPRMSettings.flat`'s keys) of the settings that do not shape the built roadmap: not part of
    its fingerprint."""
    return tuple(s.name.rpartition(".")[2] for s in parameter_specs() if not s.build)


def _yaml_value(f: Fields, key: str, spec: SettingSpec) -> Any:
    """``f[key]`` read as the setting ``spec`` (its type; numbers within its range's lower bound, the rest checked by
    :meth:`PSPRMSettings.validate`); null for a setting that may be unset."""
    if f.data.get(key) is None and spec.default is None:
        return None
    lo = spec.range[0] if spec.range is not None else None
    if spec.type is bool:
        return f.bool(key)
    if spec.type is int:
        return f.int(key, lo=lo)
    if spec.type is float:
        return f.float(key, lo=lo)
    if spec.name == "query.route_searches":  # a list of entries or one comma separated string
        return parse_route_searches(f.raw(key), f.source)
    return f.str(key)


def _yaml_kwargs(f: Fields) -> dict:
    """Keyword arguments of :class:`PSPRMSettings` from a YAML mapping of groups (``{group: {field: value}}``,
    ``seed``); every key checked, a field given outside its group named with the group it belongs to."""
    specs = {sp.name: sp for sp in parameter_specs()}
    groups = {fl.name: _nested(fl) for fl in dataclasses.fields(PSPRMSettings)}
    home = {name.rpartition(".")[2]: name.rpartition(".")[0] for name in specs if "." in name}
    out = {}
    for key in f.data:
        if key not in groups:
            if key in home:
                raise f.error(str(key), f"belongs to the '{home[key]}' group ({home[key]}: {{{key}: ...}})")
            raise f.error(str(key), f"unknown field (allowed: {', '.join(groups)})")
        cls = groups[key]
        if cls is None:
            out[key] = _yaml_value(f, key, specs[key])
            continue
        sub = f.sub(key)
        names = [fl.name for fl in dataclasses.fields(cls)]
        sub.check_keys(names)
        out[key] = cls(**{k: _yaml_value(sub, k, specs[f"{key}.{k}"]) for k in sub.data})
    return out


def _check_name(name: str, groups_too: bool = False) -> None:
    """A :class:`~psprm_core.errors.ConfigError` unless ``name`` is a setting's dotted path (or, with
    ``groups_too``, a group's name); a field's own name is told its dotted path."""
    names = {sp.name for sp in parameter_specs()}
    if name in names or (groups_too and name in {fl.name for fl in dataclasses.fields(PSPRMSettings)}):
        return
    dotted = [n for n in names if n.rpartition(".")[2] == name]
    if dotted:
        raise ConfigError("settings", name, f"settings are named by their dotted path: '{dotted[0]}'")
    raise ConfigError("settings", name, "unknown setting of PSPRMSettings (a dotted path such as 'scoring.alpha')")
