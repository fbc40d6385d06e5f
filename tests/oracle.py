"""Independent checks of a kNNRefine result, written with numpy and scipy alone.

Nothing here imports the engine: the periodic Delaunay triangulation is scipy's (qhull) over
the 3 x 3 cover, k-th-neighbour distances come from cKDTree (``boxsize`` on periodic axes),
and counts are brute force over those.
"""

from dataclasses import dataclass
from fractions import Fraction

import numpy as np
from scipy.spatial import Delaunay, cKDTree


def theorem6(tau):
    theta = np.sqrt(1.0 - 1.0 / tau**2)
    return (tau - 2.0) / (5.0 * tau - 2.0), (3.0 - theta) / (1.0 - theta)


def circumcenters(a, b, c):
    b = b - a
    c = c - a
    d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    b2 = (b**2).sum(1)
    c2 = (c**2).sum(1)
    ux = (c[:, 1] * b2 - b[:, 1] * c2) / d
    uy = (b[:, 0] * c2 - c[:, 0] * b2) / d
    return a + np.stack([ux, uy], 1), np.hypot(ux, uy)


def wrap(x, period):
    x = np.mod(x, period)
    x[x >= period] = 0.0
    return x


def periodic_delaunay(vertices, period):
    """Delaunay triangles of a periodic point set, one per torus triangle.

    Returns (ids (t, 3) torus vertex indices, corners (t, 3, 2) realised positions,
    circumcenters (t, 2) wrapped into the domain, radii (t,))."""
    m = vertices.shape[0]
    shifts = np.array(
        [(0, 0)] + [(sx, sy) for sx in (-1, 0, 1) for sy in (-1, 0, 1) if (sx, sy) != (0, 0)], float
    )
    cover = (vertices[None, :, :] + shifts[:, None, :] * period).reshape(-1, 2)
    s = Delaunay(cover).simplices
    ids = s % m
    # one representative per torus triangle: the copy whose smallest torus id is central
    j = np.argmin(ids, axis=1)
    s = s[s[np.arange(len(s)), j] < m]
    cc, r = circumcenters(cover[s[:, 0]], cover[s[:, 1]], cover[s[:, 2]])
    return s % m, cover[s], wrap(cc, period), r


def realise(torus_vertices, triangles, offsets, period):
    """Corner positions (t, 3, 2) of torus triangles given by vertex ids and corner offsets."""
    return torus_vertices[triangles] + offsets * np.asarray(period, float)


def check_triangulation(vertices, triangles, offsets, neighbors, period):
    """Raise AssertionError unless (triangles, offsets, neighbors) is a Delaunay
    triangulation of the torus with these vertices. Returns (corners, circumcenters, radii)."""
    period = np.asarray(period, float)
    m, t = len(vertices), len(triangles)
    # topology: F = 2V, V - E + F = 0, symmetric neighbours sharing the same edge
    assert t == 2 * m, (t, m)
    assert np.all(np.isin(np.arange(m), triangles)), "a vertex belongs to no triangle"
    tri = np.asarray(triangles)
    off = np.asarray(offsets, np.int64)
    nb = np.asarray(neighbors)
    f = np.repeat(np.arange(t), 3)
    i = np.tile(np.arange(3), t)
    a = tri[f, (i + 1) % 3]
    b = tri[f, (i + 2) % 3]
    n = nb[f, i]
    found = np.zeros(len(f), int)
    shared_ok = np.ones(len(f), bool)
    for j in range(3):
        hit = (nb[n, j] == f) & (tri[n, (j + 1) % 3] == b) & (tri[n, (j + 2) % 3] == a)
        found += hit
        da = off[f, (i + 1) % 3] - off[n, (j + 2) % 3]
        db = off[f, (i + 2) % 3] - off[n, (j + 1) % 3]
        shared_ok &= ~hit | np.all(da == db, axis=1)
    assert np.all(found == 1), f"{int((found != 1).sum())} neighbour links are not symmetric"
    assert np.all(shared_ok), "neighbours disagree on the offset of a shared edge"
    d = off[f, (i + 2) % 3] - off[f, (i + 1) % 3]
    flip = a > b
    key = np.stack(
        [
            np.where(flip, b, a),
            np.where(flip, a, b),
            np.where(flip, -d[:, 0], d[:, 0]),
            np.where(flip, -d[:, 1], d[:, 1]),
        ],
        1,
    )
    n_edges = len(np.unique(key, axis=0))
    assert n_edges == 3 * t // 2, "every edge must border exactly two triangles"
    assert m - n_edges + t == 0, "the Euler characteristic of a torus is 0"
    corners = realise(vertices, triangles, offsets, period)
    # orientation (in local coordinates) and coverage: areas sum to the torus area
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    area = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert np.all(area > 0), "a triangle is not counter-clockwise"
    assert abs(area.sum() - period.prod()) <= 1e-9 * period.prod(), (area.sum(), period.prod())
    # empty circles: no vertex (any periodic copy) strictly inside any circumcircle. Floats
    # find the candidates near each circle; exact rational arithmetic gives the verdict.
    cc, r = circumcenters(corners[:, 0], corners[:, 1], corners[:, 2])
    ccw = wrap(cc, period)
    tree = cKDTree(vertices, boxsize=period)
    candidates = tree.query_ball_point(ccw, r * (1 + 1e-6) + 1e-6 * r.max())
    for f, near in enumerate(candidates):
        for v in near:
            if v in tri[f]:
                continue
            p = vertices[v] + np.round((cc[f] - vertices[v]) / period) * period
            assert incircle_exact(*corners[f], p) <= 0, f"vertex {v} inside circle of {f}"
    return corners, ccw, r


def incircle_exact(a, b, c, d):
    """Sign of the in-circle determinant in exact rational arithmetic (+1: d strictly inside
    the circle through the counter-clockwise a, b, c)."""
    ax, ay, bx, by, cx, cy, dx, dy = (Fraction(float(x)) for x in (*a, *b, *c, *d))
    adx, ady, bdx, bdy, cdx, cdy = ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy
    det = (
        (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
    )
    return (det > 0) - (det < 0)


@dataclass
class TorusReport:
    m: int
    triangles: int
    max_aspect: float
    max_cell_count: int  # over cells with outradius >= min_size
    max_ball_count: int  # over circumballs with radius >= min_size
    ratio_min: float
    ratio_max: float
    alpha: float
    beta: float


def check_torus(torus, points, k, tau, min_size=0.0, n_random=4000, seed=0):
    """Theorem 6 on the whole torus of a mesh: aspect, counts and the ratio d_{M,2} / d_{P,k}.

    ``torus`` has origin, period, vertices, triangles, offsets, neighbors (input units). The
    triangulation is verified first (check_triangulation). Elements smaller than ``min_size``
    (the resolution floor) are exempt from the counts, probes with d_{P,k} < min_size from the
    ratio."""
    period = np.asarray(torus.period, float)
    origin = np.asarray(torus.origin, float)
    vertices = np.asarray(torus.vertices, float)
    points = wrap(np.asarray(points, float).reshape(-1, 2) - origin, period)
    m = vertices.shape[0]
    corners, cc, r = check_triangulation(
        vertices, torus.triangles, torus.offsets, torus.neighbors, period
    )
    R = np.zeros(m)
    for c in range(3):
        np.maximum.at(R, torus.triangles[:, c], r)
    vt = cKDTree(vertices, boxsize=period)
    d2 = vt.query(vertices, k=2)[0][:, 1]
    max_aspect = float(np.max(2.0 * R / d2))

    big = r >= min_size
    pt = cKDTree(points, boxsize=period) if len(points) else None
    ball = pt.query_ball_point(cc[big], r[big], return_length=True) if pt and big.any() else [0]
    cell = np.zeros(m, int)
    if pt is not None:
        kk = min(4, m)
        dd, ii = vt.query(points, k=kk)
        tie = dd <= dd[:, :1] * (1 + 1e-12) + 1e-300
        for j in range(kk):
            np.add.at(cell, ii[tie[:, j], j], 1)
    cell = cell[R >= min_size]

    rng = np.random.default_rng(seed)
    probes = np.concatenate([points, vertices, cc, rng.random((n_random, 2)) * period])
    rmin, rmax = ratio_range(probes, vt, pt, k, min_size, len(points))
    alpha, beta = theorem6(tau)
    return TorusReport(
        m,
        len(r),
        max_aspect,
        int(np.max(cell, initial=0)),
        int(np.max(ball, initial=0)),
        rmin,
        rmax,
        alpha,
        beta,
    )


def qhull_outradii(vertices, period):
    """R(v) for each vertex from scipy's Delaunay of the 3 x 3 cover (a cross-check of the
    engine's triangulation; reliable only at moderate scales)."""
    ids, corners, cc, r = periodic_delaunay(vertices, period)
    R = np.zeros(len(vertices))
    for c in range(3):
        np.maximum.at(R, ids[:, c], r)
    return R


def ratio_range(probes, mesh_tree, point_tree, k, min_size, n):
    """min and max of d_{M,2} / d_{P,k} over the probes whose d_{P,k} >= min_size."""
    if point_tree is None or n < k:
        return np.nan, np.nan
    dm2 = mesh_tree.query(probes, k=2)[0][:, 1]
    dpk = point_tree.query(probes, k=[k])[0][:, 0]
    ok = dpk >= min_size
    ratio = dm2[ok] / dpk[ok]
    return float(ratio.min()), float(ratio.max())


def box_trees(vertices, points, box, periodic):
    """cKDTrees of the returned vertices and of the points in the box's own metric: periodic
    axes wrapped with ``boxsize``, the others planar (boxsize 0)."""
    lo = np.array(box[:2], float)
    size = np.array(box[2:], float) - lo
    per = np.array(periodic, bool)
    boxsize = np.where(per, size, 0.0)

    def shift(x):
        x = np.asarray(x, float) - lo
        for a in range(2):
            if per[a]:
                x[:, a] = wrap(x[:, a], size[a])
        return x

    vt = cKDTree(shift(vertices), boxsize=boxsize if per.any() else None)
    pt = cKDTree(shift(points), boxsize=boxsize if per.any() else None) if len(points) else None
    return vt, pt, shift


def box_probes(vertices, points, box, n_random=4000, seed=0):
    lo = np.array(box[:2], float)
    hi = np.array(box[2:], float)
    rng = np.random.default_rng(seed)
    parts = [
        np.asarray(points, float).reshape(-1, 2),
        vertices,
        lo + rng.random((n_random, 2)) * (hi - lo),
    ]
    probes = np.concatenate(parts)
    return probes[(probes >= lo).all(1) & (probes <= hi).all(1)]
