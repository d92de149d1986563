"""Benchmark planners: the paper's baselines and thin adapters around the PS-PRM variants (paper Table II).

``make_baseline(name, scene, targets)`` builds any planner of :func:`planner_names` behind the common
:class:`~psprm_core.baselines.base.BenchPlanner` interface. Modules are imported lazily (by ``"module:Class"``
strings), so importing this package does no work.
"""

from __future__ import annotations

import importlib
from typing import Sequence

from ..errors import ConfigError, PsprmError
from ..yamlio import Fields, leaf_paths, replace_settings, setting_value, typed_value

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


#: Planner name -> ``"module:Class"`` of its settings dataclass (what ``psprm bench --set`` may change).
SETTINGS = {
    "post": "psprm_core.baselines.base:BaselineSettings",
    "rejection": "psprm_core.baselines.base:BaselineSettings",
    "manifold-line": "psprm_core.baselines.base:BaselineSettings",
    "manifold-frustum": "psprm_core.baselines.base:BaselineSettings",
    "trajopt": "psprm_core.baselines.trajopt:TrajOptSettings",
    "rl-ppo": "psprm_core.baselines.rl_ppo:PPOSettings",
    "psprm-line": "psprm_core.planning.psprm:PSPRMSettings",
    "psprm-frustum": "psprm_core.planning.psprm:PSPRMSettings",
    "neural-psprm-line": "psprm_core.planning.psprm:PSPRMSettings",
    "neural-psprm-frustum": "psprm_core.planning.psprm:PSPRMSettings",
}
#: Settings the benchmark itself decides (per-run seed; the visibility model is part of a PS-PRM variant's name).
FIXED_SETTINGS = frozenset({"seed", "constraint"})


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


def settings_class(name: str) -> type:
    """The settings dataclass of planner ``name``."""
    if name not in SETTINGS:
        raise PsprmError(f"unknown planner '{name}' (choose from {', '.join(BASELINES)})")
    mod, cls = SETTINGS[name].split(":")
    return getattr(importlib.import_module(mod), cls)


def parse_planner_settings(items: Sequence[str], planners: Sequence[str]) -> dict:
    """``["PLANNER.KEY=VALUE", ...]`` -> ``{planner: {key: value}}``, checked against each planner's settings.

    Values are read as YAML scalars and must have the type of the field's default (an int is accepted for a float
    field); the resulting settings must pass the class's ``validate()`` (e.g. ``alpha`` in [0, 1]).

    Raises
    ------
    PsprmError
        Malformed item, a planner not in ``planners``, an unknown or fixed setting, a value of the wrong type or
        out of range.
    """
    out: dict = {}
    for item in items:
        head, eq, raw = str(item).partition("=")
        head = head.strip()
        # the planner is the longest name run that prefixes the item (labels may hold dots; keys may be dotted paths)
        name = max((p for p in planners if head.startswith(p + ".")), key=len, default=head.partition(".")[0])
        key = head[len(name) + 1:] if head.startswith(name + ".") else ""
        if not eq or not name or not key or not raw.strip():
            raise PsprmError(f"--set '{item}': expected PLANNER.KEY=VALUE (e.g. neural-psprm-line.scoring.alpha=0.95)")
        if name not in planners:
            raise PsprmError(f"--set '{item}': planner '{name}' is not among the planners run "
                             f"({', '.join(planners)})")
        cls = settings_class(name.split("~", 1)[0])  # NAME~LABEL: planner NAME under its own label
        out.setdefault(name, {}).update(parse_settings([f"{key}={raw}"], cls, name, FIXED_SETTINGS, item))
    return out


def parse_settings(items: Sequence[str], cls: type, label: str, fixed: Sequence[str] = (),
                   shown: str | None = None, flag: str = "--set") -> dict:
    """``["KEY=VALUE", ...]`` -> ``{key: value}`` for the settings dataclass ``cls`` (typed like the YAML settings
    files, by the field default's type; the class's ``validate()`` run on the result); ``label`` names the settings
    in messages, ``fixed`` lists fields that cannot be set this way, ``shown`` the item as the user wrote it and
    ``flag`` the option it came with.

    Raises
    ------
    PsprmError
        Malformed item, an unknown or fixed setting, a value of the wrong type or out of range.
    """
    import dataclasses

    import yaml

    paths = leaf_paths(cls)
    defaults = cls()
    dotted_only = hasattr(cls, "coerce")  # PSPRMSettings: settings named by their dotted paths only

    def canonical(name: str) -> str:  # a setting's own name where it is unique, else its dotted path
        path = paths[name]
        if dotted_only:
            return ".".join(path)
        return path[-1] if paths.get(path[-1]) == path else ".".join(path)

    def settable(name: str) -> bool:  # a field with a plain default (not a group, not a factory), not fixed
        if name not in paths or canonical(name) in fixed or paths[name][-1] in fixed:
            return False
        *group, leaf = paths[name]
        owner = defaults
        for part in group:
            owner = getattr(owner, part)
        fl = {f.name: f for f in dataclasses.fields(owner)}[leaf]
        return fl.default is not dataclasses.MISSING

    out: dict = {}
    for item in items:
        key, eq, raw = str(item).partition("=")
        key, said = key.strip(), shown or item
        if not eq or not key or not raw.strip():
            raise PsprmError(f"{flag} '{said}': expected KEY=VALUE")
        if dotted_only and key in paths and key != canonical(key) and settable(key):
            raise PsprmError(f"{flag} '{said}': settings of {label} are named by their dotted path: "
                             f"'{canonical(key)}'")
        if not settable(key):
            names = sorted({canonical(k) for k in paths if settable(k)})
            raise PsprmError(f"{flag} '{said}': '{key}' is not a setting of {label} that {flag} can change "
                             f"(settable: {', '.join(names)})")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw.strip()
        key = canonical(key)
        default = setting_value(defaults, key)
        f = Fields({key: value}, f"{flag} {label}")
        if hasattr(cls, "coerce"):  # the class types its settings itself (PSPRMSettings: its parameter specs)
            try:
                value = cls.coerce(".".join(paths[key]), value, f"{flag} {label}")
            except ConfigError as exc:
                raise PsprmError(f"{flag} '{said}': {label}.{key} {exc.message}") from None
        try:  # typed as the YAML settings files are (the field default's type)
            if not hasattr(cls, "coerce"):
                value = typed_value(f, key, default, int_lo=None, float_lo=None)
        except ConfigError:
            kind = {bool: "true or false", int: "an integer", float: "a number"}.get(type(default), "a string")
            raise PsprmError(f"{flag} '{said}': {label}.{key} takes {kind}, got {raw.strip()!r}") from None
        try:
            probe = replace_settings(defaults, {**out, key: value})
            if hasattr(probe, "validate"):
                probe.validate(f"{flag} {label}")
        except Exception as exc:
            raise PsprmError(f"{flag} '{said}': {exc}") from None
        out[key] = value
    return out


__all__ = ["BASELINES", "SETTINGS", "planner_names", "make_baseline", "resolve", "settings_class",
           "parse_planner_settings", "parse_settings"]
