"""Piecewise-linear functions on triangles: sampled on a regular grid, clipped to rectangles.

``rasterise``: each triangle visits only the grid centres in its bounding box and writes the
linear interpolant at those inside it; for well-shaped triangles (bounded aspect, Theorem 6)
the bounding boxes cover the grid about twice, so a grid costs O(pixels + triangles), with no
point location. ``clip_triangles``: Sutherland-Hodgman against the rectangle's four sides,
the function's values carried along (integrals over a region, pieces cut to a box).
"""

import numpy as np

from .jit import kernel


@kernel(inline="always")
def _corners(nodes, a, b, c):
    """The corners a, b, c of a triangle and twice its signed area."""
    ax, ay = nodes[a, 0], nodes[a, 1]
    bx, by = nodes[b, 0], nodes[b, 1]
    cx, cy = nodes[c, 0], nodes[c, 1]
    return ax, ay, bx, by, cx, cy, (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@kernel(entry=True, nogil=True)
def rasterise(nodes, triangles, values, x0, y0, dx, dy, px, py, out, ids):
    """out[j, i] = the linear interpolant of ``values`` (given at ``nodes``) over the triangle
    holding the grid centre (x0 + (i + 1/2) dx, y0 + (j + 1/2) dy), or with ``ids`` that
    triangle's index (``values`` unused: a start for ``walk_to``). Centres on no triangle
    keep their value. Along a periodic axis (px, py) a triangle reaching past the grid writes
    the centres it covers there wrapped round (index modulo the grid's size); along the
    others the part past the grid is skipped. Centres on a shared edge take either side's
    value (the interpolant is continuous)."""
    ny, nx = out.shape
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax, ay, bx, by, cx, cy, det = _corners(nodes, a, b, c)
        if det == 0.0:
            continue
        tol = -1e-12 * abs(det)
        i0 = int(np.ceil((min(ax, bx, cx) - x0) / dx - 0.5))
        i1 = int(np.floor((max(ax, bx, cx) - x0) / dx - 0.5))
        j0 = int(np.ceil((min(ay, by, cy) - y0) / dy - 0.5))
        j1 = int(np.floor((max(ay, by, cy) - y0) / dy - 0.5))
        if not px:
            i0 = max(i0, 0)
            i1 = min(i1, nx - 1)
        if not py:
            j0 = max(j0, 0)
            j1 = min(j1, ny - 1)
        va = vb = vc = 0.0
        if not ids:
            va, vb, vc = values[a], values[b], values[c]
        for j in range(j0, j1 + 1):
            y = y0 + (j + 0.5) * dy
            jj = j % ny
            for i in range(i0, i1 + 1):
                x = x0 + (i + 0.5) * dx
                # twice the signed areas of the sub-triangles opposite a, b and c
                wa = (bx - x) * (cy - y) - (by - y) * (cx - x)
                wb = (cx - x) * (ay - y) - (cy - y) * (ax - x)
                wc = det - wa - wb
                if det > 0.0:
                    inside = wa >= tol and wb >= tol and wc >= tol
                else:
                    inside = wa <= -tol and wb <= -tol and wc <= -tol
                if inside:
                    if ids:
                        out[jj, i % nx] = t
                    else:
                        out[jj, i % nx] = (wa * va + wb * vb + wc * vc) / det
    return 0


WALK_STEPS = 4096  # a located walk's limit: far beyond a well-shaped mesh's, a lost walk's guard


@kernel(inline="always")
def _walk(nodes, triangles, neighbours, start, x0, y0, dx, dy, x, y, bary):
    """The triangle holding (x, y), reached by walking from the one ``start`` names at its
    cell (``walk_to``), with its barycentric coordinates in ``bary`` (3,); -1: not found."""
    ny, nx = start.shape
    i = min(max(int((x - x0) / dx), 0), nx - 1)
    j = min(max(int((y - y0) / dy), 0), ny - 1)
    t = int(start[j, i])
    for _ in range(WALK_STEPS):
        if t < 0:
            return -1
        ax, ay, bx, by, cx, cy, det = _corners(
            nodes, triangles[t, 0], triangles[t, 1], triangles[t, 2]
        )
        if det == 0.0:
            return -1
        la = ((bx - x) * (cy - y) - (by - y) * (cx - x)) / det
        lb = ((cx - x) * (ay - y) - (cy - y) * (ax - x)) / det
        lc = 1.0 - la - lb
        worst = min(la, lb, lc)
        if worst >= -1e-12:
            bary[0] = la
            bary[1] = lb
            bary[2] = lc
            return t
        e = 0 if la == worst else (1 if lb == worst else 2)
        t = neighbours[t, e]
    return -1


@kernel(entry=True, nogil=True)
def walk_to(nodes, triangles, neighbours, start, x0, y0, dx, dy, qx, qy, tri, bary, lo, hi):
    """Locate queries lo..hi-1 by walking over triangles: from the triangle ``start`` (an
    ``ids`` raster, as ``rasterise``) names at the query's cell, across the edge opposite
    the most negative barycentric coordinate, until all three are >= -1e-12 (relative):
    tri[q] and bary[q] (3,), or tri[q] = -1 where the cell names no triangle, the walk
    leaves the triangles (a side with no neighbour) or runs past WALK_STEPS (the caller
    locates those otherwise). The triangles must be consistently oriented, either way."""
    here = np.empty(3)
    for q in range(lo, hi):
        t = _walk(nodes, triangles, neighbours, start, x0, y0, dx, dy, qx[q], qy[q], here)
        tri[q] = t
        if t >= 0:
            bary[q, 0] = here[0]
            bary[q, 1] = here[1]
            bary[q, 2] = here[2]
    return 0


@kernel(entry=True, nogil=True)
def walk_values(nodes, triangles, neighbours, start, x0, y0, dx, dy, qx, qy, values, out, lo,
                hi):  # fmt: skip
    """``walk_to`` that interpolates: out[q] the node ``values`` (one per node) linearly
    interpolated over the triangle holding query q, NaN where the walk finds none."""
    here = np.empty(3)
    for q in range(lo, hi):
        t = _walk(nodes, triangles, neighbours, start, x0, y0, dx, dy, qx[q], qy[q], here)
        if t < 0:
            out[q] = np.nan
        else:
            out[q] = (here[0] * values[triangles[t, 0]] + here[1] * values[triangles[t, 1]]
                      + here[2] * values[triangles[t, 2]])  # fmt: skip
    return 0


MAX_CLIPPED = 7  # a triangle cut by a rectangle's four sides has at most 7 corners


@kernel(entry=True)
def clip_triangles(corners, values, x0, y0, x1, y1):
    """Each triangle (t, 3, 2) clipped to the rectangle [x0, x1] x [y0, y1], with the linear
    function's ``values`` (t, 3) at its corners carried along. Returns (polygons (t, 7, 2),
    their values (t, 7), corner counts (t,)): polygon i is the first count[i] rows, in the
    triangle's orientation; count 0 when nothing is left. Cuts lie exactly on the side."""
    t = corners.shape[0]
    poly = np.zeros((t, MAX_CLIPPED, 2))
    vals = np.zeros((t, MAX_CLIPPED))
    count = np.zeros(t, np.int64)
    px = np.empty(MAX_CLIPPED + 1)
    py = np.empty(MAX_CLIPPED + 1)
    pv = np.empty(MAX_CLIPPED + 1)
    qx = np.empty(MAX_CLIPPED + 1)
    qy = np.empty(MAX_CLIPPED + 1)
    qv = np.empty(MAX_CLIPPED + 1)
    for i in range(t):
        m = 3
        for j in range(3):
            px[j] = corners[i, j, 0]
            py[j] = corners[i, j, 1]
            pv[j] = values[i, j]
        for side in range(4):
            axis = side // 2
            sign = 1.0 if side % 2 == 0 else -1.0
            bound = (x0 if axis == 0 else y0) if side % 2 == 0 else (x1 if axis == 0 else y1)
            q = 0
            for j in range(m):
                e = j + 1 if j + 1 < m else 0
                a = px[j] if axis == 0 else py[j]
                b = px[e] if axis == 0 else py[e]
                ain = sign * (a - bound) >= 0.0
                bin_ = sign * (b - bound) >= 0.0
                if ain:
                    qx[q] = px[j]
                    qy[q] = py[j]
                    qv[q] = pv[j]
                    q += 1
                if ain != bin_:
                    s = (bound - a) / (b - a)
                    cx = px[j] + s * (px[e] - px[j])
                    cy = py[j] + s * (py[e] - py[j])
                    if axis == 0:
                        cx = bound  # exactly on the side, whatever the rounding
                    else:
                        cy = bound
                    qx[q] = cx
                    qy[q] = cy
                    qv[q] = pv[j] + s * (pv[e] - pv[j])
                    q += 1
            m = q
            for j in range(m):
                px[j] = qx[j]
                py[j] = qy[j]
                pv[j] = qv[j]
            if m == 0:
                break
        count[i] = m
        for j in range(m):
            poly[i, j, 0] = px[j]
            poly[i, j, 1] = py[j]
            vals[i, j] = pv[j]
    return poly, vals, count


def fans(poly, vals, count):
    """The clipped polygons of ``clip_triangles`` as triangles fanned from their first corner:
    (corners (f, 3, 2), values (f, 3))."""
    tri, fv = [], []
    for j in range(1, MAX_CLIPPED - 1):
        has = count >= j + 2
        if not has.any():
            break
        tri.append(poly[has][:, [0, j, j + 1]])
        fv.append(vals[has][:, [0, j, j + 1]])
    if not tri:
        return np.zeros((0, 3, 2)), np.zeros((0, 3))
    return np.concatenate(tri), np.concatenate(fv)


@kernel(entry=True, nogil=True)
def first_holding3(x, cand, origin, inv, tol, tet, bary):
    """For each point x[q] (q, 3), the first of its candidate tetrahedra cand[q] (indices;
    ones past the end are a kd-tree's "none") that holds it, up to ``tol`` in barycentric
    coordinates: a tetrahedron t has corner ``origin[t]`` and ``inv[t]`` the inverse of its
    edge matrix (rows: the coordinates 1 to 3). Sets tet[q] (left as it was when none holds
    it) and bary[q] (4,); returns how many were found."""
    found = 0
    m = origin.shape[0]
    for q in range(x.shape[0]):
        for c in range(cand.shape[1]):
            t = cand[q, c]
            if t >= m:
                continue
            r0 = x[q, 0] - origin[t, 0]
            r1 = x[q, 1] - origin[t, 1]
            r2 = x[q, 2] - origin[t, 2]
            l1 = inv[t, 0, 0] * r0 + inv[t, 0, 1] * r1 + inv[t, 0, 2] * r2
            if l1 < -tol:
                continue
            l2 = inv[t, 1, 0] * r0 + inv[t, 1, 1] * r1 + inv[t, 1, 2] * r2
            if l2 < -tol:
                continue
            l3 = inv[t, 2, 0] * r0 + inv[t, 2, 1] * r1 + inv[t, 2, 2] * r2
            if l3 < -tol:
                continue
            l0 = 1.0 - (l1 + l2 + l3)
            if l0 < -tol:
                continue
            tet[q] = t
            bary[q, 0] = l0
            bary[q, 1] = l1
            bary[q, 2] = l2
            bary[q, 3] = l3
            found += 1
            break
    return found


@kernel(entry=True, nogil=True)
def rasterise3(corners, values, x0, step, periodic, out, start, stop):
    """``rasterise`` in space, over the tetrahedra start..stop-1 (corners (t, 4, 3), their
    values (t, 4)): out[k, j, i] = the linear interpolant at the grid centre x0 + (i + 1/2,
    j + 1/2, k + 1/2) * step of the tetrahedron holding it (barycentric coordinates >= -1e-9).
    Centres on no tetrahedron keep their value; along a periodic axis a tetrahedron reaching
    past the grid writes the centres there wrapped round, along the others that part is
    skipped. Each tetrahedron visits the centres of its bounding box only."""
    nz, ny, nx = out.shape
    n = np.empty(3, np.int64)
    n[0], n[1], n[2] = nx, ny, nz
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    m = np.empty((3, 3))
    inv = np.empty((3, 3))
    for t in range(start, stop):
        for a in range(3):
            for b in range(3):
                m[a, b] = corners[t, b + 1, a] - corners[t, 0, a]  # columns: the edges
        det = (
            m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
            - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
            + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
        )
        if det == 0.0:
            continue
        for a in range(3):  # the inverse by cofactors: rows give the barycentric l1..l3
            a1, a2 = (a + 1) % 3, (a + 2) % 3
            for b in range(3):
                b1, b2 = (b + 1) % 3, (b + 2) % 3
                inv[b, a] = (m[a1, b1] * m[a2, b2] - m[a1, b2] * m[a2, b1]) / det
        empty = False
        for a in range(3):
            c_lo = min(corners[t, 0, a], corners[t, 1, a], corners[t, 2, a], corners[t, 3, a])
            c_hi = max(corners[t, 0, a], corners[t, 1, a], corners[t, 2, a], corners[t, 3, a])
            lo[a] = int(np.ceil((c_lo - x0[a]) / step[a] - 0.5))
            hi[a] = int(np.floor((c_hi - x0[a]) / step[a] - 0.5))
            if not periodic[a]:
                lo[a] = max(lo[a], 0)
                hi[a] = min(hi[a], n[a] - 1)
            if lo[a] > hi[a]:
                empty = True
        if empty:
            continue
        v0, v1, v2, v3 = values[t, 0], values[t, 1], values[t, 2], values[t, 3]
        for k in range(lo[2], hi[2] + 1):
            rz = x0[2] + (k + 0.5) * step[2] - corners[t, 0, 2]
            kk = k % nz
            for j in range(lo[1], hi[1] + 1):
                ry = x0[1] + (j + 0.5) * step[1] - corners[t, 0, 1]
                jj = j % ny
                for i in range(lo[0], hi[0] + 1):
                    rx = x0[0] + (i + 0.5) * step[0] - corners[t, 0, 0]
                    l1 = inv[0, 0] * rx + inv[0, 1] * ry + inv[0, 2] * rz
                    l2 = inv[1, 0] * rx + inv[1, 1] * ry + inv[1, 2] * rz
                    l3 = inv[2, 0] * rx + inv[2, 1] * ry + inv[2, 2] * rz
                    l0 = 1.0 - (l1 + l2 + l3)
                    if l0 >= -1e-9 and l1 >= -1e-9 and l2 >= -1e-9 and l3 >= -1e-9:
                        out[kk, jj, i % nx] = l0 * v0 + l1 * v1 + l2 * v2 + l3 * v3
    return 0
