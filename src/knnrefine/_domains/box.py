"""What the two box domains (the plane and space) share, written once: the frame their
pieces and exact indexes take (input coordinates, periodic axes wrapped), the flat balls
of their densities, the points a mesh in a box was made from, and where a run continued
from such a mesh starts (its embedding torus, its index). Each box domain's modules
re-export these under the names every domain has."""

import numpy as np

from .._engine.embedding import Embedding
from .._metric import BoxMetric
from .._validation import points_of_run
from ..errors import EngineError, InputError
from . import MERGE_UP_TO


def to_frame(mesh):
    """The map from input coordinates (q, d) to the frame of the domain's pieces and index:
    periodic axes wrapped into the box."""
    return BoxMetric(mesh.box, mesh.periodic).wrap


def answerable(mesh):
    """The rule of the query points the uses answer (``validation.answerable``'s, with the
    box): finite, and in the box along its non-periodic axes (sides included)."""
    lo = np.array(mesh.box[: len(mesh.periodic)], float)
    hi = np.array(mesh.box[len(mesh.periodic) :], float)
    bounded = ~np.array(mesh.periodic, bool)

    def inside(x):  # (an axis at a time: numpy's reductions along rows of 2 or 3 are slow)
        ok = np.ones(len(x), bool)
        with np.errstate(invalid="ignore"):
            for a in range(len(bounded)):
                column = x[:, a]
                if bounded[a]:  # (within finite sides: finite too)
                    ok &= (column >= lo[a]) & (column <= hi[a])
                else:
                    ok &= np.isfinite(column)
        return ok

    return inside


def flat_radius(mesh, d):
    """The radius of the flat ball as large as the ball of radius d: d itself in a box."""
    return np.asarray(d, float)


def points_of(mesh, points, weights):
    """The points, weights and total of the run a mesh in a box was refined from, checked
    (``validation.points_of_run``)."""
    return points_of_run(mesh, points, weights)


def not_simplicial():
    """The error of a complex in a box that is not simplicial: two edges join the same pair
    of vertices (a torus only a few cells across)."""
    return EngineError(
        "two edges join the same pair of vertices: the mesh is not a simplicial complex"
    )


def start_embedding(start) -> Embedding:
    """The embedding torus of a mesh refined in a box: its index's, else (a mesh read from
    a file) the one its torus' origin and period make (``Embedding.of_torus``)."""
    kept = getattr(start.index, "embedding", None)
    if kept is not None:
        return kept
    t = start.torus
    return Embedding.of_torus(start.box, start.periodic, t.origin, t.period)


def continued_index(start, emb, pts, w, new, new_w, merge, build):
    """The counting index over every point of a run continued from ``start``: the start's
    index (its ``state.PointForest``) with the new points added (``merge(forest, new,
    new_w)``, which answers None for an empty tree or one it cannot grow) when the mesh
    kept it and they are at most MERGE_UP_TO of its points, else one built over them all
    (``build(points, weights)``; a mesh read from a file keeps no tree). ``pts``, ``w``:
    every input point (the start's first) and weights or None; ``new`` the new points,
    internal coordinates."""
    kept = getattr(start.index, "forest", None)
    n0 = int(start.stats.n)
    if kept is not None and start.index.n == n0 and len(new) <= MERGE_UP_TO * n0:
        merged = merge(kept, new, new_w)
        if merged is not None:
            return merged
    return build(emb.to_internal(pts), w)


def start_mesh(start, emb):
    """The start's torus triangulation as a run takes it: (vertices (m, d) internal units,
    cells, offsets, neighbours); InputError for a torus without neighbours (a file written
    before they were kept in space)."""
    t = start.torus
    if t.neighbours is None:
        raise InputError(
            "start's torus has no neighbours (a file written before continuing was built): "
            "refine all the points afresh (without start=)"
        )
    return (
        np.ascontiguousarray(t.vertices * emb.scale),
        np.ascontiguousarray(t.cells, dtype=np.int32),
        np.ascontiguousarray(t.offsets, dtype=np.int8),
        np.ascontiguousarray(t.neighbours, dtype=np.int32),
    )
