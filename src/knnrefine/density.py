"""The k-th-nearest-neighbour distance everywhere, and the kNN density estimate, from a mesh.

The mesh is graded like d_{P,k} (Theorem 6), so a few exact evaluations per triangle carry
d_{P,k} across the whole box: exact values at the vertices and edge midpoints (each triangle
split in four), one kd-tree query for about 4 m nodes instead of one per query point, then
linear interpolation. The density estimate is ``f(x) = k / (n pi d_{P,k}(x)^2)``, normalised by
its integral over the box; integrals over the box or any rectangle are exact quadratures of
the interpolated d over the triangles, clipped to the rectangle.
"""

import inspect

import numpy as np
from scipy.spatial import cKDTree

from .engine.embedding import wrap_offsets
from .engine.index import PointIndex
from .engine.kernelsum import (
    AMP,
    Q11,
    Q12,
    Q22,
    ROW,
    R,
    W,
    X,
    Y,
    ball_moments,
    build_centres,
    kernel_sums,
    node_extents,
)
from .engine.raster import clip_triangles, fans, rasterise
from .engine.threads import in_chunks
from .errors import InputError
from .mesh import edges, split_in_four, triangle_areas, uniform_in_triangles
from .metric import BoxMetric
from .validation import as_points, as_queries, check_weights, default_box, weights_of_run

# Dunavant's 7-point rule (degree 5) on the reference triangle: barycentric points, weights
_QW = np.array([0.225, *[0.132394152788506] * 3, *[0.125939180544827] * 3])
_a, _b = 0.059715871789770, 0.470142064105115
_c, _d = 0.797426985353087, 0.101286507323456
_QP = np.array(
    [
        [1 / 3, 1 / 3, 1 / 3],
        [_a, _b, _b],
        [_b, _a, _b],
        [_b, _b, _a],
        [_c, _d, _d],
        [_d, _c, _d],
        [_d, _d, _c],
    ]
)


def default_k(n):
    """A default k for density estimation from n points: sqrt(n) / 2 (at least 10, at most
    n: on 5 points, 5), after the paper's k ~ sqrt(n) (k / n -> 0 and k / log n ->
    infinity)."""
    return min(max(10, int(round(0.5 * np.sqrt(n)))), max(1, int(n)))


def default_pilot_k(n):
    """The default k of the adaptive estimate's pilot: 2 sqrt(n) (at least 10, at most n,
    the points' number or total weight: k counts weight). A smoother
    pilot than the kNN estimate's own default: with the bandwidth and sensitivity chosen by
    leave-one-out likelihood, 2 sqrt(n) had lower L1 error than sqrt(n) / 2 on five of the
    study's six truths at n = 1e4 and all six at 1e5, and a held-out likelihood as good or
    better on five and six (``benchmarks/pilot_k.py``, docs/uses.md)."""
    return min(max(10, int(round(2.0 * np.sqrt(n)))), int(n))


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


class KnnDistance:
    """d_{P,k} at any point of the box, from a mesh of P and P itself.

    Parameters
    ----------
    mesh : Mesh
        From ``knnrefine.refine(points, k, ...)``; its k is the one estimated.
    points : array-like (n, 2)
        The same points.
    subdivide : bool
        Also evaluate at edge midpoints (four linear pieces per triangle): about half the
        interpolation error for four times the (cheap) exact evaluations.
    weights : array-like (n,), optional
        The weights the mesh was refined with (required for a weighted mesh, refused for
        another): d_{P,k} is then the least radius holding weight k.

    Outside the box (along a non-periodic axis, beyond any of its four sides) the estimate is
    NaN: d_{P,k} is certified only in the box; periodic axes wrap. Queries have any shape
    (..., 2) and the result the leading shape (...).
    """

    def __init__(self, mesh, points, subdivide=True, weights=None):
        pts = as_points(points)
        weights = weights_of_run(mesh.stats, len(pts), weights)
        total = len(pts) if weights is None else float(weights.sum())
        if total < mesh.k:
            what = f"{len(pts)} points" if weights is None else f"a total weight of {total:.6g}"
            raise InputError(f"{what} but k = {mesh.k}: d_Pk is infinite")
        self._frame(mesh, len(pts), total)
        self._points = pts
        self.index = self._point_index(mesh, pts, weights)
        nodes, triangles = mesh.covering()
        self.nodes, self.triangles, self.values = linear_pieces(
            nodes, triangles, *index_values(self.index, self.k), subdivide
        )

    def _frame(self, mesh, n, total):
        self.mesh = mesh
        self.k = mesh.k
        self.n = n
        self.total = total  # the points' number, or their total weight
        self.lo = np.array(mesh.box[:2], float)
        self.hi = np.array(mesh.box[2:], float)
        self._metric = BoxMetric(mesh.box, mesh.periodic)
        self._located = None  # the pieces points are located in (None: all of them)

    @classmethod
    def of_pieces(cls, mesh, n, total, nodes, triangles, values, located=None):
        """A KnnDistance from linear pieces whose node values are known already (a part of
        a partitioned mesh, ``partitioned.PartitionedDensity``): evaluation, grids and
        integrals over ``triangles``; points located in ``located`` (pieces over the same
        nodes; default: ``triangles``). Without the points, no ``exact``."""
        self = cls.__new__(cls)
        self._frame(mesh, n, total)
        self._points = self.index = None
        self.nodes, self.triangles, self.values = nodes, triangles, values
        self._located = located
        return self

    @staticmethod
    def _point_index(mesh, pts, weights):
        """The engine's index that refined the mesh when it indexes these points (and
        weights), else a new one over them (a box wide enough for them along non-periodic
        axes)."""
        kept = getattr(mesh, "index", None)
        if kept is not None and kept.indexes(pts, weights):
            return kept
        box = np.array(mesh.box, float)
        per = np.array(mesh.periodic, bool)
        if len(pts):
            box[:2] = np.where(per, box[:2], np.minimum(box[:2], pts.min(axis=0)))
            box[2:] = np.where(per, box[2:], np.maximum(box[2:], pts.max(axis=0)))
        return PointIndex.build(pts, tuple(box), mesh.periodic, weights)

    # -- evaluation ------------------------------------------------------------------------
    def __call__(self, x):
        """Estimated d_{P,k} at the query points x, shape (..., 2): an array of shape (...).
        NaN outside the box along non-periodic axes (on every side); periodic axes wrap."""
        flat, shape = as_queries(x)
        return self.interpolate(flat, self.values).reshape(shape)

    def interpolate(self, x, values):
        """Any node values (nodes, ...) linearly interpolated over the pieces at the points
        x (q, 2): shape (q, ...), NaN outside the box along non-periodic axes."""
        values = np.asarray(values, float)
        inside = self._inside(x)
        out = np.full((len(x), *values.shape[1:]), np.nan)
        tri, bary = self._locate(self._wrap(x[inside]))
        ok = tri >= 0
        found = np.full((int(inside.sum()), *values.shape[1:]), np.nan)
        corner = values[self._pieces()[tri[ok]]]  # (q, 3, ...)
        found[ok] = np.einsum("qc,qc...->q...", bary[ok], corner)
        out[inside] = found
        return out

    def exact(self, x):
        """Exact d_{P,k} at the query points (..., 2), one kd-tree query each (the reference);
        NaN outside the box along non-periodic axes, as the estimate."""
        flat, shape = as_queries(x)
        out = np.full(len(flat), np.nan)
        inside = self._inside(flat)
        out[inside] = self._exact(self._wrap(flat[inside]))
        return out.reshape(shape)

    def grid(self, shape=(512, 512)):
        """(xs, ys, values): the estimate at the centres of a ny x nx grid over the box, values
        of shape (ny, nx), row j at ys[j] (image order, origin at the lower left)."""
        ny, nx = _grid_shape(shape)
        dx, dy = (self.hi - self.lo) / (nx, ny)
        xs = self.lo[0] + (np.arange(nx) + 0.5) * dx
        ys = self.lo[1] + (np.arange(ny) + 0.5) * dy
        out = np.full((ny, nx), np.nan)
        px, py = (bool(p) for p in self.mesh.periodic)
        rasterise(self.nodes, self.triangles, self.values, *self.lo, dx, dy, px, py, out)
        missed = np.isnan(out)  # centres on no piece by rounding (none expected): located
        if missed.any():
            jj, ii = np.nonzero(missed)
            out[jj, ii] = self(np.column_stack([xs[ii], ys[jj]]))
        return xs, ys, out

    def error(self, probes=None, n_random=20000, seed=0):
        """Relative error of the estimate against exact d_{P,k}: a dict with the median, the
        99th percentile and the worst over the probes (default: random points of the box and
        as many input points)."""
        if probes is None:
            rng = np.random.default_rng(seed)
            uniform = self.lo + rng.random((n_random, 2)) * (self.hi - self.lo)
            data = self._points[rng.choice(self.n, min(n_random, self.n), replace=False)]
            probes = np.concatenate([uniform, data])
        est = self(probes)
        ref = self.exact(probes)
        rel = np.abs(est - ref) / ref
        return {
            "median": float(np.nanmedian(rel)),
            "p99": float(np.nanpercentile(rel, 99)),
            "worst": float(np.nanmax(rel)),
            "probes": int(np.isfinite(rel).sum()),
        }

    # -- integrals ---------------------------------------------------------------------------
    def integrate(self, func, region=None):
        """Integral over ``region`` = (x0, y0, x1, y1) (default: the box) of func(d), d the
        interpolated d_{P,k}: 7-point quadrature on every linear piece, the pieces clipped to
        the region. The region counts only where it meets the box along non-periodic axes
        (the estimate lives there); along periodic axes it wraps around (at most one period
        wide)."""
        return float(sum(self._integrate_rect(func, rect) for rect in self._region(region)))

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
        total = _quadrature(c[inside], d[inside], func).sum()
        if touch.any():
            corners, dv = fans(*clip_triangles(c[touch], d[touch], *rect[0], *rect[1]))
            total += _quadrature(corners, dv, func).sum()
        return float(total)

    # -- helpers -----------------------------------------------------------------------------
    def _locate(self, x):
        """The linear piece holding each point, and its barycentric coordinates (-1: none).

        The pieces are well shaped (bounded aspect, Theorem 6), so the one holding x is among
        the few whose centroids are nearest to x: a kd-tree on centroids finds it."""
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

    def sample_pieces(self, n, rng):
        """n points from the density proportional to 1 / d^2 over the box (``KnnDensity``)."""
        return sample_pieces(self.nodes, self.triangles, self.values, self.lo, self.hi, n, rng)

    def _pieces(self):
        return self.triangles if self._located is None else self._located

    def _wrap(self, x):
        return self._metric.wrap(x)

    def _inside(self, x):
        """Mask of the points in the box along its non-periodic axes (sides included)."""
        ok = np.all(np.isfinite(x), axis=1)
        for a in range(2):
            if not self.mesh.periodic[a]:
                ok &= (x[:, a] >= self.lo[a]) & (x[:, a] <= self.hi[a])
        return ok

    def _exact(self, x):
        if self.index is None:
            raise InputError(
                "this d_Pk was built from node values alone (a part of a partitioned mesh): "
                "exact values need the points; build KnnDistance(mesh, points)"
            )
        return self.index.kth(x, self.k)

    def _region(self, region):
        """The rectangles, inside the box, that make up ``region``: clipped along non-periodic
        axes, cut at the seam and wrapped along periodic ones."""
        if region is None:
            return [np.array([self.lo, self.hi])]
        try:
            x0, y0, x1, y1 = (float(r) for r in region)
        except (TypeError, ValueError):
            raise InputError(
                f"region must be four numbers (x0, y0, x1, y1), got {region!r}"
            ) from None
        if not (np.isfinite([x0, y0, x1, y1]).all() and x0 < x1 and y0 < y1):
            raise InputError(f"region {region} must be finite with x0 < x1 and y0 < y1")
        spans = []
        for a, (u0, u1) in enumerate(((x0, x1), (y0, y1))):
            lo, hi = self.lo[a], self.hi[a]
            if not self.mesh.periodic[a]:
                spans.append([(max(u0, lo), min(u1, hi))] if u1 > lo and u0 < hi else [])
                continue
            period = hi - lo
            if u1 - u0 >= period * (1 - 1e-12):
                spans.append([(lo, hi)])
                continue
            s0 = lo + float(wrap_offsets(np.array([u0]), lo, period)[0])
            s1 = s0 + (u1 - u0)
            spans.append([(s0, min(s1, hi))] + ([(lo, lo + s1 - hi)] if s1 > hi else []))
        return [
            np.array([[ax0, ay0], [ax1, ay1]])
            for ax0, ax1 in spans[0]
            for ay0, ay1 in spans[1]
            if ax1 > ax0 and ay1 > ay0
        ]


class KnnDensity:
    """The kNN density estimate f(x) = k / (n pi d_{P,k}(x)^2), from a mesh.

    ``normalized`` (default) divides by its integral over the box, so that it integrates to
    1 there. Evaluate with ``density(x)`` (x of shape (..., 2); NaN outside the box along
    non-periodic axes), on a grid with ``grid()``, and integrate over a rectangle with
    ``mass(region)``. ``subdivide``, ``weights``: see ``KnnDistance``; with weights n is
    their total, so that a weighted point is that many points.
    """

    def __init__(self, mesh, points, normalized=True, subdivide=True, weights=None):
        self._of(KnnDistance(mesh, points, subdivide=subdivide, weights=weights), normalized)

    @classmethod
    def of_distance(cls, distance, normalized=True):
        """The estimate from a d_{P,k} already built: a ``KnnDistance`` or anything with its
        ``k``, ``total``, ``__call__``, ``grid``, ``integrate`` and ``sample_pieces``
        (``partitioned.PartitionedDistance``)."""
        self = cls.__new__(cls)
        self._of(distance, normalized)
        return self

    def _of(self, distance, normalized):
        self.distance = distance
        self.k = distance.k
        self.n = distance.total
        self.raw_constant = self.k / (self.n * np.pi)
        self.raw_mass = distance.integrate(lambda d: self.raw_constant / d**2)
        self.constant = self.raw_constant / self.raw_mass if normalized else self.raw_constant

    def __call__(self, x):
        """The density at the query points x, shape (..., 2): an array of shape (...)."""
        return self.constant / self.distance(x) ** 2

    def grid(self, shape=(512, 512)):
        """(xs, ys, values): the density at the centres of a ny x nx grid over the box."""
        xs, ys, d = self.distance.grid(shape)
        return xs, ys, self.constant / d**2

    def mass(self, region=None):
        """Integral of the estimate over the rectangle (x0, y0, x1, y1) (default: the box):
        the probability of the part of the region in the box (regions wrap across periodic
        seams)."""
        return self.distance.integrate(lambda d: self.constant / d**2, region)

    def sample(self, n, rng):
        """n points (n, 2) drawn from the normalised estimate with the numpy Generator rng: a
        piece of the mesh chosen by an upper bound of its mass, a uniform point in it, kept
        with probability density / bound (exact rejection sampling of the piecewise
        estimate; the pieces are well shaped, so most proposals are kept)."""
        return self.distance.sample_pieces(n, rng)


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
        x, u = uniform_in_triangles(corners[t], rng.random((m, 2)))
        dx = d[t, 0] * (1.0 - u[:, 0] - u[:, 1]) + d[t, 1] * u[:, 0] + d[t, 2] * u[:, 1]
        keep = rng.random(m) * dx**2 <= dmin[t] ** 2
        # pieces reach past the box; each point of the box lies in exactly one of them
        keep &= np.all((x >= lo) & (x <= hi), axis=1)
        x = x[keep][: n - filled]
        out[filled : filled + len(x)] = x
        filled += len(x)
    return out


class AdaptiveDensity:
    """The adaptive (sample-point) kernel estimate with local bandwidths from d_{P,k}.

    f(x) = (1 - eps) sum_i (w_i / W) K_i(x) + eps f_kNN(x): one kernel per point, of extent
    h_i = c G (d_i / G)^(2 alpha), d_i = d_{P,k}(X_i), G their geometric mean. The kNN
    estimate f ~ 1 / d_{P,k}^2 is the pilot, so h_i ~ f(X_i)^(-alpha): the sensitivity
    alpha = 1/2 is Abramson's square-root law (1982), narrow kernels where the points are
    dense and wide ones in the tails; alpha = 0 is the fixed-bandwidth estimate (bandwidth
    c G everywhere); in between, what heavy tails and flat regions prefer (Silverman 1986,
    5.3). The mesh gives d_{P,k} at every point at once (linear interpolation over its
    pieces).

    K_i is the triweight profile (1 - u)^3, u = (x - X_i)^T Q_i (x - X_i) < 1, normalised to
    mass 1: smooth, compactly supported (sums visit only the kernels that reach x).
    ``shape="isotropic"`` makes it a disk of radius h_i; ``shape="local"`` an ellipse of the
    same area shaped like the covariance of the points within d_{P,k} of X_i (measured at the
    mesh's nodes and interpolated; axes ratio at most ``max_ratio``): long along a ridge,
    narrow across it. Kernels stay in the box: periodic axes wrap, the others fold the mass
    beyond a side back into the box (reflection), so the estimate integrates to 1 there.
    eps = 1 / W (one point's worth, W the total weight) of the kNN estimate keeps the
    estimate positive where no kernel reaches (far tails): a finite log-likelihood.

    Parameters: ``mesh``, ``points``, ``subdivide``, ``weights`` as for ``KnnDensity``;
    ``bandwidth`` > 0, the factor c, and ``sensitivity`` alpha in [0, 1]
    (``set_bandwidth`` changes both cheaply, ``loo_curve`` scores candidates by leave-one-out
    likelihood).
    """

    def __init__(
        self, mesh, points, bandwidth=1.0, shape="isotropic", weights=None, subdivide=True,
        max_ratio=10.0, knn=None, sensitivity=0.5,
    ):  # fmt: skip
        _check_shape(shape)
        if not (isinstance(max_ratio, (int, float)) and 1 <= max_ratio < np.inf):
            raise InputError(f"max_ratio must be a number >= 1, got {max_ratio!r}")
        pts = as_points(points)
        if knn is None:
            knn = KnnDensity(mesh, pts, subdivide=subdivide, weights=weights)
        self.knn = knn
        dist = knn.distance
        weights = weights_of_run(mesh.stats, len(pts), weights)
        w = np.ones(len(pts)) if weights is None else weights
        self.k, self.shape = mesh.k, shape
        self.total = float(w.sum())
        self.eps = 1.0 / self.total
        self.n_eff = self.total**2 / float((w * w).sum())
        self._metric = dist._metric
        self.lo, self.hi = dist.lo, dist.hi
        self.periodic = tuple(bool(p) for p in mesh.periodic)
        frame = self._metric.frame(pts)
        self._rows, self._box, self._node = build_centres(frame, w)
        order = self._rows[:, ROW].astype(np.int64)
        self._row_of = np.empty(len(pts), np.int64)
        self._row_of[order] = np.arange(len(pts))
        self._extent = np.zeros(len(self._node))
        # the pilot: d_{P,k} at every point, and the local covariance for shape="local"
        if shape == "local":
            cov = self._node_covariance(dist)
            pilot = dist.interpolate(pts, np.column_stack([dist.values, cov]))
            d, cov = pilot[:, 0], pilot[:, 1:]
        else:
            d, cov = dist.interpolate(pts, dist.values), None
        lost = ~np.isfinite(d)
        if lost.any():  # on no piece by rounding: exact
            d[lost] = dist.exact(pts[lost])
        unit = _unit_shapes(cov, len(pts), max_ratio)  # (n, 3): s11, s12, s22, det 1
        # per unit bandwidth: Q = S^-1 / d^2, extent d sqrt(lambda_max(S)), amp
        # w / W * 4 sqrt(det Q) / pi (the triweight's mass is pi / (4 sqrt(det Q)))
        d2 = d * d
        self._q = np.column_stack([unit[:, 2], -unit[:, 1], unit[:, 0]])[order] / d2[order, None]
        tr = unit[:, 0] + unit[:, 2]
        lmax = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - 1.0, 0.0))
        self._r = (d * np.sqrt(lmax))[order]
        self._amp = (w / self.total * 4.0 / (np.pi * d2))[order]
        self.pilot = d
        # the sensitivity rescales d around its (weighted) geometric mean G: G (d / G)^(2 alpha)
        pos = d > 0
        log_g = float((w[pos] * np.log(d[pos])).sum() / max(w[pos].sum(), 1e-300))
        self._log_ratio = np.where(pos, np.log(np.where(pos, d, 1.0)) - log_g, 0.0)[order]
        # kernels no wider than the box along any axis (wrapping and folding stay exact)
        self._cap = float(np.min(self.hi - self.lo))
        self.sensitivity = 0.5
        self.set_bandwidth(bandwidth, sensitivity)

    def _node_covariance(self, dist):
        """Covariance (xx, xy, yy) of the points within d_{P,k} of each node of the mesh."""
        q = self._metric.frame(dist.nodes)
        out = np.empty((len(q), 6))
        lx, ly = self.hi - self.lo
        px, py = self.periodic
        qx, qy = q[:, 0].copy(), q[:, 1].copy()
        rows, box, node = self._rows, self._box, self._node
        radius = np.asarray(dist.values, float)
        in_chunks(
            lambda a, b: ball_moments(rows, box, node, qx, qy, radius, lx, ly, px, py, out, a, b),
            len(q),
        )
        w = np.maximum(out[:, 0], 1e-300)
        mx, my = out[:, 1] / w, out[:, 2] / w
        return np.column_stack(
            [out[:, 3] / w - mx * mx, out[:, 4] / w - mx * my, out[:, 5] / w - my * my]
        )

    def set_bandwidth(self, bandwidth, sensitivity=None):
        """Make the kernels' extents bandwidth * (their unit extents) at this sensitivity
        (None: as it is); O(n), no new tree. Returns self."""
        c = _check_bandwidth(bandwidth)
        alpha = self.sensitivity if sensitivity is None else _check_sensitivity(sensitivity)
        self.bandwidth, self.sensitivity = c, alpha
        rho = np.exp((2.0 * alpha - 1.0) * self._log_ratio) * c  # extent / unit extent at 1/2
        r = self._r * rho
        shrink = np.maximum(r / self._cap, 1.0) ** 2  # kernels wider than the box: narrowed
        scale = shrink / (rho * rho)
        rows = self._rows
        rows[:, Q11 : Q22 + 1] = self._q * scale[:, None]
        rows[:, AMP] = self._amp * scale
        rows[:, R] = r / np.sqrt(shrink)
        node_extents(rows, self._node, self._extent)
        return self

    @property
    def unit_extents(self):
        """Each point's kernel extent per unit bandwidth (its h_i / c), in input order: the
        pilot d_{P,k}(X_i) at sensitivity 1/2, G (d / G)^(2 alpha) otherwise."""
        rho = np.exp((2.0 * self.sensitivity - 1.0) * self._log_ratio)
        return self.pilot * rho[self._row_of]

    def _sums(self, frame, loo=False):
        """Kernel sums at points in frame coordinates, and the sums of their squares (with
        ``loo``, at centres: each sum without the centres at that place, and their weight;
        ``kernelsum.kernel_sums``)."""
        m = len(frame)
        out, out2 = np.empty(m), np.empty(m)
        qx, qy = frame[:, 0].copy(), frame[:, 1].copy()
        lx, ly = self.hi - self.lo
        px, py = self.periodic
        rows, box, node, extent = self._rows, self._box, self._node, self._extent

        def call(a, b):
            kernel_sums(rows, box, node, extent, qx, qy, loo, lx, ly, px, py, out, out2, a, b)

        in_chunks(call, m)
        return out, out2

    def _at(self, flat):
        """(kernel sums, their squares, the kNN estimate) at points (q, 2); NaN outside."""
        knn = self.knn(flat)
        inside = np.isfinite(knn)
        s, s2 = np.full(len(flat), np.nan), np.full(len(flat), np.nan)
        s[inside], s2[inside] = self._sums(self._metric.frame(flat[inside]))
        return s, s2, knn

    def __call__(self, x):
        """The density at points x (..., 2): shape (...); NaN outside the box along
        non-periodic axes."""
        flat, shape = as_queries(x)
        s, _, knn = self._at(flat)
        return ((1.0 - self.eps) * s + self.eps * knn).reshape(shape)

    def standard_error(self, x):
        """Pointwise standard error at x (..., 2) -> (...): the sample-point estimate's
        variance, (sum of squared kernel terms) - f^2 / n (bandwidths held fixed)."""
        flat, shape = as_queries(x)
        s, s2, _ = self._at(flat)
        var = np.maximum(s2 - s * s / self.n_eff, 0.0)
        return ((1.0 - self.eps) * np.sqrt(var)).reshape(shape)

    def grid(self, shape=(512, 512)):
        """(xs, ys, values): the density at the centres of a ny x nx grid over the box."""
        xs, ys, knn = self.knn.grid(shape)
        gx, gy = np.meshgrid(xs, ys)
        frame = self._metric.frame(np.column_stack([gx.ravel(), gy.ravel()]))
        s = self._sums(frame)[0].reshape(knn.shape)
        return xs, ys, (1.0 - self.eps) * s + self.eps * knn

    def loo(self, sample=None):
        """Leave-one-out log-density at the points ``sample`` (indices into the points; all
        by default): the kernels of the point and of its copies at the same place left out
        (W - their weight the total then: copies are one observation, as a point of whole
        weight is, or ties would pull the bandwidth to 0); the pilot bandwidths and the eps
        part keep them (they are smooth in one point)."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        rows = self._row_of[idx]
        s, w = self._sums(self._rows[rows, X : Y + 1], loo=True)
        rest = np.maximum(self.total - w, 1e-300)
        knn = self.knn.constant / self.pilot[idx] ** 2
        f = (1.0 - self.eps) * s * self.total / rest + self.eps * knn
        with np.errstate(divide="ignore"):
            return np.log(f)

    def weights_of(self, idx):
        """The weights of the points ``idx`` (indices into the points)."""
        return self._rows[self._row_of[idx], W]

    def loo_curve(self, bandwidths, sample=None, sensitivity=None):
        """Mean leave-one-out log-likelihood (per unit weight) of each candidate bandwidth at
        the points ``sample`` (default: all), at this sensitivity (None: as it is); the
        bandwidth is left at the last one."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        w = self.weights_of(idx)  # each point's weight: its share of the score
        scores = []
        for c in bandwidths:
            self.set_bandwidth(float(c), sensitivity)
            scores.append(float((self.loo(idx) * w).sum() / w.sum()))
        return np.array(scores)

    def least_squares(self, sample=None, draws=None, seed=0):
        """The least-squares cross-validation score (Rudemo 1982, Bowman 1984) at this
        smoothing: integral f^2 - 2 (mean leave-one-out density at the points ``sample``),
        which is the integrated squared error less the constant integral of the truth^2, so
        lower is better. The integral of f^2 is the mean of f at ``draws`` points drawn from
        f (default: as many as the sample), with the generator seeded by ``seed``: the same
        draws move with the kernels from one smoothing to the next (common random numbers),
        so that scores of neighbouring candidates compare with little noise."""
        idx = np.arange(len(self._row_of)) if sample is None else np.asarray(sample)
        w = self.weights_of(idx)
        loo = float((np.exp(self.loo(idx)) * w).sum() / w.sum())
        return square_integral(self, len(idx) if draws is None else int(draws), seed) - 2 * loo

    def sample(self, n, rng):
        """n points (n, 2) drawn from the estimate: a kernel chosen by weight, a point from
        it (u = |z|^2 ~ Beta(1, 4) for the triweight), folded or wrapped into the box; with
        probability eps from the kNN part instead."""
        rows = self._rows
        out = np.empty((n, 2))
        from_knn = rng.random(n) < self.eps
        m = int(n - from_knn.sum())
        i = rng.choice(len(rows), m, p=rows[:, W] / rows[:, W].sum())
        u = rng.beta(1.0, 4.0, m)
        theta = rng.random(m) * 2 * np.pi
        z = np.sqrt(u)[:, None] * np.column_stack([np.cos(theta), np.sin(theta)])
        # x = X_i + L z with L L^T = Q^-1 (Cholesky of the 2 x 2 inverse)
        q11, q12, q22 = rows[i, Q11], rows[i, Q12], rows[i, Q22]
        det = q11 * q22 - q12 * q12
        a, b, c = q22 / det, -q12 / det, q11 / det  # Q^-1
        l11 = np.sqrt(a)
        l21 = b / l11
        l22 = np.sqrt(np.maximum(c - l21 * l21, 0.0))
        x = rows[i, X] + l11 * z[:, 0]
        y = rows[i, Y] + l21 * z[:, 0] + l22 * z[:, 1]
        out[~from_knn] = self._into_box(np.column_stack([x, y]))
        if from_knn.any():
            out[from_knn] = self.knn.sample(int(from_knn.sum()), rng)
        return out

    def _into_box(self, frame):
        """Kernel draws (frame coordinates) as points of the box: folded back along
        non-periodic axes (mirrored in the sides, as the sums fold), wrapped along periodic
        ones (``BoxMetric.wrap``, the one wrapping rule)."""
        period = self.hi - self.lo
        for a in range(2):
            if not self.periodic[a]:
                v = np.abs(frame[:, a])  # the mirror in the lower side
                frame[:, a] = np.where(v > period[a], 2 * period[a] - v, v)
        return self._metric.wrap(frame + self.lo)


def square_integral(density, draws, seed=0):
    """Monte Carlo integral of f^2 over the box for a density with ``sample`` and a call:
    the mean of f at ``draws`` points drawn from f (seeded, so repeatable)."""
    return float(np.mean(_at_own_draws(density, draws, seed)))


def _at_own_draws(density, draws, seed):
    """f at ``draws`` points drawn from f with the generator seeded by ``seed``."""
    return density(density.sample(int(draws), np.random.default_rng(seed)))


CRITERIA = ("likelihood", "least-squares")
BANDWIDTHS = tuple(2.0 ** (np.arange(-6, 7) / 2))  # 1/8 to 8, steps of sqrt(2)
SENSITIVITIES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
COARSE = 4000  # a first climb's points, when there are more than twice as many
HALF_STEP = 2.0**0.25  # the last search's step in c: half the grid's


def choose_smoothing(
    density, alphas=SENSITIVITIES, bandwidths=BANDWIDTHS, loo_points=20000, random_state=0,
    criterion="likelihood",
):  # fmt: skip
    """(sensitivity, bandwidth, table): the pair of the grid alphas x bandwidths with the
    best cross-validation score of the ``AdaptiveDensity`` at up to ``loo_points`` of its
    points (chosen by ``random_state``), by climbing from the candidates nearest (1/2, 1) to
    the best grid neighbour until none is better: the score is smooth in both, so a climb
    scores a few pairs, not all. Over 2 COARSE points, a first climb on a fifth of them
    (at least COARSE) finds the region at a fifth of the cost, and the second starts there.
    ``criterion``: "likelihood" (mean leave-one-out log-density, higher is better: what
    held-out likelihood rewards) or "least-squares" (``AdaptiveDensity.least_squares``,
    lower is better: an unbiased estimate of the integrated squared error less a constant,
    which favours the wider kernels that L1 and L2 errors reward). The climb ends on the
    grid's half steps in c at its alpha (``_widest_within_one_se``): the widest c whose
    score is within one standard error of the best, so the choice may lie between grid
    values. The table has a row (alpha, c, score) per pair the last climb scored, in that
    order, then the half steps (the score as defined above for the criterion). The density
    is left at the chosen pair."""
    criterion = _check_criterion(criterion)
    n = len(density.pilot)
    m = min(n, int(loo_points))
    sample = None if m == n else np.sort(_generator(random_state).choice(n, m, False))
    i = int(np.argmin(np.abs(np.asarray(alphas) - 0.5)))
    j = int(np.argmin(np.abs(np.log(bandwidths))))
    if m > 2 * COARSE:
        pool = np.arange(n) if sample is None else sample
        coarse = np.sort(_generator(random_state).choice(pool, max(COARSE, m // 5), False))
        i, j, _ = _climb(density, alphas, bandwidths, coarse, i, j, criterion)
    i, j, scored = _climb(density, alphas, bandwidths, sample, i, j, criterion)
    alpha, c = float(alphas[i]), float(bandwidths[j])
    rows = [(alphas[a], bandwidths[b], v) for (a, b), v in scored.items()]
    if len(bandwidths) > 1:
        c, settled = _widest_within_one_se(density, alpha, c, sample, criterion, max(bandwidths))
        near = [b for a, b, _ in rows if a == alpha]
        rows += [(alpha, b, v) for b, v in settled.items() if not np.isclose(near, b).any()]
    sign = 1.0 if criterion == "likelihood" else -1.0  # the table has the scores as defined
    table = np.array([(a, b, sign * v) for a, b, v in rows])
    density.set_bandwidth(c, alpha)
    return alpha, c, table


def _score_terms(density, c, alpha, sample, criterion):
    """The cross-validation score at (alpha, c) as terms (values, weights, factor): the score
    (higher is better) is the sum of factor * (weighted mean of values), and two smoothings'
    values pair item by item (the same points; the same seeded draws), so the standard error
    of a difference of scores comes from the differences of values."""
    density.set_bandwidth(c, alpha)
    idx = np.arange(len(density.pilot)) if sample is None else np.asarray(sample)
    w = density.weights_of(idx)
    if criterion == "likelihood":
        return [(density.loo(idx), w, 1.0)]
    return [(_at_own_draws(density, len(idx), 0), np.ones(len(idx)), -1.0),
            (np.exp(density.loo(idx)), w, 2.0)]  # fmt: skip


def _score_of(terms):
    return float(sum(f * (v * w).sum() / w.sum() for v, w, f in terms))


def _difference_se(terms, base):
    """Standard error of the score difference between two smoothings' paired terms."""
    var = 0.0
    for (v, w, f), (v0, _, _) in zip(terms, base, strict=True):
        d = v - v0
        mean = (d * w).sum() / w.sum()
        var += f * f * ((w * (d - mean)) ** 2).sum() / w.sum() ** 2
    return float(np.sqrt(var))


def _widest_within_one_se(density, alpha, c, sample, criterion, widest):
    """The last step of the search, on the grid's half steps in c at the climb's alpha: the
    best of c / HALF_STEP, c, c * HALF_STEP, then the widest c above it, step by step up to
    ``widest``, whose score is within one standard error of the best's (the one-standard-
    error rule of cross-validation: where the score is flat within its noise, the smoother
    estimate; at large n the likelihood's optimum is such a flat top, and L1 errors reward
    its wide side). Returns (c, {c: score} of the candidates scored here but c itself,
    higher is better)."""
    terms, scores = {}, {}

    def score(j):
        if j not in terms:
            terms[j] = _score_terms(density, c * HALF_STEP**j, alpha, sample, criterion)
            scores[j] = _score_of(terms[j])
        return scores[j]

    best = max((j for j in (-1, 0, 1) if c * HALF_STEP**j <= widest), key=score)
    chosen = best
    while c * HALF_STEP ** (chosen + 1) <= widest * (1 + 1e-9):
        if score(chosen + 1) < score(best) - _difference_se(terms[chosen + 1], terms[best]):
            break
        chosen += 1
    return c * HALF_STEP**chosen, {c * HALF_STEP**j: v for j, v in scores.items() if j}


def _climb(density, alphas, cs, sample, i, j, criterion="likelihood"):
    """Hill-climb of a cross-validation score over the grid alphas x cs from (i, j):
    (i, j) of the best pair found, {(i, j): score} of every pair scored (the
    least-squares score negated, so that higher is better for both criteria)."""
    scored = {}

    def score(a, b):
        if (a, b) not in scored:
            if criterion == "likelihood":
                scored[a, b] = density.loo_curve([cs[b]], sample, alphas[a])[0]
            else:
                density.set_bandwidth(cs[b], alphas[a])
                scored[a, b] = -density.least_squares(sample)
        return scored[a, b]

    best = score(i, j)
    while True:
        steps = [(i + a, j + b) for a, b in ((-1, 0), (1, 0), (0, -1), (0, 1))]
        steps = [(a, b) for a, b in steps if 0 <= a < len(alphas) and 0 <= b < len(cs)]
        top = max(steps, key=lambda ab: score(*ab))
        if not score(*top) > best:
            return i, j, scored
        (i, j), best = top, score(*top)


def _unit_shapes(cov, n, max_ratio):
    """Unit-determinant shapes (s11, s12, s22) per point: the identity without ``cov``,
    else cov scaled to determinant 1 with its axes ratio sqrt(l1 / l2) at most max_ratio."""
    if cov is None:
        return np.tile([1.0, 0.0, 1.0], (n, 1))
    a, b, c = cov[:, 0], cov[:, 1], cov[:, 2]
    half = 0.5 * (a + c)
    gap = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    l1 = np.maximum(half + gap, 1e-300)
    l2 = np.maximum(half - gap, l1 / max_ratio**2)
    # eigenvector of l1: (b, l1 - a) or, when b == 0, the axis of the larger variance
    vx = np.where(np.abs(b) > 0, b, np.where(a >= c, 1.0, 0.0))
    vy = np.where(np.abs(b) > 0, l1 - a, np.where(a >= c, 0.0, 1.0))
    norm = np.hypot(vx, vy)
    vx, vy = vx / norm, vy / norm
    bad = ~(np.isfinite(l1) & np.isfinite(vx) & np.isfinite(vy))
    s1, s2 = np.sqrt(l1 / l2), np.sqrt(l2 / l1)  # determinant 1
    out = np.column_stack(
        [s1 * vx * vx + s2 * vy * vy, (s1 - s2) * vx * vy, s1 * vy * vy + s2 * vx * vx]
    )
    out[bad] = (1.0, 0.0, 1.0)
    return out


def _grid_shape(shape):
    """(ny, nx) from a grid shape: two positive whole numbers."""
    try:
        ny, nx = (int(s) for s in shape)
        ok = all(int(s) == s for s in shape)
    except (TypeError, ValueError):
        ok = False
    if not ok or ny < 1 or nx < 1:
        raise InputError(f"shape must be two positive whole numbers (ny, nx), got {shape!r}")
    return ny, nx


def _quadrature(corners, d, func):
    """Per triangle: integral of func(d) with d linear (values d at the corners)."""
    if len(corners) == 0:
        return np.zeros(0)
    area = np.abs(triangle_areas(corners))
    dq = d @ _QP.T  # (t, 7): d at the quadrature points
    return area * (func(dq) @ _QW)


class KnnDensityEstimator:
    """knnrefine's density estimate as a scikit-learn estimator (scikit-learn itself is
    optional).

    ``fit(X)`` refines a mesh of X and builds the estimate: by default the adaptive kernel
    estimate ``AdaptiveDensity`` (bandwidths from d_{P,k}, the factor chosen by leave-one-out
    likelihood), or the plain kNN estimate ``KnnDensity`` (``method="knn"``).
    ``score_samples`` gives log-densities, ``score`` the total log-likelihood, ``sample``
    draws from the estimate. ``get_params``/``set_params`` follow scikit-learn's rules, so
    ``clone``, ``GridSearchCV(est, {"k": [...]})`` and ``cross_val_score`` work.

    Parameters
    ----------
    k : int or "cv", optional
        Which neighbour (the smoothing of the kNN estimate, the pilot's of the adaptive one:
        larger is smoother). Default ``default_pilot_k(n)`` = 2 sqrt(n) (adaptive),
        ``default_k(n)`` = sqrt(n) / 2 (kNN). ``"cv"``: the k of ``k_grid`` with the best
        held-out log-likelihood in ``cv``-fold cross-validation (folds shuffled by
        ``random_state``, every fold in the same box; adaptive: each fold with its own
        bandwidth by leave-one-out).
    method : "adaptive" or "knn"
        The estimate (see above). The adaptive one (default or ``shape="local"``) had the
        best held-out likelihood and the lowest L1 error on every truth of the project's
        study at n = 1e4 to 1e6 (``benchmarks/density_accuracy.py``, docs/uses.md).
    bandwidth : float > 0 or "cv"
        The adaptive estimate's factor c: kernel extents c G (d_i / G)^(2 alpha), d_i =
        d_{P,k}(X_i), G their geometric mean (c d_i at alpha = 1/2). ``"cv"``: chosen from
        ``BANDWIDTHS`` by leave-one-out log-likelihood at up to ``loo_points`` training
        points (chosen by ``random_state``), jointly with the sensitivity when that is
        ``"cv"`` too, then on half steps the widest within one standard error of the best
        (``choose_smoothing``). Ignored by ``method="knn"``.
    sensitivity : float in [0, 1] or "cv"
        The adaptive estimate's alpha: kernels ~ f^(-alpha). 1/2 is Abramson's law, 0 a
        fixed bandwidth; ``"cv"`` (default) chooses from ``SENSITIVITIES`` (0 to 0.6) with
        the bandwidth. Heavy tails and flat regions choose less than 1/2, narrow peaks 1/2
        (docs/uses.md).
    shape : "isotropic" or "local"
        The adaptive estimate's kernels: disks, or ellipses shaped like the local covariance
        of the points (thin ridges, curved structure).
    whiten : bool
        Work in coordinates divided by each axis' standard deviation (data whose axes have
        different units: millimetres against grams); densities are returned in the data's
        units. The mesh ``mesh_`` is then in the scaled coordinates.
    tau : float > 2
        Well-spacedness of the mesh (``refine``).
    periodic : bool or (bool, bool)
        Flat torus along these axes (``box`` then required).
    box : (xmin, ymin, xmax, ymax), optional
        Where the estimate lives: it integrates to 1 over the box and is 0 outside it along
        non-periodic axes (log-density -inf there); periodic axes wrap. Default: the data's
        bounding box widened by ``margin`` of its sides on every side, so that held-out points
        near the sample's edge score finitely.
    margin : float >= 0
        See ``box`` (ignored when a box is given).
    min_size : float, optional
        The resolution floor (``refine``).
    subdivide : bool
        Evaluate exactly at edge midpoints too (``KnnDistance``).
    cv, k_grid, random_state, loo_points
        For ``k="cv"``: the number of folds, the candidate values of k (default: 10 values
        spaced geometrically from 4 to a twentieth of a fold's training points), the seed of
        the fold assignment and of the leave-one-out subsample (an int or None); the size of
        that subsample.
    criterion : "likelihood" or "least-squares"
        What the searches ("cv" above) optimise: held-out log-likelihood (default; its
        choice wins held-out likelihood and Hellinger distance), or least-squares
        cross-validation, an estimate of the integrated squared error (``choose_smoothing``):
        it picks wider kernels, and won L1 error where likelihood's choice lost it in the
        project's study at 1e6 (docs/uses.md). ``score`` stays the log-likelihood.

    Attributes after ``fit``: ``k_``, ``bandwidth_`` (adaptive), ``box_`` (data units),
    ``scale_`` (the whitening divisors, (1, 1) without), ``n_samples_`` (weights counted),
    ``n_features_in_`` (2), ``mesh_`` (the ``Mesh``), ``density_`` (the ``AdaptiveDensity`` or
    ``KnnDensity``), ``sensitivity_`` (adaptive); when either is ``"cv"``, ``loo_scores_``
    (a row (alpha, c, score) for every pair the search scored: the leave-one-out
    log-likelihood per point, or the least-squares score, by ``criterion``) and
    ``bandwidths_``, ``bandwidth_scores_`` (the curve over c at the chosen alpha), with
    ``k="cv"`` ``cv_ks_`` and ``cv_scores_`` (each candidate's score: the mean held-out
    log-likelihood per point, or the least-squares score: the curve).
    """

    BANDWIDTHS = BANDWIDTHS
    SENSITIVITIES = SENSITIVITIES

    def __init__(
        self, k=None, *, method="adaptive", bandwidth="cv", sensitivity="cv", shape="isotropic",
        whiten=False,
        tau=3.0, periodic=False, box=None, margin=0.1, min_size=None, subdivide=True, cv=5,
        k_grid=None, random_state=0, loo_points=20000, criterion="likelihood",
    ):  # fmt: skip
        self.k = k
        self.method = method
        self.bandwidth = bandwidth
        self.sensitivity = sensitivity
        self.shape = shape
        self.whiten = whiten
        self.tau = tau
        self.periodic = periodic
        self.box = box
        self.margin = margin
        self.min_size = min_size
        self.subdivide = subdivide
        self.cv = cv
        self.k_grid = k_grid
        self.random_state = random_state
        self.loo_points = loo_points
        self.criterion = criterion

    # -- scikit-learn's parameter protocol ---------------------------------------------------
    @classmethod
    def _param_names(cls):
        params = inspect.signature(cls.__init__).parameters
        return sorted(p for p in params if p != "self")

    def get_params(self, deep=True):
        """The constructor's parameters as a dict (scikit-learn's protocol)."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params):
        """Set constructor parameters (scikit-learn's protocol); returns self."""
        valid = self._param_names()
        for name, value in params.items():
            if name not in valid:
                raise ValueError(
                    f"invalid parameter {name!r} for KnnDensityEstimator; valid ones: "
                    f"{', '.join(valid)}"
                )
            setattr(self, name, value)
        return self

    def __sklearn_tags__(self):
        """scikit-learn >= 1.6 asks estimators for their tags (imported only then)."""
        from sklearn.utils import Tags, TargetTags

        return Tags(estimator_type="DensityEstimator", target_tags=TargetTags(required=False))

    def __repr__(self):
        defaults = type(self)().get_params()
        changed = [
            f"{name}={value!r}"
            for name, value in self.get_params().items()
            if value is not defaults[name] and not _same(value, defaults[name])
        ]
        return f"KnnDensityEstimator({', '.join(changed)})"

    # -- fitting -----------------------------------------------------------------------------
    def fit(self, X, y=None, sample_weight=None):
        """Refine a mesh of X (n, 2) and build the estimate. ``sample_weight``: weights >= 0
        (the engine counts them: a point of whole weight w is w copies, real weights are
        survey or aggregation weights; n is then their total W). ``y`` is ignored. Returns
        self."""
        pts = as_points(X)
        weights = None
        if sample_weight is not None:
            weights = check_weights(sample_weight, len(pts))
            pts, weights = pts[weights > 0], weights[weights > 0]
            if np.all(weights == 1.0):
                weights = None
        self._check_options()
        n = len(pts) if weights is None else float(weights.sum())
        scale = self._scale(pts, weights)
        pts = pts / scale
        box = self._box(pts, scale)
        stale_attrs = (
            "cv_ks_", "cv_scores_", "bandwidths_", "bandwidth_scores_", "bandwidth_",
            "sensitivity_", "loo_scores_",
        )  # fmt: skip
        for stale in stale_attrs:
            self.__dict__.pop(stale, None)  # from an earlier fit
        if isinstance(self.k, str):
            if self.k != "cv":
                raise InputError(f'k must be an integer, None or "cv", got {self.k!r}')
            self.cv_ks_, self.cv_scores_ = self._cross_validate(pts, weights, box)
            pick = np.argmax if self.criterion == "likelihood" else np.argmin
            k = int(self.cv_ks_[int(pick(self.cv_scores_))])
        else:
            k = self.k
            if k is None:
                k = default_k(n) if self.method == "knn" else default_pilot_k(n)
            if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= n:
                raise InputError(f"k must be an integer in [1, n = {n:g}], got {k!r}")
        self.density_, self.mesh_ = self._estimate(pts, weights, box, int(k))
        if self.method == "adaptive":
            self.bandwidth_ = self.density_.bandwidth
            self.sensitivity_ = self.density_.sensitivity
        self._train = (pts, np.ones(len(pts)) if weights is None else weights)
        self.k_ = int(k)
        self.scale_ = tuple(float(v) for v in scale)
        self.box_ = tuple(float(b) for b in np.array(self.mesh_.box) * np.tile(scale, 2))
        self.n_samples_ = n
        self.n_features_in_ = 2
        return self

    def _check_options(self):
        if self.method not in ("adaptive", "knn"):
            raise InputError(f'method must be "adaptive" or "knn", got {self.method!r}')
        _check_shape(self.shape)
        if not isinstance(self.whiten, (bool, np.bool_)):
            raise InputError(f"whiten must be True or False, got {self.whiten!r}")
        if not (isinstance(self.bandwidth, str) and self.bandwidth == "cv"):
            _check_bandwidth(self.bandwidth, '"cv" or ')
        if not (isinstance(self.sensitivity, str) and self.sensitivity == "cv"):
            _check_sensitivity(self.sensitivity, '"cv" or ')
        _check_cv(self.cv)
        _check_criterion(self.criterion)
        m = self.loo_points
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InputError(f"loo_points must be an integer >= 1, got {m!r}")

    def _scale(self, pts, weights):
        """Per-axis divisors: the (weighted) standard deviations with ``whiten``, else 1."""
        if not self.whiten:
            return np.ones(2)
        w = np.ones(len(pts)) if weights is None else weights
        mean = (pts * w[:, None]).sum(axis=0) / w.sum()
        sd = np.sqrt((((pts - mean) ** 2) * w[:, None]).sum(axis=0) / w.sum())
        if not np.all(sd > 0):
            raise InputError(
                "whiten needs points spread along both axes (a standard deviation is 0)"
            )
        return sd

    def _estimate(self, pts, weights, box, k):
        """(density, mesh) at this k: the kNN estimate, or the adaptive one with its
        bandwidth given or chosen by leave-one-out likelihood (recording the curve)."""
        from .api import refine

        mesh = refine(
            pts, k, self.tau, periodic=self.periodic, box=box, min_size=self.min_size,
            weights=weights,
        )  # fmt: skip
        knn = KnnDensity(mesh, pts, normalized=True, subdivide=self.subdivide, weights=weights)
        if self.method == "knn":
            return knn, mesh
        cs = self.BANDWIDTHS if self.bandwidth == "cv" else (float(self.bandwidth),)
        alphas = self.SENSITIVITIES if self.sensitivity == "cv" else (float(self.sensitivity),)
        density = AdaptiveDensity(
            mesh, pts, cs[0], self.shape, weights=weights, knn=knn, sensitivity=alphas[0]
        )
        if len(cs) > 1 or len(alphas) > 1:
            alpha, _, self.loo_scores_ = choose_smoothing(
                density, alphas, cs, self.loo_points, self.random_state, self.criterion
            )  # leaves the density at the chosen pair
            at = self.loo_scores_[self.loo_scores_[:, 0] == alpha]
            at = at[np.argsort(at[:, 1])]
            self.bandwidths_, self.bandwidth_scores_ = at[:, 1], at[:, 2]
        return density, mesh

    def _k_candidates(self, n_train):
        """The candidate ks: ``k_grid`` or 10 geometric steps from 4 to n_train / 20."""
        if self.k_grid is None:
            return np.unique(np.round(np.geomspace(4, max(8, n_train / 20), 10)).astype(int))
        ks = np.unique(np.asarray(self.k_grid))
        if ks.size == 0 or not np.issubdtype(ks.dtype, np.integer) or ks[0] < 1:
            raise InputError(f"k_grid must hold integers >= 1, got {self.k_grid!r}")
        ks = ks[ks <= n_train]
        if ks.size == 0:
            raise InputError(f"no k of k_grid fits the smallest training fold ({n_train:g} points)")
        return ks

    def _box(self, pts, scale):
        """The box to refine in (scaled coordinates): the user's, else refine's default box
        of the points (``validation.default_box``) widened by ``margin``."""
        if self.box is not None:
            try:
                box = np.asarray(self.box, float)
            except (TypeError, ValueError):
                return self.box  # refine says what is wrong with it
            return tuple(box / np.tile(scale, 2)) if box.shape == (4,) else self.box
        if np.any(self.periodic):  # a torus needs its period: refine says so
            return None
        margin = self.margin
        if isinstance(margin, bool) or not isinstance(margin, (int, float, np.floating)):
            raise InputError(f"margin must be a number >= 0, got {margin!r}")
        if not 0 <= margin < np.inf:
            raise InputError(f"margin must be a finite number >= 0, got {margin!r}")
        x0, y0, x1, y1 = default_box(pts)
        px, py = margin * (x1 - x0), margin * (y1 - y0)
        return (x0 - px, y0 - py, x1 + px, y1 + py)

    def _cross_validate(self, pts, weights, box):
        """(candidate ks, the score of each): by ``criterion``, the mean held-out
        log-likelihood per unit of weight (higher is better), or the mean over folds of the
        least-squares score integral f^2 - 2 (weighted mean of f at the held-out points),
        lower is better (``square_integral``). Every fold is refined in the same box, so
        that held-out points are in it; folds split points, so a point of weight w (w
        copies) is held out whole."""
        folds = _folds(len(pts), self.cv, self.random_state)
        weight = np.ones(len(pts)) if weights is None else weights
        n = float(weight.sum())
        ks = self._k_candidates(n - max(float(weight[f].sum()) for f in folds))
        params = {**self.get_params(), "box": box, "whiten": False}
        scores = np.zeros(len(ks))
        for test in folds:
            train = np.ones(len(pts), bool)
            train[test] = False
            fold_weight = None if weights is None else weight[train]
            for i, k in enumerate(ks):
                fold = type(self)(**{**params, "k": int(k)})
                fold.fit(pts[train], sample_weight=fold_weight)
                if self.criterion == "likelihood":
                    scores[i] += (fold.score_samples(pts[test]) * weight[test]).sum() / n
                else:
                    held = np.exp(fold.score_samples(pts[test]))
                    mean = (held * weight[test]).sum() / weight[test].sum()
                    square = square_integral(fold.density_, self.loo_points)
                    scores[i] += (square - 2 * mean) / len(folds)
        return ks, scores

    # -- uncertainty -------------------------------------------------------------------------
    def standard_error(self, X):
        """Pointwise standard error of the density at X, shape (..., 2) -> (...). kNN: f(x) /
        sqrt(k) (its relative error is about 1 / sqrt(k): the ball of radius d_{P,k}(x) holds
        k points, whose count fluctuates like a Poisson variable's); adaptive: the
        sample-point estimate's variance (``AdaptiveDensity.standard_error``)."""
        density = self._fitted()
        if self.method == "knn":
            return np.exp(self.score_samples(X)) / np.sqrt(self.k_)
        flat, shape = self._queries(X)
        return (density.standard_error(flat) / self._jacobian()).reshape(shape)

    def bootstrap(self, X, n_boot=100, level=0.9, random_state=None):
        """Percentile bands (lower, upper) of the density at X, shape (..., 2) -> two arrays
        (...): the estimate refitted (same k and box) on n_boot resamples of the training
        points with replacement (as weights: no copies are made), and the (1 - level) / 2 and
        (1 + level) / 2 quantiles of its values at each point. Whole-number weights are
        copies and the copies are resampled; real weights stay with their points, which are
        resampled (the bootstrap of a weighted sample)."""
        density = self._fitted()
        if isinstance(n_boot, bool) or not isinstance(n_boot, (int, np.integer)) or n_boot < 2:
            raise InputError(f"n_boot must be an integer >= 2, got {n_boot!r}")
        if not 0 < level < 1:
            raise InputError(f"level must lie in (0, 1), got {level!r}")
        flat, shape = self._queries(X)
        pts, weight = self._train  # in the fitted (scaled) coordinates
        rng = _generator(random_state)
        whole = bool(np.all(weight == np.rint(weight)))
        params = {**self.get_params(), "k": self.k_, "box": self.mesh_.box, "whiten": False}
        if self.method == "adaptive":
            params["bandwidth"] = density.bandwidth
            params["sensitivity"] = density.sensitivity
        values = np.empty((int(n_boot), len(flat)))
        for b in range(int(n_boot)):
            if whole:  # the copies, resampled
                draw = rng.multinomial(int(weight.sum()), weight / weight.sum())
            else:  # the points, resampled, each with its weight
                draw = rng.multinomial(len(weight), np.full(len(weight), 1.0 / len(weight)))
                draw = draw * weight
            refit = type(self)(**params).fit(pts, sample_weight=draw)
            values[b] = np.exp(refit.score_samples(flat)) / self._jacobian()
        lo, hi = np.quantile(values, [(1 - level) / 2, (1 + level) / 2], axis=0)
        return lo.reshape(shape), hi.reshape(shape)

    def _fitted(self):
        if not hasattr(self, "density_"):
            raise _not_fitted()
        return self.density_

    # -- evaluation ----------------------------------------------------------------------------
    def score_samples(self, X):
        """Log-density at the points X, shape (..., 2): an array of shape (...). -inf outside
        the box along non-periodic axes (the estimate is 0 there); periodic axes wrap."""
        density = self._fitted()
        flat, shape = self._queries(X)
        f = density(flat) / self._jacobian()
        with np.errstate(divide="ignore"):
            out = np.where(np.isnan(f), -np.inf, np.log(np.where(np.isnan(f), 1.0, f)))
        return out.reshape(shape)

    def score(self, X, y=None):
        """Total log-likelihood of the points X (n, 2) under the estimate (-inf if one lies
        outside the box)."""
        return float(self.score_samples(X).sum())

    def sample(self, n_samples=1, random_state=None):
        """n_samples points (n_samples, 2) drawn exactly from the estimate
        (``AdaptiveDensity.sample``, ``KnnDensity.sample``). ``random_state``: None, an int,
        a numpy Generator or RandomState."""
        density = self._fitted()
        if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)):
            raise InputError(f"n_samples must be an integer >= 0, got {n_samples!r}")
        if n_samples < 0:
            raise InputError(f"n_samples must be >= 0, got {n_samples}")
        return density.sample(int(n_samples), _generator(random_state)) * self.scale_

    def _queries(self, X):
        """Query points (..., 2) as flat (q, 2) in the fitted (scaled) coordinates, and the
        leading shape; non-finite coordinates refused."""
        self._fitted()
        flat, shape = as_queries(X)
        if not np.isfinite(flat).all():
            raise InputError("X holds NaN or infinite coordinates; give finite points")
        return flat / np.asarray(self.scale_), shape

    def _jacobian(self):
        """Density in scaled coordinates / density in the data's: the scales' product."""
        return float(np.prod(self.scale_))


def _check_shape(shape):
    if shape not in ("isotropic", "local"):
        raise InputError(f'shape must be "isotropic" or "local", got {shape!r}')


def _check_sensitivity(alpha, alternative=""):
    """alpha: a number in [0, 1] (float), else a clear error."""
    real = (int, float, np.integer, np.floating)
    ok = not isinstance(alpha, (bool, np.bool_)) and isinstance(alpha, real)
    if not ok or not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"sensitivity must be {alternative}a number in [0, 1], got {alpha!r}")
    return float(alpha)


def _check_bandwidth(c, alternative=""):
    """The adaptive estimate's factor c: a finite number > 0, as a float."""
    real = (int, float, np.integer, np.floating)
    ok = not isinstance(c, (bool, np.bool_)) and isinstance(c, real)
    if not (ok and 0 < c < np.inf):
        raise InputError(f"bandwidth must be {alternative}a finite number > 0, got {c!r}")
    return float(c)


def _check_criterion(criterion):
    if not (isinstance(criterion, str) and criterion in CRITERIA):
        raise InputError(f'criterion must be "likelihood" or "least-squares", got {criterion!r}')
    return criterion


def _check_cv(cv):
    if isinstance(cv, bool) or not isinstance(cv, (int, np.integer)) or cv < 2:
        raise InputError(f"cv must be an integer >= 2, got {cv!r}")


def _same(a, b):
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def _folds(n, cv, random_state):
    """The test indices of each of ``cv`` folds of n points, shuffled by random_state."""
    _check_cv(cv)
    if cv > n:
        raise InputError(f"cv must be an integer in [2, n = {n}], got {cv!r}")
    order = _generator(random_state).permutation(n)
    return np.array_split(order, int(cv))


def _generator(random_state):
    """A numpy Generator from scikit-learn-style random_state values."""
    if isinstance(random_state, np.random.RandomState):
        return np.random.default_rng(random_state.randint(0, 2**63 - 1, dtype=np.int64))
    try:
        return np.random.default_rng(random_state)
    except (TypeError, ValueError):
        raise InputError(
            f"random_state must be None, an int, a numpy Generator or RandomState, got "
            f"{random_state!r}"
        ) from None


def _not_fitted():
    """scikit-learn's NotFittedError when scikit-learn is installed, else an InputError."""
    message = "this KnnDensityEstimator is not fitted yet: call fit(X) first"
    try:
        from sklearn.exceptions import NotFittedError
    except ImportError:
        return InputError(message)
    return NotFittedError(message)
