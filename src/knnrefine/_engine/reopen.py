"""A finished run continued with more points: which of its elements the new points reach.

Adding points only lowers d_{P,k}: every element of a finished mesh held fewer than k points
of the old P (or sat at the floor), and it can hold k or more of the new P only where a new
point lies in it. A circumball holds a point p exactly when its triangle is in p's cavity
(the triangles whose circumcircle holds p, connected around the triangle that holds p), and
a Voronoi cell holds p only when its vertex is p's nearest, a corner of that cavity. So a
continued run settles every element, then reopens each new point's cavity and its corners
(``reopen``), and refines from there: the rest of the mesh is not looked at again.

The cavity here is found with a floating test loosened by ``SLACK`` (a triangle joins when
p is within its circumradius times 1 + SLACK of its circumcentre): a few more elements than
the exact cavity, never fewer (a loose cavity is connected around the exact one), which only
costs their counts again. Space (``reopen3``: tetrahedra, circumspheres) and the sphere
(``reopen_sphere``: circumcaps) do the same.
"""

import numpy as np

from .geometry import circumsphere
from .index import count_in_disk
from .index3 import count_in_ball3, count_in_region3
from .jit import kernel
from .region import locate
from .region3 import locate3
from .state import C_NT, C_STAMP, GOOD, P_LX, P_LY, UNTESTED
from .triangulation import MAX_CAVITY, circumcentre, corner_of, edge_to
from .triangulation3 import load_corners, shift_across3
from .triangulation_sphere import circumcap_centre, locate_sphere

SLACK = 1e-6  # relative, on the squared circumradius
REOPEN_LOST = -1  # a walk that found no triangle (a broken mesh)
REOPEN_OVERFLOW = -2  # a loose cavity larger than MAX_CAVITY triangles


@kernel(inline="always")
def _reopen_element(book, mesh, u):
    """Mark cell u's circumball and its corners' Voronoi cells untested; 1 if the ball was
    not already, else 0."""
    for c in range(mesh.corners.shape[1]):
        book.cell_state[mesh.corners[u, c]] = UNTESTED
    if book.ball_state[u] == UNTESTED:
        return 0
    book.ball_state[u] = UNTESTED
    return 1


@kernel(inline="always")
def _seed_cavity(scratch, cnt, t):
    """Start a new cavity at cell t (a new stamp marks its cells); returns the stamp."""
    stamp = cnt[C_STAMP] + 1
    cnt[C_STAMP] = stamp
    scratch.cavity[0] = t
    scratch.mark[t] = stamp
    return stamp


@kernel(inline="always")
def _join_cavity(scratch, n, n_cav, stamp):
    """Add cell n to the cavity as its cell n_cav; False when the cavity is full."""
    if n_cav >= scratch.cavity.shape[0]:
        return False
    scratch.mark[n] = stamp
    scratch.cavity[n_cav] = n
    return True


@kernel(entry=True, nrt=False, nogil=True)
def reopen(xy, mesh, book, scratch, cnt, prm):
    """Mark untested every triangle whose circumball (loosened by ``SLACK``) holds one of the
    points xy (internal coordinates, in [0, lx) x [0, ly), best in a space-filling order),
    and every corner of such a triangle (its Voronoi cell may hold the point). Returns the
    number of triangles reopened, or REOPEN_LOST / REOPEN_OVERFLOW."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    cav = scratch.cavity
    cav_s = scratch.cavity_shift
    loose = 1.0 + SLACK
    reopened = 0
    t = 0
    for p in range(xy.shape[0]):
        px = xy[p, 0]
        py = xy[p, 1]
        t, sx, sy = locate(px, py, t, mesh, lx, ly)
        if t < 0:
            return REOPEN_LOST
        stamp = _seed_cavity(scratch, cnt, t)
        cav_s[0, 0] = sx
        cav_s[0, 1] = sy
        n_cav = 1
        i = 0
        while i < n_cav:
            u = cav[i]
            ux = cav_s[i, 0]
            uy = cav_s[i, 1]
            reopened += _reopen_element(book, mesh, u)
            for j in range(3):
                n = mesh.neighbours[u, j]
                if scratch.mark[n] == stamp:
                    continue
                ja = (j + 1) % 3
                a = mesh.corners[u, ja]
                jn = corner_of(mesh, n, a)
                nx = ux + mesh.offsets[u, ja, 0] - mesh.offsets[n, jn, 0]
                ny = uy + mesh.offsets[u, ja, 1] - mesh.offsets[n, jn, 1]
                cx, cy, r2 = circumcentre(mesh, prm, n)
                dx = px - (cx + nx * lx)
                dy = py - (cy + ny * ly)
                if dx * dx + dy * dy <= r2 * loose:
                    if n_cav >= MAX_CAVITY or not _join_cavity(scratch, n, n_cav, stamp):
                        return REOPEN_OVERFLOW
                    cav_s[n_cav, 0] = nx
                    cav_s[n_cav, 1] = ny
                    n_cav += 1
            i += 1
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def reopen_by_balls(mesh, book, prm, new, nt, stack):
    """``reopen`` for a batch of points many times the triangles: every triangle whose
    circumball (loosened by ``SLACK``) holds one of the points, and its corners, marked
    untested, by one count per triangle that stops at the first point (``count_in_disk``
    over ``new``, a ``state.PointForest`` of the points alone) instead of a walk and a
    cavity per point. The triangles found include every cavity (a triangle of one holds
    its point). Returns the number of triangles reopened."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    loose = 1.0 + SLACK
    reopened = 0
    for t in range(nt):
        cx, cy, r2 = circumcentre(mesh, prm, t)
        if count_in_disk(new, cx, cy, r2 * loose, 1.0, lx, ly, stack) >= 1.0:
            reopened += _reopen_element(book, mesh, t)
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def reopen3(xyz, mesh, book, scratch, cnt, period):
    """``reopen`` in space: every tetrahedron whose circumball (loosened by ``SLACK``) holds
    one of the points xyz (internal coordinates in [0, period), best in a space-filling
    order) and every corner of one marked untested. Returns the number of tetrahedra
    reopened, or REOPEN_LOST / REOPEN_OVERFLOW."""
    cav = scratch.cavity
    cav_s = scratch.cavity_shift
    pts = scratch.points
    shift = scratch.shift
    q = scratch.walk_point
    loose = 1.0 + SLACK
    reopened = 0
    t = 0
    for p in range(xyz.shape[0]):
        t = locate3(xyz[p], t, mesh, period, pts, shift)
        if t < 0:
            return REOPEN_LOST
        for a in range(3):
            q[a] = xyz[p, a] - shift[a] * period[a]  # p in t's frame
        stamp = _seed_cavity(scratch, cnt, t)
        cav_s[0, 0] = 0
        cav_s[0, 1] = 0
        cav_s[0, 2] = 0
        n_cav = 1
        i = 0
        while i < n_cav:
            u = cav[i]
            reopened += _reopen_element(book, mesh, u)
            for j in range(4):
                n = mesh.neighbours[u, j]
                if scratch.mark[n] == stamp:
                    continue
                ok, sx, sy, sz = shift_across3(mesh, u, j, n, cav_s[i, 0], cav_s[i, 1],
                                               cav_s[i, 2])  # fmt: skip
                if not ok:
                    return REOPEN_LOST
                load_corners(mesh, n, sx, sy, sz, period, pts)
                cx, cy, cz, r2 = circumsphere(pts)
                d2 = (q[0] - cx) ** 2 + (q[1] - cy) ** 2 + (q[2] - cz) ** 2
                if d2 <= r2 * loose:
                    if not _join_cavity(scratch, n, n_cav, stamp):
                        return REOPEN_OVERFLOW
                    cav_s[n_cav, 0] = sx
                    cav_s[n_cav, 1] = sy
                    cav_s[n_cav, 2] = sz
                    n_cav += 1
            i += 1
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def reopen_by_balls3(mesh, book, scratch, new, nt, period, stack):
    """``reopen_by_balls`` in space: every tetrahedron whose circumball (loosened by
    ``SLACK``) holds one of the points of ``new`` (their own ``state.PointForest``), and its
    corners, marked untested, by one count per tetrahedron that stops at the first point
    (``count_in_ball3``). Returns the number of tetrahedra reopened."""
    pts = scratch.points
    c = scratch.walk_point
    loose = 1.0 + SLACK
    reopened = 0
    for t in range(nt):
        load_corners(mesh, t, 0, 0, 0, period, pts)
        c[0], c[1], c[2], r2 = circumsphere(pts)
        if count_in_ball3(new, c, r2 * loose, 1.0, period, stack) >= 1.0:
            reopened += _reopen_element(book, mesh, t)
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def reopen_sphere(xyz, mesh, book, scratch, cnt):
    """``reopen`` on the sphere: every triangle whose circumcap (loosened by ``SLACK``)
    holds one of the unit vectors xyz (best in a space-filling order) and every corner of
    one marked untested. Returns the number of triangles reopened, or REOPEN_LOST /
    REOPEN_OVERFLOW."""
    cav = scratch.cavity
    pts = scratch.points
    centre = scratch.point
    loose = 1.0 + SLACK
    nt = cnt[C_NT]
    reopened = 0
    t = 0
    for p in range(xyz.shape[0]):
        t = locate_sphere(xyz[p], t, mesh, pts, nt, False)
        if t < 0:
            return REOPEN_LOST
        stamp = _seed_cavity(scratch, cnt, t)
        n_cav = 1
        i = 0
        while i < n_cav:
            u = cav[i]
            reopened += _reopen_element(book, mesh, u)
            for j in range(3):
                n = mesh.neighbours[u, j]
                if scratch.mark[n] == stamp:
                    continue
                circumcap_centre(mesh, n, centre)
                d2 = 0.0
                for a in range(3):
                    d2 += (xyz[p, a] - centre[a]) ** 2
                if d2 <= mesh.chord2[n] * loose:
                    if not _join_cavity(scratch, n, n_cav, stamp):
                        return REOPEN_OVERFLOW
                    n_cav += 1
            i += 1
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def reopen_by_caps(mesh, book, scratch, new, nt):
    """``reopen_by_balls`` on the sphere: every triangle whose circumcap (loosened by
    ``SLACK``) holds one of the unit vectors of ``new`` (their own ``state.PointTree``),
    and its corners, marked untested, by one count per triangle that stops at the first
    point (``count_in_region3`` with no half-spaces). Returns the number reopened."""
    centre = scratch.point
    loose = 1.0 + SLACK
    reopened = 0
    for t in range(nt):
        circumcap_centre(mesh, t, centre)
        held = count_in_region3(new, centre[0], centre[1], centre[2], scratch.h, scratch.hc, 0,
                                mesh.chord2[t] * loose, 1.0, scratch.stack)  # fmt: skip
        if held >= 1.0:
            reopened += _reopen_element(book, mesh, t)
    return reopened


@kernel(entry=True, nrt=False, nogil=True)
def settle_all(book, cnt, nv):
    """Every triangle's circumball and every vertex's cell settled (GOOD): a finished run's
    state, before ``reopen``."""
    for t in range(cnt[C_NT]):
        book.ball_state[t] = GOOD
    for v in range(nv):
        book.cell_state[v] = GOOD


@kernel(entry=True, nrt=False, nogil=True)
def set_nearest_from_edges(mesh, prm, nt, nv):
    """d_{M,2}(v)^2 of vertices 0..nv-1 (``mesh.nearest2``) from the edges of triangles
    0..nt-1: the shortest edge at each vertex, as ``vertex_star`` finds it walking round v
    (the same differences of grid coordinates, so the same values), in one pass over the
    triangles instead of a walk per vertex."""
    lx = prm[P_LX]
    ly = prm[P_LY]
    for v in range(nv):
        mesh.nearest2[v] = np.inf
    for t in range(nt):
        for i in range(3):
            j = (i + 1) % 3
            ex, ey = edge_to(mesh, t, i, j, lx, ly)
            e2 = ex * ex + ey * ey
            a = mesh.corners[t, i]
            b = mesh.corners[t, j]
            if e2 < mesh.nearest2[a]:
                mesh.nearest2[a] = e2
            if e2 < mesh.nearest2[b]:
                mesh.nearest2[b] = e2
