"""Sums of compactly supported kernels with one bandwidth (and shape) per centre.

The adaptive density estimate is sum_i amp_i K(u_i(x)), where K(u) = (1 - u)^3 for u < 1
(the triweight profile, 0 beyond) and u_i(x) = (x - c_i)^T Q_i (x - c_i): centre i's kernel
is supported on an ellipse of extent r_i (isotropic: a disk, Q_i = I / r_i^2). The centres
live in a kd-tree built by the counting index's builder (``index.build_tree``, which
permutes whole rows), one row per centre:

    x, y, weight, amp, q11, q12, q22, r, original row

and every node knows the largest extent below it, so that a query visits only the nodes
whose bounding box, grown by that extent, holds it; a query costs about the number of
kernels that cover it.

The box bounds the estimate. Periodic axes wrap: centre and query images one period apart.
Non-periodic axes fold: a kernel's mass beyond a side is reflected back into the box
(evaluating the kernel at the query's mirror image), so every kernel keeps mass exactly
amp_i * pi / (4 sqrt(det Q_i)) in the box; both need extents no larger than the box's width
along the axis, which the caller keeps. Coordinates are relative to the box's lower corner
(``BoxMetric.frame``).
"""

import numpy as np

from .index import STACK_SIZE, build_tree, leaves_near
from .jit import kernel
from .state import NODE_CHILD, NODE_HI, NODE_LO

X, Y, W, AMP, Q11, Q12, Q22, R, ROW = range(9)
COLUMNS = 9
MASS = np.pi / 4.0  # the integral of (1 - |x|^2)^3 over the unit disk


def build_centres(points, weights, workers=None):
    """The kd-tree over the kernel centres (n, 2) (frame coordinates) with weights (n,):
    (rows, box, node), rows (n, COLUMNS) permuted, the kernel columns still zero."""
    n = len(points)
    rows = np.zeros((n, COLUMNS))
    rows[:, X] = points[:, 0]
    rows[:, Y] = points[:, 1]
    rows[:, W] = weights
    rows[:, ROW] = np.arange(n)
    rows, box, node, _ = build_tree(rows, workers)
    return rows, box, node


def one_leaf(rows, dim):
    """(box, node) of a tree that is one leaf holding every row of a kernels' table (its
    first ``dim`` columns the centres): a query visits every kernel, which costs less than
    building the kd-tree for a few queries. Any dimension."""
    n = len(rows)
    centres = rows[:, :dim]
    lo = centres.min(axis=0) if n else np.zeros(dim)
    hi = centres.max(axis=0) if n else np.zeros(dim)
    box = np.concatenate([lo, hi])[None, :]
    node = np.array([[0, n, -1, 0]], np.int64)  # NODE_LO, NODE_HI, NODE_CHILD, NODE_AXIS
    return box, node


@kernel(entry=True)
def node_extents(r, node, extent):
    """extent[t] = the largest kernel extent r[i] among node t's centres (children before
    parents: nodes are numbered parents first, so a reverse sweep sees children first). Any
    dimension: r is the extents' column of the tree's rows."""
    for t in range(node.shape[0] - 1, -1, -1):
        c = node[t, NODE_CHILD]
        if c >= 0:
            extent[t] = max(extent[c], extent[c + 1])
        else:
            e = 0.0
            for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                e = max(e, r[i])
            extent[t] = e


@kernel(entry=True, nogil=True)
def scale_kernels(rows, q, amp, r, log_ratio, c, alpha, cap):
    """Set the kernels' columns for bandwidth c at sensitivity alpha from their unit shapes
    (q: Q at unit bandwidth, sensitivity 1/2; amp, r likewise; log_ratio: log(d_i / G)):
    extents scale by rho = c exp((2 alpha - 1) log_ratio), Q by 1 / rho^2 and amp with it
    (mass kept); a kernel wider than ``cap`` is narrowed to it (wrapping and folding stay
    exact), its shape kept."""
    for i in range(rows.shape[0]):
        rho = c * np.exp((2.0 * alpha - 1.0) * log_ratio[i])
        ri = r[i] * rho
        shrink = max(ri / cap, 1.0)
        shrink *= shrink
        scale = shrink / (rho * rho)
        rows[i, Q11] = q[i, 0] * scale
        rows[i, Q12] = q[i, 1] * scale
        rows[i, Q22] = q[i, 2] * scale
        rows[i, AMP] = amp[i] * scale
        rows[i, R] = ri / np.sqrt(shrink)
    return 0


@kernel(entry=True, nogil=True)
def isotropic_units(d, w, total, mass, dim, q, r, amp, log_ratio):
    """Unit-bandwidth columns of isotropic kernels (disks or balls) of extents d and weights
    w (both in the tree's order): q (m, 3) in the plane (1/d^2, 0, 1/d^2) or (m, 1) in space
    (1/d^2), r = d, amp = w / total / (mass d^dim), log_ratio = log(d / G) (0 where d = 0),
    G the w-weighted geometric mean of the positive d."""
    num = 0.0
    den = 0.0
    for i in range(d.shape[0]):
        if d[i] > 0.0:
            log_ratio[i] = np.log(d[i])
            num += w[i] * log_ratio[i]
            den += w[i]
    log_g = num / max(den, 1e-300)
    plane = q.shape[1] == 3
    for i in range(d.shape[0]):
        di = d[i]
        d2 = di * di
        inv = 1.0 / d2
        q[i, 0] = inv
        if plane:
            q[i, 1] = 0.0
            q[i, 2] = inv
        r[i] = di
        amp[i] = w[i] / total / (mass * (d2 if dim == 2 else d2 * di))
        log_ratio[i] = log_ratio[i] - log_g if di > 0.0 else 0.0
    return 0


@kernel(inline="always")
def axis_image(q, j, period, periodic):
    """The j-th image of a coordinate (a query's or a centre's) along one axis of the box
    [0, period]: itself, then one period down and up (periodic) or its mirror images in the
    two sides (folded)."""
    if j == 0:
        return q
    if periodic:
        return q - period if j == 1 else q + period
    return -q if j == 1 else 2.0 * period - q


@kernel(entry=True, nogil=True, fastmath=True)
def kernel_sums(rows, box, node, extent, q, loo, period, periodic, out, out2, start, stop):
    """out[j] = sum of the kernels at query j (q (m, 2), frame coordinates, in the box;
    ``period`` (2,) the box's widths, ``periodic`` (2,) booleans), out2[j] the
    sum of their squares. With ``loo`` (leave one out; the queries are centres) the centres
    at exactly the query's place are left out of its sum, all images of them (copies of a
    point leave together, as a point of whole weight would), and out2[j] is their weight.
    The kernel loop has no branch on the support (max(1 - u, 0)^3: a branch taken three
    times in four was most of its time); queries in spatial order share the tree's leaves in
    the cache (``AdaptiveDensity`` sorts them)."""
    stack = np.empty(STACK_SIZE, np.int64)
    leaves = np.empty(node.shape[0], np.int64)
    for j in range(start, stop):
        s = 0.0
        s2 = 0.0
        own = 0.0  # the left-out centres' share of s (loo)
        for a in range(3):
            x = axis_image(q[j, 0], a, period[0], periodic[0])
            for b in range(3):
                y = axis_image(q[j, 1], b, period[1], periodic[1])
                for f in range(leaves_near(box, node, extent, 0.0, x, y, stack, leaves)):
                    t = leaves[f]
                    for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                        ex = x - rows[i, X]
                        ey = y - rows[i, Y]
                        u = rows[i, Q11] * ex * ex + rows[i, Q22] * ey * ey
                        u += 2.0 * rows[i, Q12] * ex * ey
                        v = max(1.0 - u, 0.0)
                        v = rows[i, AMP] * v * v * v
                        s += v
                        if loo:
                            if rows[i, X] == q[j, 0] and rows[i, Y] == q[j, 1]:
                                own += v
                                if a == 0 and b == 0:
                                    s2 += rows[i, W]
                        else:
                            s2 += v * v
        out[j] = max(s - own, 0.0)
        out2[j] = s2
    return 0


@kernel(entry=True, nogil=True)
def ball_moments(rows, box, node, qx, qy, radius, lx, ly, px, py, out, start, stop):
    """Weighted moments of the centres within ``radius[j]`` of query j (closed disk;
    periodic axes wrap, the others do not fold): out[j] = (w, wx, wy, wxx, wxy, wyy), with
    x, y relative to the query."""
    stack = np.empty(STACK_SIZE, np.int64)
    leaves = np.empty(node.shape[0], np.int64)
    none = np.empty(0)
    for j in range(start, stop):
        for m in range(6):
            out[j, m] = 0.0
        r = radius[j]
        r2 = r * r
        for a in range(3 if px else 1):
            x = axis_image(qx[j], a, lx, True)
            for b in range(3 if py else 1):
                y = axis_image(qy[j], b, ly, True)
                for f in range(leaves_near(box, node, none, r, x, y, stack, leaves)):
                    t = leaves[f]
                    for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                        ex = rows[i, X] - x
                        ey = rows[i, Y] - y
                        if ex * ex + ey * ey <= r2:
                            w = rows[i, W]
                            out[j, 0] += w
                            out[j, 1] += w * ex
                            out[j, 2] += w * ey
                            out[j, 3] += w * ex * ex
                            out[j, 4] += w * ex * ey
                            out[j, 5] += w * ey * ey
    return 0
