"""certify in the plane: check a mesh against Theorem 6, independently of the engine.

Nothing here calls the refinement kernels. The torus triangulation that came with the mesh is
first verified (so that its circumcircles and Voronoi vertices can be trusted): it must be a
triangulation of the torus (symmetric neighbours, F = 2V, Euler characteristic 0, positive
orientation, areas adding up to the torus) whose circumcircles hold no vertex, the latter
decided in exact rational arithmetic wherever floating point is not conclusive. Distances and
counts then come from scipy's cKDTree (``boxsize`` on the torus).

Probes for the achieved constants alpha_hat = min and beta_hat = max of d_{M,2} / d_{P,k}: all
mesh vertices, all circumcenters and all edge midpoints (where d_{M,2} has its local extremes),
up to ``max_point_probes`` input points drawn at random, and ``n_random`` uniform points in the
box. Only probes in the box count, and only where d_{P,k} >= min_size (the floor).
"""

import math
from fractions import Fraction

import numpy as np
from scipy.spatial import cKDTree

from ..._metric import BoxMetric, TorusFrame, cell_tally, held_in_balls, weight_tree, weighted_kth
from ...certify.common import (
    TorusGeometry,
    cell_array_problem,
    check_cells_tile,
    checked_points,  # noqa: F401  (the box domains' own)
    find_rows,
    sorted_rows,
)
from ...certify.steps import Probes, Triangulation
from ...mesh import circumcircles, triangle_areas, uniform_in_triangles


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
        triangles' corners."""
        t = self.mesh.torus
        problems, corners, centres, radii = verify_triangulation(
            self.vertices, t.triangles, t.offsets, t.neighbours, self.period
        )
        outradii = np.zeros(len(self.vertices))
        for c in range(3):
            np.maximum.at(outradii, t.triangles[:, c], radii)
        return Triangulation(problems, centres, radii, outradii, corners)

    def returned_problems(self):
        return verify_returned_mesh(self.mesh)

    def in_box(self, x):
        return _in_box(x, self.lo, self.hi, self.periodic)

    def probes(self, tri, points, samples, n_random, max_point_probes, rng):
        """Stratified samples inside every triangle (with their area weights: the Monte
        Carlo samples of the size integral), input points, and the vertices,
        circumcentres, edge midpoints and uniform points of the box; those in the box."""
        corners = tri.extra
        per_triangle = max(4, -(-samples // max(len(corners), 1)))
        inside, weights = _triangle_samples(corners, per_triangle, rng)
        inside = self.frame(inside)
        sampled = points.sample_points(max_point_probes, rng)
        mids = 0.5 * (corners + corners[:, [1, 2, 0]]).reshape(-1, 2)
        others = np.concatenate(
            [
                self.vertices,
                tri.centres,
                self.frame(mids),
                self.lo + rng.random((n_random, 2)) * (self.hi - self.lo),
            ]
        )
        in_box = self.in_box(inside)
        sampled = sampled[self.in_box(sampled)]
        others = others[self.in_box(others)]
        x = np.concatenate([inside[in_box], sampled, others])
        mask = np.zeros(len(x), bool)
        n_in = int(in_box.sum())
        mask[n_in : n_in + len(sampled)] = True
        return Probes(x, mask, (in_box, weights, len(corners)))

    def returned_d_m2(self, x):
        return self.vertex_tree.query(x, k=2, workers=self.workers)[0][:, 1], []

    def size(self, probes, d_pk, points, rng):
        """The integral of 1 / d_{P,k}^2 over the box (d_{P,k} clipped at min_size),
        stratified over the triangles: each sample weighted by its share of its
        triangle's area, samples outside the box counting 0; with its standard error."""
        in_box, weights, triangles = probes.extra
        f = np.zeros(len(in_box))
        f[in_box] = 1.0 / np.maximum(d_pk[: int(in_box.sum())], self.floor) ** 2
        per_triangle = (weights * f).reshape(triangles, -1)
        integral = float(per_triangle.sum())
        var = (
            (per_triangle.var(axis=1, ddof=1) * per_triangle.shape[1]).sum()
            if per_triangle.shape[1] > 1
            else 0.0
        )
        return integral, float(np.sqrt(var))


class Points:
    """What every check reads of the input points in the plane: the points wrapped into
    the mesh's torus by the package's one rule, and a kd-tree over them."""

    def __init__(self, mesh, pts, weights, workers):
        self.k = mesh.k
        self.workers = workers
        self.period = np.asarray(mesh.torus.period, float)
        self.origin = np.asarray(mesh.torus.origin, float)
        self.input_frame = TorusFrame(self.origin, self.period)
        self.weights = weights
        self.weighted = weights is not None
        self.n = len(pts)
        self.total = float(len(pts)) if weights is None else math.fsum(weights)
        self.points = self.input_frame(pts)
        self.point_tree = cKDTree(self.points, boxsize=self.period)
        self._weight_tree = None

    def _weights(self):
        if self._weight_tree is None and self.weights is not None:
            self._weight_tree = weight_tree(self.point_tree, self.weights)
        return self._weight_tree

    def d_pk(self, x):
        """d_{P,k} at x (in the torus frame); weighted: the least radius holding weight k."""
        if self.weights is None:
            return self.point_tree.query(x, k=[self.k], workers=self.workers)[0][:, 0]
        return weighted_kth(self.point_tree, self._weights(), x, self.k, self.workers)

    def held(self, centres, radii):
        """What each closed disk (centre, radius) holds: its number of points, or their
        weight."""
        return held_in_balls(self.point_tree, self._weights(), centres, radii, self.workers)

    def cell_counts(self, vertices, outradii):
        """What each vertex's closed Voronoi cell holds (points equidistant to several
        vertices count for each)."""
        tree = cKDTree(vertices, boxsize=self.period)
        dd, ii = tree.query(self.points, k=min(3, len(vertices)), workers=self.workers)
        return cell_tally(dd, ii, self.weights, len(vertices))

    def sample_points(self, count, rng):
        """Up to ``count`` input points, drawn at random."""
        P = self.points
        return P if len(P) <= count else P[rng.choice(len(P), count, False)]


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
    repeated = len(v) - len(np.unique(v, axis=0))
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
    problems += check_cells_tile(mesh)
    # each returned vertex is a torus vertex shifted by whole periods, exactly
    shift = np.rint((v - origin - tv[order]) / period)
    if np.any(v != origin + (tv[order] + shift * period)):
        bad = int(np.any(v != origin + (tv[order] + shift * period), axis=1).sum())
        problems.append(f"{bad} vertices differ from their torus vertex (rounded coordinates)")
    # each returned triangle is a torus triangle (same corners, same cyclic order) shifted by
    # whole periods
    tri = np.asarray(mesh.triangles, np.int64)
    off = np.zeros(tri.shape + (2,)) if mesh.offsets is None else np.asarray(mesh.offsets, float)
    user_corners = v[tri] + off * np.array(mesh.period, float)
    ttri = np.asarray(torus.triangles, np.int64)
    tcorners = tv[ttri] + np.asarray(torus.offsets, float) * period
    # match by the vertex triple in canonical rotation (smallest index first): in a torus
    # triangulation that is a simplicial complex a triple names one triangle
    t_rot = np.argmin(ttri, axis=1)
    u_rot = np.argmin(order[tri], axis=1) if len(tri) else np.zeros(0, np.int64)
    t_key = _rotate(ttri, t_rot)
    u_key = _rotate(order[tri], u_rot)
    pos = find_rows(t_key, u_key)
    unmatched = int((pos < 0).sum())
    hit = pos >= 0
    t = pos[hit]
    target = origin + _rotate(tcorners[t], t_rot[t])
    mine = _rotate(user_corners[hit], u_rot[hit])
    d = np.rint((mine - target) / period)
    same_shift = np.all(d == d[:, :1], axis=(1, 2))
    exact = np.all(mine == origin + (_rotate(tcorners[t], t_rot[t]) + d * period), axis=(1, 2))
    moved = int((~(same_shift & exact)).sum())
    if unmatched:
        problems.append(f"{unmatched} triangles are not triangles of the torus mesh")
    if moved:
        problems.append(f"{moved} triangles have corners off their torus triangle")
    return problems


def _rotate(rows, r):
    """Each row (of 3 items) rotated left by r[i]."""
    idx = (np.arange(3)[None, :] + np.asarray(r)[:, None]) % 3
    return np.take_along_axis(rows, idx.reshape(idx.shape + (1,) * (rows.ndim - 2)), axis=1)


def verify_triangulation(vertices, triangles, offsets, neighbours, period):
    """Problems (a list of strings, empty if none) that stop (triangles, offsets, neighbours)
    from being a Delaunay triangulation of the torus; also the realised corners, circumcenters
    (wrapped into the domain) and circumradii."""
    problems = []
    m, t = len(vertices), len(triangles)
    tri = np.asarray(triangles)
    off = np.asarray(offsets, np.int64)
    nb = np.asarray(neighbours)
    if t != 2 * m:
        problems.append(f"{t} triangles for {m} vertices (a torus has F = 2V)")
    if not np.all(np.isin(np.arange(m), tri)):
        problems.append("a vertex belongs to no triangle")
    f = np.repeat(np.arange(t), 3)
    i = np.tile(np.arange(3), t)
    a = tri[f, (i + 1) % 3]
    b = tri[f, (i + 2) % 3]
    n = nb[f, i]
    found = np.zeros(len(f), int)
    same_edge = np.ones(len(f), bool)
    for j in range(3):
        hit = (nb[n, j] == f) & (tri[n, (j + 1) % 3] == b) & (tri[n, (j + 2) % 3] == a)
        found += hit
        da = off[f, (i + 1) % 3] - off[n, (j + 2) % 3]
        db = off[f, (i + 2) % 3] - off[n, (j + 1) % 3]
        same_edge &= ~hit | np.all(da == db, axis=1)
    if np.any(found != 1):
        problems.append(f"{int((found != 1).sum())} neighbour links are not symmetric")
    if not np.all(same_edge):
        problems.append("neighbours disagree on the periodic offset of a shared edge")
    d = off[f, (i + 2) % 3] - off[f, (i + 1) % 3]
    flip = a > b
    key = np.stack(
        [
            np.where(flip, b, a),
            np.where(flip, a, b),
            np.where(flip, -d[:, 0], d[:, 0]),
            np.where(flip, -d[:, 1], d[:, 1]),
        ],
        1,
    )
    _, repeats = sorted_rows(key)
    n_edges = len(key) - int(repeats.sum()) if len(key) else 0
    if m - n_edges + t != 0:
        problems.append(f"Euler characteristic {m - n_edges + t} (a torus has 0)")
    corners = vertices[tri] + off * period
    area = triangle_areas(corners)
    if np.any(area <= 0):
        problems.append(f"{int((area <= 0).sum())} triangles are not counter-clockwise")
    if abs(area.sum() - period.prod()) > 1e-9 * period.prod():
        problems.append("the triangles do not tile the torus (areas do not add up)")
    cc, r = circumcircles(corners)
    ccw = BoxMetric((0.0, 0.0, *period), (True, True)).frame(cc)
    # empty circles: floating point finds the vertices near each circle, rationals decide.
    # A circle whose 4th nearest vertex lies beyond the reach holds only its 3 corners
    # there (distinct corners lie within it): only the others are listed, by a ball query
    face, cand = _near_circles(cKDTree(vertices, boxsize=period), tri, ccw,
                               r * (1 + 1e-6) + 1e-9 * r.max())  # fmt: skip
    other = (cand != tri[face, 0]) & (cand != tri[face, 1]) & (cand != tri[face, 2])
    inside = 0
    for f_, v in zip(face[other], cand[other], strict=True):
        p = vertices[v] + np.round((cc[f_] - vertices[v]) / period) * period
        if _incircle_exact(corners[f_], p) > 0:
            inside += 1
    if inside:
        problems.append(f"{inside} circumcircles hold a vertex (not Delaunay)")
    return problems, corners, ccw, r


def _near_circles(tree, tri, centres, reach):
    """(triangle, vertex) pairs with the vertex within ``reach`` of the triangle's
    circumcentre (the tree's metric): a 4-nearest query for every circle, a ball query only
    for those whose 4th nearest vertex is within reach or whose corners repeat a vertex."""
    t = len(tri)
    if t == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    k = min(4, tree.n)
    d4 = tree.query(centres, k=[k], workers=-1)[0][:, 0]
    repeated = (tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])
    listed = np.flatnonzero((d4 <= reach) | repeated | (k < 4))
    near = tree.query_ball_point(centres[listed], reach[listed]) if len(listed) else []
    sizes = np.fromiter((len(c) for c in near), np.int64, len(near))
    if not sizes.sum():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cand = np.concatenate([np.asarray(c, np.int64) for c in near])
    face = np.repeat(listed, sizes)
    return face, cand


def _incircle_exact(c, d):
    (ax, ay), (bx, by), (cx, cy) = ((Fraction(float(u)), Fraction(float(w))) for u, w in c)
    dx, dy = Fraction(float(d[0])), Fraction(float(d[1]))
    adx, ady, bdx, bdy, cdx, cdy = ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy
    det = (
        (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
    )
    return (det > 0) - (det < 0)


def _in_box(x, lo, hi, per):
    """Mask of the points (wrapped into the torus) that lie in the box: periodic axes always,
    non-periodic axes within [lo, hi]."""
    ok = np.ones(len(x), bool)
    for a in range(2):
        if not per[a]:
            ok &= (x[:, a] >= lo[a]) & (x[:, a] <= hi[a])
    return ok


def _triangle_samples(corners, per_triangle, rng):
    """per_triangle uniform points in every triangle (triangle-major order) and the weight of
    each: its triangle's area / per_triangle, so that sum(weight * f) estimates the integral
    of f. The mesh is graded like d_{P,k}, so samples are dense where d_{P,k} is small."""
    x, _ = uniform_in_triangles(corners[:, None], rng.random((len(corners), per_triangle, 2)))
    area = np.abs(triangle_areas(corners))
    return x.reshape(-1, 2), np.repeat(area / per_triangle, per_triangle)
