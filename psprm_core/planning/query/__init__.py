"""A query: connect start and goals to the roadmap (the connect_k nearest nodes under the motion metric, checked and
scored like roadmap edges), search (A* or lazy A*), then the recovery stages when no goal is reachable."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Optional, Protocol, Sequence

import numpy as np
import torch

from ...errors import InputError
from ..results import Failure, PlanResult
from ..search.graph_search import astar, edge_perception, lazy_astar, min_edge_cost
from ..state import NP_DTYPE, PlannerContext, QueryContext, ReadsQuerySettings

if TYPE_CHECKING:
    from ..roadmap.edges import Edges
    from ..roadmap.roadmap_state import RoadmapState
    from ..roadmap.scoring import Scoring
    from ..roadmap.verification import Verification
    from ..search.heuristics import Heuristics
    from .shortcut import Shortcut
    from .trajectory import Trajectory


COMPACT_EVERY = 64  # queries between removals of retired query nodes/edges (each removal rebuilds the adjacency)
QUERY_FALLBACK_K = 3  # nearest roadmap nodes a start/goal with none within 2 max_edge_length is still tried with


class StartFix(Protocol):
    """What :class:`Query` uses of :class:`~.recovery.Recovery`: the start fix (:meth:`~.recovery.Recovery.move_out`)
    of a start inside the collision padding. A protocol, not the class: ``recovery`` imports this module."""

    def move_out(self, start: np.ndarray) -> Optional[tuple]: ...


class Query(ReadsQuerySettings):
    """Connects a query to the roadmap and searches it."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, qc: QueryContext, edges: Edges, scoring: Scoring,
                 heuristics: Heuristics, verify: Verification, shortcut: Shortcut, trajectory: Trajectory):
        self.ctx = ctx
        self.rm = rm
        self.qc = qc
        self.edges = edges
        self.scoring = scoring
        self.heuristics = heuristics
        self.verify = verify
        self.shortcut = shortcut
        self.trajectory = trajectory
        self.recovery: StartFix  # bound by bind_recovery: the recovery stage is made from this one

    def bind_recovery(self, recovery: StartFix) -> None:
        """The recovery stage (:class:`~.recovery.Recovery`), made from this one: its strategies search again
        through :meth:`plan_once`, and :meth:`plan_once` moves a start inside the collision padding out of it with
        the start fix. :class:`~.pipeline.Pipeline` binds it right after making both."""
        self.recovery = recovery

    def nearest_ids(self, qq: torch.Tensor, pool: torch.Tensor, k: int) -> torch.Tensor:
        """Indices (Q, k) of the ``k`` configurations of ``pool`` nearest to each of ``qq`` (motion metric)."""
        k = min(k, pool.shape[0])
        # the roadmap: its float64 copy is kept with it
        pool_f64 = self._roadmap_f64 if pool is self.rm.tensor_cache else None
        return self.ctx.backend.nearest(qq, pool, k, pool_f64)

    def _roadmap_f64(self) -> np.ndarray:
        """The roadmap tensor cache's configurations as float64 numpy (made when first needed)."""
        if self.rm.tensor_f64 is None:
            self.rm.tensor_f64 = self.rm.tensor_numpy.astype(np.float64)
        return self.rm.tensor_f64

    def plan_once(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True,
                  goal_costs: Optional[np.ndarray] = None, extra_candidates: Optional[dict] = None,
                  connect_k: Optional[int] = None, untracked: bool = False,
                  escapes: Optional[dict] = None) -> PlanResult:
        """One query: connect start and goals to the roadmap and search (no repair).

        ``connect_k`` (default: the setting): nearest roadmap nodes each end tries. ``extra_candidates``: roadmap node
        ids tried in addition, per end (key 0: the start, 1 + k: goal k). ``untracked``: a connection edge whose
        re-aimed knots collide is kept with its untracked knots when those are free
        (:meth:`~.verification.Verification.untracked_query_edges`). ``escapes``: per end (same keys), the
        :class:`EscapeResult` of the escape search, whose configurations and checked edges are added as query nodes and
        edges.

        ``goal_costs`` (G,), optional: a non-negative terminal cost added to the path cost (Eq. 2 units) of reaching
        each goal, so one search picks the goal minimising path cost + terminal cost (the replanner's goal hysteresis).
        The goals are joined to one virtual sink node by zero-length edges weighted c_min (Eq. 4) + terminal cost;
        the common c_min offset leaves the choice unchanged and keeps the hop heuristic informative. The returned
        ``cost`` is the path cost alone.
        """
        t0 = time.perf_counter()
        if self.rm.graph is None:
            return PlanResult(False, "roadmap not built", Failure.NOT_BUILT)
        start = np.asarray(start, float).reshape(-1)
        goals = np.asarray(goals, float).reshape(-1, self.ctx.robot.dof)
        # the query's small arrays stay numpy (rounded to the planner's dtype as torch would); only the batched
        # work (metric, collision, scores) goes through the tensor paths
        Q = np.vstack([start, goals]).astype(NP_DTYPE[self.ctx.dtype])
        if not np.isfinite(Q).all():
            return PlanResult(False, "start or goal contains NaN/inf", Failure.INVALID_INPUT)
        det = self.ctx.backend.check_detailed(Q)
        bad = det["limits"] | det["environment"] | det["self"]
        fix = origin = None
        if bad[0]:
            why = ", ".join(k for k in ("limits", "environment", "self") if det[k][0])
            pad = self.ctx.checker.padding
            if why != "environment" or not self.ctx.checker.keeps_margin or bool(self.ctx.checker.check_unpadded(self.ctx.t(Q[:1]))[0]):
                return PlanResult(False, f"start configuration invalid ({why})", Failure.START_BLOCKED)
            # inside the clearance kept from the obstacles, not touching them: the start fix moves it out first
            fix = self.recovery.move_out(Q[0])
            if fix is None:
                return PlanResult(False, f"start configuration within the collision padding ({pad:g} m) of an "
                                         f"obstacle or the sweep of a turning one, and no motion out of it was "
                                         f"found within "
                                         f"{self.ctx.settings.recovery.start_fix_radius:g} (start_fix_radius)",
                                  Failure.START_BLOCKED)
            origin, Q = Q[0].copy(), Q.copy()
            Q[0] = fix[0]
        if bad[1:].all():
            return PlanResult(False, "every goal configuration is in collision or outside the limits",
                              Failure.GOAL_BLOCKED)
        g = self.rm.graph
        added_nodes, added_edges = [], []
        try:
            self.qc.scorer_args = {}
            ids = g.add_nodes(Q.astype(np.float64))
            added_nodes = list(ids)
            s_id, goal_ids = int(ids[0]), [int(i) for i, b in zip(ids[1:], bad[1:].tolist()) if not b]
            rm_ids = self.rm.roadmap_node_ids()
            rm_q, rm_np = self.rm.tensor(rm_ids), self.rm.tensor_numpy
            # candidate edges of the start and every goal, plus start-goal, checked in one batch
            queries = [(0, s_id)] + [(1 + k, int(gid)) for k, gid in enumerate(ids[1:]) if int(gid) in goal_ids]
            qq = Q[[i for i, _ in queries]]
            # candidates: the connect_k nearest roadmap nodes under the motion metric itself (one batched evaluation;
            # the Euclidean embedding used for the roadmap's own neighbours can rank arm-heavy motions poorly)
            kk = min(connect_k or self.ctx.settings.query.connect_k, rm_q.shape[0])
            cand = self.nearest_ids(torch.from_numpy(qq).to(self.ctx.device), rm_q, kk).cpu().numpy()  # (Q, kk)
            src = np.repeat(np.arange(len(queries)), kk)
            dst = cand.reshape(-1)
            qend = np.asarray([q for _, q in queries], dtype=np.int64)
            # direct start -> goal motions last
            qa = np.concatenate([qq[src], np.repeat(Q[:1], len(goal_ids), 0)])
            qb = np.concatenate([rm_np[dst], g.configs[goal_ids].astype(Q.dtype).reshape(-1, Q.shape[1])])
            u_ids = np.concatenate([qend[src], np.full(len(goal_ids), s_id, dtype=np.int64)])
            v_ids = np.concatenate([rm_ids[dst], np.asarray(goal_ids, dtype=np.int64)])
            dist = self.edges.motion_distance(qa, qb)
            within = dist <= 2 * self.ctx.settings.roadmap.max_edge_length
            # a start or goal far from the manifold (e.g. the arm folded away) has no roadmap node within 2 delta:
            # it still gets its QUERY_FALLBACK_K nearest candidates (longer edges, checked like any other)
            cand_d = dist[: len(src)].reshape(len(queries), kk)
            lonely = ~within[: len(src)].reshape(len(queries), kk).any(1)
            if extra_candidates is not None:
                # a repaired query: the end sits where the roadmap is sparse (an aisle); a longer connection to one of
                # its connect_k nearest nodes is a candidate like any other (checked and scored the same way)
                within[:] = True
            elif lonely.any():
                nk = min(QUERY_FALLBACK_K, kk)
                pick = np.argsort(cand_d[lonely], axis=1, kind="stable")[:, :nk] + np.nonzero(lonely)[0][:, None] * kk
                within[pick.reshape(-1)] = True
            if extra_candidates:
                pos = {int(nid): i for i, nid in enumerate(rm_ids)}
                taken = set(zip(u_ids[: len(src)].tolist(), v_ids[: len(src)].tolist()))
                ex_q, ex_r = [], []
                for qi, (k, qid) in enumerate(queries):
                    for nid in np.asarray(extra_candidates.get(k, ()), dtype=np.int64).tolist():
                        if nid in pos and (qid, nid) not in taken:
                            ex_q.append(qi)
                            ex_r.append(pos[nid])
                            taken.add((qid, nid))
                if ex_q:
                    qa, qb = np.concatenate([qa, qq[ex_q]]), np.concatenate([qb, rm_np[ex_r]])
                    u_ids = np.concatenate([u_ids, qend[ex_q]])
                    v_ids = np.concatenate([v_ids, rm_ids[np.asarray(ex_r)]])
                    within = np.concatenate([within, np.ones(len(ex_q), dtype=bool)])
            near = np.nonzero(within)[0]
            ta, tb = torch.from_numpy(qa[near]).to(self.ctx.device), torch.from_numpy(qb[near]).to(self.ctx.device)
            if len(near) and self.ctx.settings.edges.lazy_collision:
                # Lazy PRM for the query edges too: endpoint estimate of Eq. 1 now, the dense collision check and the
                # interior scores only for the edges the search wants to use (usually one at each end)
                scores = self.rm.node_score_slots()
                scores[ids] = self.scoring.query_scores(Q)
                ua, vb = u_ids[near], v_ids[near]
                scale = self.rm.score_scale
                pe = edge_perception(np.clip(scores[ua] * scale, 0, 1), np.clip(scores[vb] * scale, 0, 1))
                eids = self.add_query_edges(ua, vb, pe.astype(Q.dtype), verified=False,
                                            dist=dist[near] if len(dist) == len(qa) else self.edges.motion_distance(
                                                 qa[near], qb[near]))  # extras: unknown
                added_edges.extend(eids)
                # the knots (re-aimed interior knots) of a candidate edge are computed when the search first
                # verifies it (usually one or two at each end): stored_knots() takes them from here
                self.qc.pending_knots = (np.asarray(eids, dtype=np.int64), ua, ta, tb)
                self.qc.pending_rows = {int(e): i for i, e in enumerate(eids)}
                pa, pb = qa[near], qb[near]
                self.qc.pending_np = ((pa, pb), ua, pa.astype(np.float64), pb.astype(np.float64))
            elif len(near):
                ok, pe, kn, ki = self.query_edges(ta, tb, untracked=untracked)
                okn = ok.cpu().numpy()
                if okn.any():
                    keep = near[okn]
                    ua = u_ids[keep]
                    eids = self.add_query_edges(ua, v_ids[keep], pe[ok].cpu().numpy(),
                                                dist=self.edges.motion_distance(qa[keep], qb[keep]))
                    self.edges.put_knots(np.asarray(eids), ua, kn[ok], ki[ok])
                    added_edges.extend(eids)
            search_start = s_id
            if fix is not None:  # the measured start, and its checked motion out of the padding to Q[0]
                search_start = self.add_start_fix(origin, s_id, fix, added_nodes, added_edges)
            if escapes:
                added_edges.extend(self.add_escapes(escapes, dict(queries), added_nodes))
            search_goals, sink_w = goal_ids, None
            if goal_costs is not None and len(goal_ids) > 1:
                tc = np.asarray(goal_costs, float).reshape(-1)
                if tc.shape != (len(goals),) or not (np.isfinite(tc).all() and (tc >= 0).all()):
                    raise InputError(f"goal_costs must be {len(goals)} finite non-negative values")
                sink = int(g.add_nodes(g.configs[goal_ids[0]][None])[0])
                added_nodes.append(sink)
                k_of = {int(n): k for k, n in enumerate(ids[1:])}
                c_min = min_edge_cost(g)
                sink_w = {gid: c_min + tc[k_of[gid]] for gid in goal_ids}
                se = g.add_edges(np.asarray(goal_ids), np.full(len(goal_ids), sink), np.asarray(list(sink_w.values())),
                                 c_m=0.0, c_p=np.nan, verified=1.0, checked=1.0)  # nothing to verify: no motion
                added_edges.extend(int(e) for e in se)
                search_goals = [sink]
            self.qc.untracked = bool(untracked)
            if not goal_ids:
                res = None
            else:
                heur = self.heuristics.name
                if heur == "distance":
                    heur = self.heuristics.distance(goal_ids, search_goals[0] if sink_w is not None else None)
                if self.ctx.settings.edges.lazy_edges or self.ctx.settings.edges.lazy_collision or self.rm.unverified:
                    hops = None
                    if isinstance(heur, str) and heur == "hop":
                        hops = self.heuristics.query_hops(search_goals, added_edges)
                    res = lazy_astar(g, search_start, search_goals, self.verify.verify_edges, heuristic=heur,
                                     apply_to_graph=True,
                                     hops=hops)
                else:
                    res = astar(g, search_start, search_goals, heuristic=heur)
            if res is None or not res.success:
                return PlanResult(False, "goal not reachable on the roadmap" if res is None else res.reason,
                                  Failure.UNREACHABLE if res is None else res.failure,
                                  query_ms=(time.perf_counter() - t0) * 1e3)
            path, cost, goal = res.path, res.cost, res.goal
            if sink_w is not None:  # drop the virtual sink and its terminal edge
                path, goal = path[:-1], path[-2]
                cost -= sink_w[goal]
            if self.qs.query.shortcut and len(path) > 2:
                path, cost = self.shortcut.shortcut_path(path, cost, added_edges)
            result = self.trajectory.finish(path, cost, timing)
            result.goal_index = int(np.nonzero(np.asarray(ids[1:]) == goal)[0][0])
            if fix is not None:
                result.reason = f"{result.reason} (after moving the start out of the collision padding)"
            result.query_ms = (time.perf_counter() - t0) * 1e3
            return result
        finally:
            self.qc.clear()
            # retire the query's nodes and edges: blocking the edges (weight inf) is a weight change, which keeps
            # the adjacency lists and the hop-distance caches; removal (a full rebuild) is batched in
            # RoadmapState.compact
            if added_edges:
                g.set_weights(np.asarray(added_edges), np.inf)
            self.rm.dead_edges.extend(int(e) for e in added_edges)
            self.rm.dead_nodes.extend(int(n) for n in added_nodes)
            if len(self.rm.dead_nodes) >= 2 * COMPACT_EVERY:
                self.rm.compact()

    def add_query_edges(self, ua: np.ndarray, vb: np.ndarray, p: np.ndarray, dist: np.ndarray,
                        verified: bool = True) -> list:
        """Add query edges ``ua`` -> ``vb`` with their Eq. 1 perception ``p`` (E,) and motion cost ``dist`` (E,), both
        numpy in the planner's dtype: validated and fully scored (``verified``), or unchecked with an endpoint
        estimate (verified lazily by the search). The Eq. 2 weight is computed in that dtype, as on the roadmap."""
        c_m = dist / np.asarray(self.rm.max_motion, dist.dtype)
        if self.qs.scoring.objective == "eq2":  # Eq. 2 keeps c_m in [0, 1]; the motion form's heuristic needs all
            c_m = np.clip(c_m, 0, 1)
        w = self.scoring.weight(p, c_m)
        return list(self.rm.graph.add_edges(np.asarray(ua), np.asarray(vb), w.astype(np.float64),
                                            c_m=c_m.astype(np.float64), c_p=p.astype(np.float64),
                                            verified=float(verified), checked=float(verified)))

    def query_edges(self, qa: torch.Tensor, qb: torch.Tensor, untracked: bool = False) -> tuple:
        """Validity and Eq. 1 perception of query edges (always scored in full, never lazily); with ``untracked``,
        edges whose re-aimed knots collide are tried with their untracked knots."""
        knots, interior = self.edges.query_knots(qa, qb)
        ok = self.edges.knots_valid(knots)
        if untracked and not bool(ok.all()):
            bad = torch.nonzero(~ok, as_tuple=True)[0]
            kp, ip = self.edges.edge_knots(qa[bad], qb[bad], track=False)
            free = self.edges.knots_valid(kp)
            if free.any():
                knots, interior = knots.clone(), interior.clone()
                knots[bad[free]], interior[bad[free]] = kp[free], ip[free]
                ok[bad[free]] = True
        p = torch.zeros(qa.shape[0], dtype=self.ctx.dtype, device=self.ctx.device)
        if ok.any():
            p[ok] = self.scoring.knots_perception(knots[ok], interior[ok])
        return ok, p, knots, interior

    def add_start_fix(self, origin: np.ndarray, fixed_node: int, fix: tuple, added_nodes: list,
                      added_edges: list) -> int:
        """Add the measured start ``origin`` as a query node with one edge to ``fixed_node`` (the start fix's
        configuration), carrying the fix's knots (checked against the unpadded obstacles: what the robot executes),
        scored with Eq. 1 like any other edge. Returns the node the search starts from."""
        g = self.rm.graph
        o = int(g.add_nodes(origin[None].astype(np.float64))[0])
        added_nodes.append(o)
        self.rm.node_score_slots()[o] = float(self.scoring.score_configs(self.ctx.t(origin[None]))[0])
        added_edges.extend(self.add_checked_edges(np.array([o]), np.array([fixed_node]), fix[1], fix[2]))
        return o

    def add_checked_edges(self, ua: np.ndarray, vb: np.ndarray, knots: torch.Tensor, interior: torch.Tensor) -> list:
        """Add query edges ``ua`` -> ``vb`` whose ``knots`` (E, M, dof) were checked by the caller: scored with Eq. 1
        on those knots, their motion cost from the knots' ends, verified, and the knots stored (what runs)."""
        p = self.scoring.knots_perception(knots, interior).cpu().numpy()
        d = self.edges.motion_distance(knots[:, 0].cpu().numpy(), knots[:, -1].cpu().numpy())
        new = self.add_query_edges(ua, vb, p, d, verified=True)
        self.edges.put_knots(np.asarray(new), ua, knots, interior)
        return new

    def add_escapes(self, escapes: dict, end_node: dict, added_nodes: list) -> list:
        """Add the escape searches' configurations (as query nodes, appended to ``added_nodes``) and their checked
        edges (scored with Eq. 1 on their stored untracked knots) to the graph; returns the new edge ids."""
        g = self.rm.graph
        eids = []
        for k, esc in escapes.items():
            if k not in end_node or not esc.success:
                continue
            nid = np.zeros(0, dtype=np.int64)
            if len(esc.configs):
                nid = np.asarray(g.add_nodes(esc.configs.double().cpu().numpy()), dtype=np.int64)
                added_nodes.extend(int(n) for n in nid)
                scores = self.rm.node_score_slots()
                scores[nid] = self.scoring.score_configs(esc.configs).double().cpu().numpy()

            def node(i):
                return end_node[k] if i < 0 else int(nid[i])

            for pairs, (kn, ki), rm_end in ((esc.tree, esc.tree_knots, False), (esc.conn, esc.conn_knots, True)):
                if not pairs:
                    continue
                ua = np.asarray([node(a) for a, _ in pairs])
                vb = np.asarray([b if rm_end else node(b) for _, b in pairs])
                eids.extend(self.add_checked_edges(ua, vb, kn, ki))
        return eids
