"""Roadmap construction (Alg. 1): sample nodes, connect neighbours, check and score edges, bridge components, and grow
the roadmap locally (repair); the one-time warm-up of the compiled kernels."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch

from ...kernels import edges
from ...kernels.compute import bulk
from ..search.graph import Roadmap
from ..search.graph_search import edge_perception, warm_up as warm_up_search
from ..state import PlannerContext, large_batches

if TYPE_CHECKING:
    from ..query.trajectory import Trajectory
    from ..search.heuristics import Heuristics
    from .edges import Edges
    from .knots import KnotStore
    from .neighbours import Neighbours
    from .roadmap_state import RoadmapState
    from .sampling import Sampling
    from .scoring import Scoring

log = logging.getLogger(__name__)


class Builder:
    """Builds and grows the roadmap."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, knots: KnotStore, sampling: Sampling,
                 neighbours: Neighbours, edges: Edges, scoring: Scoring, heuristics: Heuristics,
                 trajectory: Trajectory):
        self.ctx = ctx
        self.rm = rm
        self.knots = knots
        self.sampling = sampling
        self.neighbours = neighbours
        self.edges = edges
        self.scoring = scoring
        self.heuristics = heuristics
        self.trajectory = trajectory

    def build(self, template: Optional[np.ndarray] = None) -> dict:
        """Sample, project, connect and score the roadmap; returns build statistics.

        On the CPU the large batches of the build (projection, knot tracking, collision checks, FK and ray casting of
        Alg. 2) run the compiled kernels of :mod:`psprm_core.kernels.fastpath` in bulk, row chunks over
        ``torch.get_num_threads()`` threads; the surrogate's GEMMs stay in torch. The kernels are loaded (or, once
        per install, compiled) by :meth:`warm_up` first; that one-time start-up of the process is reported as
        ``warm_up_s`` and is not part of ``build_s``."""
        self.rm.template = self.ctx.robot.default_configuration() if template is None else np.asarray(template, float)
        warm = self.warm_up(score=False)
        with bulk():
            stats = self.build_roadmap(self.rm.template)
        stats["warm_up_s"] = warm
        return stats

    def build_roadmap(self, template: Optional[np.ndarray]) -> dict:
        """Alg. 1 (see :meth:`build`): uniform (and perception-biased) manifold nodes, their scores and Eq. 1's
        normalisation, neighbour edges checked and scored (Eq. 1, 2), the roadmap adopted, components bridged, the
        hop table. Returns the build statistics (``success`` False with a ``reason`` when too few nodes were found).
        """
        s = self.ctx.settings
        rng = np.random.default_rng(s.seed)
        torch.manual_seed(s.seed)
        template = self.ctx.robot.default_configuration() if template is None else np.asarray(template, float)
        self.rm.template = template
        t0 = time.perf_counter()
        nodes, tried = [], 0
        have = 0
        n_biased = int(round(s.roadmap.biased_share * s.roadmap.n_nodes))
        n_uniform = s.roadmap.n_nodes - n_biased
        while have < n_uniform:
            if time.perf_counter() - t0 > s.roadmap.build_timeout_s:
                log.warning("node sampling timed out with %d/%d nodes", have, s.roadmap.n_nodes)
                break
            q = self.sampling.manifold_samples(rng, template)
            tried += s.roadmap.sample_batch
            nodes.append(q)
            have += len(q)
        t_sample = time.perf_counter() - t0
        if have < 2:
            self.rm.stats = {"success": False, "reason": "could not sample configurations on the visibility manifold"}
            return self.rm.stats
        Q = torch.cat(nodes)[: n_uniform]
        t2 = time.perf_counter()
        node_scores = self.scoring.score_configs(Q)
        biased = {}
        if n_biased:
            t5 = time.perf_counter()
            Q, node_scores, biased = self.sampling.biased_nodes(Q, node_scores, n_biased, rng, template, t0)
            t_sample += time.perf_counter() - t5
        self.rm.score_scale = 1.0
        if s.scoring.normalize_scores:  # the normalised score of Eq. 1 (c_p in [0, 1]) is relative to this roadmap
            self.rm.score_scale = 1.0 / max(float(torch.quantile(node_scores.double(), 0.99)), 1e-3)
        t_score = time.perf_counter() - t2
        t1 = time.perf_counter()
        eu, ev, dist = self.neighbours.neighbours(Q, Q, s.roadmap.k_neighbors, exclude_self=True, k_long=s.roadmap.k_long, rng=rng)
        valid, p_edge, knots = self.edges.edges_valid(Q[eu], Q[ev], end_scores=(node_scores[eu], node_scores[ev]))
        eu, ev, dist, p_edge = eu[valid], ev[valid], dist[valid], p_edge[valid]
        if s.edges.lazy_edges:  # endpoints only for now; interiors are scored when a search first uses the edge
            norm = self.scoring.normalized
            p_edge = edge_perception(norm(node_scores[eu]), norm(node_scores[ev]))
        t_edges = time.perf_counter() - t1
        self.rm.max_motion = float(dist.max()) if len(dist) else 1.0
        c_m = (dist / self.rm.max_motion).clamp(0, 1)
        g = Roadmap(dof=self.ctx.robot.dof, node_capacity=len(Q) + 64, edge_capacity=len(eu) + 1024)
        g.add_nodes(Q.double().cpu().numpy())
        self.knots.clear()
        edge_ids = g.add_edges(eu.cpu().numpy(), ev.cpu().numpy(),
                               self.scoring.weight(p_edge, c_m).double().cpu().numpy(),
                               c_m=c_m.double().cpu().numpy(), c_p=p_edge.double().cpu().numpy(),
                               verified=np.full(len(eu), 0.0 if s.edges.lazy_edges else 1.0),
                               checked=np.full(len(eu), 0.0 if s.edges.lazy_collision else 1.0))
        self.rm.adopt(g, node_scores.double().cpu().numpy(), max_motion=self.rm.max_motion,
                      score_scale=self.rm.score_scale)
        self.edges.put_knots(edge_ids, eu.cpu().numpy(), *knots)
        t3 = time.perf_counter()
        expand = self.expand(rng) if s.roadmap.expand_rounds > 0 else {}
        t4 = time.perf_counter()
        self.heuristics.build_hop_table()
        if self.knots.data is not None:  # room for the queries' edges now: the first query does not copy the store
            self.knots.reserve(self.rm.graph.n_edges + 1)
        build_s = time.perf_counter() - t0
        self.rm.stats = {
            "success": True, "n_nodes": int(self.rm.n_roadmap_nodes), "n_edges": int(len(self.rm.roadmap_edge_ids())),
            "samples_tried": int(tried), "sample_s": t_sample, "edges_s": t_edges, "score_s": t_score,
            "hop_table_s": time.perf_counter() - t4, "build_s": build_s, "mean_node_score": float(node_scores.mean()),
            **biased,
            **({"expand_s": time.perf_counter() - t3, **expand} if expand else {}),
        }
        log.info("PS-PRM built: %s", self.rm.stats)
        return self.rm.stats

    def warm_up(self, score: bool = True) -> float:
        """Compile (first run after an install or a change of the kernels' source) or load from numba's disk cache
        every small-batch kernel a query uses (:mod:`psprm_core.kernels.fastpath`), on two template configurations, and
        the roadmap searches' kernels (:func:`~psprm_core.planning.search.graph_search.warm_up`), so that the first
        query does not pay for it; also times a three-knot path, which imports TOPP-RA (and matplotlib through it, about
        1.4 s) now rather than in the first plan. ``score=False`` leaves out the scorer (the build's own warm-up: it
        must not score views of its own, e.g. with the oracle). Returns the seconds it took."""
        c = self.ctx

        t0 = time.perf_counter()
        W = np.stack([self.rm.template] * 3)
        if c.robot.mobile:  # drive 0.2 m and 0.4 m straight ahead
            W[1:, :2] += np.outer([0.2, 0.4], [np.cos(W[0, 2]), np.sin(W[0, 2])])
        else:
            W[1:, -1] += (0.05, 0.1)
        try:
            self.trajectory.timed(W)
        except Exception as exc:  # the warm-up must never stop a build; the first plan then loads TOPP-RA itself
            log.debug("trajectory timing warm-up failed: %s", exc)
        warm_up_search()
        if not c.backend.compiled:
            return time.perf_counter() - t0
        q = c.t(np.stack([self.rm.template, self.rm.template]))
        qb = q.clone()
        qb[1, 0] += 0.1
        c.checker.check(q)
        c.checker.check_detailed(q)
        c.checker.robot_aabb(q)  # the env_hits kernel of obstacle moves
        args = edges.neural_args(c.scorer, c.dtype)
        if score or args is not None:  # a neural scorer is the surrogate (one compiled call), not a rendered view
            self.scoring.score_configs(q)
        kn, ki = self.edges.edge_knots(q, qb)  # a query's connection edges (one compiled call)
        seeds = c.compute.ops.edge_knot_seeds(c.motion, q, qb, c.settings.edges.n_interp)[0]
        self.edges.track_knots(seeds)  # step by step
        if args is not None:  # the lazy verification's compiled calls
            kit, both = c.edge_kit(), np.ones(2, bool)
            edges.check_score_knots(kit, args, kn, ki, both, both, 200)
            # a two-edge knot store of its own: edge 1's knots computed into it, both checked and scored
            batch = edges.EdgeBatch(np.arange(2), np.array([False, True]), q.double().numpy()[1:],
                                    qb.double().numpy()[1:], np.ones(1, bool), both, both)
            edges.verify_edges(kit, args, kn.numpy().copy(), ki.numpy().copy(), batch, 200)
        self.edges.pieces(q, qb, max_steps=200, include_start=False)
        c.motion.distance(q, qb)
        c.compute.ops.nearest(c.motion, q, qb, 1)
        return time.perf_counter() - t0

    def expand(self, rng: np.random.Generator) -> dict:
        """PRM expansion step: bridge disconnected components to the largest one. Each round, for the largest other
        components (``expand_components``, at least 3 nodes), ``expand_nodes`` manifold nodes are sampled (:meth:`grow`)
        with their base within reach of the gap: around the midpoint between the component's node nearest (base
        position) to the largest component and that nearest node. Narrow passages of the visibility manifold (a
        wrist camera that must look over shelves) leave a uniform roadmap in pieces; this is where samples help."""
        s = self.ctx.settings
        added, rounds = 0, 0
        for _ in range(s.roadmap.expand_rounds):
            ids, lab = self.rm.components()
            cnt = np.bincount(lab)
            main = int(np.argmax(cnt))
            others = [int(c) for c in np.argsort(-cnt, kind="stable") if c != main and cnt[c] >= 3]
            others = others[:s.roadmap.expand_components]
            if not others:
                break
            rounds += 1
            main_xy = self.ctx.t(self.rm.graph.configs[ids[lab == main], :2])
            for c in others:
                xy = self.ctx.t(self.rm.graph.configs[ids[lab == c], :2])
                d = torch.cdist(xy, main_xy)
                i = int(d.min(1).values.argmin())
                a, b = xy[i].cpu().numpy(), main_xy[int(d[i].argmin())].cpu().numpy()
                got = self.grow(s.roadmap.expand_nodes, center=(a + b) / 2, radius=float(np.linalg.norm(a - b)) / 2 + 0.3,
                                rng=rng)
                added += got["added_nodes"]
        ids, lab = self.rm.components()
        return {"expand_rounds": rounds, "expand_added_nodes": int(added),
                "largest_component": float(np.bincount(lab).max() / max(len(ids), 1))}

    @large_batches
    def grow(self, n: int, center: Optional[np.ndarray] = None, radius: float = 1.5,
             rng: Optional[np.random.Generator] = None, timeout_s: float = 2.0,
             heading: Optional[float] = None) -> dict:
        """Roadmap repair: add up to ``n`` collision-free manifold nodes (base within ``radius`` of ``center`` when
        given; with ``heading``, half of them on the line through ``center`` along that base heading and facing it,
        i.e. reachable by driving straight) and connect them to their neighbours among all roadmap nodes, as in
        :meth:`build`. Existing nodes are kept. Returns the number of nodes and edges added."""
        s, g = self.ctx.settings, self.rm.graph
        rng = rng or np.random.default_rng()
        t0 = time.perf_counter()
        got = []
        have = 0
        while have < n and time.perf_counter() - t0 < timeout_s:
            q = self.sampling.sample(max(4 * n, 256), rng, self.rm.template)
            if center is not None and self.ctx.robot.mobile:
                ang = rng.uniform(-np.pi, np.pi, len(q))
                rr = radius * np.sqrt(rng.random(len(q)))
                xy = np.asarray(center, float)[:2] + np.stack([rr * np.cos(ang), rr * np.sin(ang)], 1)
                h = 0
                if heading is not None:  # half on the heading line, facing along it
                    h = len(q) // 2
                    t = rng.uniform(-radius, radius, h)
                    xy[:h] = np.asarray(center, float)[:2] + t[:, None] * np.array([np.cos(heading), np.sin(heading)])
                    q[:h, 2] = heading
                q[:, :2] = self.ctx.t(xy)
                if h and len(self.ctx.track_cols):  # those keep their base pose: only the camera joints re-aim
                    qa, oka = self.ctx.constraint.project(q[:h], s.projection, self.ctx.lo, self.ctx.hi,
                                                          joints=self.ctx.track_cols)
                    qb, okb = self.ctx.constraint.project(q[h:], s.projection, self.ctx.lo, self.ctx.hi)
                    q, ok = torch.cat([qa, qb]), torch.cat([oka, okb])
                else:
                    q, ok = self.ctx.constraint.project(q, s.projection, self.ctx.lo, self.ctx.hi)
            else:
                q, ok = self.ctx.constraint.project(q, s.projection, self.ctx.lo, self.ctx.hi)
            q = q[ok]
            q = q[self.ctx.checker.valid(q)]
            got.append(q)
            have += len(q)
        if have == 0:
            return {"added_nodes": 0, "added_edges": 0, "node_ids": np.zeros(0, dtype=np.int64)}
        Qn = torch.cat(got)[:n]
        old_ids = self.rm.roadmap_node_ids()
        new_ids = g.add_nodes(Qn.double().cpu().numpy())
        mask = self.rm.roadmap_mask()
        mask[new_ids] = True
        self.rm.is_roadmap = mask
        scores = self.rm.node_score_slots()
        scores[new_ids] = self.scoring.score_configs(Qn).double().cpu().numpy()
        all_ids = np.concatenate([old_ids, new_ids])
        Qall = self.ctx.t(g.configs[all_ids])
        eu, ev, dist = self.neighbours.neighbours(Qn, Qall, s.roadmap.k_neighbors, k_long=s.roadmap.k_long, rng=rng)
        u_ids, v_ids = new_ids[eu.cpu().numpy()], all_ids[ev.cpu().numpy()]
        keep = u_ids != v_ids
        eu, ev, dist, u_ids, v_ids = eu[keep], ev[keep], dist[keep], u_ids[keep], v_ids[keep]
        pairs = set()
        sel = []
        for i, (a, b) in enumerate(zip(u_ids.tolist(), v_ids.tolist())):  # unique undirected, not already joined
            k = (min(a, b), max(a, b))
            if k not in pairs and g.edge_id(a, b) is None:
                pairs.add(k)
                sel.append(i)
        sel = np.asarray(sel, dtype=np.int64)
        added = 0
        if len(sel):
            qa, qb = Qn[eu[sel]], Qall[ev[sel]]
            valid, p_edge, knots = self.edges.edges_valid(qa, qb)  # old nodes' scores may predate a scene change
            if s.edges.lazy_edges:
                sc = self.ctx.t(scores)
                norm = self.scoring.normalized
                p_edge = edge_perception(norm(sc[u_ids[sel]]), norm(sc[v_ids[sel]]))
            v = valid.cpu().numpy()
            c_m = dist[sel] / self.rm.max_motion
            c_m = (c_m.clamp(0, 1) if s.scoring.objective == "eq2" else c_m)[valid]
            p_edge = p_edge[valid]
            eids = g.add_edges(u_ids[sel][v], v_ids[sel][v],
                               self.scoring.weight(p_edge, c_m).double().cpu().numpy(),
                               c_m=c_m.double().cpu().numpy(), c_p=p_edge.double().cpu().numpy(),
                               verified=np.full(int(v.sum()), 0.0 if s.edges.lazy_edges else 1.0),
                               checked=np.full(int(v.sum()), 0.0 if s.edges.lazy_collision else 1.0))
            self.edges.put_knots(eids, u_ids[sel][v], *knots)
            added = int(v.sum())
        self.rm.index = None
        return {"added_nodes": int(len(new_ids)), "added_edges": added, "grow_ms": (time.perf_counter() - t0) * 1e3,
                "node_ids": np.asarray(new_ids, dtype=np.int64)}
