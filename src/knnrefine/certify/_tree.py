"""certify's own kd-tree, apart from the engine's index: what closed balls hold (stopping once
they hold enough), k-th nearest distances, and each point's nearest sites with their ties.

The engine's counting index answers the refinement's questions; a certificate that asked it
would check the engine with itself. This tree is built another way and shares nothing with
it: in any dimension, on axes that may wrap (a torus, ``period[a] > 0``) or not, over points
that may carry weights (a point of weight 0 holds nothing and is left out by the caller).

Built along a Morton curve: the points are sorted by their Morton codes (TREE_BITS bits a
coordinate over their bounding box, a radix sort) and a node of more than ``LEAF`` points
splits where its codes' highest differing bit turns, a quadtree's midpoint split of its cell,
so that no node is long and thin and the build is a sort and one pass; where the codes no
longer tell the points apart, the sliding-midpoint rule (Maneewongvatana and Mount) splits
on: the middle of the tight box's widest side. A node whose points all coincide is never
split, whatever its size, and is asked about as one weighted point. Every node keeps its
tight box and its compensated weight total, so a ball that covers a node adds the total
without visiting its points.

Queries (each ``nogil``, over a range of queries, run on every core by ``in_chunks``):

* ``held``: what each closed ball holds, stopping once the sum reaches ``stop`` (certify
  asks "below k?": it needs the count exactly only where it is below k, and the counts at
  or above k again, in full, only where a check fails). Read from the grid of the points'
  Morton runs (``_grid_held``: the cells of about the ball's size, no walk from a root);
  where the grid leaves a ball, a depth-first walk that adds whole nodes inside it;
* ``kth``: the least radius whose closed ball holds weight k (d_{P,k}; unweighted, the k-th
  nearest distance). Queries come along a Morton curve and are answered in blocks: a run of
  them in a small box reads one window of points, gathered once and sorted into buckets,
  and each query reads only the buckets its ball meets, first the ball of 1 + GUESS times
  the answer before it (d_{P,k} is 1-Lipschitz, so each answer bounds the next); depth
  first, nearer child first, where a block starts or its window cannot answer;
* ``nearest``: each query's nearest site and every site as near up to a tie tolerance (the
  closed Voronoi cells a point counts for).

A node's box is tested with the same rounded arithmetic as its points (distances along an
axis and their squares are monotone in the coordinates), so adding or skipping a whole node
gives what testing its points one by one gives.
"""

import math
import threading
from collections import namedtuple

import numpy as np

from .._engine.geometry import plus_compensated  # shared with the engine, as _metric's sums
from .._engine.jit import kernel
from .._engine.threads import in_chunks
from ._predicates import UNSURE, orient3d_at
from ._rows import as_index, as_offsets

LEAF = 16  # points in a leaf, at most (nodes of coinciding points excepted)
GRID = 16  # buckets a side of a k-th query's window in space, at most
GRID2 = 32  # and in the plane
GUESS = 0.1  # a k-th query first reads the ball of (1 + GUESS) times the answer before it
SPAN = 8.0  # a block of k-th queries lies in a box of side SPAN times its first's answer
SPAN3 = 2.5  # (in space: a window grows as the cube of its side)
MARGIN = 1.25  # and reads the points within MARGIN times that answer of the box
HISTOGRAM = 64  # bins of the histogram that finds the k-th of a query's distances
FEW = 64  # a weighted k-th query's distances sorted in place up to this many
TREE_BITS = 20  # bits of each coordinate in the tree's Morton codes in the plane
TREE_BITS3 = 14  # and in space (below them, nodes split by the sliding midpoint)


def _build(pts, w, leaf, unit, scratch=False):
    """The tree over ``pts`` (n, d) with weights ``w`` (n,), ``unit`` whether each is 1:
    (points and weights permuted so that each node owns a contiguous range (unit: the
    weights one placeholder 1, ``_weight``), the nodes, the depth, the ``Grid`` of its
    Morton runs, or None). The points are sorted along a Morton curve (``_morton_sorted``,
    TREE_BITS a coordinate), then split by ``_split_sorted``; ``scratch``: ``pts`` is
    permuted in place, no copy. The grid keeps the codes (its runs below the table's level
    are found by bisecting them: worked out again from the coordinates instead, k-th
    queries on the earthquakes' clustered sphere took 60% longer)."""
    d = pts.shape[1]
    bits = TREE_BITS if d == 2 else TREE_BITS3
    code, order, lo, scale = morton_sorted(pts, bits)
    p, ww, T, depth = _split_sorted(pts, w, code, order, leaf, unit, scratch)
    del order
    finite = bool(np.isfinite(T[0, 4:]).all())  # (no points: one far away, no grid)
    box = T[0, 4 : 4 + d], T[0, 4 + d :]
    grid = _grid_of(p, ww, unit, code, lo, scale, bits, *box) if finite else None
    return p, ww, T, depth, grid


Grid = namedtuple("Grid", ["code", "table", "level0", "bits", "lo", "scale", "pmin", "pmax",
                           "margin", "prefix", "radial"])  # fmt: skip


def _grid_of(p, w, unit, code, lo, scale, bits, pmin, pmax):
    """The grid over the tree's points ``p`` weighing ``w`` (sorted along the Morton
    curve of ``code``, whose frame is ``lo``, ``scale``; within [pmin, pmax], the root's
    box): its codes, its table at the coarsest level of at most
    GRID_FILL points a cell on average (and at most 2^GRID_TABLE cells), how far a point
    may lie outside its cell's rounded box, (weighted, ``unit`` False) the weights'
    compensated prefix sums (``prefix`` (2, n + 1): a run's weight is a difference of
    two, in double-double), and the range of the points' squared distances from the
    origin (``radial``: on a sphere, a thin shell, so that a ball skips the cells off it
    unread)."""
    n, d = p.shape
    if n >= 2**31 - 1:  # (the table's runs are int32)
        return None
    level0 = 0
    while (1 << (d * level0)) * GRID_FILL < n and d * (level0 + 1) <= GRID_TABLE and level0 < bits:
        level0 += 1
    table = _grid_table(code, d, level0, bits)
    pmin, pmax = np.ascontiguousarray(pmin), np.ascontiguousarray(pmax)
    step = np.divide(1.0, scale, out=np.zeros(d), where=scale > 0)
    margin = 2.0 * step + 8.0 * np.finfo(float).eps * (np.abs(lo) + np.abs(pmin) + np.abs(pmax))
    prefix = np.zeros((2, 1)) if unit else _prefix_sums(w)
    low, high = np.inf, -np.inf  # the points' squared distances from the origin
    for a in range(0, n, 1 << 16):  # (a chunk at a time: no n-long copy)
        norm2 = np.einsum("ij,ij->i", p[a : a + (1 << 16)], p[a : a + (1 << 16)])
        low, high = min(low, float(norm2.min())), max(high, float(norm2.max()))
    radial = np.array([low * (1.0 - 1e-9), high * (1.0 + 1e-9)])
    return Grid(code, table, level0, bits, lo, scale, pmin, pmax, margin, prefix, radial)


@kernel(entry=True, lazy=True, nogil=True)
def _prefix_sums(w):
    """(2, n + 1): the sums of w[:j], each as a total and its compensation."""
    out = np.zeros((2, w.shape[0] + 1))
    s = 0.0
    c = 0.0
    for j in range(w.shape[0]):
        s, c = plus_compensated(s, c, w[j])
        out[0, j + 1] = s
        out[1, j + 1] = c
    return out


@kernel(entry=True, lazy=True, nogil=True)
def _split_sorted(pts, w, code, order, leaf, unit, inplace):
    """The tree over pts[order], w[order] (``_build``), ``code`` their Morton codes, sorted
    (``inplace``: pts itself permuted, and ``order`` spent on it; ``unit``: no weights,
    one placeholder 1 for all).
    A node of more than ``leaf`` points splits where its codes' highest differing bit
    turns to 1 (a quadtree's midpoint split of its cell, so no node is long and thin;
    a run of equal halves is one split); a node whose codes are all equal (points closer
    than the codes resolve) splits by the sliding-midpoint rule (Maneewongvatana and
    Mount): the middle of its tight box's widest side, moved to the points where one side
    would be empty; a node whose points all coincide is never split. Then, from the leaves
    up, each node's tight box and weight total (its count where ``unit``, else compensated:
    the sum of its points).
    A node is one row of ``T`` (nodes, 4 + 2 d), all a query reads of it in one or two
    cache lines: lo, hi, its first child (-1 at a leaf; the second follows the first), its
    weight total, its tight box (mins, then maxes)."""
    n, d = pts.shape
    ww = np.ones(1) if unit else np.empty(n)
    if not unit:
        for i in range(n):
            ww[i] = w[order[i]]
    if inplace:  # each cycle of the permutation in turn, its rows marked done (~order)
        p = pts
        held = np.empty(d)
        for i in range(n):
            if order[i] < 0:
                continue
            for a in range(d):
                held[a] = p[i, a]
            j = i
            while True:
                src = order[j]
                order[j] = ~src
                if src == i:
                    for a in range(d):
                        p[j, a] = held[a]
                    break
                for a in range(d):
                    p[j, a] = p[src, a]
                j = src
    else:
        p = np.empty((n, d))
        for i in range(n):
            j = order[i]
            for a in range(d):
                p[i, a] = pts[j, a]
    cap = 2 * (n // max(leaf, 1)) + 64
    node = np.empty((cap, 3), np.int64)
    level = np.zeros(cap, np.int64)
    node[0, 0], node[0, 1], node[0, 2] = 0, n, -1
    count = 1
    deepest = 0
    lo_ = np.empty(d)
    hi_ = np.empty(d)
    todo = np.empty(64, np.int64)  # nodes to split, last in first out: a subtree's nodes
    todo[0] = 0  # lie together (depth first), as a query walks them
    top = 1
    while top > 0:
        top -= 1
        i = todo[top]
        lo, hi = node[i, 0], node[i, 1]
        if hi - lo <= leaf:
            continue
        cut = -1
        if code[lo] != code[hi - 1]:  # the first row whose highest differing bit is 1
            bit = np.uint64(1) << np.uint64(63 - _leading_zeros(code[lo] ^ code[hi - 1]))
            a_, b_ = lo, hi - 1  # code[a_] has the bit clear, code[b_] set
            while b_ - a_ > 1:
                mid = (a_ + b_) >> 1
                if code[mid] & bit:
                    b_ = mid
                else:
                    a_ = mid
            cut = b_
        else:  # the sliding midpoint of the tight box's widest side
            for a in range(d):
                lo_[a] = np.inf
                hi_[a] = -np.inf
            for j in range(lo, hi):
                for a in range(d):
                    lo_[a] = min(lo_[a], p[j, a])
                    hi_[a] = max(hi_[a], p[j, a])
            axis = 0
            width = -1.0
            for a in range(d):
                if hi_[a] - lo_[a] > width:
                    width = hi_[a] - lo_[a]
                    axis = a
            if not width > 0.0:  # every point coincides: never split
                continue
            split = 0.5 * (lo_[axis] + hi_[axis])
            if split <= lo_[axis]:  # neighbouring floats: the larger goes right
                split = hi_[axis]
            a_ = lo
            b_ = hi - 1
            while a_ <= b_:
                if p[a_, axis] < split:
                    a_ += 1
                else:
                    for t in range(d):
                        p[a_, t], p[b_, t] = p[b_, t], p[a_, t]
                    if not unit:
                        ww[a_], ww[b_] = ww[b_], ww[a_]
                    b_ -= 1
            cut = a_
        if count + 2 > cap:
            cap = 2 * cap
            node2 = np.empty((cap, 3), np.int64)
            node2[:count] = node[:count]
            level2 = np.zeros(cap, np.int64)
            level2[:count] = level[:count]
            node, level = node2, level2
        node[i, 2] = count
        node[count, 0], node[count, 1], node[count, 2] = lo, cut, -1
        node[count + 1, 0], node[count + 1, 1], node[count + 1, 2] = cut, hi, -1
        level[count] = level[count + 1] = level[i] + 1
        deepest = max(deepest, level[i] + 1)
        if top + 2 > todo.shape[0]:
            todo2 = np.empty(2 * todo.shape[0], np.int64)
            todo2[:top] = todo[:top]
            todo = todo2
        todo[top] = count + 1
        todo[top + 1] = count
        top += 2
        count += 2
    T = np.empty((count, 4 + 2 * d))
    for i in range(count - 1, -1, -1):  # children after their parent: from the leaves up
        lo, hi, child = node[i, 0], node[i, 1], node[i, 2]
        T[i, 0], T[i, 1], T[i, 2] = lo, hi, child
        if child < 0:
            for a in range(d):
                lo_[a] = np.inf
                hi_[a] = -np.inf
            for j in range(lo, hi):
                for a in range(d):
                    lo_[a] = min(lo_[a], p[j, a])
                    hi_[a] = max(hi_[a], p[j, a])
            for a in range(d):
                T[i, 4 + a] = lo_[a]
                T[i, 4 + d + a] = hi_[a]
        else:
            for a in range(d):
                T[i, 4 + a] = min(T[child, 4 + a], T[child + 1, 4 + a])
                T[i, 4 + d + a] = max(T[child, 4 + d + a], T[child + 1, 4 + d + a])
        if unit:
            T[i, 3] = hi - lo
        else:
            s = 0.0
            c = 0.0
            for j in range(lo, hi):
                s, c = plus_compensated(s, c, ww[j])
            T[i, 3] = s + c
    return p, ww, T, deepest


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _weight(w, j):
    """The weight of the tree's point j: w[j], or w[0] where w is the one placeholder 1 of
    an unweighted tree (no n-long array of ones; a weighted tree of one point reads its
    own)."""
    return w[j] if w.shape[0] > 1 else w[0]


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _leading_zeros(v):
    """The number of leading zero bits of the 64-bit v > 0."""
    z = 0
    while not v & (np.uint64(1) << np.uint64(63 - z)):
        z += 1
    return z


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _gap(x, lo, hi, p):
    """The distance along one axis from x to [lo, hi] (on a circle of period p > 0, all
    three in [0, p))."""
    if x < lo:
        g = lo - x
        if p > 0.0:
            g = min(g, x + p - hi)
        return g
    if x > hi:
        g = x - hi
        if p > 0.0:
            g = min(g, lo + p - x)
        return g
    return 0.0


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _along(x, y, p):
    """The distance along one axis from x to y (on a circle of period p > 0)."""
    g = abs(x - y)
    if p > 0.0 and g > p - g:
        g = p - g
    return g


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _reach(x, lo, hi, p):
    """The largest distance along one axis from x to a point of [lo, hi]."""
    if p > 0.0:
        far = x + 0.5 * p if x + 0.5 * p < p else x - 0.5 * p  # the point opposite x
        if lo <= far <= hi:
            return 0.5 * p
        return max(_along(x, lo, p), _along(x, hi, p))
    return max(abs(x - lo), abs(x - hi))


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _box_near2(T, i, x, period):
    d = x.shape[0]
    s = 0.0
    for a in range(d):
        g = _gap(x[a], T[i, 4 + a], T[i, 4 + d + a], period[a])
        s += g * g
    return s


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _box_far2(T, i, x, period):
    d = x.shape[0]
    s = 0.0
    for a in range(d):
        g = _reach(x[a], T[i, 4 + a], T[i, 4 + d + a], period[a])
        s += g * g
    return s


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def point2(pts, j, x, period):
    """The squared distance from x to pts[j], to its nearest copy along each axis of
    period > 0 (``_along``: both in the frame [0, period), as the tree's points, the sites
    and every query are)."""
    s = 0.0
    for a in range(x.shape[0]):
        g = _along(x[a], pts[j, a], period[a])
        s += g * g
    return s


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _sift_up(hk, hw, n):
    """Restore the max-heap hk[:n] (weights hw alongside) after appending at n - 1."""
    j = n - 1
    key, wt = hk[j], hw[j]
    while j > 0:
        parent = (j - 1) >> 1
        if hk[parent] >= key:
            break
        hk[j], hw[j] = hk[parent], hw[parent]
        j = parent
    hk[j], hw[j] = key, wt


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _drop_top(hk, hw, n):
    """Remove the largest entry of the max-heap hk[:n]; returns the new size."""
    n -= 1
    key, wt = hk[n], hw[n]
    j = 0
    while True:
        child = 2 * j + 1
        if child >= n:
            break
        if child + 1 < n and hk[child + 1] > hk[child]:
            child += 1
        if hk[child] <= key:
            break
        hk[j], hw[j] = hk[child], hw[child]
        j = child
    if n > 0:
        hk[j], hw[j] = key, wt
    return n


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _settle(hk, hw, n, k):
    """The weighted candidates hk[:n] (squared distances, weights hw) cut to those needed:
    sorted, the least squared radius holding weight k found (compensated running sum), the
    farther ones dropped. Returns (that squared radius or inf, the new size)."""
    order = np.argsort(hk[:n])
    keys = hk[:n][order]
    wts = hw[:n][order]
    s = 0.0
    c = 0.0
    for j in range(n):
        s, c = plus_compensated(s, c, wts[j])
        if s + c >= k:
            hk[: j + 1] = keys[: j + 1]
            hw[: j + 1] = wts[: j + 1]
            return keys[j], j + 1
    hk[:n] = keys
    hw[:n] = wts
    return np.inf, n


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _kth_dfs(pts, w, T, period, xq, k, unit, stack, stack_key, hk, hw):
    """The least radius about xq holding weight k (inf where the points hold less), depth
    first, the nearer child first, pruned by the best radius so far. ``unit`` (every weight
    1): the k nearest kept in a max-heap. Weighted: the candidates within the radius so far,
    cut back (``_settle``) each time they double. Returns (the radius, hk, hw)."""
    dim = xq.shape[0]
    kk = int(math.ceil(k)) if unit else 0
    answer = np.inf
    r2 = np.inf
    n = 0
    settled = 64
    top = 1
    stack[0] = 0
    stack_key[0] = _box_near2(T, 0, xq, period)
    while top > 0:
        top -= 1
        i = stack[top]
        if stack_key[top] > r2:
            continue
        child = int(T[i, 2])
        flat = True
        for a in range(dim):
            if T[i, 4 + a] != T[i, 4 + dim + a]:
                flat = False
        if child >= 0 and not flat:
            k0 = _box_near2(T, child, xq, period)
            k1 = _box_near2(T, child + 1, xq, period)
            if k0 <= k1:
                stack[top], stack_key[top] = child + 1, k1
                stack[top + 1], stack_key[top + 1] = child, k0
            else:
                stack[top], stack_key[top] = child, k0
                stack[top + 1], stack_key[top + 1] = child + 1, k1
            top += 2
            continue
        lo = int(T[i, 0])
        hi = int(T[i, 1]) if not flat else int(T[i, 0]) + 1
        for j in range(lo, hi):
            d2 = point2(pts, j, xq, period)
            if d2 > r2:
                continue
            if unit:
                copies = min(int(T[i, 3]), kk) if flat else 1
                for _ in range(copies):  # coinciding points: a copy for each
                    if n < kk:
                        hk[n], hw[n] = d2, 1.0
                        n += 1
                        _sift_up(hk, hw, n)
                        if n == kk:
                            r2 = min(r2, hk[0])
                    elif d2 < hk[0]:
                        n = _drop_top(hk, hw, n)
                        hk[n], hw[n] = d2, 1.0
                        n += 1
                        _sift_up(hk, hw, n)
                        r2 = hk[0]
            else:
                if n == hk.shape[0]:
                    hk2 = np.empty(2 * n)
                    hw2 = np.empty(2 * n)
                    hk2[:n] = hk
                    hw2[:n] = hw
                    hk, hw = hk2, hw2
                hk[n], hw[n] = d2, (_weight(w, j) if not flat else T[i, 3])
                n += 1
                if n >= 2 * settled:
                    bound, n = _settle(hk, hw, n, k)
                    r2 = min(r2, bound)
                    settled = max(n, 32)
    if unit:
        if n == kk and kk > 0:
            answer = math.sqrt(hk[0])
    else:
        bound, n = _settle(hk, hw, n, k)
        if bound < np.inf:
            answer = math.sqrt(bound)
    return answer, hk, hw


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _select(v, n, kth):
    """The kth smallest (0-based) of v[:n], v partly reordered (Hoare's quickselect)."""
    lo = 0
    hi = n - 1
    while lo < hi:
        mid = (lo + hi) >> 1
        a, b, c = v[lo], v[mid], v[hi]
        pivot = max(min(a, b), min(max(a, b), c))
        i = lo
        j = hi
        while i <= j:
            while v[i] < pivot:
                i += 1
            while v[j] > pivot:
                j -= 1
            if i <= j:
                v[i], v[j] = v[j], v[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            return v[kth]
    return v[kth]


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _gather(pts, w, T, period, c, r2, stack, gx, gw):
    """The points (and weights) within the closed ball (c, sqrt(r2)) copied to gx, gw;
    their number, or -1 where they do not fit."""
    d = c.shape[0]
    n = 0
    top = 1
    stack[0] = 0
    while top > 0:
        top -= 1
        i = stack[top]
        if _box_near2(T, i, c, period) > r2:
            continue
        child = int(T[i, 2])
        whole = _box_far2(T, i, c, period) <= r2
        if child >= 0 and not whole:
            stack[top] = child
            stack[top + 1] = child + 1
            top += 2
            continue
        for j in range(int(T[i, 0]), int(T[i, 1])):
            if whole or point2(pts, j, c, period) <= r2:
                if n == gx.shape[0]:
                    return -1
                for a in range(d):
                    gx[n, a] = pts[j, a]
                gw[n] = _weight(w, j)
                n += 1
    return n


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def offset(x, c, p):
    """The signed distance along one axis from c to x, taken the nearer way round a circle
    of period p > 0 (by whole periods, however many). certify's own, as the engine's
    ``_wrapped`` is the engine's: certify calls no engine kernel."""
    g = x - c
    if p > 0.0:
        g -= p * math.floor(g / p + 0.5)
    return g


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def edge_at(sites, neighbours, shift, period, v, j, a):
    """Axis a of the Voronoi cells' edge j of site v as a vector from it (``steps.Cells``):
    sites[neighbours[j]] - sites[v], plus shift[j] whole periods where the sites wrap
    (``shift`` (e, d); (e, 0) where none do). Worked out where it is read, the one rule,
    rather than held: (e, d) vectors are the cells' largest array."""
    g = sites[neighbours[j], a] - sites[v, a]
    if shift.shape[1] > 0:
        g = g + np.float64(shift[j, a]) * period[a]
    return g


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def walk_nearest(sites, first, neighbours, period, xq, v):
    """(the site nearest xq, its squared distance) by a walk on a verified Delaunay
    triangulation's neighbour lists from site v: to any nearer neighbour until none is (a
    Delaunay vertex with no nearer neighbour is the nearest). Distances to each site's
    nearest copy (``point2``): the walk moves only to a site nearer on the torus, and
    where it stops no neighbour's copy is nearer, the cells' own among them. (-1, its
    distance) where the walk took more steps than there are sites (rounding in a near tie
    that never settles)."""
    m = len(first) - 1
    best = point2(sites, v, xq, period)
    for _ in range(m + 1):
        move = -1
        for j in range(first[v], first[v + 1]):
            u = neighbours[j]
            s = point2(sites, u, xq, period)
            if s < best:
                best, move = s, u
        if move < 0:
            return v, best
        v = move
    return -1, best


@kernel(entry=True, lazy=True, nogil=True)
def _nearest_sites(pts, sites, first, neighbours, period, relative, slack2, owner, start,
                   end):  # fmt: skip
    """For points [start, end) (in the tree's order: each near the one before): owner[i]
    its nearest site (walked from the one before's), and (points, sites) of the other
    sites as near up to the tie tolerance, |p - u|^2 <= |p - v|^2 (1 + relative) +
    slack2 with v the nearest, found from v through such ties (cocircular sites: a tie
    need not be v's neighbour). Returns (ties found, or -1 where a walk did not settle or
    the ties' room ran out, their points, their sites)."""
    m = len(first) - 1
    stamp = np.full(m, -1, np.int64)  # the point whose ties last saw this site
    room = 2 * (end - start) + 64
    tie_p = np.empty(room, np.int64)
    tie_v = np.empty(room, np.int64)
    sv = np.empty(64, np.int64)
    ties = 0
    v = 0
    for i in range(start, end):
        xq = pts[i]
        v, best = walk_nearest(sites, first, neighbours, period, xq, v)
        if v < 0:
            return -1, tie_p[:0], tie_v[:0]
        owner[i] = v
        limit = best * (1.0 + relative) + slack2
        stamp[v] = i
        sv[0] = v
        top = 1
        while top > 0:
            top -= 1
            t = sv[top]
            for j in range(first[t], first[t + 1]):
                u = neighbours[j]
                if stamp[u] == i:
                    continue
                if point2(sites, u, xq, period) <= limit:
                    if ties == room or top == 64:
                        return -1, tie_p[:0], tie_v[:0]
                    stamp[u] = i
                    tie_p[ties] = i
                    tie_v[ties] = u
                    ties += 1
                    sv[top] = u
                    top += 1
        v = owner[i]
    return ties, tie_p[:ties].copy(), tie_v[:ties].copy()


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _bucketed(gx, gw, n, centre, reach, period, bx, bw, first, cell):
    """The window's points gx[:n] (within ``reach`` of ``centre``) sorted into a grid of
    G buckets a side over the cube about centre: copied to bx, bw in bucket order, bucket
    b's rows first[b]:first[b + 1] (b = (i0 G + i1) G + i2: a run of buckets along the
    last axis is one run of rows). G follows n (about 4 points a bucket, at most GRID[dim]),
    and is 1 (one bucket: the points left in gx, gw) for fewer than 128 points, beyond
    three dimensions (or in one) or where an axis wraps at less than 4 reach (offsets would be
    ambiguous). Returns G."""
    dim = gx.shape[1]
    G = 1
    if 2 <= dim <= 3 and reach > 0.0 and n >= 128:  # fewer points: read them all
        G = max(1, min(int((n / 4.0) ** (1.0 / dim)), GRID2 if dim == 2 else GRID))
        for a in range(dim):
            if period[a] > 0.0 and 4.0 * reach > period[a]:
                G = 1
    if G == 1:  # one bucket: the points where they are (gx, gw)
        first[0] = 0
        first[1] = n
        return 1
    side = 2.0 * reach / G
    nb = G**dim
    for b in range(nb + 1):
        first[b] = 0
    for j in range(n):
        b = 0
        for a in range(dim):
            i = min(max(int((offset(gx[j, a], centre[a], period[a]) + reach) / side), 0), G - 1)
            b = b * G + i
        cell[j] = b
        first[b + 1] += 1
    for b in range(nb):
        first[b + 1] += first[b]
    for j in range(n):  # placed from each bucket's end backwards
        b = cell[j]
        first[b + 1] -= 1
        at = first[b + 1]
        for a in range(dim):
            bx[at, a] = gx[j, a]
        bw[at] = gw[j]
    for b in range(nb):  # first[b + 1] now holds bucket b's start
        first[b] = first[b + 1]
    first[nb] = n
    return G


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _bucket_span(o, wide, side, G):
    """The buckets [lo, hi] of a grid of G of ``side`` that [o - wide, o + wide] meets."""
    lo = min(max(int((o - wide) / side), 0), G - 1) if o - wide > 0.0 else 0
    hi = min(max(int((o + wide) / side), 0), G - 1) if o + wide > 0.0 else 0
    return lo, hi


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _read_rows(bx, bw, j0, j1, xq, far, r2, d2, dw, m):
    """The points bx[j0:j1] within sqrt(r2) of xq appended to d2 (squared distances), dw
    (weights) from m; returns the new m. ``far``: each axis' period, inf where it does not
    wrap, so that the distance along it, min(g, far - g), is ``_along``'s without a
    branch; every point is written, the count moving only for those inside."""
    dim = xq.shape[0]
    for j in range(j0, j1):
        s = 0.0
        for a in range(dim):
            g = abs(xq[a] - bx[j, a])
            g = min(g, far[a] - g)
            s += g * g
        d2[m] = s
        dw[m] = bw[j]
        m += s <= r2
    return m


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _kth_in(bx, bw, first, G, centre, reach, xq, period, far, k, unit, r, d2, dw, hist):
    """The least radius about xq holding weight k among the window's points within r of
    it (``_bucketed``: only the buckets the ball meets are read, row by row along the
    first axes, each row's run along the last axis cut to the ball's chord), or -1 where
    they hold less. Distances are those of the points one by one (``_read_rows``), so the
    buckets decide only which points are read: a margin covers the offsets' rounding.
    Unweighted, the k-th of the squared distances is found through a histogram of them
    (``hist``: the bin holding it, then that bin's few values selected)."""
    dim = xq.shape[0]
    r2 = r * r
    m = 0
    if G == 1:
        m = _read_rows(bx, bw, first[0], first[1], xq, far, r2, d2, dw, 0)
    else:
        side = 2.0 * reach / G
        scale = 0.0
        for a in range(dim):
            scale = max(scale, abs(centre[a]) + abs(xq[a]) + period[a] + reach)
        wide = r * (1.0 + 1e-9) + 1e-14 * scale
        w2 = wide * wide
        o0 = offset(xq[0], centre[0], period[0]) + reach
        o1 = offset(xq[1], centre[1], period[1]) + reach
        o2 = offset(xq[dim - 1], centre[dim - 1], period[dim - 1]) + reach
        l0, h0 = _bucket_span(o0, wide, side, G)
        for i0 in range(l0, h0 + 1):
            g0 = max(0.0, i0 * side - o0, o0 - (i0 + 1) * side)
            rem0 = w2 - g0 * g0
            if rem0 < 0.0:
                continue
            l1, h1 = _bucket_span(o1, math.sqrt(rem0), side, G)
            if dim == 2:
                m = _read_rows(bx, bw, first[i0 * G + l1], first[i0 * G + h1 + 1], xq, far,
                               r2, d2, dw, m)  # fmt: skip
                continue
            for i1 in range(l1, h1 + 1):
                g1 = max(0.0, i1 * side - o1, o1 - (i1 + 1) * side)
                rem1 = rem0 - g1 * g1
                if rem1 < 0.0:
                    continue
                l2, h2 = _bucket_span(o2, math.sqrt(rem1), side, G)
                row = (i0 * G + i1) * G
                m = _read_rows(bx, bw, first[row + l2], first[row + h2 + 1], xq, far, r2,
                               d2, dw, m)  # fmt: skip
    s = _kth_of(d2, dw, m, k, unit, 0.0, r2, hist, 0.0, 0.0)
    return math.sqrt(s) if s >= 0.0 else -1.0


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _kth_of(d2, dw, m, k, unit, lo2, r2, hist, s, c):
    """The least of the squared distances d2[:m] (weights dw; each in [lo2, r2]) at which
    the weight reaches k, s (compensation c) lying below them all; -1 where they hold
    less. Unweighted, the (k - s)-th of them, found through a histogram (``hist``: the bin
    holding it, then that bin's few values selected); weighted, in their order, a few
    sorted in place. d2, dw are reordered."""
    if unit:
        need = int(math.ceil(k)) - int(s)
        if need > m:
            return -1.0
        if r2 <= lo2 or m < 4 * hist.shape[0]:  # a few: selected directly
            return _select(d2, m, need - 1)
        nb = hist.shape[0]
        hist[:] = 0
        per = nb / (r2 - lo2)
        for j in range(m):
            hist[min(max(int((d2[j] - lo2) * per), 0), nb - 1)] += 1
        below = 0
        b = 0
        while below + hist[b] < need:
            below += hist[b]
            b += 1
        n = 0
        for j in range(m):  # bin b's values, moved to the front
            v = d2[j]
            d2[n] = v
            n += min(max(int((v - lo2) * per), 0), nb - 1) == b
        return _select(d2, n, need - below - 1)
    if m <= FEW:  # a few: sorted in place with their weights (no array made)
        for j in range(1, m):
            v, u = d2[j], dw[j]
            i = j - 1
            while i >= 0 and d2[i] > v:
                d2[i + 1], dw[i + 1] = d2[i], dw[i]
                i -= 1
            d2[i + 1], dw[i + 1] = v, u
        for j in range(m):
            s, c = plus_compensated(s, c, dw[j])
            if s + c >= k:
                return d2[j]
        return -1.0
    order = np.argsort(d2[:m])
    for j in order:
        s, c = plus_compensated(s, c, dw[j])
        if s + c >= k:
            return d2[j]
    return -1.0


@kernel(entry=True, lazy=True, nogil=True)
def _kth(pts, w, T, depth, period, x, k, unit, out, start, end):
    """out[q] for q in [start, end): the least radius whose closed ball about x[q] holds
    weight k (inf where the points hold less). Queries come in an order where neighbours
    are near (``spatial_order``) and are answered in blocks: a run of them within a box
    of side SPAN a (SPAN3 a in space; a the answer at the run's first, asked depth first:
    ``_kth_dfs``), whose window, every point within half the box's diagonal plus MARGIN a
    of its centre, is gathered once and sorted into buckets (``_bucketed``). Each query
    then reads the ball of (1 + GUESS) times the answer before it (or, d_{P,k} being
    1-Lipschitz, that answer plus their distance, where less), then the largest the
    window holds about it; one
    whose answer lies beyond, or in a window too crowded for its buffer (a void's rim:
    the run is halved until it fits), depth first."""
    dim = x.shape[1]
    stack = np.empty(2 * depth + 4, np.int64)
    stack_key = np.empty(2 * depth + 4)
    kk = int(math.ceil(k)) if unit else 0
    npts = pts.shape[0]
    hk = np.empty(max(min(kk, npts), 64))  # (k beyond the points: the heap never fills)
    hw = np.empty(max(min(kk, npts), 64))
    size = min(max(64 * int(math.ceil(min(k, npts))), 8192), npts + 1)  # a window's points
    span = SPAN if dim <= 2 else SPAN3
    gx = np.empty((size, dim))
    gw = np.empty(size)
    bx = np.empty((size, dim))
    bw = np.empty(size)
    cell = np.empty(size, np.int64)
    first = np.empty(max(GRID2**2, GRID**3) + 1, np.int64)
    d2 = np.empty(size)
    dw = np.empty(size)
    hist = np.empty(HISTOGRAM, np.int64)
    far = np.empty(dim)
    for a in range(dim):
        far[a] = period[a] if period[a] > 0.0 else np.inf
    centre = np.empty(dim)
    lo = np.empty(dim)
    hi = np.empty(dim)
    q = start
    while q < end:
        out[q], hk, hw = _kth_dfs(pts, w, T, period, x[q], k, unit, stack, stack_key, hk, hw)
        a = out[q]
        q += 1
        if not a < np.inf:
            continue
        b = q  # the block: queries [q, b) within a box of side SPAN a about x[q - 1]
        for t in range(dim):
            lo[t] = 0.0
            hi[t] = 0.0
        while b < end:
            fits = True
            for t in range(dim):
                o = offset(x[b, t], x[q - 1, t], period[t])
                if max(hi[t], o) - min(lo[t], o) > span * a:
                    fits = False
            if not fits:
                break
            for t in range(dim):
                o = offset(x[b, t], x[q - 1, t], period[t])
                lo[t] = min(lo[t], o)
                hi[t] = max(hi[t], o)
            b += 1
        n = -1
        while n < 0 and b > q:
            half = 0.0
            for t in range(dim):
                c = x[q - 1, t] + 0.5 * (lo[t] + hi[t])
                if period[t] > 0.0:
                    c = c % period[t]
                centre[t] = c
                half += (0.5 * (hi[t] - lo[t])) ** 2
            reach = math.sqrt(half) * (1.0 + 1e-12) + MARGIN * a
            n = _gather(pts, w, T, period, centre, reach * reach, stack, gx, gw)
            if n < 0:  # crowded: half the block, its box again
                b = q + (b - q) // 2
                for t in range(dim):
                    lo[t] = 0.0
                    hi[t] = 0.0
                for j in range(q, b):
                    for t in range(dim):
                        o = offset(x[j, t], x[q - 1, t], period[t])
                        lo[t] = min(lo[t], o)
                        hi[t] = max(hi[t], o)
        if n < 0:
            continue
        G = _bucketed(gx, gw, n, centre, reach, period, bx, bw, first, cell)
        px, pw = (bx, bw) if G > 1 else (gx, gw)  # one bucket: left in place
        for j in range(q, b):
            xq = x[j]
            answer = -1.0
            before = out[j - 1]
            if before < np.inf:
                delta = math.sqrt(point2(x, j - 1, xq, period))
                gap = math.sqrt(_dist_to(centre, xq, period))
                room = reach * (1.0 - 1e-12) - gap * (1.0 + 1e-12)
                top = min(room, (before + delta) * (1.0 + 1e-12))
                r = min(top, before * (1.0 + GUESS))
                if r > 0.0:
                    answer = _kth_in(px, pw, first, G, centre, reach, xq, period, far, k,
                                     unit, r, d2, dw, hist)  # fmt: skip
                if answer < 0.0 and r < top:
                    answer = _kth_in(px, pw, first, G, centre, reach, xq, period, far, k,
                                     unit, top, d2, dw, hist)  # fmt: skip
            if answer < 0.0:
                answer, hk, hw = _kth_dfs(pts, w, T, period, xq, k, unit,
                                          stack, stack_key, hk, hw)  # fmt: skip
            out[j] = answer
        q = b


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _held_one(pts, w, T, period, xq, rq, stop, stack):
    """The weight in the closed ball (xq, sqrt(rq)), exact below stop, at least stop
    otherwise: depth first, whole nodes inside added without their points."""
    s = 0.0
    c = 0.0
    top = 1
    stack[0] = 0
    while top > 0 and s + c < stop:
        top -= 1
        i = stack[top]
        if _box_near2(T, i, xq, period) > rq:
            continue
        if _box_far2(T, i, xq, period) <= rq:
            s, c = plus_compensated(s, c, T[i, 3])
            continue
        child = int(T[i, 2])
        if child >= 0:
            stack[top] = child
            stack[top + 1] = child + 1
            top += 2
            continue
        for j in range(int(T[i, 0]), int(T[i, 1])):
            if point2(pts, j, xq, period) <= rq:
                s, c = plus_compensated(s, c, _weight(w, j))
    return s + c


@kernel(entry=True, lazy=True, nogil=True)
def _held(pts, w, T, depth, period, x, r2, stop, out, start, end):
    """out[q] for q in [start, end): the weight in the closed ball (x[q], sqrt(r2[q])),
    exact below stop[q], at least stop[q] otherwise (``_held_one``)."""
    stack = np.empty(2 * depth + 4, np.int64)
    for q in range(start, end):
        out[q] = _held_one(pts, w, T, period, x[q], r2[q], stop[q], stack)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _dist_to(c, xq, period):
    s = 0.0
    for a in range(c.shape[0]):
        g = _along(c[a], xq[a], period[a])
        s += g * g
    return s


@kernel(entry=True, lazy=True, nogil=True)
def _cells_held(pts, w, T, depth, period, v, first, neighbours, moved, cell_period, outradii,
                relative, slack2, stop, out, start, end):  # fmt: skip
    """out[s] for s in [start, end): the weight in the closed Voronoi cell of site v[s]
    (``Tree.cells_held``). A node is skipped when it lies beyond the outradius or wholly
    beyond one bisector (with a margin past the tolerance), added whole when it lies within
    the outradius and inside every bisector with a margin, and otherwise opened; on a torus
    the bisector tests use the copy of the node nearest the site and are made only for
    nodes narrower than half a period (the others are opened). A site's edges are worked
    out once (``edge_at``: its neighbours ``moved`` whole periods of the sites' own
    ``cell_period``) into rows of their own."""
    dim = v.shape[1]
    stack = np.empty(2 * depth + 4, np.int64)
    rlo = np.empty(dim)
    rhi = np.empty(dim)
    most_edges = 0
    for q in range(start, end):
        most_edges = max(most_edges, first[q + 1] - first[q])
    edges = np.empty((most_edges, dim))
    for q in range(start, end):
        vq = v[q]
        big = outradii[q] * (1.0 + 1e-9)
        big2 = big * big
        e0, e1 = 0, first[q + 1] - first[q]
        for j in range(e1):
            for a in range(dim):
                edges[j, a] = edge_at(v, neighbours, moved, cell_period, q, first[q] + j, a)
        s = 0.0
        c = 0.0
        top = 1
        stack[0] = 0
        while top > 0 and s + c < stop[q]:
            top -= 1
            i = stack[top]
            if _box_near2(T, i, vq, period) > big2:
                continue
            # the node relative to the site, on a torus its copy nearest the site
            shifted = True
            for a in range(dim):
                lo = T[i, 4 + a] - vq[a]
                hi = T[i, 4 + dim + a] - vq[a]
                p = period[a]
                if p > 0.0:
                    if hi - lo >= 0.5 * p:
                        shifted = False
                    mid = 0.5 * (lo + hi)
                    shift = p * np.floor(mid / p + 0.5)
                    lo -= shift
                    hi -= shift
                rlo[a] = lo
                rhi[a] = hi
            inside = _box_far2(T, i, vq, period) <= big2 and shifted
            outside = False
            if shifted:
                for j in range(e0, e1):
                    ee = 0.0
                    most = 0.0
                    least = 0.0
                    for a in range(dim):
                        ea = edges[j, a]
                        ee += ea * ea
                        if ea >= 0.0:
                            most += rhi[a] * ea
                            least += rlo[a] * ea
                        else:
                            most += rlo[a] * ea
                            least += rhi[a] * ea
                    if 2.0 * most > ee * (1.0 - 1e-9):
                        inside = False
                    reach = big + math.sqrt(ee)
                    if 2.0 * least - ee > 1e-9 * ee + 4.0 * relative * reach * reach + 4.0 * slack2:
                        outside = True
                        break
            if outside:
                continue
            if inside:
                s, c = plus_compensated(s, c, T[i, 3])
                continue
            child = int(T[i, 2])
            if child >= 0:
                stack[top] = child
                stack[top + 1] = child + 1
                top += 2
                continue
            for j in range(int(T[i, 0]), int(T[i, 1])):
                d2 = point2(pts, j, vq, period)
                if d2 > big2:
                    continue
                ok = True
                for t in range(e0, e1):
                    o2 = 0.0
                    for a in range(dim):
                        g = pts[j, a] - vq[a]
                        if period[a] > 0.0:
                            g -= period[a] * np.floor(g / period[a] + 0.5)
                        g -= edges[t, a]
                        o2 += g * g
                    if d2 > o2 * (1.0 + relative) + slack2:
                        ok = False
                        break
                if ok:
                    s, c = plus_compensated(s, c, _weight(w, j))
        out[q] = s + c


@kernel(entry=True, lazy=True, nogil=True)
def _held_caps(pts, w, T, depth, x, outer2, corners, stop, out, start, end):
    """out[q] for q in [start, end): the weight of the points on or above the plane through
    corners[q] (three points (3, 3), counter-clockwise seen from above) among those within
    sqrt(outer2[q]) of x[q], each decided by the filtered orient3d, stopping once it
    reaches stop[q]; returns the (query, point) pairs the filter could not decide, of the
    queries still below their stop (for exact arithmetic)."""
    period = np.zeros(3)
    stack = np.empty(2 * depth + 4, np.int64)
    qs = np.empty(64, np.int64)
    ps = np.empty(64, np.int64)
    used = 0
    for q in range(start, end):
        xq = x[q]
        r_out = outer2[q]
        a = corners[q]
        s = 0.0
        c = 0.0
        top = 1
        stack[0] = 0
        mark = used
        while top > 0 and s + c < stop[q]:
            top -= 1
            i = stack[top]
            if _box_near2(T, i, xq, period) > r_out:
                continue
            child = int(T[i, 2])
            if child >= 0:
                stack[top] = child
                stack[top + 1] = child + 1
                top += 2
                continue
            for j in range(int(T[i, 0]), int(T[i, 1])):
                if point2(pts, j, xq, period) > r_out:
                    continue
                sign = orient3d_at(a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2],
                                   a[2, 0], a[2, 1], a[2, 2], pts[j, 0], pts[j, 1],
                                   pts[j, 2])  # fmt: skip
                if sign == UNSURE:
                    if used == qs.shape[0]:
                        qs2 = np.empty(2 * used, np.int64)
                        ps2 = np.empty(2 * used, np.int64)
                        qs2[:used] = qs
                        ps2[:used] = ps
                        qs, ps = qs2, ps2
                    qs[used] = q
                    ps[used] = j
                    used += 1
                elif sign <= 0:
                    s, c = plus_compensated(s, c, _weight(w, j))
        out[q] = s + c
        if s + c >= stop[q]:
            used = mark  # decided: what it left open is not needed
    return qs[:used].copy(), ps[:used].copy()


@kernel(entry=True, lazy=True, nogil=True)
def _add_weights(rows, cell, w, s, c):
    """The tree's points' weights ``w`` added, compensated, into bins (s, c) by ``cell``:
    point rows[j] into bin cell[j] (``rows`` empty: point j; with ``cell`` empty too,
    nothing)."""
    every = rows.shape[0] == 0
    for j in range(cell.shape[0]):
        b = cell[j]
        s[b], c[b] = plus_compensated(s[b], c[b], _weight(w, j if every else rows[j]))


@kernel(entry=True, lazy=True)
def sums_by(cell, w, m):
    """The weights ``w`` summed into ``m`` bins by ``cell`` (-1: none), compensated."""
    s = np.zeros(m)
    c = np.zeros(m)
    for j in range(cell.shape[0]):
        b = cell[j]
        if b >= 0:
            s[b], c[b] = plus_compensated(s[b], c[b], w[j])
    return s + c


# ---- the grid: the tree's points as runs of a Morton curve --------------------------------
#
# The build sorts the points by Morton code, so the points of any cell of the code's grid
# (2^L cells a side at level L) lie together: a run. A table gives the runs of the cells at
# one level (GRID_FILL points a cell on average); a finer cell's run is found by binary
# search in its parent's. A ball is counted from the cells of side about GRID_SIDE times its
# radius (no finer than the table's) that its box meets, with no walk from a root: a cell
# inside the ball adds its run's length (weighted: the difference of two compensated prefix
# sums, as exact as a node's compensated total), a cell outside is skipped, a cell it cuts
# is read point by point or, where it holds more than GRID_DESCEND points, as its 2^d
# children.

GRID_FILL = 4  # points a cell of the table's level holds, on average, at least
GRID_TABLE = 22  # the table's level has at most 2^GRID_TABLE cells
GRID_SIDE = 0.5  # a ball is first cut into cells of side at least GRID_SIDE its radius
GRID_SIDE3 = 0.25  # (in space: no finer than the table, and a surface's empty cells are skipped)
GRID_AXIS = 64  # cells along one axis a ball reads at most (coarser cells where more)
GRID_CELLS = 4096  # cells a ball reads at first, at most (coarser cells where more)
GRID_DESCEND = 24  # a cell the ball's sphere cuts is read as its children above this
GRID_CROWD = 4096  # a finest cell the sphere cuts and holding more: asked of the tree
GRID_GUESS = 1.0  # a k-th query's first shell: 1 -+ GRID_GUESS / sqrt(k) the answer before
GRID_KTH3 = 32  # in space, k-th queries read from the grid from this k on (the tree's below)
GRID_TRIES = 64  # shells a k-th query reads from the grid before it is asked of the tree


@kernel(entry=True, lazy=True, nogil=True)
def _grid_table(code, d, level, bits):
    """start[c], c in [0, 2^(d level)]: the first of the sorted ``code`` whose cell at
    ``level`` is c or after (the run of cell c is start[c]:start[c + 1])."""
    cells = 1 << (d * level)
    start = np.empty(cells + 1, np.int32)  # (half the cache lines of int64: n < 2^31)
    shift = np.uint64(d * (bits - level))
    n = code.shape[0]
    j = 0
    for c in range(cells + 1):
        while j < n and (code[j] >> shift) < np.uint64(c):
            j += 1
        start[c] = j
    return start


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _lower_bound(code, a, b, key):
    """The first i in [a, b) with code[i] >= key (b where none)."""
    while a < b:
        mid = (a + b) >> 1
        if code[mid] < key:
            a = mid + 1
        else:
            b = mid
    return a


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _cell_run(code, table, level0, bits, d, cell, level):
    """The run (first, end) of the points of cell ``cell`` (its Morton code) at ``level``:
    from the table at its level and above, by bisection of the points' codes below."""
    if level <= level0:
        s = np.uint64(d * (level0 - level))
        return (np.int64(table[np.int64(cell << s)]),
                np.int64(table[np.int64((cell + np.uint64(1)) << s)]))  # fmt: skip
    parent = np.int64(cell >> np.uint64(d * (level - level0)))
    a, b = np.int64(table[parent]), np.int64(table[parent + 1])
    if a == b:
        return a, a
    s = np.uint64(d * (bits - level))
    a = _lower_bound(code, a, b, cell << s)
    return a, _lower_bound(code, a, b, (cell + np.uint64(1)) << s)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _cell_side(ci, level, bits, lo, scale, pmin, pmax, margin):
    """The interval along one axis that holds every point of cell ``ci`` at ``level``."""
    if scale == 0.0:
        return pmin, pmax
    s = bits - level
    a = lo + np.float64(ci << s) / scale - margin
    b = lo + np.float64((ci + 1) << s) / scale + margin
    return max(a, pmin), min(b, pmax)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _axis_cells(xa, reach, lo, scale, pmin, pmax, p, top, s, out):
    """The cells (at level bits - s) along one axis that [xa - reach, xa + reach] meets,
    with its images a period p away (p > 0), in out, increasing: their number, or -1 where
    more than out holds."""
    if scale == 0.0:
        out[0] = 0
        return 1
    m = 0
    last = -1
    for j in range(-1, 2):
        if p > 0.0:
            if reach >= 0.5 * p:
                if j != 0:
                    continue
                u0, u1 = pmin, pmax
            else:
                u0, u1 = xa + j * p - reach, xa + j * p + reach
        else:
            if j != 0:
                continue
            u0, u1 = xa - reach, xa + reach
        u0, u1 = max(u0, pmin), min(u1, pmax)
        if u0 > u1:
            continue
        v0 = min(max((u0 - lo) * scale, -1.0), top + 1.0)
        v1 = min(max((u1 - lo) * scale, -1.0), top + 1.0)
        q0 = min(max(np.int64(math.floor(v0)) - 1, 0), np.int64(top))
        q1 = min(max(np.int64(math.floor(v1)) + 1, 0), np.int64(top))
        for c in range(max(q0 >> s, last + 1), (q1 >> s) + 1):
            if m == out.shape[0]:
                return -1
            out[m] = c
            m += 1
            last = c
    return m


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _cell_code(cx, cy, cz, d):
    """The Morton code of the cell (cx, cy[, cz]) at its level (its bits interleaved as
    the points' codes are)."""
    if d == 2:
        return _spread2(np.uint64(cx)) | (_spread2(np.uint64(cy)) << np.uint64(1))
    return (_spread3(np.uint64(cx)) | (_spread3(np.uint64(cy)) << np.uint64(1))
            | (_spread3(np.uint64(cz)) << np.uint64(2)))  # fmt: skip


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _grid_extent(bits, scale):
    """The grid's largest side (2^bits - 1 code steps along the widest axis)."""
    top = 2.0**bits - 1.0
    ext = 0.0
    for a in range(scale.shape[0]):
        if scale[a] > 0.0:
            ext = max(ext, top / scale[a])
    return ext


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _grid_buffers(bits):
    """A query's work arrays over the grid: each axis's cells, their squared gaps and
    reaches (``_grid_stack``), how many an axis has, and the stack of cells: a row is a
    cell's coordinates, its level and what it is known to be (1 inside the ball, 0 cut by
    its sphere, -1 not yet tested: a child); a descent adds 2^d - 1 cells a level."""
    cells = np.zeros((3, GRID_AXIS), np.int64)
    gap = np.zeros((6, GRID_AXIS))
    far = np.zeros((6, GRID_AXIS))
    na = np.ones(3, np.int64)
    stack = np.empty((GRID_CELLS + 8 * (bits + 2), 5), np.int64)
    return cells, gap, far, na, stack


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _run_weight(count, fix, unit, prefix, i, e):
    """(count, fix) plus the weight of the run [i, e): its length where ``unit``, else the
    difference of its two compensated prefix sums."""
    if unit:
        return count + (e - i), fix
    count, fix = plus_compensated(count, fix, prefix[0, e])
    count, fix = plus_compensated(count, fix, -prefix[0, i])
    return plus_compensated(count, fix, prefix[1, e] - prefix[1, i])


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _grid_stack(table, level0, bits, lo, scale, pmin, pmax, margin, radial, period,
                side, ext, xq, rq2, rin2, cells, gap, far, na, stack):  # fmt: skip
    """The cells about the closed ball (xq, sqrt(rq2)) stacked as ``_grid_read`` takes
    them: the cells the ball's sphere cuts first, those within sqrt(rin2) of xq last (so
    taken first); their number, or -1 where the ball's box of cells is too large even at
    level 0 for ``cells`` (then the tree). The level: cells of side about ``side`` times
    the radius, no finer than the table's. A cell none of whose points' distances from the
    origin could lie in ``radial`` holds none and is not stacked (``gap``, ``far`` (6,
    GRID_AXIS): the squared gaps and farthest reaches along each axis, rows 3 to 5 from
    the origin)."""
    d = xq.shape[0]
    top = 2.0**bits - 1.0
    r = math.sqrt(rq2)
    level = bits
    if r > 0.0 and ext > 0.0:
        t = ext / (side * r)
        if t < 2.0**bits:
            level = max(int(math.floor(math.log2(t))), 0) if t >= 1.0 else 0
    level = min(level, level0)  # no finer than the table's to start: a few points a cell
    total = 1
    while True:  # the finest level whose box of cells is within the stack
        total = 1
        for a in range(d):
            reach = r * (1.0 + 1e-12) + margin[a] + 4e-16 * abs(xq[a])
            na[a] = _axis_cells(xq[a], reach, lo[a], scale[a], pmin[a], pmax[a], period[a],
                                top, bits - level, cells[a])  # fmt: skip
            if na[a] < 0:
                total = -1
                break
            total *= na[a]
        if 0 <= total <= GRID_CELLS or level == 0:
            break
        level -= 1
    if total < 0:
        return -1
    for a in range(3):  # each axis's cells: their squared gaps to xq and to the origin,
        for i in range(na[a] if a < d else 1):  # and their farthest reach (0: no axis)
            if a == d:
                gap[a, i] = far[a, i] = gap[3 + a, i] = far[3 + a, i] = 0.0
                continue
            b0, b1 = _cell_side(cells[a, i], level, bits, lo[a], scale[a], pmin[a], pmax[a],
                                margin[a])  # fmt: skip
            g = _gap(xq[a], b0, b1, period[a])
            gap[a, i] = g * g
            g = _reach(xq[a], b0, b1, period[a])
            far[a, i] = g * g
            g = _gap(0.0, b0, b1, 0.0)
            gap[3 + a, i] = g * g
            g = _reach(0.0, b0, b1, 0.0)
            far[3 + a, i] = g * g
    n2 = na[2] if d == 3 else 1
    reach2 = 0.0
    for i2 in range(n2):
        reach2 = max(reach2, far[5, i2])
    # one pass: the cut cells stacked from the bottom, those inside from row GRID_CELLS
    # down, then moved after them (at most GRID_CELLS cells in all)
    sp = 0
    held = GRID_CELLS
    for i0 in range(na[0]):
        near0 = gap[0, i0]
        if near0 > rq2 or gap[3, i0] > radial[1]:
            continue
        for i1 in range(na[1]):
            near1 = near0 + gap[1, i1]
            low1 = gap[3, i0] + gap[4, i1]
            high1 = far[3, i0] + far[4, i1]
            if near1 > rq2 or low1 > radial[1] or high1 + reach2 < radial[0]:
                continue
            for i2 in range(n2):
                near2 = near1 + gap[2, i2]
                if near2 > rq2 or low1 + gap[5, i2] > radial[1]:
                    continue
                if high1 + far[5, i2] < radial[0]:
                    continue
                inner = far[0, i0] + far[1, i1] + far[2, i2] <= rin2
                if inner:
                    held -= 1
                    row = held
                else:
                    row = sp
                    sp += 1
                stack[row, 0] = cells[0, i0]
                stack[row, 1] = cells[1, i1]
                stack[row, 2] = cells[2, i2] if d == 3 else 0
                stack[row, 3] = level
                stack[row, 4] = 1 if inner else 0
    for j in range(held, GRID_CELLS):
        for c in range(5):
            stack[sp, c] = stack[j, c]
        sp += 1
    return sp


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _grid_read(pts, w, code, table, level0, bits, lo, scale, pmin, pmax, margin, radial,
               unit, prefix, period, xq, rq2, rin2, stop, stack, sp, keep, kw, m):  # fmt: skip
    """The stacked cells (``_grid_stack``) read until what they hold within sqrt(rin2) of
    xq reaches ``stop``: a cell within that adds its run (weighted: the difference of two
    compensated prefix sums), a cell the ball's sphere cuts is read as its 2^d children
    where it holds more than GRID_DESCEND points, point by point otherwise: a point within
    sqrt(rin2) adds its weight, one beyond it but within sqrt(rq2) is kept (its squared
    distance appended to ``keep``, its weight to ``kw``, from row m; with rin2 = rq2, none).
    Returns (the weight within sqrt(rin2), its compensation, the rows kept, whether the
    grid cannot answer: a crowded finest cell the sphere cuts, or ``keep`` full)."""
    d = xq.shape[0]
    count = 0.0
    fix = 0.0  # the compensation of a weighted count
    shell = rin2 < rq2
    while sp > 0 and count + fix < stop:
        sp -= 1
        lv = stack[sp, 3]
        inside = stack[sp, 4] == 1
        if stack[sp, 4] < 0:  # a child: its box tested here
            near2 = 0.0
            far2 = 0.0
            o0 = 0.0
            o1 = 0.0
            for a in range(d):
                b0, b1 = _cell_side(stack[sp, a], lv, bits, lo[a], scale[a], pmin[a], pmax[a],
                                    margin[a])  # fmt: skip
                g = _gap(xq[a], b0, b1, period[a])
                near2 += g * g
                g = _reach(xq[a], b0, b1, period[a])
                far2 += g * g
                g = _gap(0.0, b0, b1, 0.0)
                o0 += g * g
                g = _reach(0.0, b0, b1, 0.0)
                o1 += g * g
            if near2 > rq2 or o0 > radial[1] or o1 < radial[0]:
                continue
            inside = far2 <= rin2
        c = _cell_code(stack[sp, 0], stack[sp, 1], stack[sp, 2], d)
        i, e = _cell_run(code, table, level0, bits, d, c, lv)
        if i == e:
            continue
        if inside:
            count, fix = _run_weight(count, fix, unit, prefix, i, e)
            continue
        if e - i > GRID_DESCEND and lv < bits:
            cx, cy, cz = stack[sp, 0], stack[sp, 1], stack[sp, 2]
            for j in range(1 << d):
                stack[sp, 0] = 2 * cx + (j & 1)
                stack[sp, 1] = 2 * cy + ((j >> 1) & 1)
                stack[sp, 2] = 2 * cz + ((j >> 2) & 1) if d == 3 else 0
                stack[sp, 3] = lv + 1
                stack[sp, 4] = -1
                sp += 1
            continue
        if e - i > GRID_CROWD or (shell and m + (e - i) > keep.shape[0]):
            return count, fix, m, True
        if shell and unit:  # (without branches: each point written, kept where in the shell)
            hits = 0
            for j in range(i, e):
                s = point2(pts, j, xq, period)
                keep[m] = s
                m += (s <= rq2) & (s > rin2)
                hits += s <= rin2
            count += hits
        elif shell:  # (weighted: each point's weight written beside it)
            for j in range(i, e):
                s = point2(pts, j, xq, period)
                inner = s <= rin2
                keep[m] = s
                kw[m] = w[j]
                m += (s <= rq2) & (s > rin2)
                count, fix = plus_compensated(count, fix, w[j] if inner else 0.0)
        elif unit:  # (two loops: the branch out of the one that counts)
            hits = 0
            for j in range(i, e):
                hits += point2(pts, j, xq, period) <= rq2
            count += hits
        else:
            for j in range(i, e):
                if point2(pts, j, xq, period) <= rq2:
                    count, fix = plus_compensated(count, fix, _weight(w, j))
    return count, fix, m, False


@kernel(entry=True, lazy=True, nogil=True)
def _grid_held(pts, w, code, table, level0, bits, lo, scale, pmin, pmax, margin, radial,
               unit, prefix, period, side, x, r2, stop, loose, out, start, end):  # fmt: skip
    """out[q] for q in [start, end): the weight in the closed ball (x[q], sqrt(r2[q])) (its
    number of points where ``unit``; compensated otherwise, a run inside from ``prefix``),
    exact below stop[q], at least stop[q] otherwise; -1 where the grid leaves it to the
    tree (a radius not finite, a crowded finest cell the sphere cuts). ``loose``: below
    stop[q], an upper bound only: where the runs of all the cells the ball meets weigh
    less than stop[q], their weight, no point read (a ball far below stop is settled by
    its cells)."""
    d = pts.shape[1]
    ext = _grid_extent(bits, scale)
    cells, gap, far, na, stack = _grid_buffers(bits)
    none = np.empty(0)
    for q in range(start, end):
        rq2 = r2[q]
        if not (rq2 >= 0.0 and rq2 < np.inf):
            out[q] = -1.0
            continue
        xq = x[q]
        sp = _grid_stack(table, level0, bits, lo, scale, pmin, pmax, margin, radial,
                         period, side, ext, xq, rq2, rq2, cells, gap, far, na, stack)  # fmt: skip
        if sp < 0:
            out[q] = -1.0
            continue
        if loose:
            bound = 0.0
            fix = 0.0
            for s in range(sp):
                c = _cell_code(stack[s, 0], stack[s, 1], stack[s, 2], d)
                i, e = _cell_run(code, table, level0, bits, d, c, stack[s, 3])
                bound, fix = _run_weight(bound, fix, unit, prefix, i, e)
            if bound + fix < stop[q]:
                out[q] = bound + fix
                continue
        count, fix, _, lost = _grid_read(pts, w, code, table, level0, bits, lo, scale, pmin,
                                         pmax, margin, radial, unit, prefix, period, xq, rq2,
                                         rq2, stop[q], stack, sp, none, none, 0)  # fmt: skip
        out[q] = -1.0 if lost else count + fix


@kernel(entry=True, lazy=True, nogil=True)
def _grid_kth(pts, w, code, table, level0, bits, lo, scale, pmin, pmax, margin, radial, unit,
              prefix, period, side, x, k, out, start, end):  # fmt: skip
    """out[q] for q in [start, end): the least radius whose closed ball about x[q] holds
    weight k (inf where the points hold less), or -1 where the grid leaves it to the tree.
    Each query reads a shell about it (``_grid_read``): the cells within its inner radius
    add their runs, the points between its radii are kept, and the answer is found among
    them (``_kth_of``). The shell: between 1 - g and 1 + g times the answer before it (g =
    GRID_GUESS / sqrt(k), at most 1/2: d_{P,k}'s spread between neighbours shrinks as k
    grows), narrowed to that answer plus or minus their distance (d_{P,k} is
    1-Lipschitz, and queries come along a Morton curve); where the inner ball holds k, the
    shell moves in (its outer radius the inner one, its inner halved), where the outer
    holds less, out (doubled, but not past the Lipschitz bound). A chunk's first query
    starts from the ball that holds k on average."""
    d = pts.shape[1]
    n = pts.shape[0]
    ext = _grid_extent(bits, scale)
    cells, gap, far, na, stack = _grid_buffers(bits)
    size = min(max(64 * int(math.ceil(min(k, n))), 8192), n + 1)  # the shell's points
    keep = np.empty(size)
    kw = np.empty(size)
    hist = np.empty(HISTOGRAM, np.int64)
    typical = ext * (min(k, n) / n) ** (1.0 / d) if n > 0 else 0.0
    guess = min(GRID_GUESS / math.sqrt(max(k, 1.0)), 0.5)
    before = -1.0
    for q in range(start, end):
        xq = x[q]
        all2 = 0.0  # every point lies within sqrt(all2)
        for a in range(d):
            g = _reach(xq[a], pmin[a], pmax[a], period[a])
            all2 += g * g
        bound = np.inf  # the Lipschitz bound: the answer lies within it
        r_lo, r_hi = 0.0, typical
        if 0.0 <= before < np.inf and q > start:
            delta = math.sqrt(point2(x, q - 1, xq, period))
            if delta == 0.0:  # the same position: the same answer
                out[q] = before
                continue
            bound = (before + delta) * (1.0 + 1e-12)
            r_lo = max(before * (1.0 - guess), before - delta)
            r_hi = min(before * (1.0 + guess), bound)
        if not r_hi > 0.0:
            r_hi = min(max(typical, 1e-300), bound)
        answer = -1.0
        for _ in range(GRID_TRIES):
            rq2 = r_hi * r_hi
            rin2 = r_lo * r_lo
            sp = _grid_stack(table, level0, bits, lo, scale, pmin, pmax, margin, radial,
                             period, side, ext, xq, rq2, rin2, cells, gap, far, na,
                             stack)  # fmt: skip
            if sp < 0:
                break
            count, fix, m, lost = _grid_read(pts, w, code, table, level0, bits, lo, scale,
                                             pmin, pmax, margin, radial, unit, prefix, period,
                                             xq, rq2, rin2, k, stack, sp, keep, kw, 0)  # fmt: skip
            if lost:
                break
            if count + fix >= k:  # the inner ball holds k: the shell moves in
                if rin2 <= 0.0:
                    answer = 0.0
                    break
                r_hi = r_lo
                r_lo = 0.5 * r_lo if r_lo > 1e-300 else 0.0
                continue
            s = _kth_of(keep, kw, m, k, unit, rin2, rq2, hist, count, fix)
            if s >= 0.0:
                answer = math.sqrt(s)
                break
            if rq2 >= all2:  # every point read: they hold less than k
                answer = np.inf
                break
            r_lo = r_hi  # the outer ball holds less than k: the shell moves out
            r_hi = min(2.0 * r_hi, bound) if bound > r_hi else 2.0 * r_hi
            if r_hi * r_hi >= all2:
                r_hi = math.sqrt(all2) * (1.0 + 1e-12) + 1e-300
        out[q] = answer
        before = answer if answer >= 0.0 else -1.0


def _built_in_thread(pts, w, unit, scratch):
    """(a thread building the tree of pts, w; its result, {"tree": ...} or {"error": ...},
    once joined). A thread of its own that ends with the build: none is left waiting."""
    out = {}

    def build():
        try:
            out["tree"] = _build(pts, w, LEAF, unit, scratch)
        except BaseException as e:  # handed to the caller, who asks for the tree
            out["error"] = e

    thread = threading.Thread(target=build, name="knnrefine-certify-tree", daemon=True)
    thread.start()
    return thread, out


class Tree:
    """certify's kd-tree over ``points`` (n, d), with ``weights`` (n,) or None (every point
    weighs 1), on the torus of ``period`` (per axis; 0 or None: that axis does not wrap;
    coordinates along wrapping axes in [0, period)). ``background``: built in a thread of
    its own (the build holds no lock), so that the caller's work on the mesh goes on
    beside it; the first question waits for it. ``scratch``: ``points`` is the caller's
    to give away (a copy of its own, not read again): the tree sorts it in place (as it
    does any copy ``points`` needs to be float64 and contiguous) rather than copy it."""

    def __init__(self, points, weights=None, period=None, threads=None, background=False,
                 scratch=False):  # fmt: skip
        pts = np.ascontiguousarray(points, dtype=np.float64)
        scratch = scratch or pts is not points  # (a copy made here is the tree's own)
        self.n, self.dim = pts.shape
        self.period = (np.zeros(self.dim) if period is None
                       else np.ascontiguousarray(period, dtype=np.float64))  # fmt: skip
        self.threads = threads
        # unweighted: every point weighs 1, and the build writes the ones (w a placeholder)
        w = np.ones(1) if weights is None else np.ascontiguousarray(weights, np.float64)
        if self.n == 0:  # a node must exist: one far away holding nothing
            pts, w = np.full((1, self.dim), np.inf), np.zeros(1)
        self.unit = bool((w == 1.0).all())  # every point weighs 1: counts are integers
        if self.unit:
            w = np.ones(1)
        if background:
            self._job = _built_in_thread(pts, w, self.unit, scratch)
        else:
            self._built = _build(pts, w, LEAF, self.unit, scratch)

    def _parts(self):
        built = self.__dict__.get("_built")
        if built is None:  # (threads may ask at once: each joins, each sets the same)
            thread, out = self._job
            thread.join()
            if "error" in out:
                raise out["error"]
            built = self._built = out["tree"]
        return built

    pts = property(lambda self: self._parts()[0], doc="the points, in the tree's order")
    w = property(
        lambda self: self._parts()[1],
        doc="their weights, in the tree's order (unweighted: one placeholder 1)",
    )
    T = property(lambda self: self._parts()[2], doc="the nodes")
    depth = property(lambda self: self._parts()[3], doc="the tree's depth")
    grid = property(lambda self: self._parts()[4], doc="the grid of its Morton runs")

    def weights_of(self, rows):
        """The weights of the tree's points ``rows`` (an index array, the tree's order)."""
        w = self.w
        return np.ones(len(rows)) if self.unit else w[rows]

    def _queries(self, x):
        return np.ascontiguousarray(np.reshape(x, (-1, self.dim)), dtype=np.float64)

    def _period(self, period):
        return self.period if period is None else np.ascontiguousarray(period, np.float64)

    def _run(self, call, m):
        in_chunks(call, m, threads=self.threads, least=512)

    def held(self, centres, radii, stop=np.inf, period=None, loose=False):
        """What each closed ball (centre, radius) holds: its points' weight (their number
        unweighted), exact where below ``stop`` (a number or one per ball), at least
        ``stop`` otherwise (``loose``: below ``stop``, at least what it holds, perhaps
        more: ``fewer``). Asked along a Morton curve (``spatial_order``): neighbouring
        balls read the same nodes, from the cache."""
        x = self._queries(centres)
        r = np.broadcast_to(np.asarray(radii, np.float64), len(x))
        order = spatial_order(x)
        xs = np.ascontiguousarray(x[order])
        r2 = np.ascontiguousarray(np.square(r[order]))
        st = np.ascontiguousarray(np.broadcast_to(np.asarray(stop, np.float64), len(x))[order])
        res = np.full(len(x), -1.0)  # -1: left to the tree
        p = self._period(period)
        g = self.grid
        if g is not None:  # the grid first, the tree where it leaves a ball
            side = GRID_SIDE if self.dim == 2 else GRID_SIDE3

            def call(a, b):
                _grid_held(self.pts, self.w, g.code, g.table, g.level0, g.bits, g.lo,
                           g.scale, g.pmin, g.pmax, g.margin, g.radial, self.unit, g.prefix, p,
                           side, xs, r2, st, bool(loose), res, a, b)  # fmt: skip

            self._run(call, len(x))
        left = np.flatnonzero(res < 0)
        if len(left):
            xl, r2l, stl = (np.ascontiguousarray(v[left]) for v in (xs, r2, st))
            resl = np.empty(len(left))

            def call(a, b):
                _held(self.pts, self.w, self.T, self.depth, p, xl, r2l, stl, resl, a, b)

            self._run(call, len(left))
            res[left] = resl
        out = np.empty(len(x))
        out[order] = res
        return out

    def fewer(self, centres, radii, k, period=None, mostly=True):
        """Whether each closed ball (centre, radius) holds less than weight k. ``mostly``
        (most are expected to): each settled by the runs of the grid's cells it meets
        where they weigh less in all, read point by point otherwise (``held``'s
        ``loose``); else counted until it reaches k, the cells inside it first."""
        return self.held(centres, radii, k, period, loose=mostly) < k

    def kth(self, x, k, period=None, sort=True):
        """The least radius whose closed ball about each x holds weight k (the k-th
        nearest distance, unweighted; inf where the points hold less). The queries are
        taken in ``spatial_order`` (``sort=False``: in the order given, one where
        neighbours are near), so that each brackets the next. Read from the grid's shells
        (``_grid_kth``) in the plane, and in space from k = GRID_KTH3 on; from the tree's
        blocks (``_kth``) otherwise and where the grid leaves a query. (Single thread, per
        query: k = 100 on the sphere 3.2 against 5.8 us, k = 10 in the plane 0.96 against
        1.21; but k = 10 on the sphere 2.1 against 1.7, k = 2 in space 1.6 against 1.1: a
        small ball in space meets dozens of cells for a few points.)"""
        x = self._queries(x)
        order = spatial_order(x) if sort else np.arange(len(x))
        xs = np.ascontiguousarray(x[order])
        res = np.full(len(x), -1.0)  # -1: left to the tree
        p = self._period(period)
        unit = self.unit
        g = self.grid
        if g is not None and (self.dim == 2 or k >= GRID_KTH3):
            side = GRID_SIDE if self.dim == 2 else GRID_SIDE3

            def call(a, b):
                _grid_kth(self.pts, self.w, g.code, g.table, g.level0, g.bits, g.lo, g.scale,
                          g.pmin, g.pmax, g.margin, g.radial, unit, g.prefix, p, side, xs,
                          float(k),
                          res, a, b)  # fmt: skip

            self._run(call, len(x))
        left = np.flatnonzero(res < 0)
        if len(left):
            xl = np.ascontiguousarray(xs[left])
            resl = np.empty(len(left))

            def call(a, b):
                _kth(self.pts, self.w, self.T, self.depth, p, xl, float(k), unit, resl, a, b)

            self._run(call, len(left))
            res[left] = resl
        out = np.empty(len(x))
        out[order] = res
        return out

    def held_caps(self, centres, outer, corners, stop=np.inf):
        """(what each closed cap holds: the points on or above the plane through its three
        ``corners`` (t, 3, 3), among those within ``outer`` of ``centres``, exact below
        ``stop``; the (cap, point) pairs the float filter left undecided, for caps still
        below ``stop``, points as the tree holds them: ``pts[j]`` weighing ``w[j]``)."""
        x = self._queries(centres)
        outer2 = np.ascontiguousarray(np.broadcast_to(np.square(outer, dtype=float), len(x)))
        st = np.ascontiguousarray(np.broadcast_to(np.asarray(stop, np.float64), len(x)))
        c = np.ascontiguousarray(corners, np.float64)
        out = np.empty(len(x))

        def call(a, b):
            return _held_caps(self.pts, self.w, self.T, self.depth,
                              x, outer2, c, st, out, a, b)  # fmt: skip

        parts = in_chunks(call, len(x), threads=self.threads, least=512)
        caps = np.concatenate([q for q, _ in parts]) if parts else np.zeros(0, np.int64)
        members = np.concatenate([j for _, j in parts]) if parts else np.zeros(0, np.int64)
        return out, caps, members

    def nearest_counts(self, sites, first, neighbours, period, relative=2e-12, slack2=0.0):
        """What each site's closed Voronoi cell holds, from a verified Delaunay
        triangulation's neighbour lists (``cells_held``'s arguments but the shifts: a
        walk measures each site's nearest copy): every point's nearest site walked
        (``walk_nearest``), the point counting for it and every site as near up to the tie
        tolerance. Exact in full; None where a walk did not settle (then ask
        ``cells_held``)."""
        m = len(first) - 1
        if self.n == 0:
            return np.zeros(m)
        pts = self.pts
        owner = np.empty(len(pts), np.int32 if m < 2**31 else np.int64)
        args = (
            pts,
            np.ascontiguousarray(sites, np.float64),
            np.ascontiguousarray(first, np.int64),
            as_index(neighbours),
            np.ascontiguousarray(period, np.float64),
            float(relative),
            float(slack2),
        )

        def call(a, b):
            return _nearest_sites(*args, owner, a, b)

        parts = in_chunks(call, len(pts), threads=self.threads, least=4096)
        if any(found < 0 for found, _, _ in parts):
            return None
        if self.unit:  # counts: integers, exact
            out = np.bincount(owner, minlength=m).astype(np.float64)
            for _, _, u in parts:
                out += np.bincount(u, minlength=m)
            return out
        s, c = np.zeros(m), np.zeros(m)  # each point's weight, then each tie's, compensated
        _add_weights(np.arange(0), owner, self.w, s, c)
        for _, q, u in parts:
            _add_weights(q, u, self.w, s, c)
        return s + c

    def cells_held(self, sites, first, neighbours, shift, period, outradii, stop=np.inf,
                   relative=2e-12, slack2=0.0):  # fmt: skip
        """What the closed Voronoi cell of each site holds: the points p within its
        outradius with |p - v|^2 <= |p - u|^2 (1 + relative) + slack2 for each neighbour u of
        v (rows first[v]:first[v + 1] of ``neighbours``, each ``shift`` whole ``period``s
        away, (e, 0) where the sites do not wrap: ``edge_at``; a point as near as its
        nearest counts for each), exact below ``stop``. Whole nodes inside every bisector
        are added without their points."""
        v = self._queries(sites)
        nb, sh = as_index(neighbours), edge_shifts(shift, len(neighbours))
        cell_period = np.ascontiguousarray(period, np.float64)
        r = np.ascontiguousarray(outradii, np.float64)
        st = np.ascontiguousarray(np.broadcast_to(np.asarray(stop, np.float64), len(v)))
        first = np.ascontiguousarray(first, np.int64)
        out = np.empty(len(v))

        def call(a, b):
            _cells_held(self.pts, self.w, self.T, self.depth, self.period, v, first, nb, sh,
                        cell_period, r, float(relative), float(slack2), st, out, a,
                        b)  # fmt: skip

        self._run(call, len(v))
        return out


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _spread2(v):
    """The low 32 bits of v with a zero between each (bit i to bit 2 i)."""
    v &= np.uint64(0xFFFFFFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x0000FFFF0000FFFF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x00FF00FF00FF00FF)
    v = (v | (v << np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    v = (v | (v << np.uint64(2))) & np.uint64(0x3333333333333333)
    v = (v | (v << np.uint64(1))) & np.uint64(0x5555555555555555)
    return v


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _spread3(v):
    """The low 21 bits of v with two zeros between each (bit i to bit 3 i)."""
    v &= np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _code_of(x, i, lo, scale, top):
    """The Morton code of row i of x in the frame (lo, scale): each coordinate less lo,
    scaled and clamped to [0, top] (0 where not a number), its bits interleaved."""
    d = x.shape[1]
    c = np.uint64(0)
    for a in range(d):
        v = (x[i, a] - lo[a]) * scale[a]
        v = min(max(v, 0.0), top) if v == v else 0.0
        q = np.uint64(v)
        c |= (_spread2(q) if d == 2 else _spread3(q)) << np.uint64(a)
    return c


def morton_sorted(x, bits):
    """``_morton_sorted``: the order int32 where it can be (n < 2^31), half the memory."""
    n = len(x)
    order = np.arange(n, dtype=np.int32 if n < 2**31 else np.int64)
    return _morton_sorted(x, bits, order, np.empty_like(order))


@kernel(entry=True, lazy=True, nogil=True)
def _morton_sorted(x, bits, order, order2):
    """(the Morton codes of the rows of x (n, 2 or 3) over their finite bounding box,
    sorted; the order that sorts them (``order``, 0 to n - 1 on entry, or its buffer
    ``order2``); the frame: each axis's origin and scale): each
    coordinate less the box's least, scaled to an integer of ``bits`` bits (a coordinate
    not finite as the least), interleaved, and the codes sorted by a radix sort of 8-bit
    digits (their counts all taken in one pass; a digit the same in every code skipped)."""
    n, d = x.shape
    top = 2.0**bits - 1.0
    lo = np.full(d, np.inf)
    hi = np.full(d, -np.inf)
    for i in range(n):
        for a in range(d):
            v = x[i, a]
            if np.isfinite(v):
                lo[a] = min(lo[a], v)
                hi[a] = max(hi[a], v)
    scale = np.zeros(d)
    for a in range(d):
        if hi[a] > lo[a]:
            scale[a] = top / (hi[a] - lo[a])
        else:
            lo[a] = 0.0
    digits = (bits * d + 7) // 8
    count = np.zeros((digits, 257), np.int64)
    code = np.empty(n, np.uint64)
    for i in range(n):
        c = _code_of(x, i, lo, scale, top)
        code[i] = c
        for g in range(digits):
            count[g, ((c >> np.uint64(8 * g)) & np.uint64(0xFF)) + 1] += 1
    keys2 = np.empty(n, np.uint64)
    for g in range(digits):
        if count[g].max() == n:  # one digit for every code: nothing moves
            continue
        shift = np.uint64(8 * g)
        at = count[g]
        for b in range(256):
            at[b + 1] += at[b]
        for i in range(n):
            digit = (code[i] >> shift) & np.uint64(0xFF)
            keys2[at[digit]] = code[i]
            order2[at[digit]] = order[i]
            at[digit] += 1
        code, keys2 = keys2, code
        order, order2 = order2, order
    return code, order, lo, scale


def spatial_order(x):
    """An order of the rows of ``x`` (n, d) along a Morton curve over their bounding box
    (31 bits a coordinate in the plane, 21 in space): neighbours in it are near each
    other, as groups of queries need."""
    x = np.ascontiguousarray(x, np.float64)
    if len(x) < 2:
        return np.arange(len(x))
    if x.shape[1] not in (2, 3):
        return np.arange(len(x))
    return morton_sorted(x, 31 if x.shape[1] == 2 else 21)[1]


def edge_shifts(shift, e):
    """The cells' edge shifts (e, d) as the kernels read them: int16 as they come from
    ``neighbour_lists``, else int64; (e, 0) where none."""
    shift = np.asarray(shift)
    shift = shift if shift.dtype == np.int16 else shift.astype(np.int64)
    return np.ascontiguousarray(shift.reshape(e, -1))


SITE_BLOCKS = 8  # ranges of sites ``neighbour_lists`` gathers, a thread each in turn, at most


def neighbour_lists(cells, off, m, threads=None):
    """Each site's neighbours, once each, from the cells (t, c) of a triangulation and
    their corners' offsets (t, c, d) in whole periods (d = 0: none): (first (m + 1,):
    site v's are rows first[v]:first[v + 1] of the next two, their indices, their shifts
    (the neighbour's offset less the site's), sorted by index then shift). Every corner of
    a cell is a neighbour of every other. The sites are taken in SITE_BLOCKS ranges (a
    thread each, ``_block_rows``): the cells are read in order and the rows of the
    range's sites placed (a counting sort), deduplicated by stamps and sorted; the ranges'
    rows are joined. What is held at once: a range's c - 1 rows a corner, not every
    site's."""
    cells, off = as_index(cells), as_offsets(off)
    c, d = cells.shape[1], off.shape[2]
    index = np.int32 if m < 2**31 else np.int64
    shifts = np.int16 if off.dtype == np.int8 else np.int64  # (a difference of two offsets)
    counts = np.zeros(m + 1, np.int64)
    if len(cells):
        counts[:m] = (c - 1) * np.bincount(cells.ravel(), minlength=m)
    # ranges of about equal rows
    bounds = np.searchsorted(np.cumsum(counts), np.linspace(0, counts.sum(), SITE_BLOCKS + 1))
    bounds[0], bounds[-1] = 0, m
    bounds = np.unique(bounds)
    got = [None] * (len(bounds) - 1)
    like = np.empty(0, index), np.empty((0, d), shifts)

    def blocks(a, b):
        for j in range(a, b):
            got[j] = _block_rows(cells, off, counts, bounds[j], bounds[j + 1], *like)

    in_chunks(blocks, len(got), threads=threads, least=1, per_thread=SITE_BLOCKS)
    first = np.zeros(m + 1, np.int64)
    for j, (kept, _, _) in enumerate(got):
        first[bounds[j] + 1 : bounds[j + 1] + 1] = kept
    np.cumsum(first, out=first)
    nb = np.concatenate([g[1] for g in got]) if got else np.zeros(0, index)
    sh = np.concatenate([g[2] for g in got]) if got else np.zeros((0, d), shifts)
    return first, nb, sh.reshape(len(nb), d)


@kernel(entry=True, lazy=True, nogil=True)
def _block_rows(cells, off, counts, start, end, index, shifts):
    """(each site's rows kept, their neighbours, their shifts) for the sites [start, end):
    the cells read in order, each corner at such a site placed its cell's other corners
    (index, offset less the site's) at the site's place (``counts``: its rows); a site's
    rows kept once each (a repeat found among the rows kept since its index was first
    seen, stamped) and sorted by (index, shift) (insertion), then gathered; in the types
    of ``index`` and ``shifts``."""
    c = cells.shape[1]
    d = off.shape[2]
    n = end - start
    place = np.zeros(n + 1, np.int64)
    for v in range(n):
        place[v + 1] = place[v] + counts[start + v]
    first = place[:-1].copy()
    rows = place[n]
    nb = np.empty(rows, index.dtype)
    sh = np.empty((rows, d), shifts.dtype)
    for i in range(cells.shape[0]):
        for x in range(c):
            v = cells[i, x] - start
            if v < 0 or v >= n:
                continue
            for y in range(c):
                if y == x:
                    continue
                p = place[v]
                place[v] += 1
                nb[p] = cells[i, y]
                for a in range(d):
                    sh[p, a] = off[i, y, a] - off[i, x, a]
    m = counts.shape[0] - 1
    stamp = np.full(m, -1, np.int64)  # the site whose rows last saw this index
    seen_at = np.zeros(m, np.int64)  # where that site's rows first kept it
    row = np.empty(d, shifts.dtype)
    kept = np.zeros(n, np.int64)
    for v in range(n):
        begin = first[v]
        used = begin
        for j in range(first[v], place[v]):  # kept rows [begin, used): used <= j
            key = nb[j]
            repeat = False
            if stamp[key] == v:
                for i in range(seen_at[key], used):
                    if nb[i] == key:
                        same = True
                        for a in range(d):
                            if sh[i, a] != sh[j, a]:
                                same = False
                                break
                        if same:
                            repeat = True
                            break
            else:
                stamp[key] = v
                seen_at[key] = used
            if not repeat:
                nb[used] = key
                for a in range(d):
                    sh[used, a] = sh[j, a]
                used += 1
        for j in range(begin + 1, used):  # insertion sort of the kept rows by (b, shift)
            key = nb[j]
            for a in range(d):
                row[a] = sh[j, a]
            i = j - 1
            while i >= begin:
                less = nb[i] > key
                if nb[i] == key:
                    for a in range(d):
                        if sh[i, a] != row[a]:
                            less = sh[i, a] > row[a]
                            break
                if not less:
                    break
                nb[i + 1] = nb[i]
                for a in range(d):
                    sh[i + 1, a] = sh[i, a]
                i -= 1
            nb[i + 1] = key
            for a in range(d):
                sh[i + 1, a] = row[a]
        kept[v] = used - begin
    total = 0
    for v in range(n):
        total += kept[v]
    out_nb = np.empty(total, index.dtype)
    out_sh = np.empty((total, d), shifts.dtype)
    o = 0
    for v in range(n):
        for j in range(kept[v]):
            out_nb[o] = nb[first[v] + j]
            for a in range(d):
                out_sh[o, a] = sh[first[v] + j, a]
            o += 1
    return kept, out_nb, out_sh


def incidence(cells, m):
    """(first (m + 1,), incident): the corners of the cells (t, c) at site v are
    incident[first[v]:first[v + 1]], each as cell times c plus corner, in the cells'
    order (a cell with v twice: two in a row); a counting sort (``_incidence``)."""
    cells = as_index(cells)
    t, c = cells.shape
    first = np.zeros(m + 1, np.int64)
    if t:
        np.cumsum(np.bincount(cells.ravel(), minlength=m), out=first[1:])
    incident = np.empty(c * t, np.int32 if c * t < 2**31 else np.int64)
    _incidence(cells, first, incident)
    return first, incident


@kernel(entry=True, lazy=True, nogil=True)
def _incidence(cells, first, incident):
    """incident[first[v]:first[v + 1]]: the corners of the cells at site v, each as
    cell c + corner (cell times c plus corner), in order."""
    c = cells.shape[1]
    place = first[:-1].copy()
    for i in range(cells.shape[0]):
        for x in range(c):
            v = cells[i, x]
            incident[place[v]] = i * c + x
            place[v] += 1
