"""Mode-seeking clustering through the mesh: ToMATo on the mesh graph.

ToMATo (Chazal, Guibas, Oudot, Skraba 2013; gudhi's implementation) grows clusters from the
peaks of a density on a graph and merges those whose prominence is small. Here the graph is the
mesh (m vertices, not n points) and the density at a vertex is the kNN estimate from exact
d_{P,k} there (log scale); each input point then takes the label of its Voronoi cell, i.e. of
its nearest mesh vertex. The number of clusters is chosen at the largest gap between the
prominences, unless given.
"""

import time
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .metric import BoxMetric
from .topology import _gudhi
from .validation import as_points


@dataclass
class Clustering:
    """labels (n,): cluster of each input point (0 .. n_clusters - 1, by decreasing peak
    density); vertex_labels (m,): of each mesh vertex (-1 for vertex copies outside every
    triangle); prominence: of every peak found, by decreasing value (the n_clusters first
    were kept); seconds."""

    labels: np.ndarray
    vertex_labels: np.ndarray
    n_clusters: int
    prominence: np.ndarray
    seconds: float


def cluster(mesh, points, n_clusters=None, merge_threshold=None):
    """ToMATo clusters of ``points`` on the mesh graph (see the module docstring).

    n_clusters: how many to keep (default: cut at the largest prominence gap);
    merge_threshold: or keep the peaks more prominent than this (log density units)."""
    t0 = time.perf_counter()
    gudhi = _gudhi()
    from gudhi.clustering.tomato import Tomato

    pts = as_points(points)
    if len(pts) < mesh.k:
        raise InputError(f"{len(pts)} points but k = {mesh.k}: d_Pk is infinite")
    if n_clusters is not None and (int(n_clusters) != n_clusters or n_clusters < 1):
        raise InputError(f"n_clusters must be a positive integer, got {n_clusters!r}")
    del gudhi
    # the graph: the vertices of the triangles (a non-periodic mesh also returns vertex copies
    # near the box that no kept triangle uses) and the triangles' edges
    used, tri = np.unique(mesh.triangles.astype(np.int64), return_inverse=True)
    tri = tri.reshape(-1, 3)
    vertices = mesh.vertices[used]
    m = len(vertices)
    edges = np.unique(
        np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0
    )
    # adjacency lists, CSR-style: both directions of every edge grouped by their first vertex
    both = np.concatenate([edges, edges[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    neighbours = np.split(both[:, 1], np.cumsum(np.bincount(both[:, 0], minlength=m))[:-1])
    metric = BoxMetric(mesh.box, mesh.periodic)
    d = metric.kth(pts, vertices, mesh.k)
    log_density = np.log(mesh.k / (len(pts) * np.pi)) - 2.0 * np.log(d)
    tomato = Tomato(graph_type="manual", density_type="manual")
    tomato.fit(neighbours, weights=log_density)
    # gudhi's diagram lists the peaks that merge; the highest peak of each connected piece
    # never merges (infinite prominence)
    diagram = np.asarray(tomato.diagram_, float).reshape(-1, 2)
    finite = np.sort(diagram[:, 0] - diagram[:, 1])[::-1]
    essential = len(tomato.max_weight_per_cc_)
    prominence = np.concatenate([np.full(essential, np.inf), finite])
    if n_clusters is None and merge_threshold is None:
        # keep the peaks above the largest gap between consecutive prominences, counting the
        # gap down to 0 after the last one (when every peak is a real cluster)
        steps = np.append(finite, 0.0)
        n_clusters = essential + (int(np.argmax(steps[:-1] - steps[1:])) + 1 if len(finite) else 0)
    if n_clusters is not None:
        tomato.n_clusters_ = min(int(n_clusters), tomato.n_leaves_)
    else:
        tomato.merge_threshold_ = float(merge_threshold)
    vertex_labels = np.asarray(tomato.labels_)
    # number clusters by decreasing peak density
    peaks = np.array(
        [log_density[vertex_labels == c].max() for c in range(vertex_labels.max() + 1)]
    )
    rank = np.empty(len(peaks), int)
    rank[np.argsort(-peaks, kind="stable")] = np.arange(len(peaks))
    vertex_labels = rank[vertex_labels]
    labels = vertex_labels[metric.tree(vertices).query(metric.frame(pts), workers=-1)[1]]
    all_labels = np.full(len(mesh.vertices), -1)
    all_labels[used] = vertex_labels
    return Clustering(
        labels=labels,
        vertex_labels=all_labels,
        n_clusters=int(vertex_labels.max() + 1),
        prominence=prominence,
        seconds=time.perf_counter() - t0,
    )
