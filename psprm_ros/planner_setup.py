"""The roadmap server's planner: what it builds (:class:`PlannerSpec`, node parameters of the same names), the planner
settings it declares as parameters and their live changes, the planner and replanner it makes, and the roadmap
cache it builds into or loads from. The planning library is imported inside the functions that need it."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Optional

from psprm_core.paths import cache_dir, resolve_named
from psprm_core.planning.factory import load_preset, make_planner
from psprm_core.planning.psprm import PSPRMSettings
from psprm_core.planning.replanner import Replanner, ReplanSettings
from psprm_core.planning.settings import parameter_specs, VARIANTS

log = logging.getLogger(__name__)

#: the planner settings (dotted paths) the roadmap server declares as parameters besides the live ones: those that
#: shape its roadmap (read-only: a change needs a restart)
SERVER_BUILD_SETTINGS = ("roadmap.n_nodes", "seed", "edges.collision_padding")
#: the roadmap server's own values of planner settings, over the settings file's: 5 cm kept from every obstacle, so
#: that a robot tracking its path a few cm off stays clear (the final check before publishing uses the obstacles as
#: they are)
SERVER_SETTING_DEFAULTS = {"edges.collision_padding": 0.05}


@dataclasses.dataclass
class PlannerSpec:
    """What the roadmap server builds (node parameters of the same names; ``settings``: planner settings by dotted
    path over the settings file and :data:`SERVER_SETTING_DEFAULTS`, None leaves one as the file has it)."""

    variant: str = "neural-psprm-line"
    planner_settings: str = ""  # PSPRMSettings YAML ("" = config/planners/psprm.yaml)
    replan_settings: str = "replan_reactive"  # ReplanSettings: a name in config/planners/ or a YAML path
    roadmap_file: str = ""  # "" = cache under ~/.cache/psprm/roadmaps; "none" = always build, never save
    checkpoint: str = ""  # surrogate checkpoint ("" = the shipped one)
    settings: dict = dataclasses.field(default_factory=dict)


PLANNER_PARAMS = {f.name: f.default for f in dataclasses.fields(PlannerSpec) if f.name != "settings"}


def server_setting_specs() -> tuple:
    """The planner settings the roadmap server declares as parameters (their
    :class:`~psprm_core.planning.settings_groups.SettingSpec`): every live one, and :data:`SERVER_BUILD_SETTINGS`."""
    return tuple(s for s in parameter_specs() if s.live or s.name in SERVER_BUILD_SETTINGS)


def planner_file_settings(planner_settings: str, robot_name: str):
    """The settings a planner of the server starts from: the file ``planner_settings`` ('' = the shipped preset) for
    robot ``robot_name``, validated (a :class:`~psprm_core.errors.ConfigError` for a bad file)."""
    if planner_settings:
        return PSPRMSettings.from_yaml(planner_settings, robot=robot_name)
    return load_preset(robot=robot_name)


def server_setting_values(settings) -> dict:
    """The server's planner-setting parameters' defaults (dotted path -> value): ``settings`` (from
    :func:`planner_file_settings`) with :data:`SERVER_SETTING_DEFAULTS` applied; ``scoring.alpha`` None when the
    file leaves it unset."""
    return {spec.name: SERVER_SETTING_DEFAULTS.get(spec.name, settings.value(spec.name))
            for spec in server_setting_specs()}


def resolve_live_settings(settings, changes: dict, variant: str):
    """``settings`` (a planner's) with ``changes`` (dotted paths) applied; ``scoring.alpha`` None in ``changes`` is
    the default of ``variant``'s scorer for the objective (:func:`~psprm_core.planning.settings.default_alpha`)."""
    new = settings.changed(changes)
    if "scoring.alpha" in changes and changes["scoring.alpha"] is None:
        new = new.changed({"scoring.alpha": None}).resolved(VARIANTS.get(variant, (None, None))[1])
    return new


def make_planner_for(scene, robot, targets, spec: PlannerSpec):
    """The planner ``spec`` describes: its variant, settings file and ``settings`` (over
    :data:`SERVER_SETTING_DEFAULTS`), by dotted path."""
    settings = planner_file_settings(spec.planner_settings, robot.name) if spec.planner_settings else None
    return make_planner(spec.variant, scene, targets, robot=robot, settings=settings,
                        checkpoint=Path(spec.checkpoint) if spec.checkpoint else None,
                        options={**SERVER_SETTING_DEFAULTS, **spec.settings})


def roadmap_cache_path(planner, scene, spec: PlannerSpec) -> Optional[Path]:
    if spec.roadmap_file.lower() == "none":
        return None
    if spec.roadmap_file:
        return Path(spec.roadmap_file)
    n_nodes = planner.settings.roadmap.n_nodes
    return cache_dir() / "roadmaps" / f"{scene.name}_{spec.variant}_{n_nodes}_{planner.fingerprint()}.npz"


def build_or_load(planner, scene, spec: PlannerSpec, template=None, force_build: bool = False) -> dict:
    """Load the cached roadmap when its fingerprint matches, else build it (and save it to the cache). Then the
    planner's compiled query kernels are loaded (``warm_up``, reported as ``warm_up_s``), so that the first plan
    does not pay for them."""
    path = roadmap_cache_path(planner, scene, spec)
    t0 = time.perf_counter()
    if path is not None and path.is_file() and not force_build:
        try:
            planner.load(path)
            return {"source": "loaded", "path": str(path), "n_nodes": int(planner.n_roadmap_nodes),
                    "seconds": time.perf_counter() - t0, "warm_up_s": _warm_up(planner)}
        except Exception as exc:  # a stale or foreign roadmap file: rebuild
            log.warning("cannot use roadmap %s (%s); rebuilding", path, exc)
    stats = planner.build(template=template)
    if not stats.get("success", False):
        return {"source": "failed", "reason": stats.get("reason", "build failed"), "seconds": time.perf_counter() - t0}
    if path is not None:
        try:
            planner.save(path)
        except OSError as exc:
            log.warning("cannot save roadmap %s: %s", path, exc)
    return {"source": "built", "path": str(path) if path else "", "n_nodes": int(planner.n_roadmap_nodes),
            "seconds": time.perf_counter() - t0, "warm_up_s": _warm_up(planner)}


def _warm_up(planner) -> float:
    """Compile or load the planner's small-batch query kernels now (PSPRM.warm_up); 0 for other planners."""
    warm = getattr(planner, "warm_up", None)
    return float(warm()) if warm is not None else 0.0


def make_replanner(planner, settings_path: str = ""):
    """The core :class:`~psprm_core.planning.replanner.Replanner` around a built or loaded ``planner``."""
    settings = ReplanSettings.from_yaml(resolve_named("planner", settings_path)) if settings_path else ReplanSettings()
    return Replanner(planner, settings)
