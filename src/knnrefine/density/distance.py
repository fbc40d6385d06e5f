"""d_{P,k} everywhere in the domain, from a mesh of P and P: ``KnnDistance``, the same in
the plane, in space and on the sphere.

The mesh is graded like d_{P,k} (Theorem 6), so a few exact evaluations per cell carry
d_{P,k} across the whole domain: exact values at the vertices and edge midpoints, then
linear interpolation over the pieces (each domain's ``density.Pieces``: triangles split in
four in the plane and on the sphere, tetrahedra split in eight in space). Evaluation, grids,
integrals over boxes (wrapping across periodic seams), sampling and the error against exact
values are the same calls in every domain.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from numpy.typing import ArrayLike

if TYPE_CHECKING:  # the annotations' types only
    from ..mesh import Mesh

import numpy as np

from .._domains import part
from .._domains.plane.density import Pieces as PlanePieces
from .._domains.space.density import Pieces as SpacePieces
from .._engine.embedding import wrap_offsets
from .._validation import (
    as_queries,
    random_generator,
)
from ..errors import InputError


class MeshFrame(Protocol):
    """What d_{P,k} from known pieces needs of a mesh: a ``Mesh``, or a mesh in parts
    (``scale.parts.PartitionedMesh``, which this layer does not import)."""

    dim: int
    k: float
    box: tuple
    periodic: tuple
    domain: str
    extent: tuple


#: a grid's default cells along each axis, by dimension
DEFAULT_GRID = {2: 512, 3: 64}


class KnnDistance:
    """d_{P,k} at any point of the domain, from a mesh of P and P itself, in the plane, in
    space or on the sphere (the mesh's domain).

    Parameters
    ----------
    mesh : Mesh
        From ``knnrefine.refine(points, k, ...)``; its k is the one estimated.
    points : array-like (n, d)
        The same points.
    subdivide : bool
        Also evaluate at edge midpoints (four linear pieces per triangle, eight per
        tetrahedron): about half the interpolation error for a few times the (cheap) exact
        evaluations.
    weights : array-like (n,), optional
        The weights the mesh was refined with (required for a weighted mesh, refused for
        another): d_{P,k} is then the least radius holding weight k.

    Raises
    ------
    InputError
        Points of another dimension or number than the mesh's, weights that are not the
        run's, fewer points (or less weight) than k.

    Notes
    -----
    Outside the box (along a non-periodic axis, beyond any of its sides) the estimate is NaN:
    d_{P,k} is certified only in the box; periodic axes wrap. Queries have any shape (..., d)
    and the result the leading shape (...). ``values`` are the exact values at the pieces'
    nodes (the plane) or at the mesh's vertices (space).
    """

    def __init__(
        self,
        mesh: Mesh,
        points: ArrayLike,
        *,
        subdivide: bool = True,
        weights: ArrayLike | None = None,
    ) -> None:
        """See the class docstring."""
        domain = part(mesh.domain, "density")
        self._points, self.index, self.pieces, total = domain.build(mesh, points, weights,
                                                                    subdivide)  # fmt: skip
        self._frame(mesh, len(self._points), total)
        self.values = self.pieces.values

    def equal_area_radius(self, d: ArrayLike) -> np.ndarray:
        """The radius of the flat ball whose volume is the ball of radius d's: d itself in
        a box; on the sphere the chord 2 R sin(d / 2R), the cap's area being pi chord^2.
        The kNN density is k / (n V_d r^d) with this r.

        Parameters
        ----------
        d : array-like
            Distances (great-circle on the sphere).

        Returns
        -------
        ndarray
        """
        return self._domain.flat_radius(self.mesh, d)

    def _frame(self, mesh, n, total):
        self.mesh = mesh
        self._domain = part(mesh.domain, "density")
        self._to_frame = self._domain.to_frame(mesh)
        self.on_sphere = mesh.domain == "sphere"
        self.dim = mesh.dim
        self.k = mesh.k
        self.n = n
        self.total = total  # the points' number, or their total weight
        self.lo = np.array(mesh.extent[: self.dim], float)
        self.hi = np.array(mesh.extent[self.dim :], float)
        self._answerable = self._domain.answerable(mesh)

    @classmethod
    def of_pieces(
        cls,
        mesh: MeshFrame,
        n: int,
        total: float,
        nodes: np.ndarray,
        triangles: np.ndarray,
        values: np.ndarray,
        located: np.ndarray | None = None,
    ) -> KnnDistance:
        """A KnnDistance in the plane from linear pieces whose node values are known already
        (a part of a partitioned mesh, ``scale.parts.PartitionedDistance``). Without the
        points, no ``exact``.

        Parameters
        ----------
        mesh : Mesh or PartitionedMesh (a ``MeshFrame``)
            Its dimension, k, box and periodic axes.
        n, total : int, float
            The points' number and their total weight (n unweighted).
        nodes : ndarray (p, 2)
        triangles : ndarray (t, 3)
            The pieces that evaluation, grids and integrals use.
        values : ndarray (p,)
            d_{P,k} at the nodes.
        located : ndarray (s, 3), optional
            Pieces over the same nodes where points are located (default: ``triangles``).

        Returns
        -------
        KnnDistance
        """
        pieces = PlanePieces(nodes, triangles, values, mesh.box, mesh.periodic, located)
        return cls.of_linear_pieces(mesh, n, total, pieces)

    @classmethod
    def of_linear_pieces(
        cls, mesh: MeshFrame, n: int, total: float, pieces: PlanePieces | SpacePieces
    ) -> KnnDistance:
        """A KnnDistance from linear pieces already built, in the plane or in space (a part
        of a partitioned mesh). Without the points, no ``exact``.

        Parameters
        ----------
        mesh, n, total
            As for ``of_pieces``.
        pieces : PlanePieces or SpacePieces
            With their values at the mesh's vertices (``values``).

        Returns
        -------
        KnnDistance
        """
        self = cls.__new__(cls)
        self._frame(mesh, n, total)
        self._points = self.index = None
        self.pieces = pieces
        self.values = pieces.values
        return self

    # the plane's pieces, named as before (``scale.parts`` and the plots read them)
    @property
    def nodes(self):
        return self.pieces.nodes

    @property
    def triangles(self):
        return self.pieces.triangles

    # -- evaluation ------------------------------------------------------------------------
    def __call__(self, x: ArrayLike) -> np.ndarray:
        """The interpolated d_{P,k} at query points; NaN outside the box along non-periodic
        axes (on every side), periodic axes wrap.

        Parameters
        ----------
        x : array-like (..., d)

        Returns
        -------
        ndarray (...)
        """
        return self._where_inside(x, self.pieces.interpolate)

    def _where_inside(self, x, evaluate):
        """``evaluate`` at the query points inside the box (periodic axes wrapped), NaN
        beyond it along non-periodic axes."""
        flat, shape = as_queries(x, self.dim)
        out = np.full(len(flat), np.nan)
        inside = self._inside(flat)
        out[inside] = evaluate(self._to_frame(flat[inside]))  # the pieces' and index's frame
        return out.reshape(shape)

    def interpolate(self, x: np.ndarray, values: ArrayLike) -> np.ndarray:
        """Any node values linearly interpolated over the pieces (the plane).

        Parameters
        ----------
        x : ndarray (q, 2)
            Query points.
        values : array-like (nodes, ...)
            One value (or row) per node of the pieces.

        Returns
        -------
        ndarray (q, ...)
            NaN outside the box along non-periodic axes.
        """
        values = np.asarray(values, float)
        inside = self._inside(x)
        if inside.all():  # (the usual case: no masked copies of the points)
            return self.pieces.interpolate(self._to_frame(x), values)
        out = np.full((len(x), *values.shape[1:]), np.nan)
        out[inside] = self.pieces.interpolate(self._to_frame(x[inside]), values)
        return out

    def exact(self, x: ArrayLike) -> np.ndarray:
        """Exact d_{P,k}, one kd-tree query per point (the reference).

        Parameters
        ----------
        x : array-like (..., d)

        Returns
        -------
        ndarray (...)
            NaN outside the box along non-periodic axes, as the estimate.

        Raises
        ------
        InputError
            For a d_{P,k} built from node values alone (``of_pieces``).
        """
        index = self.index
        if index is None:
            raise InputError(
                "this d_Pk was built from node values alone (a part of a partitioned mesh): "
                "exact values need the points; build KnnDistance(mesh, points)"
            )
        return self._where_inside(x, lambda q: index.kth(q, self.k))

    def grid(
        self, shape: int | tuple | None = None, extent: Sequence[float] | None = None
    ) -> tuple:
        """The estimate at the centres of a grid over the box, or over any region.

        Parameters
        ----------
        shape : int or tuple of int, optional
            Cells per axis, slowest first: (ny, nx) in the plane, (nz, ny, nx) in space; one
            number for all axes; default 512 per axis in the plane, 64 in space.
        extent : sequence of float, optional
            The region the grid covers: (x0, y0, x1, y1) or (x0, y0, z0, x1, y1, z1) in the
            points' units, on the sphere (lon0, lat0, lon1, lat1) in degrees; default the
            box (the whole sphere). Centres beyond the box along non-periodic axes get NaN;
            periodic axes and longitudes wrap.

        Returns
        -------
        xs, ys[, zs] : ndarray
            The cells' centres along each axis.
        values : ndarray (ny, nx) or (nz, ny, nx)
            Row j at ys[j] (image order, origin at the lower left).

        Raises
        ------
        InputError
            A bad shape or extent.
        """
        shape = grid_shape(shape, self.dim)
        if extent is not None:  # any region: each centre located on the pieces
            axes = grid_axes(check_extent(extent, self.dim, self.on_sphere), shape)
            return (*axes, self(grid_points(axes)).reshape(shape))
        *axes, out = self.pieces.grid(shape)
        missed = np.isnan(out)  # centres on no piece by rounding (none expected): located
        if missed.any():
            at = np.nonzero(missed)  # slowest axis first
            x = np.column_stack([axes[a][at[self.dim - 1 - a]] for a in range(self.dim)])
            out[missed] = self(x)
        return (*axes, out)

    def error(
        self,
        probes: ArrayLike | None = None,
        *,
        n_random: int = 20000,
        random_state: int | np.random.Generator | np.random.RandomState | None = 0,
    ) -> dict:
        """Relative error of the estimate against exact d_{P,k}.

        Parameters
        ----------
        probes : array-like (q, d), optional
            Where to compare (default: ``n_random`` uniform points of the box and as many of
            the input points).
        n_random : int
            The default probes' number.
        random_state : None, int, numpy Generator or RandomState
            Where the default probes are drawn from.

        Returns
        -------
        dict
            ``median``, ``p99`` (99th percentile), ``worst``, ``probes`` (how many counted).
        """
        if probes is None:
            rng = random_generator(random_state)
            uniform = self.lo + rng.random((n_random, self.dim)) * (self.hi - self.lo)
            data = self._points[rng.choice(self.n, min(n_random, self.n), replace=False)]
            probes = np.concatenate([uniform, data])
        est = self(probes)
        ref = self.exact(probes)
        rel = np.abs(est - ref) / ref
        return {
            "median": float(np.nanmedian(rel)),
            "p99": float(np.nanpercentile(rel, 99)),
            "worst": float(np.nanmax(rel)),
            "probes": int(np.isfinite(rel).sum()),
        }

    # -- integrals ---------------------------------------------------------------------------
    def integrate(self, func: Callable, region: Sequence[float] | None = None) -> float:
        """Integral of func(d) over a region, d the interpolated d_{P,k}: a quadrature on
        every linear piece, the pieces clipped to the region.

        Parameters
        ----------
        func : callable
            Of an array of d values (vectorised).
        region : sequence of float, optional
            (x0, y0, x1, y1) in the plane, (x0, y0, z0, x1, y1, z1) in space; default the
            box. It counts only where it meets the box along non-periodic axes; along
            periodic axes it wraps around (at most one period wide).

        Returns
        -------
        float
        """
        if self.on_sphere:
            return self.pieces.integrate(func, None if region is None else _sphere_region(region))
        return float(sum(self.pieces.integrate(func, rect) for rect in self._region(region)))

    def sample_pieces(
        self, n: int, random_state: int | np.random.Generator | np.random.RandomState | None = None
    ) -> np.ndarray:
        """Points from the density proportional to 1 / d^dim over the box (``KnnDensity``).

        Parameters
        ----------
        n : int
        random_state : None, int, numpy Generator or RandomState

        Returns
        -------
        ndarray (n, d)
        """
        return self.pieces.sample(n, random_generator(random_state))

    # -- the kNN-CDF (space) -----------------------------------------------------------------
    def cdf(self, r: ArrayLike) -> np.ndarray:
        """The kNN-CDF of cosmology, CDF(r) = vol{x : d(x) <= r} / vol(box), exact for the
        interpolated d (space: its ``Pieces.cdf``).

        Parameters
        ----------
        r : array-like (q,)
            Radii.

        Returns
        -------
        ndarray (q,)

        Raises
        ------
        InputError
            In the plane.
        """
        return self._space_only("cdf")(r)

    def cdf_bounds(self, r: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Rigorous bounds of the true kNN-CDF (space).

        Parameters
        ----------
        r : array-like (q,)
            Radii.

        Returns
        -------
        lower, upper : ndarray (q,)
        """
        return self._space_only("cdf_bounds")(r)

    def _space_only(self, what):
        if self.dim != 3:
            raise InputError(f"{what} (the kNN-CDF) is built for meshes in space (3 columns)")
        return getattr(self.pieces, what)

    # -- helpers -----------------------------------------------------------------------------
    def _inside(self, x):
        """Mask of the query points the estimate answers (the domain's rule: in the box along
        its non-periodic axes, sides included; on the sphere, latitudes within +-90)."""
        return self._answerable(x)

    def _region(self, region):
        """The boxes, inside the box, that make up ``region``: clipped along non-periodic
        axes, cut at the seam and wrapped along periodic ones."""
        dim = self.dim
        if region is None:
            return [np.array([self.lo, self.hi])]
        names = "(x0, y0, x1, y1)" if dim == 2 else "(x0, y0, z0, x1, y1, z1)"
        try:
            bounds = [float(r) for r in region]
        except (TypeError, ValueError):
            bounds = []
        if len(bounds) != 2 * dim:
            raise InputError(f"region must be {2 * dim} numbers {names}, got {region!r}")
        low, high = bounds[:dim], bounds[dim:]
        if not (np.isfinite(bounds).all() and all(a < b for a, b in zip(low, high, strict=True))):
            raise InputError(f"region {region} must be finite with each lower end below its upper")
        spans = []
        for a, (u0, u1) in enumerate(zip(low, high, strict=True)):
            lo, hi = self.lo[a], self.hi[a]
            if not self.mesh.periodic[a]:
                spans.append([(max(u0, lo), min(u1, hi))] if u1 > lo and u0 < hi else [])
                continue
            period = hi - lo
            if u1 - u0 >= period * (1 - 1e-12):
                spans.append([(lo, hi)])
                continue
            s0 = lo + float(wrap_offsets(np.array([u0]), lo, period)[0])
            s1 = s0 + (u1 - u0)
            spans.append([(s0, min(s1, hi))] + ([(lo, lo + s1 - hi)] if s1 > hi else []))
        boxes = [[]]
        for axis_spans in spans:
            boxes = [b + [s] for b in boxes for s in axis_spans if s[1] > s[0]]
        return [np.array(b).T for b in boxes]


def _sphere_region(region):
    """(lon0, lat0, lon1, lat1) checked: latitudes in [-90, 90] and increasing, longitudes
    increasing (wrapping: 170 to 190 crosses the antimeridian), at most 360 apart."""
    try:
        bounds = [float(r) for r in region]
    except (TypeError, ValueError):
        bounds = []
    if len(bounds) != 4 or not np.isfinite(bounds).all():
        raise InputError(f"region on the sphere must be 4 numbers (lon0, lat0, lon1, lat1), "
                         f"got {region!r}")  # fmt: skip
    lon0, lat0, lon1, lat1 = bounds
    if not (-90 <= lat0 < lat1 <= 90 and lon0 < lon1 and lon1 - lon0 <= 360):
        raise InputError(
            f"region {tuple(region)} must have -90 <= lat0 < lat1 <= 90 and lon0 < lon1 <= "
            "lon0 + 360 (longitudes wrap: (170, -10, 190, 10) crosses the antimeridian)"
        )
    return lon0, lat0, lon1, lat1


def check_extent(extent, dim=2, sphere=False):
    """A grid's region as 2 * dim finite numbers (low corner, high corner), each side
    positive; on the sphere longitudes and latitudes in degrees, latitudes within +-90."""
    if sphere:
        names, count = "(lon0, lat0, lon1, lat1) in degrees", "four"
    else:
        names = "(x0, y0, x1, y1)" if dim == 2 else "(x0, y0, z0, x1, y1, z1)"
        count = "four" if dim == 2 else "six"
    try:
        vals = tuple(float(v) for v in extent)
    except (TypeError, ValueError):
        raise InputError(f"extent must be {count} numbers {names}, got {extent!r}") from None
    if len(vals) != 2 * dim or not np.all(np.isfinite(vals)):
        raise InputError(f"extent must be {count} finite numbers {names}, got {extent!r}")
    if not all(vals[dim + a] > vals[a] for a in range(dim)):
        raise InputError(f"extent {vals} must have each low corner below its high one {names}")
    if sphere and not -90.0 <= vals[1] < vals[3] <= 90.0:
        raise InputError(f"extent {vals}: latitudes must lie within [-90, 90]")
    return vals


def grid_axes(extent, shape):
    """The cells' centres along each axis (x first) of a grid of ``shape`` cells (slowest
    axis first) over ``extent`` (low corner, high corner)."""
    dim = len(shape)
    cells = shape[::-1]
    return [extent[a] + (np.arange(cells[a]) + 0.5) * (extent[dim + a] - extent[a]) / cells[a]
            for a in range(dim)]  # fmt: skip


def grid_points(axes):
    """The centres of a grid (its axes, x first) as points (q, d), the slowest axis's index
    changing slowest (the order of the grid's values, flattened)."""
    mesh = np.meshgrid(*axes[::-1], indexing="ij")
    return np.column_stack([g.ravel() for g in mesh[::-1]])


def grid_shape(shape, dim=2):
    """Cells per axis (slowest first) from a grid shape: ``dim`` positive whole numbers, one
    number for every axis, or None for the default."""
    if shape is None:
        return (DEFAULT_GRID[dim],) * dim
    if isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
        shape = (shape,) * dim
    try:
        out = tuple(int(s) for s in shape)
        ok = len(out) == dim and all(int(s) == s for s in shape)
    except (TypeError, ValueError):
        ok = False
    names = "(ny, nx)" if dim == 2 else "(nz, ny, nx)"
    if not ok or min(out) < 1:
        raise InputError(f"shape must be {dim} positive whole numbers {names}, got {shape!r}")
    return out
