"""Brute-force references for small inputs: every pair, every periodic copy, in the plane and
in space (the dimension is the points' number of columns).

Nothing here imports knnrefine; distances are scipy's ``cdist`` over every pair. Metrics are
given per axis by ``period``: a positive period makes that axis periodic, 0 leaves it
straight. ``knnrefine.certify`` (the scalable checker the other tests use) is validated
against these in test_certify.py.
"""

import itertools
from fractions import Fraction

import numpy as np
from scipy.spatial.distance import cdist

BLOCK = 4_000_000  # distances computed at a time (memory: 8 bytes each, a few times over)


def theorem6(tau):
    theta = np.sqrt(1.0 - 1.0 / tau**2)
    return (tau - 2.0) / (5.0 * tau - 2.0), (3.0 - theta) / (1.0 - theta)


def _copies(points, period):
    """Every point shifted by -1, 0 and +1 periods along each periodic axis: a point's copy
    nearest to anything in the box is among them."""
    period = np.asarray(period, float)
    steps = [(-1, 0, 1) if p else (0,) for p in period]
    shifts = np.array(list(itertools.product(*steps)), float) * period
    return np.concatenate([points + s for s in shifts])


def _rows(x, cover):
    """Blocks of rows of x small enough that (rows, len(cover)) distances fit in BLOCK."""
    step = max(1, BLOCK // max(1, len(cover)))
    for start in range(0, len(x), step):
        block = x[start : start + step]
        yield start, cdist(block, cover)


def _as(x, period):
    return np.asarray(x, float).reshape(-1, len(period))


def distances(x, points, period):
    """(q, n * copies) distances from each x to every periodic copy of every point."""
    cover = _copies(_as(points, period), period)
    return np.concatenate([d for _, d in _rows(_as(x, period), cover)])


def kth(x, points, k, period):
    """d_{S,k}(x) by brute force (inf where S has fewer than k points)."""
    x = _as(x, period)
    cover = _copies(_as(points, period), period)
    if len(cover) < k:
        return np.full(len(x), np.inf)
    out = np.empty(len(x))
    for start, d in _rows(x, cover):
        out[start : start + len(d)] = np.partition(d, k - 1, axis=1)[:, k - 1]
    return out


def circumcircles(corners):
    """Centres (t, d) and radii (t,) of the circumspheres of simplices (t, d + 1, d): in the
    plane by the closed form (Cramer's rule: the engine's rounding on skinny triangles), in
    space by a linear solve."""
    if corners.shape[-1] == 2:
        a = corners[:, 0]
        b = corners[:, 1] - a
        c = corners[:, 2] - a
        d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
        b2 = (b**2).sum(1)
        c2 = (c**2).sum(1)
        ux = (c[:, 1] * b2 - b[:, 1] * c2) / d
        uy = (b[:, 0] * c2 - c[:, 0] * b2) / d
        return a + np.stack([ux, uy], 1), np.hypot(ux, uy)
    a = corners[:, 0]
    edges = corners[:, 1:] - a[:, None, :]
    u = np.linalg.solve(edges, 0.5 * (edges**2).sum(-1)[..., None])[..., 0]
    return a + u, np.sqrt((u**2).sum(-1))


def _solve_exact(rows, rhs):
    """x with rows @ x = rhs, in rationals (Gauss-Jordan; rows nonsingular)."""
    n = len(rows)
    m = [list(r) + [b] for r, b in zip(rows, rhs, strict=True)]
    for c in range(n):
        p = next(i for i in range(c, n) if m[i][c] != 0)
        m[c], m[p] = m[p], m[c]
        for i in range(n):
            if i != c and m[i][c] != 0:
                f = m[i][c] / m[c][c]
                m[i] = [v - f * w for v, w in zip(m[i], m[c], strict=True)]
    return [m[i][n] / m[i][i] for i in range(n)]


def insphere_exact(corners, q):
    """+1 if q lies strictly inside the circumsphere of the simplex ``corners`` (d + 1
    points of d coordinates), 0 on it, -1 outside: decided in rational arithmetic."""
    c = [[Fraction(float(v)) for v in p] for p in corners]
    q = [Fraction(float(v)) for v in q]
    a = c[0]
    edges = [[pi - ai for pi, ai in zip(p, a, strict=True)] for p in c[1:]]
    u = _solve_exact(edges, [sum(e * e for e in row) / 2 for row in edges])
    r2 = sum(v * v for v in u)
    d2 = sum((qi - ai - ui) ** 2 for qi, ai, ui in zip(q, a, u, strict=True))
    return (d2 < r2) - (d2 > r2)


def torus_facts(torus, points):
    """Everything Theorem 6 speaks of, by brute force, on the whole torus of a mesh (a
    triangulation of the flat 2-torus or tetrahedralisation of the 3-torus).

    Returns a dict: empty (no vertex strictly inside any circumsphere, decided exactly for
    candidates), aspect (per vertex), R (outradius per vertex), ball (closed circumball
    counts), r (circumradii), cell (closed Voronoi cell counts), cc (circumcentres)."""
    period = np.asarray(torus.period, float)
    V = np.asarray(torus.vertices, float)
    dim = V.shape[1]
    P = np.mod(np.asarray(points, float).reshape(-1, dim) - np.asarray(torus.origin), period)
    cells = np.asarray(torus.cells if hasattr(torus, "cells") else torus.triangles)
    corners = V[cells] + np.asarray(torus.offsets) * period
    cc, r = circumcircles(corners)
    # empty spheres against every copy of every vertex; rationals for the close calls
    cover = _copies(V, period)
    ids = np.tile(np.arange(len(V)), len(cover) // len(V))
    empty = True
    for start, dv in _rows(cc, cover):
        for f, j in zip(*np.nonzero(dv < r[start : start + len(dv), None] * (1 + 1e-7)),
                        strict=True):  # fmt: skip
            f += start
            if ids[j] not in cells[f] and insphere_exact(corners[f], cover[j]) > 0:
                empty = False
    R = np.zeros(len(V))
    for c in range(dim + 1):
        np.maximum.at(R, cells[:, c], r)
    d2 = kth(V, V, 2, period)
    ball = np.zeros(len(r), int)
    cell = np.zeros(len(V), int)
    if len(P):
        pcover = _copies(P, period)
        for start, d in _rows(cc, pcover):
            ball[start : start + len(d)] = (d <= r[start : start + len(d), None]).sum(1)
        for _, dp in _rows(P, cover):
            hit = dp <= dp.min(1, keepdims=True) * (1 + 1e-12)
            np.add.at(cell, ids[np.nonzero(hit)[1]], 1)
    return {
        "empty": empty,
        "aspect": 2 * R / d2,
        "R": R,
        "r": r,
        "ball": ball,
        "cell": cell,
        "cc": cc,
    }


def random_cell(rng):
    """A Voronoi-like convex cell about the origin: half-planes {p : nb_j . p <= hc_j} towards
    a ring of 3 to 8 neighbours nb (hc_j half of |nb_j|^2), inside the disk of squared radius
    R2. Returns (nb (d, 2), hc (d,), R2)."""
    deg = rng.integers(3, 9)
    ang = np.sort(rng.random(deg)) * 2 * np.pi
    nb = 0.2 * rng.random() * np.stack([np.cos(ang), np.sin(ang)], 1) + 1e-3
    hc = 0.5 * (nb**2).sum(1)
    return nb, hc, float((4 * hc).max())


def in_cell(rel, nb, hc, R2, slack=1.0):
    """Mask of the points rel (relative to the cell's centre) in the cell of ``random_cell``,
    every constraint scaled by ``slack`` (1 -+ 1e-12 brackets the rounding)."""
    return np.all(rel @ nb.T <= hc * slack, axis=1) & ((rel**2).sum(1) <= R2 * slack)


# ---- the sphere -------------------------------------------------------------------------


def unit_vectors_of(lonlat):
    """Unit vectors of (longitude, latitude) in degrees, by the textbook formula."""
    lon, lat = np.radians(np.asarray(lonlat, float)).T
    return np.column_stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])


def great_circle(x, y):
    """(len(x), len(y)) great-circle angles between unit vectors, by atan2 (accurate at
    every angle, unlike arccos of the dot product)."""
    cross = np.linalg.norm(np.cross(x[:, None, :], y[None, :, :]), axis=2)
    return np.arctan2(cross, x @ y.T)


def _orient_exact(a, b, c, d):
    """Sign of det[a - d, b - d, c - d] in rational arithmetic."""
    rows = [[Fraction(float(u)) - Fraction(float(w)) for u, w in zip(r, d, strict=True)]
            for r in (a, b, c)]  # fmt: skip
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = rows
    det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
    return (det > 0) - (det < 0)


def in_caps(xyz, triangles, points):
    """(t, n) bool: point j on or above the plane of triangle t's corners (in its closed
    circumcap), decided in floating point with a wide error bound and in rationals where
    that cannot decide."""
    a, b, c = (xyz[triangles[:, i]][:, None, :] for i in range(3))
    p = points[None, :, :]
    u, v, w = a - p, b - p, c - p
    det = np.einsum("tnj,tnj->tn", u, np.cross(v, w))
    scale = np.einsum("tnj,tnj->tn", np.abs(u), np.abs(np.cross(v, w)) + 2 * np.abs(v) * np.abs(w))
    sure = np.abs(det) > 1e-12 * scale
    out = det <= 0
    for t, j in zip(*np.nonzero(~sure), strict=True):
        out[t, j] = _orient_exact(*xyz[triangles[t]], points[j]) <= 0
    return out


def sphere_facts(mesh, lonlat, k, probes):
    """Brute-force facts of a sphere mesh (angles in radians, on the unit sphere): the most
    points in a closed circumcap and in a closed Voronoi cell (nearest vertex by atan2
    angle, ties within a relative 1e-9 counting for each) among elements of angular radius
    >= the floor, and d_{M,2} / d_{P,k} at the probes (unit vectors) where d_{P,k} >= the
    floor."""
    xyz = np.asarray(mesh.xyz, float)
    tri = np.asarray(mesh.triangles)
    pts = unit_vectors_of(lonlat)
    floor = mesh.min_size / mesh.radius
    a = xyz[tri[:, 0]]
    normal = np.cross(xyz[tri[:, 1]] - a, xyz[tri[:, 2]] - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    cap = great_circle(normal, a).diagonal() if len(tri) < 4000 else None
    if cap is None:
        cap = np.array([great_circle(normal[i : i + 1], a[i : i + 1])[0, 0] for i in range(len(a))])
    held = in_caps(xyz, tri, pts).sum(axis=1)
    big = cap >= floor
    g = great_circle(pts, xyz)
    nearest = g.min(axis=1, keepdims=True)
    tie = g <= nearest * (1 + 1e-9)
    cells = tie.sum(axis=0)
    outradius = np.zeros(len(xyz))
    for i in range(3):
        np.maximum.at(outradius, tri[:, i], cap)
    d_m2 = np.sort(great_circle(probes, xyz), axis=1)[:, 1]
    d_pk = np.sort(great_circle(probes, pts), axis=1)[:, k - 1]
    use = d_pk >= floor
    return {
        "max_cap": int(held[big].max(initial=0)),
        "max_cell": int(cells[outradius >= floor].max(initial=0)),
        "ratio": d_m2[use] / d_pk[use],
        "largest_cap": float(cap.max()),
    }
