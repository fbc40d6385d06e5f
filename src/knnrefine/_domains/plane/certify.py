"""certify in the plane: check a mesh against Theorem 6, independently of the engine.

Nothing here calls the refinement kernels. The torus triangulation that came with the mesh is
first verified (so that its circumcircles and Voronoi vertices can be trusted): it must be a
triangulation of the torus (symmetric neighbours, F = 2V, Euler characteristic 0, positive
orientation, areas adding up to the torus) whose circumcircles hold no vertex, the latter
decided by certify's own filtered predicates (integers wherever floating point is not
conclusive). Distances and counts then come from certify's own kd-tree on the torus
(``certify._tree``).

Probes for the achieved constants alpha_hat = min and beta_hat = max of d_{M,2} / d_{P,k}
(``steps.Probes``: why these): every vertex and edge midpoint, the size integral's random
points in the cells, up to ``max_point_probes`` input points, and ``n_random`` uniform points
in the box. Only probes in the box count, and only where d_{P,k} >= min_size (the floor).
"""

import math

import numpy as np

from ..._engine.jit import kernel
from ..._engine.threads import in_chunks
from ..._metric import BoxMetric, TorusFrame
from ..._sampling import key_sample
from ...certify._predicates import UNSURE, exact_sign, incircle, orient2d
from ...certify._rows import as_index, as_offsets, row_classes
from ...certify._tree import Tree
from ...certify.common import (
    SizeSample,
    TorusGeometry,
    cell_array_problem,
    cell_counts,
    check_cells_tile,
    checked_points,  # noqa: F401  (the box domains' own)
    find_rows,
    gathered_probes,
    probe_parts,
    repeated_rows,
    size_integral,
    size_sample,
)
from ...certify.steps import Triangulation
from ...mesh import uniform_in_triangles


class Geometry(TorusGeometry):
    """The plane's questions about a mesh (``steps.run_checks`` asks them): its torus
    triangulation verified exactly, the returned triangles, circumdisks, probes, d_{M,2}
    from the torus' vertices, the size integral over the box. Lengths in input units,
    positions relative to the torus' origin with both axes wrapped."""

    def __init__(self, mesh, workers):
        super().__init__(mesh, workers)
        self.frame = BoxMetric((0.0, 0.0, *self.period), (True, True)).frame
        self.periodic = np.array(mesh.periodic, bool)

    def triangulation(self):
        """The torus triangulation (``verify_triangulation``), its circumcircles and each
        vertex's outradius R(v) (the largest circumradius around it); ``extra``: the
        triangles' signed areas."""
        t = self.mesh.torus
        problems, areas, centres, radii = verify_triangulation(
            self.vertices, t.triangles, t.offsets, t.neighbours, self.period, self.workers
        )
        outradii = np.zeros(len(self.vertices))
        for c in range(3):
            np.maximum.at(outradii, t.triangles[:, c], radii)
        return Triangulation(problems, centres, radii, outradii, areas)

    def returned_problems(self):
        return verify_returned_mesh(self.mesh)

    def in_box(self, x):
        return _in_box(x, self.lo, self.hi, self.periodic)

    def probes(self, tri, points, samples, n_random, max_point_probes, rng):
        """Every vertex and edge midpoint (once each), the size integral's random points
        in the cells (``common.size_sample``: ``samples`` of them, at least one in each
        cell sampled), up to min(``max_point_probes``, 2 m) input points and ``n_random``
        uniform points of the domain (``steps.Probes``: why these)."""
        t, m = len(tri.extra), len(self.vertices)
        chosen, dense = size_sample(t, samples, rng)
        cells = np.concatenate([chosen, dense])
        torus = self.mesh.torus
        corners = self.vertices[torus.triangles[cells]] + torus.offsets[cells] * self.period
        inside, _ = uniform_in_triangles(corners, rng.random((len(cells), 2)))
        del corners
        inside = self.frame(inside)
        areas = np.abs(tri.extra)
        s = len(chosen)
        count = min(int(max_point_probes), 2 * m)
        sampled = points.sample_points(count, rng)  # (drawn in this order: the probes')
        uniform = self.lo + rng.random((int(n_random), 2)) * (self.hi - self.lo)
        parts, rows = probe_parts(inside[:s], sampled, self.vertices, self.vertex_d_m2(),
                                  self.cells(tri), self.frame, uniform, self.period,
                                  self.workers, tri, inside[s:],
                                  torus.triangles[dense])  # fmt: skip
        return gathered_probes(parts, self.in_box,
                               SizeSample(None, areas[chosen], chosen, torus.triangles, areas, t),
                               3, rows)  # fmt: skip

    def returned_d_m2(self, x, tri):
        return self.torus_d_m2(x, tri), []

    def size(self, probes, d_pk, points, rng):
        """The integral of 1 / d_{P,k}^2 over the box (d_{P,k} clipped at min_size) and its
        standard error (``common.size_integral``): a point outside the box counts 0, and a
        triangle with a corner outside it is estimated whole."""
        return size_integral(probes.extra, d_pk, self.floor, 2)


class Points:
    """What every check reads of the input points in the plane: the points wrapped into
    the mesh's torus by the package's one rule, in certify's own kd-tree (``_tree.Tree``;
    weighted, the points of positive weight: the others hold nothing)."""

    def __init__(self, mesh, pts, weights, workers):
        self.k = mesh.k
        self.workers = workers
        self.period = np.asarray(mesh.torus.period, float)
        self.origin = np.asarray(mesh.torus.origin, float)
        self.input_frame = TorusFrame(self.origin, self.period)
        self.weighted = weights is not None
        self.n = len(pts)
        self.total = float(len(pts)) if weights is None else math.fsum(weights)
        self.source = pts  # (the caller's: not a copy)
        framed = self.input_frame(pts)  # (the tree's: sorted in place)
        heavy = None if weights is None else weights > 0
        # built beside the mesh's checks, which come first
        self.tree = Tree(framed if heavy is None else framed[heavy],
                         None if heavy is None else weights[heavy], self.period,
                         workers, background=True, scratch=True)  # fmt: skip

    def d_pk(self, x):
        """d_{P,k} at x (in the torus frame); weighted: the least radius holding weight k."""
        return self.tree.kth(x, self.k)

    def held(self, centres, radii, stop=np.inf):
        """What each closed disk (centre, radius) holds: its number of points, or their
        weight; exact below ``stop``."""
        return self.tree.held(centres, radii, stop)

    def fewer(self, centres, radii, k, mostly=True):
        """Whether each closed disk holds less than weight k (the torus: d_{P,k}'s)."""
        return self.tree.fewer(centres, radii, k, mostly=mostly)

    def cell_counts(self, cells, stop=np.inf):
        """What each closed Voronoi cell (``steps.Cells``) holds; exact below ``stop``."""
        return cell_counts(self.tree, cells, stop)

    def sample_points(self, count, rng):
        """About ``count`` input points, the same on every path (``_sampling``: those
        whose key is below count / n, as ``scale.checks``' strips draw them)."""
        return self.input_frame(key_sample(self.source, min(1.0, count / max(self.n, 1)))[0])


def verify_returned_mesh(mesh):
    """Problems (a list of strings) that stop ``mesh.vertices``, ``mesh.triangles`` and
    ``mesh.offsets`` (what the user works with) from being, exactly and without repeated
    vertices, copies of the torus mesh that certify checks, each once, tiling the box
    (``common.check_cells_tile``)."""
    torus = mesh.torus
    problems = []
    v = np.asarray(mesh.vertices, float)
    if v.ndim != 2 or v.shape[1] != 2 or not np.isfinite(v).all():
        return ["vertices are not finite (m, 2) coordinates"]
    repeated = repeated_rows(v)
    if repeated:
        problems.append(f"{repeated} repeated vertices")
    origin = np.asarray(torus.origin, float)
    period = np.asarray(torus.period, float)
    tv = np.asarray(torus.vertices, float)
    order = np.asarray(mesh.order)
    if len(order) != len(v) or order.min(initial=0) < 0 or order.max(initial=0) >= len(tv):
        return problems + ["vertex order does not index the torus vertices"]
    broken = cell_array_problem(mesh)
    if broken:
        return problems + [broken]
    tri, ttri = as_index(mesh.triangles), as_index(torus.triangles)
    as_torus = tri.shape == ttri.shape and np.array_equal(order[tri], ttri)
    if not (as_torus and np.all(mesh.periodic)):
        # (on a torus, triangles that are its own moved by whole periods, checked below,
        # tile it as its exactly verified triangulation does: no sort needed)
        problems += check_cells_tile(mesh)
    # each returned vertex is a torus vertex shifted by whole periods, exactly
    shift = np.rint((v - origin - tv[order]) / period)
    if np.any(v != origin + (tv[order] + shift * period)):
        bad = int(np.any(v != origin + (tv[order] + shift * period), axis=1).sum())
        problems.append(f"{bad} vertices differ from their torus vertex (rounded coordinates)")
    # each returned triangle is a torus triangle (same corners, same cyclic order) shifted by
    # whole periods
    off = np.zeros(tri.shape + (2,), np.int8) if mesh.offsets is None else _offsets(mesh.offsets)
    toff = _offsets(torus.offsets)
    if as_torus:
        # the torus' triangles, row for row, corners in the same order (a torus returned
        # as it is): each matches its own row, no rotation needed
        unmatched = 0
        pos = np.arange(len(tri))
        u_rot = t_rot = np.zeros(len(tri), np.int64)
    else:
        # match by the vertex triple in canonical rotation (smallest index first): in a
        # torus triangulation that is a simplicial complex a triple names one triangle
        t_rot = np.argmin(ttri, axis=1)
        u_rot = np.argmin(order[tri], axis=1) if len(tri) else np.zeros(0, np.int64)
        pos = find_rows(_rotate(ttri, t_rot), _rotate(order[tri], u_rot))
        unmatched = int((pos < 0).sum())
    moved = _triangles_moved(v, tri, off, np.array(mesh.period, float),
                             origin, tv, ttri, toff, period,
                             np.ascontiguousarray(pos, np.int64), u_rot.astype(np.int64),
                             t_rot.astype(np.int64))  # fmt: skip
    if unmatched:
        problems.append(f"{unmatched} triangles are not triangles of the torus mesh")
    if moved:
        problems.append(f"{moved} triangles have corners off their torus triangle")
    return problems


def _offsets(a):
    """Offsets as given to ``_triangles_moved``: integers as ``as_offsets`` keeps them, any
    others as float64 (a fraction of a period is a problem found, not rounded away)."""
    a = np.asarray(a)
    return as_offsets(a) if np.issubdtype(a.dtype, np.integer) else np.ascontiguousarray(a, float)


@kernel(entry=True, lazy=True)
def _triangles_moved(v, tri, off, user_period, origin, tv, ttri, toff, period, pos, u_rot,
                     t_rot):  # fmt: skip
    """How many returned triangles matched to a torus triangle (pos >= 0) do not have
    their corners (v + off user_period, from corner u_rot on) exactly at the torus
    triangle's (origin + tv + toff period, from corner t_rot on) moved by one whole number
    of periods along each axis, the same for every corner."""
    moved = 0
    shift = np.empty(2)
    for i in range(len(pos)):
        t = pos[i]
        if t < 0:
            continue
        ok = True
        for c in range(3):
            cu, ct = (c + u_rot[i]) % 3, (c + t_rot[t]) % 3
            for a in range(2):
                mine = v[tri[i, cu], a] + off[i, cu, a] * user_period[a]
                corner = tv[ttri[t, ct], a] + toff[t, ct, a] * period[a]
                d = np.rint((mine - (origin[a] + corner)) / period[a])
                if c == 0:
                    shift[a] = d
                elif d != shift[a]:
                    ok = False
                if mine != origin[a] + (corner + d * period[a]):
                    ok = False
        if not ok:
            moved += 1
    return moved


def _rotate(rows, r):
    """Each row (of 3 items) rotated left by r[i]."""
    idx = (np.arange(3)[None, :] + np.asarray(r)[:, None]) % 3
    return np.take_along_axis(rows, idx.reshape(idx.shape + (1,) * (rows.ndim - 2)), axis=1)


def verify_triangulation(vertices, triangles, offsets, neighbours, period, workers=None):
    """Problems (a list of strings, empty if none) that stop (triangles, offsets, neighbours)
    from being a Delaunay triangulation of the torus; also the triangles' signed areas, their
    circumcentres (wrapped into the domain) and circumradii (``_circles``: no (t, 3, 2)
    copy of the corners). ``workers``: threads for the local checks (None or -1: every
    core)."""
    problems = []
    m, t = len(vertices), len(triangles)
    vertices = np.ascontiguousarray(vertices, np.float64)
    period = np.ascontiguousarray(period, np.float64)
    tri, off, nb = as_index(triangles), as_offsets(offsets), as_index(neighbours)
    if t != 2 * m:
        problems.append(f"{t} triangles for {m} vertices (a torus has F = 2V)")
    if m and (np.bincount(tri.ravel(), minlength=m) == 0).any():
        problems.append("a vertex belongs to no triangle")
    if t and (nb.shape != tri.shape or nb.min() < 0 or nb.max() >= t):
        problems.append("neighbour links name triangles that do not exist")
        ccw_bad = not_delaunay = asymmetric = disagree = 0
        linked = False
    else:
        ccw_bad, not_delaunay, asymmetric, disagree = _local_checks(vertices, tri, off, nb,
                                                                    period, workers)  # fmt: skip
        linked = not asymmetric
    if asymmetric:
        problems.append(f"{asymmetric} neighbour links are not symmetric")
    if disagree:
        problems.append("neighbours disagree on the periodic offset of a shared edge")
    # the edges: each side's key, or where the links are symmetric (each side meets one
    # other, its twin) one key of each twin pair; a key met twice is one edge
    key = _edge_keys(tri, off, nb, linked)
    label = row_classes(key, key[:, 0].copy(), max(m, 1))
    n_edges = int((label == np.arange(len(key))).sum())
    del key, label
    if m - n_edges + t != 0:
        problems.append(f"Euler characteristic {m - n_edges + t} (a torus has 0)")
    area, centres, radii = np.empty(t), np.empty((t, 2)), np.empty(t)
    in_chunks(lambda a, b: _circles(vertices, tri, off, period, area, centres, radii, a, b), t,
              threads=workers, least=16384)  # fmt: skip
    if abs(area.sum() - period.prod()) > 1e-9 * period.prod():
        problems.append("the triangles do not tile the torus (areas do not add up)")
    centres = BoxMetric((0.0, 0.0, *period), (True, True)).frame(centres)
    if ccw_bad:
        problems.append(f"{ccw_bad} triangles are not counter-clockwise")
    if not_delaunay:
        problems.append(f"{not_delaunay} edges are not locally Delaunay (a vertex inside a "
                        "circumcircle)")  # fmt: skip
    return problems, area, centres, radii


@kernel(entry=True, lazy=True, nogil=True)
def _circles(vertices, tri, off, period, area, centres, radii, start, end):
    """For the triangles [start, end): the signed area, circumcentre (not wrapped) and
    circumradius of the corners vertices[tri] + off period, by ``mesh.triangle_areas``'
    and ``mesh.circumcircles``' formulas, operation for operation."""
    for f in range(start, end):
        ax = vertices[tri[f, 0], 0] + off[f, 0, 0] * period[0]
        ay = vertices[tri[f, 0], 1] + off[f, 0, 1] * period[1]
        bx = (vertices[tri[f, 1], 0] + off[f, 1, 0] * period[0]) - ax
        by = (vertices[tri[f, 1], 1] + off[f, 1, 1] * period[1]) - ay
        cx = (vertices[tri[f, 2], 0] + off[f, 2, 0] * period[0]) - ax
        cy = (vertices[tri[f, 2], 1] + off[f, 2, 1] * period[1]) - ay
        area[f] = 0.5 * (bx * cy - by * cx)
        d = 2.0 * (bx * cy - by * cx)
        b2 = bx * bx + by * by
        c2 = cx * cx + cy * cy
        ux = (cy * b2 - by * c2) / d
        uy = (bx * c2 - cx * b2) / d
        centres[f, 0] = ax + ux
        centres[f, 1] = ay + uy
        radii[f] = math.hypot(ux, uy)


@kernel(entry=True, lazy=True)
def _edge_keys(tri, off, nb, linked):
    """Each triangle side's key (lesser vertex, greater, the greater's offset less the
    lesser's per axis), for the edge opposite corner i of triangle f: an edge shared by two
    triangles has one key. Every side's, or where ``linked`` (each side's neighbour links
    back to it once) only the first of each twin pair's (f before its neighbour, or the
    lower side within one triangle): half the rows."""
    t = tri.shape[0]
    keep = np.ones(3 * t, np.bool_)
    if linked:
        for f in range(t):
            for i in range(3):
                n = nb[f, i]
                if n < f:
                    keep[3 * f + i] = False
                elif n == f:
                    a, b = tri[f, (i + 1) % 3], tri[f, (i + 2) % 3]
                    for j in range(3):
                        if nb[n, j] == f and tri[n, (j + 1) % 3] == b and tri[n, (j + 2) % 3] == a:
                            keep[3 * f + i] = i < j
    key = np.empty((keep.sum(), 4), np.int64)
    r = 0
    for f in range(t):
        for i in range(3):
            if not keep[3 * f + i]:
                continue
            j, k = (i + 1) % 3, (i + 2) % 3
            a, b = tri[f, j], tri[f, k]
            d0, d1 = off[f, k, 0] - off[f, j, 0], off[f, k, 1] - off[f, j, 1]
            if a > b:
                key[r, 0], key[r, 1], key[r, 2], key[r, 3] = b, a, -d0, -d1
            else:
                key[r, 0], key[r, 1], key[r, 2], key[r, 3] = a, b, d0, d1
            r += 1
    return key


@kernel(entry=True, lazy=True, nogil=True)
def _local_signs(vertices, tri, off, nb, period, orient, circle, start, end):
    """orient[f]: the sign of orient2d of triangle f's corners (UNSURE where the filter
    cannot tell); circle[f, i]: the sign of incircle of f's corners and the corner of its
    neighbour across edge i opposite that edge, placed by the edge's own offsets (3: no
    neighbour links back across that edge), for the triangles f in [start, end). Returns
    (the (triangle, edge) pairs whose neighbour does not link back exactly once, those
    whose neighbour puts the shared edge at other relative offsets)."""
    asymmetric = 0
    disagree = 0
    for f in range(start, end):
        ax = vertices[tri[f, 0], 0] + off[f, 0, 0] * period[0]
        ay = vertices[tri[f, 0], 1] + off[f, 0, 1] * period[1]
        bx = vertices[tri[f, 1], 0] + off[f, 1, 0] * period[0]
        by = vertices[tri[f, 1], 1] + off[f, 1, 1] * period[1]
        cx = vertices[tri[f, 2], 0] + off[f, 2, 0] * period[0]
        cy = vertices[tri[f, 2], 1] + off[f, 2, 1] * period[1]
        orient[f] = orient2d(ax, ay, bx, by, cx, cy)
        for i in range(3):
            n = nb[f, i]
            circle[f, i] = 3
            a, b = tri[f, (i + 1) % 3], tri[f, (i + 2) % 3]
            found = 0
            for j in range(3):
                if nb[n, j] == f and tri[n, (j + 1) % 3] == b and tri[n, (j + 2) % 3] == a:
                    found += 1
                    sx = off[f, (i + 1) % 3, 0] - off[n, (j + 2) % 3, 0]
                    sy = off[f, (i + 1) % 3, 1] - off[n, (j + 2) % 3, 1]
                    if (sx != off[f, (i + 2) % 3, 0] - off[n, (j + 1) % 3, 0]
                            or sy != off[f, (i + 2) % 3, 1] - off[n, (j + 1) % 3, 1]):  # fmt: skip
                        disagree += 1
                    if found == 1:
                        px = vertices[tri[n, j], 0] + (off[n, j, 0] + sx) * period[0]
                        py = vertices[tri[n, j], 1] + (off[n, j, 1] + sy) * period[1]
                        circle[f, i] = incircle(ax, ay, bx, by, cx, cy, px, py)
            if found != 1:
                asymmetric += 1
    return asymmetric, disagree


def _local_checks(vertices, tri, off, nb, period, workers=None):
    """(triangles not counter-clockwise, edge sides whose far corner lies inside the
    circumcircle, links not symmetric, offsets disagreeing), exactly: filtered predicates
    (``_local_signs``, on every core), integers only where the filter cannot tell. A
    triangulation of the torus (the links, Euler characteristic, orientation and area
    checks) whose every edge is locally Delaunay is Delaunay (the Delaunay lemma, on the
    periodic cover): its circumcircles hold no vertex."""
    t = len(tri)
    orient = np.empty(t, np.int8)
    circle = np.empty((t, 3), np.int8)
    args = (
        np.ascontiguousarray(vertices, np.float64), as_index(tri), as_offsets(off),
        as_index(nb), np.ascontiguousarray(period, np.float64), orient, circle,
    )  # fmt: skip
    parts = in_chunks(lambda a, b: _local_signs(*args, a, b), t, threads=workers, least=4096)
    asymmetric = sum(p[0] for p in parts)
    disagree = sum(p[1] for p in parts)
    corners = lambda f: vertices[tri[f]] + off[f] * period  # noqa: E731
    for f in np.flatnonzero(orient == UNSURE):
        orient[f] = exact_sign("orient2d", corners(f))
    for f, i in zip(*np.nonzero(circle == UNSURE), strict=True):
        n = nb[f, i]
        a, b = tri[f, (i + 1) % 3], tri[f, (i + 2) % 3]
        j = next(jj for jj in range(3) if nb[n, jj] == f and tri[n, (jj + 1) % 3] == b
                 and tri[n, (jj + 2) % 3] == a)  # fmt: skip
        shift = off[f, (i + 1) % 3] - off[n, (j + 2) % 3]
        p = vertices[tri[n, j]] + (off[n, j] + shift) * period
        circle[f, i] = exact_sign("incircle", np.vstack([corners(f), p]))
    return int((orient <= 0).sum()), int((circle == 1).sum()), asymmetric, disagree


def _in_box(x, lo, hi, per):
    """Mask of the points (wrapped into the torus) that lie in the box: periodic axes always,
    non-periodic axes within [lo, hi]."""
    ok = np.ones(len(x), bool)
    for a in range(2):
        if not per[a]:
            ok &= (x[:, a] >= lo[a]) & (x[:, a] <= hi[a])
    return ok
