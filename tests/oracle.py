"""Brute-force references for small inputs: numpy over all pairs, all periodic copies.

Nothing here imports knnrefine. Metrics are given per axis by ``period``: a positive period
makes that axis periodic, 0 leaves it planar. ``knnrefine.certify`` (the scalable checker the
other tests use) is validated against these in test_certify.py.
"""

from fractions import Fraction

import numpy as np


def theorem6(tau):
    theta = np.sqrt(1.0 - 1.0 / tau**2)
    return (tau - 2.0) / (5.0 * tau - 2.0), (3.0 - theta) / (1.0 - theta)


def _copies(points, period):
    period = np.asarray(period, float)
    shifts = [
        (sx, sy)
        for sx in ((-1, 0, 1) if period[0] else (0,))
        for sy in ((-1, 0, 1) if period[1] else (0,))
    ]
    return np.concatenate([points + np.array(s) * period for s in shifts])


def distances(x, points, period):
    """(q, n * copies) distances from each x to every periodic copy of every point."""
    c = _copies(np.asarray(points, float).reshape(-1, 2), period)
    x = np.asarray(x, float).reshape(-1, 2)
    return np.sqrt(((x[:, None, :] - c[None, :, :]) ** 2).sum(-1))


def kth(x, points, k, period):
    """d_{S,k}(x) by brute force (inf where S has fewer than k points)."""
    d = distances(x, points, period)
    if d.shape[1] < k:
        return np.full(len(d), np.inf)
    return np.partition(d, k - 1, axis=1)[:, k - 1]


def circumcircles(corners):
    a = corners[:, 0]
    b = corners[:, 1] - a
    c = corners[:, 2] - a
    d = 2.0 * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    b2 = (b**2).sum(1)
    c2 = (c**2).sum(1)
    ux = (c[:, 1] * b2 - b[:, 1] * c2) / d
    uy = (b[:, 0] * c2 - c[:, 0] * b2) / d
    return a + np.stack([ux, uy], 1), np.hypot(ux, uy)


def incircle_exact(a, b, c, d):
    """Sign of the in-circle determinant in rational arithmetic (+1: d strictly inside)."""
    ax, ay, bx, by, cx, cy, dx, dy = (Fraction(float(v)) for v in (*a, *b, *c, *d))
    adx, ady, bdx, bdy, cdx, cdy = ax - dx, ay - dy, bx - dx, by - dy, cx - dx, cy - dy
    det = (
        (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        + (bdx * bdx + bdy * bdy) * (cdx * ady - adx * cdy)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
    )
    return (det > 0) - (det < 0)


def torus_facts(torus, points):
    """Everything Theorem 6 speaks of, by brute force, on the whole torus of a mesh.

    Returns a dict: empty (no vertex strictly inside any circumcircle, decided exactly for
    candidates), aspect (per vertex), R (outradius per vertex), ball (closed circumball
    counts), r (circumradii), cell (closed Voronoi cell counts), cc (circumcenters)."""
    period = np.asarray(torus.period, float)
    V = np.asarray(torus.vertices, float)
    P = np.mod(np.asarray(points, float) - np.asarray(torus.origin), period)
    tri = np.asarray(torus.triangles)
    corners = V[tri] + np.asarray(torus.offsets) * period
    cc, r = circumcircles(corners)
    # empty circles against every copy of every vertex; rationals for the close calls
    dv = distances(cc, V, period)
    ids = np.tile(np.arange(len(V)), dv.shape[1] // len(V))
    cover = _copies(V, period)
    empty = True
    for f, j in zip(*np.nonzero(dv < r[:, None] * (1 + 1e-7)), strict=True):
        if ids[j] in tri[f]:
            continue
        if incircle_exact(*corners[f], cover[j]) > 0:
            empty = False
    R = np.zeros(len(V))
    for c in range(3):
        np.maximum.at(R, tri[:, c], r)
    dvv = distances(V, V, period)
    d2 = np.partition(dvv, 1, axis=1)[:, 1]
    ball = (distances(cc, P, period) <= r[:, None]).sum(1) if len(P) else np.zeros(len(r), int)
    cell = np.zeros(len(V), int)
    if len(P):
        dp = distances(P, V, period)
        dmin = dp.min(1, keepdims=True)
        hit = dp <= dmin * (1 + 1e-12)
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
