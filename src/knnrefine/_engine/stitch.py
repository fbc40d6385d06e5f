"""Stitching tiles' triangulations into one, in the plane (``scale/shared.py`` runs them).

Tiles of a run in threads keep their meshes. Each tile's mesh holds every vertex of the run
inside its *exact area* (a strip of the torus, or the frame around the data's box):
there, a triangle of the tile whose closed circumdisk lies inside the area is a triangle of
the run's Delaunay triangulation (its disk is empty of the tile's vertices, so of all), and
conversely. The torus is cut into *cores*: half-open strips of the data's box, each
inside one tile's exact area, and the frame around the box (where a non-periodic axis'
margin holds no data). A triangle belongs to the core holding its corner of lowest global id
(a vertex's stored position, the same double in every tile, so every tile decides alike).
Each tile hands in the triangles of its core, having checked that their disks lie in its
exact area; ``scale/shared.py`` joins them by their edges and checks the join (every edge
has one twin; 2 m triangles on the torus).

Kernels: ``owned_triangles`` (a tile's share, and whether it can vouch for it), ``hand_in``
(writing it into the run's arrays), ``largest_near`` (the mesh's size near a cut or the
data's box, which sizes the seams and the frame's band).
"""

import numpy as np

from .jit import kernel
from .refine import interval_within
from .state import FLOOR, GOOD, P_GRID, P_LX, P_LY, UNTESTED
from .triangulation import circumcentre


@kernel(inline="always")
def core_of(x, bounds, period):
    """The core [bounds[c], bounds[c + 1]) holding x in [0, period) (the last core runs on
    across the period to bounds[0])."""
    c = np.searchsorted(bounds, x, side="right") - 1
    return c % bounds.shape[0]


@kernel(inline="always")
def wrapped(x, period):
    """x reduced to [0, period)."""
    x = x - np.floor(x / period) * period
    return x - period if x >= period else x


@kernel(inline="always")
def in_box(x, y, box, prm):
    """(x, y) in the rectangle box = (x0, y0, w, h) of the torus (closed)."""
    return interval_within(x, 0.0, box[0], box[2], prm[P_LX]) and interval_within(
        y, 0.0, box[1], box[3], prm[P_LY]
    )


@kernel(inline="always")
def disk_meets_box(cx, cy, r, box, prm):
    """The disk (cx, cy, r) meets the rectangle box = (x0, y0, w, h) of the torus, which
    does not wrap (0 <= x0, x0 + w <= lx, and so along y)."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    x = wrapped(cx, lx)
    y = wrapped(cy, ly)
    best = np.inf
    for sx in (-1.0, 0.0, 1.0):
        dx = max(box[0] - (x + sx * lx), 0.0, (x + sx * lx) - (box[0] + box[2]))
        for sy in (-1.0, 0.0, 1.0):
            dy = max(box[1] - (y + sy * ly), 0.0, (y + sy * ly) - (box[1] + box[3]))
            best = min(best, dx * dx + dy * dy)
    return best <= r * r


@kernel(inline="always")
def _in_core(x, y, bounds, axis, core, data, prm):
    """(x, y) in the core number ``core`` of ``bounds`` along ``axis`` inside the data's box
    ``data``, or, for core = -1 (the frame's tile), outside that box."""
    inside = in_box(x, y, data, prm)
    if core < 0:
        return not inside
    return inside and core_of(x if axis == 0 else y, bounds, prm[P_LX + axis]) == core


@kernel(inline="always")
def _vouched(cx, cy, r, exact, prm):
    """The disk (cx, cy, r), inflated by a relative 1e-6 and a grid step, lies in the exact
    area ``exact`` (x0, y0, w, h, inside): the rectangle when inside > 0, everything
    outside it when inside = 0, the whole torus when inside < 0 (a tile that holds every
    vertex whose star reaches its region: ``scale/shared.py``'s reach rule)."""
    if exact[4] < 0.0:
        return True
    r = r * (1.0 + 1e-6) + prm[P_GRID]
    if exact[4] > 0.0:
        return interval_within(cx - r, 2.0 * r, exact[0], exact[2], prm[P_LX]) and (
            interval_within(cy - r, 2.0 * r, exact[1], exact[3], prm[P_LY])
        )
    return not disk_meets_box(cx, cy, r, exact, prm)


@kernel(inline="always")
def share_rows(mine, nt, base):
    """The run's row of each simplex t < nt of a tile's share (``mine``; -1 elsewhere), the
    share's rows running from ``base`` in the tile's order, and the row after the last."""
    row = np.full(nt, -1, np.int64)
    r = base
    for t in range(nt):
        if mine[t]:
            row[t] = r
            r += 1
    return row, r


@kernel(entry=True, nogil=True)
def owned_triangles(mesh, nt, gid, bounds, axis, core, data, exact, prm, out):
    """out[t] = True for this tile's share of the triangles t < nt: those whose corner of
    lowest global id (``gid``: a vertex's global id) lies in its core (``_in_core``: core
    number ``core`` of ``bounds`` along ``axis`` in the data's box ``data``, or the frame).
    Returns (how many of them have a circumdisk outside the tile's exact area ``exact``
    (``_vouched``), the largest radius among those): (0, 0) when the tile vouches for all of
    its share."""
    bad = 0
    largest = 0.0
    for t in range(nt):
        o = mesh.corners[t, 0]
        for i in range(1, 3):
            v = mesh.corners[t, i]
            if gid[v] < gid[o]:
                o = v
        mine = _in_core(mesh.xy[o, 0], mesh.xy[o, 1], bounds, axis, core, data, prm)
        out[t] = mine
        if not mine or exact[4] < 0.0:  # the whole torus (the reach rule): no disk to check
            continue
        cx, cy, r2 = circumcentre(mesh, prm, t)
        if not _vouched(cx, cy, np.sqrt(r2), exact, prm):
            bad += 1
            largest = max(largest, np.sqrt(r2))
    return bad, largest


@kernel(entry=True, nogil=True)
def hand_in(mesh, book, nt, nv, gid, mine, base, bounds, axis, core, data, exact, prm, out,
            caches):  # fmt: skip
    """Write this tile's share (``mine``, from ``owned_triangles``, with the same core and
    exact area) into the run's arrays ``out`` (corners, offsets, neighbours, balls, radius2,
    cells) from row ``base`` on, in the tile's order: corners as global ids, offsets,
    neighbours (the rows of the share's own triangles; -1 across an edge to another tile's
    share), the circumball states worth keeping (GOOD and FLOOR; others UNTESTED) and the
    squared circumradii. Marks in ``cells`` the vertices whose cell this tile found to hold
    < k points (GOOD: a cell only shrinks as vertices come, so it stays so). ``caches``
    (nearest2, known): each vertex of the core whose disk of radius 2 R(v) (its star) lies
    in the exact area gets its d_{M,2}(v)^2 (an edge's length, the same in every frame),
    and is marked known. Returns the number of rows written."""
    corners, offsets, neighbours, balls, radius2, cells = out
    nearest2, known = caches
    row, r = share_rows(mine, nt, base)
    for t in range(nt):
        g = row[t]
        if g < 0:
            continue
        for i in range(3):
            corners[g, i] = gid[mesh.corners[t, i]]
            offsets[g, i, 0] = mesh.offsets[t, i, 0]
            offsets[g, i, 1] = mesh.offsets[t, i, 1]
            neighbours[g, i] = row[mesh.neighbours[t, i]]
        state = book.ball_state[t]
        balls[g] = state if state == GOOD or state == FLOOR else UNTESTED
        radius2[g] = mesh.radius2[t]
    for v in range(nv):
        if book.cell_state[v] == GOOD:
            cells[gid[v]] = True
        x, y = mesh.xy[v, 0], mesh.xy[v, 1]
        if not _in_core(x, y, bounds, axis, core, data, prm):
            continue
        if _vouched(x, y, 2.0 * np.sqrt(mesh.outradius2[v]), exact, prm):
            nearest2[gid[v]] = mesh.nearest2[v]
            known[gid[v]] = True
    return r - base


@kernel(entry=True, nogil=True)
def largest_near(mesh, book, nt, slabs, data, prm, out):
    """out[s] = max(out[s], the largest circumradius of the settled (GOOD) triangles with
    their circumcentre in the data's box ``data`` (x0, y0, w, h) and their circumdisk
    meeting slab s = (axis, lo, width): [lo, lo + width] across that axis of the torus): the
    mesh's size there, from elements a tile decided (not the margins' large ones)."""
    for t in range(nt):
        if book.ball_state[t] != GOOD:
            continue
        cx, cy, r2 = circumcentre(mesh, prm, t)
        if not in_box(cx, cy, data, prm):
            continue
        r = np.sqrt(r2)
        for s in range(slabs.shape[0]):
            axis = int(slabs[s, 0])
            period = prm[P_LX + axis]
            d = np.fmod((cx if axis == 0 else cy) - slabs[s, 1], period)
            if d < 0.0:
                d += period
            if (d <= slabs[s, 2] + r or d >= period - r) and r > out[s]:
                out[s] = r
