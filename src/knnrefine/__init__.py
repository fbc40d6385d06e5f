"""knnrefine: a small certified mesh carrying the k-th-nearest-neighbour distance of planar points.

An implementation of Gardner & Sheehy, "kth Nearest Neighbor Sampling in the Plane" (CCCG 2016):
``refine(points, k, tau)`` returns mesh vertices M with alpha d_{P,k} <= d_{M,2} <= beta d_{P,k}
everywhere in the box, whose Delaunay triangulation is tau-well-spaced.
"""

import importlib
import sys
import types
from typing import TYPE_CHECKING

from .errors import (
    BudgetError,
    EngineError,
    FloorWarning,
    InputError,
    KnnRefineError,
    LargeRunWarning,
    WrapWarning,
)

if TYPE_CHECKING:  # what the names below are, for type checkers (imported on first use)
    from . import datasets, io, plot  # noqa: F401  (plot: a module, not in __all__)
    from .api import certify, refine
    from .certify import Certificate
    from .cluster import Clustering, cluster
    from .density import KnnDensity, KnnDensityEstimator, KnnDistance
    from .density.cdf import knn_cdf
    from .mesh import KIND_NAMES, Mesh, Torus, theorem6_constants
    from .scale.parts import PartitionedMesh, write_partitioned

__version__ = "0.1.0"

# the public names, each imported on first use ("module", attribute; None: the module):
# ``import knnrefine`` then loads neither numba nor scipy (0.3 s of numba's import alone)
_LAZY = {
    "refine": ("api", "refine"), "certify": ("api", "certify"),
    "Certificate": ("certify", "Certificate"),
    "Clustering": ("cluster", "Clustering"), "cluster": ("cluster", "cluster"),
    "KnnDensity": ("density", "KnnDensity"), "KnnDistance": ("density", "KnnDistance"),
    "KnnDensityEstimator": ("density", "KnnDensityEstimator"),
    "knn_cdf": ("density.cdf", "knn_cdf"),
    "KIND_NAMES": ("mesh", "KIND_NAMES"), "Mesh": ("mesh", "Mesh"), "Torus": ("mesh", "Torus"),
    "theorem6_constants": ("mesh", "theorem6_constants"),
    "PartitionedMesh": ("scale.parts", "PartitionedMesh"),
    "write_partitioned": ("scale.parts", "write_partitioned"),
    "datasets": ("datasets", None), "io": ("io", None), "plot": ("plot", None),
}  # fmt: skip


def _load(name: str):
    module, attr = _LAZY[name]
    value = importlib.import_module(f".{module}", __name__)
    return value if attr is None else getattr(value, attr)


def __getattr__(name: str):
    """The public names on first use (``_LAZY``), and the subpackages and modules (as an
    eager ``import knnrefine`` made them attributes)."""
    if name in _LAZY:
        value = _load(name)
    else:
        try:
            value = importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module 'knnrefine' has no attribute {name!r}") from None
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


def _function_named_as_its_module(name: str) -> property:
    """``knnrefine.<name>`` is the function, whatever was imported before: importing the
    module ``knnrefine.<name>`` binds the package's attribute of that name to the module,
    which would hide the function: that binding (a module) is ignored, any other value
    assigned (a test's stand-in, say) is kept and read back."""
    key = f"_assigned_{name}"

    def get(self):
        return self.__dict__.get(key) or _load(name)

    def put(self, value):
        if not isinstance(value, types.ModuleType):
            self.__dict__[key] = value

    return property(get, put)


class _Package(types.ModuleType):
    """This package's module: ``certify`` and ``cluster`` are the functions (the modules of
    those names are imported as ``knnrefine.certify`` and ``knnrefine.cluster`` by
    ``importlib`` or ``from ... import``); pickled by name, as a module is."""

    certify = _function_named_as_its_module("certify")
    cluster = _function_named_as_its_module("cluster")

    def __reduce__(self):
        return importlib.import_module, (self.__name__,)


sys.modules[__name__].__class__ = _Package


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
