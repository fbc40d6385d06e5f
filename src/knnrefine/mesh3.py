"""The result of a refinement in space: the mesh M of a 3-torus and what it promises.

The proofs of Theorem 6 carry to three dimensions with the same constants (docs/algorithm.md,
"Three dimensions"), so alpha and beta are the plane's (``mesh.theorem6_constants``).
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .mesh import KIND_NAMES, theorem6_constants
from .validation import as_points


@dataclass(frozen=True, eq=False)
class Mesh3:
    """Mesh vertices M in a periodic box of three dimensions, and their Delaunay
    tetrahedralisation of the 3-torus.

    ``local`` are the vertices relative to ``origin`` (the box's low corner), exact: corner i
    of tetrahedron t sits at ``origin + local[tetrahedra[t, i]] + offsets[t, i] * period``;
    ``vertices`` = ``origin + local`` (rounded once). ``kinds`` says how each vertex came
    (``mesh.KIND_NAMES``). ``stats``: the run's counters."""

    vertices: np.ndarray
    tetrahedra: np.ndarray
    offsets: np.ndarray
    kinds: np.ndarray
    k: int
    tau: float
    periodic: tuple
    box: tuple
    min_size: float
    origin: tuple
    period: tuple
    local: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def alpha(self):
        """Theorem 6's lower constant, the plane's (docs/algorithm.md, "Three dimensions")."""
        return theorem6_constants(self.tau)[0]

    @property
    def beta(self):
        return theorem6_constants(self.tau)[1]

    @property
    def kind_counts(self):
        return {name: int((self.kinds == i).sum()) for i, name in enumerate(KIND_NAMES)}

    def corners(self):
        """(t, 4, 3): each tetrahedron's corners relative to ``origin`` (unwrapped)."""
        return self.local[self.tetrahedra] + self.offsets * np.asarray(self.period)

    def wrap(self, x):
        """Points (q, 3) relative to ``origin``, wrapped into [0, period)."""
        period = np.asarray(self.period)
        out = np.mod(np.asarray(x, float) - np.asarray(self.origin), period)
        return np.where(out >= period, out - period, out)

    def d_m2(self, x):
        """d_{M,2} at the points x (..., 3): the distance to the second-nearest vertex."""
        flat = as_points(np.reshape(x, (-1, 3)), 3)
        tree = cKDTree(self.local, boxsize=np.asarray(self.period))
        d = tree.query(self.wrap(flat), k=2)[0][:, 1]
        return d.reshape(np.shape(x)[:-1])

    def __repr__(self):
        return (
            f"<Mesh3 m={len(self.vertices)} tetrahedra={len(self.tetrahedra)} k={self.k} "
            f"tau={self.tau:g} periodic box={self.box}>"
        )
