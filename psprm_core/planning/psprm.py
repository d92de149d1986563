"""PS-PRM: perception-score-guided probabilistic roadmap (paper Alg. 1, Eqs. 1-6).

Build:
  1. sample configurations (base uniform over the scene's workspace, joints uniform within limits), project them onto
     the visibility manifold h_M(q) = 0 (batched Gauss-Newton, :mod:`.constraints`), keep the converged,
     collision-free ones until ``n_nodes`` or the timeout;
  2. connect each node to its k nearest neighbours under the differential-drive metric (:mod:`psprm_core.motion`)
     within ``max_edge_length``; keep an edge when its local motion is collision-free and its interior keeps the
     target in the camera frustum (the edge stays near the manifold);
  3. score every node and the N interpolated configurations of every edge (batched FK -> scorer), and weight each edge
     c = 1 - alpha * c_p + (1 - alpha) * c_m  (Eq. 2) with c_p the Eq. 1 mean and c_m the motion cost normalised by the
     roadmap's longest edge.
Query: connect start and goal(s) to the roadmap, A* with the hop heuristic h = H_min * c_min (Eqs. 3-6), expand
the node path into differential-drive corners and time-parameterise it within the joint limits.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..collision import CollisionChecker
from ..errors import ConfigError
from ..motion import DiffDriveMotion
from ..robot import RobotModel
from ..scene import Scene
from ..yamlio import Fields, load_yaml
from .constraints import ProjectionSettings, VisibilityConstraint
from .graph import Roadmap
from .graph_search import astar, combined_weight, edge_perception

log = logging.getLogger(__name__)

VARIANTS = {
    "psprm-line": ("line", "oracle"),
    "psprm-frustum": ("frustum", "oracle"),
    "neural-psprm-line": ("line", "neural"),
    "neural-psprm-frustum": ("frustum", "neural"),
}


@dataclass(frozen=True)
class PSPRMSettings:
    """Settings of PS-PRM (``config/planners/psprm.yaml``). Defaults follow the paper where it says."""

    n_nodes: int = 3000
    k_neighbors: int = 15
    max_edge_length: float = 2.0  # motion-cost units (m + weighted rad)
    alpha: float = 0.8  # Eq. 2 (paper: 0.75 with the oracle, 0.8 with the surrogate)
    n_interp: int = 5  # N of Eq. 1
    constraint: str = "line"  # visibility model: line | frustum
    sample_joints: str = "camera"  # camera: sample only joints that move the camera (others at default) | all
    edge_resolution: float = 0.05  # collision-check spacing along edges (motion-cost units)
    edge_view_slack: float = 0.05  # interior configurations must keep the target centroid within the frustum
    connect_k: int = 25  # neighbours tried when connecting a start or goal
    sample_batch: int = 2048
    build_timeout_s: float = 120.0
    min_view_distance: float = 0.5
    frustum_margin: float = 0.05
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    seed: int = 0

    @classmethod
    def from_yaml(cls, path: str | Path, **overrides) -> "PSPRMSettings":
        f = Fields(load_yaml(path), str(path))
        names = [fl.name for fl in dataclasses.fields(cls)]
        f.check_keys(names)
        kw = {}
        for fl in dataclasses.fields(cls):
            if not f.has(fl.name):
                continue
            if fl.name == "projection":
                p = f.sub("projection")
                p.check_keys([x.name for x in dataclasses.fields(ProjectionSettings)])
                kw["projection"] = ProjectionSettings(**{k: p.float(k) if k != "max_iters" else p.int(k, lo=1)
                                                         for k in p.data})
            elif fl.type in ("int",) or isinstance(fl.default, int) and not isinstance(fl.default, bool):
                kw[fl.name] = f.int(fl.name, lo=0)
            elif isinstance(fl.default, float):
                kw[fl.name] = f.float(fl.name, lo=0.0)
            else:
                kw[fl.name] = f.str(fl.name)
        kw.update({k: v for k, v in overrides.items() if v is not None})
        s = cls(**kw)
        s.validate(str(path))
        return s

    def validate(self, source: str = "settings") -> None:
        if self.constraint not in ("line", "frustum"):
            raise ConfigError(source, "constraint", f"unknown visibility model '{self.constraint}' (line, frustum)")
        if self.sample_joints not in ("camera", "all"):
            raise ConfigError(source, "sample_joints", "must be 'camera' or 'all'")
        if not 0.0 <= self.alpha <= 1.0:
            raise ConfigError(source, "alpha", f"must lie in [0, 1], got {self.alpha}")
        if self.n_nodes < 2 or self.k_neighbors < 1:
            raise ConfigError(source, "n_nodes", "need at least 2 nodes and 1 neighbour")


@dataclass
class PlanResult:
    """Outcome of a query (``success`` False comes with a ``reason``; never an exception for bad problems)."""

    success: bool
    reason: str = "ok"
    path_nodes: list = field(default_factory=list)
    waypoints: Optional[np.ndarray] = None  # (M, dof) roadmap path incl. diff-drive corners
    dense: Optional[np.ndarray] = None  # (K, dof) configurations every ``edge_resolution`` along the path
    dense_scores: Optional[np.ndarray] = None  # planner's perception score along ``dense``
    trajectory: object = None  # timing.Trajectory
    cost: float = float("inf")
    path_length: float = float("nan")
    mean_score: float = float("nan")
    query_ms: float = float("nan")
    goal_index: int = -1

    def to_dict(self, joint_names: Sequence[str] | None = None) -> dict:
        d = {"success": self.success, "reason": self.reason, "cost": self.cost,
             "path_length_rad": self.path_length, "mean_perception_score": self.mean_score,
             "query_ms": self.query_ms, "goal_index": self.goal_index, "n_waypoints": 0}
        if self.waypoints is not None:
            d["n_waypoints"] = int(len(self.waypoints))
            d["waypoints"] = np.round(self.waypoints, 5).tolist()
            if joint_names is not None:
                d["joint_names"] = list(joint_names)
        if self.trajectory is not None:
            d["duration_s"] = float(self.trajectory.times[-1])
        return d


def camera_joint_mask(robot: RobotModel) -> np.ndarray:
    """Planning joints that move the camera (base joints included)."""
    chain, b = set(), robot.camera_body
    while b > 0:
        chain.add(b)
        b = robot.parent_body[b]
    mask = np.zeros(robot.dof, dtype=bool)
    mask[: robot.base_dof] = True
    for b in chain:
        mask |= robot.drive_matrix[:, b] != 0
    return mask


class PSPRM:
    """A PS-PRM planner for one robot, scene and target (or target set).

    Parameters
    ----------
    robot : RobotModel
    scene : Scene
    scorer : psprm_core.perception.scoring.Scorer
        Perception score of camera poses (neural, oracle, or any other).
    focus : (3,) array
        Point the visibility constraint keeps in view (the target's centroid, or the midpoint of several targets).
    settings : PSPRMSettings
    device : torch device for all batched work.
    """

    def __init__(self, robot: RobotModel, scene: Scene, scorer, focus, settings: PSPRMSettings = PSPRMSettings(),
                 device="cpu", checker: Optional[CollisionChecker] = None):
        settings.validate()
        self.robot, self.scene, self.scorer, self.settings = robot, scene, scorer, settings
        self.device = torch.device(device)
        self.dtype = torch.float32
        self.motion = DiffDriveMotion(robot)
        self.checker = checker or CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace,
                                                   device=self.device)
        self.constraint = VisibilityConstraint(robot, settings.constraint, focus, margin=settings.frustum_margin,
                                               min_distance=settings.min_view_distance)
        self.graph: Optional[Roadmap] = None
        self.node_scores: Optional[np.ndarray] = None
        self.stats: dict = {}
        self.max_motion = 1.0

    # ---- helpers -----------------------------------------------------------------------------------------------------
    def _t(self, a) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)

    def score_configs(self, q: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """Perception scores (B,) of configurations: FK -> camera poses -> scorer."""
        out = []
        for s in range(0, q.shape[0], chunk):
            qc = q[s:s + chunk]
            out.append(self.scorer.score(self.robot.camera_poses(qc)).to(self.dtype))
        return torch.cat(out) if out else torch.zeros(0, dtype=self.dtype, device=self.device)

    def _sample(self, n: int, rng: np.random.Generator, template: np.ndarray) -> torch.Tensor:
        r = self.robot
        lo, hi = r.lower.copy(), r.upper.copy()
        if r.mobile:
            lo[:2], hi[:2] = self.scene.workspace[:, 0], self.scene.workspace[:, 1]
            lo[2], hi[2] = -np.pi, np.pi
        lo = np.where(np.isfinite(lo), lo, -np.pi)
        hi = np.where(np.isfinite(hi), hi, np.pi)
        q = lo + rng.random((n, r.dof)) * (hi - lo)
        if self.settings.sample_joints == "camera":
            mask = camera_joint_mask(r)
            q[:, ~mask] = template[~mask]
        return self._t(q)

    # ---- build (Alg. 1) --------------------------------------------------------------------------------------------
    def build(self, template: Optional[np.ndarray] = None) -> dict:
        """Sample, project, connect and score the roadmap; returns build statistics."""
        s = self.settings
        rng = np.random.default_rng(s.seed)
        torch.manual_seed(s.seed)
        template = self.robot.default_configuration() if template is None else np.asarray(template, float)
        self.template = template
        t0 = time.perf_counter()
        nodes, tried = [], 0
        lo = self._t(np.where(np.isfinite(self.robot.lower), self.robot.lower, -1e9))
        hi = self._t(np.where(np.isfinite(self.robot.upper), self.robot.upper, 1e9))
        if self.robot.mobile:
            lo[:2], hi[:2] = self._t(self.scene.workspace[:, 0]), self._t(self.scene.workspace[:, 1])
        have = 0
        while have < s.n_nodes:
            if time.perf_counter() - t0 > s.build_timeout_s:
                log.warning("node sampling timed out with %d/%d nodes", have, s.n_nodes)
                break
            q = self._sample(s.sample_batch, rng, template)
            tried += len(q)
            q, ok = self.constraint.project(q, s.projection, lo, hi)
            q = q[ok]
            q = q[self.checker.valid(q)]
            nodes.append(q)
            have += len(q)
        t_sample = time.perf_counter() - t0
        if have < 2:
            self.stats = {"success": False, "reason": "could not sample configurations on the visibility manifold"}
            return self.stats
        Q = torch.cat(nodes)[: s.n_nodes]
        t1 = time.perf_counter()
        eu, ev, dist = self._neighbours(Q, Q, s.k_neighbors, exclude_self=True)
        valid = self._edges_valid(Q[eu], Q[ev])
        eu, ev, dist = eu[valid], ev[valid], dist[valid]
        t_edges = time.perf_counter() - t1
        t2 = time.perf_counter()
        node_scores = self.score_configs(Q)
        p_edge = self._edge_perception(Q[eu], Q[ev], node_scores[eu], node_scores[ev])
        t_score = time.perf_counter() - t2
        self.max_motion = float(dist.max()) if len(dist) else 1.0
        c_m = (dist / self.max_motion).clamp(0, 1)
        g = Roadmap(dof=self.robot.dof, node_capacity=len(Q) + 64, edge_capacity=len(eu) + 1024)
        g.add_nodes(Q.double().cpu().numpy())
        g.add_edges(eu.cpu().numpy(), ev.cpu().numpy(),
                    combined_weight(p_edge, c_m, s.alpha).double().cpu().numpy(),
                    c_m=c_m.double().cpu().numpy(), c_p=p_edge.double().cpu().numpy())
        self.graph = g
        self.node_scores = node_scores.double().cpu().numpy()
        self.n_roadmap_nodes = len(Q)
        build_s = time.perf_counter() - t0
        self.stats = {
            "success": True, "n_nodes": int(len(Q)), "n_edges": int(len(eu)), "samples_tried": int(tried),
            "sample_s": t_sample, "edges_s": t_edges, "score_s": t_score, "build_s": build_s,
            "mean_node_score": float(node_scores.mean()),
        }
        log.info("PS-PRM built: %s", self.stats)
        return self.stats

    def _embed(self, q: torch.Tensor) -> torch.Tensor:
        if not self.robot.mobile:
            return q
        w = self.motion.w_rot
        return torch.cat([q[:, :2], w * torch.cos(q[:, 2:3]), w * torch.sin(q[:, 2:3]), q[:, 3:]], -1)

    def _neighbours(self, A: torch.Tensor, B: torch.Tensor, k: int, exclude_self: bool = False) -> tuple:
        """k nearest nodes of B for each row of A under the motion metric (candidates from a Euclidean embedding).
        Returns unique undirected pairs (u in A, v in B) and their motion costs."""
        ea, eb = self._embed(A), self._embed(B)
        kk = min(2 * k + (1 if exclude_self else 0), B.shape[0])
        rows, cols = [], []
        for s in range(0, A.shape[0], 2048):
            d = torch.cdist(ea[s:s + 2048], eb)
            idx = d.topk(kk, largest=False).indices
            rows.append(torch.arange(s, s + idx.shape[0], device=A.device).repeat_interleave(kk))
            cols.append(idx.reshape(-1))
        u, v = torch.cat(rows), torch.cat(cols)
        if exclude_self:
            keep = u != v
            u, v = u[keep], v[keep]
        dist = self.motion.distance(A[u], B[v])
        # keep the k best by the true metric per row, within the connection radius
        order = torch.argsort(u * (dist.max() + 1) + dist)
        u, v, dist = u[order], v[order], dist[order]
        first = torch.ones_like(u, dtype=torch.bool)
        rank = torch.arange(len(u), device=u.device) - torch.searchsorted(u, u, right=False)
        keep = (rank < k) & (dist <= self.settings.max_edge_length) & first
        u, v, dist = u[keep], v[keep], dist[keep]
        if exclude_self:  # undirected, unique
            a, b = torch.minimum(u, v), torch.maximum(u, v)
            key = torch.unique(a * B.shape[0] + b)
            u, v = key // B.shape[0], key % B.shape[0]
            dist = self.motion.distance(A[u], B[v])
        return u, v, dist

    def _edges_valid(self, qa: torch.Tensor, qb: torch.Tensor) -> torch.Tensor:
        """Collision-free local motion whose N interior configurations keep the target in view."""
        ok = torch.ones(qa.shape[0], dtype=torch.bool, device=self.device)
        n = self.settings.n_interp
        if n > 0 and qa.shape[0]:
            s = torch.arange(1, n + 1, dtype=self.dtype, device=self.device) / (n + 1)
            qi = self.motion.interpolate(qa.repeat_interleave(n, 0), qb.repeat_interleave(n, 0), s.repeat(qa.shape[0]))
            view = self.constraint.in_view(qi, slack=self.settings.edge_view_slack).reshape(-1, n).all(-1)
            ok &= view
        idx = torch.nonzero(ok, as_tuple=True)[0]
        if len(idx):
            ok[idx] = self.motion.motion_valid(self.checker, qa[idx], qb[idx], self.settings.edge_resolution)
        return ok

    def _edge_perception(self, qa, qb, sa, sb) -> torch.Tensor:
        """Eq. 1: mean score of both ends and the N interpolated configurations."""
        n = self.settings.n_interp
        if n == 0 or qa.shape[0] == 0:
            return edge_perception(sa, sb)
        s = torch.arange(1, n + 1, dtype=self.dtype, device=self.device) / (n + 1)
        qi = self.motion.interpolate(qa.repeat_interleave(n, 0), qb.repeat_interleave(n, 0), s.repeat(qa.shape[0]))
        return edge_perception(sa, sb, self.score_configs(qi).reshape(-1, n))

    # ---- query -----------------------------------------------------------------------------------------------------
    def set_alpha(self, alpha: float) -> None:
        """Re-weight every edge with a new alpha (Eq. 2) without rebuilding (alpha = 0: shortest-path PRM)."""
        g = self.graph
        ids = g.valid_edge_ids()
        w = combined_weight(g.edge_attribute("c_p")[ids], g.edge_attribute("c_m")[ids], alpha)
        g.set_weights(ids, w)
        self.settings = dataclasses.replace(self.settings, alpha=alpha)

    def plan(self, start: np.ndarray, goals: Sequence[np.ndarray] | np.ndarray, timing: bool = True) -> PlanResult:
        """Plan from ``start`` to the cheapest of ``goals`` (one configuration (dof,) or several (G, dof))."""
        t0 = time.perf_counter()
        if self.graph is None:
            return PlanResult(False, "roadmap not built")
        start = np.asarray(start, float).reshape(-1)
        goals = np.asarray(goals, float).reshape(-1, self.robot.dof)
        qs = self._t(np.vstack([start, goals]))
        if not torch.isfinite(qs).all():
            return PlanResult(False, "start or goal contains NaN/inf")
        det = self.checker.check_detailed(qs)
        bad = det["limits"] | det["environment"] | det["self"]
        if bool(bad[0]):
            why = ", ".join(k for k in ("limits", "environment", "self") if bool(det[k][0]))
            return PlanResult(False, f"start configuration invalid ({why})")
        if bool(bad[1:].all()):
            return PlanResult(False, "every goal configuration is in collision or outside the limits")
        g = self.graph
        added_nodes, added_edges = [], []
        try:
            ids = g.add_nodes(qs.double().cpu().numpy())
            added_nodes = list(ids)
            s_id, goal_ids = int(ids[0]), [int(i) for i, b in zip(ids[1:], bad[1:].tolist()) if not b]
            rm = torch.as_tensor(g.configs[: self.n_roadmap_nodes][g.node_valid[: self.n_roadmap_nodes]],
                                 dtype=self.dtype, device=self.device)
            rm_ids = np.nonzero(g.node_valid[: self.n_roadmap_nodes])[0]
            scores_new = self.score_configs(qs)
            for qi, nid in [(0, s_id)] + [(1 + k, gid) for k, gid in enumerate(ids[1:]) if int(gid) in goal_ids]:
                e = self._connect(qs[qi:qi + 1], int(nid), rm, rm_ids, float(scores_new[qi]))
                added_edges.extend(e)
            # a start that can reach a goal directly
            if goal_ids:
                qg = self._t(g.configs[goal_ids])
                qa = qs[0:1].expand(len(goal_ids), -1)
                d = self.motion.distance(qa, qg)
                near = d <= self.settings.max_edge_length
                if near.any():
                    idx = torch.nonzero(near, as_tuple=True)[0]
                    okm = self.motion.motion_valid(self.checker, qa[idx], qg[idx], self.settings.edge_resolution)
                    for j, okj in zip(idx.tolist(), okm.tolist()):
                        if okj:
                            added_edges.extend(self._add_query_edges(qa[j:j + 1], qg[j:j + 1],
                                                                     [s_id], [goal_ids[j]],
                                                                     scores_new[0:1], scores_new[1 + j:2 + j]))
            res = astar(g, s_id, goal_ids) if goal_ids else None
            if res is None or not res.success:
                return PlanResult(False, "goal not reachable on the roadmap" if res is None else res.reason,
                                  query_ms=(time.perf_counter() - t0) * 1e3)
            path = res.path
            result = self._finish(path, res.cost, timing)
            result.goal_index = int(np.nonzero(np.asarray(ids[1:]) == res.goal)[0][0])
            result.query_ms = (time.perf_counter() - t0) * 1e3
            return result
        finally:
            if added_edges:
                g.remove_edges(added_edges)
            if added_nodes:
                g.remove_nodes(added_nodes)

    def _add_query_edges(self, qa, qb, ua, vb, sa, sb) -> list:
        dist = self.motion.distance(qa, qb)
        p = self._edge_perception(qa, qb, sa, sb)
        c_m = (dist / self.max_motion).clamp(0, 1)
        w = combined_weight(p, c_m, self.settings.alpha)
        return list(self.graph.add_edges(np.asarray(ua), np.asarray(vb), w.double().cpu().numpy(),
                                         c_m=c_m.double().cpu().numpy(), c_p=p.double().cpu().numpy()))

    def _connect(self, q: torch.Tensor, nid: int, rm: torch.Tensor, rm_ids: np.ndarray, score: float) -> list:
        k = self.settings.connect_k
        d = self.motion.distance(q.expand(rm.shape[0], -1), rm)
        kk = min(k, rm.shape[0])
        cand = torch.topk(d, kk, largest=False).indices
        cand = cand[d[cand] <= 2 * self.settings.max_edge_length]
        if len(cand) == 0:
            return []
        qa = q.expand(len(cand), -1)
        ok = self.motion.motion_valid(self.checker, qa, rm[cand], self.settings.edge_resolution)
        cand = cand[ok]
        if len(cand) == 0:
            return []
        ns = torch.as_tensor(self.node_scores[rm_ids[cand.cpu().numpy()]], dtype=self.dtype, device=self.device)
        sa = torch.full((len(cand),), score, dtype=self.dtype, device=self.device)
        return self._add_query_edges(q.expand(len(cand), -1), rm[cand], [nid] * len(cand),
                                     rm_ids[cand.cpu().numpy()], sa, ns)

    def _finish(self, path: list, cost: float, timing: bool) -> PlanResult:
        g = self.graph
        Q = torch.as_tensor(g.configs[path], dtype=torch.float64)
        corners = [Q[0:1]]
        for a, b in zip(Q[:-1], Q[1:]):
            corners.append(self.motion.base_waypoints(a, b)[1:])
        W = torch.cat(corners)
        keep = torch.ones(len(W), dtype=torch.bool)
        keep[1:] = (W[1:] - W[:-1]).abs().max(-1).values > 1e-9
        W = W[keep]
        edge, s, dense = self.motion.dense(Q[:-1], Q[1:], self.settings.edge_resolution)
        dense = torch.cat([Q[0:1], dense, Q[-1:]]) if len(dense) else Q
        dense_scores = self.score_configs(dense.to(self.dtype)).double().cpu().numpy()
        length = float(self.motion.distance(Q[:-1], Q[1:]).sum()) if len(Q) > 1 else 0.0
        traj = None
        if timing and len(W) > 1:
            from .timing import time_parameterize

            r = self.robot
            traj = time_parameterize(
                W.numpy(), r.velocity, r.acceleration, dt=0.05, joint_names=r.joint_names,
                continuous_joints=[i for i in range(r.dof) if r.continuous[i]],
                base_indices=(0, 1, 2) if r.mobile else None,
                base_linear_limits=(r.config.base.linear_velocity, r.config.base.linear_acceleration)
                if r.mobile else None, method="analytic")
        return PlanResult(True, "ok", path_nodes=list(path), waypoints=W.numpy(), dense=dense.numpy(),
                          dense_scores=dense_scores, trajectory=traj, cost=float(cost), path_length=length,
                          mean_score=float(dense_scores.mean()))

    # ---- persistence -----------------------------------------------------------------------------------------------
    def fingerprint(self) -> str:
        """Hash of the robot, scene geometry, focus point and settings the roadmap was built for."""
        h = hashlib.sha256(self.robot.hash().encode())
        for b in self.scene.collision_boxes():
            h.update(np.concatenate([b.center, b.size, b.quat]).astype(np.float64).tobytes())
        h.update(self.constraint.target.numpy().tobytes())
        h.update(json.dumps(dataclasses.asdict(self.settings), sort_keys=True, default=str).encode())
        return h.hexdigest()[:20]

    def save(self, path: str | Path) -> Path:
        g = self.graph
        n, e = self.n_roadmap_nodes, g.valid_edge_ids()
        e = e[(g.edge_u[e] < n) & (g.edge_v[e] < n)]
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, configs=g.configs[:n], node_valid=g.node_valid[:n], eu=g.edge_u[e], ev=g.edge_v[e],
                            c_m=g.edge_attribute("c_m")[e], c_p=g.edge_attribute("c_p")[e],
                            node_scores=self.node_scores[:n], max_motion=self.max_motion,
                            fingerprint=self.fingerprint(), stats=json.dumps(self.stats))
        return path

    def load(self, path: str | Path, check: bool = True) -> None:
        data = np.load(path, allow_pickle=False)
        if check and str(data["fingerprint"]) != self.fingerprint():
            raise ConfigError(str(path), "fingerprint", "roadmap was built for another robot, scene or settings")
        g = Roadmap(dof=self.robot.dof, node_capacity=len(data["configs"]) + 64, edge_capacity=len(data["eu"]) + 1024)
        g.add_nodes(data["configs"])
        bad = np.nonzero(~data["node_valid"])[0]
        w = combined_weight(data["c_p"], data["c_m"], self.settings.alpha)
        g.add_edges(data["eu"], data["ev"], w, c_m=data["c_m"], c_p=data["c_p"])
        if len(bad):
            g.remove_nodes(bad)
        self.graph, self.node_scores = g, data["node_scores"]
        self.n_roadmap_nodes = len(data["configs"])
        self.max_motion = float(data["max_motion"])
        self.stats = json.loads(str(data["stats"]))
