"""Partitioned refinement: tiles that refine at once, and why their union is a kNNRefine run.

The paper's guarantees do not depend on the order of the moves: any sequence of Break and
Clean moves, each made on an element of the current Delaunay mesh that needs it, ending when
no element does, meets them. Tiles make moves in parallel under one rule: a tile with region
R (a rectangle of the torus) moves only for an element that lies inside R: a triangle whose
closed circumdisk is in R, or a vertex v whose disk of radius 2 R(v) is in R (it holds v's
Voronoi cell, its far corner, and every vertex that can be v's neighbour). Such an element is
the same in the tile's mesh (the global vertices in R, plus the tile's own) as in the global
one, its counts need only the points in R, and the vertex it inserts is at the centre of a
disk, inside R, empty of every vertex: of the tile's, and of the other tiles' (outside R). So
the tiles' insertions, taken tile after tile, are a valid sequence of moves.

Elements that cross a region's border wait. Rounds alternate two sets of strips whose borders
interleave (``plan``), so that what crosses a border of one lies inside a strip of the other.
A round's tile skips what is settled already: a triangle (or a cell) whose disk lay inside a
strip of an earlier round q, when none of its vertices (or of v's neighbours) is newer than
q, is exactly an element that strip's tile had at its end, and a tile ends only when every
element inside its region is settled. A final pass on the whole torus (``Refinement`` with
the full index) decides what no round did, with everything else frozen.

Kernels here: ``insert_points`` (a triangulation of given vertices, by walking to each),
``mark_settled`` (the rule above), ``tile_vertices`` (a tile's share of the vertices).
"""

import numpy as np

from .geometry import morton_key
from .jit import kernel
from .predicates import orient2d
from .refine import (
    disk_in_rectangle,
    interval_within,
)
from .state import (
    C_LAST_NB,
    C_NT,
    C_NV,
    GOOD,
    INSERT_NOT_IN_SEED,
    P_FLOOR2,
    P_LX,
    P_LY,
)
from .triangulation import circumcentre, corner, corner_of, insert_vertex

WALK_LIMIT = 1 << 22  # steps of one walk: far beyond any mesh's, a broken mesh's guard
WALK_LOST = -10  # insert_points' code when a walk ran past WALK_LIMIT


@kernel(inline="always")
def locate(px, py, t, mesh, lx, ly):
    """Walk from triangle t to one that holds p (closed), on the torus: (triangle, sx, sy),
    the triangle's frame shifted by (sx, sy) periods relative to p's; (-1, 0, 0) if lost."""
    sx = 0
    sy = 0
    for step in range(WALK_LIMIT):
        moved = False
        for e in range(3):
            i = (e + step) % 3  # the edge opposite corner i, started at a turning corner
            a = (i + 1) % 3
            b = (i + 2) % 3
            ax, ay = corner(mesh, t, a, sx, sy, lx, ly)
            bx, by = corner(mesh, t, b, sx, sy, lx, ly)
            if orient2d(ax, ay, bx, by, px, py) < 0:
                n = mesh.neighbours[t, i]
                va = mesh.corners[t, a]
                j = corner_of(mesh, n, va)
                sx += mesh.offsets[t, a, 0] - mesh.offsets[n, j, 0]
                sy += mesh.offsets[t, a, 1] - mesh.offsets[n, j, 1]
                t = n
                moved = True
                break
        if not moved:
            return t, sx, sy
    return -1, 0, 0


@kernel(entry=True, nrt=False, nogil=True)
def insert_points(xy, ids, start, mesh, book, scratch, cnt, prm):
    """Insert the points xy[start:] (on the grid, in [0, lx) x [0, ly), best in a
    space-filling order) into the Delaunay triangulation, each from where the last one went;
    ids[p] is set to point p's vertex (-1 for a point that is a vertex already: skipped).
    Returns the index of the first point not inserted when the arrays need to grow (call
    again from there), xy.shape[0] when all are in, or a negative error code. New triangles
    and vertices are marked untested."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    t = 0
    if cnt[C_NV] > 0:
        t = mesh.star[cnt[C_NV] - 1]
    for p in range(start, xy.shape[0]):
        if cnt[C_NV] + 1 > mesh.xy.shape[0] or cnt[C_NT] + 2 > mesh.corners.shape[0]:
            return p
        px = xy[p, 0]
        py = xy[p, 1]
        t, sx, sy = locate(px, py, t, mesh, lx, ly)
        if t < 0:
            return WALK_LOST
        v = insert_vertex(px - sx * lx, py - sy * ly, t, mesh, scratch, cnt, prm)
        if v == INSERT_NOT_IN_SEED:  # on a vertex already (the walk stops on its corner)
            ids[p] = -1
            continue
        if v < 0:
            return v
        ids[p] = v
        book.kinds[v] = 0
        book.cell_state[v] = 0
        book.flags[v] = 0
        for e in range(cnt[C_LAST_NB]):
            book.ball_state[scratch.cavity[e]] = 0
        t = mesh.star[v]
    return xy.shape[0]


@kernel(inline="always")
def _settled_by(cx, cy, r, newest, rounds, regions, prm):
    """The disk (cx, cy, r) lay inside a region of a round q >= newest: regions (Q, T, 4)
    holds each round's regions (x0, y0, w, h), rows with w <= 0 unused; rounds = Q."""
    for q in range(max(newest, 1), rounds + 1):
        for j in range(regions.shape[1]):
            g = regions[q - 1, j]
            if g[2] > 0.0 and disk_in_rectangle(cx, cy, r, g[0], g[1], g[2], g[3], prm):
                return True
    return False


@kernel(entry=True, nrt=False, nogil=True)
def mark_settled(mesh, book, cnt, prm, stamps, regions):
    """Mark GOOD the circumballs and cells that a finished round settled (module docstring):
    stamps[v] is the round that inserted vertex v (0: before any), regions the rounds'
    regions. Elements below the Break floor are left to be looked at again (so that the
    run that ends reports them). Returns (balls, cells) marked."""
    rounds = regions.shape[0]
    nt = cnt[C_NT]
    nv = cnt[C_NV]
    balls = 0
    for t in range(nt):
        newest = max(
            stamps[mesh.corners[t, 0]], stamps[mesh.corners[t, 1]], stamps[mesh.corners[t, 2]]
        )
        cx, cy, r2 = circumcentre(mesh, prm, t)
        if r2 < prm[P_FLOOR2]:
            continue
        if _settled_by(cx, cy, np.sqrt(r2), newest, rounds, regions, prm):
            book.ball_state[t] = GOOD
            balls += 1
    cells = 0
    for v in range(nv):
        newest = stamps[v]
        t0 = mesh.star[v]
        t = t0
        while True:  # round v: its neighbours' stamps
            i = corner_of(mesh, t, v)
            newest = max(newest, stamps[mesh.corners[t, (i + 1) % 3]])
            t = mesh.neighbours[t, (i + 1) % 3]
            if t == t0:
                break
        if mesh.outradius2[v] < prm[P_FLOOR2]:
            continue
        r = 2.0 * np.sqrt(mesh.outradius2[v])
        if _settled_by(mesh.xy[v, 0], mesh.xy[v, 1], r, newest, rounds, regions, prm):
            book.cell_state[v] = GOOD
            cells += 1
    return balls, cells


@kernel(entry=True)
def spatial_order(xy, lx, ly):
    """An order of the points along a space-filling (Morton) curve: walks stay short."""
    keys = np.empty(xy.shape[0], np.int64)
    for i in range(xy.shape[0]):
        keys[i] = morton_key(xy[i, 0] / lx, xy[i, 1] / ly)
    return np.argsort(keys)


@kernel(entry=True)
def in_rectangle(xy, x0, y0, w, h, pad, lx, ly):
    """Mask of the points (torus coordinates) in the region [x0 - pad, x0 + w + pad] x
    [y0 - pad, y0 + h + pad] (wrapping; w >= lx or h >= ly: the whole axis)."""
    out = np.zeros(xy.shape[0], np.bool_)
    for i in range(xy.shape[0]):
        out[i] = interval_within(xy[i, 0], 0.0, x0 - pad, w + 2 * pad, lx) and interval_within(
            xy[i, 1], 0.0, y0 - pad, h + 2 * pad, ly
        )
    return out
