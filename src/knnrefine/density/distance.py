"""d_{P,k} everywhere in the box, from a mesh of P and P: ``KnnDistance``, the same in the
plane and in space.

The mesh is graded like d_{P,k} (Theorem 6), so a few exact evaluations per cell carry
d_{P,k} across the whole box: exact values at the vertices and edge midpoints, then linear
interpolation over the pieces (``plane.PlanePieces``: triangles split in four;
``space.SpacePieces``: tetrahedra split in eight). Evaluation, grids, integrals over boxes
(wrapping across periodic seams), sampling and the error against exact values are the same
calls in both dimensions.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from numpy.typing import ArrayLike

if TYPE_CHECKING:  # the annotations' types only
    from ..mesh import Mesh

import numpy as np

from ..engine.embedding import wrap_offsets
from ..engine.index import PointIndex
from ..engine.index3 import build_index3, kth_distances3
from ..engine.threads import in_chunks
from ..errors import InputError
from ..metric import BoxMetric, lonlat_of, unit_vectors, weighted_kth
from ..validation import (
    as_queries,
    check_inside,
    points_of_run,
    random_generator,
    sphere_points_of_run,
)
from .plane import PlanePieces, index_values, linear_pieces
from .space import SpacePieces
from .sphere import SphereIndex, SpherePieces, equal_area_radius


class MeshFrame(Protocol):
    """What d_{P,k} from known pieces needs of a mesh: a ``Mesh``, or a mesh in parts
    (``scale.parts.PartitionedMesh``, which this layer does not import)."""

    dim: int
    k: float
    box: tuple
    periodic: tuple


#: a grid's default cells along each axis, by dimension
DEFAULT_GRID = {2: 512, 3: 64}


class KnnDistance:
    """d_{P,k} at any point of the box, from a mesh of P and P itself, in the plane or in
    space (the mesh's dimension).

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
        if getattr(mesh, "on_sphere", False):
            self._on_sphere(mesh, points, subdivide, weights)
            return
        dim = mesh.dim
        pts, weights, total = points_of_run(mesh, points, weights)
        self._frame(mesh, len(pts), total)
        self._points = pts
        self.index = point_index(mesh, pts, weights)
        if dim == 2:
            nodes, triangles = mesh.covering()
            at_vertices, at_midpoints = index_values(self.index, self.k)
            nodes, triangles, values = linear_pieces(
                nodes, triangles, at_vertices, at_midpoints, subdivide
            )
            self.pieces: PlanePieces | SpacePieces = PlanePieces(
                nodes, triangles, values, mesh.box, mesh.periodic
            )
        else:
            self.pieces = SpacePieces(mesh, self.index.kth_local, subdivide)
        self.values = self.pieces.values

    def _on_sphere(self, mesh, points, subdivide, weights):
        """On the sphere: exact values from a kd-tree over the points' unit vectors, linear
        pieces over the spherical triangles (``sphere.SpherePieces``)."""
        unit, weights, total = sphere_points_of_run(mesh, points, weights)
        self._frame(mesh, len(unit), total)
        self._points = lonlat_of(unit)
        self.index = SphereIndex(unit, weights, mesh.radius)
        self.pieces = SpherePieces(mesh, self.index, mesh.k, subdivide)
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
        if self.on_sphere:
            return equal_area_radius(d, self.mesh.radius)
        return np.asarray(d, float)

    def _frame(self, mesh, n, total):
        self.mesh = mesh
        self.on_sphere = bool(getattr(mesh, "on_sphere", False))
        self.dim = mesh.dim
        self.k = mesh.k
        self.n = n
        self.total = total  # the points' number, or their total weight
        self.lo = np.array(mesh.box[: self.dim], float)
        self.hi = np.array(mesh.box[self.dim :], float)
        self._metric = BoxMetric(mesh.box, mesh.periodic)

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
        if self.on_sphere:  # the pieces and the index take unit vectors
            out[inside] = evaluate(unit_vectors(flat[inside]))
        else:
            out[inside] = evaluate(self._metric.wrap(flat[inside]))
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
        out = np.full((len(x), *values.shape[1:]), np.nan)
        out[inside] = self.pieces.interpolate(self._metric.wrap(x[inside]), values)
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
        if self.on_sphere:
            return self._where_inside(x, lambda unit: index.kth_unit(unit, self.k))
        return self._where_inside(x, lambda wrapped: index.kth(wrapped, self.k))

    def grid(self, shape: int | tuple | None = None) -> tuple:
        """The estimate at the centres of a grid over the box.

        Parameters
        ----------
        shape : int or tuple of int, optional
            Cells per axis, slowest first: (ny, nx) in the plane, (nz, ny, nx) in space; one
            number for all axes; default 512 per axis in the plane, 64 in space.

        Returns
        -------
        xs, ys[, zs] : ndarray
            The cells' centres along each axis.
        values : ndarray (ny, nx) or (nz, ny, nx)
            Row j at ys[j] (image order, origin at the lower left).
        """
        shape = grid_shape(shape, self.dim)
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
        interpolated d (space: ``space.SpacePieces.cdf``).

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
        """Mask of the points in the box along its non-periodic axes (sides included)."""
        ok = np.all(np.isfinite(x), axis=1)
        for a in range(self.dim):
            if not self.mesh.periodic[a]:
                ok &= (x[:, a] >= self.lo[a]) & (x[:, a] <= self.hi[a])
        return ok

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


def point_index(mesh, pts, weights=None):
    """Exact d_{P,k} for the mesh's points: an index with ``kth(x, k)`` at points x in the
    box (input coordinates, periodic axes wrapped). In the plane the engine's counting index
    that refined the mesh when it indexes these points (and weights), else a new one over
    them (a box wide enough for them along non-periodic axes); in space a periodic kd-tree
    (``TreeIndex``; the points must lie in the box along non-periodic axes)."""
    if mesh.dim == 3:
        check_inside(pts, mesh.box, mesh.periodic, warn=False)
        return TreeIndex(mesh, pts, weights)
    kept = getattr(mesh, "index", None)
    if kept is not None and kept.indexes(pts, weights):
        return kept
    box = np.array(mesh.box, float)
    per = np.array(mesh.periodic, bool)
    if len(pts):
        box[:2] = np.where(per, box[:2], np.minimum(box[:2], pts.min(axis=0)))
        box[2:] = np.where(per, box[2:], np.maximum(box[2:], pts.max(axis=0)))
    return PointIndex.build(pts, tuple(box), mesh.periodic, weights)


class TreeIndex:
    """Exact d_{P,k} in space from the engine's counting kd-tree over the points in the
    frame of the mesh's torus (relative to its origin, periodic axes wrapping): ``kth`` at
    input coordinates, ``kth_local`` at torus-frame ones (the pieces'). Each query collects
    the points in a window of radii about a guess and selects the k-th
    (``index3.kth_distances3``, as ``PointIndex.kth`` in the plane): nodes inside the inner
    radius count whole, so a query costs about the points in the window, not k log k as a
    k-nearest query does; below k = WINDOWS_FROM_K (unweighted) scipy's query is the
    faster. Weighted points: d_{P,k} is the least radius whose closed ball holds weight k.
    ``frame``: the torus' (origin, period) for a mesh that keeps none (a mesh in parts)."""

    def __init__(self, mesh, pts, weights=None, frame=None):
        origin, period = (mesh.torus.origin, mesh.torus.period) if frame is None else frame
        origin = np.asarray(origin, float)
        period = np.asarray(period, float)
        self.k = mesh.k
        self._origin = origin
        self._metric = BoxMetric((*origin, *(origin + period)), mesh.periodic)
        self._period = np.where(self._metric.periodic, period, np.inf)
        self._points = pts
        self._weights = weights
        local = np.ascontiguousarray(self._metric.frame(pts))
        self._tree = build_index3(local, copy=False, weights=weights)
        self.n = len(pts)
        self.total = float(len(pts) if weights is None else np.sum(weights))
        span = np.ptp(local, axis=0) if len(local) else np.ones(3)
        self._volume = float(np.prod(np.where(span > 0, span, max(span.max(), 1e-300))))

    def kth(self, x, k):
        """d_{P,k} at points x (q, 3) in input coordinates."""
        return self.kth_local(self._metric.frame(x), k)

    def kth_local(self, x, k=None):
        """d_{P,k} at points x (q, 3) relative to the torus origin (periodic coordinates
        wrapped here), on every core."""
        k = float(self.k if k is None else k)
        q = np.ascontiguousarray(self._metric.frame(np.asarray(x, float) + self._origin))
        if self._weights is None and k < WINDOWS_FROM_K:  # scipy's k-nearest query is faster
            return self._scipy_tree().query(q, k=[int(k)], workers=-1)[0][:, 0]
        return self.windows(q, k)

    def windows(self, q, k):
        """d_{P,k} at points q (q, 3) of the frame (periodic coordinates in [0, period)) by
        the counting tree's windows, whatever k (``kth_local`` takes scipy's query below
        WINDOWS_FROM_K; ``benchmarks/exact_kth3.py`` times both)."""
        k = float(k)
        q = np.ascontiguousarray(q, np.float64)
        m = len(q)
        guess, width = self._guess(q, k)
        r_in, r_out = guess / width, guess * width
        per_point = self.total / max(self.n, 1) if self._weights is not None else 1.0
        cap = int(min(self.n, 4.0 * k / max(per_point, 1e-300) + 1024)) + 1
        periodic = np.asarray(self._metric.periodic, bool)
        out = np.empty(m)
        tree, period = self._tree, self._period

        def chunk(a, b):
            kth_distances3(tree, q, k, r_in, r_out, period, periodic, cap, out, a, b)

        in_chunks(chunk, m)
        lost = np.flatnonzero(np.isnan(out))
        if len(lost):  # more ties than a window holds (rare): scipy's tree
            ck = self._scipy_tree()
            if self._weights is None:
                out[lost] = ck.query(q[lost], k=[int(k)], workers=-1)[0][:, 0]
            else:
                out[lost] = weighted_kth(ck, self._weights, q[lost], k, -1)
        return out

    def _scipy_tree(self):
        """scipy's periodic kd-tree of the points (frame coordinates), built once."""
        if getattr(self, "_ck", None) is None:
            self._ck = self._metric.tree(self._points)
        return self._ck

    def _guess(self, q, k):
        """(a guess of d_{P,k} at the queries q (frame), the window's factor about it): the
        k_s-th distance in a seeded sample of an eighth of P, at most GUESS_SAMPLE points
        (k_s: the sample's share of the points that hold weight k, at least 1), scaled by the
        cube root of the ratio of the two counts (a ball's count grows with its volume), in
        a window of about two of its standard deviations (the count's relative noise
        1 / sqrt(k_s), a third of it in the radius); below 8000 points, the radius holding k
        points at the mean density, halved and doubled. A poor guess costs only retries
        (wider windows), never a wrong answer."""
        s = min(self.n // 8, GUESS_SAMPLE)
        if s < 1000:  # few points: any window is cheap
            uniform = k * self._volume / (4.0 / 3.0 * np.pi * max(self.total, 1e-300))
            return np.full(len(q), uniform ** (1 / 3)), 2.0
        if getattr(self, "_sample_tree", None) is None:
            pick = np.random.default_rng(0).choice(self.n, s, replace=False)
            self._sample_tree = self._metric.tree(self._points[pick])
        points = k * self.n / max(self.total, 1e-300)  # points holding weight k, on average
        ks = max(int(round(points * s / self.n)), 1)
        d = self._sample_tree.query(q, k=[ks], workers=-1)[0][:, 0]
        d = d * (points * s / (ks * self.n)) ** (1 / 3)
        fine = np.isfinite(d) & (d > 0)
        width = float(np.clip(1.0 + 2.0 / (3.0 * np.sqrt(ks)), 1.03, 2.0))
        return np.where(fine, d, np.max(d[fine]) if fine.any() else 1.0), width


GUESS_SAMPLE = 30000  # points of P sampled for TreeIndex's guesses of d_Pk
# TreeIndex's windows from this k on (unweighted; below it scipy's k-nearest query was
# faster: ``benchmarks/exact_kth3.py`` at 10^5 clustered points, k = 64, 0.95 against 0.78 s;
# k = 128, 0.98 against 1.10 s)
WINDOWS_FROM_K = 100


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
