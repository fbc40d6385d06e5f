"""Superlevel-set components of a function on a graph: where each cluster meets another.

Vertices are added in decreasing order of the function; a union-find joins each one to its
already-added neighbours (Hartigan's cluster tree). The level at which two components that
each hold a significant peak first join is a saddle between clusters; a vertex whose value is
not significantly above its cluster's highest such saddle is noise.
"""

import numpy as np

from .jit import kernel


@kernel(inline="always")
def _find(parent, v):
    root = v
    while parent[root] != root:
        root = parent[root]
    while parent[v] != root:  # path compression
        nxt = parent[v]
        parent[v] = root
        v = nxt
    return root


@kernel(entry=True)
def superlevel_noise(order, indptr, indices, values, significant, peak_of, margin):
    """Noise among the vertices of a graph carrying ``values``.

    order: the vertices by decreasing value; (indptr, indices): the adjacency (CSR);
    significant: marks the significant peaks; peak_of[v]: the significant peak of v's cluster.
    A vertex is noise when its value is below its cluster's base plus ``margin``, the base
    being the value at which the cluster's superlevel component first meets another one
    holding a significant peak (its highest saddle with another cluster; none for a cluster
    that never meets one). Returns the noise mask."""
    m = order.shape[0]
    parent = np.arange(m)
    added = np.zeros(m, np.bool_)
    top = np.where(significant, np.arange(m), -1)  # per root: its highest significant peak
    base = np.full(m, -np.inf)  # per significant peak: where its cluster meets another
    noise = np.zeros(m, np.bool_)
    for i in range(m):
        v = order[i]
        added[v] = True
        for j in range(indptr[v], indptr[v + 1]):
            u = indices[j]
            if not added[u]:
                continue
            a = _find(parent, v)
            b = _find(parent, u)
            if a == b:
                continue
            ta = top[a]
            tb = top[b]
            if ta >= 0 and tb >= 0:
                if base[ta] == -np.inf:
                    base[ta] = values[v]
                if base[tb] == -np.inf:
                    base[tb] = values[v]
            parent[b] = a
            if ta < 0 or (tb >= 0 and values[tb] > values[ta]):
                top[a] = tb
    for v in range(m):
        p = peak_of[v]
        if p >= 0 and values[v] < base[p] + margin:
            noise[v] = True
    return noise
