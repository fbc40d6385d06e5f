"""Weighted points (issue 11): counts are sums of weights, d_{P,k} the least radius holding
weight k. Oracles: brute force over weights, repeated points (whole weights), and exact
rescaling (weights and k halved: sums of halves are exact)."""

import numpy as np
import oracle
import pytest
from conftest import of_trees, unit_box

import knnrefine
from knnrefine._engine import index as engine_index
from knnrefine._engine.index import LEAF_SIZE, STACK_SIZE, build_index
from knnrefine._engine.jit import python_entry
from knnrefine.density import KnnDensity, KnnDistance
from knnrefine.errors import InputError

count_in_disk = of_trees(engine_index.count_in_disk)
count_in_cell = of_trees(engine_index.count_in_cell)
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


@pytest.mark.parametrize("periodic", [(False,) * 3, (False, True, True)], ids=str)
def test_weighted_kth_distance_in_space_matches_brute_force(periodic):
    """d_{P,k} in space with weights (KnnDistance.exact, certify's weighted_kth): the least
    radius whose closed ball holds weight k, from sorted distances and running sums. Points
    repeated three times (weights below 2: under k = 7.5 together, so that refinement stops
    above the floor) and weights of 0."""
    rng = np.random.default_rng(8)
    pts = np.concatenate([rng.random((600, 3)), np.repeat(rng.random((20, 3)), 3, axis=0)])
    w = np.where(rng.random(len(pts)) < 0.2, 0.0, np.minimum(rng.gamma(1.5, 1.0, len(pts)), 2))
    box = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    mesh = knnrefine.refine(pts, 7.5, periodic=periodic, box=box, weights=w)
    q = np.concatenate([rng.random((150, 3)), pts[:30]])
    e = np.abs(q[:, None, :] - pts[None, :, :])
    for a in range(3):
        if periodic[a]:
            e[..., a] = np.minimum(e[..., a], 1.0 - e[..., a])
    d = np.sqrt((e**2).sum(-1))
    order = np.argsort(d, axis=1, kind="stable")
    held = np.cumsum(w[order], axis=1)
    dist = KnnDistance(mesh, pts, weights=w)
    for k in (0.1, 7.5, 60.0):
        at = np.argmax(held >= k * (1 - 1e-12), axis=1)
        ref = np.take_along_axis(d, order, 1)[np.arange(len(q)), at]
        np.testing.assert_allclose(dist.index.kth(q, k), ref, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_whole_weights_are_repeated_points_bit_for_bit(dim, periodic):
    rng = np.random.default_rng(3)
    n = 1500 if dim == 2 else 800
    pts = np.concatenate([rng.random((n, dim)), rng.normal(0.4, 0.02, (n // 3, dim)) % 1])
    w = rng.integers(1, 5, len(pts))
    kw = {"periodic": True, "box": unit_box(dim)} if periodic else {}
    a = knnrefine.refine(pts, 12, weights=w, **kw)
    b = knnrefine.refine(np.repeat(pts, w, axis=0), 12, **kw)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.cells, b.cells)
    assert a.stats["weight"] == w.sum() and b.stats["weight"] is None
    q = rng.random((200, dim))
    fa = KnnDensity(a, pts, weights=w)
    fb = KnnDensity(b, np.repeat(pts, w, axis=0))
    np.testing.assert_allclose(fa(q), fb(q), rtol=1e-12)
    np.testing.assert_allclose(fa.distance.exact(q), fb.distance.exact(q), rtol=1e-12)


def test_halved_weights_and_k_are_the_same_mesh(dim):
    # every sum of halves is exact: the same decisions, the same mesh, at a real k
    rng = np.random.default_rng(4)
    pts = rng.random((2500 if dim == 2 else 1200, dim))
    a = knnrefine.refine(pts, 7.5, weights=np.full(len(pts), 0.5))
    b = knnrefine.refine(pts, 15)
    assert a.k == 7.5
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.cells, b.cells)


def test_weighted_certificate_is_independent_and_catches_wrong_weights(dim):
    rng = np.random.default_rng(5)
    n = 2500 if dim == 2 else 1500
    pts = np.concatenate([rng.random((n, dim)), rng.normal(0.3, 0.02, (800, dim))])
    w = rng.gamma(1.0, 2.0, len(pts))
    mesh = knnrefine.refine(pts, 25.5, weights=w)
    cert = knnrefine.certify(mesh, pts, weights=w)
    assert cert.passed and cert.weight == pytest.approx(w.sum())
    assert cert.max_ball_count < 25.5 and cert.max_cell_count < 25.5
    assert "total weight" in str(cert)
    # the same total spread differently: the mesh is wrong for these weights
    other = np.where(np.arange(len(pts)) < n, 0.2, 5.0)
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
def test_bad_weights_are_refused_before_work(weights, k, match, dim):
    pts = np.random.default_rng(6).random((100, dim))
    with pytest.raises(InputError, match=match):
        knnrefine.refine(pts, k, weights=weights)


# -- extreme weights (issue 28) ------------------------------------------------------------------


def test_a_weight_k_beyond_int64_is_a_weight():
    """regression: k >= 2^63 (weights 1e19, k = 1e20) was kept a Python int the kernels
    could not type (numba TypingError). It is a weight: the run is certified, the same mesh
    as weights 1 and k = 10 (every weight is 1e19 exactly, the sums exact multiples)."""
    pts = np.random.default_rng(0).random((500, 2))
    big = knnrefine.refine(pts, 1e20, weights=np.full(500, 1e19))
    assert knnrefine.certify(big, pts, weights=np.full(500, 1e19)).passed
    unit = knnrefine.refine(pts, 10, weights=np.ones(500))
    np.testing.assert_array_equal(big.vertices, unit.vertices)


def test_subnormal_weights():
    """regression: weights of 5e-324 (the least double) raised 'cannot convert float NaN to
    integer' (the size estimate divided by their subnormal total). Weights are relative to
    k: 5e-324 with k = 20 x 5e-324 is the mesh of weights 1 with k = 20, exactly (sums of
    subnormals are exact)."""
    pts = np.random.default_rng(1).random((500, 2))
    tiny = np.full(500, 5e-324)
    mesh = knnrefine.refine(pts, 20 * 5e-324, weights=tiny)
    assert knnrefine.certify(mesh, pts, weights=tiny).passed
    unit = knnrefine.refine(pts, 20, weights=np.ones(500))
    np.testing.assert_array_equal(mesh.vertices, unit.vertices)


def test_a_heavy_point_does_not_swallow_light_ones():
    """regression: one point of weight 1e16 among points of weight 1, k = 1e16 + 8. Added in
    distance order, 1e16 + 1 rounds to 1e16: certify's d_Pk never reached k (infinite,
    alpha_hat 0) and failed the mesh, and the engine's counts lost the light points too, so
    circumballs holding the heavy point and 8 or more light ones (exactly, by math.fsum)
    were left unsplit. Both now sum with compensation: no circumball or cell holds k by the
    exact sums, and certify's d_Pk is the exact one at every input point."""
    import math

    from scipy.spatial import cKDTree

    from knnrefine.mesh import circumcircles

    pts = np.random.default_rng(0).random((200, 2))
    w = np.ones(200)
    w[0] = 1e16
    k = 1e16 + 8
    mesh = knnrefine.refine(pts, k, weights=w)
    cert = knnrefine.certify(mesh, pts, weights=w)
    assert cert.passed, str(cert)
    torus = mesh.torus
    period = np.array(torus.period)
    local = np.mod(pts - np.array(torus.origin), period)
    tree = cKDTree(local, boxsize=period)
    centres, radii = circumcircles(torus.vertices[torus.triangles] + torus.offsets * period)
    held = [math.fsum(w[i]) for i in tree.query_ball_point(np.mod(centres, period), radii)]
    assert max(held) < k
    # each point's nearest vertices: its Voronoi cell (ties count for each)
    dd, ii = cKDTree(torus.vertices, boxsize=period).query(local, k=3)
    cells = {}
    for p in range(len(pts)):
        for d, v in zip(dd[p], ii[p], strict=True):
            if d <= dd[p, 0] * (1 + 1e-12):
                cells.setdefault(v, []).append(w[p])
    assert max(math.fsum(c) for c in cells.values()) < k
    # d_Pk by exact sums in distance order, against certify's (compensated) one
    from knnrefine._domains.plane.certify import Points as TorusPoints

    d, i = tree.query(local, k=len(pts))
    exact = [d[p][next(j for j in range(len(pts)) if math.fsum(w[i[p][: j + 1]]) >= k)]
             for p in range(len(pts))]  # fmt: skip
    np.testing.assert_array_equal(TorusPoints(mesh, pts, w, 1).d_pk(local), exact)


def test_a_heavy_point_does_not_swallow_light_ones_in_space():
    """The same regression in space (engine/index3.py sums weights with compensation, as the
    plane's index): one point of weight 1e16 among points of weight 1, k = 1e16 + 8; no
    circumball of the mesh holds k by exact sums (math.fsum), and certify passes."""
    import math

    from scipy.spatial import cKDTree

    from knnrefine._domains.space.certify import _circumspheres

    pts = np.random.default_rng(0).random((300, 3))
    w = np.ones(300)
    w[0] = 1e16
    k = 1e16 + 8
    mesh = knnrefine.refine(pts, k, weights=w)
    assert knnrefine.certify(mesh, pts, weights=w).passed
    torus = mesh.torus
    period = np.array(torus.period)
    local = np.mod(pts - np.array(torus.origin), period)
    centres, r2, _ = _circumspheres(torus.vertices, torus.cells, torus.offsets, period)
    found = cKDTree(local, boxsize=period).query_ball_point(np.mod(centres, period), np.sqrt(r2))
    assert max(math.fsum(w[i]) for i in found) < k
    # the heavy point with 8 light ones around it does hold k: some ball about it was split
    assert any(0 in i and math.fsum(w[i]) >= 1e16 + 4 for i in found)


@pytest.mark.parametrize("bad", [0, -3, 2.5, float("inf"), float("nan"), True, "10"])
def test_max_vertices_is_checked(bad):
    with pytest.raises(InputError, match="max_vertices"):
        knnrefine.refine(np.random.default_rng(2).random((100, 2)), 5, max_vertices=bad)


def test_max_vertices_beyond_int64_means_no_budget(monkeypatch):
    """regression: max_vertices=2**70 raised a bare OverflowError; a budget beyond 2^62 is
    no budget (capped there), in the plane, in space and through the tiles."""
    pts = np.random.default_rng(3).random((2000, 2))
    mesh = knnrefine.refine(pts, 5, max_vertices=2**70)
    assert mesh.stats["max_vertices"] == 2**62
    monkeypatch.setenv("KNNREFINE_TILES", "always")  # the tiles at this size too
    assert len(knnrefine.refine(pts, 5, max_vertices=2**70, workers=2).vertices) > 0
    space = np.random.default_rng(4).random((500, 3))
    knnrefine.refine(space, 5, periodic=True, box=(0, 0, 0, 1, 1, 1), max_vertices=2**70)
