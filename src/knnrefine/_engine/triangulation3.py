"""Delaunay triangulation of the flat 3-torus [0, lx) x [0, ly) x [0, lz), updated in place.

The plane's design (``triangulation.py``) one dimension up, after CGAL's periodic 3-D
triangulation: tetrahedron t has four vertices ``corners[t, i]``, four neighbours
``neighbours[t, i]`` (neighbour i lies across the face opposite corner i) and an integer
offset per corner (ox, oy, oz) (packed: ``offset3``): the corner sits at ``xyz[v] + o * L``.
Offsets are normalised to a minimum of 0 per axis; every tetrahedron is positively oriented
(``predicates3.orient3d`` > 0). ``radius2[t]`` caches the squared circumradius.

Vertices lie on the grid q inside the fundamental domain and the periods are multiples of q,
so every corner is exact and the exact predicates (``predicates3``) answer the same from
every periodic copy. The triangulation is a simplicial complex on the torus while every
circumradius stays below a quarter of the shortest period: then a cavity never wraps round
the torus, a vertex appears at most once on a cavity's boundary, and two tetrahedra share at
most one face. The initial mesh (``initial.initial_grid3``) satisfies it and a Delaunay
insertion never increases the largest circumradius.

Insertion is Bowyer-Watson: the cavity (tetrahedra whose open circumball holds the new
point p) grows by a breadth-first search from a seed whose circumball holds p (refinement
knows one: the tetrahedron whose circumcentre is inserted); each boundary face, seen from p
strictly inside, gets a new tetrahedron: the cavity tetrahedron behind it with the corner
opposite the face replaced by p, so it keeps that tetrahedron's orientation. New
tetrahedra meet each other across faces through p, matched by their edge on the cavity's
boundary (a hash table). Unlike the plane, a cavity may have fewer boundary faces than
tetrahedra (a ball triangulated with interior edges): the slots left over are filled by
moving the last tetrahedra down (``_move``), so the arrays stay dense.

``R(v)^2`` (``outradius2``, the largest circumradius of the tetrahedra at v: Vor(v)'s far
corner) and ``d_{M,2}(v)^2`` (``nearest2``) are updated through the new tetrahedra at each
insertion. Where a tetrahedron realising R(v) leaves, R(v) is not walked again at once (in
uniform points that was 5.2 star walks an insertion): the cache keeps an upper bound, stored
negated, ``-max(old R(v)^2, the new tetrahedra's at v)``. Readers that can use a bound (queue
classes, the ball about v that holds its cell, the region tests) take ``abs``; those that
need R(v) itself (a Clean's test, a cell's pop) call ``outradius2_at3``, which walks the
star then and keeps the value.
"""

import numpy as np

from .geometry import circumsphere
from .jit import kernel
from .predicates3 import insphere
from .state import (
    C_LAST_NB,
    C_NT,
    C_NV,
    C_STAMP,
    INSERT_CAVITY_OVERFLOW,
    INSERT_NOT_IN_SEED,
    INSERT_TOPOLOGY,
)

MAX_CAVITY3 = 4096  # tetrahedra in one cavity
LINK_SIZE3 = 1 << 15  # the new tetrahedra's edge table: a power of two above 2 x its edges


OFFSET_BITS = 2  # per corner and axis in a tetrahedron's packed offsets (values 0..3)
_SHIFTS = OFFSET_BITS * np.arange(12, dtype=np.uint32)  # corner i, axis a: bits at 3 i + a


@kernel(inline="always")
def offset3(offsets, t, i, a):
    """Corner i's periodic offset along axis a in tetrahedron t: the 12 offsets of a
    tetrahedron are packed, two bits each, in one uint32 (4 bytes, not 12)."""
    return np.int64((offsets[t] >> np.uint32(OFFSET_BITS * (3 * i + a))) & np.uint32(3))


def pack_offsets(offsets):
    """(t, 4, 3) offsets in 0..3 -> (t,) uint32, as ``offset3`` reads them."""
    o = np.asarray(offsets).reshape(-1, 12).astype(np.uint32)
    if o.max(initial=0) > 3:
        raise ValueError("a tetrahedron's offsets must lie in 0..3")
    return np.bitwise_or.reduce(o << _SHIFTS, axis=1).astype(np.uint32)


@kernel(entry=True)
def unpack_offsets(packed):
    """(t,) uint32 packed offsets -> (t, 4, 3) int8 (no wider temporaries)."""
    out = np.empty((packed.shape[0], 4, 3), np.int8)
    for t in range(packed.shape[0]):
        for i in range(4):
            for a in range(3):
                out[t, i, a] = offset3(packed, t, i, a)
    return out


@kernel(inline="always")
def load_corners(mesh, t, sx, sy, sz, period, pts):
    """pts[0:4] = the corners of tetrahedron t shifted by (sx, sy, sz) periods (exact)."""
    for i in range(4):
        v = mesh.corners[t, i]
        pts[i, 0] = mesh.xyz[v, 0] + (offset3(mesh.offsets, t, i, 0) + sx) * period[0]
        pts[i, 1] = mesh.xyz[v, 1] + (offset3(mesh.offsets, t, i, 1) + sy) * period[1]
        pts[i, 2] = mesh.xyz[v, 2] + (offset3(mesh.offsets, t, i, 2) + sz) * period[2]


@kernel(inline="always")
def edge_to3(mesh, t, i, j, period):
    """The vector from corner i to corner j of tetrahedron t (exact on the grid; the same
    from every tetrahedron with that edge: ``triangulation.edge_to`` in the plane)."""
    u = mesh.corners[t, j]
    v = mesh.corners[t, i]
    o = mesh.offsets
    return (
        mesh.xyz[u, 0] - mesh.xyz[v, 0] + (offset3(o, t, j, 0) - offset3(o, t, i, 0)) * period[0],
        mesh.xyz[u, 1] - mesh.xyz[v, 1] + (offset3(o, t, j, 1) - offset3(o, t, i, 1)) * period[1],
        mesh.xyz[u, 2] - mesh.xyz[v, 2] + (offset3(o, t, j, 2) - offset3(o, t, i, 2)) * period[2],
    )


@kernel(inline="always")
def set_circumsphere(mesh, t, period, pts):
    """Cache tetrahedron t's squared circumradius (pts: scratch rows)."""
    load_corners(mesh, t, 0, 0, 0, period, pts)
    mesh.radius2[t] = circumsphere(pts)[3]


@kernel(entry=True)
def circumspheres(mesh, period, tets):
    """(len(tets), 4): each listed tetrahedron's circumcentre (x, y, z) in its own frame and
    its squared circumradius."""
    pts = np.empty((5, 3))
    out = np.empty((tets.shape[0], 4))
    for i in range(tets.shape[0]):
        load_corners(mesh, tets[i], 0, 0, 0, period, pts)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = circumsphere(pts)
    return out


@kernel(entry=True, nrt=False)
def set_all_circumspheres(mesh, period, nt, pts):
    for t in range(nt):
        set_circumsphere(mesh, t, period, pts)


@kernel(inline="always")
def corner_of3(mesh, t, v):
    """Index (0 to 3) of vertex v among the corners of t, -1 if it is none of them."""
    for i in range(4):
        if mesh.corners[t, i] == v:
            return i
    return -1


@kernel(inline="always")
def shift_across3(mesh, t, j, n, sx, sy, sz):
    """(found, the frame shift of tetrahedron n) where n is t's neighbour across face j and
    t's frame is shifted by (sx, sy, sz) periods: the shift that puts their shared corners
    in one place. found is False when n does not share t's corner (a broken mesh)."""
    a = (j + 1) % 4
    b = corner_of3(mesh, n, mesh.corners[t, a])
    if b < 0:
        return False, 0, 0, 0
    o = mesh.offsets
    return (
        True,
        sx + offset3(o, t, a, 0) - offset3(o, n, b, 0),
        sy + offset3(o, t, a, 1) - offset3(o, n, b, 1),
        sz + offset3(o, t, a, 2) - offset3(o, n, b, 2),
    )


@kernel(inline="always")
def _forget_outradius(mesh, t):
    """Tetrahedron t leaves: a corner whose R(v) it realised keeps it as a bound only
    (negated; one already a bound stays one)."""
    for i in range(4):
        c = mesh.corners[t, i]
        r2 = mesh.outradius2[c]
        if r2 >= 0.0 and mesh.radius2[t] >= r2:
            mesh.outradius2[c] = -r2


@kernel(nrt=False)
def walk_star3(v, mesh, scratch, cnt, period, h, ids):
    """Walk the tetrahedra around vertex v (breadth first, across the faces through v).

    Returns (outradius2, far, d_m2_sq, count, nh): R(v)^2, the tetrahedron whose circumcentre
    is farCorner(Vor(v)) (the first met of the largest), d_{M,2}(v)^2 (the shortest edge at
    v: the nearest other vertex is a Delaunay neighbour), the number of tetrahedra (-1 when
    they overflow the walk's stack, scratch.walk) and of neighbours: their positions
    relative to v go to h[:nh], their indices to ids[:nh] (nh = -1 when h is too short; an
    empty h collects none)."""
    stack = scratch.walk
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp
    t0 = mesh.star[v]
    stack[0] = t0
    scratch.mark[t0] = stamp
    n = 1
    i = 0
    nh = 0
    outradius2 = -1.0
    far = -1
    d_m2_sq = np.inf
    while i < n:
        t = stack[i]
        i += 1
        if mesh.radius2[t] > outradius2:
            outradius2 = mesh.radius2[t]
            far = t
        iv = corner_of3(mesh, t, v)
        for j in range(4):
            if j == iv:
                continue
            u = mesh.corners[t, j]
            dx, dy, dz = edge_to3(mesh, t, iv, j, period)
            d_m2_sq = min(d_m2_sq, dx * dx + dy * dy + dz * dz)
            if h.shape[0] > 0 and nh >= 0:
                seen = False
                for m in range(nh):
                    if ids[m] == u:
                        seen = True
                        break
                if not seen:
                    if nh >= h.shape[0]:
                        nh = -1
                    else:
                        ids[nh] = u
                        h[nh, 0] = dx
                        h[nh, 1] = dy
                        h[nh, 2] = dz
                        nh += 1
            nb = mesh.neighbours[t, j]  # across the face opposite u: it holds v
            if scratch.mark[nb] != stamp:
                if n >= stack.shape[0]:
                    return outradius2, far, d_m2_sq, -1, -1
                scratch.mark[nb] = stamp
                stack[n] = nb
                n += 1
    return outradius2, far, d_m2_sq, n, nh


@kernel(nrt=False)
def star3(v, mesh, scratch, cnt):
    """(R(v)^2, far corner's tetrahedron, tetrahedra at v, listed in scratch.walk): the walk
    of ``walk_star3`` without its edges, for the callers that need neither d_{M,2} nor the
    neighbours (most walks of a refinement: an entry of the circumball queue, an R(v) lost
    in a cavity), at about half its cost. A copy on purpose: ``walk_star3`` with a flag
    that skips the edges made a run 5-7% slower (10^6 points, k = 10, ``python
    benchmarks/paired_refine.py --dim 3``, twice)."""
    stack = scratch.walk
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp
    t0 = mesh.star[v]
    stack[0] = t0
    scratch.mark[t0] = stamp
    n = 1
    i = 0
    outradius2 = -1.0
    far = -1
    while i < n:
        t = stack[i]
        i += 1
        r2 = mesh.radius2[t]
        if r2 > outradius2:
            outradius2 = r2
            far = t
        for j in range(4):
            if mesh.corners[t, j] == v:
                continue
            nb = mesh.neighbours[t, j]  # across the face opposite corner j: it holds v
            if scratch.mark[nb] != stamp:
                if n >= stack.shape[0]:
                    return outradius2, far, -1
                scratch.mark[nb] = stamp
                stack[n] = nb
                n += 1
    return outradius2, far, n


@kernel(nrt=False)
def outradius2_at3(v, mesh, scratch, cnt):
    """R(v)^2 itself: the cache's, or, where it holds a bound only, a walk of v's star
    (``star3``: scratch.walk is overwritten), kept in the cache."""
    r2 = mesh.outradius2[v]
    if r2 < 0.0:
        r2 = star3(v, mesh, scratch, cnt)[0]
        mesh.outradius2[v] = r2
    return r2


@kernel(entry=True, nrt=False)
def refresh_outradii3(mesh, scratch, cnt, nv):
    """R(v)^2 itself in the cache for every vertex 0..nv-1 (``outradius2_at3``)."""
    for v in range(nv):
        outradius2_at3(v, mesh, scratch, cnt)


@kernel(entry=True, nrt=False, nogil=True)
def vertex_caches_from_tets3(mesh, period, nt, nv):
    """star, outradius2 and nearest2 of vertices 0..nv-1 in one pass over the tetrahedra
    (the values ``walk_star3`` finds: R(v)^2 the largest circumradius at v,
    d_{M,2}(v)^2 the shortest edge; star[v] the last tetrahedron at v), for a triangulation
    given whole (a stitched one: no star to walk from yet)."""
    for v in range(nv):
        mesh.outradius2[v] = -1.0
        mesh.nearest2[v] = np.inf
    for t in range(nt):
        r2 = mesh.radius2[t]
        for i in range(4):
            v = mesh.corners[t, i]
            mesh.star[v] = t
            if r2 > mesh.outradius2[v]:
                mesh.outradius2[v] = r2
            for j in range(i + 1, 4):
                dx, dy, dz = edge_to3(mesh, t, i, j, period)
                e2 = dx * dx + dy * dy + dz * dz
                u = mesh.corners[t, j]
                if e2 < mesh.nearest2[v]:
                    mesh.nearest2[v] = e2
                if e2 < mesh.nearest2[u]:
                    mesh.nearest2[u] = e2


@kernel(inline="always")
def _link_slot(link, stamp, a, b):
    """Slot of edge (a, b), a < b, in the edge table for this insertion (open addressing;
    entries of earlier insertions count as free)."""
    size = link.shape[0]
    key = (a << 32) | b
    h = ((a * 2654435761) ^ (b * 40503)) & (size - 1)
    while link[h, 0] == stamp and link[h, 1] != key:
        h = (h + 1) & (size - 1)
    return h, key


@kernel(inline="always")
def _move(mesh, scratch, src, dst):
    """Move tetrahedron src into the free slot dst, repointing its neighbours and stars."""
    for i in range(4):
        mesh.corners[dst, i] = mesh.corners[src, i]
        mesh.neighbours[dst, i] = mesh.neighbours[src, i]
    mesh.offsets[dst] = mesh.offsets[src]
    mesh.radius2[dst] = mesh.radius2[src]
    scratch.mark[dst] = scratch.mark[src]
    for i in range(4):
        n = mesh.neighbours[dst, i]
        for j in range(4):
            if mesh.neighbours[n, j] == src:
                mesh.neighbours[n, j] = dst
        v = mesh.corners[dst, i]
        if mesh.star[v] == src:
            mesh.star[v] = dst


@kernel(nrt=False)
def insert_vertex3(p, seed, mesh, scratch, cnt, period):
    """Insert the point p (3,), given in the frame of tetrahedron ``seed`` whose open
    circumball holds it; p on the grid. Returns the new vertex's index, or a negative
    INSERT_* code with nothing changed. Right after, with ``nb = cnt[C_LAST_NB]``, the new
    tetrahedra are ``scratch.cavity[:nb]`` (their final slots), and
    ``scratch.moved[1 : 1 + scratch.moved[0, 0]]`` the (from, to) slots of the tetrahedra
    moved down to keep the arrays dense (``_move``), in the order made."""
    corners = mesh.corners
    neighbours = mesh.neighbours
    offsets = mesh.offsets
    cav = scratch.cavity
    cav_s = scratch.cavity_shift
    bnd = scratch.boundary
    fc = scratch.face_corners
    fo = scratch.face_offsets
    pts = scratch.points
    for a in range(3):
        pts[4, a] = p[a]
    load_corners(mesh, seed, 0, 0, 0, period, pts)
    if insphere(pts) <= 0:
        return INSERT_NOT_IN_SEED
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp

    # the cavity, breadth first; cav_s holds each tetrahedron's shift relative to the seed
    cav[0] = seed
    cav_s[0, 0] = 0
    cav_s[0, 1] = 0
    cav_s[0, 2] = 0
    scratch.mark[seed] = stamp
    ncav = 1
    nb = 0
    i = 0
    while i < ncav:
        t = cav[i]
        for j in range(4):
            n = neighbours[t, j]
            if scratch.mark[n] == stamp:
                continue
            ok, sx, sy, sz = shift_across3(mesh, t, j, n, cav_s[i, 0], cav_s[i, 1], cav_s[i, 2])
            if not ok:
                return _undo(mesh, scratch, ncav, INSERT_TOPOLOGY)
            load_corners(mesh, n, sx, sy, sz, period, pts)
            if insphere(pts) > 0:
                if ncav >= cav.shape[0]:
                    return _undo(mesh, scratch, ncav, INSERT_CAVITY_OVERFLOW)
                scratch.mark[n] = stamp
                cav[ncav] = n
                cav_s[ncav, 0] = sx
                cav_s[ncav, 1] = sy
                cav_s[ncav, 2] = sz
                ncav += 1
            else:
                jj = -1
                for k in range(4):
                    if neighbours[n, k] == t:
                        jj = k
                if jj < 0 or nb >= bnd.shape[0]:
                    return _undo(mesh, scratch, ncav, INSERT_TOPOLOGY)
                bnd[nb, 0] = n
                bnd[nb, 1] = jj
                bnd[nb, 2] = j
                for k in range(4):
                    fc[nb, k] = corners[t, k]
                    fo[nb, k, 0] = offset3(offsets, t, k, 0) + cav_s[i, 0]
                    fo[nb, k, 1] = offset3(offsets, t, k, 1) + cav_s[i, 1]
                    fo[nb, k, 2] = offset3(offsets, t, k, 2) + cav_s[i, 2]
                nb += 1
        i += 1
    for e in range(ncav):
        _forget_outradius(mesh, cav[e])

    # the new vertex, wrapped into the fundamental domain; w is its offset in the seed frame
    v = cnt[C_NV]
    cnt[C_NV] = v + 1
    w = scratch.shift
    for a in range(3):
        wa = int(np.floor(p[a] / period[a]))
        q = p[a] - wa * period[a]
        while q < 0.0:
            q += period[a]
            wa -= 1
        while q >= period[a]:
            q -= period[a]
            wa += 1
        mesh.xyz[v, a] = q
        w[a] = wa

    # one new tetrahedron per boundary face: the cavity's behind it, corner j replaced by v
    link = scratch.link
    for e in range(nb):
        if e < ncav:
            s = cav[e]
        else:
            s = cnt[C_NT]
            cnt[C_NT] = s + 1
        cav[e] = s
        j = bnd[e, 2]
        for a in range(3):
            fo[e, j, a] = w[a]
        packed = 0
        for a in range(3):
            m = min(fo[e, 0, a], fo[e, 1, a], fo[e, 2, a], fo[e, 3, a])
            for k in range(4):  # 0 or 1: a tetrahedron spans under half a period
                packed |= (fo[e, k, a] - m) << (OFFSET_BITS * (3 * k + a))
        offsets[s] = packed
        for k in range(4):
            corners[s, k] = fc[e, k]
        corners[s, j] = v
        n = bnd[e, 0]
        neighbours[s, j] = n
        neighbours[n, bnd[e, 1]] = s
        scratch.mark[s] = stamp
        for k in range(4):
            if k != j:
                mesh.star[corners[s, k]] = s
        # the faces through v: opposite each other corner k, across the edge left
        for k in range(4):
            if k == j:
                continue
            a = -1
            b = -1
            for c in range(4):
                if c != j and c != k:
                    if a < 0:
                        a = corners[s, c]
                    else:
                        b = corners[s, c]
            a = np.int64(a)
            b = np.int64(b)
            if a > b:
                a, b = b, a
            h, key = _link_slot(link, stamp, a, b)
            if link[h, 0] == stamp:
                other = link[h, 2]
                neighbours[s, k] = other >> 2
                neighbours[other >> 2, other & 3] = s
            else:
                link[h, 0] = stamp
                link[h, 1] = key
                link[h, 2] = (np.int64(s) << 2) | k
    mesh.star[v] = cav[0]
    for e in range(nb):
        set_circumsphere(mesh, cav[e], period, pts)

    # fewer new tetrahedra than old: move the last ones into the slots left over
    scratch.moved[0, 0] = 0
    for e in range(nb, ncav):
        scratch.mark[cav[e]] = -1  # free
    for e in range(nb, ncav):
        f = cav[e]
        while cnt[C_NT] > 0 and scratch.mark[cnt[C_NT] - 1] == -1:
            cnt[C_NT] -= 1
        if f >= cnt[C_NT]:
            continue
        last = cnt[C_NT] - 1
        _move(mesh, scratch, last, f)
        scratch.mark[last] = -1
        m = scratch.moved[0, 0] + 1
        scratch.moved[0, 0] = m
        scratch.moved[m, 0] = last
        scratch.moved[m, 1] = f
        cnt[C_NT] = last
        for g in range(nb):
            if cav[g] == last:
                cav[g] = f
    while cnt[C_NT] > 0 and scratch.mark[cnt[C_NT] - 1] == -1:
        cnt[C_NT] -= 1
    _update_vertex_caches3(v, mesh, scratch, cnt, nb, period)
    cnt[C_LAST_NB] = nb
    return v


@kernel(inline="always")
def _undo(mesh, scratch, ncav, code):
    """Nothing was changed but the cavity marks: clear them, return code."""
    for e in range(ncav):
        scratch.mark[scratch.cavity[e]] = 0
    return code


@kernel(inline="always")
def _update_vertex_caches3(v, mesh, scratch, cnt, nb, period):
    """R and d_{M,2} after inserting v, whose new tetrahedra are scratch.cavity[:nb]."""
    outradius2 = -1.0
    nearest2 = np.inf
    for e in range(nb):
        s = scratch.cavity[e]
        iv = corner_of3(mesh, s, v)
        r2 = mesh.radius2[s]
        outradius2 = max(outradius2, r2)
        for k in range(4):
            if k == iv:
                continue
            u = mesh.corners[s, k]
            bound = mesh.outradius2[u]
            if bound >= 0.0:
                mesh.outradius2[u] = max(bound, r2)
            else:  # R(u) is known as a bound only (``_forget_outradius``): keep it one
                mesh.outradius2[u] = -max(-bound, r2)
            dx, dy, dz = edge_to3(mesh, s, iv, k, period)
            e2 = dx * dx + dy * dy + dz * dz
            mesh.nearest2[u] = min(mesh.nearest2[u], e2)
            nearest2 = min(nearest2, e2)
    mesh.outradius2[v] = outradius2
    mesh.nearest2[v] = nearest2


@kernel(nrt=False)
def insert_circumcentre3(t, mesh, scratch, cnt, period, q):
    """Insert the circumcentre of tetrahedron t (snapped to the grid q, in t's frame; t's
    circumball holds it unless the snap moved it out: then INSERT_NOT_IN_SEED)."""
    pts = scratch.points
    load_corners(mesh, t, 0, 0, 0, period, pts)
    x, y, z, _ = circumsphere(pts)
    p = scratch.walk_point
    p[0] = np.rint(x / q) * q
    p[1] = np.rint(y / q) * q
    p[2] = np.rint(z / q) * q
    return insert_vertex3(p, t, mesh, scratch, cnt, period)


@kernel(entry=True, nrt=False)
def insert_largest3(mesh, scratch, cnt, period, q, count, min_radius2):
    """Delaunay refinement by circumradius alone, for tests and benchmarks of the
    triangulation: ``count`` times, insert the circumcentre of the tetrahedron with the
    largest circumradius (stopping below ``min_radius2``). Returns the insertions made, or a
    negative INSERT_* code."""
    for c in range(count):
        best = 0
        for t in range(cnt[C_NT]):
            if mesh.radius2[t] > mesh.radius2[best]:
                best = t
        if mesh.radius2[best] < min_radius2:
            return c
        v = insert_circumcentre3(best, mesh, scratch, cnt, period, q)
        if v < 0:
            return v
    return count


@kernel(entry=True, nrt=False)
def insert_points3(points, seeds, mesh, scratch, cnt, period):
    """Insert points[i] (each in the frame of tetrahedron seeds[i], whose circumball holds
    it) in order; returns the number inserted, stopping at the first failure."""
    for i in range(points.shape[0]):
        if insert_vertex3(points[i], seeds[i], mesh, scratch, cnt, period) < 0:
            return i
    return points.shape[0]


def new_torus3(period, grid, vertices, tetrahedra):
    """(mesh, scratch, cnt): a ``TorusMesh3`` holding the triangulation ``grid`` =
    (xyz, corners, offsets, neighbours, ...) of ``initial.initial_grid3`` (or a stitched
    one: offsets (t, 4, 3), or packed (t,) as ``offset3`` reads them), with room for
    ``vertices`` vertices and ``tetrahedra`` tetrahedra, its caches filled."""
    from .state import N_COUNTERS, Scratch3, TorusMesh3, mapped

    xyz, corners, offsets, neighbours = grid[:4]
    nv, nt = len(xyz), len(corners)
    vertices, tetrahedra = max(vertices, nv), max(tetrahedra, nt)

    # the arrays sized by a capacity (and the cavity's) are mapped: the rows never written
    # cost no memory, and they grow in place (``state.grow``)
    def rows(a, size, dtype):
        out = mapped((size,) + a.shape[1:], dtype)
        out[: len(a)] = a
        return out

    mesh = TorusMesh3(
        corners=rows(corners, tetrahedra, np.int32),
        neighbours=rows(neighbours, tetrahedra, np.int32),
        offsets=rows(
            offsets if offsets.ndim == 1 else pack_offsets(offsets), tetrahedra, np.uint32
        ),  # fmt: skip
        radius2=mapped((tetrahedra,), np.float64),
        xyz=rows(xyz, vertices, np.float64),
        star=mapped((vertices,), np.int32),
        outradius2=mapped((vertices,), np.float64),
        nearest2=mapped((vertices,), np.float64),
    )
    scratch = Scratch3(
        mark=mapped((tetrahedra,), np.int32),
        cavity=mapped((MAX_CAVITY3,), np.int32),
        cavity_shift=mapped((MAX_CAVITY3, 3), np.int64),
        boundary=mapped((MAX_CAVITY3, 3), np.int64),
        face_corners=mapped((MAX_CAVITY3, 4), np.int64),
        face_offsets=mapped((MAX_CAVITY3, 4, 3), np.int64),
        link=np.zeros((LINK_SIZE3, 3), np.int64),
        walk=mapped((MAX_CAVITY3,), np.int32),
        points=np.zeros((5, 3)),
        shift=np.zeros(3, np.int64),
        walk_point=np.zeros(3),
        moved=np.zeros((MAX_CAVITY3 + 1, 2), np.int64),
        no_h=np.zeros((0, 3)),
        no_ids=np.zeros(0, np.int64),
    )
    cnt = np.zeros(N_COUNTERS, np.int64)
    cnt[C_NV], cnt[C_NT] = nv, nt
    period = np.asarray(period, float)
    set_all_circumspheres(mesh, period, nt, scratch.points)
    vertex_caches_from_tets3(mesh, period, nt, nv)
    return mesh, scratch, cnt


@kernel(nrt=False)
def vertex_neighbours3(v, mesh, scratch, cnt, period, h, ids):
    """The Delaunay neighbours of v: h[i] their positions relative to v, ids[i] their
    indices; returns their number, -1 if h or the walk's stack is too short."""
    n, nh = walk_star3(v, mesh, scratch, cnt, period, h, ids)[3:]
    return -1 if n < 0 else nh


@kernel(nrt=False)
def neighbours_local3(v, mesh, period, stack, h, ids):
    """``vertex_neighbours3`` without the shared marks: the tetrahedra met are looked up in
    the walk's own stack (a star has a few dozen), so threads may walk stars at once.
    Returns the number of neighbours, -1 if h or the stack is too short."""
    stack[0] = mesh.star[v]
    n = 1
    i = 0
    nh = 0
    while i < n:
        t = stack[i]
        i += 1
        iv = corner_of3(mesh, t, v)
        for j in range(4):
            if j == iv:
                continue
            u = mesh.corners[t, j]
            seen = False
            for m in range(nh):
                if ids[m] == u:
                    seen = True
                    break
            if not seen:
                if nh >= h.shape[0]:
                    return -1
                dx, dy, dz = edge_to3(mesh, t, iv, j, period)
                ids[nh] = u
                h[nh, 0] = dx
                h[nh, 1] = dy
                h[nh, 2] = dz
                nh += 1
            nb = mesh.neighbours[t, j]  # across the face opposite u: it holds v
            seen = False
            for m in range(n):
                if stack[m] == nb:
                    seen = True
                    break
            if not seen:
                if n >= stack.shape[0]:
                    return -1
                stack[n] = nb
                n += 1
    return nh
