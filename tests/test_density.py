"""d_{P,k} everywhere and the kNN density: against exact values and brute-force integrals."""

import numpy as np
import oracle
import pytest

import knnrefine
from knnrefine.density import KnnDensity, KnnDistance


@pytest.fixture(scope="module", params=[True, False, (True, False)])
def case(request):
    rng = np.random.default_rng(0)
    pts = (
        np.concatenate(
            [
                rng.normal([0.3, 0.3], 0.08, (1200, 2)),
                rng.normal([0.7, 0.6], 0.01, (600, 2)),
                rng.random((600, 2)),
            ]
        )
        % 1
    )
    mesh = knnrefine.refine(pts, 20, periodic=request.param, box=(0, 0, 1, 1))
    return pts, mesh


def test_exact_at_the_nodes_and_close_everywhere(case):
    pts, mesh = case
    d = KnnDistance(mesh, pts)
    per = np.array(mesh.period)
    np.testing.assert_allclose(d.values, oracle.kth(d.nodes, pts, mesh.k, per), rtol=1e-12)
    q = np.random.default_rng(1).random((1500, 2))
    ref = oracle.kth(q, pts, mesh.k, per)
    rel = np.abs(d(q) - ref) / ref
    assert np.median(rel) < 0.03 and rel.max() < 0.3
    err = d.error()
    assert err["median"] < 0.03 and err["probes"] > 2000
    # periodic axes wrap; the estimate is continuous across the seam
    if mesh.periodic[0]:
        np.testing.assert_allclose(d(q), d(q + [1.0, 0.0]), rtol=1e-9)
        edge = np.column_stack([np.full(50, 1 - 1e-9), np.linspace(0.01, 0.99, 50)])
        np.testing.assert_allclose(d(edge), d(edge - [1 - 2e-9, 0]), rtol=1e-6)
    else:
        assert np.isnan(d([[1.5, 0.5]])).all()


def test_grid_covers_the_box(case):
    pts, mesh = case
    xs, ys, g = KnnDistance(mesh, pts).grid((64, 80))
    assert g.shape == (64, 80) and np.isfinite(g).all() and (g > 0).all()
    assert xs[0] > 0 and xs[-1] < 1 and len(ys) == 64


def test_density_integrates_to_one_and_masses_add_up(case):
    pts, mesh = case
    f = KnnDensity(mesh, pts)
    assert f.mass() == pytest.approx(1.0, rel=1e-9)
    parts = [f.mass((0, 0, 0.4, 1)), f.mass((0.4, 0, 1, 0.25)), f.mass((0.4, 0.25, 1, 1))]
    assert sum(parts) == pytest.approx(1.0, rel=1e-6)  # quadrature of 1/d^2 on clipped pieces
    # brute force: the mass of the dense cluster's square on a fine grid of the estimate
    region = (0.6, 0.5, 0.8, 0.7)
    g = np.linspace(0, 1, 801)[:-1] + 1 / 1600
    gx, gy = np.meshgrid(0.6 + 0.2 * g, 0.5 + 0.2 * g)
    brute = f(np.column_stack([gx.ravel(), gy.ravel()])).mean() * 0.04
    assert f.mass(region) == pytest.approx(brute, rel=0.02)
    # the unnormalised estimate is k / (n pi d^2) and integrates to about 1 anyway
    raw = KnnDensity(mesh, pts, normalized=False)
    assert 0.8 < raw.mass() < 1.3
    q = np.random.default_rng(2).random((10, 2))
    np.testing.assert_allclose(raw(q), mesh.k / (len(pts) * np.pi * raw.distance(q) ** 2))


def test_errors():
    pts = np.random.default_rng(3).random((50, 2))
    mesh = knnrefine.refine(pts, 10)
    with pytest.raises(knnrefine.InputError, match="d_Pk is infinite"):
        KnnDistance(mesh, pts[:5])
    d = KnnDistance(mesh, pts)
    with pytest.raises(knnrefine.InputError, match="leaves the box"):
        d.integrate(lambda v: v, region=(0.5, 0.5, 2.0, 0.6))
