"""kNNRefine on the sphere: the Break and Clean moves of ``refine.py`` on the spherical
Delaunay triangulation (``triangulation_sphere.py``), counting with the 3-D index
(``index3.py``) over the points' unit vectors.

Lengths are chords between unit vectors (|x - y| = 2 sin(theta / 2) for the great-circle
angle theta, the same order as the angles), so a circumcap is the part of the sphere in a
3-D ball about its centre, and a closed Voronoi cell the part in the ball of chord R(v)
about v on v's side of each neighbour's bisecting plane (for unit vectors, |x - v| <=
|x - w| exactly when x . v >= x . w: the great-circle bisector). The aspect 2 R(v) /
d_{M,2}(v) is measured in angles.

The loop is the plane's: Clean first (a vertex whose aspect exceeds tau: insert its cell's
far corner), else Break (a triangle whose closed circumcap holds >= k points: its centre;
else a vertex whose closed cell does: its far corner), largest first by size class
(``queue.py``); counting regions inflated by a relative 1e-9 and an absolute ``SLACK2`` (the
rounding of unit vectors) and tau^2 lowered by 1e-12, so that the output passes the strict
and exact checks of independent code; the Break floor (``min_size``, at least
``geometry.RESOLUTION_ANGLE``) and the Clean floor (``RESOLUTION_ANGLE``) leave elements
smaller than them and report them. Each insertion queues its new triangles (entries carry
the slot's fill count, ``mesh.gen``: a refilled slot makes the entry stale) and re-examines
the vertices joined to the new one, whose cells changed.
"""

import numpy as np

from .index3 import count_in_forest3
from .jit import kernel
from .queue import Q_USED, queue_pop, queue_push, queue_size, size_class
from .state import (
    BREAK_BALL,
    BREAK_CELL,
    C_CELL_TESTS,
    C_DISK_TESTS,
    C_ERROR,
    C_FAILED,
    C_MAX_VERTICES,
    C_NT,
    C_NV,
    CLEAN,
    CLEAN_BELOW_FLOOR,
    CLEAN_FAILED,
    FAILED,
    FLOOR,
    GOOD,
    IN_CELL_QUEUE,
    IN_CLEAN_QUEUE,
    INSERT_CAVITY_OVERFLOW,
    STAR_OVERFLOW,
    STATUS_DONE,
    STATUS_ERROR,
    STATUS_GROW,
    STATUS_MAX_VERTICES,
    STATUS_STEPS,
    UNTESTED,
)
from .triangulation_sphere import circumcap_centre, insert_sphere, walk_star

# parameters (float64 array ``prm``) of a run on the sphere
PS_TAU2 = 0  # tau^2, lowered by a relative 1e-12
PS_FLOOR2 = 1  # the Break floor: a squared chord
PS_CLEAN_FLOOR2 = 2  # the Clean floor: a squared chord
PS_INFLATE = 3  # 1 + 1e-9
PS_K = 4
PS_SLACK2 = 5  # added to every squared chord (and bisector constant) a count compares with
N_PARAMS_SPHERE = 6

# The counting regions are balls and half-spaces about unit vectors as stored, which are unit
# only to a few ulps (|x|^2 = 1 +- 2^-50): a point p lies in the closed circumcap of (a, b, c)
# exactly when it is on or above the plane through them (``orient3d(a, b, c, p) <= 0``, what
# certify counts), and then |p - n|^2 <= |a - n|^2 + (|p|^2 - |a|^2) + O(|p - a| ulp) for the
# cap's centre n as computed: the ball needs an absolute slack of a few ulps of 1 on its
# squared chord, not only a relative one. SLACK2 is four times the bound. Against a cap of
# angle theta it is a relative 2^-48 / theta^2: 2^-8 at the resolution floor below.
SLACK2 = 2.0**-48

HEADROOM_SPHERE = 8  # free vertex slots required before an insertion (triangles: 2 per vertex)
MAX_CAVITY_SPHERE = 4096  # the most triangles a cavity may have (scratch.cavity holds 2 more)
# free entries each queue must have before an insertion: one per new triangle or touched vertex
QUEUE_HEADROOM = 2 * MAX_CAVITY_SPHERE + 16


@kernel(inline="always")
def angle_of(chord2):
    """The great-circle angle of a squared chord."""
    return 2.0 * np.arcsin(min(1.0, 0.5 * np.sqrt(chord2)))


@kernel(inline="always")
def too_aspect(far2, near2, prm):
    """aspect = 2 R(v) / d_{M,2}(v) > tau, in angles (tau^2 lowered by 1e-12)."""
    r = angle_of(far2)
    d = angle_of(near2)
    return 4.0 * r * r > prm[PS_TAU2] * d * d


@kernel(nrt=False)
def _touch(v, mesh, book, queues, scratch):
    """Re-examine vertex v after its star changed: queue its cell, and its Clean if bad."""
    nh, far, far2, near2 = walk_star(v, mesh, scratch)
    cls = size_class(0.25 * far2)
    book.cell_state[v] = UNTESTED
    if not (book.flags[v] & IN_CELL_QUEUE):
        queue_push(queues.cells, cls, v, 0)
        book.flags[v] = book.flags[v] | IN_CELL_QUEUE
    book.flags[v] = book.flags[v] & ~(CLEAN_BELOW_FLOOR | CLEAN_FAILED)
    if not (book.flags[v] & IN_CLEAN_QUEUE):
        queue_push(queues.cleans, cls, v, 0)
        book.flags[v] = book.flags[v] | IN_CLEAN_QUEUE


@kernel(nrt=False)
def _insert(p, seed, kind, mesh, book, queues, scratch, cnt):
    """Insert p from the seed triangle and queue what changed; the new vertex or a negative
    code (nothing changed)."""
    v, nb = insert_sphere(p, seed, mesh, scratch, cnt)
    if v < 0:
        return v
    book.kinds[v] = kind
    book.flags[v] = 0
    for e in range(nb):
        t = scratch.cavity[e]
        book.ball_state[t] = UNTESTED
        queue_push(queues.balls, size_class(0.25 * mesh.chord2[t]), t, mesh.gen[t])
    for e in range(nb):
        _touch(scratch.horizon[e, 0], mesh, book, queues, scratch)
    _touch(v, mesh, book, queues, scratch)
    return v


@kernel(entry=True, nrt=False)
def queue_all_sphere(mesh, book, queues, scratch, cnt):
    """Queue every triangle and vertex (the start of a run)."""
    for t in range(cnt[C_NT]):
        book.ball_state[t] = UNTESTED
        queue_push(queues.balls, size_class(0.25 * mesh.chord2[t]), t, mesh.gen[t])
    for v in range(cnt[C_NV]):
        _touch(v, mesh, book, queues, scratch)


@kernel(entry=True, nrt=False)
def queue_unsettled_sphere(mesh, book, queues, scratch, cnt):
    """Queue every triangle and vertex left untested (a continued run: ``reopen_sphere``
    marked them), the rest settled as they are."""
    for t in range(cnt[C_NT]):
        if book.ball_state[t] == UNTESTED:
            queue_push(queues.balls, size_class(0.25 * mesh.chord2[t]), t, mesh.gen[t])
    for v in range(cnt[C_NV]):
        if book.cell_state[v] == UNTESTED:
            _touch(v, mesh, book, queues, scratch)


@kernel(nrt=False)
def count_cell_sphere(v, mesh, scratch, cnt, prm, index):
    """Points of P (their weight) in the closed Voronoi cell of v, inflated: exact below k,
    else some value >= k; STAR_OVERFLOW when v has more neighbours than the scratch holds."""
    k = prm[PS_K]
    inflate = prm[PS_INFLATE]
    slack2 = prm[PS_SLACK2]
    nh, far, far2, near2 = walk_star(v, mesh, scratch)
    if nh < 0:
        return STAR_OVERFLOW
    cnt[C_CELL_TESTS] += 1
    x = mesh.xyz[v]
    h, hc = scratch.h, scratch.hc
    for j in range(nh):
        w = scratch.ids[j]
        s = 0.0
        for a in range(3):
            h[j, a] = mesh.xyz[w, a] - x[a]
            s += h[j, a] * h[j, a]
        hc[j] = 0.5 * s * inflate + slack2  # the bisector of w and v, moved past w's rounding
    return count_in_forest3(index, x[0], x[1], x[2], h, hc, nh, far2 * inflate + slack2, k,
                            scratch.stack)  # fmt: skip


@kernel(entry=True, nrt=False)
def refine_steps_sphere(mesh, book, queues, scratch, cnt, prm, index, max_steps):
    """Up to ``max_steps`` insertions of kNNRefine on the sphere; returns a STATUS_*."""
    k = prm[PS_K]
    inflate = prm[PS_INFLATE]
    steps = 0
    cap_v = mesh.xyz.shape[0]
    cap_t = mesh.corners.shape[0]
    while steps < max_steps:
        if cnt[C_NV] + HEADROOM_SPHERE > cap_v or cnt[C_NT] + 2 * HEADROOM_SPHERE > cap_t:
            return STATUS_GROW
        for q in (queues.balls, queues.cells, queues.cleans):
            if q.scalars[Q_USED] + QUEUE_HEADROOM > q.ident.shape[0]:
                return STATUS_GROW
        if cnt[C_NV] >= cnt[C_MAX_VERTICES]:
            return STATUS_MAX_VERTICES
        # Clean: a vertex whose aspect exceeds tau
        if queue_size(queues.cleans) > 0:
            cls, v, _ = queue_pop(queues.cleans)
            book.flags[v] = book.flags[v] & ~IN_CLEAN_QUEUE
            nh, far, far2, near2 = walk_star(v, mesh, scratch)
            if nh < 0:
                cnt[C_ERROR] = STAR_OVERFLOW
                return STATUS_ERROR
            if not too_aspect(far2, near2, prm):
                continue
            if far2 < prm[PS_CLEAN_FLOOR2]:
                book.flags[v] = book.flags[v] | CLEAN_BELOW_FLOOR
                continue
            circumcap_centre(mesh, far, scratch.point)
            got = _insert(scratch.point, far, CLEAN, mesh, book, queues, scratch, cnt)
            if got == INSERT_CAVITY_OVERFLOW:
                cnt[C_ERROR] = got
                return STATUS_ERROR
            if got < 0:
                book.flags[v] = book.flags[v] | CLEAN_FAILED
                cnt[C_FAILED] += 1
            steps += 1
            continue
        # Break: a circumcap holding >= k points
        if queue_size(queues.balls) > 0:
            cls, t, g = queue_pop(queues.balls)
            if mesh.gen[t] != g or book.ball_state[t] != UNTESTED:
                continue  # stale: slot t holds another triangle now, or was tested
            cnt[C_DISK_TESTS] += 1
            c = scratch.point
            circumcap_centre(mesh, t, c)
            held = count_in_forest3(
                index, c[0], c[1], c[2], scratch.h, scratch.hc, 0,
                mesh.chord2[t] * inflate + prm[PS_SLACK2], k, scratch.stack,
            )  # fmt: skip
            if held < k:
                book.ball_state[t] = GOOD
                continue
            if mesh.chord2[t] < prm[PS_FLOOR2]:
                book.ball_state[t] = FLOOR
                continue
            got = _insert(c, t, BREAK_BALL, mesh, book, queues, scratch, cnt)
            if got == INSERT_CAVITY_OVERFLOW:
                cnt[C_ERROR] = got
                return STATUS_ERROR
            if got < 0:
                book.ball_state[t] = FAILED
                cnt[C_FAILED] += 1
            steps += 1
            continue
        # Break: a Voronoi cell holding >= k points
        if queue_size(queues.cells) > 0:
            cls, v, _ = queue_pop(queues.cells)
            book.flags[v] = book.flags[v] & ~IN_CELL_QUEUE
            if book.cell_state[v] != UNTESTED:
                continue
            held = count_cell_sphere(v, mesh, scratch, cnt, prm, index)
            if held == STAR_OVERFLOW:
                cnt[C_ERROR] = STAR_OVERFLOW
                return STATUS_ERROR
            if held < k:
                book.cell_state[v] = GOOD
                continue
            nh, far, far2, near2 = walk_star(v, mesh, scratch)
            if far2 < prm[PS_FLOOR2]:
                book.cell_state[v] = FLOOR
                continue
            circumcap_centre(mesh, far, scratch.point)
            got = _insert(scratch.point, far, BREAK_CELL, mesh, book, queues, scratch, cnt)
            if got == INSERT_CAVITY_OVERFLOW:
                cnt[C_ERROR] = got
                return STATUS_ERROR
            if got < 0:
                book.cell_state[v] = FAILED
                cnt[C_FAILED] += 1
            steps += 1
            continue
        return STATUS_DONE
    return STATUS_STEPS
