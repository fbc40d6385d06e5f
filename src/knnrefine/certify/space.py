"""``certify`` in three dimensions: every promise of a ``Mesh`` in space checked without the
engine's refinement code (on the torus it refined, the box's own along periodic axes and the
embedding torus along the others; the bounds in the box's own metric).

The tetrahedralisation is checked exactly in the mesh's own frame (vertices relative to the
box's corner, exact): its faces are matched again from the corners and offsets, every
tetrahedron is positively oriented and locally Delaunay (the exact predicates of
``engine/predicates3.py``, themselves tested against rational arithmetic), and the volumes
add up to the torus' once. Counts come from scipy's cKDTree with the box as its periods:
points in every closed circumball and in every closed Voronoi cell (each point counting for
every vertex as near as its nearest), below k except for elements smaller than the
resolution floor (``min_size``: counted and reported). Aspect 2 R(v) / d_{M,2}(v) from
circumradii computed here and the vertices' own kd-tree. Lemma 2's precondition on the
initial vertices, as in the plane (``certify.check_precondition``). What the user received
(``vertices``, ``tetrahedra``, ``offsets``, ``local``) must be, exactly and without a repeated
vertex, copies of the torus mesh. The achieved constants: d_{M,2}, from the returned
vertices, over d_{P,k} at probes as dense as the plane's (stratified samples in every
tetrahedron, every vertex, circumcentre and edge midpoint, input points, uniform points of
the box), whose extremes alpha_hat and beta_hat must lie within [alpha, beta] where
d_{P,k} >= min_size.
"""

import math
import time

import numpy as np
from scipy.spatial import cKDTree

from ..engine.jit import kernel  # numba's njit(cache=True), also on read-only installs
from ..engine.predicates3 import insphere, orient3d
from ..mesh import theorem6_constants
from ..metric import BoxMetric, TorusFrame, cell_tally, held_in_balls, weighted_kth
from ..validation import as_points
from .certificate import Certificate, floor_sites, to_input
from .common import (
    cell_array_problem,
    check_cells_tile,
    check_points_are_the_meshs,
    check_precondition,
    find_rows,
    sorted_rows,
)


@kernel(entry=True, lazy=True)
def _exact_faces(local, corners, offsets, neighbours, period):
    """(tetrahedra not positively oriented, faces not locally Delaunay)."""
    bad_orient = 0
    bad_delaunay = 0
    pts = np.empty((5, 3))
    for t in range(corners.shape[0]):
        for i in range(4):
            for a in range(3):
                pts[i, a] = local[corners[t, i], a] + offsets[t, i, a] * period[a]
        if orient3d(pts) <= 0:
            bad_orient += 1
        for i in range(4):
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
                pts[4, a] = local[corners[n, jj], a] + (offsets[n, jj, a] + s) * period[a]
            if insphere(pts) > 0:
                bad_delaunay += 1
    return bad_orient, bad_delaunay


def _neighbours(corners, offsets):
    """The tetrahedron across each face, from face keys (sorted vertices and their offsets
    relative to each other); None unless every face is shared by exactly two."""
    t = len(corners)
    rows = []
    for i in range(4):
        other = [j for j in range(4) if j != i]
        v = corners[:, other].astype(np.int64)
        o = offsets[:, other].astype(np.int64)
        o -= o.min(axis=1, keepdims=True)
        order = np.argsort(v, axis=1)
        rows.append(
            np.concatenate(
                [np.take_along_axis(v, order, 1),
                 np.take_along_axis(o, order[..., None], 1).reshape(t, 9)], axis=1,
            )
        )  # fmt: skip
    order, same = sorted_rows(np.concatenate(rows))
    # every face exactly twice: the sorted keys come in equal pairs, unequal between pairs
    if len(order) % 2 or not same[0::2].all() or same[1::2].any():
        return None
    out = np.empty(4 * t, np.int64)
    out[order[0::2]] = order[1::2] % t
    out[order[1::2]] = order[0::2] % t
    return out.reshape(4, t).T


def _circumspheres(c):
    """(centres (t, 3), squared radii) of the tetrahedra with corners c (t, 4, 3)."""
    a = c[:, 0]
    m = c[:, 1:] - a[:, None]
    rhs = 0.5 * (m**2).sum(axis=2)
    u = np.linalg.solve(m, rhs[..., None])[..., 0]
    return a + u, (u**2).sum(axis=1)


class SpacePoints:
    """Every question certify asks about the input points in space, answered in this process
    from scipy's kd-trees (``scale.checks.TiledSpacePoints`` asks the same where the points
    are): what closed balls of the torus hold (``held``: a count, or a weight), what each
    vertex's closed Voronoi cell holds (``cell_counts``), d_{P,k} at probes in the box's own
    metric (``d_pk``; weighted: the least radius holding weight k), and some of the points
    (``sample_points``), all in the frame of the mesh's torus."""

    def __init__(self, mesh, pts, weights, threads):
        torus = mesh.torus
        self.origin = np.asarray(torus.origin, float)
        self.period = np.asarray(torus.period, float)
        self.points = TorusFrame(self.origin, self.period)(pts)
        self.tree = cKDTree(self.points, boxsize=self.period)
        self.weights, self.threads, self.k, self.n = weights, threads, mesh.k, len(pts)
        self.weighted = weights is not None
        self.total = float(len(pts)) if weights is None else math.fsum(weights)
        self.metric = BoxMetric((*self.origin, *(self.origin + self.period)), mesh.periodic)
        self._box_tree = self.tree if all(mesh.periodic) else self.metric.tree(pts)

    def held(self, centres, radii):
        return held_in_balls(self.tree, self.weights, centres, radii, self.threads)

    def cell_counts(self, vertices, outradii):
        """What the closed Voronoi cell of each vertex (torus frame) holds: every point
        counts for each vertex as near as its nearest (``metric.cell_tally``)."""
        tree = cKDTree(vertices, boxsize=self.period)
        dd, ii = tree.query(self.points, k=min(3, len(vertices)), workers=self.threads)
        return cell_tally(dd, ii, self.weights, len(vertices))

    def d_pk(self, x):
        """d_{P,k} at x (the torus frame, periodic axes wrapped) in the box's own metric:
        straight along non-periodic axes, so the embedding's claim is tested."""
        if self.weights is None:
            return self._box_tree.query(x, k=[self.k], workers=self.threads)[0][:, 0]
        return weighted_kth(self._box_tree, self.weights, x, self.k, self.threads)

    def sample_points(self, count, rng):
        """Up to ``count`` input points (torus frame), drawn at random."""
        P = self.points
        return P if len(P) <= count else P[rng.choice(len(P), count, replace=False)]


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
    repeated = len(v) - len(np.unique(v, axis=0))
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
    problems += check_cells_tile(mesh)
    tet = np.asarray(mesh.cells, np.int64)
    offsets = (
        np.zeros(tet.shape + (3,)) if mesh.offsets is None else np.asarray(mesh.offsets, float)
    )
    user = v[tet] + offsets * period - origin  # corners in the torus frame, unwrapped
    ids = order[tet]
    ttet = np.asarray(torus.cells, np.int64)
    tcorners = tl[ttet] + np.asarray(torus.offsets, float) * period
    u_sort, t_sort = np.argsort(ids, axis=1), np.argsort(ttet, axis=1)
    u_key = np.take_along_axis(ids, u_sort, 1)
    t_key = np.take_along_axis(ttet, t_sort, 1)
    pos = find_rows(t_key, u_key)
    hit = pos >= 0
    if (~hit).any():
        problems.append(f"{int((~hit).sum())} tetrahedra are not tetrahedra of the torus mesh")
    t = pos[hit]
    mine = np.take_along_axis(user[hit], u_sort[hit][..., None], 1)
    target = np.take_along_axis(tcorners[t], t_sort[t][..., None], 1)
    d = np.rint((mine - target) / period)
    same = np.all(d == d[:, :1], axis=(1, 2)) & np.all(
        mine == target + d * period, axis=(1, 2)
    )  # fmt: skip
    same &= _parity(ids[hit]) == _parity(ttet[t])
    if (~same).any():
        problems.append(f"{int((~same).sum())} tetrahedra have corners off their torus tetrahedron")
    return problems


def _edge_midpoints(local, corners, offsets, period):
    """The midpoint of every edge of the torus mesh, once (edges keyed by their two
    vertices and the periods between them)."""
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    a = np.concatenate([corners[:, i] for i, _ in pairs]).astype(np.int64)
    b = np.concatenate([corners[:, j] for _, j in pairs]).astype(np.int64)
    d = np.concatenate([offsets[:, j] - offsets[:, i] for i, j in pairs]).astype(np.int64)
    flip = a > b
    key = np.column_stack([np.where(flip, b, a), np.where(flip, a, b),
                           np.where(flip[:, None], -d, d)])  # fmt: skip
    by, same = sorted_rows(key)
    first = by[np.concatenate([[True], ~same])]  # each key's first row, in the keys' order
    a, b, d = a[first], b[first], d[first]
    return local[a] + 0.5 * (local[b] + d * period - local[a])


def _tetrahedron_samples(c, per, rng):
    """per uniform points in each tetrahedron with corners c (t, 4, 3): barycentric
    weights from a flat Dirichlet (normalised exponentials)."""
    w = rng.exponential(size=(len(c), per, 4))
    w /= w.sum(axis=2, keepdims=True)
    return np.einsum("tpi,tia->tpa", w, c).reshape(-1, 3)


def certify3(mesh, points, *, samples=100_000, n_random=20_000, max_point_probes=100_000,
             seed=0, weights=None, threads=-1):  # fmt: skip
    """``certify`` in space in this process (``run_checks3`` on ``SpacePoints``)."""
    t0 = time.perf_counter()
    pts = as_points(points, 3)
    weights = check_points_are_the_meshs(mesh, pts, weights)
    return run_checks3(mesh, SpacePoints(mesh, pts, weights, threads), samples=samples,
                       n_random=n_random, max_point_probes=max_point_probes, seed=seed,
                       threads=threads, t0=t0)  # fmt: skip


def run_checks3(mesh, points, *, samples, n_random, max_point_probes, seed, threads, t0):
    """Check ``mesh`` (from ``knnrefine.refine`` with (n, 3) points) against ``points``;
    returns a ``Certificate`` (nothing is raised when a check fails: see ``.passed``).

    The torus mesh (``mesh.torus``: the box's own along periodic axes, the embedding torus
    along the others) is checked as refined: exact tetrahedralisation, counts, aspect and
    Lemma 2's precondition on the torus. What the user received is checked to be that mesh
    (``verify_returned_mesh3``), and the promise the user reads is checked in the box's own
    metric (straight along non-periodic axes, so the embedding's claim is tested, not
    assumed): d_{P,k} from the points, d_{M,2} from the returned vertices, at probes in the
    box: ``samples`` stratified points in the tetrahedra (at least 4 in each), every vertex,
    circumcentre and edge midpoint, up to ``max_point_probes`` input points and ``n_random``
    uniform points. ``points`` answers every question about the input points
    (``SpacePoints`` here, ``scale.checks.TiledSpacePoints`` where they are spread over
    workers); with weights counts are sums of weights and d_{P,k} the least radius holding
    weight k. ``threads``: the kd-tree queries' threads (-1: all cores)."""
    torus = mesh.torus
    origin, period = np.asarray(torus.origin, float), np.asarray(torus.period, float)
    metric = BoxMetric((*origin, *(origin + period)), mesh.periodic)  # the torus' frame
    k = mesh.k
    corners, offsets, local = torus.cells, torus.offsets.astype(np.int64), torus.vertices
    neighbours = _neighbours(corners, offsets)
    ok_faces = neighbours is not None
    bad_o = bad_d = -1
    if ok_faces:
        bad_o, bad_d = _exact_faces(local, corners.astype(np.int64), offsets, neighbours, period)
    c = local[corners] + offsets * period
    volume = np.abs(np.linalg.det(c[:, 1:] - c[:, :1])).sum() / 6.0 / np.prod(period)
    triangulation = ok_faces and bad_o == 0 and bad_d == 0 and abs(volume - 1.0) < 1e-9

    centres, r2 = _circumspheres(c)
    held = points.held(np.mod(centres, period), np.sqrt(r2))
    vertex_tree = cKDTree(local, boxsize=period)
    outer = np.zeros(len(local))
    np.maximum.at(outer, corners.ravel(), np.repeat(r2, 4))
    cells = points.cell_counts(local, np.sqrt(outer))
    # elements below the resolution floor may hold k points (refinement leaves them)
    floor_balls = (held >= k) & (np.sqrt(r2) < mesh.min_size)
    floor_cells = (cells >= k) & (np.sqrt(outer) < mesh.min_size)
    exact = float if points.weighted else int
    max_held = exact(held[~floor_balls].max(initial=0))
    max_cell = exact(cells[~floor_cells].max(initial=0))
    d_m2 = vertex_tree.query(local, k=2, workers=threads)[0][:, 1]
    aspect = float((2.0 * np.sqrt(outer) / d_m2).max())
    precondition = check_precondition(
        local[np.asarray(torus.kinds) == 0], points, k, mesh.tau, period
    )

    # the promise in the box, in its own metric, from the returned vertices
    rng = np.random.default_rng(seed)
    per_tetrahedron = max(4, -(-int(samples) // max(len(c), 1)))
    lo = np.array(mesh.box[:3]) - origin
    hi = np.array(mesh.box[3:]) - origin
    side = np.array(mesh.box[3:]) - np.array(mesh.box[:3])
    samples_at = np.mod(_tetrahedron_samples(c, per_tetrahedron, rng), period)
    sample_weight = np.repeat(
        np.abs(np.linalg.det(c[:, 1:] - c[:, :1])) / 6.0 / per_tetrahedron, per_tetrahedron
    )
    point_probes_at = points.sample_points(max_point_probes, rng)
    probes = np.concatenate([
        samples_at, lo + rng.random((n_random, 3)) * side, local, np.mod(centres, period),
        np.mod(_edge_midpoints(local, corners, offsets, period), period), point_probes_at,
    ])  # fmt: skip
    del c
    free = ~np.array(mesh.periodic)
    in_box = (((probes >= lo) & (probes <= hi)) | ~free).all(axis=1)
    sample_in_box = in_box[: len(samples_at)]
    point_probes = np.zeros(len(probes), bool)
    point_probes[len(probes) - len(point_probes_at) :] = True
    probes, point_probes = probes[in_box], point_probes[in_box]
    mesh_problems = verify_returned_mesh3(mesh)
    returned = np.asarray(mesh.vertices, float)
    coordinates = returned.ndim == 2 and returned.shape[1] == 3 and np.isfinite(returned).all()
    if coordinates:
        returned = metric.frame(returned)  # relative to the origin, periodic axes wrapped
    else:  # not coordinates at all (a failed check already): the torus' own, for the ratio
        returned = local
    box_boxsize = np.where(mesh.periodic, period, 0.0) if any(mesh.periodic) else None
    box_vertices = cKDTree(returned, boxsize=box_boxsize)
    dm2 = box_vertices.query(probes, k=min(2, len(returned)), workers=threads)[0]
    dm2 = dm2[:, 1] if dm2.ndim == 2 else np.full(len(probes), np.inf)
    if coordinates and len(returned) >= 2:  # the copies near the box hold its two nearest
        on_torus = vertex_tree.query(probes, k=2, workers=threads)[0][:, 1]  # wraps queries
        if not np.allclose(dm2, on_torus, rtol=1e-12, atol=0.0):
            mesh_problems.append(
                "d_M2 from the returned vertices differs from the torus mesh's in the box"
            )
    dpk = points.d_pk(probes)
    use = dpk >= mesh.min_size
    ratio = dm2[use] / dpk[use]
    nan = float("nan")
    alpha_hat = beta_hat = nan
    alpha_hat_at = beta_hat_at = (nan, nan, nan)
    if len(ratio):
        i, j = int(np.argmin(ratio)), int(np.argmax(ratio))
        alpha_hat, beta_hat = float(ratio[i]), float(ratio[j])
        at = to_input(probes[use][[i, j]], origin, mesh)
        alpha_hat_at, beta_hat_at = (tuple(float(v) for v in x) for x in at)
    # the integral of 1 / d_Pk^3 over the box, stratified over the tetrahedra (d_Pk clipped
    # at min_size), with its standard error
    f = np.zeros(len(samples_at))
    f[sample_in_box] = 1.0 / np.maximum(dpk[: int(sample_in_box.sum())], mesh.min_size) ** 3
    per_tet = (sample_weight * f).reshape(len(corners), -1)
    size = float(per_tet.sum())
    stderr = (
        float(np.sqrt((per_tet.var(axis=1, ddof=1) * per_tet.shape[1]).sum()))
        if per_tet.shape[1] > 1
        else 0.0
    )
    problems = []
    if not ok_faces:
        problems.append("the tetrahedra's faces do not pair up")
    if bad_o > 0:
        problems.append(f"{bad_o} tetrahedra not positively oriented")
    if bad_d > 0:
        problems.append(f"{bad_d} faces not locally Delaunay")
    if abs(volume - 1.0) >= 1e-9:
        problems.append(f"the volumes add up to {volume:.12g} tori")
    alpha, beta = theorem6_constants(mesh.tau)
    point_dpk = dpk[point_probes]
    sites = floor_sites(
        np.concatenate([np.mod(centres[floor_balls], period), local[floor_cells]]),
        10.0 * max(mesh.min_size, 1e-300), period, origin, mesh,
    )  # fmt: skip
    return Certificate(
        n=points.n, m=len(mesh.vertices), k=k, tau=mesh.tau, periodic=tuple(mesh.periodic),
        box=tuple(mesh.box), min_size=mesh.min_size, triangulation_ok=triangulation,
        triangulation_problems=problems, max_aspect=aspect, max_cell_count=max_cell,
        max_ball_count=max_held, alpha=alpha, beta=beta, alpha_hat=alpha_hat,
        beta_hat=beta_hat, alpha_hat_at=alpha_hat_at, beta_hat_at=beta_hat_at,
        n_probes=int(use.sum()), size_integral=size, size_integral_stderr=stderr,
        size_ratio=len(mesh.vertices) / size if size > 0 else nan,
        floor_circumballs=int(floor_balls.sum()), floor_cells=int(floor_cells.sum()),
        floor_sites=sites,
        under_floor=float(np.mean(point_dpk < mesh.min_size)) if len(point_dpk) else 0.0,
        mesh_problems=mesh_problems, precondition_ok=bool(precondition[0]),
        precondition_note=precondition[1], seconds=time.perf_counter() - t0,
        weight=points.total if points.weighted else None,
        count_slack=4.0 * float(np.spacing(float(k))) if points.weighted else 0.0,
    )  # fmt: skip
