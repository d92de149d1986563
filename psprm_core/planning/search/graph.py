"""Roadmap graph for PS-PRM (paper, section "PRM construction and scoring").

The roadmap :math:`G = (V, E)` of PS-PRM holds a few thousand configuration nodes and ~10^5 undirected edges whose
weights :math:`c(q_u, q_v)` (Eq. 2) change whenever the perception target moves, and whose nodes/edges are pruned
when an obstacle moves (section "GPU-Parallelized Replanning Pipeline").  :class:`Roadmap` is tuned for that use:

* node and edge ids are **stable** integers: removal only marks a node/edge invalid (no renumbering, no rebuild), so
  per-node / per-edge arrays held by the caller (perception scores, motion costs, ...) stay aligned;
* storage is a set of growable numpy arrays (amortised doubling), so adding start/goal nodes or repair edges is cheap;
* the adjacency used by searches is a CSR structure over the *valid* edges, rebuilt lazily (only after a structural
  change, never after a weight change) and cached together with its Python-list form used by the heapq searches;
* edge weights live in one float array indexed by edge id (``Roadmap.weights``); weight updates are O(k) writes.

Edges are undirected and unique: adding ``(u, v)`` when ``(u, v)`` or ``(v, u)`` already exists (and is valid) returns
the existing edge id and overwrites its weight.  Self loops are rejected.

The arrays, their read-only views and the id checks are the base class of :class:`Roadmap`,
:class:`~psprm_core.planning.search.graph_storage.GraphStorage`; the adjacency views and their caches are its base
class, :class:`~psprm_core.planning.search.graph_adjacency.AdjacencyViews`.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
from ...errors import InputError, UnknownNameError
from .graph_adjacency import _ARRAY_PATCH_LIMIT, _MIN_CAPACITY, _PATCH_LIMIT, AdjacencyViews, CSRAdjacency  # noqa: F401
from .graph_storage import GraphStorage, _grow, _per_edge

__all__ = ["CSRAdjacency", "Roadmap"]


class Roadmap(GraphStorage):
    """Undirected roadmap graph with stable ids, invalidation and lazily rebuilt CSR adjacency.

    Parameters
    ----------
    dof : int or None
        Dimension of the configuration stored with each node; ``None`` stores no configurations (pure graph).
    node_capacity, edge_capacity : int
        Initial storage sizes (grown automatically).

    Notes
    -----
    ``weights`` holds the search weight :math:`c(q_u, q_v)` of Eq. 2 for every edge slot (valid or not).  Optional
    named per-edge float attributes (e.g. ``"c_m"``, ``"c_p"`` of Eqs. 1-2) can be registered with
    :meth:`add_edge_attribute` and are grown together with the edges.
    """

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_edges(
        cls,
        n_nodes: int,
        edges: np.ndarray,
        weights: np.ndarray | None = None,
        configs: np.ndarray | None = None,
    ) -> "Roadmap":
        """Build a roadmap from ``n_nodes`` and an ``(E, 2)`` undirected edge list (duplicates are merged).

        Parameters
        ----------
        n_nodes : int
            Number of nodes (ids ``0 .. n_nodes - 1``).
        edges : np.ndarray
            ``(E, 2)`` integer node pairs.
        weights : np.ndarray, optional
            ``(E,)`` edge weights (Eq. 2); zeros when omitted.
        configs : np.ndarray, optional
            ``(n_nodes, dof)`` node configurations.
        """
        dof = None if configs is None else int(np.asarray(configs).shape[1])
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        g = cls(dof=dof, node_capacity=n_nodes, edge_capacity=max(len(edges), 1))
        g.add_nodes(configs if configs is not None else int(n_nodes))
        g.add_edges(edges[:, 0], edges[:, 1], weights)
        return g


    # ------------------------------------------------------------------ nodes
    def add_nodes(self, configs_or_count: np.ndarray | int) -> np.ndarray:
        """Append nodes; returns their ids.

        Parameters
        ----------
        configs_or_count : np.ndarray or int
            ``(k, dof)`` configurations (required when ``dof`` is set) or a node count (``dof is None``).
        """
        if isinstance(configs_or_count, (int, np.integer)):
            if self._configs is not None:
                raise InputError("this Roadmap stores configurations: pass a (k, dof) array")
            k = int(configs_or_count)
            cfg = None
        else:
            cfg = np.asarray(configs_or_count, dtype=np.float64)
            if self._configs is None:
                raise InputError("this Roadmap was created with dof=None: pass a node count")
            cfg = cfg.reshape(-1, self.dof)
            k = cfg.shape[0]
        start = self._n_nodes
        end = start + k
        self._node_valid = _grow(self._node_valid, end, False)
        if self._configs is not None:
            self._configs = _grow(self._configs, end, 0.0)
            self._configs[start:end] = cfg
        self._node_valid[start:end] = True
        self._n_nodes = end
        self._structure_changed()
        return np.arange(start, end, dtype=np.int64)

    def add_node(self, config: np.ndarray | None = None) -> int:
        """Append one node (with its configuration when the roadmap stores them); returns its id."""
        if self._configs is None:
            return int(self.add_nodes(1)[0])
        return int(self.add_nodes(np.asarray(config, dtype=np.float64).reshape(1, -1))[0])

    def remove_nodes(self, nodes: Iterable[int] | np.ndarray) -> np.ndarray:
        """Mark nodes invalid together with all their incident edges (pruning, no renumbering).

        Returns
        -------
        np.ndarray
            Ids of the edges invalidated by this call.
        """
        nodes = self._as_ids(nodes, self._n_nodes, "node")
        if nodes.size == 0:
            return np.zeros(0, dtype=np.int64)
        self._node_valid[nodes] = False
        eids = self.incident_edges(nodes)
        self.remove_edges(eids)
        self._structure_changed()
        return eids

    def restore_nodes(self, nodes: Iterable[int] | np.ndarray) -> None:
        """Mark removed nodes valid again (their edges stay removed; see :meth:`restore_edges`)."""
        nodes = self._as_ids(nodes, self._n_nodes, "node")
        self._node_valid[nodes] = True
        self._restore_version += 1
        self._structure_changed()

    def truncate(self, n_nodes: int, n_edges: int) -> None:
        """Give back the trailing node and edge slots from ``n_nodes`` / ``n_edges`` on, which must all be invalid
        (retired): later additions reuse their ids. The slots are reset as new ones are (invalid, zero, NaN
        attributes); the adjacency is rebuilt on its next use and the search cache dropped (its entries are keyed
        by node ids).

        Raises
        ------
        InputError
            A slot to give back is still valid, or the sizes are out of range."""
        n_nodes, n_edges = int(n_nodes), int(n_edges)
        if not (0 <= n_nodes <= self._n_nodes and 0 <= n_edges <= self._n_edges):
            raise InputError(f"cannot truncate {self._n_nodes} nodes / {self._n_edges} edges to {n_nodes} / {n_edges}")
        if self._node_valid[n_nodes: self._n_nodes].any() or self._edge_valid[n_edges: self._n_edges].any():
            raise InputError("only invalid (retired) node and edge slots can be given back")
        if n_nodes == self._n_nodes and n_edges == self._n_edges:
            return
        if self._configs is not None:
            self._configs[n_nodes: self._n_nodes] = 0.0
        self._eu[n_edges: self._n_edges] = 0
        self._ev[n_edges: self._n_edges] = 0
        self._weights[n_edges: self._n_edges] = 0.0
        for arr in self._edge_attrs.values():
            arr[n_edges: self._n_edges] = np.nan
        self._n_nodes, self._n_edges = n_nodes, n_edges
        self._csr = None
        self._py_adj = self._py_weights = self._arr_adj = None
        self.search_cache.clear()
        self._removal_version += 1
        self._restore_version += 1
        self._structure_changed()

    # ------------------------------------------------------------------ edges
    def add_edge_attribute(self, name: str, fill: float = np.nan) -> np.ndarray:
        """Register a named float per-edge attribute (e.g. ``"c_m"``/``"c_p"`` of Eqs. 1-2); returns a view of it."""
        if name not in self._edge_attrs:
            arr = np.full(self._eu.shape[0], fill, dtype=np.float64)
            self._edge_attrs[name] = arr
        return self.edge_attribute(name)

    def edge_attribute(self, name: str) -> np.ndarray:
        """Writable ``(n_edges,)`` view of a registered per-edge attribute."""
        return self._edge_attrs[name][: self._n_edges]

    def add_edges(
        self,
        u: np.ndarray | Iterable[int],
        v: np.ndarray | Iterable[int],
        weights: np.ndarray | float | None = None,
        **attrs: np.ndarray | float,
    ) -> np.ndarray:
        """Add undirected edges ``(u[i], v[i])``; returns the edge id of each pair (existing id for duplicates).

        Parameters
        ----------
        u, v : array-like of int
            Endpoints (valid node ids).  Self loops raise ``ValueError``.
        weights : array-like or float, optional
            Edge weights :math:`c(q_u, q_v)` (Eq. 2), non-negative.  For an existing edge the weight is overwritten;
            when omitted, new edges get 0 and existing edges keep their weight.
        **attrs
            Values of registered edge attributes (registered on the fly when unknown).
        """
        u = np.asarray(u, dtype=np.int64).reshape(-1)
        v = np.asarray(v, dtype=np.int64).reshape(-1)
        if u.shape != v.shape:
            raise InputError("u and v must have the same length")
        k = u.shape[0]
        w = _per_edge(0.0 if weights is None else weights, k)
        self._check_weights(w)
        if k == 0:
            return np.zeros(0, dtype=np.int64)
        if min(u.min(), v.min()) < 0 or max(u.max(), v.max()) >= self._n_nodes:
            raise InputError("edge endpoint out of range")
        if (u == v).any():
            raise InputError("self loops are not allowed in the roadmap")
        if not (self._node_valid[u].all() and self._node_valid[v].all()):
            raise InputError("cannot connect a removed node")
        attr_vals = {n: _per_edge(a, k) for n, a in attrs.items()}
        for name in attr_vals:
            self.add_edge_attribute(name)

        lo = np.minimum(u, v)
        hi = np.maximum(u, v)
        out = np.empty(k, dtype=np.int64)
        new_lo: list[int] = []
        new_hi: list[int] = []
        new_pos: list[int] = []
        pair_to_edge = self._pair_to_edge
        next_id = self._n_edges
        keys = list(zip(lo.tolist(), hi.tolist()))
        found = [pair_to_edge.get(key, -1) for key in keys]
        if max(found) < 0 and len(set(keys)) == k:  # all new and distinct (a query's edges): no per-pair loop
            out[:] = np.arange(next_id, next_id + k)
            pair_to_edge.update(zip(keys, range(next_id, next_id + k)))
            new_lo, new_hi, new_pos = lo, hi, list(range(k))
            next_id += k
        else:
            for i, key in enumerate(keys):
                eid = found[i] if found[i] >= 0 else pair_to_edge.get(key)  # a duplicate inside the batch
                if eid is None:
                    eid = next_id
                    next_id += 1
                    pair_to_edge[key] = eid
                    new_lo.append(key[0])
                    new_hi.append(key[1])
                    new_pos.append(i)
                out[i] = eid
        n_new = next_id - self._n_edges
        if n_new:
            start, end = self._n_edges, next_id
            self._eu = _grow(self._eu, end, 0)
            self._ev = _grow(self._ev, end, 0)
            self._edge_valid = _grow(self._edge_valid, end, False)
            self._weights = _grow(self._weights, end, 0.0)
            for name, arr in self._edge_attrs.items():
                self._edge_attrs[name] = _grow(arr, end, np.nan)
            self._eu[start:end] = new_lo
            self._ev[start:end] = new_hi
            self._edge_valid[start:end] = True
            self._n_edges = end
            self._structure_changed()
        # Last write wins for duplicates inside the batch, as for pre-existing edges.  Without ``weights`` the
        # existing edges keep theirs and the new ones get 0.
        if weights is None:
            pos = np.asarray(new_pos, dtype=np.int64)
            out_w, w = out[pos], w[pos]
        else:
            out_w = out
        self._weights[out_w] = w
        for name, vals in attr_vals.items():
            self._edge_attrs[name][out] = vals
        self._weights_written(out_w, w)
        return out

    def add_edge(self, u: int, v: int, weight: float = 0.0, **attrs: float) -> int:
        """Add one undirected edge; returns its id (see :meth:`add_edges`)."""
        return int(self.add_edges([u], [v], weight, **attrs)[0])

    def remove_edges(self, edge_ids: Iterable[int] | np.ndarray) -> None:
        """Mark edges invalid (pruning).  Their slots, weights and attributes are kept (see :meth:`restore_edges`)."""
        eids = self._as_ids(edge_ids, self._n_edges, "edge")
        if eids.size == 0:
            return
        eids = np.unique(eids[self._edge_valid[eids]])
        if eids.size == 0:
            return
        self._edge_valid[eids] = False
        ends = list(zip(eids.tolist(), self._eu[eids].tolist(), self._ev[eids].tolist()))
        for _, a, b in ends:
            self._pair_to_edge.pop((a, b), None)
        self._patch_adjacency(ends, add=False)
        self._removal_version += 1
        self._structure_changed()

    def restore_edges(self, edge_ids: Iterable[int] | np.ndarray) -> np.ndarray:
        """Mark removed edges valid again when both endpoints are valid and the pair is not re-added meanwhile.

        Returns
        -------
        np.ndarray
            The ids actually restored.
        """
        eids = self._as_ids(edge_ids, self._n_edges, "edge")
        restored: list[int] = []
        for e, a, b in zip(eids.tolist(), self._eu[eids].tolist(), self._ev[eids].tolist()):
            if self._edge_valid[e] or not (self._node_valid[a] and self._node_valid[b]):
                continue
            if (a, b) in self._pair_to_edge:
                continue
            self._pair_to_edge[(a, b)] = e
            self._edge_valid[e] = True
            restored.append(e)
        if restored:
            r = np.asarray(restored, dtype=np.int64)
            self._patch_adjacency(list(zip(restored, self._eu[r].tolist(), self._ev[r].tolist())), add=True)
            self._removal_version += 1
            self._restore_version += 1
            self._structure_changed()
        return np.asarray(restored, dtype=np.int64)

    def set_weights(self, edge_ids: np.ndarray | Iterable[int] | slice | None, values: np.ndarray | float) -> None:
        """Overwrite edge weights (Eq. 2) for ``edge_ids`` (``None`` = all edge slots).  Weights must be >= 0."""
        vals = np.asarray(values, dtype=np.float64)
        self._check_weights(vals)
        if edge_ids is None:
            self._weights[: self._n_edges] = vals
            self._py_weights = None
            self.weights_version += 1
        else:
            ids = self._as_ids(edge_ids, self._n_edges, "edge")
            self._weights[ids] = vals
            if self._py_weights is not None:  # only the cached Python list needs the values per edge
                self._weights_written(ids, _per_edge(vals, ids.size))
            else:
                self.weights_version += 1

    def edge_id(self, u: int, v: int) -> int | None:
        """Id of the valid edge between ``u`` and ``v`` or ``None``."""
        a, b = (int(u), int(v)) if u <= v else (int(v), int(u))
        return self._pair_to_edge.get((a, b))

    def edge_ids_of_path(self, path: Iterable[int]) -> np.ndarray:
        """Edge ids along a node path; raises ``KeyError`` when two consecutive nodes are not connected."""
        p = list(path)
        out = np.empty(max(len(p) - 1, 0), dtype=np.int64)
        for i in range(len(p) - 1):
            e = self.edge_id(p[i], p[i + 1])
            if e is None:
                raise UnknownNameError(f"no valid edge between {p[i]} and {p[i + 1]}")
            out[i] = e
        return out

    def incident_edges(self, nodes: Iterable[int] | np.ndarray) -> np.ndarray:
        """Ids of the valid edges touching any of ``nodes``."""
        nodes = self._as_ids(nodes, self._n_nodes, "node")
        mask = np.zeros(self._n_nodes, dtype=bool)
        mask[nodes] = True
        eu, ev = self._eu[: self._n_edges], self._ev[: self._n_edges]
        hit = (mask[eu] | mask[ev]) & self._edge_valid[: self._n_edges]
        return np.flatnonzero(hit)

    def neighbors(self, u: int) -> tuple[np.ndarray, np.ndarray]:
        """Valid neighbours of ``u`` and the ids of the connecting edges."""
        csr = self.csr()
        lo, hi = csr.indptr[u], csr.indptr[u + 1]
        return csr.indices[lo:hi].copy(), csr.edge_ids[lo:hi].copy()

    def degree(self) -> np.ndarray:
        """``(n_nodes,)`` number of valid incident edges of every node."""
        return np.diff(self.csr().indptr)


    def __repr__(self) -> str:
        return (
            f"Roadmap(nodes={self.num_valid_nodes}/{self._n_nodes}, edges={self.num_valid_edges}/{self._n_edges}, "
            f"dof={self.dof})"
        )
