"""KnnDistance and KnnDensity, one suite over both dimensions (the ``dim`` fixture): the same
calls on a mesh in the plane and in space, against independent oracles (scipy's kd-tree for
d_{P,k}, Monte Carlo for integrals and samples)."""

import numpy as np
import pytest
from conftest import two_blobs as blobs
from conftest import unit_box
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import InputError, KnnDensity, KnnDistance

N = {2: 4000, 3: 6000}
K = 10


@pytest.fixture(params=[True, False], ids=["periodic", "box"])
def case(request, dim):
    pts = blobs(dim, N[dim], 1)
    mesh = knnrefine.refine(pts, K, periodic=request.param, box=unit_box(dim))
    return dim, request.param, pts, mesh


def exact_kth(pts, q, periodic):
    return cKDTree(pts, boxsize=1.0 if periodic else None).query(q, k=[K])[0][:, 0]


def test_one_type_in_both_dimensions(case):
    dim, periodic, pts, mesh = case
    dist = KnnDistance(mesh, pts)
    assert type(dist) is KnnDistance and dist.dim == dim == mesh.dim
    q = np.random.default_rng(2).random((5000, dim))
    np.testing.assert_allclose(dist.exact(q), exact_kth(pts, q, periodic), rtol=1e-12)
    rel = np.abs(dist(q) - dist.exact(q)) / dist.exact(q)
    assert np.median(rel) < 0.06 and rel.max() < 0.5
    err = dist.error()
    assert err["median"] < 0.06 and err["probes"] > 0
    # exact at the mesh's vertices in the box (the interpolant's nodes)
    v = mesh.vertices[((mesh.vertices >= 0) & (mesh.vertices <= 1)).all(axis=1)]
    np.testing.assert_allclose(dist(v), exact_kth(pts, v, periodic), rtol=1e-9)


def test_grid_is_the_estimate_at_the_cells_centres(case):
    dim, _, pts, mesh = case
    dist = KnnDistance(mesh, pts)
    shape = (7, 6) if dim == 2 else (5, 6, 7)
    *axes, values = dist.grid(shape)
    assert values.shape == shape and len(axes) == dim
    mesh_axes = np.meshgrid(*axes[::-1], indexing="ij")  # slowest axis first
    centres = np.stack(mesh_axes[::-1], axis=-1)
    np.testing.assert_allclose(values, dist(centres), rtol=1e-9)
    with pytest.raises(InputError, match="positive whole numbers"):
        dist.grid((4,) * (dim + 1))


def test_density_integrates_to_one_and_masses_agree_with_monte_carlo(case):
    dim, periodic, pts, mesh = case
    f = KnnDensity(mesh, pts)
    assert f.mass() == pytest.approx(1.0, rel=1e-9)
    assert f.raw_mass == pytest.approx(1.0, rel=0.35)  # the raw kNN estimate's mass is near 1
    rng = np.random.default_rng(3)
    region = (0.2,) * dim + (0.6,) * dim
    u = 0.2 + 0.4 * rng.random((100_000, dim))
    monte_carlo = f(u).mean() * 0.4**dim
    assert f.mass(region) == pytest.approx(monte_carlo, rel=0.02)
    # a region across the seam is the sum of its parts when periodic, clipped to the box if not
    across = (0.8,) * dim + (1.3,) * dim
    if periodic:
        parts = [(0.8, 1.0), (0.0, 0.3)]
        total = 0.0
        for corner in np.array(np.meshgrid(*[[0, 1]] * dim)).reshape(dim, -1).T:
            lo = [parts[c][0] for c in corner]
            hi = [parts[c][1] for c in corner]
            total += f.mass((*lo, *hi))
        assert f.mass(across) == pytest.approx(total, rel=1e-9)
    else:
        assert f.mass(across) == pytest.approx(f.mass((0.8,) * dim + (1.0,) * dim), rel=1e-12)


def test_samples_fall_in_regions_by_their_mass(case):
    dim, _, pts, mesh = case
    f = KnnDensity(mesh, pts)
    draws = f.sample(40_000, np.random.default_rng(4))
    assert draws.shape == (40_000, dim)
    assert ((draws >= 0) & (draws <= 1)).all()
    for region in [(0.2,) * dim + (0.45,) * dim, (0.0,) * dim + (0.5,) * dim]:
        lo, hi = np.array(region[:dim]), np.array(region[dim:])
        share = ((draws >= lo) & (draws <= hi)).all(axis=1).mean()
        p = f.mass(region)
        assert abs(share - p) < 4 * np.sqrt(p * (1 - p) / len(draws)) + 1e-3


def test_refusals_name_the_dimension(dim):
    pts = blobs(dim, 600, 5)
    mesh = knnrefine.refine(pts, K, periodic=True, box=unit_box(dim))
    other = blobs(5 - dim, 600, 5)
    with pytest.raises(InputError, match=f"shape \\(n, {dim}\\)|{dim} columns"):
        KnnDistance(mesh, other)
    dist = KnnDistance(mesh, pts)
    with pytest.raises(InputError, match=f"\\(\\.\\.\\., {dim}\\)"):
        dist(np.zeros((3, 5 - dim)))
    with pytest.raises(InputError, match=f"{2 * dim} numbers"):
        dist.integrate(lambda d: d, region=(0, 0, 1, 1, 1))
    with pytest.raises(InputError, match="refined without weights"):
        KnnDistance(mesh, pts, weights=np.ones(len(pts)))
    if dim == 2:
        with pytest.raises(InputError, match="built for meshes in space"):
            dist.cdf([0.1])
    else:
        assert 0.0 <= float(dist.cdf([0.05])[0]) <= 1.0


def test_estimator_in_both_dimensions(dim):
    """fit, score_samples, score, sample, k="cv" and GridSearchCV with (n, d) data; the
    default estimate is the adaptive one in the plane and the kNN one in space."""
    sklearn = pytest.importorskip("sklearn")
    from sklearn.model_selection import GridSearchCV

    from knnrefine import KnnDensityEstimator

    X = blobs(dim, 1200, 7)
    est = KnnDensityEstimator(k=20, method="knn", box=unit_box(dim)).fit(X)
    assert est.n_features_in_ == dim and est.method_ == "knn" and est.mesh_.dim == dim
    reference = KnnDensity(est.mesh_, X)
    np.testing.assert_allclose(np.exp(est.score_samples(X[:50])), reference(X[:50]), rtol=1e-9)
    assert est.score(X[:50]) == pytest.approx(np.log(reference(X[:50])).sum())
    assert est.sample(7, random_state=0).shape == (7, dim)
    cv = KnnDensityEstimator(k="cv", method="knn", k_grid=[5, 40], cv=3, box=unit_box(dim))
    cv.fit(X)
    assert cv.k_ == cv.cv_ks_[np.argmax(cv.cv_scores_)]
    search = GridSearchCV(
        KnnDensityEstimator(method="knn", box=unit_box(dim)), {"k": [5, 40]}, cv=3
    )
    assert search.fit(X).best_params_["k"] in (5, 40)
    assert sklearn.base.clone(est).get_params() == est.get_params()
    if dim == 3:
        assert KnnDensityEstimator(k=20).fit(X).method_ == "knn"
        with pytest.raises(InputError, match='method="adaptive" is built for points in the plane'):
            KnnDensityEstimator(k=20, method="adaptive").fit(X)
    with pytest.raises(InputError, match=f"\\(\\.\\.\\., {dim}\\)"):
        est.score_samples(np.zeros((2, 5 - dim)))


def test_certify_returns_one_certificate_in_both_dimensions(case):
    dim, periodic, pts, mesh = case
    cert = knnrefine.certify(mesh, pts, samples=20_000)
    assert type(cert) is knnrefine.Certificate and cert.dim == dim and cert.passed
    assert cert.n == len(pts) and cert.m == len(mesh.vertices) and cert.n_probes > 0
    assert cert.alpha <= cert.alpha_hat <= cert.beta_hat <= cert.beta
    assert len(cert.alpha_hat_at) == dim and cert.size_integral > 0
    as_dict = cert.to_dict()
    assert as_dict["passed"] is True and as_dict["periodic"] == [periodic] * dim
    text = str(cert)
    assert "PASSED" in text and f"1 / d_Pk^{dim}" in text
    with pytest.raises(InputError, match="points"):
        knnrefine.certify(mesh, pts[:-1])
