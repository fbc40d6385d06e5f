"""d_{P,k} anywhere in a box of three dimensions, the kNN density, and the kNN-CDF, from a
``Mesh3``.

As in the plane (``density.py``): exact d_{P,k} at the mesh's vertices (one query of a
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

import numpy as np
from scipy.spatial import cKDTree

from .certify import check_source
from .engine.bspline import shares_below, weighted_shares
from .errors import InputError
from .validation import as_points, check_inside


class KnnDistance3:
    """d_{P,k} at any point of the box, from a ``Mesh3`` and its points (NaN beyond the box
    along a non-periodic axis).

    ``subdivide`` (default): also exact at the edges' midpoints, each tetrahedron cut into
    eight (its corners' four and the central octahedron's four, split along one diagonal):
    d_{P,k} is a distance, peaked between its nodes, and the midpoints catch much of that."""

    def __init__(self, mesh, points, subdivide=True):
        pts = as_points(points, 3)
        if len(pts) < mesh.k:
            raise InputError(f"{len(pts)} points but k = {mesh.k}: d_Pk is infinite")
        check_source(mesh.stats, len(pts), None)
        check_inside(pts, mesh.box, mesh.periodic, warn=False)
        self.mesh, self.k, self.n = mesh, mesh.k, len(pts)
        self.period = np.asarray(mesh.period, float)
        self._periodic = np.array(mesh.periodic)
        self._points = mesh.metric.tree(pts)  # in the mesh's frame, periodic axes wrapping
        self.values = self._query(mesh.local)
        corners = mesh.corners()  # relative to the origin, unwrapped
        d = self.values[mesh.tetrahedra]
        if subdivide:
            corners, d = self._subdivided(corners, d)
        # rigorous bounds of d_{P,k} on each piece from its exact corner values (before any
        # cut: a cut point's value is interpolated, not exact): d_{P,k} is 1-Lipschitz, so on
        # the piece it lies within d_i -+ the distance from corner i to the farthest corner
        far = np.zeros(d.shape)
        for i, j in self._PAIRS:  # pair by pair: no (pieces, 4, 4, 3) temporary
            edge = np.sqrt(((corners[:, i] - corners[:, j]) ** 2).sum(axis=1))
            np.maximum(far[:, i], edge, out=far[:, i])
            np.maximum(far[:, j], edge, out=far[:, j])
        self._bounds = (d - far).max(axis=1), (d + far).min(axis=1)
        lo = np.array(mesh.box[:3]) - np.asarray(mesh.origin)
        hi = np.array(mesh.box[3:]) - np.asarray(mesh.origin)
        for a in np.flatnonzero(~self._periodic):  # cut at the box's faces
            flipped, d, source = clip_below(-corners, d, a, -lo[a])  # x >= lo, mirrored
            corners, d, again = clip_below(-flipped, d, a, hi[a])  # x <= hi
            self._bounds = tuple(b[source][again] for b in self._bounds)
        self._corners = corners
        self._d = d
        self._volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
        self._locator = None

    # the eight tetrahedra of a tetrahedron cut at its edges' midpoints, as indices into its
    # corners 0-3 and midpoints 4-9 of the edges 01, 02, 03, 12, 13, 23
    _EIGHT = np.array([
        [0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3],
        [5, 8, 4, 7], [5, 8, 7, 9], [5, 8, 9, 6], [5, 8, 6, 4],
    ])  # fmt: skip
    _PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])

    def _query(self, x):
        """Exact d_{P,k} at x (q, 3) in the mesh's frame (the kd-tree wraps queries along its
        periodic axes itself), on every core."""
        return self._points.query(x, k=[self.k], workers=-1)[0][:, 0]

    def _subdivided(self, corners, d):
        mids = 0.5 * (corners[:, self._PAIRS[:, 0]] + corners[:, self._PAIRS[:, 1]])
        # one query per edge, not per tetrahedron's edge (7.4 edges per vertex, against 38
        # tetrahedron edges): the same edge seen from two tetrahedra may be shifted by whole
        # periods, where the periodic kd-tree gives the same distance
        first, inverse = _edges(self.mesh.tetrahedra, self.mesh.offsets, self._PAIRS)
        dm = self._query(mids.reshape(-1, 3)[first])[inverse]
        nodes = np.concatenate([corners, mids], axis=1)  # (t, 10, 3)
        values = np.concatenate([d, dm.reshape(-1, 6)], axis=1)
        return nodes[:, self._EIGHT].reshape(-1, 4, 3), values[:, self._EIGHT].reshape(-1, 4)

    # -- evaluation ------------------------------------------------------------------------
    def exact(self, x):
        """Exact d_{P,k} at the points x (..., 3) (the periodic kd-tree: the reference)."""
        flat = as_points(np.reshape(x, (-1, 3)), 3)
        return self._query(self.mesh.wrap(flat)).reshape(np.shape(x)[:-1])

    def __call__(self, x):
        """The interpolated d_{P,k} at the points x (..., 3); NaN beyond the box."""
        flat = self.mesh.wrap(as_points(np.reshape(x, (-1, 3)), 3))
        out = np.full(len(flat), np.nan)
        inside = self.mesh.inside(flat)
        tet, bary = self._locate(flat[inside])
        out[inside] = np.einsum("qc,qc->q", bary, self._d[tet])
        return out.reshape(np.shape(x)[:-1])

    def _locate(self, x):
        """The tetrahedron (of the covering: the pieces and their copies one period back
        along each periodic axis) holding each wrapped point of the box, and its barycentric
        coordinates."""
        if self._locator is None:
            back = [[0, -1] if p else [0] for p in self._periodic]
            shifts = np.array(np.meshgrid(*back)).reshape(3, -1).T
            c = self._corners[None] + (shifts * self.period)[:, None, None, :]
            c = c.reshape(-1, 4, 3)
            source = np.tile(np.arange(len(self._corners)), len(shifts))  # the piece
            lo, hi = c.min(axis=1), c.max(axis=1)
            meets = ((hi >= 0) & (lo <= self.period) | ~self._periodic).all(axis=1)
            c, source = c[meets], source[meets]
            inv = np.linalg.inv(np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1)))
            self._locator = (cKDTree(c.mean(axis=1)), c[:, 0], inv, source)
        tree, origin, inv, source = self._locator
        tet = np.full(len(x), -1)
        bary = np.zeros((len(x), 4))
        todo = np.arange(len(x))
        for kk in (8, 64, 512):
            if len(todo) == 0:
                break
            cand = tree.query(x[todo], k=min(kk, len(origin)))[1].reshape(len(todo), -1)
            rel = x[todo, None, :] - origin[cand]
            l123 = np.einsum("qcij,qcj->qci", inv[cand], rel)
            l0 = 1.0 - l123.sum(axis=2)
            inside = (l0 >= -1e-9) & (l123 >= -1e-9).all(axis=2)
            hit = inside.any(axis=1)
            j = np.argmax(inside, axis=1)[hit]
            rows = todo[hit]
            tet[rows] = source[cand[hit, j]]
            bary[rows, 0] = l0[hit, j]
            bary[rows, 1:] = l123[hit, j]
            todo = todo[~hit]
        if len(todo):
            raise AssertionError(f"{len(todo)} points in no tetrahedron")
        return tet, bary

    # -- the kNN-CDF -------------------------------------------------------------------------
    def _knots(self):
        """(knots (t, 4) sorted and kept apart, weights), computed once."""
        if getattr(self, "_knot_cache", None) is None:
            d = np.sort(self._d, axis=1)
            span = d[:, 3] - d[:, 0]
            # knots kept apart by a relative 1e-7 of the span (ties would divide by zero; the
            # share moves by about as much)
            gap = np.maximum(1e-7 * span, 1e-12 * np.maximum(d[:, 3], 1e-300))
            d = d + gap[:, None] * np.arange(4)
            self._knot_cache = (d, self._volume / self._volume.sum())
        return self._knot_cache

    def cdf(self, r):
        """CDF(r) = vol{x : d(x) <= r} / vol(box) for the interpolated d, at the radii r:
        every piece adds its weight from its top knot on and its B-spline share at the radii
        that cut it (``engine.bspline.weighted_shares``, one pass over the pieces)."""
        r = np.atleast_1d(np.asarray(r, float))
        d, w = self._knots()
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
        w = self._knots()[1]

        def weight_at_most(ends):  # the pieces' weight with end <= each r: sorted once
            order = np.argsort(ends, kind="stable")
            total = np.concatenate([[0.0], np.cumsum(w[order])])
            return total[np.searchsorted(ends[order], r, side="right")]

        lower_d, upper_d = self._bounds
        return weight_at_most(upper_d), weight_at_most(lower_d)


def _edges(tetrahedra, offsets, pairs):
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
    order = np.argsort(~below, axis=1, kind="stable")  # the corners below first
    c = np.take_along_axis(corners, order[..., None], 1)
    v = np.take_along_axis(values, order, 1)

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

    out = [(corners[count == 4], values[count == 4])]
    source = [np.flatnonzero(count == 4)]
    rows = np.flatnonzero(count == 1)
    source.append(rows)
    a = (c[rows, 0], v[rows, 0])
    b, cc, d = cut(0, 1, rows), cut(0, 2, rows), cut(0, 3, rows)
    out.append((np.stack([a[0], b[0], cc[0], d[0]], 1), np.stack([a[1], b[1], cc[1], d[1]], 1)))
    rows = np.flatnonzero(count == 2)
    source += [rows] * 3
    a, b = (c[rows, 0], v[rows, 0]), (c[rows, 1], v[rows, 1])
    out += prism([a, cut(0, 2, rows), cut(0, 3, rows)], [b, cut(1, 2, rows), cut(1, 3, rows)])
    rows = np.flatnonzero(count == 3)
    source += [rows] * 3
    base = [(c[rows, i], v[rows, i]) for i in range(3)]
    out += prism(base, [cut(i, 3, rows) for i in range(3)])
    return (
        np.concatenate([x[0] for x in out]),
        np.concatenate([x[1] for x in out]),
        np.concatenate(source),
    )


def _share_below(d, r):
    """The share of each tetrahedron where the linear function with sorted corner values d
    (t, 4), distinct, is <= r (``engine.bspline``)."""
    out = np.empty(len(d))
    shares_below(np.ascontiguousarray(d, float), float(r), out)
    return out


# the 4-point degree-2 rule on the reference tetrahedron (barycentric points, equal weights)
_A, _B = 0.5854101966249685, 0.1381966011250105
_QP = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])


class KnnDensity3:
    """The kNN density in space, f(x) = k / (n (4/3) pi d_{P,k}(x)^3), from a ``Mesh3``;
    ``normalized`` (default) divides by its integral over the box (a 4-point rule on each
    tetrahedron)."""

    def __init__(self, mesh, points, normalized=True):
        self.distance = KnnDistance3(mesh, points)
        self.raw_constant = mesh.k / (self.distance.n * 4.0 / 3.0 * np.pi)
        dq = self.distance._d @ _QP.T  # (t, 4): d at the rule's points
        vol = self.distance._volume
        self.raw_mass = float((vol * (self.raw_constant / dq**3).mean(axis=1)).sum())
        self.constant = self.raw_constant / self.raw_mass if normalized else self.raw_constant

    def __call__(self, x):
        return self.constant / self.distance(x) ** 3
