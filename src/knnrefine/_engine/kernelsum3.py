"""Sums of compactly supported kernels in space, one bandwidth per centre (``kernelsum`` in
the plane).

The adaptive density estimate is sum_i amp_i K(u_i(x)) with the triweight profile
K(u) = (1 - u)^3 for u < 1 (0 beyond) and u_i(x) = q_i |x - c_i|^2: centre i's kernel is
supported on the ball of radius r_i = 1 / sqrt(q_i), and has mass amp_i * MASS * r_i^3. The
centres live in the counting index's kd-tree (``index3.build_index3``, which permutes whole
rows), one row per centre:

    x, y, z, weight, amp, q, r, original row

and every node knows the largest extent below it (``kernelsum.node_extents``), so a query
visits only the leaves whose box, grown by that extent, holds it: about the number of kernels
that cover it.

The box bounds the estimate as in the plane: periodic axes wrap, the others fold (the
kernel's mass beyond a side is reflected back, by evaluating it at the query's mirror image
in that side, ``kernelsum.axis_image``), which needs extents no larger than the box's width
along the axis (``scale_kernels`` caps them). Coordinates are relative to the box's lower
corner.
"""

import numpy as np

from .index import STACK_SIZE
from .index3 import build_index3
from .jit import kernel
from .kernelsum import axis_image
from .state import NODE_CHILD, NODE_HI, NODE_LO

X, Y, Z, W, AMP, Q, R, ROW = range(8)
COLUMNS = 8
MASS = 64.0 * np.pi / 315.0  # the integral of (1 - |x|^2)^3 over the unit ball


def build_centres(points, weights, workers=None):
    """The kd-tree over the kernel centres (n, 3) (frame coordinates) with weights (n,):
    (rows, box, node), rows (n, COLUMNS) permuted, the kernel columns still zero. (One
    thread builds it: ``workers`` is accepted for the plane's signature.)"""
    n = len(points)
    rows = np.zeros((n, COLUMNS))
    rows[:, X : Z + 1] = points
    rows[:, W] = weights
    rows[:, ROW] = np.arange(n)
    tree = build_index3(rows, copy=False)
    return tree.pts, tree.box, tree.node


@kernel(inline="always")
def _scale_isotropic(rows, q, amp, r, log_ratio, c, alpha, cap, dim):
    """Radii scale by rho = c exp((dim alpha - 1) log_ratio), q by 1 / rho^2 and amp by
    1 / rho^dim (a kernel's mass grows as r^dim): the mass kept; a kernel wider than
    ``cap`` is narrowed to it."""
    for i in range(rows.shape[0]):
        rho = c * np.exp((dim * alpha - 1.0) * log_ratio[i])
        ri = r[i] * rho
        shrink = max(ri / cap, 1.0)
        scale = shrink / rho
        rows[i, Q] = q[i, 0] * scale * scale
        a = amp[i] * scale * scale
        if dim == 3:
            a = a * scale  # ((amp s) s) s, as before the two shared this loop
        rows[i, AMP] = a
        rows[i, R] = ri / shrink
    return 0


@kernel(entry=True, nogil=True)
def scale_kernels(rows, q, amp, r, log_ratio, c, alpha, cap):
    """Set the kernels' columns for bandwidth c at sensitivity alpha from their unit values
    (q (n, 1): 1 / d^2; amp, r = d; log_ratio: log(d_i / G)), as ``kernelsum.scale_kernels``
    in the plane: extents c G (d / G)^(3 alpha) ~ f^-alpha, f ~ d^-3 in space, the balls'
    mass r^3 kept (``_scale_isotropic``)."""
    return _scale_isotropic(rows, q, amp, r, log_ratio, c, alpha, cap, 3)


@kernel(entry=True, nogil=True)
def scale_surface_kernels(rows, q, amp, r, log_ratio, c, alpha, cap):
    """``scale_kernels`` for kernels on a surface in space (the unit sphere's, in chord
    distance), whose mass grows as r^2, as the plane's disks'."""
    return _scale_isotropic(rows, q, amp, r, log_ratio, c, alpha, cap, 2)


@kernel(inline="always")
def leaves_near3(box, node, extent, x, y, z, stack, leaves):
    """The leaves whose bounding box lies within extent[t] of (x, y, z), into ``leaves``;
    returns how many (``index.leaves_near`` in the plane)."""
    found = 0
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        t = stack[sp]
        dx = max(box[t, 0] - x, 0.0, x - box[t, 3])
        dy = max(box[t, 1] - y, 0.0, y - box[t, 4])
        dz = max(box[t, 2] - z, 0.0, z - box[t, 5])
        reach = extent[t]
        if dx * dx + dy * dy + dz * dz > reach * reach:
            continue
        c = node[t, NODE_CHILD]
        if c >= 0:
            stack[sp] = c
            stack[sp + 1] = c + 1
            sp += 2
        else:
            leaves[found] = t
            found += 1
    return found


@kernel(entry=True, nogil=True, fastmath=True)
def kernel_sums(rows, box, node, extent, q, loo, period, periodic, out, out2, start, stop):
    """out[j] = the sum of the kernels at query j (q (m, 3), frame coordinates, in the box),
    out2[j] the sum of their squares; with ``loo`` (the queries are centres) the centres at
    exactly the query's place are left out, all their images, and out2[j] is their weight
    (``kernelsum.kernel_sums`` in the plane). ``period`` (3,): the box's widths;
    ``periodic`` (3,) booleans."""
    stack = np.empty(STACK_SIZE, np.int64)
    leaves = np.empty(node.shape[0], np.int64)
    for j in range(start, stop):
        s = 0.0
        s2 = 0.0
        own = 0.0
        for a in range(3):
            x = axis_image(q[j, 0], a, period[0], periodic[0])
            for b in range(3):
                y = axis_image(q[j, 1], b, period[1], periodic[1])
                for e in range(3):
                    z = axis_image(q[j, 2], e, period[2], periodic[2])
                    for f in range(leaves_near3(box, node, extent, x, y, z, stack, leaves)):
                        t = leaves[f]
                        for i in range(node[t, NODE_LO], node[t, NODE_HI]):
                            ex = x - rows[i, X]
                            ey = y - rows[i, Y]
                            ez = z - rows[i, Z]
                            u = rows[i, Q] * (ex * ex + ey * ey + ez * ez)
                            v = max(1.0 - u, 0.0)
                            v = rows[i, AMP] * v * v * v
                            s += v
                            if loo:
                                if rows[i, X] == q[j, 0] and rows[i, Y] == q[j, 1]:
                                    if rows[i, Z] == q[j, 2]:
                                        own += v
                                        if a == 0 and b == 0 and e == 0:
                                            s2 += rows[i, W]
                            else:
                                s2 += v * v
        out[j] = max(s - own, 0.0)
        out2[j] = s2
    return 0
