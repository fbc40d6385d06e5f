"""The 3-D counting index (_engine/index3.py) against scipy's cKDTree with boxsize: closed
balls anywhere on the 3-torus (across its faces, edges and corners), exact below k and at
least k when the count stops early, counting points or summing their weights; closed
Voronoi cells of a refined periodic triangulation against each point's nearest mesh
vertices."""

import math

import numpy as np
import pytest
from conftest import of_trees
from scipy.spatial import cKDTree

from knnrefine._engine import index3, triangulation3
from knnrefine._engine.geometry import Q
from knnrefine._engine.index3 import build_index3
from knnrefine._engine.initial import initial_grid3
from knnrefine._engine.jit import python_entry
from knnrefine._engine.triangulation3 import insert_largest3, new_torus3

_ball = of_trees(index3.count_in_ball3)
_cell = of_trees(index3.count_in_cell3)
_neighbours = python_entry(triangulation3.vertex_neighbours3)


def _points(n, period, seed):
    """Half uniform, half in tight clusters, with exact duplicates."""
    rng = np.random.default_rng(seed)
    u = rng.random((n // 2, 3)) * period
    c = rng.random((5, 3)) * period
    g = c[rng.integers(0, 5, n - n // 2)] + 0.01 * rng.standard_normal((n - n // 2, 3))
    pts = np.mod(np.concatenate([u, g]), period)
    pts[:50] = pts[50:100]  # duplicates
    return pts


def _weights(n, seed):
    """Weights from 1e-3 to 1e3, a tenth of them 0, one of 1e12 (a heavy point must not
    swallow light ones)."""
    rng = np.random.default_rng(seed)
    w = 10.0 ** rng.uniform(-3, 3, n)
    w[rng.random(n) < 0.1] = 0.0
    w[7] = 1e12
    return w


def _held(lists, w):
    """What each list of points holds: their number, or the exact sum of their weights."""
    if w is None:
        return np.array([len(a) for a in lists])
    return np.array([math.fsum(w[a]) for a in lists])


@pytest.mark.parametrize("weighted", [False, True], ids=["counts", "weights"])
@pytest.mark.parametrize("period", [(1.0, 1.0, 1.0), (2.0, 0.5, 1.0)], ids=str)
def test_ball_counts_match_a_periodic_kd_tree(period, weighted):
    """Unweighted, the counts exactly; weighted, the sums of weights within rounding (as
    exact sums, math.fsum over the kd-tree's points)."""
    period = np.array(period)
    pts = _points(20000, period, 1)
    w = _weights(len(pts), 4) if weighted else None
    index = build_index3(pts, weights=w)
    rows = index[0]
    if weighted:
        assert rows.shape == (len(pts), 4) and index.weight[0] == pytest.approx(w.sum())
        rows = rows[:, :3]
        assert sorted(map(tuple, index[0])) == sorted(map(tuple, np.column_stack([pts, w])))
    assert sorted(map(tuple, rows)) == sorted(map(tuple, pts))  # a permutation
    tree = cKDTree(pts, boxsize=period)
    rng = np.random.default_rng(2)
    centres = rng.random((3000, 3)) * period
    centres[:500] = rng.integers(0, 2, (500, 3)) * period  # at the torus' corners
    centres[500:1000] = pts[:500]  # on data points (the closed ball holds them)
    radii = rng.random(3000) ** 2 * 0.45 * period.min()
    want = _held(tree.query_ball_point(centres, radii), w)
    stack = np.empty(128, np.int64)
    shifted = centres + rng.integers(-2, 3, (3000, 3)) * period  # any frame
    for k in (1e15, 25.0):
        got = np.array(
            [_ball(index, c, r * r, k, period, stack) for c, r in zip(shifted, radii, strict=True)]
        )
        if not weighted and k > 10**8:
            np.testing.assert_array_equal(got, want)
        elif k > 10**8:
            np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)
        else:
            below = want < k * (1 - 1e-12)
            np.testing.assert_allclose(got[below], want[below], rtol=1e-13, atol=0)
            assert (got[want >= k * (1 + 1e-12)] >= k).all()


@pytest.mark.parametrize("weighted", [False, True], ids=["counts", "weights"])
def test_a_grown_forest_in_space_counts_as_a_periodic_kd_tree_of_all_its_points(weighted):
    """``index.grow_forest`` with space's trees (a continued run's index: the start's tree,
    untouched, and a small one over the points added since): ball counts across the
    torus' faces match cKDTree over every point, batch after batch, through the fold of
    the small tree into the large one; ``tree_of`` merges them into one tree of them all."""
    from knnrefine._engine.index import forest_of, grow_forest, tree_of

    period = np.array([1.0, 1.0, 1.0])
    pts = _points(3000, period, 7)
    w = _weights(len(pts), 8) if weighted else None
    forest = forest_of(build_index3(pts, weights=w))
    rng = np.random.default_rng(9)
    stack = np.empty(128, np.int64)
    sizes = []
    for _ in range(5):  # 120 a batch: the fourth passes 3000 / 8 and folds
        new = np.mod(rng.normal(rng.random(3), 0.02, (120, 3)), 1.0)
        w_new = _weights(120, int(rng.integers(1000))) if weighted else None
        forest = grow_forest(forest, new, w_new, index3.merge_index3,
                             lambda x, weights: build_index3(x, weights=weights))  # fmt: skip
        sizes.append(len(forest.extra.pts))
        pts = np.concatenate([pts, new])
        w = np.concatenate([w, w_new]) if weighted else None
        tree = cKDTree(pts, boxsize=period)
        centres, radii = rng.random((300, 3)), rng.random(300) * 0.3
        want = _held(tree.query_ball_point(centres, radii), w)
        got = np.array([_ball(forest, c, r * r, 1e15, period, stack)
                        for c, r in zip(centres, radii, strict=True)])  # fmt: skip
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)
    assert sizes == [120, 240, 360, 0, 120]
    one = tree_of(forest, index3.merge_index3)
    assert sorted(map(tuple, one.pts[:, :3])) == sorted(map(tuple, pts))


@pytest.mark.slow
@pytest.mark.parametrize("weighted", [False, True], ids=["counts", "weights"])
def test_cell_counts_match_each_points_nearest_vertices(weighted):
    """The closed cell of every vertex of a refined triangulation of the unit 3-torus counts
    the points whose nearest vertex it is (ties: every nearest one), as a kd-tree over the
    vertices says; weighted points, their weights (exact sums, math.fsum)."""
    period = np.array([1.0, 1.0, 1.0])
    mesh, scratch, cnt = new_torus3(period, initial_grid3(period), 2000, 20000)
    insert_largest3(mesh, scratch, cnt, period, Q, 600, 0.0)
    nv = int(cnt[0])
    pts = _points(30000, period, 3)
    pts[:200] = mesh.xyz[:200]  # on vertices
    w = _weights(len(pts), 5) if weighted else None
    index = build_index3(pts, weights=w)
    dd, ii = cKDTree(mesh.xyz[:nv], boxsize=period).query(pts, k=3)
    tie = dd <= dd[:, :1] * (1 + 1e-12)
    members = [[] for _ in range(nv)]
    for p, v in zip(*np.nonzero(tie), strict=True):
        members[ii[p, v]].append(p)
    want = _held([np.array(a, np.int64) for a in members], w)
    h = np.empty((256, 3))
    ids = np.empty(256, np.int64)
    stack = np.empty(128, np.int64)
    got = np.empty(nv)
    for v in range(nv):
        nh = _neighbours(v, mesh, scratch, cnt, period, h, ids)
        assert nh > 3
        hc = 0.5 * (h[:nh] ** 2).sum(axis=1) * (1 + 1e-9)
        r2 = abs(mesh.outradius2[v]) * (1 + 1e-9)  # R(v)^2 or a bound: the ball holds the cell
        got[v] = _cell(index, mesh.xyz[v], h[:nh].copy(), hc, nh, r2, 1e15, period, stack)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)


@pytest.mark.parametrize(
    "periodic", [(False, False, False), (True, True, True), (True, False, True)]
)
@pytest.mark.parametrize("weighted", [False, True])
def test_kth_distances3_match_scipy(periodic, weighted):
    """Exact d_{P,k} in space by windows (``index3.kth_distances3``, issue 30) against
    scipy's k-nearest query (weighted: the least radius whose closed ball holds weight k):
    clustered points with duplicates, on a torus along some axes; windows far too narrow,
    far too wide and at the answer all settle to the same value."""
    period = np.array([1.0, 2.0, 1.5])
    pts = _points(3000, period, 4)
    per = np.array(periodic, bool)
    w = np.random.default_rng(5).integers(1, 4, len(pts)).astype(float) if weighted else None
    tree = build_index3(pts, weights=w)
    q = np.random.default_rng(6).random((400, 3)) * period
    q[:50] = pts[:50]  # at the points themselves (distance 0 among the answers' ties)
    boxsize = np.where(per, period, 0.0) if per.any() else None
    ck = cKDTree(pts % np.where(per, period, np.inf), boxsize=boxsize)
    for k in (1, 7, 60):
        if w is None:
            want = ck.query(q, k=[k])[0][:, 0]
        else:
            d, i = ck.query(q, k=min(len(pts), 2 * k + 16))
            held = np.cumsum(w[i], axis=1)
            want = d[np.arange(len(q)), np.argmax(held >= k, axis=1)]
        for guess in (want * 0.01 + 1e-9, want * 30 + 1e-9, want):
            out = np.empty(len(q))
            index3.kth_distances3(tree, q, float(k), guess / 1.05, guess * 1.05,
                                  np.where(per, period, np.inf), per, 64 * k + 64, out, 0,
                                  len(q))  # fmt: skip
            np.testing.assert_allclose(out, want, rtol=1e-12)
