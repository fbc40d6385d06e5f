"""A kd-tree over weighted points that knows each node's weight: what a closed ball holds
(``ball_weights``) and the least radius whose closed ball holds weight k (``kth_radius``),
in work that does not grow with the points that weigh nothing or little.

scipy's cKDTree answers both only point by point: a ball's weight from the list of its
points, and the k-th weighted distance from nearest neighbours fetched until their weights
add up to k. Where most of the weight sits on few points, that is every point of the set for
every query (the hostile round: one point of weight n and n - 1 of weight 0 made certify
quadratic, 39 s at n = 8,000). Here a node inside the ball adds its total at once, points of
weight 0 are left out of the tree, and the k-th radius is bracketed by ball queries, halving
the bracket until few points lie between its ends, which are then sorted.

Distances are Euclidean, with periodic axes (``boxsize`` > 0, points in [0, boxsize)) at
their minimum image, as cKDTree's ``boxsize`` has them. Sums are compensated
(``geometry.plus_compensated``). Used by ``metric`` (certify and the applications), never
by the refinement; it lives here, with the engine's other indexes, so that its kernels are
cached as theirs are (also on read-only installs).
"""

from collections import namedtuple

import numpy as np

from .geometry import plus_compensated
from .jit import kernel
from .threads import in_chunks, kth_range

LEAF = 16  # points per leaf at most
SHELL = 64  # points between the bracket's ends below which they are sorted

WeightTree = namedtuple(
    "WeightTree",
    ["points", "weights", "boxsize", "start", "stop", "left", "lo", "hi", "total",
     "source_weights"],
)  # fmt: skip


def build(points, weights, boxsize=None):
    """The tree over ``points`` (n, d) with ``weights`` (n,) >= 0; ``boxsize`` (d,) the
    periods (0: not periodic) or None. Points of weight 0 are left out; ``source_weights``
    keeps the weights as given."""
    points = np.asarray(points, float)
    weights = np.asarray(weights, float)
    keep = weights > 0
    pts = np.ascontiguousarray(points[keep])
    w = np.ascontiguousarray(weights[keep])
    d = points.shape[1]
    box = np.zeros(d) if boxsize is None else np.asarray(boxsize, float).reshape(d).copy()
    nodes = max(1, 4 * (len(pts) // LEAF + 1))
    start = np.zeros(nodes, np.int64)
    stop = np.zeros(nodes, np.int64)
    left = np.full(nodes, -1, np.int64)
    lo = np.zeros((nodes, d))
    hi = np.zeros((nodes, d))
    total = np.zeros(nodes)
    order = np.arange(len(pts), dtype=np.int64)
    used = _build(pts, w, order, start, stop, left, lo, hi, total, LEAF)
    return WeightTree(
        points=np.ascontiguousarray(pts[order]),
        weights=np.ascontiguousarray(w[order]),
        boxsize=box,
        start=start[:used],
        stop=stop[:used],
        left=left[:used],
        lo=lo[:used],
        hi=hi[:used],
        total=total[:used],
        source_weights=weights,
    )


@kernel(entry=True, lazy=True)
def _build(pts, w, order, start, stop, left, lo, hi, total, leaf):
    """Split ``order`` (the points' permutation) at medians along each node's widest side;
    node i covers order[start[i]:stop[i]], its children are left[i] and left[i] + 1 (-1 for
    a leaf), with its bounding box and compensated total weight. Returns the node count."""
    d = pts.shape[1]
    n = pts.shape[0]
    stack = np.empty(128, np.int64)
    top = 0
    used = 1
    start[0] = 0
    stop[0] = n
    stack[top] = 0
    top += 1
    while top > 0:
        top -= 1
        node = stack[top]
        s, e = start[node], stop[node]
        for a in range(d):
            lo[node, a] = np.inf
            hi[node, a] = -np.inf
        acc = 0.0
        c = 0.0
        for i in range(s, e):
            p = order[i]
            acc, c = plus_compensated(acc, c, w[p])
            for a in range(d):
                lo[node, a] = min(lo[node, a], pts[p, a])
                hi[node, a] = max(hi[node, a], pts[p, a])
        total[node] = acc + c
        if e - s <= leaf:
            continue
        axis = 0
        for a in range(1, d):
            if hi[node, a] - lo[node, a] > hi[node, axis] - lo[node, axis]:
                axis = a
        if hi[node, axis] <= lo[node, axis]:  # all points alike: one leaf
            continue
        m = (s + e) // 2
        _select(order, pts, axis, s, e, m)
        left[node] = used
        start[used], stop[used] = s, m
        start[used + 1], stop[used + 1] = m, e
        stack[top] = used
        stack[top + 1] = used + 1
        top += 2
        used += 2
    return used


@kernel()
def _select(order, pts, axis, s, e, m):
    """Reorder order[s:e] so that order[m] is the point whose coordinate ``axis`` is m-th
    there, smaller ones before it, larger ones after (Hoare's selection)."""
    lo, hi = s, e - 1
    while lo < hi:
        pivot = pts[order[(lo + hi) >> 1], axis]
        i, j = lo, hi
        while i <= j:
            while pts[order[i], axis] < pivot:
                i += 1
            while pts[order[j], axis] > pivot:
                j -= 1
            if i <= j:
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if m <= j:
            hi = j
        elif m >= i:
            lo = i
        else:
            return


@kernel(inline="always")
def _gap(x, lo, hi, period):
    """(least, greatest) distance from x to the interval [lo, hi] along one axis, at the
    minimum image when ``period`` > 0."""
    if period <= 0.0:
        if x < lo:
            return lo - x, hi - x
        if x > hi:
            return x - hi, x - lo
        return 0.0, max(x - lo, hi - x)
    # on a circle: the nearest image of each end; the far end reaches half a period when
    # the point opposite x lies in the interval
    a = _wrapped(lo - x, period)
    b = _wrapped(hi - x, period)
    if lo <= x <= hi:
        near = 0.0
    else:
        near = min(abs(a), abs(b))
    opposite = x + 0.5 * period
    if opposite >= period:
        opposite -= period
    if lo <= opposite <= hi:
        far = 0.5 * period
    else:
        far = max(abs(a), abs(b))
    return near, far


@kernel(inline="always")
def _wrapped(dx, period):
    """dx moved by whole periods into [-period / 2, period / 2]."""
    if period > 0.0:
        if dx > 0.5 * period:
            dx -= period
        elif dx < -0.5 * period:
            dx += period
    return dx


@kernel(inline="always")
def _dist2(pts, i, x, boxsize):
    s = 0.0
    for a in range(x.shape[0]):
        dx = _wrapped(pts[i, a] - x[a], boxsize[a])
        s += dx * dx
    return s


@kernel()
def _held(tree, x, r2, stack):
    """(weight, points) in the closed ball of squared radius r2 about x."""
    acc = 0.0
    c = 0.0
    count = 0
    top = 0
    stack[top] = 0
    top += 1
    d = x.shape[0]
    while top > 0:
        top -= 1
        node = stack[top]
        near2 = 0.0
        far2 = 0.0
        for a in range(d):
            near, far = _gap(x[a], tree.lo[node, a], tree.hi[node, a], tree.boxsize[a])
            near2 += near * near
            far2 += far * far
        if near2 > r2:
            continue
        if far2 <= r2:
            acc, c = plus_compensated(acc, c, tree.total[node])
            count += tree.stop[node] - tree.start[node]
            continue
        child = tree.left[node]
        if child < 0:
            for i in range(tree.start[node], tree.stop[node]):
                if _dist2(tree.points, i, x, tree.boxsize) <= r2:
                    acc, c = plus_compensated(acc, c, tree.weights[i])
                    count += 1
            continue
        stack[top] = child
        stack[top + 1] = child + 1
        top += 2
    return acc + c, count


@kernel(entry=True, lazy=True, nogil=True)
def _ball_weights(tree, x, r2, out, a, b):
    stack = np.empty(256, np.int64)
    for q in range(a, b):
        out[q] = _held(tree, x[q], r2[q], stack)[0]


def ball_weights(tree, centres, radii, threads=-1):
    """What each closed ball (centre, radius) holds: the weight of its points."""
    x = np.ascontiguousarray(centres, float).reshape(-1, tree.points.shape[1])
    r2 = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, float) ** 2, len(x)))
    out = np.zeros(len(x))
    if len(tree.start) and len(tree.points):
        in_chunks(lambda a, b: _ball_weights(tree, x, r2, out, a, b), len(x), _threads(threads))
    return out


@kernel()
def _kth_one(tree, x, k, low2, high2, stack):
    """The least r whose closed ball about x holds weight >= k (the tree's total must reach
    k), given a squared radius ``low2`` whose ball holds less (-1: none known) and one,
    ``high2``, whose ball holds k (-1: none known)."""
    d = x.shape[0]
    w_lo, c_lo = (0.0, 0) if low2 < 0.0 else _held(tree, x, low2, stack)
    # an upper end: squared radii quadrupled until the ball holds k, or the whole tree
    reach2 = 0.0
    for a in range(d):
        near, far = _gap(x[a], tree.lo[0, a], tree.hi[0, a], tree.boxsize[a])
        reach2 += far * far
    hi2 = high2 if high2 > low2 else max(4.0 * low2, reach2 * 1e-6, 1e-300)
    while True:
        if hi2 >= reach2:
            hi2 = reach2
            w_hi, c_hi = tree.total[0], tree.stop[0]
            break
        w_hi, c_hi = _held(tree, x, hi2, stack)
        if w_hi >= k:
            break
        low2, w_lo, c_lo = hi2, w_hi, c_hi
        hi2 *= 4.0
    # halve the bracket (low2, hi2] until few points lie in it
    while c_hi - c_lo > SHELL:
        if low2 <= 0.0:
            mid2 = 0.25 * hi2
        elif hi2 > 4.0 * low2:  # far apart: halve the ratio, not the gap
            mid2 = np.sqrt(low2 * hi2)
        else:
            mid2 = 0.5 * (low2 + hi2)
        if mid2 <= low2 or mid2 >= hi2:
            break
        w, c = _held(tree, x, mid2, stack)
        if w >= k:
            hi2, w_hi, c_hi = mid2, w, c
        else:
            low2, w_lo, c_lo = mid2, w, c
    # the points in the bracket, nearest first, added to what the inner ball holds
    m = c_hi - c_lo
    dist = np.empty(max(m, 1))
    wt = np.empty(max(m, 1))
    got = 0
    top = 0
    stack[top] = 0
    top += 1
    while top > 0:
        top -= 1
        node = stack[top]
        near2 = 0.0
        for a in range(d):
            near, far = _gap(x[a], tree.lo[node, a], tree.hi[node, a], tree.boxsize[a])
            near2 += near * near
        if near2 > hi2:
            continue
        child = tree.left[node]
        if child < 0:
            for i in range(tree.start[node], tree.stop[node]):
                d2 = _dist2(tree.points, i, x, tree.boxsize)
                if low2 < d2 <= hi2 and got < m:
                    dist[got] = d2
                    wt[got] = tree.weights[i]
                    got += 1
            continue
        stack[top] = child
        stack[top + 1] = child + 1
        top += 2
    order = np.argsort(dist[:got], kind="mergesort")
    acc = w_lo
    c = 0.0
    for j in range(got):
        acc, c = plus_compensated(acc, c, wt[order[j]])
        if acc + c >= k:
            return np.sqrt(dist[order[j]])
    return np.sqrt(hi2)  # rounding kept the sum just short: the bracket's outer end


@kernel(entry=True, lazy=True, nogil=True)
def _kth_radii(tree, x, k, low, high, out, a, b):
    stack = np.empty(256, np.int64)
    for q in range(a, b):
        lo2 = low[q] * low[q] if low[q] >= 0.0 else -1.0
        hi2 = high[q] * high[q] if high[q] >= 0.0 else -1.0
        if hi2 > 0.0 and hi2 < np.inf:  # a radius holding k: the answer, unless less holds k
            w, c = _held(tree, x[q], hi2 * (1.0 - 1e-12), stack)
            if w < k:
                out[q] = high[q]
                continue
        out[q] = _kth_one(tree, x[q], k, lo2, hi2, stack)


def kth_radius(tree, x, k, low=None, high=None, threads=-1):
    """The least radius whose closed ball about each x holds weight >= k (inf where the
    whole tree weighs less). ``low``, ``high`` (optional, -1 where unknown): radii whose
    closed balls are known to hold less, and k (the distance of a point): when a ball just
    inside ``high`` holds less than k, ``high`` is the answer, found by one ball's count."""
    x = np.ascontiguousarray(x, float).reshape(-1, tree.points.shape[1])
    out = np.full(len(x), np.inf)
    if not len(tree.points) or tree.total[0] < k:
        return out
    low = np.full(len(x), -1.0) if low is None else np.ascontiguousarray(low, float)
    high = np.full(len(x), -1.0) if high is None else np.ascontiguousarray(high, float)
    in_chunks(lambda a, b: _kth_radii(tree, x, float(k), low, high, out, a, b), len(x),
              _threads(threads), most=kth_range(k))  # fmt: skip
    return out


def _threads(threads):
    return None if threads is None or threads < 1 else int(threads)
