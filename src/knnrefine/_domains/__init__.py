"""The three domains a mesh lives in, each a package of the same modules, as CGAL's
Periodic_2 and Periodic_3 triangulations share one shape and differ in their kernels:

- ``plane``: a box or flat torus in two dimensions (input units);
- ``space``: a box or flat torus in three dimensions (the paper's open problem 1);
- ``sphere``: the unit sphere S^2 scaled by a radius (longitude/latitude or unit vectors).

Each domain package holds:

- ``run.py``: ``checked(points, weights, **options) -> (pts, w, opt)``, every input checked
  before any work, and ``refine(pts, w, opt) -> Mesh``, the start (initial mesh, embedding,
  counting index), the engine's run and the assembled ``Mesh``;
- ``certify.py``: ``Geometry`` (certify's questions about the mesh: its triangulation
  checked exactly, circumballs, probes, the size integral) and ``Points`` (the questions
  about the input points: counts in balls and cells, d_{P,k});
- ``density.py``: ``Pieces``, d_{P,k} as linear pieces over the mesh (evaluation, integrals,
  sampling) for ``KnnDistance`` and the uses built on it.

What is the same in every domain is written once above them: ``pipeline`` (check -> start ->
run -> assemble), ``certify.steps`` (the certificate's steps), ``density`` (the uses). The
domain is decided once, at the public boundary (``domain_of``); ``part`` is the one place a
domain's module is looked up. The numba kernels stay per dimension in ``engine``.
"""

from importlib import import_module
from types import ModuleType

import numpy as np

from ..errors import InputError

NAMES = ("plane", "space", "sphere")
PARTS = ("run", "certify", "density")


# A continued run's new points per old one up to which merging them into the start's tree
# beats building a tree of them all (every domain's; 10^6 in the plane, half as many new:
# merging took 0.36 s, building 0.15 s)
MERGE_UP_TO = 0.25


def domain_of(points, sphere=False, radius=None) -> str:
    """The domain a run is in, decided once: "sphere" when asked (``radius`` is refused
    without it), else "space" for points of three columns, else "plane"."""
    if not isinstance(sphere, (bool, np.bool_)):
        raise InputError(f"sphere must be True or False, got {sphere!r}")
    if sphere:
        return "sphere"
    if radius is not None:
        raise InputError("radius is the sphere's: give it with sphere=True")
    return "space" if columns(points) == 3 else "plane"


def columns(points) -> int | None:
    """The number of columns of points given as a 2-D array or nested lists (None if they
    are not 2-D), read without converting them."""
    shape = np.shape(points) if hasattr(points, "shape") else None
    if shape is None:
        try:
            shape = np.shape(np.asarray(points, dtype=object))
        except Exception:
            return None
    return int(shape[1]) if len(shape) == 2 else None


def part(domain: str, name: str) -> ModuleType:
    """The module ``name`` ("run", "certify" or "density") of a domain ("plane", "space" or
    "sphere"), imported on first use: the one place a domain's code is chosen."""
    if domain not in NAMES or name not in PARTS:
        raise ValueError(f"no part {name!r} of domain {domain!r}: domains {NAMES}, parts {PARTS}")
    return import_module(f"{__name__}.{domain}.{name}")
