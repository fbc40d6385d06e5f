"""``certify`` on the sphere: every promise of a ``Mesh`` with ``domain="sphere"`` checked
without the engine's refinement code, in great-circle distance.

The triangulation is checked exactly on the unit vectors the user received (``Mesh.xyz``):
every edge is shared by exactly two triangles in opposite directions, there are 2 m - 4
triangles over all m vertices (a closed surface of genus 0), every triangle is positively
oriented about the centre, and every edge is locally convex (the far corner of the triangle
across it is not strictly inside the triangle's circumcap), all signs exact (certify's own
filtered ``orient3d``, integers where floating point cannot decide); and the triangles,
seen from the centre, cover the sphere once (their solid angles add up to 4 pi: a float sum
deciding an integer with a margin of 2 pi). Locally convex, facing out and covering once,
the surface is the boundary of the vectors' convex hull, which is the spherical Delaunay
triangulation. (qhull is not asked: at caps of a micro-radian its rounding calls extreme
vertices inner ones, and a verdict rests on exact signs.) The vertices in degrees must be the
vectors' longitude and latitude.

Counts: the points in every closed circumcap are those on or above the plane of its corners,
decided exactly (``orient3d``) among the candidates certify's kd-tree over the points' unit
vectors finds in a slightly larger ball; the points in every closed Voronoi cell from it
(each point counting for every vertex as near as its nearest, up to the unit vectors'
rounding). Both below k except for elements smaller than the resolution floor (counted and
reported). The aspect 2 R(v) / d_{M,2}(v) in angles. Lemma 2's
precondition on the initial vertices, ordered by peeling as in the plane. The achieved
constants: d_{M,2} / d_{P,k} at every vertex and edge midpoint, random points in the
triangles, input points and uniform points of the sphere (``steps.Probes``), within [alpha,
beta] wherever d_{P,k} >= min_size, beta from the largest circumcap measured here
(``mesh.sphere_constants``: spherical Pythagoras widens the plane's).
"""

import math
from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..._engine.jit import kernel  # numba's njit(cache=True), also on read-only installs
from ..._metric import angle_to_chord, chord_to_angle, lonlat_of
from ..._sampling import key_sample
from ..._validation import as_sphere_points, check_made_from, weights_of_run
from ...certify._predicates import UNSURE, exact_sign, orient3d_at
from ...certify._rows import grouped
from ...certify._tree import Tree, neighbour_lists, sums_by
from ...certify.common import (
    SizeSample,
    cell_counts,
    check_precondition,
    gathered_probes,
    nearest_neighbour,
    probe_parts,
    separations,
    size_integral,
    size_sample,
    walked_d_m2,
)
from ...certify.steps import Cells, Triangulation
from ...mesh import sphere_constants, uniform_in_triangles


@kernel(entry=True, lazy=True)
def _local_signs(xyz, corners, twin_tri, twin_corner, orient, convex):
    """orient[t]: the sign of orient3d of triangle t's corners and the centre (UNSURE where
    the filter cannot tell); convex[t, i]: that of its corners and the far corner of the
    triangle across edge i."""
    for t in range(corners.shape[0]):
        a, b, c = corners[t, 0], corners[t, 1], corners[t, 2]
        orient[t] = orient3d_at(xyz[a, 0], xyz[a, 1], xyz[a, 2], xyz[b, 0], xyz[b, 1], xyz[b, 2],
                                xyz[c, 0], xyz[c, 1], xyz[c, 2], 0.0, 0.0, 0.0)  # fmt: skip
        for i in range(3):
            d = corners[twin_tri[t, i], twin_corner[t, i]]
            convex[t, i] = orient3d_at(xyz[a, 0], xyz[a, 1], xyz[a, 2], xyz[b, 0], xyz[b, 1],
                                       xyz[b, 2], xyz[c, 0], xyz[c, 1], xyz[c, 2], xyz[d, 0],
                                       xyz[d, 1], xyz[d, 2])  # fmt: skip


def _exact_edges(xyz, tri, twin_tri, twin_corner):
    """(triangles not positively oriented about the centre, edges not locally convex),
    exactly: filtered signs (``_local_signs``), integers where the filter cannot tell."""
    orient = np.empty(len(tri), np.int8)
    convex = np.empty((len(tri), 3), np.int8)
    _local_signs(xyz, tri, twin_tri, twin_corner, orient, convex)
    for t in np.flatnonzero(orient == UNSURE):
        orient[t] = exact_sign("orient3d", np.vstack([xyz[tri[t]], np.zeros(3)]))
    for t, i in zip(*np.nonzero(convex == UNSURE), strict=True):
        d = tri[twin_tri[t, i], twin_corner[t, i]]
        convex[t, i] = exact_sign("orient3d", xyz[[*tri[t], d]])
    return int((orient <= 0).sum()), int((convex < 0).sum())


def _twins(tri, m):
    """For each (triangle, corner): the triangle across the opposite edge and its corner
    opposite that edge; None unless every directed edge has exactly one reversed twin."""
    t = len(tri)
    a = np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]]).astype(np.int64)
    b = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]]).astype(np.int64)
    start, order = grouped(a, m)  # the edges by tail
    twin = _edge_twins(b, start, order)
    if len(twin) == 0 or twin.min() < 0:
        return None if len(twin) else (np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64))
    return (twin % t).reshape(3, t).T.copy(), (twin // t).reshape(3, t).T.copy()


@kernel(entry=True, lazy=True)
def _edge_twins(b, start, order):
    """twin[e]: the directed edge b[e] -> a[e], found among the edges leaving b[e] (edges
    by tail a: vertex v's are order[start[v]:start[v + 1]], ``_rows.grouped``); -1 where
    there is none, and -1 everywhere where a directed edge is repeated (``_twins``: then no
    twin is exactly one)."""
    n = len(b)
    m = len(start) - 1
    twin = np.full(n, -1, np.int64)
    for v in range(m):
        for i in range(start[v], start[v + 1]):
            e = order[i]
            for j in range(i + 1, start[v + 1]):
                if b[order[j]] == b[e]:  # the edge v -> b[e] twice
                    twin[:] = -1
                    return twin
            w = b[e]
            for j in range(start[w], start[w + 1]):
                if b[order[j]] == v:
                    twin[e] = order[j]
                    break
    return twin


def _held_in_caps(xyz, tri, centres, chords, points, stop):
    """What each closed circumcap holds: the points on or above the plane of its corners,
    decided by the filtered orient3d (integers where it cannot tell) among the points
    within a ball a little larger than the cap (``CAP_CANDIDATES``); exact below ``stop``."""
    reach = np.sqrt(chords**2 * (1.0 + 1e-6) + CAP_CANDIDATES)
    tree = points.tree
    out, caps, members = tree.held_caps(centres, reach, xyz[tri], stop)
    if len(caps):
        above = np.array([exact_sign("orient3d", np.vstack([xyz[tri[q]], tree.pts[j]])) <= 0
                          for q, j in zip(caps, members, strict=True)])  # fmt: skip
        out = out + sums_by(caps[above], tree.weights_of(members[above]), len(tri))
    return out


# A cap's candidates: the points within its chord, squared, plus this (and a relative 1e-6):
# the points on or above the plane of a triangle's corners lie within |a - n|^2 +
# (|p|^2 - |a|^2) + O(ulp) of its computed centre n, the middle term 2^-50 at most for unit
# vectors as rounded (_engine/refine_sphere.py derives it); this is 2^10 times that.
CAP_CANDIDATES = 2.0**-40
# Points count for every Voronoi cell their squared chord to its vertex is within this of
# their nearest's: the unit vectors' rounding (|v|^2 = 1 +- 2^-52 each) makes the chord's
# bisector and the great circle's differ by that much (the engine's cells reach 2^-47 past).
CELL_TIES = 2.0**-50


def _degree(xyz, tri):
    """How many times the triangles, seen from the centre, cover the sphere: their solid
    angles (Van Oosterom and Strackee's formula) summed over 4 pi. A float sum deciding an
    integer: 1 for the hull's boundary, 2 or more for a surface wound round twice, whatever
    the rounding (each term is off by ulps, the margin is 2 pi)."""
    a, b, c = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    na, nb, nc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    den = (na * nb * nc + np.einsum("ij,ij->i", a, b) * nc + np.einsum("ij,ij->i", b, c) * na
           + np.einsum("ij,ij->i", c, a) * nb)  # fmt: skip
    return float(2.0 * np.arctan2(det, den).sum() / (4.0 * np.pi))


def _caps(xyz, tri):
    """(centres (t, 3) unit vectors, chords (t,), angular radii (t,)) of the triangles'
    circumcaps."""
    a, b, c = xyz[tri[:, 0]], xyz[tri[:, 1]], xyz[tri[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    chord = np.max([np.linalg.norm(n - p, axis=1) for p in (a, b, c)], axis=0)
    return n, chord, chord_to_angle(chord)


def check_triangulation(mesh):
    """(problems, returned-mesh problems): the triangulation's exact checks, and the
    vertices in degrees against the unit vectors."""
    problems, mesh_problems = [], []
    xyz = np.asarray(mesh.xyz, float)
    tri = np.asarray(mesh.triangles, np.int64)
    m = len(xyz)
    if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0:
        return [f"triangles have shape {tri.shape}, not (t, 3)"], mesh_problems
    if tri.min() < 0 or tri.max() >= m:
        return ["a triangle names a vertex that does not exist"], mesh_problems
    if len(tri) != 2 * m - 4:
        problems.append(f"{len(tri)} triangles over {m} vertices, not 2 m - 4 = {2 * m - 4}")
    unused = int((np.bincount(tri.ravel(), minlength=m) == 0).sum())
    if unused:
        problems.append(f"{unused} vertices are in no triangle")
    twins = _twins(tri, m)
    if twins is None:
        problems.append("an edge is not shared by exactly two triangles in opposite directions")
    else:
        orient, convex = _exact_edges(np.ascontiguousarray(xyz), np.ascontiguousarray(tri),
                                      twins[0], twins[1])  # fmt: skip
        if orient:
            problems.append(f"{orient} triangles are not counter-clockwise seen from outside")
        if convex:
            problems.append(f"{convex} edges are not locally Delaunay (a corner inside a cap)")
        if not orient:  # every triangle faces out: each covers its part of the sphere once
            degree = _degree(xyz, tri)
            if abs(degree - 1.0) > 0.25:
                problems.append(f"the triangles cover the sphere {degree:.3g} times, not once")
    norms = np.linalg.norm(xyz, axis=1)
    if np.abs(norms - 1.0).max(initial=0.0) > 1e-12:
        mesh_problems.append("the vertices' vectors are not unit vectors")
    if np.asarray(mesh.vertices).shape != (m, 2):
        mesh_problems.append("vertices and xyz differ in number")
    else:
        gap = np.abs(lonlat_of(xyz) - mesh.vertices)
        gap[:, 0] = np.minimum(gap[:, 0], 360.0 - gap[:, 0])  # -180 and 180 are one meridian
        gap[np.abs(mesh.vertices[:, 1]) == 90.0, 0] = 0.0  # at a pole any longitude is it
        if gap.max(initial=0.0) > 1e-9:
            mesh_problems.append(
                f"vertices (degrees) differ from their vectors by up to {gap.max():.3g} degrees"
            )
    return problems, mesh_problems


def checked_points(mesh, points, weights):
    """The points a mesh is certified against, checked to be the ones it was made from (as
    many, with weights exactly when it was refined with
    them), in the frame its ``Points`` take: (points, weights as float64 or None)."""
    unit = as_sphere_points(points)
    check_made_from(mesh.stats, len(unit), "certify a mesh against")
    return unit, weights_of_run(mesh.stats, len(unit), weights)


class Points:
    """The questions ``certify`` asks about the points, on the unit sphere: counts in caps
    (balls about unit vectors), d_{P,k} (an angle), cell tallies, from certify's own
    kd-tree over the unit vectors (``_tree.Tree``; weighted, those of positive weight)."""

    def __init__(self, mesh, unit, weights, workers):
        self.workers, self.k = workers, mesh.k
        self.n = len(unit)
        self.weighted = weights is not None
        self.total = self.n if weights is None else float(weights.sum())
        heavy = None if weights is None else weights > 0
        # built beside the mesh's checks, which come first; unweighted, the tree sorts
        # ``unit`` (``checked_points``' own copy) in place, and its points are the source
        # of the samples (keyed by coordinates: the same whatever their order)
        self.source = None if heavy is None else unit
        self.tree = Tree(unit if heavy is None else unit[heavy],
                         None if heavy is None else weights[heavy], None, workers,
                         background=True, scratch=True)  # fmt: skip

    def held(self, centres, angles, stop=np.inf):
        """What each closed cap (centre, angle) holds, inflated by a relative 1e-12; exact
        below ``stop``."""
        chord = angle_to_chord(np.asarray(angles, float)) * (1.0 + 1e-12)
        return self.tree.held(centres, chord, stop)

    def fewer(self, centres, angles, k, mostly=True):
        """Whether each closed cap (centre, angle), inflated as ``held``'s, holds less
        than weight k."""
        chord = angle_to_chord(np.asarray(angles, float)) * (1.0 + 1e-12)
        return self.tree.fewer(centres, chord, k, mostly=mostly)

    def cell_counts(self, cells, stop=np.inf):
        """What each vertex's closed Voronoi cell holds (``steps.Cells``): each point counts
        for every vertex as near as its nearest, up to the unit vectors' rounding
        (``CELL_TIES``); exact below ``stop``."""
        return cell_counts(self.tree, cells, stop)

    def d_pk(self, x):
        """d_{P,k} at unit vectors x, an angle (inf where P holds less than k)."""
        return self.kth(x, self.k)

    def kth(self, x, k):
        """d_{P,k} at unit vectors x, an angle (inf where P holds less than k)."""
        if self.total < k:
            return np.full(len(x), np.inf)
        return chord_to_angle(self.tree.kth(x, k))

    def sample_points(self, count, rng):
        """About ``count`` of the points' unit vectors, the same whatever their order
        (``_sampling``: those whose key is below count / n)."""
        source = self.tree.pts[: self.n] if self.source is None else self.source
        return key_sample(source, min(1.0, count / max(self.n, 1)))[0]


@kernel(entry=True, lazy=True, nogil=True)
def _solid_angles(xyz, tri):
    """The solid angle of each spherical triangle (its corners' unit vectors a, b, c):
    2 atan2(|a . (b x c)|, 1 + a . b + b . c + c . a) (Van Oosterom and Strackee), read
    where the corners are (no (t, 3) copies)."""
    out = np.empty(tri.shape[0])
    for t in range(tri.shape[0]):
        i, j, k = tri[t, 0], tri[t, 1], tri[t, 2]
        cx = xyz[j, 1] * xyz[k, 2] - xyz[j, 2] * xyz[k, 1]
        cy = xyz[j, 2] * xyz[k, 0] - xyz[j, 0] * xyz[k, 2]
        cz = xyz[j, 0] * xyz[k, 1] - xyz[j, 1] * xyz[k, 0]
        triple = abs(xyz[i, 0] * cx + xyz[i, 1] * cy + xyz[i, 2] * cz)
        ab = xyz[i, 0] * xyz[j, 0] + xyz[i, 1] * xyz[j, 1] + xyz[i, 2] * xyz[j, 2]
        bc = xyz[j, 0] * xyz[k, 0] + xyz[j, 1] * xyz[k, 1] + xyz[j, 2] * xyz[k, 2]
        ca = xyz[k, 0] * xyz[i, 0] + xyz[k, 1] * xyz[i, 1] + xyz[k, 2] * xyz[i, 2]
        out[t] = 2.0 * math.atan2(triple, 1.0 + ab + bc + ca)
    return out


def _spacing(vertices):
    """Each unit vector's great-circle distance to its nearest other one."""
    return chord_to_angle(cKDTree(vertices).query(vertices, k=2)[0][:, 1])


def _uniform_on_sphere(n, rng):
    x = rng.standard_normal((n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _floor_sites(sites, angle):
    """Floor elements within ``angle`` of each other grouped: [(lon, lat, count), ...]."""
    if len(sites) == 0:
        return []
    pairs = cKDTree(sites).query_pairs(angle_to_chord(angle), output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(sites), len(sites)))  # fmt: skip
    ncomp, label = connected_components(graph, directed=False)
    counts = np.bincount(label, minlength=ncomp)
    order = np.argsort(-counts, kind="stable")
    first = np.array([np.flatnonzero(label == c)[0] for c in order])
    where = lonlat_of(sites[first])
    return [(float(x[0]), float(x[1]), int(counts[c])) for x, c in zip(where, order, strict=True)]


class Geometry:
    """The sphere's questions about a mesh (``steps.run_checks`` asks them): its
    triangulation checked exactly on the unit vectors the user received, circumcaps
    counted exactly, probes over the sphere, d_{M,2} from the vertices, the size integral
    over the sphere, beta from the largest circumcap. Lengths are angles (radians)."""

    no_position = ()

    def __init__(self, mesh, workers):
        self.mesh, self.workers = mesh, workers
        self.floor = mesh.min_size / mesh.radius
        self.xyz = np.asarray(mesh.xyz, float)
        self.tri = np.asarray(mesh.triangles, np.int64)
        self._cells = None
        self._d_m2 = None
        self._returned = []  # the returned mesh's problems, found with the triangulation's

    def triangulation(self):
        """The exact checks (``check_triangulation``); the caps (centres, angles), R(v);
        ``extra``: the caps' chords."""
        problems, self._returned = check_triangulation(self.mesh)
        centres, chords, cap = _caps(self.xyz, self.tri)
        outradius = np.zeros(len(self.xyz))
        for j in range(3):
            np.maximum.at(outradius, self.tri[:, j], cap)
        return Triangulation(problems, centres, cap, outradius, chords)

    def returned_problems(self):
        return list(self._returned)

    def vertex_d_m2(self):
        """d_{M,2} at each vertex: the angle to its nearest other vertex, a Delaunay
        neighbour (the triangulation is checked first)."""
        if self._d_m2 is None:
            self._d_m2 = chord_to_angle(nearest_neighbour(self.cells(None)))
        return self._d_m2

    def cells(self, tri):
        """The Voronoi cells of the vertices: each one's neighbours across the triangles'
        edges (chords between unit vectors); a point counts for each vertex as near as its
        nearest up to the unit vectors' rounding (``CELL_TIES``). Worked out once."""
        if self._cells is not None:
            if tri is None:
                return self._cells
            walkable = not tri.problems and len(self.xyz) >= 4
            return self._cells._replace(outradii=angle_to_chord(tri.outradii), walkable=walkable)
        t = np.ascontiguousarray(self.tri, np.int64)
        m = len(self.xyz)
        first, nb, shift = neighbour_lists(t, np.zeros((len(t), 3, 0), np.int8), m, self.workers)
        # (shift (e, 0): the sites do not wrap) the cell lies within its outradius (an
        # angle) of the vertex: as a chord
        self._cells = Cells(self.xyz, first, shift, None, 2e-12, CELL_TIES, nb, np.zeros(3))
        return self.cells(tri)

    def held(self, points, tri, stop=np.inf):
        """Each closed circumcap's points, decided exactly (on or above the plane of its
        corners); the kd-tree's caps where there is no triangulation to count in (the
        verdict is FAILED already)."""
        if tri.problems:
            return points.held(tri.centres, tri.radii, stop)
        return _held_in_caps(self.xyz, self.tri, tri.centres, tri.extra, points, stop)

    def precondition(self, points, k, tau):
        initial = self.xyz[np.asarray(self.mesh.kinds) == 0]
        return check_precondition(initial, points, k, tau, spacing=_spacing)

    def probes(self, tri, points, samples, n_random, max_point_probes, rng):
        """Every vertex and edge midpoint (once each), the size integral's random points
        in the cells (``common.size_sample``: ``samples`` of them, at least one in each
        cell sampled), up to min(``max_point_probes``, 2 m) input points and ``n_random``
        uniform points of the domain (``steps.Probes``: why these)."""
        xyz, tri_ = self.xyz, self.tri
        t, m = len(tri_), len(xyz)
        chosen, dense = size_sample(t, samples, rng)
        cells = np.concatenate([chosen, dense])
        flat, _ = uniform_in_triangles((xyz, tri_), rng.random((len(cells), 2)), cells)  # flat
        # seen from the centre, the flat triangle's area element dA is the sphere's
        # h / |y|^3 dA (h: the plane's distance from the centre)
        s = len(chosen)
        a, b, c = (xyz[tri_[chosen, j]] for j in range(3))
        y = flat[:s]
        normal = np.cross(b - a, c - a)
        twice_area = np.linalg.norm(normal, axis=1)
        h = np.abs(np.einsum("ij,ij->i", normal, a)) / np.where(twice_area > 0, twice_area, 1.0)
        norm = np.linalg.norm(y, axis=1)
        weights = 0.5 * twice_area * h / np.maximum(norm, 1e-300) ** 3
        del a, b, c, normal, twice_area, h, norm
        solid = _solid_angles(xyz, np.ascontiguousarray(tri_))  # every cell's
        count = min(int(max_point_probes), 2 * m)
        sampled = points.sample_points(count, rng)  # (drawn in this order: the probes')
        uniform = _uniform_on_sphere(int(n_random), rng)
        parts, rows = probe_parts(y, sampled, xyz, self.vertex_d_m2(), self.cells(tri),
                                  lambda mids: mids, uniform, np.zeros(3), self.workers, tri,
                                  flat[s:], tri_[dense])  # fmt: skip
        probes = gathered_probes(parts, lambda x: np.ones(len(x), bool),
                                 SizeSample(None, weights, chosen, tri_, solid, t), 3,
                                 rows)  # fmt: skip
        x = probes.x  # on the sphere: unit vectors, a chunk at a time (no (n, 3) copies)
        for a in range(0, len(x), 1 << 16):
            part = x[a : a + (1 << 16)]
            np.divide(part, np.linalg.norm(part, axis=1, keepdims=True), out=part)
        return probes

    def release(self):
        """Drop the Voronoi cells and the vertices' tree (``steps.Geometry.release``)."""
        self._cells = None
        self.__dict__.pop("vtree", None)

    @cached_property
    def vtree(self):
        """A kd-tree over the vertices' unit vectors (built only where asked: d_{M,2} is
        walked on a verified triangulation)."""
        return Tree(self.xyz, None, None, self.workers)

    def returned_d_m2(self, x, tri):
        """d_{M,2} at x (unit vectors), an angle, from chords (``common.walked_d_m2``)."""
        chord = walked_d_m2(self.cells(None), x, np.zeros(3), self.workers, tri,
                            lambda: self.vtree)  # fmt: skip
        return chord_to_angle(chord), []

    def separation(self, x, rows, refs):
        """Angles from x[rows] to x[refs] (unit vectors; refs (r, w), NaN where -1):
        d_{P,k}'s metric (``common.separations``)."""
        return separations(x, rows, refs, self.workers)

    def size(self, probes, d_pk, points, rng):
        """The integral over the sphere of 1 / d_{P,k}^2 (d_{P,k} clipped at min_size) and
        its standard error (``common.size_integral``)."""
        return size_integral(probes.extra, d_pk, self.floor, 2)

    def constants(self, tri):
        return sphere_constants(self.mesh.tau, float(tri.radii.max(initial=0.0)))

    def floor_sites(self, centres, vertices):
        return _floor_sites(np.concatenate([centres, vertices]), 10.0 * max(self.floor, 1e-300))

    def to_input(self, x):
        return lonlat_of(x)
