"""Spatial index over the input points P: a static kd-tree that counts, with early exit.

The input points never enter the triangulation; refinement only asks two questions about
them, both of the form "does this region hold at least k points of P":

* the closed circumball of a triangle (``count_in_disk``), and
* the closed Voronoi cell of a mesh vertex, an intersection of half-planes inside the disk of
  radius R(v) about v (``count_in_cell``).

The tree is built once by median splits along the wider side of each node's tight bounding
box; the points are permuted in place so that every node owns a contiguous range of the
coordinate arrays and its count is ``hi - lo``. A query adds whole nodes that lie inside the
region, skips nodes that miss it, tests the points of boundary leaves one by one, and stops as
soon as the count reaches k. On the torus a query is repeated for each periodic copy of the
region that meets the fundamental domain (regions are smaller than half a period).

Layout (all flat arrays; node i's children are ``child[i]`` and ``child[i] + 1``, -1 at a leaf):
``xs, ys`` (n,) float64 permuted points; ``lo, hi, child`` (nodes,) int64;
``bx0, by0, bx1, by1`` (nodes,) float64 tight bounding boxes.
"""

import numpy as np
from numba import njit

LEAF_SIZE = 12
STACK_SIZE = 128  # > 2 * tree depth for any n that fits in memory


@njit(cache=True)
def _select(a, b, lo, hi, kth):
    """Partially sort a[lo:hi] (and b alongside) so that a[kth] is in its sorted place."""
    left = lo
    right = hi - 1
    while right > left:
        mid = (left + right) >> 1
        # median of three as pivot
        x0 = a[left]
        x1 = a[mid]
        x2 = a[right]
        if x0 > x1:
            x0, x1 = x1, x0
        if x1 > x2:
            x1 = x2
            if x0 > x1:
                x1 = x0
        pivot = x1
        i = left
        j = right
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                b[i], b[j] = b[j], b[i]
                i += 1
                j -= 1
        if kth <= j:
            right = j
        elif kth >= i:
            left = i
        else:
            break


@njit(cache=True)
def build_index(px, py):
    """Build the kd-tree over (px, py); returns the tuple of index arrays described above."""
    n = px.shape[0]
    xs = px.copy()
    ys = py.copy()
    cap = 4 * (n // LEAF_SIZE) + 8
    lo = np.empty(cap, np.int64)
    hi = np.empty(cap, np.int64)
    child = np.empty(cap, np.int64)
    bx0 = np.empty(cap)
    by0 = np.empty(cap)
    bx1 = np.empty(cap)
    by1 = np.empty(cap)
    lo[0] = 0
    hi[0] = n
    nnodes = 1
    stack = np.empty(STACK_SIZE, np.int64)
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        a = lo[node]
        b = hi[node]
        x0 = np.inf
        y0 = np.inf
        x1 = -np.inf
        y1 = -np.inf
        for i in range(a, b):
            x = xs[i]
            y = ys[i]
            if x < x0:
                x0 = x
            if x > x1:
                x1 = x
            if y < y0:
                y0 = y
            if y > y1:
                y1 = y
        bx0[node] = x0
        by0[node] = y0
        bx1[node] = x1
        by1[node] = y1
        if b - a <= LEAF_SIZE or (x1 == x0 and y1 == y0):
            child[node] = -1
            continue
        mid = (a + b) >> 1
        if x1 - x0 >= y1 - y0:
            _select(xs, ys, a, b, mid)
        else:
            _select(ys, xs, a, b, mid)
        c = nnodes
        nnodes += 2
        child[node] = c
        lo[c] = a
        hi[c] = mid
        lo[c + 1] = mid
        hi[c + 1] = b
        stack[sp] = c
        stack[sp + 1] = c + 1
        sp += 2
    return (
        xs,
        ys,
        lo[:nnodes].copy(),
        hi[:nnodes].copy(),
        child[:nnodes].copy(),
        bx0[:nnodes].copy(),
        by0[:nnodes].copy(),
        bx1[:nnodes].copy(),
        by1[:nnodes].copy(),
    )


@njit(cache=True)
def _count_disk(index, cx, cy, r2, k, count, stack):
    xs, ys, lo, hi, child, bx0, by0, bx1, by1 = index
    if lo.shape[0] == 0 or hi[0] == 0:
        return count
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        # nearest point of the box to the centre
        dx = max(bx0[node] - cx, 0.0, cx - bx1[node])
        dy = max(by0[node] - cy, 0.0, cy - by1[node])
        if dx * dx + dy * dy > r2:
            continue
        # farthest corner
        fx = max(cx - bx0[node], bx1[node] - cx)
        fy = max(cy - by0[node], by1[node] - cy)
        if fx * fx + fy * fy <= r2:
            count += hi[node] - lo[node]
            if count >= k:
                return count
            continue
        c = child[node]
        if c < 0:
            for i in range(lo[node], hi[node]):
                ex = xs[i] - cx
                ey = ys[i] - cy
                if ex * ex + ey * ey <= r2:
                    count += 1
                    if count >= k:
                        return count
            continue
        stack[sp] = c
        stack[sp + 1] = c + 1
        sp += 2
    return count


@njit(cache=True)
def count_in_disk(index, cx, cy, r2, k, lx, ly, stack):
    """Number of points of the periodic set P + (lx, ly)Z^2 in the closed disk (c, sqrt(r2)):
    exact when below k; otherwise the search stops early and returns some value >= k.
    Needs sqrt(r2) < min(lx, ly) / 2."""
    cx -= np.floor(cx / lx) * lx
    cy -= np.floor(cy / ly) * ly
    r = np.sqrt(r2)
    count = 0
    for sx in range(-1, 2):
        ox = cx + sx * lx
        if ox + r < 0.0 or ox - r > lx:
            continue
        for sy in range(-1, 2):
            oy = cy + sy * ly
            if oy + r < 0.0 or oy - r > ly:
                continue
            count = _count_disk(index, ox, oy, r2, k, count, stack)
            if count >= k:
                return count
    return count


@njit(cache=True)
def _count_cell(index, vx, vy, hx, hy, hc, nh, r2, k, count, stack):
    xs, ys, lo, hi, child, bx0, by0, bx1, by1 = index
    if lo.shape[0] == 0 or hi[0] == 0:
        return count
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        x0 = bx0[node] - vx
        x1 = bx1[node] - vx
        y0 = by0[node] - vy
        y1 = by1[node] - vy
        dx = max(x0, 0.0, -x1)
        dy = max(y0, 0.0, -y1)
        if dx * dx + dy * dy > r2:
            continue
        fx = max(-x0, x1)
        fy = max(-y0, y1)
        inside = fx * fx + fy * fy <= r2
        outside = False
        for j in range(nh):
            a = hx[j]
            b = hy[j]
            hmax = a * (x1 if a > 0.0 else x0) + b * (y1 if b > 0.0 else y0)
            if hmax <= hc[j]:
                continue
            inside = False
            hmin = a * (x0 if a > 0.0 else x1) + b * (y0 if b > 0.0 else y1)
            if hmin > hc[j]:
                outside = True
                break
        if outside:
            continue
        if inside:
            count += hi[node] - lo[node]
            if count >= k:
                return count
            continue
        c = child[node]
        if c < 0:
            for i in range(lo[node], hi[node]):
                ex = xs[i] - vx
                ey = ys[i] - vy
                ok = ex * ex + ey * ey <= r2
                for j in range(nh):
                    if not ok:
                        break
                    if hx[j] * ex + hy[j] * ey > hc[j]:
                        ok = False
                        break
                if ok:
                    count += 1
                    if count >= k:
                        return count
            continue
        stack[sp] = c
        stack[sp + 1] = c + 1
        sp += 2
    return count


@njit(cache=True)
def count_in_cell(index, vx, vy, hx, hy, hc, nh, r2, k, lx, ly, stack):
    """Number of points of the periodic P in the closed cell {v + p : hx[j] px + hy[j] py <= hc[j]}
    contained in the disk (v, sqrt(r2)): exact when below k, otherwise some value >= k. For a
    Voronoi cell, (hx[j], hy[j]) is the j-th neighbour minus v and hc[j] half its squared
    length."""
    vx -= np.floor(vx / lx) * lx
    vy -= np.floor(vy / ly) * ly
    r = np.sqrt(r2)
    count = 0
    for sx in range(-1, 2):
        ox = vx + sx * lx
        if ox + r < 0.0 or ox - r > lx:
            continue
        for sy in range(-1, 2):
            oy = vy + sy * ly
            if oy + r < 0.0 or oy - r > ly:
                continue
            count = _count_cell(index, ox, oy, hx, hy, hc, nh, r2, k, count, stack)
            if count >= k:
                return count
    return count
