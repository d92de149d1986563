"""Recovery of a query that reaches no goal: the escape search (a bounded RRT of differential-drive motions from a
boxed-in end to the roadmap) and the local roadmap repair."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np
import torch

from ..results import EscapeResult, Failure, PlanResult
from ..roadmap.knots import no_knots
from ..state import NP_DTYPE, PlannerContext, large_batches

if TYPE_CHECKING:
    from ..roadmap.builder import Builder
    from ..roadmap.edges import Edges
    from ..roadmap.roadmap_state import RoadmapState
    from . import Query

log = logging.getLogger(__name__)

ESCAPE_BATCH = 32  # random extensions per round of the escape search
ESCAPE_CONNECT = 32  # connections to the roadmap an escape round checks at most (the shortest)
ESCAPE_LONG = 4  # the escape search's long extensions, in steps
ESCAPE_STUCK_ROUNDS = 16  # escape rounds after which an end with no free motion out of it is given up
ESCAPE_MANOEUVRES = 8  # of the ESCAPE_BATCH extensions per round: drive/back-up/turn manoeuvres from tree nodes
ESCAPE_KEEP = 4  # connections to the roadmap (and their tree branches) an escape search keeps


def _ends(start, goals, dof: int) -> list:
    """The ends a recovery works on: the start and up to four goals."""
    return [np.asarray(start, float).reshape(-1)] + list(np.asarray(goals, float).reshape(-1, dof))[:4]


START_FIX_RINGS = (0.125, 0.25, 0.5, 1.0)  # rings of the start fix, as fractions of recovery.start_fix_radius
START_FIX_TRY = 8  # nearest padded-free offsets of a ring whose motion from the start is checked


class Recovery:
    """Escape search and local roadmap repair for unreachable query ends, and the start fix."""

    def __init__(self, ctx: PlannerContext, rm: RoadmapState, builder: Builder, edges: Edges, query: Query):
        self.ctx = ctx
        self.rm = rm
        self.builder = builder
        self.edges = edges
        self.query = query

    def move_out(self, start: np.ndarray) -> Optional[tuple]:
        """The start fix: a configuration near ``start`` that keeps the planner's collision padding, and the motion
        to it. For a start inside the padding (``edges.collision_padding``) but clear of the obstacles themselves:
        a robot that tracked its last path a little off, next to a shelf (MoveIt's planning-request adapter
        *FixStartStateCollision* samples such a nearby state the same way).

        Random offsets of ``start`` in rings of growing size (:data:`START_FIX_RINGS` x ``start_fix_radius``: m for
        the base and prismatic joints, rad for revolute ones; ``start_fix_samples`` per ring, within the joint
        limits) are checked against the padded boxes; of the free ones, the nearest (motion distance) whose local
        motion from ``start`` (untracked knots, :meth:`~.edges.Edges.edge_knots`) is free of the *unpadded* boxes,
        densely at ``edge_resolution`` (:meth:`~.edges.Edges.knots_valid` with ``check_unpadded``), is returned as
        ``(q (dof,), knots (1, M, dof), interior (1, N))``: the knots are what the robot executes. None when no ring
        has one (or the fix is off: radius 0)."""
        rc, ck = self.ctx.settings.recovery, self.ctx.checker
        if rc.start_fix_radius <= 0:
            return None
        dof = self.ctx.robot.dof
        q0 = np.asarray(start, float).reshape(dof)
        lo, hi = ck.lower.cpu().numpy().astype(float), ck.upper.cpu().numpy().astype(float)
        rng = np.random.default_rng([self.ctx.settings.seed, 11])
        a = self.ctx.t(q0[None])
        npd = NP_DTYPE[self.ctx.dtype]
        for frac in START_FIX_RINGS:
            r = frac * rc.start_fix_radius
            d = rng.normal(size=(rc.start_fix_samples, dof))
            d *= (r * rng.uniform(0.5, 1.0, size=(len(d), 1))) / np.linalg.norm(d, axis=1, keepdims=True)
            cand = np.clip(q0 + d, lo, hi)
            free = ~ck.check(self.ctx.t(cand)).cpu().numpy()
            if not free.any():
                continue
            cand = cand[free].astype(npd)
            dist = self.edges.motion_distance(np.repeat(q0[None].astype(npd), len(cand), 0), cand)
            pick = cand[np.argsort(dist, kind="stable")[:START_FIX_TRY]]
            b = self.ctx.t(pick)
            knots, interior = self.edges.edge_knots(a.expand(len(b), -1), b, track=False)
            # the ends are free of the real boxes (the start touches none, the picks keep the padding): the rest
            ok = self.edges.knots_valid(knots, check=ck.check_unpadded)
            if ok.any():
                i = int(torch.nonzero(ok, as_tuple=True)[0][0])
                return pick[i], knots[i:i + 1], interior[i:i + 1]
        return None

    def escape_query(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool,
                     goal_costs: Optional[np.ndarray]) -> PlanResult:
        """The escape stage of :meth:`~.pipeline.Pipeline.plan`: an :meth:`escape` search from each end (start, up to 4
        goals) to the roadmap's largest component within ``query_escape_s`` in total, then the query with the found
        configurations and edges added. Ends with a direct connection need no tree (their connections are added)."""
        s = self.ctx.settings
        t0 = time.perf_counter()
        ends = _ends(start, goals, self.ctx.robot.dof)
        self.rm.compact()
        ids, lab = self.rm.components()
        if len(ids) == 0:
            return PlanResult(False, "goal not reachable on the roadmap (empty roadmap)", Failure.UNREACHABLE)
        targets = ids[lab == int(np.argmax(np.bincount(lab)))]
        q_end = self.ctx.t(np.stack(ends))
        bad = self.ctx.checker.check(q_end).cpu().numpy()
        self.rm.escapes += 1
        rng = np.random.default_rng([s.seed, self.rm.escapes, 7])
        # first the direct connections of every end (no tree), then the time is shared by the ends that need one
        escapes = {k: self.escape(q_end[k], targets, rng, 0.0) for k in range(len(ends)) if not bad[k]}
        order = [k for k, e in escapes.items() if not e.success]
        why = []
        for j, k in enumerate(order):
            left = s.recovery.query_escape_s - (time.perf_counter() - t0)
            deadline = time.perf_counter() + max(left, 0.0) / (len(order) - j)  # unused time goes to later ends
            esc = self.escape(q_end[k], targets, rng, deadline)
            escapes[k] = esc
            if not esc.success:
                name = "start" if k == 0 else (f"goal {k - 1}" if len(ends) > 2 else "goal")
                if esc.explored <= 1:
                    why.append(f"{name} is boxed in: no collision-free motion out of it was found "
                               f"({esc.tried} short motions tried in {esc.seconds:.2f} s)")
                else:
                    where = f", bases within {esc.base_reach:.2f} m of it" if self.ctx.robot.mobile else ""
                    why.append(f"{name}: the escape search found no way to the roadmap's largest component "
                               f"({esc.explored} configurations reached in {esc.seconds:.1f} s{where})")
        res = self.query.plan_once(start, goals, timing, goal_costs, untracked=s.recovery.query_untracked_fallback,
                                   escapes={k: e for k, e in escapes.items() if e.success})
        if res.success:
            n = sum(len(e.configs) for e in escapes.values())
            res.reason = f"ok after an escape search ({n} intermediate configurations)"
        elif why:  # the ends that could not get out say why the query fails
            res.reason = "; ".join(why)
            res.failure = Failure.START_BLOCKED if why[0].startswith("start") else Failure.GOAL_BLOCKED
        log.debug("escape search: %s", res.reason)
        return res

    @large_batches
    def escape(self, q0: torch.Tensor, targets: np.ndarray, rng: np.random.Generator,
               deadline: float) -> EscapeResult:
        """Bounded RRT-like escape search from a query end ``q0`` (dof,) to the roadmap nodes ``targets``.

        For ends the first query could not connect (a mobile manipulator boxed in between shelves, facing a wall,
        its arm over a shelf): a tree of collision-free local motions grows from the end. Each round draws
        ``ESCAPE_BATCH`` random configurations (the base within ``query_escape_radius`` of the end for half of them,
        within twice that for the others, so that the tree can follow a long aisle out; any heading; the
        other joints uniform within their limits or those of a nearby target node; some are target nodes
        themselves) and extends the nearest tree node towards each along the local motion (differential drive: turn
        in place, drive straight forwards or backwards, turn; the joints move at the same time, untracked), by
        ``query_escape_step`` and by ``ESCAPE_LONG`` times that (kept when free). ``ESCAPE_MANOEUVRES`` of them are
        manoeuvres from random tree nodes instead: drive or back up along the heading, or turn in place by 90 degrees,
        the other joints kept or moving towards the template pose, so that a robot in a dead end backs out and then
        turns. Extensions are kept when their end configuration and their motion are collision-free (the motion
        checked densely, as every edge). An end from which not one extension is free after ``ESCAPE_STUCK_ROUNDS``
        rounds is given up early (boxed in). Every new configuration tries a direct connection to its
        ``query_escape_connect_k`` nearest target nodes. The search stops at the first round with a free connection,
        at ``query_escape_nodes`` tree nodes or at ``deadline``; the branches leading to the found connections are
        kept, shortened greedily (:meth:`shortcut_branch`)."""
        s, r = self.ctx.settings, self.ctx.robot
        t0 = time.perf_counter()
        dof = r.dof
        if r.mobile:  # every tree configuration lies within the radius: farther nodes are beyond a connection
            xy = np.linalg.norm(self.rm.graph.configs[targets, :2] - q0[:2].cpu().numpy(), axis=1)
            targets = targets[xy <= 2 * s.recovery.query_escape_radius + 2 * s.roadmap.max_edge_length]
            if len(targets) == 0:
                return EscapeResult(q0[None][:0], [], no_knots(self.ctx), [], no_knots(self.ctx),
                                    seconds=time.perf_counter() - t0)
        rm_q = self.ctx.t(self.rm.graph.configs[targets])
        lo = np.where(np.isfinite(r.lower), r.lower, -np.pi)
        hi = np.where(np.isfinite(r.upper), r.upper, np.pi)
        if r.mobile:
            lo[:2], hi[:2] = self.ctx.scene.workspace[:, 0], self.ctx.scene.workspace[:, 1]
        parent = [-1]
        knots_of: list = [None]  # (knots, interior) of the edge parent -> node
        T = q0[None]
        tried = 0

        def connect(new_idx: np.ndarray) -> list:
            """Free connections (tree index, target index, knots, interior) of tree nodes ``new_idx``."""
            qn = T[torch.as_tensor(new_idx, device=self.ctx.device)]
            pool = torch.arange(len(rm_q), device=self.ctx.device)
            if r.mobile:  # the motion cost is at least the base's xy distance: farther nodes are no candidates
                pool = torch.nonzero((torch.cdist(qn[:, :2], rm_q[:, :2]) <= 2 * s.roadmap.max_edge_length).any(0),
                                     as_tuple=True)[0]
                if len(pool) == 0:
                    return []
            cand = pool[self.query.nearest_ids(qn, rm_q[pool], s.recovery.query_escape_connect_k).to(self.ctx.device)]
            kk = cand.shape[1]
            src = torch.arange(len(qn), device=self.ctx.device).repeat_interleave(kk)
            dst = cand.reshape(-1)
            qa, qb = qn[src], rm_q[dst]
            d = self.ctx.motion.distance(qa, qb)
            near = torch.nonzero(d <= 2 * s.roadmap.max_edge_length, as_tuple=True)[0]
            if len(near) == 0:
                return []
            if len(near) > ESCAPE_CONNECT:  # the shortest candidates of the round (the likeliest to be free)
                near = near[d[near].topk(ESCAPE_CONNECT, largest=False).indices]
            kn, ki = self.edges.edge_knots(qa[near], qb[near], track=False)
            ok = self.edges.knots_free(kn)
            out = []
            for j in torch.nonzero(ok, as_tuple=True)[0].tolist():
                i = int(near[j])
                out.append((int(new_idx[int(src[i])]), int(dst[i]), kn[j], ki[j]))
            return out

        found = connect(np.array([0]))
        near_t = np.zeros(0, dtype=np.int64)
        if r.mobile:
            near_t = np.nonzero(np.linalg.norm(self.rm.graph.configs[targets, :2] - q0[:2].cpu().numpy(), axis=1)
                                <= s.recovery.query_escape_radius)[0]
        rounds = 0
        while not found and len(parent) < s.recovery.query_escape_nodes and time.perf_counter() < deadline:
            if len(parent) == 1 and rounds >= ESCAPE_STUCK_ROUNDS:  # not one motion out of the end is free
                break
            rounds += 1
            B = ESCAPE_BATCH
            q = lo + rng.random((B, dof)) * (hi - lo)
            pick = near_t if len(near_t) else np.arange(len(targets))
            like = rng.choice(pick, B)  # configurations of nearby target nodes
            u = rng.random(B)
            q[u < 0.5, r.base_dof:] = self.rm.graph.configs[targets[like[u < 0.5]], r.base_dof:]
            if r.mobile:
                ang = rng.uniform(-np.pi, np.pi, B)
                rad = s.recovery.query_escape_radius * np.sqrt(rng.random(B)) * np.where(np.arange(B) % 2, 2.0, 1.0)
                q[:, :2] = q0[:2].cpu().numpy() + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
                q[:, 2] = rng.uniform(-np.pi, np.pi, B)
            goal_bias = u < 0.15
            q[goal_bias] = self.rm.graph.configs[targets[like[goal_bias]]]
            nn = self.query.nearest_ids(self.ctx.t(np.clip(q, lo, hi)), T, 1)[:, 0].cpu().numpy()
            if r.mobile:  # manoeuvres from random tree nodes: drive / back up along the heading, or turn in place,
                # the other joints kept or moving towards the template (a tucked, camera-ready pose)
                m = ESCAPE_MANOEUVRES
                src = rng.integers(0, len(parent), m)
                qm = T[torch.as_tensor(src, device=self.ctx.device)].cpu().numpy().astype(float)
                sign = rng.choice([-1.0, 1.0], m)
                drive = rng.random(m) < 0.5
                L = ESCAPE_LONG * s.recovery.query_escape_step
                qm[drive, 0] += sign[drive] * L * np.cos(qm[drive, 2])
                qm[drive, 1] += sign[drive] * L * np.sin(qm[drive, 2])
                qm[~drive, 2] = np.angle(np.exp(1j * (qm[~drive, 2] + sign[~drive] * np.pi / 2)))
                tuck = rng.random(m) < 0.5
                qm[tuck, r.base_dof:] = self.rm.template[r.base_dof:]
                q[-m:], nn[-m:] = qm, src
            q_rand = self.ctx.t(np.clip(q, lo, hi))
            nn = torch.as_tensor(nn, device=self.ctx.device)
            q_near = T[nn]
            d = self.ctx.motion.distance(q_near, q_rand).clamp_min(1e-9)
            # a short and a long extension of each (the long one, ESCAPE_LONG steps, is kept where it is free: the
            # tree follows an open aisle in few steps)
            frac = torch.cat([(s.recovery.query_escape_step / d).clamp(max=1.0),
                              (ESCAPE_LONG * s.recovery.query_escape_step / d).clamp(max=1.0)])
            q_from = torch.cat([q_near, q_near])
            q_new = self.ctx.motion.interpolate(q_from, torch.cat([q_rand, q_rand]), frac)
            tried += B
            ok = self.ctx.checker.valid(q_new)
            if not ok.any():
                continue
            sel = torch.nonzero(ok, as_tuple=True)[0]
            kn, ki = self.edges.edge_knots(q_from[sel], q_new[sel], track=False)
            free = self.edges.knots_free(kn)
            okf = torch.zeros(2 * B, dtype=torch.bool, device=self.ctx.device)
            okf[sel[free]] = True
            use_long = okf[B:] & (frac[B:] > frac[:B])
            pick = torch.nonzero(use_long | okf[:B], as_tuple=True)[0]
            pick = torch.where(use_long[pick], pick + B, pick)
            if len(pick) == 0:
                continue
            row = {int(j): n for n, j in enumerate(sel.tolist())}
            first = len(parent)
            for j in pick.tolist():
                parent.append(int(nn[j % B]))
                knots_of.append((kn[row[j]], ki[row[j]]))
            T = torch.cat([T, q_new[pick]])
            found = connect(np.arange(first, len(parent)))
        seconds = time.perf_counter() - t0
        dof_zero = no_knots(self.ctx)
        reach = float((T[:, :2] - q0[:2]).norm(dim=-1).max()) if r.mobile else 0.0
        if not found:
            return EscapeResult(self.ctx.t(np.zeros((0, dof))), [], dof_zero, [], dof_zero, explored=len(parent),
                                tried=tried, seconds=seconds, base_reach=reach)
        # keep the branches to the (at most ESCAPE_KEEP) found connections, shortened
        found = found[:ESCAPE_KEEP]
        keep_nodes, tree_edges = {}, {}
        for a, _, _, _ in found:
            chain = [a]
            while parent[chain[-1]] >= 0:
                chain.append(parent[chain[-1]])
            chain = chain[::-1]  # root ... a
            for i, j, kn, ki in self.shortcut_branch(T, chain, knots_of):
                tree_edges[(i, j)] = (kn, ki)
                keep_nodes.update({i: None, j: None})
        keep_nodes.pop(0, None)
        remap = {old: n for n, old in enumerate(sorted(keep_nodes))}
        remap[0] = -1
        configs = T[torch.as_tensor(sorted(keep_nodes), dtype=torch.long, device=self.ctx.device)] if keep_nodes \
            else T[:0]
        tree = [(remap[i], remap[j]) for i, j in tree_edges]
        conn = [(remap[a], int(targets[b])) for a, b, _, _ in found]

        def stack(items):
            if not items:
                return dof_zero
            return torch.stack([k for k, _ in items]), torch.stack([i for _, i in items])

        return EscapeResult(configs, tree, stack(list(tree_edges.values())), conn,
                            stack([(kn, ki) for _, _, kn, ki in found]), explored=len(parent), tried=tried,
                            seconds=time.perf_counter() - t0, base_reach=reach)

    def shortcut_branch(self, T: torch.Tensor, chain: list, knots_of: list) -> list:
        """Greedy shortcut of a tree branch ``chain`` (tree indices, root first): from each kept node, the farthest
        later node of the branch reachable by one collision-free untracked local motion (checked densely; all
        candidates of a node in one batch). Returns the kept edges (i, j, knots, interior), i -> j along the branch."""
        out, i = [], 0
        while i < len(chain) - 1:
            later = list(range(i + 2, len(chain)))
            j = i + 1
            if later:
                qa = T[chain[i]][None].expand(len(later), -1)
                qb = T[torch.as_tensor([chain[x] for x in later], device=self.ctx.device)]
                kn, ki = self.edges.edge_knots(qa, qb, track=False)
                ok = torch.nonzero(self.edges.knots_free(kn), as_tuple=True)[0]
                if len(ok):
                    m = int(ok.max())
                    j = later[m]
                    out.append((chain[i], chain[j], kn[m], ki[m]))
                    i = j
                    continue
            kn, ki = knots_of[chain[j]]
            out.append((chain[i], chain[j], kn, ki))
            i = j
        return out


    def repair_query(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool,
                     goal_costs: Optional[np.ndarray], res: PlanResult) -> PlanResult:
        """The local roadmap repair of :meth:`~.pipeline.Pipeline.plan` after the failed query ``res``."""
        s = self.ctx.settings
        ends = _ends(start, goals, self.ctx.robot.dof)
        added, grown, again = 0, {}, None
        mobile = self.ctx.robot.mobile
        for r in range(max(1, s.recovery.query_repair_rounds)):
            if (s.recovery.query_repair_budget - self.rm.repair_added <= 0 or s.recovery.query_repair_nodes <= 0
                    or self.rm.repair_failed >= s.recovery.query_repair_failures):
                break
            self.rm.repairs += 1
            rng = np.random.default_rng([s.seed, self.rm.repairs])
            for k, q in enumerate(ends):
                n = min(s.recovery.query_repair_nodes, s.recovery.query_repair_budget - self.rm.repair_added)
                if n <= 0:
                    break
                out = self.builder.grow(n, center=q[:2] if mobile else None, radius=s.recovery.query_repair_radius * 1.5 ** r,
                                        rng=rng, timeout_s=1.0, heading=float(q[2]) if mobile else None)
                added += out["added_nodes"]
                self.rm.repair_added += out["added_nodes"]
                grown[k] = np.concatenate([grown.get(k, np.zeros(0, dtype=np.int64)), out["node_ids"]])
            # an end in a tight spot (a goal grazing a table, reachable only by turning one way) may have its few
            # valid edges beyond the connect_k nearest nodes; the nodes grown on its heading line are reachable by
            # driving straight but can rank far away under the motion metric (the camera joints re-aim on the way)
            again = self.query.plan_once(start, goals, timing, goal_costs, extra_candidates=grown,
                                         connect_k=max(s.query.connect_k, s.recovery.query_repair_connect_k))
            if again.success or again.failure is not Failure.UNREACHABLE:
                break
        if again is None:
            return res
        if not again.success and grown:  # a failed repair leaves no trace (nor a used-up budget)
            ids = np.unique(np.concatenate(list(grown.values())))
            self.rm.compact()
            self.rm.graph.remove_nodes(ids)
            self.rm.repair_added -= added
            self.rm.repair_failed += 1
            self.rm.index = None
            added = 0
        if again.success:
            again.reason = f"ok after a local roadmap repair ({added} nodes)"
        log.debug("query repair: %d nodes grown, %s", added, again.reason)
        return again
