"""Dynamic scenes (the replanner's updates): moved targets re-score the roadmap's nodes and mark their edges for lazy
Eq. 1 scoring; moved obstacles block what they touch (spatial index over nodes and edges) and give back what
they left."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from ...collision import BoxTensors
from ...scene import Scene
from ..search.graph_search import edge_perception
from ..state import PlannerContext, large_batches

if TYPE_CHECKING:
    from .knots import KnotStore
    from .roadmap_state import RoadmapState
    from .scoring import Scoring


class Dynamics:
    """Updates the roadmap when targets or obstacles move."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, scoring: Scoring):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.scoring = scoring

    def set_scene(self, scene: Scene) -> None:
        """Adopt moved targets/obstacles: the scorer's occluders and the collision checker's boxes follow ``scene``.

        Nothing is re-scored or re-checked here; see :meth:`rescore` and :meth:`invalidate_near`."""
        self.ctx.scene = scene
        self.ctx.scorer.set_scene(scene)
        self.ctx.checker.set_boxes(scene.collision_boxes())

    def set_focus(self, focus) -> None:
        """Move the point the visibility constraint aims at. Edges re-aim their camera joints at it, so every edge's
        knots are recomputed, re-checked and re-scored lazily when a search next uses it."""
        self.ctx.constraint.set_target(np.asarray(focus, float))
        self.forget_knots()

    def forget_knots(self) -> None:
        """Drop every stored knot; every edge is re-checked and re-scored (Eq. 1) when a search next uses it."""
        self.knots.clear()
        g = self.rm.graph
        if g is not None:
            e = g.valid_edge_ids()
            g.edge_attribute("checked")[e] = 0.0
            g.edge_attribute("verified")[e] = 0.0
            self.rm.unverified = True

    @large_batches
    def rescore(self, full: bool = False, tol: float = 1e-4) -> dict:
        """Re-score the roadmap after the target or an occluder moved.

        Every valid roadmap node is scored in one batch (FK -> scorer). ``full=False`` (lazy): the edges at a node whose
        score changed by more than ``tol`` get the Eq. 1 estimate from their two ends only and are marked unverified; a
        search then scores the N interior configurations (Eq. 1) only for the edges on its candidate paths
        (:meth:`~.verification.Verification.verify_edges` via :func:`lazy_astar`). ``full=True`` scores the interiors of
        every edge now (what a planner without lazy evaluation pays on every replan). Returns counts and timings."""
        t0 = time.perf_counter()
        g = self.rm.graph
        ids = self.rm.roadmap_node_ids()
        scores = self.rm.node_score_slots()
        key = hash(ids.tobytes())
        if self.rm.node_cams_key != key:  # node camera poses only change with the node set
            Q = self.rm.tensor(ids)
            cams = self.ctx.robot.camera_poses
            self.rm.node_cams = torch.cat([cams(Q[i:i + 65536]) for i in range(0, len(Q), 65536)])
            self.rm.node_cams_key = key
        new = self.ctx.scorer.score(self.rm.node_cams).double().cpu().numpy()
        changed = np.abs(new - scores[ids]) > tol
        scores[ids] = new
        e = self.rm.roadmap_edge_ids()
        if not full:
            flag = np.zeros(g.n_nodes, dtype=bool)
            flag[ids[changed]] = True
            e = e[flag[g.edge_u[e]] | flag[g.edge_v[e]]]
        t_nodes = time.perf_counter() - t0
        if len(e):
            c_p, ver = g.edge_attribute("c_p"), g.edge_attribute("verified")
            if full:
                p = np.empty(len(e))
                for s0 in range(0, len(e), 4096):
                    p[s0:s0 + 4096] = self.scoring.stored_perception(e[s0:s0 + 4096]).double().cpu().numpy()
                ver[e] = 1.0
            else:
                scale = self.rm.score_scale
                p = edge_perception(np.clip(scores[g.edge_u[e]] * scale, 0, 1),
                                    np.clip(scores[g.edge_v[e]] * scale, 0, 1))
                ver[e] = 0.0
                self.rm.unverified = True
            c_p[e] = p
            g.set_weights(e, self.scoring.weight(p, g.edge_attribute("c_m")[e]))
        return {"nodes": int(len(ids)), "changed_nodes": int(changed.sum()), "edges": int(len(e)),
                "nodes_ms": t_nodes * 1e3, "total_ms": (time.perf_counter() - t0) * 1e3}

    def spatial_index(self):
        """KD-trees over the roadmap's base positions (nodes) and edge midpoints, plus the robot's reach radius
        (largest xy distance of a collision sphere from the base over the roadmap's nodes) and the longest edge's
        half length. Built on first use and after :meth:`~.builder.Builder.grow`; removals keep it valid (stale ids are
        filtered)."""
        if self.rm.index is None:
            from scipy.spatial import cKDTree

            g = self.rm.graph
            ids, e = self.rm.roadmap_node_ids(), self.rm.roadmap_edge_ids()
            Q = self.rm.tensor(ids)
            reach = 0.0
            if self.ctx.robot.mobile and len(ids):
                r = torch.as_tensor(self.ctx.robot.spheres.radii, dtype=self.ctx.dtype, device=self.ctx.device)
                for s0 in range(0, len(Q), 4096):
                    c = self.ctx.robot.sphere_centers(Q[s0:s0 + 4096])
                    d = (c[..., :2] - Q[s0:s0 + 4096, None, :2]).norm(dim=-1) + r
                    reach = max(reach, float(d.max()))
            xy = g.configs[:, :2] if self.ctx.robot.mobile else np.zeros((g.n_nodes, 2))
            a, b = xy[g.edge_u[e]], xy[g.edge_v[e]]
            half = 0.5 * np.linalg.norm(b - a, axis=1)
            self.rm.index = {"node_ids": ids, "node_tree": cKDTree(xy[ids]), "edge_ids": e,
                             "edge_tree": cKDTree(0.5 * (a + b)) if len(e) else None,
                             "max_half": float(half.max()) if len(e) else 0.0, "reach": reach}
        return self.rm.index

    def near(self, boxes: Sequence, margin: float = 0.05) -> tuple:
        """Roadmap node ids and edge ids within the robot's reach of ``boxes`` (spatial index; everything for a
        fixed-base robot)."""
        g = self.rm.graph
        if not self.ctx.robot.mobile:
            return self.rm.roadmap_node_ids(), self.rm.roadmap_edge_ids()
        idx = self.spatial_index()
        nsel, esel = set(), set()
        for b in (b.planned() for b in boxes):  # a turning box as checked: swept through every heading
            c = np.asarray(b.center, float)[:2]
            rad = float(np.linalg.norm(np.asarray(b.size, float)[:2]) / 2) + idx["reach"] + margin \
                + self.ctx.checker.padding  # the box as checked: grown by the planner's clearance
            nsel.update(idx["node_tree"].query_ball_point(c, rad))
            if idx["edge_tree"] is not None:
                cand = np.asarray(idx["edge_tree"].query_ball_point(c, rad + idx["max_half"]), dtype=np.int64)
                if len(cand):
                    ee = idx["edge_ids"][cand]
                    pa, pb = g.configs[g.edge_u[ee], :2], g.configs[g.edge_v[ee], :2]
                    d = pb - pa
                    t = np.clip(((c - pa) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0, 1)
                    dist = np.linalg.norm(pa + t[:, None] * d - c, axis=1)
                    esel.update(ee[dist <= rad].tolist())
        nodes = idx["node_ids"][np.asarray(sorted(nsel), dtype=np.int64)] if nsel else np.zeros(0, np.int64)
        return nodes, np.asarray(sorted(esel), dtype=np.int64)

    def knots_hit(self, edges: np.ndarray, boxes) -> np.ndarray:
        """(E,) bool: some stored interior knot of the edges collides with ``boxes`` (environment check only).

        Knots whose base lies beyond the robot's reach of every box are skipped before any kinematics."""
        knots, _ = self.knots.get(edges)
        E, M, dof = knots.shape
        if M <= 2:
            return np.zeros(E, dtype=bool)
        inner = knots[:, 1:-1].reshape(-1, dof)
        near = torch.ones(len(inner), dtype=torch.bool, device=inner.device)
        if self.ctx.robot.mobile:
            box_list = list(boxes) if not hasattr(boxes, "center") else None
            if box_list is not None:
                reach = self.spatial_index()["reach"]
                near = torch.zeros(len(inner), dtype=torch.bool, device=inner.device)
                for b in (b.planned() for b in box_list):
                    r = float(np.linalg.norm(np.asarray(b.size, float)[:2]) / 2) + reach + 0.05
                    c = torch.as_tensor(np.asarray(b.center, float)[:2], dtype=inner.dtype, device=inner.device)
                    near |= (inner[:, :2] - c).norm(dim=-1) <= r
        hit = torch.zeros(len(inner), dtype=torch.bool, device=inner.device)
        # knots checked before: their cached robot bounds must overlap a box's bounds, else no kinematics is needed
        bounds = self.knots.knot_aabb(edges)[:, 1:-1].reshape(-1, 6)
        known = ~torch.isnan(bounds[:, 0])
        bt = boxes if isinstance(boxes, BoxTensors) else self.ctx.checker.box_tensors(list(boxes))
        if len(bt):
            bb = bt.aabb().to(bounds.dtype)
            overlap = ((bounds[:, None, :3] <= bb[None, :, 3:]) & (bounds[:, None, 3:] >= bb[None, :, :3])).all(-1)
            near &= ~known | overlap.any(-1)
        else:
            near &= False
        idx = torch.nonzero(near & known, as_tuple=True)[0]
        if len(idx):
            hit[idx] = self.ctx.checker.env_hits(inner[idx], bt)
        idx = torch.nonzero(near & ~known, as_tuple=True)[0]
        if len(idx):
            hit[idx], aabb = self.ctx.checker.env_hits(inner[idx], bt, return_aabb=True)
            e_pos = (idx // (M - 2)).cpu().numpy()
            self.knots.put_aabb(np.asarray(edges, dtype=np.int64)[e_pos], (idx % (M - 2)).cpu().numpy() + 1, aabb)
        return hit.reshape(E, M - 2).any(-1).cpu().numpy()

    @large_batches
    def invalidate_near(self, boxes: Sequence, old_boxes: Sequence = (), margin: float = 0.05) -> dict:
        """Obstacle update (after :meth:`set_scene`): re-check only what the moved ``boxes`` (new poses) can touch.

        Roadmap nodes whose base lies within reach of a box are checked against the moved boxes and blocked (removed
        from the graph) when in collision; edges whose base segment passes within reach have their stored knots
        checked in one batch (blocked when in collision) and are marked unchecked, so a search re-checks their dense
        interior before using them (Lazy PRM). Only the moved boxes are tested: everything else about a node or edge
        that was valid before is unchanged. Nodes and edges blocked earlier that lie near ``old_boxes`` (where an
        obstacle left) are restored, unchecked, when free at the current poses, so an obstacle moving through the
        roadmap does not erase it. A fixed-base robot re-checks everything.
        """
        g = self.rm.graph
        restored = self.restore_unblocked(old_boxes, margin) if old_boxes else {"restored_nodes": 0,
                                                                                "restored_edges": 0}
        nodes, edges = self.near(boxes, margin)
        nodes = nodes[g.node_valid[nodes]]
        removed = np.zeros(0, dtype=np.int64)
        if len(nodes):
            removed = nodes[self.ctx.checker.env_hits(self.ctx.t(g.configs[nodes]), list(boxes)).cpu().numpy()]
            if len(removed):
                gone = g.remove_nodes(removed)
                self.rm.blocked_nodes.update(removed.tolist())
                self.rm.blocked_edges.update(gone.tolist())
        edges = edges[g.edge_valid[edges]] if len(edges) else edges
        # one batched check of the near edges' stored knots prunes most newly blocked edges at once (a lazy search
        # would otherwise discover them one path at a time); the dense pieces between knots are checked lazily
        pruned = 0
        have = edges[self.knots.known(edges)]
        if len(have):
            bad = self.knots_hit(have, list(boxes))
            if bad.any():
                g.remove_edges(have[bad])
                self.rm.blocked_edges.update(have[bad].tolist())
                pruned = int(bad.sum())
            edges = edges[g.edge_valid[edges]]
        self.mark_recheck(edges)
        return {"checked_nodes": int(len(nodes)), "removed_nodes": int(len(removed)), "pruned_edges": pruned,
                "unchecked_edges": int(len(edges)), **restored}

    def mark_recheck(self, edges: np.ndarray) -> None:
        """Edges to re-check densely before use because an obstacle moved near them."""
        g = self.rm.graph
        g.edge_attribute("checked")[edges] = 0.0
        if len(self.rm.recheck) < g.n_edges:
            self.rm.recheck = np.concatenate([self.rm.recheck, np.zeros(g.n_edges - len(self.rm.recheck), dtype=bool)])
        self.rm.recheck[edges] = True

    def restore_unblocked(self, old_boxes: Sequence, margin: float = 0.05) -> dict:
        """Give back the blocked nodes and edges near where obstacles were (``old_boxes``) that are free of every
        current obstacle (edges come back unchecked: their dense interior is re-checked lazily)."""
        g = self.rm.graph
        back_n = back_e = 0
        if not (self.rm.blocked_nodes or self.rm.blocked_edges):
            return {"restored_nodes": 0, "restored_edges": 0}
        near_n, near_e = self.near(old_boxes, margin)
        boxes = self.ctx.scene.collision_boxes()  # the poses the checker holds (set_scene)
        nodes = np.asarray(sorted(self.rm.blocked_nodes.intersection(near_n.tolist())), dtype=np.int64)
        if len(nodes):
            free = nodes[~self.ctx.checker.env_hits(self.ctx.t(g.configs[nodes]), boxes).cpu().numpy()]
            if len(free):
                g.restore_nodes(free)
                self.rm.blocked_nodes.difference_update(free.tolist())
                back_n = len(free)
        e = np.asarray(sorted(self.rm.blocked_edges.intersection(near_e.tolist())), dtype=np.int64)
        if len(e):
            e = e[g.node_valid[g.edge_u[e]] & g.node_valid[g.edge_v[e]] & ~g.edge_valid[e]]
            e = e[self.knots.known(e)]
            if len(e):
                free = e[~self.knots_hit(e, boxes)]
                if len(free):
                    got = g.restore_edges(free)
                    self.rm.blocked_edges.difference_update(got.tolist())
                    self.mark_recheck(got)
                    back_e = len(got)
        return {"restored_nodes": int(back_n), "restored_edges": int(back_e)}
