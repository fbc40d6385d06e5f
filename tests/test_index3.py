"""The 3-D counting index (engine/index3.py) against scipy's cKDTree with boxsize: closed
balls anywhere on the 3-torus (across its faces, edges and corners), exact below k and at
least k when the count stops early; closed Voronoi cells of a refined periodic triangulation
against each point's nearest mesh vertices."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from knnrefine.engine import index3, triangulation3
from knnrefine.engine.geometry import Q
from knnrefine.engine.index3 import build_index3
from knnrefine.engine.initial import initial_grid3
from knnrefine.engine.jit import python_entry
from knnrefine.engine.triangulation3 import insert_largest3, new_torus3

_ball = python_entry(index3.count_in_ball3)
_cell = python_entry(index3.count_in_cell3)
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


@pytest.mark.parametrize("period", [(1.0, 1.0, 1.0), (2.0, 0.5, 1.0)], ids=str)
def test_ball_counts_match_a_periodic_kd_tree(period):
    period = np.array(period)
    pts = _points(20000, period, 1)
    index = build_index3(pts)
    assert sorted(map(tuple, index[0])) == sorted(map(tuple, pts))  # a permutation
    tree = cKDTree(pts, boxsize=period)
    rng = np.random.default_rng(2)
    centres = rng.random((3000, 3)) * period
    centres[:500] = rng.integers(0, 2, (500, 3)) * period  # at the torus' corners
    centres[500:1000] = pts[:500]  # on data points (the closed ball holds them)
    radii = rng.random(3000) ** 2 * 0.45 * period.min()
    want = tree.query_ball_point(centres, radii, return_length=True)
    stack = np.empty(128, np.int64)
    shifted = centres + rng.integers(-2, 3, (3000, 3)) * period  # any frame
    for k in (10**9, 25):
        got = np.array(
            [_ball(index, c, r * r, k, period, stack) for c, r in zip(shifted, radii, strict=True)]
        )
        if k > 10**8:
            np.testing.assert_array_equal(got, want)
        else:
            np.testing.assert_array_equal(np.minimum(got, k), np.minimum(want, k))
            assert (got[want >= k] >= k).all()


@pytest.mark.slow
def test_cell_counts_match_each_points_nearest_vertices():
    """The closed cell of every vertex of a refined triangulation of the unit 3-torus counts
    the points whose nearest vertex it is (ties: every nearest one), as a kd-tree over the
    vertices says."""
    period = np.array([1.0, 1.0, 1.0])
    mesh, scratch, cnt = new_torus3(period, initial_grid3(period), 2000, 20000)
    insert_largest3(mesh, scratch, cnt, period, Q, 600, 0.0)
    nv = int(cnt[0])
    pts = _points(30000, period, 3)
    pts[:200] = mesh.xyz[:200]  # on vertices
    index = build_index3(pts)
    dd, ii = cKDTree(mesh.xyz[:nv], boxsize=period).query(pts, k=3)
    tie = dd <= dd[:, :1] * (1 + 1e-12)
    want = np.bincount(ii[tie], minlength=nv)
    h = np.empty((256, 3))
    ids = np.empty(256, np.int64)
    stack = np.empty(128, np.int64)
    got = np.empty(nv, np.int64)
    for v in range(nv):
        nh = _neighbours(v, mesh, scratch, cnt, period, h, ids)
        assert nh > 3
        hc = 0.5 * (h[:nh] ** 2).sum(axis=1) * (1 + 1e-9)
        r2 = mesh.outradius2[v] * (1 + 1e-9)
        got[v] = _cell(index, mesh.xyz[v], h[:nh].copy(), hc, nh, r2, 10**9, period, stack)
    np.testing.assert_array_equal(got, want)
