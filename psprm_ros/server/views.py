"""What the planning loop shows besides trajectories: the roadmap's camera poses and markers, and the camera poses,
base route and scores along a plan. Built on a side thread while the planner is idle (:class:`SideJobs`), so that
pure-Python message building never competes with a replan."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch


class SideJobs:
    """One side thread that runs the newest job of each kind once the planner is idle (``idle``, waited for at most
    1 s); a job of a kind still waiting is replaced: only the newest path or roadmap matters, and while the planner
    replans back to back jobs would otherwise pile up faster than they run."""

    def __init__(self, idle: threading.Event, report):
        self.idle, self.report = idle, report
        self._lock = threading.Lock()
        self._jobs: dict = {}  # kind -> (fn, args) of the newest job waiting
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="psprm-publish")

    def submit(self, what: str, fn, *args) -> None:
        with self._lock:
            queued = what in self._jobs
            self._jobs[what] = (fn, args)
        if not queued:
            self._pool.submit(self._run, what)

    def _run(self, what: str) -> None:
        self.idle.wait(1.0)
        with self._lock:
            fn, args = self._jobs.pop(what)
        try:
            fn(*args)
        except Exception as exc:  # never lose the side thread
            self.report(f"{what} failed: {exc}", "warning")

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class RoadmapViews:
    """The roadmap's camera poses (every node slot, in the perception scorer's order) and markers, and a plan's
    camera poses along its path. ``outputs``: the loop's :class:`~psprm_ros.server.outputs.Outputs`; ``params``:
    the loop's live parameters (``publish_markers``, ``markers_period_s``, ``path_camera_samples``)."""

    def __init__(self, robot, outputs, params: dict, side: SideJobs):
        self.robot, self.outputs, self.p, self.side = robot, outputs, params, side
        self.ext_scores = None  # the perception scorer's normalised roadmap node scores
        self.dirty = False  # the markers are to be rebuilt at the next chance
        self._t = 0.0
        self._ids = np.zeros(0, dtype=np.int64)  # roadmap node slots whose camera poses were last published
        self._cams = np.zeros((0, 4, 4))

    def camera_poses(self, Q: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.robot.camera_poses(torch.as_tensor(np.asarray(Q), dtype=torch.float32)).double().numpy()

    def publish_roadmap(self, planner, scene) -> None:
        """Camera poses of every roadmap node slot (pruned ones too: the perception scorer's scores follow this
        order), then the markers. Called after a build and whenever the roadmap has grown (repair)."""
        ids = np.nonzero(planner.roadmap_mask())[0]
        T = self.camera_poses(planner.graph.configs[ids])
        self._ids, self._cams = ids, T
        self.outputs.roadmap_cameras(T)
        self.dirty = True
        self.republish(planner, scene, force=True)

    def node_scores(self, planner) -> np.ndarray:
        """Normalised scores of the published roadmap nodes: the perception scorer's when they match, else the
        planner's."""
        ids, s = self._ids, self.ext_scores
        if s is None or len(s) != len(ids):
            s = np.full(len(ids), np.nan)
            have = ids < len(planner.node_scores)
            s[have] = np.asarray(planner.node_scores, float)[ids[have]]
        return s * float(getattr(planner, "score_scale", 1.0))

    def republish(self, planner, scene, force: bool = False) -> None:
        """Roadmap markers: a snapshot of the roadmap taken here (worker thread, cheap array copies), the markers
        built and published on the side thread, at most every ``markers_period_s`` unless ``force``."""
        if not self.p["publish_markers"] or planner is None:
            return
        now = time.monotonic()
        if not force and (not self.dirty or now - self._t < self.p["markers_period_s"]):
            return
        g = planner.graph
        if len(self._ids) != planner.n_roadmap_nodes:  # the roadmap grew (repair): camera poses of its slots first
            self.publish_roadmap(planner, scene)  # (calls back with force=True)
            return
        self._t, self.dirty = now, False
        ids = self._ids
        keep = g.node_valid[ids]
        pos = np.full(g.n_nodes, -1, dtype=np.int64)
        pos[ids[keep]] = np.arange(int(keep.sum()))
        eids = planner.roadmap_edge_ids()
        e = np.stack([pos[g.edge_u[eids]], pos[g.edge_v[eids]]], 1)
        e = e[(e >= 0).all(1)]
        snap = (scene, self._cams[keep, :3, 3].copy(), self.node_scores(planner)[keep].copy(),
                g.configs[ids[keep], :2].copy(), e)
        self.side.submit("roadmap markers", self.outputs.roadmap_markers, *snap)

    def publish_path(self, res, scene, planner) -> None:
        """Side job: camera poses along the path (for the perception scorer), its base positions and scores."""
        D = res.dense if res.dense is not None else res.waypoints
        k = max(1, int(np.ceil(len(D) / max(2, self.p["path_camera_samples"]))))
        idx = np.unique(np.r_[np.arange(0, len(D), k), len(D) - 1])
        T = self.camera_poses(D[idx])
        scores = res.dense_scores[idx] if res.dense_scores is not None else np.zeros(len(idx))
        scores = scores * float(getattr(planner, "score_scale", 1.0))
        self.outputs.path(T, np.asarray(D[idx, :2], float), scores, scene)
