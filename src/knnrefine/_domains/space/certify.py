"""``certify`` in three dimensions: every promise of a ``Mesh`` in space checked without the
engine's refinement code (on the torus it refined, the box's own along periodic axes and the
embedding torus along the others; the bounds in the box's own metric).

The tetrahedralisation is checked exactly in the mesh's own frame (vertices relative to the
box's corner, exact): its faces are matched again from the corners and offsets, every
tetrahedron is positively oriented and locally Delaunay (certify's own filtered
predicates, integers where floating point cannot decide), and the volumes
add up to the torus' once. Counts come from certify's own kd-tree (``certify._tree``) on the torus:
points in every closed circumball and in every closed Voronoi cell (each point counting for
every vertex as near as its nearest), below k except for elements smaller than the
resolution floor (``min_size``: counted and reported). Aspect 2 R(v) / d_{M,2}(v) from
circumradii computed here and the vertices' own kd-tree. Lemma 2's precondition on the
initial vertices, as in the plane (``certify.check_precondition``). What the user received
(``vertices``, ``tetrahedra``, ``offsets``, ``local``) must be, exactly and without a repeated
vertex, copies of the torus mesh. The achieved constants: d_{M,2}, from the returned
vertices, over d_{P,k} at probes as the plane's (every vertex and edge midpoint, random
points in the tetrahedra, input points, uniform points of the box: ``steps.Probes``), whose
extremes alpha_hat and beta_hat must lie within [alpha, beta] where
d_{P,k} >= min_size.
"""

import math
from functools import cached_property

import numpy as np

from ..._engine.jit import kernel  # numba's njit(cache=True), also on read-only installs
from ..._engine.threads import in_chunks
from ..._metric import BoxMetric, TorusFrame
from ..._sampling import key_sample
from ...certify._predicates import UNSURE, exact_sign, insphere, orient3d
from ...certify._rows import as_index, as_offsets
from ...certify._tree import Tree, incidence
from ...certify.common import (
    SizeSample,
    TorusGeometry,
    cell_array_problem,
    cell_counts,
    check_cells_tile,
    checked_points,  # noqa: F401  (the box domains' own)
    find_rows,
    gathered_probes,
    probe_parts,
    repeated_rows,
    size_integral,
    size_sample,
)
from ...certify.steps import Triangulation


@kernel(entry=True, lazy=True, nogil=True)
def _local_signs(local, corners, offsets, neighbours, period, orient, sphere, start, end):
    """For tetrahedra t in [start, end): orient[t], the sign of orient3d of its corners
    (UNSURE where the filter cannot tell); sphere[t, i], that of insphere of its corners
    and the far corner of the tetrahedron across face i, placed by the face's own offsets
    (``_far_corner``, the same arithmetic)."""
    pts = np.empty((5, 3))
    for t in range(start, end):
        for i in range(4):
            for a in range(3):
                pts[i, a] = local[corners[t, i], a] + offsets[t, i, a] * period[a]
        orient[t] = orient3d(pts, 0, 1, 2, 3)
        for i in range(4):
            _far_corner(local, corners, offsets, neighbours, period, t, i, pts[4])
            sphere[t, i] = insphere(pts, 0, 1, 2, 3, 4)


@kernel(inline="always", cache=False)  # inlined: nothing of its own to cache
def _far_corner(local, corners, offsets, neighbours, period, t, i, out):
    """Into ``out`` (3,): the corner of the tetrahedron across face i of tetrahedron t
    opposite that face, placed by the face's own offsets (the one rule of the filtered
    test, ``_local_signs``, and of the exact one, ``_far_corners``)."""
    n = neighbours[t, i]
    shared = corners[t, (i + 1) % 4]
    ia = 0
    jj = 0
    for m in range(4):
        if corners[n, m] == shared:
            ia = m
        if neighbours[n, m] == t:
            jj = m
    for a in range(3):
        s = offsets[t, (i + 1) % 4, a] - offsets[n, ia, a]
        out[a] = local[corners[n, jj], a] + (offsets[n, jj, a] + s) * period[a]


@kernel(entry=True, lazy=True, nogil=True)
def _far_corners(local, corners, offsets, neighbours, period, cells, faces, out):
    """out[j]: ``_far_corner`` across face faces[j] of tetrahedron cells[j] (the faces
    whose insphere sign the filter could not tell)."""
    for j in range(cells.shape[0]):
        _far_corner(local, corners, offsets, neighbours, period, cells[j], faces[j], out[j])


def _exact_faces(local, corners, offsets, neighbours, period, workers=None):
    """(tetrahedra not positively oriented, faces not locally Delaunay), exactly: filtered
    signs (``_local_signs``, on ``workers`` threads: None or -1 every core), integers where
    the filter cannot tell."""
    t = len(corners)
    orient = np.empty(t, np.int8)
    sphere = np.empty((t, 4), np.int8)

    def call(a, b):
        _local_signs(local, corners, offsets, neighbours, period, orient, sphere, a, b)

    in_chunks(call, t, threads=workers, least=4096)
    at = lambda c: local[corners[c]] + offsets[c] * period  # noqa: E731
    for c in np.flatnonzero(orient == UNSURE):
        orient[c] = exact_sign("orient3d", at(c))
    cells, faces = np.nonzero(sphere == UNSURE)
    far = np.empty((len(cells), 3))
    _far_corners(local, corners, offsets, neighbours, period, cells, faces, far)
    for j, (c, i) in enumerate(zip(cells, faces, strict=True)):
        sphere[c, i] = exact_sign("insphere", np.vstack([at(c), far[j]]))
    return int((orient <= 0).sum()), int((sphere > 0).sum())


def _neighbours(corners, offsets, workers=None):
    """The tetrahedron across each face (t, 4), matched again from the corners and offsets;
    None unless every face is shared by exactly two. A face's key is its three vertices
    sorted (by vertex, then offset) and their offsets relative to the least along each
    axis; a vertex's faces (those it is the least vertex of) are gathered from its
    tetrahedra (``_tree.incidence``) and matched among
    themselves, a range of vertices a thread (``_match_faces``, on ``workers`` threads):
    what is held is the incidence and the answer, 8 t integers, not a key for every face.
    The key is written out (``_face_key``), not packed into ``common``'s corner codes as
    ``check_cells_tile`` packs its own: codes need offsets within CODE_BASE periods, and
    the torus' faces are paired whatever its offsets."""
    t = len(corners)
    corners, offsets = as_index(corners), as_offsets(offsets)
    index = np.int32 if 4 * t < 2**31 else np.int64
    if t == 0:
        return np.zeros((0, 4), index)
    m = int(corners.max()) + 1
    first, incident = incidence(corners, m)
    out = np.empty((t, 4), index)
    widest = 4 * int(np.diff(first).max())

    def match(a, b):
        _match_faces(corners, offsets, first, incident, widest, out, a, b)

    in_chunks(match, m, threads=workers, least=2048)
    return None if (out < 0).any() else out


@kernel(inline="always", cache=False)
def _face_key(corners, offsets, c, i, v, o):
    """v (3,), o (3, 3): the key of face i of tetrahedron c (the face opposite corner i):
    its vertices sorted by (vertex, offsets), their offsets less the least along each
    axis."""
    n = 0
    for j in range(4):
        if j == i:
            continue
        v[n] = corners[c, j]
        for a in range(3):
            o[n, a] = offsets[c, j, a]
        n += 1
    for a in range(3):
        least = min(o[0, a], o[1, a], o[2, a])
        for j in range(3):
            o[j, a] -= least
    for j in range(1, 3):  # insertion sort of the three by (vertex, offsets)
        b = j
        while b > 0:
            less = v[b] < v[b - 1]
            if v[b] == v[b - 1]:
                for a in range(3):
                    if o[b, a] != o[b - 1, a]:
                        less = o[b, a] < o[b - 1, a]
                        break
            if not less:
                break
            v[b], v[b - 1] = v[b - 1], v[b]
            for a in range(3):
                o[b, a], o[b - 1, a] = o[b - 1, a], o[b, a]
            b -= 1


@kernel(entry=True, lazy=True, nogil=True)
def _match_faces(corners, offsets, first, incident, widest, out, start, end):
    """out[c, i] for the faces whose least vertex is in [start, end): the tetrahedron
    whose face has the key of face i of c (``_face_key``), -1 unless exactly one face
    other than itself has it. A vertex's faces are gathered from its tetrahedra
    (``incident``, at most ``widest`` faces), ordered by their other two vertices, and
    keyed in full against the faces with the same three."""
    w = np.empty(3, np.int64)
    p = np.empty((3, 3), np.int64)
    cell = np.empty(widest, np.int64)
    face = np.empty(widest, np.int64)
    keys = np.empty((widest, 9), np.int64)
    pair = np.empty(widest, np.int64)
    m = first.shape[0] - 1
    for v in range(start, end):
        n = 0
        previous = -1
        for r in range(first[v], first[v + 1]):
            d = incident[r] // 4
            if d == previous:  # (v twice in d: its faces already read)
                continue
            previous = d
            for f in range(4):
                x0, x1, x2 = (corners[d, (f + 1) & 3], corners[d, (f + 2) & 3],
                              corners[d, (f + 3) & 3])  # fmt: skip
                if x0 > x1:
                    x0, x1 = x1, x0
                if x1 > x2:
                    x1, x2 = x2, x1
                if x0 > x1:
                    x0, x1 = x1, x0
                if x0 != v:  # (a face of the vertex its least)
                    continue
                _face_key(corners, offsets, d, f, w, p)
                cell[n], face[n] = d, f
                for j in range(3):
                    for a in range(3):
                        keys[n, 3 * j + a] = p[j, a]
                pair[n] = w[1] * m + w[2]
                n += 1
        order = np.argsort(pair[:n])
        a = 0
        while a < n:  # runs of faces with the same three vertices
            b = a + 1
            while b < n and pair[order[b]] == pair[order[a]]:
                b += 1
            for x in range(a, b):
                s = order[x]
                found = -1
                matches = 0
                for y in range(a, b):
                    u = order[y]
                    if u == s:
                        continue
                    same = True
                    for j in range(9):
                        if keys[u, j] != keys[s, j]:
                            same = False
                            break
                    if same:
                        matches += 1
                        found = cell[u]
                out[cell[s], face[s]] = found if matches == 1 else -1
            a = b


def _circumspheres(local, cells, offsets, period, workers=None):
    """(centres (t, 3), squared radii, signed volumes times 6) of the tetrahedra whose
    corners are local[cells] + offsets period, on every core (``_spheres``: the corners
    read where they are, no (t, 4, 3) copy)."""
    local = np.ascontiguousarray(local, np.float64)
    cells, offsets = as_index(cells), as_offsets(offsets)
    period = np.ascontiguousarray(period, np.float64)
    t = len(cells)
    centres, r2, det = np.empty((t, 3)), np.empty(t), np.empty(t)

    def call(a, b):
        _spheres(local, cells, offsets, period, centres, r2, det, a, b)

    in_chunks(call, t, threads=workers, least=8192)
    return centres, r2, det


@kernel(entry=True, lazy=True, nogil=True)
def _spheres(local, cells, offsets, period, centres, r2, det, start, end):
    """``_circumspheres`` for tetrahedra [start, end): with m0, m1, m2 the edges from corner
    0 and h_i = |m_i|^2 / 2, the centre less corner 0 solves m u = h, u = (h0 m1 x m2 +
    h1 m2 x m0 + h2 m0 x m1) / det (Cramer's rule: no LAPACK call per tetrahedron);
    det = m0 . (m1 x m2), 0 for a flat one (its centre not finite)."""
    m = np.empty((3, 3))
    x = np.empty((3, 3))  # x[i]: the cross product of the two other edges
    h = np.empty(3)
    c = np.empty((4, 3))  # the corners
    for t in range(start, end):
        for i in range(4):
            for a in range(3):
                c[i, a] = local[cells[t, i], a] + offsets[t, i, a] * period[a]
        for i in range(3):
            for a in range(3):
                m[i, a] = c[i + 1, a] - c[0, a]
            h[i] = 0.5 * (m[i, 0] * m[i, 0] + m[i, 1] * m[i, 1] + m[i, 2] * m[i, 2])
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            x[i, 0] = m[j, 1] * m[k, 2] - m[j, 2] * m[k, 1]
            x[i, 1] = m[j, 2] * m[k, 0] - m[j, 0] * m[k, 2]
            x[i, 2] = m[j, 0] * m[k, 1] - m[j, 1] * m[k, 0]
        d = m[0, 0] * x[0, 0] + m[0, 1] * x[0, 1] + m[0, 2] * x[0, 2]
        det[t] = d
        s = 0.0
        for a in range(3):
            u = (h[0] * x[0, a] + h[1] * x[1, a] + h[2] * x[2, a]) / d
            centres[t, a] = c[0, a] + u
            s += u * u
        r2[t] = s


class Points:
    """Every question certify asks about the input points in space, answered in this process
    from certify's own kd-tree (``_tree.Tree``, on the mesh's torus; weighted, the points of
    positive weight) (``scale.checks.TiledSpacePoints`` asks the same where the points
    are): what closed balls of the torus hold (``held``: a count, or a weight), what each
    vertex's closed Voronoi cell holds (``cell_counts``), d_{P,k} at probes in the box's own
    metric (``d_pk``, straight along non-periodic axes; weighted: the least radius holding
    weight k), and some of the points (``sample_points``), all in the frame of the mesh's
    torus."""

    def __init__(self, mesh, pts, weights, workers):
        torus = mesh.torus
        self.origin = np.asarray(torus.origin, float)
        self.period = np.asarray(torus.period, float)
        self.source, self.input_frame = pts, TorusFrame(self.origin, self.period)
        framed = self.input_frame(pts)  # (the tree's: sorted in place)
        self.workers, self.k, self.n = workers, mesh.k, len(pts)
        self.weighted = weights is not None
        self.total = float(len(pts)) if weights is None else math.fsum(weights)
        self.box_period = np.where(mesh.periodic, self.period, 0.0)
        self.metric = BoxMetric((*self.origin, *(self.origin + self.period)), mesh.periodic)
        heavy = None if weights is None else weights > 0
        # built beside the mesh's checks, which come first
        self.tree = Tree(framed if heavy is None else framed[heavy],
                         None if heavy is None else weights[heavy], self.period,
                         workers, background=True, scratch=True)  # fmt: skip

    def held(self, centres, radii, stop=np.inf):
        return self.tree.held(centres, radii, stop)

    def fewer(self, centres, radii, k, mostly=True):
        """Whether each closed ball holds less than weight k in d_{P,k}'s metric, the
        box's own (``d_pk``)."""
        return self.tree.fewer(centres, radii, k, period=self.box_period, mostly=mostly)

    def cell_counts(self, cells, stop=np.inf):
        """What the closed Voronoi cell of each vertex (``steps.Cells``, torus frame) holds:
        every point counts for each vertex as near as its nearest; exact below ``stop``."""
        return cell_counts(self.tree, cells, stop)

    def d_pk(self, x):
        """d_{P,k} at x (the torus frame, periodic axes wrapped) in the box's own metric:
        straight along non-periodic axes, so the embedding's claim is tested."""
        return self.tree.kth(x, self.k, period=self.box_period)

    def sample_points(self, count, rng):
        """About ``count`` input points (torus frame), the same on every path
        (``_sampling``: those whose key is below count / n, as ``scale.checks``' slabs draw
        them)."""
        return self.input_frame(key_sample(self.source, min(1.0, count / max(self.n, 1)))[0])


def _same_rows(a, b):
    """Whether the rows of a are those of b, exactly, in some order."""
    if a.shape != b.shape:
        return False
    return np.array_equal(a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])])


def _parity(rows):
    """The parity (0 even, 1 odd) of the permutation that sorts each row of 4."""
    inversions = np.zeros(len(rows), np.int64)
    for i in range(4):
        for j in range(i + 1, 4):
            inversions += rows[:, i] > rows[:, j]
    return inversions % 2


def verify_returned_mesh3(mesh):
    """Problems (a list of strings) that stop what the user works with, ``vertices`` (input
    coordinates) and ``tetrahedra`` with ``offsets``, from being, exactly and without
    repeated vertices, copies of the torus mesh that certify checks: each vertex a torus
    vertex moved by whole periods, each tetrahedron a torus tetrahedron (the same corners,
    the same orientation) moved by whole periods, each once, tiling the box
    (``common.check_cells_tile``)."""
    torus = mesh.torus
    v = np.asarray(mesh.vertices, float)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        return ["vertices are not finite (m, 3) coordinates"]
    problems = []
    repeated = repeated_rows(v)
    if repeated:
        problems.append(f"{repeated} repeated vertices")
    origin, period = np.asarray(torus.origin, float), np.asarray(torus.period, float)
    tl = np.asarray(torus.vertices, float)
    order = np.asarray(mesh.order)
    if len(order) != len(v) or order.min(initial=0) < 0 or order.max(initial=0) >= len(tl):
        return problems + ["vertex order does not index the torus vertices"]
    shift = np.rint((v - origin - tl[order]) / period)
    off = np.any(v != origin + (tl[order] + shift * period), axis=1)
    if off.any():
        problems.append(f"{int(off.sum())} vertices differ from their torus vertex")
    broken = cell_array_problem(mesh)
    if broken:
        return problems + [broken]
    tet = as_index(mesh.cells)
    zeros = np.zeros(tet.shape + (3,), np.int8)
    offsets = zeros if mesh.offsets is None else np.ascontiguousarray(mesh.offsets)
    ids = as_index(order.astype(np.int32) if len(tl) < 2**31 else order)[tet]
    ttet = as_index(torus.cells)
    toffsets = np.ascontiguousarray(torus.offsets)
    if ids.shape == ttet.shape and np.array_equal(ids, ttet):
        # the torus' tetrahedra, row for row, corners in the same order (a torus returned
        # as it is): each matches its own row, with its own orientation; on a torus,
        # cells that are its own moved by whole periods tile it as it does (verified
        # exactly with its triangulation), so check_cells_tile's sort is not needed
        if not np.all(mesh.periodic):
            problems += check_cells_tile(mesh)
        pos = np.arange(len(ids))
        u_sort = t_sort = np.broadcast_to(np.arange(4, dtype=np.int8), ids.shape)
        same = np.ones(len(ids), bool)
    else:
        # matched by the sorted corner quadruple (one tetrahedron in a simplicial complex),
        # the orientation by the parity of the sorting permutation
        problems += check_cells_tile(mesh)
        # (each row's order held in int8: 4 values, not argsort's int64)
        u_sort = np.argsort(ids, axis=1).astype(np.int8)
        t_sort = np.argsort(ttet, axis=1).astype(np.int8)
        u_key = np.take_along_axis(ids, u_sort, 1)
        t_key = np.take_along_axis(ttet, t_sort, 1)
        pos = find_rows(t_key, u_key)
        hit = pos >= 0
        if (~hit).any():
            problems.append(f"{int((~hit).sum())} tetrahedra are not tetrahedra of the torus mesh")
        same = np.ones(len(ids), bool)
        same[hit] = _parity(ids[hit]) == _parity(ttet[pos[hit]])
        same = same[hit]
    same &= _corners_moved_whole(
        v,
        tet,
        offsets,
        origin,
        tl,
        ttet,
        toffsets,
        period,
        pos,
        np.ascontiguousarray(u_sort),
        np.ascontiguousarray(t_sort),
    )
    if (~same).any():
        problems.append(f"{int((~same).sum())} tetrahedra have corners off their torus tetrahedron")
    return problems


@kernel(entry=True, lazy=True)
def _corners_moved_whole(v, cells, off, origin, tl, tcells, toff, period, pos, u_sort, t_sort):
    """For each returned cell matched to a torus cell (pos >= 0, in that order), whether
    its corners, in torus-frame coordinates v + off period - origin and in the order
    u_sort, are exactly the torus cell's (tl + toff period, in the order t_sort) moved by
    one whole number of periods along each axis, the same for every corner."""
    out = np.empty(int((pos >= 0).sum()), np.bool_)
    d = v.shape[1]
    shift = np.empty(d)
    q = 0
    for i in range(len(pos)):
        t = pos[i]
        if t < 0:
            continue
        ok = True
        for c in range(cells.shape[1]):
            cu, ct = u_sort[i, c], t_sort[t, c]
            for a in range(d):
                mine = v[cells[i, cu], a] + off[i, cu, a] * period[a] - origin[a]
                target = tl[tcells[t, ct], a] + toff[t, ct, a] * period[a]
                moved = np.rint((mine - target) / period[a])
                if c == 0:
                    shift[a] = moved
                elif moved != shift[a]:
                    ok = False
                if mine != target + moved * period[a]:
                    ok = False
        out[q] = ok
        q += 1
    return out


def _tetrahedron_samples(c, per, rng):
    """per uniform points in each tetrahedron with corners c (t, 4, 3): barycentric
    weights from a flat Dirichlet (normalised exponentials)."""
    w = rng.exponential(size=(len(c), per, 4))
    w /= w.sum(axis=2, keepdims=True)
    return np.einsum("tpi,tia->tpa", w, c).reshape(-1, 3)


class Geometry(TorusGeometry):
    """Space's questions about a mesh (``steps.run_checks`` asks them): its torus
    tetrahedralisation checked exactly (faces matched again from the corners and offsets,
    every tetrahedron positively oriented and locally Delaunay, the volumes adding up to the
    torus' once), the returned tetrahedra, circumballs, probes as dense as the plane's in
    the box's own metric, d_{M,2} from the returned vertices (straight along non-periodic
    axes, so the embedding's claim is tested), the size integral of 1 / d_{P,k}^3."""

    def __init__(self, mesh, workers):
        super().__init__(mesh, workers)
        torus = mesh.torus
        self.metric = BoxMetric((*self.origin, *(self.origin + self.period)), mesh.periodic)
        self.local = self.vertices
        self.corners = torus.cells
        self.offsets = as_offsets(torus.offsets)
        self.links = torus.neighbours  # what a continued run walks by: checked too
        self.pk_period = np.where(mesh.periodic, self.period, 0.0)  # the box's own metric

    def triangulation(self):
        """Faces paired (and the torus' neighbour links, where it has them, the pairing),
        orientation, local Delaunay, volume; circumballs (centres wrapped into the torus),
        R(v); ``extra``: the tetrahedra's volumes."""
        local, corners, offsets, period = self.local, self.corners, self.offsets, self.period
        neighbours = _neighbours(corners, offsets, self.workers)
        bad_o = bad_d = -1
        if neighbours is not None:
            bad_o, bad_d = _exact_faces(local, as_index(corners), offsets, neighbours, period,
                                        self.workers)  # fmt: skip
        centres, r2, det = _circumspheres(local, corners, offsets, period, self.workers)
        volume = np.abs(det).sum() / 6.0 / np.prod(period)
        problems = []
        if neighbours is None:
            problems.append("the tetrahedra's faces do not pair up")
        elif self.links is not None:
            links = np.asarray(self.links)
            wrong = (
                len(corners) if links.shape != neighbours.shape
                else int((links != neighbours).any(axis=1).sum())
            )  # fmt: skip
            if wrong:
                problems.append(f"{wrong} tetrahedra's neighbour links are not symmetric or "
                                "not across their faces")  # fmt: skip
        if bad_o > 0:
            problems.append(f"{bad_o} tetrahedra not positively oriented")
        if bad_d > 0:
            problems.append(f"{bad_d} faces not locally Delaunay")
        if abs(volume - 1.0) >= 1e-9:
            problems.append(f"the volumes add up to {volume:.12g} tori")
        outer = np.zeros(len(local))
        for j in range(4):  # (in place, a corner at a time: no copies of t rows)
            np.maximum.at(outer, corners[:, j], r2)
        np.mod(centres, period, out=centres)
        volumes = np.divide(np.abs(det, out=det), 6.0, out=det)
        return Triangulation(problems, centres, np.sqrt(r2, out=r2), np.sqrt(outer, out=outer),
                             volumes)  # fmt: skip

    def returned_problems(self):
        return verify_returned_mesh3(self.mesh)

    def probes(self, tri, points, samples, n_random, max_point_probes, rng):
        """Every vertex and edge midpoint (once each), the size integral's random points
        in the cells (``common.size_sample``: ``samples`` of them, at least one in each
        cell sampled), up to min(``max_point_probes``, 2 m) input points and ``n_random``
        uniform points of the domain (``steps.Probes``: why these)."""
        volumes, period = tri.extra, self.period
        t, m = len(volumes), len(self.local)
        chosen, dense = size_sample(t, samples, rng)
        side = np.array(self.mesh.box[3:]) - np.array(self.mesh.box[:3])
        cells = np.concatenate([chosen, dense])
        c = self.local[self.corners[cells]] + self.offsets[cells] * period
        inside = np.mod(_tetrahedron_samples(c, 1, rng), period)
        del c
        count = min(int(max_point_probes), 2 * m)
        sampled = points.sample_points(count, rng)  # (drawn in this order: the probes')
        uniform = self.lo + rng.random((int(n_random), 3)) * side
        free = ~np.array(self.mesh.periodic)
        s = len(chosen)
        parts, rows = probe_parts(inside[:s], sampled, self.local, None, self.cells(tri),
                                  lambda mids: np.mod(mids, period, out=mids), uniform,
                                  self.period, self.workers, tri, inside[s:],
                                  self.corners[dense])  # fmt: skip
        return gathered_probes(
            parts,
            lambda x: (((x >= self.lo) & (x <= self.hi)) | ~free).all(axis=1),
            SizeSample(None, volumes[chosen], chosen, self.corners, volumes, t),
            4,
            rows,
        )

    def returned_d_m2(self, x, tri):
        """d_{M,2} at x from the returned vertices in the box's own metric, and a problem
        when it differs from the torus mesh's (a copy near the box missing)."""
        coordinates, tree = self._returned
        if tree is None:
            if coordinates:
                return self.torus_d_m2(x, tri), []  # the torus' own vertices and metric
            return np.full(len(x), np.inf), []
        dm2 = tree.kth(x, 2)
        problems = []
        if coordinates:  # the copies near the box hold its two nearest
            on_torus = self.torus_d_m2(x, tri)
            # both from coordinates as large as the box's: their rounding is absolute
            scale = float(np.max(np.abs(self.mesh.box))) + float(self.period.max())
            if not np.allclose(dm2, on_torus, rtol=1e-12, atol=1e-12 * scale):
                problems.append(
                    "d_M2 from the returned vertices differs from the torus mesh's in the box"
                )
        return dm2, problems

    @cached_property
    def _returned(self):
        """(whether the returned vertices are finite (m, 3) coordinates, a kd-tree over
        them, relative to the origin with periodic axes wrapped, in the box's own metric;
        None where there are fewer than two, or, with the first True, where they are the
        torus' own on a torus: d_{M,2} is the torus mesh's)."""
        returned = np.asarray(self.mesh.vertices, float)
        coordinates = (returned.ndim == 2 and returned.shape[1] == 3
                       and np.isfinite(returned).all())  # fmt: skip
        if not coordinates:  # not coordinates at all (a failed check already): the torus'
            returned = self.local
        else:
            returned = self.metric.frame(returned)  # relative to the origin, periodic wrapped
        if len(returned) < 2:
            return False, None
        if coordinates and np.all(self.mesh.periodic) and _same_rows(returned, self.local):
            return True, None
        box_period = np.where(self.mesh.periodic, self.period, 0.0)
        return coordinates, Tree(returned, None, box_period, self.workers)

    def release(self):
        super().release()
        self.__dict__.pop("_returned", None)

    def size(self, probes, d_pk, points, rng):
        """The integral of 1 / d_{P,k}^3 over the box (d_{P,k} clipped at min_size) and its
        standard error (``common.size_integral``): a point outside the box counts 0, and a
        tetrahedron with a corner outside it is estimated whole."""
        return size_integral(probes.extra, d_pk, self.floor, 3)
