"""The box's own metric: periodic axes wrap (a torus or a cylinder), the others are planar;
the sphere's great-circle metric (``SphereMetric``, with its coordinates); and what a
kd-tree's points hold when they are weighted (``held_in_balls``, ``cell_tally``,
``weighted_kth``), summed so that a heavy point cannot swallow light ones
(``compensated_sums``). Used by certify and the applications, never by the engine."""

import itertools
import math

import numpy as np
from scipy.spatial import cKDTree

from ._engine.embedding import wrap_offsets
from ._engine.geometry import plus_compensated
from ._engine.jit import kernel
from ._engine.weight_tree import WeightTree, ball_weights, kth_radius
from ._engine.weight_tree import build as build_weight_tree


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
        x = np.asarray(x, float).reshape(-1, self.dim)  # (read only: no copy made)
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


def weight_tree(tree, weights):
    """The tree's points with their weights in a ``engine.weight_tree.WeightTree`` (node totals:
    what a ball holds without visiting its points; points of weight 0 left out), to be
    given as ``weights`` to ``held_in_balls`` and ``weighted_kth`` when they are asked
    several times about the same points; ``weights`` unchanged if already one or None."""
    if weights is None or isinstance(weights, WeightTree):
        return weights
    return build_weight_tree(tree.data, weights, tree.boxsize)


def held_in_balls(tree, weights, centres, radii, threads=-1):
    """What each closed ball (disk in the plane) about centres holds in the tree's points:
    a count, or their weight (``weights``: an array, or ``weight_tree(tree, weights)``),
    compensated (a heavy point does not swallow light ones), from node totals (light and
    weightless points cost nothing: ``engine.weight_tree``)."""
    if weights is None:
        return tree.query_ball_point(centres, radii, return_length=True, workers=threads)
    return ball_weights(weight_tree(tree, weights), centres, radii, threads)


def points_in_balls(tree, centres, radii):
    """How many of the tree's points lie in the union of the closed balls about ``centres``
    (``radii`` each, widened by a relative 1e-9): the points under the floor of every
    domain. One kd-tree query; the indices gathered without a Python loop over balls."""
    if len(centres) == 0:
        return 0
    found = tree.query_ball_point(centres, np.asarray(radii) * (1.0 + 1e-9), return_sorted=False)
    hit = np.zeros(tree.n, bool)
    hit[np.fromiter(itertools.chain.from_iterable(found), np.int64)] = True
    return int(hit.sum())


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
    """The least r whose closed disk about each x holds weight >= k (``weights``: an array,
    or ``weight_tree(tree, weights)``): the nearest points of positive weight in order,
    their weights summed, twice at most (the first count, then four times as many). Where
    they still fall short (most of the weight far away, light points near), the heavy
    points (weight >= k / 64) give a radius holding k, and the tree of node totals
    (``engine.weight_tree.kth_radius``) checks that less does not, or brackets the answer: work
    that does not grow with the light points."""
    x = np.asarray(x, float).reshape(-1, tree.m)
    wt = weights if isinstance(weights, WeightTree) else None
    w = wt.source_weights if wt is not None else np.asarray(weights, float)
    out = np.empty(len(x))
    if (w <= 0).sum() > 0.01 * len(w):  # weightless points hold nothing: not asked about
        keep = w > 0
        tree, w = cKDTree(tree.data[keep], boxsize=tree.boxsize), w[keep]
    n = tree.n
    total = float(w.sum())
    if n == 0 or total < k * (1.0 - 1e-12):
        out[:] = np.inf
        return out
    first = int(min(n, 2 * np.ceil(k / max(total / max(n, 1), 1e-300)) + 16))
    heavy = None
    for lo in range(0, len(x), chunk):
        q = x[lo : lo + chunk]
        res, low, todo = _nearest_first(tree, w, q, k, first, threads)
        if len(todo):
            if wt is None:
                wt = build_weight_tree(tree.data, w, tree.boxsize)
            if heavy is None:
                heavy = _heavy_points(tree, w, k)
            high = np.full(len(todo), -1.0)
            if heavy[0] is not None:
                high, before = _heavy_kth(heavy[0], heavy[1], q[todo], k, threads)
                # the heavy points before the one reaching k and every light point weigh
                # less than k: no smaller ball holds k
                sure = (high >= 0) & (before + heavy[2] < k * (1.0 - 1e-12))
                res[todo[sure]] = high[sure]
                todo, high = todo[~sure], high[~sure]
            if len(todo):
                res[todo] = kth_radius(wt, q[todo], k, low[todo], high, threads)
        out[lo : lo + chunk] = res
    return out


def _nearest_first(tree, w, q, k, first, threads):
    """(d_{P,k} at the queries where ``first`` nearest points of ``tree`` hold k, or four
    times as many where the first ones held k / 8 (nan elsewhere); a radius just inside the
    farthest fetched, whose ball holds less than k; the queries left unanswered)."""
    n = tree.n
    res = np.full(len(q), np.nan)
    low = np.full(len(q), -1.0)
    todo = np.arange(len(q))
    left = [todo[:0]]
    kk = first
    for attempt in range(2):
        if not len(todo):
            break
        d, i = tree.query(q[todo], k=kk, workers=threads)
        d, i = d.reshape(len(todo), kk), i.reshape(len(todo), kk)
        held = running_sums(np.ascontiguousarray(w[np.minimum(i, n - 1)] * (i < n)))
        enough = held[:, -1] >= k
        at = np.argmax(held >= k, axis=1)
        res[todo[enough]] = d[enough, at[enough]]
        low[todo] = np.where(np.isfinite(d[:, -1]), d[:, -1] * (1.0 - 1e-9), -1.0)
        short = todo[~enough]
        if kk >= n:  # every point fetched: less than k in all
            res[short] = np.inf
            break
        again = held[~enough, -1] >= k / 8.0
        left.append(short if attempt == 1 else short[~again])
        todo, kk = short[again], min(n, 4 * kk)
    return res, low, np.concatenate(left)


HEAVY = 64  # a heavy point weighs k / HEAVY or more: HEAVY of them hold k


def _heavy_points(tree, w, k):
    """(a kd-tree of the points of weight >= k / HEAVY, their weights, the total weight of
    the others), when they weigh k together and are fewer than the points; else Nones."""
    big = w >= k / HEAVY
    if big.all() or w[big].sum() < k:
        return None, None, None
    light = math.fsum(w[~big])
    return cKDTree(tree.data[big], boxsize=tree.boxsize), w[big], light


def _heavy_kth(tree, w, x, k, threads):
    """(the least radius at which the heavy points alone hold k, -1 where HEAVY of them do
    not; the weight of the heavy points fetched before the one reaching k)."""
    kk = min(tree.n, HEAVY + 1)
    d, i = tree.query(x, k=kk, workers=threads)
    d, i = d.reshape(len(x), kk), i.reshape(len(x), kk)
    held = running_sums(np.ascontiguousarray(w[np.minimum(i, tree.n - 1)] * (i < tree.n)))
    enough = held[:, -1] >= k
    at = np.argmax(held >= k, axis=1)
    rows = np.arange(len(x))
    high = np.where(enough, d[rows, at], -1.0)
    before = np.where(at > 0, held[rows, np.maximum(at - 1, 0)], 0.0)
    return high, before
