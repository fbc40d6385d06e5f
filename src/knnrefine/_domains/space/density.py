"""d_{P,k} in space as linear pieces (``Pieces``), what ``KnnDistance`` builds for a
``Mesh`` in space, and the kNN-CDF over them.

As in the plane (``plane.py``): exact d_{P,k} at the mesh's vertices (one query of a
periodic kd-tree each), carried linearly over the tetrahedra. The kNN-CDF of cosmology, the
distribution of d_{P,k} at uniformly random points of the box, CDF(r) = vol{x : d_{P,k}(x)
<= r} / vol(box), is integrated over the mesh exactly for the interpolant: on a tetrahedron
whose corners carry d_0 <= d_1 <= d_2 <= d_3, the value at a uniform point has the cubic
B-spline distribution with those knots, so the share of the tetrahedron below r is a
piecewise cubic in r. Rigorous bounds come without any assumption on the interpolant:
d_{P,k} is 1-Lipschitz, so on a tetrahedron it lies within d_i -+ e_i for each corner i (e_i
the distance to the farthest corner); counting each tetrahedron whole where its upper bound
is <= r gives a lower bound of the CDF, where its lower bound is <= r an upper bound
(``cdf_bounds``).

Along non-periodic axes the mesh's tetrahedra are the copies that meet the box; they are cut
at its faces (``clip_below``: a tetrahedron cut by a plane leaves a tetrahedron or a prism,
three tetrahedra), so that the pieces tile the box exactly and every integral is over the box.
"""

import copy

import numpy as np
from scipy.spatial import cKDTree

from ..._engine.bspline import shares_below, weighted_shares
from ..._engine.index3 import build_index3, kth_distances3, weights_at3
from ..._engine.raster import first_holding3, rasterise3
from ..._engine.threads import in_chunks, kth_range
from ..._metric import BoxMetric, weighted_kth
from ..._validation import check_inside
from ...errors import InputError
from ..box import answerable, flat_radius, not_simplicial, points_of, to_frame  # noqa: F401


def index_of(mesh, pts, weights=None):
    """Exact d_{P,k} for the mesh's points: a periodic kd-tree (``Index``) with
    ``kth(x, k)`` at points x in the box; the points must lie in it along non-periodic
    axes."""
    check_inside(pts, mesh.box, mesh.periodic, warn=False)
    return Index(mesh, pts, weights)


def build(mesh, points, weights, subdivide):
    """What ``KnnDistance`` keeps of a mesh in space: (the points, the exact index, the
    pieces, the points' number or total weight)."""
    pts, weights, total = points_of(mesh, points, weights)
    index = index_of(mesh, pts, weights)
    return pts, index, Pieces(mesh, index.kth_local, subdivide), total


class Index:
    """Exact d_{P,k} in space from the engine's counting kd-tree over the points in the
    frame of the mesh's torus (relative to its origin, periodic axes wrapping): ``kth`` at
    input coordinates, ``kth_local`` at torus-frame ones (the pieces'). Each query collects
    the points in a window of radii about a guess and selects the k-th
    (``index3.kth_distances3``, as ``PointIndex.kth`` in the plane): nodes inside the inner
    radius count whole, so a query costs about the points in the window, not k log k as a
    k-nearest query does; below k = WINDOWS_FROM_K (unweighted) scipy's query is the
    faster. Weighted points: d_{P,k} is the least radius whose closed ball holds weight k.
    ``frame``: the torus' (origin, period) for a mesh that keeps none (a mesh in parts)."""

    def __init__(self, mesh, pts, weights=None, frame=None):
        origin, period = (mesh.torus.origin, mesh.torus.period) if frame is None else frame
        origin = np.asarray(origin, float)
        period = np.asarray(period, float)
        self.k = mesh.k
        self._origin = origin
        self._metric = BoxMetric((*origin, *(origin + period)), mesh.periodic)
        self._period = np.where(self._metric.periodic, period, np.inf)
        self._points = pts
        self._weights = weights
        local = np.ascontiguousarray(self._metric.frame(pts))
        self._tree = build_index3(local, copy=False, weights=weights)
        self.n = len(pts)
        self.total = float(len(pts) if weights is None else np.sum(weights))
        span = np.ptp(local, axis=0) if len(local) else np.ones(3)
        self._volume = float(np.prod(np.where(span > 0, span, max(span.max(), 1e-300))))

    def weight_at(self, x):
        """The number of indexed points (weighted: their weight) at exactly each of the
        indexed points x (q, 3), input coordinates: one descent of the tree per point
        (``PointIndex.weight_at`` in the plane)."""
        q = np.ascontiguousarray(self._metric.frame(np.asarray(x, float)))
        out = np.empty(len(q))
        in_chunks(lambda a, b: weights_at3(self._tree, q, out, a, b), len(q))
        return out

    def kth(self, x, k):
        """d_{P,k} at points x (q, 3) in input coordinates."""
        return self.kth_local(self._metric.frame(x), k)

    def kth_local(self, x, k=None):
        """d_{P,k} at points x (q, 3) relative to the torus origin (periodic coordinates
        wrapped here), on every core."""
        k = float(self.k if k is None else k)
        q = np.ascontiguousarray(self._metric.frame(np.asarray(x, float) + self._origin))
        if self._weights is None and k < WINDOWS_FROM_K:  # scipy's k-nearest query is faster
            return self._scipy_tree().query(q, k=[int(k)], workers=-1)[0][:, 0]
        return self.windows(q, k)

    def windows(self, q, k):
        """d_{P,k} at points q (q, 3) of the frame (periodic coordinates in [0, period)) by
        the counting tree's windows, whatever k (``kth_local`` takes scipy's query below
        WINDOWS_FROM_K; ``benchmarks/exact_kth3.py`` times both)."""
        k = float(k)
        q = np.ascontiguousarray(q, np.float64)
        m = len(q)
        guess, width = self._guess(q, k)
        r_in, r_out = guess / width, guess * width
        per_point = self.total / max(self.n, 1) if self._weights is not None else 1.0
        cap = int(min(self.n, 4.0 * k / max(per_point, 1e-300) + 1024)) + 1
        periodic = np.asarray(self._metric.periodic, bool)
        out = np.empty(m)
        tree, period = self._tree, self._period

        def chunk(a, b):
            kth_distances3(tree, q, k, r_in, r_out, period, periodic, cap, out, a, b)

        in_chunks(chunk, m, most=kth_range(k))
        lost = np.flatnonzero(np.isnan(out))
        if len(lost):  # more ties than a window holds (rare): scipy's tree
            ck = self._scipy_tree()
            if self._weights is None:
                out[lost] = ck.query(q[lost], k=[int(k)], workers=-1)[0][:, 0]
            else:
                out[lost] = weighted_kth(ck, self._weights, q[lost], k, -1)
        return out

    def _scipy_tree(self):
        """scipy's periodic kd-tree of the points (frame coordinates), built once."""
        if getattr(self, "_ck", None) is None:
            self._ck = self._metric.tree(self._points)
        return self._ck

    def _guess(self, q, k):
        """(a guess of d_{P,k} at the queries q (frame), the window's factor about it): the
        k_s-th distance in a seeded sample of an eighth of P, at most GUESS_SAMPLE points
        (k_s: the sample's share of the points that hold weight k, at least 1), scaled by the
        cube root of the ratio of the two counts (a ball's count grows with its volume), in
        a window of about two of its standard deviations (the count's relative noise
        1 / sqrt(k_s), a third of it in the radius); below 8000 points, the radius holding k
        points at the mean density, halved and doubled. A poor guess costs only retries
        (wider windows), never a wrong answer."""
        s = min(self.n // 8, GUESS_SAMPLE)
        if s < 1000:  # few points: any window is cheap
            uniform = k * self._volume / (4.0 / 3.0 * np.pi * max(self.total, 1e-300))
            return np.full(len(q), uniform ** (1 / 3)), 2.0
        if getattr(self, "_sample_tree", None) is None:
            pick = np.random.default_rng(0).choice(self.n, s, replace=False)
            self._sample_tree = self._metric.tree(self._points[pick])
        points = k * self.n / max(self.total, 1e-300)  # points holding weight k, on average
        ks = max(int(round(points * s / self.n)), 1)
        d = self._sample_tree.query(q, k=[ks], workers=-1)[0][:, 0]
        d = d * (points * s / (ks * self.n)) ** (1 / 3)
        fine = np.isfinite(d) & (d > 0)
        width = float(np.clip(1.0 + 2.0 / (3.0 * np.sqrt(ks)), 1.03, 2.0))
        return np.where(fine, d, np.max(d[fine]) if fine.any() else 1.0), width


GUESS_SAMPLE = 30000  # points of P sampled for Index's guesses of d_Pk
# Index's windows from this k on (unweighted; below it scipy's k-nearest query was
# faster: ``benchmarks/exact_kth3.py`` at 10^5 clustered points, k = 64, 0.95 against 0.78 s;
# k = 128, 0.98 against 1.10 s)
WINDOWS_FROM_K = 100


class Pieces:
    """Linear pieces over the box in space, from a ``Mesh`` in space and exact d_{P,k}
    (``kth(x)``: at points given relative to the torus origin). It works in the frame of the
    mesh's torus: relative to its origin, periodic axes wrapped (``metric.BoxMetric``), where
    the mesh's offsets apply; the pieces are cut at the box's faces along non-periodic axes,
    so that they tile the box exactly.

    ``subdivide``: also exact at the edges' midpoints, each tetrahedron cut into eight (its
    corners' four and the central octahedron's four, split along one diagonal): d_{P,k} is a
    distance, peaked between its nodes, and the midpoints catch much of that.
    ``values``: d_{P,k} at the mesh's vertices; ``corners`` (t, 4, 3), ``d`` (t, 4) and
    ``volume`` (t,) the pieces, ``source`` (t,) the mesh's tetrahedron each comes from;
    ``bounds`` rigorous lower and upper bounds of d_{P,k} on each. ``kth`` is asked once,
    at ``nodes3(...)``'s points. ``frame``: (origin, period) of the torus where the mesh has
    none (a part of a mesh in parts: ``subset``)."""

    dim = 3

    def __init__(self, mesh, kth, subdivide=True, frame=None):
        self.mesh = mesh
        origin, period = (mesh.torus.origin, mesh.torus.period) if frame is None else frame
        origin = np.asarray(origin, float)
        self.origin = origin
        self.period = np.asarray(period, float)
        self._periodic = np.array(mesh.periodic)
        self.metric = BoxMetric((*origin, *(origin + self.period)), mesh.periodic)
        local, corners, mids, asked, inverse = nodes3(mesh, self.metric, self.period, subdivide)
        found = kth(asked)
        self.values = found[: len(local)]
        d = self.values[mesh.tetrahedra]
        source = np.arange(len(corners))
        if mids is not None:  # the edges' midpoints, each tetrahedron cut into eight
            nodes = np.concatenate([corners, mids], axis=1)  # (t, 10, 3)
            dm = found[len(local) :][inverse].reshape(-1, 6)
            values = np.concatenate([d, dm], axis=1)
            corners = nodes[:, self.EIGHT].reshape(-1, 4, 3)
            d = values[:, self.EIGHT].reshape(-1, 4)
            source = np.repeat(source, 8)
        # rigorous bounds of d_{P,k} on each piece from its exact corner values (before any
        # cut: a cut point's value is interpolated, not exact): d_{P,k} is 1-Lipschitz, so on
        # the piece it lies within d_i -+ the distance from corner i to the farthest corner
        far = np.zeros(d.shape)
        for i, j in self.PAIRS:  # pair by pair: no (pieces, 4, 4, 3) temporary
            edge = np.sqrt(((corners[:, i] - corners[:, j]) ** 2).sum(axis=1))
            np.maximum(far[:, i], edge, out=far[:, i])
            np.maximum(far[:, j], edge, out=far[:, j])
        self.bounds = (d - far).max(axis=1), (d + far).min(axis=1)
        lo = np.array(mesh.box[:3]) - origin
        hi = np.array(mesh.box[3:]) - origin
        self._box = lo, hi
        # cut at the box's faces, only the pieces that cross one (the others kept whole)
        free = np.flatnonzero(~self._periodic)
        reach = (corners.min(axis=1)[:, free] < lo[free]) | (
            corners.max(axis=1)[:, free] > hi[free]
        )
        cross = reach.any(axis=1)
        whole = [corners[~cross], d[~cross], source[~cross], *(b[~cross] for b in self.bounds)]
        corners, d, source = corners[cross], d[cross], source[cross]
        bounds = tuple(b[cross] for b in self.bounds)
        for a in free:
            flipped, d, first = clip_below(-corners, d, a, -lo[a])  # x >= lo, mirrored
            corners, d, again = clip_below(-flipped, d, a, hi[a])  # x <= hi
            bounds = tuple(b[first][again] for b in bounds)
            source = source[first][again]
        parts = zip(whole, (corners, d, source, *bounds), strict=True)
        corners, d, source, *bounds = (np.concatenate([w, c]) for w, c in parts)
        self.bounds = tuple(bounds)
        self.source = source
        self.corners = corners
        self.d = d
        self.volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
        self._locator = None
        self._extent = None

    # the eight tetrahedra of a tetrahedron cut at its edges' midpoints, as indices into its
    # corners 0-3 and midpoints 4-9 of the edges 01, 02, 03, 12, 13, 23
    EIGHT = np.array([
        [0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3],
        [5, 8, 4, 7], [5, 8, 7, 9], [5, 8, 9, 6], [5, 8, 6, 4],
    ])  # fmt: skip
    PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])

    def subset(self, cells):
        """The pieces of the mesh's tetrahedra marked in ``cells`` (a part's own, of a mesh in
        parts) for integrals, samples, the CDF and grids, points still located among all the
        pieces (a point of the part's strip may lie in another part's tetrahedron)."""
        keep = np.asarray(cells, bool)[self.source]
        out = copy.copy(self)
        out.corners, out.d, out.volume = self.corners[keep], self.d[keep], self.volume[keep]
        out.source = self.source[keep]
        out.bounds = tuple(b[keep] for b in self.bounds)
        out._extent = None
        out._knot_cache = None
        out.locate = self.locate  # the located pieces are all of them, interpolated there
        out.interpolate = self.interpolate
        return out

    # -- evaluation ----------------------------------------------------------------------
    def interpolate(self, x, values=None):
        """The interpolated d_{P,k} at the points x (q, 3) of the box (input coordinates,
        periodic axes wrapped)."""
        if values is not None:
            raise InputError(
                "interpolating other node values is built in the plane only: in space "
                "KnnDistance interpolates d_Pk itself"
            )
        tet, bary = self.locate(self.metric.frame(x))
        return np.einsum("qc,qc->q", bary, self.d[tet])

    def grid(self, shape):
        """(xs, ys, zs, values (nz, ny, nx)) at the centres of a grid over the box: each
        piece writes the centres it holds (``engine.raster.rasterise3``: no point location,
        about the grid's size plus the pieces' work); a centre on no piece by rounding is NaN
        (``KnnDistance.grid`` locates it)."""
        nz, ny, nx = shape
        lo, hi = (np.asarray(b, float) for b in (self.mesh.box[:3], self.mesh.box[3:]))
        step = (hi - lo) / np.array([nx, ny, nz])
        axes = [lo[a] + (np.arange(n) + 0.5) * step[a] for a, n in enumerate((nx, ny, nz))]
        out = np.full((nz, ny, nx), np.nan)
        corners, d = np.ascontiguousarray(self.corners), np.ascontiguousarray(self.d)
        x0 = np.ascontiguousarray(self._box[0], float)
        periodic = np.ascontiguousarray(self._periodic, bool)
        in_chunks(lambda a, b: rasterise3(corners, d, x0, step, periodic, out, a, b), len(corners))
        return (*axes, out)

    def integrate(self, func, rect):
        """Integral of func(d) over the box rect = [[x0, y0, z0], [x1, y1, z1]] (in the box,
        input coordinates): the pieces and their copies a period away along periodic axes
        (which tile space once), cut at the rect's faces, by a 4-point rule each."""
        lo = np.asarray(rect[0], float) - self.origin
        hi = np.asarray(rect[1], float) - self.origin
        c, d = self.corners, self.d
        if self._extent is None:  # the pieces' bounding boxes, once
            self._extent = (
                np.minimum(np.minimum(c[:, 0], c[:, 1]), np.minimum(c[:, 2], c[:, 3])),
                np.maximum(np.maximum(c[:, 0], c[:, 1]), np.maximum(c[:, 2], c[:, 3])),
            )
        cmin, cmax = self._extent
        total = 0.0
        # per axis and shift: which pieces meet the rect's slab, and which lie within it
        slabs = []
        for a in range(3):
            options = []
            for s in (-1, 0, 1) if self._periodic[a] else (0,):
                move = s * self.period[a]
                meets = (cmax[:, a] + move >= lo[a]) & (cmin[:, a] + move <= hi[a])
                if meets.any():
                    within = (cmin[:, a] + move >= lo[a]) & (cmax[:, a] + move <= hi[a])
                    options.append((s, meets, within))
            slabs.append(options)
        for sx, mx, wx in slabs[0]:
            for sy, my, wy in slabs[1]:
                mxy = mx & my
                if not mxy.any():
                    continue
                for sz, mz, wz in slabs[2]:
                    meets = mxy & mz
                    if not meets.any():
                        continue
                    move = np.array([sx, sy, sz]) * self.period
                    within = meets & wx & wy & wz
                    total += quadrature3(c[within] + move, d[within], func).sum()
                    cut = meets & ~within
                    if cut.any():
                        cc, dd = c[cut] + move, d[cut]
                        for axis in range(3):
                            flipped, dd, _ = clip_below(-cc, dd, axis, -lo[axis])
                            cc, dd, _ = clip_below(-flipped, dd, axis, hi[axis])
                        total += quadrature3(cc, dd, func).sum()
        return float(total)

    def sample(self, n, rng):
        """n points (input coordinates) from the density proportional to 1 / d^3 over the
        box: a piece chosen by an upper bound of its mass (d is linear on a piece, so its
        density peaks at a corner), a uniform point in it, kept with probability density /
        bound: exact rejection sampling of the piecewise estimate."""
        dmin = self.d.min(axis=1)
        cdf = np.cumsum(self.volume / dmin**3)
        out = np.empty((n, 3))
        filled = 0
        while filled < n:
            m = int(1.5 * (n - filled)) + 64
            t = np.minimum(
                np.searchsorted(cdf, rng.random(m) * cdf[-1], side="right"), len(cdf) - 1
            )
            w = rng.exponential(size=(m, 4))
            w /= w.sum(axis=1, keepdims=True)
            x = np.einsum("qi,qia->qa", w, self.corners[t])
            dx = np.einsum("qi,qi->q", w, self.d[t])
            keep = rng.random(m) * dx**3 <= dmin[t] ** 3
            x = x[keep][: n - filled]
            out[filled : filled + len(x)] = x
            filled += len(x)
        box = BoxMetric(self.mesh.box, self.mesh.periodic)
        return box.wrap(out + self.origin)

    def locate(self, x):
        """The tetrahedron (of the covering: the pieces and their copies one period back
        along each periodic axis) holding each wrapped point of the box, and its barycentric
        coordinates."""
        if self._locator is None:
            back = [[0, -1] if p else [0] for p in self._periodic]
            shifts = np.array(np.meshgrid(*back)).reshape(3, -1).T
            lo, hi = self.corners.min(axis=1), self.corners.max(axis=1)
            parts, sources = [], []
            for shift in shifts * self.period:  # the copies that meet the box, built alone
                meets = (hi + shift >= 0) & (lo + shift <= self.period) | ~self._periodic
                keep = np.flatnonzero(meets.all(axis=1))
                parts.append(self.corners[keep] + shift)
                sources.append(keep)  # the piece
            c, source = np.concatenate(parts), np.concatenate(sources)
            inv = np.linalg.inv(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))
            self._locator = (cKDTree(c.mean(axis=1)), np.ascontiguousarray(c[:, 0]),
                             np.ascontiguousarray(inv), source)  # fmt: skip
        tree, origin, inv, source = self._locator
        x = np.ascontiguousarray(x, float)
        tet = np.full(len(x), -1)
        bary = np.zeros((len(x), 4))
        todo = np.arange(len(x))
        for kk in (8, 64, 512):
            if len(todo) == 0:
                break
            cand = tree.query(x[todo], k=min(kk, len(origin)), workers=-1)[1]
            cand = np.ascontiguousarray(cand.reshape(len(todo), -1), np.int64)
            here, b = np.full(len(todo), -1), np.zeros((len(todo), 4))
            first_holding3(x[todo], cand, origin, inv, 1e-9, here, b)
            hit = here >= 0
            rows = todo[hit]
            tet[rows] = source[here[hit]]
            bary[rows] = b[hit]
            todo = todo[~hit]
        if len(todo):
            raise AssertionError(f"{len(todo)} points in no tetrahedron")
        return tet, bary

    # -- the kNN-CDF -------------------------------------------------------------------------
    def knots(self):
        """(knots (t, 4) sorted and kept apart, weights), computed once."""
        if getattr(self, "_knot_cache", None) is None:
            d = np.sort(self.d, axis=1)
            span = d[:, 3] - d[:, 0]
            # knots kept apart by a relative 1e-7 of the span (ties would divide by zero; the
            # share moves by about as much)
            gap = np.maximum(1e-7 * span, 1e-12 * np.maximum(d[:, 3], 1e-300))
            d = d + gap[:, None] * np.arange(4)
            self._knot_cache = (d, self.volume / self.volume.sum())
        return self._knot_cache

    def cdf(self, r):
        """CDF(r) = vol{x : d(x) <= r} / vol(box) for the interpolated d, at the radii r:
        every piece adds its weight from its top knot on and its B-spline share at the radii
        that cut it (``engine.bspline.weighted_shares``, one pass over the pieces)."""
        r = np.atleast_1d(np.asarray(r, float))
        d, w = self.knots()
        order = np.argsort(r, kind="stable")
        out = np.zeros(len(r))
        weighted_shares(d, w, r[order], out, np.zeros(len(r) + 1))
        result = np.empty(len(r))
        result[order] = out
        return result

    def cdf_bounds(self, r):
        """(lower, upper) bounds of the true kNN-CDF at the radii r: on a piece d_{P,k} lies
        within [max_i (d_i - e_i), min_i (d_i + e_i)], d_i its exact corner values and e_i
        the distance from corner i to the farthest corner (d_{P,k} is 1-Lipschitz); a piece
        counts whole where its upper end is <= r (lower bound), where its lower end is
        (upper bound)."""
        r = np.atleast_1d(np.asarray(r, float))
        w = self.knots()[1]

        def weight_at_most(ends):  # the pieces' weight with end <= each r: sorted once
            order = np.argsort(ends, kind="stable")
            total = np.concatenate([[0.0], np.cumsum(w[order])])
            return total[np.searchsorted(ends[order], r, side="right")]

        lower_d, upper_d = self.bounds
        return weight_at_most(upper_d), weight_at_most(lower_d)


def grid3(evaluate, lo, hi, shape):
    """(xs, ys, zs, values (nz, ny, nx)): ``evaluate`` at the centres of a grid of ``shape``
    (nz, ny, nx) over the box [lo, hi], a slice at a time (the memory of one slice)."""
    nz, ny, nx = shape
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [lo[a] + (np.arange(n) + 0.5) * (hi[a] - lo[a]) / n for a, n in enumerate((nx, ny, nz))]
    out = np.empty(nz * ny * nx)
    plane = np.column_stack([np.tile(axes[0], ny), np.repeat(axes[1], nx)])
    for z in range(nz):
        x = np.column_stack([plane, np.full(len(plane), axes[2][z])])
        out[z * ny * nx : (z + 1) * ny * nx] = evaluate(x)
    return (*axes, out.reshape(nz, ny, nx))


def nodes3(mesh, metric, period, subdivide=True):
    """Where ``Pieces`` needs exact d_{P,k}: (local, corners, mids, asked, inverse).
    ``local`` (m, 3) the vertices relative to the torus origin (``metric``: its frame),
    ``corners`` (t, 4, 3) the tetrahedra's there (unwrapped by their offsets), ``mids`` (t, 6,
    3) their edges' midpoints (None without ``subdivide``); ``asked`` the vertices then, with
    ``subdivide``, each distinct edge's midpoint once (7.4 edges per vertex, against 38
    tetrahedron edges: the same edge seen from two tetrahedra may be shifted by whole periods,
    where the periodic kd-tree gives the same distance); ``inverse`` each tetrahedron edge's
    (in ``Pieces.PAIRS`` order) row among those midpoints."""
    local = metric.frame(mesh.vertices)  # exact: the engine's grid
    corners = local[mesh.tetrahedra]  # relative to the origin, unwrapped
    if mesh.offsets is not None:
        corners = corners + mesh.offsets * period
    if not subdivide:
        return local, corners, None, local, None
    pairs = Pieces.PAIRS
    mids = 0.5 * (corners[:, pairs[:, 0]] + corners[:, pairs[:, 1]])
    first, inverse = edges3(mesh.tetrahedra, mesh.offsets, pairs)
    return local, corners, mids, np.concatenate([local, mids.reshape(-1, 3)[first]]), inverse


def edges3(tetrahedra, offsets, pairs):
    """The tetrahedra's edges (the corner pairs ``pairs`` of each, flattened tetrahedron by
    tetrahedron) as (first, inverse): the flat index of each distinct edge's first
    occurrence, and each occurrence's distinct edge. An edge is its two vertices and the
    offset of one relative to the other (a vertex may meet another across several periods)."""
    a = tetrahedra[:, pairs[:, 0]].ravel().astype(np.int64)
    b = tetrahedra[:, pairs[:, 1]].ravel().astype(np.int64)
    if offsets is None:
        rel = np.zeros((len(a), 3), np.int64)
    else:
        rel = (offsets[:, pairs[:, 1]] - offsets[:, pairs[:, 0]]).reshape(-1, 3).astype(np.int64)
    # the same edge from its other end: (b, a, -rel); keep the smaller of the two
    x, y, z = rel.T
    back = (a > b) | ((a == b) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    a, b = np.where(back, b, a), np.where(back, a, b)
    rel[back] *= -1
    if len(a) and b.max() < 2**27 and np.abs(rel).max() <= 3:  # one 63-bit key
        key = (a << 36) | (b << 9) | ((rel[:, 0] + 3) * 49 + (rel[:, 1] + 3) * 7 + rel[:, 2] + 3)
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    else:
        rows = np.column_stack([a, b, rel])
        _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def clip_below(corners, values, axis, bound):
    """The parts of tetrahedra (t, 4, 3), carrying linear functions with corner values
    (t, 4), where coordinate ``axis`` is <= ``bound``, as tetrahedra (corners, values, the
    tetrahedron each came from): a tetrahedron with one corner there leaves a tetrahedron,
    with two or three a prism (three tetrahedra, its quadrilaterals in the faces and the
    plane). Orientation is not kept."""
    below = corners[:, :, axis] <= bound
    count = below.sum(axis=1)
    crossing = np.flatnonzero((count > 0) & (count < 4))  # the others kept or dropped whole
    order = np.argsort(~below[crossing], axis=1, kind="stable")  # the corners below first
    c = np.take_along_axis(corners[crossing], order[..., None], 1)
    v = np.take_along_axis(values[crossing], order, 1)
    count_of = count[crossing]

    def cut(i, j, rows):
        """Where edge (i, j) of the tetrahedra ``rows`` meets the plane, and the value."""
        xi, xj = c[rows, i], c[rows, j]
        s = (bound - xi[:, axis]) / (xj[:, axis] - xi[:, axis])
        p = xi + s[:, None] * (xj - xi)
        p[:, axis] = bound
        return p, v[rows, i] + s * (v[rows, j] - v[rows, i])

    def prism(p, q):
        """Three tetrahedra of the prism with triangles p and q (lists of (points, values)),
        p[i] joined to q[i]."""
        parts = [(p[0], p[1], p[2], q[0]), (p[1], p[2], q[0], q[1]), (p[2], q[0], q[1], q[2])]
        return [(np.stack([x[0] for x in t], 1), np.stack([x[1] for x in t], 1)) for t in parts]

    inside = np.flatnonzero(count == 4)
    out = [(corners[inside], values[inside])]
    source = [inside]
    rows = np.flatnonzero(count_of == 1)  # rows of the crossing ones
    source.append(crossing[rows])
    a = (c[rows, 0], v[rows, 0])
    b, cc, d = cut(0, 1, rows), cut(0, 2, rows), cut(0, 3, rows)
    out.append((np.stack([a[0], b[0], cc[0], d[0]], 1), np.stack([a[1], b[1], cc[1], d[1]], 1)))
    rows = np.flatnonzero(count_of == 2)
    source += [crossing[rows]] * 3
    a, b = (c[rows, 0], v[rows, 0]), (c[rows, 1], v[rows, 1])
    out += prism([a, cut(0, 2, rows), cut(0, 3, rows)], [b, cut(1, 2, rows), cut(1, 3, rows)])
    rows = np.flatnonzero(count_of == 3)
    source += [crossing[rows]] * 3
    base = [(c[rows, i], v[rows, i]) for i in range(3)]
    out += prism(base, [cut(i, 3, rows) for i in range(3)])
    return (
        np.concatenate([x[0] for x in out]),
        np.concatenate([x[1] for x in out]),
        np.concatenate(source),
    )


def share_below(d, r):
    """The share of each tetrahedron where the linear function with sorted corner values d
    (t, 4), distinct, is <= r (``engine.bspline``)."""
    out = np.empty(len(d))
    shares_below(np.ascontiguousarray(d, float), float(r), out)
    return out


# the 4-point degree-2 rule on the reference tetrahedron (barycentric points, equal weights)
_A, _B = 0.5854101966249685, 0.1381966011250105
_QP = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])


def quadrature3(corners, d, func):
    """Per tetrahedron: integral of func(d) with d linear (values d at the corners), by the
    4-point rule of degree 2."""
    if len(corners) == 0:
        return np.zeros(0)
    volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
    return volume * func(d @ _QP.T).mean(axis=1)


def complex_of(mesh, subdivide=True):
    """The mesh's cells as a complex (as the plane's), each tetrahedron subdivided in eight
    through its edge midpoints: (positions, the same as nodes in the index's frame, the
    tetrahedra). EngineError where it would not be simplicial."""
    tets = mesh.tetrahedra.astype(np.int64)
    pairs = Pieces.PAIRS
    # a geometric edge is its two vertices and the offset between them; the complex is
    # simplicial when no two of them join the same vertex pair and none a vertex to itself
    first, inverse = edges3(tets, mesh.offsets, pairs)
    a = tets[:, pairs[:, 0]].ravel()[first]
    b = tets[:, pairs[:, 1]].ravel()[first]
    if np.any(a == b) or len(
        np.unique(np.minimum(a, b) * len(mesh.vertices) + np.maximum(a, b))
    ) < len(first):
        raise not_simplicial()
    if not subdivide:
        used = np.unique(tets)
        return mesh.vertices[used], mesh.vertices[used], np.searchsorted(used, tets)
    corners = mesh.corners()
    mids = 0.5 * (corners[:, pairs[:, 0]] + corners[:, pairs[:, 1]]).reshape(-1, 3)[first]
    mid_ids = len(mesh.vertices) + inverse.reshape(len(tets), 6)
    nodes = np.concatenate([tets, mid_ids], axis=1)  # corners 0-3, midpoints 4-9
    cells = nodes[:, Pieces.EIGHT].reshape(-1, 4)
    positions = np.concatenate([mesh.vertices, to_frame(mesh)(mids)])
    used = np.unique(cells)
    return positions[used], positions[used], np.searchsorted(used, cells)
