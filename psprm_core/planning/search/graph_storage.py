"""Storage of the roadmap graph, in :class:`GraphStorage` (the base class of
:class:`~psprm_core.planning.search.graph.Roadmap`): node configurations, edge endpoints, validity flags, edge
weights :math:`c(q_u, q_v)` (Eq. 2) and named per-edge attributes in growable numpy arrays (amortised doubling) indexed
by stable ids, the versions and caches the adjacency views keep on it, their read-only views, and the id and weight
checks of the roadmap's changes.
"""

from __future__ import annotations

from typing import Any, Iterable

import numpy as np

from ...errors import InputError
from .graph_adjacency import _MIN_CAPACITY, AdjacencyViews, CSRAdjacency


def _per_edge(values, k: int) -> np.ndarray:
    """(k,) float64 view or copy of a scalar or k values (``np.broadcast_to`` without its overhead)."""
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 0:
        return np.full(k, float(a))
    if a.shape != (k,):
        return np.broadcast_to(a, (k,))  # raises for an incompatible shape
    return a


def _grow(arr: np.ndarray, needed: int, fill: Any) -> np.ndarray:
    """Return ``arr`` (first axis) enlarged to at least ``needed`` rows by doubling, new rows set to ``fill``."""
    cap = arr.shape[0]
    if needed <= cap:
        return arr
    new_cap = max(_MIN_CAPACITY, cap)
    while new_cap < needed:
        new_cap *= 2
    out = np.empty((new_cap,) + arr.shape[1:], dtype=arr.dtype)
    out[:cap] = arr
    out[cap:] = fill
    return out


class GraphStorage(AdjacencyViews):
    """The arrays of a :class:`~psprm_core.planning.search.graph.Roadmap` (its base class; parameters as there) and
    their read-only views: slots ``0 .. n - 1`` of every array are the nodes / edges ever created, valid or not."""

    def __init__(self, dof: int | None = None, node_capacity: int = 1024, edge_capacity: int = 4096) -> None:
        self.dof = dof
        nc = max(_MIN_CAPACITY, int(node_capacity))
        ec = max(_MIN_CAPACITY, int(edge_capacity))
        self._n_nodes = 0
        self._n_edges = 0
        self._configs = np.zeros((nc, dof), dtype=np.float64) if dof is not None else None
        self._node_valid = np.zeros(nc, dtype=bool)
        self._eu = np.zeros(ec, dtype=np.int64)
        self._ev = np.zeros(ec, dtype=np.int64)
        self._edge_valid = np.zeros(ec, dtype=bool)
        self._weights = np.zeros(ec, dtype=np.float64)
        self._edge_attrs: dict[str, np.ndarray] = {}
        self._pair_to_edge: dict[tuple[int, int], int] = {}
        self.structure_version = 0
        self.weights_version = 0
        self._csr: CSRAdjacency | None = None
        # Per-node Python adjacency lists for the heapq searches: patched in place after additions, removals and
        # restorations of up to _PATCH_LIMIT edges (connecting a start/goal node or pruning the edges near a moved
        # obstacle does not trigger a rebuild).
        self._removal_version = 0
        self._restore_version = 0  # bumped when removed edges/nodes come back (graph distances may then decrease)
        self._py_adj: tuple[int, int, int, list[list[int]], list[list[int]]] | None = None
        self._py_weights: tuple[int, list[float]] | None = None
        # Padded array adjacency for the compiled searches (same patching policy, see array_adjacency)
        self._arr_adj: list[Any] | None = None
        #: Free-form cache used by :mod:`psprm_core.planning.search.graph_search` (hop distances per goal set).
        self.search_cache: dict[Any, Any] = {}

    # ------------------------------------------------------------------ sizes and views
    @property
    def n_nodes(self) -> int:
        """Number of node slots ever created (valid or not); node ids are ``0 .. n_nodes - 1``."""
        return self._n_nodes

    @property
    def n_edges(self) -> int:
        """Number of edge slots ever created (valid or not); edge ids are ``0 .. n_edges - 1``."""
        return self._n_edges

    @property
    def num_valid_nodes(self) -> int:
        """Number of nodes not removed."""
        return int(self._node_valid[: self._n_nodes].sum())

    @property
    def num_valid_edges(self) -> int:
        """Number of edges not removed."""
        return int(self._edge_valid[: self._n_edges].sum())

    @property
    def configs(self) -> np.ndarray:
        """``(n_nodes, dof)`` view of node configurations (raises if the roadmap stores none)."""
        if self._configs is None:
            raise AttributeError("this Roadmap was created with dof=None and stores no configurations")
        return self._configs[: self._n_nodes]

    @property
    def node_valid(self) -> np.ndarray:
        """``(n_nodes,)`` read-only boolean view: node not removed."""
        v = self._node_valid[: self._n_nodes].view()
        v.flags.writeable = False
        return v

    @property
    def edge_valid(self) -> np.ndarray:
        """``(n_edges,)`` read-only boolean view: edge not removed."""
        v = self._edge_valid[: self._n_edges].view()
        v.flags.writeable = False
        return v

    @property
    def edges(self) -> np.ndarray:
        """``(n_edges, 2)`` array of endpoints ``(u, v)`` of every edge slot (copy)."""
        return np.stack([self._eu[: self._n_edges], self._ev[: self._n_edges]], axis=1)

    @property
    def edge_u(self) -> np.ndarray:
        """``(n_edges,)`` read-only view of the first endpoint of every edge."""
        v = self._eu[: self._n_edges].view()
        v.flags.writeable = False
        return v

    @property
    def edge_v(self) -> np.ndarray:
        """``(n_edges,)`` read-only view of the second endpoint of every edge."""
        v = self._ev[: self._n_edges].view()
        v.flags.writeable = False
        return v

    @property
    def weights(self) -> np.ndarray:
        """``(n_edges,)`` read-only view of the edge weights :math:`c(q_u, q_v)` (Eq. 2); use :meth:`set_weights`."""
        v = self._weights[: self._n_edges].view()
        v.flags.writeable = False
        return v

    @property
    def restore_version(self) -> int:
        """Bumped by :meth:`restore_edges` and :meth:`restore_nodes`: the only changes after which a graph distance
        can become shorter than before other than additions (removals only lengthen distances)."""
        return self._restore_version

    @property
    def removal_version(self) -> int:
        """Counter bumped by edge removals/restorations only (additions keep it): caches built at the same
        ``removal_version`` can be updated incrementally with the nodes/edges added since."""
        return self._removal_version

    def valid_edge_ids(self) -> np.ndarray:
        """Ids of all edges that are not removed."""
        return np.flatnonzero(self._edge_valid[: self._n_edges])

    def valid_node_ids(self) -> np.ndarray:
        """Ids of all nodes that are not removed."""
        return np.flatnonzero(self._node_valid[: self._n_nodes])
    # ------------------------------------------------------------------ internals
    def _structure_changed(self) -> None:
        self.structure_version += 1

    @staticmethod
    def _check_weights(w: np.ndarray) -> None:
        if w.size and not (w >= 0).all():  # NaN compares false
            raise InputError("edge weights must be non-negative (Eq. 2 gives c in [0, 2])")

    @staticmethod
    def _as_ids(ids: Iterable[int] | np.ndarray | slice, n: int, what: str) -> np.ndarray:
        if isinstance(ids, slice):
            return np.arange(n, dtype=np.int64)[ids]
        arr = np.asarray(list(ids) if not isinstance(ids, np.ndarray) else ids, dtype=np.int64).reshape(-1)
        if arr.size and not (0 <= arr.min() and arr.max() < n):
            raise InputError(f"{what} id out of range")
        return arr
