"""d_{P,k} in the plane as linear pieces: exact values at a mesh's vertices and edge
midpoints (each triangle split in four), carried linearly over the triangles; located by a
kd-tree on the pieces' centroids, drawn into grids by the engine's rasteriser, integrated by
Dunavant's 7-point rule on triangles clipped to rectangles, and sampled by rejection
(``Pieces``). ``KnnDistance`` builds these for a mesh in the plane."""

import numpy as np
from scipy.spatial import cKDTree

from ..._engine.index import PointIndex
from ..._engine.raster import clip_triangles, fans, rasterise, walk_to, walk_values
from ..._engine.threads import in_chunks
from ...mesh import (
    TRIANGLE_RULE_POINTS,
    TRIANGLE_RULE_WEIGHTS,
    edges,
    split_in_four,
    triangle_areas,
    uniform_in_triangles,
)
from ..box import answerable, flat_radius, not_simplicial, points_of, to_frame  # noqa: F401


def index_of(mesh, pts, weights=None):
    """Exact d_{P,k} for the mesh's points: an index with ``kth(x, k)`` at points x in the
    box (input coordinates, periodic axes wrapped): the engine's counting index that refined
    the mesh when it indexes these points (and weights), else a new one over them (a box
    wide enough for them along non-periodic axes)."""
    kept = getattr(mesh, "index", None)
    if kept is not None and kept.indexes(pts, weights):
        return kept
    box = np.array(mesh.box, float)
    per = np.array(mesh.periodic, bool)
    if len(pts):
        box[:2] = np.where(per, box[:2], np.minimum(box[:2], pts.min(axis=0)))
        box[2:] = np.where(per, box[2:], np.maximum(box[2:], pts.max(axis=0)))
    return PointIndex.build(pts, tuple(box), mesh.periodic, weights)


def build(mesh, points, weights, subdivide):
    """What ``KnnDistance`` keeps of a mesh in the plane: (the points, the exact index, the
    pieces, the points' number or total weight)."""
    pts, weights, total = points_of(mesh, points, weights)
    index = index_of(mesh, pts, weights)
    nodes, triangles = mesh.covering()
    at_vertices, at_midpoints = index_values(index, mesh.k)
    nodes, triangles, values = linear_pieces(nodes, triangles, at_vertices, at_midpoints, subdivide)
    return pts, index, Pieces(nodes, triangles, values, mesh.box, mesh.periodic), total


def linear_pieces(nodes, triangles, vertex_values, midpoint_values, subdivide=True):
    """(nodes, pieces (t, 3), values): the linear pieces carrying d_{P,k} over a planar
    triangulation (nodes, triangles), exact at the nodes: ``vertex_values(nodes, near)``,
    ``near`` each node's shortest edge (a guess); with ``subdivide`` also at the edge
    midpoints, each triangle split in four: ``midpoint_values(mids, guess, low, high)``
    (``midpoints``). The four pieces of triangle t are t, t + T, t + 2T and t + 3T."""
    pairs, edge_of, length, near = node_guesses(nodes, triangles)
    values = vertex_values(nodes, near)
    if not subdivide:
        return nodes, triangles, values
    mids, guess, low, high = midpoints(nodes, pairs, length, values)
    found = midpoint_values(mids, guess, low, high)
    pieces = split_in_four(triangles, len(nodes), (pairs, edge_of))[2]
    return np.concatenate([nodes, mids]), pieces, np.concatenate([values, found])


def index_values(index, k):
    """(vertex_values, midpoint_values) for ``linear_pieces`` from the engine's counting
    index: exact d_{P,k} searched in a narrow window about the guess, widened where it
    misses (``PointIndex.kth``). At a node the guess is its shortest edge e (about
    d_{M,2}, which tracks d_{P,k} within [alpha, beta]): d_{P,k} / e has median 0.96 to 1.1
    and 5th to 95th percentiles 0.75 to 3 over tau in [2.5, 6], k in [10, 1000], uniform
    and clustered points."""

    def vertex_values(nodes, near):
        return index.kth(nodes, k, 0.94 * near, 1.06 * near)

    def midpoint_values(mids, guess, low, high):
        return index.kth(mids, k, 0.975 * guess, 1.025 * guess, low, high)

    return vertex_values, midpoint_values


def node_guesses(nodes, triangles):
    """(pairs, edge_of: ``edges(triangles)``; their lengths; each node's shortest edge, a
    guess of d_{P,k} there: ``index_values``)."""
    pairs, edge_of = edges(triangles)
    length = np.linalg.norm(nodes[pairs[:, 0]] - nodes[pairs[:, 1]], axis=1)
    near = np.full(len(nodes), np.inf)
    np.minimum.at(near, pairs[:, 0], length)
    np.minimum.at(near, pairs[:, 1], length)
    near[~np.isfinite(near)] = np.max(length) if len(length) else 1.0
    return pairs, edge_of, length, near


def midpoints(nodes, pairs, length, values):
    """(the edges' midpoints, a guess of d_{P,k} there, and bounds [low, high] on it) from
    its values at the ends. At a midpoint d_{P,k} is within a few percent of the mean of
    the ends' (on a multi-scale mixture half within 1.3%, 98% within 4%), and within half
    the edge of either end's (it is 1-Lipschitz)."""
    half = 0.5 * length
    da, db = values[pairs[:, 0]], values[pairs[:, 1]]
    mids = 0.5 * (nodes[pairs[:, 0]] + nodes[pairs[:, 1]])
    low = (np.maximum(da, db) - half) * (1 - 1e-9)
    high = (np.minimum(da, db) + half) * (1 + 1e-9)
    return mids, 0.5 * (da + db), low, high


class Pieces:
    """Linear pieces over the plane's box: ``nodes`` (p, 2), ``triangles`` (t, 3) and the
    node ``values``; points are located in ``located`` (pieces over the same nodes; default:
    ``triangles``). Coordinates are the box's, periodic axes wrapped into it."""

    dim = 2

    def __init__(self, nodes, triangles, values, box, periodic, located=None):
        self.nodes, self.triangles, self.values = nodes, triangles, values
        self.lo = np.array(box[:2], float)
        self.hi = np.array(box[2:], float)
        self.periodic = tuple(bool(p) for p in periodic)
        self._located = located

    def interpolate(self, x, values=None):
        """Node values (nodes, ...; default d_{P,k}'s) interpolated at the points x (q, 2), in
        the box: shape (q, ...), NaN where no piece holds a point (none expected)."""
        values = np.asarray(self.values if values is None else values, float)
        if values.ndim == 1 and len(x) and len(self._pieces()):  # one walk, no (q, 3) arrays
            return self._walk_values(x, values)
        tri, bary = self._locate(x)
        ok = tri >= 0
        pieces = self._pieces()
        if ok.all():  # (the usual case: no masked copies)
            ok, tri_ok, bary_ok = slice(None), tri, bary
        else:
            tri_ok, bary_ok = tri[ok], bary[ok]
        out = np.full((len(x), *values.shape[1:]), np.nan)
        if values.ndim == 1:  # d_{P,k} itself: three gathers, no (q, 3) temporaries
            out[ok] = sum(bary_ok[:, c] * values[pieces[tri_ok, c]] for c in range(3))
        else:
            out[ok] = np.einsum("qc,qc...->q...", bary_ok, values[pieces[tri_ok]])
        return out

    def grid(self, shape):
        """(xs, ys, values (ny, nx)) at the centres of a ny x nx grid over the box (NaN at a
        centre on no piece by rounding: the caller locates those)."""
        ny, nx = shape
        dx, dy = (self.hi - self.lo) / (nx, ny)
        xs = self.lo[0] + (np.arange(nx) + 0.5) * dx
        ys = self.lo[1] + (np.arange(ny) + 0.5) * dy
        out = np.full((ny, nx), np.nan)
        px, py = self.periodic
        rasterise(self.nodes, self.triangles, self.values, *self.lo, dx, dy, px, py, out, False)
        return xs, ys, out

    def integrate(self, func, rect):
        """Integral of func(d) over the rectangle rect = [[x0, y0], [x1, y1]] in the box."""
        return self._integrate_rect(func, rect)

    def sample(self, n, rng):
        """n points from the density proportional to 1 / d^2 over the box."""
        return sample_pieces(self.nodes, self.triangles, self.values, self.lo, self.hi, n, rng)

    def _pieces(self):
        return self.triangles if self._located is None else self._located

    def _integrate_rect(self, func, rect):
        c = self.nodes[self.triangles]
        d = self.values[self.triangles]
        # (numpy's reductions along short axes are slow: elementwise instead)
        cmin = np.minimum(np.minimum(c[:, 0], c[:, 1]), c[:, 2])
        cmax = np.maximum(np.maximum(c[:, 0], c[:, 1]), c[:, 2])
        within = (cmin >= rect[0]) & (cmax <= rect[1])
        meets = (cmax >= rect[0]) & (cmin <= rect[1])
        inside = within[:, 0] & within[:, 1]
        touch = meets[:, 0] & meets[:, 1] & ~inside
        total = quadrature(c[inside], d[inside], func).sum()
        if touch.any():
            corners, dv = fans(*clip_triangles(c[touch], d[touch], *rect[0], *rect[1]))
            total += quadrature(corners, dv, func).sum()
        return float(total)

    def _walk_values(self, x, values):
        """``interpolate`` of one value per node: each point's piece found by ``_locate``'s
        walk and its value interpolated there in one pass; the points the walk misses by
        ``_locate`` itself."""
        located = self._pieces()
        side = int(np.clip(2 * np.sqrt(len(x)), 64, 1024))
        start, dx, dy = self._id_raster(side)
        if not hasattr(self, "_neighbours"):
            self._neighbours = triangle_neighbours(located)
        qx, qy = np.ascontiguousarray(x[:, 0]), np.ascontiguousarray(x[:, 1])
        out = np.empty(len(x))
        in_chunks(
            lambda a, b: walk_values(self.nodes, located, self._neighbours, start, *self.lo, dx,
                                     dy, qx, qy, values, out, a, b),
            len(x),
        )  # fmt: skip
        lost = np.flatnonzero(np.isnan(out))
        if len(lost):
            tri, bary = self._locate(x[lost])
            ok = tri >= 0
            out[lost[ok]] = (bary[ok] * values[located[tri[ok]]]).sum(axis=1)
        return out

    def _locate(self, x):
        """The linear piece holding each point, and its barycentric coordinates (-1: none).

        A walk over the pieces (``engine.raster.walk_to``) from the piece a raster of piece
        indices names at the point's cell: the pieces are well shaped (bounded aspect,
        Theorem 6), so a walk takes a few steps where the raster's cells are no larger than
        the pieces, and about (cell / piece) where they are. What the walk misses (a cell
        named by no piece unwrapped, near a periodic seam) is located by ``_nearest``."""
        located = self._pieces()
        tri = np.full(len(x), -1, np.int64)
        bary = np.zeros((len(x), 3))
        if len(x) == 0 or len(located) == 0:
            return tri, bary
        side = int(np.clip(2 * np.sqrt(len(x)), 64, 1024))
        start, dx, dy = self._id_raster(side)
        if not hasattr(self, "_neighbours"):
            self._neighbours = triangle_neighbours(located)
        qx, qy = np.ascontiguousarray(x[:, 0]), np.ascontiguousarray(x[:, 1])
        in_chunks(
            lambda a, b: walk_to(self.nodes, located, self._neighbours, start, *self.lo, dx, dy,
                                 qx, qy, tri, bary, a, b),
            len(x),
        )  # fmt: skip
        lost = np.nonzero(tri < 0)[0]
        if len(lost):
            tri[lost], bary[lost] = self._nearest(x[lost])
        return tri, bary

    def _id_raster(self, side):
        """(raster (side, side) of the index of the piece holding each cell's centre, -1
        where none does unwrapped; its cell sides dx, dy), kept per side."""
        cache = self.__dict__.setdefault("_rasters", {})
        if side not in cache:
            dx, dy = (self.hi - self.lo) / side
            out = np.full((side, side), -1.0)
            empty = np.zeros(0)
            rasterise(self.nodes, self._pieces(), empty, *self.lo, dx, dy, False, False, out, True)
            cache[side] = (out, dx, dy)
        return cache[side]

    def _nearest(self, x):
        """``_locate`` by candidates: the piece holding x is among the few whose centroids are
        nearest to x (a kd-tree on centroids), for the points a walk did not place."""
        located = self._pieces()
        if not hasattr(self, "_centroids"):
            c = self.nodes[located]
            self._centroids = cKDTree(c.mean(axis=1))
            a = c[:, 0]
            e1 = c[:, 1] - a
            e2 = c[:, 2] - a
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            # rows of the inverse map from x - a to the barycentric coordinates (l1, l2)
            self._inv = (
                np.stack(
                    [np.stack([e2[:, 1], -e2[:, 0]], 1), np.stack([-e1[:, 1], e1[:, 0]], 1)], 1
                )
                / det[:, None, None]
            )
            self._origin = a
        tri = np.full(len(x), -1)
        bary = np.zeros((len(x), 3))
        todo = np.arange(len(x))
        for kk in (8, 64):
            if len(todo) == 0:
                break
            cand = self._centroids.query(x[todo], k=min(kk, len(located)), workers=-1)[1]
            cand = cand.reshape(len(todo), -1)
            rel = x[todo, None, :] - self._origin[cand]
            l12 = np.einsum("qcij,qcj->qci", self._inv[cand], rel)
            l0 = 1.0 - l12.sum(axis=2)
            inside = (l0 >= -1e-9) & (l12 >= -1e-9).all(axis=2)
            hit = inside.any(axis=1)
            first = np.argmax(inside, axis=1)
            rows = todo[hit]
            j = first[hit]
            tri[rows] = cand[hit, j]
            bary[rows, 0] = l0[hit, j]
            bary[rows, 1:] = l12[hit, j]
            todo = todo[~hit]
        return tri, bary


def triangle_neighbours(triangles):
    """(t, 3): the triangle across the edge opposite each corner, -1 where none (a side of
    the triangles, or an edge shared by more than two)."""
    t = len(triangles)
    edge_of = edges(triangles)[1].ravel()  # (t * 3,): edge of (triangle, corner)
    order = np.argsort(edge_of, kind="stable")
    e = edge_of[order]
    out = np.full(t * 3, -1, np.int64)
    pair = np.nonzero(e[1:] == e[:-1])[0]
    single = np.ones(len(pair), bool)  # an edge of exactly two triangles
    single &= (pair + 2 >= len(e)) | (e[np.minimum(pair + 2, len(e) - 1)] != e[pair])
    single &= (pair == 0) | (e[np.maximum(pair - 1, 0)] != e[pair])
    first, second = order[pair[single]], order[pair[single] + 1]
    out[first] = second // 3
    out[second] = first // 3
    return out.reshape(t, 3)


def sample_pieces(nodes, triangles, values, lo, hi, n, rng):
    """n points from the density proportional to 1 / d^2, d linear on the pieces (nodes,
    triangles, values), restricted to the box [lo, hi] (``KnnDensity.sample``)."""
    corners = nodes[triangles]
    d = values[triangles]
    area = np.abs(triangle_areas(corners))
    dmin = d.min(axis=1)  # d is linear on a piece: its density peaks at a corner
    bound = area / dmin**2
    cdf = np.cumsum(bound)
    out = np.empty((n, 2))
    filled = 0
    while filled < n:
        m = int(1.5 * (n - filled)) + 64
        t = np.minimum(np.searchsorted(cdf, rng.random(m) * cdf[-1], side="right"), len(cdf) - 1)
        x, u = uniform_in_triangles(corners, rng.random((m, 2)), t)
        dx = d[t, 0] * (1.0 - u[:, 0] - u[:, 1]) + d[t, 1] * u[:, 0] + d[t, 2] * u[:, 1]
        keep = rng.random(m) * dx**2 <= dmin[t] ** 2
        # pieces reach past the box; each point of the box lies in exactly one of them
        keep &= np.all((x >= lo) & (x <= hi), axis=1)
        x = x[keep][: n - filled]
        out[filled : filled + len(x)] = x
        filled += len(x)
    return out


def quadrature(corners, d, func):
    """Per triangle: integral of func(d) with d linear (values d at the corners)."""
    if len(corners) == 0:
        return np.zeros(0)
    area = np.abs(triangle_areas(corners))
    dq = d @ TRIANGLE_RULE_POINTS.T  # (t, 7): d at the quadrature points
    return area * (func(dq) @ TRIANGLE_RULE_WEIGHTS)


def complex_of(mesh, subdivide=True):
    """The mesh's cells as a complex (all of the torus' in periodic mode, as an abstract
    complex with positions in the box), subdivided in four through the edge midpoints:
    (positions, the same as nodes in the index's frame, the triangles). EngineError where
    it would not be simplicial (only on a torus a few cells across)."""
    corners = mesh.corners()
    tri = mesh.triangles.astype(np.int64)
    pairs, edge_of = edges(tri)
    # in a triangulated surface an edge borders two triangles (one on a boundary); a vertex
    # pair used more often means two different edges join it
    uses = np.bincount(edge_of.reshape(-1))
    if uses.max(initial=0) > 2 or (all(mesh.periodic) and np.any(uses != 2)):
        raise not_simplicial()
    if not subdivide:
        used = np.unique(tri)
        return mesh.vertices[used], mesh.vertices[used], np.searchsorted(used, tri)
    # midpoints of the geometric edges (offsets applied: across the seam where need be)
    pairs, edge_of, tri = split_in_four(tri, len(mesh.vertices))
    mid_pos = np.zeros((len(pairs), 2))
    for corner in range(3):
        a, b = (corner + 1) % 3, (corner + 2) % 3
        mid_pos[edge_of[:, corner]] = 0.5 * (corners[:, a] + corners[:, b])
    positions = np.concatenate([mesh.vertices, to_frame(mesh)(mid_pos)])
    used = np.unique(tri)  # drop the vertices of triangles left out (non-periodic mode)
    return positions[used], positions[used], np.searchsorted(used, tri)
