"""Search results, the lazy search's verification answer and the helpers the roadmap searches share (Eq. 4)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence, Union

import numpy as np

from ...errors import InputError
from ..objectives import ArrayLike
from ..results import Failure
from . import search_kernels
from .graph import Roadmap

Backend = str  # "auto" (compiled when numba is available) or "python"


@dataclass
class SearchResult:
    """Outcome of :func:`astar` / :func:`lazy_astar`.

    Attributes
    ----------
    path : list of int
        Node ids from the start to the reached goal (empty on failure).
    cost : float
        Sum of the edge weights along ``path`` (``inf`` on failure).
    expanded : int
        Nodes expanded (popped and closed), summed over all searches for :func:`lazy_astar`.
    success : bool
        Whether a path was found.
    reason : str
        Human-readable status (why it failed, or ``"ok"``).
    failure : Failure
        The kind of failure (``Failure.NONE`` on success).
    edges : list of int
        Edge ids along ``path``.
    goal : int or None
        The goal node reached.
    iterations : int
        Number of searches run (1 for :func:`astar`).
    invalidated_edges : list of int
        Edges the :func:`lazy_astar` callback rejected.
    updated_edges : dict
        ``{edge id: new weight}`` reported by the :func:`lazy_astar` callback.
    verified_edges : list of int
        Edges the :func:`lazy_astar` callback checked (accepted or rejected).
    """

    path: list[int]
    cost: float
    expanded: int
    success: bool
    reason: str
    failure: Failure = Failure.NONE
    edges: list[int] = field(default_factory=list)
    goal: int | None = None
    iterations: int = 1
    invalidated_edges: list[int] = field(default_factory=list)
    updated_edges: dict[int, float] = field(default_factory=dict)
    verified_edges: list[int] = field(default_factory=list)
    g: np.ndarray | None = field(default=None, repr=False)  # compiled search: cost from the start of every node
    closed: np.ndarray | None = field(default=None, repr=False)  # and which nodes it closed (g exact there)


@dataclass
class EdgeCheck:
    """Answer of a :func:`lazy_astar` verification callback.

    Attributes
    ----------
    invalid : sequence of int
        Edge ids that must not be used (collision, invalid projection, ...).
    weights : mapping int -> float, optional
        Updated (verified) weights of some edges, e.g. Eq. 2 recomputed with the Eq. 1 perception score of the
        interpolated configurations.  Edges passed to the callback and absent from both fields keep their weight.
    """

    invalid: Sequence[int] = ()
    weights: Mapping[int, float] | None = None


VerifyCallback = Callable[[np.ndarray, list[int]], Union[EdgeCheck, Iterable[int], None]]


def _weights_array(graph: Roadmap, weights: ArrayLike | None) -> np.ndarray:
    """Edge weights indexed by edge id as float64 numpy (``None`` = the roadmap's own weights)."""
    if weights is None:
        return np.asarray(graph.weights)
    if hasattr(weights, "detach"):  # torch tensor
        weights = weights.detach().cpu().numpy()
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.shape[0] != graph.n_edges:
        raise InputError(f"weights has {w.shape[0]} entries, the roadmap has {graph.n_edges} edge slots")
    return w


def _weights_list(graph: Roadmap, weights: ArrayLike | None) -> list[float]:
    """Edge weights as a Python list (cached for the roadmap's own weights)."""
    if weights is None:
        return graph.python_weights()
    return _weights_array(graph, weights).tolist()


def _node_ids(graph: Roadmap, nodes: int | Iterable[int] | np.ndarray, what: str) -> np.ndarray:
    arr = np.unique(np.asarray(list(nodes) if not isinstance(nodes, (int, np.integer, np.ndarray)) else nodes,
                               dtype=np.int64).reshape(-1))
    if arr.size and (arr.min() < 0 or arr.max() >= graph.n_nodes):
        raise InputError(f"{what} node id out of range [0, {graph.n_nodes})")
    return arr


def _compiled(backend: Backend = "auto") -> bool:
    """Whether to run the numba kernels (``backend`` "auto" with numba importable) or the Python loops."""
    if backend not in ("auto", "python"):
        raise InputError(f"unknown search backend {backend!r}; use 'auto' or 'python'")
    return backend == "auto" and search_kernels.available()


def _scipy_matrix(graph: Roadmap, data: np.ndarray | None) -> Any:
    """``scipy.sparse.csr_array`` of the valid edges (both directions); ``data`` per CSR entry (ones if None)."""
    from scipy.sparse import csr_array

    csr = graph.csr()
    n = graph.n_nodes
    vals = np.ones(csr.nnz, dtype=np.float64) if data is None else data
    # Explicit zero entries are kept as zero-weight edges by scipy.sparse.csgraph (zero weights are legal, Eq. 2).
    return csr_array((vals, csr.indices, csr.indptr), shape=(n, n))


def min_edge_cost(graph: Roadmap, weights: ArrayLike | None = None) -> float:
    """Minimum finite edge weight over the valid edges, Eq. 4 (0 when the roadmap has no finite edge)."""
    w = _weights_array(graph, weights)
    valid = np.asarray(graph.edge_valid)
    c = float(np.min(w, where=valid, initial=np.inf)) if w.size else np.inf  # no copy of the weights
    if not np.isfinite(c):  # no finite edge (NaN weights are rejected when set)
        return 0.0
    if c < 0:
        raise InputError("edge weights must be non-negative for the hop heuristic (Eqs. 5-6)")
    return c


def path_cost(graph: Roadmap, path: Sequence[int], weights: ArrayLike | None = None) -> float:
    """Sum of the weights along a node path (``KeyError`` when consecutive nodes are not connected)."""
    w = _weights_array(graph, weights)
    return float(w[graph.edge_ids_of_path(path)].sum()) if len(path) > 1 else 0.0
