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
  destroyed meanwhile are recognised by their stamp and dropped).
* cells: a vertex is pushed when created; a Voronoi cell only shrinks as vertices are added, so
  a cell found to hold < k points is settled for good. R(v) never grows either, so an entry
  whose class is out of date is pushed back in its current class when popped.
* clean: the vertices around each cavity (the only ones whose Voronoi cell changed) and the new
  vertex are re-examined after each insertion; those with aspect > tau are pushed.

Counting is conservative: closed disks and closed cells are inflated by a relative 1e-9 and the
aspect threshold is lowered by a relative 1e-12, so the output satisfies the strict invariants
when re-checked in floating point by independent code.

Resolution floor: an element whose circumradius (or outradius) is below ``min_size`` is not
split by Break; it is marked FLOOR and reported. Clean has its own floor at the grid's
resolution. The kernel returns after ``max_steps`` insertions or when the arrays need to grow,
so the Python driver can report progress, enforce budgets and react to Ctrl-C.
"""

from .geometry import snap
from .index import count_in_cell, count_in_disk
from .jit import kernel
from .queue import Q_SIZE, Q_USED, queue_init, queue_pop, queue_push, size_class
from .triangulation import (
    C_LAST_NB,
    C_NT,
    C_NV,
    INSERT_NOT_IN_SEED,
    P_LX,
    P_LY,
    insert_vertex,
    vertex_star,
)

# vertex kinds (insertion moves)
INITIAL = 0
BREAK_BALL = 1  # Break: circumcenter of a triangle whose circumball holds >= k points
BREAK_CELL = 2  # Break: far corner of a Voronoi cell holding >= k points
CLEAN = 3  # Clean: far corner of a cell with aspect > tau
KIND_NAMES = ("initial", "break_circumball", "break_cell", "clean")

# states of a triangle's circumball (tstate) and of a vertex's Voronoi cell (vcell)
UNTESTED = 0
GOOD = 1  # holds < k points: settled
FLOOR = 2  # holds >= k points but is smaller than min_size: left alone
FAILED = 3  # its split point landed on an existing vertex (grid resolution)

# vflag bits
IN_CELL_QUEUE = 1
IN_CLEAN_QUEUE = 2
CLEAN_FLOOR = 4  # aspect > tau but below the grid-resolution floor
CLEAN_FAILED = 8

# counters (cnt); 0-3 belong to the triangulation
C_K = 8
C_MAX_VERTICES = 9
C_Q_TRI = 10  # 10..13: the circumball queue's scalars
C_Q_CELL = 14  # 14..17: the cell queue's
C_Q_CLEAN = 18  # 18..21: the clean queue's
C_DISK_TESTS = 26
C_CELL_TESTS = 27
C_FAILED = 28
C_ERROR = 29
N_COUNTERS = 32

# parameters (prm); 0-1 belong to the triangulation
P_TAU2 = 2  # tau^2, lowered by a relative 1e-12
P_FLOOR2 = 3  # min_size^2
P_CLEAN_FLOOR2 = 4
P_INFLATE = 5  # 1 + 1e-9: inflation of the counting regions
P_GRID = 6  # the grid step q every vertex is snapped to
N_PARAMS = 8

# refine_steps results
STATUS_DONE = 0
STATUS_STEPS = 1  # max_steps insertions made; call again
STATUS_GROW = 2  # an array is nearly full; grow it and call again
STATUS_MAX_VERTICES = 3
STATUS_ERROR = 4  # a broken invariant; cnt[C_ERROR] holds the code

HEADROOM = 1100  # free slots required before an insertion (> MAX_CAVITY + 2)


@kernel(inline="always")
def _touch(v, tri, ver, queues, work, cnt, prm):
    """Re-examine vertex v after its star changed: queue its cell and, if bad, its Clean."""
    vcell = ver[3]
    vflag = ver[4]
    big2, far, d2, deg = vertex_star(v, tri, ver, prm, work[0], work[1])
    if vcell[v] == FLOOR or vcell[v] == FAILED:
        vcell[v] = UNTESTED
    if vcell[v] == UNTESTED and not (vflag[v] & IN_CELL_QUEUE):
        queue_push(queues[1], cnt, C_Q_CELL, size_class(big2), v, 0)
        vflag[v] = vflag[v] | IN_CELL_QUEUE
    vflag[v] = vflag[v] & ~(CLEAN_FLOOR | CLEAN_FAILED)
    if 4.0 * big2 > prm[P_TAU2] * d2 and not (vflag[v] & IN_CLEAN_QUEUE):
        queue_push(queues[2], cnt, C_Q_CLEAN, size_class(big2), v, 0)
        vflag[v] = vflag[v] | IN_CLEAN_QUEUE


@kernel(inline="always")
def clean(tri, ver, queues, work, cnt, prm):
    """Choose the next Clean move: the largest cell whose aspect exceeds tau.

    Returns (t, v): insert the circumcenter of triangle t, the far corner of vertex v's cell;
    (-1, -1) when no vertex needs cleaning."""
    vflag = ver[4]
    while cnt[C_Q_CLEAN + Q_SIZE] > 0:
        cls, v, _ = queue_pop(queues[2], cnt, C_Q_CLEAN)
        vflag[v] = vflag[v] & ~IN_CLEAN_QUEUE
        big2, far, d2, deg = vertex_star(v, tri, ver, prm, work[0], work[1])
        if 4.0 * big2 <= prm[P_TAU2] * d2:
            continue
        now = size_class(big2)
        if now > cls:  # outradius shrank since it was queued: requeue in its true class
            queue_push(queues[2], cnt, C_Q_CLEAN, now, v, 0)
            vflag[v] = vflag[v] | IN_CLEAN_QUEUE
            continue
        if big2 < prm[P_CLEAN_FLOOR2]:
            vflag[v] = vflag[v] | CLEAN_FLOOR
            continue
        return far, v
    return -1, -1


@kernel(inline="always")
def break_(tri, ver, queues, work, cnt, prm, index):
    """Choose the next Break move: the largest circumball holding >= k points, else the largest
    Voronoi cell holding >= k points.

    Returns (t, kind, element): insert the circumcenter of triangle t; element is the triangle
    (BREAK_BALL) or the vertex (BREAK_CELL) being split. (-1, 0, -1) when every circumball and
    cell holds < k points or is at the floor; t < -1 on error."""
    tcc = tri[3]
    tr2 = tri[4]
    tstamp = tri[5]
    tstate = tri[6]
    vxy = ver[0]
    vcell = ver[3]
    vflag = ver[4]
    hx, hy, hc, stack = work
    k = cnt[C_K]
    lx = prm[P_LX]
    ly = prm[P_LY]
    inflate = prm[P_INFLATE]
    while cnt[C_Q_TRI + Q_SIZE] > 0:
        cls, t, stamp = queue_pop(queues[0], cnt, C_Q_TRI)
        if tstamp[t] != stamp or tstate[t] != UNTESTED:
            continue
        cnt[C_DISK_TESTS] += 1
        if count_in_disk(index, tcc[t, 0], tcc[t, 1], tr2[t] * inflate, k, lx, ly, stack) < k:
            tstate[t] = GOOD
            continue
        if tr2[t] < prm[P_FLOOR2]:
            tstate[t] = FLOOR
            continue
        return t, BREAK_BALL, t
    while cnt[C_Q_CELL + Q_SIZE] > 0:
        cls, v, _ = queue_pop(queues[1], cnt, C_Q_CELL)
        vflag[v] = vflag[v] & ~IN_CELL_QUEUE
        if vcell[v] != UNTESTED:
            continue
        big2, far, d2, deg = vertex_star(v, tri, ver, prm, hx, hy)
        if deg < 0:
            return -100, 0, -1
        now = size_class(big2)
        if now > cls:
            queue_push(queues[1], cnt, C_Q_CELL, now, v, 0)
            vflag[v] = vflag[v] | IN_CELL_QUEUE
            continue
        cnt[C_CELL_TESTS] += 1
        # the cell lies in the disk of radius R(v) about v: when that disk holds < k points,
        # so does the cell, and the cheaper disk count settles it
        c = count_in_disk(index, vxy[v, 0], vxy[v, 1], big2 * inflate, k, lx, ly, stack)
        if c >= k:
            for j in range(deg):
                hc[j] = 0.5 * (hx[j] * hx[j] + hy[j] * hy[j]) * inflate
            c = count_in_cell(
                index, vxy[v, 0], vxy[v, 1], hx, hy, hc, deg, big2 * inflate, k, lx, ly, stack
            )
        if c < k:
            vcell[v] = GOOD
            continue
        if big2 < prm[P_FLOOR2]:
            vcell[v] = FLOOR
            continue
        return far, BREAK_CELL, v
    return -1, 0, -1


@kernel()
def queue_all(tri, ver, queues, work, cnt, prm):
    """Queue every triangle and vertex of a fresh triangulation (the initial mesh M0)."""
    tr2 = tri[4]
    tstamp = tri[5]
    for base in (C_Q_TRI, C_Q_CELL, C_Q_CLEAN):
        queue_init(cnt, base)
    for t in range(cnt[C_NT]):
        queue_push(queues[0], cnt, C_Q_TRI, size_class(tr2[t]), t, tstamp[t])
    for v in range(cnt[C_NV]):
        _touch(v, tri, ver, queues, work, cnt, prm)


@kernel(inline="always")
def needs_growth(tri, ver, queues, cnt):
    """True when an array could overflow during the next insertion."""
    return (
        cnt[C_NV] + 1 > ver[0].shape[0]
        or cnt[C_NT] + 2 > tri[0].shape[0]
        or cnt[C_Q_TRI + Q_USED] + HEADROOM > queues[0][1].shape[0]
        or cnt[C_Q_CELL + Q_USED] + HEADROOM > queues[1][1].shape[0]
        or cnt[C_Q_CLEAN + Q_USED] + HEADROOM > queues[2][1].shape[0]
    )


@kernel()
def refine_steps(tri, ver, queues, scr, work, cnt, prm, index, max_steps):
    """Run Algorithm 1 for at most max_steps insertions; returns a STATUS_* code."""
    tcc = tri[3]
    tr2 = tri[4]
    tstamp = tri[5]
    tstate = tri[6]
    vcell = ver[3]
    vflag = ver[4]
    cav = scr[3]
    bnd = scr[5]
    steps = 0
    while steps < max_steps:
        if cnt[C_NV] >= cnt[C_MAX_VERTICES]:
            return STATUS_MAX_VERTICES
        if needs_growth(tri, ver, queues, cnt):
            return STATUS_GROW
        # Clean first: after every Break, clean until every aspect is <= tau
        t, elem = clean(tri, ver, queues, work, cnt, prm)
        kind = CLEAN
        if t == -1:
            t, kind, elem = break_(tri, ver, queues, work, cnt, prm, index)
            if t == -1:
                return STATUS_DONE
            if t < -1:
                cnt[C_ERROR] = t
                return STATUS_ERROR
        q = prm[P_GRID]
        v = insert_vertex(snap(tcc[t, 0], q), snap(tcc[t, 1], q), t, kind, tri, ver, scr, cnt, prm)
        if v == INSERT_NOT_IN_SEED:  # the split point rounds onto an existing vertex
            cnt[C_FAILED] += 1
            if kind == CLEAN:
                vflag[elem] = vflag[elem] | CLEAN_FAILED
            elif kind == BREAK_BALL:
                tstate[elem] = FAILED
            else:
                vcell[elem] = FAILED
            continue
        if v < 0:
            cnt[C_ERROR] = v
            return STATUS_ERROR
        # queue what the insertion changed: the new triangles, the vertices around the cavity
        nb = cnt[C_LAST_NB]
        for e in range(nb):
            s = cav[e]
            queue_push(queues[0], cnt, C_Q_TRI, size_class(tr2[s]), s, tstamp[s])
        for e in range(nb + 1):
            _touch(bnd[e, 0] if e < nb else v, tri, ver, queues, work, cnt, prm)
        steps += 1
    return STATUS_STEPS
