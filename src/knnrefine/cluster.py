"""Mode-seeking clustering through the mesh: ToMATo on the mesh graph.

ToMATo (Chazal, Guibas, Oudot, Skraba 2013; gudhi's implementation) grows clusters from the
peaks of a density on a graph and merges those whose prominence is small. Here the graph is the
mesh (m vertices, not n points) and the density at a vertex is the kNN estimate from exact
d_{P,k} there (log scale); each input point then takes the label of its Voronoi cell, i.e. of
its nearest mesh vertex.

Which peaks are clusters: those whose prominence (log density at the peak minus at the saddle
where it merges into a higher one) exceeds what sampling noise produces on a flat density. The
kNN estimate's log has standard error about 1/sqrt(k) (pi rho d_{P,k}^2 is Gamma(k, 1) for a
Poisson process), a prominence is a difference of two such estimates (sqrt(2/k)), and a flat
region of n points holds about n/k independent estimates, whose largest deviation is about
sqrt(2 log(n/k)) standard errors. So the threshold is

    T = sqrt(2 / k) * sqrt(2 log(n / k)) = 2 sqrt(log(n / k) / k).

Measured on 20,000 uniform points and on one Gaussian blob (k = 20 to 200, five seeds each), the
largest spurious prominence was at most 0.86 T (uniform, k = 20) and the rule found 1 cluster
every time; see ``benchmarks/cluster_compare.py`` for unequal blobs, moons, S1 and Birch1.

The same holds in space (V d_{P,k}^3 rho is Gamma(k, 1) too, so the log-density's standard
error is again about 1/sqrt(k)). The rule assumes the points spread in the full dimension of
their space. Along a curve (a thin ring, a filament)
the count within r grows like r, not r^2, and the log-density noise is twice as large,
2 / sqrt(k): a noisy circle of 1,200 points at k = 30 splits into arcs whose prominences reach
1.9 T. Pass n_clusters there (or look at its loop with ``topology.Persistence``).
With ``noise=True`` a point is labelled -1 when log f(x) is less than T above the highest
saddle at which its cluster's superlevel component meets another cluster's (Hartigan's cluster
tree, cut at significance): the background between clusters is noise, a cluster's core is
not, and a lone cluster (one blob, uniform data) has no noise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from numpy.typing import ArrayLike

if TYPE_CHECKING:  # the annotations' types only
    from .mesh import Mesh

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ._domains import part
from ._engine.superlevel import superlevel_noise
from ._metric import BoxMetric
from .density.estimate import unit_ball_volume
from .errors import InputError
from .mesh import cell_edges
from .topology import require_gudhi


@dataclass
class Clustering:
    """What ``cluster`` found.

    Attributes
    ----------
    labels : ndarray (n,)
        The cluster of each input point, 0 .. n_clusters - 1 by decreasing peak density; -1
        for noise when asked for.
    vertex_labels : ndarray (m,)
        The cluster of each mesh vertex (-1 also for vertex copies outside every cell).
    n_clusters : int
    prominence : ndarray
        Of every peak found, by decreasing value, in natural-log density (the n_clusters
        first were kept).
    threshold : float
        The significance threshold T of the module docstring.
    seconds : float
    """

    labels: np.ndarray
    vertex_labels: np.ndarray
    n_clusters: int
    prominence: np.ndarray
    threshold: float
    seconds: float

    @property
    def noise(self):
        """How many input points are labelled noise (-1)."""
        return int(np.count_nonzero(self.labels < 0))


def significance_threshold(n, k):
    """T = 2 sqrt(log(n / k) / k): the prominence (natural-log density) a peak must exceed to
    count as a cluster (see the module docstring)."""
    return 2.0 * float(np.sqrt(np.log(max(n / k, np.e)) / k))


def cluster(
    mesh: Mesh,
    points: ArrayLike,
    *,
    n_clusters: int | None = None,
    merge_threshold: float | None = None,
    noise: bool = False,
    weights: ArrayLike | None = None,
) -> Clustering:
    """ToMATo clusters of ``points`` on the mesh graph (see the module docstring), in the
    plane, in space or on the sphere (great-circle d_Pk, the density per unit area of the
    sphere).

    Parameters
    ----------
    mesh : Mesh
        From ``knnrefine.refine(points, k, ...)``.
    points : array-like (n, d)
        The points it was refined from.
    n_clusters : int, optional
        How many to keep (default: the peaks more prominent than the significance threshold
        ``significance_threshold(n, k)``).
    merge_threshold : float, optional
        Or keep the peaks more prominent than this (natural-log density).
    noise : bool
        Label -1 the points not significantly above the level where their cluster meets
        another (see the module docstring).
    weights : array-like (n,), optional
        The weights of a weighted run (required for one, refused otherwise): the density is
        then the weighted kNN estimate, n the total weight.

    Returns
    -------
    Clustering

    Raises
    ------
    InputError
        Points or weights that are not the mesh's, bad options.
    ImportError
        Without gudhi (``pip install "knnrefine[topology]"``).
    """
    t0 = time.perf_counter()
    gudhi = require_gudhi()
    from gudhi.clustering.tomato import Tomato

    domain = part(mesh.domain, "density")
    pts, weights, total = domain.points_of(mesh, points, weights)
    if n_clusters is not None and (
        isinstance(n_clusters, bool) or int(n_clusters) != n_clusters or n_clusters < 1
    ):
        raise InputError(f"n_clusters must be a positive integer, got {n_clusters!r}")
    if merge_threshold is not None and not (np.isfinite(merge_threshold) and merge_threshold >= 0):
        raise InputError(f"merge_threshold must be a number >= 0, got {merge_threshold!r}")
    if n_clusters is not None and merge_threshold is not None:
        raise InputError("give n_clusters or merge_threshold, not both")
    del gudhi
    # the graph: the vertices of the cells (a non-periodic mesh also returns vertex copies
    # near the box that no kept cell uses) and the cells' edges
    used, cells = np.unique(mesh.cells.astype(np.int64), return_inverse=True)
    cells = cells.reshape(mesh.cells.shape)
    vertices = mesh.vertices[used]
    m = len(vertices)
    pairs = cell_edges(cells)
    # adjacency lists, CSR-style: both directions of every edge grouped by their first vertex
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(both[:, 0], minlength=m))])
    neighbours = np.split(both[:, 1], indptr[1:-1])
    dim = mesh.dim
    # d_Pk at the used vertices, exactly, in the index's frame (on the sphere the engine's
    # unit vectors); the density from the flat ball as large (on the sphere: pi chord^2)
    at = mesh.xyz[used] if mesh.xyz is not None else domain.to_frame(mesh)(vertices)
    d = domain.flat_radius(mesh, domain.index_of(mesh, pts, weights).kth(at, mesh.k))
    log_density = np.log(mesh.k / (total * unit_ball_volume(dim))) - dim * np.log(d)
    tomato = Tomato(graph_type="manual", density_type="manual")
    tomato.fit(neighbours, weights=log_density)
    # gudhi's diagram lists the peaks that merge; the highest peak of each connected piece
    # never merges (infinite prominence)
    diagram = np.asarray(tomato.diagram_, float).reshape(-1, 2)
    finite = np.sort(diagram[:, 0] - diagram[:, 1])[::-1]
    essential = len(tomato.max_weight_per_cc_)
    prominence = np.concatenate([np.full(essential, np.inf), finite])
    threshold = significance_threshold(total, mesh.k)
    if n_clusters is None and merge_threshold is None:
        n_clusters = essential + int(np.count_nonzero(finite > threshold))
    if n_clusters is not None:
        tomato.n_clusters_ = min(int(n_clusters), tomato.n_leaves_)
    else:
        tomato.merge_threshold_ = float(merge_threshold or 0.0)
    vertex_labels = np.asarray(tomato.labels_)
    if noise:
        # the kept clusters' peaks; a vertex is noise when its superlevel component holds none
        best = np.full(vertex_labels.max() + 1, -np.inf)
        np.maximum.at(best, vertex_labels, log_density)
        significant = log_density == best[vertex_labels]
        peak_of = np.zeros(len(best), np.int64)
        peak_of[vertex_labels[significant]] = np.flatnonzero(significant)
        order = np.argsort(-log_density, kind="stable")
        kept_leaf = ~superlevel_noise(
            order,
            indptr,
            both[:, 1].copy(),
            log_density,
            significant,
            peak_of[vertex_labels],
            threshold,
        )
    # number clusters by decreasing peak density
    peaks = np.array(
        [log_density[vertex_labels == c].max() for c in range(vertex_labels.max() + 1)]
    )
    rank = np.empty(len(peaks), int)
    rank[np.argsort(-peaks, kind="stable")] = np.arange(len(peaks))
    vertex_labels = rank[vertex_labels]
    if noise:
        vertex_labels = np.where(kept_leaf, vertex_labels, -1)
    if mesh.on_sphere:  # each point takes its nearest vertex's label (chords order as angles)
        labels = vertex_labels[cKDTree(at).query(pts, workers=-1)[1]]
    else:
        metric = BoxMetric(mesh.box, mesh.periodic)
        labels = vertex_labels[metric.tree(vertices).query(metric.frame(pts), workers=-1)[1]]
    all_labels = np.full(len(mesh.vertices), -1)
    all_labels[used] = vertex_labels
    return Clustering(
        labels=labels,
        vertex_labels=all_labels,
        n_clusters=int(rank.max() + 1),
        prominence=prominence,
        threshold=threshold,
        seconds=time.perf_counter() - t0,
    )
