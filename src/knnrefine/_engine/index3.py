"""The counting index over the input points in three dimensions (``index.py`` in the plane).

Refinement in space asks the plane's two questions: does the closed circumball of a
tetrahedron hold at least k points of P (``count_in_ball3``), and does the closed Voronoi cell
of a vertex, the intersection of the half-spaces of its Delaunay neighbours inside the ball
of radius R(v) about v, hold at least k (``count_in_cell3``). A static kd-tree (median splits
along the widest side of each node's tight box, points permuted so that each node owns a
contiguous range) answers both, adding whole nodes inside the region, skipping nodes that
miss it, testing the points of boundary leaves, and stopping as soon as the count reaches k.
On the 3-torus a question is asked once per periodic copy of the region that meets the
fundamental domain (regions are smaller than half the shortest period, so a point lies in at
most one copy). Both questions take the refinement's ``state.PointForest`` (two trees
counted as one: a continued run's new points in the second, ``index.grow_forest``), as in
the plane.

Layout: ``pts`` (n, 3) float64, permuted; ``box`` (nodes, 6): x0, y0, z0, x1, y1, z1;
``node`` (nodes, 4) int64: the ``state.NODE_*`` columns (lo, hi, first child, the second
following it, -1 at a leaf, split axis); ``split`` (nodes,); ``weight`` (nodes,) each node's
weight total, empty without weights. Weighted points (``build_index3(..., weights=w)``) are
(n, 4) rows, the weight last, and count with their weights as in the plane: a region holds
k when their weights sum to k or more (``geometry.plus_compensated``: a heavy point does not
swallow light ones); unweighted counts are whole numbers summed exactly.
"""

import numpy as np

from .geometry import plus_compensated
from .index import (
    LEAF_SIZE,
    STACK_SIZE,
    WINDOW_FULL,
    WINDOW_HIGH,
    WINDOW_LOW,
    axis_gap,
    grow_forest,
    held_by_node,
    merge_index,
    move_window,
    node_bound,
    node_weights,
    select_held,
    select_kth,
)
from .jit import kernel
from .state import NODE_AXIS, NODE_CHILD, NODE_HI, NODE_LO, PointTree


@kernel(entry=True)
def _build3(pts, box, node, split, root, free):
    """Split node ``root`` (its row range set) and its descendants, the rows of pts
    permuted in place, numbering new nodes from ``free``; returns the next free node (the
    node count when the root is node 0 and ``free`` 1)."""
    stack = np.empty(STACK_SIZE, np.int64)
    stack[0] = root
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        a = node[t, NODE_LO]
        b = node[t, NODE_HI]
        widest = 0
        extent = -1.0
        for ax in range(3):
            lo = np.inf
            hi = -np.inf
            for i in range(a, b):
                lo = min(lo, pts[i, ax])
                hi = max(hi, pts[i, ax])
            box[t, ax] = lo
            box[t, 3 + ax] = hi
            if hi - lo > extent:
                extent = hi - lo
                widest = ax
        if b - a <= LEAF_SIZE or extent <= 0.0:
            node[t, NODE_CHILD] = -1
            continue
        mid = (a + b) >> 1
        select_kth(pts, widest, a, b, mid)
        c = free
        free += 2
        node[t, NODE_CHILD] = c
        node[t, NODE_AXIS] = widest
        split[t] = pts[mid, widest]
        node[c, NODE_LO] = a
        node[c, NODE_HI] = mid
        node[c + 1, NODE_LO] = mid
        node[c + 1, NODE_HI] = b
        stack[sp] = c
        stack[sp + 1] = c + 1
        sp += 2
    return free


def build_index3(points, copy=True, weights=None):
    """The index (a ``state.PointTree``) over a copy of the (n, 3) points (``copy=False``:
    over the caller's float64 array itself, reordered in place); with ``weights`` ((n,),
    finite, >= 0) over a new (n, 4) array of both."""
    pts = np.ascontiguousarray(points, np.float64)
    if weights is not None:
        pts = np.column_stack([pts, np.asarray(weights, np.float64)])
    elif copy and pts is points:
        pts = pts.copy()
    cap = node_bound(len(pts))
    box = np.empty((cap, 6))
    node = np.empty((cap, 4), np.int64)
    split = np.zeros(cap)
    node[0, NODE_LO] = 0
    node[0, NODE_HI] = pts.shape[0]
    n = _build3(pts, box, node, split, 0, 1)
    node = node[:n]
    weight = np.zeros(0)
    if weights is not None:
        weight = np.empty(n)
        node_weights(pts, node, weight)
    return PointTree(pts, box[:n], node, split[:n], weight)


def merge_index3(index, q, weights=None):
    """``index.merge_index`` in space: the index of ``index``'s points and the points q
    (b, 3) together, without building it again; None when ``index`` is empty."""
    return merge_index(index, q, weights, _split_leaves3)


def grow_forest3(forest, q, weights=None):
    """``index.grow_forest`` with space's trees (space's and the sphere's continued runs):
    the new points q (b, 3) in the second tree, built over a copy of them
    (``build_index3``) or merged into it (``merge_index3``)."""
    return grow_forest(forest, q, weights, merge=merge_index3, build=_build_over)


def _build_over(x, weights=None):
    """``build_index3`` over the points x themselves (``grow_forest`` gives it a copy)."""
    return build_index3(x, copy=False, weights=weights)


@kernel(entry=True, nogil=True)
def _split_leaves3(pts, box, node, split, grown, free):
    """``_build3`` from each leaf in ``grown`` (its rows set), numbering new nodes from
    ``free``; returns the next free node."""
    for i in range(grown.shape[0]):
        free = _build3(pts, box, node, split, grown[i], free)
    return free


@kernel(inline="always")
def _box_reach(box, t, cx, cy, cz):
    """(the least, the largest) squared distance from c to node t's box."""
    near = 0.0
    far = 0.0
    for ax in range(3):
        c = cx if ax == 0 else (cy if ax == 1 else cz)
        lo = box[t, ax]
        hi = box[t, 3 + ax]
        d = max(lo - c, 0.0, c - hi)
        near += d * d
        f = max(c - lo, hi - c)
        far += f * f
    return near, far


@kernel(inline="always")
def _shifts(c, r, period):
    """(first, last) shift s in -1..1 of the copies [c - r, c + r] + s period that meet
    [0, period), c in [0, period), r below half the period."""
    return (-1 if c + r >= period else 0), (1 if c - r < 0.0 else 0)


@kernel(nrt=False)
def count_in_ball3(forest, c, r2, k, period, stack):
    """Points of P (both trees of ``forest``, a ``state.PointForest``) in the closed ball
    (c, sqrt(r2)) of the torus, up to k (the count stops there); c anywhere (wrapped here),
    the radius below half the shortest period: a cell with no half-spaces
    (``count_in_cell3``)."""
    # no half-spaces: empty slices of the index's own arrays, not module constants (numba
    # types those read-only and would compile the count a second time for them)
    return count_in_cell3(forest, c, forest.main.pts[:0], period[:0], 0, r2, k, period, stack)


@kernel(nrt=False)
def count_in_region3(index, vx, vy, vz, h, hc, nh, r2, k, stack):
    """Points x with |x - v|^2 <= r2 and (x - v) . h[i] <= hc[i] for every i < nh (their
    weight, for weighted points), up to at least k."""
    pts, box, node, weight = index.pts, index.box, index.node, index.weight
    weighted = weight.shape[0] > 0
    count = 0.0
    comp = 0.0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        near, far = _box_reach(box, t, vx, vy, vz)
        if near > r2:
            continue
        whole = far <= r2
        missed = False
        for i in range(nh):
            hi_ = 0.0
            lo_ = 0.0
            for ax in range(3):
                c = vx if ax == 0 else (vy if ax == 1 else vz)
                p = h[i, ax] * (box[t, ax] - c)
                q = h[i, ax] * (box[t, 3 + ax] - c)
                hi_ += max(p, q)
                lo_ += min(p, q)
            if lo_ > hc[i]:
                missed = True
                break
            if hi_ > hc[i]:
                whole = False
        if missed:
            continue
        if whole:
            count, comp = plus_compensated(count, comp, held_by_node(node, weight, t))
            if count + comp >= k:
                return count + comp
            continue
        if node[t, NODE_CHILD] < 0:
            for j in range(node[t, NODE_LO], node[t, NODE_HI]):
                dx = pts[j, 0] - vx
                dy = pts[j, 1] - vy
                dz = pts[j, 2] - vz
                if dx * dx + dy * dy + dz * dz > r2:
                    continue
                ok = True
                for i in range(nh):
                    if dx * h[i, 0] + dy * h[i, 1] + dz * h[i, 2] > hc[i]:
                        ok = False
                        break
                if ok:
                    count, comp = plus_compensated(count, comp, pts[j, 3] if weighted else 1.0)
                    if count + comp >= k:
                        return count + comp
            continue
        stack[sp] = node[t, NODE_CHILD]
        stack[sp + 1] = node[t, NODE_CHILD] + 1
        sp += 2
    return count + comp


@kernel(nrt=False)
def count_in_forest3(forest, vx, vy, vz, h, hc, nh, r2, k, stack):
    """``count_in_region3`` over both trees of ``forest`` (no periodic copies: the sphere's
    unit vectors), the second asked only for what the first left short of k."""
    count = count_in_region3(forest.main, vx, vy, vz, h, hc, nh, r2, k, stack)
    if count >= k or forest.extra.node[0, NODE_HI] == 0:
        return count
    return count + count_in_region3(forest.extra, vx, vy, vz, h, hc, nh, r2, k - count, stack)


@kernel(nrt=False)
def count_in_cell3(forest, v, h, hc, nh, r2, k, period, stack):
    """Points of P (both trees of ``forest``) in the closed Voronoi cell of the vertex at v:
    within sqrt(r2) (R(v), inflated) of v and on v's side of the bisector of each neighbour
    at v + h[i] (that is, (x - v) . h[i] <= hc[i] = |h[i]|^2 / 2, inflated), up to k."""
    count = _cell_copies3(forest.main, v, h, hc, nh, r2, k, period, stack)
    if count >= k or forest.extra.node[0, NODE_HI] == 0:
        return count
    return count + _cell_copies3(forest.extra, v, h, hc, nh, r2, k - count, period, stack)


@kernel(nrt=False)
def _cell_copies3(index, v, h, hc, nh, r2, k, period, stack):
    """``count_in_cell3`` in one tree."""
    r = np.sqrt(r2)
    w0 = v[0] - np.floor(v[0] / period[0]) * period[0]
    w1 = v[1] - np.floor(v[1] / period[1]) * period[1]
    w2 = v[2] - np.floor(v[2] / period[2]) * period[2]
    a0, b0 = _shifts(w0, r, period[0])
    a1, b1 = _shifts(w1, r, period[1])
    a2, b2 = _shifts(w2, r, period[2])
    count = 0.0
    comp = 0.0
    for s0 in range(a0, b0 + 1):
        for s1 in range(a1, b1 + 1):
            for s2 in range(a2, b2 + 1):
                here = count_in_region3(
                    index,
                    w0 + s0 * period[0],
                    w1 + s1 * period[1],
                    w2 + s2 * period[2],
                    h,
                    hc,
                    nh,
                    r2,
                    k - (count + comp),
                    stack,
                )
                count, comp = plus_compensated(count, comp, here)
                if count + comp >= k:
                    return count + comp
    return count + comp


@kernel(entry=True)
def holds_k_within3(index, x, r2, k, period):
    """For each point x[i]: does the closed ball of squared radius r2[i] about it hold >= k
    points of P? (Radii below half the shortest period: ``count_in_ball3``.)"""
    out = np.zeros(x.shape[0], np.bool_)
    stack = np.empty(STACK_SIZE, np.int64)
    none = index.pts[:0]
    for i in range(x.shape[0]):
        out[i] = _cell_copies3(index, x[i], none, period[:0], 0, r2[i], k, period, stack) >= k
    return out


@kernel(entry=True, nogil=True)
def weights_at3(index, x, out, start, stop):
    """out[j]: the number of points of P (weighted P: their weight) at exactly the place
    x[j], in the frame the points were indexed in (so that a point's copies meet it
    bit for bit; no periodic shift reaches a ball of radius 0): ``index.weights_at``."""
    stack = np.empty(STACK_SIZE, np.int64)
    # no half-spaces: empty slices typed as ``count_in_ball3``'s (one compile of the count)
    h, hc = index.pts[:0], index.weight[:0]
    for j in range(start, stop):
        out[j] = count_in_region3(index, x[j, 0], x[j, 1], x[j, 2], h, hc, 0, 0.0, np.inf,
                                  stack)  # fmt: skip
    return 0


# -- the k-th nearest distance itself (for evaluating d_{P,k}, not for refining) ---------------


@kernel(nrt=False)
def _kth_in_window3(index, q, k, r_in, r_out, period, periodic, stack, buf, wbuf):
    """``index._kth_in_window`` in space: the squared distance from q (3,) to its k-th
    nearest point of P (weighted: the least radius whose closed ball holds weight >= k) if
    it lies in (r_in, r_out] (nodes inside the inner ball counted whole, points between the
    radii kept in buf and wbuf, then the one needed selected), else WINDOW_LOW, WINDOW_HIGH
    or WINDOW_FULL. Periodic axes by the distance of the circle, each point counted once."""
    pts, box, node, split, weight = index
    rin2 = r_in * r_in
    rout2 = r_out * r_out
    inner = 0.0
    inner_c = 0.0
    between = 0.0
    between_c = 0.0
    kept = 0
    cap = buf.shape[0]
    unit = weight.shape[0] == 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        near2 = 0.0
        far2 = 0.0
        for a in range(3):
            g, f = axis_gap(q[a], box[t, a], box[t, 3 + a], period[a], periodic[a])
            near2 += g * g
            far2 += f * f
        if near2 > rout2:
            continue
        if far2 <= rin2:
            inner, inner_c = plus_compensated(inner, inner_c, held_by_node(node, weight, t))
            if inner + inner_c >= k:
                return WINDOW_LOW
            continue
        c = node[t, NODE_CHILD]
        if c >= 0:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
            continue
        for i in range(node[t, NODE_LO], node[t, NODE_HI]):
            d2 = 0.0
            for a in range(3):
                e = abs(pts[i, a] - q[a])
                if periodic[a]:
                    e = min(e, period[a] - e)
                d2 += e * e
            if d2 > rout2:
                continue
            if unit:  # counts: whole numbers, summed exactly
                if d2 <= rin2:
                    inner += 1.0
                    if inner >= k:
                        return WINDOW_LOW
                else:
                    if kept == cap:
                        return WINDOW_FULL
                    buf[kept] = d2
                    between += 1.0
                    kept += 1
                continue
            w = pts[i, 3]
            if d2 <= rin2:
                inner, inner_c = plus_compensated(inner, inner_c, w)
                if inner + inner_c >= k:
                    return WINDOW_LOW
            else:
                if kept == cap:
                    return WINDOW_FULL
                buf[kept] = d2
                wbuf[kept] = w
                between, between_c = plus_compensated(between, between_c, w)
                kept += 1
    inner += inner_c
    if inner + (between + between_c) < k:
        return WINDOW_HIGH
    return select_held(buf, wbuf, kept, k - inner, unit)


@kernel(entry=True, nogil=True)
def kth_distances3(index, q, k, r_in, r_out, period, periodic, cap, out, start, stop):
    """out[i] = d_{P,k}(q_i) for i in [start, stop) (q (m, 3) in the tree's frame, periodic
    coordinates in [0, period)), searched from the window (r_in[i], r_out[i]] moved as
    ``index.move_window`` says (``index.kth_distances`` in the plane); NaN where no window
    settles it within 200 tries (more points at one distance than ``cap``)."""
    stack = np.empty(STACK_SIZE, np.int64)
    buf = np.empty(cap)
    wbuf = np.empty(cap)
    for i in range(start, stop):
        known_low = 0.0
        known_high = np.inf
        a = r_in[i]
        b = max(r_out[i], a)
        if not b > a:
            b = a + max(a, 1e-300)
        width = b - a
        out[i] = np.nan
        for _ in range(200):
            d2 = _kth_in_window3(index, q[i], k, a, b, period, periodic, stack, buf, wbuf)
            done, out[i], a, b, width, known_low, known_high = move_window(
                d2, a, b, width, known_low, known_high
            )
            if done:
                break
    return 0
