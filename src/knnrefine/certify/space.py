"""``certify`` in three dimensions: every promise of a ``Mesh3`` checked without the engine's
refinement code (on the torus it refined, the box's own along periodic axes and the embedding
torus along the others; the bounds in the box's own metric).

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

import time
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..engine.jit import kernel  # numba's njit(cache=True), also on read-only installs
from ..engine.predicates3 import insphere, orient3d
from ..metric import TorusFrame
from ..validation import as_points, check_inside
from .common import check_precondition, check_source, find_rows


@dataclass
class Certificate3:
    """What certify measured in space. ``passed`` is True when every guarantee holds above
    the floor (as the plane's ``Certificate``)."""

    triangulation: bool
    view_matches_torus: bool
    orientation_failures: int
    delaunay_failures: int
    volume_ratio: float
    max_aspect: float
    max_circumball_count: int
    max_cell_count: int
    floor_circumballs: int
    floor_cells: int
    alpha_hat: float
    beta_hat: float
    alpha: float
    beta: float
    probes: int
    seconds: float
    k: int = 0
    tau: float = 0.0
    mesh_problems: list = field(default_factory=list)  # returned mesh vs the certified torus
    precondition_ok: bool = True  # Lemma 2's precondition on the initial vertices
    precondition_note: str = ""

    @property
    def passed(self):
        return bool(
            self.triangulation
            and self.view_matches_torus
            and not self.mesh_problems
            and self.precondition_ok
            and self.max_aspect <= self.tau * (1 + 1e-9)
            and self.max_circumball_count < self.k
            and self.max_cell_count < self.k
            and (np.isnan(self.alpha_hat) or self.alpha <= self.alpha_hat)
            and (np.isnan(self.beta_hat) or self.beta_hat <= self.beta)
        )

    def to_dict(self):
        d = asdict(self)
        d["passed"] = self.passed
        return d

    def __str__(self):
        verdict = "PASSED" if self.passed else "FAILED"
        ratio = (
            f"  d_M2 / d_Pk at {self.probes:,} probes in [{self.alpha_hat:.4f}, "
            f"{self.beta_hat:.4f}]; Theorem 6: [{self.alpha:.4f}, {self.beta:.2f}]"
            if self.probes
            else "  d_M2 / d_Pk: nothing measured: every probe lies where d_Pk < min_size"
        )
        return "\n".join([
            f"certify (3-D): {verdict} in {self.seconds:.2f} s",
            f"  tetrahedralisation exact: {self.triangulation} (orientation failures "
            f"{self.orientation_failures}, Delaunay failures {self.delaunay_failures}, "
            f"volume / torus {self.volume_ratio:.12f}); the box's copies match the torus: "
            f"{self.view_matches_torus}",
            "  returned mesh: the certified torus mesh, exactly, no repeated vertex: "
            + ("ok" if not self.mesh_problems else f"FAILED ({'; '.join(self.mesh_problems)})"),
            f"  initial mesh: Lemma 2's precondition: {'ok' if self.precondition_ok else 'FAILED'}"
            + (f" ({self.precondition_note})" if self.precondition_note else ""),
            f"  aspect max {self.max_aspect:.4f}; points in a circumball max "
            f"{self.max_circumball_count}, in a cell max {self.max_cell_count} (floor: "
            f"{self.floor_circumballs} circumballs, {self.floor_cells} cells)",
            ratio,
        ])  # fmt: skip


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
    _, inverse, counts = np.unique(np.concatenate(rows), axis=0, return_inverse=True,
                                   return_counts=True)  # fmt: skip
    if (counts != 2).any():
        return None
    order = np.argsort(inverse.ravel(), kind="stable")
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


def _rows_within(rows, table):
    """Whether each row of ``rows`` (sorted int64 rows) is a row of ``table``."""

    def as_void(a):
        a = np.ascontiguousarray(a, dtype=np.int64)
        return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()

    return np.isin(as_void(rows), as_void(table))


def _view_matches(mesh):
    """The mesh's own arrays are copies of its torus: each vertex a torus vertex moved by
    whole periods along non-periodic axes only (exactly), each tetrahedron a torus
    tetrahedron (``certify3`` adds: d_{M,2} from them equals the torus' in the box)."""
    if mesh.embedded is None:
        return True
    shift = (mesh.local - mesh.torus.local[mesh.order]) / np.asarray(mesh.period)
    per = np.array(mesh.periodic)
    if not ((shift == np.rint(shift)).all() and (shift[:, per] == 0).all()):
        return False
    view = np.sort(mesh.order[mesh.tetrahedra], axis=1)
    return bool(_rows_within(view, np.sort(mesh.torus.tetrahedra, axis=1)).all())


class _Points:
    """The input points on the torus, as ``certify.check_precondition`` asks about them."""

    def __init__(self, tree, n):
        self.tree, self.total = tree, float(n)

    def held(self, centres, radii):
        return self.tree.query_ball_point(centres, radii, return_length=True)


def _parity(rows):
    """The parity (0 even, 1 odd) of the permutation that sorts each row of 4."""
    inversions = np.zeros(len(rows), np.int64)
    for i in range(4):
        for j in range(i + 1, 4):
            inversions += rows[:, i] > rows[:, j]
    return inversions % 2


def verify_returned_mesh3(mesh):
    """Problems (a list of strings) that stop what the user works with, ``vertices`` (input
    coordinates), ``tetrahedra`` with ``offsets`` and ``local``, from being, exactly and
    without repeated vertices, copies of the torus mesh that certify checks: each vertex a
    torus vertex moved by whole periods, each tetrahedron a torus tetrahedron (the same
    corners, the same orientation) moved by whole periods."""
    torus = mesh.torus
    v = np.asarray(mesh.vertices, float)
    if v.ndim != 2 or v.shape[1] != 3 or not np.isfinite(v).all():
        return ["vertices are not finite (m, 3) coordinates"]
    problems = []
    repeated = len(v) - len(np.unique(v, axis=0))
    if repeated:
        problems.append(f"{repeated} repeated vertices")
    origin, period = np.asarray(mesh.origin, float), np.asarray(mesh.period, float)
    tl = np.asarray(torus.local, float)
    order = np.asarray(mesh.order)
    local = np.asarray(mesh.local, float)
    if (
        len(order) != len(v) or local.shape != v.shape
        or order.min(initial=0) < 0 or order.max(initial=0) >= len(tl)
    ):  # fmt: skip
        return problems + ["vertex order does not index the torus vertices"]
    shift = np.rint((v - origin - tl[order]) / period)
    off = np.any(v != origin + (tl[order] + shift * period), axis=1)
    if off.any():
        problems.append(f"{int(off.sum())} vertices differ from their torus vertex")
    moved = np.rint((local - tl[order]) / period)
    if np.any(local != tl[order] + moved * period) or np.any(moved[:, np.array(mesh.periodic)]):
        problems.append("local coordinates differ from the torus vertices")
    tet = np.asarray(mesh.tetrahedra, np.int64)
    if tet.ndim != 2 or tet.shape[1] != 4 or tet.min(initial=0) < 0 or tet.max(initial=0) >= len(v):
        return problems + ["tetrahedra do not index the vertices"]
    offsets = (
        np.zeros(tet.shape + (3,)) if mesh.offsets is None else np.asarray(mesh.offsets, float)
    )
    user = v[tet] + offsets * period - origin  # corners in the torus frame, unwrapped
    ids = order[tet]
    ttet = np.asarray(torus.tetrahedra, np.int64)
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
    _, first = np.unique(key, axis=0, return_index=True)
    a, b, d = a[first], b[first], d[first]
    return local[a] + 0.5 * (local[b] + d * period - local[a])


def _tetrahedron_samples(c, per, rng):
    """per uniform points in each tetrahedron with corners c (t, 4, 3): barycentric
    weights from a flat Dirichlet (normalised exponentials)."""
    w = rng.exponential(size=(len(c), per, 4))
    w /= w.sum(axis=2, keepdims=True)
    return np.einsum("tpi,tia->tpa", w, c).reshape(-1, 3)


def certify3(mesh, points, *, samples=100_000, n_random=20_000, max_point_probes=100_000,
             seed=0, workers=-1):  # fmt: skip
    """Check ``mesh`` (from ``knnrefine.refine`` with (n, 3) points) against ``points``;
    returns a ``Certificate3`` (nothing is raised when a check fails: see ``.passed``).

    The torus mesh (``mesh.torus``: the box's own along periodic axes, the embedding torus
    along the others) is checked as refined: exact tetrahedralisation, counts, aspect and
    Lemma 2's precondition on the torus. What the user received is checked to be that mesh
    (``verify_returned_mesh3``), and the promise the user reads is checked in the box's own
    metric (straight along non-periodic axes, so the embedding's claim is tested, not
    assumed): d_{P,k} from the points, d_{M,2} from the returned vertices, at probes in the
    box: ``samples`` stratified points in the tetrahedra (at least 4 in each), every vertex,
    circumcentre and edge midpoint, up to ``max_point_probes`` input points and ``n_random``
    uniform points. ``workers``: the kd-tree queries' threads (-1: all cores)."""
    t0 = time.perf_counter()
    pts = as_points(points, 3)
    check_source(mesh.stats, len(pts), None)
    check_inside(pts, mesh.box, mesh.periodic, warn=False)
    period = np.asarray(mesh.period, float)
    torus = mesh.torus
    p = TorusFrame(mesh.origin, period)(pts)
    k = mesh.k
    corners, offsets, local = torus.tetrahedra, torus.offsets.astype(np.int64), torus.local
    neighbours = _neighbours(corners, offsets)
    ok_faces = neighbours is not None
    bad_o = bad_d = -1
    if ok_faces:
        bad_o, bad_d = _exact_faces(local, corners.astype(np.int64), offsets, neighbours, period)
    c = local[corners] + offsets * period
    volume = np.abs(np.linalg.det(c[:, 1:] - c[:, :1])).sum() / 6.0 / np.prod(period)
    view = _view_matches(mesh)
    triangulation = ok_faces and bad_o == 0 and bad_d == 0 and abs(volume - 1.0) < 1e-9

    centres, r2 = _circumspheres(c)
    point_tree = cKDTree(p, boxsize=period)
    held = point_tree.query_ball_point(np.mod(centres, period), np.sqrt(r2), return_length=True,
                                       workers=workers)  # fmt: skip
    vertex_tree = cKDTree(local, boxsize=period)
    dd, ii = vertex_tree.query(p, k=min(3, len(local)), workers=workers)
    dd, ii = dd.reshape(len(p), -1), ii.reshape(len(p), -1)
    tie = dd <= dd[:, :1] * (1 + 1e-12)
    cells = np.bincount(ii[tie], minlength=len(local))
    outer = np.zeros(len(local))
    np.maximum.at(outer, corners.ravel(), np.repeat(r2, 4))
    # elements below the resolution floor may hold k points (refinement leaves them)
    floor_balls = (held >= k) & (np.sqrt(r2) < mesh.min_size)
    floor_cells = (cells >= k) & (np.sqrt(outer) < mesh.min_size)
    max_held = int(held[~floor_balls].max(initial=0))
    max_cell = int(cells[~floor_cells].max(initial=0))
    d_m2 = vertex_tree.query(local, k=2, workers=workers)[0][:, 1]
    aspect = float((2.0 * np.sqrt(outer) / d_m2).max())
    precondition = check_precondition(
        local[np.asarray(torus.kinds) == 0], _Points(point_tree, len(p)), k, mesh.tau, period
    )

    # the promise in the box, in its own metric, from the returned vertices
    rng = np.random.default_rng(seed)
    per_tetrahedron = max(4, -(-int(samples) // max(len(c), 1)))
    lo = np.array(mesh.box[:3]) - np.asarray(mesh.origin)
    side = np.array(mesh.box[3:]) - np.array(mesh.box[:3])
    probes = np.concatenate([
        np.mod(_tetrahedron_samples(c, per_tetrahedron, rng), period),
        lo + rng.random((n_random, 3)) * side, local, np.mod(centres, period),
        np.mod(_edge_midpoints(local, corners, offsets, period), period),
        p[rng.choice(len(p), min(len(p), max_point_probes), replace=False)],
    ])  # fmt: skip
    del c
    probes = probes[mesh.inside(probes)]
    mesh_problems = verify_returned_mesh3(mesh)
    returned = np.asarray(mesh.vertices, float)
    if returned.ndim == 2 and returned.shape[1] == 3 and np.isfinite(returned).all():
        returned = mesh.wrap(returned)  # relative to the origin, periodic axes wrapped
    else:  # not coordinates at all (a failed check already): the torus' own, for the ratio
        returned = local
    box_boxsize = np.where(mesh.periodic, period, 0.0) if any(mesh.periodic) else None
    if all(mesh.periodic):
        box_points = point_tree
    else:
        box_points = mesh.metric.tree(pts)
    box_vertices = cKDTree(returned, boxsize=box_boxsize)
    dm2 = box_vertices.query(probes, k=min(2, len(returned)), workers=workers)[0]
    dm2 = dm2[:, 1] if dm2.ndim == 2 else np.full(len(probes), np.inf)
    if view and not mesh_problems:  # the copies near the box hold its two nearest
        on_torus = vertex_tree.query(probes, k=2, workers=workers)[0][:, 1]  # wraps queries
        view = bool(np.allclose(dm2, on_torus, rtol=1e-12, atol=0.0))
    dpk = box_points.query(probes, k=[k], workers=workers)[0][:, 0]
    use = dpk >= mesh.min_size
    ratio = dm2[use] / dpk[use]
    alpha_hat = float(ratio.min()) if len(ratio) else float("nan")
    beta_hat = float(ratio.max()) if len(ratio) else float("nan")
    return Certificate3(
        triangulation=bool(triangulation), view_matches_torus=bool(view),
        orientation_failures=int(bad_o), delaunay_failures=int(bad_d),
        volume_ratio=float(volume), max_aspect=aspect,
        max_circumball_count=max_held, max_cell_count=max_cell,
        floor_circumballs=int(floor_balls.sum()), floor_cells=int(floor_cells.sum()),
        alpha_hat=alpha_hat, beta_hat=beta_hat, alpha=mesh.alpha, beta=mesh.beta,
        probes=int(use.sum()), seconds=time.perf_counter() - t0, k=k, tau=mesh.tau,
        mesh_problems=mesh_problems, precondition_ok=bool(precondition[0]),
        precondition_note=precondition[1],
    )  # fmt: skip
