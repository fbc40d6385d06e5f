"""Stitching tiles' triangulations into one, in space: ``stitch.py``'s kernels one dimension
up (``scale/shared.py`` runs them in both).

The argument is the plane's: a tile's mesh holds every vertex of the run inside its exact
area (a slab of the 3-torus, or the frame around the data's box), so a tetrahedron of the
tile whose closed circumball lies inside that area is a tetrahedron of the run's Delaunay
triangulation. The torus is cut into cores (half-open slabs of the data's box, and the
frame); a tetrahedron belongs to the core holding its corner of lowest global id, and the
tile of that core hands it in after checking that its ball lies in its exact area.
``scale/shared.py`` joins the shares by their faces and checks the join (every face has
one twin, the volumes add up to the torus').

Kernels: ``owned_tetrahedra`` (a tile's share and whether it vouches for it), ``hand_in3``
(writing it into the run's arrays) and ``largest_near3`` (the mesh's size near a cut or the
data's box).
"""

import numpy as np

from .geometry import circumsphere
from .jit import kernel
from .refine import interval_within
from .refine3 import P3_GRID
from .state import FLOOR, GOOD, UNTESTED
from .stitch import core_of, share_rows, wrapped
from .triangulation3 import load_corners


@kernel(inline="always")
def point_in_box3(p, box, prm):
    """The point p in the box ``box`` (corner (3), widths (3)) of the torus (closed)."""
    for a in range(3):
        if not interval_within(p[a], 0.0, box[a], box[3 + a], prm[a]):
            return False
    return True


@kernel(inline="always")
def ball_meets_box3(c, r, box, prm):
    """The ball (c, r) meets the box ``box`` of the torus, which does not wrap."""
    best = 0.0
    for a in range(3):
        x = wrapped(c[a], prm[a])
        gap = np.inf
        for s in (-1.0, 0.0, 1.0):
            y = x + s * prm[a]
            gap = min(gap, max(box[a] - y, 0.0, y - (box[a] + box[3 + a])))
        best += gap * gap  # the axes' shifts are independent: the nearest copy per axis
    return best <= r * r


@kernel(inline="always")
def _in_core3(p, bounds, axis, core, data, prm):
    """p in core number ``core`` of ``bounds`` along ``axis`` inside the data's box, or, for
    core = -1 (the frame's tile), outside that box."""
    inside = point_in_box3(p, data, prm)
    if core < 0:
        return not inside
    return inside and core_of(p[axis], bounds, prm[axis]) == core


@kernel(inline="always")
def _vouched3(c, r, exact, prm):
    """The ball (c, r), inflated by a relative 1e-6 and a grid step, lies in the exact area
    ``exact`` (corner (3), widths (3), inside): the box when inside > 0, everything outside
    it when inside = 0, the whole torus when inside < 0 (``stitch._vouched``)."""
    if exact[6] < 0.0:
        return True
    r = r * (1.0 + 1e-6) + prm[P3_GRID]
    if exact[6] > 0.0:
        for a in range(3):
            if not interval_within(c[a] - r, 2.0 * r, exact[a], exact[3 + a], prm[a]):
                return False
        return True
    return not ball_meets_box3(c, r, exact, prm)


@kernel(inline="always")
def _volume6(p):
    """det[a - d, b - d, c - d] of the rows a, b, c, d of p: six times the signed volume,
    positive for ``predicates3.orient3d``'s positive orientation."""
    ax, ay, az = p[0, 0] - p[3, 0], p[0, 1] - p[3, 1], p[0, 2] - p[3, 2]
    bx, by, bz = p[1, 0] - p[3, 0], p[1, 1] - p[3, 1], p[1, 2] - p[3, 2]
    cx, cy, cz = p[2, 0] - p[3, 0], p[2, 1] - p[3, 1], p[2, 2] - p[3, 2]
    return ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)


@kernel(inline="always")
def _lowest3(mesh, t, gid):
    o = mesh.corners[t, 0]
    for i in range(1, 4):
        v = mesh.corners[t, i]
        if gid[v] < gid[o]:
            o = v
    return o


@kernel(entry=True, nogil=True)
def owned_tetrahedra(mesh, nt, gid, bounds, axis, core, data, exact, prm, out):
    """out[t] = True for this tile's share of the tetrahedra t < nt: those whose corner of
    lowest global id lies in its core (``stitch.owned_triangles`` in the plane). Returns
    (how many of them have a circumball outside the tile's exact area, the largest radius
    among those): (0, 0) when it vouches for all of its share."""
    pts = np.empty((5, 3))
    c = np.empty(3)
    bad = 0
    largest = 0.0
    for t in range(nt):
        mine = _in_core3(mesh.xyz[_lowest3(mesh, t, gid)], bounds, axis, core, data, prm)
        out[t] = mine
        if not mine or exact[6] < 0.0:  # the whole torus (the reach rule): no ball to check
            continue
        load_corners(mesh, t, 0, 0, 0, prm, pts)
        c[0], c[1], c[2], r2 = circumsphere(pts)
        if not _vouched3(c, np.sqrt(r2), exact, prm):
            bad += 1
            largest = max(largest, np.sqrt(r2))
    return bad, largest


@kernel(entry=True, nogil=True)
def hand_in3(mesh, book, nt, nv, gid, mine, base, prm, out):
    """Write this tile's share (``mine``, from ``owned_tetrahedra``) into the run's arrays
    ``out`` (corners, offsets packed as ``triangulation3.offset3`` reads them, neighbours,
    balls, radius2, cells) from row ``base`` on, in the tile's order: corners as global
    ids, neighbours as rows of the share (-1 across a face to another tile's share), the
    circumball states worth keeping (GOOD, FLOOR; others UNTESTED), the squared
    circumradii. Marks in ``cells`` the vertices whose cell this tile found to hold < k
    points (a cell only shrinks as vertices come). Returns (rows written, their signed
    volume: positively oriented, the shares' add up to the torus')."""
    corners, offsets, neighbours, balls, radius2, cells = out
    row, r = share_rows(mine, nt, base)
    pts = np.empty((5, 3))
    volume = 0.0
    for t in range(nt):
        g = row[t]
        if g < 0:
            continue
        for i in range(4):
            corners[g, i] = gid[mesh.corners[t, i]]
            neighbours[g, i] = row[mesh.neighbours[t, i]]
        offsets[g] = mesh.offsets[t]
        state = book.ball_state[t]
        balls[g] = state if state == GOOD or state == FLOOR else UNTESTED
        radius2[g] = mesh.radius2[t]
        load_corners(mesh, t, 0, 0, 0, prm, pts)
        volume += _volume6(pts) / 6.0
    for v in range(nv):
        if book.cell_state[v] == GOOD:
            cells[gid[v]] = True
    return r - base, volume


@kernel(entry=True, nogil=True)
def largest_near3(mesh, book, nt, slabs, data, prm, out):
    """out[s] = max(out[s], the largest circumradius of the settled (GOOD) tetrahedra with
    their circumcentre in the data's box ``data`` (corner (3), widths (3)) and their
    circumball meeting slab s = (axis, lo, width) of the torus (``stitch.largest_near``)."""
    pts = np.empty((5, 3))
    c = np.empty(3)
    for t in range(nt):
        if book.ball_state[t] != GOOD:
            continue
        load_corners(mesh, t, 0, 0, 0, prm, pts)
        c[0], c[1], c[2], r2 = circumsphere(pts)
        if not point_in_box3(c, data, prm):
            continue
        r = np.sqrt(r2)
        for s in range(slabs.shape[0]):
            axis = int(slabs[s, 0])
            period = prm[axis]
            d = np.fmod(c[axis] - slabs[s, 1], period)
            if d < 0.0:
                d += period
            if (d <= slabs[s, 2] + r or d >= period - r) and r > out[s]:
                out[s] = r


@kernel(inline="always")
def _swap_if(ga, ca, gb, cb):
    if gb < ga:
        return gb, cb, ga, ca
    return ga, ca, gb, cb


@kernel(inline="always")
def _tet_key(mesh, t, gid):
    """Tetrahedron t as three words that are the same in every tile's mesh: its corners'
    global ids in increasing order (two to a word) and its packed offsets
    (``triangulation3.offset3``: normalised per axis, so the same in every frame) in that
    corner order."""
    g0, c0 = gid[mesh.corners[t, 0]], 0
    g1, c1 = gid[mesh.corners[t, 1]], 1
    g2, c2 = gid[mesh.corners[t, 2]], 2
    g3, c3 = gid[mesh.corners[t, 3]], 3
    g0, c0, g1, c1 = _swap_if(g0, c0, g1, c1)  # a sorting network of four
    g2, c2, g3, c3 = _swap_if(g2, c2, g3, c3)
    g0, c0, g2, c2 = _swap_if(g0, c0, g2, c2)
    g1, c1, g3, c3 = _swap_if(g1, c1, g3, c3)
    g1, c1, g2, c2 = _swap_if(g1, c1, g2, c2)
    o = np.int64(mesh.offsets[t])
    packed = ((o >> (6 * c0)) & 63) | (((o >> (6 * c1)) & 63) << 6)
    packed |= (((o >> (6 * c2)) & 63) << 12) | (((o >> (6 * c3)) & 63) << 18)
    return np.int64(g0) | (np.int64(g1) << 32), np.int64(g2) | (np.int64(g3) << 32), packed


@kernel(inline="always")
def _slot(a, b, c, mask):
    h = (a * np.int64(-7046029254386353131)) ^ (b * np.int64(-4658895280553007687)) ^ c
    return (h ^ (h >> 29)) & mask


@kernel(entry=True, nogil=True)
def settled_table3(mesh, book, nt, gid, prm, boxes):
    """The tetrahedra this tile settled (GOOD) whose circumcentre lies in one of ``boxes``
    (rows: corner, widths) as an open-addressing table of their keys (``_tet_key``; rows
    (a, b, offsets), a = -1 empty), for another tile to look up (``take_settled3``): a
    circumball's count depends on the tetrahedron only."""
    pts = np.empty((5, 3))
    c = np.empty(3)
    found = np.zeros(nt, np.bool_)
    count = 0
    for t in range(nt):
        if book.ball_state[t] != GOOD:
            continue
        load_corners(mesh, t, 0, 0, 0, prm, pts)
        c[0], c[1], c[2], _ = circumsphere(pts)
        for b in range(boxes.shape[0]):
            if point_in_box3(c, boxes[b], prm):
                found[t] = True
                count += 1
                break
    size = 64
    while size < 2 * count:
        size *= 2
    table = np.full((size, 3), -1, np.int64)
    mask = size - 1
    for t in range(nt):
        if not found[t]:
            continue
        a, b, o = _tet_key(mesh, t, gid)
        h = _slot(a, b, o, mask)
        while table[h, 0] != -1 and not (table[h, 0] == a and table[h, 1] == b
                                         and table[h, 2] == o):  # fmt: skip
            h = (h + 1) & mask
        table[h, 0], table[h, 1], table[h, 2] = a, b, o
    return table


@kernel(entry=True, nogil=True)
def take_settled3(mesh, book, nt, gid, table):
    """Mark GOOD the untested tetrahedra of this tile found in another tile's
    ``settled_table3``; returns how many."""
    mask = table.shape[0] - 1
    taken = 0
    for t in range(nt):
        if book.ball_state[t] != UNTESTED:
            continue
        a, b, o = _tet_key(mesh, t, gid)
        h = _slot(a, b, o, mask)
        while table[h, 0] != -1:
            if table[h, 0] == a and table[h, 1] == b and table[h, 2] == o:
                book.ball_state[t] = GOOD
                taken += 1
                break
            h = (h + 1) & mask
    return taken
