"""The box's own metric: periodic axes wrap (a torus or a cylinder), the others are planar."""

import numpy as np
from scipy.spatial import cKDTree

from .engine.embedding import wrap_offsets


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
