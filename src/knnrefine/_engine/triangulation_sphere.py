"""The Delaunay triangulation of points on the unit sphere S^2, incremental.

On the sphere the Delaunay triangulation of a point set is the boundary of its convex hull:
a triangle's circumcircle is where the plane through its corners cuts the sphere, and the
circumcap (the cap that circle bounds on the triangle's side) holds no other vertex exactly
when every other vertex lies below that plane, on the origin's side. Inserting a point p is
then one step of the incremental convex hull (the sphere's Bowyer-Watson): the triangles
whose circumcap holds p strictly are those whose plane p sees from outside (``visible``), a
connected disk around p; they are removed and p is joined to the disk's boundary.

Predicates: ``predicates3.orient3d`` in exact arithmetic on the unit vectors as stored (no
rounding through longitude and latitude). ``orient3d(a, b, c, origin) > 0`` for every
triangle (counter-clockwise seen from outside); p lies strictly inside the circumcap of
(a, b, c) when ``orient3d(a, b, c, p) < 0``. Stored vectors are unit only to rounding, so
"the sphere's Delaunay triangulation" here means the hull of the vectors as stored, which
is what ``certify`` checks.

An insertion is refused, leaving the triangulation as it was, when its point is not
strictly inside the seed's circumcap or when the visible triangles are not a disk with
every vertex on its boundary (a point within rounding of a vertex would otherwise swallow
it). The triangulation has no boundary: t = 2 v - 4 triangles always, and the slots of a
cavity are reused by the triangles that fill it, the two extra ones appended, so the slots
0 .. t - 1 are always the triangles. ``mesh.gen`` counts each slot's fillings: a queue
entry made for a triangle stays valid while its slot's count is the one it recorded.

The start is the regular tetrahedron inscribed in the sphere (``tetrahedron``): every
circumcap is smaller than a hemisphere, and so stay those of every later triangulation.
"""

import numpy as np

from .index import STACK_SIZE
from .jit import kernel
from .predicates3 import orient3d
from .state import (
    C_NT,
    C_NV,
    C_STAMP,
    INSERT_CAVITY_OVERFLOW,
    INSERT_NOT_IN_SEED,
    INSERT_TOPOLOGY,
    SphereMesh,
    SphereScratch,
)

INSERT_TOO_CLOSE = INSERT_TOPOLOGY  # the cavity was not a disk: a vertex would be swallowed


def tetrahedron():
    """(vertices (4, 3) unit vectors, triangles (4, 3) counter-clockwise from outside): the
    regular tetrahedron with a vertex at the north pole and one on the prime meridian."""
    z = -1.0 / 3.0
    s = np.sqrt(8.0) / 3.0
    angles = np.radians([0.0, 120.0, 240.0])
    xyz = np.vstack([[0.0, 0.0, 1.0], np.column_stack([s * np.cos(angles), s * np.sin(angles),
                                                       np.full(3, z)])])  # fmt: skip
    tri = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]], np.int32)
    det = np.einsum("ij,ij->i", xyz[tri[:, 0]], np.cross(xyz[tri[:, 1]], xyz[tri[:, 2]]))
    assert (det > 0).all()
    return xyz, tri


def neighbours_of(tri):
    """(t, 3) the triangle across the edge opposite each corner of a closed triangulation."""
    t = len(tri)
    a = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]]).astype(np.int64)
    b = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]]).astype(np.int64)
    base = int(tri.max()) + 1
    own = a * base + b  # directed edge of (triangle, corner); its twin is b -> a
    slot = np.repeat(np.arange(3), t) * t + np.tile(np.arange(t), 3)
    order = np.argsort(own)
    where = np.searchsorted(own[order], b * base + a)
    twin = order[where]
    out = np.empty((t, 3), np.int32)
    out[slot % t, slot // t] = twin % t
    return out


def new_sphere(capacity_v, capacity_t, zeros=np.zeros):
    """A ``SphereMesh`` holding the tetrahedron, room for ``capacity_v`` vertices and
    ``capacity_t`` triangles; returns (mesh, nv, nt)."""
    xyz0, tri0 = tetrahedron()
    mesh = SphereMesh(
        corners=zeros((capacity_t, 3), np.int32),
        neighbours=zeros((capacity_t, 3), np.int32),
        chord2=zeros((capacity_t,), np.float64),
        gen=zeros((capacity_t,), np.int32),
        xyz=zeros((capacity_v, 3), np.float64),
        star=zeros((capacity_v,), np.int32),
    )
    mesh.xyz[:4] = xyz0
    mesh.corners[:4] = tri0
    mesh.neighbours[:4] = neighbours_of(tri0)
    for t in range(4):
        set_circumcap(mesh, t)
    for i, t in enumerate([0, 0, 0, 1]):
        mesh.star[i] = t
    return mesh, 4, 4


def new_sphere_scratch(capacity_v, capacity_t, max_cavity, max_degree=256):
    """The insertion's and the star walks' working space (``state.SphereScratch``) for up to
    ``capacity_v`` vertices and ``capacity_t`` triangles, cavities of ``max_cavity``
    triangles and vertices of ``max_degree`` neighbours."""
    return SphereScratch(
        mark=np.zeros(capacity_t, np.int32),
        vmark=np.zeros(capacity_v, np.int32),
        vnext=np.zeros(capacity_v, np.int32),
        cavity=np.zeros(max_cavity + 2, np.int32),
        horizon=np.zeros((max_cavity + 2, 3), np.int32),
        points=np.zeros((4, 3)),
        point=np.zeros(3),
        ids=np.zeros(max_degree, np.int64),
        h=np.zeros((max_degree, 3)),
        hc=np.zeros(max_degree),
        stack=np.zeros(STACK_SIZE, np.int64),
    )


@kernel(inline="always")
def _centre_of(mesh, t):
    """The centre of triangle t's circumcap: the unit normal of its plane on the side away
    from the origin, (b - a) x (c - a) normalised, as three numbers."""
    a = mesh.xyz[mesh.corners[t, 0]]
    b = mesh.xyz[mesh.corners[t, 1]]
    c = mesh.xyz[mesh.corners[t, 2]]
    nx = (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1])
    ny = (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2])
    nz = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    return nx / norm, ny / norm, nz / norm


@kernel(inline="always")
def circumcap_centre(mesh, t, out):
    """The centre of triangle t's circumcap into ``out`` (3,)."""
    out[0], out[1], out[2] = _centre_of(mesh, t)


@kernel(entry=True)
def set_circumcap(mesh, t):
    """The squared chord radius of triangle t's circumcap: the largest over the corners of
    |centre - corner|^2, so that rounding never shrinks the counting region."""
    nx, ny, nz = _centre_of(mesh, t)
    r2 = 0.0
    for j in range(3):
        p = mesh.xyz[mesh.corners[t, j]]
        r2 = max(r2, (p[0] - nx) ** 2 + (p[1] - ny) ** 2 + (p[2] - nz) ** 2)
    mesh.chord2[t] = r2


@kernel(inline="always")
def visible(mesh, t, p, pts):
    """Whether p lies strictly inside the circumcap of triangle t (above its plane)."""
    for j in range(3):
        v = mesh.corners[t, j]
        for a in range(3):
            pts[j, a] = mesh.xyz[v, a]
    for a in range(3):
        pts[3, a] = p[a]
    return orient3d(pts) < 0


@kernel(inline="always")
def corner_of(mesh, t, v):
    """The corner (0, 1, 2) of triangle t at vertex v, -1 if none."""
    for j in range(3):
        if mesh.corners[t, j] == v:
            return j
    return -1


@kernel(nrt=False)
def insert_sphere(p, seed, mesh, scratch, cnt):
    """Insert the unit vector p, whose circumcap-holding triangles include ``seed``: the
    new vertex's index, or a negative code (INSERT_NOT_IN_SEED, INSERT_TOO_CLOSE,
    INSERT_CAVITY_OVERFLOW) with nothing changed. After it, ``scratch.horizon[:nb, 0]`` are
    the vertices joined to p (nb = cnt[C_LAST_NB] is not kept here: the count is
    ``cnt[C_NT]`` grown by 2 and the new slots are ``scratch.cavity[:nb]``); returns
    (vertex, nb)."""
    pts = scratch.points
    if not visible(mesh, seed, p, pts):
        return INSERT_NOT_IN_SEED, 0
    cnt[C_STAMP] += 1
    stamp = cnt[C_STAMP]
    cavity, horizon, mark = scratch.cavity, scratch.horizon, scratch.mark
    cap = cavity.shape[0] - 2
    cavity[0] = seed
    mark[seed] = stamp
    ncav = 1
    nb = 0
    i = 0
    while i < ncav:
        t = cavity[i]
        i += 1
        for j in range(3):
            u = mesh.neighbours[t, j]
            if mark[u] == stamp:
                continue
            if visible(mesh, u, p, pts):
                if ncav >= cap:
                    return INSERT_CAVITY_OVERFLOW, 0
                mark[u] = stamp
                cavity[ncav] = u
                ncav += 1
            else:
                if nb >= cap:
                    return INSERT_CAVITY_OVERFLOW, 0
                horizon[nb, 0] = mesh.corners[t, (j + 1) % 3]
                horizon[nb, 1] = mesh.corners[t, (j + 2) % 3]
                horizon[nb, 2] = u
                nb += 1
    # a disk with every vertex on its one boundary cycle: F = B - 2 and B distinct starts
    if nb != ncav + 2:
        return INSERT_TOO_CLOSE, 0
    vmark, vnext = scratch.vmark, scratch.vnext
    for e in range(nb):
        a = horizon[e, 0]
        if vmark[a] == stamp:
            return INSERT_TOO_CLOSE, 0
        vmark[a] = stamp
        vnext[a] = e
    for e in range(nb):
        if vmark[horizon[e, 1]] != stamp:
            return INSERT_TOO_CLOSE, 0
    # the new triangles take the cavity's slots, then two appended
    nv = cnt[C_NV]
    nt = cnt[C_NT]
    cavity[ncav] = nt
    cavity[ncav + 1] = nt + 1
    for a in range(3):
        mesh.xyz[nv, a] = p[a]
    for e in range(nb):
        s = cavity[e]
        a = horizon[e, 0]
        b = horizon[e, 1]
        u = horizon[e, 2]
        mesh.corners[s, 0] = a
        mesh.corners[s, 1] = b
        mesh.corners[s, 2] = nv
        mesh.neighbours[s, 2] = u
        mesh.neighbours[s, 0] = cavity[vnext[b]]  # across b-p: the new triangle from b
        mesh.gen[s] += 1
        mesh.star[a] = s
        for j in range(3):  # the outer triangle's edge b -> a now faces s
            if mesh.corners[u, j] != a and mesh.corners[u, j] != b:
                mesh.neighbours[u, j] = s
    for e in range(nb):  # across p-a: the new triangle that ends at a, whose edge's head is a
        s = cavity[e]
        mesh.neighbours[cavity[mesh_next(vnext, horizon, e)], 1] = s
    for e in range(nb):  # (marks need no reset: every insertion has a stamp of its own)
        set_circumcap(mesh, cavity[e])
    mesh.star[nv] = cavity[0]
    cnt[C_NV] = nv + 1
    cnt[C_NT] = nt + 2
    return nv, nb


@kernel(inline="always")
def mesh_next(vnext, horizon, e):
    """The boundary edge that follows edge e (it starts where e ends)."""
    return vnext[horizon[e, 1]]


@kernel(nrt=False)
def walk_star(v, mesh, scratch):
    """Round vertex v: (its neighbours' count nh, written to ``scratch.ids``; the slot of
    the star triangle with the largest circumcap, whose centre is v's farthest Voronoi
    vertex; that cap's squared chord, R(v) as a chord, v being one of its corners; the least
    squared chord from v to a neighbour). -1 for nh when the star outgrows ``ids``."""
    t = mesh.star[v]
    start = t
    ids = scratch.ids
    nh = 0
    far = t
    far2 = -1.0
    near2 = np.inf
    x = mesh.xyz[v]
    while True:
        i = corner_of(mesh, t, v)
        if nh >= ids.shape[0]:
            return -1, far, far2, near2
        w = mesh.corners[t, (i + 1) % 3]
        ids[nh] = w
        nh += 1
        d2 = 0.0
        for a in range(3):
            d2 += (mesh.xyz[w, a] - x[a]) ** 2
        near2 = min(near2, d2)
        c2 = mesh.chord2[t]
        if c2 > far2:
            far2 = c2
            far = t
        t = mesh.neighbours[t, (i + 1) % 3]
        if t == start:
            break
    return nh, far, far2, near2


@kernel(inline="always")
def locate_sphere(p, t, mesh, pts, nt, strict):
    """A triangle whose circumcap holds the unit vector p, walking from triangle t across
    the edges p lies beyond until none is left (p then lies in the triangle's cone, so its
    closed circumcap holds p). ``strict``: one whose open circumcap holds p (``visible``),
    scanning the nt triangles should the walk end on one that does not; -1 if none."""
    for _ in range(4 * nt + 16):
        if visible(mesh, t, p, pts):
            return t
        moved = False
        for j in range(3):
            a = mesh.corners[t, (j + 1) % 3]
            b = mesh.corners[t, (j + 2) % 3]
            for ax in range(3):
                pts[0, ax] = mesh.xyz[a, ax]
                pts[1, ax] = mesh.xyz[b, ax]
                pts[2, ax] = 0.0
                pts[3, ax] = p[ax]
            if orient3d(pts) > 0:  # p beyond the plane through a, b and the centre
                t = mesh.neighbours[t, j]
                moved = True
                break
        if not moved:
            if not strict:
                return t
            break
    for u in range(nt):
        if visible(mesh, u, p, pts):
            return u
    return -1


@kernel(entry=True, nrt=False)
def insert_points_sphere(points, mesh, scratch, cnt):
    """Insert unit vectors in order, each from a visible triangle found by walking from the
    last one made (for building a mesh from given vertices, as the tests do); returns the
    count inserted (it stops at the first refusal)."""
    seed = 0
    pts = scratch.points
    for i in range(points.shape[0]):
        p = points[i]
        found = locate_sphere(p, seed, mesh, pts, cnt[C_NT], True)
        if found < 0:
            return i
        v, nb = insert_sphere(p, found, mesh, scratch, cnt)
        if v < 0:
            return i
        seed = scratch.cavity[0]
    return points.shape[0]
