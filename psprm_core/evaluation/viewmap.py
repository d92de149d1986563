"""Where the real detector sees a target (``psprm perf viewmap``, :func:`detection_map`): the robot's camera aimed at
the target from every free point of a grid, each view rendered and scored by the oracle."""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ..errors import PsprmError
from ..paths import resolve_named
from ..perception.oracle import Oracle
from ..perception.render import look_at_pose
from ..robot import RobotModel, image_roll
from ..scene import load_scene


def detection_map(scene_name: str = "home", target: str | Sequence[str] | None = None, spacing: float = 0.5,
                  extra_roll_deg: float = 0.0, clearance: float = 0.2, placement: int = 0) -> dict:
    """Where in the scene the real detector sees a target: the robot's camera aimed at it from a grid of base positions.

    At every grid point of the scene's workspace (``spacing`` apart, skipping points within ``clearance`` of an
    obstacle's footprint) the camera is put at the robot's default camera height and aimed at the target's centre
    with a level, upright image (``look_at_pose``), optionally rolled by ``extra_roll_deg`` about the line of sight
    (90 shows what a sideways-mounted camera's image gives the detector). The oracle renders each view with the
    robot's intrinsics and runs the detector. Returns the share of points where the target counts as detected, the
    mean confidence, and the grid (rows from the workspace's high y to its low y) for printing.

    Several targets (a list, or one string ``"a,b"``) are monitored together as in the paper's two-nurse task: the
    camera is aimed at the mean of their centres, every target is judged in each view, ``detected_share`` counts
    the points where all of them are detected and ``detected_share_any`` those where at least one is; ``grid``
    holds the mean confidence over the targets and ``detected`` the number of targets detected per point.

    ``placement`` moves the targets to that placement first (:meth:`psprm_core.scene.Scene.with_placement`, as
    ``psprm bench --placements`` does).

    It is the ceiling of what any route can show the detector from that height: no occluder moved, no pan/tilt
    limit, every frame aimed.
    """
    import torch

    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    if target is None:
        names = [scene.target_names[0]]
    elif isinstance(target, str):
        names = [t.strip() for t in target.split(",") if t.strip()]
    else:
        names = list(target)
    for t in names:
        if t not in scene.target_names:
            raise PsprmError(f"scene '{scene.name}' has no target '{t}' (targets: {', '.join(scene.target_names)})")
    if not names or len(set(names)) != len(names):
        raise PsprmError(f"viewmap targets must be distinct scene targets, got {target!r}")
    try:
        scene = scene.with_placement(names, placement)
    except IndexError as exc:
        raise PsprmError(str(exc)) from None
    centre = np.mean([scene.target(t).center for t in names], axis=0)
    q0 = robot.default_configuration()
    height = float(robot.camera_poses(torch.as_tensor(q0[None], dtype=torch.float64))[0, 2, 3])
    (x0, x1), (y0, y1) = scene.workspace
    xs = np.arange(x0 + spacing / 2, x1, spacing)
    ys = np.arange(y0 + spacing / 2, y1, spacing)[::-1]
    # footprints (axis-aligned, grown by ``clearance``) of the boxes that reach below the camera, computed once
    feet = [(b.center[:2] - half - clearance, b.center[:2] + half + clearance)
            for b in scene.collision_boxes() if b.center[2] - 0.5 * b.size[2] < height
            for half in [0.5 * np.abs(b.rotation[:2, :2]) @ b.size[:2]]]

    def blocked(x: float, y: float) -> bool:
        return any(lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] for lo, hi in feet)

    roll = image_roll(extra_roll_deg)
    grid = np.full((len(ys), len(xs)), np.nan)
    hits = np.full((len(ys), len(xs)), -1, dtype=int)
    t0 = time.perf_counter()
    with Oracle(scene, intrinsics=robot.config.intrinsics) as oracle:
        thr = {t: oracle.threshold(oracle.detector_for(scene.target(t).detector_class), scene.target(t).detector_class)
               for t in names}
        for i, y in enumerate(ys):
            for j, x in enumerate(xs):
                if not blocked(x, y):
                    cam = look_at_pose([x, y, height], centre) @ roll
                    sc = [oracle.score(cam, t, keep_image=False).score for t in names]
                    grid[i, j] = float(np.mean(sc))
                    hits[i, j] = sum(v >= thr[t] for v, t in zip(sc, names))
    ok = np.isfinite(grid)
    out = {"scene": scene.name, "target": "+".join(names), "targets": names, "placement": placement,
           "camera_height_m": height,
           "extra_roll_deg": extra_roll_deg,
           "intrinsics": [robot.config.intrinsics.width, robot.config.intrinsics.height],
           "points": int(ok.sum()), "threshold": thr[names[0]] if len(names) == 1 else thr,
           "detected_share": float((hits[ok] == len(names)).mean()),
           "detected_share_any": float((hits[ok] > 0).mean()),
           "mean_confidence": float(grid[ok].mean()), "oracle_s": time.perf_counter() - t0,
           "x": xs.tolist(), "y": ys.tolist(), "grid": [[None if not np.isfinite(v) else round(float(v), 3)
                                                          for v in row] for row in grid]}
    if len(names) > 1:
        out["detected"] = [[None if h < 0 else int(h) for h in row] for row in hits]
    return out
