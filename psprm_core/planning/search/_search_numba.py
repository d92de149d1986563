"""Numba kernels behind :mod:`psprm_core.planning.search.search_kernels` (imported only through its :func:`kernels`).

Compiled on the first call of each kernel and cached on disk (``cache=True``).
"""

import numpy as np
from numba import njit

jit = njit(cache=True, nogil=True)


@jit
def _less(ka, na, kb, nb):  # pragma: no cover - compiled
    return ka < kb or (ka == kb and na < nb)


@jit
def _push(keys, nodes, size, key, node):  # pragma: no cover - compiled
    """Binary-heap push into the preallocated ``keys``/``nodes`` (room for it guaranteed by the caller); returns the
    new size. The buffers are filled in place, never reallocated: an array variable reassigned inside the search
    loop costs numba a reference-count update per push (the kernels ran 2-3x slower that way)."""
    i = size
    while i > 0:
        p = (i - 1) >> 1
        if _less(key, node, keys[p], nodes[p]):
            keys[i] = keys[p]
            nodes[i] = nodes[p]
            i = p
        else:
            break
    keys[i] = key
    nodes[i] = node
    return size + 1


@jit
def _pop(keys, nodes, size):  # pragma: no cover - compiled
    node = nodes[0]
    size -= 1
    lk, ln = keys[size], nodes[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and _less(keys[c + 1], nodes[c + 1], keys[c], nodes[c]):
            c += 1
        if _less(keys[c], nodes[c], lk, ln):
            keys[i] = keys[c]
            nodes[i] = nodes[c]
            i = c
        else:
            break
    if size > 0:
        keys[i] = lk
        nodes[i] = ln
    return node, size


@jit
def astar(nbr, eid, deg, w, h, use_h, start, goal_mask, max_expansions):  # pragma: no cover - compiled
    """A* (``use_h``) or Dijkstra from ``start`` to the first node of ``goal_mask`` closed.

    Returns ``(goal or -1, cost, expanded, hit_limit, parent, parent_edge, g, closed)``. With a consistent ``h`` a
    closed node is final (Eqs. 5-6) and never improves again; an admissible ``h`` that is not consistent reopens the
    closed nodes it improves, so the result is still optimal. ``h = inf`` prunes a node (no goal reachable). With a
    consistent ``h`` the heap holds at most one entry per directed edge (a node is expanded once, and pushes a
    neighbour only when it improves its g) plus the start; it is allocated once with twice that capacity (never
    reallocated: an array reassigned in the loop costs numba a reference-count update per step), and a search whose
    reopenings would need more returns goal -2.
    """
    n = deg.shape[0]
    inf = np.inf
    g = np.full(n, inf)
    parent = np.full(n, -1, np.int64)
    pedge = np.full(n, -1, np.int64)
    closed = np.zeros(n, np.bool_)
    cap = 2
    for u in range(n):
        cap += 2 * deg[u]
    keys = np.empty(cap, np.float64)
    nodes = np.empty(cap, np.int64)
    g[start] = 0.0
    size = _push(keys, nodes, 0, h[start] if use_h else 0.0, start)
    expanded = 0
    while size > 0:
        u, size = _pop(keys, nodes, size)
        if closed[u]:
            continue
        closed[u] = True
        expanded += 1
        if goal_mask[u]:
            return u, g[u], expanded, False, parent, pedge, g, closed
        if expanded == max_expansions:
            return -1, inf, expanded, True, parent, pedge, g, closed
        gu = g[u]
        for j in range(deg[u]):
            v = nbr[u, j]
            e = eid[u, j]
            nd = gu + w[e]
            if nd < g[v]:  # a closed node is reopened (only an inconsistent heuristic lets that happen)
                key = nd
                if use_h:
                    if h[v] == inf:
                        continue
                    key = nd + h[v]
                closed[v] = False
                g[v] = nd
                parent[v] = u
                pedge[v] = e
                if size == cap:  # only many reopenings get here: give up (goal -2), the caller searches again
                    return -2, inf, expanded, False, parent, pedge, g, closed
                size = _push(keys, nodes, size, key, v)
    return -1, inf, expanded, False, parent, pedge, g, closed


@jit
def _relax_fifo(nbr, deg, hops, queue, tail):  # pragma: no cover - compiled
    """FIFO label correcting of unit-weight hop distances from the ``tail`` nodes queued in ``queue[:tail]``. A node
    is queued at most once at a time (a ring buffer of one slot per node, allocated once: an array reassigned in the
    loop would cost numba a reference-count update per step)."""
    n = hops.shape[0]
    ring = np.empty(n + 1, np.int64)
    queued = np.zeros(n, np.bool_)
    cap = n + 1
    head, size = 0, 0
    for i in range(tail):
        u = queue[i]
        if not queued[u]:
            queued[u] = True
            ring[(head + size) % cap] = u
            size += 1
    while size > 0:
        u = ring[head]
        head = (head + 1) % cap
        size -= 1
        queued[u] = False
        hu = hops[u] + 1.0
        for j in range(deg[u]):
            v = nbr[u, j]
            if hu < hops[v]:
                hops[v] = hu
                if not queued[v]:
                    queued[v] = True
                    ring[(head + size) % cap] = v
                    size += 1
    return hops


@jit
def bfs_hops(nbr, deg, goals, n):  # pragma: no cover - compiled
    """Multi-source BFS: hop distance of the first ``n`` nodes to the nearest goal (``inf`` if unreachable).

    Every node enters the queue at most once (its label is final when first set), so the queue is one array of
    ``n`` slots, never grown (see :func:`_push` on why that matters)."""
    hops = np.full(n, np.inf)
    queue = np.empty(max(n, 1), np.int64)
    tail = 0
    for q in goals:
        if hops[q] == np.inf:
            hops[q] = 0.0
            queue[tail] = q
            tail += 1
    head = 0
    while head < tail:
        u = queue[head]
        head += 1
        hu = hops[u] + 1.0
        for j in range(deg[u]):
            v = nbr[u, j]
            if v < n and hu < hops[v]:
                hops[v] = hu
                queue[tail] = v
                tail += 1
    return hops


@jit
def hops_decrease(nbr, deg, hops, eu, ev):  # pragma: no cover - compiled
    """Exact hop distances after edges ``(eu, ev)`` were added (FIFO label correcting from the new edges)."""
    queue = np.empty(max(16, 2 * eu.shape[0]), np.int64)
    tail = 0
    for i in range(eu.shape[0]):
        a, b = eu[i], ev[i]
        if hops[a] + 1.0 < hops[b]:
            hops[b] = hops[a] + 1.0
            queue[tail] = b
            tail += 1
        elif hops[b] + 1.0 < hops[a]:
            hops[a] = hops[b] + 1.0
            queue[tail] = a
            tail += 1
    return _relax_fifo(nbr, deg, hops, queue, tail)


_DEBRUIJN_MUL = np.uint64(0x03F79D71B4CB0A89)
# bit index of 2^i, looked up by (2^i * _DEBRUIJN_MUL) >> 58 (a de Bruijn sequence)
_DEBRUIJN = np.array([
    0, 1, 48, 2, 57, 49, 28, 3, 61, 58, 50, 42, 38, 29, 17, 4,
    62, 55, 59, 36, 53, 51, 43, 22, 45, 39, 33, 30, 24, 18, 12, 5,
    63, 47, 56, 27, 60, 41, 37, 16, 54, 35, 52, 21, 44, 32, 23, 11,
    46, 26, 40, 15, 34, 20, 31, 10, 25, 14, 19, 9, 13, 8, 7, 6], np.int64)


@jit
def hop_columns(nbr, deg, n, lo, hi, out):  # pragma: no cover - compiled
    """Hop distances between nodes below ``n`` from the sources ``lo <= s < hi`` into columns ``s`` of ``out``
    (n, n) (uint8: saturated at 254, 255 = unreachable; the distances are symmetric, so the columns are the rows
    too, and a node's 64 sources are written side by side); only nodes below ``n`` are traversed. Multi-source BFS
    with bit masks (Then et al., "The More the Merrier: Efficient Multi-Source Graph Traversal", VLDB 2014): 64
    sources share one pass over the edges per BFS level."""
    one = np.uint64(1)
    zero = np.uint64(0)
    seen = np.empty(n, np.uint64)
    front = np.empty(n, np.uint64)
    nxt = np.empty(n, np.uint64)
    for v in range(n):
        for s in range(lo, hi):
            out[v, s] = 255
    for b0 in range(lo, hi, 64):
        b1 = min(b0 + 64, hi)
        seen[:] = zero
        front[:] = zero
        for s in range(b0, b1):
            bit = one << np.uint64(s - b0)
            seen[s] |= bit
            front[s] |= bit
            out[s, s] = 0
        level = 0
        active = True
        while active:
            level += 1
            nxt[:] = zero
            for u in range(n):
                f = front[u]
                if f != zero:
                    for j in range(deg[u]):
                        v = nbr[u, j]
                        if v < n:
                            nxt[v] |= f
            active = False
            lv = min(level, 254)
            for v in range(n):
                new = nxt[v] & ~seen[v]
                front[v] = new
                if new != zero:
                    active = True
                    seen[v] |= new
                    while new != zero:  # each set bit: its index by a de Bruijn multiplication
                        low = new & (~new + one)
                        i = _DEBRUIJN[(low * _DEBRUIJN_MUL) >> np.uint64(58)]
                        out[v, b0 + i] = lv
                        new ^= low


@jit
def query_hops(table, R, nbr, deg, eu, ev, goals):  # pragma: no cover - compiled
    """A query's hop counts (rows of ``deg``,) to ``goals`` from a hop table (R, R) (Heuristics.query_hops): 0 at the
    goals, the other query nodes (ids >= R) by a BFS over the query's own edges ``(eu, ev)`` among them, each roadmap
    node 1 + the smallest table distance to a roadmap neighbour of a labelled query node plus that node's count, then
    lowered along the query's edges by FIFO label correcting (:func:`hops_decrease`)."""
    rows = deg.shape[0]
    inf = np.inf
    hops = np.full(rows, inf)
    for q in goals:
        hops[q] = 0.0
    m = eu.shape[0]
    changed = True
    while changed:  # Bellman-Ford over the few query-query edges
        changed = False
        for i in range(m):
            a, b = eu[i], ev[i]
            if a >= R and b >= R:
                if hops[a] + 1.0 < hops[b]:
                    hops[b] = hops[a] + 1.0
                    changed = True
                elif hops[b] + 1.0 < hops[a]:
                    hops[a] = hops[b] + 1.0
                    changed = True
    for i in range(m):
        for k in range(2):
            q, r = (eu[i], ev[i]) if k == 0 else (ev[i], eu[i])
            if q >= R and r < R and hops[q] < inf:
                off = hops[q] + 1.0
                row = table[r]
                for x in range(R):
                    t = row[x]
                    if t != 255 and t + off < hops[x]:
                        hops[x] = t + off
    return hops_decrease(nbr, deg, hops, eu, ev)
