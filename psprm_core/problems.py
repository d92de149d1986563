"""Random planning problems: collision-free (start, goal) pairs with the camera aimed at the target, as the bench,
the ``psprm perf`` commands, the RL baseline's training episodes and the device check draw them."""

from __future__ import annotations

import numpy as np
import torch

from .baselines.base import aim_camera
from .motion import DiffDriveMotion
from .planning.constraints import ProjectionSettings, VisibilityConstraint, camera_joint_mask


def aim_joints(robot) -> tuple:
    """The joints that aim the camera at problem ends (non-base camera joints) and every joint's finite limits:
    (cols, lower, upper), for :func:`psprm_core.baselines.base.aim_camera`."""
    mask = camera_joint_mask(robot)
    mask[: robot.base_dof] = False
    lo = np.where(np.isfinite(robot.lower), robot.lower, -1e9)
    hi = np.where(np.isfinite(robot.upper), robot.upper, 1e9)
    return np.nonzero(mask)[0], lo, hi


def can_move_away(robot, checker, q: torch.Tensor, template: np.ndarray, drive: float = 0.3,
                  resolution: float = 0.05) -> torch.Tensor:
    """Flags (N,): configurations ``q`` (N, dof) that a collision-free drive of ``drive`` m leads out of.

    A mobile base tries eight manoeuvres from each configuration: turn in place by 0, +90, -90 or 180 degrees, then
    drive ``drive`` m straight ahead, with the other joints kept or moved to ``template`` (e.g. the arm tucked)
    during the turn. Every turn and drive is collision-checked densely (``resolution``) with the differential-drive
    local motion. A configuration none of them leaves is boxed in: collision-free, but no planner can start from it
    (or reach it); the problem generator rejects such ends. Robots without a mobile base are not checked (all
    True).
    """
    motion = DiffDriveMotion(robot)
    q = torch.as_tensor(q, dtype=checker.dtype, device=checker.device).reshape(-1, robot.dof)
    n = len(q)
    tpl = torch.as_tensor(np.asarray(template, float), dtype=q.dtype, device=q.device)
    ok = torch.zeros(n, dtype=torch.bool, device=q.device)
    if n == 0:
        return ok
    if not robot.mobile:  # the check is about a base boxed in; every shipped robot has one
        return torch.ones(n, dtype=torch.bool, device=q.device)
    for turn in (0.0, 0.5 * np.pi, -0.5 * np.pi, np.pi):
        for tuck in (False, True):
            qa = q.clone()
            qa[:, 2] = torch.remainder(q[:, 2] + turn + np.pi, 2 * np.pi) - np.pi
            if tuck:
                qa[:, robot.base_dof:] = tpl[robot.base_dof:]
            qb = qa.clone()
            qb[:, 0] += drive * torch.cos(qa[:, 2])
            qb[:, 1] += drive * torch.sin(qa[:, 2])
            free = checker.valid(qa) & checker.valid(qb)
            free &= motion.motion_valid(checker, q, qa, resolution) & motion.motion_valid(checker, qa, qb, resolution)
            ok |= free
    return ok


def random_problems(robot, scene, checker, n: int, rng: np.random.Generator, template: np.ndarray,
                    target_center: np.ndarray, min_distance: float = 1.0, aimed_only: bool = False,
                    aim_restarts: int = 0, mobile_only: bool = False) -> list:
    """``n`` random collision-free (start, goal) pairs: base poses uniform over the workspace, the camera joints
    aimed at the target (projection onto the line-of-sight manifold with the non-base joints), others at
    ``template``; start and goal at least ``min_distance`` apart.

    ``aim_restarts`` > 0 retries unconverged aims from spread-out joint values
    (:func:`psprm_core.baselines.base.aim_camera`); ``aimed_only`` keeps only configurations whose optical axis
    passes through the target (within the projection tolerance); ``mobile_only`` keeps only configurations that a
    short collision-free manoeuvre leaves (:func:`can_move_away`: no boxed-in ends)."""
    cols, lo, hi = aim_joints(robot)
    con = VisibilityConstraint(robot, "line", target_center)
    out = []
    while len(out) < n:
        q = np.tile(template, (4 * n, 1))
        q[:, 0] = rng.uniform(*scene.workspace[0], 4 * n)
        q[:, 1] = rng.uniform(*scene.workspace[1], 4 * n)
        q[:, 2] = rng.uniform(-np.pi, np.pi, 4 * n)
        if aim_restarts > 0:
            qa, ok = aim_camera(con, q, cols, lo, hi, iters=10, restarts=aim_restarts,
                                seed=int(rng.integers(2**31)))
            qt = torch.as_tensor(qa, dtype=torch.float32)
            conv = torch.as_tensor(ok)
        else:
            qt = torch.as_tensor(q, dtype=torch.float32)
            qt, conv = con.project(qt, ProjectionSettings(max_iters=10), joints=cols)
        keep = checker.valid(qt)
        if aimed_only:
            keep &= conv.to(keep.device)
        if mobile_only and bool(keep.any()):
            idx = torch.nonzero(keep, as_tuple=True)[0]
            keep[idx[~can_move_away(robot, checker, qt[idx], template).to(keep.device)]] = False
        qt = qt[keep]
        qs = qt.double().numpy()
        for a, b in zip(qs[0::2], qs[1::2]):
            if np.linalg.norm(a[:2] - b[:2]) >= min_distance and len(out) < n:
                out.append((a, b))
    return out
