"""What the plane's and space's certificates share: that the points are the run's own
(``check_source``), Lemma 2's precondition on the initial vertices (``check_precondition``) and
finding rows of integers in a table (``find_rows``), and that the points given to certify are
the mesh's (``checked_points``). Weighted counts from kd-trees are
``metric``'s (``held_in_balls``, ``cell_tally``, ``weighted_kth``)."""

import math
from collections import namedtuple
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .._engine.jit import kernel
from .._engine.threads import in_chunks
from .._validation import as_points, check_inside, check_made_from, weights_of_run
from ..errors import InputError
from ..mesh import theorem6_constants
from ._rows import as_index, as_offsets, row_classes
from ._tree import (
    Tree,
    edge_at,
    edge_shifts,
    incidence,
    neighbour_lists,
    point2,
    spatial_order,
    walk_nearest,
)
from .certificate import floor_sites, to_input
from .steps import Cells, Probes


def check_source(stats, n, weight):
    """``n`` points of total ``weight`` (None: unweighted) are as many as the run with these
    stats was refined from, else InputError."""
    made_from, total = stats.get("n"), stats.get("weight")
    if made_from is not None and int(made_from) != n:
        raise InputError(
            f"the mesh was made from {int(made_from):,} points but the source holds "
            f"{n:,}: use the points it was refined from"
        )
    if (total is None) != (weight is None) or (
        total is not None and not np.isclose(weight, total, rtol=1e-9, atol=0)
    ):
        raise InputError(
            f"the mesh was refined with total weight {total} but the source's is "
            f"{weight}: give the weights it was refined with (or none)"
        )


def checked_points(mesh, points, weights=None):
    """A mesh is certified against the points it was made from: as many as it records, inside
    its box along non-periodic axes, with weights exactly when it was refined with weights
    (of the total it records). Anything else is an input error, not a failed certificate.
    Returns (the points (n, d) as float64, the weights as float64 or None): a box domain's
    ``certify.checked_points``."""
    pts = as_points(points, mesh.dim)
    check_made_from(mesh.stats, len(pts), "certify a mesh against")
    weights = weights_of_run(mesh.stats, len(pts), weights)
    dim = mesh.dim
    for a in range(dim):
        if mesh.periodic[a]:
            continue
        lo, hi = mesh.box[a], mesh.box[a + dim]
        out = (pts[:, a] < lo) | (pts[:, a] > hi)
        if out.any():
            raise InputError(
                f"{int(out.sum()):,} of the points lie outside the mesh's box along "
                f"{'xyz'[a]} ([{lo:g}, {hi:g}]), the first at index {int(np.argmax(out))}: these "
                "are not the points the mesh was refined from"
            )
    check_inside(pts, mesh.box, mesh.periodic, warn=False)  # periodic positions not lost
    return pts, weights


def check_precondition(initial, torus, k, tau, period=None, spacing=None):
    """Lemma 2's base case, checked here independently of the engine: can the initial vertices
    be ordered so that each u has d_Pk(u) <= (K - 1) lambda_u, lambda_u its distance to the
    nearest earlier one (K = max(2 tau / (tau - 2), 3))? Peel: a vertex whose disk of radius
    (K - 1) x (distance to the nearest other remaining vertex) holds k points can go last.
    ``torus.held(centres, radii)`` counts the points; ``spacing(vertices)`` gives each
    vertex's distance to its nearest other one (default: on the torus of ``period``).
    Returns (ok, note)."""
    if spacing is None:

        def spacing(vertices):
            return cKDTree(vertices, boxsize=period).query(vertices, k=2)[0][:, 1]

    factor = max(2.0 * tau / (tau - 2.0), 3.0) - 1.0
    remaining = np.asarray(initial, float)
    if torus.total < k:
        return False, "n < k"
    rounds = 0
    while len(remaining) > 1:
        lam = spacing(remaining)
        ok = torus.held(remaining, factor * lam) >= k
        if not ok.any():
            return False, f"{len(remaining)} initial vertices have d_Pk > {factor:.3g} lambda"
        remaining = remaining[~ok]
        rounds += 1
    return True, f"{len(initial)} vertices ordered in {rounds} round{'s' if rounds != 1 else ''}"


def find_rows(table, rows):
    """Index of each of ``rows`` (rows of integers, as wide as ``table``'s, their first
    columns >= 0: vertex indices) in ``table``, -1 if absent: rows matched by
    ``_rows.row_classes``, grouped by their first column."""
    if len(rows) == 0 or len(table) == 0:
        return np.full(len(rows), -1, np.int64)
    both = as_index(np.concatenate([table, rows]))  # (int32 where both are: half the rows)
    group = both[:, 0]
    if group.min() < 0:
        group = group - group.min()
    label = row_classes(both, group, int(group.max()) + 1)[len(table) :]
    return np.where(label < len(table), label, -1)


def repeated_rows(x):
    """How many rows of the float array ``x`` (n, d) repeat an earlier one exactly (their
    bits compared, grouped by a hash of them)."""
    if len(x) < 2:
        return 0
    bits = np.ascontiguousarray(x, np.float64).view(np.int64)
    mixed = np.zeros(len(x), np.uint64)
    for a in range(bits.shape[1]):
        mixed = (mixed ^ bits[:, a].astype(np.uint64)) * np.uint64(0x9E3779B97F4A7C15)
    group = (mixed % np.uint64(len(x))).astype(np.int64)
    label = row_classes(bits, group, len(x))
    return int((label != np.arange(len(x))).sum())


def check_cells_tile(mesh):
    """Problems (a list of strings) that stop the cells the user received (``mesh.cells``
    with ``mesh.offsets``, over ``mesh.vertices``) from tiling the mesh's domain exactly, in
    any dimension: every cell listed once, every facet shared by at most two cells, and a
    facet on one cell only allowed where it cannot bound a hole, outside the open box
    (along a non-periodic axis all its corners at or beyond one side). On a torus no facet
    is on one cell only. Distinct cells of one triangulation (the caller checks that each is
    a cell of the certified torus mesh) whose boundary misses the open box cover the box or
    none of it; a corner inside the box (or a cell holding its centre) rules out none.

    Exact: integer keys, and comparisons of the returned coordinates as given."""
    broken = cell_array_problem(mesh)
    if broken:
        return [broken]
    v = np.asarray(mesh.vertices, float)
    cells = as_index(mesh.cells)
    dim = v.shape[1]
    nc = dim + 1
    per = np.array(mesh.periodic, bool)
    period = np.where(per, np.asarray(mesh.box[dim:], float) - np.asarray(mesh.box[:dim]), 0.0)
    off = np.zeros(cells.shape + (dim,), np.int8)
    if mesh.offsets is not None:  # offsets along non-periodic axes mean nothing
        off = as_offsets(np.where(per, np.asarray(mesh.offsets), 0))
    problems = []
    # a cell, and each of its facets: its corners' codes (vertex and offset relative to the
    # least, in one integer: CODE_BASE values per axis) sorted, compared with the others
    # at its least vertex (``_tile_classes``)
    t = len(cells)
    wide = off.max(axis=1).astype(np.int16) - off.min(axis=1)  # (int8's ends: 255 apart)
    spread = int((wide >= CODE_BASE).any(axis=1).sum())
    del wide
    if spread:
        return [f"{spread} cells span more than {CODE_BASE - 1} periods"]
    m = len(v)
    first, incident = incidence(cells, m)
    widest = nc * int(np.diff(first).max(initial=0))
    alone = np.zeros(nc * t, bool)  # facet i of cell c at i * t + c: on one cell only
    counted = in_chunks(
        lambda a, b: _tile_classes(cells, off, first, incident, widest, CODE_BASE, alone, a, b),
        m, least=4096,
    )  # fmt: skip
    repeats = sum(r for r, _ in counted)
    many = sum(f for _, f in counted)
    if repeats:
        problems.append(f"{repeats} cells are listed more than once")
    if many:
        problems.append(f"{many} facets are shared by more than two cells")
    single = np.flatnonzero(alone)  # flat index: facet i of cell c at i * t + c
    if len(single):
        cell, i = single % t, single // t
        other = np.array([[j for j in range(nc) if j != ii] for ii in range(nc)])[i]
        corners = v[cells[cell[:, None], other]] + off[cell[:, None], other] * period
        lo, hi = np.asarray(mesh.box[:dim], float), np.asarray(mesh.box[dim:], float)
        outside = np.zeros(len(single), bool)
        for a in np.flatnonzero(~per):
            outside |= (corners[:, :, a] <= lo[a]).all(axis=1)
            outside |= (corners[:, :, a] >= hi[a]).all(axis=1)
        if not outside.all():
            problems.append(
                f"{int((~outside).sum())} facets inside the box bound only one cell: the "
                "cells leave a hole"
            )
    if not per.all() and not _cells_meet_the_box(v, cells, off, period, per, mesh.box):
        problems.append("no cell lies in the box")
    return problems


CODE_BASE = 16  # values of a corner's offset (relative to the least) per axis in its code


@kernel(inline="always", cache=False)
def _facet_codes(cells, off, q, skip, base, out):
    """out[:c']: the codes of cell q's corners other than ``skip`` (-1: none), each
    vertex * base^d + its offset relative to the least of them (a digit an axis), sorted;
    returns c'."""
    c, d = cells.shape[1], off.shape[2]
    n = 0
    for i in range(c):
        if i == skip:
            continue
        code = cells[q, i]
        for a in range(d):
            low = off[q, i, a]
            for j in range(c):
                if j != skip:
                    low = min(low, off[q, j, a])
            code = code * base + (off[q, i, a] - low)
        j = n - 1
        while j >= 0 and out[j] > code:
            out[j + 1] = out[j]
            j -= 1
        out[j + 1] = code
        n += 1
    return n


@kernel(entry=True, lazy=True, nogil=True)
def _tile_classes(cells, off, first, incident, widest, base, alone, start, end):
    """(cells equal to an earlier one, classes of more than two equal facets) among those
    whose least vertex is in [start, end); alone[i t + c] for facet i of cell c where no
    other equals it. A vertex's cells and facets (each once: from its first corner at the
    vertex) are gathered from ``incident`` (``_tree.incidence``), hashed, ordered by hash
    (insertion), and compared in full within a run of equal hashes."""
    c = cells.shape[1]
    t = cells.shape[0]
    keys = np.empty((max(widest, 1), c), np.int64)
    flat = np.empty(max(widest, 1), np.int64)
    hashes = np.empty(max(widest, 1), np.int64)
    order = np.empty(max(widest, 1), np.int64)
    codes = np.empty(c, np.int64)
    repeats = 0
    many = 0
    for v in range(start, end):
        for facets in (False, True):
            n = 0
            for r in range(first[v], first[v + 1]):
                q = incident[r] // c
                x = incident[r] - q * c
                for i in range(c if facets else 1):
                    skip = i if facets else -1
                    if skip == x:
                        continue
                    # read once, from its first corner at v, where v is its least vertex
                    once = True
                    for j in range(c):
                        if j != skip and (cells[q, j] < v or (j < x and cells[q, j] == v)):
                            once = False
                    if not once:
                        continue
                    w = _facet_codes(cells, off, q, skip, base, codes)
                    h = 0
                    for j in range(w):
                        keys[n, j] = codes[j]
                        h = h * 1000003 + codes[j]
                    hashes[n] = h
                    flat[n] = i * t + q
                    n += 1
            for y in range(n):  # (insertion: a few dozen, no array made)
                h = hashes[y]
                z = y - 1
                while z >= 0 and hashes[order[z]] > h:
                    order[z + 1] = order[z]
                    z -= 1
                order[z + 1] = y
            a = 0
            while a < n:
                b = a + 1
                while b < n and hashes[order[b]] == hashes[order[a]]:
                    b += 1
                for y in range(a, b):
                    s = order[y]
                    size = 0
                    least = flat[s]
                    for z in range(a, b):
                        u = order[z]
                        same = True
                        for j in range(c - 1 if facets else c):
                            if keys[u, j] != keys[s, j]:
                                same = False
                                break
                        if same:
                            size += 1
                            least = min(least, flat[u])
                    if not facets:
                        repeats += least != flat[s]
                    elif size == 1:
                        alone[flat[s]] = True
                    elif size > 2 and least == flat[s]:
                        many += 1
                a = b
    return repeats, many


def cell_array_problem(mesh):
    """What stops ``mesh.cells`` and ``mesh.offsets`` from being read at all as cells over
    ``mesh.vertices`` (a wrong shape, a vertex that does not exist, no cells), or None."""
    v = np.asarray(mesh.vertices)
    cells = np.asarray(mesh.cells)
    if v.ndim != 2 or v.shape[1] not in (2, 3):
        return f"vertices have shape {v.shape}, not (m, 2) or (m, 3)"
    nc = v.shape[1] + 1
    if cells.ndim != 2 or cells.shape[1] != nc or not np.issubdtype(cells.dtype, np.integer):
        return f"cells are {cells.dtype} of shape {cells.shape}, not integers (t, {nc})"
    if len(cells) == 0:
        return "the mesh has no cells"
    if cells.min() < 0 or cells.max() >= len(v):
        return "a cell names a vertex that does not exist"
    if mesh.offsets is not None and np.shape(mesh.offsets) != cells.shape + (v.shape[1],):
        return f"offsets have shape {np.shape(mesh.offsets)}, not {cells.shape + (v.shape[1],)}"
    return None


def torus_array_problem(torus):
    """What stops a torus' arrays from being read at all by certify's kernels (cells naming
    a vertex that does not exist, offsets or neighbours of the wrong shape, neighbours
    naming a cell that does not exist), or None. Whether they form a triangulation is
    checked later, exactly."""
    v = np.asarray(torus.vertices)
    cells = np.asarray(torus.cells)
    if v.ndim != 2 or v.shape[1] not in (2, 3):
        return f"its vertices have shape {v.shape}, not (m, 2) or (m, 3)"
    nc = v.shape[1] + 1
    if cells.ndim != 2 or cells.shape[1] != nc or not np.isfinite(cells).all():
        return f"its cells have shape {cells.shape}, not (t, {nc})"
    if len(cells) and (cells.min() < 0 or cells.max() >= len(v)):
        return (f"a cell names vertex {int(cells.min()) if cells.min() < 0 else int(cells.max())}"
                f" of {len(v)}")  # fmt: skip
    off = np.asarray(torus.offsets)
    want = cells.shape + (v.shape[1],)
    if off.shape != want or not np.isfinite(off).all():
        return f"its offsets have shape {off.shape}, not {want}"
    nb = torus.neighbours
    if nb is not None:
        nb = np.asarray(nb)
        if nb.shape != cells.shape or not np.isfinite(nb).all():
            return f"its neighbours have shape {nb.shape}, not {cells.shape}"
        if len(nb) and (nb.min() < 0 or nb.max() >= len(cells)):
            return "a neighbour link names a cell that does not exist"
    return None


def _cells_meet_the_box(v, cells, off, period, per, box):
    """Whether some cell meets the open box: a corner strictly inside it along the
    non-periodic axes, or (where no vertex is inside, a box smaller than its cells) a cell
    that holds the box's centre (barycentric coordinates, to rounding)."""
    dim = v.shape[1]
    lo, hi = np.asarray(box[:dim], float), np.asarray(box[dim:], float)
    free = ~per
    used = np.zeros(len(v), bool)
    used[cells.ravel()] = True
    inside = ((v[used] > lo) & (v[used] < hi) | per).all(axis=1)
    if inside.any():
        return True
    corners = v[cells] + off * period
    centre = 0.5 * (lo + hi)
    # along periodic axes the centre moved next to each cell's first corner
    x = np.where(per, centre + np.round((corners[:, 0] - centre) / np.where(per, period, 1.0))
                 * period, centre)  # fmt: skip
    near = ((corners.min(axis=1) <= x) & (corners.max(axis=1) >= x) | ~free).all(axis=1)
    if not near.any():
        return False
    c, x = corners[near], x[near]
    edges = np.transpose(c[:, 1:] - c[:, :1], (0, 2, 1))  # (t, dim, dim): columns the edges
    try:
        lam = np.linalg.solve(edges, (x - c[:, 0])[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return False
    bary = np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)
    return bool((bary >= -1e-9).all(axis=1).any())


class TorusGeometry:
    """What the plane's and space's ``Geometry`` share: the mesh's torus (its vertices
    relative to the origin, a periodic kd-tree over them), lengths in input units, the
    circumballs counted by the points, Lemma 2's precondition on the initial vertices,
    Theorem 6's constants, the floor's sites and positions back in input coordinates."""

    def __init__(self, mesh, workers):
        broken = torus_array_problem(mesh.torus)
        if broken:  # certify's kernels index by these arrays: refused before any is read
            raise InputError(f"the mesh's torus cannot be checked: {broken}; it was altered "
                             "after knnrefine.refine made it (refine again)")  # fmt: skip
        self.mesh, self.workers = mesh, workers
        self.floor = mesh.min_size
        self.origin = np.asarray(mesh.torus.origin, float)
        self.period = np.asarray(mesh.torus.period, float)
        self.vertices = np.asarray(mesh.torus.vertices, float)
        self.pk_period = self.period  # d_{P,k}'s metric: the torus' (space: the box's own)
        self._cells = None
        self._d_m2 = None
        dim = self.vertices.shape[1]
        self.lo = np.array(mesh.box[:dim]) - self.origin
        self.hi = np.array(mesh.box[dim:]) - self.origin
        self.no_position = (float("nan"),) * dim

    def vertex_d_m2(self):
        """d_{M,2} at each vertex: its distance to its nearest other vertex, a Delaunay
        neighbour (the triangulation is checked first; where it failed, the verdict has)."""
        if self._d_m2 is None:
            self._d_m2 = nearest_neighbour(self.cells(None))
        return self._d_m2

    def cells(self, tri):
        """The Voronoi cells of the torus' vertices: each one's neighbours across the
        cells' edges and the periods between them (their outradii from ``tri``; worked
        out once)."""
        if self._cells is not None:
            if tri is None:
                return self._cells
            walkable = not tri.problems and len(self.vertices) >= 4
            return self._cells._replace(outradii=tri.outradii, walkable=walkable)
        torus = self.mesh.torus
        m = len(self.vertices)
        first, nb, nshift = neighbour_lists(torus.cells, torus.offsets, m, self.workers)
        self._cells = Cells(self.vertices, first, nshift, None, 2e-12, 0.0, nb, self.period)
        return self.cells(tri)

    def release(self):
        """Drop the Voronoi cells and the vertices' tree (``steps.Geometry.release``)."""
        self._cells = None
        self.__dict__.pop("vertex_tree", None)

    @cached_property
    def vertex_tree(self):
        """A periodic kd-tree over the torus' vertices (built only where asked: d_{M,2}
        is walked on a verified triangulation)."""
        return Tree(self.vertices, None, self.period, self.workers)

    def torus_d_m2(self, x, tri):
        """d_{M,2} at x on the torus from its vertices (``walked_d_m2``)."""
        return walked_d_m2(self.cells(None), x, self.period, self.workers, tri,
                           lambda: self.vertex_tree)  # fmt: skip

    def held(self, points, tri, stop=np.inf):
        return points.held(tri.centres, tri.radii, stop)

    def separation(self, x, rows, refs):
        """Distances from x[rows] to x[refs] (refs (r, w); NaN where -1) in d_{P,k}'s
        metric (``pk_period``: the torus', or the box's own: 0 on straight axes)."""
        return separations(x, rows, refs, self.workers, self.pk_period)

    def precondition(self, points, k, tau):
        initial = self.vertices[np.asarray(self.mesh.torus.kinds) == 0]
        return check_precondition(initial, points, k, tau, self.period)

    def constants(self, tri):
        return theorem6_constants(self.mesh.tau)

    def floor_sites(self, centres, vertices):
        return floor_sites(np.concatenate([centres, vertices]),
                           10.0 * max(self.mesh.min_size, 1e-300), self.period, self.origin,
                           self.mesh)  # fmt: skip

    def to_input(self, x):
        return to_input(x, self.origin, self.mesh)


def separations(x, rows, refs, workers, period=None):
    """Distances from x[rows] to x[refs] (refs (r, w); NaN where -1) in d_{P,k}'s metric:
    with ``period`` (per axis), straight lines, each axis taken the nearer way round where
    its period is > 0 (the torus', the box's); without, angles between unit vectors (the
    sphere's). ``_separations``, on every core (``workers``: None or -1)."""
    x = np.ascontiguousarray(x, np.float64)
    rows = np.ascontiguousarray(rows, np.int64)
    refs = np.ascontiguousarray(refs, np.int64).reshape(len(rows), -1)
    angles = period is None
    p = np.zeros(x.shape[1]) if angles else np.ascontiguousarray(period, np.float64)
    out = np.empty(refs.shape)
    in_chunks(lambda a, b: _separations(x, rows, refs, p, angles, out, a, b), len(rows),
              threads=workers, least=8192)  # fmt: skip
    return out


@kernel(entry=True, lazy=True, nogil=True)
def _separations(x, rows, refs, period, angles, out, start, end):
    """out[r, c] for r in [start, end): from x[rows[r]] to x[refs[r, c]] (NaN where
    refs[r, c] < 0), the angle atan2(|a x b|, a . b) (accurate at every angle) where
    ``angles``, else the distance, each axis's difference less the nearest whole number
    of periods where its period is > 0."""
    d = x.shape[1]
    for r in range(start, end):
        i = rows[r]
        for c in range(refs.shape[1]):
            j = refs[r, c]
            if j < 0:
                out[r, c] = np.nan
            elif angles:
                c0 = x[i, 1] * x[j, 2] - x[i, 2] * x[j, 1]
                c1 = x[i, 2] * x[j, 0] - x[i, 0] * x[j, 2]
                c2 = x[i, 0] * x[j, 1] - x[i, 1] * x[j, 0]
                dot = x[i, 0] * x[j, 0] + x[i, 1] * x[j, 1] + x[i, 2] * x[j, 2]
                out[r, c] = math.atan2(math.sqrt(c0 * c0 + c1 * c1 + c2 * c2), dot)
            else:
                s = 0.0
                for a in range(d):
                    g = x[i, a] - x[j, a]
                    if period[a] > 0.0:
                        g -= period[a] * np.rint(g / period[a])
                    s += g * g
                out[r, c] = math.sqrt(s)


def walked_d_m2(cells, x, period, workers, tri, tree):
    """d_{M,2} at each x from a Delaunay triangulation's ``cells`` (sites, neighbour lists
    and edge vectors; ``period`` per axis, 0 where none), where ``tri`` verified it
    (``walked``). ``tree()`` (a kd-tree over the sites, built only when called) answers
    where the triangulation failed its check or a walk did not settle."""
    if tri.problems or len(cells.sites) < 4:
        return tree().kth(x, 2)
    out, _ = walked(cells, x, period, workers, sites=False)
    lost = np.isnan(out)
    if lost.any():
        out[lost] = tree().kth(x[lost], 2)
    return out


def walked(cells, x, period, workers, sites=True):
    """(d_{M,2} at each x, x's nearest site or None where ``sites`` is False) from a
    verified Delaunay triangulation's ``cells``, on every core: the walk to x's nearest
    site, from the nearest of the query before along a Morton curve, moves to any nearer
    neighbour until none is (a Delaunay vertex with no nearer neighbour is the nearest),
    and the second nearest is the nearest of that site's neighbours. NaN and -1 where a
    walk did not settle. The queries are walked WALK at a time along the curve, so that
    what is held beside x is a few numbers a query."""
    x = np.asarray(x, np.float64)
    order = spatial_order(x)
    sites_ = np.ascontiguousarray(cells.sites, np.float64)
    first = np.ascontiguousarray(cells.first, np.int64)
    neighbours = as_index(cells.neighbours)
    period = np.ascontiguousarray(period, np.float64)
    out = np.empty(len(x))
    nearest = np.empty(len(x), np.int64) if sites else None
    for start in range(0, len(x), WALK):
        rows = order[start : start + WALK]
        xs = np.ascontiguousarray(x[rows])
        res, site = np.empty(len(rows)), np.empty(len(rows), np.int64)

        def call(a, b, xs=xs, res=res, site=site):
            _walk_d_m2(sites_, first, neighbours, period, xs, res, site, a, b)

        in_chunks(call, len(rows), threads=workers, least=512)
        out[rows] = res
        if sites:
            nearest[rows] = site
    return out, nearest


WALK = 1 << 18  # queries walked at once (``walked``)


@kernel(entry=True, lazy=True, nogil=True)
def _walk_d_m2(sites, first, neighbours, period, x, out, site, start, end):
    """``walked``'s work for queries [start, end) (``_tree.walk_nearest``), NaN (site -1)
    where a walk did not settle; the second nearest site is the nearest of the nearest's
    neighbours (their nearest copies, as the walk measures them)."""
    v = 0
    for q in range(start, end):
        xq = x[q]
        v, _ = walk_nearest(sites, first, neighbours, period, xq, v)
        if v < 0:
            out[q] = np.nan
            site[q] = -1
            v = 0
            continue
        second = np.inf
        for j in range(first[v], first[v + 1]):
            second = min(second, point2(sites, neighbours[j], xq, period))
        out[q] = math.sqrt(second)
        site[q] = v


def cell_counts(tree, cells, stop):
    """What each closed Voronoi cell (``steps.Cells``) holds of the points in ``tree``:
    where the triangulation was verified (``cells.walkable``), each point's nearest vertex
    walked, ties added (``Tree.nearest_counts``: exact in full, one pass over the points);
    otherwise, or where a walk did not settle, each cell asked of the tree (exact below
    ``stop``)."""
    if cells.walkable:
        counts = tree.nearest_counts(cells.sites, cells.first, cells.neighbours, cells.period,
                                     cells.relative, cells.slack2)  # fmt: skip
        if counts is not None:
            return counts
    return tree.cells_held(cells.sites, cells.first, cells.neighbours, cells.shift,
                           cells.period, cells.outradii, stop, cells.relative,
                           cells.slack2)  # fmt: skip


def _edge_arrays(cells):
    """(sites, first, neighbours, shift, period) of ``cells`` as the kernels read them."""
    return (np.ascontiguousarray(cells.sites, np.float64),
            np.ascontiguousarray(cells.first, np.int64), as_index(cells.neighbours),
            edge_shifts(cells.shift, len(cells.neighbours)),
            np.ascontiguousarray(cells.period, np.float64))  # fmt: skip


def nearest_neighbour(cells):
    """Each site's distance to its nearest neighbour among ``cells``' (a Delaunay
    triangulation's: the nearest other vertex), inf for a site with none."""
    out = np.full(len(cells.sites), np.inf)
    _nearest_lengths(*_edge_arrays(cells), out)
    return out


@kernel(entry=True, lazy=True, nogil=True)
def _nearest_lengths(sites, first, neighbours, shift, period, out):
    """out[v]: the least length of site v's edges (``_tree.edge_at``; a site is not its
    own neighbour: an edge of length 0 counts as none)."""
    for v in range(first.shape[0] - 1):
        for j in range(first[v], first[v + 1]):
            s = 0.0
            for a in range(sites.shape[1]):
                g = edge_at(sites, neighbours, shift, period, v, j, a)
                s += g * g
            length = math.sqrt(s)
            if length > 0.0:
                out[v] = min(out[v], length)


def edge_midpoints(cells, start=0, end=None):
    """(the midpoint of every edge of the sites [start, end) once, the edge's two vertices
    (e, 2)): of the two directions of an edge, the one whose vector is lexicographically
    positive, in the order of the sites; in kernels (``_positive_edges``, ``_midpoints``),
    with no gathered copies of the sites. Ranges of sites in turn give, together, the rows
    of all of them at once (``probe_parts`` makes them a range at a time)."""
    arrays = _edge_arrays(cells)
    m = len(arrays[1]) - 1
    end = m if end is None else min(end, m)
    lo, hi = int(arrays[1][start]), int(arrays[1][end])
    positive = np.zeros(hi - lo, bool)
    _positive_edges(*arrays, start, end, positive)
    index = np.int32 if len(arrays[2]) < 2**31 else np.int64
    at = np.cumsum(positive, dtype=index) - 1  # each positive row's place among them
    count = int(at[-1]) + 1 if len(at) else 0
    mids, ends = np.empty((count, arrays[0].shape[1])), np.empty((count, 2), index)
    _midpoints(*arrays, start, end, positive, at, mids, ends)
    return mids, ends


@kernel(entry=True, lazy=True, nogil=True)
def _positive_edges(sites, first, neighbours, shift, period, start, end, positive):
    """positive[j - first[start]] for the rows j of the sites [start, end): whether edge
    j's vector (``_tree.edge_at``) is lexicographically positive (its first component not
    0 is > 0)."""
    base = first[start]
    for v in range(start, end):
        for j in range(first[v], first[v + 1]):
            for a in range(sites.shape[1]):
                g = edge_at(sites, neighbours, shift, period, v, j, a)
                if g != 0.0:
                    positive[j - base] = g > 0.0
                    break


@kernel(entry=True, lazy=True, nogil=True)
def _midpoints(sites, first, neighbours, shift, period, start, end, positive, at, mids, ends):
    """``edge_midpoints``' rows: for each positive row j of a site v in [start, end), at
    its place at[j - first[start]], sites[v] + 0.5 (its edge vector) and (v, its far
    site)."""
    base = first[start]
    for v in range(start, end):
        for j in range(first[v], first[v + 1]):
            if positive[j - base]:
                i = at[j - base]
                for a in range(sites.shape[1]):
                    mids[i, a] = sites[v, a] + 0.5 * edge_at(sites, neighbours, shift, period,
                                                             v, j, a)  # fmt: skip
                ends[i, 0] = v
                ends[i, 1] = neighbours[j]


def nearest_site(cells, x, period, workers, tri):
    """The site of ``cells`` nearest each row of x, as a column (n, 1): walked
    (``walked``) where ``tri`` verified the triangulation, else from scipy's cKDTree in
    plain coordinates (across a period the nearest may be missed: any site is a valid
    bound of d_{P,k} at x, ``steps.bounded_d_pk``, the nearest only the tightest)."""
    sites = cells.sites
    if len(sites) == 0 or len(x) == 0:
        return np.full((len(x), 1), -1, np.int64)
    near = np.full(len(x), -1, np.int64)
    if not tri.problems and len(sites) >= 4:
        near = walked(cells, x, period, workers)[1]
    lost = near < 0
    if lost.any():
        near[lost] = cKDTree(sites).query(x[lost])[1]
    return near[:, None]


# the size integral's sample (``Probes.extra``): ``kept`` the mask of its points kept
# (the first probes), ``w`` each point's weight (its cell's measure, or on the sphere the
# weight that makes a point uniform in the flat triangle uniform on the sphere), ``cells``
# each point's cell, ``corners`` (t, c) each cell's corners (the mesh's vertices: its own
# array, not a copy), ``measure`` every cell's area (volume, solid angle), ``t`` the cells,
# ``at`` each vertex's row among the probes (-1 where it was not kept)
SizeSample = namedtuple("SizeSample", ["kept", "w", "cells", "corners", "measure", "t", "at"],
                        defaults=(None,))  # fmt: skip
SIZE_CHUNK = 1 << 16  # cells whose corners ``size_integral`` reads at once


def probe_parts(
    first,
    sampled,
    vertices,
    vertex_d_m2,
    voronoi,
    wrap,
    uniform,
    period,
    workers,
    tri,
    further,
    corners,
):
    """(the parts ``gathered_probes`` makes, in its order, and their number of rows): the
    size integral's samples ``first``, the input points ``sampled``, the vertices (with
    d_{M,2} where known, else None), the edge midpoints of ``voronoi`` (put in the frame by
    ``wrap``), ``uniform`` points and the further samples ``further``; near: a midpoint's
    two vertices, a uniform point's nearest vertex (``nearest_site`` in ``period``), a
    further sample's cell's ``corners``. The same six parts in every domain."""

    def midpoints():  # a range of sites at a time: no (e, d) array of them all at once
        for start in range(0, len(voronoi.first) - 1, MIDPOINT_SITES):
            mids, ends = edge_midpoints(voronoi, start, start + MIDPOINT_SITES)
            yield wrap(mids), False, None, ends

    parts = [
        lambda: [(first, False, None, None)],
        lambda: [(sampled, True, None, None)],
        lambda: [(vertices, False, vertex_d_m2, None)],
        midpoints,
        lambda: [(uniform, False, None, nearest_site(voronoi, uniform, period, workers, tri))],
        lambda: [(further, False, None, corners)],
    ]
    rows = len(first) + len(sampled) + len(vertices) + int(voronoi.first[-1]) // 2
    return parts, rows + len(uniform) + len(further)


def gathered_probes(parts, inside, size, width, capacity, vertices=2):
    """``steps.Probes`` from ``parts``, functions each making a part when called, in turn,
    as pieces (an iterable of (x, whether input points, d_{M,2} known or None (NaN:
    asked), its near rows or None)), the first part the size integral's samples, each
    kept where ``inside(x)``; ``size`` a ``SizeSample`` whose ``corners`` are indices into
    the part ``vertices`` (the mesh's vertices), returned with those vertices' rows among
    the probes kept (``at``). A part's near rows (count, r <= ``width``) are rows of the
    part ``vertices`` (which comes before them) near each of its probes (an edge's
    midpoint: its two vertices); ``Probes.near`` holds those probes' indices (-1 where one
    was dropped, beyond a part's own r columns, and for the other parts);
    ``Probes.exact`` marks the first part and the part ``vertices``, whose d_{P,k} the
    size integral reads. Each piece is copied into its place and dropped before the next
    is made (what is held at once: the probes and one piece), in arrays of ``capacity``
    rows (the caller's bound; more where it was short)."""
    index = np.int32 if capacity < 2**31 - 2**20 else np.int64
    rows = _ProbeRows(capacity, width, index)
    kept = {}  # the masks of the parts read later: the samples' and the vertices'
    at = None
    for i, make in enumerate(parts):
        start, keeps = rows.n, []
        for x, points, d_m2, near in make():
            keep = inside(x)
            rows.add(x, keep, points, d_m2, None if near is None else _rows_of(at, near[keep]))
            del x, d_m2, near
            if i in (0, vertices):
                keeps.append(keep)
        if i in (0, vertices):
            kept[i] = np.concatenate(keeps) if keeps else np.zeros(0, bool)
        if i == vertices:
            keep = kept[i]
            at = np.full(len(keep), -1, index)  # each vertex's probe row (-1: dropped)
            at[keep] = start + np.arange(int(keep.sum()), dtype=index)
    probes = rows.probes()
    probes.exact[: int(kept[0].sum())] = True  # what the size integral reads: its
    probes.exact[at[at >= 0]] = True  # samples and the corners
    return probes._replace(extra=size._replace(kept=kept[0], at=at))


def _rows_of(at, near):
    """The probe rows ``at`` of the vertices ``near`` (-1 where none, or not kept)."""
    return np.where(near >= 0, at[np.maximum(near, 0)] if len(at) else -1, -1).astype(at.dtype)


class _ProbeRows:
    """The probes' arrays filled part by part (``gathered_probes``): ``capacity`` rows,
    grown by half where a part needs more."""

    def __init__(self, capacity, width, index):
        self.n, self.width, self.index = 0, width, index
        self.x = None
        self.size = max(int(capacity), 1)

    def _arrays(self, dim):
        size, width = self.size, self.width
        return (np.empty((size, dim)), np.zeros(size, bool), np.full(size, np.nan),
                np.full((size, width), -1, self.index))  # fmt: skip

    def _room(self, rows, dim):
        if self.x is None:
            self.x, self.points, self.d_m2, self.near = self._arrays(dim)
        if self.n + rows > self.size:
            self.size = max(self.n + rows, self.size + self.size // 2)
            grown = self._arrays(dim)
            for new, old in zip(grown, (self.x, self.points, self.d_m2, self.near), strict=True):
                new[: self.n] = old[: self.n]
            self.x, self.points, self.d_m2, self.near = grown

    def add(self, x, keep, points, d_m2, near):
        """Append x[keep] (input points or not, d_{M,2} or None, near rows or None);
        returns the first one's row."""
        kept = int(keep.sum())
        self._room(kept, x.shape[1])
        a, b = self.n, self.n + kept
        np.compress(keep, x, axis=0, out=self.x[a:b])
        self.points[a:b] = points
        if d_m2 is not None:
            np.compress(keep, np.asarray(d_m2, float), out=self.d_m2[a:b])
        if near is not None:
            self.near[a:b, : near.shape[1]] = near
        self.n = b
        return a

    def probes(self):
        n = self.n
        return Probes(self.x[:n], self.points[:n], self.d_m2[:n], None, self.near[:n],
                      np.zeros(n, bool))  # fmt: skip


MIDPOINT_SITES = 1 << 15  # sites whose edges' midpoints ``probe_parts`` makes at once
SIZE_SHARE = 4  # the size integral reads one point in each of samples // SIZE_SHARE cells


def size_sample(t, samples, rng):
    """(the cell of each random point of the size integral, the cell of each further
    point that only probes the ratio), of ``samples`` points in all. A large mesh
    (``samples`` < t): one point in each of ``samples`` cells drawn without replacement;
    a small one: ``samples`` // t in every cell (a small mesh is probed densely, as its
    ratio's largest values can hide in small regions: with 4 per cell,
    test_achieved_constants_are_what_they_claim fails on 300 points). The integral reads
    one of them in each of min(t, ``samples`` // SIZE_SHARE) cells drawn without
    replacement (``size_integral``: its error is that of the integrand's spread about
    its cells' corners, so a share of the cells suffices). The further points are bounded
    by their cell's corners (``steps.bounded_d_pk``) and asked only where they could be
    extremes, so that what is asked of the points grows with the mesh."""
    share = min(t, max(int(samples) // SIZE_SHARE, 1))
    if samples < t:
        pool = rng.choice(t, int(samples), replace=False)
        return np.sort(pool[:share]), np.sort(pool[share:])
    chosen = np.sort(rng.choice(t, share, replace=False))
    each = np.full(t, int(samples) // max(t, 1))
    each[chosen] -= 1
    return chosen, np.repeat(np.arange(t), each)


def size_integral(sample, d_pk, floor, dim):
    """(the integral of 1 / d_{P,k}^dim over the domain, d_{P,k} clipped at ``floor``; its
    standard error) from a ``SizeSample`` and d_{P,k} at the probes. The integrand's mean
    over each cell's corners, h, is a control variate whose integral is exact (the sum of
    the cells' measures times h); the random points estimate the rest, the integral of the
    integrand minus h, whose spread is the integrand's within cells, not between them
    (where its corners are not all kept, a cell's h is 0: estimated whole). One point in
    each of s of the t cells: the estimate is sum(measure h) + t / s sum(w (f - h)), its
    standard error t sd(w (f - h)) / sqrt(s) (with replacement: conservative)."""
    kept, w, cells, corners, measure, t, _ = sample
    s = len(kept)
    if s == 0:
        return 0.0, 0.0
    low = max(floor, 1e-300)
    f = np.zeros(s)
    f[kept] = 1.0 / np.maximum(d_pk[: int(kept.sum())], low) ** dim
    h = np.zeros(t)
    for a in range(0, t, SIZE_CHUNK):  # (a chunk of cells at a time: no (t, dim + 1) copies)
        c = sample.at[corners[a : a + SIZE_CHUNK]]  # (their rows among the probes)
        whole = (c >= 0).all(axis=1)
        if whole.any():
            at = 1.0 / np.maximum(d_pk[c[whole]], low) ** dim
            h[a : a + SIZE_CHUNK][whole] = at.mean(axis=1)
    h[~np.isfinite(h)] = 0.0  # a corner with d_{P,k} unknown: that cell estimated whole
    y = np.where(kept, w * (f - h[cells]), 0.0)
    total = float(np.dot(measure, h)) + t / s * float(y.sum())
    stderr = t * float(np.std(y, ddof=1)) / np.sqrt(s) if s > 1 else 0.0
    return total, stderr
