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
circumradii computed here and the vertices' own kd-tree. The achieved constants:
d_{M,2} / d_{P,k} at probes (uniform random points, every vertex and circumcentre, input
points), whose extremes alpha_hat and beta_hat must lie within [alpha, beta] where
d_{P,k} >= min_size.
"""

import time
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .certify import check_source
from .engine.predicates3 import insphere, orient3d
from .metric import TorusFrame
from .validation import as_points, check_inside


@dataclass
class Certificate3:
    passed: bool
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

    def to_dict(self):
        return asdict(self)

    def __str__(self):
        verdict = "PASSED" if self.passed else "FAILED"
        return "\n".join([
            f"certify (3-D): {verdict} in {self.seconds:.2f} s",
            f"  tetrahedralisation exact: {self.triangulation} (orientation failures "
            f"{self.orientation_failures}, Delaunay failures {self.delaunay_failures}, "
            f"volume / torus {self.volume_ratio:.12f}); the box's copies match the torus: "
            f"{self.view_matches_torus}",
            f"  aspect max {self.max_aspect:.4f}; points in a circumball max "
            f"{self.max_circumball_count}, in a cell max {self.max_cell_count} (floor: "
            f"{self.floor_circumballs} circumballs, {self.floor_cells} cells)",
            f"  d_M2 / d_Pk at {self.probes:,} probes in [{self.alpha_hat:.4f}, "
            f"{self.beta_hat:.4f}]; Theorem 6: [{self.alpha:.4f}, {self.beta:.2f}]",
        ])  # fmt: skip


@njit(cache=True)
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


def certify3(mesh, points, *, n_random=20_000, max_point_probes=100_000, seed=0):
    """Check ``mesh`` (from ``knnrefine.refine`` with (n, 3) points) against ``points``;
    returns a ``Certificate3`` (nothing is raised when a check fails: see ``.passed``).

    The torus mesh (``mesh.torus``: the box's own along periodic axes, the embedding torus
    along the others) is checked as refined: exact tetrahedralisation, counts and aspect on
    the torus. The promise the user reads is checked in the box's own metric (straight along
    non-periodic axes, so the embedding's claim is tested, not assumed): d_{P,k} from the
    points, d_{M,2} from the mesh's vertices as returned, at probes in the box."""
    t0 = time.perf_counter()
    pts = as_points(points, 3)
    check_source(mesh.stats, len(pts), None)
    check_inside(pts, mesh.box, mesh.periodic)
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
    del c
    point_tree = cKDTree(p, boxsize=period)
    held = point_tree.query_ball_point(np.mod(centres, period), np.sqrt(r2), return_length=True)
    vertex_tree = cKDTree(local, boxsize=period)
    dd, ii = vertex_tree.query(p, k=min(3, len(local)))
    tie = dd <= dd[:, :1] * (1 + 1e-12)
    cells = np.bincount(ii[tie], minlength=len(local))
    outer = np.zeros(len(local))
    np.maximum.at(outer, corners.ravel(), np.repeat(r2, 4))
    # elements below the resolution floor may hold k points (refinement leaves them)
    floor_balls = (held >= k) & (np.sqrt(r2) < mesh.min_size)
    floor_cells = (cells >= k) & (np.sqrt(outer) < mesh.min_size)
    max_held = int(held[~floor_balls].max(initial=0))
    max_cell = int(cells[~floor_cells].max(initial=0))
    d_m2 = vertex_tree.query(local, k=2)[0][:, 1]
    aspect = float((2.0 * np.sqrt(outer) / d_m2).max())

    # the promise in the box, in its own metric, from the returned vertices
    rng = np.random.default_rng(seed)
    lo = np.array(mesh.box[:3]) - np.asarray(mesh.origin)
    side = np.array(mesh.box[3:]) - np.array(mesh.box[:3])
    probes = np.concatenate([
        lo + rng.random((n_random, 3)) * side, mesh.local, np.mod(centres, period),
        p[rng.choice(len(p), min(len(p), max_point_probes), replace=False)],
    ])  # fmt: skip
    probes = probes[mesh.inside(probes)]
    if all(mesh.periodic):
        box_points, box_vertices = point_tree, vertex_tree
    else:
        box_points = mesh.metric.tree(pts)
        box_vertices = cKDTree(mesh.local, boxsize=np.where(mesh.periodic, period, 0.0))
    dm2 = box_vertices.query(probes, k=2)[0][:, 1]
    if box_vertices is not vertex_tree:  # the copies near the box hold its two nearest
        on_torus = vertex_tree.query(probes, k=2)[0][:, 1]  # the tree wraps queries
        view = view and bool(np.allclose(dm2, on_torus, rtol=1e-12, atol=0.0))
    dpk = box_points.query(probes, k=[k])[0][:, 0]
    use = dpk >= mesh.min_size
    ratio = dm2[use] / dpk[use]
    alpha_hat, beta_hat = float(ratio.min()), float(ratio.max())
    passed = (
        triangulation and view and aspect <= mesh.tau * (1 + 1e-9) and max_held < k
        and max_cell < k and alpha_hat >= mesh.alpha and beta_hat <= mesh.beta
    )  # fmt: skip
    return Certificate3(
        passed=bool(passed), triangulation=bool(triangulation), view_matches_torus=bool(view),
        orientation_failures=int(bad_o), delaunay_failures=int(bad_d),
        volume_ratio=float(volume), max_aspect=aspect,
        max_circumball_count=max_held, max_cell_count=max_cell,
        floor_circumballs=int(floor_balls.sum()), floor_cells=int(floor_cells.sum()),
        alpha_hat=alpha_hat, beta_hat=beta_hat, alpha=mesh.alpha, beta=mesh.beta,
        probes=int(use.sum()), seconds=time.perf_counter() - t0,
    )  # fmt: skip
