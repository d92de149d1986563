"""The knot store: the knots of the roadmap's edges, by edge id, so that what is checked and scored is what runs."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

QUERY_KNOT_CACHE = 512  # start/goal query edges whose knots are kept (by end configurations)


def no_knots(ctx) -> tuple:
    """Empty (knots (0, M, dof), Eq. 1 positions (0, N)) of a planner's edges (``ctx``: its
    :class:`~.state.PlannerContext`)."""
    n = ctx.settings.edges.n_interp
    return (torch.zeros(0, n + 4, ctx.robot.dof, dtype=ctx.dtype, device=ctx.device),
            torch.zeros(0, n, dtype=torch.long, device=ctx.device))


def _flags(have: np.ndarray, ids) -> np.ndarray:
    """``have[ids]`` with False for ids beyond the array."""
    ids = np.asarray(ids, dtype=np.int64)
    out = np.zeros(len(ids), dtype=bool)
    inside = ids < len(have)
    out[inside] = have[ids[inside]]
    return out


class KnotStore:
    """Knots of the roadmap's edges (:meth:`.edges.Edges.edge_knots`, in the stored u -> v direction), by edge id.

    The same knots serve the collision check, the Eq. 1 interior scores and the executed path, so what is checked
    is exactly what runs (a path traversing an edge v -> u uses the flipped knots)."""

    def __init__(self):
        self.clear()

    def clear(self) -> None:
        self.data: Optional[torch.Tensor] = None  # (capacity, M, dof)
        self.interior: Optional[torch.Tensor] = None  # (capacity, N) positions of the Eq. 1 samples among the knots
        self.have = np.zeros(0, dtype=bool)
        self.cams: Optional[torch.Tensor] = None  # (capacity, N + 2, 4, 4) camera poses of the Eq. 1 points
        self.cams_have = np.zeros(0, dtype=bool)
        # (capacity, M, 6) world bounds of the robot at each knot (NaN = not computed yet): once a knot has been
        # checked, an obstacle move is tested against its bounds first and needs no kinematics when they miss
        self.aabb: Optional[torch.Tensor] = None
        # start/goal query edges' knots by their end configurations: a goal's (and a still robot's) edges recur on
        # every replan, and re-projecting the knots onto the manifold is a query's largest fixed cost
        self.query: dict = {}

    def put(self, ids: np.ndarray, knots: torch.Tensor, interior: torch.Tensor) -> None:
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        need = int(ids.max()) + 1
        if self.data is None or self.data.shape[1:] != knots.shape[1:]:
            self.data = knots.new_zeros((0,) + tuple(knots.shape[1:]))
            self.interior = interior.new_zeros((0,) + tuple(interior.shape[1:]))
            self.have = np.zeros(0, dtype=bool)
        if need > self.data.shape[0]:
            cap = max(need, int(self.data.shape[0] * 1.5) + 1024)
            grown = knots.new_zeros((cap,) + tuple(knots.shape[1:]))
            grown[: self.data.shape[0]] = self.data
            gi = interior.new_zeros((cap,) + tuple(interior.shape[1:]))
            gi[: self.interior.shape[0]] = self.interior
            self.data, self.interior = grown, gi
            self.have = np.concatenate([self.have, np.zeros(cap - len(self.have), dtype=bool)])
        idx = torch.as_tensor(ids, device=knots.device)
        self.data[idx] = knots
        self.interior[idx] = interior
        self.written(ids)

    def forget_from(self, n: int) -> None:
        """Forget the knots, camera poses and robot bounds of edge ids ``n`` and above (their slots were given back
        and will be reused by new edges; the arrays keep their capacity)."""
        self.have[n:] = False
        self.cams_have[n:] = False
        if self.aabb is not None and self.aabb.shape[0] > n:
            self.aabb[n:] = float("nan")

    def trim_query_cache(self) -> None:
        """Keep the :data:`QUERY_KNOT_CACHE` newest entries of :attr:`query` (dicts keep insertion order)."""
        while len(self.query) > QUERY_KNOT_CACHE:
            self.query.pop(next(iter(self.query)))

    def reserve(self, n: int) -> None:
        """Room for edge ids below ``n`` (the arrays must exist: after a first :meth:`put`)."""
        if n > self.data.shape[0]:
            self.put(np.asarray([n - 1]), self.data[:1].clone(), self.interior[:1].clone())
            self.have[n - 1] = False

    def written(self, ids: np.ndarray) -> None:
        """Mark the knots of edges ``ids`` as stored after they were written into :attr:`data` / :attr:`interior`
        directly (as :meth:`put` does: their camera poses and robot bounds are reset)."""
        self.have[ids] = True
        if len(self.cams_have):
            self.cams_have[ids[ids < len(self.cams_have)]] = False
        if self.aabb is not None:
            inside = ids[ids < self.aabb.shape[0]]
            if self.aabb.device.type == "cpu":
                self.aabb.numpy()[inside] = np.nan
            else:
                self.aabb[torch.as_tensor(inside, device=self.aabb.device)] = float("nan")

    def knot_aabb(self, ids: np.ndarray) -> torch.Tensor:
        """(E, M, 6) cached robot bounds at the knots of edges ``ids`` (NaN where not computed yet)."""
        ids = np.asarray(ids, dtype=np.int64)
        cap, M = self.data.shape[0], self.data.shape[1]
        if self.aabb is None or self.aabb.shape[0] < cap or self.aabb.shape[1] != M:
            grown = self.data.new_full((cap, M, 6), float("nan"))
            if self.aabb is not None and self.aabb.shape[1] == M:
                grown[: self.aabb.shape[0]] = self.aabb
            self.aabb = grown
        return self.aabb[torch.as_tensor(ids, device=self.data.device)]

    def put_aabb(self, ids: np.ndarray, knot: np.ndarray, bounds: torch.Tensor) -> None:
        """Store robot bounds (K, 6) at knot positions ``knot`` (K,) of edges ``ids`` (K,)."""
        self.knot_aabb(ids[:0])  # allocate
        dev = self.aabb.device
        self.aabb[torch.as_tensor(ids, device=dev), torch.as_tensor(knot, device=dev)] = bounds.to(self.aabb.dtype)

    def put_cams(self, ids: np.ndarray, cams: torch.Tensor | np.ndarray) -> None:
        """Camera poses (E, N + 2, 4, 4) of the Eq. 1 points of edges whose knots are stored (fixed while the
        roadmap's geometry is: a target move re-scores them without forward kinematics); a numpy array is written
        straight into a CPU store."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return
        cap = self.data.shape[0]
        if isinstance(cams, np.ndarray):
            c = self.cams
            if (c is not None and c.device.type == "cpu" and c.shape[0] >= cap and c.shape[1:] == cams.shape[1:]
                    and c.numpy().dtype == cams.dtype):
                c.numpy()[ids] = cams
                self.cams_have[ids] = True
                return
            cams = torch.from_numpy(cams).to(self.data.device)
        if self.cams is None or self.cams.shape[0] < cap or self.cams.shape[1:] != cams.shape[1:]:
            # uninitialised (rows are read only where cams_have says so): a roadmap's first query does not zero
            # tens of MB
            grown = cams.new_empty((cap,) + tuple(cams.shape[1:]))
            keep = np.zeros(cap, dtype=bool)
            if self.cams is not None and self.cams.shape[1:] == cams.shape[1:]:
                grown[: self.cams.shape[0]] = self.cams
                keep[: len(self.cams_have)] = self.cams_have
            self.cams, self.cams_have = grown, keep
        self.cams[torch.as_tensor(ids, device=cams.device)] = cams
        self.cams_have[ids] = True

    def known_cams(self, ids: np.ndarray) -> np.ndarray:
        """(E,) bool: the Eq. 1 camera poses of these edges are stored."""
        return _flags(self.cams_have, ids)

    def known(self, ids: np.ndarray) -> np.ndarray:
        """(E,) bool: the knots of these edges are stored."""
        return _flags(self.have, ids)

    def get(self, ids: np.ndarray) -> tuple:
        idx = torch.as_tensor(np.asarray(ids, dtype=np.int64), device=self.data.device)
        return self.data[idx], self.interior[idx]

