"""kNNRefine in three dimensions: the Break and Clean moves of ``refine.py``, on the periodic
3-D triangulation (``triangulation3.py``) and the 3-D counting index (``index3.py``).

The same loop and the same bookkeeping as in the plane: Clean first (a vertex with
aspect(Vor(v)) = 2 R(v) / d_{M,2}(v) > tau: insert the circumcentre of the tetrahedron at v
with the largest circumradius, Vor(v)'s far corner), else Break (a tetrahedron whose closed
circumball holds >= k points: its circumcentre; else a vertex whose closed Voronoi cell
holds >= k points: its far corner); largest first by size class (``queue.py``); counts
inflated by a relative 1e-9 and tau^2 lowered by 1e-12, so the output passes the strict
checks of independent code; a Break floor (``min_size``) and a Clean floor (2^14 grid steps)
below which elements are left and reported. What differs: the circumball queue holds
vertices, not tetrahedra. In space a vertex has ~6.4 tetrahedra and nearly all of them wait
in the queue at some time (largest first leaves the small ones for later), so an entry per
tetrahedron cost more memory than the tetrahedra's circumradii. An entry (v, class) says that
the untested tetrahedra at v of that class are due: popping it walks v's star, tests those,
and queues v again at the class of its largest untested tetrahedron left. An insertion
queues its new vertex once (every new tetrahedron has it as a corner); a tetrahedron moved to
another slot (``triangulation3._move``) keeps its corners, so no entry goes stale. A tile of
a tiled run (``_engine/region3.py``) moves only for elements inside its region, as in the
plane; the others are DEFERRED.

Circumballs in bulk: most of a run's counts are circumball counts (8.5 per vertex at k = 10
in uniform points), and whether a closed circumball holds k points is a pure function of the
tetrahedron. So when the queue first reaches a size class (every larger class empty: the
untested tetrahedra of that class are the next to be tested, bar those a Break destroys
first), ``refine_steps3`` returns STATUS_SWEEP and the driver has ``sweep_balls3`` count
them all, in slot ranges on every thread, marking GOOD those holding < k. The refinement
then pops as before and skips them: the same moves, the same mesh, with much of the
counting spread over the cores. A class the coming Breaks would mostly destroy is not worth
counting ahead: the driver counts a sample first (``driver3.Refinement3._sweep``). The cells
queued since the last sweep are swept the same way once the circumball queue is empty
(``sweep_cells3``, at least CELL_SWEEP_MIN of them: a cell only shrinks, so one under k is
settled for good).
"""

import numpy as np

from .geometry import circumsphere
from .index import STACK_SIZE
from .index3 import count_in_ball3, count_in_cell3
from .jit import kernel
from .queue import N_CLASSES, Q_SIZE, queue_clear, queue_pop, queue_push, queue_size, size_class
from .refine import interval_within
from .state import (
    BREAK_BALL,
    BREAK_CELL,
    C_BALLS_SWEPT,
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
    C_SWEEP_CELLS,
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
    STAR_OVERFLOW,
    STATUS_DONE,
    STATUS_ERROR,
    STATUS_GROW,
    STATUS_MAX_VERTICES,
    STATUS_STEPS,
    STATUS_SWEEP,
    TOUCHED,
    UNTESTED,
)
from .triangulation3 import (
    MAX_CAVITY3,
    insert_vertex3,
    load_corners,
    neighbours_local3,
    outradius2_at3,
    star3,
    vertex_neighbours3,
)

# parameters (float64 array ``prm``) of a 3-D run
P3_L0, P3_L1, P3_L2 = 0, 1, 2  # the torus' periods, internal units
P3_TAU2 = 3  # tau^2, lowered by a relative 1e-12
P3_FLOOR2 = 4  # the Break floor squared
P3_CLEAN_FLOOR2 = 5  # the Clean floor squared
P3_INFLATE = 6  # 1 + 1e-9
P3_GRID = 7  # the grid step q
P3_K = 8
P3_REGION = 9  # a tile's region (``_engine/region3.py``): its lower corner, 3 numbers, ...
P3_REGION_W = 12  # ... and its widths, 3 numbers; widths[0] = state.NO_REGION: no region
N_PARAMS3 = 15

HEADROOM3 = MAX_CAVITY3 + 64  # free slots required before an insertion
SWEEP_DUE3 = 99  # _break3's kind when the circumballs of a class should be swept first
NO_SWEEPS = N_CLASSES + 1  # cnt[C_BALLS_SWEPT] that turns the sweeps off (a tile's run)
CELL_SWEEP_MIN = 4096  # cells newly queued that make a cell sweep worthwhile


@kernel(inline="always")
def ball_in_box3(c, r, corner, widths, prm):
    """The closed ball (c, r), inflated by a relative 1e-6 and a grid step (beyond the
    counts' own inflation), lies in the box [corner, corner + widths] of the torus."""
    r = r * (1.0 + 1e-6) + prm[P3_GRID]
    for a in range(3):
        if not interval_within(c[a] - r, 2.0 * r, corner[a], widths[a], prm[a]):
            return False
    return True


@kernel(inline="always")
def in_region3(c, r, prm):
    """True when the closed ball (c, r) lies in the tile's region (``_engine/region3.py``), as
    ``refine.in_region`` in the plane; always without a region (a whole run)."""
    if prm[P3_REGION_W] < 0.0:
        return True
    return ball_in_box3(c, r, prm[P3_REGION : P3_REGION + 3], prm[P3_REGION_W : P3_REGION_W + 3],
                        prm)  # fmt: skip


@kernel(inline="always")
def is_too_aspect3(outradius2, d_m2_sq, prm):
    """2 R(v) / d_{M,2}(v) > tau, from squares."""
    return 4.0 * outradius2 > prm[P3_TAU2] * d_m2_sq


@kernel(nrt=False)
def _touch3(v, mesh, book, queues, scratch, cnt, prm):
    """Re-examine vertex v after its star changed: queue its cell and, if bad, its Clean.
    The cell is queued at the class of R(v)'s bound (``triangulation3``: its pop finds R(v)
    itself); whether v is bad is decided on R(v) itself, walked only if the bound says bad.
    Overwrites scratch.walk."""
    if book.cell_state[v] >= FLOOR:  # its cell changed: look again
        book.cell_state[v] = UNTESTED
    bound = abs(mesh.outradius2[v])
    if book.cell_state[v] == UNTESTED and not (book.flags[v] & IN_CELL_QUEUE):
        queue_push(queues.cells, size_class(bound), v, 0)
        book.flags[v] = book.flags[v] | IN_CELL_QUEUE
        cnt[C_CELLS_QUEUED] += 1
    book.flags[v] = book.flags[v] & ~(CLEAN_BELOW_FLOOR | CLEAN_FAILED)
    if book.flags[v] & IN_CLEAN_QUEUE or not is_too_aspect3(bound, mesh.nearest2[v], prm):
        return
    outradius2 = outradius2_at3(v, mesh, scratch, cnt)
    if is_too_aspect3(outradius2, mesh.nearest2[v], prm):
        queue_push(queues.cleans, size_class(outradius2), v, 0)
        book.flags[v] = book.flags[v] | IN_CLEAN_QUEUE


@kernel(entry=True, nrt=False, nogil=True)
def queue_all3(mesh, book, queues, scratch, cnt, prm):
    """Queue every tetrahedron (at its first corner) and vertex of a fresh triangulation."""
    for t in range(cnt[C_NT]):
        book.ball_state[t] = UNTESTED
        queue_push(queues.balls, size_class(mesh.radius2[t]), mesh.corners[t, 0], 0)
    for v in range(cnt[C_NV]):
        book.flags[v] = 0
        _touch3(v, mesh, book, queues, scratch, cnt, prm)


@kernel(entry=True, nrt=False, nogil=True)
def queue_seeded3(mesh, book, queues, scratch, cnt, prm):
    """Queue what a seeded triangulation (``Refinement3.seed``) has left to decide: every
    tetrahedron not settled (DEFERRED ones again) and every vertex (its cell unless GOOD,
    its Clean if bad); the queues start empty and must hold that many entries."""
    queue_clear(queues.balls)
    queue_clear(queues.cells)
    queue_clear(queues.cleans)
    for t in range(cnt[C_NT]):
        if book.ball_state[t] == DEFERRED:
            book.ball_state[t] = UNTESTED
        if book.ball_state[t] == UNTESTED:
            queue_push(queues.balls, size_class(mesh.radius2[t]), mesh.corners[t, 0], 0)
    for v in range(cnt[C_NV]):
        book.flags[v] = book.flags[v] & ~(IN_CELL_QUEUE | IN_CLEAN_QUEUE)
        _touch3(v, mesh, book, queues, scratch, cnt, prm)


@kernel(entry=True, nogil=True)
def queue_synced3(mesh, book, queues, scratch, cnt, prm, ids):
    """Queue what inserting the vertices ``ids`` (a tile's sync: ``TileRun.insert``) into a
    finished run changed, instead of everything (``queue_seeded3``): every tetrahedron an
    insertion made has the vertex it inserted as a corner, so an entry per vertex with an
    untested tetrahedron left (at the class of the largest) and a touch of every corner of
    their stars find it all. DEFERRED elements stay so (a tile's region does not change).
    The queues must hold len(ids) entries more, and the cells' and Cleans' one per vertex
    touched."""
    touched = np.empty(64 * ids.shape[0] + 64, np.int64)
    nt = 0
    for m in range(ids.shape[0]):
        v = ids[m]
        n = star3(v, mesh, scratch, cnt)[2]
        if n < 0:
            return STAR_OVERFLOW
        first = N_CLASSES
        for e in range(n):
            t = scratch.walk[e]
            if book.ball_state[t] == UNTESTED:
                first = min(first, size_class(mesh.radius2[t]))
            for i in range(4):
                u = mesh.corners[t, i]
                if not (book.flags[u] & TOUCHED):
                    book.flags[u] = book.flags[u] | TOUCHED
                    if nt == touched.shape[0]:
                        grown = np.empty(2 * nt, np.int64)
                        grown[:nt] = touched
                        touched = grown
                    touched[nt] = u
                    nt += 1
        if first < N_CLASSES:
            queue_push(queues.balls, first, v, 0)
    for m in range(nt):
        book.flags[touched[m]] = book.flags[touched[m]] & ~TOUCHED
    for m in range(nt):
        _touch3(touched[m], mesh, book, queues, scratch, cnt, prm)
    return nt


@kernel(nrt=False)
def count_cell3(v, mesh, scratch, probe, cnt, prm, index):
    """Points of P in the closed Voronoi cell of v (inflated): exact below k, else >= k;
    STAR_OVERFLOW if v has more neighbours than the probe holds."""
    k = prm[P3_K]
    inflate = prm[P3_INFLATE]
    r2 = abs(mesh.outradius2[v]) * inflate  # R(v) or a bound: the ball holds the cell
    period = prm[:3]
    cnt[C_CELL_TESTS] += 1
    # the cell lies in the ball of radius R(v) about v: the cheaper ball count may settle it
    c = count_in_ball3(index, mesh.xyz[v], r2, k, period, probe.stack)
    if c < k:
        return c
    nh = vertex_neighbours3(v, mesh, scratch, cnt, period, probe.h, probe.ids)
    if nh < 0:
        return STAR_OVERFLOW
    return _count_in_cell3(index, mesh.xyz[v], probe.h, probe.hc, nh, r2, inflate, k, period,
                           probe.stack)  # fmt: skip


@kernel(inline="always")
def _count_in_cell3(index, x, h, hc, nh, r2, inflate, k, period, stack):
    """The count of ``count_cell3`` and ``sweep_cells3`` once the ball of radius R(v) held
    >= k: the cell about x cut by the bisectors of its nh neighbours (h: their positions
    relative to x; hc: scratch for the half squared lengths, inflated), within r2."""
    for j in range(nh):
        hc[j] = 0.5 * (h[j, 0] ** 2 + h[j, 1] ** 2 + h[j, 2] ** 2) * inflate
    return count_in_cell3(index, x, h, hc, nh, r2, k, period, stack)


@kernel(inline="always")
def _clean3(mesh, book, queues, scratch, cnt, prm):
    """(t, v): insert the circumcentre of tetrahedron t, Vor(v)'s far corner, for the largest
    cell with aspect > tau; (-1, -1) when none."""
    while queue_size(queues.cleans) > 0:
        cls, v, _ = queue_pop(queues.cleans)
        book.flags[v] = book.flags[v] & ~IN_CLEAN_QUEUE
        outradius2 = outradius2_at3(v, mesh, scratch, cnt)
        if not is_too_aspect3(outradius2, mesh.nearest2[v], prm):
            continue
        now = size_class(outradius2)
        if now > cls:
            queue_push(queues.cleans, now, v, 0)
            book.flags[v] = book.flags[v] | IN_CLEAN_QUEUE
            continue
        if outradius2 < prm[P3_CLEAN_FLOOR2]:
            book.flags[v] = book.flags[v] | CLEAN_BELOW_FLOOR
            continue
        if not in_region3(mesh.xyz[v], 2.0 * np.sqrt(outradius2), prm):
            continue  # far corner and neighbours not all the tile's: left for later
        return star3(v, mesh, scratch, cnt)[1], v
    return -1, -1


@kernel(inline="always")
def _break3(mesh, book, queues, scratch, probe, cnt, prm, index):
    """(t, kind, element): the next Break, or (-1, 0, -1); t < -1 an error code."""
    k = prm[P3_K]
    inflate = prm[P3_INFLATE]
    period = prm[:3]
    pts = scratch.points
    c = scratch.walk_point
    while queue_size(queues.balls) > 0:
        # an entry (v, class): the untested tetrahedra at v of this class (or larger) are due
        cls, v, _ = queue_pop(queues.balls)
        if cls >= cnt[C_BALLS_SWEPT]:  # a class reached for the first time: sweep it
            cnt[C_BALLS_SWEPT] = cls + 1
            queue_push(queues.balls, cls, v, 0)  # the same entry, popped next
            cnt[C_SWEEP_CELLS] = 0
            return -1, SWEEP_DUE3, cls
        n = star3(v, mesh, scratch, cnt)[2]
        if n < 0:
            return STAR_OVERFLOW, 0, -1
        later = N_CLASSES
        for i in range(n):
            t = scratch.walk[i]
            if book.ball_state[t] != UNTESTED:
                continue
            now = size_class(mesh.radius2[t])
            if now > cls:
                later = min(later, now)
                continue
            load_corners(mesh, t, 0, 0, 0, period, pts)
            c[0], c[1], c[2], _ = circumsphere(pts)
            if not in_region3(c, np.sqrt(mesh.radius2[t]), prm):
                book.ball_state[t] = DEFERRED
                cnt[C_DEFERRED] += 1
                continue
            cnt[C_DISK_TESTS] += 1
            if count_in_ball3(index, c, mesh.radius2[t] * inflate, k, period, probe.stack) < k:
                book.ball_state[t] = GOOD
                continue
            if mesh.radius2[t] < prm[P3_FLOOR2]:
                book.ball_state[t] = FLOOR
                continue
            queue_push(queues.balls, cls, v, 0)  # the rest of v's star: after this Break
            return t, BREAK_BALL, t
        if later < N_CLASSES:  # v's smaller untested tetrahedra wait for their class
            queue_push(queues.balls, later, v, 0)
    if (cnt[C_BALLS_SWEPT] != NO_SWEEPS
            and cnt[C_CELLS_QUEUED] - cnt[C_CELLS_SWEPT] >= CELL_SWEEP_MIN):  # fmt: skip
        cnt[C_CELLS_SWEPT] = cnt[C_CELLS_QUEUED]  # the cells queued since: sweep them
        cnt[C_SWEEP_CELLS] = 1
        return -1, SWEEP_DUE3, -1
    while queue_size(queues.cells) > 0:
        cls, v, _ = queue_pop(queues.cells)
        book.flags[v] = book.flags[v] & ~IN_CELL_QUEUE
        if book.cell_state[v] != UNTESTED:
            continue
        outradius2 = outradius2_at3(v, mesh, scratch, cnt)
        now = size_class(outradius2)
        if now > cls:
            queue_push(queues.cells, now, v, 0)
            book.flags[v] = book.flags[v] | IN_CELL_QUEUE
            continue
        if not in_region3(mesh.xyz[v], 2.0 * np.sqrt(outradius2), prm):
            book.cell_state[v] = DEFERRED
            cnt[C_DEFERRED] += 1
            continue
        n = count_cell3(v, mesh, scratch, probe, cnt, prm, index)
        if n < 0:
            return STAR_OVERFLOW, 0, -1
        if n < k:
            book.cell_state[v] = GOOD
            continue
        if outradius2 < prm[P3_FLOOR2]:
            book.cell_state[v] = FLOOR
            continue
        return star3(v, mesh, scratch, cnt)[1], BREAK_CELL, v
    return -1, 0, -1


@kernel(entry=True, nogil=True)
def sweep_balls3(mesh, book, prm, index, cls, start, stop, stride):
    """Count the closed circumballs of the untested tetrahedra of size class <= cls in the
    slots of [start, stop) that are multiples of ``stride`` and mark GOOD those holding < k
    points (the others are counted again when popped). Returns (counts made, GOOD among
    them). It reads the mesh and writes only these slots' ball states: threads may sweep
    disjoint ranges at once."""
    k = prm[P3_K]
    inflate = prm[P3_INFLATE]
    period = prm[:3]
    pts = np.empty((5, 3))
    c = np.empty(3)
    stack = np.empty(STACK_SIZE, np.int64)
    made = 0
    good = 0
    for t in range(start, stop):
        if t % stride != 0:
            continue
        if book.ball_state[t] != UNTESTED or size_class(mesh.radius2[t]) > cls:
            continue
        load_corners(mesh, t, 0, 0, 0, period, pts)  # as _break3 does: the same ball
        c[0], c[1], c[2], _ = circumsphere(pts)
        if not in_region3(c, np.sqrt(mesh.radius2[t]), prm):
            continue
        made += 1
        if count_in_ball3(index, c, mesh.radius2[t] * inflate, k, period, stack) < k:
            book.ball_state[t] = GOOD
            good += 1
    return made, good


@kernel(entry=True, nogil=True)
def sweep_cells3(mesh, book, prm, index, start, stop):
    """Count the closed Voronoi cells of the queued vertices with untested cells among
    [start, stop) and mark GOOD those holding < k points (a cell only shrinks: settled for
    good; the others are counted again when popped). Returns the counts made, or
    STAR_OVERFLOW. Reads the mesh, writes only these vertices' cell states, and
    walks stars without the shared marks (``neighbours_local3``): threads may sweep
    disjoint ranges at once."""
    k = prm[P3_K]
    inflate = prm[P3_INFLATE]
    period = prm[:3]
    h = np.empty((1024, 3))
    hc = np.empty(1024)
    ids = np.empty(1024, np.int64)
    walk = np.empty(MAX_CAVITY3, np.int64)
    stack = np.empty(STACK_SIZE, np.int64)
    made = 0
    for v in range(start, stop):
        if not (book.flags[v] & IN_CELL_QUEUE) or book.cell_state[v] != UNTESTED:
            continue
        r2 = abs(mesh.outradius2[v])  # R(v) or a bound (no walks here: threads share marks)
        if not in_region3(mesh.xyz[v], 2.0 * np.sqrt(r2), prm):
            continue
        made += 1
        r2 = r2 * inflate  # as count_cell3 counts
        if count_in_ball3(index, mesh.xyz[v], r2, k, period, stack) < k:
            book.cell_state[v] = GOOD
            continue
        nh = neighbours_local3(v, mesh, period, walk, h, ids)  # the shared marks are not
        if nh < 0:  # this thread's: count_cell3's walk cannot be used
            return STAR_OVERFLOW
        if _count_in_cell3(index, mesh.xyz[v], h, hc, nh, r2, inflate, k, period, stack) < k:
            book.cell_state[v] = GOOD
    return made


@kernel(inline="always")
def needs_growth3(mesh, book, queues, cnt):
    return (
        cnt[C_NV] + 1 > mesh.xyz.shape[0]
        or cnt[C_NT] + HEADROOM3 > mesh.corners.shape[0]
        # entries free: those never used and those on the free list (cap - size)
        or queues.balls.scalars[Q_SIZE] + 2 * HEADROOM3 > queues.balls.ident.shape[0]
        or queues.cells.scalars[Q_SIZE] + HEADROOM3 > queues.cells.ident.shape[0]
        or queues.cleans.scalars[Q_SIZE] + HEADROOM3 > queues.cleans.ident.shape[0]
    )


@kernel(entry=True, nrt=False, nogil=True)
def refine_steps3(mesh, book, queues, scratch, probe, cnt, prm, index, max_steps):
    """Run Algorithm 1 in space for at most max_steps insertions; returns a STATUS_* code."""
    steps = 0
    q = prm[P3_GRID]
    period = prm[:3]
    pts = scratch.points
    p = scratch.walk_point
    while steps < max_steps:
        if cnt[C_NV] >= cnt[C_MAX_VERTICES]:
            return STATUS_MAX_VERTICES
        if needs_growth3(mesh, book, queues, cnt):
            return STATUS_GROW
        t, elem = _clean3(mesh, book, queues, scratch, cnt, prm)
        kind = CLEAN
        if t == -1:
            t, kind, elem = _break3(mesh, book, queues, scratch, probe, cnt, prm, index)
            if t == -1:
                return STATUS_SWEEP if kind == SWEEP_DUE3 else STATUS_DONE
            if t < -1:
                cnt[C_ERROR] = t
                return STATUS_ERROR
        load_corners(mesh, t, 0, 0, 0, period, pts)
        x, y, z, _ = circumsphere(pts)
        p[0] = np.rint(x / q) * q
        p[1] = np.rint(y / q) * q
        p[2] = np.rint(z / q) * q
        v = insert_vertex3(p, t, mesh, scratch, cnt, period)
        if v == INSERT_NOT_IN_SEED:  # the split point rounds onto or out of the ball
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
        book.kinds[v] = kind
        book.cell_state[v] = UNTESTED
        book.flags[v] = 0
        nb = cnt[C_LAST_NB]
        for e in range(scratch.moved[0, 0]):  # moved tetrahedra keep their state (and
            src = scratch.moved[1 + e, 0]  # their corners, hence their queue entries)
            dst = scratch.moved[1 + e, 1]
            book.ball_state[dst] = book.ball_state[src]
        # the new tetrahedra all have corner v: one entry, at the class of the largest
        first = N_CLASSES
        for e in range(nb):
            s = scratch.cavity[e]
            book.ball_state[s] = UNTESTED
            first = min(first, size_class(mesh.radius2[s]))
        queue_push(queues.balls, first, v, 0)
        # each corner once (a vertex is a corner of many new tetrahedra, v of all of them),
        # in the order first met, as touching them all in turn would (``_touch3`` does
        # nothing the second time)
        for e in range(nb):
            s = scratch.cavity[e]
            for i in range(4):
                u = mesh.corners[s, i]
                if not (book.flags[u] & TOUCHED):
                    book.flags[u] = book.flags[u] | TOUCHED
                    _touch3(u, mesh, book, queues, scratch, cnt, prm)
        for e in range(nb):
            s = scratch.cavity[e]
            for i in range(4):
                u = mesh.corners[s, i]
                book.flags[u] = book.flags[u] & ~TOUCHED
        steps += 1
    return STATUS_STEPS
