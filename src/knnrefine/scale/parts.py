"""A mesh kept as a folder of parts, one per strip of the box (a slab in space), read part
by part.

``write_partitioned(mesh, path, parts)`` cuts the box into ``parts`` strips across its longest
side, balanced by vertex count, and writes for each an ``.npz`` file: the vertices it owns
(those in its strip), the cells (triangles, tetrahedra in space) it owns (those whose first
corner it owns), a halo of the other vertices within 3 R_T of the circumcentre of some cell
T meeting the strip (R_T its circumradius), and its share of the torus triangulation (the
certificate's evidence). A point x of a cell T has its two nearest vertices within 2 R_T of x
(T's corners are that close: T lies in its circumball), so within 3 R_T of T's circumcentre;
a point of the strip, or of one of the part's own cells, lies in a cell meeting the strip:
so a part answers d_{M,2} exactly there without the rest of the mesh
(``PartitionedMesh.part(j).d_m2``). The argument is the same in any dimension; the files
keep the plane's names (``triangles``: the cells).

Each part also lists the other parts' cells that meet its strip (format 2), so that the kNN
density works part by part (``PartitionedDistance``, ``PartitionedMesh.density``): the piece
holding a point of the strip is among them.

The folder is written under a temporary name and renamed into place with a finished marker
(``_SUCCESS``) written last; ``PartitionedMesh(path)`` refuses a folder without it.
``to_mesh()`` puts the parts back together into the ``Mesh`` they were cut from, array for
array.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from .._domains import part
from .._domains.plane.density import index_values, midpoints, node_guesses
from .._domains.space.density import Index as SpaceIndex
from .._domains.space.density import Pieces as SpacePieces
from .._domains.space.density import grid3, nodes3
from .._engine.raster import rasterise
from .._metric import BoxMetric
from .._validation import (
    answerable,
    as_points,
    as_queries,
    check_inside,
    check_workers,
    random_generator,
    weights_of_run,
)
from ..density.distance import KnnDistance, check_extent, grid_axes, grid_points, grid_shape
from ..density.estimate import KnnDensity
from ..errors import InputError
from ..io import UNREADABLE, unreadable
from ..mesh import Mesh, Torus, circumspheres, split_in_four

FORMAT_VERSION = 2  # 2: each part also lists the others' triangles meeting its strip
FINISHED = "_SUCCESS"
MANIFEST = "manifest.json"


def _axis(box):
    """The box's longest axis (the first of equals)."""
    dim = len(box) // 2
    return int(np.argmax([box[a + dim] - box[a] for a in range(dim)]))


def _owner(coord, cuts):
    """The strip of each coordinate (relative to the box's low side, periodic axes wrapped):
    the last cut at or below it; beyond the box's ends, the end strips."""
    return np.clip(np.searchsorted(cuts, coord, side="right") - 1, 0, len(cuts) - 1)


def write_partitioned(
    mesh: Mesh, path: str | os.PathLike, parts: int, force: bool = False
) -> PartitionedMesh:
    """Write a mesh as a folder of parts (module docstring), atomically (a finished marker
    last).

    Parameters
    ----------
    mesh : Mesh
        In the plane or in space.
    path : str or PathLike
        The folder.
    parts : int
        Strips (slabs in space) across the box's longest axis, one file each.
    force : bool
        Replace an existing folder (the old one goes only once the new one is whole).

    Returns
    -------
    PartitionedMesh
        The folder, read back.
    """
    path = check_output(path, parts, force)
    parent = os.path.dirname(path)
    tmp = tempfile.mkdtemp(dir=parent, prefix=".knnrefine-")
    try:
        manifest = _write_parts(mesh, tmp, int(parts))
        with open(os.path.join(tmp, MANIFEST), "w") as f:
            json.dump(manifest, f)
        open(os.path.join(tmp, FINISHED), "w").close()
        os.chmod(tmp, 0o777 & ~_umask())
        if os.path.exists(path):  # force: the old folder goes only once the new one is whole
            old = tempfile.mkdtemp(dir=parent, prefix=".knnrefine-old-")
            os.replace(path, os.path.join(old, "x"))
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return PartitionedMesh(path)


def check_output(path, parts, force):
    """The absolute path of an output folder that may be written (checked before any work),
    ``parts`` a positive integer (or None)."""
    if parts is not None and (
        isinstance(parts, bool) or not isinstance(parts, (int, np.integer)) or parts < 1
    ):
        raise InputError(f"parts must be a positive integer, got {parts!r}")
    path = os.path.abspath(os.fspath(path))
    if os.path.exists(path) and not force:
        raise InputError(f"{path} exists; use force=True to overwrite it")
    parent = os.path.dirname(path)
    if not os.path.isdir(parent):
        raise InputError(f"{path}: the folder {parent} does not exist")
    return path


def _umask():
    u = os.umask(0)
    os.umask(u)
    return u


def _write_parts(mesh, folder, parts):
    box = np.array(mesh.box, float)
    dim = mesh.dim
    axis = _axis(box)
    metric = BoxMetric(mesh.box, mesh.periodic)
    per = bool(mesh.periodic[axis])
    side = box[axis + dim] - box[axis]
    coord = metric.frame(mesh.vertices)[:, axis]
    cuts = np.quantile(coord, np.arange(parts) / parts) if len(coord) else np.zeros(parts)
    cuts[0] = min(cuts[0], 0.0)
    owner = _owner(coord, cuts)
    ends = np.append(cuts[1:], side)

    # each strip's halo: the vertices within 3 R_T of the circumcentre of a cell T that
    # meets it (T lies in its circumball, and a point of T has its two nearest vertices
    # within 2 R_T: module docstring)
    corners = mesh.corners()
    centres, radius = circumspheres(corners)
    c_axis = corners[..., axis] - box[axis]
    first = _owner(c_axis.min(axis=1) % side if per else c_axis.min(axis=1), cuts)
    last = _owner(c_axis.max(axis=1) % side if per else c_axis.max(axis=1), cuts)
    span = (last - first) % parts + 1 if per else last - first + 1
    span[(c_axis.max(axis=1) - c_axis.min(axis=1)) >= side / 2] = parts
    tree = metric.tree(mesh.vertices)
    reach = metric.frame(centres), 3.0 * radius * (1.0 + 1e-9)
    meets = [[] for _ in range(parts)]
    for q in range(int(span.max()) if len(span) else 0):
        on = np.flatnonzero(span > q)
        strip = (first[on] + q) % parts
        for j in np.unique(strip):
            meets[j].append(on[strip == j])

    cells = mesh.cells
    tri_owner = owner[cells[:, 0]] if len(cells) else np.zeros(0, int)
    torus = mesh.torus
    t_coord = metric.frame(np.asarray(torus.vertices) + np.array(torus.origin))[:, axis]
    t_owner = _owner(t_coord, cuts)
    tt_owner = t_owner[torus.cells[:, 0]]
    no_neighbours = np.zeros((0, dim + 1), np.int64)  # the torus in space keeps none
    f_owner = _owner(metric.frame(mesh.floor_points)[:, axis], cuts)
    d_range = [np.inf, 0.0]
    files = []
    for j in range(parts):
        t = np.concatenate(meets[j]) if meets[j] else np.zeros(0, np.int64)
        found = tree.query_ball_point(reach[0][t], reach[1][t], return_sorted=False)
        near = np.zeros(len(mesh.vertices), bool)
        if len(t):
            near[np.concatenate([np.asarray(f, np.int64) for f in found])] = True
        own = np.flatnonzero(owner == j)
        ids = np.concatenate([own, np.flatnonzero(near & (owner != j))])
        local = np.full(len(mesh.vertices), -1, np.int64)
        local[ids] = np.arange(len(ids))
        tids = np.flatnonzero(tri_owner == j)
        cover = np.setdiff1d(t, tids)  # the others' triangles that meet the strip
        triangles = local[cells[tids]]
        cover_triangles = local[cells[cover]]
        if (triangles < 0).any() or (cover_triangles < 0).any():
            raise AssertionError("a part's cell reaches past its halo")
        no_offsets = np.zeros((0, dim + 1, dim), np.int8)
        arrays = {
            "format": np.array(FORMAT_VERSION),
            "vertex_ids": ids, "owned": np.array(len(own)), "vertices": mesh.vertices[ids],
            "kinds": mesh.kinds[ids], "order": mesh.order[ids],
            "triangle_ids": tids, "triangles": triangles.astype(cells.dtype),
            "offsets": no_offsets if mesh.offsets is None else mesh.offsets[tids],
            "cover_ids": cover, "cover_triangles": cover_triangles.astype(cells.dtype),
            "cover_offsets": no_offsets if mesh.offsets is None else mesh.offsets[cover],
            "floor_points": mesh.floor_points[f_owner == j],
            "floor_ids": np.flatnonzero(f_owner == j),
        }  # fmt: skip
        tv = np.flatnonzero(t_owner == j)
        tt = np.flatnonzero(tt_owner == j)
        arrays.update({
            "torus_vertex_ids": tv, "torus_vertices": torus.vertices[tv],
            "torus_kinds": torus.kinds[tv], "torus_triangle_ids": tt,
            "torus_triangles": torus.cells[tt], "torus_offsets": torus.offsets[tt],
            "torus_neighbours": no_neighbours if torus.neighbours is None else torus.neighbours[tt],
        })  # fmt: skip
        name = f"part-{j:05d}.npz"
        with open(os.path.join(folder, name), "wb") as f:
            np.savez_compressed(f, **arrays)
        part = _part_mesh(mesh, arrays, mesh.offsets is not None)
        if len(part.cells):
            d = part.d_m2(part.corners().mean(axis=1))
            d_range = [min(d_range[0], float(d.min())), max(d_range[1], float(d.max()))]
        strip = [float(cuts[j] + box[axis]), float(ends[j] + box[axis])]
        files.append({"file": name, "strip": strip,
                      "vertices": int(len(own)), "halo_vertices": int(len(ids) - len(own)),
                      "triangles": int(len(tids))})  # fmt: skip
    return {
        "format": FORMAT_VERSION, "k": mesh.k, "tau": mesh.tau,
        "periodic": list(mesh.periodic), "box": list(mesh.box), "min_size": mesh.min_size,
        "axis": axis, "cuts": [float(c) for c in cuts], "parts": files,
        "m": len(mesh.vertices), "triangles": len(cells),
        "torus": {"origin": list(torus.origin), "period": list(torus.period),
                  "m": len(torus.vertices), "triangles": len(torus.cells),
                  "neighbours": torus.neighbours is not None},
        "has_offsets": mesh.offsets is not None, "d_m2_range": d_range,
        "stats": mesh.stats.to_dict(),
    }  # fmt: skip


def _part_mesh(mesh, arrays, has_offsets):
    """A part as a small Mesh (no torus): its vertices with the halo, its own triangles;
    ``mesh``: anything with the run's k, tau, periodic, box and min_size."""
    return Mesh(
        vertices=arrays["vertices"], cells=arrays["triangles"],
        offsets=arrays["offsets"] if has_offsets else None,
        kinds=arrays["kinds"], order=arrays["order"], k=mesh.k, tau=mesh.tau,
        periodic=tuple(mesh.periodic), box=tuple(mesh.box), min_size=mesh.min_size,
        floor_points=arrays["floor_points"], stats={},
    )  # fmt: skip


class PartitionedMesh:
    """A mesh written by ``write_partitioned`` (or ``distributed.refine(..., output=)``),
    read part by part: ``part(j)`` is a small ``Mesh`` exact in its strip; ``d_m2``,
    ``plot``, ``distance`` and ``density`` go part by part; ``to_mesh()`` is the whole
    ``Mesh``.

    Parameters
    ----------
    path : str or PathLike
        The folder.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        """Open a folder written by ``write_partitioned``.

        Parameters
        ----------
        path : str or PathLike

        Raises
        ------
        InputError
            No such folder, an unfinished one, or one written by a newer knnrefine.
        """
        path = os.fspath(path)
        if not os.path.isdir(path):
            raise InputError(f"{path}: no such folder (a partitioned mesh is a folder)")
        if not os.path.exists(os.path.join(path, FINISHED)):
            raise InputError(
                f"{path}: no {FINISHED} marker: the folder was not finished (a run stopped "
                "while writing it); write it again"
            )
        with open(os.path.join(path, MANIFEST)) as f:
            self.manifest = json.load(f)
        if self.manifest["format"] > FORMAT_VERSION:
            raise InputError(f"{path}: written by a newer knnrefine")
        self.path = path
        m = self.manifest
        self.k, self.tau, self.min_size = m["k"], m["tau"], m["min_size"]
        self.periodic, self.box = tuple(m["periodic"]), tuple(m["box"])
        self.stats = m["stats"]
        self._cache: dict = {}

    @property
    def domain(self) -> str:
        """The box domain of its dimension, plane or space (``knnrefine._domains``)."""
        return "plane" if len(self.periodic) == 2 else "space"

    @property
    def extent(self) -> tuple:
        """The region its coordinates span: its box (as ``Mesh.extent``)."""
        return tuple(self.box)

    @property
    def dim(self) -> int:
        """2 in the plane, 3 in space."""
        return len(self.box) // 2

    def _plot_slices(self, axes, points=None, shape=256, title=None):
        import matplotlib.pyplot as plt

        from ..plot import plot_slices, space_figure_size

        if axes is None:
            axes = plt.subplots(1, 3, figsize=space_figure_size())[1]
        axes = list(np.ravel(axes))
        if len(axes) != 3:
            raise InputError(f"a mesh in space is drawn on three Axes, got {len(axes)}")
        m = self.manifest
        title = title or (
            f"mesh in space in {len(self)} parts: m = {m['m']:,} vertices, "
            f"{m['triangles']:,} tetrahedra, k = {self.k}, tau = {self.tau:g}"
        )
        label = "d_M2 (distance to the second-nearest vertex)"
        return list(plot_slices(self.d_m2, self, axes, label, points=points, shape=shape,
                                title=title))  # fmt: skip

    def __len__(self):
        return len(self.manifest["parts"])

    def __repr__(self):
        m = self.manifest
        return (
            f"<PartitionedMesh {self.path!r} parts={len(self)} m={m['m']} k={self.k} "
            f"tau={self.tau:g} periodic={self.periodic} box={self.box}>"
        )

    def _arrays(self, j):
        path = os.path.join(self.path, self.manifest["parts"][j]["file"])
        try:
            with np.load(path, allow_pickle=False) as d:
                return {key: d[key] for key in d.files}
        except UNREADABLE as exc:
            raise unreadable(path, "part (.npz)", exc) from None

    def part(self, j: int) -> Mesh:
        """Part j as a ``Mesh``: its vertices with the halo, its own triangles (d_{M,2} exact
        in its strip and its triangles). The last few parts read are kept.

        Parameters
        ----------
        j : int

        Returns
        -------
        Mesh
        """
        if j not in self._cache:
            if len(self._cache) >= 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[j] = _part_mesh(self, self._arrays(j), self.manifest["has_offsets"])
        return self._cache[j]

    def owner(self, x: np.ndarray) -> np.ndarray:
        """The part whose strip holds each point.

        Parameters
        ----------
        x : ndarray (q, dim)

        Returns
        -------
        ndarray (q,) int
        """
        a = self.manifest["axis"]
        coord = BoxMetric(self.box, self.periodic).frame(x)[:, a]
        return _owner(coord, np.array(self.manifest["cuts"]))

    def d_m2(self, x: ArrayLike) -> np.ndarray:
        """d_{M,2} part by part: equal to the whole mesh's in the box; NaN beyond it along
        non-periodic axes (no part's halo reaches there).

        Parameters
        ----------
        x : array-like (..., dim)

        Returns
        -------
        ndarray (...)
        """
        dim = self.dim
        flat, shape = as_queries(x, dim)
        out = np.full(len(flat), np.nan)
        inside = answerable(flat)
        for a in range(dim):
            if not self.periodic[a]:
                inside &= (flat[:, a] >= self.box[a]) & (flat[:, a] <= self.box[a + dim])
        owner = self.owner(flat[inside])
        rows = np.flatnonzero(inside)
        for j in np.unique(owner):
            at = rows[owner == j]
            out[at] = self.part(int(j)).d_m2(flat[at])
        return out.reshape(shape)

    def plot(self, ax: Any = None, **kwargs) -> Any:
        """In the plane ``plot.plot_mesh`` part by part on one axes, one colour scale for
        all; in space three slices through the box's centre coloured by d_{M,2}, answered
        part by part (``plot.plot_slices``, as ``knnrefine plot`` draws a mesh in space).

        Parameters
        ----------
        ax : matplotlib Axes (plane) or three Axes (space), optional
            Where to draw (default: a new figure).
        **kwargs
            As for ``plot.plot_mesh`` in the plane; in space ``points`` (drawn near each
            slice), ``shape`` (pixels per side) and ``title``.

        Returns
        -------
        matplotlib Axes (plane) or list of three Axes (space)
        """
        from ..plot import plot_mesh

        m = self.manifest
        if self.dim == 3:
            return self._plot_slices(ax, **kwargs)
        title = kwargs.pop("title", None) or (
            f"kNNRefine: k = {self.k}, tau = {self.tau:g}, m = {m['m']:,} in {len(self)} parts; "
            "colour: distance to the second-nearest mesh vertex"
        )
        for j in range(len(self)):
            last = j == len(self) - 1
            ax = plot_mesh(self.part(j), ax=ax, value_range=m["d_m2_range"],
                           show_colour_bar=last, title=title, **kwargs)  # fmt: skip
        assert ax is not None  # drawn on the first part's axes
        return ax

    def distance(
        self,
        points: ArrayLike,
        *,
        weights: ArrayLike | None = None,
        subdivide: bool = True,
        workers: int | None = None,
    ) -> PartitionedDistance:
        """d_{P,k} part by part from the points the mesh was refined from.

        Parameters
        ----------
        points : array-like (n, 2)
        weights : array-like (n,), optional
            The weights of a weighted run.
        subdivide : bool
            As for ``KnnDistance``.
        workers : int, optional
            None or 1: one index over the points in this process; N > 1: asked strip by
            strip in N local processes (``distributed.density`` asks a Dask cluster).

        Returns
        -------
        PartitionedDistance

        Raises
        ------
        InputError
            Points or weights that are not the run's, or a bad ``workers``.
        """
        workers = check_workers(workers)
        if workers == 1:
            return PartitionedDistance.of_index(self, points, weights, subdivide)
        from .tiled import LocalStore

        pts = as_points(points, self.dim)
        store = LocalStore(pts, weights_of_run(self.stats, len(pts), weights), workers)
        try:
            return PartitionedDistance.of_store(self, store, workers, subdivide)
        finally:
            store.close()

    def density(
        self,
        points: ArrayLike,
        *,
        weights: ArrayLike | None = None,
        normalized: bool = True,
        subdivide: bool = True,
        workers: int | None = None,
    ) -> KnnDensity:
        """The kNN density estimate part by part (``KnnDensity``: evaluate, ``grid``,
        ``mass``, ``sample``) from ``distance``'s d_{P,k}.

        Parameters
        ----------
        points, weights, subdivide, workers
            As for ``distance``.
        normalized : bool
            As for ``KnnDensity``.

        Returns
        -------
        KnnDensity

        Raises
        ------
        InputError
            As for ``distance``.
        """
        distance = self.distance(points, weights=weights, subdivide=subdivide, workers=workers)
        return KnnDensity.of_distance(distance, normalized=normalized)

    def to_mesh(self) -> Mesh:
        """The whole mesh again, as written (every array equal).

        Returns
        -------
        Mesh
        """
        m = self.manifest
        t = m["torus"]
        rows = {"": m["m"], "triangle": m["triangles"], "torus_vertex": t["m"],
                "torus_triangle": t["triangles"], "floor": None}  # fmt: skip
        out = {}

        def put(name, ids, values, count):
            if name not in out:
                out[name] = np.zeros((count, *values.shape[1:]), values.dtype)
            out[name][ids] = values

        parts = [self._arrays(j) for j in range(len(self))]
        has_neighbours = t.get("neighbours", t.get("neighbors", True))  # none in space
        floor_count = sum(len(d["floor_ids"]) for d in parts)
        for d in parts:
            own = d["vertex_ids"][: int(d["owned"])]
            for name in ("vertices", "kinds", "order"):
                put(name, own, d[name][: len(own)], rows[""])
            put("triangles", d["triangle_ids"], d["vertex_ids"][d["triangles"]].astype(
                d["triangles"].dtype), rows["triangle"])  # fmt: skip
            if m["has_offsets"]:
                put("offsets", d["triangle_ids"], d["offsets"], rows["triangle"])
            for name in ("vertices", "kinds"):
                put(
                    "torus_" + name, d["torus_vertex_ids"], d["torus_" + name], rows["torus_vertex"]
                )
            for name in ("triangles", "offsets", "neighbours")[: 3 if has_neighbours else 2]:
                key = "torus_" + name if "torus_" + name in d else "torus_neighbors"  # 0.1's
                put("torus_" + name, d["torus_triangle_ids"], d[key], rows["torus_triangle"])
            put("floor_points", d["floor_ids"], d["floor_points"].reshape(-1, self.dim),
                floor_count)  # fmt: skip
        neighbours = out["torus_neighbours"] if has_neighbours else None
        torus = Torus(origin=tuple(t["origin"]), period=tuple(t["period"]),
                      vertices=out["torus_vertices"], cells=out["torus_triangles"],
                      offsets=out["torus_offsets"], kinds=out["torus_kinds"],
                      neighbours=neighbours)  # fmt: skip
        return Mesh(
            vertices=out["vertices"], cells=out["triangles"],
            offsets=out["offsets"] if m["has_offsets"] else None, kinds=out["kinds"],
            order=out["order"], k=self.k, tau=self.tau, periodic=self.periodic, box=self.box,
            min_size=self.min_size, floor_points=out["floor_points"], stats=self.stats,
            torus=torus,
        )  # fmt: skip


class PartitionedDistance:
    """d_{P,k} over a partitioned mesh, part by part, in the plane or in space.

    Each part carries the linear pieces of the cells that meet its strip, exact at their
    nodes and edge midpoints. In the plane (its ``density.linear_pieces``: copies across
    periodic seams included) ``vertex_values(nodes, near)`` and ``midpoint_values(mids, guess, low,
    high)`` answer for all parts' nodes at once, then for all their midpoints; in space
    (space's ``density.Pieces``) ``kth(x)`` answers for all parts' vertices and distinct
    edge midpoints at once, in the frame of the torus (``of_index``: the points in this
    process; ``of_store``: asked strip by strip where they are). A query is answered by its
    strip's part (the piece holding it meets the strip); integrals, grids and samples add up
    each part's own cells (each cell is one part's). So every answer equals
    ``KnnDistance(pm.to_mesh(), points)``'s, up to rounding. Kept here: the values at every
    part's nodes (about 40 bytes per vertex in the plane); a part's pieces are rebuilt from
    its file when it is read."""

    def __init__(self, pmesh, vertex_values, midpoint_values, n, total, subdivide=True, kth=None):
        if pmesh.manifest["format"] < 2:
            raise InputError(
                f"{pmesh.path}: written by an older knnrefine (format "
                f"{pmesh.manifest['format']}), without the triangles each part needs for "
                "d_Pk; write the mesh again (write_partitioned)"
            )
        if total < pmesh.k:
            raise InputError(f"a total of {total:.6g} points but k = {pmesh.k}: d_Pk is infinite")
        self.pmesh, self.k, self.subdivide = pmesh, pmesh.k, bool(subdivide)
        self.n, self.total, self.dim = n, float(total), pmesh.dim
        self.lo = np.array(pmesh.box[: self.dim], float)
        self.hi = np.array(pmesh.box[self.dim :], float)
        self._cache = {}
        t = pmesh.manifest["torus"]
        self.frame = np.array(t["origin"], float), np.array(t["period"], float)
        if self.dim == 3:
            self.values = self._space_values(kth)
            return
        shapes = [self._covering(j) for j in range(len(pmesh))]
        guesses = [node_guesses(nodes, tri) for nodes, tri, _ in shapes]
        nodes = np.concatenate([s[0] for s in shapes])
        values = vertex_values(nodes, np.concatenate([g[3] for g in guesses]))
        values = np.split(values, np.cumsum([len(s[0]) for s in shapes])[:-1])
        if self.subdivide:
            mid = [
                midpoints(s[0], g[0], g[2], v)
                for s, g, v in zip(shapes, guesses, values, strict=True)
            ]
            found = midpoint_values(*(np.concatenate([m[i] for m in mid]) for i in range(4)))
            found = np.split(found, np.cumsum([len(m[0]) for m in mid])[:-1])
            values = [np.concatenate(vf) for vf in zip(values, found, strict=True)]
        self.values = values

    def _with_cover(self, j):
        """(part j's own cells and the others' meeting its strip as a Mesh, the mask of its
        own cells)."""
        arrays = self.pmesh._arrays(j)
        own = len(arrays["triangles"])
        arrays["triangles"] = np.concatenate([arrays["triangles"], arrays["cover_triangles"]])
        arrays["offsets"] = np.concatenate([arrays["offsets"], arrays["cover_offsets"]])
        mesh = _part_mesh(self.pmesh, arrays, self.pmesh.manifest["has_offsets"])
        return mesh, np.arange(len(mesh.cells)) < own

    def _space_values(self, kth):
        """Exact d_{P,k} where each part's pieces need it (``space.nodes3``), asked at once."""
        origin, period = self.frame
        metric = BoxMetric((*origin, *(origin + period)), self.pmesh.periodic)
        asked = [
            nodes3(self._with_cover(j)[0], metric, period, self.subdivide)[3]
            for j in range(len(self.pmesh))
        ]
        found = kth(np.concatenate(asked)) if asked else np.zeros(0)
        return np.split(found, np.cumsum([len(a) for a in asked])[:-1])

    @classmethod
    def of_index(cls, pmesh, points, weights=None, subdivide=True):
        """From the points (and the weights of a weighted run) in this process: one
        counting index, as ``KnnDistance``."""
        from ..certify import check_source

        pts = as_points(points, pmesh.dim)
        weights = weights_of_run(pmesh.stats, len(pts), weights)
        total = len(pts) if weights is None else float(weights.sum())
        check_source(pmesh.stats, len(pts), None if weights is None else total)
        if pmesh.dim == 3:  # a periodic kd-tree in the frame of the torus
            check_inside(pts, pmesh.box, pmesh.periodic, warn=False)
            t = pmesh.manifest["torus"]
            tree = SpaceIndex(pmesh, pts, weights, frame=(t["origin"], t["period"]))
            return cls(pmesh, None, None, len(pts), total, subdivide, kth=tree.kth_local)
        index = part(pmesh.domain, "density").index_of(pmesh, pts, weights)
        return cls(pmesh, *index_values(index, pmesh.k), len(pts), total, subdivide)

    @classmethod
    def of_store(cls, pmesh, store, tiles, subdivide=True):
        """From points that stay in a store (``scale.tiled.LocalStore`` or
        ``distributed.DaskStore``), asked in ``tiles`` strips where they are
        (``scale.checks.StripQuestions``; the pads are guesses, the strips answer exactly)."""
        from ..certify import check_source
        from .checks import StripQuestions

        check_source(pmesh.stats, store.n, store.weight)
        t = pmesh.manifest["torus"]
        questions = StripQuestions(store, t["origin"], t["period"], pmesh.k, tiles)
        frame = questions.input_frame

        def vertex_values(nodes, near):
            pad = float(np.quantile(4.0 * near, 0.99)) if len(near) else 0.0
            return questions.d_pk(frame(nodes), pad)

        def midpoint_values(mids, guess, low, high):
            pad = float(np.quantile(high, 0.999)) if len(high) else 0.0
            return questions.d_pk(frame(mids), pad)

        def kth(x):  # in space, at torus-frame points; the pad a guess from their spacing
            near = cKDTree(x).query(x, k=2)[0][:, 1] if len(x) > 1 else np.ones(len(x))
            return questions.d_pk(x, float(np.quantile(8.0 * near, 0.99)) if len(x) else 0.0)

        total = store.n if store.weight is None else store.weight
        self = cls(pmesh, vertex_values, midpoint_values, store.n, total, subdivide, kth)
        self.passes = questions.passes
        return self

    def _covering(self, j):
        """(nodes, triangles, mine): the covering (``Mesh.covering``) of part j's triangles
        and the others' meeting its strip; ``mine`` marks the copies of its own."""
        part, mine = self._with_cover(j)
        nodes, triangles, source = part.covering(sources=True)
        return nodes, triangles, mine[source]

    def part(self, j):
        """Part j's d_{P,k}: a ``KnnDistance`` over its own pieces, locating points in the
        pieces of every triangle meeting its strip."""

        if j not in self._cache:
            if len(self._cache) >= 8:
                self._cache.pop(next(iter(self._cache)))
            if self.dim == 3:
                mesh, mine = self._with_cover(j)
                values = self.values[j]

                def known(asked):  # what _space_values found, asked in the same order
                    assert len(asked) == len(values), "a part's nodes changed since asked"
                    return values

                pieces = SpacePieces(mesh, known, self.subdivide, frame=self.frame)
                self._cache[j] = KnnDistance.of_linear_pieces(
                    self.pmesh, self.n, self.total, pieces.subset(mine)
                )
                return self._cache[j]
            nodes, triangles, mine = self._covering(j)
            values = self.values[j]
            if self.subdivide:
                pairs, edge_of, pieces = split_in_four(triangles, len(nodes))
                nodes = np.concatenate([nodes, 0.5 * (nodes[pairs[:, 0]] + nodes[pairs[:, 1]])])
                triangles, mine = pieces, np.tile(mine, 4)
            self._cache[j] = KnnDistance.of_pieces(
                self.pmesh, self.n, self.total, nodes, triangles[mine], values, located=triangles
            )
        return self._cache[j]

    def __call__(self, x):
        """d_{P,k} at the query points (..., dim), each in its strip's part: NaN beyond the
        box along non-periodic axes."""
        flat, shape = as_queries(x, self.dim)
        out = np.full(len(flat), np.nan)
        rows = np.flatnonzero(answerable(flat))
        owner = self.pmesh.owner(flat[rows])
        for j in np.unique(owner):
            at = rows[owner == j]
            out[at] = self.part(int(j))(flat[at])
        return out.reshape(shape)

    def grid(self, shape=(512, 512), extent=None):
        """(xs, ys, values) as ``KnnDistance.grid``: every part's own pieces drawn into one
        grid; in space (xs, ys, zs, values), a slice at a time, each point by its part; over
        ``extent`` (any region, as ``KnnDistance.grid``'s) each centre by its part."""
        if extent is not None:
            full = grid_shape(shape, self.dim)
            axes = grid_axes(check_extent(extent, self.dim), full)
            return (*axes, self(grid_points(axes)).reshape(full))
        if self.dim == 3:
            return grid3(self, self.lo, self.hi, grid_shape(shape, 3))
        ny, nx = grid_shape(shape)
        dx, dy = (self.hi - self.lo) / (nx, ny)
        xs = self.lo[0] + (np.arange(nx) + 0.5) * dx
        ys = self.lo[1] + (np.arange(ny) + 0.5) * dy
        out = np.full((ny, nx), np.nan)
        px, py = (bool(p) for p in self.pmesh.periodic)
        for j in range(len(self.pmesh)):
            p = self.part(j)
            rasterise(p.nodes, p.triangles, p.values, *self.lo, dx, dy, px, py, out, False)
        missed = np.isnan(out)
        if missed.any():
            jj, ii = np.nonzero(missed)
            out[jj, ii] = self(np.column_stack([xs[ii], ys[jj]]))
        return xs, ys, out

    def integrate(self, func, region=None):
        """``KnnDistance.integrate``: the parts' integrals over their own pieces, added."""
        return float(sum(self.part(j).integrate(func, region) for j in range(len(self.pmesh))))

    def sample_pieces(self, n: int, random_state: Any = None) -> np.ndarray:
        """n points from the density proportional to 1 / d^dim over the box: each part's
        share drawn by its exact mass, then from its own pieces."""
        rng = random_generator(random_state)
        parts = [self.part(j) for j in range(len(self.pmesh))]
        dim = self.dim
        mass = np.array([p.integrate(lambda d: 1.0 / d**dim) for p in parts])
        counts = rng.multinomial(int(n), mass / mass.sum())
        drawn = [p.sample_pieces(int(c), rng) for p, c in zip(parts, counts, strict=True)]
        return np.concatenate(drawn)[rng.permutation(int(n))]
