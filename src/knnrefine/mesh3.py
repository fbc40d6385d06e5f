"""The result of a refinement in space: the mesh M of a box and what it promises.

The proofs of Theorem 6 carry to three dimensions with the same constants (docs/algorithm.md,
"Three dimensions"), so alpha and beta are the plane's (``mesh.theorem6_constants``).
"""

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .mesh import KIND_NAMES, theorem6_constants
from .metric import BoxMetric, TorusFrame
from .validation import as_queries


@dataclass(frozen=True, eq=False)
class Torus3:
    """The refined mesh of the whole 3-torus (the embedding torus along non-periodic axes):
    vertices relative to the mesh's ``origin`` in [0, period), exact; corner i of tetrahedron
    t at ``local[tetrahedra[t, i]] + offsets[t, i] * period``. What ``certify`` checks."""

    local: np.ndarray
    tetrahedra: np.ndarray
    offsets: np.ndarray
    kinds: np.ndarray


@dataclass(frozen=True, eq=False)
class Mesh3:
    """Mesh vertices M in a box of three dimensions, and their Delaunay tetrahedralisation.

    ``local`` are the vertices relative to ``origin`` (a grid point at or below the box's low
    corner), exact: corner i of tetrahedron t sits at ``origin + local[tetrahedra[t, i]] +
    offsets[t, i] * period``. ``vertices`` are the same points in input coordinates, wrapped
    into the box along periodic axes (rounded once). Along periodic axes ``period`` is the
    box's side; along non-periodic ones the box is embedded in a longer period (a margin no
    periodic copy of a point reaches, ``engine/embedding.py``) and the mesh keeps the copies
    of tetrahedra that meet the box and of the vertices near it (``order``: the torus vertex
    each copies); ``offsets`` is None when no axis is periodic. ``torus``: the whole refined
    torus mesh (``Torus3``; stored in ``embedded`` when an axis is not periodic). ``kinds``
    says how each vertex came (``mesh.KIND_NAMES``). ``stats``: the run's counters."""

    vertices: np.ndarray
    tetrahedra: np.ndarray
    offsets: np.ndarray | None
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
    order: np.ndarray | None = None
    embedded: Torus3 | None = None  # the torus mesh when an axis is not periodic

    def __post_init__(self):
        if self.order is None:  # periodic on every axis: the mesh is its torus
            object.__setattr__(self, "order", np.arange(len(self.local)))

    @property
    def torus(self):
        """The refined mesh of the whole torus (``Torus3``): the mesh itself when every axis
        is periodic, else the embedding torus's."""
        if self.embedded is not None:
            return self.embedded
        return Torus3(self.local, self.tetrahedra, self.offsets, self.kinds)

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

    @property
    def metric(self):
        """The box's metric in the mesh's frame (relative to ``origin``; periodic axes wrap
        with the box's sides, the others are straight)."""
        return BoxMetric((*self.origin, *np.add(self.origin, self.period)), self.periodic)

    def corners(self):
        """(t, 4, 3): each tetrahedron's corners relative to ``origin`` (unwrapped)."""
        c = self.local[self.tetrahedra]
        return c if self.offsets is None else c + self.offsets * np.asarray(self.period)

    def wrap(self, x):
        """Points x (q, 3), in input coordinates, in the mesh's frame: relative to ``origin``,
        wrapped into [0, period) along periodic axes (the package's one wrapping rule,
        ``metric.BoxMetric``)."""
        return self.metric.frame(x)

    def inside(self, x):
        """Whether points (q, 3) in the mesh's frame (``wrap``) lie in the closed box along
        its non-periodic axes (periodic ones always do)."""
        lo = np.array(self.box[:3]) - np.asarray(self.origin)
        hi = np.array(self.box[3:]) - np.asarray(self.origin)
        free = ~np.array(self.periodic)
        return (((x >= lo) & (x <= hi)) | ~free).all(axis=-1)

    def d_m2(self, x):
        """d_{M,2} at the points x (..., 3): the distance to the second-nearest vertex (in
        the box; beyond it along a non-periodic axis, the embedding torus's)."""
        flat, shape = as_queries(x, 3)
        if len(flat) == 0:
            return np.zeros(shape)
        d = self._torus_tree.query(TorusFrame(self.origin, self.period)(flat), k=2)[0][:, 1]
        return d.reshape(shape)

    @cached_property
    def _torus_tree(self):
        """The torus' vertices in a periodic kd-tree (built once per mesh)."""
        return cKDTree(self.torus.local, boxsize=np.asarray(self.period))

    def __repr__(self):
        kind = (
            "periodic box" if all(self.periodic)
            else "box" if not any(self.periodic) else f"box periodic={self.periodic}"
        )  # fmt: skip
        return (
            f"<Mesh3 m={len(self.vertices)} tetrahedra={len(self.tetrahedra)} k={self.k} "
            f"tau={self.tau:g} {kind}={self.box}>"
        )
