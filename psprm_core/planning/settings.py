"""Settings of PS-PRM: :class:`PSPRMSettings` groups one frozen dataclass per stage of the pipeline
(:mod:`.settings_groups`), is read from the presets in ``config/planners/`` (:func:`~.factory.load_preset`) and names
each setting by its dotted path. Each field carries its metadata (description, range or choices, per-query, live,
build); :func:`parameter_specs` lists them for parameter declarations."""

from __future__ import annotations

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
from .settings_groups import (PROJECTION_METADATA, EdgeSettings, QuerySettings, RecoverySettings, RoadmapSettings,
                              ScoringSettings, SettingSpec, VisibilitySettings, _spec, setting)


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


def _group_fields(cls) -> list:
    """``(field, metadata)`` of every field of settings group ``cls`` (the projection group's metadata from
    :data:`~.settings_groups.PROJECTION_METADATA`)."""
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
