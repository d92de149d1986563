"""The problems of ``psprm bench``: random collision-free start and goal pairs with the camera joints aimed at the
target, spread round-robin over target groups and placements (:func:`make_problems`), or independent runs of a
scene's named problem (:func:`scenario_problems`, the paper's Table III protocol)."""

from __future__ import annotations

import logging
from typing import Optional

import numpy as np

from ...baselines.base import aim_camera
from ...collision import CollisionChecker
from ...errors import PsprmError
from ...perception.surrogate import load_surrogate
from ...planning.constraints import VisibilityConstraint
from ...planning.factory import default_checkpoint, problem_configurations
from ...problems import aim_joints, random_problems

log = logging.getLogger(__name__)


#: Classes left out of the default target groups (none at present). The cup is included: an aimed, upright Stretch
#: camera detects it from 55 % of the home room (``psprm perf viewmap``), so it is benchmarked like the paper's other
#: objects (its tiled CenterNet costs ~0.45 s per judged frame).
DEFAULT_EXCLUDED_CLASSES: frozenset = frozenset()


def default_target_groups(scene) -> list:
    """Target groups the problems are spread over: ``nursing`` -> both nurses' faces together (paper Table III);
    otherwise every target whose class the shipped surrogate knows (the neural variants refuse the others), each on
    its own, except :data:`DEFAULT_EXCLUDED_CLASSES`."""
    names = scene.target_names
    if "nurse_1_face" in names and "nurse_2_face" in names:
        return [["nurse_1_face", "nurse_2_face"]]
    try:
        classes = set(load_surrogate(default_checkpoint()).classes)
    except Exception:  # pragma: no cover - no checkpoint: every target
        classes = set()
    groups = [[t] for t in names if (not classes or scene.target(t).detector_class in classes)
              and scene.target(t).detector_class not in DEFAULT_EXCLUDED_CLASSES]
    return groups or [[t] for t in names]


def make_problems(scene, robot, groups: list, n: int, seed: int, placements: int = 1) -> list:
    """``n`` problems spread round-robin over ``groups`` x target placements ``0..placements-1``: dicts with index,
    targets, placement, start, goal (numpy).

    Placement ``k`` moves every target of the group to its ``k``-th pose (:meth:`Scene.with_placement`; the paper's
    "five variations in the object's poses" per object); the problems of a placement are generated in that scene.
    Ends are collision-free, aimed at the group's centroid and not boxed in (a short turn or drive leaves them,
    :func:`psprm_core.problems.can_move_away`).
    With ``placements=1`` every problem uses the targets' scene poses (placement 0).

    Raises
    ------
    PsprmError
        ``placements`` < 1, or a target of a group with fewer placements.
    """
    if placements < 1:
        raise PsprmError(f"placements must be at least 1, got {placements}")
    for g in groups:
        for t in g:
            if scene.target(t).n_placements < placements:
                raise PsprmError(f"target '{t}' of scene '{scene.name}' has {scene.target(t).n_placements} "
                                 f"placement(s), fewer than the {placements} asked for")
    cells = [(gi, k) for gi in range(len(groups)) for k in range(placements)]
    per = [n // len(cells) + (1 if i < n % len(cells) else 0) for i in range(len(cells))]
    pairs = []
    for (gi, k), m in zip(cells, per):
        if m == 0:
            pairs.append([])
            continue
        g = groups[gi]
        placed = scene.with_placement(g, k)
        checker = CollisionChecker(robot, placed.collision_boxes(), workspace=placed.workspace)
        focus = np.mean([placed.target(t).center for t in g], axis=0)
        rng = np.random.default_rng([seed, gi] if k == 0 else [seed, gi, k])
        pairs.append(random_problems(robot, placed, checker, m, rng, robot.default_configuration(), focus,
                                     aimed_only=True, aim_restarts=8, mobile_only=True))
    out, used = [], [0] * len(cells)
    for i in range(n):
        ci = i % len(cells)
        while used[ci] >= per[ci]:
            ci = (ci + 1) % len(cells)
        a, b = pairs[ci][used[ci]]
        used[ci] += 1
        gi, k = cells[ci]
        out.append({"index": i, "targets": list(groups[gi]), "placement": k, "start": np.asarray(a, float),
                    "goal": np.asarray(b, float)})
    return out


def scenario_problems(scene, robot, name: str, n: int, seed: int, targets: Optional[list] = None) -> list:
    """``n`` independent runs of the scene's named problem ``name`` (the paper's Table III protocol).

    Every run has the problem's start and (first) goal, with the camera joints aimed at the monitoring point of
    ``targets`` (default: the problem's own targets; their centroids' mean), as in :func:`make_problems`; run ``i``
    carries ``run_seed = seed + i``, the seed every planner is built with for that run.

    Raises
    ------
    PsprmError
        Unknown problem (the known names are listed), or a start or goal in collision.
    """
    try:
        prob = scene.problem(name)
    except KeyError:
        known = ", ".join(p.name for p in scene.problems) or "none"
        raise PsprmError(f"scene '{scene.name}' has no problem '{name}' (problems: {known})") from None
    group = list(targets or prob.all_targets)
    focus = np.mean([scene.target(t).center for t in group], axis=0)
    start, goals = problem_configurations(robot, scene, prob)
    ends = np.stack([start, goals[0]])
    cols, lo, hi = aim_joints(robot)
    aimed, ok = aim_camera(VisibilityConstraint(robot, "line", focus), ends, cols, lo, hi, iters=10, restarts=8,
                           seed=seed)
    ends = np.asarray(aimed, float)  # unconverged: as close to the target as the joint limits allow
    import torch

    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    valid = checker.valid(torch.as_tensor(ends, dtype=torch.float32)).cpu().numpy()
    for which, v in zip(("start", "goal"), valid):
        if not v:
            raise PsprmError(f"problem '{name}' of scene '{scene.name}': the {which} is in collision")
    if not np.asarray(ok, bool).all():
        log.warning("problem '%s': the camera joints cannot face %s at the %s (aimed as close as the limits allow)",
                    name, "+".join(group), " and ".join(w for w, k in zip(("start", "goal"), ok) if not k))
    return [{"index": i, "targets": group, "start": ends[0].copy(), "goal": ends[1].copy(), "run_seed": seed + i,
             "scenario": name} for i in range(n)]
