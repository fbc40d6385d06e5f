"""Weighted points (issue 11): counts are sums of weights, d_{P,k} the least radius holding
weight k. Oracles: brute force over weights, repeated points (whole weights), and exact
rescaling (weights and k halved: sums of halves are exact)."""

import numpy as np
import oracle
import pytest

import knnrefine
from knnrefine.density import KnnDensity, KnnDistance
from knnrefine.engine import index as engine_index
from knnrefine.engine.index import LEAF_SIZE, STACK_SIZE, build_index
from knnrefine.engine.jit import python_entry
from knnrefine.errors import InputError

count_in_disk = python_entry(engine_index.count_in_disk)
count_in_cell = python_entry(engine_index.count_in_cell)
count_in_torus_disk = python_entry(engine_index.count_in_torus_disk)


def weighted_sets(rng):
    yield "uniform", rng.random((3000, 2)), rng.gamma(1.5, 1.0, 3000)
    yield "duplicates", np.repeat(rng.random((40, 2)), 30, axis=0), rng.random(1200) * 2
    yield "zeros", rng.random((2000, 2)), np.where(rng.random(2000) < 0.5, 0.0, 1.7)
    g = np.arange(20) / 20
    yield "lattice", np.stack(np.meshgrid(g, g), -1).reshape(-1, 2), np.full(400, 0.25)


def copies(points, weights):
    shifts = [(sx, sy) for sx in (-1, 0, 1) for sy in (-1, 0, 1)]
    return np.concatenate([points + s for s in shifts]), np.tile(weights, len(shifts))


def assert_weight(got, lo, hi, k):
    """Exact below k (up to points on the boundary, up to rounding); else at least k."""
    if got >= k:
        assert hi >= k * (1 - 1e-9) and got <= hi * (1 + 1e-9), (got, lo, hi, k)
    else:
        assert lo * (1 - 1e-9) <= got <= hi * (1 + 1e-9), (got, lo, hi, k)


@pytest.mark.parametrize("case", range(4))
def test_weighted_counts_match_brute_force(case):
    rng = np.random.default_rng(case)
    name, pts, w = list(weighted_sets(rng))[case]
    index = build_index(pts.copy(), weights=w)
    assert index[0].shape == (len(pts), 3) and index[4][0] == pytest.approx(w.sum())
    stack = np.empty(STACK_SIZE, np.int64)
    cover, cw = copies(pts, w)
    for _ in range(150):
        c = rng.random(2)
        r = rng.choice([0.01, 0.05, 0.2, 0.45]) * rng.random()
        d2 = ((cover - c) ** 2).sum(1)
        lo = cw[d2 <= r * r * (1 - 1e-12)].sum()
        hi = cw[d2 <= r * r * (1 + 1e-12)].sum()
        for k in (0.5, 3.25, 50.0, 1e9):
            assert_weight(count_in_disk(index, c[0], c[1], r * r, k, 1.0, 1.0, stack), lo, hi, k)
            torus = count_in_torus_disk(index, c[0], c[1], r * r, k, 1.0, 1.0, stack)
            assert_weight(torus, lo, hi, k)
        # a cell: half-planes towards a ring of neighbours
        nb, hc, R2 = oracle.random_cell(rng)
        deg = len(hc)
        rel = cover - c

        def held(s, rel=rel, nb=nb, hc=hc, R2=R2):
            return cw[oracle.in_cell(rel, nb, hc, R2, s)].sum()

        for k in (0.5, 5.0, 1e9):
            got = count_in_cell(
                index, c[0], c[1], nb[:, 0].copy(), nb[:, 1].copy(), hc, deg, R2, k, 1.0, 1.0,
                stack, np.zeros(LEAF_SIZE, np.bool_),
            )  # fmt: skip
            assert_weight(got, held(1 - 1e-12), held(1 + 1e-12), k)


@pytest.mark.parametrize("periodic", [(False, False), (True, True), (False, True)])
def test_weighted_kth_distance_matches_brute_force(periodic):
    rng = np.random.default_rng(7)
    for name, pts, w in weighted_sets(rng):
        index = engine_index.PointIndex.build(pts, (0.0, 0.0, 1.0, 1.0), periodic, weights=w)
        q = np.concatenate([rng.random((100, 2)), pts[:30]])
        e = np.abs(q[:, None, :] - pts[None, :, :])
        for a in range(2):
            if periodic[a]:
                e[..., a] = np.minimum(e[..., a], 1.0 - e[..., a])
        d = np.sqrt((e**2).sum(-1))
        order = np.argsort(d, axis=1, kind="stable")
        held = np.cumsum(w[order], axis=1)
        for k in (0.1, 1.0, 7.5, 60.0):
            at = np.argmax(held >= k * (1 - 1e-12), axis=1)
            ref = np.take_along_axis(d, order, 1)[np.arange(len(q)), at]
            np.testing.assert_allclose(index.kth(q, k), ref, rtol=1e-12, atol=1e-15, err_msg=name)


@pytest.mark.parametrize("kw", [{}, {"periodic": True, "box": (0, 0, 1, 1)}])
def test_whole_weights_are_repeated_points_bit_for_bit(kw):
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.random((1500, 2)), rng.normal(0.4, 0.02, (500, 2)) % 1])
    w = rng.integers(1, 5, len(pts))
    a = knnrefine.refine(pts, 12, weights=w, **kw)
    b = knnrefine.refine(np.repeat(pts, w, axis=0), 12, **kw)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)
    assert a.stats["weight"] == w.sum() and "weight" not in b.stats
    q = rng.random((200, 2))
    fa = KnnDensity(a, pts, weights=w)
    fb = KnnDensity(b, np.repeat(pts, w, axis=0))
    np.testing.assert_allclose(fa(q), fb(q), rtol=1e-12)


def test_halved_weights_and_k_are_the_same_mesh():
    # every sum of halves is exact: the same decisions, the same mesh, at a real k
    rng = np.random.default_rng(4)
    pts = rng.random((2500, 2))
    a = knnrefine.refine(pts, 7.5, weights=np.full(len(pts), 0.5))
    b = knnrefine.refine(pts, 15)
    assert a.k == 7.5
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.triangles, b.triangles)


def test_weighted_certificate_is_independent_and_catches_wrong_weights():
    rng = np.random.default_rng(5)
    pts = np.concatenate([rng.random((2500, 2)), rng.normal(0.3, 0.02, (800, 2))])
    w = rng.gamma(1.0, 2.0, len(pts))
    mesh = knnrefine.refine(pts, 25.5, weights=w)
    cert = knnrefine.certify(mesh, pts, weights=w)
    assert cert.passed and cert.weight == pytest.approx(w.sum())
    assert cert.max_ball_count < 25.5 and cert.max_cell_count < 25.5
    assert "total weight" in str(cert)
    # the same total spread differently: the mesh is wrong for these weights
    other = np.where(np.arange(len(pts)) < 2500, 0.2, 5.0)
    other *= w.sum() / other.sum()
    assert not knnrefine.certify(mesh, pts, weights=other).passed
    with pytest.raises(InputError, match="refined with weights"):
        knnrefine.certify(mesh, pts)
    with pytest.raises(InputError, match="sum to"):
        knnrefine.certify(mesh, pts, weights=2 * w)
    plain = knnrefine.refine(pts, 25)
    with pytest.raises(InputError, match="without weights"):
        knnrefine.certify(plain, pts, weights=w)
    with pytest.raises(InputError, match="refined with weights"):
        KnnDistance(mesh, pts)
    with pytest.raises(InputError, match="without weights"):
        KnnDistance(plain, pts, weights=w)


@pytest.mark.parametrize(
    "weights, k, match",
    [
        (np.full(99, 1.0), 5, "shape"),
        (np.full(100, -1.0), 5, ">= 0"),
        (np.r_[np.nan, np.ones(99)], 5, "finite"),
        (np.zeros(100), 5, "sum to 0"),
        (np.full(100, 0.1), 10.5, "total weight"),
        (np.ones(100), 0, "positive"),
        (np.ones(100), "5", "positive"),
        (np.ones(100) + 1j, 5, "real"),
    ],
)
def test_bad_weights_are_refused_before_work(weights, k, match):
    pts = np.random.default_rng(6).random((100, 2))
    with pytest.raises(InputError, match=match):
        knnrefine.refine(pts, k, weights=weights)
