"""Saving and loading a roadmap (``.npz``), keyed by a fingerprint of the robot, the scene geometry, the focus point and
the settings that shape the roadmap."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ...errors import ConfigError
from ..search.graph import Roadmap
from ..settings import query_only_settings
from ..state import PlannerContext

if TYPE_CHECKING:
    from ..search.heuristics import Heuristics
    from .knots import KnotStore
    from .roadmap_state import RoadmapState
    from .scoring import Scoring


class Persistence:
    """Saves and loads roadmaps."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, heuristics: Heuristics,
                 scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.heuristics = heuristics
        self.scoring = scoring

    def fingerprint(self) -> str:
        """Hash of the robot, scene geometry, focus point and settings the roadmap was built for."""
        h = hashlib.sha256(self.ctx.robot.hash().encode())
        for b in self.ctx.scene.collision_boxes():
            h.update(np.concatenate([b.center, b.size, b.quat]).astype(np.float64).tobytes())
        h.update(self.ctx.constraint.target.numpy().tobytes())
        query_only = set(query_only_settings())
        build = {k: v for k, v in self.ctx.settings.flat().items() if k not in query_only}
        h.update(json.dumps(build, sort_keys=True, default=str).encode())
        return h.hexdigest()[:20]

    def save(self, path: str | Path) -> Path:
        """Write the roadmap nodes and edges (without the retired query ones), their scores, Eq. 1's normalisation
        and :meth:`fingerprint` to a compressed ``.npz``; returns its path."""
        self.rm.compact()
        g = self.rm.graph
        keep, e = self.rm.roadmap_node_ids(), self.rm.roadmap_edge_ids()
        remap = np.full(g.n_nodes, -1, dtype=np.int64)
        remap[keep] = np.arange(len(keep))
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, configs=g.configs[keep], node_valid=np.ones(len(keep), dtype=bool),
                            eu=remap[g.edge_u[e]], ev=remap[g.edge_v[e]],
                            c_m=g.edge_attribute("c_m")[e], c_p=g.edge_attribute("c_p")[e],
                            verified=g.edge_attribute("verified")[e], checked=g.edge_attribute("checked")[e],
                            node_scores=self.rm.node_scores[keep], max_motion=self.rm.max_motion,
                            score_scale=self.rm.score_scale,
                            fingerprint=self.fingerprint(), stats=json.dumps(self.rm.stats))
        return path

    def load(self, path: str | Path, check: bool = True) -> None:
        """Read a roadmap written by :meth:`save` (weights recomputed for the current alpha and objective); with
        ``check``, a :class:`~psprm_core.errors.ConfigError` when its fingerprint is not this planner's."""
        data = np.load(path, allow_pickle=False)
        if check and str(data["fingerprint"]) != self.fingerprint():
            raise ConfigError(str(path), "fingerprint", "roadmap was built for another robot, scene or settings")
        g = Roadmap(dof=self.ctx.robot.dof, node_capacity=len(data["configs"]) + 64,
                    edge_capacity=len(data["eu"]) + 1024)
        g.add_nodes(data["configs"])
        bad = np.nonzero(~data["node_valid"])[0]
        w = self.scoring.weight(data["c_p"], data["c_m"])
        g.add_edges(data["eu"], data["ev"], w, c_m=data["c_m"], c_p=data["c_p"], verified=data["verified"],
                    checked=data["checked"])
        if len(bad):
            g.remove_nodes(bad)
        self.rm.adopt(g, data["node_scores"], max_motion=float(data["max_motion"]),
                      score_scale=float(data["score_scale"]),
                      unverified=bool((data["verified"] < 0.5).any()) and not self.ctx.settings.edges.lazy_edges)
        self.knots.clear()
        self.rm.stats = json.loads(str(data["stats"]))
        self.heuristics.build_hop_table()
