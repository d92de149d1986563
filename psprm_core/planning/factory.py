"""Build planners by variant name (``neural-psprm-line``, ``psprm-frustum``, ...) for a scene and target(s)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..errors import ConfigError, PsprmError
from ..kernels.compute import Compute
from ..paths import config_dir, project_root
from ..perception.oracle import Oracle
from ..perception.scoring import GeometricScorer, MultiTargetScorer, NeuralScorer, OracleScorer
from ..perception.surrogate import load_surrogate
from ..robot import RobotModel
from ..scene import Scene
from .psprm import PSPRM, VARIANTS, PSPRMSettings
from .settings import DEFAULT_ALPHA, default_alpha

__all__ = ["DEFAULT_ALPHA", "PRESETS", "default_alpha", "default_checkpoint", "load_preset", "make_scorer",
           "make_planner", "problem_configurations"]

#: the settings presets in ``config/planners/`` by name: the shipped configuration (what saw most in the
#: benchmarks) and the paper's
PRESETS = {"psprm": "psprm.yaml", "psprm_paper": "psprm_paper.yaml"}


def load_preset(name: str = "psprm", robot: Optional[str] = None) -> PSPRMSettings:
    """The settings preset ``name`` (:data:`PRESETS`) for ``robot`` (its ``robots`` section applied), validated.

    Raises
    ------
    ConfigError
        An unknown preset, a missing or malformed file."""
    if name not in PRESETS:
        raise ConfigError("settings", "preset", f"unknown preset '{name}' ({', '.join(PRESETS)})")
    return PSPRMSettings.from_yaml(config_dir() / "planners" / PRESETS[name], robot=robot)


def default_checkpoint() -> Path:
    """The shipped surrogate checkpoint (``psprm_core/data/surrogate.pt``)."""
    return project_root() / "psprm_core" / "data" / "surrogate.pt"


def make_scorer(kind: str, scene: Scene, targets: Sequence[str], intrinsics, checkpoint: Optional[Path] = None,
                multi_mode: str = "mean", oracle=None):
    """Scorer of one or several targets: ``neural`` (surrogate + ray casting), ``oracle`` or ``geometric``."""
    for t in targets:
        scene.target(t)  # clear error for unknown targets
    if kind == "neural":
        ck = Path(checkpoint) if checkpoint else default_checkpoint()
        if not ck.is_file():
            raise PsprmError(f"surrogate checkpoint not found: {ck} (train one with `psprm dataset` + `psprm train`)")
        model = load_surrogate(ck)
        per = [NeuralScorer(model, scene, t) for t in targets]
    elif kind == "oracle":
        oracle = oracle or Oracle(scene, intrinsics=intrinsics)
        per = [OracleScorer(oracle, t) for t in targets]
    elif kind == "geometric":
        per = [GeometricScorer(scene, t, intrinsics) for t in targets]
    else:
        raise PsprmError(f"unknown scorer '{kind}' (neural, oracle, geometric)")
    if len(per) == 1:
        return per[0]
    return MultiTargetScorer(per, [scene.target(t).center for t in targets], mode=multi_mode)


def make_planner(variant: str, scene: Scene, targets: Sequence[str], robot: Optional[RobotModel] = None,
                 settings: Optional[PSPRMSettings] = None, checkpoint: Optional[Path] = None,
                 multi_mode: str = "mean", device: str = "cpu", preset: str = "psprm",
                 options: Optional[Mapping[str, Any]] = None, compute: Optional[Compute] = None) -> PSPRM:
    """A PS-PRM planner for ``variant`` (one of :data:`VARIANTS`), focused on the target(s)' centroid/midpoint.
    ``settings`` None: the preset ``preset`` (:func:`load_preset`) for the robot. ``options``: settings changed
    from those, by dotted path (``{"roadmap.n_nodes": 300, "scoring.alpha": 0.5}``; a None value keeps the
    setting; a field's bare name is refused with its dotted path). ``scoring.alpha`` left unset (by ``settings`` and
    ``options``) is the variant's :func:`default_alpha` for the objective. ``compute``: where and how the batches
    run (:class:`~psprm_core.kernels.compute.Compute`; default the device's)."""
    if variant not in VARIANTS:
        raise PsprmError(f"unknown planner '{variant}' (choose from {', '.join(sorted(VARIANTS))})")
    constraint, kind = VARIANTS[variant]
    robot = robot or RobotModel.load(scene.robot)
    if settings is None:
        settings = load_preset(preset, robot.name)
    settings = settings.changed({k: v for k, v in (options or {}).items() if v is not None}).resolved(kind)
    settings = settings.changed({
        "visibility.constraint": constraint,
        "edges.lazy_edges": settings.edges.lazy_edges or kind == "oracle",
        # biased sampling scores thousands of extra samples: only with a cheap scorer
        "roadmap.biased_share": settings.roadmap.biased_share if kind != "oracle" else 0.0})
    scorer = make_scorer(kind, scene, targets, robot.config.intrinsics, checkpoint, multi_mode)
    focus = np.mean([scene.target(t).center for t in targets], axis=0)
    planner = PSPRM(robot, scene, scorer, focus, settings, device=device, compute=compute)
    planner.targets = list(targets)
    return planner


def problem_configurations(robot: RobotModel, scene: Scene, problem) -> tuple:
    """Start (dof,) and goal configurations (G, dof) of a scene problem (goal regions -> their centre poses)."""
    start = robot.configuration(problem.start)
    goals = []
    if problem.goal:
        goals.append(robot.configuration(problem.goal))
    for name in problem.goal_regions:
        gr = scene.goal(name)
        vals = dict(gr.joints)
        vals.update(base_x=gr.base[0], base_y=gr.base[1], base_theta=gr.base[2])
        goals.append(robot.configuration(vals))
    if not goals:
        raise ConfigError(scene.source, f"problems.{problem.name}", "problem has no goal")
    return start, np.stack(goals)
