"""Partitioned refinement in space: the plane's rule (``_engine/region.py``) one dimension up.

A tile with region R (a box of the 3-torus) moves only for an element inside R: a
tetrahedron whose closed circumball is in R, or a vertex v whose ball of radius 2 R(v) is in R
(it holds Vor(v), its far corner and every vertex that can be v's Delaunay neighbour: a
neighbour u shares a Voronoi face with v, whose vertices are within R(v) of both, so
|u - v| <= 2 R(v)). The argument of the plane carries unchanged: such an element is the same
in the tile's mesh as in the global one, its counts need only the points in R, and the vertex
it inserts is the centre of a ball inside R empty of every vertex, so the tiles' insertions,
taken tile after tile, are a valid sequence of kNNRefine moves. The check itself is
``refine3.in_region3``.

Kernels here: ``locate3`` (a visibility walk to the tetrahedron holding a point),
``insert_points3`` (a triangulation of given vertices by walking to each), ``mark_settled3``
(what earlier rounds settled), ``spatial_order3`` (a Z-order of points) and ``in_box3`` (the
points in a padded region).
"""

import numpy as np

from .jit import kernel
from .predicates3 import orient3d
from .refine import interval_within
from .refine3 import HEADROOM3, P3_FLOOR2, ball_in_box3
from .state import C_LAST_NB, C_NT, C_NV, GOOD, INSERT_NOT_IN_SEED
from .triangulation3 import (
    corner_of3,
    insert_vertex3,
    load_corners,
    offset3,
    outradius2_at3,
    vertex_neighbours3,
)

WALK_LIMIT3 = 1 << 22  # steps of one walk: far beyond any mesh's, a broken mesh's guard
WALK_LOST3 = -10  # insert_points3's code when a walk ran past WALK_LIMIT3


@kernel(inline="always")
def locate3(p, t, mesh, period, pts, shift):
    """Walk from tetrahedron t to one whose closed hull holds p, on the torus; returns the
    tetrahedron (-1 if lost) with ``shift`` (3,) set to its frame's shift in periods
    relative to p's. A face is crossed when p lies strictly beyond it (orient3d with p in
    place of the opposite corner < 0); the faces are tried from a turning start, so that the
    walk cannot cycle on a degenerate configuration."""
    shift[0] = 0
    shift[1] = 0
    shift[2] = 0
    for step in range(WALK_LIMIT3):
        moved = False
        load_corners(mesh, t, shift[0], shift[1], shift[2], period, pts)
        for e in range(4):
            i = (e + step) % 4
            keep0 = pts[i, 0]
            keep1 = pts[i, 1]
            keep2 = pts[i, 2]
            pts[i, 0] = p[0]
            pts[i, 1] = p[1]
            pts[i, 2] = p[2]
            beyond = orient3d(pts[:4]) < 0
            pts[i, 0] = keep0
            pts[i, 1] = keep1
            pts[i, 2] = keep2
            if beyond:
                n = mesh.neighbours[t, i]
                a = (i + 1) % 4  # a corner of the shared face
                j = corner_of3(mesh, n, mesh.corners[t, a])
                for ax in range(3):
                    shift[ax] += offset3(mesh.offsets, t, a, ax) - offset3(mesh.offsets, n, j, ax)
                t = n
                moved = True
                break
        if not moved:
            return t
    return -1


@kernel(entry=True, nrt=False, nogil=True)
def insert_points3(xyz, ids, start, mesh, book, scratch, cnt, period):
    """Insert the points xyz[start:] (on the grid, in [0, period), best in a space-filling
    order) into the Delaunay triangulation, each from where the last one went; ids[p] is
    set to point p's vertex (-1 for a point that is a vertex already: skipped). Returns the
    index of the first point not inserted when the arrays need to grow (call again from
    there), xyz.shape[0] when all are in, or a negative error code. New tetrahedra and
    vertices are marked untested."""
    t = 0
    if cnt[C_NV] > 0:
        t = mesh.star[cnt[C_NV] - 1]
    pts = scratch.points
    shift = scratch.shift
    q = scratch.walk_point
    for p in range(start, xyz.shape[0]):
        if cnt[C_NV] + 1 > mesh.xyz.shape[0] or cnt[C_NT] + HEADROOM3 > mesh.corners.shape[0]:
            return p
        t = locate3(xyz[p], t, mesh, period, pts, shift)
        if t < 0:
            return WALK_LOST3
        for a in range(3):
            q[a] = xyz[p, a] - shift[a] * period[a]
        v = insert_vertex3(q, t, mesh, scratch, cnt, period)
        if v == INSERT_NOT_IN_SEED:  # on a vertex already (its closed circumball's boundary)
            ids[p] = -1
            continue
        if v < 0:
            return v
        ids[p] = v
        book.kinds[v] = 0
        book.cell_state[v] = 0
        book.flags[v] = 0
        for e in range(scratch.moved[0, 0]):  # tetrahedra moved down keep their state
            book.ball_state[scratch.moved[1 + e, 1]] = book.ball_state[scratch.moved[1 + e, 0]]
        for e in range(cnt[C_LAST_NB]):
            book.ball_state[scratch.cavity[e]] = 0
        t = mesh.star[v]
    return xyz.shape[0]


@kernel(inline="always")
def _settled_by3(c, r, newest, rounds, regions, prm):
    """The ball (c, r) lay inside a region of a round q >= newest: regions (Q, T, 6) holds
    each round's regions (corner, widths), rows with widths[0] <= 0 unused."""
    for q in range(max(newest, 1), rounds + 1):
        for j in range(regions.shape[1]):
            g = regions[q - 1, j]
            if g[3] > 0.0 and ball_in_box3(c, r, g[:3], g[3:], prm):
                return True
    return False


@kernel(entry=True, nogil=True)
def mark_settled3(mesh, book, scratch, cnt, prm, stamps, regions):
    """Mark GOOD the circumballs and cells that a finished round settled (``region.py``'s
    rule): stamps[v] is the round that inserted vertex v (0: before any), regions the
    rounds' regions. Elements below the Break floor are left to be looked at again. Returns
    (balls, cells) marked, or (-1, -1) when a vertex has more neighbours than the scratch
    holds."""
    rounds = regions.shape[0]
    period = prm[:3]
    pts = np.empty((5, 3))
    c = np.empty(3)
    balls = 0
    for t in range(cnt[C_NT]):
        newest = 0
        for i in range(4):
            newest = max(newest, stamps[mesh.corners[t, i]])
        r2 = mesh.radius2[t]
        if r2 < prm[P3_FLOOR2]:
            continue
        load_corners(mesh, t, 0, 0, 0, period, pts)
        _circumcentre3(pts, c)
        if _settled_by3(c, np.sqrt(r2), newest, rounds, regions, prm):
            book.ball_state[t] = GOOD
            balls += 1
    h = np.empty((1024, 3))
    ids = np.empty(1024, np.int64)
    cells = 0
    for v in range(cnt[C_NV]):
        outradius2 = outradius2_at3(v, mesh, scratch, cnt)
        if outradius2 < prm[P3_FLOOR2]:
            continue
        nh = vertex_neighbours3(v, mesh, scratch, cnt, period, h, ids)
        if nh < 0:
            return -1, -1
        newest = stamps[v]
        for j in range(nh):
            newest = max(newest, stamps[ids[j]])
        if _settled_by3(mesh.xyz[v], 2.0 * np.sqrt(outradius2), newest, rounds,
                        regions, prm):  # fmt: skip
            book.cell_state[v] = GOOD
            cells += 1
    return balls, cells


@kernel(inline="always")
def _circumcentre3(pts, out):
    """out = the circumcentre of the tetrahedron pts[:4] (Cramer's rule, relative to its
    first corner)."""
    ax = pts[1, 0] - pts[0, 0]
    ay = pts[1, 1] - pts[0, 1]
    az = pts[1, 2] - pts[0, 2]
    bx = pts[2, 0] - pts[0, 0]
    by = pts[2, 1] - pts[0, 1]
    bz = pts[2, 2] - pts[0, 2]
    cx = pts[3, 0] - pts[0, 0]
    cy = pts[3, 1] - pts[0, 1]
    cz = pts[3, 2] - pts[0, 2]
    a2 = 0.5 * (ax * ax + ay * ay + az * az)
    b2 = 0.5 * (bx * bx + by * by + bz * bz)
    c2 = 0.5 * (cx * cx + cy * cy + cz * cz)
    det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    ux = a2 * (by * cz - bz * cy) - ay * (b2 * cz - bz * c2) + az * (b2 * cy - by * c2)
    uy = ax * (b2 * cz - bz * c2) - a2 * (bx * cz - bz * cx) + az * (bx * c2 - b2 * cx)
    uz = ax * (by * c2 - b2 * cy) - ay * (bx * c2 - b2 * cx) + a2 * (bx * cy - by * cx)
    out[0] = pts[0, 0] + ux / det
    out[1] = pts[0, 1] + uy / det
    out[2] = pts[0, 2] + uz / det


@kernel(inline="always")
def _spread3(x):
    """The low 21 bits of x spread to every third bit position."""
    x &= 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    return (x | (x << 2)) & 0x1249249249249249


@kernel(entry=True)
def spatial_order3(xyz, period):
    """An order of the points along a space-filling (Morton) curve: walks stay short."""
    keys = np.empty(xyz.shape[0], np.int64)
    for i in range(xyz.shape[0]):
        key = 0
        for a in range(3):
            u = min(max(int(xyz[i, a] / period[a] * 2097152.0), 0), 2097151)
            key |= _spread3(u) << a
        keys[i] = key
    return np.argsort(keys)


@kernel(entry=True)
def in_box3(xyz, region, pad, period):
    """Mask of the points (torus coordinates) in the region (corner (3,), widths (3,): a row
    of 6) widened by ``pad`` on every side (wrapping; a width >= the period: the whole
    axis)."""
    out = np.zeros(xyz.shape[0], np.bool_)
    for i in range(xyz.shape[0]):
        inside = True
        for a in range(3):
            if not interval_within(xyz[i, a], 0.0, region[a] - pad, region[3 + a] + 2 * pad,
                                   period[a]):  # fmt: skip
                inside = False
                break
        out[i] = inside
    return out
