"""d_{P,k} on the sphere from a mesh: linear pieces over the spherical triangles
(``Pieces``, as in the plane and in space).

The nodes are the mesh's unit vectors and, subdivided, its edges' midpoints pushed onto the
sphere; each triangle is split in four through them. A query is located by the ray through
it: it lies in the piece (a, b, c) where x = la a + lb b + lc c with every l >= 0, and the
value there is the linear interpolation with the weights l / (la + lb + lc) (the central
projection of the flat triangle, exact at the nodes and continuous across edges, which the
pieces share). Integrals over the sphere use Dunavant's 7-point rule on each flat triangle
with the projection's area element det[a, b, c] / |y|^3 (y the flat point), so that a
constant integrates to the sphere's area 4 pi R^2 to the rule's accuracy. Lengths are
great-circle distances times the sphere's radius R; the kNN density uses the cap's area,
pi (chord)^2 (Archimedes), through ``equal_area_radius``.
"""

import numpy as np
from scipy.spatial import cKDTree

from ..._engine.threads import in_chunks, kth_range
from ..._metric import chord_to_angle, lonlat_of, unit_vectors, weighted_kth
from ..._validation import answerable as answerable_on_sphere
from ..._validation import sphere_points_of_run
from ...mesh import TRIANGLE_RULE_POINTS, TRIANGLE_RULE_WEIGHTS, edges, split_in_four

CANDIDATES = (8, 32)  # pieces tried per query, by the nearest centroids, before all of them


class Index:
    """Exact d_{P,k} on the sphere: a kd-tree over the points' unit vectors (chords order
    points as great-circle angles do); ``kth`` at unit vectors (the domain's ``to_frame``), in
    the sphere's length unit (angle times ``radius``)."""

    def __init__(self, unit, weights, radius):
        self.tree = cKDTree(unit)
        self.weights = weights
        self.radius = float(radius)

    def kth(self, x, k):
        if self.weights is None:  # in short ranges on threads: Ctrl-C waits for few
            x = np.asarray(x, float).reshape(-1, 3)
            chord = np.empty(len(x))

            def part(a, b):
                chord[a:b] = self.tree.query(x[a:b], k=[int(k)])[0][:, 0]

            in_chunks(part, len(x), most=kth_range(k))
        else:
            chord = weighted_kth(self.tree, self.weights, x, k, -1)
        return chord_to_angle(chord) * self.radius


def to_frame(mesh):
    """The map from (longitude, latitude) degrees (q, 2) to the frame of the pieces and the
    index: unit vectors."""
    return unit_vectors


def answerable(mesh):
    """The rule of the query points the uses answer: ``validation.answerable``'s on the
    sphere (finite, latitudes within +-90; longitudes wrap)."""
    return lambda x: answerable_on_sphere(x, True)


def flat_radius(mesh, d):
    """The radius of the flat disk as large as the cap of great-circle radius d: the chord
    (``equal_area_radius``)."""
    return equal_area_radius(d, mesh.radius)


def points_of(mesh, points, weights):
    """The points as unit vectors (n, 3), weights and total of the run a mesh was refined
    from, checked (``validation.sphere_points_of_run``)."""
    return sphere_points_of_run(mesh, points, weights)


def index_of(mesh, unit, weights=None):
    """Exact d_{P,k} for the mesh's points (unit vectors): ``Index``, ``kth(x, k)`` at unit
    vectors."""
    return Index(unit, weights, mesh.radius)


def build(mesh, points, weights, subdivide):
    """What ``KnnDistance`` keeps of a mesh on the sphere: (the points in lon/lat, the exact
    index, the pieces, the points' number or total weight)."""
    unit, weights, total = points_of(mesh, points, weights)
    index = index_of(mesh, unit, weights)
    return lonlat_of(unit), index, Pieces(mesh, index, mesh.k, subdivide), total


class Pieces:
    """Linear pieces of d_{P,k} over the sphere (module docstring): ``nodes`` (p, 3) unit
    vectors, ``triangles`` (t, 3), ``values`` (p,) exact d_{P,k} at the nodes."""

    dim = 2

    def __init__(self, mesh, index, k, subdivide=True):
        xyz = np.asarray(mesh.xyz, float)
        tri = np.asarray(mesh.triangles, np.int64)
        if subdivide:
            pairs, _, tri = split_in_four(tri, len(xyz), edges(tri))
            mids = xyz[pairs[:, 0]] + xyz[pairs[:, 1]]
            xyz = np.concatenate([xyz, mids / np.linalg.norm(mids, axis=1, keepdims=True)])
        self.nodes, self.triangles = xyz, tri
        self.radius = index.radius
        self.values = index.kth(xyz, k)
        corners = xyz[tri]  # (t, 3 corners, 3 axes)
        # x = corners^T l: l = inverse(corners^T) x, one 3 x 3 inverse per piece
        self._inverse = np.linalg.inv(np.transpose(corners, (0, 2, 1)))
        centroid = corners.sum(axis=1)
        self._centroids = cKDTree(centroid / np.linalg.norm(centroid, axis=1, keepdims=True))
        self._det = np.abs(np.linalg.det(corners))

    def locate(self, x):
        """(piece, weights (q, 3) summing to 1) of unit vectors x (q, 3)."""
        piece = np.full(len(x), -1, np.int64)
        weights = np.zeros((len(x), 3))
        todo = np.arange(len(x))
        for count in (*CANDIDATES, len(self.triangles)):
            if len(todo) == 0:
                break
            count = min(count, len(self.triangles))
            cand = self._centroids.query(x[todo], k=count)[1].reshape(len(todo), count)
            lam = np.einsum("qkij,qj->qki", self._inverse[cand], x[todo])
            ok = lam.min(axis=2) >= -1e-12 * np.abs(lam).max(axis=2)
            found = ok.any(axis=1)
            first = np.argmax(ok, axis=1)
            rows = np.flatnonzero(found)
            piece[todo[rows]] = cand[rows, first[rows]]
            got = np.clip(lam[rows, first[rows]], 0.0, None)
            weights[todo[rows]] = got / got.sum(axis=1, keepdims=True)
            todo = todo[~found]
            if count == len(self.triangles):
                break
        return piece, weights

    def interpolate(self, x, values=None):
        """Node values (default d_{P,k}'s) at unit vectors x (q, 3)."""
        values = np.asarray(self.values if values is None else values, float)
        piece, w = self.locate(np.asarray(x, float))
        out = np.full((len(x), *values.shape[1:]), np.nan)
        ok = piece >= 0
        v = values[self.triangles[piece[ok]]]
        out[ok] = np.einsum("qc,qc...->q...", w[ok], v)
        return out

    def grid(self, shape):
        """(longitudes, latitudes, values (ny, nx)) at the centres of a ny x nx grid of
        longitude [-180, 180] by latitude [-90, 90]."""
        ny, nx = shape
        lon = -180.0 + (np.arange(nx) + 0.5) * 360.0 / nx
        lat = -90.0 + (np.arange(ny) + 0.5) * 180.0 / ny
        grid = np.stack(np.meshgrid(lon, lat), axis=-1).reshape(-1, 2)
        return lon, lat, self.interpolate(unit_vectors(grid)).reshape(ny, nx)

    def _rule(self):
        """(points (t, 7, 3) on the sphere, area weights (t, 7), d there (t, 7)): the 7-point
        rule on each flat piece, carried onto the sphere by the central projection."""
        corners = self.nodes[self.triangles]
        flat = np.einsum("qc,tca->tqa", TRIANGLE_RULE_POINTS, corners)
        norm = np.linalg.norm(flat, axis=2)
        # the reference triangle's area 1/2 times the projection's element det / |y|^3
        area = 0.5 * self._det[:, None] / norm**3 * TRIANGLE_RULE_WEIGHTS * self.radius**2
        d = self.values[self.triangles] @ TRIANGLE_RULE_POINTS.T
        return flat / norm[..., None], area, d

    def integrate(self, func, region=None):
        """Integral of func(d) over the sphere, or over the part of it in the longitude and
        latitude box ``region`` (lon0, lat0, lon1, lat1) (the rule's points inside it count:
        exact up to the pieces the region's border crosses)."""
        points, area, d = self._rule()
        weight = area
        if region is not None:
            lon0, lat0, lon1, lat1 = region
            at = lonlat_of(points)
            lon = (at[..., 0] - lon0) % 360.0
            inside = (lon <= (lon1 - lon0)) & (at[..., 1] >= lat0) & (at[..., 1] <= lat1)
            weight = np.where(inside, area, 0.0)
        return float((func(d) * weight).sum())

    def sample(self, n, rng, power=2):
        """n points (lon, lat) from the density proportional to 1 / chord(d)^power: a piece
        by an upper bound of its mass, a point uniform on its spherical triangle (uniform on
        the flat one, kept with the projection's element over its bound), kept with density
        over the piece's bound (d is linear on a piece: the density peaks at a corner)."""
        corners = self.nodes[self.triangles]
        d = self.values[self.triangles]
        chord = self._equal_area(d)
        dmin = chord.min(axis=1)
        norm_min = _least_norm(corners)
        element = 0.5 * self._det / norm_min**3  # the projection's element at most this
        bound = element / dmin**power
        cdf = np.cumsum(bound)
        out = np.empty((n, 3))
        filled = 0
        while filled < n:
            m = int(2 * (n - filled)) + 64
            t = np.minimum(np.searchsorted(cdf, rng.random(m) * cdf[-1], side="right"),
                           len(cdf) - 1)  # fmt: skip
            u = rng.random((m, 2))
            fold = u.sum(axis=1) > 1
            u[fold] = 1.0 - u[fold]
            lam = np.column_stack([1.0 - u[:, 0] - u[:, 1], u])
            y = np.einsum("qc,qca->qa", lam, corners[t])
            ny = np.linalg.norm(y, axis=1)
            keep = rng.random(m) * norm_min[t] ** -3 <= ny**-3  # uniform on the sphere
            dx = self._equal_area((lam * d[t]).sum(axis=1))
            keep &= rng.random(m) * dx**power <= dmin[t] ** power
            x = (y / ny[:, None])[keep][: n - filled]
            out[filled : filled + len(x)] = x
            filled += len(x)
        return lonlat_of(out)

    def _equal_area(self, d):
        return equal_area_radius(d, self.radius)


def _least_norm(corners):
    """A lower bound of |y| over each flat triangle (t, 3, 3) of unit corners: the distance
    from the centre to its plane."""
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.abs(np.einsum("ta,ta->t", n, corners[:, 0]))


def equal_area_radius(d, radius):
    """The radius of the flat disk whose area is the spherical cap's of great-circle radius
    d on the sphere of ``radius``: the chord 2 R sin(d / 2R) (Archimedes: the cap's area is
    pi chord^2), so that the kNN density is k / (n pi chord^2) per unit area."""
    return 2.0 * radius * np.sin(0.5 * np.minimum(np.asarray(d, float) / radius, np.pi))


def complex_of(mesh, subdivide=True):
    """The sphere's triangulation as a complex (closed: every edge borders two triangles),
    subdivided through the edge midpoints pushed onto the sphere: (positions in lon/lat,
    the nodes as unit vectors, the triangles)."""
    tri = mesh.triangles.astype(np.int64)
    xyz = np.asarray(mesh.xyz, float)
    if not subdivide:
        return lonlat_of(xyz), xyz, tri
    pairs, _, tri = split_in_four(tri, len(xyz))
    mids = xyz[pairs[:, 0]] + xyz[pairs[:, 1]]
    nodes = np.concatenate([xyz, mids / np.linalg.norm(mids, axis=1, keepdims=True)])
    return lonlat_of(nodes), nodes, tri
