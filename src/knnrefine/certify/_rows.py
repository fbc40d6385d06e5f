"""Rows of integers matched in linear time, for certify's checks of a mesh's combinatorics
(cells listed once, facets shared by two, edges counted, returned cells found in the torus):
rows are grouped by a small integer each carries (a vertex index: a counting sort), and
compared only within their group, by a hash first. ``np.unique(axis=0)`` and sorts of the
rows as bytes answered the same several times slower at 10^5-10^6 cells."""

import numpy as np

from .._engine.jit import kernel
from .._engine.threads import in_chunks


def as_index(a):
    """``a`` as a contiguous integer array for certify's kernels: as it is where it is the
    engine's int32, else int64 (a copy). Kernels are compiled for both; no copy of a mesh's
    cells is made where it came from refine."""
    a = np.asarray(a)
    if a.dtype == np.int32:
        return np.ascontiguousarray(a)
    return np.ascontiguousarray(a, np.int64)


def as_offsets(a):
    """A mesh's offsets in whole periods for certify's kernels: as they are where they are
    the engine's int8, else int64 (a copy)."""
    a = np.asarray(a)
    if a.dtype == np.int8:
        return np.ascontiguousarray(a)
    return np.ascontiguousarray(a, np.int64)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def rows_equal(a, i, b, j):
    """Whether row i of a equals row j of b (as wide)."""
    for c in range(a.shape[1]):
        if a[i, c] != b[j, c]:
            return False
    return True


def row_classes(rows, group, m):
    """For each row of ``rows`` (n, c) int64, the index of the first row equal to it (in
    row order): equal rows share it. ``group`` (n,) in [0, m): equal rows have equal groups
    (a vertex of the row, say); only rows of a group are compared, the groups on every
    core."""
    if len(rows) >= 2**31:  # (labels and the group order are int32)
        raise ValueError("row_classes: at most 2^31 - 1 rows")
    rows = as_index(rows)
    start, order = grouped(as_index(group), m)
    hashes = np.empty(len(rows), np.uint64)
    label = np.arange(len(rows), dtype=np.int32)

    def call(a, b):
        _label_groups(rows, start, order, hashes, label, a, b)

    in_chunks(call, m, least=4096)
    return label


@kernel(entry=True, lazy=True)
def grouped(group, m):
    """(each group's first place, the rows in group order): a counting sort."""
    n = len(group)
    start = np.zeros(m + 1, np.int64)
    for i in range(n):
        start[group[i] + 1] += 1
    for v in range(m):
        start[v + 1] += start[v]
    place = start[:m].copy()
    order = np.empty(n, np.int32)  # (rows < 2^31: a table of 2^31 rows holds 16 GB at least)
    for i in range(n):
        order[place[group[i]]] = i
        place[group[i]] += 1
    return start, order


@kernel(entry=True, lazy=True, nogil=True)
def _label_groups(rows, start, order, hashes, label, v0, v1):
    """``row_classes``' work for groups [v0, v1): each row hashed, the group sorted by
    (hash, index), rows of equal hash compared in full, the first index labelling."""
    c = rows.shape[1]
    for v in range(v0, v1):
        lo, hi = start[v], start[v + 1]
        for a in range(lo, hi):
            i = order[a]
            h = np.uint64(1469598103934665603)
            for j in range(c):
                h = (h ^ np.uint64(rows[i, j] & 0xFFFFFFFFFFFF)) * np.uint64(1099511628211)
            hashes[i] = h
        for a in range(lo + 1, hi):  # insertion sort of the group by (hash, index)
            i = order[a]
            b = a - 1
            while b >= lo and (hashes[order[b]] > hashes[i]
                               or (hashes[order[b]] == hashes[i] and order[b] > i)):  # fmt: skip
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = i
        a = lo
        while a < hi:  # runs of equal hash: rows compared in full, the first index labels
            b = a + 1
            while b < hi and hashes[order[b]] == hashes[order[a]]:
                b += 1
            for x in range(a + 1, b):
                i = order[x]
                for y in range(a, x):
                    p = order[y]
                    if label[p] != p:
                        continue
                    if rows_equal(rows, i, rows, p):
                        label[i] = p
                        break
            a = b
