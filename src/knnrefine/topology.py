"""Robust persistent homology: the sublevel sets of d_{P,k} on the mesh.

The k-th-neighbour distance is the distance-to-a-measure idea in its simplest form: outliers
no longer fill in the shape, as they do for k = 1 (the plain distance to P). The filtration is
lower-star on the mesh's own triangulation, subdivided once through the edge midpoints: every
node gets its exact d_{P,k}, an edge or triangle the largest value of its nodes, which is the
sublevel-set persistence of the piecewise-linear interpolant. On the torus the triangulation
is the combinatorial one (offsets dropped), checked to be a simplicial complex first.
Persistence is computed by gudhi (``pip install "knnrefine[topology]"``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from numpy.typing import ArrayLike

if TYPE_CHECKING:  # the annotations' types only
    from .mesh import Mesh

from itertools import combinations

import numpy as np

from ._domains import part
from ._metric import BoxMetric
from ._validation import as_points
from .errors import InputError


def require_gudhi():
    """gudhi, or an ImportError that names the extra to install."""
    try:
        import gudhi
    except ImportError:
        raise ImportError(
            "persistent homology and clustering need gudhi, an optional dependency: "
            'pip install "knnrefine[topology]"',
            name="gudhi",
        ) from None
    return gudhi


def mesh_complex(mesh, subdivide=True):
    """The triangulated domain of the filtration: (nodes (p, d) in the frame of the domain's
    exact index, as its ``density.complex_of`` gives them, cells (t, d + 1)).

    The mesh's cells, which are those that meet the box (the package's one rule: all of the
    torus' in periodic mode, as an abstract complex with positions in the box). With
    ``subdivide``, every triangle is split in four (every tetrahedron in eight) through its
    edge midpoints. Raises EngineError if two edges join the same pair of vertices, or an
    edge a vertex to itself (the complex would then not be simplicial: only on a torus a few
    cells across)."""
    positions, nodes, cells = part(mesh.domain, "density").complex_of(mesh, subdivide)
    return nodes, cells


class Persistence:
    """Sublevel-set persistence of d_{P,k} (log scale by default) on the mesh, in the plane
    (classes in dimensions 0-2) or in space (0-3).

    Parameters
    ----------
    mesh : Mesh
        From ``knnrefine.refine(points, k, ...)``.
    points : array-like (n, d)
        The points it was refined from.
    log : bool
        Filter by log d_{P,k}, which makes the diagram scale-free (features of a tight
        cluster and of a wide ring compare by ratios).
    subdivide : bool
        Split the cells through their edge midpoints (exact values there too).
    function : "d_pk" or "d_m2"
        ``"d_m2"`` filters by the mesh's own d_{M,2} instead (no query of P at all; by
        Theorem 6 it is within the factors [alpha, beta] of d_{P,k}).
    weights : array-like (n,), optional
        The weights of a weighted run (required for one, refused otherwise).

    Notes
    -----
    ``diagram(dim)``: (q, 2) birth and death of the classes in dimension dim (death inf for
    the classes that never die). ``cells`` are the filtered complex's top cells (triangles
    or tetrahedra) over ``positions``.

    On the sphere the complex is the sphere's own triangulation, ``positions`` in longitude
    and latitude: once every triangle has entered, the sublevel set is the whole sphere, so
    ``diagram(2)`` ends with one class born at the largest value of the filtration that
    never dies. That class is the sphere itself, not a feature of the data (as the one
    essential class in dimension 0 is the sphere's connectedness); the data's holes (a
    region without points enclosed by a ring of them) are the finite classes in dimension 1,
    and a cavity in dimension 2 cannot exist on a surface.
    """

    def __init__(
        self,
        mesh: Mesh,
        points: ArrayLike,
        *,
        log: bool = True,
        subdivide: bool = True,
        function: str = "d_pk",
        weights: ArrayLike | None = None,
    ) -> None:
        """See the class docstring."""
        gudhi = require_gudhi()
        if function not in ("d_pk", "d_m2"):
            raise InputError(f"function must be 'd_pk' or 'd_m2', got {function!r}")
        self.mesh = mesh
        self.log = log
        domain = part(mesh.domain, "density")
        pts, weights, _ = domain.points_of(mesh, points, weights)
        self.positions, nodes, self.cells = domain.complex_of(mesh, subdivide)
        if function == "d_pk":  # exact, at the nodes in the index's frame
            d = domain.index_of(mesh, pts, weights).kth(nodes, mesh.k)
        else:  # the mesh's own sizing: within [alpha, beta] d_Pk, free
            d = mesh.d_m2(self.positions)
        self.values = np.log(d) if log else d
        st = gudhi.SimplexTree()
        n = len(self.positions)
        st.insert_batch(np.arange(n)[None, :], self.values)
        corners = self.cells.shape[1]
        for size in range(2, corners + 1):  # every face, with the largest of its values
            faces = np.unique(
                np.sort(
                    np.concatenate(
                        [self.cells[:, list(c)] for c in combinations(range(corners), size)]
                    ),
                    axis=1,
                ),
                axis=0,
            )
            st.insert_batch(faces.T, self.values[faces].max(axis=1))
        st.compute_persistence(homology_coeff_field=2, persistence_dim_max=True)
        self.simplex_tree = st

    @property
    def triangles(self):
        """The complex's cells in the plane (its name there before space)."""
        return self.cells

    def diagram(self, dim: int) -> np.ndarray:
        """The persistence diagram in one dimension.

        Parameters
        ----------
        dim : int
            0 to 2 in the plane, 0 to 3 in space.

        Returns
        -------
        ndarray (q, 2)
            Birth and death of each class (death inf for the classes that never die).
        """
        d = np.asarray(self.simplex_tree.persistence_intervals_in_dimension(dim), float)
        return d.reshape(-1, 2)

    def betti(self, threshold: float) -> tuple:
        """Betti numbers of the sublevel set at a threshold.

        Parameters
        ----------
        threshold : float
            On the filtration's scale (log d_{P,k} by default).

        Returns
        -------
        tuple of int
            (b0, b1, ..., b_d).
        """
        return tuple(
            int(((dg[:, 0] <= threshold) & ((dg[:, 1] > threshold) | np.isinf(dg[:, 1]))).sum())
            for dg in (self.diagram(i) for i in range(self.mesh.dim + 1))
        )

    def most_persistent(self, dim: int, count: int = 3) -> np.ndarray:
        """The longest-lived finite classes in one dimension.

        Parameters
        ----------
        dim : int
        count : int

        Returns
        -------
        ndarray (<= count,)
            Their persistence (death - birth), longest first.
        """
        d = self.diagram(dim)
        life = d[:, 1] - d[:, 0]
        return np.sort(life[np.isfinite(life)])[::-1][:count]


def grid_persistence(points, k, box, periodic=(False, False), shape=(512, 512), log=True):
    """The reference: cubical sublevel-set persistence of exact d_{P,k} on a grid of cell
    centres over the box (periodic where asked), from gudhi. Returns {dim: (q, 2) array}."""
    gudhi = require_gudhi()
    pts = as_points(points)
    ny, nx = shape
    xs = box[0] + (np.arange(nx) + 0.5) * (box[2] - box[0]) / nx
    ys = box[1] + (np.arange(ny) + 0.5) * (box[3] - box[1]) / ny
    gx, gy = np.meshgrid(xs, ys)
    d = BoxMetric(box, periodic).kth(pts, np.column_stack([gx.ravel(), gy.ravel()]), k)
    values = (np.log(d) if log else d).reshape(ny, nx)
    if any(periodic):  # array axes are (y, x)
        cc = gudhi.PeriodicCubicalComplex(
            vertices=values, periodic_dimensions=[periodic[1], periodic[0]]
        )
    else:
        cc = gudhi.CubicalComplex(vertices=values)
    cc.compute_persistence(homology_coeff_field=2)
    return {
        dim: np.asarray(cc.persistence_intervals_in_dimension(dim), float).reshape(-1, 2)
        for dim in (0, 1, 2)
    }


def bottleneck(a, b):
    """Bottleneck distance between two diagrams (infinite classes matched separately: their
    births' largest difference when the counts agree, inf otherwise)."""
    gudhi = require_gudhi()
    fa, fb = a[np.isfinite(a[:, 1])], b[np.isfinite(b[:, 1])]
    ia, ib = np.sort(a[~np.isfinite(a[:, 1]), 0]), np.sort(b[~np.isfinite(b[:, 1]), 0])
    if len(ia) != len(ib):
        return float("inf")
    essential = float(np.abs(ia - ib).max()) if len(ia) else 0.0
    return max(float(gudhi.bottleneck_distance(fa, fb)), essential)
