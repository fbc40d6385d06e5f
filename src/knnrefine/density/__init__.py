"""The k-th-nearest-neighbour distance everywhere, and density estimates, from a mesh, in the
plane and in space.

- ``distance``: ``KnnDistance``, d_{P,k} at any point, on grids, integrated over boxes;
- ``estimate``: ``KnnDensity``, the kNN estimate k / (n V_d d_{P,k}^d), and default k;
- ``adaptive``: ``AdaptiveDensity``, kernels with bandwidths from d_{P,k} (the plane), and
  the choice of their smoothing by cross-validation;
- ``estimator``: ``KnnDensityEstimator``, all of it as a scikit-learn estimator;
- ``cdf``: ``knn_cdf``, the kNN-CDF of cosmology for several k at once;
- ``plane``, ``space``: the linear pieces of each dimension (kernels: users call the above).
"""

from .adaptive import BANDWIDTHS, SENSITIVITIES, AdaptiveDensity, choose_smoothing, square_integral
from .cdf import KnnCdf, knn_cdf
from .distance import KnnDistance
from .estimate import KnnDensity, default_k, default_pilot_k, unit_ball_volume
from .estimator import KnnDensityEstimator

__all__ = [
    "BANDWIDTHS",
    "SENSITIVITIES",
    "AdaptiveDensity",
    "KnnDensity",
    "KnnCdf",
    "KnnDensityEstimator",
    "KnnDistance",
    "choose_smoothing",
    "default_k",
    "default_pilot_k",
    "knn_cdf",
    "square_integral",
    "unit_ball_volume",
]
