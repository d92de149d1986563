"""Adjacency views of the roadmap graph, in :class:`AdjacencyViews` (the base class of
:class:`~psprm_core.planning.search.graph.Roadmap`): the directed CSR structure over the valid edges
(:class:`CSRAdjacency`), its per-node Python lists for the heapq searches, the padded arrays for the compiled searches
and the Python list of the edge weights, each cached and patched in place after small changes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

_MIN_CAPACITY = 16
#: Weight updates of at most this many edges patch the cached Python weight list instead of rebuilding it.
_PATCH_LIMIT = 2048
#: Removals / restorations of at most this many edges patch the array adjacency in place (else: rebuilt from the CSR).
_ARRAY_PATCH_LIMIT = 256


@dataclass(frozen=True)
class CSRAdjacency:
    """Directed CSR view of the valid undirected edges (each edge appears once per direction).

    Attributes
    ----------
    indptr : np.ndarray
        ``(n_nodes + 1,)`` int64; the neighbours of node ``u`` are ``indices[indptr[u]:indptr[u + 1]]``.
    indices : np.ndarray
        ``(2 * n_valid_edges,)`` int64 neighbour node ids.
    edge_ids : np.ndarray
        ``(2 * n_valid_edges,)`` int64 id of the undirected edge behind each CSR entry (index into ``Roadmap.weights``).
    structure_version : int
        The ``Roadmap.structure_version`` this view was built for.
    """

    indptr: np.ndarray
    indices: np.ndarray
    edge_ids: np.ndarray
    structure_version: int

    @property
    def n_nodes(self) -> int:
        """Number of node slots covered by the view."""
        return int(self.indptr.shape[0] - 1)

    @property
    def nnz(self) -> int:
        """Number of directed entries (twice the number of valid edges)."""
        return int(self.indices.shape[0])


class AdjacencyViews:
    """The cached adjacency views of a :class:`~psprm_core.planning.search.graph.Roadmap` (its base class): they read
    the roadmap's edge arrays, validity flags, weights and versions and keep their caches on it."""

    def csr(self) -> CSRAdjacency:
        """Directed CSR adjacency over the valid edges (cached until the next structural change)."""
        if self._csr is not None and self._csr.structure_version == self.structure_version:
            return self._csr
        n = self._n_nodes
        eids = np.flatnonzero(self._edge_valid[: self._n_edges])
        u = self._eu[eids]
        v = self._ev[eids]
        src = np.concatenate([u, v])
        dst = np.concatenate([v, u])
        eid2 = np.concatenate([eids, eids])
        order = np.argsort(src, kind="stable")
        counts = np.bincount(src, minlength=n)
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=indptr[1:])
        self._csr = CSRAdjacency(
            indptr=indptr,
            indices=dst[order].astype(np.int64, copy=False),
            edge_ids=eid2[order].astype(np.int64, copy=False),
            structure_version=self.structure_version,
        )
        logger.debug("rebuilt CSR adjacency: %d nodes, %d directed entries", n, self._csr.nnz)
        return self._csr

    def python_adjacency(self) -> tuple[list[list[int]], list[list[int]]]:
        """Per-node Python lists ``(neighbours[u], edge_ids[u])`` of the valid edges, for the heapq searches.

        Cached: nodes and edges added since the last call are appended in place (cheap start/goal connection), small
        removals and restorations are patched in place (:meth:`_patch_adjacency`); rebuilt from :meth:`csr` only after
        a large one.  Callers must not modify the lists.
        """
        cache = self._py_adj
        if cache is None or cache[0] != self._removal_version:
            csr = self.csr()
            ind = csr.indices.tolist()
            eid = csr.edge_ids.tolist()
            ptr = csr.indptr.tolist()
            nbrs = [ind[ptr[i] : ptr[i + 1]] for i in range(self._n_nodes)]
            eids = [eid[ptr[i] : ptr[i + 1]] for i in range(self._n_nodes)]
            self._py_adj = (self._removal_version, self._n_nodes, self._n_edges, nbrs, eids)
            return nbrs, eids
        _, n_cov, e_cov, nbrs, eids = cache
        if n_cov < self._n_nodes:
            for _ in range(self._n_nodes - n_cov):
                nbrs.append([])
                eids.append([])
        if e_cov < self._n_edges:
            new = np.arange(e_cov, self._n_edges)
            new = new[self._edge_valid[new]]
            for e, a, b in zip(new.tolist(), self._eu[new].tolist(), self._ev[new].tolist()):
                nbrs[a].append(b)
                eids[a].append(e)
                nbrs[b].append(a)
                eids[b].append(e)
        self._py_adj = (self._removal_version, self._n_nodes, self._n_edges, nbrs, eids)
        return nbrs, eids

    def _patch_adjacency(self, ends: list[tuple[int, int, int]], add: bool) -> None:
        """Keep the cached Python adjacency in step with removed / restored edges ``(edge id, u, v)``: patched in place
        for small changes (O(degree) per edge), dropped for large ones (rebuilt on the next use)."""
        self._patch_array_adjacency(ends, add)
        cache = self._py_adj
        if cache is None or cache[0] != self._removal_version:
            return
        if len(ends) > _PATCH_LIMIT:
            self._py_adj = None
            return
        _, n_cov, e_cov, nbrs, eids = cache
        for e, a, b in ends:
            if e >= e_cov:  # not in the lists yet: appended (when valid) by the next python_adjacency call
                continue
            for x, y in ((a, b), (b, a)):
                if add:
                    nbrs[x].append(y)
                    eids[x].append(e)
                else:
                    i = eids[x].index(e)
                    del nbrs[x][i]
                    del eids[x][i]
        self._py_adj = (self._removal_version + 1, n_cov, e_cov, nbrs, eids)

    def array_adjacency(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Padded array adjacency ``(nbr, eid, deg)`` of the valid edges, for the compiled searches.

        ``nbr[u, :deg[u]]`` are the neighbours of node ``u`` and ``eid[u, :deg[u]]`` the connecting edge ids (int64;
        at least ``n_nodes`` rows, spare rows and columns for cheap growth). Cached like :meth:`python_adjacency`:
        added nodes and edges are appended in place, removals and restorations of up to ``_ARRAY_PATCH_LIMIT`` edges
        are patched in place (a removed entry is replaced by the row's last one), larger ones rebuild from
        :meth:`csr`. Callers must not modify the arrays.
        """
        c = self._arr_adj
        n = self._n_nodes
        if c is None or c[0] != self._removal_version:
            csr = self.csr()
            deg = np.diff(csr.indptr)
            width = max(16, 2 * int(deg.max(initial=0)))
            rows = max(_MIN_CAPACITY, n + n // 4)
            nbr = np.full((rows, width), -1, dtype=np.int64)
            eid = np.full((rows, width), -1, dtype=np.int64)
            row = np.repeat(np.arange(n), deg)
            col = np.arange(csr.nnz) - csr.indptr[row]
            nbr[row, col] = csr.indices
            eid[row, col] = csr.edge_ids
            degs = np.zeros(rows, dtype=np.int64)
            degs[:n] = deg
            self._arr_adj = [self._removal_version, n, self._n_edges, nbr, eid, degs]
            return nbr, eid, degs
        _, n_cov, e_cov, nbr, eid, deg = c
        if n > nbr.shape[0]:
            extra = max(n - nbr.shape[0], nbr.shape[0] // 2)
            nbr = np.vstack([nbr, np.full((extra, nbr.shape[1]), -1, dtype=np.int64)])
            eid = np.vstack([eid, np.full((extra, eid.shape[1]), -1, dtype=np.int64)])
            deg = np.concatenate([deg, np.zeros(extra, dtype=np.int64)])
        if e_cov < self._n_edges:
            new = np.arange(e_cov, self._n_edges)
            new = new[self._edge_valid[new]]
            if new.size:
                src = np.concatenate([self._eu[new], self._ev[new]])
                order = np.argsort(src, kind="stable")
                src = src[order]
                dst = np.concatenate([self._ev[new], self._eu[new]])[order]
                ee = np.concatenate([new, new])[order]
                col = deg[src] + np.arange(src.size) - np.searchsorted(src, src, side="left")
                nbr, eid = self._widen(nbr, eid, int(col.max()) + 1)
                nbr[src, col] = dst
                eid[src, col] = ee
                deg += np.bincount(src, minlength=deg.shape[0])
        self._arr_adj = [self._removal_version, n, self._n_edges, nbr, eid, deg]
        return nbr, eid, deg

    @staticmethod
    def _widen(nbr: np.ndarray, eid: np.ndarray, needed: int) -> tuple[np.ndarray, np.ndarray]:
        if needed <= nbr.shape[1]:
            return nbr, eid
        extra = max(needed, 2 * nbr.shape[1]) - nbr.shape[1]
        pad = np.full((nbr.shape[0], extra), -1, dtype=np.int64)
        return np.hstack([nbr, pad]), np.hstack([eid, pad])

    def _patch_array_adjacency(self, ends: list[tuple[int, int, int]], add: bool) -> None:
        """:meth:`_patch_adjacency` for the array adjacency (removal: swap with the row's last entry)."""
        c = self._arr_adj
        if c is None or c[0] != self._removal_version:
            return
        if len(ends) > _ARRAY_PATCH_LIMIT:
            self._arr_adj = None
            return
        _, n_cov, e_cov, nbr, eid, deg = c
        for e, a, b in ends:
            if e >= e_cov:  # appended (when valid) by the next array_adjacency call
                continue
            for x, y in ((a, b), (b, a)):
                d = int(deg[x])
                if add:
                    if d >= nbr.shape[1]:
                        nbr, eid = self._widen(nbr, eid, d + 1)
                    nbr[x, d] = y
                    eid[x, d] = e
                    deg[x] = d + 1
                else:
                    i = int(np.flatnonzero(eid[x, :d] == e)[0])
                    nbr[x, i] = nbr[x, d - 1]
                    eid[x, i] = eid[x, d - 1]
                    nbr[x, d - 1] = -1
                    eid[x, d - 1] = -1
                    deg[x] = d - 1
        self._arr_adj = [self._removal_version + 1, n_cov, e_cov, nbr, eid, deg]

    def python_weights(self) -> list[float]:
        """The roadmap weights as a Python list indexed by edge id (cached per ``weights_version``).

        Small weight updates patch the cached list in place: callers must not keep or modify it.
        """
        if self._py_weights is not None and self._py_weights[0] == self.weights_version:
            return self._py_weights[1]
        lst = self._weights[: self._n_edges].tolist()
        self._py_weights = (self.weights_version, lst)
        return lst

    def _weights_written(self, ids: np.ndarray, vals: np.ndarray) -> None:
        """Bump ``weights_version``; patch the cached Python weight list in place for small updates."""
        cache = self._py_weights
        self.weights_version += 1
        if cache is None or cache[0] != self.weights_version - 1 or ids.size > _PATCH_LIMIT:
            self._py_weights = None
            return
        lst = cache[1]
        if len(lst) < self._n_edges:
            lst.extend([0.0] * (self._n_edges - len(lst)))
        for e, val in zip(ids.tolist(), vals.tolist()):
            lst[e] = val
        self._py_weights = (self.weights_version, lst)
