"""The kNN density estimate f(x) = k / (n V_d d_{P,k}(x)^d) from a mesh (V_d the volume of
the unit ball: pi in the plane, 4 pi / 3 in space), and the default choices of k."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from numpy.typing import ArrayLike

if TYPE_CHECKING:  # the annotations' types only
    from ..mesh import Mesh

import math

import numpy as np

from .._validation import default_k  # noqa: F401  (the rule lives with the validation of k)
from .distance import KnnDistance


class DistanceLike(Protocol):
    """What the estimate needs of a d_{P,k}: a ``KnnDistance``, or one answered part by
    part (``scale.parts.PartitionedDistance``, which this layer does not import)."""

    k: float
    total: float

    def __call__(self, x: ArrayLike) -> np.ndarray: ...

    def grid(self, shape: Any = None, extent: Any = None) -> tuple: ...

    def integrate(self, func: Callable, region: Any = None) -> float: ...

    def sample_pieces(
        self, n: int, random_state: int | np.random.Generator | np.random.RandomState | None = None
    ) -> np.ndarray: ...


def default_pilot_k(n: float) -> int:
    """The default k of the adaptive estimate's pilot: 2 sqrt(n), at least 10 and at most n
    (k counts weight). A smoother pilot than the kNN estimate's own default: with the
    bandwidth and sensitivity chosen by leave-one-out likelihood, 2 sqrt(n) had lower L1 error
    than sqrt(n) / 2 on five of the study's six truths at n = 1e4 and all six at 1e5, and a
    held-out likelihood as good or better on five and six (``benchmarks/pilot_k.py``,
    docs/uses.md).

    Parameters
    ----------
    n : float
        The points' number or total weight.

    Returns
    -------
    int
    """
    return min(max(10, int(round(2.0 * np.sqrt(n)))), int(n))


def unit_ball_volume(dim: int) -> float:
    """V_d = pi^(d/2) / Gamma(d/2 + 1): pi in the plane, 4 pi / 3 in space.

    Parameters
    ----------
    dim : int

    Returns
    -------
    float
    """
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1)


class KnnDensity:
    """The kNN density estimate f(x) = k / (n V_d d_{P,k}(x)^d), from a mesh in the plane
    (V_2 = pi) or in space (V_3 = 4 pi / 3).

    Parameters
    ----------
    mesh, points, subdivide, weights
        As for ``KnnDistance``; with weights n is their total, so that a weighted point is
        that many points.
    normalized : bool
        Divide by the estimate's integral over the box, so that it integrates to 1 there.

    Notes
    -----
    Evaluate with ``density(x)`` (x of shape (..., d); NaN outside the box along
    non-periodic axes), on a grid with ``grid()``, integrate over a box with
    ``mass(region)``, draw from it with ``sample(n)``.
    """

    def __init__(
        self,
        mesh: Mesh,
        points: ArrayLike,
        *,
        normalized: bool = True,
        subdivide: bool = True,
        weights: ArrayLike | None = None,
    ) -> None:
        """See the class docstring."""
        self._of(KnnDistance(mesh, points, subdivide=subdivide, weights=weights), normalized)

    @classmethod
    def of_distance(
        cls, distance: KnnDistance | DistanceLike, *, normalized: bool = True
    ) -> KnnDensity:
        """The estimate from a d_{P,k} already built.

        Parameters
        ----------
        distance : KnnDistance or PartitionedDistance (a ``DistanceLike``)
            Anything with ``k``, ``total``, ``__call__``, ``grid``, ``integrate`` and
            ``sample_pieces``.
        normalized : bool
            As for the class.

        Returns
        -------
        KnnDensity
        """
        self = cls.__new__(cls)
        self._of(distance, normalized)
        return self

    def _of(self, distance, normalized):
        self.distance = distance
        self.k = distance.k
        self.n = distance.total
        self.dim = getattr(distance, "dim", 2)
        self.raw_constant = self.k / (self.n * unit_ball_volume(self.dim))
        self.raw_mass = distance.integrate(self._of_d(self.raw_constant))
        self.constant = self.raw_constant / self.raw_mass if normalized else self.raw_constant

    def _of_d(self, constant):
        dim = self.dim
        radius = getattr(self.distance, "equal_area_radius", None)
        if radius is not None and getattr(self.distance, "on_sphere", False):
            return lambda d: constant / radius(d) ** dim  # the cap's area: pi chord^2
        return lambda d: constant / d**dim

    def __call__(self, x: ArrayLike) -> np.ndarray:
        """The density at query points (NaN outside the box along non-periodic axes).

        Parameters
        ----------
        x : array-like (..., d)

        Returns
        -------
        ndarray (...)
        """
        return self._of_d(self.constant)(self.distance(x))

    def at_distance(self, d: ArrayLike) -> np.ndarray:
        """The density where d_{P,k} = d: k / (n V_d d^d), normalised (on the sphere with
        the cap's area, pi chord(d)^2, in place of V_2 d^2).

        Parameters
        ----------
        d : array-like
            Values of d_{P,k}.

        Returns
        -------
        ndarray
        """
        return self._of_d(self.constant)(np.asarray(d, float))

    def grid(
        self, shape: int | tuple | None = None, extent: Sequence[float] | None = None
    ) -> tuple:
        """The density at the centres of a grid over the box or any region
        (``KnnDistance.grid``).

        Parameters
        ----------
        shape : int or tuple of int, optional
            Cells per axis, slowest first; default 512 per axis in the plane, 64 in space.
        extent : sequence of float, optional
            The grid's region (``KnnDistance.grid``); default the box. NaN beyond the box
            along non-periodic axes.

        Returns
        -------
        xs, ys[, zs] : ndarray
        values : ndarray (ny, nx) or (nz, ny, nx)

        Raises
        ------
        InputError
            A bad shape or extent.
        """
        *axes, d = self.distance.grid(shape, extent)
        return (*axes, self._of_d(self.constant)(d))

    def mass(self, region: Sequence[float] | None = None) -> float:
        """The estimate's integral over a region: the probability of the part of the region
        in the box (regions wrap across periodic seams).

        Parameters
        ----------
        region : sequence of float, optional
            (x0, y0, x1, y1) in the plane, (x0, y0, z0, x1, y1, z1) in space; default the
            box.

        Returns
        -------
        float
        """
        return self.distance.integrate(self._of_d(self.constant), region)

    def sample(
        self, n: int, random_state: int | np.random.Generator | np.random.RandomState | None = None
    ) -> np.ndarray:
        """Points drawn from the normalised estimate: a piece of the mesh chosen by an upper
        bound of its mass, a uniform point in it, kept with probability density / bound
        (exact rejection sampling of the piecewise estimate; the pieces are well shaped, so
        most proposals are kept).

        Parameters
        ----------
        n : int
        random_state : None, int, numpy Generator or RandomState

        Returns
        -------
        ndarray (n, d)
        """
        return self.distance.sample_pieces(n, random_state)
