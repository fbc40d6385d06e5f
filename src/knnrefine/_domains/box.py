"""What the two box domains (the plane and space) share, written once: the frame their
pieces and exact indexes take (input coordinates, periodic axes wrapped), the flat balls
of their densities, and the points a mesh in a box was made from. Each box domain's
modules re-export these under the names every domain has."""

import numpy as np

from .._metric import BoxMetric
from .._validation import points_of_run
from ..errors import EngineError


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
