"""The result of a refinement: the mesh M and what it promises (Theorem 6)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from ._engine.jit import kernel
from ._engine.raster import clip_triangles
from ._engine.state import KIND_NAMES  # how each vertex came: the insertion moves
from ._metric import BoxMetric, chord_to_angle, unit_vectors
from ._validation import answerable, as_queries
from .errors import InputError

SPHERE_EXTENT = (-180.0, -90.0, 180.0, 90.0)  # a sphere mesh's coordinates: lon/lat degrees


def theorem6_constants(tau: float) -> tuple[float, float]:
    """Theorem 6's constants for a refinement at tau.

    beta = (3 - theta) / (1 - theta), theta = sqrt(1 - 1 / tau^2) (Theorem 5). alpha =
    1 / (2 K + 1) with K = max(2 tau / (tau - 2), 3) (Lemma 2 and Theorem 3): for tau <= 6 this
    is Theorem 6's (tau - 2) / (5 tau - 2); beyond, the induction step for a Break at a cell's
    far corner needs K >= 3 (the paper's alpha is not proven there), so alpha stays 1/7.

    Parameters
    ----------
    tau : float
        The well-spacedness bound, > 2.

    Returns
    -------
    (alpha, beta) : tuple of float
        alpha d_{P,k} <= d_{M,2} <= beta d_{P,k} everywhere in the box (above the floor).
    """
    theta = np.sqrt(1.0 - 1.0 / tau**2)
    big_k = max(2.0 * tau / (tau - 2.0), 3.0)
    return 1.0 / (2.0 * big_k + 1.0), float((3.0 - theta) / (1.0 - theta))


def sphere_constants(tau: float, largest_cap: float) -> tuple[float, float]:
    """Theorem 6's constants on the sphere, for a mesh whose largest circumcap has angular
    radius ``largest_cap`` (radians, below pi / 2).

    alpha is the plane's (Lemmas 1-3 are metric arguments). Theorem 5's one Euclidean step,
    |x' - cc(t)| <= theta |p - cc(t)| in the right triangle p, o, cc(t), becomes spherical
    Pythagoras, cos R = cos |p o| cos |o cc(t)| with |p o| >= R / tau: theta grows to
    arccos(cos R / cos(R / tau)) / R, which increases with R from the plane's
    sqrt(1 - 1 / tau^2) (docs/algorithm.md, "On the sphere").

    Parameters
    ----------
    tau : float
        The well-spacedness bound, > 2.
    largest_cap : float
        The largest circumcap's angular radius R, radians.

    Returns
    -------
    (alpha, beta) : tuple of float
    """
    alpha, _ = theorem6_constants(tau)
    plane = np.sqrt(1.0 - 1.0 / tau**2)
    r = float(largest_cap)
    if not r < 0.5 * np.pi:  # a cap of a hemisphere or more: Theorem 5's step has no bound
        return alpha, float("inf")
    ratio = min(1.0, np.cos(r) / np.cos(r / tau))
    theta = plane if r <= 0 else max(plane, float(np.arccos(ratio)) / r)
    if theta >= 1.0:
        return alpha, float("inf")
    return alpha, float((3.0 - theta) / (1.0 - theta))


def moves_of(kinds) -> dict:
    """Vertices by the move that made them (``KIND_NAMES``), from their kinds."""
    counts = np.bincount(np.asarray(kinds, np.int64), minlength=len(KIND_NAMES))
    return {name: int(counts[i]) for i, name in enumerate(KIND_NAMES)}


@dataclass
class Stats(Mapping):
    """What a run did: one record with the same keys in every domain (the plane, space,
    the sphere; one process, threads or tiles), read as attributes or as a mapping
    (``stats["n"]``, ``stats.get("weight")``, ``dict(stats)``).

    Attributes
    ----------
    n : int
        Input points.
    weight : float or None
        Their total weight (a weighted run), else None.
    m, m_torus, cells : int
        Vertices returned, vertices the engine refined (the torus'; on the sphere m), cells
        returned.
    initial_vertices : int
        Vertices of the initial mesh.
    moves : dict
        Vertices by the move that made them (``KIND_NAMES``).
    circumball_tests, cell_tests : int
        Counting queries of circumballs (circumcaps on the sphere) and of Voronoi cells.
    failed_insertions : int
        Insertions the triangulation refused (a vertex too close to another).
    floor_circumballs, floor_cells : int
        Elements left at the resolution floor still holding k points.
    points_under_floor : int
        Input points in them.
    largest_circumball : float
        The largest circumradius of the triangulation the engine refined (in a box the
        torus', margins included), in input units; on the sphere the largest circumcap's
        angular radius times ``radius`` (the sphere's beta depends on it).
    estimated_vertices, max_vertices : int
        The size estimated before refining and the vertex budget. In a box the estimate is
        ``engine.size``'s (0 where none is made: a tiled run in space); on the sphere
        ``domains.sphere.run.estimate_sphere``'s (2.5 n / k, the uniform points' figure), and the
        budget max(10^6, 4 n) unless max_vertices is given. Every domain refuses a run
        whose estimate is far beyond the budget or memory, before any work.
    rounds : list or None
        A tiled run's turns and last step; None for one process.
    time : dict
        Seconds: ``setup`` (index, embedding, initial mesh), ``refine``, ``assemble``,
        ``total`` (the call).
    points_digest : str
        A hash of the points (and weights) the mesh was refined from, as checked (hex): what
        ``refine(..., start=mesh)`` checks the first rows of its points against. "" for a
        mesh of an older version.
    continued : dict or None
        For a run continued from a start mesh (``refine(..., start=)``): the points added
        (``points``), the start's vertices (``from_vertices``) and the triangles or
        tetrahedra the new points reopened (``reopened``); None for a fresh run.
    """

    n: int = 0
    weight: float | None = None
    m: int = 0
    m_torus: int = 0
    cells: int = 0
    initial_vertices: int = 0
    moves: dict = field(default_factory=dict)
    circumball_tests: int = 0
    cell_tests: int = 0
    failed_insertions: int = 0
    floor_circumballs: int = 0
    floor_cells: int = 0
    points_under_floor: int = 0
    largest_circumball: float = 0.0
    estimated_vertices: int = 0
    max_vertices: int = 0
    rounds: list | None = None
    time: dict = field(default_factory=dict)
    points_digest: str = ""
    continued: dict | None = None

    # the keys of knnrefine 0.1's per-domain dictionaries (files written then still read)
    RENAMED = {
        "disk_tests": "circumball_tests",
        "circumcap_tests": "circumball_tests",
        "failed": "failed_insertions",
        "floor_circumcaps": "floor_circumballs",
        "triangles": "cells",
    }

    @property
    def seconds(self) -> float:
        """The whole call's seconds (``time["total"]``)."""
        return float(self.time.get("total", 0.0))

    def __getitem__(self, key: str):
        if key not in _STATS_KEYS:
            raise KeyError(f"{key!r}: Mesh.stats has {', '.join(_STATS_KEYS)}")
        return getattr(self, key)

    def __setitem__(self, key: str, value) -> None:
        self[key]  # a known key, else KeyError
        setattr(self, key, value)

    def __iter__(self):
        return iter(_STATS_KEYS)

    def __len__(self) -> int:
        return len(_STATS_KEYS)

    def to_dict(self) -> dict:
        """The record as plain Python values (what .npz and JSON files keep)."""
        return {key: getattr(self, key) for key in _STATS_KEYS}

    @classmethod
    def from_dict(cls, d: Mapping, radius: float = 1.0) -> Stats:
        """The record of a file's dictionary, of this version or of 0.1's per-domain keys
        (``radius``: a sphere mesh's, whose 0.1 files kept the largest circumcap in
        radians)."""
        if isinstance(d, Stats):
            return d
        given = dict(d)
        for old, new in cls.RENAMED.items():
            if old in given:
                given.setdefault(new, given.pop(old))
        if "largest_circumcap" in given:
            given.setdefault("largest_circumball", given.pop("largest_circumcap") * radius)
        if "m0" in given:
            given.setdefault("initial_vertices", given.pop("m0").get("vertices", 0))
        if "seconds" in given:
            given.setdefault("time", {"total": given.pop("seconds")})
        if "index" in given.get("time", {}):
            given["time"] = {("setup" if k == "index" else k): v for k, v in given["time"].items()}
        return cls(**{key: given[key] for key in _STATS_KEYS if key in given})


_STATS_KEYS = tuple(f.name for f in fields(Stats))


class Cells:
    """What a torus and a mesh say of their cells in any dimension: ``dim`` from the
    vertices, and the cells by their name (``triangles`` in the plane, ``tetrahedra`` in
    space; the other name is an AttributeError saying which the mesh has)."""

    vertices: np.ndarray
    cells: np.ndarray

    @property
    def dim(self) -> int:
        """2 in the plane, 3 in space."""
        return int(np.shape(self.vertices)[1])

    @property
    def triangles(self) -> np.ndarray:
        """The cells in the plane."""
        return self._named("triangles", 2)

    @property
    def tetrahedra(self) -> np.ndarray:
        """The cells in space."""
        return self._named("tetrahedra", 3)

    def _named(self, name, dim):
        if self.dim != dim:
            other = "triangles" if name == "tetrahedra" else "tetrahedra"
            raise AttributeError(
                f"a mesh in {self.dim} dimensions has {other}, not {name} (its cells: .cells)"
            )
        return self.cells


@dataclass(frozen=True, eq=False)
class Torus(Cells):
    """The triangulation of the flat torus that the engine refined, in input units, in the
    plane or in space (the dimension is ``vertices.shape[1]``).

    In a periodic box it is the mesh itself; along non-periodic axes the box sits inside it
    with a margin (see ``knnrefine._engine.embedding``). ``vertices`` are relative to
    ``origin`` (in [0, period), exact, so that they keep full precision whatever the offset
    of the data); corner i of cell t sits at ``origin + vertices[cells[t, i]] + offsets[t, i]
    * period``, and ``neighbours[t, i]`` (kept in the plane, None in space) is the cell across
    the facet opposite corner i. ``triangles`` (plane) and ``tetrahedra`` (space) name the
    cells.

    Attributes
    ----------
    origin, period : tuple of float
        The torus' corner and sides, input units.
    vertices : ndarray (m, d)
        Relative to ``origin``, in [0, period).
    cells : ndarray (t, d + 1)
    offsets : ndarray (t, d + 1, d) int8
    kinds : ndarray (m,) int8
        How each vertex came (``KIND_NAMES``).
    neighbours : ndarray (t, d + 1) or None
    """

    origin: tuple
    period: tuple
    vertices: np.ndarray
    cells: np.ndarray
    offsets: np.ndarray
    kinds: np.ndarray
    neighbours: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Mesh(Cells):
    """Mesh vertices M whose second-nearest-neighbour distance approximates d_{P,k}: one
    type in the plane and in space (its dimension is ``vertices.shape[1]``).

    Attributes
    ----------
    vertices : (m, d) float64
        In input coordinates. Periodic axes: wrapped into the box. Non-periodic axes: every
        vertex that is one of the two nearest mesh vertices of some point of the box.
    cells : (t, d + 1) int32
        Positively oriented Delaunay cells: triangles in the plane (``triangles``),
        tetrahedra in space (``tetrahedra``). Periodic box: all cells of the torus. Along
        non-periodic axes: those that meet the box.
    offsets : (t, d + 1, d) int8 or None
        Corner i of cell t is ``vertices[cells[t, i]] + offsets[t, i] * period``
        (periodic axes only; None when no axis is periodic).
    kinds : (m,) int8
        How each vertex arrived: 0 initial, 1 Break (circumcenter of a circumball holding
        >= k points), 2 Break (far corner of a cell holding >= k points), 3 Clean.
    order : (m,) int64
        The torus vertex each vertex is (along non-periodic axes one torus vertex can appear
        as several copies); in the plane also the insertion order.
    k, tau, periodic, box, min_size, alpha, beta, period
        The run's parameters and Theorem 6's constants for tau; ``min_size`` is the floor that
        was in effect (at least the engine's resolution: 2^14 grid steps in a box, 2^-20
        radians on the sphere; see ``refine``);
        ``period`` is the box's side along periodic axes and 0 along the others.
    floor_points : (f, d) float64
        Where refinement stopped at the resolution floor ``min_size``: circumcenters of
        circumballs and vertices of cells that still hold >= k points but are smaller than
        ``min_size``. Empty when the guarantee holds everywhere.
    stats : Stats
        What the run did (the same keys in every domain): moves of each kind, counting
        tests, the floor, sizes, timings (seconds).
    torus : Torus
        The triangulation of the whole torus that the engine refined (``certify`` checks it).
    index : PointIndex or None
        The engine's counting kd-tree over P (plane), kept by ``refine`` so that d_{P,k} can
        be evaluated exactly without a second tree (``KnnDistance``, the density estimate)
        and so that a continued run (``start=``) grows it; in space the same, on the sphere
        the engine's trees alone; about 20 bytes per input point. None for a mesh read
        from a file;
        ``dataclasses.replace(mesh, index=None)`` gives a copy without it.
    domain : str
        "plane" or "space" (a box of two or three dimensions, the box above; "box", the
        default, gives the one of the box's dimension) or "sphere" (``refine(...,
        sphere=True)``):
        then ``vertices`` are (longitude, latitude) in degrees, ``xyz`` their unit vectors,
        ``triangles`` the spherical Delaunay triangulation (the convex hull of ``xyz``,
        counter-clockwise seen from outside), and every length (``d_m2``, ``min_size``) a
        great-circle distance: an angle in radians times ``radius``.
    radius : float
        The sphere's radius in the user's length unit (1: lengths are angles in radians;
        6371.0088: kilometres on the Earth). 1 in a box.
    xyz : (m, 3) float64 or None
        On the sphere, the vertices as the unit vectors the engine triangulated (exactly:
        ``vertices`` are them rounded to degrees); None in a box.
    """

    vertices: np.ndarray
    cells: np.ndarray
    offsets: np.ndarray | None
    kinds: np.ndarray
    order: np.ndarray
    k: int | float
    tau: float
    periodic: tuple
    box: tuple
    min_size: float
    floor_points: np.ndarray
    stats: Stats = field(default_factory=Stats)
    torus: Torus | None = None
    index: object = field(default=None, repr=False)
    domain: str = "box"
    radius: float = 1.0
    xyz: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.domain == "box":  # a box: the plane or space, by its dimension
            object.__setattr__(self, "domain", "plane" if len(self.periodic) == 2 else "space")
        elif self.domain not in ("plane", "space", "sphere"):
            raise InputError(f"domain must be 'plane', 'space' or 'sphere', got {self.domain!r}")
        if not isinstance(self.stats, Stats):  # a dictionary (of a file, or of 0.1's keys)
            object.__setattr__(self, "stats", Stats.from_dict(self.stats, self.radius))

    @property
    def alpha(self) -> float:
        return theorem6_constants(self.tau)[0]

    @property
    def beta(self) -> float:
        if self.on_sphere:  # spherical Pythagoras: from the largest circumcap
            return sphere_constants(self.tau, self.stats.largest_circumball / self.radius)[1]
        return theorem6_constants(self.tau)[1]

    @property
    def kind_counts(self) -> dict:
        """How many vertices came by each move (``KIND_NAMES``)."""
        return moves_of(self.kinds)

    @property
    def period(self) -> tuple:
        """Periods in input units, 0 along non-periodic axes: the torus' period, which is the
        box's side rounded to the engine's grid (a relative 2^-51 at most)."""
        d = len(self.periodic)
        sides = (
            self.torus.period
            if self.torus is not None
            else tuple(self.box[a + d] - self.box[a] for a in range(d))
        )
        return tuple(float(sides[a]) if self.periodic[a] else 0.0 for a in range(d))

    @property
    def extent(self) -> tuple:
        """The region the vertices' coordinates span, (lower corner, upper corner): the box
        in the plane and in space; on the sphere, which has no box, longitude and latitude
        (-180, -90, 180, 90)."""
        return SPHERE_EXTENT if self.on_sphere else tuple(self.box)

    @property
    def on_sphere(self) -> bool:
        """Whether this mesh lies on the sphere (``domain == "sphere"``)."""
        return self.domain == "sphere"

    @cached_property
    def _metric(self):
        return BoxMetric(self.box, self.periodic)

    @cached_property
    def _tree(self):
        if self.on_sphere:
            from scipy.spatial import cKDTree

            return cKDTree(self.xyz if self.xyz is not None else unit_vectors(self.vertices))
        return self._metric.tree(self.vertices)

    def d_m2(self, x: ArrayLike) -> np.ndarray:
        """d_{M,2}: the distance to the second-nearest mesh vertex.

        Periodic axes use the torus metric. Guaranteed to lie within [alpha, beta] d_{P,k}
        at every point of the box (above the floor). NaN at non-finite query points and, on
        the sphere, at latitudes beyond +-90 (``validation.answerable``: the rule of every
        query method).

        Parameters
        ----------
        x : array-like (..., d)
            Query points.

        Returns
        -------
        ndarray (...)
        """
        flat, shape = as_queries(x, self.dim)
        out = np.full(len(flat), np.nan)
        ok = answerable(flat, self.on_sphere)
        if not ok.any():
            return out.reshape(shape)
        if self.on_sphere:
            chord = self._tree.query(unit_vectors(flat[ok]), k=2)[0][:, 1]
            out[ok] = chord_to_angle(chord) * self.radius
        else:
            out[ok] = self._tree.query(self._metric.frame(flat[ok]), k=2)[0][:, 1]
        return out.reshape(shape)

    def corners(self) -> np.ndarray:
        """The cells' corners in input units, offsets applied (periodic cells may reach past
        the box across the seam).

        Returns
        -------
        ndarray (t, d + 1, d)
        """
        c = self.vertices[self.cells]
        if self.offsets is not None:
            c = c + self.offsets * np.array(self.period)
        return c

    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A plain planar triangulation for drawing and mesh files (the plane only; in space
        ``io``'s writers place each tetrahedron's corners). Corners that sit across a
        periodic seam become extra copies of their vertex, so every triangle is drawn where it
        is.

        Returns
        -------
        points : ndarray (p, 2)
        triangles : ndarray (t, 3)
        source : ndarray (p,)
            The vertex of ``vertices`` each point copies.
        """
        self._plane_only("flat")
        if self.offsets is None:
            return self.vertices, self.triangles, np.arange(len(self.vertices))
        own = copy_key(np.arange(len(self.vertices), dtype=np.int64), 0, 0)
        corners = copy_key(
            self.triangles.astype(np.int64), self.offsets[..., 0], self.offsets[..., 1]
        )
        keys, inverse = np.unique(np.concatenate([own, corners.ravel()]), return_inverse=True)
        # every vertex first, in its own place, then the copies across the seam
        vertex, sx, sy = copy_parts(keys)
        order = np.argsort((sx != 0) | (sy != 0), kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        vertex, sx, sy = vertex[order], sx[order], sy[order]
        points = self.vertices[vertex] + np.stack([sx, sy], axis=1) * np.array(self.period)
        triangles = rank[inverse[len(own) :]].reshape(-1, 3).astype(np.int32)
        return points, triangles, vertex

    def pieces_in_box(self) -> list[tuple[int, np.ndarray]]:
        """The triangles cut to the box, as the user's coordinates see it: along periodic
        axes a triangle across the seam becomes its pieces on either side (the far one
        shifted back by a period), along non-periodic axes the parts outside the box go;
        what GIS formats want (WGS84 longitudes stay in [-180, 180]). On the sphere, the
        triangles in longitude and latitude (``lonlat_pieces``): cut at the antimeridian,
        and a triangle round a pole split there.

        Returns
        -------
        list of (int, ndarray (q, 2))
            (triangle index, polygon inside the box), by triangle.
        """
        if self.on_sphere:
            return lonlat_pieces(self.xyz, self.triangles)
        self._plane_only("pieces_in_box")
        per = np.array(self.periodic, bool)
        period = np.array(self.period, float)
        rect = (np.array(self.box[:2], float), np.array(self.box[2:], float))
        corners = self.corners()
        out = []
        for sx in (0, -1) if per[0] else (0,):
            for sy in (0, -1) if per[1] else (0,):
                shifted = corners + np.array([sx, sy]) * period
                lo, hi = shifted.min(axis=1), shifted.max(axis=1)
                meets = np.flatnonzero(np.all((hi > rect[0]) & (lo < rect[1]), axis=1))
                poly, _, count = clip_triangles(
                    shifted[meets], np.zeros((len(meets), 3)), *rect[0], *rect[1]
                )
                # shoelace over each polygon's first count corners
                j = np.arange(poly.shape[1])
                nxt = (j + 1) % np.maximum(count, 1)[:, None]
                x, y = poly[..., 0], poly[..., 1]
                cross = x * np.take_along_axis(y, nxt, 1) - y * np.take_along_axis(x, nxt, 1)
                area = np.where(j < count[:, None], cross, 0.0).sum(axis=1)
                for i in np.flatnonzero((count >= 3) & (area != 0)):
                    out.append((int(meets[i]), poly[i, : count[i]].copy()))
        out.sort(key=lambda piece: piece[0])
        return out

    def covering(self, *, sources: bool = False) -> tuple:
        """A plain planar triangulation covering the box (the plane only): the triangles
        plus, along periodic axes, their copies one period back that still meet the box
        (corners only ever reach past the upper side of the box), one index per distinct
        point.

        Parameters
        ----------
        sources : bool
            Also return the triangle each one copies.

        Returns
        -------
        nodes : ndarray (p, 2)
        triangles : ndarray (t, 3)
        sources : ndarray (t,)
            Only with ``sources``.
        """
        self._plane_only("covering")
        per = np.array(self.periodic, bool)
        period = np.array(self.period, float)
        lo, hi = np.array(self.box[:2]), np.array(self.box[2:])
        tri = self.triangles.astype(np.int64)
        off = (
            np.zeros(tri.shape + (2,), np.int64)
            if self.offsets is None
            else self.offsets.astype(np.int64)
        )
        key_parts, source = [], []
        for sx in (0, -1) if per[0] else (0,):
            for sy in (0, -1) if per[1] else (0,):
                o = off + np.array([sx, sy])
                c = self.vertices[tri] + o * period
                meets = np.all((c.max(axis=1) >= lo) & (c.min(axis=1) <= hi), axis=1)
                key_parts.append(copy_key(tri[meets], o[meets][..., 0], o[meets][..., 1]))
                source.append(np.flatnonzero(meets))
        keys = np.concatenate(key_parts)
        unique, inverse = np.unique(keys, return_inverse=True)
        vertex, sx, sy = copy_parts(unique)
        nodes = self.vertices[vertex] + np.stack([sx, sy], axis=1) * period
        if sources:
            return nodes, inverse.reshape(-1, 3), np.concatenate(source)
        return nodes, inverse.reshape(-1, 3)

    def _plane_only(self, what):
        if self.on_sphere:
            raise InputError(
                f"Mesh.{what} is built for meshes in the plane; this one lies on the sphere "
                "(its triangles: .triangles over .xyz; maps: knnrefine.plot)"
            )
        if self.dim != 2:
            raise InputError(
                f"Mesh.{what} is built for meshes in the plane; this one is in {self.dim} "
                "dimensions"
            )

    def __repr__(self):
        if self.on_sphere:
            return (
                f"<Mesh m={len(self.vertices)} triangles={len(self.cells)} k={self.k} "
                f"tau={self.tau:g} sphere radius={self.radius:g}>"
            )
        d = self.dim
        mode = {(True,) * d: "periodic", (False,) * d: "non-periodic"}.get(
            tuple(self.periodic), f"periodic={self.periodic}"
        )
        cells = "triangles" if d == 2 else "tetrahedra"
        return (
            f"<Mesh m={len(self.vertices)} {cells}={len(self.cells)} k={self.k} "
            f"tau={self.tau:g} {mode} box={self.box}>"
        )


def lonlat_pieces(xyz, triangles):
    """The spherical triangles (unit vectors ``xyz``, ``triangles``) as polygons in
    longitude and latitude: [(triangle, polygon (q, 2)), ...]. Corners' longitudes are
    unwrapped about the first corner's, so a triangle across the antimeridian is one
    polygon reaching past +-180, then cut there into its two sides, the far one shifted back
    by 360. A triangle holding a pole is split at it into three, each (pole, a, b) drawn as
    the quadrilateral a, b, (lon b, +-90), (lon a, +-90), where the pole is a line in these
    coordinates. Edges are straight in longitude and latitude (GeoJSON's rule; the
    triangles are small)."""
    from ._metric import lonlat_of

    xyz = np.asarray(xyz, float)
    tri = np.asarray(triangles, np.int64)
    ll = lonlat_of(xyz)
    out = []
    at_pole = np.abs(ll[:, 1]) == 90.0
    for t, (a, b, c) in enumerate(tri):
        corner = [u for u in (a, b, c) if at_pole[u]]
        if corner:  # a corner at a pole: the pole is the edge lat = +-90 of one quadrilateral
            p = corner[0]
            u, v = (b, c) if p == a else (c, a) if p == b else (a, b)
            lon_u = ll[u, 0]
            lon_v = lon_u + _wrap180(ll[v, 0] - lon_u)
            lat = ll[p, 1]
            quad = np.array([[lon_u, ll[u, 1]], [lon_v, ll[v, 1]], [lon_v, lat], [lon_u, lat]])
            out.extend((t, piece) for piece in _cut_at_antimeridian(quad))
            continue
        poles = [
            z for z in (1.0, -1.0)
            if all(_cross_z(xyz[u], xyz[v]) * z > 0 for u, v in ((a, b), (b, c), (c, a)))
        ]  # fmt: skip
        if poles:
            z = poles[0]
            lat = 90.0 * z
            for u, v in ((a, b), (b, c), (c, a)):
                lon_u = ll[u, 0]
                lon_v = lon_u + _wrap180(ll[v, 0] - lon_u)
                quad = np.array([[lon_u, ll[u, 1]], [lon_v, ll[v, 1]], [lon_v, lat], [lon_u, lat]])
                out.extend((t, piece) for piece in _cut_at_antimeridian(quad))
            continue
        corners = ll[[a, b, c]].copy()
        corners[1:, 0] = corners[0, 0] + _wrap180(corners[1:, 0] - corners[0, 0])
        out.extend((t, piece) for piece in _cut_at_antimeridian(corners))
    return out


def _cross_z(u, v):
    return u[0] * v[1] - u[1] * v[0]


def _wrap180(d):
    return (np.asarray(d) + 180.0) % 360.0 - 180.0


def _cut_at_antimeridian(poly):
    """A polygon (lon, lat) whose longitudes may reach past +-180: its parts on either side
    of the antimeridian, each shifted by whole turns into [-180, 180] (degenerate parts
    dropped)."""
    lo, hi = poly[:, 0].min(), poly[:, 0].max()
    if lo >= -180.0 and hi <= 180.0:
        return [poly]
    line = 180.0 if hi > 180.0 else -180.0
    parts = [_distinct(_clip_half(poly, line, below)) for below in (True, False)]
    return [_into_range(p) for p in parts if len(p) >= 3 and abs(_shoelace(p)) > 1e-12]


def _distinct(poly):
    """The polygon without corners repeating the one before (cyclically, to 1e-12 degrees)."""
    if len(poly) == 0:
        return poly
    step = np.abs(poly - np.roll(poly, 1, axis=0)).max(axis=1)
    return poly[step > 1e-12]


def _shoelace(poly):
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _into_range(poly):
    """The polygon shifted by whole turns so that its longitudes lie in [-180, 180]."""
    mid = 0.5 * (poly[:, 0].min() + poly[:, 0].max())
    poly = poly.copy()
    poly[:, 0] -= 360.0 * np.round(mid / 360.0)
    return np.clip(poly, [-180.0, -90.0], [180.0, 90.0])


def _clip_half(poly, line, below):
    """Sutherland-Hodgman: the part of the polygon with lon <= line (below) or >= line."""
    out = []
    n = len(poly)
    for i in range(n):
        p, q = poly[i], poly[(i + 1) % n]
        p_in = p[0] <= line if below else p[0] >= line
        q_in = q[0] <= line if below else q[0] >= line
        if p_in:
            out.append(p)
        if p_in != q_in:
            f = (line - p[0]) / (q[0] - p[0])
            out.append(np.array([line, p[1] + f * (q[1] - p[1])]))
    return np.array(out).reshape(-1, 2)


def copy_key(vertex, sx, sy):
    """One integer for a vertex's copy shifted by (sx, sy) periods, shifts in [-2, 2]: the one
    encoding of a (vertex, shift) pair (``copy_parts`` decodes it; keys sort by vertex)."""
    return (np.asarray(vertex, np.int64) * 5 + (np.asarray(sx) + 2)) * 5 + (np.asarray(sy) + 2)


def copy_parts(key):
    """(vertex, sx, sy) of keys made by ``copy_key``."""
    key = np.asarray(key, np.int64)
    return key // 25, (key // 5) % 5 - 2, key % 5 - 2


def edges(triangles):
    """The edges of a triangle array: (pairs (e, 2), the distinct vertex pairs, smaller index
    first; edge_of (t, 3), the edge opposite each corner)."""
    triangles = np.asarray(triangles)
    a = np.concatenate([triangles[:, 1], triangles[:, 2], triangles[:, 0]]).astype(np.int64)
    b = np.concatenate([triangles[:, 2], triangles[:, 0], triangles[:, 1]]).astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    base = int(hi.max()) + 1 if len(hi) else 1
    keys, inverse = np.unique(lo * base + hi, return_inverse=True)  # sorted as (lo, hi) pairs
    pairs = np.stack([keys // base, keys % base], axis=1).astype(triangles.dtype, copy=False)
    return pairs, inverse.reshape(3, len(triangles)).T


def cell_edges(cells):
    """The distinct vertex pairs (e, 2), smaller index first, joined by an edge of the cells
    (t, d + 1): triangles or tetrahedra."""
    cells = np.asarray(cells, np.int64)
    corners = cells.shape[1]
    a = np.concatenate([cells[:, i] for i in range(corners) for j in range(i + 1, corners)])
    b = np.concatenate([cells[:, j] for i in range(corners) for j in range(i + 1, corners)])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    base = int(hi.max()) + 1 if len(hi) else 1
    keys = np.unique(lo * base + hi)
    return np.stack([keys // base, keys % base], axis=1)


def split_in_four(triangles, n_nodes, known_edges=None):
    """Each triangle into four through its edge midpoints, shared between neighbours.

    Returns (edges (e, 2) sorted vertex pairs, edge_of (t, 3): the edge opposite each corner,
    triangles (4 t, 3) where midpoint j is node ``n_nodes + j``). The caller places the
    midpoints (halfway along each edge, across a periodic seam if need be). known_edges:
    ``edges(triangles)`` when the caller has it already."""
    pairs, edge_of = edges(triangles) if known_edges is None else known_edges
    m = n_nodes + edge_of
    a, b, c = np.asarray(triangles).T
    pieces = np.concatenate(
        [
            np.stack([a, m[:, 2], m[:, 1]], 1),
            np.stack([m[:, 2], b, m[:, 0]], 1),
            np.stack([m[:, 1], m[:, 0], c], 1),
            np.stack([m[:, 0], m[:, 1], m[:, 2]], 1),
        ]
    )
    return pairs, edge_of, pieces


def circumcircles(corners):
    """(centres (t, 2), radii (t,)) of the circumcircles of the triangles (t, 3, 2)."""
    a = corners[:, 0]
    b = corners[:, 1] - a
    c = corners[:, 2] - a
    d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    b2 = (b**2).sum(1)
    c2 = (c**2).sum(1)
    ux = (c[:, 1] * b2 - b[:, 1] * c2) / d
    uy = (b[:, 0] * c2 - c[:, 0] * b2) / d
    return a + np.stack([ux, uy], 1), np.hypot(ux, uy)


def circumspheres(corners):
    """(centres (t, d), radii (t,)) of the circumballs of the simplices (t, d + 1, d): the
    plane's circumcircles, or in space the solution of 2 (p_i - p_0) . u = |p_i - p_0|^2."""
    if corners.shape[-1] == 2:
        return circumcircles(corners)
    a = corners[:, 0]
    edges = corners[:, 1:] - a[:, None, :]
    u = np.linalg.solve(edges, 0.5 * (edges**2).sum(-1)[..., None])[..., 0]
    return a + u, np.sqrt((u**2).sum(-1))


# Dunavant's 7-point rule (degree 5) on the reference triangle: barycentric points, weights
TRIANGLE_RULE_WEIGHTS = np.array([0.225, *[0.132394152788506] * 3, *[0.125939180544827] * 3])
_a, _b = 0.059715871789770, 0.470142064105115
_c, _d = 0.797426985353087, 0.101286507323456
TRIANGLE_RULE_POINTS = np.array(
    [
        [1 / 3, 1 / 3, 1 / 3],
        [_a, _b, _b],
        [_b, _a, _b],
        [_b, _b, _a],
        [_c, _d, _d],
        [_d, _c, _d],
        [_d, _d, _c],
    ]
)


def triangle_areas(corners):
    """Signed areas of the triangles (t, 3, 2): positive when counter-clockwise."""
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def uniform_in_triangles(corners, u, cells=None):
    """Points uniform in triangles from numbers u (s, 2) uniform in the unit square, folded
    onto each triangle along the square's diagonal: corner 0 + u0 (corner 1 - corner 0) +
    u1 (corner 2 - corner 0). ``corners`` (t, 3, d), or a pair (vertices (m, d), triangles
    (t, 3)) whose corners are read where they are; point i lies in triangle ``cells[i]``
    (default: i), in one pass of a kernel (no (s, 3, d) copy of the corners). Returns
    (points (s, d), the folded u)."""
    if isinstance(corners, tuple):
        vertices, triangles = corners
        vertices = np.ascontiguousarray(vertices, np.float64)
        triangles = np.asarray(triangles)
        triangles = np.ascontiguousarray(
            triangles, np.int32 if triangles.dtype == np.int32 else np.int64
        )
    else:  # the corners' rows, three a triangle (no triangles: rows 3 t to 3 t + 2)
        corners = np.ascontiguousarray(corners, np.float64)
        vertices = corners.reshape(-1, corners.shape[-1])
        triangles = np.zeros((0, 3), np.int64)
    u = np.array(u, dtype=np.float64, order="C").reshape(-1, 2)
    cells = np.zeros(0, np.int64) if cells is None else np.ascontiguousarray(cells, np.int64)
    out = np.empty((len(u), vertices.shape[-1]))
    _in_triangles(vertices, triangles, cells, u, out)
    return out, u


@kernel(entry=True, lazy=True, nogil=True)
def _in_triangles(vertices, triangles, cells, u, out):
    """``uniform_in_triangles``' points into ``out``, u folded in place (``cells`` empty:
    point i in triangle i; ``triangles`` empty: triangle t's corners are rows 3 t to 3 t + 2
    of ``vertices``)."""
    listed = triangles.shape[0] > 0
    for i in range(u.shape[0]):
        if u[i, 0] + u[i, 1] > 1.0:
            u[i, 0], u[i, 1] = 1.0 - u[i, 0], 1.0 - u[i, 1]
        u0, u1 = u[i, 0], u[i, 1]
        t = cells[i] if cells.shape[0] else i
        if listed:
            p0, p1, p2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        else:
            p0, p1, p2 = 3 * t, 3 * t + 1, 3 * t + 2
        for a in range(out.shape[1]):
            c0 = vertices[p0, a]
            out[i, a] = c0 + u0 * (vertices[p1, a] - c0) + u1 * (vertices[p2, a] - c0)
