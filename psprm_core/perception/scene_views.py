"""Views a planner actually chooses among, for labelling with the oracle and fine-tuning the surrogate.

The paper trains its surrogate "on data from various objects and human targets that are typically present in the
specific environment the robot is expected to operate" (Sec. "Neural surrogate model"). The studio dataset
(:mod:`psprm_core.perception.dataset`) views each target alone, from 0.4-4 m, with the target anywhere in the image.
PS-PRM plans over a different distribution: camera poses of the robot's configurations on the visibility manifold,
in a furnished scene, from up to the room's size away (``psprm perf transfer`` measures how the studio-trained
surrogate ranks those). This module draws such views: it builds the PS-PRM roadmap of a scene for each target, and
takes the camera poses of random roadmap nodes and of random Eq. 1 edge samples (the interior knots whose scores
become the edge costs). Views that ray casting marks occluded are dropped: at planning time the scorer zeroes those
anyway (Alg. 2), and their rendered labels would teach the MLP, which sees only the relative pose, a spurious low
score for the pose.
"""

from __future__ import annotations

import logging
from typing import Optional, Sequence

import numpy as np
import torch

from ..planning.factory import make_planner
from ..robot import RobotModel
from .dataset import view_parameters
from ..errors import InputError
from .occlusion import OcclusionChecker

log = logging.getLogger(__name__)


def roadmap_views(scene, targets: Sequence[str], n_per_target: int, nodes: int = 3000, seed: int = 1,
                  planner: str = "neural-psprm-line", edge_fraction: float = 0.5, drop_occluded: bool = True,
                  robot=None, checkpoint=None) -> dict:
    """Camera poses of a scene's PS-PRM roadmaps, one roadmap per target.

    Parameters
    ----------
    scene : Scene
    targets : sequence of str
        Target names of ``scene``.
    n_per_target : int
        Views per target (fewer if the roadmap has too few non-occluded views).
    nodes : int
        Roadmap size.
    seed : int
        Seed of the roadmaps (target ``i`` uses ``seed + i``) and of the draws. Use seeds other than the ones the
        evaluation builds with (``psprm perf transfer`` and ``psprm bench`` use 0), so evaluation views are unseen.
    planner : str
        PS-PRM variant whose roadmap is drawn from (its manifold decides the views).
    edge_fraction : float
        Share of the views taken from Eq. 1 edge samples (the rest are roadmap nodes).
    drop_occluded : bool
        Drop views whose ray-cast occlusion score exceeds the scorer's threshold.
    robot : RobotModel, optional
        Defaults to the scene's robot.
    checkpoint : path, optional
        Surrogate the roadmap is scored with (only its scores differ; the views depend on the manifold).

    Returns
    -------
    dict
        ``camera_poses`` (N, 4, 4), ``target_index`` (N,) int32 into ``targets``, the :func:`view_parameters`
        arrays, ``origin`` (N,) int8 (0 = node, 1 = edge sample) and ``stats`` (per target: roadmap size, views
        drawn, views dropped as occluded).
    """
    if n_per_target < 1:
        raise InputError(f"n_per_target must be positive, got {n_per_target}")
    if not 0.0 <= edge_fraction <= 1.0:
        raise InputError(f"edge_fraction must be in [0, 1], got {edge_fraction}")
    robot = robot or RobotModel.load(scene.robot)
    rng = np.random.default_rng(seed)
    poses, tidx, origin, stats = [], [], [], {}
    for i, name in enumerate(targets):
        p = make_planner(planner, scene, [name], robot=robot, checkpoint=checkpoint,
                         options={"roadmap.n_nodes": nodes, "seed": seed + i})
        p.build()
        node_ids, edge_ids = p.roadmap_node_ids(), p.roadmap_edge_ids()
        want = 2 * n_per_target  # draw extra: occluded views are dropped below
        n_edge = int(round(want * edge_fraction)) if len(edge_ids) else 0
        n_node = want - n_edge
        q = []
        if n_node:
            q.append(p.graph.configs[rng.choice(node_ids, min(n_node, len(node_ids)), replace=False)])
        if n_edge:
            eid = rng.choice(edge_ids, min(n_edge, len(edge_ids)), replace=False)
            knots, interior = p.stored_knots(eid)
            pick = torch.as_tensor(rng.integers(0, interior.shape[1], len(eid)), device=interior.device)
            k = interior[torch.arange(len(eid), device=interior.device), pick]
            q.append(knots[torch.arange(len(eid), device=knots.device), k].detach().cpu().numpy())
        kinds = np.concatenate([np.zeros(len(q[0]) if n_node else 0, np.int8),
                                np.ones(len(q[-1]) if n_edge else 0, np.int8)])
        cams = robot.camera_poses(torch.as_tensor(np.concatenate(q), dtype=torch.float64))
        keep = np.ones(len(cams), dtype=bool)
        if drop_occluded:
            keep = ~OcclusionChecker.from_scene(scene, name).occluded(cams).cpu().numpy()
        order = rng.permutation(np.flatnonzero(keep))[:n_per_target]
        if len(order) < n_per_target:
            log.warning("target '%s': only %d non-occluded views of %d wanted", name, len(order), n_per_target)
        poses.append(cams.cpu().numpy()[order])
        origin.append(kinds[order])
        tidx.append(np.full(len(order), i, dtype=np.int32))
        stats[name] = {"roadmap_nodes": int(len(node_ids)), "roadmap_edges": int(len(edge_ids)),
                       "drawn": int(len(cams)), "occluded": int((~keep).sum()), "views": int(len(order))}
    out = {"camera_poses": np.concatenate(poses), "target_index": np.concatenate(tidx)}
    tgts = [scene.target(n) for n in targets]
    out.update(view_parameters(out["camera_poses"], out["target_index"], tgts, robot.config.intrinsics))
    out["origin"] = np.concatenate(origin)
    out["stats"] = stats
    return out


def roadmap_view_source(scene_name: str, planner: str, nodes: int, seed: int, n_per_target: int,
                        edge_fraction: float, distance: Optional[Sequence[float]] = None) -> dict:
    """The ``sampling`` record of a roadmap-view dataset's metadata (identifies it when resuming)."""
    out = {"source": "roadmap", "scene": scene_name, "planner": planner, "nodes": int(nodes), "seed": int(seed),
           "n_per_target": int(n_per_target), "edge_fraction": float(edge_fraction)}
    if distance is not None:
        out["distance"] = [float(distance[0]), float(distance[1])]
    return out
