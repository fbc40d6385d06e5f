"""The adaptive kernel estimate (AdaptiveDensity, KnnDensityEstimator's default) against
brute force: the sum of every folded or wrapped triweight kernel written out from its
definition, leave-one-out likelihoods recomputed by hand, integrals on fine grids, binomial
counts of samples, Monte Carlo spread for the standard error."""

import itertools

import numpy as np
import pytest
from conftest import assert_binned_close, assert_lattice_close, load_shared

import knnrefine
from knnrefine import InputError, KnnDensityEstimator
from knnrefine.density import AdaptiveDensity, KnnDensity, default_pilot_k


def mixture(n, seed=0):
    rng = np.random.default_rng(seed)
    m = n // 4
    x = np.concatenate(
        [rng.normal([0.35, 0.4], 0.1, (n - m, 2)), rng.normal([0.75, 0.7], 0.02, (m, 2))]
    )
    return x[np.all((x > 0) & (x < 1), axis=1)]


def ridge(n, seed=0, width=0.004):
    """Points along a circular arc of radius 0.3, spread `width` across it."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.2, 2.8, n)
    r = 0.3 + width * rng.normal(size=n)
    return np.column_stack([0.5 + r * np.cos(t), 0.3 + r * np.sin(t)])


def brute(points, pilot, c, q, box, periodic, weights=None, shapes=None):
    """The estimate's kernel part at q from its definition: sum over points i and over the
    images of q (wrapped along periodic axes, mirrored in the sides along the others) of
    w_i / W * K((q' - X_i) / (c d_i)), K the triweight (1 - |z|^2)^3 of mass 1 (shapes: the
    unit-determinant matrix S_i, the kernel then (1 - z^T S_i^-1 z)^3)."""
    lo, hi = np.array(box[:2]), np.array(box[2:])
    w = np.ones(len(points)) if weights is None else weights
    h = c * pilot
    out = np.zeros(len(q))
    images = []
    for a in range(2):
        if periodic[a]:
            images.append([0.0, -(hi[a] - lo[a]), hi[a] - lo[a]])
        else:
            images.append(None)
    for j, x in enumerate(q):
        total = 0.0
        xs = (
            [x[0] + s for s in images[0]]
            if images[0]
            else [x[0], 2 * lo[0] - x[0], 2 * hi[0] - x[0]]
        )
        ys = (
            [x[1] + s for s in images[1]]
            if images[1]
            else [x[1], 2 * lo[1] - x[1], 2 * hi[1] - x[1]]
        )
        for ix in xs:
            for iy in ys:
                ex, ey = ix - points[:, 0], iy - points[:, 1]
                if shapes is None:
                    u = (ex * ex + ey * ey) / h**2
                else:
                    s11, s12, s22 = shapes.T  # inverse of a unit-determinant 2 x 2
                    u = (s22 * ex * ex - 2 * s12 * ex * ey + s11 * ey * ey) / h**2
                k = np.where(u < 1, np.clip(1 - u, 0, None) ** 3, 0.0) * 4 / (np.pi * h**2)
                total += np.sum(w * k)
        out[j] = total / w.sum()
    return out


@pytest.fixture(scope="module")
def planar():
    X = mixture(2500)
    mesh = knnrefine.refine(X, 25, box=(0, 0, 1, 1))
    return X, mesh, AdaptiveDensity(mesh, X, bandwidth=1.3)


def test_sums_match_brute_force_planar(planar):
    X, mesh, ad = planar
    q = np.concatenate([np.random.default_rng(1).random((150, 2)), [[0, 0], [1, 0.5]]])
    ref = brute(X, ad.pilot, 1.3, q, mesh.box, (False, False))
    got = (ad(q) - ad.eps * ad.knn(q)) / (1 - ad.eps)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)


def test_pilot_is_the_mesh_estimate_of_d_pk(planar):
    """Abramson's square-root law with the kNN pilot: bandwidths c d_{P,k}(X_i), d_{P,k} from
    the mesh (within a few percent of exact)."""
    X, mesh, ad = planar
    np.testing.assert_allclose(ad.pilot, KnnDensity(mesh, X).distance(X), rtol=1e-12)
    exact = KnnDensity(mesh, X).distance.exact(X)
    assert np.median(np.abs(ad.pilot / exact - 1)) < 0.03


@pytest.mark.parametrize("periodic", [(True, True), (True, False)])
def test_sums_match_brute_force_periodic(periodic):
    rng = np.random.default_rng(2)
    X = np.concatenate([rng.normal(0.02, 0.06, (1200, 2)) % 1, rng.random((300, 2))])
    w = rng.gamma(2.0, 1.0, len(X))
    mesh = knnrefine.refine(X, 20, box=(0, 0, 1, 1), periodic=periodic, weights=w)
    ad = AdaptiveDensity(mesh, X, bandwidth=2.0, weights=w)
    q = np.concatenate([rng.random((120, 2)), [[0.0, 0.0], [0.999, 0.001]]])
    ref = brute(X, ad.pilot, 2.0, q, mesh.box, periodic, weights=w)
    got = (ad(q) - ad.eps * ad.knn(q)) / (1 - ad.eps)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    # wrapping: a query and its copy a period away agree
    if all(periodic):
        np.testing.assert_allclose(ad(q + [2.0, -1.0]), ad(q), rtol=1e-12)


def test_local_shapes_match_brute_force_and_follow_a_ridge():
    X = ridge(3000, width=0.001)  # d_Pk (about 0.013) much wider than the ridge
    mesh = knnrefine.refine(X, 100, box=(0, 0, 1, 1))
    ad = AdaptiveDensity(mesh, X, bandwidth=1.0, shape="local")
    shapes = np.empty((len(X), 3))
    rows = ad._rows
    order = rows[:, 8].astype(int)
    shapes[order] = ad._q * ad.pilot[order, None] ** 2  # S^-1 entries: (s22, -s12, s11)
    shapes = shapes[:, [2, 1, 0]] * [1, -1, 1]
    np.testing.assert_allclose(shapes[:, 0] * shapes[:, 2] - shapes[:, 1] ** 2, 1, rtol=1e-9)
    q = X[:100] + np.random.default_rng(3).normal(0, 0.01, (100, 2))
    ref = brute(X, ad.pilot, 1.0, q, mesh.box, (False, False), shapes=shapes)
    got = (ad(q) - ad.eps * ad.knn(q)) / (1 - ad.eps)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    # the long axis lies along the arc (tangent (-sin t, cos t) at angle t about the centre)
    t = np.arctan2(X[:, 1] - 0.3, X[:, 0] - 0.5)
    s11, s12, s22 = shapes.T
    tangent = s11 * np.sin(t) ** 2 - 2 * s12 * np.sin(t) * np.cos(t) + s22 * np.cos(t) ** 2
    normal = s11 * np.cos(t) ** 2 + 2 * s12 * np.sin(t) * np.cos(t) + s22 * np.sin(t) ** 2
    assert np.median(tangent / normal) > 20  # capped at max_ratio^2 = 100


@pytest.mark.parametrize(
    "shape, periodic", [("isotropic", False), ("local", False), ("isotropic", True)]
)
def test_it_integrates_to_one_over_the_box(shape, periodic):
    """Folding (reflection in the sides) and wrapping keep every kernel's mass in the box."""
    X = mixture(2000, seed=4)
    X[:50] = np.random.default_rng(4).random((50, 2)) * 0.03  # a cluster at a corner
    mesh = knnrefine.refine(X, 20, box=(0, 0, 1, 1), periodic=periodic)
    ad = AdaptiveDensity(mesh, X, bandwidth=2.5, shape=shape)
    _, _, g = ad.grid((1000, 1000))
    assert g.mean() == pytest.approx(1.0, abs=2e-3)


def test_leave_one_out_matches_brute_force(planar):
    """f_-i(X_i): the kernel sum without point i, renormalised by W / (W - 1), plus the eps
    part; with a duplicated point, both copies leave together."""
    X, mesh, ad = planar
    Xd = np.concatenate([X, X[:5]])  # five points twice
    mesh2 = knnrefine.refine(Xd, 25, box=(0, 0, 1, 1))
    ad2 = AdaptiveDensity(mesh2, Xd, bandwidth=1.3)
    idx = np.array([0, 1, 2, 100, 2000, len(Xd) - 1])
    got = ad2.loo(idx)
    n = len(Xd)
    ref = []
    for i in idx:
        keep = np.all(Xd != Xd[i], axis=1)
        part = brute(Xd[keep], ad2.pilot[keep], 1.3, Xd[[i]], mesh2.box, (False, False))
        part *= keep.sum() / n  # brute normalises by the kept weight
        knn = ad2.knn.constant / ad2.pilot[i] ** 2
        ref.append(np.log((1 - ad2.eps) * part[0] * n / keep.sum() + ad2.eps * knn))
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    curve = ad2.loo_curve([0.7, 1.3], idx)
    assert curve[1] == pytest.approx(np.mean(ref), rel=1e-12)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.6])
def test_sensitivity_rescales_extents_around_the_geometric_mean(planar, alpha):
    """h_i = c G (d_i / G)^(2 alpha), G the geometric mean of the pilot: the sums match the
    brute-force estimate with those extents; alpha = 0 is the fixed-bandwidth estimate."""
    X, mesh, _ = planar
    ad = AdaptiveDensity(mesh, X, bandwidth=1.3, sensitivity=alpha)
    d = ad.pilot
    g = np.exp(np.mean(np.log(d)))
    np.testing.assert_allclose(ad.unit_extents, g * (d / g) ** (2 * alpha), rtol=1e-12)
    q = np.random.default_rng(3).random((200, 2))
    ref = brute(X, ad.unit_extents, 1.3, q, mesh.box, (False, False))
    got = (ad(q) - ad.eps * ad.knn(q)) / (1 - ad.eps)
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)
    if alpha == 0.0:  # one bandwidth for every point
        fixed = brute(X, np.full(len(X), g), 1.3, q, mesh.box, (False, False))
        np.testing.assert_allclose(got, fixed, rtol=1e-9, atol=1e-12)  # G by exp(log)
    # changing it back and forth is exact
    ad.set_bandwidth(0.8, 0.5)
    ad.set_bandwidth(1.3, alpha)
    np.testing.assert_allclose((ad(q) - ad.eps * ad.knn(q)) / (1 - ad.eps), got, rtol=1e-12)


def test_search_climbs_to_a_local_best_of_the_grid():
    """The climb's grid pair (the best grid row of the table) scores at least as well as
    each of its grid neighbours, recomputed here on a fresh estimate; the table's scores are
    the leave-one-out likelihoods of their pairs; the curve is the table at the chosen
    alpha."""
    X = mixture(3000, seed=21)
    est = KnnDensityEstimator(k=40).fit(X)
    ad = AdaptiveDensity(est.mesh_, X)
    alphas, cs = est.SENSITIVITIES, est.BANDWIDTHS
    on_grid = np.isin(est.loo_scores_[:, 1], cs)
    alpha, c, _ = est.loo_scores_[on_grid][np.argmax(est.loo_scores_[on_grid, 2])]
    assert alpha == est.sensitivity_
    i, j = alphas.index(alpha), cs.index(c)
    best = ad.loo_curve([cs[j]], None, alphas[i])[0]
    for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
        if 0 <= a < len(alphas) and 0 <= b < len(cs):
            assert ad.loo_curve([cs[b]], None, alphas[a])[0] <= best
    for alpha, c, score in est.loo_scores_:
        assert ad.loo_curve([c], None, alpha)[0] == pytest.approx(score, rel=1e-12)
    at = est.loo_scores_[est.loo_scores_[:, 0] == est.sensitivity_]
    assert sorted(at[:, 1]) == list(est.bandwidths_)
    # the climb starts at Abramson's (1/2, 1): never worse than that
    assert best >= ad.loo_curve([1.0], None, 0.5)[0]


def _one_se_choice(ad, alpha, c0, sample=None, widest=8.0):
    """The one-standard-error rule from its definition: on c0 * 2^(j/4), the best of
    j = -1, 0, 1, then the largest j above it with every score up to it within one
    standard error (of the paired per-point differences) of the best's."""
    h = 2**0.25
    per = {}

    def loo(j):
        if j not in per:
            ad.set_bandwidth(c0 * h**j, alpha)
            per[j] = ad.loo(sample)
        return per[j]

    best = max((-1, 0, 1), key=lambda j: loo(j).mean())
    j = best
    while c0 * h ** (j + 1) <= widest * (1 + 1e-9):
        d = loo(j + 1) - loo(best)
        if d.mean() < -d.std() / np.sqrt(len(d)):
            break
        j += 1
    return c0 * h**j, c0 * h**best


def test_search_ends_at_the_widest_half_step_within_one_standard_error():
    """The chosen bandwidth is the one-standard-error rule's on half steps of the grid from
    the climb's pair (recomputed from the definition), never narrower than the best-scoring
    half step; on a sharp edge (a uniform disk over a background) the wider choice lowers
    the L1 error against the true density, at about the same held-out likelihood (the study's
    sharp-edge truth, where the grid's best lost L1 at 1e6)."""
    rng = np.random.default_rng(42)
    R = 0.2

    def draw(n):
        on = rng.random(n) < 0.5
        x = rng.random((n, 2))
        r, t = R * np.sqrt(rng.random(n)), 2 * np.pi * rng.random(n)
        x[on] = 0.5 + (r[:, None] * np.column_stack([np.cos(t), np.sin(t)]))[on]
        return x

    def pdf(x):
        return 0.5 * (np.hypot(*(x - 0.5).T) <= R) / (np.pi * R * R) + 0.5

    X, test = draw(40000), draw(20000)
    est = KnnDensityEstimator(box=(0, 0, 1, 1), sensitivity=0.5).fit(X)
    # (a thinned search walks the full estimate from a scaled bandwidth: grid values to
    # rounding)
    on_grid = np.isclose(est.loo_scores_[:, 1, None], est.BANDWIDTHS, rtol=1e-9).any(axis=1)
    c0 = est.loo_scores_[on_grid][np.argmax(est.loo_scores_[on_grid, 2]), 1]
    ad = AdaptiveDensity(est.mesh_, X)
    sample = np.sort(np.random.default_rng(0).choice(len(X), 20000, False))
    chosen, best = _one_se_choice(ad, 0.5, c0, sample)
    assert est.bandwidth_ == pytest.approx(chosen, rel=1e-12)
    assert est.bandwidth_ >= best
    u = np.random.default_rng(5).random((200000, 2))

    def l1_and_ll(c):
        ad.set_bandwidth(c, 0.5)
        return np.mean(np.abs(ad(u) - pdf(u))), np.mean(np.log(ad(test)))

    (l1, ll), (l1_best, ll_best) = l1_and_ll(chosen), l1_and_ll(best)
    assert chosen > best  # this sample's likelihood is flat within its noise above the best
    assert l1 < 0.97 * l1_best
    assert ll > ll_best - 1e-3


def test_least_squares_table_holds_each_pairs_score():
    """With criterion="least-squares" every row of the table, the half steps of the last
    search included, is least_squares at its pair, recomputed on a fresh estimate."""
    X = mixture(3000, seed=24)
    est = KnnDensityEstimator(k=40, criterion="least-squares").fit(X)
    ad = AdaptiveDensity(est.mesh_, X)
    assert (~np.isin(est.loo_scores_[:, 1], est.BANDWIDTHS)).any()  # half steps present
    for alpha, c, score in est.loo_scores_:
        ad.set_bandwidth(c, alpha)
        assert ad.least_squares() == pytest.approx(score, rel=1e-12)
    rows = est.loo_scores_[est.loo_scores_[:, 0] == est.sensitivity_]
    assert est.bandwidth_ in rows[:, 1]
    # the choice is within one standard error of the best row (paired kernels and points)

    def terms(c):
        ad.set_bandwidth(c, est.sensitivity_)
        return ad.square_terms()[0], np.exp(ad.loo())  # the kernels' cubature (weights 1)

    (sq, lo), (sq0, lo0) = terms(est.bandwidth_), terms(rows[np.argmin(rows[:, 2]), 1])
    worse = (sq - sq0).mean() - 2 * (lo - lo0).mean()  # least-squares score difference
    se = np.sqrt((sq - sq0).var() / len(sq) + 4 * (lo - lo0).var() / len(X))
    assert worse <= se + 1e-12


def assert_square_integral_matches_the_grid(est, shape, smoothings=(0.7, 1.3, 2.6)):
    """``square_integral`` of an isotropic estimate against the midpoint rule on a grid of
    ``shape`` over its box, at the bandwidths ``smoothings``, and the same whatever the draws
    and seed."""
    from knnrefine.density import square_integral

    for c in smoothings:
        est.set_bandwidth(c)
        g = est.grid(shape)[-1]
        got = square_integral(est)
        assert got == pytest.approx(np.mean(g * g), rel=3e-3), (est.dim, c)
        assert square_integral(est, 10, seed=4) == got  # draws and seed unused


def test_square_integral_by_cubature_matches_a_fine_grid(planar):
    """The integral of f^2 inside the least-squares score: a cubature over the kernels (the
    binned sums at nodes folded into the box) against a midpoint rule on a 1000 x 1000 grid,
    in the plane folded and wrapped; no draws; the score is that integral less twice the
    mean leave-one-out density."""
    from knnrefine.density import square_integral

    X, mesh, ad = planar
    torus = knnrefine.refine(X, 25, box=(0, 0, 1, 1), periodic=True)
    for est in (ad, AdaptiveDensity(torus, X)):
        assert_square_integral_matches_the_grid(est, (1000, 1000))
    ad.set_bandwidth(1.3)
    idx = np.arange(0, len(ad.pilot), 7)
    loo = np.mean(np.exp(ad.loo(idx)))
    assert ad.least_squares(idx) == pytest.approx(square_integral(ad) - 2 * loo, rel=1e-12)


@pytest.mark.slow
def test_square_integral_by_cubature_in_space_matches_a_fine_grid():
    """The cubature of f^2 over balls (icosahedral directions) against a 160^3 midpoint rule,
    a wide cluster reaching the sides (folded) and a narrow one. (Narrower kernels need a
    finer grid than a test affords: at c = 0.7, 120^3 is itself 2.4 % off, 200^3 agrees
    with the cubature within 0.3 %.)"""
    rng = np.random.default_rng(3)
    X3 = np.concatenate([rng.normal(0.4, 0.12, (1500, 3)), rng.normal(0.8, 0.03, (500, 3))]) % 1
    space = AdaptiveDensity(knnrefine.refine(X3, 20, box=(0, 0, 0, 1, 1, 1)), X3)
    assert_square_integral_matches_the_grid(space, (160, 160, 160), (1.3, 2.6))


def test_square_integral_by_draws_matches_a_fine_grid(planar):
    """shape="local" (no lattices for ellipses) and the plain kNN estimate integrate f^2 by
    Monte Carlo, the mean of f at draws from f (seeded, so repeatable), within its noise of a
    1000 x 1000 grid's midpoint rule."""
    from knnrefine.density import square_integral

    X, mesh, _ = planar
    local = AdaptiveDensity(mesh, X, bandwidth=1.3, shape="local")
    _, _, g = local.grid((1000, 1000))
    draws = 200000
    got = square_integral(local, draws, seed=3)
    spread = np.std(local(local.sample(20000, np.random.default_rng(4)))) / np.sqrt(draws)
    assert abs(got - np.mean(g * g)) < 4 * spread + 1e-3 * got
    assert square_integral(local, 1000, seed=3) == square_integral(local, 1000, seed=3)
    idx = np.arange(0, len(local.pilot), 7)
    loo = np.mean(np.exp(local.loo(idx)))
    score = local.least_squares(idx, draws=draws, seed=3)
    assert score == pytest.approx(got - 2 * loo, rel=1e-12)


@pytest.mark.slow
def test_least_squares_tracks_the_integrated_squared_error():
    """Uniform density on the unit square with a hole (a sharp edge): least-squares
    cross-validation plus the constant integral of the truth^2 follows the integrated squared
    error (on a grid, against the exact density) across bandwidths, its choice is the best
    of the grid by that error, and it is wider than likelihood's, with a lower L1 error."""
    rng = np.random.default_rng(31)
    X = rng.random((60000, 2))
    X = X[np.hypot(*(X - 0.5).T) > 0.25][:20000]
    f0 = 1 / (1 - np.pi / 16)
    xs = (np.arange(600) + 0.5) / 600
    gx, gy = np.meshgrid(xs, xs)
    truth = np.where(np.hypot(gx - 0.5, gy - 0.5) > 0.25, f0, 0.0)
    fits = {
        crit: KnnDensityEstimator(box=(0, 0, 1, 1), criterion=crit, sensitivity=0).fit(X)
        for crit in ("likelihood", "least-squares")
    }
    ad = fits["least-squares"].density_
    errors, scores = {}, {}
    for c in ad.bandwidth * np.array([0.5, 1 / np.sqrt(2), 1, np.sqrt(2), 2]):
        ad.set_bandwidth(c, 0)
        g = ad.grid((600, 600))[2]
        errors[c] = (np.mean((g - truth) ** 2), np.mean(np.abs(g - truth)))
        scores[c] = ad.least_squares() + f0
    ise = {c: e[0] for c, e in errors.items()}
    chosen = fits["least-squares"].bandwidth_
    # the integral of f^2 by cubature over the kernels: the scores follow the error closely
    for c in ise:
        assert scores[c] == pytest.approx(ise[c], abs=5e-3)
        assert scores[c] - scores[chosen] == pytest.approx(ise[c] - ise[chosen], abs=5e-3)
    assert ise[chosen] <= 1.05 * min(ise.values())
    assert chosen > fits["likelihood"].bandwidth_
    ll = fits["likelihood"]
    g_ll = np.exp(ll.score_samples(np.column_stack([gx.ravel(), gy.ravel()])))
    assert errors[chosen][1] < np.mean(np.abs(g_ll - truth.ravel()))


def test_least_squares_k_by_cross_validation():
    """k="cv" with criterion="least-squares": each candidate's score is the mean over folds
    of (integral of the fold's f^2) - 2 (mean of f at the held-out points), recomputed by
    hand; the smallest wins."""
    from knnrefine.density import square_integral
    from knnrefine.density.estimator import cv_folds

    X = mixture(1500, seed=13)
    options = {"criterion": "least-squares", "method": "knn", "random_state": 2}
    est = KnnDensityEstimator(k="cv", k_grid=[5, 20, 80], cv=3, **options).fit(X)
    by_hand = []
    for k in est.cv_ks_:
        total = 0.0
        for test in cv_folds(len(X), 3, 2):
            train = np.setdiff1d(np.arange(len(X)), test)
            fold = KnnDensityEstimator(k=int(k), box=est.box_, **options).fit(X[train])
            held = np.mean(np.exp(fold.score_samples(X[test])))
            total += (square_integral(fold.density_, est.loo_points) - 2 * held) / 3
        by_hand.append(total)
    np.testing.assert_allclose(est.cv_scores_, by_hand, rtol=1e-12)
    assert est.k_ == est.cv_ks_[int(np.argmin(by_hand))]


def test_bootstrap_holds_the_chosen_sensitivity(monkeypatch):
    """regression: bootstrap refits held the bandwidth fixed but searched the sensitivity
    again (sensitivity="cv" was passed on), so each refit ran the leave-one-out climb."""
    import knnrefine.density

    X = mixture(1500, seed=8)
    est = KnnDensityEstimator(k=30).fit(X)

    def no_search(*args, **kwargs):
        raise AssertionError("a bootstrap refit searched the smoothing again")

    monkeypatch.setattr(knnrefine.density, "choose_smoothing", no_search)
    lo, hi = est.bootstrap(X[:5], n_boot=3, random_state=1)
    assert np.all(lo <= hi)


def test_fixed_sensitivity_searches_the_bandwidth_only():
    X = mixture(2000, seed=22)
    est = KnnDensityEstimator(k=30, sensitivity=0.5).fit(X)
    assert est.sensitivity_ == 0.5 and set(est.loo_scores_[:, 0]) == {0.5}
    both_fixed = KnnDensityEstimator(k=30, sensitivity=0.2, bandwidth=1.5).fit(X)
    assert (both_fixed.sensitivity_, both_fixed.bandwidth_) == (0.2, 1.5)
    assert not hasattr(both_fixed, "loo_scores_")


@pytest.mark.slow
def test_heavy_tails_choose_a_sensitivity_below_abramsons():
    """Student t (3 dof) product: the search leaves Abramson's 1/2 for a flatter law (wider
    kernels at the peak); the L1 error against the true density, by importance sampling,
    falls, and the held-out likelihood does not get worse."""
    from scipy.stats import t as student

    rng = np.random.default_rng(23)
    box = (-20, -20, 20, 20)

    def draw(n):
        x = rng.standard_t(3, (3 * n, 2))
        return x[(np.abs(x) <= 20).all(axis=1)][:n]

    X, test = draw(20000), draw(20000)
    z = (student.cdf(20, 3) - student.cdf(-20, 3)) ** 2
    pdf = student.pdf(test[:, 0], 3) * student.pdf(test[:, 1], 3) / z
    chosen = KnnDensityEstimator(box=box).fit(X)
    abramson = KnnDensityEstimator(box=box, sensitivity=0.5).fit(X)
    assert chosen.sensitivity_ < 0.5

    def l1(est):  # integral |f - p| = E_p |f / p - 1|
        return np.mean(np.abs(np.exp(est.score_samples(test)) / pdf - 1))

    assert l1(chosen) < 0.85 * l1(abramson)
    assert chosen.score(test) >= abramson.score(test) - 1e-3 * len(test)


def test_samples_follow_the_estimate(planar):
    """Counts of samples in rectangles are binomial with the estimate's mass there (the
    mass by a fine midpoint grid)."""
    _, _, ad = planar
    s = ad.sample(40000, np.random.default_rng(5))
    assert ((s >= 0) & (s <= 1)).all()
    xs, ys, g = ad.grid((800, 800))
    for x0, y0, x1, y1 in [(0.2, 0.2, 0.5, 0.6), (0.7, 0.65, 0.8, 0.75), (0.0, 0.0, 0.3, 1.0)]:
        inx = (xs >= x0) & (xs <= x1)
        iny = (ys >= y0) & (ys <= y1)
        p = g[np.ix_(iny, inx)].sum() / g.size
        hit = np.mean((s[:, 0] >= x0) & (s[:, 0] <= x1) & (s[:, 1] >= y0) & (s[:, 1] <= y1))
        assert abs(hit - p) < 4.5 * np.sqrt(p * (1 - p) / len(s)) + 2e-3


def test_estimator_default_is_adaptive_with_its_bandwidth_from_the_curve():
    X = mixture(3000, seed=6)
    est = KnnDensityEstimator().fit(X)
    assert isinstance(est.density_, AdaptiveDensity)
    # the curve is the leave-one-out likelihood, recomputed at the chosen bandwidth, which
    # is on the curve and within one standard error of its best
    again = AdaptiveDensity(est.mesh_, X, bandwidth=est.bandwidth_, sensitivity=est.sensitivity_)
    chosen = again.loo()
    at = est.bandwidth_scores_[list(est.bandwidths_).index(est.bandwidth_)]
    assert at == pytest.approx(np.mean(chosen), rel=1e-12)
    again.set_bandwidth(est.bandwidths_[int(np.argmax(est.bandwidth_scores_))])
    d = chosen - again.loo()
    assert np.mean(d) >= -d.std() / np.sqrt(len(d)) - 1e-12
    # held out, it beats the plain kNN estimate at the same k
    test = mixture(3000, seed=7)
    knn = KnnDensityEstimator(k=est.k_, method="knn").fit(X)
    assert est.score(test) > knn.score(test)


def test_weights_are_relative():
    """Issue 30: the weights' scale does not change the adaptive fit: the same k (from
    n_eff when not given), the same chosen smoothing and leave-one-out curve, the same
    density (weights normalised to sum 1 raised "k must be an integer in [1, n = 1]")."""
    X = mixture(800, seed=4)
    w = np.random.default_rng(5).integers(1, 4, len(X)).astype(float)
    a = KnnDensityEstimator().fit(X, sample_weight=w)
    b = KnnDensityEstimator().fit(X, sample_weight=w / w.sum())
    c = KnnDensityEstimator().fit(X, sample_weight=w * 1000)
    probes = mixture(300, seed=6)
    for other in (b, c):
        assert other.k_ == a.k_ and other.bandwidth_ == a.bandwidth_
        np.testing.assert_allclose(other.bandwidth_scores_, a.bandwidth_scores_, rtol=1e-9)
        np.testing.assert_allclose(other.score_samples(probes), a.score_samples(probes),
                                   rtol=1e-9)  # fmt: skip


def test_ties_do_not_pull_the_bandwidth_to_zero():
    """regression: rounded data (every point five times) chose the smallest bandwidth when a
    point's copies stayed in its leave-one-out sum."""
    X = np.repeat(mixture(600, seed=8), 5, axis=0)
    est = KnnDensityEstimator(k=40).fit(X)
    plain = KnnDensityEstimator(k=8).fit(X[::5])
    assert est.bandwidth_ >= plain.bandwidth_ / 1.5 and est.bandwidth_ > est.bandwidths_[0]


def test_whiten_makes_the_estimate_scale_equivariant():
    """Axes in different units (the second 1000 times the first): the whitened estimate of the
    stretched data is the whitened estimate of the original, divided by the stretch."""
    X = mixture(1500, seed=9)
    stretch = np.array([1.0, 1000.0])
    a = KnnDensityEstimator(k=20, whiten=True).fit(X)
    b = KnnDensityEstimator(k=20, whiten=True).fit(X * stretch)
    probes = mixture(200, seed=10)
    np.testing.assert_allclose(
        b.score_samples(probes * stretch), a.score_samples(probes) - np.log(1000), rtol=1e-6
    )
    s = b.sample(3000, random_state=0)
    lo, hi = np.array(b.box_[:2]), np.array(b.box_[2:])
    inside = np.all((s >= lo) & (s <= hi), axis=1)  # but for the tail's few (1 / n)
    assert inside.mean() > 0.995 and s[inside, 1].std() > 100 * s[inside, 0].std()


def test_local_shape_wins_on_a_thin_ridge():
    """A ridge 0.001 wide, d_Pk about 0.0065 (k = 100): ellipses along it score better held
    out than disks (0.047 nats per point here), and both far better than the kNN estimate,
    whose balls span the ridge (1.6 nats)."""
    X, test = ridge(6000, seed=11, width=0.001), ridge(6000, seed=12, width=0.001)
    box = (0, 0, 1, 1)
    iso = KnnDensityEstimator(k=100, box=box).fit(X).score(test) / len(test)
    local = KnnDensityEstimator(k=100, shape="local", box=box).fit(X).score(test) / len(test)
    knn = KnnDensityEstimator(k=100, method="knn", box=box).fit(X).score(test) / len(test)
    assert local > iso + 0.02 and iso > knn + 1.0


def test_adaptive_k_by_cross_validation():
    """k="cv" with the adaptive estimate: held-out folds, each fitted at the smoothing the
    leave-one-out search chose for that k over all the points, recomputed by hand; the
    estimate kept is the chosen k's fit over all the points, search record included (issue
    53: no k fitted twice). (Leave-one-out alone cannot choose the pilot's k: the pilot is
    computed with the left-out point, which favours small k.)"""
    from knnrefine.density.estimator import cv_folds

    X = mixture(1500, seed=13)
    est = KnnDensityEstimator(k="cv", k_grid=[5, 20, 80], cv=3, random_state=2).fit(X)
    by_hand = []
    for k, (alpha, c) in zip(est.cv_ks_, est.cv_smoothings_, strict=True):
        whole = KnnDensityEstimator(k=int(k), box=est.box_, random_state=2).fit(X)
        assert (whole.sensitivity_, whole.bandwidth_) == (alpha, c)
        total = 0.0
        for test in cv_folds(len(X), 3, 2):
            train = np.setdiff1d(np.arange(len(X)), test)
            fold = KnnDensityEstimator(k=int(k), box=est.box_, sensitivity=alpha, bandwidth=c)
            total += fold.fit(X[train]).score(X[test])
        by_hand.append(total / len(X))
    np.testing.assert_allclose(est.cv_scores_, by_hand, rtol=1e-12)
    best = int(np.argmax(by_hand))
    assert est.k_ == est.cv_ks_[best]
    whole = KnnDensityEstimator(k=int(est.k_), box=est.box_, random_state=2).fit(X)
    np.testing.assert_array_equal(est.loo_scores_, whole.loo_scores_)
    np.testing.assert_allclose(est.density_(X[:50]), whole.density_(X[:50]), rtol=1e-12)


def test_adaptive_k_by_cross_validation_walks_the_doubling_grid():
    """Without k_grid the adaptive k="cv" scores the default pilot's k times 1/2 to 8 by
    walking from the default towards the better neighbour while the score improves (issue
    53): the ks it scored are consecutive on that grid, the chosen one is their best and
    beats each scored neighbour, and the walk stopped at a worse one or the grid's end. The
    held-out points are a subsample of loo_points (each fold's share) when there are more."""
    from knnrefine.density import default_pilot_k

    X = mixture(3000, seed=15)
    est = KnnDensityEstimator(k="cv", cv=3, random_state=4, loo_points=1200).fit(X)
    grid = np.unique(np.round(default_pilot_k(3000) * 2.0 ** np.arange(-1, 4)).astype(int))
    grid = grid[grid <= 2000]
    at = np.searchsorted(grid, est.cv_ks_)
    assert np.array_equal(grid[at], est.cv_ks_) and np.all(np.diff(at) == 1)
    assert default_pilot_k(3000) in est.cv_ks_
    best = int(np.argmax(est.cv_scores_))
    assert est.k_ == est.cv_ks_[best]
    # the walk stops at a worse score or at the grid's end, on both sides of the best
    assert best < len(at) - 1 or at[-1] == len(grid) - 1
    assert best > 0 or at[0] == 0


def test_default_pilot_k_is_two_root_n():
    X = mixture(2500, seed=14)
    assert KnnDensityEstimator().fit(X).k_ == round(2 * np.sqrt(len(X)))
    assert KnnDensityEstimator(method="knn").fit(X).k_ == round(0.5 * np.sqrt(len(X)))
    # never above n, the points' number or total weight (k counts weight)
    assert [default_pilot_k(n) for n in (5, 7.5, 100, 1e6)] == [5, 7, 20, 2000]
    assert KnnDensityEstimator().fit(X[:6]).k_ == 6


def test_standard_error_matches_the_sampling_distribution():
    """The sample-point variance formula against the spread of the estimate over 40
    independent samples of the uniform density (bandwidth fixed, n = 3000, k = 30)."""
    q = 0.2 + 0.6 * np.random.default_rng(0).random((50, 2))

    def fit(seed):
        X = np.random.default_rng(seed).random((3000, 2))
        return KnnDensityEstimator(k=30, bandwidth=1.5, box=(0, 0, 1, 1)).fit(X)

    values = np.array([np.exp(fit(100 + r).score_samples(q)) for r in range(40)])
    se = fit(5).standard_error(q)
    ratio = np.mean(values.std(axis=0)) / np.mean(se)
    assert 0.75 < ratio < 1.25


def test_bad_options_are_refused_before_work():
    X = mixture(300)
    for bad, match in [
        ({"method": "kde"}, "method"),
        ({"shape": "round"}, "shape"),
        ({"bandwidth": 0}, "bandwidth"),
        ({"bandwidth": "auto"}, "bandwidth"),
        ({"bandwidth": np.inf}, "finite"),
        ({"bandwidth": 1 + 1j}, "bandwidth"),
        ({"sensitivity": -0.1}, "sensitivity"),
        ({"sensitivity": 1.5}, "sensitivity"),
        ({"sensitivity": np.nan}, "sensitivity"),
        ({"sensitivity": "auto"}, "sensitivity"),
        ({"sensitivity": True}, "sensitivity"),
        ({"whiten": "yes"}, "whiten"),
        ({"loo_points": 0}, "loo_points"),
        ({"cv": 1}, "cv must be"),
        ({"criterion": "ise"}, "criterion"),
        ({"criterion": None}, "criterion"),
    ]:
        with pytest.raises(InputError, match=match):
            KnnDensityEstimator(k=10, **bad).fit(X)
    with pytest.raises(InputError, match="whiten"):
        KnnDensityEstimator(k=10, whiten=True).fit(np.column_stack([X[:, 0], np.ones(len(X))]))


def test_infinite_bandwidth_is_refused_before_work(monkeypatch):
    """regression: bandwidth=inf passed the estimator's check (inf > 0) and failed only after
    refinement, in set_bandwidth."""
    import knnrefine._pipeline

    def no_work(*args, **kwargs):
        raise AssertionError("refine ran before the options were checked")

    monkeypatch.setattr(knnrefine._pipeline, "refine", no_work)
    with pytest.raises(InputError, match="finite"):
        KnnDensityEstimator(k=10, bandwidth=float("inf")).fit(mixture(300))


def test_real_data_old_faithful_whitened():
    """Old Faithful (minutes against minutes, but ranges 1.6-5.1 and 43-96): whitened and
    not, both score held-out rows finitely; whitening wins there."""
    X = load_shared("old_faithful.csv")[:, :2]
    order = np.random.default_rng(0).permutation(len(X))
    train, test = X[order[: len(X) * 3 // 4]], X[order[len(X) * 3 // 4 :]]
    raw = KnnDensityEstimator(k=10).fit(train)
    white = KnnDensityEstimator(k=10, whiten=True).fit(train)
    assert np.isfinite(raw.score_samples(test)).all()
    assert np.isfinite(white.score_samples(test)).all()


@pytest.mark.parametrize("route", ["drawn", "binned"])
@pytest.mark.parametrize("periodic", [(False, False), (True, True), (True, False)])
def test_grid_through_lattices_matches_the_exact_sums(periodic, route, monkeypatch):
    """Grids through lattices (issue 30: kernels drawn once on lattices of their scale, read
    by interpolation; issue 53: kernels binned on lattices, ``engine.binned``) give the exact
    sums at the centres to about 1e-3, never below 0, with kernels near every side (folded
    or wrapped) and a rectangular grid of oblong cells; drawn, where only kernels drawn on
    the grid itself reach, to rounding."""
    from knnrefine.density import adaptive

    monkeypatch.setattr(adaptive, "GRID_BINNED_CELLS", 0.0 if route == "binned" else np.inf)

    rng = np.random.default_rng(5)
    X = np.concatenate(
        [rng.normal([0.02, 0.5], [0.05, 0.2], (3000, 2)) % 1, rng.normal(0.97, 0.004, (2000, 2)),
         rng.random((3000, 2))]
    ) % 1  # fmt: skip
    mesh = knnrefine.refine(X, 40, box=(0, 0, 1, 1), periodic=periodic)
    ad = AdaptiveDensity(mesh, X, bandwidth=1.2)
    xs, ys, _ = ad.knn.grid((160, 230))
    gx, gy = np.meshgrid(xs, ys)
    exact = ad._sums(ad._metric.frame(np.column_stack([gx.ravel(), gy.ravel()])))[0]
    monkeypatch.setattr(adaptive, "EXACT_TERMS", 0.0)  # lattices at any size
    got = ad._grid_sums([xs, ys]).ravel()
    if route == "binned":
        assert_binned_close(got, exact)
        return
    assert_lattice_close(got, exact, worst=3e-3)
    # only kernels narrower than two lattice radii: on the grid itself, exact
    monkeypatch.setattr(adaptive, "LATTICE_SAMPLES", 1e6)
    np.testing.assert_allclose(ad._grid_sums([xs, ys]).ravel(), exact, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("route", ["drawn", "binned"])
@pytest.mark.parametrize("case", ["line", "duplicates", "seam"])
def test_grid_through_lattices_on_degenerate_inputs(case, route, monkeypatch):
    """The lattice grid (issue 30, drawn; issue 53, binned) on points on a line, on many
    duplicates (kernels of radius 0 where d_Pk is 0) and on a periodic seam: the exact sums
    at the centres, to the same tolerance as on general points, never below 0, mass kept."""
    from knnrefine.density import adaptive

    monkeypatch.setattr(adaptive, "GRID_BINNED_CELLS", 0.0 if route == "binned" else np.inf)

    rng = np.random.default_rng(8)
    periodic = case == "seam"
    if case == "line":
        t = rng.random(3000)
        X = np.column_stack([0.1 + 0.8 * t, 0.2 + 0.6 * t])
        X = np.concatenate([X, rng.random((500, 2))])
    elif case == "duplicates":
        X = np.concatenate([np.repeat(rng.random((40, 2)), 60, axis=0), rng.random((800, 2))])
    else:
        X = np.column_stack([rng.random(3000), rng.normal(0.0, 0.01, 3000) % 1.0])
    mesh = knnrefine.refine(X, 30, box=(0, 0, 1, 1), periodic=periodic)
    ad = AdaptiveDensity(mesh, X, bandwidth=1.2)
    xs, ys, _ = ad.knn.grid((140, 150))
    gx, gy = np.meshgrid(xs, ys)
    exact = ad._sums(ad._metric.frame(np.column_stack([gx.ravel(), gy.ravel()])))[0]
    monkeypatch.setattr(adaptive, "EXACT_TERMS", 0.0)
    got = ad._grid_sums([xs, ys]).ravel()
    if route == "binned":
        assert_binned_close(got, exact)
    else:
        assert_lattice_close(got, exact, worst=3e-3, mean_rel=2e-3)


def test_grid_of_kernels_narrow_on_the_grid_reads_the_binned_lattices(monkeypatch):
    """Regression (issue 53, the uniform disk at 10^5 points: its 512^2 grid took 0.29 s,
    six times the other truths'): the grid went centre by centre, exactly, wherever drawing
    the kernels on lattices would cost as many cells as the exact sums cost terms (no
    kernel wider than the drawn lattices' cap: equal over the box, more on a finer grid over
    a region), at a cost in queries that the terms do not count. Binned lattices cost O(n)
    whatever the kernels' width: a long sum of kernels covering many cells each reads them,
    within the binned route's tolerance of the exact sums."""
    from knnrefine._engine import binned
    from knnrefine.density import adaptive

    rng = np.random.default_rng(12)
    t = 2 * np.pi * rng.random(10000)
    X = 0.5 + 0.45 * np.sqrt(rng.random(10000))[:, None] * np.column_stack([np.cos(t), np.sin(t)])
    mesh = knnrefine.refine(X, 80, box=(0, 0, 1, 1))
    ad = AdaptiveDensity(mesh, X, bandwidth=0.7, sensitivity=0.3)
    region = (0.1, 0.1, 0.9, 0.9)  # a finer grid over a region: drawn cells > exact terms
    xs, ys, _ = ad.knn.grid((160, 160), extent=region)
    r = ad._radii()
    cell = (xs[1] - xs[0]) * (ys[1] - ys[0])
    assert (r / np.sqrt(cell) < 2 * adaptive.LATTICE_SAMPLES).all()  # none capped
    assert np.mean(np.pi * r**2 / cell) >= adaptive.GRID_BINNED_CELLS  # many cells a kernel
    assert np.pi * (r**2).sum() >= adaptive.GRID_BINNED_COVER  # and many kernels a point
    gx, gy = np.meshgrid(xs, ys)
    exact = ad._sums(ad._metric.frame(np.column_stack([gx.ravel(), gy.ravel()])))[0]
    monkeypatch.setattr(adaptive, "EXACT_TERMS", 0.0)  # a long sum at this size
    reads = []
    read = binned.BinnedSums.grid
    monkeypatch.setattr(binned.BinnedSums, "grid", lambda s, *q: reads.append(1) or read(s, *q))
    *_, got = ad.grid((160, 160), extent=region)
    assert reads == [1]
    got = (got - ad.eps * ad.knn.grid((160, 160), extent=region)[2]) / (1 - ad.eps)
    assert_binned_close(got.ravel(), exact)


def _binned_case(case, rng):
    """Points for the binned leave-one-out tests: (points, periodic, weights)."""
    if case == "line":
        t = rng.random(6000)
        X = np.concatenate([np.column_stack([0.1 + 0.8 * t, 0.2 + 0.6 * t]), rng.random((800, 2))])
    elif case == "duplicates":
        X = np.concatenate([np.repeat(rng.random((40, 2)), 30, axis=0), rng.random((6000, 2))])
    elif case == "seam":
        X = np.column_stack([rng.random(6000), rng.normal(0.0, 0.01, 6000) % 1.0])
    else:
        X = np.concatenate(
            [rng.normal([0.02, 0.5], [0.05, 0.2], (3000, 2)) % 1,
             rng.normal(0.97, 0.004, (2000, 2)) % 1, rng.random((3000, 2))]
        )  # fmt: skip
    periodic = {"torus": (True, True), "seam": (True, True), "strip": (True, False)}
    weights = rng.uniform(0.2, 3.0, len(X)) if case == "weighted" else None
    return X, periodic.get(case, (False, False)), weights


@pytest.mark.parametrize(
    "case", ["box", "torus", "strip", "weighted", "line", "duplicates", "seam", "narrow-exact"]
)
def test_binned_leave_one_out_matches_the_exact_sums(case, monkeypatch):
    """Leave-one-out values through binned lattices (issue 30: a smoothing's score at a cost
    that does not grow with c^2 k) against the exact sums: kernels folded at the sides, wrapped
    on a torus and a strip, weighted, on a line, with copies left out together, across a
    seam, and with the finest lattices summed exactly (forced by a tiny lattice budget): each
    point's density within a few per cent, the mean log-likelihood within 1e-3 (1e-2 on a
    line), at three sensitivities and bandwidths, narrow ones included (points few other
    kernels reach are summed exactly)."""
    from knnrefine._engine import binned

    if case == "narrow-exact":
        monkeypatch.setattr(binned, "VALUES_PER_CENTRE", 0.5)
        monkeypatch.setattr(binned, "LEAST_VALUES", 1000)
    rng = np.random.default_rng(11)
    X, periodic, weights = _binned_case(case, rng)
    mesh = knnrefine.refine(X, 40, box=(0, 0, 1, 1), periodic=periodic, weights=weights)
    ad = AdaptiveDensity(mesh, X, weights=weights)
    idx = np.sort(rng.choice(len(X), 3000, replace=False))
    if case == "duplicates":
        idx[:30] = np.arange(30) * 30  # some sample points have copies
    for alpha, c in ((0.5, 1.0), (0.2, 0.6), (0.6, 2.0)):
        ad.set_bandwidth(c, alpha)
        exact, got = ad.loo(idx), ad.loo(idx, binned=True)
        rel = np.abs(np.expm1(got - exact))
        assert np.median(rel) < 1e-2 and np.quantile(rel, 0.99) < 6e-2, (alpha, c)
        # on a line binning's tent reaches across it: the shape differs, not the variance
        assert abs(got.mean() - exact.mean()) < (1e-2 if case == "line" else 1e-3)
    # a grid's reads, separable (``BinnedSums.grid``), are the point reads at its centres,
    # over the box and over a region reaching beyond it (and beyond the lattices)
    lattices = ad._binned()
    for xs, ys in ((np.linspace(0.005, 0.995, 97), np.linspace(0.004, 0.996, 83)),
                   (np.linspace(-0.1, 0.4, 31), np.linspace(0.7, 1.1, 17))):  # fmt: skip
        gx, gy = np.meshgrid(xs, ys)
        points = lattices.at(gx.ravel(), gy.ravel()).reshape(gx.shape)
        np.testing.assert_allclose(lattices.grid(xs, ys), points, rtol=1e-12, atol=1e-12)
    if case == "narrow-exact":  # the budget did send lattices to exact sums
        from knnrefine._engine import kernelsum as ks

        rows = ad._rows
        mass = rows[:, ks.W] / ad.total
        sums = binned.BinnedSums([rows[:, ks.X], rows[:, ks.Y]], rows[:, ks.R], mass, np.ones(2),
                                 np.array(periodic))  # fmt: skip
        assert sums.exact is not None and len(sums.exact[0]) > 0


@pytest.mark.parametrize("case", ["box", "torus", "duplicates", "narrow-exact"])
def test_binned_levels_found_once_serve_every_bandwidth(case, monkeypatch):
    """Binned lattices made from one sensitivity's levels at bandwidth c (issue 53: a search
    over c finds its kernels' levels once) are those made from the radii c r: the same
    levels, lattice bounds and values (to rounding), read the same at centres and anywhere,
    the finest levels summed exactly alike when the budget sends them there."""
    from knnrefine._engine import binned

    if case == "narrow-exact":
        monkeypatch.setattr(binned, "VALUES_PER_CENTRE", 0.5)
        monkeypatch.setattr(binned, "LEAST_VALUES", 1000)
    rng = np.random.default_rng(12)
    X, periodic, _ = _binned_case(case, rng)
    cx, cy = X[:, 0].copy(), X[:, 1].copy()
    r = 0.01 * np.exp(rng.normal(0, 0.6, len(X)))  # radii over several levels
    r[:5] = 0.0  # no kernel
    mass = np.full(len(X), 1.0 / len(X))
    per = np.array(periodic, bool)
    levels = binned.BinnedLevels([cx, cy], r)
    idx = np.sort(rng.choice(len(X), 500, replace=False))
    q = rng.random((300, 2))
    for c in (0.5, 2.0**0.25, 3.0):
        once = binned.BinnedSums([cx, cy], None, mass, np.ones(2), per, levels=levels, scale=c)
        direct = binned.BinnedSums([cx, cy], c * r, mass, np.ones(2), per)
        assert np.array_equal(once.level, direct.level)
        assert np.array_equal(once.lattices, direct.lattices)
        np.testing.assert_allclose(once.values, direct.values, rtol=1e-9, atol=1e-12)
        assert (once.exact is None) == (direct.exact is None)
        assert once.exact is not None or case != "narrow-exact"
        for a, b in zip(once.without(idx, mass[idx]), direct.without(idx, mass[idx]), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(once.at(q[:, 0], q[:, 1]), direct.at(q[:, 0], q[:, 1]),
                                   rtol=1e-9, atol=1e-12)  # fmt: skip


def _binned_case3(case, rng):
    """Points in the unit cube for the binned tests in space: (points, periodic, weights)."""
    X = np.concatenate([rng.normal([0.02, 0.5, 0.5], [0.05, 0.2, 0.2], (1800, 3)) % 1,
                        rng.normal(0.8, 0.01, (900, 3)) % 1, rng.random((1200, 3))])  # fmt: skip
    periodic, weights = case == "torus", None
    if case == "weighted":
        weights = rng.uniform(0.2, 3.0, len(X))
    elif case == "duplicates":
        X = np.concatenate([np.repeat(rng.random((30, 3)), 10, axis=0), X])
    return X, periodic, weights


def test_binned_leave_one_out_in_space_matches_the_exact_sums(monkeypatch):
    """Issue 53: the binned leave-one-out values in space (balls binned on lattices of
    their scale, ``engine.binned``'s kernels in three dimensions) against the exact sums:
    folded at the sides, wrapped on the 3-torus, weighted, with copies left out together
    (counted by the space index, ``Index.weight_at``) and with the finest lattices summed
    exactly; and levels found once serve every bandwidth. One test: the kernels compile
    once, in the fast suite only."""
    for case in ("box", "torus", "weighted", "duplicates", "narrow-exact"):
        with monkeypatch.context() as patched:
            binned_leave_one_out_in_space(case, patched)
    binned_levels_in_space_serve_every_bandwidth()  # (the same kernels: one compile)
    with monkeypatch.context() as patched:
        thinned_search_in_space(patched)


def binned_leave_one_out_in_space(case, monkeypatch):
    """The binned leave-one-out values in space against the exact sums: each point's density
    within about 1 % (median; 12 % at the 99th percentile), the mean log-likelihood within
    2e-3, at three smoothings."""
    from knnrefine._engine import binned

    if case == "narrow-exact":
        monkeypatch.setattr(binned, "VALUES_PER_CENTRE", 0.5)
        monkeypatch.setattr(binned, "LEAST_VALUES", 1000)
    rng = np.random.default_rng(13)
    X, periodic, weights = _binned_case3(case, rng)
    mesh = knnrefine.refine(X, 50, box=(0, 0, 0, 1, 1, 1), periodic=periodic, weights=weights)
    ad = AdaptiveDensity(mesh, X, weights=weights)
    idx = np.sort(rng.choice(len(X), 1200, replace=False))
    if case == "duplicates":
        idx[:30] = np.arange(30) * 10
        held = ad._copies_at(idx)  # the index's count against a brute-force one
        brute = [(X == X[i]).all(axis=1).sum() for i in idx]
        np.testing.assert_array_equal(held, brute)
    for alpha, c in ((0.5, 1.0), (0.3, 0.7), (0.6, 1.6)):
        ad.set_bandwidth(c, alpha)
        exact, got = ad.loo(idx), ad.loo(idx, binned=True)
        rel = np.abs(np.expm1(got - exact))  # three steps a radius at least: coarser
        assert np.median(rel) < 2e-2 and np.quantile(rel, 0.99) < 0.12, (alpha, c)
        assert abs(got.mean() - exact.mean()) < 2e-3
    if case == "narrow-exact":
        assert ad._binned().exact is not None


def binned_levels_in_space_serve_every_bandwidth():
    """``BinnedLevels`` in space, found once, give the lattices made from the radii c r."""
    from knnrefine._engine import binned

    rng = np.random.default_rng(14)
    X, _, _ = _binned_case3("box", rng)
    cols = [X[:, a].copy() for a in range(3)]
    r = 0.02 * np.exp(rng.normal(0, 0.5, len(X)))
    mass = np.full(len(X), 1.0 / len(X))
    per = np.zeros(3, bool)
    levels = binned.BinnedLevels(cols, r)
    idx = np.sort(rng.choice(len(X), 300, replace=False))
    for c in (0.7, 1.5):
        once = binned.BinnedSums(cols, None, mass, np.ones(3), per, levels=levels, scale=c)
        direct = binned.BinnedSums(cols, c * r, mass, np.ones(3), per)
        assert np.array_equal(once.lattices, direct.lattices)
        np.testing.assert_allclose(once.values, direct.values, rtol=1e-9, atol=1e-12)
        for a, b in zip(once.without(idx, mass[idx]), direct.without(idx, mass[idx]), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def thinned_search_in_space(monkeypatch):
    """Issue 53: the thinned estimate (every 4th kernel along the spatial order, the same
    pilot) sums its own kernels (against brute force at points away from the sides) and
    counts copies among its own points; a search in space over THIN_FROM points climbs on
    it (every other kernel here), walks the full estimate's half steps and checks its
    neighbours in alpha: the same sensitivity as the search without it, the bandwidth
    within a half step, and the table holds the full estimate's scores."""
    from knnrefine.density import adaptive

    rng = np.random.default_rng(15)
    X = _binned_case3("duplicates", rng)[0][::2]  # (2,100 points: copies kept, every 10th)
    ad = AdaptiveDensity(knnrefine.refine(X, 40, box=(0, 0, 0, 1, 1, 1)), X, bandwidth=0.6)
    thin = ad.thinned(4)
    keep = ad._order[::4]  # the points kept, in the kernels' order
    assert len(thin.pilot) == len(keep)
    np.testing.assert_array_equal(thin.pilot, ad.pilot[keep])
    q = rng.random((200, 3))
    h = 0.6 * ad.unit_extents[keep]
    ball = 64 * np.pi / 315  # the triweight (1 - |x|^2)^3 over the unit ball
    brute = np.zeros(len(q))
    for image in itertools.product(*[(lambda v: v, lambda v: -v, lambda v: 2 - v)] * 3):
        c = np.column_stack([f(X[keep][:, a]) for a, f in enumerate(image)])  # folded sides
        u = ((q[:, None, :] - c[None]) ** 2).sum(axis=2) / h**2
        brute += (np.where(u < 1, (1 - u) ** 3, 0.0) / (ball * h**3)).sum(axis=1)
    np.testing.assert_allclose(thin(q), (1 - thin.eps) * brute / len(keep) + thin.eps * thin.knn(q),
                               rtol=1e-9)  # fmt: skip
    copies = [(X[keep] == x).all(axis=1).sum() for x in X[keep]]
    np.testing.assert_array_equal(thin._copies_at(np.arange(len(keep))), copies)
    assert max(copies) > 1
    searches = {}
    monkeypatch.setattr(adaptive, "THIN_EVERY", 2)  # (an eighth of 4,000 points: too few)
    for thin_from in (np.inf, 0):
        monkeypatch.setitem(adaptive.THIN_FROM, 3, thin_from)
        searches[thin_from] = adaptive.choose_smoothing(ad, binned=True)
    (a0, c0, _), (a1, c1, table) = searches[np.inf], searches[0]
    assert a1 == a0 and abs(np.log(c1 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    assert np.isclose(table[table[:, 0] == a1, 1], c1, rtol=1e-11).any()  # (and alpha's check)
    for alpha, c, score in table:
        ad.set_bandwidth(c, alpha)
        assert np.mean(ad.loo(None, binned=True)) == pytest.approx(score, rel=1e-9)
    # degenerate, through the thinned climb (THIN_FROM left at 0): points on a plane across
    # the box (a flat cluster) over a background
    flat = np.concatenate([np.column_stack([rng.random((1200, 2)), np.full(1200, 0.5)]),
                           rng.random((600, 3))])  # fmt: skip
    ad = AdaptiveDensity(knnrefine.refine(flat, 30, box=(0, 0, 0, 1, 1, 1)), flat)
    alpha, c, table = adaptive.choose_smoothing(ad, binned=True)
    assert alpha in adaptive.SENSITIVITIES and alpha in table[:, 0]
    assert np.isfinite(table[:, 2]).all() and np.isfinite(ad.loo()).all()


def test_thinned_search_in_the_plane_decides_the_sensitivity_on_the_full_estimate(monkeypatch):
    """Issue 53: a binned search in the plane over THIN_FROM points climbs on a thinned
    estimate, walks the full estimate's half steps in c and then checks the full estimate's
    neighbours in alpha: the same sensitivity as the search without it, the bandwidth within
    a half step, a table of the full estimate's scores; and where the thinned climb ends
    far off in alpha (forced here), the check walks the full estimate back to its choice."""
    from knnrefine.density import adaptive

    rng = np.random.default_rng(21)
    X = np.concatenate([rng.normal([0.3, 0.4], 0.1, (6000, 2)), rng.normal(0.7, 0.02, (2000, 2)),
                        rng.random((2000, 2))]) % 1  # fmt: skip
    ad = AdaptiveDensity(knnrefine.refine(X, 120, box=(0, 0, 1, 1)), X)
    monkeypatch.setattr(adaptive, "THIN_EVERY", 4)  # (an eighth of 10,000 points: too few)
    searches = {}
    for thin_from in (np.inf, 0):
        monkeypatch.setitem(adaptive.THIN_FROM, 2, thin_from)
        searches[thin_from] = adaptive.choose_smoothing(ad, binned=True)
    (a0, c0, _), (a1, c1, table) = searches[np.inf], searches[0]
    assert a1 == a0 and abs(np.log(c1 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    assert np.isclose(table[table[:, 0] == a1, 1], c1, rtol=1e-11).any()
    for alpha, c, score in table[:4]:
        ad.set_bandwidth(c, alpha)
        assert np.mean(ad.loo(None, binned=True)) == pytest.approx(score, rel=1e-9)
    climb = adaptive._climb
    far = 0 if a0 >= 0.3 else len(adaptive.SENSITIVITIES) - 1

    def off(scores, alphas, cs, i, j):  # the thinned climb ends at the far end in alpha
        i, j, scored = climb(scores, alphas, cs, i, j)
        return (far if scores.density is not ad else i), j, scored

    monkeypatch.setattr(adaptive, "_climb", off)
    a2, c2, _ = adaptive.choose_smoothing(ad, binned=True)
    assert a2 == a0 and abs(np.log(c2 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    monkeypatch.setattr(adaptive, "_climb", climb)
    # degenerate, through the thinned climb (THIN_FROM left at 0): points on a line over a
    # background, and a band across a periodic seam
    t = rng.random(3000)
    line = np.concatenate([np.column_stack([0.1 + 0.8 * t, 0.2 + 0.6 * t]), rng.random((600, 2))])
    seam = np.column_stack([rng.random(3000), rng.normal(0.0, 0.01, 3000) % 1.0])
    for pts, periodic in ((line, False), (seam, True)):
        ad = AdaptiveDensity(knnrefine.refine(pts, 40, box=(0, 0, 1, 1), periodic=periodic), pts)
        alpha, c, table = adaptive.choose_smoothing(ad, binned=True)
        assert alpha in adaptive.SENSITIVITIES and alpha in table[:, 0]
        assert np.isclose(table[table[:, 0] == alpha, 1], c, rtol=1e-11).any()
        assert np.isfinite(table[:, 2]).all() and np.isfinite(ad.loo()).all()


def test_climb_runs_along_an_improving_step():
    """The smoothing climb (issue 53): on a smooth score over the grid with its best pair
    far from the start, it ends at that pair and scores one new pair per step along a
    rising direction (a pattern search), not three."""
    from knnrefine.density import adaptive

    alphas, cs = adaptive.SENSITIVITIES, adaptive.BANDWIDTHS
    for best in [(0, 3), (6, 12), (3, 6), (0, 0)]:
        seen = []

        def score(alpha, c, best=best, seen=seen):
            seen.append((alpha, c))
            return -(((alpha - alphas[best[0]]) / 0.1) ** 2) - (np.log2(c / cs[best[1]]) * 2) ** 2

        i, j, scored = adaptive._climb(score, alphas, cs, 3, 6)
        assert (i, j) == best
        steps = abs(best[0] - 3) + abs(best[1] - 6)
        assert len(scored) == len(seen) <= 5 + steps + 4  # the start's four, a pair a step
        assert scored[best] == max(scored.values())


def test_binned_search_chooses_as_the_exact_one():
    """The smoothing chosen through binned scores is the exact search's (same sensitivity,
    bandwidth within one half step), and "auto" takes binned scores where the sample times
    k is large, exact ones on rounded data (most points have copies: binning's error is not
    small next to the share left out); the least-squares criterion as well (issue 53)."""
    from knnrefine.density import adaptive

    rng = np.random.default_rng(3)
    X = np.concatenate([rng.normal([0.3, 0.4], 0.1, (9000, 2)), rng.normal(0.7, 0.02, (3000, 2))])
    mesh = knnrefine.refine(X, 120)
    ad = AdaptiveDensity(mesh, X)
    a0, c0, _ = adaptive.choose_smoothing(ad, binned=False)
    a1, c1, _ = adaptive.choose_smoothing(ad, binned=True)
    assert a1 == a0 and abs(np.log(c1 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    assert adaptive._binned_scores(ad, None, "likelihood", None)
    assert adaptive._binned_scores(ad, None, "least-squares", None)
    # least squares through binned sums (every point read): the exact search's choice
    a0, c0, _ = adaptive.choose_smoothing(ad, binned=False, criterion="least-squares")
    a1, c1, _ = adaptive.choose_smoothing(ad, binned=True, criterion="least-squares")
    assert abs(a1 - a0) <= 0.1 + 1e-9 and abs(np.log(c1 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    rounded = np.round(X, 2)
    ad2 = AdaptiveDensity(knnrefine.refine(rounded, 120), rounded)
    assert not adaptive._binned_scores(ad2, None, "likelihood", None)


@pytest.mark.parametrize("case", ["line", "seam"])
def test_estimator_with_binned_scores_on_degenerate_inputs(case, monkeypatch):
    """Through the public estimator (issue 30: binned scores by default from loo_points x k >=
    10^6): points on a line with a background, and points across a periodic seam, choose the
    smoothing the exact search chooses (same sensitivity, bandwidth within a half step), and
    the fitted density integrates to 1 over the box; least squares binned chooses within a
    sensitivity step and a half step of bandwidth of its exact search."""
    from knnrefine.density import adaptive

    rng = np.random.default_rng(21)
    if case == "line":
        t = rng.random(7000)
        X = np.concatenate([np.column_stack([0.1 + 0.8 * t, 0.2 + 0.6 * t]), rng.random((1000, 2))])
        options = {"box": (0, 0, 1, 1)}
    else:
        X = np.column_stack([rng.random(8000), rng.normal(0.0, 0.02, 8000) % 1.0])
        options = {"box": (0, 0, 1, 1), "periodic": True}
    seen = []
    real = adaptive._binned_scores
    monkeypatch.setattr(adaptive, "_binned_scores", lambda *a: seen.append(real(*a)) or seen[-1])
    binned = KnnDensityEstimator(**options).fit(X)
    assert seen == [True]  # the default took binned scores
    monkeypatch.setattr(adaptive, "BINNED_FROM", np.inf)
    exact = KnnDensityEstimator(**options).fit(X)
    assert seen[-1] is False
    assert binned.sensitivity_ == exact.sensitivity_
    assert abs(np.log(binned.bandwidth_ / exact.bandwidth_)) <= np.log(adaptive.HALF_STEP) + 1e-9
    assert np.isfinite(binned.score_samples(X)).all()
    assert (binned.grid((100, 100))[2] >= 0).all()
    # least squares there too (issue 53: binned, every point read; f^2 by the cubature)
    ad = exact.density_
    a0, c0, _ = adaptive.choose_smoothing(ad, binned=False, criterion="least-squares")
    a1, c1, t1 = adaptive.choose_smoothing(ad, binned=True, criterion="least-squares")
    assert abs(a1 - a0) <= 0.1 + 1e-9 and abs(np.log(c1 / c0)) <= np.log(adaptive.HALF_STEP) + 1e-9
    assert np.isfinite(t1[:, 2]).all()


def test_binned_scores_are_refused_where_they_are_not_built():
    """binned=True for local shapes (either criterion) or on the sphere: a clear error before
    any work (in space and for the least-squares score, issue 53, they are built)."""
    from knnrefine.density import adaptive

    X = ridge(800)
    ad = AdaptiveDensity(knnrefine.refine(X, 20), X, shape="local")
    with pytest.raises(InputError, match="isotropic kernels in a box"):
        adaptive.choose_smoothing(ad, binned=True)
    with pytest.raises(InputError, match="isotropic kernels"):
        ad.loo(np.arange(10), binned=True)
    with pytest.raises(InputError, match="isotropic kernels in a box"):
        adaptive.choose_smoothing(ad, binned=True, criterion="least-squares")
    rng = np.random.default_rng(0)
    P = rng.random((600, 3))
    ad3 = AdaptiveDensity(knnrefine.refine(P, 20), P)
    assert np.isfinite(ad3.loo(np.arange(10), binned=True)).all()
    # a thinned estimate (issue 53): isotropic kernels, every k-th for an integer k >= 1
    with pytest.raises(InputError, match="isotropic kernels"):
        ad.thinned(2)
    for every in (0, -3, 2.5, True, "2"):
        with pytest.raises(InputError, match="every must be an integer"):
            ad3.thinned(every)
    assert len(ad3.thinned(1).pilot) == len(P) and len(ad3.thinned(600).pilot) == 1


def test_binned_scores_on_real_rounded_data():
    """Real points (../shared/data: MOPSI Finland, integer coordinates, a fifth of them at a
    place shared with others): the search keeps exact scores there (over 1% of the sample
    has copies), and binned values, asked for, stay within a few per cent of the exact ones
    (points few other kernels reach summed exactly), the mean log-likelihood within 1e-2."""
    from knnrefine.density import adaptive

    X = load_shared("mopsi_finland.csv")
    ad = AdaptiveDensity(knnrefine.refine(X, int(round(2 * np.sqrt(len(X))))), X)
    idx = np.sort(np.random.default_rng(0).choice(len(X), 5000, replace=False))
    assert not adaptive._binned_scores(ad, idx, "likelihood", None)
    for alpha, c in ((0.5, 1.0), (0.2, 0.6)):
        ad.set_bandwidth(c, alpha)
        exact, got = ad.loo(idx), ad.loo(idx, binned=True)
        rel = np.abs(np.expm1(got - exact))
        assert np.median(rel) < 1e-2 and np.quantile(rel, 0.99) < 6e-2
        assert abs(got.mean() - exact.mean()) < 1e-2


def test_binned_loo_at_a_point_on_a_lattice_line():
    """regression: a point exactly on a lattice line (the box's lower corner, frame
    coordinates 0) read lattice points with no mass, whose kernel radius is 0: numba's
    ZeroDivisionError. Its binned leave-one-out value is now finite and near the exact one."""
    rng = np.random.default_rng(4)
    X = np.concatenate([[[0.0, 0.0], [0.0, 0.5], [0.5, 0.0]], rng.random((3000, 2))])
    ad = AdaptiveDensity(knnrefine.refine(X, 30, box=(0, 0, 1, 1)), X)
    idx = np.arange(3)
    got, exact = ad.loo(idx, binned=True), ad.loo(idx)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, exact, atol=0.05)


@pytest.mark.parametrize("periodic", [False, True])
@pytest.mark.parametrize("dim", [2, 3])
def test_plan_levels_gives_each_kernel_its_lattice_by_counting(dim, periodic):
    """Issue 53: ``lattice.plan_levels`` finds the levels present by counting (np.unique's
    sort took 0.2 s of the grid at 10^6 kernels): each live kernel's level is the rank of
    its m = max(floor(log2(r / (samples x the widest step))), 0) among the m present, a dead
    kernel (radius 0) -1, and the levels' rows are one per m present, in order, each
    lattice spanning its kernels (``_level_bounds``, one pass); against numpy's unique and
    masks, with dead kernels, gaps between the m present and every kernel dead, periodic
    or not."""
    from knnrefine._engine.lattice import plan_levels

    rng = np.random.default_rng(53)
    step = np.full(dim, 1.0 / 64)
    period = np.ones(dim)
    for r in (np.where(rng.random(3000) < 0.2, 0.0, 10.0 ** rng.uniform(-3, -0.5, 3000)),
              np.r_[np.zeros(5), np.full(7, 0.4), np.full(9, 0.02)],  # m = 0 and a gap
              np.zeros(10)):  # fmt: skip
        centres = rng.random((len(r), dim))
        plan = plan_levels(centres, r, period, np.full(dim, periodic), (step / 2, step), 2, 1e9)
        level, levels, _ = plan
        m = np.full(len(r), -1)
        live = r > 0
        m[live] = np.maximum(np.floor(np.log2(r[live] / (2 * step.max()))), 0)
        present = np.unique(m[live])
        want = np.full(len(r), -1)
        want[live] = np.searchsorted(present, m[live])
        np.testing.assert_array_equal(level, want)
        assert len(levels) == len(present)
        # each level's lattice: steps the grid's times 2^m, spanning its kernels' supports
        # (and the box two steps out where one reaches a side), by numpy per level
        for j, mm in enumerate(present):
            mine = want == j
            s = step * 2.0**mm
            cm, rm = centres[mine], r[mine][:, None]
            lo = np.maximum((cm - rm).min(axis=0), -2 * s)
            hi = np.minimum((cm + rm).max(axis=0), 1 + 2 * s)
            near_lo = (cm < rm + 2 * s).any(axis=0)
            near_hi = (cm > 1 - rm - 2 * s).any(axis=0)
            if periodic:  # images one period away: the whole box and two steps
                near_lo = near_hi = near_lo | near_hi
            lo = np.where(near_lo, -2 * s, lo)
            hi = np.where(near_hi, 1 + 2 * s, hi)
            i0 = np.floor((lo - step / 2) / s)
            np.testing.assert_array_equal(levels[j, :dim], step / 2 + i0 * s)
            np.testing.assert_array_equal(levels[j, dim : 2 * dim], s)
            np.testing.assert_array_equal(levels[j, 2 * dim : 3 * dim],
                                          np.floor((hi - step / 2) / s) - i0 + 1)  # fmt: skip
