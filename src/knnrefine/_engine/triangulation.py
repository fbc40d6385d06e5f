"""Delaunay triangulation of the flat torus [0, lx) x [0, ly), updated in place.

Data structure (CGAL's periodic design, see ``docs/data-structure.md``): triangle t has three
vertices ``tv[t, i]``, three neighbours ``tn[t, i]`` (neighbour i lies across the edge
opposite corner i) and an integer offset per corner ``to[t, i] = (ox, oy)``: the corner sits at
``vxy[tv[t, i]] + (ox * lx, oy * ly)``. Offsets are normalised so that their minimum over the
three corners is 0 on each axis. Corners are counter-clockwise. ``radius2[t]`` caches the squared
circumradius; the circumcentre is recomputed from the corners where it is needed
(``circumcentre``, in the triangle's own frame), which costs less than its 16 bytes per
triangle of memory traffic.

Vertices ``vxy`` lie on the grid q of ``geometry`` inside the fundamental domain, and the
periods are multiples of q, so every realised corner is exact and the exact predicates give
the same answer from every periodic copy.

Two per-vertex caches make a vertex's Voronoi cell measurable without walking round it:
``outradius2[v]`` = R(v)^2 (the largest squared circumradius of the triangles at v: their
circumcentres are the corners of Vor(v)) and ``nearest2[v]`` = d_{M,2}(v)^2. An insertion keeps
both: a Voronoi cell only shrinks, so R(v) changes only where the largest triangle at v was
destroyed (then v's star is walked again) or through the two new triangles at v, and the
nearest vertex can only become the new one.

Insertion is Bowyer-Watson: the cavity (triangles whose open circumdisk holds the new point)
is grown from a seed triangle whose circumdisk holds it (refinement always knows one: the
triangle whose circumcenter is being inserted), then re-triangulated as a fan around the new
point. The triangulation is valid as long as every circumradius is below a quarter of the
shorter period: then edges are shorter than half a period, the triangulation is a simplicial
complex, and a cavity never wraps around the torus. The initial grid satisfies this and a
Delaunay insertion never increases the largest circumradius.

The kernels take the named structures of ``state.py``: ``mesh`` (a ``TorusMesh``: corners,
neighbours, offsets, circumcircle cache, vertex positions and stars) and, for an insertion,
``scratch``; counters and parameters by the slots named there. Nothing here knows about the
refinement: ``insert_vertex`` changes the triangulation and says what it changed (the new
vertex, the new triangles, the vertices around the cavity).
"""

import numpy as np

from .geometry import circumcircle
from .jit import kernel
from .predicates import incircle
from .state import (
    C_LAST_NB,
    C_NT,
    C_NV,
    C_STAMP,
    INSERT_CAVITY_OVERFLOW,
    INSERT_NOT_IN_SEED,
    INSERT_TOPOLOGY,
    P_LX,
    P_LY,
)

MAX_CAVITY = 1024  # triangles in one cavity; far beyond anything a refinement meets
LINK_SIZE = 4096  # the fan's link table: a power of two above twice the largest boundary


@kernel(inline="always")
def corner(mesh, t, i, sx, sy, lx, ly):
    """Position of corner i of triangle t, shifted by (sx, sy) periods (exact on the grid)."""
    v = mesh.corners[t, i]
    return (
        mesh.xy[v, 0] + (mesh.offsets[t, i, 0] + sx) * lx,
        mesh.xy[v, 1] + (mesh.offsets[t, i, 1] + sy) * ly,
    )


@kernel(inline="always")
def circumcentre(mesh, prm, t):
    """Circumcentre (x, y) of triangle t, in its own frame, and its squared circumradius."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    ax, ay = corner(mesh, t, 0, 0, 0, lx, ly)
    bx, by = corner(mesh, t, 1, 0, 0, lx, ly)
    cx, cy = corner(mesh, t, 2, 0, 0, lx, ly)
    return circumcircle(ax, ay, bx, by, cx, cy)


@kernel(inline="always")
def set_circumcircle(mesh, prm, t):
    """Cache triangle t's squared circumradius."""
    mesh.radius2[t] = circumcentre(mesh, prm, t)[2]


@kernel(entry=True)
def circumcentres(mesh, prm, triangles):
    """(len(triangles), 3): the circumcentre (x, y) of each listed triangle, in its own frame,
    and its squared circumradius."""
    out = np.empty((triangles.shape[0], 3))
    for i in range(triangles.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = circumcentre(mesh, prm, triangles[i])
    return out


@kernel(entry=True, nrt=False)
def set_all_circumcircles(mesh, prm, nt):
    for t in range(nt):
        set_circumcircle(mesh, prm, t)


@kernel(inline="always")
def edge_to(mesh, t, i, j, lx, ly):
    """The vector from corner i to corner j of triangle t (exact on the grid; the same from
    every triangle that has the edge, since offset differences do not depend on the frame)."""
    u = mesh.corners[t, j]
    v = mesh.corners[t, i]
    return (
        mesh.xy[u, 0] - mesh.xy[v, 0] + (mesh.offsets[t, j, 0] - mesh.offsets[t, i, 0]) * lx,
        mesh.xy[u, 1] - mesh.xy[v, 1] + (mesh.offsets[t, j, 1] - mesh.offsets[t, i, 1]) * ly,
    )


@kernel(inline="always")
def corner_of(mesh, t, v):
    """Index (0, 1 or 2) of vertex v among the corners of triangle t."""
    if mesh.corners[t, 1] == v:
        return 1
    if mesh.corners[t, 2] == v:
        return 2
    return 0


@kernel(inline="always")
def far_corner(v, mesh):
    """The triangle at v whose circumcentre is farCorner(Vor(v)): the largest circumradius
    (the first met walking round v from mesh.star[v], on ties). R(v)^2 is its radius2."""
    t0 = mesh.star[v]
    t = t0
    best = t0
    while True:
        if mesh.radius2[t] > mesh.radius2[best]:
            best = t
        t = mesh.neighbours[t, (corner_of(mesh, t, v) + 1) % 3]
        if t == t0:
            return best


@kernel(entry=True, nrt=False, nogil=True)
def set_outradii(mesh, nt, nv):
    """outradius2 of vertices 0..nv-1 from the cached circumradii of triangles 0..nt-1: the
    largest at each vertex, the very value the insertions compare with (``_forget_outradius``
    needs R(v)^2 to be one of its triangles' radius2, bit for bit)."""
    for v in range(nv):
        mesh.outradius2[v] = -1.0
    for t in range(nt):
        r2 = mesh.radius2[t]
        for i in range(3):
            c = mesh.corners[t, i]
            if r2 > mesh.outradius2[c]:
                mesh.outradius2[c] = r2


@kernel(entry=True, nrt=False, nogil=True)
def set_vertex_caches(mesh, prm, vertices, start, stop, hx, hy):
    """Fill outradius2 and nearest2 for vertices[start:stop] by walking their stars
    (``vertex_star``; hx, hy: its scratch, one per thread: threads may fill disjoint
    ranges at once)."""
    for i in range(start, stop):
        v = vertices[i]
        outradius2, _, d_m2_sq, _ = vertex_star(v, mesh, prm, hx, hy)
        mesh.outradius2[v] = outradius2
        mesh.nearest2[v] = d_m2_sq


@kernel(inline="always")
def in_circumcircle(mesh, prm, t, sx, sy, px, py):
    """Exact sign: +1 if p is strictly inside the circumcircle of t shifted by (sx, sy)."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    ax, ay = corner(mesh, t, 0, sx, sy, lx, ly)
    bx, by = corner(mesh, t, 1, sx, sy, lx, ly)
    cx, cy = corner(mesh, t, 2, sx, sy, lx, ly)
    return incircle(ax, ay, bx, by, cx, cy, px, py)


@kernel(inline="always")
def mirror(mesh, n, t, a):
    """Index j in triangle n of the neighbour t across the edge whose head (in n) is vertex a."""
    for j in range(3):
        if mesh.neighbours[n, j] == t and mesh.corners[n, (j + 2) % 3] == a:
            return j
    return -1


@kernel(nrt=False)
def insert_vertex(px, py, seed, mesh, scratch, cnt, prm):
    """Insert the point p, given in the frame of triangle ``seed`` whose circumcircle holds it.

    p must lie on the grid. Returns the new vertex's index, or a negative INSERT_* code when
    nothing was inserted. Right after the call, with ``nb = cnt[C_LAST_NB]``, the new triangles
    are ``scratch.cavity[:nb]`` (the cavity's slots reused first) and the vertices around the
    cavity are ``scratch.boundary[:nb, 0]``.
    """
    corners = mesh.corners
    neighbours = mesh.neighbours
    offsets = mesh.offsets
    cav = scratch.cavity
    cav_s = scratch.cavity_shift
    bnd = scratch.boundary
    bnd_o = scratch.boundary_offsets
    lx = prm[P_LX]
    ly = prm[P_LY]
    if in_circumcircle(mesh, prm, seed, 0, 0, px, py) <= 0:
        return INSERT_NOT_IN_SEED
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp

    # grow the cavity by a breadth-first search; cavity_shift holds each triangle's shift
    cav[0] = seed
    cav_s[0, 0] = 0
    cav_s[0, 1] = 0
    scratch.mark[seed] = stamp
    _forget_outradius(mesh, seed)
    ncav = 1
    nb = 0
    i = 0
    while i < ncav:
        t = cav[i]
        sx = cav_s[i, 0]
        sy = cav_s[i, 1]
        for j in range(3):
            n = neighbours[t, j]
            if scratch.mark[n] == stamp:
                continue
            ja = (j + 1) % 3
            jb = (j + 2) % 3
            a = corners[t, ja]
            jj = mirror(mesh, n, t, a)
            if jj < 0:
                return INSERT_TOPOLOGY
            nsx = sx + offsets[t, ja, 0] - offsets[n, (jj + 2) % 3, 0]
            nsy = sy + offsets[t, ja, 1] - offsets[n, (jj + 2) % 3, 1]
            if in_circumcircle(mesh, prm, n, nsx, nsy, px, py) > 0:
                if ncav >= MAX_CAVITY:
                    return INSERT_CAVITY_OVERFLOW
                scratch.mark[n] = stamp
                _forget_outradius(mesh, n)
                cav[ncav] = n
                cav_s[ncav, 0] = nsx
                cav_s[ncav, 1] = nsy
                ncav += 1
            else:
                bnd[nb, 0] = a
                bnd[nb, 1] = corners[t, jb]
                bnd[nb, 2] = n
                bnd[nb, 3] = jj
                bnd_o[nb, 0] = offsets[t, ja, 0] + sx
                bnd_o[nb, 1] = offsets[t, ja, 1] + sy
                bnd_o[nb, 2] = offsets[t, jb, 0] + sx
                bnd_o[nb, 3] = offsets[t, jb, 1] + sy
                nb += 1
        i += 1
    if nb != ncav + 2:
        return INSERT_TOPOLOGY

    # the new vertex, wrapped into the fundamental domain; w is its offset in the seed's frame
    wx = int(np.floor(px / lx))
    wy = int(np.floor(py / ly))
    qx = px - wx * lx
    qy = py - wy * ly
    while qx < 0.0:
        qx += lx
        wx -= 1
    while qx >= lx:
        qx -= lx
        wx += 1
    while qy < 0.0:
        qy += ly
        wy -= 1
    while qy >= ly:
        qy -= ly
        wy += 1
    v = cnt[C_NV]
    cnt[C_NV] = v + 1
    mesh.xy[v, 0] = qx
    mesh.xy[v, 1] = qy

    # fan of new triangles (p, a, b) over the boundary edges; reuse the cavity's slots
    for e in range(nb):
        if e < ncav:
            s = cav[e]
        else:
            s = cnt[C_NT]
            cnt[C_NT] = s + 1
        cav[e] = s
        a = bnd[e, 0]
        b = bnd[e, 1]
        ox0 = wx
        oy0 = wy
        ox1 = bnd_o[e, 0]
        oy1 = bnd_o[e, 1]
        ox2 = bnd_o[e, 2]
        oy2 = bnd_o[e, 3]
        mx = min(ox0, ox1, ox2)
        my = min(oy0, oy1, oy2)
        corners[s, 0] = v
        corners[s, 1] = a
        corners[s, 2] = b
        offsets[s, 0, 0] = ox0 - mx
        offsets[s, 0, 1] = oy0 - my
        offsets[s, 1, 0] = ox1 - mx
        offsets[s, 1, 1] = oy1 - my
        offsets[s, 2, 0] = ox2 - mx
        offsets[s, 2, 1] = oy2 - my
        n = bnd[e, 2]
        neighbours[s, 0] = n
        neighbours[n, bnd[e, 3]] = s
        _link_put(scratch.link, stamp, a, e)
        mesh.star[a] = s
    # the new triangle over edge (a, b) meets, across (v, b), the one over the edge from b
    for e in range(nb):
        s = cav[e]
        f = cav[_link_get(scratch.link, stamp, corners[s, 2])]
        neighbours[s, 1] = f
        neighbours[f, 2] = s
        set_circumcircle(mesh, prm, s)
    mesh.star[v] = cav[0]
    _update_vertex_caches(v, mesh, scratch, nb, lx, ly)
    cnt[C_LAST_NB] = nb
    return v


@kernel(inline="always")
def _link_slot(link, stamp, a):
    """Slot of vertex a in the link table for this insertion (open addressing; entries of
    earlier insertions count as free)."""
    size = link.shape[0]
    h = (a * 2654435761) & (size - 1)
    key = (stamp << 32) | a
    while link[h, 0] >> 32 == stamp and link[h, 0] != key:
        h = (h + 1) & (size - 1)
    return h, key


@kernel(inline="always")
def _link_put(link, stamp, a, e):
    h, key = _link_slot(link, stamp, a)
    link[h, 0] = key
    link[h, 1] = e


@kernel(inline="always")
def _link_get(link, stamp, a):
    return link[_link_slot(link, stamp, a)[0], 1]


@kernel(inline="always")
def _forget_outradius(mesh, t):
    """Triangle t leaves the triangulation: a corner whose R(v) it realised loses its cached
    value (marked -1, walked again after the insertion)."""
    for i in range(3):
        c = mesh.corners[t, i]
        if mesh.radius2[t] >= mesh.outradius2[c]:
            mesh.outradius2[c] = -1.0


@kernel(inline="always")
def _update_vertex_caches(v, mesh, scratch, nb, lx, ly):
    """The caches after inserting v, whose new triangles (v, a, b) are scratch.cavity[:nb]."""
    outradius2 = -1.0
    nearest2 = np.inf
    for e in range(nb):
        a = scratch.boundary[e, 0]
        if mesh.outradius2[a] < 0.0:
            mesh.outradius2[a] = mesh.radius2[far_corner(a, mesh)]
    for e in range(nb):
        s = scratch.cavity[e]
        r2 = mesh.radius2[s]
        outradius2 = max(outradius2, r2)
        a = mesh.corners[s, 1]
        b = mesh.corners[s, 2]
        mesh.outradius2[a] = max(mesh.outradius2[a], r2)
        mesh.outradius2[b] = max(mesh.outradius2[b], r2)
        ex, ey = edge_to(mesh, s, 0, 1, lx, ly)
        e2 = ex * ex + ey * ey
        mesh.nearest2[a] = min(mesh.nearest2[a], e2)
        nearest2 = min(nearest2, e2)
    mesh.outradius2[v] = outradius2
    mesh.nearest2[v] = nearest2


@kernel(nrt=False)
def vertex_star(v, mesh, prm, hx, hy):
    """Walk the triangles around vertex v: everything aspect(Vor(v)) = 2 R(v) / d_{M,2}(v) needs.

    Returns (outradius2, far_corner, d_m2_sq, degree): R(v)^2 (the largest squared circumradius
    around v), the triangle whose circumcentre is farCorner(Vor(v)), d_{M,2}(v)^2 (the shortest
    edge at v squared: the nearest other vertex is a Delaunay neighbour) and the degree. The
    neighbours, relative to v, go to hx[:degree], hy[:degree] when hx is long enough; degree
    is -1 if it is not.
    """
    lx = prm[P_LX]
    ly = prm[P_LY]
    t0 = mesh.star[v]
    t = t0
    outradius2 = -1.0
    far_corner = -1
    d_m2_sq = np.inf
    degree = 0
    cap = hx.shape[0]
    while True:
        i = corner_of(mesh, t, v)
        if mesh.radius2[t] > outradius2:
            outradius2 = mesh.radius2[t]
            far_corner = t
        i1 = (i + 1) % 3
        ex, ey = edge_to(mesh, t, i, i1, lx, ly)
        e2 = ex * ex + ey * ey
        if e2 < d_m2_sq:
            d_m2_sq = e2
        if degree < cap:
            hx[degree] = ex
            hy[degree] = ey
        degree += 1
        t = mesh.neighbours[t, i1]
        if t == t0:
            break
    if degree > cap:
        degree = -1
    return outradius2, far_corner, d_m2_sq, degree
