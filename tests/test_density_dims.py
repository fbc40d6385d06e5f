"""KnnDistance and KnnDensity, one suite over both dimensions (the ``dim`` fixture): the same
calls on a mesh in the plane and in space, against independent oracles (scipy's kd-tree for
d_{P,k}, Monte Carlo for integrals and samples)."""

import numpy as np
import pytest
from conftest import assert_lattice_close, unit_box
from conftest import two_blobs as blobs
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
    default estimate is the adaptive one in both dimensions."""
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
    assert KnnDensityEstimator(k=20).fit(X).method_ == "adaptive"  # in both (issue 30)
    if dim == 3:
        with pytest.raises(InputError, match='shape="local" is built for points in the plane'):
            KnnDensityEstimator(k=20, shape="local").fit(X)
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


# -- the adaptive estimate in both dimensions (issue 30) -----------------------------------------

TRIWEIGHT_MASS = {2: np.pi / 4, 3: 64 * np.pi / 315}  # of (1 - |x|^2)^3 over the unit ball


def brute_adaptive(ad, pts, q, periodic, leave_out=None):
    """The adaptive estimate's kernel sums at q by brute force (numpy, every point, every
    image): isotropic triweights of radius h_i = c * unit extent (capped at the unit box's
    side), mass w_i / n each; periodic axes wrap (images one period away), the others fold
    (the query's mirror images in the sides). ``leave_out``: per query, the point left out."""
    dim = pts.shape[1]
    h = np.minimum(ad.bandwidth * ad.unit_extents, 1.0)
    amp = 1.0 / len(pts) / (TRIWEIGHT_MASS[dim] * h**dim)
    images = []
    for shift in np.array(np.meshgrid(*[[0, 1, 2]] * dim)).reshape(dim, -1).T:
        img = q.copy()
        for a, j in enumerate(shift):
            if j == 0:
                continue
            if periodic:
                img[:, a] += -1.0 if j == 1 else 1.0
            else:
                img[:, a] = -img[:, a] if j == 1 else 2.0 - img[:, a]
        images.append(img)
    out = np.zeros(len(q))
    for img in images:
        u = ((img[:, None, :] - pts[None]) ** 2).sum(-1) / h[None] ** 2
        terms = amp[None] * np.clip(1.0 - u, 0.0, None) ** 3
        if leave_out is not None:
            terms[np.arange(len(q)), leave_out] = 0.0
        out += terms.sum(1)
    return out


@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_adaptive_sums_match_brute_force(dim, periodic):
    """AdaptiveDensity in the plane and in space (issue 30 built it in space): its value at
    random points, and its leave-one-out values at the points, are the brute-force kernel
    sums (every kernel, every image) to rounding, at two smoothings; it integrates to 1."""
    from knnrefine.density import AdaptiveDensity

    pts = blobs(dim, 1500, 3)
    mesh = knnrefine.refine(pts, 30, periodic=periodic, box=unit_box(dim))
    ad = AdaptiveDensity(mesh, pts, bandwidth=1.3, sensitivity=0.3)
    q = np.random.default_rng(4).random((300, dim))
    for c, alpha in ((1.3, 0.3), (2.5, 0.5)):  # the second reaches past the sides
        ad.set_bandwidth(c, alpha)
        want = (1 - ad.eps) * brute_adaptive(ad, pts, q, periodic) + ad.eps * ad.knn(q)
        np.testing.assert_allclose(ad(q), want, rtol=1e-9)
        idx = np.arange(0, 1500, 37)
        s = brute_adaptive(ad, pts, pts[idx], periodic, leave_out=idx)
        n = len(pts)
        loo = (1 - ad.eps) * s * n / (n - 1) + ad.eps * ad.knn.constant / ad.pilot[idx] ** dim
        np.testing.assert_allclose(ad.loo(idx), np.log(loo), rtol=1e-9)
    *axes, values = ad.grid(24)
    cell = np.prod([a[1] - a[0] for a in axes])
    assert values.sum() * cell == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize(
    "case",
    ["general", "plane", pytest.param("duplicates", marks=pytest.mark.slow), "seam"],
)  # fmt: skip
def test_grid_through_lattices_in_space(case, monkeypatch):
    """The lattice grid in space (``lattice.draw3`` + ``read_grid``) against the exact sums
    at the centres, on general points, points on a plane, many duplicates and across a
    periodic seam: to about 1e-3 where the estimate is seen, never below 0, mass kept."""
    from knnrefine.density import AdaptiveDensity, adaptive

    rng = np.random.default_rng(9)
    periodic = case == "seam"
    if case == "general":
        X = blobs(3, 4000, 5)
    elif case == "plane":
        t = rng.random((3000, 2))
        X = np.concatenate([np.column_stack([t, 0.5 * np.ones(3000)]), rng.random((500, 3))])
    elif case == "duplicates":
        X = np.concatenate([np.repeat(rng.random((30, 3)), 50, axis=0), rng.random((800, 3))])
    else:
        X = np.column_stack([rng.random((3000, 2)), rng.normal(0.0, 0.02, 3000) % 1.0])
    # (duplicates: d_Pk is 0 at the sites, refined down to min_size; a coarse floor)
    mesh = knnrefine.refine(X, 30, box=unit_box(3), periodic=periodic, min_size=1e-3)
    ad = AdaptiveDensity(mesh, X, bandwidth=1.2)
    axes = [(np.arange(m) + 0.5) / m for m in (64, 60, 56)]  # x, y, z: oblong cells
    g = np.meshgrid(*axes[::-1], indexing="ij")
    centres = np.column_stack([a.ravel() for a in g[::-1]])
    exact = ad._sums(ad._metric.frame(centres))[0]
    monkeypatch.setattr(adaptive, "EXACT_TERMS", 0.0)  # lattices at any size
    got = ad._grid_sums(axes).ravel()
    assert_lattice_close(got, exact, worst=1e-3, mean_rel=1e-4)
    # only kernels on the grid's own lattice: exact
    monkeypatch.setattr(adaptive, "LATTICE_SAMPLES", 1e6)
    np.testing.assert_allclose(ad._grid_sums(axes).ravel(), exact, rtol=1e-9, atol=1e-12)


def test_adaptive_samples_follow_the_estimate_in_space():
    """Draws from the adaptive estimate in space (u ~ Beta(3/2, 4) in a ball) have the
    estimate's mean and mass per octant (the octants' masses from a fine grid of it)."""
    from knnrefine.density import AdaptiveDensity

    pts = blobs(3, 3000, 6)
    mesh = knnrefine.refine(pts, 40, box=unit_box(3))
    ad = AdaptiveDensity(mesh, pts, bandwidth=1.5)
    draws = ad.sample(200_000, np.random.default_rng(0))
    assert ((draws >= 0) & (draws <= 1)).all()
    *axes, values = ad.grid(48)
    cell = np.prod([a[1] - a[0] for a in axes])
    octant = [(a >= 0.5).astype(int) for a in np.meshgrid(*axes[::-1], indexing="ij")]
    index = octant[0] * 4 + octant[1] * 2 + octant[2]  # z, y, x halves
    grid_mass = np.bincount(index.ravel(), weights=values.ravel() * cell, minlength=8)
    z, y, x = (draws[:, 2] >= 0.5), (draws[:, 1] >= 0.5), (draws[:, 0] >= 0.5)
    drawn_mass = np.bincount(z * 4 + y * 2 + x, minlength=8) / len(draws)
    np.testing.assert_allclose(drawn_mass, grid_mass, atol=0.006)


@pytest.mark.parametrize("periodic", [False, True], ids=["box", "torus"])
def test_exact_d_pk_in_space_by_windows_matches_scipy(periodic):
    """KnnDistance.exact in space at k >= WINDOWS_FROM_K goes through the counting tree's
    windows about sampled guesses (issue 30): scipy's answer at clustered points with
    duplicates, on the box and on the torus, at query points anywhere and at the points."""
    from knnrefine._domains.space.density import WINDOWS_FROM_K

    pts = blobs(3, 20000, 11)
    pts[:300] = pts[300:600]  # duplicates
    k = WINDOWS_FROM_K + 20
    mesh = knnrefine.refine(pts, k, periodic=periodic, box=unit_box(3))
    dist = KnnDistance(mesh, pts)
    q = np.concatenate([np.random.default_rng(3).random((3000, 3)), pts[:200]])
    want = cKDTree(pts, boxsize=1.0 if periodic else None).query(q, k=[k])[0][:, 0]
    np.testing.assert_allclose(dist.exact(q), want, rtol=1e-12)
