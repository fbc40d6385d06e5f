"""knnrefine: a small certified mesh carrying the k-th-nearest-neighbour distance of planar points.

An implementation of Gardner & Sheehy, "kth Nearest Neighbor Sampling in the Plane" (CCCG 2016):
``refine(points, k, tau)`` returns mesh vertices M with alpha d_{P,k} <= d_{M,2} <= beta d_{P,k}
everywhere in the box, whose Delaunay triangulation is tau-well-spaced.
"""

from . import datasets, io
from .api import certify, refine
from .certify import Certificate
from .cluster import Clustering, cluster
from .density import KnnDensity, KnnDensityEstimator, KnnDistance
from .errors import (
    BudgetError,
    EngineError,
    FloorWarning,
    InputError,
    KnnRefineError,
    LargeRunWarning,
    WrapWarning,
)
from .mesh import KIND_NAMES, Mesh, Torus, theorem6_constants
from .scale.parts import PartitionedMesh, write_partitioned

__version__ = "0.1.0"

_LAZY = {"knn_cdf": ("density.cdf", "knn_cdf"), "plot": ("plot", None)}


def __getattr__(name: str):
    """``knn_cdf`` and ``plot`` on first use (``plot`` imports matplotlib, which
    ``import knnrefine`` does not need)."""
    if name not in _LAZY:
        raise AttributeError(f"module 'knnrefine' has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    value = importlib.import_module(f".{module}", __name__)
    value = value if attr is None else getattr(value, attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "refine",
    "certify",
    "Certificate",
    "KnnDistance",
    "knn_cdf",
    "cluster",
    "Clustering",
    "KnnDensity",
    "KnnDensityEstimator",
    "datasets",
    "io",
    "Mesh",
    "Torus",
    "PartitionedMesh",
    "write_partitioned",
    "theorem6_constants",
    "KIND_NAMES",
    "KnnRefineError",
    "InputError",
    "BudgetError",
    "EngineError",
    "FloorWarning",
    "LargeRunWarning",
    "WrapWarning",
    "__version__",
]
