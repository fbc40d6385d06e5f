"""The box's own metric: periodic axes wrap (a torus or a cylinder), the others are planar;
the sphere's great-circle metric (``SphereMetric``, with its coordinates); and what a
kd-tree's points hold when they are weighted (``held_in_balls``, ``cell_tally``,
``weighted_kth``), summed so that a heavy point cannot swallow light ones
(``compensated_sums``). Used by certify and the applications, never by the engine."""

import numpy as np
from scipy.spatial import cKDTree

from .engine.embedding import wrap_offsets
from .engine.geometry import plus_compensated
from .engine.jit import kernel


class BoxMetric:
    """Coordinates and kd-trees in the metric of ``box`` with ``periodic`` axes."""

    def __init__(self, box, periodic):
        self.dim = len(box) // 2
        self.lo = np.array(box[: self.dim], float)
        self.hi = np.array(box[self.dim :], float)
        self.periodic = np.array(periodic, bool)
        self.period = self.hi - self.lo

    def frame(self, x):
        """Coordinates relative to the box's lower corner, periodic axes wrapped into
        [0, period) by the engine's one wrapping rule (accurate whatever the magnitude)."""
        x = np.array(x, float).reshape(-1, self.dim)
        out = x - self.lo
        for a in range(self.dim):
            if self.periodic[a]:
                out[:, a] = wrap_offsets(x[:, a].copy(), self.lo[a], self.period[a])
        return out

    def wrap(self, x):
        """The points with their periodic coordinates wrapped into the box."""
        return self.frame(x) + self.lo

    def tree(self, x):
        """A cKDTree of the points in this metric (query it with ``frame`` coordinates)."""
        boxsize = np.where(self.periodic, self.period, 0.0) if self.periodic.any() else None
        return cKDTree(self.frame(x), boxsize=boxsize)

    def kth(self, points, queries, k):
        """Exact d_{S,k} at the queries for the point set S = points."""
        return self.tree(points).query(self.frame(queries), k=[k], workers=-1)[0][:, 0]


def unit_vectors(x):
    """Unit vectors (n, 3) of points on the sphere given as (longitude, latitude) in degrees
    (n, 2) or as vectors (n, 3) (normalised here; the caller has checked them)."""
    x = np.asarray(x, float)
    if x.shape[-1] == 3:
        return x / np.linalg.norm(x, axis=-1, keepdims=True)
    flat = x.reshape(-1, 2)
    out = np.empty((len(flat), 3))
    for lo in range(0, len(flat), UNIT_CHUNK):  # in blocks: temporaries of one block only
        block = np.radians(flat[lo : lo + UNIT_CHUNK])
        lon, lat = block[:, 0], block[:, 1]
        c = np.cos(lat)
        out[lo : lo + len(block), 0] = c * np.cos(lon)
        out[lo : lo + len(block), 1] = c * np.sin(lon)
        out[lo : lo + len(block), 2] = np.sin(lat)
    return out.reshape(x.shape[:-1] + (3,))


UNIT_CHUNK = 1 << 16  # rows converted at a time by ``unit_vectors``


def lonlat_of(xyz):
    """(longitude in [-180, 180], latitude in [-90, 90]) in degrees of vectors (n, 3)."""
    xyz = np.asarray(xyz, float)
    lon = np.degrees(np.arctan2(xyz[..., 1], xyz[..., 0]))
    lat = np.degrees(np.arctan2(xyz[..., 2], np.hypot(xyz[..., 0], xyz[..., 1])))
    return np.stack([lon, lat], axis=-1)


def chord_to_angle(chord):
    """The great-circle angle (radians) between unit vectors ``chord`` apart."""
    return 2.0 * np.arcsin(np.minimum(1.0, 0.5 * np.asarray(chord, float)))


def angle_to_chord(angle):
    """The chord between unit vectors an ``angle`` (radians, at most pi) apart."""
    return 2.0 * np.sin(0.5 * np.minimum(np.asarray(angle, float), np.pi))


class SphereMetric:
    """Great-circle distances on the sphere of ``radius`` through kd-trees over unit vectors
    (chords order points as angles do): the sphere's ``BoxMetric``."""

    def __init__(self, radius=1.0):
        self.radius = float(radius)
        self.dim = 2

    def frame(self, x):
        """The unit vectors of lon/lat points (n, 2) or vectors (n, 3)."""
        x = np.asarray(x, float)
        return unit_vectors(x.reshape(-1, x.shape[-1]))

    def tree(self, x):
        """A cKDTree of the points' unit vectors (query it with ``frame`` coordinates)."""
        return cKDTree(self.frame(x))

    def length(self, chord):
        """The great-circle length (times ``radius``) of chords."""
        return chord_to_angle(chord) * self.radius

    def kth(self, points, queries, k):
        """Exact d_{S,k} at the queries for S = points, great-circle, times ``radius``."""
        d = self.tree(points).query(self.frame(queries), k=[k], workers=-1)[0][:, 0]
        return self.length(d)


class TorusFrame:
    """Coordinates on the torus [0, period) with its corner at ``origin`` (a mesh's
    ``torus``): the box metric of that torus, both axes wrapped. A picklable function of
    the points, for checks that run where the points are."""

    def __init__(self, origin, period):
        self.origin = tuple(float(v) for v in origin)
        self.period = tuple(float(v) for v in period)
        corner = np.add(self.origin, self.period)
        self._metric = BoxMetric((*self.origin, *corner), (True,) * len(self.period))

    def __call__(self, x):
        return self._metric.frame(x)


@kernel(entry=True, lazy=True)
def compensated_sums(values, bounds):
    """values[bounds[i]:bounds[i + 1]] summed for each i, compensated
    (``engine.geometry.plus_compensated``, the one arithmetic primitive the checks share
    with the engine): for weights >= 0 within two ulps of the exact sum whatever their order
    (plain addition loses a weight of 1 beside one of 1e16: a disk holding k = 1e16 + 8
    would hold 1e16)."""
    out = np.zeros(bounds.shape[0] - 1)
    for i in range(out.shape[0]):
        s = 0.0
        c = 0.0
        for j in range(bounds[i], bounds[i + 1]):
            s, c = plus_compensated(s, c, values[j])
        out[i] = s + c
    return out


@kernel(entry=True, lazy=True)
def running_sums(values):
    """The running sums along each row of ``values`` (rows, columns), compensated as
    ``compensated_sums``."""
    out = np.empty_like(values)
    for i in range(values.shape[0]):
        s = 0.0
        c = 0.0
        for j in range(values.shape[1]):
            s, c = plus_compensated(s, c, values[i, j])
            out[i, j] = s + c
    return out


def held_in_balls(tree, weights, centres, radii, threads=-1):
    """What each closed ball (disk in the plane) about centres holds in the tree's points:
    a count, or their weight (``compensated_sums``: a heavy point does not swallow light
    ones)."""
    if weights is None:
        return tree.query_ball_point(centres, radii, return_length=True, workers=threads)
    out = np.zeros(len(centres))
    for lo in range(0, len(centres), 10_000):
        lists = tree.query_ball_point(
            centres[lo : lo + 10_000], np.broadcast_to(radii, len(centres))[lo : lo + 10_000]
        )
        sizes = np.fromiter((len(a) for a in lists), np.int64, len(lists))
        if sizes.sum():
            members = np.concatenate([np.asarray(a, np.int64) for a in lists])
            bounds = np.concatenate([[0], np.cumsum(sizes)])
            out[lo : lo + len(lists)] = compensated_sums(weights[members], bounds)
    return out


def cell_tally(dd, ii, weights, m, slack2=0.0):
    """Points per Voronoi cell from each point's nearest vertices (dd, ii: distances and
    indices of up to 3, nearest first): a point counts for every vertex as near as its
    nearest (up to a relative 1e-12, and ``slack2`` added to the squared distance: on the
    sphere, the rounding of unit vectors), weighed by ``weights`` if given (compensated
    sums)."""
    kk = dd.shape[1] if dd.ndim == 2 else 1
    dd, ii = dd.reshape(len(dd), kk), ii.reshape(len(ii), kk)
    if slack2 > 0:
        tie = dd * dd <= dd[:, :1] ** 2 * (1.0 + 2e-12) + slack2
    else:
        tie = dd <= dd[:, :1] * (1.0 + 1e-12)
    if weights is None:
        return np.bincount(ii[tie], minlength=m)
    w = np.broadcast_to(weights[:, None], tie.shape)[tie]
    cell = ii[tie]
    order = np.argsort(cell, kind="stable")
    bounds = np.searchsorted(cell[order], np.arange(m + 1))
    return compensated_sums(np.ascontiguousarray(w[order], dtype=np.float64), bounds)


def weighted_kth(tree, weights, x, k, threads, chunk=20_000):
    """The least r whose closed disk about each x holds weight >= k: the nearest points in
    order, their weights summed, more of them fetched where the first ones fall short."""
    out = np.empty(len(x))
    n = tree.n
    first = int(min(n, 2 * np.ceil(k / max(weights.mean(), 1e-300)) + 16))
    for lo in range(0, len(x), chunk):
        q = x[lo : lo + chunk]
        res = np.full(len(q), np.nan)
        todo = np.arange(len(q))
        kk = first
        while len(todo):
            d, i = tree.query(q[todo], k=kk, workers=threads)
            d = d.reshape(len(todo), kk)
            i = i.reshape(len(todo), kk)
            held = running_sums(np.ascontiguousarray(weights[np.minimum(i, n - 1)] * (i < n)))
            enough = held[:, -1] >= k
            at = np.argmax(held >= k, axis=1)
            res[todo[enough]] = d[enough, at[enough]]
            todo = todo[~enough]
            if kk >= n:
                res[todo] = np.inf
                break
            kk = min(n, 4 * kk)
        out[lo : lo + chunk] = res
    return out
