"""kNNRefine (Algorithm 1 of Gardner & Sheehy): the Break and Clean moves, as kernels.

The loop, in the paper's priority:

1. Clean while some vertex v has aspect(Vor(v)) > tau: insert farCorner(Vor(v)).
2. Otherwise Break: if some triangle's closed circumball holds >= k input points, insert its
   circumcenter; otherwise, if some Voronoi cell holds >= k input points, insert its far corner.
3. Stop when neither applies.

Among several bad elements of one kind the largest goes first, up to a factor sqrt(2) in
radius (circumradius for circumballs, outradius R(v) for cells and for Clean): the candidates
wait in three bucket queues by size class (``queue.py``), which pop the most recent entry of
the largest class. That keeps successive insertions close together, in space and in memory.

* circumballs: every triangle is pushed once, when it is created, and tested when popped. A
  triangle never changes, so a tested one is settled for good (stale entries of triangles
  destroyed meanwhile are recognised by their apex, the vertex whose insertion made them,
  and dropped).
* cells: a vertex is pushed when created; a Voronoi cell only shrinks as vertices are added, so
  a cell found to hold < k points is settled for good. R(v) never grows either, so an entry
  whose class is out of date is pushed back in its current class when popped.
* clean: the vertices around each cavity (the only ones whose Voronoi cell changed) and the new
  vertex are re-examined after each insertion; those with aspect > tau are pushed.

Cells in bulk: a cell's state is a pure function of the mesh, and a cell found to hold < k
points stays so. So when the circumball queue runs empty with many cells newly queued, the
driver has ``sweep_cells`` count all of them at once, in the order of their vertices along a
space-filling curve (neighbouring cells share the points the counts read, so the sweep runs
from cache), and mark those holding < k as settled. The refinement then pops cells as before,
skipping the settled ones: the insertions, and the mesh, are the same as without the sweep.
The sweep runs in chunks, so progress, Ctrl-C and deadlines are served during it too.

Counting is conservative: closed disks and closed cells are inflated by a relative 1e-9 and the
aspect threshold is lowered by a relative 1e-12, so the output satisfies the strict invariants
when re-checked in floating point by independent code.

Resolution floor: an element whose circumradius (or outradius) is below ``min_size`` is not
split by Break; it is marked FLOOR and reported. Clean has its own floor at the grid's
resolution. The kernel returns after ``max_steps`` insertions or when the arrays need to grow,
so the Python driver can report progress, enforce budgets and react to Ctrl-C.

The kernels take the named structures of ``state.py``: ``mesh`` (the triangulation),
``book`` (this module's marks: ball and cell states, kinds, flags), ``queues``,
``scratch`` (the insertion's) and ``probe`` (a star walk's and a count's scratch).
"""

import numpy as np

from .geometry import morton_key, snap
from .index import count_in_cell, count_in_disk
from .jit import kernel
from .queue import N_CLASSES, Q_USED, queue_clear, queue_pop, queue_push, queue_size, size_class
from .state import (  # the named states, kinds and statuses (re-exported: refine.X)
    BREAK_BALL,
    BREAK_CELL,
    C_CELL_TESTS,
    C_CELLS_QUEUED,
    C_CELLS_SWEPT,
    C_DEFERRED,
    C_DISK_TESTS,
    C_ERROR,
    C_FAILED,
    C_LAST_NB,
    C_MAX_VERTICES,
    C_NT,
    C_NV,
    C_SWEEP_MIN,
    CLEAN,
    CLEAN_BELOW_FLOOR,
    CLEAN_FAILED,
    DEFERRED,
    FAILED,
    FLOOR,
    GOOD,
    IN_CELL_QUEUE,
    IN_CLEAN_QUEUE,
    INSERT_NOT_IN_SEED,
    P_CLEAN_FLOOR2,
    P_FLOOR2,
    P_GRID,
    P_INFLATE,
    P_K,
    P_LX,
    P_LY,
    P_REGION_H,
    P_REGION_W,
    P_REGION_X0,
    P_REGION_Y0,
    P_TAU2,
    STAR_OVERFLOW,
    STATUS_DONE,
    STATUS_ERROR,
    STATUS_GROW,
    STATUS_MAX_VERTICES,
    STATUS_STEPS,
    STATUS_SWEEP,
    UNTESTED,
)
from .triangulation import circumcentre, far_corner, insert_vertex, vertex_star

SWEEP_DUE = -2  # break_'s answer when a sweep should come first

HEADROOM = 1100  # free slots required before an insertion (> MAX_CAVITY + 2)


@kernel(inline="always")
def interval_within(lo, extent, start, width, period):
    """The interval [lo, lo + extent] of a periodic axis lies in [start, start + width]."""
    if width >= period:  # the region spans the axis
        return extent < period
    d = lo - start
    if d < 0.0:  # one period either way covers every caller's frame; fmod (a libm call,
        d += period  # the costlier) only beyond
    elif d >= period:
        d -= period
    if d < 0.0 or d >= period:
        d = np.fmod(lo - start, period)
        if d < 0.0:
            d += period
    return d + extent <= width


@kernel(inline="always")
def disk_in_rectangle(cx, cy, r, x0, y0, w, h, prm):
    """The closed disk (cx, cy, r), inflated by a relative 1e-6 and a grid step (beyond the
    counts' own inflation), lies in the rectangle [x0, x0 + w] x [y0, y0 + h] of the torus."""
    r = r * (1.0 + 1e-6) + prm[P_GRID]
    return interval_within(cx - r, 2.0 * r, x0, w, prm[P_LX]) and interval_within(
        cy - r, 2.0 * r, y0, h, prm[P_LY]
    )


@kernel(inline="always")
def in_region(cx, cy, r, prm):
    """True when the closed disk (cx, cy, r) lies in the tile's region (``_engine/region.py``): a
    tile decides only elements whose every count and every neighbour it knows. Always true
    without a region (a whole run: w = NO_REGION), never for a region of width 0."""
    w = prm[P_REGION_W]
    if w < 0.0:
        return True
    return disk_in_rectangle(cx, cy, r, prm[P_REGION_X0], prm[P_REGION_Y0], w, prm[P_REGION_H], prm)


@kernel(inline="always")
def is_too_aspect(outradius2, d_m2_sq, prm):
    """aspect(Vor(v)) = 2 R(v) / d_{M,2}(v) > tau, from squares (tau^2 lowered by 1e-12)."""
    return 4.0 * outradius2 > prm[P_TAU2] * d_m2_sq


@kernel(nrt=False)
def _touch(v, mesh, book, queues, cnt, prm):
    """Re-examine vertex v after its star changed: queue its cell and, if bad, its Clean.
    Reads the triangulation's caches of R(v)^2 and d_{M,2}(v)^2: no walk round v."""
    outradius2 = mesh.outradius2[v]
    if book.cell_state[v] >= FLOOR:  # FLOOR, FAILED, DEFERRED: its cell changed, look again
        book.cell_state[v] = UNTESTED
    if book.cell_state[v] == UNTESTED and not (book.flags[v] & IN_CELL_QUEUE):
        queue_push(queues.cells, size_class(outradius2), v, 0)
        book.flags[v] = book.flags[v] | IN_CELL_QUEUE
        cnt[C_CELLS_QUEUED] += 1
    book.flags[v] = book.flags[v] & ~(CLEAN_BELOW_FLOOR | CLEAN_FAILED)
    if is_too_aspect(outradius2, mesh.nearest2[v], prm) and not (book.flags[v] & IN_CLEAN_QUEUE):
        queue_push(queues.cleans, size_class(outradius2), v, 0)
        book.flags[v] = book.flags[v] | IN_CLEAN_QUEUE


@kernel(inline="always")
def clean(mesh, book, queues, prm):
    """Choose the next Clean move: the largest cell whose aspect exceeds tau.

    Returns (t, v): insert the circumcenter of triangle t, the far corner of vertex v's cell;
    (-1, -1) when no vertex needs cleaning."""
    while queue_size(queues.cleans) > 0:
        cls, v, _ = queue_pop(queues.cleans)
        book.flags[v] = book.flags[v] & ~IN_CLEAN_QUEUE
        outradius2 = mesh.outradius2[v]
        if not is_too_aspect(outradius2, mesh.nearest2[v], prm):
            continue
        now = size_class(outradius2)
        if now > cls:  # outradius shrank since it was queued: requeue in its true class
            queue_push(queues.cleans, now, v, 0)
            book.flags[v] = book.flags[v] | IN_CLEAN_QUEUE
            continue
        if outradius2 < prm[P_CLEAN_FLOOR2]:
            book.flags[v] = book.flags[v] | CLEAN_BELOW_FLOOR
            continue
        if not in_region(mesh.xy[v, 0], mesh.xy[v, 1], 2.0 * np.sqrt(outradius2), prm):
            continue  # far corner and neighbours not all the tile's: left for later
        return far_corner(v, mesh), v
    return -1, -1


@kernel(nrt=False)
def count_cell(v, mesh, probe, cnt, prm, index):
    """Points of P in the closed Voronoi cell of v (inflated), their weight for weighted P:
    exact below k, else some value >= k; STAR_OVERFLOW if v has more neighbours than the
    probe holds (the only negative value)."""
    k = prm[P_K]
    inflate = prm[P_INFLATE]
    outradius2 = mesh.outradius2[v]
    x = mesh.xy[v, 0]
    y = mesh.xy[v, 1]
    cnt[C_CELL_TESTS] += 1
    # the cell lies in the disk of radius R(v) about v: when that disk holds < k points, so
    # does the cell, and the cheaper disk count settles it
    c = count_in_disk(index, x, y, outradius2 * inflate, k, prm[P_LX], prm[P_LY], probe.stack)
    if c < k:
        return c
    degree = vertex_star(v, mesh, prm, probe.hx, probe.hy)[3]
    if degree < 0:
        return STAR_OVERFLOW
    for j in range(degree):
        hx = probe.hx[j]
        hy = probe.hy[j]
        probe.hc[j] = 0.5 * (hx * hx + hy * hy) * inflate
    return count_in_cell(
        index,
        x,
        y,
        probe.hx,
        probe.hy,
        probe.hc,
        degree,
        outradius2 * inflate,
        k,
        prm[P_LX],
        prm[P_LY],
        probe.stack,
        probe.mask,
    )


@kernel(inline="always")
def break_(mesh, book, queues, probe, cnt, prm, index):
    """Choose the next Break move: the largest circumball holding >= k points, else the largest
    Voronoi cell holding >= k points.

    Returns (t, kind, element): insert the circumcenter of triangle t; element is the triangle
    (BREAK_BALL) or the vertex (BREAK_CELL) being split. (-1, 0, -1) when every circumball and
    cell holds < k points or is at the floor; t < -1 is an error code (state.ERRORS)."""
    k = prm[P_K]
    lx = prm[P_LX]
    ly = prm[P_LY]
    inflate = prm[P_INFLATE]
    radius2 = mesh.radius2
    while queue_size(queues.balls) > 0:
        cls, t, apex = queue_pop(queues.balls)
        if mesh.corners[t, 0] != apex or book.ball_state[t] != UNTESTED:
            continue  # a stale entry: slot t holds another triangle now, or was tested
        cx, cy, _ = circumcentre(mesh, prm, t)
        if not in_region(cx, cy, np.sqrt(radius2[t]), prm):
            book.ball_state[t] = DEFERRED
            cnt[C_DEFERRED] += 1
            continue
        cnt[C_DISK_TESTS] += 1
        if count_in_disk(index, cx, cy, radius2[t] * inflate, k, lx, ly, probe.stack) < k:
            book.ball_state[t] = GOOD
            continue
        if radius2[t] < prm[P_FLOOR2]:
            book.ball_state[t] = FLOOR
            continue
        return t, BREAK_BALL, t
    if cnt[C_CELLS_QUEUED] - cnt[C_CELLS_SWEPT] >= cnt[C_SWEEP_MIN]:
        return SWEEP_DUE, 0, -1
    while queue_size(queues.cells) > 0:
        cls, v, _ = queue_pop(queues.cells)
        book.flags[v] = book.flags[v] & ~IN_CELL_QUEUE
        if book.cell_state[v] != UNTESTED:
            continue
        outradius2 = mesh.outradius2[v]
        now = size_class(outradius2)
        if now > cls:
            queue_push(queues.cells, now, v, 0)
            book.flags[v] = book.flags[v] | IN_CELL_QUEUE
            continue
        if not in_region(mesh.xy[v, 0], mesh.xy[v, 1], 2.0 * np.sqrt(outradius2), prm):
            book.cell_state[v] = DEFERRED
            cnt[C_DEFERRED] += 1
            continue
        c = count_cell(v, mesh, probe, cnt, prm, index)
        if c < 0:
            return STAR_OVERFLOW, 0, -1
        if c < k:
            book.cell_state[v] = GOOD
            continue
        if outradius2 < prm[P_FLOOR2]:
            book.cell_state[v] = FLOOR
            continue
        return far_corner(v, mesh), BREAK_CELL, v
    return -1, 0, -1


@kernel(entry=True, nogil=True)
def cells_to_sweep(mesh, book, queues, cnt, prm):
    """The queued vertices whose cells are untested, in Z-order of their positions (the
    sweep's order); from now on they count as swept."""
    q = queues.cells
    vertices = np.empty(queue_size(queues.cells), np.int32)
    n = 0
    for c in range(N_CLASSES):
        e = q.head[c]
        while e >= 0:
            v = q.ident[e]
            if book.cell_state[v] == UNTESTED:
                vertices[n] = v
                n += 1
            e = q.next[e]
    keys = np.empty(n, np.int64)
    for i in range(n):
        v = vertices[i]
        keys[i] = morton_key(mesh.xy[v, 0] / prm[P_LX], mesh.xy[v, 1] / prm[P_LY])
    cnt[C_CELLS_SWEPT] = cnt[C_CELLS_QUEUED]
    return vertices[np.argsort(keys)]


@kernel(entry=True, nrt=False, nogil=True)
def sweep_cells(vertices, mesh, book, probe, cnt, prm, index):
    """Count the cells of these vertices in this order and settle those holding < k points
    (the others stay queued and are counted again when popped). Returns 0, or STAR_OVERFLOW.
    It reads the mesh and writes only the vertices' own cell states and ``cnt``'s counters:
    threads may sweep disjoint vertex sets at once, each with its own probe and ``cnt``."""
    for i in range(vertices.shape[0]):
        v = vertices[i]
        if book.cell_state[v] != UNTESTED:
            continue
        c = count_cell(v, mesh, probe, cnt, prm, index)
        if c < 0:
            return STAR_OVERFLOW
        if c < prm[P_K]:
            book.cell_state[v] = GOOD
    return 0


@kernel(entry=True, nrt=False, nogil=True)
def queue_all(mesh, book, queues, cnt, prm):
    """Queue every triangle and vertex of a fresh triangulation (the initial mesh M0), or of
    one seeded with settled elements (``partition.seed``): the queues start empty, so no
    vertex is marked as queued before its cell is looked at."""
    queue_clear(queues.balls)
    queue_clear(queues.cells)
    queue_clear(queues.cleans)
    for t in range(cnt[C_NT]):
        queue_push(queues.balls, size_class(mesh.radius2[t]), t, mesh.corners[t, 0])
    for v in range(cnt[C_NV]):
        book.flags[v] = book.flags[v] & ~(IN_CELL_QUEUE | IN_CLEAN_QUEUE)
        _touch(v, mesh, book, queues, cnt, prm)


@kernel(entry=True, nrt=False, nogil=True)
def queue_unsettled(mesh, book, queues, cnt, prm):
    """Queue what a triangulation made of settled parts still needs looked at (a stitched
    one, ``scale/shared.py``): the triangles whose circumball is not settled (DEFERRED ones
    again) and the vertices as ``queue_all`` does (an untested cell, an aspect over tau)."""
    queue_clear(queues.balls)
    queue_clear(queues.cells)
    queue_clear(queues.cleans)
    for t in range(cnt[C_NT]):
        if book.ball_state[t] == DEFERRED:
            book.ball_state[t] = UNTESTED
        if book.ball_state[t] == UNTESTED:
            queue_push(queues.balls, size_class(mesh.radius2[t]), t, mesh.corners[t, 0])
    for v in range(cnt[C_NV]):
        book.flags[v] = book.flags[v] & ~(IN_CELL_QUEUE | IN_CLEAN_QUEUE)
        _touch(v, mesh, book, queues, cnt, prm)


@kernel(inline="always")
def needs_growth(mesh, queues, cnt):
    """True when an array could overflow during the next insertion."""
    return (
        cnt[C_NV] + 1 > mesh.xy.shape[0]
        or cnt[C_NT] + 2 > mesh.corners.shape[0]
        or queues.balls.scalars[Q_USED] + HEADROOM > queues.balls.ident.shape[0]
        or queues.cells.scalars[Q_USED] + HEADROOM > queues.cells.ident.shape[0]
        or queues.cleans.scalars[Q_USED] + HEADROOM > queues.cleans.ident.shape[0]
    )


@kernel(entry=True, nrt=False, nogil=True)
def refine_steps(mesh, book, queues, scratch, probe, cnt, prm, index, max_steps):
    """Run Algorithm 1 for at most max_steps insertions; returns a STATUS_* code."""
    steps = 0
    q = prm[P_GRID]
    while steps < max_steps:
        if cnt[C_NV] >= cnt[C_MAX_VERTICES]:
            return STATUS_MAX_VERTICES
        if needs_growth(mesh, queues, cnt):
            return STATUS_GROW
        # Clean first: after every Break, clean until every aspect is <= tau
        t, elem = clean(mesh, book, queues, prm)
        kind = CLEAN
        if t == -1:
            t, kind, elem = break_(mesh, book, queues, probe, cnt, prm, index)
            if t == -1:
                return STATUS_DONE
            if t == SWEEP_DUE:
                return STATUS_SWEEP
            if t < -1:
                cnt[C_ERROR] = t
                return STATUS_ERROR
        cx, cy, _ = circumcentre(mesh, prm, t)
        px = snap(cx, q)
        py = snap(cy, q)
        v = insert_vertex(px, py, t, mesh, scratch, cnt, prm)
        if v == INSERT_NOT_IN_SEED:  # the split point rounds onto an existing vertex
            cnt[C_FAILED] += 1
            if kind == CLEAN:
                book.flags[elem] = book.flags[elem] | CLEAN_FAILED
            elif kind == BREAK_BALL:
                book.ball_state[elem] = FAILED
            else:
                book.cell_state[elem] = FAILED
            continue
        if v < 0:
            cnt[C_ERROR] = v
            return STATUS_ERROR
        # the refinement's own marks on what the insertion made
        book.kinds[v] = kind
        book.cell_state[v] = UNTESTED
        book.flags[v] = 0
        nb = cnt[C_LAST_NB]
        # queue what the insertion changed: the new triangles (identified by their apex v:
        # a slot reused later gets another apex), the vertices around the cavity
        for e in range(nb):
            s = scratch.cavity[e]
            book.ball_state[s] = UNTESTED
            queue_push(queues.balls, size_class(mesh.radius2[s]), s, mesh.corners[s, 0])
        for e in range(nb + 1):
            _touch(scratch.boundary[e, 0] if e < nb else v, mesh, book, queues, cnt, prm)
        steps += 1
    return STATUS_STEPS
