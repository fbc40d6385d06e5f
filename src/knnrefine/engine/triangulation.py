"""Delaunay triangulation of the flat torus [0, lx) x [0, ly), updated in place.

Data structure (CGAL's periodic design, see ``docs/data-structure.md``): triangle t has three
vertices ``tv[t, i]``, three neighbours ``tn[t, i]`` (neighbour i lies across the edge
opposite corner i) and an integer offset per corner ``to[t, i] = (ox, oy)``: the corner sits at
``vxy[tv[t, i]] + (ox * lx, oy * ly)``. Offsets are normalised so that their minimum over the
three corners is 0 on each axis. Corners are counter-clockwise. ``tcc[t]`` and ``tr2[t]`` cache
the circumcenter (in the triangle's own frame) and the squared circumradius.

Vertices ``vxy`` lie on the grid q of ``geometry`` inside the fundamental domain, and the
periods are multiples of q, so every realised corner is exact and the exact predicates give
the same answer from every periodic copy.

Insertion is Bowyer-Watson: the cavity (triangles whose open circumdisk holds the new point)
is grown from a seed triangle whose circumdisk holds it (refinement always knows one: the
triangle whose circumcenter is being inserted), then re-triangulated as a fan around the new
point. The triangulation is valid as long as every circumradius is below a quarter of the
shorter period: then edges are shorter than half a period, the triangulation is a simplicial
complex, and a cavity never wraps around the torus. The initial grid satisfies this and a
Delaunay insertion never increases the largest circumradius.

Tuple layouts passed to every kernel:
``tri = (tv, tn, to, tcc, tr2, tstamp, tstate)``, ``ver = (vxy, vtri, vkind, vcell, vflag)``,
``scr = (tmark, vslot_a, vslot_b, cav, cav_s, bnd, bnd_o)`` (scratch), ``cnt`` int64 counters,
``prm`` float64 parameters (indices below).
"""

import numpy as np

from .geometry import circumcircle
from .jit import kernel
from .predicates import incircle

# counters (cnt)
C_NV = 0  # vertices in use
C_NT = 1  # triangles in use (always 2 * C_NV on the torus)
C_STAMP = 2  # insertion counter, stamps the cavity marks
C_LAST_NB = 3  # boundary edges of the last cavity (= new triangles)
# parameters (prm)
P_LX = 0
P_LY = 1

MAX_CAVITY = 1024  # triangles in one cavity; far beyond anything a refinement meets

# insertion results (negative: nothing was inserted)
INSERT_NOT_IN_SEED = -1  # the point is not strictly inside the seed's circumcircle (duplicate)
INSERT_CAVITY_OVERFLOW = -2
INSERT_TOPOLOGY = -3  # the cavity is not a disk: a broken invariant


@kernel(inline="always")
def corner(tv, to, vxy, t, i, sx, sy, lx, ly):
    """Position of corner i of triangle t, shifted by (sx, sy) periods (exact on the grid)."""
    v = tv[t, i]
    return vxy[v, 0] + (to[t, i, 0] + sx) * lx, vxy[v, 1] + (to[t, i, 1] + sy) * ly


@kernel(inline="always")
def set_circumcircle(tri, ver, prm, t):
    tv, tn, to, tcc, tr2, tstamp, tstate = tri
    vxy = ver[0]
    lx = prm[P_LX]
    ly = prm[P_LY]
    ax, ay = corner(tv, to, vxy, t, 0, 0, 0, lx, ly)
    bx, by = corner(tv, to, vxy, t, 1, 0, 0, lx, ly)
    cx, cy = corner(tv, to, vxy, t, 2, 0, 0, lx, ly)
    ux, uy, r2 = circumcircle(ax, ay, bx, by, cx, cy)
    tcc[t, 0] = ux
    tcc[t, 1] = uy
    tr2[t] = r2


@kernel()
def set_all_circumcircles(tri, ver, prm, nt):
    for t in range(nt):
        set_circumcircle(tri, ver, prm, t)


@kernel(inline="always")
def in_circumcircle(tri, ver, prm, t, sx, sy, px, py):
    """Exact sign: +1 if p is strictly inside the circumcircle of t shifted by (sx, sy)."""
    tv = tri[0]
    to = tri[2]
    vxy = ver[0]
    lx = prm[P_LX]
    ly = prm[P_LY]
    ax, ay = corner(tv, to, vxy, t, 0, sx, sy, lx, ly)
    bx, by = corner(tv, to, vxy, t, 1, sx, sy, lx, ly)
    cx, cy = corner(tv, to, vxy, t, 2, sx, sy, lx, ly)
    return incircle(ax, ay, bx, by, cx, cy, px, py)


@kernel(inline="always")
def mirror(tv, tn, n, t, a):
    """Index j in triangle n of the neighbour t across the edge whose head (in n) is vertex a."""
    for j in range(3):
        if tn[n, j] == t and tv[n, (j + 2) % 3] == a:
            return j
    return -1


@kernel()
def insert_vertex(px, py, seed, kind, tri, ver, scr, cnt, prm):
    """Insert the point p, given in the frame of triangle ``seed`` whose circumcircle holds it.

    p must lie on the grid. Returns the new vertex's index, or a negative INSERT_* code when
    nothing was inserted. Right after the call, with ``nb = cnt[C_LAST_NB]``, the new triangles
    are ``cav[:nb]`` (the cavity's slots reused first) and the vertices around the cavity are
    ``bnd[:nb, 0]``.
    """
    tv, tn, to, tcc, tr2, tstamp, tstate = tri
    vxy, vtri, vkind, vcell, vflag = ver
    tmark, vslot_a, vslot_b, cav, cav_s, bnd, bnd_o = scr
    lx = prm[P_LX]
    ly = prm[P_LY]
    if in_circumcircle(tri, ver, prm, seed, 0, 0, px, py) <= 0:
        return INSERT_NOT_IN_SEED
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp

    # grow the cavity by a breadth-first search; cav_s holds each triangle's shift (periods)
    cav[0] = seed
    cav_s[0, 0] = 0
    cav_s[0, 1] = 0
    tmark[seed] = stamp
    ncav = 1
    nb = 0
    i = 0
    while i < ncav:
        t = cav[i]
        sx = cav_s[i, 0]
        sy = cav_s[i, 1]
        for j in range(3):
            n = tn[t, j]
            if tmark[n] == stamp:
                continue
            ja = (j + 1) % 3
            jb = (j + 2) % 3
            a = tv[t, ja]
            jj = mirror(tv, tn, n, t, a)
            if jj < 0:
                return INSERT_TOPOLOGY
            nsx = sx + to[t, ja, 0] - to[n, (jj + 2) % 3, 0]
            nsy = sy + to[t, ja, 1] - to[n, (jj + 2) % 3, 1]
            if in_circumcircle(tri, ver, prm, n, nsx, nsy, px, py) > 0:
                if ncav >= MAX_CAVITY:
                    return INSERT_CAVITY_OVERFLOW
                tmark[n] = stamp
                cav[ncav] = n
                cav_s[ncav, 0] = nsx
                cav_s[ncav, 1] = nsy
                ncav += 1
            else:
                bnd[nb, 0] = a
                bnd[nb, 1] = tv[t, jb]
                bnd[nb, 2] = n
                bnd[nb, 3] = jj
                bnd_o[nb, 0] = to[t, ja, 0] + sx
                bnd_o[nb, 1] = to[t, ja, 1] + sy
                bnd_o[nb, 2] = to[t, jb, 0] + sx
                bnd_o[nb, 3] = to[t, jb, 1] + sy
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
    vxy[v, 0] = qx
    vxy[v, 1] = qy
    vkind[v] = kind
    vcell[v] = 0
    vflag[v] = 0

    # fan of new triangles (p, a, b) over the boundary edges; reuse the cavity's slots
    for e in range(nb):
        if e < ncav:
            s = cav[e]
        else:
            s = cnt[C_NT]
            cnt[C_NT] = s + 1
        cav[e] = s
        tstamp[s] += 1
        tstate[s] = 0
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
        tv[s, 0] = v
        tv[s, 1] = a
        tv[s, 2] = b
        to[s, 0, 0] = ox0 - mx
        to[s, 0, 1] = oy0 - my
        to[s, 1, 0] = ox1 - mx
        to[s, 1, 1] = oy1 - my
        to[s, 2, 0] = ox2 - mx
        to[s, 2, 1] = oy2 - my
        n = bnd[e, 2]
        tn[s, 0] = n
        tn[n, bnd[e, 3]] = s
        vslot_a[a] = s
        vslot_b[b] = s
        vtri[a] = s
    for e in range(nb):
        s = cav[e]
        tn[s, 1] = vslot_a[tv[s, 2]]
        tn[s, 2] = vslot_b[tv[s, 1]]
        set_circumcircle(tri, ver, prm, s)
    vtri[v] = cav[0]
    cnt[C_LAST_NB] = nb
    return v


@kernel(inline="always")
def vertex_star(v, tri, ver, prm, hx, hy):
    """Walk the triangles around vertex v: everything aspect(Vor(v)) = 2 R(v) / d_{M,2}(v) needs.

    Returns (R2, far, d2, deg): the squared outradius R(v)^2 (largest circumradius around v),
    the triangle whose circumcenter is farCorner(Vor(v)), the squared length of the shortest
    edge at v (d_{M,2}(v)^2, the nearest other vertex being a Delaunay neighbour) and the
    degree. The neighbours, relative to v, go to hx[:deg], hy[:deg] when hx is long enough;
    deg is -1 if it is not.
    """
    tv, tn, to, tcc, tr2, tstamp, tstate = tri
    vxy = ver[0]
    vtri = ver[1]
    lx = prm[P_LX]
    ly = prm[P_LY]
    t0 = vtri[v]
    t = t0
    big2 = -1.0
    far = -1
    d2 = np.inf
    deg = 0
    cap = hx.shape[0]
    while True:
        i = 0
        if tv[t, 1] == v:
            i = 1
        elif tv[t, 2] == v:
            i = 2
        if tr2[t] > big2:
            big2 = tr2[t]
            far = t
        i1 = (i + 1) % 3
        u = tv[t, i1]
        ex = vxy[u, 0] - vxy[v, 0] + (to[t, i1, 0] - to[t, i, 0]) * lx
        ey = vxy[u, 1] - vxy[v, 1] + (to[t, i1, 1] - to[t, i, 1]) * ly
        e2 = ex * ex + ey * ey
        if e2 < d2:
            d2 = e2
        if deg < cap:
            hx[deg] = ex
            hy[deg] = ey
        deg += 1
        t = tn[t, i1]
        if t == t0:
            break
    if deg > cap:
        deg = -1
    return big2, far, d2, deg
